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
from sim_fixtures import write_coverage_bag


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


def _set_mask_levels(path, value: str | None) -> None:
    """Sets (None: removes) ad.mask_levels in the model file at `path`."""
    model = onnx.load(str(path))
    kept = [p for p in model.metadata_props if p.key != "ad.mask_levels"]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    if value is not None:
        model.metadata_props.add(key="ad.mask_levels", value=value)
    onnx.save(model, str(path))


def _probabilities(csv_path) -> np.ndarray:
    import csv

    with open(csv_path, newline="") as f:
        return np.array([[float(r[f"p_{c}"]) for c in FAMILIES] for r in csv.DictReader(f)])


def test_a_student_of_grey_masks_exports_as_one_and_the_estimator_feeds_it_the_levels(tmp_path, capsys):
    """Grey masks end to end: `python -m training student --set mask_levels=coverage` trains on the bags'
    levels (the coverage cache), export records ad.mask_levels, and the estimator's offline runtime
    (estimate and evaluate, real onnxruntime) gives the model the levels, not thresholded masks: its
    estimates differ from the same model's on the thresholded bag, which the same weights marked binary
    reproduce exactly from the grey bag."""
    from ad_estimator import estimate, evaluate
    from training import data
    from training.__main__ import main

    grey_bag, _ = write_coverage_bag(tmp_path / "bags" / "grey", 6, views=1, seed=5)
    binary_bag, _ = write_coverage_bag(tmp_path / "bags_binary" / "binary", 6, views=1, seed=5, binary=True)
    cache, run = tmp_path / "cache", tmp_path / "run"
    assert main(["student", "--bags", str(grey_bag), "--cache", str(cache), "--out", str(run), "--size", "tiny",
                 "--epochs", "1", "--batch-size", "4", "--val-fraction", "0.2", "--device", "cpu", "--no-progress",
                 "--kind", "streaming", "--ablation", "none", "--set", "mask_levels=coverage"]) == 0
    assert sorted(p.name for p in cache.iterdir()) == [data.bag_key(grey_bag) + "-coverage"]  # trained on the levels
    assert torch.load(run / "best.pt", weights_only=True)["meta"]["config"]["mask_levels"] == "coverage"
    model_path = tmp_path / "grey" / "student.onnx"
    assert main(["export", "--checkpoint", str(run / "best.pt"), "--out", str(model_path)]) == 0
    for path in (model_path, model_path.with_name("student.frame.onnx")):
        meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
        assert meta["ad.mask_levels"] == "coverage", path
    info = EstimatorModel.load(model_path).info
    assert (info.mask_levels, info.input_threshold()) == ("coverage", None)
    # The same weights, marked binary (no ad.mask_levels, as every export before grey masks).
    twin = tmp_path / "twin" / "student.onnx"
    twin.parent.mkdir()
    for name in ("student.onnx", "student.frame.onnx"):
        (twin.parent / name).write_bytes((model_path.parent / name).read_bytes())
        _set_mask_levels(twin.parent / name, None)
    assert EstimatorModel.load(twin).info.mask_levels == "binary"

    def estimates(model, bag, name):
        assert estimate.main(["--model", str(model), "--quiet", str(bag), "--out", str(tmp_path / name)]) == 0
        return _probabilities(tmp_path / name)

    grey = estimates(model_path, grey_bag, "grey.csv")
    on_thresholded = estimates(model_path, binary_bag, "thresholded.csv")
    assert grey.shape == (6, 3)
    # (1 epoch: near-uniform probabilities, so the levels move them by ~1e-5; no episode gets the same)
    assert (np.abs(grey - on_thresholded).max(axis=1) > 1e-6).all(), "the coverage model was given thresholded masks"
    np.testing.assert_array_equal(estimates(twin, grey_bag, "twin.csv"), on_thresholded)
    # evaluate (the offline benchmark) and training's evaluate (from its coverage cache) read the levels too.
    assert evaluate.main(["--model", str(model_path), "--bags", str(grey_bag), "--quiet",
                          "--out", str(tmp_path / "ev")]) == 0
    evaluated = json.loads((tmp_path / "ev" / "predictions.json").read_text())["frames"]["25"]
    np.testing.assert_allclose([e["probabilities"] for e in evaluated], grey, rtol=1e-6)
    assert main(["evaluate", "--model", str(model_path), "--bags", str(grey_bag), "--cache", str(tmp_path / "cache2"),
                 "--out", str(tmp_path / "tev"), "--frames", "25", "--no-record", "--no-progress"]) == 0
    assert sorted(p.name for p in (tmp_path / "cache2").iterdir()) == [data.bag_key(grey_bag) + "-coverage"]
    trained = json.loads((tmp_path / "tev" / "predictions.json").read_text())["frames"]["25"]
    np.testing.assert_allclose([e["probabilities"] for e in trained], grey, rtol=1e-5)
    capsys.readouterr()


