//! A dead, foreign or dying target (issue 14): a port that accepts and never answers, or answers in another
//! protocol, is recognised by the pre-flight read within seconds (exit 2, saying what was tried and what
//! answered); a drive that stops answering mid-run FAILs the request that preceded the silence and the rest
//! is SKIPPED, with complete reports; a drive that is silent for a while and comes back is waited for, and
//! the report says it recovered.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use test_support::{SimProcess, TempDir, harness_bounded, read_json, run_args};

/// How long any peer thread of these tests lives at most.
const PEER_LIFETIME: Duration = Duration::from_secs(60);

/// Run the binary with `args`, at most `limit`: (exit code, stdout, stderr, wall time).
fn harness_timed(args: &[&str], limit: Duration) -> (i32, String, String, Duration) {
    let started = Instant::now();
    let (code, out, err) = harness_bounded(None, args, limit);
    (code, out, err, started.elapsed())
}

/// A loopback listener (port 0) whose connections are handled by `serve` on a thread each; the accept loop
/// ends when the returned flag is set or after [`PEER_LIFETIME`].
fn peer(serve: fn(TcpStream)) -> (SocketAddr, Arc<AtomicBool>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("addr");
    listener.set_nonblocking(true).expect("nonblocking");
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    thread::spawn(move || {
        let until = Instant::now() + PEER_LIFETIME;
        while !flag.load(Ordering::SeqCst) && Instant::now() < until {
            match listener.accept() {
                Ok((c, _)) => {
                    let _ = c.set_nonblocking(false);
                    let _ = c.set_read_timeout(Some(PEER_LIFETIME));
                    thread::spawn(move || serve(c));
                }
                Err(_) => thread::sleep(Duration::from_millis(10)),
            }
        }
    });
    (addr, stop)
}

/// Accepts, reads what comes, never answers (until the client goes or the read times out).
fn silent(mut c: TcpStream) {
    let mut buf = [0u8; 512];
    while matches!(c.read(&mut buf), Ok(n) if n > 0) {}
}

/// Answers whatever comes with an HTTP 400 and closes, as a web server does to bytes that are not HTTP.
fn http(mut c: TcpStream) {
    let mut buf = [0u8; 512];
    let _ = c.read(&mut buf);
    let _ = c.write_all(
        b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/html\r\nContent-Length: 11\r\nConnection: close\r\n\r\nBad Request",
    );
    let _ = c.shutdown(Shutdown::Both);
}

#[test]
fn a_silent_port_exits_2_within_seconds_for_run_probe_and_fuzz() {
    let (addr, stop) = peer(silent);
    let target = format!("tcp://{addr}");
    for args in [
        vec!["run", "--target", &target, "--profile", "generic"],
        vec!["probe", "--target", &target],
        vec![
            "fuzz",
            "--target",
            &target,
            "--profile",
            "generic",
            "--duration",
            "20s",
        ],
    ] {
        let (code, _, err, took) = harness_timed(&args, Duration::from_secs(60));
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(
            took < Duration::from_secs(10),
            "{args:?} took {took:?} to give up on a silent port"
        );
        for said in [
            "does not answer",
            "known-good read",
            "unit id",
            "port",
            "rtu+tcp://",
        ] {
            assert!(err.contains(said), "{args:?}: no `{said}` in {err}");
        }
    }
    stop.store(true, Ordering::SeqCst);
}

/// Every request PDU [`silent_recording`] peers received, in order.
static HEARD: Mutex<Vec<Vec<u8>>> = Mutex::new(Vec::new());

/// As [`silent`], recording each request's PDU (MBAP frames cut by their length field) in [`HEARD`].
fn silent_recording(mut c: TcpStream) {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 512];
    while let Ok(n @ 1..) = c.read(&mut chunk) {
        buf.extend_from_slice(&chunk[..n]);
        while buf.len() >= 7 {
            let len = 6 + usize::from(u16::from_be_bytes([buf[4], buf[5]]));
            if buf.len() < len {
                break;
            }
            let frame: Vec<u8> = buf.drain(..len).collect();
            HEARD
                .lock()
                .expect("heard")
                .push(frame.get(7..).unwrap_or(&[]).to_vec());
        }
    }
}

