//! Coil and discrete-input bits as FC 01/02/0F carry them: packed LSB-first, the first bit in bit 0 of the
//! first byte, unused high bits of the last byte zero.

/// Pack `bits` LSB-first into `ceil(len / 8)` bytes.
pub fn pack(bits: &[bool]) -> Vec<u8> {
    let mut out = vec![0u8; bits.len().div_ceil(8)];
    for (i, _) in bits.iter().enumerate().filter(|(_, on)| **on) {
        out[i / 8] |= 1 << (i % 8);
    }
    out
}

/// The first `quantity` bits of `data`, LSB-first; bits past the end of `data` read as off.
pub fn unpack(data: &[u8], quantity: u16) -> Vec<bool> {
    (0..usize::from(quantity))
        .map(|i| data.get(i / 8).is_some_and(|b| b & (1 << (i % 8)) != 0))
        .collect()
}

/// Bytes needed for `quantity` bits.
pub fn byte_count(quantity: u16) -> usize {
    usize::from(quantity).div_ceil(8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pack_is_lsb_first_and_unpack_inverts_it() {
        let b = [true, false, true, true, false, false, false, false, true];
        assert_eq!(pack(&b), vec![0b0000_1101, 0b0000_0001]);
        assert_eq!(unpack(&pack(&b), 9), b.to_vec());
        assert_eq!(unpack(&[0xFF], 10)[8..], [false, false]);
        assert_eq!(byte_count(0), 0);
        assert_eq!(byte_count(8), 1);
        assert_eq!(byte_count(9), 2);
    }
}
