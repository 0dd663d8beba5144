//! The standard data-model function codes, implemented once for every drive model.
//!
//! FC 01/02 (read bits), 03/04 (read registers), 05/0F (write coils), 06/10/17 (write registers), 16 (mask
//! write a register) and 07 (the exception status outputs) have the same shape on every drive: check the
//! address range, validate the whole request, apply it all or nothing, answer. What differs is the storage
//! behind them and what a write sets off (a move, a watchdog restart, a DS402 transition). A model implements
//! [`DataModel`]: reading words and bits, planning a register write without applying it, committing the plan;
//! [`serve`] does the rest, in the order the MODBUS Application Protocol v1.1b3 (section 6) gives.

use codec::{ExceptionCode, Request, Response, bits};

use crate::choices::{Decision, Rejection, ids};

/// Which register table an access goes to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RegTable {
    /// FC 03/06/10/17.
    Holding,
    /// FC 04.
    Input,
}

/// Which single-bit table an access goes to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BitTable {
    /// FC 01/05/0F.
    Coils,
    /// FC 02.
    DiscreteInputs,
}

/// The storage and the write hooks of a drive, as the standard function codes see them.
pub trait DataModel {
    /// A validated register write, ready to be applied.
    type Plan;

    /// Read `quantity` registers of `table` from `address`; any address that cannot be read fails the read.
    fn read_registers(
        &self,
        table: RegTable,
        address: u16,
        quantity: u16,
    ) -> Result<Vec<u16>, Rejection>;

    /// True when a read of `quantity` registers from `address` starts or ends inside a 32-bit register
    /// (served by the reference drives; a freedom of the manuals).
    fn splits_register(&self, _table: RegTable, _address: u16, _quantity: u16) -> bool {
        false
    }

    /// Validate a holding-register write of `words` at `address` without changing anything.
    fn plan_write(&self, address: u16, words: &[u16]) -> Result<Self::Plan, Rejection>;

    /// Note that a freedom decided the answer being given.
    fn decided(&mut self, _freedom: Decision) {}

    /// Note the freedoms `request` is about whatever the answer to it (with [`DataModel::decided`]): called
    /// before it is served, where the model's reads cannot note anything.
    fn note_request(&mut self, _request: &Request) {}

    /// Apply a plan made by [`DataModel::plan_write`], with whatever the write sets off.
    fn commit(&mut self, plan: Self::Plan);

    /// Read `quantity` bits of `table` from `address`, packed LSB-first as FC 01/02 carry them.
    /// A drive without bits answers "illegal function".
    fn read_bits(
        &self,
        _table: BitTable,
        _address: u16,
        _quantity: u16,
    ) -> Result<Vec<u8>, Rejection> {
        Err(ExceptionCode::ILLEGAL_FUNCTION.into())
    }

    /// Write coils from `address` on (FC 05/0F), all or nothing.
    fn write_coils(&mut self, _address: u16, _states: &[bool]) -> Result<(), Rejection> {
        Err(ExceptionCode::ILLEGAL_FUNCTION.into())
    }

    /// Validate and apply a register write.
    fn write_registers(&mut self, address: u16, words: &[u16]) -> Result<(), Rejection> {
        let plan = self.plan_write(address, words)?;
        self.commit(plan);
        Ok(())
    }

    /// FC 07 (spec 6.7): the eight exception status outputs, output 0 in bit 0. A drive without them answers
    /// "illegal function".
    fn exception_status(&self) -> Result<u8, Rejection> {
        Err(ExceptionCode::ILLEGAL_FUNCTION.into())
    }

    /// The value FC 16 stores for `current` (spec 6.16, [`mask_write`]); a model overrides it only to break it
    /// (`Fault::MaskWriteWrong`).
    fn masked(&self, current: u16, and_mask: u16, or_mask: u16) -> u16 {
        mask_write(current, and_mask, or_mask)
    }
}

/// The end (exclusive) of `count` addresses from `address`, or exception 02 when they run past 0xFFFF: in the
/// state diagrams of spec section 6, starting address + quantity must be a valid address range.
pub(crate) fn range_end(address: u16, count: usize) -> Result<u32, ExceptionCode> {
    u32::try_from(count)
        .ok()
        .and_then(|n| u32::from(address).checked_add(n))
        .filter(|&e| e <= 0x1_0000)
        .ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)
}

/// Spec 6.16: Result = (Current Contents AND And_Mask) OR (Or_Mask AND (NOT And_Mask)). The AND mask keeps
/// the bits it sets, the OR mask sets the others.
pub fn mask_write(current: u16, and_mask: u16, or_mask: u16) -> u16 {
    (current & and_mask) | (or_mask & !and_mask)
}

