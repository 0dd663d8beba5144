//! The oracle: the reference model's answer is what a conforming drive answers. A response passes when it
//! matches in structure, and in value where the step says the value is deterministic; or when it is what
//! another admissible choice of a freedom (where the specs and manuals leave one) gives ([`freedoms`]).

pub mod choices;
pub mod freedoms;

use crate::cases::{Compare, Level, Verdict};
use crate::targets::Received;
use codec::{
    Decoded, Direction, FieldValue, Framing, Pdu, Request, Response, decode_any, describe,
    hex_spaced,
};
use drives::profile::{Profile, Table, WordOrder};
use drives::requirements::{Freedom, FreedomKind};

pub use choices::{Choice, ChoiceLog};
pub use freedoms::{Shown, StepContext};

/// How bad a finding is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    /// Worth saying, not wrong (a function served that the profile does not list).
    Info,
    /// The harness could not establish the step's precondition (e.g. keep a split request's pieces
    /// within t1.5 on a busy machine): nothing can be concluded about the target.
    Inconclusive,
    /// A SHOULD of the specs (or a tolerated deviation) is broken.
    Should,
    /// The target answers "illegal function" where the profile says the function exists.
    Unimplemented,
    /// A MUST is broken.
    Must,
}

/// One thing wrong with a response.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Finding {
    pub severity: Severity,
    pub text: String,
}

fn must(text: impl Into<String>) -> Finding {
    Finding {
        severity: Severity::Must,
        text: text.into(),
    }
}

fn should(text: impl Into<String>) -> Finding {
    Finding {
        severity: Severity::Should,
        text: text.into(),
    }
}

/// What was sent in one frame, for echo checks.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Sent {
    pub tid: Option<u16>,
    pub unit: u8,
    pub pdu: Vec<u8>,
}

/// Describe a frame briefly: hex and, where it decodes, its function and fields.
pub fn brief(framing: Framing, bytes: &[u8]) -> String {
    brief_decoded(framing, bytes, None)
}

/// [`brief`], with `bytes` already decoded when `decoded` is `Some` (their decoding as a response under
/// `framing`).
fn brief_decoded(framing: Framing, bytes: &[u8], decoded: Option<&Decoded>) -> String {
    let mut out = hex_spaced(bytes);
    let again;
    let decoded = match decoded {
        Some(d) => Some(d),
        None => {
            again = decode_any(bytes, framing, Direction::Response).ok();
            again.as_ref()
        }
    };
    if let Some(d) = decoded {
        out.push_str(" (");
        summary_into(&d.pdu, &mut out);
        out.push(')');
    }
    out
}

/// The fields of a PDU, `FC 0xNN, name value, …`.
fn summary(p: &Pdu) -> String {
    let mut out = String::new();
    summary_into(p, &mut out);
    out
}

/// [`summary`] appended to `out`, written in place (no string per field).
fn summary_into(p: &Pdu, out: &mut String) {
    use std::fmt::Write as _;
    for (i, f) in describe(p).iter().enumerate() {
        if i > 0 {
            out.push_str(", ");
        }
        // Writing to a String cannot fail.
        let _ = match (&f.name, &f.value) {
            (&"function", FieldValue::Int(v)) => write!(out, "FC 0x{v:02X}"),
            (n, v) => write!(out, "{n} {v}"),
        };
    }
}

fn field_diff(exp: &Pdu, obs: &Pdu) -> Vec<String> {
    let e = describe(exp);
    let o = describe(obs);
    let mut out = Vec::new();
    for f in &e {
        match o.iter().find(|g| g.name == f.name) {
            Some(g) if g.value == f.value => {}
            Some(g) => out.push(format!("{}: expected {}, got {}", f.name, f.value, g.value)),
            None => out.push(format!("{}: expected {}, absent", f.name, f.value)),
        }
    }
    out
}

/// What the oracle judges at one step: the request sent, the drive's answer and the reference drive's.
#[derive(Clone, Copy, Debug)]
pub struct Observation<'a> {
    pub framing: Framing,
    pub sent: &'a Sent,
    /// The reference drive's answer; `None`: it stays silent.
    pub expected: Option<&'a [u8]>,
    /// What the drive did.
    pub observed: &'a Received,
    pub compare: &'a Compare,
    pub profile: &'a Profile,
    /// The reference drive closed the connection.
    pub reference_closed: bool,
}

/// Judge one observation against the reference answer, reading 32-bit register values in `order`.
pub fn judge(o: &Observation<'_>, order: WordOrder) -> Vec<Finding> {
    judge_with(o, order, None)
}

/// A reference answer decoded once, for judging several observations against it ([`judge_answer`]).
#[derive(Clone, Debug)]
pub struct Answer<'a> {
    framing: Framing,
    bytes: &'a [u8],
    /// `bytes` decoded as a response under `framing`; `None` where they do not decode.
    decoded: Option<Decoded>,
}

impl<'a> Answer<'a> {
    /// The reference's answer `bytes` under `framing`, decoded.
    pub fn new(framing: Framing, bytes: &'a [u8]) -> Self {
        Answer {
            framing,
            bytes,
            decoded: decode_any(bytes, framing, Direction::Response).ok(),
        }
    }
}

/// [`judge`] with the reference answer decoded beforehand: the same findings as `judge(o, order)`. `answer`
/// is used where it is the observation's reference answer (`o.expected` holds the same bytes, under the same
/// framing); otherwise the answer is decoded as `judge` does.
pub fn judge_answer(o: &Observation<'_>, order: WordOrder, answer: &Answer<'_>) -> Vec<Finding> {
    let decoded = (o.framing == answer.framing && o.expected == Some(answer.bytes))
        .then_some(answer.decoded.as_ref())
        .flatten();
    judge_with(o, order, decoded)
}

/// [`judge`]; `exp_decoded`, where `Some`, is `o.expected` decoded as a response under `o.framing`.
fn judge_with(
    o: &Observation<'_>,
    order: WordOrder,
    exp_decoded: Option<&Decoded>,
) -> Vec<Finding> {
    if *o.compare == Compare::RejectOrIgnore
        && let Some(findings) = reject_or_ignore(o.framing, o.sent, o.expected, o.observed)
    {
        return findings;
    }
    match frames_to_compare(
        o.framing,
        o.expected,
        o.observed,
        o.reference_closed,
        exp_decoded,
    ) {
        Ok((exp, obs)) => compare_frames(
            o.framing,
            o.sent,
            (exp, exp_decoded),
            obs,
            o.compare,
            o.profile,
            order,
        ),
        Err(findings) => findings,
    }
}

