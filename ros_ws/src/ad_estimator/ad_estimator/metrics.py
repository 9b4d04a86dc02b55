"""The metrics of the paper's tables (SPEC section 8), shared by `python -m training evaluate`
and `ros2 run ad_estimator evaluate`.

numpy, matplotlib and ad_sim.families only: this module must never import torch or Warp.

Inputs are a `Predictions` per number of observed frames (the largest is the full clip: 25 for
the simulator's clips, fewer for a model that takes fewer; plus the temporal-OOD prefixes 24, 22,
18, 15). Parameters are SI (friction angle in radians);
reports show the friction angle in degrees. Where the predictions carry the model's one-sigma
uncertainties, the full-clip metrics also say how well those are calibrated (uncertainty_calibration).
The full-clip report also says where the errors lie along each parameter's range (error_by_true_value).
"""
from __future__ import annotations

import argparse
import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ad_sim.families import (FAMILIES, FAMILY_RANGES, FRAME_COUNT, PARAMETER_NAMES, PARAMETER_UNITS,
                              SAMPLED_PARAMETERS, to_unit)

#: The temporal out-of-distribution rows: only the first K frames are observed.
TEMPORAL_OOD_FRAMES = (24, 22, 18, 15)


class FrameCounts(argparse.Action):
    """`--frames K ...` for the evaluators: values may be spaces or commas (`24 18` or `24,18`);
    stores the distinct counts, largest first, each checked to lie in 1..FRAME_COUNT. A bare
    `--frames` stores [] (the caller's default set)."""

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            counts = {int(v) for value in values for v in value.split(",") if v.strip()}
        except ValueError:
            parser.error(f"{option_string}: expected frame counts such as 24 18 or 24,18, got {' '.join(values)!r}")
        if values and not counts:  # `--frames ,` is a typo, not the bare flag's default set
            parser.error(f"{option_string}: expected frame counts such as 24 18 or 24,18, got {' '.join(values)!r}")
        if bad := sorted(k for k in counts if not 1 <= k <= FRAME_COUNT):
            parser.error(f"{option_string} {bad}: each K must be in 1..{FRAME_COUNT}")
        setattr(namespace, self.dest, sorted(counts, reverse=True))

# How each parameter's error is reported (SPEC 8): log-MAE (natural log), MAE, MAE in degrees.
ERROR_KIND = {
    "youngs_modulus": "log_mae",
    "poissons_ratio": "mae",
    "yield_stress": "log_mae",
    "friction_angle": "mae_deg",
}
# Column labels of the paper's table.
_SHORT = {"youngs_modulus": "E", "poissons_ratio": "nu", "yield_stress": "yield", "friction_angle": "phi"}


def family_ranges() -> dict[str, dict[str, tuple[float, float, str]]]:
    """Each family's sampled parameters and their own sampling ranges (fixed ones left out)."""
    return {f: {n: FAMILY_RANGES[f][n] for n in SAMPLED_PARAMETERS[f]} for f in FAMILIES}