def test_only_a_coverage_student_records_mask_levels(tmp_path):
    """ad.mask_levels is written for coverage students only: absent means binary, so an estimator from
    before grey masks still loads every binary export."""
    ckpt, _ = _checkpoint(tmp_path, "streaming")
    export_student(ckpt, tmp_path / "b" / "student.onnx")
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "b" / "student.onnx")).metadata_props}
    assert "ad.mask_levels" not in meta
    state = torch.load(ckpt, weights_only=False)
    state["meta"]["config"]["mask_levels"] = "coverage"
    engine.save_checkpoint(tmp_path / "grey.pt", state)
    export_student(tmp_path / "grey.pt", tmp_path / "g" / "student.onnx")
    model = EstimatorModel.load(tmp_path / "g" / "student.onnx")
    assert model.info.mask_levels == "coverage"
    # A checkpoint whose config names other levels is refused, naming them.
    state["meta"]["config"]["mask_levels"] = "grey"
    engine.save_checkpoint(tmp_path / "bad.pt", state)
    with pytest.raises(ValueError, match="mask_levels is one of binary, coverage, got 'grey'"):
        export_student(tmp_path / "bad.pt", tmp_path / "x" / "student.onnx")


def _files(folder) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_an_export_that_fails_verification_replaces_nothing(tmp_path, capsys, monkeypatch):
    """The files are written and verified in a staging folder and moved into place only when they all
    verify: a failure (onnxruntime's own error, or export's RuntimeError when it differs from torch) is one
    line, exit 1, and leaves the previous export (encoder, head and metrics) as it was, with no leftovers.
    Written in place, they had replaced the previous files before the check (a traceback)."""
    from training import export
    from training.__main__ import main

    monkeypatch.delenv("AD_DEBUG", raising=False)
    good, _ = _checkpoint(tmp_path, "streaming")
    folder = tmp_path / "models"
    out = folder / "student.onnx"
    assert main(["export", "--checkpoint", str(good), "--out", str(out)]) == 0
    before = _files(folder)
    assert list(before) == ["student.frame.onnx", "student.metrics.json", "student.onnx"]
    capsys.readouterr()
    # onnxruntime cannot load the head it wrote (its own error, InvalidProtobuf; a head it cannot run, as
    # one of embed_dim 0 was, gave InvalidArgument).
    attach = export._attach

    def broken_head(path, meta):
        attach(path, meta)
        if path.name == out.name:
            path.write_bytes(b"not onnx")

    monkeypatch.setattr(export, "_attach", broken_head)
    assert main(["export", "--checkpoint", str(good), "--out", str(out), "--model-id", "other"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.splitlines()[-1].startswith(
        f"python -m training export: the ONNX export of {good} does not verify in onnxruntime (")
    assert "INVALID_PROTOBUF" in err.splitlines()[-1]
    assert _files(folder) == before
    monkeypatch.setattr(export, "_attach", attach)
    # It runs but differs from torch (here: any difference at all is too much).
    verify = export.verify_export
    monkeypatch.setattr(export, "verify_export", lambda *args: verify(*args, atol=-1.0))
    assert main(["export", "--checkpoint", str(good), "--out", str(out), "--model-id", "other"]) == 1
    line = capsys.readouterr().err.splitlines()[-1]
    assert "differs from torch" in line and f"nothing was replaced in {folder}" in line
    assert _files(folder) == before
    # Interrupted (Ctrl-C, or a kill) before the files are moved into place: the previous export stays whole.
    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "verify_export", interrupted)
    assert main(["export", "--checkpoint", str(good), "--out", str(out), "--model-id", "other"]) == 130
    assert _files(folder) == before


def test_an_out_that_would_overwrite_the_checkpoint_is_refused(tmp_path, capsys):
    """--out (or the frame encoder or metrics JSON written beside it) naming the checkpoint is refused before
    anything is written; once, the checkpoint was overwritten with ONNX and export then failed on it."""
    from training.__main__ import main

    ckpt, _ = _checkpoint(tmp_path, "streaming")
    weights = ckpt.read_bytes()
    (tmp_path / "sub").mkdir()
    cases = [(ckpt, ckpt), (ckpt, tmp_path / "sub" / ".." / ckpt.name),
             (tmp_path / "s.frame.onnx", tmp_path / "s.onnx"), (tmp_path / "s.metrics.json", tmp_path / "s.onnx")]
    for checkpoint, out in cases:
        if checkpoint != ckpt:
            checkpoint.write_bytes(weights)
        listing = sorted(p.name for p in tmp_path.iterdir())
        assert main(["export", "--checkpoint", str(checkpoint), "--out", str(out)]) == 1, out
        (line,) = capsys.readouterr().err.splitlines()
        assert line.startswith(f"python -m training export: --out {out} would write ") and "is the checkpoint" in line
        assert checkpoint.read_bytes() == weights and sorted(p.name for p in tmp_path.iterdir()) == listing
        assert not any((tmp_path / "sub").iterdir())


# ---- mutation-testing audit (round 2)


def test_verification_compares_every_output_with_torch(tmp_path, monkeypatch):
    """verify_export fails when any one of the three outputs differs from torch (logits, params or
    params_logvar), not only the first."""
    import onnxruntime as ort

    from training.export import OUTPUTS

    ckpt, _ = _checkpoint(tmp_path, "uniformer")
    out = tmp_path / "student.onnx"
    export_student(ckpt, out)
    assert verify_export(ckpt, out) < 1e-4
    real_run = ort.InferenceSession.run
    for k in range(len(OUTPUTS)):
        def run(self, names, feeds, *args, _k=k, **kwargs):
            got = real_run(self, names, feeds, *args, **kwargs)
            if names == OUTPUTS:
                got[_k] = got[_k] + 1e-2  # this output alone is off by 1e-2
            return got

        monkeypatch.setattr(ort.InferenceSession, "run", run)
        with pytest.raises(RuntimeError, match="differs from torch by 1.00e-02"):
            verify_export(ckpt, out)


def test_the_metrics_file_records_the_last_epoch_of_the_history(tmp_path):
    """The fresh metrics JSON beside the export holds the checkpoint's final epoch: the history's last entry."""
    ckpt, _ = _checkpoint(tmp_path, "uniformer")
    history = [{"epoch": 1, "val_loss": 0.9}, {"epoch": 2, "val_loss": 0.5}, {"epoch": 3, "val_loss": 0.4}]
    (tmp_path / "history.json").write_text(json.dumps(history))
    export_student(ckpt, tmp_path / "m" / "student.onnx")
    record = json.loads((tmp_path / "m" / "student.metrics.json").read_text())
    assert record["final_epoch"] == {"epoch": 3, "val_loss": 0.4}
    assert record["model"] == "student.onnx"
