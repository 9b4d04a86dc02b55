"""sensor_msgs/Image (an rclpy message or a decoded bag message), or a NumPy mask of your own
(array_to_mask: no ROS), -> binary uint8 mask, or a clear refusal.

Pure numpy. Accepted encodings (pixel is "object" when above the threshold):
- mono8 / 8UC1: value > threshold (default 127; simulator masks are 0/255).
- mono16 / 16UC1: value > threshold * 257 (the same fraction of full scale), either endianness.
- rgb8 / bgr8 / rgba8 / bgra8 / 8UC3 / 8UC4: brightest colour channel > threshold (alpha ignored).
With threshold None the levels are kept instead (0..255; mono16 scaled down), for models that read
grey masks, each pixel's area coverage (ad.mask_levels "coverage", docs/architecture.md).
A NumPy array is read as the image of the same pixels: uint8 as mono8, uint16 as mono16, and bool
as True = object (any threshold). Anything else is refused, and so is a mask with no object pixel
(kind "empty"). The size check uses only header fields (height, width, step), so an oversized or
malformed image is refused before any buffer of ours is allocated.
"""
from __future__ import annotations

import numpy as np

# encoding -> (bytes per channel, channels, colour channels to look at)
ENCODINGS = {
    "mono8": (1, 1, 1), "8UC1": (1, 1, 1),
    "mono16": (2, 1, 1), "16UC1": (2, 1, 1),
    "rgb8": (1, 3, 3), "bgr8": (1, 3, 3), "8UC3": (1, 3, 3),
    "rgba8": (1, 4, 3), "bgra8": (1, 4, 3), "8UC4": (1, 4, 3),
}
DEFAULT_THRESHOLD = 127
MAX_IMAGE_PIXELS = 4096 * 4096  # default bound; larger images are rejected from their header


class ImageRejected(ValueError):
    """The image cannot be used; ``kind`` groups rejections for throttled logging and counters."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


def check_size(height: int, width: int, max_pixels: int) -> None:
    """Refuse an empty image, and one over max_pixels once letterboxed to a square."""
    if height <= 0 or width <= 0:
        raise ImageRejected("empty", f"empty image {width}x{height}")
    side = max(height, width)
    if side * side > max_pixels:  # a mask is letterboxed to a square before the model (model.as_simulator_mask)
        shape = f"image {width}x{height}" + ("" if height == width else f" (letterboxed to {side}x{side})")
        raise ImageRejected("too_large", f"{shape} exceeds max_image_pixels={max_pixels}")


def check_header(height: int, width: int, encoding: str, step: int, max_pixels: int) -> tuple[int, int]:
    """Validate header fields only; returns (bytes per channel, channels)."""
    check_size(height, width, max_pixels)
    if encoding not in ENCODINGS:
        raise ImageRejected("encoding", f"unsupported encoding {encoding!r}; send a mask as mono8 "
                                        f"(accepted: {', '.join(ENCODINGS)})")
    depth, channels, _ = ENCODINGS[encoding]
    if step < width * depth * channels:
        raise ImageRejected("malformed", f"step {step} < width {width} * {depth * channels} bytes per pixel")
    return depth, channels


def image_to_mask(msg, max_pixels: int, threshold: int | None = DEFAULT_THRESHOLD) -> np.ndarray:
    """(height, width) uint8 mask in {0, 255} from an Image-like ``msg`` (threshold None: its levels,
    0..255); ImageRejected if unusable."""
    height, width, step, encoding = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding)
    depth, channels = check_header(height, width, encoding, step, max_pixels)
    try:
        data = np.frombuffer(msg.data, np.uint8)
    except (TypeError, ValueError):
        data = np.asarray(msg.data, np.uint8)  # e.g. a list of ints from a hand-made message
    if data.size != step * height:
        raise ImageRejected("malformed", f"data length {data.size} != step {step} * height {height}")
    rows = data.reshape(height, step)[:, : width * depth * channels]
    if depth == 2:
        dtype = ">u2" if msg.is_bigendian else "<u2"
        pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    elif channels == 1:
        pixels = rows
    else:
        pixels = rows.reshape(height, width, channels)[:, :, : ENCODINGS[encoding][2]].max(axis=2)
    return _pixels_to_mask(pixels, threshold, f"{encoding} mask")


def array_to_mask(array: np.ndarray, max_pixels: int = MAX_IMAGE_PIXELS,
                  threshold: int | None = DEFAULT_THRESHOLD) -> np.ndarray:
    """A NumPy mask (height, width) of your own camera -> what image_to_mask gives for an image of the
    same pixels, so the node's input rules hold without ROS: uint8 is read as mono8 (pixel > threshold is
    object), uint16 as mono16 (> threshold * 257), bool as True = object. Give it ``threshold`` =
    ``model.info.input_threshold()`` (None, the levels, for a model of grey masks). Always a new array:
    the window keeps the frames it is offered, so a buffer you overwrite would change them.

    ImageRejected (a ValueError) saying what was expected for another dtype (float: threshold it
    yourself, e.g. ``probabilities > 0.5``), another shape (a batch or channel axis), a mask larger
    than ``max_pixels`` once letterboxed to a square, and a mask with no object pixel (the object is
    lost: skip the frame, as the node does)."""
    array = np.asarray(array)
    if array.ndim != 2:
        raise ImageRejected("malformed", f"a mask is one 2-D (height, width) array, got shape {array.shape}: pass "
                                         "frames one at a time, without a batch or channel axis")
    if array.dtype != bool and (array.dtype.kind != "u" or array.dtype.itemsize > 2):
        raise ImageRejected("encoding", f"a mask array is uint8 (read as mono8), uint16 (as mono16) or bool, got "
                                        f"{array.dtype}; threshold a float mask yourself (e.g. probabilities > 0.5)")
    check_size(*array.shape, max_pixels)
    if array.dtype == bool:  # True is object whatever the threshold
        if not array.any():
            raise ImageRejected("empty", "no object pixel (True) in this bool mask")
        return array.astype(np.uint8) * np.uint8(255)
    # its own argument is `threshold` (the node's parameter is mask_threshold), and a 0/1 mask can come as bool
    return _pixels_to_mask(array, threshold, f"{array.dtype} mask", "threshold",
                           "pass a 0/1 mask as bool, or threshold=0")


def _pixels_to_mask(pixels: np.ndarray, threshold: int | None, what: str, setting: str = "mask_threshold",
                    zero_one: str = "a 0/1 mask needs mask_threshold 0") -> np.ndarray:
    """(height, width) uint8 or uint16 pixels -> a new uint8 mask: {0, 255} by the threshold (scaled by
    257 for 16 bit), or the levels 0..255 for threshold None. A refusal names the threshold as `setting`
    and says what a 0/1 mask needs (`zero_one`)."""
    wide = pixels.dtype.itemsize == 2
    if threshold is None:
        mask = (pixels // 257).astype(np.uint8) if wide else np.array(pixels, np.uint8)
    else:
        mask = (pixels > (threshold * 257 if wide else threshold)).astype(np.uint8) * np.uint8(255)
    if not mask.any():  # no object: an estimate from it would be made of nothing
        brightest = int(pixels.max())
        above = "" if threshold is None else f" above {setting} {threshold}" + (
            f" (its brightest pixel is {brightest}; {zero_one})" if brightest else "")
        raise ImageRejected("empty", f"no object pixel in this {what}{above}")
    return mask
