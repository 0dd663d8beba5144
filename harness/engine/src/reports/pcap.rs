//! `session.pcapng`: every wire event as a TCP segment of a synthetic connection, one connection per case.
//!
//! Each case with traffic gets a new connection `127.0.0.1:<client port>` ↔ `127.0.0.1:<server port>` (client
//! ports cycle through 40000..44000, a range no Wireshark dissector claims), opened with a three-way
//! handshake at the case's first event and closed with FIN/ACK after its last one; sequence and
//! acknowledgement numbers follow the bytes. Packet times are the run's start plus `WireEvent::at`
//! (nanosecond resolution). Each harness write is a segment of its own (a split on purpose stays visible);
//! consecutive reads of the target are one segment at the time of the first read, because a reader's
//! chunking is not the target's segmentation and Wireshark cannot reassemble RTU frames from pieces
//! shorter than 5 bytes (the JSON and HTML wire logs keep every read).
//!
//! Packet comments mark the first packet of each case (`case <id>: <verdict>`), every frame sent malformed
//! on purpose (`malformed on purpose: <case id>`), a request written in pieces, and any frame that the
//! harness's strict codec rejects. Modbus/TCP runs carry MBAP frames, RTU runs (serial or over TCP) RTU
//! frames; see [`super::pcap_decode_args`] for the tshark options.

use std::borrow::Cow;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use etherparse::PacketBuilder;
use pcap_file::DataLink;
use pcap_file::pcapng::PcapNgWriter;
use pcap_file::pcapng::blocks::enhanced_packet::{EnhancedPacketBlock, EnhancedPacketOption};
use pcap_file::pcapng::blocks::interface_description::{
    InterfaceDescriptionBlock, InterfaceDescriptionOption,
};
use pcap_file::pcapng::blocks::section_header::{SectionHeaderBlock, SectionHeaderOption};

use super::{
    PCAP_FILE, RunInfo, Sink, Summary, Transport, partial_path, pcap_decode_args, pcap_server_port,
    promote, with_path,
};
use crate::{Case, CaseResult, Dir, WireEvent};
use codec::{Direction, Framing, decode_any, tcp};

/// First synthetic client port.
pub const CLIENT_PORT_BASE: u16 = 40_000;
/// Number of client ports used before they are reused.
pub const CLIENT_PORTS: u16 = 4_000;
/// Largest TCP payload per packet; longer writes are cut into several segments.
const MSS: usize = 1460;
const CLIENT_MAC: [u8; 6] = [0x02, 0, 0, 0, 0, 0x01];
const SERVER_MAC: [u8; 6] = [0x02, 0, 0, 0, 0, 0x02];
const LOOPBACK: [u8; 4] = [127, 0, 0, 1];
const WINDOW: u16 = 65_535;

/// Writes `session.pcapng`.
pub struct PcapSink {
    dir: PathBuf,
    partial: PathBuf,
    pcap: Option<PcapNgWriter<BufWriter<File>>>,
    start: Duration,
    server_port: u16,
    framing: Framing,
    connections: u64,
    /// Reused packet buffer.
    packet: Vec<u8>,
}

/// TCP flags of a synthetic segment.
#[derive(Clone, Copy, Default)]
struct Flags {
    syn: bool,
    ack: bool,
    psh: bool,
    fin: bool,
}

/// The state of one synthetic connection.
struct Conn {
    client_port: u16,
    /// Next sequence number of the client and of the server.
    client_seq: u32,
    server_seq: u32,
}

