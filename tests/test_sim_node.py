"""`ros2 run ad_sim node` over real DDS: a recorded bag equals generate's bag; pacing; shutdown.

Runs the real simulator (Warp on CPU), the real node and recorder as subprocesses (scripts/adrun).
"""

from __future__ import annotations

import re
import signal
import subprocess
import time

import numpy as np
import pytest
import yaml
from ros_procs import (kill_leftovers, ADRUN, REPO_ROOT, interrupt_while_starting, recorder_counts, start, stop,
                       wait_for_log)
from sim_fixtures import as_plain

from ad_sim.rosbag import BagReader

pytestmark = pytest.mark.ros


@pytest.fixture(autouse=True)
def no_leftover_processes():
    yield
    kill_leftovers()

INSTANCES = [
    {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 5.0e4, "poissons_ratio": 0.3}, "seed": 1},
    {"shape": "torus", "material": "sand", "parameters": {"friction_angle": 0.6}, "seed": 2, "views": 2},
]


@pytest.fixture
def instance_file(tmp_path):
    path = tmp_path / "instances.yaml"
    path.write_text(yaml.safe_dump(INSTANCES))
    return path


def test_recorded_bag_equals_generated_bag(ros_domain_id, tmp_path, instance_file):
    recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(tmp_path / "recorded"))
    node = start(
        "node", ros_domain_id, tmp_path / "node.log",
        instances=str(instance_file), real_time_factor=0.0, wait_for_subscribers=1,
    )
    generated = subprocess.run(
        [str(ADRUN), "ad_sim", "generate", "--instances", str(instance_file), "--out", str(tmp_path / "gen"), "--quiet"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=240,
    )
    assert generated.returncode == 0, generated.stderr
    assert node.wait(240) == 0, (tmp_path / "node.log").read_text()
    node_log = (tmp_path / "node.log").read_text()
    published = int(re.search(r"published 2 episode\(s\), (\d+) messages", node_log).group(1))
    assert stop(recorder) == 0
    record_log = (tmp_path / "record.log").read_text()
    assert "Traceback" not in node_log + record_log
    assert recorder_counts(record_log) == (published, published)

    recorded = list(BagReader(tmp_path / "recorded"))
    generated = list(BagReader(tmp_path / "gen" / "instances-0of1"))
    assert published == len(generated) == 2 + 25 * (2 * 1 + 1) + 25 * (2 * 2 + 1)
    # Same messages at the same stamps; only the order of equal stamps across topics may differ.
    key = lambda m: (m.log_time_ns, m.topic)  # noqa: E731
    assert [key(m) for m in sorted(recorded, key=key)] == [key(m) for m in sorted(generated, key=key)]
    for mine, theirs in zip(sorted(recorded, key=key), sorted(generated, key=key)):
        assert as_plain(mine.message) == as_plain(theirs.message), key(mine)
    assert BagReader(tmp_path / "recorded").topics() == BagReader(tmp_path / "gen" / "instances-0of1").topics()


def test_coverage_masks_recorded_from_the_node_equal_generated_ones_and_train_as_grey(ros_domain_id, tmp_path, caplog):
    """coverage_masks:=true publishes the grey masks that `generate --coverage-masks` writes, message for
    message, and a student's grey-mask cache reads their levels without warning that the bag is 0/255."""
    from training import data

    one = tmp_path / "one.yaml"
    one.write_text(yaml.safe_dump(INSTANCES[:1]))
    recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(tmp_path / "recorded"))
    node = start("node", ros_domain_id, tmp_path / "node.log", instances=str(one), real_time_factor=0.0,
                 wait_for_subscribers=1, coverage_masks=True)
    generated = subprocess.run(
        [str(ADRUN), "ad_sim", "generate", "--instances", str(one), "--out", str(tmp_path / "gen"), "--quiet",
         "--coverage-masks"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=240)
    assert generated.returncode == 0, generated.stderr
    assert node.wait(240) == 0, (tmp_path / "node.log").read_text()
    assert stop(recorder) == 0
    key = lambda m: (m.log_time_ns, m.topic)  # noqa: E731
    recorded = sorted(BagReader(tmp_path / "recorded"), key=key)
    theirs = sorted(BagReader(tmp_path / "gen" / "one-0of1"), key=key)
    assert [key(m) for m in recorded] == [key(m) for m in theirs] and len(recorded) == 1 + 25 * 3  # + particles, mask, camera_info
    for mine, other in zip(recorded, theirs):
        assert as_plain(mine.message) == as_plain(other.message), key(mine)
    levels = np.concatenate([np.frombuffer(bytes(m.message.data), np.uint8) for m in recorded if m.topic.endswith("mask")])
    assert ((levels > 0) & (levels < 255)).sum() > 100  # grey edges
    with caplog.at_level("WARNING", logger=data.log.name):
        grey = data.load_dataset(tmp_path / "recorded", tmp_path / "cache", progress=False, coverage=True)
    assert not [m for m in caplog.messages if m.startswith("grey-mask videos asked for")], caplog.messages
    assert ((grey.video(0) > 0) & (grey.video(0) < 255)).any()


def test_pacing_and_clean_shutdown(rclpy_context, ros_domain_id, tmp_path):
    from rcl_interfaces.srv import SetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    listener = Node("listener", context=rclpy_context)
    arrivals = []  # (stamp, wall time the node published it: DDS's source timestamp, not when this test got to it)
    listener.create_subscription(
        PointCloud2, "/ad_sim/particles",
        lambda msg, info: arrivals.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                                           info["source_timestamp"] * 1e-9)),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
    )
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(listener)
    # Two soft spheres (few substeps: quick to simulate), both simulated before playback starts.
    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    try:
        for sig in (signal.SIGTERM, signal.SIGINT):
            arrivals.clear()
            node = start("node", ros_domain_id, tmp_path / f"node{sig}.log", instances=str(instance_file), real_time_factor=2.0, loop=True)
            deadline = time.monotonic() + 120
            while len(arrivals) < 40:  # into the second episode, across the 1.5 s stamp gap
                assert time.monotonic() < deadline, (tmp_path / f"node{sig}.log").read_text()
                executor.spin_once(timeout_sec=0.05)
            if sig == signal.SIGTERM:  # parameters are read at start: a change at run time is refused, not ignored
                client = listener.create_client(SetParameters, "/ad_sim/set_parameters")
                assert client.wait_for_service(timeout_sec=10)
                future = client.call_async(SetParameters.Request(parameters=[
                    Parameter("real_time_factor", value=0.0).to_parameter_msg()]))
                executor.spin_until_future_complete(future, timeout_sec=10)
                (result,) = future.result().results
                assert not result.successful and "read-only" in result.reason
            assert stop(node, sig) == 0
            log = (tmp_path / f"node{sig}.log").read_text()
            assert "Traceback" not in log and "episode 1: custom-sphere-jelly-0001" in log
            stamps, walls = np.array(arrivals).T
            # Wall time runs at half the simulated time (real_time_factor 2), gap included.
            slope = np.polyfit(stamps, walls, 1)[0]
            assert slope == pytest.approx(0.5, rel=0.1)
            assert stamps[25] - stamps[24] > 0.5
    finally:
        executor.shutdown()
        listener.destroy_node()


