//! The `run` and `probe` commands as a user meets them: clear errors with exit code 2, reports on disk,
//! safety on real targets, `--profile auto`, and an interrupted run that still leaves a complete report.

use std::sync::atomic::{AtomicBool, Ordering};

use engine::session::{Options, resolve_profile, run};
use engine::targets::TargetUrl;
use test_support::{
    TempDir, harness, harness_ok, loopback_tcp_and_rtu, read_json, serve, sim_run_args,
    sim_run_reported,
};

#[test]
fn bad_targets_exit_2_with_a_clear_message() {
    let cases: &[(&[&str], &str)] = &[
        (&["run", "--target", "bogus://x"], "unknown scheme `bogus`"),
        (
            &[
                "run",
                "--target",
                "tcp://127.0.0.1:notaport",
                "--profile",
                "mdrive",
            ],
            "is not a number",
        ),
        (&["run", "--target", "sim:nope"], "known profiles"),
        (
            &[
                "run",
                "--target",
                "rtu:///dev/modbus-harness-no-such-tty",
                "--profile",
                "sd2x",
            ],
            "no such device",
        ),
        (
            &[
                "run",
                "--target",
                "rtu:///dev/ttyS0?baud=fast",
                "--profile",
                "sd2x",
            ],
            "baud `fast`",
        ),
        (
            &[
                "run",
                "--target",
                "tcp://127.0.0.1:1",
                "--profile",
                "mdrive",
                "--timeout",
                "200",
            ],
            "cannot connect to 127.0.0.1:1",
        ),
        (
            &["run", "--target", "tcp://127.0.0.1:502"],
            "--profile is required",
        ),
        (
            &["run", "--target", "sim:sd2x", "--fault", "nonsense"],
            "unknown fault `nonsense`",
        ),
        (
            &[
                "run",
                "--target",
                "tcp://127.0.0.1:1",
                "--profile",
                "mdrive",
                "--fault",
                "word-order",
            ],
            "in-process simulator only",
        ),
        (
            &["probe", "--target", "sim:mdrive", "--scan", "9-3"],
            "--scan",
        ),
    ];
    for (args, want) in cases {
        let (code, _, err) = harness(args);
        assert_eq!(code, 2, "{args:?}: exit code, stderr: {err}");
        assert!(err.contains(want), "{args:?}: stderr lacks `{want}`: {err}");
        assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    }
}

