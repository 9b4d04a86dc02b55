"""ONNX export: onnxruntime matches torch, the metadata contract is complete, and the
estimator's own wrapper (ad_estimator.model) runs the exported files."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import onnx
import pytest
import torch

from ad_estimator.model import REQUIRED_METADATA, EstimatorModel
from ad_estimator.window import clip_output
from ad_sim.materials import FAMILIES, PARAMETER_NAMES, denormalise
from training import engine
from training.data import resize_masks
from training.export import export_student, verify_export
from training.models.student import build_student, frame_encoder_input, student_preset


# A streaming student whose frame encoder also sees N earlier frames is named streaming_previous_N.
KINDS = ["streaming", "streaming_previous_1", "streaming_previous_3", "uniformer"]


def _previous_frames(kind: str) -> int:
    return int(kind.partition("_previous_")[2] or 0)


def _checkpoint(tmp_path, kind: str):
    torch.manual_seed(0)
    config = student_preset(kind.partition("_previous_")[0], "tiny", z_dim=32)
    config = dataclasses.replace(config, previous_frames=_previous_frames(kind))
    model = build_student(config)
    # Non-trivial BatchNorm statistics, so that eval-mode export is really checked.
    model.train()
    with torch.no_grad():
        model(torch.rand(4, 25, *config.input_size), torch.ones(4, 25))
    path = tmp_path / f"{kind}.pt"
    engine.save_checkpoint(path, {"model": model.state_dict(), "epoch": 1,
                                  "meta": {"config": config.to_dict(), "size": "tiny", "ablation": "full", "seed": 0}})
    return path, model.eval()


@pytest.mark.parametrize("kind", KINDS)
def test_onnxruntime_matches_torch_and_metadata_is_complete(tmp_path, kind):
    ckpt, _ = _checkpoint(tmp_path, kind)
    out = tmp_path / "m" / "student.onnx"
    paths = export_student(ckpt, out)
    assert verify_export(ckpt, out, atol=1e-4) < 1e-4
    streaming = kind.startswith("streaming")
    expected_files = [out.with_name("student.frame.onnx"), out] if streaming else [out]
    assert paths == expected_files
    for path in paths:
        meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
        assert set(REQUIRED_METADATA) <= set(meta)
        assert meta["ad.kind"] == ("streaming" if streaming else "clip")
        assert json.loads(meta["ad.class_names"]) == list(FAMILIES)
        assert json.loads(meta["ad.parameter_names"]) == list(PARAMETER_NAMES)
        assert json.loads(meta["ad.input_size"]) == [32, 32]
        assert meta["ad.frame_count"] == "25" and float(meta["ad.frame_interval"]) == 0.025
        assert json.loads(meta["ad.fixed_parameters"])["sand"] == {"youngs_modulus": 1e5, "poissons_ratio": 0.3}
        if streaming:
            assert meta["ad.frame_encoder"] == "student.frame.onnx"
        previous = _previous_frames(kind)
        assert ("ad.frame_inputs" in meta) == bool(previous)
        if previous:
            assert json.loads(meta["ad.frame_inputs"]) == ["mask", "previous_mask", "previous_mask_2",
                                                           "previous_mask_3"][:previous + 1]


@pytest.mark.parametrize("kind", KINDS)
def test_estimator_wrapper_runs_the_export_like_torch(tmp_path, kind):
    """What the robot runs (resize, per-frame features on the window's slots, padded window) equals
    the torch model, also with a dropped frame (an encoder of earlier frames then sees the frames
    before the gap, as in training)."""
    ckpt, model = _checkpoint(tmp_path, kind)
    out = tmp_path / "student.onnx"
    export_student(ckpt, out)
    estimator = EstimatorModel.load(out)
    streaming = kind.startswith("streaming")
    rng = np.random.default_rng(1)
    masks = np.zeros((25, 128, 128), np.uint8)
    for t in range(25):  # a blob that falls and flattens
        masks[t, 20 + 3 * t: 50 + 3 * t - t // 2, 40 - t: 80 + t] = 255
    masks[rng.random(masks.shape) < 0.01] = 255
    stamps = [t * 25_000_000 for t in range(25)]
    for k, dropped in ((25, None), (15, None), (25, 7)):
        kept = [t for t in range(k) if t != dropped]
        out = clip_output([stamps[t] for t in kept], [masks[t] for t in kept], estimator.encode, 0.025, 25,
                         slot_tolerance=0.4, history=estimator.info.previous_frames)  # a dropped frame leaves its slot empty
        est = estimator.predict(out.features, out.valid)
        x = torch.zeros(1, 25, 32, 32)
        valid = torch.zeros(1, 25)
        x[0, kept] = torch.from_numpy(resize_masks(masks[kept], (32, 32)))
        valid[0, kept] = 1
        with torch.no_grad():
            ref = model(x, valid)
            if streaming:  # each frame's embedding, from the earlier frames training gives it
                frames = frame_encoder_input(model.config, x, valid)[0, kept]
                np.testing.assert_allclose(out.features[kept], model.frame_encoder(frames).numpy(), atol=1e-4)
        np.testing.assert_allclose(est.probabilities, torch.softmax(ref["logits"][0], -1).numpy(), atol=1e-4)
        expected = [denormalise(n, float(ref["params"][0, i].clamp(0, 1))) for i, n in enumerate(PARAMETER_NAMES)]
        np.testing.assert_allclose(est.raw_parameters, expected, rtol=1e-3)
        assert est.frames_used == len(kept) and out.valid.sum() == len(kept)
