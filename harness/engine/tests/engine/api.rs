//! The library API (`engine::api`): a user's in-process [`Device`] judged by the catalog. A device that is
//! the reference drive behind the PDU seam passes over Modbus/TCP and RTU; the same drive with a fault
//! fails the fault's witness; a buggy closure is named in `assert_passes`'s panic; bad sessions are errors.

use std::time::Duration;

use codec::{rtu, tcp};
use drives::{Fault, FaultSet, Station};
use engine::api::{ApiError, Device, Results, Session, Verdict};

/// The reference drive of a corpus profile behind the PDU seam: each PDU is framed for the station and
/// its answer unframed again, so the harness's framing (`DeviceTarget`) is what the transport cases see.
struct StationDevice {
    station: Station,
    rtu: bool,
    now: Duration,
}

impl StationDevice {
    fn new(profile: &str, faults: &[Fault], rtu: bool) -> Self {
        let profile = drives::corpus::Corpus::Embedded
            .profile(profile)
            .expect("a built-in profile");
        let unit = profile.device.default_unit;
        let faults = FaultSet::of(faults);
        Self {
            station: Station::new(drives::build(profile, faults.clone()), faults, unit),
            rtu,
            now: Duration::ZERO,
        }
    }
}

impl Device for StationDevice {
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        let mut frame = Vec::new();
        if self.rtu {
            rtu::encode_adu(unit, pdu, &mut frame).ok()?;
            let answer = self.station.rtu_frame(self.now, &frame)?.bytes;
            Some(answer[1..answer.len() - 2].to_vec())
        } else {
            tcp::encode_adu(7, unit, pdu, &mut frame).ok()?;
            let answer = self.station.tcp_adu(self.now, &frame)?.bytes;
            Some(answer[tcp::MBAP_LEN..].to_vec())
        }
    }

    fn rtu_discarded(&mut self, bytes: &[u8]) {
        // The station counts a frame whose CRC does not check as a CRC error.
        let mut frame = bytes.to_vec();
        frame.truncate(256);
        if frame.len() >= 4 && rtu::crc_ok(&frame) {
            frame[0] ^= 0xFF;
        }
        self.station.rtu_frame(self.now, &frame);
    }

    fn advance(&mut self, now: Duration) {
        self.now = now;
        self.station.model_mut().advance(now);
    }
}

fn ran(results: &Results) -> usize {
    results.cases().len() - results.count(Verdict::Skipped)
}

/// The generic reference drive behind the PDU seam, over RTU framing when `rtu` (else Modbus/TCP): the run
/// passes and more than 100 cases ran.
fn reference_drive_behind_the_pdu_seam(rtu: bool) -> Results {
    let builder = Session::builder()
        .profile("generic")
        .device(StationDevice::new("generic", &[], rtu));
    let results = if rtu { builder.rtu() } else { builder.tcp() }.run();
    results.assert_passes();
    assert!(ran(&results) > 100, "{results}");
    results
}

#[test]
fn reference_drive_behind_the_pdu_seam_passes_over_tcp() {
    let results = reference_drive_behind_the_pdu_seam(false);
    assert!(results.verdict("tcp/mbap/transaction-id-echo").is_some());
}

#[test]
fn reference_drive_behind_the_pdu_seam_passes_over_rtu() {
    let results = reference_drive_behind_the_pdu_seam(true);
    assert!(
        results.cases().iter().any(|c| c.id.starts_with("rtu/")),
        "no RTU case ran:\n{results}"
    );
}

#[test]
fn a_fault_behind_the_pdu_seam_fails_its_witness() {
    let results = Session::builder()
        .profile("generic")
        .device(StationDevice::new(
            "generic",
            &[Fault::WrongExceptionCode],
            false,
        ))
        .cases("spec/*")
        .run();
    assert!(!results.passed(), "the fault went unnoticed:\n{results}");
    results.assert_fails("spec/app-7/unsupported-function/fc-0x09");
}

#[test]
fn assert_passes_names_the_failing_case_and_its_finding() {
    // FC 03 with a quantity of 0 answered with an empty read instead of exception 03.
    let device = |_unit: u8, pdu: &[u8]| -> Option<Vec<u8>> {
        match pdu {
            [0x03, _, _, 0, 0] => Some(vec![0x03, 0]),
            [fc, ..] => Some(vec![fc | 0x80, 0x01]),
            [] => None,
        }
    };
    let results = Session::builder()
        .profile("generic")
        .device(device)
        .cases("spec/app-6/quantity/fc-0x03/zero")
        .run();
    let message = std::panic::catch_unwind(|| results.assert_passes())
        .expect_err("assert_passes must panic on a FAIL");
    let message = message
        .downcast_ref::<String>()
        .expect("a formatted panic message");
    assert!(
        message.contains("FAIL spec/app-6/quantity/fc-0x03/zero"),
        "{message}"
    );
    assert!(message.contains("exception"), "{message}");
    assert_eq!(results.failing_ids(), ["spec/app-6/quantity/fc-0x03/zero"]);
}

