//! A live fuzz campaign against an endpoint: generated and mutated requests, a liveness probe every few
//! cases, detection of a drive that stops answering, answers wrongly or sends malformed frames, and a
//! reproducer for each finding (replayed, and shrunk on `sim:` targets where a fresh drive can be had).

use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::cases::catalog::known_good_read;
use crate::cases::generated::Generator;
use crate::cases::regressions::{Origin, RegressionFile, file_stem};
use crate::cases::{Case, Compare, Level, Outgoing, Step, Verdict};
use crate::expect::Expectations;
use crate::link::{LinkTally, run_over_link as over_link};
use crate::runner::skip_reason;
use crate::session::{Options, SessionError, config, open_runner, resolve_profile};

/// How a campaign runs.
#[derive(Clone, Debug)]
pub struct CampaignOptions {
    /// Target, profile, unit, timeouts, safety flags and (for `sim:`) faults.
    pub base: Options,
    /// Stop after this long.
    pub duration: Duration,
    /// Stop after this many cases, if given.
    pub max_cases: Option<u64>,
    pub seed: u64,
    /// A liveness probe after every this many cases.
    pub probe_every: u64,
    /// Go on after a non-fatal finding (a FAIL) instead of stopping at the first.
    pub keep_going: bool,
    /// Where reproducers go: `<dir>/<profile>/<name>.toml`.
    pub regressions: PathBuf,
    /// Against anything but `sim:`, send generated writes (with a banner first); without it the campaign
    /// sends reads only. Motion and destructive writes still need their own flags (`base.safety`).
    pub allow_writes: bool,
    /// With `keep_going`: stop after this many distinct findings (by signature; repeats are counted, not
    /// written again).
    pub max_findings: usize,
    /// Modbus/TCP to a real target: put up to this many generated reads in flight at once where the target
    /// answers a burst of that many known-good reads sent in one write (see
    /// [`crate::runner::Runner::discover_pipelining`]); 1 sends one request at a time.
    pub pipeline: usize,
}

/// Why the campaign does not send `case` (already rated by the classifier), if it does not: the run's
/// safety policy ([`skip_reason`]), and, against a real target, no write without `allow_writes`.
pub fn campaign_skip(
    case: &Case,
    cfg: &crate::runner::RunConfig,
    framing: codec::Framing,
    allow_writes: bool,
) -> Option<String> {
    if let Some(r) = skip_reason(case, cfg, framing) {
        return Some(r);
    }
    (!cfg.is_sim && !allow_writes && case.has(crate::cases::Tag::Write))
        .then(|| "writes, and fuzz sends writes to a real target only with --allow-writes".into())
}

/// What kind of thing went wrong.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FindingKind {
    /// The drive stopped answering the liveness probe: fatal, the campaign ends.
    StoppedAnswering,
    /// The liveness probe was answered, but its answer FAILs (malformed, or not the answer due): the drive
    /// is alive yet answers a valid read wrongly. The campaign ends, as every later probe would say so.
    ProbeFails,
    /// A generated case FAILed (wrong, malformed or missing answer) while the drive stayed alive.
    Fail,
}

/// One finding of a campaign.
#[derive(Clone, Debug)]
pub struct CampaignFinding {
    pub kind: FindingKind,
    /// The case that failed (for a stop: the first case after the last good probe).
    pub case_id: String,
    pub findings: Vec<String>,
    /// The reproducer: the cases since the last good probe, then the probe.
    pub reproducer: Case,
    /// Where it was written.
    pub file: Option<PathBuf>,
    /// On `sim:`: the reproducer FAILs on a fresh faulted drive and PASSes on a healthy one.
    pub replayed: Option<bool>,
}

