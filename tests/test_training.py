"""Teacher and student training on real (synthetic-content) bags: learning, exact resume after a
kill, weights-only checkpoints, ablations, DDP over gloo with two processes."""
from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import torch

from training import data, engine
from training.models.student import (StudentConfig, build_student, earlier_observed_slots, frame_encoder_input,
                                     student_preset)
from training.models.teacher import TEACHER_PRESETS, Teacher, farthest_point_sampling, strain_features
from training.synthetic import write_synthetic_bag
from training.train_student import ABLATIONS, VideoSet, load_student, reframe, student_loss, videos_on_device
from training.train_student import build_parser as build_student_parser
from training.train_student import run as run_student
from training.train_teacher import SYMMETRIES, TrajectoriesOnDevice, TrajectorySet, transform_trajectories
from training.train_teacher import run as run_teacher

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("train_bags")
    write_synthetic_bag(root / "a", 9, views=2, seed=1)
    return root


def _args(bags, out, cache, **kw):
    base = dict(bags=str(bags), cache=str(cache), out=str(out), size="tiny", epochs=2, batch_size=4, lr=3e-3,
                min_lr=1e-5, weight_decay=1e-4, val_fraction=0.2, seed=0, device="cpu", threads=0, no_progress=True,
                videos_on_device="auto", trajectories_on_device="auto", align_weight=0.1, regl1_weight=0.2, stop_after=0, amp=False,
                encoder_channels=None, previous_frames=0, teacher=None, select="score", set=None, shift=0, zoom=0.0)
    base.update(kw)
    return Namespace(**base)


def test_farthest_point_sampling_spreads_anchors():
    pts = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.9, 0, 0]]])
    idx = farthest_point_sampling(pts, 3)[0].tolist()
    assert idx == [0, 2, 3]


def test_strain_features_ignore_rotation():
    """A tumbling object's F = R S: the C and det F features see only the stretch S."""
    torch.manual_seed(0)
    q, _ = torch.linalg.qr(torch.randn(3, 3))
    rotation = q * torch.sign(torch.linalg.det(q))
    stretch = torch.diag(torch.tensor([1.2, 0.9, 1.05]))
    rotated = strain_features((rotation @ stretch).reshape(1, 9))[0]
    plain = strain_features(stretch.reshape(1, 9))[0]
    torch.testing.assert_close(rotated[9:], plain[9:], atol=1e-5, rtol=0)
    assert (plain[9:15] / 5).tolist() == pytest.approx([0.44, 0, 0, -0.19, 0, 0.1025], abs=1e-5)
    assert plain[15].item() / 5 == pytest.approx(1.2 * 0.9 * 1.05 - 1, abs=1e-5)


def test_square_symmetries_are_exact_augmentations():
    rng = np.random.default_rng(0)
    traj = rng.normal(size=(25, 16, 15)).astype(np.float32)
    traj[..., :3] = rng.uniform(0.2, 0.8, size=(25, 16, 3))
    outs = transform_trajectories(torch.from_numpy(np.stack([traj] * 8)), torch.from_numpy(SYMMETRIES)).numpy()
    np.testing.assert_allclose(outs[0], traj, atol=1e-6)  # the first symmetry is the identity
    for r, out in zip(SYMMETRIES, outs):
        np.testing.assert_allclose(out[..., 3:6], traj[..., 3:6] @ r.T, atol=1e-6)
        np.testing.assert_allclose(out[..., 6:].reshape(-1, 3, 3), r @ traj[..., 6:].reshape(-1, 3, 3) @ r.T, atol=1e-5)
        np.testing.assert_allclose(out[..., 2], traj[..., 2], atol=1e-6)  # gravity axis untouched
        np.testing.assert_allclose(np.linalg.norm(out[..., 3:6], axis=-1), np.linalg.norm(traj[..., 3:6], axis=-1),
                                   rtol=1e-5)
        f, g = traj[..., 6:].reshape(-1, 3, 3), out[..., 6:].reshape(-1, 3, 3)
        np.testing.assert_allclose(np.linalg.det(g), np.linalg.det(f), rtol=1e-4, atol=1e-5)
        assert ((out[..., :2] >= 0.2 - 1e-6) & (out[..., :2] <= 0.8 + 1e-6)).all()  # stays in the domain
    assert len({r.tobytes() for r in SYMMETRIES}) == 8


def test_teacher_learns_and_resumes_exactly(bags, tmp_path):
    cache = tmp_path / "cache"
    # Reference: 3 epochs in one go.
    ref = _args(bags, tmp_path / "ref", cache, epochs=3)
    run_teacher(ref)
    history = engine.load_checkpoint(tmp_path / "ref" / engine.LAST)["history"]
    assert history[-1]["train_loss"] < history[0]["train_loss"]
    # Stopped after 1 epoch (as a kill would), then the same command resumes at epoch 2.
    run_teacher(_args(bags, tmp_path / "resumed", cache, epochs=3, stop_after=1))
    state = torch.load(tmp_path / "resumed" / engine.LAST, weights_only=True)  # never arbitrary pickles
    assert state["epoch"] == 1 and isinstance(state["rng"]["torch"], torch.Tensor)
    run_teacher(_args(bags, tmp_path / "resumed", cache, epochs=3))
    a = engine.load_checkpoint(tmp_path / "ref" / engine.LAST)
    b = engine.load_checkpoint(tmp_path / "resumed" / engine.LAST)
    assert b["epoch"] == 3 and len(b["history"]) == 3
    for key, value in a["model"].items():
        torch.testing.assert_close(b["model"][key], value, rtol=0, atol=0)
    assert (tmp_path / "ref" / engine.BEST).exists()


def test_teacher_batches_built_on_device_match_host_batches(bags, tmp_path):
    """Trajectories and tubes held in (here CPU) device memory give the host path's batches, symmetries included."""
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    teacher = Teacher(TEACHER_PRESETS["tiny"])
    on_device = TrajectoriesOnDevice(ds, teacher, torch.device("cpu"), chunk=4)  # several chunks, one partial
    instances = np.array([7, 2, 5, 0, 8])  # not positions: a wrong row index shows
    for augment in (True, False):
        host = TrajectorySet(ds, instances, augment, 5, teacher)
        device = TrajectorySet(ds, instances, augment, 5, teacher, on_device)
        host.set_epoch(1), device.set_epoch(1)
        a, b = (s.collate([s[k] for k in range(len(instances))]) for s in (host, device))
        assert a.keys() == b.keys()
        for key in a:
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
        raw = torch.from_numpy(np.stack([ds.trajectory(i) for i in instances]))
        assert torch.equal(a["trajectory"], raw) != augment  # augmentation really transforms


def test_teacher_trains_the_same_with_trajectories_on_device(bags, tmp_path):
    weights = []
    for where in ("no", "yes"):
        best = run_teacher(_args(bags, tmp_path / where, tmp_path / "cache", epochs=1, trajectories_on_device=where))
        weights.append(torch.load(best, weights_only=True)["model"])
    for key, value in weights[0].items():
        torch.testing.assert_close(weights[1][key], value, rtol=0, atol=0)


@pytest.fixture(scope="module")
def teacher_ckpt(bags, tmp_path_factory):
    out = tmp_path_factory.mktemp("teacher")
    return run_teacher(_args(bags, out, out / "cache", epochs=1))


@pytest.mark.parametrize("ablation", ABLATIONS)
def test_student_ablations_train(bags, teacher_ckpt, tmp_path, ablation):
    best = run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, teacher=str(teacher_ckpt),
                             kind="streaming", ablation=ablation, alpha=0.5, full_clips=False))
    state = torch.load(best, weights_only=True)
    teacher = torch.load(teacher_ckpt, weights_only=True)["model"]
    history = torch.load(tmp_path / "s" / engine.LAST, weights_only=True)["history"]
    assert state["meta"]["ablation"] == ablation and len(history) == 1
    key = "temporal.heads.predictor.cls.weight"
    same = torch.equal(state["model"][key], teacher["heads.predictor.cls.weight"])
    # align_only keeps the teacher's predictor frozen; the others train their own.
    assert same == (ablation == "align_only")
    assert ("train_align" in history[0]) == (ablation != "none")


def test_encoder_channels_override_the_preset(bags, tmp_path):
    best = run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, kind="streaming", ablation="none",
                             alpha=0.5, full_clips=False, encoder_channels=(4, 12)))
    state = torch.load(best, weights_only=True)
    assert state["meta"]["config"]["channels"] == [4, 12]
    assert state["model"]["frame_encoder.features.0.0.weight"].shape[0] == 4
    # Only the last stage has the extra stride-1 conv, also when two stages have the same width.
    equal = build_student(dataclasses.replace(student_preset("streaming", "tiny", 8), channels=(8, 8)))
    assert [conv[0].stride for conv in equal.frame_encoder.features] == [(2, 2), (2, 2), (1, 1)]
    parser = build_student_parser()
    assert parser.parse_args(["--bags", "b", "--out", "o", "--encoder-channels", "8,16"]).encoder_channels == (8, 16)
    for bad in ("8,x", "8,0", ""):
        with pytest.raises(SystemExit):
            parser.parse_args(["--bags", "b", "--out", "o", "--encoder-channels", bad])
    with pytest.raises(SystemExit, match="streaming student only"):
        run_student(_args(bags, tmp_path / "u", tmp_path / "cache", kind="uniformer", ablation="none", alpha=0.5,
                          full_clips=False, encoder_channels=(4, 12)))


def test_set_overrides_config_fields_and_rejects_bad_ones(bags, tmp_path):
    best = run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, kind="streaming", ablation="none",
                             alpha=0.5, full_clips=False, set=["dropout=0", "pool=2", "channels=4,8", "moments=false"]))
    model, meta = load_student(best)
    config = meta["config"]
    assert (config["dropout"], config["pool"], config["channels"], config["moments"]) == (0.0, 2, [4, 8], False)
    assert model.frame_encoder.project[1].in_features == 8 * 2 * 2  # no moments: the pooled map alone
    assert build_student_parser().parse_args(["--bags", "b", "--out", "o", "--set", "pool=2", "--set", "dropout=0"]
                                             ).set == ["pool=2", "dropout=0"]
    for bad, message in (["z_dim=3"], "KEY one of"), (["pool"], "KEY=VALUE"), (["pool=two"], "pool takes a value like 4"), \
            (["moments=yes"], "moments takes"), (["pool=3"], "multiple of pool=3"):
        with pytest.raises(SystemExit, match=message):
            run_student(_args(bags, tmp_path / "bad", tmp_path / "cache", epochs=1, kind="streaming", ablation="none",
                              alpha=0.5, full_clips=False, set=bad))
    assert not (tmp_path / "bad").exists(), "a bad --set fails before anything is written"


