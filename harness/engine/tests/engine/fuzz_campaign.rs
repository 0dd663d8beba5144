//! The live fuzz campaign finds a drive that stops answering within a bounded number of cases, writes a
//! reproducer that stops the faulted simulator and not a healthy one, and finds nothing on a healthy drive.

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use drives::{Fault, FaultSet};
use engine::Verdict;
use engine::campaign::{CampaignFinding, CampaignOptions, CampaignOutcome, FindingKind, campaign};
use engine::session::{Options, run};
use engine::targets::TargetUrl;
use test_support::TempDir;

fn options(faults: &[Fault], dir: &std::path::Path, keep_going: bool) -> CampaignOptions {
    options_on("sim:mdrive", faults, dir, keep_going)
}

fn options_on(
    target: &str,
    faults: &[Fault],
    dir: &std::path::Path,
    keep_going: bool,
) -> CampaignOptions {
    let mut base = Options::new(TargetUrl::parse(target).unwrap());
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
        max_findings: 20,
        pipeline: 1,
    }
}

/// A campaign with no log, no interrupt and no progress; it must complete.
fn quiet(o: &CampaignOptions) -> CampaignOutcome {
    campaign(
        o,
        &mut std::io::sink(),
        &AtomicBool::new(false),
        |_, _, _| {},
    )
    .expect("campaign")
}

/// The campaign's finding that the drive stopped answering; panics with `missing` when there is none.
fn stopped_answering<'a>(out: &'a CampaignOutcome, missing: &str) -> &'a CampaignFinding {
    out.findings
        .iter()
        .find(|f| f.kind == FindingKind::StoppedAnswering)
        .expect(missing)
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
    let out = quiet(&o);
    let stop = stopped_answering(&out, "the liveness probe notices the dead drive");
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
    let out = quiet(&o);
    assert_eq!(out.cases, 1500);
    assert!(
        out.findings.is_empty(),
        "{:?}",
        out.findings.iter().map(|f| &f.findings).collect::<Vec<_>>()
    );
}

/// With --keep-going a bug met again with other addresses or values is one finding (counted as a repeat, no
/// second reproducer), and --max-findings ends the campaign, saying so.
#[test]
fn repeated_findings_are_counted_once_and_max_findings_stops_the_campaign() {
    let dir = TempDir::new("fuzz-dedupe");
    let mut o = options(&[Fault::RangeUnchecked], dir.path(), true);
    o.max_cases = Some(3000);
    let out = quiet(&o);
    assert!(!out.findings.is_empty(), "range-unchecked found nothing");
    assert!(out.repeats > 0, "no repeat in {} cases", out.cases);
    let files: Vec<_> = out.findings.iter().filter_map(|f| f.file.clone()).collect();
    assert_eq!(files.len(), out.findings.len(), "a reproducer per finding");
    o.max_findings = 1;
    let capped = quiet(&o);
    assert_eq!(capped.findings.len(), 1);
    assert!(
        capped.stopped.contains("--max-findings"),
        "{}",
        capped.stopped
    );
    assert!(
        capped.cases < out.cases,
        "{} vs {}",
        capped.cases,
        out.cases
    );
}

/// A drive that stops answering is probed right after the first case whose due answer did not come, not at
/// the next periodic probe: the reproducer is the few cases since the last answer, and the campaign says why
/// it ended.
#[test]
fn a_drive_that_stops_answering_is_probed_at_once() {
    let dir = TempDir::new("fuzz-at-once");
    let mut o = options(&[Fault::StopAfterMalformed], dir.path(), false);
    o.probe_every = 1_000_000;
    let out = quiet(&o);
    let f = stopped_answering(&out, "stopped answering found without a periodic probe");
    assert_eq!(out.stopped, "the drive stopped answering");
    // The malformed case, the case that went unanswered after it, and the probe.
    assert!(
        f.reproducer.steps.len() <= 8,
        "{} steps",
        f.reproducer.steps.len()
    );
}

