# The cube-drawing route of issue 25 (EVALUATION.md, sessions 88-89), whole and resumable: the demo search's
# shape-trial targets on the training scenes of data/clevr3, a keep + shape refiner fitted to them from clevr3_fc,
# two refine passes, a learnt colour step (three passes since session 104, two since 92), and the validation measures
# after the refit and after the colour step.
#   bash scripts/sharp_refit.sh OUT [COUNT] [STEPS] [DATA] [STEP_DATA]     e.g. bash scripts/sharp_refit.sh runs/s89 9000 6000
# COUNT training scenes of targets (default 9000, all of them), STEPS refit steps (default 6000), DATA the dataset
# (default data/clevr3: python3 -m prismonet data clevr --objects 3 --out data/clevr3, about 20 s; more training scenes:
# `prismonet data join data/clevr3 MORE DATA`, whose val split is data/clevr3's), STEP_DATA the colour step's training
# images (default: the first 8,192 of DATA; the shipped step used all 24,576 of `prismonet data clevr --objects 3
# --seed 7 --split 24576,0,0 --workers 1 --out data/clevr3_s7`, about 3 min). Every stage resumes where it stopped:
# rerun the same command; a finished stage is skipped. Writes under OUT: distill_c3_table/, c3_table_fit/,
# c3_table_fit_2p/, c3_table_fit_cs/, eval_fit_2p_val.txt, codes_fit_2p_val.txt, eval_fit_cs_val.txt.
set -e
out=$1; count=${2:-9000}; steps=${3:-6000}; data=${4:-data/clevr3}
if [ -z "$out" ]; then echo "usage: bash scripts/sharp_refit.sh OUT [COUNT] [STEPS] [DATA] [STEP_DATA]" >&2; exit 2; fi
data=$(cd "$data" 2>/dev/null && pwd -P) || { echo "sharp_refit: $data is missing (prismonet data clevr --objects 3 --out data/clevr3)" >&2; exit 2; }
if [ -n "$5" ]; then   # the colour step's images, checked before any work
  step=$(cd "$5" 2>/dev/null && pwd -P) || { echo "sharp_refit: $5 is missing" >&2; exit 2; }
  step_data=("$step")
else step_data=("$data" --count 8192); fi
out=$(mkdir -p "$out" && cd "$out" && pwd -P)   # absolute, as the runs record their inputs: a rerun from elsewhere still resumes
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
p() { python3 -m prismonet "$@"; }
once() { local f=$1; shift; [ -s "$f" ] || { "$@" > "$f.tmp" 2>&1 && mv "$f.tmp" "$f"; }; }   # a report, written whole once
p distill clevr3_fc "$data" --out "$out/distill_c3_table" --count "$count" --batch 32 \
  --search 3 --fit-color 50 --search-far-clip --shape-trials --search-grid 24 --quiet
p refiner clevr3_fc "$data" --targets "$out/distill_c3_table" --out "$out/c3_table_fit" --steps "$steps" --batch 32 \
  --glimpse 0.375 --coords --keep --shape --quiet
[ -f "$out/c3_table_fit_2p/model.json" ] || python3 scripts/set_refine_passes.py "$out/c3_table_fit" 2 "$out/c3_table_fit_2p"
once "$out/eval_fit_2p_val.txt" p evaluate "$out/c3_table_fit_2p" "$data" --split val --limit 1000 --batch 64
once "$out/codes_fit_2p_val.txt" python3 scripts/shape_codes.py "$out/c3_table_fit_2p" "$data" --split val --limit 400
p color-step "$out/c3_table_fit_2p" "${step_data[@]}" --out "$out/c3_table_fit_cs" --steps 1500 --batch 24 --passes 3 --quiet
once "$out/eval_fit_cs_val.txt" p evaluate "$out/c3_table_fit_cs" "$data" --split val --limit 1000 --batch 64
echo "sharp_refit: done ($out)"
