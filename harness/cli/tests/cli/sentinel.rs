//! Silence proven, not waited for (issue 17, item 1): on Modbus/TCP a request that must go unanswered is
//! followed by a known-good read on the same connection, whose answer with nothing before it proves the
//! silence; one that no sentinel can follow (its MBAP length is not its size), when the case reconnects
//! next, by half-closing the connection: the drive's close with nothing before it proves it. Shown here against `simulate` processes over loopback: the verdicts are the ones of listening out
//! the window (`--no-sentinel`), compared through snapshots; sentinels were used; and a drive that answers
//! what it must ignore still FAILs with sentinels on.

use test_support::{SimProcess, TempDir, harness, run_args};

/// The `silences:` line of a run's log: (proven by a sentinel, proven by the target's close after a
/// half-close, listened out).
fn silences(err: &str) -> (u64, u64, u64) {
    let line = err
        .lines()
        .find(|l| l.starts_with("silences: "))
        .unwrap_or_else(|| panic!("no silences line in {err}"));
    let n: Vec<u64> = line
        .split_whitespace()
        .filter_map(|w| w.parse().ok())
        .collect();
    (n[0], n[1], n[2])
}

/// The case lines of a snapshot file (`== ID  VERDICT`), in order.
fn verdicts(snap: &std::path::Path) -> Vec<String> {
    std::fs::read_to_string(snap)
        .expect("snapshot")
        .lines()
        .filter(|l| l.starts_with("== ") && !l.starts_with("== choice/"))
        .map(str::to_string)
        .collect()
}

/// The same cases over the same loopback with and without sentinels: the same case ids and verdicts. (Not
/// the same observations everywhere: a sentinel is one more request, and the FC 08 and FC 0B/0C counters of
/// target and reference both count it, so the values they read differ from a run without.)
#[test]
fn sentinels_give_the_verdicts_of_the_window() {
    for name in ["generic", "mdrive", "lmd"] {
        let sim = SimProcess::start(&["--profile", name, "--listen", "127.0.0.1:0"]);
        let url = sim.tcp_url();
        let dir = TempDir::new(&format!("sentinel-{name}"));
        let run = |snap: &std::path::Path, sentinel: bool| {
            let mut args = run_args(
                &url,
                name,
                &[
                    "--generated",
                    "300",
                    "--seed",
                    "5",
                    "--with-catalog",
                    "--no-shrink",
                    "--snapshot",
                    snap.to_str().expect("path"),
                    "--update-snapshot",
                ],
            );
            if !sentinel {
                args.push("--no-sentinel");
            }
            let (code, out, err) = harness(&args);
            assert_eq!(code, 0, "{name} (sentinel {sentinel}): {out}\n{err}");
            silences(&err)
        };
        let (window, with) = (
            dir.path().join("window.snap"),
            dir.path().join("sentinel.snap"),
        );
        let (proven, closed, listened) = run(&window, false);
        assert_eq!(
            (proven, closed),
            (0, 0),
            "{name}: silences proven with --no-sentinel"
        );
        assert!(listened > 0, "{name}: no silence was due");
        let (proven, closed, _) = run(&with, true);
        assert!(proven > 0, "{name}: no silence proven by a sentinel");
        assert!(closed > 0, "{name}: no silence proven by a close");
        let (a, b) = (verdicts(&window), verdicts(&with));
        assert!(a.len() > 300, "{name}: {} cases", a.len());
        let differ: Vec<_> = a.iter().zip(&b).filter(|(x, y)| x != y).collect();
        assert!(
            a.len() == b.len() && differ.is_empty(),
            "{name}: {differ:#?}"
        );
    }
}

/// A request no sentinel can follow (MBAP length one more than its bytes: the drive may be waiting for the
/// byte) has its silence proven by the drive's close after a half-close; the other by a sentinel. A drive
/// that answers what it must ignore FAILs either way; a healthy one PASSes without listening out a window.
#[test]
fn a_drive_that_answers_what_it_must_ignore_fails_with_sentinels_on() {
    for (case, bad, proofs) in [
        (
            "tcp/mbap/request-protocol-id-nonzero",
            "protocol-id-ignored",
            (1, 0, 0),
        ),
        (
            "tcp/mbap/request-length-plus-1",
            "mbap-length-ignored",
            (0, 1, 0),
        ),
    ] {
        for (fault, code_wanted) in [(None, 0), (Some(bad), 1)] {
            let sim = SimProcess::on_loopback("mdrive", "--listen", fault);
            let url = sim.tcp_url();
            let (code, out, err) = harness(&run_args(&url, "mdrive", &["--cases", case]));
            assert_eq!(code, code_wanted, "{case} {fault:?}: {out}\n{err}");
            match fault {
                // The healthy drive ignores the frame: the sentinel or the close proves it.
                None => assert_eq!(silences(&err), proofs, "{case}: {err}"),
                // The faulted drive answers it before the proof: FAIL.
                Some(_) => assert!(out.contains("FAIL"), "{out}"),
            }
        }
    }
}
