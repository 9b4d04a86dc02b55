"""Per-scene CMA-ES baseline (training/baseline.py) on real Warp CPU simulations, tiny budgets."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ad_estimator.metrics import compute_metrics
from ad_sim.instances import benchmark
from ad_sim.families import to_unit
from ad_sim.materials import FAMILIES, FAMILY_RANGES, SAMPLED_PARAMETERS
from ad_sim.resimulate import PSNR_CAP, resimulate, resimulation_psnr
from training import baseline

SAMPLE_BAG = Path(__file__).resolve().parents[1] / "bags" / "samples" / "unseen-masks-0of1"  # tiny unseen split


@pytest.mark.parametrize("family", FAMILIES)
def test_unit_coordinates_span_the_family_ranges_in_log_space_for_e_and_yield(family):
    low = {n: FAMILY_RANGES[family][n][0] for n in SAMPLED_PARAMETERS[family]}
    high = {n: FAMILY_RANGES[family][n][1] for n in SAMPLED_PARAMETERS[family]}
    assert baseline.from_unit(family, np.zeros(len(low))) == pytest.approx(low)
    assert baseline.from_unit(family, np.ones(len(low))) == pytest.approx(high)
    middle = baseline.from_unit(family, np.full(len(low), 0.5))
    for name in low:
        log_scale = FAMILY_RANGES[family][name][2] == "log"
        mean = math.sqrt(low[name] * high[name]) if log_scale else (low[name] + high[name]) / 2
        assert middle[name] == pytest.approx(mean)
    point = np.random.default_rng(1).random(len(low))
    back = [to_unit(value, *FAMILY_RANGES[family][name]) for name, value in baseline.from_unit(family, point).items()]
    np.testing.assert_allclose(back, point)


def test_cma_es_lowers_the_mask_loss_and_its_psnr_is_the_resimulation_psnr():
    instance = next(i for i in benchmark("tiny", "unseen") if i.episode_id == "unseen-bull-sand-0000")
    observed = resimulate([instance], [(instance.material, instance.parameters)])
    # 2 generations x 4 candidates (+ the start point): 9 simulations, batched per generation.
    fit, = baseline.fit_instances([instance], observed, generations=2, popsize=4, seed=0, progress=False)
    assert fit.family == "sand" and fit.evaluations == 9 and len(fit.history) == 2
    assert fit.loss < fit.initial_loss  # a candidate beat the middle of the range
    assert fit.history[1] <= fit.history[0]
    true_phi = instance.parameters["friction_angle"]
    start_phi = baseline.from_unit("sand", [0.5])["friction_angle"]
    assert abs(fit.parameters["friction_angle"] - true_phi) < abs(start_phi - true_phi)
    # The fit's PSNR is the re-simulation PSNR of its parameters (deterministic on CPU).
    psnr = resimulation_psnr([instance], [(fit.family, fit.parameters)], observed=observed)
    assert psnr[0] == pytest.approx(fit.psnr) and fit.psnr < PSNR_CAP
    # Same seed, same fit, also when batched with another instance's search (one launch of 18 scenes).
    batched = baseline.fit_instances([instance, instance], np.concatenate([observed, observed]), generations=2,
                                     popsize=4, seed=0, parallel=2, progress=False)
    for again in batched:
        assert dataclasses.replace(again, seconds=0.0) == dataclasses.replace(fit, seconds=0.0)
    metrics = compute_metrics(baseline.predictions_of([instance], [fit]))
    assert metrics["families"]["sand"]["acc"] == 1.0
    assert metrics["families"]["sand"]["correct"]["friction_angle"] == pytest.approx(
        math.degrees(abs(fit.parameters["friction_angle"] - true_phi)))


def test_simulator_progress_bars_are_left_out_of_a_log(tmp_path, capsys):
    """README: long work draws progress bars on a terminal only. Simulating the observed videos drew the
    simulator's bars (prepare instances, simulate + render) into a redirected stderr."""
    args = baseline.build_parser().parse_args(
        ["--size", "tiny", "--split", "unseen", "--instances", "1", "--generations", "1", "--popsize", "2",
         "--out", str(tmp_path / "b.json")])
    baseline.run(args)  # progress asked for, stderr not a terminal (captured)
    err = capsys.readouterr().err
    assert "simulate + render" not in err and "prepare instances" not in err, err


