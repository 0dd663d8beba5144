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
    /// FC 07: the exception status outputs.
    pub exception_status: Option<Spanned<ExceptionStatus>>,
    /// FC 11: the server id, run indicator and additional data.
    pub server_id: Option<Spanned<ServerId>>,
    /// FC 14/15: the files of records.
    pub files: Vec<Spanned<RecordFile>>,
    /// FC 18: the FIFO queues.
    pub fifos: Vec<Spanned<Fifo>>,
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
    exception_status: Option<Spanned<ExceptionStatus>>,
    server_id: Option<Spanned<ServerId>>,
    #[serde(rename = "file", default)]
    files: Vec<Spanned<RecordFile>>,
    #[serde(rename = "fifo", default)]
    fifos: Vec<Spanned<Fifo>>,
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
    /// The drive's digital I/O points are shared between inputs and outputs, each set up as one or the other
    /// with S1..Sn (FC 0x42), n being the number of its coils and of its discrete inputs (the MDrive, 000
    /// lines 532, 1263). False: outputs are outputs of their own (the LMD), whatever mnemonics the profile has.
    #[serde(default)]
    pub shared_io_points: bool,
    /// The device-specific contents the profile declares ([exception_status], [server_id], [[file]],
    /// [[fifo]]: App 6.7, 6.13, 6.14, 6.18 leave them to the device) are the reference drive's own, not a
    /// requirement on the target: a run against anything but `sim:` compares FC 07, 11, 18 and FC 14 (where the
    /// case writes no record first) in format only, and takes a refusal with 02 or 03 of a queue or file the
    /// device does not have. The generic profile, which stands for any Modbus server.
    #[serde(default)]
    pub reference_contents: bool,
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
    /// Where the manual gives the range two ways (`min`/`max` is then the widest reading): the values every
    /// reading takes. The harness writes no other value inside the range; empty for a range read one way.
    pub safe_values: Vec<i64>,
    /// The manual gives no written value a meaning every reading shares (MCode DC/IC, "the specified
    /// variable": its address, an index of R1-R4, or nothing at all): a drive may refuse any value with 03
    /// (freedom `value-meaning-open`), the values of `safe_values` too. The harness still writes only those.
    pub operand_open: bool,
    /// The manual gives the register's width two ways (two addresses, two bytes): a drive may take a write
    /// of its first register for a whole one. What a drive does with a half write of it is held apart from
    /// the other registers' (freedom `partial-register-write`).
    pub width_disputed: bool,
    pub default: Option<i64>,
    pub unit: Option<String>,
    pub table: Table,
    pub motion: bool,
    pub destructive: bool,
    /// Why `motion` / `destructive` are set (or deliberately not): the manual line (`file:line`) that justifies it.
    pub why: Option<String>,
    pub group: Option<String>,
    pub description: Option<String>,
    pub note: Option<String>,
    pub line: Option<u32>,
    /// False when discovered by a probe and not confirmed: the catalog only reads it.
    pub confirmed: bool,
    /// A read clears it (the MCode error code ER: "must be read or set to 0 to clear"): the safety classifier
    /// rates a read of it destructive, as it rates a write.
    pub read_clears: bool,
    /// An error record (MCode ER) whose drive says with this register (MCode EF, 0 or 1) whether an error
    /// condition exists now: while the flag is set, the drive may record the error again right after a
    /// clear, so a record read back non-zero after its clear is judged with the flag.
    pub condition_flag: Option<u16>,
    /// A write of it puts the drive's settings back to their initial values (the LMD's IP, "Reset all
    /// parameters to initial values", 001 line 2172): it changes every setting a session keeps.
    pub resets_settings: bool,
    /// A write of it saves the working settings to non-volatile memory (MCode S, "Save", 000 line 1112, 001
    /// line 2384): before a case writes it, every setting a session keeps is put back as found, so that
    /// the save stores them so.
    pub saves_settings: bool,
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

    /// Whether the manual leaves what writing `value` means open (freedom `value-meaning-open`): a value
    /// outside `safe_values`, or any value of an `operand_open` register.
    pub fn meaning_open(&self, value: i64) -> bool {
        self.operand_open || (!self.safe_values.is_empty() && !self.safe_values.contains(&value))
    }

    /// A one-register entry's value as `word` holds it, at the register's sign.
    pub fn value_of_word(&self, word: u16) -> i64 {
        if self.signed {
            i64::from(word as i16)
        } else {
            i64::from(word)
        }
    }

    /// The inclusive range a write must fall in.
    pub fn range(&self) -> (i64, i64) {
        let (lo, hi) = self.natural_range();
        (self.min.unwrap_or(lo), self.max.unwrap_or(hi))
    }

    /// `value` where every reading of the manual takes it: unchanged where the range is read one way, or
    /// outside the widest reading (refused by every reading); otherwise one of `safe_values`, chosen by the
    /// value (so that a spread of values gives each).
    pub fn undisputed(&self, value: i64) -> i64 {
        let (min, max) = self.range();
        if self.safe_values.is_empty()
            || !(min..=max).contains(&value)
            || self.safe_values.contains(&value)
        {
            return value;
        }
        self.safe_values[value.unsigned_abs() as usize % self.safe_values.len()]
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
    /// Writing it cannot be put back (an action, a counter reset).
    pub destructive: bool,
    /// Why `motion` / `destructive` are set (or deliberately not): the manual line (`file:line`) that justifies it.
    pub why: Option<String>,
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
    /// Why `motion` / `destructive` are set (or deliberately not): the manual line (`file:line`) that justifies it.
    pub why: Option<String>,
    /// The manual documents no FC 0x41 read of it on this drive, and a drive may read it as the line of
    /// this point of the setting the manual does document (the LMD's S1-S4, known only from an FC 0x42
    /// example copied from the MDrive manual, and its IS, read "=line,type,active"): a value read that
    /// begins with this number may be that line, whose fields are not the ones the setting's write takes.
    /// Where the flags keep such a setting (it is `motion` or `destructive`), the leave-as-found keeper
    /// makes no trial write of such a value (see `Keeper::take_snapshot` in the engine).
    pub read_as_line: Option<u8>,
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
    /// The request's data field must be what MODBUS Application Protocol v1.1b3 section 6.8.1 gives the
    /// sub-function (00 00; 00 00 or FF 00 for 01; CHAR 00 for 03), else exception 03 ("Data Value == OK",
    /// figure 18). Off by default: the SD2x manual only says a data word is always sent.
    #[serde(default)]
    pub check_data: bool,
    /// The size in bytes of the data field where the manual fixes it (the SD2x: "the diagnostics telegram has
    /// always the same size", two data bytes): the catalog's return query data sends that many. Unset: any
    /// number of words (6.8.1), and the catalog sends four bytes.
    pub data_bytes: Option<u8>,
    /// `counter = "diagnostic_register"` only: the register's content at power-up and after a restart.
    pub value: Option<u16>,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// What an FC 08 sub-function does (MODBUS Application Protocol v1.1b3 section 6.8.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DiagCounter {
    /// 00: return query data.
    Echo,
    /// 0A: clear counters and diagnostic register.
    Clear,
    /// 0B: bus message count.
    BusMessage,
    /// 0C: bus communication error (CRC) count.
    CrcError,
    /// 0D: bus exception error count.
    Exception,
    /// 0E: server message count.
    SlaveMessage,
    /// 0F: server no response count.
    NoResponse,
    /// 01: restart communications option.
    Restart,
    /// 02: return diagnostic register.
    DiagnosticRegister,
    /// 03: change ASCII input delimiter.
    AsciiDelimiter,
    /// 04: force listen only mode.
    ListenOnly,
    /// 10: server NAK count.
    Nak,
    /// 11: server busy count.
    Busy,
    /// 12: bus character overrun count.
    Overrun,
    /// 14: clear overrun counter and flag.
    ClearOverrun,
}

