#!/usr/bin/env python3
"""MPM simulation throughput: particle-steps/s and instances/s of the batched Warp solver.

Scenes are a representative mix (never run in CI):
  paper: box / ball / cylinder / ellipsoid, randomly rotated, about the shape library's size
         (about 3k to 11k particles at spacing dx/2), dropped 0.05-0.25 above the
         ground with a small random velocity; family uniform, parameters sampled per family.
  small: the same mix at half the linear size (about 8x fewer particles), for quick CPU checks.
--episodes times ad_sim.episode.simulate_batch on real benchmark instances instead (shapes,
tracking, MPM and mask rendering together).

Examples:
  python benchmarks/sim_throughput.py --config paper --device cpu --batch 4
  python benchmarks/sim_throughput.py --config paper --device cuda --batch 512 --instances 1024
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "ros_ws" / "src" / pkg) for pkg in ("ad_sim", "ad_estimator")]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # common, also when a test imports this file by path

import warp as wp  # noqa: E402
from ad_estimator.cli import count, positive  # noqa: E402
from common import check_warp_device, json_out, quiet_warp  # noqa: E402

quiet_warp()

from ad_sim import materials, mpm  # noqa: E402

# Edge of the shape's bounding cube: a little under the shape library's longest side (instances.SCALE,
# 0.4), with about as many particles as its objects; the README's figures were measured with these.
SHAPE_SIZE = {"paper": 0.35, "small": 0.175}
SPACING = 0.5 * mpm.DX


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 2] *= -1
    return q


def make_scene(rng: np.random.Generator, size: float) -> mpm.Scene:
    """One random scene of the representative mix."""
    h = size / 2
    axis = np.arange(-h + SPACING / 2, h, SPACING)
    pts = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    kind = rng.integers(4)
    if kind == 1:  # ball
        pts = pts[np.linalg.norm(pts, axis=1) <= h]
    elif kind == 2:  # cylinder
        pts = pts[np.linalg.norm(pts[:, :2], axis=1) <= h]
    elif kind == 3:  # flat ellipsoid
        pts = pts[np.linalg.norm(pts / np.array([h, h, 0.4 * h]), axis=1) <= 1.0]
    pts = pts @ _random_rotation(rng).T
    lo_z = mpm.BOUNDARY_CELLS * mpm.DX + rng.uniform(0.05, 0.25)
    centre = np.array([0.5 + rng.uniform(-0.1, 0.1), 0.5 + rng.uniform(-0.1, 0.1), lo_z - pts[:, 2].min()])
    pts = np.clip(pts + centre, mpm.CLAMP_LO, mpm.CLAMP_HI)
    family = materials.FAMILIES[rng.integers(3)]
    velocity = np.array([*rng.uniform(-0.2, 0.2, 2), -rng.uniform(0.0, 0.5)], dtype=np.float32)
    return mpm.Scene(
        positions=pts.astype(np.float32),
        velocity=velocity,
        family=family,
        parameters=materials.sample_parameters(family, rng),
        particle_volume=SPACING**3,
        record=np.arange(0, len(pts), max(1, len(pts) // 1024))[:1024],
    )


def bench_scenes(args) -> dict:
    rng = np.random.default_rng(args.seed)
    scenes = [make_scene(rng, SHAPE_SIZE[args.config]) for _ in range(args.instances)]
    groups = mpm.group_by_substeps(scenes, args.batch) if args.group else [
        list(range(i, min(i + args.batch, len(scenes)))) for i in range(0, len(scenes), args.batch)
    ]
    # Warm-up: compile kernels on this device outside the timed region.
    mpm.simulate(scenes[:1], device=args.device, frame_count=2)
    if args.profile:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    useful = wasted = 0
    unstable = {f: 0 for f in materials.FAMILIES}
    j_range = [np.inf, -np.inf]
    elapsed = 0.0
    for group in groups:
        batch = [scenes[i] for i in group]
        t0 = time.perf_counter()
        results = mpm.simulate(batch, device=args.device, frame_count=args.frames, progress=args.progress)
        elapsed += time.perf_counter() - t0
        iterations = max(r.substeps_per_frame for r in results)
        for sc, r in zip(batch, results):
            useful += len(sc.positions) * r.substeps_per_frame * (args.frames - 1)
            wasted += len(sc.positions) * (iterations - r.substeps_per_frame) * (args.frames - 1)
            J = np.linalg.det(r.deformation.astype(np.float64))
            finite = np.isfinite(J).all() and np.isfinite(r.all_velocities_final).all()
            if finite:
                j_range = [min(j_range[0], J.min()), max(j_range[1], J.max())]
            # Stability screen: blown-up elements or runaway speeds.
            if not finite or J.min() < 0.05 or J.max() > 20.0 or np.abs(r.all_velocities_final).max() > 20.0:
                unstable[sc.family] += 1
    kernel_seconds = {}
    if args.profile:
        for r in wp.timing_end():
            kernel_seconds[r.name] = kernel_seconds.get(r.name, 0.0) + r.elapsed / 1000.0
    counts = np.array([len(s.positions) for s in scenes])
    subs = np.array([mpm.scene_substeps(s, materials.FRAME_INTERVAL) for s in scenes])
    return {
        "mode": "mpm",
        "config": args.config,
        "device": str(wp.get_device(args.device)),
        "instances": len(scenes),
        "batch": args.batch,
        "grouped": args.group,
        "frames": args.frames,
        "particles_mean": float(counts.mean()),
        "particles_range": [int(counts.min()), int(counts.max())],
        "substeps_mean": float(subs.mean()),
        "substeps_range": [int(subs.min()), int(subs.max())],
        "seconds": elapsed,
        "instances_per_s": len(scenes) / elapsed,
        "particle_steps_per_s": useful / elapsed,
        "idle_fraction": wasted / max(1, useful + wasted),
        "courant": mpm.COURANT,
        "unstable_instances": unstable,
        "recorded_J_range": [float(j) for j in j_range],
        "block_dim": mpm.BLOCK_DIM,
        **({"kernel_seconds": {k: round(v, 3) for k, v in sorted(kernel_seconds.items())}} if args.profile else {}),
    }


def bench_episodes(args) -> dict:
    from ad_sim import episode, instances

    split = instances.benchmark(args.config, "train", base_seed=args.seed)
    picks = np.random.default_rng(args.seed).choice(len(split), min(args.instances, len(split)), replace=False)
    chosen = [split[i] for i in sorted(picks)]  # a random, seeded sample over shapes and families
    episode.simulate_batch(chosen[:1], device=args.device, frame_count=2)  # warm-up / compile
    t0 = time.perf_counter()
    episodes = episode.simulate_batch(chosen, device=args.device, max_batch=args.batch, progress=args.progress)
    wp.synchronize()
    elapsed = time.perf_counter() - t0
    return {
        "mode": "episodes",
        "config": args.config,
        "device": str(wp.get_device(args.device)),
        "instances": len(episodes),
        "batch": args.batch,
        "particles_mean": float(np.mean([e.particle_count for e in episodes])),
        "seconds": elapsed,
        "instances_per_s": len(episodes) / elapsed,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", choices=sorted(SHAPE_SIZE), default="paper", help="instance mix (default paper)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0 ... (default cpu)")
    parser.add_argument("--batch", type=positive, default=8, help="scenes per solver launch (default 8)")
    parser.add_argument("--instances", type=positive, default=None, help="instances to simulate (default: one batch)")
    parser.add_argument("--frames", type=int, default=materials.FRAME_COUNT,
                        help="frames per instance in MPM mode (default 25; --episodes always simulates 25)")
    parser.add_argument("--seed", type=count, default=0, help="random seed of the mix (default 0)")
    parser.add_argument("--no-group", dest="group", action="store_false", help="batch in order, not by substeps")
    parser.add_argument("--episodes", action="store_true", help="time episode.simulate_batch (MPM + rendering)")
    parser.add_argument("--progress", action="store_true", help="tqdm progress bars")
    parser.add_argument("--profile", action="store_true", help="CUDA: time each kernel (wp.timing_begin)")
    parser.add_argument("--block-dim", type=positive, default=None, help="override mpm.BLOCK_DIM (CUDA tuning)")
    parser.add_argument("--json", type=json_out, default=None, help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be >= 2")
    args.instances = args.instances or args.batch
    if args.block_dim:
        mpm.BLOCK_DIM = args.block_dim
    check_warp_device(parser, args.device)
    if args.profile and not wp.get_device(args.device).is_cuda:  # wp.timing_* records CUDA activity only
        parser.error(f"--profile times each CUDA kernel; Warp records no kernel timings on {args.device}, so give "
                     "--device cuda (or leave out --profile)")
    figures = bench_episodes(args) if args.episodes else bench_scenes(args)
    for key, value in figures.items():
        print(f"{key:>22}: {value:.4g}" if isinstance(value, float) else f"{key:>22}: {value}")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
