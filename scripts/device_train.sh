# Usage, on the lent GPU machine, in the repository root (what travels: the configs, $PACK and .whl):
#   [CONFIGS=configs/gpu_tableware] [DATA=data/furniture_tabletop] [PACK=gpu_pack] [DEADLINE_S=480] [PROBE=20] \
#       OUT=DIR bash scripts/device_train.sh
# The GPU machine has no kornia and no open3d: kornia travels as wheels in .whl/ (python3 -m pip download ... kornia
# kornia_rs; see BENCHMARKS.md, "Training on a GPU"), the training split as scripts/pack_split.py packs it ($PACK/train,
# with the dataset's meta.json in $PACK), and any init_from model inside $PACK. Every run in $CONFIGS then trains side
# by side until DEADLINE_S seconds after this script starts (scripts/side_by_side.py); each comes back as $OUT/NAME.tgz.
set -x
CONFIGS=${CONFIGS:-configs/gpu_tableware}
DATA=${DATA:-data/furniture_tabletop}
PACK=${PACK:-gpu_pack}
DEADLINE_S=${DEADLINE_S:-480}
T0=$(date +%s)
. scripts/device_setup.sh || exit $?
OUT=$OUT CONFIGS=$CONFIGS PROBE=${PROBE:-20} DEVICE=${DEVICE:-cuda} PYTHONUNBUFFERED=1 python3 scripts/side_by_side.py $(( T0 + DEADLINE_S ))
ls -la "$OUT"
