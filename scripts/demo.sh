#!/usr/bin/env bash
# The README's main job: set up (idempotent, quick when nothing changed), then the simulator feeding
# the estimator with the bundled model on unseen shapes, each estimate printed beside its ground
# truth (scripts/demo.py; arguments go there, e.g. --episodes 3 or --help).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
case " $* " in
  *" -h "*|*" --help "*) [[ -x .venv/bin/python ]] || ./setup.sh ;;  # help needs the environment, not a re-check
  *) ./setup.sh ;;
esac
set +u  # the venv's and colcon's setup scripts read unset variables
. ./env.sh
set -u
exec python scripts/demo.py "$@"
