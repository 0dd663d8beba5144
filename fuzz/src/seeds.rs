//! Seed inputs for every target, written to `fuzz/corpus/<target>/seed-*` by the ignored test
//! `write_seed_corpus` (tests/fuzz_corpus.rs).

use std::collections::{BTreeMap, BTreeSet};

use codec::{Framing, Request, tcp};
use drives::FaultSet;
use drives::corpus::Corpus;
use drives::golden::{Form, GoldenDirection, GoldenFile, check_frame};
use drives::profile::Profile;
use engine::cases::catalog;
use engine::{Mutation, Outgoing, Step};

use crate::differential::differential_input;
use crate::drive_model::{OP_PDU, OP_RTU, OP_TCP, OP_WAIT, Op, parse_ops};
use crate::input::push_counted;
use crate::reference::{answer, frame_request, line_timing, profiles, station};
use crate::response_validation::{COMPARES, RV_RTU, RV_WRAP};
use crate::rtu_framer::{RTU_19200_8E1, RTU_AFTER_SILENCE};

/// One seed input for a target.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Seed {
    pub target: &'static str,
    /// File name under `fuzz/corpus/<target>/`, starting with `seed-`.
    pub name: String,
    pub bytes: Vec<u8>,
}

/// Collects seeds, dropping byte-identical ones and keeping names unique per target.
#[derive(Default)]
struct SeedSet {
    seeds: Vec<Seed>,
    seen: BTreeSet<(&'static str, Vec<u8>)>,
    names: BTreeSet<(&'static str, String)>,
    shapes: BTreeSet<String>,
}

fn slug(s: &str) -> String {
    engine::cases::catalog::slug_of_length(s, 72)
}

/// A request PDU and the reference answer's PDU (empty when the drive stays silent).
struct Exchange<'a> {
    name: String,
    drive: u8,
    framing: Framing,
    /// Index into `COMPARES`.
    compare: u8,
    unit: u8,
    request: &'a [u8],
    response: &'a [u8],
}

impl Exchange<'_> {
    /// What tells exchanges apart for coverage: drive, transport, function (and MEI), the answer's function,
    /// and its exception code or length. The catalog reads and writes every register; one of each shape is
    /// enough to seed the fuzzer.
    fn shape(&self) -> String {
        let request = match self.request {
            [0x2B, mei, ..] => format!("2B/{mei:02X}"),
            [fc, ..] => format!("{fc:02X}"),
            [] => "empty".into(),
        };
        let response = match self.response {
            [fc, code] if fc & 0x80 != 0 => format!("{fc:02X}/{code:02X}"),
            [fc, ..] => format!("{fc:02X}/{}", self.response.len()),
            [] => "silent".into(),
        };
        format!(
            "{}/{:?}/{}/{request}/{response}",
            self.drive, self.framing, self.compare
        )
    }
}

impl SeedSet {
    fn add(&mut self, target: &'static str, name: &str, bytes: Vec<u8>) {
        if !self.seen.insert((target, bytes.clone())) {
            return;
        }
        let base = format!("seed-{}", slug(name));
        let mut name = base.clone();
        let mut n = 1;
        while !self.names.insert((target, name.clone())) {
            n += 1;
            name = format!("{base}-{n}");
        }
        self.seeds.push(Seed {
            target,
            name,
            bytes,
        });
    }

    /// True the first time a shape is seen.
    fn novel(&mut self, shape: String) -> bool {
        self.shapes.insert(shape)
    }

    /// An exchange as seeds of the codec, framer, oracle and differential targets.
    fn exchange(&mut self, x: &Exchange<'_>) {
        let name = &x.name;
        for (pdu, dir) in [(x.request, "request"), (x.response, "response")] {
            let mut adu = Vec::new();
            if tcp::encode_adu(1, x.unit, pdu, &mut adu).is_ok() {
                self.add("tcp_adu", &format!("{name}-{dir}"), adu);
            }
        }
        let mut stream = vec![RTU_19200_8E1];
        for pdu in [x.request, x.response] {
            if let Some(frame) = frame_request(Framing::Rtu, x.unit, pdu) {
                rtu_steps(&mut stream, &frame);
            }
        }
        self.add("rtu_framer", name, stream);
        let rtu = if x.framing == Framing::Rtu { RV_RTU } else { 0 };
        let mut rv = vec![x.drive | rtu | x.compare << 3 | RV_WRAP];
        push_counted(&mut rv, x.request);
        rv.extend_from_slice(x.response);
        self.add("response_validation", name, rv);
        if let Ok(req) = Request::decode(x.request)
            && let Some(d) = differential_input(x.unit, &req, x.response)
        {
            self.add("differential", name, d);
        }
    }
}

