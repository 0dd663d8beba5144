//! `report.html`: one self-contained page (inline CSS and JS), case rows streamed to `report.html.partial`
//! (every verdict but PASS) and `report.html.pass.partial` (PASS), put together at `finish` as header (run
//! info, counts, verdict filter), the rows that need a look first (FAIL and the others, in run order), the
//! PASS rows, and the footer (script).
//!
//! A page with a million cases is of no use in a browser: each verdict shows at most
//! [`HTML_ROWS_PER_VERDICT`] cases in full ([`HTML_PASS_ROWS`] PASS cases); the page says how many more there are, and `index.json` and
//! `cases.jsonl` hold them all (`cases/` those that ran and did not PASS).

use std::fmt::Write as _;
use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use super::{
    CASE_LINES_FILE, CASES_DIR, HTML_FILE, INDEX_FILE, RunInfo, STREAM_BUFFER, Sink, Stream,
    Summary, dir_label, iso8601_utc, promote, with_path,
};
use crate::targets::Received;
use crate::{Case, CaseResult, Dir, StepResult, Verdict};
use codec::hex_spaced;

/// The most cases of one verdict that the page shows in full.
pub const HTML_ROWS_PER_VERDICT: usize = 20_000;

/// The most PASS cases the page shows in full: they are what nobody opens, and a large generated run is
/// mostly them (20,000 PASS rows are some 40 MB of page). `cases.jsonl` has every one.
pub const HTML_PASS_ROWS: usize = 2_000;

/// The most cases of verdict `v` the page shows in full.
fn rows_shown(v: Verdict) -> usize {
    if v == Verdict::Pass {
        HTML_PASS_ROWS
    } else {
        HTML_ROWS_PER_VERDICT
    }
}

/// Writes `report.html`.
pub struct HtmlSink {
    dir: PathBuf,
    /// The case rows that need a look (every verdict but PASS), `report.html.partial`.
    rows: Stream,
    /// The PASS rows, which go after all others, `report.html.pass.partial`.
    passes: Stream,
    info: RunInfo,
    shown: [usize; 6],
    omitted: [usize; 6],
}

impl HtmlSink {
    /// Start `report.html.partial` in `dir`.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        Ok(Self {
            dir: dir.to_path_buf(),
            rows: Stream::create(dir, HTML_FILE)?,
            passes: Stream::create(dir, &format!("{HTML_FILE}.pass"))?,
            info: info.clone(),
            shown: [0; 6],
            omitted: [0; 6],
        })
    }

    fn assemble(&self, summary: &Summary) -> io::Result<()> {
        let tmp = self.dir.join(format!("{HTML_FILE}.tmp"));
        let file = File::create(&tmp).map_err(with_path("cannot create", &tmp))?;
        let mut out = BufWriter::with_capacity(STREAM_BUFFER, file);
        let write = |out: &mut BufWriter<File>| -> io::Result<()> {
            out.write_all(header(&self.info, summary).as_bytes())?;
            io::copy(&mut File::open(self.rows.partial())?, out)?;
            io::copy(&mut File::open(self.passes.partial())?, out)?;
            out.write_all(footer(&self.omitted).as_bytes())?;
            out.flush()
        };
        write(&mut out).map_err(with_path("cannot write", &tmp))?;
        drop(out);
        promote(&tmp, &self.dir.join(HTML_FILE))?;
        for partial in [self.passes.partial(), self.rows.partial()] {
            fs::remove_file(partial).map_err(with_path("cannot remove", partial))?;
        }
        Ok(())
    }
}

impl Sink for HtmlSink {
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        let v = verdict_index(result.verdict);
        if self.shown[v] >= rows_shown(result.verdict) {
            self.omitted[v] += 1;
            return Ok(());
        }
        self.shown[v] += 1;
        let row = case_row(case, result);
        let rows = if result.verdict == Verdict::Pass {
            &mut self.passes
        } else {
            &mut self.rows
        };
        rows.write(|out| out.write_all(row.as_bytes()))
    }

    fn flush(&mut self) -> io::Result<()> {
        self.passes.flush()?;
        self.rows.flush()
    }

    fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        self.passes.close()?;
        self.rows.close()?;
        self.assemble(summary)
    }
}

