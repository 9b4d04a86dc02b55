"""training.data: real MCAP bags (written by ad_sim's own writer and message code) -> cache."""
from __future__ import annotations

import io
import logging
import re
import shutil
import sys

import numpy as np
import pytest

from ad_sim import messages
from ad_sim.generate import write_episodes
from ad_sim.materials import FAMILIES, PARAMETER_NAMES, normalise
from ad_sim.rosbag import BagWriter, qos_profile
from training import data
from training.synthetic import synthetic_episode, write_synthetic_bag
from sim_fixtures import thresholded, write_coverage_bag


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    write_synthetic_bag(root / "a", 4, views=2, seed=3)
    write_synthetic_bag(root / "b", 2, views=1, seed=3, first=4)
    return root


def test_instances_labels_and_arrays_match_what_was_written(bags, tmp_path):
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    assert len(ds) == 6 and ds.num_videos == 4 * 2 + 2
    written = [synthetic_episode(i, 3, 2 if i < 4 else 1) for i in range(6)]
    assert ds.episode_ids == [e.instance.episode_id for e in written]
    for i, ep in enumerate(written):
        family = ep.instance.material
        assert ds.labels[i] == FAMILIES.index(family)
        for j, name in enumerate(PARAMETER_NAMES):
            if name in ep.instance.parameters:
                assert ds.params_si[i, j] == pytest.approx(ep.instance.parameters[name])
            else:
                assert np.isnan(ds.params_si[i, j])
        # Sand's E and nu are fixed: only its friction angle is a target.
        expected_mask = {"jelly": [1, 1, 0, 0], "plasticine": [1, 1, 1, 0], "sand": [0, 0, 0, 1]}[family]
        np.testing.assert_array_equal(ds.param_mask[i], expected_mask)
        for j, name in enumerate(PARAMETER_NAMES):
            if expected_mask[j]:
                assert ds.params_norm[i, j] == pytest.approx(normalise(name, ep.instance.parameters[name]), abs=1e-6)
        traj = ds.trajectory(i)
        assert traj.shape == (25, 1024, 15) and traj.dtype == np.float32
        np.testing.assert_allclose(traj[..., :3], ep.positions, atol=1e-3)  # float16 cache
        np.testing.assert_allclose(traj[..., 6:], ep.deformation.reshape(25, 1024, 9), atol=2e-3)
        # Displacements are scaled so that their median magnitude over frames 1..24 is 1.
        raw = np.diff(ep.positions, axis=0)
        median = np.median(np.linalg.norm(raw, axis=-1))
        np.testing.assert_allclose(traj[1:, :, 3:6], raw / median, atol=2e-2, rtol=2e-3)
        assert np.median(np.linalg.norm(traj[1:, :, 3:6], axis=-1)) == pytest.approx(1.0, abs=1e-2)
        assert not traj[0, :, 3:6].any()
        for view in range(ep.masks.shape[0]):
            (j,) = np.flatnonzero((ds.video_instance == i) & (ds.video_view == view))
            np.testing.assert_array_equal(ds.video(j), ep.masks[view])


def test_cache_is_reused_and_keyed_by_content(bags, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first = data.load_dataset(bags, cache, progress=False)
    monkeypatch.setattr(data, "read_bag", lambda bag: pytest.fail(f"re-decoded cached bag {bag}"))
    again = data.load_dataset(bags, cache, progress=False)
    assert again.shards == first.shards
    keys = {data.bag_key(b) for b in data.find_bags(bags)}
    assert len(keys) == 2
    other = write_synthetic_bag(tmp_path / "other", 4, views=2, seed=4)
    assert data.bag_key(other) not in keys


def test_grey_masks_asked_of_a_binary_bag_warn_once_naming_it(tmp_path, caplog):
    """load_dataset(coverage=True) reads the masks themselves: a bag of 0/255 masks is named in a warning
    as it is cached (however it was recorded), a grey bag is not, and the cached bag is not warned again."""
    grey, _ = write_coverage_bag(tmp_path / "bags" / "grey", 2, seed=7)
    binary, _ = write_coverage_bag(tmp_path / "bags" / "binary", 2, seed=7, binary=True)
    with caplog.at_level(logging.WARNING, logger=data.log.name):
        data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False, coverage=True)
    warned = [m for m in caplog.messages if m.startswith("grey-mask videos asked for")]
    assert len(warned) == 1 and f"the masks of {binary} are 0/255 only" in warned[0], caplog.messages
    assert str(grey) not in warned[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=data.log.name):
        data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False, coverage=True)
    assert not [m for m in caplog.messages if m.startswith("grey-mask videos asked for")]


