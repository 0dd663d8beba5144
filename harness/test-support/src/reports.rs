//! Synthetic cases and results for the report tests.
#![allow(dead_code)]

use std::time::Duration;

use engine::reports::{RunInfo, Transport};
use engine::{
    Case, CaseResult, Compare, Dir, Level, Mutation, Outgoing, Received, Step, StepResult, Tag,
    Verdict, WireEvent,
};

/// A finding that tries to inject markup into the HTML and XML reports.
pub const INJECTED: &str = "register 0 is <script>alert(1)</script> & \"quoted\"";

/// The files a finished `--report DIR` holds besides `cases/`.
pub const REPORT_FILES: [&str; 5] = [
    "index.json",
    "cases.jsonl",
    "junit.xml",
    "report.html",
    "session.pcapng",
];

/// Run info for a report test.
pub fn run_info(transport: Transport, server_port: u16) -> RunInfo {
    RunInfo {
        target: match transport {
            Transport::Tcp => format!("tcp://127.0.0.1:{server_port}"),
            Transport::Rtu => "rtu:///dev/ttyUSB0?baud=19200".to_string(),
            Transport::RtuOverTcp => format!("rtu+tcp://127.0.0.1:{server_port}"),
        },
        profile: "mdrive".to_string(),
        transport,
        server_port,
        started_unix_ms: 1_795_402_213_123,
        command_line: "modbus-harness run --target x --report out/ <test>".to_string(),
        seed: Some(42),
        shuffle: None,
        harness_version: "0.1.0-test".to_string(),
        report_dir: None,
    }
}

/// Frame a PDU for the transport (transaction id `tid` for Modbus/TCP, unit 1).
pub fn frame(transport: Transport, tid: u16, pdu: &[u8]) -> Vec<u8> {
    match transport {
        Transport::Tcp => super::tcp_adu(tid, 1, pdu),
        Transport::Rtu | Transport::RtuOverTcp => super::rtu_adu(1, pdu),
    }
}

fn case(id: &str, title: &str, pdu: &[u8], tags: Vec<Tag>) -> Case {
    Case {
        id: id.to_string(),
        title: title.to_string(),
        reference: "Modbus Application Protocol V1.1b3, 6.3".to_string(),
        requirement: "The server MUST answer a valid FC 03 request with the register values."
            .to_string(),
        level: Level::Must,
        tags,
        steps: vec![Step::Exchange {
            send: Outgoing::Pdu(pdu.to_vec()),
            compare: Compare::Exact,
            capture: None,
            note: "read 2 holding registers".to_string(),
        }],
        requirements: Vec::new(),
        freedoms: Vec::new(),
    }
}

/// One request/response exchange as a result.
#[allow(clippy::too_many_arguments)]
fn exchange(
    id: &str,
    verdict: Verdict,
    at: Duration,
    request: Vec<u8>,
    expected: Option<Vec<u8>>,
    response: Option<Vec<u8>>,
    findings: Vec<String>,
    malformed_request: bool,
) -> CaseResult {
    let mut wire = vec![WireEvent {
        dir: Dir::Tx,
        at,
        bytes: request.clone(),
        intended_malformed: malformed_request,
    }];
    let observed = match &response {
        Some(r) => {
            wire.push(WireEvent {
                dir: Dir::Rx,
                at: at + Duration::from_micros(850),
                bytes: r.clone(),
                intended_malformed: false,
            });
            vec![Received::frame(r.clone())]
        }
        None => vec![Received::silence()],
    };
    CaseResult {
        id: id.to_string(),
        verdict,
        expected_deviation: None,
        steps: vec![StepResult {
            note: "read 2 holding registers".to_string(),
            sent: Some(request),
            expected,
            observed,
            verdict,
            findings,
        }],
        wire,
        duration: Duration::from_micros(1200),
        reason: None,
    }
}

/// The FC 03 read of two registers the synthetic cases send, and the answer the reference and the target
/// give to it.
const READ: [u8; 5] = [0x03, 0x00, 0x00, 0x00, 0x02];
const ANSWER: [u8; 6] = [0x03, 0x04, 0x00, 0x0A, 0x01, 0x02];

/// The result `verdict` of a case whose [`READ`] (transaction id `tid`), sent at `at`, was answered with
/// [`ANSWER`] as expected.
fn read_answered(
    transport: Transport,
    id: &str,
    verdict: Verdict,
    at: Duration,
    tid: u16,
) -> CaseResult {
    exchange(
        id,
        verdict,
        at,
        frame(transport, tid, &READ),
        Some(frame(transport, tid, &ANSWER)),
        Some(frame(transport, tid, &ANSWER)),
        vec![],
        false,
    )
}

/// The ids of [`sample`], in order.
pub const IDS: [&str; 6] = [
    "generic/6.3/fc03-two-registers",
    "generic/6.3/fc03-bad-response",
    "profile/mdrive/motion-enable",
    "generic/framing/malformed-request",
    "generic/7/exception-code",
    "golden/mdrive/4.1-informational",
];

