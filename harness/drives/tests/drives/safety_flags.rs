//! The safety flags of the built-in profiles (issue 13): every `motion` / `destructive` flag says why, citing
//! the manual line (`file:line`) that justifies it (and so does every deliberate non-flag that gives a `why`), and the MDrive and LMD profiles, whose manuals describe the
//! same MCode registers and mnemonics the same way, flag them alike.

use std::collections::BTreeMap;

use crate::support::seeds_dir;
use drives::corpus::Corpus;
use drives::profile::Profile;

fn profile(name: &str) -> Profile {
    Corpus::Embedded.profile(name).expect("profile")
}

/// A flagged entry: what it is, its flags, its `why`, and words the cited line must contain one of.
struct Flagged {
    what: String,
    motion: bool,
    destructive: bool,
    why: Option<String>,
    words: Vec<String>,
}

fn first_word(s: &str) -> Option<String> {
    s.split_whitespace().next().map(|w| w.to_lowercase())
}

fn entries(p: &Profile) -> Vec<Flagged> {
    let mut out = Vec::new();
    for r in p.registers.iter().map(|r| r.get_ref()) {
        out.push(Flagged {
            what: format!("register 0x{:04X} {}", r.address, r.name),
            motion: r.motion,
            destructive: r.destructive,
            why: r.why.clone(),
            words: [
                first_word(&r.name),
                r.mnemonic.clone().map(|m| m.to_lowercase()),
            ]
            .into_iter()
            .flatten()
            .collect(),
        });
    }
    for c in p.coils.iter().map(|c| c.get_ref()) {
        out.push(Flagged {
            what: format!("coil {} {}", c.address, c.name),
            motion: c.motion,
            destructive: c.destructive,
            why: c.why.clone(),
            words: first_word(&c.name).into_iter().collect(),
        });
    }
    for m in p.mnemonics.iter().map(|m| m.get_ref()) {
        out.push(Flagged {
            what: format!("mnemonic {:?}", m.name),
            motion: m.motion,
            destructive: m.destructive,
            why: m.why.clone(),
            // The mnemonic, or a word of its description (first, or any of five letters or more).
            words: [
                (!m.name.is_empty()).then(|| m.name.to_lowercase()),
                m.description.as_deref().and_then(first_word),
            ]
            .into_iter()
            .flatten()
            .chain(
                m.description
                    .iter()
                    .flat_map(|d| d.split(|c: char| !c.is_alphanumeric()))
                    .filter(|w| w.len() >= 5)
                    .map(str::to_lowercase),
            )
            .collect(),
        });
    }
    for o in p.objects.iter().map(|o| o.get_ref()) {
        out.push(Flagged {
            what: format!("object 0x{:04X} {}", o.index, o.name),
            motion: o.motion,
            destructive: o.destructive,
            why: o.why.clone(),
            words: first_word(&o.name)
                .into_iter()
                .chain(Some(format!("{}", o.index)))
                .collect(),
        });
    }
    out
}

/// The `file:line` citations of a `why`.
fn citations(why: &str) -> Vec<(String, usize)> {
    let mut out = Vec::new();
    for part in why.split([' ', ',', '(', ')', ';']) {
        if let Some((file, line)) = part.trim_end_matches(':').split_once(".txt:")
            && let Ok(n) = line.parse::<usize>()
        {
            out.push((format!("{file}.txt"), n));
        }
    }
    out
}

#[test]
fn every_motion_or_destructive_flag_cites_the_manual_line_that_justifies_it() {
    check_citations();
}

