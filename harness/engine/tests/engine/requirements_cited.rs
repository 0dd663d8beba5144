//! The citation map against the catalog: every case of every built-in profile, on every transport the
//! catalog builds for, cites at least one requirement, and every entry of the map matches some case.

use std::collections::BTreeSet;

use codec::Framing;
use drives::corpus::Corpus;
use engine::cases::catalog;

#[test]
fn every_catalog_case_cites_a_requirement_and_every_cite_is_used() {
    let corpus = Corpus::Embedded;
    let reqs = corpus.requirements().unwrap_or_else(|e| panic!("{e}"));
    let mut uncited = Vec::new();
    let mut used = BTreeSet::new();
    let mut cases = 0;
    let mut cited_ids = BTreeSet::new();
    for name in corpus.profile_names() {
        let p = corpus.profile(&name).unwrap_or_else(|e| panic!("{e}"));
        let golden = corpus.golden(&name).unwrap_or_else(|e| panic!("{e}"));
        for framing in [Framing::Tcp, Framing::Rtu] {
            let mut all = catalog::build(&p, golden.as_ref(), framing, p.device.default_unit);
            all.extend(
                catalog::regressions(&corpus, &p, p.device.default_unit)
                    .unwrap_or_else(|e| panic!("{e}")),
            );
            for c in &all {
                cases += 1;
                let (r, _) = reqs.cited(&c.id, &name);
                if r.is_empty() {
                    uncited.push(format!("{name} {framing:?}: {}", c.id));
                }
                cited_ids.extend(r);
                for (i, cite) in reqs.cites().iter().enumerate() {
                    if cite.matches(&c.id, &name) {
                        used.insert(i);
                    }
                }
            }
        }
    }
    assert!(cases > 1000, "only {cases} cases built");
    test_support::assert_none(
        &uncited,
        "case(s) cite no requirement (add a [[cite]] to corpus/requirements/cases.toml)",
    );
    let unused: Vec<String> = reqs
        .cites()
        .iter()
        .enumerate()
        .filter(|(i, _)| !used.contains(i))
        .map(|(_, c)| format!("{}:{} `{}`", c.origin.file, c.origin.line, c.cases))
        .collect();
    assert!(
        unused.is_empty(),
        "citation map entries that match no catalog case:\n{}",
        unused.join("\n")
    );
    // Most of what the documents list is exercised by the catalog.
    for cov in reqs.coverage(cited_ids.iter().map(String::as_str)) {
        assert!(
            cov.exercised * 10 >= cov.listed * 8,
            "{}: {} of {} requirements exercised; not exercised: {:?}",
            cov.document,
            cov.exercised,
            cov.listed,
            cov.missing
        );
    }
}
