"""Physics checks of the batched Warp MPM solver (real kernels on CPU, small scenes, short runs)."""

import math

import numpy as np
import pytest
import warp as wp

from ad_sim.materials import FAMILY_RANGES, FRAME_INTERVAL, lame
from ad_sim.mpm import (
    CLAMP_HI,
    CLAMP_LO,
    COURANT,
    DX,
    GROUND_Z,
    Scene,
    group_by_substeps,
    scene_speed_bound,
    scene_substeps,
    simulate,
    substeps_for,
)

wp.config.log_level = wp.LOG_WARNING  # no start-up banner or kernel-load lines
SPACING = DX / 2  # 8 particles per grid cell
SOFT_JELLY = {"youngs_modulus": 3e4, "poissons_ratio": 0.25}
PLASTICINE = {"youngs_modulus": 2e5, "poissons_ratio": 0.45, "yield_stress": 2e3}


def lattice(inside, lo, hi, spacing=SPACING):
    """Particles on a regular lattice inside the bounding box [lo, hi] where inside(points) holds."""
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return pts[inside(pts)].astype(np.float32)


def box(center, size):
    c, h = np.asarray(center), np.asarray(size) / 2
    return lattice(lambda p: np.ones(len(p), bool), c - h, c + h)


def sphere(center, radius):
    c = np.asarray(center)
    return lattice(lambda p: np.linalg.norm(p - c, axis=1) <= radius, c - radius, c + radius)


def scene(points, family, parameters, velocity=(0.0, 0.0, 0.0), record=None):
    return Scene(points, np.asarray(velocity, np.float32), family, parameters, SPACING**3, record=record)


def height(points):
    return float(points[:, 2].max() - points[:, 2].min())


def test_substeps_follow_wave_speed_and_groups_sort():
    mu, lam = lame(1.5e6, 0.4)
    wave = math.sqrt((lam + 2 * mu) / 1000.0)
    for speed in (0.0, 3.0):
        n = substeps_for("jelly", {"youngs_modulus": 1.5e6, "poissons_ratio": 0.4}, speed=speed)
        # n is the smallest substep count whose dt meets the Courant condition.
        assert FRAME_INTERVAL / n * (wave + speed) / DX <= COURANT + 1e-9
        assert FRAME_INTERVAL / (n - 1) * (wave + speed) / DX > COURANT
    soft = substeps_for("jelly", {"youngs_modulus": 1.5e4, "poissons_ratio": 0.2}, speed=0.0)
    assert soft < n / 4
    assert substeps_for("jelly", {"youngs_modulus": 1.5e4, "poissons_ratio": 0.2}, speed=5.0) > soft
    # A scene's speed bound: initial speed plus free fall from its highest particle to the ground.
    high = scene(box((0.5, 0.5, 0.7), (0.1, 0.1, 0.1)), "sand", {"friction_angle": 0.5}, velocity=(3.0, 0.0, 0.0))
    drop = high.positions[:, 2].max() - GROUND_Z
    assert scene_speed_bound(high) == pytest.approx(math.sqrt(9.0 + 2 * 9.8 * drop), rel=1e-6)
    assert scene_speed_bound(high, gravity=0.0) == pytest.approx(3.0)
    pts = box((0.5, 0.5, 0.3), (0.1, 0.1, 0.1))
    scenes = [scene(pts, "jelly", {"youngs_modulus": E, "poissons_ratio": 0.3}) for E in (1e6, 2e4, 3e5, 5e4, 1e5)]
    groups = group_by_substeps(scenes, 2)
    assert sorted(sum(groups, [])) == list(range(5)) and [len(g) for g in groups] == [2, 2, 1]
    order = [substeps_for(scenes[i].family, scenes[i].parameters) for g in groups for i in g]
    assert order == sorted(order)


