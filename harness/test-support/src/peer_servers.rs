//! The peer servers of tests/peers/ (pymodbus, libmodbus) as children of a test, started with `tcp 127.0.0.1 0`.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, ExitStatus, Stdio};
use std::sync::OnceLock;

use super::{ChildGuard, STEP, line_reader, peer_file, spawn_guarded, wait_bounded};

/// Start `cmd` and wait, bounded, for its first line (`listening tcp ADDR`, `listening serial DEVICE`).
pub fn start_listening(mut cmd: Command) -> (ChildGuard, String) {
    let mut guard = spawn_guarded(&mut cmd, Stdio::piped(), Stdio::null());
    let stdout = guard.0.stdout.take().expect("stdout");
    let rx = line_reader(stdout);
    let line = rx
        .recv_timeout(STEP)
        .unwrap_or_else(|_| panic!("{cmd:?} printed no listening line within {STEP:?}"));
    assert!(
        line.starts_with("listening "),
        "unexpected first line from {cmd:?}: {line:?}"
    );
    (guard, line)
}

/// A peer server of tests/peers/ running as a child (killed on drop if a test panics first).
pub struct PeerServer {
    pub child: ChildGuard,
    pub addr: SocketAddr,
}

impl PeerServer {
    /// Start `cmd` (a server in `tcp 127.0.0.1 0` mode) and wait, bounded, for its `listening tcp ADDR` line.
    pub fn start(cmd: Command) -> Self {
        let (child, line) = start_listening(cmd);
        let addr = match line.split_whitespace().collect::<Vec<_>>().as_slice() {
            ["listening", "tcp", a] => a.parse().expect("listening address"),
            _ => panic!("unexpected first line: {line:?}"),
        };
        Self { child, addr }
    }

    pub fn pymodbus() -> Self {
        let mut c = Command::new("python3");
        c.arg(peer_file("pymodbus_server.py"))
            .args(["tcp", "127.0.0.1", "0"]);
        Self::start(c)
    }

    pub fn libmodbus() -> Self {
        let mut c = Command::new(libmodbus_server().unwrap_or_else(|e| panic!("{e}")));
        c.args(["tcp", "127.0.0.1", "0"]);
        Self::start(c)
    }

    /// bench/gateway.py in front of the RTU-over-TCP drive at `upstream`, with `args` (`--timeout MS`, ...):
    /// a Modbus/TCP-to-RTU gateway answering 0B where the drive is silent, 0A for a unit id with no path.
    pub fn gateway(upstream: SocketAddr, args: &[&str]) -> Self {
        Self::bench_script("gateway.py", &[upstream], args)
    }

    /// bench/`script` (a loopback relay) in front of `upstreams`, with `args`, ending by itself after 900 s.
    fn bench_script(script: &str, upstreams: &[SocketAddr], args: &[&str]) -> Self {
        let mut c = Command::new("python3");
        c.arg(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../bench")
                .join(script),
        )
        .args(upstreams.iter().map(ToString::to_string))
        .args(args)
        .args(["--lifetime", "900"]);
        Self::start(c)
    }

    /// bench/line.py joining the RTU-over-TCP drives at `drops` into one multi-drop line, with `args`
    /// (`--hear-replies off`, ...), served to the master over RTU over TCP.
    pub fn line(drops: &[SocketAddr], args: &[&str]) -> Self {
        Self::bench_script("line.py", drops, args)
    }

    /// bench/transactions-proxy.py in front of the Modbus/TCP drive at `upstream`: a server holding
    /// `transactions` requests at once, answering the ones after them in a batch with exception 06.
    pub fn transactions(upstream: SocketAddr, transactions: usize) -> Self {
        let n = transactions.to_string();
        Self::bench_script(
            "transactions-proxy.py",
            &[upstream],
            &["--transactions", &n],
        )
    }

    /// bench/noisy-link.py in front of the drive at `upstream`, with `args` (`--mode rtu|tcp`, `--rate R`,
    /// `--seed N`, ...): a noisy RS-485 line, or a Modbus/TCP link that drops connections.
    pub fn noisy_link(upstream: SocketAddr, args: &[&str]) -> Self {
        Self::bench_script("noisy-link.py", &[upstream], args)
    }

    /// SIGTERM by pid, then the exit status (bounded).
    pub fn terminate(mut self) -> ExitStatus {
        let pid = self.child.0.id() as libc::pid_t;
        // SAFETY: kill(2) on the pid of a child this test started and has not reaped yet.
        let rc = unsafe { libc::kill(pid, libc::SIGTERM) };
        assert_eq!(rc, 0, "kill -TERM {pid}");
        wait_bounded(&mut self.child.0, STEP, "the peer server after SIGTERM")
    }
}

/// Build tests/peers/libmodbus_server.c once per test process (renamed into place when complete).
pub fn libmodbus_server() -> Result<PathBuf, String> {
    static EXE: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    EXE.get_or_init(|| super::compile_libmodbus_peer("libmodbus_server.c", "libmodbus_server"))
        .clone()
}
