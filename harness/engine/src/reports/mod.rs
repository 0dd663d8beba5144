//! Run reports, written as the run goes: JSON index, every case's record in one JSON-lines file (and a file of
//! its own for each case that did not PASS), JUnit XML, a self-contained HTML page, a pcapng of the session,
//! and the terminal summary printed last.
//!
//! Memory does not grow with the number of cases: every case is written out when it completes (on the
//! `report-writer` thread, at most a few batches behind the run), and only counters and a capped list of
//! failing ids are kept.
//!
//! # Files in the report directory
//!
//! | file | content |
//! |---|---|
//! | `index.json` | run info, one entry per case (id, title, verdict, reference, case file if any), the summary |
//! | `cases.jsonl` | every case, one line each in run order: `{"case":…,"result":…}`, the case (requirement, reference, level, tags, steps) and its full [`CaseResult`] |
//! | `cases/<name>.json` | the same record, pretty-printed, for each case whose verdict is not PASS (what one opens to debug a failure) |
//! | `junit.xml` | one `<testsuite>`, one `<testcase>` per case |
//! | `report.html` | one self-contained page (inline CSS and JS), filterable by verdict |
//! | `session.pcapng` | every [`WireEvent`] on a synthetic TCP connection per case (see [`pcap_decode_args`]) |
//!
//! # Interrupted runs
//!
//! While the run goes, the streamed files carry a `.partial` suffix: `index.json.partial` (a prefix of
//! `index.json`, one case entry per line), `cases.jsonl.partial` (whole lines up to the last flush),
//! `session.pcapng.partial` (readable by Wireshark up to the last complete packet), `junit.xml.partial` and
//! `report.html.partial` (the `<testcase>` elements and the HTML case rows, without header and footer).
//! [`Reports::finish`] (also called with `interrupted = true` when a run is stopped) completes each file and
//! renames it to its final name, so a file without a suffix is always complete. A process that is killed
//! leaves the `.partial` files (and at worst a `.tmp` file of an assembly cut short), never a truncated
//! `index.json`, `cases.jsonl`, `junit.xml`, `report.html` or `session.pcapng`.
//! Case files in `cases/` are each complete when their entry appears in the index. A run that ends early
//! (an error, Ctrl-C, a target that stopped answering) is finished like any other: its `cases.jsonl` has
//! one complete line per case that ran.

mod html;
mod json;
mod junit;
mod pcap;
pub mod snapshot;
mod writer;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::{self, File};
use std::io::{self, BufWriter, Write as _};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Serialize;

pub use drives::profile::Transport;

use crate::targets::Received;
use crate::{Case, CaseResult, Dir, Verdict, WireEvent};
use codec::hex_spaced;

pub use html::{HTML_PASS_ROWS, HTML_ROWS_PER_VERDICT, HtmlSink, escape_html};
pub use json::{INDEX_FORMAT, JsonSink};
pub use junit::{JunitSink, PASS_IN_FULL as JUNIT_PASS_IN_FULL, junit_names};
pub use pcap::{CLIENT_PORT_BASE, CLIENT_PORTS, PcapSink};

/// The run index.
pub const INDEX_FILE: &str = "index.json";
/// Every case's full record, one JSON object per line, in run order.
pub const CASE_LINES_FILE: &str = "cases.jsonl";
/// The folder of the case files of the cases whose verdict is not PASS.
pub const CASES_DIR: &str = "cases";
/// The JUnit XML file.
pub const JUNIT_FILE: &str = "junit.xml";
/// The HTML page.
pub const HTML_FILE: &str = "report.html";
/// The pcapng capture.
pub const PCAP_FILE: &str = "session.pcapng";
/// The buffer of each streamed file: a write system call per 64 KiB, not per case (a case's records in all
/// formats are a few KiB).
pub(crate) const STREAM_BUFFER: usize = 64 * 1024;
/// Suffix of a streamed file whose run has not finished.
pub const PARTIAL_SUFFIX: &str = ".partial";