def test_coverage_videos_keep_grey_levels_in_their_own_cache(tmp_path, monkeypatch):
    """Bags of grey masks (generate --coverage-masks): load_dataset(coverage=True) keeps the levels in a
    `<key>-coverage` cache folder; the default load of the same bags reads them thresholded, as every
    consumer that thresholds does, in the bag's usual folder; the labels are the same."""
    bag, episodes = write_coverage_bag(tmp_path / "bags" / "grey", 4, views=2, seed=6)
    cache = tmp_path / "cache"
    grey = data.load_dataset(tmp_path / "bags", cache, progress=False, coverage=True)
    binary = data.load_dataset(tmp_path / "bags", cache, progress=False)
    key = data.bag_key(bag)
    assert sorted(p.name for p in cache.iterdir()) == [key, key + "-coverage"]
    assert [s.name for s in grey.shards] == [key + "-coverage"] and [s.name for s in binary.shards] == [key]
    assert grey.episode_ids == binary.episode_ids == [e.instance.episode_id for e in episodes]
    for name in ("labels", "params_si", "params_norm", "param_mask", "video_instance", "video_view"):
        np.testing.assert_array_equal(getattr(grey, name), getattr(binary, name), err_msg=name)
    np.testing.assert_array_equal(grey.trajectory(1), binary.trajectory(1))
    greys = 0
    for i, episode in enumerate(episodes):
        for view in range(2):
            (j,) = np.flatnonzero((grey.video_instance == i) & (grey.video_view == view))
            np.testing.assert_array_equal(grey.video(j), episode.masks[view])
            np.testing.assert_array_equal(binary.video(j), thresholded(episode.masks[view]))
            greys += int(((grey.video(j) > 0) & (grey.video(j) < 255)).sum())
    assert greys > 1000
    # Each cache is reused by the load that made it, not re-decoded nor mixed up with the other.
    monkeypatch.setattr(data, "read_bag", lambda *args: pytest.fail(f"re-decoded cached bag {args}"))
    assert data.load_dataset(tmp_path / "bags", cache, progress=False, coverage=True).shards == grey.shards
    assert data.load_dataset(tmp_path / "bags", cache, progress=False).shards == binary.shards
    # A student's resized frames come from the grey videos, in the coverage folder.
    frames = data.resized_videos(grey, (32, 32))
    assert (cache / (key + "-coverage") / "videos_32x32.npy").exists()
    import cv2

    expected = np.stack([cv2.resize(f, (32, 32), interpolation=cv2.INTER_AREA) for f in grey.video(0)]) / 255.0
    np.testing.assert_allclose(np.asarray(frames[0][0], np.float32), expected, atol=1e-3)


def write_edited_bag(path, episodes, edit, **writer_options) -> None:
    """A bag of the episodes (one view) in which edit(index, topic, stamp, message) gives what to
    write instead of each message (None: leave it out)."""
    types = messages.topic_types(1)
    with BagWriter(path, **writer_options) as writer:
        for index, ep in enumerate(episodes):
            for topic, stamp, msg in messages.episode_messages(ep, index):
                msg = edit(index, topic, stamp, msg)
                if msg is None:
                    continue
                if not writer.has_topic(topic):
                    writer.add_topic(topic, types[topic], [qos_profile(**messages.topic_qos(topic))])
                writer.write(topic, stamp, msg)


def test_the_cache_command_builds_the_grey_mask_cache_with_coverage(tmp_path, monkeypatch, capsys):
    """`python -m training cache --coverage` builds what a student of grey masks (mask_levels=coverage)
    and evaluate load (load_dataset(coverage=True)): the `<key>-coverage` folder, with the levels and the
    resized frames asked for; without the flag, the thresholded cache, as before."""
    from training.__main__ import main

    bag, episodes = write_coverage_bag(tmp_path / "bags" / "grey", 2, views=1, seed=7)
    cache, key = tmp_path / "cache", data.bag_key(bag)
    assert main(["cache", "--bags", str(tmp_path / "bags"), "--cache", str(cache), "--coverage",
                 "--input-size", "32", "32"]) == 0
    assert "2 instances" in capsys.readouterr().out
    assert sorted(p.name for p in cache.iterdir()) == [key + "-coverage"]
    assert (cache / (key + "-coverage") / "videos_32x32.npy").exists()
    monkeypatch.setattr(data, "read_bag", lambda *args: pytest.fail(f"re-decoded cached bag {args}"))
    grey = data.load_dataset(tmp_path / "bags", cache, progress=False, coverage=True)  # what training loads
    for j, episode in enumerate(episodes):
        np.testing.assert_array_equal(grey.video(j), episode.masks[0])
    assert ((grey.video(0) > 0) & (grey.video(0) < 255)).any()
    monkeypatch.undo()
    assert main(["cache", "--bags", str(tmp_path / "bags"), "--cache", str(cache)]) == 0
    assert sorted(p.name for p in cache.iterdir()) == [key, key + "-coverage"]
    binary = data.load_dataset(tmp_path / "bags", cache, progress=False)
    np.testing.assert_array_equal(binary.video(0), thresholded(episodes[0].masks[0]))
    capsys.readouterr()


