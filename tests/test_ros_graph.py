"""The nodes in a ROS graph as a robotics engineer wires them up: signals from a launch system, parameter
services, namespaces and remaps, over real DDS with the node in its own process where it matters."""
import signal
import subprocess
import sys
import threading

import pytest
from ad_msgs.msg import MaterialEstimate
from rcl_interfaces.srv import DescribeParameters
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from ad_estimator.parameters import MAX_QUEUE_SIZE, RANGES
from estimator_models import build_streaming_model, falling_masks
import ros_procs
from estimator_ros import image_msg, wait_for

pytestmark = pytest.mark.ros
DT = 25_000_000


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return build_streaming_model(tmp_path_factory.mktemp("graph_models"))


_started = []


@pytest.fixture(autouse=True)
def _kill_leftovers():
    yield
    while _started:
        proc = _started.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def run_node(*ros_args):
    """The estimator node's process; its output lines arrive in `proc.lines` (a reader thread: a test waiting for a
    line that never comes fails at its timeout instead of blocking in readline)."""
    proc = subprocess.Popen([sys.executable, "-m", "ad_estimator.node", "--ros-args", *ros_args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    proc.lines = []
    proc.reader = threading.Thread(target=lambda: proc.lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    proc.reader.start()
    _started.append(proc)
    return proc


def read_until(proc, text, timeout=60.0):
    assert wait_for(lambda: any(text in line for line in proc.lines) or proc.poll() is not None, timeout) and any(
        text in line for line in proc.lines), "".join(proc.lines)


def stop(proc, sig=signal.SIGINT) -> str:
    """Signal the node; its whole output once it exited."""
    ros_procs.stop(proc, sig)
    proc.reader.join(timeout=10)
    return "".join(proc.lines)


def camera_and_listener(ros, name: str, topic: str):
    """A client node on the test's executor: a reliable camera publishing on `topic`, and the estimates it gets."""
    context, executor = ros
    client = Node(name, context=context)
    estimates = []
    client.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append,
                               QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    publisher = client.create_publisher(Image, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    executor.add_node(client)
    return client, publisher, estimates


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_after_the_last_frame_loses_no_estimate(ros, model_path, sig):
    """A launch file that stops the estimator as its camera (or bag replay) ends sends SIGINT, then SIGTERM.
    rclpy's handlers shut the context down at once: frames still queued and the window's flush (the last,
    partial episode's estimate under the anytime policy) were lost. Now the node finishes its input first."""
    topic = "/graph_test/signal_mask"
    proc = run_node("-p", f"model_path:={model_path}", "-r", f"mask:={topic}", "-p", "reliable:=true",
                    "-p", "output_policy:=anytime", "-p", "min_frames:=15", "-p", "every_n:=100",
                    "-p", "idle_flush:=30.0")
    read_until(proc, "model test-streaming")
    client, publisher, estimates = camera_and_listener(ros, "graph_test_client", topic)
    assert wait_for(lambda: publisher.get_subscription_count() > 0 and client.count_publishers(
        "/ad_estimator/estimate") > 0, timeout=30), "".join(proc.lines)
    for k, mask in enumerate(falling_masks(count=20, seed=4)):  # an episode cut short: 20 of 25 frames
        publisher.publish(image_msg(mask, 10**9 + k * DT))
    assert wait_for(lambda: len(estimates) == 1, timeout=30), "".join(proc.lines)  # the one at 15 frames
    assert estimates[0].frames_used == 15
    assert publisher.wait_for_all_acked(Duration(seconds=10))  # every frame is in the node's process
    out = stop(proc, sig)
    assert proc.returncode == 0 and "Traceback" not in out, out
    # The flush at the end of the input: the episode's 20 frames, as the idle flush would have given them.
    assert wait_for(lambda: len(estimates) == 2, timeout=10), out
    assert estimates[1].frames_used == 20 and not estimates[1].complete
    assert "'published': 2" in out


def test_describe_parameters_gives_descriptions_ranges_and_why_they_are_read_only(ros, model_path):
    """`ros2 param describe` (describe_parameters) gave each parameter's description only: no range, and nothing
    saying why a set is refused."""
    from ad_estimator.node import EstimatorNode
    from estimator_ros import tracked
    from rclpy.parameter import Parameter

    context, executor = ros
    node = tracked(EstimatorNode(context=context, parameter_overrides=[Parameter("model_path", value=str(model_path)),
                                                                       Parameter("idle_flush", value=0)]))
    client_node = Node("graph_describe_client", context=context)
    executor.add_node(node)
    executor.add_node(client_node)
    client = client_node.create_client(DescribeParameters, "/ad_estimator/describe_parameters")
    assert client.wait_for_service(timeout_sec=10)
    names = ["queue_size", "threads", "idle_flush", "diagnostics_period", "model_path"]
    future = client.call_async(DescribeParameters.Request(names=names))
    assert wait_for(future.done)
    described = dict(zip(names, future.result().descriptors))
    queue_size = described["queue_size"]
    assert queue_size.description.startswith("frames waiting for the worker")
    assert [(r.from_value, r.to_value) for r in queue_size.integer_range] == [(1, MAX_QUEUE_SIZE)]
    assert [(r.from_value, r.to_value) for r in described["threads"].integer_range] == [RANGES["threads"]]
    assert [(r.from_value, r.to_value) for r in described["diagnostics_period"].floating_point_range] == [
        RANGES["diagnostics_period"]]
    assert [(r.from_value, r.to_value) for r in described["idle_flush"].floating_point_range] == [
        RANGES["idle_flush"]]  # given as a whole number (idle_flush:=0): still a range of seconds
    assert not described["model_path"].integer_range and not described["model_path"].floating_point_range
    assert all(d.read_only and "restart the node" in d.additional_constraints for d in described.values())


def test_a_late_joiner_asking_for_transient_local_estimates_is_told_the_topic_and_the_fix(ros, model_path):
    """A subscription to the estimates with transient-local durability (as for a latched topic) gets nothing. The
    node's warning (rclpy's default) named the topic `~/estimate`, as the code spells it, not the name it has in
    the graph (here in a namespace), and gave no fix."""
    from rclpy.qos import DurabilityPolicy

    proc = run_node("-p", f"model_path:={model_path}", "-r", "__ns:=/robot1")
    read_until(proc, "model test-streaming")
    context, executor = ros
    client = Node("graph_late_joiner", context=context)
    client.create_subscription(MaterialEstimate, "/robot1/ad_estimator/estimate", lambda msg: None,
                               QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor.add_node(client)
    read_until(proc, "QoS", timeout=30)
    out = stop(proc)
    assert proc.returncode == 0, out
    (warning,) = [line for line in out.splitlines() if "QoS" in line]
    assert "/robot1/ad_estimator/estimate" in warning and "(durability)" in warning, warning
    assert "subscribe volatile" in warning and "~/estimate service" in warning, warning


def test_frames_delivered_but_not_yet_taken_at_the_signal_are_estimated(ros, model_path):
    """A signal while frames sit in the subscription's DDS cache, delivered (acknowledged) but not yet taken by the
    executor (busy, or woken a moment later): finish() set the node closing at once, so on_image ignored each of
    them as the executor took them, and the last estimate was lost after all. Now finish() first takes what has
    arrived, until the input is quiet, as the recorder does before it closes its bag."""
    from ad_estimator.node import EstimatorNode, make_executor
    from estimator_ros import tracked
    from rclpy.parameter import Parameter

    context, _ = ros
    topic = "/graph_test/cached_mask"
    overrides = {"model_path": str(model_path), "reliable": True, "output_policy": "anytime", "min_frames": 15,
                 "every_n": 100, "idle_flush": 30.0, "input_depth": 100}
    node = tracked(EstimatorNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
                                 cli_args=["--ros-args", "-r", f"mask:={topic}"]))
    client, publisher, estimates = camera_and_listener(ros, "graph_cache_client", topic)
    assert wait_for(lambda: publisher.get_subscription_count() > 0 and node.publisher.get_subscription_count() > 0,
                    timeout=30)
    for k, mask in enumerate(falling_masks(count=20, seed=4)):  # the node's executor does not spin yet
        publisher.publish(image_msg(mask, 10**9 + k * DT))
    assert publisher.wait_for_all_acked(Duration(seconds=10))  # every frame is in the node's DDS cache
    own = make_executor(context)
    own.add_node(node)
    spinner = threading.Thread(target=own.spin, daemon=True)
    spinner.start()  # the executor wakes as the signal comes
    try:
        assert node.finish()
        counters = node.statistics()
        assert counters["received"] == 20 and counters["published"] == 2, counters
        assert wait_for(lambda: len(estimates) == 2, timeout=10)
        assert [e.frames_used for e in estimates] == [15, 20]
    finally:
        own.shutdown(timeout_sec=1.0)
        spinner.join(timeout=2.0)
