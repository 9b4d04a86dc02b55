"""Re-simulation PSNR of an exported student on bags (issue 6 part 3, SPEC 8).

For every complete episode of the bags: the model's estimate from its camera-0 frames (through
ad_estimator.evaluate, i.e. the node's own preprocessing), then the predicted family and
parameters re-simulated on the episode's geometry and initial state (ad_sim.resimulate, all
episodes in one batched call) and compared with the recorded masks. Also home of the bag reading
that the per-scene baseline shares (observed videos + Instances from /ad_sim/instance).
"""
from __future__ import annotations

import argparse
import logging
import math
import time
from pathlib import Path

import numpy as np

from ad_estimator.cli import count, seed, write_text_staged
from ad_estimator.metrics import json_text
from ad_sim.instances import Instance
from ad_sim.materials import FAMILIES, FRAME_COUNT, SAMPLED_PARAMETERS, full_parameters
from ad_sim.mpm import check_device
from ad_sim.resimulate import PSNR_CAP, candidate_from_row, resimulation_psnr
from training.data import EpisodeRejected, episode_video

log = logging.getLogger(__name__)

FIT_VIEW = 0  # evaluation convention: one camera per instance, the first
MASK_TOPIC = f"/ad_sim/view_{FIT_VIEW}/mask"


def bag_episodes(bags: str | Path):
    """(bag, SimInstance message, [(stamp_ns, Image)] in stamp order) of every episode under `bags`
    that has all FRAME_COUNT camera-0 frames; others are skipped with a warning. Truncated bags (a
    killed recorder) are read up to their last complete chunk, as everywhere in training."""
    from ad_estimator.evaluate import episode_frames, find_bags

    for bag in find_bags([Path(bags)]):
        for msg, frames in episode_frames(bag, MASK_TOPIC, recover=True):
            if len(frames) != FRAME_COUNT:
                log.warning("%s: episode %s has %d of %d frames; skipped", bag, msg.episode_id, len(frames),
                            FRAME_COUNT)
                continue
            if any(stamp is None for stamp, _ in frames):
                log.warning("%s: episode %s has a frame with a malformed stamp; skipped", bag, msg.episode_id)
                continue
            yield bag, msg, sorted(frames, key=lambda f: f[0])


def selected_episodes(bags: str | Path, count: int = 0, seed: int = 0) -> list[tuple]:
    """(bag, SimInstance message, frames, (T, H, W) uint8 masks) of the complete episodes, or of a
    seeded random subset of `count` of them (see `select`). Only the chosen episodes are decoded;
    one with an unusable frame is skipped with a warning (the subset is then smaller)."""
    episodes = list(bag_episodes(bags))
    if not episodes:
        raise ValueError(f"no complete episode with {MASK_TOPIC} frames in the bags under {bags}")
    chosen = []
    for i in select(count, len(episodes), seed):
        bag, msg, frames = episodes[i]
        try:
            chosen.append((bag, msg, frames, episode_video(bag, msg.episode_id, MASK_TOPIC, frames)))
        except EpisodeRejected as exc:
            log.warning("%s; episode skipped", exc)
    if not chosen:
        raise ValueError(f"no usable episode with {MASK_TOPIC} frames in the bags under {bags} (see the warnings)")
    return chosen


def instance_of(msg) -> Instance:
    """The Instance of a SimInstance message (its ground truth, one view)."""
    family = msg.material
    sampled = {n: float(v) for n, v in zip(msg.parameter_names, msg.parameters) if n in SAMPLED_PARAMETERS[family]}
    return Instance(msg.episode_id, msg.split, msg.shape, family, full_parameters(family, sampled), int(msg.seed))


def observed_from_bags(bags: str | Path, count: int = 0, seed: int = 0) -> tuple[list[Instance], np.ndarray]:
    """Instances (ground truth) and recorded camera-0 videos (N, 25, H, W) of the complete episodes,
    or of a seeded random subset of `count` of them (see `selected_episodes`)."""
    episodes = selected_episodes(bags, count, seed)
    return [instance_of(msg) for _, msg, _, _ in episodes], np.stack([video for *_, video in episodes])


def select(count: int, total: int, seed: int) -> np.ndarray:
    """Indices of a seeded random subset of `count` of `total` items, in order (all if count <= 0)."""
    if count <= 0 or count >= total:
        return np.arange(total)
    return np.sort(np.random.default_rng(seed).choice(total, size=count, replace=False))


def psnr_summary(families: list[str], psnr: np.ndarray) -> dict:
    """Mean, median, per-family mean (by true family) and exact reproductions of per-instance PSNRs."""
    per_family = {}
    for family in FAMILIES:
        rows = [k for k, f in enumerate(families) if f == family]
        per_family[family] = float(psnr[rows].mean()) if rows else math.nan
    return {"mean": float(psnr.mean()), "median": float(np.median(psnr)), "families": per_family,
            "exact": int((psnr == PSNR_CAP).sum())}  # masks reproduced to the pixel


