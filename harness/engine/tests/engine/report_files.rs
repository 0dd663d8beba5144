//! The report files: index.json, cases.jsonl, cases/, junit.xml, report.html, session.pcapng (checked with
//! tshark when installed), the terminal summary, and what an interrupted or killed run leaves.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use engine::Verdict;
use engine::reports::{
    self, FAILING_CAP, Reports, Summary, Tally, Transport, case_file_name, pcap_decode_args,
    terminal_summary,
};
use quick_xml::events::Event;
use test_support::reports::{IDS, INJECTED, REPORT_FILES, run_info, sample};

/// Write the sample run for `transport` into `dir` and return its summary.
fn write_sample(dir: &Path, transport: Transport, port: u16) -> Summary {
    let info = run_info(transport, port);
    let mut reports = Reports::create(dir, &info).expect("create reports");
    for (case, result) in sample(transport) {
        reports.case(&case, &result).expect("write case");
    }
    let summary = reports.summary(false, Duration::from_millis(1234));
    reports.finish(&summary).expect("finish reports");
    summary
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lines of a JSON-lines file, each parsed; the file must end with a complete line.
fn json_lines(path: &Path) -> Vec<serde_json::Value> {
    let text = read(path);
    assert!(
        text.is_empty() || text.ends_with('\n'),
        "{}: the last line is cut short",
        path.display()
    );
    text.lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("line {l:?}: {e}")))
        .collect()
}

/// The case ids of the lines of a `cases.jsonl`, in order.
fn line_ids(path: &Path) -> Vec<String> {
    json_lines(path)
        .iter()
        .map(|l| l["result"]["id"].as_str().expect("id").to_string())
        .collect()
}

/// The names in `dir/cases/`, sorted.
fn case_file_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir.join("cases"))
        .expect("cases/")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn index_json_has_every_case_and_the_counts() {
    let dir = test_support::TempDir::new("tempdir");
    write_sample(dir.path(), Transport::Tcp, 502);
    let index: serde_json::Value =
        serde_json::from_str(&read(&dir.path().join("index.json"))).expect("index.json parses");
    assert_eq!(index["format"], "modbus-harness-report/3");
    assert_eq!(index["run"]["profile"], "mdrive");
    assert_eq!(index["run"]["transport"], "tcp");
    let cases = index["cases"].as_array().expect("cases array");
    assert_eq!(cases.len(), IDS.len());
    for (entry, id) in cases.iter().zip(IDS) {
        assert_eq!(entry["id"], id);
        // A case file is named for the cases that have one, those that ran and did not PASS; a SKIPPED
        // case's entry has its reason instead.
        if entry["verdict"] == "PASS" {
            assert!(entry.get("file").is_none(), "{entry}");
            assert!(entry.get("reason").is_none(), "{entry}");
            continue;
        }
        if entry["verdict"] == "SKIPPED" {
            assert!(entry.get("file").is_none(), "{entry}");
            assert!(
                entry["reason"].as_str().is_some_and(|r| !r.is_empty()),
                "{entry}"
            );
            continue;
        }
        let file = entry["file"].as_str().expect("file name");
        assert_eq!(file, format!("cases/{}", case_file_name(id)));
        let case: serde_json::Value =
            serde_json::from_str(&read(&dir.path().join(file))).expect("case file parses");
        assert_eq!(case["result"]["id"], id);
        assert_eq!(case["case"]["id"], id);
        assert!(case["case"]["requirement"].is_string());
        assert!(case["case"]["steps"].is_array());
    }
    assert_eq!(cases[1]["verdict"], "FAIL");
    assert_eq!(cases[4]["verdict_before_expectations"], "FAIL");
    let s = &index["summary"];
    assert_eq!(s["cases"], 6);
    assert_eq!(s["counts"]["PASS"], 2);
    assert_eq!(s["counts"]["FAIL"], 1);
    assert_eq!(s["counts"]["SKIPPED"], 1);
    assert_eq!(s["counts"]["NON-STRICT"], 1);
    assert_eq!(s["counts"]["INFORMATIONAL"], 1);
    assert_eq!(s["counts"]["UNIMPLEMENTED"], 0);
    assert_eq!(s["failing"], serde_json::json!([IDS[1]]));
    assert_eq!(s["interrupted"], false);
    assert_eq!(s["result"], "FAIL");
    // Nothing partial is left behind by a finished run.
    for entry in std::fs::read_dir(dir.path()).expect("list") {
        let name = entry
            .expect("entry")
            .file_name()
            .to_string_lossy()
            .into_owned();
        assert!(
            !name.ends_with(".partial") && !name.ends_with(".tmp"),
            "left over: {name}"
        );
    }
}

