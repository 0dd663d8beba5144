//! The requirements, freedoms and citation map of the corpus: they load, they are consistent, the manuals'
//! quotations are on the lines they cite, and malformed files are rejected with the right line.

use std::collections::BTreeSet;

use crate::support::seeds_dir;
use drives::corpus::Corpus;
use drives::requirements::{
    DocKind, FileKind, FreedomKind, FreedomValue, KnownIds, Level, Requirements,
};

fn embedded() -> Requirements {
    Corpus::Embedded
        .requirements()
        .unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn the_embedded_corpus_loads() {
    let r = embedded();
    let docs: Vec<&str> = r.documents().iter().map(|d| d.id.as_str()).collect();
    for d in ["app", "tcp", "serial", "mdrive", "lmd", "sd2x"] {
        assert!(docs.contains(&d), "document {d} missing: {docs:?}");
        assert!(
            r.requirements().iter().any(|q| q.document == d),
            "document {d} has no requirements"
        );
    }
    assert!(r.freedoms().len() >= 30, "{} freedoms", r.freedoms().len());
    assert!(!r.cites().is_empty());
    // Every manual is cited by line, every specification by section.
    for q in r.requirements() {
        let kind = r.document(&q.document).unwrap().kind;
        assert_eq!(
            q.line.is_some(),
            kind == DocKind::Manual,
            "{}: line {:?}",
            q.id,
            q.line
        );
    }
    // The kinds the brief asks for are there, with the reference's value first.
    let f = r.freedom("value-out-of-range").unwrap();
    assert_eq!(f.kind, FreedomKind::ExceptionCode);
    assert_eq!(f.values, [FreedomValue::Int(3), FreedomValue::Int(4)]);
    let f = r.freedom("lmd-word-order").unwrap();
    assert_eq!(f.values[0], FreedomValue::Text("low-first".into()));
    let f = r.freedom("sd2x-status-word-bits").unwrap();
    assert_eq!(f.values.last(), Some(&FreedomValue::Int(0x004F)));
    assert!(r.requirements().iter().any(|q| q.level == Level::Should));
}

#[test]
fn cited_unions_the_matching_entries_and_filters_freedoms_by_profile() {
    let r = embedded();
    let (reqs, frees) = r.cited("profile/mdrive/write-out-of-range/0x0029-hc", "mdrive");
    assert!(reqs.contains(&"mdrive/5/0x0029-hc".to_string()), "{reqs:?}");
    assert!(
        reqs.contains(&"app/7/03-illegal-data-value".to_string()),
        "{reqs:?}"
    );
    assert_eq!(frees, ["value-out-of-range"]);
    // A profile-limited entry does not leak into another profile.
    let (reqs, frees) = r.cited("spec/app-6/quantity/fc-0x03/max-plus-1", "generic");
    assert!(!reqs.iter().any(|q| q.starts_with("mdrive/")), "{reqs:?}");
    assert_eq!(frees, ["exception-check-order"]);
    let (_, frees) = r.cited("spec/app-6/quantity/fc-0x03/max-plus-1", "sd2x");
    assert_eq!(frees, ["quantity-over-device-limit"]);
    // A freedom limited to other profiles is left out even where a cite names it for every profile.
    let (_, frees) = r.cited("tcp/pipeline/2-requests-one-segment", "sd2x");
    assert!(frees.is_empty(), "{frees:?}");
    // No entry: nothing cited.
    assert_eq!(r.cited("no/such/case", "mdrive"), (Vec::new(), Vec::new()));
}

#[test]
fn coverage_counts_exercised_and_listed_per_document() {
    let r = embedded();
    let cov = r.coverage(["app/7/01-illegal-function", "sd2x/3.6/node-id", "nope"]);
    let app = cov.iter().find(|c| c.document == "app").unwrap();
    assert_eq!(app.exercised, 1);
    assert_eq!(
        app.listed,
        r.requirements()
            .iter()
            .filter(|q| q.document == "app")
            .count()
    );
    assert_eq!(app.missing.len(), app.listed - 1);
    let tcp = cov.iter().find(|c| c.document == "tcp").unwrap();
    assert_eq!(tcp.exercised, 0);
}

// ---- the quotations are on the lines they cite ------------------------------------------------------------

/// The comparison form of a text: markup, emphasis, table rules, cell separators and bullets dropped,
/// hyphenated line breaks joined, whitespace collapsed, lower case.
fn normalize(s: &str) -> String {
    let mut t = s.to_string();
    for tag in [
        "b", "sup", "p", "ul", "li", "table", "thead", "tbody", "tr", "th", "td", "br",
    ] {
        t = t
            .replace(&format!("<{tag}>"), "")
            .replace(&format!("</{tag}>"), "");
        while let Some(i) = t.find(&format!("<{tag} ")) {
            let end = t[i..].find('>').map_or(t.len(), |e| i + e + 1);
            t.replace_range(i..end, "");
        }
    }
    t = t.replace('*', "");
    for c in [
        '_', '|', ';', '\t', '\u{2022}', '\u{25b6}', '\u{25a0}', '\u{fffd}',
    ] {
        t = t.replace(c, " ");
    }
    let mut out = String::new();
    for w in t.split_whitespace() {
        if w.len() >= 3 && w.chars().all(|c| c == '-') {
            continue;
        }
        if !out.is_empty() {
            out.push(' ');
        }
        out.push_str(w);
    }
    let mut out = out.to_lowercase();
    // "re- quired" (a line broken after a hyphen) → "required"; "MODBUS/ TCP" → "MODBUS/TCP".
    let mut i = 0;
    while let Some(p) = out[i..].find("- ") {
        let at = i + p;
        let before = out[..at].chars().last();
        let after = out[at + 2..].chars().next();
        if before.is_some_and(|c| c.is_ascii_lowercase())
            && after.is_some_and(|c| c.is_ascii_lowercase())
        {
            out.replace_range(at..at + 2, "");
        } else {
            i = at + 2;
        }
    }
    out.replace("/ ", "/")
}

#[test]
fn manual_quotations_are_on_their_lines() {
    let Some(dir) = seeds_dir() else {
        eprintln!("shared/seeds not found (set MODBUS_HARNESS_SEEDS): quotations not checked");
        return;
    };
    let r = embedded();
    let mut seeds = std::collections::BTreeMap::new();
    for d in r.documents().iter().filter(|d| d.kind == DocKind::Manual) {
        let text = std::fs::read_to_string(dir.join(d.seed.as_ref().unwrap()))
            .unwrap_or_else(|e| panic!("{}: {e}", d.id));
        seeds.insert(
            d.id.clone(),
            text.lines().map(str::to_string).collect::<Vec<_>>(),
        );
    }
    let mut bad = Vec::new();
    let mut checked = 0;
    let mut check = |doc: &str, line: u32, last: Option<u32>, text: &str, what: &str| {
        let lines = &seeds[doc];
        let (a, b) = (line as usize, last.unwrap_or(line) as usize);
        if b > lines.len() {
            bad.push(format!(
                "{what}: {doc} has {} lines, cited {a}-{b}",
                lines.len()
            ));
            return;
        }
        let hay = normalize(&lines[a - 1..b].join(" "));
        for part in text.split("[...]") {
            let p = normalize(part);
            checked += 1;
            if !p.is_empty() && !hay.contains(&p) {
                bad.push(format!("{what}: not on {doc} lines {a}-{b}: {part:?}"));
            }
        }
    };
    for q in r.requirements().iter().filter(|q| !q.paraphrase) {
        if let Some(l) = q.line {
            check(&q.document, l, q.last_line, &q.text, &q.id);
        }
    }
    for f in r.freedoms() {
        for s in f.sources.iter().filter(|s| !s.paraphrase) {
            if let Some(l) = s.line {
                check(&s.doc, l, s.last_line, &s.text, &f.id);
            }
        }
    }
    // Items: the register's address (its four hex digits) or the mnemonic is on the row the item cites.
    for f in r.freedoms() {
        let doc = &f.profiles[0];
        let Some(lines) = seeds.get(doc) else {
            continue;
        };
        for it in &f.items {
            let Some(l) = it.line else { continue };
            let row = lines[l as usize - 1..(l as usize + 12).min(lines.len())].join(" ");
            let found = match (&it.register, &it.mnemonic) {
                (Some(a), _) => row.to_uppercase().contains(&format!("{a:04X}")),
                (None, Some(m)) if m == "ESC" => row.contains("<ESC>"),
                (None, Some(m)) => row.contains(m.as_str()),
                _ => true,
            };
            if !found {
                bad.push(format!("{}: item {it:?} not on {doc} line {l}", f.id));
            }
        }
    }
    assert!(checked > 500, "only {checked} quotations checked");
    assert!(
        bad.is_empty(),
        "{} of {checked} quotations:\n{}",
        bad.len(),
        bad.join("\n")
    );
}

// ---- malformed files ---------------------------------------------------------------------------------------

const DOC: &str = r#"[document]
id = "m"
title = "A manual"
kind = "manual"
seed = "m.txt"

[[requirement]]
id = "m/1/a"
section = "1"
line = 3
level = "must"
text = "A."
"#;

const FREEDOMS: &str = r#"[[freedom]]
id = "f"
title = "F"
kind = "exception-code"
profiles = ["all"]
values = [3, 4]

[[freedom.sources]]
doc = "m"
line = 3
text = "A."
"#;

const CITES: &str = r#"[[cite]]
cases = "spec/*"
requirements = ["m/1/a"]
freedoms = ["f"]
"#;

fn parse(doc: &str, freedoms: &str, cites: &str) -> Result<Requirements, String> {
    let files = vec![
        (
            FileKind::Requirements,
            "m.toml".to_string(),
            doc.to_string(),
        ),
        (
            FileKind::Freedoms,
            "f.toml".to_string(),
            freedoms.to_string(),
        ),
        (FileKind::Cites, "cases.toml".to_string(), cites.to_string()),
    ];
    Requirements::parse(
        &files,
        &KnownIds {
            profiles: vec!["p".into()],
            golden_frames: Some(BTreeSet::from(["p/1/x/request".to_string()])),
        },
    )
    .map_err(|e| e.to_string())
}

#[test]
fn a_well_formed_set_parses() {
    let r = parse(DOC, FREEDOMS, CITES).unwrap();
    assert_eq!(
        r.cited("spec/x", "p"),
        (vec!["m/1/a".into()], vec!["f".into()])
    );
}

/// `units` is a range: `tcp-unit-ids` concerns every unit id from 1 to 254, not only those two.
#[test]
fn unit_ids_are_a_range() {
    let r = embedded();
    let f = r.freedom("tcp-unit-ids").expect("tcp-unit-ids");
    assert!(f.covers_unit(1) && f.covers_unit(2) && f.covers_unit(247) && f.covers_unit(254));
    assert!(!f.covers_unit(0) && !f.covers_unit(255));
    let parsed = parse(
        DOC,
        &FREEDOMS.replace("exception-code", "unit-ids").replace(
            "values = [3, 4]",
            "values = [\"answer\", \"silence\"]\nunits = [5, 9]",
        ),
        CITES,
    )
    .expect("parses");
    let g = parsed.freedom("f").expect("f");
    assert!(g.covers_unit(7) && !g.covers_unit(4) && !g.covers_unit(10));
}

#[test]
fn malformed_files_are_rejected_with_file_line_and_reason() {
    // Each case breaks one of the three files and keeps the other two as they are.
    let doc = |d: String| [d, FREEDOMS.to_string(), CITES.to_string()];
    let freedoms = |f: String| [DOC.to_string(), f, CITES.to_string()];
    let cites = |c: String| [DOC.to_string(), FREEDOMS.to_string(), c];
    let cases: &[([String; 3], &str)] = &[
        // (requirements, freedoms, cites; expected "file:line: reason" fragment)
        (
            doc(DOC.replace("level = \"must\"", "level = \"shall\"")),
            "m.toml:11: unknown variant `shall`",
        ),
        (
            doc(format!(
                "{DOC}\n[[requirement]]\nid = \"m/1/a\"\nsection = \"1\"\nline = 4\nlevel = \"may\"\ntext = \"B.\"\n"
            )),
            "m.toml:15: requirement `m/1/a` is already defined in m.toml:7",
        ),
        (
            doc(DOC.replace("line = 3\n", "")),
            "m.toml:7: requirement `m/1/a`: a manual's requirement cites its `line`",
        ),
        (
            doc(DOC.replace("id = \"m/1/a\"", "id = \"x/1/a\"")),
            "m.toml:8: requirement id `x/1/a`: must start with `m/`",
        ),
        (
            freedoms(FREEDOMS.replace("exception-code", "exception-kode")),
            "f.toml:4: unknown variant `exception-kode`",
        ),
        (
            freedoms(FREEDOMS.replace("values = [3, 4]", "values = []")),
            "f.toml:6: freedom `f` (exception-code): `values` is empty",
        ),
        (
            freedoms(FREEDOMS.replace("values = [3, 4]", "values = [3, \"four\"]")),
            "f.toml:6: freedom `f` (exception-code): value `four` is not a number",
        ),
        (
            freedoms(FREEDOMS.replace("profiles = [\"all\"]", "profiles = [\"q\"]")),
            "f.toml:5: freedom `f`: unknown profile `q`",
        ),
        (
            freedoms(FREEDOMS.replace("doc = \"m\"", "doc = \"nodoc\"")),
            "f.toml:8: freedom `f`, source: unknown document `nodoc`",
        ),
        (
            freedoms(FREEDOMS.replace(
                "values = [3, 4]\n",
                "values = [3, 4]\ngolden = [\"p/1/y/request\"]\n",
            )),
            "f.toml:7: freedom `f`: no golden frame `p/1/y/request`",
        ),
        (
            freedoms(FREEDOMS.replace("exception-code", "unit-ids").replace(
                "values = [3, 4]",
                "values = [\"answer\", \"silence\"]\nunits = [247, 1]",
            )),
            "freedom `f` (unit-ids): needs `units` = [first, last], an inclusive range",
        ),
        (
            cites(CITES.replace("[\"m/1/a\"]", "[\"m/1/b\"]")),
            "cases.toml:3: cite `spec/*`: no requirement `m/1/b`",
        ),
        (
            cites(CITES.replace("[\"f\"]", "[\"g\"]")),
            "cases.toml:4: cite `spec/*`: no freedom `g`",
        ),
        (
            cites(format!("{CITES}\n[[cite]]\ncases = \"x\"\n")),
            "cases.toml:6: cite `x`: cites neither requirements nor freedoms",
        ),
        (
            cites(CITES.replace("cases = \"spec/*\"", "cases = \"spec/*\"\nkase = 1")),
            "cases.toml:3: unknown field `kase`",
        ),
    ];
    for ([doc, fr, ci], want) in cases {
        let err = parse(doc, fr, ci).expect_err(want);
        assert!(err.contains(want), "expected `{want}`, got `{err}`");
    }
}

#[test]
fn freedom_items_exist_in_their_profile_and_the_first_access_is_the_profiles() {
    let r = embedded();
    for f in r.freedoms() {
        for p in f.profiles.iter().filter(|p| *p != "all") {
            let prof = Corpus::Embedded.profile(p).unwrap();
            for it in &f.items {
                if let Some(a) = it.register {
                    let reg = prof
                        .registers
                        .iter()
                        .map(|x| x.get_ref())
                        .find(|x| x.address == a)
                        .unwrap_or_else(|| panic!("{}: no register 0x{a:04X} in {p}", f.id));
                    if let (Some(n), Some(m)) = (&it.name, &reg.mnemonic) {
                        assert_eq!(n, m, "{}: register 0x{a:04X}", f.id);
                    }
                    if f.kind == FreedomKind::Access {
                        let want = match reg.access {
                            drives::profile::Access::Ro => "ro",
                            drives::profile::Access::Rw => "rw",
                            drives::profile::Access::Wo => "wo",
                        };
                        assert_eq!(
                            f.values[0],
                            FreedomValue::Text(want.into()),
                            "{}: register 0x{a:04X} is {want} in the {p} profile",
                            f.id
                        );
                    }
                }
                if let Some(m) = &it.mnemonic {
                    let name = if m == "ESC" { "\u{1b}" } else { m.as_str() };
                    assert!(
                        prof.mnemonic(name).is_some(),
                        "{}: no mnemonic {m} in {p}",
                        f.id
                    );
                }
            }
        }
    }
}

/// The freedoms the models decide at are freedoms of the data: code and corpus name the same choices.
#[test]
fn every_decision_site_is_a_freedom_of_the_corpus() {
    let r = drives::corpus::Corpus::Embedded
        .requirements()
        .expect("the embedded requirements load");
    for id in drives::choices::ids::ALL {
        assert!(
            r.freedom(id).is_some(),
            "the models decide at `{id}`, which no corpus/freedoms/*.toml defines"
        );
    }
}

/// A coil item (the LMD's output 4, `lmd-output-4`) is touched by FC 01/05/0F covering its address only,
/// and a request covers all of it only where it touches that coil alone.
#[test]
fn a_coil_item_is_touched_by_the_coil_requests_covering_it() {
    use codec::Request;
    let r = embedded();
    let f = r.freedom("lmd-output-4").expect("lmd-output-4");
    let [item] = f.items.as_slice() else {
        panic!("lmd-output-4: one item expected, got {:?}", f.items);
    };
    assert_eq!(item.coil, Some(0x0003));
    let p = Corpus::Embedded.profile("lmd").unwrap();
    assert!(
        p.coils.iter().any(|c| c.get_ref().address == 0x0003),
        "the lmd profile has coil 0x0003"
    );
    let read = |address, quantity| Request::ReadCoils { address, quantity };
    let write = |address| Request::WriteSingleCoil {
        address,
        value: 0xFF00,
    };
    let multiple = |address, quantity: u16| Request::WriteMultipleCoils {
        address,
        quantity,
        data: vec![0; usize::from(quantity).div_ceil(8)],
    };
    for (req, touched, alone) in [
        (read(0, 4), true, false),
        (read(0, 3), false, false),
        (read(3, 1), true, true),
        (read(4, 1), false, false),
        (write(3), true, true),
        (write(2), false, false),
        (multiple(2, 2), true, false),
        (multiple(0, 3), false, false),
        (
            Request::ReadHoldingRegisters {
                address: 3,
                quantity: 1,
            },
            false,
            false,
        ),
        (
            Request::ReadDiscreteInputs {
                address: 3,
                quantity: 1,
            },
            false,
            false,
        ),
    ] {
        assert_eq!(item.touched_by(&req, &p), touched, "touched_by {req:?}");
        if touched {
            assert_eq!(item.covers_all_of(&req, &p), alone, "covers_all_of {req:?}");
        }
    }
}

proptest::proptest! {
    /// The line index the requirements are parsed with gives every offset the line `line_of` gives it (at
    /// a newline, before the first byte, past the end).
    #[test]
    fn the_line_index_agrees_with_line_of(text in "[a\n]{0,60}", offsets in proptest::collection::vec(0usize..70, 1..10)) {
        let index = drives::profile::LineIndex::new(&text);
        for offset in offsets {
            proptest::prop_assert_eq!(index.line(offset), drives::profile::line_of(&text, offset));
        }
    }
}
