//! One conformance run from start to end: profile, catalog, selection, target, runner, reports.
//! The command line is a thin layer over this, and tests drive it directly.

use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::case::{Case, Tag, Verdict};
use super::expect::Expectations;
use super::observe::CaseResult;
use super::runner::{RunConfig, Runner, skip_reason};
use crate::corpus::Corpus;
use crate::frame::{Direction, Framing, Pdu, Request, Response, decode_any, rtu, tcp};
use crate::golden::GoldenFile;
use crate::profile::{Profile, Transport};
use crate::report::{Reports, RunInfo, Summary, Tally};
use crate::sim::{self, FaultSet, Station};
use crate::target::sim::SimTarget;
use crate::target::{self, Received, TargetError, TargetUrl};

/// Everything a run needs to know.
#[derive(Clone, Debug)]
pub struct Options {
    pub target: TargetUrl,
    /// A profile name, or `auto` to pick one from device identification.
    pub profile: Option<String>,
    pub corpus: Corpus,
    pub unit: Option<u8>,
    pub timeout: Duration,
    pub silence: Duration,
    pub connect_timeout: Duration,
    pub allow_motion: bool,
    pub allow_destructive: bool,
    pub read_only: bool,
    pub max_rate: Option<f64>,
    pub include: Vec<String>,
    pub exclude: Vec<String>,
    pub expect: Option<PathBuf>,
    /// Faults of the in-process simulator (`sim:` targets only).
    pub faults: FaultSet,
    pub report_dir: Option<PathBuf>,
    /// The command line, for the report header.
    pub command_line: String,
    /// Keep every case's verdict in the outcome (tests); off for huge runs.
    pub keep_verdicts: bool,
}

impl Options {
    /// Defaults for a target: 1 s timeout, 300 ms silence window, nothing allowed beyond reads and safe writes.
    pub fn new(target: TargetUrl) -> Self {
        Self {
            target,
            profile: None,
            corpus: Corpus::Embedded,
            unit: None,
            timeout: Duration::from_millis(1000),
            silence: Duration::from_millis(300),
            connect_timeout: Duration::from_secs(3),
            allow_motion: false,
            allow_destructive: false,
            read_only: false,
            max_rate: None,
            include: Vec::new(),
            exclude: Vec::new(),
            expect: None,
            faults: FaultSet::none(),
            report_dir: None,
            command_line: String::new(),
            keep_verdicts: false,
        }
    }
}

