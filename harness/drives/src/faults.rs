//! Injected faults: each makes a model misbehave the way real firmware does, so every conformance check
//! can be shown to catch something.

use std::collections::BTreeSet;
use std::fmt;
use std::str::FromStr;

/// One way to break a drive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Fault {
    WrongExceptionCode,
    WrongFunctionCode,
    TidNotEchoed,
    MbapLength,
    ProtocolIdIgnored,
    PipelineDrop,
    WrongCrc,
    LateResponse,
    TruncatedResponse,
    StopAfterMalformed,
    WordOrder,
    ExceptionWithoutFc,
    BroadcastAnswered,
    BroadcastWriteIgnored,
    QuantityUnchecked,
    ReservedReadable,
    ReadOnlyWritable,
    RangeUnchecked,
    AnswerOtherUnit,
    CountersFrozen,
    WatchdogDisabled,
    UnitNotEchoed,
    IllegalCoilValueAccepted,
    CrcUnchecked,
    ExceptionStatusReversed,
    ListenOnlyIgnored,
    EventCounterCountsExceptions,
    EventLogOldestFirst,
    RunIndicatorOne,
    FileRecordLengthWrong,
    FileWriteFirstOnly,
    MaskWriteWrong,
    FifoOffByOne,
    UndeclaredFunctionServed,
    BitPaddingOnes,
    PartialWrite,
    ReadBeforeWrite,
    HalfRegisterWidened,
    WriteOnlyReadable,
    MnemonicParamsUnchecked,
    MbapLengthIgnored,
    AnswerInsideSilence,
    RangeCodeInconsistent,
    QuantityLowByte,
    QuantityOverSpecDropped,
    WriteQuantityOverLimitDropped,
    VendorWriteNotApplied,
    ConformityLevelWrong,
    Ds402EnableFromSwitchOnDisabled,
    SpeedWithoutEnable,
    WatchdogFromFirstWrite,
    ListedFunctionRefused,
    InputBitsReversed,
    ZeroCountPartial,
    ByteCountOver4Served,
    UnusedDiagDataRefused02,
    QueryDataCut,
    UnusedDiagDataInconsistent,
    LetterCaseBusy,
    GroupWriteClears,
    HomingNeverEnds,
    ProgramAbsentSilent,
    QuickStopBitClear,
    ZeroFieldsBusy,
    TrailingBytes04,
    HighFunctionServed,
    MeiTypeServed,
    NulPaddingBusy,
    EqualsSignBusy,
    BlankControlBusy,
    SdoErrorOrderInconsistent,
    ErrorRecordKept,
}

