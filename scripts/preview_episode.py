#!/usr/bin/env python3
"""Simulate one episode and save a PNG contact sheet of its masks (one row per view, one column per frame).

Examples:
  scripts/preview_episode.py --size tiny --split unseen --index 0 -o /tmp/episode.png
  scripts/preview_episode.py --instances my_instances.yaml --index 2 --views 4 --full -o /tmp/episode.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "ros_ws" / "src" / pkg) for pkg in ("ad_sim", "ad_estimator")]

from ad_estimator.cli import positive  # noqa: E402
from ad_sim.episode import Episode, simulate_batch  # noqa: E402
from ad_sim.instances import BENCHMARK_SIZES, BENCHMARK_SPLITS, MAX_VIEWS, benchmark, load_instance_file  # noqa: E402

HEADER = 24  # pixels of caption above the sheet
GAP = 2  # pixels between tiles


def contact_sheet(episode: Episode, full: bool = False) -> np.ndarray:
    """Grey image: rows = views, columns = frames, mid-grey gaps, caption on top."""
    masks = episode.masks_full if full else episode.masks
    views, frames, height, width = masks.shape
    sheet = np.full((HEADER + views * (height + GAP), frames * (width + GAP)), 128, dtype=np.uint8)
    for v in range(views):
        for t in range(frames):
            y, x = HEADER + v * (height + GAP), t * (width + GAP)
            sheet[y : y + height, x : x + width] = masks[v, t]
    instance = episode.instance
    values = ", ".join(f"{k}={v:.3g}" for k, v in instance.parameters.items())
    caption = f"{instance.episode_id}  {instance.material}: {values}  seed {instance.seed}  substeps/frame {episode.substeps_per_frame}"
    cv2.putText(sheet, caption, (4, HEADER - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 255, 1, cv2.LINE_AA)
    return sheet


def one_line(error: ValueError) -> str:
    """load_instance_file's message on one line: a YAML parser's spans several (the text around the problem)."""
    import yaml

    cause = error.__context__  # the parser's error, behind load_instance_file's `raise ... from None`
    if isinstance(cause, yaml.MarkedYAMLError) and cause.problem and cause.problem_mark:
        return f"{str(error).split(': not valid YAML')[0]}: not valid YAML: {cause.problem} at line {cause.problem_mark.line + 1}"
    return " ".join(str(error).split())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--instances", type=Path, help="instance file (YAML/JSON); default: a benchmark split")
    parser.add_argument("--size", choices=sorted(BENCHMARK_SIZES), help="benchmark size (default tiny)")
    parser.add_argument("--split", choices=BENCHMARK_SPLITS, help="benchmark split (default unseen)")
    parser.add_argument("--index", type=int, default=0, help="which instance of the list (default 0)")
    parser.add_argument("--views", type=positive, help="number of views (default: the instance's)")
    parser.add_argument("--full", action="store_true", help="show the 512x512 masks instead of the 128x128 ones")
    parser.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0 (default cpu)")
    parser.add_argument("-o", "--output", type=Path, default=Path("episode.png"), help="PNG to write (default episode.png)")
    args = parser.parse_args(argv)

    # Everything that can be wrong with the arguments, before the simulation (each one line, exit 2).
    if args.instances and (args.size or args.split):  # was: silently ignored, previewing the file's instance
        parser.error("--size/--split choose a benchmark split; give them or --instances, not both")
    args.size, args.split = args.size or "tiny", args.split or "unseen"
    if args.views is not None and args.views > MAX_VIEWS:
        parser.error(f"--views must be in 1..{MAX_VIEWS}, got {args.views}")
    if args.output.is_dir():
        parser.error(f"-o/--output: {args.output} is a folder; give a file name, e.g. {args.output / 'episode.png'}")
    if not cv2.haveImageWriter(str(args.output)):
        parser.error(f"-o/--output: OpenCV cannot write {args.output.name!r}; give an image name such as "
                     "episode.png (.png, .jpg, .bmp, .tif ...)")
    try:
        instances = load_instance_file(args.instances) if args.instances else benchmark(args.size, args.split)
    except OSError as exc:  # missing, a folder, unreadable
        parser.error(f"--instances: cannot read {args.instances}: {exc.strerror or exc}")
    except ValueError as exc:  # not YAML/JSON, or an entry that is not an instance
        parser.error(f"--instances: {one_line(exc)}")
    if not 0 <= args.index < len(instances):
        parser.error(f"--index must be in [0, {len(instances)}); the list has {len(instances)} instances")
    instance = instances[args.index]
    if args.device != "cpu":  # (Warp always has its CPU; checking starts Warp, with its banner)
        from ad_sim.mpm import check_device

        try:
            check_device(args.device)
        except ValueError as exc:
            parser.error(f"--device: {exc}")
    folder = next((f for f in (args.output.parent, *args.output.parent.parents) if f.exists()), None)
    if folder is not None and not folder.is_dir():
        parser.error(f"-o/--output: {folder} is a file, not a folder")
    try:
        args.output.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # e.g. no permission
        parser.error(f"-o/--output: cannot make the folder {args.output.parent}: {exc.strerror or exc}")
    print(f"simulating {instance.episode_id} ({instance.shape}, {instance.material}) on {args.device}", file=sys.stderr)
    (episode,) = simulate_batch([instance], device=args.device, full_masks=args.full, progress=True, views=args.views)
    try:  # the name was checked above; this is a folder that refuses the file, or an encoder that fails
        if not cv2.imwrite(str(args.output), contact_sheet(episode, args.full)):
            raise SystemExit(f"could not write {args.output}; check that its folder is writable")
    except cv2.error as exc:
        raise SystemExit(f"could not write {args.output}: {exc.err}") from None
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