#[test]
fn a_run_writes_every_report_and_exits_by_verdict() {
    let (_dir, report, (code, out, err)) = sim_run_reported("cli-run", "sim:sd2x", &[]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(
        out.trim_end()
            .lines()
            .last()
            .unwrap_or("")
            .starts_with("RESULT: PASS"),
        "summary last: {out}"
    );
    // The result line is a whole line: a shell prompt or the next command's output starts on its own.
    assert!(out.ends_with(")\n"), "no newline after the result: {out:?}");
    for f in test_support::reports::REPORT_FILES {
        assert!(report.join(f).is_file(), "{f} missing");
    }
    let (code, out, _) = harness(&sim_run_args("sim:mdrive", &["--fault", "range-unchecked"]));
    assert_eq!(code, 1, "a FAIL exits 1: {out}");
    assert!(
        out.contains("FAIL profile/mdrive/write-out-of-range/"),
        "{out}"
    );
}

#[test]
fn shuffle_prints_the_order_and_keeps_the_ids() {
    let (_dir, report, (code, out, err)) =
        sim_run_reported("cli-shuffle", "sim:lmd", &["--shuffle", "42"]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(
        err.contains("shuffled with seed 42 (replay with --shuffle 42)"),
        "{err}"
    );
    assert!(out.contains("order shuffled with seed 42"), "{out}");
    // The order printed is the order run, and the reports keep the catalog's ids.
    let printed: Vec<&str> = err
        .lines()
        .skip_while(|l| !l.starts_with("order:"))
        .skip(1)
        .map_while(|l| l.trim_start().split_once(' ').map(|(_, id)| id))
        .collect();
    let index = read_json(&report.join("index.json"));
    let reported: Vec<&str> = index["cases"]
        .as_array()
        .expect("cases")
        .iter()
        .filter_map(|c| c["id"].as_str())
        .collect();
    assert_eq!(printed, reported);
    let (_, listed, _) = harness(&["run", "--list", "--target", "sim:lmd"]);
    let mut catalog: Vec<&str> = listed
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .filter(|id| id.contains('/'))
        .collect();
    assert_ne!(catalog, reported, "the order is shuffled");
    assert_eq!(
        reported.last(),
        catalog.last(),
        "what cannot be undone runs last"
    );
    catalog.sort_unstable();
    let mut ids = reported.clone();
    ids.sort_unstable();
    assert_eq!(catalog, ids, "the same cases, the same ids");
}

#[test]
fn dry_run_shows_the_safety_policy_without_touching_the_target() {
    // Nothing listens on port 1: a dry run must not connect.
    let out = harness_ok(
        None,
        &[
            "run",
            "--dry-run",
            "--target",
            "tcp://127.0.0.1:1",
            "--profile",
            "mdrive",
        ],
    );
    assert!(
        out.contains("SKIP profile/mdrive/write/0x0043-ma"),
        "a move is skipped without --allow-motion: {out}"
    );
    assert!(out.contains("--allow-motion"), "{out}");
    assert!(out.contains("RUN  profile/mdrive/read/0x008B-vm"), "{out}");
    let (_, out, _) = harness(&[
        "run",
        "--dry-run",
        "--read-only",
        "--target",
        "tcp://127.0.0.1:1",
        "--profile",
        "mdrive",
    ]);
    assert!(
        out.contains("SKIP profile/mdrive/write/0x008B-vm") && out.contains("--read-only"),
        "{out}"
    );
    let (_, out, _) = harness(&[
        "run", "--list", "--target", "sim:sd2x", "--cases", "golden/*",
    ]);
    assert!(
        out.contains("golden/sd2x/6.3/status-read/request") && !out.contains("profile/sd2x/"),
        "{out}"
    );
}

#[test]
fn probe_finds_what_the_profile_documents() {
    for p in ["mdrive", "sd2x", "generic"] {
        let scan = if p == "sd2x" { "1995-2030" } else { "0-0xC0" };
        let out = harness_ok(
            None,
            &["probe", "--target", &format!("sim:{p}"), "--scan", scan],
        );
        assert!(
            !out.contains("DIFFERENT") && !out.contains("<-"),
            "{p}: {out}"
        );
        assert!(out.contains("none of them writes"), "{out}");
    }
}

#[test]
fn profile_auto_reads_the_identification() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    for p in ["mdrive", "lmd"] {
        let h = rt.block_on(serve(p, &[], loopback_tcp_and_rtu()));
        let mut o =
            Options::new(TargetUrl::parse(&format!("tcp://{}", h.tcp_addr().unwrap())).unwrap());
        o.profile = Some("auto".into());
        let mut log = Vec::new();
        let got = resolve_profile(&o, &mut log).expect("auto resolves");
        assert_eq!(got.device.id, p, "{}", String::from_utf8_lossy(&log));
        assert!(
            String::from_utf8_lossy(&log).contains("picked"),
            "says what it found"
        );
        let log = String::from_utf8_lossy(&log);
        assert!(
            log.contains("VendorName (0x00)") && log.contains("ProductCode (0x01)"),
            "says which objects matched: {log}"
        );
    }
}

#[test]
fn an_interrupted_run_leaves_a_complete_report() {
    let dir = TempDir::new("cli-interrupt");
    let mut o = Options::new(TargetUrl::parse("sim:mdrive").unwrap());
    o.report_dir = Some(dir.path().join("r"));
    let stop = AtomicBool::new(false);
    let out = run(&o, &mut std::io::sink(), &stop, &mut |done, _, _, _| {
        if done == 10 {
            stop.store(true, Ordering::SeqCst);
        }
    })
    .expect("run");
    assert!(out.summary.interrupted);
    assert_eq!(out.summary.cases, 10);
    // index.json is written, and complete JSON.
    let index = read_json(&dir.path().join("r/index.json"));
    assert_eq!(index["cases"].as_array().map(|a| a.len()), Some(10));
    assert_eq!(
        index["summary"]["interrupted"],
        serde_json::Value::Bool(true)
    ); // Every report is complete, and says why the run ended.
    assert!(
        index["summary"]["ended"]
            .as_str()
            .is_some_and(|e| e.starts_with("interrupted")),
        "{}",
        index["summary"]
    );
    for f in ["junit.xml", "report.html", "session.pcapng"] {
        assert!(dir.path().join("r").join(f).is_file(), "{f} missing");
    }
    // cases.jsonl has a whole line for each of the 10 cases that ran, in the index's order.
    let lines =
        std::fs::read_to_string(dir.path().join("r/cases.jsonl")).expect("cases.jsonl written");
    assert!(lines.ends_with('\n'), "the last line is cut short");
    let ids: Vec<String> = lines
        .lines()
        .map(|l| {
            let record: serde_json::Value = serde_json::from_str(l).expect("line parses");
            record["result"]["id"].as_str().expect("id").to_string()
        })
        .collect();
    let indexed: Vec<String> = index["cases"]
        .as_array()
        .expect("cases")
        .iter()
        .filter_map(|c| c["id"].as_str().map(str::to_string))
        .collect();
    assert_eq!(ids, indexed);
    assert!(!dir.path().join("r/cases.jsonl.partial").exists());
}

/// A drive busy for 400 ms after an NVM save (`simulate --choose busy-after-long-command=all-requests`, over
/// Modbus/TCP in real time): the S case, then the cases behind it, PASS, their requests answered Server
/// Busy (06) sent again until the drive is free (App 7), the drive left as found; with `--busy-wait 0` the
/// 06 is judged as the answer: the cases behind the save FAIL, and the keeper's reads at the end, refused
/// too, leave it unable to say the drive is as found (NOT RESTORED, exit 3).
#[test]
fn a_drive_busy_after_a_save_is_asked_again_within_busy_wait() {
    let sim = test_support::SimProcess::start(&[
        "--profile",
        "lmd",
        "--choose",
        "busy-after-long-command=all-requests",
        "--listen",
        "127.0.0.1:0",
    ]);
    let target = sim.tcp_url();
    let cases = [
        "--cases",
        "profile/lmd/write/0x0076-s",
        "--cases",
        "profile/lmd/read/0x0077-sf",
        "--cases",
        "profile/lmd/write/0x0077-sf",
    ];
    let run = |extra: &[&str]| {
        let mut args = vec![
            "run",
            "--target",
            &target,
            "--profile",
            "lmd",
            "--allow-destructive",
            "--no-progress",
        ];
        args.extend_from_slice(&cases);
        args.extend_from_slice(extra);
        test_support::harness_bounded(None, &args, std::time::Duration::from_secs(60))
    };
    let (code, out, err) = run(&[]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS (3 PASS)"), "{out}");
    assert!(
        out.contains("every kept parameter reads as before"),
        "{out}"
    );
    let (code, out, err) = run(&["--busy-wait", "0"]);
    assert_eq!(code, 3, "{out}\n{err}");
    assert!(
        out.contains("RESULT: NOT RESTORED (2 FAIL, 1 PASS)"),
        "{out}"
    );
    assert!(out.contains("exception 6 (0x6)"), "{out}");
}
