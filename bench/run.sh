#!/usr/bin/env bash
# The benchmark of BENCHMARKS.md, in one run: the harness and its simulator side by side with libmodbus,
# pymodbus and a raw TCP ping-pong, FC 03 reads of 2 registers, one connection, one request at a time,
# every process pinned to the same core, loopback only.
#
#   bench/run.sh [--smoke] [--seconds S] [--rounds R] [--core C] [--cases N] [--out FILE] [--no-build]
#
#   --seconds S   timed seconds per figure and round (default 3)
#   --rounds R    rounds; every figure is measured once per round, in the same order (default 5); the table
#                 gives the median of the rounds and ratios of medians
#   --core C      the core everything is pinned to (default 0)
#   --cases N     cases of the memory run (default 1000000)
#   --report-cases N  cases of the memory run that also writes --report (every case in cases.jsonl, a file
#                 per non-PASS case; default 100000)
#   --out FILE    also write the Markdown table to FILE
#   --smoke       for CI: debug build, 0.2 s per figure, 1 round, 2,000-case memory runs; checks that every
#                 figure was produced (not its value) and exits non-zero otherwise. About 30 s after the build.
#   --no-build    use the binaries already built (release, or debug with --smoke, in cargo's target directory)
#
# Needs gcc, pkg-config and libmodbus-dev, python3 with pymodbus, socat, taskset (the packages .ci/run
# installs); peak RSS comes from /usr/bin/time -v (Debian package `time`), or from the same getrusage figure
# through bench/peers.c where that is not installed. Every process it starts is stopped by its pid on exit, Ctrl-C or timeout; the whole run
# is bounded by a watchdog. Prints the table on stdout and progress on stderr.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/.." && pwd)
SECS=3
ROUNDS=5
CORE=0
CASES=1000000
REPORT_CASES=100000
OUT=""
SMOKE=0
BUILD=1
while [ $# -gt 0 ]; do
  case "$1" in
    --smoke) SMOKE=1 ;;
    --seconds) SECS=$2; shift ;;
    --rounds) ROUNDS=$2; shift ;;
    --core) CORE=$2; shift ;;
    --cases) CASES=$2; shift ;;
    --report-cases) REPORT_CASES=$2; shift ;;
    --out) OUT=$2; shift ;;
    --no-build) BUILD=0 ;;
    -h|--help) sed -n '2,24p' "$0"; exit 0 ;;
    *) echo "bench/run.sh: unknown argument $1" >&2; exit 2 ;;
  esac
  shift
done
if [ "$SMOKE" = 1 ]; then
  SECS=0.2
  ROUNDS=1
  CASES=2000
  REPORT_CASES=500
fi

log() { printf 'bench: %s\n' "$*" >&2; }
die() { log "error: $*"; exit 1; }

for tool in gcc pkg-config python3 socat taskset timeout; do
  command -v "$tool" >/dev/null || die "$tool is missing (see BENCHMARKS.md, Requirements)"
done
pkg-config --exists libmodbus || die "libmodbus-dev is missing"
python3 -c 'import pymodbus' 2>/dev/null || die "python3 -c 'import pymodbus' fails (pip install 'pymodbus[serial]')"

