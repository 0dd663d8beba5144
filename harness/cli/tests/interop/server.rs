//! The simulator's servers as a client sees them on the wire: pipelining, many connections, closing on an
//! unrecoverable stream, delays, shutdown; and the `simulate` command line (faults on the wire, signals,
//! argument errors). Raw bytes throughout, so nothing here depends on a client library's leniency.

use std::process::{Command as StdCommand, Stdio};
use std::time::{Duration, Instant};

use codec::rtu::crc_ok;
use drives::Fault;
use drives::station::LATE_RESPONSE_DELAY;
use engine::servers::{self, ServerConfig, ServerError, ServerHandle};
use test_support::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// FC 03 read of `quantity` registers at `address`.
fn read_holding(address: u16, quantity: u16) -> Vec<u8> {
    let mut pdu = vec![0x03];
    pdu.extend_from_slice(&address.to_be_bytes());
    pdu.extend_from_slice(&quantity.to_be_bytes());
    pdu
}

/// FC 08 / 00 (return query data): answered by the station whatever the model, echoing `data`.
fn echo(data: u16) -> Vec<u8> {
    let mut pdu = vec![0x08, 0x00, 0x00];
    pdu.extend_from_slice(&data.to_be_bytes());
    pdu
}

/// An in-process SD2x with `faults` on loopback (Modbus/TCP and RTU over TCP, port 0), and a client
/// connected to its Modbus/TCP endpoint.
async fn sd2x_and_tcp_client(faults: &[Fault]) -> (ServerHandle, TcpStream) {
    let server = serve("sd2x", faults, loopback_tcp_and_rtu()).await;
    let s = connect(server.tcp_addr().unwrap()).await;
    (server, s)
}

/// Write `bytes` to `s`, bounded in time.
async fn send(s: &mut TcpStream, bytes: &[u8]) {
    within("write", s.write_all(bytes)).await.expect("write");
}

/// Two requests in one write are both answered, in order, each with its own transaction id.
#[tokio::test]
async fn tcp_pipelined_requests_answered_in_order() {
    let (server, mut s) = sd2x_and_tcp_client(&[]).await;
    let first = tcp_adu(0x0101, 1, &echo(0xAAAA));
    let second = tcp_adu(0x0202, 1, &echo(0x5555));
    let both = [first.clone(), second.clone()].concat();
    send(&mut s, &both).await;
    assert_eq!(read_tcp_adu(&mut s).await, first, "first reply");
    assert_eq!(read_tcp_adu(&mut s).await, second, "second reply");
    server.shutdown().await;
}

/// RTU over TCP: two frames in one segment are cut by length and CRC and answered in order.
#[tokio::test]
async fn rtu_over_tcp_back_to_back_frames_answered_in_order() {
    let server = serve("sd2x", &[], loopback_tcp_and_rtu()).await;
    let mut s = connect(server.rtu_over_tcp_addr().unwrap()).await;
    let first = rtu_adu(1, &echo(0x1111));
    let second = rtu_adu(1, &echo(0x2222));
    let both = [first.clone(), second.clone()].concat();
    send(&mut s, &both).await;
    assert_eq!(read_upto(&mut s, both.len()).await, both);
    server.shutdown().await;
}

/// With `pipeline-drop` only the first of two requests arriving together is answered: the fault reaches
/// the wire through the server (the check a conformance case relies on).
#[tokio::test]
async fn tcp_pipeline_drop_fault_reaches_the_wire() {
    let (server, mut s) = sd2x_and_tcp_client(&[Fault::PipelineDrop]).await;
    let first = tcp_adu(7, 1, &echo(1));
    let second = tcp_adu(8, 1, &echo(2));
    let third = tcp_adu(9, 1, &echo(3));
    let both = [first.clone(), second].concat();
    send(&mut s, &both).await;
    assert_eq!(read_tcp_adu(&mut s).await, first);
    // A later request on its own is answered: had the second one been answered, it would come first.
    send(&mut s, &third).await;
    assert_eq!(read_tcp_adu(&mut s).await, third);
    server.shutdown().await;
}

