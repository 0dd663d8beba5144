//! Benchmark drivers (BENCHMARKS.md, bench/run.sh): the harness's own request paths, timed, shared by the
//! `wire` and `inproc` benches (`mod support;`). Not part of the engine library.
//!
//! Every workload is the one of issue 8: FC 03 reads of 2 registers at address 0, unit 1, one connection.
//! Results print as one line in the format the C and Python peers use, so bench/run.sh reads all of them
//! alike:
//!
//! `RESULT requests=N seconds=S rps=R p50_us=P p99_us=Q`

use std::fmt;
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use codec::{Direction, Framing, Request, Response, rtu, tcp};
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{self, Choices, FaultSet, Station, TcpConn};
use engine::expect::Expectations;
use engine::reports::{Reports, RunInfo, Tally, Transport};
use engine::runner::{RunConfig, Runner, skip_reason};
use engine::session;
use engine::targets::net::TcpTarget;
use engine::targets::serial::SerialTarget;
use engine::targets::sim::SimTarget;
use engine::targets::{Received, Target, TargetError};
use engine::{Case, Compare, Level, Outgoing, Step, Verdict};

/// Requests made before timing starts (connection set-up, caches, the peer's first allocations).
pub const WARMUP: usize = 200;

/// How long one answer may take before the benchmark gives up.
const TIMEOUT: Duration = Duration::from_secs(1);

/// The unit id / slave address every benchmark addresses.
pub const UNIT: u8 = 1;

/// Throughput and latency of one timed loop.
#[derive(Clone, Debug, PartialEq)]
pub struct Stats {
    pub requests: u64,
    pub seconds: f64,
    /// Per-request latency percentiles in microseconds (0 when not measured, e.g. pipelined).
    pub p50_us: f64,
    pub p99_us: f64,
}

impl Stats {
    /// Requests per second.
    pub fn rps(&self) -> f64 {
        if self.seconds > 0.0 {
            self.requests as f64 / self.seconds
        } else {
            0.0
        }
    }

    fn from_latencies(mut lat: Vec<u32>, seconds: f64) -> Self {
        lat.sort_unstable();
        let pct = |p: usize| {
            lat.get(lat.len().saturating_sub(1) * p / 100)
                .map_or(0.0, |&ns| f64::from(ns) / 1e3)
        };
        Self {
            requests: lat.len() as u64,
            seconds,
            p50_us: pct(50),
            p99_us: pct(99),
        }
    }
}

impl fmt::Display for Stats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "RESULT requests={} seconds={:.3} rps={:.0} p50_us={:.1} p99_us={:.1}",
            self.requests,
            self.seconds,
            self.rps(),
            self.p50_us,
            self.p99_us
        )
    }
}

/// Why a benchmark stopped.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Target(#[from] TargetError),
    #[error("{0}")]
    Other(String),
}

fn other(s: impl Into<String>) -> BenchError {
    BenchError::Other(s.into())
}

/// The request PDU: FC 03, address 0, 2 registers.
pub fn read_pdu() -> Vec<u8> {
    Request::ReadHoldingRegisters {
        address: 0,
        quantity: 2,
    }
    .to_bytes()
    .unwrap_or_default()
}

/// The request framed for `framing` (the transaction id is patched per request on TCP).
fn framed(framing: Framing) -> Vec<u8> {
    let pdu = read_pdu();
    let mut out = Vec::with_capacity(16);
    match framing {
        Framing::Tcp => tcp::encode_adu(0, UNIT, &pdu, &mut out),
        _ => rtu::encode_adu(UNIT, &pdu, &mut out),
    }
    .unwrap_or_default();
    out
}

/// A normal FC 03 answer of 2 registers (9 bytes of header on TCP + 4 data bytes; RTU 3 + 4 + 2 CRC).
fn check_answer(framing: Framing, got: Received, tid: Option<u16>) -> Result<(), BenchError> {
    let Received::Frame { bytes, .. } = got else {
        return Err(other(format!("no answer: {got:?}")));
    };
    let ok = match framing {
        Framing::Tcp => {
            bytes.len() == 13
                && bytes[7] == 0x03
                && tid.is_none_or(|t| bytes[..2] == t.to_be_bytes())
        }
        _ => bytes.len() == 9 && bytes[1] == 0x03,
    };
    if ok {
        Ok(())
    } else {
        Err(other(format!("unexpected answer {bytes:02X?}")))
    }
}

