"""The estimator node over real DDS (rclpy, in-process executor) with real onnxruntime models."""
import contextlib
import itertools
import re
import signal
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest
from ad_msgs.msg import MaterialEstimate
from ad_msgs.srv import EstimateMaterial
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.node import Node
from rclpy.parameter import Parameter
from rcl_interfaces.srv import SetParameters
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image
from std_srvs.srv import Trigger

from ad_estimator import estimate
from ad_estimator.images import array_to_mask
from ad_estimator.model import EstimatorModel
from ad_estimator.node import EstimatorNode, make_executor
from ad_estimator.parameters import DEFAULT_INPUT_TOPIC, PARAMETERS
from ad_estimator.window import FrameWindow, clip_output
from ad_sim.rosbag import BagReader
from estimator_models import build_clip_model, build_streaming_model, falling_masks
from estimator_ros import image_msg, ros_context, spin_until_shutdown, tracked, wait_for
from ros_procs import ADRUN, REPO_ROOT, interrupt_while_starting, kill_leftovers
from sim_fixtures import write_coverage_bag

pytestmark = pytest.mark.ros
DT = 25_000_000
TOPIC = "/estimator_test/mask"


@pytest.fixture(scope="module")
def model_paths(tmp_path_factory):
    d = tmp_path_factory.mktemp("node_models")
    return {"streaming": build_streaming_model(d), "clip": build_clip_model(d / "clip.onnx")}