/// A PASS, a FAIL (malformed response: bad CRC on RTU, bad MBAP length on TCP, finding with markup),
/// a SKIPPED, a PASS whose request is malformed on purpose, a NON-STRICT and an INFORMATIONAL case.
pub fn sample(transport: Transport) -> Vec<(Case, CaseResult)> {
    let (read, answer) = (READ, ANSWER);
    let ms = Duration::from_millis;
    let mut out = Vec::new();

    // PASS: FC 03 exchange.
    let c = case(IDS[0], "FC 03 reads two registers", &read, vec![]);
    let r = read_answered(transport, IDS[0], Verdict::Pass, ms(10), 1);
    out.push((c, r));

    // FAIL: a malformed response.
    let mut bad = frame(transport, 2, &answer);
    match transport {
        Transport::Tcp => bad[5] += 3, // MBAP length says 3 bytes more than the frame carries
        Transport::Rtu | Transport::RtuOverTcp => {
            let n = bad.len();
            bad[n - 1] ^= 0xFF; // CRC broken
            bad[n - 2] ^= 0xFF;
        }
    }
    let c = case(IDS[1], "FC 03 answer must be well formed", &read, vec![]);
    let r = exchange(
        IDS[1],
        Verdict::Fail,
        ms(20),
        frame(transport, 2, &read),
        Some(frame(transport, 2, &answer)),
        Some(bad),
        vec![
            "the response does not decode: bad framing".to_string(),
            INJECTED.to_string(),
            "a control character \u{7} in a finding".to_string(),
        ],
        false,
    );
    out.push((c, r));

    // SKIPPED by the safety policy: no traffic.
    let c = case(
        IDS[2],
        "enable the power stage",
        &[0x06, 0x00, 0x10, 0x00, 0x01],
        vec![Tag::Write, Tag::Motion],
    );
    let r = CaseResult {
        id: IDS[2].to_string(),
        verdict: Verdict::Skipped,
        expected_deviation: None,
        steps: vec![],
        wire: vec![],
        duration: Duration::ZERO,
        reason: Some("tag `motion`: not allowed without --allow-motion".to_string()),
    };
    out.push((c, r));

    // PASS: a request malformed on purpose, answered by silence.
    let mut mutated = frame(transport, 3, &read);
    let mutation = match transport {
        Transport::Tcp => {
            mutated[3] = 0x01; // protocol id 0x0001
            Mutation::ProtocolId(1)
        }
        Transport::Rtu | Transport::RtuOverTcp => {
            let n = mutated.len();
            mutated[n - 1] ^= 0xFF;
            mutated[n - 2] ^= 0xFF;
            Mutation::BadCrc
        }
    };
    let mut c = case(IDS[3], "a malformed request is ignored", &read, vec![]);
    c.steps = vec![Step::Exchange {
        send: Outgoing::Mutated {
            pdu: read.to_vec(),
            mutation,
        },
        compare: Compare::Exact,
        capture: None,
        note: "malformed request".to_string(),
    }];
    let r = exchange(
        IDS[3],
        Verdict::Pass,
        ms(30),
        mutated,
        None,
        None,
        vec![],
        true,
    );
    out.push((c, r));

    // NON-STRICT: an exception where a SHOULD asks for another code.
    let exception = [0x83, 0x02];
    let mut c = case(
        IDS[4],
        "out-of-range address gives exception 02",
        &[0x03, 0xFF, 0x00, 0x00, 0x01],
        vec![],
    );
    c.level = Level::Should;
    let mut r = exchange(
        IDS[4],
        Verdict::NonStrict,
        ms(40),
        frame(transport, 4, &[0x03, 0xFF, 0x00, 0x00, 0x01]),
        Some(frame(transport, 4, &[0x83, 0x04])),
        Some(frame(transport, 4, &exception)),
        vec!["exception 02 where 04 is recommended".to_string()],
        false,
    );
    r.expected_deviation = Some((Verdict::Fail, "vendor answers 02, see ERRATA".to_string()));
    out.push((c, r));

    // INFORMATIONAL.
    let mut c = case(IDS[5], "what unit 0 answers", &read, vec![]);
    c.level = Level::Info;
    let r = read_answered(transport, IDS[5], Verdict::Informational, ms(50), 5);
    out.push((c, r));
    out
}

/// A small PASS case with one exchange, numbered `n`.
pub fn numbered_pass(transport: Transport, n: usize) -> (Case, CaseResult) {
    let id = format!("bulk/pass/{n:07}");
    let c = case(&id, "bulk", &READ, vec![]);
    let r = read_answered(
        transport,
        &id,
        Verdict::Pass,
        Duration::from_micros(n as u64 * 1000),
        n as u16,
    );
    (c, r)
}
