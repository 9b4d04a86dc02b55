"""Evaluate an exported ONNX student on bags: the paper's table, temporal-OOD rows, report.

Runs the model through ad_estimator.model (the estimator's own onnxruntime wrapper, so what is
measured is what the robot runs) on one view per instance (the lowest-numbered one, the
evaluation convention), and scores it with ad_estimator.metrics.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ad_estimator.cli import positive, staged, write_text_staged
from ad_estimator.metrics import (PARAMETER_NAMES, TEMPORAL_OOD_FRAMES, FrameCounts, Predictions, format_table,
                                  in_metric_order, json_text, read_frames_json, write_report)
from ad_estimator.model import EstimatorModel
from ad_estimator.window import clip_output
from ad_sim.materials import FAMILIES, FRAME_COUNT
from training import data

#: Prefix lengths scored: the full clip, the temporal-OOD rows and the anytime curve down to 10 frames.
FRAMES_SCORED = tuple(sorted({FRAME_COUNT, *TEMPORAL_OOD_FRAMES, *range(10, FRAME_COUNT, 2)}, reverse=True))


def predict_dataset(model: EstimatorModel, ds: data.Dataset, frames=FRAMES_SCORED,
                    progress: bool = True) -> dict[int, Predictions]:
    """Predictions for every observed-prefix length in `frames`, one clip per episode (a repeat or copy
    of an episode scored once): its first max(frames) frames (the model's frame count where it takes
    fewer than the clips hold)."""
    videos = ds.first_view_videos(ds.first_copies())
    probs = {k: [] for k in frames}
    params = {k: [] for k in frames}
    sigmas = {k: [] for k in frames}
    for j in tqdm(videos, desc="evaluate", unit="clip", disable=None if progress else True):
        video = list(ds.video(int(j))[:max(frames)])  # frames on the model's interval, in order
        features = clip_output([0] * len(video), video, model.encode, model.info.frame_interval,
                               model.info.frame_count, history=model.info.previous_frames).features
        for k in frames:
            est = model.predict(features[:k], np.ones(k, bool))
            probs[k].append(est.probabilities)
            params[k].append(est.raw_parameters)
            sigmas[k].append(est.raw_uncertainties)  # NaN where the model gives no log-variance
    instances = ds.video_instance[videos]
    ids = [ds.episode_ids[i] for i in instances]
    names = model.info.parameter_names
    return {k: Predictions(ds.labels[instances], ds.params_si[instances], np.array(probs[k]).reshape(-1, 3),
                           in_metric_order(params[k], names), ids, pred_sigma=in_metric_order(sigmas[k], names))
            for k in frames}


def write_evaluation(by_frames: dict[int, Predictions], out: str | Path, title: str, source: dict) -> dict:
    """The report (metrics.json, report.md, plots) and the per-episode predictions.json, headed by
    `source` (what was evaluated), into `out`; returns the metrics."""
    with staged(Path(out)) as folder:  # a failure half way leaves an earlier report whole
        results = write_report(by_frames, folder, title)
        (folder / "predictions.json").write_text(json_text(
            {**source, "parameter_names": list(PARAMETER_NAMES),
             "frames": {str(k): p.episodes() for k, p in by_frames.items()}}, indent=None))  # compact: 10 lengths
    return results


def print_results(results: dict, title: str, out: str | Path, predictions: bool = True) -> None:
    """The paper table (the full clip and the temporal-OOD rows) and where the report went."""
    full = max(map(int, results))
    print(format_table({k: v for k, v in results.items() if int(k) in (full, *TEMPORAL_OOD_FRAMES)}, title))
    where = f"report: {Path(out) / 'report.md'}"
    print(where + (f"  predictions: {Path(out) / 'predictions.json'}" if predictions else ""))


def evaluate_model(model_path: str | Path, bags: str | Path, cache: str | Path, out: str | Path | None,
                   title: str | None = None, progress: bool = True, threads: int = 1,
                   frames: tuple[int, ...] | None = None, record: bool = True) -> dict:
    """Scores the model on one clip per instance at the full clip and each prefix length of `frames`
    (default FRAMES_SCORED). The full clip is the cached clips' FRAME_COUNT frames, or the model's
    ad.frame_count where it takes fewer (its first frames, as the estimator's window would hold)."""
    model = EstimatorModel.load(model_path, threads=threads)
    full = min(model.info.frame_count, FRAME_COUNT)
    if bad := [k for k in frames or () if k > full]:
        raise ValueError(f"--frames {bad}: {model_path} observes {model.info.frame_count} frames (ad.frame_count), "
                         f"so each K must be in 1..{full}")
    frames = tuple(sorted({full, *(frames or (k for k in FRAMES_SCORED if k <= full))}, reverse=True))
    if record:
        read_model_metrics(model_path)  # a corrupt file fails now, not after the evaluation
    ds = data.load_dataset(bags, cache, progress=progress, coverage=model.info.mask_levels == "coverage")
    by_frames = predict_dataset(model, ds, frames, progress=progress)
    episodes = len(by_frames[full].episode_ids)
    title = title or f"{model.model_id} on {bags}"
    if out is None:
        out = Path(model_path).with_suffix("").with_name(Path(model_path).stem + "_eval")
    results = write_evaluation(by_frames, out, title, {"model_id": model.model_id, "model_path": str(model_path),
                                                        "episodes": episodes, "source_problems": ds.problems})
    if record:
        entry = {**summary(results), "episodes": episodes} | ({"source_problems": ds.problems} if ds.problems else {})
        print(f"recorded in {update_model_metrics(model_path, {'evaluation': {Path(bags).name: entry}})}")
    print_results(results, title, out)
    if warning := ds.train_split_warning(bags):
        print(warning, file=sys.stderr)
    if ds.problems:
        print(f"warning: only {episodes} complete episodes under {bags} were scored; {len(ds.problems)} problem(s) "
              f"in the bags are listed above and in predictions.json (masks-only bags, from --skip-particles, are "
              f"scored by `ros2 run ad_estimator evaluate`)", file=sys.stderr)
    return results


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training evaluate")
    p.description = ("Evaluate an exported student (.onnx) on bags: per-family Acc and parameter errors, RegL1, "
                     "temporal-OOD rows; writes metrics.json, report.md, plots and per-episode predictions.json, "
                     "and adds the summary to <model>.metrics.json next to the model.")
    p.add_argument("--model", required=True, help="exported student .onnx (for streaming: the temporal head file)")
    p.add_argument("--bags", required=True, help="evaluation bags (e.g. bags/small/unseen); its folder name keys "
                                                 "the results in <model>.metrics.json")
    p.add_argument("--cache", default=".cache/training", help="array cache folder")
    p.add_argument("--out", help="report folder (default: <model>_eval next to the model)")
    p.add_argument("--title", help="report title")
    p.add_argument("--threads", type=positive, default=1,
                   help="onnxruntime threads (clip models re-read every frame per estimate: give them cores)")
    p.add_argument("--frames", action=FrameCounts, nargs="*", metavar="K",
                   help=f"prefix lengths to score, e.g. --frames 20 15 or --frames 20,15 (default, also with no "
                        f"value: {' '.join(map(str, FRAMES_SCORED))}; the full clip, {FRAME_COUNT} or the model's "
                        "frame count where fewer, is always scored)")
    p.add_argument("--no-record", action="store_true",
                   help="leave <model>.metrics.json alone (e.g. for the bundled model, whose file ships)")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args) -> dict:
    return evaluate_model(args.model, args.bags, args.cache, args.out, args.title, not args.no_progress,
                          args.threads, tuple(args.frames or ()), record=not args.no_record)