/// The judgement of one observation with the freedoms applied.
#[derive(Clone, Debug, Default)]
pub struct Judged {
    pub findings: Vec<Finding>,
    /// The values the target showed for freedoms at this observation.
    pub shown: Vec<Shown>,
    /// Where several freedoms' alternatives admit the observation, the others after the first, in order:
    /// the caller may take the one that agrees with what the drive chose before (see
    /// [`Judged::agreeing`]).
    pub others: Vec<Judged>,
}

impl Judged {
    /// The first explanation of the observation (this one, then `others`) whose shown values all agree with
    /// `agrees`; this one when none does.
    pub fn agreeing(mut self, agrees: impl Fn(&Shown) -> bool) -> Judged {
        let others = std::mem::take(&mut self.others);
        if self.shown.iter().all(&agrees) {
            return self;
        }
        others
            .into_iter()
            .find(|j| j.shown.iter().all(&agrees))
            .unwrap_or(self)
    }
}

/// True when findings make a step fail (or be unimplemented): what a freedom may excuse.
fn fails(findings: &[Finding]) -> bool {
    findings
        .iter()
        .any(|f| matches!(f.severity, Severity::Must | Severity::Unimplemented))
}

/// Judge one observation against the reference answer, accepting what another admissible value of an
/// applicable freedom gives (see [`freedoms`]).
pub fn judge_admitting(
    o: &Observation<'_>,
    applicable: &[&Freedom],
    cx: &StepContext<'_>,
) -> Judged {
    let Observation {
        framing,
        sent,
        expected,
        observed,
        compare,
        profile,
        reference_closed,
    } = *o;
    // Where the reference stays silent and an outcome freedom about the step lists `close`, a close is as
    // good as the reference's own (not "closed where the reference stays silent").
    let close_admitted = matches!(observed, Received::Closed { .. })
        && applicable
            .iter()
            .any(|f| freedoms::outcome_shown(f, cx, "close").is_some());
    let strict = judge(
        &Observation {
            reference_closed: reference_closed || close_admitted,
            ..*o
        },
        profile.device.word_order,
    );
    let response = |b: &[u8]| match decode_any(b, framing, Direction::Response).map(|d| d.pdu) {
        Ok(Pdu::Response(r)) => Some(r),
        _ => None,
    };
    let exp = expected.and_then(response);
    if !fails(&strict) {
        let obs = match observed {
            Received::Frame { bytes, .. } => response(bytes),
            _ => None,
        };
        // The kind of answer the drive gave where it differs from the reference's and a request it had to
        // reject or ignore admits either (an outcome freedom): the drive's choice, shown.
        let observed_kind = outcome_kind(framing, observed);
        let reference_kind = match (&exp, reference_closed) {
            (Some(e), _) => Some(response_kind(e)),
            (None, true) => Some("close".to_string()),
            (None, false) => Some("silence".to_string()),
        };
        let shown = applicable
            .iter()
            .filter_map(|f| match (&observed_kind, &reference_kind) {
                (Some(o), Some(r)) if o != r && f.kind == FreedomKind::Outcome => {
                    freedoms::outcome_shown(f, cx, o)
                }
                // A counter read whose value the step does not compare (one not cleared before it,
                // which counts traffic the run did not see) shows no reading of the counters.
                _ if f.kind == FreedomKind::Counter && !matches!(compare, Compare::Exact) => None,
                _ => freedoms::observed_shown(f, exp.as_ref(), obs.as_ref())
                    .or_else(|| freedoms::reference_shown(f, cx, exp.as_ref(), obs.as_ref())),
            })
            .collect();
        return Judged {
            findings: strict,
            shown,
            others: Vec::new(),
        };
    }
    // A frame only another reading of a manual decodes (FC 0x41 with a 2-byte byte count): judged as the
    // codec's form of the same answer, every other freedom applied, and the reading recorded.
    if let Received::Frame { bytes, .. } = observed
        && response(bytes).is_none()
        && let Some(f) = applicable
            .iter()
            .find(|f| f.id == drives::choices::ids::FC41_BYTE_COUNT_WIDTH)
        && let Some(r) = crate::readings::other_reading(framing, bytes)
        && let Some(b) = frame_like(framing, Some(bytes), sent, &r)
    {
        let mut again = judge_admitting(
            &Observation {
                observed: &Received::frame(b),
                ..*o
            },
            applicable,
            cx,
        );
        if !fails(&again.findings) {
            again.shown.push(freedoms::shown_value(f, "", "2-byte"));
            return again;
        }
    }
    let obs = match observed {
        Received::Frame { bytes, .. } => {
            response(bytes).or_else(|| crate::readings::other_reading(framing, bytes))
        }
        _ => None,
    };
    // Every alternative that admits the observation, in the order of the freedoms.
    let mut passing: Vec<Judged> = Vec::new();
    let gateway_id = drives::choices::ids::GATEWAY_NO_RESPONSE;
    let gateway = applicable.iter().find(|f| f.id == gateway_id && cx.gateway);
    for f in applicable {
        if f.kind == FreedomKind::WordOrder {
            let other = match profile.device.word_order {
                WordOrder::HighFirst => WordOrder::LowFirst,
                WordOrder::LowFirst => WordOrder::HighFirst,
            };
            let again = judge(o, other);
            if !fails(&again) {
                let name = match other {
                    WordOrder::HighFirst => "high-first",
                    WordOrder::LowFirst => "low-first",
                };
                passing.push(Judged {
                    findings: again,
                    shown: vec![freedoms::shown_value(f, "", name)],
                    others: Vec::new(),
                });
            }
            continue;
        }
        for alt in freedoms::alternatives(f, cx, exp.as_ref(), obs.as_ref()) {
            let frame = match &alt.answer {
                Some(r) => match frame_like(framing, expected, sent, r) {
                    Some(b) => Some(b),
                    None => continue,
                },
                None => None,
            };
            let compare = if alt.values_free {
                Compare::Structure
            } else {
                compare.clone()
            };
            let observed_as = match (observed, &obs) {
                // A frame only another reading decodes is judged as that reading's bytes.
                (Received::Frame { bytes, .. }, Some(r)) if response(bytes).is_none() => {
                    match frame_like(framing, Some(bytes), sent, r) {
                        Some(b) => Received::frame(b),
                        None => observed.clone(),
                    }
                }
                _ => observed.clone(),
            };
            let again = judge(
                &Observation {
                    expected: frame.as_deref(),
                    observed: &observed_as,
                    compare: &compare,
                    reference_closed: reference_closed || alt.closes(),
                    ..*o
                },
                profile.device.word_order,
            );
            if !fails(&again) {
                let mut findings = again;
                if let Some(n) = alt.note {
                    findings.push(Finding {
                        severity: Severity::Info,
                        text: n,
                    });
                }
                passing.push(Judged {
                    findings,
                    shown: vec![alt.shown],
                    others: Vec::new(),
                });
            }
        }
    }
    // Where a freedom lets the drive be silent and a gateway is between, the gateway's answer to that
    // silence (`gateway-no-response`): both choices shown.
    if let Some(gw) = gateway
        && obs.as_ref().is_some_and(Response::is_exception)
    {
        for f in applicable
            .iter()
            .filter(|f| f.id != gateway_id && f.kind != FreedomKind::WordOrder)
        {
            let silences = freedoms::alternatives(f, cx, exp.as_ref(), None)
                .into_iter()
                .filter(|a| a.answer.is_none() && !a.closes());
            for alt in silences {
                for g in freedoms::alternatives(gw, cx, None, obs.as_ref()) {
                    let Some(frame) = g
                        .answer
                        .as_ref()
                        .and_then(|r| frame_like(framing, expected, sent, r))
                    else {
                        continue;
                    };
                    let again = judge(
                        &Observation {
                            expected: Some(&frame),
                            compare: &Compare::Exact,
                            ..*o
                        },
                        profile.device.word_order,
                    );
                    if !fails(&again) {
                        passing.push(Judged {
                            findings: again,
                            shown: vec![alt.shown.clone(), g.shown],
                            others: Vec::new(),
                        });
                    }
                }
            }
        }
    }
    if passing.is_empty() {
        return Judged {
            findings: strict,
            shown: vec![],
            others: Vec::new(),
        };
    }
    let mut first = passing.remove(0);
    first.others = passing;
    first
}

