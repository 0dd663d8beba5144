//! No catalog case depends on the order of the others: `run --shuffle SEED` gives every case the verdict it
//! has in catalog order, on every reference drive and transport, and on drives with the faults whose effect
//! the cases can undo (a drive that wrongly accepts a write is put back by the case that wrote). Each case
//! establishes its own precondition and restores what it changed; the cases that leave the drive changed for
//! good run last in any order.

use std::collections::BTreeMap;
use std::time::Instant;

use drives::{Fault, FaultSet};
use engine::session::Options;
use engine::targets::TargetUrl;
use engine::{Tag, Verdict};
use test_support::{failures_of, run_ok};

const PROFILES: [&str; 4] = ["sd2x", "mdrive", "lmd", "generic"];
/// The sim target's default transport (the profile's own), RTU and Modbus/TCP framing.
const TRANSPORTS: [&str; 3] = ["", "?transport=rtu", "?transport=tcp"];
const SEEDS: [u64; 3] = [1, 0x5EED, 0xDEAD_BEEF_CAFE];

/// Faults whose effect depends on the order by nature, not on what a case left behind: the drive stops
/// answering for good after the first malformed frame; every answer comes after the timeout and is read by a
/// later exchange; a drive changing its choice is found in the cases after the first that showed the other
/// value, whichever runs first. A drive reading the quantity's low byte shows such a change on the generic
/// profile: FC 01 quantity 2001 (0x07D1) read as 209 runs past the map (02, `exception-check-order`) while
/// FC 03 quantity 126 stays refused as a quantity (03). A homing that never ends keeps the axis moving for good:
/// every case after the first HM write that waits for rest FAILs.
const ORDER_BOUND: [Fault; 8] = [
    Fault::StopAfterMalformed,
    Fault::LateResponse,
    Fault::RangeCodeInconsistent,
    Fault::QuantityLowByte,
    Fault::HomingNeverEnds,
    // Each of its answers is admissible; the first case to show one is the drive's choice and the others
    // are held to it, so which cases are NON-STRICT depends on which comes first.
    Fault::UnusedDiagDataInconsistent,
    // The drive answers 02 to a read whose quantity is past the specification's (the address check comes
    // first), 03 to a write whose byte count disagrees with its quantity (a decode error): both admissible
    // (`exception-check-order`), the two together are a change of mind, found wherever the second comes.
    Fault::QuantityUnchecked,
    // SDO error codes in one byte order for writes and the other for reads: whichever comes first is the
    // drive's choice.
    Fault::SdoErrorOrderInconsistent,
];

/// Case id -> verdict, and the ids in run order.
fn run(
    target: &str,
    faults: &[Fault],
    shuffle: Option<u64>,
) -> (BTreeMap<String, Verdict>, Vec<String>) {
    let mut o = Options::new(TargetUrl::parse(target).expect("url"));
    o.keep_verdicts = true;
    o.faults = FaultSet::of(faults);
    o.shuffle = shuffle;
    let out = run_ok(&o);
    if faults.is_empty() {
        let fails = failures_of(&out);
        assert!(
            fails.is_empty(),
            "{target} (shuffle {shuffle:?}) FAILs: {fails:#?}"
        );
    }
    let order = out.verdicts.iter().map(|(id, _)| id.clone()).collect();
    (out.verdicts.into_iter().collect(), order)
}

/// The cases whose verdict differs between two runs (or that only one has).
fn differences(a: &BTreeMap<String, Verdict>, b: &BTreeMap<String, Verdict>) -> Vec<String> {
    a.iter()
        .filter(|(id, v)| b.get(*id) != Some(*v))
        .map(|(id, v)| format!("{id}: {v} in catalog order, {:?} shuffled", b.get(id)))
        .chain(
            b.keys()
                .filter(|id| !a.contains_key(*id))
                .map(|id| format!("{id}: only shuffled")),
        )
        .collect()
}

#[test]
fn shuffled_runs_give_every_case_its_catalog_order_verdict() {
    let started = Instant::now();
    let mut problems = Vec::new();
    for p in PROFILES {
        for t in TRANSPORTS {
            let target = format!("sim:{p}{t}");
            let (base, base_order) = run(&target, &[], None);
            assert!(base.len() > 100, "{target}: only {} cases", base.len());
            for seed in SEEDS {
                let (shuffled, order) = run(&target, &[], Some(seed));
                assert_ne!(
                    order, base_order,
                    "{target}: --shuffle {seed} kept the catalog order"
                );
                problems.extend(
                    differences(&base, &shuffled)
                        .into_iter()
                        .map(|d| format!("{target} --shuffle {seed}: {d}")),
                );
            }
        }
    }
    assert!(problems.is_empty(), "{problems:#?}");
    eprintln!("healthy: {:.1} s", started.elapsed().as_secs_f64());
}

/// On each drive's own transport (the other transports are the healthy test's): a faulty drive diverges from
/// the reference, so what one case leaves behind would show in another's verdict.
#[test]
fn shuffled_runs_on_faulty_drives_give_the_same_verdicts() {
    let started = Instant::now();
    let mut problems = Vec::new();
    for p in PROFILES {
        {
            let target = format!("sim:{p}");
            for &(fault, name, _) in Fault::ALL {
                if ORDER_BOUND.contains(&fault) {
                    continue;
                }
                let (base, _) = run(&target, &[fault], None);
                let (shuffled, _) = run(&target, &[fault], Some(SEEDS[1]));
                problems.extend(
                    differences(&base, &shuffled)
                        .into_iter()
                        .map(|d| format!("{target} --fault {name} --shuffle {}: {d}", SEEDS[1])),
                );
            }
        }
    }
    assert!(problems.is_empty(), "{problems:#?}");
    eprintln!("faulted: {:.1} s", started.elapsed().as_secs_f64());
}

#[test]
fn irreversible_cases_run_last_in_any_order() {
    for seed in [None, Some(SEEDS[0]), Some(SEEDS[2])] {
        let mut o = Options::new(TargetUrl::parse("sim:lmd").expect("url"));
        o.shuffle = seed;
        let profile = test_support::profile("lmd");
        let plan = engine::session::plan(&o, &profile).expect("plan");
        let first_irreversible = plan
            .iter()
            .position(|(c, _)| c.has(Tag::Irreversible))
            .expect("the LMD catalog clears the program (CP) and enters upgrade mode (UG)");
        assert!(
            plan[first_irreversible..]
                .iter()
                .all(|(c, _)| c.has(Tag::Irreversible)),
            "shuffle {seed:?}: a case runs after an irreversible one"
        );
        let last: Vec<&str> = plan[first_irreversible..]
            .iter()
            .map(|(c, _)| c.id.as_str())
            .collect();
        assert_eq!(
            last.first(),
            Some(&"golden/lmd/4.4.3/clear-program/request"),
            "shuffle {seed:?}: the irreversible cases keep their catalog order: {last:?}"
        );
    }
}
