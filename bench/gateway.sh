#!/usr/bin/env bash
# An RTU drive reached over Modbus/TCP through a gateway: each SD2x (the binary's own `simulate --profile sd2x
# --rtu-over-tcp`, and the independent drives tests/independent/sd2x, sd2x-b, sd2x-c) behind
# bench/gateway.py, for each binary and each gateway setting: the sd2x catalog over tcp://, and (default
# setting only) a generated run. The verdicts, and whether the drive reads as before (the run's own
# leave-as-found check; for the independent drives also their state dumped before and after, FC 08 counters
# aside).
#
#   bench/gateway.sh [--cases N] [--settings "default silence ..."] [--drives "simulate sd2x ..."] LABEL=BINARY...
#
#   --cases N        cases of the generated run (default 1500, seed 2)
#   --settings S     gateway settings (default "default silence path"): default = 0B after 200 ms of the
#                    drive's silence, 0A for unit ids outside 1-247; silence = no answer where the drive is
#                    silent; path = only unit 1 routed (0A for every other id), broadcasts answered 0B
#   --drives D       simulate and/or independent drives (default "simulate sd2x sd2x-b sd2x-c")
#   LABEL=BINARY     a modbus-harness binary; its own `simulate` serves the simulate rows
#
# Needs python3. Loopback only; every run is bounded by `timeout`, every process started is stopped at exit.
# Prints a Markdown table on stdout.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/.." && pwd)
. "$here/lib.sh"
cases=1500 settings="default silence path" drives="simulate sd2x sd2x-b sd2x-c"
BINS=()
bench_parse gateway.sh 2,18 --cases=cases --settings=settings --drives=drives LABEL=BINARY -- "$@"
bench_need_bins gateway.sh
bench_servers_workdir gateway.sh
pin=()

gateway_args() {
  case $1 in
    default) echo "" ;;
    silence) echo "--on-timeout silence" ;;
    path) echo "--units 1-1 --broadcast exception" ;;
    *) bench_fail gateway.sh "unknown setting $1 (default, silence, path)" ;;
  esac
}

# run_one LABEL BIN DRIVE SETTING KIND: one row's cell (KIND: catalog or generated).
run_one() {
  local label=$1 bin=$2 drive=$3 setting=$4 kind=$5 extra=() out
  [ "$kind" = generated ] && extra=(--generated "$cases" --seed 2 --no-shrink)
  out="$work/$label-$drive-$setting-$kind"
  if [ "$drive" = simulate ]; then
    local sim gw
    sim=$(bench_start gateway.sh "$work" "sim-${out##*/}" "$bin" simulate --profile sd2x --rtu-over-tcp 127.0.0.1:0)
    # shellcheck disable=SC2046
    gw=$(bench_start gateway.sh "$work" "gw-${out##*/}" python3 "$here/gateway.py" "$sim" $(gateway_args "$setting") --lifetime 1200)
    timeout 900 "$bin" run --target "tcp://$gw" --profile sd2x --no-progress "${extra[@]}" >"$out" 2>&1 || true
    bench_verdict "$out"
  else
    GATEWAY="$(gateway_args "$setting")" B="$bin" OUT="$work/independent" \
      "$repo/tests/independent/against.sh" "$drive" sd2x tcp "${extra[@]}" >"$out.summary" 2>&1 || true
    local dir
    dir=$(grep -o 'dir: .*' "$out.summary" | cut -c6-)
    cp "$dir/run.out" "$out" 2>/dev/null || true
    echo "$(bench_verdict "$out"); state: $(grep -o '[0-9]* differ' "$out.summary" || echo '?')"
  fi
}

echo "| binary | drive | gateway | catalog | generated $cases (seed 2) |"
echo "|---|---|---|---|---|"
for b in "${BINS[@]}"; do
  label=${b%%=*} bin=${b#*=}
  for d in $drives; do
    for s in $settings; do
      cat=$(run_one "$label" "$bin" "$d" "$s" catalog)
      gen="-"
      [ "$s" = default ] && gen=$(run_one "$label" "$bin" "$d" "$s" generated)
      echo "| $label | $d | $s | $cat | $gen |"
      echo "gateway.sh: $label $d $s done" >&2
    done
  done
done