/// 50 connections at once, each with several requests in flight one after the other: every one is
/// answered with its own transaction id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_concurrent_connections_all_answered() {
    const CONNS: u16 = 50;
    const REQUESTS: u16 = 20;
    let server = serve("sd2x", &[], loopback_tcp_and_rtu()).await;
    let addr = server.tcp_addr().unwrap();
    // Connect all first, so the connections are open at the same time.
    let mut streams = Vec::new();
    for _ in 0..CONNS {
        streams.push(connect(addr).await);
    }
    let mut tasks = tokio::task::JoinSet::new();
    for (c, mut s) in streams.into_iter().enumerate() {
        tasks.spawn(async move {
            for r in 0..REQUESTS {
                let tid = (c as u16) << 8 | r;
                let req = tcp_adu(tid, 1, &echo(tid ^ 0xFFFF));
                s.write_all(&req).await.expect("write");
                assert_eq!(
                    read_tcp_adu(&mut s).await,
                    req,
                    "connection {c} request {r}"
                );
            }
        });
    }
    let all = async {
        while let Some(done) = tasks.join_next().await {
            done.expect("client task");
        }
    };
    tokio::time::timeout(Duration::from_secs(30), all)
        .await
        .expect("50 connections not served within 30 s");
    server.shutdown().await;
}

/// An MBAP length of 1 cannot be resynchronised: the server closes the connection, and serves others.
#[tokio::test]
async fn tcp_bad_mbap_length_closes_the_connection() {
    let (server, mut s) = sd2x_and_tcp_client(&[]).await;
    let addr = server.tcp_addr().unwrap();
    send(&mut s, &[0, 1, 0, 0, 0, 1, 1]).await;
    let mut buf = [0u8; 16];
    let n = tokio::time::timeout(STEP, s.read(&mut buf))
        .await
        .expect("server neither answered nor closed")
        .unwrap_or(0);
    assert_eq!(n, 0, "expected a close, got {:02X?}", &buf[..n]);
    let req = tcp_adu(3, 1, &echo(3));
    assert_eq!(
        tcp_exchange(addr, &req).await,
        req,
        "a new connection works"
    );
    server.shutdown().await;
}

/// `late-response` delays the reply by its stated time (the server honours `Wire::delay`), and the
/// connection keeps reading meanwhile: a second request is answered right after the first.
#[tokio::test]
async fn tcp_late_response_delay_is_honoured() {
    let (server, mut s) = sd2x_and_tcp_client(&[Fault::LateResponse]).await;
    let first = tcp_adu(1, 1, &echo(1));
    let second = tcp_adu(2, 1, &echo(2));
    let sent = Instant::now();
    send(&mut s, &first).await;
    // The second request arrives while the first reply waits: in its own segment, not read together.
    let gap = Duration::from_millis(200);
    tokio::time::sleep(gap).await;
    send(&mut s, &second).await;
    assert_eq!(read_tcp_adu(&mut s).await, first);
    assert!(
        sent.elapsed() >= LATE_RESPONSE_DELAY,
        "reply after {:?}, before the fault's {LATE_RESPONSE_DELAY:?}",
        sent.elapsed()
    );
    assert_eq!(read_tcp_adu(&mut s).await, second);
    // Due at its own arrival + delay (~1.7 s), not after the first reply + delay (~3 s): generous bound.
    let bound = LATE_RESPONSE_DELAY + gap + LATE_RESPONSE_DELAY / 2;
    assert!(
        sent.elapsed() < bound,
        "second reply after {:?}: the delays were serialised",
        sent.elapsed()
    );
    server.shutdown().await;
}

/// Shutdown ends the listeners and open connections (the client sees the close) in bounded time.
#[tokio::test]
async fn shutdown_closes_open_connections() {
    let (server, mut s) = sd2x_and_tcp_client(&[]).await;
    let addr = server.tcp_addr().unwrap();
    let req = tcp_adu(1, 1, &echo(1));
    send(&mut s, &req).await;
    assert_eq!(read_tcp_adu(&mut s).await, req);
    tokio::time::timeout(STEP, server.shutdown())
        .await
        .expect("shutdown did not finish");
    let mut buf = [0u8; 8];
    let n = tokio::time::timeout(STEP, s.read(&mut buf))
        .await
        .expect("connection still open after shutdown")
        .unwrap_or(0);
    assert_eq!(n, 0);
    assert!(
        TcpStream::connect(addr).await.is_err(),
        "listener still accepting"
    );
}

#[tokio::test]
async fn start_without_endpoint_is_an_error() {
    let r = servers::start(station("sd2x", &[]), &ServerConfig::default()).await;
    assert!(matches!(r, Err(ServerError::NoEndpoint)));
}

