//! Pipelined live campaigns (issue 17, item 2): over Modbus/TCP, `fuzz` puts several generated reads in
//! flight where the target answered a burst of known-good reads sent in one write, and takes each answer by
//! transaction id. Shown here against `simulate` processes over loopback: the same cases go out in the same
//! order as one at a time (the same requests, plus the burst), healthy drives give no finding, answers out
//! of request order are attributed by transaction id, a server with one transaction (Server Busy) is not
//! pipelined and gives no finding, one that drops pipelined requests is a finding and is not pipelined,
//! and faults in the answers to reads are found on the same case as one request at a time.

use test_support::{SimProcess, TempDir, harness, skip_unless};

/// What a campaign's summary line says: (cases, pipelined, probes, requests).
fn summary(out: &str) -> (u64, u64, u64, u64) {
    let line = out
        .lines()
        .find(|l| l.starts_with("fuzz: "))
        .unwrap_or_else(|| panic!("no summary in {out}"));
    let number_before = |word: &str| -> u64 {
        let at = line
            .find(word)
            .unwrap_or_else(|| panic!("no {word} in {line}"));
        line[..at]
            .split(|c: char| !c.is_ascii_digit())
            .rfind(|w| !w.is_empty())
            .and_then(|w| w.parse().ok())
            .unwrap_or_else(|| panic!("no number before {word} in {line}"))
    };
    let pipelined = if line.contains(" pipelined") {
        number_before(" pipelined")
    } else {
        0
    };
    (
        number_before(" cases"),
        pipelined,
        number_before(" probes"),
        number_before(" requests"),
    )
}

/// `fuzz` against `url` with profile `profile`, seed 3, up to `cases` cases, reproducers into `dir`, and
/// `extra`; returns (exit code, stdout, stderr).
fn fuzz(
    url: &str,
    profile: &str,
    cases: &str,
    dir: &TempDir,
    extra: &[&str],
) -> (i32, String, String) {
    let regressions = dir.path().join("regressions");
    let mut args = vec![
        "fuzz",
        "--target",
        url,
        "--profile",
        profile,
        "--seed",
        "3",
        "--max-cases",
        cases,
        "--duration",
        "120s",
        "--regressions",
        regressions.to_str().expect("path"),
    ];
    args.extend_from_slice(extra);
    harness(&args)
}

/// `fuzz` with up to `cases` cases against `simulate --profile generic` on loopback taking `choice`
/// (`FREEDOM=VALUE`, an answer the spec allows): it must find nothing (exit 0). Returns (stdout, stderr).
fn fuzz_generic_choosing(choice: &str, cases: &str) -> (String, String) {
    let sim = SimProcess::start(&[
        "--profile",
        "generic",
        "--listen",
        "127.0.0.1:0",
        "--choose",
        choice,
    ]);
    let dir = TempDir::new("pipeline-choice");
    let (code, out, err) = fuzz(&sim.tcp_url(), "generic", cases, &dir, &[]);
    assert_eq!(code, 0, "{choice}: {out}\n{err}");
    (out, err)
}

/// The case of the first finding (`FAIL after CASE: ...`).
fn first_fail(out: &str) -> Option<String> {
    out.lines()
        .find_map(|l| l.strip_prefix("FAIL after "))
        .and_then(|l| l.split(':').next())
        .map(str::to_string)
}

#[test]
fn pipelined_campaigns_send_the_same_cases_and_find_nothing_on_healthy_drives() {
    for name in ["generic", "mdrive", "lmd"] {
        let sim = SimProcess::on_loopback(name, "--listen", None);
        let url = sim.tcp_url();
        let dir = TempDir::new(&format!("pipeline-{name}"));
        let (code, out, err) = fuzz(&url, name, "3000", &dir, &[]);
        assert_eq!(code, 0, "{name} pipelined: {out}\n{err}");
        assert!(
            err.contains("fuzz: up to 8 requests in flight"),
            "{name}: {err}"
        );
        let (cases, pipelined, probes, requests) = summary(&out);
        assert_eq!(cases, 3000, "{name}: {out}");
        assert!(
            pipelined > 500,
            "{name}: only {pipelined} of {cases} cases pipelined: {out}"
        );
        let (code, out1, err1) = fuzz(&url, name, "3000", &dir, &["--pipeline", "1"]);
        assert_eq!(code, 0, "{name} one at a time: {out1}\n{err1}");
        let (cases1, pipelined1, probes1, requests1) = summary(&out1);
        assert_eq!(pipelined1, 0, "{name}: {out1}");
        // The same cases in the same order: the same probes and the same requests, and the burst's 8.
        assert_eq!(
            (cases1, probes1, requests1 + 8),
            (cases, probes, requests),
            "{name}: pipelined {out} one at a time {out1}"
        );
    }
}

