"""End to end: instances -> real Warp MPM -> tracked particles and rendered masks."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ad_sim import render
from ad_sim.episode import Episode, sample_particles, simulate_batch
from ad_sim.instances import Instance, benchmark

FRAMES = 6  # 0.125 s: the objects are still falling or just landing


def instances() -> list[Instance]:
    return [
        Instance("e2e-sphere", "custom", "sphere", "jelly", {"youngs_modulus": 2e4, "poissons_ratio": 0.3}, seed=11, views=2),
        Instance("e2e-cone", "custom", "cone", "sand", {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.6}, seed=12),
        Instance(
            "e2e-torus", "custom", "torus", "plasticine", {"youngs_modulus": 6e4, "poissons_ratio": 0.4, "yield_stress": 800.0}, seed=13
        ),
    ]


@pytest.fixture(scope="module")
def episodes() -> list[Episode]:
    return simulate_batch(instances(), full_masks=True, frame_count=FRAMES)


def test_episodes_have_the_documented_shapes(episodes):
    assert [e.instance.episode_id for e in episodes] == ["e2e-sphere", "e2e-cone", "e2e-torus"]
    for episode in episodes:
        views = episode.instance.views
        assert episode.positions.shape == (FRAMES, 1024, 3) and episode.positions.dtype == np.float32
        assert episode.deformation.shape == (FRAMES, 1024, 3, 3) and episode.deformation.dtype == np.float32
        assert episode.masks.shape == (views, FRAMES, 128, 128) and episode.masks.dtype == np.uint8
        assert episode.masks_full.shape == (views, FRAMES, 512, 512) and episode.masks_full.dtype == np.uint8
        assert set(np.unique(episode.masks)) == {0, 255}
        assert len(episode.cameras) == views and episode.cameras[0].width == 128
        assert episode.particle_count >= 1024 and episode.substeps_per_frame >= 1
        assert np.all(np.isfinite(episode.positions)) and np.all(np.isfinite(episode.deformation))
        # Frame 0 is the initial state: undeformed, the tracked particles are distinct sampled ones.
        np.testing.assert_allclose(episode.deformation[0], np.broadcast_to(np.eye(3), (1024, 3, 3)), atol=1e-6)
        assert len(np.unique(episode.positions[0], axis=0)) == 1024
        # The 128x128 masks are the area-downsampled 512x512 ones.
        full = episode.masks_full.reshape(-1, 512, 512)
        np.testing.assert_array_equal(render.downsample(full).reshape(episode.masks.shape), episode.masks)


def test_tracked_particles_span_the_sampled_object(episodes):
    for episode in episodes:
        particles, _ = sample_particles(episode.instance)
        tracked = episode.positions[0]
        # FPS picks the extremes: the tracked set's bounding box nearly equals the object's.
        np.testing.assert_allclose(tracked.min(axis=0), particles.min(axis=0), atol=0.02)
        np.testing.assert_allclose(tracked.max(axis=0), particles.max(axis=0), atol=0.02)


def test_objects_fall_in_the_masks(episodes):
    for episode in episodes:
        z = episode.positions[:, :, 2].mean(axis=1)
        assert z[3] < z[0] - 0.01, episode.instance.episode_id
        for view in episode.masks:
            assert np.all(view.reshape(FRAMES, -1).any(axis=1)), "object must be visible in every frame"
            rows = [np.nonzero(frame)[0].mean() for frame in view]
            # Image y points down in the optical frame, so falling moves the centroid to larger rows.
            assert rows[3] > rows[0] + 1.0, episode.instance.episode_id


def test_simulate_batch_is_deterministic(episodes):
    again = simulate_batch(instances(), frame_count=FRAMES, max_batch=2)
    for a, b in zip(episodes, again):
        assert b.masks_full is None
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.deformation, b.deformation)
        np.testing.assert_array_equal(a.masks, b.masks)
        assert a.particle_count == b.particle_count


def test_resimulation_with_other_material_starts_from_the_same_state():
    original = instances()[0]
    predicted = Instance("resim", "custom", original.shape, "sand", {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.4}, original.seed)
    np.testing.assert_array_equal(sample_particles(original)[0], sample_particles(predicted)[0])
    np.testing.assert_array_equal(original.cameras(1)[0].pose, predicted.cameras(1)[0].pose)
    assert original.velocity == predicted.velocity


def test_views_override_keeps_the_seeded_cameras(episodes):
    tiny = benchmark("tiny", "unseen")
    assert len(tiny) == 6 and all(i.views == 1 for i in tiny)
    sphere = instances()[0]
    for camera, seeded in zip(episodes[0].cameras, sphere.cameras(3)):
        np.testing.assert_array_equal(camera.pose, seeded.pose)


def test_preview_contact_sheet(episodes, tmp_path):
    script = Path(__file__).resolve().parents[1] / "scripts" / "preview_episode.py"
    spec = importlib.util.spec_from_file_location("preview_episode", script)
    preview = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(preview)
    sheet = preview.contact_sheet(episodes[0])
    views = episodes[0].instance.views
    assert sheet.shape == (preview.HEADER + views * (128 + preview.GAP), FRAMES * (128 + preview.GAP))
    # Tile (view 1, frame 2) holds that mask.
    y, x = preview.HEADER + 128 + preview.GAP, 2 * (128 + preview.GAP)
    np.testing.assert_array_equal(sheet[y : y + 128, x : x + 128], episodes[0].masks[1, 2])
    help_text = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, check=True).stdout
    assert "--instances" in help_text and "--output" in help_text


def test_a_cancelled_simulation_stops_within_a_frame():
    """simulate_batch(cancelled=...) asks before each simulated frame and raises mpm.Cancelled, so a
    stopping node's worker leaves Warp at once (sim_node joins it before the interpreter exits)."""
    from ad_sim.mpm import Cancelled

    asked = []

    def cancelled() -> bool:
        asked.append(True)
        return len(asked) > 3

    with pytest.raises(Cancelled, match="cancelled at frame 4"):
        simulate_batch(benchmark("tiny", "unseen")[:2], frame_count=25, cancelled=cancelled)
    assert len(asked) == 4


# ---- mutation-testing audit (round 2)


def test_masks_are_the_silhouette_of_the_tracked_particles(episodes):
    """Every mask is drawn where the simulated body is: the tracked particles, projected through the episode's
    own (128x128) camera, fall on object pixels, and the silhouette's bounding box is the particles' bounding
    box to within a few pixels (the surface lies at most about a particle spacing outside the outermost
    particles). A mesh left at its normalised size (SCALE missing), posed with the transposed rotation, or
    drawn through the 128-pixel camera on the 512-pixel canvas all passed the other tests."""
    for episode in episodes:
        for view, camera in enumerate(episode.cameras):
            for frame in (0, FRAMES - 1):
                mask = episode.masks[view, frame] > 127
                pixels = camera.project(episode.positions[frame].astype(np.float64))
                u, v = np.round(pixels).astype(int).T
                assert u.min() >= 0 and v.min() >= 0 and u.max() < 128 and v.max() < 128
                on_object = mask[v, u].mean()
                assert on_object > 0.97, (episode.instance.episode_id, view, frame, on_object)
                rows, cols = np.nonzero(mask)
                box = np.array([cols.min(), rows.min(), cols.max(), rows.max()])
                expected = np.array([pixels[:, 0].min(), pixels[:, 1].min(), pixels[:, 0].max(), pixels[:, 1].max()])
                np.testing.assert_allclose(box, expected, atol=4.0, err_msg=f"{episode.instance.episode_id} view {view}")
