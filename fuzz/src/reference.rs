//! The reference drives the drive targets (`response_validation`, `drive_model`, `differential`) and the
//! seeds use: the embedded profiles, fault-free or faulted stations, framing, and the checks of a reply.

use std::cell::RefCell;
use std::sync::OnceLock;
use std::time::Duration;

use codec::framer::RtuTiming;
use codec::{
    CharFormat, Direction, Framing, FunctionCode, Parity, Pdu, Response, decode_any, hex_spaced,
    rtu, tcp,
};
use drives::corpus::Corpus;
use drives::profile::Profile;
use drives::{FaultSet, Station, TcpConn, Wire};
use engine::cases::catalog;

/// The reference drives the drive targets exercise, in the order of their selector bits.
pub const DRIVES: [&str; 4] = ["sd2x", "mdrive", "lmd", "generic"];

/// The transaction id requests carry in the drive targets.
pub(crate) const TID: u16 = 0x4D42;

pub(crate) fn profiles() -> &'static [Profile] {
    static PROFILES: OnceLock<Vec<Profile>> = OnceLock::new();
    PROFILES.get_or_init(|| {
        DRIVES
            .iter()
            .map(|name| {
                Corpus::Embedded
                    .profile(name)
                    .unwrap_or_else(|e| panic!("embedded profile {name}: {e}"))
            })
            .collect()
    })
}

pub(crate) fn station(p: &Profile, faults: &FaultSet) -> Station {
    Station::new(
        drives::build(p.clone(), faults.clone()),
        faults.clone(),
        p.device.default_unit,
    )
}

/// A fresh station of drive `drive` of [`DRIVES`] with `faults`: a clone of one built once per thread and
/// never used (building one costs far more than cloning it, and a clone is in exactly the state a new one is).
pub(crate) fn fresh_station(drive: usize, faults: &FaultSet) -> Station {
    thread_local! {
        /// Pristine stations by fault set, one per drive of `DRIVES`.
        static PRISTINE: RefCell<Vec<(FaultSet, Vec<Station>)>> = const { RefCell::new(Vec::new()) };
    }
    PRISTINE.with_borrow_mut(|pristine| {
        let at = match pristine.iter().position(|(f, _)| f == faults) {
            Some(at) => at,
            None => {
                let stations = profiles().iter().map(|p| station(p, faults)).collect();
                pristine.push((faults.clone(), stations));
                pristine.len() - 1
            }
        };
        pristine[at].1[drive].clone()
    })
}

/// The liveness probe of drive `drive` of [`DRIVES`]: the catalog's known-good read, computed once.
pub(crate) fn liveness_probe(drive: usize) -> &'static [u8] {
    static PROBES: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    &PROBES.get_or_init(|| profiles().iter().map(catalog::known_good_read).collect())[drive]
}

/// The serial line of the RTU side: 19200 baud 8E1, the default of the RTU profiles.
pub(crate) fn line_timing() -> RtuTiming {
    RtuTiming::new(
        19_200,
        CharFormat {
            parity: Parity::Even,
            stop_bits: 1,
        },
    )
}

/// A request PDU framed for `framing`; `None` when it cannot be (over 253 bytes).
pub(crate) fn frame_request(framing: Framing, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    match framing {
        Framing::Tcp => tcp::encode_adu(TID, unit, pdu, &mut out).ok()?,
        _ => rtu::encode_adu(unit, pdu, &mut out).ok()?,
    }
    Some(out)
}

/// What the station answers to one framed request, and whether it closes the connection.
pub(crate) fn answer(
    station: &mut Station,
    framing: Framing,
    adu: &[u8],
) -> (Option<Vec<u8>>, bool) {
    match framing {
        Framing::Tcp => {
            let out = station.serve_tcp(Duration::ZERO, &mut TcpConn::default(), adu);
            (out.replies.into_iter().next().map(|w| w.bytes), out.close)
        }
        _ => (
            station.rtu_frame(Duration::ZERO, adu).map(|w| w.bytes),
            false,
        ),
    }
}

/// Check a reply of a healthy drive: no delay beyond `silence` (on an RTU line the t3.5 that must follow a
/// request whose frame the drive cut by its length; zero elsewhere), strict decoding as a response, and, when
/// the request is known (`Some((unit, function code))`), the echoed transaction id, unit and a function code
/// that is the request's or its exception form. Returns the response.
pub(crate) fn check_reply(
    framing: Framing,
    wire: &Wire,
    request: Option<(u8, u8)>,
    silence: Duration,
) -> Response {
    assert!(
        wire.delay <= silence,
        "the drive answers late: {:?}",
        wire.delay
    );
    let decoded = decode_any(&wire.bytes, framing, Direction::Response).unwrap_or_else(|e| {
        panic!(
            "{framing:?} reply {} does not decode strictly: {e}",
            hex_spaced(&wire.bytes)
        )
    });
    let Pdu::Response(response) = decoded.pdu else {
        panic!("a response decode gave a request")
    };
    if let Some((unit, fc)) = request {
        if framing == Framing::Tcp {
            assert_eq!(
                decoded.transaction_id,
                Some(TID),
                "transaction id not echoed"
            );
        }
        assert_eq!(decoded.unit, Some(unit), "unit / address not echoed");
        let f = response.function();
        assert!(
            f == FunctionCode(fc) || f == FunctionCode(fc).exception(),
            "reply function {f} to request function 0x{fc:02X}: {}",
            hex_spaced(&wire.bytes)
        );
    }
    response
}
