//! The case catalog: golden replay, generic Modbus cases from the specs, and cases derived from the
//! profile. Expected answers are not written here: the reference model (the oracle) gives them.

use std::time::Duration;

use crate::cases::{Case, Compare, Level, Mutation, Send, Step, Tag};
use codec::{CanOpenAccess, Framing, Mnemonic, Request, rtu};
use drives::golden::{Form, GoldenDirection, GoldenFile};
use drives::profile::{Access, Profile, Register, Table};

const APP: &str = "Modbus Application Protocol Specification V1.1b3";
const TCPG: &str = "Modbus Messaging on TCP/IP Implementation Guide V1.0b";
const SER: &str = "Modbus over Serial Line Specification V1.02";

fn pdu(r: &Request) -> Vec<u8> {
    r.to_bytes().unwrap_or_default()
}

fn exchange(send: Send, compare: Compare, note: impl Into<String>) -> Step {
    Step::Exchange {
        send,
        compare,
        capture: None,
        note: note.into(),
    }
}

fn capture(send: Send, compare: Compare, slot: usize, note: impl Into<String>) -> Step {
    Step::Exchange {
        send,
        compare,
        capture: Some(slot),
        note: note.into(),
    }
}

struct Ctx<'a> {
    p: &'a Profile,
    unit: u8,
    cases: Vec<Case>,
}

impl Ctx<'_> {
    /// Add a case checking a MUST-level requirement (every catalog case is one; SHOULD-level deviations
    /// are found inside steps, e.g. RTU timing).
    fn push(
        &mut self,
        id: String,
        title: impl Into<String>,
        reference: impl Into<String>,
        requirement: impl Into<String>,
        tags: Vec<Tag>,
        steps: Vec<Step>,
    ) {
        self.cases.push(Case {
            id,
            title: title.into(),
            reference: reference.into(),
            requirement: requirement.into(),
            level: Level::Must,
            tags,
            steps,
        });
    }

    fn supports(&self, fc: u8) -> bool {
        self.p.function(fc).is_some()
    }

    fn max_quantity(&self, fc: u8) -> u16 {
        self.p
            .function(fc)
            .and_then(|f| f.max_quantity)
            .unwrap_or(match fc {
                0x01 | 0x02 => 2000,
                0x03 | 0x04 => 125,
                0x0F => 0x7B0,
                0x10 => 123,
                _ => 125,
            })
    }

    /// A read that every healthy drive of the profile answers: the liveness probe after malformed input.
    fn probe(&self) -> Step {
        exchange(
            Send::Pdu(probe_pdu(self.p)),
            Compare::Structure,
            "liveness: a valid read is still answered",
        )
    }

    fn read_request(&self, address: u16, quantity: u16, table: Table) -> Request {
        let fc04 = table == Table::Input || (!self.supports(0x03) && self.supports(0x04));
        if fc04 {
            Request::ReadInputRegisters { address, quantity }
        } else {
            Request::ReadHoldingRegisters { address, quantity }
        }
    }

    fn write_request(&self, address: u16, values: Vec<u16>) -> Request {
        if values.len() == 1 && !self.supports(0x10) && self.supports(0x06) {
            Request::WriteSingleRegister {
                address,
                value: values[0],
            }
        } else {
            Request::WriteMultipleRegisters { address, values }
        }
    }

    fn can_write_registers(&self) -> bool {
        self.supports(0x10) || self.supports(0x06)
    }
}

/// A read of the first readable register: the liveness probe.
pub fn probe_pdu(p: &Profile) -> Vec<u8> {
    let reg = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.access.readable());
    let (address, width, input) = reg.map_or((0, 1, false), |r| {
        (r.address, r.width, r.table == Table::Input)
    });
    let req = if input || p.function(0x03).is_none() && p.function(0x04).is_some() {
        Request::ReadInputRegisters {
            address,
            quantity: u16::from(width),
        }
    } else {
        Request::ReadHoldingRegisters {
            address,
            quantity: u16::from(width),
        }
    };
    pdu(&req)
}

fn slug(s: &str) -> String {
    let mut out = String::new();
    for c in s.chars() {
        if c.is_ascii_alphanumeric() {
            out.push(c.to_ascii_lowercase());
        } else if !out.ends_with('-') {
            out.push('-');
        }
    }
    out.trim_matches('-').chars().take(40).collect()
}

fn reg_slug(r: &Register) -> String {
    match &r.mnemonic {
        Some(m) => format!("0x{:04X}-{}", r.address, slug(m)),
        None => format!("0x{:04X}-{}", r.address, slug(&r.name)),
    }
}

fn encode_value(p: &Profile, r: &Register, v: i64) -> Vec<u16> {
    if r.width == 2 {
        p.device.word_order.split(v as u32).to_vec()
    } else {
        vec![v as u16]
    }
}

/// The in-range value a write case uses: the smallest change from the default.
fn probe_value(r: &Register) -> i64 {
    let (min, max) = r.range();
    match r.default {
        Some(d) if d < max => d + 1,
        Some(d) if d > min => d - 1,
        Some(d) => d,
        None => min + (max - min) / 2,
    }
}

/// Build the catalog for a profile on a transport.
pub fn build(p: &Profile, golden: Option<&GoldenFile>, framing: Framing, unit: u8) -> Vec<Case> {
    let mut cx = Ctx {
        p,

        unit,
        cases: Vec::new(),
    };
    if let Some(g) = golden {
        golden_cases(&mut cx, g);
    }
    spec_cases(&mut cx);
    match framing {
        Framing::Tcp => tcp_cases(&mut cx),
        Framing::Rtu => rtu_cases(&mut cx),
        Framing::Pdu => {}
    }
    profile_cases(&mut cx);
    if p.device.id == "sd2x" || !p.objects.is_empty() {
        canopen_cases(&mut cx);
    }
    if p.watchdog.is_some() {
        ds402_cases(&mut cx);
    }
    cx.cases
}

