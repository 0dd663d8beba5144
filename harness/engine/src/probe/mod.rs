//! `probe`: discover which function codes a target answers, which registers, coils and discrete inputs it
//! reads, its device identification and (Modbus/TCP) the unit ids it answers, and set them beside a
//! profile's, or write them as a draft profile ([`draft`]).
//!
//! By default only requests that read are sent: FC 01, 02, 03, 04 (one address at a time), 07, 08/00
//! (Return Query Data, an echo), 0B, 0C, 11 and 2B (MEI 0E device identification, else MEI 0D a CANopen
//! object read). The write function codes need [`ProbeOptions::writes`] (`--probe-writes`), and even then
//! only a request the Modbus spec requires a drive to reject before writing anything is sent (FC 05 with
//! value 0x1234, FC 0F/10/17 with quantity 0) plus the vendor codes 0x41/0x42 with a mnemonic no MDrive/LMD
//! knows. FC 06 is never sent: every FC 06 request is a valid write.

pub mod draft;

use std::time::Duration;

use crate::targets::{Received, Target, TargetError};
use codec::{DeviceIdResponse, ExceptionCode, Framing, Mnemonic, Request, Response, rtu, tcp};
use drives::profile::{Bit, Profile, Table};
use toml::Spanned;

/// What a function code probe found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Support {
    /// Answered normally, or with an exception other than 01 (it parsed the request).
    Yes(String),
    /// Exception 01.
    No,
    /// No answer within the timeout.
    Silent,
    /// Not probed, and why.
    NotProbed(&'static str),
}

/// What to probe.
#[derive(Clone, Debug)]
pub struct ProbeOptions {
    /// Unit id / slave address.
    pub unit: u8,
    /// Per-request timeout.
    pub timeout: Duration,
    /// Register, coil and discrete-input addresses to read one by one, inclusive.
    pub scan: (u16, u16),
    /// Also probe the write function codes, with requests a drive must reject before writing.
    pub writes: bool,
    /// Register addresses the scan does not read: a read of them changes the drive (the profile's
    /// `read_clears`, MCode ER: "must be read or set to 0 to clear"). See [`unread_of`].
    pub unread: Vec<u16>,
}

/// The register addresses of `profile` a read of which changes the drive (`read_clears`): a probe leaves
/// them unread.
pub fn unread_of(profile: &Profile) -> Vec<u16> {
    profile
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.read_clears)
        .flat_map(|r| r.address..r.address.saturating_add(u16::from(r.width)))
        .collect()
}

/// The outcome of a probe.
#[derive(Clone, Debug, Default)]
pub struct ProbeReport {
    pub functions: Vec<(u8, Support)>,
    /// Readable ranges (inclusive) per table: holding (FC 03), input (FC 04), coils (FC 01), discrete
    /// inputs (FC 02).
    pub holding: Vec<(u16, u16)>,
    pub input: Vec<(u16, u16)>,
    pub coils: Vec<(u16, u16)>,
    pub discrete_inputs: Vec<(u16, u16)>,
    /// FC 08/00 (Return Query Data) echoed its data.
    pub echo: bool,
    /// Register addresses of the scan left unread (FC 03 and 04): a read of them changes the drive.
    pub unread: Vec<u16>,
    /// Device identification objects (FC 2B/0E), sorted by id.
    pub identification: Vec<(u8, Vec<u8>)>,
    /// Modbus/TCP: each other unit id a read was sent to, and whether it was answered (a gateway's 0A or 0B
    /// is not an answer of a drive there: see `gateway_refused`).
    pub units: Vec<(u8, bool)>,
    /// Modbus/TCP: the other unit ids refused with 0A (no path) or 0B (no response from the target), as a
    /// gateway, or a server routing by unit id, refuses an id with no device behind it (App 7): (unit, code).
    pub gateway_refused: Vec<(u8, u8)>,
    /// The framing the target spoke.
    pub framing: Option<Framing>,
    /// Requests sent.
    pub requests: usize,
    /// Of those, requests with a write function code (05, 0F, 10, 17, 42; `--probe-writes` only).
    pub write_requests: usize,
    /// Requests the safety classifier rated `write` without `--probe-writes`: not sent (a harness bug).
    pub refused: Vec<Vec<u8>>,
    /// Why the probe stopped before its end: the target stopped answering (the known-good read, the first
    /// request it answered, went unanswered too).
    pub stopped: Option<String>,
}

