//! What a capture step keeps from the drive's answer, and the write that puts it back.
//!
//! A catalog case that changes the drive reads what it will change first (a step with `capture: Some(slot)`)
//! and writes it back after (`Outgoing::Restore`, `Outgoing::RestoreRead`), so that no case depends on what
//! another case left behind and a run leaves the drive as it found it. What is kept is the target's answer,
//! never the reference's: the reference receives the same restoring bytes and so follows the target's state.

use codec::{CanOpenAccess, FileRecordWrite, Framing, FunctionCode, Mnemonic, Request, Response};
use drives::profile::Profile;

/// What a capture step kept, with where it was read from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Captured {
    /// Registers read with FC 03 / FC 04 (or the read part of FC 23) from `address`.
    Registers { address: u16, values: Vec<u16> },
    /// Coils read with FC 01 from `address`, first coil first.
    Coils { address: u16, states: Vec<bool> },
    /// An FC 43 / MEI 0x0D object as read: node, index, subindex and little-endian data.
    Object(CanOpenAccess),
    /// A vendor setting read with FC 0x41: its mnemonic and the parameter string the drive returned.
    Setting { mnemonic: Mnemonic, params: Vec<u8> },
    /// One group of file records read with FC 14 (one sub-request): written back with FC 15.
    FileRecords {
        reference_type: u8,
        file_number: u16,
        record_number: u16,
        values: Vec<u16>,
    },
    /// The event bytes of an FC 0C answer (6.10), byte 0 first: nothing to write back, kept for
    /// `Step::EventLogShifted`.
    EventLog { events: Vec<u8> },
    /// Discrete inputs read with FC 02 from `address`, first input first: nothing to write back, kept for
    /// `Step::Agree` with the registers that mirror them.
    Inputs { address: u16, states: Vec<bool> },
}

impl Captured {
    /// The register values, when registers were kept.
    pub fn registers(&self) -> Option<&[u16]> {
        match self {
            Captured::Registers { values, .. } => Some(values),
            _ => None,
        }
    }

    /// An object's value read little-endian, when an object was kept.
    pub fn object_value(&self) -> Option<u32> {
        match self {
            Captured::Object(a) => a.value_le(),
            _ => None,
        }
    }

    /// The input states, when FC 02 inputs were kept.
    pub fn inputs(&self) -> Option<&[bool]> {
        match self {
            Captured::Inputs { states, .. } => Some(states),
            _ => None,
        }
    }

    /// The event bytes, when an FC 0C answer was kept.
    pub fn events(&self) -> Option<&[u8]> {
        match self {
            Captured::EventLog { events } => Some(events),
            _ => None,
        }
    }

    /// The request that writes this back: registers and coils at `at` (where they were read when `None`),
    /// a setting as an FC 0x42 write of the same mnemonic, an object as an FC 43 write of the same object.
    /// `None` when there is nothing to write (no coil states, an event log).
    pub fn restore(&self, at: Option<u16>, p: &Profile) -> Option<Request> {
        Some(match self {
            Captured::Registers { address, values } => {
                let address = at.unwrap_or(*address);
                if values.len() == 1 && p.function(FunctionCode::WRITE_MULTIPLE_REGISTERS).is_none()
                {
                    Request::WriteSingleRegister {
                        address,
                        value: values[0],
                    }
                } else {
                    Request::WriteMultipleRegisters {
                        address,
                        values: values.clone(),
                    }
                }
            }
            Captured::Coils { address, states } => {
                let address = at.unwrap_or(*address);
                match states.as_slice() {
                    [] => return None,
                    [on] if p.function(FunctionCode::WRITE_SINGLE_COIL).is_some() => {
                        Request::WriteSingleCoil {
                            address,
                            value: if *on { 0xFF00 } else { 0 },
                        }
                    }
                    _ => Request::WriteMultipleCoils {
                        address,
                        quantity: states.len() as u16,
                        data: pack(states),
                    },
                }
            }
            Captured::Object(a) => Request::CanOpen(CanOpenAccess::write(
                a.node_id,
                a.index,
                a.subindex,
                a.data.clone(),
            )),
            Captured::Setting { mnemonic, params } => Request::VendorWrite {
                mnemonic: *mnemonic,
                params: setting_params(params),
            },
            Captured::FileRecords {
                reference_type,
                file_number,
                record_number,
                values,
            } => Request::WriteFileRecord {
                sub_requests: vec![FileRecordWrite {
                    reference_type: *reference_type,
                    file_number: *file_number,
                    record_number: *record_number,
                    values: values.clone(),
                }],
            },
            Captured::EventLog { .. } | Captured::Inputs { .. } => return None,
        })
    }
}