impl PcapSink {
    /// Start `session.pcapng.partial` in `dir`: section header (with the run info) and one Ethernet interface.
    pub fn create(dir: &Path, info: &RunInfo) -> io::Result<Self> {
        let partial = partial_path(dir, PCAP_FILE);
        let file = File::create(&partial).map_err(with_path("cannot create", &partial))?;
        let comment = format!(
            "modbus-harness run: target {}, profile {}, transport {}, command line: {}{}; synthetic TCP, decode with: tshark -r {PCAP_FILE} {}",
            info.target,
            info.profile,
            info.transport,
            info.command_line,
            info.seed.map(|s| format!(", seed {s}")).unwrap_or_default(),
            pcap_decode_args(info).join(" ")
        );
        let section = SectionHeaderBlock {
            options: vec![
                SectionHeaderOption::UserApplication(Cow::Owned(format!(
                    "modbus-harness {}",
                    info.harness_version
                ))),
                SectionHeaderOption::Comment(Cow::Owned(comment)),
            ],
            ..Default::default()
        };
        let mut pcap = PcapNgWriter::with_section_header(
            BufWriter::with_capacity(super::STREAM_BUFFER, file),
            section,
        )
        .map_err(pcap_error(&partial))?;
        let interface = InterfaceDescriptionBlock {
            linktype: DataLink::ETHERNET,
            snaplen: 65_535,
            options: vec![
                InterfaceDescriptionOption::IfName(Cow::Borrowed("modbus-harness synthetic")),
                // pcap-file writes EPB timestamps in nanoseconds.
                InterfaceDescriptionOption::IfTsResol(9),
            ],
        };
        pcap.write_pcapng_block(interface)
            .map_err(pcap_error(&partial))?;
        let framing = match info.transport {
            Transport::Tcp => Framing::Tcp,
            Transport::Rtu | Transport::RtuOverTcp => Framing::Rtu,
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            partial,
            pcap: Some(pcap),
            start: Duration::from_millis(info.started_unix_ms),
            server_port: pcap_server_port(info),
            framing,
            connections: 0,
            packet: Vec::with_capacity(MSS + 64),
        })
    }

    fn new_conn(&mut self) -> Conn {
        let n = self.connections;
        self.connections += 1;
        let mut client_port = CLIENT_PORT_BASE + (n % u64::from(CLIENT_PORTS)) as u16;
        if client_port == self.server_port {
            client_port = CLIENT_PORT_BASE + CLIENT_PORTS;
        }
        // Distinct initial sequence numbers per connection, as a real stack would choose.
        let isn = (n as u32).wrapping_mul(0x9E37_79B9) ^ 0x1000_0000;
        Conn {
            client_port,
            client_seq: isn,
            server_seq: isn ^ 0x5A5A_5A5A,
        }
    }

    /// Write one segment from the client (`from_client`) or the server, and advance the sequence numbers.
    fn segment(
        &mut self,
        conn: &mut Conn,
        at: Duration,
        from_client: bool,
        flags: Flags,
        payload: &[u8],
        comment: Option<String>,
    ) -> io::Result<()> {
        let (src_mac, dst_mac, sport, dport, seq, ack) = if from_client {
            (
                CLIENT_MAC,
                SERVER_MAC,
                conn.client_port,
                self.server_port,
                conn.client_seq,
                conn.server_seq,
            )
        } else {
            (
                SERVER_MAC,
                CLIENT_MAC,
                self.server_port,
                conn.client_port,
                conn.server_seq,
                conn.client_seq,
            )
        };
        let mut builder = PacketBuilder::ethernet2(src_mac, dst_mac)
            .ipv4(LOOPBACK, LOOPBACK, 64)
            .tcp(sport, dport, seq, WINDOW);
        if flags.syn {
            builder = builder.syn();
        }
        if flags.ack {
            builder = builder.ack(ack);
        }
        if flags.psh {
            builder = builder.psh();
        }
        if flags.fin {
            builder = builder.fin();
        }
        self.packet.clear();
        builder
            .write(&mut self.packet, payload)
            .map_err(|e| io::Error::other(format!("cannot build a TCP packet: {e}")))?;
        let consumed = payload.len() as u32 + u32::from(flags.syn) + u32::from(flags.fin);
        if from_client {
            conn.client_seq = conn.client_seq.wrapping_add(consumed);
        } else {
            conn.server_seq = conn.server_seq.wrapping_add(consumed);
        }
        let block = EnhancedPacketBlock {
            interface_id: 0,
            timestamp: self.start + at,
            original_len: self.packet.len() as u32,
            data: Cow::Borrowed(&self.packet),
            options: comment
                .map(|c| vec![EnhancedPacketOption::Comment(Cow::Owned(c))])
                .unwrap_or_default(),
        };
        let partial = &self.partial;
        let pcap = self.pcap.as_mut().ok_or_else(|| {
            io::Error::other(format!("{}: report already finished", partial.display()))
        })?;
        pcap.write_pcapng_block(block)
            .map(|_| ())
            .map_err(pcap_error(partial))
    }

    /// The comment for a run of reads or writes in one direction that the codec rejects, if it does.
    ///
    /// Each piece is a frame (or several Modbus/TCP frames) of its own: fine. Else the pieces together
    /// must be one frame: a request written in pieces is named as such (Wireshark may show the pieces
    /// undecoded), anything else is not valid Modbus.
    fn group_problem(
        &self,
        group: &[&WireEvent],
        bytes: &[u8],
        from_client: bool,
        id: &str,
    ) -> Option<String> {
        let (direction, what) = if from_client {
            (Direction::Request, "request")
        } else {
            (Direction::Response, "response")
        };
        if group
            .iter()
            .all(|e| self.decode_problem(&e.bytes, direction).is_none())
        {
            return None;
        }
        match self.decode_problem(bytes, direction) {
            None if from_client => Some(format!("request written in {} pieces: {id}", group.len())),
            None => None,
            Some(p) => Some(format!(
                "not a valid Modbus {what} (harness codec: {p}): {id}"
            )),
        }
    }

    /// Why the harness's strict codec rejects `bytes`, if it does (Modbus/TCP reads may hold several ADUs).
    fn decode_problem(&self, bytes: &[u8], direction: Direction) -> Option<String> {
        let whole = match decode_any(bytes, self.framing, direction) {
            Ok(_) => return None,
            Err(e) => e,
        };
        if self.framing == Framing::Tcp {
            let mut rest = bytes;
            while !rest.is_empty() {
                match tcp::adu_len(rest) {
                    Some(n) if n <= rest.len() && n > 0 => {
                        if let Err(e) = decode_any(&rest[..n], self.framing, direction) {
                            return Some(e.to_string());
                        }
                        rest = &rest[n..];
                    }
                    _ => return Some(whole.to_string()),
                }
            }
            return None;
        }
        Some(whole.to_string())
    }
}

