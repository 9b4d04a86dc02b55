"""Rasteriser against analytic references, cameras, farthest point sampling, vertex binding."""

import numpy as np
import pytest
import trimesh

from ad_sim import render
from ad_sim.instances import BOUNDARY
from ad_sim.render import Camera, RenderJob, intrinsics, look_at

FULL = render.FULL_SIZE


def head_on_camera(distance: float, half_fov_deg: float = 20.0) -> Camera:
    """Camera on the -y side of (0.5, 0.5, 0.3), looking along +y."""
    target = np.array([0.5, 0.5, 0.3])
    pose = look_at(target - [0.0, distance, 0.0], target)
    return Camera(K=intrinsics(FULL, FULL, np.deg2rad(half_fov_deg)), width=FULL, height=FULL, pose=pose)


def test_sphere_mask_matches_analytic_circle():
    radius, distance = 0.2, 2.0
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    camera = head_on_camera(distance)
    vertices = sphere.vertices + [0.5, 0.5, 0.3]
    small, full = render.render_masks([vertices], [sphere.faces], [RenderJob(0, 0, camera.projection())], full=True)
    # The silhouette of a sphere centred on the optical axis is a circle of radius f tan(asin(r / d)).
    circle = camera.K[0, 0] * np.tan(np.arcsin(radius / distance))
    covered = full[0] > 0
    assert covered.sum() == pytest.approx(np.pi * circle**2, rel=0.01)
    ys, xs = np.nonzero(covered)
    assert xs.mean() == pytest.approx(camera.K[0, 2], abs=0.05)
    assert ys.mean() == pytest.approx(camera.K[1, 2], abs=0.05)
    assert set(np.unique(full)) == {0, 255} and set(np.unique(small)) == {0, 255}
    assert small.shape == (1, render.MASK_SIZE, render.MASK_SIZE)
    assert (small[0] > 0).sum() * render.DOWNSAMPLE**2 == pytest.approx(covered.sum(), rel=0.02)


def test_box_seen_head_on_covers_exactly_its_front_face():
    side, distance = 0.3, 1.7
    box = trimesh.creation.box(extents=[side] * 3)
    camera = head_on_camera(distance)
    vertices = box.vertices + [0.5, 0.5, 0.3]
    _, full = render.render_masks([vertices], [box.faces], [RenderJob(0, 0, camera.projection())], full=True)
    # Under perspective the front face (nearest) bounds the silhouette; count the pixel centres inside it.
    half = 0.5 * camera.K[0, 0] * side / (distance - side / 2)
    centre = camera.K[0, 2]
    inside = np.arange(FULL)
    inside = inside[(inside >= centre - half) & (inside <= centre + half)]
    expected = np.zeros((FULL, FULL), dtype=bool)
    expected[inside[0] : inside[-1] + 1, inside[0] : inside[-1] + 1] = True
    np.testing.assert_array_equal(full[0] > 0, expected)