def test_mask_levels_are_checked_before_anything_is_written(bags, tmp_path):
    """--set mask_levels takes binary (the default) or coverage (grey masks) only; another value fails
    before any data is cached or any run folder made."""
    assert StudentConfig().mask_levels == "binary"
    assert StudentConfig.from_dict({**student_preset("streaming", "tiny", 32).to_dict(), "mask_levels": "coverage"}
                                   ).mask_levels == "coverage"
    for bad in ("grey", "Coverage", ""):
        with pytest.raises(ValueError, match=f"mask_levels is one of binary, coverage, got {bad!r}"):
            StudentConfig(mask_levels=bad)
        with pytest.raises(SystemExit, match=f"mask_levels is one of binary, coverage, got {bad!r}"):
            run_student(_args(bags, tmp_path / "bad", tmp_path / "cache", epochs=1, kind="streaming", ablation="none",
                              alpha=0.5, full_clips=False, set=[f"mask_levels={bad}"]))
    assert not (tmp_path / "bad").exists() and not (tmp_path / "cache").exists()


def test_best_checkpoint_is_the_epoch_with_the_lowest_selected_validation_metric(bags, tmp_path):
    chosen = {}
    for select in ("score", "regl1"):
        out = tmp_path / select
        best = run_student(_args(bags, out, tmp_path / "cache", epochs=4, kind="streaming", ablation="none",
                                 alpha=0.5, full_clips=False, select=select))
        history = json.loads((out / "history.json").read_text())
        chosen[select] = min(history, key=lambda record: record[f"val_{select}"])["epoch"]
        assert torch.load(best, weights_only=True)["epoch"] == chosen[select]
        assert build_student_parser().parse_args(["--bags", "b", "--out", "o", "--select", select]).select == select
    assert chosen["score"] != chosen["regl1"], "on this data the two metrics pick different epochs, or this tests nothing"
    with pytest.raises(SystemExit):
        build_student_parser().parse_args(["--bags", "b", "--out", "o", "--select", "acc"])
    # A run resumed with another metric would compare unlike numbers: refused, naming both.
    with pytest.raises(ValueError, match="--select regl1.*--select score"):
        run_student(_args(bags, tmp_path / "regl1", tmp_path / "cache", epochs=5, kind="streaming", ablation="none",
                          alpha=0.5, full_clips=False, select="score"))
    with pytest.raises(ValueError, match="select must be one of"):
        engine.fit(None, None, None, None, tmp_path / "x", engine.FitConfig(epochs=1, batch_size=1, select="acc"),
                   None, {})


def test_a_run_resumes_only_with_the_options_it_was_trained_with(bags, tmp_path, capsys):
    """Another seed would move the validation split, another ablation or model make a different run
    under the same name: refused before any data loads, naming what differs as it is typed. The
    same run (an equivalent --set included) resumes; a finished run says so and trains nothing."""
    cache = tmp_path / "cache"
    teacher = run_teacher(_args(bags, tmp_path / "t", cache, epochs=1))
    with pytest.raises(ValueError, match=r"was trained with --lr 0.003 --seed 0; this run asks for --lr 0.01 --seed 5"):
        run_teacher(_args(bags, tmp_path / "t", cache, epochs=1, lr=0.01, seed=5))
    with pytest.raises(ValueError, match=r"--epochs 1; this run asks for --epochs 3"):
        run_teacher(_args(bags, tmp_path / "t", cache, epochs=3))
    config = TEACHER_PRESETS["tiny"].to_dict()
    recipe = torch.load(tmp_path / "t" / engine.LAST, weights_only=True)["recipe"]
    with pytest.raises(ValueError, match=r"torchrun processes 1; this run asks for torchrun processes 2"):
        engine.check_resumable(tmp_path / "t", {**recipe, "torchrun processes": 2}, config, "teacher")
    # The same path with other bags: the validation split would be drawn over other instances.
    more = tmp_path / "more_bags"
    shutil.copytree(bags, more)
    write_synthetic_bag(more / "extra", 1, views=2, seed=5)
    with pytest.raises(ValueError, match=r"was trained with --bags contents [0-9a-f]{12}; this run asks for --bags "
                                         r"contents [0-9a-f]{12}\."):
        run_teacher(_args(more, tmp_path / "t", cache, epochs=1))
    capsys.readouterr()
    run_teacher(_args(bags, tmp_path / "t", cache, epochs=1))
    assert "the run is complete (1 of 1 epochs), nothing to train" in capsys.readouterr().out
    assert len(json.loads((tmp_path / "t" / "history.json").read_text())) == 1

    student = dict(kind="streaming", ablation="full", alpha=0.5, full_clips=False, teacher=str(teacher))
    run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"], **student))
    run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=.20"], **student))  # the same model
    with pytest.raises(ValueError, match=r"--ablation full; this run asks for --ablation none"):
        run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"], **{**student, "ablation": "none"}))
    with pytest.raises(ValueError, match=r"no --full-clips; this run asks for --full-clips\."):
        run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"], **{**student, "full_clips": True}))
    with pytest.raises(ValueError, match=r"holds another model \(dropout 0.2 -> 0.0, previous_frames 0 -> 3: set by"):
        run_student(_args(bags, tmp_path / "s", cache, epochs=1, previous_frames=3, **student))
    other_teacher = run_teacher(_args(bags, tmp_path / "t_seed1", cache, epochs=1, seed=1))  # same latent size
    with pytest.raises(ValueError, match=r"--teacher contents [0-9a-f]{12}; this run asks for --teacher contents"):
        run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"],
                          **{**student, "teacher": str(other_teacher)}))
    with pytest.raises(ValueError, match="is a teacher's checkpoint, not a student's"):
        run_student(_args(bags, tmp_path / "t", cache, epochs=1, **student))  # a teacher's run folder
    with pytest.raises(ValueError, match=f"{tmp_path / 't'} is a folder; pass a checkpoint in it, e.g. "
                                         f"{tmp_path / 't' / 'best.pt'}"):
        run_student(_args(bags, tmp_path / "s2", cache, epochs=1, **{**student, "teacher": str(tmp_path / "t")}))
    # A checkpoint from before recipes were saved resumes with the same model, whatever else changed.
    last = tmp_path / "s" / engine.LAST
    state = torch.load(last, weights_only=True)
    del state["recipe"]
    torch.save(state, last)
    run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"], **{**student, "ablation": "none"}))
    # Older still: checkpoints before 8168bfd named the earlier-frame input previous_frame (a flag).
    state = torch.load(last, weights_only=True)
    state["meta"]["config"]["previous_frame"] = bool(state["meta"]["config"].pop("previous_frames"))
    torch.save(state, last)
    run_student(_args(bags, tmp_path / "s", cache, epochs=1, set=["dropout=0.2"], **student))
    with pytest.raises(ValueError, match=r"holds another model \(dropout 0.2 -> 0.0: set by"):
        run_student(_args(bags, tmp_path / "s", cache, epochs=1, **student))


def test_a_student_resumes_only_on_the_camera_views_it_trained_on(tmp_path, capsys):
    """The same episodes recorded with one camera instead of two have the same instances (the --bags contents
    digest), so a student run went on with half its videos, mixing data silently. The views are part of a
    student's data now; a checkpoint from before they were recorded resumes, with a warning that says so.
    The teacher trains on the particles alone: other cameras do not make it another run."""
    two = write_synthetic_bag(tmp_path / "two" / "a", 6, views=2, seed=1)
    one = write_synthetic_bag(tmp_path / "one" / "a", 6, views=1, seed=1)  # the same episodes, one camera
    cache = tmp_path / "cache"
    student = dict(kind="streaming", ablation="none", alpha=0.5, full_clips=False)
    run_student(_args(two.parent, tmp_path / "s", cache, stop_after=1, **student))
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 's' / engine.LAST} was trained with --bags camera "
                                                   "views 0,1 (12 videos); this run asks for --bags camera views 0 (6 "
                                                   "videos). Resume it with the same options, or train into a new "
                                                   "--out")):
        run_student(_args(one.parent, tmp_path / "s", cache, **student))
    run_teacher(_args(two.parent, tmp_path / "t", cache, stop_after=1))
    run_teacher(_args(one.parent, tmp_path / "t", cache))
    assert engine.load_checkpoint(tmp_path / "t" / engine.LAST)["epoch"] == 2
    # A student checkpoint written before the views were recorded: resumed, saying what it cannot check.
    last = tmp_path / "s" / engine.LAST
    state = torch.load(last, weights_only=True)
    del state["recipe"]["--bags camera views"]
    torch.save(state, last)
    capsys.readouterr()
    run_student(_args(one.parent, tmp_path / "s", cache, **student))
    assert (f"warning: {last} was written before its --bags camera views were recorded, so this resume cannot check "
            f"them: make sure --bags {one.parent} holds the data it trained on (--bags camera views 0 (6 videos)), or "
            "train into a new --out") in capsys.readouterr().err
    assert torch.load(last, weights_only=True)["recipe"]["--bags camera views"] == "0 (6 videos)"


def test_training_on_the_test_splits_is_warned_about(tmp_path, capsys):
    """A --bags above the splits trains on seen/unseen instances too: the run says so."""
    write_synthetic_bag(tmp_path / "bags" / "train", 6, views=1, seed=1)
    write_synthetic_bag(tmp_path / "bags" / "unseen", 3, views=1, seed=2, split="unseen")
    run_teacher(_args(tmp_path / "bags" / "train", tmp_path / "ok", tmp_path / "cache", epochs=1))
    assert "test splits" not in capsys.readouterr().err
    run_teacher(_args(tmp_path / "bags", tmp_path / "mixed", tmp_path / "cache", epochs=1))
    assert (f"warning: the 9 instances under {tmp_path / 'bags'} (training and validation) include 3 unseen "
            "instances of the benchmark's test splits") in capsys.readouterr().err


