//! The harness's side of bench/run.sh (BENCHMARKS.md): its request paths against a server that is already
//! running. Not a criterion bench: bench/run.sh starts the peers, pins everything to one core and runs this
//! binary once per figure. Each figure prints one `RESULT ...` line (see `support`).
//!
//!   wire raw tcp HOST:PORT SECS          TcpTarget send/recv, one FC 03 read at a time
//!   wire raw rtu DEVICE BAUD SECS        SerialTarget (8N1), the same
//!   wire runner tcp HOST:PORT SECS       Runner::run_case with the oracle in lockstep
//!   wire runner rtu DEVICE BAUD SECS
//!   wire pipeline HOST:PORT K SECS       K requests in flight
//!   wire inproc SECS                     codec and drive model, no sockets
//!   wire catalog-loop PROFILE CASES [REPORT_DIR]
//!                                        the sim: catalog repeated until CASES cases have run
//!
//! Without arguments (as `cargo bench` runs it) it prints this usage and exits 0.

extern crate modbus_harness_engine as engine;

mod support;

use std::process::ExitCode;

use support as bench;

const USAGE: &str = "usage: wire raw|runner tcp HOST:PORT SECS | raw|runner rtu DEVICE BAUD SECS | \
pipeline HOST:PORT K SECS | inproc SECS | catalog-loop PROFILE CASES [REPORT_DIR]";

fn num<T: std::str::FromStr>(s: Option<&String>, what: &str) -> Result<T, String> {
    s.ok_or_else(|| format!("missing {what}"))?
        .parse()
        .map_err(|_| format!("bad {what}"))
}

fn run(args: &[String]) -> Result<(), String> {
    let e = |e: bench::BenchError| e.to_string();
    match args.first().map(String::as_str) {
        Some(mode @ ("raw" | "runner")) => {
            let kind = args.get(1).ok_or("missing tcp|rtu")?;
            let addr = args.get(2).ok_or("missing address")?;
            let (baud, secs) = if kind == "rtu" {
                (
                    Some(num(args.get(3), "baud")?),
                    num(args.get(4), "seconds")?,
                )
            } else {
                (None, num(args.get(3), "seconds")?)
            };
            let target = bench::connect(kind, addr, baud).map_err(e)?;
            let stats = if mode == "raw" {
                let mut target = target;
                bench::raw(target.as_mut(), secs).map_err(e)?
            } else {
                bench::runner(target, &bench::generic_profile().map_err(e)?, secs).map_err(e)?
            };
            println!("{stats}");
        }
        Some("pipeline") => {
            let addr = args.get(1).ok_or("missing address")?;
            let k: usize = num(args.get(2), "K")?;
            let secs: f64 = num(args.get(3), "seconds")?;
            let mut target = bench::connect("tcp", addr, None).map_err(e)?;
            println!("{}", bench::pipelined(target.as_mut(), k, secs).map_err(e)?);
        }
        Some("inproc") => {
            let secs: f64 = num(args.get(1), "seconds")?;
            for r in bench::in_process(secs).map_err(e)? {
                println!("{r}");
            }
        }
        Some("catalog-loop") => {
            let profile = args.get(1).ok_or("missing profile")?;
            let cases: u64 = num(args.get(2), "cases")?;
            let report = args.get(3).map(std::path::Path::new);
            println!(
                "{}",
                bench::catalog_loop(profile, cases, report).map_err(e)?
            );
        }
        _ => return Err(USAGE.into()),
    }
    Ok(())
}

fn main() -> ExitCode {
    // `cargo bench` passes `--bench`; the figures need a peer, so a bare run only says how to use it.
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    if args.is_empty() {
        println!("{USAGE}\n(bench/run.sh runs this against the peers; see BENCHMARKS.md)");
        return ExitCode::SUCCESS;
    }
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(msg) => {
            eprintln!("wire: {msg}");
            ExitCode::from(2)
        }
    }
}