def test_batched_render_equals_one_by_one():
    rng = np.random.default_rng(3)
    meshes = [trimesh.creation.icosphere(subdivisions=2, radius=0.15), trimesh.creation.box(extents=[0.2, 0.3, 0.1])]
    vertex_sets = [m.vertices + rng.uniform(0.3, 0.7, size=3) for m in meshes for _ in range(2)]
    face_sets = [m.faces for m in meshes]
    cameras = render.sample_cameras(rng, 3, FULL, FULL)
    jobs = [RenderJob(v, v // 2, c.projection()) for v in range(4) for c in cameras]
    batched, batched_full = render.render_masks(vertex_sets, face_sets, jobs, full=True)
    for g, job in enumerate(jobs):
        single, single_full = render.render_masks([vertex_sets[job.vertex_set]], [face_sets[job.face_set]], [RenderJob(0, 0, job.projection)], full=True)
        np.testing.assert_array_equal(batched[g], single[0])
        np.testing.assert_array_equal(batched_full[g], single_full[0])
    assert all(m.any() for m in batched)


def test_downsample_is_block_mean_threshold_half():
    rng = np.random.default_rng(0)
    full = (rng.uniform(size=(3, 32, 64)) < 0.5).astype(np.uint8) * 255
    small = render.downsample(full, factor=4)
    blocks = (full > 0).reshape(3, 8, 4, 16, 4).mean(axis=(2, 4))
    np.testing.assert_array_equal(small, np.where(blocks >= 0.5, 255, 0))


def test_coverage_downsample_is_block_mean_rounded_half_up():
    """Grey masks (generate --coverage-masks): each pixel is its block's coverage as 0..255, rounded
    half up, and > 127 exactly where the binary downsample puts the object (the tie, 8 of 16, included)."""
    rng = np.random.default_rng(11)
    # Each 4x4 block its own density, so that every count 0..16 of covered pixels occurs; any non-zero
    # value is covered, as the kernel counts them.
    density = np.kron(rng.uniform(size=(3, 128, 128)), np.ones((1, 4, 4)))
    full = np.where(rng.uniform(size=(3, FULL, FULL)) < density, rng.integers(1, 256, size=(3, FULL, FULL)), 0)
    full = full.astype(np.uint8)
    grey = render.downsample(full, coverage=True)
    binary = render.downsample(full)
    counts = (full > 0).reshape(3, 128, 4, 128, 4).sum(axis=(2, 4))
    assert set(np.unique(counts)) == set(range(17))
    # floor(mean * 255 + 1/2): exact in float64, mean being k/16
    np.testing.assert_array_equal(grey, np.floor(counts / 16 * 255 + 0.5).astype(np.uint8))
    assert grey.dtype == np.uint8 and grey.shape == binary.shape == (3, 128, 128)
    assert set(np.unique(grey[counts == 8])) == {128} and set(np.unique(grey[counts == 7])) == {112}
    np.testing.assert_array_equal(grey > 127, binary == 255)
    np.testing.assert_array_equal(np.where(grey > 127, 255, 0), binary)
    # Other factors too (render_masks takes one).
    small = render.downsample(full[:, :64, :96], factor=2, coverage=True)
    pairs = (full[:, :64, :96] > 0).reshape(3, 32, 2, 48, 2).sum(axis=(2, 4))
    np.testing.assert_array_equal(small, np.floor(pairs / 4 * 255 + 0.5).astype(np.uint8))


def test_render_masks_with_coverage_have_grey_edges_that_threshold_to_the_binary_render():
    rng = np.random.default_rng(3)
    meshes = [trimesh.creation.icosphere(subdivisions=2, radius=0.15), trimesh.creation.box(extents=[0.2, 0.3, 0.1])]
    vertex_sets = [m.vertices + rng.uniform(0.3, 0.7, size=3) for m in meshes]
    cameras = render.sample_cameras(rng, 2, FULL, FULL)
    jobs = [RenderJob(v, v, c.projection()) for v in range(2) for c in cameras]
    binary, binary_full = render.render_masks(vertex_sets, [m.faces for m in meshes], jobs, full=True)
    grey, grey_full = render.render_masks(vertex_sets, [m.faces for m in meshes], jobs, full=True, coverage=True)
    np.testing.assert_array_equal(grey_full, binary_full)  # the same silhouettes, only downsampled otherwise
    np.testing.assert_array_equal(grey, render.downsample(grey_full, coverage=True))
    np.testing.assert_array_equal(grey > 127, binary == 255)
    for mask, full in zip(grey, grey_full):
        edge = (mask > 0) & (mask < 255)
        assert edge.any() and (mask == 255).any()
        # grey pixels are the partly covered blocks: the edge, never the inside or the background
        blocks = (full > 0).reshape(128, 4, 128, 4).mean(axis=(1, 3))
        np.testing.assert_array_equal(edge, (blocks > 0) & (blocks < 1))
    # Without the option the render is binary, as before.
    assert set(np.unique(binary)) == {0, 255}


def test_resized_camera_keeps_pixel_edges():
    camera = render.sample_cameras(np.random.default_rng(1), 1)[0]
    big = camera.resized(FULL, FULL)
    points = np.random.default_rng(2).uniform(0.2, 0.8, size=(10, 3))
    # Pixel edges scale by 4, centres sit half a pixel inside: u_512 = 4 u_128 + 1.5.
    np.testing.assert_allclose(big.project(points), 4 * camera.project(points) + 1.5, atol=1e-9)


def test_sampled_cameras_look_at_the_drop_region():
    rng = np.random.default_rng(5)
    cameras = render.sample_cameras(rng, 20)
    prefix = render.sample_cameras(np.random.default_rng(5), 3)
    for a, b in zip(cameras, prefix):
        np.testing.assert_array_equal(a.pose, b.pose)
    target = np.array(render.CAMERA_TARGET)
    directions = np.random.default_rng(6).normal(size=(200, 3))
    sphere = target + 0.98 * render.VIEW_RADIUS * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    # Sand spreads to the walls: the floor's corners (ground boundary layer) stay in view.
    low, high = BOUNDARY, 1 - BOUNDARY
    floor = np.array([[x, y, BOUNDARY] for x in (low, high) for y in (low, high)])
    for camera in cameras:
        np.testing.assert_allclose(camera.pose[:3, :3] @ camera.pose[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.all((camera.project(floor) >= -0.5) & (camera.project(floor) <= 127.5))
        np.testing.assert_allclose(camera.project(target[None]), [[63.5, 63.5]], atol=1e-9)
        pixels = camera.project(sphere)
        assert np.all((pixels >= -0.5) & (pixels <= 127.5))
        eye = camera.pose[:3, 3]
        elevation = np.degrees(np.arcsin((eye - target)[2] / np.linalg.norm(eye - target)))
        assert render.CAMERA_ELEVATION_DEG[0] <= elevation <= render.CAMERA_ELEVATION_DEG[1]


def test_farthest_point_sampling_spreads_points():
    points = np.random.default_rng(0).uniform(size=(5000, 3))
    chosen = render.farthest_point_sampling(points, 256, start=17)
    assert chosen[0] == 17 and len(np.unique(chosen)) == 256
    np.testing.assert_array_equal(chosen, render.farthest_point_sampling(points, 256, start=17))
    selected = points[chosen]
    gaps = np.linalg.norm(selected[:, None] - selected[None], axis=-1)
    separation = gaps[~np.eye(256, dtype=bool)].min()
    covering = np.linalg.norm(points[:, None] - selected[None], axis=-1).min(axis=1).max()
    # Greedy FPS: every point lies closer to the selection than any two selected points lie to each other.
    assert covering <= separation + 1e-12
    random_subset = points[np.random.default_rng(1).choice(5000, 256, replace=False)]
    random_gaps = np.linalg.norm(random_subset[:, None] - random_subset[None], axis=-1)
    assert separation > 3 * random_gaps[~np.eye(256, dtype=bool)].min()
    with pytest.raises(ValueError, match="at least 256"):
        render.farthest_point_sampling(points[:100], 256)


def test_batched_farthest_point_sampling_matches_a_reference():
    def reference(points, count, start):
        points = points.astype(np.float32)
        chosen, distance = [start], np.full(len(points), np.inf, dtype=np.float32)
        for _ in range(count - 1):
            distance = np.minimum(distance, ((points - points[chosen[-1]]) ** 2).sum(axis=1))
            chosen.append(int(np.argmax(distance)))
        return np.array(chosen)

    rng = np.random.default_rng(9)
    sets = [rng.uniform(size=(n, 3)) for n in (300, 500, 420)]
    # A lattice has many equal distances: ties go to the lowest index, as numpy's argmax does.
    sets.append(np.stack(np.meshgrid(*[np.arange(8.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3))
    starts = [0, 499, 17, 100]
    batched = render.farthest_point_sampling_batch(sets, 64, starts)
    for points, start, chosen in zip(sets, starts, batched):
        np.testing.assert_array_equal(chosen, reference(points, 64, start))


def test_farthest_point_sampling_rejects_starts_outside_their_own_set():
    """The sets are concatenated on the device: a start past its set's end (or negative) used to pick a point
    of the neighbouring set (or read out of bounds) and return its index without a word."""
    rng = np.random.default_rng(3)
    sets = [rng.uniform(size=(40, 3)), rng.uniform(size=(30, 3))]
    for starts in ([40, 0], [0, -1], [0, 30], [0.0, 1.5]):
        with pytest.raises(ValueError, match="start .* of point set"):
            render.farthest_point_sampling_batch(sets, 5, starts)
    with pytest.raises(ValueError, match="one start per point set"):
        render.farthest_point_sampling_batch(sets, 5, [0])
    with pytest.raises(ValueError, match="at least 1 point"):
        render.farthest_point_sampling_batch(sets, 0, [0, 0])
    picked = render.farthest_point_sampling_batch(sets, 5, [39, np.int64(29)])
    assert [p[0] for p in picked] == [39, 29] and all(p.max() < len(s) for p, s in zip(picked, sets))


def test_vertex_advection_follows_particles():
    rng = np.random.default_rng(4)
    particles = rng.uniform(0.3, 0.7, size=(500, 3))
    vertices = rng.uniform(0.3, 0.7, size=(60, 3))
    binding = render.bind_vertices(vertices, particles)
    np.testing.assert_allclose(binding.weights.sum(axis=1), 1.0)
    nearest = np.argsort(np.linalg.norm(vertices[:, None] - particles[None], axis=-1), axis=1)[:, : render.BIND_NEIGHBOURS]
    np.testing.assert_array_equal(np.sort(binding.indices, axis=1), np.sort(nearest, axis=1))

    # F = I and particles at rest: vertices stay where they are.
    frames = 3
    still = np.broadcast_to(particles, (frames, 500, 3))
    identity = np.broadcast_to(np.eye(3), (frames, 500, 3, 3))
    np.testing.assert_allclose(render.advect_vertices(binding, still, identity), np.broadcast_to(vertices, (frames, 60, 3)), atol=1e-6)

    # A rigid motion x -> R x + t with F = R moves the vertices rigidly too.
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    t = np.array([0.05, -0.02, 0.1])
    moved = render.advect_vertices(binding, (particles @ R.T + t)[None], R[None, None].repeat(500, axis=1))
    np.testing.assert_allclose(moved[0], vertices @ R.T + t, atol=1e-6)

    # Reindexing onto a recorded subset addresses the same particles.
    rows = np.unique(np.r_[binding.indices.ravel(), [0, 1, 2]])
    subset = render.advect_vertices(binding.reindexed(rows), still[:, rows], identity[:, rows])
    np.testing.assert_allclose(subset, np.broadcast_to(vertices, (frames, 60, 3)), atol=1e-6)


# ---- mutation-testing audit (round 2)


def test_binding_weights_are_inverse_distance_by_hand():
    """A vertex at distances 1, 2, 4 and 8 from its four nearest particles: weights 1/d normalised,
    i.e. 8/15, 4/15, 2/15, 1/15 (a 1/d^2 weighting passed every other test: any normalised weights do)."""
    particles = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 4.0], [8.0, 0, 0], [0, 20.0, 0]])
    binding = render.bind_vertices(np.zeros((1, 3)), particles)
    order = np.argsort(binding.indices[0])
    np.testing.assert_array_equal(binding.indices[0][order], [0, 1, 2, 3])
    np.testing.assert_allclose(binding.weights[0][order], np.array([8, 4, 2, 1]) / 15, rtol=1e-12)
    np.testing.assert_allclose(binding.offsets[0][order], -particles[:4], rtol=1e-12)


def test_resizing_to_another_aspect_scales_each_axis_by_its_own_factor():
    """u' = (u + 0.5) sx - 0.5 and v' = (v + 0.5) sy - 0.5 for a resize to a non-square image (every other
    resize in the tests is square, where sx = sy hides a swapped factor)."""
    camera = render.sample_cameras(np.random.default_rng(7), 1)[0]  # 128 x 128
    wide = camera.resized(256, 64)
    assert (wide.width, wide.height) == (256, 64)
    points = np.random.default_rng(8).uniform(0.2, 0.8, size=(10, 3))
    u, v = camera.project(points).T
    np.testing.assert_allclose(wide.project(points), np.c_[(u + 0.5) * 2 - 0.5, (v + 0.5) * 0.5 - 0.5], atol=1e-9)


def test_a_quad_over_the_whole_image_covers_every_pixel_edges_included():
    """Two triangles whose projection spans beyond the image on every side: every pixel of the 512x512 mask,
    the last row and column included, is covered (the bounding box is clipped to the image, not short of it)."""
    camera = Camera(K=intrinsics(FULL, FULL, np.deg2rad(20.0)), width=FULL, height=FULL,
                    pose=look_at(np.array([0.5, -1.5, 0.5]), np.array([0.5, 0.5, 0.5])))
    # A square in the plane y = 0.5 that is much wider than the field of view there.
    vertices = np.array([[-3.0, 0.5, -3.0], [4.0, 0.5, -3.0], [4.0, 0.5, 4.0], [-3.0, 0.5, 4.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    small, full = render.render_masks([vertices], [faces], [RenderJob(0, 0, camera.projection())], full=True)
    assert (full[0] == 255).all() and (small[0] == 255).all()
