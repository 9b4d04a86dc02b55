"""`ros2 run ad_estimator estimate BAG...`: what the node would publish for a recorded bag, offline.

For any bag with a mask topic, your own robot's included: no ground truth is needed. The frames of
--topic are taken in log-time order and go through the node's own code: images.image_to_mask, the
node's FrameWindow (episodes start at stamp gaps over --gap-threshold, stamps going backwards and
image size changes; the episode or anytime output policy), then model.predict. Each bag ends with
a flush, as the node's does when its input goes idle. So every row is an estimate that
`ros2 run ad_estimator node` publishes for the same stream with the same parameters. A frame the
node would reject is skipped, warned about and counted. Writes one CSV row per estimate. Needs no
ROS runtime.
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from ad_estimator.cli import HelpFormatter
from ad_estimator.evaluate import IMAGE_TYPE, MASK_TOPIC, find_bags
from ad_estimator.images import DEFAULT_THRESHOLD, MAX_IMAGE_PIXELS, ImageRejected, image_to_mask
from ad_estimator.model import BUNDLED_MODEL, Estimate, EstimatorModel, ModelError
from ad_estimator.window import (DEFAULT_EVERY_N, DEFAULT_GAP_THRESHOLD, DEFAULT_MIN_FRAMES, DEFAULT_SLOT_TOLERANCE,
                                 POLICIES, FrameWindow, WindowOutput, stamp_to_ns)
from ad_sim.rosbag import BagError, BagReader, one_line_warnings


@dataclass
class Row:
    """One estimate, as the node would publish it."""

    bag: str
    output: WindowOutput  # its `episode`: 1, 2, ... in the bag's stream, counting episodes that gave no estimate
    estimate: Estimate


@dataclass
class WindowSettings:
    """The node's window parameters (the same names and defaults)."""

    output_policy: str = "episode"
    min_frames: int = DEFAULT_MIN_FRAMES
    every_n: int = DEFAULT_EVERY_N
    gap_threshold: float = DEFAULT_GAP_THRESHOLD
    slot_tolerance: float = DEFAULT_SLOT_TOLERANCE
    mask_threshold: int = DEFAULT_THRESHOLD

    def window(self, model: EstimatorModel) -> FrameWindow:
        info = model.info
        return FrameWindow(info.frame_interval, info.frame_count, gap_threshold=self.gap_threshold,
                           slot_tolerance=self.slot_tolerance, policy=self.output_policy, every_n=self.every_n,
                           min_frames=min(self.min_frames, info.frame_count), history=info.previous_frames)


def mask_frames(bag: Path, topic: str, recover: bool):
    """The Image messages of `topic` in the bag, in log-time order; BagError if the topic is missing
    or carries something else, naming the bag's image topics."""
    reader = BagReader(bag, topics=[topic], recover=recover)
    topics = reader.topics()
    if topics.get(topic, IMAGE_TYPE) != IMAGE_TYPE:
        raise BagError(f"topic {topic} in {bag} carries {topics[topic]}, not {IMAGE_TYPE}")
    if topic not in topics:
        images = sorted(t for t, kind in topics.items() if kind == IMAGE_TYPE)
        raise BagError(f"{bag} has no topic {topic}; its image topics: {', '.join(images) or 'none'} "
                       "(pass one with --topic)")
    for message in reader:
        yield message.message


def estimate_bag(model: EstimatorModel, bag: Path, topic: str, settings: WindowSettings, recover: bool = False,
                 skipped: Counter | None = None) -> list[Row]:
    """Every estimate the node would publish for the bag's `topic`, in order. Rejected frames are
    warned about and counted in `skipped` by reason."""
    window = settings.window(model)
    rows: list[Row] = []

    def collect(outputs: list[WindowOutput]) -> None:
        rows.extend(Row(str(bag), out, model.predict(out.features, out.valid)) for out in outputs)

    for image in mask_frames(bag, topic, recover):
        stamp = stamp_to_ns(image.header.stamp.sec, image.header.stamp.nanosec)
        try:
            mask = image_to_mask(image, MAX_IMAGE_PIXELS, settings.mask_threshold)
        except ImageRejected as exc:
            warnings.warn(f"{bag}: frame stamped {stamp / 1e9:.3f} s skipped, as the node rejects it: {exc}")
            if skipped is not None:
                skipped[exc.kind] += 1
            continue
        collect(window.add(stamp, mask, model.encode))
    collect(window.flush())
    return rows


def columns(model: EstimatorModel) -> list[str]:
    info = model.info
    return (["bag", "episode", "episode_start_s", "oldest_stamp_s", "newest_stamp_s", "frames_used", "complete",
             "material"] + [f"p_{c}" for c in info.class_names] + list(info.parameter_names)
            + [f"{p}_sigma" for p in info.parameter_names])


