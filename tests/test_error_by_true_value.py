"""ad_estimator.metrics.error_by_true_value (where along each parameter's range the errors lie) on
hand-computed cases, its report section, and `python -m training report` (a report rebuilt from a
saved predictions.json)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ad_estimator.metrics import (Predictions, error_by_true_value, evaluate_all, format_error_by_true_value,
                                  json_text, write_report)
from ad_sim.materials import FAMILIES, PARAMETER_NAMES
from training.__main__ import main

E, NU, YIELD, PHI = range(4)
N = 9  # clips per family: thirds of 3


def _onehot(classes):
    p = np.full((len(classes), 3), 0.1)
    p[np.arange(len(classes)), classes] = 0.8
    return p


def _truth() -> tuple[np.ndarray, np.ndarray]:
    """N clips per family, their true values spread over each family's range in shuffled order."""
    rng = np.random.default_rng(0)
    classes = np.repeat([0, 1, 2], N)
    true = np.full((3 * N, 4), math.nan)
    grid = np.linspace(0, 1, N)
    for c, rows in enumerate(np.split(np.arange(3 * N), 3)):
        order = rng.permutation(grid)
        if c < 2:  # jelly, plasticine
            true[rows, E] = 2e4 * 50 ** order if c == 0 else 6e4 * 8 ** order
            true[rows, NU] = 0.25 + 0.1 * order
        if c == 1:
            true[rows, YIELD] = 600 * 40 ** order
        if c == 2:
            true[rows, PHI] = math.radians(12) + math.radians(30) * order
    return classes, true


def _predictions(pred_params, classes, true, **kw) -> Predictions:
    return Predictions(classes, true, _onehot(classes), np.where(np.isnan(pred_params), 1.0, pred_params), **kw)


def test_perfect_predictor_has_zero_error_and_correlation_one():
    classes, true = _truth()
    table = error_by_true_value(_predictions(true, classes, true))
    assert list(table) == list(FAMILIES)
    assert list(table["plasticine"]) == ["youngs_modulus", "poissons_ratio", "yield_stress"]
    assert list(table["sand"]) == ["friction_angle"]
    for parameters in table.values():
        for e in parameters.values():
            assert e["n"] == N and [b["n"] for b in e["bins"]] == [3, 3, 3]
            assert e["all"] == 0.0 and all(b["error"] == 0.0 for b in e["bins"])
            assert e["correlation"] == pytest.approx(1.0)
    # Bins hold the lowest, middle and highest third of the true values (SI: phi in radians).
    phi = np.sort(true[classes == 2, PHI])
    assert [(b["lo"], b["hi"]) for b in table["sand"]["friction_angle"]["bins"]] == [
        (phi[0], phi[2]), (phi[3], phi[5]), (phi[6], phi[8])]
    assert json.loads(json_text(table)) == table  # plain floats and ints


def test_errors_per_third_and_against_a_constant_guess():
    classes, true = _truth()
    pred = true.copy()
    jelly = np.flatnonzero(classes == 0)
    upper = jelly[true[jelly, E] >= np.sort(true[jelly, E])[6]]  # the highest third of jelly E
    pred[upper, E] *= math.exp(0.7)  # log error 0.7 there, exact below
    sand = np.flatnonzero(classes == 2)
    pred[sand, PHI] += math.radians(2.0)  # 2 degrees everywhere
    table = error_by_true_value(_predictions(pred, classes, true))
    e = table["jelly"]["youngs_modulus"]
    assert [b["error"] for b in e["bins"]] == pytest.approx([0.0, 0.0, 0.7])
    assert e["all"] == pytest.approx(0.7 / 3)
    # The constant guess is the log-midpoint of jelly's E range (1.5e4..1.5e6): 1.5e5.
    assert e["constant_guess"] == pytest.approx(np.mean(np.abs(np.log(1.5e5) - np.log(true[jelly, E]))))
    phi = table["sand"]["friction_angle"]
    assert [b["error"] for b in phi["bins"]] == pytest.approx([2.0, 2.0, 2.0]) and phi["all"] == pytest.approx(2.0)
    assert phi["correlation"] == pytest.approx(1.0)  # shifted, still perfectly correlated
    # Arithmetic midpoint of sand's phi range (10..45 degrees): 27.5 degrees.
    assert phi["constant_guess"] == pytest.approx(np.mean(np.abs(27.5 - np.degrees(true[sand, PHI]))))
    assert table["plasticine"]["poissons_ratio"]["constant_guess"] == pytest.approx(
        np.mean(np.abs((0.35 + 0.48) / 2 - true[classes == 1, NU])))


