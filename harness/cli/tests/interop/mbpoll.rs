//! mbpoll (an independent command-line master built on libmodbus) against `modbus-harness simulate`,
//! the binary as a user runs it: RTU on a socat pty pair, and Modbus/TCP.
//!
//! mbpoll numbers references from 1 unless `-0` is given; every call here uses `-0` so `-r` is the PDU
//! address. In RTU mode it defaults to even parity: `-P none` matches the SD2x's 8N1.

use test_support::*;
use tokio::process::Command;

/// The value mbpoll printed for reference `reference` (`[2000]: \t28728`).
fn mbpoll_value(out: &str, reference: u32) -> Option<String> {
    let tag = format!("[{reference}]:");
    out.lines()
        .find_map(|l| l.trim().strip_prefix(&tag))
        .map(|v| v.split_whitespace().next().unwrap_or_default().to_string())
}

/// mbpoll in RTU mode at 19200 8N1 on `tty`; `values` (after the device, as mbpoll wants) make it write.
fn mbpoll_rtu(tty: &std::path::Path, opts: &[&str], values: &[&str]) -> Command {
    let mut c = Command::new("mbpoll");
    c.args([
        "-m", "rtu", "-a", "1", "-b", "19200", "-P", "none", "-s", "1",
    ])
    .args(["-0", "-1", "-o", "1"])
    .args(opts)
    .arg(tty)
    .args(values);
    c
}

/// mbpoll over Modbus/TCP to 127.0.0.1:`port`; `values` make it write.
fn mbpoll_tcp(port: u16, opts: &[&str], values: &[&str]) -> Command {
    let mut c = Command::new("mbpoll");
    c.args(["-m", "tcp", "-a", "1", "-p", &port.to_string()])
        .args(["-0", "-1", "-o", "1"])
        .args(opts)
        .arg("127.0.0.1")
        .args(values);
    c
}

/// SD2x over its real transport, the manual's examples in order: 6.1 writes the RxPDO twice (FC 16, the
/// golden telegrams' values), the 500 ms watchdog they armed trips, and the 6.3 read of register 2000
/// (input table) returns the manual's 0x7038 = 28728.
#[tokio::test]
async fn mbpoll_rtu_pty_sd2x_status_word() {
    let test = "mbpoll_rtu_pty_sd2x_status_word";
    if !have_socat() || !have_mbpoll() {
        skip(
            test,
            "needs socat and mbpoll (apt-get install socat mbpoll)",
        );
        return;
    }
    let pty = PtyPair::start();
    let tty = pty.a.to_string_lossy().into_owned();
    let _sim = SimProcess::start(&[
        "--profile",
        "sd2x",
        "--serial",
        &tty,
        "--baud",
        "19200",
        "--parity",
        "none",
        "--stop",
        "1",
    ]);
    for words in [SD2X_SHUTDOWN, SD2X_ENABLE] {
        let values: Vec<String> = words.iter().map(u16::to_string).collect();
        let values: Vec<&str> = values.iter().map(String::as_str).collect();
        let mut cmd = mbpoll_rtu(&pty.b, &["-t", "4", "-r", "3000"], &values);
        let (ok, out, err) = run_client(&mut cmd).await;
        assert!(ok, "mbpoll write of {words:?} failed:\n{out}\n{err}");
    }
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
    let test = "mbpoll_rtu_pty_sd2x_illegal_function";
    if !have_socat() || !have_mbpoll() {
        skip(
            test,
            "needs socat and mbpoll (apt-get install socat mbpoll)",
        );
        return;
    }
    let pty = PtyPair::start();
    let tty = pty.a.to_string_lossy().into_owned();
    let _sim = SimProcess::start(&["--profile", "sd2x", "--serial", &tty, "--parity", "none"]);
    let (ok, out, err) = run_client(&mut mbpoll_rtu(&pty.b, &["-t", "0", "-r", "0"], &[])).await;
    assert!(!ok, "FC 01 should fail on an SD2x:\n{out}");
    assert!(
        err.contains("Illegal function"),
        "expected libmodbus' 'Illegal function':\n{out}\n{err}"
    );
}

/// MDrive over Modbus/TCP: VM at 0x008B as a 32-bit value, high word first (`-B`). It reads the manual's
/// FC 03 example value 768000 (VM's default), then 600000 after mbpoll writes it (the FC 16 example).
#[tokio::test]
async fn mbpoll_tcp_mdrive_max_velocity() {
    let test = "mbpoll_tcp_mdrive_max_velocity";
    if !have_mbpoll() {
        skip(test, "mbpoll is not installed (apt-get install mbpoll)");
        return;
    }
    let sim = SimProcess::start(&["--profile", "mdrive", "--listen", "127.0.0.1:0"]);
    let port = sim.tcp.expect("tcp endpoint").port();
    let read = ["-t", "4:int", "-B", "-r", "139"];
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, &read, &[])).await;
    assert!(ok, "mbpoll read failed:\n{out}\n{err}");
    assert_eq!(mbpoll_value(&out, 139).as_deref(), Some("768000"), "{out}");
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, &read, &["600000"])).await;
    assert!(ok, "mbpoll write failed:\n{out}\n{err}");
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, &read, &[])).await;
    assert!(ok, "mbpoll read back failed:\n{out}\n{err}");
    assert_eq!(mbpoll_value(&out, 139).as_deref(), Some("600000"), "{out}");
}

/// mbpoll over TCP gets a well-formed exception from the simulator binary (MDrive lists no FC 04).
#[tokio::test]
async fn mbpoll_tcp_mdrive_illegal_function() {
    let test = "mbpoll_tcp_mdrive_illegal_function";
    if !have_mbpoll() {
        skip(test, "mbpoll is not installed (apt-get install mbpoll)");
        return;
    }
    let sim = SimProcess::start(&["--profile", "mdrive", "--listen", "127.0.0.1:0"]);
    let port = sim.tcp.expect("tcp endpoint").port();
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, &["-t", "3", "-r", "0"], &[])).await;
    assert!(!ok, "FC 04 should fail on an MDrive:\n{out}");
    assert!(err.contains("Illegal function"), "{out}\n{err}");
}
