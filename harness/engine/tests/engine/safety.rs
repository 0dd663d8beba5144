//! The one safety classifier: what it rates, that every case source tags its cases at least as the
//! classifier rates their own bytes (on every built-in profile and transport), and that the runner refuses to
//! send a request rated above its case's tags.

use std::collections::BTreeSet;

use codec::Framing;
use drives::corpus::Corpus;
use drives::profile::Profile;
use engine::cases::catalog;
use engine::cases::generated::Generator;
use engine::expect::Expectations;
use engine::runner::{RunConfig, Runner, Safety, Timing};
use engine::safety::classify;
use engine::targets::sim::SimTarget;
use engine::{Case, Compare, Level, Outgoing, Step, Tag, Verdict};
use test_support::{assert_none, profile, station};

const PROFILES: [&str; 4] = ["mdrive", "lmd", "sd2x", "generic"];

fn tags(p: &Profile, pdu: &[u8]) -> BTreeSet<Tag> {
    classify(p, pdu)
}

fn set(t: &[Tag]) -> BTreeSet<Tag> {
    t.iter().copied().collect()
}

/// The classifier's safety tags a case lacks: empty when the case is tagged at least as its bytes rate.
fn weaker(c: &Case, p: &Profile, unit: u8) -> Vec<Tag> {
    engine::safety::exceeds(&c.rated(p, unit), &c.tags)
}

#[test]
fn the_classifier_rates_writes_by_their_reach_and_malformed_ones_by_the_worst() {
    let md = profile("mdrive");
    let sd = profile("sd2x");
    use Tag::*;
    // Reads are nothing.
    assert_eq!(tags(&md, &[0x03, 0x00, 0x43, 0x00, 0x02]), set(&[]));
    assert_eq!(tags(&md, &[0x41, 0x20, 0x20, 0x41, 0x4D]), set(&[]));
    // FC 06 to the MDrive's acceleration (0x0000): write; to homing mode HM (0x002B): motion.
    assert_eq!(
        tags(&md, &[0x10, 0x00, 0x00, 0x00, 0x01, 0x02, 0, 1]),
        set(&[Write])
    );
    assert_eq!(
        tags(&md, &[0x06, 0x00, 0x2B, 0x00, 0x01]),
        set(&[Write, Motion])
    );
    // Over-long FC 16: quantity 1 at 0x002A, but data for two registers reaches HM at 0x002B.
    assert_eq!(
        tags(&md, &[0x10, 0x00, 0x2A, 0x00, 0x01, 0x04, 0, 1, 0, 1]),
        set(&[Write, Motion])
    );
    // Byte count that disagrees with the quantity reaches as far as the larger.
    assert_eq!(
        tags(&md, &[0x10, 0x00, 0x2A, 0x00, 0x01, 0x04, 0, 1]),
        set(&[Write, Motion])
    );
    // Truncated before the address: it may reach any register, the worst is motion and destructive (Save).
    assert_eq!(tags(&md, &[0x10]), set(&[Write, Motion, Destructive]));
    // FC 23 with a write quantity of 0 still writes (SD2x Control Word 0x0BB8: motion).
    assert_eq!(
        tags(
            &sd,
            &[0x17, 0x07, 0xD0, 0x00, 0x01, 0x0B, 0xB8, 0x00, 0x00, 0x00]
        ),
        set(&[Write, Motion])
    );
    // FC 08: return query data is a read; clear counters and listen only cannot be put back.
    assert_eq!(tags(&sd, &[0x08, 0x00, 0x00, 0x12, 0x34]), set(&[]));
    assert_eq!(
        tags(&sd, &[0x08, 0x00, 0x0A, 0x00, 0x00]),
        set(&[Write, Destructive])
    );
    assert_eq!(
        tags(&sd, &[0x08, 0x00, 0x04, 0x00, 0x00]),
        set(&[Write, Destructive])
    );
    // Vendor write of an unknown mnemonic, or a truncated one: anything.
    assert_eq!(
        tags(&md, &[0x42, b'Z', b'Z', 0x20, 0x20, 0]),
        set(&[Write, Motion, Destructive])
    );
    assert_eq!(tags(&md, &[0x42]), set(&[Write, Motion, Destructive]));
    // FC 43/13 write of the SD2x control word object (0x0044) is motion; a read of it nothing.
    let mut w = vec![
        0x2B, 0x0D, 0x80, 0, 1, 0x00, 0x44, 0, 0, 0, 0, 2, 0x06, 0x00,
    ];
    assert_eq!(tags(&sd, &w), set(&[Write, Motion]));
    w[2] = 0;
    assert_eq!(tags(&sd, &w[..12]), set(&[]));
    // To another unit, a write may reach another drive.
    assert_eq!(
        engine::safety::classify_to_unit(&md, &[0x10, 0, 0, 0, 1, 2, 0, 1], 0, 1),
        set(&[Write, Destructive])
    );
}