def test_transfers_conserve_momentum():
    """Two jelly balls collide with gravity and walls off: total momentum stays put, velocities do not."""
    a, b = sphere((0.35, 0.5, 0.5), 0.08), sphere((0.62, 0.52, 0.5), 0.06)
    pts = np.concatenate([a, b])
    vel = np.concatenate([np.tile([2.0, 0.3, 0.0], (len(a), 1)), np.tile([-3.0, 0.0, 0.5], (len(b), 1))])
    sc = scene(pts, "jelly", {"youngs_modulus": 1e5, "poissons_ratio": 0.3}, velocity=vel.astype(np.float32))
    (res,) = simulate([sc], frame_count=4, gravity=0.0, boundaries=False)
    p0, p1 = vel.sum(0), res.all_velocities_final.astype(np.float64).sum(0)
    assert np.abs(p1 - p0).max() < 1e-4 * np.abs(vel).sum(0).max()
    # The balls did collide (velocities changed a lot), so the check above is not vacuous.
    assert np.abs(res.all_velocities_final - vel).max() > 1.0
    # With gravity on, momentum changes by M g t.
    (res_g,) = simulate([sc], frame_count=4, gravity=9.8, boundaries=False)
    dvz = res_g.all_velocities_final[:, 2].astype(np.float64).mean() - res.all_velocities_final[:, 2].mean()
    assert dvz == pytest.approx(-9.8 * 3 * FRAME_INTERVAL, rel=1e-3)
    # The substep count allows for the gravity simulated (it assumed 9.8 whatever was asked).
    assert res.substeps_per_frame < res_g.substeps_per_frame == scene_substeps(sc)
    with pytest.raises(ValueError, match="gravity must be >= 0"):
        simulate([sc], frame_count=1, gravity=-9.8)


def _rigid_residual(a, b):
    """RMS distance between point sets a and b after the best rigid alignment (Kabsch)."""
    a0, b0 = a - a.mean(0), b - b.mean(0)
    U, _, Vt = np.linalg.svd(a0.T @ b0)
    d = np.sign(np.linalg.det(U @ Vt))
    R = U @ np.diag([1, 1, d]) @ Vt
    return float(np.sqrt(((a0 @ R - b0) ** 2).sum(1).mean()))


def test_jelly_rebounds_keeps_shape_and_stiffer_deforms_less():
    pts = box((0.5, 0.5, 0.25), (0.16, 0.16, 0.16))
    moduli = (2e4, 1e5, 5e5)
    scenes = [scene(pts, "jelly", {"youngs_modulus": E, "poissons_ratio": 0.3}) for E in moduli]
    results = simulate(scenes, frame_count=15)
    squash = []
    for res in results:
        z = res.positions[..., 2]
        squash.append(float((z.max(1) - z.min(1)).min() / height(pts)))
    # Stiffer jelly flattens less on impact, strictly monotone over the sweep.
    assert squash[0] < squash[1] < squash[2] < 1.0
    assert squash[0] < 0.85 and squash[2] > 0.97

    res = results[1]
    com = res.positions[..., 2].mean(1)
    impact = int(np.argmin(com))
    assert 3 < impact < 12
    # Rebound: the centre of mass climbs back by a large part of the drop height.
    assert com[impact:].max() - com[impact] > 0.5 * (com[0] - com[impact])
    # After the impact the body has its rest volume and shape again (up to a rigid motion).
    J = np.linalg.det(res.deformation[-1].astype(np.float64))
    assert abs(J.mean() - 1.0) < 0.03
    assert _rigid_residual(res.positions[0], res.positions[-1]) < 0.05 * height(pts)


def test_plasticine_permanent_set_shrinks_with_yield_stress():
    pts = box((0.5, 0.5, 0.25), (0.16, 0.16, 0.16))
    yields = (1e3, 4e3, 2e4)
    results = simulate(
        [scene(pts, "plasticine", {"youngs_modulus": 1e5, "poissons_ratio": 0.4, "yield_stress": y}) for y in yields],
        frame_count=18,
    )
    sets = []
    for res in results:
        z = res.positions[..., 2]
        h = z.max(1) - z.min(1)
        # Settled: over the last frames the height only wobbles elastically, the deformation stays.
        assert np.ptp(h[-4:]) < 0.05 * h[0]
        sets.append(1.0 - float(h[-4:].mean() / h[0]))
    assert sets[0] > sets[1] > sets[2]
    assert sets[0] > 0.25 and sets[2] < 0.05


def test_sand_spreads_and_pile_slope_grows_with_friction_angle():
    pts = box((0.5, 0.5, 0.2), (0.16, 0.16, 0.24))
    angles = (15.0, 30.0, 45.0)
    results = simulate([scene(pts, "sand", {"friction_angle": math.radians(a)}) for a in angles], frame_count=22)
    slopes = []
    for res in results:
        final = res.positions[-1]
        radius = np.percentile(np.linalg.norm(final[:, :2] - final[:, :2].mean(0), axis=1), 95)
        # The column collapsed and spread well beyond its initial footprint (half-diagonal 0.113).
        assert radius > 0.15 and height(final) < 0.5 * height(pts)
        assert np.abs(res.all_velocities_final).max() < 0.1  # settled
        slopes.append(height(final) / radius)
    assert slopes[0] < slopes[1] < slopes[2]
    assert slopes[2] > 1.8 * slopes[0]


