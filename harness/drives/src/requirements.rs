//! Requirements, freedoms and the citation map: what the specifications and the manuals require
//! (`corpus/requirements/{app,tcp,serial,mdrive,lmd,sd2x}.toml`), where they leave a device a choice
//! (`corpus/freedoms/*.toml`), and which of both each catalog case checks (`corpus/requirements/cases.toml`).
//! The schema, the freedom kinds and how an oracle applies each: `corpus/requirements/README.md`.
//!
//! Loading validates: unknown keys, duplicate ids, unknown documents, requirements, freedoms, profiles and
//! golden frames, unknown freedom kinds, values that a kind does not allow, empty value lists, bad levels and
//! line ranges are rejected with the file, the line and the reason.

use std::collections::{BTreeMap, BTreeSet};

use serde::Deserialize;
use toml::Spanned;

use crate::corpus::Corpus;
use crate::profile::{LineIndex, line_of};
use codec::{FunctionCode, Mnemonic, Request};

/// Why the requirements could not be had from a corpus.
#[derive(Debug, thiserror::Error)]
pub enum RequirementsError {
    #[error("reading the {corpus}: {source}")]
    Read {
        corpus: String,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {reason}")]
    Invalid {
        path: String,
        line: usize,
        reason: String,
    },
}

/// Where an entry was read from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Origin {
    /// The file, as the corpus names it.
    pub file: String,
    /// 1-based line of the entry in that file.
    pub line: usize,
}

/// A specification or a manual.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Document {
    pub id: String,
    pub title: String,
    pub kind: DocKind,
    /// Manuals: the seed file under shared/seeds/ whose line numbers the entries cite.
    pub seed: Option<String>,
    /// How entries cite the document: "section" (specifications) or "line" (manuals).
    pub cite: Option<String>,
    /// Manuals: the line-number convention.
    pub lines: Option<String>,
    /// Specifications: publisher and date.
    pub published: Option<String>,
    /// Manuals: the profiles the manual documents.
    #[serde(default)]
    pub profiles: Vec<String>,
    pub note: Option<String>,
    #[serde(skip)]
    pub origin: Origin,
}

/// A published specification (cited by section) or a vendor manual (cited by line of its seed file).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DocKind {
    Spec,
    Manual,
}

/// How binding a requirement is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    Must,
    Should,
    May,
}

/// One requirement of a document.
#[derive(Clone, Debug)]
pub struct Requirement {
    /// Stable id: `<document>/<section>/<name>`.
    pub id: String,
    /// The document's id.
    pub document: String,
    pub section: String,
    /// Manuals: first line of the quoted text in the seed file.
    pub line: Option<u32>,
    /// Manuals: last line, when the text spans several.
    pub last_line: Option<u32>,
    pub level: Level,
    /// The requirement as the document states it (`[...]` marks an omission).
    pub text: String,
    /// True when `text` is a close paraphrase (a figure, a table rendered), not a quotation.
    pub paraphrase: bool,
    pub note: Option<String>,
    pub origin: Origin,
}

/// Which oracle rule applies a freedom (README.md, "Freedom kinds").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FreedomKind {
    /// Admissible exception codes for a condition (`values`: codes).
    ExceptionCode,
    /// Admissible kinds of answer: `response`, `silence`, `close`, `exception-XX`, `sdo-error` (the SD2x's
    /// extended exception response to FC 43).
    Outcome,
    /// A response field read more than one way (`field`; `values`: numbers or named readings).
    FieldValue,
    /// Items (`items`) a product may lack; `values`: `present` first, then how a lacking product answers.
    Optional,
    /// Access the manual does not state (`items`); `values`: `ro`, `rw`, `wo`.
    Access,
    /// Masks of the status-word bits that are specified, from the reference's to the loosest (`values`).
    StatusBits,
    /// The order of the two registers of a 32-bit value: `high-first`, `low-first`.
    WordOrder,
    /// Equally supported readings of the manual (`golden`: the frames that carry the other reading).
    Reading,
    /// Which unit ids (`units`) get an answer: `answer`, `silence`, `exception-XX`.
    UnitIds,
    /// How pipelined responses are matched: `request-order`, `transaction-id`.
    PipelineOrder,
    /// A function code (`functions`) the profile does not list may be served: `exception-01`, `served`.
    ServedExtra,
    /// What the FC 08 diagnostic counters count (named readings).
    Counter,
    /// Admissible SDO abort codes for a condition (`values`: 32-bit codes).
    SdoError,
}

impl FreedomKind {
    /// The kebab-case name used in the files.
    pub fn name(self) -> &'static str {
        match self {
            FreedomKind::ExceptionCode => "exception-code",
            FreedomKind::Outcome => "outcome",
            FreedomKind::FieldValue => "field-value",
            FreedomKind::Optional => "optional",
            FreedomKind::Access => "access",
            FreedomKind::StatusBits => "status-bits",
            FreedomKind::WordOrder => "word-order",
            FreedomKind::Reading => "reading",
            FreedomKind::UnitIds => "unit-ids",
            FreedomKind::PipelineOrder => "pipeline-order",
            FreedomKind::ServedExtra => "served-extra",
            FreedomKind::Counter => "counter",
            FreedomKind::SdoError => "sdo-error",
        }
    }
}