/// A drive that closes the connection on a PDU too short for its function, or ignores it, as the freedom
/// `truncated-pdu` allows: no finding pipelined either, and pipelining goes on (such requests go one at a
/// time: a server cutting requests by the function's length rules would read the next request's bytes
/// as the rest of a short one).
#[test]
fn a_drive_that_closes_or_ignores_a_truncated_pdu_is_not_blamed_pipelined() {
    for choice in ["truncated-pdu=close", "truncated-pdu=silence"] {
        let (out, err) = fuzz_generic_choosing(choice, "3000");
        let (_, pipelined, _, _) = summary(&out);
        assert!(pipelined > 500, "{choice}: {out}\n{err}");
        assert!(
            !err.contains("one request at a time from here"),
            "{choice}: {err}"
        );
    }
}

#[test]
fn answers_out_of_request_order_are_taken_by_transaction_id() {
    let (out, err) = fuzz_generic_choosing("pipelined-response-order=transaction-id", "3000");
    let (_, pipelined, _, _) = summary(&out);
    assert!(pipelined > 500, "{out}\n{err}");
}

#[test]
fn a_server_with_one_transaction_is_not_pipelined_and_not_blamed() {
    let (out, err) = fuzz_generic_choosing("pipelined-server-busy=exception-06", "1000");
    assert!(
        err.contains("one request at a time (of 8 known-good reads sent in one write, the target answered 1 normally and 7 with Server Busy"),
        "{err}"
    );
    assert_eq!(summary(&out).1, 0, "{out}");
}

#[test]
fn a_server_that_drops_pipelined_requests_is_a_finding_and_is_not_pipelined() {
    let sim = SimProcess::on_loopback("generic", "--listen", Some("pipeline-drop"));
    let dir = TempDir::new("pipeline-drop");
    let (code, out, err) = fuzz(&sim.tcp_url(), "generic", "1000", &dir, &["--keep-going"]);
    assert_eq!(code, 1, "{out}\n{err}");
    assert_eq!(
        first_fail(&out).as_deref(),
        Some("fuzz/pipeline/8-requests-one-segment"),
        "{out}"
    );
    assert!(
        err.contains("fuzz: one request at a time (the target's answers to 8 known-good reads sent in one write FAIL"),
        "{err}"
    );
    assert_eq!(summary(&out).1, 0, "{out}");
    let reproducer = dir
        .path()
        .join("regressions/generic/fuzz-3-fuzz-pipeline-8-requests-one-segment.toml");
    assert!(
        reproducer.is_file(),
        "no reproducer at {}: {out}\n{err}",
        reproducer.display()
    );
}

/// Faults in what a drive answers to reads: the pipelined campaign finds each on the case the campaign
/// one request at a time finds it on, from an answer to a request sent with others in flight.
#[test]
fn faults_in_answers_to_reads_are_found_on_the_same_case_pipelined() {
    let mut found_in_flight = 0;
    for fault in [
        "wrong-exception-code",
        "reserved-readable",
        "quantity-unchecked",
        "bit-padding-ones",
        "quantity-low-byte",
    ] {
        let sim = SimProcess::on_loopback("generic", "--listen", Some(fault));
        let url = sim.tcp_url();
        let dir = TempDir::new(&format!("pipeline-{fault}"));
        let (code, out, err) = fuzz(&url, "generic", "3000", &dir, &[]);
        assert_eq!(code, 1, "{fault} pipelined: {out}\n{err}");
        let (code1, out1, err1) = fuzz(&url, "generic", "3000", &dir, &["--pipeline", "1"]);
        assert_eq!(code1, 1, "{fault} one at a time: {out1}\n{err1}");
        assert!(first_fail(&out).is_some(), "{fault}: {out}");
        assert_eq!(
            first_fail(&out),
            first_fail(&out1),
            "{fault}: pipelined {out}\n{err}\none at a time {out1}\n{err1}"
        );
        if err.contains("(its request was sent with others in flight)") {
            found_in_flight += 1;
            // The campaign sends one request at a time after it.
            assert!(
                err.contains("fuzz: one request at a time from here: ")
                    && err.contains("was sent with other requests in flight and FAILs"),
                "{fault}: {err}"
            );
        }
    }
    assert!(
        found_in_flight >= 2,
        "only {found_in_flight} of the faults were found on a pipelined request"
    );
}

