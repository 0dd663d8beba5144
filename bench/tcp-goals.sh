#!/usr/bin/env bash
# Two goals of issue 17 against `simulate` on 127.0.0.1, beside the raw TCP ping-pong floor in the same run:
#   - the full catalog of each built-in profile (`run --target URL --profile P`, Modbus/TCP for mdrive, lmd
#     and generic, RTU over TCP for sd2x, which speaks RTU only): wall seconds (goal: under 0.2 s);
#   - a generated run (`run --target tcp://SIM --profile generic --generated N --seed 1`): wall seconds
#     (goal for 1,000,000 cases: under 60 s) and peak RSS at N/10 and N cases (goal: flat); and N cases
#     with --read-only, which sends no write and so puts nothing back.
# Every process is pinned to one core; catalog rounds are interleaved; medians.
#
#   bench/tcp-goals.sh [--rounds R] [--core C] [--cases N] [--floor-seconds S] LABEL=BINARY...
#
#   --rounds R         catalog rounds (default 5)
#   --core C           the core everything is pinned to (default 0)
#   --cases N          cases of the larger generated run (default 1000000; 0 skips the generated runs)
#   --floor-seconds S  seconds of the ping-pong floor per round (default 2)
#   LABEL=BINARY       a modbus-harness binary; its own `simulate` serves its runs
#
# Needs gcc, pkg-config, libmodbus-dev (for bench/peers.c), taskset, timeout, /usr/bin/time (Debian package
# `time`). Prints a Markdown table on stdout and progress on stderr. Every process started is stopped at exit;
# every run is bounded by `timeout`.
set -euo pipefail

ROUNDS=5
CORE=0
CASES=1000000
FLOOR_SECS=2
BINS=()
here=$(cd "$(dirname "$0")" && pwd)
. "$here/lib.sh"
bench_parse tcp-goals.sh 2,20 --rounds=ROUNDS --core=CORE --cases=CASES --floor-seconds=FLOOR_SECS \
  LABEL=BINARY -- "$@"
bench_need_bins tcp-goals.sh
for tool in gcc pkg-config taskset timeout; do
  command -v "$tool" >/dev/null || bench_fail tcp-goals.sh "$tool is missing"
done
[ -x /usr/bin/time ] || bench_fail tcp-goals.sh "/usr/bin/time is missing (apt install time)"
bench_servers_workdir tcp-goals.sh
pin=(taskset -c "$CORE")

gcc -O2 -Wall -o "$work/peers" "$here/peers.c" $(pkg-config --cflags --libs libmodbus)

# timed FILE CMD...: run CMD pinned under /usr/bin/time; FILE gets "WALL_SECONDS PEAK_RSS_KIB", CMD's output
# goes to FILE.out. A run whose verdict is FAIL (exit 1) still counts; any other failure stops the script.
timed() {
  local file=$1 rc=0
  shift
  timeout 900 "${pin[@]}" /usr/bin/time -f '%e %M' -o "$file" "$@" >"$file.out" 2>&1 || rc=$?
  if [ "$rc" != 0 ] && [ "$rc" != 1 ]; then
    echo "tcp-goals.sh: $* exited $rc: $(tail -3 "$file.out")" >&2
    exit 1
  fi
}

