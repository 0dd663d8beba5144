//! A stand-in drive that keeps its state and tells: what the station reports of each write it accepted
//! (so tests can assert what a run did), registers that latch the first value written, and presets that
//! start a drive at non-factory values. Sans-IO: the records are handed to a sink; the server writes them.

use std::sync::Arc;
use std::time::Duration;

use codec::{CanOpenAccess, FunctionCode, Mnemonic, Request, Response};

use crate::models::DriveModel;
use crate::profile::{Profile, Table};

/// What a write request can change: a range of holding registers, of coils, a vendor setting, an object.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Written {
    /// Holding registers `address .. address + quantity`.
    Holding { address: u16, quantity: u16 },
    /// Coils `address .. address + quantity`.
    Coils { address: u16, quantity: u16 },
    /// A vendor setting written with FC 0x42.
    Setting(Mnemonic),
    /// An FC 43 / MEI 0x0D object.
    Object { node: u8, index: u16, subindex: u8 },
    /// Something the station cannot read back (file records).
    Other,
}

impl Written {
    /// What `req` writes, if it writes anything.
    pub fn of(req: &Request) -> Option<Self> {
        Some(match req {
            Request::WriteSingleCoil { address, .. } => Written::Coils {
                address: *address,
                quantity: 1,
            },
            Request::WriteMultipleCoils {
                address, quantity, ..
            } => Written::Coils {
                address: *address,
                quantity: *quantity,
            },
            Request::WriteSingleRegister { address, .. }
            | Request::MaskWriteRegister { address, .. } => Written::Holding {
                address: *address,
                quantity: 1,
            },
            Request::WriteMultipleRegisters { address, values } => Written::Holding {
                address: *address,
                quantity: values.len() as u16,
            },
            Request::ReadWriteMultipleRegisters {
                write_address,
                values,
                ..
            } if !values.is_empty() => Written::Holding {
                address: *write_address,
                quantity: values.len() as u16,
            },
            Request::VendorWrite { mnemonic, .. } => Written::Setting(*mnemonic),
            Request::CanOpen(a) if a.is_write() => Written::Object {
                node: a.node_id,
                index: a.index,
                subindex: a.subindex,
            },
            Request::WriteFileRecord { .. } => Written::Other,
            _ => return None,
        })
    }

    /// The table name in journals: `holding`, `coil`, `mnemonic`, `object`, `file`.
    pub fn table(&self) -> &'static str {
        match self {
            Written::Holding { .. } => "holding",
            Written::Coils { .. } => "coil",
            Written::Setting(_) => "mnemonic",
            Written::Object { .. } => "object",
            Written::Other => "file",
        }
    }
}

/// A value as the drive shows it, before or after a write.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Shown {
    Words(Vec<u16>),
    Bits(Vec<bool>),
    /// A vendor setting's parameter string as FC 0x41 returns it.
    Text(String),
    /// An object's data bytes.
    Bytes(Vec<u8>),
    /// The drive would not read it back.
    Unreadable,
}

/// One write the drive accepted.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WriteRecord {
    /// Station time of the write.
    pub at: Duration,
    pub unit: u8,
    pub function: FunctionCode,
    pub written: Written,
    /// First address of `old`/`new` (widened to whole registers), or the object index.
    pub address: Option<u16>,
    pub old: Shown,
    pub new: Shown,
}

/// Where a station reports the writes it accepted.
pub type WriteSink = Arc<dyn Fn(&WriteRecord) + Send + Sync>;

/// The read that shows what `w` covers now: (first address, request). Holding ranges are widened to the
/// whole registers of the profile that they touch (a drive may refuse a read that splits a 32-bit register).
pub fn read_back(profile: &Profile, w: &Written) -> Option<(Option<u16>, Request)> {
    Some(match w {
        Written::Holding { address, quantity } => {
            let last = address.saturating_add(quantity.saturating_sub(1));
            let start = profile
                .register_at(*address, false)
                .map_or(*address, |r| r.address);
            let end = profile
                .register_at(last, false)
                .map_or(u32::from(last) + 1, |r| r.end());
            let quantity = (end.saturating_sub(u32::from(start))).clamp(1, 125) as u16;
            (
                Some(start),
                Request::ReadHoldingRegisters {
                    address: start,
                    quantity,
                },
            )
        }
        Written::Coils { address, quantity } => (
            Some(*address),
            Request::ReadCoils {
                address: *address,
                quantity: (*quantity).clamp(1, 2000),
            },
        ),
        Written::Setting(m) => (None, Request::VendorRead { mnemonic: *m }),
        Written::Object {
            node,
            index,
            subindex,
        } => {
            let size = profile
                .object(*index, *subindex)
                .map_or(4, |o| o.ty.size() as u16);
            (
                Some(*index),
                Request::CanOpen(CanOpenAccess::read(*node, *index, *subindex, size)),
            )
        }
        Written::Other => return None,
    })
}