#[tokio::test]
async fn start_on_a_taken_port_is_a_bind_error() {
    let first = serve("sd2x", &[], loopback_tcp_and_rtu()).await;
    let config = ServerConfig {
        tcp: first.tcp_addr(),
        ..ServerConfig::default()
    };
    let r = servers::start(station("sd2x", &[]), &config).await;
    assert!(matches!(r, Err(ServerError::Bind { .. })), "{:?}", r.err());
    first.shutdown().await;
}

// ---- the `simulate` command line ------------------------------------------------------------------------

/// `--fault tid-not-echoed` on the command line: the reply's transaction id is the request's plus one.
#[tokio::test]
async fn cli_fault_tid_not_echoed_over_tcp() {
    let plain = SimProcess::on_loopback("sd2x", "--listen", None);
    let req = tcp_adu(0x1234, 1, &echo(0xBEEF));
    assert_eq!(tcp_exchange(plain.tcp.unwrap(), &req).await, req);
    let faulty = SimProcess::on_loopback("sd2x", "--listen", Some("tid-not-echoed"));
    let reply = tcp_exchange(faulty.tcp.unwrap(), &req).await;
    assert_eq!(&reply[..2], &[0x12, 0x35], "transaction id of {reply:02X?}");
    assert_eq!(&reply[2..], &req[2..], "the rest is unchanged");
}

/// `--fault wrong-crc` on the command line, RTU over TCP: the reply's CRC is wrong (and right without it).
#[tokio::test]
async fn cli_fault_wrong_crc_over_rtu_over_tcp() {
    let req = rtu_adu(1, &echo(0x0F0F));
    for (fault, crc_good) in [(None, true), (Some("wrong-crc"), false)] {
        let sim = SimProcess::on_loopback("sd2x", "--rtu-over-tcp", fault);
        let mut s = connect(sim.rtu_over_tcp.unwrap()).await;
        send(&mut s, &req).await;
        let reply = read_upto(&mut s, req.len()).await;
        assert_eq!(reply.len(), req.len(), "{fault:?}: {reply:02X?}");
        assert_eq!(&reply[..reply.len() - 2], &req[..req.len() - 2]);
        assert_eq!(crc_ok(&reply), crc_good, "{fault:?}: {reply:02X?}");
    }
}

/// `--fault wrong-crc` on a serial line (socat pty pair): the reply's CRC is wrong.
#[tokio::test]
async fn cli_fault_wrong_crc_over_serial_pty() {
    skip_unless!(socat_or_skip);
    let pty = PtyPair::start();
    let sim = SimProcess::serial_19200_8n1(&pty.a, "sd2x", &["--fault", "wrong-crc"]);
    assert_eq!(sim.serial.as_deref(), Some(pty.a.as_path()));
    let mut port = open_pty_client(&pty.b);
    let req = rtu_adu(1, &echo(0x0F0F));
    port.write_all(&req).await.unwrap();
    let reply = read_upto(&mut port, req.len()).await;
    assert_eq!(reply.len(), req.len(), "{reply:02X?}");
    assert!(!crc_ok(&reply), "CRC should be wrong: {reply:02X?}");
}

/// SIGTERM and SIGINT stop `simulate` cleanly (exit 0), also with a client connected.
#[tokio::test]
async fn cli_stops_cleanly_on_sigterm_and_sigint() {
    for signal in ["-TERM", "-INT"] {
        let mut sim = SimProcess::start(&["--profile", "sd2x", "--listen", "127.0.0.1:0"]);
        let _client = connect(sim.tcp.unwrap()).await;
        let killed = StdCommand::new("kill")
            .arg(signal)
            .arg(sim.pid().to_string())
            .status()
            .expect("run kill");
        assert!(killed.success());
        let status = wait_bounded(&mut sim.child.0, STEP, "simulate");
        assert!(status.success(), "{signal}: {status:?}");
    }
}

/// A simulator whose serial line goes away says so and exits with failure instead of lingering.
#[tokio::test]
async fn cli_exits_when_its_serial_line_goes_away() {
    skip_unless!(socat_or_skip);
    let mut pty = PtyPair::start();
    let tty = pty.a.to_string_lossy().into_owned();
    let mut sim = SimProcess::start(&["--profile", "sd2x", "--serial", &tty]);
    pty.cut();
    let status = wait_bounded(&mut sim.child.0, STEP, "simulate");
    assert_eq!(status.code(), Some(1), "{status:?}");
}

