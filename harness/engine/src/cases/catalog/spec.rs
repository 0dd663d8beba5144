//! Generic cases from the Modbus application protocol: what every server must do with requests it
//! cannot serve (exception codes 01, 02, 03), whatever its profile.

use super::around::{Around, around_write};
use super::mcode::IoPoints;
use super::{APP, Ctx, exchange, pdu};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::FunctionCode;
use codec::Request;
use drives::profile::{Profile, Table};

/// The spec suite, family by family.
pub(super) fn cases(cx: &mut Ctx) {
    unsupported_functions(cx);
    quantities_out_of_range(cx);
    quantities_above_spec(cx);
    addresses_beyond_map(cx);
    byte_count_mismatches(cx);
    truncated_pdus(cx);
    trailing_bytes(cx);
    request_fc_over_127(cx);
    request_fc_zero(cx);
    quantity_over_device_limit_mapped(cx);
    unsupported_mei_type(cx);
    write_coil_illegal_value(cx);
    bit_padding(cx);
    no_partial_write(cx);
    write_before_read(cx);
    super::public_fc::cases(cx);
}

/// Unsupported function codes: exception 01, for every public function code the profile does not declare
/// (FC 2B aside: its MEI types have rules of their own) and three unassigned ones (issue 15: a drive that
/// serves FC 06 although its manual does not list it is caught only if FC 06 is asked). A draft profile
/// lacks codes nobody asked about: only those a probe saw refused count as unsupported.
fn unsupported_functions(cx: &mut Ctx) {
    let candidates = [
        0x07u8, 0x0B, 0x0C, 0x11, 0x14, 0x16, 0x18, 0x01, 0x02, 0x05, 0x06, 0x0F, 0x17, 0x08, 0x04,
        0x03, 0x10, 0x15, 0x09, 0x55, 0x7F,
    ];
    for fc in candidates {
        if cx.supports(fc) {
            continue;
        }
        if let Some(d) = &cx.p.draft
            && !d.unsupported_functions.contains(&fc.into())
        {
            continue;
        }
        // A request of plausible length for the code, so only the code is at fault.
        let body: Vec<u8> = match fc {
            0x07 | 0x0B | 0x0C | 0x11 => vec![fc],
            0x0F => vec![fc, 0, 0, 0, 1, 1, 1],
            0x17 => vec![fc, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 0],
            0x14 => vec![fc, 7, 6, 0, 1, 0, 0, 0, 1],
            0x16 => vec![fc, 0, 0, 0xFF, 0xFF, 0, 0],
            0x18 => vec![fc, 0, 0],
            0x10 => vec![fc, 0, 0, 0, 1, 2, 0, 0],
            // One record of file 1 (a drive serving it would write a record nothing here can read back).
            0x15 => vec![fc, 9, 6, 0, 1, 0, 0, 0, 1, 0, 0],
            _ => vec![fc, 0, 0, 0, 1],
        };
        // A code that writes (coil 0 or register 0) could change the drive if it were served after all:
        // what it would change is kept and put back.
        let mut a = Around::new();
        match fc {
            0x05 | 0x0F => a.keep_coils(cx, 0, 1),
            0x06 | 0x10 | 0x16 | 0x17 => a.keep_registers(cx, 0, 1),
            _ => {}
        }
        let tags = if matches!(fc, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17) {
            vec![Tag::Write]
        } else {
            vec![]
        };
        let steps = a.wrap(vec![exchange(
            Outgoing::Pdu(body),
            Compare::Exact,
            format!("FC 0x{fc:02X}"),
        )]);
        cx.push(
            format!("spec/app-7/unsupported-function/fc-0x{fc:02X}"),
            format!("function code 0x{fc:02X} is not supported"),
            format!("{APP}, section 7 (exception codes), 6 (state diagrams)"),
            "A function code the server does not implement is answered with exception 01 (Illegal Function) in a response whose function code is the request's with the high bit set, and the exception response is exactly 2 bytes.",
            tags,
            steps,
        );
    }
}