/// What a capture of `request` (a read PDU) would keep, with placeholder values: what a restore of it
/// writes, for rating a case's restores before any answer exists. `None` for a request that keeps nothing.
pub fn placeholder(request: &[u8]) -> Option<Captured> {
    Some(match Request::decode(request).ok()? {
        Request::ReadHoldingRegisters { address, quantity }
        | Request::ReadInputRegisters { address, quantity }
        | Request::ReadWriteMultipleRegisters {
            read_address: address,
            read_quantity: quantity,
            ..
        } => Captured::Registers {
            address,
            values: vec![0; usize::from(quantity.clamp(1, 125))],
        },
        Request::ReadCoils { address, quantity } => Captured::Coils {
            address,
            states: vec![false; usize::from(quantity.clamp(1, 2000))],
        },
        Request::VendorRead { mnemonic } => Captured::Setting {
            mnemonic,
            params: b"0".to_vec(),
        },
        Request::CanOpen(mut a) if !a.is_write() => {
            a.data = vec![0; usize::from(a.byte_count.clamp(1, 4))];
            Captured::Object(a)
        }
        _ => return None,
    })
}

/// What a response to `request` (a PDU) keeps for a later restore; `None` for an exception, silence, or an
/// answer that reads nothing.
pub fn captured(framing: Framing, request: &[u8], response: &[u8]) -> Option<Captured> {
    // FC 0x41 with a 2-byte byte count too (the other reading of `fc41-byte-count-width`).
    let resp = crate::readings::decode_response(framing, response)?;
    let req = Request::decode(request).ok();
    match (req, resp) {
        (
            Some(
                Request::ReadHoldingRegisters { address, .. }
                | Request::ReadInputRegisters { address, .. }
                | Request::ReadWriteMultipleRegisters {
                    read_address: address,
                    ..
                },
            ),
            Response::ReadHoldingRegisters { values }
            | Response::ReadInputRegisters { values }
            | Response::ReadWriteMultipleRegisters { values },
        ) => Some(Captured::Registers { address, values }),
        (Some(Request::ReadCoils { address, quantity }), Response::ReadCoils { data }) => {
            let states = (0..usize::from(quantity))
                .map(|i| data.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 == 1))
                .collect();
            Some(Captured::Coils { address, states })
        }
        (
            Some(Request::ReadDiscreteInputs { address, quantity }),
            Response::ReadDiscreteInputs { data },
        ) => {
            let states = (0..usize::from(quantity))
                .map(|i| data.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 == 1))
                .collect();
            Some(Captured::Inputs { address, states })
        }
        (Some(Request::VendorRead { mnemonic }), Response::VendorRead { params }) => {
            Some(Captured::Setting { mnemonic, params })
        }
        (_, Response::CanOpen(a)) if !a.is_write() => Some(Captured::Object(a)),
        (
            Some(Request::ReadFileRecord { sub_requests }),
            Response::ReadFileRecord { sub_responses },
        ) if sub_requests.len() == 1 && sub_responses.len() == 1 => {
            let (r, d) = (&sub_requests[0], &sub_responses[0]);
            (d.values.len() == usize::from(r.record_length)).then(|| Captured::FileRecords {
                reference_type: r.reference_type,
                file_number: r.file_number,
                record_number: r.record_number,
                values: d.values.clone(),
            })
        }
        (Some(Request::GetCommEventLog), Response::GetCommEventLog { events, .. }) => {
            Some(Captured::EventLog { events })
        }
        _ => None,
    }
}

/// An FC 0x42 parameter string from an FC 0x41 read-back: the drive may return the values as `0, 0, 0` (the
/// manuals' only printed read-back) or as written (`=0,0,0`); a write wants `=` and the values without spaces.
pub fn setting_params(read_back: &[u8]) -> Vec<u8> {
    let values: Vec<u8> = read_back
        .iter()
        .copied()
        .filter(|b| !b.is_ascii_whitespace())
        .collect();
    let values = values.strip_prefix(b"=").unwrap_or(&values);
    let mut out = Vec::with_capacity(values.len() + 1);
    out.push(b'=');
    out.extend_from_slice(values);
    out
}