/// Connect the raw engine's target: `tcp HOST:PORT` or `rtu DEVICE BAUD` (8N1).
pub fn connect(kind: &str, addr: &str, baud: Option<u32>) -> Result<Box<dyn Target>, BenchError> {
    match kind {
        "tcp" => {
            let (host, port) = addr
                .rsplit_once(':')
                .and_then(|(h, p)| Some((h, p.parse::<u16>().ok()?)))
                .ok_or_else(|| other(format!("bad address {addr}")))?;
            Ok(Box::new(TcpTarget::connect(
                host,
                port,
                Duration::from_secs(3),
                false,
            )?))
        }
        "rtu" => {
            let format = codec::CharFormat {
                parity: codec::Parity::None,
                stop_bits: 1,
            };
            Ok(Box::new(SerialTarget::open(
                addr,
                baud.unwrap_or(115_200),
                format,
            )?))
        }
        _ => Err(other(format!("unknown transport {kind} (tcp or rtu)"))),
    }
}

/// The raw engine: the target's send and receive (framing, frame cutting, deadlines), one request at a
/// time, as fast as the peer answers. No oracle, no reports.
pub fn raw(target: &mut dyn Target, secs: f64) -> Result<Stats, BenchError> {
    let framing = target.framing();
    let mut frame = framed(framing);
    let mut tid: u16 = 0;
    let mut one = |target: &mut dyn Target| -> Result<(), BenchError> {
        tid = tid.wrapping_add(1);
        if framing == Framing::Tcp {
            frame[..2].copy_from_slice(&tid.to_be_bytes());
        }
        target.send(&frame)?;
        let got = target.recv(TIMEOUT)?;
        check_answer(framing, got, (framing == Framing::Tcp).then_some(tid))
    };
    for _ in 0..WARMUP {
        one(target)?;
    }
    let mut lat = Vec::with_capacity(1 << 20);
    let start = Instant::now();
    let end = start + Duration::from_secs_f64(secs);
    let mut t = start;
    while t < end {
        one(target)?;
        let t2 = Instant::now();
        lat.push((t2 - t).as_nanos().min(u128::from(u32::MAX)) as u32);
        t = t2;
    }
    Ok(Stats::from_latencies(lat, (t - start).as_secs_f64()))
}

/// The one-exchange case the full path runs: the FC 03 read, judged by structure against the reference.
pub fn read_case() -> Case {
    Case {
        id: "bench/fc03-read-2".into(),
        title: "FC 03 read of 2 registers".into(),
        reference: "bench".into(),
        requirement: "the drive answers the read".into(),
        level: Level::Must,
        tags: vec![],
        steps: vec![Step::Exchange {
            send: Outgoing::Pdu(read_pdu()),
            compare: Compare::Structure,
            capture: None,
            note: "read".into(),
        }],
        requirements: Vec::new(),
        freedoms: Vec::new(),
    }
}

/// The generic profile (the one bench/ servers are shaped like).
pub fn generic_profile() -> Result<Profile, BenchError> {
    Corpus::Embedded
        .profile("generic")
        .map_err(|e| other(e.to_string()))
}

fn runner_for(target: Box<dyn Target>, profile: &Profile) -> Runner {
    let shadow = SimTarget::reference(profile, UNIT, Choices::reference(), target.as_ref());
    let cfg = RunConfig {
        unit: UNIT,
        timing: engine::runner::Timing {
            timeout: TIMEOUT,
            silence: Duration::from_millis(300),
            sentinel: true,
            busy_wait: engine::runner::BUSY_WITHIN,
            link_retries: 6,
        },
        safety: Default::default(),
        is_sim: false,
    };
    Runner::new(
        target,
        shadow,
        profile.clone(),
        cfg,
        Expectations::default(),
    )
}

