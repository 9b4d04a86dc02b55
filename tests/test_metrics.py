"""ad_estimator.metrics: the paper's metrics on hand-computed cases, the report files, no torch."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ad_estimator.metrics import (
    Predictions,
    compute_metrics,
    evaluate_all,
    family_ranges,
    format_table,
    json_text,
    regl1,
    regl1_from_errors,
    uncertainty_calibration,
    write_report,
)
from ad_sim.materials import FAMILIES, PARAMETER_NAMES

NAN = float("nan")
JELLY = [1e5, 0.3, NAN, NAN]
PLASTICINE = [1e5, 0.4, 3000.0, NAN]
SAND = [1e5, 0.3, NAN, math.radians(30.0)]


def _onehot(classes):
    p = np.full((len(classes), 3), 0.1)
    p[np.arange(len(classes)), classes] = 0.8
    return p


def _fill(rows):
    """Predictions need a value for every parameter; unused ones are whatever the head says."""
    return np.where(np.isnan(rows), 1.0, rows)


def test_perfect_predictions_score_zero():
    true = np.array([JELLY, PLASTICINE, SAND])
    pred = Predictions([0, 1, 2], true, _onehot([0, 1, 2]), _fill(true))
    m = compute_metrics(pred)
    assert m["accuracy"] == 1.0 and m["regl1"] == 0.0
    for family in FAMILIES:
        assert m["families"][family]["acc"] == 1.0
        assert all(v == 0.0 for v in m["families"][family]["correct"].values())
    assert m["confusion"] == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]


def test_errors_match_hand_computation():
    # jelly 0: E off by e^0.5 (log error 0.5), nu off by 0.01; jelly 1: misclassified as sand,
    # E off by e^1; sand: phi off by 2 degrees.
    true = np.array([JELLY, JELLY, SAND])
    pred_params = _fill(true.copy())
    pred_params[0, 0] *= math.exp(0.5)
    pred_params[0, 1] += 0.01
    pred_params[1, 0] *= math.exp(1.0)
    pred_params[2, 3] += math.radians(2.0)
    pred = Predictions([0, 0, 2], true, _onehot([0, 2, 2]), pred_params)
    m = compute_metrics(pred)
    jelly = m["families"]["jelly"]
    assert jelly["acc"] == pytest.approx(0.5)
    # Paper convention: only the correctly classified jelly counts.
    assert jelly["correct"]["youngs_modulus"] == pytest.approx(0.5)
    assert jelly["correct"]["poissons_ratio"] == pytest.approx(0.01)
    # Over all jelly instances: mean of 0.5 and 1.0; nu errors 0.01 and 0.
    assert jelly["all"]["youngs_modulus"] == pytest.approx(0.75)
    assert jelly["all"]["poissons_ratio"] == pytest.approx(0.005)
    assert m["families"]["sand"]["correct"]["friction_angle"] == pytest.approx(2.0)
    assert set(jelly["correct"]) == {"youngs_modulus", "poissons_ratio"}  # family's own parameters only
    # RegL1 uses each family's own range: jelly E spans ln(100), nu spans 0.2; sand phi spans 35 deg.
    expected = [(0.5 / math.log(100.0) + 0.01 / 0.2) / 2, (1.0 / math.log(100.0)) / 2, 2.0 / 35.0]
    np.testing.assert_allclose(regl1(pred), expected, rtol=1e-9)
    assert m["regl1"] == pytest.approx(np.mean(expected))
    assert m["confusion"][0] == [1, 0, 1]


def test_plasticine_uses_its_own_range_not_the_union():
    true = np.array([PLASTICINE])
    pred_params = true.copy()
    pred_params[0, 1] += 0.013  # plasticine nu range is 0.35..0.48 (0.13 wide)
    pred = Predictions([1], true, _onehot([1]), _fill(pred_params))
    assert regl1(pred)[0] == pytest.approx(0.1 / 3)
    assert family_ranges()["sand"] == {"friction_angle": family_ranges()["sand"]["friction_angle"]}


def test_shape_mismatch_is_reported():
    with pytest.raises(ValueError, match="pred_params"):
        Predictions([0], np.array([JELLY]), _onehot([0]), np.ones((1, 3)))


def test_report_files_and_table(tmp_path):
    rng = np.random.default_rng(0)
    true = np.array([JELLY, PLASTICINE, SAND] * 4)
    classes = np.array([0, 1, 2] * 4)
    by_frames = {}
    for k in (25, 24, 22, 18, 15):
        noisy = _fill(true) * np.exp(rng.normal(0, 0.05 * (26 - k), size=true.shape))
        by_frames[k] = Predictions(classes, true, _onehot(classes), noisy)
    results = write_report(by_frames, tmp_path, "unit test")
    for name in ("metrics.json", "report.md", "confusion.png", "pred_vs_true.png", "regl1_vs_frames.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert set(saved["frames"]) == {"25", "24", "22", "18", "15"}
    assert saved["frames"]["15"]["regl1"] > saved["frames"]["25"]["regl1"]  # more noise with fewer frames
    table = format_table(results)
    lines = table.splitlines()
    assert lines[0].startswith("| frames | jelly Acc | jelly E | jelly nu | plasticine Acc")
    assert [line.split("|")[1].strip() for line in lines[2:]] == ["25", "24", "22", "18", "15"]
    assert "RegL1" in lines[0]
    assert evaluate_all(by_frames)["25"]["n"] == 12


def test_report_json_is_strict_with_null_where_no_clip_qualified(tmp_path):
    """No sand clip classified as sand: its phi error is undefined. The JSON says null (not NaN,
    which jq, browsers and strict parsers reject) and the table says n/a."""
    true = np.array([JELLY, SAND])
    results = write_report({25: Predictions(np.array([0, 2]), true, _onehot([0, 0]), _fill(true))}, tmp_path, "t")
    text = (tmp_path / "metrics.json").read_text()
    saved = json.loads(text, parse_constant=lambda name: pytest.fail(f"non-standard JSON constant {name}"))
    assert saved["frames"]["25"]["families"]["sand"]["correct"]["friction_angle"] is None
    assert "n/a" in format_table(results)


# --------------------------------------------------------------------------- uncertainty calibration

E, NU, PHI = 0, 1, 3  # columns in PARAMETER_NAMES order


def _gaussian_predictions(n: int, sigma_scale: float = 1.0, seed: int = 0) -> Predictions:
    """n clips per family, all correctly classified. Each prediction is the truth plus a Gaussian error
    whose one sigma the model reports (times sigma_scale): in log space for E and yield (the SI sigma is
    pred x the log-space sigma, as the model's delta method gives), in SI for nu and phi."""
    rng = np.random.default_rng(seed)
    classes = np.repeat([0, 1, 2], n)
    true = np.array([JELLY] * n + [PLASTICINE] * n + [SAND] * n)
    sigma_log = rng.uniform(0.1, 0.8, size=true.shape)  # per clip: a heteroscedastic model
    sigma_lin = rng.uniform(0.005, 0.05, size=true.shape)
    noise = rng.standard_normal(true.shape)
    pred = _fill(true).copy()
    sigma = np.full(true.shape, np.nan)
    for j in (0, 2):  # E, yield: log space
        pred[:, j] = _fill(true)[:, j] * np.exp(sigma_log[:, j] * noise[:, j])
        sigma[:, j] = pred[:, j] * sigma_log[:, j] * sigma_scale
    for j in (1, 3):  # nu, phi: linear
        pred[:, j] = _fill(true)[:, j] + sigma_lin[:, j] * noise[:, j]
        sigma[:, j] = sigma_lin[:, j] * sigma_scale
    return Predictions(classes, true, _onehot(classes), pred, pred_sigma=sigma)


def test_honest_sigmas_cover_like_a_gaussian_and_small_ones_do_not():
    calibration = uncertainty_calibration(_gaussian_predictions(4000))
    assert list(calibration) == list(FAMILIES)
    for family, parameters in calibration.items():
        assert list(parameters) == list(family_ranges()[family])  # the family's sampled parameters only
        for name, c in parameters.items():
            assert c["n"] == 4000, (family, name)
            assert c["coverage_1sigma"] == pytest.approx(0.683, abs=0.02), (family, name)
            assert c["coverage_2sigma"] == pytest.approx(0.954, abs=0.02), (family, name)
    # Reporting units: E log units (the log-space sigma, median of U(0.1, 0.8) ~ 0.45), phi in degrees.
    assert calibration["jelly"]["youngs_modulus"]["median_sigma"] == pytest.approx(0.45, abs=0.03)
    assert calibration["sand"]["friction_angle"]["median_sigma"] == pytest.approx(math.degrees(0.0275), rel=0.05)
    assert calibration["jelly"]["poissons_ratio"]["median_sigma"] == pytest.approx(0.0275, rel=0.05)
    # The error is the paper table's: mean |ln pred - ln true| for E, |pred - true| in degrees for phi.
    pred = _gaussian_predictions(4000)
    m = compute_metrics(pred)
    for family, parameters in calibration.items():
        for name, c in parameters.items():
            assert c["error"] == pytest.approx(m["families"][family]["correct"][name], rel=1e-12)

    overconfident = uncertainty_calibration(_gaussian_predictions(4000, sigma_scale=1 / 3))
    for family, parameters in overconfident.items():
        for name, c in parameters.items():
            # |z| <= 1 with sigma / 3: |N(0,1)| <= 1/3, 0.26; |z| <= 2: 0.50
            assert c["coverage_1sigma"] == pytest.approx(0.261, abs=0.03), (family, name)
            assert c["coverage_2sigma"] == pytest.approx(0.495, abs=0.03), (family, name)


def test_log_parameters_are_standardised_in_log_space():
    """E = 1e5 predicted as 3e5 with an SI sigma of 2.4e5 (a log-space sigma of 2.4e5 / 3e5 = 0.8): the
    log error ln 3 = 1.10 is outside one sigma (1.37 sigma), where the linear rule would put it inside
    ((3e5 - 1e5) / 2.4e5 = 0.83). nu stays linear: 0.05 off with sigma 0.04 is outside one sigma."""
    true = np.array([JELLY])
    pred_params = _fill(true.copy())
    pred_params[0, E], pred_params[0, NU] = 3e5, 0.35
    sigma = np.array([[2.4e5, 0.04, NAN, NAN]])
    c = uncertainty_calibration(Predictions([0], true, _onehot([0]), pred_params, pred_sigma=sigma))["jelly"]
    assert c["youngs_modulus"]["coverage_1sigma"] == 0.0 and c["youngs_modulus"]["coverage_2sigma"] == 1.0
    assert c["youngs_modulus"]["median_sigma"] == pytest.approx(0.8)  # log units: sigma / pred
    assert c["youngs_modulus"]["error"] == pytest.approx(math.log(3.0))
    assert c["poissons_ratio"]["coverage_1sigma"] == 0.0 and c["poissons_ratio"]["coverage_2sigma"] == 1.0
    assert c["poissons_ratio"]["median_sigma"] == pytest.approx(0.04)
    # And the other way round: 1e5 predicted as 1e5 / 3 with a log sigma of 1.2 >= ln 3 is within one
    # sigma, where linearly (1e5 - 3.3e4) / 4e4 = 1.67 is not.
    pred_params[0, E] = 1e5 / 3
    sigma[0, E] = 1.2 * pred_params[0, E]
    c = uncertainty_calibration(Predictions([0], true, _onehot([0]), pred_params, pred_sigma=sigma))["jelly"]
    assert c["youngs_modulus"]["coverage_1sigma"] == 1.0


def test_wrong_class_clips_and_clips_without_sigma_are_left_out():
    true = np.array([JELLY, JELLY, JELLY, SAND])
    pred_params = _fill(true.copy())
    pred_params[:3, E] *= math.exp(0.1)  # within one log-space sigma of 0.2 ...
    pred_params[1, E] = true[1, E] * math.exp(5.0)  # ... except the misclassified clip, far off
    sigma = np.array([[0.2 * v, 0.01, NAN, NAN] for v in pred_params[:, E]])
    sigma[2, E] = NAN  # no sigma: left out of E (its nu still counts)
    pred = Predictions([0, 0, 0, 2], true, _onehot([0, 2, 0, 0]), pred_params, pred_sigma=sigma)
    c = uncertainty_calibration(pred)
    assert c["jelly"]["youngs_modulus"] == {"n": 1, "error": pytest.approx(0.1), "median_sigma": pytest.approx(0.2),
                                            "coverage_1sigma": 1.0, "coverage_2sigma": 1.0}
    assert c["jelly"]["poissons_ratio"]["n"] == 2
    # No sand clip classified as sand: n = 0 and NaN, which metrics.json writes as null.
    assert c["sand"]["friction_angle"]["n"] == 0 and math.isnan(c["sand"]["friction_angle"]["coverage_1sigma"])
    # A zero or negative sigma is no uncertainty either.
    sigma[0, E] = 0.0
    assert uncertainty_calibration(Predictions([0, 0, 0, 2], true, _onehot([0, 2, 0, 0]), pred_params,
                                               pred_sigma=sigma))["jelly"]["youngs_modulus"]["n"] == 0


def test_no_sigma_means_no_calibration():
    true = np.array([JELLY, SAND])
    assert uncertainty_calibration(Predictions([0, 2], true, _onehot([0, 2]), _fill(true))) is None
    all_nan = np.full((2, 4), NAN)  # a model without a log-variance output
    assert uncertainty_calibration(Predictions([0, 2], true, _onehot([0, 2]), _fill(true), pred_sigma=all_nan)) is None
    # None in the JSON a predictions.json gives reads as NaN.
    with_nulls = [[0.1, None, None, None], [None, None, None, 0.02]]
    pred = Predictions([0, 2], true, _onehot([0, 2]), _fill(true), pred_sigma=with_nulls)
    assert np.isnan(pred.pred_sigma[0, 1]) and pred.episodes()[1]["raw_uncertainties"][3] == 0.02
    assert "raw_uncertainties" not in Predictions([0], true[:1], _onehot([0]), _fill(true[:1])).episodes()[0]
    with pytest.raises(ValueError, match="pred_sigma"):
        Predictions([0], true[:1], _onehot([0]), _fill(true[:1]), pred_sigma=np.ones((1, 3)))


def test_report_has_a_calibration_section_for_the_full_clip_only(tmp_path):
    by_frames = {25: _gaussian_predictions(50), 18: _gaussian_predictions(50, sigma_scale=0.5, seed=1)}
    results = write_report(by_frames, tmp_path / "with", "calibrated")
    text = (tmp_path / "with" / "metrics.json").read_text()
    saved = json.loads(text, parse_constant=lambda name: pytest.fail(f"non-standard JSON constant {name}"))
    assert "calibration" in saved["frames"]["25"] and "calibration" not in saved["frames"]["18"]
    assert saved["frames"]["25"]["calibration"] == json.loads(json_text(results["25"]["calibration"]))
    assert results["25"]["calibration"] == uncertainty_calibration(by_frames[25])
    report = (tmp_path / "with" / "report.md").read_text()
    section = report.index("## Uncertainty calibration (25 frames)")
    assert section > report.index("**Over all clips of each family**")  # after the two tables
    header = "| family | parameter | n | error | median sigma | within ±1σ (0.683 if calibrated) | within ±2σ (0.954) |"
    assert header in report
    jelly_e = saved["frames"]["25"]["calibration"]["jelly"]["youngs_modulus"]
    assert (f"| jelly | E | 50 | {jelly_e['error']:.3f} | {jelly_e['median_sigma']:.3f} | "
            f"{jelly_e['coverage_1sigma']:.3f} | {jelly_e['coverage_2sigma']:.3f} |") in report
    assert "| sand | phi | 50 |" in report
    # The older keys are as before; the table ignores the new one.
    assert set(saved["frames"]["18"]) == {"n", "accuracy", "regl1", "families", "confusion"}
    assert format_table(results).splitlines()[2].startswith("| 25 |")

    # No sigmas (an older model, or Predictions built without them): no section, no key.
    plain = {k: Predictions(p.true_class, p.true_params, p.probabilities, p.pred_params) for k, p in by_frames.items()}
    write_report(plain, tmp_path / "without", "no sigma")
    assert "calibration" not in json.loads((tmp_path / "without" / "metrics.json").read_text())["frames"]["25"]
    assert "Uncertainty calibration" not in (tmp_path / "without" / "report.md").read_text()


def test_metrics_module_never_imports_torch():
    code = "import sys, ad_estimator.metrics; sys.exit(1 if 'torch' in sys.modules else 0)"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr


def test_saved_episodes_score_again_as_they_were_scored(tmp_path):
    """Predictions.from_episodes reads back what episodes() writes, and a real predictions.json of
    the estimator's runtime (the bundled model on the unseen split) gives its own metrics file."""
    rng = np.random.default_rng(5)
    classes = rng.integers(0, 3, 60)
    true = np.array([(JELLY, PLASTICINE, SAND)[c] for c in classes])
    pred = Predictions(classes, true, rng.dirichlet(np.ones(3), 60), _fill(true) * rng.uniform(0.8, 1.2, true.shape),
                       episode_ids=[f"e{i}" for i in range(60)], pred_sigma=_fill(true) * 0.1)
    records = json.loads(json_text(pred.episodes()))  # as written to disk: NaN becomes null
    again = Predictions.from_episodes(records)
    assert compute_metrics(again) == compute_metrics(pred)
    assert uncertainty_calibration(again) == uncertainty_calibration(pred)
    # Only the predicted family's own sigmas (`uncertainties`, as ad_estimator.evaluate also writes):
    # calibration reads correctly classified clips only, so it is the same.
    for record in records:
        record["uncertainties"] = record.pop("raw_uncertainties")
    assert uncertainty_calibration(Predictions.from_episodes(records)) == uncertainty_calibration(pred)
    # A model listing its parameters in another order is mapped by name.
    names = ("friction_angle", "youngs_modulus", "poissons_ratio", "yield_stress")
    for record in records:
        record["raw_parameters"] = [record["raw_parameters"][PARAMETER_NAMES.index(n)] for n in names]
    assert compute_metrics(Predictions.from_episodes(records, names)) == compute_metrics(pred)
    # Records without any sigma: no calibration.
    bare = [{k: v for k, v in r.items() if k != "uncertainties"} for r in records]
    assert uncertainty_calibration(Predictions.from_episodes(bare, names)) is None
    folder = Path(__file__).resolve().parents[1] / "docs" / "results" / "paper" / "streaming_earlier3_reg2_unseen"
    saved = Predictions.from_episodes(json.loads((folder / "estimator_runtime_predictions.json").read_text())["frames"]["25"])
    measured = json.loads((folder / "estimator_runtime.json").read_text())["frames"]["25"]
    scored = compute_metrics(saved)
    assert scored["confusion"] == measured["confusion"] and scored["regl1"] == pytest.approx(measured["regl1"], abs=1e-12)
    assert uncertainty_calibration(saved)["jelly"]["youngs_modulus"]["n"] == measured["confusion"][0][0]


def test_regl1_implied_by_a_rows_errors_is_the_regl1_of_its_clips():
    """With every clip classified correctly and the families equally many, the RegL1 that the table's
    error cells imply is exactly the clips' RegL1; in log10 cells the same errors read ln(10) times
    smaller; over other ranges (the union of the families') it normalises by those."""
    rng = np.random.default_rng(3)
    true, pred = [], []
    for row in [JELLY, PLASTICINE, SAND] * 4:
        row = np.array(row)
        true.append(row)
        noisy = row * np.exp(rng.normal(0, 0.3, 4))  # E, yield off by a log factor; nu, phi off by a fraction
        pred.append(np.where(np.isnan(row), 1.0, noisy))
    pred = Predictions([0, 1, 2] * 4, np.array(true), _onehot([0, 1, 2] * 4), np.array(pred))
    m = compute_metrics(pred)
    cells = {f: m["families"][f]["correct"] for f in FAMILIES}
    assert regl1_from_errors(cells) == pytest.approx(m["regl1"], rel=1e-12)
    log10_cells = {f: {n: (e / math.log(10) if n in ("youngs_modulus", "yield_stress") else e) for n, e in c.items()}
                   for f, c in cells.items()}
    assert regl1_from_errors(log10_cells, log_base=10) == pytest.approx(m["regl1"], rel=1e-12)
    wide = {f: {n: (lo, lo + 2 * (hi - lo), s) if s == "linear" else (lo, lo * (hi / lo) ** 2, s)
                for n, (lo, hi, s) in r.items()} for f, r in family_ranges().items()}
    assert regl1_from_errors(cells, wide) == pytest.approx(m["regl1"] / 2, rel=1e-12)


# --------------------------------------------------------------------------- an independent reference of SPEC 8

# SPEC 6's table, typed in here (not read from ad_sim.families): (low, high, log scale?). Sand's E and nu
# are fixed, not sampled, so they are no parameter of sand's errors or RegL1.
SPEC_RANGES = {
    "jelly": {"youngs_modulus": (1.5e4, 1.5e6, True), "poissons_ratio": (0.20, 0.40, False)},
    "plasticine": {"youngs_modulus": (5e4, 5e5, True), "poissons_ratio": (0.35, 0.48, False),
                   "yield_stress": (500.0, 25000.0, True)},
    "sand": {"friction_angle": (math.radians(10.0), math.radians(45.0), False)},
}
SPEC_FAMILIES = ("jelly", "plasticine", "sand")
SPEC_PARAMETERS = ("youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle")


def _spec_metrics(true_class, true_params, probabilities, pred_params) -> dict:
    """SPEC 8 from its text, one clip at a time in plain Python: Acc; E and yield log-MAE in ln;
    nu MAE; phi MAE in degrees; errors over the family's correctly classified clips and over all of
    them; RegL1 per clip = mean over the true family's sampled parameters of |pred - true| in units
    of the family's sampling range (ln for E and yield), averaged over the family's clips and over all
    clips. A non-positive E or yield prediction is read as 1e-12 (its log error stays finite)."""
    def log(v):
        return math.log(max(v, 1e-12))

    def error(name, pairs):
        if not pairs:
            return math.nan
        if name in ("youngs_modulus", "yield_stress"):
            return sum(abs(log(p) - math.log(t)) for p, t in pairs) / len(pairs)
        if name == "friction_angle":
            return sum(abs(math.degrees(p) - math.degrees(t)) for p, t in pairs) / len(pairs)
        return sum(abs(p - t) for p, t in pairs) / len(pairs)

    n = len(true_class)
    predicted = [max(range(3), key=lambda c: row[c]) for row in probabilities]  # first of a tie, as argmax
    clip_regl1 = []
    for i in range(n):
        terms = []
        for name, (lo, hi, is_log) in SPEC_RANGES[SPEC_FAMILIES[true_class[i]]].items():
            p, t = pred_params[i][SPEC_PARAMETERS.index(name)], true_params[i][SPEC_PARAMETERS.index(name)]
            span = math.log(hi) - math.log(lo) if is_log else hi - lo
            terms.append(abs((log(p) - log(t)) if is_log else (p - t)) / span)
        clip_regl1.append(sum(terms) / len(terms))
    families = {}
    for c, family in enumerate(SPEC_FAMILIES):
        clips = [i for i in range(n) if true_class[i] == c]
        correct = [i for i in clips if predicted[i] == c]
        families[family] = {
            "n": len(clips), "acc": len(correct) / len(clips) if clips else math.nan,
            "regl1": sum(clip_regl1[i] for i in clips) / len(clips) if clips else math.nan,
            **{which: {name: error(name, [(pred_params[i][SPEC_PARAMETERS.index(name)],
                                           true_params[i][SPEC_PARAMETERS.index(name)]) for i in subset])
                       for name in SPEC_RANGES[family]} for which, subset in (("correct", correct), ("all", clips))}}
    confusion = [[sum(1 for i in range(n) if true_class[i] == t and predicted[i] == p) for p in range(3)]
                 for t in range(3)]
    return {"n": n, "accuracy": sum(predicted[i] == true_class[i] for i in range(n)) / n if n else math.nan,
            "regl1": sum(clip_regl1) / n if n else math.nan, "families": families, "confusion": confusion}


def _spec_truth(rng, family: int) -> list[float]:
    """One instance of SPEC 6: log-uniform E and yield, uniform nu and phi; sand's fixed E and nu."""
    row = [1e5, 0.3, NAN, NAN] if family == 2 else [NAN] * 4
    for name, (lo, hi, is_log) in SPEC_RANGES[SPEC_FAMILIES[family]].items():
        u = rng.uniform()
        row[SPEC_PARAMETERS.index(name)] = lo * (hi / lo) ** u if is_log else lo + u * (hi - lo)
    return row


def _assert_same(code, reference, where=""):
    if isinstance(reference, dict):
        assert set(code) >= set(reference), where
        for key, value in reference.items():
            _assert_same(code[key], value, f"{where}/{key}")
    elif isinstance(reference, list):
        assert code == reference, where
    elif math.isnan(reference):
        assert math.isnan(code), where
    else:
        assert code == pytest.approx(reference, rel=1e-9, abs=1e-12), where


def test_metrics_equal_an_independent_reference_of_spec_8_on_random_prediction_sets():
    """compute_metrics against _spec_metrics on 400 seeded random prediction sets: any size from a single
    clip, some families absent, some never predicted (no correct clip: n/a), predictions far outside the
    sampling ranges (E down to 1e2 and up to 1e8, nu below 0 and above 0.5, phi up to 80 degrees),
    non-positive E and yield, sand clips whose E and nu predictions are wild (they must not count), and
    probability ties."""
    rng = np.random.default_rng(2024)
    for trial in range(400):
        n = 1 if trial % 10 == 0 else int(rng.integers(2, 25))
        present = rng.choice(3, size=int(rng.integers(1, 4)), replace=False)
        classes = rng.choice(present, size=n)
        true = np.array([_spec_truth(rng, c) for c in classes])
        pred = np.column_stack([10 ** rng.uniform(2, 8, n), rng.uniform(-0.1, 0.6, n), 10 ** rng.uniform(1, 6, n),
                                rng.uniform(0.0, math.radians(80.0), n)])
        if trial % 7 == 0:
            pred[rng.integers(n), 0] = -3.0  # a negative E
            pred[rng.integers(n), 2] = 0.0  # a zero yield
        probabilities = rng.dirichlet(np.ones(3), n)
        if trial % 5 == 0:
            probabilities[:, rng.integers(3)] = 0.0  # a family never predicted: none of its clips correct
        if trial % 11 == 0:
            probabilities[0] = [0.4, 0.4, 0.2]  # a tie
        code = compute_metrics(Predictions(classes, true, probabilities, pred))
        _assert_same(code, _spec_metrics(classes.tolist(), true.tolist(), probabilities.tolist(), pred.tolist()),
                     f"trial {trial}")
        np.testing.assert_allclose(regl1(Predictions(classes, true, probabilities, pred)),
                                   [_spec_metrics([c], [t], [p], [q])["regl1"]
                                    for c, t, p, q in zip(classes.tolist(), true.tolist(), probabilities.tolist(),
                                                          pred.tolist())], rtol=1e-9)


def test_regl1_ranges_are_spec_6s_sampled_parameters_of_each_family():
    """RegL1 and the error columns use each family's own SPEC 6 range for its sampled parameters only:
    sand's fixed E and nu count nowhere, however wrong their predictions."""
    ranges = family_ranges()
    assert {f: list(r) for f, r in ranges.items()} == {f: list(r) for f, r in SPEC_RANGES.items()}
    for family, parameters in SPEC_RANGES.items():
        for name, (lo, hi, is_log) in parameters.items():
            assert ranges[family][name] == (pytest.approx(lo), pytest.approx(hi), "log" if is_log else "linear")
    sand = np.array([SAND])
    wild = sand.copy()
    wild[0, :2] = [1e9, 0.49]  # E and nu: fixed for sand, whatever the head says
    m = compute_metrics(Predictions([2], sand, _onehot([2]), wild))
    assert m["regl1"] == 0.0 and list(m["families"]["sand"]["correct"]) == ["friction_angle"]


def test_a_clip_without_finite_class_probabilities_is_refused():
    """argmax reads NaN as the largest value: an all-NaN row would count as a confident jelly, raising
    jelly's Acc. Such a clip has no predicted family, so the predictions are refused, naming it."""
    true = np.array([JELLY, SAND])
    probabilities = _onehot([0, 2])
    probabilities[1] = NAN
    with pytest.raises(ValueError, match="not finite for 1 clip.*e1"):
        Predictions([0, 2], true, probabilities, _fill(true), episode_ids=["e0", "e1"])
    probabilities[1] = [0.1, NAN, 0.8]  # would be read as plasticine
    with pytest.raises(ValueError, match="not finite"):
        Predictions([0, 2], true, probabilities, _fill(true))


def test_a_nan_parameter_prediction_makes_its_cells_undefined_not_zero():
    """A NaN parameter (e.g. a hand-edited predictions.json with null) is not dropped: its family's error
    over the clips that hold it, that family's RegL1 and the overall RegL1 are NaN (null, n/a), as the
    reference gives; the other cells stay defined."""
    true = np.array([JELLY, JELLY, SAND])
    pred = _fill(true)
    pred[1, 0] = NAN  # the misclassified jelly's E
    probabilities = _onehot([0, 2, 2])
    m = compute_metrics(Predictions([0, 0, 2], true, probabilities, pred))
    _assert_same(m, _spec_metrics([0, 0, 2], true.tolist(), probabilities.tolist(), pred.tolist()))
    assert m["families"]["jelly"]["correct"]["youngs_modulus"] == 0.0  # the correct clip's E is exact
    assert math.isnan(m["families"]["jelly"]["all"]["youngs_modulus"]) and math.isnan(m["regl1"])
    assert m["families"]["sand"]["regl1"] == 0.0


def test_confusion_matrix_is_true_by_predicted_and_plotted_so(tmp_path, monkeypatch):
    """confusion[true][predicted]; the plot puts true families down the rows (y), predicted across (x),
    each cell's count at its own place."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ad_estimator.metrics import _plot_confusion

    # 3 jelly: 2 right, 1 as sand; 1 plasticine as jelly; 2 sand right.
    classes, predicted = [0, 0, 0, 1, 2, 2], [0, 0, 2, 0, 2, 2]
    true = np.array([(JELLY, PLASTICINE, SAND)[c] for c in classes])
    confusion = compute_metrics(Predictions(classes, true, _onehot(predicted), _fill(true)))["confusion"]
    assert confusion == [[2, 0, 1], [1, 0, 0], [0, 0, 2]]
    fig, ax = plt.subplots()
    _plot_confusion(ax, np.asarray(confusion))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("predicted", "true")
    assert [t.get_text() for t in ax.get_xticklabels()] == list(FAMILIES)
    # each true row says how many clips it holds (a family without any reads as absent, not as all wrong)
    assert [t.get_text() for t in ax.get_yticklabels()] == ["jelly\n(3 clips)", "plasticine\n(1 clips)",
                                                            "sand\n(2 clips)"]
    cells = {(round(t.get_position()[0]), round(t.get_position()[1])): int(t.get_text()) for t in ax.texts}
    assert all(cells[j, i] == confusion[i][j] for i in range(3) for j in range(3))  # text at x = predicted
    assert ax.images[0].get_array()[0, 2] == 1 and ax.images[0].get_array()[1, 0] == 1  # row = true
    plt.close(fig)


def test_report_plots_give_each_family_one_colour(tmp_path, monkeypatch):
    """pred_vs_true.png and regl1_vs_frames.png: a family has the same colour in every panel and plot
    (the default cycle drew plasticine's yield and sand's phi in jelly's colour)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.axes import Axes
    from matplotlib.colors import to_hex

    drawn = []
    scatter, plot = Axes.scatter, Axes.plot

    def record_scatter(self, *args, **kwargs):
        out = scatter(self, *args, **kwargs)
        drawn.append((kwargs.get("label"), to_hex(out.get_facecolor()[0])))
        return out

    def record_plot(self, *args, **kwargs):
        lines = plot(self, *args, **kwargs)
        drawn.extend((kwargs.get("label"), to_hex(line.get_color())) for line in lines if kwargs.get("label"))
        return lines

    monkeypatch.setattr(Axes, "scatter", record_scatter)
    monkeypatch.setattr(Axes, "plot", record_plot)
    classes = np.array([0, 1, 2] * 3)
    true = np.array([(JELLY, PLASTICINE, SAND)[c] for c in classes])
    write_report({k: Predictions(classes, true, _onehot(classes), _fill(true)) for k in (25, 15)}, tmp_path, "t")
    colours = {}
    for label, colour in drawn:
        colours.setdefault(label, set()).add(colour)
    assert {f: len(colours[f]) for f in FAMILIES} == dict.fromkeys(FAMILIES, 1), colours
    assert len({next(iter(colours[f])) for f in FAMILIES} | colours["all"]) == 4  # all distinct


def _report_figures(monkeypatch, by_frames, tmp_path) -> dict:
    """write_report's figures, by file name, kept open to be read."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    saved, savefig = {}, Figure.savefig

    def record(self, path, *args, **kwargs):
        saved[Path(path).name] = self
        return savefig(self, path, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    monkeypatch.setattr("matplotlib.pyplot.close", lambda *args: None)
    write_report(by_frames, tmp_path, "t")
    return saved


def test_report_plots_give_units_and_mark_a_family_without_clips(tmp_path, monkeypatch):
    """pred_vs_true.png names each axis's units (E, yield in Pa on log axes, phi in degrees) and the frames;
    a family without clips is named as such in every legend (before: 'sand' stood in the phi panel's and the
    RegL1 plot's legends over nothing, as if it were drawn) and its confusion row says 0 clips."""
    true = np.array([JELLY, PLASTICINE, JELLY])
    classes = np.array([0, 1, 0])
    figures = _report_figures(monkeypatch, {k: Predictions(classes, true, _onehot(classes), _fill(true))
                                            for k in (25, 15)}, tmp_path)
    panels = figures["pred_vs_true.png"].axes
    assert [(ax.get_xlabel(), ax.get_ylabel()) for ax in panels] == [
        ("true E (Pa)", "predicted E (Pa)"), ("true nu", "predicted nu"), ("true yield (Pa)", "predicted yield (Pa)"),
        ("true phi (degrees)", "predicted phi (degrees)")]
    assert [(ax.get_xscale(), ax.get_yscale()) for ax in panels] == [("log", "log"), ("linear", "linear"),
                                                                      ("log", "log"), ("linear", "linear")]
    assert "25 frames" in figures["pred_vs_true.png"].get_suptitle()
    legends = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in panels]
    assert legends == [["jelly", "plasticine"], ["jelly", "plasticine"], ["plasticine"], ["sand (no clips)"]]
    (regl1_ax,) = figures["regl1_vs_frames.png"].axes
    assert [t.get_text() for t in regl1_ax.get_legend().get_texts()] == ["all", "jelly", "plasticine",
                                                                         "sand (no clips)"]
    (confusion_ax,) = figures["confusion.png"].axes
    assert confusion_ax.get_yticklabels()[2].get_text() == "sand\n(0 clips)"


def test_report_says_how_many_clips_each_row_and_plot_covers(tmp_path):
    """A temporal-OOD row with fewer clips than the full clip's (episodes left out of it, as the estimator's
    evaluate does for a window holding fewer than K slots) is said so; before, report.md gave the full
    row's count alone. Each plot is captioned with what it shows."""
    true = np.array([JELLY, PLASTICINE, SAND] * 2)
    classes = np.array([0, 1, 2] * 2)
    full = Predictions(classes, true, _onehot(classes), _fill(true))
    short = Predictions(classes[:4], true[:4], _onehot(classes[:4]), _fill(true[:4]))
    write_report({25: full, 24: full, 15: short}, tmp_path, "t")
    report = (tmp_path / "report.md").read_text()
    assert "Clips: 6;" in report and "15 frames: 4" in report and "24 frames" not in report
    assert "RegL1: over all clips" in report  # both tables' RegL1 counts every clip, misclassified ones too
    captions = report[report.index("## Plots"):]
    assert "clip counts, rows the true family" in captions and "E and yield in Pa on log axes" in captions
    assert captions.index("clip counts") < captions.index("![confusion]") < captions.index("Pa on log axes") \
        < captions.index("![predicted vs true]") < captions.index("![RegL1 vs frames]")
    write_report({25: full, 15: full}, tmp_path / "same", "t")
    assert "Rows with another number of clips" not in (tmp_path / "same" / "report.md").read_text()


def test_report_gives_the_frames_its_clips_observed_and_keeps_a_row_without_clips(tmp_path):
    """It said "frames per clip: 25" whatever was scored: a model of 20 frames, or clips with frames missing
    (ad_estimator.evaluate's records say how many frame slots each estimate had filled). A temporal-OOD row that every episode
    was left out of stays in both tables, its cells "no clips", instead of vanishing."""
    true = np.array([JELLY, PLASTICINE, SAND] * 2)
    classes = np.array([0, 1, 2] * 2)
    full = Predictions(classes, true, _onehot(classes), _fill(true), episode_ids=[f"e{i}" for i in range(6)])
    records = [{**record, "frames_used": used} for record, used in zip(full.episodes(), [20, 20, 18, 20, 19, 20])]
    by_frames = {20: Predictions.from_episodes(records), 18: full, 15: Predictions.from_episodes([])}
    results = write_report(by_frames, tmp_path, "t")
    report = (tmp_path / "report.md").read_text()
    assert "Clips: 6; frames per clip: 20, but 2 clip(s) filled only 18 to 19 of the 20 frame slots (frames missing " \
           "or rejected)." in report
    assert "Rows with another number of clips than the 20-frame row's: 15 frames: no clips." in report
    for table in (format_table(results), report):
        rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| 15 ")]
        assert rows and all(row[1:] == ["no clips"] * 9 + ["no clips |"] for row in rows), rows
    assert json.loads((tmp_path / "metrics.json").read_text())["frames"]["15"]["n"] == 0
    write_report({20: full}, tmp_path / "whole", "t")  # every clip whole (or not recorded): the row's K
    assert "Clips: 6; frames per clip: 20." in (tmp_path / "whole" / "report.md").read_text()


# --------------------------------------------------------------------------- mutation-testing audit


def test_error_by_true_value_correlates_log_parameters_in_log_space():
    """E and yield are compared in log space (their errors are log-MAE): a prediction that is a power of the
    truth, ln pred = 2 ln true - c, is perfectly correlated there, though not linearly."""
    from ad_estimator.metrics import error_by_true_value

    true_e = 1.5e4 * 100.0 ** np.linspace(0.0, 1.0, 9)  # jelly's E range, two decades
    true = np.array([[e, 0.2 + 0.02 * i, NAN, NAN] for i, e in enumerate(true_e)])
    pred_params = _fill(true.copy())
    pred_params[:, 0] = true_e**2 / 1.5e5
    assert np.corrcoef(pred_params[:, 0], true_e)[0, 1] < 0.99  # linearly not 1: the case tells the two apart
    table = error_by_true_value(Predictions([0] * 9, true, _onehot([0] * 9), pred_params))
    assert table["jelly"]["youngs_modulus"]["correlation"] == pytest.approx(1.0, abs=1e-12)
    assert table["jelly"]["poissons_ratio"]["correlation"] == pytest.approx(1.0, abs=1e-12)  # nu: linear, exact


def test_calibration_leaves_out_log_parameter_clips_whose_prediction_has_no_log():
    """A non-positive E prediction (a saved predictions.json of another evaluator, say) has no log-space error
    to standardise: it is left out of E's calibration (n, coverage), not counted as a miss; its nu still counts."""
    true = np.array([JELLY, JELLY])
    pred_params = _fill(true.copy())
    pred_params[0, E] = 0.0
    pred_params[1, E] = true[1, E] * math.exp(0.1)  # within one log-space sigma of 0.2
    sigma = np.array([[1e4, 0.01, NAN, NAN], [0.2 * pred_params[1, E], 0.01, NAN, NAN]])
    c = uncertainty_calibration(Predictions([0, 0], true, _onehot([0, 0]), pred_params, pred_sigma=sigma))["jelly"]
    assert c["youngs_modulus"]["n"] == 1
    assert c["youngs_modulus"]["coverage_1sigma"] == 1.0 and c["youngs_modulus"]["coverage_2sigma"] == 1.0
    assert c["youngs_modulus"]["error"] == pytest.approx(0.1)
    assert c["poissons_ratio"]["n"] == 2


def test_calibration_coverage_counts_an_error_of_exactly_one_and_two_sigma_as_within():
    """coverage_ksigma is the fraction with |z| <= k (SPEC: within k sigma), boundaries included; the values
    are exact in binary floating point."""
    true = np.array([JELLY, JELLY])
    true[:, NU] = 0.25
    pred_params = _fill(true.copy())
    pred_params[:, NU] = [0.3125, 0.375]  # 0.0625 and 0.125 off: z = 1 and z = 2 with sigma 0.0625
    sigma = np.array([[NAN, 0.0625, NAN, NAN]] * 2)
    c = uncertainty_calibration(Predictions([0, 0], true, _onehot([0, 0]), pred_params, pred_sigma=sigma))["jelly"]
    assert c["poissons_ratio"]["n"] == 2
    assert c["poissons_ratio"]["coverage_1sigma"] == 0.5 and c["poissons_ratio"]["coverage_2sigma"] == 1.0


def test_saved_records_take_their_sigmas_from_raw_uncertainties_before_uncertainties():
    """A record's `uncertainties` are the predicted family's (0 for a fixed parameter, NaN for one it lacks);
    `raw_uncertainties` are the model's for every parameter, which pred_sigma holds: they win where both are."""
    true = np.array([JELLY, SAND])
    raw_sigma = np.array([[1e4, 0.01, 50.0, 0.02], [2e4, 0.02, 60.0, 0.03]])
    records = Predictions([0, 2], true, _onehot([2, 2]), _fill(true), pred_sigma=raw_sigma).episodes()
    for record in records:  # both clips predicted as sand: E and nu fixed (sigma 0), no yield
        record["uncertainties"] = [0.0, 0.0, None, record["raw_uncertainties"][3]]
    back = Predictions.from_episodes(records)
    np.testing.assert_array_equal(back.pred_sigma, raw_sigma)
    for record in records:
        del record["raw_uncertainties"]
    np.testing.assert_array_equal(Predictions.from_episodes(records).pred_sigma[:, :2], 0.0)


def test_frame_counts_take_every_count_from_1_to_the_full_clip():
    import argparse

    from ad_estimator.metrics import FrameCounts
    from ad_sim.materials import FRAME_COUNT

    parser = argparse.ArgumentParser(prog="evaluate")
    parser.add_argument("--frames", nargs="*", action=FrameCounts)
    assert parser.parse_args(["--frames", str(FRAME_COUNT), "1"]).frames == [FRAME_COUNT, 1]
    assert parser.parse_args(["--frames", "24,18", "15", "18"]).frames == [24, 18, 15]
    assert parser.parse_args(["--frames"]).frames == []
    for bad in (["0"], [str(FRAME_COUNT + 1)], [","]):
        with pytest.raises(SystemExit):
            parser.parse_args(["--frames", *bad])


def test_json_text_writes_infinities_as_null_as_it_does_nan(tmp_path):
    """inf (an overflowing sigma or error) is no more JSON than NaN: json.dumps(allow_nan=False) raised "Out of
    range float values are not JSON compliant" and the report was lost after all the inference. Both become null
    (JSON has neither), and metrics.json of a row with an infinite error is written; its table says inf."""
    INF = math.inf
    text = json_text({"a": INF, "b": [-INF, 1.5, NAN], "c": (np.float64(INF), {"d": -INF})})
    assert json.loads(text, parse_constant=lambda name: pytest.fail(f"non-standard JSON constant {name}")) == \
        {"a": None, "b": [None, 1.5, None], "c": [None, {"d": None}]}
    true = np.array([JELLY, SAND])
    pred = _fill(true)
    pred[0, NU] = INF  # the jelly's nu: its error and RegL1 are inf
    sigma = _fill(true) * 0.1
    sigma[0, E] = INF
    results = write_report({25: Predictions(np.array([0, 2]), true, _onehot([0, 2]), pred, pred_sigma=sigma)},
                           tmp_path, "t")
    saved = json.loads((tmp_path / "metrics.json").read_text())["frames"]["25"]
    assert saved["families"]["jelly"]["correct"]["poissons_ratio"] is None and saved["regl1"] is None
    assert results["25"]["regl1"] == INF and "| inf |" in format_table(results)
    assert saved["families"]["sand"]["regl1"] == results["25"]["families"]["sand"]["regl1"]