def test_cli_fits_episodes_read_from_a_bag_and_writes_the_report(tmp_path, capsys):
    out = tmp_path / "baseline.json"
    args = baseline.build_parser().parse_args(
        ["--bags", str(SAMPLE_BAG), "--instances", "1", "--generations", "1", "--popsize", "2",
         "--out", str(out), "--no-progress"])
    baseline.run(args)
    # Strict JSON (jq reads it): the families with no instance here have null, not NaN, metrics.
    result = json.loads(out.read_text(), parse_constant=lambda name: pytest.fail(f"{name} in strict JSON"))
    assert result["metrics"]["families"]["jelly"]["acc"] is None
    fit, = result["fits"]
    assert fit["episode_id"] == "unseen-bull-sand-0000"  # the seeded subset of the bag's 6 episodes
    assert fit["evaluations"] == 3 and fit["loss"] <= fit["initial_loss"]
    assert set(fit["parameters"]) == {"friction_angle"}
    assert fit["psnr"] == pytest.approx(10 * math.log10(1 / fit["loss"]))
    assert result["metrics"]["families"]["sand"]["acc"] == 1.0 and result["seconds_per_instance"] > 0
    assert result["psnr"]["families"]["sand"] == pytest.approx(fit["psnr"])
    printed = capsys.readouterr().out
    assert "| sand Acc |" in printed and "re-simulation PSNR" in printed
    assert "1 x 2 + 1 simulations each" in printed  # the start point is simulated too (evaluations == 3)


def test_registered_as_a_training_subcommand_with_help(capsys):
    from training.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main(["baseline", "--help"])
    assert exit_info.value.code == 0
    assert "--generations" in capsys.readouterr().out


def test_an_out_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """An --out that is a folder, or in a folder that cannot be made or written, is one line before the
    simulations and the CMA-ES, instead of an IsADirectory/permission error after them."""
    from training.__main__ import main

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before --out was checked")

    for name in ("observed_from_bags", "resimulate", "fit_instances"):
        monkeypatch.setattr(baseline, name, no_work)
    (tmp_path / "folder").mkdir()
    (tmp_path / "afile").write_text("")
    for source in (["--bags", str(SAMPLE_BAG)], ["--size", "tiny"]):  # observed videos read or simulated
        for out, expected in ((tmp_path / "folder", f"--out {tmp_path / 'folder'} is a folder; pass a .json file"),
                              (tmp_path / "afile" / "b.json", f"{tmp_path / 'afile'} is not a folder")):
            assert main(["baseline", *source, "--instances", "1", "--out", str(out), "--no-progress"]) == 1
            line = capsys.readouterr().err.splitlines()[-1]
            assert line.startswith("python -m training baseline: ") and expected in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "folder"] and not any((tmp_path / "folder").iterdir())


@pytest.mark.parametrize("argv, expected", [
    (["--generations", "0"], "argument --generations: expected a whole number >= 1, got '0'"),
    (["--popsize", "1"], "argument --popsize: expected a whole number >= 2, got '1'"),
    (["--parallel", "0"], "argument --parallel: expected a whole number >= 1, got '0'"),
    (["--sigma0", "0"], "argument --sigma0: expected a number > 0, got '0'"),
    (["--sigma0", "nan"], "argument --sigma0: expected a number > 0, got 'nan'"),
    (["--instances", "-2"], "argument --instances: expected a whole number >= 0, got '-2'"),
])
def test_a_bad_search_setting_is_refused_before_the_observed_videos_are_simulated(tmp_path, capsys, monkeypatch,
                                                                                   argv, expected):
    """--generations 0 (or --popsize 1, --parallel 0) failed in fit_instances only after the observed videos of the
    whole subset were simulated (minutes at paper size); --sigma0 0 failed inside cma, --instances -2 fitted all."""
    from training.__main__ import main

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the arguments were checked")

    for name in ("observed_from_bags", "resimulate", "fit_instances"):
        monkeypatch.setattr(baseline, name, no_work)
    with pytest.raises(SystemExit) as exit_info:
        main(["baseline", "--size", "tiny", "--out", str(tmp_path / "b.json"), "--no-progress", *argv])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(f"error: {expected}")


def _fake_simulations(monkeypatch, loss_of):
    """resimulate/mask_mse stand-ins (no Warp): a candidate's loss is loss_of(its SI parameters)."""
    batches = []

    def resimulate(instances, candidates, device, view, frame_count):
        batches.append(candidates)
        return np.zeros((len(candidates), frame_count, 2, 2), np.uint8)

    def mask_mse(masks, observed):
        return np.array([loss_of(parameters) for _, parameters in batches[-1]], np.float32)

    monkeypatch.setattr(baseline, "resimulate", resimulate)
    monkeypatch.setattr(baseline, "mask_mse", mask_mse)
    return batches


JELLY = next(i for i in benchmark("tiny", "unseen") if i.material == "jelly")


def test_a_candidate_whose_simulation_failed_counts_as_the_worst(monkeypatch):
    """A NaN loss (a failed simulation) was picked by np.argmin as the generation's best, so the finite losses
    of that generation were never considered (and cma took the NaN for the median)."""
    start = baseline.from_unit("jelly", [0.5, 0.5])

    def loss_of(parameters):  # the start point and every candidate softer than it "went unstable"
        if parameters["youngs_modulus"] <= start["youngs_modulus"] * (1 + 1e-9):
            return math.nan
        return abs(math.log(parameters["youngs_modulus"] / 4e5)) + abs(parameters["poissons_ratio"] - 0.3)

    batches = _fake_simulations(monkeypatch, loss_of)
    fit, = baseline.fit_instances([JELLY], np.zeros((1, 3, 2, 2), np.uint8), generations=3, popsize=6, progress=False)
    first = [loss_of(p) for _, p in batches[0]]
    assert math.isnan(fit.initial_loss) and not all(math.isnan(v) for v in first)
    assert fit.history[0] == pytest.approx(np.nanmin(first))  # was inf: the NaN start point "won"
    all_losses = [loss_of(p) for batch in batches for _, p in batch]
    assert fit.loss == pytest.approx(np.nanmin(all_losses)) and fit.loss == pytest.approx(loss_of(fit.parameters))


