"""Episodes made with numpy (no simulation) for the bag and message tests, and small helpers."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ad_sim.instances import quaternion_matrix
from ad_sim.render import intrinsics, look_at


def fabricated_episode(seed: int, views: int = 1, frames: int = 25, material: str = "plasticine") -> SimpleNamespace:
    """An object with Episode's fields (docs/architecture.md) holding random but valid data."""
    rng = np.random.default_rng(seed)
    orientation = rng.normal(size=4)
    orientation /= np.linalg.norm(orientation)
    parameters = {
        "jelly": {"youngs_modulus": 2e5, "poissons_ratio": 0.3},
        "plasticine": {"youngs_modulus": 1e5, "poissons_ratio": 0.4, "yield_stress": 3e3},
        "sand": {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.5},
    }[material]
    position = rng.uniform(0.3, 0.7, size=3)
    instance = SimpleNamespace(
        episode_id=f"unseen-sphere-{material}-{seed:04d}",
        split="unseen",
        shape="sphere",
        material=material,
        parameters=parameters,
        seed=seed,
        views=views,
        orientation=tuple(orientation),
        velocity=tuple(rng.normal(size=3)),
        position=lambda: position,
        rotation=lambda: quaternion_matrix(orientation),
    )
    cameras = []
    for _ in range(views):
        eye = np.array([0.5, 0.5, 0.3]) + rng.uniform(1.0, 2.0) * np.append(rng.normal(size=2), 0.5)
        cameras.append(SimpleNamespace(K=intrinsics(128, 128, 0.3), width=128, height=128, pose=look_at(eye, [0.5, 0.5, 0.3])))
    return SimpleNamespace(
        instance=instance,
        positions=rng.random((frames, 1024, 3), dtype=np.float32),
        deformation=rng.normal(size=(frames, 1024, 3, 3)).astype(np.float32),
        masks=(rng.random((views, frames, 128, 128)) > 0.7).astype(np.uint8) * 255,
        masks_full=None,
        cameras=cameras,
        substeps_per_frame=int(rng.integers(10, 100)),
        particle_count=int(rng.integers(3000, 9000)),
    )


def grey_masks(masks: np.ndarray, shift: tuple[int, int] = (1, 2)) -> np.ndarray:
    """0/255 masks (..., 128, 128) -> grey masks as generate --coverage-masks makes them: each pixel
    becomes its 4x4 block of the 512x512 render, the render is moved by `shift` render pixels (so
    that edges cut blocks) and area-downsampled with coverage (ad_sim.render.downsample)."""
    from ad_sim.render import DOWNSAMPLE, downsample

    size = masks.shape[-1]
    full = np.kron(masks.reshape(-1, size, size), np.ones((1, DOWNSAMPLE, DOWNSAMPLE), np.uint8))
    return downsample(np.roll(full, shift, axis=(1, 2)), coverage=True).reshape(masks.shape)


def thresholded(masks: np.ndarray) -> np.ndarray:
    """What every thresholding consumer (mask_threshold 127) reads of grey masks."""
    return np.where(masks > 127, 255, 0).astype(np.uint8)


def write_coverage_bag(folder, episodes: int, views: int = 1, seed: int = 0, binary: bool = False):
    """training.synthetic's bag (particles, ground truth, masks) with grey masks (grey_masks of its
    own); `binary`: the same bag with those masks thresholded. Returns the folder and the episodes."""
    from ad_sim.generate import write_episodes
    from ad_sim.rosbag import BagWriter
    from training.synthetic import synthetic_episode

    written = [synthetic_episode(i, seed, views) for i in range(episodes)]
    for episode in written:
        episode.masks = grey_masks(episode.masks)
        if binary:
            episode.masks = thresholded(episode.masks)
    writer = BagWriter(folder)
    write_episodes(writer, written, 0)
    writer.close()
    return Path(folder), written


def _is_field(name: str) -> bool:
    """Message fields are lower case; constants (rosbags keeps them as fields) are upper case."""
    return not name.startswith("__") and not name.isupper()


def as_plain(value):
    """Decoded message (mcap_ros2 / rosbags objects) or dict -> nested plain Python values."""
    if isinstance(value, dict):
        return {k: as_plain(v) for k, v in value.items()}
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, np.ndarray):
        return bytes(value) if value.dtype == np.uint8 else [as_plain(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [as_plain(v) for v in value]
    if hasattr(value, "__slots__"):
        return {k: as_plain(getattr(value, k)) for k in value.__slots__ if _is_field(k) and not k.startswith("_")}
    if dataclasses.is_dataclass(value):
        return {f.name: as_plain(getattr(value, f.name)) for f in dataclasses.fields(value) if _is_field(f.name)}
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, np.generic):
        return value.item()
    return value