/// The shrunk reproducers of a profile, `corpus/regressions/<profile>/*.toml`, as cases
/// `regression/<profile>/<file name>` (see [`crate::cases::regressions`] for the file format).
pub fn regressions(corpus: &drives::corpus::Corpus, p: &Profile) -> Result<Vec<Case>, String> {
    crate::cases::regressions::load_regressions(corpus, &p.device.id)
}

fn golden_cases(cx: &mut Ctx, g: &GoldenFile) {
    let p = cx.p;
    for f in g
        .frames
        .iter()
        .filter(|f| f.direction == GoldenDirection::Request)
    {
        let Some(hex) = f.corrected.as_ref().or(f.printed.as_ref()) else {
            continue;
        };
        let Ok(bytes) = codec::parse_hex(hex) else {
            continue;
        };
        let (pdu_bytes, addr) = match f.form {
            Form::Pdu => (bytes, None),
            Form::Rtu => match rtu::decode_adu(&bytes) {
                Ok(a) => (a.pdu.to_vec(), Some(a.address)),
                Err(_) => continue,
            },
            Form::Tcp => match codec::tcp::decode_adu(&bytes) {
                Ok(a) => (a.pdu.to_vec(), Some(a.header.unit_id)),
                Err(_) => continue,
            },
        };
        let Ok(req) = Request::decode(&pdu_bytes) else {
            continue;
        };
        let has_response = g
            .frames
            .iter()
            .any(|r| r.request.as_deref() == Some(f.id.as_str()));
        let mut tags = Vec::new();
        let mut steps = Vec::new();
        let mut restore = None;
        let compare = match &req {
            Request::WriteSingleRegister { address, .. }
            | Request::WriteMultipleRegisters { address, .. } => {
                tags.push(Tag::Write);
                let n = match &req {
                    Request::WriteMultipleRegisters { values, .. } => values.len() as u16,
                    _ => 1,
                };
                let regs: Vec<&Register> = (0..n)
                    .filter_map(|i| p.register_at(address.wrapping_add(i), false))
                    .collect();
                if regs.iter().any(|r| r.motion) {
                    tags.push(Tag::Motion);
                } else if cx.supports(0x03) || cx.supports(0x04) {
                    // Read what is there first, put it back after.
                    steps.push(capture(
                        Send::Pdu(pdu(&cx.read_request(*address, n, Table::Holding))),
                        Compare::Structure,
                        0,
                        "read the value the golden write will change",
                    ));
                    restore = Some(*address);
                }
                if regs.iter().any(|r| r.destructive) {
                    tags.push(Tag::Destructive);
                }
                Compare::Exact
            }
            Request::WriteSingleCoil { .. } | Request::WriteMultipleCoils { .. } => {
                tags.push(Tag::Write);
                Compare::Exact
            }
            Request::VendorWrite { mnemonic, .. } => {
                tags.push(Tag::Write);
                if let Some(m) = p.mnemonic(&mnemonic.name()) {
                    if m.motion {
                        tags.push(Tag::Motion);
                    }
                    if m.destructive {
                        tags.push(Tag::Destructive);
                    }
                }
                Compare::Structure
            }
            Request::CanOpen(a) if a.is_write() => {
                tags.push(Tag::Write);
                Compare::Exact
            }
            Request::ReadDeviceId { .. } | Request::VendorRead { .. } => Compare::Structure,
            _ => Compare::InRange,
        };
        let send = match addr {
            Some(u) if u != cx.unit => Send::PduToUnit {
                pdu: pdu_bytes.clone(),
                unit: u,
            },
            _ => Send::Pdu(pdu_bytes.clone()),
        };
        steps.push(exchange(
            send,
            compare,
            format!("golden request as corrected: {}", f.meaning),
        ));
        if let Some(a) = restore {
            steps.push(exchange(
                Send::Restore {
                    address: a,
                    slot: 0,
                },
                Compare::Exact,
                "restore the original value",
            ));
        }
        let id = format!("golden/{}", f.id);
        let reference = format!("{} line {} ({})", g.manual, f.line, f.section);
        let requirement = if has_response {
            format!(
                "The drive answers the manual's example as the reference drive does: {}",
                f.meaning
            )
        } else {
            format!("The drive handles the manual's example: {}", f.meaning)
        };
        cx.push(id, f.meaning.clone(), reference, requirement, tags, steps);
    }
}