impl Fault {
    /// Every fault with its name and what it does.
    pub const ALL: &'static [(Fault, &'static str, &'static str)] = &[
        (
            Fault::WrongExceptionCode,
            "wrong-exception-code",
            "exception responses carry the wrong code (01->02, 02->03, 03->04, 04->01)",
        ),
        (
            Fault::WrongFunctionCode,
            "wrong-function-code",
            "normal responses carry a different function code than the request (FC xor 0x01)",
        ),
        (
            Fault::TidNotEchoed,
            "tid-not-echoed",
            "Modbus/TCP: the response's transaction id is the request's plus one",
        ),
        (
            Fault::MbapLength,
            "mbap-length",
            "Modbus/TCP: the response's MBAP length field is one more than the bytes sent",
        ),
        (
            Fault::ProtocolIdIgnored,
            "protocol-id-ignored",
            "Modbus/TCP: requests with a non-zero protocol id are answered instead of discarded",
        ),
        (
            Fault::PipelineDrop,
            "pipeline-drop",
            "Modbus/TCP: of several requests arriving together only the first is answered",
        ),
        (
            Fault::WrongCrc,
            "wrong-crc",
            "RTU: responses carry a wrong CRC (low byte inverted)",
        ),
        (
            Fault::LateResponse,
            "late-response",
            "responses are sent 1.5 s late, after any sensible timeout",
        ),
        (
            Fault::TruncatedResponse,
            "truncated-response",
            "responses lose their last PDU byte (framing adjusted to match)",
        ),
        (
            Fault::StopAfterMalformed,
            "stop-after-malformed",
            "after one malformed frame the drive never answers again",
        ),
        (
            Fault::WordOrder,
            "word-order",
            "32-bit registers are read and written in the opposite word order",
        ),
        (
            Fault::ExceptionWithoutFc,
            "exception-without-fc",
            "exception responses carry 0x80 instead of 0x80|FC",
        ),
        (
            Fault::BroadcastAnswered,
            "broadcast-answered",
            "RTU: broadcast requests (address 0) get a response",
        ),
        (
            Fault::BroadcastWriteIgnored,
            "broadcast-write-ignored",
            "RTU: a broadcast write (address 0; FC 05, 06, 0F, 10, 15, 16, 17) is not applied (still not answered), although every slave must accept the broadcast for writing functions",
        ),
        (
            Fault::QuantityUnchecked,
            "quantity-unchecked",
            "quantity 0 and quantities above the limit are served instead of exception 03",
        ),
        (
            Fault::ReservedReadable,
            "reserved-readable",
            "reserved and unmapped addresses read as 0 instead of exception 02",
        ),
        (
            Fault::ReadOnlyWritable,
            "read-only-writable",
            "writes to read-only registers and objects are accepted",
        ),
        (
            Fault::RangeUnchecked,
            "range-unchecked",
            "out-of-range values are written instead of rejected",
        ),
        (
            Fault::AnswerOtherUnit,
            "answer-other-unit",
            "frames addressed to another unit/slave are answered",
        ),
        (
            Fault::CountersFrozen,
            "counters-frozen",
            "RTU: the FC 08 diagnostic counters never move",
        ),
        (
            Fault::WatchdogDisabled,
            "watchdog-disabled",
            "SD2x: the RxPDO watchdog never trips",
        ),
        (
            Fault::UnitNotEchoed,
            "unit-not-echoed",
            "the response carries a different unit id / slave address than the request",
        ),
        (
            Fault::IllegalCoilValueAccepted,
            "illegal-coil-value-accepted",
            "FC 05 values other than 0xFF00/0x0000 are accepted",
        ),
        (
            Fault::CrcUnchecked,
            "crc-unchecked",
            "RTU: frames with a bad CRC are processed and answered",
        ),
        (
            Fault::ExceptionStatusReversed,
            "exception-status-reversed",
            "FC 07: the exception status outputs are packed MSB-first (output 0 in bit 7)",
        ),
        (
            Fault::ListenOnlyIgnored,
            "listen-only-ignored",
            "FC 08/04: force listen only mode is echoed and the drive keeps answering",
        ),
        (
            Fault::EventCounterCountsExceptions,
            "event-counter-counts-exceptions",
            "FC 0B/0C: the comm event counter also counts exception responses",
        ),
        (
            Fault::EventLogOldestFirst,
            "event-log-oldest-first",
            "FC 0C: the event bytes come oldest first instead of the most recent first",
        ),
        (
            Fault::RunIndicatorOne,
            "run-indicator-one",
            "FC 11: the run indicator ON is sent as 0x01 instead of 0xFF",
        ),
        (
            Fault::FileRecordLengthWrong,
            "file-record-length-wrong",
            "FC 14: each file response length counts the record data only, not the reference type byte",
        ),
        (
            Fault::FileWriteFirstOnly,
            "file-write-first-only",
            "FC 15: only the first sub-request is written (the whole request is still echoed)",
        ),
        (
            Fault::MaskWriteWrong,
            "mask-write-wrong",
            "FC 16: the result is (current AND and_mask) OR or_mask, without masking the OR by NOT and_mask",
        ),
        (
            Fault::FifoOffByOne,
            "fifo-off-by-one",
            "FC 18: one queued register fewer than the queue holds is answered (count and byte count agree)",
        ),
        (
            Fault::UndeclaredFunctionServed,
            "undeclared-function-served",
            "the data-model functions (FC 01-06, 0F, 10, 16, 17) are served even where the profile does not declare them (FC 06 on an MDrive)",
        ),
        (
            Fault::BitPaddingOnes,
            "bit-padding-ones",
            "FC 01/02: the unused high bits of the last data byte are sent as 1 instead of 0",
        ),
        (
            Fault::PartialWrite,
            "partial-write",
            "FC 16: a rejected write still writes its registers one by one up to the first one rejected (the exception is sent)",
        ),
        (
            Fault::ReadBeforeWrite,
            "read-before-write",
            "FC 23: the registers are read before the write is performed (the answer holds the old values)",
        ),
        (
            Fault::HalfRegisterWidened,
            "half-register-widened",
            "a read or write covering one half of a 32-bit register is served as the whole pair: a read answers one register more than asked, a write is echoed with one register more (and not stored)",
        ),
        (
            Fault::WriteOnlyReadable,
            "write-only-readable",
            "MDrive/LMD: FC 0x41 of a write-only mnemonic is answered with a value (\"0\") instead of refused",
        ),
        (
            Fault::MnemonicParamsUnchecked,
            "mnemonic-params-unchecked",
            "MDrive/LMD: FC 0x42 with parameters the mnemonic does not take is answered as written (the setting keeps its value)",
        ),
        (
            Fault::MbapLengthIgnored,
            "mbap-length-ignored",
            "Modbus/TCP: requests are cut by their function code's length rules, not by the MBAP length: one whose MBAP length promises more bytes than it has is answered at once",
        ),
        (
            Fault::AnswerInsideSilence,
            "answer-inside-silence",
            "RTU: the answer starts right after the request's last byte, inside the 3.5-character silence that must separate frames (a slave that cuts frames by length and answers at once)",
        ),
        (
            Fault::RangeCodeInconsistent,
            "range-code-inconsistent",
            "out-of-range register values are refused with 03 at even addresses and 04 at odd ones: each code is admissible (value-out-of-range), the two together are not one choice",
        ),
        (
            Fault::QuantityLowByte,
            "quantity-low-byte",
            "the quantity fields of FC 01-04, 0F, 10 and 17 are read by their low byte only, as the MDrive and LMD manuals' request tables print the quantity 1 byte wide: quantity 0x0101 is served as 1 item instead of refused with 03",
        ),
        (
            Fault::QuantityOverSpecDropped,
            "quantity-over-spec-dropped",
            "a request whose quantity field is above the specification's maximum (125 registers, 123 for FC 10, 2000 bits, 1968 coils, FC 17's 125 / 121) goes unanswered, as a stack that drops what would not fit its buffer; the device's own, lower limit is still answered with 03",
        ),
        (
            Fault::WriteQuantityOverLimitDropped,
            "write-quantity-over-limit-dropped",
            "FC 17: a quantity to write above the device's own limit but within the specification's 121 (49 on the SD2x, whose manual allows 1 to 48) goes unanswered, as a stack whose receive buffer holds only the longest request the device accepts drops the longer frame; the quantity to read is still checked",
        ),
        (
            Fault::VendorWriteNotApplied,
            "vendor-write-not-applied",
            "MDrive/LMD: an FC 0x42 write of a setting is acknowledged (echoed) but not stored: FC 0x41 still reads the old values",
        ),
        (
            Fault::ConformityLevelWrong,
            "conformity-level-wrong",
            "FC 43/14: every device identification answer declares conformity level 01 (basic, stream access only) whatever objects and access the drive serves",
        ),
        (
            Fault::Ds402EnableFromSwitchOnDisabled,
            "ds402-enable-from-switch-on-disabled",
            "SD2x: enable operation (control word 0x000F) is taken straight from switch on disabled to operation enabled, skipping the shutdown the DS402 state machine requires first",
        ),
        (
            Fault::SpeedWithoutEnable,
            "speed-without-enable",
            "SD2x: the actual speed ramps to the target speed also in switch on disabled, ready to switch on and switched on (the motor turns while operation is not enabled)",
        ),
        (
            Fault::WatchdogFromFirstWrite,
            "watchdog-from-first-write",
            "SD2x: rewriting the RxPDO watchdog does not restart it: it times out counted from the write that armed it, so a drive refreshed in time still trips",
        ),
        (
            Fault::ListedFunctionRefused,
            "listed-function-refused",
            "FC 04 (Read Input Registers) is answered with exception 01 (illegal function) although the drive's profile lists it (the SD2x manual, line 277)",
        ),
        (
            Fault::InputBitsReversed,
            "input-bits-reversed",
            "FC 02: the inputs asked for are packed in reverse order (the last one in bit 0 of the first byte), padding bits still 0",
        ),
        (
            Fault::ZeroCountPartial,
            "zero-count-partial",
            "SD2x FC 43: a read with byte count 0 is answered with the object's first byte only (byte count 1): neither the length error, nor the object, nor no data",
        ),
        (
            Fault::ByteCountOver4Served,
            "byte-count-over-4-served",
            "SD2x FC 43: a byte count above 4 (outside the layout's 0..4) is taken for the object's size and served",
        ),
        (
            Fault::UnusedDiagDataRefused02,
            "unused-diag-data-refused-02",
            "FC 08: a sub-function 0A-0F request whose unused data field is not 0000 is refused with 02 (ignoring it or 03 is admissible)",
        ),
        (
            Fault::QueryDataCut,
            "query-data-cut",
            "FC 08/00: a data field of other than the manual's 2 bytes is echoed cut or padded to 2 bytes",
        ),
        (
            Fault::UnusedDiagDataInconsistent,
            "unused-diag-data-inconsistent",
            "FC 08: a non-zero unused data field is ignored for sub-function 0B and refused with 03 for the others: each is admissible (sd2x-diagnostic-unused-data), the two together are not one choice",
        ),
        (
            Fault::LetterCaseBusy,
            "letter-case-busy",
            "MDrive/LMD FC 0x41/0x42: a known mnemonic named in lower case is answered with exception 06 (busy): neither served nor refused as unknown",
        ),
        (
            Fault::GroupWriteClears,
            "group-write-clears",
            "MDrive: OT/OL written while an I/O point is an input is acknowledged, and every output is cleared instead of set as written",
        ),
        (
            Fault::HomingNeverEnds,
            "homing-never-ends",
            "MDrive/LMD: a write of HM starts a homing that never ends: MV reads 1 from then on, and the axis never comes to rest",
        ),
        (
            Fault::ProgramAbsentSilent,
            "program-absent-silent",
            "MDrive/LMD: FC 0x42 EX gets no answer: the program neither runs nor is refused as absent with a code the error tables allow (mcode-example-program-absent)",
        ),
        (
            Fault::QuickStopBitClear,
            "quick-stop-bit-clear",
            "SD2x: the status word's bit 5 (quick stop) reads 0 in operation enabled, where the DS402 state table gives it as 1 (0 there reads as quick stop active)",
        ),
        (
            Fault::ZeroFieldsBusy,
            "zero-fields-busy",
            "SD2x FC 43: a control code with bits 0-6 set, a reserved field or an address offset not zero is answered with exception 06 (busy): neither the SDO error or the field ignored, nor 03",
        ),
        (
            Fault::TrailingBytes04,
            "trailing-bytes-04",
            "A request PDU longer than its function's layout (MBAP length or CRC consistent with it) is answered with exception 04 (server device failure), which App 7 keeps for a failure while performing a request: not 03, silence, a close, or the request served",
        ),
        (
            Fault::HighFunctionServed,
            "high-function-served",
            "A request whose function code is 128-255 (the codes of exception responses, App 4.1) is served as the function with the high bit cleared: 0x83 read as FC 03",
        ),
        (
            Fault::MeiTypeServed,
            "mei-type-served",
            "FC 43 with an MEI type the drive does not serve is answered with exception 04 (server device failure) instead of being refused as unsupported (01, 02 or 03)",
        ),
        (
            Fault::NulPaddingBusy,
            "nul-padding-busy",
            "MDrive/LMD FC 0x41/0x42: a known mnemonic padded with NUL instead of spaces is answered with exception 06 (busy): neither refused as unknown nor served (mnemonic-padding)",
        ),
        (
            Fault::EqualsSignBusy,
            "equals-sign-busy",
            "MDrive/LMD FC 0x42: a setting written without the '=' the manuals print before its values is answered with exception 06 (busy): neither refused as a bad parameter nor taken (setting-equals-sign)",
        ),
        (
            Fault::BlankControlBusy,
            "blank-control-busy",
            "MDrive/LMD FC 0x42: a parameter string with an ASCII control character a text parser reads as a blank (a tab) is answered with exception 06 (busy): neither refused as a bad parameter nor read with a space for it (parameter-blank-controls)",
        ),
        (
            Fault::SdoErrorOrderInconsistent,
            "sdo-error-order-inconsistent",
            "SD2x FC 43: SDO error codes answering a write go in the printed order, those answering a read little-endian: each order is admissible (sd2x-sdo-error-byte-order), the two together are not one choice",
        ),
        (
            Fault::ErrorRecordKept,
            "error-record-kept",
            "MDrive/LMD: ER holds the code of a past error (86) while EF reads 0 (no error condition now), and a write of 0 to ER is acknowledged but not applied: the record survives the clear the manual gives it (\"must be read or set to 0 to clear\")",
        ),
    ];

    /// The command-line name of the fault.
    pub fn name(self) -> &'static str {
        self.entry().map_or("?", |f| f.1)
    }

    /// What the fault does.
    pub fn description(self) -> &'static str {
        self.entry().map_or("?", |f| f.2)
    }

    /// The fault's row of [`Fault::ALL`].
    fn entry(self) -> Option<&'static (Fault, &'static str, &'static str)> {
        Self::ALL.iter().find(|f| f.0 == self)
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A fault name that is not one of [`Fault::ALL`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown fault `{name}`; known: {}", Fault::ALL.iter().map(|f| f.1).collect::<Vec<_>>().join(", "))]
pub struct UnknownFault {
    pub name: String,
}

impl FromStr for Fault {
    type Err = UnknownFault;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .iter()
            .find(|f| f.1 == s)
            .map(|f| f.0)
            .ok_or_else(|| UnknownFault {
                name: s.to_string(),
            })
    }
}

/// The faults active in one simulator.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FaultSet(pub BTreeSet<Fault>);

impl FaultSet {
    /// No fault: a conforming drive.
    pub fn none() -> Self {
        Self::default()
    }

    /// Exactly these faults.
    pub fn of(faults: &[Fault]) -> Self {
        Self(faults.iter().copied().collect())
    }

    /// True when `f` is active.
    pub fn has(&self, f: Fault) -> bool {
        self.0.contains(&f)
    }
}
