//! Is anyone there, and is it Modbus? A known-good read of the profile, sent before the first case (the
//! pre-flight) and whenever an answer that was due did not come (the liveness probe), and what to make of a
//! peer that sends something other than Modbus.

use std::time::Duration;

use crate::targets::{Received, Target, TargetError};
use codec::{Framing, rtu, tcp};

/// How long the pre-flight and the liveness probes wait, and how long a run waits for a target that stopped
/// answering to come back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Liveness {
    /// How long the known-good read waits for its answer (pre-flight and each liveness probe).
    pub probe_timeout: Duration,
    /// How long a run waits (probing, reconnecting) for a target that stopped answering before it gives up
    /// and skips the remaining cases.
    pub recovery: Duration,
}

impl Default for Liveness {
    /// 3 s for the known-good read, 10 s for a target to come back.
    fn default() -> Self {
        Self {
            probe_timeout: Duration::from_secs(3),
            recovery: Duration::from_secs(10),
        }
    }
}

/// What came back to a known-good read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Heard {
    /// A Modbus answer (a normal or an exception response: either shows a Modbus server listening).
    Modbus,
    /// Bytes that are not a Modbus answer; what they look like.
    Foreign(String),
    /// The peer closed the connection without a word.
    Closed,
    /// Nothing within the bound.
    Nothing,
}

/// The known-good read framed for `framing` (transaction id `tid` on Modbus/TCP).
pub fn frame(pdu: &[u8], framing: Framing, unit: u8, tid: u16) -> Vec<u8> {
    let mut out = Vec::with_capacity(pdu.len() + 8);
    let _ = match framing {
        Framing::Tcp => tcp::encode_adu(tid, unit, pdu, &mut out),
        _ => rtu::encode_adu(unit, pdu, &mut out),
    };
    out
}

/// How long [`ask`] listens on after a late answer of an earlier request, for the request's own answer or
/// its echo.
const AFTER_A_LATE_ANSWER: Duration = Duration::from_millis(200);

/// Send `request` (already framed) and listen up to `bound` (on the target's clock): a Modbus answer, bytes
/// of something else, a close or nothing. Any Modbus response counts, whatever request it answers (a late
/// answer of an earlier request shows the target alive as well), except where the request itself comes back
/// ahead of its answer: that is the line's echo (a two-wire RS-485 adapter hears itself), which every case
/// would take for the drive's answer, and the target is [`Heard::Foreign`] as an echo. So a late answer of
/// an earlier request is not the end: the listening goes on a little ([`AFTER_A_LATE_ANSWER`]) for this
/// request's answer or its echo. Bounded by `bound` and by 32 receives.
pub fn ask(t: &mut dyn Target, request: &[u8], bound: Duration) -> Result<Heard, TargetError> {
    let framing = t.framing();
    t.send(request)?;
    let start = t.now();
    let mut foreign: Vec<u8> = Vec::new();
    // A Modbus response to another request came (a late answer): the target is alive, and only a short
    // while more is listened for this request's own answer or its echo (which follows the send at once).
    let mut alive = false;
    let mut bound = bound;
    for _ in 0..32 {
        let left = bound.saturating_sub(t.now().saturating_sub(start));
        if left.is_zero() {
            break;
        }
        match t.recv(left)? {
            Received::Frame { bytes, .. } => {
                if crate::readings::decode_response(framing, &bytes).is_some() {
                    if foreign.starts_with(request) {
                        break;
                    }
                    if begins_an_answer(&bytes, request, framing) {
                        return Ok(Heard::Modbus);
                    }
                    if !alive {
                        alive = true;
                        bound = bound.min(t.now().saturating_sub(start) + AFTER_A_LATE_ANSWER);
                    }
                    continue;
                }
                foreign.extend_from_slice(&bytes);
            }
            Received::Garbage { bytes, .. } => foreign.extend_from_slice(&bytes),
            Received::Silence { partial, .. } => {
                foreign.extend_from_slice(&partial);
                break;
            }
            Received::Closed { partial, .. } => {
                foreign.extend_from_slice(&partial);
                if foreign.is_empty() && !alive {
                    return Ok(Heard::Closed);
                }
                break;
            }
        }
        if foreign.len() > 4096 {
            break;
        }
    }
    if foreign.starts_with(request) {
        return Ok(Heard::Foreign(looks_like(&foreign, request)));
    }
    if alive || begins_an_answer(&foreign, request, framing) {
        // A late answer; or a Modbus server whose answer is malformed (its MBAP length disagrees with its
        // bytes, its CRC is wrong, say): the cases judge it; refusing to run would hide the fault behind
        // "not a Modbus server".
        return Ok(Heard::Modbus);
    }
    Ok(if foreign.is_empty() {
        Heard::Nothing
    } else {
        Heard::Foreign(looks_like(&foreign, request))
    })
}