/// One admissible value of a freedom: a number (exception code, SDO code, mask, field value) or a name.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(untagged)]
pub enum FreedomValue {
    Int(i64),
    Text(String),
}

impl FreedomValue {
    /// True when this is the value a user wrote (`4`, `0x04`, `04`, `exception-02`, a name).
    pub fn matches(&self, written: &str) -> bool {
        match self {
            FreedomValue::Int(i) => parse_int(written) == Some(*i),
            FreedomValue::Text(t) => t.eq_ignore_ascii_case(written),
        }
    }
}

fn parse_int(s: &str) -> Option<i64> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => i64::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

impl std::fmt::Display for FreedomValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FreedomValue::Int(i) if *i > 0xFF => write!(f, "0x{i:X}"),
            FreedomValue::Int(i) => write!(f, "{i}"),
            FreedomValue::Text(t) => f.write_str(t),
        }
    }
}

/// A register, mnemonic or object a freedom is about.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Item {
    pub register: Option<u16>,
    /// A coil (FC 01/05/0F), by address.
    pub coil: Option<u16>,
    pub mnemonic: Option<String>,
    pub object: Option<u16>,
    /// The item's name (a register's mnemonic).
    pub name: Option<String>,
    /// Line of the item in the manual of the freedom's profile.
    pub line: Option<u32>,
}

impl Item {
    /// True when the request reads or writes the item (a register by every address it occupies in the
    /// profile, a coil by FC 01/05/0F covering it, a mnemonic by name, an object by index).
    pub fn touched_by(&self, req: &Request, profile: &crate::profile::Profile) -> bool {
        let item = self;
        if let Some(c) = item.coil {
            return coils_touched(req).is_some_and(|(a, q)| covers(a, q, c));
        }
        if let Some(r) = item.register {
            let (read, written) = (registers_read(req), registers_written(req));
            // Whatever the width (at most 255 registers), a request that ends before `r` or starts past
            // `r + 255` cannot touch it: the profile lookup below is skipped (it is on the hot path of every
            // judgement and of every answer of a drive with optional items).
            let near = |(a, q): (u16, u16)| {
                let (a, q, r) = (u32::from(a), u32::from(q), u32::from(r));
                a < r + 256 && a + q > r
            };
            if !read.is_some_and(near) && !written.is_some_and(near) {
                return false;
            }
            let width = register_width(profile, r);
            let hit = |(a, q): (u16, u16)| (0..width).any(|i| covers(a, q, r.wrapping_add(i)));
            return read.is_some_and(hit) || written.is_some_and(hit);
        }
        if let Some(m) = &item.mnemonic {
            let name = |mn: &Mnemonic| mn.name().eq_ignore_ascii_case(m);
            return match req {
                Request::VendorRead { mnemonic } | Request::VendorWrite { mnemonic, .. } => {
                    name(mnemonic)
                }
                _ => false,
            };
        }
        if let Some(o) = item.object {
            return matches!(req, Request::CanOpen(a) if a.index == o);
        }
        false
    }

    /// True when every register `req` reads or writes is one of this item's (an item that is no register,
    /// a mnemonic or an object, is all a request about it touches): a refusal of the request then has no
    /// other address to be about.
    pub fn covers_all_of(&self, req: &Request, profile: &crate::profile::Profile) -> bool {
        if let Some(c) = self.coil {
            return registers_read(req).is_none()
                && registers_written(req).is_none()
                && coils_touched(req).is_none_or(|(a, q)| a == c && q == 1);
        }
        let Some(r) = self.register else {
            return true;
        };
        if coils_touched(req).is_some() {
            return false;
        }
        let width = register_width(profile, r);
        let inside = |(a, q): (u16, u16)| {
            let (a, q, r) = (u32::from(a), u32::from(q), u32::from(r));
            a >= r && a + q <= r + u32::from(width)
        };
        registers_read(req).is_none_or(inside) && registers_written(req).is_none_or(inside)
    }
}

/// The width in registers of the register the profile has at `r` (1 where it has none starting there).
fn register_width(profile: &crate::profile::Profile, r: u16) -> u16 {
    profile
        .register_at(r, false)
        .or_else(|| profile.register_at(r, true))
        .filter(|reg| reg.address == r)
        .map_or(1, |reg| u16::from(reg.width))
}

/// The (address, quantity) of coils a request reads or writes (FC 01, 05, 0F).
pub fn coils_touched(req: &Request) -> Option<(u16, u16)> {
    match req {
        Request::ReadCoils { address, quantity } => Some((*address, *quantity)),
        Request::WriteSingleCoil { address, .. } => Some((*address, 1)),
        Request::WriteMultipleCoils {
            address, quantity, ..
        } => Some((*address, *quantity)),
        _ => None,
    }
}

