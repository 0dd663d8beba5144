//! Golden frames from the manuals (corpus/golden/*.toml): loading, and checking each printed and corrected frame.
//!
//! The check of a frame is what makes an erratum testable: the corrected bytes must decode strictly and match
//! `expect`; the printed bytes of an erratum must not (else the erratum claims a fault that is not there).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Deserialize;

pub use crate::profile::WordOrder;

use codec::{
    DecodeError, Decoded, FieldValue, Framing, decode_any, describe, parse_hex, pdu::Direction,
};

/// One manual's golden frames.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GoldenFile {
    pub manual: String,
    pub title: String,
    pub profile: String,
    #[serde(rename = "frame", default)]
    pub frames: Vec<GoldenFrame>,
}

/// One printed example frame.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GoldenFrame {
    pub id: String,
    pub section: String,
    pub line: u32,
    pub form: Form,
    pub direction: GoldenDirection,
    pub request: Option<String>,
    pub printed: Option<String>,
    pub printed_text: Option<String>,
    pub meaning: String,
    pub corrected: Option<String>,
    pub erratum: Option<String>,
    pub evidence: Option<String>,
    pub alternative: Option<String>,
    pub adopted: Option<String>,
    pub note: Option<String>,
    #[serde(default)]
    pub expect: Expect,
}

/// How the manual prints a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Form {
    Rtu,
    Tcp,
    Pdu,
}

impl Form {
    /// The codec framing of this form.
    pub fn framing(self) -> Framing {
        match self {
            Form::Rtu => Framing::Rtu,
            Form::Tcp => Framing::Tcp,
            Form::Pdu => Framing::Pdu,
        }
    }
}

/// Request or response.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GoldenDirection {
    Request,
    Response,
}

impl From<GoldenDirection> for Direction {
    fn from(d: GoldenDirection) -> Self {
        match d {
            GoldenDirection::Request => Direction::Request,
            GoldenDirection::Response => Direction::Response,
        }
    }
}

/// What a frame must decode to; every key optional.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Expect {
    pub unit: Option<u8>,
    pub function: Option<u8>,
    pub exception: Option<u8>,
    pub address: Option<u16>,
    pub quantity: Option<u16>,
    pub byte_count: Option<u16>,
    pub values: Option<Vec<u16>>,
    pub bits: Option<Vec<u8>>,
    pub value32: Option<i64>,
    pub sub_function: Option<u16>,
    pub data: Option<u16>,
    pub mei: Option<u8>,
    pub control: Option<u8>,
    pub node_id: Option<u8>,
    pub index: Option<u16>,
    pub subindex: Option<u8>,
    pub object_data: Option<String>,
    pub object_value: Option<u32>,
    pub sdo_error: Option<u32>,
    pub read_code: Option<u8>,
    pub object_id: Option<u8>,
    pub objects: Option<BTreeMap<String, String>>,
    pub mnemonic: Option<String>,
    pub params: Option<String>,
}

/// Why loading a golden file failed.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Parse { path: String, message: String },
}

impl GoldenFile {
    /// Parse a golden file's text; `name` is used in errors.
    pub fn parse(name: &str, text: &str) -> Result<Self, LoadError> {
        toml::from_str(text).map_err(|e| LoadError::Parse {
            path: name.to_string(),
            message: crate::profile::toml_error_message(text, &e),
        })
    }

    /// Load a golden file from disk.
    pub fn load(path: &Path) -> Result<Self, LoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| LoadError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&path.display().to_string(), &text)
    }
}

/// The outcome of checking one frame.
#[derive(Debug)]
pub struct FrameCheck {
    pub id: String,
    /// The bytes the project uses (corrected if given, else printed).
    pub bytes: Vec<u8>,
    /// Strict decode of those bytes.
    pub decoded: Result<Decoded, DecodeError>,
    /// Expectations the used bytes do not meet.
    pub mismatches: Vec<String>,
    /// For errata with printed bytes: what is wrong with the printed bytes (empty means the erratum is vacuous).
    pub printed_faults: Option<Vec<String>>,
    /// Problems with the entry itself (bad hex, missing bytes).
    pub entry_errors: Vec<String>,
}

impl FrameCheck {
    /// True when the entry is consistent: used bytes decode and match, and every erratum is real.
    pub fn ok(&self) -> bool {
        self.entry_errors.is_empty()
            && self.decoded.is_ok()
            && self.mismatches.is_empty()
            && self.printed_faults.as_ref().is_none_or(|f| !f.is_empty())
    }
}

fn field_map(d: &Decoded) -> BTreeMap<&'static str, FieldValue> {
    let mut m: BTreeMap<&'static str, FieldValue> = describe(&d.pdu)
        .into_iter()
        .map(|f| (f.name, f.value))
        .collect();
    if let Some(u) = d.unit {
        m.insert("unit", FieldValue::Int(u.into()));
    }
    m
}

