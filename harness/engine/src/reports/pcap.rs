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
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};
use std::time::Duration;

use pcap_file::DataLink;
use pcap_file::pcapng::PcapNgWriter;
use pcap_file::pcapng::blocks::enhanced_packet::{EnhancedPacketBlock, EnhancedPacketOption};
use pcap_file::pcapng::blocks::interface_description::{
    InterfaceDescriptionBlock, InterfaceDescriptionOption,
};
use pcap_file::pcapng::blocks::section_header::{SectionHeaderBlock, SectionHeaderOption};

use super::{
    Buffered, PCAP_FILE, RunInfo, Sink, Stream, Summary, Transport, pcap_decode_args,
    pcap_server_port, promote,
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
    /// `session.pcapng.partial`.
    pcap: Stream<PcapNgWriter<BufWriter<File>>>,
    start: Duration,
    server_port: u16,
    framing: Framing,
    connections: u64,
    /// Reused packet buffer.
    packet: Vec<u8>,
}

/// TCP flags of a synthetic segment.
#[derive(Clone, Copy, Debug, Default)]
struct Flags {
    syn: bool,
    ack: bool,
    psh: bool,
    fin: bool,
}

/// One Ethernet II / IPv4 / TCP packet from loopback to loopback carrying `payload`, appended to `out`:
/// the headers written here, with their checksums, byte for byte as `etherparse::PacketBuilder` writes
/// them (a unit test compares the two), at a fifth of its cost (it was a third of what the pcap file cost,
/// BENCHMARKS.md, issue 17 item 3).
fn tcp_packet(
    out: &mut Vec<u8>,
    (src_mac, dst_mac): ([u8; 6], [u8; 6]),
    (sport, dport): (u16, u16),
    seq: u32,
    ack: Option<u32>,
    flags: Flags,
    payload: &[u8],
) -> io::Result<()> {
    const IP_HEADER: usize = 20;
    const TCP_HEADER: usize = 20;
    let tcp_len = TCP_HEADER + payload.len();
    let total = u16::try_from(IP_HEADER + tcp_len)
        .map_err(|_| io::Error::other("cannot build a TCP packet: payload too long for IPv4"))?;
    out.reserve(14 + usize::from(total));
    // Ethernet II, type IPv4.
    out.extend_from_slice(&dst_mac);
    out.extend_from_slice(&src_mac);
    out.extend_from_slice(&[0x08, 0x00]);
    // IPv4: version 4, 5 words, no DSCP/ECN, total length, id 0, don't fragment, TTL 64, protocol TCP,
    // checksum, loopback to loopback.
    let ip_start = out.len();
    out.extend_from_slice(&[0x45, 0x00]);
    out.extend_from_slice(&total.to_be_bytes());
    out.extend_from_slice(&[0, 0, 0x40, 0, 64, 6, 0, 0]);
    out.extend_from_slice(&LOOPBACK);
    out.extend_from_slice(&LOOPBACK);
    let ip_sum = ones_complement(ones_sum(0, &out[ip_start..]));
    out[ip_start + 10..ip_start + 12].copy_from_slice(&ip_sum.to_be_bytes());
    // TCP: ports, sequence, acknowledgement, 5 words, flags, window, checksum, no urgent pointer.
    let tcp_start = out.len();
    out.extend_from_slice(&sport.to_be_bytes());
    out.extend_from_slice(&dport.to_be_bytes());
    out.extend_from_slice(&seq.to_be_bytes());
    out.extend_from_slice(&ack.unwrap_or(0).to_be_bytes());
    let bits = u8::from(flags.fin)
        | u8::from(flags.syn) << 1
        | u8::from(flags.psh) << 3
        | u8::from(ack.is_some()) << 4;
    out.extend_from_slice(&[0x50, bits]);
    out.extend_from_slice(&WINDOW.to_be_bytes());
    out.extend_from_slice(&[0, 0, 0, 0]);
    out.extend_from_slice(payload);
    // The checksum over the pseudo header (addresses, protocol, TCP length) and the segment.
    let mut sum = ones_sum(0, &LOOPBACK);
    sum = ones_sum(sum, &LOOPBACK);
    sum += 6 + tcp_len as u64;
    sum = ones_sum(sum, &out[tcp_start..]);
    let tcp_sum = ones_complement(sum);
    out[tcp_start + 16..tcp_start + 18].copy_from_slice(&tcp_sum.to_be_bytes());
    Ok(())
}

/// `sum` plus the big-endian 16-bit words of `bytes` (a last odd byte padded with zero).
fn ones_sum(mut sum: u64, bytes: &[u8]) -> u64 {
    let mut words = bytes.chunks_exact(2);
    for w in &mut words {
        sum += u64::from(u16::from_be_bytes([w[0], w[1]]));
    }
    if let [last] = words.remainder() {
        sum += u64::from(*last) << 8;
    }
    sum
}