#[test]
fn cases_jsonl_has_every_case_and_cases_dir_the_failing_and_noted_ones() {
    let dir = test_support::TempDir::new("tempdir");
    write_sample(dir.path(), Transport::Tcp, 502);
    let sample = sample(Transport::Tcp);
    let lines = json_lines(&dir.path().join("cases.jsonl"));
    // One line per case, in run order, each the whole record: the case and its full result.
    assert_eq!(lines.len(), sample.len());
    let mut non_pass = Vec::new();
    for (line, (case, result)) in lines.iter().zip(&sample) {
        let want = serde_json::json!({ "case": case, "result": result });
        assert_eq!(line, &want, "the line of {}", result.id);
        if !matches!(result.verdict, Verdict::Pass | Verdict::Skipped) {
            // The case file holds the same record.
            let file = dir.path().join("cases").join(case_file_name(&result.id));
            let file: serde_json::Value =
                serde_json::from_str(&read(&file)).expect("case file parses");
            assert_eq!(file, want, "the case file of {}", result.id);
            non_pass.push(case_file_name(&result.id));
        }
    }
    // `cases/` holds exactly the cases that ran and did not PASS.
    non_pass.sort();
    assert_eq!(
        non_pass.len(),
        3,
        "the sample has 2 PASS, 1 SKIPPED and 3 others"
    );
    assert_eq!(case_file_names(dir.path()), non_pass);
}

/// Attributes of an XML start tag as (name, unescaped value).
fn attrs(e: &quick_xml::events::BytesStart) -> Vec<(String, String)> {
    e.attributes()
        .map(|a| {
            let a = a.expect("attribute");
            (
                String::from_utf8_lossy(a.key.as_ref()).into_owned(),
                a.normalized_value(quick_xml::XmlVersion::Implicit1_0)
                    .expect("attribute value")
                    .into_owned(),
            )
        })
        .collect()
}

fn attr(list: &[(String, String)], name: &str) -> Option<String> {
    list.iter().find(|(k, _)| k == name).map(|(_, v)| v.clone())
}

