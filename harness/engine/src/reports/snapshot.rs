//! Snapshots: a run's observations as text that diffs well, compared run to run, so that a firmware change
//! that alters behaviour is caught even where no check names it.
//!
//! # Format
//!
//! ```text
//! # modbus-harness snapshot 1
//! # profile mdrive · framing tcp · unit 1 · seed 42
//! # one block per case, sorted by case id; timestamps left out, transaction ids kept (deterministic per run)
//!
//! == gen/42/0/read-reg  PASS
//! > 00 01 00 00 00 06 01 03 00 8B 00 02
//! < 00 01 00 00 00 07 01 03 04 00 09 27 C0
//!
//! == gen/42/1/write-reg-badcrc  SKIPPED
//! # needs RTU framing
//! ```
//!
//! After the header come the choices the drive made where the specifications and its manual leave one (the
//! run's "choices this drive made"), one block per freedom (and item), sorted by freedom, so that a drive
//! that changes a choice between firmware versions shows as drift naming the freedom:
//!
//! ```text
//! == choice/value-out-of-range  4
//! # not the reference drive's choice
//! # seen in 3 case(s): profile/lmd/write-out-of-range/0x0000-a, profile/lmd/write-out-of-range/0x0018-d, ...
//! ```
//!
//! (`choice/FREEDOM/ITEM` for an item of an optional group; a later departure from the choice adds
//! `# then VALUE in CASE`.) The case ids are the first [`crate::oracle::choices::CASES_KEPT`] that showed
//! the choice, sorted.
//!
//! A case's block starts with `== <case id>  <verdict>` and lists, per step, the bytes sent (`> hex`, the pieces of
//! a split request joined) and what came back (`< hex`, `< (silence)`, `< (connection closed)`,
//! `< (garbage: reason) hex`), one line per frame; a step without bytes (a register/object agreement) is
//! `= note: VERDICT`. Blocks are separated by one empty line and sorted by case id in natural order
//! (`gen/1/2` before `gen/1/10`). The header names no target address, so the same observations from the
//! in-process drive and from a server give the same file.
//!
//! # Memory
//!
//! [`SnapshotWriter`] keeps at most one chunk of blocks ([`CHUNK_BYTES`]) in memory: full chunks are sorted
//! and spilled to temporary files, merged at the end. [`compare`] reads both files block by block.

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};

use crate::CaseResult;
use crate::oracle::Choice;
use codec::hex_spaced;

use super::outcome_text;

/// The first line of every snapshot file.
pub const FORMAT_LINE: &str = "# modbus-harness snapshot 1";
/// Blocks kept in memory before a sorted chunk is spilled to a temporary file (bytes of text).
pub const CHUNK_BYTES: usize = 4 << 20;
/// Changed, missing or new cases described in full in a drift report; the rest are counted.
pub const DRIFT_DETAIL_CAP: usize = 50;
/// Lines of one block diffed line by line; longer blocks are shown whole.
const DIFF_LINE_CAP: usize = 400;

/// What the header of a snapshot says about the run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SnapshotHeader {
    pub profile: String,
    /// `tcp` or `rtu`: how frames are delimited (not how they travelled).
    pub framing: String,
    pub unit: u8,
    pub seed: Option<u64>,
}

impl SnapshotHeader {
    /// The header lines, ending with an empty line.
    pub fn text(&self) -> String {
        let seed = self
            .seed
            .map_or_else(|| "none".to_string(), |s| s.to_string());
        format!(
            "{FORMAT_LINE}\n# profile {} · framing {} · unit {} · seed {seed}\n# one block per case, sorted by case id; timestamps left out, transaction ids kept (deterministic per run)\n\n",
            self.profile, self.framing, self.unit
        )
    }
}

