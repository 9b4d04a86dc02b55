"""Compare groups of evaluated runs (e.g. the seeds of one recipe against those of another) from
their metrics files: is a difference between recipes larger than the spread between seeds?

Reads what `python -m training evaluate` and `ros2 run ad_estimator evaluate` write (metrics.json),
scores nothing again, and reports in the paper's column layout (ad_estimator.metrics).
"""
from __future__ import annotations

import argparse
import json
import math
import textwrap
from pathlib import Path

import numpy as np

from ad_estimator.cli import staged
from ad_estimator.metrics import json_text, markdown_table, read_frames_json, table_cell, table_fields, table_labels
from ad_sim.materials import FRAME_COUNT


def parse_group(text: str) -> tuple[str, list[Path]]:
    """`NAME=PATH[,PATH...]` -> (name, paths)."""
    name, sep, paths = text.partition("=")
    files = [p.strip() for p in paths.split(",")]
    if not sep or not name.strip() or not all(files):
        raise ValueError(f"--group {text!r}: expected NAME=PATH[,PATH...] (a name, '=', then metrics files or "
                         "report folders separated by commas)")
    return name.strip(), [Path(f) for f in files]


def parse_groups(texts: list[str]) -> dict[str, list[Path]]:
    groups = {}
    for text in texts:
        name, files = parse_group(text)
        if name in groups:
            raise ValueError(f"--group {text!r}: the name {name!r} is already used by another --group; give each "
                             "group its own name")
        groups[name] = files
    return groups


def read_run(path: Path, frames: int, which: str) -> tuple[Path, dict[str, float]]:
    """(the metrics file, its table cells at `frames` keyed by column label, NaN where no clip
    qualified, and "clips": the clips it scored, NaN where the file lacks it) of a metrics file or of
    the metrics.json in a report folder."""
    file = path / "metrics.json" if path.is_dir() else path
    hint = "pass a metrics.json written by python -m training evaluate, or its report folder"
    metrics = read_frames_json(file, "a metrics file", hint)
    if str(frames) not in metrics["frames"]:
        raise ValueError(f"{file} has no entry for {frames} frames (it has {', '.join(metrics['frames'])}); choose "
                         "one of those with --frames")
    entry = metrics["frames"][str(frames)]
    # table_values' fields walked here, so that whatever is missing or not a number is named by its field
    # (table_values' KeyError or TypeError text named none: "lack list indices must be integers ...").
    cells = {}
    for keys, label in zip(table_fields(which), table_labels()):
        value, field = entry, f'"frames"["{frames}"]'
        for key in keys:
            if not isinstance(value, dict):
                raise ValueError(f"{file}: {field} is {_json_kind(value)}, not an object; {hint}")
            if key not in value:
                raise ValueError(f"{file}: its {frames}-frame metrics lack {field}[\"{key}\"]; {hint}")
            value, field = value[key], f'{field}["{key}"]'
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise ValueError(f"{file}: {field} is {_json_kind(value)}, not a number; {hint}")
        cells[label] = math.nan if value is None else float(value)
    # how many clips the run scored (NaN where a file lacks it): runs on other bags do not compare
    clips = entry.get("n")
    cells["clips"] = float(clips) if isinstance(clips, int) and not isinstance(clips, bool) else math.nan
    return file, cells


def _json_kind(value) -> str:
    """A JSON value as an error names it: "abc", true, null; a list or an object by its kind alone."""
    if isinstance(value, (list, dict)):
        return "a list" if isinstance(value, list) else "an object"
    return json.dumps(value)


def _sd(values: np.ndarray) -> float:
    """Sample SD (ddof=1); NaN for a single run, which has no spread."""
    return float(values.std(ddof=1)) if len(values) > 1 else math.nan


def _spread_cell(values: np.ndarray) -> str:
    """mean ± sample SD over a group's runs; the plain value for one run; n/a if a run lacks it."""
    mean = values.mean()
    if len(values) == 1 or math.isnan(mean):
        return table_cell(mean)
    return f"{table_cell(mean)} ± {table_cell(_sd(values))}"


def _precise(value: float, sign: str = "") -> str:
    """A difference between recipes is often below the table's 3 decimals."""
    return "n/a" if math.isnan(value) else f"{value:{sign}.4f}"


