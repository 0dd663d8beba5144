//! Leave as found: the parameters a session keeps, the snapshot taken before its first write, the plan that
//! puts back what differs, and the journal that makes a killed run recoverable.
//!
//! The core is sans-IO: [`inventory`] lists what the profile knows that can be read and written back (and
//! why the rest cannot), [`plan`] compares a read-back with the snapshot and gives the writes that restore
//! it. The thin I/O around it ([`Keeper`]) sends those requests through a [`Link`] (the runner) and writes
//! the [`Journal`] file, atomically and synced, before the first write is sent and as the run goes.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write as _;
use std::path::{Path, PathBuf};

use codec::{CanOpenAccess, FunctionCode, Mnemonic, Request, Response};
use drives::profile::{Access, Profile, Table};
use drives::tell::Written;
use serde::{Deserialize, Serialize};

use crate::capture::setting_lines;
use crate::cases::safety::Safety;
use crate::cases::{Case, Outgoing, Step};
use crate::targets::TargetError;

/// The exit code of a run (or `restore`) that could not leave the drive as found.
pub const EXIT_NOT_RESTORED: u8 = 3;

/// The journal file's format tag.
pub const JOURNAL_FORMAT: &str = "modbus-harness-journal/1";

/// Where a parameter lives.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "table", rename_all = "snake_case")]
pub enum Place {
    /// Holding registers `address .. address + width`.
    Holding {
        address: u16,
        width: u8,
    },
    Coil {
        address: u16,
    },
    /// A vendor setting read with FC 0x41 and written with FC 0x42.
    Mnemonic {
        mnemonic: String,
    },
    /// An FC 43 / MEI 0x0D object.
    Object {
        node: u8,
        index: u16,
        subindex: u8,
        size: u16,
    },
}

/// One parameter of the drive that a session reads before its first write and puts back.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Item {
    /// Stable key: `holding:0x0010`, `coil:3`, `mnemonic:S1`, `object:68.0`.
    pub key: String,
    pub name: String,
    #[serde(flatten)]
    pub place: Place,
}

/// A parameter left out of the restore, with the reason.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Excluded {
    pub key: String,
    pub name: String,
    pub reason: String,
}

/// A value as read from the drive.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Value {
    Words(Vec<u16>),
    Bit(bool),
    /// A vendor setting's parameter string as FC 0x41 returned it.
    Text(String),
    /// An object's data bytes, little-endian.
    Bytes(Vec<u8>),
}

impl Value {
    /// The same value as another read, as the drive means it (a setting read back as `0, 1, 0` is `=0,1,0`).
    pub fn same(&self, other: &Value) -> bool {
        match (self, other) {
            (Value::Text(a), Value::Text(b)) => {
                setting_lines(a.as_bytes()) == setting_lines(b.as_bytes())
            }
            _ => self == other,
        }
    }
}

impl std::fmt::Display for Value {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Value::Words(w) => {
                let hex: Vec<String> = w.iter().map(|w| format!("0x{w:04X}")).collect();
                write!(f, "[{}]", hex.join(" "))
            }
            Value::Bit(b) => write!(f, "{}", u8::from(*b)),
            Value::Text(t) => write!(f, "{t:?}"),
            Value::Bytes(b) => write!(f, "{}", codec::hex_spaced(b)),
        }
    }
}

/// What a session keeps and what it leaves out.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Inventory {
    pub items: Vec<Item>,
    pub excluded: Vec<Excluded>,
    /// Keys of items kept only in case the drive takes a write the profile refuses: registers the profile
    /// takes as read-only where a freedom of kind `access` says a drive may take writes (ST, say, which the
    /// LMD manual gives no access). They are read before the first write, and put back and verified only
    /// once a case has written to them: many are live values (inputs, status flags) that change by
    /// themselves, which no restore should chase.
    pub guarded: BTreeSet<String>,
    /// Holding registers a write of which puts every setting back to its initial value (the profile's
    /// `resets_settings`: the LMD's IP): a case writing one touches every kept item.
    pub resets: Vec<u16>,
    /// Holding registers a write of which saves the working settings to NVM (the profile's
    /// `saves_settings`: MCode S): before a case writing one, every kept item is put back
    /// ([`Keeper::before_save`]).
    pub saves: Vec<u16>,
    /// Keys of the vendor settings kept because the flags allow what they set up (the profile marks them
    /// motion or destructive: an I/O point's setup, which may make an input a limit or a homing input) whose
    /// FC 0x41 read the manual does not document and that a drive may read as a line of another setting
    /// (the profile's `read_as_line`), with that line's number. One whose value read begins with it gets no
    /// trial write before the first write (see [`Keeper::take_snapshot`]).
    pub reassigning: BTreeMap<String, u8>,
}

/// How the reasons of [`gate`] begin.
const GATED_MOTION: &str = "motion:";
const GATED_DESTRUCTIVE: &str = "destructive:";

fn gate(motion: bool, destructive: bool, safety: &Safety) -> Option<String> {
    if motion && !safety.allow_motion {
        return Some(format!(
            "{GATED_MOTION} writing it back could move the motor (this run does not write it without --allow-motion)"
        ));
    }
    if destructive && !safety.allow_destructive {
        return Some(format!(
            "{GATED_DESTRUCTIVE} not written back without --allow-destructive"
        ));
    }
    None
}

/// The parameters of `profile` a session reads before its first write and restores: holding registers,
/// coils, readable vendor settings and objects that are read/write; the others with the reason they are left
/// out (read-only, write-only, actions, motion or destructive without their flags, unconfirmed drafts,
/// objects that mirror a register).
pub fn inventory(profile: &Profile, safety: &Safety) -> Inventory {
    let mut inv = Inventory::default();
    let writable_freedom = writable_by_freedom(profile);
    let mut guarded = BTreeSet::new();
    // Kept, or left out with the reason.
    let mut file = |key: String, name: &str, reason: Option<String>, place: Place| match reason {
        Some(reason) => inv.excluded.push(Excluded {
            key,
            name: name.to_string(),
            reason,
        }),
        None => inv.items.push(Item {
            key,
            name: name.to_string(),
            place,
        }),
    };
    for r in profile.registers.iter().map(|r| r.get_ref()) {
        if r.table == Table::Input {
            continue;
        }
        let draft = "unconfirmed draft entry: width and access unknown, never written";
        // Read-only by the profile, but a drive may take writes (see `Inventory::guarded`).
        let guard = r.confirmed && r.access == Access::Ro && writable_freedom.contains(&r.address);
        let access = if guard { Access::Rw } else { r.access };
        let reason = access_reason((!r.confirmed).then_some(draft), access, || {
            gate(r.motion, r.destructive, safety)
        });
        if guard && reason.is_none() {
            guarded.insert(format!("holding:0x{:04X}", r.address));
        }
        let place = Place::Holding {
            address: r.address,
            width: r.width.max(1),
        };
        file(
            format!("holding:0x{:04X}", r.address),
            &r.name,
            reason,
            place,
        );
    }
    for b in profile.coils.iter().map(|b| b.get_ref()) {
        let draft = "unconfirmed draft entry, never written";
        let reason = access_reason((!b.confirmed).then_some(draft), b.access, || {
            gate(b.motion, b.destructive, safety)
        });
        let place = Place::Coil { address: b.address };
        file(format!("coil:{}", b.address), &b.name, reason, place);
    }
    for m in profile.mnemonics.iter().map(|m| m.get_ref()) {
        let reason = match (m.read, m.write) {
            (_, false) => Some("read-only".to_string()),
            (false, true) => {
                Some("an action or write-only setting: FC 0x41 cannot read it back".to_string())
            }
            (true, true) if Mnemonic::from_name(&m.name).is_none() => {
                Some("not a wire mnemonic".to_string())
            }
            (true, true) => gate(m.motion, m.destructive, safety),
        };
        if let (None, true, Some(line)) = (&reason, m.motion || m.destructive, m.read_as_line) {
            inv.reassigning.insert(format!("mnemonic:{}", m.name), line);
        }
        let place = Place::Mnemonic {
            mnemonic: m.name.clone(),
        };
        file(format!("mnemonic:{}", m.name), &m.name, reason, place);
    }
    for o in profile.objects.iter().map(|o| o.get_ref()) {
        let reason = match o.register {
            Some(r) if o.access == Access::Rw => {
                Some(format!("mirrors holding register {r}, restored there"))
            }
            _ => access_reason(None, o.access, || gate(o.motion, o.destructive, safety)),
        };
        let place = Place::Object {
            node: 0,
            index: o.index,
            subindex: o.subindex,
            size: o.ty.size() as u16,
        };
        file(
            format!("object:{}.{}", o.index, o.subindex),
            &o.name,
            reason,
            place,
        );
    }
    inv.guarded = guarded;
    inv.resets = profile
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.resets_settings && r.table != Table::Input)
        .map(|r| r.address)
        .collect();
    inv.saves = profile
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.saves_settings && r.table != Table::Input)
        .map(|r| r.address)
        .collect();
    inv
}

/// The holding registers of `profile` that a freedom of kind `access` lets a drive take writes to ("rw"
/// among its values), by address.
fn writable_by_freedom(profile: &Profile) -> BTreeSet<u16> {
    let Ok(requirements) = drives::corpus::Corpus::Embedded.requirements_shared() else {
        return BTreeSet::new();
    };
    requirements
        .freedoms()
        .iter()
        .filter(|f| {
            f.kind == drives::requirements::FreedomKind::Access
                && f.applies_to(&profile.device.id)
                && f.admits("rw")
        })
        .flat_map(|f| f.items.iter().filter_map(|i| i.register))
        .collect()
}

/// Why an entry is left out: `draft` (the reason, for a draft entry not confirmed), read-only, write-only (the
/// manual gives no read of it; a drive that reads back an instruction's last operand, as an independent LMD
/// does with MA, MR, SL, HI and HM, would run the instruction again if it were written back), or what `gated`
/// says of a read/write entry.
fn access_reason(
    draft: Option<&str>,
    access: Access,
    gated: impl FnOnce() -> Option<String>,
) -> Option<String> {
    if let Some(why) = draft {
        return Some(why.to_string());
    }
    match access {
        Access::Ro => Some("read-only".to_string()),
        Access::Wo => Some(
            "write-only by the manual: not read, and not written back (a write runs it again)"
                .to_string(),
        ),
        Access::Rw => gated(),
    }
}

/// The read that shows an item's value.
pub fn read_request(item: &Item) -> Option<Request> {
    Some(match &item.place {
        Place::Holding { address, width } => Request::ReadHoldingRegisters {
            address: *address,
            quantity: u16::from(*width),
        },
        Place::Coil { address } => Request::ReadCoils {
            address: *address,
            quantity: 1,
        },
        Place::Mnemonic { mnemonic } => Request::VendorRead {
            mnemonic: Mnemonic::from_name(mnemonic)?,
        },
        Place::Object {
            node,
            index,
            subindex,
            size,
        } => Request::CanOpen(CanOpenAccess::read(*node, *index, *subindex, *size)),
    })
}

/// The value an answer to [`read_request`] shows; `None` for an exception or an answer of another kind.
pub fn value_of(item: &Item, resp: &Response) -> Option<Value> {
    match (&item.place, resp) {
        (Place::Holding { width, .. }, Response::ReadHoldingRegisters { values })
            if values.len() == usize::from(*width) =>
        {
            Some(Value::Words(values.clone()))
        }
        (Place::Coil { .. }, Response::ReadCoils { data }) => {
            Some(Value::Bit(data.first().is_some_and(|b| b & 1 == 1)))
        }
        (Place::Mnemonic { .. }, Response::VendorRead { params }) => {
            Some(Value::Text(String::from_utf8_lossy(params).into_owned()))
        }
        (Place::Object { .. }, Response::CanOpen(a)) if !a.is_write() => {
            Some(Value::Bytes(a.data.clone()))
        }
        _ => None,
    }
}

/// The write that puts `value` back into `item`, with the function codes the profile has.
pub fn write_request(item: &Item, value: &Value, profile: Option<&Profile>) -> Option<Request> {
    let has = |fc: FunctionCode| profile.is_none_or(|p| p.function(fc).is_some());
    Some(match (&item.place, value) {
        (Place::Holding { address, .. }, Value::Words(w)) => {
            if w.len() == 1 && !has(FunctionCode::WRITE_MULTIPLE_REGISTERS) {
                Request::WriteSingleRegister {
                    address: *address,
                    value: w[0],
                }
            } else {
                Request::WriteMultipleRegisters {
                    address: *address,
                    values: w.clone(),
                }
            }
        }
        (Place::Coil { address }, Value::Bit(on)) => {
            if has(FunctionCode::WRITE_SINGLE_COIL) {
                Request::WriteSingleCoil {
                    address: *address,
                    value: if *on { 0xFF00 } else { 0 },
                }
            } else {
                Request::WriteMultipleCoils {
                    address: *address,
                    quantity: 1,
                    data: vec![u8::from(*on)],
                }
            }
        }
        (Place::Mnemonic { mnemonic }, Value::Text(t)) => Request::VendorWrite {
            mnemonic: Mnemonic::from_name(mnemonic)?,
            params: setting_lines(t.as_bytes()).into_iter().next()?,
        },
        (
            Place::Object {
                node,
                index,
                subindex,
                ..
            },
            Value::Bytes(b),
        ) => Request::CanOpen(CanOpenAccess::write(*node, *index, *subindex, b.clone())),
        _ => return None,
    })
}

/// The writes that put `value` back into `item`: [`write_request`]'s one, or for a vendor setting read for
/// several lines at once (the LMD's IS, OS, LS), one FC 0x42 per line ([`setting_lines`]). Empty when no
/// write puts it back.
pub fn write_requests(item: &Item, value: &Value, profile: Option<&Profile>) -> Vec<Request> {
    match (&item.place, value) {
        (Place::Mnemonic { mnemonic }, Value::Text(t)) => {
            let Some(mnemonic) = Mnemonic::from_name(mnemonic) else {
                return Vec::new();
            };
            setting_lines(t.as_bytes())
                .into_iter()
                .map(|params| Request::VendorWrite { mnemonic, params })
                .collect()
        }
        _ => write_request(item, value, profile).into_iter().collect(),
    }
}

/// An item whose value differs from the snapshot: what it was and what it is now (`None`: unreadable now).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Difference {
    pub key: String,
    pub name: String,
    pub before: Value,
    pub now: Option<Value>,
}

/// The restore plan: every item of `keys` whose read-back differs from the snapshot.
pub fn plan(
    items: &[Item],
    snapshot: &BTreeMap<String, Value>,
    read_back: &BTreeMap<String, Option<Value>>,
) -> Vec<Difference> {
    items
        .iter()
        .filter_map(|item| {
            let before = snapshot.get(&item.key)?;
            let now = read_back.get(&item.key)?;
            let same = now.as_ref().is_some_and(|n| n.same(before));
            (!same).then(|| Difference {
                key: item.key.clone(),
                name: item.name.clone(),
                before: before.clone(),
                now: now.clone(),
            })
        })
        .collect()
}

/// Keys of the items a case can have changed.
pub type Touched = BTreeSet<String>;

/// What a case can have changed: items whose place its requests write, or everything when a request that
/// may write cannot be decoded (malformed on purpose).
pub fn touched(items: &[Item], case: &Case) -> BTreeSet<String> {
    touched_by(items, case_pdus(case), &[])
}

/// The request PDUs a case sends (restores aside: they write back what the case read before its writes).
fn case_pdus(case: &Case) -> Vec<&[u8]> {
    let mut pdus: Vec<&[u8]> = Vec::new();
    for s in &case.steps {
        if let Step::Exchange { send, .. } | Step::Persist { send, .. } = s {
            match send {
                Outgoing::Pdu(p) => pdus.push(p),
                Outgoing::PduToUnit { pdu, .. } | Outgoing::Mutated { pdu, .. } => pdus.push(pdu),
                Outgoing::Batch(ps) => pdus.extend(ps.iter().map(Vec::as_slice)),
                // A restore writes back what the case read before its own writes.
                Outgoing::Restore { .. } | Outgoing::RestoreRead { .. } => {}
            }
        }
    }
    pdus
}