/// The block of one case (ends with an empty line).
pub fn block(r: &CaseResult) -> String {
    let mut s = format!("== {}  {}\n", r.id, r.verdict);
    if let Some(reason) = &r.reason {
        for line in reason.lines().filter(|l| !l.trim().is_empty()) {
            let _ = writeln!(s, "# {line}");
        }
    }
    for step in &r.steps {
        match &step.sent {
            Some(bytes) => {
                let _ = writeln!(s, "> {}", hex_spaced(bytes));
                for o in &step.observed {
                    let _ = writeln!(s, "< {}", outcome_text(o));
                }
            }
            None => {
                let _ = writeln!(s, "= {}: {}", step.note, step.verdict);
            }
        }
    }
    s.push('\n');
    s
}

/// The prefix of the ids of choice blocks (no case id starts with it).
pub const CHOICE_PREFIX: &str = "choice/";

/// The block of one choice the drive made: `== choice/FREEDOM[/ITEM]  VALUE`, then what showed it.
pub fn choice_block(c: &Choice) -> (String, String) {
    let id = if c.about.is_empty() {
        format!("{CHOICE_PREFIX}{}", c.freedom)
    } else {
        format!("{CHOICE_PREFIX}{}/{}", c.freedom, c.about)
    };
    let mut s = format!("== {id}  {}\n", c.value);
    if !c.reference {
        s.push_str("# not the reference drive's choice\n");
    }
    let mut cases = c.cases.clone();
    cases.sort_by(|a, b| natural_cmp(a, b));
    let more = if c.count > cases.len() { ", ..." } else { "" };
    let _ = writeln!(
        s,
        "# seen in {} case(s): {}{more}",
        c.count,
        cases.join(", ")
    );
    for (v, case) in &c.changed {
        let _ = writeln!(s, "# then {v} in {case}");
    }
    s.push('\n');
    (id, s)
}

/// Case ids in natural order: digit runs compare as numbers (`gen/1/2` < `gen/1/10`), the rest bytewise.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].is_ascii_digit() && b[j].is_ascii_digit() {
            let si = i;
            while i < a.len() && a[i].is_ascii_digit() {
                i += 1;
            }
            let sj = j;
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let na = trim_zeros(&a[si..i]);
            let nb = trim_zeros(&b[sj..j]);
            let o = na
                .len()
                .cmp(&nb.len())
                .then_with(|| na.cmp(nb))
                .then_with(|| (i - si).cmp(&(j - sj)));
            if o != Ordering::Equal {
                return o;
            }
        } else {
            if a[i] != b[j] {
                return a[i].cmp(&b[j]);
            }
            i += 1;
            j += 1;
        }
    }
    (a.len() - i).cmp(&(b.len() - j))
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let k = d.iter().take_while(|c| **c == b'0').count();
    &d[k.min(d.len().saturating_sub(1))..]
}

/// A block with its id, ordered by id (natural order), then by text.
#[derive(Debug, PartialEq, Eq)]
struct Keyed {
    id: String,
    text: String,
}

impl Ord for Keyed {
    fn cmp(&self, other: &Self) -> Ordering {
        natural_cmp(&self.id, &other.id).then_with(|| self.text.cmp(&other.text))
    }
}

impl PartialOrd for Keyed {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// A temporary file removed when dropped.
struct TempFile(PathBuf);

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn temp_path(dir: &Path, what: &str) -> PathBuf {
    static N: AtomicU64 = AtomicU64::new(0);
    dir.join(format!(
        ".modbus-harness-{what}-{}-{}.tmp",
        std::process::id(),
        N.fetch_add(1, AtomicOrdering::Relaxed)
    ))
}

/// Streams case blocks into a sorted snapshot file with bounded memory.
pub struct SnapshotWriter {
    header: String,
    dir: PathBuf,
    chunk: Vec<Keyed>,
    chunk_bytes: usize,
    chunk_limit: usize,
    runs: Vec<TempFile>,
}

impl SnapshotWriter {
    /// A writer whose temporary files go into `dir` (the destination's directory: the final file is
    /// renamed into place).
    pub fn new(header: &SnapshotHeader, dir: &Path) -> Self {
        Self {
            header: header.text(),
            dir: dir.to_path_buf(),
            chunk: Vec::new(),
            chunk_bytes: 0,
            chunk_limit: CHUNK_BYTES,
            runs: Vec::new(),
        }
    }

