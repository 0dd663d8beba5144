//! Shared pieces of the modbus-harness tests: tool detection with visible skips, a socat pty pair, the
//! simulator as a child process, in-process servers, third-party peers, report fixtures and raw frame
//! helpers. Every wait is bounded.

pub mod mbpoll;
pub mod modbus_client;
pub mod peer_servers;
pub mod reports;
use std::io::{BufRead, BufReader, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use codec::rtu;
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{self, Fault, FaultSet, Station};
use engine::servers::{self, SerialConfig, ServerConfig, ServerHandle};
use engine::session::{self, Options, RunOutcome, SessionError};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

pub mod peers;

/// The `modbus-harness` binary of this build (`target/<profile>/modbus-harness`, beside the test executable's
/// `deps/` folder). Tests of the `modbus-harness` package have it built by cargo before they run.
pub fn harness_bin() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    let dir = exe
        .parent()
        .and_then(|deps| deps.parent())
        .expect("the test executable lives in target/<profile>/deps");
    dir.join(format!("modbus-harness{}", std::env::consts::EXE_SUFFIX))
}

/// `target/tmp`: scratch space shared by the test binaries of this build (what cargo names
/// `CARGO_TARGET_TMPDIR` for integration tests), created when missing.
pub fn target_tmpdir() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    let dir = exe
        .ancestors()
        .nth(3)
        .expect("the test executable lives in target/<profile>/deps")
        .join("tmp");
    let _ = std::fs::create_dir_all(&dir);
    dir
}

/// Bound on any single step of a test (connect, one request, a child process start).
pub const STEP: Duration = Duration::from_secs(5);
/// Bound on a whole child-process client run.
pub const CHILD: Duration = Duration::from_secs(30);

/// Say that a test is skipped, visibly: the test harness captures `eprintln!`, so write to fd 2 directly.
pub fn skip(test: &str, why: &str) {
    let _ = writeln!(std::io::stderr().lock(), "SKIPPED {test}: {why}");
}

/// The name of the function it stands in, without its module path: in a test, the test's own name, so that
/// a test names itself once (in its `fn`). Taken from the type name of a function item declared in place;
/// the `{{closure}}` segments of an async body (what `#[tokio::test]` makes of one) are passed over.
#[macro_export]
macro_rules! test_name {
    () => {{
        fn here() {}
        $crate::enclosing_fn_name(::std::any::type_name_of_val(&here))
    }};
}

/// The function a `path::to::the_fn::{{closure}}::here` type name ([`test_name!`]) stands in: `the_fn`.
#[doc(hidden)]
pub fn enclosing_fn_name(here: &'static str) -> &'static str {
    here.rsplit("::")
        .filter(|segment| *segment != "{{closure}}")
        .nth(1)
        .unwrap_or_else(|| panic!("no enclosing function in {here:?}"))
}

/// Return from the calling test, after a visible skip naming it (`SKIPPED <test>: <why>`), unless `check`
/// (one of the `*_or_skip` functions, given the test's name by [`test_name!`]) finds what the test needs.
#[macro_export]
macro_rules! skip_unless {
    ($check:expr) => {
        if !$check($crate::test_name!()) {
            return;
        }
    };
}

/// True when `cmd args...` runs and exits 0.
pub fn runs(cmd: &str, args: &[&str]) -> bool {
    Command::new(cmd)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

pub fn have_socat() -> bool {
    runs("socat", &["-V"])
}

pub fn have_mbpoll() -> bool {
    runs("mbpoll", &["-V"])
}

pub fn have_libmodbus() -> bool {
    runs("gcc", &["--version"]) && runs("pkg-config", &["--exists", "libmodbus"])
}

pub fn have_pymodbus() -> bool {
    runs("python3", &["-c", "import pymodbus, serial"])
}

/// `have`, or else a visible skip of `test` saying `why` (what to install).
fn have_or_skip(test: &str, have: bool, why: &str) -> bool {
    if !have {
        skip(test, why);
    }
    have
}

/// True when socat runs; otherwise says that `test` is skipped and what to install.
pub fn socat_or_skip(test: &str) -> bool {
    have_or_skip(
        test,
        have_socat(),
        "socat is not installed (apt-get install socat)",
    )
}

/// True when mbpoll runs; otherwise says that `test` is skipped and what to install.
pub fn mbpoll_or_skip(test: &str) -> bool {
    have_or_skip(
        test,
        have_mbpoll(),
        "mbpoll is not installed (apt-get install mbpoll)",
    )
}

/// True when socat and mbpoll run; otherwise says that `test` is skipped and what to install.
pub fn socat_and_mbpoll_or_skip(test: &str) -> bool {
    have_or_skip(
        test,
        have_socat() && have_mbpoll(),
        "needs socat and mbpoll (apt-get install socat mbpoll)",
    )
}

/// True when gcc and libmodbus are there; otherwise says that `test` is skipped and what to install.
pub fn libmodbus_or_skip(test: &str) -> bool {
    have_or_skip(
        test,
        have_libmodbus(),
        "needs gcc and libmodbus (apt-get install gcc pkg-config libmodbus-dev)",
    )
}

/// True when python3 has pymodbus; otherwise says that `test` is skipped and what to install.
pub fn pymodbus_or_skip(test: &str) -> bool {
    have_or_skip(
        test,
        have_pymodbus(),
        "needs python3 with pymodbus (pip install 'pymodbus[serial]')",
    )
}

/// How long one `modbus-harness` command of a test may take before it is killed (and the test fails).
pub const COMMAND_LIMIT: Duration = Duration::from_secs(120);

/// Run `modbus-harness ARGS` in `dir` (None: the test's own directory), stdin closed, bounded by
/// [`COMMAND_LIMIT`]; (exit code, stdout, stderr). A panic of the binary fails the test.
pub fn harness_in(dir: Option<&Path>, args: &[&str]) -> (i32, String, String) {
    harness_bounded(dir, args, COMMAND_LIMIT)
}

/// [`harness_in`] a command that must exit 0 (else the failure shows its stderr): its stdout.
pub fn harness_ok(dir: Option<&Path>, args: &[&str]) -> String {
    let (code, out, err) = harness_in(dir, args);
    assert_eq!(code, 0, "{err}");
    out
}

/// [`harness_in`] bounded by `limit` instead of [`COMMAND_LIMIT`].
pub fn harness_bounded(
    dir: Option<&Path>,
    args: &[&str],
    limit: Duration,
) -> (i32, String, String) {
    let out_dir = TempDir::new("harness-out");
    let (o, e) = (out_dir.path().join("out"), out_dir.path().join("err"));
    let mut cmd = Command::new(harness_bin());
    cmd.args(args)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&o).expect("out"))
        .stderr(std::fs::File::create(&e).expect("err"));
    if let Some(d) = dir {
        cmd.current_dir(d);
    }
    let mut child = cmd.spawn().expect("spawn modbus-harness");
    let status = wait_bounded(&mut child, limit, &format!("{args:?}"));
    let out = std::fs::read_to_string(&o).unwrap_or_default();
    let err = std::fs::read_to_string(&e).unwrap_or_default();
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    (status.code().unwrap_or(-1), out, err)
}