fn spec_cases(cx: &mut Ctx) {
    let p = cx.p;
    // Unsupported function codes: exception 01 (a handful that the profile lacks, plus an undefined one).
    let candidates = [
        0x07u8, 0x0B, 0x0C, 0x11, 0x14, 0x16, 0x18, 0x01, 0x02, 0x05, 0x06, 0x0F, 0x17, 0x08, 0x04,
        0x55, 0x7F,
    ];
    let mut n = 0;
    for fc in candidates {
        if cx.supports(fc) || n >= 4 {
            continue;
        }
        n += 1;
        // A request of plausible length for the code, so only the code is at fault.
        let body: Vec<u8> = match fc {
            0x07 | 0x0B | 0x0C | 0x11 => vec![fc],
            0x0F => vec![fc, 0, 0, 0, 1, 1, 1],
            0x17 => vec![fc, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 0],
            0x14 => vec![fc, 7, 6, 0, 1, 0, 0, 0, 1],
            0x16 => vec![fc, 0, 0, 0xFF, 0xFF, 0, 0],
            0x18 => vec![fc, 0, 0],
            _ => vec![fc, 0, 0, 0, 1],
        };
        cx.push(
            format!("spec/app-7/unsupported-function/fc-0x{fc:02X}"),
            format!("function code 0x{fc:02X} is not supported"),
            format!("{APP}, section 7 (exception codes), 6 (state diagrams)"),
            "A function code the server does not implement is answered with exception 01 (Illegal Function) in a response whose function code is the request's with the high bit set, and the exception response is exactly 2 bytes.",
            vec![],
            vec![exchange(Send::Pdu(body), Compare::Exact, format!("FC 0x{fc:02X}"))],
        );
    }
    // Quantity 0 and max + 1 for every quantity-carrying function the profile supports.
    for fc in [0x01u8, 0x02, 0x03, 0x04, 0x0F, 0x10, 0x17] {
        if !cx.supports(fc) {
            continue;
        }
        let max = cx.max_quantity(fc);
        for (label, q) in [("zero", 0u16), ("max-plus-1", max.saturating_add(1))] {
            let req = match fc {
                0x01 => Request::ReadCoils {
                    address: 0,
                    quantity: q,
                },
                0x02 => Request::ReadDiscreteInputs {
                    address: 0,
                    quantity: q,
                },
                0x03 => Request::ReadHoldingRegisters {
                    address: first_reg(p, Table::Holding),
                    quantity: q,
                },
                0x04 => Request::ReadInputRegisters {
                    address: first_reg(p, Table::Input),
                    quantity: q,
                },
                0x0F => Request::WriteMultipleCoils {
                    address: 0,
                    quantity: q,
                    data: vec![0; (q as usize).div_ceil(8)],
                },
                0x10 => Request::WriteMultipleRegisters {
                    address: first_reg(p, Table::Holding),
                    values: vec![0; q as usize],
                },
                _ => Request::ReadWriteMultipleRegisters {
                    read_address: first_reg(p, Table::Holding),
                    read_quantity: q,
                    write_address: first_reg(p, Table::Holding),
                    values: vec![0],
                },
            };
            // A quantity whose data would not fit a PDU is sent with the quantity field alone changed.
            let bytes = match req.to_bytes() {
                Ok(b) => b,
                Err(_) => {
                    let mut b = pdu(&Request::WriteMultipleRegisters {
                        address: first_reg(p, Table::Holding),
                        values: vec![0],
                    });
                    b[3..5].copy_from_slice(&q.to_be_bytes());
                    b
                }
            };
            let writes = matches!(fc, 0x0F | 0x10 | 0x17);
            cx.push(
                format!("spec/app-6/quantity/fc-0x{fc:02X}/{label}"),
                format!("FC 0x{fc:02X} with quantity {q} (limit {max})"),
                format!("{APP}, section 6.{} (state diagram: quantity out of range)", fc),
                format!("A quantity of 0 or above the limit ({max} for this device) is answered with exception 03 (Illegal Data Value)."),
                if writes { vec![Tag::Write] } else { vec![] },
                vec![exchange(Send::Pdu(bytes), Compare::Exact, format!("quantity {q}"))],
            );
        }
    }
    // An address beyond the map: exception 02.
    if let Some(addr) = beyond_map(p) {
        for fc in [0x03u8, 0x04] {
            if !cx.supports(fc) {
                continue;
            }
            let req = if fc == 3 {
                Request::ReadHoldingRegisters {
                    address: addr,
                    quantity: 1,
                }
            } else {
                Request::ReadInputRegisters {
                    address: addr,
                    quantity: 1,
                }
            };
            cx.push(
                format!("spec/app-6/address-beyond-map/fc-0x{fc:02X}"),
                format!("FC 0x{fc:02X} at 0x{addr:04X}, past the last register"),
                format!("{APP}, section 6.{fc} (state diagram: starting address + quantity out of range)"),
                "A read of an address the device does not have is answered with exception 02 (Illegal Data Address).",
                vec![],
                vec![exchange(Send::Pdu(pdu(&req)), Compare::Exact, format!("address 0x{addr:04X}"))],
            );
        }
    }
    // Byte count disagreeing with the quantity: exception 03.
    if cx.supports(0x10) {
        let a = first_reg(p, Table::Holding);
        let mut b = pdu(&Request::WriteMultipleRegisters {
            address: a,
            values: vec![0, 0],
        });
        b[5] = 2; // says 2 bytes while quantity is 2 registers (4 bytes) and 4 bytes follow
        cx.push(
            "spec/app-6.12/byte-count-mismatch/fc-0x10".into(),
            "FC 16 whose byte count disagrees with its quantity",
            format!("{APP}, section 6.12"),
            "A byte count that is not 2 x quantity is answered with exception 03 (Illegal Data Value); the drive keeps answering.",
            vec![Tag::Write],
            vec![
                exchange(Send::Pdu(b), Compare::Exact, "byte count 2 for 2 registers"),
                cx.probe(),
            ],
        );
    }
    if cx.supports(0x0F) {
        let mut b = pdu(&Request::WriteMultipleCoils {
            address: 0,
            quantity: 9,
            data: vec![0, 0],
        });
        b[5] = 1;
        b.pop();
        cx.push(
            "spec/app-6.11/byte-count-mismatch/fc-0x0F".into(),
            "FC 15 whose byte count disagrees with its quantity",
            format!("{APP}, section 6.11"),
            "A byte count that is not ceil(quantity / 8) is answered with exception 03 (Illegal Data Value).",
            vec![Tag::Write],
            vec![exchange(Send::Pdu(b), Compare::Exact, "byte count 1 for 9 coils"), cx.probe()],
        );
    }
    // Truncated PDUs: a supported function code with data cut short.
    for fc in [0x03u8, 0x04, 0x01, 0x02, 0x06, 0x10] {
        if !cx.supports(fc) {
            continue;
        }
        cx.push(
            format!("spec/app-6/truncated-pdu/fc-0x{fc:02X}"),
            format!("FC 0x{fc:02X} with its data cut to 2 bytes"),
            format!("{APP}, section 6 (request PDU layouts) and 7"),
            "A request too short for its function code is rejected (exception 03) or ignored, never answered as if valid; the drive keeps answering.",
            if matches!(fc, 0x06 | 0x10) { vec![Tag::Write] } else { vec![] },
            vec![exchange(Send::Pdu(vec![fc, 0x00, 0x01]), Compare::RejectOrIgnore, "3-byte PDU"), cx.probe()],
        );
    }
    // FC 05 values other than ON/OFF.
    if cx.supports(0x05) {
        let addr = p.coils.first().map_or(0, |c| c.get_ref().address);
        cx.push(
            "spec/app-6.5/write-coil-illegal-value".into(),
            "FC 05 with value 0x1234",
            format!("{APP}, section 6.5"),
            "A Write Single Coil value other than 0xFF00 or 0x0000 is answered with exception 03 (Illegal Data Value).",
            vec![Tag::Write],
            vec![exchange(
                Send::Pdu(pdu(&Request::WriteSingleCoil { address: addr, value: 0x1234 })),
                Compare::Exact,
                "value 0x1234",
            )],
        );
    }
}