/// How many FAIL case ids a [`Summary`] built by [`Tally`] keeps; the rest are only counted.
pub const FAILING_CAP: usize = 100;
/// How many FAIL case ids the terminal summary prints.
pub const TERMINAL_FAILING_CAP: usize = 50;
/// The TCP port the pcap uses when the run has none (serial RTU): no Wireshark dissector claims it.
pub const PCAP_SERIAL_PORT: u16 = 5020;

/// What was run, against what, by whom: the header of every report.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct RunInfo {
    /// The target as the user wrote it (`tcp://…`, `rtu://…`, `sim:…`).
    pub target: String,
    /// The profile name.
    pub profile: String,
    /// How the bytes travelled.
    pub transport: Transport,
    /// The target's TCP port, 502 for the in-process simulator, 0 for a serial line.
    pub server_port: u16,
    /// When the run started (Unix time, milliseconds); wire timestamps are relative to it.
    pub started_unix_ms: u64,
    /// The command line that started the run.
    pub command_line: String,
    /// The seed of any randomness in the run.
    pub seed: Option<u64>,
    /// The seed the catalog's order was shuffled with (`run --shuffle`), if it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shuffle: Option<u64>,
    /// The harness version.
    pub harness_version: String,
    /// The `--report` directory, if any (named in the terminal summary).
    pub report_dir: Option<PathBuf>,
}

/// The outcome of a run, handed to every sink at the end.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Summary {
    /// Cases per verdict.
    pub counts: BTreeMap<Verdict, usize>,
    /// FAIL case ids, at most a cap (see [`Summary::failing_omitted`] for the rest).
    pub failing: Vec<String>,
    /// The run was stopped before all its cases ran.
    pub interrupted: bool,
    /// Wall time of the run.
    pub duration: Duration,
    /// Number of cases that completed.
    pub cases: usize,
    /// The choices the target made where the specs and manuals leave one.
    pub choices: Vec<crate::oracle::Choice>,
    /// Requirements exercised by the cases that ran, per document.
    pub coverage: Vec<drives::requirements::Coverage>,
    /// Leaving the drive as found: the snapshot, the restore writes, what could not be put back.
    pub leave_as_found: Option<crate::restore::Account>,
    /// Why the run ended before its last case, when it did (the target stopped answering, an error).
    pub ended: Option<String>,
    /// What the liveness probes saw: a target that stopped answering and came back, and after how long.
    pub liveness: Vec<String>,
    /// What the link did, where cases were run again after an attempt that FAILed as a damaged link makes
    /// a case fail (the `link: ...` line).
    pub link: Option<String>,
}

impl Summary {
    /// The number of cases with verdict `v`.
    pub fn count(&self, v: Verdict) -> usize {
        self.counts.get(&v).copied().unwrap_or(0)
    }

    /// FAIL cases whose id is not in `failing` (the list is capped).
    /// Parameters that differ from the snapshot after the final restore.
    pub fn not_restored(&self) -> usize {
        self.leave_as_found
            .as_ref()
            .map_or(0, |a| a.unrestored.len())
    }

    /// FAIL cases whose id is not in `failing` (the list is capped).
    pub fn failing_omitted(&self) -> usize {
        self.count(Verdict::Fail).saturating_sub(self.failing.len())
    }

