//! The choices a drive makes where the specifications and its manual leave one (the freedoms of
//! `corpus/freedoms/`, loaded by [`crate::requirements`]).
//!
//! The reference models take the choices as parameters (`simulate --choose FREEDOM=VALUE`), and every answer
//! they give where a freedom decided it carries the freedom's id as a [`Decision`]: the oracle then knows
//! that any admissible value of that freedom would have been as good an answer, for a catalog case, a
//! generated case or a fuzz input alike.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use codec::ExceptionCode;

use crate::profile::Profile;
use crate::requirements::{Freedom, FreedomKind, FreedomValue, Requirements};

/// Freedom ids the models decide at (each is a `[[freedom]]` id in `corpus/freedoms/`; a test checks it).
pub mod ids {
    /// The exception code for a value outside the register's range: 03 or 04.
    pub const VALUE_OUT_OF_RANGE: &str = "value-out-of-range";
    /// The exception code for a write to a read-only register or object: 02, 03 or 04.
    pub const WRITE_READ_ONLY: &str = "write-read-only-exception";
    pub const READ_WRITE_ONLY: &str = "read-write-only-exception";
    /// A quantity above the device's limit but within the spec's: 03, or 02 when the range runs past the map.
    pub const QUANTITY_OVER_DEVICE_LIMIT: &str = "quantity-over-device-limit";
    /// A read that starts or ends inside a 32-bit register: served, or 02/03/04.
    pub const PARTIAL_REGISTER_READ: &str = "partial-register-read";
    /// A write that covers half of a 32-bit register: 02, 03, 04, or accepted.
    pub const PARTIAL_REGISTER_WRITE: &str = "partial-register-write";
    /// A register read or write covering several items of the map (MDrive, LMD): served, or 02/03/04.
    pub const MULTI_ITEM_ACCESS: &str = "multi-item-access";
    /// A function code the profile does not list: 01, or served.
    pub const SERVED_EXTRA_FUNCTION: &str = "served-extra-function";
    /// FC 0x41/0x42 with a mnemonic the drive does not know.
    pub const UNKNOWN_MNEMONIC: &str = "unknown-mnemonic-exception";
    /// FC 0x41 of a write-only or FC 0x42 of a read-only mnemonic.
    pub const MNEMONIC_ACCESS: &str = "mnemonic-access-exception";
    /// FC 0x42 with parameters the mnemonic does not take.
    pub const MNEMONIC_BAD_PARAMETER: &str = "mnemonic-bad-parameter-exception";
    /// SD2x FC 43: the SDO abort code of a read or write whose length does not fit the object.
    pub const SDO_LENGTH_ERROR: &str = "sd2x-sdo-length-error";
    /// FC 0x42 response field "bytes written": the 4 mnemonic characters, or the parameter bytes.
    pub const FC42_BYTES_WRITTEN: &str = "fc42-bytes-written";
    /// FC 11's run indicator: ON or OFF.
    pub const RUN_INDICATOR_STATUS: &str = "run-indicator-status";
    /// FC 0B after 08/0A: whether the clearing request counted as a completion.
    pub const EVENT_COUNTER_CLEAR_COUNTED: &str = "event-counter-clear-counted";
    /// What the FC 08 bus message, slave message and no-response counters count.
    pub const DIAGNOSTIC_COUNTER_SEMANTICS: &str = "diagnostic-counter-semantics";

