//! Snapshot files: written in case-id order whatever the order cases complete in, the same bytes whether
//! or not sorted chunks were spilled to disk, and memory that does not grow with the number of cases,
//! neither while writing (external sort) nor while comparing (both files read block by block).
//! (No timing is measured.)

use std::sync::atomic::Ordering;
use std::time::Duration;

use engine::reports::snapshot::{SnapshotHeader, SnapshotWriter, compare, natural_cmp};
use engine::{CaseResult, Received, StepResult, Verdict};

use crate::{LIVE, PEAK, alone};

/// A completed case: one read of `n`'s register and its answer (about 200 bytes of snapshot text).
fn result(n: usize, changed: bool) -> CaseResult {
    let tid = (n as u16).to_be_bytes();
    let request = vec![tid[0], tid[1], 0, 0, 0, 6, 1, 3, 0, 0x8B, 0, 2];
    let mut answer = vec![tid[0], tid[1], 0, 0, 0, 7, 1, 3, 4, 0, 9, 0x27, 0xC0];
    if changed {
        answer[12] ^= 1;
    }
    CaseResult {
        id: format!("gen/99/{n}/read-reg-with-a-longer-kind-name"),
        verdict: Verdict::Pass,
        expected_deviation: None,
        steps: vec![
            StepResult {
                note: "read".into(),
                sent: Some(request.clone()),
                expected: None,
                observed: vec![Received::frame(answer.clone())],
                verdict: Verdict::Pass,
                findings: vec![],
            };
            2
        ],
        wire: vec![],
        duration: Duration::ZERO,
        reason: None,
    }
}

fn header() -> SnapshotHeader {
    SnapshotHeader {
        profile: "mdrive".into(),
        framing: "tcp".into(),
        unit: 1,
        seed: Some(99),
    }
}

/// Case `i` of `n` in a scrambled completion order (a permutation: 7919 is prime to every `n` used).
fn scrambled(i: usize, n: usize) -> usize {
    (i * 7919 + 13) % n
}

const CASES: usize = 100_000;
/// The writer's chunk: the most snapshot text it keeps in memory.
const CHUNK: usize = 256 * 1024;

#[test]
fn order_is_by_case_id_and_memory_does_not_grow_with_cases() {
    let _alone = alone();
    let dir = test_support::TempDir::new("tempdir");

    // Small: spilled or not, the same bytes, in natural id order.
    let (a, b) = (dir.path().join("a.txt"), dir.path().join("b.txt"));
    let mut whole = SnapshotWriter::new(&header(), dir.path());
    let mut spilled = SnapshotWriter::new(&header(), dir.path()).with_chunk_limit(4096);
    for i in 0..2_000 {
        let r = result(scrambled(i, 2_000), false);
        whole.add(&r).expect("add");
        spilled.add(&r).expect("add");
    }
    assert_eq!(whole.spilled_runs(), 0);
    assert!(spilled.spilled_runs() > 10, "{}", spilled.spilled_runs());
    whole.finish(&a).expect("finish");
    spilled.finish(&b).expect("finish");
    let text = std::fs::read_to_string(&a).expect("read");
    assert_eq!(text, std::fs::read_to_string(&b).expect("read"));
    let ids: Vec<&str> = text
        .lines()
        .filter_map(|l| l.strip_prefix("== "))
        .map(|l| l.split("  ").next().unwrap_or(""))
        .collect();
    assert_eq!(ids.len(), 2_000);
    assert!(ids.windows(2).all(|w| natural_cmp(w[0], w[1]).is_lt()));
    assert!(ids[0].starts_with("gen/99/0/") && ids[10].starts_with("gen/99/10/"));
    // No temporary file is left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);

    // Large: 100,000 cases (about 40 MB of text) written with a 256 KiB chunk.
    let (big, changed) = (dir.path().join("big.txt"), dir.path().join("changed.txt"));
    for (path, change) in [(&big, usize::MAX), (&changed, 31_337)] {
        let before = LIVE.load(Ordering::Relaxed);
        PEAK.store(before, Ordering::Relaxed);
        let mut w = SnapshotWriter::new(&header(), dir.path()).with_chunk_limit(CHUNK);
        for i in 0..CASES {
            let n = scrambled(i, CASES);
            w.add(&result(n, n == change)).expect("add");
        }
        w.finish(path).expect("finish");
        let growth = PEAK.load(Ordering::Relaxed) - before;
        let size = std::fs::metadata(path).unwrap().len();
        eprintln!("writing {size} bytes of snapshot: heap peak {growth} B above the start");
        assert!(size > 20_000_000, "{size}");
        assert!(
            growth < 4 * CHUNK as isize,
            "writing grew the heap by {growth} B (chunk {CHUNK} B)"
        );
    }

    // Comparing two such files keeps one block of each in memory.
    let before = LIVE.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let drift = compare(&big, &changed).expect("compare");
    let growth = PEAK.load(Ordering::Relaxed) - before;
    eprintln!("comparing: heap peak {growth} B above the start");
    assert!(growth < 256 * 1024, "comparing grew the heap by {growth} B");
    assert_eq!((drift.changed, drift.same), (1, CASES - 1));
    assert_eq!(
        drift.ids,
        vec!["gen/99/31337/read-reg-with-a-longer-kind-name".to_string()]
    );
}
