#!/usr/bin/env bash
# against.sh DRIVE PROFILE SCHEME [harness args...]: run the harness against one of the independent drives and
# check that it is left as found. Starts DRIVE/sim.py on a free loopback port, dumps its state (SIGUSR1), runs
# `modbus-harness run --target SCHEME://ADDR --profile PROFILE ARGS`, dumps the state again, prints the values
# that differ (the FC 08 counters change with any traffic, a sixth-wave drive's `live` values by themselves),
# stops the drive. Output under ${OUT:-/tmp/independent}.
#
#   tests/independent/against.sh sd2x sd2x rtu+tcp --generated 1500 --seed 2
#   tests/independent/against.sh lmd lmd tcp --generated 3000 --seed 10
#   PRESET=tests/independent/lmd/preset_output_function.py tests/independent/against.sh lmd lmd tcp
#   PROXY="--notice 20" tests/independent/against.sh mdrive mdrive tcp   # behind bench/one-slot-proxy.py
#   GATEWAY="--units 1-1" tests/independent/against.sh sd2x-b sd2x tcp    # an RTU drive behind bench/gateway.py
#   tests/independent/against.sh sd2x-c sd2x serial    # on one end of a socat pty pair (drives with --serial)
#   ECHO="" tests/independent/against.sh sd2x-b sd2x serial   # behind bench/echo-line.py, the run with echo=on
#                                                             # (ECHO_URL=off: without it)
#   CMD=fuzz tests/independent/against.sh lmd-b lmd tcp --duration 20s --seed 5 --keep-going --allow-writes
#                                                             # a live fuzz campaign instead of `run`
set -u
[ $# -ge 3 ] || { sed -n 2,14p "$0"; exit 2; }
drive=$1 profile=$2 scheme=$3; shift 3
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
B=${B:-${CARGO_TARGET_DIR:-$repo/target}/release/modbus-harness}
[ -x "$B" ] || { echo "no harness binary at $B: cargo build --release (or set B)" >&2; exit 2; }
# DRIVE is one of this folder's drives, or the path of another drive's folder (its sim.py, or sim.c built with
# libmodbus, takes the same options).
out=${OUT:-/tmp/independent}/$(basename "$drive")-$(date +%s%N); mkdir -p "$out"
case $drive in */*) dir=$drive; drive=$(basename "$drive") ;; *) dir=$here/$drive ;; esac
if [ -f "$dir/sim.js" ]; then
  # A drive in JavaScript on an npm library (the fifteenth wave): its packages installed by `npm ci` from its
  # lock file into cargo's target directory (once; again when the lock file changes), found by NODE_PATH.
  npmdir=${CARGO_TARGET_DIR:-$repo/target}/tmp/npm-against-$(basename "$dir")
  if ! cmp -s "$dir/package-lock.json" "$npmdir/package-lock.json" || [ ! -d "$npmdir/node_modules" ]; then
    rm -rf "$npmdir" && mkdir -p "$npmdir" && cp "$dir/package.json" "$dir/package-lock.json" "$npmdir/" &&
      (cd "$npmdir" && timeout 300 npm ci --no-audit --no-fund --loglevel=error > /dev/null) ||
      { echo "npm ci for $dir failed" >&2; rm -rf "$npmdir"; exit 2; }
  fi
  export NODE_PATH=$npmdir/node_modules
  launch=(node "$dir/sim.js")
elif [ -f "$dir/sim.c" ]; then
  # A drive in C on libmodbus (the fifth wave): built here, run as is.
  gcc -O2 -Wall -Wextra -o "$out/sim" "$dir/sim.c" $(pkg-config --cflags --libs libmodbus) || exit 2
  launch=("$out/sim")
else
  launch=(python3 "$dir/sim.py")
fi
if [ "$scheme" = serial ]; then
  # The drive on one end of a socat pty pair at 19200 8N1, the harness on the other (or behind ECHO's line).
  socat pty,raw,echo=0,link="$out/ttyA" pty,raw,echo=0,link="$out/ttyB" 2> "$out/socat.err" &
  spid=$!
  for _ in $(seq 50); do [ -e "$out/ttyA" ] && [ -e "$out/ttyB" ] && break; sleep 0.1; done
  [ -e "$out/ttyB" ] || { echo "socat made no pty pair: $(cat "$out/socat.err")" >&2; kill $spid; exit 2; }
  "${launch[@]}" ${SIM_ARGS:-} --serial "$out/ttyA" --baud 19200 --parity none --state "$out/state.json" > "$out/sim.out" 2> "$out/sim.err" &
else
  "${launch[@]}" ${SIM_ARGS:-} --listen 127.0.0.1:0 --state "$out/state.json" > "$out/sim.out" 2> "$out/sim.err" &
fi
pid=$!
trap 'kill $pid ${spid:-} 2>/dev/null; wait $pid ${spid:-} 2>/dev/null' EXIT
for _ in $(seq 50); do grep -q listening "$out/sim.out" && break; sleep 0.1; done
if [ "$scheme" = serial ]; then
  grep -q listening "$out/sim.out" || { echo "the drive did not start: $(cat "$out/sim.err")" >&2; exit 2; }
  target="rtu://$out/ttyB?baud=19200&parity=none"
  if [ -n "${ECHO+x}" ]; then
    # The harness behind bench/echo-line.py (ECHO's options, may be empty): every byte it sends comes back.
    python3 "$repo/bench/echo-line.py" "$out/ttyB" --link "$out/echoing" $ECHO --lifetime 1800 > "$out/echo.out" 2> "$out/echo.err" &
    epid=$!
    trap 'kill $pid ${spid:-} $epid 2>/dev/null; wait $pid ${spid:-} $epid 2>/dev/null' EXIT
    for _ in $(seq 50); do grep -q serial "$out/echo.out" && break; sleep 0.1; done
    [ -e "$out/echoing" ] || { echo "the echo line did not start: $(cat "$out/echo.err")" >&2; exit 2; }
    target="rtu://$out/echoing?baud=19200&parity=none"
    # ECHO_URL=off leaves echo=on out of the URL (what a harness without it meets).
    [ "${ECHO_URL:-on}" = on ] && target="$target&echo=on"
  fi
else
  addr=$(grep -oE '127\.0\.0\.1:[0-9]+' "$out/sim.out" | head -1)
  [ -n "$addr" ] || { echo "the drive did not start: $(cat "$out/sim.err")" >&2; exit 2; }
  target="$scheme://$addr"
fi
[ -n "${PRESET:-}" ] && python3 "$PRESET" "${addr:?PRESET needs a TCP drive}" > "$out/preset.out"
if [ -n "${PROXY:-}" ]; then
  # The drive behind a proxy with PROXY's options (bench/one-slot-proxy.py: one connection slot, an idle
  # timeout); the harness talks to the proxy, the state is still dumped by the drive.
  python3 "$repo/bench/one-slot-proxy.py" "$addr" $PROXY --lifetime 1800 > "$out/proxy.out" 2>&1 &
  ppid=$!
  trap 'kill $pid $ppid 2>/dev/null; wait $pid $ppid 2>/dev/null' EXIT
  for _ in $(seq 50); do grep -q listening "$out/proxy.out" && break; sleep 0.1; done
  addr=$(grep -oE '127\.0\.0\.1:[0-9]+' "$out/proxy.out" | head -1)
  [ -n "$addr" ] || { echo "the proxy did not start: $(cat "$out/proxy.out")" >&2; exit 2; }
  target="$scheme://$addr"
fi
if [ -n "${GATEWAY+x}" ]; then
  # An RTU-over-TCP drive reached over Modbus/TCP through bench/gateway.py with GATEWAY's options (may be
  # empty: the defaults); the state is still dumped by the drive.
  python3 "$repo/bench/gateway.py" "$addr" $GATEWAY --lifetime 1800 > "$out/gateway.out" 2> "$out/gateway.err" &
  gpid=$!
  trap 'kill $pid ${ppid:-} $gpid 2>/dev/null; wait $pid ${ppid:-} $gpid 2>/dev/null' EXIT
  for _ in $(seq 50); do grep -q listening "$out/gateway.out" && break; sleep 0.1; done
  addr=$(grep -oE '127\.0\.0\.1:[0-9]+' "$out/gateway.out" | head -1)
  [ -n "$addr" ] || { echo "the gateway did not start: $(cat "$out/gateway.err")" >&2; exit 2; }
  target="$scheme://$addr"
fi
kill -USR1 $pid; sleep 0.5; cp "$out/state.json" "$out/before.json"
if [ "${CMD:-run}" = fuzz ]; then
  # CMD=fuzz: a live fuzz campaign instead of a run (its options after the scheme: --duration, --seed, ...).
  timeout 1800 "$B" fuzz --target "$target" --profile "$profile" --regressions "$out/regressions" "$@" \
    > "$out/run.out" 2> "$out/run.err"
else
  timeout 1800 "$B" run --target "$target" --profile "$profile" --report "$out/report" --regressions "$out/regressions" --no-progress "$@" \
    > "$out/run.out" 2> "$out/run.err"
fi
echo "harness exit $?" >> "$out/run.out"
kill -USR1 $pid; sleep 0.5; cp "$out/state.json" "$out/after.json"
python3 - "$out" <<'PY'
import json, sys
d = sys.argv[1]
a = json.load(open(d + '/before.json')); b = json.load(open(d + '/after.json'))
def flat(x, p=''):
    if isinstance(x, dict):
        for k, v in x.items(): yield from flat(v, p + '/' + str(k))
    elif isinstance(x, list):
        for i, v in enumerate(x): yield from flat(v, p + '/' + str(i))
    else: yield p, x
fa = dict(flat(a)); fb = dict(flat(b))
diff = [(k, fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb))
        if fa.get(k) != fb.get(k) and 'diagnostic_counters' not in k and not k.startswith('/live/')]
print(f"state: {len(fa)} values, {len(diff)} differ after the run (FC 08 counters and live values aside)")
for k, x, y in diff[:60]: print(f"  {k}: {x!r} -> {y!r}")
PY
grep -E "^RESULT|harness exit" "$out/run.out"
[ -n "${PROXY:-}" ] && { sleep 1.1; grep stats "$out/proxy.out" | tail -1; }
[ -n "${GATEWAY+x}" ] && { kill $gpid; sleep 0.3; cat "$out/gateway.err"; }
[ -n "${ECHO+x}" ] && [ -n "${epid:-}" ] && { kill $epid; sleep 0.3; cat "$out/echo.err"; }
echo "dir: $out"
