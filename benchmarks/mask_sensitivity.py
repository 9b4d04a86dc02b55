#!/usr/bin/env python3
"""How visible is an error in each material parameter in the mask video?

For unseen benchmark instances of each family, re-simulates the instance with one parameter
moved up and down by the bundled model's typical error in it (its unseen log-MAE for E and yield,
MAE for nu and phi, from default.metrics.json), everything else kept, and reports the PSNR of
those masks against the instance's own (SPEC 8's re-simulation PSNR). A parameter whose typical
error leaves the masks almost unchanged (high PSNR) is one that masks say little about, whatever
the model; one whose error costs many dB is one the model could still learn.

    python benchmarks/mask_sensitivity.py --instances 4              # CPU, a few minutes
    python benchmarks/mask_sensitivity.py --instances 32 --device cuda --json out.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for pkg in ("ad_sim", "ad_estimator"):
    sys.path.insert(0, str(ROOT / "ros_ws" / "src" / pkg))
sys.path.insert(0, str(ROOT / "benchmarks"))  # common, also when a test imports this file by path

from ad_estimator.cli import HelpFormatter  # noqa: E402
from ad_estimator.metrics import ERROR_KIND  # noqa: E402
from ad_estimator.model import BUNDLED_MODEL  # noqa: E402
from ad_sim.instances import drawn_per_family  # noqa: E402
from ad_sim.materials import FAMILIES, FAMILY_RANGES, SAMPLED_PARAMETERS  # noqa: E402
from ad_sim.resimulate import mask_psnr, resimulate  # noqa: E402
from common import add_unseen_draw_options, check_warp_device, quiet_warp  # noqa: E402


def model_errors(metrics_path: Path) -> tuple[str, dict[str, dict[str, float]]]:
    """(model id, {family: {parameter: typical error}}) on unseen shapes, in the metrics' units
    (log-MAE, MAE; phi in degrees), over correctly classified instances."""
    try:
        metrics = json.loads(metrics_path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{metrics_path} cannot be read as JSON ({exc}); pass --metrics with the metrics JSON of an "
                         "evaluated model") from None
    advice = "pass --metrics with the metrics JSON of an evaluated model"
    if not isinstance(metrics, dict):
        raise SystemExit(f"{metrics_path} holds a JSON {type(metrics).__name__}, not a model's metrics (an object); "
                         f"{advice}")
    try:
        families = metrics["evaluation"]["unseen"]["full"]["families"]
        errors = {f: {n: families[f]["correct"][n] for n in SAMPLED_PARAMETERS[f]} for f in FAMILIES}
    except KeyError as exc:
        raise SystemExit(f"{metrics_path} has no unseen evaluation ({exc} missing); {advice}") from None
    except TypeError:  # a list or a number where the path evaluation.unseen.full.families.<family>.correct has objects
        raise SystemExit(f"{metrics_path} has no unseen evaluation (evaluation.unseen.full.families.<family>.correct "
                         f"is not laid out as a model's metrics); {advice}") from None
    if wrong := [f"{f} {n}" for f, e in errors.items() for n, v in e.items()
                 if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)))]:
        raise SystemExit(f"{metrics_path} has an unseen error that is not a number for {', '.join(wrong)}; {advice}")
    if missing := [f"{f} {n}" for f, e in errors.items() for n, v in e.items() if v is None]:
        raise SystemExit(f"{metrics_path} has no unseen error for {', '.join(missing)} (no correctly classified "
                         "instance); pass --metrics with another model's metrics")
    return metrics.get("model_id", metrics_path.name), {f: {n: float(v) for n, v in e.items()}
                                                         for f, e in errors.items()}


def moved(family: str, parameters: dict[str, float], name: str, error: float, sign: int) -> dict[str, float]:
    """The parameters with `name` moved by `sign` x its typical error, clipped to the family's range."""
    value, kind = parameters[name], ERROR_KIND[name]
    if kind == "log_mae":
        value *= math.exp(sign * error)
    else:
        value += sign * (math.radians(error) if kind == "mae_deg" else error)
    low, high, _ = FAMILY_RANGES[family][name]  # not clip_to_family_range: it rejects a nu past 0.5 before clipping
    return {**parameters, name: min(max(value, low), high)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    add_unseen_draw_options(p)
    p.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES), help="families to measure")
    p.add_argument("--metrics", type=Path, default=BUNDLED_MODEL.with_suffix(".metrics.json"),
                   help="metrics JSON whose unseen errors set the steps")
    p.add_argument("--device", default="cpu", help="warp device: cpu or cuda")
    args = p.parse_args(argv)
    quiet_warp()
    check_warp_device(p, args.device)

    model_id, errors = model_errors(args.metrics)
    chosen = drawn_per_family(args.size, "unseen", args.instances, args.seed, args.families)

    # One batch: each instance as it is, then each (parameter, direction) move of it.
    moves = []  # (index into chosen, parameter, moved parameters)
    for i, inst in enumerate(chosen):
        for name in SAMPLED_PARAMETERS[inst.material]:
            for sign in (-1, 1):
                params = moved(inst.material, inst.parameters, name, errors[inst.material][name], sign)
                if params[name] != inst.parameters[name]:  # at a range edge a move may be clipped away
                    moves.append((i, name, params))
    episodes = chosen + [chosen[i] for i, _, _ in moves]
    print(f"simulating {len(episodes)} episodes ({len(chosen)} instances) on {args.device}", file=sys.stderr)
    masks = resimulate(episodes, [(inst.material, inst.parameters) for inst in chosen]
                       + [(chosen[i].material, params) for i, _, params in moves], device=args.device, progress=True)
    psnr = mask_psnr(masks[len(chosen):], masks[[i for i, _, _ in moves]])  # each move against its own instance

    rows = []
    for family in args.families:
        for name in SAMPLED_PARAMETERS[family]:
            of_pair = np.array([db for db, (i, n, _) in zip(psnr, moves) if n == name and chosen[i].material == family])
            n = len(of_pair)  # 0: every move clipped away at a range edge
            rows.append({"family": family, "parameter": name, "step": errors[family][name], "n": n,
                         "median_db": float(np.median(of_pair)) if n else None,
                         "p10_db": float(np.percentile(of_pair, 10)) if n else None,
                         "p90_db": float(np.percentile(of_pair, 90)) if n else None})
    units = {"log_mae": "x e^{:.3f} (log-MAE)", "mae": "± {:.3f} (MAE)", "mae_deg": "± {:.2f}° (MAE)"}
    print(f"\nMask PSNR against the instance's own masks when one parameter moves by {model_id}'s "
          f"unseen error ({args.size} unseen, {args.instances} instances per family, both directions):\n")
    print("| family | parameter | step | PSNR median (dB) | 10th-90th percentile | moves |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        spread = "n/a | n/a" if not r["n"] else f"{r['median_db']:.1f} | {r['p10_db']:.1f}-{r['p90_db']:.1f}"
        print(f"| {r['family']} | {r['parameter']} | {units[ERROR_KIND[r['parameter']]].format(r['step'])} | {spread} | {r['n']} |")
    if args.json:
        setup = {"instances_per_family": args.instances, "size": args.size, "seed": args.seed,
                 "device": args.device, "model_id": model_id, "episodes": [i.episode_id for i in chosen]}
        args.json.write_text(json.dumps({"rows": rows, "setup": setup}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