/// What a read answered, as a value.
pub fn shown(resp: Option<&Response>, quantity: usize) -> Shown {
    match resp {
        Some(Response::ReadHoldingRegisters { values }) => Shown::Words(values.clone()),
        Some(Response::ReadCoils { data }) => Shown::Bits(
            (0..quantity)
                .map(|i| data.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 == 1))
                .collect(),
        ),
        Some(Response::VendorRead { params }) => {
            Shown::Text(String::from_utf8_lossy(params).into_owned())
        }
        Some(Response::CanOpen(a)) => Shown::Bytes(a.data.clone()),
        _ => Shown::Unreadable,
    }
}

/// Read what `w` covers from `model`, without counting it as traffic.
pub fn peek(
    model: &mut dyn DriveModel,
    now: Duration,
    unit: u8,
    w: &Written,
) -> (Option<u16>, Shown) {
    let profile = model.profile().clone();
    let Some((address, req)) = read_back(&profile, w) else {
        return (None, Shown::Unreadable);
    };
    let quantity = match &req {
        Request::ReadCoils { quantity, .. } => usize::from(*quantity),
        _ => 0,
    };
    let resp = model.handle(now, unit, &req);
    (address, shown(resp.as_ref(), quantity))
}

/// One preset value of a stand-in drive: `holding:ADDR=VALUE` (a register of the profile by address or
/// name, VALUE in the register's width and word order; `holding:` may be left out), `coil:ADDR=0|1`,
/// `mnemonic:NAME=PARAMS` (an FC 0x42 write, e.g. `mnemonic:S1=0,1,0`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Preset {
    pub spec: String,
}

/// Why a preset could not be applied.
#[derive(Debug, thiserror::Error)]
#[error("preset `{spec}`: {reason}")]
pub struct PresetError {
    pub spec: String,
    pub reason: String,
}

fn parse_u16(s: &str) -> Option<u16> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u16::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

/// The write request a preset line stands for, checked against `profile`.
pub fn preset_request(profile: &Profile, spec: &str) -> Result<Request, PresetError> {
    let err = |reason: String| PresetError {
        spec: spec.to_string(),
        reason,
    };
    let (lhs, value) = spec
        .split_once('=')
        .ok_or_else(|| err("expected TABLE:ADDR=VALUE".into()))?;
    let (table, addr) = lhs.split_once(':').unwrap_or(("holding", lhs));
    match table.trim() {
        "holding" => {
            let reg = match parse_u16(addr) {
                Some(a) => profile.register_at(a, false),
                None => profile.registers.iter().map(|r| r.get_ref()).find(|r| {
                    r.table != Table::Input
                        && (r.name.eq_ignore_ascii_case(addr.trim())
                            || r.mnemonic
                                .as_deref()
                                .is_some_and(|m| m.eq_ignore_ascii_case(addr.trim())))
                }),
            }
            .ok_or_else(|| err(format!("no holding register `{addr}` in the profile")))?;
            let v: i64 = value
                .trim()
                .parse()
                .map_err(|_| err(format!("`{value}` is not an integer")))?;
            let words = reg.words(profile.device.word_order, v);
            Ok(
                if words.len() == 1
                    && profile
                        .function(FunctionCode::WRITE_MULTIPLE_REGISTERS)
                        .is_none()
                {
                    Request::WriteSingleRegister {
                        address: reg.address,
                        value: words[0],
                    }
                } else {
                    Request::WriteMultipleRegisters {
                        address: reg.address,
                        values: words,
                    }
                },
            )
        }
        "coil" => {
            let address = parse_u16(addr).ok_or_else(|| err(format!("bad address `{addr}`")))?;
            let on = match value.trim() {
                "1" | "on" | "true" => true,
                "0" | "off" | "false" => false,
                v => return Err(err(format!("a coil is 0 or 1, not `{v}`"))),
            };
            Ok(Request::WriteMultipleCoils {
                address,
                quantity: 1,
                data: vec![u8::from(on)],
            })
        }
        "mnemonic" => {
            let mnemonic = Mnemonic::from_name(addr.trim())
                .ok_or_else(|| err(format!("`{addr}` is not a mnemonic")))?;
            let mut params = b"=".to_vec();
            params.extend_from_slice(value.trim().as_bytes());
            Ok(Request::VendorWrite { mnemonic, params })
        }
        t => Err(err(format!(
            "unknown table `{t}` (holding, coil or mnemonic)"
        ))),
    }
}

