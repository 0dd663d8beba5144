//! A case run again where a damaged link may have made it FAIL: one step cannot tell a drive from its link (a
//! bit flipped on an RS-485 line, a frame cut short, a connection a small TCP/IP stack reset); a drive's fault
//! comes back, noise does not. [`run_over_link`] runs a case, and where it FAILed as a damaged link makes a
//! case fail ([`CaseResult::link_damage`]), again, with what the attempt changed put back and what it showed
//! of the drive's choices forgotten; [`LinkTally`] counts what happened for the run's `link:` line. Used by
//! the conformance run ([`crate::session`]) and the fuzz campaign ([`crate::campaign`]).

use std::time::Duration;

use crate::observe::{CaseResult, NO_ANSWER};
use crate::runner::{RunConfig, Runner};
use crate::targets::{Received, TargetError};
use codec::Framing;
use drives::profile::Profile;

/// Pauses before the attempts of a case the link may have damaged: the second comes after half the answer
/// timeout (at least the first of these, see [`run_over_link`]), the third after 1 s, the fourth after 3 s,
/// every one after that after 1 s. A bit flipped on a serial line is gone by the next frame; a TCP link that
/// dropped (a switch port, a small stack out of buffers) is back within a few seconds, and a drive's stack
/// may refuse connects for a moment after it. On a line noisy enough to damage one frame in 50, a case of
/// 40 frames is damaged one time in two: it takes more than three more attempts to come through.
pub const LINK_PAUSES: [Duration; 4] = [
    Duration::from_millis(100),
    Duration::from_secs(1),
    Duration::from_secs(3),
    Duration::from_secs(1),
];

/// The cases of a run that were run again because the link may have damaged them.
#[derive(Default)]
pub(crate) struct LinkTally {
    /// Cases run again.
    again: usize,
    /// Of them, those that came through whole at a later attempt.
    through: usize,
    /// Of them, those judged at their first attempt: it FAILed the same way again, or an answer to it came
    /// late (the drive's own).
    own: usize,
    /// Kinds of case whose damage was the drive's own (see [`LinkDamage::kind`]): another case of the kind
    /// that FAILs the same way is judged at its first attempt (a generated or fuzz run has many).
    own_kinds: std::collections::BTreeSet<(String, usize, &'static str, Vec<u8>)>,
}

impl LinkTally {
    pub(crate) fn note(&self) -> Option<String> {
        (self.again > 0).then(|| {
            format!(
                "link: {} case(s) run again after an attempt that FAILed as a damaged link would make it (no answer, part of a frame, a frame whose CRC does not check, a closed connection): {} came through whole at a later attempt (a damaged link, or a drive that did not answer for a while: that attempt is judged), {} FAILed the same way again or answered late (the drive's own: the first attempt is judged), {} otherwise (the first attempt is judged); --link-retries 0 judges every first attempt",
                self.again,
                self.through,
                self.own,
                self.again - self.through - self.own
            )
        })
    }
}

/// Run `case`, and where it FAILed in a way a damaged link gives as well as a faulty drive
/// ([`CaseResult::link_damage`]) on a real target, run it again (at most [`crate::runner::Timing::link_retries`] times), with
/// what the attempt changed put back first (`keeper`, for a case that touches kept parameters) and what it
/// showed of the drive's choices forgotten. One step cannot tell a drive from its link; a drive's fault comes
/// back, noise does not. The case is judged at the first attempt that comes through whole; at its first
/// attempt where an answer to it came late (during the pause after it: the drive answered, no frame was
/// lost), where a later attempt FAILs the same way as the first or as the one before it (the drive's own), or
/// where none comes through. Not run again: a case the mid-case watch stopped on a connection that no longer
/// answers while a new one does (a drive that hangs a connection: its own). The result says which attempt
/// is judged and what the others saw, and carries their bytes on the wire.
pub(crate) fn run_over_link(
    runner: &mut Runner,
    mut keeper: Option<&mut crate::restore::Keeper>,
    case: &crate::cases::Case,
    profile: &Profile,
    cfg: &RunConfig,
    tally: &mut LinkTally,
) -> Result<CaseResult, TargetError> {
    let retries = if cfg.is_sim {
        0
    } else {
        cfg.timing.link_retries as usize
    };
    if retries > 0 {
        runner.mark_choices();
    }
    let first = runner.run_case(case)?;
    let framing = runner.framing();
    let Some(damage) = LinkDamage::of(&first, framing).filter(|_| retries > 0) else {
        return Ok(first);
    };
    if tally.own_kinds.contains(&damage.kind(&case.id)) {
        let mut out = first;
        note_attempts(
            &mut out,
            format!(
                "not run again: {}, as a case of its kind did before at every attempt (the drive's own)",
                damage.told(1)
            ),
        );
        return Ok(out);
    }
    // Modbus/TCP: the answer to the unanswered step came during a later step of the case (noted there as
    // late): the drive answered, no frame was lost.
    if damage.what == NO_ANSWER
        && first.steps[damage.step]
            .sent
            .as_deref()
            .is_some_and(|sent| runner.answered_late(sent))
    {
        let seen = [damage.told(1)];
        let (wire, duration) = (first.wire.clone(), first.duration);
        return Ok(judged_first(
            first,
            (wire, duration, &seen),
            "whose answer came late, during a later step (the drive answered: no frame was lost; not run again)",
        ));
    }
    tally.again += 1;
    let mut seen = vec![damage.told(1)];
    let mut shown = vec![damage];
    let mut wire = first.wire.clone();
    let mut duration = first.duration;
    let first_pause = (cfg.timing.timeout / 2).max(LINK_PAUSES[0]);
    let pauses = std::iter::once(first_pause)
        .chain(LINK_PAUSES[1..3].iter().copied())
        .chain(std::iter::repeat(LINK_PAUSES[3]));
    for (n, pause) in pauses.take(retries).enumerate() {
        let attempt = n + 2;
        // The pause first, then the keeper's read-back: an answer that comes late, right after the attempt,
        // would otherwise come while the keeper's read is out, be noted there as late, and not be seen here.
        let came = runner.came_within(pause);
        if came && shown.last().is_some_and(|d| d.what == NO_ANSWER) {
            tally.own += 1;
            seen.push(format!(
                "after it, bytes came within {} ms",
                pause.as_millis()
            ));
            return Ok(judged_first(
                first,
                (wire, duration, &seen),
                "whose answer came late (the drive answered: no frame was lost; not run again)",
            ));
        }
        if let Some(k) = keeper.as_deref_mut() {
            let put_back = k.taken(case, runner.refused_writes());
            k.after_case(runner, &case.id, &put_back, profile)?;
        }
        // What the attempt before showed of the drive's choices is not held against it.
        runner.forget_attempt();
        let r = match runner.run_case(case) {
            Ok(r) => r,
            // A link still down: a connect refused, a serial error; the next attempt waits longer.
            Err(e) => {
                seen.push(format!("attempt {attempt}: {e}"));
                continue;
            }
        };
        duration += r.duration;
        let Some(d) = LinkDamage::of(&r, framing) else {
            tally.through += 1;
            let mut out = r;
            let mut all = std::mem::take(&mut wire);
            all.append(&mut out.wire);
            out.wire = all;
            out.duration = duration;
            note_attempts(
                &mut out,
                format!(
                    "judged at attempt {attempt}, the first whole one: the attempts before FAILed as a damaged link makes a case fail ({}), run again after {} ms",
                    seen.join("; "),
                    pause.as_millis()
                ),
            );
            return Ok(out);
        };
        seen.push(d.told(attempt));
        wire.extend(r.wire);
        let times = shown.iter().filter(|s| **s == d).count() + 1;
        if times >= d.proves_after() {
            tally.own += 1;
            tally.own_kinds.insert(d.kind(&case.id));
            return Ok(judged_first(
                first,
                (wire, duration, &seen),
                "as later attempts FAILed the same way again (the drive's own, not its link's)",
            ));
        }
        shown.push(d);
    }
    Ok(judged_first(
        first,
        (wire, duration, &seen),
        "as no later attempt came through whole",
    ))
}

/// How an attempt of a case FAILed as a damaged link makes a case fail: at which step, what came (see
/// [`crate::observe::StepResult::link_damage`]), and the bytes that came there.
#[derive(Clone, Debug, PartialEq, Eq)]
struct LinkDamage {
    step: usize,
    what: &'static str,
    bytes: Vec<u8>,
}

impl LinkDamage {
    fn of(r: &CaseResult, framing: Framing) -> Option<Self> {
        let (step, what) = r.link_damage(framing)?;
        // What came damaged: whole frames are left out (their transaction ids differ from one attempt to the
        // next; a frame of several requests sent together may be answered in part).
        let bytes = r.steps[step]
            .observed
            .iter()
            .flat_map(|o| match o {
                Received::Frame { bytes, .. }
                    if framing == Framing::Rtu && !codec::rtu::crc_ok(bytes) =>
                {
                    bytes.clone()
                }
                Received::Frame { .. } => Vec::new(),
                Received::Garbage { bytes, .. } => bytes.clone(),
                Received::Silence { partial, .. } | Received::Closed { partial, .. } => {
                    partial.clone()
                }
            })
            .collect();
        Some(Self { step, what, bytes })
    }

