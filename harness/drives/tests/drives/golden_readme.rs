//! corpus/golden/README.md is generated from the golden files; it must not drift from them.

#[test]
fn errata_readme_is_up_to_date() {
    let corpus =
        drives::corpus::Corpus::Dir(concat!(env!("CARGO_MANIFEST_DIR"), "/../../corpus").into());
    let want = drives::golden::errata_markdown(&corpus.golden_files().expect("golden files load"));
    let have = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../corpus/golden/README.md"
    ))
    .expect("corpus/golden/README.md exists");
    assert!(
        have == want,
        "corpus/golden/README.md is stale: regenerate it with `cargo run -- golden --markdown > corpus/golden/README.md`"
    );
}
