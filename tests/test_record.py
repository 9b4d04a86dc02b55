"""`ros2 run ad_sim record` over real DDS: counts, content, QoS, SIGINT/SIGTERM and kill -9.

An in-process rclpy publisher plays fabricated episodes (ad_sim.messages -> rclpy messages,
as the simulator node does) with the node's QoS and ack-based flow control; the recorder runs
as a subprocess, as `ros2 run` starts it.
"""

from __future__ import annotations

import signal
import time
import warnings

import pytest
from mcap.reader import make_reader
from ros_procs import kill_leftovers, recorder_counts, start, stop, wait_for_log
from sim_fixtures import as_plain, fabricated_episode

from ad_sim import messages
from ad_sim.rosbag import BagError, BagReader

pytestmark = pytest.mark.ros


@pytest.fixture(autouse=True)
def no_leftover_processes():
    yield
    kill_leftovers()
EPISODES = 2


class Publisher:
    """The simulator node's publishers (flow control included), driven by the test."""

    def __init__(self, context, views: int = 1):
        from rclpy.node import Node

        from ad_sim.sim_node import SimPublishers

        self.node = Node("fake_sim", context=context)
        self.sim = SimPublishers(self.node, views)

    def wait_for_subscribers(self, count: int = 1, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not self.sim.matched(count):
            assert time.monotonic() < deadline, "the recorder did not subscribe to every topic"
            time.sleep(0.05)

    def publish(self, items) -> int:
        for topic, _, data in items:
            self.sim.publish(topic, data)
        return len(items)

    def close(self) -> None:
        self.node.destroy_node()


def episode_items(first: int = 0, count: int = EPISODES):
    return [item for i in range(first, first + count) for item in messages.episode_messages(fabricated_episode(i), i)]


def test_recorder_records_everything_and_finalises_on_sigint(rclpy_context, ros_domain_id, tmp_path):
    items = episode_items()
    publisher = Publisher(rclpy_context)
    try:
        # The ground truth is published before the recorder starts: transient local delivers it late.
        published = publisher.publish(items[:1])
        bag = tmp_path / "rec"
        recorder = start("record", ros_domain_id, tmp_path / "record.log", output=str(bag))
        publisher.wait_for_subscribers()
        published += publisher.publish(items[1:])
        publisher.sim.wait_for_acks()
        time.sleep(0.3)
        assert stop(recorder, signal.SIGINT) == 0
    finally:
        publisher.close()
    log = (tmp_path / "record.log").read_text()
    assert "Traceback" not in log
    assert recorder_counts(log) == (published, published) == (len(items), len(items))
    read = list(BagReader(bag))
    # Log time is the header stamp, so the bag is in simulated-time order whatever the arrival order.
    assert sorted((t, s) for t, s, _ in read) == sorted((t, s) for t, s, _ in items)
    by_key = {(t, s): as_plain(m) for t, s, m in read}
    for topic, stamp, data in items:
        assert by_key[(topic, stamp)] == as_plain(data), (topic, stamp)
    # Offered QoS recorded from the discovered publishers; receive wall time kept as publish time.
    with open(next(bag.glob("*.mcap")), "rb") as f:
        reader = make_reader(f)
        channels = {c.topic: c for c in reader.get_summary().channels.values()}
        assert "transient_local" in channels["/ad_sim/instance"].metadata["offered_qos_profiles"]
        assert "volatile" in channels["/ad_sim/particles"].metadata["offered_qos_profiles"]
        assert all(m.publish_time > 1.6e18 and m.log_time < 1e10 for _, _, m in reader.iter_messages())


def flushed(bag) -> int:
    """How many messages a recorder still writing `bag` has flushed (what a kill -9 now would leave readable)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # truncated, as a bag being written is
        try:
            return len(list(BagReader(bag, recover=True, raw=True)))
        except BagError:  # no chunk yet
            return 0


def test_sigterm_finalises_and_kill9_keeps_flushed_chunks(rclpy_context, ros_domain_id, tmp_path):
    items = episode_items()
    publisher = Publisher(rclpy_context)
    try:
        terminated = start("record", ros_domain_id, tmp_path / "term.log", output=str(tmp_path / "term"), max_bag_size=1_000_000)
        killed = start("record", ros_domain_id, tmp_path / "kill.log", output=str(tmp_path / "kill"), flush_period=0.2)
        publisher.wait_for_subscribers(count=2)
        published = publisher.publish(items)
        publisher.sim.wait_for_acks()
        # Killed once everything received is in flushed chunks (flush_period 0.2 s), as read back the way a kill -9
        # leaves the bag: acknowledged is not yet written, and a fixed second assumed a recorder that keeps up.
        deadline = time.monotonic() + 60
        while flushed(tmp_path / "kill") < published:
            assert time.monotonic() < deadline, (tmp_path / "kill.log").read_text()
            time.sleep(0.1)
        killed.send_signal(signal.SIGKILL)
        killed.wait(10)
        assert stop(terminated, signal.SIGTERM) == 0
    finally:
        publisher.close()
    log = (tmp_path / "term.log").read_text()
    assert "Traceback" not in log and recorder_counts(log) == (published, published)
    assert len(list(BagReader(tmp_path / "term"))) == published  # finalised: reads without recover
    assert len(list((tmp_path / "term").glob("*.mcap"))) >= 2  # split by max_bag_size
    with pytest.raises(BagError, match="truncated"):
        list(BagReader(tmp_path / "kill"))
    with pytest.warns(UserWarning, match="truncated"):
        recovered = list(BagReader(tmp_path / "kill", recover=True))
    assert sorted((t, s) for t, s, _ in recovered) == sorted((t, s) for t, s, _ in items)


SLOW_RECORDER = """
import sys, time
import ad_sim.rosbag

write, flush = ad_sim.rosbag.BagWriter.write, ad_sim.rosbag.BagWriter.flush

def slow_write(self, *args, **kwargs):  # a recorder behind the publisher, as on a busy machine
    time.sleep(0.01)
    return write(self, *args, **kwargs)

def slow_flush(self):  # and a chunk flush that outlasts the drain's DRAIN_IDLE (0.3 s)
    time.sleep(0.5)
    return flush(self)

ad_sim.rosbag.BagWriter.write, ad_sim.rosbag.BagWriter.flush = slow_write, slow_flush
from ad_sim.record_node import main
main(sys.argv)
"""


def test_a_slow_flush_in_the_drain_loses_no_acknowledged_message(rclpy_context, ros_domain_id, tmp_path):
    """SIGINT while the recorder is behind (every message acknowledged, many not yet taken): a flush that took
    longer than DRAIN_IDLE during the drain counted as quiet input, and the bag was closed without the messages
    still waiting in the subscriptions (here 21 to 36 of the 76, in 4 runs of 4)."""
    import os
    import subprocess
    import sys

    from ros_procs import REPO_ROOT

    items = episode_items(count=1)  # 76 messages, 0.76 s behind: within DRAIN_MAX (2 s)
    publisher = Publisher(rclpy_context)
    log = tmp_path / "record.log"
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    recorder = subprocess.Popen([sys.executable, "-c", SLOW_RECORDER, "--ros-args", "-p", f"output:={tmp_path / 'bag'}",
                                 "-p", "flush_period:=0.2"], stdout=log.open("w"), stderr=subprocess.STDOUT, env=env,
                                cwd=REPO_ROOT)
    try:
        publisher.wait_for_subscribers()
        published = publisher.publish(items)
        publisher.sim.wait_for_acks()
        assert stop(recorder, signal.SIGINT) == 0
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait()
        publisher.close()
    assert recorder_counts(log.read_text()) == (published, published), log.read_text()
    assert len(list(BagReader(tmp_path / "bag"))) == published


def test_recorder_records_only_the_topics_asked_for(rclpy_context, ros_domain_id, tmp_path):
    """An explicit topic list, including a foreign type without header (log time = receive time)."""
    from std_msgs.msg import String

    items = episode_items(count=1)
    publisher = Publisher(rclpy_context)
    chatter = publisher.node.create_publisher(String, "/chatter", 10)
    try:
        topics = ["/ad_sim/instance", "/ad_sim/particles", "/chatter"]
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output=str(tmp_path / "some"), topics=topics)
        for topic in topics:
            wait_for_log(tmp_path / "r.log", rf"subscribed to {topic} ", recorder)
        deadline = time.monotonic() + 30
        while chatter.get_subscription_count() < 1 or any(publisher.sim.by_topic[topic][1].get_subscription_count() < 1
                                                          for topic in topics[:2]):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        before = time.time_ns()
        publisher.publish(items)
        chatter.publish(String(data="hello"))
        publisher.sim.wait_for_acks(["/ad_sim/instance", "/ad_sim/particles"])
        assert chatter.wait_for_all_acked()
        time.sleep(0.3)
        assert stop(recorder) == 0
    finally:
        publisher.close()
    reader = BagReader(tmp_path / "some")
    assert reader.topics() == {
        "/ad_sim/instance": messages.INSTANCE_TYPE, "/ad_sim/particles": messages.POINT_CLOUD_TYPE, "/chatter": "std_msgs/msg/String",
    }
    read = list(reader)
    assert len(read) == 1 + 25 + 1
    hello = [m for m in read if m.topic == "/chatter"]
    assert hello[0].message.data == "hello" and hello[0].log_time_ns >= before


def test_a_stop_is_not_held_off_by_a_topic_that_keeps_publishing(rclpy_context, ros_domain_id, tmp_path):
    """SIGINT while /chatter keeps arriving every 20 ms: the recorder drains for at most DRAIN_MAX and
    closes a readable bag (it waited for 0.3 s of silence, so it ran as long as the publisher did)."""
    from std_msgs.msg import String

    from ad_sim.record_node import DRAIN_MAX

    node = Publisher(rclpy_context).node
    chatter = node.create_publisher(String, "/chatter", 10)
    try:
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output=str(tmp_path / "bag"), topics=["/chatter"])
        wait_for_log(tmp_path / "r.log", r"subscribed to /chatter ", recorder)
        for _ in range(50):
            chatter.publish(String(data="x"))
            time.sleep(0.02)
        recorder.send_signal(signal.SIGINT)
        sent = time.monotonic()
        while recorder.poll() is None and time.monotonic() - sent < DRAIN_MAX + 20:
            chatter.publish(String(data="x"))
            time.sleep(0.02)
        waited = time.monotonic() - sent
        assert recorder.poll() == 0, (tmp_path / "r.log").read_text()
        assert waited < DRAIN_MAX + 10  # generous for a loaded machine; before, it never stopped while fed
    finally:
        node.destroy_node()
    assert len(list(BagReader(tmp_path / "bag"))) >= 50


def test_a_header_stamp_that_cannot_be_a_log_time_is_recorded_at_its_receive_time(rclpy_context, ros_domain_id,
                                                                                  tmp_path):
    """Stamps 5, 6, -1 and 7 s, one with nanosec 1e9 (MCAP log times are unsigned, and 1e9 ns is no nanosecond
    part) and raw bytes too short for a header: the unusable ones are recorded at their receive time, with one
    warning for the topic, and the recorder exits 0 leaving a whole bag (the negative stamp crashed it, leaving a
    42-byte .mcap)."""
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    node = Node("stamps", context=rclpy_context)
    camera = node.create_publisher(Image, "/camera", 10)
    stamps = [(5, 0), (6, 0), (-1, 0), (7, 0), (8, 1_000_000_000)]
    try:
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output=str(tmp_path / "bag"), topics=["/camera"])
        wait_for_log(tmp_path / "r.log", r"subscribed to /camera ", recorder)
        deadline = time.monotonic() + 30
        while camera.get_subscription_count() < 1:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        before = time.time_ns()
        for sec, nanosec in stamps:
            message = Image(encoding="mono8")
            message.header.stamp.sec, message.header.stamp.nanosec = sec, nanosec
            camera.publish(message)
        camera.publish(b"\x00\x01\x00\x00")  # a CDR encapsulation header alone, published raw as replay does
        assert camera.wait_for_all_acked()
        time.sleep(0.3)
        assert stop(recorder) == 0, (tmp_path / "r.log").read_text()
        after = time.time_ns()  # acknowledged is not yet received by the recorder's callback
    finally:
        node.destroy_node()
    log = (tmp_path / "r.log").read_text()
    assert "Traceback" not in log and recorder_counts(log) == (6, 6), log
    warnings = [line for line in log.splitlines() if "receive time" in line]
    assert len(warnings) == 1 and "/camera: header stamp -1 s 0 ns cannot be a log time" in warnings[0], log
    read = list(BagReader(tmp_path / "bag", raw=True))  # finalised: reads without recover
    assert [m.log_time_ns for m in read[:3]] == [5 * 10**9, 6 * 10**9, 7 * 10**9]
    assert all(before <= m.log_time_ns <= after for m in read[3:]) and len(read) == 6
    assert bytes(read[-1].message) == b"\x00\x01\x00\x00"


def test_a_bag_that_cannot_be_written_on_stops_the_recording_and_keeps_what_was_written(rclpy_context, ros_domain_id,
                                                                                        tmp_path):
    """The recorder's files may not grow past 1 MB (RLIMIT_FSIZE: a write past it fails with EFBIG, as one on a full
    disk does with ENOSPC). The recorder logged each message it could not write, naming no file, counted as written
    those of the chunk that failed, and went on writing after the half-written chunk until a failed flush ended it
    with a traceback-less "cannot write the bag: [Errno 27] File too large" and exit status 2, its counts never
    logged. Now it stops at the first failed write with exit status 1 and an error naming the file, and the bag
    holds, readable with --recover, exactly the messages it says it wrote."""
    import resource
    import subprocess

    items = episode_items(count=3)  # about 2 MB, under the flow control window: publishing never waits
    publisher = Publisher(rclpy_context)
    bag = tmp_path / "bag"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, hard))  # for the recorder: the limit is inherited
    try:
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output=str(bag), flush_period=0.2)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    try:
        publisher.wait_for_subscribers()
        publisher.publish(items)
        try:
            status = recorder.wait(60)
        except subprocess.TimeoutExpired:  # it recorded on
            status = stop(recorder)
    finally:
        publisher.close()
    log = (tmp_path / "r.log").read_text()
    assert status == 1 and "Traceback" not in log, log
    assert f"recording stopped: cannot write {bag / 'bag_0.mcap'}: File too large. Writing stopped" in log, log
    received, written = recorder_counts(log)
    assert 0 < written < received <= len(items), log
    with pytest.warns(UserWarning, match="truncated"):
        recovered = list(BagReader(bag, recover=True, raw=True))
    assert len(recovered) == written


def test_topic_names_and_the_output_folder_are_resolved_as_ros_and_a_shell_would(rclpy_context, ros_domain_id,
                                                                                 tmp_path, monkeypatch):
    """`-p topics:="['chatter']"` (a name relative to the root namespace, as `ros2 topic pub chatter` takes it) and
    `-p output:=~/rec`: discovery lists /chatter, which never equalled "chatter", so nothing was recorded, without a
    word, into a folder literally named "~" under the working directory. Now the names are resolved as ROS
    resolves them (an invalid one is an error before anything is written) and ~ is the home folder."""
    from rclpy.node import Node
    from std_msgs.msg import String

    monkeypatch.setenv("HOME", str(tmp_path))  # start() passes the environment on
    node = Node("chatter", context=rclpy_context)
    chatter = node.create_publisher(String, "/chatter", 10)
    try:
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output="~/rec", topics=["chatter"])
        deadline = time.monotonic() + 30
        while chatter.get_subscription_count() < 1:
            assert time.monotonic() < deadline and recorder.poll() is None, (tmp_path / "r.log").read_text()
            time.sleep(0.05)
        chatter.publish(String(data="hello"))
        assert chatter.wait_for_all_acked()
        time.sleep(0.3)
        assert stop(recorder) == 0
    finally:
        node.destroy_node()
    assert [m.message.data for m in BagReader(tmp_path / "rec")] == ["hello"]
    bad = start("record", ros_domain_id, tmp_path / "bad.log", output=str(tmp_path / "bad"), topics=["/chatter/"])
    assert bad.wait(60) == 2
    assert "topics: '/chatter/' is not a topic name" in (tmp_path / "bad.log").read_text()
    assert not (tmp_path / "bad").exists()


def test_a_second_simulator_run_into_one_recording_is_warned_about(rclpy_context, ros_domain_id, tmp_path):
    """Each simulator run stamps its episodes from 0 s: a second run into a running recorder gave a bag whose two
    runs share stamps (training then mixed their frames), without a word at recording time."""
    from ad_msgs.msg import SimInstance
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    node = Node("runs", context=rclpy_context)
    truth = node.create_publisher(SimInstance, "/ad_sim/instance", QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    try:
        recorder = start("record", ros_domain_id, tmp_path / "r.log", output=str(tmp_path / "bag"))
        wait_for_log(tmp_path / "r.log", r"subscribed to /ad_sim/instance ", recorder)
        deadline = time.monotonic() + 30  # this side matched too: wait_for_all_acked waits on no one before
        while truth.get_subscription_count() < 1:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        for sec in (0, 1, 0, 1):  # episodes 0 and 1 of one run, then of another
            message = SimInstance(episode_id=f"e{sec}")
            message.header.stamp.sec = sec
            truth.publish(message)
            assert truth.wait_for_all_acked()
        time.sleep(0.3)
        assert stop(recorder) == 0, (tmp_path / "r.log").read_text()
    finally:
        node.destroy_node()
    log = (tmp_path / "r.log").read_text()
    warnings = [line for line in log.splitlines() if "a new simulator run?" in line]
    assert len(warnings) == 1 and "an episode stamped 0.000 s, not after the one before (1.000 s)" in warnings[0], log
    assert recorder_counts(log) == (4, 4), log  # recorded all the same: the bag loses nothing


def test_a_signal_while_starting_leaves_no_bag(tmp_path, monkeypatch):
    """A Ctrl-C that lands while the recorder starts (here: inside rclpy.init) stops it before it makes its bag: it
    used to go on, create the output folder and an empty bag (with the default output, a new timestamped folder on
    every such Ctrl-C), then stop."""
    import os

    import rclpy

    from ad_sim import record_node

    init = rclpy.init

    def interrupted_init(*args, **kwargs):
        init(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)  # handled by the recorder's own handler, installed first

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    monkeypatch.setattr(rclpy, "init", interrupted_init)
    try:
        record_node.main(["record", "--ros-args", "-p", f"output:={tmp_path / 'out'}"])
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert not (tmp_path / "out").exists()
    assert not rclpy.ok()  # the context was shut down