/// The lines of a setting that FC 0x41 reads for several lines at once (the LMD's IS, OS and LS: "1,1,0
/// 4,0,1" or "1,1,0;4,0,1", the form being the drive's, freedom `fc41-read-back-format`), each as the FC 0x42
/// parameter string that sets it (`=1,1,0`). Lines are apart where a `;`, a line break or a space stands
/// between two values; a space next to a comma or the `=` only pads (`0, 1, 0` is one line). One line for a
/// setting of one line.
pub fn setting_lines(read_back: &[u8]) -> Vec<Vec<u8>> {
    let text = read_back.trim_ascii();
    let text = text.strip_prefix(b"=").unwrap_or(text);
    let mut lines: Vec<Vec<u8>> = Vec::new();
    let mut line: Vec<u8> = Vec::new();
    let mut i = 0;
    let mut end = |line: &mut Vec<u8>| {
        if !line.is_empty() {
            lines.push(setting_params(line));
            line.clear();
        }
    };
    while i < text.len() {
        let b = text[i];
        if b == b';' {
            end(&mut line);
        } else if b.is_ascii_whitespace() {
            let next = text[i..].iter().find(|c| !c.is_ascii_whitespace());
            let padding = matches!(line.last(), None | Some(b',' | b'='))
                || matches!(next, None | Some(b',' | b';'));
            if !padding {
                end(&mut line);
            }
        } else {
            line.push(b);
        }
        i += 1;
    }
    end(&mut line);
    lines
}

/// Coil states packed LSB-first, as FC 0F carries them.
fn pack(states: &[bool]) -> Vec<u8> {
    let mut data = vec![0u8; states.len().div_ceil(8)];
    for (i, on) in states.iter().enumerate() {
        if *on {
            data[i / 8] |= 1 << (i % 8);
        }
    }
    data
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_read_back_setting_becomes_a_write() {
        assert_eq!(setting_params(b"0, 1, 0"), b"=0,1,0");
        assert_eq!(setting_params(b"=16,0,0"), b"=16,0,0");
        assert_eq!(setting_params(b" 1.500 "), b"=1.500");
    }

    /// A setting read for several lines at once goes back one line per write, whichever separator the drive
    /// reads it with; padding around commas does not part lines.
    #[test]
    fn a_setting_read_for_several_lines_goes_back_line_by_line() {
        let lines = |t: &[u8]| setting_lines(t);
        let want: Vec<Vec<u8>> = vec![b"=1,1,0".to_vec(), b"=4,0,1".to_vec(), b"=5,9,1".to_vec()];
        assert_eq!(lines(b"1,1,0 4,0,1 5,9,1"), want);
        assert_eq!(lines(b"=1,1,0;4,0,1;5,9,1\r\n"), want);
        assert_eq!(lines(b"1, 1, 0\r\n4 ,0,1\n5,9 , 1"), want);
        assert_eq!(lines(b"0, 1, 0"), vec![b"=0,1,0".to_vec()]);
        assert_eq!(lines(b"=16,0,0"), vec![b"=16,0,0".to_vec()]);
        assert_eq!(lines(b"0,-256000,1 1,5120000,1").len(), 2);
        assert!(lines(b"  ").is_empty());
    }

    #[test]
    fn coils_are_kept_and_packed_first_coil_first() {
        let req = Request::ReadCoils {
            address: 3,
            quantity: 10,
        }
        .to_bytes()
        .expect("request");
        let mut frame = Vec::new();
        codec::tcp::encode_adu(1, 1, &[0x01, 0x02, 0b0000_0101, 0b10], &mut frame).expect("adu");
        let c = captured(Framing::Tcp, &req, &frame).expect("captured");
        let Captured::Coils { address, states } = &c else {
            panic!("{c:?}")
        };
        assert_eq!(*address, 3);
        assert_eq!(
            states,
            &[
                true, false, true, false, false, false, false, false, false, true
            ]
        );
        assert_eq!(pack(states), vec![0b0000_0101, 0b10]);
    }
}
