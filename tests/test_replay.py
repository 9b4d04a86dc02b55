"""replay (bag -> topics with recorded timing and QoS) and the live path against the offline path."""
import json
import shutil
import os
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from ad_msgs.msg import MaterialEstimate, SimInstance
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from ad_estimator import evaluate, replay
from ad_estimator.model import BUNDLED_MODEL
from ad_sim import messages
from ad_sim.rosbag import BagError, BagReader
from estimator_bags import instance_dict, write_test_bag
from estimator_models import build_streaming_model
from estimator_ros import ros_context, wait_for

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "bags" / "samples"
SAMPLE_BAG = SAMPLES / "unseen-masks-0of1"  # a recording of the simulator node: 306 messages on 3 topics
MASK_TOPIC = "/ad_sim/view_0/mask"
INSTANCE_TOPIC = "/ad_sim/instance"
pytestmark = pytest.mark.ros
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def run(module, *args):
    """The executable as a process, on this test's ROS_DOMAIN_ID (set by the ros_domain_id fixture)."""
    return subprocess.Popen([sys.executable, "-m", module, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.fixture(scope="module")
def test_bag(tmp_path_factory):
    return write_test_bag(tmp_path_factory.mktemp("bags") / "three_episodes")


@pytest.fixture
def sample_bag(tmp_path):
    """A copy of a committed sample bag, to damage."""
    return shutil.copytree(SAMPLE_BAG, tmp_path / "bag")


def test_replay_keeps_bytes_timing_and_qos(test_bag, ros_domain_id):
    with ros_context(ros_domain_id) as (context, executor):
        node = Node("replay_listener", context=context)
        frames, instances = [], []
        # (when the replay published the frame, DDS's source timestamp in s; the frame)
        node.create_subscription(Image, MASK_TOPIC, lambda m, info: frames.append((info["source_timestamp"] / 1e9, m)),
                                 RELIABLE)
        node.create_subscription(SimInstance, INSTANCE_TOPIC, instances.append, LATCHED)
        executor.add_node(node)
        proc = run("ad_estimator.replay", str(test_bag), "--rate", "2", "--quiet", "--wait-for", MASK_TOPIC,
                   INSTANCE_TOPIC)
        assert wait_for(lambda: len(frames) > 0, timeout=30)
        info = node.get_publishers_info_by_topic(INSTANCE_TOPIC)  # as recorded: ground truth is latched
        assert info and info[0].qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert node.get_publishers_info_by_topic(MASK_TOPIC)[0].qos_profile.durability == DurabilityPolicy.VOLATILE
        assert wait_for(lambda: len(frames) == 75, timeout=30), proc.communicate(timeout=10)[0]
        out, _ = proc.communicate(timeout=20)
        assert proc.returncode == 0 and "published 78 messages" in out, out

    recorded = [(s, m) for t, s, m in BagReader(test_bag) if t == MASK_TOPIC]
    for (_, got), (stamp, want) in zip(frames, recorded):
        assert stamp_ns(got.header.stamp) == stamp and bytes(got.data) == want.data
    assert [i.episode_id for i in instances] == [f"test-disc-{m}-{k:04d}" for k, m in
                                                 enumerate(["jelly", "plasticine", "sand"])]
    # At rate 2: frames 12.5 ms apart, episodes starting 0.75 s apart, 1.8 s in all (3.6 s in the bag).
    # Timed as the replay published them (source timestamps), not as this test's executor (a background thread of
    # a busy process) got to them: a first frame taken late, then the rest in a burst, made episodes seem early.
    # A busy machine only delays the replay's publishing (it then catches up), never advances it: so no
    # episode may start early, and the whole replay must be clearly shorter than at rate 1, with room for a
    # second and a half of stalls.
    arrivals = np.array([t for t, _ in frames]) - frames[0][0]
    starts = arrivals[[0, 25, 50]]
    assert np.all(starts >= np.array([0.0, 0.75, 1.5]) - 0.05), starts
    assert 1.8 - 0.05 <= arrivals[-1] < 3.6 - 0.3, arrivals[-1]


@pytest.mark.parametrize("content", [b"\x89MCAP0\r\n" + b"\x01" * 64, b"garbage"], ids=["bad_records", "not_mcap"])
def test_replay_corrupt_bag_is_a_clear_error(tmp_path, content, ros_domain_id):
    bag = tmp_path / "bad"
    bag.mkdir()
    (bag / "bad_0.mcap").write_bytes(content)
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "bad_0.mcap" in out and "Traceback" not in out, out
    if content == b"garbage":
        assert "is not an MCAP file" in out, out


def test_replay_truncated_recording_with_recover(tmp_path, ros_domain_id):
    """A killed recorder's file: refused with a hint to --recover; with it, what was flushed plays."""
    bag = write_test_bag(tmp_path / "killed", chunk_size=20_000)
    (file,) = bag.glob("*.mcap")
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 3])
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0", "--rate", "100")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "--recover" in out and "Traceback" not in out, out
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0", "--rate", "100", "--recover")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "warning: " in out and "truncated" in out, out
    published = int(out.split("replay: published ")[1].split()[0])
    assert 0 < published < 3 * 26, out  # some, not all, of 3 episodes x (instance + 25 masks)


