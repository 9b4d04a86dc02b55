"""Section 17: per-clip signed errors of each run on unseen, from the predictions.json that average.py wrote
(--reports: the folder of report folders), into unseen_errors.json; and the error-correlation table from it.

Errors use each clip's raw parameters (the parameters predicted for its true family, whatever class won):
ln(pred / true) for E and yield stress, pred - true for nu, degrees for the friction angle. The table gives
each run's mean |error|, the correlation of the runs' errors clip by clip, and the shapes' share: the part of
the average's mean squared error that is its shape's mean error (10 clips per shape, so chance alone gives 0.1).

usage: python errors.py --reports R     (writes unseen_errors.json beside this file)
       python errors.py                 (prints the table from unseen_errors.json)
"""
import argparse
import json
import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
RUNS = ("shipped", "n1", "n2", "shipped_mirror", "avg3")
PARAMETERS = (("jelly", "youngs_modulus", 0), ("jelly", "poissons_ratio", 1), ("plasticine", "youngs_modulus", 0),
              ("plasticine", "poissons_ratio", 1), ("plasticine", "yield_stress", 2), ("sand", "friction_angle", 3))


def error(name: str, pred: float, true: float) -> float:
    if name in ("youngs_modulus", "yield_stress"):
        return math.log(pred / true)
    return math.degrees(pred - true) if name == "friction_angle" else pred - true


def extract(reports: Path) -> dict:
    clips = {}
    for run in RUNS:
        frames = json.loads((reports / f"{run}_unseen" / "predictions.json").read_text())["frames"]["25"]
        for p in frames:
            clip = clips.setdefault(p["episode_id"], {"family": p["true_material"], "errors": {}})
            clip["errors"][run] = {name: round(error(name, p["raw_parameters"][j], p["true_parameters"][name]), 6)
                                   for family, name, j in PARAMETERS if family == p["true_material"]}
    return clips


def table(clips: dict) -> list[str]:
    rows = ["| unseen, all clips of the family | `h3reg2` (shipped) | n1 | n2 | average of the 3 | error correlation "
            "shipped-n1, shipped-n2, n1-n2 | shipped-mirrored clip | the shapes' share |", "|---|---|---|---|---|---|---|---|"]
    for family, name, _ in PARAMETERS:
        e = {run: np.array([c["errors"][run][name] for c in clips.values() if c["family"] == family]) for run in RUNS}
        members = np.stack([e["shipped"], e["n1"], e["n2"]])
        corr = np.corrcoef(members)
        mirror = np.corrcoef(e["shipped"], e["shipped_mirror"])[0, 1]
        average = members.mean(0)
        shapes = np.array([k.split("-")[1] for k, c in clips.items() if c["family"] == family])  # <split>-<shape>-...
        shape_mean = {s: average[shapes == s].mean() for s in set(shapes)}
        share = np.mean([shape_mean[s] ** 2 for s in shapes]) / np.mean(average ** 2)
        cells = [f"{np.abs(e[r]).mean():.3f}" for r in ("shipped", "n1", "n2")]
        rows.append(f"| {family} {name} | {' | '.join(cells)} | {np.abs(average).mean():.3f} | "
                    f"{corr[0, 1]:.2f}, {corr[0, 2]:.2f}, {corr[1, 2]:.2f} | {mirror:.2f} | {share:.2f} |")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reports", type=Path, help="folder of average.py's report folders (<run>_unseen/)")
    args = parser.parse_args()
    if args.reports:
        (HERE / "unseen_errors.json").write_text(json.dumps(extract(args.reports), indent=0))
    print("\n".join(table(json.loads((HERE / "unseen_errors.json").read_text()))))
