//! CANopen objects over FC 43 / MEI 0x0D (SD2x): reads, refused writes, SDO errors, and the objects that
//! mirror a register pair.

use super::around::Around;
use super::{Ctx, capture, exchange, pdu, slug};
use crate::cases::{Compare, Outgoing, Step, Tag};
use codec::{CanOpenAccess, Request};
use drives::profile::Access;

const MANUAL: &str =
    "SD2x manual, section 3.6 (FC 43 Encapsulated Interface Transport) and 3.8 (SDO errors)";

/// The CANopen suite, family by family.
pub(super) fn cases(cx: &mut Ctx) {
    object_accesses(cx);
    views_agree(cx);
    missing_object(cx);
    wrong_length(cx);
    zero_count(cx);
    zero_fields(cx);
}

/// Each object read, and each read-only one refused a write.
fn object_accesses(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
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
                MANUAL,
                "The object is read with FC 43 / MEI 0x0D, its size in bytes, little-endian data.",
                vec![],
                vec![exchange(
                    Outgoing::Pdu(read.clone()),
                    Compare::Structure,
                    "read",
                )],
            );
        }
        if o.access == Access::Ro {
            let data = vec![0u8; o.ty.size()];
            // Read first and written back after: a drive that wrongly accepts the write is left as it was.
            let mut a = Around::new();
            a.keep_object(cx, o);
            let steps = a.wrap(vec![exchange(
                Outgoing::Pdu(pdu(&Request::CanOpen(CanOpenAccess::write(
                    node, o.index, o.subindex, data,
                )))),
                Compare::Exact,
                "write",
            )]);
            cx.push(
                format!("profile/{}/object/{}-{}/write-read-only", p.device.id, o.index, slug(&o.name)),
                format!("FC 43/0x0D write of read-only object {}", o.index),
                MANUAL,
                "A write to a read-only object is answered with the extended exception carrying SDO error 0xFFFF000A.",
                vec![Tag::Write],
                steps,
            );
        }
    }
}

/// Both views of a mirrored value agree: the register pair in the profile's word order, the object
/// little-endian. This is where a device's word order shows against its manual.
fn views_agree(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
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
            format!("{MANUAL}; section 4.3 (byte order of process data)"),
            "A 32-bit value read as two registers in the device's word order equals the same value read as an FC 43 object (little-endian).",
            vec![],
            vec![
                capture(Outgoing::Pdu(read_reg), Compare::InRange, 0, "read the register pair"),
                capture(Outgoing::Pdu(read_obj), Compare::Structure, 1, "read the object"),
                Step::Agree { registers: 0, more_registers: vec![], object: 1, note: "both views agree".into() },
            ],
        );
    }
}

/// A read of an object that is not in the dictionary.
fn missing_object(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
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
        MANUAL,
        "A read of an object that is not in the dictionary is answered with SDO error 0xFFFF000B.",
        vec![],
        vec![exchange(
            Outgoing::Pdu(pdu(&Request::CanOpen(CanOpenAccess::read(
                node, missing, 0, 2,
            )))),
            Compare::Exact,
            "read",
        )],
    );
}

/// A read whose byte count is not the object's size (3: the SDO length error), and one whose byte count is
/// above the layout's 0..4 (line 550): the SDO length error or exception 03 (`sd2x-fc43-byte-count-over-4`).
fn wrong_length(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
    let Some(o) = p.first_readable_object() else {
        return;
    };
    for (name, count, requirement) in [
        (
            "wrong-length",
            3,
            "A read whose byte count does not match the object's size is answered with an SDO length error.",
        ),
        (
            "count-over-4",
            5,
            "A byte count above 4, outside the layout's range, is refused: with an SDO length error or with exception 03.",
        ),
    ] {
        cx.push(
            format!("profile/{}/object/{name}/read", p.device.id),
            format!(
                "FC 43/0x0D read of object {} with byte count {count}",
                o.index
            ),
            MANUAL,
            requirement,
            vec![],
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::CanOpen(CanOpenAccess::read(
                    node, o.index, o.subindex, count,
                )))),
                Compare::Exact,
                format!("read {count} bytes"),
            )],
        );
    }
}

/// A read with byte count 0, which the layout allows (line 550) and no line explains: the length error, the
/// object at its size, or no data (`sd2x-fc43-read-zero-count`), the same way for every object.
fn zero_count(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
    let readable: Vec<_> = p
        .objects
        .iter()
        .map(|o| o.get_ref())
        .filter(|o| o.access.readable())
        .collect();
    // One of each size, so that a drive answering the object shows its size.
    let mut picked: Vec<&drives::profile::Object> = Vec::new();
    for o in readable {
        if !picked.iter().any(|q| q.ty.size() == o.ty.size()) {
            picked.push(o);
        }
    }
    if picked.is_empty() {
        return;
    }
    cx.push(
        format!("profile/{}/object/zero-count/read", p.device.id),
        "FC 43/0x0D reads with byte count 0".to_string(),
        MANUAL,
        "A read of 0 bytes is answered with an SDO length error, with the object at its size, or with no data, the header echoed, the same way for every object.",
        vec![],
        picked
            .iter()
            .map(|o| {
                exchange(
                    Outgoing::Pdu(pdu(&Request::CanOpen(CanOpenAccess::read(
                        node, o.index, o.subindex, 0,
                    )))),
                    Compare::Exact,
                    format!("read object {} with byte count 0", o.index),
                )
            })
            .collect(),
    );
}

/// A read with one of the fields the manual says to set to zero set: control code bits 0-6 (line 608), the
/// reserved field (line 545), the address offset (line 627). Refused with the field's SDO error (control
/// bits: 0003; offset: 0008) or the reserved byte ignored, as the reference does, or with exception 03 where a
/// drive checks the field's value first (`sd2x-fc43-control-bits`, `-reserved-nonzero`, `-offset-nonzero`).
fn zero_fields(cx: &mut Ctx) {
    let p = cx.p;
    let node = cx.unit;
    let Some(o) = p.first_readable_object() else {
        return;
    };
    let size = u16::try_from(o.ty.size()).unwrap_or(4);
    let read = CanOpenAccess::read(node, o.index, o.subindex, size);
    for (name, access, requirement) in [
        (
            "control-bits",
            CanOpenAccess {
                control: 0x01,
                ..read.clone()
            },
            "A control code with a bit of 0-6 set ('not used, set to zero') is refused: with SDO error 0xFFFF0003 or with exception 03.",
        ),
        (
            "reserved-nonzero",
            CanOpenAccess {
                reserved: 0x01,
                ..read.clone()
            },
            "A reserved field that is not zero is ignored (the object is read) or refused with exception 03.",
        ),
        (
            "offset-nonzero",
            CanOpenAccess {
                offset: 0x0001,
                ..read.clone()
            },
            "An address offset that is not zero ('set the address offset to zero') is refused: with SDO error 0xFFFF0008 or with exception 03.",
        ),
    ] {
        cx.push(
            format!("profile/{}/object/{name}/read", p.device.id),
            format!("FC 43/0x0D read of object {} with {name}", o.index),
            MANUAL,
            requirement,
            vec![],
            // In structure: an object a drive serves holds the drive's value.
            vec![exchange(
                Outgoing::Pdu(pdu(&Request::CanOpen(access))),
                Compare::Structure,
                format!("read with {name}"),
            )],
        );
    }
}
