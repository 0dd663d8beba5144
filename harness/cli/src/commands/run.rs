//! `modbus-harness run`: the conformance run against a target.

use crate::exit::Exit;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clap::Args;
use drives::corpus::Corpus;
use drives::{Fault, FaultSet};
use engine::Verdict;
use engine::cases::shrink::ShrinkLimits;
use engine::expect::{ExpectationState, ExpectationUse};
use engine::session::{self, Options, SnapshotOptions};
use engine::targets::TargetUrl;

/// The progress bar on a terminal: position, rate, elapsed time, time left, FAIL count and current case.
const BAR_TEMPLATE: &str = "{bar:30} {pos}/{len} {per_sec} {elapsed} ETA {eta} {msg}";

/// How many FAIL cases the terminal shows with their findings; the rest are counted (all are in the report).
const FAIL_DETAILS_CAP: usize = 20;

/// What `run --help` says, after the options, about generated cases and snapshots.
const GENERATED_HELP: &str = "\
Generated cases:
  --generated N --seed S runs N cases drawn from the profile's map (valid requests of every function
  code, boundary addresses and quantities, 32-bit halves, and malformed variants: bit flips, truncation,
  extension, byte-count mismatch, function-code swap, wrong unit, bad CRC, MBAP length, several requests
  in one write, one request split in two), ids gen/S/INDEX/KIND, judged by the same oracle. The same seed
  gives the same cases on every transport (transport-specific ones are SKIPPED on the other framing); the
  seed is printed and is in every report. --generated alone runs only the generated cases; add
  --with-catalog for the catalog too. A generated case that FAILs is shrunk against the target (at most
  --shrink-steps candidates and --shrink-time seconds each, --max-shrinks cases) and the smallest case
  that still FAILs is written to --regressions DIR/PROFILE/NAME.toml; the catalog replays those files
  as regression/PROFILE/NAME.

Snapshots:
  --snapshot FILE compares the run's observations (per case, sorted by id: request bytes, answers or
  silence or close, verdict; no timestamps) with FILE, prints a diff naming the cases that differ and
  exits 1 on drift; with --update-snapshot it writes FILE instead. Compare a sim: run with a server's
  using --policy-on-sim.

Leave as found (real targets):
  Before its first write the run reads every parameter of the profile it can read and write back
  (holding registers, coils, FC 0x41 settings, objects; read-only, write-only, motion and destructive
  ones without their flags are left out, each with the reason), keeps them in a state journal (--journal
  FILE, default REPORT/journal.json or a file in the temporary directory that is removed once the drive
  reads as found; written and synced before the first write, updated as the run goes), puts back and verifies what each writing case could have changed,
  and at the end (also after Ctrl-C, SIGTERM or an error) restores everything that differs. What cannot be
  put back is listed with its value before and after. After a killed run:
  modbus-harness restore --journal FILE.

Dead, foreign or dying targets (real targets):
  Before the first case a known-good read of the profile: no Modbus answer within --preflight-timeout is
  exit 2 with the likely causes, or what answered (HTTP, TLS, SSH, an echo). Mid-run, an answer that was
  due and did not come triggers that read again: a target that no longer answers FAILs the request before
  the silence and is waited for (--recovery-wait); it recovers (noted in the reports) or the remaining
  cases are SKIPPED and the reports say why the run ended.

Exit codes:
  0  no FAIL, the drive left as found
  1  a FAIL (or snapshot drift; with --strict-expect, an --expect entry that matches no case or is stale)
  2  the run could not be made (also: no Modbus answer to the pre-flight read; --cases/--exclude select
     no case, or a pattern is not a valid glob) or was interrupted
  3  the drive was not left as found: a parameter could not be restored (listed in the summary), also when
     the run stopped on an error such as a dead target";