def read_predictions(path: str | Path) -> tuple[dict[int, Predictions], dict]:
    """A saved predictions.json (of `evaluate`, `evaluate-teacher` or ad_estimator.evaluate, e.g. an
    estimator_runtime_predictions.json) -> Predictions per number of frames (empty for a row every
    episode was left out of), and the whole file (for its header)."""
    path = Path(path)
    what = ("pass a predictions.json written by `python -m training evaluate` or `evaluate-teacher`, or "
            "`ros2 run ad_estimator evaluate`")
    if path.is_dir():
        raise ValueError(f"{path} is a folder; pass the predictions.json inside it")
    saved = read_frames_json(path, 'a predictions file ({"25": [episode records], ...})', what)
    names = saved.get("parameter_names") or PARAMETER_NAMES
    by_frames = {}
    for k, records in saved["frames"].items():
        if not isinstance(records, list):
            raise ValueError(f'{path}: "frames"["{k}"] is not a list of episode records; {what}')
        # An unknown material is named with its episode (from_episodes' own text was "tuple.index(x): x not in tuple").
        for r in records:
            if isinstance(r, dict) and "true_material" in r and r["true_material"] not in FAMILIES:
                raise ValueError(f'{path}: "frames"["{k}"]: episode {r.get("episode_id")!r} has the unknown material '
                                 f'{r["true_material"]!r} (expected one of {", ".join(FAMILIES)}); {what}')
        try:  # an empty list (every episode left out of that row) is kept: the report shows the row without clips
            by_frames[int(k)] = Predictions.from_episodes(records, names)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f'{path}: "frames"["{k}"] is not a list of episode records ({exc!r}); {what}') from None
    if not any(by_frames.values()):
        raise ValueError(f'{path}: "frames" holds no episode records, so there is nothing to report; {what}')
    full = max(by_frames)
    if not by_frames[full]:
        raise ValueError(f'{path}: "frames"["{full}"], the full clips, holds no episode records (only shorter '
                         f'prefixes do), so there is no full-clip row to report; {what}')
    return by_frames, saved


