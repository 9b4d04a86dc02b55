"""`ros2 run ad_estimator evaluate --model M --bags DIR...`: a model over recorded bags, offline.

Every episode's mask frames go through the node's own code: images.image_to_mask, then the
window's slots (window.clip_output: the slots the live window holds when the episode's stream
ends), then model.predict. So the per-episode predictions equal what the live node publishes for
the same frames. Row K is the first K frame slots (K x the model's frame interval from the episode's
first frame: a simulator clip's first K frames, whatever the camera's rate), as the node's window fills
them. As in the node, a frame images.py rejects is skipped (with a warning, and counted)
and an image size change restarts the window. An episode whose window holds fewer than K frame
slots (cut short, or restarted) is left out of the K row, and one without a usable mask frame out
of every row, with a warning; so is one whose ground truth the metrics cannot score (unscorable_ground_truth)
and, in the rows it was scored in, one scored before (the same simulation: simulation_key), from another bag (a
copy of a recording) or from the same one (a looping simulator's replay): each is scored once a row. A bag
without ground truth gives no episode (warned, and counted); ground truth without a field evaluate reads (another
definition of the message) is an error. Metrics (SPEC 8) come from ad_estimator.metrics; --frames K adds the
temporal out-of-distribution rows (only the first K frame slots observed). Needs no ROS runtime.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ad_estimator import metrics
from ad_estimator.cli import HelpFormatter, interruptible, positive, staged, topic
from ad_estimator.images import MAX_IMAGE_PIXELS, image_to_mask
from ad_estimator.model import BUNDLED_MODEL, EstimatorModel, ModelError
from ad_estimator.parameters import DEFAULT_INPUT_TOPIC
from ad_estimator.window import DEFAULT_SLOT_TOLERANCE, clip_output, stamp_to_ns
from ad_sim import messages
from ad_sim.rosbag import BagError, BagReader, distinct_episodes, group_episodes, one_line_warnings, simulation_key

INSTANCE_TOPIC = messages.instance_topic()
INSTANCE_TYPE = messages.INSTANCE_TYPE
MASK_TOPIC = DEFAULT_INPUT_TOPIC  # the node's input: the simulator's first camera
IMAGE_TYPE = messages.IMAGE_TYPE


@dataclass
class EpisodePrediction:
    """One episode's ground truth and the model's estimate from its first `frames` frames (evaluate's rows: frame
    slots, see predict_episode)."""

    episode_id: str
    bag: str
    frames: int  # frames observed: the row's K
    true_material: str
    true_parameters: dict[str, float]
    material: str
    probabilities: list[float]
    parameters: list[float]  # for the predicted material, NaN where unused
    raw_parameters: list[float]  # every parameter denormalised (metrics use these for any family)
    raw_uncertainties: list[float]  # the model's one sigma of every raw parameter, SI (NaN: the model gives none)
    uncertainties: list[float]  # for the predicted material (0 for its fixed parameters), NaN where unused
    frames_used: int
    slots: int  # frame slots the estimate covers (frames_used of them filled)
    oldest_stamp_ns: int
    newest_stamp_ns: int


@dataclass
class Evaluation:
    """What evaluate() found: the scored predictions per K, and what it had to leave out."""

    predictions: dict[int, list[EpisodePrediction]]
    # the bag readers' warnings: damage read past with --recover, an unusable or missing metadata.yaml
    source_problems: list[str] = field(default_factory=list)
    skipped_frames: list[dict] = field(default_factory=list)  # bag, episode_id, stamp_ns, reason
    left_out: dict[int, list[dict]] = field(default_factory=dict)  # per K: bag, episode_id, reason
    # bags without a ground truth message on INSTANCE_TOPIC: none of their frames is scored
    without_ground_truth: list[str] = field(default_factory=list)

    def problems(self) -> str:
        """One line on what was skipped or left out ('' when nothing was)."""
        parts = []
        if self.source_problems:
            parts.append(f"{len(self.source_problems)} problem(s) reading the bags' files")
        if self.without_ground_truth:
            parts.append(f"{len(self.without_ground_truth)} bag(s) without ground truth on {INSTANCE_TOPIC}")
        if self.skipped_frames:
            parts.append(f"{len(self.skipped_frames)} mask frame(s) skipped, as the node rejects them")
        if rows := [f"K = {k}: {len(v)}" for k, v in self.left_out.items() if v]:
            parts.append(f"episodes left out of the rows {', '.join(rows)}")
        return "; ".join(parts)


def bag_folders(root: Path) -> list[Path]:
    """The folders under `root` that hold .mcap files, sorted, as Path.rglob finds them, but also through
    links to folders, which rglob does not enter: a bag folder that was a link (say, a shard on another disk)
    was left out without a word, and with it its episodes from the training set and its split. A folder
    reached again (a link to a folder already searched, a link loop) is searched once."""
    found, searched = set(), set()
    for folder, subfolders, files in os.walk(root, followlinks=True):
        subfolders.sort()  # depth first in sorted order: a folder is first reached by its first name in sorted order
        real = os.path.realpath(folder)
        if real in searched:
            subfolders.clear()
            continue
        searched.add(real)
        if any(name.endswith(".mcap") for name in files):
            found.add(Path(folder))
    return sorted(found)


def find_bags(paths: list[Path]) -> list[Path]:
    """Bag folders (or .mcap files) given directly or found below the given folders, each once: a bag
    named twice, or both as a folder and by one of its .mcap files, would be scored twice."""
    bags = []
    for path in paths:
        if not path.exists():
            raise BagError(f"{path} does not exist")
        if path.is_file() or (path / "metadata.yaml").is_file() or any(path.glob("*.mcap")):
            bags.append(path)
            continue
        found = bag_folders(path)
        if not found:
            raise BagError(f"no bag (.mcap files) under {path}")
        bags.extend(found)
    folders = {bag.resolve() for bag in bags if bag.is_dir()}
    unique, seen = [], set()
    for bag in bags:
        key = bag.resolve()
        if key not in seen and not (bag.is_file() and key.parent in folders):
            unique.append(bag)
            seen.add(key)
    if len(unique) < len(bags):
        warnings.warn(f"{len(bags) - len(unique)} bag(s) given more than once (or by a file of a bag folder also "
                      "given) are read once")
    return unique


def check_image_topic(topics: dict[str, str], topic: str, bag: Path) -> None:
    """BagError if the bag's `topic` (from BagReader.topics()) carries something other than Image."""
    if (carried := topics.get(topic, IMAGE_TYPE)) != IMAGE_TYPE:
        raise BagError(f"topic {topic} in {bag} carries {carried}, not {IMAGE_TYPE}; pass a mask topic "
                       "with --topic (e.g. /ad_sim/view_0/mask)")