@dataclass
class Predictions:
    """Model outputs over N clips, with their ground truth. Filled by every evaluator."""

    true_class: np.ndarray  # (N,) int, index into FAMILIES
    true_params: np.ndarray  # (N, 4) SI in PARAMETER_NAMES order; NaN where the family lacks one
    probabilities: np.ndarray  # (N, 3) class probabilities
    pred_params: np.ndarray  # (N, 4) SI, the parameters the model predicts (used for any family)
    episode_ids: list[str] = field(default_factory=list)
    # (N, 4) one sigma SI of pred_params (the model's, for every parameter, whatever the family);
    # NaN where none. None: the model gives no uncertainties (no calibration is reported).
    pred_sigma: np.ndarray | None = None
    # (N,) frame slots each estimate had filled (fewer than the row's K where frames were missing or rejected
    # and no other frame came near their slot). None: all K (an evaluator that does not record it).
    frames_used: np.ndarray | None = None

    def __post_init__(self):
        self.true_class = np.asarray(self.true_class, dtype=np.int64)
        self.true_params = np.asarray(self.true_params, dtype=np.float64)
        self.probabilities = np.asarray(self.probabilities, dtype=np.float64)
        self.pred_params = np.asarray(self.pred_params, dtype=np.float64)
        n = len(self.true_class)
        expected = {"true_params": (n, len(PARAMETER_NAMES)), "probabilities": (n, len(FAMILIES)),
                    "pred_params": (n, len(PARAMETER_NAMES))}
        if self.pred_sigma is not None:
            self.pred_sigma = np.asarray(self.pred_sigma, dtype=np.float64)  # None (JSON null) -> NaN
            expected["pred_sigma"] = (n, len(PARAMETER_NAMES))
        if self.frames_used is not None:
            self.frames_used = np.asarray(self.frames_used, dtype=np.int64)
            expected["frames_used"] = (n,)
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Predictions.{name} has shape {getattr(self, name).shape}, expected {shape}")
        # argmax reads a NaN as the largest value: a clip without class probabilities would count as a
        # confident prediction of the first class with a NaN (jelly, for an all-NaN row) and raise its Acc.
        if bad := np.flatnonzero(~np.isfinite(self.probabilities).all(axis=1)).tolist():
            ids = [self.episode_ids[i] if self.episode_ids else str(i) for i in bad[:3]]
            raise ValueError(f"Predictions.probabilities are not finite for {len(bad)} clip(s) (first: "
                             f"{', '.join(ids)}); a clip without class probabilities has no predicted family")

    @property
    def pred_class(self) -> np.ndarray:
        return self.probabilities.argmax(axis=1)

    def episodes(self) -> list[dict]:
        """One JSON-ready record per clip, with the field names of ad_estimator.evaluate's
        predictions.json (parameters in PARAMETER_NAMES order): for per-episode analysis."""
        records = [{"episode_id": self.episode_ids[i] if self.episode_ids else str(i),
                    "true_material": FAMILIES[self.true_class[i]],
                    "true_parameters": {n: float(v) for n, v in zip(PARAMETER_NAMES, self.true_params[i])
                                        if not math.isnan(v)},
                    "material": FAMILIES[self.pred_class[i]],
                    "probabilities": self.probabilities[i].tolist(),
                    "raw_parameters": self.pred_params[i].tolist()} for i in range(len(self))]
        if self.pred_sigma is not None:
            for record, sigma in zip(records, self.pred_sigma):
                record["raw_uncertainties"] = sigma.tolist()
        if self.frames_used is not None:
            for record, used in zip(records, self.frames_used):
                record["frames_used"] = int(used)
        return records

    @classmethod
    def from_episodes(cls, records: list[dict], parameter_names=PARAMETER_NAMES) -> Predictions:
        """Back from per-episode records (episodes(), or a predictions.json's list for one K), so
        that saved predictions can be scored again without the model or the bags. `raw_*` lists
        are in `parameter_names` order (a predictions.json says which under "parameter_names").
        Sigmas come from `raw_uncertainties`, or else from `uncertainties` (the predicted family's
        own: the same for every correctly classified clip, all that calibration reads). `frames_used`
        where every record has it (ad_estimator.evaluate's do)."""
        sigma_key = next((k for k in ("raw_uncertainties", "uncertainties")
                          if records and all(k in r for r in records)), None)
        used = [r["frames_used"] for r in records] if records and all("frames_used" in r for r in records) else None
        return cls(
            true_class=[FAMILIES.index(r["true_material"]) for r in records],
            true_params=np.array([[r["true_parameters"].get(n, math.nan) for n in PARAMETER_NAMES] for r in records],
                                 float).reshape(len(records), len(PARAMETER_NAMES)),
            probabilities=np.array([r["probabilities"] for r in records], float).reshape(len(records), len(FAMILIES)),
            pred_params=in_metric_order([r["raw_parameters"] for r in records], parameter_names),
            episode_ids=[r["episode_id"] for r in records],
            pred_sigma=None if sigma_key is None else in_metric_order([r[sigma_key] for r in records], parameter_names),
            frames_used=used)

    def __len__(self) -> int:
        return len(self.true_class)


