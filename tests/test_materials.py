"""Material families, parameter handling and the Warp constitutive laws against numpy references."""

import math

import numpy as np
import pytest
import warp as wp

from ad_sim import materials as M

wp.config.log_level = wp.LOG_WARNING  # no start-up banner or kernel-load lines
N_MATRICES = 256


def _random_F(rng, n=N_MATRICES, spread=0.3):
    """Random deformation gradients with det > 0 and singular values well inside the clamp."""
    F = np.eye(3) + spread * rng.normal(size=(n, 3, 3))
    F[np.linalg.det(F) < 0] *= -1.0
    F = F[np.linalg.svd(F, compute_uv=False).min(1) > 0.2]
    return F.astype(np.float32)


def _rotation_svd(F):
    """numpy SVD with U, V proper rotations (sign of det F on the last singular value)."""
    U, s, Vt = np.linalg.svd(F.astype(np.float64))
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))[:, None]
    fix_U = np.linalg.det(U) < 0
    U[fix_U, :, 2] *= -1
    fix_V = np.linalg.det(Vt) < 0
    Vt[fix_V, 2, :] *= -1
    s = s.copy()
    s[:, 2] *= d[:, 0]
    return U, s, np.transpose(Vt, (0, 2, 1))


@wp.kernel
def _apply_laws(
    F: wp.array(dtype=wp.mat33),
    mu: float,
    lam: float,
    yield_stress: float,
    alpha: float,
    corotated: wp.array(dtype=wp.mat33),
    hencky: wp.array(dtype=wp.mat33),
    identity: wp.array(dtype=wp.mat33),
    von_mises: wp.array(dtype=wp.mat33),
    drucker_prager: wp.array(dtype=wp.mat33),
):
    i = wp.tid()
    f = F[i]
    corotated[i] = M.corotated_kirchhoff(f, mu, lam)
    hencky[i] = M.hencky_kirchhoff(f, mu, lam)
    identity[i] = M.identity_projection(f)
    von_mises[i] = M.von_mises_projection(f, mu, yield_stress)
    drucker_prager[i] = M.drucker_prager_projection(f, mu, lam, alpha)


def run_laws(F, mu, lam, yield_stress=1000.0, alpha=0.3):
    Fw = wp.array(F, dtype=wp.mat33, device="cpu")
    outs = [wp.zeros(len(F), dtype=wp.mat33, device="cpu") for _ in range(5)]
    wp.launch(_apply_laws, len(F), inputs=[Fw, mu, lam, yield_stress, alpha, *outs], device="cpu")
    return [o.numpy().astype(np.float64) for o in outs]


def test_sampling_is_in_range_and_seeded():
    for family in M.FAMILIES:
        a = [M.sample_parameters(family, np.random.default_rng(s)) for s in range(200)]
        b = [M.sample_parameters(family, np.random.default_rng(s)) for s in range(200)]
        assert a == b
        assert set(a[0]) == set(M.FAMILY_PARAMETERS[family])
        for name, spec in M.FAMILY_RANGES[family].items():
            values = np.array([p[name] for p in a])
            if isinstance(spec, tuple):
                lo, hi, scale = spec
                assert values.min() >= lo and values.max() <= hi
                # log-uniform: the median sits near the geometric mean, far below the arithmetic one.
                # log-uniform parameters are uniform in log space: compare medians there.
                to_axis = np.log if scale == "log" else (lambda a: a)
                axis, lo_a, hi_a = to_axis(values), to_axis(lo), to_axis(hi)
                assert abs(np.median(axis) - (lo_a + hi_a) / 2) < 0.1 * (hi_a - lo_a)
            else:
                assert np.all(values == spec)
    assert M.FAMILY_PARAMETERS["sand"] == ("youngs_modulus", "poissons_ratio", "friction_angle")
    assert M.SAMPLED_PARAMETERS["sand"] == ("friction_angle",)
    with pytest.raises(ValueError, match="unknown material family"):
        M.sample_parameters("water", np.random.default_rng(0))