#[test]
fn junit_is_well_formed_with_one_failure_and_one_skip() {
    let dir = test_support::TempDir::new("tempdir");
    write_sample(dir.path(), Transport::RtuOverTcp, 15020);
    let xml = read(&dir.path().join("junit.xml"));
    let mut reader = quick_xml::Reader::from_str(&xml);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<String> = Vec::new();
    let mut suites = Vec::new();
    let mut testcases = Vec::new();
    let (mut failures, mut skipped) = (0, 0);
    let mut failure_text = String::new();
    let mut verdict_properties = Vec::new();
    let mut system_out = Vec::new();
    loop {
        let event = reader.read_event().expect("junit.xml is well-formed XML");
        match event {
            Event::Start(ref e) | Event::Empty(ref e) => {
                let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
                let a = attrs(e);
                match name.as_str() {
                    "testsuite" => suites.push(a.clone()),
                    "testcase" => testcases.push(a.clone()),
                    "failure" => failures += 1,
                    "skipped" => skipped += 1,
                    "properties" => assert_eq!(
                        stack.last().map(String::as_str),
                        Some("testsuite"),
                        "properties only at suite level"
                    ),
                    _ => {}
                }
                if matches!(event, Event::Start(_)) {
                    stack.push(name);
                }
            }
            Event::End(_) => {
                stack.pop();
            }
            Event::Text(t) => {
                let text = t.decode().expect("text").into_owned();
                let text = quick_xml::escape::unescape(&text)
                    .expect("unescape")
                    .into_owned();
                match stack.last().map(String::as_str) {
                    Some("failure") => failure_text.push_str(&text),
                    Some("system-out")
                        if stack.len() >= 2 && stack[stack.len() - 2] == "testcase" =>
                    {
                        if let Some(v) = text.strip_prefix("verdict: ") {
                            verdict_properties.push(v.lines().next().unwrap_or("").to_string());
                        }
                        system_out.push(text);
                    }
                    _ => {}
                }
            }
            Event::GeneralRef(r) => {
                // quick-xml 0.38+ reports entity references apart from the text around them.
                let name = String::from_utf8_lossy(&r).into_owned();
                let ch = match name.as_str() {
                    "lt" => "<",
                    "gt" => ">",
                    "amp" => "&",
                    "quot" => "\"",
                    "apos" => "'",
                    other => panic!("unexpected entity &{other};"),
                };
                match stack.last().map(String::as_str) {
                    Some("failure") => failure_text.push_str(ch),
                    Some("system-out") => {
                        if let Some(last) = system_out.last_mut() {
                            last.push_str(ch);
                        }
                    }
                    _ => {}
                }
            }
            Event::Eof => break,
            _ => {}
        }
    }
    assert!(stack.is_empty(), "unclosed elements: {stack:?}");
    assert_eq!(suites.len(), 1, "one testsuite");
    let suite = &suites[0];
    assert_eq!(attr(suite, "tests").as_deref(), Some("6"));
    assert_eq!(attr(suite, "failures").as_deref(), Some("1"));
    assert_eq!(attr(suite, "skipped").as_deref(), Some("1"));
    assert_eq!(attr(suite, "errors").as_deref(), Some("0"));
    assert_eq!((failures, skipped), (1, 1));
    assert_eq!(testcases.len(), 6);
    for (tc, id) in testcases.iter().zip(IDS) {
        let (class, name) = id.rsplit_once('/').expect("ids have a /");
        let class = class.replace('.', "_").replace('/', ".");
        assert_eq!(attr(tc, "classname").as_deref(), Some(class.as_str()));
        assert_eq!(attr(tc, "name").as_deref(), Some(name));
    }
    assert_eq!(
        verdict_properties,
        [
            "PASS",
            "FAIL",
            "SKIPPED",
            "PASS",
            "NON-STRICT",
            "INFORMATIONAL"
        ]
    );
    assert!(
        failure_text.contains(INJECTED),
        "failure body: {failure_text}"
    );
    assert!(xml.contains("&lt;script&gt;"), "markup is escaped");
    assert!(!xml.contains("<script>"), "no raw markup in the XML");
    assert!(!xml.contains('\u{7}'), "control characters are replaced");
}

#[test]
fn html_has_every_case_and_escapes_findings() {
    let dir = test_support::TempDir::new("tempdir");
    write_sample(dir.path(), Transport::Tcp, 502);
    let html = read(&dir.path().join("report.html"));
    assert!(html.starts_with("<!DOCTYPE html>"));
    assert!(html.trim_end().ends_with("</html>"));
    for id in IDS {
        assert!(html.contains(id), "{id} missing");
    }
    assert!(
        !html.contains("<script>alert(1)"),
        "finding injected markup"
    );
    assert!(html.contains("&lt;script&gt;alert(1)&lt;/script&gt; &amp; &quot;quoted&quot;"));
    // Self-contained: no external resources.
    for needle in ["src=\"http", "href=\"http", "<link ", "@import", "url("] {
        assert!(!html.contains(needle), "external resource: {needle}");
    }
    // Filter controls, one per verdict, with the counts.
    for v in Verdict::ALL {
        assert!(html.contains(&format!("data-verdict=\"{}\"", v.label())));
    }
    assert!(html.contains("malformed on purpose"));
    assert_eq!(html.matches("<details class=\"case").count(), 6);
}

/// A large run's page stays bounded: PASS rows stop at `HTML_PASS_ROWS` with a banner that counts the rest,
/// every other verdict is shown, and it comes before the PASS rows.
/// A run of `total` numbered PASS cases written to `dir`, every hundredth (n % 100 == 99) given `every_100th`.
fn write_numbered(dir: &Path, total: usize, every_100th: Verdict) {
    let mut reports = Reports::create(dir, &run_info(Transport::Tcp, 502)).expect("create");
    for n in 0..total {
        let (case, mut result) = test_support::reports::numbered_pass(Transport::Tcp, n);
        if n % 100 == 99 {
            result.verdict = every_100th;
        }
        reports.case(&case, &result).expect("write case");
    }
    let summary = reports.summary(false, Duration::from_secs(1));
    reports.finish(&summary).expect("finish");
}

