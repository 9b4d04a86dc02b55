"""The estimator as a library in a Python process of one's own, without ROS (docs/estimator.md, "In your own
Python process, without ROS"): masks as NumPy arrays, stamps as integers, the bundled model."""
import inspect
import subprocess
import sys
import threading
import types
from pathlib import Path

import numpy as np
import pytest

from ad_estimator import estimate
from ad_estimator.images import DEFAULT_THRESHOLD, ImageRejected, array_to_mask, image_to_mask
from ad_estimator.model import BUNDLED_MODEL, EstimatorModel
from ad_estimator.parameters import DEFAULT_INPUT_TOPIC, PARAMETERS, model_window
from ad_estimator.window import clip_output
from ad_sim.rosbag import BagReader

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "bags" / "samples" / "unseen-masks-0of1"
T0 = 1_700_000_000_000_000_000
DT = 25_000_000


@pytest.fixture(scope="module")
def model():
    return EstimatorModel.load(BUNDLED_MODEL)


def camera(count=40, height=480, width=640):
    """The documented example's camera: (stamp ns, bool mask) of a 0.4 m ball falling at 40 fps, framed as training."""
    rows, cols = np.mgrid[:height, :width]
    px = width / 1.4
    for k in range(count):
        t = k * 0.025
        y = min(0.3 * height + 0.5 * 9.81 * t * t * px, height - 0.2 * px)
        yield T0 + k * DT, (rows - y) ** 2 + (cols - width / 2) ** 2 <= (0.2 * px) ** 2


def stream(model, frames, values=None):
    """The documented stream: array_to_mask, the node's window, encode, predict; (output, estimate) pairs."""
    window = model_window(values or {}, model.info)
    threshold = model.info.input_threshold()
    pairs = []
    for stamp, pixels in frames:
        for out in window.add(stamp, array_to_mask(pixels, threshold=threshold), model.encode):
            pairs.append((out, model.predict(out.features, out.valid)))
    pairs += [(out, model.predict(out.features, out.valid)) for out in window.flush()]
    return pairs


def sample_frames():
    """(stamp ns, the mono8 pixels as an array) of the sample bag's mask topic."""
    for message in BagReader(SAMPLE_BAG, topics=[DEFAULT_INPUT_TOPIC]):
        image = message.message
        assert image.encoding == "mono8"
        pixels = np.frombuffer(image.data, np.uint8).reshape(image.height, image.step)[:, :image.width]
        yield image.header.stamp.sec * 10**9 + image.header.stamp.nanosec, pixels


BLOCK_ROS_AND_TORCH = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {"rclpy", "torch", "sensor_msgs", "std_msgs", "builtin_interfaces", "ad_msgs"}:
            raise ImportError(f"{name} is not to be imported here")
sys.meta_path.insert(0, Block())
"""


def test_the_documented_example_runs_without_ros_nor_torch():
    """The example's code path in a process that cannot import rclpy, ROS messages nor torch, with only the two
    source folders on the path: estimates at 15, 20 and 25 frames, and the clip's equals the stream's."""
    code = BLOCK_ROS_AND_TORCH + f"import numpy as np\nT0, DT = {T0}, {DT}\n" + inspect.getsource(camera) + """
import numpy as np
from ad_estimator.images import array_to_mask
from ad_estimator.model import BUNDLED_MODEL, EstimatorModel
from ad_estimator.parameters import model_window
from ad_estimator.window import clip_output

model = EstimatorModel.load(BUNDLED_MODEL)
info = model.info
threshold = info.input_threshold()
window = model_window({"output_policy": "anytime"}, info)
estimates = []
for stamp_ns, pixels in camera():
    for out in window.add(stamp_ns, array_to_mask(pixels, threshold=threshold), model.encode):
        estimates.append((out.frames_used, out.complete, model.predict(out.features, out.valid)))
assert not window.flush()
stamps, frames = zip(*camera())  # 1 s: the clip's frames past the model's 0.6 s are not used
out = clip_output(stamps, frames, model.encode, info.frame_interval, info.frame_count,
                  history=info.previous_frames, convert=lambda pixels: array_to_mask(pixels, threshold=threshold))
