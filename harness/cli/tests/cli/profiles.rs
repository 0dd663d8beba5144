//! Profiles of your own drive, as a user meets them: `--profile PATH` and `sim:PATH` wherever a profile is
//! named (a name still means the corpus), missing and invalid files exit 2 with file, line and reason, a
//! draft from `probe --write-profile` of every reference drive runs against that drive without a FAIL, a
//! profile written by hand (a block and two 32-bit registers, the example of corpus/profiles/SCHEMA.md)
//! passes against `simulate` and `sim:`, and the README's "Test your own drive" walkthrough works as written.
//! Every server binds port 0; every child is bounded (test-support) and killed by its pid on drop.

use std::path::{Path, PathBuf};

use drives::profile::Profile;
use test_support::{SimProcess, TempDir, harness, harness_in, harness_ok, read_json, sim_run_args};

/// The example of corpus/profiles/SCHEMA.md: a block of ten registers, two 32-bit registers, a block of coils.
const MY_DRIVE: &str = include_str!("../data/my_drive.toml");

/// `run ... --no-progress` must exit 0 with a PASS summary.
fn run_passes(dir: Option<&Path>, args: &[&str]) -> String {
    let mut all = vec!["run", "--no-progress"];
    all.extend_from_slice(args);
    let (code, out, err) = harness_in(dir, &all);
    assert_eq!(code, 0, "{all:?}: exit code\n{out}\n{err}");
    assert!(
        out.trim_end()
            .lines()
            .last()
            .is_some_and(|l| l.starts_with("RESULT: PASS")),
        "{all:?}: {out}"
    );
    out
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write file");
    p
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

#[test]
fn profile_files_work_wherever_a_profile_is_named() {
    let dir = TempDir::new("profile-files");
    let d = dir.path();
    let abs = write(d, "my.toml", MY_DRIVE);
    // sim: with a relative file, an absolute one, another framing.
    let out = run_passes(Some(d), &["--target", "sim:./my.toml"]);
    assert!(out.contains("profile my-drive"), "{out}");
    run_passes(Some(d), &["--target", "sim:my.toml"]);
    run_passes(
        None,
        &["--target", &format!("sim:{}?transport=rtu", s(&abs))],
    );
    // --profile with a file, beside a sim: of the same file.
    let out = harness_ok(
        Some(d),
        &[
            "run",
            "--list",
            "--target",
            "sim:my.toml",
            "--profile",
            "./my.toml",
        ],
    );
    assert!(
        out.contains("profile/my-drive/write/0x0100-target-position"),
        "{out}"
    );
    // sim:NAME runs NAME's drive, which --profile judges: the generic drive is not this one.
    let (code, out, err) = harness_in(
        Some(d),
        &sim_run_args("sim:generic", &["--profile", "my.toml"]),
    );
    assert_eq!(code, 1, "the generic drive judged by my.toml: {out}{err}");
    assert!(out.contains("FAIL tcp/unit-id/0"), "{out}");
    // fuzz and probe take files too.
    let (code, out, err) = harness_in(
        Some(d),
        &[
            "fuzz",
            "--target",
            "sim:my.toml",
            "--profile",
            "my.toml",
            "--duration",
            "5s",
            "--max-cases",
            "40",
            "--seed",
            "7",
            "--regressions",
            "reg",
        ],
    );
    assert_eq!(code, 0, "fuzz: {out}{err}");
    assert!(out.contains("0 finding(s)"), "{out}");
    let out = harness_ok(
        Some(d),
        &["probe", "--target", "sim:./my.toml", "--scan", "0-0x110"],
    );
    assert!(!out.contains("DIFFERENT") && out.contains("same"), "{out}");
    let out = harness_ok(
        Some(d),
        &[
            "probe",
            "--target",
            "sim:generic",
            "--profile",
            "./my.toml",
            "--scan",
            "0-9",
        ],
    );
    assert!(
        out.contains("DIFFERENT"),
        "compared with the file, not generic: {out}"
    );
    // A name still means the corpus: the built-in one, or --corpus DIR's.
    let (code, out, _) = harness(&[
        "run",
        "--list",
        "--target",
        "sim:generic",
        "--profile",
        "generic",
    ]);
    assert_eq!(code, 0);
    assert!(out.contains("profile/generic/read/"), "{out}");
    let corpus = d.join("corpus");
    std::fs::create_dir_all(corpus.join("profiles")).expect("mkdir");
    write(&corpus.join("profiles"), "mine.toml", MY_DRIVE);
    let out = harness_ok(
        None,
        &[
            "run",
            "--list",
            "--corpus",
            s(&corpus),
            "--target",
            "sim:mine",
        ],
    );
    assert!(out.contains("profile/my-drive/read/"), "{out}");
    let (code, _, err) = harness(&["run", "--target", "sim:mine"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("no profile `mine`") && err.contains("known profiles"),
        "{err}"
    );
    // Every command says the rule in its help.
    for cmd in ["run", "fuzz", "probe", "simulate"] {
        let (code, out, _) = harness(&[cmd, "--help"]);
        assert_eq!(code, 0);
        assert!(
            out.contains("containing `/` or ending in `.toml`"),
            "{cmd} --help does not say how a file is told from a name:\n{out}"
        );
    }
    let (_, out, _) = harness(&["probe", "--help"]);
    for want in [
        "--write-profile",
        "--probe-writes",
        "--force",
        "No request with a",
        "FC 06 is never",
    ] {
        assert!(out.contains(want), "probe --help lacks `{want}`:\n{out}");
    }
}

#[test]
fn missing_and_invalid_profile_files_exit_2_with_file_line_and_reason() {
    let dir = TempDir::new("profile-errors");
    let d = dir.path();
    let bad_text = format!(
        "{MY_DRIVE}\n[[register]]\naddress = 0x0101\nwidth = 1\nname = \"Stray\"\naccess = \"rw\"\n"
    );
    let bad = write(d, "bad.toml", &bad_text);
    // The error names the line of the entry's `[[register]]` header, the one before its `address`.
    let line = bad_text
        .lines()
        .position(|l| l == "address = 0x0101")
        .expect("line");
    let bad_msg = format!(
        "bad.toml:{line}: register 0x0101 `Stray` overlaps register 0x0100 `Target position` (width 2)"
    );
    let missing_msg = "nope.toml: cannot read the profile file: No such file or directory";
    for (file, want) in [
        ("./nope.toml", missing_msg),
        ("./bad.toml", bad_msg.as_str()),
    ] {
        let sim = format!("sim:{file}");
        let invocations: Vec<Vec<&str>> = vec![
            vec!["run", "--target", "sim:generic", "--profile", file],
            vec!["run", "--target", &sim],
            vec![
                "run",
                "--list",
                "--target",
                "tcp://127.0.0.1:1",
                "--profile",
                file,
            ],
            vec!["run", "--target", "tcp://127.0.0.1:1", "--profile", file],
            vec!["fuzz", "--target", &sim, "--duration", "1s"],
            vec![
                "fuzz",
                "--target",
                "sim:generic",
                "--profile",
                file,
                "--duration",
                "1s",
            ],
            vec!["probe", "--target", &sim],
            vec!["probe", "--target", "sim:generic", "--profile", file],
            vec!["simulate", "--profile", file, "--listen", "127.0.0.1:0"],
        ];
        for args in invocations {
            let (code, _, err) = harness_in(Some(d), &args);
            assert_eq!(code, 2, "{args:?}: exit code, stderr {err}");
            assert!(err.contains(want), "{args:?}: stderr lacks `{want}`: {err}");
        }
    }
    assert!(bad.is_file());
}

#[test]
fn probe_write_profile_never_replaces_a_file_unless_forced() {
    let dir = TempDir::new("profile-keep");
    let f = write(dir.path(), "edited.toml", "# my edits\n");
    // Refused before anything is sent: nothing listens on port 1, and the error is not a connect error.
    let (code, _, err) = harness(&[
        "probe",
        "--target",
        "tcp://127.0.0.1:1",
        "--write-profile",
        s(&f),
    ]);
    assert_eq!(code, 2);
    assert!(
        err.contains("exists: not replaced") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&f).expect("read"), "# my edits\n");
    let out = harness_ok(
        None,
        &[
            "probe",
            "--target",
            "sim:generic",
            "--scan",
            "0-3",
            "--write-profile",
            s(&f),
            "--force",
        ],
    );
    assert!(
        out.contains("draft profile `generic-draft` written to"),
        "{out}"
    );
    Profile::load(&f).unwrap_or_else(|e| panic!("{e}"));
    // A directory is not a file to write.
    let (code, _, err) = harness(&[
        "probe",
        "--target",
        "sim:generic",
        "--write-profile",
        s(dir.path()),
        "--force",
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("is a directory"), "{err}");
}

/// Probe `target` into a draft, load it, run the draft against the same target: no FAIL.
fn draft_and_run(dir: &Path, tag: &str, target: &str, scan: &str) -> Profile {
    let file = dir.join(format!("{tag}.toml"));
    let (code, out, err) = harness(&[
        "probe",
        "--target",
        target,
        "--scan",
        scan,
        "--write-profile",
        s(&file),
    ]);
    assert_eq!(code, 0, "{target}: probe\n{out}\n{err}");
    assert!(out.contains("none of them writes"), "{target}: {out}");
    let draft = Profile::load(&file).unwrap_or_else(|e| panic!("{target}: {e}"));
    assert!(!draft.registers.is_empty(), "{target}: registers found");
    assert!(draft.registers.iter().all(|r| !r.get_ref().confirmed));
    let out = run_passes(
        None,
        &[
            "--target",
            target,
            "--profile",
            s(&file),
            "--silence",
            "150",
        ],
    );
    assert!(
        out.contains(&format!("profile {}", draft.device.id)),
        "{out}"
    );
    draft
}

#[test]
fn drafts_of_every_reference_drive_pass_against_that_drive() {
    let dir = TempDir::new("profile-drafts");
    let d = dir.path();
    for (tag, target, scan) in [
        ("mdrive", "sim:mdrive", "0-0xFF"),
        ("lmd", "sim:lmd", "0-0xFF"),
        ("sd2x", "sim:sd2x", "1990-2100"),
        ("generic", "sim:generic", "0-0x7F"),
        ("generic-rtu", "sim:generic?transport=rtu", "0-0x7F"),
    ] {
        let draft = draft_and_run(d, tag, target, scan);
        let want = if target.contains("sd2x") || target.contains("rtu") {
            "rtu"
        } else {
            "tcp"
        };
        assert_eq!(draft.device.transports[0].label(), want, "{target}");
    }
    // `simulate` processes over Modbus/TCP, and the SD2x over RTU over TCP.
    for (profile, scan) in [("generic", "0-0x7F"), ("mdrive", "0-0x60")] {
        let sim = SimProcess::start(&["--profile", profile, "--listen", "127.0.0.1:0"]);
        let target = sim.tcp_url();
        let draft = draft_and_run(d, &format!("simulate-{profile}"), &target, scan);
        assert_eq!(
            draft.device.unit_ids,
            [0, 255],
            "{profile}: every unit id answered"
        );
    }
    let sim = SimProcess::start(&["--profile", "sd2x", "--rtu-over-tcp", "127.0.0.1:0"]);
    let target = sim.rtu_over_tcp_url();
    let draft = draft_and_run(d, "simulate-sd2x", &target, "1995-2030");
    assert_eq!(
        draft.device.unit_ids,
        [1, 1],
        "RTU: other slave addresses are not probed"
    );
}

#[test]
fn a_profile_you_write_passes_against_simulate_and_sim() {
    let schema = include_str!("../../../../corpus/profiles/SCHEMA.md");
    assert!(
        schema.contains(MY_DRIVE),
        "tests/data/my_drive.toml is the example of corpus/profiles/SCHEMA.md, word for word"
    );
    let p = Profile::parse("my_drive.toml", MY_DRIVE).unwrap_or_else(|e| panic!("{e}"));
    let wide: Vec<u16> = p
        .registers
        .iter()
        .map(|r| r.get_ref())
        .filter(|r| r.width == 2)
        .map(|r| r.address)
        .collect();
    assert_eq!(wide, [0x0100, 0x0102], "two 32-bit registers");
    assert_eq!(p.registers.len(), 12, "a block of ten and the two");
    let dir = TempDir::new("profile-own");
    let file = write(dir.path(), "my_drive.toml", MY_DRIVE);
    let sim = SimProcess::start(&["--profile", s(&file), "--listen", "127.0.0.1:0"]);
    let report = dir.path().join("report");
    let target = sim.tcp_url();
    run_passes(
        None,
        &[
            "--target",
            &target,
            "--profile",
            s(&file),
            "--report",
            s(&report),
        ],
    );
    let index = read_json(&report.join("index.json"));
    let verdict = |id: &str| {
        index["cases"]
            .as_array()
            .and_then(|cases| cases.iter().find(|c| c["id"] == id))
            .map(|c| c["verdict"].as_str().unwrap_or("").to_string())
            .unwrap_or_else(|| panic!("no case {id}"))
    };
    for id in [
        "profile/my-drive/read/0x0000-set-point-1",
        "profile/my-drive/write/0x0009-set-point-10",
        "profile/my-drive/write-out-of-range/0x0009-set-point-10",
        "profile/my-drive/read/0x0100-target-position",
        "profile/my-drive/write/0x0100-target-position",
        "profile/my-drive/write-out-of-range/0x0100-target-position",
        "profile/my-drive/write-read-only/0x0102-actual-position",
        "profile/my-drive/coil/3-output-4",
    ] {
        assert_eq!(verdict(id), "PASS", "{id}");
    }
    run_passes(None, &["--target", &format!("sim:{}", s(&file))]);
    run_passes(
        None,
        &[
            "--target",
            &format!("sim:{}", s(&file)),
            "--profile",
            s(&file),
        ],
    );
}

/// The indented code block that follows the line containing `after` in `text`, its indentation removed.
fn indented_block(text: &str, after: &str, indent: usize) -> String {
    let pad = " ".repeat(indent);
    let mut out: Vec<&str> = text
        .lines()
        .skip_while(|l| !l.contains(after))
        .skip(1)
        .skip_while(|l| l.trim().is_empty())
        .take_while(|l| l.trim().is_empty() || l.starts_with(&pad))
        .map(|l| l.get(indent..).unwrap_or(""))
        .collect();
    while out.last().is_some_and(|l| l.is_empty()) {
        out.pop();
    }
    out.join("\n") + "\n"
}

#[test]
fn the_readme_walkthrough_works_as_written() {
    let readme = include_str!("../../../../README.md");
    let section = &readme[readme
        .find("## Test your own drive")
        .expect("README section")..];
    let section = &section[..section[3..].find("\n## ").map_or(section.len(), |i| i + 3)];
    assert!(
        section.contains("(corpus/profiles/SCHEMA.md)"),
        "links the schema"
    );
    let sim = SimProcess::start(&["--profile", "generic", "--listen", "127.0.0.1:0"]);
    let addr = sim.tcp.expect("tcp endpoint").to_string();
    let dir = TempDir::new("profile-readme");
    let d = dir.path();
    // The commands of the section, on the simulator's port instead of 5020.
    let command = |line: &str| -> Vec<String> {
        assert!(section.contains(line), "README lacks `{line}`");
        line.replace("127.0.0.1:5020", &addr)
            .split_whitespace()
            .skip(1)
            .map(str::to_string)
            .collect()
    };
    let probe = command(
        "modbus-harness probe --target tcp://127.0.0.1:5020 --scan 0-0x7F --write-profile my.toml",
    );
    let args: Vec<&str> = probe.iter().map(String::as_str).collect();
    let (code, out, err) = harness_in(Some(d), &args);
    assert_eq!(code, 0, "{out}{err}");
    let run = command("modbus-harness run --target tcp://127.0.0.1:5020 --profile my.toml");
    let mut args: Vec<&str> = run.iter().map(String::as_str).collect();
    args.push("--no-progress");
    let (code, first, err) = harness_in(Some(d), &args);
    assert_eq!(code, 0, "the draft passes: {first}{err}");
    // Step 3: the draft block as the README shows it is in the draft; put the README's confirmed text there.
    let drafted = indented_block(section, "For example, a draft block", 7);
    let confirmed = indented_block(section, "confirmed as 100 read/write", 7);
    let text = std::fs::read_to_string(d.join("my.toml")).expect("draft written");
    assert!(
        text.contains(&drafted),
        "the README's draft block is not in the draft:\n{drafted}\n---\n{text}"
    );
    assert!(
        confirmed.contains("access = \"rw\"") && confirmed.contains("code = 0x10"),
        "{confirmed}"
    );
    std::fs::write(d.join("my.toml"), text.replace(&drafted, &confirmed)).expect("edit");
    let (code, second, err) = harness_in(Some(d), &args);
    assert_eq!(code, 0, "the confirmed profile passes: {second}{err}");
    let cases = |out: &str| {
        out.lines()
            .find_map(|l| l.strip_prefix("RESULT: PASS ("))
            .and_then(|l| l.split_whitespace().next())
            .and_then(|n| n.parse::<usize>().ok())
            .unwrap_or(0)
    };
    assert!(
        cases(&second) >= cases(&first) + 100,
        "confirming the registers adds their write cases: {} then {}",
        cases(&first),
        cases(&second)
    );
}
