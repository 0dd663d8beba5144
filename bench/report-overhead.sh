#!/usr/bin/env bash
# What `--report` adds to a generated run: wall time of
#   modbus-harness run --target sim:PROFILE --generated N --seed 1 --no-progress [--report DIR]
# without and with the report, for one or more binaries side by side, rounds interleaved, and the ratio of the
# medians. The run is in process (no network).
#
#   bench/report-overhead.sh [--cases N] [--rounds R] [--profile P] [--dir D] [--pin CORES]... LABEL=BINARY...
#
#   --cases N    generated cases per run (default 100000)
#   --rounds R   rounds (default 3); each round runs every binary without and with --report
#   --profile P  the sim: profile (default mdrive)
#   --dir D      where the report directory goes (default $TMPDIR or /tmp; its file system decides part of the
#                cost: a few streamed files, plus one file per case that did not PASS)
#   --pin CORES  taskset core list; repeatable, each one a separate column set (default: "0" and "0,1")
#
# Prints a Markdown table on stdout and progress on stderr. Every run is bounded by `timeout`; the report
# directory is removed after each run and at exit.
set -euo pipefail

CASES=100000
ROUNDS=3
PROFILE=mdrive
DIR=${TMPDIR:-/tmp}
PINS=()
BINS=()
. "$(dirname "$0")/lib.sh"
bench_parse report-overhead.sh 2,18 --cases=CASES --rounds=ROUNDS --profile=PROFILE --dir=DIR --pin+=PINS \
  LABEL=BINARY -- "$@"
bench_need_bins report-overhead.sh
[ ${#PINS[@]} -gt 0 ] || PINS=(0 0,1)

work=$(mktemp -d "$DIR/report-overhead.XXXXXX")
trap 'rm -rf "$work"' EXIT
trap 'exit 130' INT TERM
limit=$((60 + CASES / 500))
results="$work/results.tsv"
: >"$results"

# one LABEL BIN PIN MODE: one timed run, appends "LABEL PIN MODE SECONDS".
one() {
  local label=$1 bin=$2 pin=$3 mode=$4 extra=() t0 t1
  [ "$mode" = report ] && extra=(--report "$work/rep")
  t0=$(date +%s.%N)
  timeout "$limit" taskset -c "$pin" "$bin" run --target "sim:$PROFILE" --generated "$CASES" --seed 1 \
    --no-progress "${extra[@]}" >"$work/out" 2>&1 || [ $? = 1 ] || {
    echo "run failed: $label $pin $mode: $(tail -3 "$work/out")" >&2; exit 1; }
  t1=$(date +%s.%N)
  rm -rf "$work/rep"
  printf '%s\t%s\t%s\t%s\n' "$label" "$pin" "$mode" "$(python3 -c "print(f'{$t1 - $t0:.3f}')")" >>"$results"
  echo "round $round  $label  pin $pin  $mode  $(tail -1 "$results" | cut -f4) s" >&2
}

load_before=$(cut -d' ' -f1-3 /proc/loadavg)
for round in $(seq "$ROUNDS"); do
  for pin in "${PINS[@]}"; do
    for b in "${BINS[@]}"; do
      one "${b%%=*}" "${b#*=}" "$pin" plain
      one "${b%%=*}" "${b#*=}" "$pin" report
    done
  done
done
load_after=$(cut -d' ' -f1-3 /proc/loadavg)

python3 - "$results" "$CASES" "$PROFILE" "$load_before" "$load_after" "$(df -T "$DIR" | awk 'NR==2 {print $2}')" <<'EOF'
import statistics, sys
from collections import defaultdict
path, cases, profile, lb, la, fs = sys.argv[1:]
t = defaultdict(list)
order = []
for line in open(path):
    label, pin, mode, secs = line.rstrip("\n").split("\t")
    t[(label, pin, mode)].append(float(secs))
    if (label, pin) not in order:
        order.append((label, pin))
n = int(cases)
print(f"{n:,} generated cases, sim:{profile}, report directory on {fs}; medians of {len(next(iter(t.values())))} "
      f"interleaved rounds; load average {lb} before, {la} after")
print()
print("| binary | cores (taskset -c) | without --report s | with --report s | cases/s with | with / without |")
print("|---|---|---:|---:|---:|---:|")
for label, pin in order:
    a = statistics.median(t[(label, pin, "plain")])
    b = statistics.median(t[(label, pin, "report")])
    print(f"| {label} | {pin} | {a:.2f} | {b:.2f} | {n / b:,.0f} | {b / a:.2f} |")
EOF
