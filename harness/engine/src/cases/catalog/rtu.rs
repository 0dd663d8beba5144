//! Modbus RTU cases: CRC checking, slave addressing and broadcast, framing, and the FC 08 diagnostics.

use super::around::{Around, around_write};
use super::{APP, Ctx, SER, exchange, known_good_read, pdu, profile};
use crate::cases::{Compare, Mutation, Outgoing, Tag};
use codec::FunctionCode;
use codec::Request;
use codec::codes::diag;
use drives::profile::{Access, Profile, Register, Table};

/// The RTU suite, family by family.
pub(super) fn cases(cx: &mut Ctx) {
    crc_and_addressing(cx);
    broadcast_write(cx);
    framing(cx);
    inter_frame_silence(cx);
    // FC 08 sub-functions as the profile lists them: a drive may implement some and not others.
    let listed = |sub: u16| cx.p.diagnostics.iter().any(|d| d.sub_function == sub);
    if cx.supports(FunctionCode::DIAGNOSTICS) {
        if listed(diag::RETURN_QUERY_DATA) {
            return_query_data(cx);
        }
        if listed(diag::CLEAR_COUNTERS) {
            counters(cx);
        }
    }
}

/// The slave address the addressing cases send to where no line survey chose one: one that is not the
/// drive's (nor broadcast). On a line with other devices it may be one of theirs; the survey at the start of
/// a run against an RTU device tries it first and then [`FOREIGN_CANDIDATES`] (`session::survey_line`).
pub(crate) fn other_slave(unit: u8) -> u8 {
    // The same axis of another device: a double-axis SD2x owns two addresses, ID switch x 2 + 1 and + 2
    // (its manual, line 183), so the next address may be the target's own other axis, which answers.
    if unit > 245 {
        unit - 2
    } else {
        unit.wrapping_add(2).max(1)
    }
}

/// The addresses the line survey tries after [`other_slave`], in order: the highest unicast address and one
/// in the middle of the range, which a line numbered from 1 up (as machine builders number them) rarely
/// reaches.
pub const FOREIGN_CANDIDATES: [u8; 2] = [247, 124];

/// The addresses the line survey tries for a drive at `unit`, in order: [`other_slave`] and then
/// [`FOREIGN_CANDIDATES`], leaving out the drive's own and, for a double-axis SD2x, its other axis's.
pub fn foreign_candidates(p: &Profile, unit: u8) -> Vec<u8> {
    let mut out = vec![other_slave(unit)];
    for c in FOREIGN_CANDIDATES {
        if c != unit && !(p.device.id == "sd2x" && c == sd2x_partner(unit)) && !out.contains(&c) {
            out.push(c);
        }
    }
    out
}

/// True where the run's drive is a slave on a serial line, whose other addresses are other devices': a run
/// framed RTU, or Modbus/TCP to a drive that speaks RTU only (a gateway in front of its line).
pub fn on_a_line(framing: codec::Framing, p: &Profile) -> bool {
    framing == codec::Framing::Rtu || !p.speaks_tcp()
}

/// The other axis's address of a double-axis SD2x at `unit`: ID switch x 2 + 1 (axis A) and + 2 (axis B)
/// (its manual, line 183).
pub fn sd2x_partner(unit: u8) -> u8 {
    if unit % 2 == 1 {
        unit.wrapping_add(1)
    } else {
        unit.wrapping_sub(1)
    }
}

/// Reads answered on the timing case's own account (so that it measures something when run alone).
const TIMING_READS: usize = 8;

/// The silence before every answer of the run: one judgement per run, after the other cases (see
/// [`crate::timing`]), on eight reads of its own and every answer before them.
fn inter_frame_silence(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    let steps = (0..TIMING_READS)
        .map(|i| {
            exchange(
                Outgoing::Pdu(read.clone()),
                Compare::Structure,
                format!("read {} of {TIMING_READS}", i + 1),
            )
        })
        .collect();
    cx.push(
        "rtu/timing/inter-frame-silence".into(),
        "every answer of the run begins after the 3.5-character silence",
        format!("{SER}, section 2.5.1.1 (RTU framing: frames separated by at least 3.5 character times)"),
        "Message frames are separated by a silent interval of at least 3.5 character times: no answer of the run begins sooner after its request. Judged once for the whole run, from an upper bound of each answer's gap (exact on the simulator, close on a native UART; behind a USB adapter only gross violations show; not measurable on a pseudo-terminal or over RTU over TCP).",
        vec![Tag::RtuOnly, Tag::RunTiming],
        steps,
    );
}