work=$(mktemp -d "${TMPDIR:-/tmp}/modbus-bench.XXXXXX")
pids=()
stop_all() {
  local pid
  for pid in "${pids[@]}"; do
    kill "$pid" 2>/dev/null || true
  done
  for pid in "${pids[@]}"; do
    wait "$pid" 2>/dev/null || true
  done
  pids=()
}
cleanup() {
  local rc=$?
  stop_all
  rm -rf "$work"
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Watchdog: the whole run is bounded (builds included). It signals this script, whose EXIT trap stops the
# rest; stopped by its pid, it stops its own sleep first, so nothing is left behind.
figures=19
budget=$(python3 -c "print(int(900 + $ROUNDS * $figures * ($SECS + 3) + $CASES / 20000))")
watchdog() {
  ( trap 'kill "$s" 2>/dev/null; exit 0' TERM
    sleep "$budget" & s=$!
    wait "$s" && { log "watchdog: over ${budget}s, stopping"; kill -TERM $$; } ) 2>/dev/null &
  pids+=($!)
}
watchdog

# --- build ---------------------------------------------------------------------------------------------------
cd "$root"
if [ "$SMOKE" = 1 ]; then cargo_profile=(); prof_dir=debug; else cargo_profile=(--release); prof_dir=release; fi
gcc -O2 -Wall -o "$work/peers" "$here/peers.c" $(pkg-config --cflags --libs libmodbus)
if [ "$BUILD" = 1 ]; then
  log "building (${prof_dir})"
  cargo build "${cargo_profile[@]}" --bin modbus-harness >&2
  cargo build "${cargo_profile[@]}" --bench wire --message-format=json >"$work/build.json"
else
  cargo build "${cargo_profile[@]}" --bench wire --message-format=json --offline >"$work/build.json" 2>/dev/null
fi
# The target directory as cargo resolves it (CARGO_TARGET_DIR, build.target-dir, or $root/target).
target_dir=$(cargo metadata --format-version 1 --no-deps --offline |
  python3 -c 'import json, sys; print(json.load(sys.stdin)["target_directory"])')
mh="$target_dir/$prof_dir/modbus-harness"
wire=$(python3 -c '
import json, sys
for line in open(sys.argv[1]):
    try: m = json.loads(line)
    except ValueError: continue
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "wire" and m.get("executable"):
        print(m["executable"])' "$work/build.json" | tail -1)
[ -x "$mh" ] && [ -x "$wire" ] || die "build products missing ($mh, $wire)"

pin=(taskset -c "$CORE")

# --- servers -------------------------------------------------------------------------------------------------
# start NAME CMD...: start a pinned server, wait for its `listening ...` line, set ${NAME}_addr.
start() {
  local name=$1; shift
  "${pin[@]}" "$@" >"$work/$name.out" 2>"$work/$name.err" &
  pids+=($!)
  local i line
  for i in $(seq 200); do
    line=$(grep -m1 '^listening ' "$work/$name.out" 2>/dev/null || true)
    [ -n "$line" ] && break
    sleep 0.05
  done
  [ -n "$line" ] || { cat "$work/$name.err" >&2; die "$name did not start"; }
  printf -v "${name}_addr" '%s' "${line##* }"
}
load_before=$(cut -d' ' -f1-3 /proc/loadavg)
log "starting servers on core $CORE"
start pp "$work/peers" pp-server 0
start lm "$work/peers" lm-server tcp 0
start sim "$mh" simulate --profile generic --listen 127.0.0.1:0
start py python3 "$here/pymodbus_peers.py" server 0
"${pin[@]}" socat pty,raw,echo=0,link="$work/ttyA" pty,raw,echo=0,link="$work/ttyB" 2>"$work/socat.err" &
pids+=($!)
for i in $(seq 100); do [ -e "$work/ttyA" ] && [ -e "$work/ttyB" ] && break; sleep 0.05; done
[ -e "$work/ttyB" ] || die "socat made no pty pair"
start lmrtu "$work/peers" lm-server rtu "$work/ttyA" 115200

host() { echo "${1%:*}"; }
port() { echo "${1##*:}"; }

# --- figures -------------------------------------------------------------------------------------------------
results="$work/results.tsv"
: >"$results"
# figure NAME CMD...: run a pinned client, bounded, and record its RESULT line.
figure() {
  local name=$1; shift
  local line
  line=$(timeout $(python3 -c "print(int($SECS + 30))") "${pin[@]}" "$@" 2>"$work/client.err" | grep '^RESULT' | tail -1 || true)
  if [ -z "$line" ]; then
    log "FAILED $name: $(tr '\n' ' ' <"$work/client.err" | cut -c1-300)"
    printf '%s\t%s\t%s\n' "$round" "$name" "FAILED" >>"$results"
    return
  fi
  printf '%s\t%s\t%s\n' "$round" "$name" "$line" >>"$results"
  log "round $round  $(printf '%-22s' "$name") $line"
}

S=$SECS
for round in $(seq "$ROUNDS"); do
  figure pingpong          "$work/peers" pp-client "$(host "$pp_addr")" "$(port "$pp_addr")" "$S"
  figure libmodbus-libmodbus "$work/peers" lm-client tcp "$(host "$lm_addr")" "$(port "$lm_addr")" "$S"
  figure raw-libmodbus     "$wire" raw tcp "$lm_addr" "$S"
  figure runner-libmodbus  "$wire" runner tcp "$lm_addr" "$S"
  figure libmodbus-sim     "$work/peers" lm-client tcp "$(host "$sim_addr")" "$(port "$sim_addr")" "$S"
  figure raw-sim           "$wire" raw tcp "$sim_addr" "$S"
  figure runner-sim        "$wire" runner tcp "$sim_addr" "$S"
  figure pymodbus-pymodbus python3 "$here/pymodbus_peers.py" client "$(host "$py_addr")" "$(port "$py_addr")" "$S"
  figure raw-pymodbus      "$wire" raw tcp "$py_addr" "$S"
  figure runner-pymodbus   "$wire" runner tcp "$py_addr" "$S"
  figure pymodbus-sim      python3 "$here/pymodbus_peers.py" client "$(host "$sim_addr")" "$(port "$sim_addr")" "$S"
  figure libmodbus-pymodbus "$work/peers" lm-client tcp "$(host "$py_addr")" "$(port "$py_addr")" "$S"
  figure rtu-libmodbus-libmodbus "$work/peers" lm-client rtu "$work/ttyB" 115200 "$S"
  figure rtu-raw-libmodbus "$wire" raw rtu "$work/ttyB" 115200 "$S"
  figure rtu-runner-libmodbus "$wire" runner rtu "$work/ttyB" 115200 "$S"
  for k in 1 4 16 64; do
    figure "pipeline-k$k" "$wire" pipeline "$sim_addr" "$k" "$S"
  done
  # The live campaign (issue 17): `fuzz` over TCP against the simulator, generated cases, reads only,
  # silences proven; its summary line gives cases and exec/s (each case one or more requests).
  figure fuzz-live-sim bash -c '"$1" fuzz --target "tcp://$2" --profile generic --seed 1 --duration "$3" 2>&1 \
    | sed -n "s/^fuzz: \([0-9]*\) cases\( ([^)]*)\)\{0,1\}, [0-9]* probes in \([0-9.]*\) s (\([0-9]*\) exec\/s).*/RESULT requests=\1 seconds=\3 rps=\4 p50_us=0 p99_us=0/p"' \
    _ "$mh" "$sim_addr" "$(python3 -c "print(max(1, int($S * 1000)))")ms"
done
stop_all
# The watchdog was stopped with the servers; start it again for the rest.
watchdog

# measure FILE CMD...: run CMD pinned; write "PEAK_RSS_KIB WALL_SECONDS" to FILE; exit with CMD's status.
# /usr/bin/time -v where installed, else `peers time` (bench/peers.c: wait4's ru_maxrss, the same figure).
measure() {
  local file=$1; shift
  if [ -x /usr/bin/time ]; then
    local rc=0
    "${pin[@]}" /usr/bin/time -v -o "$file.v" "$@" || rc=$?
    printf '%s %s\n' \
      "$(sed -n 's/^[[:space:]]*Maximum resident set size (kbytes): //p' "$file.v")" \
      "$(sed -n 's/^[[:space:]]*Elapsed (wall clock) time (h:mm:ss or m:ss): //p' "$file.v" \
        | awk -F: '{ s = 0; for (i = 1; i <= NF; i++) s = s * 60 + $i; print s }')" >"$file"
    return "$rc"
  fi
  "${pin[@]}" "$work/peers" time "$file" "$@"
}

# --- in process ----------------------------------------------------------------------------------------------
log "in-process figures"
inproc_secs=$(python3 -c "print(min(1.0, $SECS))")
"${pin[@]}" "$wire" inproc "$inproc_secs" >"$work/inproc.txt" || die "inproc failed"
cat "$work/inproc.txt" >&2

# --- full catalog against each sim: profile ---------------------------------------------------------------------
log "full catalog against each sim: profile"
: >"$work/catalog.tsv"
for p in sd2x mdrive lmd generic; do
  measure "$work/time.txt" "$mh" run --target "sim:$p" --no-progress >"$work/run-$p.txt" 2>&1 \
    || [ $? = 1 ] || die "run --target sim:$p could not be made: $(tail -3 "$work/run-$p.txt")"
  cases=$(grep -oE '[0-9]+ cases' "$work/run-$p.txt" | head -1 | cut -d' ' -f1)
  read -r kib secs <"$work/time.txt"
  printf '%s\t%s\t%s %s\n' "$p" "${cases:-?}" "$secs" "$kib" >>"$work/catalog.tsv"
done
cat "$work/catalog.tsv" >&2

# --- memory --------------------------------------------------------------------------------------------------
# mem NAME CMD...: peak RSS (KiB) and wall time of one run.
mem() {
  local name=$1; shift
  log "memory: $name: $*"
  measure "$work/mem-$name.txt" "$@" >"$work/mem-$name.out" 2>&1 \
    || [ $? = 1 ] || die "memory run $name failed: $(tail -5 "$work/mem-$name.out")"
  local kib secs
  read -r kib secs <"$work/mem-$name.txt"
  printf '%s\t%s\t%s\t%s\n' "$name" "$kib" "$secs" "$*" >>"$work/mem.tsv"
  tail -1 "$work/mem-$name.out" >&2
}
: >"$work/mem.tsv"
if "$mh" run --help 2>/dev/null | grep -q -- '--generated'; then
  mem generated "$mh" run --target sim:generic --generated "$CASES" --seed 1 --no-progress
  # Reports stream ~4 KB a case to disk (cases.jsonl and the other formats), so this one is smaller (REPORT_CASES).
  mem generated-report "$mh" run --target sim:generic --generated "$REPORT_CASES" --seed 1 --no-progress --report "$work/report"
  rm -rf "$work/report"
else
  log "run --generated is not there: the catalog loop through the library stands in for it"
  mem catalog-loop "$wire" catalog-loop generic "$CASES"
  mem catalog-loop-report "$wire" catalog-loop generic "$REPORT_CASES" "$work/report"
  rm -rf "$work/report"
fi

# --- table ---------------------------------------------------------------------------------------------------
export B_RESULTS="$results" B_INPROC="$work/inproc.txt" B_CATALOG="$work/catalog.tsv" B_SMOKE="$SMOKE" B_OUT="$OUT"
export B_DATE="$(date -u '+%Y-%m-%d %H:%M UTC')" B_NPROC="$(nproc)" B_KERNEL="$(uname -r)" B_CORE="$CORE"
export B_CPU="$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ //')"
export B_ROUNDS="$ROUNDS" B_SECS="$SECS" B_LOAD_BEFORE="$load_before" B_LOAD_AFTER="$(cut -d' ' -f1-3 /proc/loadavg)"
export B_MEM="$work/mem.tsv" B_WORK="$work" B_ROOT="$root" B_PROFILE="$prof_dir"
python3 "$here/table.py"
