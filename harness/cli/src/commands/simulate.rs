//! `modbus-harness simulate`: serve a reference drive over Modbus/TCP, RTU over TCP and/or a serial line.

use crate::exit::Exit;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Args, ValueEnum};
use codec::framer::Parity;
use drives::corpus::Corpus;
use drives::profile::ParityName;
use drives::{self, Fault, FaultSet, Station};
use engine::servers::{self, SerialConfig, ServerConfig, ServerHandle};

/// Arguments of `simulate`.
#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// The drive to serve: a corpus profile's name (sd2x, mdrive, lmd, generic, or those of --corpus), or a
    /// profile file (a value containing `/` or ending in `.toml` is a file: ./my.toml, /abs/drive.toml).
    /// A profile whose device.id is sd2x, mdrive or lmd gets that drive's model; any other, the generic one.
    #[arg(
        long,
        value_name = "NAME|PATH",
        required_unless_present = "list_faults"
    )]
    profile: Option<String>,
    /// Serve Modbus/TCP on this address (port 0: any free port; the bound one is printed).
    #[arg(long, value_name = "ADDR")]
    listen: Option<SocketAddr>,
    /// Serve RTU frames inside TCP on this address.
    #[arg(long, value_name = "ADDR")]
    rtu_over_tcp: Option<SocketAddr>,
    /// Serve RTU on this serial device or pty.
    #[arg(long, value_name = "PATH")]
    serial: Option<PathBuf>,
    /// Serial baud rate (default: the profile's, else 19200).
    #[arg(long, requires = "serial")]
    baud: Option<u32>,
    /// Serial parity (default: the profile's, else even as the serial line spec says).
    #[arg(long, value_enum, requires = "serial")]
    parity: Option<ParityArg>,
    /// Serial stop bits (default: the profile's, else 1).
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=2), requires = "serial")]
    stop: Option<u8>,
    /// Unit id / slave address to answer as (default: the profile's default unit).
    #[arg(long)]
    unit: Option<u8>,
    /// Inject a fault (repeatable); see --list-faults.
    #[arg(long = "fault", value_name = "NAME", value_parser = parse_fault)]
    faults: Vec<Fault>,
    /// Take VALUE where the specs and manuals leave a choice (repeatable), e.g.
    /// `value-out-of-range=4`, `mdrive-hybrid-only=exception-02`: a drive of independent authorship that
    /// conforms all the same. The freedoms are in corpus/freedoms/; `run --list-requirements` lists them.
    #[arg(long = "choose", value_name = "FREEDOM=VALUE")]
    choose: Vec<String>,
    /// Print every fault with what it does, and exit.
    #[arg(long)]
    list_faults: bool,
    /// Corpus directory (default: the corpus built into the binary).
    #[arg(long, value_name = "DIR")]
    corpus: Option<PathBuf>,
    /// Record every write the drive accepts as a JSON line (time, unit, function code, table or mnemonic,
    /// address, old and new value), flushed per write, so that tests can assert what a run did.
    #[arg(long, value_name = "FILE")]
    journal: Option<PathBuf>,
    /// Start with this value instead of the factory one (repeatable): `holding:ADDR=VALUE` (ADDR a number or
    /// the register's name or mnemonic, VALUE in the register's width; `holding:` may be left out),
    /// `coil:ADDR=0|1`, `mnemonic:NAME=PARAMS` (e.g. mnemonic:S1=0,1,0).
    #[arg(long = "set", value_name = "TABLE:ADDR=VALUE")]
    set: Vec<String>,
    /// Start with the values of this file: one --set value a line, `#` comments.
    #[arg(long, value_name = "FILE")]
    preset: Option<PathBuf>,
    /// A holding register that keeps the first value written to it that changes it, and acknowledges later
    /// writes without taking them (repeatable; a drive that latches a setting until power cycle).
    #[arg(long = "latch", value_name = "ADDR", value_parser = parse_address)]
    latch: Vec<u16>,
    /// A 16-bit holding register that reads off its value by up to N counts (+1, -1, +2, -2, 0, ...) from
    /// its K-th read on (default 0), as a measured value on a drive with its motor attached (repeatable;
    /// the stored value does not change).
    #[arg(long = "jitter", value_name = "ADDR=N[@K]", value_parser = parse_jitter)]
    jitter: Vec<(u16, u16, u32)>,
}

fn parse_jitter(s: &str) -> Result<(u16, u16, u32), String> {
    let (addr, rest) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected ADDR=N[@K], e.g. 0x0005=2@20"))?;
    let (n, k) = rest.split_once('@').unwrap_or((rest, "0"));
    let n = n
        .parse()
        .map_err(|e| format!("`{s}`: the amplitude `{n}` is not a count: {e}"))?;
    let k = k
        .parse()
        .map_err(|e| format!("`{s}`: the reads before it starts, `{k}`, is not a count: {e}"))?;
    Ok((parse_address(addr)?, n, k))
}

