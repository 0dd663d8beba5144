//! RTU on a serial device (or a pty), with arrival timestamps for the framer's t1.5/t3.5 rules.
//!
//! A two-wire RS-485 adapter whose receiver stays on while it transmits gives back every byte sent (local
//! echo). With `echo=on` in the target URL each request's echo is read, compared with what was sent and
//! dropped before the answer is read; an echo that differs (a collision on the bus: another master, or a
//! device transmitting at the same time) or that does not come ends the run with an error rather than be
//! judged as the drive's answer.

use std::collections::VecDeque;
use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

use super::reader::FrameReader;
use super::{Received, Target, TargetError};
use codec::{CharFormat, Framing, Parity, RtuTiming};

/// An RTU serial line.
pub struct SerialTarget {
    path: String,
    port: Box<dyn serialport::SerialPort>,
    timing: RtuTiming,
    start: Instant,
    reader: FrameReader,
    /// With local echo: the bytes sent that the line has still to give back, and by when.
    echo: Option<Echo>,
}

/// How long after a write returns the line may take to give its last byte back, beyond the bytes' own
/// time on the line: a USB adapter holds received bytes up to its latency timer (16 ms by default on FTDI
/// chips) and the write may return before the last byte has left.
const ECHO_ALLOWANCE: Duration = Duration::from_millis(100);

/// How long a frame the length rules say is not complete waits for its next byte: the host sees a frame the
/// line carried whole in pieces, a USB adapter handing over what it received when its latency timer runs
/// out (16 ms by default on FTDI chips), a pseudo-terminal when its writer is paced or the machine busy.
/// The line's own timing (t1.5 between characters) is the drive's to keep, and the host cannot see it.
/// 50 ms: the FTDI default with room for a busy host; `byte_timeout=MS` in the URL sets another.
pub const HOST_BYTE_TIMEOUT: Duration = Duration::from_millis(50);

/// The local echo still due.
#[derive(Debug, Default)]
struct Echo {
    /// Bytes sent and not yet given back, oldest first.
    due: VecDeque<u8>,
    /// Bytes given back since the first still due was sent (for the message when the rest does not come).
    matched: usize,
    /// When the line must have given back everything due.
    by: Option<Instant>,
    /// An echo that went wrong while the target could not say so (in `drain`): the next receive returns it.
    failed: Option<String>,
    /// An echo went wrong: what is still on its way (the rest of a late echo, an answer) is let pass and
    /// discarded before the next request, so that it is not compared with that request's echo.
    resync: bool,
}

/// After an echo that went wrong, the quiet that ends the wait for stray bytes, and the longest wait.
const RESYNC_QUIET: Duration = ECHO_ALLOWANCE;
const RESYNC_MAX: Duration = Duration::from_secs(2);

impl Echo {
    /// The echo went wrong: nothing more is due, and stray bytes are let pass before the next request.
    fn abandon(&mut self) {
        self.due.clear();
        self.by = None;
        self.matched = 0;
        self.resync = true;
    }
}

impl SerialTarget {
    /// Open `path` at `baud` with `format`; a missing or busy device is named with the OS error.
    pub fn open(path: &str, baud: u32, format: CharFormat) -> Result<Self, TargetError> {
        if !std::path::Path::new(path).exists() {
            return Err(TargetError::Serial {
                path: path.into(),
                reason: "no such device".into(),
            });
        }
        let parity = match format.parity {
            Parity::None => serialport::Parity::None,
            Parity::Even => serialport::Parity::Even,
            Parity::Odd => serialport::Parity::Odd,
        };
        let stop = if format.stop_bits == 2 {
            serialport::StopBits::Two
        } else {
            serialport::StopBits::One
        };
        let port = serialport::new(path, baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(parity)
            .stop_bits(stop)
            .flow_control(serialport::FlowControl::None)
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| TargetError::Serial {
                path: path.into(),
                reason: e.to_string(),
            })?;
        let timing = RtuTiming::new(baud, format);
        Ok(Self {
            path: path.into(),
            port,
            timing,
            start: Instant::now(),
            reader: FrameReader::rtu_through_host(timing, HOST_BYTE_TIMEOUT),
            echo: None,
        })
    }