impl DiagCounter {
    /// The sub-function section 6.8.1 gives this behaviour.
    pub fn sub_function(self) -> u16 {
        use codec::codes::diag::*;
        match self {
            DiagCounter::Echo => RETURN_QUERY_DATA,
            DiagCounter::Restart => RESTART_COMMUNICATIONS,
            DiagCounter::DiagnosticRegister => RETURN_DIAGNOSTIC_REGISTER,
            DiagCounter::AsciiDelimiter => CHANGE_ASCII_DELIMITER,
            DiagCounter::ListenOnly => FORCE_LISTEN_ONLY,
            DiagCounter::Clear => CLEAR_COUNTERS,
            DiagCounter::BusMessage => BUS_MESSAGE_COUNT,
            DiagCounter::CrcError => BUS_COMM_ERROR_COUNT,
            DiagCounter::Exception => BUS_EXCEPTION_ERROR_COUNT,
            DiagCounter::SlaveMessage => SERVER_MESSAGE_COUNT,
            DiagCounter::NoResponse => SERVER_NO_RESPONSE_COUNT,
            DiagCounter::Nak => SERVER_NAK_COUNT,
            DiagCounter::Busy => SERVER_BUSY_COUNT,
            DiagCounter::Overrun => BUS_CHARACTER_OVERRUN_COUNT,
            DiagCounter::ClearOverrun => CLEAR_OVERRUN,
        }
    }