/// The function and the quantity a read (FC 01-04) or a multiple write (FC 0F, 10) asks for: the items read or
/// written (an FC 10's values counted). `None` for any other request.
pub fn quantity_asked(req: &Request) -> Option<(FunctionCode, usize)> {
    use Request::*;
    match req {
        ReadCoils { quantity, .. }
        | ReadDiscreteInputs { quantity, .. }
        | ReadHoldingRegisters { quantity, .. }
        | ReadInputRegisters { quantity, .. }
        | WriteMultipleCoils { quantity, .. } => Some((req.function(), usize::from(*quantity))),
        WriteMultipleRegisters { values, .. } => {
            Some((FunctionCode::WRITE_MULTIPLE_REGISTERS, values.len()))
        }
        _ => None,
    }
}

/// The (address, quantity) a request reads, for register reads.
pub fn registers_read(req: &Request) -> Option<(u16, u16)> {
    match req {
        Request::ReadHoldingRegisters { address, quantity }
        | Request::ReadInputRegisters { address, quantity } => Some((*address, *quantity)),
        Request::ReadWriteMultipleRegisters {
            read_address,
            read_quantity,
            ..
        } => Some((*read_address, *read_quantity)),
        _ => None,
    }
}

/// The (address, quantity) a request writes, for register writes.
pub fn registers_written(req: &Request) -> Option<(u16, u16)> {
    match req {
        Request::WriteSingleRegister { address, .. } => Some((*address, 1)),
        Request::WriteMultipleRegisters { address, values } => {
            Some((*address, u16::try_from(values.len()).unwrap_or(u16::MAX)))
        }
        Request::ReadWriteMultipleRegisters {
            write_address,
            values,
            ..
        } => Some((
            *write_address,
            u16::try_from(values.len()).unwrap_or(u16::MAX),
        )),
        _ => None,
    }
}

/// True when the range `address`, `quantity` covers `register`.
pub fn covers(address: u16, quantity: u16, register: u16) -> bool {
    u32::from(address) <= u32::from(register)
        && u32::from(register) < u32::from(address) + u32::from(quantity)
}

/// The text of a document that leaves the choice open.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Source {
    pub doc: String,
    pub section: Option<String>,
    pub line: Option<u32>,
    pub last_line: Option<u32>,
    pub text: String,
    #[serde(default)]
    pub paraphrase: bool,
    pub note: Option<String>,
}

/// A choice a specification or manual leaves to the device.
#[derive(Clone, Debug)]
pub struct Freedom {
    pub id: String,
    pub title: String,
    pub kind: FreedomKind,
    /// Profiles it applies to; `["all"]` for every profile.
    pub profiles: Vec<String>,
    /// The admissible values; the first is what the reference drive models do today.
    pub values: Vec<FreedomValue>,
    /// When it applies, in words.
    pub condition: Option<String>,
    pub items: Vec<Item>,
    /// Golden frame ids whose `alternative` carries another reading.
    pub golden: Vec<String>,
    /// `unit-ids`: the unit ids concerned, an inclusive range `[first, last]` (see [`Freedom::covers_unit`]).
    pub units: Vec<u8>,
    /// `served-extra`: the function codes concerned.
    pub functions: Vec<u8>,
    /// `field-value`: the field read more than one way.
    pub field: Option<String>,
    /// The register concerned (status words, error codes).
    pub register: Option<u16>,
    pub sources: Vec<Source>,
    pub note: Option<String>,
    pub origin: Origin,
}

impl Freedom {
    /// True when `value` is one of the admissible values (see [`FreedomValue::matches`]).
    pub fn admits(&self, value: &str) -> bool {
        self.values.iter().any(|v| v.matches(value))
    }

    /// `unit-ids`: true when `unit` is in the freedom's range of unit ids (`units = [first, last]`).
    pub fn covers_unit(&self, unit: u8) -> bool {
        match self.units.as_slice() {
            [first, last] => (*first..=*last).contains(&unit),
            _ => false,
        }
    }

    /// True when the freedom applies to runs against `profile`.
    pub fn applies_to(&self, profile: &str) -> bool {
        self.profiles.iter().any(|p| p == "all" || p == profile)
    }
}

/// One entry of the citation map.
#[derive(Clone, Debug)]
pub struct Cite {
    /// Glob over case ids (`*` matches any characters, `/` included).
    pub cases: String,
    pattern: glob::Pattern,
    /// The pattern's text before its first wildcard (`*`, `?`, `[`): a case id that does not start with it
    /// cannot match, and that is asked first (a run asks every entry for every case).
    literal: String,
    /// Profiles the entry is limited to; empty for every profile.
    pub profiles: Vec<String>,
    pub requirements: Vec<String>,
    pub freedoms: Vec<String>,
    pub note: Option<String>,
    pub origin: Origin,
}

impl Cite {
    /// True when the entry applies to `case_id` in a run against `profile`.
    pub fn matches(&self, case_id: &str, profile: &str) -> bool {
        case_id.starts_with(&self.literal)
            && (self.profiles.is_empty() || self.profiles.iter().any(|p| p == profile))
            && self.pattern.matches(case_id)
    }
}

/// Requirements exercised against requirements listed, for one document.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Coverage {
    pub document: String,
    pub title: String,
    /// Requirements of the document.
    pub listed: usize,
    /// Of those, the ones in the cited set.
    pub exercised: usize,
    /// Ids listed but not exercised.
    pub missing: Vec<String>,
}

