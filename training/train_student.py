"""Stage II: distil the frozen teacher into a video student (streaming or UniFormer-style)."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset as TorchDataset
from torch.utils.data import default_collate
from tqdm import tqdm

from ad_estimator.cli import count, fraction
from training import data
from training.engine import (BEST, check_resumable, fit, init_runtime, load_checkpoint, main_first,
                             model_from_checkpoint, seed_everything, wants_on_device, weights_digest)
from training.models.common import NLL_WEIGHT, align_loss, task_loss
from training.models.student import FRAME_COUNT, StudentConfig, build_student, override_config, student_preset
from training.models.teacher import TEACHER_PRESETS
from training.train_teacher import (RECIPE_OPTIONS, add_common_args, fit_config, load_run_data, load_teacher, recipe,
                                    teacher_targets)

ABLATIONS = ("none", "align_only", "full")
# SystemExit's messages carry the prefix that __main__ gives ValueErrors, so that all errors read alike.
PROG = "python -m training student"
# SPEC 9: 0.1 align + 1.0 CE + 0.2 RegL1 (+ NLL_WEIGHT, a small weight on the uncertainty head's NLL).
ALIGN_WEIGHT, CE_WEIGHT, REGL1_WEIGHT = 0.1, 1.0, 0.2
MIN_PREFIX = 10  # the streaming student sees random prefixes of 10..25 frames: estimates are anytime


class VideoSet(TorchDataset):
    """Mask videos (one item per instance view) with labels and the teacher target of the
    video's instance (shared by all its views).

    With `on_device` (a tensor of every video, from `videos_on_device`) items carry only the video's
    row, prefix length and mirror flag, and `collate` assembles the masks on that device: the
    same batches as the host path, without a host-to-device copy of every clip.

    With `augment`, clips are mirrored at random and, where `shift` (pixels) or `zoom` (a fraction)
    is set, reframed as a slightly different camera would see them (`reframe`): more views of each
    instance than the 4 rendered ones."""

    def __init__(self, ds: data.Dataset, videos: np.ndarray, frames: list[np.ndarray], targets: np.ndarray | None,
                 random_prefix: bool, augment: bool, seed: int, on_device: torch.Tensor | None = None,
                 shift: int = 0, zoom: float = 0.0):
        self.ds, self.videos, self.frames, self.targets = ds, videos, frames, targets
        self.random_prefix, self.augment, self.seed, self.epoch = random_prefix, augment, seed, 0
        self.on_device, self.shift, self.zoom = on_device, shift, zoom

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.videos)

    def __getitem__(self, k: int) -> dict:
        j = int(self.videos[k])
        i = int(self.ds.video_instance[j])
        rng = np.random.default_rng([self.seed, self.epoch, j])
        length = int(rng.integers(MIN_PREFIX, FRAME_COUNT + 1)) if self.random_prefix else FRAME_COUNT
        flip = bool(self.augment and rng.random() < 0.5)  # mirror world = mirrored image
        item = {"valid": torch.from_numpy((np.arange(FRAME_COUNT) < length).astype(np.float32)),
                "label": torch.tensor(self.ds.labels[i]), "target": torch.from_numpy(self.ds.params_norm[i]),
                "mask": torch.from_numpy(self.ds.param_mask[i])}
        if self.targets is not None:
            item["z_t"] = torch.from_numpy(self.targets[i])
        if self.augment and (self.shift or self.zoom):  # drawn after the flip: runs without them are unchanged
            dx, dy = rng.integers(-self.shift, self.shift + 1, size=2)
            item["view"] = torch.tensor([rng.uniform(1 - self.zoom, 1 + self.zoom), dx, dy], dtype=torch.float32)
        if self.on_device is not None:
            item.update(row=torch.tensor(j), flip=torch.tensor(flip))
            return item
        s, r = self.ds.video_loc[j]
        masks = data.as_unit_float(self.frames[s][r])
        masks[length:] = 0.0
        if flip:
            masks = masks[:, :, ::-1].copy()
        item["masks"] = torch.from_numpy(masks)
        return item

    def collate(self, items: list[dict]) -> dict:
        batch = default_collate(items)
        if self.on_device is not None:
            rows, flip = batch.pop("row").to(self.on_device.device), batch.pop("flip").to(self.on_device.device)
            masks = self.on_device[rows].float()
            if self.on_device.dtype == torch.uint8:
                masks = masks * (1.0 / 255.0)
            masks = torch.where(flip[:, None, None, None], masks.flip(-1), masks)
            batch["masks"] = masks * batch["valid"].to(masks.device)[:, :, None, None]
        if "view" in batch:
            batch["masks"] = reframe(batch["masks"], batch.pop("view"))
        return batch


def reframe(masks: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """Clips (B, T, H, W) as seen by a camera zoomed by view[:, 0] about the image centre and shifted by
    view[:, 1:] = (dx, dy) pixels: the same transform for every frame of a clip, nearest-neighbour so
    that masks stay binary, empty outside the original image. Zoom stands for another camera distance
    (the rendered ones span 1.5 to 2.0 m) and a shift for another aim (up to a few pixels)."""
    b, _, h, w = masks.shape
    zoom, dx, dy = view.to(masks.device, torch.float32).unbind(1)
    # affine_grid maps output to input coordinates, normalised to [-1, 1] (align_corners=False).
    theta = torch.zeros(b, 2, 3, device=masks.device)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0 / zoom
    theta[:, 0, 2] = -2.0 * dx / (w * zoom)
    theta[:, 1, 2] = -2.0 * dy / (h * zoom)
    grid = F.affine_grid(theta, list(masks.shape), align_corners=False)
    return F.grid_sample(masks, grid.to(masks.dtype), mode="nearest", padding_mode="zeros", align_corners=False)


def videos_on_device(frames: list[np.ndarray], device: torch.device, progress: bool) -> torch.Tensor:
    """Every video of `frames` (per shard, as `resized_videos` gives them) in one tensor on `device`,
    rows in global video order. The paper split at 128x128 uint8 is 15 GB: fine on a data-centre GPU."""
    total = sum(len(f) for f in frames)
    out = torch.empty((total, *frames[0].shape[1:]), dtype=torch.from_numpy(np.empty(0, frames[0].dtype)).dtype, device=device)
    row = 0
    for f in tqdm(frames, desc="videos to device", unit="bag", disable=None if progress else True, leave=False):
        for start in range(0, len(f), 1024):  # bounded host memory per copy
            chunk = np.array(f[start:start + 1024])  # a writable copy: torch warns on read-only memmaps
            out[row:row + len(chunk)] = torch.from_numpy(chunk).to(device)
            row += len(chunk)
    return out


def student_loss(ablation: str, alpha: float, align_weight: float = ALIGN_WEIGHT, regl1_weight: float = REGL1_WEIGHT):
    if ablation not in ABLATIONS:
        raise ValueError(f"unknown ablation {ablation!r}; expected one of {ABLATIONS}")

    def loss_fn(model, batch, train: bool):
        out = model(batch["masks"], batch["valid"])
        task, logs = task_loss(out, batch["label"], batch["target"], batch["mask"], regl1_weight, NLL_WEIGHT, CE_WEIGHT)
        if ablation == "none":
            return task, logs
        align = align_loss(out["z"], batch["z_t"], alpha)
        logs["align"] = align.detach()
        if ablation == "align_only":  # predictions come from the teacher's frozen predictor
            return align, logs
        return align_weight * align + task, logs

    return loss_fn


def load_student(path: str | Path, device="cpu") -> tuple[torch.nn.Module, dict]:
    state = load_checkpoint(path, "student")
    model = model_from_checkpoint(path, "student", state, lambda config: build_student(StudentConfig.from_dict(config)))
    return model.to(device).eval(), state["meta"]


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training student")
    p.description = ("Stage II: train a video student on the bags' mask videos, aligned with the frozen "
                     "teacher (loss 0.1 align + 1.0 CE + 0.2 RegL1). Writes <out>/last.pt and <out>/best.pt.")
    add_common_args(p, epochs=20, batch_size=32, lr=1e-4)
    p.add_argument("--teacher", help="teacher checkpoint (best.pt of `teacher`); required unless --ablation none")
    p.add_argument("--kind", choices=["streaming", "uniformer"], default="streaming", help="student encoder")
    p.add_argument("--ablation", choices=ABLATIONS, default="full",
                   help="none: task losses only; align_only: alignment only (teacher's predictor); full: both")
    p.add_argument("--alpha", type=float, default=0.5, help="weight of the L1 term inside the alignment loss")
    p.add_argument("--align-weight", type=float, default=ALIGN_WEIGHT, help="weight of the alignment loss (SPEC: 0.1)")
    p.add_argument("--regl1-weight", type=float, default=REGL1_WEIGHT, help="weight of RegL1 (SPEC: 0.2)")
    p.add_argument("--videos-on-device", choices=["auto", "yes", "no"], default="auto",
                   help="keep every training video on the GPU and build batches there (auto: on CUDA)")
    p.add_argument("--encoder-channels", type=_channels, metavar="C1,C2,...",
                   help="streaming: channels of the frame encoder's stride-2 stages (default: the size preset's; "
                        "wider costs CPU time per frame, see benchmarks/latency.py)")
    p.add_argument("--previous-frames", type=count, default=0, metavar="N",
                   help="streaming: the frame encoder also sees the N earlier observed frames (early fusion of "
                        "time; the estimator passes them on); the bundled model: 3")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a field of the size preset's model config, repeatable: e.g. --set dropout=0 "
                        "--set pool=8 (the fields are StudentConfig's in training/models/student.py; saved in the "
                        "checkpoint, so export and the estimator follow)")
    p.add_argument("--shift", type=count, default=0, metavar="PX",
                   help="augmentation: shift each training clip by up to PX pixels in x and y (default 0: off)")
    p.add_argument("--zoom", type=fraction, default=0.0, metavar="FRAC",
                   help="augmentation: zoom each training clip by a factor in [1 - FRAC, 1 + FRAC] about the image "
                        "centre (default 0: off; the rendered cameras' distances span about +-14%%; 0.35 makes the "
                        "student tolerate cameras framed 0.8x to 1.33x the simulator's, training/README.md)")
    p.add_argument("--full-clips", action="store_true",
                   help="train on full 25-frame clips only (default: streaming students see random prefixes)")
    return p


def student_recipe(args, rt, teacher: torch.nn.Module | None) -> dict:
    """The teacher's recipe and the student's loss and augmentation, only where they act (the model's
    own options are in its config; student_loss says which weight acts in which ablation):
    --full-clips only for streaming students, as clip students always see full clips. And which
    teacher it distils (its weights' digest: a teacher trained further under the same path is
    another teacher)."""
    acting = {"regl1_weight": args.ablation != "align_only", "alpha": args.ablation != "none",
              "align_weight": args.ablation == "full", "full_clips": args.kind == "streaming"}
    names = ("ablation", "shift", "zoom") + tuple(name for name, acts in acting.items() if acts)
    digest = {}
    if teacher is not None and args.ablation != "none":
        digest = {"--teacher contents": weights_digest(teacher)[:12]}
    return recipe(args, rt, RECIPE_OPTIONS + names) | digest


def _channels(text: str) -> tuple[int, ...]:
    try:
        channels = tuple(int(c) for c in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers like 24,48,96,192, got {text!r}") from None
    if not channels or min(channels) < 1:
        raise argparse.ArgumentTypeError(f"channels must be positive, got {text!r}")
    return channels


def run(args) -> Path:
    if args.threads:
        torch.set_num_threads(args.threads)
    seed_everything(args.seed)
    rt = init_runtime(args.device)
    if (args.encoder_channels or args.previous_frames) and args.kind != "streaming":
        raise SystemExit(f"{PROG}: --encoder-channels and --previous-frames apply to the streaming student only")
    if args.ablation != "none" and not args.teacher:
        raise SystemExit(f"{PROG}: --teacher is required for --ablation align_only/full (train one with `python -m "
                         "training teacher`), or use --ablation none")
    teacher = load_teacher(args.teacher, rt.device) if args.teacher else None
    z_dim = teacher.config.z_dim if teacher else TEACHER_PRESETS[args.size].z_dim
    config = student_preset(args.kind, args.size, z_dim)
    if args.encoder_channels:
        config = dataclasses.replace(config, channels=args.encoder_channels)
    if args.previous_frames:
        config = dataclasses.replace(config, previous_frames=args.previous_frames)
    try:
        config = override_config(config, args.set or [])
        # Built once, before the data loads, so a bad combination (say, a pool the input size cannot
        # give) fails early; loading the data draws no torch random numbers, so the init is as before.
        model = build_student(config)
    except ValueError as e:
        raise SystemExit(f"{PROG}: {e}") from None
    run_recipe = student_recipe(args, rt, teacher)
    resumed = check_resumable(Path(args.out), run_recipe, config.to_dict(), "student",
                              saved_config=lambda saved: StudentConfig.from_dict(saved).to_dict())
    ds, bags = load_run_data(args, rt, resumed, coverage=config.mask_levels == "coverage", videos=True)
    train_idx, val_idx = ds.split(args.val_fraction, args.seed)
    targets = teacher_targets(teacher, ds, rt.device) if teacher and args.ablation != "none" else None
    frames = main_first(rt, lambda: data.resized_videos(ds, tuple(config.input_size),
                                                          rt.main and not args.no_progress))

    if teacher is not None and args.ablation != "none":
        model.heads.predictor.load_state_dict(teacher.heads.predictor.state_dict())
        if args.ablation == "align_only":
            model.heads.predictor.requires_grad_(False)
    model.to(rt.device)
    del teacher
    prefix = config.kind == "streaming" and not args.full_clips
    on_device = None
    if wants_on_device(args.videos_on_device, rt):
        on_device = videos_on_device(frames, rt.device, rt.main and not args.no_progress)
    train_set = VideoSet(ds, ds.videos_of(train_idx), frames, targets, prefix, True, args.seed, on_device,
                         args.shift, args.zoom)
    val_set = VideoSet(ds, ds.first_view_videos(val_idx), frames, targets, False, False, args.seed, on_device)
    meta = {"config": config.to_dict(), "size": args.size, "ablation": args.ablation, "kind": config.kind,
            "teacher": str(args.teacher or ""), "seed": args.seed, "augment": {"shift": args.shift, "zoom": args.zoom},
            "loss_weights": {"align": args.align_weight, "ce": CE_WEIGHT, "regl1": args.regl1_weight, "nll": NLL_WEIGHT}}
    out = Path(args.out)
    fit(model, train_set, val_set, student_loss(args.ablation, args.alpha, args.align_weight, args.regl1_weight), out, fit_config(args), rt, meta,
        desc=f"student[{config.kind},{args.ablation}]", recipe=run_recipe | bags)
    return out / BEST