def test_incomplete_episodes_are_skipped(tmp_path):
    """A recording that lost frames of one episode keeps the complete ones."""
    episodes = [synthetic_episode(i, 0, 1) for i in range(3)]

    def lose_last_particle_frames(index, topic, stamp, msg):
        return None if index == 1 and topic == messages.particles_topic() and stamp > messages.frame_stamp(1, 20) else msg

    write_edited_bag(tmp_path / "bag", episodes, lose_last_particle_frames)
    ds = data.load_dataset(tmp_path / "bag", tmp_path / "cache", progress=False)
    assert ds.episode_ids == [episodes[0].instance.episode_id, episodes[2].instance.episode_id]


def test_episodes_of_two_simulator_runs_recorded_into_one_bag_are_not_mixed(tmp_path, caplog):
    """Each simulator run stamps its episodes from 0 s, so a recorder left running over two runs holds two
    episodes at each start stamp: the first lost every frame to the second, which held both runs' frames,
    some views of the first run under its name (the later message won each frame slot). Both are skipped,
    saying why; an episode without a twin is kept, and a run recorded twice is the same episode, kept once."""
    first_run = [synthetic_episode(i, 0, 2) for i in range(3)]
    second_run = [synthetic_episode(i, 5, 1, split="seen") for i in range(2)]  # 1 view: view_1 would be run 1's
    with BagWriter(tmp_path / "bags" / "two") as writer:
        write_episodes(writer, first_run, 0)
        write_episodes(writer, second_run, 0)
    with BagWriter(tmp_path / "again" / "twice") as writer:
        write_episodes(writer, first_run[:2], 0)
        write_episodes(writer, first_run[:2], 0)
    ds = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert ds.episode_ids == [first_run[2].instance.episode_id]
    for j in range(2):
        np.testing.assert_array_equal(ds.video(j), first_run[2].masks[j])
    bag = tmp_path / "bags" / "two"
    for a, b in zip(first_run, second_run):
        assert any(m.startswith(f"{bag}: episodes {a.instance.episode_id}, {b.instance.episode_id} start at the same "
                                "stamp") and "record each run into its own bag" in m for m in caplog.messages)
    assert f"{bag}: 4 of 5 episodes skipped" in ds.problems
    again = data.load_dataset(tmp_path / "again", tmp_path / "cache", progress=False)
    assert again.episode_ids == [e.instance.episode_id for e in first_run[:2]] and not again.problems
    for i, ep in enumerate(first_run[:2]):
        np.testing.assert_array_equal(again.video(2 * i + 1), ep.masks[1])


def as_mono16(msg):
    """The mono8 mask as mono16 (0 / 65535, little endian): a mask the estimator accepts."""
    pixels = np.frombuffer(bytes(msg["data"]), np.uint8).astype("<u2") * 257
    return {**msg, "encoding": "mono16", "step": msg["step"] * 2, "is_bigendian": 0, "data": pixels.tobytes()}


@pytest.mark.parametrize("damage, reason", [
    (lambda msg: {**msg, "encoding": "32FC1"}, "unsupported encoding '32FC1'"),
    (lambda msg: {**msg, "data": bytes(msg["data"])[:100]}, "data length 100 != step 128 * height 128"),
    (lambda msg: {**msg, "height": 64, "width": 64, "step": 64, "data": bytes([255]) * 64 * 64},
     "mask is 64x64, not the simulator's 128x128"),
])
def test_an_unusable_mask_frame_skips_only_its_episode(tmp_path, caplog, damage, reason):
    """Masks are converted as the estimator converts them: another encoding it accepts is read, a
    frame it refuses (or of another size) loses its episode, named with the frame, and no other."""
    episodes = [synthetic_episode(i, 0, 1) for i in range(3)]
    bad_stamp, mono16_stamp = messages.frame_stamp(1, 10), messages.frame_stamp(2, 5)

    def edit(index, topic, stamp, msg):
        if topic == messages.mask_topic(0) and stamp == bad_stamp:
            return damage(msg)
        return as_mono16(msg) if topic == messages.mask_topic(0) and stamp == mono16_stamp else msg

    write_edited_bag(tmp_path / "bag", episodes, edit)
    ds = data.load_dataset(tmp_path / "bag", tmp_path / "cache", progress=False)
    assert ds.episode_ids == [episodes[0].instance.episode_id, episodes[2].instance.episode_id]
    np.testing.assert_array_equal(ds.video(1), episodes[2].masks[0])  # its mono16 frame included
    bad = episodes[1].instance.episode_id
    where = f"{tmp_path / 'bag'}: episode {bad}: {messages.mask_topic(0)} frame stamped {bad_stamp / 1e9:.3f} s: "
    assert any(m.startswith(where + reason) and m.endswith("; episode skipped") for m in caplog.messages)
    assert f"{tmp_path / 'bag'}: 1 of 3 episodes skipped" in caplog.messages


