#!/usr/bin/env python3
"""Generated runs against reference drives that take random admissible choices (issue 12).

For each target, N times: every freedom the simulator can take for the profile is set, with probability
1/(k+1), to one of its k simulated non-reference values; then the catalog and G generated cases run against
`sim:` with those choices. A conforming drive must give no FAIL: every FAIL printed is either an oracle that
takes a reference choice for a requirement, or a limit of the simulator, and is worth a look. NON-STRICT
counts are printed too (a choice recorded inconsistently).

    python3 bench/freedom-combos.py [--seed S] [--runs N] [--generated G] [--binary PATH]

The binary defaults to target/release/modbus-harness (build it first). Everything runs in process: no
network, no files but the binary's own output.
"""

import argparse
import random
import re
import subprocess
import sys

TARGETS = [
    ("mdrive", "sim:mdrive"),
    ("lmd", "sim:lmd"),
    ("sd2x", "sim:sd2x"),
    ("generic", "sim:generic"),
    ("mdrive", "sim:mdrive?transport=rtu"),
    ("generic", "sim:generic?transport=rtu"),
]


def run(binary, *args):
    r = subprocess.run([binary, *args], capture_output=True, text=True, timeout=600)
    return r.returncode, r.stdout + r.stderr


def space(binary, profile):
    """The simulated non-reference values of every freedom of `profile`, from the binary's own errors."""
    _, out = run(binary, "run", "--target", f"sim:{profile}", "--choose", "no-such-freedom=1")
    m = re.search(r"freedoms of this profile: (.*)", out)
    if not m:
        sys.exit(f"cannot list the freedoms of {profile}: {out}")
    values = {}
    for freedom in m.group(1).split(", "):
        _, out = run(binary, "run", "--target", f"sim:{profile}", "--choose", f"{freedom}=\x01")
        m = re.search(r"admissible: (.*)", out)
        if not m:
            continue
        ok = []
        for v in [v.strip() for v in m.group(1).split(", ")][1:]:
            code, out = run(binary, "run", "--target", f"sim:{profile}", "--choose", f"{freedom}={v}",
                            "--cases", "golden/*", "--no-progress")
            if "error:" not in out:
                ok.append(v)
        if ok:
            values[freedom] = ok
    return values


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--runs", type=int, default=3, help="random configurations per target")
    ap.add_argument("--generated", type=int, default=400)
    ap.add_argument("--binary", default="target/release/modbus-harness")
    ap.add_argument("--nonstrict", action="store_true",
                    help="print the choices a run saw changed (NON-STRICT), with the run's choices")
    a = ap.parse_args()
    rng = random.Random(a.seed)
    spaces = {}
    fails = 0
    for profile, target in TARGETS:
        if profile not in spaces:
            spaces[profile] = space(a.binary, profile)
        for k in range(a.runs):
            choose = []
            for freedom, vs in spaces[profile].items():
                i = rng.randrange(len(vs) + 1)
                if i < len(vs):
                    choose.append(f"{freedom}={vs[i]}")
            seed = a.seed * 100 + k
            args = ["run", "--target", target, "--no-progress", "--no-shrink", "--with-catalog",
                    "--generated", str(a.generated), "--seed", str(seed)]
            for c in choose:
                args += ["--choose", c]
            _, out = run(a.binary, *args)
            result = next((l for l in out.splitlines() if l.startswith("RESULT")), "no RESULT: " + out[-300:])
            lines = out.splitlines()
            failed = [f"{l} | {lines[i + 1].strip() if i + 1 < len(lines) else ''}"
                      for i, l in enumerate(lines) if l.startswith("FAIL ")]
            nonstrict = [l.strip() for l in lines if " then " in l and l.startswith("  ")]
            fails += len(failed)
            print(f"{target} seed {seed}: {result}")
            for f in failed:
                print(f"    {f}")
            if a.nonstrict:
                for n in nonstrict:
                    print(f"    NON-STRICT: {n}")
            if failed or (a.nonstrict and (nonstrict or "NON-STRICT" in result)):
                print("    choices: " + " ".join(f"--choose '{c}'" for c in choose))
    print(f"FAIL in all: {fails}")


if __name__ == "__main__":
    main()