/// A request whose function code is 0x83, in the range App 4.1 reserves for exception responses: exception 01,
/// no answer, or a close (`request-fc-over-127`), and the drive keeps answering. The body is a read's, so that
/// a drive that masks the high bit reads, and writes nothing.
fn request_fc_over_127(cx: &mut Ctx) {
    cx.push(
        "spec/app-4.1/request-fc-over-127/fc-0x83".into(),
        "a request with function code 0x83, an exception response's code",
        format!("{APP}, sections 4.1 and 7"),
        "A request whose function code is in the range of exception responses (128-255) is refused with exception 01 or dropped, never served, and the drive keeps answering.",
        vec![],
        vec![
            exchange(
                Outgoing::Pdu(vec![0x83, 0x00, 0x00, 0x00, 0x01]),
                Compare::Exact,
                "FC 0x83",
            ),
            cx.liveness(),
        ],
    );
}

/// A request whose function code is 0, which App 4.1 says is not valid: exception 01, no answer, or a close
/// (`request-fc-zero`), and the drive keeps answering. The body is a read's (FC 03's with its code's bits
/// cleared, as one bit flip of FC 01, 02 or 04's may give).
fn request_fc_zero(cx: &mut Ctx) {
    cx.push(
        "spec/app-4.1/request-fc-zero/fc-0x00".into(),
        "a request with function code 0, which is not valid",
        format!("{APP}, sections 4.1 and 7"),
        "A request whose function code is 0 (not valid) is refused with exception 01 or dropped, never served, and the drive keeps answering.",
        vec![],
        vec![
            exchange(
                Outgoing::Pdu(vec![0x00, 0x00, 0x00, 0x00, 0x01]),
                Compare::Exact,
                "FC 0x00",
            ),
            cx.liveness(),
        ],
    );
}

/// FC 43 with MEI type 0x4E, which no interface has (App 6.19), where the profile has FC 43: refused, with the
/// code the drive keeps to (`unsupported-mei-type`: 01, 02 or 03).
fn unsupported_mei_type(cx: &mut Ctx) {
    if !cx.supports(FunctionCode::ENCAPSULATED_INTERFACE) {
        return;
    }
    cx.push(
        "spec/app-6.19/unsupported-mei-type/0x4E".into(),
        "FC 43 with MEI type 0x4E, which no interface has",
        format!("{APP}, sections 6.19 and 7"),
        "FC 43 with an MEI type the server does not serve is refused with an exception (01, 02 or 03, the same each time), and the drive keeps answering.",
        vec![],
        vec![
            exchange(
                Outgoing::Pdu(vec![0x2B, 0x4E, 0x01, 0x00]),
                Compare::Exact,
                "MEI type 0x4E",
            ),
            cx.liveness(),
        ],
    );
}

/// FC 03 of the device's limit + 1 registers over a range the map fills (readable holding registers end to
/// end, no register split, none a read clears), where the profile states a limit below the specification's:
/// refused (03, or 02) by a drive that keeps to its manual's limit, served by one whose limit is higher
/// (`quantity-over-device-limit-served`). Nothing where the map has no such range.
fn quantity_over_device_limit_mapped(cx: &mut Ctx) {
    let p = cx.p;
    let fc = FunctionCode::READ_HOLDING_REGISTERS;
    let Some(limit) = p.function(fc).and_then(|f| f.max_quantity) else {
        return;
    };
    let want = u32::from(limit) + 1;
    if want > u32::from(fc.max_quantity().unwrap_or(125)) {
        return;
    }
    let mut regs: Vec<&drives::profile::Register> = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.table != Table::Input)
        .collect();
    regs.sort_by_key(|r| r.address);
    let usable = |r: &drives::profile::Register| r.access.readable() && !r.read_clears;
    let start = regs.iter().enumerate().find_map(|(i, first)| {
        let mut end = u32::from(first.address);
        for r in &regs[i..] {
            if u32::from(r.address) != end || !usable(r) {
                return None;
            }
            end = r.end();
            if end - u32::from(first.address) == want {
                return Some(first.address);
            }
            if end - u32::from(first.address) > want {
                return None;
            }
        }
        None
    });
    let Some(address) = start else {
        return;
    };
    let q = want as u16;
    cx.push(
        "spec/app-6/quantity/fc-0x03/max-plus-1-mapped".to_string(),
        format!("FC 03 of {q} registers (limit {limit}) from 0x{address:04X}, every one mapped and readable"),
        format!("{APP}, section 6.3; the manual's limit"),
        format!("A quantity above the device's limit ({limit}) but within the specification's is refused (03 or 02), or served by a drive whose limit is higher than its manual states, the same way each time."),
        vec![],
        vec![exchange(
            Outgoing::Pdu(pdu(&Request::ReadHoldingRegisters {
                address,
                quantity: q,
            })),
            Compare::Structure,
            format!("quantity {q}"),
        )],
    );
}