def build_report_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training report")
    p.description = ("Rebuild an evaluation report (metrics.json, report.md, plots) from a saved predictions.json, "
                     "without the model or the bags: e.g. after the report gained a section, or for the "
                     "estimator runtime's estimator_runtime_predictions.json.")
    p.add_argument("--predictions", required=True, metavar="FILE",
                   help="predictions.json of `evaluate`, `evaluate-teacher` or `ros2 run ad_estimator evaluate`")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="report folder, created if missing; its metrics.json, report.md and plots are overwritten")
    p.add_argument("--title", help="report title (default: the file's model id or teacher, then the file, e.g. "
                                   "'h3reg2-... (reports/predictions.json)')")
    return p


def run_report(args) -> dict:
    by_frames, saved = read_predictions(args.predictions)
    source = saved.get("model_id") or saved.get("teacher")
    title = args.title or (f"{source} ({args.predictions})" if source else str(args.predictions))
    try:
        with staged(Path(args.out)) as folder:
            results = write_report(by_frames, folder, title)
    except OSError as exc:
        raise ValueError(f"cannot write the report to {args.out} ({exc.strerror or exc}); pass another --out") from None
    print_results(results, title, args.out, predictions=False)
    return results


def metrics_path(model_path: str | Path) -> Path:
    """<name>.metrics.json next to <name>.onnx."""
    model_path = Path(model_path)
    return model_path.with_name(model_path.name.removesuffix(".onnx") + ".metrics.json")


def read_model_metrics(model_path: str | Path) -> dict:
    """The model's metrics JSON, or a fresh one if it has none yet."""
    path = metrics_path(model_path)
    if not path.exists():
        return {"model": Path(model_path).name}
    try:
        current = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); fix or remove it, or pass --no-record") from None
    if not isinstance(current, dict):
        raise ValueError(f"{path} holds a JSON {type(current).__name__}, not an object; fix or remove it, "
                         "or pass --no-record")
    return current


def update_model_metrics(model_path: str | Path, update: dict) -> Path:
    """Merges `update` into the model's metrics JSON (nested dicts merged one level deep)."""
    path = metrics_path(model_path)
    current = read_model_metrics(model_path)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(current.get(key), dict):
            current[key].update(value)
        else:
            current[key] = value
    write_text_staged(path, json_text(current))
    return path


def summary(results: dict) -> dict:
    """Headline numbers of a results dict: the full clip's metrics and the temporal-OOD RegL1."""
    return {"full": results[str(max(map(int, results)))],
            "temporal_ood_regl1": {str(k): results[str(k)]["regl1"] for k in TEMPORAL_OOD_FRAMES if str(k) in results}}
