"""Stage I: train the trajectory teacher on cached bags."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset as TorchDataset
from torch.utils.data import default_collate
from tqdm import tqdm

from ad_estimator.cli import count, fraction, non_negative_number, positive, positive_number, seed, torch_device_or_auto
from ad_estimator.metrics import Predictions
from ad_sim.materials import FRAME_COUNT, PARAMETER_NAMES, denormalise
from training import data
from training.engine import (BEST, LAST, SELECT_METRICS, FitConfig, check_recipe, check_resumable, fit, init_runtime,
                             load_checkpoint, main_first, model_from_checkpoint, seed_everything, wants_on_device)
from training.evaluate import print_results, write_evaluation
from training.models.common import task_loss
from training.models.teacher import TEACHER_PRESETS, Teacher, TeacherConfig


def _square_symmetries() -> np.ndarray:
    """The 8 symmetries of the domain's square footprint (rotations by 90 deg about z, mirrors);
    gravity and the walls are invariant under them, so they are exact augmentations."""
    out = []
    for k in range(4):
        c, s = [1, 0, -1, 0][k], [0, 1, 0, -1][k]
        r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float32)
        out += [r, r @ np.diag([-1.0, 1.0, 1.0]).astype(np.float32)]
    return np.stack(out)


SYMMETRIES = _square_symmetries()  # index 0 is the identity


def transform_trajectories(traj: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Applies orthogonal maps r (B, 3, 3) about the domain centre to trajectories (B, T, N, 15):
    x -> r (x - c) + c, dx -> r dx, F -> r F r^T."""
    centre = traj.new_tensor([0.5, 0.5, 0.0])
    r = r.to(traj)
    rt = r.transpose(-1, -2)[:, None]  # (B, 1, 3, 3): the same map for every frame of a trajectory
    f = traj[..., 6:].unflatten(-1, (3, 3))
    f = r[:, None, None] @ f @ rt[:, None]
    return torch.cat([(traj[..., :3] - centre) @ rt + centre, traj[..., 3:6] @ rt, f.flatten(-2)], dim=-1)


class TrajectoriesOnDevice:
    """Every instance's trajectory and point tubes in device memory, rows in instance order: the paper
    split's 9,000 trajectories are 14 GB as float32, fine on a data-centre GPU. Building batches there
    removes the per-item host work (reading, symmetry transform) that kept the GPU waiting."""

    def __init__(self, ds: data.Dataset, teacher: Teacher, device: torch.device, progress: bool = False,
                 chunk: int = 256):
        self.trajectories = torch.empty((len(ds), *ds.trajectory(0).shape), dtype=torch.float32, device=device)
        anchors, neighbours = [], []
        for start in tqdm(range(0, len(ds), chunk), desc="trajectories to device", unit="chunk", disable=None if progress else True,
                          leave=False):
            rows = range(start, min(len(ds), start + chunk))  # bounded host memory per copy
            part = torch.from_numpy(np.stack([ds.trajectory(i) for i in rows])).to(device)
            self.trajectories[start:start + len(part)] = part
            a, n = teacher.tubes(part[:, :1])
            anchors.append(a), neighbours.append(n)
        self.anchors, self.neighbours = torch.cat(anchors), torch.cat(neighbours)


