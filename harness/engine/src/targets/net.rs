//! Modbus/TCP and RTU-over-TCP targets on a blocking socket with deadlines.

use std::io::{ErrorKind, Read, Write};
use std::mem::MaybeUninit;
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use super::reader::FrameReader;
use super::{Received, Target, TargetError};
use codec::{Framing, RtuTiming};

/// A TCP connection carrying Modbus/TCP ADUs or RTU frames.
pub struct TcpTarget {
    addr: SocketAddr,
    label: String,
    stream: Option<TcpStream>,
    connect_timeout: Duration,
    start: Instant,
    reader: FrameReader,
    rtu: bool,
    closed: bool,
    /// The read timeout set on the socket, if any (each change is a system call).
    read_timeout: Option<Duration>,
    /// When this connection was half-closed (`end_sending`), if it was.
    fin_sent: Option<Instant>,
    /// Nothing was sent on this connection yet.
    fresh: bool,
    /// When the target last sent bytes on this connection, if it has since the harness's last send (nothing
    /// of the harness's is outstanding on it then).
    answered_at: Option<Instant>,
    /// RTU over TCP: the silence the device needs to end a frame (`?gap=MS`), if given.
    resync_gap: Option<Duration>,
    /// A connection was opened to the target before: a refusal now is a link or a stack that comes back.
    opened_before: bool,
}

/// Every address `host` names (a name may have several: `localhost` is 127.0.0.1 and ::1), in the
/// resolver's order.
fn resolve(host: &str, port: u16) -> Result<Vec<SocketAddr>, TargetError> {
    let addr = format!("{host}:{port}");
    let all: Vec<SocketAddr> = (host, port)
        .to_socket_addrs()
        .map_err(|e| TargetError::Resolve {
            addr: addr.clone(),
            reason: e.to_string(),
        })?
        .collect();
    if all.is_empty() {
        return Err(TargetError::Resolve {
            addr,
            reason: "no address".into(),
        });
    }
    Ok(all)
}

/// Wait at most `d` (exactly: ppoll, not the kernel's ticks) for `s` to be readable: bytes, its close or
/// an error waiting. The number of ready descriptors (0 or 1).
fn readable_within(s: &TcpStream, d: Duration) -> nix::Result<i32> {
    use std::os::fd::AsFd;
    let mut fds = [nix::poll::PollFd::new(
        s.as_fd(),
        nix::poll::PollFlags::POLLIN,
    )];
    nix::poll::ppoll(
        &mut fds,
        Some(nix::sys::time::TimeSpec::from_duration(d)),
        None,
    )
}

/// Look, without waiting or taking it, at whether something is there to read: Ok(0) is the peer's close.
fn peek(s: &TcpStream) -> std::io::Result<usize> {
    let mut probe = [MaybeUninit::<u8>::uninit(); 1];
    socket2::SockRef::from(s).recv_with_flags(&mut probe, libc::MSG_PEEK | libc::MSG_DONTWAIT)
}

/// Connection attempts while the target refuses (see `open_retrying`).
const RECONNECT_TRIES: usize = 6;
/// How long a target that took a connection before is tried again while it refuses (see `open_retrying`).
const LINK_BACK_WITHIN: Duration = Duration::from_secs(5);
/// Waits shorter than this are made with ppoll (see `TcpTarget::read_once`).
const SHORT_WAIT: Duration = Duration::from_millis(20);
/// How long a connection being closed waits for the target's own close before the next one is opened (see
/// `TcpTarget::close_gracefully`).
const CLOSE_WAIT: Duration = Duration::from_millis(250);
/// A connection unused for this long since the target's last answer is looked at before the next request
/// goes out on it (see `send`).
const IDLE_LOOK: Duration = Duration::from_millis(5);

/// Nominal timing for RTU over TCP: frames are cut by length rules and CRC; silence only ends unknown ones.
fn rtu_over_tcp_timing() -> RtuTiming {
    RtuTiming::tcp_carrier()
}

impl TcpTarget {
    /// RTU over TCP: leave `gap` of silence after a frame the device may still hold (`?gap=MS`).
    pub fn with_resync_gap(mut self, gap: Option<Duration>) -> Self {
        self.resync_gap = gap;
        self
    }