/// The full per-case path of a run: `Runner::run_case` with the reference drive in lockstep (the oracle
/// frames, answers and judges every exchange), one case of one exchange at a time. A FAIL stops the
/// benchmark; other verdicts are the peer's (a libmodbus RTU server answers inside t3.5: NON-STRICT).
pub fn runner(target: Box<dyn Target>, profile: &Profile, secs: f64) -> Result<Stats, BenchError> {
    let mut runner = runner_for(target, profile);
    let case = read_case();
    let one = |runner: &mut Runner| -> Result<(), BenchError> {
        let r = runner.run_case(&case)?;
        if matches!(r.verdict, Verdict::Fail | Verdict::Unimplemented) {
            Err(other(format!("the read failed: {r:?}")))
        } else {
            Ok(())
        }
    };
    for _ in 0..WARMUP {
        one(&mut runner)?;
    }
    let mut lat = Vec::with_capacity(1 << 20);
    let start = Instant::now();
    let end = start + Duration::from_secs_f64(secs);
    let mut t = start;
    while t < end {
        one(&mut runner)?;
        let t2 = Instant::now();
        lat.push((t2 - t).as_nanos().min(u128::from(u32::MAX)) as u32);
        t = t2;
    }
    Ok(Stats::from_latencies(lat, (t - start).as_secs_f64()))
}

/// Pipelining: keep `k` requests in flight on one Modbus/TCP connection for `secs`, each answer checked
/// against its transaction id. The first `k` go out in one write; then, after each read, every answer
/// already buffered is taken (`recv` with a zero timeout makes no system call) and as many new requests go
/// out together in one write, so the window is full again at every write.
pub fn pipelined(target: &mut dyn Target, k: usize, secs: f64) -> Result<Stats, BenchError> {
    if target.framing() != Framing::Tcp || k == 0 {
        return Err(other("pipelining needs Modbus/TCP and k >= 1"));
    }
    let one = framed(Framing::Tcp);
    let mut sent: u16 = 0;
    let mut next = |out: &mut Vec<u8>| {
        sent = sent.wrapping_add(1);
        let at = out.len();
        out.extend_from_slice(&one);
        out[at..at + 2].copy_from_slice(&sent.to_be_bytes());
    };
    let mut batch = Vec::with_capacity(one.len() * k);
    for _ in 0..k {
        next(&mut batch);
    }
    target.send(&batch)?;
    let mut expect: u16 = 0;
    let mut answered = 0u64;
    let mut counted_from = None;
    let mut start = Instant::now();
    let mut end = start;
    loop {
        let mut got = target.recv(TIMEOUT)?;
        let mut n = 0;
        loop {
            expect = expect.wrapping_add(1);
            check_answer(Framing::Tcp, got, Some(expect))?;
            n += 1;
            got = target.recv(Duration::ZERO)?;
            if !matches!(got, Received::Frame { .. }) {
                break;
            }
        }
        answered += n as u64;
        if counted_from.is_none() && answered as usize >= WARMUP {
            counted_from = Some(answered);
            start = Instant::now();
            end = start + Duration::from_secs_f64(secs);
        } else if counted_from.is_some() && Instant::now() >= end {
            break;
        }
        batch.clear();
        for _ in 0..n {
            next(&mut batch);
        }
        target.send(&batch)?;
    }
    let seconds = start.elapsed().as_secs_f64();
    // Take the answers still in flight so the server sees a clean close.
    let mut left = usize::from(sent.wrapping_sub(expect));
    while left > 0 {
        expect = expect.wrapping_add(1);
        check_answer(Framing::Tcp, target.recv(TIMEOUT)?, Some(expect))?;
        left -= 1;
    }
    Ok(Stats {
        requests: answered - counted_from.unwrap_or(answered),
        seconds,
        p50_us: 0.0,
        p99_us: 0.0,
    })
}

/// One in-process figure: nanoseconds per operation.
#[derive(Clone, Debug)]
pub struct NsPer {
    pub name: &'static str,
    pub iterations: u64,
    pub ns: f64,
}

impl fmt::Display for NsPer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "INPROC {} ns={:.1} per_s={:.0} iterations={}",
            self.name,
            self.ns,
            1e9 / self.ns.max(1e-9),
            self.iterations
        )
    }
}