    /// FC 0x41 response byte count: one byte (the examples) or two (the tables).
    pub const FC41_BYTE_COUNT_WIDTH: &str = "fc41-byte-count-width";
    /// FC 0x41 response parameter string: the values separated by ", ", or as written ("=0,1,0").
    pub const FC41_READ_BACK_FORMAT: &str = "fc41-read-back-format";
    /// FC 0x41 read of a setting whose write format has fewer values than its read example (the MDrive's
    /// TR): the example's count, or the format's.
    pub const FC41_READ_BACK_FIELDS: &str = "fc41-read-back-fields";
    /// The LMD's S1-S4 read back with the example's three values, or the two an LMD input setting has.
    pub const LMD_INPUT_SETUP_FIELDS: &str = "lmd-input-setup-fields";
    /// A parameterless FC 0x42 command (E, PS, RS, CP, ESC): byte count 0, or no byte count at all.
    pub const FC42_PARAMETERLESS_BYTE_COUNT: &str = "fc42-parameterless-byte-count";
    /// The LMD's ESC on the wire: 20 20 20 1B (the reversal rule) or 20 20 1B 20 (as printed).
    pub const LMD_ESC_WIRE_FORM: &str = "lmd-esc-wire-form";
    /// The MDrive's E, EX, PS, RS: FC 0x42 (Table 4.1) or FC 0x41 (their sections).
    pub const MDRIVE_PROGRAM_CONTROL_FUNCTION: &str = "mdrive-program-control-function";
    /// A PDU too short for its function code: exception 03, silence, or (Modbus/TCP) a close.
    pub const TRUNCATED_PDU: &str = "truncated-pdu";
    /// RTU, a frame not as long as its function code's length rules make it: the reference's answer, or
    /// silence (the frame sized by those rules fails its CRC, or waits for bytes that never come).
    pub const RTU_LENGTH_FRAMING: &str = "rtu-length-framing";
    /// Both the quantity and the address (range) wrong: 03 (quantity checked first) or 02 (address first).
    pub const EXCEPTION_CHECK_ORDER: &str = "exception-check-order";
    /// A quantity above the manual's limit but within the specification's: refused (03 or 02, the code is
    /// `quantity-over-device-limit`'s), or served by a drive whose limit is higher than its manual says.
    pub const QUANTITY_OVER_DEVICE_LIMIT_SERVED: &str = "quantity-over-device-limit-served";
    /// A write of a value inside a register's widest range that is none of the values every reading of its
    /// manual takes (`safe_values`): taken, or refused with 03.
    pub const VALUE_MEANING_OPEN: &str = "value-meaning-open";
    /// A PDU longer than its function's layout (the frame intact): 03, silence, a close, or the request
    /// the layout's bytes make served and the rest ignored.
    pub const TRAILING_BYTES: &str = "trailing-bytes";
    /// FC 43 with an MEI type the drive does not serve: exception 01, 02 or 03.
    pub const UNSUPPORTED_MEI_TYPE: &str = "unsupported-mei-type";
    /// A request whose function code is 128-255, the codes of exception responses: 01, silence or a close.
    pub const REQUEST_FC_OVER_127: &str = "request-fc-over-127";
    /// A request whose function code is 0, not valid (App 4.1): 01, silence, or a close.
    pub const REQUEST_FC_ZERO: &str = "request-fc-zero";
    /// Modbus/TCP, a unit id in the freedom's `units` that is not the station's own (nor 0, 0xFF):
    /// answered or ignored.
    pub const TCP_UNIT_IDS: &str = "tcp-unit-ids";
    /// Modbus/TCP to a drive without Modbus/TCP (a gateway between), a well-formed request the drive leaves
    /// unanswered: silence, or the gateway's exception 0B or 0A.
    pub const GATEWAY_NO_RESPONSE: &str = "gateway-no-response";
    /// Modbus/TCP, several requests received together: answered in request order or in another order.
    pub const PIPELINED_RESPONSE_ORDER: &str = "pipelined-response-order";
    /// Modbus/TCP, a request received while another is served: served, or exception 06 (one transaction).
    pub const PIPELINED_SERVER_BUSY: &str = "pipelined-server-busy";
    /// Modbus/TCP, an MBAP length shorter than the function's layout: 03, silence or a close.
    pub const MBAP_LENGTH_SHORT: &str = "mbap-length-short";
    /// Modbus/TCP, an MBAP length longer than the function's layout: wait (silence), close, or 03.
    pub const MBAP_LENGTH_LONG: &str = "mbap-length-long";
    /// Modbus/TCP, an MBAP length announcing a PDU over 253 bytes: close, silence or 03.
    pub const PDU_OVER_253: &str = "pdu-over-253";
    /// The MDrive, a write to the output of an I/O point configured as an input: taken, or 04/03/02.
    pub const MDRIVE_OUTPUT_WRITE_WHILE_INPUT: &str = "mdrive-output-write-while-input";
    pub const MDRIVE_ENCODER_ABSENT: &str = "mdrive-encoder-absent";
    /// The MDrive and the LMD, PM switched on while EE (encoder functions) is off: taken, or 04/03.
    pub const POSITION_MAINTENANCE_WITHOUT_ENCODER: &str = "position-maintenance-without-encoder";
    /// The MDrive, a read of the output of an I/O point configured as an input: served, or 02/04.
    pub const MDRIVE_OUTPUT_READ_WHILE_INPUT: &str = "mdrive-output-read-while-input";
    /// The MDrive, a write of the outputs as a group (OT, OL) while a point is an input: taken, or 04/03/02.
    pub const MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT: &str = "mdrive-output-group-write-while-input";
    /// The LMD, a write of output 4 (coil 0x0003), which no output setup line reaches: taken, or 04/03/02.
    pub const LMD_OUTPUT_4_WRITE: &str = "lmd-output-4-write";
    /// FC 0x41/0x42 naming a known mnemonic padded with NUL where the manuals print spaces: refused as
    /// unknown, or served as the mnemonic it pads.
    pub const MNEMONIC_PADDING: &str = "mnemonic-padding";
    /// FC 0x41/0x42 naming a known mnemonic in lower or mixed case: served, or refused as unknown.
    pub const MNEMONIC_LETTER_CASE: &str = "mnemonic-letter-case";
    /// FC 0x42 of a setting whose parameter string lacks the leading '=': refused as a bad parameter, or
    /// taken as if it had it.
    pub const SETTING_EQUALS_SIGN: &str = "setting-equals-sign";
    /// FC 0x42 whose parameter string holds a control character a text parser reads as a blank (a tab):
    /// refused as a bad parameter, or read with a space for it.
    pub const PARAMETER_BLANK_CONTROLS: &str = "parameter-blank-controls";
    /// SD2x FC 43, a read with byte count 0: the length error, the object at its size, or no data.
    pub const SD2X_FC43_READ_ZERO_COUNT: &str = "sd2x-fc43-read-zero-count";
    /// SD2x FC 43, a byte count above 4: the SDO length error or exception 03.
    pub const SD2X_FC43_BYTE_COUNT_OVER_4: &str = "sd2x-fc43-byte-count-over-4";
    /// SD2x FC 43 with control code bits 0-6 not zero ("set to zero"): the SDO error 0003, or exception 03.
    pub const SD2X_FC43_CONTROL_BITS: &str = "sd2x-fc43-control-bits";
    /// SD2x FC 43 with a reserved field not zero: ignored, or exception 03.
    pub const SD2X_FC43_RESERVED_NONZERO: &str = "sd2x-fc43-reserved-nonzero";
    /// SD2x FC 43 with an address offset not zero ("set to zero"): the SDO error 0008, or exception 03.
    pub const SD2X_FC43_OFFSET_NONZERO: &str = "sd2x-fc43-offset-nonzero";
    /// SD2x FC 43 whose node-ID is not the slave address: exception 02 or 03.
    pub const SD2X_FC43_NODE_ID: &str = "sd2x-fc43-node-id";
    /// SD2x FC 08 with an unlisted sub-function and a data field other than 2 bytes, at a drive refusing
    /// other sizes with 03: 03 (the size checked first) or 01 (the sub-function first, as in 6.8's diagram).
    pub const SD2X_DIAGNOSTIC_CHECK_ORDER: &str = "sd2x-diagnostic-check-order";
    /// SD2x FC 08/0A-0F with a non-zero data field: ignored, or exception 03.
    pub const SD2X_DIAGNOSTIC_UNUSED_DATA: &str = "sd2x-diagnostic-unused-data";
    /// SD2x FC 08/00 with a data field other than 2 bytes: echoed, exception 03, or silence.
    pub const SD2X_DIAGNOSTIC_DATA_SIZE: &str = "sd2x-diagnostic-data-size";
    /// SD2x FC 43 SDO error code: little-endian (the reference), or in the order the code is printed.
    pub const SD2X_SDO_ERROR_BYTE_ORDER: &str = "sd2x-sdo-error-byte-order";
    /// After S (NVM save), CP or UG: every request, or the writes, answered Server Busy (06) for 400 ms.
    /// Taken by the station (see `MODELLED`); no answer is a decision of it: the runner asks again, and
    /// decides it where it cannot (a request of a batch refused 06 soon after an NVM save).
    pub const BUSY_AFTER_LONG_COMMAND: &str = "busy-after-long-command";