/// An FC 08 request with sub-function `sub` and one data word.
fn diag(sub: u16, data: u16) -> Vec<u8> {
    pdu(&Request::Diagnostics {
        sub_function: sub,
        data: data.to_be_bytes().to_vec(),
    })
}

/// Frames a slave must not answer: a bad CRC, another slave's address, a broadcast read.
fn crc_and_addressing(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    cx.push(
        "rtu/crc/bad-crc-silence".into(),
        "a request with a wrong CRC is not answered",
        format!("{SER}, section 2.5.1.2 (CRC checking) and 2.4.2 (no reply to a frame in error)"),
        "A frame whose CRC does not match is discarded without a response; the drive keeps answering valid frames.",
        vec![Tag::RtuOnly],
        vec![
            exchange(Outgoing::Mutated { pdu: read.clone(), mutation: Mutation::BadCrc }, Compare::Exact, "CRC inverted"),
            cx.liveness(),
        ],
    );
    let other = cx.foreign;
    cx.push(
        "rtu/address/other-slave-silence".into(),
        format!("a request to slave {other} is ignored by slave {}", cx.unit),
        format!(
            "{SER}, section 2.5.1.1 and 2.4.2 (a frame not addressed to the slave is discarded)"
        ),
        "A frame addressed to another slave is not answered.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Outgoing::PduToUnit {
                pdu: read.clone(),
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
            Outgoing::PduToUnit {
                pdu: read.clone(),
                unit: 0,
            },
            Compare::Exact,
            "address 0",
        )],
    );
}

/// A register a broadcast write can change and the case put back: confirmed, read/write, in the holding
/// table, neither motion nor destructive on its own, not the watchdog (writing it arms a timer).
fn broadcast_register<'a>(cx: &Ctx<'a>) -> Option<&'a Register> {
    let watchdog = cx.p.watchdog.as_ref().map(|w| w.register);
    cx.p.registers.iter().map(|r| r.get_ref()).find(|r| {
        r.confirmed
            && r.access == Access::Rw
            && r.table != Table::Input
            && !r.motion
            && !r.destructive
            && Some(r.address) != watchdog
    })
}

/// A broadcast write is applied (serial line spec 2.1: "All devices must accept the broadcast for writing
/// function"), where the profile says the drive takes broadcasts (`device.broadcast`; the SD2x manual never
/// mentions address 0 but as an invalid slave address, line 183, so its profile says no). The register is
/// read first (with the run's slave address) and put back after ([`around_write`]); the write goes to
/// address 0 with FC 06 (FC 16 for a 32-bit register or a profile without FC 06) and gets no answer; the
/// read back with the run's own address must hold what the reference drive, which took the broadcast,
/// holds. A broadcast reaches every drive on the bus: `Destructive`.
fn broadcast_write(cx: &mut Ctx) {
    let p = cx.p;
    if !p.device.broadcast
        || !(cx.supports(FunctionCode::READ_HOLDING_REGISTERS)
            || cx.supports(FunctionCode::READ_INPUT_REGISTERS))
    {
        return;
    }
    let Some(r) = broadcast_register(cx) else {
        return;
    };
    let v = profile::write_value(cx, r);
    let words = r.words(p.device.word_order, v);
    let write = if words.len() == 1 && cx.supports(FunctionCode::WRITE_SINGLE_REGISTER) {
        Request::WriteSingleRegister {
            address: r.address,
            value: words[0],
        }
    } else if cx.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS) {
        Request::WriteMultipleRegisters {
            address: r.address,
            values: words,
        }
    } else {
        return;
    };
    let fc = write.function().0;
    let mut tags = vec![Tag::RtuOnly, Tag::Write, Tag::Destructive];
    let mut a = Around::new();
    around_write(cx, &write, &mut a, &mut tags);
    let read = pdu(&cx.read_request(r.address, u16::from(r.width), Table::Holding));
    let steps = a.wrap(vec![
        exchange(
            Outgoing::PduToUnit {
                pdu: pdu(&write),
                unit: 0,
            },
            Compare::Exact,
            format!("broadcast FC 0x{fc:02X} {} = {v}: no answer", r.name),
        ),
        exchange(
            Outgoing::Pdu(read),
            Compare::Exact,
            format!("read back {v} at slave address {}", cx.unit),
        ),
    ]);
    cx.push(
        "rtu/address/broadcast-write-applied".into(),
        format!("a broadcast (address 0) write of {} is applied, unanswered", r.name),
        format!("{SER}, section 2.1 (broadcast mode: writing commands, accepted by all devices, no reply)"),
        format!(
            "A write of {v} to register 0x{:04X} sent to address 0 gets no response and is applied: the drive reads it back at its own address.",
            r.address
        ),
        tags,
        steps,
    );
}