/// Run `f` repeatedly for about `secs` and return ns per call.
fn time_per(name: &'static str, secs: f64, mut f: impl FnMut()) -> NsPer {
    for _ in 0..1000 {
        f();
    }
    let start = Instant::now();
    let budget = Duration::from_secs_f64(secs);
    let mut n = 0u64;
    while start.elapsed() < budget {
        for _ in 0..1000 {
            f();
        }
        n += 1000;
    }
    NsPer {
        name,
        iterations: n,
        ns: start.elapsed().as_nanos() as f64 / n as f64,
    }
}

/// The codec and the drive model without sockets: encode+decode of the FC 03 request and answer (typed PDU
/// to ADU bytes and back, TCP and RTU), the station answering request bytes, and the model answering a
/// typed request.
pub fn in_process(secs: f64) -> Result<Vec<NsPer>, BenchError> {
    let req = Request::ReadHoldingRegisters {
        address: 0,
        quantity: 2,
    };
    let resp = Response::ReadHoldingRegisters {
        values: vec![0x1234, 0x5678],
    };
    let mut out = Vec::new();
    out.push(time_per("codec-tcp-request-encode-decode", secs, || {
        let pdu = black_box(&req).to_bytes().unwrap_or_default();
        let mut adu = Vec::with_capacity(16);
        let _ = tcp::encode_adu(1, UNIT, &pdu, &mut adu);
        black_box(tcp::decode(&adu, Direction::Request).is_ok());
    }));
    out.push(time_per("codec-tcp-response-encode-decode", secs, || {
        let pdu = black_box(&resp).to_bytes().unwrap_or_default();
        let mut adu = Vec::with_capacity(16);
        let _ = tcp::encode_adu(1, UNIT, &pdu, &mut adu);
        black_box(tcp::decode(&adu, Direction::Response).is_ok());
    }));
    out.push(time_per("codec-rtu-request-encode-decode", secs, || {
        let pdu = black_box(&req).to_bytes().unwrap_or_default();
        let mut adu = Vec::with_capacity(16);
        let _ = rtu::encode_adu(UNIT, &pdu, &mut adu);
        black_box(rtu::decode(&adu, Direction::Request).is_ok());
    }));
    out.push(time_per("codec-rtu-response-encode-decode", secs, || {
        let pdu = black_box(&resp).to_bytes().unwrap_or_default();
        let mut adu = Vec::with_capacity(16);
        let _ = rtu::encode_adu(UNIT, &pdu, &mut adu);
        black_box(rtu::decode(&adu, Direction::Response).is_ok());
    }));
    let profile = generic_profile()?;
    let mut station = Station::new(
        drives::build(profile.clone(), FaultSet::none()),
        FaultSet::none(),
        UNIT,
    );
    let mut conn = TcpConn::default();
    let adu = framed(Framing::Tcp);
    let mut now = Duration::ZERO;
    out.push(time_per("station-tcp-request-to-reply", secs, || {
        now += Duration::from_micros(1);
        let r = station.serve_tcp(now, &mut conn, black_box(&adu));
        black_box(r.replies.len());
    }));
    let mut model = drives::build(profile, FaultSet::none());
    let mut now = Duration::ZERO;
    out.push(time_per("drive-model-handle", secs, || {
        now += Duration::from_micros(1);
        model.advance(now);
        black_box(model.handle(now, UNIT, black_box(&req)));
    }));
    // The copy of the reference drive the runner takes before a step whose answer a choice of the drive may
    // decide (`Runner::run_step`: every request but a plain read, and on a profile with 32-bit registers
    // every read too), per profile.
    for (name, stem) in [
        ("reference-copy-generic", "generic"),
        ("reference-copy-mdrive", "mdrive"),
        ("reference-copy-lmd", "lmd"),
        ("reference-copy-sd2x", "sd2x"),
    ] {
        let p = Corpus::Embedded
            .profile(stem)
            .map_err(|e| other(e.to_string()))?;
        let unit = p.device.default_unit;
        let reference = SimTarget::new(Station::new(
            drives::build(p, FaultSet::none()),
            FaultSet::none(),
            unit,
        ));
        out.push(time_per(name, secs, || {
            black_box(black_box(&reference).clone());
        }));
    }
    Ok(out)
}