    /// Wait `timeout` (instead of [`HOST_BYTE_TIMEOUT`]) for the next byte of an answer the length rules say
    /// is not complete (`byte_timeout=MS`: an adapter whose latency timer is set longer).
    pub fn with_byte_timeout(mut self, timeout: Option<Duration>) -> Self {
        if let Some(t) = timeout {
            self.reader = FrameReader::rtu_through_host(self.timing, t);
        }
        self
    }

    /// Expect the line to give back every byte sent (`echo=on`).
    pub fn with_echo(mut self, echo: bool) -> Self {
        self.echo = echo.then(Echo::default);
        self
    }

    /// Bytes read at `at`: the echo still due is taken off the front (and checked), the rest goes to the
    /// frame reader.
    fn arrived(&mut self, at: Duration, bytes: &[u8]) -> Result<(), TargetError> {
        let mut rest = bytes;
        if let Some(e) = self.echo.as_mut() {
            while let (Some(&want), Some((&got, tail))) = (e.due.front(), rest.split_first()) {
                if want != got {
                    let msg = format!(
                        "the line's echo of the request differs from what was sent at byte {} (sent {want:02X}, read back {got:02X}): a collision on the bus (another master, or a device transmitting while the harness did), or noise; the echo was expected because of echo=on",
                        e.matched + 1
                    );
                    e.abandon();
                    return Err(self.io(std::io::Error::new(ErrorKind::InvalidData, msg)));
                }
                e.due.pop_front();
                e.matched += 1;
                rest = tail;
            }
            if e.due.is_empty() {
                e.by = None;
                e.matched = 0;
            }
        }
        if !rest.is_empty() {
            self.reader.push(at, rest);
        }
        Ok(())
    }

    /// After an echo that went wrong: read and discard until the line has been quiet for [`RESYNC_QUIET`]
    /// (at most [`RESYNC_MAX`]), so that a late echo or answer is not taken for the next request's echo.
    fn let_pass_stray_bytes(&mut self) {
        let start = Instant::now();
        let mut last = start;
        let mut chunk = [0u8; 256];
        while start.elapsed() < RESYNC_MAX {
            let quiet_for = last.elapsed();
            if quiet_for >= RESYNC_QUIET {
                break;
            }
            if self.port.set_timeout(RESYNC_QUIET - quiet_for).is_err() {
                break;
            }
            match self.port.read(&mut chunk) {
                Ok(n) if n > 0 => last = Instant::now(),
                Ok(_) => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(_) => break,
            }
        }
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        self.reader.clear();
        if let Some(e) = self.echo.as_mut() {
            e.resync = false;
        }
    }

    /// Read until the echo due has come back (nothing to do without echo).
    fn settle_echo(&mut self) -> Result<(), TargetError> {
        if let Some(msg) = self.echo.as_mut().and_then(|e| e.failed.take()) {
            return Err(self.io(std::io::Error::new(ErrorKind::InvalidData, msg)));
        }
        loop {
            let Some((by, due, matched)) = self
                .echo
                .as_ref()
                .filter(|e| !e.due.is_empty())
                .and_then(|e| Some((e.by?, e.due.len(), e.matched)))
            else {
                return Ok(());
            };
            let now = Instant::now();
            if now >= by {
                if let Some(e) = self.echo.as_mut() {
                    e.abandon();
                }
                let msg = format!(
                    "the line gave back {matched} of the {} byte(s) sent within {} ms (echo=on expects every byte sent to be read back, as a two-wire RS-485 adapter without echo suppression does): remove echo=on if the adapter does not echo",
                    matched + due,
                    (ECHO_ALLOWANCE + self.timing.transmit_time(matched + due)).as_millis()
                );
                return Err(self.io(std::io::Error::new(ErrorKind::TimedOut, msg)));
            }
            self.read_for(by - now)?;
        }
    }

    /// Wait up to `wait` (at least 100 µs) for bytes and take what came ([`SerialTarget::arrived`]).
    fn read_for(&mut self, wait: Duration) -> Result<(), TargetError> {
        let mut chunk = [0u8; 256];
        self.port
            .set_timeout(wait.max(Duration::from_micros(100)))
            .map_err(|e| self.io(std::io::Error::other(e)))?;
        match self.port.read(&mut chunk) {
            Ok(0) => Ok(()),
            Ok(n) => {
                let at = self.now();
                self.arrived(at, &chunk[..n])
            }
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                ) =>
            {
                Ok(())
            }
            Err(e) => Err(self.io(e)),
        }
    }

    fn io(&self, source: std::io::Error) -> TargetError {
        TargetError::Io {
            target: self.path.clone(),
            source,
        }
    }
}