    /// Every id above.
    pub const ALL: &[&str] = &[
        VALUE_OUT_OF_RANGE,
        WRITE_READ_ONLY,
        READ_WRITE_ONLY,
        QUANTITY_OVER_DEVICE_LIMIT,
        PARTIAL_REGISTER_READ,
        PARTIAL_REGISTER_WRITE,
        MULTI_ITEM_ACCESS,
        SERVED_EXTRA_FUNCTION,
        UNKNOWN_MNEMONIC,
        MNEMONIC_ACCESS,
        MNEMONIC_BAD_PARAMETER,
        SDO_LENGTH_ERROR,
        FC42_BYTES_WRITTEN,
        DIAGNOSTIC_COUNTER_SEMANTICS,
        RUN_INDICATOR_STATUS,
        EVENT_COUNTER_CLEAR_COUNTED,
        FC41_BYTE_COUNT_WIDTH,
        FC41_READ_BACK_FORMAT,
        FC41_READ_BACK_FIELDS,
        LMD_INPUT_SETUP_FIELDS,
        FC42_PARAMETERLESS_BYTE_COUNT,
        LMD_ESC_WIRE_FORM,
        MDRIVE_PROGRAM_CONTROL_FUNCTION,
        TRUNCATED_PDU,
        RTU_LENGTH_FRAMING,
        TRAILING_BYTES,
        QUANTITY_OVER_DEVICE_LIMIT_SERVED,
        VALUE_MEANING_OPEN,
        REQUEST_FC_OVER_127,
        REQUEST_FC_ZERO,
        UNSUPPORTED_MEI_TYPE,
        EXCEPTION_CHECK_ORDER,
        TCP_UNIT_IDS,
        GATEWAY_NO_RESPONSE,
        PIPELINED_RESPONSE_ORDER,
        PIPELINED_SERVER_BUSY,
        MBAP_LENGTH_SHORT,
        MBAP_LENGTH_LONG,
        PDU_OVER_253,
        MDRIVE_OUTPUT_WRITE_WHILE_INPUT,
        MDRIVE_ENCODER_ABSENT,
        POSITION_MAINTENANCE_WITHOUT_ENCODER,
        MDRIVE_OUTPUT_READ_WHILE_INPUT,
        MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT,
        LMD_OUTPUT_4_WRITE,
        MNEMONIC_LETTER_CASE,
        MNEMONIC_PADDING,
        SETTING_EQUALS_SIGN,
        PARAMETER_BLANK_CONTROLS,
        SD2X_FC43_READ_ZERO_COUNT,
        SD2X_FC43_BYTE_COUNT_OVER_4,
        SD2X_FC43_CONTROL_BITS,
        SD2X_FC43_RESERVED_NONZERO,
        SD2X_FC43_OFFSET_NONZERO,
        SD2X_FC43_NODE_ID,
        SD2X_DIAGNOSTIC_CHECK_ORDER,
        SD2X_DIAGNOSTIC_UNUSED_DATA,
        SD2X_DIAGNOSTIC_DATA_SIZE,
        SD2X_SDO_ERROR_BYTE_ORDER,
    ];
}