/// The Internet checksum of a one's-complement sum: folded to 16 bits and inverted.
fn ones_complement(mut sum: u64) -> u16 {
    while sum > 0xFFFF {
        sum = (sum & 0xFFFF) + (sum >> 16);
    }
    !(sum as u16)
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
        let mut pcap = Stream::wrapping(dir, PCAP_FILE, |out| {
            PcapNgWriter::with_section_header(out, section).map_err(io_error)
        })?;
        let interface = InterfaceDescriptionBlock {
            linktype: DataLink::ETHERNET,
            snaplen: 65_535,
            options: vec![
                InterfaceDescriptionOption::IfName(Cow::Borrowed("modbus-harness synthetic")),
                // pcap-file writes EPB timestamps in nanoseconds.
                InterfaceDescriptionOption::IfTsResol(9),
            ],
        };
        pcap.write(|w| {
            w.write_pcapng_block(interface)
                .map(|_| ())
                .map_err(io_error)
        })?;
        let framing = match info.transport {
            Transport::Tcp => Framing::Tcp,
            Transport::Rtu | Transport::RtuOverTcp => Framing::Rtu,
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            pcap,
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
        self.packet.clear();
        tcp_packet(
            &mut self.packet,
            (src_mac, dst_mac),
            (sport, dport),
            seq,
            flags.ack.then_some(ack),
            flags,
            payload,
        )?;
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
        self.pcap
            .write(|w| w.write_pcapng_block(block).map(|_| ()).map_err(io_error))
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
        let flags = |syn, ack, psh, fin| Flags { syn, ack, psh, fin };
        let syn = flags(true, false, false, false);
        let syn_ack = flags(true, true, false, false);
        let ack = flags(false, true, false, false);
        let data = flags(false, true, true, false);
        let fin = flags(false, true, false, true);
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
        self.pcap.flush()
    }

    fn finish(&mut self, _summary: &Summary) -> io::Result<()> {
        self.pcap.close()?;
        promote(self.pcap.partial(), &self.dir.join(PCAP_FILE))
    }
}

/// A pcap-file error as the I/O error it is (or wraps).
fn io_error(e: pcap_file::PcapError) -> io::Error {
    match e {
        pcap_file::PcapError::IoError(e) => e,
        other => io::Error::other(other.to_string()),
    }
}

impl Buffered for PcapNgWriter<BufWriter<File>> {
    fn buffer(&mut self) -> &mut BufWriter<File> {
        self.get_mut()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hand-written packets are byte for byte those of `etherparse::PacketBuilder` (whose checksums
    /// Wireshark and tshark accept), for every flag combination the sink uses and payloads of every length
    /// parity, empty to the largest ADU.
    #[test]
    fn packets_are_those_etherparse_builds() {
        let payloads: Vec<Vec<u8>> = [0usize, 1, 2, 7, 12, 255, 260, 513]
            .iter()
            .map(|&n| (0..n).map(|i| (i * 37 + n) as u8).collect())
            .collect();
        let mut n = 0;
        for (syn, ack, psh, fin) in [
            (true, false, false, false),
            (true, true, false, false),
            (false, true, false, false),
            (false, true, true, false),
            (false, true, false, true),
            (false, false, true, false),
        ] {
            for payload in &payloads {
                for (sport, dport, seq, ack_no) in [
                    (40_000u16, 502u16, 0u32, 0u32),
                    (502, 43_999, 0xFFFF_FFFF, 0x8000_0001),
                    (41_234, 502, 0x1234_5678, 0x5A5A_5A5A),
                ] {
                    let flags = Flags { syn, ack, psh, fin };
                    let mut builder = etherparse::PacketBuilder::ethernet2(CLIENT_MAC, SERVER_MAC)
                        .ipv4(LOOPBACK, LOOPBACK, 64)
                        .tcp(sport, dport, seq, WINDOW);
                    if syn {
                        builder = builder.syn();
                    }
                    if ack {
                        builder = builder.ack(ack_no);
                    }
                    if psh {
                        builder = builder.psh();
                    }
                    if fin {
                        builder = builder.fin();
                    }
                    let mut theirs = Vec::new();
                    builder.write(&mut theirs, payload).expect("etherparse");
                    let mut ours = vec![0xEE];
                    tcp_packet(
                        &mut ours,
                        (CLIENT_MAC, SERVER_MAC),
                        (sport, dport),
                        seq,
                        ack.then_some(ack_no),
                        Flags { syn, ack, psh, fin },
                        payload,
                    )
                    .expect("packet");
                    assert_eq!(ours[0], 0xEE, "appended, not overwritten");
                    assert_eq!(
                        ours[1..],
                        theirs[..],
                        "{flags:?} payload {} ports {sport}->{dport}",
                        payload.len()
                    );
                    n += 1;
                }
            }
        }
        assert_eq!(n, 6 * 8 * 3);
    }
}
