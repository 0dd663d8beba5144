//! Snapshots of generated runs against the reference drives: the same seed gives the same observations
//! in process, over Modbus/TCP, over RTU over TCP and over RTU on a pty (socat), and they match the files
//! committed under the top-level `snapshots/` (insta; `cargo insta review` or `INSTA_UPDATE=always` to
//! accept a change). Two runs with one seed write byte-identical files; another seed, or a simulator fault,
//! is reported as drift naming the cases, and the command line exits 1 on it.
//!
//! The safety policy applies to every run here (`policy_on_sim` in process, the default on servers), so
//! motion and destructive cases are SKIPPED everywhere and no observation depends on wall-clock time.

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use drives::{Fault, FaultSet};
use engine::servers::ServerConfig;
use engine::session::{Options, SnapshotOptions};
use engine::targets::TargetUrl;
use test_support::{
    PtyPair, harness, have_socat, loopback_tcp_and_rtu, run_ok, serve, sim_run_args, skip,
};

/// The seed of every committed snapshot.
const SEED: u64 = 20_240_601;
/// Generated cases per snapshot.
const N: u64 = 60;

fn options(url: &str, profile: &str, seed: u64, faults: &[Fault]) -> Options {
    let mut o = Options::new(TargetUrl::parse(url).expect("url"));
    o.profile = Some(profile.to_string());
    o.generated = N;
    o.seed = Some(seed);
    o.faults = FaultSet::of(faults);
    o.policy_on_sim = true;
    o.shrink = None;
    o.timing.timeout = Duration::from_millis(1000);
    o.timing.silence = Duration::from_millis(150);
    o
}

/// Write the snapshot of a run to `path` and return its text.
fn write_snapshot(mut o: Options, path: &Path) -> String {
    o.snapshot = Some(SnapshotOptions {
        path: path.to_path_buf(),
        update: true,
    });
    let out = run_ok(&o);
    assert!(out.snapshot.as_ref().is_some_and(|s| s.written));
    std::fs::read_to_string(path).expect("snapshot written")
}

fn snapshot(url: &str, profile: &str) -> String {
    let dir = test_support::TempDir::new("tempdir");
    write_snapshot(
        options(url, profile, SEED, &[]),
        &dir.path().join("snap.txt"),
    )
}

/// Compare with the committed file `snapshots/<name>.snap`.
fn check(name: &str, text: &str) {
    insta::with_settings!({
        snapshot_path => "../../../../snapshots",
        prepend_module_to_snapshot => false,
        omit_expression => true,
        description => format!("modbus-harness run --generated {N} --seed {SEED} --snapshot (see harness/tests/generated_snapshots.rs)"),
    }, {
        insta::assert_snapshot!(name, text);
    });
}

/// The run `other` observed what the in-process run did. On a real line (`busy_line`), a case the runner
/// marks INFORMATIONAL because the machine could not send the pieces of a split request within t1.5 is
/// compared on its bytes only: the verdict then says the step was inconclusive, not that the drive differs.
fn same(what: &str, reference: &str, other: &str, busy_line: bool) {
    let (r, o): (Vec<&str>, Vec<&str>) = (reference.lines().collect(), other.lines().collect());
    let mut diff = Vec::new();
    let mut inconclusive = Vec::new();
    for (a, b) in r.iter().zip(&o) {
        if a == b {
            continue;
        }
        if busy_line
            && b.starts_with("== ")
            && b.ends_with("  INFORMATIONAL")
            && a.rsplit_once("  ").map(|x| x.0) == b.rsplit_once("  ").map(|x| x.0)
        {
            inconclusive.push(b.to_string());
            continue;
        }
        diff.push(format!("- {a}\n+ {b}"));
    }
    if !inconclusive.is_empty() {
        let _ = writeln!(
            std::io::stderr().lock(),
            "{what}: compared on bytes only (inconclusive timing on a busy machine): {inconclusive:?}"
        );
    }
    assert!(
        diff.is_empty() && r.len() == o.len(),
        "{what}: observations differ from the in-process run ({} vs {} lines):\n{}",
        r.len(),
        o.len(),
        diff.iter().take(10).cloned().collect::<Vec<_>>().join("\n")
    );
}