#[test]
fn html_shows_every_failure_first_and_a_bounded_number_of_passes() {
    let dir = test_support::TempDir::new("tempdir");
    let extra = 250;
    let total = reports::HTML_PASS_ROWS + extra;
    write_numbered(dir.path(), total, Verdict::Fail);
    let html = read(&dir.path().join("report.html"));
    let fails = total / 100;
    let passes = html.matches("<details class=\"case v-PASS\"").count();
    assert_eq!(passes, reports::HTML_PASS_ROWS);
    assert_eq!(
        html.matches("<details class=\"case v-FAIL\"").count(),
        fails
    );
    let banner = format!("{} more PASS case(s) are not shown", total - fails - passes);
    assert!(html.contains(&banner), "no banner {banner:?}");
    let last_fail = html.rfind("v-FAIL\"").expect("a FAIL row");
    let first_pass = html
        .find("<details class=\"case v-PASS\"")
        .expect("a PASS row");
    assert!(last_fail < first_pass, "a FAIL row after a PASS row");
}

/// A long run's JUnit file: the first PASS cases have their steps and wire log in `<system-out>`, the later
/// PASS cases their verdict and id and where the rest is; every other case has everything, however late.
#[test]
fn junit_gives_the_wire_of_a_bounded_number_of_passes_and_of_every_other_case() {
    let dir = test_support::TempDir::new("tempdir");
    let total = reports::JUNIT_PASS_IN_FULL + 300;
    write_numbered(dir.path(), total, Verdict::NonStrict);
    let xml = read(&dir.path().join("junit.xml"));
    let outs: Vec<&str> = xml
        .split("<system-out>")
        .skip(1)
        .map(|s| s.split("</system-out>").next().expect("closed"))
        .filter(|s| s.starts_with("verdict: "))
        .collect();
    assert_eq!(outs.len(), total, "one <system-out> per case");
    let (mut passes, mut brief) = (0, 0);
    for (n, out) in outs.iter().enumerate() {
        let wire = out.contains("wire log:") && out.contains("step 1:");
        if out.starts_with("verdict: PASS") {
            passes += 1;
            if passes <= reports::JUNIT_PASS_IN_FULL {
                assert!(wire, "PASS case {n} within the first ones: {out}");
            } else {
                assert!(!wire, "PASS case {n} past the first ones: {out}");
                assert!(
                    out.contains("cases.jsonl") && out.contains("session.pcapng"),
                    "{out}"
                );
                brief += 1;
            }
        } else {
            assert!(wire, "case {n}, not PASS: {out}");
        }
    }
    assert_eq!(brief, passes - reports::JUNIT_PASS_IN_FULL);
    assert!(brief > 250, "{brief}");
    // The NON-STRICT cases past the first PASS ones still have everything.
    assert!(
        outs.last()
            .is_some_and(|o| o.starts_with("verdict: NON-STRICT"))
    );
}

#[test]
fn terminal_summary_ends_with_the_result_line() {
    let dir = test_support::TempDir::new("tempdir");
    let summary = write_sample(dir.path(), Transport::Tcp, 502);
    let mut info = run_info(Transport::Tcp, 502);
    info.report_dir = Some(dir.path().to_path_buf());
    let text = terminal_summary(&summary, &info);
    assert!(text.contains(IDS[1]));
    assert!(text.contains(&dir.path().display().to_string()));
    assert_eq!(
        text.lines().last(),
        Some("RESULT: FAIL (1 FAIL, 2 PASS, 1 NON-STRICT, 1 INFORMATIONAL, 1 SKIPPED)")
    );
}

#[test]
fn terminal_summary_caps_failing_ids() {
    let mut tally = Tally::new();
    let (_, mut result) = test_support::reports::numbered_pass(Transport::Tcp, 0);
    result.verdict = Verdict::Fail;
    for n in 0..500 {
        result.id = format!("x/fail-{n}");
        tally.record(&result);
    }
    let summary = tally.summary(true, Duration::from_secs(1));
    assert_eq!(summary.failing.len(), FAILING_CAP);
    assert_eq!(summary.failing_omitted(), 500 - FAILING_CAP);
    let text = terminal_summary(&summary, &run_info(Transport::Tcp, 502));
    assert!(text.contains("x/fail-49\n"));
    assert!(!text.contains("x/fail-50\n"));
    assert!(text.contains("... and 450 more"));
    assert_eq!(
        text.lines().last(),
        Some("RESULT: FAIL (500 FAIL; interrupted)")
    );
}