fn tcp_cases(cx: &mut Ctx) {
    let probe = probe_pdu(cx.p);
    cx.push(
        "tcp/mbap/transaction-id-echo".into(),
        "transaction ids 0x0000, 0x1234 and 0xFFFF are echoed",
        format!("{TCPG}, section 3.1.3 (MBAP header)"),
        "The server copies the transaction identifier of the request into the response, and answers with protocol identifier 0 and a length field equal to the bytes that follow it.",
        vec![Tag::TcpOnly],
        vec![
            exchange(Send::Pdu(probe.clone()), Compare::Structure, "first request"),
            exchange(Send::Pdu(probe.clone()), Compare::Structure, "second request"),
            exchange(Send::Pdu(probe.clone()), Compare::Structure, "third request"),
        ],
    );
    cx.push(
        "tcp/mbap/request-protocol-id-nonzero".into(),
        "a request with protocol id 1 is not answered",
        format!("{TCPG}, section 3.1.3 and 4.4.1 (MBAP checks)"),
        "A request whose protocol identifier is not 0 (Modbus) is discarded; the server keeps serving the connection.",
        vec![Tag::TcpOnly],
        vec![
            exchange(
                Send::Mutated { pdu: probe.clone(), mutation: Mutation::ProtocolId(1) },
                Compare::Exact,
                "protocol id 1",
            ),
            Step::Reconnect,
            cx.probe(),
        ],
    );
    for (label, delta) in [("length-plus-1", 1i16), ("length-minus-1", -1)] {
        cx.push(
            format!("tcp/mbap/request-{label}"),
            format!("a request whose MBAP length is off by {delta}"),
            format!("{TCPG}, section 3.1.3 and 4.4.1"),
            "A request whose MBAP length disagrees with its PDU is not answered as a valid request, and the server recovers on a new connection.",
            vec![Tag::TcpOnly],
            vec![
                exchange(
                    Send::Mutated { pdu: probe.clone(), mutation: Mutation::LengthDelta(delta) },
                    Compare::RejectOrIgnore,
                    format!("length field {delta:+}"),
                ),
                Step::Reconnect,
                cx.probe(),
            ],
        );
    }
    for k in [2usize, 4] {
        cx.push(
            format!("tcp/pipeline/{k}-requests-one-segment"),
            format!("{k} requests in one TCP segment"),
            format!("{TCPG}, section 4.2.1 (several requests may be pipelined)"),
            "Requests that arrive together in one segment are all answered, in order, each with its own transaction id.",
            vec![Tag::TcpOnly],
            vec![exchange(Send::Batch(vec![probe.clone(); k]), Compare::Structure, format!("{k} requests"))],
        );
    }
    cx.push(
        "tcp/segment/request-split".into(),
        "one request split across two TCP segments 5 ms apart",
        format!("{TCPG}, section 4.2.1 (a TCP stream has no message boundaries)"),
        "A request whose bytes arrive in two segments is answered once, as if it had arrived whole.",
        vec![Tag::TcpOnly],
        vec![exchange(
            Send::Mutated { pdu: probe.clone(), mutation: Mutation::Split { at: 4, gap_us: 5_000 } },
            Compare::Structure,
            "split after 4 bytes",
        )],
    );
    for unit in [0u8, 1, 247, 255] {
        cx.push(
            format!("tcp/unit-id/{unit}"),
            format!("a request to unit id {unit}"),
            format!("{TCPG}, section 4.4.1.2 (unit identifier)"),
            "The server answers the unit ids its profile says it answers, echoing the unit id, and ignores the others.",
            vec![Tag::TcpOnly],
            vec![exchange(Send::PduToUnit { pdu: probe.clone(), unit }, Compare::Structure, format!("unit {unit}"))],
        );
    }
    cx.push(
        "tcp/pdu/over-253-bytes".into(),
        "a request with a 254-byte PDU (MBAP length 255)",
        format!("{APP}, section 4.1 (PDU size limit); {TCPG} 4.4.1"),
        "A frame longer than the 253-byte PDU limit is not answered as a valid request; the server recovers on a new connection.",
        vec![Tag::TcpOnly],
        vec![
            exchange(Send::Pdu(vec![0x03; 254]), Compare::RejectOrIgnore, "254-byte PDU"),
            Step::Reconnect,
            cx.probe(),
        ],
    );
}