/// A frame delivered in pieces without a silence between them is still one frame.
fn framing(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    cx.push(
        "rtu/framing/request-split-within-t1.5".into(),
        "a request whose bytes arrive in two writes, back to back",
        format!("{SER}, section 2.5.1.1 (RTU framing)"),
        "A frame delivered in pieces without an inter-character silence is answered once.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Outgoing::Mutated {
                pdu: read.clone(),
                mutation: Mutation::Split { at: 3, gap_us: 0 },
            },
            Compare::Structure,
            "split after 3 bytes",
        )],
    );
}

/// FC 08/00 echoes its data.
fn return_query_data(cx: &mut Ctx) {
    cx.push(
        "rtu/fc08/return-query-data".into(),
        "FC 08/00 echoes its data",
        format!("{APP}, section 6.8.1 (sub-function 00)"),
        "Return Query Data echoes the request's data field unchanged.",
        vec![Tag::RtuOnly],
        vec![exchange(
            Outgoing::Pdu(diag(diag::RETURN_QUERY_DATA, 0xA537)),
            Compare::Exact,
            "data 0xA537",
        )],
    );
}

/// The FC 08 counters after a known sequence of frames.
fn counters(cx: &mut Ctx) {
    let read = known_good_read(cx.p);
    let other = cx.foreign;
    let mut steps = vec![
        exchange(
            Outgoing::Pdu(diag(diag::CLEAR_COUNTERS, 0)),
            Compare::Exact,
            "clear counters",
        ),
        exchange(
            Outgoing::Pdu(read.clone()),
            Compare::Structure,
            "one valid request",
        ),
        exchange(
            Outgoing::Mutated {
                pdu: read.clone(),
                mutation: Mutation::BadCrc,
            },
            Compare::Exact,
            "one bad CRC",
        ),
        exchange(
            Outgoing::PduToUnit {
                pdu: read.clone(),
                unit: other,
            },
            Compare::Exact,
            "one frame for another slave",
        ),
        exchange(
            Outgoing::Pdu(vec![0x55, 0, 0]),
            Compare::Exact,
            "one exception (illegal function)",
        ),
    ];
    for (sub, what) in [
        (diag::BUS_MESSAGE_COUNT, "bus message count"),
        (
            diag::BUS_COMM_ERROR_COUNT,
            "bus communication (CRC) error count",
        ),
        (diag::BUS_EXCEPTION_ERROR_COUNT, "exception count"),
        (diag::SERVER_MESSAGE_COUNT, "slave message count"),
        (diag::SERVER_NO_RESPONSE_COUNT, "no-response count"),
    ] {
        if cx.p.diagnostics.iter().any(|d| d.sub_function == sub) {
            steps.push(exchange(Outgoing::Pdu(diag(sub, 0)), Compare::Exact, what));
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