fn verdict_index(v: Verdict) -> usize {
    Verdict::ALL.iter().position(|x| *x == v).unwrap_or(0)
}

/// HTML-escape text for element content and quoted attribute values; control characters become U+FFFD.
pub fn escape_html(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c if c.is_control() && !matches!(c, '\n' | '\t') => out.push('\u{FFFD}'),
            c => out.push(c),
        }
    }
    out
}

fn badge(v: Verdict) -> String {
    format!("<span class=\"badge v-{0}\">{0}</span>", v.label())
}

/// Observed bytes with the bytes that differ from `expected` (by position) marked.
fn diff_hex(observed: &[u8], expected: Option<&[u8]>) -> String {
    let Some(expected) = expected else {
        return hex_spaced(observed);
    };
    let mut s = String::with_capacity(observed.len() * 3 + 16);
    for (i, b) in observed.iter().enumerate() {
        if i > 0 {
            s.push(' ');
        }
        if expected.get(i) == Some(b) {
            let _ = write!(s, "{b:02X}");
        } else {
            let _ = write!(s, "<mark>{b:02X}</mark>");
        }
    }
    s
}

fn observed_html(o: &Received, expected: Option<&[u8]>) -> String {
    match o {
        Received::Frame { bytes, .. } => format!("<code>{}</code>", diff_hex(bytes, expected)),
        Received::Silence { .. } => "<i>silence</i>".to_string(),
        Received::Closed { .. } => "<i>connection closed</i>".to_string(),
        Received::Garbage { bytes, reason, .. } => format!(
            "<i>garbage ({})</i> <code>{}</code>",
            escape_html(reason),
            hex_spaced(bytes)
        ),
    }
}

fn step_row(i: usize, step: &StepResult) -> String {
    let mut s = String::new();
    let _ = write!(
        s,
        "<tr><td class=\"num\">{}</td><td>{}</td><td>{}</td><td>",
        i + 1,
        escape_html(&step.note),
        badge(step.verdict)
    );
    if let Some(sent) = &step.sent {
        let _ = write!(
            s,
            "<div><b>sent</b> <code>{}</code></div>",
            hex_spaced(sent)
        );
    }
    if step.sent.is_some() || step.expected.is_some() {
        let expected = step.expected.as_deref().map_or_else(
            || "<i>silence</i>".to_string(),
            |b| format!("<code>{}</code>", hex_spaced(b)),
        );
        let _ = write!(s, "<div><b>expected</b> {expected}</div>");
    }
    for o in &step.observed {
        let _ = write!(
            s,
            "<div><b>observed</b> {}</div>",
            observed_html(o, step.expected.as_deref())
        );
    }
    s.push_str("</td><td>");
    if !step.findings.is_empty() {
        s.push_str("<ul>");
        for f in &step.findings {
            let _ = write!(s, "<li>{}</li>", escape_html(f));
        }
        s.push_str("</ul>");
    }
    s.push_str("</td></tr>\n");
    s
}

