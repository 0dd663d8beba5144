//! The modbus-harness engine: the case catalog, the runner, the oracle, the targets, the servers around the
//! reference drives, and the reports. One direction of flow:
//!
//! ```text
//! corpus (drives) -> cases -> runner -> targets -> observation -> oracle -> verdicts -> reports
//! ```
//!
//! To test a drive that lives in your own process from `cargo test`, start at [`api`]: implement
//! [`Device`], build a [`Session`], assert on the [`Results`].

pub mod api;
pub mod auto_profile;
pub mod campaign;
pub mod capture;
pub mod cases;
pub mod expect;
pub mod link;
pub mod liveness;
pub mod observe;
pub mod oracle;
pub mod probe;
pub mod readings;
pub mod reports;
pub mod restore;
pub mod runner;
pub mod servers;
pub mod session;
pub mod targets;
pub mod timing;

pub use api::{Device, Results, Session};
/// The safety classifier and the policy's terms, at the top as every layer uses them.
pub use cases::safety;
pub use cases::{Case, Compare, Level, Mutation, Outgoing, Step, Tag, Verdict};
pub use observe::{CaseResult, Dir, StepResult, WireEvent};
pub use targets::Received;