/// How often and how long [`settle_axis`] reads MV: 50 ms apart, 10 s at most after each stop.
const SETTLE_POLL: std::time::Duration = std::time::Duration::from_millis(50);
const SETTLE_READS: usize = 200;

/// Before anything is put back: an axis left moving (a run interrupted during a move, a homing that found no
/// switch) is stopped and waited for, where the profile has MCode's MV ("Moving", 000 line 1089) and the
/// items to put back include DE (the run allowed motion, so a move may have been started): SL 0 (a slew
/// ramps down, 000 line 1114), then, if the axis still moves, DE = 0 (the output bridge off stops any motion,
/// 000 line 1042; DE is put back with the rest). A drive refuses to take P while it moves, its counters change
/// under the restore, and a run must not end with the axis moving. The writes it sent.
fn settle_axis(
    link: &mut dyn Link,
    profile: &Profile,
    items: &[Item],
) -> Result<usize, TargetError> {
    let reg = |m: &str| profile.register_by_mnemonic(m);
    let (Some(mv), Some(de)) = (
        reg("MV").filter(|r| r.access.readable() && r.width == 1),
        reg("DE").filter(|r| r.access == Access::Rw),
    ) else {
        return Ok(0);
    };
    if !items
        .iter()
        .any(|i| i.key == format!("holding:0x{:04X}", de.address))
    {
        return Ok(0);
    }
    let read = Request::ReadHoldingRegisters {
        address: mv.address,
        quantity: 1,
    };
    let moving = |link: &mut dyn Link| -> Result<bool, TargetError> {
        Ok(
            matches!(link.transact(&read)?, Some(Response::ReadHoldingRegisters { values }) if values.first().is_some_and(|v| *v != 0)),
        )
    };
    if !moving(link)? {
        return Ok(0);
    }
    let order = profile.device.word_order;
    let mut stops = Vec::new();
    if let Some(sl) = reg("SL").filter(|r| r.access.writable()) {
        stops.push(Request::WriteMultipleRegisters {
            address: sl.address,
            values: sl.words(order, 0),
        });
    }
    // MCode's escape where the profile has it: it ends motion and any program (a drive may keep moving with
    // its bridge disabled).
    if let Some(m) = profile
        .mnemonic("\u{1b}")
        .filter(|m| m.write)
        .and_then(|m| Mnemonic::from_name(&m.name))
    {
        stops.push(Request::VendorWrite {
            mnemonic: m,
            params: Vec::new(),
        });
    }
    stops.push(Request::WriteMultipleRegisters {
        address: de.address,
        values: de.words(order, 0),
    });
    let mut writes = 0;
    for stop in stops {
        link.transact(&stop)?;
        writes += 1;
        for _ in 0..SETTLE_READS {
            link.idle(SETTLE_POLL);
            if !moving(link)? {
                return Ok(writes);
            }
        }
    }
    Ok(writes)
}

/// The items that requests `pdus` can have written.
/// How many more reads tell a value that changes by itself ([`Keeper::live_apart`]), and the pause before
/// each.
/// Eight reads in all: an encoder count toggling between two values reads the same eight times in a row
/// once in 128, one jittering by ±1 once in 2,187, by ±2 once in 78,125 (four reads 20 ms apart, as
/// before 2026-11-29: once in 8, 27 and 125). The pauses add up to 56 ms, as the three of 20 ms did.
const LIVE_READS: usize = 7;
const LIVE_GAP: std::time::Duration = std::time::Duration::from_millis(8);

/// The reads `seen` (after a restore, nothing written between) as text, when they show a value that changes
/// by itself and is off `before` by no more than twice their spread: register values only, compared as
/// integers of their width in either word order (the nearer reading counts). `None` otherwise.
fn live_reads(before: &Value, seen: &[Value]) -> Option<String> {
    let Value::Words(b) = before else {
        return None;
    };
    let as_ints = |w: &[u16]| -> Option<[i64; 2]> {
        let n = w.len();
        if n == 0 || n > 2 || w.len() != b.len() {
            return None;
        }
        let signed = |x: u64| {
            let bits = 16 * n as u32;
            let sign = 1u64 << (bits - 1);
            if x & sign != 0 {
                x as i64 - (1i64 << bits)
            } else {
                x as i64
            }
        };
        let hi = w.iter().fold(0u64, |a, x| (a << 16) | u64::from(*x));
        let lo = w.iter().rev().fold(0u64, |a, x| (a << 16) | u64::from(*x));
        Some([signed(hi), signed(lo)])
    };
    let before = as_ints(b)?;
    let mut reads = Vec::new();
    for v in seen {
        let Value::Words(w) = v else { return None };
        reads.push(as_ints(w)?);
    }
    if seen.windows(2).all(|p| p[0] == p[1]) {
        return None;
    }
    let fits = |order: usize| {
        let xs: Vec<i64> = reads.iter().map(|r| r[order]).collect();
        let (min, max) = (xs.iter().min()?, xs.iter().max()?);
        let spread = max - min;
        let off = xs.iter().map(|x| (x - before[order]).abs()).min()?;
        (off <= 2 * spread).then_some(())
    };
    if fits(0).is_none() && fits(1).is_none() {
        return None;
    }
    Some(
        seen.iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(", "),
    )
}

/// True when one of `pdus` writes a holding register of `addresses`.
fn writes_any(pdus: &[&[u8]], addresses: &[u16]) -> bool {
    !addresses.is_empty()
        && pdus.iter().any(|pdu| {
            matches!(Request::decode(pdu).ok().as_ref().and_then(Written::of),
                Some(Written::Holding { address, quantity })
                    if addresses.iter().any(|a| address <= *a && u32::from(*a) < u32::from(address) + u32::from(quantity)))
        })
}

/// What `pdus` can have changed among `items`: the items they write, or every item where one writes a
/// register of `resets` (a reset of the settings to their initial values).
fn touched_by(items: &[Item], pdus: Vec<&[u8]>, resets: &[u16]) -> BTreeSet<String> {
    let mut keys = BTreeSet::new();
    let resetting = |w: &Written| match w {
        Written::Holding { address, quantity } => resets
            .iter()
            .any(|r| *address <= *r && u32::from(*r) < u32::from(*address) + u32::from(*quantity)),
        _ => false,
    };
    for pdu in pdus {
        let written = match Request::decode(pdu) {
            Ok(req) => Written::of(&req),
            // Malformed on purpose: where its header says it writes, and as far as its bytes reach.
            Err(_) if may_write(pdu) => match written_by_header(pdu) {
                Some(w) => Some(w),
                None => return items.iter().map(|i| i.key.clone()).collect(),
            },
            Err(_) => None,
        };
        if let Some(w) = written {
            if resetting(&w) {
                return items.iter().map(|i| i.key.clone()).collect();
            }
            keys.extend(
                items
                    .iter()
                    .filter(|i| covers(&w, i))
                    .map(|i| i.key.clone()),
            );
        }
    }
    keys
}

/// What a write PDU the codec refuses can still have written: from its address (and quantity) fields, as
/// far as the larger of its quantity and its data reach. `None` when even the address is cut off.
fn written_by_header(pdu: &[u8]) -> Option<Written> {
    let word = |i: usize| Some(u16::from_be_bytes([*pdu.get(i)?, *pdu.get(i + 1)?]));
    let data = |from: usize| pdu.len().saturating_sub(from);
    let clamp = |n: usize| n.min(usize::from(u16::MAX)) as u16;
    Some(match pdu.first()? {
        0x05 => Written::Coils {
            address: word(1)?,
            quantity: 1,
        },
        0x06 | 0x16 => Written::Holding {
            address: word(1)?,
            quantity: 1,
        },
        0x0F => Written::Coils {
            address: word(1)?,
            quantity: word(3)?.max(clamp(data(6) * 8)).max(1),
        },
        0x10 => Written::Holding {
            address: word(1)?,
            quantity: word(3)?.max(clamp(data(6) / 2)).max(1),
        },
        0x17 => Written::Holding {
            address: word(5)?,
            quantity: word(7)?.max(clamp(data(10) / 2)).max(1),
        },
        0x42 => Written::Setting(Mnemonic(pdu.get(1..5)?.try_into().ok()?)),
        _ => return None,
    })
}

/// A function code that writes (or an FC 43 that may), for bytes the codec does not take as a request.
fn may_write(pdu: &[u8]) -> bool {
    matches!(
        pdu.first(),
        Some(0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17 | 0x2B | 0x42)
    )
}

fn covers(w: &Written, item: &Item) -> bool {
    match (w, &item.place) {
        (Written::Holding { address, quantity }, Place::Holding { address: a, width }) => {
            let (s, e) = (
                u32::from(*address),
                u32::from(*address) + u32::from(*quantity),
            );
            let (ia, ie) = (u32::from(*a), u32::from(*a) + u32::from(*width));
            s < ie && ia < e
        }
        (Written::Coils { address, quantity }, Place::Coil { address: a }) => {
            *address <= *a && u32::from(*a) < u32::from(*address) + u32::from(*quantity)
        }
        (Written::Setting(m), Place::Mnemonic { mnemonic }) => {
            Mnemonic::from_name(mnemonic).is_some_and(|x| x == *m)
        }
        (
            Written::Object {
                index, subindex, ..
            },
            Place::Object {
                index: i,
                subindex: s,
                ..
            },
        ) => index == i && subindex == s,
        (Written::Other, _) => true,
        _ => false,
    }
}

/// A parameter that could not be put back.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Unrestored {
    pub key: String,
    pub name: String,
    pub before: Value,
    /// What it reads after the restore (`None`: it could not be read).
    pub after: Option<Value>,
    pub reason: String,
}

impl Unrestored {
    /// `before V, after W: reason` (`after unreadable` when it could not be read).
    pub fn what(&self) -> String {
        let after = self.after.as_ref();
        let after = after.map_or_else(|| "unreadable".to_string(), ToString::to_string);
        format!("before {}, after {after}: {}", self.before, self.reason)
    }
}

/// The account of leaving the drive as found, for the reports.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Account {
    /// Parameters read before the first write.
    pub kept: usize,
    /// Parameters left out, with the reason.
    pub excluded: Vec<Excluded>,
    /// Writes sent to put parameters back (after cases and at the end).
    pub restore_writes: usize,
    /// Requests the snapshot and the restores sent in all (reads and writes).
    #[serde(default)]
    pub requests: usize,
    /// Parameters that differ from the snapshot after the final restore.
    pub unrestored: Vec<Unrestored>,
    /// The snapshot was taken (a run with no write takes none).
    pub snapshot_taken: bool,
    /// The journal file, when one was written.
    pub journal: Option<PathBuf>,
    /// Kept parameters no case may write: writing back the value read before the first write did not
    /// put it back (a vendor setting whose FC 0x41 form the drive does not take in FC 0x42), with why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unwritable: Vec<Excluded>,
    /// Kept parameters put back and verified before the cases that leave the drive changed for good (CP,
    /// UG; [`Keeper::checkpoint`]) that the drive no longer let be read back or written after them, and that
    /// no case since could write: not counted as unrestored, listed with what the drive answered.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub verified_before_irreversible: Vec<Unrestored>,
    /// A CiA 402 drive found without a fault and left faulted (status word bit 3): the status word before
    /// the first write and at the end. Not a parameter (nothing writes it back): said, not counted as
    /// unrestored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_faulted: Option<(u16, u16)>,
    /// A CiA 402 drive found faulted and left without the fault: the status word before the first write
    /// and at the end. A fault reset a case the flags allowed cleared it; the fault and its error code cannot
    /// be put back. Said, not counted as unrestored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fault_cleared: Option<(u16, u16)>,
    /// The profile's error flag (a register an error record names as its `condition_flag`: MCode EF, "an
    /// error condition exists") where it reads otherwise at the end than before the first write: its
    /// address, before, after. A case the flags allowed cleared an error condition (MCode CF) or left one.
    /// Said, not counted as unrestored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_flag_changed: Option<(u16, u16, u16)>,
    /// Kept parameters that changed by themselves (a measured value on a drive with its motor attached: an
    /// encoder count, a lead/lag): read again with nothing written between, they read otherwise each time,
    /// within what they moved by. Not counted as unrestored; no longer put back or verified once seen.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub live: Vec<Unrestored>,
    /// The run's cases sent a program start or resume (MCode EX, RS: only with the flags), so at the end the
    /// program was ended with E before anything was put back: what was sent and what the drive answered. A
    /// running program is no parameter (the MDrive has no register that shows it), and one the run started
    /// must not be left running. Said, not counted as unrestored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program_ended: Option<String>,
}

impl Account {
    /// True when every kept parameter reads as before.
    pub fn clean(&self) -> bool {
        self.unrestored.is_empty()
    }

    /// Terminal lines: one for the account, one per unrestored parameter.
    pub fn lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.snapshot_taken {
            out.push("leave as found: nothing was written, no snapshot needed".to_string());
            return out;
        }
        out.push(format!(
            "leave as found: {} parameter(s) kept, {} restore write(s) in {} request(s), {} left out (see the report), {}",
            self.kept,
            self.restore_writes,
            self.requests,
            self.excluded.len(),
            if self.clean() {
                "every kept parameter reads as before".to_string()
            } else {
                format!(
                    "{} NOT RESTORED (exit code {EXIT_NOT_RESTORED})",
                    self.unrestored.len()
                )
            }
        ));
        if !self.unwritable.is_empty() {
            out.push(format!(
                "  {} parameter(s) that one write would not put back as read, so no case wrote them: {}",
                self.unwritable.len(),
                self.unwritable
                    .iter()
                    .map(|e| e.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        if !self.verified_before_irreversible.is_empty() {
            out.push(format!(
                "  {} parameter(s) put back and verified before the cases that leave the drive changed for good, which no case wrote after them, that the drive no longer let be read or written after them (first: {}: {})",
                self.verified_before_irreversible.len(),
                self.verified_before_irreversible[0].name,
                self.verified_before_irreversible[0].what()
            ));
        }
        if !self.live.is_empty() {
            out.push(format!(
                "  {} parameter(s) that change by themselves (measured values), neither put back nor verified once seen to: {}",
                self.live.len(),
                self.live
                    .iter()
                    .map(|u| format!("{} ({})", u.name, u.reason))
                    .collect::<Vec<_>>()
                    .join("; ")
            ));
        }
        if let Some(ended) = &self.program_ended {
            out.push(format!(
                "  the cases started or resumed an MCode program (EX, RS): ended at the end with E ({ended})"
            ));
        }
        if let Some((before, after)) = self.left_faulted {
            out.push(format!(
                "  WARNING: the drive was found without a fault (status word 0x{before:04X}) and is left faulted \
                 (0x{after:04X}, CiA 402 bit 3): a case the flags allowed tripped it. Its parameters are as found; \
                 the fault is not reset by the harness (a fault reset is a state change of its own)"
            ));
        }
        if let Some((before, after)) = self.fault_cleared {
            out.push(format!(
                "  NOTE: the drive was found faulted (status word 0x{before:04X}, CiA 402 bit 3) and is left \
                 without the fault (0x{after:04X}): a fault reset a case the flags allowed sent cleared it. A \
                 fault and its error code cannot be put back"
            ));
        }
        if let Some((address, before, after)) = self.error_flag_changed {
            out.push(if before != 0 && after == 0 {
                format!(
                    "  NOTE: the drive's error flag (0x{address:04X}) read {before} before the first write and reads 0 \
                     now: a case the flags allowed cleared the error condition. It cannot be put back"
                )
            } else {
                format!(
                    "  WARNING: the drive's error flag (0x{address:04X}) read {before} before the first write and \
                     reads {after} now: a case the flags allowed left an error condition. Its parameters are as \
                     found; the harness does not clear the error (a clear is a state change of its own)"
                )
            });
        }
        for u in &self.unrestored {
            out.push(format!(
                "  NOT RESTORED {} ({}): {}",
                u.key,
                u.name,
                u.what()
            ));
        }
        if let Some(j) = &self.journal {
            out.push(format!(
                "  journal: {} (modbus-harness restore --journal {} puts the drive back)",
                j.display(),
                j.display()
            ));
        }
        out
    }
}

/// The state journal: the snapshot and where the run stands, so that a killed run can be undone.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Journal {
    pub format: String,
    pub target: String,
    /// The profile the run used (a corpus name or a file path).
    pub profile: String,
    pub unit: u8,
    pub started_unix_ms: u64,
    pub updated_unix_ms: u64,
    /// `running`, `restored` or `unrestored`.
    pub state: String,
    pub items: Vec<JournalItem>,
    pub excluded: Vec<Excluded>,
    pub unrestored: Vec<Unrestored>,
    /// The last writing case restored after (the journal is brought up to date at most once a second, and
    /// whenever what is left unrestored changes).
    #[serde(default)]
    pub last_case: Option<String>,
}

/// A kept parameter and its value before the first write.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct JournalItem {
    #[serde(flatten)]
    pub item: Item,
    pub before: Value,
}

/// Why the journal could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("journal {}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("journal {}: {reason}", path.display())]
    Format { path: PathBuf, reason: String },
}

