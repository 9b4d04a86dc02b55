"""`ros2 run ad_estimator estimate BAG...`: what the node would publish for a recorded bag, offline.

For any bag with a mask topic, your own robot's included: no ground truth is needed. The frames of
--topic are taken in log-time order and go through the node's own code with the node's parameters
(ad_estimator.parameters: same names, defaults and checks): images.image_to_mask, the node's
FrameWindow (episodes start at stamp gaps over gap_threshold, stamps going backwards and image size
changes; the episode or anytime output policy), then model.predict. Input pausing for more than
idle_flush seconds of log time flushes the window, as the node's idle flush does when the bag is
replayed at its own rate, and each bag ends with a flush. A frame the node would reject is skipped,
warned about and counted; a bag that cannot be read is skipped with a warning, the others kept.
Writes one CSV row per estimate. Needs no ROS runtime.
"""
from __future__ import annotations

import argparse
import csv
import math
import re
import sys
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from ad_estimator.cli import HelpFormatter, interruptible, staged, topic
from ad_estimator.evaluate import check_image_topic, check_out, find_bags, image_topics
from ad_estimator.images import ImageRejected, image_to_mask
from ad_estimator.model import BUNDLED_MODEL, Estimate, EstimatorModel, ModelError
from ad_estimator.parameters import DEFAULT_INPUT_TOPIC, PARAMETERS, check_parameters, model_window
from ad_estimator.window import POLICIES, WindowOutput, stamp_to_ns
from ad_sim.rosbag import BagDamaged, BagError, BagReader, one_line_warnings

# The node's parameters that apply offline, offered as options of the same names (--gap-threshold ...).
OPTIONS = ("output_policy", "min_frames", "every_n", "gap_threshold", "slot_tolerance", "idle_flush",
           "mask_threshold", "max_image_pixels", "threads")


def as_options(message: str) -> str:
    """A parameter check's message with each of OPTIONS named as the option given here (min_frames -> --min-frames)."""
    return re.sub(rf"\b({'|'.join(OPTIONS)})\b", lambda m: "--" + m.group(1).replace("_", "-"), message)


FIRST_COLUMNS = ("bag", "episode", "episode_start_s")  # of every CSV estimate writes, whatever the model


@dataclass
class Row:
    """One estimate, as the node would publish it."""

    bag: str
    output: WindowOutput  # its `episode`: 1, 2, ... in the bag's stream, counting episodes that gave no estimate
    estimate: Estimate


def mask_frames(bag: Path, topic: str, recover: bool):
    """(log time ns, Image) of `topic` in the bag, in log-time order; BagError if the topic is missing
    (naming the bag's image topics) or carries something other than Image."""
    reader = BagReader(bag, topics=[topic], recover=recover)
    topics = reader.topics()
    check_image_topic(topics, topic, bag)
    if topic not in topics:
        raise BagError(f"{bag} has no topic {topic}; its image topics: {', '.join(image_topics(topics)) or 'none'} "
                       "(pass one with --topic)")
    for message in reader:
        yield message.log_time_ns, message.message


