#!/usr/bin/env bash
# A command's start-up thread count (prismonet.cli._set_threads): `prismonet evaluate` on 128 validation scenes with
# the load-aware choice ("auto") against fixed counts, interleaved, on a quiet machine and beside a busy 2-thread
# process (a torch matrix-product loop standing in for a training job), as in BENCHMARKS.md "Session 69".
#   bash scripts/bench_cli_threads.sh [MODEL DATA ROUNDS]      (default: chairs_pose_keep data/chairs 3; ~6 min)
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL=${1:-chairs_pose_keep}
DATA=${2:-data/chairs}
ROUNDS=${3:-3}
TMP=$(mktemp -d)
LOAD=
trap 'kill $LOAD 2>/dev/null || true; rm -rf "$TMP"' EXIT
run() {  # run VARIANT: wall seconds of one evaluation, and the thread note if one was printed
  local env=()
  [ "$1" != auto ] && env=(PRISMONET_THREADS="$1")
  local t0 t1
  t0=$(date +%s.%N)
  env -u OMP_NUM_THREADS "${env[@]}" python3 -m prismonet evaluate "$MODEL" "$DATA" --split val --limit 128 --batch 64 --quiet \
    --json "$TMP/$1.json" > "$TMP/$1.log" 2>&1
  t1=$(date +%s.%N)
  echo "$1 $(python3 -c "print(f'{$t1 - $t0:.2f}')") $(grep -c 'running on 1 thread' "$TMP/$1.log" || true)"
}
for load in quiet loaded; do
  if [ $load = loaded ]; then
    python3 -c "
import torch
torch.set_num_threads(2)
a = torch.randn(512, 512)
while True:
    a = torch.tanh(a @ a)" & LOAD=$!
    sleep 3
  fi
  for r in $(seq "$ROUNDS"); do for v in auto 2 1; do echo "$load $r $(run $v)"; done; done
  if [ $load = loaded ]; then kill $LOAD; LOAD=; fi
done | python3 -c "
import statistics, sys
rows = {}
for line in sys.stdin:
    load, r, v, s, note = line.split()
    rows.setdefault((load, v), []).append((float(s), int(note)))
print('| evaluate, 128 scenes | auto (median s; 1-thread picks) | 2 threads | 1 thread | auto against 2 |')
print('|---|---|---|---|---|')
for load in ('quiet', 'loaded'):
    m = {v: statistics.median(s for s, _ in rows[(load, v)]) for v in ('auto', '2', '1')}
    picks = sum(n for _, n in rows[(load, 'auto')])
    print(f'| {load} | {m[\"auto\"]:.2f} ({picks} of {len(rows[(load, \"auto\")])}) | {m[\"2\"]:.2f} | {m[\"1\"]:.2f} | {m[\"2\"] / m[\"auto\"]:.2f}x |')
"