/// Arguments of `run`.
///
/// Generated cases: `--generated N --seed S` runs N cases drawn from the profile's map (valid requests,
/// boundaries, malformed variants), ids `gen/S/INDEX/KIND`, judged by the same oracle; the same seed gives
/// the same cases on every transport. Alone it runs only them; `--with-catalog` runs the catalog too. A
/// failing generated case is shrunk against the target (`--shrink-steps`, `--shrink-time`) and written to
/// `corpus/regressions/PROFILE/NAME.toml`, which the catalog replays as `regression/PROFILE/NAME`.
///
/// Snapshots: `--snapshot FILE` compares the run's observations (request and response bytes, verdict, per
/// case; timestamps left out) with FILE and prints a diff naming the cases that differ (exit code 1 on
/// drift); `--update-snapshot` writes FILE instead.
#[derive(Args)]
#[command(after_help = GENERATED_HELP)]
pub struct RunArgs {
    /// The endpoint: tcp://HOST:PORT, rtu+tcp://HOST:PORT[?gap=MS] (gap: the silence the device server or drive
    /// needs to end a frame, left after a frame it may still hold; default 100), rtu:///dev/ttyX?baud=19200&parity=even&stop=1
    /// (add &byte_timeout=MS for how long an answer that is not complete waits for its next byte, default 50:
    /// a USB adapter hands over bytes when its latency timer runs out; add &echo=on for a two-wire RS-485 adapter that gives back what it sends), or sim:PROFILE (the in-process reference drive of a corpus profile, or of a profile file:
    /// sim:./my.toml, sim:/abs/x.toml?transport=rtu).
    #[arg(long, default_value = "sim:sd2x")]
    target: String,
    /// Drive profile: a corpus profile's name (mdrive, lmd, sd2x, generic, or those of --corpus), a profile
    /// file (a value containing `/` or ending in `.toml` is a file: ./my.toml, /abs/drive.toml, my.toml), or
    /// `auto` to read the device identification. Default for sim: targets: the simulator's own; with a sim:
    /// target, --profile judges that simulator's drive.
    #[arg(long, value_name = "NAME|PATH")]
    profile: Option<String>,
    /// Unit id (Modbus/TCP) or slave address (RTU); default: the profile's.
    #[arg(long)]
    unit: Option<u8>,
    /// A slave address no device on the line answers: the cases that check that a frame for another slave
    /// goes unanswered send it there. Default: found at the start of a run against an RTU drive (direct or
    /// behind a gateway) among the address next but one to the drive's, 247 and 124, the first that nothing
    /// answers; on a line where the drive is alone, the drive's neighbour's address (--unit + 2) judges
    /// strictly.
    #[arg(long, value_name = "ADDRESS", value_parser = clap::value_parser!(u8).range(1..=247))]
    foreign_address: Option<u8>,
    /// Write reports into this directory: index.json, cases.jsonl (every case, one line each), cases/ (a
    /// file per case that did not PASS), junit.xml, report.html, session.pcapng.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Expectations file: known deviations of this target, each with a reason (TOML). Entries that match
    /// no case of the run, or whose cases ran without the deviation (stale), are reported after the run.
    #[arg(long)]
    expect: Option<PathBuf>,
    /// With --expect: an entry that matches no case or is stale fails the run (exit code 1).
    #[arg(long, requires = "expect")]
    strict_expect: bool,
    /// Run only cases whose id matches (glob or id prefix; repeatable).
    #[arg(long = "cases", value_name = "GLOB")]
    cases: Vec<String>,
    /// Leave out cases whose id matches (glob or id prefix; repeatable).
    #[arg(long = "exclude", value_name = "GLOB")]
    exclude: Vec<String>,
    /// List the selected cases and exit.
    #[arg(long)]
    list: bool,
    /// List the requirements the selected cases check (per source document, with the cases citing each)
    /// and the freedoms of the profile, and exit.
    #[arg(long)]
    list_requirements: bool,
    /// Run the selected catalog cases in an order shuffled with this seed (printed, with the order; the
    /// reports keep the case ids). Cases that leave the drive changed for good still run last.
    #[arg(long, value_name = "SEED")]
    shuffle: Option<u64>,
    /// Show what would run and what the safety policy would skip, without touching the target.
    #[arg(long)]
    dry_run: bool,
    /// Allow cases that can move the motor or enable the power stage (real targets).
    #[arg(long)]
    allow_motion: bool,
    /// Allow cases that change non-volatile state or leave the drive faulted (real targets).
    #[arg(long)]
    allow_destructive: bool,
    /// Skip every case that writes.
    #[arg(long)]
    read_only: bool,
    /// At most this many requests per second (real targets).
    #[arg(long, value_name = "N")]
    max_rate: Option<f64>,
    /// How long the known-good read before the first case (and each liveness probe) waits for an answer, in
    /// milliseconds: a target that gives none is not run against (exit 2, with the likely causes).
    #[arg(long, default_value_t = 3000, value_name = "MS")]
    preflight_timeout: u64,
    /// How long to wait for a target that stopped answering mid-run to come back, in seconds, before the
    /// remaining cases are SKIPPED.
    #[arg(long, default_value_t = 10, value_name = "SECS")]
    recovery_wait: u64,
    /// Per-answer timeout in milliseconds.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    timeout: u64,
    /// How long to listen for an answer that should not come, in milliseconds (on Modbus/TCP the silence
    /// is proven sooner by a sentinel request sent right behind, see --no-sentinel).
    #[arg(long, default_value_t = 300, value_name = "MS")]
    silence: u64,
    /// Modbus/TCP: listen out the whole --silence window after a request that must go unanswered, instead
    /// of proving the silence with a sentinel (a known-good read sent right behind it on the same
    /// connection, whose answer with nothing before it proves that nothing came) or, before a new
    /// connection, by half-closing the connection (the target's close with nothing before it proves it).
    #[arg(long)]
    no_sentinel: bool,
    /// How long a request the drive answers Server Busy (exception 06: "the client should retransmit the
    /// message later", App 7; a drive saving to NVM, say) is sent again, every 20-100 ms, before that
    /// answer is judged, in milliseconds; 0: never sent again.
    #[arg(long, default_value_t = 5000, value_name = "MS")]
    busy_wait: u64,
    /// Run a case again, at most N more times (after half the answer timeout, 1 s, 3 s, then 1 s each),
    /// where it FAILed as a damaged link
    /// makes a case fail (no answer, part of a frame, a frame whose CRC does not check, a closed connection:
    /// noise on an RS-485 line, a TCP link that dropped); an attempt that comes through whole is judged, one
    /// that FAILs the same way as the first is the drive's own and the first is judged. 0: every first
    /// attempt is judged (a clean link). Real targets only.
    #[arg(long, default_value_t = 6, value_name = "N")]
    link_retries: u32,
    /// Inject a fault into the in-process simulator (sim: targets; repeatable; see `simulate --list-faults`).
    #[arg(long = "fault", value_name = "NAME")]
    faults: Vec<String>,
    /// Make the in-process simulator choose FREEDOM=VALUE where the specs and manuals leave a choice
    /// (sim: targets; repeatable; the freedoms are in corpus/freedoms/, see corpus/requirements/README.md).
    #[arg(long = "choose", value_name = "FREEDOM=VALUE")]
    choose: Vec<String>,
    /// Corpus directory (default: the corpus built into the binary).
    #[arg(long)]
    corpus: Option<PathBuf>,
    /// No progress bar (on a terminal) and no progress lines (without one).
    #[arg(long)]
    no_progress: bool,
    /// Without a terminal, print a progress line to stderr every SECS seconds (0: after every case).
    #[arg(long, default_value_t = 10, value_name = "SECS")]
    progress_every: u64,
    /// Run N generated cases (ids gen/SEED/INDEX/KIND) instead of the catalog (with it: --with-catalog).
    #[arg(long, value_name = "N")]
    generated: Option<u64>,
    /// Seed of the generated cases (default: from the clock; printed, and in every report).
    #[arg(long, value_name = "S", requires = "generated")]
    seed: Option<u64>,
    /// With --generated: run the catalog (and the regressions) too.
    #[arg(long, requires = "generated")]
    with_catalog: bool,
    /// Do not shrink failing generated cases.
    #[arg(long)]
    no_shrink: bool,
    /// Candidates run against the target at most while shrinking one case.
    #[arg(long, default_value_t = 200, value_name = "N")]
    shrink_steps: usize,
    /// Seconds spent at most shrinking one case.
    #[arg(long, default_value_t = 30, value_name = "SECS")]
    shrink_time: u64,
    /// Failing generated cases shrunk at most per run (the first ones).
    #[arg(long, default_value_t = 3, value_name = "N")]
    max_shrinks: usize,
    /// Where shrunk reproducers are written (DIR/PROFILE/NAME.toml). Default: the --corpus directory's
    /// regressions/, else ./corpus/regressions when ./corpus exists; otherwise they are only printed.
    #[arg(long, value_name = "DIR")]
    regressions: Option<PathBuf>,
    /// Compare the run's observations with this snapshot file (exit code 1 on drift).
    #[arg(long, value_name = "FILE")]
    snapshot: Option<PathBuf>,
    /// Write the --snapshot file instead of comparing with it.
    #[arg(long, requires = "snapshot")]
    update_snapshot: bool,
    /// Apply the safety policy to sim: targets as to a real drive (motion and destructive cases SKIPPED),
    /// so that a sim: run selects the same cases as a run against a server.
    #[arg(long)]
    policy_on_sim: bool,
    /// State journal of the leave-as-found snapshot (default: REPORT/journal.json, else a file in the
    /// temporary directory, removed once the drive reads as found); `modbus-harness restore --journal FILE`
    /// undoes a killed run.
    #[arg(long, value_name = "FILE")]
    journal: Option<PathBuf>,
}

