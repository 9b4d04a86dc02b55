"""MCAP bags -> per-instance arrays, cached as memory-mappable .npy files.

Reads rosbag2 MCAP bags with ad_sim.rosbag's reader (mcap + mcap-ros2-support, no ROS runtime),
following the bag layout of docs/architecture.md; episodes are split at each `/ad_sim/instance`
message (ad_sim.rosbag.group_episodes) and a frame's index is its stamp offset from the
instance's stamp in FRAME_INTERVAL units.

Cache: one folder per bag (a rosbag2 folder, or a lone .mcap file), `<cache>/<key>/`, key =
sha256 over CACHE_VERSION and, per .mcap file, its name, size, first and last MiB (the MCAP
summary and footer sit at the end: a compressed chunk's size there changes with its content) and
the CRC of each uncompressed chunk (whose size does not), so any rewrite changes the key. A bag
found twice under --bags (a copy) is read once. Contents:
  meta.json            episode ids, shapes, splits, materials, seeds; source_problems: what was
                       missing or unreadable in the bag (truncated files, skipped episodes), warned
                       again on every use of the cache
  labels.npy           (N,) int64 class index into FAMILIES
  params_si.npy        (N, 4) float64 SI, NaN where the family lacks the parameter
  params_norm.npy      (N, 4) float32 normalised over the union ranges (0 where not sampled)
  param_mask.npy       (N, 4) float32 1 where the family samples the parameter (RegL1 targets)
  trajectories.npy     (N, 25, 1024, 15) float16: x y z, median-normalised displacement, F (row-major)
  videos.npy           (M, 25, 128, 128) uint8 0/255, one per (instance, view); levels 0..255 in the
                       folder `<key>-coverage` that load_dataset(coverage=True) writes (grey masks)
  video_instance.npy   (M,) int64 row of the video's instance; video_view.npy (M,) int64 camera index
  videos_<H>x<W>.npy   (M, 25, H, W) float16 in [0, 1], area-resized for a student (made on demand)
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ad_estimator.images import DEFAULT_THRESHOLD, MAX_IMAGE_PIXELS, image_to_mask
from ad_sim.materials import (
    FAMILIES,
    FRAME_COUNT,
    FRAME_INTERVAL,
    PARAMETER_NAMES,
    SAMPLED_PARAMETERS,
    normalise,
)
from ad_sim.messages import POINT_FIELDS, instance_topic, particles_topic
from ad_sim.render import MASK_SIZE
from ad_sim.rosbag import BagError, BagReader, BagUnreadable, distinct_episodes, group_episodes

log = logging.getLogger(__name__)

# 2: meta.json records source_problems; 3: episodes sharing a start stamp are left out (distinct_episodes); 4: so is
# a parameter sweep recorded into one bag (one id and seed, runs stamped alike), no longer taken for one episode.
CACHE_VERSION = 4
MASK_TOPIC = re.compile(r"^/ad_sim/view_(\d+)/mask$")
_HASH_BLOCK = 1 << 20
RESIZE_SLICE_FRAMES = 4096  # frames resized per slice by resized_videos (64 MB of 128x128 masks)


def find_bags(root: str | Path) -> list[Path]:
    """Bags under root (ad_estimator.evaluate.find_bags); FileNotFoundError if there are none."""
    from ad_estimator.evaluate import find_bags as bags_under  # here: it pulls in metrics and the runtime

    root = Path(root)
    try:
        return bags_under([root])
    except BagError as exc:
        hint = (f"; generate some with `python -m ad_sim.generate --size tiny --split <train|seen|unseen> "
                f"--out {root}`" if root.exists() else "")
        raise FileNotFoundError(f"{exc}{hint}") from None


def _mcap_files(bag: Path) -> list[Path]:
    return [bag] if bag.is_file() else sorted(bag.glob("*.mcap"))


def has_grey_levels(episodes: list[dict]) -> bool:
    """Whether any mask of the decoded episodes holds a level other than 0 and 255: grey masks (the
    simulator's coverage masks, from `ad_sim.generate --coverage-masks` or the sim node's
    coverage_masks, recorded either way) always do at the object's edges."""
    return any(np.any((video != 0) & (video != 255)) for ep in episodes for video in ep["videos"].values())


