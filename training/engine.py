"""Training loop shared by teacher and students: AdamW + cosine schedule, DDP via torchrun,
checkpoints every epoch that resume after a kill.

Checkpoints hold only tensors, dicts, lists, ints, floats, strs and bools so that they load with
torch.load(weights_only=True).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler, Subset
from tqdm import tqdm

from ad_estimator.cli import staged, write_text_staged

LAST = "last.pt"
BEST = "best.pt"


@dataclass
class Runtime:
    rank: int
    world: int
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0


def resolve_device(device: str) -> str:
    """--device auto -> cuda if torch sees a GPU, else cpu; any other device as given."""
    return ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device


def init_runtime(device: str = "auto") -> Runtime:
    """Single process, or one process per GPU/CPU slot under torchrun (WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = resolve_device(device)
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but torch sees no GPU; use --device cpu")
    if world > 1:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        if device.startswith("cuda"):
            torch.cuda.set_device(local)
            dev = torch.device("cuda", local)
        else:
            dev = torch.device("cpu")
        if not dist.is_initialized():
            # DistributedDataParallel imports torch._dynamo; imported once a process group exists, it keeps
            # references to it that destroy_process_group cannot drop, so the group's threads outlive
            # close_runtime and are torn down at exit, where a rank can abort ("terminate called without an
            # active exception", after its work is saved). Imported before, it holds none.
            importlib.import_module("torch._dynamo")
            # device_id binds NCCL to this rank's GPU (else it guesses from the rank, and warns).
            if dev.type == "cuda":
                dist.init_process_group("nccl", device_id=dev)
            else:
                dist.init_process_group("gloo")
        return Runtime(dist.get_rank(), world, dev)
    return Runtime(0, 1, torch.device(device))


def close_runtime() -> None:
    """Ends the process group, if any, and with it its threads (see init_runtime). Without it a rank can
    abort at exit while gloo's threads are still alive ("terminate called without an active exception")."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def main_first(rt: Runtime, work: Callable):
    """Runs `work` on rank 0 first (e.g. filling a cache), then on the other ranks."""
    if rt.main:
        result = work()
    if rt.world > 1:
        dist.barrier()
    if not rt.main:
        result = work()
    return result


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def cosine_lr(step: int, total: int, lr: float, min_lr: float, warmup: int) -> float:
    """Linear warm-up, then cosine from lr down to min_lr at the last step."""
    if step < warmup:
        return lr * (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_lr + 0.5 * (lr - min_lr) * (1.0 + math.cos(math.pi * progress))


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _on_cpu(obj):
    """Tensors anywhere in nested dicts/lists moved to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _on_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_on_cpu(v) for v in obj)
    return obj


def save_checkpoint(path: Path, state: dict) -> None:
    """Through cli.staged: a kill mid-write leaves the previous checkpoint intact. Tensors are saved from the
    CPU, so a checkpoint trained on a GPU opens with a bare torch.load on a CPU-only machine."""
    with staged(path.parent) as folder:
        torch.save(_on_cpu(state), folder / path.name)


def _is_onnx(path: str | Path) -> bool:
    """Whether `path` holds an ONNX model (what `export` writes, easily passed for its checkpoint)."""
    try:
        import onnx

        model = onnx.load(str(path), load_external_data=False)
        return bool(model.ir_version) and len(model.graph.node) > 0
    except Exception:  # not protobuf at all: not an ONNX model
        return False


def _short_reason(e: Exception) -> str:
    """A load error in one line. torch's weights-only refusal spans several lines and advises loading
    with weights_only=False, which a foreign file must not be: only its unpickler's own reason is kept."""
    text = str(e)
    if "WeightsUnpickler error:" in text:
        detail = text.split("WeightsUnpickler error:", 1)[1].strip().split("\n")[0].split(". ")[0].rstrip(".")
        return f"it holds objects other than tensors and plain values ({detail})"
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if isinstance(e, ValueError) and first:  # ours (e.g. a config's field), already worded for a reader
        return first
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def incompatible(path: str | Path, stage: str, reason: str) -> ValueError:
    """The one-line error for a checkpoint that loads but cannot be this stage's model."""
    return ValueError(f"{path} is not a compatible {stage} checkpoint: {reason}")