/// The kind of answer an observation is, as outcome freedoms name it: `response`, `exception-XX`, `silence`
/// (nothing, not even a partial frame), `close` (Modbus/TCP); `None` for garbage.
/// The kind of answer observed, as outcome freedoms name their values: `silence`, `close`, `response`,
/// `exception-XX` (`None`: garbage, or a silence with bytes in it).
pub fn outcome_kind(framing: Framing, observed: &Received) -> Option<String> {
    match observed {
        Received::Silence { partial, .. } if partial.is_empty() => Some("silence".into()),
        Received::Closed { .. } if framing == Framing::Tcp => Some("close".into()),
        Received::Frame { bytes, .. } => {
            match decode_any(bytes, framing, Direction::Response).map(|d| d.pdu) {
                Ok(Pdu::Response(r)) => Some(response_kind(&r)),
                _ => None,
            }
        }
        _ => None,
    }
}

fn response_kind(r: &Response) -> String {
    match r {
        Response::Exception { code, .. } => format!("exception-{:02X}", code.0),
        _ => "response".into(),
    }
}

/// A response frame carrying `pdu` with the addressing of `like` (the reference's frame, or else the
/// request's transaction id and unit).
fn frame_like(
    framing: Framing,
    like: Option<&[u8]>,
    sent: &Sent,
    pdu: &Response,
) -> Option<Vec<u8>> {
    let body = pdu.to_bytes().ok()?;
    let mut out = Vec::new();
    match framing {
        Framing::Tcp => {
            let (tid, unit) = match like.and_then(codec::tcp::Mbap::parse) {
                Some(h) => (h.transaction_id, h.unit_id),
                None => (sent.tid.unwrap_or(0), sent.unit),
            };
            codec::tcp::encode_adu(tid, unit, &body, &mut out).ok()?;
        }
        _ => {
            let unit = like.and_then(|b| b.first().copied()).unwrap_or(sent.unit);
            codec::rtu::encode_adu(unit, &body, &mut out).ok()?;
        }
    }
    Some(out)
}

/// A request that must be rejected or ignored: silence, a close (TCP) or any exception settles it; `None`
/// when the observation needs the usual comparison.
fn reject_or_ignore(
    framing: Framing,
    sent: &Sent,
    expected: Option<&[u8]>,
    observed: &Received,
) -> Option<Vec<Finding>> {
    let mut out = Vec::new();
    match observed {
        Received::Silence { partial, .. } if partial.is_empty() => Some(out),
        Received::Closed { .. } if framing == Framing::Tcp => Some(out),
        Received::Frame { bytes, .. } if expected.is_none() => {
            // The reference ignores it; a target may reject it instead, with any exception code, but in the
            // exception form of the request's function code (App 7: the function code with its MSB set).
            let exception = match decode_any(bytes, framing, Direction::Response).map(|d| d.pdu) {
                Ok(Pdu::Response(r)) if r.is_exception() => Some(r.function()),
                _ => None,
            };
            match (exception, sent.pdu.first()) {
                (None, _) => out.push(must(format!(
                    "an invalid request was answered as valid: {}",
                    brief(framing, bytes)
                ))),
                (Some(f), Some(&fc)) if fc < 0x80 && f.0 != fc | 0x80 => out.push(should(format!(
                    "the request is rejected, but with function code 0x{:02X}, not the request's 0x{fc:02X} + 0x80 (App 7)",
                    f.0
                ))),
                _ => {}
            }
            Some(out)
        }
        _ => None,
    }
}

/// The reference's frame and the observed one, when both are frames; otherwise the verdict on the
/// silence, close or garbage that came (or should have come) instead. `exp_decoded`: `expected` decoded,
/// where the caller has it.
fn frames_to_compare<'a>(
    framing: Framing,
    expected: Option<&'a [u8]>,
    observed: &'a Received,
    reference_closed: bool,
    exp_decoded: Option<&Decoded>,
) -> Result<(&'a [u8], &'a [u8]), Vec<Finding>> {
    let mut out = Vec::new();
    match (expected, observed) {
        (None, Received::Silence { partial, .. }) => {
            if !partial.is_empty() {
                out.push(must(format!(
                    "expected no response, but {} stray byte(s) arrived: {}",
                    partial.len(),
                    hex_spaced(partial)
                )));
            }
            Err(out)
        }
        (None, Received::Closed { .. }) => {
            if !reference_closed {
                out.push(should("the connection was closed where the reference drive stays silent and keeps it open"));
            }
            Err(out)
        }
        (None, Received::Frame { bytes, .. }) => {
            out.push(must(format!(
                "expected no response, got {}",
                brief(framing, bytes)
            )));
            Err(out)
        }
        (None, Received::Garbage { bytes, reason, .. }) => {
            out.push(must(format!(
                "expected no response, got malformed bytes {} ({reason})",
                hex_spaced(bytes)
            )));
            Err(out)
        }
        (Some(e), Received::Silence { partial, .. }) => {
            let tail = if partial.is_empty() {
                String::new()
            } else {
                format!(
                    "; {} byte(s) of an incomplete frame arrived: {}",
                    partial.len(),
                    hex_spaced(partial)
                )
            };
            out.push(must(format!(
                "no response within the timeout; the reference answers {}{tail}",
                brief_decoded(framing, e, exp_decoded)
            )));
            Err(out)
        }
        (Some(e), Received::Closed { .. }) => {
            out.push(must(format!(
                "the connection was closed instead of an answer; the reference answers {}",
                brief_decoded(framing, e, exp_decoded)
            )));
            Err(out)
        }
        (Some(_), Received::Garbage { bytes, reason, .. }) => {
            out.push(must(format!(
                "malformed response {}: {reason}",
                hex_spaced(bytes)
            )));
            Err(out)
        }
        (Some(e), Received::Frame { bytes, .. }) => Ok((e, bytes.as_slice())),
    }
}

