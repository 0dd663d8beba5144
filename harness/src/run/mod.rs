//! The conformance run: case catalog, safety policy, runner, oracle and verdicts.

pub mod campaign;
pub mod case;
pub mod catalog;
pub mod expect;
pub mod generated;
pub mod observe;
pub mod oracle;
pub mod probe;
pub mod runner;
pub mod session;
pub mod shrink;

pub use case::{Case, Compare, Level, Mutation, Send, Step, Tag, Verdict};
pub use observe::{CaseResult, Dir, Outcome, StepResult, WireEvent};
