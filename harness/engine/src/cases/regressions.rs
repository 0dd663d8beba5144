//! The regression reproducers in `corpus/regressions/<profile>/*.toml`: the file form of a case, writing
//! a shrunk case as one, and loading a profile's files as cases `regression/<profile>/<file stem>`, which
//! the catalog replays after its own cases.
//!
//! # Regression file format
//!
//! ```toml
//! title = "FC 10 write of 0x0000 A = 1525878998 (above max)"
//! reference = "…"
//! requirement = "…"
//! level = "MUST"
//! tags = ["write"]
//!
//! [[step]]                      # kind = "exchange" unless said otherwise
//! pdu = "10 00 00 00 02 04 5A F1 07 D6"   # the PDU in hex, framed with the run's unit id
//! compare = "exact"             # exact | structure | in_range | any
//! note = "…"
//! # unit = 5                    # framed for this unit id instead
//! # mutation = "bad_crc"        # or a table: [step.mutation] bit_flip = { bit = 3 }, …
//! # batch = ["03 00 00 00 01", "03 00 01 00 01"]
//! # capture = 0 / restore_address = 0 + restore_slot = 0 / restore_slot = 0 alone (where it was read)
//! # kind = "wait" + wait_us = 1000 | kind = "reconnect" | kind = "agree" + registers + object
//! # kind = "event_log_shifted" + before + after + max_new
//!
//! [origin]                      # where the reproducer came from (informational)
//! case = "gen/42/17/write-reg"
//! seed = 42
//! …
//! ```

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::cases::shrink::Shrunk;
use crate::cases::{Case, Compare, Level, Mutation, Outgoing, Step, Tag, Verdict};
use codec::{hex_spaced, parse_hex};

/// The id prefix of replayed regression cases: `regression/<profile>/<name>`.
pub const REGRESSION_PREFIX: &str = "regression";

/// What a step does, in a regression file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepKind {
    #[default]
    Exchange,
    Wait,
    Reconnect,
    Agree,
    EventLogShifted,
    ClearedUnlessFlagged,
    Until,
    Persist,
}

fn is_exchange(k: &StepKind) -> bool {
    *k == StepKind::Exchange
}

/// One step in a regression file (hex PDUs; absent fields are not used by the step's kind).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepFile {
    #[serde(default, skip_serializing_if = "is_exchange")]
    pub kind: StepKind,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pdu: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit: Option<u8>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch: Option<Vec<String>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub restore_address: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub restore_slot: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub compare: Option<Compare>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub capture: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wait_us: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub registers: Option<usize>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub more_registers: Vec<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub before: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub after: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_new: Option<usize>,
    /// `cleared_unless_flagged`: the slots of the error record and of the error flag.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub record: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flag: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mutation: Option<Mutation>,
    /// `until`: the value the register must come to (in the bits of `mask`, all of them where absent), the
    /// verdict when it never does (FAIL where absent), how often it is read and for how long at most.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub value: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mask: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timeout: Option<Verdict>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub every_us: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub within_us: Option<u64>,
}

/// Where a reproducer came from (informational; the catalog ignores it).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Origin {
    /// The generated case that failed.
    pub case: String,
    pub seed: u64,
    pub index: u64,
    /// The target it failed on, and the simulator faults injected, if any.
    pub target: String,
    #[serde(default)]
    pub faults: Vec<String>,
    pub harness: String,
    /// Steps of the original case, and candidates run to shrink it.
    pub original_steps: usize,
    pub shrink_steps: usize,
    /// Why the reproducer FAILed there.
    #[serde(default)]
    pub findings: Vec<String>,
}

/// A regression file: a case without its id (the file name gives it).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegressionFile {
    pub title: String,
    pub reference: String,
    pub requirement: String,
    pub level: Level,
    #[serde(default)]
    pub tags: Vec<Tag>,
    #[serde(rename = "step")]
    pub steps: Vec<StepFile>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<Origin>,
}