/// `bytes` decoded as a response under `framing`, or `pre` where the caller has that decoding already.
fn decoded<'a>(
    framing: Framing,
    bytes: &[u8],
    pre: Option<&'a Decoded>,
) -> Result<std::borrow::Cow<'a, Decoded>, codec::DecodeError> {
    match pre {
        Some(d) => Ok(std::borrow::Cow::Borrowed(d)),
        None => decode_any(bytes, framing, Direction::Response).map(std::borrow::Cow::Owned),
    }
}

/// Compare two decoded frames: they decode, the echoes match (transaction id, unit), exceptions agree, then
/// the compare mode of the step. `exp` is the reference's frame and, where the caller has it, its decoding.
fn compare_frames(
    framing: Framing,
    sent: &Sent,
    (exp, exp_pre): (&[u8], Option<&Decoded>),
    obs: &[u8],
    compare: &Compare,
    profile: &Profile,
    order: WordOrder,
) -> Vec<Finding> {
    let mut out = Vec::new();
    // A reply identical to the reference's carries the right echoes by construction, and decodes as it
    // does: decoded once (the reference's own answer judged against itself, a drive that answers as it).
    let identical = obs == exp;
    let obs_d = match decoded(framing, obs, exp_pre.filter(|_| identical)) {
        Ok(d) => d,
        Err(err) => {
            out.push(must(format!(
                "response {} does not decode: {err}",
                hex_spaced(obs)
            )));
            return out;
        }
    };
    let exp_own;
    let exp_d: &Decoded = if identical {
        &obs_d
    } else {
        match decoded(framing, exp, exp_pre) {
            Ok(d) => {
                exp_own = d;
                &exp_own
            }
            Err(_) => {
                out.push(must(format!(
                    "internal: the reference answer {} does not decode",
                    hex_spaced(exp)
                )));
                return out;
            }
        }
    };
    let obs_d: &Decoded = &obs_d;
    if let (Some(t), Some(got)) = (sent.tid, obs_d.transaction_id)
        && t != got
        && !identical
    {
        out.push(must(format!(
            "transaction id 0x{got:04X} is not the request's 0x{t:04X}"
        )));
    }
    if let Some(u) = obs_d.unit
        && u != sent.unit
        && !identical
    {
        out.push(must(format!(
            "unit id / slave address {u} is not the request's {}",
            sent.unit
        )));
    }
    let (Pdu::Response(e), Pdu::Response(o)) = (&exp_d.pdu, &obs_d.pdu) else {
        return out;
    };
    // The manual line that lists the function, where the profile is a manual's (the generic profile's
    // functions are the spec's optional ones).
    let listed = profile
        .function(e.function().without_exception_bit())
        .filter(|f| f.confirmed)
        .and_then(|f| f.line);
    if let Some(f) = exception_mismatch(e, o, &exp_d.pdu, &obs_d.pdu, listed) {
        out.extend(f);
        return out;
    }
    if e.function() != o.function() {
        out.push(must(format!(
            "function code 0x{:02X} is not the request's 0x{:02X}",
            o.function().0,
            e.function().0
        )));
        return out;
    }
    match compare {
        Compare::Exact => {
            if exp_d.pdu != obs_d.pdu {
                let diffs = field_diff(&exp_d.pdu, &obs_d.pdu);
                out.push(must(format!(
                    "value differs from the reference: {}",
                    if diffs.is_empty() {
                        format!("got {}", hex_spaced(obs))
                    } else {
                        diffs.join("; ")
                    }
                )));
            }
        }
        Compare::Structure => {
            structure(e, o, &mut out);
            if out.is_empty() {
                padding_zero(&sent.pdu, o, &mut out);
                identification_consistent(&sent.pdu, o, &mut out);
            }
        }
        Compare::InRange => {
            structure(e, o, &mut out);
            if out.is_empty() {
                in_range(&sent.pdu, o, profile, order, &mut out);
            }
        }
        Compare::Near { tolerance } => {
            structure(e, o, &mut out);
            if out.is_empty() {
                near(&sent.pdu, e, o, profile, order, *tolerance, &mut out);
            }
        }
        Compare::Any | Compare::RejectOrIgnore => {}
    }
    out
}

/// The first address of a register read (FC 03, 04) and whether it reads the input table: where the profile
/// has no input register of its own, FC 04 reads the holding registers' map (the SD2x, line 327). `None` for
/// another request.
fn register_read(req: &[u8], p: &Profile) -> Option<(u16, bool)> {
    match Request::decode(req) {
        Ok(Request::ReadHoldingRegisters { address, .. }) => Some((address, false)),
        Ok(Request::ReadInputRegisters { address, .. }) => Some((
            address,
            p.registers
                .iter()
                .any(|r| r.get_ref().table == Table::Input),
        )),
        _ => None,
    }
}

