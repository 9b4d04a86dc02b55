#!/usr/bin/env python3
"""Does the estimator answer the same from a camera of higher resolution?

Training sees the simulator's 128x128 masks: 512x512 renders, area-downsampled and thresholded
at half coverage (ad_sim.render.downsample). A robot's segmentation arrives at its camera's own
resolution, and the estimator brings it to the model's input size (EstimatorModel.prepare). This
simulates unseen benchmark instances once, keeps both the 128x128 masks and the 512x512 renders
they came from, estimates each instance from both through the estimator's runtime, and reports
the paper table for each and how often the two estimates agree.

    python benchmarks/camera_resolution.py --instances 4              # CPU, about a minute
    python benchmarks/camera_resolution.py --instances 100 --device cuda --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for pkg in ("ad_sim", "ad_estimator"):
    sys.path.insert(0, str(ROOT / "ros_ws" / "src" / pkg))

from ad_estimator.cli import HelpFormatter  # noqa: E402
from ad_estimator.evaluate import predict_episode, to_metrics  # noqa: E402
from ad_estimator.metrics import (Predictions, compute_metrics, json_text, markdown_table, regl1,  # noqa: E402
                                  table_cell, table_labels, table_values)
from ad_estimator.model import BUNDLED_MODEL, EstimatorModel  # noqa: E402
from ad_sim.episode import simulate_batch  # noqa: E402
from ad_sim.instances import benchmark  # noqa: E402
from ad_sim.materials import FAMILIES, FRAME_INTERVAL  # noqa: E402


def as_message(instance):
    """The fields of ad_msgs/SimInstance that the estimator's evaluation reads."""
    return SimpleNamespace(episode_id=instance.episode_id, material=instance.material,
                           parameter_names=list(instance.parameters), parameters=list(instance.parameters.values()))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--instances", type=int, default=4, help="unseen instances per family")
    p.add_argument("--size", default="paper", choices=("tiny", "small", "paper"),
                   help="benchmark the instances are drawn from")
    p.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="exported student (.onnx)")
    p.add_argument("--device", default="cpu", help="warp device for the simulation: cpu or cuda")
    p.add_argument("--seed", type=int, default=0, help="which instances are drawn")
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args(argv)
    if args.instances < 1:
        p.error("--instances must be at least 1")

    model = EstimatorModel.load(args.model)
    rng = np.random.default_rng(args.seed)
    pool = benchmark(args.size, "unseen")
    chosen = []
    for family in FAMILIES:
        of_family = [inst for inst in pool if inst.material == family]
        chosen += [of_family[i] for i in sorted(rng.choice(len(of_family), min(args.instances, len(of_family)),
                                                           replace=False))]
    print(f"simulating {len(chosen)} episodes on {args.device}", file=sys.stderr)
    episodes = simulate_batch(chosen, device=args.device, full_masks=True, views=1, progress=True)

    stamps = [(round(k * FRAME_INTERVAL * 1e9), None) for k in range(model.info.frame_count)]
    by_camera = {}
    for camera, field in (("128x128 (simulator)", "masks"), ("512x512 camera", "masks_full")):
        estimates = [predict_episode(model, camera, as_message(inst), stamps, len(stamps),
                                     masks=list(getattr(ep, field)[0])) for inst, ep in zip(chosen, episodes)]
        by_camera[camera] = to_metrics(estimates, model.info.parameter_names)

    low, high = by_camera.values()
    agree = float(np.mean(low.pred_class == high.pred_class))
    # How far apart the two estimates are, in RegL1's units: the 512 estimate scored against the 128 one.
    apart = regl1(Predictions(low.true_class, low.pred_params, high.probabilities, high.pred_params))
    results = {camera: compute_metrics(pred) for camera, pred in by_camera.items()}
    print(f"\n{model.model_id} on {len(chosen)} {args.size} unseen instances, {model.info.frame_count} frames "
          "(parameter errors over correctly classified clips; E, yield: log-MAE; nu: MAE; phi: MAE in degrees)\n")
    print("\n".join(markdown_table(["camera", *table_labels()], [[camera, *map(table_cell, table_values(m))]
                                                                  for camera, m in results.items()])))
    print(f"\nSame family from both cameras: {agree:.3f}; mean RegL1 distance between the two estimates: "
          f"{float(np.nanmean(apart)):.3f}")
    if args.json:
        setup = {"instances_per_family": args.instances, "size": args.size, "seed": args.seed, "device": args.device,
                 "model_id": model.model_id, "episodes": [i.episode_id for i in chosen]}
        args.json.write_text(json_text({"results": results, "same_family": agree,
                                        "regl1_between_estimates": float(np.nanmean(apart)), "setup": setup}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
