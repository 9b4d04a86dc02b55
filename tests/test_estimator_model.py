"""ad_estimator.model (real onnxruntime on contract-following ONNX files) and ad_estimator.images."""
import math
import types

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ad_estimator.images import DEFAULT_THRESHOLD, ImageRejected, image_to_mask
from ad_estimator.model import (BUNDLED_MODEL, MASK_LEVELS, SIMULATOR_MASK_SIZE, TRAINED_EXTENT, EstimatorModel,
                                ModelError, as_simulator_mask, frame_inputs, object_extent)
from estimator_models import build_clip_model, build_streaming_model, falling_masks


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    return {"clip": EstimatorModel.load(build_clip_model(d / "clip.onnx")),
            "streaming": EstimatorModel.load(build_streaming_model(d))}


@pytest.mark.parametrize("kind", ["clip", "streaming"])
def test_predict_full_clip(models, kind):
    model = models[kind]
    assert model.info.kind == kind and model.info.frame_count == 25 and model.info.input_size == (32, 32)
    features = np.stack([model.encode(m) for m in falling_masks()])
    est = model.predict(features, np.ones(25, bool))
    assert est.frames_used == 25 and est.inference_time > 0
    assert est.probabilities.shape == (3,) and math.isclose(est.probabilities.sum(), 1.0, rel_tol=1e-9)
    assert est.material == est.class_names[int(np.argmax(est.probabilities))]
    lo_hi = {"youngs_modulus": (1.5e4, 1.5e6), "poissons_ratio": (0.2, 0.48), "yield_stress": (500, 25000),
             "friction_angle": (math.radians(10), math.radians(45))}
    for name, value in zip(est.parameter_names, est.raw_parameters):
        assert lo_hi[name][0] <= value <= lo_hi[name][1]
    assert np.all(est.raw_uncertainties > 0)


def test_family_parameters_nan_and_fixed(models):
    model = models["streaming"]
    raw = np.array([2e5, 0.3, 1000.0, 0.5])
    sigma = np.array([1e4, 0.01, 10.0, 0.02])
    jelly, jelly_sigma = model.family_parameters("jelly", raw, sigma)
    assert jelly[:2].tolist() == [2e5, 0.3] and np.isnan(jelly[2:]).all() and np.isnan(jelly_sigma[2:]).all()
    sand, sand_sigma = model.family_parameters("sand", raw, sigma)
    assert sand[:2].tolist() == [1e5, 0.3] and sand_sigma[:2].tolist() == [0.0, 0.0]
    assert np.isnan(sand[2]) and sand[3] == 0.5
    plasticine, _ = model.family_parameters("plasticine", raw, sigma)
    assert plasticine[:3].tolist() == [2e5, 0.3, 1000.0] and np.isnan(plasticine[3])


def test_a_log_line_gives_each_parameter_its_unit():
    """Friction angle went out in radians with no unit, while the demo prints degrees."""
    from ad_estimator.model import Estimate

    names = ("youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle")
    nan = np.full(4, np.nan)
    sand = Estimate(("jelly", "plasticine", "sand"), np.array([0.1, 0.1, 0.8]), "sand", names,
                    np.array([1e5, 0.3, np.nan, 0.5]), nan, nan, nan, 25, 0.003)
    assert sand.describe() == "sand p=0.80; youngs_modulus 1e+05 Pa, poissons_ratio 0.3, friction_angle 0.5 rad"


def test_uncertainty_is_the_delta_method_in_si(models):
    model = models["clip"]
    rng = model.info.parameter_ranges["youngs_modulus"]
    u, sigma_u, h = 0.4, 0.01, 1e-6
    value = rng.denormalise(u)
    derivative = (rng.denormalise(u + h) - rng.denormalise(u - h)) / (2 * h)
    assert math.isclose(rng.sigma(value, sigma_u), derivative * sigma_u, rel_tol=1e-5)
    nu = model.info.parameter_ranges["poissons_ratio"]
    assert math.isclose(nu.sigma(nu.denormalise(0.5), 0.1), 0.028, rel_tol=1e-9)


def test_without_logvar_uncertainty_is_nan(tmp_path):
    model = EstimatorModel.load(build_clip_model(tmp_path / "m.onnx", with_logvar=False))
    est = model.predict(np.zeros((3, 32, 32), np.float32), np.ones(3, bool))
    assert np.isnan(est.raw_uncertainties).all()


@pytest.mark.parametrize("kind", ["clip", "streaming"])
def test_invalid_slots_do_not_influence_the_estimate(models, kind):
    model = models[kind]
    features = np.stack([model.encode(m) for m in falling_masks(12)])
    valid = np.ones(12, bool)
    valid[[3, 7]] = False
    a = model.predict(features, valid)
    garbage = features.copy()
    garbage[[3, 7]] = 1e3
    b = model.predict(garbage, valid)
    assert np.array_equal(a.probabilities, b.probabilities) and a.frames_used == 10
    c = model.predict(features, np.ones(12, bool))
    assert not np.allclose(a.probabilities, c.probabilities)


def test_streaming_equals_encoding_then_head(models):
    """Cached embeddings give exactly what a fresh encoding gives (B=1 everywhere)."""
    model = models["streaming"]
    masks = falling_masks()
    first = np.stack([model.encode(m) for m in masks])
    again = np.stack([model.encode(m) for m in masks])
    assert np.array_equal(first, again) and first.shape == (25, 16)


