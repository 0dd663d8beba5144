//! tokio-modbus (an independent Rust client) against the simulator's servers: Modbus/TCP, RTU over TCP,
//! and RTU on a socat pty pair. Function codes tokio-modbus does not know (FC 08, FC 43) go as raw bytes.
//!
//! The value checks are the manuals' answers (golden frames): they hold once the drive models are in.

use engine::servers::{ServerConfig, ServerHandle};
use test_support::modbus_client::{self, answered};
use test_support::*;
use tokio::io::AsyncWriteExt;
use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;

/// The transports a fixture can use.
#[derive(Clone, Copy, Debug)]
enum Via {
    Tcp,
    RtuOverTcp,
    Pty,
}

/// A server for a profile and a tokio-modbus client connected to it. Drop order: client, server, pty.
struct Fixture {
    ctx: Context,
    server: ServerHandle,
    _pty: Option<PtyPair>,
}

/// `None` (after a printed skip notice) when the transport needs a tool that is missing.
async fn fixture(test: &str, profile_name: &str, via: Via) -> Option<Fixture> {
    let unit = profile(profile_name).device.default_unit;
    match via {
        Via::Tcp | Via::RtuOverTcp => {
            let server = serve(profile_name, &[], loopback_tcp_and_rtu()).await;
            let ctx = match via {
                Via::Tcp => {
                    let addr = server.tcp_addr().expect("tcp addr");
                    modbus_client::tcp(addr, unit).await
                }
                _ => {
                    let addr = server.rtu_over_tcp_addr().expect("rtu-over-tcp addr");
                    modbus_client::rtu_over_tcp(addr, unit).await
                }
            };
            Some(Fixture {
                ctx,
                server,
                _pty: None,
            })
        }
        Via::Pty => {
            let (pty, server, port) = on_a_pty(test, profile_name).await?;
            Some(Fixture {
                ctx: modbus_client::rtu_on(port, unit),
                server,
                _pty: Some(pty),
            })
        }
    }
}

/// An in-process server for `profile_name` on one end of a socat pty pair (19200 8N1), and the client side of
/// the other end; `None` (after a printed skip notice) without socat. In drop order last to first: the pty
/// outlives the server and the port.
async fn on_a_pty(
    test: &str,
    profile_name: &str,
) -> Option<(PtyPair, ServerHandle, tokio_serial::SerialStream)> {
    if !socat_or_skip(test) {
        return None;
    }
    let pty = PtyPair::start();
    let config = ServerConfig {
        serial: Some(serial_19200_8n1(&pty.a)),
        ..ServerConfig::default()
    };
    let server = serve(profile_name, &[], config).await;
    let port = open_pty_client(&pty.b);
    Some((pty, server, port))
}

/// One test per transport for `scenario(test, via)`, each named as given.
macro_rules! on_every_transport {
    ($scenario:ident: $tcp:ident, $rtu_over_tcp:ident, $pty:ident) => {
        #[tokio::test]
        async fn $tcp() {
            $scenario(stringify!($tcp), Via::Tcp).await;
        }

        #[tokio::test]
        async fn $rtu_over_tcp() {
            $scenario(stringify!($rtu_over_tcp), Via::RtuOverTcp).await;
        }

        #[tokio::test]
        async fn $pty() {
            $scenario(stringify!($pty), Via::Pty).await;
        }
    };
}