def test_single_instance_from_parameters_and_bad_parameters(ros_domain_id, tmp_path):
    node = start(
        "node", ros_domain_id, tmp_path / "one.log", shape="sphere", material="sand",
        friction_angle=0.5, instance_seed=9, real_time_factor=0,  # an int where a float is declared: taken
    )
    assert node.wait(120) == 0, (tmp_path / "one.log").read_text()
    log = (tmp_path / "one.log").read_text()
    assert "episode 0: custom-sphere-sand-0000 (sphere, sand: youngs_modulus=1e+05, poissons_ratio=0.3, friction_angle=0.5)" in log
    assert "published 1 episode(s), 76 messages" in log
    node = start("node", ros_domain_id, tmp_path / "bad.log", instances=str(tmp_path / "missing.yaml"))
    assert node.wait(60) == 2
    assert "missing.yaml" in (tmp_path / "bad.log").read_text()
    node = start("node", ros_domain_id, tmp_path / "bad2.log", shape="sphere", material="jelly", youngs_modulus=1.0)
    assert node.wait(60) == 2
    assert "youngs_modulus" in (tmp_path / "bad2.log").read_text()


@pytest.mark.parametrize("executable, params, expected", [
    ("node", {"seed": 1.5}, "Trying to set parameter 'seed' to '1.5' of type 'DOUBLE', expecting type 'INTEGER'"),
    ("node", {"views": -1}, "views must be in 0..16 (0: the instances' own), got -1"),
    # no upper bound: 100000000 views were taken and the node ran out of memory making its publishers
    ("node", {"views": 100000000}, "views must be in 0..16 (0: the instances' own), got 100000000"),
    ("node", {"real_time_factor": -1.0}, "real_time_factor must be a finite number >= 0 (0 = as fast as possible), got -1.0"),
    ("node", {"batch": 0}, "batch must be >= 1, got 0"),
    ("node", {"qos_depth": 2**31}, "qos_depth must be <= 2147483647, got 2147483648"),
    ("node", {"qos_depth": -3}, "qos_depth must be >= 1, got -3"),
    ("node", {"ack_timeout": 0.0}, "ack_timeout must be > 0 (seconds), got 0.0"),
    ("node", {"loop_memory_mb": -1}, "loop_memory_mb must be >= 0, got -1"),
    ("node", {"real_time_factor": "abc"}, "real_time_factor must be a number, got 'abc'"),
    ("node", {"shape": "sphere", "youngs_modulus": "abc"}, "youngs_modulus must be a number, got 'abc'"),
    ("node", {"topic_prefix": "1bad"}, "Invalid topic name: topic name token must not start with a number: '1bad/instance'"),
    # frame ids without a name, with a leading '/' (tf2 refuses both) or with blanks were published as given
    *(("node", {"frame_id": value}, "frame_id must be parts of letters, digits and '_' joined by single '/', e.g. "
       f"ad_sim or robot1/ad_sim (no blanks, no '/' at either end: it prefixes <frame_id>/world), got {shown}")
      for value, shown in (("''", "''"), ("' '", "' '"), ("/ad_sim", "'/ad_sim'"), ("ad_sim/", "'ad_sim/'"),
                           ("'ad sim'", "'ad sim'"))),
    ("record", {"flush_period": 0}, "flush_period must be a positive number of seconds, got 0.0"),
    ("record", {"topics": "/ad_sim/view_0/mask"}, "expecting type 'STRING_ARRAY'"),
    ("record", {"output": "/proc/nope/bag"}, "cannot write the bag: [Errno 2] No such file or directory: '/proc/nope'"),
])
def test_bad_parameter_values_are_one_line(executable, params, expected, ros_domain_id, tmp_path):
    """Wrong types, out-of-range values and unusable paths: exit 2 and one line naming the parameter,
    before anything is published or written."""
    process = start(executable, ros_domain_id, tmp_path / "bad.log", **params)
    assert process.wait(60) == 2
    log = (tmp_path / "bad.log").read_text()
    assert log.splitlines() == [f"ad_sim {executable}: " + log.split(": ", 1)[1].rstrip()] and expected in log, log


