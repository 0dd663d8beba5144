//! `modbus-harness fuzz`: a live fuzz campaign against an endpoint.

use crate::exit::{Exit, unusable};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use clap::Args;
use drives::corpus::Corpus;
use drives::{Fault, FaultSet};
use engine::campaign::{CampaignOptions, FindingKind, campaign};
use engine::cases::generated::clock_seed;
use engine::session::Options;
use engine::targets::TargetUrl;

/// Arguments of `fuzz`.
#[derive(Args)]
#[command(
    after_help = "Safety: against anything but sim:, fuzz sends reads only unless --allow-writes (a banner \
then says so); cases the classifier rates motion or destructive are skipped unless --allow-motion / \
--allow-destructive, as for `run`; --read-only sends no write function code at all. With --allow-writes \
the drive is left as found, as by `run`: its parameters are read before the first write (--journal), the \
reference drive takes them, what a case changed is put back after it and everything at the end (exit 3 \
if something could not be)."
)]
pub struct FuzzArgs {
    /// The endpoint (tcp://, rtu+tcp://, rtu://, sim:PROFILE, sim:PATH.toml).
    #[arg(long)]
    target: String,
    /// Drive profile: a corpus profile's name, or a profile file (a value containing `/` or ending in
    /// `.toml` is a file: ./my.toml). Default: the simulator's own for sim:.
    #[arg(long, value_name = "NAME|PATH")]
    profile: Option<String>,
    /// Unit id / slave address (default: the profile's).
    #[arg(long)]
    unit: Option<u8>,
    /// A slave address no device on the line answers: the cases that check that a frame for another slave
    /// goes unanswered send it there. Default: found at the start of a run against an RTU drive (direct or
    /// behind a gateway) among the address next but one to the drive's, 247 and 124, the first that nothing
    /// answers; on a line where the drive is alone, the drive's neighbour's address (--unit + 2) judges
    /// strictly.
    #[arg(long, value_name = "ADDRESS", value_parser = clap::value_parser!(u8).range(1..=247))]
    foreign_address: Option<u8>,
    /// How long to fuzz: 30s, 10m, 1h, 500ms.
    #[arg(long, default_value = "60s")]
    duration: String,
    /// Stop after this many cases.
    #[arg(long)]
    max_cases: Option<u64>,
    /// Seed of the generated cases (default: from the clock; always printed).
    #[arg(long)]
    seed: Option<u64>,
    /// A liveness probe (a known-good read) after every N cases.
    #[arg(long, default_value_t = 20, value_name = "N")]
    probe_every: u64,
    /// Go on after a FAIL finding; a drive that stops answering always ends the campaign.
    #[arg(long)]
    keep_going: bool,
    /// Directory for reproducers (default: corpus/regressions if ./corpus exists, else ./regressions).
    #[arg(long)]
    regressions: Option<PathBuf>,
    /// How long the known-good read before the first case (and each liveness probe) waits for an answer, in
    /// milliseconds: a target that gives none is not run against (exit 2, with the likely causes).
    #[arg(long, default_value_t = 3000, value_name = "MS")]
    preflight_timeout: u64,
    /// Per-answer timeout in milliseconds.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    timeout: u64,
    /// How long to listen for an answer that should not come, in milliseconds: on RTU (a serial line, RTU
    /// over TCP) after every broadcast, request to another address and malformed frame; on Modbus/TCP only
    /// where no sentinel or half-close can prove the silence (see --no-sentinel). As `run --silence`.
    #[arg(long, default_value_t = 300, value_name = "MS")]
    silence: u64,
    /// Inject a simulator fault (sim: only; repeatable).
    #[arg(long = "fault", value_name = "NAME")]
    faults: Vec<String>,
    /// Allow cases that can move the motor or enable the power stage (real targets).
    #[arg(long)]
    allow_motion: bool,
    /// Allow cases that change non-volatile state (real targets).
    #[arg(long)]
    allow_destructive: bool,
    /// Skip every case that writes: no write function code goes on the wire.
    #[arg(long, conflicts_with = "allow_writes")]
    read_only: bool,
    /// Send generated writes to a real target (not needed for sim:); a banner says so first. Motion and
    /// destructive writes also need --allow-motion / --allow-destructive.
    #[arg(long)]
    allow_writes: bool,
    /// Modbus/TCP: listen out the whole silence window after a request that must go unanswered, instead of
    /// proving the silence with a sentinel (a known-good read sent right behind it on the same connection)
    /// or, before a new connection, by half-closing the connection (the target's close proves it).
    #[arg(long)]
    no_sentinel: bool,
    /// How long a request the drive answers Server Busy (exception 06: "the client should retransmit the
    /// message later", App 7; a drive saving to NVM, say) is sent again, every 20-100 ms, before that
    /// answer is judged, in milliseconds; 0: never sent again.
    #[arg(long, default_value_t = 5000, value_name = "MS")]
    busy_wait: u64,
    /// Run a case (or a liveness probe) again, at most N more times (after half the answer timeout, 1 s, 3 s,
    /// then 1 s each), where it
    /// FAILed as a damaged link makes a case fail (no answer, part of a frame, a frame whose CRC does not
    /// check, a closed connection); it is a finding only where no attempt comes through whole. 0: every
    /// first attempt is judged. Real targets only; pipelined batches are not run again.
    #[arg(long, default_value_t = 6, value_name = "N")]
    link_retries: u32,
    /// With --keep-going: stop after this many distinct findings (the same kind, case family and finding
    /// with other numbers is a repeat: counted, no second reproducer).
    #[arg(long, default_value_t = 20, value_name = "N")]
    max_findings: usize,
    /// Modbus/TCP: put up to N generated reads in flight at once, when the target answers a burst of N
    /// known-good reads sent in one write normally (sent before the first case; a FAIL of it is a finding).
    /// Only well-formed reads of FC 01-04 and the one-byte FC 07, 0B, 0C, 11 are pipelined; each is still
    /// judged alone, its answer taken by transaction id. A pipelined case left unanswered is asked again
    /// alone and judged so; after that, or after a pipelined case FAILs or is refused as busy, the rest of
    /// the campaign sends one request at a time. 1: one request at a time throughout.
    #[arg(long, default_value_t = 8, value_name = "N", value_parser = clap::value_parser!(u16).range(1..=engine::runner::MAX_IN_FLIGHT as i64))]
    pipeline: u16,
    /// With --allow-writes against a real drive: the state journal of the parameters read before the first
    /// write (default: a file in the temporary directory, named in the output, removed once every parameter
    /// reads as before); `restore --journal FILE` puts them back if the campaign could not.
    #[arg(long, value_name = "FILE")]
    journal: Option<PathBuf>,
}

