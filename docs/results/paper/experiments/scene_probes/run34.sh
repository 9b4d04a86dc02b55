#!/usr/bin/env bash
# Section 18, two more seeds of the upright probe (run33.sh's `up`): seeds 1 and 2 side by side.
set -uo pipefail
SRC=$(cd "$(dirname "$0")/../../.." && pwd)
J=$SRC/.gpu/b/jobs
log() { echo "$(date +%T) $*"; }
log start; nvidia-smi -L; df -h /root | tail -1
rm -rf /root/repo_up && cp -a "$SRC" /root/repo_up
python3 $J/patch33.py upright /root/repo_up/ros_ws/src/ad_sim/ad_sim/instances.py
cd /root/repo_up && . .gpu/b/env.sh
export PYTHONPATH="/root/repo_up/ros_ws/src/ad_sim:/root/repo_up/ros_ws/src/ad_estimator:/root/repo_up:$PYTHONPATH"
W=/root/w; R=/root/r; mkdir -p $W $R/models $R/reports
python -m ad_sim.generate --size tiny --split unseen --limit 1 --out $W/warmup --device cuda --quiet
for i in 0 1 2 3; do
  (python -m ad_sim.generate --size paper --split train --shard $i/4 --out $W/up/train --device cuda --quiet
   for split in seen unseen; do
     python -m ad_sim.generate --size paper --split $split --shard $i/4 --out $W/up/$split --device cuda --quiet --skip-particles
   done) &
done; wait
log generated; du -sh $W/up/*
for bag in $W/up/train/*; do
  python -c "import sys; from training import data; data.load_dataset(sys.argv[1], '$R/cache_up', False)" $bag &
done; wait
log cached; df -h /root | tail -1
S=(python -m training student --kind streaming --size paper --batch-size 32 --device cuda --amp --no-progress
   --lr 1e-4 --epochs 20 --previous-frames 3 --regl1-weight 2.0 --ablation none --bags $W/up/train --cache $R/cache_up)
for seed in 1 2; do timeout 1080 "${S[@]}" --seed $seed --out $R/up_s$seed > $R/up_s$seed.log 2>&1 & done; wait
log trained
for seed in 1 2; do
  (python -m training export --checkpoint $R/up_s$seed/best.pt --out $R/models/up_s$seed.onnx > $R/export_up_s$seed.log 2>&1
   for split in seen unseen; do
     python -m ad_estimator.evaluate --model $R/models/up_s$seed.onnx --bags $W/up/$split --frames --out $R/reports/up_s${seed}_$split \
       --title "upright scenes: h3reg2 recipe without alignment, seed $seed, $split" --threads 4 --quiet > $R/eval_up_s${seed}_$split.log 2>&1 &
   done; wait) &
done; wait
log evaluated
for f in $R/eval_*.log; do echo "== $f"; grep '^| 25 ' $f; done
cd $R && tar czf /root/results34.tgz *.log up_s*/*.json reports/*/*.json reports/*/*.md; ls -la /root/results34.tgz
log done
