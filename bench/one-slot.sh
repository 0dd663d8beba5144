#!/usr/bin/env bash
# A drive with one connection slot: `simulate --profile P` (factory values; each run's own leave-as-found
# check reads every kept parameter back) behind
# bench/one-slot-proxy.py, which relays one connection at a time, closes (or resets) connections that come
# while the slot is held, and notices a client's close NOTICE ms late. For each binary and each proxy
# setting: the profile's catalog, a generated run, and three catalog runs started one the moment the last
# ended; the verdicts, whether the run left the drive as found, and how many connections the proxy refused.
#
#   bench/one-slot.sh [--profile P] [--cases N] [--settings "refuse:0 refuse:5 ..."] LABEL=BINARY...
#
#   --profile P      mdrive (default), lmd or generic (Modbus/TCP); sd2x goes over RTU over TCP
#   --cases N        cases of the generated run (default 2000, seed 1)
#   --settings S     proxy settings POLICY:NOTICE_MS (default "refuse:0 refuse:5 refuse:20 reset:20 queue:20
#                    replace:20"; see bench/one-slot-proxy.py)
#   LABEL=BINARY     a modbus-harness binary; its own `simulate` serves its runs
#
# Needs python3. Loopback only; every run is bounded by `timeout`, every process started is stopped at exit.
# Prints a Markdown table on stdout.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
. "$here/lib.sh"
profile=mdrive cases=2000 settings="refuse:0 refuse:5 refuse:20 reset:20 queue:20 replace:20"
BINS=()
bench_parse one-slot.sh 2,17 --profile=profile --cases=cases --settings=settings LABEL=BINARY -- "$@"
bench_need_bins one-slot.sh
bench_servers_workdir one-slot.sh
pin=()
listen=--listen scheme=tcp
[ "$profile" = sd2x ] && listen=--rtu-over-tcp scheme=rtu+tcp

echo "| binary | proxy | catalog | generated $cases (seed 1) | 3 catalogs back to back (exit codes) | connections refused |"
echo "|---|---|---|---|---|---:|"
for b in "${BINS[@]}"; do
  label=${b%%=*} bin=${b#*=}
  for s in $settings; do
    policy=${s%%:*} notice=${s#*:}
    tag="$label-$policy-$notice"
    sim=$(bench_start one-slot.sh "$work" "sim-$tag" "$bin" simulate --profile "$profile" "$listen" 127.0.0.1:0)
    proxy=$(bench_start one-slot.sh "$work" "proxy-$tag" python3 "$here/one-slot-proxy.py" "$sim" \
      --policy "$policy" --notice "$notice" --lifetime 1200)
    url="$scheme://$proxy"
    timeout 300 "$bin" run --target "$url" --profile "$profile" --no-progress >"$work/cat-$tag" 2>&1 || true
    timeout 900 "$bin" run --target "$url" --profile "$profile" --no-progress --generated "$cases" --seed 1 \
      >"$work/gen-$tag" 2>&1 || true
    codes=""
    for k in 1 2 3; do
      rc=0
      timeout 300 "$bin" run --target "$url" --profile "$profile" --no-progress >"$work/b2b-$tag-$k" 2>&1 || rc=$?
      codes="$codes $rc"
    done
    sleep 1.2
    refused=$(grep -o "'refused': [0-9]*" "$work/proxy-$tag.out" | tail -1 | grep -o '[0-9]*$' || echo "?")
    echo "| $label | $policy, notices a close ${notice} ms late | $(bench_verdict "$work/cat-$tag") | $(bench_verdict "$work/gen-$tag") |$codes | $refused |"
    echo "one-slot.sh: $tag done" >&2
  done
done
