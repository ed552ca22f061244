# Evaluate a finished ShapeNet-style run on its seen and novel test splits (first 2,000 scenes each),
# feed-forward; waits for the run's model.json when its training is still going.
#   bash scripts/shapenet_eval.sh RUN DATA      e.g. bash scripts/shapenet_eval.sh runs/chairs data/chairs
# writes runs/NAME_eval_{seen,novel}.{json,txt} and runs/NAME_eval.done (NAME = the run folder's name)
set -e
run=$1; data=$2; name=$(basename "$run")
if [ -z "$run" ] || [ -z "$data" ]; then echo "usage: bash scripts/shapenet_eval.sh RUN DATA" >&2; exit 2; fi
while [ ! -f "$run/model.json" ] || pgrep -f "train configs/$name.json" > /dev/null; do sleep 20; done
mkdir -p runs
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
python3 -m prismonet evaluate "$run" "$data" --split test --limit 2000 --quiet --json "runs/${name}_eval_seen.json" > "runs/${name}_eval_seen.txt" 2>&1
python3 -m prismonet evaluate "$run" "${data}_novel" --split test --limit 2000 --quiet --json "runs/${name}_eval_novel.json" > "runs/${name}_eval_novel.txt" 2>&1
echo done > "runs/${name}_eval.done"