    /// Spill chunks of at most `bytes` (tests force several sorted runs with a small value).
    pub fn with_chunk_limit(mut self, bytes: usize) -> Self {
        self.chunk_limit = bytes.max(1);
        self
    }

    /// Add the block of one completed case.
    pub fn add(&mut self, r: &CaseResult) -> io::Result<()> {
        let text = block(r);
        self.chunk_bytes += text.len();
        self.chunk.push(Keyed {
            id: r.id.clone(),
            text,
        });
        if self.chunk_bytes >= self.chunk_limit {
            self.spill()?;
        }
        Ok(())
    }

    /// Add the choices the drive made (one block each, see [`choice_block`]); call once, before
    /// [`SnapshotWriter::finish`].
    pub fn add_choices<'a>(
        &mut self,
        choices: impl IntoIterator<Item = &'a Choice>,
    ) -> io::Result<()> {
        for c in choices {
            let (id, text) = choice_block(c);
            self.chunk_bytes += text.len();
            self.chunk.push(Keyed { id, text });
        }
        if self.chunk_bytes >= self.chunk_limit {
            self.spill()?;
        }
        Ok(())
    }

    /// Number of sorted runs spilled so far.
    pub fn spilled_runs(&self) -> usize {
        self.runs.len()
    }

    fn spill(&mut self) -> io::Result<()> {
        self.chunk.sort();
        let t = TempFile(temp_path(&self.dir, "snapshot-run"));
        let mut w =
            BufWriter::new(File::create(&t.0).map_err(super::with_path("cannot create", &t.0))?);
        for k in self.chunk.drain(..) {
            w.write_all(k.text.as_bytes())?;
        }
        w.flush()?;
        self.chunk_bytes = 0;
        self.runs.push(t);
        Ok(())
    }

    /// Write the sorted snapshot to `out` (through a temporary file renamed into place).
    pub fn finish(mut self, out: &Path) -> io::Result<()> {
        let tmp = TempFile(temp_path(&self.dir, "snapshot"));
        {
            let mut w = BufWriter::new(
                File::create(&tmp.0).map_err(super::with_path("cannot create", &tmp.0))?,
            );
            // A file that insta manages (the committed snapshots/) keeps its front matter.
            if let Some(front) = insta_front_matter(out) {
                w.write_all(front.as_bytes())?;
            }
            w.write_all(self.header.as_bytes())?;
            if self.runs.is_empty() {
                self.chunk.sort();
                for k in &self.chunk {
                    w.write_all(k.text.as_bytes())?;
                }
            } else {
                if !self.chunk.is_empty() {
                    self.spill()?;
                }
                merge(&self.runs, &mut w)?;
            }
            w.flush()?;
        }
        std::fs::rename(&tmp.0, out).map_err(super::with_path("cannot write", out))?;
        Ok(())
    }
}

/// K-way merge of sorted runs (one block of each in memory).
fn merge(runs: &[TempFile], w: &mut impl Write) -> io::Result<()> {
    let mut readers = Vec::with_capacity(runs.len());
    for r in runs {
        readers.push(BlockReader::new(BufReader::new(
            File::open(&r.0).map_err(super::with_path("cannot open", &r.0))?,
        ))?);
    }
    let mut heap = BinaryHeap::new();
    for (i, r) in readers.iter_mut().enumerate() {
        if let Some(b) = r.next_block()? {
            heap.push(std::cmp::Reverse((b.keyed(), i)));
        }
    }
    while let Some(std::cmp::Reverse((k, i))) = heap.pop() {
        w.write_all(k.text.as_bytes())?;
        if let Some(b) = readers[i].next_block()? {
            heap.push(std::cmp::Reverse((b.keyed(), i)));
        }
    }
    Ok(())
}

/// One block read back: its id and lines.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Block {
    pub id: String,
    pub lines: Vec<String>,
}

