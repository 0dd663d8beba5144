#!/usr/bin/env bash
# Pipelined and one-at-a-time live campaigns judged the same (issue 17 item 2): for every fault of
# `simulate --list-faults` and each profile asked for, `fuzz --seed S --max-cases N` against a fresh
# `simulate --profile P --fault F` over Modbus/TCP on 127.0.0.1, once with --pipeline 8 and once with
# --pipeline 1 (each against its own simulator: some faults leave the drive dead), and the first finding of
# each side by side.
#
#   bench/pipeline-faults.sh [--profiles "generic mdrive"] [--cases N] [--seed S] BINARY
#
# Prints a Markdown table on stdout (fault, profile, first finding pipelined, first finding one at a time,
# agree?) and a count of rows that disagree on whether a fault is found; progress on stderr. Every run is
# bounded by `timeout`; every simulator is stopped.
set -euo pipefail

PROFILES="generic mdrive"
CASES=3000
SEED=1
here=$(cd "$(dirname "$0")" && pwd)
. "$here/lib.sh"
BIN=
args=()
for a in "$@"; do
  if [ -z "$BIN" ] && [ -x "$a" ] && [ -f "$a" ]; then BIN=$a; else args+=("$a"); fi
done
bench_parse pipeline-faults.sh 2,12 --profiles=PROFILES --cases=CASES --seed=SEED -- "${args[@]+"${args[@]}"}"
[ -n "$BIN" ] || bench_fail pipeline-faults.sh "give the modbus-harness binary"
work=$(mktemp -d "${TMPDIR:-/tmp}/pipeline-faults.XXXXXX")
sim_pid=
cleanup() {
  [ -z "$sim_pid" ] || kill "$sim_pid" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# first FAULT PROFILE DEPTH: the first finding line of a campaign against a fresh faulted simulator.
first() {
  "$BIN" simulate --profile "$2" --listen 127.0.0.1:0 --fault "$1" >"$work/sim.out" 2>&1 &
  sim_pid=$!
  local addr=
  for _ in $(seq 100); do
    addr=$(sed -n 's/^listening tcp //p' "$work/sim.out" | head -1)
    [ -n "$addr" ] && break
    sleep 0.05
  done
  [ -n "$addr" ] || { echo "pipeline-faults.sh: simulate did not start: $(cat "$work/sim.out")" >&2; exit 1; }
  rm -rf "$work/regressions"
  local line
  line=$(timeout 90 "$BIN" fuzz --target "tcp://$addr" --profile "$2" --seed "$SEED" --max-cases "$CASES" \
    --duration 60s --pipeline "$3" --regressions "$work/regressions" 2>/dev/null \
    | grep -E '^(FAIL|STOPPED ANSWERING|PROBE ANSWERED WRONGLY OR LATE) after ' | head -1 || true)
  kill "$sim_pid" 2>/dev/null || true
  wait "$sim_pid" 2>/dev/null || true
  sim_pid=
  # The kind and the case, without the finding's text.
  sed -E 's/^(FAIL|STOPPED ANSWERING|PROBE ANSWERED WRONGLY OR LATE) after ([^:]*):.*/\1 after `\2`/' <<<"${line:-none}"
}

echo "| fault | profile | first finding, --pipeline 8 | first finding, --pipeline 1 | |"
echo "|---|---|---|---|---|"
differ=0
for fault in $("$BIN" simulate --list-faults | awk '{print $1}'); do
  for p in $PROFILES; do
    a=$(first "$fault" "$p" 8)
    b=$(first "$fault" "$p" 1)
    if [ "$a" = "$b" ]; then
      mark="same"
    elif [ "$a" = none ] || [ "$b" = none ]; then
      mark="**found by one only**"
      differ=$((differ + 1))
    elif [[ "$a" == *'`fuzz/pipeline/'* ]]; then
      mark="found first by the burst"
    else
      mark="both found, other case"
    fi
    echo "| $fault | $p | $a | $b | $mark |"
    echo "$fault $p: $a | $b" >&2
  done
done
echo
echo "Faults found by one mode and not the other: $differ."
