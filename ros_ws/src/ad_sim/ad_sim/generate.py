"""Bulk generation of a benchmark split (or an instance file) straight to rosbag2 MCAP bags.

Same content as recording the simulator node's topics (ad_sim.messages is shared), without
DDS. Output is sharded: shard i of N holds instances i, i+N, i+2N, ... of the list in
OUT/<name>-<i>of<N>/ (name: the split, the instance file's stem or --name), a bag folder. A finished shard has a DONE marker and is skipped when the
command is run again with the same settings (refused with other ones) and its files are intact; a shard without it (a killed
run), with a damaged marker or with files missing or cut short is deleted and redone, if it holds only what generate writes.
Deterministic: the same arguments give byte-identical bags.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import shutil
import sys
from pathlib import Path

# ad_sim.messages (and through it Warp and SciPy, a second of imports) is imported where it is used, so
# that a Ctrl-C right after start lands in main's handler (one line, exit 130) instead of a traceback.
from .rosbag import METADATA_FILE, MIN_SPLIT_SIZE, BagError, BagWriter, qos_profile

DONE_MARKER = "DONE"
DONE_PARTIAL = "DONE.tmp"  # the marker while it is written (renamed to DONE_MARKER)
DEFAULT_BATCH = {"cpu": 8, "cuda": 256}


def parse_shard(text: str) -> tuple[int, int]:
    """'i/N' -> (i, N) with 0 <= i < N."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shard expects i/N (e.g. 0/4), got {text!r}") from None
    if count < 1 or not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"--shard {text}: need N >= 1 and 0 <= i < N")
    return index, count


def plain_name(text: str) -> bool:
    """Whether `text` names an entry of a folder (no path separator, not . or ..)."""
    return text not in ("", ".", "..") and Path(text).name == text


def shard_dir(out: Path, name: str, index: int, count: int) -> Path:
    return out / f"{name}-{index}of{count}"


def is_done(folder: Path) -> bool:
    return (folder / DONE_MARKER).is_file()


class ShardMismatch(ValueError):
    """A finished shard was written with other settings than those asked for now."""


class ForeignFiles(ValueError):
    """A shard path to be (re)written holds something generate did not write there, so it is not deleted."""


def _own_file(folder: Path, path: Path) -> bool:
    """Whether `path` in shard `folder` is one generate writes: BagWriter's metadata.yaml (and the .tmp it
    renames), its <folder>_<i>.mcap files, and the DONE marker (and its .tmp)."""
    own = path.name in (METADATA_FILE, f"{METADATA_FILE}.tmp", DONE_MARKER, DONE_PARTIAL) \
        or re.fullmatch(re.escape(folder.name) + r"_\d+\.mcap", path.name) is not None
    return own and (path.is_symlink() or not path.is_dir())


def check_replaceable(folder: Path) -> None:
    """Raises ForeignFiles unless `folder` is absent or looks like a shard generate wrote (then deleting it
    loses nothing: the same command writes it again, byte for byte)."""
    if not folder.exists() and not folder.is_symlink():
        return
    if folder.is_symlink() or not folder.is_dir():
        raise ForeignFiles(f"cannot write {folder}: it is a file or a link, not a shard folder; move it or choose "
                           "another --out")
    unexpected = sorted(p.name for p in folder.iterdir() if not _own_file(folder, p))
    if unexpected:
        listed = ", ".join(unexpected[:5]) + (f" and {len(unexpected) - 5} more" if len(unexpected) > 5 else "")
        raise ForeignFiles(f"{folder} would be redone, but it holds files generate does not write ({listed}); "
                           "move them or choose another --out")