def test_prepare_resizes_any_size_with_area_interpolation(models):
    model = models["clip"]
    mask = np.zeros((128, 128), np.uint8)
    mask[:64] = 255
    out = model.prepare(mask)
    assert out.shape == (32, 32) and out.dtype == np.float32
    assert np.all(out[:16] == 1.0) and np.all(out[16:] == 0.0)
    assert model.prepare(np.full((7, 300), 255, np.uint8)).shape == (32, 32)


def camera_masks(seed: int, size: tuple[int, int] = (512, 512)) -> np.ndarray:
    """Full-resolution binary masks: discs of random centres and radii, with edges at sub-pixel
    offsets of the 128x128 grid, so that area averages land on both sides of one half."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[: size[0], : size[1]]
    masks = []
    for _ in range(4):
        cy, cx, r = rng.uniform(0.3, 0.7) * size[0], rng.uniform(0.3, 0.7) * size[1], rng.uniform(20, 150)
        masks.append(np.where((y - cy) ** 2 + (x - cx) ** 2 <= r * r, 255, 0).astype(np.uint8))
    return np.stack(masks)


def test_simulator_mask_size_is_the_simulators():
    from ad_sim.render import MASK_SIZE

    assert SIMULATOR_MASK_SIZE == MASK_SIZE


def test_camera_masks_become_the_simulators_masks(models):
    """A 512x512 camera mask reaches the model exactly as the simulator's own downsampling (the
    Warp kernel that made every training mask) would have made it, for both model kinds."""
    from ad_sim.render import downsample

    full = camera_masks(0)
    simulator = downsample(full)
    for mask, expected in zip(full, simulator):
        got = as_simulator_mask(mask)
        assert got.dtype == np.uint8 and np.array_equal(got, expected)
        assert 0 < (expected == 255).mean() < 1
        for model in models.values():
            assert np.array_equal(model.prepare(mask), model.prepare(expected))


def test_any_binary_encoding_counts_non_zero_pixels_as_the_kernel_does():
    from ad_sim.render import downsample

    full = camera_masks(3)
    for mask, expected in zip(full, downsample(full)):
        for binary in (mask == 255, (mask == 255).astype(np.uint8), np.where(mask == 255, 200, 0).astype(np.uint8)):
            assert np.array_equal(as_simulator_mask(binary), expected)


def test_any_camera_size_gives_a_binary_simulator_mask():
    for mask in camera_masks(1, (480, 640)):
        got = as_simulator_mask(mask)
        assert got.shape == (SIMULATOR_MASK_SIZE, SIMULATOR_MASK_SIZE) and set(np.unique(got)) <= {0, 255}
        # the same object, letterboxed into the square: its area shrinks by the padding, 480/640
        assert abs((got == 255).mean() - 0.75 * (mask == 255).mean()) < 0.02


def test_a_camera_that_is_not_square_keeps_the_objects_proportions():
    """A 4:3 (or 3:4) view of the same scene, cut from a square render where the cut bands are
    empty, gives exactly the square render's simulator mask: letterboxed, not stretched."""
    from ad_sim.render import downsample

    checked = 0
    for mask in camera_masks(2):
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        expected = downsample(mask[None])[0]
        if rows[0] >= 64 and rows[-1] < 448:
            assert np.array_equal(as_simulator_mask(mask[64:448]), expected)
            checked += 1
        if cols[0] >= 64 and cols[-1] < 448:
            assert np.array_equal(as_simulator_mask(mask[:, 64:448]), expected)
            checked += 1
    assert checked >= 2
    disc = np.zeros((384, 512), np.uint8)
    disc[np.hypot(*np.mgrid[-192:192, -256:256]) < 100] = 255
    got = as_simulator_mask(disc)
    rows, cols = np.flatnonzero(got.any(axis=1)), np.flatnonzero(got.any(axis=0))
    assert abs(len(rows) - len(cols)) <= 1  # a disc stays round


