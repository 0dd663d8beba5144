//! A drive that speaks only Modbus RTU (the SD2x), reached over Modbus/TCP through a gateway. Where the drive
//! is silent the gateway may answer exception 0B (no response from the target) or 0A (no path to it), App 7
//! (`gateway-no-response`), and another unit id is another slave's, which may be absent (`tcp-unit-ids`).
//! The oracle admits these answers only where the drive itself may be silent, with the request's function
//! code; a gateway that answers so cannot hide a fault of the drive behind it.

use std::collections::BTreeSet;

use codec::{Framing, Request};
use drives::corpus::Corpus;
use drives::{Fault, FaultSet};
use engine::Verdict;
use engine::cases::Compare;
use engine::oracle::{Judged, Observation, Sent, StepContext, judge_admitting};
use engine::session::{Options, RunOutcome};
use engine::targets::{Received, TargetUrl};
use test_support::{failures_of, run_quietly};

/// The SD2x in process over Modbus/TCP framing: the drive with an ideal gateway in front.
const TARGET: &str = "sim:sd2x?transport=tcp";

fn options(choose: &[&str], faults: &[Fault]) -> Options {
    let mut o = Options::new(TargetUrl::parse(TARGET).expect("url"));
    o.choose = choose.iter().map(|c| c.to_string()).collect();
    o.faults = FaultSet::of(faults);
    o.keep_verdicts = true;
    o
}

fn run(choose: &[&str], faults: &[Fault]) -> RunOutcome {
    run_quietly(&options(choose, faults))
        .unwrap_or_else(|e| panic!("{TARGET} --choose {choose:?} --fault {faults:?}: {e}"))
}

fn failing(out: &RunOutcome) -> BTreeSet<String> {
    out.verdicts
        .iter()
        .filter(|(_, v)| *v == Verdict::Fail)
        .map(|(id, _)| id.clone())
        .collect()
}

fn adu(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    codec::tcp::encode_adu(tid, unit, pdu, &mut out).expect("encodes");
    out
}

/// The judgement of `observed` (a PDU in an ADU echoing transaction 7 and `unit`) for a request `pdu` to
/// `unit` of the SD2x, where the reference answers `expected` (a PDU; `None`: silence) and the freedoms
/// `ids` apply, decided where `decided`; `gateway`: the request went through a gateway.
fn judge(
    unit: u8,
    pdu: &[u8],
    expected: Option<&[u8]>,
    observed: &[u8],
    (ids, decided, gateway): (&[&str], &[drives::Decision], bool),
) -> Judged {
    let reqs = Corpus::Embedded.requirements().expect("requirements");
    let p = Corpus::Embedded.profile("sd2x").expect("sd2x");
    let applicable: Vec<&drives::requirements::Freedom> = ids
        .iter()
        .map(|id| reqs.freedom(id).expect("freedom"))
        .collect();
    let request = Request::decode(pdu).ok();
    let cx = StepContext {
        request: request.as_ref(),
        pdu,
        unit,
        run_unit: p.device.default_unit,
        profile: &p,
        malformed: request.is_none(),
        batch: false,
        decided,
        counter_alternatives: &[],
        choice_alternatives: &[],
        closed: false,
        short_of_length: false,
        gateway,
    };
    let sent = Sent {
        tid: Some(7),
        unit,
        pdu: pdu.to_vec(),
    };
    let expected = expected.map(|e| adu(7, unit, e));
    let observed = Received::frame(adu(7, unit, observed));
    judge_admitting(
        &Observation {
            framing: Framing::Tcp,
            sent: &sent,
            expected: expected.as_deref(),
            observed: &observed,
            compare: &Compare::Structure,
            profile: &p,
            reference_closed: false,
        },
        &applicable,
        &cx,
    )
}

fn fails(j: &Judged) -> bool {
    j.findings.iter().any(|f| {
        matches!(
            f.severity,
            engine::oracle::Severity::Must | engine::oracle::Severity::Unimplemented
        )
    })
}

const READ: &[u8] = &[0x03, 0x0B, 0xB8, 0x00, 0x01];
const GATEWAY: &str = drives::choices::ids::GATEWAY_NO_RESPONSE;

