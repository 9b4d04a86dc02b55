#!/usr/bin/env bash
# The README's main job: set up (idempotent, quick when nothing changed), then the simulator feeding
# the estimator with the bundled model on unseen shapes, each estimate printed beside its ground
# truth (scripts/demo.py; arguments go there, e.g. --episodes 3 or --help). It stays in the caller's
# directory, so that relative paths in the arguments (--model, --logs) mean what the caller meant.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case " $* " in
  *" -h "*|*" --help "*) (. "$ROOT/env.sh") >/dev/null 2>&1 || "$ROOT/setup.sh" ;;  # help needs a working environment, not a re-check
  *) "$ROOT/setup.sh" ;;
esac
. "$ROOT/env.sh"
exec python "$ROOT/scripts/demo.py" "$@"