def test_camera_masks_become_the_simulators_coverage_masks(tmp_path):
    """For a model of grey masks (ad.mask_levels coverage), a 512x512 camera mask reaches the model as
    the simulator's coverage downsampling (generate --coverage-masks) would have made it: the
    same levels, rounded the same way, so prepare sees grey edges."""
    from ad_sim.render import downsample

    full = camera_masks(0)
    simulator = downsample(full, coverage=True)
    coverage = {}
    for kind, path in (("clip", build_clip_model(tmp_path / "clip.onnx")), ("streaming", build_streaming_model(tmp_path))):
        _with_metadata(path, **{"ad.mask_levels": "coverage"})
        coverage[kind] = EstimatorModel.load(path)
    for mask, expected in zip(full, simulator):
        got = as_simulator_mask(mask, coverage=True)
        assert got.dtype == np.uint8 and got.shape == (SIMULATOR_MASK_SIZE, SIMULATOR_MASK_SIZE)
        np.testing.assert_array_equal(got, expected)
        assert ((expected > 0) & (expected < 255)).any()
        np.testing.assert_array_equal(got > 127, as_simulator_mask(mask) == 255)  # thresholds to the binary mask
        np.testing.assert_array_equal(as_simulator_mask(expected, coverage=True), expected)  # 128x128: as it is
        for model in coverage.values():
            prepared = model.prepare(mask)
            np.testing.assert_array_equal(prepared, model.prepare(expected))
            assert ((prepared > 0) & (prepared < 1)).any()
    # Every coverage of a 4x4 block, the tie at 8 of 16 included, rounds as the simulator rounds it.
    rng = np.random.default_rng(4)
    counts = rng.integers(0, 17, size=(128, 128))
    counts[0, :17] = np.arange(17)
    blocks = np.arange(16) < counts[..., None]
    blocks = rng.permuted(blocks, axis=-1).reshape(128, 128, 4, 4)
    full = np.where(blocks.transpose(0, 2, 1, 3).reshape(512, 512), 255, 0).astype(np.uint8)
    expected = downsample(full[None], coverage=True)[0]
    np.testing.assert_array_equal(expected, (510 * counts + 16) // 32)
    np.testing.assert_array_equal(as_simulator_mask(full, coverage=True), expected)


@pytest.mark.parametrize("entries, levels", [({}, "binary"), ({"ad.mask_levels": "binary"}, "binary"),
                                             ({"ad.mask_levels": "coverage"}, "coverage")])
@pytest.mark.parametrize("kind", ["clip", "streaming"])
def test_mask_levels_metadata(tmp_path, kind, entries, levels):
    """ad.mask_levels absent (every model before grey masks) means binary: the node's threshold
    applies; coverage: the levels are read (no threshold)."""
    path = build_clip_model(tmp_path / "m.onnx") if kind == "clip" else build_streaming_model(tmp_path)
    _with_metadata(path, **entries)
    info = EstimatorModel.load(path).info
    assert info.mask_levels == levels
    assert info.input_threshold() == (DEFAULT_THRESHOLD if levels == "binary" else None)
    assert info.input_threshold(90) == (90 if levels == "binary" else None)
    assert levels in MASK_LEVELS


@pytest.mark.parametrize("value", ["grey", "Coverage", "", "1"])
def test_an_unknown_mask_levels_value_is_refused_at_load(tmp_path, value):
    path = build_clip_model(tmp_path / "m.onnx")
    _with_metadata(path, **{"ad.mask_levels": value})
    with pytest.raises(ModelError, match=rf"m.onnx: ad.mask_levels is {value!r}, expected one of \('binary', "
                                         r"'coverage'\); update ad_estimator or re-export"):
        EstimatorModel.load(path)


def test_prepare_reads_levels_only_for_a_coverage_model(tmp_path):
    """A binary model (the default) still thresholds a camera's full-resolution mask at half coverage;
    a coverage model keeps the coverage, so the two see different inputs, except on binary 128x128 masks."""
    binary = EstimatorModel.load(build_clip_model(tmp_path / "b.onnx"))
    grey_path = build_clip_model(tmp_path / "g.onnx")
    _with_metadata(grey_path, **{"ad.mask_levels": "coverage"})
    grey = EstimatorModel.load(grey_path)
    mask = camera_masks(5)[0]
    np.testing.assert_array_equal(binary.prepare(mask), binary.prepare(as_simulator_mask(mask)))
    assert not np.array_equal(grey.prepare(mask), binary.prepare(mask))
    # On the simulator's own binary 128x128 masks both prepare the same input.
    np.testing.assert_array_equal(grey.prepare(as_simulator_mask(mask)), binary.prepare(as_simulator_mask(mask)))


def test_object_extent_is_the_larger_side_in_the_simulator_mask():
    box = np.zeros((512, 512), np.uint8)
    box[100:254, 200:277] = 255  # 154 x 77 px of 512: the larger side is 0.3 of the image side
    assert abs(object_extent(box) - 154 / 512) <= 1 / 128
    assert object_extent(np.zeros((512, 512), np.uint8)) == 0.0
    four_three = box[64:448]  # 512 wide, 384 high: letterboxed, so still a fraction of 512
    assert abs(object_extent(four_three) - 154 / 512) <= 1 / 128
    assert TRAINED_EXTENT[0] < object_extent(falling_masks()[0]) < TRAINED_EXTENT[1]


def test_missing_model_names_the_file(tmp_path):
    path = tmp_path / "nothing.onnx"
    with pytest.raises(ModelError, match="nothing.onnx"):
        EstimatorModel.load(path)


def test_unknown_execution_provider_is_refused(tmp_path):
    with pytest.raises(ModelError, match="unknown execution provider 'tpu'"):
        EstimatorModel.load(build_clip_model(tmp_path / "m.onnx"), provider="tpu")


def test_cuda_provider_loads_or_says_what_is_missing(tmp_path):
    """provider cuda: runs where onnxruntime has the CUDA provider, else a clear error (never a
    silent fall-back to the CPU)."""
    import onnxruntime as ort

    path = build_streaming_model(tmp_path)
    if "CUDAExecutionProvider" in ort.get_available_providers():
        model = EstimatorModel.load(path, provider="cuda")
        assert model.predict(np.zeros((1, *model.feature_shape), np.float32), np.ones(1, bool)).frames_used == 1
    else:
        with pytest.raises(ModelError, match="no CUDAExecutionProvider.*onnxruntime-gpu"):
            EstimatorModel.load(path, provider="cuda")


def test_corrupt_model_names_the_file(tmp_path):
    path = tmp_path / "corrupt.onnx"
    path.write_bytes(b"\x08\x07garbage" * 100)
    with pytest.raises(ModelError, match="corrupt.onnx") as error:
        EstimatorModel.load(path)
    assert "export it first" not in str(error.value)  # that hint is for .pt files only


def test_a_training_checkpoint_given_as_the_model_is_told_to_be_exported(tmp_path):
    path = tmp_path / "best.pt"
    path.write_bytes(b"PK\x03\x04" + b"\x00" * 64)  # a torch checkpoint is a zip archive
    with pytest.raises(ModelError, match=r"best.pt looks like a training checkpoint: if it is a student's, export it first \(python -m "
                                         r"training export --checkpoint .*best.pt --out .*best.onnx\)"):
        EstimatorModel.load(path)


def test_truncated_model_names_the_file(tmp_path):
    good = build_clip_model(tmp_path / "good.onnx")
    path = tmp_path / "truncated.onnx"
    path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ModelError, match="truncated.onnx"):
        EstimatorModel.load(path)


