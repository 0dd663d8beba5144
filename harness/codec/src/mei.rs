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