fn parse_address(s: &str) -> Result<u16, String> {
    let r = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u16::from_str_radix(h, 16),
        None => s.parse(),
    };
    r.map_err(|e| format!("`{s}` is not a register address: {e}"))
}

/// A journal sink: one JSON line per accepted write, written at once (no buffering).
fn journal_sink(path: &std::path::Path) -> Result<drives::tell::WriteSink, String> {
    use drives::tell::{Shown, WriteRecord, Written};
    let file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| format!("cannot open the journal {}: {e}", path.display()))?;
    let file = std::sync::Mutex::new(file);
    let value = |v: &Shown| match v {
        Shown::Words(w) => serde_json::json!(w),
        Shown::Bits(b) => serde_json::json!(b.iter().map(|b| u8::from(*b)).collect::<Vec<_>>()),
        Shown::Text(t) => serde_json::json!(t),
        Shown::Bytes(b) => serde_json::json!(codec::hex_spaced(b)),
        Shown::Unreadable => serde_json::Value::Null,
    };
    Ok(std::sync::Arc::new(move |r: &WriteRecord| {
        let unix_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        let mnemonic = match &r.written {
            Written::Setting(m) => Some(m.name().trim().to_string()),
            _ => None,
        };
        let line = serde_json::json!({
            "unix_ms": unix_ms,
            "station_us": r.at.as_micros() as u64,
            "unit": r.unit,
            "fc": r.function.0,
            "table": r.written.table(),
            "mnemonic": mnemonic,
            "address": r.address,
            "old": value(&r.old),
            "new": value(&r.new),
        });
        // One write per record: a reader never sees two records interleaved, at worst the last one partial.
        let mut text = line.to_string();
        text.push('\n');
        let mut f = file.lock().unwrap_or_else(|e| e.into_inner());
        let _ = f.write_all(text.as_bytes());
        let _ = f.flush();
    }))
}

/// Parity on the command line.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum ParityArg {
    None,
    Even,
    Odd,
}

fn parse_fault(s: &str) -> Result<Fault, drives::faults::UnknownFault> {
    s.parse()
}

/// How long shutdown may take before the process gives up on stragglers.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);

/// Run `simulate`: exit 0 after a clean stop (SIGINT/SIGTERM), 2 on unusable arguments, 1 when serving failed
/// (the runtime, or an endpoint such as a serial line that stopped working).
pub fn run(args: SimulateArgs) -> ExitCode {
    if args.list_faults {
        let width = Fault::ALL.iter().map(|f| f.1.len()).max().unwrap_or(0);
        for (_, name, what) in Fault::ALL {
            println!("{name:width$}  {what}");
        }
        return ExitCode::from(Exit::Ok);
    }
    let (station, config, summary) = match prepare(&args) {
        Ok(x) => x,
        Err(msg) => {
            eprintln!("error: {msg}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    // Two workers at most: the machines this runs on have two cores, and a client usually shares them.
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get().min(2));
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(workers)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("error: cannot start the runtime: {e}");
            return ExitCode::from(Exit::Failed);
        }
    };
    rt.block_on(serve(station, config, summary))
}

async fn serve(station: Station, config: ServerConfig, summary: String) -> ExitCode {
    let mut signals = StopSignals::install();
    let mut handle = match servers::start(station, &config).await {
        Ok(h) => h,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(Exit::Unusable);
        }
    };
    eprintln!("simulate: {summary}");
    print_endpoints(&handle);
    let code = tokio::select! {
        signal = signals.recv() => {
            eprintln!("simulate: {signal}, stopping");
            ExitCode::from(Exit::Ok)
        }
        // A simulator that silently lost its serial line would look alive to whoever started it.
        _ = handle.endpoint_stopped() => {
            eprintln!("simulate: an endpoint stopped serving (error above), stopping");
            ExitCode::from(Exit::Failed)
        }
    };
    if tokio::time::timeout(SHUTDOWN_GRACE, handle.shutdown())
        .await
        .is_err()
    {
        eprintln!("simulate: connections still open after {SHUTDOWN_GRACE:?}, exiting anyway");
    }
    code
}

/// One line per endpoint on stdout, flushed at once: scripts and tests wait for these lines.
fn print_endpoints(handle: &ServerHandle) {
    let mut out = std::io::stdout().lock();
    if let Some(a) = handle.tcp_addr() {
        let _ = writeln!(out, "listening tcp {a}");
    }
    if let Some(a) = handle.rtu_over_tcp_addr() {
        let _ = writeln!(out, "listening rtu-over-tcp {a}");
    }
    if let Some(s) = handle.serial() {
        let _ = writeln!(
            out,
            "listening serial {} {}",
            s.path.display(),
            s.describe()
        );
    }
    let _ = out.flush();
}

/// The signals that stop the simulator, watched from before the listening lines are printed: a script that
/// signals right after reading them must not meet the default action (death by signal, not a clean exit).
struct StopSignals {
    int: Option<tokio::signal::unix::Signal>,
    term: Option<tokio::signal::unix::Signal>,
}