/// The finding ids of a campaign's summary (`FAIL after ID: ...` and the other kinds), in order.
fn finding_ids(out: &str) -> Vec<String> {
    out.lines()
        .filter_map(|l| {
            [
                "FAIL after ",
                "STOPPED ANSWERING after ",
                "PROBE ANSWERED WRONGLY OR LATE after ",
            ]
            .iter()
            .find_map(|k| l.strip_prefix(k))
        })
        .filter_map(|l| l.split(':').next())
        .map(str::to_string)
        .collect()
}

/// A server of independent authorship that drops what arrives behind a request it refuses: libmodbus
/// answers most exceptions after sleeping its response timeout and then flushes its input, so the requests
/// in flight behind it are never read. The pipelined campaign asks the first of them that went unanswered
/// again alone, judges it so, and pipelines no more: its findings are those of one request at a time.
#[test]
fn a_server_that_flushes_behind_a_refused_request_is_not_blamed() {
    skip_unless!(test_support::libmodbus_or_skip);
    let run = |depth: &str| {
        let server = test_support::peer_servers::PeerServer::libmodbus();
        let dir = TempDir::new(&format!("pipeline-libmodbus-{depth}"));
        let url = format!("tcp://{}", server.addr);
        let extra = ["--pipeline", depth, "--keep-going", "--max-findings", "3"];
        let (code, out, err) = fuzz(&url, "generic", "60", &dir, &extra);
        assert_eq!(code, 1, "--pipeline {depth}: {out}\n{err}");
        (finding_ids(&out), err)
    };
    let (piped, err) = run("8");
    let (alone, _) = run("1");
    assert!(
        err.contains("went unanswered with other requests in flight, and was asked again alone"),
        "{err}"
    );
    assert_eq!(piped, alone, "{err}");
}

/// A server holds "a value from 1 to 16" transactions at once (TCP guide 4.4.2.1) and answers a request
/// beyond them Server Busy (4.4.2.2). The reference has one. bench/transactions-proxy.py in front of
/// `simulate` gives a server with 1, 2 or 3: each keeps to its number, and the catalog and 1,000 generated
/// cases (their batches of 2 to 4 requests) PASS, the refusals shown per place in the batch ("request 3 of
/// those sent together" for a server with two). Before, a server with two showed `exception-06` at the third
/// request of a batch, the reference took that for one transaction and refused the second request of every
/// batch after it: 1 FAIL and 3 NON-STRICT in this generated run.
#[test]
fn a_server_with_two_or_three_transactions_passes() {
    use test_support::peer_servers::PeerServer;
    let sim = SimProcess::start(&["--profile", "mdrive", "--listen", "127.0.0.1:0"]);
    let upstream = sim.tcp.expect("tcp");
    let shown = |out: &str, place: usize| {
        out.contains(&format!(
            "pipelined-server-busy [request {place} of those sent together] = exception-06"
        ))
    };
    for n in [1, 2, 3] {
        let server = PeerServer::transactions(upstream, n);
        let url = format!("tcp://{}", server.addr);
        for extra in [&[][..], &["--generated", "1000", "--seed", "3"][..]] {
            let mut args = vec![
                "run",
                "--target",
                &url,
                "--profile",
                "mdrive",
                "--no-progress",
            ];
            args.extend_from_slice(extra);
            let (code, out, err) = harness(&args);
            let row = format!("{n} transaction(s), {extra:?}");
            assert_eq!(code, 0, "{row}\n{out}\n{err}");
            let result = out
                .lines()
                .find(|l| l.starts_with("RESULT: "))
                .unwrap_or_default();
            assert!(
                result.starts_with("RESULT: PASS") && !result.contains("NON-STRICT"),
                "{row}\n{out}"
            );
            // Refused from the place after its last transaction on, never before it.
            for place in 2..=n {
                assert!(!shown(&out, place), "{row}: refused at {place}\n{out}");
            }
            // The catalog's burst of four shows the refusal right after the last transaction.
            if extra.is_empty() {
                assert!(shown(&out, n + 1), "{row}\n{out}");
            }
        }
    }
    drop(sim);
}
