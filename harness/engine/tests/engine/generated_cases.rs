//! Generated cases: reproducible from the seed, covering every function code, boundary and alteration of a
//! profile, tagged for the safety policy, passing on healthy drives; a faulted drive fails them and the
//! shrinker, with the drive in the loop, returns a reproducer within the stated bound; the committed
//! reproducer is replayed by the catalog.
//!
//! Every seed is fixed and printed; every run is against the in-process drives (virtual clock, no sleeps).

use std::collections::BTreeSet;
use std::io::Write;

use codec::FunctionCode;
use codec::{MAX_PDU_LEN, Request};
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{Fault, FaultSet};
use engine::cases::generated::{Generator, pdu_tags};
use engine::cases::regressions::RegressionFile;
use engine::cases::shrink::{self, ShrinkLimits};
use engine::session::{self, Options};
use engine::targets::TargetUrl;
use engine::{Case, Outgoing, Step, Tag, Verdict};
use test_support::{failures_of, profile, run_ok};

/// The size bound of a shrunk reproducer (RangeUnchecked / QuantityUnchecked on the MDrive): at most this
/// many exchange steps ...
const SHRUNK_MAX_EXCHANGES: usize = 2;
/// ... and no step sending more than this many PDU bytes.
const SHRUNK_MAX_PDU: usize = 16;
/// The committed reproducer (shrunk from `run --target sim:mdrive --fault range-unchecked --generated 200
/// --seed 7`).
const COMMITTED: &str = "regression/mdrive/gen-7-3-write-reg";

fn say(line: &str) {
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

fn generated(target: &str, n: u64, seed: u64, faults: &[Fault]) -> Options {
    let mut o = Options::new(TargetUrl::parse(target).expect("url"));
    o.generated = n;
    o.seed = Some(seed);
    o.faults = FaultSet::of(faults);
    o.keep_verdicts = true;
    o
}

/// The PDUs a case sends, as built (mutations applied where they act on the PDU).
fn pdus(c: &Case) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for s in &c.steps {
        if let Step::Exchange { send, .. } = s {
            match send {
                Outgoing::Pdu(p) | Outgoing::PduToUnit { pdu: p, .. } => out.push(p.clone()),
                Outgoing::Mutated { pdu, mutation } => {
                    out.push(mutation.apply_to_pdu(pdu).unwrap_or_else(|| pdu.clone()))
                }
                Outgoing::Batch(ps) => out.extend(ps.iter().cloned()),
                Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => {}
            }
        }
    }
    out
}

#[test]
fn the_same_seed_gives_the_same_cases_and_case_i_does_not_depend_on_n() {
    let p = profile("mdrive");
    let seed = 0x5EED;
    say(&format!("seed {seed}"));
    let a: Vec<Case> = Generator::new(&p, 1, seed).cases(60).collect();
    let b: Vec<Case> = Generator::new(&p, 1, seed).cases(60).collect();
    assert_eq!(a, b);
    let longer: Vec<Case> = Generator::new(&p, 1, seed).cases(120).collect();
    assert_eq!(a[..], longer[..60]);
    assert!(
        a[0].id.starts_with(&format!("gen/{seed}/0/")),
        "{}",
        a[0].id
    );
    let other: Vec<Case> = Generator::new(&p, 1, seed + 1).cases(60).collect();
    let same = a
        .iter()
        .zip(&other)
        .filter(|(x, y)| x.steps == y.steps)
        .count();
    assert!(same < 10, "{same} of 60 cases equal under another seed");
}