/// SD2x manual 6.1 then 6.3 through the client: the two RxPDO telegrams (golden sd2x/6.1), then nothing,
/// so the 500 ms watchdog they armed trips; register 2000 then reads the manual's 0x7038 (golden
/// sd2x/6.3/status-read, the 0x8784 read) by FC 04 and by FC 03 (the same map, manual line 327).
async fn sd2x_status_word(test: &str, via: Via) {
    let Some(mut f) = fixture(test, "sd2x", via).await else {
        return;
    };
    for (what, words) in [
        ("shutdown", SD2X_SHUTDOWN),
        ("enable operation", SD2X_ENABLE),
    ] {
        within(what, f.ctx.write_multiple_registers(3000, &words))
            .await
            .expect("transport")
            .unwrap_or_else(|e| panic!("6.1 {what}: exception {e:?}"));
    }
    // The watchdog runs on the drive's clock: poll the status word until it shows, bounded.
    let give_up = tokio::time::Instant::now() + SD2X_WATCHDOG_BOUND;
    let mut last = None;
    while tokio::time::Instant::now() < give_up {
        let r = within("FC 04 read 2000", f.ctx.read_input_registers(2000, 1)).await;
        last = Some(r.expect("transport"));
        if last == Some(Ok(vec![SD2X_STATUS_AFTER_61])) {
            break;
        }
        tokio::time::sleep(STATUS_POLL).await;
    }
    assert_eq!(
        last,
        Some(Ok(vec![SD2X_STATUS_AFTER_61])),
        "FC 04 status word after the 6.1 telegrams and the watchdog"
    );
    assert_eq!(
        answered(
            "FC 03 read 2000",
            f.ctx.read_holding_registers(2000, 1),
            "no exception"
        )
        .await,
        vec![SD2X_STATUS_AFTER_61],
        "FC 03 status word"
    );
    f.server.shutdown().await;
}

on_every_transport!(sd2x_status_word: tcp_sd2x_status_word, rtu_over_tcp_sd2x_status_word, rtu_pty_sd2x_status_word);

/// A function code the profile does not list is refused with exception 01 by every transport
/// (SD2x has no FC 05). This is the station's own check, so it holds with any model.
async fn sd2x_illegal_function(test: &str, via: Via) {
    let Some(mut f) = fixture(test, "sd2x", via).await else {
        return;
    };
    let r = within("FC 05", f.ctx.write_single_coil(0, true)).await;
    assert_eq!(
        r.expect("transport"),
        Err(ExceptionCode::IllegalFunction),
        "FC 05 on an SD2x"
    );
    f.server.shutdown().await;
}

on_every_transport!(sd2x_illegal_function: tcp_illegal_function_exception, rtu_over_tcp_illegal_function_exception, rtu_pty_illegal_function_exception);

/// SD2x manual 6.2, as corrected in corpus/golden/sd2x.toml: FC 43 / MEI 0x0D read of object 41
/// (temperature power stage) answers 170 (17.0 degC), data little-endian.
const FC43_TEMP_REQUEST: [u8; 15] = [
    0x01, 0x2B, 0x0D, 0x00, 0x00, 0x01, 0x00, 0x29, 0x00, 0x00, 0x00, 0x00, 0x02, 0x19, 0x56,
];
const FC43_TEMP_RESPONSE: [u8; 17] = [
    0x01, 0x2B, 0x0D, 0x00, 0x00, 0x01, 0x00, 0x29, 0x00, 0x00, 0x00, 0x00, 0x02, 0xAA, 0x00, 0xF5,
    0x0E,
];

#[tokio::test]
async fn rtu_pty_sd2x_fc43_temperature_golden() {
    let Some((_pty, server, mut port)) = on_a_pty(test_name!(), "sd2x").await else {
        return;
    };
    within("write", port.write_all(&FC43_TEMP_REQUEST))
        .await
        .expect("write");
    let reply = read_upto(&mut port, FC43_TEMP_RESPONSE.len()).await;
    assert_eq!(reply, FC43_TEMP_RESPONSE, "FC 43 object 41 over RTU");
    server.shutdown().await;
}

#[tokio::test]
async fn rtu_over_tcp_sd2x_fc43_temperature_golden() {
    let server = serve("sd2x", &[], loopback_tcp_and_rtu()).await;
    let mut s = connect(server.rtu_over_tcp_addr().unwrap()).await;
    within("write", s.write_all(&FC43_TEMP_REQUEST))
        .await
        .expect("write");
    let reply = read_upto(&mut s, FC43_TEMP_RESPONSE.len()).await;
    assert_eq!(
        reply, FC43_TEMP_RESPONSE,
        "FC 43 object 41 over RTU over TCP"
    );
    server.shutdown().await;
}