/// Run `run`: exit 0 without FAIL, 1 with a FAIL, 2 when the run could not be made, 3 when the drive was
/// not left as found.
pub fn run(args: &RunArgs) -> ExitCode {
    let url = match TargetUrl::parse(&args.target) {
        Ok(u) => u,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    let mut faults = FaultSet::none();
    for f in &args.faults {
        match f.parse::<Fault>() {
            Ok(f) => {
                faults.0.insert(f);
            }
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(Exit::Unusable);
            }
        }
    }
    if let Some(r) = args.max_rate
        && !(r > 0.0 && r.is_finite())
    {
        eprintln!("error: --max-rate must be a positive number of requests per second");
        return ExitCode::from(Exit::Unusable);
    }
    if let Err(e) = check_patterns(&args.cases, &args.exclude) {
        eprintln!("error: {e}");
        return ExitCode::from(Exit::Unusable);
    }
    let mut opts = Options::new(url);
    opts.profile = args.profile.clone();
    opts.corpus = Corpus::from_option(args.corpus.as_deref());
    opts.unit = args.unit;
    opts.foreign = args.foreign_address;
    opts.timing.timeout = Duration::from_millis(args.timeout.max(1));
    opts.liveness = Some(engine::liveness::Liveness {
        probe_timeout: Duration::from_millis(args.preflight_timeout.max(1)),
        recovery: Duration::from_secs(args.recovery_wait),
    });
    opts.timing.silence = Duration::from_millis(args.silence.max(1));
    opts.timing.sentinel = !args.no_sentinel;
    opts.timing.busy_wait = Duration::from_millis(args.busy_wait);
    opts.timing.link_retries = args.link_retries;
    opts.safety.allow_motion = args.allow_motion;
    opts.safety.allow_destructive = args.allow_destructive;
    opts.safety.read_only = args.read_only;
    opts.safety.max_rate = args.max_rate;
    opts.include = args.cases.clone();
    opts.exclude = args.exclude.clone();
    opts.expect = args.expect.clone();
    opts.faults = faults;
    opts.choose.clone_from(&args.choose);
    opts.report_dir = args.report.clone();
    opts.command_line = std::env::args().collect::<Vec<_>>().join(" ");
    if let Some(n) = args.generated {
        opts.generated = n;
        let seed = args
            .seed
            .unwrap_or_else(engine::cases::generated::clock_seed);
        opts.seed = Some(seed);
        opts.with_catalog = args.with_catalog;
        eprintln!("seed: {seed} (replay with --generated {n} --seed {seed})");
    }
    opts.shrink = (!args.no_shrink).then(|| ShrinkLimits {
        max_steps: args.shrink_steps.max(1),
        max_time: Duration::from_secs(args.shrink_time.max(1)),
    });
    opts.max_shrinks = args.max_shrinks;
    opts.regressions_dir = args.regressions.clone().or_else(|| match &args.corpus {
        Some(c) => Some(c.join("regressions")),
        None => std::path::Path::new("corpus")
            .is_dir()
            .then(|| PathBuf::from("corpus/regressions")),
    });
    opts.snapshot = args.snapshot.clone().map(|path| SnapshotOptions {
        path,
        update: args.update_snapshot,
    });
    opts.policy_on_sim = args.policy_on_sim;
    opts.shuffle = args.shuffle;
    opts.journal = args.journal.clone();

    if args.list_requirements {
        return list_requirements(&opts);
    }
    if args.list || args.dry_run {
        return list(&opts, args, args.dry_run);
    }

    let interrupt = Arc::new(AtomicBool::new(false));
    {
        let flag = interrupt.clone();
        // A second Ctrl-C while the report is being finished ends the process at once.
        let _ = ctrlc::set_handler(move || {
            if flag.swap(true, Ordering::SeqCst) {
                // Ends now, without putting back what the run changed: say how it can be.
                eprintln!(
                    "\ninterrupted again: exiting at once; anything changed is NOT put back (modbus-harness restore --journal FILE, with the journal the log named, puts it back)"
                );
                std::process::exit(130);
            }
            eprintln!("\ninterrupted: finishing the current case and writing the report ...");
        });
    }
    let terminal = std::io::stderr().is_terminal();
    let bar = (!args.no_progress && terminal).then(|| {
        let b = indicatif::ProgressBar::new(0);
        b.set_style(
            indicatif::ProgressStyle::with_template(BAR_TEMPLATE)
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    });
    // Without a terminal (CI logs, a pipe): a plain line every --progress-every seconds.
    let mut lines = (!args.no_progress && !terminal)
        .then(|| ProgressLines::new(Duration::from_secs(args.progress_every)));
    let mut fails = 0usize;
    let mut progress = |done: usize, total: usize, id: &str, v: Verdict| {
        if v == Verdict::Fail {
            fails += 1;
        }
        if let Some(b) = &bar {
            b.set_length(total as u64);
            b.set_position(done as u64);
            b.set_message(format!("{fails} FAIL  {id}"));
        }
        if let Some(l) = lines.as_mut() {
            l.case_done(done, total, fails);
        }
    };
    let mut log = std::io::stderr();
    let outcome = session::run(&opts, &mut log, &interrupt, &mut progress);
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    match outcome {
        Ok(o) => {
            for f in o.failures.iter().take(FAIL_DETAILS_CAP) {
                println!("FAIL {}", f.id);
                for line in f.findings().take(3) {
                    println!("     {line}");
                }
            }
            let all_fails = o.summary.count(Verdict::Fail);
            let shown = o.failures.len().min(FAIL_DETAILS_CAP);
            if all_fails > shown {
                match &args.report {
                    Some(dir) => println!(
                        "{} more FAIL details in the report ({})",
                        all_fails - shown,
                        dir.display()
                    ),
                    None => println!(
                        "{} more FAIL details: rerun with --report DIR for all of them",
                        all_fails - shown
                    ),
                }
            }
            for r in &o.shrunk {
                match (&r.shrunk, &r.file) {
                    (Some(s), Some(p)) => println!(
                        "SHRUNK {} -> {} ({} step(s); {} candidates run): {}",
                        r.id,
                        s.case.id,
                        s.case.steps.len(),
                        s.steps,
                        p.display()
                    ),
                    (Some(s), None) => println!(
                        "SHRUNK {} -> {} ({} step(s); {} candidates run){}",
                        r.id,
                        s.case.id,
                        s.case.steps.len(),
                        s.steps,
                        r.note.as_ref().map_or(
                            " (not written: pass --regressions DIR)".to_string(),
                            |n| format!(": {n}")
                        )
                    ),
                    (None, _) => {
                        println!("NOT SHRUNK {}: {}", r.id, r.note.as_deref().unwrap_or(""))
                    }
                }
            }
            let drift = o.snapshot.as_ref().is_some_and(|s| s.drifted());
            if let Some(s) = &o.snapshot {
                match &s.drift {
                    _ if s.written => println!("snapshot written: {}", s.path.display()),
                    Some(d) if !d.is_clean() => {
                        println!("snapshot {} differs from this run:", s.path.display());
                        print!("{}", d.render());
                    }
                    Some(d) => println!("{} ({})", d.summary(), s.path.display()),
                    None => {}
                }
            }
            if drift {
                println!(
                    "the observations drifted: exit code 1 (accept them with --update-snapshot)"
                );
            }
            let expect_problems = report_expectations(&o.expectations, args.strict_expect);
            let empty = o.summary.cases == 0 && !o.summary.interrupted;
            if empty {
                eprintln!("error: {}", no_case_message(args));
            }
            println!("{}", engine::reports::terminal_summary(&o.summary, &o.info));
            if o.not_restored() > 0 {
                ExitCode::from(Exit::NotRestored)
            } else if o.summary.count(Verdict::Fail) > 0
                || drift
                || (args.strict_expect && expect_problems > 0 && !o.summary.interrupted)
            {
                ExitCode::from(Exit::Failed)
            } else if empty || o.summary.interrupted {
                ExitCode::from(Exit::Unusable)
            } else {
                ExitCode::from(Exit::Ok)
            }
        }
        Err(e @ session::SessionError::LeftChanged { .. }) => {
            eprintln!("error: {e}");
            ExitCode::from(Exit::NotRestored)
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(Exit::Unusable)
        }
    }
}

/// `run --list-requirements`: every requirement of the documents the selected cases cite (and the profile's
/// manual), marked `x` when a selected case checks it, then the profile's freedoms.
fn list_requirements(opts: &Options) -> ExitCode {
    let mut log = std::io::stderr();
    let planned = session::resolve_profile(opts, &mut log)
        .map_err(|e| e.to_string())
        .and_then(|profile| {
            let planned = session::plan(opts, &profile).map_err(|e| e.to_string())?;
            let requirements = session::requirements_of(&opts.corpus).map_err(|e| e.to_string())?;
            Ok((profile, planned, requirements))
        });
    let (profile, planned, requirements) = match planned {
        Ok(x) => x,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    let mut cited: std::collections::BTreeMap<&str, Vec<&str>> = std::collections::BTreeMap::new();
    for (c, _) in &planned {
        for r in &c.requirements {
            cited.entry(r.as_str()).or_default().push(c.id.as_str());
        }
    }
    let own = profile.device.id.as_str();
    for cov in requirements.coverage(cited.keys().copied()) {
        if cov.exercised == 0 && cov.document != own {
            continue;
        }
        println!(
            "{} ({}): {}/{} checked by the {} selected case(s)",
            cov.document,
            cov.title,
            cov.exercised,
            cov.listed,
            planned.len()
        );
        for r in requirements
            .requirements()
            .iter()
            .filter(|r| r.document == cov.document)
        {
            let place = match r.line {
                Some(l) => format!("line {l}"),
                None => format!("§{}", r.section),
            };
            let cases = cited.get(r.id.as_str()).map_or(String::new(), |c| {
                let more = if c.len() > 2 {
                    format!(" and {} more", c.len() - 2)
                } else {
                    String::new()
                };
                format!(
                    "  <- {}{more}",
                    c.iter().take(2).copied().collect::<Vec<_>>().join(", ")
                )
            });
            let mark = if cases.is_empty() { ' ' } else { 'x' };
            let text: String = r.text.chars().take(90).collect();
            let cut = if r.text.chars().count() > 90 {
                "..."
            } else {
                ""
            };
            println!(
                "  [{mark}] {} {:?} {place}: {text}{cut}{cases}",
                r.id, r.level
            );
        }
        println!();
    }
    println!(
        "freedoms of profile {own} (the first value is the reference drive's; any value passes):"
    );
    for f in requirements.freedoms_for(own) {
        let values: Vec<String> = f.values.iter().map(|v| v.to_string()).collect();
        let source = f
            .sources
            .first()
            .map(|s| match (s.line, &s.section) {
                (Some(l), _) => format!("{} line {l}", s.doc),
                (None, Some(sec)) => format!("{} §{sec}", s.doc),
                (None, None) => s.doc.clone(),
            })
            .unwrap_or_default();
        println!(
            "  {} ({:?}): {}  [{source}] {}",
            f.id,
            f.kind,
            values.join(" | "),
            f.title
        );
    }
    ExitCode::from(Exit::Ok)
}

fn list(opts: &Options, args: &RunArgs, dry: bool) -> ExitCode {
    let mut log = std::io::stderr();
    let profile = match session::resolve_profile(opts, &mut log) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    let planned = match session::plan(opts, &profile) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    if planned.is_empty() {
        eprintln!("error: {}", no_case_message(args));
        return ExitCode::from(Exit::Unusable);
    }
    // `run --list | head -1`: a reader that goes away ends the listing quietly, without a panic.
    match print_list(opts, &profile, &planned, dry) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
            eprintln!("error: cannot write the list: {e}");
            ExitCode::from(Exit::Unusable)
        }
        _ => ExitCode::from(Exit::Ok),
    }
}