def test_a_cache_of_a_truncated_bag_warns_on_every_use(tmp_path, caplog, monkeypatch):
    """A bag cut short by a killed recorder is read up to its last complete chunk once, and every later
    use of its cache still says that its source was incomplete."""
    episodes = [synthetic_episode(i, 0, 1) for i in range(3)]
    write_edited_bag(tmp_path / "bag", episodes, lambda index, topic, stamp, msg: msg, chunk_size=50_000)
    file = tmp_path / "bag" / "bag_0.mcap"
    file.write_bytes(file.read_bytes()[: int(file.stat().st_size * 0.8)])
    with pytest.warns(UserWarning, match=r"bag_0\.mcap is truncated: no MCAP footer .*: recovered \d+ messages"):
        first = data.load_dataset(tmp_path / "bag", tmp_path / "cache", progress=False)
    assert first.episode_ids == [e.instance.episode_id for e in episodes[:2]]
    monkeypatch.setattr(data, "read_bag", lambda bag: pytest.fail(f"re-decoded cached bag {bag}"))
    for _ in range(2):
        caplog.clear()
        again = data.load_dataset(tmp_path / "bag", tmp_path / "cache", progress=False)
        assert again.shards == first.shards
        hits = [m for m in caplog.messages if m.startswith("cached from an incomplete bag: ")]
        assert any(f"{file} is truncated: no MCAP footer" in m for m in hits)
        assert any(f"episode {episodes[2].instance.episode_id} is incomplete" in m for m in hits)


def test_a_bag_with_nothing_readable_is_left_out_saying_why(tmp_path, caplog):
    """A bag cut inside its first chunk holds nothing to recover: the others are cached, and the
    dataset's problems say why that one is left out."""
    write_synthetic_bag(tmp_path / "bags" / "good", 2, views=1, seed=3)
    cut = write_synthetic_bag(tmp_path / "bags" / "cut", 2, views=1, seed=3, first=2)
    (file,) = cut.glob("*.mcap")
    file.write_bytes(file.read_bytes()[:300])
    ds = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert len(ds) == 2
    assert ds.problems == [f"nothing readable in {file}: it is truncated before its first complete chunk (300 bytes; "
                           "was the writer killed?)", f"{cut} holds no complete episode; left out"]
    assert ds.problems[0] in caplog.messages


@pytest.mark.parametrize("damage, reason", [
    (lambda shard: (shard / "trajectories.npy").write_bytes((shard / "trajectories.npy").read_bytes()[:1000]),
     "trajectories.npy: mmap length is greater than file size"),
    (lambda shard: (shard / "labels.npy").write_bytes((shard / "labels.npy").read_bytes()[:100]), "labels.npy: EOF"),
    (lambda shard: (shard / "labels.npy").unlink(), "labels.npy: missing"),
    (lambda shard: (shard / "meta.json").write_text("{bad"), "meta.json: Expecting property name"),
    (lambda shard: (shard / "meta.json").write_text("{}"), "meta.json: no lists episode_id"),
    (lambda shard: (shard / "meta.json").write_text("[]"), "meta.json: a JSON list, not an object"),
    (lambda shard: (shard / "meta.json").unlink(), "meta.json: missing"),
])
def test_a_damaged_cache_folder_is_named_with_how_to_rebuild_it(bags, tmp_path, capsys, damage, reason):
    """A cache folder damaged after it was written (numpy's and json's own errors named neither the folder nor
    the file) is one line naming both and saying that deleting the folder rebuilds it."""
    from training.__main__ import main

    cache = tmp_path / "cache"
    data.load_dataset(bags, cache, progress=False)
    shard = cache / data.bag_key(bags / "a")
    damage(shard)
    assert main(["cache", "--bags", str(bags), "--cache", str(cache)]) == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]  # (after the progress bar's)
    assert line.startswith(f"python -m training cache: the cache folder {shard} is damaged ({reason}"), line
    assert line.endswith("; delete that folder and it is rebuilt from its bag on the next run"), line
    shutil.rmtree(shard)
    assert main(["cache", "--bags", str(bags), "--cache", str(cache)]) == 0  # as it says: rebuilt