def test_constant_predictor_scores_the_constant_guess_with_undefined_correlation():
    classes, true = _truth()
    middle = [math.sqrt(1.5e4 * 1.5e6), 0.30, math.nan, math.nan]
    pred = np.where(classes[:, None] == 0, middle, true)
    table = error_by_true_value(_predictions(pred, classes, true))
    for e in table["jelly"].values():
        assert e["all"] == pytest.approx(e["constant_guess"])
        assert math.isnan(e["correlation"])
    assert json.loads(json_text(table))["jelly"]["poissons_ratio"]["correlation"] is None
    assert "| jelly | nu |" in format_error_by_true_value(table, 25)


def test_misclassified_clips_count_and_absent_families_are_left_out():
    classes, true = _truth()
    keep = classes != 1
    classes, true = classes[keep], true[keep]
    probabilities = _onehot(classes)
    probabilities[0] = [0.1, 0.1, 0.8]  # a jelly clip called sand: still scored as jelly ("all")
    pred = Predictions(classes, true, probabilities, np.where(np.isnan(true), 1.0, true))
    table = error_by_true_value(pred)
    assert list(table) == ["jelly", "sand"] and table["jelly"]["youngs_modulus"]["n"] == N
    # Fewer clips than bins: one clip is the median; the empty bins are NaN, and n/a in the table.
    one = error_by_true_value(Predictions(classes[:1], true[:1], probabilities[:1], pred.pred_params[:1]))
    assert [b["n"] for b in one["jelly"]["youngs_modulus"]["bins"]] == [0, 1, 0]
    assert math.isnan(one["jelly"]["youngs_modulus"]["bins"][0]["lo"])
    assert math.isnan(one["jelly"]["youngs_modulus"]["correlation"])
    assert "| jelly | E | 1 | n/a | 0.000 (" in format_error_by_true_value(one, 25)  # n: the one clip
    # A count that does not divide (10 jelly clips, two of them the same): the leftover goes to the middle.
    ten = np.r_[np.flatnonzero(classes == 0), 1]
    ten = error_by_true_value(Predictions(classes[ten], true[ten], probabilities[ten], pred.pred_params[ten]))
    assert [b["n"] for b in ten["jelly"]["youngs_modulus"]["bins"]] == [3, 4, 3]
    eleven = np.r_[np.flatnonzero(classes == 0), 1, 2]  # two left over: one to each end
    eleven = error_by_true_value(Predictions(classes[eleven], true[eleven], probabilities[eleven],
                                             pred.pred_params[eleven]))
    assert [b["n"] for b in eleven["jelly"]["youngs_modulus"]["bins"]] == [4, 3, 4]


def test_clips_without_a_true_value_are_left_out():
    classes, true = _truth()
    pred_params = np.where(np.isnan(true), 1.0, true * 1.5)
    true[0, E] = math.nan  # a jelly clip whose E truth is missing
    e = error_by_true_value(_predictions(pred_params, classes, true))["jelly"]["youngs_modulus"]
    assert e["n"] == N - 1 and sum(b["n"] for b in e["bins"]) == N - 1
    assert e["all"] == pytest.approx(math.log(1.5)) and all(math.isfinite(b["hi"]) for b in e["bins"])


def test_formatted_section_has_a_row_per_family_parameter_and_the_columns():
    classes, true = _truth()
    table = error_by_true_value(_predictions(true * 1.1, classes, true))
    text = format_error_by_true_value(table, 18)
    lines = text.splitlines()
    assert lines[0] == "## Error by true value (18 frames)"
    # n: the clips each row covers (with 2 a correlation of 1.000 says nothing; the reader must see it)
    assert ("| family | parameter | n | lowest third | middle third | highest third | all | constant guess | "
            "correlation |") in lines
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| family")]
    assert [tuple(r.split(" | ")[:2]) for r in rows] == [
        ("| jelly", "E"), ("| jelly", "nu"), ("| plasticine", "E"), ("| plasticine", "nu"),
        ("| plasticine", "yield"), ("| sand", "phi")]
    e = table["jelly"]["youngs_modulus"]
    lo, hi = e["bins"][0]["lo"], e["bins"][0]["hi"]
    assert rows[0].startswith(f"| jelly | E | {e['n']} | {e['bins'][0]['error']:.3f} ({lo:.3g}–{hi:.3g}) |")
    assert all(len(r.split(" | ")) == len(lines[lines.index(next(h for h in lines if h.startswith("| family")))]
                                          .split(" | ")) for r in rows)  # as many cells as the header
    assert rows[0].endswith(f"| {e['all']:.3f} | {e['constant_guess']:.3f} | {e['correlation']:.3f} |")
    phi = table["sand"]["friction_angle"]["bins"][2]  # range shown in degrees
    assert f"({math.degrees(phi['lo']):.3g}–{math.degrees(phi['hi']):.3g})" in rows[-1]
    four = format_error_by_true_value(error_by_true_value(_predictions(true, classes, true), bins=4), 25)
    assert "| family | parameter | n | bin 1 | bin 2 | bin 3 | bin 4 | all | constant guess | correlation |" in four