/// [`harness_in`] the test's own directory.
pub fn harness(args: &[&str]) -> (i32, String, String) {
    harness_in(None, args)
}

/// The arguments of a conformance run of `profile` against `target` without progress lines:
/// `run --target TARGET --profile PROFILE --no-progress EXTRA...`.
pub fn run_args<'a>(target: &'a str, profile: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec![
        "run",
        "--target",
        target,
        "--profile",
        profile,
        "--no-progress",
    ];
    args.extend_from_slice(extra);
    args
}

/// The arguments of a conformance run against `target` (a `sim:` one, whose profile goes with it) without
/// progress lines: `run --target TARGET --no-progress EXTRA...`.
pub fn sim_run_args<'a>(target: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["run", "--target", target, "--no-progress"];
    args.extend_from_slice(extra);
    args
}

/// [`harness`] `run --target TARGET --no-progress EXTRA... --report REPORT` ([`sim_run_args`]), the report
/// in a fresh temporary directory tagged `tag`: that directory (removed when dropped), the report's path
/// (`DIR/report`), and the run's (exit code, stdout, stderr).
pub fn sim_run_reported(
    tag: &str,
    target: &str,
    extra: &[&str],
) -> (TempDir, PathBuf, (i32, String, String)) {
    harness_reported(tag, &sim_run_args(target, extra))
}

/// [`harness`] `ARGS... --report REPORT`, the report in a fresh temporary directory tagged `tag`: that
/// directory (removed when dropped), the report's path (`DIR/report`), and the run's (exit code, stdout,
/// stderr).
pub fn harness_reported(tag: &str, args: &[&str]) -> (TempDir, PathBuf, (i32, String, String)) {
    let dir = TempDir::new(tag);
    let report = dir.path().join("report");
    let mut args = args.to_vec();
    args.extend(["--report", report.to_str().expect("utf-8 path")]);
    let ran = harness(&args);
    (dir, report, ran)
}

/// A JSON file (a report's index, a journal), parsed; panics naming the file when it cannot be read or is
/// not JSON.
pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{} is not JSON: {e}", path.display()))
}

/// A fresh temporary directory (`mbh-TAG-` and a random suffix, in the system's temporary directory), removed
/// on drop. `tempfile` is a normal dependency of this crate so that `cargo build` at the top level resolves the
/// features `cargo test` does (see [`modbus_client`]).
pub struct TempDir(tempfile::TempDir);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        Self(
            tempfile::Builder::new()
                .prefix(&format!("mbh-{tag}-"))
                .tempdir()
                .expect("create temp dir"),
        )
    }

    pub fn path(&self) -> &Path {
        self.0.path()
    }
}

