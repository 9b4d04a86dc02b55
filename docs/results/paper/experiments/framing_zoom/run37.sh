#!/usr/bin/env bash
# Framing probe: the shipped recipe without alignment, trained with --zoom 0.35 (each training clip reframed
# by a zoom in [0.65, 1.35]); camera_resolution (20 unseen instances per family) for it and for the shipped
# model, on the same GPU, and the unseen split's table for it.
set -uo pipefail
SRC=$(cd "$(dirname "$0")/../../.." && pwd)
log() { echo "$(date +%T) $*"; }
log start; nvidia-smi -L; df -h /root | tail -1
rm -rf /root/repo_z && mkdir -p /root/repo_z && tar -C /root/repo_z -xzf $SRC/.gpu/b/tree.tgz  # HEAD, not the working tree
cd /root/repo_z && . $SRC/.gpu/b/env.sh
export PYTHONPATH="/root/repo_z/ros_ws/src/ad_sim:/root/repo_z/ros_ws/src/ad_estimator:/root/repo_z:$PYTHONPATH"
W=/root/w; R=/root/r; mkdir -p $W $R/models $R/reports
SHIPPED=$SRC/ros_ws/src/ad_estimator/ad_estimator/models/default.onnx
python -m ad_sim.generate --size tiny --split unseen --limit 1 --out $W/warmup --device cuda --quiet
for i in 0 1 2 3; do
  (python -m ad_sim.generate --size paper --split train --shard $i/4 --out $W/z/train --device cuda --quiet
   python -m ad_sim.generate --size paper --split unseen --shard $i/4 --out $W/z/unseen --device cuda --quiet --skip-particles) &
done; wait
log generated; du -sh $W/z/*
for bag in $W/z/train/*; do
  python -c "import sys; from training import data; data.load_dataset(sys.argv[1], '$R/cache_z', False)" $bag &
done; wait
log cached
S=(python -m training student --kind streaming --size paper --batch-size 32 --device cuda --amp --no-progress
   --lr 1e-4 --epochs 20 --previous-frames 3 --regl1-weight 2.0 --ablation none --bags $W/z/train --cache $R/cache_z)
timeout 900 "${S[@]}" --zoom 0.35 --seed 0 --out $R/zoom35 > $R/zoom35.log 2>&1 &
python benchmarks/camera_resolution.py --instances 20 --device cuda --model $SHIPPED --json $R/cam_shipped.json > $R/cam_shipped.log 2>&1
log "shipped camera_resolution rc=$?"
wait
log trained
python -m training export --checkpoint $R/zoom35/best.pt --out $R/models/zoom35.onnx > $R/export_zoom35.log 2>&1
python -m ad_estimator.evaluate --model $R/models/zoom35.onnx --bags $W/z/unseen --frames --out $R/reports/zoom35_unseen \
  --title "h3reg2 recipe without alignment, --zoom 0.35, seed 0, unseen" --threads 8 --quiet > $R/eval_zoom35_unseen.log 2>&1 &
python benchmarks/camera_resolution.py --instances 20 --device cuda --model $R/models/zoom35.onnx --json $R/cam_zoom35.json > $R/cam_zoom35.log 2>&1
log "zoom camera_resolution rc=$?"
wait
log evaluated
grep '^| 25 ' $R/eval_zoom35_unseen.log; tail -25 $R/cam_zoom35.log
cd $R && tar czf /root/results37.tgz *.log zoom35/*.json cam_*.json reports/*/*.json reports/*/*.md; ls -la /root/results37.tgz
log done
