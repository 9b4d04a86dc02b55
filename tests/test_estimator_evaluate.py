"""`ad_estimator evaluate`: offline metrics over bags (no ROS runtime)."""
import csv
import json
import math
import re
import shutil
import warnings
from collections import Counter

import numpy as np
import pytest
from mcap.reader import make_reader

from ad_estimator import estimate, evaluate
from ad_estimator.metrics import FAMILIES, family_ranges, table_labels
from ad_estimator.model import EstimatorModel
from ad_estimator.window import FrameWindow
from ad_sim import messages
from estimator_bags import EPISODES, damaged, write_test_bag
from estimator_models import build_streaming_model, falling_masks


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("evaluate")
    return build_streaming_model(d), write_test_bag(d / "bags" / "one")


def test_report_with_temporal_ood_rows(setup, tmp_path, capsys):
    model, bag = setup
    assert evaluate.main(["--model", str(model), "--bags", str(bag.parent), "--frames", "--out", str(tmp_path),
                          "--quiet"]) == 0
    table = capsys.readouterr().out
    rows = [line.split("|")[1].strip() for line in table.splitlines() if line.startswith("| ") and "frames" not in line]
    assert rows == ["25", "24", "22", "18", "15"]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert set(metrics["frames"]) == {"25", "24", "22", "18", "15"}
    assert (tmp_path / "report.md").is_file() and (tmp_path / "confusion.png").is_file()
    predictions = json.loads((tmp_path / "predictions.json").read_text())["frames"]
    assert [p["true_material"] for p in predictions["25"]] == [m for m, _ in EPISODES]
    assert [p["frames_used"] for p in predictions["18"]] == [18, 18, 18]
    # Whether the model's sigmas are honest: calibration of the full clip (only), from every raw sigma.
    # This random-weight model gets no episode's family right, so every family's is null ...
    assert "calibration" not in metrics["frames"]["18"]
    assert check_calibration(metrics["frames"]["25"]["calibration"], predictions["25"]) == Counter()
    assert "## Uncertainty calibration (25 frames)" in (tmp_path / "report.md").read_text()
    # ... and one with other random weights gets the jelly right: its E and nu have coverages.
    other = build_streaming_model(tmp_path, name="other", seed=2)
    assert evaluate.main(["--model", str(other), "--bags", str(bag), "--out", str(tmp_path / "other"), "--quiet"]) == 0
    calibration = json.loads((tmp_path / "other" / "metrics.json").read_text())["frames"]["25"]["calibration"]
    episodes = json.loads((tmp_path / "other" / "predictions.json").read_text())["frames"]["25"]
    assert check_calibration(calibration, episodes) == Counter(jelly=1)
    assert "| jelly | E | 1 |" in (tmp_path / "other" / "report.md").read_text()


def check_calibration(calibration: dict, episodes: list[dict]) -> Counter:
    """Each family's sampled parameters, counted over its correctly classified episodes (all of which have
    a sigma), with finite coverages in [0, 1]; null where the family has none. Returns those counts."""
    assert all(len(e["raw_uncertainties"]) == 4 and all(u > 0 for u in e["raw_uncertainties"]) for e in episodes)
    correct = Counter(e["true_material"] for e in episodes if e["material"] == e["true_material"])
    assert {f: set(v) for f, v in calibration.items()} == {f: set(v) for f, v in family_ranges().items()}
    for family, parameters in calibration.items():
        for name, c in parameters.items():
            assert c["n"] == correct[family], (family, name)
            for key in ("coverage_1sigma", "coverage_2sigma", "error", "median_sigma"):
                if correct[family]:
                    assert math.isfinite(c[key]) and (0.0 <= c[key] <= 1.0 or "coverage" not in key), (family, key)
                else:
                    assert c[key] is None, (family, name, key)
    return correct


def test_training_evaluate_reports_calibration_too(setup, tmp_path, capsys):
    """`python -m training evaluate` (the training-side evaluator, on its cached dataset) passes the model's
    raw sigmas to the metrics as well: per-episode raw_uncertainties and the calibration section."""
    from training import evaluate as training_evaluate
    from training.synthetic import write_synthetic_bag

    model, _ = setup
    bags = tmp_path / "bags" / "unseen"
    write_synthetic_bag(bags / "unseen-0of1", 6, views=1, seed=12, split="unseen")
    training_evaluate.evaluate_model(model, bags, tmp_path / "cache", tmp_path / "out", progress=False,
                                     frames=(25, 18), record=False)
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]
    assert "calibration" not in saved["18"]
    episodes = json.loads((tmp_path / "out" / "predictions.json").read_text())["frames"]["25"]
    assert check_calibration(saved["25"]["calibration"], episodes), "no episode classified right: nothing checked"
    assert "## Uncertainty calibration (25 frames)" in (tmp_path / "out" / "report.md").read_text()


def test_training_evaluate_scores_a_looping_simulators_repeats_once(setup, tmp_path):
    """`python -m training evaluate` on a recording of a looping simulator scored each episode once a pass
    (as `ros2 run ad_estimator evaluate` no longer does): the same scores as one pass, and n counts episodes."""
    from ad_sim.generate import write_episodes
    from ad_sim.rosbag import BagWriter
    from training import evaluate as training_evaluate
    from training.synthetic import synthetic_episode

    model, _ = setup
    episodes = [synthetic_episode(i, 12, 1, "unseen") for i in range(4)]
    for name, passes in (("once", 1), ("looped", 2)):
        with BagWriter(tmp_path / name / "bag") as writer:
            for p in range(passes):
                write_episodes(writer, episodes, p * len(episodes))
        training_evaluate.evaluate_model(model, tmp_path / name, tmp_path / "cache", tmp_path / f"{name}_out",
                                         progress=False, frames=(25,), record=False)
    once, looped = (json.loads((tmp_path / f"{name}_out" / "metrics.json").read_text())
                    for name in ("once", "looped"))
    assert looped["frames"] == once["frames"] and once["frames"]["25"]["n"] == 4
    saved = json.loads((tmp_path / "looped_out" / "predictions.json").read_text())
    assert saved["episodes"] == 4 and len(saved["frames"]["25"]) == 4


