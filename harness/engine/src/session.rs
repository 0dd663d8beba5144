//! One conformance run from start to end: profile, catalog, selection, target, runner, reports.
//! The command line is a thin layer over this, and tests drive it directly.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::cases::generated::{self, Generator};
use crate::cases::regressions::{self, Origin};
use crate::cases::shrink::{self, ShrinkLimits, Shrunk};
use crate::cases::{Case, Tag, Verdict};
use crate::expect::Expectations;
use crate::observe::CaseResult;
use crate::reports::snapshot::{self, Drift, SnapshotHeader, SnapshotWriter};
use crate::reports::{Reports, RunInfo, Summary, Tally};
use crate::runner::{RunConfig, Runner, Safety, Timing, skip_reason};
use crate::targets::sim::SimTarget;
use crate::targets::{self, Received, TargetError, TargetUrl};
use codec::{Direction, Framing, Pdu, Request, Response, decode_any, rtu, tcp};
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::requirements::Requirements;
use drives::{self, FaultSet, Station};

/// Everything a run needs to know.
#[derive(Clone, Debug)]
pub struct Options {
    pub target: TargetUrl,
    /// A profile of the corpus by name, a profile file (a value with a `/` or ending in `.toml`, see
    /// [`drives::corpus::is_profile_path`]), or `auto` to pick one from device identification.
    pub profile: Option<String>,
    pub corpus: Corpus,
    pub unit: Option<u8>,
    /// A slave address no device on the line answers (`--foreign-address`): the cases that check a frame
    /// for another slave goes unanswered send to it. `None`: found by the line survey at the start of a run
    /// against an RTU device ([`survey_line`]).
    pub foreign: Option<u8>,
    /// How long to wait for answers and for silence.
    pub timing: Timing,
    pub connect_timeout: Duration,
    /// What the run may do to a real drive.
    pub safety: Safety,
    pub include: Vec<String>,
    pub exclude: Vec<String>,
    pub expect: Option<PathBuf>,
    /// Faults of the in-process simulator (`sim:` targets only).
    pub faults: FaultSet,
    /// Choices of the in-process simulator where the freedoms leave one (`FREEDOM=VALUE`, `sim:` only).
    pub choose: Vec<String>,
    pub report_dir: Option<PathBuf>,
    /// The command line, for the report header.
    pub command_line: String,
    /// Keep every case's verdict in the outcome (tests); off for huge runs.
    pub keep_verdicts: bool,
    /// Generated cases to run (`--generated N`); 0 runs none.
    pub generated: u64,
    /// Seed of the generated cases; `None` takes one from the clock (logged and put in the reports).
    pub seed: Option<u64>,
    /// With generated cases, run the catalog (and the regressions) too; without them the catalog always runs.
    pub with_catalog: bool,
    /// Shrink failing generated cases against the target within these bounds; `None` does not shrink.
    pub shrink: Option<ShrinkLimits>,
    /// Failing generated cases shrunk at most in one run (the first ones).
    pub max_shrinks: usize,
    /// Write each shrunk reproducer to `<dir>/<profile>/<name>.toml` (`corpus/regressions` for the catalog).
    pub regressions_dir: Option<PathBuf>,
    /// Compare the run's observations with a snapshot file, or write it.
    pub snapshot: Option<SnapshotOptions>,
    /// Apply the safety policy to the in-process simulator as to a real drive, so that a `sim:` run selects
    /// the same cases as a run against a server (for comparing their snapshots).
    pub policy_on_sim: bool,
    /// Run the selected catalog cases (and regressions) in an order shuffled with this seed; reports keep
    /// the case ids, generated cases follow in their own order.
    pub shuffle: Option<u64>,
    /// Leave the drive as found (real targets; off with `--read-only`, where nothing is written): read every
    /// parameter before the first write, restore after each writing case and at the end.
    pub leave_as_found: bool,
    /// The state journal (default: `journal.json` in the report directory, else a file in the temporary
    /// directory named after the process).
    pub journal: Option<PathBuf>,
    /// The pre-flight read before the first case and the liveness probes when an answer that was due does
    /// not come (real targets only: the in-process drive cannot go away); `None` sends neither.
    pub liveness: Option<crate::liveness::Liveness>,
}

/// Where the run's snapshot goes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SnapshotOptions {
    /// The snapshot file.
    pub path: PathBuf,
    /// Write the file instead of comparing with it.
    pub update: bool,
}

impl Options {
    /// Defaults for a target: 1 s timeout, 300 ms silence window, nothing allowed beyond reads and safe writes.
    pub fn new(target: TargetUrl) -> Self {
        Self {
            target,
            profile: None,
            corpus: Corpus::Embedded,
            unit: None,
            foreign: None,
            timing: Timing::default(),
            connect_timeout: Duration::from_secs(3),
            safety: Safety::default(),
            include: Vec::new(),
            exclude: Vec::new(),
            expect: None,
            faults: FaultSet::none(),
            choose: Vec::new(),
            report_dir: None,
            command_line: String::new(),
            keep_verdicts: false,
            generated: 0,
            seed: None,
            with_catalog: false,
            shrink: Some(ShrinkLimits::default()),
            max_shrinks: 3,
            regressions_dir: None,
            snapshot: None,
            policy_on_sim: false,
            shuffle: None,
            leave_as_found: true,
            journal: None,
            liveness: Some(crate::liveness::Liveness::default()),
        }
    }
}

