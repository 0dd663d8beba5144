//! Drive profiles (corpus/profiles/*.toml): register maps, limits, vendor mnemonics, object dictionaries.
//! Loading validates: unknown keys, unknown access modes, overlapping registers and bad ranges are rejected
//! with the file, the line and the reason. No I/O beyond reading the file.
//!
//! A `[[register]]`, `[[coil]]` or `[[discrete_input]]` entry may be a block: `count` (or `end`) entries from
//! `address` on, `stride` apart, named by a template (`name = "Holding register {address}"`). Loading expands
//! blocks, so everything after it sees one entry per register or bit (see corpus/profiles/SCHEMA.md).

mod blocks;

use std::collections::BTreeMap;
use std::path::Path;

use codec::{ExceptionCode, FunctionCode};
use serde::Deserialize;
use toml::Spanned;

use blocks::{BitEntry, RegisterEntry, expand_all};

/// A loaded, validated profile: blocks expanded to one entry per register, coil and discrete input, each
/// entry spanned by the text of the table it came from (for error lines).
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    pub device: Device,
    pub serial: Option<Serial>,
    pub functions: Vec<Function>,
    pub exceptions: Vec<NamedCode>,
    pub registers: Vec<Spanned<Register>>,
    pub reserved: Vec<Spanned<Reserved>>,
    pub coils: Vec<Spanned<Bit>>,
    pub discrete_inputs: Vec<Spanned<Bit>>,
    pub mnemonics: Vec<Spanned<VendorMnemonic>>,
    pub identification: Vec<IdObject>,
    pub diagnostics: Vec<Diagnostic>,
    pub objects: Vec<Spanned<Object>>,
    pub sdo_errors: Vec<NamedCode32>,
    pub watchdog: Option<Watchdog>,
    /// Present when the profile is a draft discovered by `probe --write-profile`: what the probe covered.
    pub draft: Option<Draft>,
}

/// A profile file as written: the tables of [`Profile`], with register and bit entries that may be blocks.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ProfileFile {
    device: Device,
    serial: Option<Serial>,
    #[serde(rename = "function", default)]
    functions: Vec<Function>,
    #[serde(rename = "exception", default)]
    exceptions: Vec<NamedCode>,
    #[serde(rename = "register", default)]
    registers: Vec<Spanned<RegisterEntry>>,
    #[serde(rename = "reserved", default)]
    reserved: Vec<Spanned<Reserved>>,
    #[serde(rename = "coil", default)]
    coils: Vec<Spanned<BitEntry>>,
    #[serde(rename = "discrete_input", default)]
    discrete_inputs: Vec<Spanned<BitEntry>>,
    #[serde(rename = "mnemonic", default)]
    mnemonics: Vec<Spanned<VendorMnemonic>>,
    #[serde(rename = "identification", default)]
    identification: Vec<IdObject>,
    #[serde(rename = "diagnostic", default)]
    diagnostics: Vec<Diagnostic>,
    #[serde(rename = "object", default)]
    objects: Vec<Spanned<Object>>,
    #[serde(rename = "sdo_error", default)]
    sdo_errors: Vec<NamedCode32>,
    watchdog: Option<Watchdog>,
    draft: Option<Spanned<Draft>>,
}

/// What `probe --write-profile` covered when it drafted the profile. With it, the catalog takes only what
/// the probe saw as known: a function code is unsupported only when it is in `unsupported_functions`, and
/// an address is unmapped only when it lies in `scan`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Draft {
    /// The target probed (as the probe was given it).
    pub target: String,
    /// Register, coil and discrete-input addresses read one by one, inclusive.
    pub scan: [u16; 2],
    /// Function codes the target answered with exception 01 (Illegal Function).
    #[serde(default)]
    pub unsupported_functions: Vec<FunctionCode>,
    pub note: Option<String>,
    pub line: Option<u32>,
}

impl Draft {
    /// True when the probe read `address` (register or bit).
    pub fn scanned(&self, address: u16) -> bool {
        self.scan[0] <= address && address <= self.scan[1]
    }
}

/// Identity and addressing of the device.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Device {
    pub id: String,
    pub name: String,
    pub vendor: String,
    pub manual: Option<String>,
    pub transports: Vec<Transport>,
    #[serde(default)]
    pub word_order: WordOrder,
    pub default_unit: u8,
    pub unit_ids: [u8; 2],
    #[serde(default)]
    pub broadcast: bool,
    #[serde(default = "default_max_pdu")]
    pub max_pdu: u16,
    pub note: Option<String>,
    pub line: Option<u32>,
}