def test_replay_of_a_bag_corrupt_part_way_says_how_much_it_published(sample_bag, ros_domain_id):
    """Without --recover the replay stops at the damage, on one line that says what already went out."""
    (file,) = sample_bag.glob("*.mcap")
    with file.open("r+b") as f:  # inside a chunk past the first ones
        f.seek(30_000)
        f.write(b"\xff" * 4)
    readable = 0
    with pytest.raises(BagError, match="corrupt record"):
        for _ in BagReader(sample_bag, raw=True):
            readable += 1
    assert 0 < readable < 306
    proc = run("ad_estimator.replay", str(sample_bag), "--quiet", "--delay", "0", "--rate", "100")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and len(out.splitlines()) == 1, out
    assert out.startswith(f"replay: stopped after {readable} of 306 messages from {sample_bag}: {file}: corrupt "
                          "record"), out
    assert "--recover" in out, out


def test_replay_of_a_bag_with_nothing_readable_fails_saying_so(tmp_path, ros_domain_id):
    """Cut inside its first chunk: --recover plays nothing, which is an error saying why (not "published 0")."""
    bag = write_test_bag(tmp_path / "cut")
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[:300])
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0", "--recover")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and out == (f"replay: nothing readable in {file}: it is truncated before its first "
                                            "complete chunk (300 bytes; was the writer killed?)\n"), out


def test_replay_of_a_bag_with_an_unusable_metadata_yaml(test_bag, tmp_path, ros_domain_id):
    """An empty metadata.yaml: one line naming --recover; with it, the .mcap beside it plays in full."""
    bag = tmp_path / "bag"
    shutil.copytree(test_bag, bag)
    (bag / "metadata.yaml").write_text("")
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and out == (f"replay: {bag}/metadata.yaml is unreadable (empty); pass --recover to "
                                            "read the 1 .mcap file(s) beside it\n"), out
    proc = run("ad_estimator.replay", str(bag), "--quiet", "--delay", "0", "--rate", "100", "--recover")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and out.splitlines()[0] == (f"warning: {bag}/metadata.yaml is unreadable (empty); "
                                                            "reading the 1 .mcap file(s) beside it"), out
    assert f"published 78 messages from {bag}" in out, out


@pytest.mark.parametrize("topic, recorded, unusable, expected", [
    # unknown history with a depth, and the older numeric form (rmw enums: 0 system default): the rest of the
    # recorded QoS stays
    (INSTANCE_TOPIC, [{"history": "unknown", "depth": 5, "reliability": "reliable", "durability": "transient_local"}],
     "history 'unknown'", ("reliable", "transient_local", "keep_last", 5)),
    (MASK_TOPIC, [{"history": 0, "depth": 0, "reliability": 2, "durability": 2}],
     "history 0, depth 0", ("best_effort", "volatile", "keep_last", 100)),
    (MASK_TOPIC, [{"history": "keep_last", "depth": "abc", "reliability": "best_effort", "durability": "volatile"}],
     "depth 'abc'", ("best_effort", "volatile", "keep_last", 100)),
    (MASK_TOPIC, [{"history": "keep_last", "depth": 5, "reliability": "system_default", "durability": ["x"]}],
     "reliability 'system_default', durability ['x']", ("reliable", "volatile", "keep_last", 5)),
    # malformed as a whole: the topic's default (ground truth latched, as the simulator offers it)
    (INSTANCE_TOPIC, "garbage", "not a list of profiles ('garbage')",
     ("reliable", "transient_local", "keep_last", 1)),
    (INSTANCE_TOPIC, ["x"], "not a list of profiles (['x'])", ("reliable", "transient_local", "keep_last", 1)),
    (MASK_TOPIC, {"depth": 5}, "not a list of profiles ({'depth': 5})", ("reliable", "volatile", "keep_last", 100)),
    (MASK_TOPIC, "- history: [keep_last\n  depth: 'x", "not YAML (expected ',' or ']', but got ':')",
     ("reliable", "volatile", "keep_last", 100)),
], ids=["fast_dds_unknown", "numeric_system_default", "depth_not_a_number", "unknown_enums", "string",
        "list_of_strings", "mapping", "broken_yaml_string"])
