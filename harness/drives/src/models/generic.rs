//! A plain Modbus server over any profile: FC 01-06, 0F, 10, 17 on the profile's data model and FC 2B/0E
//! device identification, answering as the MODBUS Application Protocol v1.1b3 requires.
//!
//! The station has already rejected unsupported function codes (01), malformed PDUs and bad quantities (03);
//! what is left here is the address check of each state diagram (02) and the profile's access and range rules
//! (see `bank`). Used for every profile that has no model of its own (`corpus/profiles/generic.toml` is the
//! reference one); the device identification code is shared with the MDrive/LMD model.

use std::sync::Arc;
use std::time::Duration;

use super::DriveModel;
use super::bank::RegisterBank;
use super::data_model;
use crate::faults::FaultSet;
use crate::profile::Profile;
use codec::mei::read_code;
use codec::{
    DeviceIdObject, DeviceIdResponse, ExceptionCode, FunctionCode, MAX_PDU_LEN, Request, Response,
};

/// A spec-conforming Modbus server over a profile's registers, coils and discrete inputs.
#[derive(Clone)]
pub struct Generic {
    profile: Arc<Profile>,
    bank: RegisterBank,
}

impl Generic {
    /// Build the model from its profile; model-level faults (word order, reserved-readable, read-only-writable,
    /// range-unchecked) act through the register bank.
    pub fn new(profile: Profile, faults: FaultSet) -> Self {
        let bank = RegisterBank::new(&profile, &faults);
        Self {
            profile: Arc::new(profile),
            bank,
        }
    }

    /// The data model (tests and the in-process target inspect it).
    pub fn bank(&self) -> &RegisterBank {
        &self.bank
    }

    /// The data model, mutably (tests drive input registers and discrete inputs through it).
    pub fn bank_mut(&mut self) -> &mut RegisterBank {
        &mut self.bank
    }
}

/// FC 2B/0E header bytes before the first object: FC, MEI, read code, conformity, more follows, next id, count.
const DEVICE_ID_HEADER: usize = 7;

/// The identification objects of a profile, sorted by id; a profile without any gets the three mandatory
/// basic objects (spec 6.21) from its `[device]` table.
fn identification_objects(profile: &Profile) -> Vec<(u8, Vec<u8>)> {
    let mut objs: Vec<(u8, Vec<u8>)> = profile
        .identification
        .iter()
        .map(|o| (o.object_id, o.value.as_bytes().to_vec()))
        .collect();
    if objs.is_empty() {
        objs = vec![
            (0x00, profile.device.vendor.as_bytes().to_vec()),
            (0x01, profile.device.id.as_bytes().to_vec()),
            (0x02, env!("CARGO_PKG_VERSION").as_bytes().to_vec()),
        ];
    }
    objs.sort_by_key(|o| o.0);
    objs.dedup_by_key(|o| o.0);
    objs
}

/// Read Device Identification (FC 2B / MEI 0E, MODBUS Application Protocol v1.1b3 section 6.21).
///
/// Stream reads (codes 01 basic 0x00-0x02, 02 regular 0x00-0x7F, 03 extended 0x00-0xFF) start at the requested
/// object, or restart at object 0 when that object is unknown (or outside the code's category), and set
/// `more_follows` = 0xFF and `next_object_id` when the objects do not fit one PDU. A code above the device's
/// conformity level is answered at its actual level. Individual access (04) of an unknown object gives
/// exception 02; any other read code gives exception 03. Conformity is the highest category present, with bit 7
/// set because individual access is supported.
pub fn read_device_id(profile: &Profile, code: u8, object_id: u8) -> Response {
    let fc = FunctionCode::ENCAPSULATED_INTERFACE;
    let objects = identification_objects(profile);
    let category = if objects.iter().any(|o| o.0 >= 0x80) {
        0x03
    } else if objects.iter().any(|o| o.0 >= 0x03) {
        0x02
    } else {
        0x01
    };
    let conformity = 0x80 | category;
    // At least the header and one (empty) object, at most what the spec allows.
    let limit = usize::from(profile.device.max_pdu).clamp(DEVICE_ID_HEADER + 2, MAX_PDU_LEN);
    // Longest value one object can carry in a PDU of its own (the length field is one byte).
    let room = (limit - DEVICE_ID_HEADER - 2).min(255);
    let object = |id: u8, v: &[u8]| DeviceIdObject {
        id,
        value: v.get(..v.len().min(room)).unwrap_or_default().to_vec(),
    };
    let last = match code {
        read_code::BASIC => 0x02,
        read_code::REGULAR => 0x7F,
        read_code::EXTENDED => 0xFF,
        read_code::INDIVIDUAL => {
            return match objects.iter().find(|o| o.0 == object_id) {
                Some((id, v)) => Response::ReadDeviceId(DeviceIdResponse {
                    read_code: code,
                    conformity,
                    more_follows: 0x00,
                    next_object_id: 0x00,
                    objects: vec![object(*id, v)],
                }),
                None => Response::exception(fc, ExceptionCode::ILLEGAL_DATA_ADDRESS),
            };
        }
        _ => return Response::exception(fc, ExceptionCode::ILLEGAL_DATA_VALUE),
    };
    let stream: Vec<&(u8, Vec<u8>)> = objects.iter().filter(|o| o.0 <= last).collect();
    let start = if stream.iter().any(|o| o.0 == object_id) {
        object_id
    } else {
        0
    };
    let mut used = DEVICE_ID_HEADER;
    let mut out = Vec::new();
    let mut next = None;
    for (id, v) in stream.into_iter().filter(|o| o.0 >= start) {
        let o = object(*id, v);
        let need = 2 + o.value.len();
        // The first object always goes out (truncated to the PDU if need be), so a client paging with
        // next_object_id always makes progress.
        if !out.is_empty() && used + need > limit {
            next = Some(*id);
            break;
        }
        used += need;
        out.push(o);
    }
    Response::ReadDeviceId(DeviceIdResponse {
        read_code: code,
        conformity,
        more_follows: if next.is_some() { 0xFF } else { 0x00 },
        next_object_id: next.unwrap_or(0),
        objects: out,
    })
}

impl DriveModel for Generic {
    fn profile(&self) -> &Profile {
        &self.profile
    }

    fn box_clone(&self) -> Box<dyn DriveModel> {
        Box::new(self.clone())
    }

    /// A plain server has no state that evolves on its own.
    fn advance(&mut self, _now: Duration) {}

    fn handle(&mut self, _now: Duration, _unit: u8, request: &Request) -> Option<Response> {
        if let Some(r) = data_model::serve(&mut self.bank, request) {
            return Some(r);
        }
        Some(match request {
            Request::ReadDeviceId {
                read_code,
                object_id,
            } => read_device_id(&self.profile, *read_code, *object_id),
            // MEI types other than 0x0E, vendor codes and anything else a profile may list but a plain server
            // does not implement: illegal function (spec 7, code 01).
            other => Response::exception(other.function(), ExceptionCode::ILLEGAL_FUNCTION),
        })
    }
}