class TrajectorySet(TorchDataset):
    """Trajectories with labels and each instance's point tubes (anchors and neighbours at t=0,
    computed once: they depend only on the first frame, and the square symmetries keep them).

    Items carry a symmetry (index into SYMMETRIES; the identity without `augment`) that `collate`
    applies to the whole batch. With `on_device`, items carry only the instance's row, and `collate`
    gathers trajectories and tubes on that device: the same batches as the host path."""

    def __init__(self, ds: data.Dataset, instances: np.ndarray, augment: bool, seed: int, teacher: Teacher,
                 on_device: TrajectoriesOnDevice | None = None):
        self.ds, self.instances, self.augment, self.seed, self.epoch = ds, instances, augment, seed, 0
        self.teacher, self.on_device = teacher, on_device
        self._tubes: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.instances)

    def __getitem__(self, k: int) -> dict:
        i = int(self.instances[k])
        sym = int(np.random.default_rng([self.seed, self.epoch, i]).integers(len(SYMMETRIES))) if self.augment else 0
        item = {"sym": torch.tensor(sym), "label": torch.tensor(self.ds.labels[i]),
                "target": torch.from_numpy(self.ds.params_norm[i]), "mask": torch.from_numpy(self.ds.param_mask[i])}
        if self.on_device is not None:
            item["row"] = torch.tensor(i)
            return item
        traj = torch.from_numpy(self.ds.trajectory(i))
        if i not in self._tubes:
            anchors, neighbours = self.teacher.tubes(traj[None, :1])
            self._tubes[i] = (anchors[0], neighbours[0])
        item.update(trajectory=traj, anchors=self._tubes[i][0], neighbours=self._tubes[i][1])
        return item

    def collate(self, items: list[dict]) -> dict:
        batch = default_collate(items)
        if self.on_device is not None:
            rows = batch.pop("row").to(self.on_device.trajectories.device)
            batch.update(trajectory=self.on_device.trajectories[rows], anchors=self.on_device.anchors[rows],
                         neighbours=self.on_device.neighbours[rows])
        sym = batch.pop("sym")
        if sym.any():
            batch["trajectory"] = transform_trajectories(batch["trajectory"], torch.from_numpy(SYMMETRIES)[sym])
        return batch


def teacher_loss(model, batch, train: bool):
    out = model(batch["trajectory"], batch["anchors"], batch["neighbours"])
    return task_loss(out, batch["label"], batch["target"], batch["mask"])


def load_teacher(path: str | Path, device="cpu") -> Teacher:
    state = load_checkpoint(path, "teacher")
    teacher = model_from_checkpoint(path, "teacher", state, lambda config: Teacher(TeacherConfig.from_dict(config)))
    return teacher.to(device).eval()


@torch.no_grad()
def _teacher_outputs(teacher: Teacher, ds: data.Dataset, device, batch_size: int, instances=None):
    """The frozen teacher's outputs (eval mode, no augmentation), a batch of instances at a time, in order
    (`instances`: these indices, default all)."""
    instances = range(len(ds)) if instances is None else instances
    for start in range(0, len(instances), batch_size):
        idx = instances[start:start + batch_size]
        yield teacher(torch.from_numpy(np.stack([ds.trajectory(int(i)) for i in idx])).to(device))


def teacher_targets(teacher: Teacher, ds: data.Dataset, device, batch_size: int = 16) -> np.ndarray:
    """z_T of every instance: (N, z_dim) float32."""
    out = [o["z"].float().cpu().numpy() for o in _teacher_outputs(teacher, ds, device, batch_size)]
    return np.concatenate(out) if out else np.zeros((0, teacher.config.z_dim), np.float32)


def teacher_predictions(teacher: Teacher, ds: data.Dataset, device, batch_size: int = 16) -> Predictions:
    """The teacher's estimates for each episode of ds once (a repeat or copy scored once, as the students'
    evaluation does), as metrics.Predictions (SI parameters)."""
    scored = ds.first_copies()
    probs, params = [], []
    for out in _teacher_outputs(teacher, ds, device, batch_size, scored):
        probs.append(torch.softmax(out["logits"].float(), -1).cpu().numpy())
        params.append(out["params"].float().clamp(0, 1).cpu().numpy())
    normalised = np.concatenate(params)
    si = np.stack([denormalise(n, normalised[:, j]) for j, n in enumerate(PARAMETER_NAMES)], axis=1)
    return Predictions(ds.labels[scored], ds.params_si[scored], np.concatenate(probs), si,
                       [ds.episode_ids[i] for i in scored])


