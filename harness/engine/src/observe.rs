//! What the runner saw: every byte with its timestamp, and the outcome of each step.

use std::time::Duration;

use serde::Serialize;

use crate::cases::Verdict;
use crate::targets::Received;

/// Which way bytes went.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Dir {
    Tx,
    Rx,
}

/// Bytes on the wire at a time (since the start of the run).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct WireEvent {
    pub dir: Dir,
    #[serde(serialize_with = "micros")]
    pub at: Duration,
    #[serde(serialize_with = "hex_bytes")]
    pub bytes: Vec<u8>,
    /// Sent malformed on purpose (the pcap and the case log mark it).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub intended_malformed: bool,
}

/// The judged result of one step.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct StepResult {
    pub note: String,
    #[serde(serialize_with = "opt_hex")]
    pub sent: Option<Vec<u8>>,
    /// What the reference model answers (framed as on the wire; None = silence).
    #[serde(serialize_with = "opt_hex")]
    pub expected: Option<Vec<u8>>,
    pub observed: Vec<Received>,
    pub verdict: Verdict,
    /// Why the verdict is not PASS, one line each.
    pub findings: Vec<String>,
}

/// The judged result of a case.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct CaseResult {
    pub id: String,
    pub verdict: Verdict,
    /// The verdict before an expectations file changed it, with the file's reason.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub expected_deviation: Option<(Verdict, String)>,
    pub steps: Vec<StepResult>,
    pub wire: Vec<WireEvent>,
    #[serde(serialize_with = "micros")]
    pub duration: Duration,
    /// Why the case was skipped or could not complete.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

impl StepResult {
    /// True when the step expected an answer and got silence or a close (nothing of a frame before it: part
    /// of a frame is an answer, wrong).
    pub fn unanswered(&self) -> bool {
        self.expected.is_some()
            && self.observed.iter().any(|o| {
                matches!(
                    o,
                    crate::targets::Received::Silence { partial, .. }
                        | crate::targets::Received::Closed { partial, .. } if partial.is_empty()
                )
            })
    }
}

impl CaseResult {
    /// True when a step expected an answer and got silence or a close (see [`StepResult::unanswered`]).
    pub fn unanswered(&self) -> bool {
        self.steps.iter().any(StepResult::unanswered)
    }

    /// The result of a case that was not run, and why.
    pub fn skipped(id: &str, reason: String) -> Self {
        CaseResult {
            id: id.to_string(),
            verdict: Verdict::Skipped,
            expected_deviation: None,
            steps: vec![],
            wire: vec![],
            duration: Duration::ZERO,
            reason: Some(reason),
        }
    }

    /// Every finding of every step, in order.
    pub fn findings(&self) -> impl Iterator<Item = &String> {
        self.steps.iter().flat_map(|s| s.findings.iter())
    }
}

impl crate::cases::shrink::Outcome for CaseResult {
    fn fails(&self) -> bool {
        self.verdict == Verdict::Fail
    }

    fn findings(&self) -> Vec<String> {
        CaseResult::findings(self).cloned().collect()
    }
}

fn micros<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_u64(d.as_micros() as u64)
}

pub(crate) fn hex_bytes<S: serde::Serializer>(b: &[u8], s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&codec::hex_spaced(b))
}

fn opt_hex<S: serde::Serializer>(b: &Option<Vec<u8>>, s: S) -> Result<S::Ok, S::Error> {
    match b {
        Some(b) => s.serialize_str(&codec::hex_spaced(b)),
        None => s.serialize_none(),
    }
}