fn step_file(step: &Step) -> StepFile {
    let mut f = StepFile::default();
    match step {
        Step::Exchange {
            send,
            compare,
            capture,
            note,
        } => {
            f.compare = Some(compare.clone());
            f.capture = *capture;
            f.note = Some(note.clone());
            match send {
                Outgoing::Pdu(p) => f.pdu = Some(hex_spaced(p)),
                Outgoing::PduToUnit { pdu, unit } => {
                    f.pdu = Some(hex_spaced(pdu));
                    f.unit = Some(*unit);
                }
                Outgoing::Mutated { pdu, mutation } => {
                    f.pdu = Some(hex_spaced(pdu));
                    f.mutation = Some(mutation.clone());
                }
                Outgoing::Batch(ps) => f.batch = Some(ps.iter().map(|p| hex_spaced(p)).collect()),
                Outgoing::Restore { address, slot } => {
                    f.restore_address = Some(*address);
                    f.restore_slot = Some(*slot);
                }
                Outgoing::RestoreRead { slot } => f.restore_slot = Some(*slot),
            }
        }
        Step::Wait(d) => {
            f.kind = StepKind::Wait;
            f.wait_us = Some(d.as_micros() as u64);
        }
        Step::Reconnect => f.kind = StepKind::Reconnect,
        Step::Until {
            read,
            mask,
            value,
            timeout,
            stop,
            every,
            within,
            note,
        } => {
            f.kind = StepKind::Until;
            f.pdu = Some(hex_spaced(read));
            f.batch = (!stop.is_empty()).then(|| stop.iter().map(|p| hex_spaced(p)).collect());
            f.mask = (*mask != 0xFFFF).then_some(*mask);
            f.timeout = (*timeout != Verdict::Fail).then_some(*timeout);
            f.value = Some(*value);
            f.every_us = Some(every.as_micros() as u64);
            f.within_us = Some(within.as_micros() as u64);
            f.note = Some(note.clone());
        }
        Step::Persist {
            send,
            compare,
            every,
            within,
            note,
        } => {
            f.kind = StepKind::Persist;
            f.compare = Some(compare.clone());
            f.every_us = Some(every.as_micros() as u64);
            f.within_us = Some(within.as_micros() as u64);
            f.note = Some(note.clone());
            if let Outgoing::Pdu(p) = send {
                f.pdu = Some(hex_spaced(p));
            }
        }
        Step::Agree {
            registers,
            more_registers,
            object,
            note,
        } => {
            f.kind = StepKind::Agree;
            f.registers = Some(*registers);
            f.more_registers = more_registers.clone();
            f.object = Some(*object);
            f.note = Some(note.clone());
        }
        Step::EventLogShifted {
            before,
            after,
            max_new,
            note,
        } => {
            f.kind = StepKind::EventLogShifted;
            f.before = Some(*before);
            f.after = Some(*after);
            f.max_new = Some(*max_new);
            f.note = Some(note.clone());
        }
        Step::ClearedUnlessFlagged { record, flag, note } => {
            f.kind = StepKind::ClearedUnlessFlagged;
            f.record = Some(*record);
            f.flag = Some(*flag);
            f.note = Some(note.clone());
        }
    }
    f
}

/// Why a regression file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum RegressionError {
    /// The file is not valid TOML or not a regression file.
    #[error("{file}: {reason}")]
    Parse { file: String, reason: String },
    /// A step of the file does not make a step.
    #[error("{file}step {step}: {reason}")]
    Step {
        /// The file and `: `, or empty when the file is not known yet.
        file: String,
        step: usize,
        reason: String,
    },
    /// The folder of regressions cannot be read.
    #[error("regressions of {profile}: {source}")]
    Read {
        profile: String,
        source: std::io::Error,
    },
}

