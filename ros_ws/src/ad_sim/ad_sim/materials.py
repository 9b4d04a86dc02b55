"""The constitutive laws of the simulator, and (re-exported from ad_sim.families) the material families and
their parameter ranges.

Pure Python plus Warp functions; no ROS. The laws follow the paper's MPM appendix (NCLaw style):
each elastic law maps a deformation gradient to a Kirchhoff stress, each plastic law projects a
trial deformation gradient back onto its yield surface. A family is an (elastic, plastic) pair.

All laws work on the SVD F = U diag(sigma) V^T (U, V rotations). Singular values are clamped to
[SIGMA_MIN, SIGMA_MAX] before any log or product, and norms carry an epsilon, so no law can
produce NaN or inf for any finite F (inverted elements included: Warp's SVD puts the sign of
det F on the last singular value, which the clamp lifts to SIGMA_MIN).
"""

from __future__ import annotations

import math

import warp as wp

from .families import (  # noqa: F401 - re-exported: the simulator's users read them here
    FAMILIES, FAMILY_PARAMETERS, FAMILY_RANGES, FIXED_PARAMETERS, FRAME_COUNT, FRAME_INTERVAL, PARAMETER_NAMES,
    PARAMETER_RANGES, SAMPLED_PARAMETERS, denormalise, full_parameters, normalise, sample_parameters)

GRID_RESOLUTION = 32  # grid cells per axis of the unit cube
GRAVITY = 9.8  # m/s^2, along -z
DENSITY = 1000.0  # kg/m^3

# Singular-value clamp of every law: keeps log() finite and stresses bounded under extreme
# compression / inversion, while leaving physically reached strains (|log sigma| < ~2) untouched.
SIGMA_MIN = 1e-2
SIGMA_MAX = 1e2
NORM_EPS = 1e-12

# Integer family codes used inside kernels (index into FAMILIES).
FAMILY_CODES = {family: code for code, family in enumerate(FAMILIES)}
JELLY = wp.constant(FAMILY_CODES["jelly"])
PLASTICINE = wp.constant(FAMILY_CODES["plasticine"])
SAND = wp.constant(FAMILY_CODES["sand"])


def lame(youngs_modulus: float, poissons_ratio: float) -> tuple[float, float]:
    """Lame parameters (mu, lambda) from Young's modulus and Poisson's ratio."""
    mu = youngs_modulus / (2.0 * (1.0 + poissons_ratio))
    lam = youngs_modulus * poissons_ratio / ((1.0 + poissons_ratio) * (1.0 - 2.0 * poissons_ratio))
    return mu, lam


def drucker_prager_alpha(friction_angle: float) -> float:
    """alpha = sqrt(2/3) * 2 sin(phi) / (3 - sin(phi)) of the Drucker-Prager cone."""
    s = math.sin(friction_angle)
    return math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)


# ----------------------------------------------------------------------------------------------
# Warp laws. Each works on the SVD (U, sigma, V); the F-level wrappers exist for direct use/tests.
# ----------------------------------------------------------------------------------------------


@wp.func
def clamp_sigma(sigma: wp.vec3):
    return wp.vec3(
        wp.clamp(sigma[0], SIGMA_MIN, SIGMA_MAX),
        wp.clamp(sigma[1], SIGMA_MIN, SIGMA_MAX),
        wp.clamp(sigma[2], SIGMA_MIN, SIGMA_MAX),
    )


@wp.func
def compose(U: wp.mat33, sigma: wp.vec3, V: wp.mat33):
    """U diag(sigma) V^T."""
    return U * wp.diag(sigma) * wp.transpose(V)


@wp.func
def projected(F: wp.mat33, U: wp.mat33, sigma: wp.vec3, sigma_new: wp.vec3, V: wp.mat33):
    """F after a projection that changed sigma to sigma_new; F itself (no SVD round-off) if unchanged."""
    if sigma_new[0] == sigma[0] and sigma_new[1] == sigma[1] and sigma_new[2] == sigma[2]:
        return F
    return compose(U, sigma_new, V)


@wp.func
def log_sigma(sigma: wp.vec3):
    return wp.vec3(wp.log(sigma[0]), wp.log(sigma[1]), wp.log(sigma[2]))


@wp.func
def exp_vec(eps: wp.vec3):
    return wp.vec3(wp.exp(eps[0]), wp.exp(eps[1]), wp.exp(eps[2]))


@wp.func
def deviatoric(eps: wp.vec3):
    mean = (eps[0] + eps[1] + eps[2]) / 3.0
    return eps - wp.vec3(mean, mean, mean)


@wp.func
def safe_norm(v: wp.vec3):
    return wp.sqrt(wp.dot(v, v) + NORM_EPS)


