//! `modbus-harness probe`: what a target answers, beside its profile, or as a draft profile.

use crate::exit::{Exit, unusable};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{self, FaultSet, Station};
use engine::probe::{self, ProbeOptions, draft};
use engine::targets::{self, TargetUrl};

/// What `probe --help` says after the options.
const PROBE_HELP: &str = "\
What is sent:
  By default only requests that read: FC 01, 02, 03, 04 (one address at a time over --scan), 07, 08/00
  (Return Query Data: an echo), 0B, 0C, 11 and 2B (MEI 0E device identification, else MEI 0D a CANopen
  object read), and on Modbus/TCP one read to each of the unit ids 0, 1, 247 and 255. No request with a
  write function code is sent. --probe-writes adds, for each write code, one request the Modbus spec
  requires a drive to reject before writing anything: FC 05 with the value 0x1234, FC 0F, 10 and 17 with
  quantity 0; and the vendor codes 0x41/0x42 with the mnemonic QQ that no MDrive/LMD knows (other vendors
  give 0x41-0x48 meanings of their own: leave --probe-writes out on a drive of unknown make). FC 06 is never
  sent: every FC 06 request is a valid write.

Draft profile:
  --write-profile FILE writes what the probe found as a profile to start from: the function codes answered,
  the readable holding and input register ranges, coils and discrete inputs (as blocks), the FC 2B/0E
  identification objects, the unit ids and the transport. Every entry is marked `confirmed = false`: reads
  cannot show widths, ranges or access, so the draft claims none, and `run --profile FILE` only reads what
  it lists. See the README section \"Test your own drive\" and corpus/profiles/SCHEMA.md.";

/// Arguments of `probe`.
#[derive(Args)]
#[command(after_help = PROBE_HELP)]
pub struct ProbeArgs {
    /// The endpoint (tcp://, rtu+tcp://, rtu://, sim:PROFILE, sim:PATH.toml).
    #[arg(long)]
    target: String,
    /// A profile to compare with (for sim: targets, the simulator's own by default): a corpus profile's
    /// name, or a profile file (a value containing `/` or ending in `.toml`, e.g. ./my.toml).
    #[arg(long, value_name = "NAME|PATH")]
    profile: Option<String>,
    /// Unit id / slave address.
    #[arg(long, default_value_t = 1)]
    unit: u8,
    /// Addresses to read one by one (registers, coils, discrete inputs), inclusive, e.g. 0-0x1FF or 2000-2030.
    #[arg(long, default_value = "0-0xFF")]
    scan: String,
    /// How long the first read (the pre-flight) waits for an answer, in milliseconds: a target that gives
    /// none is not scanned (exit 2, with the likely causes).
    #[arg(long, default_value_t = 3000, value_name = "MS")]
    preflight_timeout: u64,
    /// Per-request timeout in milliseconds.
    #[arg(long, default_value_t = 500, value_name = "MS")]
    timeout: u64,
    /// Also probe the write function codes (05, 0F, 10, 17) and the vendor codes 0x41/0x42, each with a
    /// request a drive must reject before writing (see below).
    #[arg(long)]
    probe_writes: bool,
    /// Read requests only (the default, said explicitly as for `run` and `fuzz`; refuses --probe-writes).
    #[arg(long, conflicts_with = "probe_writes")]
    read_only: bool,
    /// Write a draft profile of what the probe found to FILE (every entry `confirmed = false`).
    #[arg(long, value_name = "FILE")]
    write_profile: Option<PathBuf>,
    /// With --write-profile: replace FILE if it exists (without it, an existing file is left alone).
    #[arg(long, requires = "write_profile")]
    force: bool,
}

fn parse_u16(s: &str) -> Option<u16> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u16::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

/// Write `text` to `path` whole or not at all (a temporary file beside it, then renamed).
fn write_atomically(path: &Path, text: &str) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        path.file_name()
            .map_or_else(|| "profile".into(), |n| n.to_string_lossy()),
        std::process::id()
    ));
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, path).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