fn step_of(i: usize, f: &StepFile) -> Result<Step, RegressionError> {
    let at = |what: &str| RegressionError::Step {
        file: String::new(),
        step: i + 1,
        reason: what.to_string(),
    };
    let hex = |s: &str| parse_hex(s).map_err(|e| at(&format!("bad hex `{s}`: {e}")));
    Ok(match f.kind {
        StepKind::Wait => Step::Wait(Duration::from_micros(
            f.wait_us.ok_or_else(|| at("a wait needs wait_us"))?,
        )),
        StepKind::Reconnect => Step::Reconnect,
        StepKind::Until => Step::Until {
            read: hex(f.pdu.as_deref().ok_or_else(|| at("until needs pdu"))?)?,
            mask: f.mask.unwrap_or(0xFFFF),
            value: f.value.ok_or_else(|| at("until needs value"))?,
            timeout: f.timeout.unwrap_or(Verdict::Fail),
            stop: f
                .batch
                .iter()
                .flatten()
                .map(|p| hex(p))
                .collect::<Result<_, _>>()?,
            every: Duration::from_micros(f.every_us.ok_or_else(|| at("until needs every_us"))?),
            within: Duration::from_micros(f.within_us.ok_or_else(|| at("until needs within_us"))?),
            note: f.note.clone().unwrap_or_default(),
        },
        StepKind::Persist => Step::Persist {
            send: Outgoing::Pdu(hex(f
                .pdu
                .as_deref()
                .ok_or_else(|| at("persist needs pdu"))?)?),
            compare: f.compare.clone().unwrap_or(Compare::Exact),
            every: Duration::from_micros(f.every_us.ok_or_else(|| at("persist needs every_us"))?),
            within: Duration::from_micros(
                f.within_us.ok_or_else(|| at("persist needs within_us"))?,
            ),
            note: f.note.clone().unwrap_or_default(),
        },
        StepKind::Agree => Step::Agree {
            registers: f.registers.ok_or_else(|| at("agree needs registers"))?,
            more_registers: f.more_registers.clone(),
            object: f.object.ok_or_else(|| at("agree needs object"))?,
            note: f.note.clone().unwrap_or_default(),
        },
        StepKind::EventLogShifted => Step::EventLogShifted {
            before: f
                .before
                .ok_or_else(|| at("event_log_shifted needs before"))?,
            after: f.after.ok_or_else(|| at("event_log_shifted needs after"))?,
            max_new: f
                .max_new
                .ok_or_else(|| at("event_log_shifted needs max_new"))?,
            note: f.note.clone().unwrap_or_default(),
        },
        StepKind::ClearedUnlessFlagged => Step::ClearedUnlessFlagged {
            record: f
                .record
                .ok_or_else(|| at("cleared_unless_flagged needs record"))?,
            flag: f
                .flag
                .ok_or_else(|| at("cleared_unless_flagged needs flag"))?,
            note: f.note.clone().unwrap_or_default(),
        },
        StepKind::Exchange => {
            let send = match (&f.pdu, &f.batch, f.restore_address) {
                (Some(p), None, None) => {
                    let pdu = hex(p)?;
                    match (&f.mutation, f.unit) {
                        (None, None) => Outgoing::Pdu(pdu),
                        (None, Some(unit)) => Outgoing::PduToUnit { pdu, unit },
                        (Some(m), None) => Outgoing::Mutated {
                            pdu,
                            mutation: m.clone(),
                        },
                        (Some(_), Some(_)) => {
                            return Err(at("a step has either unit or mutation, not both"));
                        }
                    }
                }
                (None, Some(b), None) => {
                    Outgoing::Batch(b.iter().map(|p| hex(p)).collect::<Result<Vec<_>, _>>()?)
                }
                (None, None, Some(address)) => Outgoing::Restore {
                    address,
                    slot: f.restore_slot.unwrap_or(0),
                },
                (None, None, None) if f.restore_slot.is_some() => Outgoing::RestoreRead {
                    slot: f.restore_slot.unwrap_or(0),
                },
                _ => {
                    return Err(at(
                        "an exchange has exactly one of pdu, batch, restore_address, restore_slot",
                    ));
                }
            };
            Step::Exchange {
                send,
                compare: f.compare.clone().unwrap_or(Compare::Structure),
                capture: f.capture,
                note: f.note.clone().unwrap_or_default(),
            }
        }
    })
}