/// Why a run could not start or complete (exit code 2).
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// A profile or golden file could not be loaded.
    #[error(transparent)]
    Corpus(#[from] drives::corpus::CorpusError),
    #[error("--profile is required for {target}: a profile file (./my.toml; draft one with `probe --write-profile`), one of {}, or auto to read the device identification", known.join(", "))]
    ProfileRequired { target: String, known: Vec<String> },
    /// `--profile auto` could not pick a profile.
    #[error("--profile auto: {0}")]
    AutoProfile(String),
    #[error(
        "--fault applies to the in-process simulator only (sim:PROFILE); for a server use `simulate --fault`"
    )]
    FaultNeedsSim,
    #[error(
        "--choose applies to the in-process simulator only (sim:PROFILE); for a server use `simulate --choose`"
    )]
    ChoicesNeedSim,
    #[error(transparent)]
    Choice(#[from] drives::choices::ChoiceError),
    #[error(transparent)]
    Expectations(#[from] crate::expect::ExpectError),
    #[error(transparent)]
    Regressions(#[from] crate::cases::regressions::RegressionError),
    #[error("no snapshot at {}: write it with --update-snapshot", .0.display())]
    NoSnapshot(PathBuf),
    #[error(
        "--foreign-address {0} is the drive's own address{1}: give an address no device on the line answers"
    )]
    ForeignIsOwn(u8, &'static str),
    #[error("cannot create directory {}: {source}", path.display())]
    CreateDir {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Requirements(#[from] drives::requirements::RequirementsError),
    #[error(transparent)]
    Target(#[from] TargetError),
    /// The pre-flight read got no Modbus answer: what was tried, and the likely causes or what answered.
    #[error("{0}")]
    NotAnswering(String),
    #[error("writing the report: {0}")]
    Report(#[from] std::io::Error),
    /// The snapshot before the first write could not be taken or journaled: nothing was written.
    #[error("leave as found: {0} (nothing was written)")]
    Snapshot(#[from] crate::restore::SnapshotError),
    /// The run stopped on an error (a dead target) and could not put the drive back.
    #[error(
        "{error}; the drive was NOT left as found: {unrestored} parameter(s) not restored (after the drive is back: modbus-harness restore --journal {})",
        journal.as_ref().map_or_else(|| "FILE".to_string(), |p| p.display().to_string())
    )]
    LeftChanged {
        error: Box<SessionError>,
        unrestored: usize,
        journal: Option<PathBuf>,
    },
}

/// What a run produced.
#[derive(Debug)]
pub struct RunOutcome {
    pub summary: Summary,
    pub info: RunInfo,
    /// (case id, verdict), when `keep_verdicts` was set.
    pub verdicts: Vec<(String, Verdict)>,
    /// Full results of FAIL cases (capped), for tests and the terminal.
    pub failures: Vec<CaseResult>,
    /// The failing generated cases that were shrunk (or could not be), in run order.
    pub shrunk: Vec<ShrinkReport>,
    /// The snapshot written or compared, if `--snapshot` was given.
    pub snapshot: Option<SnapshotOutcome>,
    /// Each entry of the expectations file (`--expect`): the cases it matched and the deviations it excused.
    pub expectations: Vec<crate::expect::ExpectationUse>,
}

impl RunOutcome {
    /// Parameters the run could not put back (see [`crate::restore::EXIT_NOT_RESTORED`]).
    pub fn not_restored(&self) -> usize {
        self.summary.not_restored()
    }
}

/// What became of one failing generated case.
#[derive(Clone, Debug)]
pub struct ShrinkReport {
    /// The generated case that failed.
    pub id: String,
    /// The shrink, when the case failed again when re-run alone.
    pub shrunk: Option<Shrunk>,
    /// The regression file written.
    pub file: Option<PathBuf>,
    /// Why there is no shrink or no file, if so.
    pub note: Option<String>,
}

/// The snapshot of a run.
#[derive(Clone, Debug)]
pub struct SnapshotOutcome {
    pub path: PathBuf,
    /// The file was written (`--update-snapshot`), not compared.
    pub written: bool,
    /// The comparison, when compared.
    pub drift: Option<Drift>,
}

impl SnapshotOutcome {
    /// True when the run's observations differ from the file.
    pub fn drifted(&self) -> bool {
        self.drift.as_ref().is_some_and(|d| !d.is_clean())
    }
}

impl RunOutcome {
    /// The verdict of a case, when kept.
    pub fn verdict(&self, id: &str) -> Option<Verdict> {
        self.verdicts.iter().find(|(i, _)| i == id).map(|(_, v)| *v)
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
            if profile.speaks_tcp() {
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

/// Resolve the profile a run uses: named or a file (`--profile`), the sim's own, or read from the device
/// (`auto`).
pub fn resolve_profile(opts: &Options, log: &mut dyn Write) -> Result<Profile, SessionError> {
    let name = match (&opts.profile, &opts.target) {
        (Some(p), _) if p != "auto" => p.clone(),
        (None | Some(_), TargetUrl::Sim { profile, .. }) => profile.clone(),
        (Some(_), _) => return auto_profile(opts, log),
        (None, _) => {
            return Err(SessionError::ProfileRequired {
                target: opts.target.to_string(),
                known: opts.corpus.profile_names(),
            });
        }
    };
    Ok(opts.corpus.load(&name)?)
}

/// The profile of the drive a `sim:` target runs: its own (`sim:NAME`, `sim:PATH`, named `own`), which a
/// `--profile` naming another one judges; `profile` (the run's) when they are the same.
fn simulated(
    opts: &Options,
    own: &str,
    profile: &Profile,
) -> Result<Profile, drives::corpus::CorpusError> {
    match &opts.profile {
        Some(p) if p != "auto" && p != own => opts.corpus.load(own),
        _ => Ok(profile.clone()),
    }
}

/// The framing of a run: the target's, or for a `sim:` target its drive's native one.
fn run_framing(opts: &Options, profile: &Profile) -> Result<Framing, SessionError> {
    Ok(match &opts.target {
        TargetUrl::Sim { profile: own, .. } => {
            framing_of(&opts.target, &simulated(opts, own, profile)?)
        }
        _ => framing_of(&opts.target, profile),
    })
}

/// Read FC 2B/0E basic identification from the target and pick the profile whose objects match.
fn auto_profile(opts: &Options, log: &mut dyn Write) -> Result<Profile, SessionError> {
    let mut t = targets::open(
        &opts.target,
        |name| {
            let p = opts.corpus.load(name)?;
            Ok(Station::new(
                drives::build(p, FaultSet::none()),
                FaultSet::none(),
                opts.unit.unwrap_or(1),
            ))
        },
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
    let got = t.recv(opts.timing.timeout)?;
    let Received::Frame { bytes, .. } = got else {
        return Err(SessionError::AutoProfile(format!(
            "{} gave no device identification answer ({got:?}); name the profile with --profile",
            opts.target
        )));
    };
    let objects = match decode_any(&bytes, framing, Direction::Response).map(|d| d.pdu) {
        Ok(Pdu::Response(Response::ReadDeviceId(d))) => d.objects,
        other => {
            return Err(SessionError::AutoProfile(format!(
                "the identification answer is not usable ({other:?}); name the profile with --profile"
            )));
        }
    };
    let found: Vec<(u8, String)> = objects
        .iter()
        .map(|o| (o.id, String::from_utf8_lossy(&o.value).trim().to_string()))
        .collect();
    let _ = writeln!(
        log,
        "device identification: {}",
        crate::auto_profile::describe(&found)
    );
    let profiles: Vec<Profile> = opts
        .corpus
        .profile_names()
        .iter()
        .filter_map(|n| opts.corpus.profile(n).ok())
        .collect();
    let m = crate::auto_profile::pick(&found, &profiles).map_err(SessionError::AutoProfile)?;
    let _ = writeln!(
        log,
        "--profile auto: picked `{}`: {}",
        m.profile,
        m.matched
            .iter()
            .map(|(id, name, v)| format!("{name} (0x{id:02X}) = {v:?}"))
            .collect::<Vec<_>>()
            .join(" and ")
    );
    profiles
        .into_iter()
        .find(|p| p.device.id == m.profile)
        .ok_or_else(|| SessionError::AutoProfile(format!("profile `{}` vanished", m.profile)))
}

/// True when the catalog runs: always, unless only generated cases were asked for.
fn runs_catalog(opts: &Options) -> bool {
    opts.generated == 0 || opts.with_catalog
}

/// The catalog part of a run (catalog and regressions, or nothing for a generated-only run), selected,
/// with the reason each case would be skipped.
fn catalog_plan(
    opts: &Options,
    profile: &Profile,
    requirements: &Requirements,
) -> Result<Vec<(Case, Option<String>)>, SessionError> {
    if !runs_catalog(opts) {
        return Ok(Vec::new());
    }
    let golden = opts.corpus.golden(&profile.device.id)?;
    let framing = run_framing(opts, profile)?;
    let unit = opts.unit.unwrap_or(profile.device.default_unit);
    let mut all =
        crate::cases::catalog::build_on_line(profile, golden.as_ref(), framing, unit, opts.foreign);
    all.extend(crate::cases::catalog::regressions(
        &opts.corpus,
        profile,
        unit,
    )?);
    let cases = run_order(select(all, &opts.include, &opts.exclude), opts.shuffle);
    let cfg = config(opts, profile);
    Ok(cases
        .into_iter()
        .map(|mut c| {
            (c.requirements, c.freedoms) = requirements.cited(&c.id, &profile.device.id);
            let skip = skip_reason(&c, &cfg, framing);
            (c, skip)
        })
        .collect())
}

/// The choices of the in-process drive (`--choose FREEDOM=VALUE`, `sim:` targets only), checked against the
/// freedoms of the profile.
pub fn choices_of(
    opts: &Options,
    profile: &Profile,
    requirements: &Requirements,
) -> Result<drives::Choices, SessionError> {
    if opts.choose.is_empty() {
        return Ok(drives::Choices::reference());
    }
    if !opts.target.is_sim() {
        return Err(SessionError::ChoicesNeedSim);
    }
    Ok(drives::Choices::parse_all(
        &opts.choose,
        requirements,
        profile,
    )?)
}

/// The requirements, freedoms and citations of the run's corpus; a corpus directory without them (a user's
/// profiles only) is judged with the built-in ones. The built-in ones are loaded once per process.
pub fn requirements_of(corpus: &Corpus) -> Result<Arc<Requirements>, SessionError> {
    Ok(corpus.requirements_shared()?)
}

/// The order a run takes its catalog cases in: as built, or shuffled with `seed`. Either way the cases that
/// judge what the run measured ([`Tag::RunTiming`]) and then those that leave the drive changed for good
/// ([`Tag::Irreversible`]) come last, in their own order.
pub fn run_order(cases: Vec<Case>, shuffle: Option<u64>) -> Vec<Case> {
    let cases = crate::cases::catalog::irreversible_last(cases);
    let Some(seed) = shuffle else {
        return cases;
    };
    let (mut free, last): (Vec<Case>, Vec<Case>) = cases
        .into_iter()
        .partition(|c| !c.has(Tag::Irreversible) && !c.has(Tag::RunTiming));
    // Fisher-Yates with SplitMix64: the same seed gives the same order on every platform and version.
    let mut state = seed;
    let mut next = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    for i in (1..free.len()).rev() {
        let j = (next() % (i as u64 + 1)) as usize;
        free.swap(i, j);
    }
    free.extend(last);
    free
}

/// The generator of a run's generated cases, if it has any (seed: the options', else the clock's).
pub fn generator(opts: &Options, profile: &Profile) -> Option<Generator> {
    (opts.generated > 0).then(|| {
        Generator::new(
            profile,
            opts.unit.unwrap_or(profile.device.default_unit),
            opts.seed.unwrap_or_else(generated::clock_seed),
        )
        .on_line(opts.foreign)
    })
}

/// The cases a run would use (catalog and regressions, then generated), with the reason each would be
/// skipped. Generated cases are all built here: for listing; `run` builds them one at a time.
pub fn plan(
    opts: &Options,
    profile: &Profile,
) -> Result<Vec<(Case, Option<String>)>, SessionError> {
    let requirements = requirements_of(&opts.corpus)?;
    let mut out = catalog_plan(opts, profile, &requirements)?;
    if let Some(g) = generator(opts, profile) {
        let cfg = config(opts, profile);
        let framing = run_framing(opts, profile)?;
        out.extend(
            g.cases(opts.generated)
                .filter(|c| selected(c, &opts.include, &opts.exclude))
                .map(|c| {
                    let skip = skip_reason(&c, &cfg, framing);
                    (c, skip)
                }),
        );
    }
    Ok(out)
}

/// True when a case passes the include/exclude selection.
fn selected(c: &Case, include: &[String], exclude: &[String]) -> bool {
    (include.is_empty() || matches_any(&c.id, include)) && !matches_any(&c.id, exclude)
}

pub(crate) fn config(opts: &Options, profile: &Profile) -> RunConfig {
    RunConfig {
        unit: opts.unit.unwrap_or(profile.device.default_unit),
        timing: opts.timing,
        safety: opts.safety,
        is_sim: opts.target.is_sim() && !opts.policy_on_sim,
    }
}

/// Open the target and its reference drive (fault-free, in lockstep) and put a runner around them. A `sim:`
/// target runs its own drive (with the run's faults); the reference drive is always the run's profile's.
/// The runner has learned the drive's choices ([`learn_choices`]).
pub(crate) fn open_runner(
    opts: &Options,
    profile: &Profile,
    cfg: &RunConfig,
    expectations: &Expectations,
) -> Result<Runner, SessionError> {
    let mut runner = open_unlearned(opts, profile, cfg, expectations)?;
    learn_choices(&mut runner);
    Ok(runner)
}

/// [`open_runner`] with the [`preflight`] first: a target that does not answer, or a line that echoes, is
/// said before the runner's own reads (each of which would wait its timeout, or read an echo).
///
/// Where no `--unit` was given and the profile's unit id gets no answer over Modbus/TCP but one of the ids
/// a device that is not a gateway answers does (0xFF, 0: TCP guide 4.4.1.3; neither manual states the
/// MDrive's or the LMD's), the run takes that one: `cfg.unit` is set to it and `log` says so.
pub(crate) fn open_checked_runner(
    opts: &Options,
    profile: &Profile,
    cfg: &mut RunConfig,
    expectations: &Expectations,
    log: &mut dyn Write,
) -> Result<Runner, SessionError> {
    let mut runner = open_unlearned(opts, profile, cfg, expectations)?;
    if let Some(unit) = preflight(opts, profile, &mut runner)? {
        let _ = writeln!(
            log,
            "unit id: {} (the profile's) gets no answer, unit {unit} does: the run uses unit {unit} (the TCP implementation guide, 4.4.1.3, recommends 0xFF for a device that is not a gateway; --unit to choose)",
            cfg.unit
        );
        // The connection closed first: a drive with one connection slot frees it (see
        // `TcpTarget::close_gracefully`).
        drop(runner);
        cfg.unit = unit;
        runner = open_unlearned(opts, profile, cfg, expectations)?;
        preflight(
            &Options {
                unit: Some(unit),
                ..opts.clone()
            },
            profile,
            &mut runner,
        )?;
    }
    learn_choices(&mut runner);
    Ok(runner)
}

/// Where a freedom leaves the word order (and the FC 43 form, the input addressing, the output setup)
/// open, the cases are judged in the drive's own: read from it here.
fn learn_choices(runner: &mut Runner) {
    runner.learn_word_order();
    runner.learn_fc43_form();
    runner.learn_input_addressing();
    runner.learn_partial_register_read();
    runner.learn_output_setup();
}

fn open_unlearned(
    opts: &Options,
    profile: &Profile,
    cfg: &RunConfig,
    expectations: &Expectations,
) -> Result<Runner, SessionError> {
    let requirements = requirements_of(&opts.corpus)?;
    let choices = choices_of(opts, profile, &requirements)?;
    let faults = opts.faults.clone();
    let unit = cfg.unit;
    let target = targets::open(
        &opts.target,
        |own| {
            Ok(Station::new(
                drives::build_with(
                    simulated(opts, own, profile)?,
                    faults.clone(),
                    choices.clone(),
                ),
                faults.clone(),
                unit,
            )
            .with_choices(choices.clone()))
        },
        opts.connect_timeout,
    )?;
    let shadow = SimTarget::reference(profile, unit, drives::Choices::reference(), target.as_ref());
    Ok(Runner::new(
        target,
        shadow,
        profile.clone(),
        cfg.clone(),
        expectations.clone(),
    )
    .with_requirements(requirements))
}

/// How the silences due were settled (run and fuzz, at their end), when there were any.
pub fn log_silences(log: &mut dyn Write, runner: &Runner) {
    let timing = runner.timing();
    let crate::runner::Silences {
        sentinel,
        close,
        listened,
    } = runner.silences();
    if sentinel + close + listened > 0 {
        let _ = writeln!(
            log,
            "silences: {sentinel} proven by a sentinel request, {close} by the target's close after a half-close, {listened} listened out for the whole window ({} ms{})",
            timing.silence.as_millis(),
            match (timing.sentinel, runner.framing()) {
                (_, codec::Framing::Rtu) => ": RTU has no sentinel, see --silence",
                (true, _) =>
                    ": a frame the target may still be reading, or a target that dropped a sentinel",
                (false, _) => ": --no-sentinel",
            }
        );
    }
}

/// The bounds of the liveness checks of a run: real targets with `opts.liveness` set.
fn liveness_of(opts: &Options) -> Option<crate::liveness::Liveness> {
    opts.liveness.filter(|_| !opts.target.is_sim())
}

/// Before the first case: a known-good read of the profile over the target's framing. No Modbus answer
/// within the bound is [`SessionError::NotAnswering`] (exit 2), saying what was tried and why it may not
/// have answered, or what answered instead. Nothing is sent on `sim:` targets or without `opts.liveness`.
/// `Some(unit)`: no `--unit` was given, and over Modbus/TCP the profile's unit id gets no answer where
/// `unit` gets one (the caller runs at `unit`).
pub fn preflight(
    opts: &Options,
    profile: &Profile,
    runner: &mut Runner,
) -> Result<Option<u8>, SessionError> {
    let Some(bounds) = liveness_of(opts) else {
        return Ok(None);
    };
    let pdu = crate::cases::catalog::known_good_read(profile);
    let unit = opts.unit.unwrap_or(profile.device.default_unit);
    let failure = |runner: &Runner, heard: &crate::liveness::Heard, request: &[u8]| {
        crate::liveness::preflight_failure(
            &runner.target().describe(),
            heard,
            request,
            runner.framing(),
            match opts.target {
                TargetUrl::Serial { echo, .. } => Some(echo),
                _ => None,
            },
            unit,
            bounds.probe_timeout,
        )
    };
    let (mut heard, mut request) = runner.known_good(&pdu, bounds.probe_timeout)?;
    // RTU: noise on the line may damage the read or its answer (serial line spec 2.5.1.2), which a slave
    // discards or the harness cannot decode: asked twice more, 1 s each at most, before the target counts
    // as not answering (as a case is run again, `--link-retries`; not with 0).
    if runner.framing() == codec::Framing::Rtu && opts.timing.link_retries > 0 {
        for _ in 0..2 {
            if failure(runner, &heard, &request).is_none() {
                break;
            }
            (heard, request) =
                runner.known_good(&pdu, bounds.probe_timeout.min(Duration::from_secs(1)))?;
        }
    }
    match failure(runner, &heard, &request) {
        None => Ok(None),
        Some(mut m) => {
            // Silence on Modbus/TCP: is it the unit id? The same read at the unit ids a device that is not a
            // gateway commonly answers (TCP guide 4.4.1.3: 0xFF recommended, 0 accepted too). Reads only; not
            // on a serial line, where another address may be another device.
            if heard == crate::liveness::Heard::Nothing && runner.framing() == codec::Framing::Tcp {
                let short = bounds.probe_timeout.min(Duration::from_millis(500));
                for other in [255u8, 0, 1].into_iter().filter(|u| *u != unit) {
                    if runner.answers_at_unit(&pdu, other, short)? {
                        if opts.unit.is_none() {
                            return Ok(Some(other));
                        }
                        m = format!(
                            "{m}. The same read at unit {other} is answered: the device's unit id is likely {other} (the TCP implementation guide, 4.4.1.3, recommends 0xFF for a device that is not a gateway): run again with --unit {other}"
                        );
                        break;
                    }
                }
            }
            Err(SessionError::NotAnswering(m))
        }
    }
}

/// The line survey: where the drive is a serial-line slave (an RTU target, or an RTU drive behind a
/// gateway), the address its cases send another slave's frames to ("a frame not addressed to the slave is
/// discarded", serial line spec 2.5.1.1 and 2.4.2) must be one no other device on the line answers. A line
/// has up to 247 slaves (spec 2.1) and machine builders number them from 1 up, so the address next but one
/// to the drive's, which the cases used alone, is often another device's, whose answer the cases took for
/// the drive's. The survey sends the known-good read to [`foreign_candidates`] in turn and takes the first
/// that nothing answers (silence; behind a gateway also its exceptions 0A and 0B, which say that no device
/// answered): the run's cases then send there. The addresses that answered are said in `log`, as another
/// device on the line or the drive answering them too, which the run cannot tell apart; where every
/// candidate answers, the drive is taken to answer frames for any address, and the cases send to the first
/// (and FAIL). Reads only. A `sim:` target is alone on its line: the first address, without a survey (so
/// its cases are those a survey of it would give); nothing over Modbus/TCP to a device that speaks it
/// itself. `--foreign-address` chooses the address and skips the survey.
///
/// [`foreign_candidates`]: crate::cases::catalog::rtu::foreign_candidates
pub(crate) fn survey_line(
    opts: &Options,
    profile: &Profile,
    unit: u8,
    runner: &mut Runner,
    log: &mut dyn Write,
) -> Result<Option<u8>, SessionError> {
    let framing = runner.framing();
    if opts.foreign.is_some() || !crate::cases::catalog::rtu::on_a_line(framing, profile) {
        return Ok(opts.foreign);
    }
    let candidates = crate::cases::catalog::rtu::foreign_candidates(profile, unit);
    if opts.target.is_sim() {
        // The in-process drive is alone on its line: the first address, as a survey would find it (so
        // that the cases are the same in process and over a transport).
        return Ok(Some(candidates[0]));
    }
    let pdu = crate::cases::catalog::known_good_read(profile);
    let mut answered: Vec<String> = Vec::new();
    for &c in &candidates {
        let heard = runner.heard_at_unit(&pdu, c, opts.timing.silence)?;
        let nobody = match &heard {
            None => true,
            // A gateway's own answer that no device answered.
            Some(b) => matches!(
                crate::readings::decode_response(framing, b),
                Some(codec::Response::Exception { code, .. }) if code.is_gateway()
            ),
        };
        if nobody {
            if answered.is_empty() {
                let _ = writeln!(
                    log,
                    "line: nothing answers slave {c}: the cases that send a frame for another slave send it there (--foreign-address to choose)"
                );
            } else {
                let _ = writeln!(
                    log,
                    "line: {}: another device on the line, or the drive answering that address as well (with the drive alone on its line, --foreign-address {} judges it); nothing answers slave {c}, and the cases that send a frame for another slave send it there",
                    answered.join("; "),
                    candidates[0]
                );
            }
            return Ok(Some(c));
        }
        answered.push(format!(
            "slave {c} answered a read ({})",
            crate::liveness::hex(heard.as_deref().unwrap_or_default())
        ));
    }
    let _ = writeln!(
        log,
        "line: {}: the drive answers frames for other slaves (or devices sit at every one of these addresses); the cases send to slave {}",
        answered.join("; "),
        candidates[0]
    );
    Ok(Some(candidates[0]))
}

/// A run's watch over a real target: when an answer that was due does not come, a liveness probe (the
/// known-good read); a target that no longer answers makes the case FAIL with "stopped answering after
/// this request", and is waited for (probing, reconnecting) within a bound; if it does not come back the
/// remaining cases are SKIPPED.
struct Watch {
    bounds: crate::liveness::Liveness,
    probe: Vec<u8>,
    /// Whether a probe that got no answer is asked again before the target counts as silent (cases are run
    /// again too, `--link-retries` above 0): a damaged link loses a probe as it loses any frame.
    ask_again: bool,
    /// Why the remaining cases are not run: the target stopped answering and did not come back.
    dead: Option<String>,
    /// Targets that stopped answering and came back, with after how long.
    notes: Vec<String>,
}

impl Watch {
    fn new(opts: &Options, profile: &Profile) -> Option<Self> {
        liveness_of(opts).map(|bounds| Self {
            bounds,
            probe: crate::cases::catalog::known_good_read(profile),
            ask_again: opts.timing.link_retries > 0,
            dead: None,
            notes: Vec::new(),
        })
    }

    fn alive(&self, runner: &mut Runner, bound: Duration) -> bool {
        matches!(
            runner.known_good(&self.probe, bound),
            Ok((crate::liveness::Heard::Modbus, _))
        )
    }

    /// Is the target still there after a case whose due answer did not come? The probe, and where it got
    /// no answer and reruns are on, twice more, as the pre-flight's read is on RTU (noise on the line may
    /// damage the probe or its answer, serial line spec 2.5.1.2) and over Modbus/TCP on a new connection (a
    /// link that dropped the connection under the probe). A target that stopped answering misses all three.
    fn still_there(&self, runner: &mut Runner) -> bool {
        if self.alive(runner, self.bounds.probe_timeout) {
            return true;
        }
        if !self.ask_again {
            return false;
        }
        let bound = self.bounds.probe_timeout.min(Duration::from_secs(1));
        (0..2).any(|_| {
            if runner.framing() == codec::Framing::Tcp {
                let _ = runner.reconnect();
            }
            self.alive(runner, bound)
        })
    }

    /// After a case: if an answer that was due did not come, is the target still there?
    fn after_case(&mut self, runner: &mut Runner, result: &mut CaseResult, log: &mut dyn Write) {
        let Some(mut step) = result.steps.iter().position(|s| {
            s.expected.is_some()
                && s.observed
                    .iter()
                    .any(|o| matches!(o, Received::Silence { .. } | Received::Closed { .. }))
        }) else {
            return;
        };
        if runner.stalled().is_some() {
            // The case stopped after its last step run: that is the one the target went silent after.
            step = result.steps.len() - 1;
        } else if runner.first_unanswered().is_none() {
            // The target answered after that step (a later step of the case, a sentinel): it is there. (A
            // silence a freedom admits, a short request left unanswered, is followed by the case's own
            // known-good read.)
            return;
        }
        // The request that preceded the silence: the first one sent since the last answer (an earlier
        // case's when the target took it silently, as a malformed frame may be), else this step's.
        let preceding = runner.stalled_by().or(runner.first_unanswered()).cloned();
        let started = runner.now();
        match runner.stalled() {
            // The case stopped on a hung connection and a new one is answered (the step says so).
            Some(crate::runner::Stall::Connection) => {
                let (by, sent) = preceding.unwrap_or_else(|| {
                    (
                        result.id.clone(),
                        result.steps[step].sent.clone().unwrap_or_default(),
                    )
                });
                let _ = writeln!(
                    log,
                    "liveness: the connection stopped answering after {by} (request {}); a new connection is answered, the rest of {} was not sent",
                    crate::liveness::hex(&sent),
                    result.id,
                );
                return;
            }
            // The case stopped with nothing answering on a new connection either: known, not asked again.
            Some(crate::runner::Stall::Target) => {}
            None => {
                if self.still_there(runner) {
                    return;
                }
            }
        }
        let (by, sent) = preceding.unwrap_or_else(|| {
            (
                result.id.clone(),
                result.steps[step].sent.clone().unwrap_or_default(),
            )
        });
        let which = if by == result.id {
            "this request".to_string()
        } else {
            format!("this request of {by} (no answer since)")
        };
        let s = &mut result.steps[step];
        s.findings.push(format!(
            "the target stopped answering after {which}: {} (a known-good read got no answer within {:.1} s)",
            crate::liveness::hex(&sent),
            self.bounds.probe_timeout.as_secs_f64()
        ));
        s.verdict = Verdict::Fail;
        match result.expected_deviation.as_mut() {
            // A deviation the expectations file declares for this case (say, a peer whose RTU framer drops
            // a frame it cannot size and the request after it): the silence is part of it; the verdict stays
            // the declared one, the finding is kept and the deviation is recorded as a FAIL.
            Some((actual, _)) => *actual = Verdict::Fail,
            None => result.verdict = Verdict::Fail,
        }
        let _ = writeln!(
            log,
            "liveness: the target stopped answering after {by} (request {}); waiting up to {:.0} s for it to come back",
            crate::liveness::hex(&sent),
            self.bounds.recovery.as_secs_f64()
        );
        // Bounded by the recovery time on the target's clock and by a count.
        let mut back = None;
        for _ in 0..120 {
            let waited = runner.now().saturating_sub(started);
            if waited >= self.bounds.recovery {
                break;
            }
            runner.idle(Duration::from_secs(1).min(self.bounds.recovery - waited));
            let _ = runner.reconnect();
            let left = self
                .bounds
                .recovery
                .saturating_sub(runner.now().saturating_sub(started));
            let bound = self
                .bounds
                .probe_timeout
                .min(left)
                .max(Duration::from_millis(200));
            if self.alive(runner, bound) {
                back = Some(runner.now().saturating_sub(started));
                break;
            }
        }
        match back {
            Some(d) => {
                let note = format!(
                    "the target stopped answering after {by} and recovered after {:.1} s",
                    d.as_secs_f64()
                );
                result.steps[step].findings.push(format!(
                    "the target answered again {:.1} s later (recovered)",
                    d.as_secs_f64()
                ));
                let _ = writeln!(log, "liveness: {note}");
                self.notes.push(note);
            }
            None => {
                let reason = format!(
                    "the target stopped answering after {by} (request {}) and did not answer again within {:.0} s; the remaining cases were SKIPPED",
                    crate::liveness::hex(&sent),
                    self.bounds.recovery.as_secs_f64()
                );
                let _ = writeln!(log, "liveness: {reason}");
                self.dead = Some(reason);
            }
        }
    }
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// What a run collects as its cases complete: counts, verdicts if kept, the first failures, and the failing
/// generated cases to shrink afterwards.
struct Collected {
    tally: Tally,
    verdicts: Vec<(String, Verdict)>,
    failures: Vec<CaseResult>,
    /// Failing generated cases to shrink after the run (the first `max_shrinks`): (index, id).
    to_shrink: Vec<(u64, String)>,
    /// The requirements cited by the cases that ran (not skipped).
    exercised: std::collections::BTreeSet<String>,
    /// The use of each entry of the expectations file.
    expectations: crate::expect::ExpectationTally,
}

impl Collected {
    fn new(expectations: &Expectations) -> Self {
        Self {
            expectations: expectations.tally(),
            tally: Tally::new(),
            verdicts: Vec::new(),
            failures: Vec::new(),
            to_shrink: Vec::new(),
            exercised: std::collections::BTreeSet::new(),
        }
    }

    fn record(&mut self, opts: &Options, case: &Case, result: &CaseResult, gen_index: Option<u64>) {
        self.tally.record(result);
        self.expectations.record(result);
        if result.verdict != Verdict::Skipped {
            self.exercised.extend(case.requirements.iter().cloned());
        }
        if opts.keep_verdicts {
            self.verdicts.push((case.id.clone(), result.verdict));
        }
        if result.verdict == Verdict::Fail {
            if let Some(index) = gen_index
                && self.to_shrink.len() < opts.max_shrinks
            {
                self.to_shrink.push((index, case.id.clone()));
            }
            if self.failures.len() < 200 {
                self.failures.push(result.clone());
            }
        }
    }
}

/// The checks of a run's options against its profile, before anything is opened; the expectations file.
fn check_options(
    opts: &Options,
    profile: &Profile,
    cfg: &RunConfig,
    log: &mut dyn Write,
) -> Result<Expectations, SessionError> {
    if !opts.faults.0.is_empty() && !opts.target.is_sim() {
        return Err(SessionError::FaultNeedsSim);
    }
    let expectations = match &opts.expect {
        Some(p) => Expectations::load(p)?,
        None => Expectations::default(),
    };
    let [lo, hi] = profile.device.unit_ids;
    let broadcast = profile.device.broadcast && cfg.unit == 0;
    if !((lo..=hi).contains(&cfg.unit) || broadcast) {
        let _ = writeln!(
            log,
            "warning: unit {} is outside the profile's unit ids {lo}..={hi}",
            cfg.unit
        );
    }
    if let Some(snap) = &opts.snapshot
        && !snap.update
        && !snap.path.is_file()
    {
        return Err(SessionError::NoSnapshot(snap.path.clone()));
    }
    check_foreign(opts, profile, cfg.unit)?;
    Ok(expectations)
}

/// `--foreign-address` may not be an address of the drive's own (the unit's, or a double-axis SD2x's other
/// axis's: its manual, line 183).
pub(crate) fn check_foreign(
    opts: &Options,
    profile: &Profile,
    unit: u8,
) -> Result<(), SessionError> {
    match opts.foreign {
        Some(f) if f == unit => Err(SessionError::ForeignIsOwn(f, "")),
        Some(f)
            if profile.device.id == "sd2x"
                && f == crate::cases::catalog::rtu::sd2x_partner(unit) =>
        {
            Err(SessionError::ForeignIsOwn(
                f,
                " (a double-axis SD2x's other axis: its manual, line 183)",
            ))
        }
        _ => Ok(()),
    }
}

/// The header of every report of the run.
fn run_info(
    opts: &Options,
    profile: &Profile,
    runner: &Runner,
    generator: Option<&Generator>,
) -> RunInfo {
    RunInfo {
        target: opts.target.to_string(),
        profile: profile.device.id.clone(),
        transport: match (&opts.target, runner.framing()) {
            (TargetUrl::RtuOverTcp { .. }, _) => crate::reports::Transport::RtuOverTcp,
            (_, Framing::Rtu) => crate::reports::Transport::Rtu,
            _ => crate::reports::Transport::Tcp,
        },
        server_port: runner.target().server_port(),
        started_unix_ms: unix_ms(),
        command_line: opts.command_line.clone(),
        seed: generator.map(Generator::seed).or(opts.seed),
        shuffle: opts.shuffle,
        harness_version: env!("CARGO_PKG_VERSION").to_string(),
        report_dir: opts.report_dir.clone(),
    }
}

/// The snapshot writer of a run that has `--snapshot`.
fn open_snapshot(
    opts: &Options,
    info: &RunInfo,
    framing: Framing,
    unit: u8,
) -> Result<Option<SnapshotWriter>, SessionError> {
    let Some(s) = &opts.snapshot else {
        return Ok(None);
    };
    let dir = snapshot_dir(&s.path)?;
    let header = SnapshotHeader {
        profile: info.profile.clone(),
        framing: if framing == Framing::Rtu {
            "rtu"
        } else {
            "tcp"
        }
        .into(),
        unit,
        seed: info.seed,
    };
    Ok(Some(SnapshotWriter::new(&header, &dir)))
}

/// A skipped case's result.
fn skipped(case: &Case, reason: String) -> CaseResult {
    CaseResult::skipped(&case.id, reason)
}

/// Run the selected catalog. `progress` is called after each case with (done, total, id, verdict).
pub fn run(
    opts: &Options,
    log: &mut dyn Write,
    interrupt: &AtomicBool,
    progress: &mut dyn FnMut(usize, usize, &str, Verdict),
) -> Result<RunOutcome, SessionError> {
    let profile = resolve_profile(opts, log)?;
    let mut cfg = config(opts, &profile);
    let expectations = check_options(opts, &profile, &cfg, log)?;
    // One seed for the whole run, chosen before anything is generated.
    let mut opts = opts.clone();
    if opts.generated > 0 && opts.seed.is_none() {
        opts.seed = Some(generated::clock_seed());
    }
    let opts = &opts;
    let requirements = requirements_of(&opts.corpus)?;
    // The plan is checked before the target is opened (a corpus error is said first), and made again once
    // the line survey has chosen where another slave's frames go.
    catalog_plan(opts, &profile, &requirements)?;
    let mut runner = open_checked_runner(opts, &profile, &mut cfg, &expectations, log)?;
    let opts = &Options {
        foreign: survey_line(opts, &profile, cfg.unit, &mut runner, log)?,
        ..opts.clone()
    };
    let planned = catalog_plan(opts, &profile, &requirements)?;
    let generator = generator(opts, &profile);
    let mut watch = Watch::new(opts, &profile);
    if let Some(w) = watch.as_ref() {
        runner.watch_mid_case(w.probe.clone(), w.bounds.probe_timeout);
    }
    let framing = runner.framing();
    let info = run_info(opts, &profile, &runner, generator.as_ref());
    let mut reports = match &opts.report_dir {
        Some(d) => Some(Reports::create(d, &info)?),
        None => None,
    };
    let mut snap = open_snapshot(opts, &info, framing, cfg.unit)?;
    let total = planned.len() + usize::try_from(opts.generated).unwrap_or(usize::MAX);
    let _ = writeln!(
        log,
        "modbus-harness: {} with profile `{}` (unit {}), {} cases",
        runner.target().describe(),
        profile.device.id,
        cfg.unit,
        total
    );
    if let Some(seed) = opts.shuffle {
        let _ = writeln!(
            log,
            "order: {} catalog case(s) shuffled with seed {seed} (replay with --shuffle {seed}):",
            planned.len()
        );
        for (i, (c, _)) in planned.iter().enumerate() {
            let _ = writeln!(log, "  {:>4} {}", i + 1, c.id);
        }
    }
    if let Some(g) = &generator {
        let _ = writeln!(
            log,
            "generated: {} case(s), seed {} (replay with --seed {})",
            opts.generated,
            g.seed(),
            g.seed()
        );
    }
    let mut collected = Collected::new(&expectations);
    let mut link = crate::link::LinkTally::default();
    let started = Instant::now();
    let mut banner_done = cfg.is_sim;
    let mut interrupted = false;
    let policy = &cfg;
    let generated_cases = generator.iter().flat_map(|g| {
        (0..opts.generated).filter_map(move |i| {
            let c = g.case(i);
            selected(&c, &opts.include, &opts.exclude).then(|| {
                let skip = skip_reason(&c, policy, framing);
                (c, skip, Some(i))
            })
        })
    });
    let cases = planned
        .iter()
        .map(|(c, s)| (c.clone(), s.clone(), None))
        .chain(generated_cases);
    let mut keeper = keeper(opts, &profile, &cfg);
    let mut checkpointed = false;
    // An error of the target mid-run: the drive is put back (as far as it answers) before it is returned.
    let mut failed: Option<SessionError> = None;
    for (i, (case, skip, gen_index)) in cases.enumerate() {
        if interrupt.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let mut after: Option<crate::restore::Touched> = None;
        let dead = watch.as_ref().and_then(|w| w.dead.clone());
        let result = match (skip, dead) {
            (Some(reason), _) => skipped(&case, reason),
            (None, Some(dead)) => skipped(&case, format!("not run: {dead}")),
            (None, None) => {
                if !banner_done && case.has(Tag::Write) {
                    banner_done = true;
                    write_banner(log, &planned, &profile, opts.generated);
                }
                let mut unrestorable = None;
                if let Some(k) = keeper.as_mut() {
                    // Before the first case that leaves the drive changed for good: everything put back
                    // and verified while the drive still answers as it did.
                    if case.has(Tag::Irreversible) && k.armed() && !checkpointed {
                        checkpointed = true;
                        let clean = k.checkpoint(&mut runner, &profile);
                        let _ = writeln!(
                            log,
                            "leave as found: before the cases that leave the drive changed for good, every kept parameter {}",
                            if clean {
                                "put back and verified"
                            } else {
                                "put back as far as it would go (see the end of the run)"
                            }
                        );
                    }
                    let touched = k.touched(&case);
                    // The snapshot comes before the first case that may write anything.
                    if (case.has(Tag::Write) || !touched.is_empty()) && !k.armed() {
                        k.take_snapshot(&mut runner)?;
                        log_snapshot(log, k);
                        align_reference(log, k, &mut runner, &profile);
                    }
                    unrestorable = k.unrestorable(&case);
                    if !touched.is_empty() && unrestorable.is_none() {
                        after = Some(touched);
                    }
                    // A save to NVM stores the settings as found, whatever the cases before changed.
                    if unrestorable.is_none() {
                        k.note_case(&case);
                        k.before_save(&mut runner, &case, &profile);
                    }
                }
                match unrestorable.map_or_else(
                    || {
                        let touched = after.as_ref();
                        let keeper = keeper.as_mut().filter(|_| touched.is_some());
                        crate::link::run_over_link(
                            &mut runner,
                            keeper,
                            &case,
                            &profile,
                            &cfg,
                            &mut link,
                        )
                    },
                    |why| Ok(skipped(&case, why)),
                ) {
                    Ok(mut r) => {
                        if let Some(w) = watch.as_mut() {
                            w.after_case(&mut runner, &mut r, log);
                        }
                        r
                    }
                    Err(e) => {
                        failed = Some(e.into());
                        break;
                    }
                }
            }
        };
        // A report or snapshot that cannot be written ends the run, but like an error of the target: after
        // this case's writes are put back, and with the drive restored at the end (`failed`), not by
        // returning at once, which would leave the drive as the case left it.
        let mut unwritten: Option<SessionError> = None;
        if let Some(w) = snap.as_mut()
            && let Err(e) = w.add(&result)
        {
            unwritten = Some(e.into());
        }
        progress(i + 1, total, &case.id, result.verdict);
        collected.record(opts, &case, &result, gen_index);
        // A guarded status flag or input that the case only tried to write (refused) is not put back from now on.
        if let (Some(k), Some(t)) = (keeper.as_ref(), after.as_mut()) {
            *t = k.taken(&case, runner.refused_writes());
        }
        let id = after.as_ref().map(|_| case.id.clone());
        // The case and its result go to the report writer as they are, not copied (the copy was the run
        // loop's share of what `--report` cost; BENCHMARKS.md, issue 17 item 3).
        if let Some(r) = reports.as_mut()
            && let Err(e) = r.case_owned(case, result)
            && unwritten.is_none()
        {
            unwritten = Some(e.into());
        }
        // A target that stopped answering is put back at the end, as far as it answers again then.
        let gone = watch.as_ref().is_some_and(|w| w.dead.is_some());
        if let (Some(k), Some(touched), Some(id), false) = (keeper.as_mut(), after, id, gone)
            && let Err(e) = k.after_case(&mut runner, &id, &touched, &profile)
        {
            failed = Some(e.into());
            break;
        }
        if let Some(e) = unwritten {
            failed = Some(e);
            break;
        }
    }
    if let Some(e) = failed {
        let account = keeper.as_mut().map(|k| k.finish(&mut runner, &profile));
        // The reports are completed with what ran and why the run ended, then the error is returned.
        if let Some(r) = reports {
            let mut summary = collected.tally.summary(false, started.elapsed());
            summary.ended = Some(format!("stopped on an error: {e}"));
            summary.liveness = watch.map(|w| w.notes).unwrap_or_default();
            summary.link = link.note();
            summary.leave_as_found = account.clone();
            if let Err(re) = r.finish(&summary) {
                let _ = writeln!(log, "cannot complete the reports: {re}");
            }
        }
        if let Some(account) = account {
            for line in account.lines() {
                let _ = writeln!(log, "{line}");
            }
            if !account.clean() {
                return Err(SessionError::LeftChanged {
                    error: Box::new(e),
                    unrestored: account.unrestored.len(),
                    journal: account.journal,
                });
            }
        }
        return Err(e);
    }
    let mut shrunk = Vec::new();
    if let (Some(limits), Some(g), false) = (&opts.shrink, &generator, interrupted) {
        for (index, id) in std::mem::take(&mut collected.to_shrink) {
            if interrupt.load(Ordering::SeqCst) {
                break;
            }
            let report = shrink_one(
                opts,
                &profile,
                &cfg,
                &expectations,
                &mut runner,
                g,
                index,
                id,
                limits,
            );
            log_shrink(log, &report);
            shrunk.push(report);
        }
    }
    log_silences(log, &runner);
    let link_note = link.note();
    if let Some(n) = &link_note {
        let _ = writeln!(log, "{n}");
    }
    // At the end, interrupted or not: everything that differs from the snapshot is put back and verified.
    let leave_as_found = keeper.as_mut().map(|k| k.finish(&mut runner, &profile));
    let mut summary = collected.tally.summary(interrupted, started.elapsed());
    summary.leave_as_found = leave_as_found;
    if let Some(w) = watch {
        summary.ended = w.dead;
        summary.liveness = w.notes;
    }
    summary.link = link_note;
    if interrupted && summary.ended.is_none() {
        summary.ended = Some(
            "interrupted (Ctrl-C or SIGTERM): the cases after the last one reported were not run"
                .into(),
        );
    }
    summary.choices = runner.choices().choices().cloned().collect();
    summary.coverage = requirements
        .coverage(collected.exercised.iter().map(String::as_str))
        .into_iter()
        .filter(|c| {
            // The specifications of the transport in use, and the profile's own manual.
            let transport_doc = match c.document.as_str() {
                "tcp" => framing == Framing::Tcp,
                "serial" => framing == Framing::Rtu,
                _ => true,
            };
            transport_doc
                && requirements.document(&c.document).is_some_and(|d| {
                    d.kind == drives::requirements::DocKind::Spec
                        || d.profiles.contains(&profile.device.id)
                })
        })
        .collect();
    if let Some(r) = reports {
        r.finish(&summary)?;
    }
    let snapshot = match (snap, &opts.snapshot) {
        (Some(mut w), Some(s)) => {
            w.add_choices(runner.choices().choices())?;
            Some(finish_snapshot(w, s)?)
        }
        _ => None,
    };
    Ok(RunOutcome {
        summary,
        info,
        verdicts: collected.verdicts,
        failures: collected.failures,
        shrunk,
        snapshot,
        expectations: collected.expectations.finish(),
    })
}

/// The keeper of a run that leaves the drive as found: real targets, unless nothing may be written.
pub fn keeper(
    opts: &Options,
    profile: &Profile,
    cfg: &RunConfig,
) -> Option<crate::restore::Keeper> {
    if !opts.leave_as_found || opts.target.is_sim() || opts.safety.read_only {
        return None;
    }
    let scratch = opts.journal.is_none() && opts.report_dir.is_none();
    let journal = opts
        .journal
        .clone()
        .unwrap_or_else(|| match &opts.report_dir {
            Some(d) => d.join("journal.json"),
            None => {
                // One name per run: runs in one process (a test binary, an embedding tool) must not
                // share a journal, and one's clean exit must not remove another's.
                static RUNS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
                let n = RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                std::env::temp_dir().join(format!(
                    "modbus-harness-journal-{}-{n}.json",
                    std::process::id()
                ))
            }
        });
    // The profile as `restore` must load it again: a corpus name, or a file by its absolute path.
    let profile_name = match &opts.profile {
        Some(p) if p != "auto" && drives::corpus::is_profile_path(p) => {
            std::fs::canonicalize(p).map_or_else(|_| p.clone(), |a| a.display().to_string())
        }
        Some(p) if p != "auto" => p.clone(),
        _ => profile.device.id.clone(),
    };
    let keeper = crate::restore::Keeper::new(
        crate::restore::inventory(profile, &opts.safety),
        opts.target.to_string(),
        profile_name,
        cfg.unit,
        Some(journal),
    )
    .watch_status(profile);
    Some(if scratch {
        keeper.scratch_journal()
    } else {
        keeper
    })
}

/// The reference drive takes the parameters the target was found with, so that a drive found off its
/// factory values is judged against a reference holding the same values (a generated write that the drive
/// refuses because of another parameter's value is then refused by the reference too).
pub fn align_reference(
    log: &mut dyn Write,
    k: &crate::restore::Keeper,
    runner: &mut crate::runner::Runner,
    profile: &Profile,
) {
    runner.learn_live(&k.account().live);
    let left = k.align(&mut runner.reference(), profile);
    if !left.is_empty() {
        let _ = writeln!(
            log,
            "leave as found: the reference drive did not take {} of the values found (it judges those from its own): {}",
            left.len(),
            left.iter()
                .map(|u| u.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
}

fn log_snapshot(log: &mut dyn Write, k: &crate::restore::Keeper) {
    let a = k.account();
    let _ = writeln!(
        log,
        "leave as found: read {} parameter(s) before the first write ({} left out); journal {}",
        a.kept,
        a.excluded.len(),
        a.journal
            .as_ref()
            .map_or_else(|| "none".to_string(), |p| p.display().to_string())
    );
    for e in &a.unwritable {
        let _ = writeln!(
            log,
            "leave as found: {} is written by no case: {}",
            e.name, e.reason
        );
    }
    if let Some(state) = k.found_state() {
        let _ = writeln!(
            log,
            "leave as found: the drive was found {state}; the end of the run says whether it is left so"
        );
    }
}

/// The directory of a snapshot file (created when the file is to be written).
fn snapshot_dir(path: &std::path::Path) -> Result<PathBuf, SessionError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(|source| SessionError::CreateDir {
        path: dir.clone(),
        source,
    })?;
    Ok(dir)
}

/// Write the snapshot, or write it aside and compare it with the file.
fn finish_snapshot(
    w: SnapshotWriter,
    s: &SnapshotOptions,
) -> Result<SnapshotOutcome, SessionError> {
    if s.update {
        w.finish(&s.path)?;
        return Ok(SnapshotOutcome {
            path: s.path.clone(),
            written: true,
            drift: None,
        });
    }
    let dir = snapshot_dir(&s.path)?;
    let fresh = dir.join(format!(
        ".{}.{}.new",
        s.path
            .file_name()
            .map_or_else(|| "snapshot".into(), |n| n.to_string_lossy()),
        std::process::id()
    ));
    w.finish(&fresh)?;
    let drift = snapshot::compare(&s.path, &fresh);
    let _ = std::fs::remove_file(&fresh);
    Ok(SnapshotOutcome {
        path: s.path.clone(),
        written: false,
        drift: Some(drift?),
    })
}

/// Shrink one failing generated case: against a fresh in-process drive per candidate on `sim:`, against
/// the run's own connection otherwise; write the reproducer when a directory is set.
#[allow(clippy::too_many_arguments)]
fn shrink_one(
    opts: &Options,
    profile: &Profile,
    cfg: &RunConfig,
    expectations: &Expectations,
    runner: &mut Runner,
    g: &Generator,
    index: u64,
    id: String,
    limits: &ShrinkLimits,
) -> ShrinkReport {
    let framing = runner.framing();
    // A candidate the safety policy would skip is not run: it counts as not failing.
    let result = if opts.target.is_sim() {
        shrink::shrink(g, index, limits, |case| {
            if let Some(reason) = skip_reason(case, cfg, framing) {
                return Ok::<_, SessionError>(skipped(case, reason));
            }
            Ok(open_runner(opts, profile, cfg, expectations)?.run_case(case)?)
        })
    } else {
        shrink::shrink(g, index, limits, |case| {
            if let Some(reason) = skip_reason(case, cfg, framing) {
                return Ok::<_, SessionError>(skipped(case, reason));
            }
            Ok(runner.run_case(case)?)
        })
    };
    let mut report = ShrinkReport {
        id,
        shrunk: None,
        file: None,
        note: None,
    };
    match result {
        Err(e) => report.note = Some(format!("shrinking stopped: {e}")),
        Ok(None) => {
            report.note = Some(
                "does not FAIL when run again alone (it needs the state earlier cases left): not shrunk"
                    .into(),
            )
        }
        Ok(Some(s)) => {
            if let Some(dir) = &opts.regressions_dir {
                let origin = Origin {
                    case: report.id.clone(),
                    seed: g.seed(),
                    index,
                    target: opts.target.to_string(),
                    faults: opts.faults.0.iter().map(|f| f.name().to_string()).collect(),
                    harness: env!("CARGO_PKG_VERSION").to_string(),
                    original_steps: s.original.steps.len(),
                    shrink_steps: s.steps,
                    findings: s.findings.clone(),
                };
                match regressions::write_regression(dir, &profile.device.id, &s, origin) {
                    Ok(p) => report.file = Some(p),
                    Err(e) => report.note = Some(format!("cannot write the reproducer: {e}")),
                }
            }
            report.shrunk = Some(s);
        }
    }
    report
}

fn log_shrink(log: &mut dyn Write, r: &ShrinkReport) {
    match &r.shrunk {
        Some(s) => {
            let (exchanges, largest) = shrink::case_size(&s.case);
            let _ = writeln!(
                log,
                "shrunk {} -> {}: {} step(s), {exchanges} exchange(s), largest PDU {largest} bytes ({} candidates run, {:.1} s, {:?})",
                r.id,
                s.case.id,
                s.case.steps.len(),
                s.steps,
                s.elapsed.as_secs_f64(),
                s.stop
            );
            for f in s.findings.iter().take(3) {
                let _ = writeln!(log, "     {f}");
            }
        }
        None => {
            let _ = writeln!(log, "not shrunk {}", r.id);
        }
    }
    if let Some(p) = &r.file {
        let _ = writeln!(log, "     reproducer: {}", p.display());
    }
    if let Some(n) = &r.note {
        let _ = writeln!(log, "     {n}");
    }
}

/// Before the first write on real hardware: say what will be written.
fn write_banner(
    log: &mut dyn Write,
    planned: &[(Case, Option<String>)],
    profile: &Profile,
    generated: u64,
) {
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
    if generated > 0 {
        let _ = writeln!(
            log,
            "  plus the generated cases that write, tagged by the same policy (list them with --dry-run)"
        );
    }
    let _ = writeln!(
        log,
        "Values changed are read first and written back where the case can (read, write, restore); before the\nfirst write every parameter the profile lets a client write back is read and journaled, and whatever differs\nis restored after each writing case and at the end.\n"
    );
}

/// `restore --journal FILE`: put the drive a journal describes back as it was before the run's first write
/// (on `target`, or the journal's), verify by reading, and record the outcome in the journal.
pub fn restore_journal(
    path: &std::path::Path,
    target: Option<TargetUrl>,
    corpus: Corpus,
    timing: Timing,
    connect_timeout: Duration,
    log: &mut dyn Write,
) -> Result<crate::restore::Account, SessionError> {
    use crate::restore::{Journal, JournalError};
    let mut journal = Journal::load(path).map_err(crate::restore::SnapshotError::from)?;
    let target = match target {
        Some(t) => t,
        None => TargetUrl::parse(&journal.target).map_err(|e| {
            crate::restore::SnapshotError::from(JournalError::Format {
                path: path.to_path_buf(),
                reason: format!("target `{}`: {e}", journal.target),
            })
        })?,
    };
    let mut opts = Options::new(target);
    opts.profile = Some(journal.profile.clone());
    opts.corpus = corpus;
    opts.unit = Some(journal.unit);
    opts.timing = timing;
    opts.connect_timeout = connect_timeout;
    let profile = resolve_profile(&opts, log)?;
    let cfg = config(&opts, &profile);
    let mut runner = open_runner(&opts, &profile, &cfg, &Expectations::default())?;
    let items = journal.kept();
    let snapshot = journal.snapshot();
    let _ = writeln!(
        log,
        "restore: {} parameter(s) of `{}` (unit {}) from {} on {}",
        items.len(),
        journal.profile,
        journal.unit,
        path.display(),
        runner.target().describe()
    );
    let mut counting = crate::restore::Counting {
        link: &mut runner,
        sent: 0,
    };
    let (writes, unrestored) =
        crate::restore::restore(&mut counting, &items, &snapshot, Some(&profile))?;
    let requests = counting.sent;
    journal.state = if unrestored.is_empty() {
        "restored"
    } else {
        "unrestored"
    }
    .into();
    journal.unrestored.clone_from(&unrestored);
    journal.updated_unix_ms = unix_ms();
    journal
        .save(path)
        .map_err(crate::restore::SnapshotError::from)?;
    Ok(crate::restore::Account {
        kept: items.len(),
        excluded: journal.excluded.clone(),
        restore_writes: writes,
        requests,
        unrestored,
        snapshot_taken: true,
        journal: Some(path.to_path_buf()),
        unwritable: Vec::new(),
        verified_before_irreversible: Vec::new(),
        left_faulted: None,
        fault_cleared: None,
        error_flag_changed: None,
        live: Vec::new(),
        program_ended: None,
    })
}
