#!/usr/bin/env bash
# The live campaign of issue 17 beside the wire's floor, binaries side by side: exec/s of
#   modbus-harness fuzz --target tcp://SIM --profile P --seed 1 --duration S
# against `simulate --profile P` on 127.0.0.1, and the raw TCP ping-pong floor (bench/peers.c) in the same
# rounds, every process pinned to one core, rounds interleaved, medians.
#
#   bench/live-campaign.sh [--seconds S] [--rounds R] [--profile P] [--core C] [--sim BIN] LABEL=BINARY...
#
#   --seconds S  seconds per campaign and per floor figure (default 5)
#   --rounds R   rounds (default 3)
#   --profile P  drive profile of the simulator and the campaign (default mdrive)
#   --core C     the core everything is pinned to (default 0)
#   --sim BIN    the binary whose `simulate` serves (default: the last LABEL=BINARY); one simulator per round,
#                so every binary of a round fuzzes the same server
#   LABEL=BINARY a modbus-harness binary to measure, with `--no-sentinel` as a second row when LABEL ends in +w,
#                and with `--pipeline 1` (one request at a time; the binary's default pipelines) as another
#                row when it ends in +p (+wp: both)
#
# Needs gcc, pkg-config, libmodbus-dev (for bench/peers.c), taskset, timeout. Prints a Markdown table on
# stdout and progress on stderr. Every process started is stopped at exit; every run is bounded by `timeout`.
set -euo pipefail

SECS=5
ROUNDS=3
PROFILE=mdrive
CORE=0
SIM=
BINS=()
here=$(cd "$(dirname "$0")" && pwd)
. "$here/lib.sh"
bench_parse live-campaign.sh 2,18 --seconds=SECS --rounds=ROUNDS --profile=PROFILE --core=CORE --sim=SIM \
  LABEL=BINARY -- "$@"
bench_need_bins live-campaign.sh
[ -n "$SIM" ] || SIM=${BINS[-1]#*=}
# Servers are started inside $(...) (bench_start): their pids go to a file, stopped at exit.
bench_servers_workdir live-campaign.sh
pin=(taskset -c "$CORE")
limit=$(python3 -c "print(int($SECS) + 30)")

gcc -O2 -Wall -o "$work/peers" "$here/peers.c" $(pkg-config --cflags --libs libmodbus)

results="$work/results.tsv"
: >"$results"
pp=$(bench_start live-campaign.sh "$work" pingpong "$work/peers" pp-server 0)
load_before=$(cut -d' ' -f1-3 /proc/loadavg)
for round in $(seq "$ROUNDS"); do
  sim=$(bench_start live-campaign.sh "$work" "sim$round" "$SIM" simulate --profile "$PROFILE" --listen 127.0.0.1:0)
  floor=$(timeout "$limit" "${pin[@]}" "$work/peers" pp-client "${pp%:*}" "${pp##*:}" "$SECS" \
    | sed -n 's/^RESULT .*rps=\([0-9.]*\).*/\1/p')
  printf 'floor\t%s\n' "$floor" >>"$results"
  echo "round $round  ping-pong floor  $floor req/s" >&2
  for b in "${BINS[@]}"; do
    label=${b%%=*} bin=${b#*=}
    flags=${label##*+}
    [ "$flags" != "$label" ] || flags=
    for mode in sentinel window one-at-a-time; do
      extra=()
      if [ "$mode" = window ]; then
        [[ "$flags" == *w* ]] || continue
        extra=(--no-sentinel)
      fi
      if [ "$mode" = one-at-a-time ]; then
        [[ "$flags" == *p* ]] || continue
        extra=(--pipeline 1)
      fi
      line=$(timeout "$limit" "${pin[@]}" "$bin" fuzz --target "tcp://$sim" --profile "$PROFILE" --seed 1 \
        --duration "${SECS}s" "${extra[@]}" 2>&1 | grep -E '^fuzz: [0-9]+ cases' | tail -1 || true)
      eps=$(sed -n 's/.*(\([0-9]*\) exec\/s).*/\1/p' <<<"$line")
      [ -n "$eps" ] || { echo "live-campaign.sh: $label ($mode) gave no summary" >&2; exit 1; }
      printf '%s\t%s\n' "${label%+*} ($mode)" "$eps" >>"$results"
      # Binaries that print the requests they sent (cases, sentinels, probes, restores) get a row of those.
      rps=$(sed -n 's/.* requests (\([0-9]*\)\/s).*/\1/p' <<<"$line")
      [ -z "$rps" ] || printf '%s\t%s\n' "${label%+*} ($mode), requests" "$rps" >>"$results"
      echo "round $round  ${label%+*} ($mode)  $eps exec/s${rps:+, $rps requests/s}" >&2
    done
  done
  kill "$(tail -1 "$work/pids")" 2>/dev/null || true
done
load_after=$(cut -d' ' -f1-3 /proc/loadavg)

python3 - "$results" "$PROFILE" "$SECS" "$ROUNDS" "$load_before" "$load_after" <<'EOF'
import statistics, sys
from collections import defaultdict
path, profile, secs, rounds, lb, la = sys.argv[1:]
v, order = defaultdict(list), []
for line in open(path):
    k, x = line.rstrip("\n").split("\t")
    if k not in order:
        order.append(k)
    v[k].append(float(x))
floor = statistics.median(v["floor"])
print(f"`fuzz --profile {profile} --seed 1 --duration {secs}s` against `simulate --profile {profile}` on 127.0.0.1, "
      f"{rounds} round(s), medians; load average before {lb}, after {la}.")
print()
print("| client → simulator | exec/s (req/s for the floor and the `requests` rows) | per round | of the ping-pong floor |")
print("|---|---:|---|---:|")
for k in order:
    m = statistics.median(v[k])
    name = "raw TCP ping-pong (the floor)" if k == "floor" else f"`fuzz` {k}"
    if k.endswith(", requests"):
        name = f"`fuzz` {k[: -len(', requests')]}: requests sent"
    print(f"| {name} | {m:,.0f} | {', '.join(f'{x:,.0f}' for x in v[k])} | {m / floor * 100:.1f}% |")
EOF
