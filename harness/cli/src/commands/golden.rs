//! `modbus-harness golden`: check every golden frame of the manuals and list the errata.

use crate::exit::Exit;
use std::path::Path;
use std::process::ExitCode;

use codec::hex_spaced;
use drives::corpus::Corpus;
use drives::golden::{GoldenFile, WordOrder, check_frame};
use drives::profile::Profile;

/// Run `golden`: exit 0 when every entry is consistent, 1 otherwise, 2 when the corpus cannot be read.
pub fn run(dir: Option<&Path>, verbose: bool) -> ExitCode {
    let corpus = Corpus::from_option(dir);
    let files = match corpus.files("golden") {
        Ok(f) if !f.is_empty() => f,
        Ok(_) => {
            eprintln!("error: no golden files in the {}", corpus.describe());
            return ExitCode::from(Exit::Unusable);
        }
        Err(e) => {
            eprintln!("error: reading the {}: {e}", corpus.describe());
            return ExitCode::from(Exit::Unusable);
        }
    };
    let (mut frames, mut errata, mut bad) = (0, 0, 0);
    for (name, text) in files {
        let g = match GoldenFile::parse(&name, &text) {
            Ok(g) => g,
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(Exit::Unusable);
            }
        };
        let order = corpus
            .file("profiles", &g.profile)
            .ok()
            .and_then(|(n, t)| Profile::parse(&n, &t).ok())
            .map(|p| p.device.word_order)
            .unwrap_or(WordOrder::HighFirst);
        println!("{} — {} ({} frames)", g.title, g.manual, g.frames.len());
        for f in &g.frames {
            frames += 1;
            let c = check_frame(f, order);
            let is_erratum = f.erratum.is_some();
            errata += usize::from(is_erratum);
            if !c.ok() {
                bad += 1;
            }
            if verbose || is_erratum || !c.ok() {
                let tag = match (c.ok(), is_erratum) {
                    (false, _) => "FAIL   ",
                    (true, true) => "ERRATUM",
                    (true, false) => "ok     ",
                };
                println!("  {tag} {}  (line {})", f.id, f.line);
                if let Some(p) = &f.printed {
                    println!("          printed   {p}");
                }
                if is_erratum {
                    println!("          corrected {}", hex_spaced(&c.bytes));
                }
                if let Some(e) = &f.erratum {
                    println!("          erratum   {e}");
                }
                if let Some(faults) = &c.printed_faults {
                    for fault in faults {
                        println!("          printed → {fault}");
                    }
                    if faults.is_empty() {
                        println!(
                            "          printed bytes decode and meet every expectation: the erratum is not shown"
                        );
                    }
                }
                if let Err(e) = &c.decoded {
                    println!("          used bytes do not decode: {e}");
                }
                for m in c.mismatches.iter().chain(&c.entry_errors) {
                    println!("          {m}");
                }
            }
        }
    }
    println!("\n{frames} golden frames, {errata} with corrected bytes, {bad} inconsistent");
    if bad == 0 {
        ExitCode::from(Exit::Ok)
    } else {
        ExitCode::from(Exit::Failed)
    }
}

/// Print the errata index (corpus/golden/README.md) generated from the golden files.
pub fn markdown(dir: Option<&Path>) -> ExitCode {
    let corpus = Corpus::from_option(dir);
    match corpus
        .golden_files()
        .map(|g| drives::golden::errata_markdown(&g))
    {
        Ok(md) => {
            print!("{md}");
            ExitCode::from(Exit::Ok)
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(Exit::Unusable)
        }
    }
}