def test_normalise_round_trip_and_endpoints():
    for name, (lo, hi, scale) in M.PARAMETER_RANGES.items():
        assert M.normalise(name, lo) == pytest.approx(0.0, abs=1e-12)
        assert M.normalise(name, hi) == pytest.approx(1.0, abs=1e-12)
        u = np.linspace(0, 1, 11)
        assert np.allclose(M.normalise(name, M.denormalise(name, u)), u)
        mid = M.denormalise(name, 0.5)
        assert mid == pytest.approx(math.sqrt(lo * hi) if scale == "log" else (lo + hi) / 2)
    assert M.normalise("poissons_ratio", 0.48) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        M.normalise("density", 1.0)


def test_lame_and_full_parameters():
    mu, lam = M.lame(1e5, 0.3)
    assert mu == pytest.approx(1e5 / 2.6)
    assert lam == pytest.approx(1e5 * 0.3 / (1.3 * 0.4))
    assert M.full_parameters("sand", {"friction_angle": 0.5}) == {
        "youngs_modulus": 1e5,
        "poissons_ratio": 0.3,
        "friction_angle": 0.5,
    }
    with pytest.raises(ValueError, match="needs parameter"):
        M.full_parameters("plasticine", {"youngs_modulus": 1e5, "poissons_ratio": 0.4})
    with pytest.raises(ValueError, match="unphysical"):
        M.full_parameters("jelly", {"youngs_modulus": 1e5, "poissons_ratio": 0.5})
    with pytest.raises(ValueError, match="unphysical"):
        M.full_parameters("sand", {"friction_angle": 30.0})  # degrees by mistake
    # Sand's E and nu are fixed: given again they must be the same (they simulated sand at E = 1e6 before).
    assert M.full_parameters("sand", {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.5})["youngs_modulus"] == 1e5
    with pytest.raises(ValueError, match=r"sand fixes \['youngs_modulus'\] at \[100000.0\]"):
        M.full_parameters("sand", {"youngs_modulus": 1e6, "friction_angle": 0.5})


def test_elastic_laws_match_numpy():
    rng = np.random.default_rng(1)
    F = _random_F(rng)
    mu, lam = M.lame(2e5, 0.35)
    corotated, hencky, identity, _, _ = run_laws(F, mu, lam)
    U, s, V = _rotation_svd(F)
    Fd = F.astype(np.float64)
    R = U @ np.transpose(V, (0, 2, 1))
    J = np.linalg.det(Fd)
    ref_corot = 2 * mu * (Fd - R) @ np.transpose(Fd, (0, 2, 1)) + (lam * J * (J - 1))[:, None, None] * np.eye(3)
    eps = np.log(s)
    d = 2 * mu * eps + lam * eps.sum(1, keepdims=True)
    ref_hencky = np.einsum("nij,nj,nkj->nik", U, d, U)
    scale = mu + lam
    assert np.abs(corotated - ref_corot).max() < 1e-4 * scale
    assert np.abs(hencky - ref_hencky).max() < 1e-4 * scale
    assert np.array_equal(identity, Fd)
    # Rest state is stress free; a pure rotation is stress free for both laws.
    c0, h0, *_ = run_laws(np.eye(3, dtype=np.float32)[None], mu, lam)
    assert np.abs(c0).max() < 1e-6 * scale and np.abs(h0).max() < 1e-6 * scale
    rot = R[:8].astype(np.float32)
    c1, h1, *_ = run_laws(rot, mu, lam)
    assert np.abs(c1).max() < 1e-4 * scale and np.abs(h1).max() < 1e-4 * scale