/// Every case of every source (catalog, regressions, generated), on every built-in profile and framing, is
/// tagged at least as the classifier rates its own bytes; and the check catches a case whose tags are weaker.
#[test]
fn no_case_is_tagged_weaker_than_the_classifier_rates_its_bytes() {
    let corpus = Corpus::Embedded;
    let mut checked = 0usize;
    let mut bad = Vec::new();
    for name in PROFILES {
        let p = profile(name);
        let unit = p.device.default_unit;
        let golden = corpus.golden(name).expect("golden");
        let mut cases = Vec::new();
        for framing in [Framing::Tcp, Framing::Rtu] {
            cases.extend(catalog::build(&p, golden.as_ref(), framing, unit));
        }
        cases.extend(catalog::regressions(&corpus, &p, unit).expect("regressions"));
        cases.extend(Generator::new(&p, unit, 0x5AFE).cases(300));
        for c in &cases {
            checked += 1;
            let w = weaker(c, &p, unit);
            if !w.is_empty() {
                bad.push(format!("{name}: {} lacks {w:?} (tags {:?})", c.id, c.tags));
            }
        }
        // The check can fail: strip the safety tags of a writing case and it is caught.
        let mut stripped = cases
            .iter()
            .find(|c| c.has(Tag::Write))
            .expect("a writing case")
            .clone();
        stripped
            .tags
            .retain(|t| !matches!(t, Tag::Write | Tag::Motion | Tag::Destructive));
        assert!(
            !weaker(&stripped, &p, unit).is_empty(),
            "{name}: {}",
            stripped.id
        );
    }
    assert!(checked > 1000, "only {checked} cases");
    assert_none(&bad, "cases tagged weaker than their bytes");
}

/// A case tagged read-only whose bytes write a motion register (the MDrive's homing mode) is not sent: the
/// runner reports a harness bug (FAIL) and the drive never sees the write, on `sim:` as on a real target.
#[test]
fn the_runner_refuses_a_request_rated_above_its_case() {
    let p = profile("mdrive");
    let hm = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.mnemonic.as_deref() == Some("HM"))
        .expect("HM");
    assert!(hm.motion);
    let write_hm = vec![0x10, 0x00, hm.address as u8, 0x00, 0x01, 0x02, 0x00, 0x03];
    let step = |pdu: Vec<u8>| Step::Exchange {
        send: Outgoing::Pdu(pdu),
        compare: Compare::Structure,
        capture: None,
        note: String::new(),
    };
    let case = |id: &str, tags: Vec<Tag>, steps: Vec<Step>| Case {
        id: id.into(),
        title: id.into(),
        reference: "test".into(),
        requirement: "test".into(),
        level: Level::Must,
        tags,
        steps,
        requirements: vec![],
        freedoms: vec![],
    };
    for is_sim in [true, false] {
        let cfg = RunConfig {
            unit: 1,
            timing: Timing::default(),
            safety: Safety::default(),
            is_sim,
        };
        let target = SimTarget::new(station("mdrive", &[]));
        let shadow = SimTarget::new(station("mdrive", &[]));
        // An expectations file that accepts anything of any case does not hide a harness bug.
        let lenient = Expectations {
            target: None,
            deviations: vec![engine::expect::ExpectedDeviation {
                case: "*".into(),
                verdict: "INFORMATIONAL".into(),
                reason: "accept everything".into(),
            }],
        };
        let mut runner = Runner::new(Box::new(target), shadow, p.clone(), cfg, lenient);
        let mistagged = case("mistagged", vec![], vec![step(write_hm.clone())]);
        let r = runner.run_case(&mistagged).expect("run");
        assert_eq!(r.verdict, Verdict::Fail, "is_sim {is_sim}: {r:#?}");
        assert!(r.wire.is_empty(), "sent: {:?}", r.wire);
        let text = r
            .steps
            .iter()
            .flat_map(|s| s.findings.clone())
            .collect::<Vec<_>>()
            .join("\n");
        assert!(
            text.contains("harness bug") && text.contains("motion"),
            "{text}"
        );
        // Tagged as what it does, the same write goes out.
        let ok = case(
            "tagged",
            vec![Tag::Write, Tag::Motion],
            vec![step(write_hm.clone())],
        );
        let r = runner.run_case(&ok).expect("run");
        assert!(!r.wire.is_empty(), "a correctly tagged case sends");
    }
}

/// The profile-free `is_write` (used by `probe`) agrees with the classifier's `write` on every profile, for
/// every function code with short, truncated and long bodies.
#[test]
fn is_write_agrees_with_the_classifier() {
    let profiles: Vec<Profile> = PROFILES.iter().map(|n| profile(n)).collect();
    let mut n = 0;
    for fc in 0..=255u8 {
        for body in [
            vec![],
            vec![0x00],
            vec![0x00, 0x00],
            vec![0x00, 0x01, 0x00, 0x00],
            vec![0x00, 0x0A, 0x00, 0x00],
            vec![0x0D],
            vec![0x0D, 0x00, 0x00, 0x00, 0x44, 0x00],
            vec![0x0D, 0x80, 0x00, 0x00, 0x44, 0x00],
            vec![0x0E, 0x01, 0x00],
            vec![0x00, 0x14, 0xFF, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00],
        ] {
            let mut pdu = vec![fc];
            pdu.extend(body);
            for p in &profiles {
                n += 1;
                assert_eq!(
                    engine::safety::is_write(&pdu),
                    classify(p, &pdu).contains(&Tag::Write),
                    "{pdu:02X?} on {}",
                    p.device.id
                );
            }
        }
    }
    assert!(n > 10_000);
}
