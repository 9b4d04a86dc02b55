"""Export a student checkpoint to ONNX with the metadata of docs/architecture.md.

streaming: <name>.frame.onnx (frame (B,C,H,W) -> embedding (B,D); channels after the first hold
the earlier observed masks, newest first, see ad.frame_inputs) and <name>.onnx (embeddings
(B,T,D), valid (B,T) -> logits, params, params_logvar). clip: <name>.onnx (masks (B,T,H,W),
valid (B,T) -> the same outputs). T is the frame count, 25: the estimator gives unobserved slots
zeros with valid 0.
"""
from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from ad_sim.materials import (
    FAMILIES,
    FAMILY_PARAMETERS,
    FIXED_PARAMETERS,
    FRAME_COUNT,
    FRAME_INTERVAL,
    PARAMETER_NAMES,
    PARAMETER_RANGES,
)
from ad_estimator.cli import seed, staged
from ad_estimator.model import frame_inputs
from training.engine import weights_digest
from training.evaluate import metrics_path
from training.models.student import frame_channels, frame_encoder_input
from training.train_student import load_student

OUTPUTS = ["logits", "params", "params_logvar"]
OPSET = 17


class _Outputs(nn.Module):
    """Wraps a head so the graph returns the three contract outputs as a tuple."""

    def __init__(self, head: nn.Module):
        super().__init__()
        self.head = head

    def forward(self, x: torch.Tensor, valid: torch.Tensor):
        out = self.head(x, valid)
        return out["logits"], out["params"], out["params_logvar"]


def metadata(model_id: str, kind: str, input_size, extra: dict | None = None) -> dict[str, str]:
    meta = {
        "ad.model_id": model_id,
        "ad.kind": kind,
        "ad.class_names": json.dumps(list(FAMILIES)),
        "ad.parameter_names": json.dumps(list(PARAMETER_NAMES)),
        "ad.parameter_ranges": json.dumps({n: list(PARAMETER_RANGES[n]) for n in PARAMETER_NAMES}),
        "ad.family_parameters": json.dumps({f: list(FAMILY_PARAMETERS[f]) for f in FAMILIES}),
        "ad.fixed_parameters": json.dumps({f: FIXED_PARAMETERS[f] for f in FAMILIES}),
        "ad.frame_interval": repr(FRAME_INTERVAL),
        "ad.frame_count": str(FRAME_COUNT),
        "ad.input_size": json.dumps(list(input_size)),
    }
    meta.update(extra or {})
    return meta


def _attach(path: Path, meta: dict[str, str]) -> None:
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _export(module: nn.Module, args: tuple, path: Path, inputs: list[str], outputs: list[str], dynamic: dict) -> None:
    # The TorchScript exporter (no onnxscript dependency) warns about its own deprecation and about
    # Python control flow on shapes that is constant by design (the clip graph takes 25 frames).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=DeprecationWarning)
        warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
        _torch_export(module, args, path, inputs, outputs, dynamic)


def _torch_export(module, args, path, inputs, outputs, dynamic) -> None:
    torch.onnx.export(module, args, str(path), input_names=inputs, output_names=outputs, dynamic_axes=dynamic,
                      opset_version=OPSET, dynamo=False, do_constant_folding=True)


def frame_encoder_path(onnx_path: Path) -> Path:
    """<name>.frame.onnx beside a streaming student's <name>.onnx."""
    return onnx_path.with_name(onnx_path.stem + ".frame.onnx")


def _check_out(checkpoint: str | Path, out: Path) -> None:
    """Refuses, before anything is written, an `out` that is a folder or whose files would overwrite the
    checkpoint (the ONNX, its frame encoder or its metrics JSON written over the only copy of the weights)."""
    if out.is_dir():  # before anything is written: a streaming student's frame encoder would land beside it
        raise ValueError(f"--out {out} is a folder; give the model's file name, e.g. {out / 'student.onnx'}")
    source = Path(checkpoint).resolve()
    for path in (out, frame_encoder_path(out), metrics_path(out)):
        if path.resolve() == source:
            raise ValueError(f"--out {out} would write {path}, which is the checkpoint {checkpoint}; give the "
                             f"model's own file name, e.g. {out.with_name('student.onnx')}")


def export_student(checkpoint: str | Path, out: str | Path, model_id: str | None = None) -> list[Path]:
    """Writes the ONNX file(s) for a student checkpoint; `out` is <name>.onnx. Returns the paths."""
    out = Path(out)
    _check_out(checkpoint, out)
    model, meta = load_student(checkpoint)
    return _write(model, meta, checkpoint, out, model_id)


def export_verified(checkpoint: str | Path, out: str | Path, model_id: str | None = None,
                    seed: int = 0) -> tuple[list[Path], float]:
    """export_student, then verify_export, in a staging folder in out's folder; the files (ONNX and metrics
    JSON) replace those at `out` only once they all verify. Returns the paths and the verification error.

    Why: written in place, a failed verification or a kill half way left a new frame encoder beside an old
    head (which `evaluate` scores without a word) or broken files over a good export."""
    out = Path(out)
    _check_out(checkpoint, out)
    model, meta = load_student(checkpoint)  # a bad checkpoint fails before any folder is made
    # Staged under their final names, so that the head's ad.frame_encoder finds its encoder when verified;
    # the head is moved in last (staged's `last`).
    with staged(out.parent, last=out.name) as folder:
        written = _write(model, meta, checkpoint, folder / out.name, model_id)
        try:
            error = verify_export(checkpoint, folder / out.name, seed)
        except Exception as exc:  # onnxruntime's errors (InvalidArgument, Fail, ...) share no base beyond Exception
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise ValueError(f"the ONNX export of {checkpoint} does not verify in onnxruntime ({first}); nothing "
                             f"was replaced in {out.parent}") from exc
    return [out.parent / path.name for path in written], error


