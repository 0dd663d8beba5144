//! `index.json` (streamed: the case array grows line by line, the summary closes it) and `cases/*.json`.

use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::{
    CASES_DIR, INDEX_FILE, RunInfo, Sink, Summary, case_file_name, partial_path, promote, with_path,
};
use crate::{Case, CaseResult};

/// Format tag at the top of `index.json`, bumped when its layout changes.
pub const INDEX_FORMAT: &str = "modbus-harness-report/1";

/// Writes `index.json` and one JSON file per case in `cases/`.
pub struct JsonSink {
    dir: PathBuf,
    partial: PathBuf,
    out: Option<BufWriter<File>>,
    first: bool,
    /// Reused for each case file: bounded by the largest case, not by the number of cases.
    scratch: Vec<u8>,
}

/// What a case file holds.
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
    file: String,
}

impl JsonSink {
    /// Start `index.json.partial` in `dir` with the run info; case files go to `dir/cases/`.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        let partial = partial_path(dir, INDEX_FILE);
        let file = File::create(&partial).map_err(with_path("cannot create", &partial))?;
        let mut out = BufWriter::new(file);
        let run = serde_json::to_string(info).map_err(io::Error::other)?;
        write!(
            out,
            "{{\"format\":\"{INDEX_FORMAT}\",\n\"run\":{run},\n\"cases\":["
        )
        .map_err(with_path("cannot write", &partial))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            partial,
            out: Some(out),
            first: true,
            scratch: Vec::new(),
        })
    }

    fn out(&mut self) -> io::Result<&mut BufWriter<File>> {
        let partial = &self.partial;
        self.out.as_mut().ok_or_else(|| {
            io::Error::other(format!("{}: report already finished", partial.display()))
        })
    }
}

impl Sink for JsonSink {
    fn case(&mut self, case: &Case, result: &CaseResult) -> io::Result<()> {
        let name = case_file_name(&result.id);
        let path = self.dir.join(CASES_DIR).join(&name);
        self.scratch.clear();
        serde_json::to_writer_pretty(&mut self.scratch, &CaseFile { case, result })
            .map_err(|e| io::Error::other(format!("cannot serialise case {}: {e}", result.id)))?;
        self.scratch.push(b'\n');
        fs::write(&path, &self.scratch).map_err(with_path("cannot write", &path))?;

        let entry = IndexEntry {
            id: &result.id,
            title: &case.title,
            verdict: result.verdict.label(),
            verdict_before_expectations: result.expected_deviation.as_ref().map(|(v, _)| v.label()),
            reference: &case.reference,
            duration_us: result.duration.as_micros() as u64,
            file: format!("{CASES_DIR}/{name}"),
        };
        let sep = if self.first { "\n" } else { ",\n" };
        self.first = false;
        let partial = self.partial.clone();
        let out = self.out()?;
        out.write_all(sep.as_bytes())
            .and_then(|()| serde_json::to_writer(&mut *out, &entry).map_err(io::Error::other))
            .map_err(with_path("cannot write", &partial))
    }

    fn flush(&mut self) -> io::Result<()> {
        let partial = self.partial.clone();
        match self.out.as_mut() {
            Some(out) => out.flush().map_err(with_path("cannot write", &partial)),
            None => Ok(()),
        }
    }

    fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        let partial = self.partial.clone();
        let mut out = self.out.take().ok_or_else(|| {
            io::Error::other(format!("{}: report already finished", partial.display()))
        })?;
        let summary = serde_json::to_string(&summary.to_json()).map_err(io::Error::other)?;
        write!(out, "\n],\n\"summary\":{summary}\n}}\n")
            .and_then(|()| out.flush())
            .map_err(with_path("cannot write", &partial))?;
        drop(out);
        promote(&partial, &self.dir.join(INDEX_FILE))
    }
}
