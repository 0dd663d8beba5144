//! mbpoll (an independent command-line master built on libmodbus) against `modbus-harness simulate`,
//! the binary as a user runs it: RTU on a socat pty pair, and Modbus/TCP. How mbpoll is called:
//! test_support::mbpoll.

use test_support::mbpoll::*;
use test_support::*;

/// A `simulate --profile mdrive` process on loopback Modbus/TCP (port 0), and the port it listens on.
fn mdrive_over_tcp() -> (SimProcess, u16) {
    let sim = SimProcess::on_loopback("mdrive", "--listen", None);
    let port = sim.tcp.expect("tcp endpoint").port();
    (sim, port)
}

/// SD2x over its real transport, the manual's examples in order: 6.1 writes the RxPDO twice (FC 16, the
/// golden telegrams' values), the 500 ms watchdog they armed trips, and the 6.3 read of register 2000
/// (input table) returns the manual's 0x7038 = 28728.
#[tokio::test]
async fn mbpoll_rtu_pty_sd2x_status_word() {
    skip_unless!(socat_and_mbpoll_or_skip);
    let pty = PtyPair::start();
    let _sim = SimProcess::serial_19200_8n1(&pty.a, "sd2x", &["--stop", "1"]);
    mbpoll_sd2x_61(&pty.b).await;
    // The watchdog runs on the drive's clock: read until the status shows, bounded.
    let give_up = tokio::time::Instant::now() + SD2X_WATCHDOG_BOUND;
    let want = SD2X_STATUS_AFTER_61.to_string();
    let mut last;
    loop {
        let (ok, out, err) =
            run_client(&mut mbpoll_rtu(&pty.b, &["-t", "3", "-r", "2000"], &[])).await;
        assert!(ok, "mbpoll read failed:\n{out}\n{err}");
        last = mbpoll_value(&out, 2000);
        if last.as_deref() == Some(want.as_str()) || tokio::time::Instant::now() >= give_up {
            break;
        }
        tokio::time::sleep(STATUS_POLL).await;
    }
    assert_eq!(
        last,
        Some(want),
        "status word 0x7038 after 6.1 and the watchdog"
    );
}

/// An unsupported function code comes back as exception 01 through mbpoll (SD2x has no FC 01); the
/// station answers this itself, whatever the model.
#[tokio::test]
async fn mbpoll_rtu_pty_sd2x_illegal_function() {
    skip_unless!(socat_and_mbpoll_or_skip);
    let pty = PtyPair::start();
    let tty = pty.a.to_string_lossy().into_owned();
    let _sim = SimProcess::start(&["--profile", "sd2x", "--serial", &tty, "--parity", "none"]);
    mbpoll_sd2x_illegal_function(&pty.b).await;
}

/// MDrive over Modbus/TCP: VM at 0x008B as a 32-bit value, high word first (`-B`). It reads the manual's
/// FC 03 example value 768000 (VM's default), then 600000 after mbpoll writes it (the FC 16 example).
#[tokio::test]
async fn mbpoll_tcp_mdrive_max_velocity() {
    skip_unless!(mbpoll_or_skip);
    let (_sim, port) = mdrive_over_tcp();
    mbpoll_tcp_vm_768000_then_600000(port, &["-t", "4:int", "-B", "-r", "139"]).await;
}

/// mbpoll over TCP gets a well-formed exception from the simulator binary (MDrive lists no FC 04).
#[tokio::test]
async fn mbpoll_tcp_mdrive_illegal_function() {
    skip_unless!(mbpoll_or_skip);
    let (_sim, port) = mdrive_over_tcp();
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, &["-t", "3", "-r", "0"], &[])).await;
    assert!(!ok, "FC 04 should fail on an MDrive:\n{out}");
    assert!(err.contains("Illegal function"), "{out}\n{err}");
}