def in_metric_order(rows, parameter_names) -> np.ndarray:
    """(N, P) values in a model's parameter order (None or NaN where none) -> (N, 4) float in
    PARAMETER_NAMES order, mapped by name: a model may list its parameters in another order."""
    order = [list(parameter_names).index(n) for n in PARAMETER_NAMES]
    return np.array(rows, dtype=np.float64).reshape(-1, len(parameter_names))[:, order]


def _normalise(values: np.ndarray, lo: float, hi: float, scale: str) -> np.ndarray:
    # A non-positive prediction is infinitely wrong in log space; clip to keep the mean finite.
    return np.asarray(to_unit(np.clip(values, 1e-12, None) if scale == "log" else values, lo, hi, scale))


def regl1(pred: Predictions) -> np.ndarray:
    """Per clip: mean over the true family's sampled parameters of |pred_n - true_n|, each
    normalised to [0, 1] over that family's own sampling range (log space for E and yield)."""
    out = np.zeros(len(pred))
    for c, (family, ranges) in enumerate(family_ranges().items()):
        rows = pred.true_class == c
        if not rows.any():
            continue
        errors = []
        for name, (lo, hi, scale) in ranges.items():
            j = PARAMETER_NAMES.index(name)
            errors.append(np.abs(_normalise(pred.pred_params[rows, j], lo, hi, scale)
                                 - _normalise(pred.true_params[rows, j], lo, hi, scale)))
        out[rows] = np.mean(errors, axis=0)
    return out


def regl1_from_errors(errors: dict[str, dict[str, float]], ranges: dict | None = None,
                      log_base: float = math.e) -> float:
    """The RegL1 that a table row's parameter errors imply (family -> parameter -> its cell: log-MAE in
    `log_base` for E and yield, MAE for nu, MAE in degrees for phi), were every clip classified
    correctly and the families equally many: regl1's normalisation of each error (over
    `ranges`, family -> parameter -> (lo, hi, scale), by default each family's own, family_ranges()),
    averaged over the family's parameters, then over the families. It is how a paper's RegL1
    cell is checked against its own row."""
    ranges = family_ranges() if ranges is None else ranges
    per_family = []
    for family, cells in errors.items():
        normalised = []
        for name, error in cells.items():
            lo, hi, scale = ranges[family][name]
            if ERROR_KIND[name] == "log_mae":
                error = error * math.log(log_base)  # natural-log units, as _normalise
            elif ERROR_KIND[name] == "mae_deg":
                error = math.radians(error)
            normalised.append(error / (math.log(hi / lo) if scale == "log" else hi - lo))
        per_family.append(sum(normalised) / len(normalised))
    return sum(per_family) / len(per_family)


def parameter_error(name: str, pred: np.ndarray, true: np.ndarray) -> float:
    if len(true) == 0:
        return float("nan")
    kind = ERROR_KIND[name]
    if kind == "log_mae":
        return float(np.mean(np.abs(np.log(np.clip(pred, 1e-12, None)) - np.log(true))))
    if kind == "mae_deg":
        return float(np.degrees(np.mean(np.abs(pred - true))))
    return float(np.mean(np.abs(pred - true)))