fn rtu_cases(cx: &mut Ctx) {
    let probe = probe_pdu(cx.p);
    cx.push(
        "rtu/crc/bad-crc-silence".into(),
        "a request with a wrong CRC is not answered",
        format!("{SER}, section 2.5.1.2 (CRC checking)"),
        "A frame whose CRC does not match is discarded without a response; the drive keeps answering valid frames.",
        vec![Tag::RtuOnly],
        vec![
            exchange(Send::Mutated { pdu: probe.clone(), mutation: Mutation::BadCrc }, Compare::Exact, "CRC inverted"),
            cx.probe(),
        ],
    );
    let other = if cx.unit == 247 {
        246
    } else {
        cx.unit.wrapping_add(1).max(1)
    };
    cx.push(
        "rtu/address/other-slave-silence".into(),
        format!("a request to slave {other} is ignored by slave {}", cx.unit),
        format!("{SER}, section 2.2 (slave addressing)"),
        "A frame addressed to another slave is not answered.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Send::PduToUnit {
                pdu: probe.clone(),
                unit: other,
            },
            Compare::Exact,
            format!("address {other}"),
        )],
    );
    cx.push(
        "rtu/address/broadcast-no-reply".into(),
        "a broadcast (address 0) read is not answered",
        format!("{SER}, section 2.1 (broadcast mode: no reply)"),
        "No slave answers a frame sent to address 0.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Send::PduToUnit {
                pdu: probe.clone(),
                unit: 0,
            },
            Compare::Exact,
            "address 0",
        )],
    );
    cx.push(
        "rtu/framing/request-split-within-t1.5".into(),
        "a request whose bytes arrive in two writes, back to back",
        format!("{SER}, section 2.5.1.1 (RTU framing)"),
        "A frame delivered in pieces without an inter-character silence is answered once.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Send::Mutated {
                pdu: probe.clone(),
                mutation: Mutation::Split { at: 3, gap_us: 0 },
            },
            Compare::Structure,
            "split after 3 bytes",
        )],
    );
    if cx.supports(0x08) {
        let diag = |sub: u16, data: u16| {
            pdu(&Request::Diagnostics {
                sub_function: sub,
                data: data.to_be_bytes().to_vec(),
            })
        };
        cx.push(
            "rtu/fc08/return-query-data".into(),
            "FC 08/00 echoes its data",
            format!("{SER}, section 6.1.1; {APP} 6.8"),
            "Return Query Data echoes the request's data field unchanged.",
            vec![Tag::RtuOnly],
            vec![exchange(
                Send::Pdu(diag(0x00, 0xA537)),
                Compare::Exact,
                "data 0xA537",
            )],
        );
        let mut steps = vec![
            exchange(Send::Pdu(diag(0x0A, 0)), Compare::Exact, "clear counters"),
            exchange(
                Send::Pdu(probe.clone()),
                Compare::Structure,
                "one valid request",
            ),
            exchange(
                Send::Mutated {
                    pdu: probe.clone(),
                    mutation: Mutation::BadCrc,
                },
                Compare::Exact,
                "one bad CRC",
            ),
            exchange(
                Send::PduToUnit {
                    pdu: probe.clone(),
                    unit: other,
                },
                Compare::Exact,
                "one frame for another slave",
            ),
            exchange(
                Send::Pdu(vec![0x55, 0, 0]),
                Compare::Exact,
                "one exception (illegal function)",
            ),
        ];
        for (sub, what) in [
            (0x0Bu16, "bus message count"),
            (0x0C, "bus communication (CRC) error count"),
            (0x0D, "exception count"),
            (0x0E, "slave message count"),
            (0x0F, "no-response count"),
        ] {
            if cx.p.diagnostics.iter().any(|d| d.sub_function == sub) {
                steps.push(exchange(Send::Pdu(diag(sub, 0)), Compare::Exact, what));
            }
        }
        cx.push(
            "rtu/fc08/counters".into(),
            "FC 08 counters after a known sequence",
            format!("{SER}, section 6.1 (diagnostic counters)"),
            "After Clear Counters, the bus message, CRC error, exception, slave message and no-response counters count exactly the frames that followed.",
            vec![Tag::RtuOnly],
            steps,
        );
    }
}

fn first_reg(p: &Profile, table: Table) -> u16 {
    p.registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.access.readable() && (r.table == table || r.table == Table::Both))
        .map_or(0, |r| r.address)
}

/// The first address past every register and reserved range, if there is one.
fn beyond_map(p: &Profile) -> Option<u16> {
    let end = p
        .registers
        .iter()
        .map(|r| r.get_ref().end())
        .chain(p.reserved.iter().map(|r| u32::from(r.get_ref().end) + 1))
        .max()?;
    u16::try_from(end).ok()
}