/// Every expectation `d` fails, as readable sentences.
pub fn mismatches(exp: &Expect, d: &Decoded, order: WordOrder) -> Vec<String> {
    let m = field_map(d);
    let mut out = Vec::new();
    let mut int = |key: &'static str, want: Option<u64>| {
        if let Some(w) = want {
            match m.get(key) {
                Some(FieldValue::Int(v)) if *v == w => {}
                Some(v) => out.push(format!("{key}: expected {w} (0x{w:X}), decoded {v}")),
                None => out.push(format!(
                    "{key}: expected {w} (0x{w:X}), the frame has no such field"
                )),
            }
        }
    };
    int("unit", exp.unit.map(u64::from));
    int("function", exp.function.map(u64::from));
    int("exception", exp.exception.map(u64::from));
    int("address", exp.address.map(u64::from));
    int("quantity", exp.quantity.map(u64::from));
    int("byte_count", exp.byte_count.map(u64::from));
    int("sub_function", exp.sub_function.map(u64::from));
    int("data", exp.data.map(u64::from));
    int("mei", exp.mei.map(u64::from));
    int("control", exp.control.map(u64::from));
    int("node_id", exp.node_id.map(u64::from));
    int("index", exp.index.map(u64::from));
    int("subindex", exp.subindex.map(u64::from));
    int("object_value", exp.object_value.map(u64::from));
    int("sdo_error", exp.sdo_error.map(u64::from));
    int("read_code", exp.read_code.map(u64::from));
    int("object_id", exp.object_id.map(u64::from));
    let regs = match m.get("values") {
        Some(FieldValue::Ints(v)) => Some(v.clone()),
        _ => None,
    };
    if let Some(want) = &exp.values {
        let want: Vec<u64> = want.iter().map(|x| *x as u64).collect();
        if regs.as_ref() != Some(&want) {
            out.push(format!("values: expected {want:?}, decoded {regs:?}"));
        }
    }
    if let Some(want) = exp.value32 {
        let got = regs
            .as_ref()
            .filter(|r| r.len() >= 2)
            .map(|r| order.join(r[0] as u16, r[1] as u16));
        let want32 = want as u32;
        if got != Some(want32) {
            out.push(format!(
                "value32: expected {want} (0x{want32:08X}), decoded {:?}",
                got.map(|g| format!("{g} (0x{g:08X})"))
            ));
        }
    }
    if let Some(want) = &exp.bits {
        let got = match m.get("bits") {
            Some(FieldValue::Ints(v)) => v.clone(),
            _ => Vec::new(),
        };
        let want: Vec<u64> = want.iter().map(|x| *x as u64).collect();
        if got.len() < want.len() || got[..want.len()] != want[..] {
            out.push(format!(
                "bits: expected {want:?} from the first address, decoded {got:?}"
            ));
        }
    }
    if let Some(want) = &exp.object_data {
        match (parse_hex(want), m.get("object_data")) {
            (Ok(w), Some(FieldValue::Bytes(g))) if &w == g => {}
            (Ok(_), g) => out.push(format!("object_data: expected {want}, decoded {g:?}")),
            (Err(e), _) => out.push(format!("object_data: expectation is not hex: {e}")),
        }
    }
    for (key, want) in [("mnemonic", &exp.mnemonic), ("params", &exp.params)] {
        if let Some(w) = want {
            match m.get(key) {
                Some(FieldValue::Text(g)) if g == w => {}
                g => out.push(format!("{key}: expected {w:?}, decoded {g:?}")),
            }
        }
    }
    if let Some(want) = &exp.objects {
        let got: BTreeMap<String, String> = match m.get("objects") {
            Some(FieldValue::Objects(o)) => {
                o.iter().map(|(i, v)| (i.to_string(), v.clone())).collect()
            }
            _ => BTreeMap::new(),
        };
        if &got != want {
            out.push(format!("objects: expected {want:?}, decoded {got:?}"));
        }
    }
    out
}

fn faults_of(bytes: &[u8], frame: &GoldenFrame, order: WordOrder) -> Vec<String> {
    match decode_any(bytes, frame.form.framing(), frame.direction.into()) {
        Err(e) => vec![format!("does not decode: {e}")],
        Ok(d) => mismatches(&frame.expect, &d, order),
    }
}

