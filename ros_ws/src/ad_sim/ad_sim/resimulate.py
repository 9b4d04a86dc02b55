"""Re-simulation of predicted materials and the re-simulation PSNR (SPEC section 8).

No ROS, no torch. A candidate is a (family, SI parameters) pair. Re-simulating it for an
instance means simulating the instance's geometry and initial state (pose, drop, velocity,
particles: all drawn from (shape, seed) only, see ad_sim.instances.Instance) with the
candidate's material instead, and rendering the same camera(s). Many candidates are simulated
in ONE ad_sim.episode.simulate_batch call, which batches them into shared solver launches.

PSNR = 10 log10(1 / MSE), MSE over every pixel of every frame of one view's mask video, masks
scaled to [0, 1]. Identical videos (MSE = 0) score PSNR_CAP (a finite number keeps means finite);
one differing pixel in a 25 x 128 x 128 video already gives 56 dB, so the cap is never reached
otherwise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from .episode import simulate_batch
from .instances import Instance
from .materials import FAMILY_RANGES, FIXED_PARAMETERS, FRAME_COUNT, PARAMETER_NAMES, SAMPLED_PARAMETERS, full_parameters
from .render import MASK_SIZE

#: PSNR (dB) of two identical mask videos.
PSNR_CAP = 100.0

Candidate = tuple[str, Mapping[str, float]]  # (family, SI parameters, radians for friction_angle)


def clip_to_family_range(family: str, parameters: Mapping[str, float]) -> dict[str, float]:
    """The family's full parameter set with each sampled parameter clipped into its sampling range
    and each fixed one (sand's E and nu) at its fixed value, whatever value was given for it.

    The simulator's stability (and its substep count, i.e. cost) is validated over the sampling
    ranges (docs/simulator.md); a model may predict slightly outside them, and a family's law is
    only defined with its fixed values (a full row of predictions also holds E and nu for sand).
    """
    given = {name: value for name, value in parameters.items() if name not in FIXED_PARAMETERS.get(family, {})}
    out = full_parameters(family, given)
    for name in SAMPLED_PARAMETERS[family]:
        low, high, _ = FAMILY_RANGES[family][name]
        out[name] = float(min(max(out[name], low), high))
    return out


def candidate_from_row(family: str, row: Sequence[float]) -> Candidate:
    """(family, parameters) from a (4,) SI row in PARAMETER_NAMES order (metrics.Predictions layout)."""
    return family, {name: float(row[PARAMETER_NAMES.index(name)]) for name in SAMPLED_PARAMETERS[family]}


def with_material(instance: Instance, family: str, parameters: Mapping[str, float]) -> Instance:
    """A copy of the instance made of another material; same geometry, initial state and cameras.

    dataclasses.replace re-runs __post_init__, which draws pose, velocity and camera and sampling
    seeds from the unchanged seed, so the copy starts exactly where the original does.
    """
    return dataclasses.replace(instance, material=family, parameters=clip_to_family_range(family, parameters))


def resimulate(
    instances: Sequence[Instance],
    candidates: Sequence[Candidate],
    device: str = "cpu",
    view: int = 0,
    frame_count: int = FRAME_COUNT,
    progress: bool = False,
) -> np.ndarray:
    """Masks (N, T, 128, 128) uint8 {0, 255} of camera `view` for candidate i simulated on instance i.

    All N scenes go through one simulate_batch call (grouped by substeps into solver launches).
    An instance may appear many times (e.g. one per CMA-ES candidate).
    """
    if len(instances) != len(candidates):
        raise ValueError(f"need one candidate per instance, got {len(candidates)} for {len(instances)} instances")
    if view < 0:
        raise ValueError(f"view must be >= 0, got {view}")
    if not instances:
        return np.zeros((0, frame_count, MASK_SIZE, MASK_SIZE), dtype=np.uint8)
    copies = [with_material(inst, family, params) for inst, (family, params) in zip(instances, candidates)]
    # The first k cameras of an instance do not depend on how many are asked for.
    episodes = simulate_batch(copies, device=device, views=view + 1, frame_count=frame_count, progress=progress)
    return np.stack([episode.masks[view] for episode in episodes])


def mask_mse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean squared error over the last three axes (frames, height, width) of mask videos.

    uint8 masks are read as 0/255 and scaled to [0, 1]; float masks must already be in [0, 1].
    """
    a, b = _unit(a), _unit(b)
    if a.shape[-3:] != b.shape[-3:]:
        raise ValueError(f"mask videos differ in shape: {a.shape} vs {b.shape}")
    return np.mean((a - b) ** 2, axis=(-3, -2, -1))


def psnr_from_mse(mse):
    """10 log10(1 / MSE), PSNR_CAP where MSE is 0; float for a scalar, array otherwise."""
    mse = np.asarray(mse, dtype=np.float64)
    with np.errstate(divide="ignore"):
        out = np.minimum(10.0 * np.log10(1.0 / mse), PSNR_CAP)
    return float(out) if out.ndim == 0 else out


def mask_psnr(a: np.ndarray, b: np.ndarray):
    """PSNR (dB) of mask video(s) a against b over (frames, height, width); see psnr_from_mse."""
    return psnr_from_mse(mask_mse(a, b))


def _unit(masks: np.ndarray) -> np.ndarray:
    masks = np.asarray(masks)
    if masks.dtype == np.uint8:
        return masks.astype(np.float32) / 255.0
    masks = masks.astype(np.float32)
    if masks.size and (masks.min() < 0.0 or masks.max() > 1.0):
        raise ValueError("float mask videos must lie in [0, 1] (uint8 masks are read as 0/255)")
    return masks


def resimulation_psnr(
    instances: Sequence[Instance],
    predictions: Sequence[Candidate],
    device: str = "cpu",
    view: int = 0,
    observed: np.ndarray | None = None,
    progress: bool = False,
) -> np.ndarray:
    """Per-instance PSNR (dB) of the re-simulated prediction against the observed mask video.

    observed: (N, T, H, W) masks of camera `view` (e.g. read from the bag), T = FRAME_COUNT; None
    simulates the ground truth (instance.material, instance.parameters) in the same batch as the
    predictions.
    """
    if len(instances) != len(predictions):
        raise ValueError(f"need one prediction per instance, got {len(predictions)} for {len(instances)} instances")
    if observed is None:
        truth = [(inst.material, inst.parameters) for inst in instances]
        masks = resimulate(list(instances) * 2, truth + list(predictions), device, view, progress=progress)
        observed, predicted = masks[: len(instances)], masks[len(instances) :]
    else:
        if len(observed) != len(instances):
            raise ValueError(f"need one observed video per instance, got {len(observed)} for {len(instances)}")
        frame_count = np.shape(observed)[1]
        predicted = resimulate(instances, predictions, device, view, frame_count=frame_count, progress=progress)
    return np.atleast_1d(mask_psnr(predicted, observed))

