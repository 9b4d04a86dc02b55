#!/usr/bin/env python3
"""Student inference time on a GPU with PyTorch (the robot runs ONNX on its CPU: benchmarks/latency.py).

Times, at batch 1 and from a uint8 mask on the host to the outputs back on the host:
- streaming, per frame: one frame encoding plus the temporal head over the 25-frame window of
  embeddings (the streaming student's steady state; earlier embeddings are kept on the GPU);
- streaming and UniFormer-style, per instance: the whole 25-frame clip in one forward pass
  (what the paper's 3.83 ms on an RTX 4090 measures);
and throughput in instances per second for batches of whole clips.

Weights are random unless --checkpoint is given: the time of these fixed-shape networks does
not depend on their values. Needs torch and warp (imported by ad_sim.materials), not ROS or
onnxruntime; --checkpoint also needs mcap:

  PYTHONPATH=.:ros_ws/src/ad_sim:ros_ws/src/ad_estimator python benchmarks/gpu_inference.py --json out.json
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "ros_ws" / "src" / "ad_sim"), str(ROOT / "ros_ws" / "src" / "ad_estimator")]

from ad_estimator.cli import count, positive, torch_device  # noqa: E402
from common import falling_disc_clips, json_out, percentiles  # noqa: E402  (benchmarks/, the script's folder)
from training.models.student import FRAME_COUNT, build_student, frame_encoder_input, student_preset  # noqa: E402
from training.models.teacher import TEACHER_PRESETS  # noqa: E402


def timed(step, iterations: int, warmup: int, device: torch.device) -> list[float]:
    """Wall time of `step()` from the host's point of view (synchronised after each call)."""
    def synchronise():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(warmup):
        step()
    synchronise()
    out = []
    for _ in range(iterations):
        start = time.perf_counter()
        step()
        synchronise()
        out.append(time.perf_counter() - start)
    return out


def to_device(masks: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.from_numpy(masks).to(device).float().mul_(1.0 / 255.0)


def outputs_to_host(out: dict) -> None:
    for key in ("logits", "params", "params_logvar"):
        out[key].cpu()


def measure(model: torch.nn.Module, weights: str, preset: str | None, args, device: torch.device) -> dict:
    """The figures of one model; `preset` is its size preset (a checkpoint's own, or --size)."""
    print(f"timing {model.config.kind} ({weights}) on {device}: {args.iterations} calls per figure after "
          f"{args.warmup} warm-up calls", file=sys.stderr)  # on a CPU the defaults take a long time
    size = tuple(model.config.input_size)
    if size[0] != size[1]:
        raise ValueError(f"input size {size}: the synthetic clips are square")
    clips = falling_disc_clips(args.batch, size[0])
    valid = torch.ones(1, FRAME_COUNT, device=device)
    result = {"weights": weights, "size": preset, "input_size": list(size),
              "parameters": sum(p.numel() for p in model.parameters())}
    with torch.inference_mode(), torch.autocast(device.type, torch.bfloat16, enabled=args.amp):
        result["per_instance"] = percentiles(timed(
            lambda: outputs_to_host(model(to_device(clips[:1], device), valid)), args.iterations, args.warmup, device))
        if model.config.kind == "streaming":
            # Steady state: the window's embeddings stay on the GPU; a new frame is encoded and the
            # temporal head reads the last 25.
            frames = frame_encoder_input(model.config, to_device(clips[:1], device), valid)[0]  # (25, C, H, W)
            window = model.frame_encoder(frames).unsqueeze(0)
            frame = frames[-1:].mul(255.0).to(torch.uint8).cpu().numpy()  # a host mask, as a camera gives it

            def step():
                nonlocal window
                embedding = model.frame_encoder(to_device(frame, device))
                window = torch.cat([window[:, 1:], embedding[:, None]], dim=1)
                outputs_to_host(model.temporal(window, valid))

            result["per_frame"] = percentiles(timed(step, args.iterations, args.warmup, device))
        batch_valid = torch.ones(args.batch, FRAME_COUNT, device=device)
        seconds = timed(lambda: outputs_to_host(model(to_device(clips, device), batch_valid)),
                        max(5, args.iterations // 20), 3, device)
        result["throughput"] = {"batch": args.batch, "instances_per_s": args.batch / float(np.median(seconds))}
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                     epilog="On a CPU, lower --iterations, --warmup and --batch: the defaults are "
                                            "sized for a GPU (hours on a CPU).")
    parser.add_argument("--kinds", nargs="+", choices=["streaming", "uniformer"], default=["streaming", "uniformer"],
                        help="students to time")
    parser.add_argument("--size", choices=["tiny", "small", "paper"], default="paper",
                        help="model preset of the random-weight models")
    parser.add_argument("--checkpoint", type=Path, default=None, help="a student checkpoint to time instead of random weights")
    parser.add_argument("--device", type=torch_device, default="cuda", help="torch device: cuda, cuda:<index> or cpu")
    parser.add_argument("--iterations", type=positive, default=500, help="timed calls per figure")
    parser.add_argument("--warmup", type=count, default=50, help="untimed calls before each figure")
    parser.add_argument("--batch", type=positive, default=64, help="clips per batch for the throughput figure")
    parser.add_argument("--amp", action="store_true", help="bfloat16 autocast")
    parser.add_argument("--json", type=json_out, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("no CUDA device here; pass --device cpu to try the script on a CPU")
    trained = {}
    if args.checkpoint:
        from training.train_student import load_student  # needs mcap (training data); random weights do not
        try:
            model, meta = load_student(args.checkpoint, device)
        except (OSError, ValueError) as exc:
            parser.error(f"--checkpoint: {exc}")
        trained[meta["kind"]] = model, meta.get("size")
    torch.backends.cudnn.benchmark = True
    result = {}
    for kind in args.kinds:
        if kind in trained:
            model, preset = trained[kind]
            result[kind] = measure(model, str(args.checkpoint), preset, args, device)
        else:
            model = build_student(student_preset(kind, args.size, TEACHER_PRESETS[args.size].z_dim))
            result[kind] = measure(model.to(device).eval(), "random", args.size, args, device)
    cpu = platform.processor() or platform.machine()  # processor() is empty on Linux
    result["setup"] = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu,
                       "torch": torch.__version__, "size": args.size, "amp": args.amp, "iterations": args.iterations}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
