//! Function and exception codes as newtypes: vendor values are normal in Modbus, so these are open sets.

use std::fmt;

/// A code newtype: a byte with its own type (open: any byte is one), its byte both ways.
macro_rules! byte_newtype {
    ($(#[$doc:meta])* $t:ident) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
        #[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
        #[cfg_attr(
            feature = "serde",
            derive(serde::Serialize, serde::Deserialize),
            serde(transparent)
        )]
        pub struct $t(pub u8);

        impl From<u8> for $t {
            fn from(b: u8) -> Self {
                Self(b)
            }
        }

        impl From<$t> for u8 {
            fn from(c: $t) -> Self {
                c.0
            }
        }
    };
}

byte_newtype!(
    /// A Modbus function code byte (the high bit set marks an exception response).
    FunctionCode
);
byte_newtype!(
    /// A Modbus exception code byte.
    ExceptionCode
);

impl FunctionCode {
    pub const READ_COILS: Self = Self(0x01);
    pub const READ_DISCRETE_INPUTS: Self = Self(0x02);
    pub const READ_HOLDING_REGISTERS: Self = Self(0x03);
    pub const READ_INPUT_REGISTERS: Self = Self(0x04);
    pub const WRITE_SINGLE_COIL: Self = Self(0x05);
    pub const WRITE_SINGLE_REGISTER: Self = Self(0x06);
    pub const READ_EXCEPTION_STATUS: Self = Self(0x07);
    pub const DIAGNOSTICS: Self = Self(0x08);
    pub const GET_COMM_EVENT_COUNTER: Self = Self(0x0B);
    pub const GET_COMM_EVENT_LOG: Self = Self(0x0C);
    pub const WRITE_MULTIPLE_COILS: Self = Self(0x0F);
    pub const WRITE_MULTIPLE_REGISTERS: Self = Self(0x10);
    pub const REPORT_SERVER_ID: Self = Self(0x11);
    pub const READ_FILE_RECORD: Self = Self(0x14);
    pub const WRITE_FILE_RECORD: Self = Self(0x15);
    pub const MASK_WRITE_REGISTER: Self = Self(0x16);
    pub const READ_WRITE_MULTIPLE_REGISTERS: Self = Self(0x17);
    pub const READ_FIFO_QUEUE: Self = Self(0x18);
    pub const ENCAPSULATED_INTERFACE: Self = Self(0x2B);
    /// IMS MDrive/LMD vendor code: read a parameter by MCode mnemonic.
    pub const VENDOR_READ: Self = Self(0x41);
    /// IMS MDrive/LMD vendor code: write a parameter or run a command by MCode mnemonic.
    pub const VENDOR_WRITE: Self = Self(0x42);

    /// True when the high bit marks an exception response.
    pub fn is_exception(self) -> bool {
        self.0 & 0x80 != 0
    }

    /// The exception form of this code (0x80 | code).
    pub fn exception(self) -> Self {
        Self(self.0 | 0x80)
    }

    /// The request code an exception response answers.
    pub fn without_exception_bit(self) -> Self {
        Self(self.0 & 0x7F)
    }

    /// The largest quantity the MODBUS Application Protocol v1.1b3 allows in a request of this function
    /// (section 6: FC 01/02 2000 bits, FC 03/04 125 registers, FC 0F 1968 coils, FC 10 123 registers, the read
    /// part of FC 17 125 registers); `None` for functions without a quantity.
    pub fn max_quantity(self) -> Option<u16> {
        Some(match self {
            Self::READ_COILS | Self::READ_DISCRETE_INPUTS => 2000,
            Self::READ_HOLDING_REGISTERS | Self::READ_INPUT_REGISTERS => 125,
            Self::WRITE_MULTIPLE_COILS => 0x7B0,
            Self::WRITE_MULTIPLE_REGISTERS => 123,
            Self::READ_WRITE_MULTIPLE_REGISTERS => 125,
            _ => return None,
        })
    }

    /// The largest write quantity of FC 17 (section 6.17: 121 registers).
    pub const MAX_READ_WRITE_WRITE_QUANTITY: u16 = 121;

