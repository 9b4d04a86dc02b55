#!/usr/bin/env bash
# The main job in one command: scripts/demo.sh sets everything up (idempotent), then runs the
# simulator feeding the estimator with the bundled model. Arguments go to scripts/demo.py; paths in
# them are taken from the directory you run this in.
set -euo pipefail
exec "$(dirname "${BASH_SOURCE[0]}")/scripts/demo.sh" "$@"