impl ProbeReport {
    /// True when the probe found `fc` answered.
    pub fn supports(&self, fc: u8) -> bool {
        self.functions
            .iter()
            .any(|(f, s)| *f == fc && matches!(s, Support::Yes(_)))
    }
}

/// The codes `probe` asks about, in order.
pub const PROBED: [u8; 17] = [
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F, 0x10, 0x11, 0x17, 0x2B, 0x41,
    0x42,
];

/// The codes probed only with `--probe-writes`: the write codes, and the vendor codes 0x41/0x42 (whose meaning
/// on a drive of unknown make is the vendor's).
pub const WRITE_PROBES: [u8; 6] = [0x05, 0x0F, 0x10, 0x17, 0x41, 0x42];

/// The unit ids the Modbus/TCP unit-id cases use: a probe asks each of them for a read.
pub const UNIT_PROBES: [u8; 4] = [0, 1, 247, 255];

/// The request probing `fc`, or why there is none. Read codes are sent as reads; write codes as a request
/// the drive must reject before writing (an illegal coil value, quantity 0, an unknown mnemonic).
fn probe_pdu(fc: u8, writes: bool) -> Result<Vec<u8>, &'static str> {
    if WRITE_PROBES.contains(&fc) && !writes {
        return Err(if fc >= 0x41 {
            "vendor code: --probe-writes"
        } else {
            "write code: --probe-writes"
        });
    }
    let req = match fc {
        0x01..=0x04 => Request::read(codec::FunctionCode(fc), 0, 1).ok_or("not a read")?,
        0x05 => Request::WriteSingleCoil {
            address: 0,
            value: 0x1234,
        },
        0x08 => Request::Diagnostics {
            sub_function: 0,
            data: vec![0x12, 0x34],
        },
        0x0F => Request::WriteMultipleCoils {
            address: 0,
            quantity: 0,
            data: vec![],
        },
        0x10 => Request::WriteMultipleRegisters {
            address: 0,
            values: vec![],
        },
        0x17 => Request::ReadWriteMultipleRegisters {
            read_address: 0,
            read_quantity: 0,
            write_address: 0,
            values: vec![],
        },
        0x2B => Request::ReadDeviceId {
            read_code: 1,
            object_id: 0,
        },
        0x41 => Request::VendorRead {
            mnemonic: Mnemonic::from_name("QQ").ok_or("no mnemonic")?,
        },
        0x42 => Request::VendorWrite {
            mnemonic: Mnemonic::from_name("QQ").ok_or("no mnemonic")?,
            params: b"=0".to_vec(),
        },
        0x07 | 0x0B | 0x0C | 0x11 => Request::Raw {
            function: codec::FunctionCode(fc),
            data: vec![],
        },
        _ => return Err("every request writes"),
    };
    req.to_bytes().map_err(|_| "cannot encode")
}

/// One request and its decoded answer (`None`: silence, a close, or an answer that does not decode).
struct Prober<'t> {
    t: &'t mut dyn Target,
    timeout: Duration,
    tid: u16,
    requests: usize,
    /// `--probe-writes`: without it, a request the classifier rates `write` is not sent.
    writes: bool,
    refused: Vec<Vec<u8>>,
    /// The first request the target answered (unit, PDU): asked again after a run of silences.
    good: Option<(u8, Vec<u8>)>,
    /// Requests in a row without an answer.
    silent: usize,
    /// The target stopped answering: nothing more is sent.
    dead: Option<String>,
}

/// Unanswered requests in a row after which the probe asks the known-good read again.
const SILENCES_BEFORE_LIVENESS: usize = 8;