def shard_settings(instances: list, views: int | None, skip: frozenset[str], compression: str, max_bag_size: int,
                   coverage_masks: bool = False) -> dict:
    """What decides a shard's content, as recorded in its DONE marker."""
    episodes = [[i.episode_id, i.split, i.shape, i.material, i.parameters, i.seed] for i in instances]
    settings = {
        "episodes": hashlib.sha256(json.dumps(episodes, sort_keys=True).encode()).hexdigest(),
        "views": sorted({views or i.views for i in instances}),  # as simulated: --views 1 on unseen is the default
        "skip": sorted(skip), "compression": compression, "max_bag_size": max_bag_size,
    }
    # Only when set, so that markers written before the option still match the default.
    return settings | ({"masks": "coverage"} if coverage_masks else {})


def _read_marker(folder: Path) -> dict | None:
    """The DONE marker of `folder`, or None (after a one-line warning) if it is not one generate writes (empty,
    cut short, edited): like a shard without a marker, it is then redone."""
    marker = folder / DONE_MARKER
    try:
        done = json.loads(marker.read_text())
    except ValueError:  # not JSON, or not UTF-8
        done = None
    files, sizes = (done.get("sha256"), done.get("sizes")) if isinstance(done, dict) else (None, None)
    if not (isinstance(done, dict) and isinstance(done.get("settings") or {}, dict) and isinstance(files, dict) and files
            and all(plain_name(name) and isinstance(digest, str) for name, digest in files.items())
            and (sizes is None or (isinstance(sizes, dict) and sizes
                                   and all(plain_name(name) and type(n) is int for name, n in sizes.items())))):
        print(f"warning: {marker} is not a marker generate writes (damaged or edited), so {folder} is taken as "
              "unfinished and redone", file=sys.stderr)
        return None
    return done


def _file_sizes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(folder.glob("*.mcap"))} | {
        METADATA_FILE: (folder / METADATA_FILE).stat().st_size}


def _damage(folder: Path, done: dict) -> str:
    """What is wrong with the files of finished shard `folder` ("" if nothing), against its marker `done`.

    By their sizes, not their sha256: re-reading a shard (gigabytes) on every re-run would take minutes, and what
    breaks finished files in practice (a deleted file, a copy or a full disk that stopped part way) changes their
    size; the marker keeps the sha256s for a full check (sha256sum). A marker from before sizes were recorded is
    checked once by its sha256s, and then given the sizes."""
    sizes = done.get("sizes")
    for name in sizes or [*done["sha256"], METADATA_FILE]:
        if not (folder / name).is_file():
            return f"{name} is missing"
    if sizes is not None:
        for name, size in sizes.items():
            if (actual := (folder / name).stat().st_size) != size:
                return f"{name} has {actual} bytes, not the {size} it was written with"
        return ""
    for name, digest in done["sha256"].items():
        if _file_digest(folder / name) != digest:
            return f"{name} is not the file it was written as (sha256)"
    try:
        _write_marker(folder, done | {"sizes": _file_sizes(folder)})
    except OSError:  # a read-only copy: checked by sha256 again next time
        pass
    return ""


def _write_marker(folder: Path, done: dict) -> None:
    partial = folder / DONE_PARTIAL
    partial.write_text(json.dumps(done, indent=2) + "\n")
    partial.replace(folder / DONE_MARKER)  # atomic: a kill never leaves a half-written marker


def _check_settings(folder: Path, recorded: dict | None, settings: dict) -> None:
    if recorded is None:  # written before markers recorded their settings: they cannot be compared
        print(f"warning: {folder} records no settings (an older version wrote it), so it is taken as done whatever "
              "was asked for now; delete it to write it with these settings", file=sys.stderr)
        return
    differing = sorted(key for key in settings.keys() | recorded.keys() if recorded.get(key) != settings.get(key))
    if differing:
        names = ", ".join("instances (split, seed, --limit or file)" if key == "episodes" else key for key in differing)
        raise ShardMismatch(
            f"{folder} was written with other settings ({names}); delete it or choose another --out to write it anew")


def _file_digest(path: Path) -> str:
    with open(path, "rb") as f:  # streamed: a shard's file can be larger than memory
        return hashlib.file_digest(f, "sha256").hexdigest()


def _file_digests(folder: Path) -> dict[str, str]:
    return {p.name: _file_digest(p) for p in sorted(folder.glob("*.mcap"))}


