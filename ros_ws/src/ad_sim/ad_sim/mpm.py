"""Batched explicit MLS-MPM (APIC transfers, quadratic B-splines) in Warp, CPU and CUDA.

Many scenes advance in the same kernel launches: particles of all scenes are concatenated with a
particle -> scene index (and sorted spatially within each scene), every scene owns one 32^3 grid
(flat arrays of S * 32^3 nodes) and its own material constants and time step. Each scene takes
n_s = scene_substeps(...) substeps per frame; the solver loops max(n_s) times per frame and a scene
whose n_s is exhausted sits the remaining iterations out, so every scene lands exactly on the frame
times. On CUDA, P2G accumulates in shared memory (p2g_tiled). See docs/simulator.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import warp as wp

from ad_sim.materials import (
    DENSITY,
    FAMILY_CODES,
    FRAME_COUNT,
    FRAME_INTERVAL,
    GRAVITY,
    GRID_RESOLUTION,
    drucker_prager_alpha,
    full_parameters,
    kirchhoff_svd,
    lame,
    project_sigma,
    projected,
    svd,
)

DX = 1.0 / GRID_RESOLUTION
BOUNDARY_CELLS = 3  # grid nodes within this many cells of a face carry the boundary conditions
COURANT = 0.5  # dt = COURANT * dx / (wave speed + bound on material speed)
GROUND_FRICTION = 0.5  # Coulomb coefficient between material and ground (bottom boundary layer)
# Default bound on material speed (free fall through the whole unit cube) when a scene's own bound
# (scene_speed_bound) is not known; added to the elastic wave speed so soft materials also take
# small enough steps while falling.
FALL_SPEED = math.sqrt(2.0 * GRAVITY * 1.0)
GROUND_Z = BOUNDARY_CELLS * DX  # top of the ground boundary layer
# Particles are kept inside [CLAMP_LO, CLAMP_HI]^3 so that their 3x3x3 stencil stays on the grid.
CLAMP_LO = 2.0 * DX
CLAMP_HI = 1.0 - 2.0 * DX

# Grids are flat arrays of S * 32^3 nodes, node (s, i, j, k) at s * 32^3 + (i * 32 + j) * 32 + k:
# multi-dimensional launches are an order of magnitude slower per thread on Warp's CPU backend.
NODES = GRID_RESOLUTION**3
_GRID = wp.constant(GRID_RESOLUTION)
_NODES = wp.constant(NODES)
_INV_DX = wp.constant(float(GRID_RESOLUTION))
_DX = wp.constant(DX)
# -O3: ~2x faster SVD-heavy kernels on CPU than the default -O2; no adjoints: the solver is never
# differentiated, and skipping them halves compile time.
wp.set_module_options({"optimization_level": 3, "enable_backward": False})
BLOCK_DIM = 256  # CUDA threads per block of the particle kernels (tuning knob, see benchmarks/)

# Shared-memory P2G (CUDA): a block of TILE_BLOCK spatially sorted particles of one scene adds its
# transfers into a PATCH^3-node patch in shared memory, then flushes the patch to the global grid,
# replacing ~27 x 4 global float atomics per particle by a few per node. Particles whose stencil
# leaves the patch (or that belong to another scene than the block's first) use global atomics.
PATCH = 10
TILE_BLOCK = 256
PATCH_SLOTS = -(-(PATCH**3) // TILE_BLOCK) * TILE_BLOCK  # patch nodes padded to whole flush rounds
_PATCH = wp.constant(PATCH)
_PATCH_SLOTS = wp.constant(PATCH_SLOTS)
_TILE_BLOCK = wp.constant(TILE_BLOCK)
_FAR = wp.constant(1 << 20)
_BOUND = wp.constant(BOUNDARY_CELLS)
_GROUND_FRICTION = wp.constant(GROUND_FRICTION)
_CLAMP_LO = wp.constant(CLAMP_LO)
_CLAMP_HI = wp.constant(CLAMP_HI)


class Cancelled(Exception):
    """simulate() was asked to stop (its `cancelled` callable returned True)."""


@dataclass
class Scene:
    """One object to simulate.

    positions: (N, 3) float32 particle positions in world coordinates inside the unit cube (z up).
    velocity: (3,) initial velocity of every particle (m/s), or (N, 3) per particle.
    family: one of materials.FAMILIES; parameters: SI values (radians for friction_angle), fixed
    ones (sand's E, nu) may be omitted. particle_volume: m^3 per particle.
    record: particle indices whose position and F are recorded each frame (None: all).
    """

    positions: np.ndarray
    velocity: np.ndarray
    family: str
    parameters: dict
    particle_volume: float
    record: np.ndarray | None = None
    density: float = DENSITY


@dataclass
class SceneResult:
    """Recorded trajectory of one scene: frame 0 is the initial state, T = frame_count."""

    positions: np.ndarray  # (T, R, 3) float32
    deformation: np.ndarray  # (T, R, 3, 3) float32, row-major F
    substeps_per_frame: int
    all_positions_final: np.ndarray  # (N, 3) float32
    all_velocities_final: np.ndarray = field(repr=False)  # (N, 3) float32


def _check_frame_interval(frame_interval: float) -> None:
    # dt = frame_interval / n_s: zero or a negative interval would run the scene backwards in time.
    if not (math.isfinite(frame_interval) and frame_interval > 0):
        raise ValueError(f"frame_interval must be a positive number of seconds, got {frame_interval!r}")


def substeps_for(
    family: str,
    parameters: dict,
    density: float = DENSITY,
    speed: float = FALL_SPEED,
    frame_interval: float = FRAME_INTERVAL,
) -> int:
    """Substeps per frame: n = ceil(frame_interval / dt), dt = COURANT * dx / (c + speed).

    c = sqrt((lambda + 2 mu) / rho) is the P-wave speed; `speed` bounds the material's speed
    (default: free fall through the whole domain; scene_substeps() uses the scene's own bound).
    """
    _check_frame_interval(frame_interval)
    p = full_parameters(family, parameters)
    mu, lam = lame(p["youngs_modulus"], p["poissons_ratio"])
    wave = math.sqrt((lam + 2.0 * mu) / density)
    dt = COURANT * DX / (wave + speed)
    return max(1, math.ceil(frame_interval / dt - 1e-9))


def group_by_substeps(scenes: list[Scene], max_batch: int, frame_interval: float = FRAME_INTERVAL) -> list[list[int]]:
    """Splits scene indices into batches of at most max_batch with similar substep counts.

    A batch costs max(n_s) iterations, so sorting by n_s before chunking wastes the fewest.
    Order within a batch and between batches follows increasing n_s (ties by index: deterministic).
    """
    if max_batch < 1:
        raise ValueError("max_batch must be >= 1")
    n = [scene_substeps(s, frame_interval) for s in scenes]
    order = sorted(range(len(scenes)), key=lambda i: (n[i], i))
    return [order[i : i + max_batch] for i in range(0, len(order), max_batch)]


def scene_speed_bound(scene: Scene, gravity: float = GRAVITY) -> float:
    """Energy bound on any particle's speed: |v|^2 <= |v0|^2 + 2 g (z0 - ground), largest over particles.

    Gravity is the only energy source (boundaries and plasticity only dissipate).
    """
    v0 = np.asarray(scene.velocity, dtype=np.float64).reshape(-1, 3)
    z0 = np.asarray(scene.positions, dtype=np.float64)[:, 2]
    drop = max(float(z0.max()) - GROUND_Z, 0.0)
    return math.sqrt(float((v0**2).sum(1).max()) + 2.0 * gravity * drop)


def scene_substeps(scene: Scene, frame_interval: float = FRAME_INTERVAL, gravity: float = GRAVITY) -> int:
    """substeps_for() of a scene with its own speed bound."""
    return substeps_for(scene.family, scene.parameters, scene.density, scene_speed_bound(scene, gravity), frame_interval)


@wp.func
def node_index(s: int, i: int, j: int, k: int):
    return s * _NODES + (i * _GRID + j) * _GRID + k


@wp.func
def stencil_base(xg: wp.vec3):
    """Lowest node of the 3x3x3 stencil of a particle at grid coordinates xg."""
    return wp.vec3i(int(xg[0] - 0.5), int(xg[1] - 0.5), int(xg[2] - 0.5))


@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights: row o = offset o (0, 1, 2) of the stencil, column = axis."""
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.mat33(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])


@wp.func
def stencil(x: wp.vec3):
    """A particle's stencil: lowest node, position relative to it (in cells) and B-spline weights."""
    xg = x * _INV_DX
    base = stencil_base(xg)
    fx = xg - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    return base, fx, bspline_weights(fx)


@wp.func
def stencil_node(w: wp.mat33, fx: wp.vec3, i: int, j: int, k: int):
    """Weight of stencil node (i, j, k) and its offset from the particle (metres)."""
    weight = w[i, 0] * w[j, 1] * w[k, 2]
    return weight, (wp.vec3(float(i), float(j), float(k)) - fx) * _DX


@wp.func
def mls_affine(dt: float, volume: float, stress: wp.mat33, m: float, C: wp.mat33):
    """The particle's affine momentum term. MLS-MPM: the stress force enters as an affine term,
    M_p^-1 = 4 / dx^2 for quadratic splines; APIC adds m C."""
    return (-dt * volume * 4.0 * _INV_DX * _INV_DX) * stress + m * C


@wp.kernel
def p2g(
    iteration: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    stress: wp.array(dtype=wp.mat33),
    scene: wp.array(dtype=wp.int32),
    substeps: wp.array(dtype=wp.int32),
    dt: wp.array(dtype=float),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
):
    p = wp.tid()
    s = scene[p]
    if iteration >= substeps[s]:
        return
    m = mass[s]
    affine = mls_affine(dt[s], volume[s], stress[p], m, C[p])
    mv = m * v[p]
    base, fx, w = stencil(x[p])
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight, dpos = stencil_node(w, fx, i, j, k)
                n = node_index(s, base[0] + i, base[1] + j, base[2] + k)
                wp.atomic_add(grid_mv, n, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, n, weight * m)


@wp.kernel
def p2g_tiled(
    iteration: int,
    total: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    stress: wp.array(dtype=wp.mat33),
    scene: wp.array(dtype=wp.int32),
    substeps: wp.array(dtype=wp.int32),
    dt: wp.array(dtype=float),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
):
    """p2g with a shared-memory patch per block (same sums as p2g up to float summation order)."""
    block, lane = wp.tid()
    first = block * _TILE_BLOCK
    last = wp.min(first + _TILE_BLOCK - 1, total - 1)
    s0 = scene[first]
    if s0 == scene[last] and iteration >= substeps[s0]:
        return  # block-uniform: the whole block is idle this iteration
    p = wp.min(first + lane, total - 1)
    s = scene[p]
    active = first + lane < total and iteration < substeps[s]
    m = mass[s]
    affine = mls_affine(dt[s], volume[s], stress[p], m, C[p])
    mv = m * v[p]
    base, fx, w = stencil(x[p])
    # Patch origin: smallest stencil base over the block's particles of scene s0.
    mine = active and s == s0
    ox = wp.tile_extract(wp.tile_min(wp.tile(wp.where(mine, base[0], _FAR))), 0)
    oy = wp.tile_extract(wp.tile_min(wp.tile(wp.where(mine, base[1], _FAR))), 0)
    oz = wp.tile_extract(wp.tile_min(wp.tile(wp.where(mine, base[2], _FAR))), 0)
    lx = base[0] - ox
    ly = base[1] - oy
    lz = base[2] - oz
    in_patch = mine and lx + 2 < _PATCH and ly + 2 < _PATCH and lz + 2 < _PATCH
    # One (momentum, mass) vec4 per node: one cooperative scatter per stencil node, not two.
    patch = wp.tile_zeros(shape=_PATCH_SLOTS, dtype=wp.vec4, storage="shared")
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight, dpos = stencil_node(w, fx, i, j, k)
                value = weight * (mv + affine * dpos)
                local = wp.where(in_patch, ((lx + i) * _PATCH + ly + j) * _PATCH + lz + k, 0)
                wp.tile_scatter_add(patch, local, wp.vec4(value[0], value[1], value[2], weight * m), in_patch)
                if active and not in_patch:
                    n = node_index(s, base[0] + i, base[1] + j, base[2] + k)
                    wp.atomic_add(grid_mv, n, value)
                    wp.atomic_add(grid_m, n, weight * m)
    for r in range(_PATCH_SLOTS // _TILE_BLOCK):
        local = r * _TILE_BLOCK + lane
        node = wp.tile_extract(patch, local)
        if node[3] > 0.0:  # padding slots and untouched nodes have no mass
            n = node_index(s0, ox + local / (_PATCH * _PATCH), oy + (local / _PATCH) % _PATCH, oz + local % _PATCH)
            wp.atomic_add(grid_mv, n, wp.vec3(node[0], node[1], node[2]))
            wp.atomic_add(grid_m, n, node[3])


@wp.kernel
def grid_update(
    iteration: int,
    substeps: wp.array(dtype=wp.int32),
    dt: wp.array(dtype=float),
    gravity: float,
    boundaries: int,
    grid_mv: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
    grid_v: wp.array(dtype=wp.vec3),
):
    """Momentum -> velocity, gravity, boundaries; also clears mass/momentum for the next P2G.

    Nodes without mass are neither read by G2P with a non-zero weight nor written here.
    """
    n = wp.tid()
    s = n / _NODES
    if iteration >= substeps[s]:
        return
    m = grid_m[n]
    if m <= 0.0:
        return
    vel = grid_mv[n] / m + wp.vec3(0.0, 0.0, -gravity * dt[s])
    grid_mv[n] = wp.vec3(0.0)
    grid_m[n] = 0.0
    i = (n / (_GRID * _GRID)) % _GRID
    j = (n / _GRID) % _GRID
    k = n % _GRID
    if boundaries != 0:
        vx = vel[0]
        vy = vel[1]
        vz = vel[2]
        # Walls and ceiling: free slip, separation allowed.
        if (i < _BOUND and vx < 0.0) or (i >= _GRID - _BOUND and vx > 0.0):
            vx = 0.0
        if (j < _BOUND and vy < 0.0) or (j >= _GRID - _BOUND and vy > 0.0):
            vy = 0.0
        if k >= _GRID - _BOUND and vz > 0.0:
            vz = 0.0
        # Ground: no penetration, Coulomb friction |dv_t| <= mu_g |v_n| on the tangential part.
        if k < _BOUND and vz < 0.0:
            vt = wp.sqrt(vx * vx + vy * vy)
            if vt > 0.0:
                scale = wp.max(vt + _GROUND_FRICTION * vz, 0.0) / vt
                vx = vx * scale
                vy = vy * scale
            vz = 0.0
        vel = wp.vec3(vx, vy, vz)
    grid_v[n] = vel


@wp.kernel
def g2p(
    iteration: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    stress: wp.array(dtype=wp.mat33),
    scene: wp.array(dtype=wp.int32),
    substeps: wp.array(dtype=wp.int32),
    dt: wp.array(dtype=float),
    family: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    yield_stress: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    grid_v: wp.array(dtype=wp.vec3),
):
    p = wp.tid()
    s = scene[p]
    if iteration >= substeps[s]:
        return
    h = dt[s]
    base, fx, w = stencil(x[p])
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight, dpos = stencil_node(w, fx, i, j, k)
                gv = grid_v[node_index(s, base[0] + i, base[1] + j, base[2] + k)]
                new_v += weight * gv
                new_C += (4.0 * _INV_DX * _INV_DX * weight) * wp.outer(gv, dpos)
    v[p] = new_v
    C[p] = new_C
    nx = x[p] + h * new_v
    lo, hi = _CLAMP_LO, _CLAMP_HI
    x[p] = wp.vec3(wp.clamp(nx[0], lo, hi), wp.clamp(nx[1], lo, hi), wp.clamp(nx[2], lo, hi))
    # Deformation update, plastic return mapping, then the stress the next P2G will use (one SVD).
    f_trial = (wp.identity(n=3, dtype=float) + h * new_C) * F[p]
    fam = family[s]
    U, sigma, V = svd(f_trial)
    sigma_new = project_sigma(fam, sigma, mu[s], lam[s], yield_stress[s], alpha[s])
    F[p] = projected(f_trial, U, sigma, sigma_new, V)
    stress[p] = kirchhoff_svd(fam, U, sigma_new, mu[s], lam[s])


@wp.kernel
def record_frame(
    frame: int,
    index: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    out_x: wp.array2d(dtype=wp.vec3),
    out_F: wp.array2d(dtype=wp.mat33),
):
    r = wp.tid()
    p = index[r]
    out_x[frame, r] = x[p]
    out_F[frame, r] = F[p]


def _validate(scene: Scene, number: int) -> np.ndarray:
    pos = np.asarray(scene.positions, dtype=np.float32)
    if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) == 0:
        raise ValueError(f"scene {number}: positions must be a non-empty (N, 3) array, got shape {pos.shape}")
    if not np.all(np.isfinite(pos)) or pos.min() < CLAMP_LO or pos.max() > CLAMP_HI:
        raise ValueError(
            f"scene {number}: positions must lie inside [{CLAMP_LO:.4f}, {CLAMP_HI:.4f}]^3 "
            f"(unit cube minus the boundary layer); got [{pos.min():.4f}, {pos.max():.4f}]. "
            "Scale/translate the shape into the domain above the ground."
        )
    # (NaN passes a plain "<= 0" test, and NaN or inf mass sends every particle into a corner.)
    if not all(math.isfinite(q) and q > 0 for q in (float(scene.particle_volume), float(scene.density))):
        raise ValueError(
            f"scene {number}: particle_volume and density must be finite and positive, "
            f"got {scene.particle_volume!r} and {scene.density!r}"
        )
    return pos


def _initial_velocity(scene: Scene, count: int, number: int) -> np.ndarray:
    vel = np.asarray(scene.velocity, dtype=np.float32)
    if vel.shape not in ((3,), (count, 3)) or not np.all(np.isfinite(vel)):
        raise ValueError(f"scene {number}: velocity must be finite, shape (3,) or ({count}, 3); got {vel.shape}")
    return np.broadcast_to(vel, (count, 3))


# Bits of a cell coordinate spread three apart, for Morton codes by table lookup.
_MORTON_BITS = (GRID_RESOLUTION - 1).bit_length()
_MORTON_SPREAD = np.array(
    [sum(((c >> b) & 1) << (3 * b) for b in range(_MORTON_BITS)) for c in range(GRID_RESOLUTION)], dtype=np.int64
)


def _morton_cells(points: np.ndarray) -> np.ndarray:
    """Morton (Z-order) code of the grid cell of each point: nearby cells get nearby codes."""
    cells = np.clip((points * GRID_RESOLUTION).astype(np.int64), 0, GRID_RESOLUTION - 1)
    return _MORTON_SPREAD[cells[:, 0]] | (_MORTON_SPREAD[cells[:, 1]] << 1) | (_MORTON_SPREAD[cells[:, 2]] << 2)


def spatial_order(points: np.ndarray, scene_ids: np.ndarray) -> np.ndarray:
    """Permutation that sorts particles by scene, then by Morton code of their cell (stable).

    Particles stay near their memory neighbours as the continuum deforms, so sorting once at the
    start keeps each block of particles compact for the shared-memory P2G (and the CPU caches).
    The order within a scene does not depend on the other scenes of the batch.
    """
    key = scene_ids.astype(np.int64) * NODES + _morton_cells(points)
    return np.argsort(key, kind="stable")


def check_device(device: str, use_cpu: str = "--device cpu") -> None:
    """A one-line ValueError for a Warp device this machine lacks, for command lines to give before
    any work (Warp fails only at its first use of the device, "cuda" without a driver with a RuntimeError);
    `use_cpu` is how the caller's users ask for the CPU instead."""
    available = [d.alias for d in wp.get_devices()]
    if device in available or (device == "cuda" and wp.is_cuda_available()):
        return
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"Warp device {device!r} is not available: no CUDA GPU or driver on this machine; use {use_cpu}")
    raise ValueError(f"Warp device {device!r} is not available; this machine has: {', '.join(available)}")