/// A drive whose answers carry a wrong MBAP length, or come late, is alive: its wrong answers are findings,
/// never "stopped answering" (the incomplete frame, the late answer, is heard), and a drive that does stop
/// is still told apart.
#[test]
fn a_drive_that_answers_malformed_is_not_taken_for_one_that_stopped() {
    let dir = TempDir::new("fuzz-malformed-alive");
    // The first finding's kind: part of a frame where an answer was due is the case's own FAIL (no probe
    // first); a late answer heard by the probe makes it a wrong probe answer; silence a stop.
    for (fault, first) in [
        (Fault::MbapLength, FindingKind::Fail),
        (Fault::LateResponse, FindingKind::ProbeFails),
        (Fault::StopAfterMalformed, FindingKind::StoppedAnswering),
    ] {
        let out = quiet(&options(&[fault], dir.path(), false));
        let kinds: Vec<FindingKind> = out.findings.iter().map(|f| f.kind).collect();
        assert_eq!(
            kinds.first(),
            Some(&first),
            "{fault:?}: {kinds:?}, {}",
            out.stopped
        );
        assert_eq!(
            kinds.contains(&FindingKind::StoppedAnswering),
            fault == Fault::StopAfterMalformed,
            "{fault:?}: {kinds:?}"
        );
    }
}

/// The faults of the public function codes the generator draws on the generic profile (issue 17 item 5:
/// FC 07, 0B, 0C, 11, 14, 15, 16, 18, 2B/0E, and 08/04 followed by 08/01), each with the framing where the
/// function shows it (the event log after a restart and listen only mode act on a serial line), and an SD2x
/// that refuses a function code its manual lists.
const PUBLIC_FC_FAULTS: &[(Fault, &str)] = &[
    (Fault::ExceptionStatusReversed, "sim:generic"),
    (Fault::EventCounterCountsExceptions, "sim:generic"),
    (Fault::EventLogOldestFirst, "sim:generic?transport=rtu"),
    (Fault::RunIndicatorOne, "sim:generic"),
    (Fault::FileRecordLengthWrong, "sim:generic"),
    (Fault::FileWriteFirstOnly, "sim:generic"),
    (Fault::MaskWriteWrong, "sim:generic"),
    (Fault::FifoOffByOne, "sim:generic"),
    (Fault::ListenOnlyIgnored, "sim:generic?transport=rtu"),
    // FC 2B/0E: a regular object where the declared conformity level says basic (6.21).
    (Fault::ConformityLevelWrong, "sim:generic"),
    // FC 04 refused although the SD2x manual lists it (line 277).
    (Fault::ListedFunctionRefused, "sim:sd2x"),
];

/// Each fault of [`PUBLIC_FC_FAULTS`] is found by a short seeded campaign, and the same campaigns find
/// nothing on the healthy drives (no case of these function codes FAILs a conforming answer).
#[test]
fn the_public_function_code_faults_are_found_and_healthy_drives_give_none() {
    let dir = TempDir::new("fuzz-public-fc");
    let mut problems = Vec::new();
    for (fault, target) in PUBLIC_FC_FAULTS {
        let mut o = options_on(target, &[*fault], dir.path(), false);
        o.max_cases = Some(1500);
        let out = quiet(&o);
        if !out
            .findings
            .iter()
            .any(|f| f.kind == FindingKind::Fail && f.replayed == Some(true))
        {
            problems.push(format!(
                "{fault:?} on {target}: not found in {} cases ({:?})",
                out.cases,
                out.findings.iter().map(|f| &f.findings).collect::<Vec<_>>()
            ));
        }
    }
    for target in ["sim:generic", "sim:generic?transport=rtu", "sim:sd2x"] {
        let mut o = options_on(target, &[], dir.path(), true);
        o.max_cases = Some(1500);
        let out = quiet(&o);
        if !out.findings.is_empty() {
            problems.push(format!(
                "healthy {target}: {:?}",
                out.findings
                    .iter()
                    .map(|f| (&f.case_id, &f.findings))
                    .collect::<Vec<_>>()
            ));
        }
    }
    assert!(problems.is_empty(), "{problems:#?}");
}