def format_psnr(summary: dict, n: int) -> str:
    families = ", ".join(f"{f} {'n/a' if math.isnan(v) else f'{v:.2f}'}" for f, v in summary["families"].items())
    return (f"re-simulation PSNR: mean {summary['mean']:.2f} dB, median {summary['median']:.2f} dB, "
            f"{summary['exact']} of {n} reproduced to the pixel; per true family mean {families}")


def model_psnr(model_path: str | Path, bags: str | Path, device: str = "cpu", count: int = 0, seed: int = 0,
               progress: bool = True) -> dict:
    """Metrics and per-episode re-simulation PSNR of a student's estimates on (a subset of) the bags."""
    from ad_estimator import metrics
    from ad_estimator.evaluate import check_scorable, predict_episode, to_metrics
    from ad_estimator.model import EstimatorModel

    model = EstimatorModel.load(model_path)
    check_scorable(model)  # as evaluate does: FAMILIES[c] below reads the classes in that order
    episodes = selected_episodes(bags, count, seed)
    # The frames converted as the model reads them (a coverage model keeps grey levels); the PSNR
    # compares binary masks, as re-simulation renders them.
    estimates = [predict_episode(model, bag, msg, frames, model.info.frame_count) for bag, msg, frames, _ in episodes]
    predictions = to_metrics(estimates, model.info.parameter_names)
    instances = [instance_of(msg) for _, msg, _, _ in episodes]
    candidates = [candidate_from_row(FAMILIES[c], row)
                  for c, row in zip(predictions.pred_class, predictions.pred_params)]
    start = time.perf_counter()
    psnr = resimulation_psnr(instances, candidates, device, FIT_VIEW,
                             observed=np.stack([video for *_, video in episodes]), progress=progress)
    return {
        "model": str(model_path), "model_id": model.model_id, "bags": str(bags), "device": device,
        "metrics": metrics.compute_metrics(predictions),
        "psnr": psnr_summary([inst.material for inst in instances], psnr),
        "resimulation_seconds": time.perf_counter() - start,
        "episodes": [{"episode_id": inst.episode_id, "true_material": inst.material, "material": family,
                      "parameters": params, "psnr": float(p)}
                     for inst, (family, params), p in zip(instances, candidates, psnr)],
    }


def check_json_out(out: Path) -> None:
    """--out can be written as a JSON file, checked before any work (creating nothing): an --out that is a
    folder or cannot be written otherwise fails only after the whole re-simulation or CMA-ES."""
    from ad_estimator.evaluate import check_out

    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; pass a .json file name, e.g. {out / 'result.json'}")
    check_out(out, file="a .json file")


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training resim-psnr")
    p.description = ("Re-simulation PSNR (SPEC 8) of an exported student: its estimate (family + parameters) of each "
                     "bag episode is re-simulated on the episode's geometry and initial state and its camera-0 masks "
                     "compared with the recorded ones. Writes a JSON with the metrics table and per-episode PSNR.")
    p.add_argument("--model", required=True, help="exported student .onnx (for streaming: the temporal head file)")
    p.add_argument("--bags", required=True, help="evaluation bags (a bag folder or a folder of bags)")
    p.add_argument("--instances", type=count, default=0, help="a seeded random subset of this many episodes (0: all)")
    p.add_argument("--seed", type=seed, default=0, help="seeds the subset")
    p.add_argument("--device", default="cpu", help="Warp device for the re-simulation: cpu, cuda, cuda:N")
    p.add_argument("--out", help="output JSON (default runs/resim_psnr/<model id>-<bags name>.json)")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args) -> dict:
    from ad_estimator.metrics import format_table

    check_device(args.device)
    # Before the work, not when writing its result; without --out, the default's folder (its file name
    # holds the model's id, known once the model loads).
    check_json_out(Path(args.out or f"runs/resim_psnr/<model id>-{Path(args.bags).name}.json"))
    result = model_psnr(args.model, args.bags, args.device, args.instances, args.seed, not args.no_progress)
    out = Path(args.out or f"runs/resim_psnr/{result['model_id']}-{Path(args.bags).name}.json")
    write_text_staged(out, json_text(result))  # strict JSON: NaN (no instance of a family) becomes null
    print(format_table({str(FRAME_COUNT): result["metrics"]}, f"{result['model_id']} on {args.bags}"))
    print(format_psnr(result["psnr"], len(result["episodes"])))
    print(f"wrote {out}")
    return result
