//! The proptest strategies of generated cases, over a profile's [`GenContext`].
//!
//! Strategies put the simplest choice first (index 0, quantity 1, the first alternative of a union), so
//! proptest's shrinking moves toward the first register, the smallest quantity, the plainest request.
//! The order of the alternatives and their weights fix which case a seed gives: changing either changes
//! every generated case id and the committed snapshots.

use proptest::prelude::*;
use proptest::strategy::{BoxedStrategy, Union};

use super::build::GenContext;
use codec::FunctionCode;

use super::spec::{
    Alter, Edge, FileGroup, MAX_BATCH_EXTRA, MAX_EXTEND, MAX_OPS, Op, Quantity, Req, Spec, Value,
};

/// The weighted alternatives of the request union, in union order.
/// The weighted strategies of the request kinds the profile supports.
#[derive(Default)]
struct Arms(Vec<(u32, BoxedStrategy<Req>)>);

impl Arms {
    /// Add `strategy` with `weight`.
    fn add(&mut self, weight: u32, strategy: impl Strategy<Value = Req> + 'static) {
        self.0.push((weight, strategy.boxed()));
    }
}

/// An address choice in a list of `n` addresses.
fn edge(n: usize) -> BoxedStrategy<Edge> {
    let n = n.clamp(1, usize::from(u16::MAX)) as u16;
    prop_oneof![
        Just(Edge::First),
        Just(Edge::Last),
        (0..n).prop_map(Edge::Entry)
    ]
    .boxed()
}

/// A quantity choice: the limit's boundaries twice as often as each out-of-range one.
fn quantity() -> BoxedStrategy<Quantity> {
    prop_oneof![
        2 => Just(Quantity::One),
        2 => Just(Quantity::Max),
        1 => Just(Quantity::Zero),
        1 => Just(Quantity::AboveMax),
        3 => any::<u16>().prop_map(Quantity::Any),
    ]
    .boxed()
}

/// A value choice: in range most of the time.
fn value() -> BoxedStrategy<Value> {
    prop_oneof![
        1 => Just(Value::Min),
        1 => Just(Value::Max),
        1 => Just(Value::BelowMin),
        1 => Just(Value::AboveMax),
        4 => any::<u32>().prop_map(Value::InRange),
        1 => any::<u32>().prop_map(Value::Raw),
    ]
    .boxed()
}

/// An index into a list of `n` entries.
fn index(n: usize) -> BoxedStrategy<u16> {
    (0..n.clamp(1, usize::from(u16::MAX)) as u16).boxed()
}

impl GenContext {
    /// Requests of every function code the profile supports, weighted toward the map's registers.
    pub fn req_strategy(&self) -> BoxedStrategy<Req> {
        let mut arms = Arms::default();
        // The order of these calls is the union's order.
        self.register_read_arms(&mut arms);
        self.register_write_arms(&mut arms);
        self.bit_arms(&mut arms);
        self.read_write_arm(&mut arms);
        self.diagnostic_and_id_arms(&mut arms);
        self.object_arms(&mut arms);
        self.vendor_arms(&mut arms);
        self.public_fc_arms(&mut arms);
        self.unsupported_arm(&mut arms);
        if arms.0.is_empty() {
            return Just(Req::Unsupported { fc: 0, len: 0 }).boxed();
        }
        Union::new_weighted(arms.0).boxed()
    }

    /// Alterations: PDU-level ones on every transport, frame-level ones tagged for their transport.
    pub fn alter_strategy(&self) -> BoxedStrategy<Alter> {
        let extra = proptest::collection::vec(self.req_strategy(), 1..=MAX_BATCH_EXTRA);
        prop_oneof![
            3 => any::<u16>().prop_map(|bit| Alter::BitFlip { bit }),
            2 => any::<u8>().prop_map(|keep| Alter::Truncate { keep }),
            2 => proptest::collection::vec(any::<u8>(), 1..=MAX_EXTEND)
                .prop_map(|bytes| Alter::Extend { bytes }),
            2 => prop_oneof![Just(1i8), Just(-1i8), any::<i8>()]
                .prop_map(|delta| Alter::ByteCount { delta }),
            1 => any::<u8>().prop_map(|to| Alter::FunctionSwap { to }),
            2 => any::<u8>().prop_map(|unit| Alter::WrongUnit { unit }),
            1 => Just(Alter::BadCrc),
            1 => prop_oneof![Just(1i8), Just(-1i8), any::<i8>()]
                .prop_map(|delta| Alter::MbapLength { delta }),
            1 => any::<u16>().prop_map(|id| Alter::ProtocolId { id }),
            1 => (any::<u8>(), any::<u16>()).prop_map(|(at, gap_us)| Alter::Split { at, gap_us }),
            1 => extra.prop_map(|extra| Alter::Batch { extra }),
        ]
        .boxed()
    }