#[test]
fn every_function_code_boundary_and_alteration_is_generated() {
    let seed = 11;
    say(&format!("seed {seed}"));
    for name in ["mdrive", "lmd", "sd2x", "generic"] {
        let p = profile(name);
        let g = Generator::new(&p, p.device.default_unit, seed);
        let mut fcs = BTreeSet::new();
        let mut kinds = BTreeSet::new();
        let mut quantities = BTreeSet::new();
        for c in g.cases(3000) {
            for k in c.id.split('/').nth(3).unwrap_or("").split('-') {
                kinds.insert(k.to_string());
            }
            for pdu in pdus(&c) {
                // Over-long frames are the catalog's (tcp/pdu/over-253-bytes), not the generators'.
                assert!(pdu.len() <= MAX_PDU_LEN, "{}: {}-byte PDU", c.id, pdu.len());
                fcs.extend(pdu.first().copied());
                if let Ok(
                    Request::ReadHoldingRegisters { quantity, .. }
                    | Request::ReadInputRegisters { quantity, .. },
                ) = Request::decode(&pdu)
                {
                    quantities.insert(quantity);
                }
            }
        }
        for f in &p.functions {
            assert!(
                fcs.contains(&f.code.0),
                "{name}: FC 0x{:02X} never generated",
                f.code.0
            );
        }
        assert!(
            fcs.iter().any(|fc| p.function(*fc).is_none()),
            "{name}: no unsupported FC"
        );
        let max = p
            .function(FunctionCode::READ_HOLDING_REGISTERS)
            .or(p.function(FunctionCode::READ_INPUT_REGISTERS))
            .and_then(|f| f.max_quantity)
            .unwrap_or(125);
        for q in [0, 1, max, max + 1] {
            assert!(
                quantities.contains(&q),
                "{name}: read quantity {q} never generated"
            );
        }
        let mut want = vec![
            "bitflip",
            "truncated",
            "extended",
            "bytecount",
            "fcswap",
            "unit",
            "badcrc",
            "mbaplen",
            "protoid",
            "split",
            "batch",
            "seq2",
            "seq3",
            "span",
        ];
        if p.registers.iter().any(|r| r.get_ref().width == 2) {
            want.push("half");
        }
        for k in want {
            assert!(
                kinds.contains(k),
                "{name}: no `{k}` case in 3000: {kinds:?}"
            );
        }
    }
}

#[test]
fn generated_writes_carry_the_safety_tags_of_what_they_write() {
    let md = profile("mdrive");
    let sd = profile("sd2x");
    let tags = |p: &Profile, pdu: &[u8]| pdu_tags(p, pdu).into_iter().collect::<Vec<_>>();
    // MDrive MR (0x0046, a relative move) is a motion register; A (0x0000) a plain setting.
    let mr = Request::WriteMultipleRegisters {
        address: 0x46,
        values: vec![0, 1],
    }
    .to_bytes()
    .unwrap();
    assert_eq!(tags(&md, &mr), vec![Tag::Write, Tag::Motion]);
    let a = Request::WriteMultipleRegisters {
        address: 0,
        values: vec![0, 1000],
    }
    .to_bytes()
    .unwrap();
    assert_eq!(tags(&md, &a), vec![Tag::Write]);
    // The SD2x watchdog faults the drive when it runs out: destructive.
    let wd = Request::WriteSingleRegister {
        address: 3003,
        value: 100,
    }
    .to_bytes()
    .unwrap();
    assert!(tags(&sd, &wd).contains(&Tag::Destructive));
    // A malformed write may do anything; a read nothing.
    assert_eq!(
        tags(&md, &[0x10, 0x00]),
        vec![Tag::Write, Tag::Motion, Tag::Destructive]
    );
    assert!(tags(&md, &[0x03, 0, 0, 0, 1]).is_empty());
    // Every generated case that sends a write is tagged `write`, and the policy skips it on a read-only run.
    let g = Generator::new(&md, 1, 3);
    for c in g.cases(500) {
        let writes = pdus(&c)
            .iter()
            .any(|p| pdu_tags(&md, p).contains(&Tag::Write));
        assert!(!writes || c.has(Tag::Write), "{} writes untagged", c.id);
    }
    let mut o = generated("sim:mdrive", 200, 3, &[]);
    o.safety.read_only = true;
    let plan = session::plan(&o, &md).expect("plan");
    assert!(plan.iter().any(|(c, s)| c.has(Tag::Write) && s.is_some()));
    assert!(plan.iter().all(|(c, s)| !c.has(Tag::Write) || s.is_some()));
}

#[test]
fn healthy_reference_drives_pass_every_generated_case() {
    let seed = 2024;
    say(&format!("seed {seed}"));
    for target in [
        "sim:mdrive",
        "sim:lmd",
        "sim:sd2x",
        "sim:generic",
        "sim:mdrive?transport=rtu",
    ] {
        let out = run_ok(&generated(target, 400, seed, &[]));
        let fails = failures_of(&out);
        assert!(fails.is_empty(), "{target} seed {seed}: {fails:#?}");
        assert_eq!(out.info.seed, Some(seed));
        assert!(
            out.summary.count(Verdict::Pass) > 300,
            "{target}: {:?}",
            out.summary
        );
    }
}

