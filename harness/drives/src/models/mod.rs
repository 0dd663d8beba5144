//! Reference drive models and the wire-level station around them. Sans-IO: time is passed in.
//!
//! A `DriveModel` answers typed requests and evolves on a virtual clock; the `Station` owns the wire:
//! Modbus/TCP stream splitting and MBAP checks, RTU addressing, broadcast, the serial-line counters of
//! FC 08, and the injected faults that act on bytes.

pub mod bank;
pub mod data_model;
pub mod generic;
pub mod mdrive;
pub mod sd2x;

use std::time::Duration;

use crate::profile::Profile;
use codec::{Request, Response};

use crate::choices::{Choices, Decision, Freedoms};
use crate::faults::FaultSet;

/// An executable model of a drive: what a conforming drive answers, and its state over time.
pub trait DriveModel: Send + BoxClone {
    /// The profile the model was built from.
    fn profile(&self) -> &Profile;

    /// Move internal state (motion, watchdog, actual speed) forward to `now`. Time never goes back.
    fn advance(&mut self, now: Duration);

    /// Answer a request addressed to this drive as unit `unit` at `now` (after `advance(now)`).
    /// `None` means the drive stays silent. Broadcasts are handled too; the station drops their answer.
    fn handle(&mut self, now: Duration, unit: u8, request: &Request) -> Option<Response>;

    /// The choices the model takes and the freedoms that decided its answers (see [`crate::choices`]).
    fn freedoms(&mut self) -> &mut Freedoms;

    /// The freedoms that decided the answers since the last call (see [`crate::choices`]).
    fn take_decisions(&mut self) -> Vec<Decision> {
        self.freedoms().take_decisions()
    }

    /// The answers other values of the deciding freedoms would have given since the last call (see
    /// [`crate::choices::Freedoms::alternative`]).
    fn take_alternatives(&mut self) -> Vec<crate::choices::ModelledAlternative> {
        self.freedoms().take_alternatives()
    }

    /// Take `choices` from now on where they act at run time (a refusal or an answer where a freedom
    /// leaves the choice), keeping the state. An oracle's reference drive follows what the drive under
    /// test showed it chose, so that the two keep the same state (a half of a 32-bit register the drive
    /// took is taken by the reference too). Choices that shape the model (access, word order, addressing)
    /// are fixed when it is built and stay as they are.
    fn adopt(&mut self, choices: &Choices) {
        self.freedoms().adopt(choices);
    }
}

/// A copy of a model in its present state, which then evolves on its own: every model that is `Clone` has
/// it. Cheap: the profile and the register map are shared, only the state is copied (the in-process fuzz
/// targets clone a pristine model per input instead of building one).
pub trait BoxClone {
    fn box_clone(&self) -> Box<dyn DriveModel>;
}

impl<T: DriveModel + Clone + 'static> BoxClone for T {
    fn box_clone(&self) -> Box<dyn DriveModel> {
        Box::new(self.clone())
    }
}

impl Clone for Box<dyn DriveModel> {
    fn clone(&self) -> Self {
        self.box_clone()
    }
}

/// Build the reference model a profile describes: sd2x, mdrive and lmd have their own models, anything
/// else is generic.
pub fn build(profile: Profile, faults: FaultSet) -> Box<dyn DriveModel> {
    build_with(profile, faults, Choices::reference())
}

/// Build the model a profile describes, taking `choices` where the freedoms leave one.
pub fn build_with(profile: Profile, faults: FaultSet, choices: Choices) -> Box<dyn DriveModel> {
    let profile = shaped(profile, &choices);
    match profile.device.id.as_str() {
        "sd2x" => Box::new(sd2x::Sd2x::new(profile, faults, choices)),
        "mdrive" | "lmd" => Box::new(mdrive::Mdrive::new(profile, faults, choices)),
        _ => Box::new(generic::Generic::new(profile, faults, choices)),
    }
}

/// The LMD's discrete-input addressing (`corpus/freedoms/lmd.toml`).
const DISCRETE_INPUT_ADDRESSING: &str = "lmd-discrete-input-addressing";

/// The profile as a drive that made `choices` has it: the access it gives the items of the `access`
/// freedoms, the word order of a `word-order` freedom, the discrete inputs' addresses of the LMD's reading. (Optional items a product lacks are refused by the
/// station, see [`crate::station`]; the other freedoms act inside the models.)
pub fn shaped(mut profile: Profile, choices: &Choices) -> Profile {
    use crate::profile::{Access, WordOrder};
    use crate::requirements::{FreedomKind, FreedomValue};
    for (f, value) in choices.defined_of(FreedomKind::Access) {
        let access = match value {
            FreedomValue::Text(t) if t == "ro" => Access::Ro,
            FreedomValue::Text(t) if t == "rw" => Access::Rw,
            FreedomValue::Text(t) if t == "wo" => Access::Wo,
            _ => continue,
        };
        for item in &f.items {
            if let Some(address) = item.register {
                for r in &mut profile.registers {
                    if r.get_ref().address == address {
                        r.get_mut().access = access;
                    }
                }
            }
            if let Some(name) = &item.mnemonic {
                for m in &mut profile.mnemonics {
                    let m = m.get_mut();
                    if m.name.eq_ignore_ascii_case(name) {
                        m.read = access.readable();
                        m.write = access.writable();
                    }
                }
            }
        }
    }
    if choices.name(DISCRETE_INPUT_ADDRESSING) == Some("inputs-at-0x002D") {
        // The LMD's FC 02 example reads inputs 1-4 from 0x002D (001 line 763), the table from 0x0000.
        for b in &mut profile.discrete_inputs {
            let b = b.get_mut();
            b.address = b.address.wrapping_add(0x002D);
        }
    }
    for (_, value) in choices.defined_of(FreedomKind::WordOrder) {
        match value {
            FreedomValue::Text(t) if t == "high-first" => {
                profile.device.word_order = WordOrder::HighFirst;
            }
            FreedomValue::Text(t) if t == "low-first" => {
                profile.device.word_order = WordOrder::LowFirst;
            }
            _ => {}
        }
    }
    profile
}
