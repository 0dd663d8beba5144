//! RTU on a real target: after a malformed frame the harness leaves the line silent for t3.5 before the next
//! frame, as the reference drive assumes. Without it, a frame one byte longer than its function's length
//! rule whose first eight bytes are a valid frame (an appended byte equal to the CRC's low byte: the CRC of
//! the longer frame then starts with the old CRC's high byte) left its last byte in the drive's framer,
//! which took it with the next request as one garbled frame: the healthy simulator "failed" the following
//! liveness read (seed 1, case gen/1/123/read-reg-bytecount). Over TCP the silence is twice the carrier's
//! 50 ms: a drive or device server ending frames after 50 ms of its own lost a liveness read sent 50.2 ms
//! after the answer (tests/independent/sd2x-i), or the gap the target URL gives (`rtu+tcp://…?gap=MS`, a
//! device server or drive whose own frame timeout is longer).

use std::path::Path;

use test_support::{SimProcess, harness_reported, read_json, run_args};

/// The silence (µs) before the first frame sent after the malformed frame of `case`, from the report's wire.
fn silence_after_the_malformed_frame(report: &Path, case: &str) -> u64 {
    let line = std::fs::read_to_string(report.join("cases.jsonl"))
        .expect("cases.jsonl")
        .lines()
        .find(|l| l.contains(&format!("\"{case}\"")))
        .map(str::to_string)
        .expect("the case's line");
    let record: serde_json::Value = serde_json::from_str(&line).expect("json");
    let wire = record["result"]["wire"].as_array().expect("wire");
    let malformed = wire
        .iter()
        .position(|w| w["intended_malformed"] == true)
        .expect("the malformed frame");
    let next_tx = wire[malformed + 1..]
        .iter()
        .position(|w| w["dir"] == "tx")
        .map(|i| malformed + 1 + i)
        .expect("the liveness read");
    let at = |i: usize| wire[i]["at"].as_u64().expect("at");
    at(next_tx) - at(next_tx - 1)
}

#[test]
fn generated_cases_over_rtu_over_tcp_pass_on_a_healthy_simulator() {
    let sim = SimProcess::start(&["--profile", "generic", "--rtu-over-tcp", "127.0.0.1:0"]);
    let url = sim.rtu_over_tcp_url();
    let extra = ["--generated", "130", "--seed", "1", "--no-shrink"];
    let (_dir, report, (code, out, err)) =
        harness_reported("rtu-resync", &run_args(&url, "generic", &extra));
    assert_eq!(code, 0, "{out}\n{err}");
    let index = read_json(&report.join("index.json"));
    let case = index["cases"]
        .as_array()
        .expect("cases")
        .iter()
        .find(|c| c["id"] == "gen/1/123/read-reg-bytecount")
        .expect("the case ran");
    assert_eq!(case["verdict"], "PASS", "{case}");
    // Its wire: the malformed frame, its answer, then the liveness read at least 100 ms after the last byte.
    let gap = silence_after_the_malformed_frame(&report, "gen/1/123/read-reg-bytecount");
    assert!(gap >= 100_000, "{gap} µs of silence before the next frame");
    // A device whose frame timeout is longer: the URL's gap.
    let extra = [
        "--generated",
        "124",
        "--seed",
        "1",
        "--no-shrink",
        "--cases",
        "gen/1/123/*",
    ];
    let (_dir, report, (code, out, err)) = harness_reported(
        "rtu-resync-gap",
        &run_args(&format!("{url}?gap=250"), "generic", &extra),
    );
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("RESULT: PASS (1 PASS)"), "{out}");
    let gap = silence_after_the_malformed_frame(&report, "gen/1/123/read-reg-bytecount");
    assert!(
        (250_000..400_000).contains(&gap),
        "{gap} µs of silence before the next frame with ?gap=250"
    );
}
