#!/usr/bin/env bash
# Set up (idempotent) and run the default test suite. Slow tests are opt-in: `-m slow`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec python3 -m pytest "$@"
