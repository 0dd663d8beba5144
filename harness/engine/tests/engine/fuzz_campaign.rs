//! The live fuzz campaign finds a drive that stops answering within a bounded number of cases, writes a
//! reproducer that stops the faulted simulator and not a healthy one, and finds nothing on a healthy drive.

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use drives::{Fault, FaultSet};
use engine::Verdict;
use engine::campaign::{CampaignOptions, FindingKind, campaign};
use engine::session::{Options, run};
use engine::targets::TargetUrl;
use test_support::TempDir;

fn options(faults: &[Fault], dir: &std::path::Path, keep_going: bool) -> CampaignOptions {
    let mut base = Options::new(TargetUrl::parse("sim:mdrive").unwrap());
    base.faults = FaultSet::of(faults);
    CampaignOptions {
        base,
        duration: Duration::from_secs(60),
        max_cases: Some(3000),
        seed: 11,
        probe_every: 10,
        keep_going,
        regressions: dir.to_path_buf(),
        allow_writes: false,
    }
}

#[test]
fn finds_a_drive_that_stops_answering_and_keeps_a_reproducer() {
    // A private copy of the corpus: the reproducer lands in its regressions/, and runs replay from it.
    let dir = TempDir::new("fuzz-campaign");
    let corpus = dir.path().join("corpus");
    let status = std::process::Command::new("cp")
        .args(["-r", concat!(env!("CARGO_MANIFEST_DIR"), "/../../corpus")])
        .arg(&corpus)
        .status()
        .expect("cp");
    assert!(status.success());
    let o = options(
        &[Fault::StopAfterMalformed],
        &corpus.join("regressions"),
        true,
    );
    let out = campaign(
        &o,
        &mut std::io::sink(),
        &AtomicBool::new(false),
        |_, _, _| {},
    )
    .expect("campaign");
    let stop = out
        .findings
        .iter()
        .find(|f| f.kind == FindingKind::StoppedAnswering)
        .expect("the liveness probe notices the dead drive");
    assert!(out.cases <= 3000, "bounded: {} cases", out.cases);
    assert_eq!(
        stop.replayed,
        Some(true),
        "the reproducer stops the faulted drive and not a healthy one"
    );
    let file = stop.file.as_ref().expect("reproducer written");
    assert!(file.is_file());
    // Replayed as a regression case through a normal run: FAIL on the faulted drive, PASS on a healthy one.
    for (faults, want) in [
        (vec![Fault::StopAfterMalformed], Verdict::Fail),
        (vec![], Verdict::Pass),
    ] {
        let mut r = Options::new(TargetUrl::parse("sim:mdrive").unwrap());
        r.corpus = drives::corpus::Corpus::Dir(corpus.clone());
        r.include = vec![stop.reproducer.id.clone()];
        r.faults = FaultSet::of(&faults);
        r.keep_verdicts = true;
        let got = run(
            &r,
            &mut std::io::sink(),
            &AtomicBool::new(false),
            &mut |_, _, _, _| {},
        )
        .expect("run");
        assert_eq!(
            got.verdicts.len(),
            1,
            "the reproducer is in the catalog: {:?}",
            got.verdicts
        );
        assert_eq!(got.verdicts[0].1, want, "faults {faults:?}");
    }
}

#[test]
fn a_healthy_drive_gives_no_finding() {
    let dir = TempDir::new("fuzz-healthy");
    let mut o = options(&[], dir.path(), false);
    o.max_cases = Some(1500);
    let out = campaign(
        &o,
        &mut std::io::sink(),
        &AtomicBool::new(false),
        |_, _, _| {},
    )
    .expect("campaign");
    assert_eq!(out.cases, 1500);
    assert!(
        out.findings.is_empty(),
        "{:?}",
        out.findings.iter().map(|f| &f.findings).collect::<Vec<_>>()
    );
}
