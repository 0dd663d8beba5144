//! `probe`: discover which function codes a target supports and which addresses it reads, without writing
//! anything, and set them beside a profile's.

use std::time::Duration;

use crate::targets::{Received, Target, TargetError};
use codec::{
    Direction, ExceptionCode, Framing, Mnemonic, Pdu, Request, Response, decode_any, rtu, tcp,
};
use drives::profile::{Profile, Table};

/// What a function code probe found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Support {
    /// Answered normally, or with an exception other than 01 (it parsed the request).
    Yes(String),
    /// Exception 01.
    No,
    /// No answer within the timeout.
    Silent,
    /// Not probed: every request of this code would write.
    NotProbed,
}

/// The outcome of a probe.
#[derive(Clone, Debug, Default)]
pub struct ProbeReport {
    pub functions: Vec<(u8, Support)>,
    /// Readable register ranges (inclusive) per table: holding (FC 03) and input (FC 04).
    pub holding: Vec<(u16, u16)>,
    pub input: Vec<(u16, u16)>,
    /// Requests sent.
    pub requests: usize,
}

/// A non-writing request for each function code, or None when the code always writes.
/// Write codes are probed with a request the drive must reject before writing (quantity 0, an illegal
/// coil value, an unknown mnemonic): exception 03 or 02 shows the code is implemented.
fn probe_pdu(fc: u8) -> Option<Vec<u8>> {
    let req = match fc {
        0x01 => Request::ReadCoils {
            address: 0,
            quantity: 1,
        },
        0x02 => Request::ReadDiscreteInputs {
            address: 0,
            quantity: 1,
        },
        0x03 => Request::ReadHoldingRegisters {
            address: 0,
            quantity: 1,
        },
        0x04 => Request::ReadInputRegisters {
            address: 0,
            quantity: 1,
        },
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
            mnemonic: Mnemonic::from_name("VM")?,
        },
        0x42 => Request::VendorWrite {
            mnemonic: Mnemonic::from_name("QQ")?,
            params: b"=0".to_vec(),
        },
        0x07 | 0x0B | 0x0C | 0x11 => Request::Raw {
            function: codec::FunctionCode(fc),
            data: vec![],
        },
        _ => return None,
    };
    req.to_bytes().ok()
}

/// The codes `probe` asks about, in order.
pub const PROBED: [u8; 17] = [
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F, 0x10, 0x11, 0x17, 0x2B, 0x41,
    0x42,
];

fn exchange(
    t: &mut dyn Target,
    unit: u8,
    pdu: &[u8],
    timeout: Duration,
    tid: u16,
) -> Result<Option<Response>, TargetError> {
    let mut frame = Vec::new();
    let framing = t.framing();
    if framing == Framing::Tcp {
        let _ = tcp::encode_adu(tid, unit, pdu, &mut frame);
    } else {
        let _ = rtu::encode_adu(unit, pdu, &mut frame);
    }
    t.drain();
    t.send(&frame)?;
    match t.recv(timeout)? {
        Received::Frame { bytes, .. } => {
            Ok(match decode_any(&bytes, framing, Direction::Response) {
                Ok(d) => match d.pdu {
                    Pdu::Response(r) => Some(r),
                    Pdu::Request(_) => None,
                },
                Err(_) => None,
            })
        }
        Received::Closed { .. } => {
            t.reconnect()?;
            Ok(None)
        }
        _ => Ok(None),
    }
}

/// Probe the function codes and scan `scan` (inclusive) with one-register reads on FC 03 and FC 04.
pub fn probe(
    t: &mut dyn Target,
    unit: u8,
    timeout: Duration,
    scan: (u16, u16),
) -> Result<ProbeReport, TargetError> {
    let mut report = ProbeReport::default();
    let mut tid = 1u16;
    for fc in PROBED {
        let Some(pdu) = probe_pdu(fc) else {
            report.functions.push((fc, Support::NotProbed));
            continue;
        };
        tid = tid.wrapping_add(1);
        report.requests += 1;
        let mut answer = exchange(t, unit, &pdu, timeout, tid)?;
        // FC 2B carries two MEI types; a drive may implement only CANopen access (SD2x).
        if fc == 0x2B
            && matches!(answer, Some(Response::Exception { code, .. }) if code == ExceptionCode::ILLEGAL_FUNCTION)
        {
            let canopen = Request::CanOpen(codec::CanOpenAccess::read(unit, 0, 0, 2));
            tid = tid.wrapping_add(1);
            report.requests += 1;
            answer = exchange(
                t,
                unit,
                &canopen.to_bytes().unwrap_or_default(),
                timeout,
                tid,
            )?;
        }
        let s = match answer {
            None => Support::Silent,
            Some(Response::Exception { code, .. }) if code == ExceptionCode::ILLEGAL_FUNCTION => {
                Support::No
            }
            Some(Response::Exception { code, .. }) => Support::Yes(format!("exception {code}")),
            Some(r) => Support::Yes(format!("answered FC 0x{:02X}", r.function().0)),
        };
        report.functions.push((fc, s));
    }
    let supported = |fc: u8| {
        report
            .functions
            .iter()
            .any(|(f, s)| *f == fc && matches!(s, Support::Yes(_)))
    };
    for (fc, input) in [(0x03u8, false), (0x04u8, true)] {
        if !supported(fc) {
            continue;
        }
        let mut ranges: Vec<(u16, u16)> = Vec::new();
        let (start, end) = scan;
        for a in start..=end {
            let req = if input {
                Request::ReadInputRegisters {
                    address: a,
                    quantity: 1,
                }
            } else {
                Request::ReadHoldingRegisters {
                    address: a,
                    quantity: 1,
                }
            };
            tid = tid.wrapping_add(1);
            report.requests += 1;
            let ok = matches!(
                exchange(t, unit, &req.to_bytes().unwrap_or_default(), timeout, tid)?,
                Some(Response::ReadHoldingRegisters { .. } | Response::ReadInputRegisters { .. })
            );
            if ok {
                match ranges.last_mut() {
                    Some(r) if r.1.wrapping_add(1) == a => r.1 = a,
                    _ => ranges.push((a, a)),
                }
            }
        }
        if input {
            report.input = ranges;
        } else {
            report.holding = ranges;
        }
    }
    Ok(report)
}

/// The readable ranges a profile documents for a table (registers merged where contiguous).
pub fn profile_ranges(p: &Profile, input: bool) -> Vec<(u16, u16)> {
    let mut regs: Vec<(u16, u16)> = p
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
    regs.sort();
    let mut out: Vec<(u16, u16)> = Vec::new();
    for (a, b) in regs {
        match out.last_mut() {
            Some(r) if r.1.wrapping_add(1) >= a => r.1 = r.1.max(b),
            _ => out.push((a, b)),
        }
    }
    out
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
            Support::NotProbed => "not probed (always writes)".into(),
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
    for (label, got, input) in [
        ("holding (FC 03)", &report.holding, false),
        ("input (FC 04)", &report.input, true),
    ] {
        let _ = writeln!(
            s,
            "\n{label} readable in 0x{:04X}-0x{:04X}:",
            scan.0, scan.1
        );
        let _ = writeln!(s, "  target:  {}", fmt(got));
        if let Some(p) = profile {
            let want = clip(profile_ranges(p, input));
            let _ = writeln!(s, "  profile: {}", fmt(&want));
            let _ = writeln!(s, "  {}", if &want == got { "same" } else { "DIFFERENT" });
        }
    }
    let _ = writeln!(s, "\n{} requests, none of them writes", report.requests);
    s
}