def test_incomplete_metadata_names_file_and_keys(tmp_path):
    path = build_clip_model(tmp_path / "nometa.onnx", drop_metadata=("ad.parameter_ranges", "ad.frame_count"))
    with pytest.raises(ModelError, match=r"nometa.onnx.*ad.parameter_ranges.*ad.frame_count"):
        EstimatorModel.load(path)


def test_streaming_without_frame_encoder_names_it(tmp_path):
    head = build_streaming_model(tmp_path, name="lonely")
    (tmp_path / "lonely.frame.onnx").unlink()
    with pytest.raises(ModelError) as error:
        EstimatorModel.load(head)
    # the head the user passed is right: the message names the missing encoder, not "set --model"
    assert str(error.value) == (f"{head} is a streaming model whose frame encoder lonely.frame.onnx (its "
                                f"ad.frame_encoder metadata) is missing from {tmp_path}; copy the two files together")


def _with_metadata(path, **entries):
    """Sets (adds or replaces) metadata entries of the model file at `path`."""
    model = onnx.load(str(path))
    kept = [p for p in model.metadata_props if p.key not in entries]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    for key, value in entries.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))


def test_frame_inputs_name_the_mask_then_the_earlier_frames():
    assert frame_inputs(0) == ("mask",)
    assert frame_inputs(1) == ("mask", "previous_mask")
    assert frame_inputs(3) == ("mask", "previous_mask", "previous_mask_2", "previous_mask_3")


@pytest.mark.parametrize("previous_frames, inputs, message", [
    (0, '["mask", "depth"]', r"ad.frame_inputs \['mask', 'depth'\] is not one this estimator knows"),
    (0, '["mask", "previous_mask"]', r"s.frame.onnx takes 1 input channels, its metadata names \['mask', 'previous_mask'\]"),
    (2, '["mask", "previous_mask"]', r"s.frame.onnx takes 3 input channels, its metadata names \['mask', 'previous_mask'\]"),
    (1, '["mask", "previous_mask_2"]', r"ad.frame_inputs \['mask', 'previous_mask_2'\] is not one this estimator knows"),
    (2, '["mask", "previous_mask_2", "previous_mask"]', r"ad.frame_inputs \['mask', 'previous_mask_2', 'previous_mask'\] "
                                                       r"is not one this estimator knows"),
    (1, '["previous_mask", "mask"]', r"ad.frame_inputs \['previous_mask', 'mask'\] is not one this estimator knows"),
    (2, '["mask", "previous_mask", "previous_mask_3"]', r"ad.frame_inputs .* is not one this estimator knows"),
    (0, "[]", r"ad.frame_inputs \[\] is not one this estimator knows"),
    (0, "mask", "ad.frame_inputs.*not valid JSON"),
    (0, '{"mask": 1}', r"ad.frame_inputs \[\{'mask': 1\}\] is not one this estimator knows"),
    (0, "2", r"ad.frame_inputs \[2\] is not one this estimator knows"),
])
def test_frame_inputs_the_encoder_does_not_match_are_refused(tmp_path, previous_frames, inputs, message):
    head = build_streaming_model(tmp_path, name="s", previous_frames=previous_frames)
    _with_metadata(head, **{"ad.frame_inputs": inputs})
    with pytest.raises(ModelError, match=message):
        EstimatorModel.load(head)


def _embedding(model, frame):
    """The frame encoder run directly on a (C, H, W) stack of prepared masks."""
    return ort.InferenceSession(str(model.info.frame_encoder)).run(["embedding"], {"frame": frame[None]})[0][0]


@pytest.mark.parametrize("previous_frames, given, layout", [
    (1, 0, [4, 4]), (1, 1, [4, 3]), (1, 4, [4, 3]),
    (2, 0, [4, 4, 4]), (2, 1, [4, 3, 3]), (2, 2, [4, 3, 2]), (2, 4, [4, 3, 2]),
    (3, 0, [4, 4, 4, 4]), (3, 1, [4, 3, 3, 3]), (3, 2, [4, 3, 2, 2]), (3, 3, [4, 3, 2, 1]), (3, 4, [4, 3, 2, 1]),
])
def test_encode_stacks_the_earlier_frames_newest_first_the_oldest_standing_in(tmp_path, previous_frames, given, layout):
    """Frame 4 with `given` of its earlier frames 3, 2, 1, 0: channel k is the k-th earlier frame;
    where fewer are given, the oldest one given (or the frame itself) stands in; frames beyond
    previous_frames are not read."""
    model = EstimatorModel.load(build_streaming_model(tmp_path, previous_frames=previous_frames))
    assert model.info.frame_inputs == frame_inputs(previous_frames) and model.info.previous_frames == previous_frames
    masks = falling_masks(5, seed=3)
    expected = _embedding(model, np.stack([model.prepare(masks[i]) for i in layout]))
    np.testing.assert_allclose(model.encode(masks[4], list(masks[3::-1])[:given]), expected, rtol=1e-5, atol=1e-6)
    # The test encoder tells the frames and their order apart.
    assert not np.allclose(model.encode(masks[4], [masks[3], masks[2]]), model.encode(masks[4], [masks[2], masks[3]]))


