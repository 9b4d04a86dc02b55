"""ad_sim.shapes: the 60-shape library, its split, meshes, volumetric sampling and build/verify script."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ad_sim import shapes

REPO_ROOT = Path(__file__).resolve().parents[1]
BUILD_SCRIPT = REPO_ROOT / "scripts" / "build_shapes.py"
REQUIRED = ("box", "sphere", "cylinder", "cone", "torus", "capsule")
# What the simulator uses: unit-cube domain, particles at half a 32^3 grid cell, objects at 0.35.
SPACING, SCALE, MIN_PARTICLES = 1 / 64, 0.35, 1500
ALL = [s.name for s in shapes.list_shapes()]


def test_library_has_60_shapes_with_required_names():
    infos = shapes.list_shapes()
    kinds = [s.kind for s in infos]
    assert len(infos) == 60 and len(set(ALL)) == 60
    assert kinds.count("synthetic") == 25 and kinds.count("everyday") == 35
    synthetic = {s.name for s in infos if s.kind == "synthetic"}
    assert set(REQUIRED) <= synthetic
    assert ALL == sorted(ALL)
    assert all(s.source for s in infos)


@pytest.mark.parametrize("split, synthetic, everyday", [("train", 10, 20), ("unseen", 15, 15)])
def test_split_counts(split, synthetic, everyday):
    infos = shapes.list_shapes(split)
    assert all(s.split == split for s in infos)
    assert sum(s.kind == "synthetic" for s in infos) == synthetic
    assert sum(s.kind == "everyday" for s in infos) == everyday


def test_split_file_is_the_source_of_the_split():
    split = json.loads(shapes.SPLIT_FILE.read_text())
    assert split["version"] == 1 and shapes.SPLIT_FILE.name == "split_v1.json"
    for info in shapes.list_shapes():
        assert info.name in split[info.split][info.kind]
    assert not set(n for k in split["train"].values() for n in k) & set(n for k in split["unseen"].values() for n in k)


def test_shape_records_are_the_list_shapes_json():
    records = shapes.shape_records()
    assert [r["name"] for r in records] == ALL
    for record in records:
        assert set(record) == {"name", "kind", "split", "source"}
        assert json.loads(json.dumps(record)) == record


def test_unknown_names_and_splits_are_clear_errors():
    with pytest.raises(ValueError, match="unknown shape 'teapot'.*box.*torus"):
        shapes.load_mesh("teapot")
    with pytest.raises(ValueError, match="unknown shape 'teapot'"):
        shapes.sample_volume("teapot", SPACING)
    with pytest.raises(ValueError, match="split 'seen'"):
        shapes.list_shapes("seen")


@pytest.mark.parametrize("name", ALL)
def test_mesh_is_closed_and_normalised(name):
    mesh = shapes.load_mesh(name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0.01  # outward normals, and not a sliver
    lo, hi = mesh.bounds
    assert np.all(lo >= -0.5 - 1e-6) and np.all(hi <= 0.5 + 1e-6)
    assert abs((hi - lo).max() - 1.0) < 1e-5
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-5)
    assert len(mesh.faces) <= 2000
    assert len(mesh.split(only_watertight=False)) == 1
    # load_mesh hands out copies: callers may transform theirs
    mesh.apply_scale(2.0)
    assert abs(shapes.load_mesh(name).extents.max() - 1.0) < 1e-5


def _inside_fraction(mesh, points: np.ndarray) -> float:
    """Fraction of `points` inside `mesh` by the exact generalized winding number (not the fast one)."""
    import igl

    winding = igl.winding_number(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                                 points.astype(np.float64))
    return float(np.mean(winding > 0.5))


def _signature(name: str) -> np.ndarray:
    mesh = shapes.load_mesh(name)
    return np.concatenate([[mesh.volume], np.linalg.eigvalsh(mesh.moment_inertia), np.sort(mesh.extents)])


def test_meshes_are_distinct():
    signatures = {name: _signature(name) for name in ALL}
    for i, a in enumerate(ALL):
        for b in ALL[i + 1:]:
            x, y = signatures[a], signatures[b]
            difference = np.max(np.abs(x - y) / np.maximum(np.abs(x), np.abs(y)))
            assert difference > 0.05, f"{a} and {b} have near-identical volume, inertia and extents"


def test_sample_volume_fills_the_mesh():
    """Particle count x cell volume matches the mesh volume; every point is inside the mesh."""
    for name in ("box", "sphere", "torus", "bowl", "mug", "duck", "bunny"):
        points = shapes.sample_volume(name, SPACING, scale=SCALE)
        mesh = shapes.load_mesh(name)
        mesh.apply_scale(SCALE)
        assert points.dtype == np.float32 and points.shape[1] == 3
        assert abs(len(points) * SPACING**3 / mesh.volume - 1.0) < 0.12, name
        assert _inside_fraction(mesh, points) > 0.99, name
    # a 0.35 cube holds exactly 22^3 cell-centred lattice points at 1/64
    assert len(shapes.sample_volume("box", SPACING, scale=SCALE)) == 22**3


def test_every_shape_gives_enough_particles():
    """Synthetic shapes are thick enough at the nominal spacing; thin everyday ones use min_count."""
    for name in ALL:
        plain = shapes.sample_volume(name, SPACING, scale=SCALE)
        info = next(s for s in shapes.list_shapes() if s.name == name)
        if info.kind == "synthetic":
            assert len(plain) >= MIN_PARTICLES, name
        refined = shapes.sample_volume(name, SPACING, scale=SCALE, min_count=MIN_PARTICLES)
        assert len(refined) >= MIN_PARTICLES, name
        if len(plain) >= MIN_PARTICLES:
            np.testing.assert_array_equal(refined, plain)  # no refinement when not needed
        else:
            spacing = shapes.effective_spacing(name, SPACING, SCALE, MIN_PARTICLES)
            assert spacing < SPACING and len(refined) < 4 * MIN_PARTICLES, name  # refined, but not wastefully


def test_min_count_refines_a_thin_shape():
    thin = "wuson"
    plain = shapes.sample_volume(thin, SPACING, scale=SCALE)
    assert len(plain) < MIN_PARTICLES
    spacing = shapes.effective_spacing(thin, SPACING, SCALE, 4000)
    points = shapes.sample_volume(thin, SPACING, scale=SCALE, min_count=4000)
    assert len(points) >= 4000 and spacing < SPACING
    np.testing.assert_array_equal(points, shapes.sample_volume(thin, spacing, scale=SCALE))
    mesh = shapes.load_mesh(thin)
    mesh.apply_scale(SCALE)
    assert _inside_fraction(mesh, points) > 0.97


def test_jitter_is_seeded_and_bounded():
    lattice = shapes.sample_volume("capsule", SPACING, scale=SCALE)
    a = shapes.sample_volume("capsule", SPACING, scale=SCALE, rng=7)
    b = shapes.sample_volume("capsule", SPACING, scale=SCALE, rng=np.random.default_rng(7))
    c = shapes.sample_volume("capsule", SPACING, scale=SCALE, rng=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    offset = np.abs(a - lattice)
    assert offset.max() <= shapes.DEFAULT_JITTER * SPACING + 1e-7 and offset.mean() > 0.05 * SPACING
    # the cached lattice is never modified by jitter
    np.testing.assert_array_equal(lattice, shapes.sample_volume("capsule", SPACING, scale=SCALE))


def test_attribution_lists_every_everyday_shape():
    text = (shapes.DATA_DIR / "ATTRIBUTION.md").read_text()
    for info in shapes.list_shapes():
        if info.kind == "everyday":
            assert f"| {info.name} |" in text
    assert "Stanford" in text and "CC0" in text


def test_build_script_verify_passes_and_has_help():
    verify = subprocess.run([sys.executable, str(BUILD_SCRIPT), "verify"], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    assert "verify: ok" in verify.stdout
    helped = subprocess.run([sys.executable, str(BUILD_SCRIPT), "--help"], capture_output=True, text=True, timeout=60)
    assert helped.returncode == 0 and "build" in helped.stdout and "verify" in helped.stdout


def test_committed_data_is_small():
    total = sum(p.stat().st_size for p in shapes.DATA_DIR.rglob("*") if p.is_file())
    assert total < 3_000_000


def test_build_script_verify_catches_a_changed_mesh(tmp_path):
    library = tmp_path / "shapes"
    shutil.copytree(shapes.DATA_DIR, library)
    mesh = library / "meshes" / "torus.ply.gz"
    mesh.write_bytes(mesh.read_bytes()[:-8])
    (library / "meshes" / "stray.ply.gz").write_bytes(b"")
    verify = subprocess.run([sys.executable, str(BUILD_SCRIPT), "verify", "--shapes-dir", str(library)],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 1
    assert "torus: torus.ply.gz does not match its sha256" in verify.stderr
    assert "stray.ply.gz" in verify.stderr


def test_a_ctrl_c_during_a_swallowing_import_is_held_and_raised_after(tmp_path, monkeypatch):
    """trimesh catches BaseException around its optional imports, so a Ctrl-C during its first import was
    lost (and libigl's turned into an ImportError): ctrl_c_held holds it and hands it on after."""
    import importlib
    import signal
    import threading

    from ad_sim.shapes import ctrl_c_held

    (tmp_path / "swallows_ctrl_c.py").write_text(
        "import os, signal, time\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(0.2)  # the handler runs here\n"
        "except BaseException:\n"
        "    pass  # as trimesh does around its optional imports\n"
        "LOADED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))

    def import_fresh():
        sys.modules.pop("swallows_ctrl_c", None)
        with ctrl_c_held():
            return importlib.import_module("swallows_ctrl_c")

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):  # Python's own handler: raised once the import is done
        import_fresh()
    assert sys.modules["swallows_ctrl_c"].LOADED  # imported whole, then the Ctrl-C
    assert signal.getsignal(signal.SIGINT) is before
    calls = []  # a program's own handler (a node's stop flag) gets the held signal, once
    signal.signal(signal.SIGINT, lambda *args: calls.append(args[0]))
    try:
        assert import_fresh().LOADED
    finally:
        signal.signal(signal.SIGINT, before)
    assert calls == [signal.SIGINT]
    ran = []  # outside the main thread signal handlers cannot be set: the block runs as it is

    def in_a_thread():
        with ctrl_c_held():
            ran.append(signal.getsignal(signal.SIGINT))

    thread = threading.Thread(target=in_a_thread)
    thread.start()
    thread.join()
    assert ran == [before]
    sys.modules.pop("swallows_ctrl_c", None)


# --------------------------------------------------------------------------- mutation-testing audit


def test_the_lattice_is_cell_centred_and_centred_on_the_mesh():
    """Points sit at (k + 1/2) * spacing: a box centred at 0 gets a lattice centred at 0 (mean 0, symmetric),
    never on its faces."""
    points = shapes.sample_volume("box", SPACING, scale=SCALE).astype(np.float64)
    k = points / SPACING - 0.5
    np.testing.assert_allclose(k, np.round(k), atol=1e-4)
    np.testing.assert_allclose(points.mean(axis=0), 0.0, atol=1e-6)
    np.testing.assert_allclose(points.min(axis=0), -points.max(axis=0), atol=1e-6)


def test_jitter_is_symmetric_about_the_lattice_point():
    """Each point moves by a uniform offset in [-jitter, jitter] * spacing per axis: on average nowhere, so the
    object is not shifted by sampling."""
    lattice = shapes.sample_volume("capsule", SPACING, scale=SCALE)
    offset = (shapes.sample_volume("capsule", SPACING, scale=SCALE, rng=7) - lattice) / SPACING
    assert len(offset) > 1000
    np.testing.assert_allclose(offset.mean(axis=0), 0.0, atol=0.02)  # a one-sided offset: 0.125
    assert (offset < -0.2).any() and (offset > 0.2).any()


def test_a_shape_holding_exactly_min_count_points_is_not_refined():
    plain = shapes.sample_volume("sphere", SPACING, scale=SCALE)
    assert shapes.effective_spacing("sphere", SPACING, SCALE, min_count=len(plain)) == SPACING
    np.testing.assert_array_equal(shapes.sample_volume("sphere", SPACING, scale=SCALE, min_count=len(plain)), plain)
    assert shapes.effective_spacing("sphere", SPACING, SCALE, min_count=len(plain) + 1) < SPACING