def add_common_args(p: argparse.ArgumentParser, epochs: int, batch_size: int, lr: float = 1e-4) -> None:
    p.add_argument("--bags", required=True, help="folder of training .mcap bags (searched recursively)")
    p.add_argument("--cache", default=".cache/training", help="array cache folder (keyed by bag content)")
    p.add_argument("--out", required=True, help="run folder: checkpoints, history; an existing one is resumed")
    p.add_argument("--size", choices=["tiny", "small", "paper"], default="small",
                   help="model size preset; it picks the model only: --epochs, --batch-size and --lr keep their own "
                        "defaults (SPEC 9's paper recipe; `pipeline` sets per-size ones)")
    p.add_argument("--epochs", type=positive, default=epochs, help=f"epochs (default {epochs}; paper values in SPEC 9)")
    p.add_argument("--batch-size", type=positive, default=batch_size, help="per-process batch size")
    # Checked here, before anything is written: AdamW refuses them only once the data has loaded.
    p.add_argument("--lr", type=positive_number, default=lr, help="AdamW peak learning rate (cosine to --min-lr)")
    p.add_argument("--min-lr", type=non_negative_number, default=1e-6,
                   help="floor of the cosine schedule (approached over the last steps)")
    p.add_argument("--weight-decay", type=non_negative_number, default=1e-4, help="AdamW weight decay")
    p.add_argument("--val-fraction", type=fraction, default=0.1, help="instances held out for validation")
    p.add_argument("--seed", type=seed, default=0,
                   help="seeds initialisation, the validation split (--val-fraction), batch order, "
                        "augmentation and the students' random prefixes")
    p.add_argument("--device", type=torch_device_or_auto, default="auto",
                   help="auto | cpu | cuda | cuda:<index> (torchrun: one process per GPU)")
    p.add_argument("--threads", type=count, default=0, help="torch CPU threads (0: torch default)")
    p.add_argument("--amp", action="store_true", help="bfloat16 autocast (CUDA only)")
    p.add_argument("--stop-after", type=count, default=0,
                   help="stop after this many epochs in this run (time-limited sessions); rerun to continue")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--select", choices=SELECT_METRICS, default="score",
                   help="validation metric that picks best.pt: score = CE + RegL1 (favours classification), "
                        "regl1 = RegL1 alone (favours the parameters planners use); keep it when resuming")


# The options that make a training run what it is, beside its model config (engine.check_resumable): a
# resumed run must keep them. Paths (--bags, --cache, --teacher) may move between machines, and --device,
# --threads, --amp, --stop-after and progress only change how it runs.
RECIPE_OPTIONS = ("epochs", "batch_size", "lr", "min_lr", "weight_decay", "val_fraction", "seed", "select")


def recipe(args, rt, names: tuple[str, ...] = RECIPE_OPTIONS) -> dict:
    """{command-line flag: value} of `names` in args, and the number of processes (with the batch
    size, it sets the steps per epoch and so the learning-rate schedule)."""
    return {"--" + name.replace("_", "-"): getattr(args, name) for name in names} | {"torchrun processes": rt.world}


def load_run_data(args, rt, resumed: dict | None, coverage: bool = False,
                  videos: bool = False) -> tuple[data.Dataset, dict]:
    """The instances under --bags and their recipe entries; a run being resumed (`resumed`: its
    recorded recipe, from check_resumable) must have trained on the same ones. `videos` (a student,
    which trains on every camera view of an instance): the views count too, so that a resume on
    bags with other cameras is refused rather than mixed in. Warns when they include the benchmark's
    test instances, and when `resumed` predates an entry (it cannot be checked). `coverage`: grey
    mask videos (data.load_dataset)."""
    ds = main_first(rt, lambda: data.load_dataset(args.bags, args.cache, progress=rt.main and not args.no_progress,
                                                  coverage=coverage))
    bags = {"--bags contents": ds.fingerprint()} | ({"--bags camera views": ds.camera_views()} if videos else {})
    if resumed is not None:
        last = Path(args.out) / LAST
        check_recipe(last, resumed, bags)
        if rt.main and (unchecked := [entry for entry in bags if entry not in resumed]):
            tqdm.write(f"warning: {last} was written before its {' and '.join(unchecked)} were recorded, so this "
                       f"resume cannot check them: make sure --bags {args.bags} holds the data it trained on "
                       f"({', '.join(f'{entry} {bags[entry]}' for entry in unchecked)}), or train into a new --out",
                       file=sys.stderr)
    if rt.main and (warning := ds.test_split_warning(args.bags)):
        tqdm.write(warning, file=sys.stderr)
    return ds, bags