def test_an_instance_file_with_too_many_views_is_one_line_at_start(ros_domain_id, tmp_path):
    """An instance file's `views: 100000000` loaded, and the node ran out of memory making its cameras' publishers."""
    path = tmp_path / "views.yaml"
    path.write_text(yaml.safe_dump([dict(INSTANCES[0], views=100000000)]))
    process = start("node", ros_domain_id, tmp_path / "bad.log", instances=str(path), real_time_factor=0)
    assert process.wait(60) == 2
    log = (tmp_path / "bad.log").read_text()
    assert log.splitlines()[-1] == (f"ad_sim node: {path}: entry 0 ('sphere'): field 'views': expected an integer in "
                                    "[1, 16], got 100000000"), log


def a_listener(rclpy_context, views: int = 1):
    """A node subscribed (reliable, volatile) to every simulator topic of `views` cameras: (node, executor,
    received (topic, message) pairs)."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from ad_sim import messages
    from ad_sim.dds import message_class

    listener = Node("listener", context=rclpy_context)
    received = []
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    for topic, type_name in messages.topic_types(views).items():
        listener.create_subscription(message_class(type_name), topic, lambda m, t=topic: received.append((t, m)), qos)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(listener)
    return listener, executor, received


def test_a_late_subscriber_gets_the_ground_truth_of_the_episode_now_playing_only(rclpy_context, ros_domain_id, tmp_path):
    """SPEC 5: /ad_sim/instance is transient local, the ground truth of the episode now playing. Its writer kept
    qos_depth (100) messages, so a subscriber (a recorder) joining at episode k got the ground truth of episodes
    0..k-1 as well: episodes without frames at the start of its recording."""
    from ad_msgs.msg import SimInstance
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    node = start("node", ros_domain_id, tmp_path / "node.log", instances=str(instance_file), real_time_factor=1.0, loop=True)
    wait_for_log(tmp_path / "node.log", r"episode 2:", node, timeout=120)
    late = Node("late", context=rclpy_context)
    indices = []
    late.create_subscription(SimInstance, "/ad_sim/instance", lambda m: indices.append(m.episode_index), QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(late)
    try:
        deadline = time.monotonic() + 60
        while not indices:  # the latched one, at once
            assert time.monotonic() < deadline, (tmp_path / "node.log").read_text()
            executor.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 1.0  # and any backlog behind it
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        late.destroy_node()
    assert stop(node, signal.SIGINT) == 0
    # "episode 2:" is logged before its first frame's wait, when the latched ground truth may still be episode 1's
    # (the one whose frames just ended); the bug gave all of them: [0, 1, 2, ...].
    assert indices and min(indices) >= 1, indices


def test_a_stop_between_episodes_publishes_nothing_ahead_of_its_time(rclpy_context, ros_domain_id, tmp_path):
    """A SIGINT while the node waits for the next episode's wall time ended the wait and published that
    episode's ground truth at once, 0.9 s early and alone: an empty episode at the end of a recording, and
    the log said the episode was cut short."""
    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    listener, executor, received = a_listener(rclpy_context)
    try:
        # real_time_factor 0.25: the gap before episode 1 lasts 3.6 s of wall time (0.9 s at 1.0), so that a busy
        # machine's delay in delivering episode 0 to this listener and in seeing it cannot push the stop past it.
        node = start("node", ros_domain_id, tmp_path / "node.log", instances=str(instance_file), real_time_factor=0.25,
                     batch=2, wait_for_subscribers=1)  # both episodes simulated before the first is played
        deadline = time.monotonic() + 120
        while sum(topic.endswith("particles") for topic, _ in received) < 25:  # episode 0 played whole
            assert time.monotonic() < deadline, (tmp_path / "node.log").read_text()
            executor.spin_once(timeout_sec=0.01)
        assert stop(node, signal.SIGINT) == 0  # within the gap before episode 1
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        listener.destroy_node()
    log = (tmp_path / "node.log").read_text()
    assert [m.episode_index for t, m in received if t.endswith("instance")] == [0], log
    assert len(received) == 76 and "published 1 episode(s), 76 messages" in log, log  # not "cut short"


FAILING_SIMULATION = """
import sys
import ad_sim.episode

