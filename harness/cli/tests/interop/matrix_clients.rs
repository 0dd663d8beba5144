//! The client pairs of the interop matrix that the other interop tests leave out: every third-party client
//! (tokio-modbus, mbpoll, the libmodbus client, the pymodbus client) against every reference drive over the
//! transports its manual gives it. The others cover SD2x over a pty (all four clients) and RTU over TCP
//! (tokio-modbus), MDrive over Modbus/TCP (all four); this file adds:
//!
//! - LMD over Modbus/TCP, all four clients: the manual's 4.2.2 output read (O1=1, O2=0, O3=1), 4.2.4 VM read
//!   (768000, low word first), 4.2.5 VM write (600000) read back, 4.2.3 output write;
//! - SD2x over RTU over TCP for the pymodbus client (its RTU framer on a socket), the libmodbus client and
//!   mbpoll (neither speaks RTU over TCP: a socat pty whose bytes go to the simulator's RTU-over-TCP
//!   endpoint carries their RTU frames): the manual's 6.1 telegrams, the watchdog, the 6.3 status word
//!   0x7038, and exception 01 for a function the SD2x lacks.
//!
//! The README's "Interoperability" table lists which test covers which (client, drive, transport).

use engine::servers::{ServerConfig, ServerHandle};
use test_support::mbpoll::*;
use test_support::peers::{Peer, client_command};
use test_support::*;
use tokio_modbus::prelude::*;

use test_support::modbus_client::{self, answered};

/// Run `peer` with `endpoint` and the operations of `ops`, and compare every output line with the expected
/// one (`ops`: operation, expected line).
async fn expect_lines(peer: Peer, test: &str, endpoint: &[String], ops: &[(&str, &str)]) {
    let mut cmd = client_command(peer, test).expect("toolchain checked by the caller");
    cmd.args(endpoint).args(ops.iter().map(|(op, _)| op));
    let (ok, out, err) = run_client(&mut cmd).await;
    let got: Vec<&str> = out.lines().collect();
    for (i, (op, want)) in ops.iter().enumerate() {
        assert_eq!(
            got.get(i).copied(),
            Some(*want),
            "{test}: {peer:?}, op {op}; whole output:\n{out}\nstderr:\n{err}"
        );
    }
    assert!(ok, "{test}: {peer:?} exited with failure:\n{out}\n{err}");
}

/// An in-process server for `profile` on one loopback endpoint (port 0).
async fn serve_on(profile_name: &str, rtu_over_tcp: bool) -> ServerHandle {
    let any: std::net::SocketAddr = "127.0.0.1:0".parse().unwrap();
    let config = if rtu_over_tcp {
        ServerConfig {
            rtu_over_tcp: Some(any),
            ..ServerConfig::default()
        }
    } else {
        ServerConfig {
            tcp: Some(any),
            ..ServerConfig::default()
        }
    };
    serve(profile_name, &[], config).await
}

// ---- LMD over Modbus/TCP ---------------------------------------------------------------------------------

/// LMD manual 4.2.4: VM (0x008B-0x008C) reads its default 768000 = 0x000BB800, low word first.
const LMD_VM_DEFAULT: [u16; 2] = [0xB800, 0x000B];
/// LMD manual 4.2.5: VM = 600000 = 0x000927C0, low word first.
const LMD_VM_600000: [u16; 2] = [0x27C0, 0x0009];

/// The LMD's manual answers through a client that prints lines: 4.2.2 outputs (O1=1, O2=0, O3=1), 4.2.4 VM,
/// 4.2.5 VM written and read back, 4.2.3 output 3 ON (its echo), then output 2 ON reads back.
async fn lmd_tcp(peer: Peer, test: &str) {
    if client_command(peer, test).is_none() {
        return;
    }
    let server = serve_on("lmd", false).await;
    let port = server.tcp_addr().expect("tcp addr").port().to_string();
    let unit = profile("lmd").device.default_unit.to_string();
    let endpoint = vec!["tcp".into(), "127.0.0.1".into(), port, unit];
    let vm = |w: [u16; 2]| format!("{} {}", w[0], w[1]);
    let (vm_default, vm_new) = (vm(LMD_VM_DEFAULT), vm(LMD_VM_600000));
    let write = format!("wh:0x8B:{},{}", LMD_VM_600000[0], LMD_VM_600000[1]);
    expect_lines(
        peer,
        test,
        &endpoint,
        &[
            ("rc:0:3", "1 0 1"),
            ("rh:0x8B:2", &vm_default),
            (&write, "ok"),
            ("rh:0x8B:2", &vm_new),
            ("wc:2:1", "ok"),
            ("wc:1:1", "ok"),
            ("rc:0:3", "1 1 1"),
        ],
    )
    .await;
    server.shutdown().await;
}