    /// Connect within `timeout`; `rtu` selects RTU-over-TCP framing.
    pub fn connect(
        host: &str,
        port: u16,
        timeout: Duration,
        rtu: bool,
    ) -> Result<Self, TargetError> {
        Self::connect_to(&resolve(host, port)?, timeout, rtu)
    }

    /// Connect to the first of `addrs` (not empty) that takes a connection, within `timeout` each.
    fn connect_to(addrs: &[SocketAddr], timeout: Duration, rtu: bool) -> Result<Self, TargetError> {
        let label = |a: &SocketAddr| format!("{}://{a}", if rtu { "rtu+tcp" } else { "tcp" });
        let mut t = Self {
            addr: addrs[0],
            label: label(&addrs[0]),
            stream: None,
            connect_timeout: timeout,
            start: Instant::now(),
            reader: if rtu {
                FrameReader::rtu(rtu_over_tcp_timing())
            } else {
                FrameReader::mbap()
            },
            rtu,
            closed: false,
            read_timeout: None,
            fin_sent: None,
            fresh: false,
            answered_at: None,
            resync_gap: None,
            opened_before: false,
        };
        // A name with several addresses: the first that takes a connection is the target (as
        // `TcpStream::connect` does); where none does, the first is tried again as below.
        if addrs.len() > 1 {
            for a in addrs {
                t.addr = *a;
                if t.open().is_ok() {
                    t.label = label(a);
                    return Ok(t);
                }
            }
            t.addr = addrs[0];
        }
        t.open_retrying()?;
        Ok(t)
    }

    fn open(&mut self) -> Result<(), TargetError> {
        let s = TcpStream::connect_timeout(&self.addr, self.connect_timeout).map_err(|source| {
            TargetError::Connect {
                addr: self.addr.to_string(),
                source,
            }
        })?;
        s.set_nodelay(true).ok();
        self.stream = Some(s);
        self.reader.clear();
        self.closed = false;
        self.read_timeout = None;
        self.fin_sent = None;
        self.fresh = true;
        self.answered_at = None;
        self.opened_before = true;
        Ok(())
    }

    /// Close the connection the way that lets a drive with one connection slot take the next one: half-close
    /// it (TCP FIN) and wait, at most [`CLOSE_WAIT`] after the FIN, for the target's own close, discarding
    /// what comes before it (late answers). A drive frees its slot when it closes its side; one that notices
    /// a client's close only on the next turn of its loop (a firmware polling its sockets every few
    /// milliseconds, a serial device server) would otherwise still hold the slot when the harness's next
    /// connection arrives, and accept and close it at once (the TCP guide leaves the number of connections
    /// to the device, 4.4.2.1, and says nothing of when a closed one is free again). Not waited for where the
    /// target closed first. A target that keeps a half-closed connection open is given up on after the wait.
    fn close_gracefully(&mut self) {
        let Some(mut s) = self.stream.take() else {
            return;
        };
        if self.closed {
            return;
        }
        let fin = *self.fin_sent.get_or_insert_with(Instant::now);
        if s.shutdown(std::net::Shutdown::Write).is_err() {
            return;
        }
        let until = fin + CLOSE_WAIT;
        let mut chunk = [0u8; 1024];
        // Bounded by the wait, and by 64 KiB of late bytes at most.
        for _ in 0..64 {
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() || s.set_read_timeout(Some(left)).is_err() {
                break;
            }
            match s.read(&mut chunk) {
                Ok(1..) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                // Its close (or a reset), or the wait is over.
                _ => break,
            }
        }
        self.closed = true;
    }

    /// Before the first request on a new connection: whether the target closes it within `look` (zero: has
    /// closed it already, one look without waiting). A drive whose connection slots are taken may accept a
    /// connection and close it at once (a refusal after the handshake, where others refuse the connect
    /// itself).
    fn closed_within(&self, look: Duration) -> bool {
        let Some(s) = self.stream.as_ref() else {
            return false;
        };
        if !look.is_zero() && !matches!(readable_within(s, look), Ok(1..)) {
            return false;
        }
        match peek(s) {
            Ok(0) => true,
            Ok(_) => false,
            Err(e) => matches!(
                e.kind(),
                ErrorKind::ConnectionReset | ErrorKind::ConnectionAborted | ErrorKind::BrokenPipe
            ),
        }
    }