/// True when `bytes` begin as an answer to `request`, whatever follows: on Modbus/TCP its transaction id,
/// protocol id 0, unit id and function code (or the exception form of it); on RTU its address and function
/// code. An echo of the request is not an answer.
fn begins_an_answer(bytes: &[u8], request: &[u8], framing: Framing) -> bool {
    let fc_at = if framing == Framing::Tcp { 7 } else { 1 };
    match (bytes.get(..=fc_at), request.get(..=fc_at)) {
        (Some(b), Some(r)) => {
            let head = if framing == Framing::Tcp {
                b[..4] == r[..4] && b[6] == r[6]
            } else {
                b[0] == r[0]
            };
            head && (b[fc_at] & 0x7F) == r[fc_at] && !bytes.starts_with(request)
        }
        _ => false,
    }
}

/// How [`looks_like`] names an echo of the request.
const ECHO: &str = "an echo of the request";

/// What bytes that are not Modbus look like ("HTTP (...)", "TLS", "SSH", an echo of the request, text, or
/// their first bytes in hex), to follow "looks like".
pub fn looks_like(bytes: &[u8], request: &[u8]) -> String {
    let text = String::from_utf8_lossy(bytes);
    let first_line: String = text
        .lines()
        .next()
        .unwrap_or("")
        .chars()
        .filter(|c| !c.is_control())
        .take(80)
        .collect();
    if bytes.starts_with(b"HTTP/") || text.contains("HTTP/1.") || text.contains("<html") {
        return format!("HTTP (a web server: \"{first_line}\")");
    }
    if bytes.len() >= 3 && matches!(bytes[0], 0x14..=0x17) && bytes[1] == 0x03 {
        return "TLS (a TLS record: an encrypted service, Modbus/TCP Security or HTTPS?)".into();
    }
    if bytes.starts_with(b"SSH-") {
        return format!("SSH (banner \"{first_line}\")");
    }
    if !request.is_empty() && bytes.starts_with(request) {
        return format!(
            "{ECHO} (an echo service, a loopback, or a serial adapter echoing what is sent)"
        );
    }
    let printable = bytes
        .iter()
        .filter(|b| b.is_ascii_graphic() || b.is_ascii_whitespace())
        .count();
    if printable * 10 >= bytes.len() * 9 {
        return format!("text: \"{first_line}\"");
    }
    format!(
        "none of Modbus: {} byte(s), {}",
        bytes.len(),
        hex(&bytes[..bytes.len().min(32)])
    )
}

/// What to tell the user when the pre-flight read did not get a Modbus answer (`None` when it did): what
/// was tried, and the likely causes or what the peer looks like instead.
/// `serial` is `Some(echo)` on a serial line, `echo` its `echo=on`.
pub fn preflight_failure(
    target: &str,
    heard: &Heard,
    request: &[u8],
    framing: Framing,
    serial: Option<bool>,
    unit: u8,
    bound: Duration,
) -> Option<String> {
    let echo_expected = serial == Some(true);
    let serial = serial.is_some();
    let pdu = match framing {
        Framing::Tcp => request.get(7..).unwrap_or(&[]),
        _ => request
            .get(1..request.len().saturating_sub(2))
            .unwrap_or(&[]),
    };
    let what = codec::Request::decode(pdu).map_or_else(|_| hex(pdu), |r| format!("{r:?}"));
    let framing_name = match (framing, serial) {
        (Framing::Tcp, _) => "Modbus/TCP",
        (_, true) => "RTU",
        _ => "RTU over TCP",
    };
    let tried = format!(
        "a known-good read ({what}; {framing_name} framing, unit {unit}: {})",
        hex(request)
    );
    let secs = bound.as_secs_f64();
    match heard {
        Heard::Modbus => None,
        Heard::Nothing => Some(format!(
            "{target} does not answer: no answer within {secs:.1} s to {tried}, so no case was run. Likely causes: {} (wait longer with --preflight-timeout MS)",
            likely_causes(framing, serial, unit)
        )),
        Heard::Closed => Some(format!(
            "{target} closed the connection without answering {tried}, so no case was run. Likely causes: {}",
            likely_causes(framing, serial, unit)
        )),
        Heard::Foreign(looks) if serial && !echo_expected && looks.starts_with(ECHO) => {
            Some(format!(
                "{target} gave back {tried} as it was sent, so no case was run: a two-wire RS-485 adapter whose receiver stays on while it transmits hears itself. Add echo=on to the target URL (rtu://PATH?...&echo=on): each request's echo is then read back, checked and dropped before the answer"
            ))
        }
        Heard::Foreign(looks) => Some(format!(
            "{target} is not a Modbus server: it answered {tried} with what looks like {looks}, so no case was run"
        )),
    }
}