def test_von_mises_projects_onto_yield_surface():
    rng = np.random.default_rng(2)
    F = np.concatenate([_random_F(rng), _random_F(rng, spread=0.02)])
    mu, lam = M.lame(1e5, 0.4)
    yield_stress = 3000.0
    *_, vm, _ = run_laws(F, mu, lam, yield_stress=yield_stress)
    _, s_in, _ = _rotation_svd(F)
    _, s_out, _ = _rotation_svd(vm)
    eps_in, eps_out = np.log(s_in), np.log(s_out)
    dev = lambda e: e - e.mean(1, keepdims=True)  # noqa: E731
    radius = yield_stress / (2 * mu)
    outside = np.linalg.norm(dev(eps_in), axis=1) > radius
    assert outside.sum() > 50 and (~outside).sum() > 0
    # Yielded states land on the surface, volume (tr eps) is untouched, elastic ones stay put.
    assert np.allclose(np.linalg.norm(dev(eps_out[outside]), axis=1), radius, rtol=1e-3)
    assert np.allclose(eps_out.sum(1), eps_in.sum(1), atol=2e-4)
    assert np.allclose(vm[~outside], F[~outside], atol=1e-5)


def test_drucker_prager_tension_cone_and_return():
    rng = np.random.default_rng(3)
    F = _random_F(rng, n=2000, spread=0.25)
    mu, lam = M.lame(1e5, 0.3)
    alpha = M.drucker_prager_alpha(math.radians(30))
    *_, dp = run_laws(F, mu, lam, alpha=alpha)
    U, s_in, V = _rotation_svd(F)
    eps = np.log(s_in)
    tr = eps.sum(1)
    dev = eps - tr[:, None] / 3
    dgamma = np.linalg.norm(dev, axis=1) + alpha * (3 * lam + 2 * mu) * tr / (2 * mu)
    tension = tr > 1e-4
    inside = (tr < -1e-4) & (dgamma < -1e-4)
    crushed = (tr < -1e-4) & (dgamma > 1e-4)
    assert tension.sum() > 10 and inside.sum() > 10 and crushed.sum() > 10
    # Tension: Sigma = I, so F becomes the rotation U V^T (Warp's float32 SVD is good to ~1e-3).
    R = U @ np.transpose(V, (0, 2, 1))
    assert np.allclose(dp[tension] @ np.transpose(dp[tension], (0, 2, 1)), np.eye(3), atol=1e-5)
    assert np.allclose(dp[tension], R[tension], atol=2e-3)
    assert np.allclose(dp[inside], F[inside], atol=1e-5)
    # Crushed: on the cone |eps_hat| = -alpha (3 lam + 2 mu) tr(eps) / (2 mu), tr(eps) unchanged.
    _, s_out, _ = _rotation_svd(dp[crushed])
    e_out = np.log(s_out)
    t_out = e_out.sum(1)
    assert np.allclose(t_out, tr[crushed], atol=2e-4)
    cone = -alpha * (3 * lam + 2 * mu) * t_out / (2 * mu)
    assert np.allclose(np.linalg.norm(e_out - t_out[:, None] / 3, axis=1), cone, rtol=2e-3, atol=2e-5)


def test_laws_never_produce_nan():
    rng = np.random.default_rng(4)
    extreme = [
        np.zeros((3, 3)),
        np.diag([1.0, 1.0, -1.0]),
        np.diag([1e-9, 1.0, 1.0]),
        np.diag([1e6, 1e6, 1e6]),
        np.diag([1e-6, 1e-6, 1e-6]),
        np.ones((3, 3)),
    ]
    F = np.concatenate([np.array(extreme), 50 * rng.normal(size=(64, 3, 3))]).astype(np.float32)
    for E, nu in [(1.5e6, 0.4), (5e5, 0.48), (1.5e4, 0.2)]:
        mu, lam = M.lame(E, nu)
        for out in run_laws(F, mu, lam, yield_stress=500.0, alpha=M.drucker_prager_alpha(math.radians(45))):
            assert np.all(np.isfinite(out))


# --------------------------------------------------------------------------- mutation-testing audit


def test_drucker_prager_alpha_by_hand():
    """alpha = sqrt(2/3) * 2 sin(phi) / (3 - sin(phi)) (docs/simulator.md): at 30 degrees sin = 1/2, so
    alpha = sqrt(2/3) * 1 / 2.5; no friction, no cone."""
    assert M.drucker_prager_alpha(math.radians(30.0)) == pytest.approx(math.sqrt(2 / 3) * 0.4, rel=1e-12)
    assert M.drucker_prager_alpha(math.radians(90.0)) == pytest.approx(math.sqrt(2 / 3), rel=1e-12)  # 2 / (3 - 1)
    assert M.drucker_prager_alpha(0.0) == 0.0


