//! The edges of the command line a CI job meets: a committed insta snapshot compared as it is, an empty
//! selection or a bad glob (exit 2), unused and stale expectations (`--strict-expect`), progress lines
//! without a terminal, capped FAIL details, and `run --list` into a pipe that closes early.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use test_support::{TempDir, harness, sim_run_args, sim_run_reported};

/// The workspace's top-level directory (where `snapshots/` is).
fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The run `snapshots/README.md` gives for the committed SD2x RTU snapshot, against `snapshot`.
fn sd2x_snapshot_run(snapshot: &Path, extra: &[&str]) -> (i32, String, String) {
    let mut args = vec![
        "run",
        "--target",
        "sim:sd2x?transport=rtu",
        "--policy-on-sim",
        "--generated",
        "60",
        "--seed",
        "20240601",
        "--no-progress",
        "--snapshot",
        snapshot.to_str().expect("utf-8 path"),
    ];
    args.extend_from_slice(extra);
    harness(&args)
}

#[test]
fn a_committed_insta_snapshot_compares_clean_on_a_healthy_target_and_drifts_when_changed() {
    let committed = workspace().join("snapshots/generated-sd2x-rtu.snap");
    let text = std::fs::read_to_string(&committed).expect("committed snapshot");
    assert!(text.starts_with("---\n"), "an insta file with front matter");
    let (code, out, err) = sd2x_snapshot_run(&committed, &[]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("no drift (60 cases the same)"), "{out}");
    assert!(!out.contains("headers differ"), "{out}");

    // The same file with one observation changed drifts: the front matter is skipped, not the text.
    let dir = TempDir::new("cli-edges-snap");
    let changed = dir.path().join("changed.snap");
    let (pos, _) = text
        .match_indices("\n== ")
        .filter(|(at, _)| !text[at + 1..].starts_with("== choice/"))
        .nth(3)
        .expect("a fourth case block");
    let line_end = pos + 1 + text[pos + 1..].find('\n').expect("block line");
    let mut edited = text.clone();
    edited.insert_str(line_end + 1, "  an observation no drive made\n");
    std::fs::write(&changed, edited).expect("write");
    let (code, out, _) = sd2x_snapshot_run(&changed, &[]);
    assert_eq!(code, 1, "drift exits 1: {out}");
    assert!(out.contains("1 changed"), "{out}");

    // --update-snapshot keeps the front matter insta needs, and the text compares clean again.
    let (code, out, err) = sd2x_snapshot_run(&changed, &["--update-snapshot"]);
    assert_eq!(code, 0, "{out}{err}");
    let rewritten = std::fs::read_to_string(&changed).expect("rewritten");
    // (insta keeps no empty line at the end of the file; the writer ends its last block with one.)
    assert!(
        rewritten.trim_end() == text.trim_end(),
        "rewritten as committed, front matter included:\n{}",
        &rewritten[..rewritten.len().min(400)]
    );
}

#[test]
fn an_empty_selection_or_an_invalid_glob_exits_2_with_a_clear_message() {
    // What follows `run --target sim:sd2x`.
    let cases: &[(&[&str], &str)] = &[
        (
            &["--no-progress", "--cases", "nothing/*"],
            "no case selected: --cases `nothing/*` matches no case",
        ),
        (
            &["--list", "--cases", "nothing/*"],
            "no case selected: --cases `nothing/*` matches no case",
        ),
        (
            &[
                "--no-progress",
                "--cases",
                "golden/*",
                "--exclude",
                "golden",
            ],
            "--cases `golden/*` with --exclude `golden` leaves no case",
        ),
        (
            &["--cases", "spec/[x"],
            "--cases `spec/[x` is not a valid glob",
        ),
        (
            &["--exclude", "spec/[x"],
            "--exclude `spec/[x` is not a valid glob",
        ),
    ];
    for (rest, message) in cases {
        let args = [&["run", "--target", "sim:sd2x"], *rest].concat();
        let (code, out, err) = harness(&args);
        assert_eq!(code, 2, "{args:?}: {out}{err}");
        assert!(err.contains(message), "{args:?}: {err}");
    }
    // A selection that matches runs as before.
    let (code, out, err) = harness(&sim_run_args("sim:sd2x", &["--cases", "golden/*"]));
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("RESULT: PASS"), "{out}");
}

const EXPECT: &str = r#"
target = "sim:mdrive with the range-unchecked fault"

[[deviation]]
case = "profile/mdrive/write-out-of-range/*"
verdict = "NON-STRICT"
reason = "this firmware stores out-of-range values (known)"

[[deviation]]
case = "golden/mdrive/4.2.4/*"
verdict = "INFORMATIONAL"
reason = "read max velocity was wrong in an old firmware"

[[deviation]]
case = "no/such/case"
verdict = "INFORMATIONAL"
reason = "a typo"
"#;

