#!/usr/bin/env bash
# Fuzz smoke run for CI: build every cargo-fuzz target on stable Rust (no sanitizer) and run each for a bounded
# time, seeded from fuzz/corpus/<target>/ with the Modbus dictionary. Installs cargo-fuzz when it is missing.
#
#   FUZZ_SECONDS=20 fuzz/run-smoke.sh            # seconds per target (default 20)
#   FUZZ_TARGETS="tcp_adu differential" fuzz/run-smoke.sh   # a subset (default: every target)
#   FUZZ_DEV=1 fuzz/run-smoke.sh                 # build without optimizations (CI: 142 s against 266 s to
#                                                # build on 2 cores; each target then runs 3-10x slower)
#
# New inputs go to a scratch directory, so the committed corpus stays as it is. A finding fails the script;
# the reproducer is in fuzz/artifacts/<target>/ (replay: cargo fuzz run -s none <target> <file>).
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${FUZZ_SECONDS:-20}"
export CARGO_TERM_COLOR=never

if ! command -v cargo-fuzz >/dev/null; then
  echo "cargo-fuzz is missing: cargo install --locked cargo-fuzz"
  cargo install --locked cargo-fuzz
fi

build=()
[ "${FUZZ_DEV:-0}" = 1 ] && build=(--dev)
cargo fuzz build -s none "${build[@]}"
targets="${FUZZ_TARGETS:-$(cargo fuzz list)}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

failed=()
summary=()
for t in $targets; do
  mkdir -p "$work/$t"
  echo "=== $t: ${seconds}s"
  status=0
  cargo fuzz run -s none "${build[@]}" "$t" "$work/$t" "fuzz/corpus/$t" -- \
    -max_total_time="$seconds" -dict=fuzz/dict/modbus.dict -print_final_stats=1 \
    >"$work/$t.log" 2>&1 || status=$?
  runs=$(awk '/stat::number_of_executed_units/ {print $2}' "$work/$t.log")
  rate=$(awk '/stat::average_exec_per_sec/ {print $2}' "$work/$t.log")
  summary+=("$(printf '%-20s %10s runs %8s exec/s' "$t" "${runs:-?}" "${rate:-?}")")
  if [ "$status" -ne 0 ]; then
    failed+=("$t")
    grep -E -A20 'panicked|ERROR: libFuzzer|SUMMARY' "$work/$t.log" | head -60 || tail -40 "$work/$t.log"
  fi
done

echo "=== fuzz smoke summary (${seconds}s per target)"
printf '%s\n' "${summary[@]}"
if [ ${#failed[@]} -gt 0 ]; then
  echo "findings in: ${failed[*]} (reproducers in fuzz/artifacts/)"
  exit 1
fi
