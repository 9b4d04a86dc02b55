"""Everything for one benchmark size: bags (generated with ad_sim.generate when missing) ->
teacher -> students (one per ablation) -> ONNX -> evaluation on seen and unseen objects.

Every stage resumes: generation skips finished shards, training resumes from last.pt, and a
finished training (all epochs in last.pt) is not redone.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from argparse import Namespace
from pathlib import Path

from ad_estimator.cli import count, fraction, positive, seed, staged, torch_device_or_auto, write_text_staged
from ad_estimator.metrics import compute_metrics, format_table, json_text
from ad_sim.materials import FRAME_COUNT
from training import data, evaluate, export, train_student, train_teacher
from training.engine import init_runtime, resolve_device
from training.train_student import ABLATIONS

# Epochs per size: paper values (SPEC 9) for `paper`; `small` fits 2 CPU cores in under an hour.
EPOCHS = {"tiny": (2, 2), "small": (80, 20), "paper": (300, 20)}
BATCH = {"tiny": (4, 8), "small": (16, 32), "paper": (32, 32)}
# Peak learning rates: the paper's 1e-4 at paper scale; few CPU steps need a larger one.
LR = {"tiny": 1e-3, "small": 5e-4, "paper": 1e-4}
SPLITS = ("train", "seen", "unseen")


def generate_settings(folder: Path) -> dict[Path, dict | None]:
    """Each bag folder under `folder` -> the custom data that `ad_sim.generate` recorded in its metadata.yaml
    (generator, seed, split, ...), or None for bags that generate did not write (recorded ones, an unreadable
    metadata.yaml)."""
    import yaml

    settings = {}
    for path in folder.rglob("metadata.yaml"):
        try:
            info = (yaml.safe_load(path.read_text()) or {}).get("rosbag2_bagfile_information") or {}
            custom = info.get("custom_data") or {}
        except (OSError, ValueError, AttributeError, yaml.YAMLError):
            custom = None
        generated = isinstance(custom, dict) and custom.get("generator") == "ad_sim.generate"
        settings[path.parent] = custom if generated else None
    return settings


def benchmark_seeds(folder: Path) -> dict[Path, str | None]:
    """Each bag folder under `folder` -> the benchmark seed (`ad_sim.generate --seed`) it was generated with, or
    None where it records none: bags recorded through topics, generated from an instance file, or with an
    unreadable metadata.yaml."""
    return {bag: str(custom["seed"]) if custom and "seed" in custom else None
            for bag, custom in generate_settings(folder).items()}


def check_data_seed(folder: Path, seed: int) -> list[Path]:
    """ValueError if bags under `folder` were generated with another benchmark seed than `seed`. Returns the bags
    there that record no seed and so cannot be checked (they are used as they are; no seed is assumed for them)."""
    seeds = benchmark_seeds(folder)
    if other := sorted({s for s in seeds.values() if s is not None} - {str(seed)}):
        raise ValueError(f"{folder} holds bags generated with --seed {', '.join(other)}, not the benchmark seed "
                         f"{seed} asked for (--data-seed, default --seed); pass --data-seed {other[0]} to train on "
                         f"them, or another --data to generate the seed-{seed} benchmark")
    return sorted(bag for bag, s in seeds.items() if s is None)


def ensure_bags(data_dir: Path, size: str, split: str, seed: int, device: str, progress: bool = True) -> Path:
    """data_dir/<size>/<split>, generated (resumably) with benchmark seed `seed` if it holds no finished bag
    (run checks first, with check_data_seed, that bags there were generated with that seed)."""
    from ad_sim.generate import main as generate

    folder = data_dir / size / split
    # Bags that generate did not write (recorded through topics) are the data: generating beside them would
    # train on both, each recorded episode twice.
    if foreign := sorted(bag for bag, custom in generate_settings(folder).items() if custom is None):
        print(f"using the bags under {folder} as they are ({len(foreign)} not written by ad_sim.generate, e.g. "
              f"{foreign[0]}): nothing generated beside them")
        return folder
    if not list(folder.rglob("*.mcap")) or not list(folder.rglob("DONE")):
        print(f"generating {size}/{split} bags into {folder} (ad_sim.generate, resumable)")
        code = generate(["--size", size, "--split", split, "--seed", str(seed), "--out", str(folder),
                         "--device", resolve_device(device), *([] if progress else ["--quiet"])])  # cuda:<index> too
        if code == 130:  # Ctrl-C: generate has said what is unfinished; stop as the pipeline's own Ctrl-C does
            raise KeyboardInterrupt
        if code:
            raise SystemExit(f"ad_sim.generate failed for {size}/{split} (exit {code})")
    return folder


def _stage_args(build_parser, args, bags: Path, out: Path, **kw) -> Namespace:
    """A stage's arguments: its own command line's defaults (so they cannot drift from it), the
    pipeline's shared settings, then `kw`."""
    stage = build_parser().parse_args(["--bags", str(bags), "--out", str(out)])
    vars(stage).update(cache=args.cache, size=args.size, lr=LR[args.size], val_fraction=args.val_fraction,
                       seed=args.seed, device=args.device, threads=args.threads, no_progress=args.no_progress, **kw)
    return stage


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training pipeline")
    p.description = ("Bags (generated if missing) -> teacher -> students -> ONNX -> evaluation. "
                     "Re-running resumes every stage.")
    p.add_argument("--size", choices=sorted(EPOCHS), default="small", help="benchmark and model size")
    p.add_argument("--data", default="bags", help="bag root: uses/generates <data>/<size>/{train,seen,unseen}")
    p.add_argument("--out", help="run folder (default runs/<size>)")
    p.add_argument("--cache", default=".cache/training", help="array cache folder")
    p.add_argument("--kind", choices=["streaming", "uniformer"], default="streaming", help="student encoder")
    p.add_argument("--ablations", default="full",
                   help=f"comma-separated student ablations to train, from {','.join(ABLATIONS)}")
    for i, stage in enumerate(("teacher", "student")):
        per_size = ", ".join(f"{epochs[i]} for {size}" for size, epochs in EPOCHS.items())
        p.add_argument(f"--{stage}-epochs", type=positive, help=f"{stage} epochs (default: {per_size})")
    p.add_argument("--val-fraction", type=fraction, default=0.1, help="instances held out for validation")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of training (initialisation, validation split, batches) and, unless --data-seed, of "
                        "the benchmark bags generated")
    p.add_argument("--data-seed", type=seed,
                   help="benchmark seed of the bags (ad_sim.generate --seed; default: --seed): bags found under "
                        "--data that were generated with another one are refused, not used")
    p.add_argument("--device", type=torch_device_or_auto, default="auto", help="auto | cpu | cuda | cuda:<index>")
    p.add_argument("--threads", type=count, default=0, help="torch CPU threads (0: default)")
    p.add_argument("--install", help="copy the `full` student (without one in --ablations, the last trained) here "
                                     "as <dir>/default.onnx (+ default.frame.onnx, default.metrics.json)")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args) -> dict:
    started = time.time()
    out = Path(args.out or f"runs/{args.size}")
    ablations = [a.strip() for a in args.ablations.split(",") if a.strip()]
    if unknown := [a for a in ablations if a not in ABLATIONS]:
        raise SystemExit(f"unknown ablation(s) {unknown}; choose from {ABLATIONS}")
    teacher_epochs = args.teacher_epochs or EPOCHS[args.size][0]
    student_epochs = args.student_epochs or EPOCHS[args.size][1]
    teacher_batch, student_batch = BATCH[args.size]
    data_seed = args.seed if args.data_seed is None else args.data_seed
    # Bags of another seed would be used as they are, so the same command would train on other data depending
    # on what an earlier run left in --data. All splits are checked before any is generated.
    unseeded = [bag for split in SPLITS for bag in check_data_seed(Path(args.data) / args.size / split, data_seed)]
    if unseeded and args.data_seed is not None:  # asked for a check that these bags cannot give: said, not passed
        named = ", ".join(map(str, unseeded[:5])) + (f" and {len(unseeded) - 5} more" if len(unseeded) > 5 else "")
        print(f"warning: --data-seed {data_seed} cannot be checked for {len(unseeded)} bag(s) under {args.data}: they "
              f"record no benchmark seed (recorded through topics, or generated from an instance file), so they are "
              f"used as they are, whatever seed they came from: {named}", file=sys.stderr)
    bags = {s: ensure_bags(Path(args.data), args.size, s, data_seed, args.device, not args.no_progress)
            for s in SPLITS}
    timings = {"generate_s": time.time() - started}

    t = time.time()
    teacher = train_teacher.run(_stage_args(train_teacher.build_parser, args, bags["train"], out / "teacher",
                                            epochs=teacher_epochs, batch_size=teacher_batch))
    timings["teacher_s"] = time.time() - t

    summary = {"size": args.size, "seed": args.seed, "data_seed": data_seed,
               "bags_without_seed": [str(bag) for bag in unseeded],  # data_seed says nothing of these
               "teacher": str(teacher),
               "teacher_metrics": {}, "students": {}}
    device = init_runtime(args.device).device
    model = train_teacher.load_teacher(teacher, device)
    for split in ("seen", "unseen"):
        ds = data.load_dataset(bags[split], args.cache, progress=False)
        res = compute_metrics(train_teacher.teacher_predictions(model, ds, device))
        summary["teacher_metrics"][split] = {"accuracy": res["accuracy"], "regl1": res["regl1"],
                                             "families": res["families"]}
        print(format_table({str(FRAME_COUNT): res}, f"teacher on {args.size}/{split}"))
    del model
    installed = None
    for ablation in ablations:
        name = f"{args.kind}_{ablation}"
        t = time.time()
        best = train_student.run(_stage_args(
            train_student.build_parser, args, bags["train"], out / name, epochs=student_epochs,
            batch_size=student_batch, teacher=str(teacher), kind=args.kind, ablation=ablation))
        timings[f"{name}_s"] = time.time() - t
        onnx_path = out / "models" / f"{name}.onnx"
        paths, error = export.export_verified(best, onnx_path)  # replaces the previous export only once verified
        results = {}
        for split in ("seen", "unseen"):
            res = evaluate.evaluate_model(onnx_path, bags[split], args.cache, out / "reports" / f"{name}_{split}",
                                          title=f"{name} on {args.size}/{split}", progress=not args.no_progress)
            results[split] = evaluate.summary(res)
        metrics_path = evaluate.update_model_metrics(onnx_path, {
            "epochs": {"teacher": teacher_epochs, "student": student_epochs}, "onnx_max_abs_error": error,
            "timings_s": {k: round(v, 1) for k, v in timings.items()}})
        summary["students"][ablation] = {
            "onnx": [str(p) for p in paths], "metrics": str(metrics_path),
            **{f"{split}_{key}": results[split]["full"][key] for split in ("seen", "unseen")
               for key in ("accuracy", "regl1")}}
        if ablation == "full" or "full" not in ablations:  # --install's help: the full student, else the last
            installed = (onnx_path, metrics_path)
    timings["total_s"] = time.time() - started
    summary["timings"] = timings
    write_text_staged(out / "summary.json", json_text(summary))
    if args.install and installed:
        install(installed[0], installed[1], Path(args.install))
    print(json_text(summary))
    return summary


def install(onnx_path: Path, metrics_path: Path, folder: Path, name: str = "default") -> None:
    """Copies an exported student as <folder>/<name>.onnx (+ .frame.onnx, .metrics.json), fixing
    the frame-encoder file name in the head's metadata."""
    import onnx

    frame = export.frame_encoder_path(onnx_path)
    target = folder / f"{name}.onnx"
    # Staged, head last: a failure or a kill never pairs the bundled head with another model's frame encoder.
    with staged(folder, last=target.name) as staging:
        if frame.exists():
            for source, file in ((frame, f"{name}.frame.onnx"), (onnx_path, target.name)):
                model = onnx.load(str(source))
                for prop in model.metadata_props:
                    if prop.key == "ad.frame_encoder":
                        prop.value = f"{name}.frame.onnx"
                onnx.save(model, str(staging / file))
        else:
            shutil.copyfile(onnx_path, staging / target.name)
        shutil.copyfile(metrics_path, staging / f"{name}.metrics.json")
    print(f"installed {target}")
