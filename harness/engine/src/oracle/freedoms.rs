//! Judging by the requirements, not by the reference drive's choices.
//!
//! Where a specification or a manual leaves a choice (a freedom of `corpus/freedoms/`), the reference drive
//! answers one admissible way. A step's observation that differs from it passes when it is the answer some
//! other admissible value of an applicable freedom gives: the oracle builds that alternative answer and judges
//! the observation against it with the same strictness (echoes, framing, structure). Every freedom a drive
//! showed a value for is recorded ([`Shown`]), so that the run can hold the drive to its choice and the
//! report can say which choices it made.
//!
//! A freedom applies to a step when the reference drive decided its answer there (a [`drives::Decision`]),
//! when the case cites it (`corpus/requirements/cases.toml`), or when the request touches what the freedom is
//! about (an optional register, a status word, a unit id); always only for the profiles it lists.

use codec::{ExceptionCode, FunctionCode, Request, Response};
use drives::requirements::{Freedom, FreedomKind, FreedomValue, Item, Requirements};
use drives::requirements::{covers, registers_read, registers_written};

/// A value a drive showed for a freedom, at one step.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Shown {
    /// The freedom's id.
    pub freedom: String,
    /// What the choice is about within the freedom (an item of an optional group), empty for the whole freedom.
    pub about: String,
    /// The value shown, as the freedom's data names it.
    pub value: String,
    /// True when it is the reference drive's own value.
    pub reference: bool,
}

/// What the oracle needs to know about a step to apply freedoms.
pub struct StepContext<'a> {
    /// The request as sent (decoded, when it decodes).
    pub request: Option<&'a Request>,
    /// The request's PDU as sent (what a drive reading the manual another way may decode otherwise).
    pub pdu: &'a [u8],
    /// The unit id / slave address the request went to.
    pub unit: u8,
    /// The unit id / slave address the run talks to: requests to it must be answered.
    pub run_unit: u8,
    /// The run's profile.
    pub profile: &'a drives::profile::Profile,
    /// The request was sent malformed on purpose.
    pub malformed: bool,
    /// The request went out with others in one write (pipelining).
    pub batch: bool,
    /// The freedoms the reference drive's answer was decided by.
    pub decided: &'a [drives::Decision],
    /// The FC 08 counter values the other readings of `diagnostic-counter-semantics` give, for a counter
    /// where some reading gives another value than the reference's: (sub-function, reading, value), the
    /// readings that give the reference's value too included.
    pub counter_alternatives: &'a [(u16, &'static str, u16)],
    /// What the reference would have answered under other values of the freedoms that decided its answer,
    /// where the model computed it (see [`drives::choices::Freedoms::alternative`]).
    pub choice_alternatives: &'a [drives::choices::ModelledAlternative],
    /// The target closed the connection instead of answering (Modbus/TCP).
    pub closed: bool,
    /// The MBAP length announced more bytes than were sent (Modbus/TCP): a drive that waits for them is
    /// silent whatever it would do once they are in.
    pub short_of_length: bool,
    /// A Modbus/TCP request (protocol id 0) to a profile without Modbus/TCP among its transports: a gateway
    /// is between, which answers where the drive is silent as `gateway-no-response` admits.
    pub gateway: bool,
}

impl Alternative {
    /// `answer` (`None`: no answer), compared as the step compares, shown as `shown`.
    pub fn exact(answer: Option<Response>, shown: Shown) -> Self {
        Alternative {
            answer,
            shown,
            values_free: false,
            note: None,
        }
    }

    /// `answer`, compared in structure only: its data values are free.
    pub fn values_free(answer: Option<Response>, shown: Shown) -> Self {
        Alternative {
            values_free: true,
            ..Self::exact(answer, shown)
        }
    }

    /// True when the alternative is the connection closed (an outcome freedom's `close`).
    pub fn closes(&self) -> bool {
        self.answer.is_none() && self.shown.value == "close"
    }
}

impl StepContext<'_> {
    fn decided(&self, f: &Freedom) -> bool {
        self.decided.iter().any(|d| *d == f.id)
    }
}

/// An alternative answer a freedom admits: the answer (`None`: silence, or a close where the value shown is
/// `close`), what the freedom's value is called, and whether the answer's data values are free (compared in
/// structure only).
#[derive(Debug)]
pub struct Alternative {
    pub answer: Option<Response>,
    pub shown: Shown,
    pub values_free: bool,
    /// A note for the report when the alternative is admissible but worth saying (a function served that
    /// the profile does not list).
    pub note: Option<String>,
}

/// The freedoms of `requirements` that apply to `profile` and that a request can touch (see [`touches`]):
/// the only ones [`applicable_among`] has to look at beyond those decided or cited. The same for every step
/// of a run, so a runner finds them once; looking at every freedom for every answer was a tenth of an
/// in-process campaign's time.
pub fn touchable(requirements: &Requirements, profile: &str) -> Vec<usize> {
    requirements
        .freedoms()
        .iter()
        .enumerate()
        .filter(|(_, f)| f.applies_to(profile) && may_touch(f))
        .map(|(i, _)| i)
        .collect()
}

/// The freedoms applicable to a step: decided by the reference drive, cited by the case, or about what the
/// request touches (among `touchable`, what [`touchable`] found for the step's profile); only those of the
/// run's profile.
pub fn applicable_among<'a>(
    requirements: &'a Requirements,
    touchable: &[usize],
    cx: &StepContext<'_>,
    decisions: &[drives::Decision],
    cited: &[String],
) -> Vec<&'a Freedom> {
    let mut out: Vec<&'a Freedom> = Vec::new();
    let by_id = decisions
        .iter()
        .copied()
        .chain(cited.iter().map(String::as_str))
        .filter_map(|id| requirements.freedom(id));
    let freedoms = requirements.freedoms();
    let touched = touchable
        .iter()
        .filter_map(|&i| freedoms.get(i))
        .filter(|f| touches(f, cx));
    for f in by_id.chain(touched) {
        if f.applies_to(&cx.profile.device.id) && !out.iter().any(|g| g.id == f.id) {
            out.push(f);
        }
    }
    out
}

/// Where the LMD manual's example reads the inputs (0x002D, line 763) relative to its table's addresses
/// (0x0000, line 731): `lmd-discrete-input-addressing`.
pub const LMD_EXAMPLE_INPUT_OFFSET: u16 = 0x002D;

/// False when [`touches`] is false for `f` whatever the step: it looks only at these kinds (and at
/// `fc41-read-back-fields` by id).
fn may_touch(f: &Freedom) -> bool {
    f.id == drives::choices::ids::FC41_READ_BACK_FIELDS
        || f.id == drives::choices::ids::LMD_INPUT_SETUP_FIELDS
        || f.id == drives::choices::ids::GATEWAY_NO_RESPONSE
        || matches!(
            f.kind,
            FreedomKind::Reading
                | FreedomKind::UnitIds
                | FreedomKind::Optional
                | FreedomKind::Access
                | FreedomKind::StatusBits
                | FreedomKind::FieldValue
                | FreedomKind::WordOrder
        )
}

/// True when the request touches what a freedom is about (item-, register- and unit-bound freedoms).
/// Every freedom this can be true for must pass [`may_touch`] (test `touchable_is_every_freedom_touched`).
fn touches(f: &Freedom, cx: &StepContext<'_>) -> bool {
    // The readings of the vendor functions, wherever such a request goes (generated and fuzz cases cite
    // nothing); the others where a case cites them (the LMD input addressing is learned before the cases).
    if f.kind == FreedomKind::Reading {
        // The FC 43 layout cut by one byte is the example's form whole: a drive taking that form reads a
        // request there (a decodable request's form is learned before the cases).
        if f.id == "sd2x-fc43-reserved-byte" {
            return cx.request.is_none() && canopen_example_form(cx.pdu);
        }
        // An FC 02 read at the example's input addresses: a drive may serve them as an alias (`reading`).
        if f.id == "lmd-discrete-input-addressing" {
            return matches!(cx.request, Some(Request::ReadDiscreteInputs { address, .. })
                if cx.profile.discrete_inputs.iter().any(|b| b.get_ref().address.wrapping_add(LMD_EXAMPLE_INPUT_OFFSET) == *address));
        }
        return matches!(
            f.id.as_str(),
            "fc42-parameterless-byte-count"
                | "lmd-esc-wire-form"
                | "mdrive-program-control-function"
        ) && reading_concerns(f, cx.request, cx.pdu);
    }
    // A gateway is between the harness and the drive: about every request it forwards.
    if f.id == drives::choices::ids::GATEWAY_NO_RESPONSE {
        return cx.gateway;
    }
    // A unit id is about the frame, whatever its PDU (a malformed one to another unit goes unanswered too).
    if f.kind == FreedomKind::UnitIds {
        return cx.unit != cx.run_unit && f.covers_unit(cx.unit);
    }
    let Some(req) = cx.request else {
        return false;
    };
    // Any FC 0x41 read (the alternative is there only for a setting whose format and example disagree).
    if f.id == drives::choices::ids::FC41_READ_BACK_FIELDS {
        return matches!(req, Request::VendorRead { .. });
    }
    // An FC 0x41 read of S1-S4.
    if f.id == drives::choices::ids::LMD_INPUT_SETUP_FIELDS {
        return matches!(req, Request::VendorRead { .. })
            && f.items
                .iter()
                .any(|item| item_touched(item, req, cx.profile));
    }
    match f.kind {
        FreedomKind::Optional | FreedomKind::Access => f
            .items
            .iter()
            .any(|item| item_touched(item, req, cx.profile)),
        FreedomKind::StatusBits | FreedomKind::FieldValue => f
            .register
            .is_some_and(|r| registers_read(req).is_some_and(|(a, q)| covers(a, q, r))),
        FreedomKind::WordOrder => true,
        _ => false,
    }
}

fn item_touched(item: &Item, req: &Request, profile: &drives::profile::Profile) -> bool {
    item.touched_by(req, profile)
}

fn item_name(item: &Item) -> String {
    match (&item.name, item.register, &item.mnemonic, item.object) {
        (Some(n), _, _, _) => n.clone(),
        (None, Some(r), _, _) => format!("0x{r:04X}"),
        // Apart from a register of the same name (the LMD's MU is both): a drive may refuse the mnemonic
        // with a code of the vendor functions' error tables and the register with its own.
        (None, None, Some(m), _) => format!("{m} (FC 0x41/0x42)"),
        (None, None, None, Some(o)) => format!("object {o}"),
        _ => item
            .coil
            .map_or_else(String::new, |c| format!("coil 0x{c:04X}")),
    }
}

fn shown(f: &Freedom, about: impl Into<String>, value: &FreedomValue) -> Shown {
    Shown {
        freedom: f.id.clone(),
        about: about.into(),
        value: value.to_string(),
        reference: f.values.first() == Some(value),
    }
}

/// The `Shown` of a named value of `f`.
pub fn shown_value(f: &Freedom, about: impl Into<String>, value: &str) -> Shown {
    shown_named(f, about, value)
}

fn shown_named(f: &Freedom, about: impl Into<String>, value: &str) -> Shown {
    let v = f
        .values
        .iter()
        .find(|v| v.matches(value))
        .cloned()
        .unwrap_or(FreedomValue::Text(value.to_string()));
    shown(f, about, &v)
}

/// "exception-02" → 0x02.
fn exception_of(r: &Response) -> Option<(FunctionCode, ExceptionCode)> {
    match r {
        Response::Exception { function, code } => Some((*function, *code)),
        _ => None,
    }
}

fn int_values(f: &Freedom) -> impl Iterator<Item = i64> + '_ {
    f.values.iter().filter_map(|v| match v {
        FreedomValue::Int(i) => Some(*i),
        FreedomValue::Text(_) => None,
    })
}

/// Outcome freedoms whose reference value is recorded where a drive gives it, so that the run holds the drive
/// to one answer (the SD2x's FC 43 byte count above 4 and FC 08 data fields).
const HELD_OUTCOMES: &[&str] = &[
    drives::choices::ids::SD2X_FC43_BYTE_COUNT_OVER_4,
    drives::choices::ids::SD2X_FC43_CONTROL_BITS,
    drives::choices::ids::SD2X_FC43_RESERVED_NONZERO,
    drives::choices::ids::SD2X_FC43_OFFSET_NONZERO,
    drives::choices::ids::SD2X_DIAGNOSTIC_UNUSED_DATA,
    drives::choices::ids::SD2X_DIAGNOSTIC_DATA_SIZE,
];