impl Sink for PcapSink {
    fn case(&mut self, _case: &Case, result: &CaseResult) -> io::Result<()> {
        let events: Vec<&WireEvent> = result.wire.iter().filter(|e| !e.bytes.is_empty()).collect();
        let (Some(first), Some(last)) = (events.first(), events.last()) else {
            return Ok(());
        };
        let (t0, t_end) = (first.at, last.at);
        let mut conn = self.new_conn();
        let syn = Flags {
            syn: true,
            ..Flags::default()
        };
        let syn_ack = Flags {
            syn: true,
            ack: true,
            ..Flags::default()
        };
        let ack = Flags {
            ack: true,
            ..Flags::default()
        };
        let data = Flags {
            ack: true,
            psh: true,
            ..Flags::default()
        };
        let fin = Flags {
            ack: true,
            fin: true,
            ..Flags::default()
        };
        let label = format!("case {}: {}", result.id, result.verdict);
        self.segment(&mut conn, t0, true, syn, &[], Some(label))?;
        self.segment(&mut conn, t0, false, syn_ack, &[], None)?;
        self.segment(&mut conn, t0, true, ack, &[], None)?;
        // Consecutive reads or writes in one direction are checked together (a frame may come in pieces).
        let mut i = 0;
        while i < events.len() {
            let dir = events[i].dir;
            let end = events[i..]
                .iter()
                .position(|e| e.dir != dir)
                .map_or(events.len(), |n| i + n);
            let group = &events[i..end];
            let from_client = dir == Dir::Tx;
            let bytes: Vec<u8> = group.iter().flat_map(|e| e.bytes.iter().copied()).collect();
            let mut problem = if group.iter().any(|e| e.intended_malformed) {
                None
            } else {
                self.group_problem(group, &bytes, from_client, &result.id)
            };
            if from_client {
                for e in group {
                    let mut comment = if e.intended_malformed {
                        Some(format!("malformed on purpose: {}", result.id))
                    } else {
                        problem.take()
                    };
                    for chunk in e.bytes.chunks(MSS) {
                        self.segment(&mut conn, e.at, true, data, chunk, comment.take())?;
                    }
                }
            } else {
                // How a reader chunked the target's bytes says nothing about the target's segments, and
                // Wireshark cannot reassemble RTU frames from pieces of fewer than 5 bytes: one segment
                // (or MSS-sized segments) at the time of the first piece. The wire log keeps every read.
                for chunk in bytes.chunks(MSS) {
                    self.segment(&mut conn, group[0].at, false, data, chunk, problem.take())?;
                }
            }
            i = end;
        }
        self.segment(&mut conn, t_end, true, fin, &[], None)?;
        self.segment(&mut conn, t_end, false, fin, &[], None)?;
        self.segment(&mut conn, t_end, true, ack, &[], None)
    }

    fn flush(&mut self) -> io::Result<()> {
        match self.pcap.as_mut() {
            Some(pcap) => pcap
                .get_mut()
                .flush()
                .map_err(with_path("cannot write", &self.partial)),
            None => Ok(()),
        }
    }

    fn finish(&mut self, _summary: &Summary) -> io::Result<()> {
        let pcap = self.pcap.take().ok_or_else(|| {
            io::Error::other(format!(
                "{}: report already finished",
                self.partial.display()
            ))
        })?;
        let mut out = pcap.into_inner();
        out.flush()
            .map_err(with_path("cannot write", &self.partial))?;
        drop(out);
        promote(&self.partial, &self.dir.join(PCAP_FILE))
    }
}

fn pcap_error(path: &Path) -> impl FnOnce(pcap_file::PcapError) -> io::Error {
    let path = path.to_path_buf();
    move |e| {
        let e = match e {
            pcap_file::PcapError::IoError(e) => e,
            other => io::Error::other(other.to_string()),
        };
        io::Error::new(e.kind(), format!("cannot write {}: {e}", path.display()))
    }
}
