//! `junit.xml`: one `<testsuite>` in a `<testsuites>`, one `<testcase>` per case.
//!
//! Verdict mapping: FAIL has a `<failure>` (first finding as the message, every finding in the body),
//! SKIPPED a `<skipped>` (the reason as the message); PASS, NON-STRICT, INFORMATIONAL and UNIMPLEMENTED are
//! passing test cases. Each test case's `<system-out>` starts with `verdict: …`; the suite has a property per
//! verdict count (`count.NON-STRICT`, ...) and a `<system-out>` listing the NON-STRICT, UNIMPLEMENTED and
//! INFORMATIONAL cases, so that they are visible in a CI's JUnit view without failing the job. The
//! `<system-out>` of a PASS case has its steps and wire log for the first [`PASS_IN_FULL`] PASS cases only;
//! later ones have the verdict and the id, and say where the rest is (`cases.jsonl`, `session.pcapng`): a
//! long generated run's JUnit file stays readable by a CI, and writing a million PASS cases' wire logs twice
//! was the larger part of what the JUnit file cost (BENCHMARKS.md, issue 17 item 3).
//!
//! The file is valid against the schema Jenkins' xUnit plugin uses (`harness/cli/tests/data/jenkins-junit.xsd`,
//! checked by a test): no `<properties>` inside a `<testcase>`, no `skipped` on `<testsuites>`. The class
//! name is the case id up to its last `/` with `/` as `.` and the dots of a segment as `_`
//! (`golden/sd2x/6.1/shutdown/request` is class `golden.sd2x.6_1.shutdown`, test `request`), so that a CI
//! that splits the class name at its dots into packages gets the id's own levels.
//!
//! The test cases are streamed to `junit.xml.partial`; the `<testsuite>` header with the final counts is
//! written at `finish`, which assembles `junit.xml`.

use std::fmt::Write as _;
use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use quick_xml::Writer;
use quick_xml::events::{BytesDecl, BytesEnd, BytesStart, BytesText, Event};

use super::{
    Buffered, CASE_LINES_FILE, JUNIT_FILE, PCAP_FILE, RunInfo, Sink, Stream, Summary, iso8601_utc,
    outcome_text, promote, wire_line, with_path, xml_safe,
};
use crate::{Case, CaseResult, Verdict};
use codec::hex_spaced;

/// Writes `junit.xml`.
pub struct JunitSink {
    dir: PathBuf,
    info: RunInfo,
    /// The `<testcase>` elements, `junit.xml.partial`.
    cases: Stream<Writer<BufWriter<File>>>,
    tests: usize,
    failures: usize,
    skipped: usize,
    /// The first case ids of each verdict in [`NOTED`], and how many there were.
    noted: Vec<(Verdict, Vec<String>, usize)>,
    /// PASS cases written so far.
    passes: usize,
}

/// How many PASS cases have their steps and wire log in `<system-out>` (as many as the HTML report shows).
pub const PASS_IN_FULL: usize = super::html::HTML_PASS_ROWS;

/// How many case ids per verdict the suite's `<system-out>` lists (the rest are counted).
const LISTED_PER_VERDICT: usize = 200;

/// The verdicts that pass but that a CI view should show: listed in the suite's `<system-out>`.
const NOTED: [Verdict; 3] = [
    Verdict::NonStrict,
    Verdict::Unimplemented,
    Verdict::Informational,
];

/// `classname` (the id up to its last `/`, `/` as `.` and a segment's own dots as `_`) and `name` (the
/// last segment) of a case id.
pub fn junit_names(id: &str) -> (String, &str) {
    match id.rsplit_once('/') {
        Some((class, name)) => (
            class
                .split('/')
                .map(|segment| segment.replace('.', "_"))
                .collect::<Vec<_>>()
                .join("."),
            name,
        ),
        None => ("modbus-harness".to_string(), id),
    }
}

impl Buffered for Writer<BufWriter<File>> {
    fn buffer(&mut self) -> &mut BufWriter<File> {
        self.get_mut()
    }
}

