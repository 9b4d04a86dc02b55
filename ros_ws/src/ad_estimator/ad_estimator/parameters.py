"""The estimator's parameters: one table of name -> (default, description), their checks, and the
frame window they configure for a model. ROS-free, so that the node (where each is a ROS parameter)
and the offline `estimate` (where the window's and images' ones are options) share one definition."""
from __future__ import annotations

from ad_estimator.images import DEFAULT_THRESHOLD, MAX_IMAGE_PIXELS
from ad_estimator.window import (DEFAULT_EVERY_N, DEFAULT_GAP_THRESHOLD, DEFAULT_MIN_FRAMES, DEFAULT_SLOT_TOLERANCE,
                                 MAX_SECONDS, FrameWindow)
from ad_sim import messages

DEFAULT_INPUT_TOPIC = messages.mask_topic(0)  # the simulator's first camera: what the node reads unless remapped
MIN_DIAGNOSTICS_PERIOD = 0.01  # s; shorter is a busy loop of /diagnostics
MAX_THREADS = 256
MAX_INPUT_DEPTH = 1_000_000  # frames: 40,000 episodes; rclpy itself fails past 2^31 - 1
# Frames waiting for the worker: 25 s of a 40 fps camera (40 episodes). A frame waits there whole (up to
# max_image_pixels each), so a longer queue only holds memory and estimates minutes late; it grew without bound.
MAX_QUEUE_SIZE = 1000
DEFAULT_IDLE_FLUSH = 0.3  # s; replayed and simulated streams pause > 0.5 s between episodes, frames 0.025 s apart
# name -> (default, description); every knob of the node is a ROS parameter.
PARAMETERS = {
    "model_path": ("", "ONNX model (temporal head for streaming models); empty: the bundled default"),
    "threads": (1, "onnxruntime intra-op threads (1 keeps latency low on a 2-core robot CPU)"),
    "execution_provider": ("cpu", "onnxruntime execution provider: cpu, or cuda (needs onnxruntime-gpu)"),
    "reliable": (False, "input QoS: reliable instead of sensor-data best effort"),
    "input_depth": (25, "input QoS history depth (a burst of one episode fits)"),
    "gap_threshold": (DEFAULT_GAP_THRESHOLD, "seconds of stamp gap that start a new episode"),
    "slot_tolerance": (DEFAULT_SLOT_TOLERANCE, "how far (in frame intervals) a frame may be from a slot time to fill it"),
    "output_policy": ("episode", "'episode': one estimate per episode, when all the model's frame slots (25 for the "
                                 "bundled model) are settled; a shorter episode gives none; every_n and min_frames "
                                 "do not apply. 'anytime': the first estimate when min_frames slots are settled, "
                                 "then one each time every_n more are, always one when the episode is complete, "
                                 "and one when input stops (idle_flush, or a new episode starts) if slots settled "
                                 "since the last estimate"),
    "every_n": (DEFAULT_EVERY_N, "anytime policy only: an estimate every N more frames after the first"),
    "min_frames": (DEFAULT_MIN_FRAMES, "anytime policy only: frames before the first estimate (capped at the model's "
                                       "frame count). From 15 frames on the bundled model is nearly as accurate as "
                                       "from 25; from fewer it is much less (temporal OOD in models/MODEL_CARD.md "
                                       "and the README)"),
    "max_image_pixels": (MAX_IMAGE_PIXELS, "images over this many pixels, counted as the square they are letterboxed to, are rejected from their header alone"),
    "mask_threshold": (DEFAULT_THRESHOLD, "pixel > threshold (of 255, scaled for 16 bit) is object "
                                          "(models of grey masks, ad.mask_levels coverage, read the levels instead)"),
    "queue_size": (64, f"frames waiting for the worker (at most {MAX_QUEUE_SIZE}); more are dropped and counted"),
    "idle_flush": (DEFAULT_IDLE_FLUSH, "seconds without input after which pending slots settle (0: never)"),
    "diagnostics_period": (1.0, "seconds between /diagnostics messages"),
}

# name -> (least, most): the numeric parameters' ranges, checked by check_parameters and given to ROS as the
# parameters' descriptors' ranges (`ros2 param describe`). The window checks gap_threshold and slot_tolerance.
RANGES = {
    "threads": (1, MAX_THREADS),
    "input_depth": (1, MAX_INPUT_DEPTH),
    "queue_size": (1, MAX_QUEUE_SIZE),
    "every_n": (1, 2**31 - 1),
    "min_frames": (1, 2**31 - 1),
    "max_image_pixels": (1, 2**62),
    "mask_threshold": (0, 254),
    "idle_flush": (0.0, MAX_SECONDS),
    "diagnostics_period": (MIN_DIAGNOSTICS_PERIOD, MAX_SECONDS),
}

_COUNTS = ("queue_size", "threads", "max_image_pixels", "every_n", "min_frames", "input_depth")  # whole numbers >= 1


def check_parameters(values: dict) -> None:
    """ValueError naming what is wrong with the values given (any subset of PARAMETERS); the window
    checks its own (policy, counts, interval, tolerance) when it is made."""
    positive = [n for n in _COUNTS if n in values and values[n] < RANGES[n][0]]
    if positive:
        raise ValueError(f"{', '.join(positive)} must be positive")
    if "mask_threshold" in values and not _within("mask_threshold", values):
        raise ValueError(f"mask_threshold is a pixel value in 0..254 (of 255), got {values['mask_threshold']}")
    if "idle_flush" in values and not _within("idle_flush", values):
        raise ValueError(f"idle_flush is seconds in 0..{MAX_SECONDS:g} (0: never), got {values['idle_flush']}")
    if "diagnostics_period" in values and not _within("diagnostics_period", values):
        raise ValueError(f"diagnostics_period is seconds in [{MIN_DIAGNOSTICS_PERIOD:g}, {MAX_SECONDS:g}], got "
                         f"{values['diagnostics_period']}")
    for name in _COUNTS:
        most = RANGES[name][1]
        if name in values and values[name] > most:  # (threads:=100000 took minutes and 16 GB to load the model)
            raise ValueError(f"{name} must be at most {most}, got {values[name]}")


def _within(name: str, values: dict) -> bool:
    least, most = RANGES[name]
    return least <= values[name] <= most  # False for NaN


def model_window(values: dict, info) -> FrameWindow:
    """The node's window for a model (`info`: its ModelInfo): the model's frame interval, frame count
    and earlier frames; min_frames capped at the frame count. Parameters missing from `values` take
    the node's defaults (model_window({}, info) is the node's default window)."""
    values = {name: default for name, (default, _) in PARAMETERS.items()} | values
    return FrameWindow(info.frame_interval, info.frame_count, gap_threshold=values["gap_threshold"],
                       slot_tolerance=values["slot_tolerance"], policy=values["output_policy"],
                       every_n=values["every_n"], min_frames=min(values["min_frames"], info.frame_count),
                       history=info.previous_frames)