/// The end of a campaign.
#[derive(Clone, Debug)]
pub struct CampaignOutcome {
    pub cases: u64,
    pub probes: u64,
    /// Requests sent to the target in all: the cases', the sentinels, the probes, the restore's.
    pub requests: u64,
    pub elapsed: Duration,
    pub findings: Vec<CampaignFinding>,
    /// Findings that repeated an earlier one's signature (same kind, same case family, same first finding
    /// with the numbers left out): counted, no reproducer written.
    pub repeats: u64,
    /// Why the campaign ended.
    pub stopped: String,
    pub seed: u64,
    /// With `--allow-writes` against a real drive: what was read before the first write and put back.
    pub leave_as_found: Option<crate::restore::Account>,
    /// How many requests were put in flight at once (at the start; 1 when one at a time), and why.
    pub pipelining: crate::runner::Pipelining,
    /// Cases whose request went out with others in flight.
    pub pipelined: u64,
}

impl CampaignOutcome {
    /// Cases per second over the whole campaign.
    pub fn exec_per_sec(&self) -> f64 {
        self.cases as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }

    /// Requests sent to the target per second over the whole campaign (a case sends one or more).
    pub fn requests_per_sec(&self) -> f64 {
        self.requests as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

fn probe_case(profile: &drives::profile::Profile) -> Case {
    Case {
        id: "fuzz/liveness-probe".into(),
        title: "liveness probe".into(),
        reference: "Modbus Application Protocol Specification V1.1b3, section 6".into(),
        requirement:
            "After any sequence of requests, valid or not, the drive still answers a valid read."
                .into(),
        level: Level::Must,
        tags: vec![],
        steps: vec![Step::Exchange {
            send: Outgoing::Pdu(known_good_read(profile)),
            compare: Compare::Structure,
            capture: None,
            note: "liveness probe".into(),
        }],
        requirements: Vec::new(),
        freedoms: Vec::new(),
    }
}

/// Concatenate cases into one reproducer ending with the liveness probe.
fn reproducer(name: &str, history: &[Case], probe: &Case, requirement: &str) -> Case {
    let mut steps = Vec::new();
    let mut tags = Vec::new();
    for c in history {
        steps.extend(c.steps.iter().cloned());
        for t in &c.tags {
            if !tags.contains(t) {
                tags.push(*t);
            }
        }
    }
    steps.extend(probe.steps.iter().cloned());
    Case {
        id: name.to_string(),
        title: format!(
            "fuzz finding: {} case(s) then a liveness probe",
            history.len()
        ),
        reference: probe.reference.clone(),
        requirement: requirement.to_string(),
        level: Level::Must,
        tags,
        steps,
        requirements: Vec::new(),
        freedoms: Vec::new(),
    }
}

/// Run a case on a fresh drive of the run's target (sim: only); None when no fresh drive can be had.
fn verdict_on_fresh(opts: &Options, case: &Case) -> Option<Verdict> {
    if !opts.target.is_sim() {
        return None;
    }
    let profile = resolve_profile(opts, &mut std::io::sink()).ok()?;
    let cfg = config(opts, &profile);
    let mut runner = open_runner(opts, &profile, &cfg, &Expectations::default()).ok()?;
    runner.run_case(case).ok().map(|r| r.verdict)
}

/// Remove history cases one at a time while the reproducer still FAILs on a fresh drive (bounded).
fn shrink_history(
    opts: &Options,
    history: Vec<Case>,
    probe: &Case,
    requirement: &str,
    deadline: Instant,
) -> Vec<Case> {
    let mut h = history;
    let mut i = 0;
    while i < h.len() && Instant::now() < deadline && h.len() > 1 {
        let mut candidate = h.clone();
        candidate.remove(i);
        let r = reproducer("fuzz/candidate", &candidate, probe, requirement);
        if verdict_on_fresh(opts, &r) == Some(Verdict::Fail) {
            h = candidate;
        } else {
            i += 1;
        }
    }
    h
}

/// What the loop saw, before it becomes a reproducer.
struct Detected {
    kind: FindingKind,
    case_id: String,
    findings: Vec<String>,
    history: Vec<Case>,
}

fn record(
    opts: &CampaignOptions,
    profile: &str,
    d: Detected,
    probe: &Case,
    log: &mut dyn Write,
) -> CampaignFinding {
    let Detected {
        kind,
        case_id,
        findings,
        history,
    } = d;
    let case_id = case_id.as_str();
    let requirement = match kind {
        FindingKind::StoppedAnswering => {
            "After this sequence the drive still answers a valid read (it stopped answering)."
        }
        FindingKind::ProbeFails => {
            "After this sequence the drive answers a valid read correctly (its answer to it FAILs)."
        }
        FindingKind::Fail => "The drive answers this sequence as the reference drive does.",
    };
    let original = history.len();
    let history = shrink_history(
        &opts.base,
        history,
        probe,
        requirement,
        Instant::now() + Duration::from_secs(30),
    );
    let name = format!("fuzz-{}-{}", opts.seed, file_stem(case_id));
    let case = reproducer(
        &format!("regression/{profile}/{name}"),
        &history,
        probe,
        requirement,
    );
    let replayed = if opts.base.target.is_sim() {
        let faulted = verdict_on_fresh(&opts.base, &case);
        let mut healthy = opts.base.clone();
        healthy.faults = drives::FaultSet::none();
        let ok = verdict_on_fresh(&healthy, &case);
        Some(faulted == Some(Verdict::Fail) && ok == Some(Verdict::Pass))
    } else {
        None
    };
    let origin = Origin {
        case: case_id.to_string(),
        seed: opts.seed,
        index: 0,
        target: opts.base.target.to_string(),
        faults: opts
            .base
            .faults
            .0
            .iter()
            .map(|f| f.name().to_string())
            .collect(),
        harness: env!("CARGO_PKG_VERSION").to_string(),
        original_steps: original,
        shrink_steps: original - history.len(),
        findings: findings.clone(),
    };
    let dir = opts.regressions.join(profile);
    let path = dir.join(format!("{name}.toml"));
    let file = std::fs::create_dir_all(&dir)
        .and_then(|_| {
            std::fs::write(
                &path,
                RegressionFile::from_case(&case, Some(origin)).to_toml(),
            )
        })
        .map(|_| path.clone());
    match &file {
        Ok(p) => {
            let _ = writeln!(
                log,
                "  reproducer: {} ({} case(s) of {original} kept)",
                p.display(),
                history.len()
            );
        }
        Err(e) => {
            let _ = writeln!(log, "  reproducer not written to {}: {e}", path.display());
        }
    }
    CampaignFinding {
        kind,
        case_id: case_id.to_string(),
        findings,
        reproducer: case,
        file: file.ok(),
        replayed,
    }
}

/// Run a campaign until the duration, the case limit, an interrupt, or the first fatal finding.
pub fn campaign(
    opts: &CampaignOptions,
    log: &mut dyn Write,
    interrupt: &AtomicBool,
    mut tick: impl FnMut(u64, f64, usize),
) -> Result<CampaignOutcome, SessionError> {
    let base = &opts.base;
    let profile = resolve_profile(base, log)?;
    if !base.faults.0.is_empty() && !base.target.is_sim() {
        return Err(SessionError::FaultNeedsSim);
    }
    let mut cfg = config(base, &profile);
    crate::session::check_foreign(base, &profile, cfg.unit)?;
    let mut runner = crate::session::open_checked_runner(
        base,
        &profile,
        &mut cfg,
        &Expectations::default(),
        log,
    )?;
    let foreign = crate::session::survey_line(base, &profile, cfg.unit, &mut runner, log)?;
    if !cfg.is_sim && !cfg.safety.read_only && opts.allow_writes {
        let allowed = |yes: bool| if yes { "ALLOWED" } else { "not sent" };
        let _ = writeln!(
            log,
            "\n*** FUZZ WRITES AHEAD: generated writes will be sent to this {} ({}) ***\n  motion writes: {} (--allow-motion), destructive writes: {} (--allow-destructive)\n  the drive's parameters are read first (journaled), put back after each writing case and at the end, and verified\n",
            profile.device.name,
            runner.target().describe(),
            allowed(cfg.safety.allow_motion),
            allowed(cfg.safety.allow_destructive),
        );
    } else if !cfg.is_sim {
        let _ = writeln!(
            log,
            "fuzz: read requests only (no write function code is sent{})",
            if cfg.safety.read_only {
                ": --read-only"
            } else {
                "; --allow-writes sends generated writes"
            }
        );
    }
    let _ = writeln!(
        log,
        "fuzz: {} with profile `{}`, seed {}, probe every {} cases, for {:?}",
        runner.target().describe(),
        profile.device.id,
        opts.seed,
        opts.probe_every,
        opts.duration
    );
    // With --allow-writes against a real drive: the drive's parameters are read before the first write
    // (journaled), the reference takes them, what a case changed is put back after it, and everything at
    // the end, on every way out (as `run` does).
    let mut keeper = if opts.allow_writes {
        crate::session::keeper(base, &profile, &cfg)
    } else {
        None
    };
    let outcome = fuzz_loop(
        opts,
        &profile,
        foreign,
        &cfg,
        &mut runner,
        keeper.as_mut(),
        log,
        interrupt,
        &mut tick,
    );
    let Some(k) = keeper.as_mut() else {
        return outcome;
    };
    let account = k.finish(&mut runner, &profile);
    for line in account.lines() {
        let _ = writeln!(log, "{line}");
    }
    match outcome {
        Err(e) if !account.clean() => Err(SessionError::LeftChanged {
            error: Box::new(e),
            unrestored: account.unrestored.len(),
            journal: account.journal,
        }),
        Err(e) => Err(e),
        Ok(mut o) => {
            o.leave_as_found = Some(account);
            Ok(o)
        }
    }
}

/// A finding's signature: its kind, the family of the case (the generated id without seed and index) and
/// its first finding with every digit left out, so that the same bug met with other addresses or values
/// is one finding.
fn signature(kind: FindingKind, case_id: &str, first: &str) -> String {
    let family = case_id.rsplit('/').next().unwrap_or(case_id);
    let text: String = first.chars().filter(|c| !c.is_ascii_hexdigit()).collect();
    format!("{kind:?} {family} {text}")
}

/// True when any bytes came back in the case: a frame, garbage, part of a frame before a silence or a
/// close, or a late answer to an earlier request (on the wire, not taken for a step's answer).
fn heard_anything(result: &crate::observe::CaseResult) -> bool {
    use crate::targets::Received;
    result
        .wire
        .iter()
        .any(|w| w.dir == crate::observe::Dir::Rx && !w.bytes.is_empty())
        || result
            .steps
            .iter()
            .flat_map(|s| &s.observed)
            .any(|o| match o {
                Received::Frame { .. } | Received::Garbage { .. } => true,
                Received::Silence { partial, .. } | Received::Closed { partial, .. } => {
                    !partial.is_empty()
                }
            })
}

/// A case whose answer may come from a pipeline, and whether it did.
type Ran = (Case, crate::observe::CaseResult, bool);

/// The campaign's loop (see [`campaign`]).
#[allow(clippy::too_many_arguments)]
fn fuzz_loop(
    opts: &CampaignOptions,
    profile: &drives::profile::Profile,
    foreign: Option<u8>,
    cfg: &crate::runner::RunConfig,
    runner: &mut crate::runner::Runner,
    mut keeper: Option<&mut crate::restore::Keeper>,
    log: &mut dyn Write,
    interrupt: &AtomicBool,
    tick: &mut impl FnMut(u64, f64, usize),
) -> Result<CampaignOutcome, SessionError> {
    let framing = runner.framing();
    let generator = Generator::new(profile, cfg.unit, opts.seed).on_line(foreign);
    let probe = probe_case(profile);
    let started = Instant::now();
    let mut last_tick = Instant::now();
    let (mut cases, mut probes, mut index, mut pipelined) = (0u64, 0u64, 0u64, 0u64);
    let mut history: Vec<Case> = Vec::new();
    let mut findings = Vec::new();
    let mut seen = std::collections::BTreeSet::new();
    let mut repeats = 0u64;
    let mut stopped = None;
    // Requests in flight at once: found out before the first case (a FAIL of the burst is a finding).
    let (pipelining, burst) = runner.discover_pipelining(opts.pipeline)?;
    if opts.pipeline > 1 && !cfg.is_sim {
        let _ = writeln!(
            log,
            "fuzz: {} ({})",
            if pipelining.depth > 1 {
                format!("up to {} requests in flight", pipelining.depth)
            } else {
                "one request at a time".to_string()
            },
            pipelining.why
        );
    }
    let mut depth = pipelining.depth;
    // Cases run again where a damaged link may have made them FAIL (see `link::run_over_link`).
    let mut link = LinkTally::default();
    if let Some((case, result)) = burst.filter(|(_, r)| r.verdict == Verdict::Fail) {
        let f: Vec<String> = result.findings().cloned().collect();
        let first = f.first().cloned().unwrap_or_default();
        let _ = writeln!(log, "finding: {} FAILs: {first}", case.id);
        seen.insert(signature(FindingKind::Fail, &case.id, &first));
        let d = Detected {
            kind: FindingKind::Fail,
            case_id: case.id.clone(),
            findings: f,
            history: vec![case],
        };
        findings.push(record(opts, &profile.device.id, d, &probe, log));
        if !opts.keep_going {
            stopped = Some("the first finding (--keep-going goes on)".to_string());
        }
    }
    // Cases generated and allowed, not run yet (a case that ended a pipelined batch runs next).
    let mut queue: std::collections::VecDeque<Case> = std::collections::VecDeque::new();
    // Bounded by the duration, the case limit and the interrupt; a generator that only produced skipped
    // cases is bounded by the index limit.
    while stopped.is_none()
        && started.elapsed() < opts.duration
        && opts.max_cases.is_none_or(|m| cases < m)
        && !interrupt.load(Ordering::SeqCst)
        && index < u64::MAX / 2
    {
        // Every generated input is rated by the classifier before the policy decides; the runner rates
        // the bytes again just before sending.
        let next_case = |index: &mut u64| {
            let case = generator.case(*index).retagged(profile, cfg.unit);
            *index += 1;
            campaign_skip(&case, cfg, framing, opts.allow_writes)
                .is_none()
                .then_some(case)
        };
        let Some(case) = queue.pop_front().or_else(|| next_case(&mut index)) else {
            continue;
        };
        let untouched = |k: &Option<&mut crate::restore::Keeper>, c: &Case| {
            k.as_deref().is_none_or(|k| k.touched(c).is_empty())
        };
        let ran: Vec<Ran> = if depth > 1 && runner.pipelinable(&case) && untouched(&keeper, &case) {
            // A batch: this case and the pipelinable ones after it, up to the depth, the next liveness
            // probe and the case limit; the first one that cannot be pipelined runs after them.
            let every = opts.probe_every.max(1);
            let room = (every - cases % every)
                .min(opts.max_cases.map_or(u64::MAX, |m| m.saturating_sub(cases)))
                .min(depth as u64) as usize;
            let mut batch = vec![case];
            // Bounded by the room and by the generated indices looked at (skipped ones included).
            for _ in 0..room.saturating_mul(8) {
                if batch.len() >= room {
                    break;
                }
                let Some(c) = next_case(&mut index) else {
                    continue;
                };
                if runner.pipelinable(&c) && untouched(&keeper, &c) {
                    batch.push(c);
                } else {
                    queue.push_back(c);
                    break;
                }
            }
            if batch.len() < 2 {
                // Nothing to put in flight beside it.
                let case = batch.remove(0);
                let result = over_link(runner, None, &case, profile, cfg, &mut link)?;
                vec![(case, result, false)]
            } else {
                let results = runner.run_pipelined(&batch)?;
                batch
                    .into_iter()
                    .zip(results)
                    .map(|(c, (r, p))| (c, r, p))
                    .collect()
            }
        } else {
            vec![run_one(
                runner,
                keeper.as_deref_mut(),
                case,
                (profile, cfg),
                &mut link,
                log,
            )?]
        };
        cases += ran.len() as u64;
        pipelined += ran.iter().filter(|r| r.2).count() as u64;
        history.extend(ran.iter().map(|r| r.0.clone()));
        // A liveness probe right after a case whose due answer did not come (before judging it: a drive
        // that stopped answering is that finding, not a wrong answer), and every N cases.
        if ran.iter().any(|r| r.1.unanswered()) || cases % opts.probe_every.max(1) == 0 {
            probes += 1;
            let p = over_link(runner, None, &probe, profile, cfg, &mut link)?;
            if p.verdict == Verdict::Fail {
                let first = history.first().map_or("?".to_string(), |c| c.id.clone());
                let mut f: Vec<String> = p.findings().cloned().collect();
                // Bytes came back: the drive is alive, its answer is what FAILs (an answer whose MBAP length
                // disagrees with its bytes arrives as an incomplete frame, say).
                let heard = heard_anything(&p);
                // Nothing came: the probe once more on a new connection tells a drive that hangs a
                // connection (and answers on a new one: jsmodbus 5) from one that stopped altogether.
                let hung = !heard
                    && runner.target().has_connections()
                    && runner.reconnect().is_ok()
                    && runner
                        .run_case(&probe)
                        .is_ok_and(|again| again.verdict == Verdict::Pass);
                if hung {
                    f.push(
                        "the same read on a new connection is answered: the drive left the connection it was on hung"
                            .to_string(),
                    );
                }
                let what = match (heard, hung) {
                    (true, _) => "the liveness probe was answered wrongly or late",
                    (false, true) => "the connection stopped answering (a new one is answered)",
                    (false, false) => "the drive stopped answering",
                };
                let _ = writeln!(
                    log,
                    "finding: {what} within the {} case(s) since the last good probe (from {first})",
                    history.len()
                );
                let h = std::mem::take(&mut history);
                let kind = if heard {
                    FindingKind::ProbeFails
                } else {
                    FindingKind::StoppedAnswering
                };
                let d = Detected {
                    kind,
                    case_id: first,
                    findings: f,
                    history: h,
                };
                findings.push(record(opts, &profile.device.id, d, &probe, log));
                stopped = Some(
                    match (heard, hung) {
                        (true, _) => "a wrong or late answer to the liveness probe",
                        (false, true) => "the connection stopped answering",
                        (false, false) => "the drive stopped answering",
                    }
                    .to_string(),
                );
                break;
            }
            history.clear();
        }
        if depth > 1
            && let Some(id) = runner.pipeline_failed()
        {
            depth = 1;
            let _ = writeln!(
                log,
                "fuzz: one request at a time from here: {id} went unanswered with other requests in flight, and was asked again alone (judged so)"
            );
        }
        // A pipelined case that FAILs or was refused as busy ends the pipelining: from here one request at a
        // time, so that every later finding is one of a request sent alone. (A silence or a close the oracle
        // admits is the drive's choice, not trouble with requests in flight: the requests lost with a close
        // were sent again.)
        if let Some((c, r, _)) = ran
            .iter()
            .find(|(_, r, p)| *p && (r.verdict == Verdict::Fail || busy(r)))
        {
            depth = 1;
            let _ = writeln!(
                log,
                "fuzz: one request at a time from here: {} was sent with other requests in flight and {}",
                c.id,
                if busy(r) {
                    "was refused as busy (exception 06)"
                } else {
                    "FAILs"
                }
            );
        }
        for (case, result, in_flight) in &ran {
            if result.verdict != Verdict::Fail {
                continue;
            }
            let f: Vec<String> = result.findings().cloned().collect();
            let first = f.first().cloned().unwrap_or_default();
            if seen.insert(signature(FindingKind::Fail, &case.id, &first)) {
                let _ = writeln!(
                    log,
                    "finding: {} FAILs{}: {first}",
                    case.id,
                    if *in_flight {
                        " (its request was sent with others in flight)"
                    } else {
                        ""
                    }
                );
                let d = Detected {
                    kind: FindingKind::Fail,
                    case_id: case.id.clone(),
                    findings: f,
                    history: vec![case.clone()],
                };
                findings.push(record(opts, &profile.device.id, d, &probe, log));
            } else {
                repeats += 1;
            }
            if !opts.keep_going {
                stopped = Some("the first finding (--keep-going goes on)".to_string());
                break;
            }
            if findings.len() >= opts.max_findings.max(1) {
                stopped = Some(format!(
                    "{} distinct findings (--max-findings)",
                    findings.len()
                ));
                break;
            }
        }
        if last_tick.elapsed() >= Duration::from_secs(1) {
            last_tick = Instant::now();
            tick(
                cases,
                cases as f64 / started.elapsed().as_secs_f64().max(1e-9),
                findings.len(),
            );
        }
    }
    crate::session::log_silences(log, runner);
    if let Some(n) = link.note() {
        let _ = writeln!(log, "{n}");
    }
    let stopped = stopped.unwrap_or_else(|| {
        if interrupt.load(Ordering::SeqCst) {
            "interrupted".to_string()
        } else if opts.max_cases.is_some_and(|m| cases >= m) {
            "the case limit (--max-cases)".to_string()
        } else {
            "the duration".to_string()
        }
    });
    Ok(CampaignOutcome {
        cases,
        probes,
        requests: runner.requests(),
        elapsed: started.elapsed(),
        findings,
        repeats,
        stopped,
        seed: opts.seed,
        leave_as_found: None,
        pipelining,
        pipelined,
    })
}

/// Run one case alone; with a keeper (`--allow-writes` against a real drive), the drive's parameters are
/// read before the first case that may write, and what the case changed is put back after it.
fn run_one(
    runner: &mut crate::runner::Runner,
    keeper: Option<&mut crate::restore::Keeper>,
    case: Case,
    (profile, cfg): (&drives::profile::Profile, &crate::runner::RunConfig),
    link: &mut LinkTally,
    log: &mut dyn Write,
) -> Result<Ran, SessionError> {
    let Some(k) = keeper else {
        let result = over_link(runner, None, &case, profile, cfg, link)?;
        return Ok((case, result, false));
    };
    let t = k.touched(&case);
    if (case.has(crate::cases::Tag::Write) || !t.is_empty()) && !k.armed() {
        k.take_snapshot(runner)?;
        let a = k.account();
        let _ = writeln!(
            log,
            "leave as found: {} parameter(s) read before the first write (journal {})",
            a.kept,
            a.journal
                .as_ref()
                .map_or_else(|| "none".into(), |p| p.display().to_string())
        );
        crate::session::align_reference(log, k, runner, profile);
    }
    if let Some(why) = k.unrestorable(&case) {
        let skipped = crate::observe::CaseResult::skipped(&case.id, why);
        return Ok((case, skipped, false));
    }
    // A save to NVM stores the settings as found, whatever the cases before changed.
    k.note_case(&case);
    k.before_save(runner, &case, profile);
    let keep = (!t.is_empty()).then_some(&mut *k);
    let result = over_link(runner, keep, &case, profile, cfg, link)?;
    if !t.is_empty() {
        let t = k.taken(&case, runner.refused_writes());
        k.after_case(runner, &case.id, &t, profile)?;
    }
    Ok((case, result, false))
}

/// True when an answer of the case was exception 06, Server Busy.
fn busy(result: &crate::observe::CaseResult) -> bool {
    result.steps.iter().flat_map(|s| &s.observed).any(|o| {
        matches!(o, crate::targets::Received::Frame { bytes, .. } if crate::runner::busy_refusal(bytes))
    })
}
