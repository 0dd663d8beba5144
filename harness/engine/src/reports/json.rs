//! `index.json` (streamed: the case array grows line by line, the summary closes it), `cases.jsonl` (every
//! case's full record, one line each, streamed) and `cases/*.json` (the same record, pretty, for the cases
//! that ran and did not PASS).
//!
//! One streamed file for every case instead of one file per case: opening, writing and closing a file per
//! case was most of what `--report` cost (three system calls and a directory entry per case, ~75 % of the
//! samples in the kernel on ext4; BENCHMARKS.md, issue 17 item 3). The files a user opens to debug a
//! failure stay one per case. A SKIPPED case has none: nothing of it reached the wire, and its reason is in
//! its `index.json` entry (a generated run skips the alterations its transport cannot carry, ~3 % of its
//! cases; their files were a third of what `--report` cost on ext4).

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::{
    CASE_LINES_FILE, CASES_DIR, INDEX_FILE, RunInfo, Sink, Stream, Summary, case_file_name,
    promote, with_path,
};
use crate::{Case, CaseResult, Verdict};

/// Format tag at the top of `index.json`, bumped when its layout changes (2: `file` only for the cases that
/// have a case file, the non-PASS ones; every case's record is in `cases.jsonl`. 3: no case file for a
/// SKIPPED case, whose entry has the `reason` instead).
pub const INDEX_FORMAT: &str = "modbus-harness-report/3";

/// Writes `index.json`, `cases.jsonl` and a JSON file in `cases/` per case that ran and did not PASS.
pub struct JsonSink {
    dir: PathBuf,
    index: Stream,
    lines: Stream,
    first: bool,
    /// Reused for each case file: bounded by the largest case, not by the number of cases.
    scratch: Vec<u8>,
}

/// What a case file holds, and what a line of `cases.jsonl` holds.
#[derive(Serialize)]
struct CaseFile<'a> {
    case: &'a Case,
    result: &'a CaseResult,
}

/// One element of the `cases` array of `index.json`.
#[derive(Serialize)]
struct IndexEntry<'a> {
    id: &'a str,
    title: &'a str,
    verdict: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    verdict_before_expectations: Option<&'static str>,
    reference: &'a str,
    duration_us: u64,
    /// The case file, for the cases that have one (ran, and not PASS).
    #[serde(skip_serializing_if = "Option::is_none")]
    file: Option<String>,
    /// Why the case was skipped or could not complete, for a case without a case file.
    #[serde(skip_serializing_if = "Option::is_none")]
    reason: Option<&'a str>,
}

impl JsonSink {
    /// Start `index.json.partial` in `dir` with the run info, and `cases.jsonl.partial`; case files go to
    /// `dir/cases/`.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        let mut index = Stream::create(dir, INDEX_FILE)?;
        let run = serde_json::to_string(info).map_err(io::Error::other)?;
        index.write(|out| {
            write!(
                out,
                "{{\"format\":\"{INDEX_FORMAT}\",\n\"run\":{run},\n\"cases\":["
            )
        })?;
        Ok(Self {
            dir: dir.to_path_buf(),
            index,
            lines: Stream::create(dir, CASE_LINES_FILE)?,
            first: true,
            scratch: Vec::new(),
        })
    }
}

impl Sink for JsonSink {
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        let record = CaseFile { case, result };
        let cannot = |e| io::Error::other(format!("cannot serialise case {}: {e}", result.id));
        // Serialised straight into the stream's buffer: no copy per case.
        self.lines.write(|out| {
            serde_json::to_writer(&mut *out, &record).map_err(cannot)?;
            out.write_all(b"\n")
        })?;
        let file = if matches!(result.verdict, Verdict::Pass | Verdict::Skipped) {
            None
        } else {
            let name = case_file_name(&result.id);
            let path = self.dir.join(CASES_DIR).join(&name);
            self.scratch.clear();
            serde_json::to_writer_pretty(&mut self.scratch, &record).map_err(cannot)?;
            self.scratch.push(b'\n');
            fs::write(&path, &self.scratch).map_err(with_path("cannot write", &path))?;
            Some(format!("{CASES_DIR}/{name}"))
        };

        let entry = IndexEntry {
            id: &result.id,
            title: &case.title,
            verdict: result.verdict.label(),
            verdict_before_expectations: result.expected_deviation.as_ref().map(|(v, _)| v.label()),
            reference: &case.reference,
            duration_us: result.duration.as_micros() as u64,
            reason: result.reason.as_deref().filter(|_| file.is_none()),
            file,
        };
        let sep = if self.first { "\n" } else { ",\n" };
        self.first = false;
        self.index.write(|out| {
            out.write_all(sep.as_bytes())?;
            serde_json::to_writer(&mut *out, &entry).map_err(io::Error::other)
        })
    }

    fn flush(&mut self) -> io::Result<()> {
        let lines = self.lines.flush();
        super::first_error([lines, self.index.flush()].into_iter())
    }

    fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        self.lines.close()?;
        promote(self.lines.partial(), &self.dir.join(CASE_LINES_FILE))?;
        let summary = serde_json::to_string(&summary.to_json()).map_err(io::Error::other)?;
        self.index
            .write(|out| write!(out, "\n],\n\"summary\":{summary}\n}}\n"))?;
        self.index.close()?;
        promote(self.index.partial(), &self.dir.join(INDEX_FILE))
    }
}