def test_training_evaluate_that_cannot_write_leaves_the_earlier_report_whole(setup, tmp_path):
    """`python -m training evaluate` and `report` write their reports in a staging folder, moved in once
    complete: under a file size limit that stops them at the plots, the earlier report is as it was."""
    import subprocess
    import sys

    from training import evaluate as training_evaluate
    from training.synthetic import write_synthetic_bag

    model, _ = setup
    bags, out = tmp_path / "bags" / "unseen", tmp_path / "out"
    write_synthetic_bag(bags / "unseen-0of1", 3, views=1, seed=12, split="unseen")
    training_evaluate.evaluate_model(model, bags, tmp_path / "cache", out, progress=False, record=False)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {"report.md", "metrics.json", "predictions.json", "pred_vs_true.png"} <= set(before)
    limit = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000)); "
             "from training.__main__ import main; sys.exit(main(sys.argv[1:]))")
    for command in (["evaluate", "--model", str(model), "--bags", str(bags), "--cache", str(tmp_path / "cache"),
                     "--no-record", "--no-progress"], ["report", "--predictions", str(out / "predictions.json")]):
        proc = subprocess.run([sys.executable, "-c", limit, *command, "--title", "another", "--out", str(out)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 1 and "File too large" in proc.stderr, proc.stderr
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, command[0]


def test_frames_take_spaces_or_commas(setup, tmp_path, capsys):
    """`--frames 22,18 15` is the same as `--frames 22 18 15`: both evaluators read both forms."""
    model, bag = setup
    assert evaluate.main(["--model", str(model), "--bags", str(bag), "--frames", "22,18", "15", "--out", str(tmp_path),
                          "--quiet"]) == 0
    assert set(json.loads((tmp_path / "metrics.json").read_text())["frames"]) == {"25", "22", "18", "15"}


def test_per_episode_prediction_is_the_models_on_those_frames(setup, tmp_path):
    """Evaluate's estimate of an episode equals the model run directly on that episode's masks."""
    model_path, bag = setup
    model = EstimatorModel.load(model_path)
    (instance, frames), *_ = evaluate.episode_frames(bag)
    prediction = evaluate.predict_episode(model, bag, instance, frames, 25)
    direct = model.predict(np.stack([model.encode(m) for m in falling_masks(seed=100)]), np.ones(25, bool))
    np.testing.assert_allclose(prediction.probabilities, direct.probabilities, rtol=1e-6)
    assert prediction.episode_id == instance.episode_id and prediction.oldest_stamp_ns == 0


def test_earlier_frames_reach_the_frame_encoder_and_each_frame_is_encoded_once(setup, tmp_path, monkeypatch):
    """A frame encoder that sees 3 earlier frames: every prefix's estimate is that of each frame encoded
    with its 3 predecessors, newest first; the prefixes share the episode's encodings."""
    _, bag = setup
    model = EstimatorModel.load(build_streaming_model(tmp_path, previous_frames=3))
    encode = model.encode
    calls = []
    monkeypatch.setattr(model, "encode", lambda mask, earlier=(): calls.append(1) or encode(mask, earlier))
    result = evaluate.evaluate(model, [bag], [25, 18], progress=False)
    assert len(calls) == 25 * len(EPISODES)
    for index in range(len(EPISODES)):
        masks = falling_masks(seed=100 + index)
        features = np.stack([encode(mask, list(masks[:t][::-1])) for t, mask in enumerate(masks)])
        for k in (25, 18):
            direct = model.predict(features[:k], np.ones(k, bool))
            np.testing.assert_allclose(result.predictions[k][index].probabilities, direct.probabilities, rtol=1e-6)


def test_clear_errors(setup, tmp_path, capsys):
    model, bag = setup
    assert evaluate.main(["--model", str(tmp_path / "absent.onnx"), "--bags", str(bag)]) == 1
    assert "absent.onnx" in capsys.readouterr().err
    assert evaluate.main(["--model", str(model), "--bags", str(tmp_path / "nowhere")]) == 1
    assert "nowhere" in capsys.readouterr().err
    for frames, message in (("30", "--frames [30]: each K must be in 1..25"), ("20,0", "--frames [0]: each K"),
                            ("24,x", "expected frame counts such as 24 18 or 24,18"),
                            (",", "expected frame counts such as 24 18 or 24,18, got ','")):
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main(["--model", str(model), "--bags", str(bag), "--frames", frames])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    for threads in ("0", "-3"):  # were taken, and handed to onnxruntime
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main(["--model", str(model), "--bags", str(bag), "--threads", threads])
        assert exit_info.value.code == 2 and "argument --threads: expected a whole number >= 1" in capsys.readouterr().err


def test_truncated_recording_needs_recover_and_then_gives_its_complete_episodes(setup, tmp_path, capsys):
    """A killed recorder leaves a file without a footer: evaluate says so and names --recover;
    with it, the episodes in complete chunks are scored, with a one-line warning."""
    model, _ = setup
    bag = write_test_bag(tmp_path / "killed", chunk_size=20_000)
    (file,) = bag.glob("*.mcap")
    with open(file, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    cut = chunks[len(chunks) // 2]  # killed while writing the middle chunk (the second episode)
    file.write_bytes(file.read_bytes()[: cut.chunk_start_offset + cut.chunk_length // 2])
    assert evaluate.main(["--model", str(model), "--bags", str(bag), "--quiet", "--out", str(tmp_path / "a")]) == 1
    assert "truncated" in (err := capsys.readouterr().err) and "--recover" in err, err
    with pytest.warns(UserWarning, match="truncated"):
        assert evaluate.main(["--model", str(model), "--bags", str(bag), "--quiet", "--recover",
                              "--out", str(tmp_path / "b")]) == 0
    assert warnings.formatwarning("x is truncated", UserWarning, "rosbag.py", 1) == "warning: x is truncated\n"
    predictions = json.loads((tmp_path / "b" / "predictions.json").read_text())
    assert 1 <= len(predictions["frames"]["25"]) < len(EPISODES)
    # What was lost is recorded with the results, as the other input problems are, not only warned about.
    (problem,) = predictions["source_problems"]
    assert problem.startswith(f"{file} is truncated: no MCAP footer") and "recovered" in problem, problem
    assert "input problems: 1 problem(s) reading the bags' files" in capsys.readouterr().out
    assert "Input problems: 1 problem(s) reading the bags' files" in (tmp_path / "b" / "report.md").read_text()


def test_an_intact_bag_records_no_source_problem(setup, tmp_path, capsys):
    model, bag = setup
    assert run_main(model, bag, tmp_path / "out") == 0
    assert json.loads((tmp_path / "out" / "predictions.json").read_text())["source_problems"] == []
    out = capsys.readouterr().out
    assert "input problems" not in out and out.rstrip().endswith("predictions.json")
    assert "Input problems" not in (tmp_path / "out" / "report.md").read_text()
    # A second run into the same folder says that it replaced the first's report.
    assert run_main(model, bag, tmp_path / "out") == 0
    assert capsys.readouterr().out.rstrip().endswith("predictions.json (it replaced the report of an earlier run)")


def test_a_bag_with_nothing_readable_says_so(setup, tmp_path, capsys):
    """Cut inside its first chunk: --recover reads nothing, and the one-line error says so instead of
    blaming the topic."""
    model, _ = setup
    bag = write_test_bag(tmp_path / "cut")
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[:300])
    assert run_main(model, bag, tmp_path / "out", "--recover") == 1
    assert capsys.readouterr().err == (f"evaluate: nothing readable in {file}: it is truncated before its first "
                                       "complete chunk (300 bytes; was the writer killed?)\n")


def test_an_unusable_metadata_yaml_needs_recover_and_is_recorded(setup, tmp_path, capsys):
    """A metadata.yaml that is not YAML: one line naming --recover; with it, the .mcap beside it is scored
    in full, and the problem is recorded with the results."""
    model, good = setup
    bag = tmp_path / "bag"
    shutil.copytree(good, bag)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n  : - x: {")
    assert run_main(model, bag, tmp_path / "a") == 1
    assert capsys.readouterr().err == (f"evaluate: {bag}/metadata.yaml is unreadable (not YAML: expected ',' or ']', "
                                       "but got ':' at line 2); pass --recover to read the 1 .mcap file(s) beside it\n")
    with pytest.warns(UserWarning, match="metadata.yaml is unreadable"):
        assert run_main(model, bag, tmp_path / "b", "--recover") == 0
    predictions = json.loads((tmp_path / "b" / "predictions.json").read_text())
    assert len(predictions["frames"]["25"]) == len(EPISODES)
    assert predictions["source_problems"] == [f"{bag}/metadata.yaml is unreadable (not YAML: expected ',' or ']', but "
                                              "got ':' at line 2); reading the 1 .mcap file(s) beside it"]


# --------------------------------------------------------------------------- bad input


def run_main(model, bag, out, *extra):
    return evaluate.main(["--model", str(model), "--bags", str(bag), "--quiet", "--out", str(out), *extra])


@pytest.mark.parametrize("edit, reason", [
    (lambda m: m.update(encoding="32FC1"), "unsupported encoding '32FC1'"),
    (lambda m: m.update(data=m["data"][:100]), "data length 100 != step 128 * height 128"),
    (lambda m: m.update(step=10), "step 10 < width 128"),
    (lambda m: m.update(height=0, width=0, step=0, data=b""), "empty image 0x0"),
    (lambda m: m.update(height=100_000, width=100_000, step=100_000), "exceeds max_image_pixels"),
])
def test_a_frame_the_node_rejects_is_skipped_warned_and_counted(setup, tmp_path, capsys, edit, reason):
    """The rest of the run goes on; the episode gets the estimate the node's window gives without that frame."""
    model_path, _ = setup
    bag = write_test_bag(tmp_path / "bag", edit_mask=damaged(1, 5, edit))
    with pytest.warns(UserWarning, match=rf"bag: episode test-disc-plasticine-0001: 1 mask frame\(s\) skipped.*"
                                         rf"stamp 1\.625 s: .*{re.escape(reason)}"):
        assert run_main(model_path, bag, tmp_path / "out") == 0
    assert "input problems: 1 mask frame(s) skipped, as the node rejects them" in capsys.readouterr().out
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["episode_id"] for p in predictions["frames"]["25"]] == [f"test-disc-{m}-000{i}" for i, (m, _) in
                                                                     enumerate(EPISODES)]
    ((skipped),) = predictions["skipped_frames"]
    assert skipped["episode_id"] == "test-disc-plasticine-0001" and skipped["stamp_ns"] == 1_625_000_000
    assert reason in skipped["reason"]
    model = EstimatorModel.load(model_path)
    window = FrameWindow(model.info.frame_interval, model.info.frame_count,  # the node's defaults
                         history=model.info.previous_frames)
    masks = falling_masks(seed=101)
    (out,) = [o for k in range(25) if k != 5 for o in window.add(messages.frame_stamp(1, k), masks[k], model.encode)]
    episode = predictions["frames"]["25"][1]
    assert episode["slots"] == 25 and episode["newest_stamp_ns"] == out.newest_stamp_ns
    np.testing.assert_allclose(episode["probabilities"], model.predict(out.features, out.valid).probabilities,
                               rtol=1e-5)
    assert "Input problems: 1 mask frame(s) skipped" in (tmp_path / "out" / "report.md").read_text()


def test_a_frame_with_a_malformed_stamp_is_skipped_as_in_the_node(setup, tmp_path, capsys):
    """A stamp with nanosec >= 1e9, which the node and estimate reject: one frame skipped (it ended the
    whole evaluation with an error), the episode scored from the others as the node would."""
    model_path, _ = setup
    bag = write_test_bag(tmp_path / "bag", edit_mask=damaged(1, 5, lambda m: m["header"]["stamp"].update(
        nanosec=1_500_000_000)))
    with pytest.warns(UserWarning, match=r"episode test-disc-plasticine-0001: 1 mask frame\(s\) skipped.* stamp "
                                         r"\(malformed\): stamp nanosec 1500000000 is not below 1e9"):
        assert run_main(model_path, bag, tmp_path / "out") == 0
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    ((skipped),) = predictions["skipped_frames"]
    assert skipped["stamp_ns"] is None and skipped["episode_id"] == "test-disc-plasticine-0001"
    assert [p["slots"] for p in predictions["frames"]["25"]] == [25, 25, 25]
    with pytest.warns(UserWarning, match="stamp nanosec 1500000000"):  # estimate skips it too
        assert estimate.main(["--model", str(model_path), str(bag), "--out", str(tmp_path / "e.csv"), "--quiet"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "e.csv")))
    np.testing.assert_allclose(predictions["frames"]["25"][1]["probabilities"],
                               [float(rows[1][f"p_{c}"]) for c in ("jelly", "plasticine", "sand")], rtol=1e-5)


def test_an_image_size_change_restarts_the_window_as_in_the_node(setup, tmp_path):
    """A 64x64 frame 5 in a 128x128 episode: the window restarts twice (at frames 5 and 6), so the episode's
    window never fills 25 (nor 20: frames 6 to 24 fill 19) slots: it is left out of those rows, kept in the K = 4
    row (slots that end before the change)."""
    model_path, _ = setup
    small = falling_masks(seed=3, size=64)[0]
    bag = write_test_bag(tmp_path / "bag", edit_mask=damaged(1, 5, lambda m: m.update(
        height=64, width=64, step=64, data=small.tobytes())))
    with pytest.warns(UserWarning) as caught:
        assert run_main(model_path, bag, tmp_path / "out", "--frames", "20", "4") == 0
    messages = [str(w.message) for w in caught]
    assert any("episode test-disc-plasticine-0001: the image size changes from 128x128 to 64x64 at stamp 1.625 s"
               in m for m in messages), messages
    restarted = "the first: its window restarted at the image size change at stamp 1.650 s)"
    assert any("episode test-disc-plasticine-0001: left out of the K = 25, 20 row(s)" in m and m.endswith(restarted)
               for m in messages), messages
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [len(predictions["frames"][k]) for k in ("25", "20", "4")] == [2, 2, 3]
    assert predictions["left_out"]["25"] == [{"bag": str(bag), "episode_id": "test-disc-plasticine-0001",
                                              "reason": "its window holds 19 of 25 frame slots"}]
    assert "Clips: 2;" in (tmp_path / "out" / "report.md").read_text()


def test_a_row_ends_with_its_last_slot_whatever_comes_after(setup, tmp_path):
    """Row K holds the frames up to its last slot: what comes later changes none of its slots, as in the node,
    whose estimate from them is out by then. An image size change at frame 15 left the K = 15 row (its slots end
    at frame 14) out; frames 27 and 28 of a 30-frame episode out of order left every row out."""
    model_path, _ = setup
    small = falling_masks(seed=3, size=64)[0]
    bag = write_test_bag(tmp_path / "size", edit_mask=damaged(1, 15, lambda m: m.update(
        height=64, width=64, step=64, data=small.tobytes())))
    with pytest.warns(UserWarning, match="left out of the K = 25, 18 row"):
        assert run_main(model_path, bag, tmp_path / "size_out", "--frames", "18", "15") == 0
    predictions = json.loads((tmp_path / "size_out" / "predictions.json").read_text())
    assert [len(predictions["frames"][k]) for k in ("25", "18", "15")] == [2, 2, 3]

    def swapped(index, frame):
        return messages.frame_stamp(index, {27: 28, 28: 27}.get(frame, frame))

    late = write_test_bag(tmp_path / "late", frames=30, frame_stamp=swapped)
    assert run_main(model_path, late, tmp_path / "late_out", "--frames", "18") == 0
    predictions = json.loads((tmp_path / "late_out" / "predictions.json").read_text())
    assert [len(predictions["frames"][k]) for k in ("25", "18")] == [3, 3] and not predictions["left_out"]["25"]


def test_a_copy_fills_the_rows_an_earlier_copy_was_left_out_of(setup, tmp_path):
    """The first bag's episodes cut at 20 frames (scored in the K = 18 row only), a whole copy in the second: the
    copy fills the full row and is left out of the K = 18 row. The first copy claimed every row: the full row
    lost the episodes."""
    model_path, good = setup
    write_test_bag(tmp_path / "bags" / "a", frames=20)
    shutil.copytree(good, tmp_path / "bags" / "b")
    with pytest.warns(UserWarning):
        assert run_main(model_path, tmp_path / "bags", tmp_path / "out", "--frames", "18") == 0
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    a, b = str(tmp_path / "bags" / "a"), str(tmp_path / "bags" / "b")
    assert [p["bag"] for p in saved["frames"]["25"]] == [b] * 3 and [p["bag"] for p in saved["frames"]["18"]] == [a] * 3
    assert [(e["bag"], e["reason"]) for e in saved["left_out"]["18"]] == [(b, f"the same simulation was scored from {a}")] * 3


def test_an_episode_cut_short_is_left_out_of_the_rows_it_cannot_fill(setup, tmp_path, capsys):
    model_path, _ = setup
    bag = write_test_bag(tmp_path / "bag", edit_mask=lambda index, k, m: None if index == 2 and k >= 12 else m)
    with pytest.warns(UserWarning, match=r"episode test-disc-sand-0002: left out of the K = 25, 18 row\(s\): fewer "
                                         r"frame slots than K \(the K = 25 window holds 12; its 12 accepted frames "
                                         r"span 0\.275 s, slot 24 lies 0\.600 s after the first: the episode is cut "
                                         r"short\)"):
        assert run_main(model_path, bag, tmp_path / "out", "--frames", "18", "12") == 0
    assert "episodes left out of the rows K = 25: 1, K = 18: 1" in capsys.readouterr().out
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["true_material"] for p in predictions["frames"]["25"]] == ["jelly", "plasticine"]
    assert [p["frames_used"] for p in predictions["frames"]["12"]] == [12, 12, 12]
    assert [e["episode_id"] for e in predictions["left_out"]["18"]] == ["test-disc-sand-0002"]
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]
    assert (metrics["25"]["n"], metrics["18"]["n"], metrics["12"]["n"]) == (2, 2, 3)
    assert "Clips: 2;" in (tmp_path / "out" / "report.md").read_text()


def burst_stamp(index: int, frame: int) -> int:
    """A camera that sends frames 10-17 of each episode 4 times as fast as the model's interval and the rest
    further apart (in intervals from the start: 0..9, 9.25..11, then 14, 17, .., 32): the first 18 frames span
    12 frame slots, the first 10 fill 10, and the first 25 reach past the last slot (their window is complete).
    Every slot of every window lies within a frame interval of a frame, so each is filled."""
    at = frame if frame < 10 else 9 + 0.25 * (frame - 9) if frame < 18 else 11 + 3 * (frame - 17)
    return messages.frame_stamp(index, 0) + round(at * 25_000_000)


def test_a_temporal_ood_row_that_every_episode_was_left_out_of_stays_as_no_clips(setup, tmp_path, capsys, monkeypatch):
    """A row that no episode fills, kept in the K = 25 and 10 rows: here every episode's K = 18 window is made to
    hold 12 slots. (No bag gives that now that rows are frame slots: a window that fills the full clip's slots fills
    every K's; with rows of camera frames, a burst of frames, burst_stamp, gave it.) The 18 row stays, in
    metrics.json (n 0) and in both of report.md's tables and the output as "no clips" (it was dropped: the report
    read as if 18 had not been asked for); the other rows are those of a run without it. `python -m training
    report` rebuilds the same report from the predictions.json."""
    import dataclasses

    from training.__main__ import main as training_main

    model, bag = setup
    predict = evaluate.predict_episode

    def twelve_slots_at_18(*args, **kwargs):
        prediction = predict(*args, **kwargs)
        return dataclasses.replace(prediction, slots=12) if kwargs.get("slots") == 18 else prediction

    monkeypatch.setattr(evaluate, "predict_episode", twelve_slots_at_18)
    with pytest.warns(UserWarning) as caught:
        assert run_main(model, bag, tmp_path / "out", "--frames", "18", "10") == 0
    assert [str(w.message).split(";")[0] for w in caught] == [
        f"{bag}: episode test-disc-{material}-000{i}: left out of the K = 18 row(s): fewer frame slots than K (the "
        "K = 18 window holds 12" for i, (material, _) in enumerate(EPISODES)]
    empty = "| 18 | " + " | ".join(["no clips"] * len(table_labels())) + " |"
    out = capsys.readouterr().out
    assert empty in out and "episodes left out of the rows K = 18: 3" in out, out
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]
    assert {k: v["n"] for k, v in saved.items()} == {"25": 3, "18": 0, "10": 3}
    assert {family: v["n"] for family, v in saved["18"]["families"].items()} == dict.fromkeys(FAMILIES, 0)
    report = (tmp_path / "out" / "report.md").read_text()
    assert report.count(empty) == 2, report  # both conventions' tables
    assert "Clips: 3; frames per clip: 25. Rows with another number of clips than the 25-frame row's: " \
           "18 frames: no clips." in report, report
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert predictions["frames"]["18"] == [] and [p["slots"] for p in predictions["frames"]["10"]] == [10, 10, 10]
    assert [e["reason"] for e in predictions["left_out"]["18"]] == ["its window holds 12 of 18 frame slots"] * 3
    assert predictions["left_out"]["25"] == predictions["left_out"]["10"] == []
    # The other rows are as without the 18 row.
    assert run_main(model, bag, tmp_path / "without", "--frames", "10") == 0
    capsys.readouterr()
    without = json.loads((tmp_path / "without" / "metrics.json").read_text())["frames"]
    assert without == {k: v for k, v in saved.items() if k != "18"}
    rows = [line for line in report.splitlines() if line.startswith(("| 25 |", "| 10 |"))]
    assert len(rows) == 4 and rows == [line for line in (tmp_path / "without" / "report.md").read_text().splitlines()
                                       if line.startswith(("| 25 |", "| 10 |"))]
    # The training side's report of that predictions.json keeps the row too (--frames 10 is no temporal-OOD row of
    # its printed table, which shows the full clip and K = 24, 22, 18, 15 only).
    assert training_main(["report", "--predictions", str(tmp_path / "out" / "predictions.json"),
                          "--out", str(tmp_path / "report")]) == 0
    assert empty in capsys.readouterr().out
    assert (tmp_path / "report" / "report.md").read_text().count(empty) == 2
    assert json.loads((tmp_path / "report" / "metrics.json").read_text())["frames"] == saved


def test_a_topic_that_is_not_an_image_is_named(setup, tmp_path, capsys):
    model, bag = setup
    assert run_main(model, bag, tmp_path / "out", "--topic", "/ad_sim/instance") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "topic /ad_sim/instance in" in err, err
    assert "carries ad_msgs/msg/SimInstance, not sensor_msgs/msg/Image" in err


def test_a_missing_topic_names_the_bags_image_topics(setup, tmp_path, capsys):
    model, bag = setup
    with pytest.warns(UserWarning) as said:
        assert run_main(model, bag, tmp_path / "out", "--topic", "/cam/mask") == 1
    assert [str(w.message) for w in said] == [f"{bag}: 3 episode(s) left out of every row: it has no mask frame on the topic"]
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no episode with 25 frames on /cam/mask" in err, err
    assert err.rstrip().endswith("the bags' image topics: /ad_sim/view_0/mask (pass one with --topic)"), err


def test_an_unusable_out_is_refused_before_any_work(setup, tmp_path, capsys):
    """Before the bags are even looked at (a missing bag is not reported: --out is checked first)."""
    model, _ = setup
    (tmp_path / "file").write_text("keep")
    for out, message in ((tmp_path / "file", "file is not a folder"),
                         (tmp_path / "file" / "sub", "file is not a folder")):
        assert run_main(model, tmp_path / "no_bag", out) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"evaluate: --out {out}: " in err and message in err, err
    assert (tmp_path / "file").read_text() == "keep"
    assert run_main(model, tmp_path / "no_bag", tmp_path / "new" / "report") == 1
    assert "no_bag does not exist" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()  # nothing is created for a run that does no work


def test_a_report_that_cannot_be_written_leaves_the_earlier_one_whole(setup, tmp_path):
    """The report is written beside --out and moved in once complete: under a file size limit that stops
    it half way (the plots), the earlier report's files are all as they were, and nothing is left over."""
    import subprocess
    import sys

    model, bag = setup
    out = tmp_path / "report"
    assert run_main(model, bag, out) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {"report.md", "metrics.json", "predictions.json", "confusion.png", "pred_vs_true.png"} <= set(before)
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000)); "
            "from ad_estimator import evaluate; sys.exit(evaluate.main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "--model", str(model), "--bags", str(bag), "--quiet",
                           "--title", "another run", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and f"evaluate: cannot write the report to {out} (" in proc.stderr, proc.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]  # the partial report is gone


