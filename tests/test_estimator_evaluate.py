"""`ad_estimator evaluate`: offline metrics over bags (no ROS runtime)."""
import json
import warnings

import numpy as np
import pytest
from mcap.reader import make_reader

from ad_estimator import evaluate
from ad_estimator.model import EstimatorModel
from estimator_bags import EPISODES, write_test_bag
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


def test_clear_errors(setup, tmp_path, capsys):
    model, bag = setup
    assert evaluate.main(["--model", str(tmp_path / "absent.onnx"), "--bags", str(bag)]) == 1
    assert "absent.onnx" in capsys.readouterr().err
    assert evaluate.main(["--model", str(model), "--bags", str(tmp_path / "nowhere")]) == 1
    assert "nowhere" in capsys.readouterr().err
    for frames, message in (("30", "--frames [30]: each K must be in 1..25"), ("20,0", "--frames [0]: each K"),
                            ("24,x", "expected frame counts such as 24 18 or 24,18")):
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main(["--model", str(model), "--bags", str(bag), "--frames", frames])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


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
    scored = json.loads((tmp_path / "b" / "predictions.json").read_text())["frames"]["25"]
    assert 1 <= len(scored) < len(EPISODES)