impl Journal {
    /// The snapshot as a map from key to value.
    pub fn snapshot(&self) -> BTreeMap<String, Value> {
        self.items
            .iter()
            .map(|j| (j.item.key.clone(), j.before.clone()))
            .collect()
    }

    /// The kept items.
    pub fn kept(&self) -> Vec<Item> {
        self.items.iter().map(|j| j.item.clone()).collect()
    }

    /// Write the journal to `path` atomically: a temporary file beside it, synced, renamed over it, the
    /// directory synced. A reader sees the old journal or the new one, never a part.
    pub fn save(&self, path: &Path) -> Result<(), JournalError> {
        let io = |source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        };
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&dir).map_err(io)?;
        let name = path
            .file_name()
            .map_or_else(|| "journal".into(), |n| n.to_string_lossy().into_owned());
        let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let text = serde_json::to_vec_pretty(self).map_err(|e| JournalError::Format {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        {
            let mut f = std::fs::File::create(&tmp).map_err(io)?;
            f.write_all(&text).map_err(io)?;
            f.write_all(b"\n").map_err(io)?;
            f.sync_all().map_err(io)?;
        }
        std::fs::rename(&tmp, path).map_err(io)?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    /// Read a journal file.
    pub fn load(path: &Path) -> Result<Self, JournalError> {
        let text = std::fs::read_to_string(path).map_err(|source| JournalError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let j: Journal = serde_json::from_str(&text).map_err(|e| JournalError::Format {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        if j.format != JOURNAL_FORMAT {
            return Err(JournalError::Format {
                path: path.to_path_buf(),
                reason: format!("format `{}`, expected `{JOURNAL_FORMAT}`", j.format),
            });
        }
        Ok(j)
    }
}

/// One request and its answer, the I/O the keeper needs (the runner provides it).
pub trait Link {
    /// Send `req`, return the decoded answer (`None`: silence, a close, or an undecodable answer).
    fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError>;

    /// Whether adjacent parameters may be read ([`read_all`]) or put back ([`restore`]) in one request:
    /// true until the target did not take such a request as asked ([`Link::refuse_blocks`]).
    fn blocks(&self, _kind: Block) -> bool {
        true
    }

    /// The target did not take a request of `kind` for several parameters as asked: one parameter a request
    /// from now on.
    fn refuse_blocks(&mut self, _kind: Block) {}

    /// Let `d` pass with the line idle (a target that moves needs the time to come to rest).
    fn idle(&mut self, _d: std::time::Duration) {}
}

/// A request for several adjacent parameters at once (see [`Link::blocks`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Block {
    /// One FC 03 or FC 01 read ([`read_all`]).
    Read,
    /// One FC 10 or FC 0F write putting them back ([`restore`]).
    Write,
}

/// Requests in a row without an answer after which the target counts as gone: a restore against a dead
/// drive stops there instead of waiting out a timeout for every parameter.
pub const SILENT_IN_A_ROW: u32 = 5;

/// A link that gives up after [`SILENT_IN_A_ROW`] requests without an answer.
struct Bounded<'a> {
    link: &'a mut dyn Link,
    silent: u32,
}

impl Link for Bounded<'_> {
    fn blocks(&self, kind: Block) -> bool {
        self.link.blocks(kind)
    }

    fn idle(&mut self, d: std::time::Duration) {
        self.link.idle(d);
    }

    fn refuse_blocks(&mut self, kind: Block) {
        self.link.refuse_blocks(kind);
    }

    fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
        let r = self.link.transact(req)?;
        if r.is_some() {
            self.silent = 0;
        } else {
            self.silent += 1;
            if self.silent >= SILENT_IN_A_ROW {
                return Err(TargetError::Io {
                    target: "the target".into(),
                    source: std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        format!("no answer to {SILENT_IN_A_ROW} requests in a row"),
                    ),
                });
            }
        }
        Ok(r)
    }
}

/// A link that counts the requests sent through it.
pub(crate) struct Counting<'a> {
    pub(crate) link: &'a mut dyn Link,
    pub(crate) sent: usize,
}

impl Link for Counting<'_> {
    fn idle(&mut self, d: std::time::Duration) {
        self.link.idle(d);
    }

    fn blocks(&self, kind: Block) -> bool {
        self.link.blocks(kind)
    }

    fn refuse_blocks(&mut self, kind: Block) {
        self.link.refuse_blocks(kind);
    }

    fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
        self.sent += 1;
        self.link.transact(req)
    }
}

/// Registers or coils read in one request at most by [`read_all`] (FC 03 allows 125 registers; a coil
/// block is held to the same count).
const MAX_BLOCK: usize = 125;

/// Registers or coils put back in one request at most by [`restore`] (FC 10 allows 123 registers; a coil
/// block is held to the same count).
const MAX_WRITE_BLOCK: usize = 123;

/// Read `items` through `link`: each key with its value, `None` where the drive gave none. Adjacent holding
/// registers (or coils), in the order given, are read in one request while the link allows it; a block the
/// target does not answer as asked is read again one parameter at a time, and so is everything after it.
pub fn read_all(
    link: &mut dyn Link,
    items: &[Item],
) -> Result<BTreeMap<String, Option<Value>>, TargetError> {
    let link = &mut Bounded { link, silent: 0 };
    let mut out = BTreeMap::new();
    let mut at = 0;
    while at < items.len() {
        let run = adjacent(&items[at..], MAX_BLOCK);
        if run.len() > 1 && link.blocks(Block::Read) {
            match read_block(link, run)? {
                Some(values) => {
                    for (item, v) in run.iter().zip(values) {
                        out.insert(item.key.clone(), Some(v));
                    }
                    at += run.len();
                    continue;
                }
                None => link.refuse_blocks(Block::Read),
            }
        }
        let item = &items[at];
        let v = match read_request(item) {
            Some(req) => link.transact(&req)?.and_then(|r| value_of(item, &r)),
            None => None,
        };
        out.insert(item.key.clone(), v);
        at += 1;
    }
    Ok(out)
}

/// A 32-bit parameter the drive does not read whole but reads as one register is kept, read and put back as
/// that one register (`items` and `read` changed to match): the MDrive and LMD manuals print LT as
/// "0x009C – 0x009D" with "Bytes 2" (MDrive line 1147, LMD line 2666), and an eighth-wave MDrive and LMD
/// both take it as one 16-bit register, refusing the pair with 02; the runs wrote its first register and,
/// the pair unread, left it changed. A drive that reads neither leaves it out, as before.
fn narrow_unread_pairs(
    link: &mut dyn Link,
    items: &mut [Item],
    read: &mut BTreeMap<String, Option<Value>>,
) -> Result<(), TargetError> {
    for item in items.iter_mut() {
        let Place::Holding { address, width: 2 } = item.place else {
            continue;
        };
        if !matches!(read.get(&item.key), Some(None)) {
            continue;
        }
        let narrow = Item {
            place: Place::Holding { address, width: 1 },
            ..item.clone()
        };
        let got = read_all(link, std::slice::from_ref(&narrow))?;
        if let Some(Some(v)) = got.get(&item.key) {
            read.insert(item.key.clone(), Some(v.clone()));
            *item = narrow;
        }
    }
    Ok(())
}

/// Where a parameter that a block read can cover lies: (holding register or coil, first address, registers
/// or coils); `None` for the others.
fn span(place: &Place) -> Option<(bool, u32, u32)> {
    match place {
        Place::Holding { address, width } => Some((true, u32::from(*address), u32::from(*width))),
        Place::Coil { address } => Some((false, u32::from(*address), 1)),
        _ => None,
    }
}

/// The longest prefix of `items` that one read shows: holding registers each starting where the one before
/// ends, or coils at consecutive addresses; at most `max` registers or coils.
fn adjacent(items: &[Item], max: usize) -> &[Item] {
    let Some((holding, start, size)) = items.first().and_then(|i| span(&i.place)) else {
        return &items[..items.len().min(1)];
    };
    let mut end = start + size;
    let mut n = 1;
    for item in &items[1..] {
        match span(&item.place) {
            Some((h, s, z)) if h == holding && s == end && end + z - start <= max as u32 => {
                end += z;
                n += 1;
            }
            _ => break,
        }
    }
    &items[..n]
}

/// Read `run` (from [`adjacent`]) in one request: each item's value as its own read would show it
/// ([`value_of`] of its part of the answer), or `None` when the target did not answer as asked (an
/// exception, silence, another length).
fn read_block(link: &mut dyn Link, run: &[Item]) -> Result<Option<Vec<Value>>, TargetError> {
    let spans: Vec<_> = run.iter().filter_map(|i| span(&i.place)).collect();
    let Some(&(holding, first, _)) = spans.first() else {
        return Ok(None);
    };
    let (address, quantity) = (first as u16, spans.iter().map(|s| s.2).sum::<u32>() as u16);
    let req = if holding {
        Request::ReadHoldingRegisters { address, quantity }
    } else {
        Request::ReadCoils { address, quantity }
    };
    let Some(answer) = link.transact(&req)? else {
        return Ok(None);
    };
    let n = usize::from(quantity);
    let mut out = Vec::with_capacity(run.len());
    for (item, (_, at, size)) in run.iter().zip(&spans) {
        let (at, size) = ((at - first) as usize, *size as usize);
        let part = match &answer {
            Response::ReadHoldingRegisters { values } if holding && values.len() == n => {
                Response::ReadHoldingRegisters {
                    values: values[at..at + size].to_vec(),
                }
            }
            Response::ReadCoils { data } if !holding && data.len() == n.div_ceil(8) => {
                Response::ReadCoils {
                    data: vec![data[at / 8] >> (at % 8) & 1],
                }
            }
            _ => return Ok(None),
        };
        let Some(v) = value_of(item, &part) else {
            return Ok(None);
        };
        out.push(v);
    }
    Ok(Some(out))
}

/// One write putting the adjacent parameters `run` (from [`adjacent`]) back to `values`: FC 10 for holding
/// registers, FC 0F for coils, where the profile has it; `None` otherwise, or when a value is not of its
/// parameter's width.
fn block_write_request(
    run: &[Item],
    values: &[&Value],
    profile: Option<&Profile>,
) -> Option<Request> {
    let spans: Vec<_> = run.iter().map(|i| span(&i.place)).collect::<Option<_>>()?;
    let &(holding, first, _) = spans.first()?;
    let fc = if holding {
        FunctionCode::WRITE_MULTIPLE_REGISTERS
    } else {
        FunctionCode::WRITE_MULTIPLE_COILS
    };
    if profile.is_some_and(|p| p.function(fc).is_none()) {
        return None;
    }
    let address = u16::try_from(first).ok()?;
    if holding {
        let mut words = Vec::new();
        for ((_, _, size), v) in spans.iter().zip(values) {
            match v {
                Value::Words(w) if w.len() == *size as usize => words.extend_from_slice(w),
                _ => return None,
            }
        }
        return Some(Request::WriteMultipleRegisters {
            address,
            values: words,
        });
    }
    let mut data = vec![0u8; values.len().div_ceil(8)];
    for (k, v) in values.iter().enumerate() {
        match v {
            Value::Bit(on) => data[k / 8] |= u8::from(*on) << (k % 8),
            _ => return None,
        }
    }
    Some(Request::WriteMultipleCoils {
        address,
        quantity: u16::try_from(values.len()).ok()?,
        data,
    })
}

/// Whether `answer` acknowledges the block write `req` as sent: its address and quantity echoed.
fn acknowledges(req: &Request, answer: &Response) -> bool {
    match (req, answer) {
        (
            Request::WriteMultipleRegisters { address, values },
            Response::WriteMultipleRegisters {
                address: a,
                quantity,
            },
        ) => a == address && usize::from(*quantity) == values.len(),
        (
            Request::WriteMultipleCoils {
                address, quantity, ..
            },
            Response::WriteMultipleCoils {
                address: a,
                quantity: q,
            },
        ) => a == address && q == quantity,
        _ => false,
    }
}

/// Put back every item of `items` that differs from `snapshot` and verify by reading: the writes sent and
/// the items still differing after. Bounded: two write-and-verify rounds.
pub fn restore(
    link: &mut dyn Link,
    items: &[Item],
    snapshot: &BTreeMap<String, Value>,
    profile: Option<&Profile>,
) -> Result<(usize, Vec<Unrestored>), TargetError> {
    let link = &mut Bounded { link, silent: 0 };
    let mut writes = 0;
    if let Some(p) = profile {
        writes += settle_axis(link, p, items)?;
    }
    let mut now = read_all(link, items)?;
    let mut refused: BTreeMap<String, String> = BTreeMap::new();
    for _round in 0..2 {
        let diffs = plan(items, snapshot, &now);
        if diffs.is_empty() {
            break;
        }
        let (differing, before): (Vec<Item>, Vec<&Value>) = diffs
            .iter()
            .filter_map(|d| Some((items.iter().find(|i| i.key == d.key)?.clone(), &d.before)))
            .unzip();
        let mut changed = Vec::new();
        // Keys put back by a block write the target acknowledged.
        let mut in_blocks = Vec::new();
        let mut at = 0;
        while at < differing.len() {
            let run = adjacent(&differing[at..], MAX_WRITE_BLOCK);
            if run.len() > 1
                && link.blocks(Block::Write)
                && let Some(req) = block_write_request(run, &before[at..at + run.len()], profile)
            {
                writes += 1;
                if link.transact(&req)?.is_some_and(|r| acknowledges(&req, &r)) {
                    for i in run {
                        refused.remove(&i.key);
                        in_blocks.push(i.key.clone());
                    }
                    changed.extend_from_slice(run);
                    at += run.len();
                    continue;
                }
                // Refused, unanswered or answered otherwise: each parameter alone, as without blocks.
                link.refuse_blocks(Block::Write);
            }
            let (item, value) = (&differing[at], before[at]);
            at += 1;
            let reqs = write_requests(item, value, profile);
            if reqs.is_empty() {
                refused.insert(item.key.clone(), "no write puts this value back".into());
                continue;
            }
            refused.remove(&item.key);
            for req in &reqs {
                writes += 1;
                let why = match link.transact(req)? {
                    Some(r) if !r.is_exception() => continue,
                    Some(r) => format!("the drive refused the write: {r:?}"),
                    None => "no answer to the write".into(),
                };
                refused.insert(item.key.clone(), why);
            }
            changed.push(item.clone());
        }
        let again = read_all(link, &changed)?;
        // A block write acknowledged but not read back as written (a drive that takes the first parameter of
        // such a write only, say): the next round puts each parameter back alone, as without blocks.
        let taken = |k: &String| {
            again
                .get(k)
                .is_some_and(|v| v.as_ref().is_some_and(|v| v.same(&snapshot[k])))
        };
        if !in_blocks.iter().all(taken) {
            link.refuse_blocks(Block::Write);
        }
        now.extend(again);
    }
    let left = plan(items, snapshot, &now)
        .into_iter()
        .map(|d| Unrestored {
            reason: refused.get(&d.key).cloned().unwrap_or_else(|| {
                "written back and acknowledged, but it does not read back as before".into()
            }),
            key: d.key,
            name: d.name,
            before: d.before,
            after: d.now,
        })
        .collect();
    Ok((writes, left))
}

