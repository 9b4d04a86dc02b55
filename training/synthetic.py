"""Synthetic bags for tests and smoke runs: fast, deterministic episodes whose motion depends on
the material family and parameters, written through ad_sim's own bag writer and message code
(ad_sim.generate.write_episodes), so they have exactly the layout of generated bags.

Not physics: a ball of particles falls, hits the ground and then bounces (jelly, higher for
stiffer), flattens (plasticine, more for lower yield stress) or spreads (sand, more for lower
friction angle). Masks are orthographic silhouettes from the side.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ad_sim.generate import write_episodes
from ad_sim.materials import FAMILIES, FRAME_COUNT, FRAME_INTERVAL, normalise, sample_parameters
from ad_sim.rosbag import BagWriter

PARTICLES = 1024
IMAGE = 128


def _motion(material: str, params: dict, rng: np.random.Generator):
    """Per frame: centre height, vertical scale, horizontal scale of the blob."""
    t = np.arange(FRAME_COUNT) * FRAME_INTERVAL
    drop = rng.uniform(0.05, 0.2)
    z0 = 0.12 + drop
    z = np.maximum(z0 - 0.5 * 9.8 * t ** 2, 0.12)
    impact = int(np.argmax(z <= 0.12)) if (z <= 0.12).any() else FRAME_COUNT
    after = np.clip(np.arange(FRAME_COUNT) - impact, 0, None) * FRAME_INTERVAL
    if material == "jelly":
        stiff = normalise("youngs_modulus", params["youngs_modulus"])
        z = z + (after > 0) * 0.1 * stiff * np.abs(np.sin(after * 12.0))
        squash = 1.0 - 0.3 * (1.0 - stiff) * np.exp(-after * 8.0) * (after > 0)
        spread = 1.0 / np.sqrt(squash)
    elif material == "plasticine":
        soft = 1.0 - normalise("yield_stress", params["yield_stress"])
        squash = 1.0 - 0.6 * soft * (1.0 - np.exp(-after * 10.0))
        spread = 1.0 / np.sqrt(squash)
    else:
        loose = 1.0 - normalise("friction_angle", params["friction_angle"])
        squash = 1.0 - 0.7 * (0.3 + 0.7 * loose) * (1.0 - np.exp(-after * 6.0))
        spread = 1.0 + 1.5 * (0.3 + 0.7 * loose) * (1.0 - np.exp(-after * 6.0))
    return z, squash, spread


def synthetic_episode(index: int, seed: int, views: int, split: str = "train"):
    """An Episode-like object (the attributes ad_sim.messages reads)."""
    rng = np.random.default_rng([seed, index])
    material = FAMILIES[index % len(FAMILIES)]
    params = sample_parameters(material, rng)
    ball = rng.normal(size=(PARTICLES, 3))
    ball *= (rng.uniform(size=(PARTICLES, 1)) ** (1 / 3)) / np.linalg.norm(ball, axis=1, keepdims=True)
    radius, centre_xy = 0.1, 0.5 + rng.uniform(-0.1, 0.1, size=2)
    z, squash, spread = _motion(material, params, rng)
    positions = np.empty((FRAME_COUNT, PARTICLES, 3), np.float32)
    deformation = np.zeros((FRAME_COUNT, PARTICLES, 3, 3), np.float32)
    masks = np.zeros((views, FRAME_COUNT, IMAGE, IMAGE), np.uint8)
    for t in range(FRAME_COUNT):
        positions[t, :, :2] = centre_xy + radius * spread[t] * ball[:, :2]
        positions[t, :, 2] = z[t] + radius * squash[t] * ball[:, 2]
        deformation[t] = np.diag([spread[t], spread[t], squash[t]])
        for v in range(views):
            horizontal = positions[t, :, v % 2]
            cols = np.clip((horizontal * IMAGE).astype(int), 0, IMAGE - 1)
            rows = np.clip(((1.0 - positions[t, :, 2]) * IMAGE).astype(int), 0, IMAGE - 1)
            masks[v, t, rows, cols] = 255
    camera = SimpleNamespace(K=np.array([[IMAGE, 0, IMAGE / 2], [0, IMAGE, IMAGE / 2], [0, 0, 1.0]]), width=IMAGE,
                             height=IMAGE, pose=np.eye(4))
    instance = SimpleNamespace(
        episode_id=f"{split}-synthetic-{material}-{index:04d}", split=split, shape="synthetic", material=material,
        parameters=params, seed=int(seed * 1000 + index), velocity=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0),
        position=lambda: np.array([*centre_xy, z[0]]))
    return SimpleNamespace(instance=instance, positions=positions, deformation=deformation, masks=masks,
                           cameras=[camera] * views, substeps_per_frame=1, particle_count=PARTICLES)


def write_synthetic_bag(folder: str | Path, episodes: int, views: int = 2, seed: int = 0,
                        split: str = "train", first: int = 0, custom_data: dict | None = None) -> Path:
    """Writes `episodes` synthetic episodes (indices first, first+1, ...) as one bag folder (`custom_data` in
    its metadata.yaml, e.g. generate's)."""
    with BagWriter(folder, custom_data=custom_data) as writer:
        write_episodes(writer, [synthetic_episode(first + i, seed, views, split) for i in range(episodes)], 0)
    return Path(folder)