clip = model.predict(out.features, out.valid)
assert (out.frames_used, out.complete, out.newest_stamp_ns, out.newest_frame) == (25, True, T0 + 24 * DT, 24)
assert [(n, c) for n, c, _ in estimates] == [(15, False), (20, False), (25, True)], estimates
assert np.array_equal(clip.probabilities, estimates[-1][2].probabilities)
assert np.array_equal(clip.parameters, estimates[-1][2].parameters, equal_nan=True)
print(sorted({"rclpy", "torch", "warp", "scipy"} & set(sys.modules)))
"""
    paths = [ROOT / "ros_ws" / "src" / "ad_estimator", ROOT / "ros_ws" / "src" / "ad_sim"]
    probe = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                           env={"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(map(str, paths))})
    assert probe.returncode == 0 and probe.stdout.strip() == "[]", probe.stdout + probe.stderr


def documented_example() -> str:
    """The Python example of docs/estimator.md, "In your own Python process, without ROS", as it is written."""
    section = (ROOT / "docs" / "estimator.md").read_text().split("## In your own Python process, without ROS\n")[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def test_the_documented_example_runs_as_written():
    """The example's own text (the test above runs a copy with assertions), without rclpy and torch: it prints the
    estimates at 15, 20 and 25 frames, then its whole 1 s clip's, which is the 25-frame one."""
    paths = [ROOT / "ros_ws" / "src" / "ad_estimator", ROOT / "ros_ws" / "src" / "ad_sim"]
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(map(str, paths))}
    probe = subprocess.run([sys.executable, "-c", BLOCK_ROS_AND_TORCH + documented_example()], capture_output=True,
                           text=True, timeout=120, env=env)
    assert probe.returncode == 0, probe.stdout + probe.stderr
    lines = probe.stdout.splitlines()
    assert [line.split(":")[0] for line in lines[:3]] == [
        "15 frames, complete False", "20 frames, complete False", "25 frames, complete True"], probe.stdout
    assert len(lines) == 4 and lines[2].split(": ", 1)[1].startswith(lines[3].split()[0]), probe.stdout


def test_the_library_gives_the_estimates_the_nodes_code_path_gives_for_a_bag(model):
    """A NumPy pipeline holding the sample bag's pixels gets exactly what `estimate` (the node's path from Image
    messages, which tests/test_replay.py checks against the node) writes for the bag."""
    values = {name: default for name, (default, _) in PARAMETERS.items()}
    rows = estimate.estimate_bag(model, SAMPLE_BAG, DEFAULT_INPUT_TOPIC, values)
    pairs = stream(model, sample_frames())
    assert len(rows) == len(pairs) >= 5
    for row, (out, est) in zip(rows, pairs):
        assert (out.episode, out.newest_stamp_ns, out.frames_used) == (row.output.episode, row.output.newest_stamp_ns,
                                                                       row.output.frames_used)
        assert est.material == row.estimate.material
        np.testing.assert_array_equal(est.probabilities, row.estimate.probabilities)
        np.testing.assert_array_equal(est.parameters, row.estimate.parameters)


def image(pixels: np.ndarray, encoding: str):
    """The sensor_msgs/Image of `pixels` (little-endian)."""
    return types.SimpleNamespace(height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
                                 step=pixels.shape[1] * pixels.itemsize, is_bigendian=False,
                                 data=np.ascontiguousarray(pixels).astype(pixels.dtype.newbyteorder("<")).tobytes())


@pytest.mark.parametrize("threshold", [DEFAULT_THRESHOLD, 0, 200, None])
def test_an_array_is_read_as_the_node_reads_the_image_of_its_pixels(threshold):
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 256, (48, 64)).astype(np.uint8)
    for pixels, encoding in ((levels, "mono8"), (levels.astype(np.uint16) * 257 + 3, "mono16")):
        expected = image_to_mask(image(pixels, encoding), 64 * 64, threshold)
        np.testing.assert_array_equal(array_to_mask(pixels, 64 * 64, threshold), expected)
        framed = np.zeros((60, 80), pixels.dtype)
        framed[6:54, 8:72] = pixels
        np.testing.assert_array_equal(array_to_mask(framed[6:54, 8:72], 64 * 64, threshold), expected)  # a view
        np.testing.assert_array_equal(array_to_mask(pixels.T, 64 * 64, threshold), expected.T)
    inside = levels > 100  # bool: True is object whatever the threshold, as a 0/255 mono8 image
    np.testing.assert_array_equal(array_to_mask(inside, threshold=threshold),
                                  image_to_mask(image(inside.astype(np.uint8) * np.uint8(255), "mono8"), 64 * 64,
                                                threshold))
    mask = array_to_mask(levels, threshold=threshold)
    assert mask.dtype == np.uint8 and not np.shares_memory(mask, levels)  # the window keeps it: never the caller's


@pytest.mark.parametrize("size", [(128, 128), (512, 512), (480, 640)])
def test_a_mask_that_is_not_a_0_255_uint8_one_is_read_alike_or_refused_at_every_size(model, size):
    """bool, 0/1 and float 0..1 masks of the simulator's own size reached the model as levels 1/255 of a 0/255
    mask (nearly empty: a confident estimate of another family), while at any other size non-zero was object."""
    rows, cols = np.mgrid[:size[0], :size[1]]
    inside = (rows - size[0] / 2) ** 2 + (cols - size[1] / 2) ** 2 <= (size[1] / 7) ** 2
    binary = inside.astype(np.uint8) * np.uint8(255)
    expected = model.encode(binary)
    np.testing.assert_array_equal(model.encode(inside.astype(np.uint8)), expected)  # 0/1: non-zero is object
    np.testing.assert_array_equal(model.encode(array_to_mask(inside)), expected)
    for other in (inside, inside.astype(np.float32), binary / 255.0, binary[None]):
        with pytest.raises(ValueError, match=r"a frame is a 2-D uint8 mask, got .* make it with "
                                             r"ad_estimator.images.array_to_mask"):
            model.encode(other)


