"""The bundled student as an onnxruntime model: metadata, per-frame features, estimates in SI.

Follows docs/architecture.md "ONNX model metadata". Runtime dependencies: onnxruntime, numpy,
opencv (never torch). Two kinds of model:

- ``clip``: one graph, ``masks`` (B, T, H, W) + ``valid`` (B, T) -> logits, params, params_logvar.
  A frame's feature is the resized mask itself.
- ``streaming``: ``<name>.frame.onnx`` maps one frame to an embedding, ``<name>.onnx`` (the
  temporal head) maps the embeddings of a window to the outputs. A frame's feature is its
  embedding, so a new frame costs one frame encoding plus one run of the small head. A frame
  encoder may also take the episode's N earlier observed frames (``ad.frame_inputs``), stacked
  as channels after the frame, newest first.

Callers (node, evaluate, service, benchmark) all go ``encode`` per frame, keep the features on
the model's frame slots (``ad_estimator.window``), then ``predict``.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import onnxruntime as ort

from ad_sim.families import PARAMETER_UNITS, from_unit

from .images import DEFAULT_THRESHOLD

REQUIRED_METADATA = (
    "ad.model_id",
    "ad.class_names",
    "ad.parameter_names",
    "ad.parameter_ranges",
    "ad.family_parameters",
    "ad.fixed_parameters",
    "ad.frame_interval",
    "ad.frame_count",
    "ad.input_size",
    "ad.kind",
)
KINDS = ("clip", "streaming")
# What a mask pixel holds for the model (ad.mask_levels, default binary): 0/255, or the area coverage
# 0..255 of the simulator's 512x512 render (ad_sim.generate --coverage-masks).
MASK_LEVELS = ("binary", "coverage")
# The bundled default model, installed with the package (package data, found next to this module).
BUNDLED_MODEL = Path(__file__).resolve().parent / "models" / "default.onnx"


class ModelError(ValueError):
    """The model file is missing, unreadable or does not follow the metadata contract."""


def frame_inputs(previous_frames: int) -> tuple[str, ...]:
    """``ad.frame_inputs`` of a streaming frame encoder that also sees ``previous_frames`` earlier
    observed frames: what its input channels hold, in order (absent from the metadata: the mask only)."""
    return ("mask", *(f"previous_mask_{k}" if k > 1 else "previous_mask" for k in range(1, previous_frames + 1)))


# The size of the simulator's masks (ad_sim.render.MASK_SIZE; a test keeps the two equal), the size
# every model was trained from.
SIMULATOR_MASK_SIZE = 128


def as_simulator_mask(mask: np.ndarray, coverage: bool = False) -> np.ndarray:
    """A binary mask (non-zero = object) of any size -> the 128x128 0/255 mask the simulator would
    have made of it from its 512x512 render (ad_sim.render.downsample): the area average, inside
    where at least half of the pixel is covered. A 128x128 mask is taken as it is. Without the
    threshold, a camera's full-resolution mask would reach the model with grey edges that it never
    saw in training. With `coverage` (models trained on grey masks, ad.mask_levels), `mask` holds
    levels 0..255 and the area average is kept as 0..255, rounded as the simulator rounds it. A mask
    that is not square is first centred on a square background (letterboxed): the simulator's
    cameras are square, and stretching would change the object's proportions, which is what the
    model reads materials from."""
    size = (SIMULATOR_MASK_SIZE, SIMULATOR_MASK_SIZE)
    if mask.shape == size:
        return mask
    height, width = mask.shape
    side = max(height, width)  # images.check_header bounds side * side by max_image_pixels
    inside = np.zeros((side, side), np.float32)
    top, left = (side - height) // 2, (side - width) // 2
    # the kernel counts non-zero pixels
    inside[top : top + height, left : left + width] = mask * np.float32(1 / 255) if coverage else mask != 0
    covered = cv2.resize(inside, size[::-1], interpolation=cv2.INTER_AREA)
    if coverage:
        return np.floor(covered * 255 + 0.5).astype(np.uint8)
    return np.where(covered >= 0.5, 255, 0).astype(np.uint8)


# The object's extent in an episode's first simulator mask (object_extent) over the 90 clips of the
# `small` seen split, whose cameras are drawn as training's are: 0.16 to 0.53 (median 0.31).
# Outside this range, a camera frames objects unlike any training clip (docs/estimator.md, "Images").
TRAINED_EXTENT = (0.15, 0.55)


def object_extent(mask: np.ndarray) -> float:
    """The object's larger side (height or width of its bounding box) in the simulator mask of
    `mask`, as a fraction of the image side; 0 without an object."""
    inside = as_simulator_mask(mask) > 127  # a grey (coverage) mask's edge pixels count from half covered
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if not len(rows):
        return 0.0
    return max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1) / SIMULATOR_MASK_SIZE


@dataclass(frozen=True)
class ParameterRange:
    """Sampling range of one parameter; the model predicts values normalised to [0, 1] over it."""

    low: float
    high: float
    scale: str  # "log" or "linear"

    def denormalise(self, u: np.ndarray) -> np.ndarray:
        # predictions outside the prior range are not plausible values
        return np.asarray(from_unit(np.clip(u, 0.0, 1.0), self.low, self.high, self.scale))

    def sigma(self, value: np.ndarray, sigma_u: np.ndarray) -> np.ndarray:
        """One-sigma in SI from one-sigma in normalised units (delta method, first order)."""
        if self.scale == "log":
            return value * (math.log(self.high) - math.log(self.low)) * sigma_u
        return (self.high - self.low) * sigma_u


@dataclass(frozen=True)
class ModelInfo:
    path: Path
    model_id: str
    kind: str
    class_names: tuple[str, ...]
    parameter_names: tuple[str, ...]
    parameter_ranges: dict[str, ParameterRange]
    family_parameters: dict[str, tuple[str, ...]]
    fixed_parameters: dict[str, dict[str, float]]
    frame_interval: float
    frame_count: int
    input_size: tuple[int, int]  # (H, W)
    frame_encoder: Path | None  # streaming models only
    frame_inputs: tuple[str, ...] = ("mask",)  # input channels of the frame encoder, see frame_inputs()
    mask_levels: str = "binary"  # binary: 0/255 masks; coverage: each pixel's area coverage, 0..255

    def input_threshold(self, mask_threshold: int = DEFAULT_THRESHOLD) -> int | None:
        """What images.image_to_mask is given for this model: the node's mask_threshold for a binary
        model, None (the levels themselves) for a coverage model."""
        return None if self.mask_levels == "coverage" else mask_threshold

    @property
    def previous_frames(self) -> int:
        """How many earlier observed frames of the episode the frame encoder sees besides the frame."""
        return len(self.frame_inputs) - 1


@dataclass
class Estimate:
    """One estimate. Parameters are SI; NaN where the predicted family does not use a parameter."""

    class_names: tuple[str, ...]
    probabilities: np.ndarray  # (C,)
    material: str
    parameter_names: tuple[str, ...]
    parameters: np.ndarray  # (P,) for `material`
    uncertainties: np.ndarray  # (P,) one sigma, SI; NaN where none
    raw_parameters: np.ndarray  # (P,) every head output denormalised, whatever the family
    raw_uncertainties: np.ndarray  # (P,)
    frames_used: int
    inference_time: float  # seconds spent in predict()

    def describe(self) -> str:
        """One line for logs: the family, its probability and its parameters (SI, with their units)."""
        used = ", ".join(f"{name} {value:.4g} {PARAMETER_UNITS.get(name, '')}".rstrip()
                         for name, value in zip(self.parameter_names, self.parameters) if not math.isnan(value))
        return f"{self.material} p={self.probabilities.max():.2f}; {used}"


def _json(meta: dict, key: str, path: Path):
    try:
        return json.loads(meta[key])
    except (json.JSONDecodeError, TypeError) as exc:
        raise ModelError(f"{path}: metadata {key!r} is not valid JSON ({exc}); re-export the model") from exc


def parse_metadata(meta: dict[str, str], path: Path) -> ModelInfo:
    """Validate the ``ad.*`` metadata of ``path``; ModelError names the file and what is wrong."""
    missing = [k for k in REQUIRED_METADATA if k not in meta]
    if missing:
        raise ModelError(
            f"{path}: ONNX metadata incomplete, missing {', '.join(missing)} "
            "(see docs/architecture.md 'ONNX model metadata'; re-export with python -m training export)")
    try:
        kind = meta["ad.kind"]
        if kind not in KINDS:
            raise ModelError(f"{path}: ad.kind is {kind!r}, expected one of {KINDS}")
        class_names = tuple(_json(meta, "ad.class_names", path))
        parameter_names = tuple(_json(meta, "ad.parameter_names", path))
        ranges = {}
        for name, spec in _json(meta, "ad.parameter_ranges", path).items():
            low, high, scale = spec
            if scale not in ("log", "linear") or not float(low) < float(high) or (scale == "log" and float(low) <= 0):
                raise ModelError(f"{path}: bad range for {name}: {spec}")
            ranges[name] = ParameterRange(float(low), float(high), scale)
        family_parameters = {f: tuple(v) for f, v in _json(meta, "ad.family_parameters", path).items()}
        fixed = {f: {k: float(v) for k, v in d.items()} for f, d in _json(meta, "ad.fixed_parameters", path).items()}
        input_size = tuple(int(v) for v in _json(meta, "ad.input_size", path))
        frame_interval = float(meta["ad.frame_interval"])
        frame_count = int(meta["ad.frame_count"])
    except ModelError:
        raise
    except (ValueError, TypeError, AttributeError) as exc:
        raise ModelError(f"{path}: malformed ad.* metadata ({exc}); re-export the model") from exc
    if missing_ranges := [n for n in parameter_names if n not in ranges]:
        raise ModelError(f"{path}: ad.parameter_ranges lacks {missing_ranges}")
    if unknown := [f for f in family_parameters if f not in class_names]:
        raise ModelError(f"{path}: ad.family_parameters names unknown families {unknown}")
    if len(input_size) != 2 or min(input_size) <= 0 or frame_count <= 0 or not 0 < frame_interval < math.inf:
        raise ModelError(f"{path}: bad input_size/frame_count/frame_interval metadata ({meta['ad.input_size']}, "
                         f"{meta['ad.frame_count']}, {meta['ad.frame_interval']}); re-export the model")
    frame_encoder = None
    inputs = frame_inputs(0)
    if kind == "streaming":
        if "ad.frame_encoder" not in meta:
            raise ModelError(f"{path}: streaming model without ad.frame_encoder metadata")
        frame_encoder = path.parent / meta["ad.frame_encoder"]
        if "ad.frame_inputs" in meta:
            listed = _json(meta, "ad.frame_inputs", path)
            inputs = tuple(listed) if isinstance(listed, list) else (listed,)
            if not inputs or inputs != frame_inputs(len(inputs) - 1):
                raise ModelError(f"{path}: ad.frame_inputs {list(inputs)} is not one this estimator knows "
                                 f"({list(frame_inputs(0))}, {list(frame_inputs(1))}, {list(frame_inputs(2))}, ...: "
                                 "the mask, then its earlier observed frames, newest first); "
                                 "update ad_estimator or re-export")
    mask_levels = meta.get("ad.mask_levels", "binary")
    if mask_levels not in MASK_LEVELS:
        raise ModelError(f"{path}: ad.mask_levels is {mask_levels!r}, expected one of {MASK_LEVELS}; update ad_estimator "
                         "or re-export")
    return ModelInfo(path, meta["ad.model_id"], kind, class_names, parameter_names, ranges, family_parameters,
                     fixed, frame_interval, frame_count, input_size, frame_encoder, inputs, mask_levels)


# Execution providers by short name. CPU is the robot's default: for a model this small, copying
# each frame to a GPU costs about what the whole CPU inference does.
PROVIDERS = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider"}


def _session(path: Path, threads: int, provider: str = "cpu") -> ort.InferenceSession:
    if provider not in PROVIDERS:
        raise ModelError(f"unknown execution provider {provider!r}; expected one of {sorted(PROVIDERS)}")
    if PROVIDERS[provider] not in ort.get_available_providers():
        raise ModelError(f"onnxruntime here has no {PROVIDERS[provider]} (available: {ort.get_available_providers()}); "
                         "install onnxruntime-gpu for cuda, or use provider cpu")
    if not path.is_file():
        problem = f"{path} is a folder, not a model file" if path.is_dir() else f"model file not found: {path}"
        raise ModelError(f"{problem} (set the model_path parameter / --model to an exported .onnx)")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=[PROVIDERS[provider]])
    except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
        hint = (f"; {path.name} looks like a training checkpoint: if it is a student's, export it first (python -m "
                f"training export --checkpoint {path} --out {path.with_suffix('.onnx')})") \
            if path.suffix in (".pt", ".pth") else ""
        raise ModelError(f"cannot load ONNX model {path}: {exc}{hint}") from exc


def _require_io(session: ort.InferenceSession, path: Path, inputs: tuple[str, ...], outputs: tuple[str, ...]):
    have_in = {i.name for i in session.get_inputs()}
    have_out = {o.name for o in session.get_outputs()}
    if not set(inputs) <= have_in or not set(outputs) <= have_out:
        raise ModelError(f"{path}: expected inputs {inputs} and outputs {outputs}, "
                         f"found inputs {sorted(have_in)} and outputs {sorted(have_out)}")


def _require_dims(session: ort.InferenceSession, path: Path, name: str, axes: tuple[int, ...],
                  expected: tuple[int, ...], key: str) -> None:
    """The input's static sizes at ``axes`` equal the metadata's (symbolic sizes are checked by the trial run)."""
    shape = next(i.shape for i in session.get_inputs() if i.name == name)
    if len(shape) <= max(axes) or any(isinstance(shape[a], int) and shape[a] != e for a, e in zip(axes, expected)):
        raise ModelError(f"{path}: input {name!r} has shape {shape}, which does not fit metadata {key} "
                         f"{list(expected)}; re-export the model")


def _require_slot_count(session: ort.InferenceSession, path: Path, features: str, frame_count: int) -> None:
    for name in (features, "valid"):  # both (B, T, ...)
        _require_dims(session, path, name, (1,), (frame_count,), "ad.frame_count")


def _quiet_run() -> ort.RunOptions:
    """For the trial run at load: its failure becomes a ModelError, without onnxruntime's own error log."""
    options = ort.RunOptions()
    options.log_severity_level = 4
    return options