def image_topics(topics: dict[str, str]) -> list[str]:
    """The Image topics among a bag's (BagReader.topics()), sorted."""
    return sorted(t for t, kind in topics.items() if kind == IMAGE_TYPE)


def episode_frames(bag: Path, mask_topic: str = MASK_TOPIC, recover: bool = False,
                   problems: list[str] | None = None, without_ground_truth: list[str] | None = None):
    """(instance, [(stamp_ns, Image)]) per episode of the bag, in order; stamp_ns is None for a frame
    whose stamp is malformed (the node rejects it; accepted_frames says why). `recover`: read a truncated
    or damaged file (a killed recorder) up to its last complete chunk, with a warning. `problems`,
    if given, gets the reader's warnings (BagReader.problems) once the bag is read; `without_ground_truth`
    the bag, if it holds no ground truth message (so no episode)."""
    reader = BagReader(bag, topics=[INSTANCE_TOPIC, mask_topic], recover=recover)
    topics = reader.topics()
    check_image_topic(topics, mask_topic, bag)
    if (carried := topics.get(INSTANCE_TOPIC, INSTANCE_TYPE)) != INSTANCE_TYPE:  # its messages have no episode_id
        raise BagError(f"topic {INSTANCE_TOPIC} in {bag} carries {carried}, not the simulator's ground truth "
                       f"{INSTANCE_TYPE}, which evaluate splits episodes at and scores them against")

    def collided(_, reason: str) -> None:  # their ground truth and frames cannot be paired
        warnings.warn(f"{bag}: {reason}")

    instances = 0

    def counted(episodes):
        nonlocal instances
        for episode in episodes:
            instances += 1
            check_ground_truth(episode.instance, bag)
            yield episode

    for episode in distinct_episodes(counted(group_episodes(reader, INSTANCE_TOPIC)), collided):
        yield episode.instance, [(_stamp_or_none(m.header.stamp), m) for _, m in episode.messages.get(mask_topic, [])]
    if problems is not None:
        problems += reader.problems
    if without_ground_truth is not None and not instances:
        without_ground_truth.append(str(bag))


