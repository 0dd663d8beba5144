//! `modbus-harness run`: the conformance run against a target.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use clap::Args;
use modbus_harness::corpus::Corpus;
use modbus_harness::run::Verdict;
use modbus_harness::run::session::{self, Options};
use modbus_harness::sim::{Fault, FaultSet};
use modbus_harness::target::TargetUrl;

/// Arguments of `run`.
#[derive(Args)]
pub struct RunArgs {
    /// The endpoint: tcp://HOST:PORT, rtu+tcp://HOST:PORT, rtu:///dev/ttyX?baud=19200&parity=even&stop=1, or sim:PROFILE.
    #[arg(long, default_value = "sim:sd2x")]
    target: String,
    /// Drive profile (mdrive, lmd, sd2x, generic, ...) or `auto` to read the device identification.
    /// Defaults to the simulator's own profile for sim: targets.
    #[arg(long)]
    profile: Option<String>,
    /// Unit id (Modbus/TCP) or slave address (RTU); default: the profile's.
    #[arg(long)]
    unit: Option<u8>,
    /// Write JSON, JUnit XML, HTML and pcapng reports into this directory.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Expectations file: known deviations of this target, each with a reason (TOML).
    #[arg(long)]
    expect: Option<PathBuf>,
    /// Run only cases whose id matches (glob or id prefix; repeatable).
    #[arg(long = "cases", value_name = "GLOB")]
    cases: Vec<String>,
    /// Leave out cases whose id matches (glob or id prefix; repeatable).
    #[arg(long = "exclude", value_name = "GLOB")]
    exclude: Vec<String>,
    /// List the selected cases and exit.
    #[arg(long)]
    list: bool,
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
    /// Per-answer timeout in milliseconds.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    timeout: u64,
    /// How long to listen for an answer that should not come, in milliseconds.
    #[arg(long, default_value_t = 300, value_name = "MS")]
    silence: u64,
    /// Inject a fault into the in-process simulator (sim: targets; repeatable; see `simulate --list-faults`).
    #[arg(long = "fault", value_name = "NAME")]
    faults: Vec<String>,
    /// Corpus directory (default: the corpus built into the binary).
    #[arg(long)]
    corpus: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    no_progress: bool,
}

/// Run `run`: exit 0 without FAIL, 1 with a FAIL, 2 when the run could not be made.
pub fn run(args: &RunArgs) -> ExitCode {
    let url = match TargetUrl::parse(&args.target) {
        Ok(u) => u,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
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
                return ExitCode::from(2);
            }
        }
    }
    if let Some(r) = args.max_rate
        && !(r > 0.0 && r.is_finite())
    {
        eprintln!("error: --max-rate must be a positive number of requests per second");
        return ExitCode::from(2);
    }
    let mut opts = Options::new(url);
    opts.profile = args.profile.clone();
    opts.corpus = Corpus::from_option(args.corpus.as_deref());
    opts.unit = args.unit;
    opts.timeout = Duration::from_millis(args.timeout.max(1));
    opts.silence = Duration::from_millis(args.silence.max(1));
    opts.allow_motion = args.allow_motion;
    opts.allow_destructive = args.allow_destructive;
    opts.read_only = args.read_only;
    opts.max_rate = args.max_rate;
    opts.include = args.cases.clone();
    opts.exclude = args.exclude.clone();
    opts.expect = args.expect.clone();
    opts.faults = faults;
    opts.report_dir = args.report.clone();
    opts.command_line = std::env::args().collect::<Vec<_>>().join(" ");

    if args.list || args.dry_run {
        return list(&opts, args.dry_run);
    }

    let interrupt = Arc::new(AtomicBool::new(false));
    {
        let flag = interrupt.clone();
        // A second Ctrl-C while the report is being finished ends the process at once.
        let _ = ctrlc::set_handler(move || {
            if flag.swap(true, Ordering::SeqCst) {
                std::process::exit(130);
            }
            eprintln!("\ninterrupted: finishing the current case and writing the report ...");
        });
    }
    let bar = (!args.no_progress && std::io::stderr().is_terminal()).then(|| {
        let b = indicatif::ProgressBar::new(0);
        b.set_style(
            indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    });
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
    };
    let mut log = std::io::stderr();
    let outcome = session::run(&opts, &mut log, &interrupt, &mut progress);
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    match outcome {
        Ok(o) => {
            for f in o.failures.iter().take(20) {
                println!("FAIL {}", f.id);
                for line in f.findings().take(3) {
                    println!("     {line}");
                }
            }
            print!(
                "{}",
                modbus_harness::report::terminal_summary(&o.summary, &o.info)
            );
            if o.summary.count(Verdict::Fail) > 0 {
                ExitCode::from(1)
            } else if o.summary.interrupted {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            }
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn list(opts: &Options, dry: bool) -> ExitCode {
    let mut log = std::io::stderr();
    let profile = match session::resolve_profile(opts, &mut log) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let planned = match session::plan(opts, &profile) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let (mut run, mut skip) = (0, 0);
    for (c, s) in &planned {
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
                println!("SKIP {}{tags}  ({reason})", c.id);
            }
            (true, None) => {
                run += 1;
                println!("RUN  {}{tags}  {}", c.id, c.title);
            }
            (false, _) => println!("{}{tags}  {}", c.id, c.title),
        }
    }
    if dry {
        println!(
            "\n{run} to run, {skip} skipped by the safety policy or the transport, against {}",
            opts.target
        );
    } else {
        println!("\n{} cases", planned.len());
    }
    ExitCode::SUCCESS
}