def test_ground_truth_of_another_material_is_left_out_saying_so(setup, tmp_path, capsys):
    """An episode whose ground truth names a material the metrics do not know: left out of every row
    with a warning naming it (it was a traceback after all the inference), the others scored."""
    model, _ = setup
    bag = write_test_bag(tmp_path / "rubber", episodes=[("rubber", EPISODES[0][1]), *EPISODES[1:]])
    with pytest.warns(UserWarning, match=r"episode test-disc-rubber-0000: left out of every row: its material "
                                         r"'rubber' is none of jelly, plasticine, sand"):
        assert run_main(model, bag, tmp_path / "out") == 0
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["true_material"] for p in saved["frames"]["25"]] == ["plasticine", "sand"]
    assert saved["left_out"]["25"][0]["reason"] == "its material 'rubber' is none of jelly, plasticine, sand"
    assert "episodes left out of the rows K = 25: 1" in capsys.readouterr().out


@pytest.mark.parametrize("edit_mask, reason", [
    (lambda index, k, m: None if index == 2 else m, "it has no mask frame on the topic"),
    (lambda index, k, m: {**m, "encoding": "32FC1"} if index == 2 else m, "all 25 of its mask frames are rejected"),
])
def test_an_episode_without_a_usable_frame_is_left_out_saying_so(setup, tmp_path, capsys, edit_mask, reason):
    """An episode that gives no estimate at all (no mask frame recorded, or every one rejected) is left
    out of every row with a warning and counted, not dropped silently: its family's column would read
    n/a (or its n shrink) as if the bags held none of it."""
    model, _ = setup
    bag = write_test_bag(tmp_path / "bag", edit_mask=edit_mask)
    # (no frame at all is said once a bag, with the count: a wrong --topic would give a line an episode)
    said = rf"episode test-disc-sand-0002: left out of every row: {reason}" if "rejected" in reason else \
        rf"{bag}: 1 episode\(s\) left out of every row: {reason}"
    with pytest.warns(UserWarning, match=said):
        assert run_main(model, bag, tmp_path / "out", "--frames", "18") == 0
    assert "episodes left out of the rows K = 25: 1, K = 18: 1" in capsys.readouterr().out
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["true_material"] for p in saved["frames"]["25"]] == ["jelly", "plasticine"]
    assert [(e["episode_id"], e["reason"]) for e in saved["left_out"]["25"]] == [("test-disc-sand-0002", reason)]
    assert saved["left_out"]["18"] == saved["left_out"]["25"]