def test_teacher_and_student_never_validate_on_an_episode_they_train_on(tmp_path, monkeypatch):
    """Bags holding some episodes twice (another recording of them): both stages keep each episode on one side."""
    from training import train_student, train_teacher

    write_synthetic_bag(tmp_path / "bags" / "a", 6, views=1, seed=1)
    write_synthetic_bag(tmp_path / "bags" / "b", 6, views=2, seed=1)  # the same episodes, recorded again
    sides = {}

    def fake_fit(name, instances):
        def fit(model, train_set, val_set, *args, **kwargs):
            ds = train_set.ds
            sides[name] = [{ds.episode_ids[i] for i in instances(s)} for s in (train_set, val_set)]
        return fit

    monkeypatch.setattr(train_teacher, "fit", fake_fit("teacher", lambda s: s.instances))
    monkeypatch.setattr(train_student, "fit", fake_fit("student", lambda s: s.ds.video_instance[s.videos]))
    for seed in range(3):
        run_teacher(_args(tmp_path / "bags", tmp_path / "t", tmp_path / "cache", val_fraction=0.5, seed=seed))
        run_student(_args(tmp_path / "bags", tmp_path / "s", tmp_path / "cache", val_fraction=0.5, seed=seed,
                          kind="streaming", ablation="none", alpha=0.5, full_clips=False))
        for name, (train, val) in sides.items():
            assert train and val and not train & val, (name, seed, train & val)


def test_earlier_observed_slots_skip_unobserved_slots_and_repeat_the_oldest():
    valid = torch.tensor([[1.0, 1, 1, 1, 1], [1, 0, 1, 0, 1], [0, 1, 1, 1, 0]])
    sources = earlier_observed_slots(valid, 3)
    # Newest first; a gap is skipped to the last observed slot; with fewer earlier frames than asked
    # the oldest one stands in, and the first slot, with none, sees itself.
    assert sources[0].tolist() == [[0, 0, 0], [0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 2, 1]]
    assert sources[1].tolist() == [[0, 0, 0], [0, 0, 0], [0, 0, 0], [2, 0, 0], [2, 0, 0]]
    assert sources[2][:4].tolist() == [[0, 0, 0], [1, 1, 1], [1, 1, 1], [2, 1, 1]]
    masks = torch.arange(5.0).view(1, 5, 1, 1).expand(3, 5, 2, 3).clone()  # slot k holds the value k
    config = student_preset("streaming", "tiny", z_dim=32)
    frames = frame_encoder_input(dataclasses.replace(config, previous_frames=3), masks, valid)
    assert frames.shape == (3, 5, 4, 2, 3)
    assert frames[0, :, :, 0, 0].tolist() == [[0, 0, 0, 0], [1, 0, 0, 0], [2, 1, 0, 0], [3, 2, 1, 0], [4, 3, 2, 1]]
    assert frame_encoder_input(config, masks, valid).shape == (3, 5, 1, 2, 3)


def test_old_checkpoint_config_with_a_previous_frame_flag_loads():
    config = student_preset("streaming", "tiny", z_dim=32).to_dict()
    del config["previous_frames"]
    for flag, expected in ((True, 1), (False, 0)):
        assert StudentConfig.from_dict({**config, "previous_frame": flag}).previous_frames == expected


@pytest.mark.parametrize("previous_frames", [1, 2])
def test_student_with_earlier_frames_trains_with_one_input_channel_each(bags, tmp_path, previous_frames):
    best = run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, kind="streaming", ablation="none",
                             alpha=0.5, full_clips=False, previous_frames=previous_frames))
    model, meta = load_student(best)
    assert meta["config"]["previous_frames"] == previous_frames
    assert model.frame_encoder.features[0][0].weight.shape[1] == 1 + previous_frames
    # The previous frame changes the embedding: the same mask after a different one encodes differently.
    mask = torch.zeros(1, 1, 32, 32)
    mask[..., 10:20, 10:20] = 1.0
    with torch.no_grad():
        still = model.frame_encoder(torch.cat([mask] * (1 + previous_frames), 1))
        moved = model.frame_encoder(torch.cat([mask] + [mask.roll(3, -2)] * previous_frames, 1))
    assert not torch.allclose(still, moved)
    with pytest.raises(SystemExit, match="streaming student only"):
        run_student(_args(bags, tmp_path / "u", tmp_path / "cache", kind="uniformer", ablation="none", alpha=0.5,
                          full_clips=False, previous_frames=previous_frames))


def test_batches_built_on_device_match_host_batches(bags, tmp_path):
    """The videos-on-device path (here with the tensor on the CPU) gives the host path's batches."""
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    frames = data.resized_videos(ds, (32, 32), progress=False)
    on_device = videos_on_device(frames, torch.device("cpu"), progress=False)
    videos = np.arange(ds.num_videos)
    host = VideoSet(ds, videos, frames, None, random_prefix=True, augment=True, seed=3)
    device = VideoSet(ds, videos, frames, None, random_prefix=True, augment=True, seed=3, on_device=on_device)
    for epoch in (0, 1):
        host.set_epoch(epoch), device.set_epoch(epoch)
        a = host.collate([host[k] for k in range(len(videos))])
        b = device.collate([device[k] for k in range(len(videos))])
        assert a.keys() == b.keys()
        for key in a:
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=1e-3 if key == "masks" else 0)
    # Prefixes and mirror flips really happen (so the comparison above covers them).
    assert (a["valid"].sum(1) < 25).any() and not torch.equal(a["masks"], a["masks"].flip(-1))


def test_reframed_batches_match_on_device_and_are_reproducible(bags, tmp_path):
    """Shift and zoom augmentation: the same clips on both paths, the same again from the seed, and
    really reframed (the masks differ from the unaugmented batch's, but take no value it lacks)."""
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    frames = data.resized_videos(ds, (32, 32), progress=False)
    on_device = videos_on_device(frames, torch.device("cpu"), progress=False)
    videos = np.arange(ds.num_videos)

    def batch(**kw):
        vs = VideoSet(ds, videos, frames, None, random_prefix=True, augment=True, seed=3, **kw)
        return vs.collate([vs[k] for k in range(len(videos))])

    plain, host = batch(), batch(shift=3, zoom=0.1)
    device = batch(shift=3, zoom=0.1, on_device=on_device)
    assert "view" not in plain and host.keys() == plain.keys() == device.keys()
    torch.testing.assert_close(host["masks"], device["masks"], rtol=0, atol=1e-3)
    torch.testing.assert_close(host["masks"], batch(shift=3, zoom=0.1)["masks"], rtol=0, atol=0)
    assert torch.equal(host["valid"], plain["valid"])  # the prefixes and flips are drawn as before
    assert not torch.equal(host["masks"], plain["masks"])
    assert set(host["masks"].unique().tolist()) <= set(plain["masks"].unique().tolist())  # nearest: no new values


def test_reframe_shifts_and_zooms_about_the_centre():
    masks = torch.zeros(2, 3, 16, 16)
    masks[:, :, 6:10, 5:9] = 1.0  # a 4x4 square, centred in y (rows 6..9), one pixel left of centre in x
    same = reframe(masks, torch.tensor([[1.0, 0, 0], [1.0, 0, 0]]))
    assert torch.equal(same, masks)
    shifted = reframe(masks, torch.tensor([[1.0, 2, -1], [1.0, -7, 0]]))
    expected = torch.zeros_like(masks)
    expected[0, :, 5:9, 7:11] = 1.0  # 2 px right, 1 px up
    expected[1, :, 6:10, 0:2] = 1.0  # 7 px left: the left half falls outside the image
    assert torch.equal(shifted, expected)
    zoomed = reframe(masks, torch.tensor([[2.0, 0, 0], [2.0, 0, 0]]))
    assert zoomed[0].sum(dim=(1, 2)).tolist() == [64.0] * 3  # twice the side, four times the area
    assert zoomed[0, 0].any(1).nonzero().flatten().tolist() == list(range(4, 12))  # still centred in y
    centred = torch.zeros(1, 1, 16, 16)
    centred[..., 4:12, 4:12] = 1.0
    expected = torch.zeros_like(centred)
    expected[..., 6:10, 6:10] = 1.0
    assert torch.equal(reframe(centred, torch.tensor([[0.5, 0, 0]])), expected)


@pytest.mark.parametrize("option", [["--zoom", "1.0"], ["--zoom", "-0.1"], ["--zoom", "x"], ["--shift", "-2"]])
def test_augmentation_options_are_checked(option, capsys):
    with pytest.raises(SystemExit):
        build_student_parser().parse_args(["--bags", "b", "--out", "o", *option])
    assert "expected" in capsys.readouterr().err


def test_native_size_videos_are_not_copied(bags, tmp_path):
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    frames = data.resized_videos(ds, (128, 128), progress=False)
    assert frames[0].dtype == np.uint8 and not list(Path(ds.shards[0]).glob("videos_*x*.npy"))
    assert data.as_unit_float(frames[0][:1]).max() == 1.0


def test_student_loss_weights():
    torch.manual_seed(0)
    batch = {"masks": torch.rand(2, 25, 8, 8), "valid": torch.ones(2, 25), "label": torch.tensor([0, 2]),
             "target": torch.rand(2, 4), "mask": torch.tensor([[1.0, 1, 0, 0], [0, 0, 0, 1]]), "z_t": torch.randn(2, 8)}
    z = torch.randn(2, 8)

    def model(masks, valid):
        return {"z": z, "logits": torch.tensor([[2.0, 0, 0], [0, 0, 1.0]]), "params": torch.full((2, 4), 0.5),
                "params_logvar": torch.zeros(2, 4)}

    losses = {a: student_loss(a, alpha=0.5)(model, batch, True) for a in ABLATIONS}
    logs = losses["full"][1]
    align = float(logs["align"])
    ce, reg = float(logs["ce"]), float(logs["regl1"])
    cos = torch.nn.functional.cosine_similarity(z, batch["z_t"]).mean().item()
    assert align == pytest.approx(1 - cos + 0.5 * (z - batch["z_t"]).abs().mean().item(), rel=1e-5)
    assert float(losses["align_only"][0]) == pytest.approx(align)
    nll_part = float(losses["none"][0]) - (ce + 0.2 * reg)
    assert float(losses["full"][0]) == pytest.approx(0.1 * align + ce + 0.2 * reg + nll_part, rel=1e-5)


def test_training_regl1_is_the_metric_regl1():
    """The RegL1 that training minimises and logs is SPEC 8's, the figure the evaluation reports
    (each family's own ranges), not a union-range variant of it."""
    from ad_estimator.metrics import Predictions, regl1
    from ad_sim.materials import FAMILIES, PARAMETER_NAMES, denormalise, sample_parameters

    from training.models.common import masked_regl1

    rng = np.random.default_rng(3)
    labels = rng.integers(0, len(FAMILIES), 60)
    truth = [sample_parameters(FAMILIES[c], rng) for c in labels]
    _, true_si, target, mask = zip(*(data.labels_of(FAMILIES[c], list(t), list(t.values())) for c, t in zip(labels, truth)))
    pred = rng.uniform(0.0, 1.0, (60, 4))  # heads' outputs: union-normalised, inside [0, 1]
    pred_si = np.stack([denormalise(n, pred[:, j]) for j, n in enumerate(PARAMETER_NAMES)], 1)
    metric = regl1(Predictions(true_class=labels, true_params=np.array(true_si), probabilities=np.eye(3)[labels],
                               pred_params=pred_si)).mean()
    trained = masked_regl1(torch.tensor(pred), torch.tensor(np.array(target)), torch.tensor(np.array(mask)),
                           torch.tensor(labels))
    assert float(trained) == pytest.approx(metric, rel=1e-5)
    # The union-range figure (what training logged before) understates it: plasticine's E and nu
    # span half the union range.
    union = ((np.abs(pred - np.array(target)) * np.array(mask)).sum(1) / np.array(mask).sum(1)).mean()
    assert union < 0.9 * metric


