"""`ad_estimator estimate`: the node's estimates for any bag, offline, without ground truth (no ROS runtime)."""
import csv
import fcntl
import json
import os
import pty
import shutil
import struct
import termios
from pathlib import Path

import numpy as np
import pytest

from ad_estimator import estimate, evaluate
from ad_estimator.model import EstimatorModel
from ad_sim import messages
from mcap.reader import make_reader

from ad_sim.rosbag import BagWriter, qos_profile
from estimator_bags import EPISODES, damaged, write_test_bag
from estimator_models import build_streaming_model, falling_masks

CAMERA = "/robot/camera/mask"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("estimate")
    return build_streaming_model(d, previous_frames=2), write_test_bag(d / "bags" / "sim")


def robot_bag(path, episodes: int = 2, frames: int = 25, period_ns: int = 25_000_000, pause_after: int | None = None):
    """What a robot records: one mask topic of its own name, no ground truth; episodes 1 s apart.
    `pause_after` k: the recording pauses 0.8 s (log time) after frame k, the stamps do not."""
    with BagWriter(path) as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        for episode in range(episodes):
            for k, mask in enumerate(falling_masks(count=frames, seed=200 + episode)):
                stamp = 5_000_000_000 + episode * 10_000_000_000 + k * period_ns
                log = stamp + (800_000_000 if pause_after is not None and k > pause_after else 0)
                writer.write(CAMERA, log, messages.mask_message(mask, stamp, "robot/camera"))
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
            else:
                assert row[f"{name}_sigma"] == ""
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
    assert [(float(r["episode_start_s"]), float(r["oldest_stamp_s"]), float(r["newest_stamp_s"])) for r in rows] == \
        [(5.0, 5.0, 5.6), (15.0, 15.0, 15.6)]
    # Its estimates are the evaluator's on the same frames, once they carry ground truth: checked above on
    # simulator bags; here the two episodes' different frames give different estimates.
    assert rows[0]["p_jelly"] != rows[1]["p_jelly"]
    assert out.rstrip().endswith("r.csv")
    # A second run into the same file says that it replaced the first's (the default name is per model).
    assert estimate.main(["--model", str(model), str(bag), "--topic", CAMERA, "--out", str(tmp_path / "r.csv"),
                          "--quiet"]) == 0
    assert capsys.readouterr().out.rstrip().endswith("r.csv (it replaced the file of an earlier run)")
    # A topic named as a node in the root namespace would name it (relative) is found too.
    assert estimate.main(["--model", str(model), str(bag), "--topic", CAMERA.lstrip("/"), "--out", str(tmp_path / "r.csv"),
                          "--quiet"]) == 0
    assert len(read_csv(tmp_path / "r.csv")) == 2


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
    # The end of the bag flushes the window: the 17-frame episode's last frames give a last estimate.
    assert run(model, tmp_path / "short", "--topic", CAMERA, "--output-policy", "anytime", "--min-frames", "10",
               "--out", tmp_path / "short.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "short.csv")] == ["10", "15", "17"]
    # min_frames is capped at the model's frame count, as in the node.
    assert run(model, bag, "--topic", CAMERA, "--output-policy", "anytime", "--min-frames", "40",
               "--out", tmp_path / "cap.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "cap.csv")] == ["25"]


def test_a_pause_in_the_recording_flushes_the_window_as_the_nodes_idle_flush_does(setup, tmp_path):
    """Played at its own rate into the node, a 0.8 s pause after frame 12 leaves the node's input idle
    past idle_flush (0.3 s), and it flushes: estimates at 10, 13, 18, 23 and 25 frames (what the node
    published in a review's replay of this bag). Without the pause, or with idle_flush 0: 10, 15, 20, 25."""
    model, _ = setup
    bag = robot_bag(tmp_path / "paused", episodes=1, pause_after=12)
    anytime = ("--topic", CAMERA, "--output-policy", "anytime", "--min-frames", "10", "--every-n", "5")
    assert run(model, bag, *anytime, "--out", tmp_path / "a.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "a.csv")] == ["10", "13", "18", "23", "25"]
    assert run(model, bag, *anytime, "--idle-flush", "0", "--out", tmp_path / "b.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "b.csv")] == ["10", "15", "20", "25"]
    assert run(model, bag, *anytime, "--idle-flush", "1.0", "--out", tmp_path / "c.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "c.csv")] == ["10", "15", "20", "25"]
    # a pause just over idle_flush is enough (one of 0.8 s against 0.5 s flushes; a mutant took twice idle_flush)
    assert run(model, bag, *anytime, "--idle-flush", "0.5", "--out", tmp_path / "d.csv") == 0
    assert [r["frames_used"] for r in read_csv(tmp_path / "d.csv")] == ["10", "13", "18", "23", "25"]


def test_the_nodes_window_and_image_parameters_apply(setup, tmp_path):
    model, _ = setup
    bag = robot_bag(tmp_path / "two", episodes=2)  # episodes 10 s apart, frames 25 ms apart
    # A gap threshold above the 10 s between episodes joins them: one episode, its first 25 slots.
    assert run(model, bag, "--topic", CAMERA, "--gap-threshold", "20", "--out", tmp_path / "g.csv") == 0
    assert [(r["episode"], r["newest_stamp_s"]) for r in read_csv(tmp_path / "g.csv")] == [("1", "5.6")]
    # Masks with object pixels of 100: empty at the default threshold (127), whole at threshold 50.
    dim = tmp_path / "dim"
    with BagWriter(dim) as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        for k, mask in enumerate(falling_masks(seed=200)):
            stamp = 5_000_000_000 + k * 25_000_000
            writer.write(CAMERA, stamp, messages.mask_message((mask // 255 * 100).astype(np.uint8), stamp, "c"))
    assert run(model, dim, "--topic", CAMERA, "--mask-threshold", "50", "--out", tmp_path / "dim.csv") == 0
    assert run(model, bag, "--topic", CAMERA, "--out", tmp_path / "full.csv") == 0
    assert read_csv(tmp_path / "dim.csv")[0]["p_jelly"] == read_csv(tmp_path / "full.csv")[0]["p_jelly"]
    # At the default threshold they hold no object pixel: rejected, saying why (they gave an estimate of nothing).
    with pytest.warns(UserWarning) as caught:
        assert run(model, dim, "--topic", CAMERA, "--out", tmp_path / "empty.csv") == 1
    assert [str(w.message).split(": ", 1)[1] for w in caught] == [
        "frame stamped 5.000 s skipped, as the node rejects it: no object pixel in this mono8 mask above "
        "mask_threshold 127 (its brightest pixel is 100; a 0/1 mask needs mask_threshold 0)",
        "25 frames in all skipped for the reason of the first (empty)"]
    assert not (tmp_path / "empty.csv").exists()
    # Too large for max_image_pixels: every frame is rejected, and the error says none was accepted. The
    # first is warned about, then the count: one warning per frame flooded the terminal.
    with pytest.warns(UserWarning) as caught:
        assert run(model, bag, "--topic", CAMERA, "--max-image-pixels", "100", "--out", tmp_path / "x.csv") == 1
    said = [str(w.message) for w in caught]
    frames = sum(1 for _ in estimate.mask_frames(bag, CAMERA, recover=False))
    assert frames > 25 and sum("exceeds max_image_pixels" in text for text in said) == 1, said
    assert sum(f"{frames} frames in all skipped for the reason of the first (too_large)" in text for text in said) == 1, said


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


def test_a_bag_that_cannot_be_read_is_skipped_and_the_others_kept(setup, tmp_path, capsys):
    model, good = setup
    bad = robot_bag(tmp_path / "robot", episodes=1)  # no /ad_sim/view_0/mask
    with pytest.warns(UserWarning, match=rf"bag skipped: {bad} has no topic /ad_sim/view_0/mask; its image "
                                         rf"topics: {CAMERA} \(pass one with --topic\)"):
        assert run(model, good, bad, "--out", tmp_path / "e.csv") == 1
    assert f"1 bag(s) could not be read: {bad}: {tmp_path / 'e.csv'}" in capsys.readouterr().out
    assert len(read_csv(tmp_path / "e.csv")) == 3  # the good bag's estimates are written
    with pytest.warns(UserWarning, match="carries ad_msgs/msg/SimInstance, not sensor_msgs/msg/Image"):
        assert run(model, good, "--topic", "/ad_sim/instance", "--out", tmp_path / "n.csv") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0 frame(s) read, 0 accepted; 1 bag(s) could not be read" in err, err
    assert "try --output-policy" not in err and not (tmp_path / "n.csv").exists()


def test_a_damaged_bag_points_at_recover(setup, tmp_path, capsys):
    """A chunk of the last episode's frames corrupted in the copy: without --recover the bag is
    refused and the hint is --recover (not the output policy); with it, the other episodes come out."""
    model, intact = setup
    bag = write_test_bag(tmp_path / "bag", chunk_size=64 * 1024)
    file = next(bag.glob("*.mcap"))
    with open(file, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    data = bytearray(file.read_bytes())
    middle = chunks[-1].chunk_start_offset + chunks[-1].chunk_length // 2
    data[middle : middle + 64] = bytes(64)
    file.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=r"bag skipped: .*corrupt record.*pass --recover"):
        assert run(model, bag, "--out", tmp_path / "e.csv") == 1
    err = capsys.readouterr().err
    assert "Pass --recover to read the undamaged part" in err and "output-policy" not in err, err
    with pytest.warns(UserWarning, match=r"corrupt record .*skipped"):
        assert run(model, bag, "--recover", "--out", tmp_path / "r.csv") == 0
    rows = read_csv(tmp_path / "r.csv")
    assert [(r["episode"], r["frames_used"], r["complete"]) for r in rows] == [("1", "25", "True"), ("2", "25", "True")]
    assert run(model, intact, "--out", tmp_path / "i.csv") == 0  # the episodes before the damage: as from an intact copy
    assert [r["p_jelly"] for r in rows] == [r["p_jelly"] for r in read_csv(tmp_path / "i.csv")[:2]]


def test_a_message_that_does_not_decode_costs_only_itself_with_recover(setup, tmp_path, capsys):
    """One mask message recorded as 8 bytes of CDR (its chunk's CRC is valid): without --recover the bag
    is refused, naming the topic and log time, and the hint is --recover; with it, only that frame is
    skipped (its episode's window fills from the others) and estimate and evaluate keep every episode."""
    model, intact = setup
    bad_stamp = messages.frame_stamp(0, 5)
    original = BagWriter.write

    def write(self, topic, log_time_ns, message, *args):
        if topic == messages.mask_topic(0) and log_time_ns == bad_stamp:
            message = b"\x00\x01\x00\x00\x01\x00\x00\x00"
        return original(self, topic, log_time_ns, message, *args)

    BagWriter.write = write
    try:
        bag = write_test_bag(tmp_path / "bad_cdr")
    finally:
        BagWriter.write = original
    where = rf"the message on /ad_sim/view_0/mask logged at {bad_stamp / 1e9:.3f} s does not decode"
    with pytest.warns(UserWarning, match=rf"bag skipped: .*{where} .*pass --recover"):
        assert run(model, bag, "--out", tmp_path / "e.csv") == 1
    assert "Pass --recover to read the undamaged part" in capsys.readouterr().err
    with pytest.warns(UserWarning, match=rf"{where} .*it was skipped"):
        assert run(model, bag, "--recover", "--out", tmp_path / "r.csv") == 0
    rows = read_csv(tmp_path / "r.csv")
    assert [r["episode"] for r in rows] == ["1", "2", "3"]
    assert run(model, intact, "--out", tmp_path / "i.csv") == 0  # the undamaged episodes: as from an intact copy
    assert [r["p_jelly"] for r in rows[1:]] == [r["p_jelly"] for r in read_csv(tmp_path / "i.csv")[1:]]
    with pytest.warns(UserWarning, match=rf"{where} .*it was skipped"):
        assert evaluate.main(["--model", str(model), "--bags", str(bag), "--recover", "--quiet",
                              "--out", str(tmp_path / "ev")]) == 0
    scored = json.loads((tmp_path / "ev" / "predictions.json").read_text())
    assert len(scored["frames"]["25"]) == 3 and any("does not decode" in p for p in scored["source_problems"])


def test_a_bag_with_nothing_readable_is_skipped_saying_so(setup, tmp_path, capsys):
    """Cut inside its first chunk, a bag holds nothing that --recover can read: it is skipped with that
    reason (not as a bag without the topic), the other bags' estimates are written, and the exit status is 1."""
    model, good = setup
    bag = write_test_bag(tmp_path / "cut")
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[:300])
    with pytest.warns(UserWarning) as caught:
        assert run(model, good, bag, "--recover", "--out", tmp_path / "e.csv") == 1
    assert [str(w.message) for w in caught] == [
        f"bag skipped: nothing readable in {file}: it is truncated before its first complete chunk (300 bytes; was "
        "the writer killed?)"]
    assert f"1 bag(s) could not be read: {bag}" in capsys.readouterr().out
    assert len(read_csv(tmp_path / "e.csv")) == 3
    with pytest.warns(UserWarning, match="bag skipped: nothing readable"):
        assert run(model, bag, "--recover", "--out", tmp_path / "n.csv") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0 frame(s) read" in err and "Pass --recover" not in err, err


def test_an_unusable_metadata_yaml_does_not_block_the_mcap_beside_it(setup, tmp_path, capsys):
    """An empty metadata.yaml: the bag is skipped with a one-line reason naming --recover; with it, the
    .mcap file beside it gives the intact bag's estimates."""
    model, good = setup
    bag = tmp_path / "bag"
    shutil.copytree(good, bag)
    (bag / "metadata.yaml").write_text("")
    with pytest.warns(UserWarning, match=rf"^bag skipped: {bag}/metadata\.yaml is unreadable \(empty\); pass --recover "
                                         r"to read the 1 \.mcap file\(s\) beside it$"):
        assert run(model, bag, "--out", tmp_path / "e.csv") == 1
    assert "Pass --recover to read the undamaged part" in capsys.readouterr().err
    with pytest.warns(UserWarning, match=r"metadata\.yaml is unreadable \(empty\); reading the 1 \.mcap file\(s\)"):
        assert run(model, bag, "--recover", "--out", tmp_path / "r.csv") == 0
    assert run(model, good, "--out", tmp_path / "g.csv") == 0
    assert [r["p_jelly"] for r in read_csv(tmp_path / "r.csv")] == [r["p_jelly"] for r in read_csv(tmp_path / "g.csv")]


def test_clear_errors_before_any_work(setup, tmp_path, capsys):
    model, bag = setup
    (tmp_path / "file").write_text("keep")
    cases = [
        # named as the options given (the node's messages name its parameters)
        (["--output-policy", "anytime", "--min-frames", "0"], "--min-frames must be positive"),
        (["--threads", "0"], "--threads must be positive"),
        (["--mask-threshold", "300"], "--mask-threshold is a pixel value in 0..254"),
        (["--idle-flush", "-1"], "--idle-flush is seconds in 0..1e+06 (0: never), got -1.0"),
        (["--idle-flush", "inf"], "--idle-flush is seconds in 0..1e+06 (0: never), got inf"),  # was an OverflowError
        (["--gap-threshold", "inf"], "--gap-threshold must be a number of seconds up to 1e+06, got inf"),
        (["--gap-threshold", "1e300"], "--gap-threshold must be a number of seconds up to 1e+06, got 1e+300"),
        (["--slot-tolerance", "3"], "--slot-tolerance"),
        (["--out", tmp_path], "is a folder; pass a .csv file name"),
        # --out is a CSV file: the messages ask for one, not for a folder
        (["--out", tmp_path / "file" / "e.csv"], f"--out {tmp_path / 'file' / 'e.csv'}: {tmp_path / 'file'} is not a "
                                                 "folder; pass a .csv file in a folder"),
    ]
    if Path("/proc/self").is_dir():  # where nothing can be created
        cases.append((["--out", "/proc/e.csv"], "--out /proc/e.csv: cannot write in /proc ("))
    for extra, message in cases:
        assert run(model, bag, *extra) == 1
        err = capsys.readouterr().err
        assert err.startswith("estimate: ") and err.count("\n") == 1 and message in err, (extra, err)
        assert "report" not in err and ("/proc" not in err or err.endswith(
            "); pass a .csv file in a folder that you can write in\n")), err
    assert estimate.main(["--model", str(tmp_path / "missing.onnx"), str(bag)]) == 1
    assert "missing.onnx" in capsys.readouterr().err
    assert run(model, tmp_path / "no_bag") == 1
    assert "does not exist" in capsys.readouterr().err


def test_frames_out_of_stamp_order_are_skipped_as_the_node_skips_them(setup, tmp_path, capsys):
    """Two swapped frames once restarted the window: the episode vanished from the CSV, silently."""
    model, _ = setup
    masks = falling_masks(seed=9)
    with BagWriter(tmp_path / "swapped") as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        for log, k in enumerate([*range(10), 11, 10, *range(12, 25)]):
            writer.write(CAMERA, log + 1, messages.mask_message(masks[k], k * 25_000_000, "robot/camera"))
    with pytest.warns(UserWarning, match=r"swapped: 1 frame\(s\) came after a later-stamped frame and were skipped"):
        assert run(model, tmp_path / "swapped", "--topic", CAMERA, "--out", tmp_path / "e.csv") == 0
    assert "1 estimate(s) of 1 episode(s)" in capsys.readouterr().out
    (row,) = read_csv(tmp_path / "e.csv")
    assert (row["episode"], row["frames_used"], row["complete"]) == ("1", "25", "True")


def test_an_unstamped_camera_is_named_as_the_reason_for_no_estimate(setup, tmp_path, capsys):
    model, _ = setup
    with BagWriter(tmp_path / "unstamped") as writer:
        writer.add_topic(CAMERA, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(messages.mask_topic(0)))])
        for log, mask in enumerate(falling_masks(seed=9)):
            writer.write(CAMERA, log + 1, messages.mask_message(mask, 0, "robot/camera"))
    with pytest.warns(UserWarning, match=r"24 frame\(s\) had the stamp of the frame before and were skipped"):
        assert run(model, tmp_path / "unstamped", "--topic", CAMERA, "--out", tmp_path / "e.csv") == 1
    assert capsys.readouterr().err.endswith(
        "25 frame(s) read, 1 accepted; 24 frame(s) skipped ({'repeated stamp': 24}). Frames that repeat the stamp "
        "before them are skipped: was the camera stamping its images?\n")


def test_an_estimate_the_model_cannot_make_is_warned_and_the_others_kept(setup, tmp_path, monkeypatch):
    """A model whose outputs turn NaN for one window: that row is left out (as the node publishes
    nothing), the others are written; it once ended the run with a traceback."""
    model_path, bag = setup
    predict = EstimatorModel.predict
    calls = []

    def second_fails(self, features, valid):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("the model's outputs are not finite (NaN or inf) for these 25 frames")
        return predict(self, features, valid)

    monkeypatch.setattr(EstimatorModel, "predict", second_fails)
    with pytest.warns(UserWarning, match=r"episode 2: no estimate: the model's outputs are not finite"):
        assert run(model_path, bag, "--out", tmp_path / "e.csv") == 0
    assert [r["episode"] for r in read_csv(tmp_path / "e.csv")] == ["1", "3"]


def test_an_out_that_is_not_an_estimate_csv_is_refused_and_a_failed_write_keeps_the_old_one(setup, tmp_path, capsys):
    """--out naming a file estimate did not write (here the bag's own .mcap) is refused before any work
    and the file is untouched; a write that fails (a 512-byte file size limit) leaves the earlier CSV whole."""
    import subprocess
    import sys

    model, bag = setup
    copy = tmp_path / "bag"
    shutil.copytree(bag, copy)
    recording = next(copy.glob("*.mcap"))
    before = recording.read_bytes()
    for victim in (recording, copy / "metadata.yaml"):
        assert run(model, copy, "--out", victim) == 1
        assert f"--out {victim} exists and is not a CSV that estimate wrote" in capsys.readouterr().err
    assert recording.read_bytes() == before
    good = tmp_path / "e.csv"
    assert run(model, bag, "--out", good) == 0
    written = good.read_bytes()
    assert len(written) > 512
    umask = os.umask(0)
    os.umask(umask)
    assert good.stat().st_mode & 0o777 == 0o666 & ~umask  # as open() makes it, not a temporary file's 0600
    limit = "import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (512, 512)); "
    code = (limit + "from ad_estimator import estimate; sys.exit(estimate.main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "--model", str(model), "--quiet", str(bag), "--out", str(good)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and f"estimate: cannot write {good} (File too large)" in proc.stderr, proc.stderr
    assert good.read_bytes() == written and sorted(p.name for p in tmp_path.iterdir()) == ["bag", "e.csv"]


def test_a_bag_named_twice_is_read_once(setup, tmp_path):
    """The same bag as a folder, again, and by its .mcap file: one bag's estimates, and a warning."""
    model, bag = setup
    mcap = next(bag.glob("*.mcap"))
    with pytest.warns(UserWarning, match=r"2 bag\(s\) given more than once .* are read once"):
        assert run(model, bag, bag, mcap, "--out", tmp_path / "e.csv") == 0
    assert len(read_csv(tmp_path / "e.csv")) == len(EPISODES)


def read_terminal(fd: int) -> bytes:
    """What a pseudo-terminal has for us; b"" once the process on its other side has closed it (EIO)."""
    try:
        return os.read(fd, 4096)
    except OSError:
        return b""


def test_ctrl_c_is_one_line_and_writes_nothing(setup, tmp_path):
    """A real SIGINT while estimate works through many bags: status 130, one line, no CSV (was a
    KeyboardInterrupt traceback)."""
    import signal
    import subprocess
    import sys

    model, bag = setup
    copies = [str(shutil.copytree(bag, tmp_path / "bags" / f"b{i}")) for i in range(200)]
    terminal, stderr = pty.openpty()  # progress bars are drawn on a terminal only, one with columns
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "ad_estimator.estimate", "--model", str(model), *copies,
                             "--out", str(tmp_path / "e.csv")], stderr=stderr)
    os.close(stderr)
    seen = b""
    while b"bags:" not in seen:  # the progress bar: start-up is over, the bags are being read
        chunk = read_terminal(terminal)
        assert chunk, f"estimate ended before reading the bags: {seen!r}"
        seen += chunk
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    while chunk := read_terminal(terminal):
        seen += chunk
    os.close(terminal)
    err = seen.decode().replace("\r\n", "\n")
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "estimate: interrupted; nothing was written", err
    assert "Traceback" not in err and not (tmp_path / "e.csv").exists()
