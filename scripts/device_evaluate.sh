# Usage, on the lent GPU machine, in the repository root:
#   PACKS="gpu_pack_chairs/val:data/chairs/val gpu_pack_chairs/novel_test:data/chairs_novel/test" OUT=DIR \
#       bash scripts/device_evaluate.sh COMMANDS_FILE
# Evaluates on the GPU splits made here (the GPU machine has no open3d to make them): each PACK_DIR:DATA/SPLIT pair is a
# split packed by scripts/pack_split.py (the first N scenes or all) unpacked into DATA/SPLIT; any
# *_model.* file in a pack goes to prismonet/assets (scripts/device_slim.sh leaves the shipped weights behind). Then
# every line of COMMANDS_FILE runs (bash), its output in $OUT/log.txt; each evaluate should write --json $OUT/NAME.json.
# Kornia comes from carried wheels (.whl/) as in scripts/device_setup.sh. Carry data/furniture/NAME too for an imported
# setting: without its meshes the rotation columns up to symmetry read as the plain rotation error.
set -x
T0=$(date +%s)
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
for pair in $PACKS; do
    src=${pair%%:*}; dst=${pair#*:}
    python3 scripts/pack_split.py unpack "$src" "$dst" || exit 4   # writes the split's entries into DATA/meta.json
    cp "$src"/*_model.* prismonet/assets/ 2>/dev/null
done
nvidia-smi -L 2>/dev/null
python3 -c "import torch, kornia, prismonet; print(torch.__version__, torch.cuda.is_available(), kornia.__version__)" || exit 5
export PYTHONUNBUFFERED=1
bash "$1" 2>&1 | tr '\r' '\n' | grep -v "it/s\]$\|s/it\]$" | tee "$OUT/log.txt"
echo "$(( $(date +%s) - T0 )) s since start"