/// Parse 30s / 10m / 1h / 500ms / a bare number of seconds.
fn parse_duration(s: &str) -> Option<Duration> {
    let s = s.trim();
    let (num, unit) = s
        .find(|c: char| !c.is_ascii_digit())
        .map_or((s, "s"), |i| s.split_at(i));
    let n: u64 = num.parse().ok()?;
    Some(match unit {
        "ms" => Duration::from_millis(n),
        "s" => Duration::from_secs(n),
        "m" => Duration::from_secs(n.checked_mul(60)?),
        "h" => Duration::from_secs(n.checked_mul(3600)?),
        _ => return None,
    })
}

/// Run `fuzz`: exit 0 without findings, 1 with findings, 2 when it could not run.
pub fn run(args: &FuzzArgs) -> ExitCode {
    let url = match TargetUrl::parse(&args.target) {
        Ok(u) => u,
        Err(e) => return unusable(e),
    };
    let Some(duration) = parse_duration(&args.duration).filter(|d| !d.is_zero()) else {
        return unusable(format!(
            "--duration `{}` is not a duration like 30s, 10m, 1h or 500ms",
            args.duration
        ));
    };
    let mut faults = FaultSet::none();
    for f in &args.faults {
        match f.parse::<Fault>() {
            Ok(f) => {
                faults.0.insert(f);
            }
            Err(e) => return unusable(e),
        }
    }
    let mut base = Options::new(url);
    base.profile = args.profile.clone();
    base.corpus = Corpus::Embedded;
    base.unit = args.unit;
    base.foreign = args.foreign_address;
    base.timing.timeout = Duration::from_millis(args.timeout.max(1));
    base.timing.silence = Duration::from_millis(args.silence.max(1));
    base.liveness = Some(engine::liveness::Liveness {
        probe_timeout: Duration::from_millis(args.preflight_timeout.max(1)),
        recovery: engine::liveness::Liveness::default().recovery,
    });
    base.faults = faults;
    base.safety.allow_motion = args.allow_motion;
    base.safety.allow_destructive = args.allow_destructive;
    base.safety.read_only = args.read_only;
    base.journal = args.journal.clone();
    base.timing.sentinel = !args.no_sentinel;
    base.timing.busy_wait = Duration::from_millis(args.busy_wait);
    base.timing.link_retries = args.link_retries;
    let regressions = args.regressions.clone().unwrap_or_else(|| {
        if std::path::Path::new("corpus").is_dir() {
            PathBuf::from("corpus/regressions")
        } else {
            PathBuf::from("regressions")
        }
    });
    let seed = args.seed.unwrap_or_else(clock_seed);
    let opts = CampaignOptions {
        base,
        duration,
        max_cases: args.max_cases,
        seed,
        probe_every: args.probe_every.max(1),
        keep_going: args.keep_going,
        regressions,
        allow_writes: args.allow_writes,
        max_findings: args.max_findings,
        pipeline: usize::from(args.pipeline),
    };
    let interrupt = Arc::new(AtomicBool::new(false));
    {
        let flag = interrupt.clone();
        let _ = ctrlc::set_handler(move || {
            if flag.swap(true, Ordering::SeqCst) {
                // Ends now, without putting back what the run changed: say how it can be.
                eprintln!(
                    "\ninterrupted again: exiting at once; anything changed is NOT put back (modbus-harness restore --journal FILE, with the journal the log named, puts it back)"
                );
                std::process::exit(130);
            }
        });
    }
    let tty = std::io::stderr().is_terminal();
    let mut log = std::io::stderr();
    let outcome = campaign(&opts, &mut log, &interrupt, |cases, rate, found| {
        if tty {
            eprint!("\r{cases} cases, {rate:.0} exec/s, {found} finding(s)   ");
        } else {
            eprintln!("{cases} cases, {rate:.0} exec/s, {found} finding(s)");
        }
    });
    if tty {
        eprintln!();
    }
    match outcome {
        Ok(o) => {
            for f in &o.findings {
                let kind = match f.kind {
                    FindingKind::StoppedAnswering => "STOPPED ANSWERING",
                    FindingKind::ProbeFails => "PROBE ANSWERED WRONGLY OR LATE",
                    FindingKind::Fail => "FAIL",
                };
                println!(
                    "{kind} after {}: {}",
                    f.case_id,
                    f.findings.first().cloned().unwrap_or_default()
                );
                if let Some(p) = &f.file {
                    println!(
                        "  reproducer {} ({} steps)",
                        p.display(),
                        f.reproducer.steps.len()
                    );
                }
                match f.replayed {
                    Some(true) => println!(
                        "  replayed: FAILs on a fresh faulted drive, PASSes on a healthy one"
                    ),
                    Some(false) => println!(
                        "  replayed: does NOT reproduce on a fresh drive (depends on earlier state)"
                    ),
                    None => println!("  not replayed: a real target cannot be reset from here"),
                }
            }
            println!(
                "fuzz: {} cases{}, {} probes in {:.1} s ({:.0} exec/s), {} requests ({:.0}/s), seed {}, {} finding(s){}; stopped by {}",
                o.cases,
                if o.pipelined > 0 {
                    format!(
                        " ({} pipelined, up to {} in flight)",
                        o.pipelined, o.pipelining.depth
                    )
                } else {
                    String::new()
                },
                o.probes,
                o.elapsed.as_secs_f64(),
                o.exec_per_sec(),
                o.requests,
                o.requests_per_sec(),
                o.seed,
                o.findings.len(),
                if o.repeats > 0 {
                    format!(" (+{} repeat(s) of them)", o.repeats)
                } else {
                    String::new()
                },
                o.stopped
            );
            if o.leave_as_found.as_ref().is_some_and(|a| !a.clean()) {
                ExitCode::from(Exit::NotRestored)
            } else if o.findings.is_empty() {
                ExitCode::from(Exit::Ok)
            } else {
                ExitCode::from(Exit::Failed)
            }
        }
        Err(e @ engine::session::SessionError::LeftChanged { .. }) => {
            eprintln!("error: {e}");
            ExitCode::from(Exit::NotRestored)
        }
        Err(e) => unusable(e),
    }
}