/// Apply presets to `model` directly (not as traffic): each must be accepted.
pub fn apply_presets(
    model: &mut dyn DriveModel,
    unit: u8,
    specs: &[String],
) -> Result<(), PresetError> {
    let profile = model.profile().clone();
    for spec in specs {
        let req = preset_request(&profile, spec)?;
        match model.handle(Duration::ZERO, unit, &req) {
            Some(r) if !r.is_exception() => {}
            other => {
                return Err(PresetError {
                    spec: spec.clone(),
                    reason: format!("the drive refused it ({other:?})"),
                });
            }
        }
    }
    Ok(())
}

/// Preset lines of a file: one `TABLE:ADDR=VALUE` a line, `#` starts a comment.
pub fn preset_lines(text: &str) -> Vec<String> {
    text.lines()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .filter(|l| !l.is_empty())
        .map(str::to_string)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FaultSet, Station};
    use std::sync::Mutex;

    fn mdrive() -> (Station, Arc<Mutex<Vec<WriteRecord>>>) {
        let p = crate::corpus::Corpus::Embedded
            .load("mdrive")
            .expect("mdrive");
        let log = Arc::new(Mutex::new(Vec::new()));
        let sink_log = Arc::clone(&log);
        let station = Station::new(crate::build(p, FaultSet::none()), FaultSet::none(), 1)
            .with_write_sink(Arc::new(move |r: &WriteRecord| {
                sink_log.lock().expect("log").push(r.clone())
            }));
        (station, log)
    }

    fn tcp(station: &mut Station, pdu: &[u8]) -> Vec<u8> {
        let mut adu = Vec::new();
        codec::tcp::encode_adu(1, 1, pdu, &mut adu).expect("adu");
        station
            .tcp_adu(Duration::from_millis(1), &adu)
            .map(|w| w.bytes)
            .unwrap_or_default()
    }

    #[test]
    fn accepted_writes_are_told_with_old_and_new_value_refused_ones_are_not() {
        let (mut s, log) = mdrive();
        let p = s.profile().clone();
        let req = preset_request(&p, "holding:0=1000003").expect("preset");
        tcp(&mut s, &req.to_bytes().expect("pdu"));
        let out_of_range = preset_request(&p, "holding:0=1525878998").expect("preset");
        let answer = tcp(&mut s, &out_of_range.to_bytes().expect("pdu"));
        assert!(answer.get(7).is_some_and(|fc| fc & 0x80 != 0), "{answer:?}");
        let log = log.lock().expect("log");
        assert_eq!(log.len(), 1, "{log:?}");
        assert_eq!(log[0].written.table(), "holding");
        assert_eq!(log[0].address, Some(0));
        assert_eq!(log[0].old, Shown::Words(vec![15, 16960]));
        assert_eq!(log[0].new, Shown::Words(vec![15, 16963]));
    }

    #[test]
    fn a_latched_register_keeps_the_first_value_that_changed_it() {
        let (s, _) = mdrive();
        let mut s = s.with_latched([0, 1]);
        let p = s.profile().clone();
        let write = |s: &mut Station, v: i64| {
            let req = preset_request(&p, &format!("holding:0={v}")).expect("preset");
            tcp(s, &req.to_bytes().expect("pdu"))
        };
        let read = |s: &mut Station| {
            let req = Request::ReadHoldingRegisters {
                address: 0,
                quantity: 2,
            };
            tcp(s, &req.to_bytes().expect("pdu"))[9..].to_vec()
        };
        write(&mut s, 1_000_000); // the value it holds: latches nothing
        write(&mut s, 2_000_000);
        let second = read(&mut s);
        let ack = write(&mut s, 1_000_000);
        assert!(ack.get(7).is_some_and(|fc| *fc == 0x10), "{ack:?}");
        assert_eq!(read(&mut s), second, "the latched value must stay");
    }
}
