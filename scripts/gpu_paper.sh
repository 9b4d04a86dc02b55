#!/usr/bin/env bash
# The full-scale job (issue 6) on the GPU machine, resumable across 10-minute device calls:
#   scripts/gpu_paper.sh WORK [RESULTS]        run (or continue) the job
#   scripts/gpu_paper.sh --pack WORK RESULTS   only pack what is there (after a `timeout`)
# 1. generates the `paper` benchmark (train 9000 x 4 views, seen 900, unseen 900) into WORK/bags with
#    CUDA Warp, GEN_PROCS generator processes per split spread over the GPUs (finished shards are skipped);
# 2. runs scripts/gpu_train.sh (teacher, the three streaming-student ablations, the UniFormer-style
#    reference, export, seen/unseen evaluation with temporal OOD) into WORK/run;
# 3. with BASELINE>0: the per-scene CMA-ES baseline and the re-simulation PSNR of the `full` student on
#    BASELINE random unseen instances;
# 4. packs models, metrics, reports and logs into RESULTS/results.tar.gz (small enough to bring back).
# Run it again after a time limit: every stage continues where it stopped. Knobs: those of
# scripts/gpu_train.sh, plus GEN_PROCS [4], SIZE_BENCH [paper], BASELINE [0], DEVICE [cuda].
set -euo pipefail
[ $# -ge 1 ] || { sed -n '2,13p' "$0"; exit 2; }
PACK_ONLY=0
if [ "$1" = --pack ]; then
    PACK_ONLY=1
    shift
    [ $# -ge 1 ] || { echo "gpu_paper.sh: --pack needs WORK, the folder of an earlier run: --pack WORK [RESULTS]" >&2; exit 2; }
fi
WORK=$1
RESULTS=${2:-$WORK/results}
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
export PYTHONPATH="$ROOT/ros_ws/src/ad_sim:$ROOT/ros_ws/src/ad_estimator:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
GEN_PROCS=${GEN_PROCS:-4}
SIZE_BENCH=${SIZE_BENCH:-paper}
BASELINE=${BASELINE:-0}
export DEVICE=${DEVICE:-cuda}
BAGS=$WORK/bags
RUN=$WORK/run

packed() {  # what of WORK goes into the archive, relative to WORK (nothing if WORK is missing)
    (cd "$WORK" 2>/dev/null && ls -d run/models run/reports run/*.log run/*/history.json run/summary.json \
        baseline 2>/dev/null) || true
}
pack() {
    mkdir -p "$RESULTS"
    tar -czf "$RESULTS/results.tar.gz" -C "$WORK" --ignore-failed-read $(packed) 2>/dev/null || true
    # The teacher travels on its own: with it a later machine trains students without retraining it.
    [ -f "$WORK/run/teacher/best.pt" ] && cp "$WORK/run/teacher/best.pt" "$RESULTS/teacher.pt" || true
}
if [ "$PACK_ONLY" = 1 ]; then
    [ -d "$WORK" ] || { echo "gpu_paper.sh: --pack: $WORK does not exist; give the WORK folder of an earlier run" >&2; exit 1; }
    [ -n "$(packed)" ] || { echo "gpu_paper.sh: --pack: nothing to pack in $WORK (no run/models, run/reports, run logs or" \
        "baseline); give the WORK folder of an earlier run" >&2; exit 1; }
    rm -f "$RESULTS/results.tar.gz"  # an earlier archive must not pass for this one
    pack
    [ -s "$RESULTS/results.tar.gz" ] || { echo "gpu_paper.sh: --pack: no archive written to $RESULTS" >&2; exit 1; }
    ls -la "$RESULTS"
    exit 0
fi
mkdir -p "$BAGS" "$RUN" "$RESULTS"
trap pack EXIT

echo "==> generate $SIZE_BENCH ($GEN_PROCS processes per split) $(date +%T)"
# One short run first compiles Warp's kernels into the cache the shard processes then share.
python -m ad_sim.generate --size tiny --split unseen --limit 1 --out "$WORK/warmup" --device "$DEVICE" --quiet
# GPUs by index (nvidia-smi -L would also count MIG instances)
GPUS=$( (nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null || true) | wc -l)
for split in train seen unseen; do
    pids=()
    for ((i = 0; i < GEN_PROCS; i++)); do
        gpu=()  # shard i on GPU i mod GPUS
        [ "$GPUS" -gt 1 ] && gpu=(env CUDA_VISIBLE_DEVICES=$(( i % GPUS )))
        "${gpu[@]}" python -m ad_sim.generate --size "$SIZE_BENCH" --split "$split" --shard "$i/$GEN_PROCS" \
            --out "$BAGS/$split" --device "$DEVICE" --quiet &
        pids+=($!)
    done
    for pid in "${pids[@]}"; do wait "$pid"; done
    echo "    $split done $(date +%T): $(du -sh "$BAGS/$split" | cut -f1)"
done

echo "==> train $(date +%T)"
scripts/gpu_train.sh "$BAGS" "$RUN"

if [ "$BASELINE" -gt 0 ]; then
    echo "==> baseline and re-simulation PSNR on $BASELINE unseen instances $(date +%T)"
    mkdir -p "$WORK/baseline"
    [ -f "$WORK/baseline/baseline.json" ] || python -m training baseline --bags "$BAGS/unseen" \
        --instances "$BASELINE" --device "$DEVICE" --out "$WORK/baseline/baseline.json"
    [ -f "$WORK/baseline/student_psnr.json" ] || python -m training resim-psnr \
        --model "$RUN/models/streaming_full.onnx" --bags "$BAGS/unseen" --instances "$BASELINE" \
        --device "$DEVICE" --out "$WORK/baseline/student_psnr.json"
fi
echo "==> done $(date +%T)"