/// A place where a freedom decided an answer (the drive took its chosen value there).
pub type Decision = &'static str;

/// A refused request: the exception code, and the freedom that decided the code, if one did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rejection {
    pub code: ExceptionCode,
    pub freedom: Option<Decision>,
}

impl Rejection {
    /// A refusal the specs fix (no freedom).
    pub fn fixed(code: ExceptionCode) -> Self {
        Self {
            code,
            freedom: None,
        }
    }

    /// A refusal whose code the freedom `freedom` decided.
    pub fn by(freedom: Decision, code: ExceptionCode) -> Self {
        Self {
            code,
            freedom: Some(freedom),
        }
    }
}

impl From<ExceptionCode> for Rejection {
    fn from(code: ExceptionCode) -> Self {
        Self::fixed(code)
    }
}

/// Why a choice was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChoiceError {
    #[error("`{0}`: a choice is FREEDOM=VALUE")]
    Syntax(String),
    #[error("no freedom `{id}`; freedoms of this profile: {}", known.join(", "))]
    UnknownFreedom { id: String, known: Vec<String> },
    #[error("freedom `{id}` does not apply to profile `{profile}` (it applies to {})", applies.join(", "))]
    NotForProfile {
        id: String,
        profile: String,
        applies: Vec<String>,
    },
    #[error("the reference drives cannot take `{id}={value}` yet (a simulator choice must change what the drive answers); simulated: {}", simulated.join(", "))]
    NotSimulated {
        id: String,
        value: String,
        simulated: Vec<String>,
    },
    #[error("`{value}` is not an admissible value of `{id}`; admissible: {}", admissible.join(", "))]
    NotAdmissible {
        id: String,
        value: String,
        admissible: Vec<String>,
    },
}