impl Target for SerialTarget {
    fn framing(&self) -> Framing {
        Framing::Rtu
    }

    fn now(&self) -> Duration {
        self.start.elapsed()
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError> {
        if self.echo.as_ref().is_some_and(|e| e.resync) {
            self.let_pass_stray_bytes();
        }
        self.port.write_all(bytes).map_err(|e| self.io(e))?;
        self.port.flush().map_err(|e| self.io(e))?;
        let on_line = self.timing.transmit_time(bytes.len());
        if let Some(e) = self.echo.as_mut() {
            e.due.extend(bytes);
            // The allowance counts from the last piece sent: a request sent in pieces is echoed piece by piece.
            e.by = Some(Instant::now() + on_line + ECHO_ALLOWANCE);
        }
        Ok(())
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        // The answer's window opens when the request has come back whole: the echo's wait is the line's.
        self.settle_echo()?;
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(r) = self.reader.next() {
                return Ok(r);
            }
            let now = Instant::now();
            let silence = self.reader.deadline().map(|d| self.start + d);
            if let Some(s) = silence
                && now >= s
            {
                self.reader.poll(self.now());
                continue;
            }
            if now >= deadline {
                return Ok(Received::Silence {
                    partial: self.reader.partial(),
                    at: self.now(),
                });
            }
            let until = silence.map_or(deadline, |s| s.min(deadline));
            self.read_for(until.saturating_duration_since(now))?;
        }
    }

    fn idle(&mut self, d: Duration) {
        std::thread::sleep(d);
    }

    fn reconnect(&mut self) -> Result<(), TargetError> {
        self.drain();
        Ok(())
    }

    fn drain(&mut self) {
        // An echo still due is read first: cleared away, it would come after the clear and be taken for
        // an answer. What goes wrong with it is said by the next receive.
        if let Err(e) = self.settle_echo()
            && let Some(echo) = self.echo.as_mut()
        {
            echo.failed = Some(match e {
                TargetError::Io { source, .. } => source.to_string(),
                other => other.to_string(),
            });
        }
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        self.reader.clear();
    }

    fn describe(&self) -> String {
        format!(
            "rtu://{} ({} baud{})",
            self.path,
            self.timing.baud,
            if self.echo.is_some() {
                ", local echo"
            } else {
                ""
            }
        )
    }

    fn server_port(&self) -> u16 {
        0
    }

    fn rtu_timing(&self) -> Option<RtuTiming> {
        Some(self.timing)
    }