#: The ground truth's fields evaluate reads: the episode's identity (id and seed), and what it is scored against.
GROUND_TRUTH_FIELDS = ("episode_id", "seed", "material", "parameter_names", "parameters")


def check_ground_truth(instance, bag: Path) -> None:
    """BagError unless the ground truth message has every field evaluate reads. A bag records its own definition
    of each message type (its schema), with which its messages are decoded: one of an older or foreign
    ad_msgs/SimInstance of the same name may lack some (that was an AttributeError traceback)."""
    if missing := [name for name in GROUND_TRUTH_FIELDS if not hasattr(instance, name)]:
        raise BagError(f"{bag}: the ground truth on {INSTANCE_TOPIC} lacks the field{'s' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} that evaluate reads (the bag records another definition of "
                       f"{INSTANCE_TYPE} than this one: an older or a foreign one)")


def _stamp_or_none(stamp) -> int | None:
    try:
        return stamp_to_ns(stamp.sec, stamp.nanosec)
    except ValueError:
        return None


def predict_episode(model: EstimatorModel, bag: Path, instance, frames, observed: int,
                    slot_tolerance: float = DEFAULT_SLOT_TOLERANCE,
                    masks: list[np.ndarray] | None = None, encode=None, slots: int | None = None
                    ) -> EpisodePrediction | None:
    """The estimate from the episode's first `observed` frames (all of them placed on the model's slots), or
    with `slots` (at most the model's frame count), from its first `slots` frame slots, which is what evaluate's
    rows are: the slots 0..slots-1 of the node's window (the frames up to the last one's time, and the tolerance
    past it), as they are when the last of them settles; later frames change none of them. At the model's frame
    interval (a simulator clip) both are the first K frames; from a faster camera K frames fill fewer slots,
    from a slower one more. `masks` (the frames converted) and `encode` (e.g. caching) let several prefixes of
    one episode share that work."""
    frames = frames[:observed]
    if not frames:
        return None
    if slots:  # the frames up to the first at or after the last slot's time: any later one (late, another image
        # size) changes none of the row's slots, as in the node, whose estimate from them is out by then
        last = frames[0][0] + (slots - 1) * round(model.info.frame_interval * 1e9)
        frames = frames[:next((i + 1 for i, (stamp, _) in enumerate(frames) if stamp >= last), len(frames))]
    if masks is None:
        masks = [image_to_mask(image, MAX_IMAGE_PIXELS, model.info.input_threshold()) for _, image in frames]
    # A window of `slots` slots fills its slots as the model's does its first `slots`: the same frames, encoded
    # with the same earlier ones.
    out = clip_output([s for s, _ in frames], masks[:len(frames)], encode or model.encode, model.info.frame_interval,
                      slots or model.info.frame_count, slot_tolerance=slot_tolerance,
                      history=model.info.previous_frames)
    estimate = model.predict(out.features, out.valid)
    return EpisodePrediction(
        episode_id=instance.episode_id, bag=str(bag), frames=slots or observed, true_material=instance.material,
        true_parameters=dict(zip(instance.parameter_names, (float(v) for v in instance.parameters))),
        material=estimate.material, probabilities=estimate.probabilities.tolist(),
        parameters=estimate.parameters.tolist(), raw_parameters=estimate.raw_parameters.tolist(),
        raw_uncertainties=estimate.raw_uncertainties.tolist(), uncertainties=estimate.uncertainties.tolist(),
        frames_used=out.frames_used, slots=len(out.valid),
        oldest_stamp_ns=out.oldest_stamp_ns, newest_stamp_ns=out.newest_stamp_ns)