def softmax(logits: np.ndarray) -> np.ndarray:
    z = np.exp(logits - logits.max())
    return z / z.sum()


class EstimatorModel:
    """An exported student. ``load`` it, ``encode`` frames, ``predict`` from a window of features."""

    def __init__(self, info: ModelInfo, session: ort.InferenceSession, frame_session: ort.InferenceSession | None):
        self.info = info
        self._session = session
        self._frame_session = frame_session
        self._has_logvar = "params_logvar" in {o.name for o in session.get_outputs()}
        self._outputs = ["logits", "params"] + (["params_logvar"] if self._has_logvar else [])
        self._recently_prepared: tuple[tuple[np.ndarray, np.ndarray], ...] = ()  # (mask, prepare(mask)), see _prepared
        h, w = info.input_size
        # A trial run at the metadata's sizes: graphs that do not fit their metadata fail here, at load, not on
        # the first frame; it is also the warm-up (the first onnxruntime call allocates).
        try:
            if frame_session is None:
                self.feature_shape: tuple[int, ...] = (h, w)
            else:
                frame = np.zeros((1, len(info.frame_inputs), h, w), np.float32)
                embedding = frame_session.run(["embedding"], {"frame": frame}, _quiet_run())[0]
                self.feature_shape = tuple(embedding.shape[1:])
            outputs = self._run(np.zeros((1, *self.feature_shape), np.float32), np.ones(1, bool), _quiet_run())
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises several unrelated types
            raise ModelError(f"{info.path}: a trial run at the metadata's input_size {list(info.input_size)} and "
                             f"frame_count {info.frame_count} failed, so the graph does not fit its ad.* metadata "
                             f"({' '.join(str(exc).split())}); re-export the model") from exc
        named_by = {"logits": ("ad.class_names", info.class_names), "params": ("ad.parameter_names", info.parameter_names),
                    "params_logvar": ("ad.parameter_names", info.parameter_names)}
        for name, output in zip(self._outputs, outputs):
            key, names = named_by[name]
            if output.shape[-1] != len(names):
                raise ModelError(f"{info.path}: output {name!r} has {output.shape[-1]} values but metadata {key} "
                                 f"names {len(names)} ({', '.join(names)}); re-export the model")
            if not np.isfinite(output).all():  # broken weights: every estimate would be NaN, published as valid
                raise ModelError(f"{info.path}: output {name!r} is not finite (NaN or inf) in the trial run, so its "
                                 "weights are broken; re-export the model from a checkpoint that trained")

    @classmethod
    def load(cls, path: str | Path, threads: int = 1, provider: str = "cpu") -> "EstimatorModel":
        """Open ``path`` (for streaming models the temporal head; its frame encoder is found via metadata)
        on the onnxruntime execution provider ``provider`` (a key of PROVIDERS).

        Raises ModelError naming the file when it is missing, corrupt, its metadata is incomplete or does
        not fit the graph (input size, frame count, number of classes and parameters).
        """
        path = Path(path)
        session = _session(path, threads, provider)
        info = parse_metadata(session.get_modelmeta().custom_metadata_map, path)
        if info.kind == "clip":
            _require_io(session, path, ("masks", "valid"), ("logits", "params"))
            _require_dims(session, path, "masks", (2, 3), info.input_size, "ad.input_size")
            _require_slot_count(session, path, "masks", info.frame_count)
            return cls(info, session, None)
        if {i.name for i in session.get_inputs()} == {"frame"}:
            raise ModelError(f"{path} is a frame encoder; pass the temporal head model "
                             f"({path.name.replace('.frame.onnx', '.onnx')}) instead")
        _require_io(session, path, ("embeddings", "valid"), ("logits", "params"))
        _require_slot_count(session, path, "embeddings", info.frame_count)
        if not info.frame_encoder.is_file():  # the head was copied without its encoder: say so, not "set --model"
            raise ModelError(f"{path} is a streaming model whose frame encoder {info.frame_encoder.name} (its "
                             f"ad.frame_encoder metadata) is missing from {path.parent}; copy the two files together")
        frame_session = _session(info.frame_encoder, threads, provider)
        _require_io(frame_session, info.frame_encoder, ("frame",), ("embedding",))
        _require_dims(frame_session, info.frame_encoder, "frame", (2, 3), info.input_size, "ad.input_size")
        shape = next(i.shape for i in frame_session.get_inputs() if i.name == "frame")
        channels = shape[1] if len(shape) == 4 else None  # (B, C, H, W); a symbolic C is not checked here
        if isinstance(channels, int) and channels != len(info.frame_inputs):
            raise ModelError(f"{info.frame_encoder} takes {channels} input channels, its metadata names "
                             f"{list(info.frame_inputs)}; re-export the model")
        return cls(info, session, frame_session)

    @property
    def model_id(self) -> str:
        return self.info.model_id

    def prepare(self, mask: np.ndarray) -> np.ndarray:
        """Binary uint8 mask (0/255, non-zero being object; levels 0..255 for a coverage model) of any size,
        as images.image_to_mask and images.array_to_mask make it -> float32 (H, W) in [0, 1] at the model's
        input size: first the simulator's mask (as_simulator_mask), then area interpolation, as training
        does. ValueError for anything but a 2-D uint8 array."""
        if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != np.uint8:
            # a bool or float 0..1 mask read as levels would give a plausible but wrong estimate
            raise ValueError(f"a frame is a 2-D uint8 mask, got {getattr(mask, 'dtype', type(mask).__name__)} of shape "
                             f"{np.shape(mask)}; make it with ad_estimator.images.array_to_mask")
        h, w = self.info.input_size
        coverage = self.info.mask_levels == "coverage"
        mask = as_simulator_mask(mask, coverage)
        if not coverage:  # non-zero is object, as at other sizes: a 128x128 0/1 mask was read as nearly empty
            mask = (mask != 0).astype(np.uint8) * np.uint8(255)
        if mask.shape != (h, w):
            mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA)
        return mask.astype(np.float32) * np.float32(1.0 / 255.0)

    def encode(self, mask: np.ndarray, earlier: Sequence[np.ndarray] = ()) -> np.ndarray:
        """Feature of one frame: the prepared mask (clip models) or its embedding (streaming models).

        ``mask``: see prepare; it must not change afterwards (a stream's recent frames are recognised as
        the same objects, so a reused buffer would be read as the frame it held first).
        ``earlier``: the episode's earlier observed masks, newest first (empty for its first frame);
        only the first ``info.previous_frames`` are read. Where fewer are given, the oldest one given
        (or the mask itself) stands in for the missing ones, as in training."""
        if isinstance(earlier, np.ndarray):  # one mask, as encode(mask, previous) once took, would pass as rows
            raise TypeError("earlier is a sequence of masks, newest first (e.g. [previous]), not one array")
        if self._frame_session is None:
            return self.prepare(mask)
        count = self.info.previous_frames
        masks = [mask, *earlier[:count]]
        masks += [masks[-1]] * (count + 1 - len(masks))
        frame = np.stack([self._prepared(m) for m in masks])[None]
        return self._frame_session.run(["embedding"], {"frame": frame})[0][0]

    def _prepared(self, mask: np.ndarray) -> np.ndarray:
        """prepare(), remembering the last ``previous_frames + 1`` masks (one encoding's): in a stream,
        a frame's earlier frames are the ones prepared just before, so each frame is resized once
        (masks are not changed once offered, which the window relies on too)."""
        recent = self._recently_prepared  # one read: the node's worker and service threads may both encode
        for seen, frame in recent:
            if seen is mask:
                return frame
        frame = self.prepare(mask)
        self._recently_prepared = (*recent, (mask, frame))[-(self.info.previous_frames + 1):]
        return frame

    def predict(self, features: np.ndarray, valid: np.ndarray) -> Estimate:
        """Estimate from per-slot features (T <= frame_count, oldest first) and their validity."""
        start = time.perf_counter()
        count = self.info.frame_count
        features = np.asarray(features, np.float32)
        valid = np.asarray(valid, bool)
        if features.shape[1:] != self.feature_shape or len(features) != len(valid) or not 0 < len(valid) <= count:
            raise ValueError(f"features {features.shape} / valid {valid.shape} do not fit the model "
                             f"(up to {count} slots of {self.feature_shape})")
        outputs = self._run(features, valid)
        if not all(np.isfinite(output).all() for output in outputs):  # never an estimate made of NaN
            raise ValueError(f"{self.info.path}: the model's outputs are not finite (NaN or inf) for these "
                             f"{int(valid.sum())} frames, so there is no estimate")
        logits, params = outputs[0][0], outputs[1][0]
        logvar = outputs[2][0] if self._has_logvar else None
        return self._estimate(logits, params, logvar, int(valid.sum()), time.perf_counter() - start)

    def _run(self, features: np.ndarray, valid: np.ndarray, options: ort.RunOptions | None = None) -> list[np.ndarray]:
        """The head's outputs for checked features: padded to frame_count slots, the unobserved ones invalid."""
        padded = np.zeros((1, self.info.frame_count, *self.feature_shape), np.float32)
        padded[0, : len(features)][valid] = features[valid]  # unobserved slots stay zero
        mask = np.zeros((1, self.info.frame_count), np.float32)
        mask[0, : len(valid)] = valid
        name = "masks" if self._frame_session is None else "embeddings"
        return self._session.run(self._outputs, {name: padded, "valid": mask}, options)

    def _estimate(self, logits, params, logvar, frames_used, elapsed) -> Estimate:
        info = self.info
        probabilities = softmax(logits.astype(np.float64))
        material = info.class_names[int(np.argmax(probabilities))]
        raw = np.empty(len(info.parameter_names))
        raw_sigma = np.full(len(info.parameter_names), np.nan)
        for i, name in enumerate(info.parameter_names):
            rng = info.parameter_ranges[name]
            raw[i] = rng.denormalise(float(params[i]))
            if logvar is not None:
                raw_sigma[i] = rng.sigma(raw[i], math.exp(0.5 * float(np.clip(logvar[i], -30.0, 30.0))))
        values, sigma = self.family_parameters(material, raw, raw_sigma)
        return Estimate(info.class_names, probabilities, material, info.parameter_names, values, sigma,
                        raw, raw_sigma, frames_used, elapsed)

    def family_parameters(self, family: str, raw: np.ndarray, raw_sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parameters (and sigmas) of ``family``: its fixed values exact, unused ones NaN."""
        used = self.info.family_parameters.get(family, ())
        fixed = self.info.fixed_parameters.get(family, {})
        values = np.full(len(raw), np.nan)
        sigma = np.full(len(raw), np.nan)
        for i, name in enumerate(self.info.parameter_names):
            if name in fixed:
                values[i], sigma[i] = fixed[name], 0.0
            elif name in used:
                values[i], sigma[i] = raw[i], raw_sigma[i]
        return values, sigma
