//! A pymodbus client (tests/peers/pymodbus_client.py) against the simulator's servers: Modbus/TCP and RTU
//! on a socat pty pair. The value checks are the manuals' answers and hold once the drive models are in;
//! the exception checks are the station's own.

use test_support::peers::{Peer, Scenario, Via, run};
use test_support::test_name;

#[tokio::test]
async fn pymodbus_tcp_sd2x_status_word() {
    run(
        Peer::Pymodbus,
        Scenario::Sd2xStatusWord,
        Via::Tcp,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_rtu_pty_sd2x_status_word() {
    run(
        Peer::Pymodbus,
        Scenario::Sd2xStatusWord,
        Via::Pty,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_tcp_sd2x_illegal_function() {
    run(
        Peer::Pymodbus,
        Scenario::Sd2xIllegalFunction,
        Via::Tcp,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_rtu_pty_sd2x_illegal_function() {
    run(
        Peer::Pymodbus,
        Scenario::Sd2xIllegalFunction,
        Via::Pty,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_tcp_mdrive_max_velocity() {
    run(
        Peer::Pymodbus,
        Scenario::MdriveMaxVelocity,
        Via::Tcp,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_tcp_generic_round_trip() {
    run(
        Peer::Pymodbus,
        Scenario::GenericRoundTrip,
        Via::Tcp,
        test_name!(),
    )
    .await;
}

#[tokio::test]
async fn pymodbus_rtu_pty_generic_round_trip() {
    run(
        Peer::Pymodbus,
        Scenario::GenericRoundTrip,
        Via::Pty,
        test_name!(),
    )
    .await;
}
