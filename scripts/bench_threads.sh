#!/usr/bin/env bash
# Training step under each thread / wait policy, on a quiet machine and with one competing busy
# process (a pure-Python loop on one core), as in BENCHMARKS.md "Threads on a shared machine".
#   bash scripts/bench_threads.sh [DATA]        (needs data/clevr3; ~6 min)
# Part 1: scripts/bench_step.py (the step alone) per policy. Part 2: the real trainer, 100 steps from
# the shipped weights, ms per step over steps 25-100 from its log.jsonl, threads = 2, 1 and 0 (adaptive).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/clevr3}
TMP=$(mktemp -d)
trap 'kill $LOAD 2>/dev/null || true; rm -rf "$TMP"' EXIT
LOAD=
step() { env "$@" python3 scripts/bench_step.py --data "$DATA" --variants blur --rounds 3 --steps 4 | tail -1 | cut -d'|' -f3; }
trainer() {
  python3 -m prismonet train configs/clevr3_shipped.json --out "$TMP/$1-$2" --quiet --set data="$DATA" --set steps=100 \
    --set threads="$2" --set init_from=clevr3_fc --set lr_decay_from=null --set 'lr_restarts=[]' --set checkpoint_every=1000 \
    --set image_every=1000 --set log_every=25 >/dev/null
  python3 -c "
import json, sys
L = [json.loads(l) for l in open(sys.argv[1])]
a = next(l for l in L if l['step'] == 25); b = L[-1]
print(f\"{1e3 * (b['time_s'] - a['time_s']) / (b['step'] - a['step']):.1f} ms/step, {b['threads']} thread(s) at the end\")" "$TMP/$1-$2/log.jsonl"
}
for load in quiet loaded; do
  if [ $load = loaded ]; then python3 -c "while True: pass" & LOAD=$!; sleep 1; fi
  echo "== $load"
  echo "step, 2 threads, default wait:      $(step X=1) ms"
  echo "step, 2 threads, GOMP_SPINCOUNT=1e4: $(step GOMP_SPINCOUNT=10000) ms"
  echo "step, 2 threads, OMP_WAIT_POLICY=PASSIVE: $(step OMP_WAIT_POLICY=PASSIVE) ms"
  echo "step, 1 thread:                      $(python3 scripts/bench_step.py --data "$DATA" --variants blur --rounds 3 --steps 4 --threads 1 | tail -1 | cut -d'|' -f3) ms"
  for th in 2 1 0; do echo "trainer threads=$th: $(trainer $load $th)"; done
  if [ $load = loaded ]; then kill $LOAD; LOAD=; fi
done