impl Prober<'_> {
    /// One request, with a liveness check after a run of silences: a target that no longer answers even
    /// the first request it answered stops the probe (every later request returns `None` unsent).
    fn exchange(&mut self, unit: u8, pdu: &[u8]) -> Result<Option<Response>, TargetError> {
        if self.dead.is_some() {
            return Ok(None);
        }
        let answer = self.exchange_once(unit, pdu)?;
        if answer.is_some() {
            self.silent = 0;
            if self.good.is_none() {
                self.good = Some((unit, pdu.to_vec()));
            }
            return Ok(answer);
        }
        self.silent += 1;
        if self.silent >= SILENCES_BEFORE_LIVENESS
            && let Some((u, good)) = self.good.clone()
        {
            self.silent = 0;
            if self.exchange_once(u, &good)?.is_none() {
                self.dead = Some(format!(
                    "the target stopped answering: {SILENCES_BEFORE_LIVENESS} requests in a row went unanswered (the last {}), and so did the first request it had answered ({}); the results after that are incomplete",
                    hex::encode(pdu),
                    hex::encode(&good)
                ));
            }
        }
        Ok(answer)
    }

    fn exchange_once(&mut self, unit: u8, pdu: &[u8]) -> Result<Option<Response>, TargetError> {
        // The safety assertion before sending: a read-only probe puts no write on the wire, whatever the
        // code above built.
        if !self.writes && crate::cases::safety::is_write(pdu) {
            self.refused.push(pdu.to_vec());
            return Ok(None);
        }
        let mut frame = Vec::new();
        let framing = self.t.framing();
        self.tid = self.tid.wrapping_add(1);
        self.requests += 1;
        if framing == Framing::Tcp {
            let _ = tcp::encode_adu(self.tid, unit, pdu, &mut frame);
        } else {
            let _ = rtu::encode_adu(unit, pdu, &mut frame);
        }
        self.t.drain();
        self.t.send(&frame)?;
        match self.t.recv(self.timeout)? {
            Received::Frame { bytes, .. } => Ok(crate::readings::decode_response(framing, &bytes)),
            Received::Closed { .. } => {
                self.t.reconnect()?;
                Ok(None)
            }
            _ => Ok(None),
        }
    }

    fn request(&mut self, unit: u8, req: &Request) -> Result<Option<Response>, TargetError> {
        let pdu = req.to_bytes().unwrap_or_default();
        self.exchange(unit, &pdu)
    }
}

/// Inclusive ranges `r` without the addresses `out`.
fn without(r: Vec<(u16, u16)>, out: &[u16]) -> Vec<(u16, u16)> {
    if out.is_empty() {
        return r;
    }
    let mut kept = Vec::new();
    for (a, b) in r {
        for x in a..=b {
            if !out.contains(&x) {
                extend(&mut kept, x);
            }
        }
    }
    kept
}

/// Add `a` to sorted inclusive ranges built in ascending order.
fn extend(ranges: &mut Vec<(u16, u16)>, a: u16) {
    match ranges.last_mut() {
        Some(r) if r.1.wrapping_add(1) == a && r.1 < a => r.1 = a,
        _ => ranges.push((a, a)),
    }
}