real, calls = ad_sim.episode.simulate_batch, []

def simulate_batch(*args, **kwargs):
    calls.append(1)
    if len(calls) > 1:
        raise RuntimeError("injected failure")
    return real(*args, **kwargs)

ad_sim.episode.simulate_batch = simulate_batch
from ad_sim.sim_node import main
main(sys.argv)
"""


def test_a_simulation_failure_plays_what_was_simulated_then_exits_1(ros_domain_id, tmp_path):
    """The second batch fails: the first batch's episode is played whole, then the node exits with status 1. The
    failure used to stop playback at once: the episode playing was cut short and the queued ones dropped."""
    import os
    import sys

    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    log = tmp_path / "node.log"
    args = [sys.executable, "-c", FAILING_SIMULATION, "--ros-args", "-p", f"instances:={instance_file}",
            "-p", "real_time_factor:=0.0", "-p", "batch:=1"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    with log.open("w") as out:
        assert subprocess.run(args, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT, timeout=240).returncode == 1
    text = log.read_text()
    assert "simulation failed: RuntimeError: injected failure" in text and "Traceback" not in text, text
    assert "published 1 episode(s), 76 messages" in text, text


COUNTING_SIMULATION = """
import os
import sys
import ad_sim.episode
import ad_sim.sim_node