def to_metrics(predictions: list[EpisodePrediction], parameter_names: tuple[str, ...]) -> metrics.Predictions:
    """The metrics' view of the episodes' predictions (raw_* lists in the model's parameter order)."""
    return metrics.Predictions.from_episodes([vars(p) for p in predictions], parameter_names)


def accepted_frames(bag: Path, instance, frames, threshold: int | None) -> tuple[list, list[np.ndarray], list[dict]]:
    """The episode's frames the node would accept, their masks (image_to_mask with `threshold`), and the
    ones it would reject."""
    accepted, masks, rejected = [], [], []
    for stamp, image in frames:
        try:
            if stamp is None:
                stamp_to_ns(image.header.stamp.sec, image.header.stamp.nanosec)  # raises, saying why
            masks.append(image_to_mask(image, MAX_IMAGE_PIXELS, threshold))
            accepted.append((stamp, image))
        except ValueError as exc:  # ImageRejected, or a malformed stamp
            rejected.append({"bag": str(bag), "episode_id": instance.episode_id, "stamp_ns": stamp, "reason": str(exc)})
    return accepted, masks, rejected


def stamp_text(stamp_ns: int | None) -> str:
    return "(malformed)" if stamp_ns is None else f"{stamp_ns / 1e9:.3f} s"


def check_scorable(model: EstimatorModel) -> None:
    """ModelError unless the metrics can read the model's outputs: its probabilities in FAMILIES order, and
    every parameter they score by name (a model with its classes in another order would be scored, and
    re-simulated, as the wrong family)."""
    if model.info.class_names != tuple(metrics.FAMILIES):
        raise ModelError(f"{model.info.path}: classes {model.info.class_names} differ from {metrics.FAMILIES}")
    if missing := [n for n in metrics.PARAMETER_NAMES if n not in model.info.parameter_names]:
        raise ModelError(f"{model.info.path}: ad.parameter_names lacks {missing}, which the metrics need")


def evaluate(model: EstimatorModel, bags: list[Path], frame_counts: list[int], mask_topic: str = MASK_TOPIC,
             progress: bool = True, recover: bool = False) -> Evaluation:
    """Predictions per number of observed frames (frame slots), every episode of every bag (see score_episode),
    each distinct simulation (simulation_key) once in each row: a copy in a later bag, or a repeat later in the same
    bag (a looping simulator's), of an episode scored already is left out of the rows it was scored in (it fills
    those a cut-short first copy did not), with one warning a bag."""
    check_scorable(model)
    result = Evaluation({k: [] for k in frame_counts}, left_out={k: [] for k in frame_counts})
    scored_from: dict[tuple[tuple, int], Path] = {}  # (simulation_key, K) -> the bag its K row was scored from
    with tqdm(desc="episodes", unit="ep", disable=None if progress else True, file=sys.stderr) as bar:
        for bag in bags:
            before = len(result.left_out[frame_counts[0]])
            copies: dict[Path, int] = {}  # episodes scored before, per bag they were scored from
            repeats = 0  # episodes scored before from this bag
            for instance, frames in episode_frames(bag, mask_topic, recover, result.source_problems,
                                                   result.without_ground_truth):
                bar.update()
                key = simulation_key(instance)
                # A row that holds the simulation already would count it twice: it is scored there once, the first
                # time; a copy fills only the rows an earlier one was left out of (cut short, say).
                taken = {k: source for k in frame_counts if (source := scored_from.get((key, k))) is not None}
                if taken:
                    first = next(iter(taken.values()))
                    if first == bag:
                        repeats += 1  # a looping simulator's later pass (the same simulation, later stamps)
                    else:
                        copies[first] = copies.get(first, 0) + 1  # a copy of a recording
                    for k, source in taken.items():
                        result.left_out[k].append({"bag": str(bag), "episode_id": instance.episode_id,
                                                   "reason": REPEAT if source == bag else f"{COPY} {source}"})
                rows = [k for k in frame_counts if k not in taken]
                if not rows:
                    continue
                scored = {k: len(result.predictions[k]) for k in rows}
                score_episode(model, bag, instance, frames, rows, result)
                scored_from.update({(key, k): bag for k in rows if len(result.predictions[k]) > scored[k]})
            if silent := sum(e["reason"] == NO_FRAME for e in result.left_out[frame_counts[0]][before:]):
                warnings.warn(f"{bag}: {silent} episode(s) left out of every row: {NO_FRAME}")  # one line a bag
            if repeats:  # one line a bag, as a looping simulator replays every episode
                warnings.warn(f"{bag}: {repeats} episode(s) left out of the rows they were scored in: {REPEAT} (a "
                              "looping simulator's later passes replay its episodes; each is scored once)")
            for first, count in copies.items():  # one line a bag, as a whole copied bag would give one an episode
                warnings.warn(f"{bag}: {count} episode(s) left out of the rows they were scored in: {COPY} {first} "
                              "(a copy of a recording is scored once)")
            if str(bag) in result.without_ground_truth:
                warnings.warn(f"{bag}: no ground truth ({INSTANCE_TYPE} on {INSTANCE_TOPIC}), so no episode: "
                              "nothing in it is scored")
    return result