def test_episodes_of_two_simulator_runs_in_one_bag_are_left_out_saying_so(tmp_path):
    """A recorder left running over two simulator runs (each stamps its episodes from 0 s): each episode of the
    second run shares its start stamp with one of the first, and all their frames went to one ground truth,
    scored as if they were its own. Such episodes are left out with a warning; an episode without a twin stays."""
    from ad_sim.rosbag import BagWriter, qos_profile
    from estimator_bags import instance_dict

    instance_topic, mask_topic = messages.instance_topic(), messages.mask_topic(0)
    with BagWriter(tmp_path / "two_runs") as writer:
        for topic, kind in ((instance_topic, messages.INSTANCE_TYPE), (mask_topic, messages.IMAGE_TYPE)):
            writer.add_topic(topic, kind, [qos_profile(**messages.topic_qos(topic))])
        for run, count in ((0, 3), (1, 2)):  # the second run stopped after 2 episodes
            for index, (material, parameters) in enumerate(EPISODES[:count]):
                start = messages.frame_stamp(index, 0)
                instance = instance_dict(index, material, parameters, start) | {"seed": 10 * run + index}
                writer.write(instance_topic, start, instance)
                for frame, mask in enumerate(falling_masks(seed=100 + 10 * run + index)):
                    stamp = messages.frame_stamp(index, frame)
                    writer.write(mask_topic, stamp, messages.mask_message(mask, stamp, "ad_sim/view_0"))
    with pytest.warns(UserWarning, match="start at the same stamp") as caught:
        kept = [(instance.seed, len(frames)) for instance, frames in evaluate.episode_frames(tmp_path / "two_runs")]
    assert kept == [(2, 25)]
    assert len([w for w in caught if "record each run into its own bag" in str(w.message)]) == 2


