"""`ad_estimator estimate`: the node's estimates for any bag, offline, without ground truth (no ROS runtime)."""
import csv
import json

import numpy as np
import pytest

from ad_estimator import estimate, evaluate
from ad_sim import messages
from ad_sim.rosbag import BagWriter, qos_profile
from estimator_bags import EPISODES, damaged, write_test_bag
from estimator_models import build_streaming_model, falling_masks

CAMERA = "/robot/camera/mask"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("estimate")
    return build_streaming_model(d, previous_frames=2), write_test_bag(d / "bags" / "sim")


def robot_bag(path, episodes: int = 2, frames: int = 25, period_ns: int = 25_000_000):
    """What a robot records: one mask topic of its own name, no ground truth; episodes 1 s apart."""
    with BagWriter(path) as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        for episode in range(episodes):
            for k, mask in enumerate(falling_masks(count=frames, seed=200 + episode)):
                stamp = 5_000_000_000 + episode * 1_000_000_000 + k * period_ns
                writer.write(CAMERA, stamp, messages.mask_message(mask, stamp, "robot/camera"))
    return path


def run(model, *args):
    return estimate.main(["--model", str(model), "--quiet", *map(str, args)])


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_estimates_of_a_simulator_bag_are_the_evaluators(setup, tmp_path):
    """The same frames through the same window and model: evaluate's per-episode predictions, without
    reading the ground truth."""
    model, bag = setup
    assert run(model, bag, "--out", tmp_path / "e.csv") == 0
    rows = read_csv(tmp_path / "e.csv")
    assert [(r["episode"], r["frames_used"], r["complete"]) for r in rows] == [(str(i), "25", "True") for i in (1, 2, 3)]
    assert evaluate.main(["--model", str(model), "--bags", str(bag), "--quiet", "--out", str(tmp_path / "ev")]) == 0
    truth = json.loads((tmp_path / "ev" / "predictions.json").read_text())["frames"]["25"]
    assert len(truth) == len(EPISODES)
    for row, episode in zip(rows, truth):
        assert row["material"] == episode["material"]
        np.testing.assert_allclose([float(row[f"p_{c}"]) for c in ("jelly", "plasticine", "sand")],
                                   episode["probabilities"], rtol=1e-6)
        names = ("youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle")
        for name, value, sigma in zip(names, episode["parameters"], episode["uncertainties"]):
            assert (row[name] == "") == (value is None or np.isnan(value))
            if row[name]:  # (a family's fixed parameters, such as sand's E, have sigma 0)
                assert float(row[name]) == pytest.approx(value, rel=1e-6)
                assert float(row[f"{name}_sigma"]) == pytest.approx(sigma, rel=1e-6)
        assert float(row["newest_stamp_s"]) == pytest.approx(episode["newest_stamp_ns"] / 1e9)


def test_a_robot_bag_without_ground_truth_gets_estimates_on_its_own_topic(setup, tmp_path, capsys):
    model, _ = setup
    bag = robot_bag(tmp_path / "robot")
    # evaluate needs the simulator's ground truth to split and score episodes ...
    assert evaluate.main(["--model", str(model), "--bags", str(bag), "--topic", CAMERA, "--quiet",
                          "--out", str(tmp_path / "ev")]) == 1
    assert "no episode" in capsys.readouterr().err
    # ... estimate splits them at the stamp gap, as the node does, and prints a line per estimate.
    assert estimate.main(["--model", str(model), str(bag), "--topic", CAMERA, "--out", str(tmp_path / "r.csv")]) == 0
    out = capsys.readouterr().out
    assert "robot episode 1 (25 frames): " in out and "robot episode 2 (25 frames): " in out
    assert "2 estimate(s) of 2 episode(s) with test-streaming" in out
    rows = read_csv(tmp_path / "r.csv")
    assert [float(r["episode_start_s"]) for r in rows] == [5.0, 6.0]
    assert all(sum(float(r[f"p_{c}"]) for c in ("jelly", "plasticine", "sand")) == pytest.approx(1.0) for r in rows)