@pytest.mark.parametrize("size", [["0", "0"], ["-4", "8"], ["32", "x"]])
def test_the_cache_commands_input_size_is_checked_by_argparse(bags, tmp_path, capsys, size):
    """--input-size below 1 was a cv2 assertion traceback after the bags were decoded."""
    from training.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main(["cache", "--bags", str(bags), "--cache", str(tmp_path / "cache"), "--input-size", *size])
    assert exit_info.value.code == 2
    assert "argument --input-size: expected a whole number >= 1" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists()


def test_an_uncompressed_bag_rewritten_in_the_middle_is_not_served_from_its_stale_cache(tmp_path):
    """Uncompressed chunks (generate --compression none) of fixed-size messages keep every size, so a bag
    rewritten with another middle episode had the same size, first and last MiB: the key, and with it
    the old episode's labels, stayed."""
    def write(seeds):
        shutil.rmtree(tmp_path / "bags", ignore_errors=True)
        with BagWriter(tmp_path / "bags" / "bag", compression="none") as writer:  # ~1.6 MB per episode
            write_episodes(writer, [synthetic_episode(i, seed, 1) for i, seed in enumerate(seeds)], 0)

    write([1, 1, 1])
    before = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    write([1, 2, 1])  # the middle episode's parameters and motion change, none of the sizes
    after = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert after.shards != before.shards
    expected = synthetic_episode(1, 2, 1).instance.parameters
    assert after.params_si[1, 0] == pytest.approx(expected["youngs_modulus"])
    assert before.params_si[1, 0] != pytest.approx(expected["youngs_modulus"])
    # Compressed bags keep the keys they had (their chunk sizes already change with their content).
    for bag, hashed in ((tmp_path / "bags" / "bag", True), (write_synthetic_bag(tmp_path / "zstd", 1, views=1), False)):
        with open(next(bag.glob("*.mcap")), "rb") as f:
            assert bool(data._uncompressed_chunk_crcs(f)) == hashed


def test_missing_bags_error_says_what_to_do(tmp_path):
    with pytest.raises(FileNotFoundError, match="ad_sim.generate"):
        data.find_bags(tmp_path)


def test_split_is_deterministic_and_disjoint():
    train, val = data.split_instances(50, 0.2, seed=7)
    again = data.split_instances(50, 0.2, seed=7)
    np.testing.assert_array_equal(train, again[0])
    assert len(val) == 10 and not set(train) & set(val) and len(train) + len(val) == 50
    assert not np.array_equal(val, data.split_instances(50, 0.2, seed=8)[1])


def test_an_episode_in_two_bags_is_never_on_both_sides_of_the_split(tmp_path, caplog):
    """A bag and its copy under --bags (or the same episodes recorded again in another bag) counted
    each episode twice, and the split, drawn over instances, validated on episodes it trained on."""
    write_synthetic_bag(tmp_path / "bags" / "a", 6, views=2, seed=1)
    write_synthetic_bag(tmp_path / "bags" / "b", 3, views=1, seed=1)  # episodes 0..2 again, another recording
    shutil.copytree(tmp_path / "bags" / "a", tmp_path / "bags" / "backup" / "a")  # the same recording
    with caplog.at_level(logging.WARNING, logger="training.data"):
        ds = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert len(ds) == 6 + 3 and "same recording" in caplog.text  # the copy is read once
    ids = np.array(ds.episode_ids)
    for seed in range(8):
        train, val = ds.split(0.3, seed)
        assert len(val) and not set(ids[train]) & set(ids[val]), seed
        first = set(ds.first_copies().tolist())  # validation scores each episode once; training keeps each copy
        assert set(val.tolist()) <= first and first <= set(train.tolist()) | set(val.tolist()), seed
        assert set(train.tolist()) == {i for i in range(len(ds)) if ids[i] not in set(ids[val])}, seed
    # Distinct episodes split as before (a run resumed across this change keeps its validation set).
    for seed in range(3):
        keyed = data.split_instances(40, 0.2, seed, keys=[("e", i) for i in range(40)])
        for a, b in zip(keyed, data.split_instances(40, 0.2, seed)):
            np.testing.assert_array_equal(a, b)


