"""Cameras, tracked-particle selection, mesh-to-particle binding and the batched mask rasteriser.

No ROS here. The rasteriser is a pair of Warp kernels that run on CPU and CUDA alike:
one thread per (image, triangle) marks the pixels whose centre the projected triangle
covers (binary coverage, no depth test needed for silhouettes), then one thread per
output pixel area-downsamples the 512x512 masks to 128x128.

Pixel convention (OpenCV / ROS CameraInfo): pixel (u, v) has its centre at integer
coordinates (u, v) and covers [u - 0.5, u + 0.5) x [v - 0.5, v + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

# Rendering resolutions (SPEC 6): rasterise at FULL_SIZE, the model sees MASK_SIZE.
FULL_SIZE = 512
MASK_SIZE = 128
DOWNSAMPLE = FULL_SIZE // MASK_SIZE

TRACKED_PARTICLES = 1024
BIND_NEIGHBOURS = 4

# Cameras look at the region where objects fall and land (the domain is the unit cube,
# z up, ground boundary at z ~ 0.09). A sphere of VIEW_RADIUS around CAMERA_TARGET is kept
# inside the field of view: it holds every drop pose and the whole floor between the walls
# (sand spreads wall to wall).
CAMERA_TARGET = (0.5, 0.5, 0.35)
VIEW_RADIUS = 0.65
CAMERA_DISTANCE = (1.5, 2.0)
CAMERA_ELEVATION_DEG = (10.0, 45.0)

# Bound on one rasteriser launch's output (images x 512 x 512 bytes) so that big batches
# fit in GPU memory; larger jobs are split into chunks of this many images.
MAX_IMAGES_PER_LAUNCH = 2048


# ----------------------------------------------------------------------------- cameras


@dataclass
class Camera:
    """Pinhole camera. `pose` maps the optical frame (x right, y down, z forward) to world."""

    K: np.ndarray  # (3, 3) intrinsics at (width, height)
    width: int
    height: int
    pose: np.ndarray  # (4, 4) camera -> world

    def projection(self) -> np.ndarray:
        """(3, 4) world -> homogeneous pixel matrix K [R | t] of the world->camera transform."""
        world_to_camera = np.linalg.inv(self.pose)
        return self.K @ world_to_camera[:3, :]

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera with an image of another size (same field of view)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[1, 1] *= sy
        # Pixel edges scale, centres sit half a pixel inside them.
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Camera(K=K, width=width, height=height, pose=self.pose.copy())

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of world points (N, 3) (numpy reference, for tests and tools)."""
        homogeneous = np.c_[points, np.ones(len(points))] @ self.projection().T
        return homogeneous[:, :2] / homogeneous[:, 2:3]


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera->world pose (4, 4) of an optical frame at `eye` looking at `target`."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def intrinsics(width: int, height: int, half_fov: float) -> np.ndarray:
    """Square-pixel K whose half field of view (along the shorter side) is `half_fov` rad."""
    focal = 0.5 * min(width, height) / np.tan(half_fov)
    return np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])


def sample_cameras(rng: np.random.Generator, n: int, width: int = MASK_SIZE, height: int = MASK_SIZE) -> list[Camera]:
    """n random views of the drop region: azimuth uniform, elevation 10-45 deg, distance 1.5-2.0.

    Cameras are drawn one after another, so the first k of n cameras do not depend on n.
    The field of view just holds a sphere of VIEW_RADIUS around CAMERA_TARGET.
    """
    target = np.array(CAMERA_TARGET)
    cameras = []
    for _ in range(n):
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        elevation = np.deg2rad(rng.uniform(*CAMERA_ELEVATION_DEG))
        distance = rng.uniform(*CAMERA_DISTANCE)
        direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        pose = look_at(target + distance * direction, target)
        K = intrinsics(width, height, np.arcsin(VIEW_RADIUS / distance))
        cameras.append(Camera(K=K, width=width, height=height, pose=pose))
    return cameras


# ----------------------------------------------------------------- particles and binding


@wp.kernel
def _fps_update_kernel(
    points: wp.array(dtype=wp.vec3),
    set_of: wp.array(dtype=wp.int32),
    chosen: wp.array2d(dtype=wp.int32),
    step: int,
    distance: wp.array(dtype=wp.float32),
    best: wp.array(dtype=wp.float32),
):
    """Distance of each point to the selection so far (adding point chosen[s, step - 1])."""
    p = wp.tid()
    s = set_of[p]
    d = wp.min(distance[p], wp.length_sq(points[p] - points[chosen[s, step - 1]]))
    distance[p] = d
    wp.atomic_max(best, s, d)


