#!/usr/bin/env bash
# Placeholder so that run_demo.sh works end to end; the estimator engineer replaces it with the
# demo (ad_sim node feeding ad_estimator node with the bundled model).
echo "scripts/demo.sh: not implemented yet" >&2
exit 1
