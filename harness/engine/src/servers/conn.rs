//! One byte stream (a TCP connection or a serial line) served by the shared station.
//!
//! A single task per stream reads, feeds the station, and writes the replies when they are due, in
//! request order. Replies due at once go out in one write: a client that pipelines gets one segment back.
//! Delayed replies (`Wire::delay`) wait in a bounded queue while reading goes on, so a late reply does
//! not distort the arrival times of the requests behind it.

use std::collections::VecDeque;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

use super::SharedStation;
use super::shutdown::Shutdown;
use codec::framer::RtuTiming;
use drives::{RtuPort, Station, TcpConn, Wire};

/// Bytes read at once: room for many pipelined requests (a Modbus/TCP ADU is at most 260 bytes).
const READ_BUF: usize = 8192;

/// Replies waiting for their time before reading stops: bounds memory against a client that sends
/// faster than delayed replies drain.
const MAX_PENDING: usize = 1024;

/// The framing of a stream, between the bytes and the station.
pub(crate) trait Protocol {
    /// Feed bytes that arrived at `now`; returns the replies and whether the stream must close after them.
    fn received(&mut self, station: &mut Station, now: Duration, bytes: &[u8])
    -> (Vec<Wire>, bool);

    /// When `poll` must be called, if at all.
    fn deadline(&self) -> Option<Duration>;

    /// Let the time `now` act (silence ending a frame).
    fn poll(&mut self, station: &mut Station, now: Duration) -> Vec<Wire>;

    /// The earliest time a reply produced at `now` may start.
    fn not_before(&self, now: Duration) -> Duration;
}

/// Modbus/TCP: frames cut by the MBAP length.
#[derive(Default)]
pub(crate) struct Tcp {
    conn: TcpConn,
}

impl Protocol for Tcp {
    fn received(
        &mut self,
        station: &mut Station,
        now: Duration,
        bytes: &[u8],
    ) -> (Vec<Wire>, bool) {
        let out = station.serve_tcp(now, &mut self.conn, bytes);
        (out.replies, out.close)
    }

    fn deadline(&self) -> Option<Duration> {
        None
    }

    fn poll(&mut self, _station: &mut Station, _now: Duration) -> Vec<Wire> {
        Vec::new()
    }

    fn not_before(&self, now: Duration) -> Duration {
        now
    }
}

/// RTU on a line or inside TCP: frames cut by length and CRC, or by silence.
pub(crate) struct Rtu {
    port: RtuPort,
    timing: RtuTiming,
    /// Keep t3.5 of silence after a request before answering (a real line; not over TCP).
    keep_silence: bool,
    /// Arrival time of the last bytes read.
    last_rx: Duration,
}

impl Rtu {
    pub(crate) fn new(timing: RtuTiming, keep_silence: bool) -> Self {
        Self {
            port: RtuPort::new(timing),
            timing,
            keep_silence,
            last_rx: Duration::ZERO,
        }
    }
}

impl Protocol for Rtu {
    fn received(
        &mut self,
        station: &mut Station,
        now: Duration,
        bytes: &[u8],
    ) -> (Vec<Wire>, bool) {
        self.last_rx = now;
        (station.serve_rtu(now, &mut self.port, bytes), false)
    }

    fn deadline(&self) -> Option<Duration> {
        self.port.deadline()
    }

    fn poll(&mut self, station: &mut Station, now: Duration) -> Vec<Wire> {
        station.poll_rtu(now, &mut self.port)
    }

    fn not_before(&self, now: Duration) -> Duration {
        if self.keep_silence {
            // The serial line spec: a frame starts only after t3.5 of silence. A frame cut by its length
            // ended with the last bytes read; one cut by silence already had its t3.5.
            now.max(self.last_rx + self.timing.t3_5)
        } else {
            now
        }
    }
}

/// Serve one stream until the peer closes it, an I/O error, the protocol asks to close, or shutdown.
/// Errors end the stream and are logged with `label`; they never reach the other streams.
pub(crate) async fn drive<S, P>(
    mut stream: S,
    mut proto: P,
    shared: &SharedStation,
    mut shutdown: Shutdown,
    label: &str,
) where
    S: AsyncRead + AsyncWrite + Unpin,
    P: Protocol,
{
    let mut rbuf = vec![0u8; READ_BUF];
    let mut wbuf: Vec<u8> = Vec::with_capacity(1024);
    // (station time the reply is due, bytes), in request order.
    let mut pending: VecDeque<(Duration, Vec<u8>)> = VecDeque::new();
    // No more reading: the peer finished sending or the stream cannot be resynchronised.
    let mut closing = false;
    // One shutdown future for the whole stream: it registers with the signal once, not at every select.
    let stop = shutdown.wait();
    tokio::pin!(stop);
    loop {
        // Everything due goes out in one write, in order; a reply not yet due holds back those behind it.
        let now = shared.now();
        while pending.front().is_some_and(|(due, _)| *due <= now) {
            if let Some((_, bytes)) = pending.pop_front() {
                wbuf.extend_from_slice(&bytes);
            }
        }
        if !wbuf.is_empty() {
            tokio::select! {
                biased;
                _ = &mut stop => return,
                written = stream.write_all(&wbuf) => {
                    if let Err(e) = written {
                        eprintln!("server: {label}: write failed: {e}");
                        return;
                    }
                }
            }
            wbuf.clear();
        }
        if closing && pending.is_empty() {
            return;
        }

        let next_due = pending.front().map(|(due, _)| *due);
        let deadline = proto.deadline();
        let can_read = !closing && pending.len() < MAX_PENDING;
        // select! builds every branch's future even when its condition is false: give the sleeps a value.
        let due_at = tokio::time::Instant::from_std(shared.instant(next_due.unwrap_or(now)));
        let poll_at = tokio::time::Instant::from_std(shared.instant(deadline.unwrap_or(now)));
        tokio::select! {
            biased;
            _ = &mut stop => return,
            _ = tokio::time::sleep_until(due_at), if next_due.is_some() => {}
            _ = tokio::time::sleep_until(poll_at), if deadline.is_some() => {
                let now = shared.now();
                let replies = proto.poll(&mut shared.lock(), now);
                queue(&mut pending, replies, proto.not_before(now));
            }
            read = stream.read(&mut rbuf), if can_read => match read {
                // The peer will send no more; replies still owed are sent before closing (a half-closed
                // TCP peer can still read them).
                Ok(0) => closing = true,
                Ok(n) => {
                    let now = shared.now();
                    let (replies, close) = proto.received(&mut shared.lock(), now, &rbuf[..n]);
                    queue(&mut pending, replies, proto.not_before(now));
                    closing |= close;
                }
                Err(e) => {
                    eprintln!("server: {label}: read failed: {e}");
                    return;
                }
            },
        }
    }
}

/// Queue replies produced together, each due `delay` after `start`, never before the one ahead of it.
fn queue(pending: &mut VecDeque<(Duration, Vec<u8>)>, replies: Vec<Wire>, start: Duration) {
    for w in replies {
        let due = pending
            .back()
            .map_or(start + w.delay, |(last, _)| (start + w.delay).max(*last));
        pending.push_back((due, w.bytes));
    }
}
