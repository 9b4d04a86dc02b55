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
from estimator_ros import image_msg, ros_context, wait_for

pytestmark = pytest.mark.ros
DT = 25_000_000


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return build_streaming_model(tmp_path_factory.mktemp("graph_models"))


@pytest.fixture
def ros(ros_domain_id):
    with ros_context(ros_domain_id) as (context, executor):
        yield context, executor


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
    proc.send_signal(sig)
    proc.wait(timeout=30)
    proc.reader.join(timeout=10)
    return "".join(proc.lines)


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
    context, executor = ros
    client = Node("graph_test_client", context=context)
    estimates = []
    client.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append,
                               QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    publisher = client.create_publisher(Image, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    executor.add_node(client)
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


def test_queue_size_has_a_sensible_bound(model_path, ros_domain_id):
    """queue_size could be anything up to 10**6 frames: a queue that only holds memory (a frame waits whole, up to
    max_image_pixels) and estimates minutes late. Past MAX_QUEUE_SIZE it is refused in one line at start."""
    proc = run_node("-p", f"model_path:={model_path}", "-p", f"queue_size:={MAX_QUEUE_SIZE + 1}")
    read_until(proc, "queue_size")
    proc.wait(timeout=30)
    proc.reader.join(timeout=10)
    out = "".join(proc.lines)
    assert proc.returncode == 1 and f"queue_size must be at most {MAX_QUEUE_SIZE}, got {MAX_QUEUE_SIZE + 1}" in out, out
    assert "Traceback" not in out
    assert MAX_QUEUE_SIZE <= 10_000


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
