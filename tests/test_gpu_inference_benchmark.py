"""benchmarks/gpu_inference.py runs end to end (on the CPU here) and reports every figure it
promises; the figures themselves are measured on the GPU machine, not asserted here."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from training.engine import save_checkpoint
from training.models.student import build_student, student_preset
from training.models.teacher import TEACHER_PRESETS

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "gpu_inference.py"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=240)


def test_reports_per_frame_per_instance_and_throughput(tmp_path):
    out = tmp_path / "figures.json"
    result = run("--device", "cpu", "--size", "tiny", "--iterations", "3", "--warmup", "1", "--batch", "2",
                 "--json", str(out))
    assert result.returncode == 0, result.stderr
    figures = json.loads(out.read_text())
    assert figures == json.loads(result.stdout)
    for kind in ("streaming", "uniformer"):
        assert figures[kind]["weights"] == "random"
        assert figures[kind]["per_instance"]["n"] == 3 and figures[kind]["per_instance"]["p50_ms"] > 0
        assert figures[kind]["throughput"]["batch"] == 2 and figures[kind]["throughput"]["instances_per_s"] > 0
    assert figures["streaming"]["per_frame"]["p99_ms"] >= figures["streaming"]["per_frame"]["p50_ms"] > 0
    assert "per_frame" not in figures["uniformer"]  # a clip model has no per-frame step
    assert figures["setup"]["size"] == figures["streaming"]["size"] == "tiny"
    assert "timing streaming (random) on cpu: 3 calls per figure after 1 warm-up calls" in result.stderr


@pytest.mark.parametrize("previous_frames", [0, 1, 3])
def test_times_a_trained_checkpoint_when_given(tmp_path, previous_frames):
    config = student_preset("streaming", "tiny", TEACHER_PRESETS["tiny"].z_dim)
    # The bundled model's encoder has 4 inputs (3 earlier frames); the frame encoder's input grows with them.
    config = dataclasses.replace(config, previous_frames=previous_frames)
    model = build_student(config)
    checkpoint = tmp_path / "student.pt"
    save_checkpoint(checkpoint, {"model": model.state_dict(), "epoch": 1,
                                 "meta": {"config": config.to_dict(), "kind": "streaming", "size": "tiny"}})
    result = run("--device", "cpu", "--kinds", "streaming", "--checkpoint", str(checkpoint), "--iterations", "2",
                 "--warmup", "0", "--batch", "2")  # no warm-up is allowed (cheap CPU runs)
    assert result.returncode == 0, result.stderr
    figures = json.loads(result.stdout)
    assert figures["streaming"]["weights"] == str(checkpoint)
    assert figures["streaming"]["parameters"] == sum(p.numel() for p in model.parameters())
    assert figures["streaming"]["per_frame"]["p50_ms"] > 0
    assert figures["streaming"]["size"] == "tiny"  # the checkpoint's preset, not --size's default
    assert figures["setup"]["device"]  # platform.processor() alone is empty on Linux


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_asking_for_cuda_without_a_gpu_is_a_clear_error():
    result = run("--iterations", "1")
    assert result.returncode == 2
    assert "no CUDA device" in result.stderr and "--device cpu" in result.stderr