NO_FRAME = "it has no mask frame on the topic"
COPY = "the same simulation was scored from"
REPEAT = "the same simulation was scored earlier from this bag"


def unscorable_ground_truth(instance) -> str:
    """Why the metrics cannot score against the episode's ground truth ('' when they can): a material they do not
    know, or a parameter they score for it missing, not finite, or not positive where scored in log space (one
    such episode made a column, and RegL1 over all clips, n/a or a number of no meaning)."""
    if instance.material not in metrics.FAMILIES:
        return f"its material {instance.material!r} is none of {', '.join(metrics.FAMILIES)}"
    given = dict(zip(instance.parameter_names, instance.parameters))
    for name, (_, _, scale) in metrics.family_ranges()[instance.material].items():
        if name not in given:
            return (f"its ground truth lacks {name}, which the metrics score for {instance.material} (it gives "
                    f"{', '.join(instance.parameter_names) or 'no parameter'})")
        if not (math.isfinite(value := float(given[name])) and (value > 0 or scale != "log")):
            return f"its ground truth {name} {value:g} is not a {'positive' if scale == 'log' else 'finite'} number"
    return ""


def score_episode(model: EstimatorModel, bag: Path, instance, frames, frame_counts: list[int],
                  result: Evaluation) -> None:
    """Adds the episode's prediction for each K (its first K frame slots, predict_episode) to `result`. As in
    the node, rejected frames are skipped; an episode whose window holds fewer than K frame slots is left out
    of the K row.
    Each of these is noted in `result` and warned about, naming the bag and episode."""
    where = f"{bag}: episode {instance.episode_id}"
    if reason := unscorable_ground_truth(instance):  # no ground truth the metrics can score
        warnings.warn(f"{where}: left out of every row: {reason}")
        for k in frame_counts:
            result.left_out[k].append({"bag": str(bag), "episode_id": instance.episode_id, "reason": reason})
        return
    frames, masks, rejected = accepted_frames(bag, instance, frames, model.info.input_threshold())
    if rejected:
        result.skipped_frames += rejected
        warnings.warn(f"{where}: {len(rejected)} mask frame(s) skipped, as the node rejects them; the first at "
                      f"stamp {stamp_text(rejected[0]['stamp_ns'])}: {rejected[0]['reason']}")
    if not frames:  # no estimate at all: said and counted, not dropped silently from every row
        reason = f"all {len(rejected)} of its mask frames are rejected" if rejected else NO_FRAME
        if rejected:  # (evaluate says NO_FRAME once a bag: a wrong --topic would give a line an episode)
            warnings.warn(f"{where}: left out of every row: {reason}")
        for k in frame_counts:
            result.left_out[k].append({"bag": str(bag), "episode_id": instance.episode_id, "reason": reason})
        return
    if changes := [i for i in range(1, len(masks)) if masks[i].shape != masks[i - 1].shape]:
        before, after = masks[changes[0] - 1].shape, masks[changes[0]].shape
        warnings.warn(f"{where}: the image size changes from {before[1]}x{before[0]} to {after[1]}x{after[0]} at "
                      f"stamp {stamp_text(frames[changes[0]][0])}; as in the node, the frame window restarts there")
    # Every prefix length reuses the episode's conversions and frame encodings.
    features: dict[tuple[int, tuple[int, ...]], np.ndarray] = {}

    def encode(mask: np.ndarray, earlier: list[np.ndarray]) -> np.ndarray:
        key = (id(mask), tuple(id(e) for e in earlier))
        if key not in features:
            features[key] = model.encode(mask, earlier)
        return features[key]

    by_k, refused = {}, {}
    for k in frame_counts:
        try:
            by_k[k] = predict_episode(model, bag, instance, frames, len(frames), masks=masks, encode=encode, slots=k)
        except ValueError as exc:  # e.g. stamps that repeat or go backwards among the row's frames
            refused[k] = str(exc)
    if refused:
        first = next(iter(refused.values()))
        warnings.warn(f"{where}: left out of the K = {', '.join(map(str, refused))} row(s): {first}")
    left_out = {k: f"its window holds {p.slots} of {k} frame slots"
                for k, p in by_k.items() if p is not None and p.slots < k}
    if left_out:
        longest, interval = max(left_out), model.info.frame_interval
        span = (frames[-1][0] - frames[0][0]) / 1e9
        start = by_k[longest].oldest_stamp_ns  # slot 0's frame: the episode's first unless the window restarted
        cause = "the episode is cut short" if start == frames[0][0] else \
            f"its window restarted at the image size change at stamp {stamp_text(start)}"
        warnings.warn(f"{where}: left out of the K = {', '.join(map(str, left_out))} row(s): fewer frame slots "
                      f"than K (the K = {longest} window holds {by_k[longest].slots}; its {len(frames)} accepted "
                      f"frames span {span:.3f} s, slot {longest - 1} lies {(longest - 1) * interval:.3f} s after "
                      f"the first: {cause})")
    left_out.update(refused)
    for k, reason in left_out.items():
        result.left_out[k].append({"bag": str(bag), "episode_id": instance.episode_id, "reason": reason})
    for k, prediction in by_k.items():
        if prediction is not None and k not in left_out:
            result.predictions[k].append(prediction)


