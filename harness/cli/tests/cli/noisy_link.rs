//! A drive behind an imperfect link (bench/noisy-link.py): an RS-485 line whose noise flips bits, loses
//! bytes, adds stray ones and cuts frames short, in both directions; a Modbus/TCP link that drops
//! connections (a request lost, an answer lost after the request was executed, an outage during which
//! connects are reset). One step cannot tell a drive from its link: a case that FAILed as a damaged link
//! makes a case fail is run again, and judged at the first attempt that comes through whole; one that FAILs
//! the same way again is the drive's own. Before, each damaged frame was a FAIL of a good drive.

use std::time::Duration;

use test_support::peer_servers::PeerServer;
use test_support::{SimProcess, TempDir, harness_bounded, run_args};

use super::leave_as_found::PresetDrive;

const RUN_LIMIT: Duration = Duration::from_secs(240);

/// The `link: ...` line of a run's log: (cases run again, of them come through whole, the same again).
fn link_line(err: &str) -> (usize, usize, usize) {
    let line = err
        .lines()
        .find(|l| l.starts_with("link: "))
        .unwrap_or_else(|| panic!("no link line in the log:\n{err}"));
    let num = |after: &str| -> usize {
        let i = line
            .find(after)
            .unwrap_or_else(|| panic!("{after:?} not in {line:?}"));
        let digits: String = line[..i]
            .chars()
            .rev()
            .skip_while(|c| *c == ' ')
            .take_while(char::is_ascii_digit)
            .collect::<Vec<_>>()
            .into_iter()
            .rev()
            .collect();
        digits
            .parse()
            .unwrap_or_else(|_| panic!("no number before {after:?} in {line:?}"))
    };
    (
        num(" case(s) run again"),
        num(" came through whole"),
        num(" FAILed the same way again"),
    )
}

/// The SD2x (preset off its factory values) behind a line with 25 damaged frames in 1,000: the catalog with
/// the flags PASSes, some cases run again and all of them come through, and every parameter reads as before;
/// with `--link-retries 0` the same line FAILs the run (the noise is real).
#[test]
fn an_rtu_drive_on_a_noisy_line_passes_and_is_left_as_found() {
    let dir = TempDir::new("noisy-rtu");
    let drive = PresetDrive::start_framed("sd2x", dir.path(), &[], true);
    let before = drive.read();
    let upstream = drive.sim.rtu_over_tcp.expect("rtu-over-tcp endpoint");
    let line = PeerServer::noisy_link(upstream, &["--mode", "rtu", "--rate", "25", "--seed", "7"]);
    let url = format!("rtu+tcp://{}", line.addr);
    let flags = ["--allow-motion", "--allow-destructive"];
    let (code, out, err) = harness_bounded(None, &run_args(&url, "sd2x", &flags), RUN_LIMIT);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS"), "{out}");
    let (again, through, same) = link_line(&err);
    assert!(again >= 1, "the noise damaged no case: {err}");
    assert_eq!((through, same), (again, 0), "{err}");
    // The summary says it on a line of its own (not as a liveness note).
    assert!(
        out.lines().any(|l| l.starts_with("link: ")) && !out.contains("liveness: link"),
        "{out}"
    );
    drive.assert_reads_as(&before, "after the catalog on a noisy line");

    let (code, out, err) = harness_bounded(
        None,
        &run_args(&url, "sd2x", &["--link-retries", "0"]),
        RUN_LIMIT,
    );
    assert_eq!(
        code, 1,
        "without reruns the noise FAILs cases: {out}\n{err}"
    );
    assert!(!err.contains("link: "), "{err}");
}

/// On the line of the test above, a fault of the drive that looks like a damaged link (it drops a request
/// whose quantity is above the specification's limit) still FAILs, judged at its first attempt, "the same
/// way again"; a fuzz campaign over the line has no finding.
#[test]
fn an_rtu_drive_on_a_noisy_line_still_fails_its_own_faults_and_fuzzes_clean() {
    let faulty = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--fault",
        "quantity-over-spec-dropped",
    ]);
    let noisy = PeerServer::noisy_link(
        faulty.rtu_over_tcp.expect("rtu-over-tcp endpoint"),
        &["--mode", "rtu", "--rate", "25", "--seed", "7"],
    );
    let (code, out, err) = harness_bounded(
        None,
        &run_args(
            &format!("rtu+tcp://{}", noisy.addr),
            "sd2x",
            &["--cases", "spec/app-6/quantity/*"],
        ),
        RUN_LIMIT,
    );
    assert_eq!(code, 1, "{out}\n{err}");
    assert!(
        out.contains("FAIL spec/app-6/quantity/fc-0x03/spec-max-plus-1"),
        "{out}"
    );
    let (again, _, same) = link_line(&err);
    assert!(same >= 1 && same <= again, "{err}");

    let dir = TempDir::new("noisy-rtu-fuzz");
    let drive = SimProcess::start(&["--profile", "sd2x", "--rtu-over-tcp", "127.0.0.1:0"]);
    let line = PeerServer::noisy_link(
        drive.rtu_over_tcp.expect("rtu-over-tcp endpoint"),
        &["--mode", "rtu", "--rate", "25", "--seed", "7"],
    );
    let url = format!("rtu+tcp://{}", line.addr);
    let (code, out, err) = harness_bounded(
        None,
        &[
            "fuzz",
            "--target",
            &url,
            "--profile",
            "sd2x",
            "--max-cases",
            "80",
            "--seed",
            "1",
            "--regressions",
            dir.path().join("regressions").to_str().expect("path"),
        ],
        RUN_LIMIT,
    );
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains(" 0 finding(s)"), "{out}\n{err}");
}

