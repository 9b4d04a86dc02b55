#!/usr/bin/env python3
"""Does the estimator answer the same from a camera of another resolution, shape or framing?

Training sees the simulator's 128x128 masks: 512x512 renders, area-downsampled and thresholded
at half coverage (ad_sim.render.downsample). A robot's segmentation arrives at its camera's own
resolution, and the estimator brings it to the model's input size (EstimatorModel.prepare). This
simulates unseen benchmark instances once, keeps both the 128x128 masks and the 512x512 renders
they came from, estimates each instance from the 128x128 masks, the 512x512 renders, a 4:3 crop of
them, two framings with the object larger and smaller than in training, and the renders with their
boundary moved out or in by 2 px (a biased segmenter), and the simulator's masks with frames lost,
through the estimator's runtime. It reports the paper table for each camera and how close its estimates are to
those from the simulator's masks. A model of grey masks (ad.mask_levels coverage) gets the simulator's grey
masks (generate --coverage-masks) for the 128x128 reference and the lost-frame cameras, as it was trained on
them; the full-resolution cameras stay binary, as a segmenter's masks are, and the estimator takes their area
coverage.

    python benchmarks/camera_resolution.py --instances 4              # CPU, about 20 s
    python benchmarks/camera_resolution.py --instances 100 --device cuda --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for pkg in ("ad_sim", "ad_estimator"):
    sys.path.insert(0, str(ROOT / "ros_ws" / "src" / pkg))
sys.path.insert(0, str(ROOT / "benchmarks"))  # common, also when a test imports this file by path

from ad_estimator.cli import HelpFormatter  # noqa: E402
from ad_estimator.evaluate import predict_episode, to_metrics  # noqa: E402
from ad_estimator.metrics import (Predictions, compute_metrics, json_text, markdown_table, regl1,  # noqa: E402
                                  table_cell, table_labels, table_values)
from ad_estimator.model import BUNDLED_MODEL  # noqa: E402
from ad_sim.episode import simulate_batch  # noqa: E402
from ad_sim.messages import instance_message  # noqa: E402
from ad_sim.instances import drawn_per_family  # noqa: E402
from ad_sim.materials import FRAME_INTERVAL  # noqa: E402
from common import add_unseen_draw_options, check_warp_device, load_model, quiet_warp  # noqa: E402


CROP = 64  # rows cut from the top and from the bottom of the 512x512 render for the 4:3 camera
ZOOM_IN = 64  # pixels cut from each side of the render: 384/512, the object 1.33x larger (factor 3: exact)
ZOOM_OUT = 64  # pixels of background added on each side: 512/640, the object 0.8x the size


def morphed(masks: np.ndarray, operation) -> np.ndarray:
    """Each frame dilated or eroded (cv2.dilate, cv2.erode) by a disc of radius 2 px."""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    return np.stack([operation(frame, disc) for frame in masks])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter,
                                epilog="About 20 s on the CPU with --instances 4; the figures in docs/estimator.md "
                                       "are --instances 20 (about 2 minutes).")
    add_unseen_draw_options(p)
    p.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="exported student (.onnx)")
    p.add_argument("--device", default="cpu", help="warp device for the simulation: cpu or cuda")
    args = p.parse_args(argv)
    quiet_warp()
    check_warp_device(p, args.device)
    model = load_model(p, args.model)
    chosen = drawn_per_family(args.size, "unseen", args.instances, args.seed)
    print(f"simulating {len(chosen)} episodes on {args.device}", file=sys.stderr)
    # The 128x128 masks as the model was trained on them: 0/255, or each pixel's area coverage of the
    # render for a model of grey masks (the render itself stays binary: the full-resolution cameras).
    coverage = model.info.mask_levels == "coverage"
    episodes = simulate_batch(chosen, device=args.device, full_masks=True, views=1, progress=True,
                              coverage_masks=coverage)

    # Each camera's masks of an episode (view 0). The 4:3 camera is the 512x512 render without its top
    # and bottom 64 rows: what a 640x480-style sensor with the same horizontal view would see.
    # The last two frame the object larger and smaller than training did (about 38 px of 128): the
    # central 384x384 of the render, and the render on a 640x640 background.
    cameras = {"128x128 (simulator)": lambda ep: ep.masks[0],
               "512x512 camera": lambda ep: ep.masks_full[0],
               "512x384 camera (4:3)": lambda ep: ep.masks_full[0][:, CROP:-CROP],
               "object 1.33x larger": lambda ep: ep.masks_full[0][:, ZOOM_IN:-ZOOM_IN, ZOOM_IN:-ZOOM_IN],
               "object 0.8x smaller": lambda ep: np.pad(ep.masks_full[0], ((0, 0), (ZOOM_OUT,) * 2, (ZOOM_OUT,) * 2)),
               # A segmenter whose boundary is biased outwards or inwards by 2 render pixels (half a mask pixel).
               "mask grown by 2 px of 512": lambda ep: morphed(ep.masks_full[0], cv2.dilate),
               "mask shrunk by 2 px of 512": lambda ep: morphed(ep.masks_full[0], cv2.erode)}
    # Frames lost on the way (best-effort QoS on a busy link), from the simulator's masks: each
    # camera's frames kept, per episode. The window fills a lost frame's slot with a neighbour within
    # slot_tolerance (default 1.0), else leaves it empty.
    count = model.info.frame_count
    lossy = {"every 4th frame lost": lambda i: [k for k in range(count) if k % 4 != 3],
             "10% of frames lost at random": lambda i: [  # never the first: it starts the episode
                 k for k, u in enumerate(np.random.default_rng([args.seed, i]).random(count)) if k == 0 or u >= 0.1]}
    for camera in lossy:
        cameras[camera] = cameras["128x128 (simulator)"]
    stamps = [(round(k * FRAME_INTERVAL * 1e9), None) for k in range(count)]

    truths = [SimpleNamespace(**instance_message(ep, i, 0)) for i, ep in enumerate(episodes)]

    def estimate(camera: str, i: int, ep):
        kept = lossy[camera](i) if camera in lossy else range(count)
        frames = cameras[camera](ep)
        return predict_episode(model, camera, truths[i], [stamps[k] for k in kept], len(kept),
                               masks=[frames[k] for k in kept])

    by_camera = {camera: to_metrics([estimate(camera, i, ep) for i, ep in enumerate(episodes)],
                                    model.info.parameter_names) for camera in cameras}
    # Object pixels a cropped camera does not see: where its estimates may rightly differ.
    def missed(camera: str) -> float:
        return float(np.mean([1 - (cameras[camera](ep) > 0).sum() / max((ep.masks_full[0] > 0).sum(), 1)
                              for ep in episodes]))

    outside = {camera: missed(camera) for camera in ("512x384 camera (4:3)", "object 1.33x larger")}

    simulator = by_camera["128x128 (simulator)"]
    results = {camera: compute_metrics(pred) for camera, pred in by_camera.items()}
    # Against the simulator's masks: how often the family agrees, and how far apart the estimates are in
    # RegL1's units (the camera's estimate scored against the simulator-mask one).
    against = {camera: {"same_family": float(np.mean(pred.pred_class == simulator.pred_class)),
                        "regl1_between_estimates": float(np.nanmean(regl1(Predictions(
                            simulator.true_class, simulator.pred_params, pred.probabilities, pred.pred_params))))}
               for camera, pred in by_camera.items() if pred is not simulator}
    print(f"\n{model.model_id} on {len(chosen)} {args.size} unseen instances, {model.info.frame_count} frames "
          "(parameter errors over correctly classified clips; E, yield: log-MAE; nu: MAE; phi: MAE in degrees)\n")
    print("\n".join(markdown_table(["camera", *table_labels()], [[camera, *map(table_cell, table_values(m))]
                                                                  for camera, m in results.items()])))
    print("\nAgainst the estimates from the simulator's masks:\n")
    print("\n".join(markdown_table(["camera", "same family", "RegL1 between the estimates"],
                                    [[camera, f"{a['same_family']:.3f}", f"{a['regl1_between_estimates']:.3f}"]
                                     for camera, a in against.items()])))
    print("\nObject pixels out of view (mean over episodes): "
          + "; ".join(f"{camera}: {100 * share:.2f}%" for camera, share in outside.items()))
    if args.json:
        setup = {"instances_per_family": args.instances, "size": args.size, "seed": args.seed, "device": args.device,
                 "model_id": model.model_id, "mask_levels": model.info.mask_levels,
                 "episodes": [i.episode_id for i in chosen]}
        args.json.write_text(json_text({"results": results, "against_simulator_masks": against,
                                        "object_pixels_out_of_view": outside, "setup": setup}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
