//! A toy drive firmware: 8 holding registers and 8 coils behind a Modbus request handler. It knows nothing
//! about the harness; `tests/conformance.rs` plugs [`Toy::handle_pdu`] into it.

/// A bug to build into the firmware, for the test that shows the harness catches it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bug {
    /// FC 03 with a quantity of 0 answers an empty read instead of exception 03.
    ReadsZeroRegisters,
    /// A read past the last register answers exception 03 instead of 02 (illegal data address).
    WrongExceptionForBadAddress,
}

/// The drive's state and its request handler.
#[derive(Debug, Default)]
pub struct Toy {
    pub registers: [u16; 8],
    pub coils: [bool; 8],
    pub bug: Option<Bug>,
}

const ILLEGAL_FUNCTION: u8 = 0x01;
const ILLEGAL_ADDRESS: u8 = 0x02;
const ILLEGAL_VALUE: u8 = 0x03;

impl Toy {
    /// Answer one request PDU (function code first) with a response PDU; `None` answers nothing.
    pub fn handle_pdu(&mut self, pdu: &[u8]) -> Option<Vec<u8>> {
        let fc = *pdu.first()?;
        match self.serve(fc, pdu) {
            Ok(response) => Some(response),
            Err(code) => Some(vec![fc | 0x80, code]),
        }
    }

    fn serve(&mut self, fc: u8, pdu: &[u8]) -> Result<Vec<u8>, u8> {
        let word = |i: usize| u16::from_be_bytes([pdu[i], pdu[i + 1]]);
        // Every function here starts with an address and a quantity or value (4 bytes).
        if !matches!(fc, 0x01 | 0x03 | 0x05 | 0x06 | 0x0F | 0x10) {
            return Err(ILLEGAL_FUNCTION);
        }
        if pdu.len() < 5 {
            return Err(ILLEGAL_VALUE);
        }
        let (addr, n) = (word(1) as usize, word(3) as usize);
        match fc {
            0x01 | 0x03 => {
                let max = if fc == 0x01 { 2000 } else { 125 };
                let zero_ok = self.bug == Some(Bug::ReadsZeroRegisters) && fc == 0x03;
                if pdu.len() != 5 || n > max || (n == 0 && !zero_ok) {
                    return Err(ILLEGAL_VALUE);
                }
                if addr + n > 8 {
                    return Err(match self.bug {
                        Some(Bug::WrongExceptionForBadAddress) => ILLEGAL_VALUE,
                        _ => ILLEGAL_ADDRESS,
                    });
                }
                if fc == 0x03 {
                    let mut out = vec![fc, (2 * n) as u8];
                    for r in &self.registers[addr..addr + n] {
                        out.extend(r.to_be_bytes());
                    }
                    return Ok(out);
                }
                let mut bytes = vec![0u8; n.div_ceil(8)];
                for (i, _) in self.coils[addr..addr + n]
                    .iter()
                    .enumerate()
                    .filter(|c| *c.1)
                {
                    bytes[i / 8] |= 1 << (i % 8);
                }
                Ok([vec![fc, bytes.len() as u8], bytes].concat())
            }
            0x05 | 0x06 => {
                let value = word(3);
                if pdu.len() != 5 || (fc == 0x05 && value != 0xFF00 && value != 0x0000) {
                    return Err(ILLEGAL_VALUE);
                }
                if addr >= 8 {
                    return Err(ILLEGAL_ADDRESS);
                }
                if fc == 0x05 {
                    self.coils[addr] = value == 0xFF00;
                } else {
                    self.registers[addr] = value;
                }
                Ok(pdu.to_vec())
            }
            _ => {
                // 0x0F and 0x10: address, quantity, byte count, values.
                let (max, byte_count) = if fc == 0x0F {
                    (0x7B0, n.div_ceil(8))
                } else {
                    (0x7B, 2 * n)
                };
                if n == 0 || n > max || pdu.get(5) != Some(&(byte_count as u8)) {
                    return Err(ILLEGAL_VALUE);
                }
                if pdu.len() != 6 + byte_count {
                    return Err(ILLEGAL_VALUE);
                }
                if addr + n > 8 {
                    return Err(ILLEGAL_ADDRESS);
                }
                for i in 0..n {
                    if fc == 0x0F {
                        self.coils[addr + i] = pdu[6 + i / 8] & (1 << (i % 8)) != 0;
                    } else {
                        self.registers[addr + i] = word(6 + 2 * i);
                    }
                }
                Ok(pdu[..5].to_vec())
            }
        }
    }
}
