//! Subcommand implementations: thin layers over the library.
pub mod decode;
pub mod fuzz;
pub mod golden;
pub mod probe;
pub mod restore;
pub mod run;
pub mod simulate;