def test_encode_of_the_bundled_model_sees_its_earlier_frames():
    model = EstimatorModel.load(BUNDLED_MODEL)
    assert model.info.frame_inputs == frame_inputs(3) and model.info.previous_frames == 3
    *earlier, mask = falling_masks(4, seed=4)
    earlier = earlier[::-1]  # newest first
    prepared = [model.prepare(m) for m in (mask, *earlier)]
    np.testing.assert_allclose(model.encode(mask, earlier), _embedding(model, np.stack(prepared)),
                               rtol=1e-4, atol=1e-5)
    # Fewer earlier frames than the model reads: the oldest one there stands in; none: the frame itself.
    np.testing.assert_allclose(model.encode(mask, earlier[:1]), model.encode(mask, earlier[:1] * 3), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(model.encode(mask), model.encode(mask, [mask] * 3), rtol=1e-6, atol=1e-6)
    # One array where a sequence belongs (the old encode(mask, previous)) would be read as rows: refused.
    with pytest.raises(TypeError, match="sequence of masks"):
        model.encode(mask, earlier[0])


@pytest.mark.parametrize("previous_frames", [0, 1, 3])
def test_each_mask_of_a_stream_is_resized_once(tmp_path, previous_frames, monkeypatch):
    model = EstimatorModel.load(build_streaming_model(tmp_path, previous_frames=previous_frames))
    prepared = []
    prepare = model.prepare
    monkeypatch.setattr(model, "prepare", lambda mask: prepared.append(mask) or prepare(mask))
    masks = list(falling_masks(10))
    for t, mask in enumerate(masks):
        model.encode(mask, masks[t - 1::-1] if t else [])
    assert len(prepared) == len(masks)


def test_passing_the_frame_encoder_says_which_file_to_pass(tmp_path):
    build_streaming_model(tmp_path, name="s")
    with pytest.raises(ModelError, match=r"s\.onnx"):
        EstimatorModel.load(tmp_path / "s.frame.onnx")


@pytest.mark.parametrize("kind, entries, message", [
    ("clip", {"ad.input_size": "[24, 24]"}, r"m.onnx: input 'masks' has shape \['B', 25, 32, 32\], which does not "
                                           r"fit metadata ad.input_size \[24, 24\]; re-export"),
    ("streaming", {"ad.input_size": "[24, 24]"}, r"s.frame.onnx: input 'frame' has shape \['B', 1, 32, 32\], "
                                                r"which does not fit metadata ad.input_size \[24, 24\]"),
    ("clip", {"ad.frame_count": "30"}, r"m.onnx: input 'masks' .* ad.frame_count \[30\]"),
    ("streaming", {"ad.frame_count": "30"}, r"s.onnx: input 'embeddings' .* ad.frame_count \[30\]"),
    ("streaming", {"ad.parameter_names": '["youngs_modulus"]'},
     r"s.onnx: output 'params' has 4 values but metadata ad.parameter_names names 1 \(youngs_modulus\)"),
    ("clip", {"ad.frame_interval": "inf"}, r"m.onnx: bad input_size/frame_count/frame_interval metadata .*inf"),
    ("clip", {"ad.frame_interval": "nan"}, r"m.onnx: bad input_size/frame_count/frame_interval metadata .*nan"),
    ("clip", {"ad.frame_interval": "0"}, r"m.onnx: bad input_size/frame_count/frame_interval metadata"),
])
def test_metadata_that_does_not_fit_the_graph_is_refused_at_load(tmp_path, kind, entries, message):
    path = build_clip_model(tmp_path / "m.onnx") if kind == "clip" else build_streaming_model(tmp_path, name="s")
    _with_metadata(path, **entries)
    with pytest.raises(ModelError, match=message):
        EstimatorModel.load(path)


def test_a_frame_count_the_graph_cannot_run_is_refused_at_load(tmp_path, capfd):
    """A symbolic slot dimension cannot be checked statically: the trial run at load finds it
    (the test head's per-slot weights have 25 slots), without onnxruntime's own error log."""
    head = build_streaming_model(tmp_path, name="s")
    model = onnx.load(str(head))
    for graph_input in model.graph.input:
        graph_input.type.tensor_type.shape.dim[1].dim_param = "T"
    onnx.save(model, str(head))
    assert EstimatorModel.load(head).info.frame_count == 25
    _with_metadata(head, **{"ad.frame_count": "30"})
    with pytest.raises(ModelError, match=r"s.onnx: a trial run at the metadata's input_size \[32, 32\] and "
                                         r"frame_count 30 failed, so the graph does not fit its ad.\* metadata"):
        EstimatorModel.load(head)
    assert "onnxruntime" not in capfd.readouterr().err


# --------------------------------------------------------------------------- images


def image(height, width, encoding, data, step=None, bigendian=False):
    depth = {"mono8": 1, "8UC1": 1, "mono16": 2, "16UC1": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
    step = width * depth.get(encoding, 1) if step is None else step
    return types.SimpleNamespace(height=height, width=width, encoding=encoding, step=step, data=data,
                                 is_bigendian=bigendian)


def test_mono8_threshold():
    data = np.array([[0, 127, 128, 255]], np.uint8)
    assert image_to_mask(image(1, 4, "mono8", data.tobytes()), 100).tolist() == [[0, 0, 255, 255]]


def test_mono8_with_row_padding():
    data = np.array([[255, 0, 9, 9], [0, 255, 9, 9]], np.uint8)
    mask = image_to_mask(image(2, 2, "mono8", data.tobytes(), step=4), 100)
    assert mask.tolist() == [[255, 0], [0, 255]]


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_threshold_both_endiannesses(bigendian):
    values = np.array([[0, 127 * 257, 127 * 257 + 1, 65535]], ">u2" if bigendian else "<u2")
    msg = image(1, 4, "16UC1", values.tobytes(), bigendian=bigendian)
    assert image_to_mask(msg, 100).tolist() == [[0, 0, 255, 255]]


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8"])
def test_colour_uses_brightest_channel(encoding):
    channels = 4 if encoding == "rgba8" else 3
    data = np.zeros((1, 2, channels), np.uint8)
    data[0, 1, 1] = 200
    if channels == 4:
        data[0, 0, 3] = 255  # alpha alone is not object
    assert image_to_mask(image(1, 2, encoding, data.tobytes()), 100).tolist() == [[0, 255]]


class UntouchableData(types.SimpleNamespace):
    @property
    def data(self):
        raise AssertionError("data touched before the header was checked")


@pytest.mark.parametrize("fields,kind", [
    (dict(height=100_000, width=100_000, encoding="mono8", step=100_000), "too_large"),
    (dict(height=1, width=20_000, encoding="mono8", step=20_000), "too_large"),  # letterboxed: 20000^2
    (dict(height=10, width=10, encoding="32FC1", step=40), "encoding"),
    (dict(height=10, width=10, encoding="rgb8", step=10), "malformed"),
    (dict(height=0, width=10, encoding="mono8", step=10), "empty"),
])
def test_bad_headers_rejected_before_touching_data(fields, kind):
    with pytest.raises(ImageRejected) as info:
        image_to_mask(UntouchableData(is_bigendian=False, **fields), 4096 * 4096)
    assert info.value.kind == kind


def test_truncated_data_rejected():
    with pytest.raises(ImageRejected, match="data length"):
        image_to_mask(image(4, 4, "mono8", bytes(15)), 100)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 70), st.integers(0, 70), st.sampled_from(["mono8", "mono16", "rgb8", "bgra8", "yuv422", ""]),
       st.integers(0, 300), st.binary(max_size=5000), st.booleans())