    /// The name a profile gives it (`counter = "..."`).
    pub fn key(self) -> &'static str {
        match self {
            DiagCounter::Echo => "echo",
            DiagCounter::Clear => "clear",
            DiagCounter::BusMessage => "bus_message",
            DiagCounter::CrcError => "crc_error",
            DiagCounter::Exception => "exception",
            DiagCounter::SlaveMessage => "slave_message",
            DiagCounter::NoResponse => "no_response",
            DiagCounter::Restart => "restart",
            DiagCounter::DiagnosticRegister => "diagnostic_register",
            DiagCounter::AsciiDelimiter => "ascii_delimiter",
            DiagCounter::ListenOnly => "listen_only",
            DiagCounter::Nak => "nak",
            DiagCounter::Busy => "busy",
            DiagCounter::Overrun => "overrun",
            DiagCounter::ClearOverrun => "clear_overrun",
        }
    }

    /// Every behaviour, in sub-function order.
    pub const ALL: [DiagCounter; 15] = [
        DiagCounter::Echo,
        DiagCounter::Restart,
        DiagCounter::DiagnosticRegister,
        DiagCounter::AsciiDelimiter,
        DiagCounter::ListenOnly,
        DiagCounter::Clear,
        DiagCounter::BusMessage,
        DiagCounter::CrcError,
        DiagCounter::Exception,
        DiagCounter::SlaveMessage,
        DiagCounter::NoResponse,
        DiagCounter::Nak,
        DiagCounter::Busy,
        DiagCounter::Overrun,
        DiagCounter::ClearOverrun,
    ];

    /// The behaviour of a public sub-function; `None` for a reserved one.
    pub fn of_sub_function(sub_function: u16) -> Option<Self> {
        Self::ALL
            .into_iter()
            .find(|c| c.sub_function() == sub_function)
    }

    /// Sub-functions that act on a serial port itself: restarting it (01), the ASCII delimiter (03), leaving the
    /// bus (04), character overruns (12, 14). A Modbus/TCP server answers them with exception 01; the others
    /// (the echo, the diagnostic register, the counters) are answered on every transport.
    pub fn serial_line_only(self) -> bool {
        matches!(
            self,
            DiagCounter::Restart
                | DiagCounter::AsciiDelimiter
                | DiagCounter::ListenOnly
                | DiagCounter::Overrun
                | DiagCounter::ClearOverrun
        )
    }
}

/// The eight exception status outputs of FC 07 (MODBUS Application Protocol v1.1b3 section 6.7).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExceptionStatus {
    /// The status byte (output 0 in bit 0) for the outputs no coil drives.
    #[serde(default)]
    pub value: u8,
    /// Coils that drive outputs 0, 1, ... (at most 8): output i is the state of `coils[i]`.
    #[serde(default)]
    pub coils: Vec<u16>,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// What FC 11 reports (MODBUS Application Protocol v1.1b3 section 6.13).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerId {
    /// The server id bytes (device specific length).
    pub id: Vec<u8>,
    /// The run indicator status: ON (0xFF) or OFF (0x00).
    #[serde(default = "yes")]
    pub run_indicator: bool,
    /// Device specific additional data after the run indicator, as text.
    #[serde(default)]
    pub additional_data: String,
    pub note: Option<String>,
    pub line: Option<u32>,
}

impl ServerId {
    /// The data FC 11 answers after its byte count: id, run indicator (0xFF on, 0x00 off), additional data.
    pub fn data(&self) -> Vec<u8> {
        let mut d = self.id.clone();
        d.push(if self.run_indicator { 0xFF } else { 0x00 });
        d.extend_from_slice(self.additional_data.as_bytes());
        d
    }
}

/// A file of records for FC 14/15 (MODBUS Application Protocol v1.1b3 sections 6.14, 6.15).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordFile {
    /// The file number, 1 to 0xFFFF.
    pub number: u16,
    pub name: Option<String>,
    /// How many records (registers) the file holds, 1 to 10000; records 0 to `records - 1` exist.
    pub records: u16,
    /// The content from record 0 on; records past it start at 0.
    #[serde(default)]
    pub values: Vec<u16>,
    /// `ro` files refuse FC 15 (exception 02), `wo` files FC 14.
    #[serde(default = "read_write")]
    pub access: Access,
    pub note: Option<String>,
    pub line: Option<u32>,
}

