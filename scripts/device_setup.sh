# Sourced on the lent GPU machine by scripts/device_train.sh and scripts/device_distill.sh, in the repository root:
# kornia from carried wheels (.whl/, if there), PYTHONPATH, and the packed training split $PACK/train
# (scripts/pack_split.py) unpacked into $DATA/train beside $PACK/meta.json; then what the machine has.
# Returns 3 (wheels), 4 (split) or 5 (imports) when a step fails.
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || return 3
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
mkdir -p "$DATA" && cp "$PACK/meta.json" "$DATA/" && python3 scripts/pack_split.py unpack "$PACK/train" "$DATA/train" || return 4
nvidia-smi -L 2>/dev/null
python3 -c "import torch, kornia, prismonet; print(torch.__version__, torch.cuda.is_available(), kornia.__version__)" || return 5
