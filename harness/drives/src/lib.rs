//! Drives: profiles (register maps, limits, mnemonics, object dictionaries), the golden frames of the
//! manuals, and the executable reference drive models with the wire-level station and injected faults.
//!
//! Sans-IO: no sockets, no clock of its own (time is passed in), no tokio.

pub mod choices;
pub mod corpus;
pub mod ds402;
pub mod faults;
pub mod golden;
pub mod models;
pub mod profile;
pub mod requirements;
pub mod station;
pub mod tell;

pub use choices::{Choices, Decision, Rejection};
pub use faults::{Fault, FaultSet};
pub use models::{BoxClone, DriveModel, build, build_with};
pub use station::{Counters, RtuPort, Station, TcpConn, Wire};
