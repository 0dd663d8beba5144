//! In-process figures (BENCHMARKS.md): codec encode+decode per frame, the station answering request bytes,
//! and the drive model answering a typed request, without sockets.
//!
//!   cargo bench --bench inproc [-- SECS]     SECS per figure, default 1

extern crate modbus_harness_engine as engine;

// The drivers of bench/run.sh's figures; this bench runs the in-process ones only.
#[allow(dead_code)]
mod support;

use std::process::ExitCode;

fn main() -> ExitCode {
    let secs = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with("--"))
        .and_then(|a| a.parse::<f64>().ok())
        .unwrap_or(1.0);
    match support::in_process(secs) {
        Ok(figures) => {
            for f in figures {
                println!("{f}");
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("inproc: {e}");
            ExitCode::FAILURE
        }
    }
}