impl StopSignals {
    fn install() -> Self {
        use tokio::signal::unix::{SignalKind, signal};
        let watch = |kind: SignalKind, name: &str| match signal(kind) {
            Ok(s) => Some(s),
            Err(e) => {
                eprintln!("simulate: cannot watch {name} ({e})");
                None
            }
        };
        Self {
            int: watch(SignalKind::interrupt(), "SIGINT"),
            term: watch(SignalKind::terminate(), "SIGTERM"),
        }
    }

    /// Resolves on SIGINT (Ctrl-C) or SIGTERM, naming the signal.
    async fn recv(&mut self) -> &'static str {
        async fn on(s: &mut Option<tokio::signal::unix::Signal>) {
            match s {
                Some(s) => {
                    s.recv().await;
                }
                None => std::future::pending::<()>().await,
            }
        }
        tokio::select! {
            _ = on(&mut self.int) => "SIGINT",
            _ = on(&mut self.term) => "SIGTERM",
        }
    }
}

/// Load the profile, check the arguments against it, build the station and the endpoint list.
fn prepare(args: &SimulateArgs) -> Result<(Station, ServerConfig, String), String> {
    let name = args.profile.as_deref().unwrap_or_default();
    let corpus = Corpus::from_option(args.corpus.as_deref());
    let profile = corpus.load(name).map_err(|e| e.to_string())?;
    if args.listen.is_none() && args.rtu_over_tcp.is_none() && args.serial.is_none() {
        return Err(
            "nothing to serve: give at least one of --listen ADDR, --rtu-over-tcp ADDR, --serial PATH"
                .into(),
        );
    }
    let [lo, hi] = profile.device.unit_ids;
    let unit = args.unit.unwrap_or(profile.device.default_unit);
    if !(lo..=hi).contains(&unit) {
        return Err(format!(
            "unit {unit} is not a unit id of profile {} (allowed: {lo}..={hi})",
            profile.device.id
        ));
    }
    if unit == 0 && (args.serial.is_some() || args.rtu_over_tcp.is_some()) {
        return Err(
            "unit 0 is the RTU broadcast address, not a slave address: give --unit 1..=247 for RTU"
                .into(),
        );
    }
    let serial = args.serial.as_ref().map(|path| {
        let ps = profile.serial.as_ref();
        let parity = match args.parity {
            Some(ParityArg::None) => Parity::None,
            Some(ParityArg::Even) => Parity::Even,
            Some(ParityArg::Odd) => Parity::Odd,
            None => match ps.map(|s| s.default_parity) {
                Some(ParityName::None) => Parity::None,
                Some(ParityName::Odd) => Parity::Odd,
                Some(ParityName::Even) | None => Parity::Even,
            },
        };
        SerialConfig {
            path: path.clone(),
            baud: args.baud.or(ps.map(|s| s.default_baud)).unwrap_or(19_200),
            parity,
            stop_bits: args.stop.or(ps.map(|s| s.stop_bits)).unwrap_or(1),
        }
    });
    if let Some(s) = &serial {
        if s.baud == 0 {
            return Err("--baud must be above 0".into());
        }
    }
    let faults = FaultSet::of(&args.faults);
    let fault_names = if args.faults.is_empty() {
        "none".to_string()
    } else {
        args.faults
            .iter()
            .map(|f| f.name())
            .collect::<Vec<_>>()
            .join(", ")
    };
    let choices = if args.choose.is_empty() {
        drives::Choices::reference()
    } else {
        let requirements = corpus.requirements().map_err(|e| e.to_string())?;
        drives::Choices::parse_all(&args.choose, &requirements, &profile)
            .map_err(|e| e.to_string())?
    };
    let summary = format!(
        "profile {} ({}), unit {unit}, faults: {fault_names}, choices: {choices}",
        profile.device.id, profile.device.name
    );
    let mut station = Station::new(
        drives::build_with(profile, faults.clone(), choices.clone()),
        faults,
        unit,
    )
    .with_choices(choices)
    .with_latched(args.latch.iter().copied());
    for &(address, amplitude, after) in &args.jitter {
        station = station.with_jitter(address, amplitude, after);
    }
    let mut presets = Vec::new();
    if let Some(p) = &args.preset {
        let text = std::fs::read_to_string(p)
            .map_err(|e| format!("cannot read the preset {}: {e}", p.display()))?;
        presets.extend(drives::tell::preset_lines(&text));
    }
    presets.extend(args.set.iter().cloned());
    drives::tell::apply_presets(station.model_mut(), unit, &presets).map_err(|e| e.to_string())?;
    if let Some(j) = &args.journal {
        station = station.with_write_sink(journal_sink(j)?);
    }
    let summary = format!(
        "{summary}{}",
        if presets.is_empty() {
            String::new()
        } else {
            format!(", {} preset value(s)", presets.len())
        }
    );
    let config = ServerConfig {
        tcp: args.listen,
        rtu_over_tcp: args.rtu_over_tcp,
        serial,
        ..ServerConfig::default()
    };
    Ok((station, config, summary))
}