fn default_max_pdu() -> u16 {
    253
}

/// How Modbus travels: what a device speaks (a profile's `transports`) and how a run reached it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Transport {
    /// Modbus/TCP (MBAP framing).
    Tcp,
    /// RTU on a serial line.
    Rtu,
    /// RTU frames carried in a TCP stream (serial gateways).
    RtuOverTcp,
}

impl Transport {
    /// The name used in reports and on the command line.
    pub fn label(self) -> &'static str {
        match self {
            Transport::Tcp => "tcp",
            Transport::Rtu => "rtu",
            Transport::RtuOverTcp => "rtu-over-tcp",
        }
    }
}

impl std::fmt::Display for Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.label())
    }
}

/// Serial line settings (RTU drives).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Serial {
    pub baud_rates: Vec<u32>,
    pub default_baud: u32,
    pub parity: Vec<ParityName>,
    pub default_parity: ParityName,
    #[serde(default = "one")]
    pub stop_bits: u8,
    pub note: Option<String>,
    pub line: Option<u32>,
}

fn one() -> u8 {
    1
}

/// Parity as a profile names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ParityName {
    None,
    Even,
    Odd,
}

/// A supported function code.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Function {
    pub code: FunctionCode,
    pub name: String,
    pub max_quantity: Option<u16>,
    pub max_write_quantity: Option<u16>,
    /// False when discovered by a probe and not yet confirmed by a person (documentation only).
    #[serde(default = "yes")]
    pub confirmed: bool,
    pub note: Option<String>,
    pub line: Option<u32>,
}

fn yes() -> bool {
    true
}

/// A code with a name (exception codes).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NamedCode {
    pub code: ExceptionCode,
    pub name: String,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// A 32-bit code with a name (SDO errors).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NamedCode32 {
    pub code: u32,
    pub name: String,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// Access mode of a register, coil or object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Access {
    Ro,
    Rw,
    Wo,
}

impl Access {
    /// Readable by a client.
    pub fn readable(self) -> bool {
        self != Access::Wo
    }
    /// Writable by a client.
    pub fn writable(self) -> bool {
        self != Access::Ro
    }
}

/// Which read function sees a register.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Table {
    Holding,
    Input,
    #[default]
    Both,
}

/// A register (16-bit) or register pair (32-bit).
#[derive(Clone, Debug, PartialEq)]
pub struct Register {
    pub address: u16,
    pub width: u8,
    pub name: String,
    pub mnemonic: Option<String>,
    /// For an unconfirmed entry that does not say, `Ro`: the harness never writes it.
    pub access: Access,
    pub signed: bool,
    pub min: Option<i64>,
    pub max: Option<i64>,
    pub default: Option<i64>,
    pub unit: Option<String>,
    pub table: Table,
    pub motion: bool,
    pub destructive: bool,
    pub group: Option<String>,
    pub description: Option<String>,
    pub note: Option<String>,
    pub line: Option<u32>,
    /// False when discovered by a probe and not confirmed: the catalog only reads it.
    pub confirmed: bool,
}

impl Register {
    /// One past the last register address this entry occupies.
    pub fn end(&self) -> u32 {
        u32::from(self.address) + u32::from(self.width)
    }

    /// The inclusive range of values the register can hold at its width and sign.
    pub fn natural_range(&self) -> (i64, i64) {
        let bits = 16 * u32::from(self.width);
        if self.signed {
            (-(1i64 << (bits - 1)), (1i64 << (bits - 1)) - 1)
        } else {
            (0, (1i64 << bits) - 1)
        }
    }

    /// `value` as the register's words on the wire: a 32-bit value split in `order`.
    pub fn words(&self, order: WordOrder, value: i64) -> Vec<u16> {
        if self.width == 2 {
            order.split(value as u32).to_vec()
        } else {
            vec![value as u16]
        }
    }

    /// The inclusive range a write must fall in.
    pub fn range(&self) -> (i64, i64) {
        let (lo, hi) = self.natural_range();
        (self.min.unwrap_or(lo), self.max.unwrap_or(hi))
    }
}

