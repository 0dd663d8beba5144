#!/usr/bin/env bash
# Time to first finding of the seeded live fuzz campaign, per simulator fault:
#
#   modbus-harness simulate --profile P --listen 127.0.0.1:0 --fault F          (pinned, port 0)
#   modbus-harness fuzz --target tcp://127.0.0.1:PORT --profile P --seed S --duration 30s
#
# for every fault of `simulate --list-faults` and seeds 1..5, and prints a Markdown table: fault → profile,
# median time to the first finding (or "not found in 30 s"), the five times. `fuzz` does not print its time
# to first finding, so the time is measured from the start of the `fuzz` process to its first `finding:`
# line on stderr (process start-up, connection and profile loading included).
#
#   bench/first-finding.sh [--bin PATH] [--seeds N] [--duration SECS] [--core C] [--faults F,F,...]
#
#   --bin PATH       the modbus-harness binary (default: target/release/modbus-harness, built if missing)
#   --seeds N        seeds 1..N (default 5)
#   --duration SECS  each campaign's --duration (default 30)
#   --core C         the core both processes are pinned to with taskset (default 0)
#   --faults LIST    only these faults (comma-separated)
#   --profile P      use profile P for every fault instead of the one chosen below
#   --allow-writes   add --allow-writes to every campaign (against a real target `fuzz` sends reads only
#                    without it, so faults that only a write shows cannot be found)
#   --allow-destructive, --allow-motion
#                    add these to every campaign too (with --allow-writes): FC 08 state changes (08/0A clear
#                    counters, 08/01 restart, 08/04 listen only) are destructive, FC 15 file records rate as
#                    motion and destructive (the classifier cannot tell what a file holds)
#   --expect TEXT    count only a `finding:` line containing TEXT (e.g. the case kind `comm-event-log`), and
#                    run the campaigns with --keep-going so that another finding does not end them first
#   --timeout MS, --preflight-timeout MS, --silence MS
#                    pass these to every campaign (defaults of `fuzz`: 1000, 3000 and 300 ms, made for a real
#                    drive; a fault whose finding is an answer that does not come is found after them, and
#                    over RTU over TCP every broadcast and request to another address listens out --silence)
#
# The profile is the one whose behaviour the fault concerns: sd2x for the DS402/watchdog faults,
# write-quantity-over-limit-dropped (the only FC 17 write limit below 121) and the FC 04 its manual lists,
# mdrive for the MDrive/LMD mnemonic faults, word order, 32-bit halves, undeclared functions, the inputs'
# bit order (its inputs are not all off) and the range codes (its registers have ranges), generic (which
# declares the whole public function code set) for the rest. RTU-only faults (those of framing and of the serial line's
# state: the event log after a restart, listen only mode) are run over RTU over TCP
# (`simulate --rtu-over-tcp`, `fuzz --target rtu+tcp://`). Reproducers go to a temporary directory. Once three
# seeds of a fault found nothing the median is "not found" and its other seeds are not run.
#
# Loopback only; every campaign is bounded by --duration and a hard limit of duration + 15 s; every process
# started is stopped by its pid when its campaign ends and when the script exits or is interrupted.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
BIN=""
SEEDS=5
DURATION=30
CORE=0
FAULTS=""
WRITES=""
PROFILE=""
EXPECT=""
TIMEOUT=""
PREFLIGHT=""
SILENCE=""
. "$here/lib.sh"
bench_parse first-finding.sh 2,40 --bin=BIN --seeds=SEEDS --duration=DURATION --core=CORE --faults=FAULTS \
  --allow-writes@=WRITES --allow-destructive@=WRITES --allow-motion@=WRITES --profile=PROFILE \
  --expect=EXPECT --timeout=TIMEOUT --preflight-timeout=PREFLIGHT --silence=SILENCE -- "$@"
[ -z "$TIMEOUT" ] || WRITES="$WRITES --timeout $TIMEOUT"
[ -z "$SILENCE" ] || WRITES="$WRITES --silence $SILENCE"
[ -z "$PREFLIGHT" ] || WRITES="$WRITES --preflight-timeout $PREFLIGHT"
for tool in python3 taskset; do
  command -v "$tool" >/dev/null || { echo "first-finding.sh: $tool is missing" >&2; exit 1; }
done
if [ -z "$BIN" ]; then
  BIN="$root/target/release/modbus-harness"
  [ -x "$BIN" ] || (cd "$root" && cargo build --release --bin modbus-harness >&2)
fi

exec python3 - "$BIN" "$SEEDS" "$DURATION" "$CORE" "$FAULTS" "$WRITES" "$PROFILE" "$EXPECT" <<'EOF'
import os, select, signal, statistics, subprocess, sys, tempfile, time

bin_, seeds, duration, core, only = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
extra = sys.argv[6].split()
forced = sys.argv[7]
expect = sys.argv[8].encode()
if expect:
    extra.append("--keep-going")
pin = ["taskset", "-c", core]
procs = []

def stop(p):
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()

def stop_all(*_):
    for p in procs:
        stop(p)
    procs.clear()

def on_signal(sig, _frame):
    stop_all()
    sys.exit(128 + sig)

signal.signal(signal.SIGINT, on_signal)
signal.signal(signal.SIGTERM, on_signal)

# answer-other-unit: on Modbus/TCP the generic and MDrive profiles answer every unit id (unit_ids 0-255), so
# the fault changes nothing there; on RTU a frame for another address must go unanswered.
RTU_ONLY = {"wrong-crc", "broadcast-answered", "counters-frozen", "crc-unchecked", "event-log-oldest-first",
            "listen-only-ignored", "answer-other-unit", "broadcast-write-ignored", "answer-inside-silence"}
# input-bits-reversed: the MDrive's inputs are not all off (the generic drive's are, and reversed zeros are
# zeros); range-code-inconsistent: the MDrive has ranged registers (the generic drive's take any value).
MDRIVE = {"write-only-readable", "mnemonic-params-unchecked", "half-register-widened", "word-order",
          "undeclared-function-served", "vendor-write-not-applied", "input-bits-reversed",
          "range-code-inconsistent"}
# listed-function-refused: the SD2x lists FC 04 (the generic drive too, but the fault concerns the manual's list).
SD2X = {"watchdog-disabled", "write-quantity-over-limit-dropped", "ds402-enable-from-switch-on-disabled",
        "speed-without-enable", "watchdog-from-first-write", "listed-function-refused"}

def profile_of(fault):
    if forced:
        return forced
    # write-quantity-over-limit-dropped: only a profile whose FC 17 write limit is below the spec's (the SD2x).
    if fault in SD2X:
        return "sd2x"
    return "mdrive" if fault in MDRIVE else "generic"

def lines_until(p, stream, deadline, want, containing=b""):
    """Read `stream` of `p` line by line until a line starting with `want` (and containing `containing`); its
    time, or None."""
    buf = b""
    fd = stream.fileno()
    while time.monotonic() < deadline:
        r, _, _ = select.select([fd], [], [], max(0.0, min(0.5, deadline - time.monotonic())))
        if not r:
            if p.poll() is not None:
                return None, buf
            continue
        chunk = os.read(fd, 65536)
        if not chunk:
            return None, buf
        buf += chunk
        for line in buf.split(b"\n")[:-1]:
            if line.startswith(want) and containing in line:
                return time.monotonic(), line
        buf = buf[buf.rfind(b"\n") + 1:] if b"\n" in buf else buf
    return None, buf

def campaign(fault, seed, regressions):
    profile = profile_of(fault)
    rtu = fault in RTU_ONLY
    listen = ["--rtu-over-tcp" if rtu else "--listen", "127.0.0.1:0"]
    sim = subprocess.Popen(pin + [bin_, "simulate", "--profile", profile, *listen, "--fault", fault],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    procs.append(sim)
    try:
        _, line = lines_until(sim, sim.stdout, time.monotonic() + 10, b"listening ")
        if not line or not line.startswith(b"listening "):
            raise RuntimeError(f"simulate --fault {fault} did not start")
        addr = line.decode().split()[-1]
        scheme = "rtu+tcp" if rtu else "tcp"
        t0 = time.monotonic()
        fuzz = subprocess.Popen(pin + [bin_, "fuzz", "--target", f"{scheme}://{addr}", "--profile", profile,
                                       "--seed", str(seed), "--duration", f"{duration}s",
                                       "--regressions", regressions, *extra],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        procs.append(fuzz)
        try:
            at, line = lines_until(fuzz, fuzz.stderr, t0 + duration + 15, b"finding:", expect)
        finally:
            stop(fuzz)
            if fuzz in procs:
                procs.remove(fuzz)
        return (None, None) if at is None else (at - t0, line)
    finally:
        stop(sim)
        if sim in procs:
            procs.remove(sim)

faults = subprocess.run([bin_, "simulate", "--list-faults"], capture_output=True, text=True, check=True)
faults = [l.split()[0] for l in faults.stdout.splitlines() if l.strip()]
if only:
    faults = [f for f in faults if f in only.split(",")]

load_before = open("/proc/loadavg").read().split()[:3]
started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
rows = []
with tempfile.TemporaryDirectory(prefix="first-finding.") as regressions:
    for fault in faults:
        times = []
        for seed in range(1, seeds + 1):
            t, line = campaign(fault, seed, regressions)
            times.append(t)
            # The finding itself, so that one that is not the fault's shows (see --expect).
            what = "" if line is None else " (" + line.decode(errors="replace").strip()[:200] + ")"
            print(f"first-finding: {fault} seed {seed}: "
                  f"{'not found' if t is None else f'{t:.2f} s'}{what}", file=sys.stderr, flush=True)
            if sum(x is None for x in times) * 2 > seeds:
                break
        found = sorted(x for x in times if x is not None)
        if len(found) * 2 > seeds:
            # Missing seeds count as not found (infinite): the median is the middle of all `seeds` values.
            ranked = found + [float("inf")] * (seeds - len(found))
            median = f"{statistics.median_low(ranked):.2f} s" if seeds % 2 else f"{statistics.median(ranked):.2f} s"
        else:
            median = f"not found in {duration} s"
        shown = ", ".join("–" if x is None else f"{x:.2f}" for x in times)
        rows.append((fault, profile_of(fault) + (" (rtu+tcp)" if fault in RTU_ONLY else ""), median, shown))
load_after = open("/proc/loadavg").read().split()[:3]

print(f"Run {started}, {os.cpu_count()} cores, both processes pinned to core {core}; "
      f"load average {' '.join(load_before)} before, {' '.join(load_after)} after; seeds 1..{seeds}, "
      f"--duration {duration}s{''.join(' ' + e for e in extra)}; time from the start of `fuzz` to its first `finding:` line"
      f"{' containing ' + repr(expect.decode()) if expect else ''}.")
print()
print("| fault | profile | median time to first finding | per seed (s; – not found) |")
print("|---|---|---:|---|")
for r in rows:
    print("| " + " | ".join(r) + " |")
EOF