def _write(model: nn.Module, meta: dict, checkpoint: str | Path, out: Path, model_id: str | None) -> list[Path]:
    """export_student's files for a loaded student: the ONNX file(s) and a fresh metrics JSON at `out`."""
    model = model.float().eval()
    config = model.config
    out.parent.mkdir(parents=True, exist_ok=True)
    digest = weights_digest(model)
    model_id = model_id or f"{out.stem}-{config.kind}-{meta.get('ablation', 'full')}-{digest[:8]}"
    h, w = config.input_size
    extra = {"ad.training": json.dumps({k: meta[k] for k in ("size", "ablation", "seed") if k in meta})}
    if config.mask_levels != "binary":  # absent means binary, so earlier estimators refuse nothing they can read
        extra["ad.mask_levels"] = config.mask_levels
    written = []
    with torch.no_grad():
        if config.kind == "streaming":
            frame_path = frame_encoder_path(out)
            channels = frame_channels(config)
            _export(model.frame_encoder, (torch.zeros(2, channels, h, w),), frame_path, ["frame"], ["embedding"],
                    {"frame": {0: "batch"}, "embedding": {0: "batch"}})
            d = config.embed_dim
            _export(_Outputs(model.temporal), (torch.zeros(2, FRAME_COUNT, d), torch.ones(2, FRAME_COUNT)), out,
                    ["embeddings", "valid"], OUTPUTS,
                    {"embeddings": {0: "batch", 1: "time"}, "valid": {0: "batch", 1: "time"},
                     **{o: {0: "batch"} for o in OUTPUTS}})
            extra.update({"ad.frame_encoder": frame_path.name, "ad.embedding_dim": str(d)})
            if config.previous_frames:  # what the channels hold, for the estimator's window
                extra["ad.frame_inputs"] = json.dumps(frame_inputs(config.previous_frames))
            meta_all = metadata(model_id, "streaming", (h, w), extra)
            _attach(frame_path, meta_all)
            written.append(frame_path)
        else:
            _export(_Outputs(model), (torch.zeros(2, FRAME_COUNT, h, w), torch.ones(2, FRAME_COUNT)), out,
                    ["masks", "valid"], OUTPUTS,
                    {"masks": {0: "batch"}, "valid": {0: "batch"}, **{o: {0: "batch"} for o in OUTPUTS}})
            meta_all = metadata(model_id, "clip", (h, w), extra)
        _attach(out, meta_all)
    written.append(out)
    # A fresh export starts a fresh metrics file; `evaluate` adds its results to it.
    history = Path(checkpoint).with_name("history.json")
    record = {"model": out.name, "model_id": model_id, "kind": config.kind, "training": meta,
              "final_epoch": json.loads(history.read_text())[-1] if history.exists() else None}
    metrics_path(out).write_text(json.dumps(record, indent=2))
    return written


def verify_export(checkpoint: str | Path, onnx_path: str | Path, seed: int = 0, atol: float = 1e-4) -> float:
    """Max |onnxruntime - torch| over the outputs on random masks; raises if above atol."""
    import onnxruntime as ort

    model, _ = load_student(checkpoint)
    model = model.float().eval()
    h, w = model.config.input_size
    rng = np.random.default_rng(seed)
    masks = (rng.random((2, FRAME_COUNT, h, w)) > 0.5).astype(np.float32)
    valid = np.ones((2, FRAME_COUNT), np.float32)
    valid[1, 17:] = 0.0
    masks[1, 17:] = 0.0
    with torch.no_grad():
        ref = model(torch.from_numpy(masks), torch.from_numpy(valid))
    onnx_path = Path(onnx_path)
    opts = ort.SessionOptions()
    opts.log_severity_level = 4  # fatal only: a failing run raises with the message its error log line repeats
    session = ort.InferenceSession(str(onnx_path), opts)
    if "embeddings" in {i.name for i in session.get_inputs()}:  # streaming: frame encoder + temporal head
        frame = ort.InferenceSession(str(frame_encoder_path(onnx_path)), opts)
        frames = frame_encoder_input(model.config, torch.from_numpy(masks), torch.from_numpy(valid)).numpy()
        emb = frame.run(None, {"frame": frames.reshape(2 * FRAME_COUNT, -1, h, w)})[0].reshape(2, FRAME_COUNT, -1)
        got = session.run(OUTPUTS, {"embeddings": emb, "valid": valid})
    else:
        got = session.run(OUTPUTS, {"masks": masks, "valid": valid})
    err = max(float(np.abs(g - ref[name].numpy()).max()) for g, name in zip(got, OUTPUTS))
    if err > atol:
        raise RuntimeError(f"ONNX export of {checkpoint} differs from torch by {err:.2e} (> {atol})")
    return err


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training export")
    p.description = ("Export a student checkpoint to ONNX with the estimator's metadata (streaming students: "
                     "<name>.frame.onnx + <name>.onnx), then check onnxruntime against torch.")
    p.add_argument("--checkpoint", required=True, help="student checkpoint (best.pt or last.pt)")
    p.add_argument("--out", required=True, help="output <name>.onnx")
    p.add_argument("--model-id", help="ad.model_id (default: <name>-<kind>-<ablation>-<weights hash>)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the verification input")
    return p


def run(args) -> list[Path]:
    paths, err = export_verified(args.checkpoint, args.out, args.model_id, args.seed)
    print(f"exported {', '.join(map(str, paths))}; onnxruntime vs torch max error {err:.2e}")
    return paths
