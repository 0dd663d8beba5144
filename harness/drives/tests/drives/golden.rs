//! The golden frames of the manuals (corpus/golden/*.toml, as embedded in the build): every entry is consistent,
//! every erratum is demonstrated, the bytes the project uses are canonical frames, and the check itself bites.

use std::collections::{BTreeMap, BTreeSet};

use codec::{DecodeErrorKind, Framing, decode_any, hex_spaced, parse_hex, rtu, tcp};
use drives::corpus::Corpus;
use drives::golden::{
    Expect, Form, GoldenDirection, GoldenFile, GoldenFrame, WordOrder, check_frame,
};
use drives::profile::Profile;

struct Loaded {
    name: String,
    file: GoldenFile,
    order: WordOrder,
}

/// Every golden file with the word order of its profile (high word first while the profile does not exist yet).
/// A file or profile that does not parse fails the test here, with every such problem listed.
fn load_all() -> Vec<Loaded> {
    let corpus = Corpus::Embedded;
    let files = corpus.files("golden").expect("embedded corpus");
    assert!(!files.is_empty(), "no golden files embedded");
    let mut out = Vec::new();
    let mut problems = Vec::new();
    for (name, text) in files {
        let file = match GoldenFile::parse(&name, &text) {
            Ok(f) => f,
            Err(e) => {
                problems.push(e.to_string());
                continue;
            }
        };
        let order = match corpus.file("profiles", &file.profile) {
            Ok((pname, ptext)) => match Profile::parse(&pname, &ptext) {
                Ok(p) => p.device.word_order,
                Err(e) => {
                    problems.push(format!("{name}: profile `{}`: {e}", file.profile));
                    continue;
                }
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => WordOrder::HighFirst,
            Err(e) => panic!("reading profile {}: {e}", file.profile),
        };
        out.push(Loaded { name, file, order });
    }
    assert!(
        problems.is_empty(),
        "corpus files do not load:\n  {}",
        problems.join("\n  ")
    );
    out
}

fn frames() -> Vec<(String, GoldenFrame, WordOrder)> {
    load_all()
        .into_iter()
        .flat_map(|l| {
            let name = l.name;
            let order = l.order;
            l.file
                .frames
                .into_iter()
                .map(move |f| (name.clone(), f, order))
        })
        .collect()
}

fn fail_with(what: &str, problems: Vec<String>) {
    assert!(
        problems.is_empty(),
        "{} golden frame(s) {what}:\n  {}",
        problems.len(),
        problems.join("\n  ")
    );
}

/// The bytes of an optional hex field, when it is there and parses.
fn bytes_of(s: &Option<String>) -> Option<Vec<u8>> {
    s.as_ref().and_then(|h| parse_hex(h).ok())
}

#[test]
fn every_golden_frame_is_consistent() {
    let all = frames();
    assert!(!all.is_empty(), "the golden files hold no frames");
    let mut problems = Vec::new();
    for (file, f, order) in &all {
        let c = check_frame(f, *order);
        if c.ok() {
            continue;
        }
        let mut why = Vec::new();
        if let Err(e) = &c.decoded {
            why.push(format!(
                "used bytes [{}] do not decode: {e}",
                hex_spaced(&c.bytes)
            ));
        }
        why.extend(c.mismatches.iter().cloned());
        why.extend(c.entry_errors.iter().cloned());
        if c.printed_faults.as_ref().is_some_and(|p| p.is_empty()) {
            why.push(
                "erratum not shown: the printed bytes decode and meet every expectation".into(),
            );
        }
        problems.push(format!(
            "{} ({file}, line {}): {}",
            f.id,
            f.line,
            why.join("; ")
        ));
    }
    fail_with("are inconsistent", problems);
}

#[test]
fn corrected_bytes_make_the_printed_ones_faulty() {
    let mut problems = Vec::new();
    for (_, f, order) in frames() {
        let (Some(p), Some(c)) = (bytes_of(&f.printed), bytes_of(&f.corrected)) else {
            continue;
        };
        if p == c {
            continue;
        }
        match check_frame(&f, order).printed_faults {
            Some(faults) if !faults.is_empty() => {}
            other => problems.push(format!(
                "{}: printed [{}] differs from corrected [{}] but is not shown faulty ({other:?})",
                f.id,
                hex_spaced(&p),
                hex_spaced(&c)
            )),
        }
    }
    fail_with("claim an erratum the printed bytes do not show", problems);
}

#[test]
fn rtu_frames_carry_a_valid_crc() {
    let mut problems = Vec::new();
    let mut seen = 0;
    for (_, f, order) in frames() {
        if f.form != Form::Rtu {
            continue;
        }
        seen += 1;
        let used = check_frame(&f, order).bytes;
        if !rtu::crc_ok(&used) {
            let crc = if used.len() >= 2 {
                rtu::crc16(&used[..used.len() - 2])
            } else {
                0
            };
            problems.push(format!(
                "{}: [{}] has a bad CRC (expected {:02X} {:02X})",
                f.id,
                hex_spaced(&used),
                crc & 0xFF,
                crc >> 8
            ));
        }
    }
    assert!(seen > 0, "no RTU golden frames to check");
    fail_with("carry a bad CRC", problems);
}

#[test]
fn used_frames_re_encode_to_the_same_bytes() {
    let mut problems = Vec::new();
    for (_, f, order) in frames() {
        let used = check_frame(&f, order).bytes;
        let framing = f.form.framing();
        let Ok(d) = decode_any(&used, framing, f.direction.into()) else {
            continue; // reported by every_golden_frame_is_consistent
        };
        let again = match framing {
            Framing::Rtu => rtu::encode(d.unit.expect("RTU has an address"), &d.pdu),
            Framing::Tcp => tcp::encode(
                d.transaction_id.expect("MBAP has a transaction id"),
                d.unit.expect("MBAP has a unit id"),
                &d.pdu,
            ),
            Framing::Pdu => {
                let mut v = Vec::new();
                d.pdu.encode(&mut v).map(|_| v)
            }
        };
        match again {
            Ok(b) if b == used => {}
            Ok(b) => problems.push(format!(
                "{}: [{}] re-encodes as [{}]",
                f.id,
                hex_spaced(&used),
                hex_spaced(&b)
            )),
            Err(e) => problems.push(format!("{}: decodes but does not re-encode: {e}", f.id)),
        }
    }
    fail_with("do not round-trip", problems);
}

#[test]
fn ids_are_unique_and_responses_name_a_request_of_their_file() {
    let mut problems = Vec::new();
    let mut all_ids = BTreeSet::new();
    for l in load_all() {
        let directions: BTreeMap<&str, GoldenDirection> = l
            .file
            .frames
            .iter()
            .map(|f| (f.id.as_str(), f.direction))
            .collect();
        for f in &l.file.frames {
            if !all_ids.insert(f.id.clone()) {
                problems.push(format!("{}: duplicate id", f.id));
            }
            if let Some(r) = &f.request {
                if f.direction != GoldenDirection::Response {
                    problems.push(format!("{}: a request entry names a request `{r}`", f.id));
                }
                match directions.get(r.as_str()) {
                    Some(GoldenDirection::Request) => {}
                    Some(GoldenDirection::Response) => {
                        problems.push(format!("{}: `request = {r}` is a response entry", f.id))
                    }
                    None => problems.push(format!(
                        "{}: `request = {r}` is no entry of {}",
                        f.id, l.name
                    )),
                }
            }
        }
    }
    fail_with("have bad ids", problems);
}

// ---------------------------------------------------------------------------------------------------------------
// The check bites: corrupted corrected bytes and vacuous errata are reported
// ---------------------------------------------------------------------------------------------------------------

/// `f` with `bytes` as its corrected bytes and no printed bytes (a template), so that only the corrected bytes
/// decide the outcome.
fn with_corrected(f: &GoldenFrame, bytes: &[u8]) -> GoldenFrame {
    let mut g = f.clone();
    g.printed = None;
    g.printed_text = Some("template".into());
    g.corrected = Some(hex_spaced(bytes));
    g.erratum = Some("test".into());
    g.evidence = Some("test".into());
    g.alternative = None;
    g.adopted = None;
    g
}

fn fc_offset(form: Form) -> usize {
    match form {
        Form::Rtu => 1,
        Form::Tcp => tcp::MBAP_LEN,
        Form::Pdu => 0,
    }
}

#[test]
fn corrupted_golden_frames_are_reported() {
    let mut tried_fc = 0;
    let mut tried_crc = 0;
    for (_, f, order) in frames() {
        let original = check_frame(&f, order);
        if !original.ok() {
            continue; // inconsistent entries are reported by every_golden_frame_is_consistent
        }
        let used = original.bytes.clone();
        let base = with_corrected(&f, &used);
        let c = check_frame(&base, order);
        assert!(
            c.ok(),
            "{}: the unmodified clone must pass: {:?}",
            f.id,
            (c.decoded, c.mismatches, c.entry_errors)
        );

        // another function code (CRC recomputed for RTU): every entry that expects a function code must fail
        if let Some(want) = f.expect.function {
            tried_fc += 1;
            let mut bad = used.clone();
            bad[fc_offset(f.form)] ^= 0x01;
            if f.form == Form::Rtu {
                let n = bad.len() - 2;
                let crc = rtu::crc16(&bad[..n]);
                bad[n..].copy_from_slice(&crc.to_le_bytes());
            }
            let c = check_frame(&with_corrected(&f, &bad), order);
            assert!(
                !c.ok(),
                "{}: function code 0x{:02X} instead of 0x{want:02X} passes the check",
                f.id,
                bad[fc_offset(f.form)]
            );
            assert!(c.entry_errors.is_empty(), "{:?}", c.entry_errors);
            if c.decoded.is_ok() {
                assert!(
                    c.mismatches.iter().any(|m| m.starts_with("function")),
                    "{}: {:?}",
                    f.id,
                    c.mismatches
                );
            }
        }

        // a broken CRC
        if f.form == Form::Rtu {
            tried_crc += 1;
            let mut bad = used.clone();
            *bad.last_mut().unwrap() ^= 0x01;
            let c = check_frame(&with_corrected(&f, &bad), order);
            assert!(!c.ok(), "{}: a bad CRC passes the check", f.id);
            match &c.decoded {
                Err(e) => assert!(
                    matches!(e.kind, DecodeErrorKind::Crc { .. }),
                    "{}: {e}",
                    f.id
                ),
                Ok(d) => panic!("{}: bad CRC decodes as {d:?}", f.id),
            }
        }
    }
    assert!(
        tried_fc > 0,
        "no consistent golden frame with an expected function code"
    );
    assert!(tried_crc > 0, "no consistent RTU golden frame");
}

#[test]
fn an_erratum_whose_printed_bytes_are_fine_is_reported() {
    let (_, real, order) = frames()
        .into_iter()
        .next()
        .expect("at least one golden frame");
    let mut f = real.clone();
    f.form = Form::Pdu;
    f.direction = GoldenDirection::Request;
    f.request = None;
    f.printed = Some("03 07 D0 00 01".into());
    f.printed_text = None;
    f.corrected = Some("03 07 D0 00 02".into());
    f.erratum = Some("quantity".into());
    f.evidence = Some("test".into());
    f.alternative = None;
    f.adopted = None;
    f.expect = Expect::default();
    // nothing pins the quantity: the printed bytes are as good as the corrected ones
    let c = check_frame(&f, order);
    assert_eq!(c.printed_faults, Some(vec![]));
    assert!(!c.ok(), "a vacuous erratum passes");
    // pin it, and the erratum is shown
    f.expect.quantity = Some(2);
    let c = check_frame(&f, order);
    assert!(c.ok(), "{:?}", (c.mismatches, c.printed_faults));
    assert!(
        c.printed_faults
            .as_ref()
            .is_some_and(|p| p.iter().any(|m| m.starts_with("quantity"))),
        "{:?}",
        c.printed_faults
    );
}