    /// The kind of case it happened in (a generated case's kind: `gen/3/204/diag-batch` is `diag-batch`; a
    /// catalog case is its own kind), with where and what.
    fn kind(&self, case: &str) -> (String, usize, &'static str, Vec<u8>) {
        let kind = if case.starts_with("gen/") {
            case.rsplit('/').next().unwrap_or(case)
        } else {
            case
        };
        (kind.to_string(), self.step, self.what, self.bytes.clone())
    }

    /// How many attempts must show it for it to be the drive's own: two where bytes came (noise does not
    /// damage a frame into the same bytes twice), three where nothing came (a damaged request, or an answer
    /// lost with its connection, twice at the same step is rare, three times rarer still).
    fn proves_after(&self) -> usize {
        if self.bytes.is_empty() { 3 } else { 2 }
    }

    fn told(&self, attempt: usize) -> String {
        format!("attempt {attempt}: {} at step {}", self.what, self.step + 1)
    }
}

/// The first attempt of a case run again, judged (see [`run_over_link`]), with the bytes of every attempt, the
/// time they took, and what each saw.
fn judged_first(
    mut first: CaseResult,
    (wire, duration, seen): (Vec<crate::observe::WireEvent>, Duration, &[String]),
    why: &str,
) -> CaseResult {
    first.wire = wire;
    first.duration = duration;
    let told = format!("judged at attempt 1, {why}: {}", seen.join("; "));
    note_attempts(&mut first, told);
    first
}

/// Say in a case's result which attempt it is and what the others saw (the first step's note).
fn note_attempts(r: &mut CaseResult, told: String) {
    if let Some(s) = r.steps.first_mut() {
        s.note = format!("{} ({told})", s.note);
    } else {
        r.reason = Some(told);
    }
}
