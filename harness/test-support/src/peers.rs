//! The C (libmodbus) and Python (pymodbus) clients of tests/peers/, and the scenarios both run against an
//! in-process server. Both clients take the same arguments and print one line per operation.

use std::path::PathBuf;
use std::sync::OnceLock;

use engine::servers::{ServerConfig, ServerHandle};

use super::*;

/// A third-party client program.
#[derive(Clone, Copy, Debug)]
pub enum Peer {
    Libmodbus,
    Pymodbus,
}

/// Where the client talks to the server.
#[derive(Clone, Copy, Debug)]
pub enum Via {
    Tcp,
    Pty,
}

/// What the client does.
#[derive(Clone, Copy, Debug)]
pub enum Scenario {
    /// SD2x manual 6.1 then 6.3: the two RxPDO telegrams, the watchdog they arm runs out, and the status
    /// word (register 2000) reads the manual's 0x7038 by FC 04 and FC 03.
    Sd2xStatusWord,
    /// SD2x has no FC 05: exception 01, from the station whatever the model.
    Sd2xIllegalFunction,
    /// MDrive VM at 0x008B: write 600000 by FC 16, read it back by FC 03 (golden FC 16/FC 03 examples).
    MdriveMaxVelocity,
    /// Generic profile: a holding register and a coil written and read back.
    GenericRoundTrip,
}

/// Compile tests/peers/libmodbus_client.c once per test process; `Err` says what is missing or failed.
fn libmodbus_client() -> Result<PathBuf, String> {
    static EXE: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    EXE.get_or_init(|| super::compile_libmodbus_peer("libmodbus_client.c", "libmodbus_client"))
        .clone()
}

/// The command that runs `peer`, or `None` after a printed skip notice when its toolchain is missing.
pub fn client_command(peer: Peer, test: &str) -> Option<tokio::process::Command> {
    match peer {
        Peer::Libmodbus => {
            if !libmodbus_or_skip(test) {
                return None;
            }
            // The toolchain is there, so a build failure is a real failure.
            let exe = libmodbus_client().unwrap_or_else(|e| panic!("libmodbus client: {e}"));
            Some(tokio::process::Command::new(exe))
        }
        Peer::Pymodbus => {
            if !pymodbus_or_skip(test) {
                return None;
            }
            let mut c = tokio::process::Command::new("python3");
            c.arg(peer_file("pymodbus_client.py"));
            Some(c)
        }
    }
}

/// A scenario as client runs: (operation, expected output line) pairs, and the SD2x status word the
/// drive must show (waited for in-process, bounded) before the second run.
struct Plan {
    profile: &'static str,
    first: Vec<(String, String)>,
    wait_status: Option<u16>,
    then: Vec<(String, String)>,
}

fn plan(scenario: Scenario) -> Plan {
    let pairs = |v: &[(&str, &str)]| -> Vec<(String, String)> {
        v.iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect()
    };
    let words = |w: &[u16]| w.iter().map(u16::to_string).collect::<Vec<_>>().join(",");
    let simple = |profile, ops| Plan {
        profile,
        first: ops,
        wait_status: None,
        then: Vec::new(),
    };
    match scenario {
        Scenario::Sd2xStatusWord => {
            let status = SD2X_STATUS_AFTER_61.to_string();
            Plan {
                profile: "sd2x",
                first: vec![
                    (format!("wh:3000:{}", words(&SD2X_SHUTDOWN)), "ok".into()),
                    (format!("wh:3000:{}", words(&SD2X_ENABLE)), "ok".into()),
                ],
                wait_status: Some(SD2X_STATUS_AFTER_61),
                then: vec![
                    ("ri:2000:1".into(), status.clone()),
                    ("rh:2000:1".into(), status),
                ],
            }
        }
        Scenario::Sd2xIllegalFunction => simple("sd2x", pairs(&[("wc:0:1", "exception 1")])),
        Scenario::MdriveMaxVelocity => simple(
            "mdrive",
            pairs(&[("wh:0x8B:9,10176", "ok"), ("rh:0x8B:2", "9 10176")]),
        ),
        Scenario::GenericRoundTrip => {
            let p = profile("generic");
            let (reg, coil) = rw_holding_and_coil(&p);
            let (a, v) = reg.expect("generic profile has a writable holding register");
            let c = coil.expect("generic profile has a writable coil");
            let w = v ^ 1;
            simple(
                "generic",
                vec![
                    (format!("wr:{a}:{v}"), "ok".into()),
                    (format!("rh:{a}:1"), v.to_string()),
                    (format!("wh:{a}:{w}"), "ok".into()),
                    (format!("rh:{a}:1"), w.to_string()),
                    (format!("wc:{c}:1"), "ok".into()),
                    (format!("rc:{c}:1"), "1".into()),
                    (format!("wm:{c}:0"), "ok".into()),
                    (format!("rc:{c}:1"), "0".into()),
                ],
            )
        }
    }
}

/// Run `scenario` with `peer` over `via` against an in-process server, comparing every output line.
pub async fn run(peer: Peer, scenario: Scenario, via: Via, test: &str) {
    if client_command(peer, test).is_none() {
        return;
    }
    if matches!(via, Via::Pty) && !socat_or_skip(test) {
        return;
    }
    let plan = plan(scenario);
    let unit = profile(plan.profile).device.default_unit.to_string();
    // Declared first, dropped last: the pty pair outlives the server and the clients.
    let pty = matches!(via, Via::Pty).then(PtyPair::start);
    let config = match &pty {
        None => ServerConfig {
            tcp: Some("127.0.0.1:0".parse().unwrap()),
            ..ServerConfig::default()
        },
        Some(pty) => ServerConfig {
            serial: Some(serial_19200_8n1(&pty.a)),
            ..ServerConfig::default()
        },
    };
    let server: ServerHandle = serve(plan.profile, &[], config).await;
    let endpoint: Vec<String> = match &pty {
        None => {
            let port = server.tcp_addr().expect("tcp addr").port();
            vec!["tcp".into(), "127.0.0.1".into(), port.to_string(), unit]
        }
        Some(pty) => vec![
            "rtu".into(),
            pty.b.to_string_lossy().into_owned(),
            "19200".into(),
            "N".into(),
            "1".into(),
            unit,
        ],
    };
    let client_run = |ops: &[(String, String)]| {
        let mut cmd = client_command(peer, test).expect("checked above");
        cmd.args(&endpoint).args(ops.iter().map(|(op, _)| op));
        let ops = ops.to_vec();
        async move {
            let (ok, out, err) = run_client(&mut cmd).await;
            let got: Vec<&str> = out.lines().collect();
            for (i, (op, want)) in ops.iter().enumerate() {
                assert_eq!(
                    got.get(i).copied(),
                    Some(want.as_str()),
                    "{peer:?} over {via:?}, op {op}: whole output:\n{out}\nstderr:\n{err}"
                );
            }
            assert!(ok, "{peer:?} exited with failure:\n{out}\n{err}");
        }
    };
    client_run(&plan.first).await;
    if let Some(want) = plan.wait_status {
        if let Err(last) = wait_sd2x_status(&server, want).await {
            panic!(
                "the SD2x status word did not become {want:#06X} within {SD2X_WATCHDOG_BOUND:?} \
                 (last seen: {last:04X?})"
            );
        }
    }
    if !plan.then.is_empty() {
        client_run(&plan.then).await;
    }
    server.shutdown().await;
}