results="$work/results.tsv"
: >"$results"
pp=$(bench_start tcp-goals.sh "$work" pingpong "$work/peers" pp-server 0)
load_before=$(cut -d' ' -f1-3 /proc/loadavg)
for round in $(seq "$ROUNDS"); do
  floor=$(timeout 60 "${pin[@]}" "$work/peers" pp-client "${pp%:*}" "${pp##*:}" "$FLOOR_SECS" \
    | sed -n 's/^RESULT .*rps=\([0-9.]*\).*/\1/p')
  printf 'floor\t-\t%s\t-\n' "$floor" >>"$results"
  echo "round $round  ping-pong floor  $floor req/s" >&2
  for b in "${BINS[@]}"; do
    label=${b%%=*} bin=${b#*=}
    for p in sd2x mdrive lmd generic; do
      if [ "$p" = sd2x ]; then
        a=$(bench_start tcp-goals.sh "$work" "sim-$label-$p-$round" "$bin" simulate --profile "$p" \
          --rtu-over-tcp 127.0.0.1:0)
        url="rtu+tcp://$a"
      else
        a=$(bench_start tcp-goals.sh "$work" "sim-$label-$p-$round" "$bin" simulate --profile "$p" \
          --listen 127.0.0.1:0)
        url="tcp://$a"
      fi
      timed "$work/t" "$bin" run --target "$url" --profile "$p" --no-progress
      read -r secs _ <"$work/t"
      counts=$(grep -oE '^RESULT: [A-Z-]+ \([^)]*\)' "$work/t.out" | tail -1)
      printf 'catalog\t%s %s\t%s\t%s\n' "$label" "$p" "$secs" "$counts" >>"$results"
      echo "round $round  $label catalog $p over $url: $secs s  $counts" >&2
      kill "$(tail -1 "$work/pids")" 2>/dev/null || true
    done
  done
done

if [ "$CASES" -gt 0 ]; then
  for b in "${BINS[@]}"; do
    label=${b%%=*} bin=${b#*=}
    # The writing cases of a generated run are put back after each (leave as found: the snapshot's reads and
    # the restore's reads and writes); the --read-only run sends no write and so no restore.
    for run in "$((CASES / 10))" "$CASES" "$CASES read-only"; do
      n=${run%% *}
      extra=()
      [ "$run" = "$n" ] || extra=(--read-only)
      a=$(bench_start tcp-goals.sh "$work" "sim-$label-gen-${run// /-}" "$bin" simulate --profile generic \
        --listen 127.0.0.1:0)
      timed "$work/g" "$bin" run --target "tcp://$a" --profile generic --generated "$n" --seed 1 \
        --no-progress "${extra[@]}"
      read -r secs kib <"$work/g"
      counts=$(grep -oE '^RESULT: [A-Z-]+ \([^)]*\)' "$work/g.out" | tail -1)
      restore=$(sed -n 's/.* in \([0-9]*\) request(s).*/\1/p' "$work/g.out" | tail -1)
      printf 'generated\t%s %s\t%s\t%s; %s KiB peak; %s snapshot and restore requests\n' "$label" "$run" \
        "$secs" "$counts" "$kib" "${restore:-0}" >>"$results"
      echo "$label generated $run over TCP: $secs s, peak RSS $kib KiB, $counts, ${restore:-0} restore requests" >&2
      kill "$(tail -1 "$work/pids")" 2>/dev/null || true
    done
  done
fi
load_after=$(cut -d' ' -f1-3 /proc/loadavg)

python3 - "$results" "$ROUNDS" "$load_before" "$load_after" <<'EOF'
import statistics, sys
from collections import defaultdict
path, rounds, lb, la = sys.argv[1:]
v, note, order = defaultdict(list), {}, []
for line in open(path):
    kind, name, x, what = line.rstrip("\n").split("\t")
    key = (kind, name)
    if key not in order:
        order.append(key)
    v[key].append(float(x))
    note[key] = what
floor = statistics.median(v[("floor", "-")])
print(f"Against `simulate` on 127.0.0.1, every process on one core; catalog: {rounds} round(s), medians; "
      f"load average before {lb}, after {la}. Ping-pong floor: {floor:,.0f} req/s "
      f"({1e6 / floor:.1f} µs a request).")
print()
print("| run | wall s (median) | per round | verdicts and notes |")
print("|---|---:|---|---|")
for key in order:
    kind, name = key
    if kind == "floor":
        continue
    label = (f"catalog, {name}" if kind == "catalog" else f"generated over TCP, {name} cases")
    xs = v[key]
    print(f"| {label} | {statistics.median(xs):.2f} | {', '.join(f'{x:.2f}' for x in xs)} | {note[key]} |")
EOF