impl RegressionFile {
    /// The file form of a case.
    pub fn from_case(case: &Case, origin: Option<Origin>) -> Self {
        Self {
            title: case.title.clone(),
            reference: case.reference.clone(),
            requirement: case.requirement.clone(),
            level: case.level,
            tags: case.tags.clone(),
            steps: case.steps.iter().map(step_file).collect(),
            origin,
        }
    }

    /// The case, with id `id`.
    pub fn to_case(&self, id: String) -> Result<Case, RegressionError> {
        Ok(Case {
            id,
            title: self.title.clone(),
            reference: self.reference.clone(),
            requirement: self.requirement.clone(),
            level: self.level,
            tags: self.tags.clone(),
            steps: self
                .steps
                .iter()
                .enumerate()
                .map(|(i, s)| step_of(i, s))
                .collect::<Result<_, _>>()?,
            requirements: Vec::new(),
            freedoms: Vec::new(),
        })
    }

    /// Parse a regression file; `name` is used in errors.
    pub fn parse(name: &str, text: &str) -> Result<Self, RegressionError> {
        toml::from_str(text).map_err(|e| RegressionError::Parse {
            file: name.to_string(),
            reason: drives::profile::toml_error_message(text, &e),
        })
    }

    /// The file's text, with a comment saying what it is.
    pub fn to_toml(&self) -> String {
        let body = toml::to_string(self).unwrap_or_else(|e| format!("# cannot serialise: {e}\n"));
        format!(
            "# A reproducer shrunk by `modbus-harness run --generated` against a live target. The catalog replays\n# it as regression/<profile>/<file name>; it must PASS on a conforming drive.\n\n{body}"
        )
    }
}

/// The file name stem of a case id: `gen/42/7/write-reg` → `gen-42-7-write-reg`.
pub fn file_stem(id: &str) -> String {
    let mut s: String = id
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '-'
            }
        })
        .collect();
    s.truncate(100);
    s
}

/// Write a shrunk case to `dir/<profile>/<stem>.toml`; returns the path.
pub fn write_regression(
    dir: &Path,
    profile: &str,
    shrunk: &Shrunk,
    origin: Origin,
) -> std::io::Result<PathBuf> {
    let sub = dir.join(profile);
    std::fs::create_dir_all(&sub)?;
    let path = sub.join(format!("{}.toml", file_stem(&shrunk.case.id)));
    let text = RegressionFile::from_case(&shrunk.case, Some(origin)).to_toml();
    // Written beside and renamed: a reader never sees half a file.
    let tmp = path.with_extension("toml.tmp");
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, &path)?;
    Ok(path)
}