def estimate_bag(model: EstimatorModel, bag: Path, topic: str, values: dict, recover: bool = False,
                 tally: Counter | None = None) -> list[Row]:
    """Every estimate the node would publish for the bag's `topic`, in order, with the node's
    parameter `values` (PARAMETERS names). `tally` counts the frames read ("frames") and those
    rejected, by reason; the first rejection of each reason is warned about, and how many there were in
    all at the end of the bag (one warning per frame flooded the terminal for a bag of thousands)."""
    window = model_window(values, model.info)
    threshold = model.info.input_threshold(values["mask_threshold"])  # as the node
    idle_ns = int(values["idle_flush"] * 1e9)
    tally = Counter() if tally is None else tally
    rows: list[Row] = []

    def collect(outputs: list[WindowOutput]) -> None:
        for out in outputs:
            try:
                rows.append(Row(str(bag), out, model.predict(out.features, out.valid)))
            except ValueError as exc:  # outputs that are not finite: no row, as the node publishes none
                warnings.warn(f"{bag}: episode {out.episode}: no estimate: {exc}")

    rejected: Counter = Counter()

    def reject(kind: str, where: str, exc: Exception) -> None:
        rejected[kind] += 1
        tally[kind] += 1  # now: a bag that fails further on keeps its count
        if rejected[kind] == 1:
            warnings.warn(f"{bag}: frame {where} skipped, as the node rejects it: {exc}")

    last_log = None
    for log_time, image in mask_frames(bag, topic, recover):
        tally["frames"] += 1
        if idle_ns > 0 and last_log is not None and log_time - last_log > idle_ns:
            collect(window.flush())  # the node's idle flush: input paused longer than idle_flush
        last_log = log_time
        try:
            stamp = stamp_to_ns(image.header.stamp.sec, image.header.stamp.nanosec)
        except ValueError as exc:  # as the node rejects it
            reject("stamp", f"logged at {log_time / 1e9:.3f} s", exc)
            continue
        try:
            mask = image_to_mask(image, values["max_image_pixels"], threshold)
        except ImageRejected as exc:
            reject(exc.kind, f"stamped {stamp / 1e9:.3f} s", exc)
            continue
        collect(window.add(stamp, mask, model.encode))
    collect(window.flush())
    for kind, count in rejected.items():
        if count > 1:
            warnings.warn(f"{bag}: {count} frames in all skipped for the reason of the first ({kind})")
    for kind, count, why in (("late", window.stats.late, "came after a later-stamped frame"),
                             ("repeated stamp", window.stats.duplicates, "had the stamp of the frame before")):
        if count:  # skipped by the window, as the node skips them
            warnings.warn(f"{bag}: {count} frame(s) {why} and were skipped, as the node skips them")
            tally[kind] += count
    return rows