/// Run `probe`: exit 0 when it ran, 2 when it could not.
pub fn run(args: &ProbeArgs) -> ExitCode {
    let url = match TargetUrl::parse(&args.target) {
        Ok(u) => u,
        Err(e) => return unusable(e),
    };
    let scan = match args
        .scan
        .split_once('-')
        .and_then(|(a, b)| Some((parse_u16(a)?, parse_u16(b)?)))
    {
        Some((a, b)) if a <= b && b - a <= 4096 => (a, b),
        _ => {
            return unusable(format!(
                "--scan `{}` must be START-END with at most 4097 addresses (e.g. 0-0xFF)",
                args.scan
            ));
        }
    };
    // Checked before anything is sent: a draft must not replace a profile someone has edited.
    if let Some(f) = &args.write_profile {
        if f.exists() && !args.force {
            return unusable(format!(
                "{} exists: not replaced (choose another file, or --force to replace it)",
                f.display()
            ));
        }
        if f.is_dir() {
            return unusable(format!("{} is a directory", f.display()));
        }
    }
    let corpus = Corpus::Embedded;
    let profile_name = args.profile.clone().or(match &url {
        TargetUrl::Sim { profile, .. } => Some(profile.clone()),
        _ => None,
    });
    let profile: Option<Profile> = match profile_name.as_deref().map(|n| corpus.load(n)) {
        Some(Ok(p)) => Some(p),
        Some(Err(e)) => return unusable(e),
        None => None,
    };
    let unit = args.unit;
    let mut t = match targets::open(
        &url,
        |name| {
            let p = corpus.load(name)?;
            Ok(Station::new(
                drives::build(p, FaultSet::none()),
                FaultSet::none(),
                unit,
            ))
        },
        Duration::from_secs(3),
    ) {
        Ok(t) => t,
        Err(e) => return unusable(e),
    };
    // Pre-flight: a known-good read (the profile's, else holding register 0; an exception answer counts).
    if !url.is_sim() {
        let pdu = profile.as_ref().map_or_else(
            || vec![0x03, 0x00, 0x00, 0x00, 0x01],
            engine::cases::catalog::known_good_read,
        );
        let framing = t.framing();
        let request = engine::liveness::frame(&pdu, framing, unit, 0x5046);
        let bound = Duration::from_millis(args.preflight_timeout.max(1));
        let heard = match engine::liveness::ask(t.as_mut(), &request, bound) {
            Ok(h) => h,
            Err(e) => return unusable(e),
        };
        if let Some(m) = engine::liveness::preflight_failure(
            &t.describe(),
            &heard,
            &request,
            framing,
            match url {
                TargetUrl::Serial { echo, .. } => Some(echo),
                _ => None,
            },
            unit,
            bound,
        ) {
            return unusable(m);
        }
    }
    eprintln!(
        "probing {} (unit {unit}), scanning 0x{:04X}-0x{:04X}{} ...",
        t.describe(),
        scan.0,
        scan.1,
        if args.probe_writes {
            ", write codes with requests a drive must reject"
        } else {
            ", read requests only"
        }
    );
    let options = ProbeOptions {
        unit,
        timeout: Duration::from_millis(args.timeout.max(1)),
        scan,
        writes: args.probe_writes,
        unread: profile.as_ref().map(probe::unread_of).unwrap_or_default(),
    };
    let report = match probe::probe(t.as_mut(), &options) {
        Ok(r) => r,
        Err(e) => return unusable(e),
    };
    print!("{}", probe::render(&report, profile.as_ref(), scan));
    // A target that stopped answering mid-probe: what was found is printed, no draft is written from it.
    if let Some(why) = &report.stopped {
        return unusable(format!(
            "{why}{}",
            if args.write_profile.is_some() {
                "; no draft profile written"
            } else {
                ""
            }
        ));
    }
    let Some(file) = &args.write_profile else {
        return ExitCode::from(Exit::Ok);
    };
    let text = draft::write(&report, &url, unit, scan);
    let loaded = match Profile::parse(&file.display().to_string(), &text) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("{text}");
            return unusable(format!(
                "internal: the draft does not load ({e}); not written"
            ));
        }
    };
    if let Err(e) = write_atomically(file, &text) {
        return unusable(format!("cannot write {}: {e}", file.display()));
    }
    println!(
        "\ndraft profile `{}` written to {}: {} function code(s), {} register(s), {} coil(s), {} discrete input(s), \
{} identification object(s), all unconfirmed.\nNext: confirm widths, access and ranges in it (README: \"Test your own drive\"), \
then: modbus-harness run --target {url} --profile {}",
        loaded.device.id,
        file.display(),
        loaded.functions.len(),
        loaded.registers.len(),
        loaded.coils.len(),
        loaded.discrete_inputs.len(),
        loaded.identification.len(),
        file.display()
    );
    ExitCode::from(Exit::Ok)
}
