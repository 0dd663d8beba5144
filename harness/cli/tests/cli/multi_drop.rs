//! A drive on a multi-drop RS-485 line with other devices (MODBUS over Serial Line V1.02, 2.1: one master, up
//! to 247 slaves). bench/line.py joins RTU-over-TCP drives into one line: every frame the harness sends
//! reaches every drive. The cases that check a frame for another slave goes unanswered used to send it to the
//! address next but one to the drive's, which on a line numbered from 1 up is another device's: its answer
//! was taken for the drive's (`rtu/address/other-slave-silence` FAILed, and with the flags
//! `rtu/fc08/counters` too). The line survey at the start of the run finds an address nothing answers and
//! says which answered.
//!
//! Every drive hears the others' replies, as on a real line. The reference drive sized what it heard by the
//! request layouts only, so another slave's reply followed at once by the master's next request reached it
//! as one run of bytes, which it discarded with the request in it; it now sizes the frame after a request
//! for another slave by the response layouts too (`RtuFramer::listen_as`).

use std::time::Duration;

use test_support::peer_servers::PeerServer;
use test_support::{SimProcess, TempDir, harness_bounded, run_args};

use super::leave_as_found::{PresetDrive, journal_lines};

const RUN_LIMIT: Duration = Duration::from_secs(120);

/// The SD2x at slave 1 (preset off its factory values), another SD2x at slave 3 that records every write it
/// takes, on one line.
fn line_of_two(dir: &std::path::Path) -> (PresetDrive, SimProcess, PeerServer, std::path::PathBuf) {
    let drive = PresetDrive::start_framed("sd2x", dir, &[], true);
    let journal = dir.join("neighbour.jsonl");
    let neighbour = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--unit",
        "3",
        "--journal",
        journal.to_str().expect("path"),
    ]);
    let line = PeerServer::line(
        &[
            drive.sim.rtu_over_tcp.expect("rtu-over-tcp endpoint"),
            neighbour.rtu_over_tcp.expect("rtu-over-tcp endpoint"),
        ],
        &[],
    );
    (drive, neighbour, line, journal)
}

/// The addressing cases against `url` with `extra`: they FAIL `other-slave-silence` (exit 1). The log.
fn addressing_fails(url: &str, extra: &[&str]) -> String {
    let mut args = vec!["--cases", "rtu/address/*"];
    args.extend_from_slice(extra);
    let (code, out, err) = harness_bounded(None, &run_args(url, "sd2x", &args), RUN_LIMIT);
    assert_eq!(code, 1, "{out}\n{err}");
    assert!(
        out.contains("FAIL rtu/address/other-slave-silence"),
        "{out}"
    );
    err
}

/// The catalog (and with the flags, the FC 08 counters case) and a generated run PASS against the drive at
/// slave 1 with another SD2x at slave 3 on its line, the run saying that slave 3 answered and sending its
/// frames for another slave to 247; the drive is left as found and the neighbour takes no write.
/// `--foreign-address 3` sends them to the neighbour, as for a drive alone on its line, and the case FAILs.
#[test]
fn a_drive_on_a_line_with_another_drive_is_judged_alone_and_both_are_left_as_found() {
    let dir = TempDir::new("multi-drop");
    let (drive, _neighbour, line, journal) = line_of_two(dir.path());
    let before = drive.read();
    let url = format!("rtu+tcp://{}", line.addr);
    for extra in [
        &[][..],
        &["--cases", "rtu/*", "--allow-destructive"][..],
        &["--generated", "300", "--seed", "1"][..],
    ] {
        let (code, out, err) = harness_bounded(None, &run_args(&url, "sd2x", extra), RUN_LIMIT);
        assert_eq!(code, 0, "{extra:?}: {out}\n{err}");
        assert!(out.contains("RESULT: PASS"), "{extra:?}: {out}");
        assert!(
            err.contains("line: slave 3 answered a read (03 03 02")
                && err.contains("nothing answers slave 247"),
            "{extra:?}: the survey is not said: {err}"
        );
    }
    let err = addressing_fails(&url, &["--foreign-address", "3"]);
    assert!(
        !err.contains("line:"),
        "no survey with --foreign-address: {err}"
    );
    drive.assert_reads_as(&before, "the drive on the line: not left as found");
    let writes = journal_lines(&journal);
    assert!(writes.is_empty(), "the neighbour took writes: {writes:?}");
}

/// A drive that answers frames for every address (`--fault answer-other-unit`), alone on its line: every
/// address the survey tries answers, so the run says the drive answers frames for other slaves, and the case
/// sends to the first and FAILs, as before the survey. `--foreign-address` the drive's own address is refused.
#[test]
fn a_drive_answering_every_address_still_fails_and_a_foreign_address_of_its_own_is_refused() {
    let sim = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--fault",
        "answer-other-unit",
    ]);
    let url = format!("rtu+tcp://{}", sim.rtu_over_tcp.expect("endpoint"));
    let err = addressing_fails(&url, &[]);
    assert!(
        err.contains("slave 3 answered")
            && err.contains("slave 247 answered")
            && err.contains("slave 124 answered")
            && err.contains("the drive answers frames for other slaves"),
        "{err}"
    );
    for own in ["1", "2"] {
        let (code, out, err) = harness_bounded(
            None,
            &run_args(&url, "sd2x", &["--foreign-address", own]),
            RUN_LIMIT,
        );
        assert_eq!(code, 2, "--foreign-address {own}: {out}\n{err}");
        assert!(
            err.contains(&format!(
                "--foreign-address {own} is the drive's own address"
            )),
            "{err}"
        );
    }
}

/// The drive at slave 3 with another SD2x at slave 1 on its line: the manual's examples, printed for slave 1,
/// go to the drive at 3, also with the flags, and the SD2x at 1 takes no write. Before, they went to slave
/// 1 as printed: the catalog FAILed them (the other drive answered), and with the flags the examples of
/// 6.1 (shutdown, enable operation, 100 Hz, the watchdog on) were written to the other drive and left it
/// in fault.
#[test]
fn the_manuals_examples_go_to_the_drive_under_test_not_to_slave_1() {
    let dir = TempDir::new("multi-drop-golden");
    let journal = dir.path().join("slave-1.jsonl");
    let slave_1 = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--journal",
        journal.to_str().expect("path"),
    ]);
    let drive = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--unit",
        "3",
    ]);
    let line = PeerServer::line(
        &[
            slave_1.rtu_over_tcp.expect("endpoint"),
            drive.rtu_over_tcp.expect("endpoint"),
        ],
        &[],
    );
    let url = format!("rtu+tcp://{}", line.addr);
    let (code, out, err) = harness_bounded(
        None,
        &run_args(
            &url,
            "sd2x",
            &[
                "--unit",
                "3",
                "--cases",
                "golden/*",
                "--allow-motion",
                "--allow-destructive",
            ],
        ),
        RUN_LIMIT,
    );
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS"), "{out}");
    assert!(
        out.contains("every kept parameter reads as before"),
        "{out}"
    );
    let writes = journal_lines(&journal);
    assert!(writes.is_empty(), "slave 1 took writes: {writes:?}");
}