def _saved(tmp_path, by_frames: dict[int, Predictions], names=PARAMETER_NAMES, **header):
    path = tmp_path / "predictions.json"
    order = [PARAMETER_NAMES.index(n) for n in names]
    frames = {}
    for k, p in by_frames.items():
        frames[str(k)] = p.episodes()
        for record in frames[str(k)]:  # a model listing its parameters in another order
            record["raw_parameters"] = [record["raw_parameters"][j] for j in order]
            record["raw_uncertainties"] = [record["raw_uncertainties"][j] for j in order]
    path.write_text(json_text({**header, "parameter_names": list(names), "frames": frames}, indent=None))
    return path


def test_report_command_rebuilds_the_report_of_saved_predictions(tmp_path, capsys):
    classes, true = _truth()
    rng = np.random.default_rng(1)
    by_frames = {k: _predictions(true * rng.uniform(0.7, 1.4, true.shape), classes, true,
                                 episode_ids=[f"e{i}" for i in range(len(classes))],
                                 pred_sigma=np.abs(np.where(np.isnan(true), 1.0, true)) * 0.2)
                 for k in (25, 18)}
    names = ("friction_angle", "youngs_modulus", "poissons_ratio", "yield_stress")
    path = _saved(tmp_path, by_frames, names, model_id="m-1")
    out = tmp_path / "report"
    assert main(["report", "--predictions", str(path), "--out", str(out), "--title", "again"]) == 0
    assert "report.md" in capsys.readouterr().out
    write_report(by_frames, tmp_path / "direct", "again")
    assert (out / "metrics.json").read_text() == (tmp_path / "direct" / "metrics.json").read_text()
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json_text(
        {"title": "again", "frames": evaluate_all(by_frames)}))
    report = (out / "report.md").read_text()
    assert report == (tmp_path / "direct" / "report.md").read_text()
    section = report.index("## Error by true value (25 frames)")
    assert report.index("## Uncertainty calibration (25 frames)") < section < report.index("![confusion]")
    assert format_error_by_true_value(error_by_true_value(by_frames[25]), 25) in report
    for plot in ("confusion.png", "pred_vs_true.png", "regl1_vs_frames.png"):
        assert (out / plot).read_bytes().startswith(b"\x89PNG")
    # Default title: what the file says was evaluated.
    assert main(["report", "--predictions", str(path), "--out", str(tmp_path / "titled")]) == 0
    assert json.loads((tmp_path / "titled" / "metrics.json").read_text())["title"] == f"m-1 ({path})"


@pytest.mark.parametrize("content, message", [
    (None, "does not exist"),
    ("{not json", "is not valid JSON"),
    ('[1, 2]', 'has no "frames" object'),
    ('{"model_id": "m"}', 'has no "frames" object'),
    ('{"frames": {}}', "holds no episode records"),
    ('{"frames": {"25": []}}', "holds no episode records"),
    ('{"frames": {"25": [{"episode_id": "e"}]}}', '"frames"["25"] is not a list of episode records'),
])
def test_report_command_says_what_is_wrong_with_the_file(tmp_path, capsys, content, message):
    path = tmp_path / "predictions.json"
    if content is not None:
        path.write_text(content)
    assert main(["report", "--predictions", str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"python -m training report: {path}") and message in err
    assert "predictions.json written by `python -m training evaluate`" in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_report_command_says_what_is_wrong_with_the_paths(tmp_path, capsys):
    assert main(["report", "--predictions", str(tmp_path), "--out", str(tmp_path / "out")]) == 1
    assert "is a folder; pass the predictions.json inside it" in capsys.readouterr().err
    classes, true = _truth()
    saved = tmp_path / "predictions.json"
    saved.write_text(json_text({"frames": {"25": _predictions(true, classes, true).episodes()}}))
    taken = tmp_path / "taken"
    taken.write_text("a file, not a folder")
    assert main(["report", "--predictions", str(saved), "--out", str(taken)]) == 1
    err = capsys.readouterr().err.strip()
    assert f"cannot write the report to {taken}" in err and "pass another --out" in err and "\n" not in err
    assert taken.read_text() == "a file, not a folder"


def test_report_command_reads_the_estimator_runtimes_predictions(tmp_path):
    """A real estimator_runtime_predictions.json (no "parameter_names": the metrics' order) gives the
    metrics the runtime measured."""
    folder = Path(__file__).resolve().parents[1] / "docs" / "results" / "paper" / "streaming_earlier3_reg2_unseen"
    assert main(["report", "--predictions", str(folder / "estimator_runtime_predictions.json"),
                 "--out", str(tmp_path)]) == 0
    rebuilt = json.loads((tmp_path / "metrics.json").read_text())["frames"]["25"]
    measured = json.loads((folder / "estimator_runtime.json").read_text())["frames"]["25"]
    assert rebuilt["confusion"] == measured["confusion"] and rebuilt["regl1"] == pytest.approx(measured["regl1"])
    assert "| sand | phi |" in (tmp_path / "report.md").read_text()
