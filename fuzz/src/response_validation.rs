//! `response_validation`: whatever a target sends back, judged by the oracle.

use std::time::Duration;

use codec::{Framing, hex_spaced, rtu, tcp};
use drives::FaultSet;
use engine::targets::Received;
use engine::{Compare, Level, oracle};

use crate::input::Input;
use crate::reference::{TID, answer, frame_request, fresh_station, profiles};

pub(crate) const COMPARES: [Compare; 4] = [
    Compare::Exact,
    Compare::Structure,
    Compare::InRange,
    Compare::Any,
];

/// `response_validation` mode bits.
pub(crate) const RV_RTU: u8 = 0x04;
pub(crate) const RV_WRAP: u8 = 0x80;

/// `response_validation`: whatever a target sends back never panics the oracle. Input: a mode byte (bits 0-1
/// the drive of [`DRIVES`], bit 2 RTU instead of TCP, bits 3-4 the comparison Exact/Structure/InRange/Any,
/// bits 5-6 what was observed: a frame, silence, a close or garbage, bit 7 the observed bytes are a PDU to
/// frame correctly for the request), then a counted request PDU, then the observed bytes. The expected answer
/// is what a fresh fault-free reference drive answers to the request. Invariants: `judge`, `verdict`, `brief`
/// and `captured` never panic; the reference drive's own answer passes every comparison; the exact comparison
/// flags every frame that differs from the reference answer.
///
/// [`DRIVES`]: crate::DRIVES
pub fn response_validation(data: &[u8]) {
    let mut input = Input(data);
    let mode = input.u8();
    let drive = usize::from(mode & 3);
    let profile = &profiles()[drive];
    let framing = if mode & RV_RTU != 0 {
        Framing::Rtu
    } else {
        Framing::Tcp
    };
    let compare = &COMPARES[usize::from(mode >> 3 & 3)];
    let request = input.counted();
    let observed = input.rest();
    let unit = profile.device.default_unit;
    let (expected, closed) = frame_request(framing, unit, request).map_or((None, false), |adu| {
        answer(&mut fresh_station(drive, &FaultSet::none()), framing, &adu)
    });
    let bytes = if mode & RV_WRAP != 0 {
        let mut out = Vec::new();
        let framed = match framing {
            Framing::Tcp => tcp::encode_adu(TID, unit, observed, &mut out),
            _ => rtu::encode_adu(unit, observed, &mut out),
        };
        if framed.is_err() {
            out = observed.to_vec();
        }
        out
    } else {
        observed.to_vec()
    };
    let at = Duration::ZERO;
    let received = match mode >> 5 & 3 {
        0 => Received::Frame {
            bytes,
            first_at: at,
            last_at: at,
            max_gap: at,
        },
        1 => Received::Silence { partial: bytes, at },
        2 => Received::Closed { partial: bytes, at },
        _ => Received::Garbage {
            bytes,
            at,
            reason: "fuzz".into(),
        },
    };
    // The observed bytes, as the observation holds them (moved there, not copied).
    let (Received::Frame { bytes, .. }
    | Received::Garbage { bytes, .. }
    | Received::Silence { partial: bytes, .. }
    | Received::Closed { partial: bytes, .. }) = &received;
    let sent = oracle::Sent {
        tid: (framing == Framing::Tcp).then_some(TID),
        unit,
        pdu: request.to_vec(),
    };
    let observation = oracle::Observation {
        framing,
        sent: &sent,
        expected: expected.as_deref(),
        observed: &received,
        compare,
        profile,
        reference_closed: closed,
    };
    let findings = oracle::judge(&observation, profile.device.word_order);
    for level in [Level::Must, Level::Should, Level::Info] {
        let _ = oracle::verdict(&findings, level);
    }
    let _ = oracle::brief(framing, bytes);
    let _ = engine::capture::captured(framing, &sent.pdu, bytes);
    if let (Some(e), Received::Frame { bytes, .. }, Compare::Exact) =
        (&expected, &received, compare)
        && bytes != e
    {
        assert!(
            !findings.is_empty(),
            "the exact comparison accepts {} where the reference answers {}",
            hex_spaced(bytes),
            hex_spaced(e)
        );
    }
    if let Some(e) = &expected {
        let own = Received::Frame {
            bytes: e.clone(),
            first_at: at,
            last_at: at,
            max_gap: at,
        };
        // The reference answer decoded once for the four judgements (`judge_answer` judges as `judge`).
        let answer = oracle::Answer::new(framing, e);
        for compare in &COMPARES {
            let itself = oracle::Observation {
                expected: Some(e),
                observed: &own,
                compare,
                ..observation
            };
            let findings = oracle::judge_answer(&itself, profile.device.word_order, &answer);
            assert!(
                findings.is_empty(),
                "{} judged against itself ({compare:?}): {findings:?}",
                hex_spaced(e)
            );
        }
    }
}
