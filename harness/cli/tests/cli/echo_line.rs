//! A serial line that gives back what the harness sends: the local echo of a two-wire RS-485 adapter whose
//! receiver stays on while it transmits. `simulate --serial` serves one end of a socat pty pair (it ends
//! frames by the line's silence, as a drive on RS-485 does) and bench/echo-line.py relays the other end to a
//! pty of its own that echoes every byte the harness writes. With `echo=on` in the target URL each request's
//! echo is read back, checked and dropped, and the drive is judged as on the plain line (the harness on the
//! pair's other end directly); without it the pre-flight names the echo and nothing is sent after it; an echo
//! that differs (a collision) ends the run with an error, the drive put back. The drive also serves RTU over
//! TCP, where the test reads its parameters.

use std::path::Path;
use std::time::Duration;

use test_support::{PtyPair, TempDir, echo_line, harness_bounded, run_args, socat_or_skip};

use super::leave_as_found::{PresetDrive, journal_lines};

const RUN_LIMIT: Duration = Duration::from_secs(120);

/// The generic profile's drive (RTU among its transports; kept parameters a run writes), preset off its
/// factory values, on `pty.a` at 19200 8N1 and on RTU over TCP; `extra`: its faults.
fn drive_on(pty: &PtyPair, dir: &Path, extra: &[&str]) -> PresetDrive {
    let tty = pty.a.to_string_lossy().into_owned();
    let mut args = vec!["--serial", &tty, "--baud", "19200", "--parity", "none"];
    args.extend_from_slice(extra);
    PresetDrive::start_framed("generic", dir, &args, true)
}

fn url(tty: &Path, echo: bool) -> String {
    format!(
        "rtu://{}?baud=19200&parity=none{}",
        tty.display(),
        if echo { "&echo=on" } else { "" }
    )
}

/// The RESULT line of a run's output.
fn result_line(out: &str) -> String {
    out.lines()
        .find(|l| l.starts_with("RESULT:"))
        .unwrap_or_else(|| panic!("no RESULT line: {out}"))
        .to_string()
}

/// A RESULT line's counts, PASS and INFORMATIONAL together: a step sent in timed pieces is INFORMATIONAL
/// ("inconclusive: the machine is too busy for this step") where the harness itself was held up between the
/// pieces, which a loaded test machine does now and then, echo or not.
fn judged(result: &str) -> Vec<(String, u64)> {
    let inner = result
        .split_once('(')
        .and_then(|(_, r)| r.strip_suffix(')'))
        .unwrap_or("");
    let mut counts: std::collections::BTreeMap<String, u64> = Default::default();
    for part in inner.split(", ") {
        if let Some((n, v)) = part.split_once(' ') {
            let v = if v == "INFORMATIONAL" { "PASS" } else { v };
            *counts.entry(v.to_string()).or_default() += n.parse::<u64>().unwrap_or(0);
        }
    }
    let verdict = result.split_whitespace().nth(1).unwrap_or("").to_string();
    std::iter::once((verdict, 0)).chain(counts).collect()
}

/// The cases a run printed as FAILed (`FAIL case-id` lines), sorted.
fn failed_cases(out: &str) -> Vec<String> {
    let mut ids: Vec<String> = out
        .lines()
        .filter_map(|l| l.strip_prefix("FAIL "))
        .filter_map(|rest| rest.split_whitespace().next())
        .map(str::to_string)
        .collect();
    ids.sort();
    ids
}

/// Runs with each of `extras` through an echoing line with echo=on, then the same on the plain line (the
/// pair's other end, no relay): the two runs' (exit code, stdout, stderr) for each.
#[allow(clippy::type_complexity)]
fn echoing_then_plain(
    pty: &PtyPair,
    dir: &Path,
    extras: &[&[&str]],
) -> Vec<((i32, String, String), (i32, String, String))> {
    let link = dir.join("echoing");
    let line = echo_line(&pty.b, &link, &[]);
    let on_echo = url(&link, true);
    let echoed: Vec<_> = extras
        .iter()
        .map(|extra| harness_bounded(None, &run_args(&on_echo, "generic", extra), RUN_LIMIT))
        .collect();
    drop(line);
    let plain = url(&pty.b, false);
    echoed
        .into_iter()
        .zip(extras)
        .map(|(e, extra)| {
            (
                e,
                harness_bounded(None, &run_args(&plain, "generic", extra), RUN_LIMIT),
            )
        })
        .collect()
}

