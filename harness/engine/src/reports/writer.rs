//! The report writer thread: [`super::Reports`] hands each completed (case, result) to it in small batches
//! over a bounded channel, so that serialising and writing the files (mostly serialising, since every case
//! but those that ran and did not PASS goes to streamed files only) runs beside the run loop instead of inside it.
//!
//! Memory stays flat: at most [`BATCH`] cases are being collected, one batch waits in the channel, one is
//! being written and one written batch waits to be dropped; when the writer falls behind, handing over the
//! next batch waits (back-pressure). Written batches go back to the run loop's thread, which drops them
//! and reuses their vector: the cases are freed by the thread that allocated them, so the two threads do
//! not contend for the allocator's lock (measured: 13 % of the writer's time went to that lock's futex when
//! the writer freed them).
//! The first error of a sink stops the thread; it is returned by the next [`Writer::send`], by
//! [`Writer::flush`] or by [`Writer::finish`], which joins the thread.

use std::io;
use std::mem;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::{self, JoinHandle};

use super::{Sink, Summary, first_error};
use crate::{Case, CaseResult};

/// Cases handed over together (one channel message): 64 rather than 8 took a run with reports on two
/// cores from 1.32× to 1.18× the run without (fewer wake-ups of the writer; BENCHMARKS.md, issue 17 item 3).
pub(crate) const BATCH: usize = 64;
/// Batches that may wait in the channel while the writer writes one.
const QUEUED_BATCHES: usize = 1;

type Sinks = Vec<Box<dyn Sink + Send>>;
type Batch = Vec<(Case, CaseResult)>;

enum Msg {
    /// Cases to write, in order.
    Cases(Batch),
    /// Push buffered bytes to the files, then answer.
    Flush(SyncSender<io::Result<()>>),
    /// Complete every file with the summary; the thread ends with the result.
    Finish(Box<Summary>),
}

/// The run loop's side of the writer thread.
pub(crate) struct Writer {
    tx: Option<SyncSender<Msg>>,
    thread: Option<JoinHandle<io::Result<()>>>,
    /// Cases collected for the next message.
    batch: Batch,
    /// Written batches, to be dropped on this thread.
    written: Option<Receiver<Batch>>,
    /// An error already returned to the caller (the thread is gone), returned again on later calls.
    failed: Option<(io::ErrorKind, String)>,
}

impl Writer {
    /// Start the thread that feeds `sinks`.
    pub(crate) fn spawn(sinks: Sinks) -> io::Result<Self> {
        let (tx, rx) = sync_channel(QUEUED_BATCHES);
        let (back, written) = sync_channel(1);
        let thread = thread::Builder::new()
            .name("report-writer".into())
            .spawn(move || write_loop(sinks, &rx, &back))?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            batch: Vec::with_capacity(BATCH),
            written: Some(written),
            failed: None,
        })
    }

    /// Queue one case; hands the batch over when it is full.
    pub(crate) fn send(&mut self, case: Case, result: CaseResult) -> io::Result<()> {
        self.check()?;
        self.batch.push((case, result));
        if self.batch.len() >= BATCH {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Hand the cases collected so far to the thread, and wait until everything is in the files' buffers
    /// and pushed to the files.
    pub(crate) fn flush(&mut self) -> io::Result<()> {
        self.check()?;
        self.hand_over()?;
        let (reply, answer) = sync_channel(1);
        self.message(Msg::Flush(reply))?;
        match answer.recv() {
            Ok(r) => r,
            // The thread ended without answering: its error.
            Err(_) => self.ended(),
        }
    }

    /// Hand over the rest, complete every file, join the thread and return the first error.
    pub(crate) fn finish(&mut self, summary: &Summary) -> io::Result<()> {
        self.check()?;
        self.hand_over()?;
        self.message(Msg::Finish(Box::new(summary.clone())))?;
        self.ended()
    }

    fn check(&self) -> io::Result<()> {
        match &self.failed {
            Some((kind, msg)) => Err(io::Error::new(*kind, msg.clone())),
            None => Ok(()),
        }
    }

    fn hand_over(&mut self) -> io::Result<()> {
        if self.batch.is_empty() {
            return Ok(());
        }
        // A written batch, emptied here (its cases freed by the thread that allocated them), is the next one.
        let next = match self.written.as_ref().and_then(|w| w.try_recv().ok()) {
            Some(mut done) => {
                done.clear();
                done
            }
            None => Vec::with_capacity(BATCH),
        };
        let batch = mem::replace(&mut self.batch, next);
        self.message(Msg::Cases(batch))
    }

    fn message(&mut self, msg: Msg) -> io::Result<()> {
        let sent = match &self.tx {
            Some(tx) => tx.send(msg).is_ok(),
            None => false,
        };
        if sent { Ok(()) } else { self.ended() }
    }

    /// Join the thread and return how it ended; an error is kept for later calls.
    fn ended(&mut self) -> io::Result<()> {
        self.tx = None;
        self.written = None;
        let result = match self.thread.take() {
            Some(t) => t
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("the report writer thread panicked"))),
            None => Err(io::Error::other("report already finished")),
        };
        if let Err(e) = &result
            && self.failed.is_none()
        {
            self.failed = Some((e.kind(), e.to_string()));
        }
        result
    }
}

impl Drop for Writer {
    /// A run that ends without `finish` (killed by an error of its own): the cases handed over so far are
    /// written and the `.partial` files flushed, as the sinks would have done, before the thread is joined.
    fn drop(&mut self) {
        if self.thread.is_some() {
            let _ = self.hand_over();
            self.tx = None;
            self.written = None;
            if let Some(t) = self.thread.take() {
                let _ = t.join();
            }
        }
    }
}

/// The thread: write every case to every sink in order; stop at the first error, at `Finish`, or when
/// the run side is gone (the sinks are then dropped, which flushes their buffers).
///
/// A written batch goes back to the run side to be dropped there; if the one before is still waiting (or the
/// run side is gone), it is dropped here.
fn write_loop(mut sinks: Sinks, rx: &Receiver<Msg>, back: &SyncSender<Batch>) -> io::Result<()> {
    while let Ok(msg) = rx.recv() {
        match msg {
            Msg::Cases(batch) => {
                for (case, result) in &batch {
                    first_error(sinks.iter_mut().map(|s| s.case(case, result)))?;
                }
                let _ = back.try_send(batch);
            }
            Msg::Flush(reply) => {
                let r = first_error(sinks.iter_mut().map(|s| s.flush()));
                let failed = r
                    .as_ref()
                    .err()
                    .map(|e| io::Error::new(e.kind(), e.to_string()));
                let _ = reply.send(r);
                if let Some(e) = failed {
                    return Err(e);
                }
            }
            Msg::Finish(summary) => {
                return first_error(sinks.iter_mut().map(|s| s.finish(&summary)));
            }
        }
    }
    Ok(())
}