    /// The name of a known function code.
    pub fn name(self) -> Option<&'static str> {
        Some(match self.without_exception_bit().0 {
            0x01 => "Read Coils",
            0x02 => "Read Discrete Inputs",
            0x03 => "Read Holding Registers",
            0x04 => "Read Input Registers",
            0x05 => "Write Single Coil",
            0x06 => "Write Single Register",
            0x07 => "Read Exception Status",
            0x08 => "Diagnostics",
            0x0B => "Get Comm Event Counter",
            0x0C => "Get Comm Event Log",
            0x0F => "Write Multiple Coils",
            0x10 => "Write Multiple Registers",
            0x11 => "Report Server ID",
            0x14 => "Read File Record",
            0x15 => "Write File Record",
            0x16 => "Mask Write Register",
            0x17 => "Read/Write Multiple Registers",
            0x18 => "Read FIFO Queue",
            0x2B => "Encapsulated Interface Transport",
            0x41 => "Vendor Read (MCode mnemonic)",
            0x42 => "Vendor Write (MCode mnemonic)",
            _ => return None,
        })
    }
}

impl fmt::Display for FunctionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(n) if self.is_exception() => write!(f, "0x{:02X} (exception: {n})", self.0),
            Some(n) => write!(f, "0x{:02X} ({n})", self.0),
            None => write!(f, "0x{:02X}", self.0),
        }
    }
}

impl ExceptionCode {
    pub const ILLEGAL_FUNCTION: Self = Self(0x01);
    pub const ILLEGAL_DATA_ADDRESS: Self = Self(0x02);
    pub const ILLEGAL_DATA_VALUE: Self = Self(0x03);
    pub const SERVER_DEVICE_FAILURE: Self = Self(0x04);
    pub const ACKNOWLEDGE: Self = Self(0x05);
    pub const SERVER_DEVICE_BUSY: Self = Self(0x06);
    pub const MEMORY_PARITY_ERROR: Self = Self(0x08);
    pub const GATEWAY_PATH_UNAVAILABLE: Self = Self(0x0A);
    pub const GATEWAY_TARGET_FAILED: Self = Self(0x0B);
    /// SD2x FC 43/0x0D: an extended exception (SDO error) follows.
    pub const EXTENDED: Self = Self(0xFF);

    /// True for 0A and 0B, the codes a gateway answers for the device behind it (App 7).
    pub fn is_gateway(self) -> bool {
        self == Self::GATEWAY_PATH_UNAVAILABLE || self == Self::GATEWAY_TARGET_FAILED
    }

    /// The name of a known exception code.
    pub fn name(self) -> Option<&'static str> {
        Some(match self.0 {
            0x01 => "Illegal Function",
            0x02 => "Illegal Data Address",
            0x03 => "Illegal Data Value",
            0x04 => "Server Device Failure",
            0x05 => "Acknowledge",
            0x06 => "Server Device Busy",
            0x08 => "Memory Parity Error",
            0x0A => "Gateway Path Unavailable",
            0x0B => "Gateway Target Device Failed To Respond",
            0xFF => "Extended Exception",
            _ => return None,
        })
    }
}

impl fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(n) => write!(f, "0x{:02X} ({n})", self.0),
            None => write!(f, "0x{:02X}", self.0),
        }
    }
}

/// MEI types of function code 0x2B.
pub mod mei {
    /// CANopen general reference (SD2x object dictionary access).
    pub const CANOPEN: u8 = 0x0D;
    /// Read device identification.
    pub const DEVICE_ID: u8 = 0x0E;
}

/// FC 08 sub-function codes: the public ones of MODBUS Application Protocol v1.1b3 section 6.8.1 (their
/// behaviour on a serial line is in MODBUS over Serial Line v1.02 and the same section). 05-09 and 13 are
/// reserved, as is everything from 0x15 up (Annex A).
pub mod diag {
    pub const RETURN_QUERY_DATA: u16 = 0x00;
    pub const RESTART_COMMUNICATIONS: u16 = 0x01;
    pub const RETURN_DIAGNOSTIC_REGISTER: u16 = 0x02;
    pub const CHANGE_ASCII_DELIMITER: u16 = 0x03;
    pub const FORCE_LISTEN_ONLY: u16 = 0x04;
    pub const CLEAR_COUNTERS: u16 = 0x0A;
    pub const BUS_MESSAGE_COUNT: u16 = 0x0B;
    pub const BUS_COMM_ERROR_COUNT: u16 = 0x0C;
    pub const BUS_EXCEPTION_ERROR_COUNT: u16 = 0x0D;
    pub const SERVER_MESSAGE_COUNT: u16 = 0x0E;
    pub const SERVER_NO_RESPONSE_COUNT: u16 = 0x0F;
    pub const SERVER_NAK_COUNT: u16 = 0x10;
    pub const SERVER_BUSY_COUNT: u16 = 0x11;
    pub const BUS_CHARACTER_OVERRUN_COUNT: u16 = 0x12;
    pub const CLEAR_OVERRUN: u16 = 0x14;

    /// 08/01 data: restart and clear the communications event log too (00 00 keeps it).
    pub const RESTART_CLEAR_LOG: u16 = 0xFF00;