real = ad_sim.episode.simulate_batch

def simulate_batch(instances, *args, **kwargs):
    for instance in instances:
        # One write per line: print writes the newline apart, and a log line from another thread came between.
        os.write(1, f"simulating {instance.episode_id}\\n".encode())
    return real(instances, *args, **kwargs)

ad_sim.episode.simulate_batch = simulate_batch
"""


@pytest.mark.parametrize("loop_memory_mb", [None, 1, 0])
def test_a_looping_node_replays_its_episodes_instead_of_simulating_them_again(rclpy_context, ros_domain_id, tmp_path,
                                                                               loop_memory_mb):
    """Every pass simulated every episode again (a pause of seconds between passes on CPU). Now the first pass's
    episodes are replayed, the same messages with the stamps and indices of their place in the stream; a pass
    over loop_memory_mb (1 MiB here: an episode of 1 view takes 1.6 MB; 0: never kept) is simulated again, as
    before."""
    import os
    import sys

    from ad_sim import messages

    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    args = [sys.executable, "-c", COUNTING_SIMULATION + "ad_sim.sim_node.main(sys.argv)\n", "--ros-args",
            "-p", f"instances:={instance_file}", "-p", "real_time_factor:=0.0", "-p", "batch:=1", "-p", "loop:=true",
            "-p", "wait_for_subscribers:=1"]
    args += [] if loop_memory_mb is None else ["-p", f"loop_memory_mb:={loop_memory_mb}"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    log = tmp_path / "node.log"
    listener, executor, received = a_listener(rclpy_context)
    node = subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT)
    try:
        deadline = time.monotonic() + 180
        while sum(topic.endswith("particles") for topic, _ in received) < 4 * 25:  # two passes played whole
            assert time.monotonic() < deadline and node.poll() is None, log.read_text()
            executor.spin_once(timeout_sec=0.01)
        assert stop(node, signal.SIGINT) == 0
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
        executor.shutdown()
        listener.destroy_node()
    text = log.read_text()
    simulated = re.findall(r"^simulating (\S+)$", text, re.M)
    ids = ["custom-sphere-jelly-0000", "custom-sphere-jelly-0001"]
    if loop_memory_mb is None:
        assert simulated == ids and "loop: the later passes replay the 2 episode(s) simulated" in text, text
    else:
        assert simulated[:4] == ids + ids and "each pass simulates them again" in text, text
    grounds = [m for topic, m in received if topic.endswith("instance")][:4]
    assert [(m.episode_id, m.episode_index) for m in grounds] == list(zip(ids + ids, range(4)))
    for topic in messages.topic_types(1):
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for t, m in received if t == topic]
        assert stamps == sorted(set(stamps)), topic  # increasing across the passes
    frames = {(t, m.header.stamp.sec * 10**9 + m.header.stamp.nanosec): bytes(m.data) for t, m in received
              if t.endswith(("mask", "particles"))}
    for topic in (messages.mask_topic(0), messages.particles_topic()):
        for first, again in ((0, 2), (1, 3)):  # the second pass plays the first's frames at its own stamps
            assert all(frames[topic, messages.frame_stamp(again, f)] == frames[topic, messages.frame_stamp(first, f)]
                       for f in range(25)), (topic, first)


def test_a_device_this_machine_lacks_is_refused_at_start(ros_domain_id, tmp_path):
    """Before anything is published (it failed when the first batch simulated, exit 1); Warp's own
    start-up lines may come first."""
    process = start("node", ros_domain_id, tmp_path / "bad.log", device="bogus", real_time_factor=0)
    assert process.wait(60) == 2
    log = (tmp_path / "bad.log").read_text()
    assert log.splitlines()[-1].startswith("ad_sim node: Warp device 'bogus' is not available; this machine has: "), log
    assert "episode 0" not in log and "Traceback" not in log


@pytest.mark.parametrize("executable", ["node", "record"])
def test_ctrl_c_while_starting_exits_quietly_as_any_ctrl_c(executable, ros_domain_id, tmp_path):
    """A Ctrl-C during the executable's imports (most of its first second, before it handles signals) printed
    Python's KeyboardInterrupt traceback, and the process died of the signal. Wherever it lands before the node is
    up, the node now exits with status 0 as after any Ctrl-C, with one line if it came during the imports."""
    during_imports = 0
    for attempt, delay in enumerate((0.0, 0.0, 0.05, 0.15, 0.3, 0.6, 1.0, 2.0)):
        args = [str(ADRUN), "ad_sim", executable, "--ros-args"]
        args += ["-p", f"output:={tmp_path / f'bag{attempt}'}"] if executable == "record" else []
        status, lines = interrupt_while_starting(args, tmp_path / f"{attempt}.log", delay)
        text = "\n".join(lines)
        assert status == 0 and "Traceback" not in text and "KeyboardInterrupt" not in text, (delay, text)
        during_imports += lines == [f"ad_sim {executable}: interrupted while starting"]
    assert during_imports, "no Ctrl-C landed during the imports"


def test_ctrl_c_does_not_wait_for_a_recorder_that_died(rclpy_context, ros_domain_id, tmp_path):
    """A subscriber killed while the node waits for its acknowledgements: SIGINT still ends the node
    within about a second, not after ACK_TIMEOUT (10 s) per topic."""
    # Two quick episodes, both simulated in the first batch and replayed by the later passes: the node never stops
    # to simulate, so wherever the kill lands it soon waits on the dead recorder (the ground truth's depth 1 makes
    # each episode's first message wait for the one before). With the benchmark's batches of 4 it played episodes 1
    # to 3 within ~80 ms of "episode 1:"; a kill that came later found it simulating the next batch for seconds, and
    # SIGINT ended that wait with no episode cut short. qos_depth 999 (no multiple of an episode's 25 frames) keeps
    # the flow-control waits off an episode's last message, after which the episode would count as played whole.
    soft = {"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}}
    instance_file = tmp_path / "soft.yaml"
    instance_file.write_text(yaml.safe_dump([dict(soft, seed=3), dict(soft, seed=4)]))
    recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(tmp_path / "bag"))
    node = start("node", ros_domain_id, tmp_path / "node.log", instances=str(instance_file), real_time_factor=0,
                 loop=True, wait_for_subscribers=1, qos_depth=999)
    wait_for_log(tmp_path / "node.log", r"episode 1:", node, timeout=120)
    recorder.send_signal(signal.SIGKILL)
    recorder.wait()
    time.sleep(1.0)  # the node now blocks on acknowledgements that will not come
    started = time.monotonic()
    assert stop(node, signal.SIGINT) == 0
    assert time.monotonic() - started < 5.0, (tmp_path / "node.log").read_text()  # was 10 s and more
    log = (tmp_path / "node.log").read_text()
    assert re.search(r"published (\d+) episode\(s\) \(episode \1 cut short by the stop\)", log), log


SHORT_LEASE_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="short_lease" is_default_profile="true"><rtps><builtin><discovery_config>
    <leaseDuration><sec>8</sec></leaseDuration><leaseAnnouncement><sec>1</sec></leaseAnnouncement>
  </discovery_config></builtin></rtps></participant>
</profiles>
"""


