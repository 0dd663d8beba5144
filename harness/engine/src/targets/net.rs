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
}

fn resolve(host: &str, port: u16) -> Result<SocketAddr, TargetError> {
    let addr = format!("{host}:{port}");
    (host, port)
        .to_socket_addrs()
        .map_err(|e| TargetError::Resolve {
            addr: addr.clone(),
            reason: e.to_string(),
        })?
        .next()
        .ok_or(TargetError::Resolve {
            addr,
            reason: "no address".into(),
        })
}

/// Connection attempts while the target refuses (see `open_retrying`).
const RECONNECT_TRIES: usize = 6;
/// Waits shorter than this are made with ppoll (see `TcpTarget::read_once`).
const SHORT_WAIT: Duration = Duration::from_millis(20);

/// Nominal timing for RTU over TCP: frames are cut by length rules and CRC; silence only ends unknown ones.
fn rtu_over_tcp_timing() -> RtuTiming {
    RtuTiming::tcp_carrier()
}

impl TcpTarget {
    /// Connect within `timeout`; `rtu` selects RTU-over-TCP framing.
    pub fn connect(
        host: &str,
        port: u16,
        timeout: Duration,
        rtu: bool,
    ) -> Result<Self, TargetError> {
        let addr = resolve(host, port)?;
        let mut t = Self {
            addr,
            label: format!("{}://{addr}", if rtu { "rtu+tcp" } else { "tcp" }),
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
        };
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
        Ok(())
    }

    /// Open, trying again while the connection is refused or reset: a drive with one connection slot (the
    /// TCP guide leaves the number to the device, 4.4.2.1) may refuse a connection until it has freed the one
    /// just closed (the harness closes and reopens between cases, and after reading the identification).
    /// At most RECONNECT_TRIES attempts over about 0.6 s; a port nobody listens on is reported that much later.
    fn open_retrying(&mut self) -> Result<(), TargetError> {
        let mut wait = Duration::from_millis(20);
        for _ in 1..RECONNECT_TRIES {
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
                    wait *= 2;
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
            use std::os::fd::AsFd;
            let mut fds = [nix::poll::PollFd::new(
                s.as_fd(),
                nix::poll::PollFlags::POLLIN,
            )];
            let timeout = nix::sys::time::TimeSpec::from_duration(left);
            match nix::poll::ppoll(&mut fds, Some(timeout), None) {
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
                let now = self.start.elapsed();
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

impl Target for TcpTarget {
    fn end_sending(&mut self) -> Result<bool, TargetError> {
        let Some(s) = self.stream.as_ref() else {
            return Ok(false);
        };
        match s.shutdown(std::net::Shutdown::Write) {
            Ok(()) => Ok(true),
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
        if self.closed {
            self.open_retrying()?;
        }
        let Some(s) = self.stream.as_mut() else {
            return Err(self.io(ErrorKind::NotConnected.into()));
        };
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
        if let Some(s) = self.stream.take() {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
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
        let waiting = self.stream.as_ref().is_some_and(|s| {
            let mut probe = [MaybeUninit::<u8>::uninit(); 1];
            socket2::SockRef::from(s)
                .recv_with_flags(&mut probe, libc::MSG_PEEK | libc::MSG_DONTWAIT)
                .is_ok()
        });
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

    /// A drive that frees its one connection slot a moment after the close (here: a listener that is gone for
    /// 150 ms, so connects are refused) is reconnected to, not given up on.
    #[test]
    fn a_reconnect_refused_for_a_moment_is_tried_again() {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        let mut t = TcpTarget::connect("127.0.0.1", addr.port(), Duration::from_secs(2), false)
            .expect("connect");
        let (first, _) = listener.accept().expect("accept");
        drop(listener);
        let back = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(150));
            let listener = TcpListener::bind(addr).expect("bind the same port again");
            listener.set_nonblocking(true).expect("nonblocking");
            // Bounded: one connection within 3 s.
            let until = Instant::now() + Duration::from_secs(3);
            while Instant::now() < until {
                if let Ok((s, _)) = listener.accept() {
                    return Some(s);
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            None
        });
        t.reconnect().expect("reconnected once the slot is free");
        assert!(
            back.join().expect("thread").is_some(),
            "the new connection was accepted"
        );
        drop(first);
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
}
