//! The description of a generated case: a short sequence of requests drawn from the profile, each maybe
//! altered on purpose. Values come from the strategies (`strategy.rs`), from `arbitrary` in the fuzz
//! targets, or from a shrink; `build.rs` turns them into a [`Case`](crate::cases::Case).
//!
//! A [`Spec`] holds no profile data: indices into the profile's lists are taken modulo the lists' lengths
//! when the case is built, so every value (from a strategy, from `arbitrary`, from a shrink) builds a case.

/// At most this many operations in one generated case.
pub const MAX_OPS: usize = 3;
/// At most this many extra requests in one [`Alter::Batch`].
pub const MAX_BATCH_EXTRA: usize = 3;
/// At most this many bytes appended by [`Alter::Extend`].
pub const MAX_EXTEND: usize = 4;
/// Gap between the two pieces of a split request, at most (µs): well inside t1.5 at 19200 baud (859 µs).
pub const MAX_SPLIT_GAP_US: u64 = 100;
/// At most this many records in one generated group of file records.
pub const MAX_FILE_GROUP: u16 = 8;

/// One generated case: a short sequence of operations.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Spec {
    /// The operations, in order (1 to [`MAX_OPS`] are built; more are ignored).
    pub ops: Vec<Op>,
}

/// One request, how it is altered, and whether a liveness probe follows.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Op {
    /// The request as a conforming client would send it.
    pub req: Req,
    /// What is done to it on purpose.
    pub alter: Alter,
    /// After an altered request: check with a valid read that the drive still answers.
    pub liveness: bool,
}

/// An address choice: the first or last mapped address of a table, or the address of one entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Edge {
    First,
    Last,
    Entry(u16),
}

/// A quantity choice: the boundaries of the function's limit, or any value in 1..=limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Quantity {
    One,
    Max,
    Zero,
    AboveMax,
    Any(u16),
}

/// A value choice for a register or object: its range's boundaries, just outside them, or any value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Value {
    Min,
    Max,
    BelowMin,
    AboveMax,
    /// A value within the range (taken modulo its size).
    InRange(u32),
    /// Any value the register's width can carry.
    Raw(u32),
}

/// A request drawn from the profile. Indices pick entries of the profile's lists (modulo their length).
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Req {
    /// FC 03/04: one register (or pair) at its width.
    ReadRegister { reg: u16, input: bool },
    /// FC 03/04: one half of a 32-bit register.
    ReadHalf { reg: u16, second: bool },
    /// FC 03/04: a block from a boundary address with a boundary quantity.
    ReadSpan {
        at: Edge,
        quantity: Quantity,
        input: bool,
    },
    /// FC 16 (or FC 06): one register (or pair) at its width; `check` reads first, reads back and restores.
    WriteRegister {
        reg: u16,
        value: Value,
        fc06: bool,
        check: bool,
    },
    /// FC 06 or FC 16: one half of a 32-bit register.
    WriteHalf {
        reg: u16,
        second: bool,
        word: u16,
        fc06: bool,
    },
    /// FC 16: a block of registers, every one set to `word`.
    WriteSpan {
        at: Edge,
        quantity: Quantity,
        word: u16,
    },
    /// FC 01 (coils) or FC 02 (discrete inputs).
    ReadBits {
        discrete: bool,
        at: Edge,
        quantity: Quantity,
    },
    /// FC 05: one coil ON or OFF; `check` reads first, reads back and restores.
    WriteCoil { coil: u16, on: bool, check: bool },
    /// FC 15: a block of coils.
    WriteCoils {
        at: Edge,
        quantity: Quantity,
        bits: u32,
    },
    /// FC 23: read a block, write one register at its width.
    ReadWrite {
        at: Edge,
        quantity: Quantity,
        reg: u16,
        value: Value,
    },
    /// FC 08: a sub-function of the profile (or one it does not list).
    Diagnostic { sub: u16, data: u16 },
    /// FC 43/14: read device identification.
    DeviceId { code: u8, object: u8 },
    /// FC 43/13: read an object, with its size or another byte count.
    ObjectRead { obj: u16, count: Option<u8> },
    /// FC 43/13: write an object.
    ObjectWrite { obj: u16, value: Value },
    /// FC 65: read a vendor mnemonic (the last index: one the drive does not know).
    VendorRead { mnemonic: u16 },
    /// FC 66: write a vendor mnemonic with its manual example.
    VendorWrite { mnemonic: u16 },
    /// A function code the profile does not support, with a few data bytes.
    Unsupported { fc: u16, len: u8 },
    /// FC 07: read exception status; with `pattern`, the outputs the profile maps to coils set to it first
    /// (a write, put back after).
    ExceptionStatus { pattern: Option<u8> },
    /// FC 0B (FC 0C with `log`) after a prelude (`prelude` modulo 3: none, 08/0A clear counters, 08/01 FF 00
    /// restart), a successful read and two exception responses.
    CommEvent { log: bool, prelude: u8 },
    /// FC 11: report server id.
    ServerId,
    /// FC 14: one or two groups of file records.
    FileRead {
        first: FileGroup,
        second: Option<FileGroup>,
    },
    /// FC 15: one or two groups of a writable file set to `word`, `word + 1`, ...; read first, read back and
    /// put back.
    FileWrite {
        first: FileGroup,
        second: Option<FileGroup>,
        word: u16,
    },
    /// FC 16: mask write of a register first set to `current`; read back and put back.
    MaskWrite {
        reg: u16,
        current: u16,
        and: u16,
        or: u16,
    },
    /// FC 18: read a queue of the profile.
    Fifo { queue: u16 },
}