def write_episodes(
    writer: BagWriter, episodes, first_index: int, prefix: str | None = None, skip: frozenset[str] = frozenset()
) -> None:
    """Write episodes to an open bag, numbering them from first_index; topics in `skip` are left out;
    `prefix`: the topics' (default messages.DEFAULT_PREFIX)."""
    from . import messages

    prefix = messages.DEFAULT_PREFIX if prefix is None else prefix
    for offset, episode in enumerate(episodes):
        types = messages.topic_types(len(episode.cameras), prefix)
        for topic, stamp, message in messages.episode_messages(episode, first_index + offset, prefix=prefix):
            if topic in skip:
                continue
            if not writer.has_topic(topic):
                writer.add_topic(topic, types[topic], [qos_profile(**messages.topic_qos(topic, prefix))])
            writer.write(topic, stamp, message)


def shard_to_write(folder: Path, settings: dict) -> bool:
    """Whether shard `folder` is to be (re)written for `settings` (shard_settings); False if it is finished
    with them. Raises ShardMismatch if it was finished with others, ForeignFiles if it is to be (re)written
    but holds files generate does not write. Warns about a damaged shard or marker, which is redone."""
    if is_done(folder) and (done := _read_marker(folder)) is not None:
        if done.get("settings") is not None:  # other settings: refused even if damaged (redoing would change them)
            _check_settings(folder, done["settings"], settings)
        if damage := _damage(folder, done):
            check_replaceable(folder)  # before saying it is redone
            print(f"warning: {folder} is damaged ({damage}), so it is redone", file=sys.stderr)
            return True
        if done.get("settings") is None:
            _check_settings(folder, None, settings)
        return False
    check_replaceable(folder)
    return True


