#!/usr/bin/env bash
# Set up PriSMONet on a fresh machine: system library for open3d, then the package itself.
# Idempotent and quick when everything is already there. Installs into the active Python
# (a venv if one is active). Needs Python 3.11.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
export PIP_ROOT_USER_ACTION=ignore PIP_DISABLE_PIP_VERSION_CHECK=1

if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)'; then
  echo "setup: Python 3.11 is required, found $("$PY" --version 2>&1)" >&2
  exit 1
fi

# open3d fails to import without libusb-1.0. (Capture first: `ldconfig -p | grep -q` under
# pipefail fails whenever grep quits early and ldconfig gets SIGPIPE.)
libs=$(ldconfig -p 2>/dev/null || /sbin/ldconfig -p 2>/dev/null || true)
if [[ "$libs" != *libusb-1.0.so.0* ]]; then
  echo "setup: installing libusb-1.0-0 (needed by open3d)"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

# torch first and pinned, so that nothing can resolve a newer (CUDA) build.
if ! "$PY" -c 'import torch, sys; sys.exit(0 if torch.__version__.startswith("2.13.0") else 1)' 2>/dev/null; then
  "$PY" -m pip install -q torch==2.13.0
fi
if ! "$PY" -m pip show -q prismonet >/dev/null 2>&1 || [ "${PRISMONET_REINSTALL:-0}" = 1 ]; then
  "$PY" -m pip install -q -e ".[test]"
else
  # already installed in editable mode from somewhere: make sure it is this checkout
  loc=$("$PY" -c 'import prismonet, os; print(os.path.dirname(os.path.dirname(os.path.abspath(prismonet.__file__))))' 2>/dev/null || true)
  if [ "$loc" != "$(pwd)" ]; then "$PY" -m pip install -q -e ".[test]"; fi
fi
"$PY" -c 'import open3d, kornia, cv2, torch; print(f"setup: ok (torch {torch.__version__}, kornia {kornia.__version__}, open3d {open3d.__version__}, opencv {cv2.__version__})")'