/// Files are readable and writable unless the profile says otherwise.
fn read_write() -> Access {
    Access::Rw
}

/// A FIFO queue for FC 18 (MODBUS Application Protocol v1.1b3 section 6.18).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fifo {
    /// The FIFO pointer address a request names.
    pub address: u16,
    pub name: Option<String>,
    /// The queued registers, oldest first. More than 31 is allowed: the server then answers exception 03.
    #[serde(default)]
    pub values: Vec<u16>,
    pub note: Option<String>,
    pub line: Option<u32>,
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
    /// Writing it cannot be put back (a store, a reset).
    #[serde(default)]
    pub destructive: bool,
    /// Why `motion` / `destructive` are set (or deliberately not): the manual line (`file:line`) that justifies it.
    pub why: Option<String>,
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

/// Where entries whose type carries no span start in the text (a second, lenient read of the same text).
#[derive(Default, Deserialize)]
struct EntrySpans {
    #[serde(default)]
    diagnostic: Vec<Spanned<toml::Value>>,
    #[serde(default)]
    identification: Vec<Spanned<toml::Value>>,
    #[serde(default)]
    function: Vec<Spanned<toml::Value>>,
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

/// Line numbers of byte offsets in one text, by binary search over its newlines: [`line_of`] scans the text up
/// to the offset, and a corpus of a few thousand requirements, freedoms and cites scanned its files once for
/// each (a third of the time a one-case run took to start).
pub struct LineIndex(Vec<usize>);

impl LineIndex {
    pub fn new(text: &str) -> Self {
        Self(
            text.bytes()
                .enumerate()
                .filter_map(|(i, b)| (b == b'\n').then_some(i))
                .collect(),
        )
    }