def test_the_student_loss_weights_are_those_recorded_in_its_checkpoint(monkeypatch):
    """The checkpoint records loss_weights (align, ce, regl1, nll); the CE weight was recorded but the loss
    hard-coded 1. Each recorded weight now scales its term: changing one changes the loss by that term."""
    from training import train_student

    rng = torch.Generator().manual_seed(0)
    out = {"logits": torch.randn(4, 3, generator=rng), "params": torch.rand(4, 4, generator=rng),
           "params_logvar": torch.randn(4, 4, generator=rng), "z": torch.randn(4, 8, generator=rng)}
    batch = {"masks": None, "valid": None, "label": torch.tensor([0, 1, 2, 1]), "target": torch.rand(4, 4, generator=rng),
             "mask": torch.tensor([[1, 1, 0, 0], [1, 1, 1, 0], [0, 0, 0, 1], [1, 1, 1, 0]], dtype=torch.float32),
             "z_t": torch.randn(4, 8, generator=rng)}

    def loss(**weights):
        for name, value in weights.items():
            monkeypatch.setattr(train_student, name, value)
        total, logs = train_student.student_loss("full", alpha=2.0)(lambda masks, valid: out, batch, True)
        return float(total), logs

    base, logs = loss(CE_WEIGHT=1.0, NLL_WEIGHT=0.05)
    assert loss(CE_WEIGHT=3.0)[0] == pytest.approx(base + 2.0 * float(logs["ce"]), rel=1e-6)
    assert loss(CE_WEIGHT=1.0, NLL_WEIGHT=0.15)[0] == pytest.approx(base + 0.1 * float(logs["nll"]), rel=1e-6)


def test_teacher_output_shapes():
    model = Teacher(TEACHER_PRESETS["tiny"]).eval()
    out = model(torch.rand(3, 25, 1024, 15))
    assert out["z"].shape == (3, TEACHER_PRESETS["tiny"].z_dim) and out["logits"].shape == (3, 3)
    assert ((out["params"] >= 0) & (out["params"] <= 1)).all() and out["params_logvar"].shape == (3, 4)


@pytest.mark.parametrize("size, world", [(10, 3), (9, 2), (2, 4), (7, 1)])
def test_validation_shares_count_every_sample_once_over_the_ranks(size, world):
    """DistributedSampler padded the ranks by repeating samples, which biased the validation mean that picks
    best.pt; the shares now hold each sample once (or, with fewer samples than ranks, all of them on each)."""
    shares = [list(engine.validation_share(list(range(size)), rank, world)) for rank in range(world)]
    if size < world:
        assert shares == [list(range(size))] * world
    else:
        assert sorted(i for share in shares for i in share) == list(range(size))


def _torchrun(*args: str) -> subprocess.CompletedProcess:
    """`torchrun --standalone --nproc_per_node=2 ARGS` (over gloo, one thread a rank) with this interpreter's
    path, asserted to exit 0."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", *args],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result


@pytest.mark.parametrize("ablation", ["full", "align_only"])
def test_ddp_two_processes_gloo(bags, teacher_ckpt, tmp_path, ablation):
    """torchrun --nproc_per_node=2 -m training student: both ranks train, rank 0 checkpoints, and the validation
    figures it logs (which pick best.pt) are over the whole validation set, both ranks' shares reduced.
    align_only as well, as scripts/gpu_train.sh runs it: the teacher's predictor it keeps must be frozen, not
    merely left without gradients (DDP then fails at the second step, waiting for their reduction)."""
    out = tmp_path / "ddp"
    # --val-fraction 0.3: 3 validation instances, 2 on one rank and 1 on the other
    result = _torchrun("-m", "training", "student", "--bags", str(bags), "--cache", str(tmp_path / "cache"), "--out",
                       str(out), "--size", "tiny", "--epochs", "1", "--batch-size", "4", "--teacher", str(teacher_ckpt),
                       "--device", "cpu", "--no-progress", "--val-fraction", "0.3", "--ablation", ablation)
    state = torch.load(out / engine.LAST, weights_only=True)
    assert state["epoch"] == 1
    # One log line per epoch (rank 0 only).
    assert result.stdout.count(f"student[streaming,{ablation}] epoch=1") + result.stderr.count(
        f"student[streaming,{ablation}] epoch=1") == 1
    expected = _student_validation(bags, tmp_path / "cache", out, teacher_ckpt, 0.3, 0, 0.5, 0.1, 0.2, ablation)
    for key, value in expected.items():
        assert state["history"][0][f"val_{key}"] == pytest.approx(value, rel=1e-5, abs=1e-7), key
    if ablation == "align_only":  # predictions come from the teacher's predictor, as it was
        teacher = torch.load(teacher_ckpt, weights_only=True)["model"]
        assert torch.equal(state["model"]["temporal.heads.predictor.cls.weight"], teacher["heads.predictor.cls.weight"])


def test_ddp_teacher_with_trajectories_on_device_stops_and_resumes(bags, tmp_path):
    """What the GPU job does (run in time slices under torchrun), over gloo: each rank holds every
    trajectory, builds its batches from it, stops after one epoch and resumes for the second."""
    out = tmp_path / "ddp_teacher"
    for epoch in (1, 2):
        result = _torchrun("-m", "training", "teacher", "--bags", str(bags), "--cache", str(tmp_path / "cache"), "--out",
                           str(out), "--size", "tiny", "--epochs", "2", "--batch-size", "2", "--device", "cpu",
                           "--trajectories-on-device", "yes", "--stop-after", "1", "--no-progress")
        assert torch.load(out / engine.LAST, weights_only=True)["epoch"] == epoch
        assert (result.stdout + result.stderr).count(f"teacher epoch={epoch}") == 1


_RANK_AFTER_FIT = """
import os, sys, torch
from pathlib import Path
from training import engine
rt = engine.init_runtime("cpu")
samples = [{"x": torch.randn(4), "y": torch.randn(1)} for _ in range(8)]
def loss_fn(net, batch, train):
    loss = ((net(batch["x"]) - batch["y"]) ** 2).mean()
    return loss, {"score": loss.detach()}
engine.fit(torch.nn.Linear(4, 1), samples, None, loss_fn, Path(sys.argv[1]) / str(rt.rank),
           engine.FitConfig(epochs=1, batch_size=2, progress=False), rt, meta={})