    /// The overall result: `FAIL` if any case failed, else `INTERRUPTED`, `NO CASES` or `PASS`.
    pub fn result_label(&self) -> &'static str {
        if self.not_restored() > 0 {
            "NOT RESTORED"
        } else if self.count(Verdict::Fail) > 0 {
            "FAIL"
        } else if self.interrupted {
            "INTERRUPTED"
        } else if self.cases == 0 {
            "NO CASES"
        } else {
            "PASS"
        }
    }

    /// `3 FAIL, 120 PASS, 2 SKIPPED`: FAIL first, then the other verdicts in report order, zeros left out.
    pub fn counts_line(&self) -> String {
        let order = std::iter::once(Verdict::Fail)
            .chain(Verdict::ALL.into_iter().filter(|v| *v != Verdict::Fail));
        let parts: Vec<String> = order
            .filter_map(|v| match self.count(v) {
                0 => None,
                n => Some(format!("{n} {v}")),
            })
            .collect();
        if parts.is_empty() {
            "0 cases".to_string()
        } else {
            parts.join(", ")
        }
    }

    /// The summary as JSON (as in `index.json`).
    pub fn to_json(&self) -> serde_json::Value {
        let counts: serde_json::Map<String, serde_json::Value> = Verdict::ALL
            .into_iter()
            .map(|v| (v.label().to_string(), self.count(v).into()))
            .collect();
        let mut json = serde_json::json!({
            "result": self.result_label(),
            "cases": self.cases,
            "counts": counts,
            "failing": self.failing,
            "failing_omitted": self.failing_omitted(),
            "interrupted": self.interrupted,
            "duration_us": self.duration.as_micros() as u64,
            "choices": self.choices,
            "leave_as_found": self.leave_as_found,
            "coverage": self
                .coverage
                .iter()
                .map(|c| serde_json::json!({
                    "document": c.document,
                    "title": c.title,
                    "listed": c.listed,
                    "exercised": c.exercised,
                }))
                .collect::<Vec<_>>(),
        });
        // Only when there is something to say: the index of a run that went as planned keeps its shape.
        if let Some(o) = json.as_object_mut() {
            if let Some(e) = &self.ended {
                o.insert("ended".into(), e.clone().into());
            }
            if !self.liveness.is_empty() {
                o.insert("liveness".into(), self.liveness.clone().into());
            }
            if let Some(l) = &self.link {
                o.insert("link".into(), l.clone().into());
            }
        }
        json
    }

    /// The "choices this drive made" lines: one per freedom (and item) the target showed a value for.
    pub fn choice_lines(&self) -> Vec<String> {
        let log: crate::oracle::ChoiceLog = self.choices.iter().cloned().collect();
        log.lines()
    }
}

/// Counts verdicts and keeps the first [`FAILING_CAP`] FAIL ids: the only state a run needs for its summary.
#[derive(Clone, Debug, Default)]
pub struct Tally {
    counts: BTreeMap<Verdict, usize>,
    failing: Vec<String>,
    cases: usize,
}

impl Tally {
    /// An empty tally.
    pub fn new() -> Self {
        Self::default()
    }

    /// Count one completed case.
    pub fn record(&mut self, result: &CaseResult) {
        *self.counts.entry(result.verdict).or_insert(0) += 1;
        self.cases += 1;
        if result.verdict == Verdict::Fail && self.failing.len() < FAILING_CAP {
            self.failing.push(result.id.clone());
        }
    }

    /// Number of cases recorded.
    pub fn cases(&self) -> usize {
        self.cases
    }

    /// The FAIL ids kept (at most [`FAILING_CAP`]).
    pub fn failing(&self) -> &[String] {
        &self.failing
    }

    /// The summary of what was recorded.
    pub fn summary(&self, interrupted: bool, duration: Duration) -> Summary {
        Summary {
            counts: self.counts.clone(),
            failing: self.failing.clone(),
            interrupted,
            duration,
            cases: self.cases,
            choices: Vec::new(),
            coverage: Vec::new(),
            leave_as_found: None,
            ended: None,
            liveness: Vec::new(),
            link: None,
        }
    }
}