/// The run's keeper of the snapshot: takes it before the first write, restores after each writing case
/// and at the end, and keeps the journal up to date.
pub struct Keeper {
    inventory: Inventory,
    snapshot: Option<BTreeMap<String, Value>>,
    journal_path: Option<PathBuf>,
    journal: Option<Journal>,
    header: (String, String, u8),
    account: Account,
    /// Items a case left differing that the restore after it could not put back (retried at the end).
    pending: BTreeMap<String, Unrestored>,
    last_saved: Option<std::time::Instant>,
    /// The journal is the run's own file in the temporary directory (no `--journal`, no report directory):
    /// removed once every kept parameter reads as before, kept otherwise for `restore --journal`.
    scratch_journal: bool,
    /// Kept parameters that would not write back as read (see [`Account::unwritable`]): no case writes them.
    unwritable: Vec<Item>,
    /// Kept settings read for several lines at once, which the keeper puts back line by line: no case
    /// writes them itself (its write-back is one write), a reset of every setting may.
    multi_line: Vec<Item>,
    /// Kept items seen to change by themselves ([`Account::live`]): no longer put back or verified.
    live: BTreeSet<String>,
    /// The guarded items (see [`Inventory::guarded`]) a case has written to: from then on they are put back
    /// and verified like the others.
    written: BTreeSet<String>,
    /// After [`Keeper::checkpoint`]: the keys it left unrestored, and the keys cases wrote since.
    checkpoint: Option<(BTreeSet<String>, BTreeSet<String>)>,
    /// A CiA 402 status word to read before the first write and at the end (see [`Keeper::watch_status`]),
    /// and what it read before.
    status_word: Option<Watched>,
    /// The profile's error flag to read before the first write and at the end (see
    /// [`Keeper::watch_status`]), and what it read before.
    error_flag: Option<Watched>,
    /// A case sent a program start or resume (MCode EX, RS; [`Keeper::note_case`]): E at the end.
    program_started: bool,
}

/// A one-register state the keeper reads before the first write and at the end (see
/// [`Keeper::watch_status`]): where it is, and what it read before.
#[derive(Clone, Debug)]
struct Watched {
    address: u16,
    read: Request,
    before: Option<u16>,
}

impl Watched {
    fn of(r: &drives::profile::Register) -> Self {
        let (address, quantity) = (r.address, 1);
        let read = match r.table {
            Table::Input => Request::ReadInputRegisters { address, quantity },
            _ => Request::ReadHoldingRegisters { address, quantity },
        };
        Self {
            address,
            read,
            before: None,
        }
    }

    /// The register as the drive answers it now (`None`: no answer, or not a register).
    fn read(&self, link: &mut dyn Link) -> Option<u16> {
        match link.transact(&self.read).ok()?? {
            Response::ReadInputRegisters { values } | Response::ReadHoldingRegisters { values } => {
                values.first().copied()
            }
            _ => None,
        }
    }
}

impl Keeper {
    /// A keeper of `inventory` for a run of `profile_name` on `target` as `unit`, journaling to `journal`.
    pub fn new(
        inventory: Inventory,
        target: String,
        profile_name: String,
        unit: u8,
        journal: Option<PathBuf>,
    ) -> Self {
        let account = Account {
            excluded: inventory.excluded.clone(),
            journal: journal.clone(),
            ..Account::default()
        };
        Self {
            inventory,
            snapshot: None,
            journal_path: journal,
            journal: None,
            header: (target, profile_name, unit),
            account,
            pending: BTreeMap::new(),
            last_saved: None,
            scratch_journal: false,
            unwritable: Vec::new(),
            multi_line: Vec::new(),
            live: BTreeSet::new(),
            written: BTreeSet::new(),
            checkpoint: None,
            status_word: None,
            error_flag: None,
            program_started: false,
        }
    }

    /// Before a case runs: note whether it sends a program start or resume (FC 0x41 or 0x42 of MCode's EX
    /// or RS, the form the manual prints and the form a drive may take them in), so that [`Keeper::finish`]
    /// ends the program with E. The fourteenth wave's MDrive holds a program at the example's label A3: the
    /// catalog's golden EX, PS and RS frames (with `--allow-motion --allow-destructive`) left it running.
    pub fn note_case(&mut self, case: &Case) {
        let starts = ["EX", "RS"].map(Mnemonic::from_name);
        self.program_started |= case_pdus(case).iter().any(|pdu| {
            matches!(pdu.first(), Some(0x41 | 0x42))
                && pdu
                    .get(1..5)
                    .is_some_and(|m| starts.iter().flatten().any(|s| s.0.as_slice() == m))
        });
    }

    /// End a program the cases may have started ([`Keeper::note_case`]): E by FC 0x42 (the function the
    /// manuals' tables give program control), and by FC 0x41 (the one the MDrive's sections print, freedom
    /// `mdrive-program-control-function`) where 0x42 is refused or unanswered. A drive running nothing
    /// acknowledges E or refuses it; either leaves it as it was.
    fn end_program(&mut self, link: &mut dyn Link, profile: &Profile) {
        let Some(e) = profile
            .mnemonic("E")
            .filter(|m| m.write)
            .and_then(|m| Mnemonic::from_name(&m.name))
        else {
            return;
        };
        let mut counting = Counting { link, sent: 0 };
        let mut said = Vec::new();
        for req in [
            Request::VendorWrite {
                mnemonic: e,
                params: Vec::new(),
            },
            Request::VendorRead { mnemonic: e },
        ] {
            let fc = req.function().0;
            let answer = counting.transact(&req);
            let ended = matches!(&answer, Ok(Some(r)) if !r.is_exception());
            said.push(match answer {
                Ok(Some(Response::Exception { code, .. })) => {
                    format!("FC 0x{fc:02X}: refused with {code}")
                }
                Ok(Some(_)) => format!("FC 0x{fc:02X}: acknowledged"),
                Ok(None) => format!("FC 0x{fc:02X}: no answer"),
                Err(e) => format!("FC 0x{fc:02X}: {e}"),
            });
            if ended {
                break;
            }
        }
        self.account.requests += counting.sent;
        self.account.program_ended = Some(said.join(", then "));
    }

    /// Read the profile's CiA 402 status word (a read-only register named "Status Word") and its error flag
    /// (the `condition_flag` of an error record: MCode EF) before the first write and at the end, and say
    /// when a run leaves a drive found without a fault faulted, a drive found faulted without its fault, or
    /// its error flag otherwise than found.
    pub fn watch_status(mut self, profile: &Profile) -> Self {
        let registers = || profile.registers.iter().map(|r| r.get_ref());
        self.status_word = registers()
            .find(|r| {
                r.width == 1 && r.access == Access::Ro && r.name.eq_ignore_ascii_case("status word")
            })
            .map(Watched::of);
        self.error_flag = registers()
            .find_map(|r| r.condition_flag)
            .and_then(|flag| profile.register_at(flag, false))
            .map(Watched::of);
        self
    }

    /// What the drive's watched status said before the first write when it was not healthy: a CiA 402 fault
    /// (status word bit 3), an error condition (the error flag non-zero). `None` when healthy or not read.
    pub fn found_state(&self) -> Option<String> {
        let mut said = Vec::new();
        if let Some(word) = self.status_word.as_ref().and_then(|w| w.before)
            && word & (1 << 3) != 0
        {
            said.push(format!(
                "in fault (status word 0x{word:04X}, CiA 402 bit 3)"
            ));
        }
        if let Some(Watched {
            address,
            before: Some(flag),
            ..
        }) = &self.error_flag
            && *flag != 0
        {
            said.push(format!(
                "with an error condition (error flag 0x{address:04X} reads {flag})"
            ));
        }
        (!said.is_empty()).then(|| said.join(" and "))
    }

    /// The journal is a scratch file nobody asked for: remove it when the run ends with every kept
    /// parameter restored and verified (a killed run, or one that leaves a parameter changed, keeps it).
    pub fn scratch_journal(mut self) -> Self {
        self.scratch_journal = true;
        self
    }

    /// The account so far.
    pub fn account(&self) -> &Account {
        &self.account
    }

    /// True once the snapshot is taken.
    pub fn armed(&self) -> bool {
        self.snapshot.is_some()
    }

    /// The kept items the final restore puts back: all but the guarded ones no case has written to.
    fn restored_items(&self) -> impl Iterator<Item = &Item> {
        self.inventory.items.iter().filter(|i| {
            (!self.inventory.guarded.contains(&i.key) || self.written.contains(&i.key))
                && !self.live.contains(&i.key)
        })
    }

    /// What `case` can change among the kept items (a reset of every setting: every one but the guarded
    /// ones, which the profile takes as read-only, and the ones seen to change by themselves).
    pub fn touched(&self, case: &Case) -> BTreeSet<String> {
        let pdus = case_pdus(case);
        let mut keys = touched_by(&self.inventory.items, pdus.clone(), &self.inventory.resets);
        if !self.live.is_empty() {
            keys.retain(|k| !self.live.contains(k));
        }
        // A guarded item counts only where a request names it (a reset leaves what is read-only alone).
        if !self.inventory.resets.is_empty()
            && keys.iter().any(|k| self.inventory.guarded.contains(k))
        {
            let named = touched_by(&self.inventory.items, pdus, &[]);
            keys.retain(|k| !self.inventory.guarded.contains(k) || named.contains(k));
        }
        keys
    }

    /// Of the items `left` differing after a restore, the ones that change by themselves go to
    /// [`Account::live`] and are not put back or verified from then on; the others are returned. An item
    /// changes by itself when [`LIVE_READS`] more reads, with nothing written between, do not all read the
    /// same, and the value is off the snapshot by no more than twice what those reads spread over (an
    /// encoder's jitter; a write the drive did not take leaves a value far off, which stays unrestored).
    fn live_apart(
        items: &[Item],
        live: &mut BTreeSet<String>,
        account: &mut Account,
        link: &mut dyn Link,
        left: Vec<Unrestored>,
    ) -> Vec<Unrestored> {
        let mut out = Vec::new();
        for u in left {
            let Some(item) = items.iter().find(|i| i.key == u.key).cloned() else {
                out.push(u);
                continue;
            };
            let Some(after) = u.after.clone() else {
                out.push(u);
                continue;
            };
            let mut seen = vec![after];
            for _ in 0..LIVE_READS {
                link.idle(LIVE_GAP);
                match read_all(link, std::slice::from_ref(&item)) {
                    Ok(mut m) => match m.remove(&item.key).flatten() {
                        Some(v) => seen.push(v),
                        None => break,
                    },
                    Err(_) => break,
                }
            }
            if let Some(reads) = live_reads(&u.before, &seen) {
                live.insert(u.key.clone());
                account.live.push(Unrestored {
                    reason: format!("read {reads} with nothing written between"),
                    ..u
                });
            } else {
                out.push(u);
            }
        }
        out
    }

    /// What `case` can have changed, once it ran: [`touched`](Self::touched), less the guarded items (see
    /// [`Inventory::guarded`]) that only writes the drive refused (`refused`, request PDUs answered with an
    /// exception only: [`crate::runner::Runner::refused_writes`]) would have written. A refused write to a
    /// status flag or an input changes nothing; were it counted, the flag would be put back from then on, and
    /// a flag or input that changes by itself (the axis moving, a switch) would read as not restored.
    pub fn taken(&self, case: &Case, refused: &[Vec<u8>]) -> Touched {
        let all = self.touched(case);
        let guarded: Vec<Item> = self
            .inventory
            .items
            .iter()
            .filter(|i| all.contains(&i.key) && self.inventory.guarded.contains(&i.key))
            .cloned()
            .collect();
        if guarded.is_empty() || refused.is_empty() {
            return all;
        }
        let pdus = case_pdus(case)
            .into_iter()
            .filter(|p| !refused.iter().any(|r| r.as_slice() == *p))
            .collect();
        // A reset of the settings leaves what is read-only alone.
        let taken = touched_by(&guarded, pdus, &[]);
        all.into_iter()
            .filter(|k| !self.inventory.guarded.contains(k) || taken.contains(k))
            .collect()
    }

    /// Why `case` may not run once the snapshot is taken: it can write a parameter that would not write back
    /// as read (see [`Account::unwritable`]). `None` when nothing stands in its way.
    pub fn unrestorable(&self, case: &Case) -> Option<String> {
        // A reset of every setting also resets the settings this run keeps none of (motion or destructive
        // ones without their flags: the LMD's MS, IS): nothing would put them back.
        let gated: Vec<&str> = self
            .inventory
            .excluded
            .iter()
            .filter(|e| {
                e.reason.starts_with(GATED_MOTION) || e.reason.starts_with(GATED_DESTRUCTIVE)
            })
            .map(|e| e.name.as_str())
            .collect();
        if !gated.is_empty() && writes_any(&case_pdus(case), &self.inventory.resets) {
            return Some(format!(
                "not run: it resets every setting, and this run keeps and puts back none of {} (left out without --allow-motion or --allow-destructive; leave as found)",
                gated.join(", ")
            ));
        }
        if self.unwritable.is_empty() && self.multi_line.is_empty() {
            return None;
        }
        let mut keys = touched_by(&self.unwritable, case_pdus(case), &self.inventory.resets);
        keys.extend(touched_by(&self.multi_line, case_pdus(case), &[]));
        let names: Vec<&str> = self
            .account
            .unwritable
            .iter()
            .filter(|e| keys.contains(&e.key))
            .map(|e| e.name.as_str())
            .collect();
        (!names.is_empty()).then(|| {
            format!(
                "not run: it can change {}, which one write did not put back as read before the first write, or which was not tried (leave as found; see the report)",
                names.join(", ")
            )
        })
    }

    /// A kept setting no case may write, with why (listed in the account).
    fn written_by_no_case(&mut self, item: &Item, reason: String) {
        self.account.unwritable.push(Excluded {
            key: item.key.clone(),
            name: item.name.clone(),
            reason,
        });
        self.unwritable.push(item.clone());
    }