@pytest.mark.parametrize("pixels, message", [
    (np.full((64, 64), 0.9), r"a mask array is uint8 \(read as mono8\), uint16 \(as mono16\) or bool, got float64; "
                             r"threshold a float mask yourself \(e.g. probabilities > 0.5\)"),
    (np.full((64, 64), np.nan, np.float32), "got float32"),
    (np.full((64, 64), 255, np.int64), "got int64"),
    (np.full((1, 64, 64), 255, np.uint8), r"a mask is one 2-D \(height, width\) array, got shape \(1, 64, 64\): pass "
                                          "frames one at a time, without a batch or channel axis"),
    (np.full((64, 64, 3), 255, np.uint8), r"got shape \(64, 64, 3\)"),
    # array_to_mask's own argument is `threshold` (mask_threshold is the node's parameter), and it does not apply
    # to a bool mask: the refusals named mask_threshold for both
    (np.zeros((64, 64), np.uint8), "no object pixel in this uint8 mask above threshold 127$"),
    (np.zeros((64, 64), bool), r"no object pixel \(True\) in this bool mask$"),
    (np.ones((64, 64), np.uint8), r"above threshold 127 \(its brightest pixel is 1; pass a 0/1 mask as bool, or "
                                  r"threshold=0\)$"),
    (np.full((64, 64), 1, np.uint16), r"in this uint16 mask above threshold 127 \(its brightest pixel is 1; pass a "
                                      r"0/1 mask as bool, or threshold=0\)$"),
    (np.ones((1, 5000), bool), r"image 5000x1 \(letterboxed to 5000x5000\) exceeds max_image_pixels=16777216"),
])
def test_an_array_the_node_would_not_take_is_refused_saying_what_was_expected(pixels, message):
    with pytest.raises(ImageRejected, match=message):
        array_to_mask(pixels)


def test_stamps_are_whole_nanoseconds_numpy_ones_included(model):
    """uint64 stamps (as numpy arrays of ns give them) wrapped around in the window's differences: every frame
    went "backwards" and restarted the episode, so no estimate at all; a float failed deep in the window."""
    frames = list(camera(25))
    expected = stream(model, frames)
    assert len(expected) == 1 and expected[0][0].complete
    for stamps in (np.array([s for s, _ in frames], np.uint64), np.array([s for s, _ in frames], np.int64)):
        got = stream(model, zip(stamps, (p for _, p in frames)))
        assert len(got) == 1 and got[0][0].newest_stamp_ns == expected[0][0].newest_stamp_ns
        np.testing.assert_array_equal(got[0][1].probabilities, expected[0][1].probabilities)
    window = model_window({}, model.info)
    with pytest.raises(TypeError, match=r"stamp_ns is a whole number of nanoseconds, got float 1.7e\+18; from "
                                        r"seconds: round\(t \* 1e9\)"):
        window.add(float(T0), array_to_mask(frames[0][1]), model.encode)


def test_model_window_takes_the_nodes_defaults_for_parameters_not_given(model):
    default = model_window({}, model.info)
    assert (default.policy, default.min_frames, default.gap_ns, default.history) == (
        "episode", model.info.frame_count, 300_000_000, model.info.previous_frames)
    anytime = model_window({"output_policy": "anytime", "every_n": 2}, model.info)
    assert (anytime.policy, anytime.min_frames, anytime.every_n) == ("anytime", 15, 2)


def test_one_model_serves_several_threads_each_with_its_own_window(model):
    """Streams of different clips in four threads at once, on one model (its recent frames' cache shared):
    each gets what it gets alone."""
    clips = [list(camera(25, 240 + 40 * i, 320)) for i in range(4)]
    alone = [stream(model, clip, {"output_policy": "anytime", "every_n": 1}) for clip in clips]
    together: dict[int, list] = {}
    threads = [threading.Thread(target=lambda i=i: together.__setitem__(
        i, [stream(model, clips[i], {"output_policy": "anytime", "every_n": 1}) for _ in range(3)])) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for i in range(4):
        for run in together[i]:
            assert len(run) == len(alone[i]) == 11
            for (_, got), (_, expected) in zip(run, alone[i]):
                np.testing.assert_array_equal(got.probabilities, expected.probabilities)


def test_clip_output_is_the_streams_complete_output(model):
    frames = list(camera(25))
    (out, expected), = stream(model, frames)
    threshold = model.info.input_threshold()
    clip = clip_output([s for s, _ in frames], [array_to_mask(p, threshold=threshold) for _, p in frames],
                       model.encode, model.info.frame_interval, model.info.frame_count,
                       history=model.info.previous_frames)
    np.testing.assert_array_equal(clip.features, out.features)
    assert model.predict(clip.features, clip.valid).material == expected.material
