//! The `decode` and `golden` commands, run as a user runs them: exit codes and what the output names.

use std::process::{Command, Output};

fn run(args: &[&str]) -> (i32, String, String) {
    let Output {
        status,
        stdout,
        stderr,
    } = Command::new(env!("CARGO_BIN_EXE_modbus-harness"))
        .args(args)
        .output()
        .expect("the binary runs");
    (
        status.code().expect("exited, not killed"),
        String::from_utf8(stdout).expect("UTF-8 stdout"),
        String::from_utf8(stderr).expect("UTF-8 stderr"),
    )
}

/// The first output line that starts with `error:` (empty when there is none).
fn error_line(out: &str) -> &str {
    out.lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_default()
}

/// The value column of the first output row named `name`.
fn row<'a>(out: &'a str, name: &str) -> Option<&'a str> {
    out.lines().find_map(|l| {
        let l = l.trim_start();
        l.strip_prefix(name)
            .filter(|rest| rest.starts_with(' '))
            .map(str::trim)
    })
}

#[test]
fn decode_rtu_status_read() {
    let (code, out, err) = run(&["decode", "--rtu", "010307D000018487"]);
    assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
    assert_eq!(row(&out, "slave address"), Some("1 (0x01)"), "{out}");
    let function = row(&out, "function").unwrap_or_default();
    assert!(function.contains("0x03"), "{out}");
    assert_eq!(row(&out, "address"), Some("2000 (0x7D0)"), "{out}");
    assert_eq!(row(&out, "quantity"), Some("1 (0x1)"), "{out}");
    let crc = row(&out, "CRC").unwrap_or_default();
    assert!(crc.contains("0x8784") && crc.ends_with("OK"), "{out}");
    assert!(out.contains("OK: decodes strictly"), "{out}");
    assert!(!out.contains("error"), "{out}");
}

/// `decode ARGS` of a frame that breaks a rule: exit code 1, the row `field` shows each of `row_shows`, and
/// the `error:` line gives the offset (`at byte AT_BYTE`) and each of `error_names`. Returns stdout.
fn rejected(
    args: &[&str],
    field: &str,
    row_shows: &[&str],
    at_byte: usize,
    error_names: &[&str],
) -> String {
    let (code, out, err) = run(args);
    assert_eq!(code, 1, "stdout:\n{out}\nstderr:\n{err}");
    let shown = row(&out, field).unwrap_or_default();
    for want in row_shows {
        assert!(shown.contains(want), "row {field} lacks {want}:\n{out}");
    }
    let error = error_line(&out);
    let at = format!("at byte {at_byte}");
    for want in std::iter::once(at.as_str()).chain(error_names.iter().copied()) {
        assert!(error.contains(want), "error line lacks {want}:\n{out}");
    }
    out
}

#[test]
fn decode_rtu_bad_crc() {
    let out = rejected(
        &["decode", "--rtu", "010307D000018488"],
        "CRC",
        &["0x8884", "0x8784", "MISMATCH"],
        6,
        &["0x8784", "0x8884"],
    );
    // what the frame meant is still shown
    assert_eq!(row(&out, "address"), Some("2000 (0x7D0)"), "{out}");
}

#[test]
fn decode_tcp_with_protocol_id_1() {
    rejected(
        &["decode", "--tcp", "00 01 00 01 00 06 01 03 07 D0 00 01"],
        "protocol id",
        &["0x0001", "must be 0"],
        2,
        &["protocol id is 0x0001"],
    );
}

#[test]
fn decode_pdu_extended_exception() {
    let (code, out, err) = run(&[
        "decode",
        "--pdu",
        "--response",
        "AB FF 00 06 0D CE 0B 00 FF FF",
    ]);
    assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
    assert_eq!(
        row(&out, "sdo_error"),
        Some("4294901771 (0xFFFF000B)"),
        "{out}"
    );
}

#[test]
fn decode_bad_hex_is_a_usage_error() {
    let (code, out, err) = run(&["decode", "--rtu", "01 0G"]);
    assert_eq!(code, 2, "stdout:\n{out}\nstderr:\n{err}");
    assert!(err.contains("not hex"), "{err}");
    assert!(err.contains("0G"), "the input is echoed: {err}");
    assert!(out.is_empty(), "nothing decoded on bad input: {out}");

    let (code, _, err) = run(&["decode", "--rtu", ""]);
    assert_eq!(code, 2);
    assert!(err.contains("no bytes"), "{err}");
}

#[test]
fn decode_needs_a_framing() {
    let (code, _, err) = run(&["decode", "010307D000018487"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--rtu") || err.contains("--tcp"), "{err}");
}

#[test]
fn golden_corpus_is_consistent() {
    let (code, out, err) = run(&["golden"]);
    // On failure show the failing entries and the summary, not the whole errata listing.
    let failing: Vec<&str> = out
        .lines()
        .filter(|l| l.starts_with("  FAIL") || l.contains("inconsistent"))
        .collect();
    assert_eq!(code, 0, "{}\nstderr:\n{err}", failing.join("\n"));
    assert!(out.contains(" 0 inconsistent"), "{out}");
}