def fit_config(args) -> FitConfig:
    return FitConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, weight_decay=args.weight_decay,
                     min_lr=args.min_lr, seed=args.seed, progress=not args.no_progress,
                     stop_after=args.stop_after, amp=args.amp, select=args.select)


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training teacher")
    p.description = ("Stage I: train the P4Transformer-style trajectory teacher (CE + masked RegL1) on the "
                     "tracked particles of MCAP bags. Writes <out>/last.pt (resume) and <out>/best.pt.")
    add_common_args(p, epochs=300, batch_size=32, lr=1e-4)
    p.add_argument("--trajectories-on-device", choices=["auto", "yes", "no"], default="auto",
                   help="keep every trajectory on the GPU and build batches there (auto: on CUDA)")
    return p


def run(args) -> Path:
    if args.threads:
        torch.set_num_threads(args.threads)
    seed_everything(args.seed)
    rt = init_runtime(args.device)
    config = TEACHER_PRESETS[args.size]
    resumed = check_resumable(Path(args.out), recipe(args, rt), config.to_dict(), "teacher")
    ds, bags = load_run_data(args, rt, resumed)
    train_idx, val_idx = ds.split(args.val_fraction, args.seed)
    model = Teacher(config).to(rt.device)
    on_device = None
    if wants_on_device(args.trajectories_on_device, rt):
        on_device = TrajectoriesOnDevice(ds, model, rt.device, rt.main and not args.no_progress)
    out = Path(args.out)
    fit(model, TrajectorySet(ds, train_idx, True, args.seed, model, on_device),
        TrajectorySet(ds, val_idx, False, args.seed, model, on_device),
        teacher_loss, out, fit_config(args), rt, meta={"config": config.to_dict(), "size": args.size},
        desc="teacher", recipe=recipe(args, rt) | bags)
    return out / BEST


def build_eval_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training evaluate-teacher")
    p.description = ("Evaluate a trained teacher on bags' tracked particles (privileged states the robot never "
                     "has): the paper's table for all 25 frames, as a reference for the video students "
                     "distilled from it, which see less. Writes metrics.json, report.md, plots and per-episode "
                     "predictions.json.")
    p.add_argument("--teacher", required=True, help="teacher checkpoint (best.pt of `python -m training teacher`)")
    p.add_argument("--bags", required=True, help="evaluation bags (e.g. bags/paper/unseen)")
    p.add_argument("--cache", default=".cache/training", help="array cache folder")
    p.add_argument("--out", required=True, help="report folder")
    p.add_argument("--title", help="report title (default: the checkpoint and the bags)")
    p.add_argument("--device", type=torch_device_or_auto, default="auto", help="auto | cpu | cuda | cuda:<index>")
    p.add_argument("--amp", action="store_true", help="bfloat16 autocast (CUDA only)")
    p.add_argument("--batch-size", type=int, default=64, help="instances per forward pass")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def run_eval(args) -> dict:
    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be at least 1, got {args.batch_size}")
    device = init_runtime(args.device).device
    teacher = load_teacher(args.teacher, device)
    ds = data.load_dataset(args.bags, args.cache, progress=not args.no_progress)
    with torch.autocast(device.type, torch.bfloat16, enabled=args.amp and device.type == "cuda"):
        predictions = teacher_predictions(teacher, ds, device, args.batch_size)
    title = args.title or f"teacher {args.teacher} on {args.bags}"
    results = write_evaluation({FRAME_COUNT: predictions}, args.out, title, {"teacher": str(args.teacher)})
    print_results(results, title, args.out)
    return results