/// The quantity-carrying functions, in the order their cases run.
const QUANTITY_FUNCTIONS: [u8; 7] = [0x01, 0x02, 0x03, 0x04, 0x0F, 0x10, 0x17];

/// Quantity 0 and max + 1 for every quantity-carrying function the profile supports: exception 03.
fn quantities_out_of_range(cx: &mut Ctx) {
    let p = cx.p;
    for fc in QUANTITY_FUNCTIONS {
        if !cx.supports(fc) {
            continue;
        }
        let max = cx.max_quantity(fc);
        for (label, q) in [("zero", 0u16), ("max-plus-1", max.saturating_add(1))] {
            let address = match fc {
                0x01 | 0x02 | 0x0F => 0,
                0x04 => first_reg(p, Table::Input),
                _ => first_reg(p, Table::Holding),
            };
            let (bytes, _) = quantity_request(fc, q, false, address);
            let writes = matches!(fc, 0x0F | 0x10 | 0x17);
            // What a drive that wrongly served the request would write is kept and put back.
            let mut a = Around::new();
            match fc {
                0x0F => a.keep_coils(cx, 0, q),
                0x10 => a.keep_registers(cx, first_reg(p, Table::Holding), q),
                0x17 => a.keep_registers(cx, first_reg(p, Table::Holding), 1),
                _ => {}
            }
            let steps = a.wrap(vec![exchange(
                Outgoing::Pdu(bytes),
                Compare::Exact,
                format!("quantity {q}"),
            )]);
            cx.push(
                format!("spec/app-6/quantity/fc-0x{fc:02X}/{label}"),
                format!("FC 0x{fc:02X} with quantity {q} (limit {max})"),
                format!("{APP}, section {} (state diagram: quantity out of range)", section(fc)),
                format!("A quantity of 0 or above the limit ({max} for this device) is answered with exception 03 (Illegal Data Value)."),
                if writes { vec![Tag::Write] } else { vec![] },
                steps,
            );
        }
        // FC 23's quantity to write has a limit of its own (121 in the specification): one above the
        // device's, where the profile declares one below the specification's (above it,
        // `write-spec-max-plus-1` is the same request).
        let wmax = p.function(fc).and_then(|f| f.max_write_quantity);
        if let Some(wmax) =
            wmax.filter(|&w| fc == 0x17 && w < FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY)
        {
            let q = wmax + 1;
            let address = first_reg(p, Table::Holding);
            let (bytes, _) = quantity_request(fc, q, true, address);
            let mut a = Around::new();
            a.keep_registers(cx, address, q);
            let steps = a.wrap(vec![exchange(
                Outgoing::Pdu(bytes),
                Compare::Exact,
                format!("quantity to write {q}"),
            )]);
            cx.push(
                format!("spec/app-6/quantity/fc-0x{fc:02X}/write-max-plus-1"),
                format!("FC 0x{fc:02X} with quantity to write {q} (limit {wmax})"),
                format!("{APP}, section {} (state diagram: quantity out of range)", section(fc)),
                format!("A quantity to write above the limit ({wmax} for this device) is answered with exception 03 (Illegal Data Value)."),
                vec![Tag::Write],
                steps,
            );
        }
    }
}

