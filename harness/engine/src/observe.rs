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

/// What [`StepResult::link_damage`] calls a step that got nothing at all where the reference answers.
pub const NO_ANSWER: &str = "no answer";

impl StepResult {
    /// Where the step FAILed in a way a damaged link gives as well as a faulty drive, what came, in a few
    /// words: nothing where the reference answers (no answer, a closed connection: a request damaged on its
    /// way, an answer lost with its connection), or no whole frame (part of one, then silence; bytes that
    /// are no frame; over RTU a frame whose CRC does not check: an answer damaged on its way). Noise on an
    /// RS-485 line flips bits, loses bytes and adds stray ones (serial line spec 2.5.1.2: the CRC is there to
    /// catch them), and a TCP link drops connections; the drive cannot be told from its link by one step.
    /// Also a step NON-STRICT for a connection closed where the reference keeps it open (no answer due): a
    /// link that drops the connection then makes that too.
    pub fn link_damage(&self, framing: codec::Framing) -> Option<&'static str> {
        let fail = self.verdict == Verdict::Fail;
        if !fail && self.verdict != Verdict::NonStrict {
            return None;
        }
        self.observed.iter().find_map(|o| match o {
            Received::Silence { partial, .. } | Received::Closed { partial, .. }
                if fail && !partial.is_empty() =>
            {
                Some("part of a frame, then nothing")
            }
            Received::Closed { .. } => Some("the connection closed without an answer"),
            _ if !fail => None,
            Received::Silence { .. } if self.expected.is_some() => Some(NO_ANSWER),
            Received::Garbage { .. } => Some("bytes that are no frame"),
            Received::Frame { bytes, .. }
                if framing == codec::Framing::Rtu && !codec::rtu::crc_ok(bytes) =>
            {
                Some("a frame whose CRC does not check")
            }
            // A gateway's exception 0B, "gateway target device failed to respond" (App 7): its serial side
            // got no answer in time, which a damaged line or a busy host gives as well.
            Received::Frame { bytes, .. }
                if framing == codec::Framing::Tcp
                    && bytes.len() == 9
                    && bytes[7] & 0x80 != 0
                    && bytes[8] == 0x0B =>
            {
                Some("a gateway's exception 0B (its target did not answer)")
            }
            // Cut short where the CRC of what is left happens to check: sd2x-m's exception 01 to FC 0x44,
            // 01 C4 01 B3 00 cut after 4 bytes, is 01 C4 with a valid CRC (0xB301), and no response.
            Received::Frame { bytes, .. }
                if framing == codec::Framing::Rtu
                    && crate::readings::decode_response(framing, bytes).is_none() =>
            {
                Some("a frame that does not decode")
            }
            _ => None,
        })
    }
}

impl CaseResult {
    /// The first step that FAILed in a way a damaged link gives too (see [`StepResult::link_damage`]): its
    /// index and what came.
    pub fn link_damage(&self, framing: codec::Framing) -> Option<(usize, &'static str)> {
        self.steps
            .iter()
            .enumerate()
            .find_map(|(k, s)| s.link_damage(framing).map(|d| (k, d)))
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    fn step(expected: Option<&[u8]>, observed: Received, verdict: Verdict) -> StepResult {
        StepResult {
            note: String::new(),
            sent: None,
            expected: expected.map(<[u8]>::to_vec),
            observed: vec![observed],
            verdict,
            findings: vec![],
        }
    }

    /// An exception `code` to FC 03 in a Modbus/TCP frame (transaction 1, unit 1).
    fn gateway(code: u8) -> Vec<u8> {
        vec![0x00, 0x01, 0x00, 0x00, 0x00, 0x03, 0x01, 0x83, code]
    }

    /// `pdu` of unit 1 as an RTU frame with its CRC.
    fn rtu_adu(pdu: &[u8]) -> Vec<u8> {
        let mut f = vec![0x01];
        f.extend_from_slice(pdu);
        let crc = codec::rtu::crc16(&f);
        f.extend_from_slice(&crc.to_le_bytes());
        f
    }

    /// What a damaged link gives is told from what it cannot give: a whole frame whose CRC checks, or a
    /// silence where the reference is silent too, is the drive's; so is anything of a step that did not FAIL.
    #[test]
    fn link_damage_is_what_a_link_can_give() {
        use codec::Framing::{Rtu, Tcp};
        let answer = [0x01u8, 0x03, 0x02, 0x00, 0x00, 0xB8, 0x44];
        let mut bad = answer.to_vec();
        bad[3] ^= 0x10;
        let exp = Some(&answer[..]);
        let fail = Verdict::Fail;
        let cases: [(StepResult, codec::Framing, Option<&str>); 14] = [
            (step(exp, Received::silence(), fail), Rtu, Some("no answer")),
            (step(None, Received::silence(), fail), Rtu, None),
            (
                step(exp, Received::frame(bad.clone()), fail),
                Rtu,
                Some("a frame whose CRC does not check"),
            ),
            (step(exp, Received::frame(bad.clone()), fail), Tcp, None),
            (step(exp, Received::frame(answer.to_vec()), fail), Rtu, None),
            (
                step(
                    exp,
                    Received::Silence {
                        partial: answer[..3].to_vec(),
                        at: Duration::ZERO,
                    },
                    fail,
                ),
                Rtu,
                Some("part of a frame, then nothing"),
            ),
            (
                step(
                    exp,
                    Received::Closed {
                        partial: vec![],
                        at: Duration::ZERO,
                    },
                    fail,
                ),
                Tcp,
                Some("the connection closed without an answer"),
            ),
            (step(exp, Received::silence(), Verdict::Pass), Rtu, None),
            (
                step(
                    None,
                    Received::Closed {
                        partial: vec![],
                        at: Duration::ZERO,
                    },
                    Verdict::NonStrict,
                ),
                Tcp,
                Some("the connection closed without an answer"),
            ),
            (
                step(None, Received::silence(), Verdict::NonStrict),
                Tcp,
                None,
            ),
            (
                step(exp, Received::frame(vec![0x01, 0xC4, 0x01, 0xB3]), fail),
                Rtu,
                Some("a frame that does not decode"),
            ),
            // A gateway's 0B over Modbus/TCP: its serial side got nothing in time.
            (
                step(exp, Received::frame(gateway(0x0B)), fail),
                Tcp,
                Some("a gateway's exception 0B (its target did not answer)"),
            ),
            // Another exception is the drive's (or the gateway's) answer: 0A, no path to the unit.
            (step(exp, Received::frame(gateway(0x0A)), fail), Tcp, None),
            // A whole RTU exception 0B with its CRC is a frame the line delivered.
            (
                step(exp, Received::frame(rtu_adu(&[0x83, 0x0B])), fail),
                Rtu,
                None,
            ),
        ];
        for (k, (s, framing, want)) in cases.iter().enumerate() {
            assert_eq!(s.link_damage(*framing), *want, "case {k}");
        }
    }
}
