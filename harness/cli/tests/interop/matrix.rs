//! The interop matrix can fail: what `.ci/interop` relies on, shown against real processes.
//!
//! - The peer servers of tests/peers/ (pymodbus, libmodbus) bind port 0, print where they listen, serve the
//!   generic profile's map (and nothing past it) and stop on SIGTERM with exit code 0.
//! - The conformance run against the pymodbus server passes with its committed expectations file and fails
//!   (exit code 1, the case named) when one entry is taken out: a peer that changes behaviour, or an entry
//!   that goes missing, turns the matrix red.
//! - The run against `modbus-harness simulate --fault wrong-exception-code` fails (exit code 1) where the
//!   same run against the healthy simulator passes: a broken reference drive turns the matrix red.
//! - A generated run that writes leaves the pymodbus and libmodbus servers' maps as it found them, and
//!   `restore --journal` puts back a map changed everywhere, both checked by raw reads made here.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use test_support::peer_servers::PeerServer;
use test_support::*;

/// Bound on one conformance run in these tests (they select a few dozen cases).
const RUN_LIMIT: Duration = Duration::from_secs(120);

/// The repository's top directory.
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `modbus-harness run --target TARGET --profile generic --no-progress EXTRA...`, bounded: (exit code,
/// stdout, stderr).
fn harness_run(target: &str, extra: &[&str]) -> (i32, String, String) {
    harness_bounded(None, &run_args(target, "generic", extra), RUN_LIMIT)
}

/// The generic profile's map through one connection each: input register n holds n, coil 99 is the last
/// coil, coil 100 and holding register 100 are past the map (exception 02).
async fn serves_the_generic_map(addr: SocketAddr, who: &str) {
    let cases: [(&[u8], &[u8], &str); 4] = [
        (
            &[0x04, 0x00, 0x07, 0x00, 0x01],
            &[0x04, 0x02, 0x00, 0x07],
            "input register 7 = 7",
        ),
        (
            &[0x01, 0x00, 0x63, 0x00, 0x01],
            &[0x01, 0x01, 0x00],
            "coil 99 = 0",
        ),
        (
            &[0x01, 0x00, 0x64, 0x00, 0x01],
            &[0x81, 0x02],
            "coil 100: exception 02",
        ),
        (
            &[0x03, 0x00, 0x64, 0x00, 0x01],
            &[0x83, 0x02],
            "holding 100: exception 02",
        ),
    ];
    for (tid, (req, want, what)) in cases.iter().enumerate() {
        let reply = tcp_exchange(addr, &tcp_adu(tid as u16 + 1, 1, req)).await;
        assert_eq!(&reply[7..], *want, "{who}: {what}; reply {reply:02X?}");
    }
}

/// `server` serves the generic profile's map, then stops on SIGTERM with exit code 0.
async fn serves_the_generic_map_and_stops_on_sigterm(server: PeerServer, who: &str) {
    serves_the_generic_map(server.addr, who).await;
    let status = server.terminate();
    assert!(status.success(), "{who} server after SIGTERM: {status}");
}

#[tokio::test]
async fn pymodbus_server_serves_the_generic_map_and_stops_on_sigterm() {
    skip_unless!(pymodbus_or_skip);
    serves_the_generic_map_and_stops_on_sigterm(PeerServer::pymodbus(), "pymodbus").await;
}

#[tokio::test]
async fn libmodbus_server_serves_the_generic_map_and_stops_on_sigterm() {
    skip_unless!(libmodbus_or_skip);
    serves_the_generic_map_and_stops_on_sigterm(PeerServer::libmodbus(), "libmodbus").await;
}

/// Write the generic map's 100 holding registers (`regs`, 200 bytes) and 100 coils (`coils`, 13 bytes, the bits
/// past coil 99 cleared here) with raw FC 10 and FC 0F requests built here, each echoed; what was written.
async fn write_map(
    addr: SocketAddr,
    who: &str,
    regs: Vec<u8>,
    mut coils: Vec<u8>,
) -> (Vec<u8>, Vec<u8>) {
    coils[12] &= 0x0F;
    let requests = [
        ([0x10, 0, 0, 0, 100, 200], &regs),
        ([0x0F, 0, 0, 0, 100, 13], &coils),
    ];
    for (tid, (head, data)) in requests.into_iter().enumerate() {
        let pdu = [&head[..], data].concat();
        let reply = tcp_exchange(addr, &tcp_adu(tid as u16 + 1, 1, &pdu)).await;
        assert_eq!(&reply[7..], &pdu[..5], "{who}: FC {:02X} echoed", head[0]);
    }
    (regs, coils)
}

/// The generic map set to a pattern (no value the profile starts with).
async fn set_pattern(addr: SocketAddr, who: &str) -> (Vec<u8>, Vec<u8>) {
    let regs = (0..100u16)
        .flat_map(|i| (0x1000 + i * 7).to_be_bytes())
        .collect();
    let coils = (0..13)
        .map(|k| (0..8).fold(0u8, |b, j| b | u8::from((k * 8 + j) % 3 == 0) << j))
        .collect();
    write_map(addr, who, regs, coils).await
}

/// The map as read by raw FC 03 and FC 01 requests: (register bytes, coil bytes).
async fn read_map(addr: SocketAddr, who: &str) -> (Vec<u8>, Vec<u8>) {
    let mut out = Vec::new();
    for (tid, (fc, len)) in [(0x03u8, 200usize), (0x01, 13)].into_iter().enumerate() {
        let reply = tcp_exchange(addr, &tcp_adu(10 + tid as u16, 1, &[fc, 0, 0, 0, 100])).await;
        assert_eq!(
            reply[7..9],
            [fc, len as u8],
            "{who}: FC {fc:02X} of the map answered"
        );
        out.push(reply[9..].to_vec());
    }
    (out.remove(0), out.remove(0))
}

/// Leave as found against stacks nobody here wrote: the map is set to a pattern, a generated run (whose FC 10
/// and FC 0F cases, malformed ones among them, write all over it) puts back what it changed, and afterwards
/// every holding register and coil reads as set, by raw reads that share no code with the harness's restore.
/// Then every parameter of the map is changed and `restore --journal` of that run puts all of it back (the
/// 100 registers with one FC 10, the 100 coils with one FC 0F, where the server takes them), read back the
/// same way.
async fn leaves_the_map_as_found(server: PeerServer, who: &str, cases: &'static str) {
    let addr = server.addr;
    let set = set_pattern(addr, who).await;
    let target = format!("tcp://{addr}");
    let dir = TempDir::new("leave-as-found");
    let journal = dir
        .path()
        .join("journal.json")
        .to_string_lossy()
        .into_owned();
    let (t, j) = (target.clone(), journal.clone());
    let (code, out, err) = tokio::task::spawn_blocking(move || {
        harness_run(&t, &["--generated", cases, "--seed", "1", "--journal", &j])
    })
    .await
    .expect("the run's thread");
    assert!(
        code == 0 || code == 1,
        "{who}: the run ends with a verdict, not 3 (left changed) or an error:\n{out}\n{err}"
    );
    let account = err
        .lines()
        .chain(out.lines())
        .find(|l| l.contains("parameter(s) kept"))
        .unwrap_or_else(|| panic!("{who}: no leave-as-found account:\n{out}\n{err}"));
    assert!(
        account.contains("every kept parameter reads as before"),
        "{who}: {account}"
    );
    // "... kept, 50 restore write(s) in 265 request(s), ..."
    let writes: usize = account
        .split(", ")
        .find(|p| p.contains("restore write(s)"))
        .and_then(|p| p.split_whitespace().next()?.parse().ok())
        .unwrap_or(0);
    assert!(
        writes > 0,
        "{who}: the run changed something to put back: {account}"
    );
    assert_eq!(
        read_map(addr, who).await,
        set,
        "{who}: the map reads as it was set"
    );

    // Every register to 0 and every coil to the opposite of its value: all 200 parameters differ.
    write_map(addr, who, vec![0; 200], set.1.iter().map(|b| !b).collect()).await;
    let (code, out, err) = tokio::task::spawn_blocking(move || {
        harness_bounded(
            None,
            &["restore", "--journal", &journal, "--target", &target],
            RUN_LIMIT,
        )
    })
    .await
    .expect("the restore's thread");
    assert_eq!(
        code, 0,
        "{who}: restore puts everything back:\n{out}\n{err}"
    );
    assert_eq!(
        read_map(addr, who).await,
        set,
        "{who}: the map reads as set after the restore"
    );
    let status = server.terminate();
    assert!(status.success(), "{who} server after SIGTERM: {status}");
}

#[tokio::test]
async fn a_generated_run_leaves_the_pymodbus_server_as_found() {
    skip_unless!(pymodbus_or_skip);
    leaves_the_map_as_found(PeerServer::pymodbus(), "pymodbus", "400").await;
}

/// Fewer cases: the libmodbus server sleeps its response timeout (0.5 s) before most exceptions.
#[tokio::test]
async fn a_generated_run_leaves_the_libmodbus_server_as_found() {
    skip_unless!(libmodbus_or_skip);
    leaves_the_map_as_found(PeerServer::libmodbus(), "libmodbus", "80").await;
}

/// The expectations entry this test takes out, and the cases both runs select: that entry's case and the
/// cases of two other entries, which must stay tolerated in both runs.
const DROPPED: &str = "spec/app-6.5/write-coil-illegal-value";
const SELECTED: [&str; 3] = [
    DROPPED,
    "spec/app-6/quantity/*",
    "spec/app-7/unsupported-function/*",
];

/// `text` without the `[[deviation]]` block whose case is `case`.
fn without_entry(text: &str, case: &str) -> String {
    let needle = format!("case = \"{case}\"");
    let mut parts = text.split("[[deviation]]");
    let mut out = parts.next().unwrap_or_default().to_string();
    let mut dropped = 0;
    for block in parts {
        if block.contains(&needle) {
            dropped += 1;
        } else {
            out.push_str("[[deviation]]");
            out.push_str(block);
        }
    }
    assert_eq!(dropped, 1, "exactly one entry for {case}");
    out
}

/// The count the terminal summary gives for `verdict` (its line `  NON-STRICT      12`).
fn count(summary: &str, verdict: &str) -> usize {
    summary
        .lines()
        .find_map(|l| l.trim().strip_prefix(verdict))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or(0)
}

fn run_pymodbus(expect: &Path) -> (i32, String, String) {
    // A fresh server per run: the cases write to it.
    let server = PeerServer::pymodbus();
    let target = format!("tcp://{}", server.addr);
    let expect = expect.to_string_lossy().into_owned();
    let mut args = vec!["--expect", &expect];
    for c in SELECTED {
        args.extend(["--cases", c]);
    }
    let out = harness_run(&target, &args);
    let status = server.terminate();
    assert!(status.success(), "pymodbus server after SIGTERM: {status}");
    out
}

#[test]
fn a_missing_expectation_fails_the_run_against_the_pymodbus_server() {
    skip_unless!(pymodbus_or_skip);
    let full = repo().join("tests/expect/pymodbus-tcp.toml");
    let (code, out, err) = run_pymodbus(&full);
    assert_eq!(
        code, 0,
        "with the committed expectations the selected cases pass:\n{out}\n{err}"
    );
    assert!(
        count(&out, "NON-STRICT") > 0,
        "the listed deviations are NON-STRICT:\n{out}"
    );

    let dir = TempDir::new("expect");
    let partial = dir.path().join("pymodbus-tcp-minus-one.toml");
    let text = std::fs::read_to_string(&full).expect("read the expectations file");
    std::fs::write(&partial, without_entry(&text, DROPPED)).expect("write the reduced file");
    let (code, out, err) = run_pymodbus(&partial);
    assert_eq!(
        code, 1,
        "without the entry for {DROPPED} the run fails:\n{out}\n{err}"
    );
    assert!(
        out.contains(&format!("FAIL {DROPPED}")),
        "the failing case is named:\n{out}"
    );
    assert_eq!(
        out.lines().filter(|l| l.starts_with("FAIL ")).count(),
        1,
        "only that case fails:\n{out}"
    );
}

#[test]
fn a_simulator_fault_fails_the_run_where_the_healthy_simulator_passes() {
    let run = |fault: Option<&str>| {
        let sim = SimProcess::on_loopback("generic", "--listen", fault);
        let out = harness_run(&sim.tcp_url(), &["--cases", "spec/*"]);
        drop(sim);
        out
    };
    let (code, out, err) = run(None);
    assert_eq!(code, 0, "the healthy simulator passes:\n{out}\n{err}");
    let (code, out, err) = run(Some("wrong-exception-code"));
    assert_eq!(code, 1, "wrong-exception-code fails the run:\n{out}\n{err}");
    assert!(
        out.contains("FAIL spec/app-7/unsupported-function/"),
        "an exception case is named among the failures:\n{out}"
    );
}
