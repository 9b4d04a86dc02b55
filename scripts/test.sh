#!/usr/bin/env bash
# The README's test command: ./setup.sh (quick when nothing changed), then the pytest suite
# (tests/ plus any ros_ws/src/<pkg>/test). Arguments go to pytest instead of the default paths,
# e.g. `scripts/test.sh tests/test_workspace.py -x`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

./setup.sh
. ./env.sh

# A ROS domain of its own for each run and discovery on this machine only, so that concurrent runs
# and other hosts never cross-talk (tests/conftest.py gives each test the next domain from here).
ROS_DOMAIN_ID=$(( (RANDOM + $$) % 100 + 1 ))
export ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset ROS_LOCALHOST_ONLY ROS_STATIC_PEERS  # ROS_LOCALHOST_ONLY is deprecated and overrides the range

if [ $# -eq 0 ]; then
    set -- tests
    for package_tests in ros_ws/src/*/test; do
        [ -d "$package_tests" ] && set -- "$@" "$package_tests"
    done
fi

echo "==> pytest $* (ROS_DOMAIN_ID=$ROS_DOMAIN_ID)"
status=0
# A module that fails to import fails the run, but the rest of the suite still runs and reports.
python -m pytest -p no:cacheprovider --continue-on-collection-errors "$@" || status=$?
if [ "$status" -eq 5 ]; then
    echo "scripts/test.sh: pytest collected no tests from: $* (check the paths and -k/-m filters)" >&2
    exit 1
fi
exit "$status"
