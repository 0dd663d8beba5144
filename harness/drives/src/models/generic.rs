//! A plain Modbus server over any profile: FC 01-07, 0F, 10, 16, 17 on the profile's data model, FC 11 report
//! server id, FC 14/15 file records, FC 18 FIFO queues and FC 2B/0E device identification, answering as the
//! MODBUS Application Protocol v1.1b3 requires (FC 08, 0B and 0C are the station's).
//!
//! The station has already rejected unsupported function codes (01), malformed PDUs and bad quantities (03);
//! what is left here is the address check of each state diagram (02) and the profile's access and range rules
//! (see `bank`). Used for every profile that has no model of its own (`corpus/profiles/generic.toml` is the
//! reference one); the device identification code is shared with the MDrive/LMD model.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use super::DriveModel;
use super::bank::RegisterBank;
use super::data_model;
use crate::choices::{Choices, Freedoms};
use crate::faults::{Fault, FaultSet};
use crate::profile::{Access, Profile};
use codec::codes::{MAX_FIFO_COUNT, file};
use codec::mei::read_code;
use codec::{
    DeviceIdObject, DeviceIdResponse, ExceptionCode, FileRecordData, FileRecordRef,
    FileRecordWrite, FunctionCode, MAX_PDU_LEN, Request, Response,
};

/// A spec-conforming Modbus server over a profile's registers, coils, discrete inputs, files and FIFO queues.
#[derive(Clone)]
pub struct Generic {
    profile: Arc<Profile>,
    bank: RegisterBank,
    /// Each file's access and records (all `records` of them), by file number.
    files: BTreeMap<u16, (Access, Vec<u16>)>,
    faults: FaultSet,
}

impl Generic {
    /// Build the model from its profile; model-level faults (word order, reserved-readable, read-only-writable,
    /// range-unchecked, the FC 07 and 16 ones) act through the register bank, those of FC 11, 14, 15 and 18
    /// here.
    pub fn new(profile: Profile, faults: FaultSet, choices: Choices) -> Self {
        let bank = RegisterBank::new(&profile, &faults, &choices);
        let files = profile
            .files
            .iter()
            .map(|f| {
                let f = f.get_ref();
                let mut records = f.values.clone();
                records.resize(usize::from(f.records), 0);
                (f.number, (f.access, records))
            })
            .collect();
        Self {
            profile: Arc::new(profile),
            bank,
            files,
            faults,
        }
    }

    /// The records of file `number` (tests inspect them).
    pub fn file(&self, number: u16) -> Option<&[u16]> {
        self.files.get(&number).map(|(_, r)| r.as_slice())
    }

    /// The largest PDU this device answers.
    fn max_pdu(&self) -> usize {
        usize::from(self.profile.device.max_pdu).min(MAX_PDU_LEN)
    }

    /// Report Server ID (FC 11, spec 6.13): the profile's id, run indicator and additional data.
    fn report_server_id(&self) -> Response {
        let Some(sid) = &self.profile.server_id else {
            // Profile validation requires the table with FC 11, so only a drive serving functions beyond
            // its profile (`served-extra-function`) gets here: with nothing to report, it has no FC 11.
            return Response::exception(
                FunctionCode::REPORT_SERVER_ID,
                ExceptionCode::ILLEGAL_FUNCTION,
            );
        };
        let sid = sid.get_ref();
        let mut data = sid.data();
        if sid.run_indicator && self.faults.has(Fault::RunIndicatorOne) {
            data[sid.id.len()] = 0x01;
        }
        Response::ReportServerId { data }
    }

    /// [`Self::file_group`] of each sub-request, given as (reference type, file, record, length): the first
    /// refusal, or every group.
    fn file_groups(
        &self,
        subs: impl Iterator<Item = (u8, u16, u16, usize)>,
        write: bool,
    ) -> Result<Vec<(u16, usize)>, ExceptionCode> {
        subs.map(|(reference_type, number, record, length)| {
            self.file_group(reference_type, number, record, length, write)
        })
        .collect()
    }

    /// The file and first record a sub-request names, if the state diagrams of spec 6.14/6.15 (figures 24,
    /// 25) let it through: reference type 6, a file of the profile, record number 0x0000-0x270F, and the
    /// group inside the file; else exception 02. `write` also needs a writable file, a read a readable one.
    fn file_group(
        &self,
        reference_type: u8,
        number: u16,
        record: u16,
        length: usize,
        write: bool,
    ) -> Result<(u16, usize), ExceptionCode> {
        let bad = ExceptionCode::ILLEGAL_DATA_ADDRESS;
        let (access, records) = self.files.get(&number).ok_or(bad)?;
        let allowed = if write {
            access.writable() || self.faults.has(Fault::ReadOnlyWritable)
        } else {
            access.readable()
        };
        let end = usize::from(record) + length;
        if reference_type != file::REFERENCE_TYPE
            || !allowed
            || u32::from(record) >= file::RECORDS_PER_FILE
            || end > records.len()
        {
            return Err(bad);
        }
        Ok((number, usize::from(record)))
    }