/// The specification's own quantity limits, which a device limit below them hides from the max + 1 cases
/// (issue 15): one above the specification's maximum where the profile's limit is below it (126 registers,
/// 124 for FC 16, 2001 bits, 1969 coils for FC 15), FC 23's write quantity 122 (one above 121), and a
/// quantity whose high byte is set while its low byte is within every limit (0x0101 registers, 0x0801 bits),
/// which firmware reading the quantity as one byte (as the MDrive and LMD manuals print the field) would
/// serve. All are above the specification's range: exception 03 by the state diagrams (02 where the range
/// runs past the map too, the freedom `exception-check-order`).
fn quantities_above_spec(cx: &mut Ctx) {
    let p = cx.p;
    for fc in QUANTITY_FUNCTIONS {
        if !cx.supports(fc) {
            continue;
        }
        let code = FunctionCode(fc);
        let spec = code.max_quantity().unwrap_or(125);
        let device = cx.max_quantity(fc);
        let high_byte = if matches!(fc, 0x01 | 0x02 | 0x0F) {
            0x0801
        } else {
            0x0101
        };
        let mut probes: Vec<(&str, u16, bool)> = Vec::new();
        if device < spec {
            probes.push(("spec-max-plus-1", spec + 1, false));
        }
        if fc == 0x17 {
            probes.push((
                "write-spec-max-plus-1",
                FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY + 1,
                true,
            ));
        }
        probes.push(("high-byte-set", high_byte, false));
        let address = probe_address(p, fc);
        for (label, q, write_quantity) in probes {
            let (bytes, carried) = quantity_request(fc, q, write_quantity, address);
            // What a drive that wrongly served the request could write (the data it carries, as it would
            // read them) is kept and put back, with what such a write needs around it.
            let mut a = Around::new();
            let mut tags = if matches!(fc, 0x0F | 0x10 | 0x17) {
                vec![Tag::Write]
            } else {
                vec![]
            };
            match &carried {
                Request::ReadWriteMultipleRegisters {
                    write_address,
                    values,
                    ..
                } => a.keep_registers(cx, *write_address, values.len() as u16),
                r => around_write(cx, r, &mut a, &mut tags),
            }
            let steps = a.wrap(vec![exchange(
                Outgoing::Pdu(bytes),
                Compare::Exact,
                format!("quantity {q} (0x{q:04X})"),
            )]);
            let field = if write_quantity {
                "quantity to write"
            } else if fc == 0x17 {
                "quantity to read"
            } else {
                "quantity"
            };
            let spec_max = if write_quantity {
                FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY
            } else {
                spec
            };
            let (title, requirement) = if label == "high-byte-set" {
                (
                    format!(
                        "FC 0x{fc:02X} with {field} 0x{q:04X} ({q}): high byte set, low byte {} within the limit",
                        q & 0xFF
                    ),
                    format!(
                        "The {field} is a 2-byte field: 0x{q:04X} ({q}, above the specification's {spec_max}) is answered with exception 03 (Illegal Data Value), not served as its low byte ({}).",
                        q & 0xFF
                    ),
                )
            } else {
                (
                    format!(
                        "FC 0x{fc:02X} with {field} {q}, one above the specification's {spec_max} (device limit {})",
                        if write_quantity {
                            p.function(code)
                                .and_then(|f| f.max_write_quantity)
                                .unwrap_or(spec_max)
                        } else {
                            device
                        }
                    ),
                    format!(
                        "A {field} above the specification's maximum ({spec_max}) is answered with exception 03 (Illegal Data Value), whatever the device's own limit."
                    ),
                )
            };
            cx.push(
                format!("spec/app-6/quantity/fc-0x{fc:02X}/{label}"),
                title,
                format!(
                    "{APP}, section {} (state diagram: quantity out of range)",
                    section(fc)
                ),
                requirement,
                tags,
                steps,
            );
        }
    }
}

