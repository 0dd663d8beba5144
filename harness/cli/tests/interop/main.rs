//! Interoperability: the harness and its reference drives against implementations nobody here wrote
//! (tokio-modbus, mbpoll, libmodbus, pymodbus), over Modbus/TCP, RTU on socat ptys and RTU over TCP.

mod independent;
mod libmodbus;
mod matrix;
mod matrix_clients;
mod mbpoll;
mod pymodbus;
mod server;
mod tokio_modbus;