def check_out(out: Path, file: str = "") -> None:
    """--out can be made and written, checked before any work (creating nothing yet): the report
    folder `out`, or with `file` (what it is: "a .csv file") the file `out`, in its folder."""
    folder = out.parent if file else out
    wanted = f"{file} in a folder" if file else "a folder for the report"
    base = next(p for p in (folder, *folder.parents) if p.exists())  # the folder that would hold it
    if not base.is_dir():
        raise ValueError(f"--out {out}: {base} is not a folder; pass {wanted}")
    try:
        tempfile.TemporaryFile(dir=base).close()
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot write in {base} ({exc.strerror}); pass {wanted} "
                         "that you can write in") from exc


def write_report(folder: Path, by_frames: dict, title: str, evaluation: Evaluation, model: EstimatorModel,
                 args: argparse.Namespace) -> dict:
    """The report (metrics.write_report) and predictions.json in `folder`; returns the metrics."""
    report = metrics.write_report(by_frames, folder, title)
    if problems := evaluation.problems():
        with open(folder / "report.md", "a") as md:
            md.write(f"\nInput problems: {problems} (listed in predictions.json).\n")
    (folder / "predictions.json").write_text(metrics.json_text(
        {"model_id": model.model_id, "model_path": str(args.model), "topic": args.topic,
         "parameter_names": list(model.info.parameter_names),
         "frames": {str(k): [vars(p) for p in v] for k, v in evaluation.predictions.items()},
         "source_problems": evaluation.source_problems, "skipped_frames": evaluation.skipped_frames,
         "without_ground_truth": evaluation.without_ground_truth,
         "left_out": {str(k): v for k, v in evaluation.left_out.items()}}, indent=1))
    return report


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ros2 run ad_estimator evaluate", formatter_class=HelpFormatter,
        description="Run an ONNX student over recorded bags offline (same preprocessing and frame slots as the "
                    "node) and report the paper's metrics (SPEC 8). Needs bags recorded from the simulator: "
                    f"episodes are split at, and scored against, the ground truth on {INSTANCE_TOPIC} "
                    "(material and parameters); frames before the first such message are skipped, and a bag "
                    "without any gives no episodes. For your own bags without ground truth, `ros2 run ad_estimator "
                    "estimate BAG --topic TOPIC` writes the node's estimates as a CSV.")
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: the bundled one)")
    parser.add_argument("--bags", type=Path, nargs="+", required=True,
                        help="bag folders, .mcap files, or folders holding bags (searched recursively)")
    parser.add_argument("--frames", action=metrics.FrameCounts, nargs="*", default=None, metavar="K",
                        help=f"also evaluate with only the first K frame slots observed (temporal OOD; "
                             f"K x the model's frame interval, whatever the camera's rate), e.g. "
                             f"--frames 24 18 or --frames 24,18; with no value: "
                             f"{' '.join(map(str, metrics.TEMPORAL_OOD_FRAMES))} (those below the model's frame "
                             "count)")
    parser.add_argument("--topic", type=topic, default=MASK_TOPIC, help="mask topic to evaluate (one camera; sensor_msgs/Image)")
    parser.add_argument("--out", type=Path, default=None,
                        help="report folder (default reports/evaluate/<model id>)")
    parser.add_argument("--title", default=None, help="report title")
    parser.add_argument("--threads", type=positive, default=1, help="onnxruntime intra-op threads")
    parser.add_argument("--recover", action="store_true",
                        help="read truncated or damaged files (a killed recorder) up to their last complete chunk")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser.parse_args(argv)