/// A report format written case by case.
pub trait Sink {
    /// Write one completed case.
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()>;
    /// Complete the report with the run's summary (also for an interrupted run).
    fn finish(&mut self, summary: &Summary) -> io::Result<()>;
    /// Push buffered bytes to the files (e.g. on an interrupt signal).
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// Every report format of a `--report DIR`, fed together.
///
/// The formats are written on a thread of their own (`report-writer`): [`Reports::case`] counts the
/// verdict and hands a copy of the case and its result ([`Reports::case_owned`]: the case and its result
/// themselves) over a bounded channel, in small batches, so the run
/// loop does not wait for the files unless the writer falls behind by more than two batches. The first
/// error of a format is returned by a later [`Reports::case`], by [`Reports::flush`] or by
/// [`Reports::finish`], which completes the files and joins the thread. Dropped without `finish`, the
/// cases handed over are still written to the `.partial` files and the thread is joined.
pub struct Reports {
    dir: PathBuf,
    writer: writer::Writer,
    tally: Tally,
}

impl Reports {
    /// Create `dir` (and `dir/cases`), remove the reports of an earlier run in it, and open every format.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        fs::create_dir_all(dir).map_err(with_path("cannot create report directory", dir))?;
        let cases = dir.join(CASES_DIR);
        fs::create_dir_all(&cases).map_err(with_path("cannot create directory", &cases))?;
        clean_earlier_run(dir)?;
        let sinks: Vec<Box<dyn Sink + Send>> = vec![
            Box::new(JsonSink::create(dir, info)?),
            Box::new(JunitSink::create(dir, info)?),
            Box::new(HtmlSink::create(dir, info)?),
            Box::new(PcapSink::create(dir, info)?),
        ];
        Ok(Self {
            dir: dir.to_path_buf(),
            writer: writer::Writer::spawn(sinks)?,
            tally: Tally::new(),
        })
    }

    /// The report directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The verdict counts so far.
    pub fn tally(&self) -> &Tally {
        &self.tally
    }

    /// The summary of the cases written so far.
    pub fn summary(&self, interrupted: bool, duration: Duration) -> Summary {
        self.tally.summary(interrupted, duration)
    }

    /// Count one completed case and hand it to the writer thread, which writes it to every format (every
    /// format is tried; the first error stops the thread and is returned by the next call).
    pub fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        self.case_owned(case.clone(), result.clone())
    }

    /// As [`Reports::case`], for a caller that is done with the case and its result: handed over without a
    /// copy.
    pub fn case_owned(&mut self, case: Case, result: CaseResult) -> io::Result<()> {
        self.tally.record(&result);
        self.writer.send(case, result)
    }

    /// Write every case handed over so far and push buffered bytes to the `.partial` files (e.g. when an
    /// interrupt arrives); returns when they are in the files.
    pub fn flush(&mut self) -> io::Result<()> {
        self.writer.flush()
    }

    /// Write the remaining cases, complete every file, give it its final name, and join the writer thread.
    pub fn finish(mut self, summary: &Summary) -> io::Result<()> {
        self.writer.finish(summary)
    }
}

impl Sink for Reports {
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        Reports::case(self, case, result)
    }

    fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        self.writer.finish(summary)
    }

    fn flush(&mut self) -> io::Result<()> {
        Reports::flush(self)
    }
}

/// Run every result to the end and keep the first error.
fn first_error(results: impl Iterator<Item = io::Result<()>>) -> io::Result<()> {
    let mut first = Ok(());
    for r in results {
        if let (Err(e), true) = (r, first.is_ok()) {
            first = Err(e);
        }
    }
    first
}

/// Remove the final and partial files of an earlier run, and its case files, so nothing stale remains.
fn clean_earlier_run(dir: &Path) -> io::Result<()> {
    for name in [
        INDEX_FILE,
        CASE_LINES_FILE,
        JUNIT_FILE,
        HTML_FILE,
        PCAP_FILE,
    ] {
        for suffix in ["", PARTIAL_SUFFIX, ".tmp"] {
            remove_if_exists(&dir.join(format!("{name}{suffix}")))?;
        }
    }
    let cases = dir.join(CASES_DIR);
    let entries = fs::read_dir(&cases).map_err(with_path("cannot list", &cases))?;
    for entry in entries {
        let path = entry.map_err(with_path("cannot list", &cases))?.path();
        if path.extension().is_some_and(|e| e == "json") {
            remove_if_exists(&path)?;
        }
    }
    Ok(())
}