def _corner_parameters():
    corners = []
    jelly, plasticine, sand = (FAMILY_RANGES[f] for f in ("jelly", "plasticine", "sand"))
    for E in jelly["youngs_modulus"][:2]:
        for nu in jelly["poissons_ratio"][:2]:
            corners.append(("jelly", {"youngs_modulus": E, "poissons_ratio": nu}))
    for E in plasticine["youngs_modulus"][:2]:
        for nu in plasticine["poissons_ratio"][:2]:
            for y in plasticine["yield_stress"][:2]:
                corners.append(("plasticine", {"youngs_modulus": E, "poissons_ratio": nu, "yield_stress": y}))
    for phi in sand["friction_angle"][:2]:
        corners.append(("sand", {"friction_angle": phi}))
    return corners


def test_extreme_parameter_corners_stay_finite_and_inside():
    """Every corner of every range, on a box, a ball and a thin slab, dropped or thrown at a wall."""
    shapes = (
        lambda c: box(c, (0.12, 0.12, 0.12)),
        lambda c: sphere(c, 0.07),
        lambda c: box(c, (0.3, 0.3, 0.03)),
    )
    throws = ((0.0, 0.0, 0.0), (5.0, 0.0, -3.0), (0.0, -4.0, 2.0))
    corners = _corner_parameters()
    assert len(corners) == 14
    scenes = [
        scene(shapes[i % 3]((0.5, 0.5, 0.2)), family, params, velocity=throws[i % 3])
        for i, (family, params) in enumerate(corners)
    ]
    results = simulate(scenes, frame_count=10)
    for (family, params), res in zip(corners, results):
        label = f"{family} {params}"
        assert np.all(np.isfinite(res.positions)) and np.all(np.isfinite(res.deformation)), label
        assert np.all(np.isfinite(res.all_velocities_final)), label
        assert res.positions.min() >= CLAMP_LO and res.positions.max() <= CLAMP_HI, label
        # Boundary conditions, not the safety clamp, keep the material in: almost nobody sits on it.
        at_clamp = (res.positions[-1] <= CLAMP_LO + 1e-6) | (res.positions[-1] >= CLAMP_HI - 1e-6)
        assert at_clamp.mean() < 0.02, label
        # Stable: no energy blow-up, no collapsed or exploded elements.
        assert np.abs(res.all_velocities_final).max() < 8.0, label
        J = np.linalg.det(res.deformation.astype(np.float64))
        assert J.min() > 0.2 and J.max() < 2.0, label


def test_batched_equals_one_at_a_time_and_is_deterministic():
    scenes = [
        scene(sphere((0.3, 0.4, 0.3), 0.07), "jelly", SOFT_JELLY, velocity=(1, 0, 0)),
        scene(box((0.6, 0.6, 0.2), (0.1, 0.12, 0.08)), "plasticine", PLASTICINE),
        scene(box((0.5, 0.5, 0.15), (0.2, 0.2, 0.04)), "sand", {"friction_angle": 0.6}, record=np.array([5, 0, 17])),
    ]
    batched = simulate(scenes, frame_count=8)
    again = simulate(scenes, frame_count=8)
    assert len({r.substeps_per_frame for r in batched}) == 3
    for sc, b, a in zip(scenes, batched, again):
        (single,) = simulate([sc], frame_count=8)
        assert b.positions.shape == (8, len(sc.positions) if sc.record is None else len(sc.record), 3)
        # On CPU (sequential atomics) batching is exact; on CUDA it agrees to float rounding.
        assert np.array_equal(b.positions, single.positions)
        assert np.array_equal(b.deformation, single.deformation)
        assert np.array_equal(b.positions, a.positions) and np.array_equal(b.deformation, a.deformation)
    # Recorded indices follow `record` (frame 0 is the initial state).
    assert np.array_equal(batched[2].positions[0], scenes[2].positions[[5, 0, 17]])
    assert np.abs(batched[2].positions[-1] - batched[2].positions[0]).max() > 0.01