/// Steps of an `rtu_framer` input that push `frame` after a t3.5 silence, in chunks of at most 255 bytes.
fn rtu_steps(out: &mut Vec<u8>, frame: &[u8]) {
    for (i, chunk) in frame.chunks(255).enumerate() {
        out.push(if i == 0 { RTU_AFTER_SILENCE } else { 0 });
        push_counted(out, chunk);
    }
}

/// A `drive_model` request operation to `unit` of a drive whose default unit is `default`.
fn op_request(out: &mut Vec<u8>, default: u8, unit: u8, pdu: &[u8]) {
    out.extend_from_slice(&[OP_PDU, unit.wrapping_sub(default)]);
    push_counted(out, pdu);
}

/// `drive_model` operations putting `bytes` on the TCP stream (one per 255 bytes).
fn op_tcp(out: &mut Vec<u8>, bytes: &[u8]) {
    for chunk in bytes.chunks(255) {
        out.push(OP_TCP);
        push_counted(out, chunk);
    }
}

/// `drive_model` operations putting `bytes` on the RTU line after a silence of `gap` sixteenths of t3.5.
fn op_rtu(out: &mut Vec<u8>, gap: u8, bytes: &[u8]) {
    for (i, chunk) in bytes.chunks(255).enumerate() {
        out.extend_from_slice(&[OP_RTU, if i == 0 { gap } else { 0 }]);
        push_counted(out, chunk);
    }
}

/// The `drive_model` operations of a catalog case's steps (what the harness sends; expectations aside).
fn case_ops(p: &Profile, steps: &[Step]) -> Vec<u8> {
    let default = p.device.default_unit;
    let mut out = Vec::new();
    for step in steps {
        match step {
            Step::Exchange { send, .. } => match send {
                Outgoing::Pdu(pdu) => op_request(&mut out, default, default, pdu),
                Outgoing::PduToUnit { pdu, unit } => op_request(&mut out, default, *unit, pdu),
                Outgoing::Mutated { pdu, mutation } => {
                    let tcp = frame_request(Framing::Tcp, default, pdu);
                    let rtu = frame_request(Framing::Rtu, default, pdu);
                    match (mutation, tcp, rtu) {
                        (Mutation::ProtocolId(id), Some(mut adu), _) => {
                            adu[2..4].copy_from_slice(&id.to_be_bytes());
                            op_tcp(&mut out, &adu);
                        }
                        (Mutation::LengthDelta(d), Some(mut adu), _) => {
                            let len = u16::from_be_bytes([adu[4], adu[5]]).wrapping_add_signed(*d);
                            adu[4..6].copy_from_slice(&len.to_be_bytes());
                            op_tcp(&mut out, &adu);
                        }
                        (Mutation::BadCrc, _, Some(mut frame)) => {
                            let n = frame.len();
                            frame[n - 2] ^= 0xFF;
                            op_rtu(&mut out, RTU_AFTER_SILENCE, &frame);
                        }
                        (Mutation::Split { at, gap_us }, _, Some(frame)) => {
                            let (a, b) = frame.split_at((*at).min(frame.len()));
                            let t3_5 = line_timing().t3_5.as_micros().max(1) as u64;
                            let gap = (gap_us * 16 / t3_5).min(63) as u8;
                            op_rtu(&mut out, RTU_AFTER_SILENCE, a);
                            op_rtu(&mut out, gap, b);
                        }
                        _ => op_request(&mut out, default, default, pdu),
                    }
                }
                Outgoing::Batch(pdus) => {
                    let mut stream = Vec::new();
                    for pdu in pdus {
                        stream
                            .extend(frame_request(Framing::Tcp, default, pdu).unwrap_or_default());
                    }
                    op_tcp(&mut out, &stream);
                }
                Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => {}
            },
            // A command sent until the drive takes it: once, as the reference takes it at once.
            Step::Persist {
                send: Outgoing::Pdu(pdu),
                ..
            } => op_request(&mut out, default, default, pdu),
            Step::Persist { .. } => {}
            Step::Wait(d) => {
                out.push(OP_WAIT);
                let ms = u16::try_from(d.as_millis()).unwrap_or(u16::MAX);
                out.extend_from_slice(&ms.to_be_bytes());
            }
            Step::Reconnect
            | Step::Agree { .. }
            | Step::EventLogShifted { .. }
            | Step::ClearedUnlessFlagged { .. }
            | Step::Until { .. } => {}
        }
    }
    out
}