    /// Read every kept parameter and write the journal, before the first write. Items the drive does not
    /// read are left out with the reason.
    pub fn take_snapshot(&mut self, link: &mut dyn Link) -> Result<(), SnapshotError> {
        let mut counting = Counting { link, sent: 0 };
        for w in [&mut self.status_word, &mut self.error_flag]
            .into_iter()
            .flatten()
        {
            w.before = w.read(&mut counting);
        }
        let mut read = read_all(&mut counting, &self.inventory.items);
        if let Ok(first) = read.as_mut() {
            narrow_unread_pairs(&mut counting, &mut self.inventory.items, first)?;
        }
        // Read again, [`LIVE_READS`] times, [`LIVE_GAP`] apart: a value that differs between the reads,
        // nothing written between, changes by itself (an encoder count, a lead/lag on a drive with its
        // motor attached): neither put back nor verified. (An encoder jittering by ±2 reads the same eight
        // times in a row once in 78,125; see [`LIVE_READS`].)
        let mut again = Vec::new();
        for _ in 0..LIVE_READS {
            counting.idle(LIVE_GAP);
            again.push(read_all(&mut counting, &self.inventory.items));
        }
        self.account.requests += counting.sent;
        let read = read?;
        let again = again.into_iter().collect::<Result<Vec<_>, _>>()?;
        let mut snapshot = BTreeMap::new();
        let mut kept = Vec::new();
        for item in std::mem::take(&mut self.inventory.items) {
            let first = read.get(&item.key).cloned().flatten();
            let second = again
                .iter()
                .filter_map(|m| m.get(&item.key).cloned().flatten())
                .find(|b| first.as_ref().is_some_and(|a| !a.same(b)));
            if let (Some(a), Some(b)) = (&first, &second) {
                let reason = format!("read {a}, then {b}, with nothing written between");
                self.inventory.excluded.push(Excluded {
                    key: item.key.clone(),
                    name: item.name.clone(),
                    reason: format!("it changes by itself ({reason}): a measured value, neither put back nor verified"),
                });
                self.account.live.push(Unrestored {
                    key: item.key.clone(),
                    name: item.name.clone(),
                    before: a.clone(),
                    after: Some(b.clone()),
                    reason,
                });
                continue;
            }
            match first {
                Some(v) => {
                    snapshot.insert(item.key.clone(), v);
                    kept.push(item);
                }
                None => self.inventory.excluded.push(Excluded {
                    key: item.key.clone(),
                    name: item.name.clone(),
                    reason: "the drive did not read it back before the first write".into(),
                }),
            }
        }
        // A vendor setting goes back by writing what FC 0x41 read, in the form the drive reads it in, which is
        // the drive's choice (freedom `fc41-read-back-format`): a drive may read a setting in a form its FC 0x42
        // does not take (the setups of all lines where a write sets one). Before anything changes it, that
        // write is tried with the value as found and read back; a setting it does not put back is written
        // by no case. (Registers, coils and objects go back in the form the specification fixes.)
        let sent = counting.sent;
        // A setting read for several lines at once goes back one line per write: the keeper puts it back
        // so (after a reset of every setting, say), but a case's own write-back is one write, so no case
        // writes it directly.
        //
        // The trial write is itself a write: a drive that reads a setting in another form than it takes
        // (the twelfth wave's LMD reads S1 as IS's line, "1, 0, 1" = line, type, active, and takes S1 as
        // type, active, sink) takes the fields for others, and a field it does not read back (sink or
        // source) cannot be put back at all. So a setting whose read the manual does not document, whose
        // setup the flags allow (an input that may become a limit or a homing input), and whose value read
        // begins with the number of the line it may be read as (the profile's `read_as_line`: S1 read
        // "1, ..."), gets no trial write: it may be that line, or the write's fields with a first field that
        // happens to be the same (input 1 a homing input, type 1), which only a write tells apart. No case
        // writes it, and it is never written. Any other value (the reference's "0, 0, 0", the tenth wave's
        // "0, 1", freedom `lmd-input-setup-fields`) cannot be the line, and the trial is made; so it is where
        // the manual gives the form, as the MDrive's for S1-S4 (line 730).
        for item in kept
            .iter()
            .filter(|i| matches!(i.place, Place::Mnemonic { .. }))
        {
            let found = &snapshot[&item.key];
            if let (Some(&line), Value::Text(t)) =
                (self.inventory.reassigning.get(&item.key), found)
                && t.trim_start_matches('=')
                    .split(',')
                    .next()
                    .and_then(|f| f.trim().parse::<u8>().ok())
                    == Some(line)
            {
                self.written_by_no_case(item, format!(
                    "it reads {found}, which may be the line of point {line} of another setting (the manual documents no read of it), and it sets up what the flags allow (an I/O point, a limit): a write of it as read, to try whether it puts the setting back, may be taken as other fields and change it, so none is made and no case writes it"
                ));
                continue;
            }
            let reqs = write_requests(item, found, None);
            if reqs.is_empty() {
                // Read as nothing (a drive that lists the outputs set up, and has none yet): no write puts
                // that back, so no case writes it (the fourteenth wave's LMD read OS as "", and a case's
                // "=1,16,0" made its shared I/O point 1 an output for good).
                self.written_by_no_case(item, format!(
                    "it reads {found}, and no write puts a setting back as nothing, so none is tried and no case writes it"
                ));
                continue;
            }
            let mut answer = None;
            for req in &reqs {
                answer = counting.transact(req)?;
                if answer.as_ref().is_none_or(Response::is_exception) {
                    break;
                }
            }
            let after = read_all(&mut counting, std::slice::from_ref(item))?;
            let after = after.get(&item.key).cloned().flatten();
            let why = match (&answer, &after) {
                (None, _) => "no answer".to_string(),
                (Some(Response::Exception { code, .. }), _) => format!("refused with {code}"),
                (Some(r), _) if r.is_exception() => format!("refused: {r:?}"),
                (_, Some(v)) if v.same(found) && reqs.len() == 1 => continue,
                (_, Some(v)) if v.same(found) => {
                    self.account.unwritable.push(Excluded {
                        key: item.key.clone(),
                        name: item.name.clone(),
                        reason: format!(
                            "it reads as {} lines ({found}), which one write does not set: the keeper puts it back one line per write, as it did with the value read first",
                            reqs.len()
                        ),
                    });
                    self.multi_line.push(item.clone());
                    continue;
                }
                (_, Some(v)) => format!("acknowledged, but it then read {v}"),
                (_, None) => "acknowledged, but it then did not read back".to_string(),
            };
            self.written_by_no_case(
                item,
                format!("writing back the value read first ({found}) did not put it back: {why}"),
            );
        }
        self.account.requests += counting.sent - sent;
        self.inventory.items = kept;
        self.account.kept = snapshot.len();
        self.account.excluded = self.inventory.excluded.clone();
        self.account.snapshot_taken = true;
        let now = unix_ms();
        self.journal = Some(Journal {
            format: JOURNAL_FORMAT.into(),
            target: self.header.0.clone(),
            profile: self.header.1.clone(),
            unit: self.header.2,
            started_unix_ms: now,
            updated_unix_ms: now,
            state: "running".into(),
            items: self
                .inventory
                .items
                .iter()
                .filter(|i| !self.inventory.guarded.contains(&i.key))
                .map(|i| JournalItem {
                    item: i.clone(),
                    before: snapshot[&i.key].clone(),
                })
                .collect(),
            excluded: self.inventory.excluded.clone(),
            unrestored: Vec::new(),
            last_case: None,
        });
        self.snapshot = Some(snapshot);
        self.save_journal()?;
        Ok(())
    }

    fn save_journal(&mut self) -> Result<(), JournalError> {
        if let (Some(j), Some(p)) = (self.journal.as_mut(), &self.journal_path) {
            j.updated_unix_ms = unix_ms();
            j.save(p)?;
            self.last_saved = Some(std::time::Instant::now());
        }
        Ok(())
    }

    /// Bring `link` (the reference drive, see [`crate::runner::Runner::reference`]) to the snapshot: every
    /// kept parameter written to the value the target was found with. The items the reference would not
    /// take are returned (the reference then judges them from its own value).
    pub fn align(&self, link: &mut dyn Link, profile: &Profile) -> Vec<Unrestored> {
        let Some(snapshot) = &self.snapshot else {
            return Vec::new();
        };
        let items: Vec<Item> = self.restored_items().cloned().collect();
        match restore(link, &items, snapshot, Some(profile)) {
            Ok((_, left)) => left,
            Err(e) => items
                .iter()
                .filter_map(|i| {
                    Some(Unrestored {
                        key: i.key.clone(),
                        name: i.name.clone(),
                        before: snapshot.get(&i.key)?.clone(),
                        after: None,
                        reason: format!("the reference drive: {e}"),
                    })
                })
                .collect(),
        }
    }

    /// After a case: restore what it can have changed (`keys`) and verify.
    pub fn after_case(
        &mut self,
        link: &mut dyn Link,
        case_id: &str,
        keys: &BTreeSet<String>,
        profile: &Profile,
    ) -> Result<(), TargetError> {
        let Some(snapshot) = &self.snapshot else {
            return Ok(());
        };
        if let Some((_, since)) = self.checkpoint.as_mut() {
            since.extend(keys.iter().cloned());
        }
        let items: Vec<Item> = self
            .inventory
            .items
            .iter()
            .filter(|i| keys.contains(&i.key))
            .cloned()
            .collect();
        if items.is_empty() {
            return Ok(());
        }
        for i in items
            .iter()
            .filter(|i| self.inventory.guarded.contains(&i.key))
        {
            if self.written.insert(i.key.clone())
                && let Some(j) = self.journal.as_mut()
            {
                j.items.push(JournalItem {
                    item: i.clone(),
                    before: snapshot[&i.key].clone(),
                });
                self.last_saved = None;
            }
        }
        let left = self.put_back(link, &items, profile)?;
        let was: Vec<Unrestored> = self.pending.values().cloned().collect();
        for i in &items {
            self.pending.remove(&i.key);
        }
        for u in left {
            self.pending.insert(u.key.clone(), u);
        }
        let now: Vec<Unrestored> = self.pending.values().cloned().collect();
        let due = self
            .last_saved
            .is_none_or(|t| t.elapsed() >= std::time::Duration::from_secs(1));
        if let Some(j) = self.journal.as_mut() {
            j.last_case = Some(case_id.to_string());
            if now != was || due {
                j.unrestored = now;
                let _ = self.save_journal();
            }
        }
        Ok(())
    }

    /// Before the first case that leaves the drive changed for good ([`crate::cases::Tag::Irreversible`]:
    /// the LMD's CP clears the stored program, UG puts the drive in firmware-upgrade mode, where it may refuse
    /// the reads and writes of a restore): everything that differs is put back and verified now, while the
    /// drive still answers as it did. At the end, a parameter verified here that no case wrote since and that
    /// the drive then no longer lets be read or written is listed apart
    /// ([`Account::verified_before_irreversible`]), not as unrestored. True when everything read as before.
    pub fn checkpoint(&mut self, link: &mut dyn Link, profile: &Profile) -> bool {
        if self.snapshot.is_none() || self.checkpoint.is_some() {
            return true;
        }
        let items: Vec<Item> = self.restored_items().cloned().collect();
        let left: BTreeSet<String> = match self.put_back(link, &items, profile) {
            Ok(left) => left.into_iter().map(|u| u.key).collect(),
            Err(_) => items.iter().map(|i| i.key.clone()).collect(),
        };
        let clean = left.is_empty();
        self.checkpoint = Some((left, BTreeSet::new()));
        clean
    }

    /// Before a case that saves the working settings to NVM (it writes a register of [`Inventory::saves`]):
    /// every kept item that differs is put back now, so that the save stores the settings as found. A case
    /// may change a setting no request of it names (DC/IC change the variable their value names), and the
    /// restore after each case puts back only what the case named; the save would store that change for
    /// good. True when the case saves (whatever the restore gave: the final one says what is left).
    pub fn before_save(&mut self, link: &mut dyn Link, case: &Case, profile: &Profile) -> bool {
        if self.snapshot.is_none() || !writes_any(&case_pdus(case), &self.inventory.saves) {
            return false;
        }
        let items: Vec<Item> = self.restored_items().cloned().collect();
        let _ = self.put_back(link, &items, profile);
        true
    }

    /// Put back every item of `items` that differs from the snapshot and verify ([`restore`]), counting the
    /// requests and writes; the items still differing, less those seen to change by themselves
    /// ([`Keeper::live_apart`]).
    fn put_back(
        &mut self,
        link: &mut dyn Link,
        items: &[Item],
        profile: &Profile,
    ) -> Result<Vec<Unrestored>, TargetError> {
        let Some(snapshot) = self.snapshot.take() else {
            return Ok(Vec::new());
        };
        let mut counting = Counting { link, sent: 0 };
        let restored =
            restore(&mut counting, items, &snapshot, Some(profile)).map(|(writes, left)| {
                self.account.restore_writes += writes;
                Self::live_apart(
                    &self.inventory.items,
                    &mut self.live,
                    &mut self.account,
                    &mut counting,
                    left,
                )
            });
        self.account.requests += counting.sent;
        self.snapshot = Some(snapshot);
        restored
    }

    /// At the end (or on an interrupt, an error, a dead target): restore everything that differs and verify.
    /// When the target no longer answers, every item is reported unrestored and the journal stays `running`
    /// for `restore --journal`.
    pub fn finish(&mut self, link: &mut dyn Link, profile: &Profile) -> Account {
        let Some(snapshot) = self.snapshot.clone() else {
            return self.account.clone();
        };
        // A program the cases started changes what is put back while it runs, and must not be left running.
        if std::mem::take(&mut self.program_started) {
            self.end_program(link, profile);
        }
        let items: Vec<Item> = self.restored_items().cloned().collect();
        let restored = self.put_back(link, &items, profile);
        let mut counting = Counting { link, sent: 0 };
        const FAULT: u16 = 1 << 3;
        if let Some(w) = &self.status_word
            && let Some(before) = w.before
            && let Some(after) = w.read(&mut counting)
        {
            match (before & FAULT != 0, after & FAULT != 0) {
                (false, true) => self.account.left_faulted = Some((before, after)),
                (true, false) => self.account.fault_cleared = Some((before, after)),
                _ => {}
            }
        }
        if let Some(w) = &self.error_flag
            && let Some(before) = w.before
            && let Some(after) = w.read(&mut counting)
            && (before != 0) != (after != 0)
        {
            self.account.error_flag_changed = Some((w.address, before, after));
        }
        self.account.requests += counting.sent;
        match restored {
            Ok(left) => {
                // Verified before the irreversible cases, written by none since, refused now: the drive's
                // state after those cases, not a parameter the run left changed.
                let (apart, left): (Vec<Unrestored>, Vec<Unrestored>) =
                    left.into_iter().partition(|u| {
                        self.checkpoint.as_ref().is_some_and(|(bad, since)| {
                            !bad.contains(&u.key)
                                && !since.contains(&u.key)
                                && (u.after.is_none() || u.reason.contains("refused"))
                        })
                    });
                self.account.verified_before_irreversible = apart;
                self.account.unrestored = left;
                if let Some(j) = self.journal.as_mut() {
                    j.state = if self.account.unrestored.is_empty() {
                        "restored"
                    } else {
                        "unrestored"
                    }
                    .into();
                    j.unrestored = self.account.unrestored.clone();
                }
            }
            Err(e) => {
                self.account.unrestored = items
                    .iter()
                    .map(|i| Unrestored {
                        key: i.key.clone(),
                        name: i.name.clone(),
                        before: snapshot[&i.key].clone(),
                        after: None,
                        reason: format!("the target stopped answering: {e}"),
                    })
                    .collect();
            }
        }
        if let Err(e) = self.save_journal() {
            self.account.unrestored.push(Unrestored {
                key: "journal".into(),
                name: "state journal".into(),
                before: Value::Text(String::new()),
                after: None,
                reason: e.to_string(),
            });
        }
        if self.scratch_journal
            && self.account.clean()
            && let Some(path) = &self.journal_path
            && std::fs::remove_file(path).is_ok()
        {
            self.account.journal = None;
        }
        self.account.clone()
    }
}