#[test]
fn interrupted_and_killed_runs() {
    let info = run_info(Transport::Tcp, 502);
    let cases = sample(Transport::Tcp);

    // Killed: no finish. Only .partial files, the index prefix has one complete entry per line.
    let dir = test_support::TempDir::new("tempdir");
    let mut reports = Reports::create(dir.path(), &info).expect("create");
    for (case, result) in &cases[..3] {
        reports.case(case, result).expect("case");
    }
    reports.flush().expect("flush");
    // Flushed, before the writer is gone: every case handed over is a complete line.
    assert_eq!(line_ids(&dir.path().join("cases.jsonl.partial")), IDS[..3]);
    drop(reports);
    assert_eq!(line_ids(&dir.path().join("cases.jsonl.partial")), IDS[..3]);
    for name in REPORT_FILES {
        assert!(!dir.path().join(name).exists(), "{name} must not exist");
        assert!(dir.path().join(format!("{name}.partial")).exists());
    }
    let partial = read(&dir.path().join("index.json.partial"));
    let entries: Vec<serde_json::Value> = partial
        .lines()
        .skip_while(|l| !l.starts_with("\"cases\":["))
        .skip(1)
        .map(|l| serde_json::from_str(l.trim_end_matches(',')).expect("entry line parses"))
        .collect();
    assert_eq!(entries.len(), 3);
    assert_eq!(entries[2]["id"], IDS[2]);

    // Interrupted: finish with interrupted = true completes every file.
    let mut reports = Reports::create(dir.path(), &info).expect("create again");
    assert!(
        !dir.path().join("index.json.partial").exists() || {
            // The new run's own partial index holds no case yet.
            read(&dir.path().join("index.json.partial")).lines().count() <= 3
        }
    );
    for (case, result) in &cases[..2] {
        reports.case(case, result).expect("case");
    }
    let summary = reports.summary(true, Duration::from_millis(5));
    reports.finish(&summary).expect("finish");
    let index: serde_json::Value =
        serde_json::from_str(&read(&dir.path().join("index.json"))).expect("index parses");
    assert_eq!(index["summary"]["interrupted"], true);
    assert_eq!(index["cases"].as_array().map(Vec::len), Some(2));
    assert!(read(&dir.path().join("report.html")).contains("interrupted"));
    // The interrupted run's cases.jsonl is complete: a line for each case that ran, nothing of the killed run.
    assert_eq!(line_ids(&dir.path().join("cases.jsonl")), IDS[..2]);
    assert!(!dir.path().join("cases.jsonl.partial").exists());
    // Case files of the killed run (IDS[1] and IDS[2]) were removed when the new run started: only the
    // FAIL of the two cases that ran has one.
    assert_eq!(case_file_names(dir.path()), [case_file_name(IDS[1])]);
}

#[test]
fn an_error_of_the_writer_thread_is_returned_and_finish_joins_it() {
    // The case file of a FAIL cannot be written once `cases/` is gone: the writer thread stops at the first
    // error, and a later `case`, `flush` or `finish` returns it, naming the file.
    let dir = test_support::TempDir::new("tempdir");
    let info = run_info(Transport::Tcp, 502);
    let mut reports = Reports::create(dir.path(), &info).expect("create");
    std::fs::remove_dir_all(dir.path().join("cases")).expect("remove cases/");
    let (case, mut result) = test_support::reports::numbered_pass(Transport::Tcp, 1);
    result.verdict = Verdict::Fail;
    let mut err = None;
    for _ in 0..100 {
        if let Err(e) = reports.case(&case, &result) {
            err = Some(e);
            break;
        }
    }
    let err = match err {
        Some(e) => e,
        None => reports
            .flush()
            .expect_err("flush returns the writer's error"),
    };
    assert!(err.to_string().contains("cannot write"), "{err}");
    // Every later call returns it too, and finish does not hang.
    assert!(reports.flush().is_err());
    let summary = reports.summary(false, Duration::ZERO);
    assert!(reports.finish(&summary).is_err());
    // What the stopped writer had taken is in the files, whole lines only.
    let lines = json_lines(&dir.path().join("cases.jsonl.partial"));
    assert!(!lines.is_empty());
    assert!(
        lines
            .iter()
            .all(|l| l["result"]["id"] == result.id.as_str())
    );
}

