"""The episode pipeline: instances -> particles -> MPM -> tracked states and rendered masks.

No ROS here. simulate_batch() samples and poses each instance's particles, picks the 1024
tracked particles by farthest point sampling, binds the mesh vertices to particles, runs the
batched MPM solver (scenes grouped by substep count), advects the vertices and renders every
(instance, view, frame) mask in shared rasteriser launches. Deterministic on CPU given the seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import mpm, shapes
from .instances import PARTICLE_SPACING, SCALE, Instance
from .materials import FRAME_COUNT
from .render import (
    DOWNSAMPLE,
    FULL_SIZE,
    TRACKED_PARTICLES,
    Binding,
    Camera,
    RenderJob,
    advect_vertices,
    bind_vertices,
    farthest_point_sampling_batch,
    render_masks,
)

# Scenes per solver launch: on a GPU ~256 scenes grouped by substeps is the solver's sweet spot
# (docs/simulator.md); on CPU large batches only waste the iterations of scenes that need fewer
# substeps than the stiffest one.
MAX_BATCH = {"cpu": 16, "cuda": 256}


@dataclass
class Episode:
    """One simulated episode (docs/architecture.md)."""

    instance: Instance
    positions: np.ndarray  # (25, 1024, 3) float32, tracked particles
    deformation: np.ndarray  # (25, 1024, 3, 3) float32, F of tracked particles (row-major)
    masks: np.ndarray  # (V, 25, 128, 128) uint8 in {0, 255}, or 0..255 area coverage if asked for
    masks_full: np.ndarray | None  # (V, 25, 512, 512) uint8 in {0, 255}, only if asked for
    cameras: list[Camera]  # per view, at the 128x128 mask resolution
    substeps_per_frame: int
    particle_count: int


@dataclass
class _Prepared:
    """An instance turned into a solver scene plus what is needed to read its results."""

    scene: mpm.Scene  # record is set by _track()
    binding: Binding  # vertex binding; onto rows of the recorded set after _track()
    fps_start: int  # first particle of farthest point sampling
    faces: np.ndarray  # (M, 3) mesh triangles
    cameras: list[Camera]
    tracked: np.ndarray | None = None  # (1024,) rows of the recorded set, in FPS order


def sample_particles(instance: Instance) -> tuple[np.ndarray, float]:
    """World positions (N, 3) of the instance's posed particles (N >= 1024) and their spacing.

    Thin shapes get a finer lattice than PARTICLE_SPACING, so that farthest point sampling
    has TRACKED_PARTICLES to choose from.
    """
    rng = np.random.Generator(np.random.PCG64(instance.sampling_seed))
    local = shapes.sample_volume(instance.shape, PARTICLE_SPACING, SCALE, rng, min_count=TRACKED_PARTICLES)
    spacing = shapes.effective_spacing(instance.shape, PARTICLE_SPACING, SCALE, TRACKED_PARTICLES)
    pose = instance.pose()
    return local @ pose[:3, :3].T + pose[:3, 3], spacing


def _prepare(instance: Instance, views: int | None) -> _Prepared:
    particles, spacing = sample_particles(instance)
    pose = instance.pose()
    mesh = shapes.load_mesh(instance.shape)
    vertices = SCALE * np.asarray(mesh.vertices) @ pose[:3, :3].T + pose[:3, 3]
    scene = mpm.Scene(
        positions=particles.astype(np.float32),
        velocity=np.array(instance.velocity, dtype=np.float32),
        family=instance.material,
        parameters=instance.parameters,
        particle_volume=spacing**3,
    )
    # A second stream of the sampling seed, independent of the draws sample_volume made.
    start = int(np.random.Generator(np.random.PCG64([instance.sampling_seed, 1])).integers(len(particles)))
    return _Prepared(
        scene=scene,
        binding=bind_vertices(vertices, particles),
        fps_start=start,
        faces=np.asarray(mesh.faces),
        cameras=instance.cameras(views),
    )


def _track(members: list[_Prepared], device: str) -> None:
    """Farthest point sampling of a group in shared launches; records tracked + bound particles."""
    picks = farthest_point_sampling_batch(
        [p.scene.positions for p in members], TRACKED_PARTICLES, [p.fps_start for p in members], device
    )
    for p, fps in zip(members, picks):
        record = np.union1d(fps, p.binding.indices.ravel())
        p.scene.record = record
        p.tracked = np.searchsorted(record, fps)
        p.binding = p.binding.reindexed(record)


def _render(prepared: list[_Prepared], vertices: list[np.ndarray], full: bool, coverage: bool, device: str):
    """Masks of every view and frame of a group of instances, in shared launches."""
    vertex_sets, jobs = [], []
    for i, (p, v) in enumerate(zip(prepared, vertices)):
        first = len(vertex_sets)
        vertex_sets.extend(v)  # one vertex set per frame
        for camera in p.cameras:
            projection = camera.resized(FULL_SIZE, FULL_SIZE).projection()
            jobs.extend(RenderJob(first + t, i, projection) for t in range(len(v)))
    masks, masks_full = render_masks(vertex_sets, [p.faces for p in prepared], jobs, FULL_SIZE, DOWNSAMPLE, full, device,
                                     coverage)
    out, start = [], 0
    for p, v in zip(prepared, vertices):
        shape = (len(p.cameras), len(v))
        count = shape[0] * shape[1]
        out.append(
            (
                masks[start : start + count].reshape(shape + masks.shape[1:]),
                None if masks_full is None else masks_full[start : start + count].reshape(shape + masks_full.shape[1:]),
            )
        )
        start += count
    return out


def simulate_batch(
    instances: list[Instance],
    device: str = "cpu",
    full_masks: bool = False,
    progress: bool = False,
    views: int | None = None,
    max_batch: int | None = None,
    frame_count: int = FRAME_COUNT,
    coverage_masks: bool = False,
    cancelled=None,
) -> list[Episode]:
    """Simulates and renders the instances; returns their episodes in the same order.

    views overrides each instance's number of views; max_batch bounds scenes per solver launch
    (default MAX_BATCH of the device kind); frame_count < 25 is for quick checks only;
    coverage_masks keeps each mask pixel's area coverage (render.downsample) instead of 0/255;
    cancelled (a callable) ends the work early with mpm.Cancelled (mpm.simulate).
    """
    if max_batch is None:
        max_batch = MAX_BATCH["cuda" if str(device).startswith("cuda") else "cpu"]
    indices = range(len(instances))
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="prepare instances", unit="instance", disable=None)  # terminal only
    prepared = [_prepare(instances[i], views) for i in indices]
    groups = mpm.group_by_substeps([p.scene for p in prepared], max_batch)
    if progress:
        groups = tqdm(groups, desc="simulate + render", unit="batch", disable=None)
    episodes: list[Episode | None] = [None] * len(instances)
    for group in groups:
        members = [prepared[i] for i in group]
        _track(members, device)
        results = mpm.simulate([p.scene for p in members], device=device, frame_count=frame_count, cancelled=cancelled)
        vertices = [advect_vertices(p.binding, r.positions, r.deformation) for p, r in zip(members, results)]
        rendered = _render(members, vertices, full_masks, coverage_masks, device)
        for i, p, r, (masks, masks_full) in zip(group, members, results, rendered):
            episodes[i] = Episode(
                instance=instances[i],
                positions=np.ascontiguousarray(r.positions[:, p.tracked]),
                deformation=np.ascontiguousarray(r.deformation[:, p.tracked]),
                masks=masks,
                masks_full=masks_full,
                cameras=p.cameras,
                substeps_per_frame=r.substeps_per_frame,
                particle_count=len(p.scene.positions),
            )
    return episodes
