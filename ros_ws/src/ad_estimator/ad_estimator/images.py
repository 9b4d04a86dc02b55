"""sensor_msgs/Image (an rclpy message or a decoded bag message) -> binary uint8 mask, or a clear refusal.

Pure numpy. Accepted encodings (pixel is "object" when above the threshold):
- mono8 / 8UC1: value > threshold (default 127; simulator masks are 0/255).
- mono16 / 16UC1: value > threshold * 257 (the same fraction of full scale), either endianness.
- rgb8 / bgr8 / rgba8 / bgra8 / 8UC3 / 8UC4: brightest colour channel > threshold (alpha ignored).
With threshold None the levels are kept instead (0..255; mono16 scaled down), for models that read
grey masks, each pixel's area coverage (ad.mask_levels "coverage", docs/architecture.md).
Anything else is refused, and so is a mask with no object pixel (kind "empty"). The size check uses only header fields (height, width, step), so an
oversized or malformed image is refused before any buffer of ours is allocated.
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


def check_header(height: int, width: int, encoding: str, step: int, max_pixels: int) -> tuple[int, int]:
    """Validate header fields only; returns (bytes per channel, channels)."""
    if height <= 0 or width <= 0:
        raise ImageRejected("empty", f"empty image {width}x{height}")
    side = max(height, width)
    if side * side > max_pixels:  # a mask is letterboxed to a square before the model (model.as_simulator_mask)
        shape = f"image {width}x{height}" + ("" if height == width else f" (letterboxed to {side}x{side})")
        raise ImageRejected("too_large", f"{shape} exceeds max_image_pixels={max_pixels}")
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
        limit = None if threshold is None else threshold * 257
    elif channels == 1:
        pixels, limit = rows, threshold
    else:
        pixels = rows.reshape(height, width, channels)[:, :, : ENCODINGS[encoding][2]].max(axis=2)
        limit = threshold
    if threshold is None:
        mask = (pixels // 257).astype(np.uint8) if depth == 2 else np.array(pixels, np.uint8)
    else:
        mask = (pixels > limit).astype(np.uint8) * np.uint8(255)
    if not mask.any():  # no object: an estimate from it would be made of nothing
        brightest = int(pixels.max())
        above = "" if threshold is None else f" above mask_threshold {threshold}" + (
            f" (its brightest pixel is {brightest}; a 0/1 mask needs mask_threshold 0)" if brightest else "")
        raise ImageRejected("empty", f"no object pixel in this {encoding} mask{above}")
    return mask