/// Where the drive is silent (the reference: a request to unit 0xFF, which is no serial address), the
/// gateway's 0B or 0A with the request's function code passes and is shown as the gateway's choice for that
/// unit. Not another code, not another function code, not without the gateway (a protocol id other than 0,
/// which the gateway discards; a drive speaking Modbus/TCP itself), and not where the drive must answer: a
/// 0B there is the drive failing to answer.
#[test]
fn a_gateways_0b_or_0a_passes_only_where_the_drive_is_silent() {
    let gw = (&[GATEWAY][..], &[GATEWAY][..], true);
    for code in [0x0B, 0x0A] {
        let j = judge(0xFF, READ, None, &[0x83, code], gw);
        assert!(!fails(&j), "83 {code:02X}: {:?}", j.findings);
        assert_eq!(
            j.shown
                .iter()
                .map(|s| (s.freedom.as_str(), s.value.clone()))
                .collect::<Vec<_>>(),
            [(GATEWAY, format!("exception-{code:02X}"))]
        );
    }
    for (observed, what) in [
        (&[0x83, 0x04][..], "another exception code"),
        (&[0x84, 0x0B][..], "another function code"),
        (&[0x80, 0x0B][..], "no function code"),
        (&[0x03, 0x02, 0x00, 0x00][..], "an answer"),
    ] {
        assert!(fails(&judge(0xFF, READ, None, observed, gw)), "{what}");
    }
    let no_gateway = (&[GATEWAY][..], &[GATEWAY][..], false);
    assert!(
        fails(&judge(0xFF, READ, None, &[0x83, 0x0B], no_gateway)),
        "without a gateway"
    );
    // The drive must answer this read: the reference does.
    let answered = [0x03, 0x02, 0x00, 0x00];
    assert!(
        fails(&judge(1, READ, Some(&answered), &[0x83, 0x0B], gw)),
        "0B where the drive answers"
    );
    // A drive with Modbus/TCP is no gateway: the freedom is not the MDrive's.
    let reqs = Corpus::Embedded.requirements().expect("requirements");
    let f = reqs.freedom(GATEWAY).expect("freedom");
    assert!(f.applies_to("sd2x") && !f.applies_to("mdrive") && !f.applies_to("generic"));
}

/// Where another freedom lets the drive be silent (`truncated-pdu`: a PDU too short for its function, 03
/// or silence), the gateway's answer to that silence passes, both choices shown; without the gateway, or
/// where that freedom does not apply, it FAILs.
#[test]
fn a_gateways_answer_to_a_silence_another_freedom_admits_passes() {
    let truncated = [0x03, 0x0B];
    let refused = [0x83, 0x03];
    let ids = [drives::choices::ids::TRUNCATED_PDU, GATEWAY];
    let decided = [drives::choices::ids::TRUNCATED_PDU];
    let j = judge(
        1,
        &truncated,
        Some(&refused),
        &[0x83, 0x0B],
        (&ids, &decided, true),
    );
    assert!(!fails(&j), "{:?}", j.findings);
    let shown: BTreeSet<(String, String)> = j
        .shown
        .iter()
        .map(|s| (s.freedom.clone(), s.value.clone()))
        .collect();
    assert_eq!(
        shown,
        BTreeSet::from([
            ("truncated-pdu".to_string(), "silence".to_string()),
            (GATEWAY.to_string(), "exception-0B".to_string()),
        ])
    );
    assert!(fails(&judge(
        1,
        &truncated,
        Some(&refused),
        &[0x83, 0x0B],
        (&ids, &decided, false)
    )));
    assert!(fails(&judge(
        1,
        &truncated,
        Some(&refused),
        &[0x83, 0x0B],
        (&[GATEWAY], &[], true)
    )));
}

