//! RTU on a serial device or pty.

use std::path::PathBuf;

use tokio_serial::{DataBits, FlowControl, SerialPortBuilderExt, SerialStream, StopBits};

use codec::framer::{CharFormat, Parity, RtuTiming};

/// A serial line: device path and character format (RTU is always 8 data bits).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SerialConfig {
    pub path: PathBuf,
    pub baud: u32,
    pub parity: Parity,
    /// 1 or 2.
    pub stop_bits: u8,
}

impl SerialConfig {
    /// The character format of the line.
    pub fn format(&self) -> CharFormat {
        CharFormat {
            parity: self.parity,
            stop_bits: self.stop_bits,
        }
    }

    /// The RTU silences of the line.
    pub fn timing(&self) -> RtuTiming {
        RtuTiming::new(self.baud, self.format())
    }

    /// The usual short form, e.g. `19200 8N1`.
    pub fn describe(&self) -> String {
        let p = match self.parity {
            Parity::None => 'N',
            Parity::Even => 'E',
            Parity::Odd => 'O',
        };
        format!("{} 8{p}{}", self.baud, self.stop_bits)
    }
}

/// Open and configure the device. Must run inside a tokio runtime (the port registers with its reactor).
pub(crate) fn open(cfg: &SerialConfig) -> Result<SerialStream, tokio_serial::Error> {
    let parity = match cfg.parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Even => tokio_serial::Parity::Even,
        Parity::Odd => tokio_serial::Parity::Odd,
    };
    let stop_bits = if cfg.stop_bits >= 2 {
        StopBits::Two
    } else {
        StopBits::One
    };
    // serialport takes the path as a string; a non-UTF-8 path is passed lossily and fails to open by name.
    tokio_serial::new(cfg.path.to_string_lossy(), cfg.baud)
        .data_bits(DataBits::Eight)
        .parity(parity)
        .stop_bits(stop_bits)
        .flow_control(FlowControl::None)
        .open_native_async()
}