/// Print the planned cases (and with `dry`, what the safety policy skips and leaving the drive as found).
fn print_list(
    opts: &Options,
    profile: &drives::profile::Profile,
    planned: &[(engine::Case, Option<String>)],
    dry: bool,
) -> std::io::Result<()> {
    let mut out = std::io::stdout().lock();
    let (mut run, mut skip) = (0, 0);
    for (c, s) in planned {
        let tags: Vec<String> = c
            .tags
            .iter()
            .map(|t| format!("{t:?}").to_lowercase())
            .collect();
        let tags = if tags.is_empty() {
            String::new()
        } else {
            format!(" [{}]", tags.join(","))
        };
        match (dry, s) {
            (true, Some(reason)) => {
                skip += 1;
                writeln!(out, "SKIP {}{tags}  ({reason})", c.id)?;
            }
            (true, None) => {
                run += 1;
                writeln!(out, "RUN  {}{tags}  {}", c.id, c.title)?;
            }
            (false, _) => writeln!(out, "{}{tags}  {}", c.id, c.title)?,
        }
    }
    if dry {
        writeln!(
            out,
            "\n{run} to run, {skip} skipped by the safety policy or the transport, against {}",
            opts.target
        )?;
        if !opts.target.is_sim() && !opts.safety.read_only {
            let inv = engine::restore::inventory(profile, &opts.safety);
            writeln!(
                out,
                "leave as found: {} parameter(s) read before the first write and restored; {} left out:",
                inv.items.len(),
                inv.excluded.len()
            )?;
            for e in &inv.excluded {
                writeln!(out, "  {} ({}): {}", e.key, e.name, e.reason)?;
            }
        }
    } else {
        writeln!(out, "\n{} cases", planned.len())?;
    }
    out.flush()
}