@wp.kernel
def _fps_pick_kernel(
    set_of: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.float32),
    best: wp.array(dtype=wp.float32),
    pick: wp.array(dtype=wp.int32),
):
    """Among the farthest points of each set, the lowest index (deterministic tie-break)."""
    p = wp.tid()
    s = set_of[p]
    if distance[p] == best[s]:
        wp.atomic_min(pick, s, p)


@wp.kernel
def _fps_commit_kernel(
    step: int,
    pick: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.float32),
    chosen: wp.array2d(dtype=wp.int32),
):
    s = wp.tid()
    chosen[s, step] = pick[s]
    pick[s] = 2147483647
    best[s] = -1.0


def farthest_point_sampling_batch(
    point_sets: Sequence[np.ndarray], count: int, starts: Sequence[int], device: str = "cpu"
) -> list[np.ndarray]:
    """Farthest point sampling of many point sets (N_i, 3) at once: `count` indices per set.

    Each pick is the point farthest from those already chosen (lowest index on ties), starting
    from `starts[i]`. All sets advance together, three kernel launches per pick.
    """
    sizes = np.array([len(p) for p in point_sets], dtype=np.int64)
    if len(sizes) == 0:
        return []
    if count < 1:
        raise ValueError(f"farthest point sampling picks at least 1 point, asked for {count}")
    if sizes.min() < count:
        raise ValueError(f"farthest point sampling needs at least {count} points, got {int(sizes.min())}")
    starts = np.asarray(starts).reshape(-1)
    if len(starts) != len(sizes):
        raise ValueError(f"need one start per point set, got {len(starts)} for {len(sizes)} sets")
    # The sets are concatenated: an index outside its own set would silently start in a neighbour's.
    bad = [i for i, (start, size) in enumerate(zip(starts, sizes)) if not 0 <= start < size]
    if starts.dtype.kind not in "iu" or bad:
        i = bad[0] if bad else 0
        raise ValueError(f"start {starts[i]!r} of point set {i} is not an index into its {sizes[i]} points")
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    with wp.ScopedDevice(device):
        points = wp.array(np.concatenate(point_sets).astype(np.float32), dtype=wp.vec3)
        set_of = wp.array(np.repeat(np.arange(len(sizes)), sizes).astype(np.int32), dtype=wp.int32)
        initial = np.zeros((len(sizes), count), dtype=np.int32)
        initial[:, 0] = np.asarray(starts, dtype=np.int64) + offsets[:-1]
        chosen = wp.array(initial, dtype=wp.int32)
        distance = wp.array(np.full(int(offsets[-1]), np.inf, dtype=np.float32), dtype=wp.float32)
        best = wp.array(np.full(len(sizes), -1.0, dtype=np.float32), dtype=wp.float32)
        pick = wp.array(np.full(len(sizes), 2**31 - 1, dtype=np.int32), dtype=wp.int32)
        for step in range(1, count):
            wp.launch(_fps_update_kernel, dim=len(set_of), inputs=[points, set_of, chosen, step, distance, best])
            wp.launch(_fps_pick_kernel, dim=len(set_of), inputs=[set_of, distance, best, pick])
            wp.launch(_fps_commit_kernel, dim=len(sizes), inputs=[step, pick, best, chosen])
        result = chosen.numpy().astype(np.int64) - offsets[:-1, None]
    return list(result)


def farthest_point_sampling(points: np.ndarray, count: int, start: int = 0, device: str = "cpu") -> np.ndarray:
    """Indices of `count` points of one set chosen by farthest point sampling from `start`."""
    return farthest_point_sampling_batch([points], count, [start], device)[0]


@dataclass
class Binding:
    """Each mesh vertex bound to k particles: x_v = sum_j w_j (x_j + F_j (X_v - X_j(0)))."""

    indices: np.ndarray  # (V, k) int64 particle rows
    weights: np.ndarray  # (V, k) float64, rows sum to 1
    offsets: np.ndarray  # (V, k, 3) float64, X_v - X_j(0)

    def reindexed(self, rows: np.ndarray) -> "Binding":
        """The binding with particle indices replaced by their position in sorted `rows`
        (e.g. the recorded subset handed to the simulator)."""
        return Binding(np.searchsorted(rows, self.indices), self.weights, self.offsets)