/// The pre-flight comes before the runner's own reads (the word order, the forms it learns from the drive by
/// reading): a target that does not answer gets the pre-flight's known-good read (and the same read at unit
/// ids 255 and 0) and nothing else. Before, the learning reads went first and each waited its timeout: 11.3 s
/// to the LMD's error instead of 4.3 s (BENCHMARKS.md, "A serial line that echoes"); on a line that echoes
/// they read echoes.
#[test]
fn nothing_but_the_preflight_read_goes_to_a_target_that_does_not_answer() {
    let (addr, stop) = peer(silent_recording);
    let target = format!("tcp://{addr}");
    for profile in ["lmd", "mdrive", "generic"] {
        HEARD.lock().expect("heard").clear();
        let (code, _, err) = harness_bounded(
            None,
            &run_args(&target, profile, &[]),
            Duration::from_secs(60),
        );
        assert_eq!(code, 2, "{profile}: {err}");
        assert!(err.contains("does not answer"), "{profile}: {err}");
        let heard = HEARD.lock().expect("heard").clone();
        let first = heard
            .first()
            .unwrap_or_else(|| panic!("{profile}: nothing sent"));
        assert!(
            heard.iter().all(|pdu| pdu == first),
            "{profile}: more than the pre-flight read went out: {heard:02X?}"
        );
    }
    stop.store(true, Ordering::SeqCst);
}

/// A Modbus/TCP server that answers only unit id 255 (and 0), as the TCP implementation guide recommends for a
/// device that is not a gateway (drives written independently from the MDrive and LMD manuals do so): a run
/// without `--unit` gets no answer at the profile's unit 1 and runs at 255, saying so; a run told `--unit 1`
/// exits 2, and the error says which unit id answers the same read.
#[test]
fn a_server_of_another_unit_id_is_run_at_the_one_that_answers_unless_told_otherwise() {
    let sim = SimProcess::start(&[
        "--profile",
        "generic",
        "--listen",
        "127.0.0.1:0",
        "--unit",
        "255",
        "--choose",
        "tcp-unit-ids=silence",
    ]);
    let target = sim.tcp_url();
    let (code, _, err, took) = harness_timed(
        &[
            "run",
            "--target",
            &target,
            "--profile",
            "generic",
            "--unit",
            "1",
        ],
        Duration::from_secs(60),
    );
    assert_eq!(code, 2, "{err}");
    assert!(took < Duration::from_secs(10), "took {took:?}");
    assert!(
        err.contains("unit 255 is answered") && err.contains("--unit 255"),
        "{err}"
    );
    // Without it, the run goes ahead at 255.
    let (code, out, err, _) = harness_timed(
        &[
            "run",
            "--target",
            &target,
            "--profile",
            "generic",
            "--read-only",
            "--no-progress",
        ],
        Duration::from_secs(120),
    );
    assert!(code == 0 || code == 1, "{out}{err}");
    assert!(out.contains("RESULT: PASS"), "{out}{err}");
    assert!(
        err.contains(
            "unit id: 1 (the profile's) gets no answer, unit 255 does: the run uses unit 255"
        ),
        "{err}"
    );
    assert!(err.contains("(unit 255)"), "{err}");
}

#[test]
fn an_http_server_is_named_not_modbus() {
    let (addr, stop) = peer(http);
    for target in [format!("tcp://{addr}"), format!("rtu+tcp://{addr}")] {
        for args in [
            vec!["run", "--target", &target, "--profile", "generic"],
            vec!["probe", "--target", &target],
        ] {
            let (code, _, err, took) = harness_timed(&args, Duration::from_secs(60));
            assert_eq!(code, 2, "{args:?}: {err}");
            assert!(took < Duration::from_secs(10), "{args:?} took {took:?}");
            assert!(
                err.contains("is not a Modbus server") && err.contains("looks like HTTP"),
                "{args:?}: {err}"
            );
        }
    }
    stop.store(true, Ordering::SeqCst);
}

/// Every case's record in a report directory (the lines of `cases.jsonl`), as text; each line must parse,
/// the last one too.
fn case_records(dir: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(dir.join("cases.jsonl")).expect("cases.jsonl");
    assert!(
        text.ends_with('\n'),
        "cases.jsonl: the last line is cut short"
    );
    text.lines()
        .inspect(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .unwrap_or_else(|e| panic!("cases.jsonl: {e}: {l}"));
        })
        .map(str::to_string)
        .collect()
}