/// Run `simulate ARGS` expecting it to exit by itself; returns (exit code, stdout, stderr).
fn simulate_exits(args: &[&str]) -> (Option<i32>, String, String) {
    let mut child = spawn_guarded(
        StdCommand::new(env!("CARGO_BIN_EXE_modbus-harness"))
            .arg("simulate")
            .args(args),
        Stdio::piped(),
        Stdio::piped(),
    );
    let status = wait_bounded(&mut child.0, STEP, "simulate");
    let mut out = String::new();
    let mut err = String::new();
    use std::io::Read;
    if let Some(mut o) = child.0.stdout.take() {
        let _ = o.read_to_string(&mut out);
    }
    if let Some(mut e) = child.0.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    (status.code(), out, err)
}

#[test]
fn cli_unknown_profile_lists_the_known_ones() {
    let (code, _, err) = simulate_exits(&["--profile", "nosuch", "--listen", "127.0.0.1:0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("nosuch") && err.contains("sd2x") && err.contains("mdrive"),
        "{err}"
    );
}

#[test]
fn cli_unknown_fault_lists_the_known_ones() {
    let (code, _, err) = simulate_exits(&[
        "--profile",
        "sd2x",
        "--listen",
        "127.0.0.1:0",
        "--fault",
        "nosuch",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("nosuch") && err.contains("tid-not-echoed") && err.contains("wrong-crc"),
        "{err}"
    );
}

#[test]
fn cli_unopenable_serial_names_the_path_and_the_error() {
    let dir = TempDir::new("noserial");
    let path = dir.path().join("no-such-tty");
    let path = path.to_string_lossy().into_owned();
    let (code, _, err) = simulate_exits(&["--profile", "sd2x", "--serial", &path]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains(&path) && err.contains("No such file"), "{err}");
}

#[test]
fn cli_needs_an_endpoint() {
    let (code, _, err) = simulate_exits(&["--profile", "sd2x"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--listen"), "{err}");
}

#[test]
fn cli_rejects_a_unit_outside_the_profile() {
    let (code, _, err) = simulate_exits(&[
        "--profile",
        "sd2x",
        "--listen",
        "127.0.0.1:0",
        "--unit",
        "255",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("255"), "{err}");
}

#[test]
fn cli_list_faults_prints_every_fault() {
    let (code, out, err) = simulate_exits(&["--list-faults"]);
    assert_eq!(code, Some(0), "{err}");
    for (fault, name, what) in Fault::ALL {
        let line = out
            .lines()
            .find(|l| l.split_whitespace().next() == Some(*name))
            .unwrap_or_else(|| panic!("{fault:?} missing from:\n{out}"));
        assert!(line.contains(what), "{line}");
    }
}

/// `--unit` is honoured on RTU: a frame for the profile's default address is ignored, one for the given
/// address is answered.
#[tokio::test]
async fn cli_unit_selects_the_rtu_address() {
    let sim = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--rtu-over-tcp",
        "127.0.0.1:0",
        "--unit",
        "7",
    ]);
    let mut s = connect(sim.rtu_over_tcp.unwrap()).await;
    let ours = rtu_adu(7, &echo(0x0707));
    // Addressed to slave 1 (not us) first, then to 7: only the second is answered.
    let other = rtu_adu(1, &echo(0x0101));
    s.write_all(&[other, ours.clone()].concat()).await.unwrap();
    assert_eq!(read_upto(&mut s, ours.len() * 2).await, ours);
}

/// The listening lines name every endpoint asked for, each with the bound port.
#[tokio::test]
async fn cli_prints_one_listening_line_per_endpoint() {
    let sim = SimProcess::start(&[
        "--profile",
        "mdrive",
        "--listen",
        "127.0.0.1:0",
        "--rtu-over-tcp",
        "127.0.0.1:0",
    ]);
    let tcp = sim.tcp.expect("tcp line");
    let rot = sim.rtu_over_tcp.expect("rtu-over-tcp line");
    assert_ne!(tcp.port(), 0);
    assert_ne!(rot.port(), 0);
    assert_ne!(tcp.port(), rot.port());
    let req = tcp_adu(5, 1, &read_holding(0x008B, 2));
    let reply = tcp_exchange(tcp, &req).await;
    assert_eq!(&reply[..2], &[0, 5], "{reply:02X?}");
}