#[tokio::test]
async fn tcp_sd2x_fc43_temperature() {
    let server = serve("sd2x", &[], loopback_tcp_and_rtu()).await;
    // The RTU golden frame's PDU inside an MBAP header.
    let pdu = &FC43_TEMP_REQUEST[1..FC43_TEMP_REQUEST.len() - 2];
    let reply = tcp_exchange(server.tcp_addr().unwrap(), &tcp_adu(0x4321, 1, pdu)).await;
    let want_pdu = &FC43_TEMP_RESPONSE[1..FC43_TEMP_RESPONSE.len() - 2];
    assert_eq!(
        reply,
        tcp_adu(0x4321, 1, want_pdu),
        "FC 43 object 41 over TCP"
    );
    server.shutdown().await;
}

/// FC 08 sub-function 0 (return query data) echoes the request; answered by the station itself.
#[tokio::test]
async fn rtu_pty_diagnostics_echo() {
    let Some((_pty, server, mut port)) = on_a_pty(test_name!(), "sd2x").await else {
        return;
    };
    let req = rtu_adu(1, &[0x08, 0x00, 0x00, 0xA5, 0x37]);
    within("write", port.write_all(&req)).await.expect("write");
    assert_eq!(read_n(&mut port, req.len()).await, req, "FC 08/00 echo");
    server.shutdown().await;
}

/// MDrive manual FC 16 example (golden, corrected to 0x008B): write VM = 600000 (0x0009 0x27C0, high word
/// first) and read it back with FC 03.
#[tokio::test]
async fn tcp_mdrive_max_velocity_write_read() {
    let Some(mut f) = fixture(test_name!(), "mdrive", Via::Tcp).await else {
        return;
    };
    answered(
        "FC 16 write 0x008B",
        f.ctx.write_multiple_registers(0x008B, &[0x0009, 0x27C0]),
        "FC 16 accepted",
    )
    .await;
    let words = answered(
        "FC 03 read 0x008B",
        f.ctx.read_holding_registers(0x008B, 2),
        "FC 03 answered",
    )
    .await;
    assert_eq!(words, vec![0x0009, 0x27C0]);
    assert_eq!((u32::from(words[0]) << 16) | u32::from(words[1]), 600_000);
    f.server.shutdown().await;
}

/// The generic profile: a holding register and a coil written and read back.
async fn generic_round_trip(test: &str, via: Via) {
    let p = profile("generic");
    let (reg, coil) = rw_holding_and_coil(&p);
    let (addr, value) = reg.expect("generic profile has a writable holding register");
    let coil = coil.expect("generic profile has a writable coil");
    let Some(mut f) = fixture(test, "generic", via).await else {
        return;
    };
    answered(
        "FC 06",
        f.ctx.write_single_register(addr, value),
        "FC 06 accepted",
    )
    .await;
    assert_eq!(
        answered("FC 03", f.ctx.read_holding_registers(addr, 1), "FC 03").await,
        vec![value]
    );
    answered(
        "FC 16",
        f.ctx.write_multiple_registers(addr, &[value ^ 1]),
        "FC 16 accepted",
    )
    .await;
    assert_eq!(
        answered("FC 03", f.ctx.read_holding_registers(addr, 1), "FC 03").await,
        vec![value ^ 1]
    );
    for on in [true, false] {
        answered("FC 05", f.ctx.write_single_coil(coil, on), "FC 05 accepted").await;
        assert_eq!(
            answered("FC 01", f.ctx.read_coils(coil, 1), "FC 01").await,
            vec![on]
        );
    }
    answered(
        "FC 15",
        f.ctx.write_multiple_coils(coil, &[true]),
        "FC 15 accepted",
    )
    .await;
    assert_eq!(
        answered("FC 01", f.ctx.read_coils(coil, 1), "FC 01").await,
        vec![true]
    );
    f.server.shutdown().await;
}

on_every_transport!(generic_round_trip: tcp_generic_round_trip, rtu_over_tcp_generic_round_trip, rtu_pty_generic_round_trip);