def compute_metrics(pred: Predictions) -> dict:
    """Per family: n, Acc, parameter errors over correctly classified clips (the paper's
    convention) and over all clips of the family; per-family and overall RegL1."""
    ranges = family_ranges()
    per_clip_regl1 = regl1(pred)
    pred_class = pred.pred_class
    families = {}
    for c, family in enumerate(FAMILIES):
        rows = pred.true_class == c
        correct = rows & (pred_class == c)
        entry = {"n": int(rows.sum()), "acc": float(correct.sum() / rows.sum()) if rows.any() else float("nan"),
                 "regl1": float(per_clip_regl1[rows].mean()) if rows.any() else float("nan"),
                 "correct": {}, "all": {}}
        for name in ranges[family]:
            j = PARAMETER_NAMES.index(name)
            entry["correct"][name] = parameter_error(name, pred.pred_params[correct, j], pred.true_params[correct, j])
            entry["all"][name] = parameter_error(name, pred.pred_params[rows, j], pred.true_params[rows, j])
        families[family] = entry
    confusion = np.zeros((len(FAMILIES), len(FAMILIES)), dtype=np.int64)
    np.add.at(confusion, (pred.true_class, pred_class), 1)
    return {
        "n": len(pred),
        "accuracy": float((pred_class == pred.true_class).mean()) if len(pred) else float("nan"),
        "regl1": float(per_clip_regl1.mean()) if len(pred) else float("nan"),
        "families": families,
        "confusion": confusion.tolist(),
    }


#: Fraction of a Gaussian within one and two sigma: what a calibrated uncertainty's coverage gives.
GAUSSIAN_COVERAGE = {1: math.erf(1 / math.sqrt(2)), 2: math.erf(2 / math.sqrt(2))}


def uncertainty_calibration(pred: Predictions) -> dict | None:
    """Whether the model's one-sigma uncertainties are honest; None when it gives none.

    Per family and sampled parameter, over the family's correctly classified clips (the paper's
    convention) whose sigma is finite and positive: the standardised error z = (ln pred - ln true) /
    (sigma / pred) for the log-MAE parameters (E, yield: the SI sigma of a log-scaled output is
    pred x its log-space sigma, delta method) and (pred - true) / sigma otherwise; n; coverage_1sigma
    and coverage_2sigma, the fractions with |z| <= 1 and <= 2 (a calibrated Gaussian: 0.683, 0.954;
    lower: overconfident, higher: underconfident); median_sigma and error (as the paper table, over
    the same clips) in the reporting units: log units for E and yield, nu as is, phi in degrees.
    NaN where n == 0."""
    if pred.pred_sigma is None or not np.isfinite(pred.pred_sigma).any():
        return None
    pred_class = pred.pred_class
    result = {}
    for c, (family, ranges) in enumerate(family_ranges().items()):
        correct = (pred.true_class == c) & (pred_class == c)
        result[family] = {}
        for name in ranges:
            j = PARAMETER_NAMES.index(name)
            value, true, sigma = pred.pred_params[:, j], pred.true_params[:, j], pred.pred_sigma[:, j]
            use = correct & np.isfinite(sigma) & (sigma > 0) & np.isfinite(value) & np.isfinite(true)
            kind = ERROR_KIND[name]
            if kind == "log_mae":
                use &= (value > 0) & (true > 0)
            n = int(use.sum())
            if n == 0:
                result[family][name] = {"n": 0, **dict.fromkeys(
                    ("error", "median_sigma", "coverage_1sigma", "coverage_2sigma"), float("nan"))}
                continue
            value, true, sigma = value[use], true[use], sigma[use]
            if kind == "log_mae":  # log space: the residual in log units, the sigma relative
                residual, scale = np.log(value) - np.log(true), sigma / value
            else:
                residual, scale = value - true, sigma
            z = np.abs(residual) / scale
            units = math.degrees(1.0) if kind == "mae_deg" else 1.0
            result[family][name] = {
                "n": n,
                "error": parameter_error(name, value, true),
                "median_sigma": float(np.median(scale) * units),
                "coverage_1sigma": float(np.mean(z <= 1.0)),
                "coverage_2sigma": float(np.mean(z <= 2.0)),
            }
    return result


def evaluate_all(by_frames: dict[int, Predictions]) -> dict:
    """Metrics for every number of observed frames; keys of the result are str(K). The full-clip
    entry (the largest K) also holds "calibration" (uncertainty_calibration) when the predictions
    carry sigmas; older metrics files lack it, so readers must not rely on it."""
    results = {str(k): compute_metrics(p) for k, p in sorted(by_frames.items(), reverse=True)}
    if by_frames:
        full_k = max(by_frames)
        if (calibration := uncertainty_calibration(by_frames[full_k])) is not None:
            results[str(full_k)]["calibration"] = calibration
    return results