fn golden_seeds(set: &mut SeedSet, drive: u8, p: &Profile, g: &GoldenFile) {
    let default = p.device.default_unit;
    let mut requests = Vec::new();
    let mut pdus = BTreeMap::new();
    for frame in &g.frames {
        let check = check_frame(frame, p.device.word_order);
        let Ok(decoded) = &check.decoded else {
            continue;
        };
        let mut pdu = Vec::new();
        if decoded.pdu.encode(&mut pdu).is_err() {
            continue;
        }
        let unit = decoded.unit.unwrap_or(default);
        if frame.direction == GoldenDirection::Request {
            op_request(&mut requests, default, unit, &pdu);
        }
        pdus.insert(frame.id.clone(), (unit, pdu.clone()));
        // The printed bytes of an erratum are malformed traffic: seeds for the codec's error paths.
        if let (Some(printed), Some(_)) = (&frame.printed, &frame.corrected)
            && let Ok(bytes) = codec::parse_hex(printed)
        {
            set.add("tcp_adu", &format!("{}-printed", frame.id), {
                let mut adu = Vec::new();
                let pdu = match frame.form {
                    Form::Rtu => bytes.get(1..bytes.len().saturating_sub(2)),
                    Form::Tcp => bytes.get(tcp::MBAP_LEN..),
                    Form::Pdu => Some(&bytes[..]),
                };
                let _ = tcp::encode_adu(1, unit, pdu.unwrap_or_default(), &mut adu);
                adu
            });
            if frame.form == Form::Rtu {
                let mut stream = vec![RTU_19200_8E1];
                rtu_steps(&mut stream, &bytes);
                set.add("rtu_framer", &format!("{}-printed", frame.id), stream);
            }
        }
    }
    for frame in &g.frames {
        let (Some(req_id), Some((unit, response))) = (&frame.request, pdus.get(&frame.id)) else {
            continue;
        };
        let Some((_, request)) = pdus.get(req_id) else {
            continue;
        };
        for (framing, compare) in [(Framing::Tcp, 1), (Framing::Rtu, 0)] {
            set.exchange(&Exchange {
                name: format!("golden-{}", frame.id),
                drive,
                framing,
                compare,
                unit: *unit,
                request,
                response,
            });
        }
    }
    set.add("drive_model", &format!("golden-{}", p.device.id), requests);
}

/// The PDU of a framed reply.
fn pdu_of(framing: Framing, adu: &[u8]) -> &[u8] {
    match framing {
        Framing::Tcp => adu.get(tcp::MBAP_LEN..),
        _ => adu.get(1..adu.len().saturating_sub(2)),
    }
    .unwrap_or_default()
}

/// The shape of a `drive_model` input: its operations with the unit offset and function code of each request.
fn ops_shape(ops: &[u8]) -> String {
    parse_ops(ops)
        .iter()
        .map(|op| match op {
            Op::Request { unit, pdu } => format!("{unit}:{:02X?}", pdu.first()),
            Op::TcpStream(b) => format!("tcp{}", b.len()),
            Op::RtuStream { bytes, .. } => format!("rtu{}", bytes.len()),
            Op::Wait(_) => "wait".into(),
        })
        .collect::<Vec<_>>()
        .join(",")
}

fn catalog_seeds(set: &mut SeedSet, drive: u8, p: &Profile, g: Option<&GoldenFile>) {
    let unit = p.device.default_unit;
    for framing in [Framing::Tcp, Framing::Rtu] {
        let mut drive_station = station(p, &FaultSet::none());
        for case in catalog::build(p, g, framing, unit) {
            let ops = case_ops(p, &case.steps);
            if set.novel(format!("{drive}/{}", ops_shape(&ops))) {
                set.add("drive_model", &case.id, ops);
            }
            for (i, step) in case.steps.iter().enumerate() {
                let Step::Exchange {
                    send: Outgoing::Pdu(pdu),
                    compare,
                    ..
                } = step
                else {
                    continue;
                };
                let Some(adu) = frame_request(framing, unit, pdu) else {
                    continue;
                };
                let reply = answer(&mut drive_station, framing, &adu)
                    .0
                    .unwrap_or_default();
                let x = Exchange {
                    name: format!("{}-{i}", case.id),
                    drive,
                    framing,
                    compare: COMPARES.iter().position(|c| c == compare).unwrap_or(0) as u8,
                    unit,
                    request: pdu,
                    response: pdu_of(framing, &reply),
                };
                if set.novel(x.shape()) {
                    set.exchange(&x);
                }
            }
        }
    }
}

/// Seed inputs for every target, from the embedded golden frames and the case catalog of each reference drive:
/// each golden request/response pair and each catalog exchange (with the reference answer) as a TCP ADU, an
/// RTU stream, an oracle input and, for the standard function codes, a differential input; each catalog case
/// and each manual's requests as a drive sequence.
pub fn seeds() -> Vec<Seed> {
    let mut set = SeedSet::default();
    for (drive, p) in profiles().iter().enumerate() {
        let golden = Corpus::Embedded
            .golden(&p.device.id)
            .unwrap_or_else(|e| panic!("embedded golden file of {}: {e}", p.device.id));
        if let Some(g) = &golden {
            golden_seeds(&mut set, drive as u8, p, g);
        }
        catalog_seeds(&mut set, drive as u8, p, golden.as_ref());
    }
    set.seeds
}