def test_episodes_are_counted_by_the_window_so_a_looped_recording_keeps_them_apart(setup, tmp_path):
    """Two loops of the same clip, the second with the first's stamps (a simulator restarted with its
    clock), then a short episode under the episode policy: it gives no row but is counted."""
    model, _ = setup
    masks = falling_masks(seed=7)
    with BagWriter(tmp_path / "loop") as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        log = 0
        for loop_frames in (25, 25, 10, 25):
            for k in range(loop_frames):
                log += 1
                writer.write(CAMERA, log, messages.mask_message(masks[k], k * 25_000_000, "robot/camera"))
    assert run(model, tmp_path / "loop", "--topic", CAMERA, "--out", tmp_path / "e.csv") == 0
    rows = read_csv(tmp_path / "e.csv")
    assert [(r["episode"], r["episode_start_s"]) for r in rows] == [("1", "0.0"), ("2", "0.0"), ("4", "0.0")]
    assert rows[0]["p_jelly"] == rows[1]["p_jelly"] == rows[2]["p_jelly"]  # the same frames, the same estimate


def test_anytime_policy_and_a_short_episode(setup, tmp_path, capsys):
    model, _ = setup
    bag = robot_bag(tmp_path / "short", episodes=1, frames=17)
    # The episode policy waits for all 25 slots, which a 17-frame episode never fills: no estimate, and a hint.
    assert run(model, bag, "--topic", CAMERA, "--out", tmp_path / "none.csv") == 1
    assert "try --output-policy anytime" in capsys.readouterr().err
    assert not (tmp_path / "none.csv").exists()
    bag = robot_bag(tmp_path / "long", episodes=1)
    assert run(model, bag, "--topic", CAMERA, "--output-policy", "anytime", "--min-frames", "10", "--every-n", "5",
               "--out", tmp_path / "any.csv") == 0
    rows = read_csv(tmp_path / "any.csv")
    assert [(r["frames_used"], r["complete"]) for r in rows] == [("10", "False"), ("15", "False"), ("20", "False"),
                                                                 ("25", "True")]


def test_a_frame_the_node_rejects_is_skipped_warned_and_counted(setup, tmp_path, capsys):
    model, _ = setup
    bag = write_test_bag(tmp_path / "bag", edit_mask=damaged(1, 5, lambda m: m.update(encoding="32FC1")))
    with pytest.warns(UserWarning, match=r"frame stamped 1\.625 s skipped, as the node rejects it: .*32FC1"):
        assert run(model, bag, "--out", tmp_path / "e.csv") == 0
    assert "3 estimate(s) of 3 episode(s) with test-streaming; 1 frame(s) skipped ({'encoding': 1})" in \
        capsys.readouterr().out
    rows = read_csv(tmp_path / "e.csv")
    # Slot 5 takes a neighbouring frame instead (within the slot tolerance), as in the node and evaluate.
    with pytest.warns(UserWarning, match="1 mask frame"):
        assert evaluate.main(["--model", str(model), "--bags", str(bag), "--quiet", "--out", str(tmp_path / "ev")]) == 0
    truth = json.loads((tmp_path / "ev" / "predictions.json").read_text())["frames"]["25"]
    assert [r["frames_used"] for r in rows] == [str(e["frames_used"]) for e in truth] == ["25"] * 3
    np.testing.assert_allclose([float(rows[1][f"p_{c}"]) for c in ("jelly", "plasticine", "sand")],
                               truth[1]["probabilities"], rtol=1e-6)


def test_clear_errors(setup, tmp_path, capsys):
    model, bag = setup
    cases = [
        (["--topic", "/nothing"], f"{bag} has no topic /nothing; its image topics: /ad_sim/view_0/mask"),
        (["--topic", "/ad_sim/instance"], "carries ad_msgs/msg/SimInstance, not sensor_msgs/msg/Image"),
        (["--output-policy", "anytime", "--min-frames", "0"], "min_frames"),
        (["--out", tmp_path], "is a folder; pass a .csv file name"),
    ]
    for extra, message in cases:
        assert run(model, bag, *extra) == 1
        err = capsys.readouterr().err
        assert err.startswith("estimate: ") and err.count("\n") == 1 and message in err, (extra, err)
    assert estimate.main(["--model", str(tmp_path / "missing.onnx"), str(bag)]) == 1
    assert "missing.onnx" in capsys.readouterr().err
    assert run(model, tmp_path / "no_bag") == 1
    assert "does not exist" in capsys.readouterr().err