impl Block {
    /// True for the block of a choice of the drive (not a case).
    pub fn is_choice(&self) -> bool {
        self.id.starts_with(CHOICE_PREFIX)
    }

    fn keyed(&self) -> Keyed {
        let mut text = self.lines.join("\n");
        text.push_str("\n\n");
        Keyed {
            id: self.id.clone(),
            text,
        }
    }
}

/// The id in a block's first line (`== <id>  <VERDICT>`).
fn block_id(line: &str) -> Option<&str> {
    let rest = line.strip_prefix("== ")?;
    Some(rest.rsplit_once("  ").map_or(rest, |(id, _)| id))
}

/// The line that opens and closes the front matter of an insta snapshot file.
const INSTA_FENCE: &str = "---";

/// The insta front matter of the file at `path` (both fences and what is between them), if it has one.
fn insta_front_matter(path: &Path) -> Option<String> {
    let mut lines = BufReader::new(File::open(path).ok()?).lines();
    if lines.next()?.ok()? != INSTA_FENCE {
        return None;
    }
    let mut front = format!("{INSTA_FENCE}\n");
    // A few lines at most (source, description, expression); a file without a closing fence has none.
    for line in lines.take(64) {
        let line = line.ok()?;
        front.push_str(&line);
        front.push('\n');
        if line == INSTA_FENCE {
            return Some(front);
        }
    }
    None
}

/// Reads a snapshot file block by block; the header is read first.
pub struct BlockReader<R> {
    input: R,
    header: Vec<String>,
    pending: Option<String>,
    line: String,
}

impl<R: BufRead> BlockReader<R> {
    /// Read the header (lines before the first block).
    pub fn new(mut input: R) -> io::Result<Self> {
        let mut header = Vec::new();
        let mut line = String::new();
        let mut pending = None;
        // The front matter of an insta snapshot (`---`, `source: ...`, `---`) is not part of the run's
        // observations: a committed `snapshots/*.snap` compares with a run as its text does.
        let mut front_matter = false;
        let mut first = true;
        loop {
            line.clear();
            if input.read_line(&mut line)? == 0 {
                break;
            }
            let l = line.trim_end_matches(['\n', '\r']);
            if std::mem::take(&mut first) && l == INSTA_FENCE {
                front_matter = true;
                continue;
            }
            if front_matter {
                front_matter = l != INSTA_FENCE;
                continue;
            }
            if l.starts_with("== ") {
                pending = Some(l.to_string());
                break;
            }
            if !l.is_empty() {
                header.push(l.to_string());
            }
        }
        Ok(Self {
            input,
            header,
            pending,
            line,
        })
    }

    /// The header lines (without empty lines).
    pub fn header(&self) -> &[String] {
        &self.header
    }

    /// The next block, or `None` at the end.
    pub fn next_block(&mut self) -> io::Result<Option<Block>> {
        let Some(first) = self.pending.take() else {
            return Ok(None);
        };
        let id = block_id(&first).unwrap_or_default().to_string();
        let mut lines = vec![first];
        loop {
            self.line.clear();
            if self.input.read_line(&mut self.line)? == 0 {
                break;
            }
            let l = self.line.trim_end_matches(['\n', '\r']);
            if l.starts_with("== ") {
                self.pending = Some(l.to_string());
                break;
            }
            if !l.is_empty() {
                lines.push(l.to_string());
            }
        }
        Ok(Some(Block { id, lines }))
    }
}

/// How a run's snapshot differs from the committed one.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Drift {
    /// The header lines, when they differ: (snapshot, this run).
    pub header: Option<(Vec<String>, Vec<String>)>,
    /// Cases in both files, the same.
    pub same: usize,
    /// Cases in both files, with different observations or verdicts.
    pub changed: usize,
    /// Cases only in the snapshot file.
    pub missing: usize,
    /// Cases only in this run.
    pub added: usize,
    /// Choices of the drive (`choice/` blocks) that differ: another value, or one shown only in one file.
    pub choices: usize,
    /// The first [`DRIFT_DETAIL_CAP`] differing cases, rendered.
    pub details: Vec<String>,
    /// The ids of the differing cases described in `details`.
    pub ids: Vec<String>,
}