/// In process and over TCP (Modbus/TCP framing); in process, RTU over TCP and a pty (RTU framing).
fn drive_on_every_transport(profile: &str, tcp: bool) {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    if tcp {
        let inproc = snapshot(&format!("sim:{profile}"), profile);
        let h = rt.block_on(serve(profile, &[], loopback_tcp_and_rtu()));
        let over_tcp = snapshot(&format!("tcp://{}", h.tcp_addr().expect("tcp")), profile);
        drop(h);
        same(&format!("{profile} over TCP"), &inproc, &over_tcp, false);
        check(&format!("generated-{profile}-tcp"), &inproc);
    }
    let inproc = snapshot(&format!("sim:{profile}?transport=rtu"), profile);
    let h = rt.block_on(serve(profile, &[], loopback_tcp_and_rtu()));
    let rtu_tcp = snapshot(
        &format!("rtu+tcp://{}", h.rtu_over_tcp_addr().expect("rtu over tcp")),
        profile,
    );
    drop(h);
    same(
        &format!("{profile} over RTU over TCP"),
        &inproc,
        &rtu_tcp,
        false,
    );
    if have_socat() {
        let pty = PtyPair::start();
        let config = ServerConfig {
            serial: Some(test_support::serial_run_8n1(&pty.a)),
            ..ServerConfig::default()
        };
        let h = rt.block_on(serve(profile, &[], config));
        let serial = snapshot(
            &format!(
                "rtu://{}?baud={}&parity=none",
                pty.b.display(),
                test_support::PTY_RUN_BAUD
            ),
            profile,
        );
        drop(h);
        same(&format!("{profile} over a pty"), &inproc, &serial, true);
    } else {
        skip(
            &format!("generated snapshot of {profile} over a pty"),
            "socat is not installed",
        );
    }
    check(&format!("generated-{profile}-rtu"), &inproc);
}

#[test]
fn mdrive_generated_observations_are_the_same_on_every_transport_and_match_the_snapshots() {
    drive_on_every_transport("mdrive", true);
}

#[test]
fn lmd_generated_observations_are_the_same_on_every_transport_and_match_the_snapshots() {
    drive_on_every_transport("lmd", true);
}

#[test]
fn sd2x_generated_observations_are_the_same_on_every_transport_and_match_the_snapshots() {
    drive_on_every_transport("sd2x", false);
}

/// Generated observations of the third-party servers of tests/peers/ on the generic profile: a change in
/// pymodbus or libmodbus behaviour (or in the harness's judgement of it) shows as drift here.
#[test]
fn peer_server_snapshots() {
    use test_support::peer_servers::PeerServer;
    type Start = fn() -> PeerServer;
    let peers: [(&str, Start, bool); 2] = [
        (
            "pymodbus",
            PeerServer::pymodbus,
            test_support::have_pymodbus(),
        ),
        (
            "libmodbus",
            PeerServer::libmodbus,
            test_support::have_libmodbus(),
        ),
    ];
    for (peer, start, available) in peers {
        if !available {
            skip(
                &format!("generated snapshot of the {peer} server"),
                &format!("{peer} is not installed"),
            );
            continue;
        }
        let server = start();
        let text = snapshot(&format!("tcp://{}", server.addr), "generic");
        check(&format!("generated-{peer}-tcp"), &text);
        server.terminate();
    }
}

#[test]
fn the_same_seed_twice_writes_byte_identical_snapshot_files() {
    let dir = test_support::TempDir::new("tempdir");
    let (a, b) = (dir.path().join("a.txt"), dir.path().join("b.txt"));
    write_snapshot(options("sim:mdrive", "mdrive", SEED, &[]), &a);
    write_snapshot(options("sim:mdrive", "mdrive", SEED, &[]), &b);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    // Against a server too: a fresh one per run, since generated writes change the drive.
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let mut texts = Vec::new();
    for name in ["c.txt", "d.txt"] {
        let h = rt.block_on(serve("lmd", &[], loopback_tcp_and_rtu()));
        let url = format!("tcp://{}", h.tcp_addr().expect("tcp"));
        write_snapshot(options(&url, "lmd", SEED, &[]), &dir.path().join(name));
        texts.push(std::fs::read(dir.path().join(name)).unwrap());
    }
    assert_eq!(texts[0], texts[1]);
}

#[test]
fn another_seed_or_a_fault_is_drift_naming_the_cases() {
    let dir = test_support::TempDir::new("tempdir");
    let file = dir.path().join("mdrive.snap.txt");
    // Without the policy on the simulator: every write runs, so the faults below have cases to spoil.
    let opts = |seed: u64, faults: &[Fault]| {
        let mut o = options("sim:mdrive", "mdrive", seed, faults);
        o.policy_on_sim = false;
        o
    };
    write_snapshot(opts(SEED, &[]), &file);
    let compare = |seed: u64, faults: &[Fault]| {
        let mut o = opts(seed, faults);
        o.snapshot = Some(SnapshotOptions {
            path: file.clone(),
            update: false,
        });
        run_ok(&o)
    };
    // The same run: no drift.
    let out = compare(SEED, &[]);
    let s = out.snapshot.expect("compared");
    assert!(!s.drifted(), "{}", s.drift.unwrap().render());
    // Another seed: every case is another case.
    let out = compare(SEED + 1, &[]);
    let d = out.snapshot.expect("compared").drift.expect("drift");
    assert!(d.header.is_some(), "the seed is in the header");
    assert_eq!((d.missing, d.added, d.same), (N as usize, N as usize, 0));
    let text = d.render();
    assert!(text.contains(&format!("- gen/{SEED}/0/")), "{text}");
    // Besides the cases, only the choices the drive made differ (other cases show other freedoms).
    assert!(
        d.ids
            .iter()
            .all(|i| i.starts_with("gen/") || i.starts_with("choice/"))
    );
    // The report is capped; the rest is counted.
    assert!(
        text.contains(&format!(
            "... and {} more case(s) or choice(s)",
            2 * N as usize + d.choices - engine::reports::snapshot::DRIFT_DETAIL_CAP
        )),
        "{text}"
    );
    // A fault: the cases it changes are named, with the lines that differ.
    let out = compare(SEED, &[Fault::RangeUnchecked, Fault::QuantityUnchecked]);
    let failing: Vec<String> = out.failures.iter().map(|f| f.id.clone()).collect();
    let d = out.snapshot.expect("compared").drift.expect("drift");
    assert!(d.header.is_none());
    assert!(
        d.changed > 0 && d.missing == 0 && d.added == 0,
        "{}",
        d.summary()
    );
    assert!(!failing.is_empty());
    for id in &failing {
        assert!(
            d.ids.contains(id),
            "FAIL case {id} not named in the drift: {:?}",
            d.ids
        );
    }
    let text = d.render();
    assert!(text.contains(&format!("~ {}", failing[0])), "{text}");
    assert!(
        text.contains("    - == ") && text.contains("    + == "),
        "{text}"
    );
}

