"""The 60-shape library: 25 synthetic shapes and 35 everyday objects (SPEC section 7).

Meshes live in data/shapes/ (gzipped binary PLY, closed, normalised into [-0.5, 0.5]^3 with
longest side 1), with the catalogue (catalog.json), the versioned train/unseen split
(split_v1.json) and ATTRIBUTION.md. scripts/build_shapes.py rebuilds them from the
packages they come from, and `verify`s them.
"""
from __future__ import annotations

import gzip
import io
import json
import os
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np


@contextmanager
def ctrl_c_held():
    """For imports that mishandle a Ctrl-C during their first import (about a second): trimesh catches
    BaseException around its optional imports and so swallows it, and libigl's native start-up turns it
    into "ImportError: std::bad_cast". In the main thread, a SIGINT that arrives meanwhile is held and
    handed, once the block is done, to the handler that was there (Python's raises KeyboardInterrupt; a
    node's may set its stop flag); elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    previous = signal.signal(signal.SIGINT, lambda *_: held.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if held and callable(previous):
        previous(signal.SIGINT, None)
    elif held and previous == signal.SIG_DFL:
        os.kill(os.getpid(), signal.SIGINT)  # ends the process, as it would have


# At import, not inside the sampler: a first import of igl within a Ctrl-C aborts the process.
with ctrl_c_held():
    import igl
    import trimesh

DATA_DIR = Path(__file__).resolve().parent / "data" / "shapes"
SPLIT_FILE = DATA_DIR / "split_v1.json"
CATALOG_FILE = DATA_DIR / "catalog.json"
SPLITS = ("train", "unseen")
KINDS = ("synthetic", "everyday")
# Lattice jitter, as a fraction of the spacing, when sample_volume gets an rng.
DEFAULT_JITTER = 0.25
# sample_volume(min_count=...) shrinks the spacing by at least this factor per refinement.
MIN_REFINEMENT = 1.1


@dataclass(frozen=True)
class ShapeInfo:
    name: str
    kind: str  # "synthetic" | "everyday"
    split: str  # "train" | "unseen"
    source: str  # how it was made, or package==version: path of the original mesh


@lru_cache(maxsize=1)
def _library() -> dict[str, tuple[ShapeInfo, Path]]:
    split = json.loads(SPLIT_FILE.read_text())
    split_of = {name: part for part in SPLITS for kind in KINDS for name in split[part][kind]}
    library = {}
    for record in json.loads(CATALOG_FILE.read_text())["shapes"]:
        name = record["name"]
        info = ShapeInfo(name, record["kind"], split_of[name], record["source"])
        library[name] = (info, DATA_DIR / record["file"])
    return dict(sorted(library.items()))


def _entry(name: str) -> tuple[ShapeInfo, Path]:
    library = _library()
    if name not in library:
        raise ValueError(f"unknown shape {name!r}; known shapes: {', '.join(library)}")
    return library[name]


def list_shapes(split: str | None = None) -> list[ShapeInfo]:
    """All shapes sorted by name, or those of one split ("train" | "unseen")."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"unknown shape split {split!r}; use one of {SPLITS} or None for all")
    return [info for info, _ in _library().values() if split is None or info.split == split]


def shape_records() -> list[dict]:
    """What `generate --list-shapes` prints: one JSON-able dict per shape."""
    return [{"name": s.name, "kind": s.kind, "split": s.split, "source": s.source} for s in list_shapes()]


@lru_cache(maxsize=None)
def _mesh(name: str) -> trimesh.Trimesh:
    _, path = _entry(name)
    data = gzip.decompress(path.read_bytes())
    return trimesh.load(io.BytesIO(data), file_type="ply", force="mesh", process=False)


def load_mesh(name: str) -> trimesh.Trimesh:
    """The closed mesh of `name`, centred in [-0.5, 0.5]^3 with longest side 1 (a fresh copy)."""
    return _mesh(name).copy()


@lru_cache(maxsize=256)  # ~10k points (120 kB) each at the simulator's spacing
def _lattice_inside(name: str, spacing: float, scale: float) -> np.ndarray:
    """Cell-centred lattice points at `spacing` inside the mesh scaled by `scale` (read-only)."""
    mesh = _mesh(name)
    vertices = np.asarray(mesh.vertices, np.float64) * scale
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    # points (k + 1/2) * spacing within the bounds: never on a face at the box's +-scale/2
    axes = [(np.arange(np.ceil(lo[i] / spacing - 0.5), np.floor(hi[i] / spacing - 0.5) + 1) + 0.5) * spacing
            for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    winding = igl.fast_winding_number(vertices, np.asarray(mesh.faces, np.int64), grid)
    points = grid[winding > 0.5].astype(np.float32)
    points.flags.writeable = False
    return points


def sample_volume(
    name: str,
    spacing: float,
    scale: float = 1.0,
    rng: np.random.Generator | int | None = None,
    jitter: float = DEFAULT_JITTER,
    min_count: int = 0,
) -> np.ndarray:
    """Volumetric particles (N, 3) float32 filling the mesh of `name` scaled by `scale`, centred at 0.

    A regular cell-centred lattice at `spacing`, kept where the mesh's winding number is
    above 1/2. With an `rng` (Generator or seed) each point moves by a uniform offset of up
    to `jitter * spacing` per axis. If fewer than `min_count` points fit, the spacing shrinks
    until they do; the spacing used is then `effective_spacing(name, spacing, scale, min_count)`.
    """
    spacing = effective_spacing(name, spacing, scale, min_count)
    points = _lattice_inside(name, float(spacing), float(scale)).copy()
    if rng is not None and jitter > 0:
        rng = np.random.default_rng(rng)
        points += (rng.uniform(-jitter, jitter, size=points.shape) * spacing).astype(np.float32)
    return points


def effective_spacing(name: str, spacing: float, scale: float = 1.0, min_count: int = 0) -> float:
    """The lattice spacing sample_volume uses: `spacing`, refined until `min_count` points fit."""
    if spacing <= 0 or scale <= 0:
        raise ValueError(f"spacing and scale must be positive (got spacing={spacing}, scale={scale})")
    spacing = float(spacing)
    while (count := len(_lattice_inside(name, spacing, float(scale)))) < min_count:
        # the count grows like spacing^-3: aim just past min_count, and always shrink a little
        ratio = (max(count, 1) / min_count) ** (1.0 / 3.0)
        spacing *= min(ratio * 0.98, 1.0 / MIN_REFINEMENT)
        if spacing < 1e-4 * scale:
            raise ValueError(f"shape {name!r} cannot hold {min_count} particles at scale {scale}")
    return spacing