/// The values a drive takes for freedoms; a freedom not set takes the reference's value (its first).
///
/// A choice made with [`Choices::choose`] keeps the freedom's definition too, so that a model can act on its
/// items (the registers and mnemonics a product lacks, the access it gives them).
#[derive(Clone, Debug, Default)]
pub struct Choices {
    values: BTreeMap<String, FreedomValue>,
    defs: BTreeMap<String, Arc<Freedom>>,
}

impl PartialEq for Choices {
    fn eq(&self, other: &Self) -> bool {
        self.values == other.values
    }
}

impl Eq for Choices {}

impl Choices {
    /// The reference drive's choices: every freedom at its first value.
    pub fn reference() -> Self {
        Self::default()
    }

    /// True when nothing departs from the reference.
    pub fn is_reference(&self) -> bool {
        self.values.is_empty()
    }

    /// Parse `FREEDOM=VALUE` and check it against the freedoms of `profile`.
    pub fn parse_one(
        spec: &str,
        requirements: &Requirements,
        profile: &Profile,
    ) -> Result<(String, FreedomValue), ChoiceError> {
        let (device, profile) = (profile, profile.device.id.as_str());
        let (id, value) = spec
            .split_once('=')
            .ok_or_else(|| ChoiceError::Syntax(spec.to_string()))?;
        let (id, value) = (id.trim(), value.trim());
        let known = || {
            requirements
                .freedoms_for(profile)
                .map(|f| f.id.clone())
                .collect::<Vec<_>>()
        };
        let f = requirements
            .freedom(id)
            .ok_or_else(|| ChoiceError::UnknownFreedom {
                id: id.to_string(),
                known: known(),
            })?;
        if !f.applies_to(profile) {
            return Err(ChoiceError::NotForProfile {
                id: id.to_string(),
                profile: profile.to_string(),
                applies: f.profiles.clone(),
            });
        }
        let chosen = f
            .values
            .iter()
            .find(|v| v.matches(value))
            .cloned()
            .ok_or_else(|| ChoiceError::NotAdmissible {
                id: id.to_string(),
                value: value.to_string(),
                admissible: f.values.iter().map(|v| v.to_string()).collect(),
            })?;
        if !simulated_on(f, &chosen, device) {
            return Err(ChoiceError::NotSimulated {
                id: id.to_string(),
                value: chosen.to_string(),
                simulated: requirements
                    .freedoms_for(profile)
                    .flat_map(|f| {
                        f.values
                            .iter()
                            .skip(1)
                            .filter(|v| simulated_on(f, v, device))
                            .map(|v| format!("{}={v}", f.id))
                            .collect::<Vec<_>>()
                    })
                    .collect(),
            });
        }
        Ok((id.to_string(), chosen))
    }

