//! The vector files of `tests/vectors/` (schema: tests/vectors/README.md): loaded, and every entry checked.
//! A file's entries are all checked before the test fails, and the failure names each failing entry and
//! what differs.

use std::collections::BTreeSet;
use std::fmt::Debug;
use std::path::PathBuf;
use std::time::Duration;

use codec::pdu::{Direction, Pdu, Request, Response};
use codec::{
    CharFormat, DecodeError, DecodeErrorKind, FieldValue, Mnemonic, Parity, RtuTiming, describe,
    parse_hex, rtu, tcp,
};
use serde::Deserialize;

/// One vector file: any of these tables.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    vector: Vec<Vector>,
    #[serde(default)]
    mnemonic: Vec<MnemonicRow>,
    #[serde(default)]
    char_format: Vec<CharFormatRow>,
    #[serde(default)]
    timing: Vec<TimingRow>,
    #[serde(default)]
    hex_input: Vec<HexInputRow>,
}

#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Framing {
    Rtu,
    Tcp,
    Pdu,
}

#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Dir {
    Request,
    Response,
}

/// Bytes to decode and what they must decode to, or the exact error.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Vector {
    name: String,
    framing: Framing,
    direction: Dir,
    hex: String,
    len: Option<usize>,
    // what the bytes decode to: an error, or a PDU (at least one of these keys)
    error: Option<toml::Table>,
    pdu: Option<String>,
    fields: Option<Vec<(String, toml::Value)>>,
    ok: Option<bool>,
    message: Option<Vec<String>>,
    address: Option<u8>,
    mbap: Option<MbapWant>,
    function: Option<u8>,
    is_exception: Option<bool>,
    encodes_back: Option<bool>,
    // RTU and MBAP framing details
    crc: Option<u16>,
    crc_ok: Option<bool>,
    check_adu: Option<bool>,
    adu_len: Option<usize>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MbapWant {
    transaction_id: u16,
    protocol_id: u16,
    length: u16,
    unit_id: u8,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MnemonicRow {
    name: String,
    wire: Option<String>,
    #[serde(default = "yes")]
    valid: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CharFormatRow {
    parity: String,
    stop_bits: u8,
    bits: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TimingRow {
    baud: u32,
    parity: String,
    stop_bits: u8,
    tolerance_us: u64,
    t3_5_us: u64,
    t1_5_us: u64,
    char_time_us: Option<u64>,
    transmit_8_bytes_us: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct HexInputRow {
    text: String,
    bytes: Option<Vec<u8>>,
    #[serde(default = "yes")]
    valid: bool,
}

fn yes() -> bool {
    true
}

fn dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/vectors"))
}

/// The `.toml` files of tests/vectors/ are exactly `files`: none is left unchecked.
pub fn assert_files_are(files: &[&str]) {
    let on_disk: BTreeSet<String> = std::fs::read_dir(dir())
        .expect("tests/vectors/ exists")
        .map(|e| {
            e.expect("directory entry")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .filter(|n| n.ends_with(".toml"))
        .collect();
    let checked: BTreeSet<String> = files.iter().map(|f| f.to_string()).collect();
    assert_eq!(
        on_disk, checked,
        "vector files without a test, or tests without a file"
    );
}

/// Load `tests/vectors/<name>` and check every entry; fail naming each entry that does not hold.
pub fn check_file(name: &str) {
    let path = dir().join(name);
    let text =
        std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    let file: File =
        toml::from_str(&text).unwrap_or_else(|e| panic!("parse {}: {e}", path.display()));
    let mut run = Run::default();
    for v in &file.vector {
        run.entry(&v.name, |c| check_vector(v, c));
    }
    for m in &file.mnemonic {
        run.entry(&format!("mnemonic {:?}", m.name), |c| check_mnemonic(m, c));
    }
    for f in &file.char_format {
        let what = format!(
            "char format {} parity, {} stop bit(s)",
            f.parity, f.stop_bits
        );
        run.entry(&what, |c| {
            let format = char_format(&f.parity, f.stop_bits);
            c.eq("bits per character", format.bits(), f.bits);
        });
    }
    for t in &file.timing {
        let what = format!(
            "timing {} baud, {} parity, {} stop bit(s)",
            t.baud, t.parity, t.stop_bits
        );
        run.entry(&what, |c| check_timing(t, c));
    }
    for h in &file.hex_input {
        run.entry(&format!("hex input {:?}", h.text), |c| {
            check_hex_input(h, c)
        });
    }
    run.finish(name);
}

/// The checks of one file: how many entries and checks ran, and every failure under its entry's name.
#[derive(Default)]
struct Run {
    entries: usize,
    checks: usize,
    failed: Vec<String>,
}

impl Run {
    fn entry(&mut self, name: &str, check: impl FnOnce(&mut Checks)) {
        let mut c = Checks::default();
        check(&mut c);
        self.entries += 1;
        self.checks += c.count;
        if c.count == 0 {
            c.failures.push("nothing is checked".into());
        }
        if !c.failures.is_empty() {
            self.failed
                .push(format!("{name}:\n      {}", c.failures.join("\n      ")));
        }
    }

    fn finish(self, file: &str) {
        // Shown with `--nocapture`: what the file holds.
        eprintln!("{file}: {} entries, {} checks", self.entries, self.checks);
        assert!(self.entries > 0, "{file} holds no entries");
        assert!(
            self.failed.is_empty(),
            "{} of {} entries of tests/vectors/{file} fail:\n  {}",
            self.failed.len(),
            self.entries,
            self.failed.join("\n  ")
        );
    }
}

/// The checks of one entry.
#[derive(Default)]
struct Checks {
    count: usize,
    failures: Vec<String>,
}

impl Checks {
    fn eq<T: PartialEq + Debug>(&mut self, what: &str, got: T, want: T) {
        self.count += 1;
        if got != want {
            self.failures
                .push(format!("{what}: got {got:?}, want {want:?}"));
        }
    }

    fn fail(&mut self, why: String) {
        self.count += 1;
        self.failures.push(why);
    }
}

/// Bytes written as hex, one byte per token; `XX*N` stands for N bytes XX.
fn hex_bytes(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    for token in text.split_whitespace() {
        let (byte, times) = match token.split_once('*') {
            Some((b, n)) => (
                b,
                n.parse::<usize>().map_err(|e| format!("{token:?}: {e}"))?,
            ),
            None => (token, 1),
        };
        if byte.len() != 2 {
            return Err(format!("{token:?}: one byte per token, two hex digits"));
        }
        let b = u8::from_str_radix(byte, 16).map_err(|e| format!("{token:?}: {e}"))?;
        out.extend(std::iter::repeat_n(b, times));
    }
    Ok(out)
}

fn char_format(parity: &str, stop_bits: u8) -> CharFormat {
    let parity = match parity {
        "none" => Parity::None,
        "even" => Parity::Even,
        "odd" => Parity::Odd,
        other => panic!("parity {other:?}: none, even or odd"),
    };
    CharFormat { parity, stop_bits }
}

/// A decode error as the vector files write it: `offset`, `kind` (the rule) and the rule's own fields;
/// shown as the files write it, an inline table.
#[derive(Clone, PartialEq)]
struct ErrorTable(toml::Table);

impl Debug for ErrorTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", toml::Value::Table(self.0.clone()))
    }
}

fn error_table(e: &DecodeError) -> ErrorTable {
    use DecodeErrorKind::*;
    use toml::Value;
    let int = |n: u64| Value::Integer(n as i64);
    let text = |s: &str| Value::String(s.to_string());
    let (kind, fields): (&str, Vec<(&str, Value)>) = match &e.kind {
        Empty => ("Empty", vec![]),
        Truncated {
            field,
            needed,
            available,
        } => (
            "Truncated",
            vec![
                ("field", text(field)),
                ("needed", int(*needed as u64)),
                ("available", int(*available as u64)),
            ],
        ),
        TrailingBytes { extra } => ("TrailingBytes", vec![("extra", int(*extra as u64))]),
        ByteCountMismatch {
            field,
            declared,
            expected,
            basis,
        } => (
            "ByteCountMismatch",
            vec![
                ("field", text(field)),
                ("declared", int(*declared as u64)),
                ("expected", int(*expected as u64)),
                ("basis", text(basis)),
            ],
        ),
        InvalidField { field, value, rule } => (
            "InvalidField",
            vec![
                ("field", text(field)),
                ("value", int(u64::from(*value))),
                ("rule", text(rule)),
            ],
        ),
        PduTooLong { len } => ("PduTooLong", vec![("len", int(*len as u64))]),
        ProtocolId { found } => ("ProtocolId", vec![("found", int(u64::from(*found)))]),
        MbapLength { declared, actual } => (
            "MbapLength",
            vec![
                ("declared", int(u64::from(*declared))),
                ("actual", int(*actual as u64)),
            ],
        ),
        MbapShort { len } => ("MbapShort", vec![("len", int(*len as u64))]),
        RtuShort { len } => ("RtuShort", vec![("len", int(*len as u64))]),
        RtuTooLong { len } => ("RtuTooLong", vec![("len", int(*len as u64))]),
        Crc { expected, received } => (
            "Crc",
            vec![
                ("expected", int(u64::from(*expected))),
                ("received", int(u64::from(*received))),
            ],
        ),
    };
    let mut t = toml::Table::new();
    t.insert("offset".into(), int(e.offset as u64));
    t.insert("kind".into(), text(kind));
    for (k, v) in fields {
        t.insert(k.into(), v);
    }
    ErrorTable(t)
}

/// A field value of `describe` as the vector files write it: an integer, an array of integers, a string,
/// or `{ bytes = "hex" }`.
fn field_value(v: &toml::Value) -> Result<FieldValue, String> {
    use toml::Value;
    let uint = |v: &Value| {
        v.as_integer()
            .and_then(|i| u64::try_from(i).ok())
            .ok_or_else(|| format!("{v}: not an unsigned integer"))
    };
    match v {
        Value::Integer(_) => uint(v).map(FieldValue::Int),
        Value::Array(a) => a
            .iter()
            .map(uint)
            .collect::<Result<_, _>>()
            .map(FieldValue::Ints),
        Value::String(s) => Ok(FieldValue::Text(s.clone())),
        Value::Table(t) => match t.get("bytes").and_then(Value::as_str) {
            Some(h) if t.len() == 1 => hex_bytes(h).map(FieldValue::Bytes),
            _ => Err(format!("{v}: a table is {{ bytes = \"hex\" }}")),
        },
        other => Err(format!("{other}: not a field value")),
    }
}

/// What decoding a vector gave: the PDU, and the RTU address or the MBAP header around it.
struct Decoded {
    pdu: Pdu,
    address: Option<u8>,
    mbap: Option<tcp::Mbap>,
}

fn decode(framing: Framing, dir: Direction, bytes: &[u8]) -> Result<Decoded, DecodeError> {
    match framing {
        Framing::Rtu => rtu::decode(bytes, dir).map(|(address, pdu)| Decoded {
            pdu,
            address: Some(address),
            mbap: None,
        }),
        Framing::Tcp => tcp::decode(bytes, dir).map(|(h, pdu)| Decoded {
            pdu,
            address: None,
            mbap: Some(h),
        }),
        Framing::Pdu => match dir {
            Direction::Request => Request::decode(bytes).map(Pdu::Request),
            Direction::Response => Response::decode(bytes).map(Pdu::Response),
        }
        .map(|pdu| Decoded {
            pdu,
            address: None,
            mbap: None,
        }),
    }
}

fn check_vector(v: &Vector, c: &mut Checks) {
    let bytes = match hex_bytes(&v.hex) {
        Ok(b) => b,
        Err(e) => return c.fail(format!("bad hex: {e}")),
    };
    if v.error.is_none() && v.pdu.is_none() && v.fields.is_none() && v.ok != Some(true) {
        return c.fail("no expectation: give `error`, `pdu`, `fields` or `ok = true`".into());
    }
    let dir = match v.direction {
        Dir::Request => Direction::Request,
        Dir::Response => Direction::Response,
    };
    if let Some(len) = v.len {
        c.eq("length of the bytes", bytes.len(), len);
    }
    let body_len = bytes.len().saturating_sub(2);
    if let Some(crc) = v.crc {
        c.eq(
            "CRC-16 of all but the last two bytes",
            rtu::crc16(&bytes[..body_len]),
            crc,
        );
    }
    if let Some(ok) = v.crc_ok {
        c.eq("rtu::crc_ok", rtu::crc_ok(&bytes), ok);
    }
    if let Some(len) = v.adu_len {
        c.eq("tcp::adu_len of 5 bytes", tcp::adu_len(&bytes[..5]), None);
        c.eq(
            "tcp::adu_len of 6 bytes",
            tcp::adu_len(&bytes[..6]),
            Some(len),
        );
    }
    if v.check_adu == Some(true) {
        // rtu::decode_adu agrees: the same error for a broken ADU, else the address/PDU/CRC split.
        match rtu::decode_adu(&bytes) {
            Err(e) => c.eq(
                "rtu::decode_adu error",
                Some(error_table(&e)),
                v.error.clone().map(ErrorTable),
            ),
            Ok(adu) => {
                let tail = u16::from_le_bytes([bytes[body_len], bytes[body_len + 1]]);
                c.eq(
                    "rtu::decode_adu (address, PDU, CRC)",
                    (adu.address, adu.pdu.to_vec(), adu.crc),
                    (
                        v.address.unwrap_or(bytes[0]),
                        bytes[1..body_len].to_vec(),
                        v.crc.unwrap_or(tail),
                    ),
                );
            }
        }
    }
    match (decode(v.framing, dir, &bytes), &v.error) {
        (Err(e), Some(want)) => {
            c.eq("error", error_table(&e), ErrorTable(want.clone()));
            let text = e.to_string();
            for part in v.message.iter().flatten() {
                c.eq(
                    &format!("message {text:?} contains {part:?}"),
                    text.contains(part.as_str()),
                    true,
                );
            }
        }
        (Ok(d), Some(want)) => c.fail(format!(
            "decodes as {:?}, want error {:?}",
            d.pdu,
            ErrorTable(want.clone())
        )),
        (Err(e), None) => c.fail(format!("does not decode: {e}")),
        (Ok(d), None) => check_decoded(v, &bytes, &d, c),
    }
}

fn check_decoded(v: &Vector, bytes: &[u8], d: &Decoded, c: &mut Checks) {
    if v.ok == Some(true) {
        c.count += 1; // it decodes
    }
    if let Some(want) = &v.pdu {
        let got = match &d.pdu {
            Pdu::Request(r) => format!("{r:?}"),
            Pdu::Response(r) => format!("{r:?}"),
        };
        c.eq("decoded PDU", &got, want);
    }
    if let Some(want) = &v.fields {
        let want: Result<Vec<(String, FieldValue)>, String> = want
            .iter()
            .map(|(name, value)| field_value(value).map(|f| (name.clone(), f)))
            .collect();
        match want {
            Ok(want) => {
                let got: Vec<(String, FieldValue)> = describe(&d.pdu)
                    .into_iter()
                    .map(|f| (f.name.to_string(), f.value))
                    .collect();
                c.eq("describe() fields", got, want);
            }
            Err(e) => c.fail(format!("bad `fields`: {e}")),
        }
    }
    if let Some(want) = v.address {
        c.eq("RTU address", d.address, Some(want));
    }
    if let Some(m) = &v.mbap {
        let want = tcp::Mbap {
            transaction_id: m.transaction_id,
            protocol_id: m.protocol_id,
            length: m.length,
            unit_id: m.unit_id,
        };
        c.eq("MBAP header", d.mbap, Some(want));
    }
    if let Some(want) = v.function {
        let got = match &d.pdu {
            Pdu::Request(r) => r.function(),
            Pdu::Response(r) => r.function(),
        };
        c.eq("function()", got.0, want);
    }
    if let Some(want) = v.is_exception {
        match &d.pdu {
            Pdu::Response(r) => c.eq("is_exception()", r.is_exception(), want),
            Pdu::Request(_) => c.fail("`is_exception` is for responses".into()),
        }
    }
    if v.encodes_back == Some(true) {
        let again = match (d.address, d.mbap, &d.pdu) {
            (Some(address), _, pdu) => rtu::encode(address, pdu),
            (_, Some(h), pdu) => tcp::encode(h.transaction_id, h.unit_id, pdu),
            (None, None, Pdu::Request(r)) => r.to_bytes(),
            (None, None, Pdu::Response(r)) => r.to_bytes(),
        };
        c.eq("encoded again", again, Ok(bytes.to_vec()));
    }
}

fn check_mnemonic(m: &MnemonicRow, c: &mut Checks) {
    let got = Mnemonic::from_name(&m.name);
    if !m.valid {
        return c.eq("from_name", got, None);
    }
    if let Some(wire) = &m.wire {
        match hex_bytes(wire).map(<[u8; 4]>::try_from) {
            Ok(Ok(wire)) => {
                c.eq("from_name", got, Some(Mnemonic(wire)));
                c.eq(
                    "name() of the wire form",
                    Mnemonic(wire).name(),
                    m.name.clone(),
                );
            }
            _ => return c.fail(format!("wire {wire:?}: four bytes of hex")),
        }
    }
    match got {
        Some(got) => {
            c.eq("name()", got.name(), m.name.clone());
            c.eq("to_string()", got.to_string(), m.name.clone());
        }
        None => c.fail("from_name gives None".into()),
    }
}

fn near(c: &mut Checks, what: &str, got: Duration, micros: u64, tolerance_us: u64) {
    let lo = Duration::from_micros(micros - tolerance_us);
    let hi = Duration::from_micros(micros + tolerance_us);
    c.count += 1;
    if !(lo <= got && got <= hi) {
        c.failures.push(format!(
            "{what}: {got:?} not within {micros} ± {tolerance_us} µs"
        ));
    }
}

fn check_timing(t: &TimingRow, c: &mut Checks) {
    let timing = RtuTiming::new(t.baud, char_format(&t.parity, t.stop_bits));
    let tol = t.tolerance_us;
    near(c, "t3.5", timing.t3_5, t.t3_5_us, tol);
    near(c, "t1.5", timing.t1_5, t.t1_5_us, tol);
    if let Some(us) = t.char_time_us {
        near(c, "character time", timing.char_time, us, tol);
    }
    if let Some(us) = t.transmit_8_bytes_us {
        near(
            c,
            "transmit time of 8 bytes",
            timing.transmit_time(8),
            us,
            tol,
        );
    }
}

fn check_hex_input(h: &HexInputRow, c: &mut Checks) {
    let got = parse_hex(&h.text);
    match (&h.bytes, h.valid) {
        (Some(want), true) => c.eq("parse_hex", got.as_ref().ok(), Some(want)),
        (None, false) => c.eq("parse_hex is an error", got.is_err(), true),
        _ => c.fail("give `bytes`, or `valid = false`".into()),
    }
}