    fn answer_gap_measurable(&self) -> Result<(), String> {
        // A pseudo-terminal (socat, a simulator on a pty pair) passes bytes at once, without baud timing.
        let real = std::fs::canonicalize(&self.path).unwrap_or_else(|_| self.path.clone().into());
        if real.starts_with("/dev/pts") || real == std::path::Path::new("/dev/ptmx") {
            Err(format!(
                "{} is a pseudo-terminal: bytes pass without the line's timing",
                self.path
            ))
        } else {
            Ok(())
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use serialport::{SerialPort, TTYPort};

    /// A pty pair: the target on the slave end, the test (the adapter and the drive) on the master end.
    pub(crate) fn line(echo: bool) -> (SerialTarget, TTYPort, TTYPort) {
        let (master, slave) = TTYPort::pair().expect("a pty pair");
        let path = slave.name().expect("the slave's name");
        let t = SerialTarget::open(
            &path,
            19_200,
            CharFormat {
                parity: Parity::None,
                stop_bits: 1,
            },
        )
        .expect("open the pty")
        .with_echo(echo);
        (t, master, slave)
    }

    pub(crate) fn adu(pdu: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        codec::rtu::encode_adu(1, pdu, &mut out).expect("an RTU frame");
        out
    }

    /// What the target sent, as the master end reads it (bounded).
    pub(crate) fn sent(master: &mut TTYPort, n: usize) -> Vec<u8> {
        let mut got = vec![0u8; n];
        master.set_timeout(Duration::from_secs(2)).expect("timeout");
        master.read_exact(&mut got).expect("the request");
        got
    }

    fn frame(r: Received) -> Vec<u8> {
        match r {
            Received::Frame { bytes, .. } => bytes,
            other => panic!("not a frame: {other:?}"),
        }
    }

    /// One exchange on an echoing line: `req` sent, its echo and `answer` written back at once, and `answer`
    /// received as the frame.
    fn echoed_exchange(t: &mut SerialTarget, master: &mut TTYPort, req: &[u8], answer: &[u8]) {
        t.send(req).expect("send");
        assert_eq!(sent(master, req.len()), req);
        let mut back = req.to_vec();
        back.extend_from_slice(answer);
        master.write_all(&back).expect("echo and answer");
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
    }

    /// The echo is taken off before the answer, also where the answer is the request again (FC 06 answers
    /// with its request) and where echo and answer come in one piece or byte by byte.
    #[test]
    fn the_echo_is_dropped_and_the_answer_read_even_when_it_equals_the_request() {
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        let answer = adu(&[0x03, 0x02, 0x12, 0x34]);
        let write = adu(&[0x06, 0x00, 0x10, 0xAB, 0xCD]);
        let (mut t, mut master, _slave) = line(true);
        for (req, ans) in [(&read, &answer), (&write, &write)] {
            echoed_exchange(&mut t, &mut master, req, ans);
        }
        // Byte by byte, the echo's last byte and the answer's first in one write.
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        let mut back = read.clone();
        back.extend_from_slice(&answer);
        let (head, tail) = back.split_at(read.len() - 1);
        for b in head {
            master.write_all(&[*b]).expect("a byte of the echo");
        }
        master.write_all(tail).expect("the rest");
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
        // A silent drive: silence with nothing partial, the echo not counted as part of an answer.
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master.write_all(&read).expect("the echo only");
        match t.recv(Duration::from_millis(50)).expect("recv") {
            Received::Silence { partial, .. } => assert!(partial.is_empty(), "{partial:02X?}"),
            other => panic!("not silence: {other:?}"),
        }
    }

    /// An answer the host gets in pieces (a USB adapter's latency timer, a paced writer) is one frame when the
    /// pieces come within [`HOST_BYTE_TIMEOUT`], however far past the line's t3.5 (1.8 ms at 19,200 baud);
    /// an answer that stops inside the length its rules give is discarded once that wait is out, and a
    /// complete answer is taken at once. An independent SD2x writing each byte at the line's pace through
    /// socat gave 32 false FAILs with t3.5 as the host's wait (tests/independent/sd2x-j).
    #[test]
    fn an_answer_in_pieces_is_one_frame_and_a_cut_one_is_discarded_after_the_hosts_wait() {
        let read = adu(&[0x03, 0x07, 0xD0, 0x00, 0x02]);
        let answer = adu(&[0x03, 0x04, 0x00, 0x50, 0x12, 0x34]);
        let (mut t, mut master, _slave) = line(false);
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        let mut writer = master.try_clone_native().expect("a second handle");
        let pieces = answer.clone();
        let paced = std::thread::spawn(move || {
            for (i, byte) in pieces.iter().enumerate() {
                writer.write_all(&[*byte]).expect("a byte");
                std::thread::sleep(Duration::from_millis(if i % 2 == 0 { 3 } else { 12 }));
            }
        });
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
        paced.join().expect("the writer");
        // Cut after 5 of its 9 bytes: garbage once the host's wait passes without the rest, not a frame.
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master.write_all(&answer[..5]).expect("the first bytes");
        let started = Instant::now();
        match t.recv(Duration::from_secs(1)).expect("recv") {
            Received::Garbage { bytes, .. } => assert_eq!(bytes, answer[..5]),
            other => panic!("not garbage: {other:?}"),
        }
        assert!(
            started.elapsed() >= HOST_BYTE_TIMEOUT,
            "{:?}",
            started.elapsed()
        );
        // Whole: taken without waiting for any silence.
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master.write_all(&answer).expect("the answer");
        let started = Instant::now();
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
        assert!(
            started.elapsed() < HOST_BYTE_TIMEOUT,
            "{:?}",
            started.elapsed()
        );
        // `byte_timeout=200`: pieces 100 ms apart are still one answer.
        let (t, mut master, _slave) = line(false);
        let mut t = t.with_byte_timeout(Some(Duration::from_millis(200)));
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        let mut writer = master.try_clone_native().expect("a second handle");
        let pieces = answer.clone();
        let paced = std::thread::spawn(move || {
            writer.write_all(&pieces[..4]).expect("the first piece");
            std::thread::sleep(Duration::from_millis(100));
            writer.write_all(&pieces[4..]).expect("the rest");
        });
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
        paced.join().expect("the writer");
    }

    /// Without echo=on the echo is what the target hears first: the frame the cases would judge (which is why
    /// the pre-flight names it and says to add echo=on).
    #[test]
    fn without_echo_on_the_echo_is_heard_as_a_frame() {
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        let (mut t, mut master, _slave) = line(false);
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master.write_all(&read).expect("echo");
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), read);
    }