/// The register values of a read response `o` that lie farther than `tolerance` from the reference's `e`
/// ([`Compare::Near`]): each register of the profile the read covers as one value of its width, in the
/// drive's word order, signed where the profile says; a register the profile lacks as a word.
fn near(
    req: &[u8],
    e: &Response,
    o: &Response,
    p: &Profile,
    order: WordOrder,
    tolerance: u32,
    out: &mut Vec<Finding>,
) {
    let Some((address, input)) = register_read(req, p) else {
        return;
    };
    let values = |r: &Response| match r {
        Response::ReadHoldingRegisters { values } | Response::ReadInputRegisters { values } => {
            Some(values.clone())
        }
        _ => None,
    };
    let (Some(exp), Some(obs)) = (values(e), values(o)) else {
        return;
    };
    let mut i = 0usize;
    while i < obs.len().min(exp.len()) {
        let a = address.wrapping_add(i as u16);
        let r = p
            .register_at(a, input)
            .filter(|r| r.address == a && (r.table != Table::Input || input));
        let (w, signed) = match r {
            Some(r) if r.width == 2 && i + 1 < obs.len() => (2, r.signed),
            Some(r) => (1, r.signed),
            None => (1, false),
        };
        let value = |v: &[u16]| -> i64 {
            match (w, signed) {
                (2, true) => i64::from(order.join(v[i], v[i + 1]) as i32),
                (2, false) => i64::from(order.join(v[i], v[i + 1])),
                (_, true) => i64::from(v[i] as i16),
                _ => i64::from(v[i]),
            }
        };
        let (x, y) = (value(&exp), value(&obs));
        if x.abs_diff(y) > u64::from(tolerance) {
            out.push(must(format!(
                "0x{a:04X}{} reads {y} where the reference reads {x}: more than {tolerance} apart",
                r.map(|r| format!(" {}", r.name)).unwrap_or_default()
            )));
        }
        i += w;
    }
}

/// Where the reference or the target answers with an exception: the findings, or `None` when neither does.
/// "Illegal function" for a function the profile has is graded UNIMPLEMENTED: the target lacks it; but where
/// the drive's manual lists the function (`listed`: its line), serving it is a requirement of the manual, and
/// refusing a request the reference serves with 01 is a FAIL.
fn exception_mismatch(
    e: &Response,
    o: &Response,
    exp: &Pdu,
    obs: &Pdu,
    listed: Option<u32>,
) -> Option<Vec<Finding>> {
    let lacks = |same_function: bool| {
        matches!(o, Response::Exception { code, .. } if code.0 == 1) && same_function
    };
    let differs = || {
        format!(
            "exception {} where the reference answers {}",
            summary(obs),
            summary(exp)
        )
    };
    let finding = |unimplemented: bool, text: String| {
        if unimplemented {
            Finding {
                severity: Severity::Unimplemented,
                text,
            }
        } else {
            must(text)
        }
    };
    match (e.is_exception(), o.is_exception()) {
        (true, true) if exp == obs => Some(vec![]),
        (true, true) => Some(vec![finding(
            lacks(o.function().without_exception_bit() == e.function().without_exception_bit()),
            differs(),
        )]),
        (true, false) => Some(vec![must(format!(
            "answered {} where the reference answers with exception {}",
            summary(obs),
            summary(exp)
        ))]),
        (false, true) => {
            let lacking = lacks(o.function().without_exception_bit() == e.function());
            Some(vec![match listed.filter(|_| lacking) {
                Some(line) => must(format!(
                    "{}: the manual lists function 0x{:02X} (manual line {line}), so the drive must serve it",
                    differs(),
                    e.function().0
                )),
                None => finding(lacking, differs()),
            }])
        }
        (false, false) => None,
    }
}

/// Same shape: counts, echoed addresses, object lists; data values free.
fn structure(e: &Response, o: &Response, out: &mut Vec<Finding>) {
    use Response::*;
    let bad = match (e, o) {
        (ReadCoils { data: a }, ReadCoils { data: b })
        | (ReadDiscreteInputs { data: a }, ReadDiscreteInputs { data: b }) => (a.len() != b.len())
            .then(|| format!("byte count {} where {} is required", b.len(), a.len())),
        (ReadHoldingRegisters { values: a }, ReadHoldingRegisters { values: b })
        | (ReadInputRegisters { values: a }, ReadInputRegisters { values: b })
        | (ReadWriteMultipleRegisters { values: a }, ReadWriteMultipleRegisters { values: b }) => {
            (a.len() != b.len())
                .then(|| format!("{} register(s) where {} were requested", b.len(), a.len()))
        }
        (
            Diagnostics {
                sub_function: a,
                data: da,
            },
            Diagnostics {
                sub_function: b,
                data: db,
            },
        ) => (a != b || da.len() != db.len()).then(|| {
            format!(
                "sub-function 0x{b:04X} / {} data bytes, expected 0x{a:04X} / {}",
                db.len(),
                da.len()
            )
        }),
        (CanOpen(a), CanOpen(b)) => (a.control != b.control
            || a.node_id != b.node_id
            || a.index != b.index
            || a.subindex != b.subindex
            || a.byte_count != b.byte_count
            || a.data.len() != b.data.len())
        .then(|| format!("object access header differs: expected {a:?}, got {b:?}")),
        (CanOpenError { sdo_code: a }, CanOpenError { sdo_code: b }) => {
            (a != b).then(|| format!("SDO error 0x{b:08X}, expected 0x{a:08X}"))
        }
        (ReadDeviceId(a), ReadDeviceId(b)) => {
            let ids =
                |d: &codec::DeviceIdResponse| d.objects.iter().map(|o| o.id).collect::<Vec<_>>();
            (a.read_code != b.read_code || ids(a) != ids(b) || a.more_follows != b.more_follows).then(|| {
                format!(
                    "identification: read code {} objects {:?} more-follows 0x{:02X}, expected read code {} objects {:?} more-follows 0x{:02X}",
                    b.read_code, ids(b), b.more_follows, a.read_code, ids(a), a.more_follows
                )
            })
        }
        (VendorRead { .. }, VendorRead { .. }) => None,
        // Answers, not echoes, of the serial-line and file functions (6.7-6.18): their lengths are the
        // structure, their values the device's (output states, counts, ids, record and queue contents).
        (ReadExceptionStatus { .. }, ReadExceptionStatus { .. })
        | (ReportServerId { .. }, ReportServerId { .. })
        | (ReadFifoQueue { .. }, ReadFifoQueue { .. }) => None,
        (GetCommEventCounter { .. }, GetCommEventCounter { status, .. })
        | (GetCommEventLog { .. }, GetCommEventLog { status, .. }) => {
            (!matches!(status, 0x0000 | 0xFFFF))
                .then(|| format!("status 0x{status:04X}: only 0x0000 and 0xFFFF are defined (6.9)"))
        }
        (ReadFileRecord { sub_responses: a }, ReadFileRecord { sub_responses: b }) => {
            let lens = |v: &[codec::FileRecordData]| {
                v.iter()
                    .map(|d| (d.reference_type, d.values.len()))
                    .collect::<Vec<_>>()
            };
            (lens(a) != lens(b)).then(|| {
                format!(
                    "file sub-responses (reference type, records) {:?}, expected {:?}",
                    lens(b),
                    lens(a)
                )
            })
        }
        (a, b) if std::mem::discriminant(a) == std::mem::discriminant(b) => {
            // Echo responses (FC 05, 06, 0F, 10, 42) carry the request's fields: they must match exactly.
            (a != b).then(|| format!("echo differs: expected {a:?}, got {b:?}"))
        }
        (a, b) => Some(format!("response layout {b:?} where {a:?} is expected")),
    };
    if let Some(t) = bad {
        out.push(must(t));
    }
}