/// One `<details>` element per case.
fn case_row(case: &Case, result: &CaseResult) -> String {
    let v = result.verdict.label();
    let mut s = String::with_capacity(2048);
    let _ = write!(
        s,
        "<details class=\"case v-{v}\" data-id=\"{id}\"{open}>\n<summary>{badge} <code class=\"id\">{id}</code> <span class=\"title\">{title}</span></summary>\n<div class=\"body\">\n<dl>",
        id = escape_html(&result.id),
        open = if result.verdict == Verdict::Fail {
            " open"
        } else {
            ""
        },
        badge = badge(result.verdict),
        title = escape_html(&case.title),
    );
    let tags: Vec<String> = case
        .tags
        .iter()
        .map(|t| format!("{t:?}").to_lowercase())
        .collect();
    let mut item = |name: &str, value: &str| {
        let _ = write!(s, "<dt>{name}</dt><dd>{}</dd>", escape_html(value));
    };
    item("Requirement", &case.requirement);
    item("Reference", &case.reference);
    item("Level", &format!("{:?}", case.level).to_uppercase());
    if !tags.is_empty() {
        item("Tags", &tags.join(", "));
    }
    item("Duration", &format!("{} µs", result.duration.as_micros()));
    if let Some(reason) = &result.reason {
        item("Reason", reason);
    }
    if let Some((was, why)) = &result.expected_deviation {
        item(
            "Expectations",
            &format!(
                "{was} turned into {} by the expectations file: {why}",
                result.verdict
            ),
        );
    }
    s.push_str("</dl>\n");
    if !result.steps.is_empty() {
        s.push_str("<table class=\"steps\"><tr><th>#</th><th>Step</th><th>Verdict</th><th>Sent, expected, observed (bytes differing from the expected ones marked)</th><th>Findings</th></tr>\n");
        for (i, step) in result.steps.iter().enumerate() {
            s.push_str(&step_row(i, step));
        }
        s.push_str("</table>\n");
    }
    if !result.wire.is_empty() {
        s.push_str(
            "<table class=\"wire\"><tr><th>Dir</th><th>At (µs)</th><th>Bytes</th><th></th></tr>\n",
        );
        for e in &result.wire {
            let class = match (e.dir, e.intended_malformed) {
                (Dir::Tx, true) => "tx malformed",
                (Dir::Tx, false) => "tx",
                (Dir::Rx, _) => "rx",
            };
            let _ = writeln!(
                s,
                "<tr class=\"{class}\"><td>{}</td><td class=\"num\">{}</td><td><code>{}</code></td><td>{}</td></tr>",
                dir_label(e.dir),
                e.at.as_micros(),
                hex_spaced(&e.bytes),
                if e.intended_malformed {
                    "<span class=\"mal\" title=\"sent malformed on purpose\">⚠ malformed on purpose</span>"
                } else {
                    ""
                }
            );
        }
        s.push_str("</table>\n");
    }
    s.push_str("</div>\n</details>\n");
    s
}