/// The bytes of an `fc` request with quantity `q` (for FC 23 the quantity to read, or with `write_quantity`
/// the quantity to write) at `address` (both of FC 23's), and the request its data carry (what a drive that
/// took the quantity from its data would serve). A quantity whose data would not fit a PDU is sent with one
/// item of data and the quantity field alone changed.
fn quantity_request(fc: u8, q: u16, write_quantity: bool, address: u16) -> (Vec<u8>, Request) {
    let build = |q: u16| match fc {
        0x01 => Request::ReadCoils {
            address,
            quantity: q,
        },
        0x02 => Request::ReadDiscreteInputs {
            address,
            quantity: q,
        },
        0x03 => Request::ReadHoldingRegisters {
            address,
            quantity: q,
        },
        0x04 => Request::ReadInputRegisters {
            address,
            quantity: q,
        },
        0x0F => Request::WriteMultipleCoils {
            address,
            quantity: q,
            data: vec![0; (q as usize).div_ceil(8)],
        },
        0x10 => Request::WriteMultipleRegisters {
            address,
            values: vec![0; q as usize],
        },
        _ if write_quantity => Request::ReadWriteMultipleRegisters {
            read_address: address,
            read_quantity: 1,
            write_address: address,
            values: vec![0; q as usize],
        },
        _ => Request::ReadWriteMultipleRegisters {
            read_address: address,
            read_quantity: q,
            write_address: address,
            values: vec![0],
        },
    };
    let req = build(q);
    match req.to_bytes() {
        Ok(b) => (b, req),
        Err(_) => {
            let one = build(1);
            let mut b = pdu(&one);
            // FC 23's quantity to write follows its read address, quantity and write address.
            let at = if write_quantity { 7 } else { 3 };
            b[at..at + 2].copy_from_slice(&q.to_be_bytes());
            (b, one)
        }
    }
}

/// Where the cases above the specification's limits start: at an item a one-item request of `fc` serves
/// (and, for a write, with 0 a value it takes and no motion), so that a drive reading less than the whole
/// quantity field serves it instead of refusing it for its address; the quantity cases' own start where the
/// profile has none.
fn probe_address(p: &Profile, fc: u8) -> u16 {
    fn bit<'a>(bits: impl Iterator<Item = &'a drives::profile::Bit>, write: bool) -> u16 {
        bits.filter(|b| {
            if write {
                b.access == drives::profile::Access::Rw && !b.motion && !b.destructive
            } else {
                b.access.readable()
            }
        })
        .map(|b| b.address)
        .next()
        .unwrap_or(0)
    }
    match fc {
        0x01 => bit(p.coils.iter().map(|b| b.get_ref()), false),
        0x02 => bit(p.discrete_inputs.iter().map(|b| b.get_ref()), false),
        0x0F => bit(p.coils.iter().map(|b| b.get_ref()), true),
        // A one-register read of half of a 32-bit register is a choice of the drive's
        // (`partial-register-read`): a register of its own.
        0x03 | 0x04 => {
            let table = if fc == 0x03 {
                Table::Holding
            } else {
                Table::Input
            };
            p.registers
                .iter()
                .map(|r| r.get_ref())
                .find(|r| {
                    r.width == 1
                        && r.access.readable()
                        && (r.table == table || r.table == Table::Both)
                })
                .map_or_else(|| first_reg(p, table), |r| r.address)
        }
        _ => p
            .registers
            .iter()
            .map(|r| r.get_ref())
            .find(|r| r.access.readable() && settable(r, 0, 0))
            .map_or_else(|| first_reg(p, Table::Holding), |r| r.address),
    }
}

/// An address beyond the map: exception 02 (for a draft profile, only an address its probe read).
fn addresses_beyond_map(cx: &mut Ctx) {
    let p = cx.p;
    if let Some(addr) = beyond_map(p)
        && p.draft.as_ref().is_none_or(|d| d.scanned(addr))
    {
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
                format!("{APP}, section {} (state diagram: starting address + quantity out of range)", section(fc)),
                "A read of an address the device does not have is answered with exception 02 (Illegal Data Address).",
                vec![],
                vec![exchange(Outgoing::Pdu(pdu(&req)), Compare::Exact, format!("address 0x{addr:04X}"))],
            );
        }
    }
}

