#!/usr/bin/env bash
# Optional: Blender as a Python module, for the photoreal test ladder (`prismonet data blender`).
# bpy 4.5 pins numpy<2, which the project's own environment cannot take, so it goes into its own
# virtual environment, .venv-blender, which the ladder's worker runs in. About 370 MB to download and
# 950 MB installed. Needs Python 3.11 and X/GL client libraries (libx11-6 libxrender1 libxfixes3
# libxi6 libxkbcommon0 libxext6 libsm6 libice6 libgl1 on Debian); the README of the Blender assets
# (prismonet/assets/clevr_blender) has the measured facts.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
export PIP_ROOT_USER_ACTION=ignore PIP_DISABLE_PIP_VERSION_CHECK=1
if [ ! -x .venv-blender/bin/python ]; then
  "$PY" -m venv .venv-blender
fi
if ! .venv-blender/bin/python -c 'import bpy' 2>/dev/null; then
  .venv-blender/bin/python -m pip install -q "bpy==4.5.15"
fi
.venv-blender/bin/python -c 'import bpy; print(f"setup_blender: ok (bpy {bpy.app.version_string}) in .venv-blender")'