def test_an_instance_without_any_finite_loss_is_named(monkeypatch):
    _fake_simulations(monkeypatch, lambda parameters: math.nan)
    with pytest.raises(ValueError, match=f"{JELLY.episode_id}: no candidate simulation gave a finite mask loss"):
        baseline.fit_instances([JELLY], np.zeros((1, 3, 2, 2), np.uint8), generations=1, popsize=2, progress=False)


def test_observed_videos_with_nan_are_refused_before_the_search(monkeypatch):
    """A NaN in a float observed video passes mask_mse's [0, 1] check and made every loss NaN."""
    batches = []
    monkeypatch.setattr(baseline, "resimulate", lambda *a, **k: batches.append(a) or np.zeros((3, 3, 2, 2), np.uint8))
    observed = np.zeros((1, 3, 2, 2), np.float32)
    observed[0, 1, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"finite and in \[0, 1\]"):
        baseline.fit_instances([JELLY], observed, generations=1, popsize=2, progress=False)
    assert batches == []


# ---- mutation-testing audit (round 2)


def test_cma_es_is_told_the_loss_of_each_point_it_asked_for(monkeypatch):
    """Each generation, cma's tell gets, for each candidate it asked for, that candidate's own loss (capped
    at FAILED_LOSS); the start point's loss (generation 0) is the fit's initial loss and is not told. Losses
    shifted by one (the start point's told in place of the first candidate's) or all raised to the cap
    passed the other tests."""
    import cma

    def loss_of(parameters):
        return abs(math.log(parameters["youngs_modulus"] / 4e5)) + abs(parameters["poissons_ratio"] - 0.3)

    _fake_simulations(monkeypatch, loss_of)
    told = []
    real_tell = cma.CMAEvolutionStrategy.tell

    def tell(self, solutions, function_values, *args, **kwargs):
        told.append((np.array(solutions), list(function_values)))
        return real_tell(self, solutions, function_values, *args, **kwargs)

    monkeypatch.setattr(cma.CMAEvolutionStrategy, "tell", tell)
    fit, = baseline.fit_instances([JELLY], np.zeros((1, 3, 2, 2), np.uint8), generations=3, popsize=5,
                                  progress=False)
    assert len(told) == 3
    for solutions, values in told:
        assert len(solutions) == len(values) == 5
        expected = [min(loss_of(baseline.from_unit("jelly", s)), baseline.FAILED_LOSS) for s in solutions]
        np.testing.assert_allclose(values, expected, rtol=1e-6)
    assert fit.initial_loss == pytest.approx(loss_of(baseline.from_unit("jelly", [0.5, 0.5])), rel=1e-6)
    best = min(min(loss_of(baseline.from_unit("jelly", s)) for s in solutions) for solutions, _ in told)
    assert fit.loss == pytest.approx(min(best, fit.initial_loss), rel=1e-6)


def test_seconds_per_instance_is_the_batch_time_shared_by_its_instances(monkeypatch):
    """Instances optimised together share their batch's wall time: 2 instances in a batch that took 10 s
    are 5 s each (a clock that advances 10 s per reading)."""
    from types import SimpleNamespace

    _fake_simulations(monkeypatch, lambda parameters: 0.1)
    readings = iter(range(0, 1000, 10))
    monkeypatch.setattr(baseline, "time", SimpleNamespace(perf_counter=lambda: float(next(readings))))
    fits = baseline.fit_instances([JELLY, JELLY], np.zeros((2, 3, 2, 2), np.uint8), generations=1, popsize=2,
                                  parallel=2, progress=False)
    assert [fit.seconds for fit in fits] == [5.0, 5.0]


def test_each_unit_coordinate_maps_to_its_own_parameter():
    """Coordinate i is SAMPLED_PARAMETERS[family][i]: (0, 1) is jelly's lowest E with its highest nu (points with
    equal coordinates, as the other test uses, cannot tell a swap)."""
    (e_low, _, _), (_, nu_high, _) = (FAMILY_RANGES["jelly"][n] for n in ("youngs_modulus", "poissons_ratio"))
    assert baseline.from_unit("jelly", [0.0, 1.0]) == pytest.approx({"youngs_modulus": e_low, "poissons_ratio": nu_high})
    plasticine = baseline.from_unit("plasticine", [1.0, 0.5, 0.0])
    assert plasticine["youngs_modulus"] == pytest.approx(FAMILY_RANGES["plasticine"]["youngs_modulus"][1])
    assert plasticine["yield_stress"] == pytest.approx(FAMILY_RANGES["plasticine"]["yield_stress"][0])