    /// The 1-based line of `offset`: as [`line_of`].
    pub fn line(&self, offset: usize) -> usize {
        self.0.partition_point(|&nl| nl < offset) + 1
    }
}

/// A TOML error as "line N: message" (toml's own text names the line too, but spans are the truth).
pub fn toml_error_message(text: &str, e: &toml::de::Error) -> String {
    match e.span() {
        Some(s) => format!("line {}: {}", line_of(text, s.start), e.message()),
        None => e.message().to_string(),
    }
}

impl Profile {
    /// True when the device speaks Modbus/TCP itself (`transports`): without it, a Modbus/TCP client reaches
    /// it through a gateway.
    pub fn speaks_tcp(&self) -> bool {
        self.device.transports.contains(&Transport::Tcp)
    }

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
        // Where the entries without a span of their own start, for the errors about them.
        let spans: EntrySpans = toml::from_str(text).unwrap_or_default();
        p.validate()
            .and_then(|()| p.validate_function_data(&spans))
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
            exception_status: f.exception_status,
            server_id: f.server_id,
            files: f.files,
            fifos: f.fifos,
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
            if let Some(flag) = reg.condition_flag
                && !self
                    .registers
                    .iter()
                    .map(|r| r.get_ref())
                    .any(|f| f.address == flag && f.width == 1 && f.access.readable())
            {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: condition_flag 0x{flag:04X} is not a readable one-register register of the profile",
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
            if let Some(v) = reg.safe_values.iter().find(|v| !(min..=max).contains(*v)) {
                return Err((
                    at,
                    format!(
                        "register 0x{:04X} `{}`: safe value {v} is outside its range {min}..={max}",
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
        if self.device.shared_io_points {
            let n = self.coils.len();
            if n == 0 || self.discrete_inputs.len() != n {
                return Err((
                    0,
                    format!(
                        "device.shared_io_points: needs as many discrete inputs as coils, at least one (has {n} coils, {} discrete inputs)",
                        self.discrete_inputs.len()
                    ),
                ));
            }
            if let Some(k) = (1..=n).find(|k| {
                !self.mnemonics.iter().any(|m| {
                    m.get_ref().name == format!("S{k}") && m.get_ref().read && m.get_ref().write
                })
            }) {
                return Err((
                    0,
                    format!(
                        "device.shared_io_points: point {k} has no read/write setup mnemonic `S{k}` (points 1..{n} are set up with S1..S{n})"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Checks of the data the function codes 07, 08, 11, 14, 15, 18 and 2B/0E serve: each needs its function
    /// declared, and holds only what the MODBUS Application Protocol v1.1b3 lets a server answer.
    fn validate_function_data(&self, spans: &EntrySpans) -> Result<(), (usize, String)> {
        let needs = |fcs: &[FunctionCode], at: usize, what: &str| {
            if fcs.iter().any(|fc| self.function(*fc).is_some()) {
                return Ok(());
            }
            let codes: Vec<String> = fcs
                .iter()
                .map(|fc| format!("0x{:02X} ({})", fc.0, fc.name().unwrap_or("?")))
                .collect();
            Err((
                at,
                format!(
                    "{what} is served by function {}, which the profile does not declare in [[function]]",
                    codes.join(" or ")
                ),
            ))
        };
        // The largest PDU the device answers.
        let max_pdu = usize::from(self.device.max_pdu).min(codec::MAX_PDU_LEN);
        self.validate_diagnostics(&spans.diagnostic, &needs)?;
        if let Some(e) = &self.exception_status {
            let at = e.span().start;
            needs(
                &[FunctionCode::READ_EXCEPTION_STATUS],
                at,
                "[exception_status]",
            )?;
            let coils = &e.get_ref().coils;
            if coils.len() > 8 {
                return Err((
                    at,
                    format!(
                        "[exception_status]: {} coils for eight outputs (spec 6.7)",
                        coils.len()
                    ),
                ));
            }
            if let Some(c) = coils
                .iter()
                .find(|c| !self.coils.iter().any(|b| b.get_ref().address == **c))
            {
                return Err((
                    at,
                    format!("[exception_status]: coil {c} is not a [[coil]] of the profile"),
                ));
            }
        }
        if let Some(i) = self
            .functions
            .iter()
            .position(|f| f.code == FunctionCode::REPORT_SERVER_ID)
            && self.server_id.is_none()
        {
            return Err((
                spans.function.get(i).map_or(0, |s| s.span().start),
                "function 0x11 (Report Server ID) needs a [server_id] table: what the device reports is device \
                 specific (spec 6.13)"
                    .to_string(),
            ));
        }
        if let Some(sid) = &self.server_id {
            let at = sid.span().start;
            needs(&[FunctionCode::REPORT_SERVER_ID], at, "[server_id]")?;
            // FC, byte count, then the data.
            let n = sid.get_ref().data().len();
            if n + 2 > max_pdu {
                return Err((
                    at,
                    format!(
                        "[server_id]: id, run indicator and additional data are {n} bytes; with the function code \
                         and byte count they exceed the {max_pdu}-byte PDU (spec 6.13)"
                    ),
                ));
            }
        }
        let mut numbers = BTreeMap::new();
        for f in &self.files {
            let at = f.span().start;
            let file = f.get_ref();
            let what = format!("[[file]] {}", file.number);
            needs(
                &[
                    FunctionCode::READ_FILE_RECORD,
                    FunctionCode::WRITE_FILE_RECORD,
                ],
                at,
                &what,
            )?;
            if file.number == 0 {
                return Err((
                    at,
                    format!("{what}: file numbers run from 1 to 0xFFFF (spec 6.14)"),
                ));
            }
            if numbers.insert(file.number, ()).is_some() {
                return Err((at, format!("{what} defined twice")));
            }
            if file.records == 0 || u32::from(file.records) > codec::codes::file::RECORDS_PER_FILE {
                return Err((
                    at,
                    format!(
                        "{what}: {} records; a file holds 1 to 10000 (records 0x0000-0x270F, spec 6.14)",
                        file.records
                    ),
                ));
            }
            if file.values.len() > usize::from(file.records) {
                return Err((
                    at,
                    format!(
                        "{what}: {} values for {} records",
                        file.values.len(),
                        file.records
                    ),
                ));
            }
        }
        let mut pointers = BTreeMap::new();
        for q in &self.fifos {
            let at = q.span().start;
            let fifo = q.get_ref();
            let what = format!("[[fifo]] 0x{:04X}", fifo.address);
            needs(&[FunctionCode::READ_FIFO_QUEUE], at, &what)?;
            if pointers.insert(fifo.address, ()).is_some() {
                return Err((at, format!("{what} defined twice")));
            }
            if fifo.values.len() > usize::from(u16::MAX) {
                return Err((at, format!("{what}: {} values", fifo.values.len())));
            }
        }
        // Spec 6.21: "an object is indivisible": each must fit a response of its own (FC, MEI, read code,
        // conformity, more follows, next object id, object count, then id and length).
        let room = max_pdu.saturating_sub(9).min(255);
        for (i, o) in self.identification.iter().enumerate() {
            if o.value.len() > room {
                return Err((
                    spans.identification.get(i).map_or(0, |s| s.span().start),
                    format!(
                        "identification object 0x{:02X} `{}`: {} bytes do not fit one FC 2B/0E response (at most \
                         {room} with max_pdu {max_pdu}); an object is indivisible (spec 6.21)",
                        o.object_id,
                        o.name,
                        o.value.len()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// `[[diagnostic]]` entries: FC 08 declared, each public sub-function once with the behaviour section 6.8.1
    /// gives it, no reserved sub-function.
    fn validate_diagnostics(
        &self,
        spans: &[Spanned<toml::Value>],
        needs: &impl Fn(&[FunctionCode], usize, &str) -> Result<(), (usize, String)>,
    ) -> Result<(), (usize, String)> {
        let mut seen = BTreeMap::new();
        for (i, d) in self.diagnostics.iter().enumerate() {
            let at = spans.get(i).map_or(0, |s| s.span().start);
            let what = format!("[[diagnostic]] sub-function 0x{:02X}", d.sub_function);
            needs(&[FunctionCode::DIAGNOSTICS], at, &what)?;
            if seen.insert(d.sub_function, ()).is_some() {
                return Err((at, format!("{what} defined twice")));
            }
            match DiagCounter::of_sub_function(d.sub_function) {
                None => {
                    return Err((
                        at,
                        format!(
                            "{what} is reserved (MODBUS Application Protocol v1.1b3, 6.8.1 and Annex A): only the \
                             public sub-functions 00-04, 0A-12 and 14 can be served"
                        ),
                    ));
                }
                Some(c) if c != d.counter => {
                    return Err((
                        at,
                        format!(
                            "{what} is {} (spec 6.8.1): counter must be \"{}\", not \"{}\"",
                            codec::codes::diag::name(d.sub_function).unwrap_or("?"),
                            c.key(),
                            d.counter.key()
                        ),
                    ));
                }
                Some(_) => {}
            }
            if d.value.is_some() && d.counter != DiagCounter::DiagnosticRegister {
                return Err((
                    at,
                    format!(
                        "{what}: `value` is the diagnostic register's content, only for counter = \"diagnostic_register\""
                    ),
                ));
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

    /// The most items one request of `code` may carry on this drive: the profile's limit, else the spec's,
    /// else 125.
    pub fn max_quantity(&self, code: impl Into<FunctionCode>) -> u16 {
        let code = code.into();
        self.function(code)
            .and_then(|f| f.max_quantity)
            .or(code.max_quantity())
            .unwrap_or(125)
    }

    /// The register whose MCode mnemonic is `name` (case-insensitive).
    pub fn register_by_mnemonic(&self, name: &str) -> Option<&Register> {
        self.registers.iter().map(|r| r.get_ref()).find(|r| {
            r.mnemonic
                .as_deref()
                .is_some_and(|m| m.eq_ignore_ascii_case(name))
        })
    }

    /// The mnemonic entry named `name`.
    pub fn mnemonic(&self, name: &str) -> Option<&VendorMnemonic> {
        self.mnemonics
            .iter()
            .map(|m| m.get_ref())
            .find(|m| m.name.eq_ignore_ascii_case(name))
    }

    /// The FIFO queue whose pointer address is `address` (FC 18).
    pub fn fifo(&self, address: u16) -> Option<&Fifo> {
        self.fifos
            .iter()
            .map(|q| q.get_ref())
            .find(|q| q.address == address)
    }

    /// The file numbered `number` (FC 14/15).
    pub fn file(&self, number: u16) -> Option<&RecordFile> {
        self.files
            .iter()
            .map(|f| f.get_ref())
            .find(|f| f.number == number)
    }

    /// The FC 08 sub-function entry for `sub_function`.
    pub fn diagnostic(&self, sub_function: u16) -> Option<&Diagnostic> {
        self.diagnostics
            .iter()
            .find(|d| d.sub_function == sub_function)
    }

    /// The object at `index`/`subindex`.
    pub fn object(&self, index: u16, subindex: u8) -> Option<&Object> {
        self.objects
            .iter()
            .map(|o| o.get_ref())
            .find(|o| o.index == index && o.subindex == subindex)
    }

    /// The first object a client may read (the one the CANopen cases and the learning read use).
    pub fn first_readable_object(&self) -> Option<&Object> {
        self.objects
            .iter()
            .map(|o| o.get_ref())
            .find(|o| o.access.readable())
    }
}