/// Check one frame: the used bytes decode and match; an erratum's printed bytes are shown to be wrong.
pub fn check_frame(frame: &GoldenFrame, order: WordOrder) -> FrameCheck {
    let mut entry_errors = Vec::new();
    let hex_of = |s: &Option<String>, what: &str, errs: &mut Vec<String>| {
        s.as_ref().and_then(|h| match parse_hex(h) {
            Ok(b) => Some(b),
            Err(e) => {
                errs.push(format!("{what} is not hex: {e}"));
                None
            }
        })
    };
    let printed = hex_of(&frame.printed, "printed", &mut entry_errors);
    let corrected = hex_of(&frame.corrected, "corrected", &mut entry_errors);
    if frame.printed.is_none() && frame.printed_text.is_none() {
        entry_errors.push("neither `printed` nor `printed_text`".into());
    }
    if frame.printed.is_none() && frame.corrected.is_none() {
        entry_errors.push("a template (`printed_text`) needs `corrected` bytes".into());
    }
    // A template (`printed_text`) instantiated as `corrected` bytes is not an erratum; changed bytes are.
    if frame.printed.is_some() && frame.corrected.is_some() && frame.erratum.is_none() {
        entry_errors.push("`corrected` bytes differ from `printed` without an `erratum`".into());
    }
    if frame.erratum.is_some() && frame.evidence.is_none() {
        entry_errors.push("`erratum` without `evidence`".into());
    }
    if frame.alternative.is_some() != frame.adopted.is_some() {
        entry_errors.push("`alternative` and `adopted` go together".into());
    }
    let bytes = corrected.clone().or(printed.clone()).unwrap_or_default();
    let decoded = decode_any(&bytes, frame.form.framing(), frame.direction.into());
    let mismatches = match &decoded {
        Ok(d) => mismatches(&frame.expect, d, order),
        Err(_) => Vec::new(),
    };
    let printed_faults = match (&printed, &corrected) {
        (Some(p), Some(c)) if p != c => Some(faults_of(p, frame, order)),
        _ => None,
    };
    FrameCheck {
        id: frame.id.clone(),
        bytes,
        decoded,
        mismatches,
        printed_faults,
        entry_errors,
    }
}

/// The errata index of golden files (a corpus's: [`crate::corpus::Corpus::golden_files`]) as Markdown:
/// every frame whose printed bytes the project corrects or reads one of two ways, per manual, with the
/// evidence. corpus/golden/README.md is this text.
pub fn errata_markdown(golden: &[GoldenFile]) -> String {
    use std::fmt::Write;
    let mut md = String::from(
        "# Golden frames and the errata of the manuals\n\n\
         Generated by `modbus-harness golden --markdown > corpus/golden/README.md` from the golden files; a test\n\
         fails when this file is out of date. Every frame printed in the three manuals is an entry of\n\
         `mdrive.toml`, `lmd.toml` or `sd2x.toml` (schema: `SCHEMA.md`). Where a printed frame is wrong, the entry\n\
         keeps the printed bytes, the corrected bytes and the evidence; `modbus-harness golden` checks that the\n\
         corrected bytes decode to what the manual means and that the printed bytes do not. Errata in the prose,\n\
         tables and register maps (not only in frames) are in `ERRATA-mdrive.md`, `ERRATA-lmd.md` and\n\
         `ERRATA-sd2x.md`, with line numbers. Check any frame yourself with `modbus-harness decode --rtu|--pdu HEX`.\n\n",
    );
    for g in golden {
        let errata: Vec<&GoldenFrame> = g
            .frames
            .iter()
            .filter(|f| f.erratum.is_some() || f.alternative.is_some())
            .collect();
        let _ = writeln!(
            md,
            "## {}\n\nManual `{}`: {} printed frames, {} with an erratum or two readings.\n",
            g.title,
            g.manual,
            g.frames.len(),
            errata.len()
        );
        let _ = writeln!(
            md,
            "| frame | line | printed | used | what is wrong | evidence |\n|---|---|---|---|---|---|"
        );
        let cell = |s: &str| s.replace('|', "\\|").replace('\n', " ");
        for f in errata {
            let printed = f.printed.clone().unwrap_or_else(|| "(template)".into());
            let used = f.corrected.clone().unwrap_or_else(|| printed.clone());
            let what = match (&f.erratum, &f.alternative, &f.adopted) {
                (Some(e), Some(a), Some(ad)) => format!("{e} Other reading: `{a}`. Adopted: {ad}"),
                (Some(e), _, _) => e.clone(),
                (None, Some(a), Some(ad)) => format!("Two readings; other: `{a}`. Adopted: {ad}"),
                _ => String::new(),
            };
            let _ = writeln!(
                md,
                "| `{}` | {} | `{}` | `{}` | {} | {} |",
                f.id,
                f.line,
                cell(&printed),
                cell(&used),
                cell(&what),
                cell(f.evidence.as_deref().unwrap_or(""))
            );
        }
        md.push('\n');
    }
    md
}