    /// Open, trying again while the connection is refused or reset: a drive with one connection slot (the
    /// TCP guide leaves the number to the device, 4.4.2.1) may refuse a connection until it has freed the one
    /// just closed (the harness closes and reopens between cases, and after reading the identification).
    /// At most RECONNECT_TRIES attempts over about 0.6 s; a port nobody listens on is reported that much later.
    /// A target that took a connection before is tried for [`LINK_BACK_WITHIN`], the pause between attempts
    /// growing to 1 s: a link that dropped for a moment (a switch port, a cable), after which a drive's small
    /// stack may refuse connects for a while, is waited for and not taken for a drive gone for good.
    fn open_retrying(&mut self) -> Result<(), TargetError> {
        let mut wait = Duration::from_millis(20);
        let started = Instant::now();
        let mut tries = 1;
        while tries < RECONNECT_TRIES
            || (self.opened_before && started.elapsed() + wait < LINK_BACK_WITHIN)
        {
            tries += 1;
            match self.open() {
                Err(TargetError::Connect { source, .. })
                    if matches!(
                        source.kind(),
                        ErrorKind::ConnectionRefused
                            | ErrorKind::ConnectionReset
                            | ErrorKind::ConnectionAborted
                    ) =>
                {
                    std::thread::sleep(wait);
                    wait = (wait * 2).min(Duration::from_secs(1));
                }
                other => return other,
            }
        }
        self.open()
    }

    fn io(&self, source: std::io::Error) -> TargetError {
        TargetError::Io {
            target: self.label.clone(),
            source,
        }
    }

    /// Read once, waiting at most until `until`; returns false when the peer has closed.
    fn read_once(&mut self, until: Instant) -> Result<bool, TargetError> {
        let left = until
            .saturating_duration_since(Instant::now())
            .max(Duration::from_micros(50));
        let Some(s) = self.stream.as_mut() else {
            return Ok(false);
        };
        // A socket's receive timeout is counted in the kernel's ticks: 250 µs lasts 4-7 ms here. A short wait
        // (the tail of a window, the look before a half-close) is made with ppoll, whose timeout is exact;
        // the read then finds the bytes or the close waiting.
        if left < SHORT_WAIT {
            match readable_within(s, left) {
                Ok(0) | Err(nix::errno::Errno::EINTR) => return Ok(true),
                Ok(_) => {}
                Err(e) => return Err(self.io(std::io::Error::from(e))),
            }
        }
        // Keep the timeout already set while it ends the read no later than `until` and not much before
        // (at least half of what is left): successive exchanges with the same timeout set it once.
        if self.read_timeout.is_none_or(|t| t > left || t < left / 2) {
            s.set_read_timeout(Some(left))
                .map_err(|e| TargetError::Io {
                    target: String::new(),
                    source: e,
                })?;
            self.read_timeout = Some(left);
        }
        let mut chunk = [0u8; 1024];
        match s.read(&mut chunk) {
            Ok(0) => Ok(false),
            Ok(n) => {
                let at = Instant::now();
                self.answered_at = Some(at);
                let now = at - self.start;
                self.reader.push(now, &chunk[..n]);
                Ok(true)
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) =>
            {
                Ok(true)
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::ConnectionReset
                        | ErrorKind::ConnectionAborted
                        | ErrorKind::BrokenPipe
                ) =>
            {
                Ok(false)
            }
            Err(e) => Err(self.io(e)),
        }
    }
}

impl Drop for TcpTarget {
    /// The last connection too is closed so that the drive has freed its slot when the process ends (the
    /// next run, or `restore --journal`, may follow at once).
    fn drop(&mut self) {
        self.close_gracefully();
    }
}

impl Target for TcpTarget {
    fn resync_gap(&self) -> Option<Duration> {
        self.resync_gap.filter(|_| self.rtu)
    }

    fn end_sending(&mut self) -> Result<bool, TargetError> {
        let Some(s) = self.stream.as_ref() else {
            return Ok(false);
        };
        match s.shutdown(std::net::Shutdown::Write) {
            Ok(()) => {
                self.fin_sent = Some(Instant::now());
                Ok(true)
            }
            // Closed by the peer already: the receive that follows sees it.
            Err(e) if e.kind() == ErrorKind::NotConnected => Ok(false),
            Err(e) => Err(self.io(e)),
        }
    }