/// The value the reference drive took for a freedom that decided its answer, as shown by this step (for the
/// record of choices). `None` when the step says nothing about the freedom's value.
pub fn reference_shown(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Option<Shown> {
    let first = f.values.first()?;
    match f.kind {
        // A code the reference chose shows the drive's choice only where the freedom decided it.
        FreedomKind::ExceptionCode | FreedomKind::SdoError | FreedomKind::FieldValue
            if !cx.decided(f) =>
        {
            None
        }
        FreedomKind::ExceptionCode => {
            let (_, code) = exception_of(expected?)?;
            (FreedomValue::Int(i64::from(code.0)) == *first).then(|| shown(f, "", first))
        }
        FreedomKind::SdoError => match expected? {
            Response::CanOpenError { sdo_code } => {
                (FreedomValue::Int(i64::from(*sdo_code)) == *first).then(|| shown(f, "", first))
            }
            _ => None,
        },
        FreedomKind::Optional => {
            // Only an answer the item's presence gives shows it: a refusal (a write to a read-only item)
            // is what a product lacking the item answers too.
            let req = cx.request?;
            let item = f.items.iter().find(|i| item_touched(i, req, cx.profile))?;
            (!expected?.is_exception()).then(|| shown(f, item_name(item), first))
        }
        FreedomKind::Access => {
            // Only the access a request exercises shows it: a write whether an item is read-only, a read
            // whether it is write-only.
            let req = cx.request?;
            let item = f.items.iter().find(|i| item_touched(i, req, cx.profile))?;
            let writes =
                registers_written(req).is_some() || matches!(req, Request::VendorWrite { .. });
            let reads = registers_read(req).is_some() || matches!(req, Request::VendorRead { .. });
            // A write tells only where a value of the freedom refuses writes (`ro`), a read only where one
            // refuses reads (`wo`): a write HM takes shows nothing between `rw` and `wo`.
            let has = |name: &str| f.admits(name);
            let shows = (writes && has("ro")) || (reads && has("wo"));
            // A refusal of a request that covers other addresses too may be theirs (a reserved register
            // beside a write-only one answers 02 whatever the drive takes the write-only one for).
            let alone = !expected.is_some_and(Response::is_exception)
                || item.covers_all_of(req, cx.profile);
            (shows && alone).then(|| shown(f, item_name(item), first))
        }
        FreedomKind::Counter => {
            // The counter a reading is about shows the reference's reading where another gives another value,
            // and the drive's value is the reference's (a comparison of the structure only lets any value
            // through: the reading the value shows is then the one that gives it, if only one does).
            let (sub, e) = counter_read(expected?)?;
            let o = observed.and_then(counter_read).map_or(e, |(_, o)| o);
            let about = format!("0x{sub:02X}");
            if o == e {
                // Shown where another reading gives another value and none gives this one.
                let about_sub = || cx.counter_alternatives.iter().filter(|(s, _, _)| *s == sub);
                return (about_sub().any(|(_, _, v)| *v != e)
                    && !about_sub().any(|(_, _, v)| *v == e))
                .then(|| shown(f, about, first));
            }
            let mut giving = cx
                .counter_alternatives
                .iter()
                .filter(|(s, _, v)| *s == sub && *v == o);
            match (giving.next(), giving.next()) {
                (Some((_, reading, _)), None) => Some(shown_named(f, about, reading)),
                _ => None,
            }
        }
        // A write (or read) of an MDrive output whose point is an input, taken as the reference takes it: the drive's
        // choice, held against a refusal of another such write (an outcome freedom's other values are shown
        // by the answers that differ from the reference's, see `outcome_shown`).
        FreedomKind::Outcome
            if (f.id == drives::choices::ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT
                || f.id == drives::choices::ids::MDRIVE_OUTPUT_READ_WHILE_INPUT
                || f.id == drives::choices::ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT
                || f.id == drives::choices::ids::LMD_OUTPUT_4_WRITE)
                && cx.decided(f) =>
        {
            let taken = !expected?.is_exception() && !observed?.is_exception();
            taken.then(|| shown_named(f, "", "response"))
        }
        // An SDO error sent as the reference sends it: the drive's byte order, held against the other.
        FreedomKind::Reading
            if f.id == drives::choices::ids::SD2X_SDO_ERROR_BYTE_ORDER && cx.decided(f) =>
        {
            let sdo = |r: &Response| matches!(r, Response::CanOpenError { .. });
            (sdo(expected?) && sdo(observed?)).then(|| shown(f, "", first))
        }
        FreedomKind::FieldValue if f.id == drives::choices::ids::SD2X_FC43_READ_ZERO_COUNT => {
            let value = match expected? {
                Response::CanOpenError { .. } => "sdo-error",
                Response::CanOpen(a) if a.byte_count == 0 => "zero",
                Response::CanOpen(_) => "object-size",
                _ => return None,
            };
            Some(shown_named(f, "", value))
        }
        // The SD2x's outcome freedoms a drive keeps to, whichever answer it gives: the reference's, shown
        // where the drive gave it too (the other values are shown by `outcome_shown`).
        FreedomKind::Outcome if HELD_OUTCOMES.contains(&f.id.as_str()) && cx.decided(f) => {
            // A reference leaving an unused field alone (it then computes no answer for leaving it alone):
            // whatever the telegram got then, that is `response`.
            if UNUSED_FIELDS.contains(&f.id.as_str())
                && !cx.choice_alternatives.iter().any(|(id, _, _)| *id == f.id)
            {
                return Some(shown_named(f, "", "response"));
            }
            let value = match expected {
                None => "silence".to_string(),
                Some(Response::Exception { code, .. }) => format!("exception-{:02X}", code.0),
                Some(Response::CanOpenError { .. }) => "sdo-error".to_string(),
                Some(_) => "response".to_string(),
            };
            f.admits(&value).then(|| shown_named(f, "", &value))
        }
        FreedomKind::FieldValue if f.id == drives::choices::ids::FC42_BYTES_WRITTEN => {
            // Four parameter bytes read the same both ways: that shows no choice.
            let ambiguous = matches!(cx.request, Some(Request::VendorWrite { params, .. }) if params.len() == 4);
            (matches!(expected?, Response::VendorWrite { .. }) && !ambiguous)
                .then(|| shown(f, "", first))
        }
        _ => None,
    }
}

/// A value other than the reference's that an answer passing as it is shows for a freedom whose field the
/// comparison leaves free (the FC 0x41 parameter string is compared in structure only). The reference's own
/// value is left to [`reference_shown`], which does not record it: nearly every read shows it.
pub fn observed_shown(
    f: &Freedom,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Option<Shown> {
    match (f.id.as_str(), expected?, observed?) {
        (
            drives::choices::ids::FC41_READ_BACK_FORMAT,
            Response::VendorRead { .. },
            Response::VendorRead { params },
        ) if params.first() == Some(&b'=') => Some(shown_named(f, "", "as-written")),
        _ => None,
    }
}

/// The values shown that the observation `kind` (see [`crate::oracle::outcome_kind`]) really shows. A
/// refusal shows a freedom's value only where nothing else could be its reason: where the request touches
/// an item a product may lack (an optional group listing the exception), an item whose access the manual
/// leaves open, a register it covers in part, a value out of range and so on, two or more of these
/// reasons at once make the exception no evidence of any one of them (the drive answering 02 for I6,
/// which is read-only and which an MDrive Hybrid lacks, says nothing of its code for read-only writes).
/// The access freedom and the code for writes to read-only items are one reason. Nor does a request sent
/// malformed, in a batch or to another unit id show the access or the presence of an item; nor silence
/// before an ADU's announced bytes are all in a way of skipping it. Whether an address is valid, where the
/// order of the checks decides the code (`exception-check-order`), is a reason of its own where the
/// register at either end of the range is one a product may lack or not give that access to.
pub fn unambiguous(
    shown: Vec<Shown>,
    applicable: &[&Freedom],
    cx: &StepContext<'_>,
    kind: Option<&str>,
    requirements: &Requirements,
) -> Vec<Shown> {
    // A half of a register whose width the manual gives two ways is a choice of its own (see `about_of`).
    let shown: Vec<Shown> = shown
        .into_iter()
        .map(|mut s| {
            if s.about.is_empty() {
                s.about = about_of(&s.freedom, cx);
            }
            s
        })
        .collect();
    // A frame not as long as its function's rules make it (`rtu-length-framing`) that another freedom of the
    // request explains alike (a truncated PDU's silence): the drive's choice is that one's, which is held per
    // function code; the framing freedom is left to the frames only it explains.
    let framing = drives::choices::ids::RTU_LENGTH_FRAMING;
    let shown: Vec<Shown> = if shown.iter().any(|s| {
        s.freedom == framing
            && shown
                .iter()
                .any(|o| o.freedom != framing && o.value == s.value)
    }) {
        shown.into_iter().filter(|s| s.freedom != framing).collect()
    } else {
        shown
    };
    let value_codes = requirements.freedom(drives::choices::ids::VALUE_OUT_OF_RANGE);
    let item_bound = |id: &str| {
        applicable
            .iter()
            .find(|f| f.id == id)
            .is_some_and(|f| matches!(f.kind, FreedomKind::Optional | FreedomKind::Access))
    };
    let shown: Vec<Shown> = if cx.malformed || cx.batch || cx.unit != cx.run_unit {
        shown
            .into_iter()
            .filter(|s| !item_bound(&s.freedom))
            .collect()
    } else {
        shown
    };
    // A refusal of the FC 43 layout cut to the example's length shows that the drive takes that form too,
    // not that it does not take the layout's (which one the cases use is learned before them). What a drive
    // does with an FC 08 data field of another size is its choice for Return Query Data (00): a counter's or
    // an unlisted sub-function's refusal is the reference's too.
    let not_query_data = cx.request.is_some_and(
        |r| !matches!(r, Request::Diagnostics { sub_function, .. } if *sub_function == 0),
    );
    let shown: Vec<Shown> = shown
        .into_iter()
        .filter(|s| {
            let form = cx.request.is_none() && s.freedom == "sd2x-fc43-reserved-byte";
            let size =
                not_query_data && s.freedom == drives::choices::ids::SD2X_DIAGNOSTIC_DATA_SIZE;
            !(form || size)
        })
        .collect();
    // A drive skips an ADU over 253 bytes (silently or with 03) once its bytes are in: before that, it is
    // silent whichever it chose.
    let shown: Vec<Shown> = if cx.short_of_length && kind == Some("silence") {
        shown
            .into_iter()
            .filter(|s| s.freedom != drives::choices::ids::PDU_OVER_253)
            .collect()
    } else {
        shown
    };
    let Some(code) = kind.and_then(|k| k.strip_prefix("exception-")) else {
        return shown;
    };
    let exception = format!("exception-{code}");
    // The reasons a refusal of this request could have (the access freedoms and the read-only code are
    // one), and the freedoms that name them.
    let mut reasons: Vec<&str> = Vec::new();
    let mut named: Vec<&str> = Vec::new();
    for f in applicable {
        let listed = f.admits(&exception);
        let reason = match f.kind {
            FreedomKind::Optional if listed && touches(f, cx) => f.id.as_str(),
            FreedomKind::Access if touches(f, cx) => {
                // A drive taking the item as writable refuses a write by its value instead (with a code
                // `value-out-of-range` lists): a second reason for the same exception.
                let writable = f.values.iter().any(|v| v.matches("rw") || v.matches("wo"));
                let writes = cx.request.is_some_and(|r| {
                    registers_written(r).is_some() || matches!(r, Request::VendorWrite { .. })
                });
                let value_code = u8::from_str_radix(code, 16).is_ok_and(|c| {
                    value_codes.is_some_and(|v| int_values(v).any(|x| x == i64::from(c)))
                });
                if writable && writes && value_code && !reasons.contains(&"value") {
                    reasons.push("value");
                }
                "access"
            }
            FreedomKind::ExceptionCode
                if (f.id == drives::choices::ids::WRITE_READ_ONLY
                    || f.id == drives::choices::ids::READ_WRITE_ONLY)
                    && cx.decided(f) =>
            {
                // A range that also runs into an address the profile does not map may be refused for
                // that (02) before the item's access is looked at (an independent MDrive reads 0x001B-0x001E,
                // DC with a reserved register, as 02 and DC alone as 04): a second reason.
                if covers_unmapped(cx) && !reasons.contains(&"address") {
                    reasons.push("address");
                }
                "access"
            }
            // Nor is a quantity over the device's limit served or refused: its refusal's code is
            // `quantity-over-device-limit`'s, which this exception shows.
            FreedomKind::Outcome
                if f.id == drives::choices::ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED =>
            {
                continue;
            }
            // Nor is a frame's length on a serial line a reason for one code or another: it decides only
            // whether the drive took the frame whole (and answered as the request asks) or ignored it.
            FreedomKind::Outcome if f.id == drives::choices::ids::RTU_LENGTH_FRAMING => continue,
            // An SDO error freedom is no reason for an exception: it chooses among SDO errors only.
            FreedomKind::ExceptionCode | FreedomKind::Outcome if cx.decided(f) => f.id.as_str(),
            _ => continue,
        };
        if !reasons.contains(&reason) {
            reasons.push(reason);
        }
        named.push(f.id.as_str());
    }
    if named.contains(&drives::choices::ids::EXCEPTION_CHECK_ORDER)
        && !reasons.contains(&"access")
        && range_ends_open(requirements, cx)
    {
        reasons.push("access");
    }
    if reasons.len() < 2 {
        return shown;
    }
    shown
        .into_iter()
        .filter(|s| !named.contains(&s.freedom.as_str()))
        .collect()
}

/// True when the registers the request reads or writes include an address the profile maps to no register.
fn covers_unmapped(cx: &StepContext<'_>) -> bool {
    let Some((a, q)) = cx
        .request
        .and_then(|r| registers_read(r).or_else(|| registers_written(r)))
    else {
        return false;
    };
    (u32::from(a)..u32::from(a) + u32::from(q))
        .any(|x| cx.profile.register_at(x as u16, false).is_none())
}

/// True when a register (or coil) at either end of the request's range (the addresses the reference tries for the
/// order of the checks: the first, and the last of at least one) is an item of an optional group or of an
/// access the manual leaves open: whether the address is valid there is a choice of the drive's.
fn range_ends_open(requirements: &Requirements, cx: &StepContext<'_>) -> bool {
    let Some(req) = cx.request else {
        return false;
    };
    let coils = drives::requirements::coils_touched(req);
    let Some((a, q)) = coils.or_else(|| registers_read(req).or_else(|| registers_written(req)))
    else {
        return false;
    };
    let last = a.saturating_add(q.max(1) - 1);
    let ends = [a, last].map(|address| match coils {
        Some(_) => Request::ReadCoils {
            address,
            quantity: 1,
        },
        None => Request::ReadHoldingRegisters {
            address,
            quantity: 1,
        },
    });
    requirements.freedoms().iter().any(|f| {
        matches!(f.kind, FreedomKind::Optional | FreedomKind::Access)
            && f.applies_to(&cx.profile.device.id)
            && f.items
                .iter()
                .any(|i| ends.iter().any(|r| item_touched(i, r, cx.profile)))
    })
}

/// An outcome freedom's value `kind` (`silence`, `close`, `exception-XX`, `response`) shown by a step the
/// reference answers another way and whose observation passed as it is (a request to be rejected or ignored,
/// where any of those settles it): where the freedom is about the step (as for [`alternatives`]) and lists
/// the value.
pub fn outcome_shown(f: &Freedom, cx: &StepContext<'_>, kind: &str) -> Option<Shown> {
    let about = cx.decided(f) || cx.malformed || (cx.batch && f.id.starts_with("pipelined"));
    let listed = f.admits(kind);
    (f.kind == FreedomKind::Outcome && about && listed).then(|| shown_named(f, "", kind))
}

/// Where the data a request's byte count counts begin (its fields before them: function code, addresses,
/// quantities, the byte count), for the functions whose layout has one (App 6.11, 6.12, 6.14, 6.15, 6.17).
fn counted_data_from(fc: u8) -> Option<usize> {
    match fc {
        0x0F | 0x10 => Some(6),
        0x17 => Some(10),
        0x14 | 0x15 => Some(2),
        _ => None,
    }
}

/// What a choice shown at this step is about within its freedom: for the answer to a read or write of part
/// of a 32-bit register, the register whose width the manual gives two ways (a drive may take its first
/// register for all of it, and keep to another choice for the others); otherwise the whole freedom ("").
pub fn about_of(freedom: &str, cx: &StepContext<'_>) -> String {
    use drives::choices::ids::{PARTIAL_REGISTER_READ, PARTIAL_REGISTER_WRITE, VALUE_MEANING_OPEN};
    // A value the manual gives no meaning: the drive's answer is about that register and that value (a
    // drive taking DC with the address of a user variable refuses other values).
    if freedom == VALUE_MEANING_OPEN {
        return value_meaning_about(cx).unwrap_or_default();
    }
    // A gateway answers per unit id: a broadcast, an id with no path and the drive's own silences may each
    // get their own answer (silence for a broadcast, 0A where it has no path, 0B where the drive is silent).
    if freedom == drives::choices::ids::GATEWAY_NO_RESPONSE {
        return format!("unit {}", cx.unit);
    }
    // A write to an output of an I/O point configured as an input, with a value the register cannot hold
    // (O1-O4 are 0 or 1): a drive may refuse the value (03) before it looks at the point's configuration, as
    // an independent MDrive does (tests/independent/mdrive-h: 03 to O1 = 52098, 02 to FC 05 ON of the same
    // point). A value in range and one out of it are held apart.
    if freedom == drives::choices::ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT {
        let in_range = |address: u16, values: &[u16]| {
            values.iter().zip(address..).all(|(v, a)| {
                cx.profile.register_at(a, false).is_none_or(|r| {
                    let (min, max) = r.range();
                    (min..=max).contains(&r.value_of_word(*v))
                })
            })
        };
        let fits = match cx.request {
            Some(Request::WriteSingleRegister { address, value }) => in_range(*address, &[*value]),
            Some(Request::WriteMultipleRegisters { address, values })
            | Some(Request::ReadWriteMultipleRegisters {
                write_address: address,
                values,
                ..
            }) => in_range(*address, values),
            _ => true,
        };
        return if fits {
            String::new()
        } else {
            "a value out of range".into()
        };
    }
    // FC 43 with an MEI type the drive does not serve: App 7's 03 also covers a request whose "implied length
    // is incorrect", so a drive that checks the PDU's length against the one interface it serves (Read Device
    // Identification: function code, MEI type, read code, object id, 4 bytes, App 6.21) before it looks at
    // the MEI type refuses another length with 03 and an unknown MEI type of that length with 01, as an
    // independent LMD does (tests/independent/lmd-m, DECISIONS.md section 1: "PDU length wrong for the FC:
    // exception 03"). It keeps to each.
    if freedom == drives::choices::ids::UNSUPPORTED_MEI_TYPE {
        return if cx.pdu.len() == 4 {
            "4 bytes, as Read Device Identification".into()
        } else {
            "another length".into()
        };
    }
    // A group write of the outputs (OT/OL) that sets no output at all cannot drive a point that is an input:
    // a drive may take it and refuse one that sets a bit (an independent MDrive refuses with 03 a bit of a
    // point that is not an output, and takes 0). Held apart.
    if freedom == drives::choices::ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT {
        let zero = match cx.request {
            Some(Request::WriteSingleRegister { value, .. }) => *value == 0,
            Some(Request::WriteMultipleRegisters { values, .. })
            | Some(Request::ReadWriteMultipleRegisters { values, .. }) => {
                values.iter().all(|v| *v == 0)
            }
            _ => false,
        };
        return if zero {
            "writing 0".into()
        } else {
            "setting an output".into()
        };
    }
    // FC 08's data field is N x 2 bytes (App 6.8): a field of an odd size is no telegram of the layout, one of
    // an even size other than the manual's 2 bytes is; a drive may echo the one and refuse the other.
    // And a field cut short of the manual's 2 bytes is a request cut short: a drive may drop it as a frame
    // it cannot parse and refuse a longer one with 03 (tests/independent/sd2x-g).
    if freedom == drives::choices::ids::SD2X_DIAGNOSTIC_DATA_SIZE {
        let data = cx.pdu.len().saturating_sub(3);
        return if data < 2 {
            "cut short".into()
        } else if data % 2 == 1 {
            "odd size".into()
        } else {
            "even size".into()
        };
    }
    // The order of the checks is drawn per function in app section 6 (a state diagram each): a drive keeps
    // to its choice per function code. And per check: section 6 tests the quantity and the byte count
    // before the address, 4.5 every data value after it; a drive that tests a quantity above the maximum
    // first (it bounds the address range), and a quantity of 0 or the byte count after the address (rmodbus
    // 0.13), takes one of the two drawn orders for each, and keeps to each.
    if freedom == drives::choices::ids::EXCEPTION_CHECK_ORDER {
        return cx
            .pdu
            .first()
            .map(|fc| {
                if quantity_zero(cx.pdu) {
                    format!("FC 0x{fc:02X} quantity 0")
                } else if byte_count_refused(cx.pdu) {
                    format!("FC 0x{fc:02X} byte count")
                } else {
                    format!("FC 0x{fc:02X}")
                }
            })
            .unwrap_or_default();
    }
    // A PDU longer than its layout carries a byte count that no longer matches in some functions and not
    // in others: a drive keeps to its choice per function code. So with a quantity above the manual's
    // limit: each function has its own state diagram (App 6), and a drive may bound a register read by its
    // quantity (03) and a read of its few I/O points by their addresses (02), as an independent LMD does.
    if freedom == drives::choices::ids::TRAILING_BYTES {
        return cx
            .pdu
            .first()
            .map(|fc| format!("FC 0x{fc:02X}"))
            .unwrap_or_default();
    }
    // A request cut short: each function has its own state diagram (App 6), and where its layout has a byte
    // count, a PDU cut inside the fields before it cannot be parsed at all (the serial line guide: a frame
    // in error, no answer), while one cut inside the data it counts holds a byte count the data do not match
    // (App 7: the implied length is incorrect, 03). A drive may drop the one and refuse the other, as an
    // independent SD2x does (tests/independent/sd2x-g), and keeps to each per function code.
    if freedom == drives::choices::ids::TRUNCATED_PDU {
        let Some(&fc) = cx.pdu.first() else {
            return String::new();
        };
        return match counted_data_from(fc) {
            Some(n) if cx.pdu.len() >= n => format!("FC 0x{fc:02X}, data short of its byte count"),
            _ => format!("FC 0x{fc:02X}"),
        };
    }
    // And per whether the range runs into reserved or missing addresses: a drive that checks the addresses
    // before its own limit answers 02 there (App 6.3, Figure 13: address + quantity) and its limit's 03 over
    // a range it maps whole, as an independent MDrive does (tests/independent/mdrive-f).
    if freedom == drives::choices::ids::QUANTITY_OVER_DEVICE_LIMIT {
        let Some(fc) = cx.pdu.first() else {
            return String::new();
        };
        return if cx
            .request
            .is_some_and(|r| every_address_mapped(r, cx.profile))
        {
            format!("FC 0x{fc:02X}, every address mapped")
        } else {
            format!("FC 0x{fc:02X}")
        };
    }
    // Whether a quantity above the manual's limit is served is about that quantity: a drive's own limit may
    // lie between the manual's and the specification's, as an independent MDrive's does (tests/independent/
    // mdrive-g, DECISIONS.md item 3: 4 to read and to write, the manual's 2 to write). It serves up to its
    // limit and refuses above, and keeps to each quantity.
    if freedom == drives::choices::ids::QUANTITY_OVER_DEVICE_LIMIT_SERVED {
        return cx
            .request
            .and_then(drives::requirements::quantity_asked)
            .map(|(fc, q)| format!("FC 0x{:02X} quantity {q}", fc.0))
            .unwrap_or_default();
    }
    if freedom != PARTIAL_REGISTER_WRITE && freedom != PARTIAL_REGISTER_READ {
        return String::new();
    }
    let Some(req) = cx.request else {
        return String::new();
    };
    let Some((address, quantity)) = registers_written(req).or_else(|| registers_read(req)) else {
        return String::new();
    };
    let end = u32::from(address) + u32::from(quantity);
    let overlapped =
        |r: &&drives::profile::Register| u32::from(r.address) < end && r.end() > u32::from(address);
    let registers = || cx.profile.registers.iter().map(|r| r.get_ref());
    // Where the range cuts a 32-bit register: from its second register, from its first and ending there,
    // or from an earlier register and ending in its first. And a write of a register the profile says is
    // read-only: a drive may refuse it for that (02, App 7: not an allowable address for a write) before it
    // looks at the halves, as an independent MDrive does for V (tests/independent/mdrive-h).
    let write = freedom == PARTIAL_REGISTER_WRITE;
    let cut = |r: &drives::profile::Register| {
        (r.width == 2 && overlapped(&r) && (r.address < address || r.end() > end)).then(|| {
            let half = if r.address < address {
                "from inside it"
            } else if r.address == address {
                "from its first register"
            } else {
                "up to its first register"
            };
            if write && !r.access.writable() {
                format!("{half}, read-only")
            } else {
                half.to_string()
            }
        })
    };
    // A register whose width the manual gives two ways is a choice of its own, and so is each of its
    // halves: a drive that reads it as one register takes a write of its first and refuses one of its
    // second, a reserved address (02); one that reads it as two refuses both, the first as a quantity that
    // does not cover it (03) and the second as a start inside it (02), as an independent LMD does with LT
    // (tests/independent/lmd-m, DECISIONS.md section 2, "Writing").
    if let Some(r) = registers().find(|r| r.width_disputed && overlapped(r)) {
        let name = r.mnemonic.clone().unwrap_or_else(|| r.name.clone());
        return match cut(r) {
            Some(half) => format!("{name}, {half}"),
            None => name,
        };
    }
    // A write that starts where a 32-bit register starts reads as a write of it (a drive may take its first
    // register for the whole value), one that starts inside it cannot: a drive may take the one and refuse
    // the other, and keeps to each. A write that starts at an earlier register and ends in a 32-bit one's
    // first register is a third case: no register is written from inside, but the last is cut short. A drive
    // may refuse the address of a write that starts inside a parameter (02) and the quantity of one that
    // does not cover its last parameter (03), as an independent LMD does (tests/independent/lmd-m,
    // DECISIONS.md section 2, "Writing"); it keeps to each. Only the registers the write cuts count (one
    // it covers whole is written as a whole).
    // The same for reads: a drive may refuse a read that starts inside a 32-bit register with 02 (no item
    // starts there) and one whose quantity ends inside it with 03, as an independent MDrive does
    // (tests/independent/mdrive-h, DECISIONS.md item 4: "items are only accessed whole ... this applies to
    // both reads and writes"); it keeps to each.
    registers().find_map(cut).unwrap_or_default()
}

/// True when every address a read or multiple write (FC 01-04, 0F, 10) covers is one the profile maps, and
/// reads (a read) or writes (a write): registers by the register map, coils and inputs by their lists.
fn every_address_mapped(req: &Request, p: &drives::profile::Profile) -> bool {
    let regs = |address: u16, quantity: u16, input: bool, write: bool| {
        (u32::from(address)..u32::from(address) + u32::from(quantity)).all(|a| {
            u16::try_from(a)
                .ok()
                .and_then(|a| p.register_at(a, input))
                .is_some_and(|r| {
                    if write {
                        r.access.writable()
                    } else {
                        r.access.readable()
                    }
                })
        })
    };
    let bits = |list: Vec<u16>, address: u16, quantity: u16| {
        (u32::from(address)..u32::from(address) + u32::from(quantity))
            .all(|a| list.iter().any(|b| u32::from(*b) == a))
    };
    let coils = || p.coils.iter().map(|b| b.get_ref().address).collect();
    let inputs = || {
        p.discrete_inputs
            .iter()
            .map(|b| b.get_ref().address)
            .collect()
    };
    match req {
        Request::ReadHoldingRegisters { address, quantity } => {
            regs(*address, *quantity, false, false)
        }
        Request::ReadInputRegisters { address, quantity } => regs(*address, *quantity, true, false),
        Request::WriteMultipleRegisters { address, values } => regs(
            *address,
            u16::try_from(values.len()).unwrap_or(u16::MAX),
            false,
            true,
        ),
        Request::ReadCoils { address, quantity }
        | Request::WriteMultipleCoils {
            address, quantity, ..
        } => bits(coils(), *address, *quantity),
        Request::ReadDiscreteInputs { address, quantity } => bits(inputs(), *address, *quantity),
        _ => false,
    }
}

/// True when a quantity field of a read or multiple write (FC 01-04, 0F, 10, 17) is 0.
fn quantity_zero(pdu: &[u8]) -> bool {
    let zero = |i: usize| pdu.get(i..i + 2) == Some(&[0, 0][..]);
    match pdu.first() {
        Some(0x01..=0x04 | 0x0F | 0x10) => zero(3),
        Some(0x17) => zero(3) || zero(7),
        _ => false,
    }
}

/// True when a multiple write's quantities are in the specification's range and its byte count is not the
/// one they give (FC 0F: app 6.11, N = quantity / 8 rounded up; FC 10: 6.12, 2 x quantity; FC 17: 6.17, 2 x
/// the quantity to write): the value a refusal with 03 is about is then the byte count, not a quantity.
fn byte_count_refused(pdu: &[u8]) -> bool {
    let word = |i: usize| {
        pdu.get(i..i + 2)
            .map(|b| usize::from(u16::from_be_bytes([b[0], b[1]])))
    };
    let count = |i: usize| pdu.get(i).map(|b| usize::from(*b));
    // A quantity at `i` within 1..=max (the spec's limits, `FunctionCode::max_quantity`).
    let quantity = |i: usize, max: Option<u16>| {
        word(i).filter(|q| max.is_some_and(|m| (1..=usize::from(m)).contains(q)))
    };
    let Some(&fc) = pdu.first() else {
        return false;
    };
    let max = FunctionCode(fc).max_quantity();
    match fc {
        0x0F => matches!((quantity(3, max), count(5)), (Some(q), Some(n)) if n != q.div_ceil(8)),
        0x10 => matches!((quantity(3, max), count(5)), (Some(q), Some(n)) if n != 2 * q),
        0x17 => {
            quantity(3, max).is_some()
                && matches!(
                    (quantity(7, Some(FunctionCode::MAX_READ_WRITE_WRITE_QUANTITY)), count(9)),
                    (Some(q), Some(n)) if n != 2 * q
                )
        }
        _ => false,
    }
}

/// The alternative answers a freedom admits for a step whose reference answer is `expected` (`None`:
/// silence), tailored to what was `observed` (`None`: silence or no frame).
pub fn alternatives(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let alt = Alternative::exact;
    match f.kind {
        FreedomKind::ExceptionCode => {
            // Any listed code where the reference answers with a listed code.
            let (Some((efn, ecode)), Some((ofn, ocode))) = (
                expected.and_then(exception_of),
                observed.and_then(exception_of),
            ) else {
                return vec![];
            };
            let listed = |c: ExceptionCode| int_values(f).any(|v| v == i64::from(c.0));
            if efn == ofn && listed(ecode) && listed(ocode) {
                vec![alt(
                    observed.cloned(),
                    shown(f, "", &FreedomValue::Int(i64::from(ocode.0))),
                )]
            } else {
                vec![]
            }
        }
        FreedomKind::SdoError => match (expected, observed) {
            (
                Some(Response::CanOpenError { sdo_code: e }),
                Some(Response::CanOpenError { sdo_code: o }),
            ) if int_values(f).any(|v| v == i64::from(*e))
                && int_values(f).any(|v| v == i64::from(*o)) =>
            {
                vec![alt(
                    observed.cloned(),
                    shown(f, "", &FreedomValue::Int(i64::from(*o))),
                )]
            }
            _ => vec![],
        },
        FreedomKind::Optional => optional(f, cx, expected, observed),
        FreedomKind::Access => access(f, cx, expected, observed),
        // The gateway's answer is free only where the drive is silent: the reference's (here), or another
        // freedom's admissible silence (`oracle::judge_admitting`). Where the drive must answer, a 0B is the
        // drive failing to.
        FreedomKind::Outcome if f.id == drives::choices::ids::GATEWAY_NO_RESPONSE => {
            // The reference is silent, or answers as the gateway a drive chose before (the reference
            // follows it): the drive is silent there.
            let gateways = |e: &Response| {
                cx.decided(f) && exception_of(e).is_some_and(|(_, c)| c.is_gateway())
            };
            if cx.gateway && expected.is_none_or(gateways) {
                outcome(f, cx, expected, observed)
            } else {
                vec![]
            }
        }
        // What kind of answer is free only where the freedom decided it, or for a request sent malformed
        // on purpose (pipelining freedoms: for requests sent together).
        FreedomKind::Outcome
            if cx.decided(f) || cx.malformed || (cx.batch && f.id.starts_with("pipelined")) =>
        {
            let mut out = outcome(f, cx, expected, observed);
            out.extend(modelled(f, cx, observed));
            out
        }
        FreedomKind::Outcome => vec![],
        FreedomKind::UnitIds => {
            // The run's own unit must answer: the freedom is about the others.
            if cx.unit == cx.run_unit || !f.covers_unit(cx.unit) {
                return vec![];
            }
            let mut out = Vec::new();
            if observed.is_none() && f.admits("silence") {
                out.push(alt(
                    None,
                    shown_named(f, format!("unit {}", cx.unit), "silence"),
                ));
            }
            if let (Some(e), Some((_, code))) = (expected, observed.and_then(exception_of)) {
                let name = format!("exception-{:02X}", code.0);
                if f.admits(&name) {
                    out.push(alt(
                        Some(Response::exception(
                            e.function().without_exception_bit(),
                            code,
                        )),
                        shown_named(f, format!("unit {}", cx.unit), &name),
                    ));
                }
            }
            out
        }
        FreedomKind::ServedExtra => {
            // The reference refuses a function the profile does not list; serving it is admissible.
            let (Some(e), Some(o)) = (expected, observed) else {
                return vec![];
            };
            let Some((efn, code)) = exception_of(e) else {
                return vec![];
            };
            let fc = efn.without_exception_bit();
            if code != ExceptionCode::ILLEGAL_FUNCTION || !f.functions.contains(&fc.0) {
                return vec![];
            }
            let shown = shown_named(f, format!("FC 0x{:02X}", fc.0), "served");
            let served = format!(
                "FC 0x{:02X} is served although the profile does not list it (admissible: {})",
                fc.0, f.id
            );
            // A drive serving the function refuses a malformed request for it as any served function's:
            // 03, the implied length incorrect (App 7).
            if cx.malformed
                && exception_of(o).is_some_and(|(ofn, c)| {
                    ofn.without_exception_bit() == fc && c == ExceptionCode::ILLEGAL_DATA_VALUE
                })
            {
                return vec![Alternative {
                    note: Some(format!(
                        "{served}; this malformed request for it is refused with 03"
                    )),
                    ..Alternative::exact(Some(o.clone()), shown)
                }];
            }
            if o.is_exception() || o.function() != fc {
                return vec![];
            }
            vec![Alternative {
                note: Some(served),
                ..Alternative::values_free(Some(o.clone()), shown)
            }]
        }
        FreedomKind::StatusBits => status_bits(f, cx, expected, observed),
        FreedomKind::FieldValue => field_value(f, cx, expected, observed),
        // The SDO error code in the other byte order, as the model gives it (where it decided one).
        FreedomKind::Reading if f.id == drives::choices::ids::SD2X_SDO_ERROR_BYTE_ORDER => {
            if cx.decided(f) {
                modelled(f, cx, observed)
            } else {
                vec![]
            }
        }
        FreedomKind::Reading if f.id == drives::choices::ids::BUSY_AFTER_LONG_COMMAND => {
            busy_after_long_command(f, cx, observed)
        }
        FreedomKind::Reading => reading(f, cx, expected, observed),
        FreedomKind::Counter => {
            // Another reading of what the counter counts: the value it gives, for the same sub-function.
            let (Some((sub, e)), Some((osub, o))) = (
                expected.and_then(counter_read),
                observed.and_then(counter_read),
            ) else {
                return vec![];
            };
            if sub != osub || e == o {
                return vec![];
            }
            cx.counter_alternatives
                .iter()
                .filter(|(s, _, v)| *s == sub && *v == o)
                .map(|(_, reading, _)| {
                    alt(
                        observed.cloned(),
                        shown_named(f, format!("0x{sub:02X}"), reading),
                    )
                })
                .collect()
        }
        FreedomKind::WordOrder | FreedomKind::PipelineOrder => vec![],
    }
}

/// An FC 08 answer with a 16-bit value: (sub-function, value).
fn counter_read(r: &Response) -> Option<(u16, u16)> {
    match r {
        Response::Diagnostics { sub_function, data } if data.len() == 2 => {
            Some((*sub_function, u16::from_be_bytes([data[0], data[1]])))
        }
        _ => None,
    }
}

/// An item a product may lack: the listed exception (or silence) instead of the reference's answer.
fn optional(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let Some(req) = cx.request else {
        return vec![];
    };
    let Some(item) = f.items.iter().find(|i| item_touched(i, req, cx.profile)) else {
        return vec![];
    };
    let about = item_name(item);
    let fc = req.function();
    let mut out = Vec::new();
    match observed {
        None if f.admits("silence") => {
            out.push(Alternative::exact(None, shown_named(f, about, "silence")));
        }
        Some(o) => {
            if let Some((ofn, code)) = exception_of(o) {
                // A mnemonic the product lacks, named in FC 0x41/0x42: their error tables list 01, 02, 03
                // or 04 for any refusal (MDrive lines 958-962 and 998-1002, LMD 1131-1135 and 1192-1196;
                // `unknown-mnemonic-exception`), and an open-loop LMD may refuse MU with 01, the mnemonic
                // naming an action it does not have (tests/independent/lmd-g).
                let vendor_code = item.mnemonic.is_some()
                    && matches!(
                        req,
                        Request::VendorRead { .. } | Request::VendorWrite { .. }
                    )
                    && (1..=4).contains(&code.0);
                let absent = vendor_code
                    || f.values
                        .iter()
                        .any(|v| drives::Choices::exception_value(v) == Some(code));
                if absent && ofn.without_exception_bit() == fc && expected != observed {
                    out.push(Alternative::exact(
                        Some(Response::exception(fc, code)),
                        shown_named(f, about, &format!("exception-{:02X}", code.0)),
                    ));
                }
            }
        }
        None => {}
    }
    out
}

/// Access the manual does not state: a write the reference refuses may be accepted, a read it refuses may be
/// served (values free), a read it serves may be refused (the item is write-only on that drive).
fn access(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let (Some(req), Some(e), Some(o)) = (cx.request, expected, observed) else {
        return vec![];
    };
    let Some(item) = f.items.iter().find(|i| item_touched(i, req, cx.profile)) else {
        return vec![];
    };
    let about = item_name(item);
    let has = |name: &str| f.admits(name);
    let mut out = Vec::new();
    let writes = registers_written(req).is_some() || matches!(req, Request::VendorWrite { .. });
    let reads = registers_read(req).is_some() || matches!(req, Request::VendorRead { .. });
    let refused_access =
        matches!(exception_of(e), Some((_, c)) if c == ExceptionCode::ILLEGAL_DATA_ADDRESS);
    if refused_access && !o.is_exception() && o.function() == req.function() {
        // The reference takes the item as read-only (writes refused) or write-only (reads refused): 02, the
        // address does not allow that access (a range error, 03, is not about access).
        let value = if writes && (has("rw") || has("wo")) {
            Some(if has("rw") { "rw" } else { "wo" })
        } else if reads && (has("rw") || has("ro")) {
            Some(if has("rw") { "rw" } else { "ro" })
        } else {
            None
        };
        if let Some(v) = value {
            out.push(Alternative::values_free(
                Some(o.clone()),
                shown_named(f, about, v),
            ));
        }
    } else if !e.is_exception()
        && let Some((_, code)) = exception_of(o)
    {
        // The reference serves the item; a drive taking it as write-only refuses reads, as read-only writes.
        let value = if reads && has("wo") {
            Some("wo")
        } else if writes && has("ro") {
            Some("ro")
        } else {
            None
        };
        let refusal = [
            ExceptionCode::ILLEGAL_FUNCTION,
            ExceptionCode::ILLEGAL_DATA_ADDRESS,
            ExceptionCode::ILLEGAL_DATA_VALUE,
            ExceptionCode::SERVER_DEVICE_FAILURE,
        ]
        .contains(&code);
        if let (Some(v), true) = (value, refusal) {
            out.push(Alternative::exact(
                Some(Response::exception(req.function(), code)),
                shown_named(f, about, v),
            ));
        }
    }
    out
}

/// The kind of answer is free among the listed ones: response, silence, close, exception-XX. A close is
/// told from silence (the oracle judges the alternative `close` as an answer that closes, see
/// [`Alternative::closes`]).
fn outcome(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let request = cx.request;
    let has = |name: &str| f.admits(name);
    // A listed exception to the function `fc` the request asked for, where the drive answered one.
    // (A request of function 128-255 is refused with that function: its own bit 7 is set already.)
    let exception = |o: &Response, fc: FunctionCode| match exception_of(o) {
        Some((ofn, code))
            if ofn.without_exception_bit() == fc.without_exception_bit()
                && has(&format!("exception-{:02X}", code.0)) =>
        {
            vec![Alternative::exact(
                Some(Response::exception(fc, code)),
                shown_named(f, "", &format!("exception-{:02X}", code.0)),
            )]
        }
        _ => vec![],
    };
    match (expected, observed) {
        // The reference stays silent (an MBAP length still waiting for bytes, say): a listed exception to
        // the request's function is as good. The function is the PDU's first byte: a request malformed on
        // purpose (or of a function the profile lacks) may not decode.
        // Or, where the freedom lists it, the request served (a PDU longer than its layout, served as its
        // layout's bytes ask by a drive that answered another such request with silence before).
        (None, Some(o)) => {
            let fc = request
                .map(Request::function)
                .or_else(|| cx.pdu.first().map(|&b| FunctionCode(b)));
            match fc {
                Some(fc) if exception_of(o).is_none() && !fc.is_exception() => {
                    served(f, request, o, fc)
                }
                Some(fc) => exception(o, fc),
                None => vec![],
            }
        }
        (_, None) if cx.closed && has("close") => {
            vec![Alternative::exact(None, shown_named(f, "", "close"))]
        }
        (_, None) if has("silence") => {
            vec![Alternative::exact(None, shown_named(f, "", "silence"))]
        }
        (Some(e), Some(o)) => {
            let fc = e.function().without_exception_bit();
            if exception_of(o).is_some() {
                exception(o, fc)
            } else if let Response::CanOpenError { sdo_code } = o {
                // The SD2x's extended exception response where the reference refuses otherwise: a length
                // error (the only SDO error an outcome freedom is about).
                use drives::models::sd2x::sdo::{LENGTH_TOO_LONG, LENGTH_TOO_SHORT, LENGTH_WRONG};
                let length = matches!(*sdo_code, LENGTH_WRONG | LENGTH_TOO_LONG | LENGTH_TOO_SHORT);
                if has("sdo-error") && length && !matches!(e, Response::CanOpenError { .. }) {
                    vec![Alternative::exact(
                        Some(o.clone()),
                        shown_named(f, "", "sdo-error"),
                    )]
                } else {
                    vec![]
                }
            } else if e.is_exception() && !UNUSED_FIELDS.contains(&f.id.as_str()) {
                served(f, request, o, fc)
            } else if e.is_exception() {
                // A field left alone: what the telegram gets then is the model's (`modelled`).
                vec![]
            } else {
                unused_fields_echoed(f, request, e, o)
            }
        }
        _ => vec![],
    }
}

/// The SD2x FC 43 fields "not used" (the control code's bits 0-6, 004 line 608; the address offset, line
/// 627), which a drive may leave alone (`response`).
const UNUSED_FIELDS: &[&str] = &[
    drives::choices::ids::SD2X_FC43_CONTROL_BITS,
    drives::choices::ids::SD2X_FC43_OFFSET_NONZERO,
];

/// The SD2x FC 43 fields "not used" left alone by a drive that serves the request (`response`): its answer
/// may carry them as the response layout prints them (00h/80h, 0000h, line 560; the reference) or as the
/// request had them (echoed).
fn unused_fields_echoed(
    f: &Freedom,
    request: Option<&Request>,
    e: &Response,
    o: &Response,
) -> Vec<Alternative> {
    if !UNUSED_FIELDS.contains(&f.id.as_str()) || !f.admits("response") {
        return vec![];
    }
    echoed(request, e, o)
        .map(|answer| Alternative::exact(Some(answer), shown_named(f, "", "response")))
        .into_iter()
        .collect()
}

/// `e` with the control code and address offset the request had, where `o` carries them so and `e` does
/// not (a served FC 43 telegram echoing its unused fields); the rest is compared as the step compares.
fn echoed(request: Option<&Request>, e: &Response, o: &Response) -> Option<Response> {
    let (Some(Request::CanOpen(r)), Response::CanOpen(ea), Response::CanOpen(oa)) = (request, e, o)
    else {
        return None;
    };
    let mut echoed = ea.clone();
    if oa.control == r.control {
        echoed.control = r.control;
    }
    if oa.offset == r.offset {
        echoed.offset = r.offset;
    }
    (echoed != *ea).then_some(Response::CanOpen(echoed))
}

/// The answers the model computed for other values of `f` (`cx.choice_alternatives`), compared with the
/// drive's as the step compares: where what a value leads to depends on the drive's state and the rest of
/// the request (an SD2x leaving a field alone then checks the telegram on: the object, its access, the
/// length), the model answers it on a copy of itself.
fn modelled(f: &Freedom, cx: &StepContext<'_>, observed: Option<&Response>) -> Vec<Alternative> {
    let Some(o) = observed else {
        return vec![];
    };
    cx.choice_alternatives
        .iter()
        .filter(|(id, value, _)| *id == f.id && f.admits(value))
        .map(|(_, value, answer)| {
            let answer = echoed(cx.request, answer, o).unwrap_or_else(|| answer.clone());
            Alternative::exact(Some(answer), shown_named(f, "", value))
        })
        .collect()
}

/// The request served, where the outcome freedom `f` lists it and the drive's answer `o` is of its function
/// `fc`: a write's echo is the request's (App 6.5, 6.6, 6.11, 6.12), compared as the step compares; the
/// values read are the drive's.
fn served(
    f: &Freedom,
    request: Option<&Request>,
    o: &Response,
    fc: FunctionCode,
) -> Vec<Alternative> {
    if !f.admits("response") || o.function() != fc {
        return vec![];
    }
    let echo = request.is_some_and(|r| registers_written(r).is_some() || is_coil_write(r))
        && !matches!(request, Some(Request::ReadWriteMultipleRegisters { .. }));
    let served = Some(served_as_asked(request).unwrap_or_else(|| o.clone()));
    let shown = shown_named(f, "", "response");
    vec![if echo {
        Alternative::exact(served, shown)
    } else {
        Alternative::values_free(served, shown)
    }]
}

/// FC 05 or FC 0F.
fn is_coil_write(r: &Request) -> bool {
    matches!(
        r,
        Request::WriteSingleCoil { .. } | Request::WriteMultipleCoils { .. }
    )
}

/// The shape of an answer that serves `request` as asked, where a drive may serve what the reference
/// refuses: the echo of a register write, as many registers as a read asks for (values free). `None` for
/// other requests (the answer observed is then the only guide).
fn served_as_asked(request: Option<&Request>) -> Option<Response> {
    Some(match request? {
        Request::WriteMultipleRegisters { address, values } => Response::WriteMultipleRegisters {
            address: *address,
            quantity: u16::try_from(values.len()).ok()?,
        },
        Request::WriteSingleRegister { address, value } => Response::WriteSingleRegister {
            address: *address,
            value: *value,
        },
        Request::WriteSingleCoil { address, value } => Response::WriteSingleCoil {
            address: *address,
            value: *value,
        },
        Request::WriteMultipleCoils {
            address, quantity, ..
        } => Response::WriteMultipleCoils {
            address: *address,
            quantity: *quantity,
        },
        Request::ReadHoldingRegisters { quantity, .. } => Response::ReadHoldingRegisters {
            values: vec![0; usize::from(*quantity)],
        },
        Request::ReadInputRegisters { quantity, .. } => Response::ReadInputRegisters {
            values: vec![0; usize::from(*quantity)],
        },
        Request::ReadWriteMultipleRegisters { read_quantity, .. } => {
            Response::ReadWriteMultipleRegisters {
                values: vec![0; usize::from(*read_quantity)],
            }
        }
        _ => return None,
    })
}

/// A status word equal to the reference's under the loosest listed mask.
fn status_bits(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let (Some(req), Some(e), Some(o)) = (cx.request, expected, observed) else {
        return vec![];
    };
    let Some((index, ev, ov)) = register_word(f, req, e, o) else {
        return vec![];
    };
    if register_values(e).map(Vec::len) != register_values(o).map(Vec::len) {
        return vec![];
    }
    // The tightest listed mask under which the two words agree. The DS402 mask that leaves bit 5 open
    // applies only where the state table leaves it open, in the state the reference's word codes.
    let Some(mask) = int_values(f).find(|m| {
        let m = *m as u16;
        ev & m == ov & m
            && (m != drives::ds402::status::BIT5_OPEN_MASK || drives::ds402::status::bit5_open(ev))
    }) else {
        return vec![];
    };
    let Some(answer) = with_word(e, index, ov) else {
        return vec![];
    };
    let answer = Some(answer);
    vec![Alternative::exact(
        answer,
        shown(f, "", &FreedomValue::Int(mask)),
    )]
}

/// The word of the freedom's register in what a register read `req` answers: its index in the values, and
/// the word `expected` and `observed` give it.
fn register_word(
    f: &Freedom,
    req: &Request,
    expected: &Response,
    observed: &Response,
) -> Option<(usize, u16, u16)> {
    let (address, _) = registers_read(req)?;
    let index = usize::from(f.register?.wrapping_sub(address));
    let e = *register_values(expected)?.get(index)?;
    let o = *register_values(observed)?.get(index)?;
    Some((index, e, o))
}

/// `answer` with the word at `index` replaced by `word`.
fn with_word(answer: &Response, index: usize, word: u16) -> Option<Response> {
    let mut values = register_values(answer)?.clone();
    *values.get_mut(index)? = word;
    with_register_values(answer, values)
}

fn register_values(r: &Response) -> Option<&Vec<u16>> {
    match r {
        Response::ReadHoldingRegisters { values }
        | Response::ReadInputRegisters { values }
        | Response::ReadWriteMultipleRegisters { values } => Some(values),
        _ => None,
    }
}

fn with_register_values(r: &Response, values: Vec<u16>) -> Option<Response> {
    Some(match r {
        Response::ReadHoldingRegisters { .. } => Response::ReadHoldingRegisters { values },
        Response::ReadInputRegisters { .. } => Response::ReadInputRegisters { values },
        Response::ReadWriteMultipleRegisters { .. } => {
            Response::ReadWriteMultipleRegisters { values }
        }
        _ => return None,
    })
}

/// A response field read more than one way.
fn field_value(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let (Some(e), Some(o)) = (expected, observed) else {
        return vec![];
    };
    let one = |answer: Response, value: &str| {
        vec![Alternative::exact(Some(answer), shown_named(f, "", value))]
    };
    match (f.id.as_str(), e, o, cx.request) {
        (
            "fc42-bytes-written",
            Response::VendorWrite { mnemonic, .. },
            Response::VendorWrite {
                written,
                mnemonic: om,
            },
            Some(Request::VendorWrite { params, .. }),
        ) if mnemonic == om => {
            if usize::from(*written) == params.len() {
                one(o.clone(), "parameter-bytes")
            } else if *written == 4 {
                one(o.clone(), "mnemonic-characters")
            } else {
                vec![]
            }
        }
        (
            "fc41-read-back-format",
            Response::VendorRead { params: ep },
            Response::VendorRead { params: op },
            _,
        ) => {
            if same_values(&parameter_values(ep), &parameter_values(op)) {
                one(o.clone(), "as-written")
            } else {
                vec![]
            }
        }
        (
            drives::choices::ids::FC41_READ_BACK_FIELDS,
            Response::VendorRead { params: ep },
            Response::VendorRead { params: op },
            Some(Request::VendorRead { mnemonic }),
        ) => {
            // The values the manual's write format has, where the reference reads back more of them.
            let name = mnemonic.name();
            let name = name.trim();
            let Some(format) = cx
                .profile
                .mnemonics
                .iter()
                .map(|m| m.get_ref())
                .find(|m| m.name == name)
                .and_then(|m| m.format.as_deref())
            else {
                return vec![];
            };
            let fields = parameter_values(format.as_bytes()).len();
            let (ev, ov) = (parameter_values(ep), parameter_values(op));
            if ev.len() > fields && ov.len() == fields && same_values(&ev[..fields], &ov) {
                vec![Alternative::exact(
                    Some(o.clone()),
                    shown_named(f, name, "format-count"),
                )]
            } else {
                vec![]
            }
        }
        (
            drives::choices::ids::LMD_INPUT_SETUP_FIELDS,
            Response::VendorRead { params: ep },
            Response::VendorRead { params: op },
            Some(Request::VendorRead { mnemonic }),
        ) => {
            // The example's three values, of which the drive keeps the first two.
            let (ev, ov) = (parameter_values(ep), parameter_values(op));
            if ev.len() == 3 && ov.len() == 2 && same_values(&ev[..2], &ov) {
                let name = mnemonic.name();
                vec![Alternative::exact(
                    Some(o.clone()),
                    shown_named(f, name.trim(), "two"),
                )]
            } else {
                vec![]
            }
        }
        (
            "run-indicator-status",
            Response::ReportServerId { data: ed },
            Response::ReportServerId { data: od },
            _,
        ) => {
            // The same bytes but one, where the reference has a run indicator and the drive the other one.
            let differ: Vec<usize> = (0..ed.len().min(od.len()))
                .filter(|i| ed[*i] != od[*i])
                .collect();
            match differ.as_slice() {
                [i] if ed.len() == od.len()
                    && matches!(ed[*i], 0x00 | 0xFF)
                    && matches!(od[*i], 0x00 | 0xFF) =>
                {
                    one(o.clone(), if od[*i] == 0xFF { "on" } else { "off" })
                }
                _ => vec![],
            }
        }
        (
            "event-counter-clear-counted",
            Response::GetCommEventCounter {
                status: es,
                event_count: ec,
            },
            Response::GetCommEventCounter {
                status: os,
                event_count: oc,
            },
            _,
        ) if es == os && *oc == ec.wrapping_add(1) => one(o.clone(), "counted"),
        (drives::choices::ids::SD2X_FC43_READ_ZERO_COUNT, _, _, Some(Request::CanOpen(a)))
            if !a.is_write() && a.byte_count == 0 =>
        {
            zero_count_read(f, cx, a, o)
        }
        ("sd2x-watchdog-trip-state", _, _, Some(req)) => {
            // Fault (xxxx 1000 in bits 0-3 and 6) or fault reaction active (xxxx 1111).
            let Some((index, ev, ov)) = register_word(f, req, e, o) else {
                return vec![];
            };
            const FAULT: u16 = 0x0008;
            const REACTION: u16 = 0x000F;
            if ev & 0x004F == FAULT && ov & 0x004F == REACTION {
                with_word(e, index, ov)
                    .map(|a| one(a, "fault-reaction-active"))
                    .unwrap_or_default()
            } else {
                vec![]
            }
        }
        (_, _, _, Some(req)) => {
            // A numeric register field: any listed value, or any non-zero one where the data says so.
            let Some((index, ev, ov)) = register_word(f, req, e, o) else {
                return vec![];
            };
            let listed = |w: u16| int_values(f).any(|v| v == i64::from(w));
            let any_nonzero = f.admits("any-nonzero");
            if !listed(ev) || ev == ov {
                return vec![];
            }
            let value = if listed(ov) {
                format!("0x{ov:04X}")
            } else if any_nonzero && ov != 0 {
                "any-nonzero".to_string()
            } else {
                return vec![];
            };
            with_word(e, index, ov)
                .map(|a| one(a, &value))
                .unwrap_or_default()
        }
        _ => vec![],
    }
}

/// An FC 43 read of 0 bytes (`sd2x-fc43-read-zero-count`): the SDO length error for a count too short (or
/// not correct), the object at its size, or no data; a response echoes the request's header. The data
/// values are free (what the object holds is judged by the reads of its size).
fn zero_count_read(
    f: &Freedom,
    cx: &StepContext<'_>,
    asked: &codec::CanOpenAccess,
    o: &Response,
) -> Vec<Alternative> {
    match o {
        Response::CanOpenError { sdo_code } => {
            use drives::models::sd2x::sdo::{LENGTH_TOO_SHORT, LENGTH_WRONG};
            if matches!(*sdo_code, LENGTH_WRONG | LENGTH_TOO_SHORT) {
                vec![Alternative::exact(
                    Some(o.clone()),
                    shown_named(f, "", "sdo-error"),
                )]
            } else {
                vec![]
            }
        }
        Response::CanOpen(r) if !r.is_write() => {
            let Some(size) = cx
                .profile
                .object(asked.index, asked.subindex)
                .map(|ob| ob.ty.size())
            else {
                return vec![];
            };
            let (count, value) = match usize::from(r.byte_count) {
                0 => (0, "zero"),
                n if n == size => (size, "object-size"),
                _ => return vec![],
            };
            let answer = codec::CanOpenAccess {
                byte_count: count as u16,
                data: vec![0; count],
                ..asked.clone()
            };
            vec![Alternative::values_free(
                Some(Response::CanOpen(answer)),
                shown_named(f, "", value),
            )]
        }
        _ => vec![],
    }
}

/// The values of an FC 0x41 parameter string, however separated ("=0,0,0", "0, 0, 0").
/// The same parameter values: equal strings, or numbers of the same value ("1.500" and "1.5": the manual
/// prints settings with a fixed number of decimals, a drive may not).
fn same_values(a: &[String], b: &[String]) -> bool {
    a.len() == b.len()
        && a.iter().zip(b).all(|(x, y)| {
            x == y || matches!((x.parse::<f64>(), y.parse::<f64>()), (Ok(u), Ok(v)) if u == v)
        })
}

fn parameter_values(p: &[u8]) -> Vec<String> {
    let s = String::from_utf8_lossy(p);
    s.trim()
        .trim_start_matches('=')
        .split(',')
        .map(|v| v.trim().to_string())
        .collect()
}

/// Equally supported readings of a manual: a drive following another one may refuse the adopted form of a
/// request (01-04, or the SD2x extended exception); its answers then say which reading it follows.
fn reading(
    f: &Freedom,
    cx: &StepContext<'_>,
    expected: Option<&Response>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let (Some(o), Some(&fc)) = (observed, cx.pdu.first()) else {
        return vec![];
    };
    if expected == observed || !reading_concerns(f, cx.request, cx.pdu) {
        return vec![];
    }
    let other = f.values.get(1).map(|v| v.to_string()).unwrap_or_default();
    // An LMD that serves its inputs at both addresses the manual gives (the table's 0x0000, which the run
    // found it serving, and the example's 0x002D as an alias): a read of the inputs at the example's
    // address served where the reference, following the table, refuses it with 02. Its own choice (about
    // the alias), so that a drive refusing such a read later is held to it.
    if f.id == "lmd-discrete-input-addressing"
        && let (Some(Request::ReadDiscreteInputs { address, quantity }), Some(e)) =
            (cx.request, expected)
        && matches!(e, Response::Exception { code, .. } if code.0 == 2)
        && matches!(o, Response::ReadDiscreteInputs { .. })
    {
        let inputs: Vec<u16> = cx
            .profile
            .discrete_inputs
            .iter()
            .map(|b| b.get_ref().address.wrapping_add(LMD_EXAMPLE_INPUT_OFFSET))
            .collect();
        let last = u32::from(*address) + u32::from(*quantity.max(&1)) - 1;
        let within =
            (u32::from(*address)..=last).all(|a| inputs.iter().any(|&i| u32::from(i) == a));
        return if within {
            vec![Alternative {
                answer: Some(o.clone()),
                shown: shown_named(f, "0x002D as an alias", &other),
                values_free: true,
                note: Some(
                    "the drive serves its inputs at the example's address 0x002D too, as well as at the \
                     table's (lmd-discrete-input-addressing)"
                        .into(),
                ),
            }]
        } else {
            vec![]
        };
    }
    let refused = match o {
        Response::Exception { function, code } => {
            function.without_exception_bit().0 == fc && (1..=4).contains(&code.0)
        }
        Response::CanOpenError { .. } => {
            matches!(cx.request, Some(Request::CanOpen(_))) || canopen_example_form(cx.pdu)
        }
        _ => false,
    };
    if !refused {
        return vec![];
    }
    let note = if cx.request.is_none() {
        format!(
            "cut to its length, the request is a whole one in the form of the manual's example; the drive \
             refuses it as such ({}: {other})",
            f.id
        )
    } else {
        format!(
            "the drive refuses the form of the request the project adopted; it may follow the other reading \
             of the manual ({}: {other})",
            f.id
        )
    };
    vec![Alternative {
        answer: Some(o.clone()),
        shown: shown_named(f, "", &other),
        values_free: false,
        note: Some(note),
    }]
}

/// `busy-after-long-command`, where the runner found it decided the answer (a request sent with others,
/// refused Server Busy soon after the drive took a long-duration command: an NVM save; App 7, exception 06):
/// the refusal is admitted. Which requests a drive refuses while busy is its choice (every one, or the
/// writes), so each kind of request is a choice of its own: a refused write shows no more than that writes
/// are refused.
fn busy_after_long_command(
    f: &Freedom,
    cx: &StepContext<'_>,
    observed: Option<&Response>,
) -> Vec<Alternative> {
    let (Some(o @ Response::Exception { function, code }), Some(&fc), true) =
        (observed, cx.pdu.first(), cx.decided(f))
    else {
        return vec![];
    };
    if function.without_exception_bit().0 != fc || *code != ExceptionCode::SERVER_DEVICE_BUSY {
        return vec![];
    }
    let (about, value) = if crate::cases::safety::is_write(cx.pdu) {
        ("a write", "writes")
    } else {
        ("a request that writes nothing", "all-requests")
    };
    vec![Alternative {
        answer: Some(o.clone()),
        shown: shown_named(f, about, value),
        values_free: false,
        // Shown in the run's choices, as the pipelining freedom's refusal is.
        note: None,
    }]
}

/// True when `pdu` is a whole FC 43 / MEI 0x0D telegram in the form of the SD2x manual's example (the layout
/// without its Reserved byte): control, node-ID, index, subindex, offset, byte count, and the data a write
/// carries.
fn canopen_example_form(pdu: &[u8]) -> bool {
    match pdu {
        [0x2B, 0x0D, control, _, _, _, _, _, _, hi, lo, data @ ..] => {
            let count = usize::from(u16::from_be_bytes([*hi, *lo]));
            data.len() == if control & 0x80 != 0 { count } else { 0 }
        }
        _ => false,
    }
}

/// True when a request (decoded, or its PDU where the codec refuses it) is what a reading of the manual is
/// about: the one a drive may read otherwise.
fn reading_concerns(f: &Freedom, req: Option<&Request>, pdu: &[u8]) -> bool {
    match (f.id.as_str(), req) {
        ("sd2x-fc43-reserved-byte", Some(r)) => matches!(r, Request::CanOpen(_)),
        ("sd2x-fc43-reserved-byte", None) => canopen_example_form(pdu),
        // The codec's parameterless command (byte count 0), or the 5-byte form without a count that a drive
        // following the other reading takes for one (the codec refuses it).
        ("fc42-parameterless-byte-count", r) => {
            matches!(r, Some(Request::VendorWrite { params, .. }) if params.is_empty())
                || (r.is_none() && pdu.len() == 5 && pdu[0] == FunctionCode::VENDOR_WRITE.0)
        }
        ("lmd-esc-wire-form", Some(r)) => {
            matches!(r, Request::VendorWrite { mnemonic, .. } if mnemonic.name() == "\u{1b}")
        }
        ("lmd-discrete-input-addressing", Some(r)) => {
            matches!(r, Request::ReadDiscreteInputs { .. })
        }
        ("mdrive-program-control-function", Some(r)) => matches!(
            r,
            Request::VendorWrite { mnemonic, .. }
                if ["E", "EX", "PS", "RS", "\u{1b}"].contains(&mnemonic.name().as_str())
        ),
        ("fc41-byte-count-width", _) => false,
        (_, r) => r.is_some(),
    }
}

/// The register and value a write of a value without a meaning names: "TE=17".
fn value_meaning_about(cx: &StepContext<'_>) -> Option<String> {
    let (address, values) = match cx.request? {
        Request::WriteSingleRegister { address, value } => (*address, vec![*value]),
        Request::WriteMultipleRegisters { address, values } => (*address, values.clone()),
        Request::ReadWriteMultipleRegisters {
            write_address,
            values,
            ..
        } => (*write_address, values.clone()),
        _ => return None,
    };
    // One-register entries (every register with safe_values is one).
    cx.profile
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| {
            (!r.safe_values.is_empty() || r.operand_open) && r.width == 1 && r.address >= address
        })
        .find_map(|r| {
            let v = r.value_of_word(*values.get(usize::from(r.address - address))?);
            r.meaning_open(v).then(|| {
                format!(
                    "{}={v}",
                    r.mnemonic.clone().unwrap_or_else(|| r.name.clone())
                )
            })
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use drives::choices::ids::{PARTIAL_REGISTER_WRITE, UNKNOWN_MNEMONIC};

    /// The embedded corpus's profile `name`.
    fn embedded_profile(name: &str) -> drives::profile::Profile {
        drives::corpus::Corpus::Embedded
            .profile(name)
            .expect("an embedded profile")
    }

    /// The embedded corpus's requirements and freedoms.
    fn embedded_requirements() -> drives::requirements::Requirements {
        drives::corpus::Corpus::Embedded
            .requirements()
            .expect("requirements")
    }

    fn cx_for<'a>(
        request: &'a Request,
        pdu: &'a [u8],
        profile: &'a drives::profile::Profile,
    ) -> StepContext<'a> {
        StepContext {
            request: Some(request),
            pdu,
            unit: 1,
            run_unit: 1,
            profile,
            malformed: false,
            batch: false,
            decided: &[],
            counter_alternatives: &[],
            choice_alternatives: &[],
            closed: false,
            short_of_length: false,
            gateway: false,
        }
    }

    /// A quantity above the manual's limit is a choice per function code: an independent LMD refuses a
    /// register read of 3 (limit 2) with 03 and a read of inputs past its four points with 02, each function
    /// by its own state diagram (App 6). Two register reads are one choice, held to one code.
    #[test]
    fn a_quantity_over_the_device_limit_is_a_choice_per_function() {
        let profile = embedded_profile("lmd");
        let about = |pdu: &[u8]| {
            let req = Request::decode(pdu).expect("a request");
            about_of(
                drives::choices::ids::QUANTITY_OVER_DEVICE_LIMIT,
                &cx_for(&req, pdu, &profile),
            )
        };
        let inputs = about(&[0x02, 0x00, 0x03, 0x00, 0x05]);
        // 0x0089-0x008B: VI and the first half of VM, mapped whole; 0x003C-0x003E: IP and a reserved range.
        let registers = about(&[0x03, 0x00, 0x89, 0x00, 0x03]);
        let other_registers = about(&[0x03, 0x00, 0x8B, 0x00, 0x03]);
        let into_reserved = about(&[0x03, 0x00, 0x3B, 0x00, 0x03]);
        assert_ne!(inputs, registers);
        assert_eq!(registers, other_registers);
        assert_eq!(registers, "FC 0x03, every address mapped");
        // A range that runs into reserved or missing addresses is a choice of its own: a drive that checks
        // the addresses first answers 02 there and its limit's 03 over a range it maps whole (the sixth
        // wave's MDrive).
        assert_eq!(into_reserved, "FC 0x03");
    }

    /// A read of part of a 32-bit register is a choice per where it cuts the register, as a write is: mdrive-h
    /// refuses a read from P's second register (0x0058) with 02 and one that ends in a register's first with
    /// 03 ("items are only accessed whole"); the run held the 02 against the 03 it learned before the cases
    /// (a read of A's first register) as one choice.
    #[test]
    fn a_half_read_is_a_choice_per_where_it_cuts_the_register() {
        let mdrive = embedded_profile("mdrive");
        let requirements = embedded_requirements();
        let f = requirements
            .freedom(drives::choices::ids::PARTIAL_REGISTER_READ)
            .expect("freedom");
        let about = |address: u16, quantity: u16| {
            let req = Request::ReadHoldingRegisters { address, quantity };
            let pdu = req.to_bytes().expect("pdu");
            about_of(
                drives::choices::ids::PARTIAL_REGISTER_READ,
                &cx_for(&req, &pdu, &mdrive),
            )
        };
        assert_eq!(mdrive.register_at(0x0057, false).map(|r| r.width), Some(2));
        assert_eq!(about(0x0057, 1), "from its first register");
        assert_eq!(about(0x0058, 1), "from inside it");
        assert_eq!(about(0x0057, 2), "", "a whole register is no half");
        let mut log = super::super::choices::ChoiceLog::default();
        let first = shown_named(f, about(0x0000, 1), "exception-03");
        let inside = shown_named(f, about(0x0058, 1), "exception-02");
        assert_eq!(log.record(&first, "learned", &requirements), None);
        assert_eq!(log.record(&inside, "read-half", &requirements), None);
        let first_again = shown_named(f, about(0x0057, 1), "exception-02");
        assert!(log.record(&first_again, "other", &requirements).is_some());
    }

    /// mdrive-h refuses a half write of V (0x0085, read-only) with 02 and half writes of registers it may
    /// write with 03; and a write of O1 = 52098 (O1-O4 hold 0 or 1) with 03 where an FC 05 of the same point
    /// configured as an input gets 02. Each pair is held apart.
    #[test]
    fn a_read_only_half_and_an_output_value_out_of_range_are_choices_of_their_own() {
        let mdrive = embedded_profile("mdrive");
        let about = |freedom: &str, req: Request| {
            let pdu = req.to_bytes().expect("pdu");
            about_of(freedom, &cx_for(&req, &pdu, &mdrive))
        };
        let half = |address: u16| {
            about(
                PARTIAL_REGISTER_WRITE,
                Request::WriteMultipleRegisters {
                    address,
                    values: vec![7],
                },
            )
        };
        assert_eq!(half(0x0085), "from its first register, read-only");
        assert_eq!(half(0x0057), "from its first register");
        let output = drives::choices::ids::MDRIVE_OUTPUT_WRITE_WHILE_INPUT;
        let o1 = |value: u16| {
            about(
                output,
                Request::WriteMultipleRegisters {
                    address: 0x004B,
                    values: vec![value],
                },
            )
        };
        assert_eq!(o1(52098), "a value out of range");
        assert_eq!(o1(1), "");
        let coil = about(
            output,
            Request::WriteSingleCoil {
                address: 0x004B,
                value: 0xFF00,
            },
        );
        assert_eq!(coil, "");
    }

    /// An FC 43 with an MEI type the drive does not serve is a choice per whether the PDU has Read Device
    /// Identification's 4 bytes: lmd-m answers `2B 2E 05 AF` (a bit flip of a device-id read) 01 and `2B 00 9E
    /// 00 02` (a register read's body under FC 43) 03, its length check first; the run held the one against
    /// the other as one choice ("a drive keeps to one choice"). Two of the same length are one choice.
    #[test]
    fn an_unserved_mei_type_is_a_choice_per_whether_the_length_is_a_device_id_reads() {
        let profile = embedded_profile("lmd");
        let requirements = embedded_requirements();
        let f = requirements
            .freedom(drives::choices::ids::UNSUPPORTED_MEI_TYPE)
            .expect("freedom");
        let shown = |pdu: &[u8], code: &str| {
            let cx = StepContext {
                request: None,
                malformed: true,
                ..cx_for(&Request::ReadExceptionStatus, pdu, &profile)
            };
            shown_named(
                f,
                about_of(drives::choices::ids::UNSUPPORTED_MEI_TYPE, &cx),
                code,
            )
        };
        let mut log = super::super::choices::ChoiceLog::default();
        let four = shown(&[0x2B, 0x2E, 0x05, 0xAF], "1");
        let longer = shown(&[0x2B, 0x00, 0x9E, 0x00, 0x02], "3");
        assert_ne!(four.about, longer.about);
        assert_eq!(log.record(&longer, "fcswap", &requirements), None);
        assert_eq!(log.record(&four, "bitflip", &requirements), None);
        // The same length refused another way is a change of mind.
        let four_again = shown(&[0x2B, 0x0F, 0x01, 0x00], "3");
        assert!(log.record(&four_again, "other", &requirements).is_some());
        let longer_again = shown(&[0x2B, 0x01, 0x01, 0x00, 0x00, 0x00], "3");
        assert_eq!(
            log.record(&longer_again, "other-longer", &requirements),
            None
        );
    }

    /// A request cut short is a choice per function code, and, where the layout has a byte count, per whether
    /// the cut falls inside the data it counts (sd2x-g drops an FC 10 cut inside its fields and refuses one
    /// cut inside its data with 03).
    #[test]
    fn a_request_cut_short_is_a_choice_per_function_and_per_where_it_is_cut() {
        let profile = embedded_profile("sd2x");
        let about = |pdu: &[u8]| {
            let cx = StepContext {
                request: None,
                ..cx_for(&Request::ReadExceptionStatus, pdu, &profile)
            };
            about_of(drives::choices::ids::TRUNCATED_PDU, &cx)
        };
        // FC 10 of one register at 0x07E5 with its value cut to one byte, and cut before its byte count.
        let in_data = about(&[0x10, 0x07, 0xE5, 0x00, 0x01, 0x02, 0x36]);
        let in_fields = about(&[0x10, 0x07, 0xE5, 0x00]);
        assert_eq!(in_data, "FC 0x10, data short of its byte count");
        assert_eq!(in_fields, "FC 0x10");
        assert_ne!(about(&[0x06, 0x0B, 0xB8, 0x00]), in_fields);
        assert_eq!(about(&[0x03, 0x0B]), about(&[0x03, 0x0B, 0xB8, 0x00]));
        assert_eq!(
            about(&[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0]),
            "FC 0x17, data short of its byte count"
        );
        // FC 08's data field cut short of the manual's 2 bytes is held apart from one longer than it (sd2x-g
        // drops the one and refuses the other with 03).
        let size = |pdu: &[u8]| {
            let cx = StepContext {
                request: None,
                ..cx_for(&Request::ReadExceptionStatus, pdu, &profile)
            };
            about_of(drives::choices::ids::SD2X_DIAGNOSTIC_DATA_SIZE, &cx)
        };
        assert_eq!(size(&[0x08, 0x00, 0x00]), "cut short");
        assert_eq!(size(&[0x08, 0x00, 0x00, 0x12]), "cut short");
        assert_eq!(size(&[0x08, 0x00, 0x00, 1, 2, 3, 4]), "even size");
        assert_eq!(size(&[0x08, 0x00, 0x00, 1, 2, 3]), "odd size");
    }

    /// The check order is held per function code and per value refused: a drive may test a quantity above
    /// the maximum before the address and the byte count or a quantity of 0 after it (rmodbus 0.13 answers FC
    /// 0F with a bad byte count and address 02, with a quantity of 0 and a bad address 02, with a quantity
    /// too large and a bad address 03), each one of the two orders the spec draws.
    #[test]
    fn the_check_order_is_held_apart_for_the_quantity_and_the_byte_count() {
        let profile = embedded_profile("generic");
        let about = |pdu: &[u8]| {
            let cx = StepContext {
                request: None,
                ..cx_for(&Request::ReadExceptionStatus, pdu, &profile)
            };
            about_of(drives::choices::ids::EXCEPTION_CHECK_ORDER, &cx)
        };
        let bad_count = [0x0F, 0x00, 0x4C, 0x04, 0x76, 0x8E, 0x00];
        let bad_quantity = [0x0F, 0x00, 0x63, 0x40, 0x01, 0x01, 0xC8];
        assert_eq!(about(&bad_count), "FC 0x0F byte count");
        assert_eq!(about(&bad_quantity), "FC 0x0F");
        // FC 10: 2 registers with 3 bytes; with 4 bytes the count is right.
        assert_eq!(about(&[0x10, 0, 0, 0, 2, 3, 0, 0, 0]), "FC 0x10 byte count");
        assert_eq!(about(&[0x10, 0, 0, 0, 2, 4, 0, 0, 0, 0]), "FC 0x10");
        assert_eq!(about(&[0x10, 0, 0, 0, 0x7C, 0xF8]), "FC 0x10");
        // FC 17: the byte count of the write part.
        assert_eq!(
            about(&[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 3, 0, 0, 0]),
            "FC 0x17 byte count"
        );
        assert_eq!(about(&[0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 0]), "FC 0x17");
        assert_eq!(about(&[0x03, 0, 0, 0, 0x7E]), "FC 0x03");
        // A quantity of 0 apart from one above the maximum (rmodbus: 02 for `0F 02 09 00 00 00`, 03 for
        // `0F 00 63 40 01 01 C8`).
        assert_eq!(about(&[0x0F, 0x02, 0x09, 0, 0, 0]), "FC 0x0F quantity 0");
        assert_eq!(about(&[0x03, 0, 0, 0, 0]), "FC 0x03 quantity 0");
        assert_eq!(
            about(&[0x17, 0, 0, 0, 1, 0, 0, 0, 0, 0]),
            "FC 0x17 quantity 0"
        );
    }

    /// `applicable_among` with a runner's `touchable` list finds what looking at every freedom finds: over
    /// 3,000 generated cases of every embedded profile (every request and unit id a step sends, decoded or
    /// not), no freedom outside the list is touched, and the two give the same freedoms in the same order.
    /// A `touches` that learns a kind `may_touch` does not list fails here.
    #[test]
    fn touchable_is_every_freedom_touched() {
        use crate::cases::{Outgoing, Step};
        let requirements = embedded_requirements();
        let mut touched = 0usize;
        for stem in ["generic", "mdrive", "lmd", "sd2x"] {
            let profile = drives::corpus::Corpus::Embedded
                .profile(stem)
                .expect("profile");
            let touchable = touchable(&requirements, &profile.device.id);
            let generator = crate::cases::generated::Generator::new(&profile, 1, 7);
            for case in generator.cases(3_000) {
                for step in &case.steps {
                    let Step::Exchange { send, .. } = step else {
                        continue;
                    };
                    let sent: Vec<(&[u8], u8)> = match send {
                        Outgoing::Pdu(p) | Outgoing::Mutated { pdu: p, .. } => vec![(p, 1)],
                        Outgoing::PduToUnit { pdu, unit } => vec![(pdu, *unit)],
                        Outgoing::Batch(ps) => ps.iter().map(|p| (p.as_slice(), 1)).collect(),
                        _ => Vec::new(),
                    };
                    for (pdu, unit) in sent {
                        let request = Request::decode(pdu).ok();
                        let mut cx = match &request {
                            Some(r) => cx_for(r, pdu, &profile),
                            None => StepContext {
                                request: None,
                                ..cx_for(&Request::ReadExceptionStatus, pdu, &profile)
                            },
                        };
                        cx.unit = unit;
                        let all: Vec<&Freedom> = requirements
                            .freedoms()
                            .iter()
                            .filter(|f| f.applies_to(&profile.device.id) && touches(f, &cx))
                            .collect();
                        for f in &all {
                            assert!(may_touch(f), "{} touched but not listed", f.id);
                        }
                        touched += all.len();
                        let ids =
                            |v: Vec<&Freedom>| v.iter().map(|f| f.id.clone()).collect::<Vec<_>>();
                        assert_eq!(
                            ids(applicable_among(&requirements, &touchable, &cx, &[], &[])),
                            ids(all),
                            "{stem}: {}",
                            codec::hex_spaced(pdu)
                        );
                    }
                }
            }
        }
        assert!(
            touched > 1000,
            "only {touched} freedoms touched: the test sees nothing"
        );
    }

    /// An LMD serving its inputs at the example's address 0x002D as well as at the table's: a read there
    /// served where the reference refuses it with 02 is admitted (values free, its own choice); one past the
    /// inputs (0x0031) served, or an input read refused with another code, is not.
    #[test]
    fn an_lmd_serving_its_inputs_at_both_addresses_is_admitted() {
        let lmd = embedded_profile("lmd");
        let requirements = embedded_requirements();
        let f = requirements
            .freedom("lmd-discrete-input-addressing")
            .expect("freedom");
        let refused = Response::exception(FunctionCode::READ_DISCRETE_INPUTS, ExceptionCode(2));
        let served = Response::ReadDiscreteInputs { data: vec![0] };
        let judged = |address: u16, quantity: u16, observed: &Response| {
            let req = Request::ReadDiscreteInputs { address, quantity };
            let pdu = req.to_bytes().expect("pdu");
            let cx = cx_for(&req, &pdu, &lmd);
            (
                touches(f, &cx),
                reading(f, &cx, Some(&refused), Some(observed)),
            )
        };
        let (touched, alternatives) = judged(0x002D, 4, &served);
        assert!(touched);
        assert_eq!(alternatives.len(), 1);
        assert!(alternatives[0].values_free);
        assert_eq!(alternatives[0].shown.about, "0x002D as an alias");
        let (touched, alternatives) = judged(0x002E, 4, &served);
        assert!(
            touched && alternatives.is_empty(),
            "0x002E-0x0031 runs past the inputs"
        );
        let (touched, _) = judged(0x0040, 1, &served);
        assert!(!touched);
        let busy = Response::exception(FunctionCode::READ_DISCRETE_INPUTS, ExceptionCode(4));
        let (_, alternatives) = judged(0x002D, 1, &busy);
        assert!(
            alternatives
                .iter()
                .all(|a| a.answer.as_ref() != Some(&served))
        );
    }

    /// A group write of the MDrive's outputs (OT) is about whether it sets an output: an independent MDrive
    /// takes OT = 0 and refuses OT = 8 with 03 while the points are inputs, and keeps to both.
    #[test]
    fn a_group_write_of_the_outputs_is_keyed_by_whether_it_sets_one() {
        let mdrive = embedded_profile("mdrive");
        let about = |value: u16| {
            let req = Request::WriteMultipleRegisters {
                address: 0x0056,
                values: vec![value],
            };
            let pdu = req.to_bytes().expect("pdu");
            about_of(
                drives::choices::ids::MDRIVE_OUTPUT_GROUP_WRITE_WHILE_INPUT,
                &cx_for(&req, &pdu, &mdrive),
            )
        };
        assert_eq!(about(0), "writing 0");
        assert_eq!(about(8), "setting an output");
        assert_eq!(about(15), "setting an output");
    }

    /// TR's FC 0x41 read-back: the manual's example reads back three values, its write format has one. A drive
    /// answering the format's one value, equal to the reference's first, is admitted (`format-count`); one
    /// value that differs, or as many values as the reference with one wrong, is not.
    #[test]
    fn a_read_back_of_the_format_fields_is_admitted_only_with_the_reference_values() {
        let mdrive = embedded_profile("mdrive");
        let requirements = embedded_requirements();
        let f = requirements
            .freedom(drives::choices::ids::FC41_READ_BACK_FIELDS)
            .expect("freedom");
        let req = Request::VendorRead {
            mnemonic: codec::vendor::Mnemonic::from_name("TR").expect("TR"),
        };
        let pdu = req.to_bytes().expect("pdu");
        let cx = cx_for(&req, &pdu, &mdrive);
        let read = |p: &str| Response::VendorRead {
            params: p.as_bytes().to_vec(),
        };
        let expected = read("6500, 0, 0");
        let admitted = |o: &str| !field_value(f, &cx, Some(&expected), Some(&read(o))).is_empty();
        assert!(admitted("6500"));
        assert!(admitted("=6500"));
        assert!(!admitted("6501"));
        assert!(!admitted("6500, 1"));
        assert!(!admitted("6500, 0, 1"));
        // Not for a setting whose format has as many values as it reads back (S1: "=A,B,C"), nor for a
        // mnemonic the profile does not know.
        for (name, back, answer) in [("S1", "16, 0, 0", "16"), ("QQ", "1, 2", "1")] {
            let other = Request::VendorRead {
                mnemonic: codec::vendor::Mnemonic::from_name(name).expect("mnemonic"),
            };
            let pdu = other.to_bytes().expect("pdu");
            let cx = cx_for(&other, &pdu, &mdrive);
            assert!(
                field_value(f, &cx, Some(&read(back)), Some(&read(answer))).is_empty(),
                "{name}"
            );
        }
    }

    /// A half write of a register whose width the LMD manual gives two ways (LT: "0x009C-0x009D", "Bytes 2")
    /// is a choice about that register; a half write of any other 32-bit register is about the whole
    /// freedom, so a drive taking LT's first register alone and refusing other half writes keeps its choices.
    #[test]
    fn a_half_write_of_a_register_of_disputed_width_is_a_choice_of_its_own() {
        let lmd = embedded_profile("lmd");
        let about = |address: u16, freedom: &str| {
            let req = Request::WriteMultipleRegisters {
                address,
                values: vec![7],
            };
            let pdu = req.to_bytes().expect("pdu");
            about_of(freedom, &cx_for(&req, &pdu, &lmd))
        };
        assert_eq!(
            about(0x009C, PARTIAL_REGISTER_WRITE),
            "LT, from its first register"
        );
        assert_eq!(
            about(0x00A3, PARTIAL_REGISTER_WRITE),
            "TS, from its first register"
        );
        // LT's second half is another choice (lmd-m refuses the first with 03, the second with 02; a drive
        // reading LT as one register would take the first and refuse the second as reserved).
        assert_eq!(about(0x009D, PARTIAL_REGISTER_WRITE), "LT, from inside it");
        // R2 (0x0061) and A (0x0000) are 32-bit one way only: a half write of them is about where it starts
        // (a drive may take a write from a register's first word as the whole value, and refuse one from
        // inside it); other freedoms are about the whole freedom.
        assert_eq!(
            about(0x0061, PARTIAL_REGISTER_WRITE),
            "from its first register"
        );
        assert_eq!(
            about(0x0000, PARTIAL_REGISTER_WRITE),
            "from its first register"
        );
        assert_eq!(about(0x0001, PARTIAL_REGISTER_WRITE), "from inside it");
        assert_eq!(about(0x009C, UNKNOWN_MNEMONIC), "");
        // Writes of several registers: only the 32-bit registers they cut count. VF (0x00A7, one register)
        // and the first register of the 32-bit one after it: cut short at its end (lmd-m answers this 03 and a
        // write from inside a parameter 02; a bit flip of a write from 0x00B7 made it, and the run held the
        // 03 against the 02, "a drive keeps to one choice"). C1 (0x0005-0x0006) whole and the first register
        // of C2: the same. From C1's second register on: from inside it, wherever it ends.
        let about_n = |address: u16, n: usize| {
            let req = Request::WriteMultipleRegisters {
                address,
                values: vec![7; n],
            };
            let pdu = req.to_bytes().expect("pdu");
            about_of(PARTIAL_REGISTER_WRITE, &cx_for(&req, &pdu, &lmd))
        };
        let width_at = |a: u16| lmd.register_at(a, false).map(|r| (r.address, r.width));
        assert_eq!(width_at(0x00A7), Some((0x00A7, 1)));
        assert_eq!(width_at(0x00A8), Some((0x00A8, 2)));
        assert_eq!(about_n(0x00A7, 2), "up to its first register");
        assert_eq!(width_at(0x0005), Some((0x0005, 2)));
        assert_eq!(width_at(0x0007), Some((0x0007, 2)));
        assert_eq!(about_n(0x0005, 3), "up to its first register");
        assert_eq!(about_n(0x0006, 2), "from inside it");
        assert_eq!(about_n(0x0006, 3), "from inside it");
        assert_eq!(about_n(0x0000, 1), "from its first register");
        let mut log = super::super::choices::ChoiceLog::default();
        let requirements = embedded_requirements();
        let f = requirements
            .freedom(PARTIAL_REGISTER_WRITE)
            .expect("freedom");
        let lt = shown_named(f, about(0x009C, PARTIAL_REGISTER_WRITE), "response");
        let r2 = shown_named(f, about(0x0061, PARTIAL_REGISTER_WRITE), "exception-02");
        let a = shown_named(f, about(0x0000, PARTIAL_REGISTER_WRITE), "response");
        assert_eq!(log.record(&lt, "lt", &requirements), None);
        assert_eq!(log.record(&r2, "r2", &requirements), None);
        // Taking a half write of A after refusing R2's (both from their first register) is a change of mind;
        // refusing one from inside A is another choice.
        assert!(log.record(&a, "a", &requirements).is_some());
        let inside = shown_named(f, about(0x0001, PARTIAL_REGISTER_WRITE), "exception-02");
        assert_eq!(log.record(&inside, "a2", &requirements), None);
    }
}
