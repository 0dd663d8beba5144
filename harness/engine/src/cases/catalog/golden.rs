//! Golden replay: the manual's example requests, sent as the manual prints them (as corrected).

use super::around::{self, Around};
use super::{Ctx, exchange};
use crate::cases::{Compare, Outgoing, Tag};
use codec::{Request, rtu};
use drives::golden::{Form, GoldenDirection, GoldenFile, GoldenFrame};
use drives::profile::Register;

/// One case per request frame of the golden file that decodes as a request.
///
/// A frame printed for a unit id is sent to that unit, except on a serial line (a run framed RTU, or a drive
/// that speaks RTU only, behind a gateway): there an address other than the run's is another device's (the
/// SD2x manual prints its examples for slave 1; a drive at slave 3 shares its line with the one at 1), so
/// the example's PDU goes to the run's slave, and the step says so.
pub(super) fn cases(cx: &mut Ctx, g: &GoldenFile, framing: codec::Framing) {
    let on_line = super::rtu::on_a_line(framing, cx.p);
    for f in g
        .frames
        .iter()
        .filter(|f| f.direction == GoldenDirection::Request)
    {
        let Some((pdu_bytes, addr, req)) = decode(f) else {
            continue;
        };
        let has_response = g
            .frames
            .iter()
            .any(|r| r.request.as_deref() == Some(f.id.as_str()));
        let mut tags = Vec::new();
        let mut around = Around::new();
        let compare = judge(cx, &req, &mut tags, &mut around);
        let (send, readdressed) = match addr {
            Some(u) if u != cx.unit && on_line => (
                Outgoing::Pdu(pdu_bytes.clone()),
                format!(
                    " (printed for slave {u}, sent to the run's slave {})",
                    cx.unit
                ),
            ),
            Some(u) if u != cx.unit => (
                Outgoing::PduToUnit {
                    pdu: pdu_bytes.clone(),
                    unit: u,
                },
                String::new(),
            ),
            _ => (Outgoing::Pdu(pdu_bytes.clone()), String::new()),
        };
        let steps = around.wrap(vec![exchange(
            send,
            compare,
            format!("golden request as corrected{readdressed}: {}", f.meaning),
        )]);
        let id = format!("golden/{}", f.id);
        // Cited by the manual's name and section; the line is of the seed text the corpus quotes.
        let reference = format!(
            "{}, section {} (line {} of {})",
            g.title, f.section, f.line, g.manual
        );
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

/// The PDU of a golden request, the unit it is addressed to (if the frame carries one), and the request.
/// `None` for frames the harness cannot send as printed: no bytes, bad hex, a bad frame, an unknown request.
fn decode(f: &GoldenFrame) -> Option<(Vec<u8>, Option<u8>, Request)> {
    let hex = f.corrected.as_ref().or(f.printed.as_ref())?;
    let bytes = codec::parse_hex(hex).ok()?;
    let (pdu_bytes, addr) = match f.form {
        Form::Pdu => (bytes, None),
        Form::Rtu => {
            let a = rtu::decode_adu(&bytes).ok()?;
            (a.pdu.to_vec(), Some(a.address))
        }
        Form::Tcp => {
            let a = codec::tcp::decode_adu(&bytes).ok()?;
            (a.pdu.to_vec(), Some(a.header.unit_id))
        }
    };
    let req = Request::decode(&pdu_bytes).ok()?;
    Some((pdu_bytes, addr, req))
}

/// How the golden request's answer is compared, its safety tags, and what is established before it and put
/// back after ([`around::around_write`]).
fn judge(cx: &Ctx, req: &Request, tags: &mut Vec<Tag>, around: &mut Around) -> Compare {
    let p = cx.p;
    let compare = match req {
        Request::WriteSingleRegister { address, .. }
        | Request::WriteMultipleRegisters { address, .. } => {
            tags.push(Tag::Write);
            let n = match req {
                Request::WriteMultipleRegisters { values, .. } => values.len() as u16,
                _ => 1,
            };
            let regs: Vec<&Register> = (0..n)
                .filter_map(|i| p.register_at(address.wrapping_add(i), false))
                .collect();
            if regs.iter().any(|r| r.motion) {
                tags.push(Tag::Motion);
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
    around::around_write(cx, req, around, tags);
    compare
}
