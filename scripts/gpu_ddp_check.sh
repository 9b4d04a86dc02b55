#!/usr/bin/env bash
# Multi-GPU check (issue 4): the same teacher trained by one process and by torchrun/DDP over every
# GPU of the machine, with a stop and resume in the middle of the DDP run, then a DDP student.
#   scripts/gpu_ddp_check.sh WORK
# Generates the `small` train split into WORK/bags with CUDA Warp (skipped if there), prints each
# run's wall time, the speed-up ratio and both runs' final validation figures, and leaves logs,
# histories and ddp_check.json in WORK. Knobs: EPOCHS [8], DATA [small] (benchmark size generated),
# MODEL [paper] (model preset: the paper-size teacher gives the GPUs enough work to compare).
set -euo pipefail
[ $# -eq 1 ] || { sed -n '2,8p' "$0"; exit 2; }
WORK=$1
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
export PYTHONPATH="$ROOT/ros_ws/src/ad_sim:$ROOT/ros_ws/src/ad_estimator:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
EPOCHS=${EPOCHS:-8}
DATA=${DATA:-small}
MODEL=${MODEL:-paper}
command -v nvidia-smi >/dev/null || {
    echo "gpu_ddp_check.sh: nvidia-smi not found: this check runs on a machine with 2 or more NVIDIA GPUs and their driver" >&2
    exit 1
}
# GPUs by index, as scripts/gpu_paper.sh counts them (nvidia-smi -L would also count MIG instances); none if
# nvidia-smi fails (no driver loaded), which the check below then says
GPUS=$( (nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null || true) | wc -l)
[ "$GPUS" -ge 2 ] || { echo "gpu_ddp_check.sh: needs 2 or more GPUs, found $GPUS" >&2; exit 1; }
mkdir -p "$WORK"
BAGS=$WORK/bags/train
COMMON=(--bags "$BAGS" --cache "$WORK/cache" --size "$MODEL" --device cuda --amp --no-progress)
DDP=(python -m torch.distributed.run --standalone --nproc_per_node="$GPUS" -m training)

[ -d "$BAGS" ] || python -m ad_sim.generate --size "$DATA" --split train --out "$BAGS" --device cuda --quiet
python -m training cache --bags "$BAGS" --cache "$WORK/cache"

timed() {  # timed NAME CMD...: runs CMD, logs to WORK/NAME.log, records start and end in WORK/NAME.seconds
    local name=$1 start
    shift
    start=$(date +%s.%N)
    "$@" >>"$WORK/$name.log" 2>&1 || { tail -20 "$WORK/$name.log" >&2; exit 1; }
    echo "$start $(date +%s.%N)" >"$WORK/$name.seconds"
}
rm -rf "$WORK/single" "$WORK/ddp" "$WORK/ddp_student" "$WORK"/*.log "$WORK"/*.seconds
timed single python -m training teacher --out "$WORK/single" --epochs "$EPOCHS" "${COMMON[@]}"
# DDP: stop after half the epochs (as a time limit would), then resume to the end.
timed ddp_first "${DDP[@]}" teacher --out "$WORK/ddp" --epochs "$EPOCHS" --stop-after $((EPOCHS / 2)) "${COMMON[@]}"
timed ddp_resume "${DDP[@]}" teacher --out "$WORK/ddp" --epochs "$EPOCHS" "${COMMON[@]}"
timed ddp_student "${DDP[@]}" student --out "$WORK/ddp_student" --teacher "$WORK/ddp/best.pt" --epochs 2 "${COMMON[@]}"

python - "$WORK" "$GPUS" <<'EOF'
import json, sys
from pathlib import Path
work, gpus = Path(sys.argv[1]), int(sys.argv[2])
seconds = {p.stem: (lambda a, b: b - a)(*map(float, p.read_text().split())) for p in work.glob("*.seconds")}
history = {name: json.loads((work / name / "history.json").read_text()) for name in ("single", "ddp", "ddp_student")}
ddp_seconds = seconds["ddp_first"] + seconds["ddp_resume"]
result = {"gpus": gpus, "seconds": seconds, "teacher_speedup": seconds["single"] / ddp_seconds,
          "resumed": [line for line in (work / "ddp_resume.log").read_text().splitlines() if "resumed from" in line],
          "final": {name: {k: v for k, v in h[-1].items() if k.startswith(("val_", "epoch"))}
                    for name, h in history.items()}}
(work / "ddp_check.json").write_text(json.dumps(result, indent=1))
print(json.dumps(result, indent=1))
EOF