    fn framing(&self) -> Framing {
        if self.rtu { Framing::Rtu } else { Framing::Tcp }
    }

    fn now(&self) -> Duration {
        self.start.elapsed()
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        // A connection left unused since the drive's last answer (a paced run, a wait, the watch's pauses)
        // may have been closed by the drive meanwhile (an idle timeout): the request goes out on a new one,
        // not to a connection whose close is already here, which would have been taken for the drive's answer
        // to it. Not after a send with nothing back since (the next piece of a request sent in pieces, a
        // request after one that went unanswered): a close there is the drive's answer to what was sent.
        if !self.closed
            && self.answered_at.is_some_and(|at| at.elapsed() >= IDLE_LOOK)
            && self.closed_within(Duration::ZERO)
        {
            self.closed = true;
        }
        // A new connection closed before its first request was refused after the handshake: the drive's
        // slot is not free yet. Opened again as after a refused connect, each new one watched for as long as
        // the pause before it (a refusal takes a round trip to arrive), at most about 1.2 s in all.
        let mut wait = Duration::from_millis(20);
        let mut look = Duration::ZERO;
        for tried in 1..=RECONNECT_TRIES {
            if self.closed {
                self.close_gracefully();
                self.open_retrying()?;
            }
            // At the last try the request goes out all the same: its receive sees the close.
            if tried == RECONNECT_TRIES || !(self.fresh && self.closed_within(look)) {
                break;
            }
            self.stream = None;
            self.closed = true;
            std::thread::sleep(wait);
            look = wait;
            wait *= 2;
        }
        self.fresh = false;
        let Some(s) = self.stream.as_mut() else {
            return Err(self.io(ErrorKind::NotConnected.into()));
        };
        self.answered_at = None;
        match s.write_all(bytes) {
            Ok(()) => Ok(()),
            Err(e) if matches!(e.kind(), ErrorKind::BrokenPipe | ErrorKind::ConnectionReset) => {
                // The peer closed since the last exchange: the step observes the close on receive.
                self.closed = true;
                Ok(())
            }
            Err(e) => Err(self.io(e)),
        }
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            if self.closed {
                return Ok(Received::Closed {
                    partial: self.reader.partial(),
                    at: self.now(),
                });
            }
            let now = Instant::now();
            // RTU over TCP: wake at the silence deadline so silence-delimited frames complete.
            let silence = self
                .reader
                .deadline()
                .map(|d| self.start + d)
                .filter(|d| *d < deadline);
            if now >= deadline && silence.is_none() {
                self.reader.poll(self.now());
                if let Some(r) = self.reader.next() {
                    return Ok(r);
                }
                return Ok(Received::Silence {
                    partial: self.reader.partial(),
                    at: self.now(),
                });
            }
            if let Some(s) = silence
                && now >= s
            {
                self.reader.poll(self.now());
                continue;
            }
            if !self.read_once(silence.unwrap_or(deadline))? {
                self.closed = true;
                self.stream = None;
            }
        }
    }

    fn idle(&mut self, d: Duration) {
        std::thread::sleep(d);
    }

    fn has_connections(&self) -> bool {
        true
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.close_gracefully();
        self.open_retrying()
    }

    fn drain(&mut self) {
        if let Some(s) = self.stream.as_ref() {
            // Non-blocking receives (MSG_DONTWAIT) on the blocking socket: one system call when nothing is
            // stale, where switching the socket to non-blocking mode and back took two more.
            let sock = socket2::SockRef::from(s);
            let mut chunk = [MaybeUninit::<u8>::uninit(); 1024];
            // Bounded: at most 64 KiB of stale bytes are discarded.
            for _ in 0..64 {
                match sock.recv_with_flags(&mut chunk, libc::MSG_DONTWAIT) {
                    Ok(0) => {
                        self.closed = true;
                        break;
                    }
                    Ok(_) => continue,
                    Err(_) => break,
                }
            }
        }
        self.reader.clear();
    }

    fn drain_stale(&mut self) -> Vec<u8> {
        let mut stale = self.reader.partial();
        // Before every case: one system call when nothing is there (a non-blocking peek at one byte), where
        // switching the socket to non-blocking mode and back took two more.
        let waiting = self.stream.as_ref().is_some_and(|s| peek(s).is_ok());
        if let Some(s) = self.stream.as_ref().filter(|_| waiting) {
            // Non-blocking for the while: what is there is taken, nothing is waited for.
            if s.set_nonblocking(true).is_ok() {
                let mut chunk = [0u8; 1024];
                // Bounded as `drain`: at most 64 KiB.
                for _ in 0..64 {
                    match std::io::Read::read(&mut &*s, &mut chunk) {
                        Ok(0) => {
                            self.closed = true;
                            break;
                        }
                        Ok(n) => stale.extend_from_slice(&chunk[..n]),
                        Err(_) => break,
                    }
                }
                let _ = s.set_nonblocking(false);
            }
        }
        self.reader.clear();
        stale
    }

    fn describe(&self) -> String {
        self.label.clone()
    }

    fn server_port(&self) -> u16 {
        self.addr.port()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    /// A target connected to a loopback listener that is then gone (connects refused): the target, the
    /// accepted connection, and the address to listen on again.
    fn connected_then_refused() -> (TcpTarget, std::net::TcpStream, std::net::SocketAddr) {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        let t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        let (first, _) = listener.accept().expect("accept");
        (t, first, addr)
    }

    /// After `gone`, listen on `addr` again and take one connection (bounded by `within`): a drive that
    /// refused connects for a while.
    fn listen_again(
        addr: std::net::SocketAddr,
        gone: Duration,
        within: Duration,
    ) -> std::thread::JoinHandle<Option<std::net::TcpStream>> {
        std::thread::spawn(move || {
            std::thread::sleep(gone);
            let listener = TcpListener::bind(addr).expect("bind the same port again");
            listener.set_nonblocking(true).expect("nonblocking");
            let until = Instant::now() + within;
            while Instant::now() < until {
                if let Ok((s, _)) = listener.accept() {
                    return Some(s);
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            None
        })
    }

    /// A drive that frees its one connection slot a moment after the close (here: a listener that is gone for
    /// 150 ms, so connects are refused) is reconnected to, not given up on.
    #[test]
    fn a_reconnect_refused_for_a_moment_is_tried_again() {
        let (mut t, first, addr) = connected_then_refused();
        let back = listen_again(addr, Duration::from_millis(150), Duration::from_secs(3));
        t.reconnect().expect("reconnected once the slot is free");
        assert!(
            back.join().expect("thread").is_some(),
            "the new connection was accepted"
        );
        drop(first);
    }

    /// A target that took a connection and then refuses for 2 s (a link that dropped for a moment, a small
    /// stack that refuses connects while it recovers) is waited for: longer than the 0.6 s of tries a target
    /// that never took a connection gets. One that refuses for longer than [`LINK_BACK_WITHIN`] is given up
    /// after about that long, and a port nobody ever listened on is reported within the short tries.
    #[test]
    fn a_target_that_took_a_connection_is_waited_for_while_it_refuses() {
        let (mut t, first, addr) = connected_then_refused();
        let back = listen_again(addr, Duration::from_secs(2), Duration::from_secs(5));
        t.reconnect()
            .expect("reconnected once the target takes connections again");
        let second = back.join().expect("thread");
        assert!(second.is_some(), "the new connection was accepted");
        drop(first);
        // The listener is gone for good now.
        let started = Instant::now();
        let gone = t.reconnect();
        let took = started.elapsed();
        assert!(
            matches!(gone, Err(TargetError::Connect { .. })),
            "{:?}",
            gone.map(|_| ())
        );
        assert!(
            took > LINK_BACK_WITHIN - Duration::from_secs(1)
                && took < LINK_BACK_WITHIN + Duration::from_secs(2),
            "given up after {took:?}"
        );
        drop(second);
        // Never took a connection: reported after the short tries.
        let started = Instant::now();
        assert!(
            TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false).is_err()
        );
        assert!(
            started.elapsed() < Duration::from_secs(2),
            "{:?}",
            started.elapsed()
        );
    }

    /// What the peer sent unasked is taken before a case, all of it, and nothing is waited for when nothing
    /// was sent; a close seen there is remembered.
    #[test]
    fn stale_bytes_are_taken_without_waiting() {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        let (mut peer, _) = listener.accept().expect("accept");
        let started = Instant::now();
        assert!(t.drain_stale().is_empty(), "nothing was sent");
        assert!(
            started.elapsed() < Duration::from_millis(500),
            "nothing is waited for"
        );
        // More than one receive's worth, in two writes.
        let sent: Vec<u8> = (0..3000u32).map(|i| (i % 251) as u8).collect();
        peer.write_all(&sent[..1500]).expect("write");
        peer.write_all(&sent[1500..]).expect("write");
        peer.flush().expect("flush");
        // Bounded: the bytes are on loopback within 2 s.
        let until = Instant::now() + Duration::from_secs(2);
        let mut got = Vec::new();
        while got.len() < sent.len() && Instant::now() < until {
            got.extend(t.drain_stale());
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(got, sent, "every stale byte is taken, in order");
        assert!(!t.closed);
        drop(peer);
        let until = Instant::now() + Duration::from_secs(2);
        while !t.closed && Instant::now() < until {
            assert!(t.drain_stale().is_empty());
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(t.closed, "the close is seen");
    }

    /// A request that the one-slot drive below echoes back (a whole MBAP frame).
    const ECHOED: [u8; 12] = [0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 2];

    /// A drive with one connection slot, on a thread for at most 10 s: a connection that arrives while the
    /// slot is held is accepted and closed at once (its count is returned), the first `refuse_first`
    /// connections too; the one in the slot has what it sends echoed, and its client's close is noticed
    /// `notice` late (a firmware that polls its sockets), when the drive closes it and frees the slot.
    fn one_slot_drive(
        notice: Duration,
        refuse_first: usize,
    ) -> (SocketAddr, std::sync::Arc<std::sync::atomic::AtomicUsize>) {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        listener.set_nonblocking(true).expect("nonblocking");
        let refused = std::sync::Arc::new(AtomicUsize::new(0));
        let count = refused.clone();
        std::thread::spawn(move || {
            let mut slot: Option<(TcpStream, Option<Instant>)> = None;
            let mut seen = 0;
            let until = Instant::now() + Duration::from_secs(10);
            while Instant::now() < until {
                while let Ok((c, _)) = listener.accept() {
                    seen += 1;
                    if slot.is_some() || seen <= refuse_first {
                        count.fetch_add(1, Ordering::SeqCst);
                        drop(c);
                    } else {
                        c.set_nonblocking(true).expect("nonblocking");
                        slot = Some((c, None));
                    }
                }
                if let Some((c, eof)) = slot.as_mut() {
                    let mut buf = [0u8; 256];
                    match c.read(&mut buf) {
                        Ok(0) => {
                            eof.get_or_insert_with(Instant::now);
                        }
                        Ok(n) => {
                            let _ = c.write_all(&buf[..n]);
                        }
                        Err(_) => {}
                    }
                    if eof.is_some_and(|at| at.elapsed() >= notice) {
                        slot = None;
                    }
                }
                std::thread::sleep(Duration::from_millis(1));
            }
        });
        (addr, refused)
    }

    fn echoed(t: &mut TcpTarget) -> bool {
        t.send(&ECHOED).expect("send");
        matches!(t.recv(Duration::from_secs(2)), Ok(Received::Frame { bytes, .. }) if bytes == ECHOED)
    }

    /// A drive with one connection slot that frees it only when it notices the close (here 40 ms late) is
    /// served by the next connection, after a reconnect and after the target is dropped: the harness waits
    /// for the drive's own close before it connects again. Without that wait the next connection arrived
    /// while the slot was held and was closed at once.
    #[test]
    fn a_one_slot_drive_is_reconnected_to_after_it_closed_the_last_connection() {
        use std::sync::atomic::Ordering;
        let (addr, refused) = one_slot_drive(Duration::from_millis(40), 0);
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        assert!(echoed(&mut t), "the first connection is served");
        for k in 0..3 {
            t.reconnect().expect("reconnect");
            assert!(
                echoed(&mut t),
                "reconnect {k}: the next connection is served"
            );
        }
        drop(t);
        let mut again = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        assert!(echoed(&mut again), "a new target at once is served");
        assert_eq!(
            refused.load(Ordering::SeqCst),
            0,
            "a connection was refused"
        );
    }

    /// A connection the drive accepts and closes before the first request on it (its slots taken) is opened
    /// again, as a refused connect is, instead of carrying the request to a closed connection.
    #[test]
    fn a_connection_closed_before_its_first_request_is_opened_again() {
        use std::sync::atomic::Ordering;
        let (addr, refused) = one_slot_drive(Duration::ZERO, 2);
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        // The drive's close is on loopback well within this.
        std::thread::sleep(Duration::from_millis(50));
        assert!(
            echoed(&mut t),
            "the request went out on a connection the drive serves"
        );
        assert_eq!(refused.load(Ordering::SeqCst), 2, "both refusals were made");
    }

    /// A drive that closes a connection when it has been idle for 30 ms (an idle timeout) and echoes what it
    /// gets; with `close_first`, it closes its first connection as soon as anything arrives on it. On a
    /// thread for at most 10 s.
    fn idle_closing_drive(close_first: bool) -> SocketAddr {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        std::thread::spawn(move || {
            let until = Instant::now() + Duration::from_secs(10);
            let mut first = close_first;
            while Instant::now() < until {
                let Ok((mut c, _)) = listener.accept() else {
                    return;
                };
                c.set_read_timeout(Some(Duration::from_millis(30)))
                    .expect("timeout");
                let mut buf = [0u8; 256];
                while let Ok(n @ 1..) = c.read(&mut buf) {
                    if std::mem::take(&mut first) {
                        break;
                    }
                    let _ = c.write_all(&buf[..n]);
                }
            }
        });
        addr
    }

    /// The drive closed the connection while it was idle after its last answer: the next request goes out
    /// on a new connection, and is answered, instead of meeting the close (which was taken for the drive's
    /// answer to it: "the connection was closed instead of an answer").
    #[test]
    fn a_connection_the_drive_closed_while_idle_is_reopened_for_the_next_request() {
        let addr = idle_closing_drive(false);
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        assert!(echoed(&mut t), "the first request is answered");
        for k in 0..3 {
            // Past the drive's idle timeout; its close is here well within this on loopback.
            std::thread::sleep(Duration::from_millis(100));
            assert!(
                echoed(&mut t),
                "request {k} after an idle close is answered"
            );
        }
    }

    /// A close after a send with nothing back since is the drive's answer to what was sent: the rest of a
    /// request sent in pieces goes to that connection, and its receive sees the close (not an answer on a
    /// new connection).
    #[test]
    fn a_close_after_the_first_piece_of_a_request_is_the_drives_answer() {
        let addr = idle_closing_drive(true);
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        t.send(&ECHOED[..6]).expect("first piece");
        std::thread::sleep(Duration::from_millis(50));
        t.send(&ECHOED[6..]).expect("second piece");
        // (On a new connection the second piece would have been echoed, and then closed as idle.)
        assert!(
            matches!(t.recv(Duration::from_secs(2)), Ok(Received::Closed { partial, .. }) if partial.is_empty()),
            "the close was not what the request met"
        );
    }

    /// A name with several addresses (`localhost`: 127.0.0.1 and ::1, where the resolver gives both) is the
    /// first that takes a connection; a port nobody listens on is reported for the first address.
    #[test]
    fn the_first_address_that_takes_a_connection_is_the_target() {
        let live = TcpListener::bind("127.0.0.1:0").expect("bind");
        let dead = TcpListener::bind("127.0.0.1:0").expect("bind");
        let (live_addr, dead_addr) = (
            live.local_addr().expect("addr"),
            dead.local_addr().expect("addr"),
        );
        drop(dead);
        let t = TcpTarget::connect_to(&[dead_addr, live_addr], Duration::from_secs(2), false)
            .expect("connected to the second address");
        assert_eq!(t.addr, live_addr);
        assert_eq!(t.describe(), format!("tcp://{live_addr}"));
        drop(live);
        let Err(TargetError::Connect { addr, .. }) =
            TcpTarget::connect_to(&[dead_addr, live_addr], Duration::from_secs(2), false)
        else {
            panic!("connected to nobody")
        };
        assert_eq!(addr, dead_addr.to_string());
    }
}