/// An MDrive (preset) behind a Modbus/TCP link that drops a connection at 15 requests in 1,000 (a request
/// lost, an answer lost after the drive executed the request, an outage of 600 ms with connects reset): the
/// catalog with the flags PASSes and every parameter reads as before; without reruns it FAILs.
#[test]
fn a_tcp_drive_behind_a_link_that_drops_passes_and_is_left_as_found() {
    let dir = TempDir::new("noisy-tcp");
    let drive = PresetDrive::start_framed("mdrive", dir.path(), &[], false);
    let before = drive.read();
    let upstream = drive.sim.tcp.expect("tcp endpoint");
    let link = PeerServer::noisy_link(
        upstream,
        &[
            "--mode",
            "tcp",
            "--rate",
            "15",
            "--seed",
            "3",
            "--outage-ms",
            "600",
        ],
    );
    let url = format!("tcp://{}", link.addr);
    let flags = ["--allow-motion", "--allow-destructive"];
    let (code, out, err) = harness_bounded(None, &run_args(&url, "mdrive", &flags), RUN_LIMIT);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS"), "{out}");
    let (again, through, _) = link_line(&err);
    assert!(again >= 1, "the link dropped no case: {err}");
    assert_eq!(through, again, "{err}");
    drive.assert_reads_as(&before, "after the catalog behind a link that drops");

    let (code, out, err) = harness_bounded(
        None,
        &run_args(&url, "mdrive", &["--link-retries", "0"]),
        RUN_LIMIT,
    );
    assert_eq!(code, 1, "without reruns the drops FAIL cases: {out}\n{err}");
}

/// A generated run has many cases of a kind: once one FAILed the same way at every attempt (the drive's own),
/// another of its kind that FAILs the same way at the same step is judged at its first attempt, not run
/// again. Against a drive that drops requests with a quantity above the specification's limit (a fault
/// that looks like a lost frame), 300 generated cases of seed 1: every FAIL is run again or named "not run
/// again" (at least one is), and the verdicts are those of a run that judges every first attempt.
#[test]
fn a_kind_of_generated_case_proven_the_drives_own_is_not_run_again() {
    let sim = SimProcess::start(&[
        "--profile",
        "generic",
        "--listen",
        "127.0.0.1:0",
        "--fault",
        "quantity-over-spec-dropped",
    ]);
    let target = format!("tcp://{}", sim.tcp.expect("tcp endpoint"));
    let dir = TempDir::new("own-kinds");
    let report = dir.path().join("report");
    let report_s = report.to_string_lossy().into_owned();
    let generated = [
        "--generated",
        "300",
        "--seed",
        "1",
        "--no-shrink",
        "--timeout",
        "200",
    ];
    let mut args = run_args(&target, "generic", &generated);
    args.extend_from_slice(&["--report", &report_s]);
    let (code, out, err) = harness_bounded(None, &args, RUN_LIMIT);
    assert_eq!(code, 1, "{out}\n{err}");
    let records = std::fs::read_to_string(report.join("cases.jsonl")).expect("cases.jsonl");
    let fails: Vec<(String, bool)> = records
        .lines()
        .filter_map(|l| {
            let c: serde_json::Value = serde_json::from_str(l).expect("a case record");
            (c["result"]["verdict"] == "FAIL").then(|| {
                (
                    c["case"]["id"].as_str().expect("id").to_string(),
                    l.contains("as a case of its kind did before at every attempt"),
                )
            })
        })
        .collect();
    let not_again = fails.iter().filter(|(_, n)| *n).count();
    assert!(not_again >= 1, "no FAIL was judged as its kind: {fails:?}");
    let (again, through, same) = link_line(&err);
    assert_eq!(
        (again + not_again, through, same),
        (fails.len(), 0, again),
        "{err}"
    );

    let mut first = run_args(&target, "generic", &generated);
    first.extend_from_slice(&["--link-retries", "0"]);
    let (code0, out0, err0) = harness_bounded(None, &first, RUN_LIMIT);
    assert_eq!(code0, 1, "{out0}\n{err0}");
    let failing = |out: &str| -> Vec<String> {
        out.lines()
            .filter_map(|l| l.strip_prefix("FAIL "))
            .map(|l| l.split_whitespace().next().unwrap_or("").to_string())
            .collect()
    };
    assert_eq!(failing(&out), failing(&out0), "{out}\n{out0}");
    assert!(!failing(&out).is_empty());
}