    /// Parse every `FREEDOM=VALUE` of `specs` for `profile` (see [`Choices::parse_one`]) into choices that
    /// keep each freedom's definition.
    pub fn parse_all<S: AsRef<str>>(
        specs: &[S],
        requirements: &Requirements,
        profile: &Profile,
    ) -> Result<Self, ChoiceError> {
        let mut choices = Self::reference();
        for spec in specs {
            let (id, value) = Self::parse_one(spec.as_ref(), requirements, profile)?;
            match requirements.freedom(&id) {
                Some(f) => choices.choose(f, value),
                None => choices.set(id, value),
            }
        }
        Ok(choices)
    }

    /// Set `freedom` to `value` (the value the data lists, see [`Choices::parse_one`]).
    pub fn set(&mut self, freedom: impl Into<String>, value: FreedomValue) {
        self.values.insert(freedom.into(), value);
    }

    /// Set `freedom` to `value`, keeping its definition for the models (items, register).
    pub fn choose(&mut self, freedom: &Freedom, value: FreedomValue) {
        self.values.insert(freedom.id.clone(), value);
        self.defs
            .insert(freedom.id.clone(), Arc::new(freedom.clone()));
    }

    /// The choices made with their definitions: (freedom, value chosen).
    pub fn defined(&self) -> impl Iterator<Item = (&Freedom, &FreedomValue)> {
        self.defs
            .iter()
            .filter_map(|(id, f)| Some((f.as_ref(), self.values.get(id)?)))
    }

    /// The choices made of `kind`, with their definitions.
    pub fn defined_of(&self, kind: FreedomKind) -> impl Iterator<Item = (&Freedom, &FreedomValue)> {
        self.defined().filter(move |(f, _)| f.kind == kind)
    }

    /// The exception code a named value `exception-XX` stands for.
    pub fn exception_value(value: &FreedomValue) -> Option<ExceptionCode> {
        match value {
            FreedomValue::Text(t) => t
                .strip_prefix("exception-")
                .and_then(|h| u8::from_str_radix(h, 16).ok())
                .map(ExceptionCode),
            FreedomValue::Int(_) => None,
        }
    }

    /// The value set for `freedom`, if any.
    pub fn get(&self, freedom: &str) -> Option<&FreedomValue> {
        self.values.get(freedom)
    }

    /// The exception code chosen for an `exception-code` freedom (or an `outcome` one chosen
    /// `exception-XX`), else `reference`.
    pub fn code(&self, freedom: &str, reference: ExceptionCode) -> ExceptionCode {
        match self.values.get(freedom) {
            Some(FreedomValue::Int(c)) => u8::try_from(*c).map_or(reference, ExceptionCode),
            Some(v) => Self::exception_value(v).unwrap_or(reference),
            None => reference,
        }
    }

    /// A refusal under an `exception-code` freedom: the chosen code, decided by the freedom.
    pub fn reject(&self, freedom: Decision, reference: ExceptionCode) -> Rejection {
        Rejection::by(freedom, self.code(freedom, reference))
    }

    /// The name chosen for a freedom with named values, else `None` (the reference's).
    pub fn name(&self, freedom: &str) -> Option<&str> {
        match self.values.get(freedom) {
            Some(FreedomValue::Text(t)) => Some(t),
            _ => None,
        }
    }

    /// Every choice set.
    pub fn iter(&self) -> impl Iterator<Item = (&String, &FreedomValue)> {
        self.values.iter()
    }
}

/// A drive model's side of the freedoms: the choices it takes where they leave one, and the freedoms that
/// decided the answer being given (drained per request). Every model keeps one; [`crate::DriveModel`]'s
/// `adopt` and `take_decisions` act on it.
#[derive(Clone, Debug)]
pub struct Freedoms {
    choices: Choices,
    decisions: Vec<Decision>,
    alternatives: Vec<ModelledAlternative>,
}