fn check_citations() {
    let seeds = seeds_dir();
    if seeds.is_none() {
        eprintln!("shared/seeds not found (set MODBUS_HARNESS_SEEDS): cited lines not read");
    }
    let mut bad = Vec::new();
    let mut flagged = 0;
    for name in ["mdrive", "lmd", "sd2x"] {
        let p = profile(name);
        let manual = p.device.manual.clone().expect("manual");
        let text = seeds
            .as_ref()
            .map(|d| std::fs::read_to_string(d.join(&manual)).expect("manual readable"));
        let lines: Vec<&str> = text.as_deref().map_or(vec![], |t| t.lines().collect());
        for e in entries(&p) {
            // Flagged entries must say why; a deliberate non-flag that says why is held to the same rule.
            if !(e.motion || e.destructive) && e.why.is_none() {
                continue;
            }
            flagged += 1;
            let Some(why) = &e.why else {
                bad.push(format!("{name} {}: flagged without a why", e.what));
                continue;
            };
            let cites = citations(why);
            let Some((file, n)) = cites.first() else {
                bad.push(format!("{name} {}: why cites no file:line: {why}", e.what));
                continue;
            };
            if *file != manual {
                bad.push(format!(
                    "{name} {}: cites {file}, not its manual {manual}",
                    e.what
                ));
            }
            if text.is_some() {
                // Hyphens as spaces: "make up mode" names the make-up mnemonic.
                let line = lines
                    .get(n.wrapping_sub(1))
                    .map(|l| l.to_lowercase().replace('-', " "));
                match line {
                    None => bad.push(format!("{name} {}: {file}:{n} is past the end", e.what)),
                    Some(l) if !e.words.iter().any(|w| l.contains(&w.replace('-', " "))) => bad
                        .push(format!(
                            "{name} {}: {file}:{n} mentions none of {:?}: {l:?}",
                            e.what, e.words
                        )),
                    _ => {}
                }
            }
        }
    }
    assert!(flagged >= 100, "only {flagged} entries with a why");
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Flags by MCode mnemonic: registers by their mnemonic, vendor mnemonics by name, coils by name.
fn by_mnemonic(p: &Profile) -> BTreeMap<String, Vec<(String, bool, bool)>> {
    let mut m: BTreeMap<String, Vec<(String, bool, bool)>> = BTreeMap::new();
    for r in p.registers.iter().map(|r| r.get_ref()) {
        if let Some(n) = &r.mnemonic {
            m.entry(n.to_uppercase()).or_default().push((
                format!("register 0x{:04X}", r.address),
                r.motion,
                r.destructive,
            ));
        }
    }
    for v in p.mnemonics.iter().map(|v| v.get_ref()) {
        m.entry(v.name.to_uppercase()).or_default().push((
            "FC 0x42 mnemonic".into(),
            v.motion,
            v.destructive,
        ));
    }
    for c in p.coils.iter().map(|c| c.get_ref()) {
        m.entry(c.name.to_uppercase()).or_default().push((
            format!("coil {}", c.address),
            c.motion,
            c.destructive,
        ));
    }
    m
}

/// Where the two manuals disagree on purpose: (mnemonic, the MDrive line, the LMD line, why). None today.
const DOCUMENTED_EXCEPTIONS: &[(&str, &str, &str, &str)] = &[];

/// Every disagreement between two profiles' flags for the same mnemonic (and within each profile).
fn disagreements(a: &Profile, b: &Profile) -> Vec<String> {
    let (ma, mb) = (by_mnemonic(a), by_mnemonic(b));
    let mut bad = Vec::new();
    for (p, m) in [(a, &ma), (b, &mb)] {
        for (name, v) in m {
            if v.iter().any(|e| (e.1, e.2) != (v[0].1, v[0].2)) {
                bad.push(format!(
                    "{}: {name} flagged differently within the profile: {v:?}",
                    p.device.id
                ));
            }
        }
    }
    for (name, va) in &ma {
        let Some(vb) = mb.get(name) else { continue };
        if DOCUMENTED_EXCEPTIONS.iter().any(|e| e.0 == name) {
            continue;
        }
        if (va[0].1, va[0].2) != (vb[0].1, vb[0].2) {
            bad.push(format!(
                "{name}: {} {:?} (motion, destructive) = {:?}, {} {:?} = {:?}",
                a.device.id,
                va[0].0,
                (va[0].1, va[0].2),
                b.device.id,
                vb[0].0,
                (vb[0].1, vb[0].2)
            ));
        }
    }
    bad
}

#[test]
fn mdrive_and_lmd_flag_the_same_mnemonics_alike() {
    let (md, lmd) = (profile("mdrive"), profile("lmd"));
    let shared = by_mnemonic(&md)
        .keys()
        .filter(|k| by_mnemonic(&lmd).contains_key(*k))
        .count();
    assert!(shared >= 60, "only {shared} shared mnemonics");
    let bad = disagreements(&md, &lmd);
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    for (name, mdrive_line, lmd_line, why) in DOCUMENTED_EXCEPTIONS {
        assert!(
            !why.is_empty() && mdrive_line.contains(".txt:") && lmd_line.contains(".txt:"),
            "exception {name} must cite both manuals' lines and say why"
        );
    }
    // The check can fail: the MDrive's MS unflagged disagrees with the LMD's.
    let mut changed = md.clone();
    for r in changed.registers.iter_mut() {
        let r = r.get_mut();
        if r.mnemonic.as_deref() == Some("MS") {
            r.motion = false;
        }
    }
    assert!(
        disagreements(&changed, &lmd)
            .iter()
            .any(|d| d.starts_with("MS:")),
        "an unflagged MS is caught"
    );
}
