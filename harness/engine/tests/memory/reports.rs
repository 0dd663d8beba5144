//! The report layer keeps no per-case data: 100,000 cases go through `Reports` while the live heap stays
//! flat and the summary's failing list stays capped; the files still hold every case (one line each in
//! `cases.jsonl`, a case file for each FAIL). (No timing is measured.)

use std::sync::atomic::Ordering;
use std::time::Duration;

use engine::Verdict;
use engine::reports::{FAILING_CAP, Reports, Transport};
use test_support::reports::{numbered_pass, run_info};

use crate::{LIVE, alone};

const CASES: usize = 100_000;
/// Every this many cases is a FAIL, so the failing list would grow past its cap if it were not capped.
const FAIL_EVERY: usize = 40;

#[test]
fn memory_does_not_grow_with_the_number_of_cases() {
    let _alone = alone();
    let dir = test_support::TempDir::new("tempdir");
    let info = run_info(Transport::Tcp, 502);
    let mut reports = Reports::create(dir.path(), &info).expect("create reports");
    // The live heap varies with the writer thread's pipeline (up to four batches of cases, one being filled,
    // one queued, one being written, one on its way back: tens of kilobytes, held or not at any moment), so
    // what is compared is the highest live heap over cases 2,000-20,000 (after warm-up, many pipeline
    // cycles) with the highest over the 80,000 cases after them: the pipeline's swing is in both.
    let (mut early, mut late) = (0isize, 0isize);
    for n in 0..CASES {
        let (case, mut result) = numbered_pass(Transport::Tcp, n);
        if n % FAIL_EVERY == 0 {
            result.verdict = Verdict::Fail;
        }
        reports.case(&case, &result).expect("write case");
        drop((case, result));
        let live = LIVE.load(Ordering::Relaxed);
        match n {
            0..2_000 => {}
            2_000..20_000 => early = early.max(live),
            _ => late = late.max(live),
        }
    }
    let growth = late - early;
    eprintln!(
        "highest live heap over cases 2,000-20,000: {early} B; over the 80,000 after: {late} B"
    );
    // A per-case leak of even 1 byte would show up as 80,000 bytes here.
    assert!(
        growth < 16 * 1024,
        "the live heap grew by {growth} bytes over {} cases",
        CASES - 20_000
    );

    let summary = reports.summary(false, Duration::from_secs(1));
    assert_eq!(summary.cases, CASES);
    assert_eq!(summary.count(Verdict::Fail), CASES / FAIL_EVERY);
    assert_eq!(summary.count(Verdict::Pass), CASES - CASES / FAIL_EVERY);
    assert_eq!(summary.failing.len(), FAILING_CAP);
    assert_eq!(summary.failing_omitted(), CASES / FAIL_EVERY - FAILING_CAP);
    assert_eq!(reports.tally().failing().len(), FAILING_CAP);
    reports.finish(&summary).expect("finish");

    // The files hold every case even though memory held none of them.
    let index: serde_json::Value = serde_json::from_reader(std::io::BufReader::new(
        std::fs::File::open(dir.path().join("index.json")).expect("index.json"),
    ))
    .expect("index.json parses");
    assert_eq!(index["cases"].as_array().map(Vec::len), Some(CASES));
    assert_eq!(index["summary"]["counts"]["FAIL"], CASES / FAIL_EVERY);
    let junit = std::fs::read_to_string(dir.path().join("junit.xml")).expect("junit.xml");
    assert_eq!(junit.matches("<testcase ").count(), CASES);
    // cases.jsonl has a line per case, in order; cases/ a file per FAIL only.
    let lines = std::io::BufReader::new(
        std::fs::File::open(dir.path().join("cases.jsonl")).expect("cases.jsonl"),
    );
    let mut n = 0;
    for line in std::io::BufRead::lines(lines) {
        let record: serde_json::Value =
            serde_json::from_str(&line.expect("read line")).expect("line parses");
        let want = if n % FAIL_EVERY == 0 { "FAIL" } else { "PASS" };
        assert_eq!(record["result"]["verdict"], want, "line {n}: {record}");
        assert_eq!(
            record["result"]["id"],
            numbered_pass(Transport::Tcp, n).1.id
        );
        n += 1;
    }
    assert_eq!(n, CASES);
    let case_files = std::fs::read_dir(dir.path().join("cases"))
        .expect("cases/")
        .count();
    assert_eq!(case_files, CASES / FAIL_EVERY);
}