fn profile_cases(cx: &mut Ctx) {
    let p = cx.p;
    let pid = p.device.id.clone();
    let watchdog = p.watchdog.as_ref().map(|w| w.register);
    for r in p.registers.iter().map(|r| r.get_ref()) {
        let table = if r.table == Table::Input {
            Table::Input
        } else {
            Table::Holding
        };
        let read = pdu(&cx.read_request(r.address, u16::from(r.width), table));
        if r.access.readable() && (cx.supports(0x03) || cx.supports(0x04)) {
            cx.push(
                format!("profile/{pid}/read/{}", reg_slug(r)),
                format!("read {} at its width", r.name),
                format!(
                    "{} register map: 0x{:04X} {}",
                    p.device.name, r.address, r.name
                ),
                format!(
                    "Register 0x{:04X} ({} register{}) is readable and holds a value in {}..={}.",
                    r.address,
                    r.width,
                    if r.width == 2 {
                        "s, one 32-bit value"
                    } else {
                        ""
                    },
                    r.range().0,
                    r.range().1
                ),
                vec![],
                vec![exchange(Send::Pdu(read.clone()), Compare::InRange, "read")],
            );
        }
        if !cx.can_write_registers() || Some(r.address) == watchdog {
            continue;
        }
        let mut tags = vec![Tag::Write];
        if r.motion {
            tags.push(Tag::Motion);
        }
        if r.destructive {
            tags.push(Tag::Destructive);
        }
        if r.access.writable() {
            let v = probe_value(r);
            let mut steps = Vec::new();
            let restorable = r.access.readable() && !r.motion;
            if restorable {
                steps.push(capture(
                    Send::Pdu(read.clone()),
                    Compare::InRange,
                    0,
                    "read the current value",
                ));
            }
            steps.push(exchange(
                Send::Pdu(pdu(&cx.write_request(r.address, encode_value(p, r, v)))),
                Compare::Exact,
                format!("write {v}"),
            ));
            if r.access.readable() {
                steps.push(exchange(
                    Send::Pdu(read.clone()),
                    Compare::Exact,
                    format!("read back {v}"),
                ));
            }
            if restorable {
                steps.push(exchange(
                    Send::Restore {
                        address: r.address,
                        slot: 0,
                    },
                    Compare::Exact,
                    "restore",
                ));
            }
            cx.push(
                format!("profile/{pid}/write/{}", reg_slug(r)),
                format!("write {} in range and read it back", r.name),
                format!("{} register map: 0x{:04X} {}", p.device.name, r.address, r.name),
                format!("Register 0x{:04X} accepts {v} and reads it back unchanged, in the device's word order.", r.address),
                tags.clone(),
                steps,
            );
            let (lo, hi) = r.natural_range();
            let (min, max) = r.range();
            let bad = if max < hi {
                Some(max + 1)
            } else if min > lo {
                Some(min - 1)
            } else {
                None
            };
            if let Some(b) = bad {
                cx.push(
                    format!("profile/{pid}/write-out-of-range/{}", reg_slug(r)),
                    format!("write {} = {b}, outside {min}..={max}", r.name),
                    format!("{} register map: 0x{:04X} {} range", p.device.name, r.address, r.name),
                    format!("A value outside {min}..={max} is rejected with an exception and not stored."),
                    tags.clone(),
                    vec![
                        exchange(
                            Send::Pdu(pdu(&cx.write_request(r.address, encode_value(p, r, b)))),
                            Compare::Exact,
                            format!("write {b}"),
                        ),
                        exchange(Send::Pdu(read.clone()), Compare::InRange, "the value is still in range"),
                    ],
                );
            }
        } else {
            let v = r.default.unwrap_or(0);
            cx.push(
                format!("profile/{pid}/write-read-only/{}", reg_slug(r)),
                format!("write read-only {}", r.name),
                format!(
                    "{} register map: 0x{:04X} {} (read-only)",
                    p.device.name, r.address, r.name
                ),
                "A write to a read-only register is rejected with an exception.",
                vec![Tag::Write],
                vec![exchange(
                    Send::Pdu(pdu(&cx.write_request(r.address, encode_value(p, r, v)))),
                    Compare::Exact,
                    "write",
                )],
            );
        }
    }
    for res in p.reserved.iter().map(|r| r.get_ref()) {
        if !(cx.supports(0x03) || cx.supports(0x04)) {
            break;
        }
        cx.push(
            format!("profile/{pid}/reserved/0x{:04X}", res.start),
            format!("read reserved 0x{:04X}..=0x{:04X}", res.start, res.end),
            format!("{} register map: reserved", p.device.name),
            "A read of a reserved address is answered with exception 02 (Illegal Data Address).",
            vec![],
            vec![exchange(
                Send::Pdu(pdu(&cx.read_request(res.start, 1, Table::Holding))),
                Compare::Exact,
                "read",
            )],
        );
    }
    // Coils: write ON, read back, restore.
    if cx.supports(0x05) && cx.supports(0x01) {
        for c in p
            .coils
            .iter()
            .map(|c| c.get_ref())
            .filter(|c| c.access.writable())
        {
            let read = pdu(&Request::ReadCoils {
                address: c.address,
                quantity: 1,
            });
            let mut tags = vec![Tag::Write];
            if c.motion {
                tags.push(Tag::Motion);
            }
            cx.push(
                format!("profile/{pid}/coil/{}-{}", c.address, slug(&c.name)),
                format!("switch {} on and read it back", c.name),
                format!("{}: coil {} {}", p.device.name, c.address, c.name),
                "Write Single Coil ON is echoed and Read Coils then shows the coil on.",
                tags,
                vec![
                    capture(Send::Pdu(read.clone()), Compare::Structure, 0, "read"),
                    exchange(
                        Send::Pdu(pdu(&Request::WriteSingleCoil {
                            address: c.address,
                            value: 0xFF00,
                        })),
                        Compare::Exact,
                        "ON",
                    ),
                    exchange(Send::Pdu(read), Compare::Exact, "read back"),
                    exchange(
                        Send::Restore {
                            address: c.address,
                            slot: 0,
                        },
                        Compare::Exact,
                        "restore",
                    ),
                ],
            );
        }
    }
    if cx.supports(0x02) {
        for d in p.discrete_inputs.iter().map(|c| c.get_ref()) {
            cx.push(
                format!(
                    "profile/{pid}/discrete-input/{}-{}",
                    d.address,
                    slug(&d.name)
                ),
                format!("read {}", d.name),
                format!("{}: discrete input {} {}", p.device.name, d.address, d.name),
                "The input is readable with Read Discrete Inputs.",
                vec![],
                vec![exchange(
                    Send::Pdu(pdu(&Request::ReadDiscreteInputs {
                        address: d.address,
                        quantity: 1,
                    })),
                    Compare::Structure,
                    "read",
                )],
            );
        }
    }
    // Vendor mnemonics.
    for m in p.mnemonics.iter().map(|m| m.get_ref()) {
        let Some(w) = Mnemonic::from_name(&m.name) else {
            continue;
        };
        if m.read && cx.supports(0x41) {
            cx.push(
                format!("profile/{pid}/mnemonic/{}/read", slug(&m.name)),
                format!("FC 0x41 read of {}", m.name),
                format!("{}: vendor FC 0x41, mnemonic {}", p.device.name, m.name),
                "A readable mnemonic is answered with its parameter string.",
                vec![],
                vec![exchange(
                    Send::Pdu(pdu(&Request::VendorRead { mnemonic: w })),
                    Compare::Structure,
                    "read",
                )],
            );
        }
        if m.write
            && cx.supports(0x42)
            && let Some(ex) = &m.example
        {
            let mut tags = vec![Tag::Write];
            if m.motion {
                tags.push(Tag::Motion);
            }
            if m.destructive {
                tags.push(Tag::Destructive);
            }
            cx.push(
                format!("profile/{pid}/mnemonic/{}/write", slug(&m.name)),
                format!("FC 0x42 write of {}{}", m.name, ex),
                format!("{}: vendor FC 0x42, mnemonic {}", p.device.name, m.name),
                "A writable mnemonic accepts the manual's example parameters and echoes the mnemonic.",
                tags,
                vec![exchange(
                    Send::Pdu(pdu(&Request::VendorWrite { mnemonic: w, params: ex.as_bytes().to_vec() })),
                    Compare::Exact,
                    "write",
                )],
            );
        }
    }
    let unknown = Mnemonic::from_name("QQ").expect("2 ASCII bytes");
    if cx.supports(0x41) {
        cx.push(
            format!("profile/{pid}/mnemonic/unknown/read"),
            "FC 0x41 read of an unknown mnemonic",
            format!("{}: vendor FC 0x41", p.device.name),
            "A mnemonic the drive does not know is answered with an exception.",
            vec![],
            vec![exchange(
                Send::Pdu(pdu(&Request::VendorRead { mnemonic: unknown })),
                Compare::Exact,
                "QQ",
            )],
        );
    }
    // Device identification.
    if cx.supports(0x2B) && !p.identification.is_empty() {
        for (code, label) in [(1u8, "basic"), (2, "regular")] {
            cx.push(
                format!("profile/{pid}/identification/{label}"),
                format!("read device identification, {label} stream"),
                format!("{APP}, section 6.21; {} device id", p.device.name),
                "Read Device Identification returns the objects of the requested category with a consistent object list.",
                vec![],
                vec![exchange(
                    Send::Pdu(pdu(&Request::ReadDeviceId { read_code: code, object_id: 0 })),
                    Compare::Structure,
                    label,
                )],
            );
        }
        cx.push(
            format!("profile/{pid}/identification/individual-missing"),
            "read an individual identification object that does not exist",
            format!("{APP}, section 6.21"),
            "An individual access to an object id the device does not have is answered with exception 02.",
            vec![],
            vec![exchange(
                Send::Pdu(pdu(&Request::ReadDeviceId { read_code: 4, object_id: 0x7F })),
                Compare::Exact,
                "object 0x7F",
            )],
        );
    }
}