/// On a line that echoes: without echo=on the pre-flight says to add it and nothing else is sent; with it the
/// catalog and a generated run give the verdicts of the plain line, and the drive is left as found.
#[test]
fn a_drive_behind_a_line_that_echoes_passes_with_echo_on_and_is_left_as_found() {
    if !socat_or_skip("echo_line::a_drive_behind_a_line_that_echoes_passes_with_echo_on") {
        return;
    }
    let dir = TempDir::new("echo-line");
    let pty = PtyPair::start();
    let drive = drive_on(&pty, dir.path(), &[]);
    let before = drive.read();
    {
        let link = dir.path().join("unasked");
        let _line = echo_line(&pty.b, &link, &[]);
        let (code, out, err) = harness_bounded(
            None,
            &run_args(&url(&link, false), "generic", &[]),
            RUN_LIMIT,
        );
        assert_eq!(code, 2, "{out}\n{err}");
        assert!(
            err.contains("gave back a known-good read") && err.contains("Add echo=on"),
            "{err}"
        );
        assert!(
            journal_lines(&dir.path().join("sim.jsonl")).is_empty(),
            "a write went out after the pre-flight saw the echo"
        );
    }
    let extras: [&[&str]; 2] = [&[], &["--generated", "200", "--seed", "1"]];
    for ((echoed, plain), extra) in echoing_then_plain(&pty, dir.path(), &extras)
        .into_iter()
        .zip(extras)
    {
        let (code, out, err) = echoed;
        assert_eq!(code, 0, "{extra:?}: {out}\n{err}");
        assert!(out.contains("RESULT: PASS"), "{extra:?}: {out}");
        assert!(
            out.contains("every kept parameter reads as before"),
            "{extra:?}: {out}"
        );
        assert_eq!(plain.0, 0, "{extra:?}: {}\n{}", plain.1, plain.2);
        assert_eq!(
            judged(&result_line(&out)),
            judged(&result_line(&plain.1)),
            "{extra:?}: echoing line against plain line"
        );
    }
    let lines = journal_lines(&dir.path().join("sim.jsonl"));
    assert!(
        lines.iter().any(|j| j["old"] != j["new"]),
        "the runs changed nothing: as found proves nothing"
    );
    drive.assert_reads_as(&before, "generic behind an echoing line: not left as found");
}

/// A drive with faults behind the echoing line: the same cases FAIL as on the plain line (dropping the echo
/// hides nothing of the answer), and they are not none.
#[test]
fn a_fault_fails_the_same_cases_behind_a_line_that_echoes() {
    if !socat_or_skip("echo_line::a_fault_fails_the_same_cases_behind_a_line_that_echoes") {
        return;
    }
    let dir = TempDir::new("echo-line-fault");
    let pty = PtyPair::start();
    let _drive = drive_on(
        &pty,
        dir.path(),
        &["--fault", "range-unchecked", "--fault", "bit-padding-ones"],
    );
    let runs = echoing_then_plain(&pty, dir.path(), &[&[]]);
    let ((code, out, err), (pcode, pout, perr)) = &runs[0];
    assert_eq!(*code, 1, "{out}\n{err}");
    assert_eq!(*pcode, 1, "{pout}\n{perr}");
    let failed = failed_cases(out);
    assert!(!failed.is_empty(), "no FAIL listed: {out}");
    assert_eq!(
        failed,
        failed_cases(pout),
        "echoing line against plain line"
    );
    assert_eq!(result_line(out), result_line(pout));
}

/// A collision halfway through a run (bench/echo-line.py flips a bit of the 700th echo, after the first
/// writes): the run ends with the error naming it (exit 2), not with a verdict on the drive, and what the run
/// changed is put back and verified over the same line.
#[test]
fn a_collision_ends_the_run_with_an_error_and_the_drive_put_back() {
    if !socat_or_skip("echo_line::a_collision_ends_the_run_with_an_error_and_the_drive_put_back") {
        return;
    }
    let dir = TempDir::new("echo-line-collision");
    let pty = PtyPair::start();
    let drive = drive_on(&pty, dir.path(), &[]);
    let before = drive.read();
    let link = dir.path().join("echoing");
    let _line = echo_line(&pty.b, &link, &["--corrupt-at", "700"]);
    let (code, out, err) = harness_bounded(
        None,
        &run_args(&url(&link, true), "generic", &[]),
        RUN_LIMIT,
    );
    let all = format!("{out}\n{err}");
    assert_eq!(code, 2, "{all}");
    assert!(
        err.contains("echo of the request differs from what was sent") && err.contains("collision"),
        "{all}"
    );
    assert!(
        !all.contains("RESULT:"),
        "a verdict after a collision: {all}"
    );
    assert!(
        all.contains("every kept parameter reads as before"),
        "not put back and verified: {all}"
    );
    let lines = journal_lines(&dir.path().join("sim.jsonl"));
    assert!(
        lines.iter().any(|j| j["old"] != j["new"]),
        "nothing was changed before the collision: the test proves nothing"
    );
    drive.assert_reads_as(&before, "not left as found after a collision");
}