/// A reserved address range.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reserved {
    pub start: u16,
    pub end: u16,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// A coil or discrete input.
#[derive(Clone, Debug, PartialEq)]
pub struct Bit {
    pub address: u16,
    pub name: String,
    pub access: Access,
    pub motion: bool,
    pub note: Option<String>,
    pub line: Option<u32>,
    /// False when discovered by a probe and not confirmed: the catalog only reads it.
    pub confirmed: bool,
}

/// A vendor FC 0x41/0x42 mnemonic.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VendorMnemonic {
    pub name: String,
    pub description: Option<String>,
    pub read: bool,
    pub write: bool,
    pub format: Option<String>,
    pub example: Option<String>,
    pub register: Option<u16>,
    #[serde(default)]
    pub motion: bool,
    #[serde(default)]
    pub destructive: bool,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// A device identification object (FC 2B/0E).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IdObject {
    pub object_id: u8,
    pub name: String,
    pub value: String,
    /// False when discovered by a probe and not confirmed.
    #[serde(default = "yes")]
    pub confirmed: bool,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// An FC 08 sub-function.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Diagnostic {
    pub sub_function: u16,
    pub name: String,
    pub counter: DiagCounter,
    /// False when discovered by a probe and not confirmed.
    #[serde(default = "yes")]
    pub confirmed: bool,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// What an FC 08 sub-function does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DiagCounter {
    Echo,
    Clear,
    BusMessage,
    CrcError,
    Exception,
    SlaveMessage,
    NoResponse,
}

/// Data type of a CANopen object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ObjectType {
    U16,
    I16,
    U32,
    I32,
}

impl ObjectType {
    /// Size in bytes.
    pub fn size(self) -> usize {
        match self {
            ObjectType::U16 | ObjectType::I16 => 2,
            ObjectType::U32 | ObjectType::I32 => 4,
        }
    }
}

/// A CANopen object (FC 2B/0D).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Object {
    pub index: u16,
    #[serde(default)]
    pub subindex: u8,
    pub name: String,
    #[serde(rename = "type")]
    pub ty: ObjectType,
    pub access: Access,
    pub unit: Option<String>,
    pub default: Option<i64>,
    pub min: Option<i64>,
    pub max: Option<i64>,
    #[serde(default)]
    pub motion: bool,
    /// The PDO register (first of a pair) this object mirrors: both views must agree.
    pub register: Option<u16>,
    pub description: Option<String>,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// The RxPDO watchdog (SD2x).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Watchdog {
    pub register: u16,
    #[serde(default = "one_u32")]
    pub unit_ms: u32,
    pub fault_error_code: Option<u16>,
    pub note: Option<String>,
    pub line: Option<u32>,
}

fn one_u32() -> u32 {
    1
}

/// Order of the two registers of a 32-bit value.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WordOrder {
    #[default]
    HighFirst,
    LowFirst,
}

impl WordOrder {
    /// Join two registers into a 32-bit value.
    pub fn join(self, a: u16, b: u16) -> u32 {
        match self {
            WordOrder::HighFirst => (u32::from(a) << 16) | u32::from(b),
            WordOrder::LowFirst => (u32::from(b) << 16) | u32::from(a),
        }
    }

    /// Split a 32-bit value into two registers in wire order.
    pub fn split(self, v: u32) -> [u16; 2] {
        let (hi, lo) = ((v >> 16) as u16, v as u16);
        match self {
            WordOrder::HighFirst => [hi, lo],
            WordOrder::LowFirst => [lo, hi],
        }
    }
}

/// Why a profile was rejected.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    #[error("{path}: cannot read the profile file: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {reason}")]
    Invalid {
        path: String,
        line: usize,
        reason: String,
    },
}

/// Line (1-based) of a byte offset in `text`.
pub fn line_of(text: &str, offset: usize) -> usize {
    text.as_bytes()[..offset.min(text.len())]
        .iter()
        .filter(|b| **b == b'\n')
        .count()
        + 1
}

/// A TOML error as "line N: message" (toml's own text names the line too, but spans are the truth).
pub fn toml_error_message(text: &str, e: &toml::de::Error) -> String {
    match e.span() {
        Some(s) => format!("line {}: {}", line_of(text, s.start), e.message()),
        None => e.message().to_string(),
    }
}

