//! `junit.xml` as a CI reads it: valid against the JUnit schema of Jenkins' xUnit plugin
//! (`tests/data/jenkins-junit.xsd`, with `xmllint` when it is installed: `.ci/run` installs it), class names
//! that split at their dots into the case id's levels, and NON-STRICT / UNIMPLEMENTED cases visible at suite
//! level (properties and `<system-out>`) although they pass.

use std::path::{Path, PathBuf};
use std::process::Command;

use test_support::{TempDir, harness, runs, sim_run_args, skip, skip_unless};

fn xsd() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/jenkins-junit.xsd")
}

/// `xmllint --schema` on `file`: Ok, or the errors it printed.
fn validate(file: &Path) -> Result<(), String> {
    let out = Command::new("xmllint")
        .args(["--noout", "--schema"])
        .arg(xsd())
        .arg(file)
        .output()
        .expect("run xmllint");
    if out.status.success() {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).into_owned())
    }
}

/// True when xmllint is there; in CI (`CI` set) its absence is a failure, elsewhere a visible skip.
fn xmllint_or_skip(test: &str) -> bool {
    let have = runs("xmllint", &["--version"]);
    if !have {
        assert!(
            std::env::var_os("CI").is_none(),
            "xmllint is missing in CI: .ci/run installs libxml2-utils"
        );
        skip(
            test,
            "xmllint is not installed (apt-get install libxml2-utils)",
        );
    }
    have
}

const EXPECT: &str = r#"
[[deviation]]
case = "profile/mdrive/write-out-of-range/0x0000-*"
verdict = "NON-STRICT"
reason = "accepted for this test: register 0x0000 stores out-of-range values"
"#;

/// A run with every kind of test case: FAIL, SKIPPED (--policy-on-sim), NON-STRICT (an expected deviation).
fn report(dir: &Path) -> (String, PathBuf) {
    let expect = dir.join("expect.toml");
    std::fs::write(&expect, EXPECT).expect("write");
    let report = dir.join("r");
    let (code, _, err) = harness(&sim_run_args(
        "sim:mdrive",
        &[
            "--policy-on-sim",
            "--fault",
            "range-unchecked",
            "--expect",
            expect.to_str().expect("utf-8 path"),
            "--report",
            report.to_str().expect("utf-8 path"),
        ],
    ));
    assert_eq!(code, 1, "{err}");
    let file = report.join("junit.xml");
    (std::fs::read_to_string(&file).expect("junit.xml"), file)
}

/// The value of attribute `name` in the first element that starts with `tag`.
fn attribute<'a>(xml: &'a str, tag: &str, name: &str) -> Option<&'a str> {
    let start = xml.find(tag)?;
    let element = &xml[start..start + xml[start..].find('>')?];
    let at = element.find(&format!(" {name}=\""))? + name.len() + 3;
    Some(&element[at..at + element[at..].find('"')?])
}

#[test]
fn junit_is_valid_against_the_jenkins_schema_and_shows_non_strict_cases() {
    let dir = TempDir::new("cli-junit");
    let (xml, file) = report(dir.path());

    // The structure the schema asks for, checked here too (also where xmllint is missing).
    assert!(
        attribute(&xml, "<testsuites", "skipped").is_none(),
        "no skipped on <testsuites>"
    );
    assert!(attribute(&xml, "<testsuite ", "skipped").is_some_and(|n| n != "0"));
    let mut cases = 0;
    for chunk in xml.split("<testcase ").skip(1) {
        cases += 1;
        let body = &chunk[..chunk.find("</testcase>").expect("closed testcase")];
        assert!(
            !body.contains("<properties"),
            "properties in a testcase: {body}"
        );
        let class = attribute(&format!("<testcase {body}"), "<testcase", "classname")
            .expect("classname")
            .to_string();
        assert!(!class.contains('/'), "{class}");
    }
    assert!(cases > 300, "{cases} test cases");
    // The id's levels are the class name's packages; the dots of a section number do not split it.
    assert!(
        xml.contains(
            r#"<testcase classname="golden.mdrive.4_2_4.read-max-velocity" name="request""#
        ),
        "class names"
    );

    // NON-STRICT is visible at suite level: a count property and the case in the suite's system-out.
    let non_strict = attribute(&xml, r#"<property name="count.NON-STRICT""#, "value")
        .expect("count.NON-STRICT")
        .parse::<usize>()
        .expect("a number");
    assert!(
        non_strict > 0,
        "the expected deviation made NON-STRICT cases"
    );
    assert!(
        attribute(&xml, r#"<property name="count.UNIMPLEMENTED""#, "value").is_some(),
        "count.UNIMPLEMENTED"
    );
    let suite_out = &xml[xml.rfind("<system-out>").expect("suite system-out")..];
    assert!(
        suite_out.contains(&format!("NON-STRICT ({non_strict}):")),
        "{suite_out}"
    );
    assert!(
        suite_out.contains("  profile/mdrive/write-out-of-range/0x0000-a"),
        "{suite_out}"
    );
    assert!(suite_out.contains("RESULT: FAIL ("), "{suite_out}");

    skip_unless!(xmllint_or_skip);
    validate(&file).unwrap_or_else(|e| panic!("junit.xml is not valid:\n{e}"));
    // The schema is not a formality: the shape this file had before (properties inside a test case, a
    // skipped count on <testsuites>) is refused.
    for (what, bad) in [
        (
            "properties in a testcase",
            xml.replacen(
                "<system-out>verdict:",
                r#"<properties><property name="verdict" value="PASS"/></properties><system-out>verdict:"#,
                1,
            ),
        ),
        (
            "skipped on testsuites",
            xml.replacen(
                r#"<testsuites name="modbus-harness""#,
                r#"<testsuites name="modbus-harness" skipped="1""#,
                1,
            ),
        ),
    ] {
        assert_ne!(bad, xml, "{what}: the edit applies");
        let f = dir.path().join("bad.xml");
        std::fs::write(&f, bad).expect("write");
        assert!(validate(&f).is_err(), "{what} must not validate");
    }
}