@wp.kernel
def _family_laws(
    U: wp.mat33,
    sigma: wp.vec3,
    mu: float,
    lam: float,
    yield_stress: float,
    alpha: float,
    stress: wp.array(dtype=wp.mat33),
    projected: wp.array(dtype=wp.vec3),
):
    family = wp.tid()
    stress[family] = M.kirchhoff_svd(family, U, sigma, mu, lam)
    projected[family] = M.project_sigma(family, sigma, mu, lam, yield_stress, alpha)


def test_each_family_uses_its_own_elastic_and_plastic_law():
    """docs/simulator.md: jelly = corotated + identity, plasticine = Hencky + von Mises, sand = Hencky +
    Drucker-Prager. A stretched state (all singular values > 1: tension for sand, far outside a small yield
    surface for plasticine) tells every pairing apart."""
    s = np.array([1.3, 1.1, 1.05])
    mu, lam = M.lame(1e5, 0.3)
    stress = wp.zeros(3, dtype=wp.mat33, device="cpu")
    projected = wp.zeros(3, dtype=wp.vec3, device="cpu")
    identity = wp.mat33(*np.eye(3).ravel())
    alpha = M.drucker_prager_alpha(0.5)
    wp.launch(_family_laws, 3, inputs=[identity, wp.vec3(*s), mu, lam, 100.0, alpha, stress, projected], device="cpu")
    stress, projected = stress.numpy().astype(np.float64), projected.numpy().astype(np.float64)
    J = s.prod()
    corotated = np.diag(2 * mu * (s - 1) * s + lam * J * (J - 1))
    hencky = np.diag(2 * mu * np.log(s) + lam * np.log(s).sum())
    assert np.abs(corotated - hencky).max() > 0.05 * mu  # the state tells the laws apart
    codes = M.FAMILY_CODES
    np.testing.assert_allclose(stress[codes["jelly"]], corotated, rtol=1e-4, atol=1e-3 * mu)
    for family in ("plasticine", "sand"):
        np.testing.assert_allclose(stress[codes[family]], hencky, rtol=1e-4, atol=1e-3 * mu)
    np.testing.assert_allclose(projected[codes["jelly"]], s, rtol=1e-6)  # no plasticity
    np.testing.assert_allclose(projected[codes["sand"]], 1.0, rtol=1e-6)  # tension: Sigma <- I
    eps = np.log(projected[codes["plasticine"]])
    # von Mises: the deviatoric strain lands on the yield surface, the volume (tr eps) is kept
    assert np.linalg.norm(eps - eps.mean()) == pytest.approx(100.0 / (2 * mu), rel=1e-3)
    assert eps.sum() == pytest.approx(np.log(s).sum(), rel=1e-4)


def test_physical_bounds_of_parameters_outside_the_sampling_ranges():
    """full_parameters allows values outside the sampling ranges (re-simulated predictions), unphysical ones
    not: -1 < nu < 0.5, 0 <= phi < pi/2; a family's fixed values only as they are."""
    assert M.full_parameters("jelly", {"youngs_modulus": 1e3, "poissons_ratio": -0.5})["poissons_ratio"] == -0.5
    assert M.full_parameters("sand", {"friction_angle": 1.5})["friction_angle"] == 1.5
    for family, parameters in [("jelly", {"youngs_modulus": 1e5, "poissons_ratio": -1.0}),
                               ("sand", {"friction_angle": math.pi / 2}),
                               ("sand", {"friction_angle": 2.0}),
                               ("plasticine", {"youngs_modulus": 1e5, "poissons_ratio": 0.4, "yield_stress": 0.0})]:
        with pytest.raises(ValueError, match="unphysical"):
            M.full_parameters(family, parameters)
    with pytest.raises(ValueError, match="sand fixes"):
        M.full_parameters("sand", {"youngs_modulus": 1.2e5, "friction_angle": 0.5})