def test_replay_takes_the_default_for_unusable_recorded_qos(sample_bag, topic, recorded, unusable, expected):
    """A setting that cannot be used falls back to the topic's default with one warning naming the topic."""
    metadata_file = sample_bag / "metadata.yaml"
    metadata = yaml.safe_load(metadata_file.read_text())
    for entry in metadata["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if entry["topic_metadata"]["name"] == topic:
            entry["topic_metadata"]["offered_qos_profiles"] = recorded
    metadata_file.write_text(yaml.safe_dump(metadata))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        qos = replay.recorded_topics(BagReader(sample_bag, raw=True))[topic][1]
    assert [str(w.message) for w in caught] == [
        f"unusable QoS for {topic} in metadata.yaml ({unusable}); replaying it as {', '.join(expected[:3])}, "
        f"depth {expected[3]} (the default for what was unusable)"]
    assert (qos.reliability, qos.durability, qos.history, qos.depth) == (
        ReliabilityPolicy[expected[0].upper()], DurabilityPolicy[expected[1].upper()],
        HistoryPolicy[expected[2].upper()], expected[3])


def test_what_ros2_bag_record_writes_for_a_discovered_publisher_takes_the_default_quietly(sample_bag):
    """history 3 (unknown) and depth 0, in rosbag2's string form (ros2/rosbag2#1237 shows it): what every
    topic of a `ros2 bag record` bag holds, so no warning; reliability and durability are kept."""
    metadata_file = sample_bag / "metadata.yaml"
    metadata = yaml.safe_load(metadata_file.read_text())
    for entry in metadata["rosbag2_bagfile_information"]["topics_with_message_count"]:
        entry["topic_metadata"]["offered_qos_profiles"] = (
            "- history: 3\n  depth: 0\n  reliability: 2\n  durability: 1\n  deadline:\n    sec: 9223372036\n"
            "    nsec: 854775807\n  avoid_ros_namespace_conventions: false")
    metadata_file.write_text(yaml.safe_dump(metadata))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        topics = replay.recorded_topics(BagReader(sample_bag, raw=True))
    for topic, (_, qos) in topics.items():
        assert (qos.reliability, qos.durability, qos.history, qos.depth) == (
            ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.TRANSIENT_LOCAL, HistoryPolicy.KEEP_LAST,
            messages.topic_qos(topic)["depth"])


def test_a_topic_metadata_yaml_leaves_out_is_replayed_with_the_files_type(sample_bag, ros_domain_id):
    """topics_with_message_count: [] passed validation, then replay died of KeyError on the first message."""
    metadata_file = sample_bag / "metadata.yaml"
    metadata = yaml.safe_load(metadata_file.read_text())
    metadata["rosbag2_bagfile_information"]["topics_with_message_count"] = []
    metadata_file.write_text(yaml.safe_dump(metadata))
    proc = run("ad_estimator.replay", str(sample_bag), "--quiet", "--delay", "0", "--rate", "100")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and out.splitlines()[-1] == f"replay: published 306 messages from {sample_bag}", out


def test_replay_of_a_bag_with_unusable_recorded_qos_plays_it_all(sample_bag, ros_domain_id):
    """The command line: a warning line for that topic, then the whole bag (it was refused, naming no topic)."""
    metadata_file = sample_bag / "metadata.yaml"
    metadata_file.write_text(metadata_file.read_text().replace("history: keep_last\n        depth: 1\n",
                                                               "history: system_default\n        depth: 0\n", 1))
    proc = run("ad_estimator.replay", str(sample_bag), "--quiet", "--delay", "0", "--rate", "100")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and out.splitlines() == [
        f"warning: unusable QoS for {INSTANCE_TOPIC} in metadata.yaml (history 'system_default', depth 0); "
        "replaying it as "
        "reliable, transient_local, keep_last, depth 1 (the default for what was unusable)",
        f"replay: published 306 messages from {sample_bag}"], out


@pytest.mark.parametrize("options, message", [
    (["--delay", "-1"], "--delay must be a number of seconds from 0 to 86400 (a day)"),
    (["--delay", "inf"], "--delay must be a number of seconds from 0 to 86400 (a day)"),
    (["--delay", "1e300"], "--delay must be a number of seconds from 0 to 86400 (a day)"),  # time.sleep overflowed
    (["--wait-timeout", "-5"], "--wait-timeout must be a number of seconds >= 0"),
    (["--wait-timeout", "nan"], "--wait-timeout must be a number of seconds >= 0"),
    (["--rate", "0"], "--rate must be at least 0.001"),
    (["--rate", "1e-300"], "--rate must be at least 0.001"),  # the pacing sleep overflowed
])
def test_replay_refuses_bad_timing_options_before_starting(test_bag, options, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        replay.main(["replay", str(test_bag), *options])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_replay_wait_for_names_the_bags_topics(test_bag, ros_domain_id):
    proc = run("ad_estimator.replay", str(test_bag), "--wait-for", "/camera/mask", "--wait-timeout", "1", "--quiet")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "Traceback" not in out, out
    assert "--wait-for /camera/mask: not a replayed topic; name one of the bag's topics (/ad_sim/instance, " \
           "/ad_sim/view_0/mask)" in out, out


def test_replay_that_hears_no_subscriber_says_what_to_check(test_bag, ros_domain_id):
    proc = run("ad_estimator.replay", str(test_bag), "--wait-for", "/ad_sim/view_0/mask", "--wait-timeout", "1",
               "--quiet")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "Traceback" not in out, out
    assert (f"no subscriber on /ad_sim/view_0/mask after 1.0 s; is the subscriber running with the same ROS_DOMAIN_ID "
            f"({ros_domain_id}) and discovery range (ROS_AUTOMATIC_DISCOVERY_RANGE "
            f"{os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'unset')})?") in out, out


def test_replay_of_a_bag_without_messages_says_so(tmp_path, ros_domain_id):
    from ad_sim.rosbag import BagWriter

    with BagWriter(tmp_path / "empty") as writer:
        writer.add_topic(messages.mask_topic(0), messages.IMAGE_TYPE)
    proc = run("ad_estimator.replay", str(tmp_path / "empty"), "--quiet", "--delay", "0")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "published 0 messages" in out and "(it holds none on the replayed topics)" in out, out


def test_replay_missing_bag(tmp_path, ros_domain_id):
    proc = run("ad_estimator.replay", str(tmp_path / "nothing"))
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "does not exist" in out


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_replay_stops_cleanly_on_signals(test_bag, sig, ros_domain_id):
    with ros_context(ros_domain_id) as (context, executor):
        node = Node("replay_listener", context=context)
        frames = []
        node.create_subscription(Image, MASK_TOPIC, frames.append, RELIABLE)
        executor.add_node(node)
        proc = run("ad_estimator.replay", str(test_bag), "--rate", "0.2", "--quiet", "--delay", "0")
        # The signal once the replay publishes (the bag lasts 18 s at rate 0.2). Sent 2 s after the start, it could
        # find a busy machine's replay still importing: death by SIGTERM, or "interrupted while starting".
        assert wait_for(lambda: frames or proc.poll() is not None, timeout=60) and frames, proc.communicate()[0]
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=20)
    # Says how far it got, for SIGTERM too (it said nothing, or "published N" as if the bag had been played).
    assert proc.returncode == 0 and "Traceback" not in out and "published" not in out, out
    assert re.search(rf"replay: stopped after \d+ of 78 messages from {re.escape(str(test_bag))}", out), out


def test_replay_interrupted_in_its_wait_for_acknowledgements_says_all_was_published(test_bag, ros_domain_id,
                                                                                      monkeypatch, capsys):
    """Ctrl-C after the last message, in the wait for reliable subscribers' acknowledgements: everything went out,
    so it is not "stopped after 78 of 78 messages"."""
    def interrupted(self, timeout):
        raise KeyboardInterrupt

    monkeypatch.setattr(replay.Replayer, "wait_for_acknowledgments", interrupted)
    assert replay.main(["replay", str(test_bag), "--quiet", "--delay", "0", "--rate", "1000"]) == 0
    err = capsys.readouterr().err
    assert "stopped after" not in err, err
    assert err.endswith(f"replay: published 78 messages from {test_bag}; interrupted while waiting for reliable "
                        "subscribers' acknowledgements (all published)\n"), err


def test_replay_waits_out_a_gap_too_long_for_one_sleep(tmp_path, ros_domain_id):
    """Log times 317 years apart (past what time.sleep takes, OverflowError): the replay waits until stopped."""
    from ad_sim.rosbag import BagWriter

    with BagWriter(tmp_path / "gap") as writer:
        writer.add_topic(INSTANCE_TOPIC, messages.INSTANCE_TYPE)
        for index, log_time in enumerate([0, 10**19]):
            writer.write(INSTANCE_TOPIC, log_time, instance_dict(index, "jelly", {}, stamp_ns=index))
    with ros_context(ros_domain_id) as (context, executor):
        node = Node("replay_listener", context=context)
        instances = []
        node.create_subscription(SimInstance, INSTANCE_TOPIC, instances.append, RELIABLE)
        executor.add_node(node)
        proc = run("ad_estimator.replay", str(tmp_path / "gap"), "--quiet", "--delay", "0", "--wait-for",
                   INSTANCE_TOPIC)
        assert wait_for(lambda: len(instances) == 1, timeout=30)
        time.sleep(0.5)  # into the wait for the second message
        assert proc.poll() is None, proc.communicate()[0]
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0 and out == f"replay: stopped after 1 of 2 messages from {tmp_path / 'gap'}\n", out


def test_replay_loop_plays_the_bag_again_until_stopped(test_bag, ros_domain_id):
    with ros_context(ros_domain_id) as (context, executor):
        node = Node("replay_listener", context=context)
        frames = []
        node.create_subscription(Image, MASK_TOPIC, lambda m: frames.append(stamp_ns(m.header.stamp)), RELIABLE)
        executor.add_node(node)
        proc = run("ad_estimator.replay", str(test_bag), "--rate", "20", "--quiet", "--loop", "--wait-for",
                   MASK_TOPIC)
        recorded = [stamp for topic, stamp, _ in BagReader(test_bag) if topic == MASK_TOPIC]

        def a_later_pass_is_the_whole_bag():  # the first frames of the first pass may precede discovery
            starts = [i for i, stamp in enumerate(frames) if i > 0 and stamp == recorded[0]]
            return any(frames[i:i + len(recorded)] == recorded for i in starts)

        assert wait_for(a_later_pass_is_the_whole_bag, timeout=60), frames
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0 and re.search(r"replay: stopped after \d+ messages from ", out), out


def test_replay_clock_publishes_the_bags_time_for_use_sim_time_nodes(test_bag, ros_domain_id):
    """--clock: /clock carries each message's log time (rclpy's time source, best effort, reads it), never
    going back within a pass; a node with use_sim_time ends on the bag's time. Without it there is no /clock."""
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    log_times = sorted({log_time for _, log_time, _ in BagReader(test_bag, raw=True)})
    with ros_context(ros_domain_id) as (context, executor):
        node = Node("clock_listener", context=context,
                    parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        clocks = []
        node.create_subscription(Clock, "/clock", lambda m: clocks.append(stamp_ns(m.clock)),
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        executor.add_node(node)
        proc = run("ad_estimator.replay", str(test_bag), "--rate", "4", "--quiet", "--clock", "--wait-for", MASK_TOPIC)
        node.create_subscription(Image, MASK_TOPIC, lambda m: None, RELIABLE)  # what --wait-for waits for
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0, out
        assert wait_for(lambda: node.get_clock().now().nanoseconds == log_times[-1], timeout=5), (
            node.get_clock().now().nanoseconds, log_times[-1])
        # The first replay's publishers out of this node's graph first (discovery hears of a participant's end
        # asynchronously, at its lease if the word is lost): else its /mask and /clock could be the ones counted.
        assert wait_for(lambda: node.count_publishers(MASK_TOPIC) == 0 and node.count_publishers("/clock") == 0,
                        timeout=30)
        without = run("ad_estimator.replay", str(test_bag), "--rate", "4", "--quiet", "--wait-for", MASK_TOPIC)
        assert wait_for(lambda: node.count_publishers(MASK_TOPIC) > 0, timeout=30)
        assert node.count_publishers("/clock") == 0
        without.communicate(timeout=60)
    assert clocks == sorted(clocks) and set(clocks) <= set(log_times), clocks
    assert len(clocks) >= len(log_times) // 2, (len(clocks), len(log_times))  # best effort: most, on one machine


def live_and_offline_inputs(tmp_path):
    """The committed sample bags and the bundled model when they exist, else a written bag and test model."""
    bags = sorted(p.parent for p in SAMPLES.glob("*/metadata.yaml"))
    if not bags:
        bags = [write_test_bag(tmp_path / "bag")]
    model = BUNDLED_MODEL if BUNDLED_MODEL.is_file() else build_streaming_model(tmp_path)
    return bags, model


def test_live_path_equals_offline_path(tmp_path, ros_domain_id):
    """replay -> node -> estimates (with SimInstance ground truth) == evaluate on the same bags."""
    bags, model = live_and_offline_inputs(tmp_path)
    assert evaluate.main(["--model", str(model), "--bags", *map(str, bags), "--out", str(tmp_path / "report"),
                          "--quiet"]) == 0
    offline = json.loads((tmp_path / "report" / "predictions.json").read_text())["frames"]["25"]
    assert offline

    with ros_context(ros_domain_id) as (context, executor):
        listener = Node("live_listener", context=context)
        estimates, instances = [], {}
        listener.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append, RELIABLE)
        listener.create_subscription(SimInstance, INSTANCE_TOPIC,
                                     lambda m: instances.setdefault(stamp_ns(m.header.stamp), m), LATCHED)
        executor.add_node(listener)
        estimator = run("ad_estimator.node", "--ros-args", "-p", f"model_path:={model}", "-p", "reliable:=true",
                        "-p", "input_depth:=200")  # a busy CI machine must not lose a frame
        live = {}
        try:
            assert wait_for(lambda: listener.count_publishers("/ad_estimator/estimate") > 0, timeout=30)
            for bag in bags:  # one at a time: every bag's stamps start at 0
                expected = [p for p in offline if p["bag"] == str(bag)]
                # The listener must have matched the latched ground truth before the replay can exit.
                replay = run("ad_estimator.replay", str(bag), "--rate", "3", "--quiet", "--wait-for", MASK_TOPIC,
                             INSTANCE_TOPIC)
                out, _ = replay.communicate(timeout=120)
                assert replay.returncode == 0, out
                assert wait_for(lambda: len(estimates) >= len(expected), timeout=20), (len(estimates), bag)
                time.sleep(0.3)
                live[bag] = (list(estimates), dict(instances))
                estimates.clear()
                instances.clear()
        finally:
            estimator.terminate()
            log = estimator.communicate(timeout=20)[0]
        assert estimator.returncode == 0, log

    for bag, (bag_estimates, bag_instances) in live.items():
        expected_by_start = {p["oldest_stamp_ns"]: p for p in offline if p["bag"] == str(bag)}
        assert len(bag_estimates) == len(expected_by_start)
        for estimate in bag_estimates:
            start = stamp_ns(estimate.oldest_stamp)
            expected = expected_by_start[start]
            truth = bag_instances[start]  # ground truth of the episode, stamped at its frame 0
            assert truth.episode_id == expected["episode_id"] and truth.material == expected["true_material"]
            assert estimate.complete and estimate.frames_used == expected["frames_used"] == 25
            assert stamp_ns(estimate.header.stamp) == expected["newest_stamp_ns"]
            assert estimate.material == expected["material"]
            np.testing.assert_allclose(estimate.class_probabilities, expected["probabilities"], rtol=1e-5)
            # predictions.json is strict JSON: null where the predicted family has no such parameter.
            parameters = [np.nan if v is None else v for v in expected["parameters"]]
            np.testing.assert_allclose(estimate.parameters, parameters, rtol=1e-5)