/// Why a run could not start or complete (exit code 2).
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("{0}")]
    Setup(String),
    #[error(transparent)]
    Target(#[from] TargetError),
    #[error("writing the report: {0}")]
    Report(#[from] std::io::Error),
}

/// What a run produced.
#[derive(Debug)]
pub struct Outcome {
    pub summary: Summary,
    pub info: RunInfo,
    /// (case id, verdict), when `keep_verdicts` was set.
    pub verdicts: Vec<(String, Verdict)>,
    /// Full results of FAIL cases (capped), for tests and the terminal.
    pub failures: Vec<CaseResult>,
}

impl Outcome {
    /// The verdict of a case, when kept.
    pub fn verdict(&self, id: &str) -> Option<Verdict> {
        self.verdicts.iter().find(|(i, _)| i == id).map(|(_, v)| *v)
    }
}

/// The names of the profiles in a corpus.
pub fn profile_names(corpus: &Corpus) -> Vec<String> {
    corpus
        .files("profiles")
        .unwrap_or_default()
        .iter()
        .filter_map(|(n, _)| {
            std::path::Path::new(n.trim_end_matches(" (embedded)"))
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
        })
        .collect()
}

/// Load a profile by name, listing the known ones when it is not there.
pub fn load_profile(corpus: &Corpus, name: &str) -> Result<Profile, String> {
    let (file, text) = corpus.file("profiles", name).map_err(|_| {
        format!(
            "no profile `{name}` in the {}; known profiles: {}",
            corpus.describe(),
            profile_names(corpus).join(", ")
        )
    })?;
    Profile::parse(&file, &text).map_err(|e| e.to_string())
}

/// The golden frames of a profile's manual, if the corpus has them.
pub fn load_golden(corpus: &Corpus, profile: &str) -> Result<Option<GoldenFile>, String> {
    match corpus.file("golden", profile) {
        Ok((file, text)) => GoldenFile::parse(&file, &text)
            .map(Some)
            .map_err(|e| e.to_string()),
        Err(_) => Ok(None),
    }
}

/// The framing a target URL implies (for `sim:`, the profile's native transport).
pub fn framing_of(url: &TargetUrl, profile: &Profile) -> Framing {
    match url {
        TargetUrl::Tcp { .. } => Framing::Tcp,
        TargetUrl::RtuOverTcp { .. } | TargetUrl::Serial { .. } => Framing::Rtu,
        TargetUrl::Sim {
            rtu: Some(true), ..
        } => Framing::Rtu,
        TargetUrl::Sim {
            rtu: Some(false), ..
        } => Framing::Tcp,
        TargetUrl::Sim { rtu: None, .. } => {
            if profile.device.transports.contains(&Transport::Tcp) {
                Framing::Tcp
            } else {
                Framing::Rtu
            }
        }
    }
}

fn matches_any(id: &str, globs: &[String]) -> bool {
    globs.iter().any(|g| {
        glob::Pattern::new(g).is_ok_and(|p| p.matches(id))
            || id == g
            || id.starts_with(&format!("{}/", g.trim_end_matches('/')))
    })
}

/// The catalog of a profile on a framing, selected by include/exclude globs.
pub fn select(cases: Vec<Case>, include: &[String], exclude: &[String]) -> Vec<Case> {
    cases
        .into_iter()
        .filter(|c| include.is_empty() || matches_any(&c.id, include))
        .filter(|c| !matches_any(&c.id, exclude))
        .collect()
}

/// Resolve the profile a run uses: named, the sim's own, or read from the device (`auto`).
pub fn resolve_profile(opts: &Options, log: &mut dyn Write) -> Result<Profile, SessionError> {
    let name = match (&opts.profile, &opts.target) {
        (Some(p), _) if p != "auto" => p.clone(),
        (None | Some(_), TargetUrl::Sim { profile, .. }) => profile.clone(),
        (Some(_), _) => return auto_profile(opts, log),
        (None, _) => {
            return Err(SessionError::Setup(format!(
                "--profile is required for {} (one of: {}, or auto to read the device identification)",
                opts.target,
                profile_names(&opts.corpus).join(", ")
            )));
        }
    };
    load_profile(&opts.corpus, &name).map_err(SessionError::Setup)
}

/// Read FC 2B/0E basic identification from the target and pick the profile whose objects match.
fn auto_profile(opts: &Options, log: &mut dyn Write) -> Result<Profile, SessionError> {
    let mut t = target::open(
        &opts.target,
        |_| Err("sim: has its own profile".into()),
        opts.connect_timeout,
    )?;
    let unit = opts.unit.unwrap_or(1);
    let pdu = Request::ReadDeviceId {
        read_code: 1,
        object_id: 0,
    }
    .to_bytes()
    .unwrap_or_default();
    let mut frame = Vec::new();
    let framing = t.framing();
    if framing == Framing::Tcp {
        let _ = tcp::encode_adu(0x4144, unit, &pdu, &mut frame);
    } else {
        let _ = rtu::encode_adu(unit, &pdu, &mut frame);
    }
    t.send(&frame)?;
    let got = t.recv(opts.timeout)?;
    let Received::Frame { bytes, .. } = got else {
        return Err(SessionError::Setup(format!(
            "--profile auto: {} gave no device identification answer ({got:?}); name the profile with --profile",
            opts.target
        )));
    };
    let objects = match decode_any(&bytes, framing, Direction::Response).map(|d| d.pdu) {
        Ok(Pdu::Response(Response::ReadDeviceId(d))) => d.objects,
        other => {
            return Err(SessionError::Setup(format!(
                "--profile auto: the identification answer is not usable ({other:?}); name the profile with --profile"
            )));
        }
    };
    let found: Vec<(u8, String)> = objects
        .iter()
        .map(|o| (o.id, String::from_utf8_lossy(&o.value).trim().to_string()))
        .collect();
    let _ = writeln!(log, "device identification: {found:?}");
    let lower = |s: &str| s.to_ascii_lowercase();
    let mut best: Option<(usize, Profile)> = None;
    for name in profile_names(&opts.corpus) {
        let Ok(p) = load_profile(&opts.corpus, &name) else {
            continue;
        };
        let score = p
            .identification
            .iter()
            .filter(|o| o.object_id <= 2)
            .filter(|o| {
                found.iter().any(|(id, v)| {
                    *id == o.object_id
                        && !v.is_empty()
                        && (lower(v).contains(&lower(&o.value))
                            || lower(&o.value).contains(&lower(v)))
                })
            })
            .count();
        if score > 0 && best.as_ref().is_none_or(|(s, _)| score > *s) {
            best = Some((score, p));
        }
    }
    match best {
        Some((score, p)) => {
            let _ = writeln!(
                log,
                "--profile auto: picked `{}` ({score} identification object(s) match)",
                p.device.id
            );
            Ok(p)
        }
        None => Err(SessionError::Setup(format!(
            "--profile auto: no profile matches the identification {found:?}; known profiles: {}",
            profile_names(&opts.corpus).join(", ")
        ))),
    }
}

/// The catalog a run would use, with the reason each case would be skipped.
pub fn plan(
    opts: &Options,
    profile: &Profile,
) -> Result<Vec<(Case, Option<String>)>, SessionError> {
    let golden = load_golden(&opts.corpus, &profile.device.id).map_err(SessionError::Setup)?;
    let framing = framing_of(&opts.target, profile);
    let unit = opts.unit.unwrap_or(profile.device.default_unit);
    let cases = select(
        super::catalog::build(profile, golden.as_ref(), framing, unit),
        &opts.include,
        &opts.exclude,
    );
    let cfg = config(opts, profile);
    Ok(cases
        .into_iter()
        .map(|c| {
            let skip = skip_reason(&c, &cfg, framing);
            (c, skip)
        })
        .collect())
}

fn config(opts: &Options, profile: &Profile) -> RunConfig {
    RunConfig {
        unit: opts.unit.unwrap_or(profile.device.default_unit),
        timeout: opts.timeout,
        silence: opts.silence,
        allow_motion: opts.allow_motion,
        allow_destructive: opts.allow_destructive,
        read_only: opts.read_only,
        max_rate: opts.max_rate,
        is_sim: opts.target.is_sim(),
    }
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Run the selected catalog. `progress` is called after each case with (done, total, id, verdict).
pub fn run(
    opts: &Options,
    log: &mut dyn Write,
    interrupt: &AtomicBool,
    progress: &mut dyn FnMut(usize, usize, &str, Verdict),
) -> Result<Outcome, SessionError> {
    let profile = resolve_profile(opts, log)?;
    if !opts.faults.0.is_empty() && !opts.target.is_sim() {
        return Err(SessionError::Setup(
            "--fault applies to the in-process simulator only (sim:PROFILE); for a server use `simulate --fault`".into(),
        ));
    }
    let expectations = match &opts.expect {
        Some(p) => Expectations::load(p).map_err(SessionError::Setup)?,
        None => Expectations::default(),
    };
    let cfg = config(opts, &profile);
    let [lo, hi] = profile.device.unit_ids;
    let broadcast = profile.device.broadcast && cfg.unit == 0;
    if !((lo..=hi).contains(&cfg.unit) || broadcast) {
        let _ = writeln!(
            log,
            "warning: unit {} is outside the profile's unit ids {lo}..={hi}",
            cfg.unit
        );
    }
    let planned = plan(opts, &profile)?;
    let faults = opts.faults.clone();
    let unit = cfg.unit;
    let target = target::open(
        &opts.target,
        |_| {
            Ok(Station::new(
                sim::build(profile.clone(), faults.clone()),
                faults.clone(),
                unit,
            ))
        },
        opts.connect_timeout,
    )?;
    let framing = target.framing();
    let shadow_station = Station::new(
        sim::build(profile.clone(), FaultSet::none()),
        FaultSet::none(),
        unit,
    );
    let shadow = SimTarget::with_framing(shadow_station, framing, target.rtu_timing()).mirror();
    let info = RunInfo {
        target: opts.target.to_string(),
        profile: profile.device.id.clone(),
        transport: match (&opts.target, framing) {
            (TargetUrl::RtuOverTcp { .. }, _) => crate::report::Transport::RtuOverTcp,
            (_, Framing::Rtu) => crate::report::Transport::Rtu,
            _ => crate::report::Transport::Tcp,
        },
        server_port: target.server_port(),
        started_unix_ms: unix_ms(),
        command_line: opts.command_line.clone(),
        seed: None,
        harness_version: env!("CARGO_PKG_VERSION").to_string(),
        report_dir: opts.report_dir.clone(),
    };
    let mut reports = match &opts.report_dir {
        Some(d) => Some(Reports::create(d, &info)?),
        None => None,
    };
    let _ = writeln!(
        log,
        "modbus-harness: {} with profile `{}` (unit {}), {} cases",
        target.describe(),
        profile.device.id,
        cfg.unit,
        planned.len()
    );
    let mut runner = Runner::new(target, shadow, profile.clone(), cfg.clone(), expectations);
    let mut tally = Tally::new();
    let mut verdicts = Vec::new();
    let mut failures = Vec::new();
    let started = Instant::now();
    let mut banner_done = cfg.is_sim;
    let total = planned.len();
    let mut interrupted = false;
    for (i, (case, skip)) in planned.iter().enumerate() {
        if interrupt.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let result = match skip {
            Some(reason) => CaseResult {
                id: case.id.clone(),
                verdict: Verdict::Skipped,
                expected_deviation: None,
                steps: vec![],
                wire: vec![],
                duration: Duration::ZERO,
                reason: Some(reason.clone()),
            },
            None => {
                if !banner_done && case.has(Tag::Write) {
                    banner_done = true;
                    write_banner(log, &planned, &profile);
                }
                runner.run_case(case)?
            }
        };
        tally.record(&result);
        if let Some(r) = reports.as_mut() {
            r.case(case, &result)?;
        }
        progress(i + 1, total, &case.id, result.verdict);
        if opts.keep_verdicts {
            verdicts.push((case.id.clone(), result.verdict));
        }
        if result.verdict == Verdict::Fail && failures.len() < 200 {
            failures.push(result);
        }
    }
    let summary = tally.summary(interrupted, started.elapsed());
    if let Some(r) = reports {
        r.finish(&summary)?;
    }
    Ok(Outcome {
        summary,
        info,
        verdicts,
        failures,
    })
}

/// Before the first write on real hardware: say what will be written.
fn write_banner(log: &mut dyn Write, planned: &[(Case, Option<String>)], profile: &Profile) {
    let writes: Vec<&Case> = planned
        .iter()
        .filter(|(c, s)| s.is_none() && c.has(Tag::Write))
        .map(|(c, _)| c)
        .collect();
    let _ = writeln!(
        log,
        "\n*** WRITES AHEAD: {} case(s) will write to this {} ***",
        writes.len(),
        profile.device.name
    );
    for c in writes.iter().take(30) {
        let kinds: Vec<&str> = [(Tag::Motion, "motion"), (Tag::Destructive, "destructive")]
            .iter()
            .filter(|(t, _)| c.has(*t))
            .map(|(_, n)| *n)
            .collect();
        let _ = writeln!(
            log,
            "  {}  {}{}",
            c.id,
            c.title,
            if kinds.is_empty() {
                String::new()
            } else {
                format!("  [{}]", kinds.join(", "))
            }
        );
    }
    if writes.len() > 30 {
        let _ = writeln!(log, "  ... and {} more (see --dry-run)", writes.len() - 30);
    }
    let _ = writeln!(
        log,
        "Values changed are read first and written back where the case can (read, write, restore).\n"
    );
}