impl JunitSink {
    /// Start `junit.xml.partial` in `dir`.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        Ok(Self {
            dir: dir.to_path_buf(),
            info: info.clone(),
            cases: Stream::wrapping(dir, JUNIT_FILE, |out| {
                io::Result::Ok(Writer::new_with_indent(out, b' ', 2))
            })?,
            tests: 0,
            failures: 0,
            skipped: 0,
            noted: NOTED.iter().map(|v| (*v, Vec::new(), 0)).collect(),
            passes: 0,
        })
    }

    fn write_case(
        xml: &mut Writer<BufWriter<File>>,
        case: &Case,
        result: &CaseResult,
        in_full: bool,
    ) -> io::Result<()> {
        let id = xml_safe(&result.id);
        let (class, name) = junit_names(&id);
        let time = format!("{:.6}", result.duration.as_secs_f64());
        let start = BytesStart::new("testcase").with_attributes([
            ("classname", class.as_str()),
            ("name", name),
            ("time", time.as_str()),
        ]);
        xml.write_event(Event::Start(start))?;

        // No <properties> here: the common JUnit schema has none in a test case; the verdict, an expected
        // deviation, the reference and the level are the first lines of <system-out>.
        match result.verdict {
            Verdict::Fail => {
                let body = findings_text(result);
                let message = result
                    .findings()
                    .next()
                    .or(result.reason.as_ref())
                    .map_or_else(|| "FAIL".to_string(), |m| one_line(m));
                xml.create_element("failure")
                    .with_attributes([("message", message.as_str()), ("type", "FAIL")])
                    .write_text_content(BytesText::new(&xml_safe(&body)))?;
            }
            Verdict::Skipped => {
                let message = one_line(result.reason.as_deref().unwrap_or("skipped"));
                xml.create_element("skipped")
                    .with_attribute(("message", message.as_str()))
                    .write_empty()?;
            }
            _ => {}
        }

        let out = if in_full {
            system_out(case, result)
        } else {
            format!(
                "verdict: {}\nid: {}\nsteps and wire log: {CASE_LINES_FILE}, {PCAP_FILE} (junit.xml has them for the first {PASS_IN_FULL} PASS cases)\n",
                result.verdict, result.id
            )
        };
        xml.create_element("system-out")
            .write_text_content(BytesText::new(&xml_safe(&out)))?;
        xml.write_event(Event::End(BytesEnd::new("testcase")))
    }

    fn assemble(&self, summary: &Summary) -> io::Result<()> {
        let tmp = self.dir.join(format!("{JUNIT_FILE}.tmp"));
        let file = File::create(&tmp).map_err(with_path("cannot create", &tmp))?;
        let mut xml = Writer::new_with_indent(
            BufWriter::with_capacity(super::STREAM_BUFFER, file),
            b' ',
            2,
        );
        let tests = self.tests.to_string();
        let failures = self.failures.to_string();
        let skipped = self.skipped.to_string();
        let time = format!("{:.3}", summary.duration.as_secs_f64());
        let stamp = iso8601_utc(self.info.started_unix_ms);
        let timestamp = &stamp[..19];
        let suite_name = xml_safe(&format!(
            "modbus-harness {} {}",
            self.info.profile, self.info.target
        ))
        .into_owned();
        let counts: [(&str, &str); 4] = [
            ("tests", &tests),
            ("failures", &failures),
            ("errors", "0"),
            ("time", &time),
        ];
        let write = |xml: &mut Writer<BufWriter<File>>| -> io::Result<()> {
            xml.write_event(Event::Decl(BytesDecl::new("1.0", Some("UTF-8"), None)))?;
            xml.write_event(Event::Start(
                BytesStart::new("testsuites")
                    .with_attributes([("name", "modbus-harness")])
                    .with_attributes(counts),
            ))?;
            xml.write_event(Event::Start(
                BytesStart::new("testsuite")
                    .with_attributes([("name", suite_name.as_str())])
                    .with_attributes(counts)
                    .with_attributes([("skipped", skipped.as_str())])
                    .with_attributes([("timestamp", timestamp), ("hostname", "localhost")]),
            ))?;
            xml.write_event(Event::Start(BytesStart::new("properties")))?;
            let seed = self.info.seed.map(|s| s.to_string()).unwrap_or_default();
            let port = self.info.server_port.to_string();
            let interrupted = summary.interrupted.to_string();
            let counts_by_verdict: Vec<(String, String)> = Verdict::ALL
                .into_iter()
                .map(|v| (format!("count.{}", v.label()), summary.count(v).to_string()))
                .collect();
            // Leaving the drive as found: one property for the account, one per parameter not put back.
            let mut restore: Vec<(String, String)> = Vec::new();
            if let Some(a) = &summary.leave_as_found {
                restore.push((
                    "leave_as_found".into(),
                    if !a.snapshot_taken {
                        "nothing written".into()
                    } else if a.clean() {
                        format!("restored: {} parameter(s) read as before", a.kept)
                    } else {
                        format!("NOT RESTORED: {} parameter(s)", a.unrestored.len())
                    },
                ));
                for u in &a.unrestored {
                    restore.push((
                        format!("not_restored.{}", u.key),
                        format!("{}: {}", u.name, u.what()),
                    ));
                }
            }
            // Why the run ended early, and the targets that stopped answering and came back.
            if let Some(e) = &summary.ended {
                restore.push(("ended".into(), e.clone()));
            }
            for (i, l) in summary.liveness.iter().enumerate() {
                restore.push((format!("liveness.{i}"), l.clone()));
            }
            if let Some(l) = &summary.link {
                restore.push(("link".into(), l.clone()));
            }
            for (name, value) in restore
                .iter()
                .map(|(n, v)| (n.as_str(), v.as_str()))
                .chain([
                    ("target", self.info.target.as_str()),
                    ("profile", &self.info.profile),
                    ("transport", self.info.transport.label()),
                    ("server_port", &port),
                    ("command_line", &self.info.command_line),
                    ("seed", &seed),
                    ("harness_version", &self.info.harness_version),
                    ("interrupted", &interrupted),
                    ("result", summary.result_label()),
                ])
                .chain(
                    counts_by_verdict
                        .iter()
                        .map(|(n, v)| (n.as_str(), v.as_str())),
                )
            {
                let value = one_line(value);
                xml.write_event(Event::Empty(
                    BytesStart::new("property")
                        .with_attributes([("name", name), ("value", &*value)]),
                ))?;
            }
            xml.write_event(Event::End(BytesEnd::new("properties")))?;
            xml.get_mut().write_all(b"\n")?;
            let mut cases = File::open(self.cases.partial())?;
            io::copy(&mut cases, xml.get_mut())?;
            xml.create_element("system-out")
                .write_text_content(BytesText::new(&xml_safe(&self.suite_out(summary))))?;
            xml.write_event(Event::End(BytesEnd::new("testsuite")))?;
            xml.write_event(Event::End(BytesEnd::new("testsuites")))?;
            xml.get_mut().write_all(b"\n")?;
            xml.get_mut().flush()
        };
        write(&mut xml).map_err(with_path("cannot write", &tmp))?;
        drop(xml);
        promote(&tmp, &self.dir.join(JUNIT_FILE))?;
        let partial = self.cases.partial();
        fs::remove_file(partial).map_err(with_path("cannot remove", partial))
    }
}