def test_an_instance_topic_of_another_type_is_a_one_line_error(setup, tmp_path, capsys):
    """A bag whose /ad_sim/instance carries something other than the simulator's ground truth: a one-line error
    naming the topic and type (it was an AttributeError traceback: "'Image' object has no attribute 'episode_id'")."""
    from ad_sim.rosbag import BagWriter, qos_profile

    model, _ = setup
    instance_topic, mask_topic = messages.instance_topic(), messages.mask_topic(0)
    with BagWriter(tmp_path / "bag") as writer:
        for topic in (instance_topic, mask_topic):
            writer.add_topic(topic, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(topic))])
        for frame, mask in enumerate(falling_masks(seed=100)):
            stamp = messages.frame_stamp(0, frame)
            for topic in (instance_topic, mask_topic) if frame == 0 else (mask_topic,):
                writer.write(topic, stamp, messages.mask_message(mask, stamp, "ad_sim/view_0"))
    assert run_main(model, tmp_path / "bag", tmp_path / "out") == 1
    assert capsys.readouterr().err == (
        f"evaluate: topic /ad_sim/instance in {tmp_path / 'bag'} carries sensor_msgs/msg/Image, not the simulator's "
        "ground truth ad_msgs/msg/SimInstance, which evaluate splits episodes at and scores them against\n")
    assert not (tmp_path / "out").exists()