/// Byte count disagreeing with the quantity: exception 03.
fn byte_count_mismatches(cx: &mut Ctx) {
    let p = cx.p;
    if cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS) {
        let a = first_reg(p, Table::Holding);
        let mut b = pdu(&Request::WriteMultipleRegisters {
            address: a,
            values: vec![0, 0],
        });
        b[5] = 2; // says 2 bytes while quantity is 2 registers (4 bytes) and 4 bytes follow
        let mut around = Around::new();
        around.keep_registers(cx, a, 2);
        let steps = around.wrap(vec![
            exchange(
                Outgoing::Pdu(b),
                Compare::Exact,
                "byte count 2 for 2 registers",
            ),
            cx.liveness(),
        ]);
        cx.push(
            "spec/app-6.12/byte-count-mismatch/fc-0x10".into(),
            "FC 16 whose byte count disagrees with its quantity",
            format!("{APP}, section 6.12"),
            "A byte count that is not 2 x quantity is answered with exception 03 (Illegal Data Value); the drive keeps answering.",
            vec![Tag::Write],
            steps,
        );
    }
    if cx.supports(FunctionCode::WRITE_MULTIPLE_COILS) {
        let mut b = pdu(&Request::WriteMultipleCoils {
            address: 0,
            quantity: 9,
            data: vec![0, 0],
        });
        b[5] = 1;
        b.pop();
        let mut around = Around::new();
        around.keep_coils(cx, 0, 9);
        let steps = around.wrap(vec![
            exchange(Outgoing::Pdu(b), Compare::Exact, "byte count 1 for 9 coils"),
            cx.liveness(),
        ]);
        cx.push(
            "spec/app-6.11/byte-count-mismatch/fc-0x0F".into(),
            "FC 15 whose byte count disagrees with its quantity",
            format!("{APP}, section 6.11"),
            "A byte count that is not ceil(quantity / 8) is answered with exception 03 (Illegal Data Value).",
            vec![Tag::Write],
            steps,
        );
    }
}

/// A request one byte longer than its function's layout, on Modbus/TCP, whose MBAP length counts the byte
/// (RTU has no length field: a slave that frames by the layout reads the byte and the CRC after it as a frame
/// in error). Refused with 03 (the reference), dropped, the connection closed, or the request served with
/// the byte ignored (`trailing-bytes`): a read, so that serving it changes nothing.
fn trailing_bytes(cx: &mut Ctx) {
    let mut read = super::known_good_read(cx.p);
    read.push(0x00);
    cx.push(
        "spec/app-6/trailing-bytes/read".into(),
        "a read with one byte after its layout",
        format!("{APP}, sections 6 (request PDU layouts) and 7"),
        "A request longer than its function's layout is refused (exception 03), ignored or served as the layout reads it, the same way each time; never answered otherwise, and the drive keeps answering.",
        vec![Tag::TcpOnly],
        vec![
            exchange(Outgoing::Pdu(read), Compare::Exact, "one byte more"),
            cx.liveness(),
        ],
    );
}

/// Truncated PDUs: a supported function code with data cut short.
fn truncated_pdus(cx: &mut Ctx) {
    for fc in [0x03u8, 0x04, 0x01, 0x02, 0x06, 0x10] {
        if !cx.supports(fc) {
            continue;
        }
        // The PDU names address 1 and no value: a drive that wrote anything would write there.
        let writes = matches!(fc, 0x06 | 0x10);
        let mut a = Around::new();
        if writes {
            a.keep_registers(cx, 1, 1);
        }
        let steps = a.wrap(vec![
            exchange(
                Outgoing::Pdu(vec![fc, 0x00, 0x01]),
                Compare::RejectOrIgnore,
                "3-byte PDU",
            ),
            cx.liveness(),
        ]);
        cx.push(
            format!("spec/app-6/truncated-pdu/fc-0x{fc:02X}"),
            format!("FC 0x{fc:02X} with its data cut to 2 bytes"),
            format!("{APP}, section 6 (request PDU layouts) and 7"),
            "A request too short for its function code is rejected (exception 03) or ignored, never answered as if valid; the drive keeps answering.",
            if writes { vec![Tag::Write] } else { vec![] },
            steps,
        );
    }
}

/// FC 05 values other than ON/OFF.
fn write_coil_illegal_value(cx: &mut Ctx) {
    let p = cx.p;
    if cx.supports(FunctionCode::WRITE_SINGLE_COIL) {
        let addr = p.coils.first().map_or(0, |c| c.get_ref().address);
        // The coil must be writable for its value to be the only fault (MDrive: the point an output); a
        // drive that wrongly accepts the value is left as it was.
        let mut a = Around::new();
        if let Some(io) = IoPoints::of(p) {
            io.configure_outputs(cx, &mut a, &io.of_coils(addr, 1));
        }
        a.keep_coils(cx, addr, 1);
        let steps: Vec<Step> = a.wrap(vec![exchange(
            Outgoing::Pdu(pdu(&Request::WriteSingleCoil {
                address: addr,
                value: 0x1234,
            })),
            Compare::Exact,
            "value 0x1234",
        )]);
        cx.push(
            "spec/app-6.5/write-coil-illegal-value".into(),
            "FC 05 with value 0x1234",
            format!("{APP}, section 6.5"),
            "A Write Single Coil value other than 0xFF00 or 0x0000 is answered with exception 03 (Illegal Data Value).",
            vec![Tag::Write],
            steps,
        );
    }
}