def table_columns() -> list[tuple[str, str, str | None]]:
    """(family, label, parameter or None for Acc) in the paper's column order."""
    ranges = family_ranges()
    cols = []
    for family in FAMILIES:
        cols.append((family, f"{family} Acc", None))
        cols += [(family, f"{family} {_SHORT[n]}", n) for n in ranges[family]]
    return cols


def read_frames_json(path: str | Path, what: str, hint: str) -> dict:
    """A JSON file keyed by number of frames ({"frames": {"25": ...}, ...}: the metrics.json and
    predictions.json that evaluations write). Every way it can be unusable is a one-line ValueError
    naming the file, what it should be (`what`, e.g. "a metrics file") and what to pass (`hint`)."""
    path = Path(path)
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path} does not exist; {hint}") from None
    except OSError as exc:
        raise ValueError(f"{path} cannot be read ({exc.strerror}); {hint}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); {hint}") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("frames"), dict):
        raise ValueError(f'{path} has no "frames" object, so it is not {what}; {hint}')
    return saved


def json_text(obj, indent: int = 2) -> str:
    """Strict JSON (what jq and browsers read): NaN, meaning "no clip qualified" (or no value), becomes null, and
    so does an infinity (say, a model's sigma that overflowed), which JSON has no number for either: it raised
    ValueError after all the work. Read back, null is NaN (Predictions.from_episodes), which metrics treat as no
    value, as they do an infinite sigma."""

    def clean(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value

    return json.dumps(clean(obj), indent=indent, allow_nan=False)


def table_cell(value: float | None) -> str:
    """A table cell; n/a where no clip qualified (e.g. no correctly classified clip of a family):
    NaN in memory, null in a metrics.json read back."""
    return "n/a" if value is None or math.isnan(value) else f"{value:.3f}"


def table_labels() -> list[str]:
    """The paper table's value columns: table_columns()'s labels, then RegL1."""
    return [label for _, label, _ in table_columns()] + ["RegL1"]


def table_fields(which: str = "correct") -> list[tuple[str, ...]]:
    """Where each of table_labels()' values sits in a metrics entry (one number of frames), as keys."""
    return [("families", family, "acc") if name is None else ("families", family, which, name)
            for family, _, name in table_columns()] + [("regl1",)]


def table_values(entry: dict, which: str = "correct") -> list[float | None]:
    """One metrics entry's (one number of frames) values in table_labels() order; None where a
    metrics.json read back has null."""
    return [functools.reduce(lambda value, key: value[key], keys, entry) for keys in table_fields(which)]


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(row) + " |" for row in rows)]


def format_table(results: dict, title: str = "", which: str = "correct") -> str:
    """The paper's table layout as Markdown: one row per number of observed frames (the
    full clip first, then the temporal-OOD rows). `which` is "correct" (paper) or "all". A row
    that scored no clip (every episode left out of it) stays, with "no clips" in its cells."""
    lines = []
    if title:
        lines.append(f"**{title}** (parameter errors over {'correctly classified' if which == 'correct' else 'all'} "
                     "clips of each family; E, yield: log-MAE; nu: MAE; phi: MAE in degrees; RegL1: over all clips)")
        lines.append("")
    lines += markdown_table(["frames", *table_labels()],
                            [[str(k), *(["no clips"] * len(table_labels()) if m["n"] == 0
                                        else map(table_cell, table_values(m, which)))]
                             for k, m in sorted(results.items(), key=lambda kv: -int(kv[0]))])
    return "\n".join(lines)