def load_checkpoint(path: str | Path, stage: str | None = None) -> dict:
    """A checkpoint written by `fit`, on the CPU, with a clear error for a truncated or foreign file
    (an ONNX model named as such) and, with `stage` ("teacher" or "student"), for a checkpoint of the
    other stage or one without a model config (`model_from_checkpoint` checks the config and weights)."""
    if Path(path).is_dir():
        raise ValueError(f"{path} is a folder; pass a checkpoint in it, e.g. {Path(path) / BEST}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # a truncated archive, a pickle with foreign objects, not a torch file at all
        if _is_onnx(path):
            raise ValueError(f"{path} is an ONNX model (what `python -m training export` writes), not a checkpoint; "
                             "pass the training run's best.pt") from e
        raise ValueError(f"{path} is not a readable checkpoint ({_short_reason(e)}); copy it again or "
                         "retrain") from e
    if not isinstance(state, dict) or not {"model", "meta"} <= state.keys():
        raise ValueError(f"{path} is not a checkpoint written by python -m training (it has no model and meta)")
    meta = state["meta"]
    if not isinstance(meta, dict):  # (below, .get on it would be an AttributeError)
        if stage:
            raise incompatible(path, stage, f"its meta is a {type(meta).__name__}, not a dict")
        raise ValueError(f"{path} is not a checkpoint written by python -m training (its meta is not a dict)")
    if stage and not isinstance(meta.get("config"), dict):  # (else a KeyError where the model is built)
        config = meta.get("config")
        raise incompatible(path, stage, "its meta holds no model config" if config is None else
                           f"its model config is a {type(config).__name__}, not a dict")
    kind = meta.get("config", {}).get("kind")  # every StudentConfig has a kind, no TeacherConfig has
    if stage == "teacher" and kind:
        raise ValueError(f"{path} is a {kind} student's checkpoint, not a teacher's")
    if stage == "student" and not kind:
        raise ValueError(f"{path} is a teacher's checkpoint, not a student's")
    return state


def model_from_checkpoint(path: str | Path, stage: str, state: dict,
                          build: Callable[[dict], torch.nn.Module]) -> torch.nn.Module:
    """The model that `build` makes from the config of `state` (load_checkpoint(path, stage)), with the
    checkpoint's weights. A config that cannot be built (an unknown field, a bad value) or weights
    that do not fit it are one line (incompatible), not a TypeError or torch's many-line size-mismatch list."""
    try:
        model = build(state["meta"]["config"])
    except Exception as e:  # the config is the file's content: anything it makes fail is the file's fault
        raise incompatible(path, stage, f"its model config cannot be built ({_short_reason(e)})") from None
    weights = state["model"]
    if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
        raise incompatible(path, stage, "its model is not a dict of tensors")
    expected = model.state_dict()
    missing = [k for k in expected if k not in weights]
    unexpected = [k for k in weights if k not in expected]
    resized = [k for k in expected if k in weights and weights[k].shape != expected[k].shape]
    if missing or unexpected or resized:
        parts = []
        if resized:
            k = resized[0]
            parts.append(f"{len(resized)} weights have other shapes than its config gives (e.g. {k}: "
                         f"{tuple(weights[k].shape)} saved, {tuple(expected[k].shape)} expected)")
        if missing:
            parts.append(f"{len(missing)} weights are missing (e.g. {missing[0]})")
        if unexpected:
            parts.append(f"{len(unexpected)} weights are not the config's model's (e.g. {unexpected[0]})")
        raise incompatible(path, stage, "; ".join(parts))
    model.load_state_dict(weights)
    return model


def wants_on_device(choice: str, rt: Runtime) -> bool:
    """--videos-on-device / --trajectories-on-device: yes, no, or auto (on CUDA)."""
    return choice == "yes" or (choice == "auto" and rt.device.type == "cuda")


def validation_share(dataset, rank: int, world: int):
    """This rank's part of the validation set: every sample once over the ranks. (DistributedSampler pads
    the ranks to equal sizes by repeating samples, which the count-weighted mean then counted twice, and that
    mean picks best.pt.) With fewer samples than ranks, every rank takes them all: each rank's mean, and so
    the mean over ranks, is then the set's."""
    if world == 1 or len(dataset) < world:
        return dataset
    return Subset(dataset, range(rank, len(dataset), world))


def _reduce_mean(values: dict[str, float], count: int, rt: Runtime) -> dict[str, float]:
    """Count-weighted mean of per-process sums across ranks."""
    keys = sorted(values)
    t = torch.tensor([values[k] for k in keys] + [float(count)], dtype=torch.float64, device=rt.device)
    if rt.world > 1:
        dist.all_reduce(t)
    n = max(t[-1].item(), 1.0)
    return {k: t[i].item() / n for i, k in enumerate(keys)}


@dataclass
class FitConfig:
    epochs: int
    batch_size: int
    lr: float = 1e-4
    weight_decay: float = 1e-4
    min_lr: float = 1e-6
    warmup_fraction: float = 0.05
    seed: int = 0
    grad_clip: float = 1.0
    progress: bool = True
    amp: bool = False  # bfloat16 autocast on CUDA
    stop_after: int = 0  # >0: return after this many epochs in this call (time-sliced jobs); rerun to go on
    select: str = "score"  # the validation metric (lower is better) that picks BEST, one of SELECT_METRICS


# Validation metrics that can pick BEST (logged by models.common.task_loss): CE + RegL1, or RegL1 alone.
SELECT_METRICS = ("score", "regl1")


def weights_digest(model: torch.nn.Module) -> str:
    """sha256 (hex) over a model's weights: which model it is, whatever file it came from."""
    return hashlib.sha256(b"".join(t.detach().cpu().numpy().tobytes() for t in model.state_dict().values())).hexdigest()


def _shown(flag: str, value) -> str:
    """A recipe entry as it is typed: --full-clips / no --full-clips, --encoder-channels 8,16."""
    if isinstance(value, bool):
        return flag if value else f"no {flag}"
    if isinstance(value, (tuple, list)):
        return f"{flag} {','.join(map(str, value))}"
    return f"{flag} {value}"


def check_resumable(out_dir: Path, recipe: dict, config: dict, stage: str,
                    saved_config: Callable[[dict], dict] = dict) -> dict | None:
    """Refuses, before any data loads, to resume the run in `out_dir` under options other than
    those it was trained with: another seed or validation fraction would move the validation
    split, another batch size, epoch count or number of processes the learning-rate schedule,
    another loss or model make a different run under the same name. `recipe` maps command-line
    flags to values (checkpoints from before recipes were saved recorded only --select); `config`
    is the resolved model config (from --size, --kind, --set, ..., and a student's teacher).
    `saved_config` brings the config saved in `last.pt` to today's fields (older checkpoints named
    some otherwise). Returns the recipe `last.pt` recorded (None when there is no run to resume),
    for check_recipe of the entries known only once the data has loaded."""
    last = out_dir / LAST
    if not last.exists():
        return None
    try:
        state = load_checkpoint(last, stage)
    except ValueError as e:
        raise ValueError(f"{e} (or delete {last} to start this run over)") from None
    recorded = state.get("recipe") or {"--select": state.get("select", "score")}
    check_recipe(last, recorded, recipe)
    try:
        saved = saved_config(state["meta"]["config"])
    except (TypeError, ValueError) as e:  # e.g. a field this version does not know
        raise ValueError(f"{incompatible(last, stage, _short_reason(e))} (or delete {last} to start this run "
                         "over)") from None
    if differing := [key for key in sorted(saved.keys() | config.keys()) if saved.get(key) != config.get(key)]:
        change = ", ".join(f"{key} {saved.get(key)} -> {config.get(key)}" for key in differing)
        raise ValueError(f"{last} holds another model ({change}: set by --size, --kind, --previous-frames, "
                         f"--encoder-channels, --set, or a student's teacher). {_restart_hint(last)}")
    return recorded


def check_recipe(last: Path, recorded: dict, recipe: dict) -> None:
    """Refuses a resume of `last` (whose recipe was `recorded`) under a `recipe` that differs in any entry both have."""
    if differing := [flag for flag in recorded if flag in recipe and recorded[flag] != recipe[flag]]:
        was = " ".join(_shown(flag, recorded[flag]) for flag in differing)
        now = " ".join(_shown(flag, recipe[flag]) for flag in differing)
        raise ValueError(f"{last} was trained with {was}; this run asks for {now}. {_restart_hint(last)}")


def _restart_hint(last: Path) -> str:
    return f"Resume it with the same options, or train into a new --out (or delete {last} to start this run over)"


def fit(model: torch.nn.Module, train_set, val_set, loss_fn: Callable, out_dir: Path, cfg: FitConfig, rt: Runtime,
        meta: dict, desc: str = "train", recipe: dict | None = None) -> dict:
    """Trains `model` (already on rt.device) and returns the history.

    loss_fn(model, batch, train: bool) -> (loss tensor, {name: float tensor}); the batch is a dict
    of tensors on rt.device. Every epoch: validate, log, save LAST (model, optimizer, epoch,
    step, RNG, history, meta, `recipe`: see check_resumable) and BEST by the validation
    `cfg.select` metric (lower is better). A run finds LAST in out_dir and resumes from it; the
    caller has checked that it may (check_resumable).
    """
    if cfg.select not in SELECT_METRICS:
        raise ValueError(f"select must be one of {SELECT_METRICS}, got {cfg.select!r}")
    out_dir.mkdir(parents=True, exist_ok=True)
    # Also used with one process: the same seeded shuffle per epoch, so a resumed run sees the same order.
    sampler = DistributedSampler(train_set, num_replicas=rt.world, rank=rt.rank, shuffle=True, seed=cfg.seed)
    # A dataset may build its batches itself (on the GPU: then there is nothing to pin).
    collate = getattr(train_set, "collate", None)
    loader = DataLoader(train_set, batch_size=cfg.batch_size, sampler=sampler, num_workers=0, collate_fn=collate,
                        pin_memory=rt.device.type == "cuda" and getattr(train_set, "on_device", None) is None)
    val_loader = DataLoader(validation_share(val_set, rt.rank, rt.world), batch_size=cfg.batch_size,
                            collate_fn=getattr(val_set, "collate", None)) if val_set is not None and len(val_set) else None

    raw = model
    if rt.world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[rt.device.index] if rt.device.type == "cuda" else None)
    optimizer = torch.optim.AdamW([p for p in raw.parameters() if p.requires_grad], lr=cfg.lr,
                                  weight_decay=cfg.weight_decay)
    total = cfg.epochs * max(1, len(loader))
    warmup = int(cfg.warmup_fraction * total)
    epoch, step, history, best = 0, 0, [], float("inf")

    last = out_dir / LAST
    if last.exists():
        # Loaded on the CPU: load_state_dict moves weights and optimizer moments to the parameters'
        # device, and AdamW's step counters must stay on the CPU (on a GPU each step would sync).
        state = load_checkpoint(last)
        raw.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        epoch, step, history, best = state["epoch"], state["step"], state["history"], state["best"]
        set_rng_state(state["rng"])
        if rt.main:
            done = f": the run is complete ({epoch} of {cfg.epochs} epochs), nothing to train" \
                if epoch >= cfg.epochs else ""
            tqdm.write(f"{desc}: resumed from {last} at epoch {epoch}{done}")

    stop_at = min(cfg.epochs, epoch + cfg.stop_after) if cfg.stop_after > 0 else cfg.epochs
    while epoch < stop_at:
        sampler.set_epoch(epoch)
        if hasattr(train_set, "set_epoch"):
            train_set.set_epoch(epoch)
        model.train()
        sums, count = {}, 0
        bar = tqdm(loader, desc=f"{desc} epoch {epoch + 1}/{cfg.epochs}", disable=None if rt.main and cfg.progress else True,
                   leave=False, unit="batch")
        for batch in bar:
            batch = {k: v.to(rt.device, non_blocking=True) for k, v in batch.items()}
            for group in optimizer.param_groups:
                group["lr"] = cosine_lr(step, total, cfg.lr, cfg.min_lr, warmup)
            with torch.autocast(rt.device.type, dtype=torch.bfloat16, enabled=cfg.amp and rt.device.type == "cuda"):
                loss, logs = loss_fn(model, batch, True)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(raw.parameters(), cfg.grad_clip)
            optimizer.step()
            step += 1
            n = len(next(iter(batch.values())))
            count += n
            for k, v in {"loss": loss.detach(), **logs}.items():
                sums[k] = sums.get(k, 0.0) + float(v) * n
            bar.set_postfix(loss=f"{loss.item():.3f}")
        record = {"epoch": epoch + 1, "lr": optimizer.param_groups[0]["lr"]}
        record.update({f"train_{k}": v for k, v in _reduce_mean(sums, count, rt).items()})
        if val_loader is not None:
            record.update({f"val_{k}": v for k, v in evaluate_loss(model, val_loader, loss_fn, rt).items()})
        history.append(record)
        epoch += 1
        score = record.get(f"val_{cfg.select}", record.get(f"train_{cfg.select}", record["train_loss"]))
        if rt.main:
            if score < best:
                best = score
                save_checkpoint(out_dir / BEST, {"model": raw.state_dict(), "epoch": epoch, "meta": meta})
            save_checkpoint(last, {"model": raw.state_dict(), "optimizer": optimizer.state_dict(), "epoch": epoch,
                                   "step": step, "rng": rng_state(), "history": history, "best": best,
                                   "recipe": recipe or {}, "meta": meta})
            write_text_staged(out_dir / "history.json", json.dumps(history, indent=1))
            tqdm.write(f"{desc} " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                             for k, v in record.items()))
        if rt.world > 1:
            dist.barrier()
    return {"history": history, "best": best}


@torch.no_grad()
def evaluate_loss(model, loader, loss_fn, rt: Runtime) -> dict[str, float]:
    model.eval()
    sums, count = {}, 0
    for batch in loader:
        batch = {k: v.to(rt.device) for k, v in batch.items()}
        loss, logs = loss_fn(model, batch, False)
        n = len(next(iter(batch.values())))
        count += n
        for k, v in {"loss": loss, **logs}.items():
            sums[k] = sums.get(k, 0.0) + float(v) * n
    return _reduce_mean(sums, count, rt)