    /// Read File Record (FC 14, spec 6.14). Exception 03 for a byte count outside 0x07-0xF5 (figure 24), a
    /// group of no registers or a response that would not fit the PDU (section 7, 03: "the implied length
    /// is incorrect"); then 02 for any group outside its file; then every group is read.
    fn read_file_record(&self, subs: &[FileRecordRef]) -> Response {
        let exc = |e| Response::exception(FunctionCode::READ_FILE_RECORD, e);
        let byte_count = 7 * subs.len();
        // Each sub-response: its length byte, the reference type, 2 bytes per register; after FC and length.
        let response_len: usize = 2 + subs
            .iter()
            .map(|s| 2 + 2 * usize::from(s.record_length))
            .sum::<usize>();
        if !(0x07..=0xF5).contains(&byte_count)
            || subs.iter().any(|s| s.record_length == 0)
            || response_len > self.max_pdu()
        {
            return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let named = subs.iter().map(|s| {
            let n = usize::from(s.record_length);
            (s.reference_type, s.file_number, s.record_number, n)
        });
        let groups = match self.file_groups(named, false) {
            Ok(g) => g,
            Err(e) => return exc(e),
        };
        let sub_responses = groups
            .into_iter()
            .zip(subs)
            .map(|((number, start), s)| {
                let end = start + usize::from(s.record_length);
                let records = self.files.get(&number).and_then(|(_, r)| r.get(start..end));
                FileRecordData {
                    reference_type: file::REFERENCE_TYPE,
                    values: records.unwrap_or_default().to_vec(),
                }
            })
            .collect();
        Response::ReadFileRecord { sub_responses }
    }

    /// Write File Record (FC 15, spec 6.15): exception 03 for a request data length outside 0x09-0xFB (the
    /// request table; figure 25 repeats FC 14's 0x07-0xF5, which would refuse requests the table allows) or a
    /// group of no registers; then 02 for any group outside its file or in a read-only file; then every group
    /// is written, all or nothing, and the request echoed.
    fn write_file_record(&mut self, subs: &[FileRecordWrite]) -> Response {
        let exc = |e| Response::exception(FunctionCode::WRITE_FILE_RECORD, e);
        let data_len: usize = subs.iter().map(|s| 7 + 2 * s.values.len()).sum();
        if !(0x09..=0xFB).contains(&data_len) || subs.iter().any(|s| s.values.is_empty()) {
            return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let named = subs.iter().map(|s| {
            (
                s.reference_type,
                s.file_number,
                s.record_number,
                s.values.len(),
            )
        });
        let groups = match self.file_groups(named, true) {
            Ok(g) => g,
            Err(e) => return exc(e),
        };
        let n = if self.faults.has(Fault::FileWriteFirstOnly) {
            1
        } else {
            groups.len()
        };
        let values = subs.iter().map(|s| &s.values);
        for ((number, start), values) in groups.into_iter().zip(values).take(n) {
            if let Some(dst) = self
                .files
                .get_mut(&number)
                .and_then(|(_, r)| r.get_mut(start..start + values.len()))
            {
                dst.copy_from_slice(values);
            }
        }
        Response::WriteFileRecord {
            sub_requests: subs.to_vec(),
        }
    }

    /// Read FIFO Queue (FC 18, spec 6.18, figure 28): exception 02 for a pointer address that is no queue of
    /// the profile, 03 for a queue of more than 31 registers; else the queue, oldest first, left as it was.
    fn read_fifo(&self, address: u16) -> Response {
        let exc = |e| Response::exception(FunctionCode::READ_FIFO_QUEUE, e);
        let Some(q) = self.profile.fifo(address) else {
            return exc(ExceptionCode::ILLEGAL_DATA_ADDRESS);
        };
        if q.values.len() > usize::from(MAX_FIFO_COUNT) {
            return exc(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let mut values = q.values.clone();
        if self.faults.has(Fault::FifoOffByOne) {
            values.pop();
        }
        Response::ReadFifoQueue { values }
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
        // The first object always goes out, so a client paging with next_object_id always makes progress.
        // Profile validation keeps every object within one response (spec 6.21: an object is indivisible);
        // the truncation above only guards a profile built in code.
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

    /// A plain server has no state that evolves on its own.
    fn advance(&mut self, _now: Duration) {}

    fn freedoms(&mut self) -> &mut Freedoms {
        self.bank.freedoms()
    }

    fn handle(&mut self, _now: Duration, _unit: u8, request: &Request) -> Option<Response> {
        if let Some(r) = data_model::serve(&mut self.bank, request) {
            return Some(r);
        }
        Some(match request {
            Request::ReadDeviceId {
                read_code,
                object_id,
            } => read_device_id(&self.profile, *read_code, *object_id),
            Request::ReportServerId => self.report_server_id(),
            Request::ReadFileRecord { sub_requests } => self.read_file_record(sub_requests),
            Request::WriteFileRecord { sub_requests } => self.write_file_record(sub_requests),
            Request::ReadFifoQueue { address } => self.read_fifo(*address),
            // MEI types other than 0x0E, vendor codes and anything else a profile may list but a plain server
            // does not implement: illegal function (spec 7, code 01).
            other => Response::exception(other.function(), ExceptionCode::ILLEGAL_FUNCTION),
        })
    }
}