/// Why the snapshot could not be taken (the run stops before its first write).
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    #[error(transparent)]
    Target(#[from] TargetError),
    #[error(transparent)]
    Journal(#[from] JournalError),
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn item(key: &str, place: Place) -> Item {
        Item {
            key: key.into(),
            name: key.into(),
            place,
        }
    }

    #[test]
    fn the_plan_lists_what_differs_and_settings_compare_as_the_drive_means_them() {
        let items = vec![
            item(
                "h",
                Place::Holding {
                    address: 1,
                    width: 2,
                },
            ),
            item("c", Place::Coil { address: 0 }),
            item(
                "m",
                Place::Mnemonic {
                    mnemonic: "S1".into(),
                },
            ),
        ];
        let snap: BTreeMap<String, Value> = [
            ("h".to_string(), Value::Words(vec![1, 2])),
            ("c".to_string(), Value::Bit(true)),
            ("m".to_string(), Value::Text("0, 1, 0".into())),
        ]
        .into();
        let now: BTreeMap<String, Option<Value>> = [
            ("h".to_string(), Some(Value::Words(vec![1, 3]))),
            ("c".to_string(), None),
            ("m".to_string(), Some(Value::Text("=0,1,0".into()))),
        ]
        .into();
        let p = plan(&items, &snap, &now);
        let keys: Vec<&str> = p.iter().map(|d| d.key.as_str()).collect();
        assert_eq!(keys, ["h", "c"]);
        assert_eq!(
            write_request(&items[0], &p[0].before, None),
            Some(Request::WriteMultipleRegisters {
                address: 1,
                values: vec![1, 2]
            })
        );
    }

    /// A drive of 16-bit holding registers in memory; `dead` stops it answering, `stuck` ignores writes to
    /// one address.
    struct Fake {
        regs: BTreeMap<u16, u16>,
        dead: bool,
        stuck: Option<u16>,
        requests: usize,
        /// Reads of more than one register are refused (exception 02), as some drives do across parameters.
        one_at_a_time: bool,
        /// Writes of more than one register are refused (exception 02).
        writes_one_at_a_time: bool,
        /// Writes of more than one register are acknowledged, but only the first register is written.
        writes_first_only: bool,
        /// The blocks the restore was told the target refuses (`Link::refuse_blocks`).
        refused: Vec<Block>,
    }

    impl Fake {
        /// Holding registers 0-2 holding 10, 11, 12; answering, nothing stuck.
        fn three() -> Self {
            Fake {
                regs: [(0, 10), (1, 11), (2, 12)].into(),
                dead: false,
                stuck: None,
                requests: 0,
                one_at_a_time: false,
                writes_one_at_a_time: false,
                writes_first_only: false,
                refused: Vec::new(),
            }
        }
    }

    impl Link for Fake {
        fn blocks(&self, kind: Block) -> bool {
            !self.refused.contains(&kind)
        }

        fn refuse_blocks(&mut self, kind: Block) {
            self.refused.push(kind);
        }

        fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
            self.requests += 1;
            if self.dead {
                return Ok(None);
            }
            Ok(match req {
                Request::ReadHoldingRegisters { quantity, .. }
                    if self.one_at_a_time && *quantity > 1 =>
                {
                    Some(Response::exception(
                        FunctionCode::READ_HOLDING_REGISTERS,
                        codec::ExceptionCode::ILLEGAL_DATA_ADDRESS,
                    ))
                }
                Request::ReadHoldingRegisters { address, quantity } => (0..*quantity)
                    .map(|i| self.regs.get(&(address + i)).copied())
                    .collect::<Option<Vec<u16>>>()
                    .map(|values| Response::ReadHoldingRegisters { values }),
                Request::WriteMultipleRegisters { values, .. }
                    if self.writes_one_at_a_time && values.len() > 1 =>
                {
                    Some(Response::exception(
                        FunctionCode::WRITE_MULTIPLE_REGISTERS,
                        codec::ExceptionCode::ILLEGAL_DATA_ADDRESS,
                    ))
                }
                Request::WriteMultipleRegisters { address, values } => {
                    let taken = if self.writes_first_only {
                        1
                    } else {
                        values.len()
                    };
                    for (a, v) in (*address..).zip(&values[..taken]) {
                        if self.stuck != Some(a) {
                            self.regs.insert(a, *v);
                        }
                    }
                    Some(Response::WriteMultipleRegisters {
                        address: *address,
                        quantity: values.len() as u16,
                    })
                }
                _ => None,
            })
        }
    }

    fn holding(address: u16, width: u8) -> Item {
        item(
            &format!("holding:{address}"),
            Place::Holding { address, width },
        )
    }

    /// A 32-bit parameter the target does not read whole (register 3 is not there) but reads as one register
    /// is kept as that one register, read and put back at its width; one it reads whole, or not at all,
    /// stays as it was.
    #[test]
    fn a_pair_read_only_as_one_register_is_kept_as_one() {
        let mut fake = Fake::three();
        let mut items = vec![holding(0, 2), holding(2, 2), holding(5, 2)];
        let mut read = read_all(&mut fake, &items).expect("reads");
        assert_eq!(read["holding:2"], None, "the pair 2-3 is not read whole");
        narrow_unread_pairs(&mut fake, &mut items, &mut read).expect("reads");
        assert_eq!(read["holding:0"], Some(Value::Words(vec![10, 11])));
        assert_eq!(read["holding:2"], Some(Value::Words(vec![12])));
        assert_eq!(read["holding:5"], None);
        assert_eq!(
            items[0].place,
            Place::Holding {
                address: 0,
                width: 2
            }
        );
        assert_eq!(
            items[1].place,
            Place::Holding {
                address: 2,
                width: 1
            }
        );
        assert_eq!(
            items[2].place,
            Place::Holding {
                address: 5,
                width: 2
            }
        );
    }

    /// Adjacent registers are read in one request, each parameter at its width; a gap or a coil starts
    /// another read.
    #[test]
    fn adjacent_parameters_are_read_in_one_request() {
        let mut fake = Fake::three();
        fake.regs.extend([(3, 13), (7, 17)]);
        let items = [holding(0, 2), holding(2, 1), holding(3, 1), holding(7, 1)];
        let read = read_all(&mut fake, &items).expect("reads");
        assert_eq!(fake.requests, 2, "0-3 in one read, 7 in another");
        assert_eq!(read["holding:0"], Some(Value::Words(vec![10, 11])));
        assert_eq!(read["holding:2"], Some(Value::Words(vec![12])));
        assert_eq!(read["holding:3"], Some(Value::Words(vec![13])));
        assert_eq!(read["holding:7"], Some(Value::Words(vec![17])));
        assert!(fake.refused.is_empty());
    }

    /// A target that refuses a read of several parameters is read one at a time, the same values, and no
    /// block read is tried on it again.
    #[test]
    fn a_target_refusing_block_reads_is_read_one_parameter_at_a_time() {
        let mut fake = Fake::three();
        fake.one_at_a_time = true;
        let items = [holding(0, 1), holding(1, 1), holding(2, 1)];
        let read = read_all(&mut fake, &items).expect("reads");
        assert_eq!(fake.requests, 4, "the refused block, then one read each");
        assert_eq!(fake.refused, [Block::Read]);
        for (a, v) in [(0, 10), (1, 11), (2, 12)] {
            assert_eq!(read[&format!("holding:{a}")], Some(Value::Words(vec![v])));
        }
        fake.requests = 0;
        read_all(&mut fake, &items).expect("reads");
        assert_eq!(fake.requests, 3, "no block read again");
    }

    /// The snapshot of `fake`'s registers 0-2 (10, 11, 12) as three one-register parameters, and `fake` with
    /// all three changed since.
    fn three_changed(fake: &mut Fake) -> (Vec<Item>, BTreeMap<String, Value>) {
        let items = vec![holding(0, 1), holding(1, 1), holding(2, 1)];
        let snapshot = [(0, 10), (1, 11), (2, 12)]
            .map(|(a, v)| (format!("holding:{a}"), Value::Words(vec![v])))
            .into();
        fake.regs.extend([(0, 90), (1, 91), (2, 92)]);
        (items, snapshot)
    }

    /// Restore the three registers [`three_changed`] changed: each put back, none left over; the writes sent.
    fn put_back_three(fake: &mut Fake) -> usize {
        let (items, snapshot) = three_changed(fake);
        let (writes, left) = restore(fake, &items, &snapshot, None).expect("restore");
        assert!(left.is_empty(), "{left:?}");
        assert_eq!(fake.regs, [(0, 10), (1, 11), (2, 12)].into());
        writes
    }

    /// Adjacent parameters that differ are put back with one FC 10 and verified with one read.
    #[test]
    fn adjacent_differing_parameters_are_put_back_in_one_write() {
        let mut fake = Fake::three();
        let writes = put_back_three(&mut fake);
        assert_eq!(writes, 1);
        assert_eq!(
            fake.requests, 3,
            "the read-back, one write, one verifying read"
        );
        assert!(fake.refused.is_empty());
    }

    /// A target that refuses a write of several parameters gets one write a parameter, and no block write
    /// again.
    #[test]
    fn a_target_refusing_block_writes_is_put_back_one_parameter_at_a_time() {
        let mut fake = Fake::three();
        fake.writes_one_at_a_time = true;
        let writes = put_back_three(&mut fake);
        assert_eq!(writes, 4, "the refused block, then one write each");
        assert_eq!(fake.refused, [Block::Write]);
        let (items, snapshot) = three_changed(&mut fake);
        fake.requests = 0;
        restore(&mut fake, &items, &snapshot, None).expect("restore");
        assert_eq!(
            fake.requests, 5,
            "the read-back, three writes, one verifying read"
        );
    }

    /// A target that acknowledges a block write but takes its first register only is put back one parameter
    /// at a time in the second round: nothing is left changed that single writes would have put back.
    #[test]
    fn a_block_write_acknowledged_but_not_taken_is_done_again_one_parameter_at_a_time() {
        let mut fake = Fake::three();
        fake.writes_first_only = true;
        let writes = put_back_three(&mut fake);
        assert_eq!(writes, 3, "the block, then registers 1 and 2 alone");
        assert_eq!(fake.refused, [Block::Write]);
    }

    /// Adjacent coils go back with one FC 0F, bit k of the data for the k-th coil (spec 6.11); anything but
    /// adjacent coils or holding registers, or a value not of its parameter's width, gets no block write.
    #[test]
    fn adjacent_coils_are_put_back_with_one_fc_0f() {
        let coils: Vec<Item> = (4..14u16)
            .map(|a| item(&format!("coil:{a}"), Place::Coil { address: a }))
            .collect();
        let (on, off) = (Value::Bit(true), Value::Bit(false));
        let values: Vec<&Value> = (0..10)
            .map(|k| if k % 3 == 0 { &on } else { &off })
            .collect();
        assert_eq!(adjacent(&coils, MAX_WRITE_BLOCK).len(), 10);
        assert_eq!(
            block_write_request(&coils, &values, None),
            Some(Request::WriteMultipleCoils {
                address: 4,
                quantity: 10,
                data: vec![0b0100_1001, 0b10],
            })
        );
        let wide = [holding(0, 2), holding(2, 1)];
        let one = Value::Words(vec![1]);
        assert_eq!(block_write_request(&wide, &[&one, &one], None), None);
        let m = item(
            "m",
            Place::Mnemonic {
                mnemonic: "S1".into(),
            },
        );
        assert_eq!(adjacent(&[m.clone(), m], MAX_WRITE_BLOCK).len(), 1);
    }

    /// A profile without FC 10 gets no block write.
    #[test]
    fn no_block_write_where_the_profile_has_no_fc_10() {
        let run = [holding(0, 1), holding(1, 1)];
        let v = Value::Words(vec![1]);
        let mut p = drives::corpus::Corpus::Embedded
            .load("generic")
            .expect("generic");
        assert!(block_write_request(&run, &[&v, &v], Some(&p)).is_some());
        p.functions
            .retain(|f| f.code != FunctionCode::WRITE_MULTIPLE_REGISTERS);
        assert!(block_write_request(&run, &[&v, &v], Some(&p)).is_none());
    }

    fn keeper_of(fake: &mut Fake, journal: &Path) -> Keeper {
        keeper_watching(fake, journal, None)
    }

    /// [`keeper_of`], the keeper watching `profile`'s status word where one is given.
    fn keeper_watching(fake: &mut Fake, journal: &Path, profile: Option<&Profile>) -> Keeper {
        let items = (0..3u16)
            .map(|a| {
                item(
                    &format!("holding:{a}"),
                    Place::Holding {
                        address: a,
                        width: 1,
                    },
                )
            })
            .collect();
        let mut k = Keeper::new(
            Inventory {
                items,
                ..Inventory::default()
            },
            "tcp://127.0.0.1:1".into(),
            "generic".into(),
            1,
            Some(journal.to_path_buf()),
        );
        if let Some(p) = profile {
            k = k.watch_status(p);
        }
        k.take_snapshot(fake).expect("snapshot");
        k
    }

    /// A CiA 402 drive found without a fault and left faulted (a watchdog a case armed tripped) is said at
    /// the end: the status word before the first write and after the final restore. Not when it stays
    /// healthy, nor when it was found faulted already.
    #[test]
    fn a_drive_left_faulted_is_said() {
        let sd2x = drives::corpus::Corpus::Embedded
            .profile("sd2x")
            .expect("sd2x");
        let dir = std::env::temp_dir().join(format!("keeper-fault-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        // (found, left, left faulted said, fault cleared said)
        for (found, left, faulted, cleared) in [
            (0x1270u16, 0x1238u16, true, false),
            (0x1270, 0x1270, false, false),
            (0x1238, 0x1238, false, false),
            (0x1238, 0x1270, false, true),
        ] {
            let mut fake = Fake::three();
            fake.regs.insert(2000, found);
            let mut k = keeper_watching(&mut fake, &dir.join("journal.json"), Some(&sd2x));
            assert_eq!(
                k.found_state().is_some(),
                found & 0x08 != 0,
                "{found:#06X}: {:?}",
                k.found_state()
            );
            fake.regs.insert(2000, left);
            let account = k.finish(&mut fake, &sd2x);
            assert!(account.clean());
            assert_eq!(
                account.left_faulted.is_some(),
                faulted,
                "{found:#06X} -> {left:#06X}"
            );
            assert_eq!(
                account.fault_cleared.is_some(),
                cleared,
                "{found:#06X} -> {left:#06X}"
            );
            let text = account.lines().join("\n");
            assert_eq!(text.contains("left faulted (0x1238"), faulted, "{text}");
            assert_eq!(
                text.contains("found faulted (status word 0x1238"),
                cleared,
                "{text}"
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The MCode error flag (EF, the `condition_flag` of ER) read before the first write and at the end: a
    /// run that clears an error condition (a CF the flags allowed) or leaves one says so. Not when it reads
    /// the same.
    #[test]
    fn an_error_flag_changed_by_a_run_is_said() {
        let mdrive = drives::corpus::Corpus::Embedded
            .profile("mdrive")
            .expect("mdrive");
        let dir = std::env::temp_dir().join(format!("keeper-flag-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        for (found, left, said) in [
            (1u16, 0u16, Some("cleared the error condition")),
            (0, 1, Some("left an error condition")),
            (1, 1, None),
            (0, 0, None),
        ] {
            let mut fake = Fake::three();
            fake.regs.insert(0x001F, found);
            let mut k = keeper_watching(&mut fake, &dir.join("journal.json"), Some(&mdrive));
            assert_eq!(
                k.found_state(),
                (found != 0)
                    .then(|| format!("with an error condition (error flag 0x001F reads {found})"))
            );
            fake.regs.insert(0x001F, left);
            let account = k.finish(&mut fake, &mdrive);
            assert!(account.clean());
            assert_eq!(
                account.error_flag_changed,
                said.map(|_| (0x001F, found, left)),
                "{found} -> {left}"
            );
            let text = account.lines().join("\n");
            if let Some(words) = said {
                assert!(text.contains(words), "{text}");
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A register the profile takes as read-only but a drive may take writes to (ST of the LMD) is kept,
    /// and put back only once a case wrote to it: a live value that changes by itself is not chased.
    #[test]
    fn a_guarded_register_is_put_back_only_once_a_case_wrote_it() {
        let lmd = drives::corpus::Corpus::Embedded.load("lmd").expect("lmd");
        let inv = inventory(&lmd, &Safety::default());
        assert!(
            inv.guarded.contains("holding:0x007B"),
            "ST: {:?}",
            inv.guarded
        );
        assert!(inv.items.iter().any(|i| i.key == "holding:0x007B"));
        assert!(
            !inv.guarded.contains("holding:0x0000"),
            "A is read/write by the profile"
        );
        let (dir, journal, p) = journal_and_generic("mbh-guarded");
        let keeper = |fake: &mut Fake| {
            let mut k = Keeper::new(
                Inventory {
                    items: (0..3u16).map(|a| holding(a, 1)).collect(),
                    guarded: ["holding:2".to_string()].into(),
                    ..Inventory::default()
                },
                "tcp://127.0.0.1:1".into(),
                "generic".into(),
                1,
                Some(journal.clone()),
            );
            k.take_snapshot(fake).expect("snapshot");
            k
        };
        // Changed by itself, no case wrote it: left alone, and not in the journal.
        let mut fake = Fake::three();
        let mut k = keeper(&mut fake);
        assert_eq!(Journal::load(&journal).expect("journal").items.len(), 2);
        fake.regs.insert(0, 99);
        fake.regs.insert(2, 98);
        let a = k.finish(&mut fake, &p);
        assert_eq!((fake.regs[&0], fake.regs[&2]), (10, 98));
        assert!(a.clean(), "{a:?}");
        // Written by a case (the drive took it): put back after the case and verified at the end.
        let mut fake = Fake::three();
        let mut k = keeper(&mut fake);
        fake.regs.insert(2, 97);
        k.after_case(&mut fake, "c", &["holding:2".to_string()].into(), &p)
            .expect("restore");
        assert_eq!(fake.regs[&2], 12, "put back after the case");
        assert_eq!(Journal::load(&journal).expect("journal").items.len(), 3);
        fake.regs.insert(2, 96);
        let a = k.finish(&mut fake, &p);
        assert_eq!(fake.regs[&2], 12, "put back at the end");
        assert!(a.clean(), "{a:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_guarded_register_whose_write_the_drive_refused_is_not_taken_as_written() {
        let (dir, journal, _) = journal_and_generic("mbh-taken");
        let mut fake = Fake::three();
        let mut k = Keeper::new(
            Inventory {
                items: (0..3u16).map(|a| holding(a, 1)).collect(),
                guarded: ["holding:2".to_string()].into(),
                ..Inventory::default()
            },
            "tcp://127.0.0.1:1".into(),
            "generic".into(),
            1,
            Some(journal),
        );
        k.take_snapshot(&mut fake).expect("snapshot");
        let key = |a: u16| format!("holding:{a}");
        // FC 16 of registers 1-2: one request writes a kept register and a guarded one.
        let both = vec![0x10, 0, 1, 0, 2, 4, 0, 7, 0, 8];
        let guarded_only = vec![0x06, 0, 2, 0, 9];
        let other = vec![0x06, 0, 1, 0, 9];
        let all: Touched = [key(1), key(2)].into();
        let c = one_request_case(both.clone());
        assert_eq!(k.taken(&c, &[]), all, "nothing refused: all it touches");
        assert_eq!(
            k.taken(&c, std::slice::from_ref(&both)),
            [key(1)].into(),
            "refused: the guarded register is not taken, the kept one is restored all the same"
        );
        let c = one_request_case(guarded_only.clone());
        assert!(k.taken(&c, std::slice::from_ref(&guarded_only)).is_empty());
        assert_eq!(k.taken(&c, std::slice::from_ref(&other)), [key(2)].into());
        let mut two = one_request_case(guarded_only.clone());
        two.steps.extend(one_request_case(both.clone()).steps);
        assert_eq!(
            k.taken(&two, std::slice::from_ref(&guarded_only)),
            all,
            "a second write of the guarded register was taken"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A directory of this test process for a journal (its path), and the generic profile.
    fn journal_and_generic(name: &str) -> (PathBuf, PathBuf, Profile) {
        let dir = std::env::temp_dir().join(format!("{name}-{}", std::process::id()));
        let journal = dir.join("journal.json");
        let p = drives::corpus::Corpus::Embedded
            .load("generic")
            .expect("generic");
        (dir, journal, p)
    }

    #[test]
    fn the_keeper_restores_verifies_and_journals_and_names_what_does_not_come_back() {
        let (dir, journal, p) = journal_and_generic("mbh-keeper");
        let mut fake = Fake {
            stuck: Some(2),
            ..Fake::three()
        };
        let mut k = keeper_of(&mut fake, &journal);
        let j = Journal::load(&journal).expect("journal before the first write");
        assert_eq!(j.state, "running");
        assert_eq!(j.snapshot().len(), 3);
        fake.regs.insert(0, 99);
        fake.regs.insert(2, 98);
        fake.stuck = Some(2);
        let a = k.finish(&mut fake, &p);
        assert_eq!(fake.regs[&0], 10, "restored");
        assert_eq!(a.unrestored.len(), 1, "{a:?}");
        assert_eq!(a.unrestored[0].key, "holding:2");
        assert_eq!(a.unrestored[0].before, Value::Words(vec![12]));
        assert_eq!(a.unrestored[0].after, Some(Value::Words(vec![98])));
        assert_eq!(
            Journal::load(&journal).expect("journal").state,
            "unrestored"
        );

        // A dead target: the keeper gives up after a bounded number of silent requests, and the journal
        // stays `running` for `restore --journal`.
        let mut fake = Fake::three();
        let mut k = keeper_of(&mut fake, &journal);
        fake.dead = true;
        fake.requests = 0;
        let a = k.finish(&mut fake, &p);
        assert_eq!(a.unrestored.len(), 3, "{a:?}");
        assert!(
            a.unrestored[0].reason.contains("stopped answering"),
            "{a:?}"
        );
        assert!(
            fake.requests <= SILENT_IN_A_ROW as usize,
            "{}",
            fake.requests
        );
        assert_eq!(Journal::load(&journal).expect("journal").state, "running");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A journal nobody asked for (no `--journal`, no report directory) is removed after a verified
    /// restore, and kept where a parameter did not come back or the target stopped answering.
    #[test]
    fn a_scratch_journal_goes_once_the_drive_reads_as_found() {
        let (dir, journal, p) = journal_and_generic("mbh-scratch");
        let fresh = Fake::three;
        let finish = |fake: &mut Fake, change: &dyn Fn(&mut Fake), scratch: bool| {
            let mut k = keeper_of(fake, &journal);
            if scratch {
                k = k.scratch_journal();
            }
            assert!(journal.exists(), "journaled before the first write");
            fake.regs.insert(0, 99);
            change(fake);
            k.finish(fake, &p)
        };
        let a = finish(&mut fresh(), &|_| {}, true);
        assert!(a.clean(), "{a:?}");
        assert!(!journal.exists(), "removed after the verified restore");
        assert_eq!(a.journal, None, "and not named as the way back");
        // Asked for (`--journal`, a report directory): kept.
        let a = finish(&mut fresh(), &|_| {}, false);
        assert!(a.clean() && journal.exists(), "{a:?}");
        assert_eq!(a.journal.as_deref(), Some(journal.as_path()));
        // A parameter that does not come back, a target that stopped answering: kept.
        let a = finish(&mut fresh(), &|f| f.stuck = Some(0), true);
        assert!(!a.clean() && journal.exists(), "{a:?}");
        assert_eq!(
            Journal::load(&journal).expect("journal").state,
            "unrestored"
        );
        let a = finish(&mut fresh(), &|f| f.dead = true, true);
        assert!(!a.clean() && journal.exists(), "{a:?}");
        assert_eq!(Journal::load(&journal).expect("journal").state, "running");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_malformed_write_touches_what_its_header_and_bytes_reach_or_everything() {
        let items: Vec<Item> = (0..8u16)
            .map(|a| {
                item(
                    &format!("h{a}"),
                    Place::Holding {
                        address: a,
                        width: 1,
                    },
                )
            })
            .collect();
        let case = one_request_case;
        // FC 16 at 2, quantity 1, byte count 4 (disagrees), two words of data: registers 2 and 3.
        let t = touched(&items, &case(vec![0x10, 0, 2, 0, 1, 4, 0, 1, 0, 2]));
        assert_eq!(t, ["h2", "h3"].map(String::from).into());
        // FC 06 cut after its function code: the address is unknown, everything may have changed.
        assert_eq!(touched(&items, &case(vec![0x06])).len(), 8);
        // A read touches nothing.
        assert!(touched(&items, &case(vec![0x03, 0, 0, 0, 8])).is_empty());
    }

    /// A case of one exchange sending `pdu`.
    fn one_request_case(pdu: Vec<u8>) -> Case {
        Case {
            id: "t".into(),
            title: String::new(),
            reference: String::new(),
            requirement: String::new(),
            level: crate::cases::Level::Must,
            tags: vec![],
            steps: vec![Step::Exchange {
                send: Outgoing::Pdu(pdu),
                compare: crate::cases::Compare::Exact,
                capture: None,
                note: String::new(),
            }],
            requirements: vec![],
            freedoms: vec![],
        }
    }

    /// A drive of two vendor settings: S1 reads as `0, 1, 0` and takes `=0,1,0` back; OS reads the setups of
    /// all its lines (`1,16,1;2,16,1`, or apart by `sep`) where a write sets one line, so its FC 0x42 refuses
    /// what FC 0x41 read, and takes it one line per write (none where `locked`).
    struct Settings {
        s1: String,
        os: String,
        sep: &'static str,
        locked: bool,
        writes: Vec<String>,
    }

    impl Settings {
        fn new(sep: &'static str, locked: bool) -> Self {
            Settings {
                s1: "0, 1, 0".into(),
                os: ["1,16,1", "2,16,1"].join(sep),
                sep,
                locked,
                writes: vec![],
            }
        }
    }

    impl Link for Settings {
        fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
            let name = |m: &Mnemonic| m.name().trim().to_string();
            Ok(Some(match req {
                Request::VendorRead { mnemonic } => Response::VendorRead {
                    params: match name(mnemonic).as_str() {
                        "S1" => self.s1.clone(),
                        _ => self.os.clone(),
                    }
                    .into_bytes(),
                },
                Request::VendorWrite { mnemonic, params } => {
                    let text = String::from_utf8_lossy(params).into_owned();
                    self.writes.push(format!("{}{text}", name(mnemonic)));
                    let values = text.trim_start_matches('=');
                    let fields: Vec<&str> = values.split(',').collect();
                    match name(mnemonic).as_str() {
                        "S1" => self.s1 = fields.join(", "),
                        _ if self.locked || values.contains(';') || fields.len() != 3 => {
                            return Ok(Some(Response::exception(
                                FunctionCode::VENDOR_WRITE,
                                codec::ExceptionCode::ILLEGAL_DATA_VALUE,
                            )));
                        }
                        _ => {
                            // One line: it replaces the line of its number.
                            let mut lines: Vec<String> =
                                self.os.split(self.sep).map(str::to_string).collect();
                            for l in &mut lines {
                                if l.split(',').next() == Some(fields[0]) {
                                    *l = values.to_string();
                                }
                            }
                            self.os = lines.join(self.sep);
                        }
                    }
                    Response::VendorWrite {
                        mnemonic: *mnemonic,
                        written: params.len() as u8,
                    }
                }
                // IP, the reset of every setting (register 0x003C): the factory setup.
                Request::WriteSingleRegister { address: 0x3C, .. } => {
                    self.os = ["1,0,0", "2,0,0"].join(self.sep);
                    self.s1 = "0, 0, 0".into();
                    Response::WriteSingleRegister {
                        address: 0x3C,
                        value: 1,
                    }
                }
                _ => return Ok(None),
            }))
        }
    }

    fn settings_keeper() -> Keeper {
        let mnemonic = |m: &str| {
            item(
                &format!("mnemonic:{m}"),
                Place::Mnemonic { mnemonic: m.into() },
            )
        };
        Keeper::new(
            Inventory {
                items: vec![mnemonic("S1"), mnemonic("OS")],
                resets: vec![0x3C],
                ..Inventory::default()
            },
            "tcp://127.0.0.1:1".into(),
            "lmd".into(),
            1,
            None,
        )
    }

    fn setting_write(m: &str) -> Case {
        let req = Request::VendorWrite {
            mnemonic: Mnemonic::from_name(m).expect("mnemonic"),
            params: b"=1,16,0".to_vec(),
        };
        one_request_case(req.to_bytes().expect("pdu"))
    }

    fn reset() -> Case {
        let req = Request::WriteSingleRegister {
            address: 0x3C,
            value: 1,
        };
        one_request_case(req.to_bytes().expect("pdu"))
    }

    /// A vendor setting whose value as read does not write back is found out before the first write, and
    /// no case may write it, nor reset every setting; one that writes back as read is kept as usual.
    #[test]
    fn a_setting_that_does_not_write_back_as_read_is_written_by_no_case() {
        let mut k = settings_keeper();
        let mut drive = Settings::new(";", true);
        k.take_snapshot(&mut drive).expect("snapshot");
        // Each setting was written back as read, once, before anything changed it: OS line by line, the
        // first line refused.
        assert_eq!(drive.writes, ["S1=0,1,0", "OS=1,16,1"]);
        assert_eq!(
            (drive.s1.as_str(), drive.os.as_str()),
            ("0, 1, 0", "1,16,1;2,16,1")
        );
        let a = k.account();
        assert_eq!(a.kept, 2, "both are kept (and so verified at the end)");
        let keys: Vec<&str> = a.unwritable.iter().map(|e| e.key.as_str()).collect();
        assert_eq!(keys, ["mnemonic:OS"], "{a:?}");
        assert!(a.unwritable[0].reason.contains("refused"), "{a:?}");
        assert!(
            a.lines()
                .iter()
                .any(|l| l.contains("so no case wrote them: mnemonic:OS"))
        );
        let read = Request::VendorRead {
            mnemonic: Mnemonic::from_name("OS").expect("mnemonic"),
        };
        let why = k
            .unrestorable(&setting_write("OS"))
            .expect("a write of OS may not run");
        assert!(why.contains("mnemonic:OS"), "{why}");
        assert!(
            k.unrestorable(&reset()).is_some(),
            "a reset of every setting would change OS"
        );
        assert_eq!(k.unrestorable(&setting_write("S1")), None);
        assert_eq!(
            k.unrestorable(&one_request_case(read.to_bytes().expect("pdu"))),
            None
        );
    }

    /// A setting whose read the manual does not document, that sets up what only the flags allow (the LMD's
    /// S1, an input that may become a limit or a homing input), read beginning with the number of the line
    /// it may be read as (`read_as_line`), gets no trial write before the first write: the twelfth wave's
    /// LMD reads S1 as IS's line ("1, 0, 1": line, type, active) and takes S1 as type, active, sink, so
    /// writing back what it read made input 1 a homing input, sourcing, which no read shows. No case may
    /// write it. Read otherwise ("0, 1", the tenth wave's LMD: type and active), or kept without the flags'
    /// reason, it gets its trial write.
    #[test]
    fn a_reassigning_setting_read_as_a_line_gets_no_trial_write() {
        let mut k = settings_keeper();
        k.inventory.reassigning.insert("mnemonic:S1".into(), 1);
        let mut drive = Settings::new(";", true);
        drive.s1 = "1, 0, 1".into();
        k.take_snapshot(&mut drive).expect("snapshot");
        assert_eq!(drive.writes, ["OS=1,16,1"], "no write of S1");
        assert_eq!(drive.s1, "1, 0, 1");
        let a = k.account();
        let s1 = a
            .unwritable
            .iter()
            .find(|e| e.key == "mnemonic:S1")
            .expect("S1 is written by no case");
        assert!(
            s1.reason.contains("may be the line of point 1") && s1.reason.contains("none is made"),
            "{}",
            s1.reason
        );
        let why = k
            .unrestorable(&setting_write("S1"))
            .expect("a write of S1 may not run");
        assert!(why.contains("mnemonic:S1"), "{why}");
        // Without the flags' reason to keep it (not reassigning), the same drive gets the trial write, and the
        // write taken in another form is what the trial finds.
        let mut k = settings_keeper();
        let mut drive = Settings::new(";", true);
        drive.s1 = "1, 0, 1".into();
        k.take_snapshot(&mut drive).expect("snapshot");
        assert_eq!(drive.writes, ["S1=1,0,1", "OS=1,16,1"]);
        let mut k = settings_keeper();
        k.inventory.reassigning.insert("mnemonic:S1".into(), 1);
        let mut drive = Settings::new(";", true);
        drive.s1 = "0, 1".into();
        k.take_snapshot(&mut drive).expect("snapshot");
        assert_eq!(drive.writes, ["S1=0,1", "OS=1,16,1"]);
        assert_eq!(k.unrestorable(&setting_write("S1")), None);
    }

    /// A case that starts or resumes a program (MCode EX or RS, by FC 0x42 or 0x41) makes `finish` end it
    /// with E before anything is put back: by FC 0x42, and by FC 0x41 where 0x42 is refused (this drive takes
    /// E only as a read); a run whose cases sent neither sends no E.
    #[test]
    fn a_program_a_case_started_is_ended_at_the_end() {
        let p = drives::corpus::Corpus::Embedded.load("lmd").expect("lmd");
        let m = |name: &str| Mnemonic::from_name(name).expect("mnemonic");
        let bytes = |r: Request| r.to_bytes().expect("pdu");
        let starts = [
            bytes(Request::VendorWrite {
                mnemonic: m("EX"),
                params: b"A3".to_vec(),
            }),
            bytes(Request::VendorRead { mnemonic: m("RS") }),
            bytes(Request::VendorRead { mnemonic: m("EX") }),
        ];
        for pdu in starts {
            let mut k = settings_keeper();
            let mut drive = Settings::new(";", false);
            k.take_snapshot(&mut drive).expect("snapshot");
            k.note_case(&one_request_case(pdu.clone()));
            let a = k.finish(&mut drive, &p);
            assert_eq!(
                drive.writes.last().map(String::as_str),
                Some("E"),
                "{pdu:02X?}"
            );
            let said = a.program_ended.as_deref().expect("the program is ended");
            assert!(
                said.starts_with("FC 0x42: refused") && said.ends_with("FC 0x41: acknowledged"),
                "{said}"
            );
            assert!(
                a.lines()
                    .iter()
                    .any(|l| l.contains("ended at the end with E"))
            );
        }
        for case in [setting_write("S1"), reset()] {
            let mut k = settings_keeper();
            let mut drive = Settings::new(";", false);
            k.take_snapshot(&mut drive).expect("snapshot");
            k.note_case(&case);
            let a = k.finish(&mut drive, &p);
            assert!(!drive.writes.iter().any(|w| w == "E"), "{:?}", drive.writes);
            assert_eq!(a.program_ended, None);
        }
    }

    /// A setting read as nothing (the fourteenth wave's LMD lists the I/O points set up as outputs, and has
    /// none at first: OS reads "") has no write that puts it back: none is tried and no case may write it
    /// (a case's "OS=1,16,0" made that LMD's shared point 1 an output, which nothing could undo).
    #[test]
    fn a_setting_read_as_nothing_is_written_by_no_case() {
        for empty in ["", " ", "="] {
            let mut k = settings_keeper();
            let mut drive = Settings::new(";", false);
            drive.os = empty.into();
            k.take_snapshot(&mut drive).expect("snapshot");
            assert_eq!(drive.writes, ["S1=0,1,0"], "no write of OS ({empty:?})");
            let a = k.account();
            let os = a
                .unwritable
                .iter()
                .find(|e| e.key == "mnemonic:OS")
                .expect("OS is written by no case");
            assert!(os.reason.contains("as nothing"), "{}", os.reason);
            let why = k
                .unrestorable(&setting_write("OS"))
                .expect("a write of OS may not run");
            assert!(why.contains("mnemonic:OS"), "{why}");
            assert_eq!(k.unrestorable(&setting_write("S1")), None);
        }
    }

    /// A setting read for all its lines at once (the LMD's OS, with the lines apart by `;` or by a space, as
    /// an independent LMD reads it) goes back one line per write: before the first write, and after a reset
    /// of every setting (the LMD's IP), which touches every kept item and may run; a case writing the
    /// setting itself may not (its own write-back is one write).
    #[test]
    fn a_setting_read_for_several_lines_goes_back_line_by_line_after_a_reset() {
        let p = drives::corpus::Corpus::Embedded.load("lmd").expect("lmd");
        for sep in [";", " "] {
            let mut k = settings_keeper();
            let mut drive = Settings::new(sep, false);
            k.take_snapshot(&mut drive).expect("snapshot");
            assert_eq!(
                drive.writes,
                ["S1=0,1,0", "OS=1,16,1", "OS=2,16,1"],
                "{sep:?}"
            );
            assert!(k.unrestorable(&setting_write("OS")).is_some(), "{sep:?}");
            assert_eq!(k.unrestorable(&reset()), None, "{sep:?}");
            let touched = k.touched(&reset());
            assert_eq!(touched.len(), 2, "{touched:?}");
            // The reset: every setting back to the factory's, then put back as found.
            drive
                .transact(&Request::WriteSingleRegister {
                    address: 0x3C,
                    value: 1,
                })
                .expect("reset");
            drive.writes.clear();
            k.after_case(&mut drive, "reset", &touched, &p)
                .expect("restore");
            assert_eq!(
                drive.os,
                ["1,16,1", "2,16,1"].join(sep),
                "{:?}",
                drive.writes
            );
            assert_eq!(drive.s1, "0, 1, 0");
            assert_eq!(drive.writes, ["S1=0,1,0", "OS=1,16,1", "OS=2,16,1"]);
            let a = k.finish(&mut drive, &p);
            assert!(a.clean(), "{a:?}");
        }
    }

    /// A drive with a parameter at 0x10 that stays as written and measured values at 0x20 (an encoder
    /// count that jitters by ±2 around what was written, read after read) and at 0x30 (still until
    /// `jitter_from` reads of it, then jittering); a write to 0x40 is acknowledged and not taken.
    struct Bench {
        regs: BTreeMap<u16, u16>,
        reads: BTreeMap<u16, usize>,
        jitter_from: usize,
        seed: u32,
    }

    impl Bench {
        fn new(jitter_from: usize) -> Self {
            Bench {
                regs: [(0x10, 7), (0x20, 100), (0x30, 200), (0x40, 5)].into(),
                reads: BTreeMap::new(),
                jitter_from,
                seed: 1,
            }
        }

        fn value(&mut self, a: u16) -> u16 {
            let n = self.reads.entry(a).or_default();
            *n += 1;
            let n = *n;
            let base = self.regs[&a];
            let jitters = a == 0x20 || (a == 0x30 && n > self.jitter_from);
            if !jitters {
                return base;
            }
            // A small deterministic walk: -2..=2 around the value.
            self.seed = self.seed.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            base.wrapping_add(((self.seed >> 16) % 5) as u16)
                .wrapping_sub(2)
        }
    }

    impl Link for Bench {
        fn blocks(&self, _kind: Block) -> bool {
            false
        }

        fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
            Ok(Some(match req {
                Request::ReadHoldingRegisters {
                    address,
                    quantity: 1,
                } => Response::ReadHoldingRegisters {
                    values: vec![self.value(*address)],
                },
                Request::WriteMultipleRegisters { address, values } => {
                    if *address != 0x40 {
                        self.regs.insert(*address, values[0]);
                    }
                    Response::WriteMultipleRegisters {
                        address: *address,
                        quantity: values.len() as u16,
                    }
                }
                _ => return Ok(None),
            }))
        }
    }

    fn bench_keeper() -> Keeper {
        Keeper::new(
            Inventory {
                items: [0x10, 0x20, 0x30, 0x40].map(|a| holding(a, 1)).to_vec(),
                ..Inventory::default()
            },
            "tcp://127.0.0.1:1".into(),
            "generic".into(),
            1,
            None,
        )
    }

    /// A measured value that reads otherwise with nothing written between (an encoder count on a drive with
    /// its motor attached) is neither put back nor verified: found so before the first write, or when a
    /// restore does not read back as before and more reads keep moving, within what they move by. A
    /// parameter whose write the drive does not take stays unrestored, and one a case moved far off is put
    /// back.
    #[test]
    fn a_value_that_changes_by_itself_is_neither_put_back_nor_verified() {
        let p = drives::corpus::Corpus::Embedded
            .load("generic")
            .expect("generic");
        let mut drive = Bench::new(usize::MAX);
        let mut k = bench_keeper();
        k.take_snapshot(&mut drive).expect("snapshot");
        let a = k.account();
        assert_eq!(a.kept, 3, "{a:?}");
        let live: Vec<&str> = a.live.iter().map(|u| u.key.as_str()).collect();
        assert_eq!(live, ["holding:32"], "{a:?}");
        assert!(a.lines().iter().any(|l| l.contains("change by themselves")));
        // A case moves 0x10 and 0x40; the restore puts 0x10 back, 0x40 does not take it.
        drive.regs.insert(0x10, 900);
        drive.regs.insert(0x40, 6);
        let a = k.finish(&mut drive, &p);
        let left: Vec<&str> = a.unrestored.iter().map(|u| u.key.as_str()).collect();
        assert_eq!(left, ["holding:64"], "{a:?}");
        assert_eq!(drive.regs[&0x10], 7);

        // 0x30 still while the snapshot reads it, jittering from then on: the final verification tells.
        let mut drive = Bench::new(LIVE_READS + 1);
        let mut k = bench_keeper();
        k.take_snapshot(&mut drive).expect("snapshot");
        assert_eq!(k.account().live.len(), 1, "{:?}", k.account());
        let a = k.finish(&mut drive, &p);
        let live: Vec<&str> = a.live.iter().map(|u| u.key.as_str()).collect();
        assert!(a.unrestored.iter().all(|u| u.key != "holding:48"), "{a:?}");
        assert_eq!(live, ["holding:32", "holding:48"], "{a:?}");
        // A value far off that keeps moving is not taken for jitter.
        assert_eq!(
            live_reads(
                &Value::Words(vec![7]),
                &[Value::Words(vec![900]), Value::Words(vec![901])]
            ),
            None
        );
        assert!(
            live_reads(
                &Value::Words(vec![100]),
                &[Value::Words(vec![101]), Value::Words(vec![99])]
            )
            .is_some()
        );
        // Reads that agree show nothing moving.
        assert_eq!(
            live_reads(
                &Value::Words(vec![100]),
                &[Value::Words(vec![101]), Value::Words(vec![101])]
            ),
            None
        );
    }

    /// A reset of every setting does not run where the run keeps some setting of the drive out (a motion
    /// setting without --allow-motion: the LMD's MS, IS): nothing would put it back. With every setting
    /// kept, it runs (and the keeper puts all back after it).
    #[test]
    fn a_reset_of_every_setting_does_not_run_where_a_setting_is_left_out() {
        let p = drives::corpus::Corpus::Embedded.load("lmd").expect("lmd");
        let reset_case = |safety: &Safety| {
            let mut k = Keeper::new(
                inventory(&p, safety),
                "tcp://127.0.0.1:1".into(),
                "lmd".into(),
                1,
                None,
            );
            k.snapshot = Some(BTreeMap::new());
            k.unrestorable(&reset())
        };
        let why = reset_case(&Safety {
            allow_destructive: true,
            ..Safety::default()
        })
        .expect("left out: the motion settings");
        assert!(why.contains("resets every setting"), "{why}");
        let all = Safety {
            allow_destructive: true,
            allow_motion: true,
            ..Safety::default()
        };
        assert_eq!(reset_case(&all), None);
    }

    #[test]
    fn motion_registers_are_kept_only_when_motion_is_allowed() {
        let p = drives::corpus::Corpus::Embedded
            .load("mdrive")
            .expect("mdrive");
        let safe = inventory(&p, &Safety::default());
        let motion: Vec<u16> = p
            .registers
            .iter()
            .map(|r| r.get_ref())
            .filter(|r| r.motion)
            .map(|r| r.address)
            .collect();
        assert!(!motion.is_empty());
        assert!(safe.items.iter().all(
            |i| !matches!(i.place, Place::Holding { address, .. } if motion.contains(&address))
        ));
        assert!(
            safe.items
                .iter()
                .any(|i| matches!(i.place, Place::Mnemonic { .. }))
        );
        let allowed = inventory(
            &p,
            &Safety {
                allow_motion: true,
                allow_destructive: true,
                ..Safety::default()
            },
        );
        assert!(allowed.items.len() > safe.items.len());
    }

    /// A coil or object whose write cannot be put back (an action, a counter reset) is not written back without
    /// --allow-destructive, as a destructive register or setting is not: writing its old value may do the
    /// action again.
    #[test]
    fn destructive_coils_and_objects_are_kept_only_when_destructive_writes_are_allowed() {
        let mut p = drives::corpus::Corpus::Embedded
            .load("generic")
            .expect("generic");
        p.coils[0].get_mut().destructive = true;
        let first = p.coils[0].get_ref().address;
        let kept = |inv: &Inventory| {
            inv.items
                .iter()
                .any(|i| matches!(i.place, Place::Coil { address } if address == first))
        };
        let safe = inventory(&p, &Safety::default());
        assert!(!kept(&safe), "kept without --allow-destructive");
        let why = safe
            .excluded
            .iter()
            .find(|e| e.key == format!("coil:{first}"));
        assert!(
            why.is_some_and(|e| e.reason.starts_with("destructive")),
            "{why:?}"
        );
        let allowed = Safety {
            allow_destructive: true,
            ..Safety::default()
        };
        assert!(kept(&inventory(&p, &allowed)));
        // The other coils are kept either way.
        assert!(
            safe.items
                .iter()
                .any(|i| matches!(i.place, Place::Coil { .. }))
        );
        // An object that mirrors no register, likewise (the SD2x's own read/write objects all mirror one or
        // move the motor: the first one, made a plain setting).
        let mut p = drives::corpus::Corpus::Embedded.load("sd2x").expect("sd2x");
        let (index, subindex) = {
            let o = p.objects[0].get_mut();
            (o.access, o.register, o.motion) = (drives::profile::Access::Rw, None, false);
            (o.index, o.subindex)
        };
        assert!(
            kept_object(&inventory(&p, &Safety::default()), index, subindex),
            "kept while not destructive"
        );
        p.objects[0].get_mut().destructive = true;
        assert!(!kept_object(
            &inventory(&p, &Safety::default()),
            index,
            subindex
        ));
        assert!(kept_object(&inventory(&p, &allowed), index, subindex));
    }

    fn kept_object(inv: &Inventory, index: u16, subindex: u8) -> bool {
        inv.items.iter().any(|i| {
            matches!(i.place, Place::Object { index: x, subindex: s, .. } if x == index && s == subindex)
        })
    }

    /// An MDrive axis left moving by an interrupted run: MV reads 1 until DE = 0 (SL 0 does not stop a point
    /// move), and P is refused with 04 while it moves. The restore stops it first (SL 0, then DE 0), then puts
    /// P and DE back; without the stop P could not be put back.
    struct Axis {
        regs: BTreeMap<u16, u16>,
        moving: bool,
        sent: Vec<Request>,
    }

    const MV: u16 = 0x004A;
    const DE: u16 = 0x001C;
    const P: u16 = 0x0057;

    impl Link for Axis {
        fn transact(&mut self, req: &Request) -> Result<Option<Response>, TargetError> {
            self.sent.push(req.clone());
            Ok(match req {
                Request::ReadHoldingRegisters { address, quantity } => (0..*quantity)
                    .map(|i| {
                        let a = address + i;
                        if a == MV {
                            Some(u16::from(self.moving))
                        } else {
                            self.regs.get(&a).copied()
                        }
                    })
                    .collect::<Option<Vec<u16>>>()
                    .map(|values| Response::ReadHoldingRegisters { values }),
                Request::WriteMultipleRegisters { address, values } => {
                    if self.moving && *address == P {
                        return Ok(Some(Response::exception(
                            FunctionCode::WRITE_MULTIPLE_REGISTERS,
                            codec::ExceptionCode::SERVER_DEVICE_FAILURE,
                        )));
                    }
                    for (a, v) in (*address..).zip(values) {
                        self.regs.insert(a, *v);
                    }
                    if *address == DE && values.first() == Some(&0) {
                        self.moving = false;
                    }
                    Some(Response::WriteMultipleRegisters {
                        address: *address,
                        quantity: values.len() as u16,
                    })
                }
                _ => None,
            })
        }
    }

    #[test]
    fn an_axis_left_moving_is_stopped_before_anything_is_put_back() {
        let profile = drives::corpus::Corpus::Embedded
            .profile("mdrive")
            .expect("mdrive profile");
        let safety = Safety {
            allow_motion: true,
            allow_destructive: true,
            ..Safety::default()
        };
        let inv = inventory(&profile, &safety);
        let items: Vec<Item> = inv
            .items
            .iter()
            .filter(|i| {
                i.key == format!("holding:0x{DE:04X}") || i.key == format!("holding:0x{P:04X}")
            })
            .cloned()
            .collect();
        assert_eq!(items.len(), 2, "DE and P are kept with motion allowed");
        let snapshot: BTreeMap<String, Value> = [
            (format!("holding:0x{DE:04X}"), Value::Words(vec![1])),
            (format!("holding:0x{P:04X}"), Value::Words(vec![0, 0])),
        ]
        .into();
        let moving = || Axis {
            regs: [(DE, 1), (P, 0x0001), (P + 1, 0x2345)].into(),
            moving: true,
            sent: Vec::new(),
        };
        let mut axis = moving();
        let (_, left) = restore(&mut axis, &items, &snapshot, Some(&profile)).expect("restore");
        assert!(left.is_empty(), "{left:?}");
        assert!(!axis.moving);
        assert_eq!(axis.regs[&DE], 1, "DE put back after the stop");
        assert_eq!((axis.regs[&P], axis.regs[&(P + 1)]), (0, 0));
        // Without the profile (no stop): P stays refused.
        let mut axis = moving();
        let (_, left) = restore(&mut axis, &items, &snapshot, None).expect("restore");
        assert!(
            left.iter().any(|u| u.key == format!("holding:0x{P:04X}")),
            "{left:?}"
        );
    }
}
