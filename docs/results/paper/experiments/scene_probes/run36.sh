#!/usr/bin/env bash
# Section 19, upright and fixed-motion probe: upright, drop gap, offset and velocity fixed; seed 0.
set -uo pipefail
SRC=$(cd "$(dirname "$0")/../../.." && pwd)
J=$SRC/.gpu/b/jobs
log() { echo "$(date +%T) $*"; }
log start; nvidia-smi -L; df -h /root | tail -1
rm -rf /root/repo_uf && mkdir -p /root/repo_uf && tar -C /root/repo_uf -xzf $SRC/.gpu/b/tree.tgz  # HEAD, not the working tree
python3 $J/patch33.py upright_fixed_motion /root/repo_uf/ros_ws/src/ad_sim/ad_sim/instances.py
cd /root/repo_uf && . $SRC/.gpu/b/env.sh
export PYTHONPATH="/root/repo_uf/ros_ws/src/ad_sim:/root/repo_uf/ros_ws/src/ad_estimator:/root/repo_uf:$PYTHONPATH"
W=/root/w; R=/root/r; mkdir -p $W $R/models $R/reports
python -m ad_sim.generate --size tiny --split unseen --limit 1 --out $W/warmup --device cuda --quiet
for i in 0 1 2 3; do
  (python -m ad_sim.generate --size paper --split train --shard $i/4 --out $W/uf/train --device cuda --quiet
   for split in seen unseen; do
     python -m ad_sim.generate --size paper --split $split --shard $i/4 --out $W/uf/$split --device cuda --quiet --skip-particles
   done) &
done; wait
log generated; du -sh $W/uf/*
for bag in $W/uf/train/*; do
  python -c "import sys; from training import data; data.load_dataset(sys.argv[1], '$R/cache_uf', False)" $bag &
done; wait
log cached; df -h /root | tail -1
S=(python -m training student --kind streaming --size paper --batch-size 32 --device cuda --amp --no-progress
   --lr 1e-4 --epochs 20 --previous-frames 3 --regl1-weight 2.0 --ablation none --bags $W/uf/train --cache $R/cache_uf)
for seed in 0; do timeout 900 "${S[@]}" --seed $seed --out $R/uf_s$seed > $R/uf_s$seed.log 2>&1 & done; wait
log trained
for seed in 0; do
  (python -m training export --checkpoint $R/uf_s$seed/best.pt --out $R/models/uf_s$seed.onnx > $R/export_uf_s$seed.log 2>&1
   for split in seen unseen; do
     python -m ad_estimator.evaluate --model $R/models/uf_s$seed.onnx --bags $W/uf/$split --frames --out $R/reports/uf_s${seed}_$split \
       --title "upright fixed-motion scenes: h3reg2 recipe without alignment, seed $seed, $split" --threads 4 --quiet > $R/eval_uf_s${seed}_$split.log 2>&1 &
   done; wait) &
done; wait
log evaluated
for f in $R/eval_*.log; do echo "== $f"; grep '^| 25 ' $f; done
mkdir -p ${OUT:-/root/out}; cd $R && tar czf /root/results36.tgz *.log uf_s*/*.json reports/*/*.json reports/*/*.md; ls -la /root/results36.tgz
log done
