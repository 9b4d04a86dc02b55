"""The estimator node from a consumer's side: a planner's rclpy node, over real DDS, reading
MaterialEstimate as ad_msgs' comments, the README and docs/estimator.md describe it (SPEC 5), calling
~/estimate with odd clips and ~/reset, and joining late."""
import math
import threading
import time
import types

import numpy as np
import pytest
from ad_msgs.msg import MaterialEstimate
from ad_msgs.srv import EstimateMaterial
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_srvs.srv import Trigger

import ad_estimator.node as estimator_node
from ad_estimator.model import BUNDLED_MODEL
from ad_estimator.node import MAX_CLIP_FRAMES, EstimatorNode
from estimator_models import build_streaming_model, falling_masks
from estimator_ros import image_msg, tracked, wait_for

pytestmark = pytest.mark.ros
DT = 25_000_000
T0 = 1_700_000_000 * 10**9  # a clock stamp, as a robot's camera gives
TOPIC = "/planner_test/mask"
CAMERA = "camera_optical"
# SPEC 5 and 6: the names, their SI units and the sampled ranges (friction angle in radians).
PARAMETER_NAMES = ["youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle"]
RANGES = {"youngs_modulus": (1.5e4, 1.5e6), "poissons_ratio": (0.2, 0.48), "yield_stress": (500.0, 25000.0),
          "friction_angle": (math.radians(10), math.radians(45))}
USED = {"jelly": {"youngs_modulus", "poissons_ratio"},
        "plasticine": {"youngs_modulus", "poissons_ratio", "yield_stress"},
        "sand": {"youngs_modulus", "poissons_ratio", "friction_angle"}}
FIXED = {"sand": {"youngs_modulus": 1e5, "poissons_ratio": 0.3}}


@pytest.fixture(scope="module")
def test_model(tmp_path_factory):
    return build_streaming_model(tmp_path_factory.mktemp("client_models"))


