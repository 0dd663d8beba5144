#!/usr/bin/env bash
# Shows that a change of the code changed no observation and no verdict: two binaries of modbus-harness
# (before, after) run the same cases against the in-process reference drives, the first writes a snapshot
# (every case's request bytes, answers or silence or close, and verdict; no timestamps) and the second is
# compared with it. Runs: the catalog of every built-in profile on its own transport; the same with
# 2,000 generated cases; and the catalog against drives with faults injected (so that FAIL verdicts are
# compared too).
#
# Usage: bench/same-observations.sh OLD_BINARY NEW_BINARY [--generated N]
# Exit 0 when every run gives the same snapshot; 1 with the runs that differ.
set -euo pipefail
if [ $# -lt 2 ] || [ "${1:-}" = "--help" ] || [ "${1:-}" = "-h" ]; then
  sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
fi
old=$1 new=$2
shift 2
generated=2000
while [ $# -gt 0 ]; do
  case $1 in
    --generated) generated=$2; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
for b in "$old" "$new"; do
  [ -x "$b" ] || { echo "not an executable: $b" >&2; exit 2; }
done
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT

differ=()
runs=0
compare() {
  local name=$1
  shift
  runs=$((runs + 1))
  # The first run writes the snapshot (its exit code is the verdict of the run, not of this check).
  "$old" run "$@" --no-progress --snapshot "$dir/$name.snap" --update-snapshot >"$dir/$name.old" 2>&1 || true
  if [ ! -s "$dir/$name.snap" ]; then
    echo "$name: the old binary wrote no snapshot:" >&2
    tail -5 "$dir/$name.old" >&2
    differ+=("$name")
    return
  fi
  "$new" run "$@" --no-progress --snapshot "$dir/$name.snap" >"$dir/$name.new" 2>&1 || true
  if grep -q "^snapshot: no drift" "$dir/$name.new"; then
    printf '%-24s same: %s\n' "$name" "$(grep "^snapshot: no drift" "$dir/$name.new" | sed 's/^snapshot: no drift //; s/ (.*snap)$//')"
  else
    printf '%-24s DIFFERS\n' "$name"
    grep -i -A12 "snapshot" "$dir/$name.new" | head -20
    differ+=("$name")
  fi
}

for p in sd2x mdrive lmd generic; do
  compare "catalog-$p" --target "sim:$p"
  compare "generated-$p" --target "sim:$p" --generated "$generated" --seed 7 --with-catalog --no-shrink
done
# FAIL verdicts: a fault per profile that the catalog catches.
compare "fault-sd2x" --target sim:sd2x --fault wrong-exception-code --fault wrong-crc --fault counters-frozen
compare "fault-mdrive" --target sim:mdrive --fault range-unchecked --fault word-order --fault reserved-readable --fault half-register-widened
compare "fault-generic" --target sim:generic --fault quantity-unchecked --fault bit-padding-ones --fault file-write-first-only

echo "$runs runs, ${#differ[@]} differ"
[ ${#differ[@]} -eq 0 ]