@interruptible("evaluate")
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_line_warnings()
    try:
        model = EstimatorModel.load(args.model, threads=args.threads)
        count = model.info.frame_count
        # --frames alone: the temporal-OOD rows the model's frames reach (for a model of 20 frames, 18 and 15)
        extra = [k for k in metrics.TEMPORAL_OOD_FRAMES if k < count] if args.frames == [] else (args.frames or [])
        if bad := [k for k in extra if not 1 <= k <= count]:
            raise ValueError(f"--frames {bad}: each K must be in 1..{count}")
        counts = sorted({count, *extra}, reverse=True)
        out = args.out or Path("reports") / "evaluate" / model.model_id
        check_out(out)
        bags = find_bags(args.bags)
        evaluation = evaluate(model, bags, counts, args.topic, progress=not args.quiet, recover=args.recover)
    except (ModelError, BagError, ValueError) as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 1
    results, problems = evaluation.predictions, evaluation.problems()
    if len(evaluation.without_ground_truth) == len(bags):
        print(f"evaluate: no ground truth ({INSTANCE_TYPE} on {INSTANCE_TOPIC}) in {[str(b) for b in args.bags]}, "
              "so no episode to score: evaluate scores recordings of the simulator, whose ground truth splits them "
              "into episodes and is what they are scored against; for bags without it, `ros2 run ad_estimator "
              "estimate BAG --topic TOPIC` writes the node's estimates as a CSV", file=sys.stderr)
        return 1
    if not results[count]:
        with warnings.catch_warnings():  # the bags' own problems were said while reading them
            warnings.simplefilter("ignore")
            images = sorted({t for bag in bags for t in image_topics(BagReader(bag, recover=True).topics())})
        hint = "" if args.topic in images else f"; the bags' image topics: {', '.join(images) or 'none'} " \
                                                "(pass one with --topic)"
        print(f"evaluate: no episode with {count} frames on {args.topic} in {[str(b) for b in args.bags]}"
              + (f"; {problems}" if problems else "") + hint, file=sys.stderr)
        return 1
    title = args.title or f"{model.model_id} on {', '.join(str(b) for b in args.bags)}"
    by_frames = {k: to_metrics(v, model.info.parameter_names) for k, v in results.items()}
    replaced = " (it replaced the report of an earlier run)" if (out / "report.md").exists() else ""
    try:
        with staged(out) as folder:  # an earlier report stays whole if this one cannot be written
            report = write_report(folder, by_frames, title, evaluation, model, args)
    except OSError as exc:
        print(f"evaluate: cannot write the report to {out} ({exc}); free space there or pass another --out",
              file=sys.stderr)
        return 1
    print(metrics.format_table(report, title))
    if problems:
        print(f"\ninput problems: {problems} (see the warnings above)")
    print(f"\nreport: {out / 'report.md'}  predictions: {out / 'predictions.json'}{replaced}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