def test_a_bag_without_ground_truth_is_said_and_counted(setup, tmp_path, capsys):
    """A bag of masks without the simulator's ground truth gives no episode. Beside other bags, it was left out
    without a word (the report read as if it held nothing); alone, the error blamed the mask topic ("no episode
    with 25 frames on /ad_sim/view_0/mask"), which has them. Now it is warned about, counted in the output's and
    report.md's input problems and listed in predictions.json; alone, the error says what is missing."""
    model, good = setup
    masks_only = write_test_bag(tmp_path / "bags" / "masks_only", ground_truth=False)
    with pytest.warns(UserWarning) as caught:
        assert run_main(model, masks_only, tmp_path / "alone") == 1
    assert [str(w.message) for w in caught] == [f"{masks_only}: no ground truth (ad_msgs/msg/SimInstance on "
                                                "/ad_sim/instance), so no episode: nothing in it is scored"]
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(
        f"evaluate: no ground truth (ad_msgs/msg/SimInstance on /ad_sim/instance) in {[str(masks_only)]}, so no "
        "episode to score: ") and \
        "`ros2 run ad_estimator estimate BAG --topic TOPIC`" in err, err
    shutil.copytree(good, tmp_path / "bags" / "sim")
    with pytest.warns(UserWarning, match="masks_only: no ground truth"):
        assert run_main(model, tmp_path / "bags", tmp_path / "out") == 0
    said = "1 bag(s) without ground truth on /ad_sim/instance"
    assert f"input problems: {said} (see the warnings above)" in capsys.readouterr().out
    assert f"Input problems: {said} (listed in predictions.json)" in (tmp_path / "out" / "report.md").read_text()
    predictions = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert predictions["without_ground_truth"] == [str(masks_only)] and len(predictions["frames"]["25"]) == 3


