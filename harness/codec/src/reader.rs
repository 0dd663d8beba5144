//! A bounds-checked cursor over a byte slice: every read names its field so truncation errors are precise.

use super::error::{DecodeError, DecodeErrorKind};

/// Cursor over a PDU; never panics, never reads past the end.
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0 }
    }

    pub fn pos(&self) -> usize {
        self.pos
    }

    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    pub fn take(&mut self, field: &'static str, n: usize) -> Result<&'a [u8], DecodeError> {
        if self.remaining() < n {
            return Err(DecodeError::new(
                self.pos,
                DecodeErrorKind::Truncated {
                    field,
                    needed: n,
                    available: self.remaining(),
                },
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, DecodeError> {
        Ok(self.take(field, 1)?[0])
    }

    pub fn u16(&mut self, field: &'static str) -> Result<u16, DecodeError> {
        let b = self.take(field, 2)?;
        Ok(u16::from_be_bytes([b[0], b[1]]))
    }

    pub fn rest(&mut self) -> &'a [u8] {
        let s = &self.bytes[self.pos..];
        self.pos = self.bytes.len();
        s
    }

    /// Registers (big-endian u16) filling exactly `byte_count` bytes.
    pub fn registers(
        &mut self,
        field: &'static str,
        byte_count: usize,
    ) -> Result<Vec<u16>, DecodeError> {
        let b = self.take(field, byte_count)?;
        Ok(b.chunks_exact(2)
            .map(|c| u16::from_be_bytes([c[0], c[1]]))
            .collect())
    }

    /// Strict end: every byte must have been consumed.
    pub fn finish(&self) -> Result<(), DecodeError> {
        if self.remaining() != 0 {
            return Err(DecodeError::new(
                self.pos,
                DecodeErrorKind::TrailingBytes {
                    extra: self.remaining(),
                },
            ));
        }
        Ok(())
    }
}

pub(crate) fn mismatch(
    offset: usize,
    field: &'static str,
    declared: usize,
    expected: usize,
    basis: &'static str,
) -> DecodeError {
    DecodeError::new(
        offset,
        DecodeErrorKind::ByteCountMismatch {
            field,
            declared,
            expected,
            basis,
        },
    )
}