/// Noise may damage the pre-flight's known-good read on an RS-485 line (serial line spec 2.5.1.2): a slave
/// discards it and stays silent. With reruns (the default) the read is asked twice more over RTU before the
/// target counts as not answering: a line that loses the first two reads still runs (one case, PASS); a
/// third lost read, or one lost read with `--link-retries 0`, is "does not answer" (exit 2), no case run.
#[test]
fn an_rtu_preflight_read_lost_on_the_line_is_asked_again() {
    let sim = SimProcess::start(&["--profile", "sd2x", "--rtu-over-tcp", "127.0.0.1:0"]);
    let upstream = sim.rtu_over_tcp.expect("rtu-over-tcp endpoint");
    let case = ["--cases", "golden/sd2x/6.2/read-temperature/request"];
    for (lose, retries, code) in [("2", "2", 0), ("3", "2", 2), ("1", "0", 2)] {
        let line = PeerServer::noisy_link(
            upstream,
            &["--mode", "rtu", "--rate", "0", "--lose-first", lose],
        );
        let url = format!("rtu+tcp://{}", line.addr);
        let mut extra = vec!["--preflight-timeout", "500", "--link-retries", retries];
        extra.extend_from_slice(&case);
        let (got, out, err) = harness_bounded(None, &run_args(&url, "sd2x", &extra), RUN_LIMIT);
        let row = format!("{lose} read(s) lost, --link-retries {retries}");
        assert_eq!(got, code, "{row}\n{out}\n{err}");
        if code == 0 {
            assert!(out.contains("RESULT: PASS (1 PASS)"), "{row}\n{out}");
        } else {
            assert!(err.contains("does not answer"), "{row}\n{err}");
            assert!(!out.contains("RESULT:"), "{row}: no case is run\n{out}");
        }
    }
    drop(sim);
}

/// The liveness probe after a case whose due answer did not come may be lost on the line as well. The drive
/// here chooses silence for a request too short for its function code (`truncated-pdu`, which admits it), and
/// the generated case has no known-good read of its own after it: the harness probes after the case. With
/// reruns (the default) a probe that gets no answer is asked twice more before the target counts as having
/// stopped answering: a line that loses the first two probes PASSes; a third lost probe, or one lost probe
/// with `--link-retries 0`, FAILs the case with "stopped answering" (the silence is then real to the
/// harness). Before, one lost probe FAILed this good drive.
#[test]
fn a_liveness_probe_lost_on_the_line_is_asked_again() {
    let sim = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--choose",
        "truncated-pdu=silence",
        "--choose",
        "rtu-length-framing=silence",
    ]);
    let upstream = sim.rtu_over_tcp.expect("rtu-over-tcp endpoint");
    // An FC 03 read cut to 4 bytes, alone in its case (no known-good read follows it in the case).
    let case = [
        "--generated",
        "300",
        "--seed",
        "1",
        "--cases",
        "gen/1/164/read-reg-truncated",
        "--foreign-address",
        "3",
        "--preflight-timeout",
        "500",
    ];
    for (lose, retries, code) in [("2", "2", 0), ("3", "2", 1), ("1", "0", 1)] {
        let line = PeerServer::noisy_link(
            upstream,
            &[
                "--mode",
                "rtu",
                "--rate",
                "0",
                "--lose-after-unanswered",
                lose,
            ],
        );
        let url = format!("rtu+tcp://{}", line.addr);
        let mut extra = vec!["--link-retries", retries];
        extra.extend_from_slice(&case);
        let (got, out, err) = harness_bounded(None, &run_args(&url, "sd2x", &extra), RUN_LIMIT);
        let row = format!("{lose} probe(s) lost, --link-retries {retries}");
        assert_eq!(got, code, "{row}\n{out}\n{err}");
        assert!(
            out.contains("truncated-pdu [FC 0x03] = silence"),
            "{row}: the case is the one meant\n{out}"
        );
        if code == 0 {
            assert!(out.contains("RESULT: PASS (1 PASS)"), "{row}\n{out}");
            assert!(!err.contains("stopped answering"), "{row}\n{err}");
        } else {
            assert!(out.contains("RESULT: FAIL (1 FAIL)"), "{row}\n{out}");
            assert!(
                out.contains("the target stopped answering after this request"),
                "{row}\n{out}"
            );
        }
    }
    drop(sim);
}