def test_random_images_either_convert_or_are_rejected(height, width, encoding, step, data, bigendian):
    msg = image(height, width, encoding, data, step=step, bigendian=bigendian)
    try:
        mask = image_to_mask(msg, 64 * 64)
    except ImageRejected:
        return
    assert mask.shape == (height, width) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}


def test_mono8_levels_kept_without_threshold():
    """threshold None (models of grey masks): the levels as they are, row padding dropped."""
    data = np.array([[0, 1, 127, 128, 254, 255, 7, 7], [255, 64, 0, 200, 3, 129, 7, 7]], np.uint8)
    mask = image_to_mask(image(2, 6, "mono8", data.tobytes(), step=8), 100, None)
    assert mask.dtype == np.uint8 and mask.tolist() == data[:, :6].tolist()
    assert image_to_mask(image(2, 6, "8UC1", data.tobytes(), step=8), 100, None).tolist() == data[:, :6].tolist()
    # thresholded at the default, the levels are the binary mask
    binary = image_to_mask(image(2, 6, "mono8", data.tobytes(), step=8), 100)
    assert np.array_equal(np.where(mask > 127, 255, 0), binary)


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_levels_are_scaled_to_8_bit(bigendian):
    values = np.array([[0, 256, 257, 127 * 257, 128 * 257 - 1, 128 * 257, 200 * 257 + 100, 65535]],
                      ">u2" if bigendian else "<u2")
    mask = image_to_mask(image(1, 8, "mono16", values.tobytes(), bigendian=bigendian), 100, None)
    assert mask.dtype == np.uint8 and mask.tolist() == [[0, 0, 1, 127, 127, 128, 200, 255]]
    # a mono8 mask stored as mono16 (level * 257, as_mono16 in the training tests) keeps its levels exactly
    levels = np.arange(256, dtype=np.uint8)[None]
    wide = (levels.astype("<u2") * 257).astype(">u2" if bigendian else "<u2")
    assert image_to_mask(image(1, 256, "16UC1", wide.tobytes(), bigendian=bigendian), 256 * 256, None).tolist() == \
        levels.tolist()


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_levels_are_the_brightest_channel(encoding):
    channels = 4 if encoding.endswith("a8") else 3
    data = np.zeros((1, 3, channels), np.uint8)
    data[0, 0, 0], data[0, 1, 1], data[0, 1, 2], data[0, 2, 2] = 90, 30, 170, 255
    if channels == 4:
        data[0, :, 3] = 250  # alpha is no level
    assert image_to_mask(image(1, 3, encoding, data.tobytes()), 100, None).tolist() == [[90, 170, 255]]


