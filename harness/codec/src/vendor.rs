//! IMS MDrive/LMD vendor function codes 0x41/0x42: MCode mnemonics carried reversed and space-padded.

use std::fmt;

/// A 4-byte mnemonic field as on the wire (e.g. `TR` travels as `20 20 52 54`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Mnemonic(pub [u8; 4]);

impl Mnemonic {
    /// The wire form of a mnemonic given in reading order (`"S13"` → `20 33 31 53`); None if longer than 4 bytes.
    pub fn from_name(name: &str) -> Option<Self> {
        let b = name.as_bytes();
        if b.is_empty() || b.len() > 4 {
            return None;
        }
        let mut w = [b' '; 4];
        for (i, c) in b.iter().rev().enumerate() {
            w[4 - b.len() + i] = *c;
        }
        Some(Self(w))
    }

    /// The mnemonic in reading order, padding removed (lossy for non-ASCII bytes).
    pub fn name(&self) -> String {
        let rev: Vec<u8> = self.0.iter().rev().copied().collect();
        String::from_utf8_lossy(&rev)
            .trim_end_matches(' ')
            .to_string()
    }
}

impl fmt::Display for Mnemonic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.name())
    }
}