fn canopen_cases(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
    let manual =
        "SD2x manual, section 3.6 (FC 43 Encapsulated Interface Transport) and 3.8 (SDO errors)";
    for o in p.objects.iter().map(|o| o.get_ref()) {
        let read = pdu(&Request::CanOpen(CanOpenAccess::read(
            node,
            o.index,
            o.subindex,
            o.ty.size() as u16,
        )));
        if o.access.readable() {
            cx.push(
                format!(
                    "profile/{}/object/{}-{}/read",
                    p.device.id,
                    o.index,
                    slug(&o.name)
                ),
                format!("FC 43/0x0D read of object {} {}", o.index, o.name),
                manual,
                "The object is read with FC 43 / MEI 0x0D, its size in bytes, little-endian data.",
                vec![],
                vec![exchange(
                    Send::Pdu(read.clone()),
                    Compare::Structure,
                    "read",
                )],
            );
        }
        if o.access == Access::Ro {
            let data = vec![0u8; o.ty.size()];
            cx.push(
                format!("profile/{}/object/{}-{}/write-read-only", p.device.id, o.index, slug(&o.name)),
                format!("FC 43/0x0D write of read-only object {}", o.index),
                manual,
                "A write to a read-only object is answered with the extended exception carrying SDO error 0xFFFF000A.",
                vec![Tag::Write],
                vec![exchange(
                    Send::Pdu(pdu(&Request::CanOpen(CanOpenAccess::write(node, o.index, o.subindex, data)))),
                    Compare::Exact,
                    "write",
                )],
            );
        }
    }
    // Both views of a mirrored value agree: the register pair in the profile's word order, the object
    // little-endian. This is where a device's word order shows against its manual.
    for o in p.objects.iter().map(|o| o.get_ref()) {
        let Some(reg) = o
            .register
            .and_then(|a| p.register_at(a, true).filter(|r| r.address == a))
        else {
            continue;
        };
        if reg.width != 2 || !o.access.readable() || !reg.access.readable() {
            continue;
        }
        let read_reg = pdu(&cx.read_request(reg.address, 2, reg.table));
        let read_obj = pdu(&Request::CanOpen(CanOpenAccess::read(
            node,
            o.index,
            o.subindex,
            o.ty.size() as u16,
        )));
        cx.push(
            format!("profile/{}/object/{}-{}/agrees-with-register", p.device.id, o.index, slug(&o.name)),
            format!("object {} and registers {}..{} hold the same value", o.index, reg.address, reg.address + 1),
            format!("{manual}; section 4.3 (byte order of process data)"),
            "A 32-bit value read as two registers in the device's word order equals the same value read as an FC 43 object (little-endian).",
            vec![],
            vec![
                capture(Send::Pdu(read_reg), Compare::InRange, 0, "read the register pair"),
                capture(Send::Pdu(read_obj), Compare::Structure, 1, "read the object"),
                Step::Agree { registers: 0, object: 1, note: "both views agree".into() },
            ],
        );
    }
    let missing = p
        .objects
        .iter()
        .map(|o| o.get_ref().index)
        .max()
        .unwrap_or(0)
        .saturating_add(100);
    cx.push(
        format!("profile/{}/object/missing/read", p.device.id),
        format!("FC 43/0x0D read of object {missing}, which does not exist"),
        manual,
        "A read of an object that is not in the dictionary is answered with SDO error 0xFFFF000B.",
        vec![],
        vec![exchange(
            Send::Pdu(pdu(&Request::CanOpen(CanOpenAccess::read(
                node, missing, 0, 2,
            )))),
            Compare::Exact,
            "read",
        )],
    );
    if let Some(o) = p
        .objects
        .iter()
        .map(|o| o.get_ref())
        .find(|o| o.access.readable())
    {
        cx.push(
            format!("profile/{}/object/wrong-length/read", p.device.id),
            format!("FC 43/0x0D read of object {} with byte count 3", o.index),
            manual,
            "A read whose byte count does not match the object's size is answered with an SDO length error.",
            vec![],
            vec![exchange(
                Send::Pdu(pdu(&Request::CanOpen(CanOpenAccess::read(node, o.index, o.subindex, 3)))),
                Compare::Exact,
                "read 3 bytes",
            )],
        );
    }
}

