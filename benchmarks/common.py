"""Shared by the benchmark scripts: synthetic input clips, the summary of timed samples, the options
that pick the unseen instances a benchmark simulates, and argument checks that refuse a bad count,
output path, model or Warp device before any work (a run can take hours)."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ad_estimator.cli import count, positive

FRAME_COUNT = 25


def falling_disc_clips(count: int, size: int = 128) -> np.ndarray:
    """(count, 25, size, size) uint8 masks of a disc that falls and squashes, in 4 variants that
    differ in position (what a mask contains does not change a fixed-shape network's time)."""
    k = size / 128.0  # the shapes are drawn for 128 px and scaled
    yy, xx = np.mgrid[0:size, 0:size]
    variants = np.zeros((4, FRAME_COUNT, size, size), np.uint8)
    for e in range(4):
        for t in range(FRAME_COUNT):
            cy = min(25 * k + 0.5 * 9.8 * (t * 0.025) ** 2 * size * 3, size - 22 * k)
            disc = ((xx - (50 + 8 * e) * k) / (20.0 * k)) ** 2 + ((yy - cy) / ((20.0 - 0.2 * t) * k)) ** 2 <= 1
            variants[e, t][disc] = 255
    return variants[np.arange(count) % 4]


def percentiles(seconds) -> dict:
    """Samples in seconds -> n, p50/p95/p99, mean and max in milliseconds."""
    a = np.asarray(seconds, float) * 1e3
    if not len(a):
        return {"n": 0}
    return {"n": int(len(a)), "p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)),
            "p99_ms": float(np.percentile(a, 99)), "mean_ms": float(a.mean()), "max_ms": float(a.max())}


def output_file(text: str, example: str = "figures.json") -> Path:
    """An output file whose folder exists (argparse.ArgumentTypeError otherwise), checked before the run rather
    than after it; `example` is the file name the message suggests for a folder."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder; give a file name, e.g. {path / example}")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"the folder {path.parent} does not exist")
    return path


def json_out(text: str) -> Path:
    """argparse type of --json: a file whose folder exists, checked before the run rather than after it."""
    return output_file(text, "figures.json")


def quiet_warp() -> None:
    """No Warp start-up banner or kernel-load lines: they would mix into the tables on stdout."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING


def check_warp_device(parser: argparse.ArgumentParser, device: str) -> None:
    """parser.error (one line, exit 2) for a Warp device this machine lacks, before any simulation."""
    from ad_sim import mpm

    try:
        mpm.check_device(device)
    except ValueError as exc:
        parser.error(str(exc))


def load_model(parser: argparse.ArgumentParser, path: Path, **options):
    """EstimatorModel.load(path, **options), or parser.error (one line, exit 2) naming what is wrong with it."""
    from ad_estimator.model import EstimatorModel, ModelError

    try:
        return EstimatorModel.load(path, **options)
    except ModelError as exc:
        parser.error(str(exc))


def add_unseen_draw_options(parser: argparse.ArgumentParser) -> None:
    """--instances, --size, --seed (the draw of ad_sim.instances.drawn_per_family) and --json."""
    parser.add_argument("--instances", type=positive, default=4, help="unseen instances per family")
    parser.add_argument("--size", default="paper", choices=("tiny", "small", "paper"),
                        help="benchmark the instances are drawn from")
    parser.add_argument("--seed", type=count, default=0, help="which instances are drawn")
    parser.add_argument("--json", type=json_out, help="also write the figures here")