/// FC 01/02 answers to a quantity that is not a multiple of 8: the unused bits of the last byte are 0. Where the
/// coils can be written (FC 0F, no I/O-point setup), the eight coils read are switched on first, so that a drive
/// that fills the padding with the following coils' states shows it too; put back after.
fn bit_padding(cx: &mut Ctx) {
    let p = cx.p;
    let coils: Vec<u16> = p.coils.iter().map(|c| c.get_ref().address).collect();
    let inputs: Vec<u16> = p
        .discrete_inputs
        .iter()
        .map(|c| c.get_ref().address)
        .collect();
    for (fc, addrs, what, section) in [
        (0x01u8, coils, "coils", "6.1"),
        (0x02, inputs, "discrete inputs", "6.2"),
    ] {
        if !cx.supports(fc) || addrs.len() < 3 {
            continue;
        }
        let first = addrs[0];
        // The longest run of consecutive addresses from the first, at most 8.
        let run = addrs
            .iter()
            .zip(first..)
            .take_while(|(a, b)| **a == *b)
            .count()
            .min(8) as u16;
        if run < 3 {
            continue;
        }
        let quantity = if run == 8 { 5 } else { run - 1 };
        let req = if fc == 0x01 {
            Request::ReadCoils {
                address: first,
                quantity,
            }
        } else {
            Request::ReadDiscreteInputs {
                address: first,
                quantity,
            }
        };
        let settable = fc == 0x01
            && IoPoints::of(p).is_none()
            && cx.supports(FunctionCode::WRITE_MULTIPLE_COILS)
            && p.coils
                .iter()
                .map(|c| c.get_ref())
                .filter(|c| c.address >= first && c.address < first + run)
                .all(|c| c.access.writable());
        let mut a = Around::new();
        let mut body = Vec::new();
        let mut tags = vec![];
        if settable {
            a.keep_coils(cx, first, run);
            body.push(exchange(
                Outgoing::Pdu(pdu(&Request::WriteMultipleCoils {
                    address: first,
                    quantity: run,
                    data: vec![(0xFFu16 >> (8 - run)) as u8],
                })),
                Compare::Exact,
                format!("coils {first}..+{run} on"),
            ));
            tags.push(Tag::Write);
        }
        // The states read are the drive's (its inputs, its I/O): only where the case set them are they
        // compared; the padding bits are checked either way (`Compare::Structure` does for FC 01/02).
        body.push(exchange(
            Outgoing::Pdu(pdu(&req)),
            if settable {
                Compare::Exact
            } else {
                Compare::Structure
            },
            format!(
                "{quantity} {what}: the high {} bits of the byte are 0",
                8 - quantity
            ),
        ));
        cx.push(
            format!("spec/app-{section}/padding-bits-zero"),
            format!("FC 0x{fc:02X} of {quantity} {what}: padding bits 0"),
            format!("{APP}, section {section}"),
            "If the returned quantity is not a multiple of eight, the remaining bits in the final data byte are padded with zeros (toward the high order end of the byte).",
            tags,
            a.wrap(body),
        );
    }
}

/// A one-word holding register the write cases may set to 0x1111 and 0x2222 and put back: a parameter, never
/// a `motion` or `destructive` one (a profile does not say which motion registers are plain setpoints and
/// which are command words, so none is taken; the SD2x, whose writable registers are all motion or the
/// watchdog, has no such case).
fn test_register(r: &drives::profile::Register) -> bool {
    settable(r, 0x1111, 0x2222)
}

/// A one-word holding register, read and written, neither `motion` nor `destructive`, whose range holds
/// `low..=high`.
pub(super) fn settable(r: &drives::profile::Register, low: i64, high: i64) -> bool {
    r.width == 1
        && r.table != Table::Input
        && r.access == drives::profile::Access::Rw
        && !r.motion
        && !r.destructive
        && r.min.is_none_or(|m| m <= low)
        && r.max.is_none_or(|m| m >= high)
}