    /// The name section 6.8.1 gives a public sub-function.
    pub fn name(sub_function: u16) -> Option<&'static str> {
        Some(match sub_function {
            RETURN_QUERY_DATA => "Return Query Data",
            RESTART_COMMUNICATIONS => "Restart Communications Option",
            RETURN_DIAGNOSTIC_REGISTER => "Return Diagnostic Register",
            CHANGE_ASCII_DELIMITER => "Change ASCII Input Delimiter",
            FORCE_LISTEN_ONLY => "Force Listen Only Mode",
            CLEAR_COUNTERS => "Clear Counters and Diagnostic Register",
            BUS_MESSAGE_COUNT => "Return Bus Message Count",
            BUS_COMM_ERROR_COUNT => "Return Bus Communication Error Count",
            BUS_EXCEPTION_ERROR_COUNT => "Return Bus Exception Error Count",
            SERVER_MESSAGE_COUNT => "Return Server Message Count",
            SERVER_NO_RESPONSE_COUNT => "Return Server No Response Count",
            SERVER_NAK_COUNT => "Return Server NAK Count",
            SERVER_BUSY_COUNT => "Return Server Busy Count",
            BUS_CHARACTER_OVERRUN_COUNT => "Return Bus Character Overrun Count",
            CLEAR_OVERRUN => "Clear Overrun Counter and Flag",
            _ => return None,
        })
    }
}

/// The event bytes of the communications event log (FC 0C, MODBUS Application Protocol v1.1b3 section 6.10,
/// "What the Event Bytes Contain").
pub mod event {
    /// Receive event: bit 7 set, stored when a query arrives, before it is processed.
    pub const RECEIVE: u8 = 0x80;
    /// Receive event bit 1: communication error.
    pub const RECEIVE_COMM_ERROR: u8 = 0x02;
    /// Receive event bit 4: character overrun.
    pub const RECEIVE_OVERRUN: u8 = 0x10;
    /// Receive event bit 5, send event bit 5: currently in listen only mode.
    pub const LISTEN_ONLY: u8 = 0x20;
    /// Receive event bit 6: broadcast received.
    pub const RECEIVE_BROADCAST: u8 = 0x40;
    /// Send event: bit 7 clear, bit 6 set, stored when the processing of a request ends (whether a normal
    /// response, an exception or nothing was sent).
    pub const SEND: u8 = 0x40;
    /// Send event bit 0: read exception sent (exception codes 1-3).
    pub const SEND_READ_EXCEPTION: u8 = 0x01;
    /// Send event bit 1: server abort exception sent (exception code 4).
    pub const SEND_ABORT_EXCEPTION: u8 = 0x02;
    /// Send event bit 2: server busy exception sent (exception codes 5-6).
    pub const SEND_BUSY_EXCEPTION: u8 = 0x04;
    /// Send event bit 3: server program NAK exception sent (exception code 7).
    pub const SEND_NAK_EXCEPTION: u8 = 0x08;
    /// Send event bit 4: write timeout error occurred.
    pub const SEND_WRITE_TIMEOUT: u8 = 0x10;
    /// The server entered listen only mode (08/04). The section's own example reads event 20 hex as "entered
    /// the Listen Only Mode"; the definition above it says 04 hex, which is what is used (20 hex is none of the
    /// four event types: neither bit 7 of a receive event nor bit 6 of a send event, nor 04 or 00).
    pub const ENTERED_LISTEN_ONLY: u8 = 0x04;
    /// The server restarted its communications port (08/01). With data FF 00 ("Stop on Error") the log is
    /// cleared first, so this event is then the only one.
    pub const COMM_RESTART: u8 = 0x00;
    /// The log holds at most this many event bytes ("0-64 bytes").
    pub const LOG_CAPACITY: usize = 64;
}

/// FC 18: a FIFO queue answers at most 31 queued registers (MODBUS Application Protocol v1.1b3 section 6.18).
pub const MAX_FIFO_COUNT: u16 = 31;

/// FC 14/15 file records (MODBUS Application Protocol v1.1b3 sections 6.14, 6.15).
pub mod file {
    /// The only reference type the spec defines ("must be specified as 6").
    pub const REFERENCE_TYPE: u8 = 6;
    /// Records in a file: 0x0000 to 0x270F.
    pub const RECORDS_PER_FILE: u32 = 10_000;
    /// Bytes of one FC 14 sub-request (reference type, file, record, length) and of an FC 15 sub-request
    /// before its data.
    pub const SUB_REQUEST_LEN: usize = 7;
}
