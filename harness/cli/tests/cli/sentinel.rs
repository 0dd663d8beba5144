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

/// A request the drive answers by closing the connection, as the reference does (a PDU over 253 bytes),
/// ends its wait at the close: the log does not count it as a silence listened out for the whole window, as
/// it did (1 of 1 here; in a 10 s `fuzz` campaign against `simulate`, 1,486 "listened out for the whole
/// window (300 ms)", every one of them ended by a close within 0.2 ms). Where the window does run out
/// (`--no-sentinel`), it is counted.
#[test]
fn a_close_is_not_counted_as_a_window_listened_out() {
    let sim = SimProcess::on_loopback("mdrive", "--listen", None);
    let url = sim.tcp_url();
    let (code, out, err) = harness(&run_args(
        &url,
        "mdrive",
        &["--cases", "tcp/pdu/over-253-bytes"],
    ));
    assert_eq!(code, 0, "{out}\n{err}");
    let line = err.lines().find(|l| l.starts_with("silences: "));
    assert!(
        line.is_none_or(|_| silences(&err).2 == 0),
        "a close counted as a window listened out: {err}"
    );
    let (code, out, err) = harness(&run_args(
        &url,
        "mdrive",
        &[
            "--cases",
            "tcp/mbap/request-protocol-id-nonzero",
            "--no-sentinel",
        ],
    ));
    assert_eq!(code, 0, "{out}\n{err}");
    assert_eq!(silences(&err), (0, 0, 1), "{err}");
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

/// A relay on 127.0.0.1:0 in front of `upstream` that holds each chunk the server sends for `delay` before
/// passing it on, and closes both sides as soon as its client half-closes, dropping what it holds: a server
/// that writes its answers on a later turn of its event loop and closes when it reads the client's FIN
/// (modbus-serial 8.0.25). Its threads end when the connections close; the listener ends on drop.
struct DeferringProxy {
    addr: std::net::SocketAddr,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl DeferringProxy {
    fn start(upstream: std::net::SocketAddr, delay: std::time::Duration) -> Self {
        use std::io::{Read, Write};
        use std::net::{Shutdown, TcpListener, TcpStream};
        use std::sync::Arc;
        use std::sync::atomic::{AtomicBool, Ordering};
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("address");
        let stop = Arc::new(AtomicBool::new(false));
        let st = stop.clone();
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                if st.load(Ordering::SeqCst) {
                    break;
                }
                let Ok(client) = conn else { continue };
                let Ok(server) =
                    TcpStream::connect_timeout(&upstream, std::time::Duration::from_secs(2))
                else {
                    continue;
                };
                let _ = client.set_nodelay(true);
                let _ = server.set_nodelay(true);
                let closed = Arc::new(AtomicBool::new(false));
                let (mut c_in, mut s_out) = (
                    client.try_clone().expect("clone"),
                    server.try_clone().expect("clone"),
                );
                let shut = closed.clone();
                std::thread::spawn(move || {
                    let mut buf = [0u8; 4096];
                    while let Ok(n @ 1..) = c_in.read(&mut buf) {
                        if s_out.write_all(&buf[..n]).is_err() {
                            break;
                        }
                    }
                    // The client's FIN (or an error): close at once, whatever is held.
                    shut.store(true, Ordering::SeqCst);
                    let _ = s_out.shutdown(Shutdown::Both);
                    let _ = c_in.shutdown(Shutdown::Both);
                });
                let (mut s_in, mut c_out) = (server, client);
                std::thread::spawn(move || {
                    let mut buf = [0u8; 4096];
                    while let Ok(n @ 1..) = s_in.read(&mut buf) {
                        std::thread::sleep(delay);
                        if closed.load(Ordering::SeqCst) || c_out.write_all(&buf[..n]).is_err() {
                            break;
                        }
                    }
                    let _ = c_out.shutdown(Shutdown::Both);
                    let _ = s_in.shutdown(Shutdown::Both);
                });
            }
        });
        Self { addr, stop }
    }
}

impl Drop for DeferringProxy {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        let _ =
            std::net::TcpStream::connect_timeout(&self.addr, std::time::Duration::from_millis(200));
    }
}

/// A drive that answers 5 ms after each request and closes on the harness's FIN, dropping an answer not yet
/// sent: the half-close that proves a silence comes after twice the slowest recent answer, so an answer
/// to the request the drive must ignore (`mbap-length-ignored`) is seen and FAILs, as with the window
/// listened out; the healthy drive's silence is still proven by its close. (With the FIN right behind the
/// request, the faulted drive PASSed: its answer was never sent.)
#[test]
fn an_answer_written_late_is_seen_before_the_half_close() {
    let case = "tcp/mbap/request-length-plus-1";
    for (fault, code_wanted) in [(None, 0), (Some("mbap-length-ignored"), 1)] {
        let sim = SimProcess::on_loopback("mdrive", "--listen", fault);
        let upstream = sim
            .tcp_url()
            .trim_start_matches("tcp://")
            .parse()
            .expect("address");
        let proxy = DeferringProxy::start(upstream, std::time::Duration::from_millis(5));
        let url = format!("tcp://{}", proxy.addr);
        let (code, out, err) = harness(&run_args(&url, "mdrive", &["--cases", case]));
        assert_eq!(code, code_wanted, "{case} {fault:?}: {out}\n{err}");
        match fault {
            None => assert_eq!(silences(&err), (0, 1, 0), "{case}: {err}"),
            Some(_) => assert!(out.contains("FAIL"), "{out}"),
        }
    }
}

/// RTU has no sentinel: a broadcast or a request to another address listens out the window, which `fuzz`
/// takes from `--silence` as `run` does (300 ms by default, made for a real line; on loopback a shorter one
/// lets a campaign over RTU over TCP run). Its log says how many silences were listened out and for how
/// long; a drive that answers a broadcast still FAILs with the shorter window.
#[test]
fn fuzz_listens_out_rtu_silences_for_its_silence_window() {
    for (fault, code_wanted) in [(None, 0), (Some("broadcast-answered"), 1)] {
        let sim = SimProcess::on_loopback("generic", "--rtu-over-tcp", fault);
        let url = sim.rtu_over_tcp_url();
        let dir = TempDir::new("fuzz-silence");
        let regressions = dir.path().to_string_lossy().into_owned();
        let (code, out, err) = harness(&[
            "fuzz",
            "--target",
            &url,
            "--profile",
            "generic",
            "--seed",
            "1",
            "--max-cases",
            "200",
            "--duration",
            "60s",
            "--silence",
            "40",
            "--timeout",
            "300",
            "--preflight-timeout",
            "1000",
            "--regressions",
            &regressions,
        ]);
        assert_eq!(code, code_wanted, "{fault:?}: {out}\n{err}");
        match fault {
            None => {
                let (sentinel, close, listened) = silences(&err);
                assert_eq!((sentinel, close), (0, 0), "{err}");
                assert!(listened > 0, "{err}");
                assert!(
                    err.contains("listened out for the whole window (40 ms: RTU has no sentinel"),
                    "{err}"
                );
            }
            Some(_) => assert!(err.contains("expected no response, got"), "{err}"),
        }
    }
}
