//! Pipelined cases (issue 17): over Modbus/TCP, the requests of several cases go out in one write, and each
//! case is then run as if it were alone. Each step's answer is taken by transaction id (answers to the
//! requests after it that arrive first are kept for them), the reference drive gets the requests one at a
//! time in case order, and the oracle judges each case as it judges one sent alone.
//!
//! Only where the target showed that it answers requests sent together ([`Runner::discover_pipelining`]:
//! a burst of known-good reads in one write, every one answered normally), and only for cases whose every
//! step is a request to the run's unit that any server cuts from the stream where it ends
//! ([`Runner::pipelinable`], [`complete_pdu`]): reads of FC 01-04 and the one-byte FC 07, 0B, 0C, 11, as
//! generated or altered (a bit flipped) so long as they still decode strictly. A server that cuts requests
//! by the function's length rules instead of the MBAP length (libmodbus) would take the bytes after a
//! malformed or unknown request for part of it, and the next request, innocent, would go unanswered: such
//! requests, writes, FC 08 (a restart or listen-only mode silences the drive), a request to another unit, a
//! wait or a new connection go one at a time, as do the liveness probes and the silence sentinels.
//!
//! Each step waits for its own answer as long as when alone (where the reference stays silent, no sentinel
//! follows a pipelined request: the window is listened out). A drive that closes the connection has
//! dropped the requests behind it: they are sent again, one at a time, when their cases' turns come. A
//! pipelined case left without an answer where one was due is asked again alone before it is judged (a
//! server may drop what arrives behind a request it refuses), and pipelining ends there.

use std::time::Duration;

use super::{Framed, Runner, busy_refusal};
use crate::cases::{Case, Compare, Level, Outgoing, Step, Tag, Verdict};
use crate::observe::CaseResult;
use crate::targets::{Received, TargetError};
use codec::Framing;

/// A request of a case still to run, on the wire already.
pub(super) struct Ahead {
    /// The case it is for.
    pub(super) case: String,
    pub(super) frame: Framed,
    /// The target's time just before the write that carried it.
    pub(super) at: Duration,
}

/// The most requests put in flight at once (the Modbus/TCP guide's NumberMaxOfServerTransaction is at
/// most 16; a deeper pipeline only queues in the target's socket).
pub const MAX_IN_FLIGHT: usize = 64;

/// The freedom a pipelined request's answer may take: exception 06, Server Busy, from a server with fewer
/// transactions than requests in flight (Modbus/TCP guide, 4.4.2.2).
pub(super) const SERVER_BUSY: &str = drives::choices::ids::PIPELINED_SERVER_BUSY;

/// Whether requests go out several at a time, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pipelining {
    /// Requests in flight at most (1: one at a time).
    pub depth: usize,
    /// Why: what the burst showed, or why none was sent.
    pub why: String,
}

impl Pipelining {
    fn off(why: impl Into<String>) -> Self {
        Pipelining {
            depth: 1,
            why: why.into(),
        }
    }
}

/// The burst that shows whether a target answers requests sent together: `depth` known-good reads in one
/// write, judged as the catalog's `tcp/pipeline/*` cases are.
fn burst_case(profile: &drives::profile::Profile, depth: usize) -> Case {
    let read = crate::cases::catalog::known_good_read(profile);
    Case {
        id: format!("fuzz/pipeline/{depth}-requests-one-segment"),
        title: format!("{depth} known-good reads in one TCP segment (may requests be pipelined?)"),
        reference: "MODBUS Messaging on TCP/IP Implementation Guide V1.0b, section 4.2.1.1 (several transactions may be active on one connection)".into(),
        requirement: "Requests that arrive together in one segment are all answered, each with its own transaction id, in any order (they are paired by transaction id); a server with a single transaction may answer the ones behind the first with exception 06, Server Busy.".into(),
        level: Level::Must,
        tags: vec![Tag::TcpOnly],
        steps: vec![Step::Exchange {
            send: Outgoing::Batch(vec![read; depth]),
            compare: Compare::Structure,
            capture: None,
            note: format!("{depth} requests"),
        }],
        requirements: Vec::new(),
        freedoms: Vec::new(),
    }
}