def test_rejects_particles_outside_the_domain():
    pts = box((0.5, 0.5, 0.03), (0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="inside"):
        simulate([scene(pts, "jelly", {"youngs_modulus": 1e5, "poissons_ratio": 0.3})])


def test_rejects_bad_time_step_mass_and_record_arguments():
    """Each of these used to run without a word: frame_interval <= 0 (dt <= 0, time runs backwards),
    NaN volume or infinite density (NaN mass: every particle ends in the clamp's corner), a boolean or float
    `record` (cast to rows 0/1 or truncated)."""
    pts = box((0.5, 0.5, 0.5), (0.05, 0.05, 0.05))
    jelly = {"youngs_modulus": 1e5, "poissons_ratio": 0.3}
    for interval in (0.0, -FRAME_INTERVAL, math.nan):
        with pytest.raises(ValueError, match="frame_interval"):
            simulate([scene(pts, "jelly", jelly)], frame_count=2, frame_interval=interval)
        with pytest.raises(ValueError, match="frame_interval"):
            substeps_for("jelly", jelly, frame_interval=interval)
    for volume, density in ((math.nan, 1000.0), (SPACING**3, math.inf), (-1.0, 1000.0)):
        bad = Scene(pts, np.zeros(3, np.float32), "jelly", jelly, volume, density=density)
        with pytest.raises(ValueError, match="finite and positive"):
            simulate([bad], frame_count=2)
    for record in (np.ones(len(pts), bool), np.array([0.5, 1.7])):
        with pytest.raises(ValueError, match="integer particle indices"):
            simulate([scene(pts, "jelly", jelly, record=record)], frame_count=2)
    # Integer indices of any integer type (and an empty record) are fine.
    (res,) = simulate([scene(pts, "jelly", jelly, record=np.array([3, 1], np.uint16))], frame_count=2)
    np.testing.assert_array_equal(res.positions[0], pts[[3, 1]])
    (res,) = simulate([scene(pts, "jelly", jelly, record=[])], frame_count=2)
    assert res.positions.shape == (2, 0, 3)


def test_shared_memory_p2g_matches_plain_p2g():
    """The CUDA P2G (shared-memory patches) run on Warp's CPU block emulation equals the plain P2G."""
    scenes = [
        scene(sphere((0.3, 0.4, 0.3), 0.07), "jelly", SOFT_JELLY, velocity=(1, 0, 0)),
        # A thin wide slab: some blocks span more than a patch (and one block spans both scenes),
        # so the global-atomics fallback is exercised too (~300 of 2405 particles at t = 0).
        scene(box((0.5, 0.5, 0.15), (0.4, 0.4, 0.04)), "sand", {"friction_angle": 0.6}),
    ]
    plain = simulate(scenes, frame_count=6, shared_p2g=False)
    previous = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        shared = simulate(scenes, frame_count=6, shared_p2g=True)
    finally:
        wp.config.enable_cpu_blocks = previous
    for a, b in zip(plain, shared):
        assert np.abs(a.positions[-1] - a.positions[0]).max() > 0.01  # things moved
        assert np.allclose(a.positions, b.positions, atol=2e-6)
        assert np.allclose(a.deformation, b.deformation, atol=5e-5)


# ---- mutation-testing audit (round 2)


def test_a_ball_thrown_at_any_face_of_the_domain_is_stopped_by_it():
    """Gravity off, a jelly ball thrown at 3 m/s at each of the six faces (four walls, ceiling, ground): the
    boundary layer stops it, so it ends moving away from or along the face, not into it, and almost nothing
    sits on the safety clamp. Only throws at +x, -y and down were tested: a low-x wall that let material in
    (its test on vx flipped) or a ceiling that held falling material instead of stopping rising material
    passed."""
    speed = 3.0
    directions = np.concatenate([np.eye(3), -np.eye(3)])
    ball = sphere((0.5, 0.5, 0.5), 0.06)
    scenes = [scene(ball, "jelly", {"youngs_modulus": 1e5, "poissons_ratio": 0.3}, velocity=speed * d)
              for d in directions]
    results = simulate(scenes, frame_count=12, gravity=0.0)  # 0.275 s: the face is reached after ~0.15 s
    for d, res in zip(directions, results):
        final = res.positions[-1].astype(np.float64)
        along = float(res.all_velocities_final.astype(np.float64).mean(0) @ d)
        assert along < 0.25 * speed, (d, along)  # stopped or bounced back, not still moving into the face
        at_clamp = (final <= CLAMP_LO + 1e-6) | (final >= CLAMP_HI - 1e-6)
        assert at_clamp.any(axis=1).mean() < 0.02, d
        # It did travel to the face (its centre came well over half the way there) before it was stopped.
        assert ((res.positions.astype(np.float64).mean(1) - ball.mean(0)) @ d).max() > 0.2, d