#[test]
fn unmatched_and_stale_expectations_are_reported_and_strict_expect_fails_on_them() {
    let dir = TempDir::new("cli-edges-expect");
    let expect = dir.path().join("expect.toml");
    std::fs::write(&expect, EXPECT).expect("write");
    let used_only = dir.path().join("used.toml");
    std::fs::write(
        &used_only,
        EXPECT
            .split("\n[[deviation]]\ncase = \"golden")
            .next()
            .unwrap(),
    )
    .expect("write");
    let run = |file: &Path, strict: bool| {
        let mut args = sim_run_args(
            "sim:mdrive",
            &[
                "--fault",
                "range-unchecked",
                "--cases",
                "profile/mdrive/write-out-of-range/*",
                "--cases",
                "golden/mdrive/4.2.4/*",
                "--expect",
                file.to_str().unwrap(),
            ],
        );
        if strict {
            args.push("--strict-expect");
        }
        harness(&args)
    };
    let (code, out, err) = run(&expect, false);
    assert_eq!(code, 0, "excused deviations, no FAIL: {out}{err}");
    assert!(
        out.contains("expectations: 2 of 3 entries not used"),
        "{out}"
    );
    assert!(out.contains("UNMATCHED no/such/case"), "{out}");
    assert!(out.contains("STALE     golden/mdrive/4.2.4/*"), "{out}");
    assert!(
        !out.contains("profile/mdrive/write-out-of-range/* ("),
        "the used entry is not reported: {out}"
    );
    let (code, out, err) = run(&expect, true);
    assert_eq!(code, 1, "--strict-expect fails on them: {out}{err}");
    assert!(out.contains("--strict-expect: exit code 1"), "{out}");
    // Every entry used: --strict-expect passes.
    let (code, out, err) = run(&used_only, true);
    assert_eq!(code, 0, "{out}{err}");
    assert!(!out.contains("expectations:"), "{out}");
    // --strict-expect without --expect is a usage error.
    let (code, _, err) = harness(&["run", "--target", "sim:sd2x", "--strict-expect"]);
    assert_eq!(code, 2, "{err}");
}

#[test]
fn without_a_terminal_the_run_prints_plain_progress_lines_to_stderr() {
    let (code, out, err) = harness(&["run", "--target", "sim:sd2x", "--progress-every", "0"]);
    assert_eq!(code, 0, "{out}{err}");
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("progress: "))
        .collect();
    assert!(
        lines.len() > 10,
        "a line per case with --progress-every 0: {err}"
    );
    let first = lines[0];
    for part in ["1/", "cases (", "0 FAIL", "cases/s", "s elapsed", "ETA "] {
        assert!(first.contains(part), "{part} in {first}");
    }
    assert!(!out.contains("progress: "), "progress goes to stderr only");
    let (_, _, err) = harness(&[
        "run",
        "--target",
        "sim:sd2x",
        "--progress-every",
        "0",
        "--no-progress",
    ]);
    assert!(!err.contains("progress: "), "--no-progress: none: {err}");
    // The default interval (10 s) prints nothing in a run of well under a second.
    let (_, _, err) = harness(&["run", "--target", "sim:sd2x"]);
    assert!(!err.contains("progress: "), "{err}");
}

#[test]
fn fail_details_beyond_the_cap_are_counted_and_sent_to_the_report() {
    let range_unchecked = ["--fault", "range-unchecked"];
    let (_dir, report, (code, out, err)) =
        sim_run_reported("cli-edges-fails", "sim:mdrive", &range_unchecked);
    assert_eq!(code, 1, "{out}{err}");
    let fails: usize = out
        .lines()
        .find_map(|l| l.strip_prefix("RESULT: FAIL ("))
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("RESULT line with the FAIL count");
    assert!(fails > 20, "enough FAILs to reach the cap: {fails}");
    let detailed = out.lines().filter(|l| l.starts_with("FAIL ")).count();
    assert_eq!(detailed, 20, "{out}");
    assert!(
        out.contains(&format!(
            "{} more FAIL details in the report ({})",
            fails - 20,
            report.display()
        )),
        "{out}"
    );
    // Without --report the count says how to get them.
    let (_, out, _) = harness(&sim_run_args("sim:mdrive", &range_unchecked));
    assert!(
        out.contains(&format!(
            "{} more FAIL details: rerun with --report DIR",
            fails - 20
        )),
        "{out}"
    );
}

#[test]
fn run_list_into_a_pipe_closed_after_one_line_exits_quietly() {
    // Far more than a pipe buffer holds, so that the listing is still writing when the reader goes away.
    let mut child = Command::new(env!("CARGO_BIN_EXE_modbus-harness"))
        .args([
            "run",
            "--target",
            "sim:mdrive",
            "--list",
            "--generated",
            "3000",
            "--seed",
            "1",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let mut first = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut first)
        .expect("one line");
    // The reader (and the pipe) is dropped here, like `head -1` exiting.
    assert!(!first.trim().is_empty());
    let out = child.wait_with_output().expect("wait");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(out.status.code(), Some(0), "{err}");
}