#[tokio::test]
async fn libmodbus_tcp_lmd_manual_answers() {
    lmd_tcp(Peer::Libmodbus, test_name!()).await;
}

#[tokio::test]
async fn pymodbus_tcp_lmd_manual_answers() {
    lmd_tcp(Peer::Pymodbus, test_name!()).await;
}

/// The same LMD answers through tokio-modbus.
#[tokio::test]
async fn tokio_modbus_tcp_lmd_manual_answers() {
    let server = serve_on("lmd", false).await;
    let addr = server.tcp_addr().expect("tcp addr");
    let mut ctx = modbus_client::tcp(addr, profile("lmd").device.default_unit).await;
    assert_eq!(
        answered("FC 01", ctx.read_coils(0, 3), "FC 01").await,
        [true, false, true]
    );
    assert_eq!(
        answered("FC 03", ctx.read_holding_registers(0x8B, 2), "FC 03").await,
        LMD_VM_DEFAULT
    );
    answered(
        "FC 16",
        ctx.write_multiple_registers(0x8B, &LMD_VM_600000),
        "FC 16 accepted",
    )
    .await;
    let words = answered("FC 03", ctx.read_holding_registers(0x8B, 2), "FC 03").await;
    assert_eq!(words, LMD_VM_600000);
    assert_eq!(
        (u32::from(words[1]) << 16) | u32::from(words[0]),
        600_000,
        "low word first"
    );
    for coil in [2, 1] {
        answered("FC 05", ctx.write_single_coil(coil, true), "FC 05 accepted").await;
    }
    assert_eq!(
        answered("FC 01", ctx.read_coils(0, 3), "FC 01").await,
        [true, true, true]
    );
    server.shutdown().await;
}

/// LMD through mbpoll: VM as a 32-bit integer in mbpoll's default word order, which is the LMD's (low word
/// first): 768000, then 600000 after mbpoll writes it; the three outputs read 1 0 1.
#[tokio::test]
async fn mbpoll_tcp_lmd_manual_answers() {
    skip_unless!(mbpoll_or_skip);
    let server = serve_on("lmd", false).await;
    let port = server.tcp_addr().expect("tcp addr").port();
    mbpoll_tcp_vm_768000_then_600000(port, &["-t", "4:int", "-r", "139"]).await;
    let (ok, out, err) = run_client(&mut mbpoll_tcp(
        port,
        &["-t", "0", "-r", "0", "-c", "3"],
        &[],
    ))
    .await;
    assert!(ok, "mbpoll coil read failed:\n{out}\n{err}");
    let outputs: Vec<Option<String>> = (0..3).map(|r| mbpoll_value(&out, r)).collect();
    assert_eq!(
        outputs,
        [Some("1".into()), Some("0".into()), Some("1".into())],
        "{out}"
    );
    server.shutdown().await;
}

// ---- SD2x over RTU over TCP ------------------------------------------------------------------------------

/// How a client reaches the SD2x's RTU-over-TCP endpoint.
fn sd2x_endpoint(peer: Peer, server: &ServerHandle, bridge: Option<&PtyTcpBridge>) -> Vec<String> {
    let unit = profile("sd2x").device.default_unit.to_string();
    match (peer, bridge) {
        (Peer::Libmodbus, Some(b)) => vec![
            "rtu".into(),
            b.tty.to_string_lossy().into_owned(),
            "19200".into(),
            "N".into(),
            "1".into(),
            unit,
        ],
        (Peer::Pymodbus, None) => {
            let addr = server.rtu_over_tcp_addr().expect("rtu-over-tcp addr");
            vec![
                "rtutcp".into(),
                addr.ip().to_string(),
                addr.port().to_string(),
                unit,
            ]
        }
        (p, b) => panic!("no RTU-over-TCP route for {p:?} (bridge: {})", b.is_some()),
    }
}