def start(ros, model_path, remap=f"mask:={TOPIC}", node_executor=None, **params):
    """The node on the test's executor, or on `node_executor` (e.g. the node's own, make_executor())."""
    context, executor = ros
    # Tests publish bursts faster than real time; a busy CI machine can stall a burst for longer than
    # the default idle flush, which would emit an early estimate: tests of idle flushing set it.
    params = {"reliable": True, "input_depth": 100, "idle_flush": 30.0, **params}
    overrides = [Parameter("model_path", value=str(model_path))]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    node = tracked(EstimatorNode(context=context, parameter_overrides=overrides,
                                 cli_args=["--ros-args", "-r", remap]))
    client = Node("estimator_test_client", context=context)
    estimates = []
    client.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append, 10)
    publisher = client.create_publisher(Image, TOPIC, QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
    (node_executor or executor).add_node(node)
    executor.add_node(client)
    assert wait_for(lambda: publisher.get_subscription_count() > 0 and client.count_publishers(
        "/ad_estimator/estimate") > 0), "estimator did not come up"
    return types.SimpleNamespace(node=node, client=client, estimates=estimates, publisher=publisher,
                                 executor=executor)


def publish_episode(t, masks, t0, step=DT):
    for k, mask in enumerate(masks):
        t.publisher.publish(image_msg(mask, t0 + k * step))


def offline(model_path, masks, stamps, policy="episode", **kw):
    """The expected estimates: model + window run directly."""
    model = EstimatorModel.load(model_path)
    window = FrameWindow(0.025, 25, policy=policy, history=model.info.previous_frames, **kw)
    outputs = []
    for mask, stamp in zip(masks, stamps):
        outputs += window.add(stamp, mask, model.encode)
    return [(out, model.predict(out.features, out.valid)) for out in outputs]


def stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.mark.parametrize("kind", ["streaming", "clip"])
def test_one_estimate_per_episode_matches_offline(ros, model_paths, kind):
    t = start(ros, model_paths[kind])
    episodes = [falling_masks(seed=1), falling_masks(seed=2)]
    starts = [1_000_000_000, 2_500_000_000]
    for masks, t0 in zip(episodes, starts):
        publish_episode(t, masks, t0)
    assert wait_for(lambda: len(t.estimates) >= 2)
    time.sleep(0.3)
    assert len(t.estimates) == 2
    for msg, masks, t0 in zip(t.estimates, episodes, starts):
        ((out, expected),) = offline(model_paths[kind], masks, [t0 + k * DT for k in range(25)])
        assert msg.complete and msg.frames_used == 25
        assert stamp_ns(msg.header.stamp) == t0 + 24 * DT and stamp_ns(msg.oldest_stamp) == t0
        assert msg.header.frame_id == "ad_sim/view_0"
        assert msg.model_id == f"test-{kind}" and msg.inference_time > 0
        assert msg.material == expected.material and list(msg.class_names) == list(expected.class_names)
        np.testing.assert_allclose(msg.class_probabilities, expected.probabilities, rtol=1e-6)
        np.testing.assert_allclose(msg.parameters, expected.parameters, rtol=1e-6)
        np.testing.assert_allclose(msg.parameter_uncertainties, expected.uncertainties, rtol=1e-6)
    stats = t.node.statistics()
    assert stats["received"] == 50 and stats["published"] == 2 and stats["dropped"] == 0
    assert stats["latency_p50_ms"] > 0


def test_anytime_policy_reports_frames_used_and_uncertainty(ros, model_paths):
    t = start(ros, model_paths["streaming"], output_policy="anytime", min_frames=10, every_n=5)
    publish_episode(t, falling_masks(seed=3), 0)
    assert wait_for(lambda: len(t.estimates) >= 4)
    assert [m.frames_used for m in t.estimates] == [10, 15, 20, 25]
    assert [m.complete for m in t.estimates] == [False, False, False, True]
    for m in t.estimates:
        used = ~np.isnan(m.parameters)
        assert np.all(np.isfinite(np.asarray(m.parameter_uncertainties)[used]))


def test_thirty_fps_camera_gets_the_models_spacing(ros, model_paths):
    t = start(ros, model_paths["streaming"])
    masks = falling_masks(40, seed=4)
    stamps = [round(k * 1e9 / 30) for k in range(19)]
    for mask, stamp in zip(masks, stamps):
        t.publisher.publish(image_msg(mask, stamp))
    assert wait_for(lambda: len(t.estimates) >= 1)
    ((out, expected),) = offline(model_paths["streaming"], masks, stamps)
    assert t.estimates[0].frames_used == 25 and out.frames_used == 25
    np.testing.assert_allclose(t.estimates[0].class_probabilities, expected.probabilities, rtol=1e-6)


def test_idle_input_settles_the_last_slot(ros, model_paths):
    """A stream that ends with its last frame just before the last slot time still gets its estimate."""
    t = start(ros, model_paths["streaming"], idle_flush=0.2)
    taken, handle_frame = [], t.node.handle_frame

    def timed_handle_frame(*args):  # when the worker takes each frame, by its own clock (not when this test looks)
        taken.append(time.monotonic())
        return handle_frame(*args)

    t.node.handle_frame = timed_handle_frame
    masks = falling_masks(seed=10)
    for k, mask in enumerate(masks):
        t.publisher.publish(image_msg(mask, k * DT - (2_000_000 if k == 24 else 0)))
    assert wait_for(lambda: t.node.statistics()["processed"] == 25)
    assert wait_for(lambda: len(t.estimates) == 1, timeout=5)
    # Only once the input went idle (0.2 s): measured from when the worker took the last frame. Measured from when
    # this test saw it processed, a test thread that looked late on a busy machine found the estimate there already.
    assert len(taken) == 25 and time.monotonic() - taken[-1] > 0.1
    assert t.estimates[0].complete and t.estimates[0].frames_used == 25


def test_reset_service_restarts_the_window(ros, model_paths):
    t = start(ros, model_paths["streaming"])
    masks = falling_masks(seed=5)
    publish_episode(t, masks[:10], 0)
    assert wait_for(lambda: t.node.statistics()["processed"] == 10)
    reset = t.client.create_client(Trigger, "/ad_estimator/reset")
    assert reset.wait_for_service(timeout_sec=5)
    future = reset.call_async(Trigger.Request())
    assert wait_for(future.done) and future.result().success
    publish_episode(t, masks, 10 * DT)  # stamps continue without a gap: only the reset restarts
    assert wait_for(lambda: len(t.estimates) >= 1)
    assert stamp_ns(t.estimates[0].oldest_stamp) == 10 * DT and t.estimates[0].frames_used == 25


def test_reset_counts_the_queued_frames_it_discards(ros, model_paths):
    """Frames waiting in the queue when ~/reset comes belong to the old episode: they are discarded, and
    counted (they were counted nowhere, so received no longer added up)."""
    t = start(ros, model_paths["streaming"], diagnostics_period=0.2)
    arrays = []
    t.client.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    release, encode = threading.Event(), t.node.model.encode

    def held_encode(*args):  # the worker holds the first frame, so the next ones wait in the queue
        release.wait(timeout=30)
        return encode(*args)

    t.node.model.encode = held_encode
    publish_episode(t, falling_masks(seed=5)[:7], 0)
    assert wait_for(lambda: t.node.statistics()["received"] == 7 and t.node.queue.qsize() == 6)
    reset = t.client.create_client(Trigger, "/ad_estimator/reset")
    assert reset.wait_for_service(timeout_sec=5)
    future = reset.call_async(Trigger.Request())
    assert wait_for(future.done) and future.result().success
    assert "6 queued frame(s) discarded" in future.result().message
    release.set()
    assert wait_for(lambda: t.node.statistics()["processed"] == 1)
    stats = t.node.statistics()
    assert stats["cleared_by_reset"] == 6 and stats["received"] == stats["processed"] + stats["cleared_by_reset"]
    assert wait_for(lambda: any({kv.key: kv.value for kv in a.status[0].values}.get("frames_cleared_by_reset") == "6"
                                for a in arrays))


@pytest.mark.parametrize("cause", ["backwards", "size"])
def test_window_restarts_on_backwards_stamps_and_size_change(ros, model_paths, cause):
    t = start(ros, model_paths["streaming"])
    publish_episode(t, falling_masks(seed=6)[:12], 10**9)
    masks = falling_masks(size=96 if cause == "size" else 128, seed=7)
    t0 = 10**9 + 12 * DT if cause == "size" else 10**9 - 5 * DT
    publish_episode(t, masks, t0)
    assert wait_for(lambda: len(t.estimates) >= 1)
    assert stamp_ns(t.estimates[0].oldest_stamp) == t0 and t.estimates[0].frames_used == 25
    assert t.node.window.stats.restarts[cause] == 1


def test_the_stream_is_served_while_a_clip_is_estimated(ros, model_paths):
    """A clip call that takes long (held here until the stream's estimate arrives) no longer holds up the
    subscription: it shared the executor's callback group, so a 9 s clip of large frames lost the stream.
    The node spins on its own executor here, as in `ros2 run` (single-threaded: the clip service has its own)."""
    context, _ = ros
    node_executor = make_executor(context)
    threading.Thread(target=spin_until_shutdown, args=(node_executor, context), daemon=True).start()
    t = start(ros, model_paths["streaming"], node_executor=node_executor)
    busy, release, estimate_clip = threading.Event(), threading.Event(), t.node.estimate_clip

    def slow_clip(frames):
        busy.set()
        release.wait(30)
        return estimate_clip(frames)

    t.node.estimate_clip = slow_clip
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    masks = falling_masks(seed=23)
    future = client.call_async(EstimateMaterial.Request(frames=[image_msg(m, 0) for m in masks]))
    assert wait_for(busy.is_set)
    publish_episode(t, masks, 10**9)
    try:
        assert wait_for(lambda: len(t.estimates) == 1, timeout=20) and not future.done()
    finally:
        release.set()
    assert wait_for(future.done) and future.result().success
    assert t.node.statistics()["received"] == 25


def test_the_clip_service_outlives_a_failure_of_its_executor(ros, model_paths, monkeypatch):
    """An error out of the clip service's executor ended its thread for good: ~/estimate never answered again,
    while the stream went on. Now it is counted and warned about, and the service goes on."""
    t = start(ros, model_paths["streaming"])
    spin_once, failed = t.node.clip_executor.spin_once, threading.Event()

    def failing_once(*args, **kwargs):
        if not failed.is_set():
            failed.set()
            raise RuntimeError("a service failure")
        return spin_once(*args, **kwargs)

    monkeypatch.setattr(t.node.clip_executor, "spin_once", failing_once)
    assert wait_for(lambda: failed.is_set() and t.node.statistics()["errors"] == 1)
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(EstimateMaterial.Request(frames=[image_msg(m, k * DT) for k, m in
                                                                 enumerate(falling_masks(seed=3))]))
    assert wait_for(future.done) and future.result().success, future.result()
    assert t.node.clip_server.is_alive()


def test_estimate_service_answers_a_clip(ros, model_paths):
    t = start(ros, model_paths["streaming"])
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    masks = falling_masks(seed=8)
    request = EstimateMaterial.Request(frames=[image_msg(m, 0) for m in masks])  # unstamped: model spacing
    future = client.call_async(request)
    assert wait_for(future.done)
    response = future.result()
    assert response.success, response.message
    ((_, expected),) = offline(model_paths["streaming"], masks, [k * DT for k in range(25)])
    assert response.estimate.complete and response.estimate.frames_used == 25 and response.message == ""
    np.testing.assert_allclose(response.estimate.class_probabilities, expected.probabilities, rtol=1e-6)

    # A 5 s gap after frame 10: the frames after it are past the 25 slots. An estimate, said to be partial.
    gapped = EstimateMaterial.Request(frames=[image_msg(m, k * DT + (5 * 10**9 if k > 10 else 0))
                                              for k, m in enumerate(masks)])
    future = client.call_async(gapped)
    assert wait_for(future.done) and future.result().success
    assert future.result().estimate.frames_used == 12  # frame 10 also fills slot 11, within the slot tolerance
    assert future.result().message == ("partial: 12 of the model's 25 frame slots filled from 25 frames; slots are "
                                       "25 ms apart from the first frame's stamp, and frames past the last slot are "
                                       "not used")

    bad = EstimateMaterial.Request(frames=[image_msg(masks[0].astype(np.float32), 0, encoding="32FC1")])
    future = client.call_async(bad)
    assert wait_for(future.done)
    assert not future.result().success and "32FC1" in future.result().message
    mixed = EstimateMaterial.Request(frames=[image_msg(masks[0], 0), image_msg(falling_masks(size=64)[1], 0)])
    future = client.call_async(mixed)
    assert wait_for(future.done)
    assert not future.result().success
    assert future.result().message == "frame 1: 64x64, frame 0: 128x128; clip frames must all have the same size"
    future = client.call_async(EstimateMaterial.Request())
    assert wait_for(future.done)
    assert not future.result().success and "empty" in future.result().message


def clip_of(case: str) -> tuple[list[int], np.ndarray]:
    """(stamps ns, mono8 pixels) of an odd clip: what a planner may send ~/estimate, and a library user clip_output."""
    clock = 1_700_000_000 * 10**9
    if case == "long":  # 2 s; the object leaves the view after 1 s
        masks = falling_masks(80, seed=31)
        masks[40:] = 0
        return [clock + k * DT for k in range(80)], masks
    if case == "thirty_fps":  # 1 s of a jittery 30 fps camera
        rng = np.random.default_rng(32)
        stamps = [clock + int(k * 1e9 / 30) + int(rng.integers(-3, 4)) * 10**6 for k in range(30)]
        return stamps, falling_masks(30, seed=32)
    if case == "equal_stamps":  # all stamped alike: frames on the model's interval
        return [clock] * 25, falling_masks(25, seed=33)
    assert case == "first_unstamped"  # frame 0 stamped 0, the others with the clock
    return [0] + [clock + k * DT for k in range(1, 25)], falling_masks(25, seed=34)


@pytest.mark.parametrize("case", ["long", "thirty_fps", "equal_stamps", "first_unstamped"])
def test_the_clip_service_and_the_library_give_the_same_estimate_for_a_clip(ros, model_paths, case):
    """~/estimate and window.clip_output (docs/estimator.md, "In your own Python process, without ROS") prepare a
    clip with the same code: for a long clip, one of equal stamps, and one whose first frame is stamped 0 and the
    others with the clock, the same slots, estimate and stamps. The library gave the slot times for equal stamps,
    refused a first frame stamped 0 ("gap_threshold must be a number of seconds up to 1e+06"), and could not take
    frames past the last slot that have no object (array_to_mask refuses them)."""
    stamps, pixels = clip_of(case)
    model = EstimatorModel.load(model_paths["streaming"])
    info, threshold = model.info, model.info.input_threshold()
    if case == "long":  # frames 40 on have no object: converted only if used (they are not)
        out = clip_output(stamps, list(pixels), model.encode, info.frame_interval, info.frame_count,
                          history=info.previous_frames, convert=lambda p: array_to_mask(p, threshold=threshold))
    else:
        out = clip_output(stamps, [array_to_mask(p, threshold=threshold) for p in pixels], model.encode,
                          info.frame_interval, info.frame_count, history=info.previous_frames)
    expected = model.predict(out.features, out.valid)

    t = start(ros, model_paths["streaming"])
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(EstimateMaterial.Request(frames=[image_msg(p, s) for s, p in zip(stamps, pixels)]))
    assert wait_for(future.done) and future.result().success, future.result().message
    answer = future.result().estimate
    assert (stamp_ns(answer.oldest_stamp), stamp_ns(answer.header.stamp), answer.frames_used, answer.complete) == (
        out.oldest_stamp_ns, out.newest_stamp_ns, out.frames_used, out.complete)
    assert answer.material == expected.material
    np.testing.assert_array_equal(np.array(answer.class_probabilities, np.float32),
                                  expected.probabilities.astype(np.float32))
    np.testing.assert_array_equal(answer.parameters, expected.parameters)  # NaN where unused, in both
    np.testing.assert_array_equal(answer.parameter_uncertainties, expected.uncertainties)


def test_streams_and_clips_reach_the_frame_encoder_with_their_earlier_frames(ros, tmp_path):
    """A frame encoder that sees 3 earlier frames: the streamed episode's estimate and the service's
    answer for the same clip are those of each frame encoded with its 3 predecessors, newest first."""
    model_path = build_streaming_model(tmp_path, previous_frames=3)
    model = EstimatorModel.load(model_path)
    masks = falling_masks(seed=12)
    features = np.stack([model.encode(mask, list(masks[:t][::-1])) for t, mask in enumerate(masks)])
    expected = model.predict(features, np.ones(25, bool))
    t = start(ros, model_path)
    publish_episode(t, masks, 10**9)
    assert wait_for(lambda: len(t.estimates) >= 1)
    np.testing.assert_allclose(t.estimates[0].class_probabilities, expected.probabilities, rtol=1e-6)
    np.testing.assert_allclose(t.estimates[0].parameters, expected.parameters, rtol=1e-6)
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(EstimateMaterial.Request(frames=[image_msg(m, 0) for m in masks]))
    assert wait_for(future.done) and future.result().success, future.result().message
    np.testing.assert_allclose(future.result().estimate.class_probabilities, expected.probabilities, rtol=1e-6)


@pytest.fixture(scope="module")
def grey_masks(tmp_path_factory):
    """A streaming model of grey masks (ad.mask_levels coverage; onnx.helper, no torch) and two bags of
    the same two episodes: their masks grey (generate --coverage-masks) and those masks thresholded."""
    d = tmp_path_factory.mktemp("grey_masks")
    model = build_streaming_model(d, model_id="test-coverage", mask_levels="coverage")
    grey, _ = write_coverage_bag(d / "grey", 2, seed=3)
    binary, _ = write_coverage_bag(d / "binary", 2, seed=3, binary=True)
    return types.SimpleNamespace(model=model, grey=grey, binary=binary)


def test_a_model_of_grey_masks_is_fed_their_levels_from_the_topic_and_the_service(ros, grey_masks):
    """The recorded grey frames, published as they are on the node's mask topic, give the estimates that
    `ros2 run ad_estimator estimate` (offline) computes from the bag, not those of the thresholded
    frames; the ~/estimate service answers the first episode's clip with the same estimate."""
    model = EstimatorModel.load(grey_masks.model)
    assert model.info.mask_levels == "coverage"
    values = {name: PARAMETERS[name][0] for name in estimate.OPTIONS}  # the node's defaults, as estimate's
    offline = estimate.estimate_bag(model, grey_masks.grey, DEFAULT_INPUT_TOPIC, values)
    thresholded = estimate.estimate_bag(model, grey_masks.binary, DEFAULT_INPUT_TOPIC, values)
    assert len(offline) == len(thresholded) == 2 and all(r.output.complete for r in offline)
    frames = [data for _, _, data in BagReader(grey_masks.grey, raw=True, topics=[DEFAULT_INPUT_TOPIC])]
    assert len(frames) == 50
    t = start(ros, grey_masks.model)
    for data in frames:
        t.publisher.publish(bytes(data))  # the recorded CDR: the frames as the bag holds them
    assert wait_for(lambda: len(t.estimates) >= 2)
    time.sleep(0.3)
    assert len(t.estimates) == 2
    stats = t.node.statistics()
    assert (stats["received"], stats["processed"], stats["rejected"], stats["errors"]) == (50, 50, 0, 0)
    for msg, row, other in zip(t.estimates, offline, thresholded):
        assert msg.complete and msg.frames_used == 25 and msg.model_id == "test-coverage"
        assert stamp_ns(msg.oldest_stamp) == row.output.oldest_stamp_ns == other.output.oldest_stamp_ns
        expected = row.estimate
        assert msg.material == expected.material
        np.testing.assert_allclose(msg.class_probabilities, expected.probabilities, rtol=1e-6)
        np.testing.assert_allclose(msg.parameters, expected.parameters, rtol=1e-6)
        np.testing.assert_allclose(msg.parameter_uncertainties, expected.uncertainties, rtol=1e-6)
        # Thresholded, the same frames would give another estimate: the node read the levels.
        assert np.abs(np.subtract(msg.class_probabilities, other.estimate.probabilities)).max() > 1e-3
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    clip = [deserialize_message(bytes(data), Image) for data in frames[:25]]
    levels = np.frombuffer(b"".join(bytes(image.data) for image in clip), np.uint8)
    assert ((levels > 0) & (levels < 255)).sum() > 1000  # grey frames indeed
    future = client.call_async(EstimateMaterial.Request(frames=clip))
    assert wait_for(future.done) and future.result().success, future.result().message
    answer = future.result().estimate
    assert answer.complete and answer.frames_used == 25
    np.testing.assert_allclose(answer.class_probabilities, offline[0].estimate.probabilities, rtol=1e-6)
    np.testing.assert_allclose(answer.parameters, offline[0].estimate.parameters, rtol=1e-6)


def test_throttled_warnings_account_for_every_call_from_both_threads():
    """The worker and the clip service's thread share the node's Throttle: every call is either logged or
    counted in a later line's "N more like this suppressed", none lost to a race. Threads switch every
    microsecond here, so that a race shows (without the lock, about one trial in five lost counts)."""
    from ad_estimator.node import Throttle

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for _ in range(20):
            lines = []
            warn = Throttle(lines.append, period=0.002)

            def hammer():
                for _ in range(5000):
                    warn("key", "x")

            threads = [threading.Thread(target=hammer) for _ in range(2)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            time.sleep(0.003)
            warn("key", "x")  # reports what was suppressed since the last line
            suppressed = sum(int(line.split("(")[1].split()[0]) for line in lines if "suppressed" in line)
            assert len(lines) + suppressed == 10001 and len(lines) > 1
    finally:
        sys.setswitchinterval(interval)


def test_the_input_remapped_by_its_full_name_is_the_one_reported(ros, model_paths):
    """Remapped by the full name (as docs/estimator.md allows), the subscription was on the new topic but the
    start-up line, /diagnostics and the QoS error named the default one."""
    t = start(ros, model_paths["streaming"], remap=f"{DEFAULT_INPUT_TOPIC}:={TOPIC}")  # up: subscribed to TOPIC
    assert t.node.input_topic == TOPIC
    publish_episode(t, falling_masks(seed=9), 0)
    assert wait_for(lambda: len(t.estimates) == 1)


def test_diagnostics(ros, model_paths):
    t = start(ros, model_paths["streaming"], diagnostics_period=0.2)
    arrays = []
    t.client.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    publish_episode(t, falling_masks(seed=9), 0)
    assert wait_for(lambda: any(
        dict((kv.key, kv.value) for kv in a.status[0].values).get("estimates_published") == "1" for a in arrays))
    values = {kv.key: kv.value for kv in arrays[-1].status[0].values}
    assert values["model_id"] == "test-streaming" and values["frames_received"] == "25"
    assert float(values["latency_p50_ms"]) > 0 and values["frames_dropped"] == "0"
    for key in ("input_rate_hz", "estimate_rate_hz", "latency_p95_ms", "model_time_p50_ms"):
        float(values[key])


def test_late_and_repeated_stamps_are_counted_warned_and_lose_no_episode(ros, model_paths):
    """Two frames swapped upstream once restarted the window (no estimate, and a new episode anchored
    mid-fall); an unstamped camera gave nothing, silently. Now: the estimate, and WARN saying why."""
    t = start(ros, model_paths["streaming"], diagnostics_period=0.2)
    arrays = []
    t.client.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    masks = falling_masks(seed=10)
    order = [*range(10), 11, 10, *range(12, 25)]
    for k in order:
        t.publisher.publish(image_msg(masks[k], 10**9 + k * DT))
    assert wait_for(lambda: len(t.estimates) == 1)
    assert t.estimates[0].frames_used == 25 and stamp_ns(t.estimates[0].oldest_stamp) == 10**9
    assert t.node.counters["late"] == 1 and t.node.window.episodes == 1

    def warned(what):
        return any(a.status[0].level == DiagnosticStatus.WARN and what in a.status[0].message for a in arrays)

    assert wait_for(lambda: warned("1 frames late"))
    for mask in falling_masks(seed=11):  # a camera that does not stamp: 5 s later, then all at one stamp
        t.publisher.publish(image_msg(mask, 6 * 10**9))
    assert wait_for(lambda: t.node.counters["duplicate"] == 24)
    assert wait_for(lambda: warned("frames with a repeated stamp"))  # in one period or split over two
    values = {kv.key: kv.value for kv in arrays[-1].status[0].values}
    assert values["frames_late"] == "1" and values["frames_duplicate"] == "24"
    assert len(t.estimates) == 1


def test_an_episode_that_ends_without_an_estimate_is_counted_and_warned(ros, model_paths):
    """Frame 0 lost (a best-effort link, late discovery): 24 slots, no estimate under the episode
    policy, and nothing once said so."""
    t = start(ros, model_paths["streaming"], diagnostics_period=0.2)
    arrays = []
    t.client.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    publish_episode(t, falling_masks(seed=12)[1:], 10**9 + DT)
    publish_episode(t, falling_masks(seed=13), 3 * 10**9)  # the next episode ends the first
    assert wait_for(lambda: len(t.estimates) == 1) and stamp_ns(t.estimates[0].oldest_stamp) == 3 * 10**9
    assert wait_for(lambda: any(a.status[0].level == DiagnosticStatus.WARN and "1 episodes ended without an "
                                "estimate" in a.status[0].message for a in arrays))
    assert t.node.counters["without_estimate"] == 1
    assert {kv.key: kv.value for kv in arrays[-1].status[0].values}["episodes_without_estimate"] == "1"


def test_each_complete_estimate_is_logged_in_one_line(ros, model_paths, capfd):
    """Without ros2 topic echo a running node looked idle: it logged nothing after start-up."""
    t = start(ros, model_paths["streaming"])
    publish_episode(t, falling_masks(seed=14), 10**9)
    assert wait_for(lambda: len(t.estimates) == 1)
    estimate = t.estimates[0]
    # The episode's number as the node counts it (1 unless its window restarted on the way, as a loaded CI
    # machine once seemed to make it), with the estimate's family and probability.
    expected = re.compile(rf"episode \d+: {estimate.material} p={max(estimate.class_probabilities):.2f}; ")
    err = ""

    def logged() -> bool:  # the node logs just after it publishes, so the line may trail the estimate
        nonlocal err
        err += capfd.readouterr().err
        return bool(expected.search(err))

    assert wait_for(logged), (f"no {expected.pattern!r} line; stderr: {err[-3000:]!r}; counters: "
                              f"{dict(t.node.counters)}; estimates: {[(e.frames_used, e.complete) for e in t.estimates]}")
    (line,) = [line for line in err.splitlines() if expected.search(line)]
    assert line.startswith("[INFO]") and line.endswith(" ms)")


def test_parameters_are_read_only_and_whole_numbers_fill_decimal_ones(ros, model_paths):
    """`ros2 param set` once answered success and changed nothing; `idle_flush:=0` (documented: never)
    was refused as an INTEGER for a DOUBLE."""
    t = start(ros, model_paths["streaming"], idle_flush=0, slot_tolerance=1)
    assert t.node.idle_flush == 0.0 and t.node.slot_tolerance == 1.0
    client = t.client.create_client(SetParameters, "/ad_estimator/set_parameters")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(SetParameters.Request(parameters=[
        Parameter("output_policy", value="anytime").to_parameter_msg()]))
    assert wait_for(future.done)
    (result,) = future.result().results
    assert not result.successful and "read-only" in result.reason
    assert t.node.get_parameter("output_policy").value == "episode"


def test_a_best_effort_camera_against_a_reliable_subscription_is_reported(ros, model_paths):
    """DDS delivers nothing from a best-effort publisher to a reliable subscription: the node counts
    the publisher and puts it in /diagnostics as a warning, instead of waiting in silence."""
    t = start(ros, model_paths["streaming"], diagnostics_period=0.2)  # reliable:=true
    arrays = []
    t.client.create_subscription(DiagnosticArray, "/diagnostics", arrays.append, 10)
    camera = t.client.create_publisher(Image, TOPIC, QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    assert wait_for(lambda: t.node.statistics()["incompatible_publishers"] == 1)
    assert wait_for(lambda: arrays and arrays[-1].status[0].message == "no frames; 1 input publisher(s) with "
                                                                       "incompatible QoS seen")
    assert arrays[-1].status[0].level == DiagnosticStatus.WARN
    assert {kv.key: kv.value for kv in arrays[-1].status[0].values}["incompatible_publishers"] == "1"
    # The camera fixed (a reliable publisher): frames arrive, and the warning clears.
    publish_episode(t, falling_masks(seed=9), 0)
    assert wait_for(lambda: t.estimates)
    arrays.clear()
    assert wait_for(lambda: arrays and arrays[-1].status[0].level == DiagnosticStatus.OK, timeout=5)


# --------------------------------------------------------------------------- bad input


def raw_image(height, width, encoding, step, data, stamp_ns, bigendian=False):
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.height, msg.width, msg.encoding, msg.step, msg.is_bigendian = height, width, encoding, step, bigendian
    msg.data = data
    return msg


@pytest.fixture(scope="module")
def fuzz_node(model_paths):
    with ros_context() as (context, _):
        node = EstimatorNode(context=context, parameter_overrides=[
            Parameter("model_path", value=str(model_paths["streaming"])),
            Parameter("max_image_pixels", value=300 * 300), Parameter("output_policy", value="anytime"),
            Parameter("min_frames", value=1), Parameter("every_n", value=1), Parameter("queue_size", value=8)])
        yield node
        node.destroy_node()


ENCODINGS = st.sampled_from(["mono8", "8UC1", "mono16", "16UC1", "rgb8", "bgr8", "rgba8", "32FC1", "yuv422", ""])


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(0, 400), st.integers(0, 400), ENCODINGS, st.integers(0, 1300), st.integers(0, 40_000),
       st.integers(0, 2**33), st.booleans(), st.booleans())
def test_fuzz_callback_never_crashes(fuzz_node, height, width, encoding, step, length, stamp, bigendian, direct):
    data = np.random.default_rng(length).integers(0, 256, length, dtype=np.uint8).tobytes()
    msg = raw_image(height, width, encoding, step, data, stamp, bigendian)
    before = fuzz_node.statistics()
    if direct:
        fuzz_node.handle_frame(msg, time.perf_counter())  # the worker's path, synchronously
    else:
        fuzz_node.on_image(msg)  # the subscription callback (header checks, queue)
    after = fuzz_node.statistics()
    assert fuzz_node.worker.is_alive() and after["errors"] == 0
    assert fuzz_node.queue.qsize() <= 8
    if not direct:
        assert after["received"] == before["received"] + 1
        if height * width > 300 * 300:
            # Refused from the header alone. At least one: the worker may reject an earlier
            # example's queued frame meanwhile (test_oversized_frames_never_reach_the_worker
            # checks the exact count on a quiet node).
            assert after["rejected"] >= before["rejected"] + 1


def test_oversized_frames_never_reach_the_worker(model_paths):
    with ros_context() as (context, _):
        node = EstimatorNode(context=context, parameter_overrides=[
            Parameter("model_path", value=str(model_paths["streaming"])),
            Parameter("max_image_pixels", value=64 * 64), Parameter("min_frames", value=1)])
        try:
            data = np.zeros(65 * 64, np.uint8).tobytes()
            node.on_image(raw_image(65, 64, "mono8", 64, data, 10**9, False))
            stats = node.statistics()
            assert (stats["received"], stats["rejected"], stats["queue_depth"]) == (1, 1, 0)
            time.sleep(0.2)  # a frame that had slipped into the queue would now be processed or rejected again
            stats = node.statistics()
            assert (stats["rejected"], stats["processed"], stats["errors"]) == (1, 0, 0)
        finally:
            node.destroy_node()


def disc(side: int, diameter: float, height: int | None = None) -> np.ndarray:
    """A mask with a centred disc `diameter` (a fraction of `side`) across."""
    yy, xx = np.mgrid[: height or side, :side]
    return np.where(np.hypot(yy - (height or side) / 2, xx - side / 2) <= diameter * side / 2, 255, 0).astype(np.uint8)


def test_episodes_framed_unlike_training_are_counted(model_paths):
    """An episode whose first frame shows the object much larger or smaller than any training clip
    is counted (and warned about, throttled); one framed as in training is not."""
    with ros_context() as (context, _):
        node = EstimatorNode(context=context, parameter_overrides=[
            Parameter("model_path", value=str(model_paths["streaming"]))])
        try:
            stamp = 10**9
            for diameter, off in ((0.3, 0), (0.8, 1), (0.3, 1), (0.05, 2)):
                stamp += 10**9  # a gap: a new episode
                for k in range(3):
                    node.handle_frame(image_msg(disc(512, diameter), stamp + k * DT), time.perf_counter())
                stats = node.statistics()
                assert (stats["off_framing"], stats["errors"]) == (off, 0), diameter
            # The clip service checks its clip the same way, still answers, and tells its caller.
            clip = [image_msg(disc(512, 0.8), stamp + 10**9 + k * DT) for k in range(3)]
            estimate, framing = node.estimate_clip(clip)
            assert estimate.material and node.statistics()["off_framing"] == 3
            assert framing.startswith("the object spans 80% of the image side; training objects spanned")
            response = node.on_estimate(EstimateMaterial.Request(frames=clip), EstimateMaterial.Response())
            assert response.success and response.message.startswith("partial: 3 of the model's 25 frame slots")
            assert response.message.endswith("; " + framing)
        finally:
            node.destroy_node()


def test_valid_fuzzed_frames_produce_estimates(fuzz_node):
    """Well-formed frames of random sizes and stamps, straight into the handler: estimates come out.
    (Also: the worker has processed every fuzzed frame queued before without an error.)"""
    assert wait_for(lambda: fuzz_node.queue.qsize() == 0)
    time.sleep(0.2)
    rng = np.random.default_rng(0)
    published = 0
    stamp = 5 * 10**9
    for _ in range(60):
        h, w = rng.choice([64, 128, 200]), rng.choice([64, 128, 200])
        mask = (rng.random((h, w)) > 0.5).astype(np.uint8) * 255
        stamp += int(rng.choice([DT, -DT, 10**9, DT // 2]))
        published += len(fuzz_node.handle_frame(image_msg(mask, max(stamp, 0)), time.perf_counter()))
    assert published > 0 and fuzz_node.statistics()["errors"] == 0


def test_flood_keeps_the_queue_bounded_and_counts_drops(ros, model_paths):
    context, executor = ros
    node = EstimatorNode(context=context, parameter_overrides=[
        Parameter("model_path", value=str(model_paths["clip"])), Parameter("queue_size", value=4)])
    try:
        msg = image_msg(np.full((512, 512), 255, np.uint8), 0)
        depth = 0
        for i in range(2000):
            msg.header.stamp.nanosec = i * 1000
            node.on_image(msg)
            depth = max(depth, node.queue.qsize())
        stats = node.statistics()
        assert depth <= 4 and stats["dropped"] > 1000
        assert stats["received"] == 2000 and node.worker.is_alive()
        assert wait_for(lambda: node.queue.qsize() == 0)
    finally:
        node.destroy_node()


# --------------------------------------------------------------------------- process level


def run_node(*ros_args, **kwargs):
    return subprocess.Popen([sys.executable, "-m", "ad_estimator.node", "--ros-args", *ros_args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)


@contextlib.contextmanager
def killed_at_exit(proc: subprocess.Popen):
    """The process, killed when the block ends with it still running (a failed assertion)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def read_until(proc: subprocess.Popen, lines: list[str], text: str) -> None:
    """Reads the process's output into `lines` until one holds `text`; AssertionError with it all if it ends first."""
    while not any(text in line for line in lines):
        lines.append(proc.stdout.readline())
        if not lines[-1]:
            raise AssertionError("".join(lines))


def assert_exited_cleanly(proc: subprocess.Popen, out: str) -> None:
    assert proc.returncode == 0 and "Traceback" not in out and "terminate called" not in out, out


@pytest.mark.parametrize("content", [None, b"not an onnx file", b""])
def test_missing_or_corrupt_model_fails_at_start_naming_the_file(tmp_path, content):
    path = tmp_path / "broken_model.onnx"
    if content is not None:
        path.write_bytes(content)
    proc = run_node("-p", f"model_path:={path}")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and str(path) in out and "Traceback" not in out


@pytest.mark.parametrize("parameter, message", [
    ("diagnostics_period:=0.0", "diagnostics_period is seconds in [0.01, 1e+06], got 0.0"),  # a busy loop
    ("diagnostics_period:=-1.0", "diagnostics_period is seconds in [0.01, 1e+06], got -1.0"),  # failed in rcl
    ("diagnostics_period:=1e300", "diagnostics_period is seconds in [0.01, 1e+06], got 1e+300"),  # overflowed
    ("diagnostics_period:=0.000000001", "diagnostics_period is seconds in [0.01, 1e+06], got 1e-09"),
    ("threads:=100000", "threads must be at most 256, got 100000"),  # took minutes and 16 GB to load
    ("input_depth:=9223372036854775807", "input_depth must be at most 1000000, got 9223372036854775807"),
    ("queue_size:=1001", "queue_size must be at most 1000, got 1001"),  # up to 10**6 once: memory, estimates late
])
def test_a_parameter_out_of_range_is_refused(model_paths, parameter, message, ros_domain_id):
    proc = run_node("-p", f"model_path:={model_paths['streaming']}", "-p", parameter)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1 and message in out, out
    assert "Traceback" not in out


def test_frames_without_object_or_with_a_malformed_stamp_are_rejected_not_estimated(ros, model_paths):
    """A 0/1 mask (nothing above mask_threshold 127) gave an estimate of nothing, with confidence; a stamp
    with nanosec >= 1e9 was read as seconds later. Both are rejected and counted, from the topic and the
    service, and a good episode afterwards gets its estimate."""
    t = start(ros, model_paths["streaming"])
    masks = falling_masks(seed=21)
    publish_episode(t, [m // 255 for m in masks], 10**9)  # 0/1 masks
    bad_stamp = image_msg(masks[0], 5 * 10**9)
    bad_stamp.header.stamp.nanosec = 3_000_000_000
    t.publisher.publish(bad_stamp)
    assert wait_for(lambda: t.node.statistics()["rejected"] == 26)
    stats = t.node.statistics()
    assert stats["processed"] == 0 and not t.estimates
    publish_episode(t, masks, 10 * 10**9)
    assert wait_for(lambda: len(t.estimates) == 1) and t.estimates[0].frames_used == 25
    client = t.client.create_client(EstimateMaterial, "/ad_estimator/estimate")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(EstimateMaterial.Request(frames=[image_msg(m // 255, 0) for m in masks]))
    assert wait_for(future.done) and not future.result().success
    assert future.result().message.startswith("frame 0: no object pixel in this mono8 mask above mask_threshold 127 "
                                              "(its brightest pixel is 1; a 0/1 mask needs mask_threshold 0)")
    stamped = [image_msg(m, k * DT) for k, m in enumerate(masks)]
    stamped[3].header.stamp.nanosec = 1_000_000_000
    future = client.call_async(EstimateMaterial.Request(frames=stamped))
    assert wait_for(future.done) and not future.result().success
    assert "stamp nanosec 1000000000 is not below 1e9" in future.result().message


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_clean_shutdown_on_signals(model_paths, sig, ros_domain_id):
    proc = run_node("-p", f"model_path:={model_paths['streaming']}", "-r", "mask:=/estimator_test/signal")
    lines = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if "model test-streaming" in line or not line:
            break
    assert any("model test-streaming" in line for line in lines), "".join(lines)
    time.sleep(0.5)  # let it reach spin (a signal during start-up exits cleanly too, with less to say)
    proc.send_signal(sig)
    out = "".join(lines) + proc.communicate(timeout=20)[0]
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "shutting down" in out


def test_signals_in_a_row_through_the_shutdown_exit_cleanly(model_paths, ros_domain_id):
    """SIGINT, then SIGINT and SIGTERM about every millisecond until the node exits (Ctrl-C pressed again and again,
    launch escalating): the second cuts finishing the input short, the rest change nothing. Each later signal raised
    KeyboardInterrupt wherever the main thread was: a traceback out of rclpy destroying the node, an abort (C++
    terminate) from a thread left in rclpy, or, as the interpreter exited, death by the signal itself."""
    with killed_at_exit(run_node("-p", f"model_path:={model_paths['streaming']}", "-r",
                                 "mask:=/estimator_test/signals")) as proc:
        lines = []
        read_until(proc, lines, "model test-streaming")
        signals = itertools.cycle([signal.SIGINT, signal.SIGTERM])
        while proc.poll() is None:
            proc.send_signal(next(signals))
            time.sleep(0.001)
        out = "".join(lines) + proc.communicate(timeout=20)[0]
    assert_exited_cleanly(proc, out)
    assert out.count("shutting down") == 1, out


@pytest.mark.parametrize("executable", ["node", "replay"])
def test_ctrl_c_while_starting_exits_quietly_as_any_ctrl_c(executable, model_paths, ros_domain_id, tmp_path):
    """A Ctrl-C during the node's imports (most of its first second, before it handles signals) printed Python's
    KeyboardInterrupt traceback, and the process died of the signal. Wherever it lands before the node is up, the
    node now exits with status 0 as after any Ctrl-C, with one line if it came during the imports. So does
    replay, an rclpy executable too, during its imports."""
    if executable == "node":
        args = ["--ros-args", "-p", f"model_path:={model_paths['streaming']}", "-r", "mask:=/estimator_test/interrupted"]
        delays, said = (0.0, 0.0, 0.05, 0.15, 0.3, 0.6, 1.0, 2.0), "ad_estimator: interrupted while starting"
    else:
        args = [str(REPO_ROOT / "bags" / "samples" / "unseen-masks-0of1")]
        delays, said = (0.0, 0.0, 0.05), "replay: interrupted while starting"
    during_imports = 0
    try:
        for attempt, delay in enumerate(delays):
            status, lines = interrupt_while_starting([str(ADRUN), "ad_estimator", executable, *args],
                                                     tmp_path / f"{attempt}.log", delay)
            text = "\n".join(lines)
            assert status == 0 and "Traceback" not in text and "KeyboardInterrupt" not in text, (delay, text)
            during_imports += lines == [said]
    finally:
        kill_leftovers()
    assert during_imports, "no Ctrl-C landed during the imports"


def test_the_installed_example_params_file_configures_the_node(model_paths, ros_domain_id):
    """config/anytime.yaml, installed to share/ad_estimator/config, is read by the node through
    --params-file (what ros2 run and launch files pass), and the node says what it applied."""
    from ament_index_python.packages import get_package_share_directory

    params = Path(get_package_share_directory("ad_estimator")) / "config" / "anytime.yaml"
    assert params.is_file(), f"{params} is not installed (ros_ws/src/ad_estimator/setup.py data_files)"
    proc = run_node("--params-file", str(params), "-p", f"model_path:={model_paths['streaming']}",
                    "-r", "mask:=/estimator_test/params")
    try:
        deadline, lines = time.monotonic() + 60, []
        while time.monotonic() < deadline and not any("model test-streaming" in line for line in lines):
            lines.append(proc.stdout.readline())
            if not lines[-1]:
                break
        started = next((line for line in lines if "model test-streaming" in line), "")
        assert "(reliable)" in started and "policy anytime (from 15 frames, every 1)" in started, "".join(lines)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=20)


def test_estimator_runtime_never_imports_torch_nor_warp():
    """What runs on the robot loads neither torch nor the simulator's Warp and SciPy (Warp came in through the
    metrics' family constants: about 1 s at start-up, and a simulator's dependency on the robot)."""
    code = ("import sys, ad_estimator.node, ad_estimator.replay, ad_estimator.evaluate, ad_estimator.estimate, "
            "ad_estimator.model, ad_estimator.metrics; print(sorted({'torch', 'warp', 'scipy'} & set(sys.modules)))")
    probe = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0 and probe.stdout.strip() == "[]", probe.stdout + probe.stderr


def test_an_overtaken_first_frame_is_checked_for_framing_as_the_episodes_first(ros, model_paths):
    """The episode's true first frame, overtaken at the release, restarts the episode from itself (no new episode
    is counted): its framing went unchecked, so an episode whose first frame showed the object framed unlike
    training was not counted nor warned about when frame 1 arrived first. Counted once per episode."""
    t = start(ros, model_paths["streaming"])
    for t0, (first, second) in ((10**9, (0.8, 0.3)), (5 * 10**9, (0.8, 0.8))):
        order = [(t0 + DT, second), (t0, first), (t0 + 2 * DT, second)]  # frames 1 and 0 swapped upstream
        for stamp, diameter in order:
            t.publisher.publish(image_msg(disc(512, diameter), stamp))
    assert wait_for(lambda: t.node.statistics()["processed"] == 6)
    stats = t.node.statistics()
    assert (stats["late"], stats["errors"], t.node.window.episodes) == (0, 0, 2)
    assert stats["off_framing"] == 2  # the first episode by its true first frame, the second once


def test_an_estimate_flushed_by_the_next_episode_does_not_take_its_encoding_time(ros, model_paths):
    """The first frame of an episode flushes the estimate of the one before (anytime policy): that estimate's
    inference_time included the new frame's encoding, which it does not use."""
    t = start(ros, model_paths["streaming"], output_policy="anytime", min_frames=10, every_n=5)
    publish_episode(t, falling_masks(seed=15)[:12], 10**9)
    assert wait_for(lambda: t.node.statistics()["processed"] == 12 and len(t.estimates) == 1)
    encode = t.node.model.encode

    def slow_encode(*args):
        time.sleep(0.3)
        return encode(*args)

    t.node.model.encode = slow_encode
    t.publisher.publish(image_msg(falling_masks(seed=16)[0], 3 * 10**9))
    assert wait_for(lambda: len(t.estimates) == 2)
    flushed = t.estimates[1]
    assert flushed.frames_used == 12 and stamp_ns(flushed.oldest_stamp) == 10**9
    assert 0 < flushed.inference_time < 0.3, flushed.inference_time


def test_a_second_sigint_while_a_clip_call_holds_up_the_shutdown_exits_cleanly(ros, model_paths):
    """SIGINT while ~/estimate works on a clip: the node waits (up to 2 s) for the call. A second SIGINT then
    raised KeyboardInterrupt out of that wait: a traceback, no rclpy shutdown, and an abort (C++ terminate)."""
    code = ("import sys, time\nfrom ad_estimator import node\n"
            "def slow_clip(self, frames):\n    print('clip call started', flush=True)\n    time.sleep(60)\n"
            "node.EstimatorNode.estimate_clip = slow_clip\n"
            f"sys.exit(node.main(['node', '--ros-args', '-p', 'model_path:={model_paths['streaming']}']))\n")
    with killed_at_exit(subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, text=True)) as proc:
        lines = []
        read_until(proc, lines, "model test-streaming")
        context, _ = ros
        client_node = Node("clip_caller", context=context)
        ros[1].add_node(client_node)
        client = client_node.create_client(EstimateMaterial, "/ad_estimator/estimate")
        assert client.wait_for_service(timeout_sec=10)
        client.call_async(EstimateMaterial.Request(frames=[image_msg(m, 0) for m in falling_masks(seed=3)[:3]]))
        read_until(proc, lines, "clip call started")
        proc.send_signal(signal.SIGINT)
        time.sleep(0.5)  # in the wait for the clip call
        stopped = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out = "".join(lines) + proc.communicate(timeout=20)[0]
    assert_exited_cleanly(proc, out)
    assert "shutting down" in out and time.monotonic() - stopped < 5, out


@pytest.mark.parametrize("signals", [[signal.SIGINT], [signal.SIGINT, signal.SIGTERM]], ids=["one", "two"])
def test_signals_while_starting_up_stop_the_start_up(model_paths, signals, ros_domain_id):
    """A signal while the node started up (here: a model that takes 5 s to load) took effect only once the node was
    up: it spun, then finished its input (here made to take 60 s, as one a second signal should cut short), and a
    second signal during start-up was ignored. Start-up now ends with the step in progress (the model's loading: one
    call into onnxruntime), and the node exits cleanly without spinning or finishing input it never took."""
    code = ("import sys, time\nfrom ad_estimator import node\n"
            "load = node.EstimatorModel.load\n"
            "def slow_load(*args, **kwargs):\n    print('loading the model', flush=True)\n    time.sleep(5)\n"
            "    return load(*args, **kwargs)\n"
            "def slow_finish(self, timeout=None):\n    print('finishing the input', flush=True)\n    time.sleep(60)\n"
            "    return True\n"
            "node.EstimatorModel.load = slow_load\nnode.EstimatorNode.finish = slow_finish\n"
            f"sys.exit(node.main(['node', '--ros-args', '-p', 'model_path:={model_paths['streaming']}', "
            "'-r', 'mask:=/estimator_test/starting']))\n")
    with killed_at_exit(subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, text=True)) as proc:
        lines = []
        read_until(proc, lines, "loading the model")
        for sig in signals:
            proc.send_signal(sig)
        try:
            out = "".join(lines) + proc.communicate(timeout=30)[0]  # the load's 5 s, and the clean-up
        except subprocess.TimeoutExpired:
            proc.kill()
            raise AssertionError("".join(lines) + proc.communicate()[0]) from None
    assert_exited_cleanly(proc, out)
    assert "finishing the input" not in out and "shutting down" in out, out


def test_a_later_signal_that_came_before_the_wait_for_the_input_still_cuts_it_short():
    """A second signal that came before the main thread began its wait for the input's finish (during start-up, or
    as the first signal woke it) was ignored, and the wait ran its full time."""
    from ad_estimator.node import StopSignals

    stop = StopSignals()
    stop(signal.SIGINT, None)
    stop(signal.SIGTERM, None)
    waited = []
    stop.interruptible(lambda: waited.append(True))
    assert stop.requested.is_set() and not waited