def _uncompressed_chunk_crcs(f) -> bytes:
    """The content CRCs of an MCAP file's uncompressed chunks, read from their record headers (a few
    bytes each, found through the summary), in file order. The first and last MiB miss a change in
    the middle of a bag whose sizes stay the same, which uncompressed chunks of fixed-size messages
    (`ad_sim.generate --compression none`) do: a compressed chunk's size changes with its content,
    and the summary that lists the sizes is at the end. A file without a readable summary (cut
    short) gives nothing here: its size and ends are its key."""
    from mcap.reader import SeekingReader

    try:
        f.seek(0)  # (the reader checks the magic where the stream stands)
        summary = SeekingReader(f).get_summary()
    except Exception:  # no footer or summary: a truncated file (read in recover mode)
        return b""
    crcs = []
    for chunk in sorted(summary.chunk_indexes if summary else [], key=lambda c: c.chunk_start_offset):
        if chunk.compression:
            continue
        # Chunk record: opcode (1), record length (8), message start and end time (8 + 8), uncompressed
        # size (8), then the uncompressed CRC (4).
        f.seek(chunk.chunk_start_offset + 33)
        crc = f.read(4)
        if crc == bytes(4):  # written without CRCs: the chunk itself
            f.seek(chunk.chunk_start_offset)
            crc = hashlib.sha256(f.read(chunk.chunk_length)).digest()
        crcs.append(crc)
    return b"".join(crcs)


def bag_key(bag: Path) -> str:
    """Content key of one bag (see the module docstring)."""
    h = hashlib.sha256(f"v{CACHE_VERSION}".encode())
    for path in _mcap_files(bag):
        size = path.stat().st_size
        h.update(f"{path.name}:{size}".encode())
        with open(path, "rb") as f:
            h.update(f.read(_HASH_BLOCK))
            f.seek(max(0, size - _HASH_BLOCK))
            h.update(f.read(_HASH_BLOCK))
            h.update(_uncompressed_chunk_crcs(f))  # nothing for compressed chunks: their keys stay as they were
    return h.hexdigest()[:32]


class EpisodeRejected(ValueError):
    """An episode of a bag cannot be used (the message names the bag, the episode and why)."""


def episode_video(bag: Path, episode_id: str, topic: str, frames, coverage: bool = False) -> np.ndarray:
    """(T, MASK_SIZE, MASK_SIZE) uint8 {0, 255} masks of one episode's [(stamp_ns, Image)] frames
    (with `coverage`, the levels as they are: grey masks), converted as the estimator converts
    camera frames (ad_estimator.images). EpisodeRejected
    for a frame that cannot be used or is not of the simulator's mask size (what re-simulation
    renders and the cache stacks)."""
    masks = []
    for stamp, image in frames:
        where = f"{bag}: episode {episode_id}: {topic} frame stamped {stamp / 1e9:.3f} s"
        try:
            mask = image_to_mask(image, MAX_IMAGE_PIXELS, None if coverage else DEFAULT_THRESHOLD)
        except ValueError as exc:
            raise EpisodeRejected(f"{where}: {exc}") from exc
        if mask.shape != (MASK_SIZE, MASK_SIZE):
            raise EpisodeRejected(f"{where}: mask is {mask.shape[1]}x{mask.shape[0]}, "
                                  f"not the simulator's {MASK_SIZE}x{MASK_SIZE}")
        masks.append(mask)
    return np.stack(masks)


def _particles(msg) -> np.ndarray:
    """PointCloud2 -> (points, 15) float32 in POINT_FIELDS order (fields located by name)."""
    offsets = {f.name: f.offset for f in msg.fields}
    missing = [n for n in POINT_FIELDS if n not in offsets]
    if missing:
        raise ValueError(f"particle cloud lacks fields {missing}")
    n = msg.width * msg.height
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(n, msg.point_step)
    return np.stack([raw[:, offsets[name]: offsets[name] + 4].copy().view("<f4")[:, 0] for name in POINT_FIELDS],
                    axis=1).astype(np.float32)


# Normalised displacements stay below this: the cache stores trajectories as float16 (largest 65504).
FLOAT16_SAFE = 6.0e4