/// What kind of corpus file a text is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// `requirements/<document>.toml`: a `[document]` and its `[[requirement]]`s.
    Requirements,
    /// `freedoms/*.toml`: `[[freedom]]`s.
    Freedoms,
    /// `requirements/cases.toml`: `[[cite]]`s.
    Cites,
}

/// All requirements, freedoms and citations of a corpus, validated.
#[derive(Clone, Debug, Default)]
pub struct Requirements {
    documents: Vec<Document>,
    requirements: Vec<Requirement>,
    freedoms: Vec<Freedom>,
    cites: Vec<Cite>,
    by_requirement: BTreeMap<String, usize>,
    by_freedom: BTreeMap<String, usize>,
}

// ---- the files as written -------------------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RequirementFile {
    document: Spanned<Document>,
    #[serde(default, rename = "requirement")]
    requirements: Vec<Spanned<RawRequirement>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRequirement {
    id: Spanned<String>,
    section: String,
    line: Option<Spanned<u32>>,
    last_line: Option<u32>,
    level: Level,
    text: String,
    #[serde(default)]
    paraphrase: bool,
    note: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FreedomFile {
    #[serde(default, rename = "freedom")]
    freedoms: Vec<Spanned<RawFreedom>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFreedom {
    id: Spanned<String>,
    title: String,
    kind: FreedomKind,
    profiles: Spanned<Vec<String>>,
    values: Spanned<Vec<FreedomValue>>,
    condition: Option<String>,
    items: Option<Spanned<Vec<Item>>>,
    golden: Option<Spanned<Vec<String>>>,
    #[serde(default)]
    units: Vec<u8>,
    #[serde(default)]
    functions: Vec<u8>,
    field: Option<String>,
    register: Option<u16>,
    #[serde(default)]
    sources: Vec<Spanned<Source>>,
    note: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CiteFile {
    #[serde(default, rename = "cite")]
    cites: Vec<Spanned<RawCite>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCite {
    cases: Spanned<String>,
    profiles: Option<Spanned<Vec<String>>>,
    requirements: Option<Spanned<Vec<String>>>,
    freedoms: Option<Spanned<Vec<String>>>,
    note: Option<String>,
}

/// What every corpus file is checked against besides the other files.
#[derive(Clone, Debug, Default)]
pub struct KnownIds {
    /// Profile ids (file stems of `profiles/*.toml`); a freedom or cite naming another is rejected.
    pub profiles: Vec<String>,
    /// Golden frame ids; `None` leaves freedoms' `golden` lists unchecked.
    pub golden_frames: Option<BTreeSet<String>>,
}

type Fail = (usize, String);

/// An optional spanned list: its start offset (`at` when absent) and its items.
fn list<T>(v: Option<Spanned<Vec<T>>>, at: usize) -> (usize, Vec<T>) {
    match v {
        Some(s) => (s.span().start, s.into_inner()),
        None => (at, Vec::new()),
    }
}

/// Outcome names: `exception-XX` with two hex digits.
fn is_exception_name(s: &str) -> bool {
    s.strip_prefix("exception-")
        .is_some_and(|h| h.len() == 2 && u8::from_str_radix(h, 16).is_ok())
}

impl Requirements {
    /// Load and validate the requirements, freedoms and citation map of `corpus`.
    pub fn load(corpus: &Corpus) -> Result<Self, RequirementsError> {
        let read = |sub: &str| {
            corpus.files(sub).map_err(|source| RequirementsError::Read {
                corpus: corpus.describe(),
                source,
            })
        };
        let mut files = Vec::new();
        for (name, text) in read("requirements")? {
            let stem = std::path::Path::new(name.trim_end_matches(" (embedded)"))
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned());
            let kind = if stem.as_deref() == Some("cases") {
                FileKind::Cites
            } else {
                FileKind::Requirements
            };
            files.push((kind, name, text));
        }
        for (name, text) in read("freedoms")? {
            files.push((FileKind::Freedoms, name, text));
        }
        let mut golden = BTreeSet::new();
        for p in corpus.profile_names() {
            if let Ok(Some(g)) = corpus.golden(&p) {
                golden.extend(g.frames.iter().map(|f| f.id.clone()));
            }
        }
        Self::parse(
            &files,
            &KnownIds {
                profiles: corpus.profile_names(),
                golden_frames: Some(golden),
            },
        )
    }

    /// Parse and validate files given as (kind, name for errors, text).
    pub fn parse(
        files: &[(FileKind, String, String)],
        known: &KnownIds,
    ) -> Result<Self, RequirementsError> {
        let mut out = Requirements::default();
        let mut doc_kinds: BTreeMap<String, (DocKind, Origin)> = BTreeMap::new();
        let mut raw_cites = Vec::new();
        let mut raw_freedoms = Vec::new();
        let invalid = |name: &str, text: &str, (offset, reason): Fail| RequirementsError::Invalid {
            path: name.to_string(),
            line: line_of(text, offset),
            reason,
        };
        let toml_err = |name: &str, text: &str, e: toml::de::Error| RequirementsError::Invalid {
            path: name.to_string(),
            line: e.span().map(|s| line_of(text, s.start)).unwrap_or(0),
            reason: e.message().to_string(),
        };
        // Documents and requirements first: freedoms and cites refer to them.
        for (kind, name, text) in files {
            match kind {
                FileKind::Requirements => {
                    let f: RequirementFile =
                        toml::from_str(text).map_err(|e| toml_err(name, text, e))?;
                    let doc_at = f.document.span().start;
                    let mut doc = f.document.into_inner();
                    doc.origin = Origin {
                        file: name.clone(),
                        line: line_of(text, doc_at),
                    };
                    out.add_document(doc, &mut doc_kinds, known)
                        .map_err(|r| invalid(name, text, (doc_at, r)))?;
                    let lines = LineIndex::new(text);
                    let doc_id = out
                        .documents
                        .last()
                        .map(|d| d.id.clone())
                        .unwrap_or_default();
                    let doc_kind = out.documents.last().map(|d| d.kind);
                    for r in f.requirements {
                        let at = r.span().start;
                        out.add_requirement(r.into_inner(), &doc_id, doc_kind, name, &lines, at)
                            .map_err(|e| invalid(name, text, e))?;
                    }
                }
                FileKind::Freedoms => raw_freedoms.push((name, text)),
                FileKind::Cites => raw_cites.push((name, text)),
            }
        }
        for (name, text) in raw_freedoms {
            let f: FreedomFile = toml::from_str(text).map_err(|e| toml_err(name, text, e))?;
            let lines = LineIndex::new(text);
            for fr in f.freedoms {
                let at = fr.span().start;
                out.add_freedom(fr.into_inner(), &doc_kinds, known, name, &lines, at)
                    .map_err(|e| invalid(name, text, e))?;
            }
        }
        for (name, text) in raw_cites {
            let f: CiteFile = toml::from_str(text).map_err(|e| toml_err(name, text, e))?;
            let lines = LineIndex::new(text);
            for c in f.cites {
                let at = c.span().start;
                out.add_cite(c.into_inner(), known, name, &lines, at)
                    .map_err(|e| invalid(name, text, e))?;
            }
        }
        Ok(out)
    }

    fn add_document(
        &mut self,
        doc: Document,
        kinds: &mut BTreeMap<String, (DocKind, Origin)>,
        known: &KnownIds,
    ) -> Result<(), String> {
        if !is_id(&doc.id) || doc.id.contains('/') {
            return Err(format!(
                "document id `{}`: lowercase letters, digits and dashes only",
                doc.id
            ));
        }
        if let Some((_, o)) = kinds.get(&doc.id) {
            return Err(format!(
                "document `{}` is already defined in {}:{}",
                doc.id, o.file, o.line
            ));
        }
        if doc.kind == DocKind::Manual && doc.seed.is_none() {
            return Err(format!(
                "document `{}`: a manual names its `seed` file (the line numbers are its lines)",
                doc.id
            ));
        }
        check_profiles(&doc.profiles, known, false)?;
        kinds.insert(doc.id.clone(), (doc.kind, doc.origin.clone()));
        self.documents.push(doc);
        Ok(())
    }

    fn add_requirement(
        &mut self,
        r: RawRequirement,
        doc: &str,
        doc_kind: Option<DocKind>,
        file: &str,
        lines: &LineIndex,
        at: usize,
    ) -> Result<(), Fail> {
        let id_at = r.id.span().start;
        let id = r.id.into_inner();
        if !is_id(&id) || !id.starts_with(&format!("{doc}/")) {
            return Err((
                id_at,
                format!(
                    "requirement id `{id}`: must start with `{doc}/` and use lowercase letters, digits, '.', '-', '/' (hex digits may be upper case)"
                ),
            ));
        }
        if let Some(&i) = self.by_requirement.get(&id) {
            let o = &self.requirements[i].origin;
            return Err((
                id_at,
                format!(
                    "requirement `{id}` is already defined in {}:{}",
                    o.file, o.line
                ),
            ));
        }
        if r.text.trim().is_empty() {
            return Err((at, format!("requirement `{id}`: empty text")));
        }
        let line = r.line.as_ref().map(|l| *l.get_ref());
        check_lines(line, r.last_line).map_err(|m| {
            (
                r.line.as_ref().map_or(at, |l| l.span().start),
                format!("requirement `{id}`: {m}"),
            )
        })?;
        if doc_kind == Some(DocKind::Manual) && line.is_none() {
            return Err((
                at,
                format!("requirement `{id}`: a manual's requirement cites its `line`"),
            ));
        }
        self.by_requirement
            .insert(id.clone(), self.requirements.len());
        self.requirements.push(Requirement {
            id,
            document: doc.to_string(),
            section: r.section,
            line,
            last_line: r.last_line,
            level: r.level,
            text: r.text,
            paraphrase: r.paraphrase,
            note: r.note,
            origin: Origin {
                file: file.to_string(),
                line: lines.line(at),
            },
        });
        Ok(())
    }

    fn add_freedom(
        &mut self,
        f: RawFreedom,
        docs: &BTreeMap<String, (DocKind, Origin)>,
        known: &KnownIds,
        file: &str,
        lines: &LineIndex,
        at: usize,
    ) -> Result<(), Fail> {
        let id_at = f.id.span().start;
        let id = f.id.into_inner();
        if !is_id(&id) || id.contains('/') {
            return Err((
                id_at,
                format!("freedom id `{id}`: lowercase letters, digits and dashes only"),
            ));
        }
        if let Some(&i) = self.by_freedom.get(&id) {
            let o = &self.freedoms[i].origin;
            return Err((
                id_at,
                format!("freedom `{id}` is already defined in {}:{}", o.file, o.line),
            ));
        }
        let profiles_at = f.profiles.span().start;
        let profiles = f.profiles.into_inner();
        if profiles.is_empty() {
            return Err((
                profiles_at,
                format!("freedom `{id}`: `profiles` is empty (use [\"all\"])"),
            ));
        }
        check_profiles(&profiles, known, true)
            .map_err(|m| (profiles_at, format!("freedom `{id}`: {m}")))?;
        let values_at = f.values.span().start;
        let values = f.values.into_inner();
        check_values(f.kind, &values).map_err(|m| {
            (
                values_at,
                format!("freedom `{id}` ({}): {m}", f.kind.name()),
            )
        })?;
        let (items_at, items) = list(f.items, at);
        let needs = |ok: bool, what: &str| -> Result<(), Fail> {
            if ok {
                Ok(())
            } else {
                Err((
                    at,
                    format!("freedom `{id}` ({}): needs {what}", f.kind.name()),
                ))
            }
        };
        match f.kind {
            FreedomKind::Optional | FreedomKind::Access => needs(!items.is_empty(), "`items`")?,
            FreedomKind::UnitIds => needs(
                matches!(f.units.as_slice(), [first, last] if first <= last),
                "`units` = [first, last], an inclusive range",
            )?,
            FreedomKind::ServedExtra => needs(!f.functions.is_empty(), "`functions`")?,
            FreedomKind::FieldValue => needs(f.field.is_some(), "`field`")?,
            _ => {}
        }
        for it in &items {
            let named = [
                it.register.is_some(),
                it.coil.is_some(),
                it.mnemonic.is_some(),
                it.object.is_some(),
            ];
            if named.iter().filter(|n| **n).count() != 1 {
                return Err((
                    items_at,
                    format!(
                        "freedom `{id}`: an item names one `register`, `coil`, `mnemonic` or `object`"
                    ),
                ));
            }
        }
        let (golden_at, golden) = list(f.golden, at);
        if let Some(frames) = &known.golden_frames
            && let Some(g) = golden.iter().find(|g| !frames.contains(*g))
        {
            return Err((golden_at, format!("freedom `{id}`: no golden frame `{g}`")));
        }
        if f.sources.is_empty() {
            return Err((at, format!("freedom `{id}`: no `sources`")));
        }
        let mut sources = Vec::new();
        for s in f.sources {
            let s_at = s.span().start;
            let s = s.into_inner();
            let fail = |m: String| (s_at, format!("freedom `{id}`, source: {m}"));
            let Some((kind, _)) = docs.get(&s.doc) else {
                return Err(fail(format!(
                    "unknown document `{}` (known: {})",
                    s.doc,
                    docs.keys().cloned().collect::<Vec<_>>().join(", ")
                )));
            };
            match kind {
                DocKind::Manual if s.line.is_none() => {
                    return Err(fail(format!("a manual (`{}`) is cited by `line`", s.doc)));
                }
                DocKind::Spec if s.section.is_none() => {
                    return Err(fail(format!(
                        "a specification (`{}`) is cited by `section`",
                        s.doc
                    )));
                }
                _ => {}
            }
            check_lines(s.line, s.last_line).map_err(fail)?;
            if s.text.trim().is_empty() {
                return Err(fail("empty text".into()));
            }
            sources.push(s);
        }
        self.by_freedom.insert(id.clone(), self.freedoms.len());
        self.freedoms.push(Freedom {
            id,
            title: f.title,
            kind: f.kind,
            profiles,
            values,
            condition: f.condition,
            items,
            golden,
            units: f.units,
            functions: f.functions,
            field: f.field,
            register: f.register,
            sources,
            note: f.note,
            origin: Origin {
                file: file.to_string(),
                line: lines.line(at),
            },
        });
        Ok(())
    }

    fn add_cite(
        &mut self,
        c: RawCite,
        known: &KnownIds,
        file: &str,
        lines: &LineIndex,
        at: usize,
    ) -> Result<(), Fail> {
        let cases_at = c.cases.span().start;
        let cases = c.cases.into_inner();
        let pattern = glob::Pattern::new(&cases)
            .map_err(|e| (cases_at, format!("cite `{cases}`: bad glob: {e}")))?;
        let (profiles_at, profiles) = list(c.profiles, at);
        check_profiles(&profiles, known, false)
            .map_err(|m| (profiles_at, format!("cite `{cases}`: {m}")))?;
        let (req_at, requirements) = list(c.requirements, at);
        if let Some(r) = requirements
            .iter()
            .find(|r| !self.by_requirement.contains_key(*r))
        {
            return Err((req_at, format!("cite `{cases}`: no requirement `{r}`")));
        }
        let (fr_at, freedoms) = list(c.freedoms, at);
        if let Some(r) = freedoms.iter().find(|r| !self.by_freedom.contains_key(*r)) {
            return Err((fr_at, format!("cite `{cases}`: no freedom `{r}`")));
        }
        if requirements.is_empty() && freedoms.is_empty() {
            return Err((
                at,
                format!("cite `{cases}`: cites neither requirements nor freedoms"),
            ));
        }
        let literal = cases
            .split(['*', '?', '['])
            .next()
            .unwrap_or_default()
            .to_string();
        self.cites.push(Cite {
            cases,
            pattern,
            literal,
            profiles,
            requirements,
            freedoms,
            note: c.note,
            origin: Origin {
                file: file.to_string(),
                line: lines.line(at),
            },
        });
        Ok(())
    }

    /// Every document, in file order.
    pub fn documents(&self) -> &[Document] {
        &self.documents
    }

    /// Every requirement, in file order.
    pub fn requirements(&self) -> &[Requirement] {
        &self.requirements
    }

    /// Every freedom, in file order.
    pub fn freedoms(&self) -> &[Freedom] {
        &self.freedoms
    }

    /// Every entry of the citation map, in file order.
    pub fn cites(&self) -> &[Cite] {
        &self.cites
    }

    /// The document `id`.
    pub fn document(&self, id: &str) -> Option<&Document> {
        self.documents.iter().find(|d| d.id == id)
    }

    /// The requirement `id`.
    pub fn requirement(&self, id: &str) -> Option<&Requirement> {
        self.by_requirement.get(id).map(|&i| &self.requirements[i])
    }

    /// The freedom `id`.
    pub fn freedom(&self, id: &str) -> Option<&Freedom> {
        self.by_freedom.get(id).map(|&i| &self.freedoms[i])
    }

    /// The freedoms that apply to `profile`.
    pub fn freedoms_for<'a>(&'a self, profile: &'a str) -> impl Iterator<Item = &'a Freedom> {
        self.freedoms.iter().filter(move |f| f.applies_to(profile))
    }

    /// The requirement ids and freedom ids a case cites in a run against `profile`: the union over every
    /// matching entry of the citation map, sorted, without duplicates; freedoms that do not apply to the
    /// profile are left out.
    pub fn cited(&self, case_id: &str, profile: &str) -> (Vec<String>, Vec<String>) {
        let mut reqs = BTreeSet::new();
        let mut frees = BTreeSet::new();
        for c in self.cites.iter().filter(|c| c.matches(case_id, profile)) {
            reqs.extend(c.requirements.iter().cloned());
            frees.extend(
                c.freedoms
                    .iter()
                    .filter(|f| self.freedom(f).is_some_and(|f| f.applies_to(profile)))
                    .cloned(),
            );
        }
        (reqs.into_iter().collect(), frees.into_iter().collect())
    }

    /// Per document: how many of its requirements are in `cited` (e.g. every id cited by a run's cases).
    pub fn coverage<'a>(&self, cited: impl IntoIterator<Item = &'a str>) -> Vec<Coverage> {
        let cited: BTreeSet<&str> = cited.into_iter().collect();
        self.documents
            .iter()
            .map(|d| {
                let listed: Vec<&Requirement> = self
                    .requirements
                    .iter()
                    .filter(|r| r.document == d.id)
                    .collect();
                let missing: Vec<String> = listed
                    .iter()
                    .filter(|r| !cited.contains(r.id.as_str()))
                    .map(|r| r.id.clone())
                    .collect();
                Coverage {
                    document: d.id.clone(),
                    title: d.title.clone(),
                    listed: listed.len(),
                    exercised: listed.len() - missing.len(),
                    missing,
                }
            })
            .collect()
    }
}

/// Ids: lowercase ASCII letters, digits, '-', '.', '/', '_'; upper case only as hex digits after "0x".
fn is_id(id: &str) -> bool {
    !id.is_empty()
        && !id.starts_with('/')
        && !id.ends_with('/')
        && !id.contains("//")
        && id.split('/').all(|seg| {
            let lower_hex = seg
                .to_ascii_lowercase()
                .strip_prefix("0x")
                .map(|_| seg.len() > 2)
                .unwrap_or(false);
            seg.chars().all(|c| {
                c.is_ascii_lowercase()
                    || c.is_ascii_digit()
                    || matches!(c, '-' | '.' | '_')
                    || (lower_hex && c.is_ascii_uppercase())
            })
        })
}

fn check_lines(line: Option<u32>, last: Option<u32>) -> Result<(), String> {
    match (line, last) {
        (Some(0), _) => Err("lines are 1-based (line 0)".into()),
        (None, Some(_)) => Err("`last_line` without `line`".into()),
        (Some(l), Some(e)) if e < l => Err(format!("last_line {e} < line {l}")),
        _ => Ok(()),
    }
}

fn check_profiles(profiles: &[String], known: &KnownIds, all_ok: bool) -> Result<(), String> {
    for p in profiles {
        if all_ok && p == "all" {
            if profiles.len() > 1 {
                return Err("\"all\" stands alone in `profiles`".into());
            }
            continue;
        }
        if !known.profiles.is_empty() && !known.profiles.contains(p) {
            return Err(format!(
                "unknown profile `{p}` (known: {})",
                known.profiles.join(", ")
            ));
        }
    }
    Ok(())
}

/// The values a kind allows; the first is the reference's.
fn check_values(kind: FreedomKind, values: &[FreedomValue]) -> Result<(), String> {
    if values.is_empty() {
        return Err("`values` is empty".into());
    }
    for (i, v) in values.iter().enumerate() {
        if values[..i].contains(v) {
            return Err(format!("value `{v}` listed twice"));
        }
    }
    if matches!(kind, FreedomKind::Reading | FreedomKind::WordOrder) && values.len() < 2 {
        return Err("a reading needs at least two values".into());
    }
    let text = |allowed: &[&str], exceptions: bool| -> Result<(), String> {
        for v in values {
            match v {
                FreedomValue::Text(t)
                    if allowed.contains(&t.as_str()) || (exceptions && is_exception_name(t)) => {}
                other => {
                    return Err(format!(
                        "value `{other}` is not one of {}{}",
                        allowed.join(", "),
                        if exceptions { ", exception-XX" } else { "" }
                    ));
                }
            }
        }
        Ok(())
    };
    let ints = |lo: i64, hi: i64| -> Result<(), String> {
        for v in values {
            match v {
                FreedomValue::Int(i) if (lo..=hi).contains(i) => {}
                other => return Err(format!("value `{other}` is not a number in {lo}..={hi}")),
            }
        }
        Ok(())
    };
    match kind {
        FreedomKind::ExceptionCode => ints(1, 0xFF),
        FreedomKind::SdoError => ints(0, 0xFFFF_FFFF),
        FreedomKind::StatusBits => ints(1, 0xFFFF),
        FreedomKind::Outcome => text(&["response", "silence", "close", "sdo-error"], true),
        FreedomKind::Optional => text(&["present", "silence"], true),
        FreedomKind::UnitIds => text(&["answer", "silence"], true),
        FreedomKind::ServedExtra => text(&["served"], true),
        FreedomKind::Access => text(&["ro", "rw", "wo"], false),
        FreedomKind::WordOrder => text(&["high-first", "low-first"], false),
        FreedomKind::PipelineOrder => text(&["request-order", "transaction-id"], false),
        FreedomKind::Counter => text(
            &[
                "standard",
                "bus-count-includes-bad-crc",
                "no-response-includes-other-slaves",
                "slave-count-is-responses-sent",
                "excludes-current-request",
            ],
            false,
        ),
        FreedomKind::Reading | FreedomKind::FieldValue => Ok(()),
    }
}

impl Corpus {
    /// Load and validate the corpus's requirements, freedoms and citation map.
    pub fn requirements(&self) -> Result<Requirements, RequirementsError> {
        Requirements::load(self)
    }

    /// The requirements a run judges by: the corpus's own, or the built-in ones where a corpus directory
    /// has none (a user's profiles only). The built-in ones are loaded once per process.
    pub fn requirements_shared(&self) -> Result<std::sync::Arc<Requirements>, RequirementsError> {
        use std::sync::{Arc, OnceLock};
        static EMBEDDED: OnceLock<Arc<Requirements>> = OnceLock::new();
        let embedded = || -> Result<Arc<Requirements>, RequirementsError> {
            if let Some(r) = EMBEDDED.get() {
                return Ok(Arc::clone(r));
            }
            let r = Arc::new(Corpus::Embedded.requirements()?);
            Ok(Arc::clone(EMBEDDED.get_or_init(|| r)))
        };
        match self {
            Corpus::Embedded => embedded(),
            Corpus::Dir(d) if !d.join("requirements").is_dir() => embedded(),
            Corpus::Dir(_) => Ok(Arc::new(self.requirements()?)),
        }
    }

    /// True when the corpus has freedom `id` and it applies to profile `profile` (false when the
    /// requirements do not load).
    pub fn freedom_applies(&self, id: &str, profile: &str) -> bool {
        self.requirements_shared()
            .is_ok_and(|r| r.freedom(id).is_some_and(|f| f.applies_to(profile)))
    }
}

#[cfg(test)]
mod tests {
    use crate::corpus::Corpus;

    /// The literal-prefix check before the glob changes no answer: every entry of the citation map asked
    /// about ids made from every entry's pattern (wildcards filled in several ways, cut at every `/`).
    #[test]
    fn the_literal_prefix_check_agrees_with_the_glob() {
        let r = Corpus::Embedded.requirements().expect("requirements");
        let mut ids = std::collections::BTreeSet::new();
        for c in r.cites() {
            for fill in ["", "x", "a/b", "0x03/max-plus-1"] {
                let id = c.cases.replace(['*', '?'], fill).replace(['[', ']'], "");
                for (i, _) in id.match_indices('/') {
                    ids.insert(id[..i].to_string());
                }
                ids.insert(id);
            }
        }
        let mut matched = 0;
        for c in r.cites() {
            assert!(c.cases.starts_with(&c.literal), "{}", c.cases);
            for id in &ids {
                let fast = c.matches(id, "mdrive");
                let glob = (c.profiles.is_empty() || c.profiles.iter().any(|p| p == "mdrive"))
                    && c.pattern.matches(id);
                assert_eq!(fast, glob, "{} against {id}", c.cases);
                matched += usize::from(fast);
            }
        }
        assert!(matched > r.cites().len() / 2, "{matched} matches");
    }
}
