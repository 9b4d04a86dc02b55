"""Material families, their parameters and sampling ranges, and the episode timing: what the estimator
and the metrics share with the simulator. Pure Python and NumPy, without Warp, so that the estimator's
runtime does not load Warp (ad_sim.materials, which re-exports all of this, holds the laws)."""

from __future__ import annotations

import math

import numpy as np

FAMILIES = ("jelly", "plasticine", "sand")
PARAMETER_NAMES = ("youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle")
PARAMETER_UNITS = {"youngs_modulus": "Pa", "poissons_ratio": "", "yield_stress": "Pa", "friction_angle": "rad"}  # SI, REP-103

FRAME_INTERVAL = 0.025  # s between recorded frames
FRAME_COUNT = 25  # frames per episode, frame 0 = initial state

# Family sampling ranges (SPEC section 6): (low, high, "log" | "linear") or a fixed float.
_PHI_LO, _PHI_HI = math.radians(10.0), math.radians(45.0)
FAMILY_RANGES: dict[str, dict[str, tuple[float, float, str] | float]] = {
    "jelly": {
        "youngs_modulus": (1.5e4, 1.5e6, "log"),
        "poissons_ratio": (0.20, 0.40, "linear"),
    },
    "plasticine": {
        "youngs_modulus": (5e4, 5e5, "log"),
        "poissons_ratio": (0.35, 0.48, "linear"),
        "yield_stress": (500.0, 25000.0, "log"),
    },
    "sand": {
        "youngs_modulus": 1e5,
        "poissons_ratio": 0.3,
        "friction_angle": (_PHI_LO, _PHI_HI, "linear"),
    },
}

# Which parameters each family's law uses (fixed ones included), in PARAMETER_NAMES order.
FAMILY_PARAMETERS: dict[str, tuple[str, ...]] = {
    family: tuple(n for n in PARAMETER_NAMES if n in FAMILY_RANGES[family]) for family in FAMILIES
}
# Sampled (learnable) parameters per family and the fixed values of the others.
SAMPLED_PARAMETERS: dict[str, tuple[str, ...]] = {
    family: tuple(n for n in FAMILY_PARAMETERS[family] if isinstance(FAMILY_RANGES[family][n], tuple))
    for family in FAMILIES
}
FIXED_PARAMETERS: dict[str, dict[str, float]] = {
    family: {n: float(v) for n, v in FAMILY_RANGES[family].items() if not isinstance(v, tuple)}
    for family in FAMILIES
}

# Union ranges used by normalise()/denormalise() (docs/architecture.md): one head serves all families.
PARAMETER_RANGES: dict[str, tuple[float, float, str]] = {
    "youngs_modulus": (1.5e4, 1.5e6, "log"),
    "poissons_ratio": (0.20, 0.48, "linear"),
    "yield_stress": (500.0, 25000.0, "log"),
    "friction_angle": (_PHI_LO, _PHI_HI, "linear"),
}

def _check_family(family: str) -> None:
    if family not in FAMILY_RANGES:
        raise ValueError(f"unknown material family {family!r}; expected one of {FAMILIES}")


def sample_parameters(family: str, rng: np.random.Generator) -> dict[str, float]:
    """Draws one parameter set of `family` (SI units, radians): log-uniform E and yield, uniform nu/phi."""
    _check_family(family)
    out: dict[str, float] = {}
    for name in FAMILY_PARAMETERS[family]:
        spec = FAMILY_RANGES[family][name]
        if not isinstance(spec, tuple):
            out[name] = float(spec)
            continue
        lo, hi, scale = spec
        if scale == "log":
            out[name] = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        else:
            out[name] = float(rng.uniform(lo, hi))
    return out


def _union_range(name: str) -> tuple[float, float, str]:
    if name not in PARAMETER_RANGES:
        raise ValueError(f"unknown parameter {name!r}; expected one of {PARAMETER_NAMES}")
    return PARAMETER_RANGES[name]


def to_unit(value, low: float, high: float, scale: str):
    """A value (SI; a float or an array) -> its place in the range [low, high]: 0 at low, 1 at high, in log
    space for scale "log"; a value outside the range maps outside [0, 1]."""
    v = np.asarray(value, dtype=np.float64)
    out = np.log(v / low) / math.log(high / low) if scale == "log" else (v - low) / (high - low)
    return float(out) if out.ndim == 0 else out


def from_unit(unit, low: float, high: float, scale: str):
    """Inverse of to_unit."""
    u = np.asarray(unit, dtype=np.float64)
    out = low * (high / low) ** u if scale == "log" else low + u * (high - low)
    return float(out) if out.ndim == 0 else out


def normalise(name: str, value):
    """Maps a parameter (SI) to [0, 1] over its union range (log space for E and yield stress).

    Works on floats and numpy arrays alike; values outside the range map outside [0, 1].
    """
    return to_unit(value, *_union_range(name))


def denormalise(name: str, value):
    """Inverse of normalise()."""
    return from_unit(value, *_union_range(name))


def full_parameters(family: str, parameters: dict[str, float]) -> dict[str, float]:
    """The family's parameters with fixed values filled in; raises on missing or foreign names, or a fixed
    parameter given another value."""
    _check_family(family)
    unknown = set(parameters) - set(PARAMETER_NAMES)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; expected names from {PARAMETER_NAMES}")
    fixed = FIXED_PARAMETERS[family]
    changed = {k: v for k, v in parameters.items() if k in fixed and not math.isclose(v, fixed[k], rel_tol=1e-6)}
    if changed:  # the family's law is defined with them (and the substep rule validated for them)
        raise ValueError(f"{family} fixes {sorted(changed)} at {[fixed[k] for k in sorted(changed)]}, got {changed}")
    out = dict(fixed)
    out.update({k: float(v) for k, v in parameters.items() if k in FAMILY_PARAMETERS[family] and k not in fixed})
    missing = [n for n in FAMILY_PARAMETERS[family] if n not in out]
    if missing:
        raise ValueError(f"{family} needs parameter(s) {missing} (SI units, radians for friction_angle)")
    # Values outside the sampling ranges are allowed (e.g. re-simulating predictions), unphysical ones not.
    valid = {
        "youngs_modulus": lambda v: v > 0.0,
        "poissons_ratio": lambda v: -1.0 < v < 0.5,
        "yield_stress": lambda v: v > 0.0,
        "friction_angle": lambda v: 0.0 <= v < math.pi / 2,
    }
    bad = {n: v for n, v in out.items() if not (math.isfinite(v) and valid[n](v))}
    if bad:
        raise ValueError(
            f"{family}: unphysical parameter(s) {bad}; need E > 0, -1 < nu < 0.5, yield > 0, 0 <= phi < pi/2 (radians)"
        )
    return out