fn remove_if_exists(path: &Path) -> io::Result<()> {
    match fs::remove_file(path) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(with_path("cannot remove", path)(e)),
        _ => Ok(()),
    }
}

/// Wrap an I/O error so that it names what was being done and the file.
pub(crate) fn with_path(what: &'static str, path: &Path) -> impl FnOnce(io::Error) -> io::Error {
    let path = path.to_path_buf();
    move |e| io::Error::new(e.kind(), format!("{what} {}: {e}", path.display()))
}

/// A streamed file: written through a [`STREAM_BUFFER`] to its `.partial` name, by `W` (the buffer itself, or
/// a format's writer around it); its sink completes it and gives it its final name.
pub(crate) struct Stream<W = BufWriter<File>> {
    partial: PathBuf,
    out: Option<W>,
}

/// A writer whose bytes end in a stream's buffer.
pub(crate) trait Buffered {
    fn buffer(&mut self) -> &mut BufWriter<File>;
}

impl Buffered for BufWriter<File> {
    fn buffer(&mut self) -> &mut BufWriter<File> {
        self
    }
}

impl Stream {
    /// Create `dir/name.partial`.
    pub(crate) fn create(dir: &Path, name: &str) -> io::Result<Self> {
        Stream::wrapping(dir, name, io::Result::Ok)
    }
}

impl<W: Buffered> Stream<W> {
    /// Create `dir/name.partial`, written by what `wrap` makes of its buffer (`wrap`'s error names the
    /// file).
    pub(crate) fn wrapping<E>(
        dir: &Path,
        name: &str,
        wrap: impl FnOnce(BufWriter<File>) -> Result<W, E>,
    ) -> io::Result<Self>
    where
        io::Error: From<E>,
    {
        let partial = partial_path(dir, name);
        let file = File::create(&partial).map_err(with_path("cannot create", &partial))?;
        let out = wrap(BufWriter::with_capacity(STREAM_BUFFER, file))
            .map_err(|e| with_path("cannot write", &partial)(e.into()))?;
        Ok(Self {
            partial,
            out: Some(out),
        })
    }

    /// The `.partial` file.
    pub(crate) fn partial(&self) -> &Path {
        &self.partial
    }

    /// Write with `f`; an error names the file, and so does a write after [`Stream::close`].
    pub(crate) fn write<E>(&mut self, f: impl FnOnce(&mut W) -> Result<(), E>) -> io::Result<()>
    where
        io::Error: From<E>,
    {
        match self.out.as_mut() {
            Some(out) => f(out).map_err(|e| with_path("cannot write", &self.partial)(e.into())),
            None => Err(io::Error::other(format!(
                "{}: report already finished",
                self.partial.display()
            ))),
        }
    }

    /// Push the buffered bytes to the file (nothing once closed).
    pub(crate) fn flush(&mut self) -> io::Result<()> {
        match self.out.as_mut() {
            Some(out) => out
                .buffer()
                .flush()
                .map_err(with_path("cannot write", &self.partial)),
            None => Ok(()),
        }
    }

    /// Flush and close the file; a second call is an error.
    pub(crate) fn close(&mut self) -> io::Result<()> {
        self.write(|out| out.buffer().flush())?;
        self.out = None;
        Ok(())
    }
}

/// `path` with `.partial` appended.
pub(crate) fn partial_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}{PARTIAL_SUFFIX}"))
}

/// Rename a completed file to its final name.
pub(crate) fn promote(from: &Path, to: &Path) -> io::Result<()> {
    fs::rename(from, to).map_err(|e| {
        io::Error::new(
            e.kind(),
            format!("cannot rename {} to {}: {e}", from.display(), to.display()),
        )
    })
}