impl Drift {
    /// True when both files hold the same observations.
    pub fn is_clean(&self) -> bool {
        self.header.is_none()
            && self.changed == 0
            && self.missing == 0
            && self.added == 0
            && self.choices == 0
    }

    /// Cases and choices that differ, in all.
    pub fn differing(&self) -> usize {
        self.changed + self.missing + self.added + self.choices
    }

    /// The one-line summary: `snapshot drift: 2 changed, 1 only in the snapshot, 0 new (120 the same)`.
    pub fn summary(&self) -> String {
        if self.is_clean() {
            return format!("snapshot: no drift ({} cases the same)", self.same);
        }
        format!(
            "snapshot drift: {} changed, {} only in the snapshot, {} new in this run ({} the same){}{}",
            self.changed,
            self.missing,
            self.added,
            self.same,
            if self.choices > 0 {
                format!("; {} choice(s) of the drive differ", self.choices)
            } else {
                String::new()
            },
            if self.header.is_some() {
                "; the headers differ"
            } else {
                ""
            }
        )
    }

    /// The readable diff: header, each differing case (capped), the summary last.
    pub fn render(&self) -> String {
        let mut s = String::new();
        if let Some((old, new)) = &self.header {
            let _ = writeln!(s, "header:");
            for l in old {
                let _ = writeln!(s, "  - {l}");
            }
            for l in new {
                let _ = writeln!(s, "  + {l}");
            }
        }
        for d in &self.details {
            s.push_str(d);
        }
        let shown = self.details.len();
        if self.differing() > shown {
            let _ = writeln!(
                s,
                "... and {} more case(s) or choice(s)",
                self.differing() - shown
            );
        }
        s.push_str(&self.summary());
        s.push('\n');
        s
    }

    /// The counter a differing block adds to: `choices` for a choice block, else `which`.
    fn counter(&mut self, b: &Block, which: fn(&mut Self) -> &mut usize) -> &mut usize {
        if b.is_choice() {
            &mut self.choices
        } else {
            which(self)
        }
    }

    fn only_in_snapshot(&mut self, b: &Block) {
        *self.counter(b, |d| &mut d.missing) += 1;
        let text = if b.is_choice() {
            format!(
                "- {}  (a choice only in the snapshot)\n",
                b.lines.join("\n    ")
            )
        } else {
            format!("- {}  (only in the snapshot)\n", b.id)
        };
        self.note(&b.id, text);
    }

    fn only_in_run(&mut self, b: &Block) {
        *self.counter(b, |d| &mut d.added) += 1;
        let text = if b.is_choice() {
            format!("+ {}  (a choice new in this run)\n", b.lines.join("\n    "))
        } else {
            format!("+ {}  (new in this run)\n", b.id)
        };
        self.note(&b.id, text);
    }

    fn note(&mut self, id: &str, text: String) {
        if self.details.len() < DRIFT_DETAIL_CAP {
            self.details.push(text);
            self.ids.push(id.to_string());
        }
    }
}

/// A line diff of two small blocks: unchanged lines indented, removed `-`, added `+`.
fn diff_lines(old: &[String], new: &[String]) -> String {
    let mut s = String::new();
    if old.len() > DIFF_LINE_CAP || new.len() > DIFF_LINE_CAP {
        for l in old {
            let _ = writeln!(s, "    - {l}");
        }
        for l in new {
            let _ = writeln!(s, "    + {l}");
        }
        return s;
    }
    // Longest common subsequence table (blocks are a few lines).
    let (n, m) = (old.len(), new.len());
    let mut t = vec![vec![0u16; m + 1]; n + 1];
    for i in (0..n).rev() {
        for j in (0..m).rev() {
            t[i][j] = if old[i] == new[j] {
                t[i + 1][j + 1] + 1
            } else {
                t[i + 1][j].max(t[i][j + 1])
            };
        }
    }
    let (mut i, mut j) = (0, 0);
    while i < n || j < m {
        if i < n && j < m && old[i] == new[j] {
            let _ = writeln!(s, "      {}", old[i]);
            i += 1;
            j += 1;
        } else if i < n && (j == m || t[i + 1][j] >= t[i][j + 1]) {
            let _ = writeln!(s, "    - {}", old[i]);
            i += 1;
        } else {
            let _ = writeln!(s, "    + {}", new[j]);
            j += 1;
        }
    }
    s
}

