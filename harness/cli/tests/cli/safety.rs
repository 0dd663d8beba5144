//! Safe on real drives, on the wire: a `simulate` process (MDrive, LMD, SD2x over Modbus/TCP) behind a
//! recording proxy on loopback (port 0)
//! receives no write function code from `run --read-only`, `fuzz --read-only`, a default `fuzz`, `probe` and
//! `probe --read-only`,
//! while a default `run` and `fuzz --allow-writes` (the controls) are seen writing, so the check can fail.

use drives::profile::Profile;
use engine::Tag;
use engine::safety::{classify, is_write_fc};
use test_support::{RecordingProxy, SimProcess, harness, profile, run_args};

/// The requests the drive received that write, as `fc pdu-hex`: a write function code, or anything the
/// classifier rates `write` (FC 08 restart, listen only, clear counters; FC 43 object writes).
fn writes(p: &Profile, pdus: &[Vec<u8>]) -> Vec<String> {
    pdus.iter()
        .filter(|pdu| {
            pdu.first().is_some_and(|fc| is_write_fc(*fc)) || classify(p, pdu).contains(&Tag::Write)
        })
        .map(|pdu| format!("{:02X} {}", pdu[0], hex_of(pdu)))
        .collect()
}

fn hex_of(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// One command against a fresh `simulate --profile NAME` behind a fresh proxy: (exit code, stderr, the
/// writes the drive received, every request it received).
fn through_proxy(name: &str, args: &[&str]) -> (i32, String, Vec<String>, Vec<Vec<u8>>) {
    let sim = SimProcess::start(&["--profile", name, "--listen", "127.0.0.1:0"]);
    let proxy = RecordingProxy::start(sim.tcp.expect("tcp endpoint"));
    let target = format!("tcp://{}", proxy.addr);
    let mut all: Vec<&str> = args.to_vec();
    all.extend_from_slice(&["--target", &target]);
    let (code, _out, err) = harness(&all);
    drop(sim);
    let p = profile(name);
    let pdus = proxy.request_pdus();
    (code, err, writes(&p, &pdus), pdus)
}

#[test]
fn read_only_run_fuzz_and_probe_put_no_write_on_the_mdrive_wire() {
    read_only_puts_no_write_on_the_wire("mdrive");
}

#[test]
fn read_only_run_fuzz_and_probe_put_no_write_on_the_lmd_wire() {
    read_only_puts_no_write_on_the_wire("lmd");
}

#[test]
fn read_only_run_fuzz_and_probe_put_no_write_on_the_sd2x_wire() {
    read_only_puts_no_write_on_the_wire("sd2x");
}

/// The bounds of the read-only fuzz campaigns tried here.
const SHORT_FUZZ: [&str; 8] = [
    "--duration",
    "2s",
    "--max-cases",
    "400",
    "--timeout",
    "300",
    "--seed",
    "7",
];

fn read_only_puts_no_write_on_the_wire(name: &str) {
    {
        let cases: [(&str, Vec<&str>); 5] = [
            (
                "run --read-only",
                vec!["run", "--profile", name, "--read-only", "--no-progress"],
            ),
            (
                "fuzz --read-only",
                [&["fuzz", "--profile", name, "--read-only"][..], &SHORT_FUZZ].concat(),
            ),
            // The default fuzz against a real target: reads only, no flag needed.
            (
                "fuzz (default)",
                [&["fuzz", "--profile", name][..], &SHORT_FUZZ].concat(),
            ),
            ("probe", vec!["probe", "--profile", name]),
            (
                "probe --read-only",
                vec!["probe", "--profile", name, "--read-only"],
            ),
        ];
        for (what, args) in cases {
            let (code, err, w, pdus) = through_proxy(name, &args);
            let n = pdus.len();
            assert!(code == 0 || code == 1, "{name} {what}: exit {code}\n{err}");
            assert!(
                n > 20,
                "{name} {what}: only {n} requests reached the drive\n{err}"
            );
            assert!(
                w.is_empty(),
                "{name} {what}: {} write(s) on the wire: {:#?}",
                w.len(),
                &w[..w.len().min(20)]
            );
            assert!(
                !err.contains("WRITES AHEAD"),
                "{name} {what}: a write banner\n{err}"
            );
        }
    }
}

/// The controls: the same recording sees the writes of a default `run` and of `fuzz --allow-writes` (which
/// says so first on stderr), and none the classifier rates motion or destructive.
#[test]
fn writes_are_seen_when_allowed_and_never_motion_without_the_flag() {
    let p = profile("mdrive");
    let (_, err, w, _) = through_proxy("mdrive", &["run", "--profile", "mdrive", "--no-progress"]);
    assert!(!w.is_empty(), "a default run writes (with a banner): {err}");
    let (code, err, w, pdus) = through_proxy(
        "mdrive",
        &[
            "fuzz",
            "--profile",
            "mdrive",
            "--allow-writes",
            "--duration",
            "3s",
            "--max-cases",
            "600",
            "--seed",
            "7",
        ],
    );
    assert!(code == 0 || code == 1, "exit {code}\n{err}");
    assert!(!w.is_empty(), "fuzz --allow-writes wrote nothing: {err}");
    assert!(err.contains("FUZZ WRITES AHEAD"), "no banner: {err}");
    // What the drive received: nothing motion or destructive without --allow-motion / --allow-destructive.
    let dangerous: Vec<String> = pdus
        .iter()
        .filter(|pdu| {
            let t = classify(&p, pdu);
            t.contains(&Tag::Motion) || t.contains(&Tag::Destructive)
        })
        .map(|pdu| hex_of(pdu))
        .collect();
    assert!(
        dangerous.is_empty(),
        "motion/destructive sent: {dangerous:#?}"
    );
}

/// A drive of your own (the SCHEMA.md example) that identifies as ACME / X1 revision "1.0": `--profile auto`
/// matched generic on the revision's "1.0" before; now it is exit 2 with the identification read and how to
/// name a profile, and nothing is sent after the identification request.
#[test]
fn profile_auto_without_an_exact_match_is_exit_2_with_the_identification() {
    let dir = test_support::TempDir::new("auto-nomatch");
    let mut text = include_str!("../data/my_drive.toml").to_string();
    text.push_str(
        "\n[[function]]\ncode = 0x2B\nname = \"Read Device Identification\"\n\n\
         [[identification]]\nobject_id = 0x00\nname = \"VendorName\"\nvalue = \"ACME\"\n\n\
         [[identification]]\nobject_id = 0x01\nname = \"ProductCode\"\nvalue = \"X1\"\n\n\
         [[identification]]\nobject_id = 0x02\nname = \"MajorMinorRevision\"\nvalue = \"1.0\"\n",
    );
    let file = dir.path().join("acme.toml");
    std::fs::write(&file, text).expect("write profile");
    let sim = SimProcess::start(&[
        "--profile",
        file.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
    ]);
    let proxy = RecordingProxy::start(sim.tcp.expect("tcp"));
    let target = format!("tcp://{}", proxy.addr);
    for cmd in ["run", "fuzz"] {
        let mut args = vec![cmd, "--target", &target, "--profile", "auto"];
        if cmd == "fuzz" {
            args.extend_from_slice(&["--duration", "1s"]);
        }
        let (code, _, err) = harness(&args);
        assert_eq!(code, 2, "{cmd}: {err}");
        for want in [
            "\"ACME\"",
            "\"X1\"",
            "\"1.0\"",
            "no profile matches",
            "--profile NAME|PATH",
        ] {
            assert!(err.contains(want), "{cmd}: `{want}` missing: {err}");
        }
        assert!(!err.contains("picked"), "{cmd}: {err}");
    }
    // Only identification requests reached the drive.
    let pdus = proxy.request_pdus();
    assert!(!pdus.is_empty());
    assert!(pdus.iter().all(|p| p.first() == Some(&0x2B)), "{pdus:?}");
    // The same drive, named: the run goes ahead.
    let (code, _, err) = harness(&[
        "run",
        "--target",
        &target,
        "--profile",
        file.to_str().unwrap(),
        "--read-only",
        "--no-progress",
    ]);
    assert_eq!(code, 0, "{err}");
}

/// `--max-rate` paces requests, not the pieces of one: the case that splits a request across two TCP
/// segments 5 ms apart sends them 5 ms apart at `--max-rate 2` too, and the request still goes half a
/// second after the pre-flight read. (It paced every piece: the segments went 500 ms apart, past a drive's
/// partial-frame or idle timeout, and on a serial line past t1.5, which made such a step inconclusive.)
#[test]
fn max_rate_paces_requests_not_the_pieces_of_one() {
    let sim = SimProcess::on_loopback("mdrive", "--listen", None);
    let url = sim.tcp_url();
    let dir = test_support::TempDir::new("max-rate-pieces");
    let report = dir.path().join("report");
    let (code, out, err) = harness(&run_args(
        &url,
        "mdrive",
        &[
            "--max-rate",
            "2",
            "--cases",
            "tcp/segment/request-split",
            "--report",
            report.to_str().expect("path"),
        ],
    ));
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS (1 PASS)"), "{out}");
    let line = std::fs::read_to_string(report.join("cases.jsonl")).expect("cases.jsonl");
    let case: serde_json::Value =
        serde_json::from_str(line.lines().next().expect("one case")).expect("json");
    // On the target's clock, in microseconds from its opening (the pre-flight read went at about 0).
    let tx: Vec<u64> = case["result"]["wire"]
        .as_array()
        .expect("wire")
        .iter()
        .filter(|w| w["dir"] == "tx")
        .map(|w| w["at"].as_u64().expect("at"))
        .collect();
    assert_eq!(tx.len(), 2, "the request's two pieces: {tx:?}");
    assert!(
        tx[0] >= 450_000,
        "the request went {} µs after the pre-flight read",
        tx[0]
    );
    assert!(
        tx[1] - tx[0] < 100_000,
        "the pieces of one request went {} µs apart",
        tx[1] - tx[0]
    );
}