def columns(model: EstimatorModel) -> list[str]:
    info = model.info
    return ([*FIRST_COLUMNS, "oldest_stamp_s", "newest_stamp_s", "frames_used", "complete",
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


def is_estimate_csv(path: Path) -> bool:
    """Whether `path` starts with the header estimate writes (its first columns, whatever the model)."""
    start = ",".join(FIRST_COLUMNS)
    try:
        with open(path, "rb") as f:
            return f.read(len(start)) == start.encode()
    except OSError as exc:  # unreadable: not one we can tell is ours, so not one to overwrite
        raise ValueError(f"--out {path} exists and cannot be read ({exc.strerror}); pass another --out") from exc


def summary_line(row: Row) -> str:
    return (f"{Path(row.bag).name} episode {row.output.episode} ({row.output.frames_used} frames"
            f"{'' if row.output.complete else ', partial'}): {row.estimate.describe()}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ros2 run ad_estimator estimate", formatter_class=HelpFormatter,
        description="Estimate the material of every episode in recorded bags, offline, as the node would (same "
                    "image checks, episode splitting, frame slots, idle flush and output policy, with the node's "
                    "parameters as options of the same names), with no ground truth needed: your own robot's "
                    "bags work. Writes one CSV row per estimate and prints a line for each. To score a model "
                    "against the simulator's ground truth, use `ros2 run ad_estimator evaluate`. Exit status 1 "
                    "if there is no estimate or a bag could not be read (the CSV still holds the others').")
    parser.add_argument("bags", type=Path, nargs="+",
                        help="bag folders, .mcap files, or folders holding bags (searched recursively)")
    parser.add_argument("--topic", type=topic, default=DEFAULT_INPUT_TOPIC,
                        help="mask topic (sensor_msgs/Image: mono8, mono16, or colour, as the node takes them)")
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: the bundled one)")
    parser.add_argument("--out", type=Path, default=None,
                        help="CSV file to write (default reports/estimate/<model id>.csv)")
    for name in OPTIONS:
        default, description = PARAMETERS[name]
        parser.add_argument(f"--{name.replace('_', '-')}", type=type(default), default=default,
                            choices=POLICIES if name == "output_policy" else None,
                            help=f"the node's {name}: {description}")
    parser.add_argument("--recover", action="store_true",
                        help="read truncated or damaged files (a killed recorder) up to their last complete chunk")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no line per estimate")
    return parser.parse_args(argv)


@interruptible("estimate")
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_line_warnings()
    values = {name: getattr(args, name) for name in OPTIONS}
    tally: Counter = Counter()
    try:
        try:
            check_parameters(values)
            model = EstimatorModel.load(args.model, threads=args.threads)
            model_window(values, model.info)  # bad window settings fail before any work
        except ValueError as exc:
            raise ValueError(as_options(str(exc))) from None
        out = args.out or Path("reports") / "estimate" / f"{model.model_id}.csv"
        if out.is_dir():
            raise ValueError(f"--out {out} is a folder; pass a .csv file name")
        if out.is_file() and not is_estimate_csv(out):  # e.g. a bag's own .mcap or metadata.yaml
            raise ValueError(f"--out {out} exists and is not a CSV that estimate wrote; pass another --out, "
                             "so that it is not overwritten")
        check_out(out, file="a .csv file")
        bags = find_bags(args.bags)
    except (ModelError, BagError, ValueError) as exc:
        print(f"estimate: {exc}", file=sys.stderr)
        return 1
    rows, failed, damaged = [], [], False
    # A context manager closes the bar (ending its line) before a Ctrl-C's message is printed.
    with tqdm(bags, desc="bags", unit="bag", disable=True if args.quiet else None) as bar:
        for bag in bar:
            try:
                rows += estimate_bag(model, bag, args.topic, values, args.recover, tally)
            except BagError as exc:  # the other bags are still worth their estimates
                warnings.warn(f"bag skipped: {exc}")
                failed.append(str(bag))
                damaged |= isinstance(exc, BagDamaged)
    frames = tally.pop("frames", 0)
    problems = "".join([f"; {sum(tally.values())} frame(s) skipped ({dict(tally)})" if tally else "",
                        f"; {len(failed)} bag(s) could not be read: {', '.join(failed)}" if failed else ""])
    if not rows:
        accepted = frames - sum(tally.values())
        if damaged:
            hint = " Pass --recover to read the undamaged part of the damaged bags."
        elif 0 < accepted <= tally["repeated stamp"]:
            hint = " Frames that repeat the stamp before them are skipped: was the camera stamping its images?"
        elif accepted and not failed and args.output_policy == "episode":
            hint = (" Episodes shorter than the model's frame slots give no estimate under the episode policy; "
                    "try --output-policy anytime.")
        else:
            hint = ""
        print(f"estimate: no estimate from {args.topic} in {[str(b) for b in args.bags]}: {frames} frame(s) read, "
              f"{accepted} accepted{problems}.{hint}", file=sys.stderr)
        return 1
    replaced = " (it replaced the file of an earlier run)" if out.exists() else ""  # the default name is per model
    try:
        with staged(out.parent) as folder:  # a full disk or a kill leaves the earlier CSV whole
            with open(folder / out.name, "w", newline="") as f:
                writer = csv.writer(f)
                writer.writerow(columns(model))
                writer.writerows(csv_row(r) for r in rows)
    except OSError as exc:
        print(f"estimate: cannot write {out} ({exc.strerror}); pass another --out", file=sys.stderr)
        return 1
    if not args.quiet:
        print("\n".join(summary_line(r) for r in rows))
    episodes = len({(r.bag, r.output.episode) for r in rows})
    print(f"{len(rows)} estimate(s) of {episodes} episode(s) with {model.model_id}{problems}: {out}{replaced}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
