#!/usr/bin/env bash
# The main job in one command: scripts/demo.sh sets everything up (idempotent), then runs the
# simulator feeding the estimator with the bundled model. Arguments go to scripts/demo.py.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
exec scripts/demo.sh "$@"