    /// An echo that differs is an error naming the byte (never an answer); the stray bytes behind it are let
    /// pass before the next request, which then works as before.
    #[test]
    fn an_echo_that_differs_is_an_error_and_the_line_is_usable_after_it() {
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        let answer = adu(&[0x03, 0x02, 0x12, 0x34]);
        let (mut t, mut master, _slave) = line(true);
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        let mut garbled = read.clone();
        garbled[1] ^= 0x01;
        garbled.extend_from_slice(&answer);
        master.write_all(&garbled[..2]).expect("a garbled echo");
        let e = t.recv(Duration::from_secs(1)).expect_err("a collision");
        let msg = e.to_string();
        assert!(
            msg.contains("differs from what was sent at byte 2 (sent 03, read back 02)")
                && msg.contains("collision"),
            "{msg}"
        );
        // The rest of the garbled transaction comes after: not the next request's echo.
        master.write_all(&garbled[2..]).expect("the rest");
        let read = adu(&[0x04, 0x00, 0x00, 0x00, 0x01]);
        let answer = adu(&[0x04, 0x02, 0x56, 0x78]);
        echoed_exchange(&mut t, &mut master, &read, &answer);
    }

    /// An echo that does not come is an error within the bytes' time on the line and the allowance, named
    /// as such; a late one is not compared with the next request's.
    #[test]
    fn an_echo_that_does_not_come_is_an_error_and_a_late_one_is_let_pass() {
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        let answer = adu(&[0x03, 0x02, 0x12, 0x34]);
        let (mut t, mut master, _slave) = line(true);
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master
            .write_all(&read[..3])
            .expect("three bytes of the echo");
        let began = Instant::now();
        let e = t.recv(Duration::from_secs(5)).expect_err("no whole echo");
        let waited = began.elapsed();
        assert!(
            e.to_string()
                .contains("gave back 3 of the 8 byte(s) sent within 104 ms"),
            "{e}"
        );
        assert!(
            waited < Duration::from_secs(1),
            "waited {waited:?}, not the receive's 5 s"
        );
        // The rest of the echo and an answer come late.
        master.write_all(&read[3..]).expect("the late rest");
        master.write_all(&answer).expect("a late answer");
        echoed_exchange(&mut t, &mut master, &read, &answer);
    }

    /// A request sent in pieces is echoed piece by piece; `drain` between them waits for the echo due
    /// instead of clearing it away (it would then be read as an answer).
    #[test]
    fn pieces_and_drains_keep_the_echo_apart_from_the_answer() {
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        let answer = adu(&[0x03, 0x02, 0x12, 0x34]);
        let (mut t, mut master, _slave) = line(true);
        let (a, b) = read.split_at(3);
        t.send(a).expect("first piece");
        assert_eq!(sent(&mut master, a.len()), a);
        master.write_all(a).expect("its echo");
        t.send(b).expect("second piece");
        assert_eq!(sent(&mut master, b.len()), b);
        master.write_all(b).expect("its echo");
        master.write_all(&answer).expect("the answer");
        assert_eq!(frame(t.recv(Duration::from_secs(1)).expect("recv")), answer);
        // A drain where the echo has come but was not read yet: it is read as the echo, not cleared away
        // (the next request's echo would then be compared with it).
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        master.write_all(&read).expect("the echo");
        std::thread::sleep(Duration::from_millis(20));
        t.drain();
        let other = adu(&[0x04, 0x00, 0x00, 0x00, 0x01]);
        let other_answer = adu(&[0x04, 0x02, 0x56, 0x78]);
        echoed_exchange(&mut t, &mut master, &other, &other_answer);
        // A drain while an echo is still on its way.
        t.send(&read).expect("send");
        sent(&mut master, read.len());
        let writer = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            master.write_all(&read).expect("a late echo");
            master
        });
        t.drain();
        let mut master = writer.join().expect("the writer");
        let read = adu(&[0x03, 0x00, 0x00, 0x00, 0x01]);
        echoed_exchange(&mut t, &mut master, &read, &answer);
    }
}