/// Peak resident set size of this process so far (VmHWM), in KiB.
pub fn peak_rss_kib() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// What a catalog loop did.
#[derive(Clone, Debug)]
pub struct LoopOutcome {
    pub cases: u64,
    pub catalogs: u64,
    pub seconds: f64,
    pub fails: u64,
    pub peak_rss_kib: Option<u64>,
}

impl fmt::Display for LoopOutcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "LOOP cases={} catalogs={} seconds={:.1} cases_per_s={:.0} fails={} peak_rss_kib={}",
            self.cases,
            self.catalogs,
            self.seconds,
            self.cases as f64 / self.seconds.max(1e-9),
            self.fails,
            self.peak_rss_kib.map_or("?".into(), |k| k.to_string())
        )
    }
}

/// The stand-in for the 1,000,000-case generated run while `run --generated` does not exist: the catalog of
/// `sim:PROFILE` run again and again through one `Runner` (one target, one oracle, as a run has) until
/// `cases` cases have run, each result tallied and, with `report`, streamed to the report files.
pub fn catalog_loop(
    profile_name: &str,
    cases: u64,
    report: Option<&Path>,
) -> Result<LoopOutcome, BenchError> {
    let opts = session::Options::new(engine::targets::TargetUrl::Sim {
        profile: profile_name.into(),
        rtu: None,
    });
    let profile = opts
        .corpus
        .profile(profile_name)
        .map_err(|e| other(e.to_string()))?;
    let planned = session::plan(&opts, &profile).map_err(|e| other(e.to_string()))?;
    let unit = profile.device.default_unit;
    let station = Station::new(
        drives::build(profile.clone(), FaultSet::none()),
        FaultSet::none(),
        unit,
    );
    let target: Box<dyn Target> = Box::new(SimTarget::new(station));
    let framing = target.framing();
    let shadow = SimTarget::with_framing(
        Station::new(
            drives::build(profile.clone(), FaultSet::none()),
            FaultSet::none(),
            unit,
        ),
        framing,
        target.rtu_timing(),
    )
    .mirror();
    let cfg = RunConfig {
        unit,
        timing: opts.timing,
        safety: Default::default(),
        is_sim: true,
    };
    let mut reports = match report {
        Some(dir) => Some(
            Reports::create(
                dir,
                &RunInfo {
                    target: format!("sim:{profile_name}"),
                    profile: profile.device.id.clone(),
                    transport: if framing == Framing::Tcp {
                        Transport::Tcp
                    } else {
                        Transport::Rtu
                    },
                    server_port: 502,
                    started_unix_ms: 0,
                    command_line: "catalog-loop".into(),
                    seed: None,
                    shuffle: None,
                    harness_version: env!("CARGO_PKG_VERSION").into(),
                    report_dir: Some(dir.to_path_buf()),
                },
            )
            .map_err(|e| other(e.to_string()))?,
        ),
        None => None,
    };
    let mut runner = Runner::new(
        target,
        shadow,
        profile,
        cfg.clone(),
        Expectations::default(),
    );
    let runnable: Vec<&Case> = planned
        .iter()
        .filter(|(c, skip)| skip.is_none() && skip_reason(c, &cfg, framing).is_none())
        .map(|(c, _)| c)
        .collect();
    if runnable.is_empty() {
        return Err(other("the catalog is empty"));
    }
    let mut tally = Tally::new();
    let start = Instant::now();
    let (mut done, mut catalogs, mut fails) = (0u64, 0u64, 0u64);
    'outer: loop {
        for case in &runnable {
            if done >= cases {
                break 'outer;
            }
            let r = runner.run_case(case)?;
            if r.verdict == Verdict::Fail {
                fails += 1;
            }
            tally.record(&r);
            if let Some(rep) = reports.as_mut() {
                rep.case(case, &r).map_err(|e| other(e.to_string()))?;
            }
            done += 1;
        }
        catalogs += 1;
    }
    let seconds = start.elapsed().as_secs_f64();
    if let Some(rep) = reports {
        rep.finish(&tally.summary(false, start.elapsed()))
            .map_err(|e| other(e.to_string()))?;
    }
    Ok(LoopOutcome {
        cases: done,
        catalogs,
        seconds,
        fails,
        peak_rss_kib: peak_rss_kib(),
    })
}