/// No `.partial` file is left anywhere in the report directory: every report was completed.
fn assert_complete(dir: &Path) {
    for f in test_support::reports::REPORT_FILES {
        assert!(dir.join(f).is_file(), "{f} missing in {}", dir.display());
    }
    let partial: Vec<_> = walk(dir)
        .into_iter()
        .filter(|p| p.to_string_lossy().ends_with(".partial"))
        .collect();
    assert!(partial.is_empty(), "left unfinished: {partial:?}");
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

fn index(dir: &Path) -> serde_json::Value {
    read_json(&dir.join("index.json"))
}

/// `run --target TARGET --profile generic --read-only --no-progress EXTRA... --report DIR/report`, at most
/// 90 s: the report directory, and (exit code, stdout, stderr, wall time).
fn read_only_generic_run(
    target: &str,
    dir: &TempDir,
    extra: &[&str],
) -> (PathBuf, (i32, String, String, Duration)) {
    let report = dir.path().join("report");
    let report_s = report.to_string_lossy().into_owned();
    let mut args = run_args(target, "generic", &["--read-only"]);
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--report", &report_s]);
    let ran = harness_timed(&args, Duration::from_secs(90));
    (report, ran)
}

#[test]
fn a_drive_that_dies_is_one_fail_then_skipped_with_complete_reports() {
    // The simulator stops answering for good at its first malformed frame.
    let sim = SimProcess::start(&[
        "--profile",
        "generic",
        "--listen",
        "127.0.0.1:0",
        "--fault",
        "stop-after-malformed",
    ]);
    let dir = TempDir::new("dead-target");
    let (report, (code, out, err, took)) =
        read_only_generic_run(&sim.tcp_url(), &dir, &["--recovery-wait", "3"]);
    assert_eq!(code, 1, "one FAIL: exit 1\n{out}\n{err}");
    assert!(took < Duration::from_secs(30), "took {took:?}");
    assert!(
        out.contains("the run ended early: the target stopped answering after"),
        "{out}"
    );
    assert_complete(&report);
    let summary = &index(&report)["summary"];
    assert_eq!(summary["counts"]["FAIL"], 1, "{summary}");
    assert!(
        summary["counts"]["PASS"].as_u64().unwrap_or(0) > 0,
        "{summary}"
    );
    assert!(
        summary["counts"]["SKIPPED"].as_u64().unwrap_or(0) > 100,
        "the rest is SKIPPED: {summary}"
    );
    let failing = summary["failing"][0].as_str().expect("one failing case");
    let ended = summary["ended"].as_str().expect("why the run ended");
    assert!(
        ended.contains(&format!("stopped answering after {failing}")),
        "{ended}"
    );
    // The failing case carries the finding with the request's bytes.
    let cases = case_records(&report);
    // A line for every case, SKIPPED ones included, as in the index.
    assert_eq!(
        Some(cases.len()),
        index(&report)["cases"].as_array().map(Vec::len)
    );
    let fail = cases
        .iter()
        .find(|c| c.contains("the target stopped answering after this request: "))
        .expect("a case with the finding");
    assert!(fail.contains(failing), "{fail}");
    // The cases after it are SKIPPED, saying why.
    assert!(
        cases
            .iter()
            .any(|c| c.contains("not run: the target stopped answering after")),
        "no SKIPPED case names the dead target"
    );
    let junit = std::fs::read_to_string(report.join("junit.xml")).expect("junit");
    assert!(
        junit.contains("name=\"ended\"") && junit.contains("stopped answering"),
        "junit: no reason"
    );
    let html = std::fs::read_to_string(report.join("report.html")).expect("html");
    assert!(html.contains("stopped answering after"), "html: no reason");
}

/// What a [`Proxy`] does to the traffic.
#[derive(Clone, Copy)]
enum Mode {
    /// From the `at`-th chunk the clients send (counted over all connections), everything both ways is
    /// dropped for the duration: a drive that goes silent for a while and comes back.
    Pause(usize, Duration),
    /// The `at`-th chunk the server sends is held back for the duration, the others pass: one late answer.
    Delay(usize, Duration),
    /// The answer to the first request chunk containing these bytes is held back for the first duration
    /// (once), every other answer for the second: one late answer to a chosen request, from a drive that
    /// takes its time with every answer.
    DelayAnswerTo(&'static [u8], Duration, Duration),
    /// The first request chunk containing these bytes goes to the server, and from then on nothing passes
    /// on that connection either way (its answer included); other connections are relayed as usual: a drive
    /// that leaves a connection hung after a request, as jsmodbus 5 does.
    Hang(&'static [u8]),
    /// As `Hang`, but from then on nothing passes on any connection, old or new: a drive that dies mid-case.
    Die(&'static [u8]),
    /// The first request chunk containing these bytes is held until the client sends its next chunk; then
    /// the held one goes to the server and the next one is dropped: a drive that holds a frame until more
    /// bytes come, answers it then, and swallows what completed it (pymodbus 3.16 after an MBAP length of
    /// 1). Everything else passes.
    Swallow(&'static [u8]),
}

/// A Modbus/TCP proxy on 127.0.0.1:0 in front of `upstream` that misbehaves as its [`Mode`] says. Its threads
/// end with their connections, or after [`PEER_LIFETIME`].
struct Proxy {
    addr: SocketAddr,
}

impl Proxy {
    fn start(upstream: SocketAddr, mode: Mode) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind proxy");
        let addr = listener.local_addr().expect("proxy address");
        let requests = Arc::new(AtomicUsize::new(0));
        let answers = Arc::new(AtomicUsize::new(0));
        let paused_until: Arc<Mutex<Option<Instant>>> = Arc::default();
        let dead = Arc::new(AtomicBool::new(false));
        listener.set_nonblocking(true).expect("nonblocking");
        thread::spawn(move || {
            let until = Instant::now() + PEER_LIFETIME;
            while Instant::now() < until {
                let Ok((client, _)) = listener.accept() else {
                    thread::sleep(Duration::from_millis(10));
                    continue;
                };
                let _ = client.set_nonblocking(false);
                let Ok(server) = TcpStream::connect_timeout(&upstream, Duration::from_secs(5))
                else {
                    continue;
                };
                for s in [&client, &server] {
                    let _ = s.set_nodelay(true);
                    let _ = s.set_read_timeout(Some(PEER_LIFETIME));
                }
                // A connection of a dead drive is hung from the start.
                let hung = match mode {
                    Mode::Die(_) => dead.clone(),
                    _ => Arc::new(AtomicBool::new(false)),
                };
                let swallowing: Arc<Mutex<Option<Vec<u8>>>> = Arc::default();
                // DelayAnswerTo: the next answer is to be held (set by the request, taken by its answer).
                let hold_next = Arc::new(AtomicBool::new(false));
                let pump = |mut from: TcpStream, to: TcpStream, upward: bool| {
                    let (requests, answers, paused_until, hung, swallowing, dead, hold_next) = (
                        requests.clone(),
                        answers.clone(),
                        paused_until.clone(),
                        hung.clone(),
                        swallowing.clone(),
                        dead.clone(),
                        hold_next.clone(),
                    );
                    let to = Arc::new(Mutex::new(to));
                    thread::spawn(move || {
                        let mut buf = [0u8; 4096];
                        while let Ok(n @ 1..) = from.read(&mut buf) {
                            let now = Instant::now();
                            let chunk = buf[..n].to_vec();
                            let count = if upward { &requests } else { &answers };
                            let nth = count.fetch_add(1, Ordering::SeqCst) + 1;
                            if let (Mode::Swallow(pattern), true) = (mode, upward) {
                                let mut held = swallowing.lock().expect("held");
                                if let Some(first) = held.take() {
                                    // The next chunk completes the held frame: the held one goes on, this
                                    // one is lost. Once only (`dead` marks it done).
                                    if to.lock().expect("to").write_all(&first).is_err() {
                                        break;
                                    }
                                    continue;
                                }
                                if !dead.load(Ordering::SeqCst)
                                    && chunk.windows(pattern.len()).any(|w| w == pattern)
                                {
                                    dead.store(true, Ordering::SeqCst);
                                    *held = Some(chunk);
                                    continue;
                                }
                            }
                            if let Mode::Hang(pattern) | Mode::Die(pattern) = mode {
                                if hung.load(Ordering::SeqCst) {
                                    continue;
                                }
                                if upward && chunk.windows(pattern.len()).any(|w| w == pattern) {
                                    // Hung before the server can answer: its answer is dropped too.
                                    hung.store(true, Ordering::SeqCst);
                                }
                            }
                            let mut held = None;
                            let mut lag = None;
                            {
                                let mut p = paused_until.lock().expect("pause");
                                match mode {
                                    Mode::Pause(at, pause) if upward && nth == at => {
                                        *p = Some(now + pause)
                                    }
                                    Mode::Delay(at, delay) if !upward && nth == at => {
                                        held = Some(delay)
                                    }
                                    // Once (`dead` marks it done); the answer of that connection.
                                    Mode::DelayAnswerTo(pattern, _, _)
                                        if upward
                                            && !dead.load(Ordering::SeqCst)
                                            && chunk
                                                .windows(pattern.len())
                                                .any(|w| w == pattern) =>
                                    {
                                        dead.store(true, Ordering::SeqCst);
                                        hold_next.store(true, Ordering::SeqCst);
                                    }
                                    Mode::DelayAnswerTo(_, delay, _)
                                        if !upward && hold_next.swap(false, Ordering::SeqCst) =>
                                    {
                                        held = Some(delay)
                                    }
                                    Mode::DelayAnswerTo(_, _, latency) if !upward => {
                                        lag = Some(latency)
                                    }
                                    _ => {}
                                }
                                if p.is_some_and(|u| now < u) {
                                    continue;
                                }
                            }
                            if let Some(lag) = lag {
                                thread::sleep(lag);
                            }
                            if let Some(delay) = held {
                                let to = to.clone();
                                thread::spawn(move || {
                                    thread::sleep(delay);
                                    let _ = to.lock().expect("to").write_all(&chunk);
                                });
                                continue;
                            }
                            if to.lock().expect("to").write_all(&chunk).is_err() {
                                break;
                            }
                        }
                        let to = to.lock().expect("to");
                        let _ = to.shutdown(Shutdown::Both);
                        let _ = from.shutdown(Shutdown::Both);
                    });
                };
                let (c2, s2) = (
                    client.try_clone().expect("clone"),
                    server.try_clone().expect("clone"),
                );
                pump(client, server, true);
                pump(s2, c2, false);
            }
        });
        Self { addr }
    }

    /// A `simulate --profile generic` process with a proxy in `mode` in front of it: the simulator (to be
    /// kept to the end of the test) and the proxy's target URL.
    fn before_generic_sim(mode: Mode) -> (SimProcess, String) {
        let sim = SimProcess::start(&["--profile", "generic", "--listen", "127.0.0.1:0"]);
        let proxy = Proxy::start(sim.tcp.expect("tcp"), mode);
        (sim, format!("tcp://{}", proxy.addr))
    }
}

#[test]
fn a_drive_silent_for_3_s_is_waited_for_and_the_run_goes_on() {
    // The 30th request: early in the catalog, among single-request read cases (a case of several requests
    // would see the silence end before its liveness probe).
    // Every case judged at its first attempt (see the test below for the reruns).
    let (sim, target) = Proxy::before_generic_sim(Mode::Pause(30, Duration::from_secs(3)));
    let dir = TempDir::new("paused-target");
    let (report, (code, out, err, took)) =
        read_only_generic_run(&target, &dir, &["--link-retries", "0"]);
    assert_eq!(
        code, 1,
        "the request lost in the silence FAILs\n{out}\n{err}"
    );
    assert!(took < Duration::from_secs(30), "took {took:?}");
    assert_complete(&report);
    let summary = &index(&report)["summary"];
    assert!(summary.get("ended").is_none(), "the run went on: {summary}");
    let liveness = summary["liveness"][0].as_str().expect("a liveness note");
    assert!(liveness.contains("recovered after"), "{liveness}");
    assert!(out.contains("recovered after"), "{out}");
    // Only the request(s) lost in the silence FAIL; the run went on to the end.
    let fails = summary["counts"]["FAIL"].as_u64().unwrap_or(0);
    assert!((1..=3).contains(&fails), "{summary}");
    assert!(
        summary["counts"]["PASS"].as_u64().unwrap_or(0) > 300,
        "{summary}"
    );
    // The simulator lives to the end of the test.
    drop(sim);
}

/// The same silence with the default reruns (`--link-retries 3`): the case whose request was lost in it got
/// no answer, as a case whose request a link lost does, and is run again after 0.5 s and 1 s; the attempt
/// after the silence comes through whole and is judged (PASS), and the run says that one case was run
/// again. A drive that goes silent for a while cannot be told from a link that drops for a while.
#[test]
fn a_request_lost_in_a_silence_of_3_s_is_run_again_and_judged_when_answered() {
    let (sim, target) = Proxy::before_generic_sim(Mode::Pause(30, Duration::from_secs(3)));
    let dir = TempDir::new("paused-target-again");
    let (report, (code, out, err, took)) = read_only_generic_run(&target, &dir, &[]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(took < Duration::from_secs(30), "took {took:?}");
    assert_complete(&report);
    assert!(
        err.contains("link: 1 case(s) run again") && err.contains(": 1 came through whole"),
        "{err}"
    );
    let summary = &index(&report)["summary"];
    assert_eq!(summary["counts"]["FAIL"], 0, "{summary}");
    drop(sim);
}

/// The case the two tests below stop: read coil 7, write it ON, read it back, write it OFF again. The
/// proxy's trigger is its write (unit 1, FC 05, coil 7, ON), which reaches the simulator.
const COIL_7: &str = "profile/generic/coil/7-coil-7";
const COIL_7_ON: &[u8] = &[0x01, 0x05, 0x00, 0x07, 0xFF, 0x00];

/// `run --cases 'profile/generic/coil/*' --preflight-timeout 500 EXTRA...` through a proxy in `mode` in front
/// of `simulate --profile generic`, checked to take under 20 s, complete its reports, FAIL [`COIL_7`]
/// alone and stop it after its write (two steps run): (exit code, stdout, stderr), the index's summary, and
/// that case's steps.
fn coil_7_through(
    mode: Mode,
    extra: &[&str],
) -> (
    i32,
    String,
    String,
    serde_json::Value,
    Vec<serde_json::Value>,
) {
    let (sim, target) = Proxy::before_generic_sim(mode);
    let dir = TempDir::new("coil-7");
    let report = dir.path().join("report");
    let report_s = report.to_string_lossy().into_owned();
    let mut args = run_args(&target, "generic", &["--cases", "profile/generic/coil/*"]);
    // The mid-case watch alone: a case that stalls is not run again (see noisy_link.rs for that).
    args.extend_from_slice(&[
        "--preflight-timeout",
        "500",
        "--report",
        &report_s,
        "--link-retries",
        "0",
    ]);
    args.extend_from_slice(extra);
    let (code, out, err, took) = harness_timed(&args, Duration::from_secs(60));
    drop(sim);
    assert!(took < Duration::from_secs(20), "took {took:?}");
    assert_complete(&report);
    let summary = index(&report)["summary"].clone();
    assert_eq!(summary["counts"]["FAIL"], 1, "{summary}");
    assert_eq!(summary["failing"][0], COIL_7, "{summary}");
    let record = case_records(&report)
        .into_iter()
        .find(|c| c.contains(&format!("\"id\":\"{COIL_7}\"")))
        .expect("the case's record");
    let record: serde_json::Value = serde_json::from_str(&record).expect("json");
    let steps = record["result"]["steps"].as_array().expect("steps").clone();
    assert_eq!(steps.len(), 2, "stopped after the write: {steps:#?}");
    (code, out, err, summary, steps)
}

/// A drive that leaves a connection hung after a request and answers on a new one (jsmodbus 5 did after an
/// unsupported function, and after a request with a byte too many): the case stops at that request, which
/// FAILs saying so, instead of sending its remaining steps to the hung connection (where each FAILed "no
/// response", the step that puts the coil back included); the run goes on, and the coil the unanswered
/// write set is put back by the leave-as-found keeper right after the case.
#[test]
fn a_connection_left_hung_mid_case_stops_the_case_at_that_request() {
    let (code, out, err, summary, steps) = coil_7_through(Mode::Hang(COIL_7_ON), &[]);
    assert_eq!(code, 1, "one FAIL\n{out}\n{err}");
    assert!(summary.get("ended").is_none(), "the run went on: {summary}");
    assert!(
        summary["counts"]["PASS"].as_u64().unwrap_or(0) >= 90,
        "the other coils' cases PASS on new connections: {summary}"
    );
    assert_eq!(steps[0]["verdict"], "PASS", "{steps:#?}");
    assert_eq!(steps[1]["verdict"], "FAIL", "{steps:#?}");
    let findings = steps[1]["findings"].to_string();
    assert!(
        findings.contains("the connection stopped answering after this request")
            && findings.contains("2 remaining step(s) were not sent"),
        "{findings}"
    );
    assert!(
        err.contains(&format!(
            "liveness: the connection stopped answering after {COIL_7}"
        )),
        "{err}"
    );
    // Put back by the keeper, verified by its read-back (the coil was written ON by the simulator).
    assert!(
        out.contains("every kept parameter reads as before"),
        "{out}"
    );
}

/// A drive that dies mid-case (nothing answers from one request on, on any connection): the case stops at
/// that request, which FAILs with what was tried, the run waits `--recovery-wait` for the drive and SKIPs
/// the rest; the remaining steps of the case are not sent into the silence one by one.
#[test]
fn a_drive_that_dies_mid_case_stops_the_case_and_the_run() {
    let (code, out, err, summary, steps) =
        coil_7_through(Mode::Die(COIL_7_ON), &["--recovery-wait", "2"]);
    assert_ne!(code, 0, "{out}\n{err}");
    let ended = summary["ended"].as_str().expect("why the run ended");
    assert!(
        ended.contains(&format!("stopped answering after {COIL_7}")),
        "{ended}"
    );
    let findings = steps[1]["findings"].to_string();
    assert!(
        findings.contains(
            "on this connection or a new one: the case's 2 remaining step(s) were not sent"
        ) && findings.contains("the target stopped answering after this request"),
        "{findings}"
    );
}

/// A drive that holds the request until the next bytes come, then answers it and swallows those (the
/// known-good read sent after the step's silence): the late answer to the step is not taken for the read's
/// own, it is noted on the step, and as the read's own answer never comes the case stops there. (Taking
/// any answer for the read's, the case went on, and the late answer showed nowhere in the report.)
#[test]
fn a_late_answer_to_the_step_is_not_taken_for_the_mid_case_reads() {
    let (code, out, err, _, steps) =
        coil_7_through(Mode::Swallow(COIL_7_ON), &["--timeout", "300"]);
    assert_eq!(code, 1, "{out}\n{err}");
    let findings = steps[1]["findings"].to_string();
    assert!(
        findings.contains("a late answer (transaction id")
            && findings.contains("during the known-good read after this step"),
        "{findings}"
    );
    assert!(
        out.contains("every kept parameter reads as before"),
        "{out}"
    );
}

/// `fuzz` against a drive that hangs a connection (after an FC 07 here: MBAP length 2, unit 1, FC 07) and
/// answers on a new one: the finding says the connection stopped answering, not the drive; against one that
/// dies there, that the drive stopped answering.
#[test]
fn fuzz_tells_a_hung_connection_from_a_dead_drive() {
    const FC_07: &[u8] = &[0x00, 0x02, 0x01, 0x07];
    for (mode, said) in [
        (
            Mode::Hang(FC_07),
            "the connection stopped answering (a new one is answered)",
        ),
        (Mode::Die(FC_07), "finding: the drive stopped answering"),
    ] {
        let (sim, target) = Proxy::before_generic_sim(mode);
        let dir = TempDir::new("fuzz-hung");
        let regressions = dir.path().to_string_lossy().into_owned();
        let (code, out, err, _) = harness_timed(
            &[
                "fuzz",
                "--target",
                &target,
                "--profile",
                "generic",
                "--seed",
                "1",
                "--max-cases",
                "3000",
                "--duration",
                "60s",
                "--timeout",
                "300",
                "--preflight-timeout",
                "500",
                "--regressions",
                &regressions,
            ],
            Duration::from_secs(90),
        );
        drop(sim);
        assert_eq!(code, 1, "{out}\n{err}");
        assert!(err.contains(said), "{err}");
    }
}

#[test]
fn a_run_stopped_by_an_error_still_completes_its_reports() {
    use engine::session::{Options, SessionError, run};
    use engine::targets::TargetUrl;
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let server = rt.block_on(test_support::serve(
        "generic",
        &[],
        test_support::loopback_tcp_and_rtu(),
    ));
    let dir = TempDir::new("error-reports");
    let report = dir.path().join("r");
    let mut o = Options::new(
        TargetUrl::parse(&format!("tcp://{}", server.tcp_addr().expect("tcp"))).expect("url"),
    );
    o.profile = Some("generic".into());
    o.report_dir = Some(report.clone());
    o.safety.read_only = true;
    // No liveness probe: the server going away is met as an error of the target (the connection refused).
    o.liveness = None;
    let stop = AtomicBool::new(false);
    let got = run(&o, &mut std::io::sink(), &stop, &mut |done, _, _, _| {
        if done == 10 {
            server.signal_shutdown();
        }
    });
    assert!(
        matches!(got, Err(SessionError::Target(_))),
        "the run stops on the target's error: {got:?}"
    );
    assert_complete(&report);
    let summary = &index(&report)["summary"];
    let ended = summary["ended"].as_str().expect("why the run ended");
    assert!(ended.starts_with("stopped on an error: "), "{ended}");
    assert!(summary["cases"].as_u64().unwrap_or(0) >= 10, "{summary}");
}

#[test]
fn a_late_answer_is_attributed_to_its_request_by_transaction_id() {
    // The 100th answer (a profile read: cases that keep their connection follow) comes 1.3 s late: after
    // its case's 1 s timeout and the liveness probe, within a later case (paced at 200 requests/s, so that
    // the run is still going when it comes).
    // Every case judged at its first attempt: run again, the late case would come through whole (a link that
    // holds an answer for a while, TCP retransmitting a lost segment, is not told from a late drive there).
    let (sim, target) = Proxy::before_generic_sim(Mode::Delay(100, Duration::from_millis(1300)));
    let dir = TempDir::new("late-answer");
    let (report, (code, out, err, _)) =
        read_only_generic_run(&target, &dir, &["--max-rate", "200", "--link-retries", "0"]);
    assert_eq!(
        code, 1,
        "the case whose answer was late FAILs\n{out}\n{err}"
    );
    assert_complete(&report);
    let summary = &index(&report)["summary"];
    // Only the late one FAILs: the later case that met its answer is not blamed for it.
    assert_eq!(summary["counts"]["FAIL"], 1, "{summary}");
    let late = summary["failing"][0].as_str().expect("the late case");
    let cases = case_records(&report);
    let noted = cases
        .iter()
        .find(|c| c.contains("a late answer (transaction id"))
        .unwrap_or_else(|| {
            panic!(
                "the late answer is noted where it arrived; the late case: {:?}",
                cases.iter().find(|c| c.contains(late))
            )
        });
    assert!(
        noted.contains(&format!("to a request of {late} arrived")),
        "attributed to {late}: {noted}"
    );
    assert!(summary.get("ended").is_none(), "{summary}");
    drop(sim);
}

/// The late answer of the test above with the default reruns: it comes 0.3 s after the case's 1 s timeout,
/// within the pause before the case would be run again (half the timeout). The drive answered and no frame
/// was lost, so the case is not run again: its first attempt is judged (FAIL), as without reruns, and the
/// run counts it among the drive's own. Run again, it would come through whole and PASS.
#[test]
fn a_late_answer_in_the_pause_before_a_rerun_is_judged_at_the_first_attempt() {
    let (sim, target) = Proxy::before_generic_sim(Mode::Delay(100, Duration::from_millis(1300)));
    let dir = TempDir::new("late-answer-rerun");
    let (report, (code, out, err, _)) =
        read_only_generic_run(&target, &dir, &["--max-rate", "200"]);
    assert_eq!(code, 1, "the late case FAILs\n{out}\n{err}");
    let summary = &index(&report)["summary"];
    assert_eq!(summary["counts"]["FAIL"], 1, "{summary}");
    let late = summary["failing"][0].as_str().expect("the late case");
    let cases = case_records(&report);
    let record = cases
        .iter()
        .find(|c| c.contains(&format!("\"{late}\"")))
        .expect("the late case's record");
    assert!(
        record.contains("judged at attempt 1, whose answer came late"),
        "{record}"
    );
    assert!(
        err.contains("link: 1 case(s) run again")
            && err.contains("1 FAILed the same way again or answered late"),
        "{err}"
    );
    drop(sim);
}

/// The same for a case that writes, against a drive that takes 200 ms over every answer and answers the
/// case's FC 16 whose byte count disagrees with its quantity late (timeout 1 s). Between attempts the keeper
/// reads back what the case may have changed, on the same connection; and the case has steps after the
/// unanswered one. A late answer that came while the keeper's read was out was noted there as late, and the
/// look for one in the pause after it saw nothing: the case was run again and PASSed at its second attempt.
/// Now the pause comes before the keeper's read. And a late answer that comes during a later step of the
/// case (noted there, not taken for that step's) is the drive's answer too. Either way the case is judged at
/// its first attempt, FAIL, as without reruns, and the drive is left as found.
#[test]
fn a_late_answer_to_a_writing_case_is_seen_after_the_case_or_during_it() {
    for (late_ms, judged) in [
        // After the case's last step (its put-back write, sent about 1.43 s after the late request and
        // answered 0.2 s later),
        // while the keeper's read-back is out.
        (
            1730,
            "judged at attempt 1, whose answer came late (the drive answered",
        ),
        // During that last step.
        (
            1530,
            "judged at attempt 1, whose answer came late, during a later step",
        ),
    ] {
        let (sim, target) = Proxy::before_generic_sim(Mode::DelayAnswerTo(
            &[0x01, 0x10, 0x00, 0x00, 0x00, 0x02, 0x02],
            Duration::from_millis(late_ms),
            Duration::from_millis(200),
        ));
        let dir = TempDir::new("late-answer-keeper");
        let report = dir.path().join("report");
        let report_s = report.to_string_lossy().into_owned();
        let args = run_args(
            &target,
            "generic",
            &[
                "--cases",
                "spec/app-6.12/byte-count-mismatch/fc-0x10",
                "--report",
                &report_s,
            ],
        );
        let (code, out, err, _) = harness_timed(&args, Duration::from_secs(90));
        let cases = case_records(&report);
        assert_eq!(code, 1, "the late case FAILs ({late_ms} ms)\n{out}\n{err}");
        assert_eq!(cases.len(), 1, "{cases:?}");
        assert!(cases[0].contains(judged), "{late_ms} ms: {}", cases[0]);
        assert!(
            out.contains("every kept parameter reads as before"),
            "{out}"
        );
        drop(sim);
    }
}

#[test]
fn a_probe_whose_target_stops_answering_stops_and_exits_2() {
    // From the 30th request on (the pre-flight and the function codes answered, the scan begun) the drive
    // is silent for longer than the probe lasts.
    let (sim, target) = Proxy::before_generic_sim(Mode::Pause(30, Duration::from_secs(60)));
    let (code, out, err, took) = harness_timed(
        &[
            "probe",
            "--target",
            &target,
            "--scan",
            "0-0xFF",
            "--timeout",
            "200",
        ],
        Duration::from_secs(90),
    );
    assert_eq!(code, 2, "{out}\n{err}");
    // 8 unanswered reads and the known-good one at 200 ms each, not 4 x 256 of them.
    assert!(took < Duration::from_secs(10), "took {took:?}");
    assert!(out.contains("THE PROBE STOPPED EARLY"), "{out}");
    assert!(err.contains("the target stopped answering"), "{err}");
    drop(sim);
}