/// FC 16 over the last two writable holding registers and the address after them, past the map: the request
/// is refused (exception 02) and writes nothing, read back. The two registers are given known values first
/// and put back after.
fn no_partial_write(cx: &mut Ctx) {
    let p = cx.p;
    if !cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS)
        || !cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
    {
        return;
    }
    if p.draft.is_some() {
        return;
    }
    let Some(end) = beyond_map(p) else {
        return;
    };
    let writable = |a: u16| {
        p.register_at(a, false)
            .filter(|r| r.address == a && test_register(r))
    };
    let (Some(a0), Some(a1)) = (end.checked_sub(2), end.checked_sub(1)) else {
        return;
    };
    if writable(a0).is_none() || writable(a1).is_none() {
        return;
    }
    let mut a = Around::new();
    a.keep_registers(cx, a0, 2);
    let steps = a.wrap(vec![
        exchange(
            Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
                address: a0,
                values: vec![0x1111, 0x2222],
            })),
            Compare::Exact,
            format!("registers 0x{a0:04X}, 0x{a1:04X} set to 0x1111, 0x2222"),
        ),
        exchange(
            Outgoing::Pdu(pdu(&Request::WriteMultipleRegisters {
                address: a0,
                values: vec![0xAAAA, 0xBBBB, 0xCCCC],
            })),
            Compare::Exact,
            format!("3 registers from 0x{a0:04X}, the last past the map: refused"),
        ),
        exchange(
            Outgoing::Pdu(pdu(&Request::ReadHoldingRegisters {
                address: a0,
                quantity: 2,
            })),
            Compare::Exact,
            "read back: still 0x1111, 0x2222",
        ),
    ]);
    cx.push(
        "spec/app-6.12/no-partial-write/past-the-map".into(),
        "FC 16 whose last register is past the map writes nothing",
        format!("{APP}, section 6.12 (state diagram) and 4.5"),
        "A Write Multiple Registers request whose address range runs out of the map is answered with exception 02 (Illegal Data Address) and not processed: none of its registers is written.",
        vec![Tag::Write],
        steps,
    );
}

/// FC 23 reading and writing the same register: the write is performed before the read, so the answer holds
/// the value written (spec 6.17). The register is set to a known value first and put back after.
fn write_before_read(cx: &mut Ctx) {
    let p = cx.p;
    if !cx.supports(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS) || !cx.can_write_registers() {
        return;
    }
    let Some(address) = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .find(|r| r.confirmed && test_register(r))
        .map(|r| r.address)
    else {
        return;
    };
    let mut a = Around::new();
    a.keep_registers(cx, address, 1);
    let steps = a.wrap(vec![
        exchange(
            Outgoing::Pdu(pdu(&cx.write_request(address, vec![0x1111]))),
            Compare::Exact,
            format!("register 0x{address:04X} set to 0x1111"),
        ),
        exchange(
            Outgoing::Pdu(pdu(&Request::ReadWriteMultipleRegisters {
                read_address: address,
                read_quantity: 1,
                write_address: address,
                values: vec![0x2222],
            })),
            Compare::Exact,
            "FC 23 writes 0x2222 and reads the same register: 0x2222",
        ),
    ]);
    cx.push(
        format!("spec/app-6.17/write-before-read/0x{address:04X}"),
        "FC 23 on one register answers the value it wrote",
        format!("{APP}, section 6.17"),
        "Read/Write Multiple registers performs the write operation before the read: a read of the register written returns the new value.",
        vec![Tag::Write],
        steps,
    );
}

/// The section of the application protocol specification that describes function `fc` (6.1 Read Coils ...
/// 6.17 Read/Write Multiple registers): the sections are numbered in order, not by function code.
fn section(fc: u8) -> &'static str {
    match fc {
        0x01 => "6.1",
        0x02 => "6.2",
        0x03 => "6.3",
        0x04 => "6.4",
        0x05 => "6.5",
        0x06 => "6.6",
        0x0F => "6.11",
        0x10 => "6.12",
        0x17 => "6.17",
        _ => "6",
    }
}

/// The address of the first readable register of `table` (or of both tables); 0 if there is none.
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
