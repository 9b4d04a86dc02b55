"""Small ONNX models that follow the student contract (docs/architecture.md "ONNX model metadata").

A test double of the *model file* (not of the estimator): random-weight graphs built with
onnx.helper, no torch, whose outputs depend on every valid frame, on the slot order and on the
valid mask, so tests can tell when frames were placed or dropped wrongly.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from ad_estimator.model import frame_inputs

CLASS_NAMES = ["jelly", "plasticine", "sand"]
PARAMETER_NAMES = ["youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle"]
PARAMETER_RANGES = {
    "youngs_modulus": [1.5e4, 1.5e6, "log"],
    "poissons_ratio": [0.2, 0.48, "linear"],
    "yield_stress": [500.0, 25000.0, "log"],
    "friction_angle": [math.radians(10.0), math.radians(45.0), "linear"],
}
FAMILY_PARAMETERS = {
    "jelly": ["youngs_modulus", "poissons_ratio"],
    "plasticine": ["youngs_modulus", "poissons_ratio", "yield_stress"],
    "sand": ["youngs_modulus", "poissons_ratio", "friction_angle"],
}
FIXED_PARAMETERS = {"sand": {"youngs_modulus": 1.0e5, "poissons_ratio": 0.3}}
OPSET = [helper.make_opsetid("", 17)]


def metadata(kind: str, model_id: str, input_size, frame_count: int, frame_encoder: str | None) -> dict[str, str]:
    meta = {
        "ad.model_id": model_id,
        "ad.class_names": json.dumps(CLASS_NAMES),
        "ad.parameter_names": json.dumps(PARAMETER_NAMES),
        "ad.parameter_ranges": json.dumps(PARAMETER_RANGES),
        "ad.family_parameters": json.dumps(FAMILY_PARAMETERS),
        "ad.fixed_parameters": json.dumps(FIXED_PARAMETERS),
        "ad.frame_interval": "0.025",
        "ad.frame_count": str(frame_count),
        "ad.input_size": json.dumps(list(input_size)),
        "ad.kind": kind,
    }
    if frame_encoder:
        meta["ad.frame_encoder"] = frame_encoder
    return meta


def _save(graph, meta: dict[str, str], path: Path) -> None:
    model = helper.make_model(graph, opset_imports=OPSET, producer_name="tests.estimator_models")
    model.ir_version = 8
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _head_nodes(features: str, valid: str, frame_count: int, dim: int, rng, with_logvar: bool):
    """(B, T, D) features + (B, T) valid -> logits, params (sigmoid), params_logvar."""
    outputs = 3 + 4 + 4
    init = [
        numpy_helper.from_array(rng.uniform(0.5, 1.5, (1, frame_count, 1)).astype(np.float32), "time_weight"),
        numpy_helper.from_array(rng.normal(0, 1.0, (dim, outputs)).astype(np.float32), "w_head"),
        numpy_helper.from_array(rng.normal(0, 0.1, (outputs,)).astype(np.float32), "b_head"),
        numpy_helper.from_array(np.array([2], np.int64), "axis2"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
        numpy_helper.from_array(np.array([1e-6], np.float32), "eps"),
    ]
    nodes = [
        helper.make_node("Unsqueeze", [valid, "axis2"], ["valid3"]),
        helper.make_node("Mul", [features, "valid3"], ["masked"]),
        helper.make_node("Mul", ["masked", "time_weight"], ["weighted"]),
        helper.make_node("ReduceSum", ["weighted", "axis1"], ["summed"], keepdims=0),
        helper.make_node("ReduceSum", [valid, "axis1"], ["count"], keepdims=1),
        helper.make_node("Add", ["count", "eps"], ["count_eps"]),
        helper.make_node("Div", ["summed", "count_eps"], ["pooled"]),
        helper.make_node("MatMul", ["pooled", "w_head"], ["head_mm"]),
        helper.make_node("Add", ["head_mm", "b_head"], ["head"]),
        helper.make_node("Split", ["head", "split_sizes"], ["logits", "params_pre", "logvar_out"], axis=1),
        helper.make_node("Sigmoid", ["params_pre"], ["params"]),
    ]
    init.append(numpy_helper.from_array(np.array([3, 4, 4], np.int64), "split_sizes"))
    outs = [helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["B", 3]),
            helper.make_tensor_value_info("params", TensorProto.FLOAT, ["B", 4])]
    if with_logvar:
        nodes.append(helper.make_node("Identity", ["logvar_out"], ["params_logvar"]))
        outs.append(helper.make_tensor_value_info("params_logvar", TensorProto.FLOAT, ["B", 4]))
    return nodes, init, outs


def build_clip_model(path: Path, input_size=(32, 32), frame_count: int = 25, dim: int = 16, seed: int = 0,
                     model_id: str = "test-clip", with_logvar: bool = True, drop_metadata: tuple[str, ...] = ()) -> Path:
    """``masks`` (B, T, H, W) + ``valid`` (B, T) -> logits, params, params_logvar."""
    rng = np.random.default_rng(seed)
    h, w = input_size
    init = [
        numpy_helper.from_array(rng.normal(0, 4.0 / math.sqrt(h * w), (h * w, dim)).astype(np.float32), "w_frame"),
        numpy_helper.from_array(np.array([0, 0, h * w], np.int64), "flat_shape"),
    ]
    nodes = [
        helper.make_node("Reshape", ["masks", "flat_shape"], ["flat"]),
        helper.make_node("MatMul", ["flat", "w_frame"], ["frame_mm"]),
        helper.make_node("Tanh", ["frame_mm"], ["frame_features"]),
    ]
    head_nodes, head_init, outs = _head_nodes("frame_features", "valid", frame_count, dim, rng, with_logvar)
    graph = helper.make_graph(
        nodes + head_nodes, "clip_student",
        [helper.make_tensor_value_info("masks", TensorProto.FLOAT, ["B", frame_count, h, w]),
         helper.make_tensor_value_info("valid", TensorProto.FLOAT, ["B", frame_count])],
        outs, init + head_init)
    meta = metadata("clip", model_id, input_size, frame_count, None)
    for key in drop_metadata:
        meta.pop(key)
    _save(graph, meta, path)
    return path


def build_streaming_model(directory: Path, name: str = "student", input_size=(32, 32), frame_count: int = 25,
                          dim: int = 16, seed: int = 0, model_id: str = "test-streaming", previous_frames: int = 0,
                          mask_levels: str | None = None) -> Path:
    """``<name>.frame.onnx`` (frame -> embedding) and ``<name>.onnx`` (temporal head); returns the head's path.
    The frame encoder takes the mask and ``previous_frames`` earlier ones as channels. ``mask_levels``:
    ad.mask_levels to record ("coverage": a model of grey masks; None: none, which means binary)."""
    rng = np.random.default_rng(seed)
    h, w = input_size
    channels = 1 + previous_frames
    frame_file = f"{name}.frame.onnx"
    meta = metadata("streaming", model_id, input_size, frame_count, frame_file)
    if previous_frames:
        meta["ad.frame_inputs"] = json.dumps(frame_inputs(previous_frames))
    if mask_levels is not None:
        meta["ad.mask_levels"] = mask_levels
    encoder = helper.make_graph(
        [helper.make_node("Flatten", ["frame"], ["flat"], axis=1),
         helper.make_node("MatMul", ["flat", "w_frame"], ["frame_mm"]),
         helper.make_node("Tanh", ["frame_mm"], ["embedding"])],
        "frame_encoder",
        [helper.make_tensor_value_info("frame", TensorProto.FLOAT, ["B", channels, h, w])],
        [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["B", dim])],
        [numpy_helper.from_array(rng.normal(0, 4.0 / math.sqrt(h * w), (channels * h * w, dim)).astype(np.float32),
                                 "w_frame")])
    _save(encoder, meta, directory / frame_file)
    head_nodes, head_init, outs = _head_nodes("embeddings", "valid", frame_count, dim, rng, True)
    head = helper.make_graph(
        head_nodes, "temporal_head",
        [helper.make_tensor_value_info("embeddings", TensorProto.FLOAT, ["B", frame_count, dim]),
         helper.make_tensor_value_info("valid", TensorProto.FLOAT, ["B", frame_count])],
        outs, head_init)
    path = directory / f"{name}.onnx"
    _save(head, meta, path)
    return path


def falling_masks(count: int = 25, size: int = 128, seed: int = 0) -> np.ndarray:
    """(count, size, size) uint8 0/255: a disc falling and squashing, so frames differ."""
    rng = np.random.default_rng(seed)
    radius = size * rng.uniform(0.12, 0.2)
    cx = size * rng.uniform(0.35, 0.65)
    yy, xx = np.mgrid[0:size, 0:size]
    frames = np.zeros((count, size, size), np.uint8)
    for t in range(count):
        squash = 1.0 + 0.6 * max(0.0, t - count / 2) / count
        cy = min(size * 0.2 + 0.5 * 9.8 * (t * 0.025) ** 2 * size, size - radius / squash)
        inside = ((xx - cx) / (radius * squash)) ** 2 + ((yy - cy) * squash / radius) ** 2 <= 1.0
        frames[t][inside] = 255
    return frames