def test_episodes_in_several_bags_are_warned_about(tmp_path, caplog):
    """A split recorded through topics and generated as well, under one --bags, is two bags of the same
    episodes with other bytes (a recording keeps its receive times): each copy was trained on and scored,
    without a word. Now one warning names an episode and its bags; distinct bags say nothing."""
    write_synthetic_bag(tmp_path / "bags" / "generated", 3, views=2, seed=1)
    write_synthetic_bag(tmp_path / "bags" / "recorded", 2, views=1, seed=1)
    write_synthetic_bag(tmp_path / "other", 2, views=1, seed=1, first=3)
    with caplog.at_level(logging.WARNING, logger="training.data"):
        assert len(data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)) == 5
        assert len(data.load_dataset(tmp_path / "other", tmp_path / "cache", progress=False)) == 2
    (warning,) = [m for m in caplog.messages if "more than one bag" in m]
    assert warning.startswith(f"2 episode(s) under {tmp_path / 'bags'} are in more than one bag (e.g. "
                              f"{synthetic_episode(0, 1, 1).instance.episode_id}, in {tmp_path / 'bags' / 'generated'} "
                              f"and {tmp_path / 'bags' / 'recorded'})")


def test_a_looping_simulators_repeats_are_warned_about_and_evaluated_once(tmp_path, caplog):
    """A recording of the simulator node with loop: true holds each episode once a pass, the same simulation
    with later stamps. Nothing said so: each repeat was trained on, and validation and `python -m training
    evaluate` scored it once a pass. Now one warning names an episode and its bag, training keeps the repeats
    on its side of the split, and validation and first_copies (what evaluation scores) hold each episode once."""
    episodes = [synthetic_episode(i, 1, 1) for i in range(3)]
    with BagWriter(tmp_path / "bags" / "looped") as writer:
        for first in (0, 3, 6):  # three passes
            write_episodes(writer, episodes, first)
    with caplog.at_level(logging.WARNING, logger="training.data"):
        ds = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert len(ds) == 9
    (warning,) = [m for m in caplog.messages if "repeat" in m]
    assert warning.startswith(f"3 episode(s) under {tmp_path / 'bags'} repeat within a bag (e.g. "
                              f"{episodes[0].instance.episode_id}, 3 times in {tmp_path / 'bags' / 'looped'}): "
                              "a looping simulator (loop: true) was recorded"), warning
    np.testing.assert_array_equal(ds.first_copies(), [0, 1, 2])
    ids = np.array(ds.episode_ids)
    for seed in range(6):
        train, val = ds.split(0.3, seed)
        assert len(train) == 6 and len(val) == 1 and not set(ids[train]) & set(ids[val]), seed


def test_a_parameter_sweep_of_one_id_and_seed_is_distinct_episodes(tmp_path, caplog):
    """The simulator node's single-instance mode names every episode custom-<shape>-<material>-0000 with
    the seed given, so a stiffness sweep is one bag per Young's modulus, all of one id and seed: distinct
    simulations, which neither warn as copies nor are left out as repeats."""
    for e in (2e4, 2e5, 2e6):
        episode = synthetic_episode(0, 1, 1)
        episode.instance.parameters = {**episode.instance.parameters, "youngs_modulus": e}
        with BagWriter(tmp_path / "bags" / f"E{e:.0e}") as writer:
            write_episodes(writer, [episode], 0)
    with caplog.at_level(logging.WARNING, logger="training.data"):
        ds = data.load_dataset(tmp_path / "bags", tmp_path / "cache", progress=False)
    assert not caplog.messages and len(set(ds.episode_keys())) == 3
    np.testing.assert_array_equal(ds.first_copies(), [0, 1, 2])
    assert sorted(ds.params_si[:, PARAMETER_NAMES.index("youngs_modulus")]) == [2e4, 2e5, 2e6]


def test_resized_videos_are_area_averaged(bags, tmp_path):
    import cv2

    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    frames = data.resized_videos(ds, (32, 32))
    s, r = ds.video_loc[3]
    video = ds.video(3)
    expected = np.stack([cv2.resize(f, (32, 32), interpolation=cv2.INTER_AREA) for f in video]) / 255.0
    np.testing.assert_allclose(np.asarray(frames[s][r], np.float32), expected, atol=1e-3)
    assert (tmp_path / "cache" / ds.shards[s].name / "videos_32x32.npy").exists()


