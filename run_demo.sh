#!/usr/bin/env bash
# The main job in one command: set everything up (idempotent), then run the simulator feeding the
# estimator with the bundled model (scripts/demo.sh). Arguments go to scripts/demo.sh.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
./setup.sh
exec scripts/demo.sh "$@"
