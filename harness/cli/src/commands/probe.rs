//! `modbus-harness probe`: what a target answers, beside its profile.

use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use drives::corpus::Corpus;
use drives::{self, FaultSet, Station};
use engine::probe;
use engine::targets::{self, TargetUrl};

/// Arguments of `probe`.
#[derive(Args)]
pub struct ProbeArgs {
    /// The endpoint (tcp://, rtu+tcp://, rtu://, sim:).
    #[arg(long)]
    target: String,
    /// A profile to compare with (for sim: targets, the simulator's own by default).
    #[arg(long)]
    profile: Option<String>,
    /// Unit id / slave address.
    #[arg(long, default_value_t = 1)]
    unit: u8,
    /// Register addresses to scan, inclusive, e.g. 0-0x1FF or 2000-2030.
    #[arg(long, default_value = "0-0xFF")]
    scan: String,
    /// Per-request timeout in milliseconds.
    #[arg(long, default_value_t = 500, value_name = "MS")]
    timeout: u64,
}

fn parse_u16(s: &str) -> Option<u16> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u16::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

/// Run `probe`: exit 0 when it ran, 2 when it could not.
pub fn run(args: &ProbeArgs) -> ExitCode {
    let url = match TargetUrl::parse(&args.target) {
        Ok(u) => u,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let scan = match args
        .scan
        .split_once('-')
        .and_then(|(a, b)| Some((parse_u16(a)?, parse_u16(b)?)))
    {
        Some((a, b)) if a <= b && b - a <= 4096 => (a, b),
        _ => {
            eprintln!(
                "error: --scan `{}` must be START-END with at most 4097 addresses (e.g. 0-0xFF)",
                args.scan
            );
            return ExitCode::from(2);
        }
    };
    let corpus = Corpus::Embedded;
    let profile_name = args.profile.clone().or(match &url {
        TargetUrl::Sim { profile, .. } => Some(profile.clone()),
        _ => None,
    });
    let profile = match profile_name.as_deref().map(|n| corpus.profile(n)) {
        Some(Ok(p)) => Some(p),
        Some(Err(e)) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
        None => None,
    };
    let unit = args.unit;
    let mut t = match targets::open(
        &url,
        |name| {
            let p = corpus.profile(name)?;
            Ok(Station::new(
                drives::build(p, FaultSet::none()),
                FaultSet::none(),
                unit,
            ))
        },
        Duration::from_secs(3),
    ) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    eprintln!(
        "probing {} (unit {unit}), scanning 0x{:04X}-0x{:04X} ...",
        t.describe(),
        scan.0,
        scan.1
    );
    match probe::probe(
        t.as_mut(),
        unit,
        Duration::from_millis(args.timeout.max(1)),
        scan,
    ) {
        Ok(r) => {
            print!("{}", probe::render(&r, profile.as_ref(), scan));
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