def test_a_copy_of_a_bag_is_scored_once(setup, tmp_path, capsys):
    """Bags holding the same episodes (the same simulations; say, a backup copy beside the bag under --bags): each
    episode is scored once, the copies left out with one warning a bag, and counted (they were all scored
    again: every n doubled, and a copied bag's episodes weighed twice as much as the others'). `python -m
    training evaluate` reads such a copy once too."""
    model, good = setup
    for name in ("a", "b"):
        shutil.copytree(good, tmp_path / "bags" / name)
    with pytest.warns(UserWarning) as caught:
        assert run_main(model, tmp_path / "bags", tmp_path / "out", "--frames", "18") == 0
    first, copy = tmp_path / "bags" / "a", tmp_path / "bags" / "b"
    assert [str(w.message) for w in caught] == [f"{copy}: 3 episode(s) left out of the rows they were scored in: "
                                                f"the same simulation "
                                                f"was scored from {first} (a copy of a recording is scored once)"]
    assert "episodes left out of the rows K = 25: 3, K = 18: 3" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]
    assert run_main(model, good, tmp_path / "one") == 0
    assert metrics["25"] == json.loads((tmp_path / "one" / "metrics.json").read_text())["frames"]["25"]
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert {p["bag"] for p in saved["frames"]["25"]} == {str(first)}
    assert [(e["bag"], e["reason"]) for e in saved["left_out"]["18"]] == \
        [(str(copy), f"the same simulation was scored from {first}")] * 3


def test_a_parameter_sweep_of_one_id_and_seed_is_not_taken_for_copies(setup, tmp_path):
    """A stiffness sweep of the simulator node's single-instance mode: one bag per Young's modulus, each episode
    of the same id (custom-<shape>-<material>-0000) and seed, as docs/simulator.md advises for comparing
    parameters. Evaluate took every bag after the first for a copy of it and scored one episode of three."""
    model, _ = setup
    for e in (2e4, 2e5, 2e6):
        write_test_bag(tmp_path / "bags" / f"E{e:.0e}", episodes=[("jelly", {"youngs_modulus": e, "poissons_ratio": 0.3})])
    assert run_main(model, tmp_path / "bags", tmp_path / "out") == 0
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert sorted(p["true_parameters"]["youngs_modulus"] for p in saved["frames"]["25"]) == [2e4, 2e5, 2e6]
    assert not saved["left_out"]["25"]


def test_a_copy_left_out_of_every_row_does_not_keep_a_whole_copy_out(setup, tmp_path, capsys):
    """The first bag's episodes cut short (10 frames: in no row), a whole copy in the second: the copy is scored.
    The first bag claimed the episodes before they were scored, and the run ended with no episode at all."""
    model, good = setup
    write_test_bag(tmp_path / "bags" / "a", frames=10)
    shutil.copytree(good, tmp_path / "bags" / "b")
    with pytest.warns(UserWarning, match="cut short"):
        assert run_main(model, tmp_path / "bags", tmp_path / "out") == 0
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert {p["bag"] for p in saved["frames"]["25"]} == {str(tmp_path / "bags" / "b")} and len(saved["frames"]["25"]) == 3


@pytest.mark.parametrize("episode, reason", [
    (("plasticine", {"youngs_modulus": 1.0e5, "poissons_ratio": 0.4}),
     "its ground truth lacks yield_stress, which the metrics score for plasticine (it gives youngs_modulus, "
     "poissons_ratio)"),
    (("jelly", {"youngs_modulus": float("nan"), "poissons_ratio": 0.3}),
     "its ground truth youngs_modulus nan is not a positive number"),
    (("jelly", {"youngs_modulus": -2.0e5, "poissons_ratio": 0.3}),
     "its ground truth youngs_modulus -200000 is not a positive number"),
    (("sand", {"youngs_modulus": 1.0e5, "poissons_ratio": 0.3, "friction_angle": float("inf")}),
     "its ground truth friction_angle inf is not a finite number"),
])
def test_ground_truth_the_metrics_cannot_score_is_left_out_saying_so(setup, tmp_path, capsys, episode, reason):
    """An episode whose ground truth lacks a parameter the metrics score for its family, or gives one as NaN, inf or
    (scored in log space) <= 0: left out of every row with a warning naming it. It was scored without a word, and
    made RegL1 over all clips n/a (a missing or NaN value) or a number of no meaning (log of a negative E), or, for
    an infinite value, ended the run with a traceback when predictions.json was written (inf is no JSON)."""
    model, _ = setup
    bag = write_test_bag(tmp_path / "bag", episodes=[*EPISODES, episode])
    name = f"test-disc-{episode[0]}-0003"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert run_main(model, bag, tmp_path / "out") == 0
    assert [str(w.message) for w in caught] == [f"{bag}: episode {name}: left out of every row: {reason}"]
    assert "episodes left out of the rows K = 25: 1" in capsys.readouterr().out
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["true_material"] for p in saved["frames"]["25"]] == [m for m, _ in EPISODES]
    assert saved["left_out"]["25"] == [{"bag": str(bag), "episode_id": name, "reason": reason}]
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]["25"]
    assert metrics["n"] == 3 and math.isfinite(metrics["regl1"])


def test_frames_alone_for_a_model_of_fewer_frames_gives_the_rows_it_reaches(tmp_path, capsys):
    """`--frames` with no value for a model of 20 frames: the temporal-OOD rows below 20 (18, 15), as `python -m
    training evaluate` does. It was refused, naming K values the user had not given ("--frames [24, 22]: each K
    must be in 1..20"); K values given are still checked."""
    model = build_streaming_model(tmp_path, name="m20", frame_count=20)
    bag = write_test_bag(tmp_path / "bag")
    assert run_main(model, bag, tmp_path / "out", "--frames") == 0
    assert set(json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]) == {"20", "18", "15"}
    capsys.readouterr()
    assert run_main(model, bag, tmp_path / "out", "--frames", "22") == 1
    assert capsys.readouterr().err == "evaluate: --frames [22]: each K must be in 1..20\n"


# --------------------------------------------------------------------------- audit: inf, loops, old schemas, slots


def test_an_infinite_sigma_is_written_as_null_and_the_run_is_kept(setup, tmp_path, monkeypatch, capsys):
    """A model whose sigma overflows to inf (here E's and yield's, the log-scaled ones): the run ended after all the
    inference with a traceback at predictions.json ("Out of range float values are not JSON compliant"), and
    lost. Now both JSON files are strict JSON, the inf written as null as NaN is, and `python -m training report`
    rebuilds the same metrics from that predictions.json (a null sigma, like an inf one, is no sigma)."""
    from ad_estimator.model import ParameterRange
    from training.__main__ import main as training_main

    model, bag = setup
    finite = ParameterRange.sigma
    monkeypatch.setattr(ParameterRange, "sigma",
                        lambda self, value, sigma_u: math.inf if self.scale == "log" else finite(self, value, sigma_u))
    assert run_main(model, bag, tmp_path / "out") == 0
    strict = {"parse_constant": lambda name: pytest.fail(f"non-standard JSON constant {name}")}
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text(), **strict)
    for episode in saved["frames"]["25"]:
        assert episode["raw_uncertainties"][0] is None and episode["raw_uncertainties"][2] is None
        assert all(isinstance(u, float) and u > 0 for u in (episode["raw_uncertainties"][1],
                                                             episode["raw_uncertainties"][3]))
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text(), **strict)["frames"]
    capsys.readouterr()
    assert training_main(["report", "--predictions", str(tmp_path / "out" / "predictions.json"),
                          "--out", str(tmp_path / "again")]) == 0
    assert json.loads((tmp_path / "again" / "metrics.json").read_text())["frames"] == metrics