const STYLE: &str = r#"
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;margin:0 1.5em 2em;color:#222;background:#fafafa}
h1{font-size:1.4em;margin:.8em 0 .4em}
table{border-collapse:collapse}
td,th{border:1px solid #ddd;padding:.2em .5em;text-align:left;vertical-align:top}
th{background:#f0f0f0}
code{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-size:.9em;word-break:break-all}
.run td:first-child{font-weight:600;white-space:nowrap}
.badge{display:inline-block;min-width:8em;text-align:center;border-radius:3px;padding:0 .4em;font-size:.85em;font-weight:600;color:#fff}
.v-PASS.badge{background:#2e7d32}.v-NON-STRICT.badge{background:#ef6c00}.v-INFORMATIONAL.badge{background:#1565c0}
.v-FAIL.badge{background:#c62828}.v-UNIMPLEMENTED.badge{background:#6a1b9a}.v-SKIPPED.badge{background:#757575}
#controls{position:sticky;top:0;background:#fafafa;padding:.5em 0;border-bottom:1px solid #ddd;z-index:1}
#controls label{margin-right:1em;white-space:nowrap}
#controls input[type=search]{width:20em}
.banner{background:#fff3e0;border:1px solid #ef6c00;padding:.4em .8em;margin:.5em 0}
details.case{background:#fff;border:1px solid #ddd;border-radius:3px;margin:.3em 0}
details.case>summary{cursor:pointer;padding:.3em .5em}
details.case .title{color:#555}
details.case .body{padding:.2em 1em 1em}
dl{display:grid;grid-template-columns:max-content auto;gap:.1em 1em;margin:.5em 0}
dt{font-weight:600}dd{margin:0}
table.steps,table.wire{margin:.5em 0;width:100%}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.rx td{background:#f3f8ff}
tr.malformed td{background:#fff0f0}
.mal{color:#c62828;font-weight:600}
mark{background:#ffcdd2}
.nomatch{display:none}
.hide-PASS .v-PASS.case,.hide-NON-STRICT .v-NON-STRICT.case,.hide-INFORMATIONAL .v-INFORMATIONAL.case,
.hide-FAIL .v-FAIL.case,.hide-UNIMPLEMENTED .v-UNIMPLEMENTED.case,.hide-SKIPPED .v-SKIPPED.case{display:none}
"#;

const SCRIPT: &str = r#"
(function () {
  var boxes = document.querySelectorAll('#controls input[data-verdict]');
  function applyVerdicts() {
    boxes.forEach(function (b) {
      document.body.classList.toggle('hide-' + b.getAttribute('data-verdict'), !b.checked);
    });
  }
  boxes.forEach(function (b) { b.addEventListener('change', applyVerdicts); });
  var search = document.getElementById('search');
  search.addEventListener('input', function () {
    var q = search.value.toLowerCase();
    document.querySelectorAll('details.case').forEach(function (d) {
      var text = d.querySelector('summary').textContent.toLowerCase();
      d.classList.toggle('nomatch', q !== '' && text.indexOf(q) < 0);
    });
  });
  function setOpen(open) {
    document.querySelectorAll('details.case').forEach(function (d) { d.open = open; });
  }
  document.getElementById('expand').addEventListener('click', function () { setOpen(true); });
  document.getElementById('collapse').addEventListener('click', function () { setOpen(false); });
  applyVerdicts();
})();
"#;

fn header(info: &RunInfo, summary: &Summary) -> String {
    let mut s = String::with_capacity(8192);
    let title = format!(
        "modbus-harness: {} on {} — {}",
        info.profile,
        info.target,
        summary.result_label()
    );
    let _ = write!(
        s,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{t}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>{t}</h1>\n",
        t = escape_html(&title)
    );
    if summary.interrupted {
        let _ = writeln!(
            s,
            "<p class=\"banner\">The run was interrupted after {} case(s): this report is incomplete.</p>",
            summary.cases
        );
    }
    // An interrupted run has its banner above.
    if let Some(e) = summary.ended.as_ref().filter(|_| !summary.interrupted) {
        let _ = writeln!(
            s,
            "<p class=\"banner\">The run ended after {} case(s): {}</p>",
            summary.cases,
            escape_html(e)
        );
    }
    for l in summary.liveness.iter().chain(&summary.link) {
        let _ = writeln!(s, "<p class=\"banner\">{}</p>", escape_html(l));
    }
    s.push_str("<table class=\"run\">\n");
    let seed = info
        .seed
        .map_or_else(|| "none".to_string(), |x| x.to_string());
    let rows: [(&str, String); 10] = [
        (
            "Result",
            format!("{} ({})", summary.result_label(), summary.counts_line()),
        ),
        ("Target", info.target.clone()),
        ("Profile", info.profile.clone()),
        ("Transport", info.transport.label().to_string()),
        ("Server port", info.server_port.to_string()),
        ("Started (UTC)", iso8601_utc(info.started_unix_ms)),
        (
            "Duration",
            format!("{:.3} s", summary.duration.as_secs_f64()),
        ),
        ("Command line", info.command_line.clone()),
        ("Seed", seed),
        ("Harness version", info.harness_version.clone()),
    ];
    for (name, value) in rows {
        let _ = writeln!(
            s,
            "<tr><td>{name}</td><td>{}</td></tr>",
            escape_html(&value)
        );
    }
    s.push_str("</table>\n<div id=\"controls\">\n");
    for v in Verdict::ALL {
        let _ = writeln!(
            s,
            "<label><input type=\"checkbox\" data-verdict=\"{l}\" checked> {b} {n}</label>",
            l = v.label(),
            b = badge(v),
            n = summary.count(v)
        );
    }
    s.push_str("<br><input type=\"search\" id=\"search\" placeholder=\"filter by id or title\"> <button id=\"expand\" type=\"button\">expand all</button> <button id=\"collapse\" type=\"button\">collapse all</button>\n</div>\n<main>\n");
    s
}

fn footer(omitted: &[usize; 6]) -> String {
    let mut s = String::from("</main>\n");
    for (v, n) in Verdict::ALL.iter().zip(omitted) {
        if *n > 0 {
            let _ = writeln!(
                s,
                "<p class=\"banner\">{n} more {v} case(s) are not shown (at most {} of them); {INDEX_FILE} and {CASE_LINES_FILE} have every case, {CASES_DIR}/ those that ran and did not PASS.</p>",
                rows_shown(*v)
            );
        }
    }
    let _ = write!(s, "<script>{SCRIPT}</script>\n</body>\n</html>\n");
    s
}