impl JunitSink {
    /// The suite's `<system-out>`: the result, the counts, and the cases that pass with a remark.
    fn suite_out(&self, summary: &Summary) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "RESULT: {} ({})",
            summary.result_label(),
            summary.counts_line()
        );
        for (verdict, ids, count) in &self.noted {
            if *count == 0 {
                continue;
            }
            let _ = writeln!(s, "{verdict} ({count}):");
            for id in ids {
                let _ = writeln!(s, "  {id}");
            }
            if *count > ids.len() {
                let _ = writeln!(s, "  ... and {} more", count - ids.len());
            }
        }
        s
    }
}

impl Sink for JunitSink {
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        let in_full = result.verdict != Verdict::Pass || self.passes < PASS_IN_FULL;
        self.cases
            .write(|xml| Self::write_case(xml, case, result, in_full))?;
        self.passes += usize::from(result.verdict == Verdict::Pass);
        self.tests += 1;
        match result.verdict {
            Verdict::Fail => self.failures += 1,
            Verdict::Skipped => self.skipped += 1,
            _ => {}
        }
        if let Some((_, ids, count)) = self.noted.iter_mut().find(|(v, ..)| *v == result.verdict) {
            *count += 1;
            if ids.len() < LISTED_PER_VERDICT {
                ids.push(result.id.clone());
            }
        }
        Ok(())
    }

    fn flush(&mut self) -> io::Result<()> {
        self.cases.flush()
    }

    fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        self.cases.close()?;
        self.assemble(summary)
    }
}

/// An attribute value on one line (parsers turn newlines in attributes into spaces anyway).
fn one_line(s: &str) -> String {
    xml_safe(s).replace(['\r', '\n'], " ")
}

/// Every finding, with its step, one per line; and the reason, if any.
fn findings_text(result: &CaseResult) -> String {
    let mut s = String::new();
    for (i, step) in result.steps.iter().enumerate() {
        for f in &step.findings {
            let _ = writeln!(s, "step {} ({}): {f}", i + 1, step.note);
        }
    }
    if let Some(reason) = &result.reason {
        let _ = writeln!(s, "{reason}");
    }
    s
}

/// The verdict, the requirement, each step's sent/expected/observed bytes, and the wire log.
fn system_out(case: &Case, result: &CaseResult) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "verdict: {}", result.verdict);
    if let Some((was, why)) = &result.expected_deviation {
        let _ = writeln!(s, "verdict before the expectations file: {was} ({why})");
    }
    let _ = writeln!(s, "id: {}", result.id);
    let _ = writeln!(s, "title: {}", case.title);
    let _ = writeln!(s, "requirement: {}", case.requirement);
    let _ = writeln!(s, "reference: {}", case.reference);
    let _ = writeln!(s, "level: {}", format!("{:?}", case.level).to_uppercase());
    if let Some(reason) = &result.reason {
        let _ = writeln!(s, "reason: {reason}");
    }
    for (i, step) in result.steps.iter().enumerate() {
        let _ = writeln!(s, "step {}: {} [{}]", i + 1, step.note, step.verdict);
        if let Some(sent) = &step.sent {
            let _ = writeln!(s, "  sent:     {}", hex_spaced(sent));
        }
        let expected = step
            .expected
            .as_deref()
            .map_or_else(|| "(silence)".to_string(), hex_spaced);
        let _ = writeln!(s, "  expected: {expected}");
        for o in &step.observed {
            let _ = writeln!(s, "  observed: {}", outcome_text(o));
        }
        for f in &step.findings {
            let _ = writeln!(s, "  finding:  {f}");
        }
    }
    if !result.wire.is_empty() {
        let _ = writeln!(s, "wire log:");
        for e in &result.wire {
            let _ = writeln!(s, "  {}", wire_line(e));
        }
    }
    s
}
