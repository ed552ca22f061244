# Usage, on the lent GPU machine, in the repository root:
#   PACK=gpu_pack_c3 DATA=data/clevr3 TARGETS=runs/s75/distill_c3_fp4k DEADLINE_S=480 OUT=DIR \
#       bash scripts/device_distill.sh DISTILL_ARGS...
# Makes `prismonet distill` targets on the GPU until DEADLINE_S seconds after this script starts, then returns every
# chunk of $TARGETS as $OUT/targets.tgz (unpack it over the folder here: the chunks made here before are in it too).
# What travels: $PACK (the training split packed by scripts/pack_split.py as $PACK/train, the dataset's meta.json, and
# any shipped *_model.safetensors the command names, since scripts/device_slim.sh leaves them behind), .whl (kornia
# wheels; see BENCHMARKS.md, "Training on a GPU") and $TARGETS (its targets.json and chunks, so that the run resumes).
# Tries batches of 256 scenes, then 64 if that fails before making a chunk.
set -x
PACK=${PACK:-gpu_pack_c3}
DATA=${DATA:-data/clevr3}
TARGETS=${TARGETS:?name the targets folder}
DEADLINE_S=${DEADLINE_S:-480}
T0=$(date +%s)
mkdir -p "$TARGETS"
. scripts/device_setup.sh || exit $?
cp "$PACK"/*_model.* prismonet/assets/ 2>/dev/null
before=$(ls "$TARGETS"/chunk_*.safetensors 2>/dev/null | wc -l)
for batch in 256 64; do
    left=$(( T0 + DEADLINE_S - $(date +%s) ))
    [ "$left" -gt 30 ] || break
    PYTHONUNBUFFERED=1 timeout "$left" python3 -m prismonet distill "$@" --out "$TARGETS" --batch $batch --device cuda
    rc=$?
    now=$(ls "$TARGETS"/chunk_*.safetensors 2>/dev/null | wc -l)
    echo "batch $batch: exit $rc, chunks $before -> $now, $(( $(date +%s) - T0 )) s since start"
    [ "$rc" -eq 0 ] || [ "$rc" -eq 124 ] || [ "$now" -gt "$before" ] && break
done
tar czf "$OUT/targets.tgz" -C "$TARGETS" .
ls -la "$OUT"
