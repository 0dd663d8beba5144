//! The CiA 402 (DS402) drive profile as far as a Modbus drive exposes it: the control word's bits and the
//! commands that walk the state machine. The SD2x model implements it; the DS402 cases send these commands.

/// Control word bits and commands (0x6040).
pub mod control {
    /// Bit 0: switch on.
    pub const SWITCH_ON: u16 = 1 << 0;
    /// Bit 1: enable voltage.
    pub const ENABLE_VOLTAGE: u16 = 1 << 1;
    /// Bit 2: quick stop; 0 requests a quick stop.
    pub const QUICK_STOP: u16 = 1 << 2;
    /// Bit 3: enable operation.
    pub const ENABLE_OPERATION: u16 = 1 << 3;
    /// Bit 7: fault reset (acts on the rising edge).
    pub const FAULT_RESET: u16 = 1 << 7;
    /// Bit 8: halt.
    pub const HALT: u16 = 1 << 8;
    /// Command "shutdown" (example 6.1, line 1202).
    pub const CMD_SHUTDOWN: u16 = 0x0006;
    /// Command "switch on" (and "disable operation" from operation enabled).
    pub const CMD_SWITCH_ON: u16 = 0x0007;
    /// Command "switch on + enable operation" (example 6.1, line 1245).
    pub const CMD_ENABLE_OPERATION: u16 = 0x000F;
    /// Command "disable voltage".
    pub const CMD_DISABLE_VOLTAGE: u16 = 0x0000;
    /// Command "quick stop".
    pub const CMD_QUICK_STOP: u16 = 0x0002;
    /// Command "fault reset".
    pub const CMD_FAULT_RESET: u16 = 0x0080;
}

/// Status word (0x6041) coding of the CiA 402 state table.
pub mod status {
    /// The mask of the states in which the table leaves bit 5 (quick stop) open: not ready to switch on
    /// (`x0xx 0000`), switch on disabled (`x1xx 0000`), fault reaction active (`x0xx 1111`) and fault
    /// (`x0xx 1000`). In the other four states the table gives bit 5, and the mask is 0x006F.
    pub const BIT5_OPEN_MASK: u16 = 0x004F;

    /// True when `word` codes one of the states whose bit 5 the state table leaves open ([`BIT5_OPEN_MASK`]).
    pub fn bit5_open(word: u16) -> bool {
        matches!(word & BIT5_OPEN_MASK, 0x0000 | 0x0040 | 0x000F | 0x0008)
    }
}