#[test]
fn a_faulted_drive_fails_generated_cases_and_the_shrinker_returns_a_small_reproducer() {
    let seed = 7;
    say(&format!("seed {seed}"));
    for fault in [Fault::RangeUnchecked, Fault::QuantityUnchecked] {
        let dir = test_support::TempDir::new("tempdir");
        let mut o = generated("sim:mdrive", 200, seed, &[fault]);
        o.regressions_dir = Some(dir.path().to_path_buf());
        o.max_shrinks = 3;
        o.shrink = Some(ShrinkLimits::default());
        let out = run_ok(&o);
        assert!(out.summary.count(Verdict::Fail) > 0, "{fault}: no FAIL");
        assert!(!out.shrunk.is_empty(), "{fault}: nothing shrunk");
        for r in &out.shrunk {
            let s = r
                .shrunk
                .as_ref()
                .unwrap_or_else(|| panic!("{fault} {}: {:?}", r.id, r.note));
            let (exchanges, largest) = shrink::case_size(&s.case);
            say(&format!(
                "{fault}: {} -> {} in {} candidate(s) ({} kept, {:?}): {exchanges} exchange(s), largest PDU {largest} bytes",
                r.id, s.case.id, s.steps, s.accepted, s.stop
            ));
            assert!(
                exchanges <= SHRUNK_MAX_EXCHANGES && largest <= SHRUNK_MAX_PDU,
                "{fault}: {} shrank to {exchanges} exchanges / {largest}-byte PDU: {:#?}",
                r.id,
                s.case
            );
            assert!(s.steps <= ShrinkLimits::default().max_steps);
            assert!(
                shrink::case_size(&s.original).0 >= exchanges,
                "shrinking grew the case"
            );
            // The reproducer file reads back as the same case.
            let file = r.file.as_ref().expect("reproducer written");
            let text = std::fs::read_to_string(file).expect("read reproducer");
            let back = RegressionFile::parse(&file.display().to_string(), &text)
                .expect("parse")
                .to_case(s.case.id.clone())
                .expect("case");
            assert_eq!(back, s.case);
        }
    }
}

#[test]
fn the_shrinker_respects_its_step_bound() {
    let dir = test_support::TempDir::new("tempdir");
    let mut o = generated("sim:mdrive", 200, 7, &[Fault::RangeUnchecked]);
    o.regressions_dir = Some(dir.path().to_path_buf());
    o.shrink = Some(ShrinkLimits {
        max_steps: 3,
        max_time: std::time::Duration::from_secs(30),
    });
    let out = run_ok(&o);
    assert!(!out.shrunk.is_empty());
    for r in &out.shrunk {
        let s = r.shrunk.as_ref().expect("shrunk");
        assert!(s.steps <= 3, "{}: {} steps", r.id, s.steps);
    }
}

#[test]
fn the_committed_reproducer_is_in_the_catalog_passes_healthy_and_fails_faulted() {
    let md = profile("mdrive");
    let ids: Vec<String> =
        session::plan(&Options::new(TargetUrl::parse("sim:mdrive").unwrap()), &md)
            .expect("plan")
            .into_iter()
            .map(|(c, _)| c.id)
            .collect();
    assert!(
        ids.iter().any(|i| i == COMMITTED),
        "{COMMITTED} not in the catalog"
    );
    let verdict = |faults: &[Fault]| {
        let mut o = Options::new(TargetUrl::parse("sim:mdrive").unwrap());
        o.include = vec![COMMITTED.to_string()];
        o.faults = FaultSet::of(faults);
        o.keep_verdicts = true;
        let out = run_ok(&o);
        assert_eq!(out.verdicts.len(), 1, "{:?}", out.verdicts);
        out.verdicts[0].1
    };
    assert_eq!(verdict(&[]), Verdict::Pass);
    assert_eq!(verdict(&[Fault::RangeUnchecked]), Verdict::Fail);
    // Within the stated bound too.
    let (file, text) = Corpus::Embedded
        .files("regressions/mdrive")
        .expect("files")
        .into_iter()
        .find(|(n, _)| n.contains("gen-7-3-write-reg"))
        .expect("committed file");
    let case = RegressionFile::parse(&file, &text)
        .expect("parse")
        .to_case(COMMITTED.into())
        .expect("case");
    let (exchanges, largest) = shrink::case_size(&case);
    assert!(exchanges <= SHRUNK_MAX_EXCHANGES && largest <= SHRUNK_MAX_PDU);
}

#[test]
fn generated_only_runs_skip_the_catalog_unless_asked() {
    let md = profile("mdrive");
    let o = generated("sim:mdrive", 5, 1, &[]);
    let plan = session::plan(&o, &md).expect("plan");
    assert_eq!(plan.len(), 5);
    assert!(plan.iter().all(|(c, _)| c.id.starts_with("gen/1/")));
    let mut with = o.clone();
    with.with_catalog = true;
    let plan = session::plan(&with, &md).expect("plan");
    assert!(plan.len() > 100);
    assert!(plan.iter().any(|(c, _)| c.id.starts_with("golden/")));
    assert_eq!(
        plan.iter()
            .filter(|(c, _)| c.id.starts_with("gen/"))
            .count(),
        5
    );
}
