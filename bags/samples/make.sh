#!/usr/bin/env bash
# Regenerates the committed sample bags (bags/README.md). Deterministic: same code, same bytes.
set -euo pipefail
cd "$(dirname "$0")/../.."
rm -rf bags/samples/unseen-masks-0of1 bags/samples/unseen-particles-0of1
# Every family on the tiny unseen split (2 unseen shapes x 3 families), one view, no particles.
scripts/adrun ad_sim generate --size tiny --split unseen --views 1 --skip-particles --name unseen-masks --out bags/samples
# Two more unseen episodes with every topic, tracked particles included (60 KB a frame).
scripts/adrun ad_sim generate --instances bags/samples/particles.yaml --name unseen-particles --out bags/samples