/// Probe the function codes, then read every address of `scan` one at a time (FC 03, 04, 01, 02 where
/// answered), the device identification and (Modbus/TCP) the other unit ids. Bounded: at most
/// 17 + 1 + 4 x (scan length) + 2 x 64 + 4 requests.
pub fn probe(t: &mut dyn Target, o: &ProbeOptions) -> Result<ProbeReport, TargetError> {
    let mut report = ProbeReport {
        framing: Some(t.framing()),
        ..ProbeReport::default()
    };
    let mut p = Prober {
        t,
        timeout: o.timeout,
        tid: 0,
        requests: 0,
        writes: o.writes,
        refused: Vec::new(),
        good: None,
        silent: 0,
        dead: None,
    };
    let unit = o.unit;
    let mut basic_id = None;
    for fc in PROBED {
        let pdu = match probe_pdu(fc, o.writes) {
            Ok(pdu) => pdu,
            Err(why) => {
                report.functions.push((fc, Support::NotProbed(why)));
                continue;
            }
        };
        if WRITE_PROBES.contains(&fc) && fc != 0x41 {
            report.write_requests += 1;
        }
        let mut answer = p.exchange(unit, &pdu)?;
        let mut how = "";
        if fc == 0x08 {
            report.echo = matches!(&answer, Some(Response::Diagnostics { sub_function: 0, data }) if data == &[0x12, 0x34]);
        }
        if fc == 0x2B {
            if let Some(Response::ReadDeviceId(d)) = &answer {
                basic_id = Some(d.clone());
            }
            // FC 2B carries two MEI types; a drive may implement only CANopen access (SD2x).
            if matches!(answer, Some(Response::Exception { code, .. }) if code == ExceptionCode::ILLEGAL_FUNCTION)
            {
                let canopen = Request::CanOpen(codec::CanOpenAccess::read(unit, 0, 0, 2));
                answer = p.request(unit, &canopen)?;
                how = "MEI 0E refused, MEI 0D ";
            }
        }
        let s = match answer {
            None => Support::Silent,
            Some(Response::Exception { code, .. }) if code == ExceptionCode::ILLEGAL_FUNCTION => {
                Support::No
            }
            Some(Response::Exception { code, .. }) => {
                Support::Yes(format!("{how}exception {code}"))
            }
            Some(r) => Support::Yes(format!("{how}answered FC 0x{:02X}", r.function().0)),
        };
        report.functions.push((fc, s));
    }
    let (start, end) = o.scan;
    for fc in [0x03u8, 0x04, 0x01, 0x02] {
        if !report.supports(fc) {
            continue;
        }
        let mut ranges: Vec<(u16, u16)> = Vec::new();
        for a in start..=end {
            if matches!(fc, 0x03 | 0x04) && o.unread.contains(&a) {
                if !report.unread.contains(&a) {
                    report.unread.push(a);
                }
                continue;
            }
            let req = match fc {
                0x03 => Request::ReadHoldingRegisters {
                    address: a,
                    quantity: 1,
                },
                0x04 => Request::ReadInputRegisters {
                    address: a,
                    quantity: 1,
                },
                0x01 => Request::ReadCoils {
                    address: a,
                    quantity: 1,
                },
                _ => Request::ReadDiscreteInputs {
                    address: a,
                    quantity: 1,
                },
            };
            let ok = matches!(
                p.request(unit, &req)?,
                Some(
                    Response::ReadHoldingRegisters { .. }
                        | Response::ReadInputRegisters { .. }
                        | Response::ReadCoils { .. }
                        | Response::ReadDiscreteInputs { .. }
                )
            );
            if ok {
                extend(&mut ranges, a);
            }
        }
        match fc {
            0x03 => report.holding = ranges,
            0x04 => report.input = ranges,
            0x01 => report.coils = ranges,
            _ => report.discrete_inputs = ranges,
        }
    }
    if let Some(basic) = basic_id {
        report.identification = identification(&mut p, unit, basic)?;
    }
    if report.framing == Some(Framing::Tcp) {
        // A read every healthy drive answers: the first readable register, else the identification.
        let read = if let Some((a, _)) = report.holding.first() {
            Some(Request::ReadHoldingRegisters {
                address: *a,
                quantity: 1,
            })
        } else if let Some((a, _)) = report.input.first() {
            Some(Request::ReadInputRegisters {
                address: *a,
                quantity: 1,
            })
        } else if !report.identification.is_empty() {
            Some(Request::ReadDeviceId {
                read_code: 1,
                object_id: 0,
            })
        } else {
            None
        };
        if let Some(read) = read {
            for u in UNIT_PROBES.into_iter().filter(|u| *u != unit) {
                let got = p.request(u, &read)?;
                let gateway = match &got {
                    Some(Response::Exception { code, .. }) if code.is_gateway() => Some(code.0),
                    _ => None,
                };
                if let Some(code) = gateway {
                    report.gateway_refused.push((u, code));
                }
                report.units.push((u, got.is_some() && gateway.is_none()));
            }
        }
    }
    report.requests = p.requests;
    report.refused = std::mem::take(&mut p.refused);
    report.stopped = p.dead.take();
    Ok(report)
}