engine.close_runtime()
threads = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
(Path(sys.argv[1]) / f"threads{rt.rank}.txt").write_text("\\n".join(threads))
"""


def test_a_rank_ends_its_process_group_threads_before_it_exits(tmp_path):
    """A CI run once saw a rank abort at exit after training and saving ("terminate called without an active
    exception", exit 1 from torchrun): DistributedDataParallel imported torch._dynamo after the process group
    existed, which then kept it alive past close_runtime, so gloo's threads were torn down at exit. After
    close_runtime a rank that trained under DDP must have no gloo thread left."""
    script = tmp_path / "rank.py"
    script.write_text(_RANK_AFTER_FIT)
    _torchrun(str(script), str(tmp_path))
    for rank in (0, 1):
        threads = (tmp_path / f"threads{rank}.txt").read_text().splitlines()
        assert threads and not [name for name in threads if "gloo" in name], (rank, threads)


def test_evaluate_teacher_writes_the_papers_table(bags, teacher_ckpt, tmp_path, capsys):
    """`python -m training evaluate-teacher`: the teacher's own predictions, scored and reported as
    the students' reports are."""
    from ad_estimator.metrics import Predictions, compute_metrics
    from training.__main__ import main
    from training.train_teacher import load_teacher, teacher_predictions

    out = tmp_path / "report"
    assert main(["evaluate-teacher", "--teacher", str(teacher_ckpt), "--bags", str(bags), "--cache",
                 str(tmp_path / "cache"), "--out", str(out), "--device", "cpu", "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert list(metrics["frames"]) == ["25"] and (out / "report.md").exists() and (out / "confusion.png").exists()
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    expected = compute_metrics(teacher_predictions(load_teacher(teacher_ckpt), ds, "cpu"))
    assert metrics["frames"]["25"]["regl1"] == pytest.approx(expected["regl1"])
    assert metrics["frames"]["25"]["n"] == len(ds)
    saved = json.loads((out / "predictions.json").read_text())
    again = compute_metrics(Predictions.from_episodes(saved["frames"]["25"], saved["parameter_names"]))
    assert again["regl1"] == pytest.approx(expected["regl1"]) and len(saved["frames"]["25"]) == len(ds)
    assert "RegL1" in capsys.readouterr().out


def test_the_teacher_scores_a_looping_simulators_repeats_once(teacher_ckpt, tmp_path):
    """evaluate-teacher (and pipeline's teacher summary) scored every repeat of a looping simulator's recording,
    where the students' evaluation scores each episode once: the same predictions as one pass now."""
    from ad_estimator.metrics import compute_metrics
    from ad_sim.generate import write_episodes
    from ad_sim.rosbag import BagWriter
    from training.synthetic import synthetic_episode
    from training.train_teacher import load_teacher, teacher_predictions

    episodes = [synthetic_episode(i, 5, 1, "unseen") for i in range(4)]
    scored = {}
    for name, passes in (("once", 1), ("looped", 3)):
        with BagWriter(tmp_path / name / "bag") as writer:
            for p in range(passes):
                write_episodes(writer, episodes, p * len(episodes))
        ds = data.load_dataset(tmp_path / name, tmp_path / "cache", progress=False)
        scored[name] = teacher_predictions(load_teacher(teacher_ckpt), ds, "cpu", batch_size=3)
    assert scored["looped"].episode_ids == scored["once"].episode_ids == [e.instance.episode_id for e in episodes]
    np.testing.assert_allclose(scored["looped"].pred_params, scored["once"].pred_params, rtol=1e-5)
    assert compute_metrics(scored["looped"])["n"] == 4


def test_checkpoint_errors_are_one_clear_line(bags, teacher_ckpt, tmp_path, capsys):
    from training.__main__ import main

    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(Path(teacher_ckpt).read_bytes()[:1000])
    student = run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, kind="streaming",
                                ablation="none", alpha=0.5, full_clips=False))
    cases = {truncated: "not a readable checkpoint", student: "student's checkpoint, not a teacher's",
             tmp_path / "missing.pt": "No such file"}
    for path, message in cases.items():
        assert main(["evaluate-teacher", "--teacher", str(path), "--bags", str(bags), "--out", str(tmp_path / "r"),
                     "--device", "cpu", "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(ValueError, match="teacher's checkpoint, not a student's"):
        load_student(teacher_ckpt)
    assert main(["evaluate-teacher", "--teacher", str(teacher_ckpt), "--bags", str(bags), "--out", str(tmp_path / "r"),
                 "--device", "cpu", "--batch-size", "0"]) == 1
    assert "--batch-size must be at least 1" in capsys.readouterr().err


@pytest.mark.parametrize("kind, bad, message", [
    ("streaming", "pool=0", "--set 'pool=0': pool must be a whole number >= 1, got 0"),
    ("streaming", "previous_frames=-1", "--set 'previous_frames=-1': previous_frames must be a whole number >= 0"),
    ("streaming", "input_size=32", "--set 'input_size=32': input_size must be two whole numbers >= 1"),
    ("streaming", "embed_dim=0", "--set 'embed_dim=0': embed_dim must be a whole number >= 1"),
    ("streaming", "channels=8,0", "--set 'channels=8,0': channels must be one or more whole numbers >= 1"),
    ("streaming", "dropout=1.5", "--set 'dropout=1.5': dropout must be a number in [0, 1)"),
    ("streaming", "temporal_heads=3", "--set 'temporal_heads=3': temporal_width 32 is not divisible by "
                                      "temporal_heads 3"),
    ("uniformer", "dims=8", "--set 'dims=8': dims (8,) and depths (1, 1) must have one entry per stage each"),
    ("uniformer", "input_size=4,4", "input size (4, 4) is too small for 2 stages"),
])
def test_set_values_are_checked_before_anything_is_written(bags, tmp_path, kind, bad, message):
    """Values --set reads as the right type but cannot build a model (or built one that cannot be exported,
    embed_dim=0) are one line naming the field, before the data loads or --out is made (were a
    ZeroDivisionError, a torch error after the data loaded, an unpacking error)."""
    with pytest.raises(SystemExit, match="^" + re.escape(f"python -m training student: {message}")):
        run_student(_args(bags, tmp_path / "bad", tmp_path / "cache", epochs=1, kind=kind, ablation="none",
                          alpha=0.5, full_clips=False, set=[bad]))
    assert not (tmp_path / "bad").exists() and not (tmp_path / "cache").exists()


def test_student_usage_errors_carry_the_commands_prefix(bags, tmp_path, capsys):
    from training.__main__ import main

    with pytest.raises(SystemExit, match="^python -m training student: --teacher is required"):
        main(["student", "--bags", str(bags), "--out", str(tmp_path / "s"), "--device", "cpu"])
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("stage", ["teacher", "student"])
@pytest.mark.parametrize("option", [["--lr", "-1"], ["--lr", "0"], ["--lr", "nan"], ["--min-lr", "-0.5"],
                                    ["--weight-decay", "-0.1"]])
def test_learning_rates_are_checked_before_anything_is_written(bags, tmp_path, capsys, stage, option):
    """AdamW refused them only after the data had loaded, leaving an empty --out."""
    from training.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main([stage, "--bags", str(bags), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"),
              *(["--ablation", "none"] if stage == "student" else []), *option])
    assert exit_info.value.code == 2
    assert f"argument {option[0]}: expected a number >" in capsys.readouterr().err
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()


def _tiny_student_checkpoint(path: Path, config: dict | None = None, model: dict | None = None) -> Path:
    """A student checkpoint as `fit` writes it (untrained weights), optionally with another config or weights."""
    preset = student_preset("streaming", "tiny", 32)
    torch.save({"model": build_student(preset).state_dict() if model is None else model,
                "meta": {"config": preset.to_dict() if config is None else config}}, path)
    return path


def test_checkpoints_with_the_wrong_contents_are_one_line(bags, teacher_ckpt, tmp_path, capsys):
    """A checkpoint that loads but cannot be the stage's model (a config field this version lacks, no config,
    meta not a dict, weights of another model) was a TypeError, KeyError, AttributeError or torch's many-line
    size-mismatch list; now one line: <path> is not a compatible <stage> checkpoint: <why>."""
    from training.__main__ import main

    teacher = torch.load(teacher_ckpt, weights_only=True)
    student = student_preset("streaming", "tiny", 32).to_dict()

    def teacher_with(name: str, **changes) -> Path:
        torch.save({**teacher, **changes}, tmp_path / name)
        return tmp_path / name

    cases = {
        teacher_with("t_bogus.pt", meta={**teacher["meta"], "config": {**teacher["meta"]["config"], "bogus": 1}}):
            "its model config cannot be built (unknown config field 'bogus')",
        teacher_with("t_empty.pt", model={}, meta={}): "its meta holds no model config",
        teacher_with("t_meta.pt", meta=[1]): "its meta is a list, not a dict",
        teacher_with("t_config.pt", meta={"config": "abc"}): "its model config is a str, not a dict",
        teacher_with("t_width.pt", meta={**teacher["meta"], "config": {**teacher["meta"]["config"], "width": 64}}):
            "25 weights have other shapes than its config gives (e.g. temporal.weight: (32, 32, 3) saved, "
            "(64, 32, 3) expected)",
        teacher_with("t_list.pt", model=[1]): "its model is not a dict of tensors",
    }
    for path, reason in cases.items():
        expected = f"{path} is not a compatible teacher checkpoint: {reason}"
        for command in (["evaluate-teacher", "--teacher", str(path), "--bags", str(bags), "--out",
                         str(tmp_path / "r")],
                        ["student", "--teacher", str(path), "--bags", str(bags), "--out", str(tmp_path / "s"),
                         "--size", "tiny"]):
            assert main([*command, "--device", "cpu", "--no-progress"]) == 1
            err = capsys.readouterr().err.strip()
            assert err.startswith(f"python -m training {command[0]}: {expected}") and "\n" not in err, err
        assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()

    students = {
        _tiny_student_checkpoint(tmp_path / "s_bogus.pt", {**student, "bogus": 1}):
            "its model config cannot be built (unknown config field 'bogus')",
        _tiny_student_checkpoint(tmp_path / "s_pool.pt", {**student, "pool": 0}):
            "its model config cannot be built (pool must be a whole number >= 1, got 0)",
        _tiny_student_checkpoint(tmp_path / "s_embed.pt", {**student, "embed_dim": 64}):
            "5 weights have other shapes than its config gives",
        _tiny_student_checkpoint(tmp_path / "s_missing.pt", model={}):
            "53 weights are missing (e.g. frame_encoder.features.0.0.weight)",
    }
    for path, reason in students.items():
        with pytest.raises(ValueError) as info:
            load_student(path)  # what export and resim-psnr load students with
        assert str(info.value).startswith(f"{path} is not a compatible student checkpoint: {reason}")
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="is not a compatible student checkpoint: its meta holds no model config"):
        load_student(teacher_with("empty.pt", model={}, meta={}))
    assert load_student(_tiny_student_checkpoint(tmp_path / "good.pt"))[1]["config"] == student


def test_a_resumed_run_whose_last_checkpoint_has_an_unknown_config_field_is_one_line(bags, tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    config = student_preset("streaming", "tiny", 32).to_dict()
    _tiny_student_checkpoint(out / engine.LAST, {**config, "bogus": 1})
    with pytest.raises(ValueError, match=re.escape(f"{out / engine.LAST} is not a compatible student checkpoint: "
                                                   "unknown config field 'bogus' (or delete")):
        run_student(_args(bags, out, tmp_path / "cache", epochs=1, kind="streaming", ablation="none", alpha=0.5,
                          full_clips=False))


def test_an_onnx_model_or_a_foreign_pickle_passed_as_a_checkpoint_is_one_line(bags, tmp_path, capsys):
    """torch's refusal spanned 6 lines and advised weights_only=False, which would run the file's code."""
    import onnx
    from onnx import TensorProto, helper

    from training.__main__ import main

    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
    model = tmp_path / "student.onnx"
    onnx.save(helper.make_model(graph), str(model))
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": {}, "meta": {}, "args": Namespace(lr=1.0)}, foreign)
    cases = {model: f"{model} is an ONNX model (what `python -m training export` writes), not a checkpoint; pass "
                    "the training run's best.pt",
             foreign: f"{foreign} is not a readable checkpoint (it holds objects other than tensors and plain values "
                      "(Unsupported global: GLOBAL argparse.Namespace was not an allowed global by default)); copy "
                      "it again or retrain"}
    for path, expected in cases.items():
        for command in (["evaluate-teacher", "--teacher", str(path), "--bags", str(bags), "--out",
                         str(tmp_path / "r")],
                        ["student", "--teacher", str(path), "--bags", str(bags), "--out", str(tmp_path / "s")]):
            assert main([*command, "--device", "cpu", "--no-progress"]) == 1
            assert capsys.readouterr().err.strip() == f"python -m training {command[0]}: {expected}"
        with pytest.raises(ValueError) as info:
            load_student(path)
        assert str(info.value) == expected


def test_report_names_the_episode_of_an_unknown_material(tmp_path, capsys):
    """It blamed the whole "frames"["25"] list with Python's "tuple.index(x): x not in tuple"."""
    from training.__main__ import main

    record = {"episode_id": "e1", "true_material": "honey", "true_parameters": {"youngs_modulus": 1e5},
              "probabilities": [0.5, 0.3, 0.2], "raw_parameters": [1e5, 0.3, 1e3, 30.0]}
    path = tmp_path / "predictions.json"
    path.write_text(json.dumps({"frames": {"25": [{**record, "episode_id": "e0", "true_material": "jelly"}, record]}}))
    assert main(["report", "--predictions", str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"python -m training report: {path}: \"frames\"[\"25\"]: episode 'e1' has the unknown "
                          "material 'honey' (expected one of jelly, plasticine, sand); pass a predictions.json"), err
    assert "\n" not in err and not (tmp_path / "out").exists()


def test_report_keeps_a_temporal_ood_row_that_every_episode_was_left_out_of(tmp_path, capsys):
    """ad_estimator.evaluate's predictions.json keeps an empty list for a K row every episode was left out of
    (say, a camera at twice the model's rate: the first K frames span K/2 slots), and `report` dropped that row
    from its tables. It stays, "no clips" in its cells; the frame slots each clip filled are its frames_used."""
    from training.__main__ import main

    record = {"episode_id": "e0", "true_material": "jelly", "true_parameters": {"youngs_modulus": 1e5,
              "poissons_ratio": 0.3}, "probabilities": [0.8, 0.1, 0.1], "raw_parameters": [1e5, 0.3, 1e3, 0.5],
              "frames_used": 24, "slots": 25}
    path = tmp_path / "predictions.json"
    left_out = {"bag": "b", "episode_id": "e0", "reason": "its window holds 9 of 18 frame slots"}
    path.write_text(json.dumps({"model_id": "m", "frames": {"25": [record, {**record, "episode_id": "e1",
                                                                            "frames_used": 25}], "18": []},
                                "left_out": {"25": [], "18": [left_out, {**left_out, "episode_id": "e1"}]}}))
    assert main(["report", "--predictions", str(path), "--out", str(tmp_path / "out")]) == 0
    assert "| 18 | no clips | no clips |" in capsys.readouterr().out
    report = (tmp_path / "out" / "report.md").read_text()
    assert report.count("| 18 | no clips | no clips |") == 2  # both conventions' tables
    assert "Clips: 2; frames per clip: 25, but 1 clip(s) filled only 24 of the 25 frame slots" in report
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["frames"]["18"]["n"] == 0
    # Prefixes alone, without the full clips: there is no full-clip row to report.
    path.write_text(json.dumps({"frames": {"25": [], "18": [record]}}))
    assert main(["report", "--predictions", str(path), "--out", str(tmp_path / "short")]) == 1
    assert f'{path}: "frames"["25"], the full clips, holds no episode records' in capsys.readouterr().err


def test_evaluate_scores_a_model_of_fewer_frames_on_its_first_frames_and_says_so(tmp_path, capsys):
    """A model whose ad.frame_count is 20 was given all 25 cached frames: the evaluation failed ("features (20,
    16) / valid (25,) do not fit the model"), and its report would have said 25 frames per clip."""
    from estimator_models import build_streaming_model

    from training.evaluate import evaluate_model

    model = build_streaming_model(tmp_path, name="m20", frame_count=20)
    write_synthetic_bag(tmp_path / "bags" / "unseen", 3, views=1, seed=2, split="unseen")
    results = evaluate_model(model, tmp_path / "bags", tmp_path / "cache", tmp_path / "out", progress=False,
                             record=False)
    assert sorted(map(int, results), reverse=True) == [20, 18, 16, 15, 14, 12, 10]
    assert "Clips: 3; frames per clip: 20." in (tmp_path / "out" / "report.md").read_text()
    printed = [line.split("|")[1].strip() for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    assert printed[1:] == ["20", "18", "15"]  # the paper table: the full clip and the temporal-OOD rows it has
    with pytest.raises(ValueError, match=re.escape(f"--frames [24]: {model} observes 20 frames (ad.frame_count), "
                                                   "so each K must be in 1..20")):
        evaluate_model(model, tmp_path / "bags", tmp_path / "cache", tmp_path / "out2", frames=(24, 15), record=False)


def test_the_pipeline_trains_on_recorded_bags_and_generates_nothing_beside_them(tmp_path, monkeypatch, capsys):
    """Bags recorded through topics (`ad_sim record`: no generate settings in their metadata) under <data>/<size>/<split> are the data: the
    pipeline generated the split beside them, as for a half-generated folder, and trained on both (each recorded
    episode twice). A shard generate left unfinished is still generated (resumed)."""
    from training.pipeline import ensure_bags

    calls = []
    monkeypatch.setattr("ad_sim.generate.main", lambda argv: calls.append(argv) or 0)
    write_synthetic_bag(tmp_path / "data" / "tiny" / "train" / "recorded", 2, views=1)
    assert ensure_bags(tmp_path / "data", "tiny", "train", 0, "cpu", progress=False) == tmp_path / "data/tiny/train"
    assert not calls and "nothing generated beside them" in capsys.readouterr().out
    write_synthetic_bag(tmp_path / "data" / "tiny" / "seen" / "seen-0of1", 2, views=1,  # generate's, unfinished
                        custom_data={"generator": "ad_sim.generate", "shard": "0/1", "size": "tiny", "split": "seen",
                                     "seed": "0"})
    ensure_bags(tmp_path / "data", "tiny", "seen", 0, "cpu", progress=False)
    assert len(calls) == 1 and "--split" in calls[0]


# --------------------------------------------------------------------------- mutation-testing audit


def test_learning_rate_warms_up_linearly_then_follows_a_cosine_down_to_min_lr():
    lr, low, warmup, total = 1e-3, 1e-5, 10, 110
    def at(step):
        return engine.cosine_lr(step, total, lr, low, warmup)
    # warm-up: step k (from 0) runs at (k + 1) / warmup of lr, so the first step already learns
    assert [at(k) for k in (0, 4, 9)] == pytest.approx([lr / 10, lr / 2, lr], rel=1e-12)
    # cosine over the remaining 100 steps: lr at its start, the mean of lr and min_lr halfway, min_lr at the end
    assert at(10) == pytest.approx(lr, rel=1e-12)
    assert at(60) == pytest.approx((lr + low) / 2, rel=1e-12)
    assert at(35) == pytest.approx(low + (lr - low) * (1 + np.sqrt(0.5)) / 2, rel=1e-12)  # a quarter: cos(pi/4)
    assert at(110) == pytest.approx(low, rel=1e-12) and at(500) == pytest.approx(low, rel=1e-12)  # and stays
    lrs = [at(k) for k in range(10, 111)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))  # never rises again
    assert engine.cosine_lr(0, 100, lr, low, 0) == pytest.approx(lr, rel=1e-12)  # without warm-up


def _squared_error(net, batch, train):
    """A loss_fn for engine.fit on {"x", "y"} samples: the mean squared error, which is also the score."""
    loss = ((net(batch["x"]) - batch["y"]) ** 2).mean()
    return loss, {"score": loss.detach()}


def test_fit_schedules_the_learning_rate_over_all_its_steps(tmp_path):
    """fit's schedule: warm-up over warmup_fraction of all steps (epochs x batches per epoch), then the cosine;
    an epoch's record holds the rate of its last step."""
    torch.manual_seed(0)
    model = torch.nn.Linear(2, 1)
    samples = [{"x": torch.randn(2), "y": torch.randn(1)} for _ in range(8)]
    cfg = engine.FitConfig(epochs=4, batch_size=2, lr=1e-2, min_lr=1e-4, warmup_fraction=0.25, progress=False)
    rt = engine.Runtime(0, 1, torch.device("cpu"))
    history = engine.fit(model, samples, samples[:2], _squared_error, tmp_path, cfg, rt, meta={})["history"]
    # 4 batches an epoch, 16 steps, 4 of warm-up: epoch e ends with step 4e - 1
    def expected(step):
        if step < 4:
            return 1e-2 * (step + 1) / 4
        return 1e-4 + (1e-2 - 1e-4) * (1 + np.cos(np.pi * (step - 4) / 12)) / 2
    assert [r["lr"] for r in history] == pytest.approx([expected(4 * e - 1) for e in (1, 2, 3, 4)], rel=1e-9)


# --------------------------------------------------------------------------- mutation audit of the training stages


class _Numbered(torch.utils.data.Dataset):
    """Samples 0..n-1 for engine.fit, remembering the epochs that fit announces (VideoSet and TrajectorySet draw
    their prefixes, mirrors and symmetries from the epoch it sets)."""

    def __init__(self, n: int, target: float = 1.0):
        generator = torch.Generator().manual_seed(n)
        self.x, self.y = torch.randn(n, 4, generator=generator), torch.full((n, 1), target)
        self.y += torch.randn(n, 1, generator=generator) * abs(target)  # unlike targets: batch means != sample means
        self.epochs = []

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, k: int) -> dict:
        return {"i": torch.tensor(k), "x": self.x[k], "y": self.y[k]}

    def set_epoch(self, epoch: int) -> None:
        self.epochs.append(epoch)


def _mlp() -> torch.nn.Module:
    return torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.ReLU(), torch.nn.Dropout(0.5), torch.nn.Linear(16, 1))


def _toy_fit(out, train, val, make=_mlp, seen=None, **cfg):
    """engine.fit of a seeded `make()` (default: a small MLP with dropout) on `train`, validated on `val`; `seen`
    collects each training batch's sample numbers. Returns fit's result and the trained model."""
    torch.manual_seed(0)
    model = make()

    def loss_fn(net, batch, train):
        if train and seen is not None:
            seen.append(batch["i"].tolist())
        return _squared_error(net, batch, train)

    config = engine.FitConfig(**{"epochs": 3, "batch_size": 4, "lr": 1e-2, "progress": False, **cfg})
    return engine.fit(model, train, val, loss_fn, out, config, engine.Runtime(0, 1, torch.device("cpu")), meta={}), model


def test_fit_shuffles_every_epoch_from_the_seed_and_tells_the_dataset_the_epoch(tmp_path):
    """Training batches are drawn in a new order each epoch, from --seed, and a resumed run draws the orders
    an uninterrupted one would. Batches in the same order every epoch (no set_epoch), in file order (no
    shuffle) or whatever the seed (a fixed one) train a different model than the recipe says, silently; a
    dataset never told the epoch repeats its augmentation (the same prefixes, mirrors and symmetries) forever."""
    def orders(out, seed, **cfg):
        seen, samples = [], _Numbered(12)
        _toy_fit(out, samples, None, seen=seen, seed=seed, **cfg)
        return [sum(seen[k:k + 3], []) for k in range(0, len(seen), 3)], samples.epochs  # 3 batches an epoch

    reference, told = orders(tmp_path / "ref", seed=0)
    assert told == [0, 1, 2]
    assert all(sorted(order) == list(range(12)) for order in reference)  # every sample once an epoch
    assert len({tuple(order) for order in reference}) == 3, "the same order in two epochs"
    assert all(order != sorted(order) for order in reference), "not shuffled"
    assert orders(tmp_path / "seed1", seed=1)[0] != reference, "the order does not follow the seed"
    first, _ = orders(tmp_path / "resumed", seed=0, stop_after=1)
    rest, told = orders(tmp_path / "resumed", seed=0)
    assert first + rest == reference and told == [1, 2]


def test_validation_figures_are_the_eval_mode_mean_over_every_sample(tmp_path):
    """The validation loss picks best.pt: it is the model's loss in eval mode (no dropout noise in it), averaged
    over the samples, not over batches (5 samples in batches of 2: a mean of the batch means would weigh the
    last batch's one sample as much as each other batch's two)."""
    train, val = _Numbered(8), _Numbered(5, target=-4.0)
    history = _toy_fit(tmp_path, train, val, batch_size=2, epochs=1)[0]["history"]
    model = _mlp()
    model.load_state_dict(engine.load_checkpoint(tmp_path / engine.LAST)["model"])
    with torch.no_grad():
        per_sample = ((model.eval()(val.x) - val.y) ** 2).flatten()
    assert history[0]["val_loss"] == pytest.approx(per_sample.mean().item(), rel=1e-6)


def test_best_checkpoint_survives_a_resume_and_stop_after_never_passes_the_epochs(tmp_path):
    """Training toward targets opposite to the validation ones makes epoch 1 the best. A run stopped after it and
    resumed must keep that best.pt (not overwrite it with a worse later epoch because it forgot the best score),
    and end where the uninterrupted run ends; --stop-after larger than the epochs left stops at --epochs."""
    def run(out, **cfg):
        return _toy_fit(out, _Numbered(8, target=3.0), _Numbered(4, target=-3.0), make=lambda: torch.nn.Linear(4, 1),
                        lr=0.05, **cfg)[0]

    history = run(tmp_path / "ref")["history"]
    assert [r["val_score"] for r in history] == sorted(r["val_score"] for r in history), "epoch 1 is not the best"
    run(tmp_path / "resumed", stop_after=1)
    run(tmp_path / "resumed", stop_after=5)  # two epochs were left
    ref, resumed = (engine.load_checkpoint(tmp_path / name / engine.BEST) for name in ("ref", "resumed"))
    assert ref["epoch"] == resumed["epoch"] == 1
    for key, value in ref["model"].items():
        torch.testing.assert_close(resumed["model"][key], value, rtol=0, atol=0)
    last = engine.load_checkpoint(tmp_path / "resumed" / engine.LAST)
    assert last["epoch"] == 3 and len(last["history"]) == 3 and last["best"] == pytest.approx(history[0]["val_score"])


def test_amp_is_cuda_only_a_cpu_run_trains_in_float32(tmp_path):
    """--amp (bfloat16 autocast) is documented for CUDA only: on the CPU the run is the float32 run, bit for bit,
    not a silently lower-precision one."""
    weights = [_toy_fit(tmp_path / str(amp), _Numbered(8), None, amp=amp, epochs=1)[1].state_dict() for amp in (False, True)]
    for key, value in weights[0].items():
        torch.testing.assert_close(weights[1][key], value, rtol=0, atol=0)


def test_each_update_is_adamw_on_the_gradient_clipped_to_grad_clip(tmp_path):
    """fit clips the gradient norm to grad_clip (1.0) before each AdamW step, on the cosine schedule, which
    keeps a bad batch from throwing the weights far; here every gradient is far above that norm, and a run
    without the clipping ends elsewhere. The steps are repeated by hand."""
    torch.manual_seed(0)
    x, y = torch.randn(1, 4) * 30, torch.tensor([[50.0]])  # gradients far above norm 1
    samples = [{"x": x[0], "y": y[0]}]

    def by_hand(clip: bool):
        torch.manual_seed(1)
        net = torch.nn.Linear(4, 1)
        opt = torch.optim.AdamW(net.parameters(), lr=0.1, weight_decay=1e-4)
        for step in range(4):
            for group in opt.param_groups:
                group["lr"] = engine.cosine_lr(step, 4, 0.1, 1e-6, 0)
            opt.zero_grad()
            _squared_error(net, {"x": x, "y": y}, True)[0].backward()
            if clip:
                torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
        return torch.cat([p.detach().flatten() for p in net.parameters()])

    torch.manual_seed(1)
    net = torch.nn.Linear(4, 1)
    engine.fit(net, samples, None, _squared_error, tmp_path, engine.FitConfig(epochs=4, batch_size=1, lr=0.1, progress=False,
                                                                      warmup_fraction=0.0),
               engine.Runtime(0, 1, torch.device("cpu")), meta={})
    trained = torch.cat([p.detach().flatten() for p in net.parameters()])
    torch.testing.assert_close(trained, by_hand(clip=True), rtol=1e-6, atol=1e-7)
    assert not torch.allclose(trained, by_hand(clip=False), rtol=1e-4, atol=1e-5), "clipping changes nothing here"


def test_training_options_reach_the_training_loop():
    """Every option of the teacher and student commands that shapes training reaches fit: --min-lr, --weight-decay
    and --seed (batch order) were each one keyword away from being ignored, with their value still recorded in
    the recipe as if it had been used."""
    from training.train_teacher import fit_config

    args = _args("b", "o", "c", epochs=7, batch_size=3, lr=0.02, min_lr=0.001, weight_decay=0.3, seed=11, stop_after=2,
                 select="regl1", amp=True, no_progress=True)
    cfg = fit_config(args)
    assert (cfg.epochs, cfg.batch_size, cfg.lr, cfg.min_lr, cfg.weight_decay, cfg.seed, cfg.stop_after, cfg.select,
            cfg.amp, cfg.progress) == (7, 3, 0.02, 0.001, 0.3, 11, 2, "regl1", True, False)


def test_a_student_stopped_and_resumed_trains_the_weights_of_an_uninterrupted_run(bags, teacher_ckpt, tmp_path):
    """The README promises the same result after a resume, and the teacher's test showed it for a model without
    dropout or augmentation. A student with dropout, shifts and zooms draws random numbers every step: a resume
    must restore torch's RNG state, the optimizer and the schedule, and the run must be seeded, or the resumed
    student differs from the uninterrupted one (and two identical commands give two models)."""
    student = dict(kind="streaming", ablation="full", alpha=0.5, full_clips=False, teacher=str(teacher_ckpt),
                   set=["dropout=0.3"], shift=2, zoom=0.2, epochs=2)
    run_student(_args(bags, tmp_path / "ref", tmp_path / "cache", **student))
    run_student(_args(bags, tmp_path / "resumed", tmp_path / "cache", stop_after=1, **student))
    run_student(_args(bags, tmp_path / "resumed", tmp_path / "cache", **student))
    ref, resumed = (engine.load_checkpoint(tmp_path / name / engine.LAST) for name in ("ref", "resumed"))
    assert resumed["epoch"] == 2 and resumed["history"] == ref["history"]
    for key, value in ref["model"].items():
        torch.testing.assert_close(resumed["model"][key], value, rtol=0, atol=0)


def _student_validation(bags, cache, run, teacher_ckpt, val_fraction, seed, alpha, align_weight, regl1_weight,
                        ablation="full"):
    """A student run's validation figures recomputed from its last.pt: the first view of each validation
    instance, full clips, no mirror or reframing, the model in eval mode, all in one batch."""
    from training.train_teacher import load_teacher, teacher_targets

    model, meta = load_student(run / engine.LAST)
    ds = data.load_dataset(bags, cache, progress=False)
    _, val_idx = ds.split(val_fraction, seed)
    frames = data.resized_videos(ds, tuple(meta["config"]["input_size"]), progress=False)
    targets = teacher_targets(load_teacher(teacher_ckpt), ds, "cpu")
    videos = ds.first_view_videos(val_idx)
    clips = torch.stack([torch.from_numpy(data.as_unit_float(frames[ds.video_loc[j][0]][ds.video_loc[j][1]]))
                         for j in videos])
    instances = ds.video_instance[videos]
    batch = {"masks": clips, "valid": torch.ones(len(videos), 25), "label": torch.tensor(ds.labels[instances]),
             "target": torch.from_numpy(ds.params_norm[instances]), "mask": torch.from_numpy(ds.param_mask[instances]),
             "z_t": torch.from_numpy(targets[instances])}
    with torch.no_grad():
        loss, logs = student_loss(ablation, alpha, align_weight, regl1_weight)(model.eval(), batch, False)
    return {"loss": float(loss), **{k: float(v) for k, v in logs.items()}}


def test_a_students_figures_are_its_loss_on_unaugmented_validation_clips_with_the_weights_asked_for(
        bags, teacher_ckpt, tmp_path):
    """history.json's validation figures (which pick best.pt) are the student's loss on the first view of each
    held-out instance, whole and as rendered: not mirrored, shifted, zoomed or cut to a prefix as training clips
    are, not on the training instances, and with the --alpha asked for. The training loss is
    --align-weight x align + CE + --regl1-weight x RegL1 + the NLL term: weights set on the command line were
    recorded in the checkpoint even when the loss used the defaults."""
    from training.models.common import NLL_WEIGHT

    weights = dict(alpha=2.0, align_weight=0.3, regl1_weight=0.7)
    run_student(_args(bags, tmp_path / "s", tmp_path / "cache", epochs=1, kind="streaming", ablation="full",
                      full_clips=False, teacher=str(teacher_ckpt), shift=3, zoom=0.3, val_fraction=0.4,
                      set=["dropout=0.3"], **weights))
    record = engine.load_checkpoint(tmp_path / "s" / engine.LAST)["history"][0]
    expected = _student_validation(bags, tmp_path / "cache", tmp_path / "s", teacher_ckpt, 0.4, 0, **weights)
    for key, value in expected.items():
        assert record[f"val_{key}"] == pytest.approx(value, rel=1e-5, abs=1e-7), key
    assert record["train_loss"] == pytest.approx(0.3 * record["train_align"] + record["train_ce"] + 0.7 *
                                                 record["train_regl1"] + NLL_WEIGHT * record["train_nll"], rel=1e-5)


def test_a_teachers_figures_are_its_loss_on_the_validation_instances_untransformed(bags, tmp_path):
    """The teacher's validation figures are its loss on the held-out instances as simulated: the square
    symmetries are a training augmentation only, and the held-out part is the smaller one, not trained on."""
    from training.train_teacher import load_teacher, teacher_loss

    run_teacher(_args(bags, tmp_path / "t", tmp_path / "cache", epochs=1, val_fraction=0.4))
    record = engine.load_checkpoint(tmp_path / "t" / engine.LAST)["history"][0]
    teacher = load_teacher(tmp_path / "t" / engine.LAST)
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    train_idx, val_idx = ds.split(0.4, 0)
    assert len(val_idx) < len(train_idx)
    trajectories = torch.from_numpy(np.stack([ds.trajectory(i) for i in val_idx]))
    anchors, neighbours = teacher.tubes(trajectories[:, :1])
    batch = {"trajectory": trajectories, "anchors": anchors, "neighbours": neighbours,
             "label": torch.from_numpy(ds.labels[val_idx]), "target": torch.from_numpy(ds.params_norm[val_idx]),
             "mask": torch.from_numpy(ds.param_mask[val_idx])}
    with torch.no_grad():
        loss, logs = teacher_loss(teacher, batch, False)
    for key, value in {"loss": loss, **logs}.items():
        assert record[f"val_{key}"] == pytest.approx(float(value), rel=1e-5, abs=1e-7), key


def test_training_clips_are_drawn_anew_each_epoch_over_the_documented_ranges(bags, tmp_path):
    """The streaming student's prefixes span 10..25 frames (the full clip included), about half the clips are
    mirrored and the others not, shifts reach -PX..+PX in x and y independently and zooms both sides of 1 within
    [1 - FRAC, 1 + FRAC]; the draws change with the epoch, and validation clips (no augmentation) are never
    mirrored. A range one short, a mirror never or always taken, or the draws of epoch 0 repeated forever
    would each leave the batch tests above passing."""
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    frames = data.resized_videos(ds, (32, 32), progress=False)
    videos = np.arange(ds.num_videos)
    augmented = VideoSet(ds, videos, frames, None, random_prefix=True, augment=True, seed=3, shift=2, zoom=0.2)
    plain = VideoSet(ds, videos, frames, None, random_prefix=True, augment=False, seed=3)
    lengths, views, flips, per_epoch = [], [], [], []
    for epoch in range(8):
        augmented.set_epoch(epoch), plain.set_epoch(epoch)
        items = [augmented[k] for k in range(len(videos))]
        unaugmented = [plain[k] for k in range(len(videos))]
        lengths += [int(item["valid"].sum()) for item in items]
        views += [item["view"] for item in items]
        for item, other in zip(items, unaugmented):
            assert torch.equal(item["valid"], other["valid"])
            if not torch.equal(item["masks"], other["masks"]):
                assert torch.equal(item["masks"], other["masks"].flip(-1))  # mirrored left-right
                flips.append(True)
            else:
                flips.append(False)
        per_epoch.append(tuple(lengths[-len(videos):]))
    assert min(lengths) == 10 and max(lengths) == 25
    assert 0.3 < np.mean(flips) < 0.7
    views = torch.stack(views)
    assert 0.8 <= views[:, 0].min() < 0.9 and 1.1 < views[:, 0].max() <= 1.2
    for axis in (1, 2):
        assert set(views[:, axis].tolist()) == {-2.0, -1.0, 0.0, 1.0, 2.0}
    assert not torch.equal(views[:, 1], views[:, 2])
    assert len(set(per_epoch)) == len(per_epoch), "an epoch repeated another's prefixes"
    validation = VideoSet(ds, videos, frames, None, random_prefix=False, augment=False, seed=3)
    for k in range(len(videos)):
        s, r = ds.video_loc[k]
        assert torch.equal(validation[k]["masks"], torch.from_numpy(data.as_unit_float(frames[s][r])))


def test_teacher_symmetries_are_drawn_anew_each_epoch_and_only_transformed_items_change(bags, tmp_path):
    """Every one of the 8 square symmetries is drawn (the last included), the draws change with the epoch, and
    in a batch mixing the identity with other symmetries each item gets its own: identity items untouched."""
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    teacher = Teacher(TEACHER_PRESETS["tiny"])
    instances = np.arange(len(ds))
    augmented = TrajectorySet(ds, instances, True, 5, teacher)
    draws = []
    for epoch in range(6):
        augmented.set_epoch(epoch)
        draws.append(tuple(int(augmented[k]["sym"]) for k in range(len(instances))))
    assert set(sum(draws, ())) == set(range(8)) and len(set(draws)) == len(draws)
    epoch = next(e for e, d in enumerate(draws) if 0 in d and set(d) != {0})
    augmented.set_epoch(epoch)
    batch = augmented.collate([augmented[k] for k in range(len(instances))])
    for k, sym in enumerate(draws[epoch]):
        raw = torch.from_numpy(ds.trajectory(int(instances[k])))
        assert torch.equal(batch["trajectory"][k], raw) == (sym == 0)


def test_reframe_scales_shifts_by_each_axis_of_a_non_square_image():
    """--set input_size takes two numbers: on an image wider than tall, a shift of dx pixels in x is dx of the
    width's pixels, and dy of the height's."""
    masks = torch.zeros(1, 1, 16, 24)
    masks[..., 6:10, 10:14] = 1.0
    expected = torch.zeros_like(masks)
    expected[..., 7:11, 13:17] = 1.0  # 3 px right, 1 px down
    assert torch.equal(reframe(masks, torch.tensor([[1.0, 3, 1]])), expected)


def test_videos_on_device_copies_every_row_of_every_shard_in_order():
    """Videos are copied to the device 1024 at a time: shards of more than 1024 videos (the paper split's hold
    thousands) must arrive whole and in order, rows past the first chunk included."""
    shards = [np.arange(1030 * 2, dtype=np.float32).reshape(1030, 1, 2, 1), np.full((3, 1, 2, 1), -1.0, np.float32)]
    on_device = videos_on_device(shards, torch.device("cpu"), progress=False)
    torch.testing.assert_close(on_device, torch.from_numpy(np.concatenate(shards)), rtol=0, atol=0)


def test_a_loaded_teacher_gives_the_same_targets_every_time(bags, tmp_path):
    """The small and paper teachers train with dropout: the teacher a student distils must be loaded in eval mode,
    or every call of teacher_targets gives other z_T (dropout noise in the alignment targets)."""
    from training.train_teacher import load_teacher, teacher_targets

    config = dataclasses.replace(TEACHER_PRESETS["tiny"], dropout=0.5)
    torch.manual_seed(0)
    engine.save_checkpoint(tmp_path / "t.pt", {"model": Teacher(config).state_dict(), "meta": {"config": config.to_dict()}})
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    teacher = load_teacher(tmp_path / "t.pt")
    np.testing.assert_array_equal(teacher_targets(teacher, ds, "cpu"), teacher_targets(teacher, ds, "cpu"))


def test_a_resume_under_any_other_training_option_is_refused(bags, teacher_ckpt, tmp_path):
    """Every option in a student's recipe is checked on resume, each naming its old and new value: the earlier
    test covers --lr, --seed, --epochs and --select; a changed batch size, learning-rate floor, weight decay,
    validation fraction, augmentation or loss weight would each have gone on silently as another run."""
    student = dict(kind="streaming", ablation="full", alpha=0.5, full_clips=False, shift=1, zoom=0.1, epochs=2,
                   teacher=str(teacher_ckpt))
    run_student(_args(bags, tmp_path / "s", tmp_path / "cache", stop_after=1, **student))
    for option, value in (("batch_size", 2), ("min_lr", 1e-4), ("weight_decay", 0.0), ("val_fraction", 0.4),
                          ("shift", 2), ("zoom", 0.2), ("alpha", 1.0), ("align_weight", 0.5), ("regl1_weight", 0.5)):
        flag = "--" + option.replace("_", "-")
        with pytest.raises(ValueError, match=rf"was trained with {flag} \S+; this run asks for {flag} "
                                             rf"{re.escape(str(value))}\. Resume it"):
            run_student(_args(bags, tmp_path / "s", tmp_path / "cache", **{**student, option: value}))
    run_student(_args(bags, tmp_path / "s", tmp_path / "cache", **student))
    assert engine.load_checkpoint(tmp_path / "s" / engine.LAST)["epoch"] == 2


def test_the_stages_train_on_every_augmented_view_and_validate_on_plain_first_views(bags, tmp_path, monkeypatch):
    """What each command hands its training loop: the teacher trains on the split's training instances under
    random square symmetries; a student on every camera view of them (not one per instance), with random
    prefixes (streaming, unless --full-clips: clip students always see whole clips), mirrors and the --shift and
    --zoom asked for. Validation: the other instances, the first view, whole and untransformed. A training set
    left unaugmented, cut to one view or given whole clips trains a different model under the same command."""
    from training import train_student, train_teacher

    handed = {}

    def fit(model, train_set, val_set, *args, **kwargs):
        handed.update(train=train_set, val=val_set)

    monkeypatch.setattr(train_teacher, "fit", fit)
    monkeypatch.setattr(train_student, "fit", fit)
    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    train_idx, val_idx = ds.split(0.2, 0)
    run_teacher(_args(bags, tmp_path / "t", tmp_path / "cache"))
    train, val = handed["train"], handed["val"]
    assert (list(train.instances), train.augment) == (list(train_idx), True)
    assert (list(val.instances), val.augment) == (list(val_idx), False)
    cases = ((dict(kind="streaming", full_clips=False), True), (dict(kind="streaming", full_clips=True), False),
             (dict(kind="uniformer", full_clips=False), False))
    for options, prefixes in cases:
        run_student(_args(bags, tmp_path / "s", tmp_path / "cache", ablation="none", alpha=0.5, shift=3, zoom=0.25,
                          **options))
        train, val = handed["train"], handed["val"]
        assert list(train.videos) == list(ds.videos_of(train_idx)) and len(train.videos) == 2 * len(train_idx)
        assert (train.random_prefix, train.augment, train.shift, train.zoom) == (prefixes, True, 3, 0.25), options
        assert list(val.videos) == list(ds.first_view_videos(val_idx))
        assert (val.random_prefix, val.augment, val.shift, val.zoom) == (False, False, 0, 0.0), options


def test_the_teachers_predictions_are_its_own_outputs_for_each_episode(bags, teacher_ckpt, tmp_path):
    """evaluate-teacher's probabilities are the softmax of the teacher's logits over the three classes for each
    episode, and its parameters the heads' outputs in SI units, whatever episodes share its batch (a softmax over
    the batch instead also gives numbers between 0 and 1)."""
    from ad_sim.materials import PARAMETER_NAMES, denormalise

    from training.train_teacher import load_teacher, teacher_predictions

    ds = data.load_dataset(bags, tmp_path / "cache", progress=False)
    teacher = load_teacher(teacher_ckpt)
    predictions = teacher_predictions(teacher, ds, "cpu", batch_size=4)
    assert predictions.episode_ids == ds.episode_ids
    for k in (0, 5, 8):  # in the first, second and last (partial) batch
        with torch.no_grad():
            out = teacher(torch.from_numpy(ds.trajectory(k))[None])
        np.testing.assert_allclose(predictions.probabilities[k], torch.softmax(out["logits"][0], -1).numpy(), rtol=1e-4,
                                   atol=1e-6)
        si = [denormalise(name, out["params"][0, j].item()) for j, name in enumerate(PARAMETER_NAMES)]
        np.testing.assert_allclose(predictions.pred_params[k], si, rtol=1e-4)
