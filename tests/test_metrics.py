"""ad_estimator.metrics: the paper's metrics on hand-computed cases, the report files, no torch."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from ad_estimator.metrics import (
    Predictions,
    compute_metrics,
    evaluate_all,
    family_ranges,
    format_table,
    regl1,
    write_report,
)
from ad_sim.materials import FAMILIES

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


def test_metrics_module_never_imports_torch():
    code = "import sys, ad_estimator.metrics; sys.exit(1 if 'torch' in sys.modules else 0)"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr
