#!/usr/bin/env python3
"""Rebuild (or verify) the 60-shape library of ad_sim.

`build` downloads the source packages (PyPI wheels with `pip download --no-deps`, Debian
packages with `apt-get download`), extracts only the mesh files it needs, closes each
mesh, simplifies it, normalises it into [-0.5, 0.5]^3 and writes everything under
ros_ws/src/ad_sim/ad_sim/data/shapes/ together with the catalogue, the versioned split
and ATTRIBUTION.md. The 25 synthetic shapes are generated here, in code.

`verify` is cheap (no downloads, no mesh processing): it checks that the committed mesh
files, the catalogue, the split file and ATTRIBUTION.md agree with each other and with
the tables in this script.

Everything is deterministic: same packages in, byte-identical files out.
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import io
import json
import subprocess
import sys
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import fast_simplification
import igl
import manifold3d
import numpy as np
import trimesh
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
SHAPES_DIR = REPO / "ros_ws/src/ad_sim/ad_sim/data/shapes"
CATALOG_FILE = "catalog.json"
SPLIT_FILE = "split_v1.json"
ATTRIBUTION_FILE = "ATTRIBUTION.md"

MAX_FACES = 2000
FILL_RESOLUTION = 96  # winding-number grid cells along the longest side


# ----------------------------------------------------------------------------- sources
@dataclass(frozen=True)
class Package:
    """A PyPI wheel or Debian package that ships meshes."""

    kind: str  # "pypi" | "deb"
    name: str
    version: str
    licence: str

    @property
    def label(self) -> str:
        return f"{self.name}=={self.version}" if self.kind == "pypi" else f"{self.name}={self.version} (Debian)"


PACKAGES = {
    "robosuite": Package("pypi", "robosuite", "1.5.2", "MIT"),
    "metaworld": Package("pypi", "metaworld", "3.1.1", "MIT"),
    "gymnasium-robotics": Package("pypi", "gymnasium-robotics", "1.4.2", "Apache-2.0 (kitchen models)"),
    "pybullet": Package("pypi", "pybullet", "3.2.7", "zlib"),
    "genesis-world": Package("pypi", "genesis-world", "1.4.5", "Apache-2.0"),
    "libcgal-demo": Package("deb", "libcgal-demo", "5.5.1-2", "CC0 (CGAL data meshes)"),
    "assimp-testmodels": Package("deb", "assimp-testmodels", "5.2.5~ds0-1", "BSD-3-Clause"),
}

CGAL_TAR = "usr/share/doc/libcgal-dev/data.tar.gz"  # libcgal-demo ships it (libcgal-demo doc dir is a link)


@dataclass(frozen=True)
class Everyday:
    """One everyday object: where its parts live and how they are made closed.

    method: "as-is" (closed as shipped), "union" (closed parts merged with manifold3d),
    "stitch" (open boundary loops capped), "fill" (generalized winding number on a grid,
    threshold 0.5, marching cubes: solidifies loose or open triangles).
    up: the source's up axis; rotated onto +z so that objects stand upright.
    licence: where the mesh has a licence of its own, other than its package's.
    """

    name: str
    package: str
    paths: tuple[str, ...]  # inside the package; "a.tar.gz!member" reads a member of an inner tarball
    method: str
    up: str = "z"
    licence: str = ""

    @property
    def mesh_licence(self) -> str:
        return self.licence or PACKAGES[self.package].licence


def _cgal(name: str, method: str = "as-is", up: str = "y", file: str = "") -> Everyday:
    return Everyday(name, "libcgal-demo", (f"{CGAL_TAR}!data/meshes/{file or name}.off",), method, up)


RS = "robosuite/models/assets/objects/meshes/"
MW = "metaworld/assets/objects/meshes/"
KITCHEN = "gymnasium_robotics/envs/assets/kitchen_franka/kitchen_assets/meshes/"

EVERYDAY = [
    Everyday("bread", "robosuite", (RS + "bread.stl",), "as-is"),
    Everyday("milk_carton", "robosuite", (RS + "milk.stl",), "as-is"),
    Everyday("bottle", "robosuite", (RS + "bottle.stl",), "fill"),
    Everyday("mug", "metaworld", (MW + "coffeemachine/mug.stl",), "as-is"),
    Everyday("kettle", "gymnasium-robotics", (KITCHEN + "kettle.stl", KITCHEN + "kettlehandle.stl"), "fill"),
    Everyday("microwave", "gymnasium-robotics", (KITCHEN + "micro.stl",), "union"),
    Everyday("stove_knob", "gymnasium-robotics", (KITCHEN + "knob.stl",), "stitch"),
    Everyday("hammer", "metaworld", (MW + "hammer/hammerhead.stl", MW + "hammer/hammerhandle.stl"), "union"),
    Everyday("bolt", "genesis-world", ("genesis/assets/meshes/bolt_nut/bolt.stl",), "as-is"),
    Everyday("hex_nut", "genesis-world", ("genesis/assets/meshes/bolt_nut/nut.stl",), "as-is"),
    Everyday("faucet_base", "metaworld", (MW + "faucet/faucetbase.stl",), "as-is"),
    Everyday("door_handle", "metaworld", (MW + "doorlock/door_handle.stl",), "union"),
    Everyday("camera", "genesis-world", ("genesis/assets/meshes/camera/camera.glb",), "union", "y"),
    Everyday("duck", "pybullet", ("pybullet_data/duck.obj",), "as-is", "y",
             "SCEA Shared Source License 1.0 (COLLADA sample)"),
    Everyday("bunny", "pybullet", ("pybullet_data/bunny.obj",), "as-is", "y",
             "Stanford 3D Scanning Repository (free use, acknowledgement requested)"),
    Everyday("traffic_cone", "pybullet", ("pybullet_data/racecar/meshes/cone.obj",), "as-is", "z"),
    Everyday("lego_brick", "pybullet", ("pybullet_data/lego/lego.obj",), "fill", "y"),
    Everyday("bathtub", "genesis-world", ("genesis/assets/meshes/bathtub/bathtub.obj",), "fill", "y"),
    _cgal("spool"),
    _cgal("pinion"),
    _cgal("cow"),
    _cgal("elephant"),
    _cgal("camel"),
    _cgal("bull"),
    _cgal("bear"),
    _cgal("dino", up="z"),
    _cgal("armadillo"),
    _cgal("pig", "stitch"),
    _cgal("lion_head", "stitch", file="lion-head"),
    _cgal("hand", up="z"),
    _cgal("helmet", up="z"),
    _cgal("mushroom", "stitch", up="z"),
    _cgal("head", "stitch"),
    _cgal("homer"),
    Everyday("wuson", "assimp-testmodels", ("usr/share/assimp/models/OFF/Wuson.off",), "fill", "y"),
]


# ----------------------------------------------------------------------------- fetching
def fetch_package(pkg: Package, cache: Path) -> Path:
    """Download `pkg` into `cache` (once) and return the path of the wheel or unpacked .deb."""
    cache.mkdir(parents=True, exist_ok=True)
    if pkg.kind == "pypi":
        stem = pkg.name.replace("-", "_")
        found = sorted(cache.glob(f"{stem}-{pkg.version}-*.whl"))
        if not found:
            _run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                  f"{pkg.name}=={pkg.version}", "-d", str(cache)], f"pip download {pkg.label}")
            found = sorted(cache.glob(f"{stem}-{pkg.version}-*.whl"))
        if not found:
            raise SystemExit(f"pip download of {pkg.label} produced no wheel in {cache}")
        return found[0]
    unpacked = cache / f"deb-{pkg.name}-{pkg.version}"
    if not unpacked.is_dir():
        debs = sorted(cache.glob(f"{pkg.name}_*.deb"))
        if not debs:
            _run(["apt-get", "download", f"{pkg.name}={pkg.version}"], f"apt-get download {pkg.label}", cwd=cache)
            debs = sorted(cache.glob(f"{pkg.name}_*.deb"))
        if not debs:
            raise SystemExit(f"apt-get download of {pkg.label} produced no .deb in {cache} (run `apt-get update` first)")
        _run(["dpkg", "-x", str(debs[0]), str(unpacked)], f"dpkg -x {debs[0].name}")
    return unpacked


def _run(cmd: list[str], what: str, cwd: Path | None = None) -> None:
    result = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{what} failed (exit {result.returncode}):\n{result.stderr.strip()}\n"
                         "Check network access to PyPI/Debian, or pass --cache with the packages already there.")


def read_member(archive: Path, path: str) -> bytes:
    """Bytes of `path` inside a wheel (zip) or an unpacked .deb folder; `a!b` reads b from tarball a."""
    outer, _, inner = path.partition("!")
    if archive.suffix == ".whl":
        with zipfile.ZipFile(archive) as zf:
            data = zf.read(outer)
    else:
        data = (archive / outer).read_bytes()
    if inner:
        with tarfile.open(fileobj=io.BytesIO(data)) as tf:
            member = tf.extractfile(inner)
            if member is None:
                raise SystemExit(f"{inner} is not a file inside {outer}")
            data = member.read()
    return data


# ----------------------------------------------------------------------------- closing
def load_part(data: bytes, path: str):

    file_type = path.rsplit(".", 1)[-1].lower()
    loaded = trimesh.load(io.BytesIO(data), file_type=file_type, force="mesh", process=True)
    loaded.merge_vertices(merge_tex=True, merge_norm=True)
    return loaded


def to_manifold(mesh):

    m = manifold3d.Manifold(manifold3d.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                                            tri_verts=np.asarray(mesh.faces, np.uint32)))
    if m.status() != manifold3d.Error.NoError:
        raise ValueError(f"not a closed manifold: {m.status()}")
    return m


def from_manifold(m):

    out = m.to_mesh()
    # process=False: manifold3d already shares vertices; merging by position could pinch the surface
    return trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts), process=False)


def close_union(parts):
    """Union of the closed bodies of all parts (manifold3d)."""

    bodies = [to_manifold(b) for p in parts for b in p.split(only_watertight=False)]
    return from_manifold(manifold3d.Manifold.batch_boolean(bodies, manifold3d.OpType.Add))


def close_stitch(mesh):
    """Cap the open boundary loops (an open underside) with fans."""

    caps = trimesh.repair.stitch(mesh)
    closed = trimesh.Trimesh(mesh.vertices, np.vstack([mesh.faces, caps]), process=True)
    closed.merge_vertices()
    trimesh.repair.fix_normals(closed)
    return closed


def close_fill(parts, resolution: int = FILL_RESOLUTION):
    """Solidify a triangle soup: generalized winding number on a grid, iso 0.5, marching cubes."""

    soup = trimesh.util.concatenate(parts)
    lo, hi = soup.bounds
    cell = float((hi - lo).max()) / resolution
    lo, hi = lo - 2 * cell, hi + 2 * cell
    n = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[i] + cell * np.arange(n[i]) for i in range(3)]
    # igl wants x fastest: S(x + y*nx + z*nx*ny)
    gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    grid = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    wn = np.abs(igl.fast_winding_number(np.asarray(soup.vertices, np.float64), np.asarray(soup.faces, np.int64), grid))
    verts, faces, _ = igl.marching_cubes(wn - 0.5, grid, int(n[0]), int(n[1]), int(n[2]), 0.0)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def largest_body(mesh):
    bodies = mesh.split(only_watertight=False)
    return mesh if len(bodies) <= 1 else max(bodies, key=lambda b: abs(b.volume))


def is_closed(mesh) -> bool:
    try:
        to_manifold(mesh)
    except ValueError:
        return False
    return bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0)


def simplify(mesh, max_faces: int = MAX_FACES):
    """Decimate to at most `max_faces` faces, keeping the mesh a closed manifold.

    Quadric decimation (fast-simplification) first, more aggressive if its result is not
    closed; then manifold3d's own simplification, which cannot break manifoldness.
    """

    if len(mesh.faces) <= max_faces:
        return mesh
    for agg in (7.0, 9.0, 11.0):
        v, f = fast_simplification.simplify(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32),
                                            target_count=int(0.95 * max_faces), agg=agg)
        try:
            m = to_manifold(trimesh.Trimesh(v, f, process=False))
        except ValueError:
            continue
        if m.num_tri() <= max_faces:
            return largest_body(from_manifold(m))
    m = to_manifold(mesh)
    tolerance = 1e-3 * float(np.ptp(mesh.bounds, axis=0).max())
    while m.num_tri() > max_faces:
        m = m.simplify(tolerance)
        tolerance *= 1.5
    return largest_body(from_manifold(m))


UP_TO_Z = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # +y -> +z
    "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # +x -> +z
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # -x -> +z
}


def normalise(mesh, up: str = "z"):
    """Rotate `up` onto +z, centre the bounding box at the origin, longest side 1, outward normals."""

    out = mesh.copy()
    transform = np.eye(4)
    transform[:3, :3] = UP_TO_Z[up]
    out.apply_transform(transform)
    lo, hi = out.bounds
    out.apply_translation(-(lo + hi) / 2)
    out.apply_scale(1.0 / float((hi - lo).max()))
    trimesh.repair.fix_normals(out)
    if out.volume < 0:
        out.invert()
    return out


def process_everyday(entry: Everyday, archive: Path):
    parts = [load_part(read_member(archive, p), p) for p in entry.paths]
    if entry.method == "as-is":
        mesh = trimesh.util.concatenate(parts)
    elif entry.method == "union":
        mesh = close_union(parts)
    elif entry.method == "stitch":
        mesh = close_stitch(trimesh.util.concatenate(parts))
    elif entry.method == "fill":
        mesh = close_fill(parts)
    else:
        raise ValueError(f"unknown method {entry.method!r} for {entry.name}")
    mesh = largest_body(mesh)
    if not is_closed(mesh):
        raise SystemExit(f"{entry.name}: method {entry.method!r} did not give a closed mesh")
    return normalise(simplify(mesh), entry.up)


# ----------------------------------------------------------------------------- synthetic
# Every synthetic shape is at least ~0.15 of its longest side thick, so that it survives
# particle sampling at spacing 1/64 after scaling to ~0.35 of the unit cube.
def _extrude(points, height: float):

    return manifold3d.CrossSection([np.asarray(points, float)]).extrude(height).translate((0, 0, -height / 2))


def _star(n: int, outer: float, inner: float):
    angles = np.pi / 2 + np.arange(2 * n) * np.pi / n
    radii = np.where(np.arange(2 * n) % 2 == 0, outer, inner)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def _corners(size, inset: float):
    half = np.asarray(size) / 2 - inset
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half


def synthetic_shapes() -> dict[str, tuple[str, object]]:
    """name -> (description, manifold3d.Manifold) for the 25 synthetic shapes."""

    M, CS = manifold3d.Manifold, manifold3d.CrossSection
    add, sub = manifold3d.OpType.Add, manifold3d.OpType.Subtract
    seg = 48

    def union(*parts):
        return M.batch_boolean(list(parts), add)

    def ball(r, at):
        return M.sphere(r, seg).translate(at)

    shapes = {
        "box": ("cube, side 1", M.cube((1, 1, 1), True)),
        "sphere": ("sphere, diameter 1", M.sphere(0.5, seg)),
        "cylinder": ("cylinder, height 0.8, diameter 0.6", M.cylinder(0.8, 0.3, 0.3, seg, True)),
        "cone": ("cone, height 0.9, base diameter 1", M.cylinder(0.9, 0.5, 0.0, seg, True)),
        "torus": ("torus, major radius 0.35, minor radius 0.15",
                  CS.circle(0.15, 32).translate((0.35, 0)).revolve(seg)),
        "capsule": ("capsule, length 1, diameter 0.5", M.batch_hull([ball(0.25, (0, 0, -0.25)), ball(0.25, (0, 0, 0.25))])),
        "ellipsoid": ("ellipsoid, axes 1 x 0.7 x 0.5", M.sphere(0.5, seg).scale((1, 0.7, 0.5))),
        "tetrahedron": ("regular tetrahedron (alternate cube corners)",
                        M.hull_points(np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float))),
        "octahedron": ("regular octahedron", M.hull_points(np.vstack([np.eye(3), -np.eye(3)]))),
        "open_box": ("open-topped box 1 x 1 x 0.7 with walls and floor 0.15 thick",
                     M.batch_boolean([M.cube((1, 1, .7), True), M.cube((.7, .7, .7), True).translate((0, 0, .2))], sub)),
        "hex_prism": ("hexagonal prism, across corners 1, height 0.45", M.cylinder(0.45, 0.5, 0.5, 6, True)),
        "tri_prism": ("equilateral triangular prism, side 0.6, length 1",
                      _extrude(0.6 / 3 ** 0.5 * np.array([[np.cos(a), np.sin(a)] for a in np.pi / 2 + np.arange(3) * 2 * np.pi / 3]), 1.0)
                      .rotate((0, 90, 0))),
        "pyramid": ("square pyramid, base 1 x 1, height 0.8",
                    M.hull_points(np.array([[-.5, -.5, 0], [.5, -.5, 0], [.5, .5, 0], [-.5, .5, 0], [0, 0, .8]]))),
        "wedge": ("right-angled wedge (ramp) 1 x 0.6 x 0.55",
                  _extrude([[0, 0], [1, 0], [0, 0.55]], 0.6).rotate((90, 0, 0))),
        "l_block": ("L-shaped block, 1 x 0.8, arms 0.35 wide, 0.4 thick",
                    _extrude([[0, 0], [1, 0], [1, .35], [.35, .35], [.35, .8], [0, .8]], 0.4)),
        "t_block": ("T-shaped block, 1 x 0.9, bars 0.3 wide, 0.4 thick",
                    union(_extrude([[-.5, .6], [.5, .6], [.5, .9], [-.5, .9]], 0.4),
                          _extrude([[-.15, 0], [.15, 0], [.15, .61], [-.15, .61]], 0.4))),
        "cross": ("three orthogonal bars 1 x 0.3 x 0.3 (a jack)",
                  union(M.cube((1, .3, .3), True), M.cube((.3, 1, .3), True), M.cube((.3, .3, 1), True))),
        "star_prism": ("five-pointed star, radii 0.5 / 0.28, extruded 0.45", _extrude(_star(5, 0.5, 0.28), 0.45)),
        "ring_slab": ("flat ring (washer), diameters 1 / 0.5, thickness 0.3",
                      M.batch_boolean([M.cylinder(0.3, 0.5, 0.5, seg, True), M.cylinder(0.4, 0.25, 0.25, seg, True)], sub)),
        "bowl": ("hemispherical bowl, outer diameter 1, wall 0.16",
                 M.batch_boolean([M.sphere(0.5, seg), M.sphere(0.34, seg)], sub).trim_by_plane((0, 0, -1), 0.0)),
        "tube": ("hollow cylinder, length 1, diameters 0.6 / 0.34",
                 M.batch_boolean([M.cylinder(1.0, 0.3, 0.3, seg, True), M.cylinder(1.2, 0.17, 0.17, seg, True)], sub)),
        "dumbbell": ("two discs (diameter 0.64, 0.24 thick) on a bar of diameter 0.24, length 1",
                     union(M.cylinder(0.24, 0.32, 0.32, seg, True).rotate((0, 90, 0)).translate((-0.38, 0, 0)),
                           M.cylinder(0.24, 0.32, 0.32, seg, True).rotate((0, 90, 0)).translate((0.38, 0, 0)),
                           M.cylinder(0.6, 0.12, 0.12, seg, True).rotate((0, 90, 0)))),
        "arch": ("block 1 x 0.45 x 0.75 with a semicircular opening of radius 0.3",
                 M.batch_boolean([M.cube((1, .45, .75), True).translate((0, 0, .375)),
                                  M.cylinder(0.6, 0.3, 0.3, seg, True).rotate((90, 0, 0))], sub)),
        "stairs": ("three steps, 1 x 1 profile, 0.6 wide",
                   _extrude([[0, 0], [1, 0], [1, 1], [2 / 3, 1], [2 / 3, 2 / 3], [1 / 3, 2 / 3], [1 / 3, 1 / 3], [0, 1 / 3]], 0.6)
                   .rotate((90, 0, 0))),
        "rounded_box": ("box 1 x 0.7 x 0.45 with edges rounded at radius 0.12",
                        M.batch_hull([ball(0.12, tuple(c)) for c in _corners((1, .7, .45), 0.12)])),
    }
    return shapes


# ----------------------------------------------------------------------------- split
SPLIT_VERSION = 1
# By hand: each split gets the plain primitives' relatives and a mix of household
# objects, tools and figures, so that "unseen" tests new shapes, not new categories.
SPLIT = {
    "train": {
        "synthetic": ["box", "sphere", "cylinder", "cone", "capsule", "ellipsoid", "tetrahedron", "l_block",
                      "star_prism", "bowl"],
        "everyday": ["bread", "bottle", "mug", "microwave", "hammer", "bolt", "door_handle", "traffic_cone", "bathtub",
                     "spool", "helmet", "mushroom", "cow", "elephant", "bear", "armadillo", "bunny", "head", "wuson",
                     "dino"],
    },
    "unseen": {
        "synthetic": ["torus", "octahedron", "open_box", "hex_prism", "tri_prism", "pyramid", "wedge", "t_block",
                      "cross", "ring_slab", "tube", "dumbbell", "arch", "stairs", "rounded_box"],
        "everyday": ["milk_carton", "kettle", "stove_knob", "hex_nut", "faucet_base", "camera", "lego_brick", "pinion",
                     "camel", "bull", "pig", "duck", "lion_head", "homer", "hand"],
    },
}

METHOD_TEXT = {
    "as-is": "closed as shipped",
    "union": "closed parts merged (manifold3d union)",
    "stitch": "open boundary capped (trimesh stitch)",
    "fill": f"solidified: generalized winding number (libigl) on a {FILL_RESOLUTION}-cell grid, iso 0.5, marching cubes",
    "synthetic": "generated in scripts/build_shapes.py (manifold3d)",
}

ACKNOWLEDGEMENTS = """\
- Stanford Bunny (`bunny`): Stanford Computer Graphics Laboratory, The Stanford 3D Scanning
  Repository; the copy used is the decimated one shipped in pybullet's `pybullet_data`.
- COLLADA duck (`duck`): Sony Computer Entertainment Inc., COLLADA sample model (SCEA Shared
  Source License 1.0), as shipped in pybullet's `pybullet_data`.
- CGAL data meshes (cow, elephant, camel, bull, bear, dino, armadillo, pig, lion_head, hand,
  helmet, mushroom, head, homer, spool, pinion): the CGAL project, CC0 1.0 per Debian's
  libcgal-dev copyright file ("all other files that do not have an explicit copyright notice").
- Wuson (`wuson`): the Open Asset Import Library (assimp) test models, BSD-3-Clause.
- robosuite (MIT), Meta-World (MIT), Gymnasium-Robotics kitchen models (Apache-2.0),
  pybullet data (zlib), Genesis (Apache-2.0; the package does not document the origin of
  every asset): as packaged.
"""


def everyday_source(entry: Everyday) -> str:
    return f"{PACKAGES[entry.package].label}: {' + '.join(entry.paths)}"


def mesh_file(name: str) -> str:
    return f"meshes/{name}.ply.gz"


def mesh_bytes(mesh) -> bytes:
    """Binary PLY, gzipped without timestamp or file name so that rebuilds are byte-identical."""
    ply = mesh.export(file_type="ply", encoding="binary")
    buffer = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buffer, mtime=0, compresslevel=9) as gz:
        gz.write(ply)
    return buffer.getvalue()


def split_of(name: str) -> str:
    return next(split for split, kinds in SPLIT.items() for names in kinds.values() if name in names)


def attribution_text(records: list[dict]) -> str:
    rows = ["| name | split | package | path inside the package | licence | processing |",
            "| --- | --- | --- | --- | --- | --- |"]
    for r in records:
        if r["kind"] == "everyday":
            entry = next(e for e in EVERYDAY if e.name == r["name"])
            rows.append(f"| {r['name']} | {r['split']} | {PACKAGES[entry.package].label} | {'<br>'.join(entry.paths)} | "
                        f"{entry.mesh_licence} | "
                        f"{METHOD_TEXT[entry.method]}; up axis {entry.up} |")
    return f"""# Shape library: attribution

60 closed meshes: 25 synthetic shapes generated in code and 35 everyday objects extracted
from permissively licensed meshes that ship inside PyPI wheels or Debian packages.
`scripts/build_shapes.py build` rebuilds every file here from those packages;
`scripts/build_shapes.py verify` checks these files against each other.

Every mesh was closed (method below), reduced to its largest body, simplified to at most
{MAX_FACES} faces (fast-simplification, else manifold3d) while staying a closed manifold, rotated so
that its up axis is +z, centred on its bounding-box centre and scaled so that its longest
side is 1 (it fits [-0.5, 0.5]^3), with outward normals. Files are gzipped binary PLY.

## Everyday objects

{chr(10).join(rows)}

## Acknowledgements

{ACKNOWLEDGEMENTS}
## Synthetic shapes

{chr(10).join(f"- `{r['name']}` ({r['split']}): {r['source']}" for r in records if r['kind'] == 'synthetic')}
"""


# ----------------------------------------------------------------------------- build / verify
def build(cache: Path, shapes_dir: Path = SHAPES_DIR) -> None:
    synthetic = synthetic_shapes()
    jobs = [(name, "synthetic") for name in synthetic] + [(e.name, "everyday") for e in EVERYDAY]
    meshes, records = {}, []
    for name, kind in tqdm(jobs, desc="shapes", unit="shape"):
        if kind == "synthetic":
            description, manifold = synthetic[name]
            mesh = normalise(simplify(largest_body(from_manifold(manifold))))
            source, method, licence = f"synthetic: {description}", "synthetic", "CC0 (this project)"
        else:
            entry = next(e for e in EVERYDAY if e.name == name)
            mesh = process_everyday(entry, fetch_package(PACKAGES[entry.package], cache))
            source, method, licence = everyday_source(entry), entry.method, entry.mesh_licence
        problems = check_mesh(mesh)
        if problems:
            raise SystemExit(f"{name}: {'; '.join(problems)}")
        meshes[name] = mesh_bytes(mesh)
        records.append({"name": name, "kind": kind, "split": split_of(name), "source": source, "method": method,
                        "licence": licence, "file": mesh_file(name), "faces": len(mesh.faces),
                        "sha256": hashlib.sha256(meshes[name]).hexdigest()})
    records.sort(key=lambda r: r["name"])
    mesh_dir = shapes_dir / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for stale in set(mesh_dir.glob("*.ply.gz")) - {shapes_dir / r["file"] for r in records}:
        stale.unlink()
    for name, data in meshes.items():
        (shapes_dir / mesh_file(name)).write_bytes(data)
    (shapes_dir / CATALOG_FILE).write_text(json.dumps({"version": SPLIT_VERSION, "shapes": records}, indent=1) + "\n")
    (shapes_dir / SPLIT_FILE).write_text(json.dumps({"version": SPLIT_VERSION, **SPLIT}, indent=1) + "\n")
    (shapes_dir / ATTRIBUTION_FILE).write_text(attribution_text(records))
    total = sum(len(d) for d in meshes.values())
    print(f"wrote {len(records)} meshes ({total / 1e6:.2f} MB) to {shapes_dir}")


def check_mesh(mesh) -> list[str]:
    problems = []
    if not is_closed(mesh):
        problems.append("not a closed, consistently oriented manifold with positive volume")
    if len(mesh.faces) > MAX_FACES:
        problems.append(f"{len(mesh.faces)} faces > {MAX_FACES}")
    lo, hi = mesh.bounds
    if lo.min() < -0.5 - 1e-6 or hi.max() > 0.5 + 1e-6 or abs(float((hi - lo).max()) - 1.0) > 1e-6:
        problems.append(f"bounds {lo} .. {hi} do not fit [-0.5, 0.5]^3 with longest side 1")
    return problems


def verify(shapes_dir: Path = SHAPES_DIR) -> list[str]:
    """Cheap consistency checks of the committed files; returns the problems found."""
    problems = []
    split_file, catalog_file = shapes_dir / SPLIT_FILE, shapes_dir / CATALOG_FILE
    if not split_file.is_file() or not catalog_file.is_file():
        return [f"missing {SPLIT_FILE} or {CATALOG_FILE} in {shapes_dir}: run `build` first"]
    try:  # a hand-edited or truncated file is a problem to report, not a traceback
        split = json.loads(split_file.read_text())
        catalog = json.loads(catalog_file.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        return [f"{SPLIT_FILE} or {CATALOG_FILE} is not valid JSON: {exc}"]
    records = catalog.get("shapes") if isinstance(catalog, dict) else None
    if not isinstance(split, dict) or not isinstance(records, list) or not all(
            isinstance(r, dict) and {"name", "kind", "split", "source", "file", "sha256"} <= set(r) for r in records):
        return [f"{CATALOG_FILE} or {SPLIT_FILE} does not have the layout `build` writes: rerun `build`"]
    if split != {"version": SPLIT_VERSION, **SPLIT}:
        problems.append(f"{SPLIT_FILE} differs from SPLIT in this script")
    expected_counts = {("train", "synthetic"): 10, ("train", "everyday"): 20,
                       ("unseen", "synthetic"): 15, ("unseen", "everyday"): 15}
    for (part, kind), count in expected_counts.items():
        got = len(split.get(part, {}).get(kind, []))
        if got != count:
            problems.append(f"split {part}/{kind} has {got} shapes, expected {count}")
    split_names = [n for part in ("train", "unseen") for kind in ("synthetic", "everyday")
                   for n in split.get(part, {}).get(kind, [])]
    if len(split_names) != len(set(split_names)):
        problems.append("a shape appears twice in the split")
    by_name = {r["name"]: r for r in records}
    if set(by_name) != set(split_names):
        problems.append(f"catalogue and split disagree: {sorted(set(by_name) ^ set(split_names))}")
    if set(synthetic_shapes()) != {n for n, r in by_name.items() if r["kind"] == "synthetic"}:
        problems.append("synthetic shapes in the catalogue differ from synthetic_shapes()")
    for entry in EVERYDAY:
        record = by_name.get(entry.name)
        if record is None or record["kind"] != "everyday" or record["source"] != everyday_source(entry):
            problems.append(f"catalogue entry of {entry.name} does not match the EVERYDAY table")
    for r in records:
        if r["name"] in split_names and r["split"] != split_of(r["name"]):
            problems.append(f"{r['name']}: catalogue split {r['split']!r} differs from the split file")
        path = shapes_dir / r["file"]
        if not path.is_file():
            problems.append(f"{r['name']}: missing {path}")
        elif hashlib.sha256(path.read_bytes()).hexdigest() != r["sha256"]:
            problems.append(f"{r['name']}: {path.name} does not match its sha256 in the catalogue")
    extra = {p.name for p in (shapes_dir / "meshes").glob("*")} - {Path(r["file"]).name for r in records}
    if extra:
        problems.append(f"files not in the catalogue: {sorted(extra)}")
    attribution_file = shapes_dir / ATTRIBUTION_FILE
    attribution = attribution_file.read_text() if attribution_file.is_file() else ""
    if attribution != attribution_text(records):
        problems.append(f"{ATTRIBUTION_FILE} is missing or out of date (rerun `build`)")
    missing = [r["name"] for r in records if r["kind"] == "everyday" and f"| {r['name']} |" not in attribution]
    if missing:
        problems.append(f"{ATTRIBUTION_FILE} does not list {missing}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="download the packages and rebuild every mesh, the catalogue, split and attribution")
    b.add_argument("--cache", type=Path, default=REPO / ".cache/shape-packages",
                   help="where downloaded wheels and .deb files are kept (default: %(default)s)")
    v = sub.add_parser("verify", help="cheap check that the committed files agree with each other and with this script")
    for p in (b, v):
        p.add_argument("--shapes-dir", type=Path, default=SHAPES_DIR, help="library folder (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.command == "build":
        # Before the synthetic shapes are made (the cache is first used after them): was a FileExistsError
        if args.cache.exists() and not args.cache.is_dir():
            parser.error(f"--cache: {args.cache} is a file; give a folder for the downloaded packages")
        build(args.cache, args.shapes_dir)
    problems = verify(args.shapes_dir)
    for problem in problems:
        print(f"verify: {problem}", file=sys.stderr)
    if problems:
        return 1
    print(f"verify: ok ({args.shapes_dir}: {SPLIT_FILE}, {CATALOG_FILE}, {ATTRIBUTION_FILE}, meshes/)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