/// What the model would have answered had it taken another value of a freedom that decided its answer:
/// (the freedom, the value, the answer). Where the answer under another value depends on the drive's state
/// and the rest of the request (a field left alone, the telegram then checked on), the oracle cannot
/// derive it from the reference's answer; the model computes it on a copy of itself.
pub type ModelledAlternative = (Decision, &'static str, codec::Response);

impl Freedoms {
    /// Taking `choices`, with nothing decided yet.
    pub fn new(choices: Choices) -> Self {
        Self {
            choices,
            decisions: Vec::new(),
            alternatives: Vec::new(),
        }
    }

    /// The choices taken.
    pub fn choices(&self) -> &Choices {
        &self.choices
    }

    /// Take `choices` from now on (see [`crate::DriveModel::adopt`]).
    pub fn adopt(&mut self, choices: &Choices) {
        self.choices = choices.clone();
    }

    /// Note that `freedom` decided the answer being given.
    pub fn decided(&mut self, freedom: Decision) {
        self.decisions.push(freedom);
    }

    /// The freedoms that decided answers since the last call.
    pub fn take_decisions(&mut self) -> Vec<Decision> {
        std::mem::take(&mut self.decisions)
    }

    /// Note that under `value` of `freedom` the answer being given would have been `answer`.
    pub fn alternative(&mut self, freedom: Decision, value: &'static str, answer: codec::Response) {
        self.alternatives.push((freedom, value, answer));
    }

    /// The answers other values would have given since the last call ([`Freedoms::alternative`]).
    pub fn take_alternatives(&mut self) -> Vec<ModelledAlternative> {
        std::mem::take(&mut self.alternatives)
    }
}

impl fmt::Display for Choices {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.values.is_empty() {
            return f.write_str("reference");
        }
        let parts: Vec<String> = self
            .values
            .iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        f.write_str(&parts.join(" "))
    }
}

/// True when the reference drive models can take `value` for `f` (`simulate --choose`, `run --choose`): the
/// items of optional groups and their access, the word order, functions served beyond the profile, reads
/// inside or half of a 32-bit register, and every freedom the models or the station decide at (see [`ids`]:
/// the exception codes, the SDO length error, the answer to a truncated PDU, the exception check order, the
/// Modbus/TCP transport outcomes (unit ids, pipelining order and Server Busy, MBAP lengths, PDUs over 253
/// bytes), the FC 0x41/0x42 fields and readings of the MDrive/LMD manuals, the FC 08 counters, the FC 11 run
/// indicator, the FC 0B count of a clear) and those in `MODELLED` (the SD2x status-word bits, watchdog and
/// FC 43 form, the LMD's discrete-input addressing). The reference's own value always is. See also [`simulated_on`]: a
/// `close` needs a connection.
///
pub fn simulated(f: &Freedom, value: &FreedomValue) -> bool {
    if f.values.first() == Some(value) {
        return true;
    }
    match f.kind {
        FreedomKind::Optional | FreedomKind::Access | FreedomKind::WordOrder => true,
        FreedomKind::ServedExtra => value.matches("served"),
        _ if MODELLED.contains(&f.id.as_str()) => true,
        _ => ids::ALL.contains(&f.id.as_str()),
    }
}

/// Freedoms whose every value the models take although no answer of theirs is a [`Decision`] of it (the
/// oracle applies them where a case cites them or a read touches their register).
const MODELLED: &[&str] = &[
    "sd2x-status-word-bits",
    "sd2x-watchdog-error-code",
    "sd2x-watchdog-trip-state",
    "sd2x-fc43-reserved-byte",
    "lmd-discrete-input-addressing",
    ids::BUSY_AFTER_LONG_COMMAND,
];

/// [`simulated`] for a drive of `profile`: a drive that speaks no Modbus/TCP has no connection to close, so
/// an outcome `close` is not a choice it can make (on an RTU line a station chosen `close` keeps silent).
pub fn simulated_on(f: &Freedom, value: &FreedomValue, profile: &Profile) -> bool {
    let tcp = profile.speaks_tcp();
    simulated(f, value) && (tcp || !value.matches("close"))
}

/// The freedoms of `kind` that apply to `profile`.
pub fn of_kind<'a>(
    requirements: &'a Requirements,
    profile: &'a str,
    kind: FreedomKind,
) -> impl Iterator<Item = &'a Freedom> {
    requirements
        .freedoms_for(profile)
        .filter(move |f| f.kind == kind)
}