def test_a_dead_subscriber_stalls_playback_for_ack_timeout_not_for_its_lease(ros_domain_id, tmp_path, monkeypatch):
    """A recorder killed with SIGKILL stays matched until DDS drops it at its lease (8 s here, 20 s by
    default). The node gives up waiting for it after ack_timeout (1 s here), warns, and plays on without
    waiting until every topic is acknowledged again (the recorder dropped). It used to wait 10 s per topic,
    so playback stood still until the lease ended. qos_depth 10 fills the window within an episode."""
    profile = tmp_path / "short_lease.xml"
    profile.write_text(SHORT_LEASE_PROFILE)
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))  # the recorder's lease only
    recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(tmp_path / "bag"))
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE")
    node = start("node", ros_domain_id, tmp_path / "node.log", real_time_factor=0, loop=True, wait_for_subscribers=1,
                 ack_timeout=1.0, qos_depth=10, shape="sphere", youngs_modulus=5.0e4, poissons_ratio=0.3)
    wait_for_log(tmp_path / "node.log", r"episode 1:", node, timeout=120)
    recorder.send_signal(signal.SIGKILL)
    recorder.wait()
    warned = wait_for_log(tmp_path / "node.log", r"did not acknowledge within 1 s \(did one die or stall\?\)", node)
    again = wait_for_log(tmp_path / "node.log", r"every topic's subscribers acknowledge again", node, timeout=60)
    assert warned.start() < again.start()
    wait_for_log(tmp_path / "node.log", r"acknowledge again.*\n(?:.*\n)*?.*episode \d+:", node)  # and plays on
    assert stop(node, signal.SIGINT) == 0