impl Profile {
    /// Parse and validate profile text (blocks expanded); `name` is used in errors.
    pub fn parse(name: &str, text: &str) -> Result<Self, ProfileError> {
        let invalid = |offset: usize, reason: String| ProfileError::Invalid {
            path: name.to_string(),
            line: line_of(text, offset),
            reason,
        };
        let f: ProfileFile = toml::from_str(text).map_err(|e| ProfileError::Invalid {
            path: name.to_string(),
            line: e.span().map(|s| line_of(text, s.start)).unwrap_or(0),
            reason: e.message().to_string(),
        })?;
        let p = Profile::from_file(f).map_err(|(offset, reason)| invalid(offset, reason))?;
        p.validate()
            .map_err(|(offset, reason)| invalid(offset, reason))?;
        Ok(p)
    }

    /// Expand the blocks of a parsed file; the error carries the byte offset of the offending entry.
    fn from_file(f: ProfileFile) -> Result<Self, (usize, String)> {
        let draft = match f.draft {
            Some(d) => {
                let at = d.span().start;
                let d = d.into_inner();
                if d.scan[0] > d.scan[1] {
                    return Err((
                        at,
                        format!("draft.scan {:?} is not an ascending range", d.scan),
                    ));
                }
                if let Some(code) = d
                    .unsupported_functions
                    .iter()
                    .find(|c| f.functions.iter().any(|fun| fun.code == **c))
                {
                    return Err((
                        at,
                        format!(
                            "function 0x{:02X} is in draft.unsupported_functions and has a [[function]] entry",
                            code.0
                        ),
                    ));
                }
                Some(d)
            }
            None => None,
        };
        Ok(Profile {
            registers: expand_all(f.registers, RegisterEntry::expand)?,
            coils: expand_all(f.coils, |b: &BitEntry| b.expand("coil"))?,
            discrete_inputs: expand_all(f.discrete_inputs, |b: &BitEntry| {
                b.expand("discrete input")
            })?,
            device: f.device,
            serial: f.serial,
            functions: f.functions,
            exceptions: f.exceptions,
            reserved: f.reserved,
            mnemonics: f.mnemonics,
            identification: f.identification,
            diagnostics: f.diagnostics,
            objects: f.objects,
            sdo_errors: f.sdo_errors,
            watchdog: f.watchdog,
            draft,
        })
    }

    /// Load and validate a profile file.
    pub fn load(path: &Path) -> Result<Self, ProfileError> {
        let text = std::fs::read_to_string(path).map_err(|source| ProfileError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&path.display().to_string(), &text)
    }

