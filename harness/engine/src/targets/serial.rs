//! RTU on a serial device (or a pty), with arrival timestamps for the framer's t1.5/t3.5 rules.

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
            reader: FrameReader::rtu(timing),
        })
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
        self.port.write_all(bytes).map_err(|e| self.io(e))?;
        self.port.flush().map_err(|e| self.io(e))
    }

    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError> {
        let deadline = Instant::now() + timeout;
        let mut chunk = [0u8; 256];
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
            let wait = until
                .saturating_duration_since(now)
                .max(Duration::from_micros(100));
            self.port
                .set_timeout(wait)
                .map_err(|e| self.io(std::io::Error::other(e)))?;
            match self.port.read(&mut chunk) {
                Ok(0) => {}
                Ok(n) => {
                    let at = self.now();
                    self.reader.push(at, &chunk[..n]);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.io(e)),
            }
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
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        self.reader.clear();
    }

    fn describe(&self) -> String {
        format!("rtu://{} ({} baud)", self.path, self.timing.baud)
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