def test_a_mistyped_parameter_is_warned_about_not_silently_ignored(ros_domain_id, tmp_path):
    """rclpy drops values for undeclared parameters: `flush_perod:=0.2` left the default without a word."""
    recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(tmp_path / "bag"), flush_perod=0.2)
    wait_for_log(tmp_path / "record.log", r"ignoring parameter 'flush_perod': this node has none of that name "
                                          r"\(did you mean flush_period\? --help lists them\)", recorder)
    assert stop(recorder, signal.SIGINT) == 0
    assert "use_sim_time" not in (tmp_path / "record.log").read_text()  # rclpy's own parameters are known


def test_help_lists_the_parameters():
    for executable, parameters in (("node", ("instances", "real_time_factor", "views", "wait_for_subscribers", "ack_timeout", "loop_memory_mb")), ("record", ("output", "topics", "max_bag_size"))):
        result = subprocess.run([str(ADRUN), "ad_sim", executable, "--help"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        assert f"ros2 run ad_sim {executable}" in result.stdout
        for name in parameters:
            assert re.search(rf"^  {name} +\S+  \S", result.stdout, re.M), result.stdout  # name, default, meaning


def test_unknown_arguments_are_a_usage_error():
    """Outside --ros-args, a mistyped option must not start a node that ignores it."""
    for executable in ("node", "record"):
        result = subprocess.run([str(ADRUN), "ad_sim", executable, "--bogus", "--ros-args", "-p", "output:=x"],
                                cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, result.stderr
        assert "unrecognized arguments: --bogus" in result.stderr
        assert "output:=x" not in result.stderr  # ROS arguments are the node's, not argparse's


def test_a_ctrl_c_python_swallows_during_the_imports_still_stops_the_start():
    """A CI run saw `ad_sim record` run on for 60 s after a Ctrl-C during its imports: the KeyboardInterrupt was
    raised in importlib's module-lock weakref callback, where Python prints "Exception ignored in ..." and goes on.
    quiet_interrupt remembers the signal, and the start stops when the imports end, as for any Ctrl-C there."""
    import os
    import signal

    from ad_sim.dds import StartInterrupted, quiet_interrupt

    class SignalledWhileDeleted:
        def __del__(self):  # a KeyboardInterrupt raised in here is printed and swallowed
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(10_000))  # Python runs the handler here, between bytecodes

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(StartInterrupted), quiet_interrupt("prog"):
        SignalledWhileDeleted()
    assert signal.getsignal(signal.SIGINT) is before