/// The file name (in `cases/`) of a case that did not PASS: the id with `/` as `__`; ids with other characters, `..`,
/// or more than 120 characters get a readable prefix and `~` plus a hash of the id, so names never collide.
pub fn case_file_name(id: &str) -> String {
    let plain = !id.is_empty()
        && id.len() <= 120
        && !id.contains("..")
        && !id.starts_with('.')
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'-' || b == b'/');
    let mut readable = String::with_capacity(id.len().min(120) + 8);
    for c in id.chars().take(120) {
        match c {
            '/' => readable.push_str("__"),
            '.' if plain => readable.push('.'),
            c if c.is_ascii_alphanumeric() || c == '-' => readable.push(c),
            _ => readable.push('_'),
        }
    }
    if plain {
        format!("{readable}.json")
    } else {
        format!("{readable}~{:016x}.json", fnv1a64(id.as_bytes()))
    }
}

fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The TCP port the pcap puts the target on: the real one, or [`PCAP_SERIAL_PORT`] when there is none.
pub fn pcap_server_port(info: &RunInfo) -> u16 {
    if info.server_port == 0 {
        match info.transport {
            Transport::Tcp => 502,
            Transport::Rtu | Transport::RtuOverTcp => PCAP_SERIAL_PORT,
        }
    } else {
        info.server_port
    }
}

/// The `tshark`/`wireshark` options that decode `session.pcapng` as Modbus for this run.
pub fn pcap_decode_args(info: &RunInfo) -> Vec<String> {
    let port = pcap_server_port(info);
    match info.transport {
        Transport::Tcp => vec!["-o".into(), format!("mbtcp.tcp.port:{port}")],
        Transport::Rtu | Transport::RtuOverTcp => vec![
            "-d".into(),
            format!("tcp.port=={port},mbrtu"),
            "-o".into(),
            "mbrtu.crc_verification:TRUE".into(),
        ],
    }
}

/// The text printed at the end of a run: counts per verdict, failing ids (capped), where the reports are,
/// and a last line `RESULT: FAIL (3 FAIL, 120 PASS, 2 SKIPPED)`.
pub fn terminal_summary(summary: &Summary, info: &RunInfo) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "modbus-harness {} · target {} · profile {} · {} case(s) in {:.1} s{}",
        info.harness_version,
        info.target,
        info.profile,
        summary.cases,
        summary.duration.as_secs_f64(),
        if summary.interrupted {
            " · INTERRUPTED"
        } else {
            ""
        }
    );
    if let Some(seed) = info.seed {
        let _ = writeln!(s, "seed: {seed}");
    }
    if let Some(seed) = info.shuffle {
        let _ = writeln!(
            s,
            "order shuffled with seed {seed} (replay with --shuffle {seed})"
        );
    }
    for v in Verdict::ALL {
        let _ = writeln!(s, "  {:<14}{:>8}", v.label(), summary.count(v));
    }
    let fails = summary.count(Verdict::Fail);
    if fails > 0 {
        let _ = writeln!(s, "FAIL:");
        for id in summary.failing.iter().take(TERMINAL_FAILING_CAP) {
            let _ = writeln!(s, "  {id}");
        }
        let shown = summary.failing.len().min(TERMINAL_FAILING_CAP);
        if fails > shown {
            let _ = writeln!(s, "  ... and {} more", fails - shown);
        }
    }
    if !summary.choices.is_empty() {
        // The choices where the drive differs from the reference drive (or changed its mind) in full; the
        // reference's own choices are counted (every one is in index.json and the HTML page).
        let departed: Vec<crate::oracle::Choice> = summary
            .choices
            .iter()
            .filter(|c| !c.reference || !c.changed.is_empty())
            .cloned()
            .collect();
        let _ = writeln!(
            s,
            "choices this drive made: {} freedom(s) exercised, {} as the reference drive, {} otherwise{}",
            summary.choices.len(),
            summary.choices.len() - departed.len(),
            departed.len(),
            if departed.is_empty() { "" } else { ":" }
        );
        let log: crate::oracle::ChoiceLog = departed.into_iter().collect();
        let lines = log.lines();
        for line in lines.iter().take(TERMINAL_FAILING_CAP) {
            let _ = writeln!(s, "  {line}");
        }
        if lines.len() > TERMINAL_FAILING_CAP {
            let _ = writeln!(
                s,
                "  ... and {} more (index.json)",
                lines.len() - TERMINAL_FAILING_CAP
            );
        }
    }
    if !summary.coverage.is_empty() {
        let parts: Vec<String> = summary
            .coverage
            .iter()
            .filter(|c| c.listed > 0)
            .map(|c| format!("{} {}/{}", c.document, c.exercised, c.listed))
            .collect();
        let _ = writeln!(s, "requirements exercised: {}", parts.join(", "));
    }
    if let Some(a) = &summary.leave_as_found {
        for line in a.lines() {
            let _ = writeln!(s, "{line}");
        }
    }
    for l in &summary.liveness {
        let _ = writeln!(s, "liveness: {l}");
    }
    if let Some(l) = &summary.link {
        let _ = writeln!(s, "{l}");
    }
    if let Some(e) = &summary.ended {
        let _ = writeln!(s, "the run ended early: {e}");
    }
    if let Some(dir) = &info.report_dir {
        let _ = writeln!(
            s,
            "reports: {} ({INDEX_FILE}, {JUNIT_FILE}, {HTML_FILE}, {PCAP_FILE}, {CASE_LINES_FILE}, {CASES_DIR}/ for the cases that ran and did not PASS)",
            dir.display()
        );
        let _ = writeln!(
            s,
            "pcap: tshark -r {} {}",
            dir.join(PCAP_FILE).display(),
            pcap_decode_args(info).join(" ")
        );
    }
    let _ = write!(
        s,
        "RESULT: {} ({}{})",
        summary.result_label(),
        summary.counts_line(),
        if summary.interrupted {
            "; interrupted"
        } else {
            ""
        }
    );
    s
}

