//! `Station::clone` (through `BoxClone::box_clone`): a clone is an independent drive in the state of the
//! original. The in-process fuzz targets clone a pristine station per input instead of building one, so a
//! clone must answer exactly as a new station does, and what is done to one must not show in the other.

use std::time::Duration;

use codec::tcp;
use codec::{Mnemonic, Request};
use drives::profile::{Profile, Table};
use drives::{FaultSet, Station};

use crate::support::profile;

fn station(p: &Profile) -> Station {
    Station::new(
        drives::build(p.clone(), FaultSet::none()),
        FaultSet::none(),
        p.device.default_unit,
    )
}

/// Requests that change a drive's state: every writable register set to its minimum (or maximum, when that
/// is its starting value), every writable coil on, and for the MDrive/LMD model stored vendor parameters and
/// a program state.
fn writes(p: &Profile) -> Vec<Request> {
    let mut out = Vec::new();
    for r in p.registers.iter().map(|r| r.get_ref()) {
        if !r.access.writable() || r.table == Table::Input {
            continue;
        }
        let (lo, hi) = r.range();
        let value = if r.default == Some(lo) { hi } else { lo };
        let words = if r.width == 1 {
            vec![value as u16]
        } else {
            let v = value as u32;
            vec![(v >> 16) as u16, v as u16]
        };
        out.push(Request::WriteMultipleRegisters {
            address: r.address,
            values: words,
        });
    }
    for c in p.coils.iter().map(|c| c.get_ref()) {
        if c.access.writable() {
            out.push(Request::WriteSingleCoil {
                address: c.address,
                value: 0xFF00,
            });
        }
    }
    if matches!(p.device.id.as_str(), "mdrive" | "lmd") {
        for (name, params) in [("S1", "=0,1,0"), ("TR", "=6500"), ("EX", "A3")] {
            out.push(Request::VendorWrite {
                mnemonic: Mnemonic::from_name(name).expect("mnemonic"),
                params: params.as_bytes().to_vec(),
            });
        }
    }
    out
}

/// Requests that show a drive's state: every register, coil and discrete input read, the vendor parameters.
fn reads(p: &Profile) -> Vec<Request> {
    let mut out: Vec<Request> = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .map(|r| match r.table {
            Table::Input => Request::ReadInputRegisters {
                address: r.address,
                quantity: r.width.into(),
            },
            _ => Request::ReadHoldingRegisters {
                address: r.address,
                quantity: r.width.into(),
            },
        })
        .collect();
    for c in p.coils.iter().map(|c| c.get_ref()) {
        out.push(Request::ReadCoils {
            address: c.address,
            quantity: 1,
        });
    }
    for d in p.discrete_inputs.iter().map(|d| d.get_ref()) {
        out.push(Request::ReadDiscreteInputs {
            address: d.address,
            quantity: 1,
        });
    }
    if matches!(p.device.id.as_str(), "mdrive" | "lmd") {
        for name in ["S1", "TR"] {
            out.push(Request::VendorRead {
                mnemonic: Mnemonic::from_name(name).expect("mnemonic"),
            });
        }
    }
    out
}

/// What the station answers to each request in turn, at `ms` milliseconds.
fn answers(s: &mut Station, p: &Profile, ms: u64, requests: &[Request]) -> Vec<Option<Vec<u8>>> {
    requests
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let pdu = r.to_bytes().expect("the request encodes");
            let mut adu = Vec::new();
            tcp::encode_adu(i as u16, p.device.default_unit, &pdu, &mut adu).expect("frames");
            s.tcp_adu(Duration::from_millis(ms), &adu).map(|w| w.bytes)
        })
        .collect()
}

#[test]
fn a_clone_is_an_independent_drive_in_the_same_state() {
    for stem in ["sd2x", "mdrive", "lmd", "generic"] {
        let p = profile(stem);
        let (writes, reads) = (writes(&p), reads(&p));
        let pristine = station(&p);
        let mut fresh = station(&p);
        let mut clone = pristine.clone();
        // A clone of a pristine station answers as a new one, writes included.
        assert_eq!(
            answers(&mut clone, &p, 10, &writes),
            answers(&mut fresh, &p, 10, &writes),
            "{stem}: the writes"
        );
        let after = answers(&mut fresh, &p, 20, &reads);
        assert_eq!(answers(&mut clone, &p, 20, &reads), after, "{stem}: after");
        // The writes changed what the drive answers, so the comparisons below can fail.
        let mut untouched = station(&p);
        let before = answers(&mut untouched, &p, 20, &reads);
        assert_ne!(before, after, "{stem}: the writes change nothing");
        // What was done to the clone does not show in the station it was cloned from.
        let mut pristine_now = pristine.clone();
        assert_eq!(
            answers(&mut pristine_now, &p, 20, &reads),
            before,
            "{stem}: pristine"
        );
        // A clone of a used station carries its state, then goes its own way.
        let mut second = clone.clone();
        assert_eq!(
            second.counters(),
            clone.counters(),
            "{stem}: the FC 08 counters are copied"
        );
        assert_eq!(
            answers(&mut second, &p, 30, &reads),
            after,
            "{stem}: second"
        );
    }
}