/// The regression cases of a profile in a corpus: `regression/<profile>/<file stem>`, sorted by name.
pub fn load_regressions(
    corpus: &drives::corpus::Corpus,
    profile: &str,
) -> Result<Vec<Case>, RegressionError> {
    let files = match corpus.files(&format!("{REGRESSION_PREFIX}s/{profile}")) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(source) => {
            return Err(RegressionError::Read {
                profile: profile.to_string(),
                source,
            });
        }
    };
    let mut out = Vec::new();
    for (name, text) in files {
        let path = Path::new(name.trim_end_matches(" (embedded)"));
        // Only the profile's own folder, not deeper ones.
        if path
            .parent()
            .and_then(|p| p.file_name())
            .is_none_or(|p| p != profile)
        {
            continue;
        }
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let file = RegressionFile::parse(&name, &text)?;
        out.push(
            file.to_case(format!("{REGRESSION_PREFIX}/{profile}/{stem}"))
                .map_err(|e| match e {
                    RegressionError::Step { step, reason, .. } => RegressionError::Step {
                        file: format!("{name}: "),
                        step,
                        reason,
                    },
                    other => other,
                })?,
        );
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Case {
        Case {
            id: "gen/1/2/x".into(),
            title: "t".into(),
            reference: "r".into(),
            requirement: "q".into(),
            level: Level::Must,
            tags: vec![Tag::Write, Tag::TcpOnly],
            steps: vec![
                Step::Exchange {
                    send: Outgoing::Pdu(vec![3, 0, 0, 0, 1]),
                    compare: Compare::InRange,
                    capture: Some(0),
                    note: "read".into(),
                },
                Step::Exchange {
                    send: Outgoing::Mutated {
                        pdu: vec![3, 0, 0, 0, 1],
                        mutation: Mutation::BitFlip { bit: 3 },
                    },
                    compare: Compare::Structure,
                    capture: None,
                    note: "flip".into(),
                },
                Step::Exchange {
                    send: Outgoing::Mutated {
                        pdu: vec![3, 0, 0, 0, 1],
                        mutation: Mutation::BadCrc,
                    },
                    compare: Compare::Exact,
                    capture: None,
                    note: "crc".into(),
                },
                Step::Exchange {
                    send: Outgoing::Mutated {
                        pdu: vec![3],
                        mutation: Mutation::Extend(vec![1, 2]),
                    },
                    compare: Compare::Exact,
                    capture: None,
                    note: "ext".into(),
                },
                Step::Exchange {
                    send: Outgoing::PduToUnit {
                        pdu: vec![3, 0, 0, 0, 1],
                        unit: 9,
                    },
                    compare: Compare::Exact,
                    capture: None,
                    note: "unit".into(),
                },
                Step::Exchange {
                    send: Outgoing::Batch(vec![vec![3, 0, 0, 0, 1], vec![4, 0, 0, 0, 1]]),
                    compare: Compare::Structure,
                    capture: None,
                    note: "batch".into(),
                },
                Step::Exchange {
                    send: Outgoing::Restore {
                        address: 7,
                        slot: 0,
                    },
                    compare: Compare::Exact,
                    capture: None,
                    note: "restore".into(),
                },
                Step::Wait(Duration::from_millis(5)),
                Step::Persist {
                    send: Outgoing::Pdu(vec![0x10, 0, 0x43, 0, 2, 4, 0xFF, 0xFF, 0xFF, 0xFF]),
                    compare: Compare::Exact,
                    every: Duration::from_millis(50),
                    within: Duration::from_secs(5),
                    note: "move".into(),
                },
                Step::Until {
                    read: vec![3, 0, 0x4A, 0, 1],
                    mask: 0x0080,
                    value: 0,
                    timeout: Verdict::Informational,
                    stop: vec![vec![0x10, 0, 0x1C, 0, 1, 2, 0, 0]],
                    every: Duration::from_millis(50),
                    within: Duration::from_secs(10),
                    note: "at rest".into(),
                },
                Step::Reconnect,
                Step::Agree {
                    registers: 0,
                    more_registers: vec![],
                    object: 1,
                    note: "agree".into(),
                },
                Step::EventLogShifted {
                    before: 0,
                    after: 1,
                    max_new: 6,
                    note: "shifted".into(),
                },
                Step::ClearedUnlessFlagged {
                    record: 0,
                    flag: 1,
                    note: "cleared".into(),
                },
            ],
            requirements: Vec::new(),
            freedoms: Vec::new(),
        }
    }

    #[test]
    fn a_case_survives_the_file_format() {
        let case = sample();
        let text = RegressionFile::from_case(&case, Some(Origin::default())).to_toml();
        let back = RegressionFile::parse("x.toml", &text)
            .expect("parse")
            .to_case(case.id.clone())
            .expect("case");
        assert_eq!(back, case, "{text}");
    }

    #[test]
    fn file_stems_are_plain() {
        assert_eq!(file_stem("gen/42/7/write-reg"), "gen-42-7-write-reg");
    }
}
