//! Function code 0x2B payloads: SD2x CANopen object access (MEI 0x0D) and device identification (MEI 0x0E).

/// SD2x CANopen object access (FC 0x2B, MEI 0x0D), the same layout in both directions.
///
/// Layout after MEI: control, reserved, node id, index (BE), subindex, offset (BE), byte count (BE), data.
/// Data are little-endian, unlike everything else in Modbus.
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct CanOpenAccess {
    /// 0x00 read, 0x80 write (bit 7).
    pub control: u8,
    pub reserved: u8,
    pub node_id: u8,
    pub index: u16,
    pub subindex: u8,
    pub offset: u16,
    /// Bytes to read (read request) or carried (write request, read response).
    pub byte_count: u16,
    pub data: Vec<u8>,
}

impl CanOpenAccess {
    /// Control bit 7: the access writes.
    pub const WRITE: u8 = 0x80;

    /// True for a write access.
    pub fn is_write(&self) -> bool {
        self.control & Self::WRITE != 0
    }

    /// The data read little-endian (up to 4 bytes), as the SD2x manual specifies.
    pub fn value_le(&self) -> Option<u32> {
        if self.data.is_empty() || self.data.len() > 4 {
            return None;
        }
        let mut b = [0u8; 4];
        b[..self.data.len()].copy_from_slice(&self.data);
        Some(u32::from_le_bytes(b))
    }

    /// A read request of `byte_count` bytes of object `index`/`subindex`.
    pub fn read(node_id: u8, index: u16, subindex: u8, byte_count: u16) -> Self {
        Self {
            control: 0,
            reserved: 0,
            node_id,
            index,
            subindex,
            offset: 0,
            byte_count,
            data: Vec::new(),
        }
    }

    /// A write request carrying `data` (already little-endian).
    pub fn write(node_id: u8, index: u16, subindex: u8, data: Vec<u8>) -> Self {
        Self {
            control: Self::WRITE,
            reserved: 0,
            node_id,
            index,
            subindex,
            offset: 0,
            byte_count: data.len() as u16,
            data,
        }
    }
}

/// The form of an FC 0x2B / MEI 0x0D telegram (request or response, SDO errors aside) that the SD2x manual's
/// only example prints: the section 3.6 layout without its Reserved byte (control code, node id, index, ...).
/// The project's codec reads the layout; a drive may follow the example instead (freedom
/// `sd2x-fc43-reserved-byte`). These two functions convert one PDU between the forms; every other PDU is
/// left alone (`None`).
///
/// The layout's PDU (`2B 0D control 00 node ...`) without its Reserved byte, when that byte is 0x00.
pub fn canopen_without_reserved(pdu: &[u8]) -> Option<Vec<u8>> {
    match pdu {
        [0x2B, crate::codes::mei::CANOPEN, _, 0x00, ..] => {
            let mut short = Vec::with_capacity(pdu.len() - 1);
            short.extend_from_slice(&pdu[..3]);
            short.extend_from_slice(&pdu[4..]);
            Some(short)
        }
        _ => None,
    }
}

/// The example form's PDU (`2B 0D control node ...`) with the layout's Reserved byte (0x00) put back after
/// the control code.
pub fn canopen_with_reserved(pdu: &[u8]) -> Option<Vec<u8>> {
    match pdu {
        [0x2B, crate::codes::mei::CANOPEN, _, ..] => {
            let mut long = Vec::with_capacity(pdu.len() + 1);
            long.extend_from_slice(&pdu[..3]);
            long.push(0x00);
            long.extend_from_slice(&pdu[3..]);
            Some(long)
        }
        _ => None,
    }
}

/// One device identification object (FC 0x2B / MEI 0x0E).
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct DeviceIdObject {
    pub id: u8,
    pub value: Vec<u8>,
}

/// Read device identification response (FC 0x2B / MEI 0x0E).
#[derive(Clone, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct DeviceIdResponse {
    pub read_code: u8,
    pub conformity: u8,
    /// 0x00 no more objects, 0xFF more follow.
    pub more_follows: u8,
    pub next_object_id: u8,
    pub objects: Vec<DeviceIdObject>,
}

/// Read device id codes.
pub mod read_code {
    pub const BASIC: u8 = 0x01;
    pub const REGULAR: u8 = 0x02;
    pub const EXTENDED: u8 = 0x03;
    pub const INDIVIDUAL: u8 = 0x04;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SD2x manual's example request (line 1297, printed without the Reserved byte; its CRC 0x2BC1 is
    /// right for that form) and the corpus's corrected request are the same telegram in the two forms.
    #[test]
    fn the_two_forms_of_the_manuals_example_convert_into_each_other() {
        let printed = crate::parse_hex("2B 0D 00 01 00 29 00 00 00 00 02").unwrap();
        let layout = crate::parse_hex("2B 0D 00 00 01 00 29 00 00 00 00 02").unwrap();
        assert_eq!(
            canopen_with_reserved(&printed).as_deref(),
            Some(&layout[..])
        );
        assert_eq!(
            canopen_without_reserved(&layout).as_deref(),
            Some(&printed[..])
        );
        assert!(crate::Request::decode(&layout).is_ok());
        assert!(crate::Request::decode(&printed).is_err());
    }

    #[test]
    fn other_pdus_and_a_set_reserved_byte_are_left_alone() {
        assert_eq!(
            canopen_without_reserved(&[0x2B, 0x0D, 0x00, 0x01, 0x01]),
            None
        );
        assert_eq!(canopen_without_reserved(&[0x2B, 0x0E, 0x01, 0x00]), None);
        assert_eq!(canopen_with_reserved(&[0x03, 0x00, 0x00, 0x00, 0x01]), None);
        assert_eq!(canopen_with_reserved(&[0x2B, 0x0D]), None);
        assert_eq!(canopen_with_reserved(&[0xAB, 0xFF, 0x00, 0x06]), None);
    }
}