#[test]
fn sessions_that_cannot_run_say_why() {
    let no_device = Session::builder().profile("generic").try_run();
    assert!(
        matches!(no_device, Err(ApiError::NoDevice)),
        "{no_device:?}"
    );
    let no_profile = Session::builder().device(|_: u8, _: &[u8]| None).try_run();
    assert!(
        matches!(no_profile, Err(ApiError::NoProfile)),
        "{no_profile:?}"
    );
    let nothing = Session::builder()
        .profile("generic")
        .device(|_: u8, _: &[u8]| None)
        .cases("no-such-suite/*")
        .try_run();
    assert!(
        matches!(nothing, Err(ApiError::NoCases { .. })),
        "{nothing:?}"
    );
    let unknown = Session::builder()
        .profile("no-such-drive")
        .device(|_: u8, _: &[u8]| None)
        .try_run();
    assert!(
        unknown
            .as_ref()
            .is_err_and(|e| e.to_string().contains("no-such-drive")),
        "{unknown:?}"
    );
}

#[test]
fn a_shared_device_can_be_inspected_after_the_run() {
    use std::cell::RefCell;
    use std::rc::Rc;
    let device = Rc::new(RefCell::new(StationDevice::new("generic", &[], false)));
    let results = Session::builder()
        .profile("generic")
        .device(Rc::clone(&device))
        .cases("spec/app-6/quantity/*")
        .run();
    results.assert_passes();
    // Every exception answer went through the shared device's station.
    let exceptions = device.borrow().station.counters().exception;
    assert!(
        usize::from(exceptions) >= results.count(Verdict::Pass),
        "{exceptions} exception(s) for {results}"
    );
}

/// An SD2x that follows its manual's only FC 43 example (lines 1302-1304: no Reserved byte after the
/// control code) instead of the section 3.6 layout (line 545, 561), written here as a translation around the
/// layout-form reference drive, independently of the simulator's own `--choose`: a request is read in the
/// example's form (a Reserved byte is put back before the drive sees it, so a request in the layout's form
/// is read one byte off), and the answer loses its Reserved byte.
struct ExampleFormFc43(StationDevice);

impl Device for ExampleFormFc43 {
    fn handle(&mut self, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
        let request = match pdu {
            [0x2B, 0x0D, control, rest @ ..] => [&[0x2B, 0x0D, *control, 0x00][..], rest].concat(),
            _ => pdu.to_vec(),
        };
        let answer = self.0.handle(unit, &request)?;
        Some(match answer.as_slice() {
            [0x2B, 0x0D, control, 0x00, rest @ ..] => [&[0x2B, 0x0D, *control][..], rest].concat(),
            _ => answer,
        })
    }

    fn rtu_discarded(&mut self, bytes: &[u8]) {
        self.0.rtu_discarded(bytes);
    }

    fn advance(&mut self, now: Duration) {
        self.0.advance(now);
    }
}

/// Such a drive conforms (freedom `sd2x-fc43-reserved-byte`): the harness learns its form before the cases,
/// sends every FC 43 request of the cases in it, and checks the objects it reads, instead of taking every
/// FC 43 case for a refusal the reading admits: the objects' values are compared, and a drive whose object
/// and register views disagree (fault `word-order`) still FAILs.
#[test]
fn an_sd2x_following_the_fc43_example_is_learned_and_its_objects_are_checked() {
    let session = |faults: &[Fault]| {
        Session::builder()
            .profile("sd2x")
            .device(ExampleFormFc43(StationDevice::new("sd2x", faults, true)))
            .rtu()
            .cases("profile/sd2x/object/*")
            .run()
    };
    let healthy = session(&[]);
    healthy.assert_passes();
    let reads: Vec<_> = healthy
        .cases()
        .iter()
        .filter(|c| {
            c.id.ends_with("/read")
                && !c.id.contains("/missing/")
                && !c.id.contains("/wrong-length/")
                && !c.id.contains("/zero-count/")
                && !c.id.contains("/count-over-4/")
                && !c.id.contains("/control-bits/")
                && !c.id.contains("/reserved-nonzero/")
                && !c.id.contains("/offset-nonzero/")
        })
        .collect();
    assert!(reads.len() >= 10, "{healthy}");
    for case in reads {
        // On the wire: the request without the Reserved byte (slave, 2B 0D, control 00, then the node id),
        // and the object in the answer, in the same form (not an exception, not an SDO error).
        let on_wire = |dir: engine::observe::Dir| -> Vec<&[u8]> {
            case.wire
                .iter()
                .filter(|w| w.dir == dir)
                .map(|w| w.bytes.as_slice())
                .collect()
        };
        let (tx, rx) = (
            on_wire(engine::observe::Dir::Tx),
            on_wire(engine::observe::Dir::Rx),
        );
        assert!(
            matches!(tx.as_slice(), [[_, 0x2B, 0x0D, 0x00, node, ..]] if *node != 0),
            "{}: sent {tx:02X?}",
            case.id
        );
        assert!(
            matches!(rx.as_slice(), [[_, 0x2B, 0x0D, 0x00, node, ..]] if *node != 0),
            "{}: got {rx:02X?}",
            case.id
        );
        assert_eq!(case.verdict, Verdict::Pass, "{}", case.id);
    }
    let faulty = session(&[Fault::WordOrder]);
    assert_eq!(
        faulty.verdict("profile/sd2x/object/2-hardware-id/agrees-with-register"),
        Some(Verdict::Fail),
        "{faulty}"
    );
}