    /// Semantic checks; the error carries the byte offset of the offending entry.
    fn validate(&self) -> Result<(), (usize, String)> {
        if self.device.unit_ids[0] > self.device.unit_ids[1] {
            return Err((
                0,
                format!(
                    "device.unit_ids {:?} is not an ascending range",
                    self.device.unit_ids
                ),
            ));
        }
        let mut by_addr: BTreeMap<(bool, u16), (usize, &Register)> = BTreeMap::new();
        for r in &self.registers {
            let at = r.span().start;
            let reg = r.get_ref();
            if reg.width != 1 && reg.width != 2 {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: width {} (must be 1 or 2 registers)",
                        reg.address, reg.name, reg.width
                    ),
                ));
            }
            if reg.end() > 0x1_0000 {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: runs past address 0xFFFF",
                        reg.address, reg.name
                    ),
                ));
            }
            let (lo, hi) = reg.natural_range();
            let (min, max) = reg.range();
            if min > max {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: min {min} > max {max}",
                        reg.address, reg.name
                    ),
                ));
            }
            if min < lo || max > hi {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: range {min}..={max} does not fit {} {}-bit (allowed {lo}..={hi})",
                        reg.address,
                        reg.name,
                        if reg.signed { "signed" } else { "unsigned" },
                        16 * reg.width
                    ),
                ));
            }
            if let Some(d) = reg.default
                && (d < min || d > max)
            {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: default {d} outside {min}..={max}",
                        reg.address, reg.name
                    ),
                ));
            }
            // Holding and input tables may overlap each other only when one is input-only and one holding-only.
            let tables: &[bool] = match reg.table {
                Table::Both => &[false, true],
                Table::Holding => &[false],
                Table::Input => &[true],
            };
            for &input in tables {
                if let Some((_, (_, prev))) = by_addr.range(..=(input, reg.address)).next_back()
                    && by_addr
                        .range(..=(input, reg.address))
                        .next_back()
                        .map(|(k, _)| k.0)
                        == Some(input)
                    && prev.end() > u32::from(reg.address)
                {
                    return Err((
                        at,
                        format!(
                            "register 0x{:04X} `{}` overlaps register 0x{:04X} `{}` (width {})",
                            reg.address, reg.name, prev.address, prev.name, prev.width
                        ),
                    ));
                }
                if let Some((k, (_, next))) = by_addr.range((input, reg.address)..).next()
                    && k.0 == input
                    && u32::from(next.address) < reg.end()
                {
                    return Err((
                        at,
                        format!(
                            "register 0x{:04X} `{}` (width {}) overlaps register 0x{:04X} `{}`",
                            reg.address, reg.name, reg.width, next.address, next.name
                        ),
                    ));
                }
                by_addr.insert((input, reg.address), (at, reg));
            }
        }
        for r in &self.reserved {
            let res = r.get_ref();
            if res.start > res.end {
                return Err((
                    r.span().start,
                    format!(
                        "reserved range 0x{:04X}..0x{:04X} is reversed",
                        res.start, res.end
                    ),
                ));
            }
            if let Some(reg) = self.registers.iter().map(|r| r.get_ref()).find(|reg| {
                u32::from(reg.address) <= u32::from(res.end) && reg.end() > u32::from(res.start)
            }) {
                return Err((
                    r.span().start,
                    format!(
                        "reserved range 0x{:04X}..=0x{:04X} overlaps register 0x{:04X} `{}`",
                        res.start, res.end, reg.address, reg.name
                    ),
                ));
            }
        }
        let mut seen = BTreeMap::new();
        for m in &self.mnemonics {
            let name = &m.get_ref().name;
            if name.is_empty() || name.len() > 4 || !name.is_ascii() {
                return Err((
                    m.span().start,
                    format!("mnemonic `{name}`: must be 1 to 4 ASCII characters"),
                ));
            }
            if seen.insert(name.clone(), ()).is_some() {
                return Err((m.span().start, format!("mnemonic `{name}` defined twice")));
            }
        }
        let mut objs = BTreeMap::new();
        for o in &self.objects {
            let ob = o.get_ref();
            if objs.insert((ob.index, ob.subindex), ()).is_some() {
                return Err((
                    o.span().start,
                    format!("object {}.{} defined twice", ob.index, ob.subindex),
                ));
            }
        }
        for (list, what) in [
            (&self.coils, "coil"),
            (&self.discrete_inputs, "discrete input"),
        ] {
            let mut seen = BTreeMap::new();
            for b in list {
                if seen.insert(b.get_ref().address, ()).is_some() {
                    return Err((
                        b.span().start,
                        format!("{what} {} defined twice", b.get_ref().address),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The register entry covering `address` (either register of a 32-bit pair), holding or input table.
    pub fn register_at(&self, address: u16, input: bool) -> Option<&Register> {
        self.registers.iter().map(|r| r.get_ref()).find(|r| {
            let t = match r.table {
                Table::Both => true,
                Table::Holding => !input,
                Table::Input => input,
            };
            t && u32::from(r.address) <= u32::from(address) && u32::from(address) < r.end()
        })
    }

    /// True when `address` lies in a reserved range.
    pub fn is_reserved(&self, address: u16) -> bool {
        self.reserved
            .iter()
            .any(|r| r.get_ref().start <= address && address <= r.get_ref().end)
    }

    /// The function entry for `code`, if supported.
    pub fn function(&self, code: impl Into<FunctionCode>) -> Option<&Function> {
        let code = code.into();
        self.functions.iter().find(|f| f.code == code)
    }

    /// The mnemonic entry named `name`.
    pub fn mnemonic(&self, name: &str) -> Option<&VendorMnemonic> {
        self.mnemonics
            .iter()
            .map(|m| m.get_ref())
            .find(|m| m.name.eq_ignore_ascii_case(name))
    }

    /// The object at `index`/`subindex`.
    pub fn object(&self, index: u16, subindex: u8) -> Option<&Object> {
        self.objects
            .iter()
            .map(|o| o.get_ref())
            .find(|o| o.index == index && o.subindex == subindex)
    }
}
