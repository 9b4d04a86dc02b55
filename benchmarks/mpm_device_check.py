#!/usr/bin/env python3
"""Runs a fixed set of MPM scenes on one device and saves the trajectories; compares two such files.

Checks that CUDA and CPU runs of the same scenes agree (CUDA float atomics add in a different
order, so agreement is to a tolerance, not bitwise):
  python benchmarks/mpm_device_check.py --device cpu --output cpu.npz
  python benchmarks/mpm_device_check.py --device cuda --output cuda.npz     (on the GPU machine)
  python benchmarks/mpm_device_check.py --compare cpu.npz cuda.npz
"""

from __future__ import annotations

import argparse
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "ros_ws" / "src" / "ad_sim"), str(ROOT / "ros_ws" / "src" / "ad_estimator"), str(ROOT / "benchmarks")]

from ad_estimator.cli import positive  # noqa: E402
from common import check_warp_device, output_file  # noqa: E402
from sim_throughput import SHAPE_SIZE, make_scene  # noqa: E402

from ad_sim import mpm  # noqa: E402


def npz_out(text: str) -> Path:
    """argparse type of --output: a file whose folder exists, checked before the simulation; .npz is appended
    to a name without it (as numpy.savez_compressed would do anyway), so that the name printed is the file's."""
    path = output_file(text, "cpu.npz")
    return path if path.suffix == ".npz" else output_file(f"{path}.npz", "cpu.npz")


def load_run(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a file written by --output, or ValueError naming what is wrong with it (one line)."""
    not_ours = f"{path} is not a file written by mpm_device_check.py --output"
    try:
        data = np.load(path)  # allow_pickle=False: a file that is not numpy data is refused, not unpickled
    except OSError as exc:  # missing, a folder, unreadable
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    except EOFError:
        raise ValueError(f"{not_ours} (it is empty)") from None
    except (ValueError, zipfile.BadZipFile):  # numpy's message would speak of pickled data: a file it cannot tell
        raise ValueError(f"{not_ours} (not an .npz file)") from None
    if not isinstance(data, np.lib.npyio.NpzFile):  # a single array (.npy)
        raise ValueError(f"{not_ours} (a single .npy array, not an .npz file)")
    try:
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error) as exc:  # a damaged member
        raise ValueError(f"{not_ours} (damaged: {exc})") from None
    if "families" not in arrays:
        raise ValueError(f"{not_ours} (it has no 'families' array)")
    expected = {"families"} | {f"{kind}{i}" for i in range(len(arrays["families"])) for kind in "xF"}
    if set(arrays) != expected:
        raise ValueError(f"{not_ours} (its arrays are not x0.., F0.. and families, one x and F per scene)")
    return arrays


def run(device: str, output: Path, count: int, frames: int) -> None:
    rng = np.random.default_rng(123)
    scenes = [make_scene(rng, SHAPE_SIZE["small"]) for _ in range(count)]
    results = mpm.simulate(scenes, device=device, frame_count=frames)
    np.savez_compressed(
        output,
        **{f"x{i}": r.positions for i, r in enumerate(results)},
        **{f"F{i}": r.deformation for i, r in enumerate(results)},
        families=np.array([s.family for s in scenes]),
    )
    print(f"wrote {output}: {count} scenes, {frames} frames on {device}")


def compare(a: Path, b: Path) -> None:
    A, B = load_run(a), load_run(b)
    shapes = {name: {key: arrays[key].shape for key in arrays if key != "families"} for name, arrays in ((a, A), (b, B))}
    if shapes[a] != shapes[b] or list(A["families"]) != list(B["families"]):
        raise ValueError(f"{a} and {b} hold different runs (scenes, families or frames differ); compare files "
                         "written with the same --scenes and --frames")
    for i, family in enumerate(A["families"]):
        dx = np.abs(A[f"x{i}"] - B[f"x{i}"]).max()
        dF = np.abs(A[f"F{i}"] - B[f"F{i}"]).max()
        print(f"scene {i:2d} {family:>10}: max |dx| {dx:.2e} m, max |dF| {dF:.2e}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="Warp device to run on (default cpu)")
    parser.add_argument("--output", type=npz_out, help="npz file to write (.npz is appended to a name without it)")
    parser.add_argument("--scenes", type=positive, default=6, help="number of scenes (default 6)")
    parser.add_argument("--frames", type=positive, default=25, help="frames (default 25)")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="compare two npz files")
    args = parser.parse_args(argv)
    if args.compare:
        try:
            compare(*args.compare)
        except (OSError, ValueError) as exc:
            parser.error(str(exc))
    elif args.output:
        check_warp_device(parser, args.device)
        run(args.device, args.output, args.scenes, args.frames)
    else:
        parser.error("give --output to run, or --compare A B")
    return 0


if __name__ == "__main__":
    sys.exit(main())