def write_shard(
    instances: list,
    folder: Path,
    *,
    device: str = "cpu",
    views: int | None = None,
    batch: int | None = None,
    max_bag_size: int = 0,
    compression: str = "zstd",
    custom_data: dict[str, str] | None = None,
    skip: frozenset[str] = frozenset(),
    progress: bool = True,
    coverage_masks: bool = False,
) -> None:
    """Simulate `instances` and write them as one bag folder, replacing what shard_to_write found there,
    with a DONE marker recording its shard_settings. coverage_masks: mask pixels hold their area coverage (0..255)
    instead of 0/255 (episode.simulate_batch)."""
    from tqdm import tqdm

    from .episode import simulate_batch

    check_replaceable(folder)  # deletes only a shard of generate's own (a killed run's, or damaged)
    if folder.exists():
        shutil.rmtree(folder)
    batch = batch or DEFAULT_BATCH["cuda" if device.startswith("cuda") else "cpu"]
    # Closed also on an error or Ctrl-C: what was written stays readable (the shard, without its marker,
    # is still redone by the next run).
    with BagWriter(folder, max_bag_size=max_bag_size, compression=compression, custom_data=custom_data) as writer, \
            tqdm(total=len(instances), desc=folder.name, unit="episode", disable=None if progress else True) as bar:
        for start in range(0, len(instances), batch):
            episodes = simulate_batch(instances[start : start + batch], device=device, views=views,
                                      coverage_masks=coverage_masks)
            write_episodes(writer, episodes, start, skip=skip)
            bar.update(len(episodes))
    done = {"episodes": len(instances), "messages": writer.message_count, "sha256": _file_digests(folder),
            "sizes": _file_sizes(folder),
            "settings": shard_settings(instances, views, skip, compression, max_bag_size, coverage_masks)}
    _write_marker(folder, done)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ros2 run ad_sim generate",
        description=__doc__.split("\n\n")[0],
        epilog="Example: generate --size small --split train --shards 4 --out bags/small --device cuda",
    )
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--instances", type=Path, help="instance file (YAML or JSON, SPEC 4) instead of a benchmark split")
    source.add_argument("--list-shapes", action="store_true", help="print the shape library, one JSON object per line, and exit")
    parser.add_argument("--size", default="tiny", choices=("tiny", "small", "paper"), help="benchmark size (default %(default)s)")
    parser.add_argument("--split", default="unseen", choices=("train", "seen", "unseen"), help="benchmark split (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the benchmark (default %(default)s)")
    shards = parser.add_mutually_exclusive_group()
    shards.add_argument("--shard", type=parse_shard, help="write only shard i of N, as i/N")
    shards.add_argument("--shards", type=int, default=1, help="write all N shards, one after another (default %(default)s)")
    parser.add_argument("--name", help="shard folder prefix (default: the split, or the instance file's name)")
    parser.add_argument("--out", type=Path, default=Path("bags"), help="output folder for the shard bag folders (default %(default)s)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu, cuda or cuda:<n> (default %(default)s)")
    parser.add_argument("--views", type=int, help="cameras per episode (default: 4 for train, 1 otherwise)")
    parser.add_argument("--batch", type=int, help="episodes per simulator batch (default: " + ", ".join(f"{n} on {d}" for d, n in DEFAULT_BATCH.items()) + ")")
    parser.add_argument("--limit", type=int, help="use only the first n instances (quick looks)")
    parser.add_argument("--write-instances", type=Path, metavar="FILE",
                        help="write the instances it would generate (after --limit) as an instance file, YAML or JSON "
                             "by FILE's suffix, and exit: a template for scenes of one's own (docs/simulator.md)")
    parser.add_argument("--max-bag-size", type=int, default=0, help=f"split .mcap files at this many bytes (0: never; else >= {MIN_SPLIT_SIZE})")
    parser.add_argument("--compression", default="zstd", choices=("zstd", "lz4", "none"), help="chunk compression (default %(default)s)")
    parser.add_argument(
        "--skip-particles", action="store_true", help="leave out /ad_sim/particles (60 KB a frame, hardly compressible): masks-only bags"
    )
    parser.add_argument(
        "--coverage-masks", action="store_true",
        help="mask pixels hold their area coverage of the 512x512 render (0..255, grey edges) instead of 0/255: for "
             "training students on grey masks (python -m training student --set mask_levels=coverage); a pixel > 127 is "
             "still exactly the object, so the estimator and everything that thresholds reads the same masks")
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bars, no Warp start-up banner or kernel-load lines (Warp's warnings stay)")
    return parser


def _write_instances(instances, path: Path, views: int | None) -> int:
    from dataclasses import replace

    from .instances import write_instance_file

    if path.exists():  # someone's edited scenes, maybe
        print(f"error: --write-instances {path} exists; delete it or pass another file name", file=sys.stderr)
        return 1
    try:
        write_instance_file([replace(i, views=views) if views else i for i in instances], path)
    except (OSError, ValueError) as exc:
        print(f"error: --write-instances {path}: {exc}", file=sys.stderr)
        return 1
    print(f"{path}: {len(instances)} instance(s) written", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    writing: list[Path] = []  # the shard under way, for the message on Ctrl-C
    try:
        return _generate(argv, writing)
    except KeyboardInterrupt:  # wherever it lands (arguments, instances, Warp start-up, a shard): no traceback
        if writing:  # it has no DONE marker yet, so a re-run redoes it
            print(f"interrupted: {writing[0]} is unfinished; run the same command again to redo it (finished shards "
                  "are kept)", file=sys.stderr)
        else:
            print("interrupted while no shard was being written; run the same command again to go on (finished "
                  "shards are kept)", file=sys.stderr)
        return 130


def _generate(argv: list[str] | None, writing: list[Path]) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    # Checked here, naming the option, before Warp starts: a negative --batch once wrote an empty shard marked
    # done (and 0 meant the default), a negative --seed failed in NumPy without naming it.
    for option, value, least in (("--batch", args.batch, 1), ("--seed", args.seed, 0), ("--max-bag-size", args.max_bag_size, 0)):
        if value is not None and value < least:
            parser.error(f"{option} must be >= {least}, got {value}")
    if 0 < args.max_bag_size < MIN_SPLIT_SIZE:  # the bag writer refused it too, but only after Warp's start-up
        parser.error(f"--max-bag-size must be 0 (no split) or >= {MIN_SPLIT_SIZE} bytes, got {args.max_bag_size}")
    if args.name is not None and not plain_name(args.name):  # it could write (and delete) outside --out
        parser.error(f"--name must be a plain folder name (no / or ..), got {args.name!r}")
    if args.list_shapes:
        from .shapes import shape_records

        for record in shape_records():
            print(json.dumps(record))
        return 0
    if args.quiet:  # Warp's start-up banner and kernel-load lines too (before anything initialises it)
        import warp

        warp.config.log_level = warp.LOG_WARNING
    from .instances import MAX_VIEWS, benchmark, load_instance_file
    from .mpm import check_device

    try:
        if args.instances:
            instances, name = load_instance_file(args.instances), args.instances.stem
        else:
            instances, name = benchmark(args.size, args.split, args.seed), args.split
        if not args.write_instances:  # (writing them needs no Warp)
            check_device(args.device)
    except (OSError, ValueError) as exc:
        parser.error(str(exc))
    name = args.name or name
    if args.limit is not None:
        if args.limit < 1:
            parser.error(f"--limit must be >= 1 (the number of instances to keep), got {args.limit}")
        instances = instances[: args.limit]
    if args.views is not None and not 1 <= args.views <= MAX_VIEWS:
        parser.error(f"--views must be in 1..{MAX_VIEWS}, got {args.views}")
    if args.write_instances:
        return _write_instances(instances, args.write_instances, args.views)
    if args.shards < 1:
        parser.error("--shards must be >= 1")
    index_range, count = ((args.shard[0],), args.shard[1]) if args.shard else (range(args.shards), args.shards)
    if index_range[-1] >= len(instances):  # refused: an empty bag marked done is of no use, and likely a mistake
        asked = f"--shard {args.shard[0]}/{count}" if args.shard else f"--shards {count}"
        parser.error(f"{asked}: {len(instances)} instance(s) leave shard {index_range[-1]} of {count} empty; "
                     f"use at most {len(instances)} shards")
    source = {"instances": str(args.instances)} if args.instances else {"size": args.size, "split": args.split, "seed": str(args.seed)}
    from . import messages

    # What would stop a shard being written is found before any simulation: --out not a folder or not
    # writable, a finished shard written with other settings, a shard to (re)write that is a file or holds
    # files generate did not write.
    if args.out.exists() and not args.out.is_dir():
        print(f"error: cannot write in --out {args.out}: it is a file, not a folder", file=sys.stderr)
        return 1
    skip = frozenset([messages.particles_topic()]) if args.skip_particles else frozenset()
    settings = {index: shard_settings(instances[index::count], args.views, skip, args.compression, args.max_bag_size,
                                      args.coverage_masks) for index in index_range}
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        to_write = [index for index in index_range
                    if shard_to_write(shard_dir(args.out, name, index, count), settings[index])]
    except (ShardMismatch, ForeignFiles) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: cannot write in --out {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    for index in index_range:
        folder = shard_dir(args.out, name, index, count)
        if index not in to_write:
            print(f"{folder}: already done, skipped", file=sys.stderr)
            continue
        custom = {"generator": "ad_sim.generate", "shard": f"{index}/{count}", **source,
                  **({"masks": "coverage"} if args.coverage_masks else {})}
        writing.append(folder)
        try:
            write_shard(
                instances[index::count],
                folder,
                device=args.device,
                views=args.views,
                batch=args.batch,
                max_bag_size=args.max_bag_size,
                compression=args.compression,
                custom_data=custom,
                skip=skip,
                progress=not args.quiet,
                coverage_masks=args.coverage_masks,
            )
        except BagError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        except OSError as exc:  # a full disk, a folder made read-only: one line (the shard has no marker: a re-run redoes it)
            print(f"error: cannot write {folder}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        writing.clear()
        print(f"{folder}: written", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