/// The SD2x behind gateways answering in every admissible way (silence, 0B, 0A where the drive is silent;
/// another unit id absent, unreachable or ignored; the drive ignoring truncated PDUs, the gateway answering
/// that) passes the whole catalog, and the run records each choice it showed.
#[test]
fn an_rtu_drive_behind_any_admissible_gateway_passes_the_catalog() {
    let configurations: &[(&[&str], &[&str])] = &[
        (&[], &[]),
        (
            &["gateway-no-response=exception-0B"],
            &["gateway-no-response=exception-0B"],
        ),
        (
            &["gateway-no-response=exception-0A"],
            &["gateway-no-response=exception-0A"],
        ),
        (
            &["tcp-unit-ids=exception-0B"],
            &["tcp-unit-ids=exception-0B"],
        ),
        (
            &["tcp-unit-ids=exception-0A"],
            &["tcp-unit-ids=exception-0A"],
        ),
        (&["tcp-unit-ids=silence"], &["tcp-unit-ids=silence"]),
        (
            &["tcp-unit-ids=silence", "gateway-no-response=exception-0B"],
            &["gateway-no-response=exception-0B"],
        ),
        (
            &[
                "truncated-pdu=silence",
                "gateway-no-response=exception-0B",
                "tcp-unit-ids=exception-0A",
            ],
            &[
                "truncated-pdu=silence",
                "gateway-no-response=exception-0B",
                "tcp-unit-ids=exception-0A",
            ],
        ),
    ];
    let mut problems = Vec::new();
    for (choose, shown) in configurations {
        let out = run(choose, &[]);
        let bad = out.summary.count(Verdict::Fail) + out.summary.count(Verdict::NonStrict);
        if bad > 0 {
            problems.push(format!(
                "--choose {choose:?}: {bad} FAIL or NON-STRICT: {:#?}",
                failures_of(&out)
            ));
        }
        for s in *shown {
            let (id, value) = s.split_once('=').expect("choice");
            let seen = out.summary.choices.iter().any(|c| {
                c.freedom == id && (c.value == value || c.changed.iter().any(|(v, _)| v == value))
            });
            if !seen {
                problems.push(format!("--choose {choose:?}: {s} not shown"));
            }
        }
    }
    assert!(problems.is_empty(), "{problems:#?}");
}

/// No fault of the drive hides behind a gateway that answers its silences with 0B: the fault matrix's
/// witness of every SD2x fault but those of the RTU framing FAILs behind it (where the case runs over
/// Modbus/TCP), and every case a fault makes FAIL
/// behind a silent gateway FAILs behind that one too. And the gateway's own exception is held to the form of
/// any exception: without the function code, with the transaction or unit id not echoed, the request to
/// unit 0xFF FAILs where it passes on a healthy box.
#[test]
fn no_fault_hides_behind_a_gateway_answering_0b() {
    let gateway = ["gateway-no-response=exception-0B"];
    let mut problems = Vec::new();
    let mut witnessed = 0;
    for (fault, target, case) in super::fault_matrix::WITNESSES {
        if target.split('?').next() != Some("sim:sd2x") {
            continue;
        }
        let fault: Fault = fault.parse().expect("fault");
        // A fault of the RTU framing (a CRC, a broadcast answered) is not on the Modbus/TCP side.
        let rtu_only = Fault::ALL
            .iter()
            .any(|(f, _, what)| *f == fault && what.starts_with("RTU:"));
        if rtu_only {
            continue;
        }
        let mut o = options(&gateway, &[fault]);
        o.include = vec![case.to_string()];
        let out = run_quietly(&o).expect("runs");
        match out.verdicts.first().map(|(_, v)| *v) {
            // An RTU case (a CRC, a slave address, the line's silences): not run over Modbus/TCP.
            None | Some(Verdict::Skipped) => {}
            Some(Verdict::Fail) => witnessed += 1,
            other => problems.push(format!("{fault:?}: witness {case} gives {other:?}")),
        }
    }
    assert!(
        witnessed >= 20,
        "only {witnessed} SD2x witnesses run over Modbus/TCP"
    );
    let mut seen = 0;
    for (fault, name, _) in Fault::ALL {
        let silent = failing(&run(&[], &[*fault]));
        let answering = failing(&run(&gateway, &[*fault]));
        seen += usize::from(!silent.is_empty());
        let hidden: Vec<&String> = silent.difference(&answering).collect();
        if !hidden.is_empty() {
            problems.push(format!(
                "{name}: FAIL behind a silent gateway, not behind one answering 0B: {hidden:?}"
            ));
        }
    }
    assert!(
        seen >= 30,
        "only {seen} faults FAIL a case over Modbus/TCP at all"
    );
    let healthy = failing(&run(&gateway, &[]));
    assert!(healthy.is_empty(), "{healthy:?}");
    for fault in [
        Fault::ExceptionWithoutFc,
        Fault::TidNotEchoed,
        Fault::UnitNotEchoed,
    ] {
        let mut o = options(&gateway, &[fault]);
        o.include = vec!["tcp/unit-id/255".into()];
        let out = run_quietly(&o).expect("runs");
        if out.verdicts.first().map(|(_, v)| *v) != Some(Verdict::Fail) {
            problems.push(format!(
                "{fault:?}: tcp/unit-id/255 gives {:?}",
                out.verdicts
            ));
        }
    }
    assert!(problems.is_empty(), "{problems:#?}");
}