def test_resizing_a_shard_holds_a_slice_of_it_in_memory_not_all_of_it(bags, tmp_path, monkeypatch):
    """At paper size one shard's videos are 3.7 GB of uint8, and resizing them at once took tens of GB of float32.
    In slices, the peak is a slice's; the file equals the all-at-once result."""
    import tracemalloc

    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    monkeypatch.setattr(data, "RESIZE_SLICE_FRAMES", 30)  # one video of 25 frames per slice
    videos = np.load(ds.shards[0] / "videos.npy")
    tracemalloc.start()
    try:
        frames = data.resized_videos(ds, (64, 64), progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(videos) >= 4 and peak < videos.nbytes / 2, (peak, videos.nbytes)
    np.testing.assert_array_equal(frames[0], data.resize_masks(videos, (64, 64)).astype(np.float16))


def test_displacements_are_scaled_by_their_median_and_never_overflow_the_float16_cache():
    """SPEC 6's median scaling, unchanged for an ordinary episode; an object at rest for most frames
    (median near zero: one hard impact, then stillness) is scaled just enough that float16 keeps it finite."""
    rng = np.random.default_rng(0)
    moving = rng.normal(size=(25, 1024, 15)).astype(np.float32)
    expected = moving[:, :, 3:6] / np.median(np.linalg.norm(moving[1:, :, 3:6], axis=-1))
    np.testing.assert_allclose(data.normalise_displacement(moving.copy())[:, :, 3:6], expected, rtol=1e-6)

    resting = np.zeros((25, 1024, 15), np.float32)
    resting[1:3, :, 5] = -0.1  # two frames of falling, 0.1 m each, then rest
    resting[3:, :, 3] = 1e-9   # and a creep far below the float16 range's reach
    scaled = data.normalise_displacement(resting.copy())[:, :, 3:6]
    assert np.isfinite(scaled.astype(np.float16)).all()
    assert np.abs(scaled).max() == pytest.approx(data.FLOAT16_SAFE, rel=1e-5)
    np.testing.assert_allclose(scaled[3:, :, 0] / scaled[1, :, 2], -1e-8, rtol=1e-5)  # proportions kept
    assert not data.normalise_displacement(np.zeros((25, 4, 15), np.float32)).any()  # motionless: zeros


def test_bag_folders_that_are_links_are_found_once_and_in_order(tmp_path):
    """A bag folder under --bags that is a link (a shard kept on another disk) was left out without a word, and
    with it its episodes; bags are found in the same sorted order as without links (the split follows it), each
    real folder once, and a link loop ends."""
    plain = tmp_path / "plain"
    for i, name in enumerate(("train-0of3", "train-1of3", "train-2of3")):
        write_synthetic_bag(plain / name, 1, views=1, seed=5, first=i)
    linked = tmp_path / "linked"
    linked.mkdir()
    shutil.copytree(plain / "train-0of3", linked / "train-0of3")
    (linked / "train-1of3").symlink_to(plain / "train-1of3", target_is_directory=True)
    (linked / "more").mkdir()
    (linked / "more" / "train-2of3").symlink_to(plain / "train-2of3", target_is_directory=True)
    (linked / "more" / "loop").symlink_to(linked, target_is_directory=True)
    (linked / "zz-again").symlink_to(plain / "train-1of3", target_is_directory=True)  # the same bag by two names
    assert [b.relative_to(plain) for b in data.find_bags(plain)] == [
        plain.joinpath(n).relative_to(plain) for n in ("train-0of3", "train-1of3", "train-2of3")]
    assert [str(b.relative_to(linked)) for b in data.find_bags(linked)] == [
        "more/train-2of3", "train-0of3", "train-1of3"]
    a = data.load_dataset(plain, tmp_path / "cache", progress=False)
    b = data.load_dataset(linked, tmp_path / "cache", progress=False)
    assert len(a) == 3 and b.episode_ids == [a.episode_ids[i] for i in (2, 0, 1)]


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_bars_are_drawn_on_a_terminal_and_not_into_a_redirected_log(bags, tmp_path, monkeypatch):
    for stderr, drawn in ((Terminal(), True), (io.StringIO(), False)):
        monkeypatch.setattr(sys, "stderr", stderr)
        data.load_dataset(bags, tmp_path / f"cache_{drawn}", progress=True)
        assert ("cache bags" in stderr.getvalue()) == drawn, stderr.getvalue()


def test_camera_views_tell_apart_datasets_of_the_same_instances(tmp_path):
    """A student's resume check (train_teacher.load_run_data) reads the views beside the instances' fingerprint:
    the same two episodes with their two cameras split the other way over them are other videos."""
    for root, (first, second) in {"x": (2, 1), "y": (1, 2)}.items():
        write_synthetic_bag(tmp_path / root / "a", 1, views=first, seed=3)
        write_synthetic_bag(tmp_path / root / "b", 1, views=second, seed=3, first=1)
    x, y = (data.load_dataset(tmp_path / root, tmp_path / "cache", progress=False) for root in "xy")
    assert x.fingerprint() == y.fingerprint()
    for ds in (x, y):
        assert re.fullmatch(r"0,1 \(3 videos\), per instance [0-9a-f]{12}", ds.camera_views()), ds.camera_views()
    assert x.camera_views() != y.camera_views()
    write_synthetic_bag(tmp_path / "z" / "a", 2, views=2, seed=3)  # every instance with both: no digest needed
    assert data.load_dataset(tmp_path / "z", tmp_path / "cache", progress=False).camera_views() == "0,1 (4 videos)"


# --------------------------------------------------------------------------- mutation-testing audit


def test_a_frames_index_is_its_stamp_offset_rounded_to_the_nearest_interval():
    """A frame stamped a little before or after its time (a clock's jitter, float stamps) keeps its index;
    a frame past the last one (the 26th) is not one of the episode's."""
    start = 1_700_000_000_000_000_000
    step = 25_000_000  # FRAME_INTERVAL in ns
    exact = [(start + k * step, f"exact {k}") for k in range(26)]
    frames = data._frames(exact, start)
    assert sorted(frames) == list(range(25)) and frames[24] == (start + 24 * step, "exact 24")
    early = data._frames([(start + k * step - 1, k) for k in range(1, 25)], start)
    assert {t: m for t, (_, m) in early.items()} == {k: k for k in range(1, 25)}
    jittered = data._frames([(start + k * step + (4 if k % 2 else -4) * step // 10, k) for k in range(25)], start)
    assert {t: m for t, (_, m) in jittered.items()} == {k: k for k in range(25)}
    assert data._frames([(start - step, "before"), (start + 25 * step, "after")], start) == {}


def test_labels_normalise_the_sampled_parameters_over_the_union_ranges_and_zero_the_others():
    label, si, norm, mask = data.labels_of("jelly", ["youngs_modulus", "poissons_ratio"], [1.5e5, 0.34])
    assert label == FAMILIES.index("jelly") and np.isnan(si[2:]).all()
    # union ranges: E 1.5e4..1.5e6 (log): 1.5e5 is the middle; nu 0.20..0.48: 0.34 is the middle
    np.testing.assert_allclose(norm, [0.5, 0.5, 0.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(mask, [1, 1, 0, 0])
    label, si, norm, mask = data.labels_of("sand", ["youngs_modulus", "poissons_ratio", "friction_angle"],
                                           [1e5, 0.3, np.radians(27.5)])
    np.testing.assert_array_equal(si[:2], [1e5, 0.3])  # sand's fixed E and nu are known ...
    np.testing.assert_allclose(norm, [0.0, 0.0, 0.0, 0.5], atol=1e-6)  # ... but no targets: 0 and masked
    np.testing.assert_array_equal(mask, [0, 0, 0, 1])
    with pytest.raises(ValueError, match="unknown material 'water'"):
        data.labels_of("water", [], [])


def test_the_validation_share_is_the_nearest_count_and_at_least_one():
    def sizes(n, fraction):
        train, val = data.split_instances(n, fraction, seed=0)
        assert len(train) + len(val) == n and not set(train) & set(val)
        return len(val)

    assert sizes(9, 0.2) == 2  # 1.8 -> 2
    assert sizes(11, 0.2) == 2  # 2.2 -> 2
    assert sizes(4, 0.1) == 1  # 0.4: still one validation instance
    assert sizes(2, 0.9) == 1  # and at least one training instance
    assert sizes(10, 0.0) == 0 and sizes(1, 0.5) == 0


def test_the_first_view_of_each_instance_is_its_lowest(bags, tmp_path):
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    assert set(ds.video_view.tolist()) == {0, 1}
    picked = ds.first_view_videos()
    np.testing.assert_array_equal(ds.video_instance[picked], np.arange(len(ds)))
    assert (ds.video_view[picked] == 0).all()
    some = ds.first_view_videos(np.array([1, 4]))
    np.testing.assert_array_equal(ds.video_instance[some], [1, 4])
    assert (ds.video_view[some] == 0).all()


def test_unit_floats_of_cached_videos():
    np.testing.assert_allclose(data.as_unit_float(np.array([0, 128, 255], np.uint8)), [0.0, 128 / 255, 1.0], rtol=1e-6)
    half = np.array([0.0, 0.25, 1.0], np.float16)
    out = data.as_unit_float(half)
    assert out.dtype == np.float32 and out.tolist() == [0.0, 0.25, 1.0]