#[test]
fn io_errors_name_the_file() {
    let dir = test_support::TempDir::new("tempdir");
    let blocker = dir.path().join("not-a-dir");
    std::fs::write(&blocker, b"x").expect("write");
    let err = match Reports::create(&blocker.join("out"), &run_info(Transport::Tcp, 502)) {
        Err(e) => e,
        Ok(_) => panic!("a report dir under a file cannot be created"),
    };
    assert!(err.to_string().contains("not-a-dir"), "{err}");
}

// ---- pcapng through tshark ----

fn tshark_available() -> bool {
    match Command::new("tshark").arg("--version").output() {
        Ok(o) if o.status.success() => true,
        _ => {
            eprintln!(
                "tshark is not installed: skipping the pcapng decode check (apt-get install -y tshark)"
            );
            false
        }
    }
}

/// tshark fields, one line per packet, tab-separated.
fn tshark(pcap: &Path, decode: &[String], filter: &str, fields: &[&str]) -> Vec<Vec<String>> {
    let mut cmd = Command::new("tshark");
    cmd.arg("-r")
        .arg(pcap)
        .args(decode)
        .args(["-Y", filter, "-T", "fields"]);
    for f in fields {
        cmd.args(["-e", f]);
    }
    cmd.args(["-E", "separator=\t"]);
    let out = cmd.output().expect("run tshark");
    assert!(
        out.status.success(),
        "tshark failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.split('\t').map(str::to_string).collect())
        .collect()
}

fn check_pcap(transport: Transport, port: u16) {
    if !tshark_available() {
        return;
    }
    let dir = test_support::TempDir::new("tempdir");
    write_sample(dir.path(), transport, port);
    let info = run_info(transport, port);
    let pcap = dir.path().join("session.pcapng");
    let decode = pcap_decode_args(&info);
    let modbus = match transport {
        Transport::Tcp => "mbtcp",
        Transport::Rtu | Transport::RtuOverTcp => "mbrtu",
    };

    // Every packet is there: 5 cases with traffic, 3 handshake + 3 closing packets each, 9 payload packets.
    let all = tshark(&pcap, &decode, "frame", &["frame.number"]);
    assert_eq!(all.len(), 5 * 6 + 9, "packet count");

    // Every payload is decoded as Modbus, except packets the harness commented on.
    let undecoded = tshark(
        &pcap,
        &decode,
        &format!("tcp.len > 0 && !{modbus}"),
        &["frame.number", "frame.comment"],
    );
    for row in &undecoded {
        assert!(
            row.get(1).is_some_and(|c| !c.is_empty()),
            "packet {} is not decoded as {modbus} and has no comment",
            row[0]
        );
    }
    let decoded = tshark(&pcap, &decode, modbus, &["frame.number"]);
    // At most the two frames broken on purpose or by the target stay undecoded.
    assert!(
        decoded.len() + undecoded.len() == 9 && decoded.len() >= 7,
        "decoded {}",
        decoded.len()
    );

    // No malformed Modbus frame but those with a comment (the intended one and the FAIL's bad answer).
    let malformed = tshark(
        &pcap,
        &decode,
        &format!("{modbus} && (_ws.malformed || _ws.expert.severity >= warning)"),
        &["frame.number", "frame.comment"],
    );
    for row in &malformed {
        assert!(
            row.get(1).is_some_and(|c| !c.is_empty()),
            "packet {} is malformed Modbus without a comment",
            row[0]
        );
    }
    let on_purpose = tshark(
        &pcap,
        &decode,
        "frame.comment contains \"malformed on purpose\"",
        &["frame.comment"],
    );
    assert_eq!(on_purpose.len(), 1);
    assert!(on_purpose[0][0].contains(&format!("malformed on purpose: {}", IDS[3])));

    // The synthetic TCP is coherent: no analysis complaint (lost segments, unseen ACKs, retransmissions).
    let tcp_problems = tshark(
        &pcap,
        &decode,
        "tcp.analysis.flags && !tcp.analysis.window_update",
        &["frame.number", "_ws.col.Info"],
    );
    assert!(tcp_problems.is_empty(), "TCP analysis: {tcp_problems:?}");
    let handshakes = tshark(
        &pcap,
        &decode,
        "tcp.flags.syn == 1 && tcp.flags.ack == 0",
        &["tcp.srcport", "tcp.dstport"],
    );
    assert_eq!(handshakes.len(), 5);
    for row in &handshakes {
        assert!(row[0].parse::<u16>().is_ok_and(|p| p >= 40_000));
        assert_eq!(row[1], reports::pcap_server_port(&info).to_string());
    }

    // Timestamps: run start + event time (the first request is at +10 ms).
    let first = tshark(&pcap, &decode, "tcp.len > 0", &["frame.time_epoch"]);
    let t: f64 = first[0][0].parse().expect("time");
    let want = info.started_unix_ms as f64 / 1000.0 + 0.010;
    assert!((t - want).abs() < 1e-5, "first payload at {t}, want {want}");
}

#[test]
fn pcap_decodes_as_modbus_tcp() {
    check_pcap(Transport::Tcp, 502);
}

#[test]
fn pcap_decodes_as_modbus_tcp_on_another_port() {
    check_pcap(Transport::Tcp, 45_678);
}

#[test]
fn pcap_decodes_as_modbus_rtu_over_tcp() {
    check_pcap(Transport::RtuOverTcp, 15_020);
}

#[test]
fn pcap_decodes_serial_rtu() {
    check_pcap(Transport::Rtu, 0);
}

#[test]
fn case_file_names_are_readable_and_distinct() {
    assert_eq!(
        case_file_name("golden/sd2x/3.2-read"),
        "golden__sd2x__3.2-read.json"
    );
    let names = ["a/b", "a__b", "a b", "a_b", "../x", ".x", ""].map(case_file_name);
    for (i, a) in names.iter().enumerate() {
        assert!(!a.starts_with('.'), "{a} is hidden");
        assert!(!a.contains('/'), "{a}");
        for b in &names[i + 1..] {
            assert_ne!(a, b);
        }
    }
    assert!(case_file_name(&"x".repeat(500)).len() < 160);
}

#[test]
fn iso_dates() {
    assert_eq!(reports::iso8601_utc(0), "1970-01-01T00:00:00.000Z");
    assert_eq!(
        reports::iso8601_utc(951_782_400_000),
        "2000-02-29T00:00:00.000Z"
    );
    assert_eq!(
        reports::iso8601_utc(1_795_315_813_123),
        "2026-11-22T02:50:13.123Z"
    );
}

#[test]
fn pcap_reassembles_a_response_read_in_pieces() {
    if !tshark_available() {
        return;
    }
    let transport = Transport::RtuOverTcp;
    let (case, mut result) = test_support::reports::numbered_pass(transport, 1);
    let rx = result.wire.pop().expect("response event");
    let (a, b) = rx.bytes.split_at(3);
    for (k, part) in [a, b].into_iter().enumerate() {
        result.wire.push(engine::WireEvent {
            bytes: part.to_vec(),
            at: rx.at + Duration::from_micros(400 * k as u64),
            ..rx.clone()
        });
    }
    let dir = test_support::TempDir::new("tempdir");
    let info = run_info(transport, 15_020);
    let mut reports = Reports::create(dir.path(), &info).expect("create");
    reports.case(&case, &result).expect("case");
    let summary = reports.summary(false, Duration::ZERO);
    reports.finish(&summary).expect("finish");
    let pcap = dir.path().join("session.pcapng");
    let decode = pcap_decode_args(&info);
    let responses = tshark(
        &pcap,
        &decode,
        "mbrtu && tcp.srcport == 15020",
        &["frame.number"],
    );
    assert_eq!(responses.len(), 1, "one reassembled response");
    let bad = tshark(
        &pcap,
        &decode,
        "_ws.malformed || _ws.expert.severity >= warning",
        &["frame.number"],
    );
    assert!(bad.is_empty(), "malformed: {bad:?}");
    // Only the case label: the two reads are one segment and the codec check sees them together.
    let comments = tshark(&pcap, &decode, "frame.comment", &["frame.comment"]);
    assert_eq!(comments.len(), 1, "{comments:?}");
    assert!(comments[0][0].starts_with("case bulk/pass/"));
}

#[test]
fn reports_can_move_to_another_thread() {
    fn send<T: Send>() {}
    send::<Reports>();
}
