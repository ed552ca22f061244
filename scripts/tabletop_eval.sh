# Evaluate a finished real-tabletop run (a camera-frame 1-8 object model) on everything issue 21 measures it by:
# its own test split, the plain-look 1-8 split, the photoreal ladder, and the labelled real photos (feed-forward,
# and with search 3 + colour fit 50 + pruning). Waits for the run's model.json when its training is still going.
#   bash scripts/tabletop_eval.sh RUN DATA      e.g. bash scripts/tabletop_eval.sh runs/tabletop_v3 data/tabletop_v3
# writes runs/NAME_eval_*.{json,txt}, runs/ladder_NAME/, runs/real_eval_NAME{,_fit}/ and runs/NAME_eval.done
set -e
run=$1; data=$2; name=$(basename "$run")
if [ -z "$run" ] || [ -z "$data" ]; then echo "usage: bash scripts/tabletop_eval.sh RUN DATA" >&2; exit 2; fi
while [ ! -f "$run/model.json" ] || pgrep -f "train configs/$name.json" > /dev/null; do sleep 20; done
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
ev() { python3 -m prismonet evaluate "$run" "$@"; }
ev "$data" --split test --limit 1000 --quiet --json "runs/${name}_eval_own.json" > "runs/${name}_eval_own.txt" 2>&1
ev "$data" --split test --limit 1000 --prune --quiet --json "runs/${name}_eval_own_prune.json" > "runs/${name}_eval_own_prune.txt" 2>&1
ev data/clevr1to8 --split test --limit 500 --quiet --json "runs/${name}_eval_1to8.json" > "runs/${name}_eval_1to8.txt" 2>&1
python3 scripts/ladder.py --ladder data/ladder --base data/clevr3 --limit 500 --model "$run" --out "runs/ladder_${name}" > "runs/${name}_ladder.txt" 2>&1
python3 -m prismonet real evaluate realdata/samples/labels --model "$run" --out "runs/real_eval_${name}" --quiet > "runs/${name}_real.txt" 2>&1
python3 -m prismonet real evaluate realdata/samples/labels --model "$run" --out "runs/real_eval_${name}_fit" --search 3 --fit-color 50 --prune --quiet > "runs/${name}_real_fit.txt" 2>&1
python3 -m prismonet real evaluate realdata/samples/labels --model "$run" --out "runs/real_eval_${name}_elev" --label-elevations --quiet > "runs/${name}_real_elev.txt" 2>&1
python3 -m prismonet real evaluate realdata/samples/labels --model "$run" --out "runs/real_eval_${name}_elev_fit" --label-elevations --search 3 --fit-color 50 --prune --quiet > "runs/${name}_real_elev_fit.txt" 2>&1
echo done > "runs/${name}_eval.done"