def format_calibration(calibration: dict, frames: int = FRAME_COUNT) -> str:
    """uncertainty_calibration's result (or a metrics.json's "calibration", nulls and all) as a
    Markdown section."""
    one, two = (f"{GAUSSIAN_COVERAGE[k]:.3f}" for k in (1, 2))
    lines = [f"## Uncertainty calibration ({frames} frames)", "",
             "The model's one-sigma uncertainties against its errors, over correctly classified clips of each "
             "family: the fraction of clips whose error is within one (two) of their own sigma. Lower than a "
             "calibrated Gaussian's: the sigmas are too small (overconfident); higher: too large. Error and "
             "median sigma in the table's units (E, yield: log units, i.e. relative; nu: absolute; "
             "phi: degrees).", "",
             *markdown_table(["family", "parameter", "n", "error", "median sigma",
                              f"within ±1σ ({one} if calibrated)", f"within ±2σ ({two})"],
                             [[family, _SHORT.get(name, name), str(c["n"]),
                               *(table_cell(c[key]) for key in ("error", "median_sigma", "coverage_1sigma",
                                                                "coverage_2sigma"))]
                              for family, parameters in calibration.items() for name, c in parameters.items()])]
    return "\n".join(lines)


def _pearson(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson's r; NaN where undefined (fewer than 2 clips, a non-finite value, or a constant)."""
    if len(x) < 2 or not (np.isfinite(x).all() and np.isfinite(y).all()) or np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def error_by_true_value(pred: Predictions, bins: int = 3) -> dict:
    """Where the parameter errors lie: per family (those with clips) and sampled parameter, over all
    clips of the true family (the "all" convention): n; "bins", `bins` equal-count bins of the true
    value, lowest first, each with its n, true-value range lo..hi (SI) and error; the error over all
    ("all"); "constant_guess", the error of always predicting the middle of the family's range (the
    log-midpoint for log-MAE parameters), what a model that learned nothing scores; "correlation",
    Pearson's r of predicted and true (log space for log-MAE parameters), NaN where undefined.
    Errors as parameter_error gives them (phi in degrees)."""
    result = {}
    for c, (family, ranges) in enumerate(family_ranges().items()):
        rows = pred.true_class == c
        if not rows.any():
            continue
        result[family] = {}
        for name, (lo, hi, _) in ranges.items():
            j = PARAMETER_NAMES.index(name)
            known = rows & np.isfinite(pred.true_params[:, j])  # a clip without this truth cannot be placed
            p, t = pred.pred_params[known, j], pred.true_params[known, j]
            if not len(t):
                continue
            log = ERROR_KIND[name] == "log_mae"
            middle = math.sqrt(lo * hi) if log else (lo + hi) / 2
            # Bin by rank (mid-rank quantile), not by value: counts differ by at most one even where true
            # values tie, and uneven counts stay symmetric (10 clips: 3/4/3; 11: 4/3/4; one clip: the middle).
            rank_bin = ((np.arange(len(t)) + 0.5) * bins / len(t)).astype(int)
            order = np.argsort(t, kind="stable")
            groups = [order[rank_bin == b] for b in range(bins)]
            result[family][name] = {
                "n": len(t),
                "bins": [{"n": len(g), "lo": float(t[g].min()) if len(g) else float("nan"),
                          "hi": float(t[g].max()) if len(g) else float("nan"),
                          "error": parameter_error(name, p[g], t[g])} for g in groups],
                "all": parameter_error(name, p, t),
                "constant_guess": parameter_error(name, np.full_like(t, middle), t),
                "correlation": _pearson(np.log(np.clip(p, 1e-12, None)), np.log(t)) if log else _pearson(p, t),
            }
    return result


def format_error_by_true_value(table: dict, frames: int) -> str:
    """error_by_true_value's result as a Markdown section: each bin's error with its true-value range
    (phi in degrees), the error over all clips, the constant guess's error and the correlation."""
    k = max((len(e["bins"]) for parameters in table.values() for e in parameters.values()), default=3)
    names = ["lowest third", "middle third", "highest third"] if k == 3 else [f"bin {i + 1}" for i in range(k)]

    def cell(name: str, b: dict) -> str:
        if b["n"] == 0:
            return "n/a"
        lo, hi = (math.degrees(b[key]) if name == "friction_angle" else b[key] for key in ("lo", "hi"))
        return f"{table_cell(b['error'])} ({lo:.3g}–{hi:.3g})"

    rows = [[family, _SHORT.get(name, name), str(e["n"]), *(cell(name, b) for b in e["bins"]),
             *(table_cell(e[key]) for key in ("all", "constant_guess", "correlation"))]
            for family, parameters in table.items() for name, e in parameters.items()]
    return "\n".join([
        f"## Error by true value ({frames} frames)", "",
        "Parameter errors over all clips of each family, in equal-count bins of the true value (its range in "
        "parentheses: SI, phi in degrees), against a constant guess at the middle of the family's range (what a "
        "model that learned nothing scores) and the correlation of predicted and true (log space for E, yield); "
        "n: the clips of the family.",
        "", *markdown_table(["family", "parameter", "n", *names, "all", "constant guess", "correlation"], rows)])


#: Each family's colour in the report's plots (matplotlib's default cycle would give plasticine's yield
#: and sand's phi jelly's colour, and shift every family in the RegL1 plot).
FAMILY_COLORS = {family: f"C{i}" for i, family in enumerate(FAMILIES)}


def _axis_label(name: str) -> str:
    """A parameter's axis label in the plots, with its SI unit (phi in degrees, as in the tables)."""
    unit = "degrees" if name == "friction_angle" else PARAMETER_UNITS[name]
    return f"{_SHORT[name]} ({unit})" if unit else _SHORT[name]


def _family_label(family: str, clips: int) -> str:
    """A family's legend entry: a family without clips is named as absent, not drawn as if it had no error."""
    return family if clips else f"{family} (no clips)"


def _plot_confusion(ax, confusion: np.ndarray) -> None:
    """Clip counts, true family down the rows (each with its number of clips: 0 for a family absent
    from the evaluation), predicted across."""
    ax.imshow(confusion, cmap="Blues")
    ax.set_xticks(range(len(FAMILIES)), FAMILIES)
    ax.set_yticks(range(len(FAMILIES)), [f"{f}\n({n} clips)" for f, n in zip(FAMILIES, confusion.sum(axis=1))])
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    for i in range(confusion.shape[0]):
        for j in range(confusion.shape[1]):
            ax.text(j, i, str(confusion[i, j]), ha="center", va="center",
                    color="white" if confusion[i, j] > confusion.max() / 2 else "black")


def _frames_per_clip(full: Predictions, frames: int) -> str:
    """The frames of the full-clip row's clips: `frames`, its K (the model's frame count, or the clips'
    where shorter), and where the evaluator recorded frames_used, the clips that filled fewer slots."""
    used = full.frames_used
    if used is None or (used >= frames).all():
        return f"frames per clip: {frames}"
    short = used[used < frames]
    filled = f"{short.min()}" if short.min() == short.max() else f"{short.min()} to {short.max()}"
    return (f"frames per clip: {frames}, but {len(short)} clip(s) filled only {filled} of the {frames} frame slots "
            "(frames missing or rejected)")


def write_report(by_frames: dict[int, Predictions], out_dir: str | Path, title: str = "evaluation") -> dict:
    """Writes metrics.json, report.md and the plots (confusion matrix, predicted vs true per
    parameter, RegL1 against frames observed) into out_dir; returns the metrics. The largest K is
    the full clip; a row without clips (a temporal-OOD row every episode was left out of) is kept,
    said as such."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = evaluate_all(by_frames)
    full_k = max(by_frames)
    full = by_frames[full_k]
    (out / "metrics.json").write_text(json_text({"title": title, "frames": results}))

    fig, ax = plt.subplots(figsize=(4, 4))
    _plot_confusion(ax, np.asarray(results[str(full_k)]["confusion"]))
    ax.set_title(f"confusion, clip counts ({full_k} frames)")
    fig.tight_layout()
    fig.savefig(out / "confusion.png", dpi=100)
    plt.close(fig)

    ranges = family_ranges()
    fig, axes = plt.subplots(1, len(PARAMETER_NAMES), figsize=(4 * len(PARAMETER_NAMES), 4))
    for j, name in enumerate(PARAMETER_NAMES):
        ax = axes[j]
        families = [f for f in FAMILIES if name in ranges[f]]
        for family in families:
            rows = full.true_class == FAMILIES.index(family)
            t, p = full.true_params[rows, j], full.pred_params[rows, j]
            if name == "friction_angle":
                t, p = np.degrees(t), np.degrees(p)
            ax.scatter(t, p, s=8, label=_family_label(family, int(rows.sum())),
                       color=FAMILY_COLORS[family])  # one colour per family in every plot
        lims = [min(ranges[f][name][0] for f in families), max(ranges[f][name][1] for f in families)]
        if name == "friction_angle":
            lims = list(np.degrees(lims))
        ax.plot(lims, lims, "k--", lw=1)
        if ERROR_KIND[name] == "log_mae":
            ax.set_xscale("log")
            ax.set_yscale("log")
        ax.set_xlabel(f"true {_axis_label(name)}")
        ax.set_ylabel(f"predicted {_axis_label(name)}")
        ax.legend(fontsize=7)
    fig.suptitle(f"predicted vs true ({full_k} frames; every clip of each true family, misclassified ones too; "
                 "dashed: predicted = true)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "pred_vs_true.png", dpi=100)
    plt.close(fig)

    ks = sorted(by_frames)
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(ks, [results[str(k)]["regl1"] for k in ks], "o-", label="all", color="k")
    for family in FAMILIES:
        ax.plot(ks, [results[str(k)]["families"][family]["regl1"] for k in ks], ".--",
                label=_family_label(family, max(results[str(k)]["families"][family]["n"] for k in ks)),
                color=FAMILY_COLORS[family])
    ax.set_xlabel("frames observed")
    ax.set_ylabel("RegL1 (0 = exact)")
    ax.set_title("RegL1 over all clips, by true family", fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "regl1_vs_frames.png", dpi=100)
    plt.close(fig)

    clips = f"Clips: {len(full)}; {_frames_per_clip(full, full_k)}."
    if fewer := [f"{k} frames: {len(by_frames[k]) or 'no clips'}" for k in sorted(by_frames, reverse=True)
                 if len(by_frames[k]) != len(full)]:  # e.g. episodes left out of a temporal-OOD row
        clips += f" Rows with another number of clips than the {full_k}-frame row's: {', '.join(fewer)}."
    md = [f"# {title}", "", format_table(results, "Paper convention"), "",
          format_table(results, "Over all clips of each family", which="all"), "",
          clips, "",
          "RegL1: each clip's mean error over its true family's sampled parameters, each normalised by the "
          "width of that family's sampling range (log space for E, yield), averaged over the clips.", ""]
    if (calibration := results[str(full_k)].get("calibration")) is not None:
        md += [format_calibration(calibration, full_k), ""]
    md += [format_error_by_true_value(error_by_true_value(full), full_k), ""]
    md += ["## Plots", "",
           f"Confusion matrix ({full_k} frames, {len(full)} clips): clip counts, rows the true family (with its "
           "number of clips), columns the predicted one.", "", "![confusion](confusion.png)", "",
           f"Predicted against true parameters ({full_k} frames): every clip of each true family, misclassified "
           "ones too (the parameters the model estimates whatever family it predicts); E and yield in Pa on "
           "log axes, nu, phi in degrees; the dashed line is predicted = true over the families' ranges. "
           "A family has one colour in every plot; one without clips is marked \"(no clips)\".", "",
           "![predicted vs true](pred_vs_true.png)", "",
           "RegL1 against the frames observed (the tables' rows: the full clip and the temporal-OOD prefixes), "
           "over all clips and per true family.", "", "![RegL1 vs frames](regl1_vs_frames.png)", ""]
    (out / "report.md").write_text("\n".join(md))
    return results