@wp.func
def corotated_kirchhoff_svd(U: wp.mat33, sigma: wp.vec3, mu: float, lam: float):
    """tau = 2 mu (F - R) F^T + lambda J (J - 1) I with R = U V^T, J = det F, on clamped sigma.

    (F - R) F^T = U (S - I) S U^T, so tau is diagonal in the U basis.
    """
    s = clamp_sigma(sigma)
    J = s[0] * s[1] * s[2]
    vol = lam * J * (J - 1.0)
    d = wp.vec3(
        2.0 * mu * (s[0] - 1.0) * s[0] + vol,
        2.0 * mu * (s[1] - 1.0) * s[1] + vol,
        2.0 * mu * (s[2] - 1.0) * s[2] + vol,
    )
    return U * wp.diag(d) * wp.transpose(U)


@wp.func
def hencky_kirchhoff_svd(U: wp.mat33, sigma: wp.vec3, mu: float, lam: float):
    """tau = U (2 mu eps + lambda tr(eps) I) U^T with eps = log sigma (StVK in Hencky strain)."""
    eps = log_sigma(clamp_sigma(sigma))
    tr = eps[0] + eps[1] + eps[2]
    d = 2.0 * mu * eps + wp.vec3(lam * tr, lam * tr, lam * tr)
    return U * wp.diag(d) * wp.transpose(U)


@wp.func
def identity_projection_sigma(sigma: wp.vec3):
    """No plasticity: the state is returned unchanged."""
    return sigma


@wp.func
def von_mises_projection_sigma(sigma: wp.vec3, mu: float, yield_stress: float):
    """dgamma = |eps_hat| - sigma_y / (2 mu); if > 0, eps <- eps - dgamma eps_hat / |eps_hat|."""
    eps = log_sigma(clamp_sigma(sigma))
    eps_hat = deviatoric(eps)
    norm = safe_norm(eps_hat)
    dgamma = norm - yield_stress / (2.0 * mu)
    if dgamma <= 0.0:
        return sigma
    return exp_vec(eps - (dgamma / norm) * eps_hat)


@wp.func
def drucker_prager_projection_sigma(sigma: wp.vec3, mu: float, lam: float, alpha: float):
    """Sand: Sigma <- I in tension (tr eps > 0); unchanged inside the cone; else radial return onto it."""
    eps = log_sigma(clamp_sigma(sigma))
    tr = eps[0] + eps[1] + eps[2]
    if tr > 0.0:
        return wp.vec3(1.0, 1.0, 1.0)
    eps_hat = deviatoric(eps)
    norm = safe_norm(eps_hat)
    dgamma = norm + alpha * (3.0 * lam + 2.0 * mu) * tr / (2.0 * mu)
    if dgamma <= 0.0:
        return sigma
    return exp_vec(eps - (dgamma / norm) * eps_hat)


@wp.func
def svd(F: wp.mat33):
    U = wp.mat33()
    sigma = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sigma, V)
    return U, sigma, V


@wp.func
def corotated_kirchhoff(F: wp.mat33, mu: float, lam: float):
    U, sigma, V = svd(F)
    return corotated_kirchhoff_svd(U, sigma, mu, lam)


@wp.func
def hencky_kirchhoff(F: wp.mat33, mu: float, lam: float):
    U, sigma, V = svd(F)
    return hencky_kirchhoff_svd(U, sigma, mu, lam)


@wp.func
def identity_projection(F: wp.mat33):
    return F


@wp.func
def von_mises_projection(F: wp.mat33, mu: float, yield_stress: float):
    U, sigma, V = svd(F)
    return projected(F, U, sigma, von_mises_projection_sigma(sigma, mu, yield_stress), V)


@wp.func
def drucker_prager_projection(F: wp.mat33, mu: float, lam: float, alpha: float):
    U, sigma, V = svd(F)
    return projected(F, U, sigma, drucker_prager_projection_sigma(sigma, mu, lam, alpha), V)


@wp.func
def project_sigma(family: int, sigma: wp.vec3, mu: float, lam: float, yield_stress: float, alpha: float):
    """The family's plastic projection on singular values."""
    if family == PLASTICINE:
        return von_mises_projection_sigma(sigma, mu, yield_stress)
    if family == SAND:
        return drucker_prager_projection_sigma(sigma, mu, lam, alpha)
    return identity_projection_sigma(sigma)


@wp.func
def kirchhoff_svd(family: int, U: wp.mat33, sigma: wp.vec3, mu: float, lam: float):
    """The family's elastic Kirchhoff stress from the SVD of F."""
    if family == JELLY:
        return corotated_kirchhoff_svd(U, sigma, mu, lam)
    return hencky_kirchhoff_svd(U, sigma, mu, lam)