def test_a_looping_simulators_replayed_episodes_are_scored_once(setup, tmp_path, capsys):
    """The simulator node with `loop: true` replays its first pass's episodes with the same episode id and seed
    (sim_node: the kept episodes, or the same instances simulated again), only episode_index and stamps going on.
    A recording of two passes scored each episode twice (a copy in another bag was scored once). Now the repeats are
    left out of every row with one warning a bag giving their count, and listed in left_out; the metrics are those of
    one pass. A copy of the looping bag beside it has all its episodes left out as copies."""
    model, one_pass = setup
    looped = write_test_bag(tmp_path / "bags" / "looped", passes=2)
    with pytest.warns(UserWarning) as caught:
        assert run_main(model, looped, tmp_path / "out", "--frames", "18") == 0
    repeat = "the same simulation was scored earlier from this bag"
    assert [str(w.message) for w in caught] == [
        f"{looped}: 3 episode(s) left out of the rows they were scored in: {repeat} (a looping simulator's later passes replay its "
        "episodes; each is scored once)"]
    assert "episodes left out of the rows K = 25: 3, K = 18: 3" in capsys.readouterr().out
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [p["episode_id"] for p in saved["frames"]["25"]] == [f"test-disc-{m}-000{i}" for i, (m, _) in
                                                                enumerate(EPISODES)]
    assert [p["oldest_stamp_ns"] for p in saved["frames"]["25"]] == [messages.frame_stamp(i, 0) for i in range(3)]
    assert saved["left_out"]["18"] == saved["left_out"]["25"] == [
        {"bag": str(looped), "episode_id": f"test-disc-{m}-000{i}", "reason": repeat} for i, (m, _) in
        enumerate(EPISODES)]
    assert run_main(model, one_pass, tmp_path / "one", "--frames", "18") == 0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"] == \
        json.loads((tmp_path / "one" / "metrics.json").read_text())["frames"]
    shutil.copytree(looped, tmp_path / "bags" / "zcopy")
    with pytest.warns(UserWarning) as caught:
        assert run_main(model, tmp_path / "bags", tmp_path / "two") == 0
    assert [str(w.message).split(":")[0] for w in caught] == [str(looped), str(tmp_path / "bags" / "zcopy")]
    assert str(caught[1].message).startswith(f"{tmp_path / 'bags' / 'zcopy'}: 6 episode(s) left out of the rows they were scored in: "
                                             f"the same simulation was scored from {looped}")
    assert len(json.loads((tmp_path / "two" / "predictions.json").read_text())["frames"]["25"]) == 3


@pytest.mark.parametrize("field", ["seed", "episode_id", "material", "parameter_names", "parameters"])
def test_ground_truth_of_an_older_definition_is_a_one_line_error(setup, tmp_path, capsys, field):
    """A bag whose /ad_sim/instance is recorded with an ad_msgs/msg/SimInstance definition (the bag's own schema
    text) that lacks a field evaluate reads: a one-line error naming the bag, the topic and the field. It was an
    AttributeError traceback ("'SimInstance' object has no attribute 'seed'"), from ad_sim.rosbag's
    distinct_episodes for the id and seed, from the scoring for the others."""
    from estimator_bags import without_field

    model, _ = setup
    bag = write_test_bag(tmp_path / "old", instance_schema=without_field(messages.INSTANCE_TYPE, field))
    assert run_main(model, bag, tmp_path / "out") == 1
    assert capsys.readouterr().err == (
        f"evaluate: {bag}: the ground truth on /ad_sim/instance lacks the field {field} that evaluate reads (the bag "
        "records another definition of ad_msgs/msg/SimInstance than this one: an older or a foreign one)\n")
    assert not (tmp_path / "out").exists()


def at_fps(fps: float):
    return lambda index, frame: messages.frame_stamp(index, 0) + round(frame * 1e9 / fps)


@pytest.mark.parametrize("frame_stamp, frames", [(at_fps(60), 40), (at_fps(30), 25), (burst_stamp, 25)],
                         ids=["60fps", "30fps", "burst"])
def test_rows_are_frame_slots_whatever_the_camera_rate(setup, tmp_path, capsys, frame_stamp, frames):
    """Row K is the first K frame slots (K x the model's 25 ms from the episode's first frame), as the node's window
    fills them, not the first K camera frames. At 60 fps the first 25 frames reach 0.4 s, 17 slots: every episode
    was left out of the full row (exit 1, "no episode with 25 frames") though the node estimates each of them;
    at 30 fps the first 18 frames reach 0.57 s, and the K = 18 row's estimates were made from 24 slots; a burst of
    frames (burst_stamp) left every episode out of the K = 18 row. Now each row's estimate is the node's: its
    complete one (episode policy) for the full row, and for K, the first K slots of its anytime window when they
    settle."""
    model_path, _ = setup
    bag = write_test_bag(tmp_path / "bag", frame_stamp=frame_stamp, frames=frames)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing is left out, nothing warned about
        assert run_main(model_path, bag, tmp_path / "out", "--frames", "18", "10") == 0
    saved = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert {k: [p["slots"] for p in v] for k, v in saved["frames"].items()} == {
        "25": [25] * 3, "18": [18] * 3, "10": [10] * 3}
    model = EstimatorModel.load(model_path)
    for index in range(len(EPISODES)):
        stamps = [frame_stamp(index, k) for k in range(frames)]
        masks = falling_masks(count=frames, seed=100 + index)
        for k in (25, 18, 10):
            window = FrameWindow(model.info.frame_interval, model.info.frame_count, history=model.info.previous_frames,
                                 **({} if k == 25 else {"policy": "anytime", "min_frames": k, "every_n": 25}))
            out, *_ = [o for s, m in zip(stamps, masks) for o in window.add(s, m, model.encode)]
            assert len(out.valid) == k and out.valid.all()
            episode = saved["frames"][str(k)][index]
            assert (episode["frames_used"], episode["newest_stamp_ns"]) == (k, out.newest_stamp_ns)
            np.testing.assert_allclose(episode["probabilities"],
                                       model.predict(out.features, out.valid).probabilities, rtol=1e-5)
