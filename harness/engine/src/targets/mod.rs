//! Targets: raw bytes in and out with timestamps. TCP, RTU over TCP, RTU on a serial line, and the
//! in-process reference drive. Blocking I/O with deadlines: the runner exchanges one step at a time.

pub mod device;
mod line;
pub mod net;
mod reader;
pub mod serial;
pub mod sim;
pub mod url;

use std::time::Duration;

use codec::Framing;

pub use url::{TargetUrl, UrlError};

/// What one receive produced: the observation of a step. Reports serialize it as
/// `{"kind": "frame", "bytes": "..."}` etc.; the timestamps stay in the case's wire log.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Received {
    /// A complete frame (by MBAP length, or by RTU length rules + CRC, or by silence).
    Frame {
        #[serde(serialize_with = "crate::observe::hex_bytes")]
        bytes: Vec<u8>,
        #[serde(skip)]
        first_at: Duration,
        #[serde(skip)]
        last_at: Duration,
        /// Largest silence between two bytes of the frame.
        #[serde(skip)]
        max_gap: Duration,
    },
    /// Nothing complete before the deadline; `partial` holds bytes of an incomplete frame.
    Silence {
        #[serde(skip)]
        partial: Vec<u8>,
        #[serde(skip)]
        at: Duration,
    },
    /// The peer closed the connection.
    Closed {
        #[serde(skip)]
        partial: Vec<u8>,
        #[serde(skip)]
        at: Duration,
    },
    /// Bytes that cannot be a frame (bad CRC after silence, impossible MBAP length).
    Garbage {
        #[serde(serialize_with = "crate::observe::hex_bytes")]
        bytes: Vec<u8>,
        #[serde(skip)]
        at: Duration,
        reason: String,
    },
}

impl Received {
    /// A frame with no timing (tests, reconstructed observations).
    pub fn frame(bytes: Vec<u8>) -> Self {
        Received::Frame {
            bytes,
            first_at: Duration::ZERO,
            last_at: Duration::ZERO,
            max_gap: Duration::ZERO,
        }
    }

    /// Silence with nothing partial.
    pub fn silence() -> Self {
        Received::Silence {
            partial: Vec::new(),
            at: Duration::ZERO,
        }
    }

    /// When the observation ended (the frame's first byte for a frame).
    pub fn at(&self) -> Duration {
        match self {
            Received::Frame { first_at, .. } => *first_at,
            Received::Silence { at, .. }
            | Received::Closed { at, .. }
            | Received::Garbage { at, .. } => *at,
        }
    }
}

/// Why a target could not be used.
#[derive(Debug, thiserror::Error)]
pub enum TargetError {
    #[error(transparent)]
    Url(#[from] UrlError),
    #[error("cannot connect to {addr}: {source}")]
    Connect {
        addr: String,
        source: std::io::Error,
    },
    #[error("cannot resolve {addr}: {reason}")]
    Resolve { addr: String, reason: String },
    #[error("cannot open serial port {path}: {reason}")]
    Serial { path: String, reason: String },
    #[error(transparent)]
    Profile(#[from] drives::corpus::CorpusError),
    #[error("I/O error on {target}: {source}")]
    Io {
        target: String,
        source: std::io::Error,
    },
}

/// A Modbus endpoint the runner talks to.
pub trait Target {
    /// How frames are delimited on this target.
    fn framing(&self) -> Framing;
    /// Time since the target was opened (virtual on `sim:`).
    fn now(&self) -> Duration;
    /// Send bytes in one write.
    fn send(&mut self, bytes: &[u8]) -> Result<(), TargetError>;
    /// Wait up to `timeout` for one frame.
    fn recv(&mut self, timeout: Duration) -> Result<Received, TargetError>;
    /// Let `d` pass with the line idle.
    fn idle(&mut self, d: Duration);
    /// Close and reopen the connection (no-op on a serial line).
    fn reconnect(&mut self) -> Result<(), TargetError>;
    /// Whether [`Target::reconnect`] opens a new connection to a peer that may treat it apart from the old
    /// one (TCP; not a serial line, nor the in-process drive).
    fn has_connections(&self) -> bool {
        false
    }
    /// Discard whatever arrived unasked (late answers of an earlier case).
    fn drain(&mut self);
    /// Half-close the connection: tell the peer that nothing more will be sent on it (TCP FIN), while its
    /// answers can still be read. The next `send` needs a `reconnect` first. False where the target has no
    /// such thing (the default).
    fn end_sending(&mut self) -> Result<bool, TargetError> {
        Ok(false)
    }
    /// Discard whatever arrived unasked, returning those bytes where the target can tell them (a late
    /// answer is then attributed to its request by the runner); by default they are only discarded.
    fn drain_stale(&mut self) -> Vec<u8> {
        self.drain();
        Vec::new()
    }
    /// A description for reports.
    fn describe(&self) -> String;
    /// The server port for the pcap (502 when there is none).
    fn server_port(&self) -> u16 {
        502
    }
    /// The RTU line timing, when the target has one that is real (serial lines).
    fn rtu_timing(&self) -> Option<codec::RtuTiming> {
        None
    }

    /// RTU over TCP: the silence the device behind the connection needs to end a frame, when the user gave
    /// it (`rtu+tcp://HOST:PORT?gap=MS`).
    fn resync_gap(&self) -> Option<Duration> {
        None
    }

    /// Whether the silence before an answer can be measured on this target (see [`crate::timing`]), and if
    /// not, why.
    fn answer_gap_measurable(&self) -> Result<(), String> {
        Err(
            "no serial line on this transport (RTU over TCP carries frames without line timing)"
                .into(),
        )
    }
}

/// Open the target a URL names; `sim:` needs the run's profile and unit.
pub fn open(
    url: &TargetUrl,
    sim_station: impl FnOnce(&str) -> Result<drives::Station, drives::corpus::CorpusError>,
    connect_timeout: Duration,
) -> Result<Box<dyn Target>, TargetError> {
    Ok(match url {
        TargetUrl::Tcp { host, port } => Box::new(net::TcpTarget::connect(
            host,
            *port,
            connect_timeout,
            false,
        )?),
        TargetUrl::RtuOverTcp { host, port, gap_ms } => Box::new(
            net::TcpTarget::connect(host, *port, connect_timeout, true)?
                .with_resync_gap(gap_ms.map(|g| Duration::from_millis(u64::from(g)))),
        ),
        TargetUrl::Serial {
            path,
            baud,
            format,
            echo,
            byte_timeout_ms,
        } => Box::new(
            serial::SerialTarget::open(path, *baud, *format)?
                .with_echo(*echo)
                .with_byte_timeout(byte_timeout_ms.map(|t| Duration::from_millis(u64::from(t)))),
        ),
        TargetUrl::Sim { profile, rtu } => {
            // The drive under test: nobody takes its decisions (the reference's are the oracle's).
            let station = sim_station(profile)?.forgetting_decisions();
            match rtu {
                None => Box::new(sim::SimTarget::new(station)),
                Some(r) => {
                    let framing = if *r { Framing::Rtu } else { Framing::Tcp };
                    Box::new(sim::SimTarget::with_framing(station, framing, None))
                }
            }
        }
    })
}