def simulate(
    scenes: list[Scene],
    device: str = "cpu",
    frame_count: int = FRAME_COUNT,
    frame_interval: float = FRAME_INTERVAL,
    progress: bool = False,
    gravity: float = GRAVITY,
    boundaries: bool = True,
    shared_p2g: bool | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> list[SceneResult]:
    """Simulates all scenes together in the same kernel launches; returns one result per scene.
    `cancelled`, asked before each frame, ends the simulation early by raising Cancelled (a stopping
    node's worker must not be inside Warp when the interpreter exits).

    gravity (m/s^2 along -z, >= 0; the substep count allows for it) and boundaries (walls + ground) can
    be switched off for physics tests.
    shared_p2g selects the shared-memory P2G kernel (default: on CUDA devices only; on CPU it
    needs warp.config.enable_cpu_blocks and is slower, but it is how the CUDA path is tested).
    """
    if not scenes:
        return []
    if frame_count < 1:
        raise ValueError("frame_count must be >= 1")
    _check_frame_interval(frame_interval)
    if not (math.isfinite(gravity) and gravity >= 0):  # the substep rule's speed bound assumes a fall to the ground
        raise ValueError(f"gravity must be >= 0 (m/s^2 along -z), got {gravity!r}")
    positions = [_validate(s, i) for i, s in enumerate(scenes)]
    counts = np.array([len(p) for p in positions], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    records = []
    for i, (s, n) in enumerate(zip(scenes, counts)):
        rec = np.arange(n) if s.record is None else np.asarray(s.record).reshape(-1)
        if len(rec) and rec.dtype.kind not in "iu":
            # A boolean mask or float indices would be cast to the wrong rows without a word.
            raise ValueError(f"scene {i}: record must hold integer particle indices, got dtype {rec.dtype}")
        rec = rec.astype(np.int64)
        if len(rec) and (rec.min() < 0 or rec.max() >= n):
            raise ValueError(f"scene {i}: record indices must lie in [0, {n})")
        records.append(rec)
    rec_counts = np.array([len(r) for r in records], dtype=np.int64)
    rec_offsets = np.concatenate([[0], np.cumsum(rec_counts)])

    velocities = np.concatenate([_initial_velocity(s, n, i) for i, (s, n) in enumerate(zip(scenes, counts))])
    params = [full_parameters(s.family, s.parameters) for s in scenes]
    substeps = np.array([scene_substeps(s, frame_interval, gravity) for s in scenes], dtype=np.int32)
    lame_pairs = [lame(p["youngs_modulus"], p["poissons_ratio"]) for p in params]
    num_scenes, total = len(scenes), int(offsets[-1])
    scene_ids = np.repeat(np.arange(num_scenes), counts)
    order = spatial_order(np.concatenate(positions), scene_ids)
    rank = np.empty_like(order)
    rank[order] = np.arange(total)  # rank[i]: slot of input particle i in the solver arrays

    with wp.ScopedDevice(device):
        if shared_p2g is None:
            shared_p2g = wp.get_device().is_cuda
        if shared_p2g and wp.get_device().is_cpu and not wp.config.enable_cpu_blocks:
            # Without CPU blocks a tiled launch runs one lane per block and would skip particles.
            raise ValueError("shared_p2g on CPU needs warp.config.enable_cpu_blocks = True")
        f32 = lambda a: wp.array(np.asarray(a, dtype=np.float32), dtype=float)  # noqa: E731
        i32 = lambda a: wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32)  # noqa: E731
        x = wp.array(np.concatenate(positions)[order], dtype=wp.vec3)
        v = wp.array(velocities[order], dtype=wp.vec3)
        C = wp.zeros(total, dtype=wp.mat33)
        F = wp.full(total, wp.mat33(np.eye(3, dtype=np.float32)), dtype=wp.mat33)
        stress = wp.zeros(total, dtype=wp.mat33)
        scene_of = i32(scene_ids[order])
        n_sub = i32(substeps)
        dt = f32(frame_interval / substeps.astype(np.float64))
        mass = f32([s.density * s.particle_volume for s in scenes])
        volume = f32([s.particle_volume for s in scenes])
        family = i32([FAMILY_CODES[s.family] for s in scenes])
        mu = f32([m for m, _ in lame_pairs])
        lam = f32([l for _, l in lame_pairs])
        yield_stress = f32([p.get("yield_stress", 0.0) for p in params])
        alpha = f32([drucker_prager_alpha(p["friction_angle"]) if "friction_angle" in p else 0.0 for p in params])
        shape = num_scenes * NODES
        grid_mv = wp.zeros(shape, dtype=wp.vec3)
        grid_m = wp.zeros(shape, dtype=float)
        grid_v = wp.zeros(shape, dtype=wp.vec3)
        rec_index = i32(rank[np.concatenate([r + o for r, o in zip(records, offsets[:-1])])])
        n_rec = int(rec_offsets[-1])
        out_x = wp.zeros((frame_count, n_rec), dtype=wp.vec3)
        out_F = wp.zeros((frame_count, n_rec), dtype=wp.mat33)

        def record(frame: int) -> None:
            if n_rec:
                wp.launch(record_frame, n_rec, inputs=[frame, rec_index, x, F, out_x, out_F])

        record(0)
        iterations = int(substeps.max())
        frames = range(1, frame_count)
        if progress:
            from tqdm import tqdm

            frames = tqdm(frames, desc=f"MPM {num_scenes} scenes", unit="frame")
        for frame in frames:
            if cancelled is not None and cancelled():
                raise Cancelled(f"simulation of {num_scenes} scene(s) cancelled at frame {frame}")
            for it in range(iterations):
                if shared_p2g:
                    wp.launch_tiled(
                        p2g_tiled,
                        dim=[(total + TILE_BLOCK - 1) // TILE_BLOCK],
                        inputs=[it, total, x, v, C, stress, scene_of, n_sub, dt, mass, volume, grid_mv, grid_m],
                        block_dim=TILE_BLOCK,
                    )
                else:
                    wp.launch(
                        p2g,
                        total,
                        inputs=[it, x, v, C, stress, scene_of, n_sub, dt, mass, volume, grid_mv, grid_m],
                        block_dim=BLOCK_DIM,
                    )
                wp.launch(
                    grid_update,
                    shape,
                    inputs=[it, n_sub, dt, float(gravity), int(boundaries), grid_mv, grid_m, grid_v],
                )
                wp.launch(
                    g2p,
                    total,
                    inputs=[it, x, v, C, F, stress, scene_of, n_sub, dt, family, mu, lam, yield_stress, alpha, grid_v],
                    block_dim=BLOCK_DIM,
                )
            record(frame)
        all_x, all_v = x.numpy()[rank], v.numpy()[rank]  # back to input order
        rec_x, rec_F = out_x.numpy(), out_F.numpy()

    results = []
    for i in range(num_scenes):
        r0, r1, p0, p1 = rec_offsets[i], rec_offsets[i + 1], offsets[i], offsets[i + 1]
        results.append(
            SceneResult(
                positions=np.ascontiguousarray(rec_x[:, r0:r1]),
                deformation=np.ascontiguousarray(rec_F[:, r0:r1]),
                substeps_per_frame=int(substeps[i]),
                all_positions_final=all_x[p0:p1].copy(),
                all_velocities_final=all_v[p0:p1].copy(),
            )
        )
    return results