def bind_vertices(vertices: np.ndarray, particles: np.ndarray, k: int = BIND_NEIGHBOURS) -> Binding:
    """Bind each vertex (V, 3) to its k nearest particles (N, 3) at t = 0, inverse-distance weights."""
    distance, indices = cKDTree(particles).query(vertices, k=k)
    distance, indices = distance.reshape(len(vertices), k), indices.reshape(len(vertices), k)
    # The floor keeps a vertex that sits on a particle from dividing by zero.
    weights = 1.0 / np.maximum(distance, 1e-9)
    weights /= weights.sum(axis=1, keepdims=True)
    offsets = vertices[:, None, :] - particles[indices]
    return Binding(indices=indices.astype(np.int64), weights=weights, offsets=offsets)


def advect_vertices(binding: Binding, positions: np.ndarray, deformation: np.ndarray) -> np.ndarray:
    """Vertex positions (T, V, 3) from particle positions (T, N, 3) and deformation gradients (T, N, 3, 3)."""
    x = positions[:, binding.indices]  # (T, V, k, 3)
    F = deformation[:, binding.indices]  # (T, V, k, 3, 3)
    moved = x + np.einsum("tvkij,vkj->tvki", F, binding.offsets)
    return np.einsum("tvki,vk->tvi", moved, binding.weights).astype(np.float32)


# -------------------------------------------------------------------------- rasteriser


@wp.func
def _project(projection: wp.array3d(dtype=wp.float32), image: int, p: wp.vec3) -> wp.vec3:
    row = wp.vec3(0.0)
    for r in range(3):
        row[r] = (
            projection[image, r, 0] * p[0]
            + projection[image, r, 1] * p[1]
            + projection[image, r, 2] * p[2]
            + projection[image, r, 3]
        )
    return row


@wp.kernel
def _rasterise_kernel(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    work_start: wp.array(dtype=wp.int32),
    face_offset: wp.array(dtype=wp.int32),
    vertex_offset: wp.array(dtype=wp.int32),
    projection: wp.array3d(dtype=wp.float32),
    image_count: int,
    masks: wp.array3d(dtype=wp.uint8),
):
    work = wp.tid()
    # Which image this (image, triangle) work item belongs to: binary search in work_start.
    lo = int(0)
    hi = image_count
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if work_start[mid] <= work:
            lo = mid
        else:
            hi = mid
    image = lo
    face = faces[face_offset[image] + work - work_start[image]]
    base = vertex_offset[image]
    a = _project(projection, image, vertices[base + face[0]])
    b = _project(projection, image, vertices[base + face[1]])
    c = _project(projection, image, vertices[base + face[2]])
    # Cameras sit far outside the domain; a vertex at or behind the eye is not drawable.
    if a[2] <= 1.0e-6 or b[2] <= 1.0e-6 or c[2] <= 1.0e-6:
        return
    ax = a[0] / a[2]
    ay = a[1] / a[2]
    bx = b[0] / b[2]
    by = b[1] / b[2]
    cx = c[0] / c[2]
    cy = c[1] / c[2]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if wp.abs(area) < 1.0e-12:
        return
    orientation = wp.sign(area)
    height = masks.shape[1]
    width = masks.shape[2]
    x0 = wp.max(int(wp.ceil(wp.min(ax, wp.min(bx, cx)))), 0)
    x1 = wp.min(int(wp.floor(wp.max(ax, wp.max(bx, cx)))), width - 1)
    y0 = wp.max(int(wp.ceil(wp.min(ay, wp.min(by, cy)))), 0)
    y1 = wp.min(int(wp.floor(wp.max(ay, wp.max(by, cy)))), height - 1)
    for y in range(y0, y1 + 1):
        py = float(y)
        for x in range(x0, x1 + 1):
            px = float(x)
            e0 = orientation * ((bx - ax) * (py - ay) - (by - ay) * (px - ax))
            e1 = orientation * ((cx - bx) * (py - by) - (cy - by) * (px - bx))
            e2 = orientation * ((ax - cx) * (py - cy) - (ay - cy) * (px - cx))
            if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                masks[image, y, x] = wp.uint8(255)


@wp.kernel
def _downsample_kernel(full: wp.array3d(dtype=wp.uint8), factor: int, coverage: int, out: wp.array3d(dtype=wp.uint8)):
    # A flat launch: multi-dimensional launches are much slower per thread on Warp's CPU backend.
    n = wp.tid()
    height = out.shape[1]
    width = out.shape[2]
    image = n / (height * width)
    y = (n / width) % height
    x = n % width
    covered = int(0)
    for dy in range(factor):
        for dx in range(factor):
            if full[image, y * factor + dy, x * factor + dx] != wp.uint8(0):
                covered += 1
    area = factor * factor
    if coverage != 0:
        # The block mean as 0..255, rounded half up: > 127 exactly where the threshold below says inside.
        out[image, y, x] = wp.uint8((510 * covered + area) / (2 * area))
    elif 2 * covered >= area:  # block mean >= 0.5 -> inside
        out[image, y, x] = wp.uint8(255)
    else:
        out[image, y, x] = wp.uint8(0)


