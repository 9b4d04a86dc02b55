"""Re-simulation PSNR of a student on bags (training/resim_psnr.py): real onnxruntime, real Warp CPU."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ad_sim.instances import benchmark
from ad_sim.materials import FAMILIES
from ad_sim.resimulate import PSNR_CAP, resimulation_psnr
from ad_sim.rosbag import BagReader, BagWriter, qos_profile
from estimator_models import build_clip_model
from training import resim_psnr

SAMPLE_BAG = Path(__file__).resolve().parents[1] / "bags" / "samples" / "unseen-masks-0of1"  # tiny unseen split


def test_subset_is_seeded_sorted_and_distinct():
    a = resim_psnr.select(5, 20, seed=3)
    np.testing.assert_array_equal(a, resim_psnr.select(5, 20, seed=3))
    assert len(set(a)) == 5 and list(a) == sorted(a) and a.max() < 20
    assert not np.array_equal(a, resim_psnr.select(5, 20, seed=4))
    np.testing.assert_array_equal(resim_psnr.select(0, 4, seed=0), np.arange(4))


def test_bag_episodes_carry_the_benchmark_instances_and_their_videos():
    instances, videos = resim_psnr.observed_from_bags(SAMPLE_BAG)
    expected = benchmark("tiny", "unseen")
    assert [i.episode_id for i in instances] == [i.episode_id for i in expected]
    for got, want in zip(instances, expected):
        assert (got.shape, got.material, got.seed) == (want.shape, want.material, want.seed)
        np.testing.assert_array_equal(got.pose(), want.pose())
        assert got.parameters == pytest.approx(want.parameters, rel=1e-12)
    assert videos.shape == (6, 25, 128, 128) and videos.dtype == np.uint8 and set(np.unique(videos)) == {0, 255}


def test_simulator_progress_bars_are_left_out_of_a_log(tmp_path, capsys):
    """README: long work draws progress bars on a terminal only. The simulator's bars (prepare instances,
    simulate + render) went to a redirected stderr, into the log."""
    model = build_clip_model(tmp_path / "student.onnx", seed=3)
    args = resim_psnr.build_parser().parse_args(
        ["--model", str(model), "--bags", str(SAMPLE_BAG), "--instances", "1", "--out", str(tmp_path / "p.json")])
    resim_psnr.run(args)  # progress asked for, stderr not a terminal (captured)
    err = capsys.readouterr().err
    assert "simulate + render" not in err and "prepare instances" not in err, err


def test_cli_scores_a_students_estimates_by_resimulation(tmp_path, capsys):
    model = build_clip_model(tmp_path / "student.onnx", seed=3)
    out = tmp_path / "psnr.json"
    args = resim_psnr.build_parser().parse_args(
        ["--model", str(model), "--bags", str(SAMPLE_BAG), "--instances", "1", "--out", str(out), "--no-progress"])
    resim_psnr.run(args)
    result = json.loads(out.read_text())
    episode, = result["episodes"]
    assert episode["episode_id"] == "unseen-bull-sand-0000" and episode["true_material"] == "sand"
    assert episode["material"] in FAMILIES and 0.0 < episode["psnr"] < PSNR_CAP  # random weights: not the truth
    assert result["metrics"]["n"] == 1 and result["psnr"]["mean"] == pytest.approx(episode["psnr"])
    # The same candidate scored against the ground truth simulated here (not read from the bag).
    instance = next(i for i in benchmark("tiny", "unseen") if i.episode_id == episode["episode_id"])
    again = resimulation_psnr([instance], [(episode["material"], episode["parameters"])])
    assert again[0] == pytest.approx(episode["psnr"])
    assert "re-simulation PSNR" in capsys.readouterr().out


def test_registered_as_a_training_subcommand_with_help(capsys):
    from training.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main(["resim-psnr", "--help"])
    assert exit_info.value.code == 0
    assert "--model" in capsys.readouterr().out


def test_truncated_bags_are_read_up_to_their_last_complete_chunk(tmp_path):
    """A recording cut short (a killed recorder) is read as every training stage reads it: in recover mode."""
    (tmp_path / "cut").mkdir()
    (source,) = SAMPLE_BAG.glob("*.mcap")
    data = source.read_bytes()
    (tmp_path / "cut" / source.name).write_bytes(data[: len(data) // 2])
    (tmp_path / "cut" / "metadata.yaml").write_bytes((SAMPLE_BAG / "metadata.yaml").read_bytes())
    with pytest.warns(UserWarning, match=r"is truncated: no MCAP footer .*: recovered \d+ messages"):
        instances, videos = resim_psnr.observed_from_bags(tmp_path / "cut")
    expected = [i.episode_id for i in benchmark("tiny", "unseen")]
    assert 0 < len(instances) < len(expected) and [i.episode_id for i in instances] == expected[: len(instances)]
    assert videos.shape == (len(instances), 25, 128, 128)


def test_an_unusable_frame_loses_its_episode_only(tmp_path, caplog):
    """A mask the estimator refuses skips its episode, named with the frame; the other episodes are scored."""
    raw, decoded = BagReader(SAMPLE_BAG, raw=True), BagReader(SAMPLE_BAG)
    masks_seen = 0
    with BagWriter(tmp_path / "bad") as writer:
        for topic, type_name in raw.topics().items():
            writer.add_topic(topic, type_name, [qos_profile()])
        for (topic, stamp, data), (_, _, message) in zip(raw, decoded):
            if topic == resim_psnr.MASK_TOPIC:
                masks_seen += 1
                if masks_seen == 30:  # the second episode's 5th frame
                    message.encoding, bad_stamp = "32FC1", stamp
                    data = message
            writer.write(topic, stamp, data)
    instances, _ = resim_psnr.observed_from_bags(tmp_path / "bad")
    expected = [i.episode_id for i in benchmark("tiny", "unseen")]
    assert [i.episode_id for i in instances] == expected[:1] + expected[2:]
    assert any(m.startswith(f"{tmp_path / 'bad'}: episode {expected[1]}: {resim_psnr.MASK_TOPIC} frame stamped "
                            f"{bad_stamp / 1e9:.3f} s: unsupported encoding '32FC1'") for m in caplog.messages)
    # Only the chosen subset is decoded: a subset without that episode meets no bad frame.
    seed = next(seed for seed in range(100) if 1 not in resim_psnr.select(2, len(expected), seed))
    caplog.clear()
    instances, videos = resim_psnr.observed_from_bags(tmp_path / "bad", 2, seed)
    assert [i.episode_id for i in instances] == [expected[j] for j in resim_psnr.select(2, len(expected), seed)]
    assert videos.shape[0] == 2 and not any("32FC1" in m for m in caplog.messages)


def test_a_device_this_machine_lacks_is_refused_before_any_work(tmp_path, capsys):
    from training.__main__ import main

    # Neither the model nor the bags exist: the device is checked first.
    for command in (["resim-psnr", "--model", str(tmp_path / "missing.onnx"), "--bags", str(tmp_path)],
                    ["baseline", "--bags", str(tmp_path)]):
        assert main([*command, "--device", "cuda:99"]) == 1
        (line,) = capsys.readouterr().err.splitlines()
        assert line.startswith(f"python -m training {command[0]}: Warp device 'cuda:99' is not available")


def test_an_out_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """An --out that is a folder, or in a folder that cannot be made or written, is one line before the
    re-simulation, instead of an IsADirectory/permission error after it."""
    from training.__main__ import main

    def no_work(*args, **kwargs):
        raise AssertionError("the re-simulation started before --out was checked")

    monkeypatch.setattr(resim_psnr, "model_psnr", no_work)
    model = build_clip_model(tmp_path / "student.onnx", seed=3)
    (tmp_path / "folder").mkdir()
    (tmp_path / "afile").write_text("")
    command = ["resim-psnr", "--model", str(model), "--bags", str(SAMPLE_BAG), "--no-progress"]
    for out, expected in ((tmp_path / "folder", f"--out {tmp_path / 'folder'} is a folder; pass a .json file name"),
                          (tmp_path / "afile" / "r.json", f"{tmp_path / 'afile'} is not a folder")):
        assert main([*command, "--out", str(out)]) == 1
        line = capsys.readouterr().err.splitlines()[-1]
        assert line.startswith("python -m training resim-psnr: ") and expected in line, line
    # The default --out's folder too (runs/resim_psnr under the working folder).
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").write_text("")
    assert main(command) == 1
    assert "runs is not a folder" in capsys.readouterr().err.splitlines()[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "folder", "runs", "student.onnx"]


def test_psnr_is_ten_log10_of_one_over_the_mask_mse_and_summarised_per_true_family():
    """SPEC 8 from its text, by hand: PSNR = 10 log10(1 / MSE) over the mask frames read in [0, 1] (uint8
    0/255), every frame and pixel; identical videos score the cap; the summary's mean, median and per
    true family mean are over the instances' PSNRs, an absent family n/a."""
    from ad_sim.resimulate import mask_psnr

    observed = np.zeros((2, 25, 128, 128), np.uint8)
    predicted = observed.copy()
    predicted[0, 3, :8, :8] = 255  # 64 pixels wrong of 25 x 128 x 128
    predicted[1, :, :64] = 255  # half of every frame wrong
    psnr = mask_psnr(predicted, observed)
    assert psnr == pytest.approx([10 * np.log10(25 * 128 * 128 / 64), 10 * np.log10(2.0)], rel=1e-6)  # float32 means
    assert mask_psnr(observed[0], observed[0]) == PSNR_CAP
    summary = resim_psnr.psnr_summary(["sand", "jelly", "sand"], np.array([20.0, 30.0, PSNR_CAP]))
    assert summary["mean"] == pytest.approx(50.0) and summary["median"] == 30.0 and summary["exact"] == 1
    assert summary["families"]["sand"] == pytest.approx(60.0) and summary["families"]["jelly"] == 30.0
    assert np.isnan(summary["families"]["plasticine"])