/// The PDU a step sends to the run's unit where any server cuts it from the stream where it ends, whether
/// it goes by the MBAP length (as the guide says) or by the function's length rules (libmodbus does, and
/// then reads the bytes a function it does not know leaves as the start of the next request): a PDU as it
/// is, or altered by a PDU-level mutation, that decodes strictly as a read of FC 01-04 (5 bytes) or as
/// FC 07, 0B, 0C or 11 (the function code alone). Not FC 08 (a restart or listen-only mode silences the
/// drive), no write, nothing whose length a server could read otherwise.
fn complete_pdu(send: &Outgoing) -> Option<Vec<u8>> {
    let pdu = match send {
        Outgoing::Pdu(p) => p.clone(),
        Outgoing::Mutated { pdu, mutation } => mutation.apply_to_pdu(pdu)?,
        _ => return None,
    };
    let framed_alike = match pdu.first() {
        Some(0x01..=0x04) => pdu.len() == 5,
        Some(0x07 | 0x0B | 0x0C | 0x11) => pdu.len() == 1,
        _ => false,
    };
    (framed_alike && codec::Request::decode(&pdu).is_ok()).then_some(pdu)
}

/// The transaction id of a Modbus/TCP frame.
fn tid_of(r: &Received) -> Option<u16> {
    match r {
        Received::Frame { bytes, .. } if bytes.len() >= 2 => {
            Some(u16::from_be_bytes([bytes[0], bytes[1]]))
        }
        _ => None,
    }
}