/// Read a child's pipe line by line on a thread, so waits on it can time out.
pub(crate) fn line_reader(pipe: impl std::io::Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(pipe).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Kills (by pid) and reaps a child when dropped, also when the test panics.
pub struct ChildGuard(pub Child);

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start `cmd` as a child with stdin closed and the given stdout and stderr, killed on drop; panics naming
/// `cmd` when it does not start.
pub fn spawn_guarded(cmd: &mut Command, stdout: Stdio, stderr: Stdio) -> ChildGuard {
    let child = cmd
        .stdin(Stdio::null())
        .stdout(stdout)
        .stderr(stderr)
        .spawn()
        .unwrap_or_else(|e| panic!("spawn {cmd:?}: {e}"));
    ChildGuard(child)
}

/// Wait for `child` to exit, at most `limit`; kill it and panic, naming `what`, past that.
pub fn wait_bounded(child: &mut Child, limit: Duration, what: &str) -> ExitStatus {
    let give_up = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() >= give_up {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what} did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// socat run with `-d -d` between `a` and `b` (socat address specs), killed on drop; returns once it runs
/// its transfer loop (bounded, see `wait_socat_ready`), with its log so far.
fn start_socat(a: String, b: String, what: &str) -> (ChildGuard, Vec<String>) {
    let mut guard = spawn_guarded(
        Command::new("socat").args(["-d", "-d"]).arg(a).arg(b),
        Stdio::null(),
        Stdio::piped(),
    );
    let stderr = guard.0.stderr.take().expect("socat stderr");
    // socat logs "starting data transfer loop" once both addresses are set up; the reader thread keeps
    // draining its stderr afterwards so it never blocks on a full pipe.
    let log = wait_socat_ready(stderr, what);
    (guard, log)
}

/// A virtual serial line: two linked ptys made by socat. The simulator opens `a`, the client `b`.
pub struct PtyPair {
    pub a: PathBuf,
    pub b: PathBuf,
    // Field order: socat is killed before its directory goes.
    socat: ChildGuard,
    _dir: TempDir,
}

impl PtyPair {
    /// Start socat and wait (bounded) until it runs its transfer loop and both links exist.
    pub fn start() -> Self {
        let dir = TempDir::new("pty");
        let a = dir.path().join("ttyA");
        let b = dir.path().join("ttyB");
        let (socat, log) = start_socat(
            format!("pty,raw,echo=0,link={}", a.display()),
            format!("pty,raw,echo=0,link={}", b.display()),
            "socat",
        );
        assert!(a.exists() && b.exists(), "socat links missing: {log:#?}");
        Self {
            a,
            b,
            socat,
            _dir: dir,
        }
    }

    /// Take the line away (kill socat now): both ends see the ptys close.
    pub fn cut(&mut self) {
        let _ = self.socat.0.kill();
        let _ = self.socat.0.wait();
    }
}

/// bench/echo-line.py: a pty linked at `link` that gives back every byte written to it (the local echo of a
/// two-wire RS-485 adapter) and relays it to the serial device `upstream` (one end of a [`PtyPair`]), with
/// `extra` (`--corrupt-at N`, `--echo off`); returns once the link exists (bounded), killed on drop.
pub fn echo_line(upstream: &Path, link: &Path, extra: &[&str]) -> ChildGuard {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../bench/echo-line.py");
    let mut c = Command::new("python3");
    c.arg(script)
        .arg(upstream)
        .arg("--link")
        .arg(link)
        .args(extra)
        .args(["--lifetime", "600"]);
    let mut guard = spawn_guarded(&mut c, Stdio::null(), Stdio::null());
    let began = Instant::now();
    while !link.exists() {
        if let Ok(Some(status)) = guard.0.try_wait() {
            panic!("echo-line.py ended before its link existed: {status}");
        }
        assert!(
            began.elapsed() < STEP,
            "echo-line.py made no link within {STEP:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    guard
}

/// A pty whose bytes socat carries to a TCP endpoint and back: an RTU client that only speaks serial (the
/// libmodbus client, mbpoll) reaches an RTU-over-TCP endpoint through it. Killed on drop.
pub struct PtyTcpBridge {
    pub tty: PathBuf,
    // Field order: socat is killed before its directory goes.
    _socat: ChildGuard,
    _dir: TempDir,
}

impl PtyTcpBridge {
    /// Start socat and wait (bounded) until it runs its transfer loop (pty made, TCP connected).
    pub fn new(to: SocketAddr) -> Self {
        let dir = TempDir::new("bridge");
        let tty = dir.path().join("tty");
        let (socat, log) = start_socat(
            format!("pty,raw,echo=0,link={}", tty.display()),
            format!("tcp:{to}"),
            &format!("socat bridge to {to}"),
        );
        assert!(tty.exists(), "socat link missing: {log:#?}");
        Self {
            tty,
            _socat: socat,
            _dir: dir,
        }
    }
}

/// The client side of a pty at 19200 baud, 8N1.
pub fn open_pty_client(path: &Path) -> tokio_serial::SerialStream {
    use tokio_serial::SerialPortBuilderExt;
    tokio_serial::new(path.to_string_lossy(), 19_200)
        .open_native_async()
        .expect("open the client side of the pty")
}

/// The `modbus-harness simulate` binary running as a child, killed on drop.
pub struct SimProcess {
    pub child: ChildGuard,
    pub tcp: Option<SocketAddr>,
    pub rtu_over_tcp: Option<SocketAddr>,
    pub serial: Option<PathBuf>,
    pub stderr: mpsc::Receiver<String>,
}

impl SimProcess {
    /// Run `simulate ARGS` and wait (bounded) for one `listening` line per endpoint asked for.
    pub fn start(args: &[&str]) -> Self {
        let want = args
            .iter()
            .filter(|a| ["--listen", "--rtu-over-tcp", "--serial"].contains(a))
            .count();
        assert!(want > 0, "no endpoint in {args:?}");
        let mut child = spawn_guarded(
            Command::new(harness_bin()).arg("simulate").args(args),
            Stdio::piped(),
            Stdio::piped(),
        );
        let out = line_reader(child.0.stdout.take().expect("stdout"));
        let stderr = line_reader(child.0.stderr.take().expect("stderr"));
        let mut sim = Self {
            child,
            tcp: None,
            rtu_over_tcp: None,
            serial: None,
            stderr,
        };
        for _ in 0..want {
            let line = match out.recv_timeout(STEP) {
                Ok(l) => l,
                Err(_) => panic!(
                    "simulate {args:?} printed no listening line within {STEP:?}; stderr: {:?}",
                    sim.stderr.try_iter().collect::<Vec<_>>()
                ),
            };
            let parts: Vec<&str> = line.split_whitespace().collect();
            match parts.as_slice() {
                ["listening", "tcp", a] => sim.tcp = Some(a.parse().expect("tcp address")),
                ["listening", "rtu-over-tcp", a] => {
                    sim.rtu_over_tcp = Some(a.parse().expect("rtu-over-tcp address"))
                }
                ["listening", "serial", p, ..] => sim.serial = Some(PathBuf::from(p)),
                _ => panic!("unexpected line from simulate: {line:?}"),
            }
        }
        sim
    }

    /// `simulate --profile PROFILE ENDPOINT 127.0.0.1:0 [--fault FAULT]`: one loopback endpoint (`ENDPOINT`
    /// `--listen` or `--rtu-over-tcp`) on any free port, with `fault` when there is one.
    pub fn on_loopback(profile: &str, endpoint: &str, fault: Option<&str>) -> Self {
        let mut args = vec!["--profile", profile, endpoint, "127.0.0.1:0"];
        if let Some(f) = fault {
            args.extend(["--fault", f]);
        }
        Self::start(&args)
    }

    /// `simulate --profile PROFILE --serial TTY --baud 19200 --parity none EXTRA...`: the simulator on `tty`
    /// (its end of a pty pair) at 19200 8N1.
    pub fn serial_19200_8n1(tty: &Path, profile: &str, extra: &[&str]) -> Self {
        let tty = tty.to_string_lossy();
        let mut args = vec![
            "--profile",
            profile,
            "--serial",
            &tty,
            "--baud",
            "19200",
            "--parity",
            "none",
        ];
        args.extend_from_slice(extra);
        Self::start(&args)
    }

    /// `tcp://ADDRESS` of the Modbus/TCP endpoint (asked for with `--listen`).
    pub fn tcp_url(&self) -> String {
        format!("tcp://{}", self.tcp.expect("a tcp endpoint"))
    }

    /// `rtu+tcp://ADDRESS` of the RTU over TCP endpoint (asked for with `--rtu-over-tcp`).
    pub fn rtu_over_tcp_url(&self) -> String {
        format!(
            "rtu+tcp://{}",
            self.rtu_over_tcp.expect("an rtu-over-tcp endpoint")
        )
    }

    pub fn pid(&self) -> u32 {
        self.child.0.id()
    }
}

/// A profile from the embedded corpus.
pub fn profile(name: &str) -> Profile {
    let (file, text) = Corpus::Embedded
        .file("profiles", name)
        .unwrap_or_else(|e| panic!("profile {name}: {e}"));
    Profile::parse(&file, &text).unwrap_or_else(|e| panic!("profile {name}: {e}"))
}

/// A station for a corpus profile, answering as the profile's default unit.
pub fn station(name: &str, faults: &[Fault]) -> Station {
    let p = profile(name);
    let unit = p.device.default_unit;
    let faults = FaultSet::of(faults);
    Station::new(drives::build(p, faults.clone()), faults, unit)
}

/// An in-process server for a corpus profile; set the endpoints in `config` (port 0).
pub async fn serve(name: &str, faults: &[Fault], config: ServerConfig) -> ServerHandle {
    tokio::time::timeout(STEP, servers::start(station(name, faults), &config))
        .await
        .expect("server start timed out")
        .expect("server start")
}

/// Server config with Modbus/TCP and RTU over TCP on loopback, any port.
pub fn loopback_tcp_and_rtu() -> ServerConfig {
    ServerConfig {
        tcp: Some("127.0.0.1:0".parse().unwrap()),
        rtu_over_tcp: Some("127.0.0.1:0".parse().unwrap()),
        ..ServerConfig::default()
    }
}

/// The harness's conformance runs over a pty use 2400 baud: a pty has no line, and socat relays bytes in
/// pieces; at 2400 baud t3.5 is 16 ms, so a busy machine's stalls do not cut a request in two, while the
/// framing is still the real RTU silence framing.
pub const PTY_RUN_BAUD: u32 = 2400;

/// A serial endpoint at `PTY_RUN_BAUD` 8N1 on `path`.
pub fn serial_run_8n1(path: &Path) -> SerialConfig {
    SerialConfig {
        baud: PTY_RUN_BAUD,
        ..serial_19200_8n1(path)
    }
}

/// A serial endpoint at 19200 8N1 on `path`.
pub fn serial_19200_8n1(path: &Path) -> SerialConfig {
    SerialConfig {
        path: path.to_path_buf(),
        baud: 19_200,
        parity: codec::framer::Parity::None,
        stop_bits: 1,
    }
}

/// An RTU ADU: address + PDU + CRC.
pub fn rtu_adu(address: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    rtu::encode_adu(address, pdu, &mut out).expect("encode RTU ADU");
    out
}

/// A Modbus/TCP ADU.
pub fn tcp_adu(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut out = tid.to_be_bytes().to_vec();
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    out.push(unit);
    out.extend_from_slice(pdu);
    out
}

/// Read one Modbus/TCP ADU (by its MBAP length), bounded in time.
pub async fn read_tcp_adu(s: &mut TcpStream) -> Vec<u8> {
    let mut head = [0u8; 6];
    tokio::time::timeout(STEP, s.read_exact(&mut head))
        .await
        .expect("MBAP header timed out")
        .expect("read MBAP header");
    let len = u16::from_be_bytes([head[4], head[5]]) as usize;
    let mut rest = vec![0u8; len];
    tokio::time::timeout(STEP, s.read_exact(&mut rest))
        .await
        .expect("ADU body timed out")
        .expect("read ADU body");
    let mut adu = head.to_vec();
    adu.extend_from_slice(&rest);
    adu
}

/// Connect to `addr`, bounded in time.
pub async fn connect(addr: SocketAddr) -> TcpStream {
    tokio::time::timeout(STEP, TcpStream::connect(addr))
        .await
        .expect("connect timed out")
        .expect("connect")
}

/// Bound one client call in time, naming it when it times out.
pub async fn within<T>(what: &str, f: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(STEP, f)
        .await
        .unwrap_or_else(|_| panic!("{what}: no answer within {STEP:?}"))
}

/// Send one Modbus/TCP request and return the response ADU.
pub async fn tcp_exchange(addr: SocketAddr, adu: &[u8]) -> Vec<u8> {
    let mut s = connect(addr).await;
    tokio::time::timeout(STEP, s.write_all(adu))
        .await
        .expect("write timed out")
        .expect("write");
    read_tcp_adu(&mut s).await
}

/// Read from `r` until `n` bytes have arrived, bounded in time.
pub async fn read_n<R: tokio::io::AsyncRead + Unpin>(r: &mut R, n: usize) -> Vec<u8> {
    let mut buf = vec![0u8; n];
    tokio::time::timeout(STEP, r.read_exact(&mut buf))
        .await
        .unwrap_or_else(|_| panic!("no {n}-byte reply within {STEP:?}"))
        .expect("read reply");
    buf
}

/// Run a client child process to completion, bounded; returns (exit ok, stdout, stderr).
pub async fn run_client(cmd: &mut tokio::process::Command) -> (bool, String, String) {
    cmd.stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    let child = cmd.spawn().expect("spawn client");
    let out = tokio::time::timeout(CHILD, child.wait_with_output())
        .await
        .unwrap_or_else(|_| panic!("client {cmd:?} did not finish within {CHILD:?}"))
        .expect("client output");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The path of a file under the repository's tests/peers/.
pub fn peer_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/peers")
        .join(name)
}

/// The registers of a profile that a run may write and must put back (the kept parameters): read/write
/// holding registers that neither move a motor nor destroy anything.
pub fn kept_registers(p: &Profile) -> impl Iterator<Item = &drives::profile::Register> {
    use drives::profile::{Access, Table};
    p.registers.iter().map(|r| r.get_ref()).filter(|r| {
        r.access == Access::Rw && r.table != Table::Input && !r.motion && !r.destructive
    })
}

/// A writable 16-bit holding register of a profile with a value in its range (not its default) to write,
/// and a writable coil: what a read/write round trip can use without moving a motor.
pub fn rw_holding_and_coil(p: &Profile) -> (Option<(u16, u16)>, Option<u16>) {
    use drives::profile::Access;
    let reg = kept_registers(p).find(|r| r.width == 1).map(|r| {
        let (lo, hi) = r.range();
        let mut v = 0x1234i64.clamp(lo, hi);
        if Some(v) == r.default {
            v = if v < hi { v + 1 } else { v - 1 };
        }
        (r.address, v as u16)
    });
    let coil = p
        .coils
        .iter()
        .map(|c| c.get_ref())
        .find(|c| c.access == Access::Rw && !c.motion)
        .map(|c| c.address);
    (reg, coil)
}

/// Read up to `n` bytes: stops at `n`, after 300 ms without a byte once something arrived, or after
/// `STEP` of nothing. Returns what arrived, so a wrong reply shows its bytes instead of a timeout.
pub async fn read_upto<R: tokio::io::AsyncRead + Unpin>(r: &mut R, n: usize) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while got.len() < n {
        let wait = if got.is_empty() {
            STEP
        } else {
            Duration::from_millis(300)
        };
        match tokio::time::timeout(wait, r.read(&mut buf)).await {
            Ok(Ok(0)) | Err(_) => break,
            Ok(Ok(k)) => got.extend_from_slice(&buf[..k]),
            Ok(Err(e)) => panic!("read failed: {e}"),
        }
    }
    got
}

/// SD2x manual 6.1 "shutdown" (golden sd2x/6.1/shutdown): RxPDO 3000..3003 = control word 0x0006, target
/// speed 1000 (100 Hz), torque limit 100 (10 A), watchdog 500 ms.
pub const SD2X_SHUTDOWN: [u16; 4] = [0x0006, 1000, 100, 500];
/// SD2x manual 6.1 "enable operation" (golden sd2x/6.1/enable-operation): control word 0x000F.
pub const SD2X_ENABLE: [u16; 4] = [0x000F, 1000, 100, 500];
/// The status word the manual's 6.3 read returns (golden sd2x/6.3/status-read/response): a fault state,
/// which the model reaches after the 6.1 telegrams stop and their 500 ms watchdog trips.
pub const SD2X_STATUS_AFTER_61: u16 = 0x7038;
/// Bound on reaching that state: the watchdog (500 ms) plus the fault reaction's ramp down, with margin.
pub const SD2X_WATCHDOG_BOUND: Duration = Duration::from_secs(5);
/// How often a test looks at the status word while waiting for the watchdog.
pub const STATUS_POLL: Duration = Duration::from_millis(50);

/// The SD2x status word (register 2000) as the in-process station answers it now.
pub fn sd2x_status_in_process(server: &ServerHandle) -> Option<u16> {
    let shared = server.station();
    let req = tcp_adu(1, 1, &[0x04, 0x07, 0xD0, 0x00, 0x01]);
    let reply = shared.lock().tcp_adu(shared.now(), &req)?;
    // MBAP (7) + FC 04 + byte count 2 + the word.
    (reply.bytes.len() == 11 && reply.bytes[7] == 0x04)
        .then(|| u16::from_be_bytes([reply.bytes[9], reply.bytes[10]]))
}

/// Wait (bounded) until the in-process SD2x shows `want`; the last status seen otherwise.
pub async fn wait_sd2x_status(server: &ServerHandle, want: u16) -> Result<(), Option<u16>> {
    let give_up = tokio::time::Instant::now() + SD2X_WATCHDOG_BOUND;
    loop {
        let now = sd2x_status_in_process(server);
        if now == Some(want) {
            return Ok(());
        }
        if tokio::time::Instant::now() >= give_up {
            return Err(now);
        }
        tokio::time::sleep(STATUS_POLL).await;
    }
}

/// Compile a libmodbus peer of tests/peers/ (`source`) into cargo's test scratch directory as `exe_name`.
/// Built under a name of this process and renamed into place: test processes running at once never see a
/// half-written file. `Err` says what is missing or failed.
pub fn compile_libmodbus_peer(source: &str, exe_name: &str) -> Result<PathBuf, String> {
    compile_libmodbus(&peer_file(source), exe_name)
}

/// Build the C file `source` against libmodbus (gcc, `pkg-config --cflags --libs libmodbus`, warnings as
/// errors) into the target's scratch directory as `exe_name`.
pub fn compile_libmodbus(source: &Path, exe_name: &str) -> Result<PathBuf, String> {
    let flags = Command::new("pkg-config")
        .args(["--cflags", "--libs", "libmodbus"])
        .output()
        .map_err(|e| format!("pkg-config: {e}"))?;
    if !flags.status.success() {
        return Err("pkg-config does not know libmodbus".into());
    }
    let flags = String::from_utf8_lossy(&flags.stdout).into_owned();
    let dir = target_tmpdir();
    let dir = dir.as_path();
    let exe = dir.join(exe_name);
    let tmp = dir.join(format!("{exe_name}.{}", std::process::id()));
    let out = Command::new("gcc")
        .args(["-O2", "-Wall", "-Wextra", "-Werror"])
        .arg(source)
        .arg("-o")
        .arg(&tmp)
        .args(flags.split_whitespace())
        .output()
        .map_err(|e| format!("gcc: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "gcc {} failed:\n{}",
            source.display(),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    std::fs::rename(&tmp, &exe).map_err(|e| format!("rename {}: {e}", tmp.display()))?;
    Ok(exe)
}

/// The npm packages of the Node.js program in `dir` (its `package.json` and `package-lock.json`), installed
/// with `npm ci` into the target's scratch directory as `name` (the source tree gets no `node_modules`), once:
/// again only when the lock file changed. Returns the `node_modules` folder, for `NODE_PATH`. Made under a
/// name of this process and renamed into place, so test processes running at once never see half of it.
/// `Err` says what is missing or failed (no npm, no registry).
pub fn npm_modules(dir: &Path, name: &str) -> Result<PathBuf, String> {
    let lock = std::fs::read(dir.join("package-lock.json"))
        .map_err(|e| format!("{}: package-lock.json: {e}", dir.display()))?;
    let root = target_tmpdir().join(format!("npm-{name}"));
    let modules = root.join("node_modules");
    if std::fs::read(root.join("package-lock.json")).is_ok_and(|l| l == lock) && modules.is_dir() {
        return Ok(modules);
    }
    let tmp = target_tmpdir().join(format!("npm-{name}.{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| format!("{}: {e}", tmp.display()))?;
    for f in ["package.json", "package-lock.json"] {
        std::fs::copy(dir.join(f), tmp.join(f)).map_err(|e| format!("{f}: {e}"))?;
    }
    let mut child = Command::new("npm")
        .args(["ci", "--no-audit", "--no-fund", "--loglevel=error"])
        .current_dir(&tmp)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| {
            format!(
                "npm: {e} (Node.js and npm are needed for {})",
                dir.display()
            )
        })?;
    // Bounded: a registry that does not answer ends the install after 5 minutes.
    let until = Instant::now() + Duration::from_secs(300);
    let status = loop {
        if let Some(st) = child.try_wait().map_err(|e| format!("npm: {e}"))? {
            break st;
        }
        if Instant::now() > until {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("npm ci in {} took over 5 minutes", tmp.display()));
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    if !status.success() {
        let mut err = String::new();
        if let Some(mut e) = child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut e, &mut err);
        }
        return Err(format!("npm ci for {} failed: {err}", dir.display()));
    }
    let _ = std::fs::remove_dir_all(&root);
    if let Err(e) = std::fs::rename(&tmp, &root) {
        // Another test process put its copy in place first.
        let _ = std::fs::remove_dir_all(&tmp);
        if !(std::fs::read(root.join("package-lock.json")).is_ok_and(|l| l == lock)
            && modules.is_dir())
        {
            return Err(format!("rename {}: {e}", tmp.display()));
        }
    }
    Ok(modules)
}

/// Drain socat's log (stderr, run with `-d -d`) on a thread so it never blocks on a full pipe, and wait,
/// bounded by `STEP`, until it logs "starting data transfer loop" (ptys and links made, peers connected).
/// Returns the log so far; panics with it, naming `what`, when socat does not get there in time.
pub fn wait_socat_ready(stderr: impl std::io::Read + Send + 'static, what: &str) -> Vec<String> {
    let lines = line_reader(stderr);
    let mut log = Vec::new();
    loop {
        match lines.recv_timeout(STEP) {
            Ok(l) => {
                let ready = l.contains("starting data transfer loop");
                log.push(l);
                if ready {
                    return log;
                }
            }
            Err(_) => panic!("{what} did not start within {STEP:?}: {log:#?}"),
        }
    }
}

/// Panics with `what`, preceded by how many and followed by one a line, unless `items` is empty: a check
/// over a whole corpus or catalog that lists everything it found wrong.
pub fn assert_none(items: &[String], what: &str) {
    assert!(
        items.is_empty(),
        "{} {what}:\n{}",
        items.len(),
        items.join("\n")
    );
}

/// A conformance run with no log, no interruption and no progress reports.
pub fn run_quietly(o: &Options) -> Result<RunOutcome, SessionError> {
    session::run(
        o,
        &mut std::io::sink(),
        &std::sync::atomic::AtomicBool::new(false),
        &mut |_, _, _, _| {},
    )
}

/// `run_quietly`, panicking with the target named when the run fails to run.
pub fn run_ok(o: &Options) -> RunOutcome {
    run_quietly(o).unwrap_or_else(|e| panic!("{}: {e}", o.target))
}

/// The FAILs of a run, each as its case id and findings.
pub fn failures_of(out: &RunOutcome) -> Vec<String> {
    out.failures
        .iter()
        .map(|f| format!("{}: {:?}", f.id, f.findings().collect::<Vec<_>>()))
        .collect()
}

/// The bytes one connection's client sent, shared with its pump thread.
type ClientLog = std::sync::Arc<std::sync::Mutex<Vec<u8>>>;

/// A Modbus/TCP proxy on 127.0.0.1 (port 0) in front of `upstream` that keeps every byte its clients sent,
/// connection by connection: what a drive behind it received, for tests that assert what went on the wire.
/// Its threads end when the connections close; the listener ends on drop.
pub struct RecordingProxy {
    pub addr: SocketAddr,
    streams: std::sync::Arc<std::sync::Mutex<Vec<ClientLog>>>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl RecordingProxy {
    /// Listen on 127.0.0.1:0 and forward each connection to `upstream`.
    pub fn start(upstream: SocketAddr) -> Self {
        use std::net::{Shutdown, TcpListener, TcpStream};
        use std::sync::atomic::AtomicBool;
        use std::sync::{Arc, Mutex};
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind proxy");
        let addr = listener.local_addr().expect("proxy address");
        let streams: Arc<Mutex<Vec<ClientLog>>> = Arc::default();
        let stop = Arc::new(AtomicBool::new(false));
        let (s, st) = (streams.clone(), stop.clone());
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                if st.load(Ordering::SeqCst) {
                    break;
                }
                let Ok(client) = conn else { continue };
                let Ok(server) = TcpStream::connect_timeout(&upstream, STEP) else {
                    continue;
                };
                let _ = client.set_nodelay(true);
                let _ = server.set_nodelay(true);
                let log: ClientLog = Arc::default();
                s.lock().expect("streams").push(log.clone());
                let pump =
                    |mut from: TcpStream, mut to: TcpStream, log: Option<Arc<Mutex<Vec<u8>>>>| {
                        std::thread::spawn(move || {
                            let mut buf = [0u8; 4096];
                            loop {
                                match std::io::Read::read(&mut from, &mut buf) {
                                    Ok(0) | Err(_) => break,
                                    Ok(n) => {
                                        if let Some(l) = &log {
                                            l.lock().expect("log").extend_from_slice(&buf[..n]);
                                        }
                                        if to.write_all(&buf[..n]).is_err() {
                                            break;
                                        }
                                    }
                                }
                            }
                            let _ = to.shutdown(Shutdown::Both);
                            let _ = from.shutdown(Shutdown::Both);
                        });
                    };
                let (c2, s2) = (
                    client.try_clone().expect("clone"),
                    server.try_clone().expect("clone"),
                );
                pump(client, server, Some(log));
                pump(s2, c2, None);
            }
        });
        Self {
            addr,
            streams,
            stop,
        }
    }

    /// The request PDUs the clients sent, split by each connection's MBAP length fields as a server reads
    /// them (a frame cut short at the end of a connection is kept as far as it went).
    pub fn request_pdus(&self) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        for s in self.streams.lock().expect("streams").iter() {
            let bytes = s.lock().expect("log").clone();
            let mut at = 0;
            while at + 7 <= bytes.len() {
                let len = usize::from(u16::from_be_bytes([bytes[at + 4], bytes[at + 5]]));
                let end = (at + 6 + len.max(1)).min(bytes.len());
                out.push(bytes[at + 7..end.max(at + 7)].to_vec());
                at = end.max(at + 7);
            }
        }
        out
    }

    /// How many bytes the clients sent in all.
    pub fn bytes_sent(&self) -> usize {
        self.streams
            .lock()
            .expect("streams")
            .iter()
            .map(|s| s.lock().expect("log").len())
            .sum()
    }
}

impl Drop for RecordingProxy {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop so that it sees the flag.
        let _ = std::net::TcpStream::connect_timeout(&self.addr, Duration::from_millis(200));
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn test_name_is_the_enclosing_test_fn() {
        assert_eq!(test_name!(), "test_name_is_the_enclosing_test_fn");
    }

    #[tokio::test]
    async fn test_name_passes_over_the_async_body_of_a_tokio_test() {
        assert_eq!(
            test_name!(),
            "test_name_passes_over_the_async_body_of_a_tokio_test"
        );
    }
}