def csv_row(row: Row) -> list:
    """Stamps in seconds; parameters the predicted family does not use are empty cells."""
    out, est = row.output, row.estimate

    def cell(v: float):
        return "" if math.isnan(v) else float(v)

    return ([row.bag, out.episode, out.episode_start_ns / 1e9, out.oldest_stamp_ns / 1e9, out.newest_stamp_ns / 1e9,
             out.frames_used, out.complete, est.material] + [float(p) for p in est.probabilities]
            + [cell(v) for v in est.parameters] + [cell(v) for v in est.uncertainties])


def summary_line(row: Row) -> str:
    est = row.estimate
    used = ", ".join(f"{name} {value:.4g}" for name, value in zip(est.parameter_names, est.parameters)
                     if not math.isnan(value))
    return (f"{Path(row.bag).name} episode {row.output.episode} ({row.output.frames_used} frames"
            f"{'' if row.output.complete else ', partial'}): {est.material} "
            f"p={est.probabilities.max():.2f}; {used}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ros2 run ad_estimator estimate", formatter_class=HelpFormatter,
        description="Estimate the material of every episode in recorded bags, offline, as the node would (same "
                    "image checks, episode splitting, frame slots and output policy), with no ground truth needed: "
                    "your own robot's bags work. Writes one CSV row per estimate and prints a line for each. To "
                    "score a model against the simulator's ground truth, use `ros2 run ad_estimator evaluate`.")
    parser.add_argument("bags", type=Path, nargs="+",
                        help="bag folders, .mcap files, or folders holding bags (searched recursively)")
    parser.add_argument("--topic", default=MASK_TOPIC, help="mask topic (sensor_msgs/Image, mono8 or mono16)")
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: the bundled one)")
    parser.add_argument("--out", type=Path, default=None,
                        help="CSV file to write (default reports/estimate/<model id>.csv)")
    parser.add_argument("--output-policy", choices=POLICIES, default="episode",
                        help="as the node's output_policy: episode (one estimate per complete episode) or anytime")
    parser.add_argument("--min-frames", type=int, default=DEFAULT_MIN_FRAMES,
                        help="anytime policy: frames before the first estimate (the node's min_frames)")
    parser.add_argument("--every-n", type=int, default=DEFAULT_EVERY_N,
                        help="anytime policy: an estimate every N more frames (the node's every_n)")
    parser.add_argument("--gap-threshold", type=float, default=DEFAULT_GAP_THRESHOLD,
                        help="seconds of stamp gap that start a new episode (the node's gap_threshold)")
    parser.add_argument("--slot-tolerance", type=float, default=DEFAULT_SLOT_TOLERANCE,
                        help="how far, in frame intervals, a frame may be from a slot time (the node's slot_tolerance)")
    parser.add_argument("--mask-threshold", type=int, default=DEFAULT_THRESHOLD,
                        help="pixel > threshold (of 255, scaled for 16 bit) is object (the node's mask_threshold)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    parser.add_argument("--recover", action="store_true",
                        help="read truncated or damaged files (a killed recorder) up to their last complete chunk")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no line per estimate")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_line_warnings()
    settings = WindowSettings(args.output_policy, args.min_frames, args.every_n, args.gap_threshold,
                              args.slot_tolerance, args.mask_threshold)
    skipped: Counter = Counter()
    try:
        model = EstimatorModel.load(args.model, threads=args.threads)
        settings.window(model)  # bad window settings fail before any work
        out = args.out or Path("reports") / "estimate" / f"{model.model_id}.csv"
        if out.is_dir():
            raise ValueError(f"--out {out} is a folder; pass a .csv file name")
        rows = []
        for bag in tqdm(find_bags(args.bags), desc="bags", unit="bag", disable=args.quiet):
            rows += estimate_bag(model, bag, args.topic, settings, args.recover, skipped)
    except (ModelError, BagError, ValueError) as exc:
        print(f"estimate: {exc}", file=sys.stderr)
        return 1
    problems = f"; {sum(skipped.values())} frame(s) skipped ({dict(skipped)})" if skipped else ""
    if not rows:
        hint = (" Episodes shorter than the model's frame count give no estimate under the episode policy; "
                "try --output-policy anytime." if args.output_policy == "episode" else "")
        print(f"estimate: no estimate from {args.topic} in {[str(b) for b in args.bags]}{problems}.{hint}",
              file=sys.stderr)
        return 1
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(columns(model))
            writer.writerows(csv_row(r) for r in rows)
    except OSError as exc:
        print(f"estimate: cannot write {out} ({exc.strerror}); pass another --out", file=sys.stderr)
        return 1
    if not args.quiet:
        print("\n".join(summary_line(r) for r in rows))
    episodes = len({(r.bag, r.output.episode) for r in rows})
    print(f"{len(rows)} estimate(s) of {episodes} episode(s) with {model.model_id}{problems}: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