/// Answer a data-model request (FC 01-07, 0F, 10, 16, 17) from `model`; `None` for any other request.
///
/// The station has already checked the quantities (exception 03) and the FC 05 value; what is left is the
/// model's address, access and value rules.
pub fn serve<M: DataModel + ?Sized>(model: &mut M, request: &Request) -> Option<Response> {
    let fc = request.function();
    let mut decided = None;
    let mut exc = |e: Rejection| {
        decided = e.freedom;
        Response::exception(fc, e.code)
    };
    if let Request::ReadHoldingRegisters { address, quantity }
    | Request::ReadInputRegisters { address, quantity } = request
    {
        let table = if matches!(request, Request::ReadInputRegisters { .. }) {
            RegTable::Input
        } else {
            RegTable::Holding
        };
        if model.splits_register(table, *address, *quantity) {
            model.decided(ids::PARTIAL_REGISTER_READ);
        }
    }
    model.note_request(request);
    let answer = Some(match request {
        Request::ReadCoils { address, quantity } => model
            .read_bits(BitTable::Coils, *address, *quantity)
            .map_or_else(exc, |data| Response::ReadCoils { data }),
        Request::ReadDiscreteInputs { address, quantity } => model
            .read_bits(BitTable::DiscreteInputs, *address, *quantity)
            .map_or_else(exc, |data| Response::ReadDiscreteInputs { data }),
        Request::ReadHoldingRegisters { address, quantity } => model
            .read_registers(RegTable::Holding, *address, *quantity)
            .map_or_else(exc, |values| Response::ReadHoldingRegisters { values }),
        Request::ReadInputRegisters { address, quantity } => model
            .read_registers(RegTable::Input, *address, *quantity)
            .map_or_else(exc, |values| Response::ReadInputRegisters { values }),
        Request::WriteSingleCoil { address, value } => {
            // Only 0xFF00/0x0000 get here unless the station's value check is faulted off; then any
            // non-zero value switches the coil on.
            match model.write_coils(*address, &[*value != 0]) {
                Ok(()) => Response::WriteSingleCoil {
                    address: *address,
                    value: *value,
                },
                Err(e) => exc(e),
            }
        }
        Request::WriteSingleRegister { address, value } => {
            match model.write_registers(*address, &[*value]) {
                Ok(()) => Response::WriteSingleRegister {
                    address: *address,
                    value: *value,
                },
                Err(e) => exc(e),
            }
        }
        Request::WriteMultipleCoils {
            address,
            quantity,
            data,
        } => match model.write_coils(*address, &bits::unpack(data, *quantity)) {
            Ok(()) => Response::WriteMultipleCoils {
                address: *address,
                quantity: *quantity,
            },
            Err(e) => exc(e),
        },
        Request::WriteMultipleRegisters { address, values } => {
            match model.write_registers(*address, values) {
                Ok(()) => Response::WriteMultipleRegisters {
                    address: *address,
                    // Echo the count written; the station caps it at 123, so it fits.
                    quantity: u16::try_from(values.len()).unwrap_or(u16::MAX),
                },
                Err(e) => exc(e),
            }
        }
        Request::ReadWriteMultipleRegisters {
            read_address,
            read_quantity,
            write_address,
            values,
        } => {
            // Spec 6.17: both address ranges are checked before anything happens, the write is done before the
            // read, and the read returns the registers as they are after the write.
            let answer = model
                .read_registers(RegTable::Holding, *read_address, *read_quantity)
                .and_then(|_| model.plan_write(*write_address, values))
                .and_then(|plan| {
                    model.commit(plan);
                    model.read_registers(RegTable::Holding, *read_address, *read_quantity)
                });
            answer.map_or_else(exc, |values| Response::ReadWriteMultipleRegisters {
                values,
            })
        }
        Request::ReadExceptionStatus => model
            .exception_status()
            .map_or_else(exc, |status| Response::ReadExceptionStatus { status }),
        Request::MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        } => {
            // Spec 6.16 (figure 26): the reference address must name a holding register the model can read and
            // write (02); the result goes through the model's own write path, so its hooks and range checks (03)
            // apply as to FC 06. The response, an echo, is sent after the register has been written.
            let answer = model
                .read_registers(RegTable::Holding, *address, 1)
                .and_then(|current| {
                    let current = current.first().copied().unwrap_or(0);
                    let result = model.masked(current, *and_mask, *or_mask);
                    model.write_registers(*address, &[result])
                });
            match answer {
                Ok(()) => Response::MaskWriteRegister {
                    address: *address,
                    and_mask: *and_mask,
                    or_mask: *or_mask,
                },
                Err(e) => exc(e),
            }
        }
        _ => return None,
    });
    if let Some(d) = decided {
        model.decided(d);
    }
    answer
}

#[cfg(test)]
mod tests {
    use super::mask_write;

    /// The example of spec 6.16 and its note: OR mask 0 only ANDs, AND mask 0 gives the OR mask.
    #[test]
    fn mask_write_follows_the_spec_example() {
        assert_eq!(mask_write(0x12, 0xF2, 0x25), 0x17);
        assert_eq!(mask_write(0x1234, 0x00FF, 0), 0x0034);
        assert_eq!(mask_write(0x1234, 0, 0xBEEF), 0xBEEF);
        assert_eq!(mask_write(0x1234, 0xFFFF, 0xBEEF), 0x1234);
    }
}
