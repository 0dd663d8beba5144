//! The CI snippets of `ci-examples/` are YAML that GitHub Actions and GitLab CI read, and every
//! `modbus-harness` command in them names a subcommand and options the binary has (its `--help`); each has
//! the three gates: the run's exit code, the JUnit artifact, the snapshot.

use std::path::{Path, PathBuf};
use std::process::Command;

use test_support::{runs, skip, test_name};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_modbus-harness"))
        .args(args)
        .arg("--help")
        .output()
        .expect("run the binary");
    assert!(out.status.success(), "{args:?} --help");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Every shell line of the YAML file (GitHub `run:`, GitLab `script:`), parsed by PyYAML.
fn shell_lines(file: &Path) -> Vec<String> {
    const WALK: &str = r#"
import json, sys, yaml
doc = yaml.safe_load(open(sys.argv[1]))
out = []
def walk(node, key=None):
    if isinstance(node, dict):
        for k, v in node.items():
            walk(v, k)
    elif isinstance(node, list):
        for v in node:
            walk(v, key)
    elif isinstance(node, str) and key in ("run", "script"):
        out.extend(l for l in node.splitlines() if l.strip())
walk(doc)
print(json.dumps({"lines": out}))
"#;
    let out = Command::new("python3")
        .args(["-c", WALK])
        .arg(file)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "{} is not valid YAML: {}",
        file.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    v["lines"]
        .as_array()
        .expect("lines")
        .iter()
        .map(|l| l.as_str().expect("a string").to_string())
        .collect()
}

#[test]
fn ci_examples_parse_and_run_only_commands_the_cli_has() {
    if !runs("python3", &["-c", "import yaml"]) {
        assert!(
            std::env::var_os("CI").is_none(),
            "PyYAML is missing in CI: .ci/python-peers installs it"
        );
        skip(
            test_name!(),
            "python3 has no yaml module (pip install pyyaml)",
        );
        return;
    }
    let top = help(&[]);
    for name in ["github-actions.yml", "gitlab-ci.yml"] {
        let file = workspace().join("ci-examples").join(name);
        let lines = shell_lines(&file);
        let mut commands = 0;
        let (mut gate, mut junit, mut snapshot) = (false, false, false);
        for line in &lines {
            if let Some(path) = line.split("cargo install --locked --path ").nth(1) {
                let path = path.split_whitespace().next().expect("a path");
                assert!(
                    workspace().join(path).join("Cargo.toml").is_file(),
                    "{name}: {path}"
                );
            }
            let Some(rest) = line.trim().strip_prefix("modbus-harness ") else {
                continue;
            };
            commands += 1;
            let words: Vec<&str> = rest.split_whitespace().collect();
            let sub = words[0];
            assert!(
                top.contains(&format!("\n  {sub} ")),
                "{name}: `{sub}` is not a subcommand:\n{top}"
            );
            let sub_help = help(&[sub]);
            for w in words.iter().filter(|w| w.starts_with("--")) {
                let flag = w.split('=').next().unwrap_or(w);
                assert!(
                    sub_help.contains(&format!("{flag} "))
                        || sub_help.contains(&format!("{flag}\n")),
                    "{name}: `{sub}` has no option {flag}"
                );
            }
            if sub == "run" {
                gate = true;
                junit |= words.contains(&"--report");
                snapshot |= words.contains(&"--snapshot");
            }
        }
        assert!(commands >= 3, "{name}: {lines:?}");
        assert!(
            gate && junit && snapshot,
            "{name}: exit code, JUnit and snapshot gates"
        );
        let text = std::fs::read_to_string(&file).expect("read");
        assert!(
            text.contains("out/"),
            "{name}: the report directory is kept as an artifact"
        );
    }
}
