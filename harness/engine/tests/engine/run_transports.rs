//! The conformance run over real transports against `simulate`'s servers: every drive passes over
//! Modbus/TCP, RTU over TCP and RTU on a pty, and the transport-independent cases give the same verdicts
//! as the in-process run.

use std::collections::BTreeMap;
use std::time::Duration;

use engine::Verdict;
use engine::servers::ServerConfig;
use engine::session::Options;
use engine::targets::TargetUrl;
use test_support::{
    PtyPair, failures_of, have_socat, loopback_tcp_and_rtu, run_quietly, serve, skip,
};

fn verdicts(url: &str, profile: &str) -> BTreeMap<String, Verdict> {
    let mut o = Options::new(TargetUrl::parse(url).expect("url"));
    o.profile = Some(profile.to_string());
    o.keep_verdicts = true;
    // Equivalence needs every case on every transport; these are simulators, nothing moves.
    o.safety.allow_motion = true;
    o.safety.allow_destructive = true;
    o.timing.timeout = Duration::from_millis(1000);
    o.timing.silence = Duration::from_millis(150);
    let out = run_quietly(&o).unwrap_or_else(|e| panic!("{url}: {e}"));
    let fails = failures_of(&out);
    assert!(fails.is_empty(), "{url} ({profile}) has FAILs: {fails:#?}");
    out.verdicts.into_iter().collect()
}

/// The case judging the silence before the answers: measured on a line (the simulator's virtual one), not
/// over RTU over TCP (INFORMATIONAL there), so it differs between transports by design.
const TIMING: &str = "rtu/timing/inter-frame-silence";

/// Both runs have the same cases with the same verdicts (the timing case aside: see [`TIMING`]).
fn same_all(a: &BTreeMap<String, Verdict>, b: &BTreeMap<String, Verdict>, what: &str) {
    let diff: Vec<String> = a
        .iter()
        .filter(|(id, v)| *id != TIMING && b.get(*id) != Some(*v))
        .map(|(id, v)| format!("{id}: {v} vs {:?}", b.get(id)))
        .chain(
            b.keys()
                .filter(|id| !a.contains_key(*id))
                .map(|id| format!("{id}: only in the second run")),
        )
        .collect();
    assert!(diff.is_empty(), "{what}: {diff:#?}");
}

/// Cases whose meaning does not depend on the transport carry the same verdict on both runs.
fn same_independent(a: &BTreeMap<String, Verdict>, b: &BTreeMap<String, Verdict>, what: &str) {
    let mut compared = 0;
    for (id, va) in a {
        if id.starts_with("tcp/") || id.starts_with("rtu/") {
            continue;
        }
        if let Some(vb) = b.get(id) {
            // A spec case for one transport only (FC 08 listen only mode on a serial line, FC 0B after 08/0A
            // over Modbus/TCP) is skipped on the other: these runs allow motion and destructive cases, so a
            // skip is the transport's.
            if *va == Verdict::Skipped || *vb == Verdict::Skipped {
                continue;
            }
            compared += 1;
            assert!(va == vb, "{what}: {id}: {va} vs {vb}");
        }
    }
    assert!(compared > 50, "{what}: only {compared} cases in common");
}

#[test]
fn tcp_profiles_over_tcp_and_rtu_over_tcp() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    for profile in ["mdrive", "lmd", "generic"] {
        let inproc = verdicts(&format!("sim:{profile}"), profile);
        // A fresh server per run: the catalog writes, and each run starts from power-on state.
        let h = rt.block_on(serve(profile, &[], loopback_tcp_and_rtu()));
        let tcp = verdicts(&format!("tcp://{}", h.tcp_addr().expect("tcp")), profile);
        same_all(&inproc, &tcp, &format!("{profile} tcp vs sim"));
        drop(h);
        let h = rt.block_on(serve(profile, &[], loopback_tcp_and_rtu()));
        let rtu = verdicts(
            &format!("rtu+tcp://{}", h.rtu_over_tcp_addr().expect("rtu")),
            profile,
        );
        same_independent(&inproc, &rtu, &format!("{profile} rtu+tcp vs sim"));
        drop(h);
    }
}

#[test]
fn sd2x_over_rtu_over_tcp_and_a_pty() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let inproc = verdicts("sim:sd2x", "sd2x");
    let h = rt.block_on(serve("sd2x", &[], loopback_tcp_and_rtu()));
    let rtu = verdicts(
        &format!("rtu+tcp://{}", h.rtu_over_tcp_addr().expect("rtu")),
        "sd2x",
    );
    same_all(&inproc, &rtu, "sd2x rtu+tcp vs sim");
    drop(h);
    if !have_socat() {
        skip(
            "sd2x_over_rtu_over_tcp_and_a_pty (pty part)",
            "socat is not installed",
        );
        return;
    }
    let pty = PtyPair::start();
    let config = ServerConfig {
        serial: Some(test_support::serial_run_8n1(&pty.a)),
        ..ServerConfig::default()
    };
    let h = rt.block_on(serve("sd2x", &[], config));
    let serial = verdicts(
        &format!(
            "rtu://{}?baud={}&parity=none",
            pty.b.display(),
            test_support::PTY_RUN_BAUD
        ),
        "sd2x",
    );
    same_independent(&inproc, &serial, "sd2x pty vs sim");
    drop(h);
}

/// `simulate`'s served drive keeps no record of what its answers decided beyond the last request: nobody
/// takes it, and kept it grew with every request (400 KB a second under a live campaign) and was copied
/// with the model for every request. The catalog over Modbus/TCP decides freedoms on hundreds of requests.
#[test]
fn a_served_drive_forgets_its_decisions_request_by_request() {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let h = rt.block_on(serve("mdrive", &[], loopback_tcp_and_rtu()));
    let url = format!("tcp://{}", h.tcp_addr().expect("tcp"));
    let served = verdicts(&url, "mdrive");
    assert!(served.len() > 100, "{} cases", served.len());
    let left = h.station().lock().take_decisions();
    assert!(left.len() < 10, "{} decisions kept: {left:?}", left.len());
    drop(h);
}