    /// One operation: a request, sent as is 3 times in 5, altered otherwise.
    pub fn op_strategy(&self) -> BoxedStrategy<Op> {
        let alter = prop_oneof![3 => Just(Alter::None), 2 => self.alter_strategy()];
        (self.req_strategy(), alter, any::<bool>())
            .prop_map(|(req, alter, liveness)| Op {
                req,
                alter,
                liveness,
            })
            .boxed()
    }

    /// Generated cases: one operation 4 times in 5, else up to [`MAX_OPS`].
    pub fn spec_strategy(&self) -> BoxedStrategy<Spec> {
        let op = self.op_strategy();
        prop_oneof![
            4 => op.clone().prop_map(|o| vec![o]),
            1 => proptest::collection::vec(op, 1..=MAX_OPS),
        ]
        .prop_map(|ops| Spec { ops })
        .boxed()
    }

    /// FC 03/04: one register, a span, one half of a 32-bit register.
    fn register_read_arms(&self, arms: &mut Arms) {
        let reads = self.supports(FunctionCode::READ_HOLDING_REGISTERS)
            || self.supports(FunctionCode::READ_INPUT_REGISTERS);
        let (nr, nw) = (self.regs.len(), self.wide.len());
        if reads && nr > 0 {
            arms.add(
                4,
                (index(nr), any::<bool>())
                    .prop_map(|(reg, input)| Req::ReadRegister { reg, input }),
            );
            arms.add(
                2,
                (
                    edge(self.holding.len().max(self.input.len())),
                    quantity(),
                    any::<bool>(),
                )
                    .prop_map(|(at, quantity, input)| Req::ReadSpan {
                        at,
                        quantity,
                        input,
                    }),
            );
            if nw > 0 {
                arms.add(
                    1,
                    (index(nw), any::<bool>())
                        .prop_map(|(reg, second)| Req::ReadHalf { reg, second }),
                );
            }
        }
    }

