"""benchmarks/mask_sensitivity.py: the parameter moves it simulates, and one real run on the CPU
(warp kernels, rendering); the figures themselves are measured on the GPU machine."""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from ad_sim.materials import FAMILY_RANGES

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "mask_sensitivity.py"
spec = importlib.util.spec_from_file_location("mask_sensitivity", SCRIPT)
mask_sensitivity = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mask_sensitivity)


def test_moves_are_in_the_metrics_units_and_stay_in_range():
    jelly = {"youngs_modulus": 1e5, "poissons_ratio": 0.3}
    up = mask_sensitivity.moved("jelly", jelly, "youngs_modulus", 0.5, +1)
    assert up["youngs_modulus"] == pytest.approx(1e5 * math.exp(0.5)) and up["poissons_ratio"] == 0.3
    assert mask_sensitivity.moved("jelly", jelly, "poissons_ratio", 0.05, -1)["poissons_ratio"] == pytest.approx(0.25)
    top = FAMILY_RANGES["jelly"]["poissons_ratio"][1]
    assert mask_sensitivity.moved("jelly", jelly, "poissons_ratio", 1.0, +1)["poissons_ratio"] == top
    sand = {"friction_angle": 0.5, "youngs_modulus": 1e5, "poissons_ratio": 0.3}
    assert mask_sensitivity.moved("sand", sand, "friction_angle", 3.0, +1)["friction_angle"] == pytest.approx(
        0.5 + math.radians(3.0))  # phi's error is in degrees, the parameter in radians


def test_steps_come_from_the_bundled_models_unseen_errors(tmp_path):
    model_id, errors = mask_sensitivity.model_errors(mask_sensitivity.BUNDLED_MODEL.with_suffix(".metrics.json"))
    metrics = json.loads(mask_sensitivity.BUNDLED_MODEL.with_suffix(".metrics.json").read_text())
    assert model_id == metrics["model_id"]
    assert errors["sand"] == {"friction_angle": metrics["evaluation"]["unseen"]["full"]["families"]["sand"]
                              ["correct"]["friction_angle"]}
    unevaluated = tmp_path / "m.metrics.json"
    unevaluated.write_text(json.dumps({"model_id": "x"}))
    with pytest.raises(SystemExit, match="no unseen evaluation"):
        mask_sensitivity.model_errors(unevaluated)


def test_a_run_on_the_cpu_reports_how_much_a_move_changes_the_masks(tmp_path):
    out = tmp_path / "figures.json"
    result = subprocess.run([sys.executable, str(SCRIPT), "--size", "tiny", "--instances", "1", "--families", "sand",
                             "--json", str(out)], capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr
    figures = json.loads(out.read_text())
    [row] = figures["rows"]
    assert row["family"] == "sand" and row["parameter"] == "friction_angle" and 1 <= row["n"] <= 2
    # A 3.5 degree change of the friction angle moves the sand visibly, but far from every pixel.
    assert 10.0 < row["p10_db"] <= row["median_db"] <= row["p90_db"] < 60.0
    assert "| sand | friction_angle |" in result.stdout


@pytest.mark.parametrize("content, expected", [
    ("{", "cannot be read as JSON"), ('{"model_id": "x"}', "no unseen evaluation"),
    ("[1, 2]", "holds a JSON list, not a model's metrics (an object); pass --metrics"),  # was "(list indices ... missing)"
    ('{"evaluation": {"unseen": {"full": {"families": [1]}}}}',
     "has no unseen evaluation (evaluation.unseen.full.families.<family>.correct is not laid out as a model's metrics)")])
def test_a_bad_metrics_file_is_one_clear_line(tmp_path, content, expected):
    metrics = tmp_path / "m.metrics.json"
    metrics.write_text(content)
    result = subprocess.run([sys.executable, str(SCRIPT), "--metrics", str(metrics)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 1 and expected in result.stderr and "Traceback" not in result.stderr


def test_a_missing_error_is_named(tmp_path):
    metrics = json.loads(mask_sensitivity.BUNDLED_MODEL.with_suffix(".metrics.json").read_text())
    metrics["evaluation"]["unseen"]["full"]["families"]["jelly"]["correct"]["poissons_ratio"] = None
    path = tmp_path / "m.metrics.json"
    path.write_text(json.dumps(metrics))
    with pytest.raises(SystemExit, match="jelly poissons_ratio"):
        mask_sensitivity.model_errors(path)


def test_an_error_that_is_not_a_number_is_named(tmp_path):
    metrics = json.loads(mask_sensitivity.BUNDLED_MODEL.with_suffix(".metrics.json").read_text())
    metrics["evaluation"]["unseen"]["full"]["families"]["sand"]["correct"]["friction_angle"] = "3.5"
    path = tmp_path / "m.metrics.json"
    path.write_text(json.dumps(metrics))
    with pytest.raises(SystemExit, match="not a number for sand friction_angle"):  # was a ValueError from float()
        mask_sensitivity.model_errors(path)
