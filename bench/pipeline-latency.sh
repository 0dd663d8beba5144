#!/usr/bin/env bash
# Pipelined live campaigns (issue 17 item 2) where they pay: `fuzz` against `simulate` over Modbus/TCP,
# directly and behind bench/delay-proxy.py (a fixed one-way latency per direction, as a drive on a network
# would have), with --pipeline 1 (one request at a time) and the depths asked for, side by side in the same
# rounds, every process pinned to one core, rounds interleaved, medians.
#
#   bench/pipeline-latency.sh [--seconds S] [--rounds R] [--profile P] [--core C] [--delays "0 0.5"]
#                             [--depths "1 8 16"] BINARY
#
#   --seconds S     seconds per campaign (default 5)
#   --rounds R      rounds (default 3)
#   --profile P     drive profile of the simulator and the campaign (default generic)
#   --core C        the core everything is pinned to (default 0)
#   --delays LIST   one-way delays in ms; 0 is the simulator without the proxy (default "0 0.5")
#   --depths LIST   values of --pipeline (default "1 8 16")
#   BINARY          the modbus-harness binary (serves and fuzzes)
#
# Needs python3, taskset, timeout. Prints a Markdown table on stdout and progress on stderr. Every process
# started is stopped at exit; every run is bounded by `timeout`.
set -euo pipefail

SECS=5
ROUNDS=3
PROFILE=generic
CORE=0
DELAYS="0 0.5"
DEPTHS="1 8 16"
here=$(cd "$(dirname "$0")" && pwd)
. "$here/lib.sh"
BIN=
args=()
for a in "$@"; do
  case "$a" in
    -*|*=*) args+=("$a") ;;
    *) if [ -z "$BIN" ] && [ -x "$a" ]; then BIN=$a; else args+=("$a"); fi ;;
  esac
done
bench_parse pipeline-latency.sh 2,19 --seconds=SECS --rounds=ROUNDS --profile=PROFILE --core=CORE \
  --delays=DELAYS --depths=DEPTHS -- "${args[@]+"${args[@]}"}"
[ -n "$BIN" ] || bench_fail pipeline-latency.sh "give the modbus-harness binary"
# Servers are started inside $(...) (bench_start): their pids go to a file, stopped at exit.
bench_servers_workdir pipeline-latency.sh
pin=(taskset -c "$CORE")
limit=$(python3 -c "print(int($SECS) + 30)")

results="$work/results.tsv"
: >"$results"
load_before=$(cut -d' ' -f1-3 /proc/loadavg)
for round in $(seq "$ROUNDS"); do
  sim=$(bench_start pipeline-latency.sh "$work" "sim$round" "$BIN" simulate --profile "$PROFILE" --listen 127.0.0.1:0)
  for delay in $DELAYS; do
    target=$sim
    if [ "$delay" != 0 ]; then
      target=$(bench_start pipeline-latency.sh "$work" "proxy$round-$delay" python3 "$here/delay-proxy.py" --to "$sim" --delay-ms "$delay")
    fi
    for depth in $DEPTHS; do
      line=$(timeout "$limit" "${pin[@]}" "$BIN" fuzz --target "tcp://$target" --profile "$PROFILE" --seed 1 \
        --duration "${SECS}s" --pipeline "$depth" 2>&1 | grep -E '^fuzz: [0-9]+ cases' | tail -1 || true)
      eps=$(sed -n 's/.*(\([0-9]*\) exec\/s).*/\1/p' <<<"$line")
      [ -n "$eps" ] || { echo "pipeline-latency.sh: delay $delay, depth $depth gave no summary" >&2; exit 1; }
      share=$(python3 -c "import re,sys; m=re.match(r'fuzz: (\d+) cases(?: \((\d+) pipelined)?', sys.argv[1]); print(f'{int(m.group(2) or 0)/int(m.group(1))*100:.0f}')" "$line")
      printf '%s\t%s\t%s\t%s\n' "$delay" "$depth" "$eps" "$share" >>"$results"
      echo "round $round  delay $delay ms  --pipeline $depth  $eps exec/s ($share% of the cases pipelined)" >&2
    done
  done
  while read -r p; do kill "$p" 2>/dev/null || true; done <"$work/pids"
  : >"$work/pids"
done
load_after=$(cut -d' ' -f1-3 /proc/loadavg)

python3 - "$results" "$PROFILE" "$SECS" "$ROUNDS" "$load_before" "$load_after" <<'EOF'
import statistics, sys
from collections import defaultdict
path, profile, secs, rounds, lb, la = sys.argv[1:]
v, share, order = defaultdict(list), defaultdict(list), []
for line in open(path):
    d, k, x, s = line.rstrip("\n").split("\t")
    if (d, k) not in order:
        order.append((d, k))
    v[(d, k)].append(float(x))
    share[(d, k)].append(float(s))
print(f"`fuzz --profile {profile} --seed 1 --duration {secs}s --pipeline K` against `simulate --profile {profile}`, "
      f"{rounds} round(s), medians; load average before {lb}, after {la}.")
print()
print("| one-way delay | --pipeline | exec/s | per round | cases pipelined | of --pipeline 1 |")
print("|---|---:|---:|---|---:|---:|")
for d, k in order:
    m = statistics.median(v[(d, k)])
    base = statistics.median(v.get((d, "1"), [m]))
    where = "none (direct)" if d == "0" else f"{d} ms (delay-proxy.py)"
    print(f"| {where} | {k} | {m:,.0f} | {', '.join(f'{x:,.0f}' for x in v[(d, k)])} | "
          f"{statistics.median(share[(d, k)]):.0f}% | {m / base:.2f}× |")
EOF