fn out_of_order(file: &Path, prev: &str, id: &str) -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidData,
        format!(
            "{}: case `{id}` comes after `{prev}`: the file is not in case-id order (write it again with --update-snapshot)",
            file.display()
        ),
    )
}

/// Compare the snapshot file `expected` with `actual` (both sorted by id), block by block.
pub fn compare(expected: &Path, actual: &Path) -> io::Result<Drift> {
    let open = |p: &Path| -> io::Result<BlockReader<BufReader<File>>> {
        BlockReader::new(BufReader::new(
            File::open(p).map_err(super::with_path("cannot open", p))?,
        ))
    };
    let mut e = open(expected)?;
    let mut a = open(actual)?;
    let mut drift = Drift::default();
    if e.header() != a.header() {
        drift.header = Some((e.header().to_vec(), a.header().to_vec()));
    }
    let mut x = e.next_block()?;
    let mut y = a.next_block()?;
    let (mut last_x, mut last_y) = (String::new(), String::new());
    loop {
        for (b, last, file) in [(&x, &mut last_x, expected), (&y, &mut last_y, actual)] {
            if let Some(b) = b {
                if !last.is_empty() && natural_cmp(last, &b.id) == Ordering::Greater {
                    return Err(out_of_order(file, last, &b.id));
                }
                last.clone_from(&b.id);
            }
        }
        match (&x, &y) {
            (None, None) => break,
            (Some(bx), Some(by)) => match natural_cmp(&bx.id, &by.id) {
                Ordering::Less => {
                    drift.only_in_snapshot(bx);
                    x = e.next_block()?;
                }
                Ordering::Greater => {
                    drift.only_in_run(by);
                    y = a.next_block()?;
                }
                Ordering::Equal => {
                    if bx.lines == by.lines {
                        if !bx.is_choice() {
                            drift.same += 1;
                        }
                    } else {
                        *drift.counter(bx, |d| &mut d.changed) += 1;
                        let text = format!("~ {}\n{}", bx.id, diff_lines(&bx.lines, &by.lines));
                        drift.note(&bx.id, text);
                    }
                    x = e.next_block()?;
                    y = a.next_block()?;
                }
            },
            (Some(bx), None) => {
                drift.only_in_snapshot(bx);
                x = e.next_block()?;
            }
            (None, Some(by)) => {
                drift.only_in_run(by);
                y = a.next_block()?;
            }
        }
    }
    Ok(drift)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut ids = vec![
            "gen/1/10/a",
            "gen/1/2/b",
            "gen/1/2/a",
            "gen/2/0",
            "a",
            "gen/1/1",
        ];
        ids.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            ids,
            vec![
                "a",
                "gen/1/1",
                "gen/1/2/a",
                "gen/1/2/b",
                "gen/1/10/a",
                "gen/2/0"
            ]
        );
        // Leading zeros: equal values, the shorter first.
        assert_eq!(natural_cmp("x/1", "x/01"), Ordering::Less);
    }

    #[test]
    fn line_diff_marks_changes() {
        let old: Vec<String> = ["== x  PASS", "> 01", "< 02"].map(String::from).to_vec();
        let new: Vec<String> = ["== x  FAIL", "> 01", "< (silence)"]
            .map(String::from)
            .to_vec();
        let d = diff_lines(&old, &new);
        assert!(d.contains("    - == x  PASS"), "{d}");
        assert!(d.contains("    + == x  FAIL"), "{d}");
        assert!(d.contains("      > 01"), "{d}");
        assert!(d.contains("    + < (silence)"), "{d}");
    }
}
