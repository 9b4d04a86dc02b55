#!/usr/bin/env bash
# Section 18: how much does the scenes' randomness cost? Two probes of the benchmark's scenes, each in a
# private patched copy of the tree (patch33.py), the shipped recipe without alignment, seed 0, side by side:
#   up: every instance upright (cameras, drop gap, offset, velocity, particles as in the benchmark);
#   ps: one pose per shape (orientation, drop gap, offset, velocity from the shape alone).
# And, with the unpatched tree, the shipped model on seen-split parameters simulated in training scenes
# (trainscenes_seen_params.yaml: each seen instance's parameters with the seed of the training instance of
# the same shape, family and index, so its pose, velocity, particles and view 0 are a training clip's).
set -uo pipefail
SRC=$(cd "$(dirname "$0")/../../.." && pwd)
J=$SRC/.gpu/b/jobs
log() { echo "$(date +%T) $*"; }
log start; nvidia-smi -L; df -h /root | tail -1
rm -rf /root/repo /root/repo_up /root/repo_ps
cp -a "$SRC" /root/repo && cp -a "$SRC" /root/repo_up && cp -a "$SRC" /root/repo_ps
python3 $J/patch33.py upright /root/repo_up/ros_ws/src/ad_sim/ad_sim/instances.py
python3 $J/patch33.py pose_per_shape /root/repo_ps/ros_ws/src/ad_sim/ad_sim/instances.py
cd /root/repo && . .gpu/b/env.sh
BASE=$PYTHONPATH
in_tree() { local t=$1; shift; (cd $t && PYTHONPATH="$t/ros_ws/src/ad_sim:$t/ros_ws/src/ad_estimator:$t:$BASE" "$@"); }
W=/root/w; R=/root/r; mkdir -p $W $R/models $R/reports
TRAIN_S=${TRAIN_S:-1080}
M=/root/repo/ros_ws/src/ad_estimator/ad_estimator/models/default.onnx
in_tree /root/repo python -m ad_sim.generate --size tiny --split unseen --limit 1 --out $W/warmup --device cuda --quiet
# Four generating processes at a time, as in sections 15 to 17: eight at once (both probes) took the machine down.
for v in up ps; do
  for i in 0 1 2 3; do
    (in_tree /root/repo_$v python -m ad_sim.generate --size paper --split train --shard $i/4 --out $W/$v/train --device cuda --quiet
     for split in seen unseen; do
       in_tree /root/repo_$v python -m ad_sim.generate --size paper --split $split --shard $i/4 --out $W/$v/$split --device cuda --quiet --skip-particles
     done) &
  done; wait; log "generated $v"; free -g | head -2
done
in_tree /root/repo python -m ad_sim.generate --instances $J/trainscenes_seen_params.yaml --out $W/trainscenes --device cuda --quiet --skip-particles
log generated; du -sh $W/*/*; df -h /root | tail -1
for v in up ps; do   # one process per bag, one probe at a time (host memory)
  for bag in $W/$v/train/*; do
    in_tree /root/repo_$v python -c "import sys; from training import data; data.load_dataset(sys.argv[1], '$R/cache_$v', False)" $bag &
  done; wait
done
log cached; du -sh $R/cache_*; df -h /root | tail -1
S=(python -m training student --kind streaming --size paper --batch-size 32 --device cuda --amp --no-progress
   --lr 1e-4 --epochs 20 --previous-frames 3 --regl1-weight 2.0 --ablation none)
for v in up ps; do
  in_tree /root/repo_$v timeout $TRAIN_S "${S[@]}" --bags $W/$v/train --cache $R/cache_$v --out $R/$v > $R/$v.log 2>&1 &
done
E=(python -m training evaluate --cache $R/cache_eval --no-progress --no-record --threads 4)
in_tree /root/repo "${E[@]}" --model $M --bags $W/trainscenes --out $R/reports/shipped_trainscenes \
  --title "shipped h3reg2 on seen-split parameters in training scenes" > $R/eval_shipped_trainscenes.log 2>&1
for v in up ps; do for split in seen unseen; do   # the shipped model on the probes' scenes, while they train
  in_tree /root/repo "${E[@]}" --model $M --bags $W/$v/$split --out $R/reports/shipped_${v}_$split \
    --title "shipped h3reg2 on $v scenes, $split" > $R/eval_shipped_${v}_$split.log 2>&1
done; done
log "shipped evaluated"
wait
log trained
for v in up ps; do
  (in_tree /root/repo_$v python -m training export --checkpoint $R/$v/best.pt --out $R/models/$v.onnx > $R/export_$v.log 2>&1
   for split in seen unseen; do
     in_tree /root/repo_$v "${E[@]}" --model $R/models/$v.onnx --bags $W/$v/$split --out $R/reports/${v}_$split \
       --title "$v scenes: h3reg2 recipe without alignment, seed 0, $split" > $R/eval_${v}_$split.log 2>&1 &
   done; wait) &
done; wait
log evaluated
for f in $R/eval_*.log; do echo "== $f"; grep '^| 25 ' $f; done
cd $R && tar czf /root/results33.tgz *.log up/*.json ps/*.json reports/*/*.json reports/*/*.md 2>/dev/null
tar czf /root/plots33.tgz reports 2>/dev/null; ls -la /root/results33.tgz /root/plots33.tgz
log done
