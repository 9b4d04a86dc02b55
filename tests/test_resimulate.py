"""Re-simulation and the re-simulation PSNR (SPEC 8): ad_sim.resimulate on real Warp CPU simulations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ad_sim.episode import simulate_batch
from ad_sim.instances import benchmark
from ad_sim.resimulate import (
    PSNR_CAP,
    candidate_from_row,
    mask_psnr,
    resimulate,
    resimulation_psnr,
    with_material,
)

# A small (1.2k particles) sand instance: sand's E and nu are fixed, so every candidate costs the
# same substeps (~1.4 s per 25-frame episode on one CPU core), and it spreads visibly on impact.
SAND = "unseen-bull-sand-0000"


def tiny_instance(episode_id: str):
    return next(i for i in benchmark("tiny", "unseen") if i.episode_id == episode_id)


def test_psnr_of_identical_videos_is_the_cap_and_of_different_ones_finite_and_lower():
    rng = np.random.default_rng(0)
    a = (rng.random((25, 128, 128)) > 0.5).astype(np.uint8) * 255
    assert mask_psnr(a, a.copy()) == PSNR_CAP
    b = a.copy()
    b[3, :64] = 255 - b[3, :64]  # flip half of one frame: MSE = (64 * 128) / (25 * 128 * 128)
    expected = 10 * math.log10(25 * 128 * 128 / (64 * 128))
    assert mask_psnr(a, b) == pytest.approx(expected, rel=1e-6)
    assert math.isfinite(mask_psnr(a, b)) and mask_psnr(a, b) < PSNR_CAP
    one_pixel = a.copy()
    one_pixel[0, 0, 0] ^= 255
    assert 56.0 < mask_psnr(a, one_pixel) < 56.2 < PSNR_CAP  # 10 log10(25 * 128^2)
    # uint8 0/255 and float [0, 1] masks are the same videos; batches give one PSNR per video.
    assert mask_psnr(a / 255.0, b / 255.0) == pytest.approx(mask_psnr(a, b))
    np.testing.assert_allclose(mask_psnr(np.stack([a, a]), np.stack([a, b])), [PSNR_CAP, expected], rtol=1e-6)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        mask_psnr(a.astype(np.float32), a.astype(np.float32))


def test_copy_with_another_material_keeps_initial_state_and_cameras_and_clips_into_range():
    original = tiny_instance("unseen-arch-plasticine-0000")
    copy = with_material(original, "jelly", {"youngs_modulus": 3e5, "poissons_ratio": 0.45})
    assert copy.material == "jelly" and copy.shape == original.shape and copy.seed == original.seed
    assert copy.parameters == {"youngs_modulus": 3e5, "poissons_ratio": 0.40}  # nu clipped to jelly's range
    for name in ("orientation", "drop_gap", "jitter", "velocity", "camera_seed", "sampling_seed"):
        assert getattr(copy, name) == getattr(original, name), name
    np.testing.assert_array_equal(copy.pose(), original.pose())
    np.testing.assert_array_equal(copy.cameras(2)[1].pose, original.cameras(2)[1].pose)
    assert original.material == "plasticine"  # the original is untouched
    assert candidate_from_row("sand", [1e5, 0.3, np.nan, 0.5]) == ("sand", {"friction_angle": 0.5})


def test_a_candidate_cannot_change_a_family_s_fixed_parameters():
    """Sand's E and nu are fixed (SPEC 6): a candidate that carries values for them (a full row of predictions)
    is simulated with the fixed ones, as its family's law defines, not with E = 1e6 (9x the substeps)."""
    original = tiny_instance(SAND)
    full_row = {"youngs_modulus": 1e6, "poissons_ratio": 0.45, "friction_angle": 0.5}
    copy = with_material(original, "sand", full_row)
    assert copy.parameters == {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.5}
    # A fixed value the model left undefined does not matter either; sampled values are still checked.
    assert with_material(original, "sand", {"youngs_modulus": math.nan, "friction_angle": 0.5}).parameters == copy.parameters
    with pytest.raises(ValueError, match="unphysical"):
        with_material(original, "sand", {"friction_angle": math.nan})


def test_resimulating_the_truth_reproduces_the_masks_and_another_parameter_does_not():
    instance = tiny_instance(SAND)
    observed = simulate_batch([instance])[0].masks[0]  # what the generator records
    truth = (instance.material, instance.parameters)
    other = ("sand", {"friction_angle": math.radians(12.0)})  # true phi is ~30 degrees
    psnr = resimulation_psnr([instance, instance], [truth, other], observed=np.stack([observed, observed]))
    assert psnr[0] == PSNR_CAP  # bitwise identical on CPU, though batched with another scene
    assert 10.0 < psnr[1] < 50.0
    # Without observed videos the ground truth is simulated in the same batch: same numbers.
    np.testing.assert_array_equal(resimulation_psnr([instance], [other]), psnr[1:])


def test_resimulate_renders_the_requested_view_and_checks_its_inputs():
    instance = tiny_instance(SAND)
    masks = resimulate([instance], [(instance.material, instance.parameters)], view=1, frame_count=2)
    episode = simulate_batch([instance], views=2, frame_count=2)[0]
    np.testing.assert_array_equal(masks[0], episode.masks[1])
    with pytest.raises(ValueError, match="one candidate per instance"):
        resimulate([instance], [])
    with pytest.raises(ValueError, match="unphysical"):
        resimulate([instance], [("jelly", {"youngs_modulus": -1.0, "poissons_ratio": 0.3})])


# ---- mutation-testing audit (round 2)


def test_parameters_below_a_range_are_clipped_up_to_its_low_end():
    """clip_to_family_range clips at both ends: only the upper end was tested (nu 0.45 -> 0.40)."""
    from ad_sim.materials import FAMILY_RANGES
    from ad_sim.resimulate import clip_to_family_range

    (e_low, e_high, _), (nu_low, nu_high, _) = (FAMILY_RANGES["jelly"][n] for n in ("youngs_modulus", "poissons_ratio"))
    assert clip_to_family_range("jelly", {"youngs_modulus": e_low / 10, "poissons_ratio": -0.2}) == {
        "youngs_modulus": e_low, "poissons_ratio": nu_low}
    assert clip_to_family_range("jelly", {"youngs_modulus": e_high * 10, "poissons_ratio": 0.49}) == {
        "youngs_modulus": e_high, "poissons_ratio": nu_high}
    phi_low = FAMILY_RANGES["sand"]["friction_angle"][0]
    assert clip_to_family_range("sand", {"friction_angle": phi_low / 2})["friction_angle"] == phi_low
    inside = {"youngs_modulus": math.sqrt(e_low * e_high), "poissons_ratio": (nu_low + nu_high) / 2}
    assert clip_to_family_range("jelly", inside) == inside


def test_mse_of_grey_float_masks_squares_the_differences():
    """Float masks in [0, 1] (grey levels) are accepted: the MSE squares each difference, so a video at 0.5
    against one at 0 has MSE 0.25 (PSNR 10 log10 4), not 0.5 (an absolute error is the same only for 0/1 masks)."""
    from ad_sim.resimulate import mask_mse

    grey, black = np.full((25, 8, 8), 0.5, np.float32), np.zeros((25, 8, 8), np.float32)
    assert mask_mse(grey, black) == pytest.approx(0.25)
    assert mask_psnr(grey, black) == pytest.approx(10 * math.log10(4.0))
    quarter = black.copy()
    quarter[:, :4, :4] = 0.25  # a quarter of the pixels off by 0.25
    assert mask_mse(quarter, black) == pytest.approx(0.25 * 0.25**2)