/// Every identification object: the extended stream (read code 03), else the regular (02), else the basic
/// one already read, following `more_follows` (at most 64 requests per stream).
fn identification(
    p: &mut Prober,
    unit: u8,
    basic: DeviceIdResponse,
) -> Result<Vec<(u8, Vec<u8>)>, TargetError> {
    let mut objects: Vec<(u8, Vec<u8>)> = Vec::new();
    let add = |d: &DeviceIdResponse, objects: &mut Vec<(u8, Vec<u8>)>| {
        for o in &d.objects {
            if !objects.iter().any(|(id, _)| *id == o.id) {
                objects.push((o.id, o.value.clone()));
            }
        }
    };
    'codes: for code in [3u8, 2] {
        let mut next = 0u8;
        let mut got = Vec::new();
        for _ in 0..64 {
            let answer = p.request(
                unit,
                &Request::ReadDeviceId {
                    read_code: code,
                    object_id: next,
                },
            )?;
            let Some(Response::ReadDeviceId(d)) = answer else {
                continue 'codes;
            };
            add(&d, &mut got);
            if d.more_follows != 0xFF || d.next_object_id <= next {
                break;
            }
            next = d.next_object_id;
        }
        objects = got;
        break;
    }
    add(&basic, &mut objects);
    objects.sort_by_key(|o| o.0);
    Ok(objects)
}

/// The readable ranges a profile documents for a register table (registers merged where contiguous).
pub fn profile_ranges(p: &Profile, input: bool) -> Vec<(u16, u16)> {
    let regs: Vec<(u16, u16)> = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.access.readable())
        .filter(|r| match r.table {
            Table::Both => true,
            Table::Holding => !input,
            Table::Input => input,
        })
        .map(|r| (r.address, (r.end() - 1) as u16))
        .collect();
    merge(regs)
}

/// The readable addresses a profile documents for coils or discrete inputs, merged.
fn bit_ranges(bits: &[Spanned<Bit>]) -> Vec<(u16, u16)> {
    merge(
        bits.iter()
            .map(|b| b.get_ref())
            .filter(|b| b.access.readable())
            .map(|b| (b.address, b.address))
            .collect(),
    )
}

fn merge(mut v: Vec<(u16, u16)>) -> Vec<(u16, u16)> {
    v.sort();
    let mut out: Vec<(u16, u16)> = Vec::new();
    for (a, b) in v {
        match out.last_mut() {
            Some(r) if r.1.wrapping_add(1) >= a && r.1 != u16::MAX => r.1 = r.1.max(b),
            _ => out.push((a, b)),
        }
    }
    out
}

/// The standard name of an identification object id (spec 6.21).
pub fn id_object_name(id: u8) -> String {
    match id {
        0x00 => "VendorName".into(),
        0x01 => "ProductCode".into(),
        0x02 => "MajorMinorRevision".into(),
        0x03 => "VendorUrl".into(),
        0x04 => "ProductName".into(),
        0x05 => "ModelName".into(),
        0x06 => "UserApplicationName".into(),
        _ => format!("Object 0x{id:02X}"),
    }
}

