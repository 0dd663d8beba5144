//! Replays every file of `fuzz/corpus/<target>/` through the fuzz target functions on stable Rust, so CI
//! exercises the seeds and every crash regression without libFuzzer.
//!
//! `cargo test --manifest-path fuzz/Cargo.toml --test fuzz_corpus -- --ignored write_seed_corpus` rewrites
//! the `seed-*` files from the embedded golden frames and the case catalog (after an input format or the
//! corpus changed); other files (regressions, inputs the fuzzer found) are kept.

use std::fs;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use drives::{Fault, FaultSet};
use modbus_harness_fuzz::{self as fuzzing, TARGETS};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf()
}

fn corpus_files(target: &str) -> Vec<PathBuf> {
    let dir = fuzz_dir().join("corpus").join(target);
    let mut files: Vec<PathBuf> = fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("a directory entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
}

/// Run every corpus file of `target`; report all the files that panic, not only the first.
fn replay(target: &str) {
    let run = fuzzing::target(target).expect("a known target");
    let files = corpus_files(target);
    assert!(!files.is_empty(), "fuzz/corpus/{target}/ has no inputs");
    let failed: Vec<String> = files
        .iter()
        .filter(|path| {
            let data = fs::read(path).expect("a readable corpus file");
            catch_unwind(AssertUnwindSafe(|| run(&data))).is_err()
        })
        .map(|path| path.display().to_string())
        .collect();
    assert!(
        failed.is_empty(),
        "{} of {} {target} inputs fail (panic messages above): {failed:#?}",
        failed.len(),
        files.len()
    );
}

#[test]
fn tcp_adu_corpus() {
    replay("tcp_adu");
}

#[test]
fn rtu_framer_corpus() {
    replay("rtu_framer");
}

#[test]
fn response_validation_corpus() {
    replay("response_validation");
}

#[test]
fn drive_model_corpus() {
    replay("drive_model");
}

#[test]
fn differential_corpus() {
    replay("differential");
}

#[test]
fn every_target_has_a_libfuzzer_binary() {
    let manifest = fs::read_to_string(fuzz_dir().join("Cargo.toml")).expect("fuzz/Cargo.toml");
    for target in TARGETS {
        assert!(
            manifest.contains(&format!("name = \"{target}\"")),
            "fuzz/Cargo.toml has no [[bin]] {target}"
        );
        assert!(
            fuzz_dir()
                .join("fuzz_targets")
                .join(format!("{target}.rs"))
                .is_file(),
            "fuzz/fuzz_targets/{target}.rs is missing"
        );
    }
}

#[test]
#[ignore = "rewrites fuzz/corpus/*/seed-*; run after changing an input format or the corpus"]
fn write_seed_corpus() {
    for target in TARGETS {
        fs::create_dir_all(fuzz_dir().join("corpus").join(target)).expect("a corpus directory");
        for path in corpus_files(target) {
            if path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("seed-"))
            {
                fs::remove_file(&path).expect("removable seed");
            }
        }
    }
    let seeds = fuzzing::seeds();
    for seed in &seeds {
        let path = fuzz_dir().join("corpus").join(seed.target).join(&seed.name);
        fs::write(&path, &seed.bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    }
    for target in TARGETS {
        let n = seeds.iter().filter(|s| s.target == target).count();
        println!("{target}: {n} seeds");
    }
}

/// The drive_model invariants are not vacuous: for each wire-level fault, some corpus input makes the target
/// fail against a drive with that fault.
#[test]
fn drive_model_corpus_catches_wire_faults() {
    let inputs: Vec<Vec<u8>> = corpus_files("drive_model")
        .iter()
        .map(|p| fs::read(p).expect("a readable corpus file"))
        .collect();
    let missed: Vec<&str> = [
        "wrong-function-code",
        "exception-without-fc",
        "tid-not-echoed",
        "unit-not-echoed",
        "mbap-length",
        "wrong-crc",
        "truncated-response",
        "late-response",
        "stop-after-malformed",
        "answer-other-unit",
        "broadcast-answered",
    ]
    .into_iter()
    .filter(|name| {
        let faults = FaultSet::of(&[name.parse::<Fault>().expect("a known fault")]);
        !inputs.iter().any(|data| {
            catch_unwind(AssertUnwindSafe(|| {
                fuzzing::drive_model_with_faults(data, &faults)
            }))
            .is_err()
        })
    })
    .collect();
    assert!(missed.is_empty(), "no drive_model input catches {missed:?}");
}
