//! RTU ADU: slave address + PDU + CRC-16/MODBUS (low byte first).

use super::error::{DecodeError, DecodeErrorKind, EncodeError};
use super::pdu::{Direction, MAX_PDU_LEN, Pdu};

/// Largest RTU ADU (address + 253-byte PDU + CRC).
pub const MAX_ADU_LEN: usize = 256;
/// Smallest RTU ADU (address, function code, CRC).
pub const MIN_ADU_LEN: usize = 4;
/// Slave address 0: broadcast.
pub const BROADCAST: u8 = 0;

const CRC16: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_MODBUS);

/// CRC-16/MODBUS of `bytes` (the value, transmitted low byte first).
pub fn crc16(bytes: &[u8]) -> u16 {
    CRC16.checksum(bytes)
}

/// True when the last two bytes of `frame` are the CRC of the rest.
pub fn crc_ok(frame: &[u8]) -> bool {
    frame.len() >= 3 && {
        let (body, c) = frame.split_at(frame.len() - 2);
        crc16(body) == u16::from_le_bytes([c[0], c[1]])
    }
}

/// An RTU ADU with its PDU still as bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RtuAdu<'a> {
    pub address: u8,
    pub pdu: &'a [u8],
    pub crc: u16,
}

/// Strictly decode exactly one RTU ADU: 4..=256 bytes and a matching CRC.
pub fn decode_adu(frame: &[u8]) -> Result<RtuAdu<'_>, DecodeError> {
    if frame.len() < MIN_ADU_LEN {
        return Err(DecodeError::new(
            frame.len(),
            DecodeErrorKind::RtuShort { len: frame.len() },
        ));
    }
    if frame.len() > MAX_ADU_LEN {
        return Err(DecodeError::new(
            MAX_ADU_LEN,
            DecodeErrorKind::RtuTooLong { len: frame.len() },
        ));
    }
    let (body, c) = frame.split_at(frame.len() - 2);
    let received = u16::from_le_bytes([c[0], c[1]]);
    let expected = crc16(body);
    if expected != received {
        return Err(DecodeError::new(
            frame.len() - 2,
            DecodeErrorKind::Crc { expected, received },
        ));
    }
    Ok(RtuAdu {
        address: body[0],
        pdu: &body[1..],
        crc: received,
    })
}

/// Strictly decode one RTU ADU and its PDU in the given direction.
pub fn decode(frame: &[u8], dir: Direction) -> Result<(u8, Pdu), DecodeError> {
    let adu = decode_adu(frame)?;
    let pdu = Pdu::decode(adu.pdu, dir).map_err(|e| e.shifted(1))?;
    Ok((adu.address, pdu))
}

/// Frame an already-encoded PDU: address + PDU + CRC.
pub fn encode_adu(address: u8, pdu: &[u8], out: &mut Vec<u8>) -> Result<(), EncodeError> {
    if pdu.len() > MAX_PDU_LEN {
        return Err(EncodeError::TooLong {
            field: "PDU",
            len: pdu.len(),
            max: MAX_PDU_LEN,
        });
    }
    let start = out.len();
    out.push(address);
    out.extend_from_slice(pdu);
    let crc = crc16(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// Encode a typed PDU as an RTU ADU.
pub fn encode(address: u8, pdu: &Pdu) -> Result<Vec<u8>, EncodeError> {
    let mut body = Vec::with_capacity(16);
    pdu.encode(&mut body)?;
    let mut out = Vec::with_capacity(body.len() + 3);
    encode_adu(address, &body, &mut out)?;
    Ok(out)
}