/// Characters XML 1.0 forbids even escaped (most C0 controls, U+FFFE, U+FFFF) replaced by U+FFFD.
pub(crate) fn xml_safe(s: &str) -> std::borrow::Cow<'_, str> {
    fn bad(c: char) -> bool {
        (c < ' ' && !matches!(c, '\t' | '\n' | '\r')) || c == '\u{FFFE}' || c == '\u{FFFF}'
    }
    if s.chars().any(bad) {
        s.chars()
            .map(|c| if bad(c) { '\u{FFFD}' } else { c })
            .collect::<String>()
            .into()
    } else {
        s.into()
    }
}

/// One line of a wire log: `     10850 µs  Rx  01 03 …` (`[malformed on purpose]` at the end if so).
pub(crate) fn wire_line(e: &WireEvent) -> String {
    format!(
        "{:>10} µs  {}  {}{}",
        e.at.as_micros(),
        dir_label(e.dir),
        hex_spaced(&e.bytes),
        if e.intended_malformed {
            "  [malformed on purpose]"
        } else {
            ""
        }
    )
}

/// `Tx` or `Rx`.
pub(crate) fn dir_label(d: Dir) -> &'static str {
    match d {
        Dir::Tx => "Tx",
        Dir::Rx => "Rx",
    }
}

/// An observed outcome in one line.
pub(crate) fn outcome_text(o: &Received) -> String {
    match o {
        Received::Frame { bytes, .. } => hex_spaced(bytes),
        Received::Silence { .. } => "(silence)".to_string(),
        Received::Closed { .. } => "(connection closed)".to_string(),
        Received::Garbage { bytes, reason, .. } => {
            format!("(garbage: {reason}) {}", hex_spaced(bytes))
        }
    }
}

/// Unix milliseconds as an ISO 8601 UTC time (`2026-11-22T02:50:13.123Z`).
pub fn iso8601_utc(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    // Howard Hinnant's days-to-civil algorithm.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        unix_ms % 1000
    )
}