@dataclass
class RenderJob:
    """One image: draw mesh `faces[face_set]` with vertex set `vertex_set` through `projection`."""

    vertex_set: int
    face_set: int
    projection: np.ndarray  # (3, 4) world -> pixel at the full resolution


def _downsample_device(full: wp.array, factor: int, coverage: bool, device: str) -> wp.array:
    count, height, width = full.shape
    if height % factor or width % factor:
        raise ValueError(f"mask size {height}x{width} is not a multiple of {factor}")
    out = wp.empty((count, height // factor, width // factor), dtype=wp.uint8, device=device)
    wp.launch(_downsample_kernel, dim=out.size, inputs=[full, factor, int(coverage), out], device=device)
    return out


def downsample(full: np.ndarray, factor: int = DOWNSAMPLE, coverage: bool = False, device: str = "cpu") -> np.ndarray:
    """Area-downsample binary masks (G, H, W) by `factor`: the block mean thresholded at 0.5 -> {0, 255},
    or with `coverage` the block mean itself as 0..255 (rounded; > 127 exactly where the threshold
    puts the object, so a consumer that thresholds at 127 reads the binary masks)."""
    source = wp.array(np.ascontiguousarray(full, dtype=np.uint8), dtype=wp.uint8, device=device)
    return _downsample_device(source, factor, coverage, device).numpy()


def render_masks(
    vertex_sets: Sequence[np.ndarray],
    face_sets: Sequence[np.ndarray],
    jobs: Sequence[RenderJob],
    size: int = FULL_SIZE,
    factor: int = DOWNSAMPLE,
    full: bool = False,
    device: str = "cpu",
    coverage: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Rasterise many silhouettes in shared kernel launches.

    vertex_sets: world-space vertex arrays (N_i, 3); face_sets: triangle index arrays (M_j, 3)
    indexing into a vertex set; jobs: one RenderJob per image. Returns masks (G, size/factor,
    size/factor) uint8 {0, 255} (with `coverage`: 0..255, see downsample) and, if `full`, the
    (G, size, size) masks they came from.
    """
    vertex_counts = np.array([len(v) for v in vertex_sets], dtype=np.int64)
    face_counts = np.array([len(f) for f in face_sets], dtype=np.int64)
    vertex_starts = np.concatenate([[0], np.cumsum(vertex_counts)])
    face_starts = np.concatenate([[0], np.cumsum(face_counts)])
    if vertex_starts[-1] >= 2**31 or face_starts[-1] >= 2**31:
        raise ValueError("too many vertices or faces for one render call; split the batch")
    vertices = wp.array(np.concatenate(vertex_sets).astype(np.float32), dtype=wp.vec3, device=device)
    faces = wp.array(np.concatenate(face_sets).astype(np.int32), dtype=wp.vec3i, device=device)

    small = size // factor
    masks = np.empty((len(jobs), small, small), dtype=np.uint8)
    masks_full = np.empty((len(jobs), size, size), dtype=np.uint8) if full else None
    for first in range(0, len(jobs), MAX_IMAGES_PER_LAUNCH):
        chunk = jobs[first : first + MAX_IMAGES_PER_LAUNCH]
        counts = np.array([face_counts[j.face_set] for j in chunk], dtype=np.int64)
        work_start = np.concatenate([[0], np.cumsum(counts)])
        if work_start[-1] >= 2**31:
            raise ValueError("too many triangles in one launch; lower MAX_IMAGES_PER_LAUNCH")
        chunk_full = wp.zeros((len(chunk), size, size), dtype=wp.uint8, device=device)
        wp.launch(
            _rasterise_kernel,
            dim=int(work_start[-1]),
            inputs=[
                vertices,
                faces,
                wp.array(work_start.astype(np.int32), dtype=wp.int32, device=device),
                wp.array(np.array([face_starts[j.face_set] for j in chunk], np.int32), dtype=wp.int32, device=device),
                wp.array(np.array([vertex_starts[j.vertex_set] for j in chunk], np.int32), dtype=wp.int32, device=device),
                wp.array(np.stack([j.projection for j in chunk]).astype(np.float32), dtype=wp.float32, device=device),
                len(chunk),
                chunk_full,
            ],
            device=device,
        )
        masks[first : first + len(chunk)] = _downsample_device(chunk_full, factor, coverage, device).numpy()
        if full:
            masks_full[first : first + len(chunk)] = chunk_full.numpy()
    return masks, masks_full