/// The progress of a run without a terminal: a plain line to stderr at most every `every`.
struct ProgressLines {
    every: Duration,
    started: Instant,
    last: Instant,
}

impl ProgressLines {
    fn new(every: Duration) -> Self {
        let now = Instant::now();
        Self {
            every,
            started: now,
            last: now,
        }
    }

    /// After each case: a line when `every` has passed since the last one (the summary follows the last case).
    fn case_done(&mut self, done: usize, total: usize, fails: usize) {
        let now = Instant::now();
        if now.duration_since(self.last) < self.every || done >= total {
            return;
        }
        self.last = now;
        let elapsed = now.duration_since(self.started).as_secs_f64();
        let rate = done as f64 / elapsed.max(1e-3);
        let eta = (total.saturating_sub(done)) as f64 / rate.max(1e-9);
        let percent = done * 100 / total.max(1);
        // A closed stderr must not end the run (the drive is still to be put back).
        let _ = writeln!(
            std::io::stderr(),
            "progress: {done}/{total} cases ({percent}%), {fails} FAIL, {rate:.1} cases/s, {elapsed:.0} s elapsed, ETA {eta:.0} s"
        );
    }
}

/// Every --cases and --exclude pattern is a valid glob.
fn check_patterns(cases: &[String], exclude: &[String]) -> Result<(), String> {
    for (flag, patterns) in [("--cases", cases), ("--exclude", exclude)] {
        for p in patterns {
            if let Err(e) = glob::Pattern::new(p) {
                return Err(format!("{flag} `{p}` is not a valid glob: {e}"));
            }
        }
    }
    Ok(())
}