    /// FC 06/16: one register, one half of a 32-bit register, a span.
    fn register_write_arms(&self, arms: &mut Arms) {
        let (nr, nw) = (self.regs.len(), self.wide.len());
        if (self.supports(FunctionCode::WRITE_SINGLE_REGISTER)
            || self.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS))
            && nr > 0
        {
            arms.add(
                4,
                (index(nr), value(), any::<bool>(), any::<bool>()).prop_map(
                    |(reg, value, fc06, check)| Req::WriteRegister {
                        reg,
                        value,
                        fc06,
                        check,
                    },
                ),
            );
            if nw > 0 {
                arms.add(
                    1,
                    (index(nw), any::<bool>(), any::<u16>(), any::<bool>()).prop_map(
                        |(reg, second, word, fc06)| Req::WriteHalf {
                            reg,
                            second,
                            word,
                            fc06,
                        },
                    ),
                );
            }
        }
        if self.supports(FunctionCode::WRITE_MULTIPLE_REGISTERS) && nr > 0 {
            arms.add(
                1,
                (edge(self.holding.len()), quantity(), any::<u16>())
                    .prop_map(|(at, quantity, word)| Req::WriteSpan { at, quantity, word }),
            );
        }
    }

    /// FC 01/02 reads, FC 05 and FC 15 writes.
    fn bit_arms(&self, arms: &mut Arms) {
        for (fc, discrete, n) in [
            (0x01, false, self.coils.len()),
            (0x02, true, self.discretes.len()),
        ] {
            if self.supports(fc) {
                arms.add(
                    1,
                    (edge(n), quantity()).prop_map(move |(at, quantity)| Req::ReadBits {
                        discrete,
                        at,
                        quantity,
                    }),
                );
            }
        }
        if self.supports(FunctionCode::WRITE_SINGLE_COIL) {
            arms.add(
                1,
                (index(self.coils.len()), any::<bool>(), any::<bool>())
                    .prop_map(|(coil, on, check)| Req::WriteCoil { coil, on, check }),
            );
        }
        if self.supports(FunctionCode::WRITE_MULTIPLE_COILS) {
            arms.add(
                1,
                (edge(self.coils.len()), quantity(), any::<u32>())
                    .prop_map(|(at, quantity, bits)| Req::WriteCoils { at, quantity, bits }),
            );
        }
    }

    /// FC 23.
    fn read_write_arm(&self, arms: &mut Arms) {
        let nr = self.regs.len();
        if self.supports(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS) && nr > 0 {
            arms.add(
                1,
                (edge(self.holding.len()), quantity(), index(nr), value()).prop_map(
                    |(at, quantity, reg, value)| Req::ReadWrite {
                        at,
                        quantity,
                        reg,
                        value,
                    },
                ),
            );
        }
    }

    /// FC 08 and FC 43/14.
    fn diagnostic_and_id_arms(&self, arms: &mut Arms) {
        if self.supports(FunctionCode::DIAGNOSTICS) {
            arms.add(
                1,
                (index(self.diagnostics.len() + 1), any::<u16>())
                    .prop_map(|(sub, data)| Req::Diagnostic { sub, data }),
            );
        }
        if self.supports(FunctionCode::ENCAPSULATED_INTERFACE) && !self.id_objects.is_empty() {
            arms.add(
                1,
                (0u8..6, any::<u8>()).prop_map(|(code, object)| Req::DeviceId { code, object }),
            );
        }
    }

    /// FC 43/13 reads and writes.
    fn object_arms(&self, arms: &mut Arms) {
        if self.supports(FunctionCode::ENCAPSULATED_INTERFACE) && !self.objects.is_empty() {
            let n = self.objects.len();
            arms.add(
                2,
                (index(n), proptest::option::weighted(0.25, 0u8..6))
                    .prop_map(|(obj, count)| Req::ObjectRead { obj, count }),
            );
            arms.add(
                1,
                (index(n), value()).prop_map(|(obj, value)| Req::ObjectWrite { obj, value }),
            );
        }
    }

    /// FC 65 and FC 66.
    fn vendor_arms(&self, arms: &mut Arms) {
        if self.supports(FunctionCode::VENDOR_READ) {
            arms.add(
                1,
                index(self.read_mnemonics.len() + 1)
                    .prop_map(|mnemonic| Req::VendorRead { mnemonic }),
            );
        }
        if self.supports(FunctionCode::VENDOR_WRITE) && !self.write_mnemonics.is_empty() {
            arms.add(
                1,
                index(self.write_mnemonics.len())
                    .prop_map(|mnemonic| Req::VendorWrite { mnemonic }),
            );
        }
    }

    /// FC 07, 0B/0C, 11, 14, 15, 16 and 18 (spec 6.7-6.18), each where the profile declares it and has what
    /// it acts on (coils, files, registers, queues); the writes (FC 15, FC 16, FC 07 with a pattern) are
    /// tagged so by the classifier, so that a campaign sends them only where writes are allowed.
    fn public_fc_arms(&self, arms: &mut Arms) {
        if self.supports(FunctionCode::READ_EXCEPTION_STATUS) {
            arms.add(
                1,
                proptest::option::of(any::<u8>())
                    .prop_map(|pattern| Req::ExceptionStatus { pattern }),
            );
        }
        if self.supports(FunctionCode::GET_COMM_EVENT_COUNTER)
            || self.supports(FunctionCode::GET_COMM_EVENT_LOG)
        {
            arms.add(
                1,
                (any::<bool>(), 0u8..3).prop_map(|(log, prelude)| Req::CommEvent { log, prelude }),
            );
        }
        if self.supports(FunctionCode::REPORT_SERVER_ID) {
            arms.add(1, Just(Req::ServerId));
        }
        let group = || {
            (index(self.files.len()), any::<u16>(), any::<u8>())
                .prop_map(|(file, record, len)| FileGroup { file, record, len })
        };
        if self.supports(FunctionCode::READ_FILE_RECORD) && !self.files.is_empty() {
            arms.add(
                1,
                (group(), proptest::option::of(group()))
                    .prop_map(|(first, second)| Req::FileRead { first, second }),
            );
        }
        if self.supports(FunctionCode::WRITE_FILE_RECORD)
            && self.supports(FunctionCode::READ_FILE_RECORD)
            && self.files.iter().any(|f| f.2)
        {
            arms.add(
                1,
                (group(), proptest::option::of(group()), any::<u16>()).prop_map(
                    |(first, second, word)| Req::FileWrite {
                        first,
                        second,
                        word,
                    },
                ),
            );
        }
        if self.supports(FunctionCode::MASK_WRITE_REGISTER) && !self.mask_regs.is_empty() {
            arms.add(
                1,
                (
                    index(self.mask_regs.len()),
                    any::<u16>(),
                    any::<u16>(),
                    any::<u16>(),
                )
                    .prop_map(|(reg, current, and, or)| Req::MaskWrite {
                        reg,
                        current,
                        and,
                        or,
                    }),
            );
        }
        if self.supports(FunctionCode::READ_FIFO_QUEUE) && !self.fifos.is_empty() {
            arms.add(
                1,
                index(self.fifos.len()).prop_map(|queue| Req::Fifo { queue }),
            );
        }
    }

    /// A function code the profile does not support.
    fn unsupported_arm(&self, arms: &mut Arms) {
        if !self.unsupported.is_empty() {
            arms.add(
                1,
                (index(self.unsupported.len()), 0u8..5)
                    .prop_map(|(fc, len)| Req::Unsupported { fc, len }),
            );
        }
    }
}