def normalise_displacement(trajectory: np.ndarray) -> np.ndarray:
    """Scales the displacement channels (3:6) by their median magnitude over particles and
    frames 1..T-1 (SPEC 6), in place; a motionless episode keeps its zeros. An object at rest for
    most of the episode (a hard impact) can have a median near zero: the scale is then raised just
    enough that the largest displacement stays within FLOAT16_SAFE, instead of caching infinities."""
    mags = np.linalg.norm(trajectory[1:, :, 3:6], axis=-1)
    scale = max(float(np.median(mags)), float(mags.max(initial=0.0)) / FLOAT16_SAFE)
    if scale > 1e-12:
        trajectory[:, :, 3:6] /= scale
    return trajectory


def labels_of(material: str, names, values) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """SimInstance ground truth -> (class, SI params with NaN, normalised params, validity mask)."""
    if material not in FAMILIES:
        raise ValueError(f"unknown material {material!r} in bag; expected one of {FAMILIES}")
    si = np.full(len(PARAMETER_NAMES), np.nan)
    for name, value in zip(names, values):
        si[PARAMETER_NAMES.index(name)] = value
    mask = np.array([n in SAMPLED_PARAMETERS[material] for n in PARAMETER_NAMES], dtype=np.float32)
    norm = np.array([normalise(n, si[j]) if mask[j] else 0.0 for j, n in enumerate(PARAMETER_NAMES)],
                    dtype=np.float32)
    return FAMILIES.index(material), si, norm, mask


def _frames(items, start_ns: int) -> dict[int, tuple[int, object]]:
    """(stamp_ns, message) of one topic keyed by frame index (stamp offset / FRAME_INTERVAL)."""
    out = {}
    for stamp, msg in items:
        t = round((stamp - start_ns) * 1e-9 / FRAME_INTERVAL)
        if 0 <= t < FRAME_COUNT:
            out[t] = (stamp, msg)
    return out


def read_bag(bag: Path, coverage: bool = False) -> tuple[list[dict], list[str]]:
    """Decodes one bag into its complete episodes, and what was missing or unreadable, one line each:
    the reader's warnings (a truncated file, read in recover mode) and the episodes skipped, each
    warned as it is found. An episode is skipped when it lacks frames or one of its frames cannot
    be used, or when it starts at the stamp of another episode (distinct_episodes); the others are kept."""
    out, skipped = [], []
    wanted = {instance_topic(), particles_topic()}
    reader = BagReader(bag, recover=True)  # one reader: its topics() scan and the reading warn once
    reader.topic_filter = {t for t in reader.topics() if t in wanted or MASK_TOPIC.match(t)}
    episodes = lost = 0

    def collided(same, reason: str) -> None:
        nonlocal episodes, lost
        episodes, lost = episodes + len(same), lost + len(same)
        skipped.append(f"{bag}: {reason}")
        log.warning("%s", skipped[-1])

    for ep in distinct_episodes(group_episodes(reader, instance_topic()), collided):
        episodes += 1
        inst = ep.instance
        particles = _frames(ep.messages.get(particles_topic(), []), ep.stamp_ns)
        views = {}
        for topic, items in ep.messages.items():
            m = MASK_TOPIC.match(topic)
            frames = _frames(items, ep.stamp_ns) if m else {}
            if len(frames) == FRAME_COUNT:
                views[int(m.group(1))] = (topic, [frames[t] for t in range(FRAME_COUNT)])
        if len(particles) != FRAME_COUNT or not views:
            skipped.append(f"{bag}: episode {inst.episode_id} is incomplete ({len(particles)} particle frames, "
                           f"{len(views)} complete views); skipped")
            log.warning("%s", skipped[-1])
            lost += 1
            continue
        try:
            videos = {view: episode_video(bag, inst.episode_id, topic, frames, coverage)
                      for view, (topic, frames) in views.items()}
        except EpisodeRejected as exc:
            skipped.append(f"{exc}; episode skipped")
            log.warning("%s", skipped[-1])
            lost += 1
            continue
        trajectory = np.stack([_particles(particles[t][1]) for t in range(FRAME_COUNT)])
        label, si, norm, mask = labels_of(inst.material, inst.parameter_names, inst.parameters)
        out.append({
            "episode_id": inst.episode_id, "shape": inst.shape, "split": inst.split, "material": inst.material,
            "seed": int(inst.seed), "label": label, "params_si": si, "params_norm": norm, "param_mask": mask,
            "trajectory": normalise_displacement(trajectory), "videos": dict(sorted(videos.items())),
        })
    if skipped:
        skipped.append(f"{bag}: {lost} of {episodes} episodes skipped")
        log.warning("%s", skipped[-1])
    return out, reader.problems + skipped