@pytest.mark.parametrize("key, value, expected", [
    ("ad.class_names", ["sand", "jelly", "plasticine"], "differ from"),
    ("ad.parameter_names", ["youngs_modulus", "poissons_ratio", "yield_stress", "friction"],
     "lacks ['friction_angle']"),
])
def test_a_model_whose_classes_or_parameters_the_metrics_cannot_read_is_refused(tmp_path, capsys, monkeypatch, key,
                                                                                  value, expected):
    """As `evaluate` refuses it: the probabilities were read in FAMILIES order, so a model listing its classes in
    another order was scored and re-simulated as the wrong family (and one lacking a parameter failed after
    the bags were decoded, with "'friction_angle' is not in list")."""
    import onnx

    from training.__main__ import main

    def no_work(*args, **kwargs):
        raise AssertionError("the bags were read before the model was checked")

    monkeypatch.setattr(resim_psnr, "selected_episodes", no_work)
    model_file = build_clip_model(tmp_path / "student.onnx", seed=3)
    model = onnx.load(str(model_file))
    next(p for p in model.metadata_props if p.key == key).value = json.dumps(value)
    if key == "ad.parameter_names":
        ranges = next(p for p in model.metadata_props if p.key == "ad.parameter_ranges")
        ranges.value = ranges.value.replace('"friction_angle"', '"friction"')
    onnx.save(model, str(model_file))
    assert main(["resim-psnr", "--model", str(model_file), "--bags", str(SAMPLE_BAG), "--out",
                 str(tmp_path / "r.json"), "--no-progress"]) == 1
    line = capsys.readouterr().err.splitlines()[-1]
    assert line.startswith(f"python -m training resim-psnr: {model_file}: ") and expected in line, line