@pytest.mark.parametrize("fields,kind", [
    (dict(height=100_000, width=100_000, encoding="mono8", step=100_000), "too_large"),
    (dict(height=1, width=20_000, encoding="mono8", step=20_000), "too_large"),
    (dict(height=10, width=10, encoding="32FC1", step=40), "encoding"),
    (dict(height=10, width=10, encoding="rgb8", step=10), "malformed"),
    (dict(height=0, width=10, encoding="mono8", step=10), "empty"),
])
def test_without_threshold_bad_headers_are_still_rejected_before_touching_data(fields, kind):
    with pytest.raises(ImageRejected) as info:
        image_to_mask(UntouchableData(is_bigendian=False, **fields), 4096 * 4096, None)
    assert info.value.kind == kind
    with pytest.raises(ImageRejected, match="data length"):
        image_to_mask(image(4, 4, "mono8", bytes(15)), 100, None)


@st.composite
def mostly_valid_images(draw):
    """Images whose header mostly fits their data (random ones are nearly always rejected), with
    padded rows, either endianness, and now and then a wrong step, length or encoding."""
    encoding = draw(st.sampled_from(["mono8", "8UC1", "mono16", "16UC1", "rgb8", "bgra8", "yuv422"]))
    depth = {"mono16": 2, "16UC1": 2, "rgb8": 3, "bgra8": 4}.get(encoding, 1)
    height, width = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    step = width * depth + draw(st.integers(-1, 3))
    size = max(step, 0) * height + draw(st.sampled_from([0, 0, 0, -1, 5]))
    data = draw(st.binary(min_size=max(size, 0), max_size=max(size, 0)))
    return image(height, width, encoding, data, step=step, bigendian=draw(st.booleans()))