impl Runner {
    /// Why no case of this run can be pipelined, if none can.
    pub fn pipeline_unavailable(&self) -> Option<&'static str> {
        if self.target.framing() != Framing::Tcp {
            Some("only Modbus/TCP pairs answers with their requests (by transaction id)")
        } else if self.cfg.is_sim {
            Some("the in-process reference drive answers every request at once")
        } else if self.cfg.safety.max_rate.is_some() {
            Some("--max-rate paces every request")
        } else {
            None
        }
    }

    /// Whether `case` may go out with other cases' requests in flight: every step an exchange of a request
    /// any server cuts where it ends (see [`complete_pdu`]), nothing captured, no write, on a run that can
    /// pipeline at all.
    pub fn pipelinable(&self, case: &Case) -> bool {
        !case.steps.is_empty()
            && case.steps.len() <= MAX_IN_FLIGHT
            && !case.has(Tag::Write)
            && !case.has(Tag::Motion)
            && !case.has(Tag::Destructive)
            && case.steps.iter().all(|s| match s {
                Step::Exchange {
                    send,
                    capture: None,
                    ..
                } => complete_pdu(send).is_some(),
                _ => false,
            })
            && self.pipeline_unavailable().is_none()
    }

    /// Find out whether the target answers `depth` requests sent together: `depth` known-good reads go out in
    /// one write (with transaction ids of the sequence the liveness probes use, so that the cases' own ids
    /// are the same with or without it) and are judged. Pipelining is on when the burst PASSes with every
    /// read answered normally; otherwise off, with the reason. The burst and its result are returned when it
    /// was sent: a FAIL is a finding (a server must answer requests that arrive together, or refuse them as
    /// busy).
    pub fn discover_pipelining(
        &mut self,
        depth: usize,
    ) -> Result<(Pipelining, Option<(Case, CaseResult)>), TargetError> {
        let depth = depth.min(MAX_IN_FLIGHT);
        if depth < 2 {
            return Ok((
                Pipelining::off("one request at a time (--pipeline 1)"),
                None,
            ));
        }
        if let Some(why) = self.pipeline_unavailable() {
            return Ok((Pipelining::off(why), None));
        }
        let case = burst_case(&self.profile, depth);
        let case_tid = std::mem::replace(&mut self.next_tid, self.restore_tid);
        let result = self.run_case(&case);
        self.restore_tid = std::mem::replace(&mut self.next_tid, case_tid);
        let result = result?;
        let answers: Vec<&[u8]> = result
            .steps
            .iter()
            .flat_map(|s| &s.observed)
            .filter_map(|o| match o {
                Received::Frame { bytes, .. } => Some(bytes.as_slice()),
                _ => None,
            })
            .collect();
        let normal = answers
            .iter()
            .filter(|b| b.get(codec::tcp::MBAP_LEN).is_some_and(|fc| fc & 0x80 == 0))
            .count();
        let busy = answers.iter().filter(|b| busy_refusal(b)).count();
        let p = match result.verdict {
            Verdict::Pass if normal == depth => Pipelining {
                depth,
                why: format!(
                    "the target answered {depth} known-good reads sent in one write, each normally"
                ),
            },
            Verdict::Fail => Pipelining::off(format!(
                "the target's answers to {depth} known-good reads sent in one write FAIL ({})",
                result.findings().next().map_or("", String::as_str)
            )),
            _ => Pipelining::off(format!(
                "of {depth} known-good reads sent in one write, the target answered {normal} normally and {busy} with Server Busy (exception 06)"
            )),
        };
        Ok((p, Some((case, result))))
    }

    /// Run `cases` in order; one result per case, with whether its requests went out pipelined. The requests
    /// of the leading pipelinable cases (at most [`MAX_IN_FLIGHT`]) go out together in one write first, then
    /// each case runs as if alone; the cases after the first that cannot be pipelined run one at a time
    /// behind them. Call it only once pipelining was found to work ([`Runner::discover_pipelining`]).
    pub fn run_pipelined(
        &mut self,
        cases: &[Case],
    ) -> Result<Vec<(CaseResult, bool)>, TargetError> {
        let results = self.run_ahead(cases);
        // Whatever happened, nothing stays ahead: no later case may take a request sent for another, nor an
        // answer kept for one.
        self.ahead.clear();
        self.stash.clear();
        self.presented = None;
        self.ahead_lost = false;
        results
    }

    fn run_ahead(&mut self, cases: &[Case]) -> Result<Vec<(CaseResult, bool)>, TargetError> {
        let (late, stale) = self.take_stale();
        let at = self.target.now();
        let mut bytes = Vec::new();
        'cases: for case in cases {
            if !self.pipelinable(case) || self.ahead.len() + case.steps.len() > MAX_IN_FLIGHT {
                break;
            }
            self.case_id.clone_from(&case.id);
            self.case_tags.clone_from(&case.tags);
            let mut framed = Vec::new();
            for step in &case.steps {
                let Step::Exchange { send, .. } = step else {
                    break 'cases;
                };
                let Some((mut frames, _)) = self.outgoing(send) else {
                    break 'cases;
                };
                // The safety assertion, on the bytes that go out, before any does (as for a case sent
                // alone).
                if frames.len() != 1 || self.refusal(&frames).is_some() {
                    break 'cases;
                }
                framed.push(frames.remove(0));
            }
            for frame in framed {
                bytes.extend_from_slice(&frame.bytes);
                self.ahead.push_back(Ahead {
                    case: case.id.clone(),
                    frame,
                    at,
                });
            }
        }
        self.ahead_lost = false;
        if !self.ahead.is_empty() {
            self.target.send(&bytes)?;
            self.requests += self.ahead.len() as u64;
        }
        let mut first = Some((late, stale));
        let mut results = Vec::with_capacity(cases.len());
        for case in cases {
            let (late, wire) = first.take().unwrap_or_default();
            let ahead = self.ahead.front().is_some_and(|a| a.case == case.id) && !self.ahead_lost;
            let before = ahead.then(|| self.shadow.clone());
            let result = self.run_case_after(case, late, wire)?;
            match before {
                Some(before) if result.unanswered() => {
                    // No answer where one was due, with other requests in flight: a server that drops what
                    // arrives behind a request it refuses (libmodbus flushes its input after most
                    // exceptions) does that to innocent requests. The case is asked again alone, from the
                    // reference's state before it, and judged so; the requests still ahead go again, one at
                    // a time; the campaign pipelines no more (`pipeline_failed`).
                    self.ahead_lost = true;
                    self.pipeline_failed = Some(case.id.clone());
                    self.shadow = before;
                    let alone = self.run_case(case)?;
                    results.push((alone, false));
                }
                _ => results.push((result, ahead)),
            }
        }
        Ok(results)
    }

    /// The pipelined case that went unanswered and was asked again alone, if one did (see `run_ahead`).
    pub fn pipeline_failed(&self) -> Option<&str> {
        self.pipeline_failed.as_deref()
    }

    /// The next answer for `frames` (the step's requests): one kept for them already, else what the target
    /// sends within `wait`. Answers to the requests of the cases still ahead are kept for those, bounded by
    /// their number and by `wait`. A close ends them too: their requests are sent again (see `ahead_lost`).
    pub(super) fn recv_answer(
        &mut self,
        frames: &[Framed],
        wait: Duration,
    ) -> Result<Received, TargetError> {
        let ours =
            |r: &Received| tid_of(r).is_some_and(|t| frames.iter().any(|f| f.sent.tid == Some(t)));
        if let Some(k) = self.stash.iter().position(ours) {
            return Ok(self.stash.remove(k));
        }
        if self.ahead.is_empty() {
            return self.target.recv(wait);
        }
        let start = self.target.now();
        for _ in 0..=self.ahead.len() {
            let left = wait.saturating_sub(self.target.now().saturating_sub(start));
            let got = self.target.recv(left)?;
            let theirs = tid_of(&got)
                .is_some_and(|t| self.ahead.iter().any(|a| a.frame.sent.tid == Some(t)));
            if !theirs || ours(&got) {
                if matches!(got, Received::Closed { .. }) {
                    // The requests behind the step's are gone with the connection.
                    self.ahead_lost = true;
                }
                return Ok(got);
            }
            self.stash.push(got);
        }
        let left = wait.saturating_sub(self.target.now().saturating_sub(start));
        self.target.recv(left)
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::generic_runner_choosing;
    use super::*;

    /// A one-step read case.
    fn read(id: &str, pdu: &[u8]) -> Case {
        Case {
            id: id.into(),
            title: String::new(),
            reference: String::new(),
            requirement: String::new(),
            level: Level::Must,
            tags: vec![],
            steps: vec![Step::Exchange {
                send: Outgoing::Pdu(pdu.to_vec()),
                compare: Compare::Exact,
                capture: None,
                note: String::new(),
            }],
            requirements: Vec::new(),
            freedoms: Vec::new(),
        }
    }

    /// Reads answered normally and with exceptions (an unmapped address, a quantity of 0).
    fn reads() -> Vec<Case> {
        [
            [0x03, 0x00, 0x00, 0x00, 0x02],
            [0x03, 0xFF, 0x00, 0x00, 0x01],
            [0x04, 0x00, 0x00, 0x00, 0x01],
            [0x01, 0x00, 0x00, 0x00, 0x00],
            [0x02, 0x00, 0x00, 0x00, 0x08],
            [0x03, 0x00, 0x01, 0x00, 0x01],
        ]
        .iter()
        .enumerate()
        .map(|(i, p)| read(&format!("read/{i}"), p))
        .collect()
    }

    /// The transaction id and the PDU of what a case observed.
    fn seen(r: &CaseResult) -> Vec<(Option<u16>, Vec<u8>)> {
        r.steps
            .iter()
            .flat_map(|s| &s.observed)
            .map(|o| match o {
                Received::Frame { bytes, .. } => {
                    (tid_of(o), bytes[codec::tcp::MBAP_LEN..].to_vec())
                }
                other => (None, format!("{other:?}").into_bytes()),
            })
            .collect()
    }

    /// Pipelined, each case sees the answer to its own request, judged as when it is sent alone; a drive
    /// that answers requests sent together last first (`pipelined-response-order=transaction-id`) included.
    #[test]
    fn pipelined_cases_see_their_own_answers_as_when_sent_alone() {
        for choices in [&[][..], &["pipelined-response-order=transaction-id"][..]] {
            let mut alone = generic_runner_choosing(choices);
            let mut piped = generic_runner_choosing(choices);
            let cases = reads();
            assert!(cases.iter().all(|c| piped.pipelinable(c)));
            let one: Vec<CaseResult> = cases
                .iter()
                .map(|c| alone.run_case(c).expect("alone"))
                .collect();
            let many = piped.run_pipelined(&cases).expect("pipelined");
            assert_eq!(many.len(), cases.len());
            for ((a, (p, in_flight)), c) in one.iter().zip(&many).zip(&cases) {
                assert!(in_flight, "{}: not pipelined", c.id);
                assert_eq!(p.verdict, Verdict::Pass, "{choices:?} {}: {p:#?}", c.id);
                assert_eq!(a.verdict, p.verdict, "{}", c.id);
                assert_eq!(seen(a), seen(p), "{choices:?} {}", c.id);
                assert_eq!(seen(p).len(), 1, "{}", c.id);
            }
            assert_eq!(piped.requests(), alone.requests());
            assert!(piped.ahead.is_empty() && piped.stash.is_empty());
        }
    }

    /// A drive that finds its transactions taken answers a pipelined read Server Busy (exception 06), as the
    /// Modbus/TCP guide allows (4.4.2.2): the case is not blamed for it.
    #[test]
    fn a_pipelined_read_refused_as_busy_is_admitted() {
        let mut runner = generic_runner_choosing(&["pipelined-server-busy=exception-06"]);
        let results = runner.run_pipelined(&reads()[..3]).expect("pipelined");
        let busy: Vec<bool> = results
            .iter()
            .map(|(r, _)| super::super::busy_refusal(&observed_adu(r)))
            .collect();
        assert_eq!(busy, [false, true, true], "{results:#?}");
        for (r, in_flight) in &results {
            assert!(in_flight);
            assert_eq!(r.verdict, Verdict::Pass, "{r:#?}");
        }
    }

    fn observed_adu(r: &CaseResult) -> Vec<u8> {
        match r.steps[0].observed.first() {
            Some(Received::Frame { bytes, .. }) => bytes.clone(),
            other => panic!("no frame: {other:?}"),
        }
    }

    /// The burst: on with every read answered normally; off, without blame, for a server that answers the
    /// ones behind the first Server Busy; off, and a FAIL, for one that answers only the first.
    #[test]
    fn the_burst_decides_whether_to_pipeline() {
        let (p, burst) = generic_runner_choosing(&[])
            .discover_pipelining(8)
            .expect("burst");
        assert_eq!(p.depth, 8, "{p:?}");
        assert_eq!(burst.expect("sent").1.verdict, Verdict::Pass);
        let (p, burst) = generic_runner_choosing(&["pipelined-server-busy=exception-06"])
            .discover_pipelining(8)
            .expect("burst");
        assert_eq!(p.depth, 1, "{p:?}");
        assert!(
            p.why.contains("answered 1 normally and 7 with Server Busy"),
            "{p:?}"
        );
        assert_eq!(burst.expect("sent").1.verdict, Verdict::Pass);
        let (p, burst) = generic_runner_choosing(&[])
            .discover_pipelining(1)
            .expect("burst");
        assert_eq!((p.depth, burst.is_none()), (1, true));
    }
}