_META_KEYS = ("episode_id", "shape", "split", "material", "seed")  # per-episode lists of a shard's meta.json


def _write_shard(folder: Path, episodes: list[dict], source_problems: list[str]) -> None:
    tmp = folder.with_name(folder.name + f".tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    np.save(tmp / "labels.npy", np.array([e["label"] for e in episodes], dtype=np.int64))
    np.save(tmp / "params_si.npy", np.array([e["params_si"] for e in episodes], dtype=np.float64).reshape(-1, 4))
    np.save(tmp / "params_norm.npy", np.array([e["params_norm"] for e in episodes], dtype=np.float32).reshape(-1, 4))
    np.save(tmp / "param_mask.npy", np.array([e["param_mask"] for e in episodes], dtype=np.float32).reshape(-1, 4))
    np.save(tmp / "trajectories.npy", np.array([e["trajectory"] for e in episodes], dtype=np.float16))
    videos, owner, views = [], [], []
    for i, e in enumerate(episodes):
        for v, video in e["videos"].items():
            videos.append(video)
            owner.append(i)
            views.append(v)
    np.save(tmp / "videos.npy", np.stack(videos).astype(np.uint8))  # every episode has >= 1 complete view
    np.save(tmp / "video_instance.npy", np.array(owner, dtype=np.int64))
    np.save(tmp / "video_view.npy", np.array(views, dtype=np.int64))
    meta = {key: [e[key] for e in episodes] for key in _META_KEYS}
    meta["source_problems"] = source_problems
    (tmp / "meta.json").write_text(json.dumps(meta))
    try:
        os.replace(tmp, folder)  # atomic: a killed run never leaves a half-written shard
    except OSError:
        if not (folder / "meta.json").exists():
            raise
        shutil.rmtree(tmp)  # another process cached the same bag first


def damaged_shard(folder: Path, name: str, exc: Exception) -> ValueError:
    """The one-line error for a file `name` of a cache folder that cannot be read (truncated, removed,
    edited): which folder and file, and that deleting the folder rebuilds it from its bag (numpy's or
    json's own text named neither)."""
    if isinstance(exc, FileNotFoundError):
        reason = "missing"
    else:  # the first sentence: numpy's advice on pickles does not apply to a cache
        reason = (str(exc).strip().splitlines() or [""])[0].split(". ")[0] or type(exc).__name__
    return ValueError(f"the cache folder {folder} is damaged ({name}: {reason}); delete that folder and it is "
                      "rebuilt from its bag on the next run")


def shard_meta(folder: Path) -> dict:
    """A cache folder's meta.json, checked (damaged_shard if it cannot be used)."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
        if not isinstance(meta, dict):
            raise ValueError(f"a JSON {type(meta).__name__}, not an object")
        if missing := [k for k in (*_META_KEYS, "source_problems") if not isinstance(meta.get(k), list)]:
            raise ValueError(f"no lists {', '.join(missing)}")
    except (OSError, ValueError) as exc:  # (json's and Unicode decode errors are ValueErrors)
        raise damaged_shard(folder, "meta.json", exc) from None
    return meta


def _shard_array(folder: Path, name: str, mmap: bool = False) -> np.ndarray:
    try:
        return np.load(folder / name, mmap_mode="r" if mmap else None)
    except (OSError, ValueError, EOFError) as exc:  # missing, truncated ("mmap length is greater ..."), not .npy
        raise damaged_shard(folder, name, exc) from None


class Dataset:
    """All instances of a set of bags; small arrays in memory, big ones memory-mapped per shard."""

    def __init__(self, shards: list[Path], problems: list[str] = ()):
        if not shards:
            raise ValueError("a Dataset needs at least one cached bag")
        self.shards = shards
        self.problems = list(problems)  # what in the source bags was left out (episodes, whole bags, truncation)

        def load(name: str, mmap: bool = False) -> list[np.ndarray]:
            return [_shard_array(s, name, mmap) for s in shards]

        self._trajectories = load("trajectories.npy", mmap=True)
        self._videos = load("videos.npy", mmap=True)
        self.labels = np.concatenate(load("labels.npy"))
        self.params_si, self.params_norm, self.param_mask = (
            np.concatenate(load(f"{name}.npy")).reshape(-1, 4) for name in ("params_si", "params_norm", "param_mask"))
        metas = [shard_meta(s) for s in shards]
        self.meta = {k: sum((m[k] for m in metas), []) for k in _META_KEYS}
        self.episode_ids: list[str] = self.meta["episode_id"]
        # Global instance index -> (shard, row); global video index -> (shard, row) and its instance.
        self._inst_loc = [(s, r) for s, a in enumerate(self._trajectories) for r in range(len(a))]
        offsets = np.cumsum([0] + [len(a) for a in self._trajectories])
        owners = load("video_instance.npy")
        self.video_loc = [(s, r) for s, o in enumerate(owners) for r in range(len(o))]
        self.video_instance = np.concatenate([o + offsets[s] for s, o in enumerate(owners)])
        self.video_view = np.concatenate(load("video_view.npy"))

    def __len__(self) -> int:
        return len(self.labels)

    def fingerprint(self) -> str:
        """Which instances, in which order (the validation split is drawn over their indices): equal
        for the same bags wherever they lie, different if any instance is added, removed or moved."""
        h = hashlib.sha256()
        for episode_id, seed in zip(self.meta["episode_id"], self.meta["seed"]):
            h.update(f"{episode_id}:{seed}\n".encode())
        return h.hexdigest()[:12]

    def camera_views(self) -> str:
        """Which camera views the instances have, as a resume check shows it: the views and the number
        of videos ("0,1 (18 videos)"), and where instances differ in their views, a digest of each one's
        (with `fingerprint` equal, that pins down every video a student trains on)."""
        views: dict[int, list[int]] = {}
        for i, v in zip(self.video_instance.tolist(), self.video_view.tolist()):
            views.setdefault(i, []).append(v)
        per_instance = [",".join(map(str, sorted(views[i]))) for i in range(len(self))]
        text = f"{','.join(map(str, sorted(set(self.video_view.tolist()))))} ({self.num_videos} videos)"
        if len(set(per_instance)) > 1:
            text += f", per instance {hashlib.sha256(' '.join(per_instance).encode()).hexdigest()[:12]}"
        return text

    def episode_keys(self) -> list[tuple]:
        """Per instance, which simulation it is: its id and seed (as `fingerprint` names it), shape, family and
        parameters. The same for an episode found in two bags (say, regenerated with another shard count, or
        repaired beside the original) or replayed by a looping simulator; not for a sweep of one id and seed over
        parameters (the simulator node's single-instance mode), whose episodes are distinct simulations."""
        return [(*key, self.params_si[i].tobytes()) for i, key in enumerate(
            zip(self.meta["episode_id"], self.meta["seed"], self.meta["shape"], self.meta["material"]))]

    def split(self, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The train/validation split of these instances (split_instances), every copy of an episode on
        one side: with a copy on each, validation would score episodes the model trained on. Training
        keeps every copy; validation scores each episode once, as evaluation does (first_copies)."""
        train, val = split_instances(len(self), val_fraction, seed, self.episode_keys())
        return train, val[np.isin(val, self.first_copies())]

    def test_split_warning(self, bags) -> str | None:
        """A warning when these training instances include benchmark test instances (a --bags that
        points at the folder above the splits), which would score the model on what it trained on."""
        held_out = {split: self.meta["split"].count(split) for split in ("seen", "unseen")}
        if not any(held_out.values()):
            return None
        which = " and ".join(f"{n} {split}" for split, n in held_out.items() if n)
        return (f"warning: the {len(self)} instances under {bags} (training and validation) include {which} "
                "instances of the benchmark's test splits, so scores on those splits would not measure "
                "generalisation; point --bags at the train split (for example bags/paper/train)")

    def train_split_warning(self, bags) -> str | None:
        """The other way round, for an evaluation: a warning when these instances include the benchmark's
        train split, which models are trained on, so scores on them flatter the model."""
        trained_on = self.meta["split"].count("train")
        if not trained_on:
            return None
        return (f"warning: {trained_on} of the {len(self)} instances scored under {bags} are from the benchmark's "
                "train split, which models are trained on, so these scores do not measure generalisation; "
                "evaluate on the seen or unseen split (for example bags/paper/unseen)")

    @property
    def num_videos(self) -> int:
        return len(self.video_instance)

    def trajectory(self, i: int) -> np.ndarray:
        """(25, 1024, 15) float32 of instance i."""
        s, r = self._inst_loc[i]
        return np.asarray(self._trajectories[s][r], dtype=np.float32)

    def video(self, j: int) -> np.ndarray:
        """(25, 128, 128) uint8 mask video j: 0/255, or levels 0..255 in a coverage dataset."""
        s, r = self.video_loc[j]
        return np.asarray(self._videos[s][r])

    def videos_of(self, instances: np.ndarray) -> np.ndarray:
        """Indices of every video of the given instances."""
        return np.flatnonzero(np.isin(self.video_instance, instances))

    def first_copies(self) -> np.ndarray:
        """Indices of the instances that are the first copy of their episode (episode_keys): a looping
        simulator's replays and a second recording's copies left out, so that each episode is scored once."""
        first: dict = {}
        for i, key in enumerate(self.episode_keys()):
            first.setdefault(key, i)
        return np.array(sorted(first.values()), dtype=np.int64)

    def first_view_videos(self, instances: np.ndarray | None = None) -> np.ndarray:
        """One video per instance (its lowest view), the evaluation convention."""
        wanted = None if instances is None else set(np.asarray(instances).tolist())
        pick = {}
        for j, (i, v) in enumerate(zip(self.video_instance.tolist(), self.video_view.tolist())):
            if (wanted is None or i in wanted) and (i not in pick or v < self.video_view[pick[i]]):
                pick[int(i)] = j
        return np.array([pick[i] for i in sorted(pick)], dtype=np.int64)


def load_dataset(bags: str | Path, cache_dir: str | Path, progress: bool = True, coverage: bool = False) -> Dataset:
    """Decodes every bag under `bags` that is not cached yet, then opens the cached dataset. With
    `coverage` the videos keep the masks' grey levels (a separate cache folder per bag)."""
    cache_dir = Path(cache_dir)
    shards, sources, problems = [], [], []
    paths = find_bags(bags)
    for path in tqdm(paths, desc="cache bags", disable=None if progress else True, unit="bag"):
        folder = cache_dir / (bag_key(path) + ("-coverage" if coverage else ""))
        if folder in shards:  # a copy of a bag already read (its episodes would count twice)
            log.warning("%s holds the same recording as a bag read before (cache %s); read once", path, folder.name)
            continue
        if (folder / "meta.json").exists():
            source_problems = shard_meta(folder)["source_problems"]
            for problem in source_problems:
                log.warning("cached from an incomplete bag: %s", problem)
        elif folder.exists():  # shards appear whole (_write_shard renames them in): this one lost its meta.json
            raise damaged_shard(folder, "meta.json", FileNotFoundError())
        else:
            try:
                episodes, source_problems = read_bag(path, coverage)
            except BagUnreadable as exc:  # damaged before its first complete chunk: left out, saying why
                episodes, source_problems = [], [str(exc)]
                log.warning("%s", exc)
            if not episodes:
                problems += [*source_problems, f"{path} holds no complete episode; left out"]
                log.warning("%s", problems[-1])
                continue
            if coverage and not has_grey_levels(episodes):  # said once, as the bag is cached
                log.warning("grey-mask videos asked for, but the masks of %s are 0/255 only: it was not recorded "
                            "with coverage masks (ad_sim.generate --coverage-masks, or the sim node's coverage_masks "
                            "parameter), so a grey-mask student learns thresholded masks from it", path)
            _write_shard(folder, episodes, source_problems)
        problems += source_problems
        shards.append(folder)
        sources.append(path)
    if not shards:
        raise ValueError(f"no complete episodes in the bags under {bags}: training and `python -m training` "
                         f"evaluation need all {FRAME_COUNT} frames of a mask view and of the tracked particles "
                         f"({particles_topic()}), which bags generated with --skip-particles lack (evaluate those "
                         f"with `ros2 run ad_estimator evaluate`)")
    dataset = Dataset(shards, problems)
    _warn_of_repeated_episodes(dataset, sources, bags)
    return dataset


def _warn_of_repeated_episodes(dataset: Dataset, sources: list[Path], bags) -> None:
    """One warning if an episode (the same simulation: episode_keys) is in more than one of the bags read (say,
    a split recorded through topics and generated as well, under one --bags), and one if an episode repeats
    within a bag (a looping simulator recorded): each copy is trained on; evaluation scores each once."""
    shards_of: dict = {}
    for (s, _), key in zip(dataset._inst_loc, dataset.episode_keys()):
        shards_of.setdefault(key, []).append(s)
    if several := [key for key, shards in shards_of.items() if len(set(shards)) > 1]:
        log.warning("%d episode(s) under %s are in more than one bag (e.g. %s, in %s): each copy counts in training "
                    "(validation and evaluation score it once); keep one bag of each",
                    len(several), bags, several[0][0],
                    " and ".join(str(sources[s]) for s in sorted(set(shards_of[several[0]]))))
    if repeated := [key for key, shards in shards_of.items() if len(set(shards)) < len(shards)]:
        shards = shards_of[repeated[0]]
        bag = next(s for s in shards if shards.count(s) > 1)
        log.warning("%d episode(s) under %s repeat within a bag (e.g. %s, %d times in %s): a looping simulator "
                    "(loop: true) was recorded, and each repeat counts in training (validation and evaluation score it "
                    "once); record one pass", len(repeated), bags, repeated[0][0],
                    shards.count(bag), sources[bag])


def split_instances(n: int, val_fraction: float, seed: int, keys=None) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic train/val split of instance indices (all views of an instance stay together).
    With `keys` (one per instance, e.g. Dataset.episode_keys()) instances with the same key go to the
    same side, so an episode recorded in two bags is never trained on and validated on; with distinct
    keys the split is the one without them."""
    if keys is None:
        groups = np.arange(n)
    else:  # group numbers in order of first appearance: distinct keys number the instances themselves
        first: dict = {}
        groups = np.array([first.setdefault(key, len(first)) for key in keys], dtype=np.int64)
        if len(groups) != n:
            raise ValueError(f"{len(groups)} keys for {n} instances")
    m = int(groups.max()) + 1 if n else 0
    order = np.random.default_rng(seed).permutation(m)
    n_val = int(round(m * val_fraction)) if m > 1 else 0
    n_val = min(max(n_val, 1 if val_fraction > 0 and m > 1 else 0), m - 1) if m > 1 else 0
    val = np.isin(groups, order[:n_val])
    return np.flatnonzero(~val), np.flatnonzero(val)


def resize_masks(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(..., H, W) uint8 masks (0/255, or coverage levels) -> (..., h, w) float32 in [0, 1], area-averaged
    (what the estimator does to camera frames before the model)."""
    import cv2

    h, w = size
    flat = frames.reshape(-1, *frames.shape[-2:])
    if flat.shape[-2:] == (h, w):
        out = flat.astype(np.float32)
    else:
        out = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in flat]).astype(np.float32)
    return (out / 255.0).reshape(*frames.shape[:-2], h, w)


def resized_videos(dataset: Dataset, size: tuple[int, int], progress: bool = True) -> list[np.ndarray]:
    """Per shard, every video at `size`: the cached uint8 videos themselves at their own size
    (no copy), else area-resized float16 in [0, 1], cached beside the shard. `as_unit_float` reads
    either kind."""
    if dataset._videos[0].shape[-2:] == tuple(size):
        return list(dataset._videos)
    out = []
    for shard in tqdm(dataset.shards, desc=f"resize videos {size[0]}x{size[1]}", unit="bag", leave=False,
                      disable=None if progress else True):
        path = shard / f"videos_{size[0]}x{size[1]}.npy"
        if not path.exists():
            videos = np.load(shard / "videos.npy", mmap_mode="r")
            tmp = path.with_name(path.name + f".tmp{os.getpid()}.npy")
            # In slices: a paper-size shard resized at once would take tens of GB of float32.
            resized = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(*videos.shape[:-2], *size))
            step = max(1, RESIZE_SLICE_FRAMES // math.prod(videos.shape[1:-2]))
            for start in range(0, len(videos), step):
                resized[start : start + step] = resize_masks(np.asarray(videos[start : start + step]), size)
            resized.flush()
            del resized
            os.replace(tmp, path)
        out.append(_shard_array(shard, path.name, mmap=True))
    return out


def as_unit_float(frames: np.ndarray) -> np.ndarray:
    """Masks from `resized_videos` (uint8 0/255 or float16 in [0, 1]) -> float32 in [0, 1]."""
    if frames.dtype == np.uint8:
        return frames.astype(np.float32) * np.float32(1.0 / 255.0)
    return np.asarray(frames, dtype=np.float32)
