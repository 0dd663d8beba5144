//! tokio-modbus, an independent Rust client, connected to a drive under test: over Modbus/TCP, RTU over TCP,
//! and RTU on a serial port (a pty), every connect and call bounded in time ([`crate::STEP`]). The interop
//! tests (harness/cli/tests/interop/) ask the reference drives through it.
//!
//! A normal dependency here, not a dev-dependency of the tests: `cargo build` at the top level then resolves
//! the same features as `cargo test` (tokio-modbus's `async-trait` turns on a feature of `syn`, which every
//! derive macro and everything built on them would otherwise be built twice for), so CI's builds after the
//! tests and a newcomer's `cargo run` after `cargo test` reuse what the tests built.

use std::net::SocketAddr;

use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;

use crate::{STEP, connect, within};

/// A Modbus/TCP client of unit `unit` at `addr`.
pub async fn tcp(addr: SocketAddr, unit: u8) -> Context {
    tokio::time::timeout(STEP, tcp::connect_slave(addr, Slave(unit)))
        .await
        .expect("connect timed out")
        .expect("connect")
}

/// An RTU client of unit `unit` over a TCP connection to `addr` (RTU over TCP).
pub async fn rtu_over_tcp(addr: SocketAddr, unit: u8) -> Context {
    rtu::attach_slave(connect(addr).await, Slave(unit))
}

/// An RTU client of unit `unit` on an open serial port (see [`crate::open_pty_client`]).
pub fn rtu_on(port: tokio_serial::SerialStream, unit: u8) -> Context {
    rtu::attach_slave(port, Slave(unit))
}

/// A tokio-modbus call, bounded in time ([`within`], naming it `what`), that must reach the drive (else a
/// panic saying `transport`) and be answered without an exception (else a panic saying `exception`): the
/// answer.
pub async fn answered<T, X: std::fmt::Debug, E: std::fmt::Debug>(
    what: &str,
    call: impl std::future::Future<Output = Result<Result<T, X>, E>>,
    exception: &str,
) -> T {
    within(what, call)
        .await
        .expect("transport")
        .expect(exception)
}
