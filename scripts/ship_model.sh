#!/usr/bin/env bash
# Copy a finished run into the package as a named model: ship_model.sh RUN NAME CONFIG
#   -> prismonet/assets/NAME_model.{safetensors,json}, NAME_train_config.json, NAME_train_log.jsonl
set -euo pipefail
run=$1; name=$2; config=$3
[ -f "$run/model.safetensors" ] && [ -f "$run/model.json" ] || { echo "ship_model: $run has no finished model" >&2; exit 2; }
dst=prismonet/assets
cp "$run/model.safetensors" "$dst/${name}_model.safetensors"
cp "$run/model.json" "$dst/${name}_model.json"
cp "$config" "$dst/${name}_train_config.json"
cp "$run/log.jsonl" "$dst/${name}_train_log.jsonl"
echo "shipped $run as $name ($(du -ch $dst/${name}_* | tail -1 | cut -f1))"
