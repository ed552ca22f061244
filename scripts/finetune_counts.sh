#!/usr/bin/env bash
set -euo pipefail
# Fine-tune the shipped 3-object model on 2, 4 and 5 objects (issue 23), then evaluate each feed-forward on the
# full test split and with search 3 + colour fit 50 on the first 200 scenes. Needs data/clevr{2,4,5}
# (prismonet data clevr --objects N --out data/clevrN). Resumable: rerun; finished parts are skipped.
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1
for n in 2 4 5; do
  [ -f data/clevr$n/meta.json ] || { echo "finetune_counts: no data/clevr$n (prismonet data clevr --objects $n --out data/clevr$n)" >&2; exit 2; }
  python3 -m prismonet train configs/clevr${n}_finetune.json --out runs/clevr${n}_ft --set threads=1 --quiet || exit 1
  [ -f runs/clevr${n}_ft/eval_ff.json ] || python3 -m prismonet evaluate runs/clevr${n}_ft data/clevr$n --json runs/clevr${n}_ft/eval_ff.json --quiet > runs/clevr${n}_ft/eval_ff.txt
done
for n in 2 4 5; do
  [ -f runs/clevr${n}_ft/eval_sf200.json ] || python3 -m prismonet evaluate runs/clevr${n}_ft data/clevr$n --limit 200 --search 3 --fit-color 50 --json runs/clevr${n}_ft/eval_sf200.json --quiet > runs/clevr${n}_ft/eval_sf200.txt
done
echo chain done