def start(ros, model_path=BUNDLED_MODEL, **params):
    """The node, and a planner node apart from it that subscribes to the estimates and calls the services,
    and a camera node that publishes masks."""
    context, executor = ros
    params = {"reliable": True, "input_depth": 100, "idle_flush": 30.0, **params}
    overrides = [Parameter("model_path", value=str(model_path))] + [Parameter(k, value=v) for k, v in params.items()]
    node = tracked(EstimatorNode(context=context, parameter_overrides=overrides,
                                 cli_args=["--ros-args", "-r", f"mask:={TOPIC}"]))
    planner, camera = Node("planner", context=context), Node("camera", context=context)
    estimates = []
    planner.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append, 10)
    publisher = camera.create_publisher(Image, TOPIC, QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
    clips = planner.create_client(EstimateMaterial, "/ad_estimator/estimate")
    reset = planner.create_client(Trigger, "/ad_estimator/reset")
    for n in (node, planner, camera):
        executor.add_node(n)
    assert wait_for(lambda: publisher.get_subscription_count() > 0
                    and planner.count_publishers("/ad_estimator/estimate") > 0), "estimator did not come up"
    assert clips.wait_for_service(timeout_sec=5) and reset.wait_for_service(timeout_sec=5)
    return types.SimpleNamespace(node=node, planner=planner, estimates=estimates, publisher=publisher, clips=clips,
                                 reset=reset, executor=executor, context=context)


def call(client, request, timeout=30.0):
    future = client.call_async(request)
    assert wait_for(future.done, timeout=timeout), "no answer"
    return future.result()


def clip(t, frames):
    return call(t.clips, EstimateMaterial.Request(frames=frames))


def frames_of(masks, t0=T0, step=DT, frame_id=CAMERA):
    return [image_msg(m, t0 + k * step, frame_id=frame_id) for k, m in enumerate(masks)]


def ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def check_fields(msg: MaterialEstimate, model_id: str):
    """Every field as MaterialEstimate.msg and docs/estimator.md ("Estimates") say, whatever the family."""
    assert msg.model_id == model_id and 0 < msg.inference_time < 1.0
    assert list(msg.class_names) == ["jelly", "plasticine", "sand"]
    probabilities = np.array(msg.class_probabilities)
    assert len(probabilities) == len(msg.class_names) and (probabilities >= 0).all()
    assert abs(probabilities.sum() - 1.0) < 1e-5  # float32 on the wire
    assert msg.material == msg.class_names[int(np.argmax(probabilities))]
    assert list(msg.parameter_names) == PARAMETER_NAMES
    assert len(msg.parameters) == len(msg.parameter_uncertainties) == len(PARAMETER_NAMES)
    for name, value, sigma in zip(msg.parameter_names, msg.parameters, msg.parameter_uncertainties):
        if name in FIXED.get(msg.material, {}):
            assert value == FIXED[msg.material][name] and sigma == 0.0, name  # fixed: exact, sigma 0
        elif name in USED[msg.material]:
            low, high = RANGES[name]  # SI; the friction angle in radians
            assert low * (1 - 1e-9) <= value <= high * (1 + 1e-9) and 0 < sigma < math.inf, (name, value, sigma)
        else:
            assert math.isnan(value) and math.isnan(sigma), name  # unused: NaN, and so is its sigma
    assert ns(msg.oldest_stamp) <= ns(msg.header.stamp)
    assert 1 <= msg.frames_used <= 25


def same_estimate(a: MaterialEstimate, b: MaterialEstimate) -> bool:
    """Equal in every field but the inference time; NaN equal to NaN (repr gives floats exactly)."""
    fields = [name for name in a.get_fields_and_field_types() if name != "inference_time"]
    return all(repr(getattr(a, name)) == repr(getattr(b, name)) for name in fields)


def test_a_planner_reads_every_field_of_an_estimate_as_documented(ros):
    """The bundled model's estimate of a streamed episode, and the service's of the same clip."""
    t = start(ros)
    masks = falling_masks(seed=3)
    for frame in frames_of(masks):
        t.publisher.publish(frame)
    assert wait_for(lambda: len(t.estimates) == 1)
    streamed = t.estimates[0]
    check_fields(streamed, t.node.info.model_id)
    assert ns(streamed.header.stamp) == T0 + 24 * DT and ns(streamed.oldest_stamp) == T0  # newest / oldest used
    assert streamed.header.frame_id == CAMERA and streamed.frames_used == 25 and streamed.complete
    response = clip(t, frames_of(masks))
    assert response.success and response.message == ""
    answered = response.estimate
    check_fields(answered, t.node.info.model_id)
    assert (answered.header, answered.oldest_stamp, answered.frames_used, answered.complete, answered.material) == (
        streamed.header, streamed.oldest_stamp, streamed.frames_used, streamed.complete, streamed.material)
    np.testing.assert_allclose(answered.class_probabilities, streamed.class_probabilities, rtol=1e-6)
    np.testing.assert_allclose(answered.parameters, streamed.parameters, rtol=1e-6)


def test_odd_clips_get_a_clear_answer_and_the_node_lives_on(ros):
    """Each odd clip is answered, an error as success false and a message naming the frame (the estimate is then
    an empty message); the stream still gets its estimate afterwards. Duplicate or unsorted stamps and a malformed
    stamp said neither which frame nor (a stamp) where."""
    t = start(ros)
    masks = falling_masks(30, seed=4)
    model_id = t.node.info.model_id

    def refused(frames, message):
        response = clip(t, frames)
        assert not response.success and response.message.startswith(message), response.message
        assert response.estimate == MaterialEstimate()  # nothing to read in it

    refused([], "empty clip: send at least one frame")
    one = clip(t, frames_of(masks[:1]))
    assert one.success and one.message.startswith("partial: 1 of the model's 25 frame slots filled from 1 frames")
    check_fields(one.estimate, model_id)
    assert one.estimate.frames_used == 1 and not one.estimate.complete
    assert ns(one.estimate.header.stamp) == ns(one.estimate.oldest_stamp) == T0
    longer = clip(t, frames_of(masks))  # 30 frames: those past the 25th slot are not used
    assert longer.success and longer.message == "" and longer.estimate.frames_used == 25
    assert ns(longer.estimate.header.stamp) == T0 + 24 * DT and longer.estimate.complete

    swapped = frames_of(masks[:25])
    swapped[3], swapped[4] = swapped[4], swapped[3]
    refused(swapped, "frame 4: stamp 1700000000.075000000 s is not after frame 3's (1700000000.100000000 s); clip "
                     "stamps must be strictly increasing")
    repeated = frames_of(masks[:25])
    repeated[4].header.stamp = repeated[3].header.stamp
    refused(repeated, "frame 4: stamp 1700000000.075000000 s is not after frame 3's (1700000000.075000000 s)")
    mixed = frames_of(masks[:25])
    mixed[10] = image_msg(falling_masks(1, size=64)[0], T0 + 10 * DT)
    refused(mixed, "frame 10: 64x64, frame 0: 128x128; clip frames must all have the same size")
    encoding = frames_of(masks[:25])
    encoding[12] = image_msg(masks[12].astype(np.float32), T0 + 12 * DT, encoding="32FC1")
    refused(encoding, "frame 12: unsupported encoding '32FC1'")
    malformed = frames_of(masks[:25])
    malformed[7].header.stamp.nanosec = 1_500_000_000
    refused(malformed, "frame 7: stamp nanosec 1500000000 is not below 1e9")

    unstamped = clip(t, frames_of(masks[:25], t0=0, step=0))  # all zero: frames on the model's interval
    assert unstamped.success and unstamped.estimate.frames_used == 25 and unstamped.estimate.complete
    np.testing.assert_allclose(unstamped.estimate.class_probabilities, longer.estimate.class_probabilities, rtol=1e-6)

    many = falling_masks(MAX_CLIP_FRAMES, seed=5)
    started = time.monotonic()
    large = clip(t, frames_of(many))
    assert large.success and large.estimate.frames_used == 25 and time.monotonic() - started < 5
    check_fields(large.estimate, model_id)
    refused(frames_of(np.concatenate([many, many[:1]])), f"clip of {MAX_CLIP_FRAMES + 1} frames exceeds 1000")

    for frame in frames_of(masks[:25], t0=T0 + 100 * 10**9):  # the stream goes on
        t.publisher.publish(frame)
    assert wait_for(lambda: len(t.estimates) == 1) and t.estimates[0].frames_used == 25
    assert t.node.clip_server.is_alive() and t.node.worker.is_alive() and t.node.statistics()["errors"] == 0


def test_a_clip_of_equal_stamps_carries_them(ros, test_model):
    """Frames all stamped alike are spread on the model's interval for the slots only: the estimate's stamps are
    the frames' own. header.stamp was 0.6 s after every frame of the clip (a time no frame was taken at: a
    planner looking the camera up in tf then asked for the future), and 0.6 s for unstamped frames."""
    t = start(ros, test_model)
    masks = falling_masks(seed=6)
    for t0 in (T0, 0):
        response = clip(t, frames_of(masks, t0=t0, step=0))
        assert response.success and response.estimate.frames_used == 25
        assert ns(response.estimate.header.stamp) == ns(response.estimate.oldest_stamp) == t0


def test_a_clip_whose_first_frame_is_unstamped_gets_the_documented_partial_estimate(ros, test_model):
    """A first frame stamped 0 and the others with the clock: frames past the last slot are not used, so a partial
    estimate from frame 0 (as for any gap). It was refused with "gap_threshold must be a number of seconds up to
    1e+06", a parameter the caller never set."""
    t = start(ros, test_model)
    masks = falling_masks(seed=7)
    frames = frames_of(masks)
    frames[0].header.stamp.sec, frames[0].header.stamp.nanosec = 0, 0
    response = clip(t, frames)
    assert response.success, response.message
    assert response.message.startswith("partial: 2 of the model's 25 frame slots filled from 25 frames")
    assert ns(response.estimate.header.stamp) == ns(response.estimate.oldest_stamp) == 0
    gapped = clip(t, [frames[0], image_msg(masks[1], 5 * 10**9, frame_id=CAMERA)])  # any gap gives the same slots
    assert same_estimate(response.estimate, gapped.estimate)


def test_frames_past_the_last_slot_neither_count_nor_fail_the_clip(ros, test_model):
    """A long clip whose object leaves the view after the 0.6 s the model reads: the estimate is that of its first
    25 frames. The empty mask of an unused frame failed the whole clip ("frame 40: no object pixel")."""
    t = start(ros, test_model)
    masks = falling_masks(60, seed=8)
    masks[40:] = 0
    response = clip(t, frames_of(masks))
    assert response.success, response.message
    first = clip(t, frames_of(masks[:26]))  # the 26th settles the last slot, as the frames after it
    assert same_estimate(response.estimate, first.estimate) and response.estimate.frames_used == 25
    broken = frames_of(masks)
    broken[10].data = bytes(3)  # a used frame is still checked
    response = clip(t, broken)
    assert not response.success and response.message.startswith("frame 10: data length 3 != step")


def test_a_clips_inference_time_is_the_models(ros, test_model, monkeypatch):
    """inference_time is the wall time in the model (MaterialEstimate.msg); the clip's took the images'
    conversion too (here slowed to 20 ms a frame)."""
    t = start(ros, test_model)
    convert = estimator_node.image_to_mask

    def slow(*args):
        time.sleep(0.02)
        return convert(*args)

    monkeypatch.setattr(estimator_node, "image_to_mask", slow)
    response = clip(t, frames_of(falling_masks(seed=9)))
    assert response.success and 0 < response.estimate.inference_time < 0.25, response.estimate.inference_time


def test_reset_forgets_the_episode_whose_estimate_was_being_computed(ros, test_model):
    """~/reset "forgets the current episode": the estimate of its last frame, which the worker was computing as the
    reset came, was published after the reply. Now none of the old episode goes out after it; the next episode
    gets its estimate."""
    t = start(ros, test_model)
    busy, release, encode = threading.Event(), threading.Event(), t.node.model.encode
    calls = []

    def held(*args):
        calls.append(1)
        if len(calls) == 25:  # the episode's last frame: its estimate would follow
            busy.set()
            release.wait(30)
        return encode(*args)

    t.node.model.encode = held
    for frame in frames_of(falling_masks(seed=10)):
        t.publisher.publish(frame)
    assert wait_for(busy.is_set)
    try:
        reply = call(t.reset, Trigger.Request(), timeout=2)
    finally:
        release.set()
    assert reply.success and reply.message.startswith("window reset:")
    assert wait_for(lambda: t.node.statistics()["processed"] == 25)
    time.sleep(0.3)
    assert t.estimates == []
    for frame in frames_of(falling_masks(seed=11), t0=T0 + 10**9):
        t.publisher.publish(frame)
    assert wait_for(lambda: len(t.estimates) == 1)
    assert ns(t.estimates[0].oldest_stamp) == T0 + 10**9 and t.estimates[0].frames_used == 25


def test_an_estimate_flushed_by_the_next_episode_keeps_its_cameras_frame_id(ros, test_model):
    """The anytime estimate of an episode that the next one's first frame (another camera's size) flushed out was
    labelled with that next frame's frame_id: header.frame_id is the camera of the frames used."""
    t = start(ros, test_model, output_policy="anytime", min_frames=5, every_n=100)
    for frame in frames_of(falling_masks(12, seed=12), frame_id="camera_a"):
        t.publisher.publish(frame)
    for frame in frames_of(falling_masks(25, size=96, seed=13), t0=T0 + 12 * DT, frame_id="camera_b"):
        t.publisher.publish(frame)
    assert wait_for(lambda: len(t.estimates) >= 2 and t.estimates[-1].complete)
    for msg in t.estimates:
        camera = "camera_a" if ns(msg.oldest_stamp) < T0 + 12 * DT else "camera_b"
        assert msg.header.frame_id == camera, (ns(msg.oldest_stamp) - T0, msg.frames_used, msg.header.frame_id)
    assert [m.frames_used for m in t.estimates if m.header.frame_id == "camera_a"] == [5, 12]


def test_a_late_joining_subscriber_gets_only_the_estimates_after_it(ros, test_model):
    """/ad_estimator/estimate is reliable and volatile (SPEC 5 asks for reliable only): a subscriber that joins late
    gets no earlier estimate, and one asking for transient local durability (a latched topic) gets none at all,
    its QoS being incompatible (docs/estimator.md says so)."""
    t = start(ros, test_model)
    for frame in frames_of(falling_masks(seed=14)):
        t.publisher.publish(frame)
    assert wait_for(lambda: len(t.estimates) == 1)
    late = Node("late_planner", context=t.context)
    volatile, latched = [], []
    late.create_subscription(MaterialEstimate, "/ad_estimator/estimate", volatile.append, 10)
    late.create_subscription(MaterialEstimate, "/ad_estimator/estimate", latched.append,
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    t.executor.add_node(late)
    assert wait_for(lambda: t.node.publisher.get_subscription_count() >= 2)
    time.sleep(0.3)
    assert volatile == [] and latched == []
    for frame in frames_of(falling_masks(seed=15), t0=T0 + 10**9):
        t.publisher.publish(frame)
    assert wait_for(lambda: len(volatile) == 1)
    time.sleep(0.3)
    assert latched == [] and ns(volatile[0].oldest_stamp) == T0 + 10**9