/// Bytes as spaced hex.
pub fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The likely causes of a target that does not answer a known-good read, for the framing in use.
pub fn likely_causes(framing: Framing, serial: bool, unit: u8) -> String {
    let mut causes = vec![format!(
        "the unit id (--unit; {unit} was used) is not the device's"
    )];
    match (framing, serial) {
        (Framing::Tcp, _) => {
            causes.push("the host or port is not the Modbus server's".into());
            causes.push(
                "the device speaks RTU over TCP (a serial gateway in transparent mode): try rtu+tcp://"
                    .into(),
            );
        }
        (_, true) => {
            causes.push("the baud rate, parity or stop bits differ from the device's (?baud=19200&parity=even&stop=1)".into());
            causes.push("the wiring (A/B swapped, no termination) or the adapter".into());
        }
        _ => {
            causes.push("the host or port is not the gateway's".into());
            causes.push(
                "the device speaks Modbus/TCP (MBAP framing), not RTU over TCP: try tcp://".into(),
            );
        }
    }
    causes.push("the device is not a Modbus server, or it is busy with another master".into());
    causes.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn foreign_peers_are_named() {
        let req = [0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1];
        assert!(looks_like(b"HTTP/1.1 400 Bad Request\r\n\r\n", &req).contains("HTTP"));
        assert!(looks_like(&[0x15, 0x03, 0x01, 0x00, 0x02, 0x02, 0x32], &req).contains("TLS"));
        assert!(looks_like(b"SSH-2.0-OpenSSH_9.6\r\n", &req).contains("SSH"));
        assert!(looks_like(&req, &req).contains("echo"));
        assert!(looks_like(&[0xFE, 0x00, 0x81], &req).contains("FE 00 81"));
    }

    /// A drive whose answers carry a wrong MBAP length, or a wrong CRC, is a Modbus server with a fault (its
    /// cases FAIL), not "not a Modbus server"; an echo of the request is still not Modbus.
    #[test]
    fn a_malformed_modbus_answer_is_modbus_and_an_echo_is_not() {
        use crate::targets::sim::SimTarget;
        use drives::{Fault, FaultSet, Station};
        let p = test_support::profile("generic");
        let req = [0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1];
        let rtu_req = [1, 3, 0, 0, 0, 1, 0x84, 0x0A];
        for (fault, framing, req) in [
            (None, Framing::Tcp, &req[..]),
            (Some(Fault::MbapLength), Framing::Tcp, &req[..]),
            (None, Framing::Rtu, &rtu_req[..]),
            (Some(Fault::WrongCrc), Framing::Rtu, &rtu_req[..]),
        ] {
            let faults = FaultSet::of(fault.as_slice());
            let station = Station::new(drives::build(p.clone(), faults.clone()), faults, 1);
            let mut t = SimTarget::with_framing(station, framing, None);
            let heard = ask(&mut t, req, Duration::from_millis(200)).expect("ask");
            assert_eq!(heard, Heard::Modbus, "{fault:?} {framing:?}");
        }
        let tcp = Framing::Tcp;
        assert!(begins_an_answer(
            &[0, 1, 0, 0, 0, 6, 1, 3, 2, 0, 0],
            &req,
            tcp
        ));
        assert!(begins_an_answer(&[0, 1, 0, 0, 0, 3, 1, 0x83, 2], &req, tcp));
        assert!(!begins_an_answer(&req, &req, tcp), "an echo");
        assert!(
            !begins_an_answer(&[0, 2, 0, 0, 0, 6, 1, 3, 2, 0, 0], &req, tcp),
            "another tid"
        );
        assert!(
            !begins_an_answer(&[0, 1, 0, 0, 0, 6, 1, 4, 2, 0, 0], &req, tcp),
            "another fc"
        );
        let rtu = Framing::Rtu;
        assert!(
            begins_an_answer(&[1, 3, 2, 0, 0, 0x47, 0x44], &rtu_req, rtu),
            "bad CRC"
        );
        assert!(!begins_an_answer(&rtu_req, &rtu_req, rtu), "an echo");
        assert!(
            !begins_an_answer(&[2, 3, 2, 0, 0, 0x47, 0x44], &rtu_req, rtu),
            "another address"
        );
    }

    /// A serial line that echoes (a pty pair: the test is the adapter and the drive).
    mod on_an_echoing_line {
        use super::*;
        use crate::targets::serial::tests::{adu, line, sent};
        use std::io::Write;
        use std::time::Instant;

        /// The pre-flight's known-good read on a line that echoes: without echo=on the request back ahead of
        /// the answer is named an echo and the message says to add echo=on (before, the answer behind it made
        /// the pre-flight pass and then every case judged the echo); with echo=on it is the answer.
        #[test]
        fn the_preflight_names_an_echo_ahead_of_the_answer_and_says_to_add_echo_on() {
            let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
            let answer = adu(&[0x03, 0x02, 0x12, 0x34]);
            for echo in [false, true] {
                let (mut t, mut master, _slave) = line(echo);
                let (req, ans) = (read.clone(), answer.clone());
                let adapter = std::thread::spawn(move || {
                    // The echo at once, the drive's answer after its turnaround (more than t3.5 later).
                    let got = sent(&mut master, req.len());
                    master.write_all(&got).expect("the echo");
                    std::thread::sleep(Duration::from_millis(10));
                    master.write_all(&ans).expect("the answer");
                    master
                });
                let heard = ask(&mut t, &read, Duration::from_millis(500)).expect("ask");
                let _master = adapter.join().expect("the adapter");
                let failure = preflight_failure(
                    "rtu:///dev/ttyUSB0",
                    &heard,
                    &read,
                    Framing::Rtu,
                    Some(echo),
                    1,
                    Duration::from_millis(500),
                );
                if echo {
                    assert_eq!(heard, Heard::Modbus);
                    assert_eq!(failure, None);
                } else {
                    assert!(
                        matches!(&heard, Heard::Foreign(l) if l.starts_with("an echo of the request")),
                        "{heard:?}"
                    );
                    let m = failure.expect("a pre-flight failure");
                    assert!(
                        m.contains("gave back") && m.contains("Add echo=on to the target URL"),
                        "{m}"
                    );
                }
            }
        }

        /// The pre-flight runs after reads of its own (the runner learns the drive's word order and FC 43 form
        /// first); on an echoing line their answers come late, after the echo they were taken for. A late answer
        /// ahead of the pre-flight's echo must not make the pre-flight pass: the listening goes on for the echo
        /// (it failed about one run in three against sd2x-b before). Without an echo the late answer and then
        /// the answer are a Modbus server, heard at once.
        #[test]
        fn a_late_answer_ahead_of_the_echo_does_not_hide_the_echo() {
            let read = adu(&[0x03, 0x0B, 0xB8, 0x00, 0x01]);
            let answer = adu(&[0x03, 0x02, 0x00, 0x00]);
            let late = adu(&[0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x00]);
            for echoing in [true, false] {
                let (mut t, mut master, _slave) = line(false);
                let (req, ans, late) = (read.clone(), answer.clone(), late.clone());
                let adapter = std::thread::spawn(move || {
                    let got = sent(&mut master, req.len());
                    master
                        .write_all(&late)
                        .expect("a late answer of another request");
                    std::thread::sleep(Duration::from_millis(10));
                    if echoing {
                        master.write_all(&got).expect("the echo");
                        std::thread::sleep(Duration::from_millis(10));
                    }
                    master.write_all(&ans).expect("the answer");
                    master
                });
                let began = Instant::now();
                let heard = ask(&mut t, &read, Duration::from_secs(3)).expect("ask");
                let took = began.elapsed();
                let _master = adapter.join().expect("the adapter");
                if echoing {
                    assert!(
                        matches!(&heard, Heard::Foreign(l) if l.starts_with("an echo of the request")),
                        "{heard:?}"
                    );
                } else {
                    assert_eq!(heard, Heard::Modbus);
                }
                assert!(took < Duration::from_secs(1), "{echoing}: took {took:?}");
            }
        }
    }
}