@settings(max_examples=300, deadline=None)
@given(mostly_valid_images())
def test_random_images_give_levels_exactly_when_they_give_a_mask(msg):
    """Keeping levels rejects exactly what thresholding rejects, for the same reason; 8-bit levels
    thresholded at 127 are the default mask, 16-bit ones are the value // 257."""
    try:
        binary = image_to_mask(msg, 64 * 64)
    except ImageRejected as rejected:
        if rejected.kind == "empty":  # nothing above the threshold: the levels may still hold faint pixels
            try:
                assert image_to_mask(msg, 64 * 64, None).max() <= 127
            except ImageRejected as again:
                assert again.kind == "empty"
            return
        with pytest.raises(ImageRejected) as again:
            image_to_mask(msg, 64 * 64, None)
        assert (again.value.kind, str(again.value)) == (rejected.kind, str(rejected))
        return
    levels = image_to_mask(msg, 64 * 64, None)
    assert levels.shape == (msg.height, msg.width) and levels.dtype == np.uint8
    if msg.encoding in ("mono16", "16UC1"):
        rows = np.frombuffer(msg.data[: msg.step * msg.height], np.uint8).reshape(msg.height, msg.step)
        values = np.ascontiguousarray(rows[:, : 2 * msg.width]).view(">u2" if msg.is_bigendian else "<u2")
        assert np.array_equal(levels, values // 257)
        assert np.array_equal(binary, np.where(values > 127 * 257, 255, 0))
    else:
        assert np.array_equal(np.where(levels > 127, 255, 0), binary)


def test_a_model_with_broken_weights_is_refused_at_load(tmp_path):
    """NaN weights (a diverged run exported anyway) once gave 'jelly' with NaN parameters, published as valid."""
    path = build_clip_model(tmp_path / "m.onnx")
    model = onnx.load(str(path))
    weights = next(t for t in model.graph.initializer if t.data_type == onnx.TensorProto.FLOAT and len(t.dims) == 2)
    weights.CopyFrom(onnx.numpy_helper.from_array(np.full(tuple(weights.dims), np.nan, np.float32), weights.name))
    onnx.save(model, str(path))
    with pytest.raises(ModelError, match=r"m.onnx: output '\w+' is not finite \(NaN or inf\) in the trial run, so "
                                         r"its weights are broken; re-export"):
        EstimatorModel.load(path)


def test_no_estimate_is_made_of_outputs_that_are_not_finite(tmp_path):
    """Outputs that turn NaN for some inputs only (the all-zero trial run at load passes): an error, not an
    estimate. A real graph: the clip model's logits plus log(0.01 - mean mask), NaN once a mask covers
    more than 1% of the clip."""
    path = build_clip_model(tmp_path / "m.onnx")
    graph = onnx.load(str(path))
    producer = next(n for n in graph.graph.node if "logits" in n.output)
    producer.output[list(producer.output).index("logits")] = "logits_raw"
    size = 25 * 32 * 32
    graph.graph.initializer.extend([
        onnx.numpy_helper.from_array(np.full((size, 1), 1.0 / size, np.float32), "mean_weights"),
        onnx.numpy_helper.from_array(np.array(0.01, np.float32), "covered_limit")])
    graph.graph.node.extend([
        onnx.helper.make_node("Flatten", ["masks"], ["all_pixels"], axis=1),
        onnx.helper.make_node("MatMul", ["all_pixels", "mean_weights"], ["mean_mask"]),
        onnx.helper.make_node("Sub", ["covered_limit", "mean_mask"], ["headroom"]),
        onnx.helper.make_node("Log", ["headroom"], ["log_headroom"]),
        onnx.helper.make_node("Add", ["logits_raw", "log_headroom"], ["logits"])])
    onnx.save(graph, str(path))
    model = EstimatorModel.load(path)  # the trial run's zeros give finite outputs
    masks = falling_masks(25, size=32)
    with pytest.raises(ValueError, match=r"m.onnx: the model's outputs are not finite \(NaN or inf\) for these 25 "
                                         r"frames, so there is no estimate"):
        model.predict(np.stack([model.encode(m) for m in masks]), np.ones(25, bool))


# --------------------------------------------------------------------------- mutation-testing audit


def test_an_estimate_reads_the_head_outputs_as_the_metadata_contract_says(tmp_path):
    """With all-zero features the test model's head gives its bias: logits, params (through a sigmoid) and
    params_logvar are known numbers, and the estimate follows from them by hand: probabilities the softmax
    of the logits, each parameter denormalised over its range (log for E and yield), each sigma
    exp(logvar / 2) in normalised units, taken to SI by the range's derivative (docs/architecture.md)."""
    from onnx import numpy_helper

    path = build_clip_model(tmp_path / "m.onnx")
    bias = next(numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer
                if t.name == "b_head").astype(np.float64)
    logits, u, logvar = bias[:3], 1 / (1 + np.exp(-bias[3:7])), bias[7:11]
    est = EstimatorModel.load(path).predict(np.zeros((5, 32, 32), np.float32), np.ones(5, bool))
    expected_p = np.exp(logits) / np.exp(logits).sum()
    np.testing.assert_allclose(est.probabilities, expected_p, rtol=1e-5)
    sigma_u = np.exp(logvar / 2)  # a standard deviation: the square root of the variance
    e = 1.5e4 * 100.0 ** u[0]
    nu = 0.2 + 0.28 * u[1]
    y = 500.0 * 50.0 ** u[2]
    phi = math.radians(10) + math.radians(35) * u[3]
    np.testing.assert_allclose(est.raw_parameters, [e, nu, y, phi], rtol=1e-5)
    np.testing.assert_allclose(est.raw_uncertainties, [e * math.log(100.0) * sigma_u[0], 0.28 * sigma_u[1],
                                                       y * math.log(50.0) * sigma_u[2],
                                                       math.radians(35) * sigma_u[3]], rtol=1e-4)


def test_denormalise_clamps_outputs_outside_the_range_to_its_ends():
    from ad_estimator.model import ParameterRange

    for rng in (ParameterRange(1.5e4, 1.5e6, "log"), ParameterRange(0.2, 0.48, "linear")):
        assert rng.denormalise(np.array(1.3)) == pytest.approx(rng.high, rel=1e-12)
        assert rng.denormalise(np.array(-0.2)) == pytest.approx(rng.low, rel=1e-12)
    assert ParameterRange(1.5e4, 1.5e6, "log").denormalise(np.array(0.5)) == pytest.approx(1.5e5)


def test_softmax_of_large_logits_is_finite():
    from ad_estimator.model import softmax

    np.testing.assert_allclose(softmax(np.array([1000.0, 0.0, -1000.0])), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(softmax(np.array([801.0, 800.0])), [math.e / (1 + math.e), 1 / (1 + math.e)])


@pytest.mark.parametrize("spec", [[0.0, 1.0, "log"], [-1.0, 1.0, "log"], [1.0, 1.0, "linear"], [2.0, 1.0, "linear"],
                                  [1.0, 2.0, "ln"]])
def test_a_parameter_range_without_a_scale_it_can_have_is_refused(spec):
    import json
    from pathlib import Path

    from ad_estimator.model import parse_metadata
    from estimator_models import PARAMETER_RANGES, metadata

    meta = metadata("clip", "m", (32, 32), 25, None)
    meta["ad.parameter_ranges"] = json.dumps({**PARAMETER_RANGES, "yield_stress": spec})
    with pytest.raises(ModelError, match="bad range for yield_stress"):
        parse_metadata(meta, Path("m.onnx"))


def test_object_extent_counts_whole_simulator_pixels():
    mask = np.zeros((128, 128), np.uint8)
    mask[10:50, 20:40] = 255  # 40 x 20 simulator pixels
    assert object_extent(mask) == 40 / 128
    dot = np.zeros((128, 128), np.uint8)
    dot[64, 64] = 255
    assert object_extent(dot) == 1 / 128
    # A coverage (grey) mask of the simulator's size: its edge pixels count from half covered on.
    grey = mask.copy()
    grey[9, 20:40] = grey[50, 20:40] = 100  # under half: not the object
    assert object_extent(grey) == 40 / 128
    grey[9, 20:40] = grey[50, 20:40] = 200
    assert object_extent(grey) == 42 / 128


def test_unobserved_slots_reach_the_graph_as_zeros(tmp_path):
    """The head sees zeros, not the caller's leftovers, at invalid slots and past the slots given."""
    model = EstimatorModel.load(build_clip_model(tmp_path / "m.onnx"))
    session, feeds = model._session, []

    class Recording:
        def run(self, names, given, options=None):
            feeds.append(given)
            return session.run(names, given, options)

    model._session = Recording()
    features = np.full((12, 32, 32), 0.5, np.float32)
    valid = np.ones(12, bool)
    valid[[3, 7]] = False
    features[[3, 7]] = 7.0
    model.predict(features, valid)
    (fed,) = feeds
    assert fed["masks"].shape == (1, 25, 32, 32) and fed["valid"].shape == (1, 25)
    np.testing.assert_array_equal(fed["valid"][0], np.r_[valid, np.zeros(13, bool)].astype(np.float32))
    assert (fed["masks"][0, [3, 7]] == 0).all() and (fed["masks"][0, 12:] == 0).all()
    assert (fed["masks"][0, valid.nonzero()[0]] == 0.5).all()
