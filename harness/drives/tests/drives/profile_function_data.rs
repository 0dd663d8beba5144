//! Profile validation of the data the function codes 07, 08, 11, 14/15, 18 and 2B/0E serve: every case of
//! tests/data/function_data_errors.toml is rejected at the line of its offending entry with its reason, and
//! tests/data/full_fc.toml, which declares them all, loads.

use drives::profile::{Profile, ProfileError};
use serde::Deserialize;

use crate::support::profile;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Cases {
    base: String,
    case: Vec<Case>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Case {
    name: String,
    text: String,
    line: usize,
    reason: String,
}

#[test]
fn function_data_errors_name_the_line_and_the_rule() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/function_data_errors.toml"
    );
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {path}: {e}"));
    let cases: Cases = toml::from_str(&text).unwrap_or_else(|e| panic!("parse {path}: {e}"));
    // `max_pdu = N` lines of a case belong to [device]: the base ends with that table.
    let base_lines = cases.base.lines().count();
    let mut wrong = Vec::new();
    for c in &cases.case {
        let profile_text = format!("{}{}", cases.base, c.text);
        let want_line = base_lines + c.line;
        match Profile::parse(&c.name, &profile_text) {
            Err(ProfileError::Invalid { line, reason, .. })
                if line == want_line && reason.contains(&c.reason) => {}
            Err(e) => wrong.push(format!(
                "{}: {e}; want line {want_line} and `{}`",
                c.name, c.reason
            )),
            Ok(_) => wrong.push(format!("{}: accepted", c.name)),
        }
    }
    assert!(
        wrong.is_empty(),
        "{} of {} cases:\n  {}",
        wrong.len(),
        cases.case.len(),
        wrong.join("\n  ")
    );
}

#[test]
fn the_full_function_code_profile_loads() {
    let p = profile("data/full_fc");
    assert_eq!(p.functions.len(), 19);
    assert_eq!(p.diagnostics.len(), 15);
    assert_eq!(p.files.len(), 4);
    assert_eq!(p.fifos.len(), 4);
    assert_eq!(p.fifo(0x04DE).map(|q| q.values.len()), Some(2));
    assert_eq!(p.file(6).map(|f| f.records), Some(10_000));
    assert!(p.server_id.is_some() && p.exception_status.is_some());
}