/// Why a run or a listing has no case: the selection that left none.
fn no_case_message(args: &RunArgs) -> String {
    let quoted = |v: &[String]| {
        v.iter()
            .map(|p| format!("`{p}`"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let what = match (args.cases.is_empty(), args.exclude.is_empty()) {
        (false, true) => format!("--cases {} matches no case", quoted(&args.cases)),
        (false, false) => format!(
            "--cases {} with --exclude {} leaves no case",
            quoted(&args.cases),
            quoted(&args.exclude)
        ),
        (true, false) => format!("--exclude {} leaves no case", quoted(&args.exclude)),
        (true, true) => "the run has no case".to_string(),
    };
    format!("no case selected: {what} (`modbus-harness run --list` lists the case ids)")
}

/// Print the entries of the expectations file that match no case or are stale; their number.
fn report_expectations(uses: &[ExpectationUse], strict: bool) -> usize {
    let problems: Vec<&ExpectationUse> = uses
        .iter()
        .filter(|u| {
            matches!(
                u.state(),
                ExpectationState::Unmatched | ExpectationState::Stale
            )
        })
        .collect();
    if problems.is_empty() {
        return 0;
    }
    println!(
        "expectations: {} of {} entr{} not used{}:",
        problems.len(),
        uses.len(),
        if uses.len() == 1 { "y" } else { "ies" },
        if strict {
            " (--strict-expect: exit code 1)"
        } else {
            " (--strict-expect makes this a failure)"
        }
    );
    for u in &problems {
        match u.state() {
            ExpectationState::Unmatched => println!(
                "  UNMATCHED {} ({}): matches no case of this run",
                u.case, u.verdict
            ),
            _ => println!(
                "  STALE     {} ({}): its {} case(s) ran without the deviation; remove the entry if it is fixed",
                u.case, u.verdict, u.ran
            ),
        }
    }
    problems.len()
}