/// A group of file records: indices into the profile's files and their records, a length (taken modulo
/// what fits, at most [`MAX_FILE_GROUP`] records).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct FileGroup {
    pub file: u16,
    pub record: u16,
    pub len: u8,
}

/// What is done on purpose to a request.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Alter {
    /// Sent as is.
    None,
    /// One bit of the PDU inverted.
    BitFlip { bit: u16 },
    /// The PDU cut short.
    Truncate { keep: u8 },
    /// Bytes appended to the PDU.
    Extend { bytes: Vec<u8> },
    /// The byte count field off by `delta` (one byte too many where the PDU has none).
    ByteCount { delta: i8 },
    /// The function code replaced by another one the profile supports.
    FunctionSwap { to: u8 },
    /// Addressed to another unit id / slave address (0 = broadcast).
    WrongUnit { unit: u8 },
    /// RTU: the CRC inverted.
    BadCrc,
    /// Modbus/TCP: the MBAP length field off by `delta`; the connection is reopened after.
    MbapLength { delta: i8 },
    /// Modbus/TCP: a non-zero protocol id; the connection is reopened after.
    ProtocolId { id: u16 },
    /// The frame in two writes, split after `at` bytes, `gap_us` apart.
    Split { at: u8, gap_us: u16 },
    /// Modbus/TCP: more requests in the same write.
    Batch { extra: Vec<Req> },
}

impl Spec {
    /// The operations that are built (at most [`MAX_OPS`]).
    pub fn ops(&self) -> &[Op] {
        &self.ops[..self.ops.len().min(MAX_OPS)]
    }
}

impl Alter {
    /// The suffix of an operation's kind naming the alteration (`-bitflip`); empty for none.
    pub(super) fn label(&self) -> &'static str {
        match self {
            Alter::None => "",
            Alter::BitFlip { .. } => "-bitflip",
            Alter::Truncate { .. } => "-truncated",
            Alter::Extend { .. } => "-extended",
            Alter::ByteCount { .. } => "-bytecount",
            Alter::FunctionSwap { .. } => "-fcswap",
            Alter::WrongUnit { .. } => "-unit",
            Alter::BadCrc => "-badcrc",
            Alter::MbapLength { .. } => "-mbaplen",
            Alter::ProtocolId { .. } => "-protoid",
            Alter::Split { .. } => "-split",
            Alter::Batch { .. } => "-batch",
        }
    }
}