def test_a_negative_subset_size_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        resim_psnr.build_parser().parse_args(["--model", "m.onnx", "--bags", str(tmp_path), "--instances", "-3"])
    assert exit_info.value.code == 2  # was: every episode, as for 0
    assert "argument --instances: expected a whole number >= 0, got '-3'" in capsys.readouterr().err


# ---- mutation-testing audit (round 2)


def test_summary_per_family_is_a_mean_and_exact_counts_only_the_cap():
    """Per true family the summary is the mean of its instances' PSNRs (three sand values whose median differs
    from their mean), and only PSNR_CAP (identical videos) counts as reproduced to the pixel: one wrong pixel
    (~56 dB) or a value just below the cap does not."""
    one_pixel = 10 * np.log10(25 * 128 * 128)
    psnr = np.array([10.0, 20.0, 60.0, one_pixel, PSNR_CAP - 0.01, PSNR_CAP])
    summary = resim_psnr.psnr_summary(["sand", "sand", "sand", "jelly", "jelly", "plasticine"], psnr)
    assert summary["families"]["sand"] == pytest.approx(30.0)
    assert summary["families"]["jelly"] == pytest.approx((one_pixel + PSNR_CAP - 0.01) / 2)
    assert summary["families"]["plasticine"] == PSNR_CAP
    assert summary["exact"] == 1
    assert summary["mean"] == pytest.approx(psnr.mean()) and summary["median"] == pytest.approx((60.0 + one_pixel) / 2)