/// The snapshot records the choices the drive made where the sources leave one: a drive that makes another
/// admissible choice (firmware changed its mind) drifts, and the drift names the freedom and both values,
/// although every case still passes.
#[test]
fn another_admissible_choice_is_drift_naming_the_freedom() {
    let dir = test_support::TempDir::new("tempdir");
    let file = dir.path().join("lmd.snap.txt");
    let opts = |choose: &[&str]| {
        let mut o = options("sim:lmd", "lmd", SEED, &[]);
        o.choose = choose.iter().map(|c| c.to_string()).collect();
        o
    };
    let text = write_snapshot(opts(&[]), &file);
    assert!(
        text.contains("== choice/lmd-word-order  low-first\n"),
        "{text}"
    );
    assert!(text.contains("== choice/value-out-of-range  3\n"), "{text}");
    for (choose, freedom, old, new) in [
        ("value-out-of-range=4", "value-out-of-range", "3", "4"),
        (
            "lmd-word-order=high-first",
            "lmd-word-order",
            "low-first",
            "high-first",
        ),
    ] {
        let mut o = opts(&[choose]);
        o.snapshot = Some(SnapshotOptions {
            path: file.clone(),
            update: false,
        });
        let out = run_ok(&o);
        assert_eq!(
            out.summary.count(engine::Verdict::Fail),
            0,
            "--choose {choose}: an admissible choice passes"
        );
        let d = out.snapshot.expect("compared").drift.expect("drift");
        assert!(d.choices >= 1 && !d.is_clean(), "{}", d.render());
        let id = format!("choice/{freedom}");
        assert!(d.ids.contains(&id), "--choose {choose}: {:?}", d.ids);
        let text = d.render();
        assert!(
            text.contains(&format!("    - == {id}  {old}"))
                && text.contains(&format!("    + == {id}  {new}")),
            "{text}"
        );
        assert!(text.contains("choice(s) of the drive differ"), "{text}");
    }
}

#[test]
fn the_command_line_exits_1_on_drift_and_prints_the_cases() {
    let dir = test_support::TempDir::new("tempdir");
    let file = dir.path().join("snap.txt");
    let snap = file.to_str().expect("utf-8 path");
    let cli = |extra: &[&str]| {
        let mut args = sim_run_args(
            "sim:mdrive",
            &["--no-shrink", "--generated", "30", "--snapshot", snap],
        );
        args.extend_from_slice(extra);
        harness(&args)
    };
    let seed = SEED.to_string();
    let (code, stdout, _) = cli(&["--seed", &seed, "--update-snapshot"]);
    assert_eq!(code, 0, "{stdout}");
    assert!(stdout.contains("snapshot written"), "{stdout}");
    let (code, stdout, stderr) = cli(&["--seed", &seed]);
    assert_eq!(code, 0, "{stdout}");
    assert!(stdout.contains("no drift"), "{stdout}");
    assert!(
        stderr.contains(&format!("seed: {SEED}")),
        "the seed is printed: {stderr}"
    );
    let other = (SEED + 1).to_string();
    let (code, stdout, _) = cli(&["--seed", &other]);
    assert_eq!(code, 1, "{stdout}");
    assert!(stdout.contains("differs from this run"), "{stdout}");
    assert!(stdout.contains(&format!("+ gen/{other}/0/")), "{stdout}");
    // Without a file there is nothing to compare with: the run cannot be made (exit 2), and says how.
    let missing = dir.path().join("none.txt");
    let (code, _, stderr) = harness(&[
        "run",
        "--target",
        "sim:mdrive",
        "--generated",
        "3",
        "--snapshot",
        missing.to_str().expect("utf-8 path"),
    ]);
    assert_eq!(code, 2);
    assert!(stderr.contains("--update-snapshot"));
}
