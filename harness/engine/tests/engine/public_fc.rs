//! The catalog cases of the public function code set (FC 07-18, spec 6.7-6.18): the freedom that lets a
//! server report its run indicator OFF, and the FC 14 capture that an FC 15 case writes back.

use codec::{FileRecordRef, Framing, Request, Response, rtu};
use drives::corpus::Corpus;
use engine::capture::{Captured, captured};
use engine::oracle::StepContext;
use engine::oracle::freedoms::alternatives;

/// The embedded requirements and the generic profile.
fn corpus() -> (drives::requirements::Requirements, drives::profile::Profile) {
    let reqs = Corpus::Embedded
        .requirements()
        .unwrap_or_else(|e| panic!("{e}"));
    let p = Corpus::Embedded.profile("generic").expect("generic");
    (reqs, p)
}

/// The context of a step sending `req` to unit 1 of `p`, well-formed, nothing decided yet.
fn context<'a>(p: &'a drives::profile::Profile, req: &'a Request) -> StepContext<'a> {
    StepContext {
        request: Some(req),
        pdu: &[],
        unit: 1,
        run_unit: 1,
        profile: p,
        malformed: false,
        batch: false,
        decided: &[],
        counter_alternatives: &[],
        choice_alternatives: &[],
        closed: false,
        short_of_length: false,
        gateway: false,
    }
}

/// `check` with the corpus freedom `id` and the context of a step sending `req` to the generic profile.
fn with_freedom(
    id: &str,
    req: Request,
    check: impl FnOnce(&drives::requirements::Freedom, &StepContext<'_>),
) {
    let (reqs, p) = corpus();
    let f = reqs.freedom(id).expect("freedom in the corpus");
    check(f, &context(&p, &req));
}

fn server_id(run: u8) -> Response {
    let mut data = vec![0x47, run];
    data.extend_from_slice(b"modbus-harness generic");
    Response::ReportServerId { data }
}

/// `run-indicator-status`: OFF (0x00) is admissible where the reference answers ON; 0x01, or another byte
/// changed, is not.
#[test]
fn run_indicator_off_is_admissible_and_0x01_is_not() {
    with_freedom("run-indicator-status", Request::ReportServerId, |f, cx| {
        let on = server_id(0xFF);
        let off = alternatives(f, cx, Some(&on), Some(&server_id(0x00)));
        assert_eq!(off.len(), 1);
        assert_eq!(off[0].shown.value, "off");
        assert_eq!(off[0].answer.as_ref(), Some(&server_id(0x00)));
        assert!(alternatives(f, cx, Some(&on), Some(&server_id(0x01))).is_empty());
        let mut other_id = server_id(0x00);
        if let Response::ReportServerId { data } = &mut other_id {
            data[0] = 0x48;
        }
        assert!(alternatives(f, cx, Some(&on), Some(&other_id)).is_empty());
    });
}

/// A one-group FC 14 answer is kept and written back with FC 15 at the same records.
#[test]
fn file_records_are_captured_and_restored_with_fc15() {
    let req = Request::ReadFileRecord {
        sub_requests: vec![FileRecordRef {
            reference_type: 6,
            file_number: 4,
            record_number: 1,
            record_length: 2,
        }],
    };
    let req_pdu = req.to_bytes().expect("encodes");
    let mut adu = Vec::new();
    rtu::encode_adu(
        1,
        &[0x14, 0x06, 0x05, 0x06, 0x0D, 0xFE, 0x00, 0x20],
        &mut adu,
    )
    .expect("encodes");
    let kept = captured(Framing::Rtu, &req_pdu, &adu).expect("captured");
    assert!(matches!(
        kept,
        Captured::FileRecords {
            file_number: 4,
            record_number: 1,
            ..
        }
    ));
    let p = Corpus::Embedded.profile("generic").expect("generic");
    let back = kept.restore(None, &p).expect("a restore");
    assert_eq!(
        back.to_bytes().expect("encodes"),
        vec![
            0x15, 0x0B, 0x06, 0x00, 0x04, 0x00, 0x01, 0x00, 0x02, 0x0D, 0xFE, 0x00, 0x20
        ]
    );
}

/// `event-counter-clear-counted`: one more than the reference after 08/0A is admissible (the clearing request
/// counted), two more (the exceptions counted, fault `event-counter-counts-exceptions`) is not.
#[test]
fn event_counter_may_count_the_clear_but_nothing_more() {
    with_freedom(
        "event-counter-clear-counted",
        Request::GetCommEventCounter,
        |f, cx| {
            let count = |n| Response::GetCommEventCounter {
                status: 0,
                event_count: n,
            };
            let one_more = alternatives(f, cx, Some(&count(1)), Some(&count(2)));
            assert_eq!(one_more.len(), 1);
            assert_eq!(one_more[0].shown.value, "counted");
            assert!(alternatives(f, cx, Some(&count(1)), Some(&count(3))).is_empty());
            assert!(alternatives(f, cx, Some(&count(1)), Some(&count(0))).is_empty());
        },
    );
}

/// `truncated-pdu`: where the reference refuses a truncated PDU with 03 and the drive closes the connection
/// (Modbus/TCP), the close is the freedom's `close`, admitted without a finding; a close where the freedom
/// does not apply still fails. (Before, a close was taken for `silence` with a SHOULD finding, and a close
/// where no freedom applies is a MUST.)
#[test]
fn a_close_is_the_outcome_close_not_silence() {
    use engine::cases::Compare;
    use engine::oracle::{Judged, Observation, Sent, judge_admitting};
    use engine::targets::Received;
    use std::time::Duration;

    let (reqs, p) = corpus();
    let f = reqs
        .freedom("truncated-pdu")
        .expect("freedom in the corpus");
    let sent = Sent {
        tid: Some(7),
        unit: 1,
        pdu: vec![0x05, 0x00],
    };
    let mut reference = Vec::new();
    codec::tcp::encode_adu(7, 1, &[0x85, 0x03], &mut reference).expect("encodes");
    let closed = Received::Closed {
        partial: vec![],
        at: Duration::ZERO,
    };
    let judge =
        |applicable: &[&drives::requirements::Freedom], decided: &[drives::Decision]| -> Judged {
            let cx = StepContext {
                request: None,
                pdu: &[],
                unit: 1,
                run_unit: 1,
                profile: &p,
                malformed: true,
                batch: false,
                decided,
                counter_alternatives: &[],
                choice_alternatives: &[],
                closed: true,
                short_of_length: false,
                gateway: false,
            };
            let observation = Observation {
                framing: Framing::Tcp,
                sent: &sent,
                expected: Some(&reference),
                observed: &closed,
                compare: &Compare::Exact,
                profile: &p,
                reference_closed: false,
            };
            judge_admitting(&observation, applicable, &cx)
        };
    let admitted = judge(&[f], &[drives::choices::ids::TRUNCATED_PDU]);
    assert!(admitted.findings.is_empty(), "{:?}", admitted.findings);
    assert_eq!(admitted.shown.len(), 1);
    assert_eq!(admitted.shown[0].value, "close");
    let not_admitted = judge(&[], &[]);
    assert!(!not_admitted.findings.is_empty());
}