/// A side-by-side text of what the probe found and what the profile says.
pub fn render(report: &ProbeReport, profile: Option<&Profile>, scan: (u16, u16)) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "  function code                          target                                       profile"
    );
    for (fc, sup) in &report.functions {
        let t = match sup {
            Support::Yes(how) => format!("yes ({how})"),
            Support::No => "no (exception 01)".into(),
            Support::Silent => "no answer".into(),
            Support::NotProbed(why) => format!("not probed ({why})"),
        };
        let p = profile.map_or(String::new(), |p| {
            if p.function(*fc).is_some() {
                "yes".into()
            } else {
                "no".into()
            }
        });
        let mark = match (sup, profile.map(|p| p.function(*fc).is_some())) {
            (Support::Yes(_), Some(false)) => "  <- undocumented",
            (Support::No | Support::Silent, Some(true)) => "  <- documented, not answered",
            _ => "",
        };
        let name = codec::FunctionCode(*fc).name().unwrap_or("");
        let _ = writeln!(s, "  0x{fc:02X} {name:<33} {t:<44} {p}{mark}");
    }
    let fmt = |r: &[(u16, u16)]| {
        if r.is_empty() {
            "none".to_string()
        } else {
            r.iter()
                .map(|(a, b)| {
                    if a == b {
                        format!("0x{a:04X}")
                    } else {
                        format!("0x{a:04X}-0x{b:04X}")
                    }
                })
                .collect::<Vec<_>>()
                .join(", ")
        }
    };
    let clip = |r: Vec<(u16, u16)>| -> Vec<(u16, u16)> {
        r.into_iter()
            .filter(|(a, b)| *b >= scan.0 && *a <= scan.1)
            .map(|(a, b)| (a.max(scan.0), b.min(scan.1)))
            .collect()
    };
    /// The ranges a profile documents for one table.
    type Documented = fn(&Profile) -> Vec<(u16, u16)>;
    let tables = [
        (
            "holding (FC 03)",
            0x03u8,
            &report.holding,
            (|p| profile_ranges(p, false)) as Documented,
        ),
        (
            "input (FC 04)",
            0x04,
            &report.input,
            (|p| profile_ranges(p, true)) as Documented,
        ),
        (
            "coils (FC 01)",
            0x01,
            &report.coils,
            (|p| bit_ranges(&p.coils)) as Documented,
        ),
        (
            "discrete inputs (FC 02)",
            0x02,
            &report.discrete_inputs,
            (|p| bit_ranges(&p.discrete_inputs)) as Documented,
        ),
    ];
    for (label, fc, got, documented) in tables {
        // Coils and discrete inputs are shown when the target or the profile has them.
        if fc <= 0x02 && !report.supports(fc) && profile.is_none_or(|p| p.function(fc).is_none()) {
            continue;
        }
        let _ = writeln!(
            s,
            "\n{label} readable in 0x{:04X}-0x{:04X}:",
            scan.0, scan.1
        );
        let _ = writeln!(s, "  target:  {}", fmt(got));
        // Registers a read would change were not read: not compared either.
        let unread: &[u16] = if fc >= 0x03 { &report.unread } else { &[] };
        if !unread.is_empty() {
            let list: Vec<String> = unread.iter().map(|a| format!("0x{a:04X}")).collect();
            let _ = writeln!(
                s,
                "  not read: {} (a read clears it: the profile's read_clears)",
                list.join(", ")
            );
        }
        if let Some(p) = profile {
            let want = without(clip(documented(p)), unread);
            let _ = writeln!(s, "  profile: {}", fmt(&want));
            let _ = writeln!(s, "  {}", if &want == got { "same" } else { "DIFFERENT" });
        }
    }
    if !report.identification.is_empty() {
        let _ = writeln!(s, "\ndevice identification (FC 2B/0E):");
        for (id, v) in &report.identification {
            let _ = writeln!(
                s,
                "  0x{id:02X} {:<20} {:?}",
                id_object_name(*id),
                String::from_utf8_lossy(v)
            );
        }
    }
    if !report.units.is_empty() {
        let list = |answered: bool| {
            let v: Vec<String> = report
                .units
                .iter()
                .filter(|(_, a)| *a == answered)
                .map(|(u, _)| u.to_string())
                .collect();
            if v.is_empty() {
                "none".to_string()
            } else {
                v.join(", ")
            }
        };
        let _ = writeln!(
            s,
            "\nother unit ids: answered {}; not answered {}",
            list(true),
            list(false)
        );
        if !report.gateway_refused.is_empty() {
            let v: Vec<String> = report
                .gateway_refused
                .iter()
                .map(|(u, c)| format!("{u} (0x{c:02X})"))
                .collect();
            let _ = writeln!(
                s,
                "  of those not answered, refused as a gateway refuses an id with no device behind it (0A: no path, 0B: no response, App 7): {}",
                v.join(", ")
            );
        }
    }
    if let Some(why) = &report.stopped {
        let _ = writeln!(s, "\nTHE PROBE STOPPED EARLY: {why}");
    }
    if !report.refused.is_empty() {
        let _ = writeln!(
            s,
            "\nHARNESS BUG: {} request(s) the safety classifier rates as writes were built without --probe-writes and NOT sent: {}",
            report.refused.len(),
            report
                .refused
                .iter()
                .map(hex::encode)
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    if report.write_requests == 0 {
        let _ = writeln!(
            s,
            "\n{} requests, none of them writes (read function codes only; --probe-writes probes the write codes)",
            report.requests
        );
    } else {
        let _ = writeln!(
            s,
            "\n{} requests; {} of them with a write function code, each one a request a drive must reject before \
writing (FC 05 value 0x1234, FC 0F/10/17 quantity 0), and the vendor codes 0x41/0x42 with the unknown mnemonic QQ",
            report.requests, report.write_requests
        );
    }
    s
}
