//! mbpoll, an independent command-line master built on libmodbus, as the interop tests run it.
//!
//! mbpoll numbers references from 1 unless `-0` is given; every command here uses `-0` so `-r` is the PDU
//! address, and `-1 -o 1` (one poll, 1 s timeout). In RTU mode it defaults to even parity: `-P none` matches
//! the SD2x's 8N1.

use std::path::Path;

use tokio::process::Command;

use super::{SD2X_ENABLE, SD2X_SHUTDOWN, run_client};

/// mbpoll in RTU mode at 19200 8N1 on `tty`, slave 1; `values` (after the device, as mbpoll wants) make it
/// write.
pub fn mbpoll_rtu(tty: &Path, opts: &[&str], values: &[&str]) -> Command {
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
pub fn mbpoll_tcp(port: u16, opts: &[&str], values: &[&str]) -> Command {
    let mut c = Command::new("mbpoll");
    c.args(["-m", "tcp", "-a", "1", "-p", &port.to_string()])
        .args(["-0", "-1", "-o", "1"])
        .args(opts)
        .arg("127.0.0.1")
        .args(values);
    c
}

/// The value mbpoll printed for reference `reference` (`[2000]: \t28728`).
pub fn mbpoll_value(out: &str, reference: u32) -> Option<String> {
    let tag = format!("[{reference}]:");
    out.lines()
        .find_map(|l| l.trim().strip_prefix(&tag))
        .map(|v| v.split_whitespace().next().unwrap_or_default().to_string())
}

/// SD2x manual 6.1 through mbpoll on `tty`: the shutdown and enable-operation telegrams (FC 16 to the RxPDO,
/// 3000..3003), each of which must succeed.
pub async fn mbpoll_sd2x_61(tty: &Path) {
    for words in [SD2X_SHUTDOWN, SD2X_ENABLE] {
        let values: Vec<String> = words.iter().map(u16::to_string).collect();
        let values: Vec<&str> = values.iter().map(String::as_str).collect();
        let mut cmd = mbpoll_rtu(tty, &["-t", "4", "-r", "3000"], &values);
        let (ok, out, err) = run_client(&mut cmd).await;
        assert!(ok, "mbpoll write of {words:?} failed:\n{out}\n{err}");
    }
}

/// FC 01 (not an SD2x function) through mbpoll on `tty` fails with libmodbus' "Illegal function".
pub async fn mbpoll_sd2x_illegal_function(tty: &Path) {
    let (ok, out, err) = run_client(&mut mbpoll_rtu(tty, &["-t", "0", "-r", "0"], &[])).await;
    assert!(!ok, "FC 01 should fail on an SD2x:\n{out}");
    assert!(
        err.contains("Illegal function"),
        "expected libmodbus' 'Illegal function':\n{out}\n{err}"
    );
}

/// VM (reference 139 = 0x008B, a 32-bit register of the MDrive and the LMD) through mbpoll over Modbus/TCP to
/// 127.0.0.1:`port`, read with `read` (the type and word order): the default 768000, then 600000 after
/// mbpoll writes it.
pub async fn mbpoll_tcp_vm_768000_then_600000(port: u16, read: &[&str]) {
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, read, &[])).await;
    assert!(ok, "mbpoll read failed:\n{out}\n{err}");
    assert_eq!(mbpoll_value(&out, 139).as_deref(), Some("768000"), "{out}");
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, read, &["600000"])).await;
    assert!(ok, "mbpoll write failed:\n{out}\n{err}");
    let (ok, out, err) = run_client(&mut mbpoll_tcp(port, read, &[])).await;
    assert!(ok, "mbpoll read back failed:\n{out}\n{err}");
    assert_eq!(mbpoll_value(&out, 139).as_deref(), Some("600000"), "{out}");
}