/// FC 01/02: the bits of the last data byte past the quantity asked for are 0 (spec 6.1, 6.2: "padded with
/// zeros"), whatever the states of the bits read.
fn padding_zero(req: &[u8], o: &Response, out: &mut Vec<Finding>) {
    let quantity = match Request::decode(req) {
        Ok(Request::ReadCoils { quantity, .. } | Request::ReadDiscreteInputs { quantity, .. }) => {
            quantity
        }
        _ => return,
    };
    let data = match o {
        Response::ReadCoils { data } | Response::ReadDiscreteInputs { data } => data,
        _ => return,
    };
    let used = quantity % 8;
    if let Some(last) = data.last()
        && used != 0
        && last >> used != 0
    {
        out.push(must(format!(
            "padding bits not 0: last data byte 0x{last:02X} for {quantity} bits (the high {} bits must be 0)",
            8 - used
        )));
    }
}

/// FC 43 / MEI 0x0E: the conformity level a device declares agrees with what it answers (spec 6.21: the
/// level is 01 basic, 02 regular, 03 extended, stream access only, or 81-83 with individual access too;
/// objects 00-02 are basic, 03-7F regular, 80-FF extended; a device asked for more than its level answers
/// in accordance with its level). An object above the declared level, or an individual access (code 04)
/// answered by a device that declares stream access only, contradicts it.
fn identification_consistent(req: &[u8], o: &Response, out: &mut Vec<Finding>) {
    let Response::ReadDeviceId(d) = o else {
        return;
    };
    let level = d.conformity & 0x7F;
    if !(1..=3).contains(&level) || d.conformity & 0x80 != d.conformity & 0xF0 {
        out.push(must(format!(
            "identification: conformity level 0x{:02X} is none of 01-03, 81-83 (6.21)",
            d.conformity
        )));
        return;
    }
    let category = |id: u8| -> usize {
        match id {
            0x00..=0x02 => 1,
            0x03..=0x7F => 2,
            _ => 3,
        }
    };
    let level = usize::from(level);
    if let Some(obj) = d.objects.iter().find(|obj| category(obj.id) > level) {
        out.push(must(format!(
            "identification: object 0x{:02X} is {} but the device declares conformity level 0x{:02X} ({}) (6.21)",
            obj.id,
            ["basic", "regular", "extended"][category(obj.id) - 1],
            d.conformity,
            ["basic", "regular", "extended"][level - 1],
        )));
    }
    let individual = matches!(
        Request::decode(req),
        Ok(Request::ReadDeviceId { read_code: 4, .. })
    );
    if individual && d.conformity & 0x80 == 0 {
        out.push(must(format!(
            "identification: an individual access (code 04) is answered, but conformity level 0x{:02X} declares stream access only (6.21)",
            d.conformity
        )));
    }
}

/// Register values lie within the profile's ranges, read in the device's word order.
fn in_range(req: &[u8], o: &Response, p: &Profile, order: WordOrder, out: &mut Vec<Finding>) {
    let Some((address, input)) = register_read(req, p) else {
        return;
    };
    let (Response::ReadHoldingRegisters { values } | Response::ReadInputRegisters { values }) = o
    else {
        return;
    };
    let mut i = 0usize;
    while i < values.len() {
        let a = address.wrapping_add(i as u16);
        let Some(r) = p
            .register_at(a, input)
            .filter(|r| r.address == a && (r.table != Table::Input || input))
        else {
            i += 1;
            continue;
        };
        let w = usize::from(r.width);
        if i + w > values.len() {
            break;
        }
        let raw = if w == 2 {
            order.join(values[i], values[i + 1]) as i64
        } else {
            i64::from(values[i])
        };
        let v = match (r.signed, w) {
            (true, 2) => i64::from(raw as u32 as i32),
            (true, _) => i64::from(raw as u16 as i16),
            _ => raw,
        };
        let (min, max) = r.range();
        if v < min || v > max {
            out.push(must(format!(
                "0x{:04X} {} reads {v} (0x{raw:X}), outside {min}..={max}{}",
                r.address,
                r.name,
                if w == 2 {
                    " — a word-order mix-up reads like this"
                } else {
                    ""
                }
            )));
        }
        i += w;
    }
}

/// The verdict of a list of findings under a requirement level.
pub fn verdict(findings: &[Finding], level: Level) -> Verdict {
    if findings
        .iter()
        .any(|f| f.severity == Severity::Inconclusive)
    {
        return Verdict::Informational;
    }
    let worst = findings.iter().map(|f| f.severity).max();
    match (worst, level) {
        (None, _) => Verdict::Pass,
        (Some(Severity::Info), _) => Verdict::Informational,
        (Some(_), Level::Info) => Verdict::Informational,
        (Some(Severity::Must), Level::Must) => Verdict::Fail,
        (Some(Severity::Unimplemented), _) => Verdict::Unimplemented,
        (Some(_), _) => Verdict::NonStrict,
    }
}

/// How many events a device entered in front of its FC 0C event log between two reads, `before` and
/// `after` (each byte 0 first), when `after` is `before` with at most `max_new` new events in front and its
/// oldest ones flushed (spec 6.10: "Byte 0 is the most recent event. Each new byte flushes the oldest byte
/// from the field."): the smallest `n <= max_new` with `after[n..] == before[..after.len() - n]`, the log no
/// shorter than before (nothing but a restart clears it) and no longer than 64 bytes or `before.len() + n`
/// (a device may keep fewer than 64). `None` when no such `n` exists: the events are not in that order.
pub fn event_log_shift(before: &[u8], after: &[u8], max_new: usize) -> Option<usize> {
    let cap = codec::codes::event::LOG_CAPACITY;
    (0..=max_new.min(after.len())).find(|&n| {
        after.len() >= before.len()
            && after.len() <= cap.min(before.len() + n)
            && after[n..] == before[..after.len() - n]
    })
}

#[cfg(test)]
mod event_log_tests {
    use super::event_log_shift;

