#!/usr/bin/env bash
# The whole GPU training job, given generated bags:
#   scripts/gpu_train.sh BAGS OUT
# BAGS holds train/, seen/ and unseen/ (ad_sim.generate output, e.g. bags/paper). Writes teacher,
# students (ablations none, align_only, full; streaming, plus a UniFormer-style reference),
# exported ONNX models with <name>.metrics.json and evaluation reports under OUT.
# Every step resumes: re-running after a kill or a time limit continues from the last epoch.
#
# Environment knobs (defaults in brackets):
#   NPROC [number of GPUs]      processes (one per GPU; >1 runs through torchrun/DDP)
#   SIZE [paper]                model size preset: tiny | small | paper
#   TEACHER_EPOCHS [300] STUDENT_EPOCHS [20] BATCH [32] (per process) LR [1e-4]
#   REGL1_WEIGHT [training's default, SPEC 9's 0.2]  the students' RegL1 weight (the bundled
#                               model: 2.0). A resumed run refuses another value: use a fresh OUT to change it
#   PREVIOUS_FRAMES [0]         N: streaming students' frame encoders also see the N earlier
#                               observed frames (--previous-frames; the bundled model: 3). Fresh OUT to change it
#   ABLATION_EPOCHS [STUDENT_EPOCHS]  epochs of the none and align_only ablations
#   TEACHER [unset]             a trained teacher checkpoint to use instead of training one
#   ABLATIONS ["none align_only full"]  KINDS ["streaming uniformer"]
#   PARALLEL [0]                1: train the students side by side, one process each, spread over
#                               the GPUs in turn (logs in OUT/<name>.log); 0: one after another (DDP if NPROC>1)
#   SEED [0]                    seed of data split, initialisation and batches (a second seed: a fresh OUT)
#   SELECT [score]              validation metric that picks best.pt: score (CE + RegL1) or regl1
#   STOP_AFTER [0]              >0: every training step stops after that many epochs in this run
#   CACHE [OUT/cache]           DEVICE [cuda] (cpu: quick end-to-end checks of this script)
set -euo pipefail
if [ $# -ne 2 ]; then
    sed -n '2,25p' "$0"
    exit 2
fi
BAGS=$1
OUT=$2
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
export PYTHONPATH="$ROOT/ros_ws/src/ad_sim:$ROOT/ros_ws/src/ad_estimator:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
# GPUs by index (nvidia-smi -L would also count MIG instances)
GPUS=$( (nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null || true) | wc -l)
NPROC=${NPROC:-$GPUS}
NPROC=$(( NPROC > 0 ? NPROC : 1 ))
SIZE=${SIZE:-paper}
TEACHER_EPOCHS=${TEACHER_EPOCHS:-300}
STUDENT_EPOCHS=${STUDENT_EPOCHS:-20}
ABLATION_EPOCHS=${ABLATION_EPOCHS:-$STUDENT_EPOCHS}
BATCH=${BATCH:-32}
LR=${LR:-1e-4}
ABLATIONS=${ABLATIONS:-none align_only full}
KINDS=${KINDS:-streaming uniformer}
STOP_AFTER=${STOP_AFTER:-0}
PARALLEL=${PARALLEL:-0}
DEVICE=${DEVICE:-cuda}
CACHE=${CACHE:-$OUT/cache}
for split in train seen unseen; do
    [ -d "$BAGS/$split" ] || { echo "gpu_train.sh: $BAGS/$split missing; generate it with" \
        "python -m ad_sim.generate --size paper --split $split --out $BAGS/$split --device cuda" >&2; exit 1; }
done
if [ "$NPROC" -gt 1 ]; then
    RUN=(python -m torch.distributed.run --standalone --nproc_per_node="$NPROC" -m training)
else
    RUN=(python -m training)
fi
COMMON=(--cache "$CACHE" --size "$SIZE" --batch-size "$BATCH" --lr "$LR" --device "$DEVICE" --stop-after "$STOP_AFTER"
        --seed "${SEED:-0}" --select "${SELECT:-score}")
[ "$DEVICE" = cpu ] || COMMON+=(--amp)
mkdir -p "$OUT"

echo "==> cache ($BAGS)"
# One process per bag: decoding is CPU-bound and the cache is keyed per bag.
pids=()
for bag in "$BAGS"/{train,seen,unseen}/*/; do
    python -m training cache --bags "$bag" --cache "$CACHE" >/dev/null &
    pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done

# trained DIR EPOCHS: DIR's run has all EPOCHS epochs (a --stop-after slice or a kill leaves fewer).
trained() {
    python -c 'import json, sys; sys.exit(len(json.load(open(sys.argv[1]))) < int(sys.argv[2]))' \
        "$1/history.json" "$2" 2>/dev/null
}

if [ -n "${TEACHER:-}" ]; then
    echo "==> teacher: $TEACHER"
    mkdir -p "$OUT/teacher"
    cp "$TEACHER" "$OUT/teacher/best.pt"
else
    echo "==> teacher ($NPROC process(es), $TEACHER_EPOCHS epochs)"
    "${RUN[@]}" teacher --bags "$BAGS/train" --out "$OUT/teacher" --epochs "$TEACHER_EPOCHS" "${COMMON[@]}"
    # Students distil the finished teacher only: after a STOP_AFTER slice, run this script again.
    trained "$OUT/teacher" "$TEACHER_EPOCHS" || { echo "==> teacher not finished; run again to go on"; exit 0; }
fi

# Students: each trains in its own process; with PARALLEL=1 they train at the same time, one
# process each, spread over the GPUs in turn (one H200 has room for several: two paper students
# share one at about 43 s per epoch each, against about 30 s alone).
STUDENTS=()
for kind in $KINDS; do
    for ablation in $ABLATIONS; do
        # The UniFormer-style reference is trained in the full setting only.
        [ "$kind" = uniformer ] && [ "$ablation" != full ] && continue
        STUDENTS+=("$kind:$ablation")
    done
done
pids=() names=()
trap '[ ${#pids[@]} -eq 0 ] || kill "${pids[@]}" 2>/dev/null' EXIT  # a time limit stops the students too
STUDENT_RUN=("${RUN[@]}")
[ "$PARALLEL" = 1 ] && STUDENT_RUN=(python -m training)
for student in "${STUDENTS[@]}"; do
    kind=${student%%:*} ablation=${student##*:} name="${student/:/_}"
    epochs=$STUDENT_EPOCHS
    [ "$ablation" = full ] || epochs=$ABLATION_EPOCHS
    trained "$OUT/$name" "$epochs" && { echo "==> student $name: trained"; continue; }
    echo "==> student $name ($epochs epochs)"
    cmd=("${STUDENT_RUN[@]}" student --bags "$BAGS/train" --out "$OUT/$name" --epochs "$epochs"
         --teacher "$OUT/teacher/best.pt" --kind "$kind" --ablation "$ablation"
         ${REGL1_WEIGHT:+--regl1-weight "$REGL1_WEIGHT"} "${COMMON[@]}")
    [ "${PREVIOUS_FRAMES:-0}" != 0 ] && [ "$kind" = streaming ] && cmd+=(--previous-frames "$PREVIOUS_FRAMES")
    if [ "$PARALLEL" = 1 ]; then
        gpu=()
        [ "$GPUS" -gt 1 ] && gpu=(env CUDA_VISIBLE_DEVICES=$(( ${#pids[@]} % GPUS )))
        "${gpu[@]}" "${cmd[@]}" --no-progress >"$OUT/$name.log" 2>&1 &
        pids+=($!) names+=("$name")
    else
        "${cmd[@]}"
    fi
done
# A student that fails leaves the others running (its log says why; the loop below skips it).
for i in "${!pids[@]}"; do
    wait "${pids[$i]}" || echo "==> student ${names[$i]} failed (exit $?); see $OUT/${names[$i]}.log"
done
pids=()
for student in "${STUDENTS[@]}"; do
    name="${student/:/_}" model="$OUT/models/${student/:/_}.onnx"
    epochs=$STUDENT_EPOCHS
    [ "${student##*:}" = full ] || epochs=$ABLATION_EPOCHS
    trained "$OUT/$name" "$epochs" || { echo "==> $name not finished; run again to go on"; continue; }
    # A clip model re-reads all 25 frames per estimate (~0.4 s on one core at paper size): give it every core.
    threads=1
    [ "${student%%:*}" = uniformer ] && threads=$(nproc)
    # Each step is skipped when its output is newer than its input (a re-run after a time limit).
    [ "$model" -nt "$OUT/$name/best.pt" ] ||
        python -m training export --checkpoint "$OUT/$name/best.pt" --out "$model"
    for split in seen unseen; do
        [ "$OUT/reports/${name}_$split/metrics.json" -nt "$model" ] ||
            python -m training evaluate --model "$model" --bags "$BAGS/$split" --cache "$CACHE" \
                --out "$OUT/reports/${name}_$split" --title "$name on $split" --threads "$threads" --no-progress
    done
done
echo "==> done: models in $OUT/models, reports in $OUT/reports"