def compare(groups: dict[str, list[Path]], out: str | Path, frames: int = FRAME_COUNT, which: str = "correct",
            title: str | None = None) -> dict:
    """Writes compare.md, compare.json and compare.png into `out`; returns what compare.json holds."""
    runs = {name: [read_run(path, frames, which) for path in paths] for name, paths in groups.items()}
    title = title or f"{' vs '.join(groups)} ({frames} frames)"
    labels = table_labels()
    arrays = {name: np.array([[v[label] for label in labels] for _, v in rs]) for name, rs in runs.items()}
    regl1 = {name: a[:, -1] for name, a in arrays.items()}
    first = next(iter(groups))
    differences = [{"group": name, "versus": first,
                    "regl1_mean_difference": float(regl1[name].mean() - regl1[first].mean()),
                    "welch_standard_error": math.sqrt(_sd(regl1[name]) ** 2 / len(regl1[name])
                                                      + _sd(regl1[first]) ** 2 / len(regl1[first])),
                    "first_runs_below_every_run": int((regl1[first] < regl1[name].min()).sum()),
                    "first_runs": len(regl1[first])} for name in list(groups)[1:]]
    result = {"title": title, "frames": frames, "which": which, "differences": differences,
              "groups": {name: {"n": len(rs), "mean": dict(zip(labels, arrays[name].mean(axis=0).tolist())),
                                "sd": {label: _sd(arrays[name][:, j]) for j, label in enumerate(labels)},
                                "runs": [{"path": str(f), **v} for f, v in rs]} for name, rs in runs.items()}}

    md = [f"# {title}", "",
          f"Metrics at {frames} frames observed; parameter errors over "
          f"{'correctly classified' if which == 'correct' else 'all'} clips of each family (E, yield: log-MAE; "
          "nu: MAE; phi: MAE in degrees). Groups: mean ± sample SD over their runs (n).", "",
          *markdown_table(["group", *labels, "n"],
                          [[name, *(_spread_cell(a[:, j]) for j in range(len(labels))), str(len(a))]
                           for name, a in arrays.items()]),
          "", "Every run:", "",
          *markdown_table(["group", "run", *labels, "clips"],
                          [[name, str(Path(f.parent.name) / f.name), *(table_cell(v[label]) for label in labels),
                            "n/a" if math.isnan(v["clips"]) else str(int(v["clips"]))]
                           for name, rs in runs.items() for f, v in rs])]
    if len(counts := {v["clips"] for rs in runs.values() for _, v in rs if not math.isnan(v["clips"])}) > 1:
        md += ["", f"**The runs scored different numbers of clips** ({', '.join(str(int(c)) for c in sorted(counts))}"
                   "): they were evaluated on different bags, or episodes were left out, so their figures may not "
                   "compare."]
    if differences:
        md += ["", f"RegL1 against {first}:", ""]
        md += [f"- {d['group']}: mean difference {_precise(d['regl1_mean_difference'], '+')} "
               f"({d['group']} − {first}), Welch standard error {_precise(d['welch_standard_error'])}; "
               f"{d['first_runs_below_every_run']} of {d['first_runs']} {first} runs are below every {d['group']} run"
               for d in differences]
    md += ["", "![RegL1 of every run](compare.png)", ""]

    out = Path(out)
    try:
        with staged(out) as folder:  # a failure half way leaves an earlier report whole
            (folder / "compare.md").write_text("\n".join(md))
            (folder / "compare.json").write_text(json_text(result))
            plot_regl1(regl1, folder / "compare.png", f"RegL1 ({frames} frames)", title)
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot write the report there ({exc.strerror or exc}); pass a folder you can "
                         "write to") from None
    return result


def plot_regl1(regl1: dict[str, np.ndarray], path: Path, ylabel: str, title: str) -> None:
    """Every run's RegL1 as a dot over its group, the group mean as a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(regl1) + 2), 4))
    for i, values in enumerate(regl1.values()):
        ax.scatter(np.full(len(values), i), values, color="C0", zorder=2, label="run" if i == 0 else None)
        ax.hlines(values.mean(), i - 0.25, i + 0.25, color="k", label="group mean" if i == 0 else None)
    # long group names would run into each other under neighbouring groups
    ax.set_xticks(range(len(regl1)), ["\n".join(textwrap.wrap(name, 16)) for name in regl1], fontsize=8)
    ax.set_xlim(-0.75, len(regl1) - 0.25)
    ax.set_xlabel("group")
    ax.set_ylabel(ylabel)
    ax.set_title("\n".join(textwrap.wrap(title, 48)), fontsize=9)  # a long title would be cut at the edge
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training compare")
    p.description = ("Compare groups of evaluated runs (e.g. seeds of one recipe against seeds of another) from their "
                     "metrics files: the paper's table with mean ± SD per group, every run's row, the RegL1 "
                     "difference of each group from the first with its Welch standard error, and a plot of every "
                     "run's RegL1. Writes compare.md, compare.json and compare.png.")
    p.add_argument("--group", action="append", required=True, metavar="NAME=PATH[,PATH...]",
                   help="a group of runs: metrics.json files (python -m training evaluate) or report folders holding "
                        "one; repeat for each group (the first is the reference)")
    p.add_argument("--frames", type=int, default=FRAME_COUNT, metavar="K",
                   help="number of observed frames to compare at")
    p.add_argument("--which", choices=("correct", "all"), default="correct",
                   help="parameter errors over correctly classified clips (the paper's convention) or all clips")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--title", help="report title (default: the group names and frames)")
    return p


def run(args) -> dict:
    result = compare(parse_groups(args.group), args.out, args.frames, args.which, args.title)
    print((Path(args.out) / "compare.md").read_text())
    print(f"wrote {Path(args.out) / 'compare.md'}, compare.json, compare.png")
    return result