/// SD2x manual 6.1 then 6.3 over RTU over TCP: the two RxPDO telegrams, the 500 ms watchdog they arm runs
/// out, the status word reads 0x7038 by FC 04 and FC 03; FC 05 (not an SD2x function) gets exception 01.
async fn sd2x_rtu_over_tcp(peer: Peer, test: &str) {
    if client_command(peer, test).is_none() {
        return;
    }
    if matches!(peer, Peer::Libmodbus) && !socat_or_skip(test) {
        return;
    }
    let server = serve_on("sd2x", true).await;
    let bridge = matches!(peer, Peer::Libmodbus)
        .then(|| PtyTcpBridge::new(server.rtu_over_tcp_addr().expect("rtu-over-tcp addr")));
    let endpoint = sd2x_endpoint(peer, &server, bridge.as_ref());
    let words = |w: &[u16]| w.iter().map(u16::to_string).collect::<Vec<_>>().join(",");
    let (shutdown, enable) = (
        format!("wh:3000:{}", words(&SD2X_SHUTDOWN)),
        format!("wh:3000:{}", words(&SD2X_ENABLE)),
    );
    expect_lines(
        peer,
        test,
        &endpoint,
        &[
            (&shutdown, "ok"),
            (&enable, "ok"),
            ("wc:0:1", "exception 1"),
        ],
    )
    .await;
    if let Err(last) = wait_sd2x_status(&server, SD2X_STATUS_AFTER_61).await {
        panic!(
            "{test}: the SD2x status word did not become 0x7038 within {SD2X_WATCHDOG_BOUND:?} (last: {last:04X?})"
        );
    }
    let status = SD2X_STATUS_AFTER_61.to_string();
    expect_lines(
        peer,
        test,
        &endpoint,
        &[("ri:2000:1", &status), ("rh:2000:1", &status)],
    )
    .await;
    drop(bridge);
    server.shutdown().await;
}

#[tokio::test]
async fn libmodbus_rtu_over_tcp_sd2x_status_word_and_illegal_function() {
    sd2x_rtu_over_tcp(Peer::Libmodbus, test_name!()).await;
}

#[tokio::test]
async fn pymodbus_rtu_over_tcp_sd2x_status_word_and_illegal_function() {
    sd2x_rtu_over_tcp(Peer::Pymodbus, test_name!()).await;
}

/// SD2x over RTU over TCP through mbpoll (on a socat pty bridged to the endpoint): 6.1, the watchdog, the
/// 6.3 status word 28728 = 0x7038; FC 01 (not an SD2x function) fails with libmodbus' "Illegal function".
#[tokio::test]
async fn mbpoll_rtu_over_tcp_sd2x_status_word_and_illegal_function() {
    skip_unless!(socat_and_mbpoll_or_skip);
    let server = serve_on("sd2x", true).await;
    let bridge = PtyTcpBridge::new(server.rtu_over_tcp_addr().expect("rtu-over-tcp addr"));
    mbpoll_sd2x_61(&bridge.tty).await;
    if let Err(last) = wait_sd2x_status(&server, SD2X_STATUS_AFTER_61).await {
        panic!("the SD2x status word did not become 0x7038 (last: {last:04X?})");
    }
    let (ok, out, err) = run_client(&mut mbpoll_rtu(
        &bridge.tty,
        &["-t", "3", "-r", "2000"],
        &[],
    ))
    .await;
    assert!(ok, "mbpoll read failed:\n{out}\n{err}");
    assert_eq!(
        mbpoll_value(&out, 2000),
        Some(SD2X_STATUS_AFTER_61.to_string()),
        "{out}"
    );
    mbpoll_sd2x_illegal_function(&bridge.tty).await;
    drop(bridge);
    server.shutdown().await;
}