fn ds402_cases(cx: &mut Ctx) {
    let p = cx.p;
    let Some(w) = p.watchdog.as_ref() else { return };
    let Some(ctrl) = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.access.writable() && r.address < w.register && w.register - r.address <= 3)
    else {
        return;
    };
    let base = ctrl.address;
    let n = (w.register - base + 1) as usize;
    let ro = |pred: &dyn Fn(&Register) -> bool| {
        p.registers
            .iter()
            .map(|r| r.get_ref())
            .find(|r| r.access == Access::Ro && r.width == 1 && pred(r))
            .map(|r| r.address)
    };
    let status = ro(&|_| true).unwrap_or(2000);
    let error_code = ro(&|r| r.name.to_ascii_lowercase().contains("error")).unwrap_or(status);
    let write = |cw: u16, wd: u16| {
        let mut v = vec![0u16; n];
        v[0] = cw;
        v[n - 1] = wd;
        Send::Pdu(pdu(&Request::WriteMultipleRegisters {
            address: base,
            values: v,
        }))
    };
    // Only the state words: speeds and currents depend on the exact time of the read.
    let read = |address: u16| {
        Send::Pdu(pdu(&Request::ReadHoldingRegisters {
            address,
            quantity: 1,
        }))
    };
    let reset = || {
        vec![
            exchange(
                write(0x80, 0),
                Compare::Exact,
                "fault reset (0x80), watchdog off",
            ),
            exchange(write(0x00, 0), Compare::Exact, "control word 0"),
            exchange(read(status), Compare::Exact, "status: switch on disabled"),
        ]
    };
    let manual =
        "SD2x manual, section 4 (process data), 6.1 (drive operation); CiA 402 state machine";
    let mut steps = reset();
    steps.extend([
        exchange(write(0x06, 0), Compare::Exact, "shutdown (0x06)"),
        exchange(read(status), Compare::Exact, "status: ready to switch on"),
        exchange(write(0x07, 0), Compare::Exact, "switch on (0x07)"),
        exchange(read(status), Compare::Exact, "status: switched on"),
        exchange(write(0x0F, 0), Compare::Exact, "enable operation (0x0F)"),
        exchange(read(status), Compare::Exact, "status: operation enabled"),
        exchange(write(0x06, 0), Compare::Exact, "shutdown again"),
        exchange(read(status), Compare::Exact, "status: ready to switch on"),
    ]);
    cx.push(
        format!("profile/{}/ds402/enable-sequence", p.device.id),
        "DS402: fault reset, shutdown, switch on, enable operation, disable",
        manual,
        "The status word follows the control word through the DS402 states: switch on disabled, ready to switch on, switched on, operation enabled, and back.",
        vec![Tag::Write, Tag::Motion],
        steps,
    );
    let mut steps = reset();
    steps.extend([
        exchange(
            write(0x06, 100),
            Compare::Exact,
            "shutdown with watchdog 100 ms",
        ),
        Step::Wait(Duration::from_millis(50)),
        exchange(read(status), Compare::Exact, "50 ms later: not faulted"),
        exchange(
            read(error_code),
            Compare::Exact,
            "50 ms later: no error code",
        ),
        Step::Wait(Duration::from_millis(150)),
        exchange(
            read(status),
            Compare::Exact,
            "200 ms later: faulted by the watchdog",
        ),
        exchange(
            read(error_code),
            Compare::Exact,
            "200 ms later: the watchdog's error code",
        ),
    ]);
    steps.extend(reset());
    cx.push(
        format!("profile/{}/ds402/watchdog", p.device.id),
        "RxPDO watchdog: a 100 ms watchdog not rewritten trips the drive",
        format!("SD2x manual, section 4.1 and 6.1 (watchdog register {})", w.register),
        "With a watchdog time set, the drive is not faulted before the time elapses and is faulted, with its error code, once the RxPDO has not been rewritten for longer than the time.",
        vec![Tag::Write, Tag::Motion, Tag::Destructive],
        steps,
    );
}