    #[test]
    fn new_events_in_front_pass_and_a_reversed_log_does_not() {
        let before = [0x80, 0x40, 0x80, 0x40, 0x80];
        // Nothing logged (a device that logs no Modbus/TCP traffic), two, six events in front.
        assert_eq!(event_log_shift(&before, &before, 6), Some(0));
        let two = [0x80, 0x41, 0x80, 0x40, 0x80, 0x40, 0x80];
        assert_eq!(event_log_shift(&before, &two, 6), Some(2));
        // More new events than the requests can have made.
        assert_eq!(event_log_shift(&before, &two, 1), None);
        // A full log flushes the oldest bytes, also for a device that keeps fewer than 64.
        let full: Vec<u8> = (0..64).collect();
        let mut next = vec![0xC0, 0xC1];
        next.extend_from_slice(&full[..62]);
        assert_eq!(event_log_shift(&full, &next, 6), Some(2));
        assert_eq!(event_log_shift(&full[..32], &next[..32], 6), Some(2));
        // The log sent oldest first: the new events at the end.
        let mut b = vec![0x80, 0x40, 0x80, 0x41, 0x80];
        let mut a = vec![
            0x80, 0x41, 0x80, 0x40, 0x80, 0x40, 0x80, 0x40, 0x80, 0x41, 0x80,
        ];
        assert!(event_log_shift(&b, &a, 6).is_some());
        b.reverse();
        a.reverse();
        assert_eq!(event_log_shift(&b, &a, 6), None);
        // A log that lost events without a restart.
        assert_eq!(event_log_shift(&before, &before[..3], 6), None);
    }
}

#[cfg(test)]
mod identification_tests {
    use super::identification_consistent;
    use codec::{DeviceIdObject, DeviceIdResponse, Request, Response};

    fn answer(conformity: u8, ids: &[u8]) -> Response {
        Response::ReadDeviceId(DeviceIdResponse {
            read_code: 2,
            conformity,
            more_follows: 0,
            next_object_id: 0,
            objects: ids
                .iter()
                .map(|&id| DeviceIdObject {
                    id,
                    value: b"x".to_vec(),
                })
                .collect(),
        })
    }

    fn findings(read_code: u8, o: &Response) -> usize {
        let req = Request::ReadDeviceId {
            read_code,
            object_id: 0,
        }
        .to_bytes()
        .unwrap();
        let mut out = Vec::new();
        identification_consistent(&req, o, &mut out);
        out.len()
    }

    #[test]
    fn the_declared_level_must_cover_the_objects_and_the_access() {
        // Consistent: regular objects at level 02 or 82; a basic-only device answering code 02 with its
        // basic objects (6.21: "in accordance with its actual conformity level").
        assert_eq!(findings(2, &answer(0x82, &[0, 1, 2, 3, 6])), 0);
        assert_eq!(findings(2, &answer(0x02, &[0, 1, 2, 3])), 0);
        assert_eq!(findings(2, &answer(0x01, &[0, 1, 2])), 0);
        assert_eq!(findings(3, &answer(0x83, &[0x80])), 0);
        assert_eq!(findings(4, &answer(0x81, &[1])), 0);
        // Objects above the level, individual access at a stream-only level, a level the spec lacks.
        assert_eq!(findings(2, &answer(0x01, &[0, 1, 2, 3])), 1);
        assert_eq!(findings(3, &answer(0x82, &[0x80])), 1);
        assert_eq!(findings(4, &answer(0x02, &[1])), 1);
        assert_eq!(findings(2, &answer(0x04, &[0])), 1);
        assert_eq!(findings(2, &answer(0x42, &[0])), 1);
    }
}

#[cfg(test)]
mod reject_tests {
    use super::{Sent, Severity, reject_or_ignore};
    use crate::targets::Received;
    use codec::Framing;
    use std::time::Duration;

    fn frame(hex: &str) -> Received {
        Received::Frame {
            bytes: codec::parse_hex(hex).unwrap(),
            first_at: Duration::ZERO,
            last_at: Duration::ZERO,
            max_gap: Duration::ZERO,
        }
    }

    /// An invalid request the reference ignores may be rejected with any exception code, in the exception
    /// form of the request's function code (App 7); another function code is NON-STRICT, an answer as valid
    /// a FAIL.
    #[test]
    fn a_rejection_carries_the_requests_function_code() {
        let sent = Sent {
            tid: Some(1),
            unit: 1,
            pdu: vec![0x03; 254],
        };
        let judge = |hex: &str| reject_or_ignore(Framing::Tcp, &sent, None, &frame(hex)).unwrap();
        assert!(judge("00 01 00 00 00 03 01 83 03").is_empty());
        assert!(judge("00 01 00 00 00 03 01 83 01").is_empty());
        let wrong = judge("00 01 00 00 00 03 01 80 01");
        assert_eq!(wrong.len(), 1);
        assert_eq!(wrong[0].severity, Severity::Should);
        let served = judge("00 01 00 00 00 05 01 03 02 00 00");
        assert_eq!(served[0].severity, Severity::Must);
    }
}

#[cfg(test)]
mod brief_tests {
    use super::brief;
    use codec::{
        Direction, FieldValue, Framing, decode_any, describe, hex_spaced, parse_hex, rtu, tcp,
    };

    /// What `brief` printed when each field went through its own string, joined.
    fn joined(framing: Framing, bytes: &[u8]) -> String {
        match decode_any(bytes, framing, Direction::Response) {
            Ok(d) => {
                let fields = describe(&d.pdu)
                    .iter()
                    .map(|f| match (&f.name, &f.value) {
                        (&"function", FieldValue::Int(v)) => format!("FC 0x{v:02X}"),
                        (n, v) => format!("{n} {v}"),
                    })
                    .collect::<Vec<_>>()
                    .join(", ");
                format!("{} ({fields})", hex_spaced(bytes))
            }
            Err(_) => hex_spaced(bytes),
        }
    }

    #[test]
    fn brief_prints_the_hex_and_the_fields() {
        let pdus = [
            "03 04 00 01 BE EF",
            "83 02",
            "01 01 05",
            "05 00 10 FF 00",
            "2B 0E 01 81 00 00 02 00 03 49 4D 53 01 02 41 42",
            "41 00",
            "",
            "03 05 00",
        ];
        for pdu in pdus {
            let pdu = parse_hex(pdu).unwrap();
            let mut t = Vec::new();
            tcp::encode_adu(7, 1, &pdu, &mut t).unwrap();
            let mut r = Vec::new();
            rtu::encode_adu(1, &pdu, &mut r).unwrap();
            for (framing, bytes) in [(Framing::Tcp, &t), (Framing::Rtu, &r), (Framing::Tcp, &pdu)] {
                assert_eq!(brief(framing, bytes), joined(framing, bytes));
            }
        }
        let mut t = Vec::new();
        tcp::encode_adu(7, 1, &parse_hex("03 04 00 01 BE EF").unwrap(), &mut t).unwrap();
        assert_eq!(
            brief(Framing::Tcp, &t),
            "00 07 00 00 00 07 01 03 04 00 01 BE EF (FC 0x03, byte_count 4 (0x4), values [0x0001 (1), 0xBEEF (48879)])"
        );
    }
}

