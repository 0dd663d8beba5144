#!/bin/bash
# bench/link-retries.sh OLD NEW: what the link reruns cost where the link is clean. Against `simulate` over TCP on
# loopback, client on core 0, server on core 1, old and new alternating, two rounds:
#  1. 100,000 generated cases (mdrive, seed 1): every case PASSes or is SKIPPED, nothing is run again;
#  2. the catalog against a drive with a fault that drops requests (quantity-over-spec-dropped): its FAILs
#     get no answer, so each is run again (twice more, the drive's own after three attempts).
set -u
OLD=$1 NEW=$2
start_sim() {
  taskset -c 1 $OLD simulate "$@" --listen 127.0.0.1:0 > /tmp/bsim.out 2>/dev/null &
  spid=$!
  for _ in $(seq 50); do grep -q listening /tmp/bsim.out && break; sleep 0.1; done
  addr=$(grep -oE '127\.0\.0\.1:[0-9]+' /tmp/bsim.out | head -1)
}
timed() { local s e; s=$(date +%s.%N); "$@" > /tmp/bl.out 2>/tmp/bl.err; e=$(date +%s.%N); echo "$(echo "$e - $s" | bc) s, $(tail -n1 /tmp/bl.out)"; }
for round in 1 2; do
  for b in $OLD $NEW; do
    start_sim --profile mdrive
    echo "round $round $(basename $b) generated 100000: $(timed taskset -c 0 $b run --target tcp://$addr --profile mdrive --generated 100000 --seed 1 --no-progress)"
    kill $spid; wait $spid 2>/dev/null
    start_sim --profile mdrive --fault quantity-over-spec-dropped
    echo "round $round $(basename $b) catalog, fault quantity-over-spec-dropped: $(timed taskset -c 0 $b run --target tcp://$addr --profile mdrive --no-progress)"
    kill $spid; wait $spid 2>/dev/null
  done
done