#[cfg(test)]
mod answer_tests {
    use super::{Answer, Observation, Sent, judge, judge_answer};
    use crate::cases::Compare;
    use crate::targets::Received;
    use codec::{Framing, parse_hex, rtu, tcp};
    use std::time::Duration;

    fn framed(framing: Framing, pdu: &str) -> Vec<u8> {
        let pdu = parse_hex(pdu).unwrap();
        let mut out = Vec::new();
        match framing {
            Framing::Tcp => tcp::encode_adu(1, 1, &pdu, &mut out).unwrap(),
            _ => rtu::encode_adu(1, &pdu, &mut out).unwrap(),
        }
        out
    }

    /// `judge_answer` finds what `judge` finds, whatever the answer passed (the observation's reference
    /// answer, another one, one under another framing, one that does not decode).
    #[test]
    fn judging_with_the_answer_decoded_finds_what_judge_finds() {
        let profile = drives::corpus::Corpus::Embedded.profile("sd2x").unwrap();
        let order = profile.device.word_order;
        let compares = [
            Compare::Exact,
            Compare::Structure,
            Compare::InRange,
            Compare::Any,
            Compare::RejectOrIgnore,
        ];
        let pdus = [
            "03 04 00 01 BE EF",
            "03 04 00 02 BE EF",
            "03 02 00 01",
            "83 02",
            "83 01",
            "06 00 10 00 05",
            "01 01 05",
            "2B 0E 01 81 00 00 01 00 03 49 4D 53",
        ];
        let mut checked = 0;
        for framing in [Framing::Tcp, Framing::Rtu] {
            let sent = Sent {
                tid: (framing == Framing::Tcp).then_some(1),
                unit: 1,
                pdu: parse_hex("03 00 00 00 02").unwrap(),
            };
            let frames: Vec<Vec<u8>> = pdus
                .iter()
                .map(|p| framed(framing, p))
                .chain([vec![0x00, 0x01, 0x02], vec![]])
                .collect();
            let mut observed: Vec<Received> = frames.iter().cloned().map(Received::frame).collect();
            for partial in [vec![], vec![0x01, 0x03]] {
                observed.push(Received::Silence {
                    partial: partial.clone(),
                    at: Duration::ZERO,
                });
                observed.push(Received::Closed {
                    partial,
                    at: Duration::ZERO,
                });
            }
            observed.push(Received::Garbage {
                bytes: vec![0xFF; 3],
                at: Duration::ZERO,
                reason: "test".into(),
            });
            for expected in frames.iter().map(|f| Some(f.as_slice())).chain([None]) {
                for o in &observed {
                    for compare in &compares {
                        for closed in [false, true] {
                            let observation = Observation {
                                framing,
                                sent: &sent,
                                expected,
                                observed: o,
                                compare,
                                profile: &profile,
                                reference_closed: closed,
                            };
                            let want = judge(&observation, order);
                            let answers = frames.iter().flat_map(|f| {
                                [Answer::new(framing, f), Answer::new(Framing::Pdu, f)]
                            });
                            for answer in answers {
                                assert_eq!(
                                    judge_answer(&observation, order, &answer),
                                    want,
                                    "{observation:?} with {answer:?}"
                                );
                                checked += 1;
                            }
                        }
                    }
                }
            }
        }
        assert!(checked > 10_000);
    }
}

#[cfg(test)]
mod near_tests {
    use super::{Observation, Sent, judge};
    use crate::cases::Compare;
    use crate::targets::Received;
    use codec::{Framing, tcp};

    /// The findings of a read of `quantity` registers at `address` answered `observed` where the reference
    /// answers `expected`, compared within `tolerance`.
    fn near(
        profile: &str,
        address: u16,
        expected: &[u16],
        observed: &[u16],
        tolerance: u32,
    ) -> usize {
        let profile = drives::corpus::Corpus::Embedded.profile(profile).unwrap();
        let order = profile.device.word_order;
        let read = codec::Request::ReadHoldingRegisters {
            address,
            quantity: expected.len() as u16,
        };
        let sent = Sent {
            tid: Some(1),
            unit: 1,
            pdu: read.to_bytes().unwrap(),
        };
        let frame = |values: &[u16]| {
            let pdu = codec::Response::ReadHoldingRegisters {
                values: values.to_vec(),
            }
            .to_bytes()
            .unwrap();
            let mut out = Vec::new();
            tcp::encode_adu(1, 1, &pdu, &mut out).unwrap();
            out
        };
        let (e, o) = (frame(expected), Received::frame(frame(observed)));
        let compare = Compare::Near { tolerance };
        let observation = Observation {
            framing: Framing::Tcp,
            sent: &sent,
            expected: Some(&e),
            observed: &o,
            compare: &compare,
            profile: &profile,
            reference_closed: false,
        };
        judge(&observation, order).len()
    }

    /// A measured value within the tolerance of the reference's passes, one farther off does not; a 32-bit
    /// register is one value in the drive's word order and sign (an encoder count of -1 jittering to 1 is 2
    /// apart, not 65,534), so a word-order mix-up is still found.
    #[test]
    fn a_read_compared_near_passes_within_its_tolerance_only() {
        // SD2x actual speed, register 2001 (0x07D1), 16-bit signed: 0 against ±1, ±10 and 11.
        for (got, findings) in [
            (1u16, 0),
            (0xFFFF, 0),
            (10, 0),
            (0xFFF6, 0),
            (11, 1),
            (1000, 1),
        ] {
            assert_eq!(
                near("sd2x", 0x07D1, &[0], &[got], 10),
                findings,
                "{got:#06X}"
            );
        }
        // LMD Counter 2 (0x0007), 32-bit signed, low word first: -1 against 1, 3 and 7.
        let lmd = |lo: u16, hi: u16| near("lmd", 0x0007, &[0xFFFF, 0xFFFF], &[lo, hi], 4);
        assert_eq!(lmd(0x0001, 0x0000), 0);
        assert_eq!(lmd(0x0003, 0x0000), 0);
        assert_eq!(lmd(0x0007, 0x0000), 1);
        // The words swapped (high word first where the drive sends low first) are far off.
        assert_eq!(lmd(0x0000, 0x0001), 1);
        // A structure that differs is found as with Structure.
        assert_eq!(near("sd2x", 0x07D1, &[0, 0], &[0], 10), 1);
    }
}
