"""Instances: reproducible from their seed, benchmark sizes and seeds, instance file validation."""

import json
import math

import numpy as np
import pytest

from ad_sim import materials, shapes
from ad_sim.instances import (
    BENCHMARK_SIZES,
    BOUNDARY,
    DROP_GAP,
    SCALE,
    WALL_MARGIN,
    Instance,
    benchmark,
    instance_seed,
    load_instance_file,
)


def make(seed: int, shape: str = "sphere", material: str = "jelly") -> Instance:
    parameters = materials.sample_parameters(material, np.random.default_rng(seed))
    return Instance(episode_id=f"custom-{seed}", split="custom", shape=shape, material=material, parameters=parameters, seed=seed)


def test_instance_is_reproduced_by_its_seed():
    a, b, c = make(7), make(7), make(8)
    assert a == b
    for name in ("orientation", "drop_gap", "jitter", "velocity", "camera_seed", "sampling_seed"):
        assert getattr(a, name) == getattr(b, name)
        assert getattr(a, name) != getattr(c, name)
    np.testing.assert_array_equal(a.pose(), b.pose())
    for x, y in zip(a.cameras(3), b.cameras(3)):
        np.testing.assert_array_equal(x.pose, y.pose)
    # Asking for more views keeps the first ones.
    np.testing.assert_array_equal(a.cameras(1)[0].pose, a.cameras(4)[0].pose)


def test_orientations_are_uniform_rotations():
    rotations = np.stack([make(seed).rotation() for seed in range(2000)])
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    # A uniform rotation sends any axis to a uniform direction: mean ~ 0, E[z^2] = 1/3.
    z = rotations[:, :, 2]
    assert np.all(np.abs(z.mean(axis=0)) < 0.06)
    assert np.all(np.abs((z**2).mean(axis=0) - 1 / 3) < 0.03)


@pytest.mark.parametrize("shape", ["sphere", "box", "torus", "cone", "hammer"])
def test_drop_pose_is_above_the_ground_and_inside_the_walls(shape):
    vertices = np.asarray(shapes.load_mesh(shape).vertices)
    for seed in range(20):
        instance = make(seed, shape)
        pose = instance.pose()
        posed = SCALE * vertices @ pose[:3, :3].T + pose[:3, 3]
        gap = posed[:, 2].min() - BOUNDARY
        assert DROP_GAP[0] <= instance.drop_gap <= DROP_GAP[1]
        # The drawn gap, unless the top would reach the ceiling's boundary layer.
        top_room = 1 - 2 * BOUNDARY - WALL_MARGIN - np.ptp(posed[:, 2])
        assert gap == pytest.approx(min(instance.drop_gap, top_room))
        assert gap > 0.02 and posed[:, 2].max() <= 1 - BOUNDARY - WALL_MARGIN + 1e-9
        assert posed[:, :2].min() >= BOUNDARY + WALL_MARGIN - 1e-9
        assert posed[:, :2].max() <= 1 - BOUNDARY - WALL_MARGIN + 1e-9
        vx, vy, vz = instance.velocity
        assert vz <= 0 and math.hypot(vx, vy) <= 0.2


def test_paper_benchmark_counts_and_seeds():
    splits = {split: benchmark("paper", split) for split in ("train", "seen", "unseen")}
    assert {s: len(v) for s, v in splits.items()} == {"train": 9000, "seen": 900, "unseen": 900}
    seeds = [i.seed for v in splits.values() for i in v]
    assert len(set(seeds)) == len(seeds)
    ids = [i.episode_id for v in splits.values() for i in v]
    assert len(set(ids)) == len(ids)
    train_shapes = {i.shape for i in splits["train"]}
    assert train_shapes == {i.shape for i in splits["seen"]}
    assert not train_shapes & {i.shape for i in splits["unseen"]}
    assert len(train_shapes) == 30
    assert {i.views for i in splits["train"]} == {4} and {i.views for i in splits["unseen"]} == {1}
    for instance in splits["seen"]:
        for name, value in instance.parameters.items():
            spec = materials.FAMILY_RANGES[instance.material][name]
            if isinstance(spec, tuple):
                assert spec[0] <= value <= spec[1]
            else:
                assert value == spec
    # Seen-test instances draw new parameters, not those of the training instances.
    def sampled(split):
        return {(i.material, v) for i in splits[split] for n, v in i.parameters.items() if n in materials.SAMPLED_PARAMETERS[i.material]}

    assert not sampled("train") & sampled("seen")


def test_small_and_tiny_benchmarks_are_deterministic_and_nested():
    for size, expected in (("small", {"train": 360, "seen": 90, "unseen": 90}), ("tiny", {"train": 6, "seen": 6, "unseen": 6})):
        for split, count in expected.items():
            assert len(benchmark(size, split)) == count
    tiny = benchmark("tiny", "unseen")
    assert tiny == benchmark("tiny", "unseen")
    # Seeds depend on (split, shape, family, index), not on the size: tiny is a subset of paper.
    paper = {i.episode_id: i for i in benchmark("paper", "unseen")}
    assert all(paper[i.episode_id] == i for i in tiny)
    assert benchmark("tiny", "unseen", base_seed=1)[0].seed != tiny[0].seed
    assert instance_seed("train", "sphere", "jelly", 0) == instance_seed("train", "sphere", "jelly", 0)
    assert sorted(BENCHMARK_SIZES) == ["paper", "small", "tiny"]
    with pytest.raises(ValueError, match="unknown benchmark size"):
        benchmark("huge", "train")


def test_instance_file_yaml_and_json(tmp_path):
    path = tmp_path / "instances.yaml"
    path.write_text(
        "- shape: sphere\n  material: jelly\n  parameters: {youngs_modulus: 1.5e6, poissons_ratio: 0.2}\n  seed: 7\n"
        "- {shape: box, material: sand, parameters: {friction_angle: 0.5}, seed: 8, views: 2}\n"
    )
    first, second = load_instance_file(path)
    assert (first.shape, first.material, first.seed, first.split, first.views) == ("sphere", "jelly", 7, "custom", 1)
    assert first.parameters == {"youngs_modulus": 1.5e6, "poissons_ratio": 0.2}
    assert second.parameters == {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "friction_angle": 0.5}
    assert second.views == 2 and first.episode_id != second.episode_id
    json_path = tmp_path / "instances.json"
    json_path.write_text(json.dumps([{"shape": "sphere", "material": "jelly", "parameters": first.parameters, "seed": 7}]))
    assert load_instance_file(json_path) == [first]


GOOD = {"shape": "sphere", "material": "plasticine", "parameters": {"youngs_modulus": 1e5, "poissons_ratio": 0.4, "yield_stress": 3000.0}, "seed": 1}


@pytest.mark.parametrize(
    "change, message",
    [
        ({"shape": "teapot-x"}, r"entry 1 \(teapot-x\): field 'shape': unknown shape"),
        ({"material": "rubber"}, r"entry 1 \(sphere\): field 'material': unknown material"),
        ({"parameters": {**GOOD["parameters"], "stiffness": 1.0}}, r"entry 1 \(sphere\): field 'parameters.stiffness': unknown parameter"),
        ({"parameters": {**GOOD["parameters"], "friction_angle": 0.3}}, r"field 'parameters.friction_angle': plasticine has no such parameter"),
        ({"parameters": {**GOOD["parameters"], "youngs_modulus": 1e7}}, r"field 'parameters.youngs_modulus': 10000000.0 is outside"),
        ({"parameters": {"youngs_modulus": 1e5, "poissons_ratio": 0.4}}, r"field 'parameters': missing \['yield_stress'\]"),
        ({"material": "sand", "parameters": {"friction_angle": 30.0}}, r"parameters.friction_angle': 30.0 is outside .* \(radians\)"),
        ({"material": "sand", "parameters": {"friction_angle": 0.5, "youngs_modulus": 2e5}}, r"sand fixes it at 100000.0"),
        ({"seed": -1}, r"field 'seed': expected an integer"),
        ({"views": 0}, r"field 'views': expected a positive integer"),
        ({"colour": "red"}, r"unknown field\(s\) \['colour'\]"),
        ({"seed": None}, r"field 'seed'"),
        # wrong types and huge ints were tracebacks (an unhashable list, a float overflow)
        ({"shape": ["sphere"]}, r"entry 1 \(\['sphere'\]\): field 'shape': unknown shape \['sphere'\]"),
        ({"material": ["jelly"]}, r"field 'material': unknown material \['jelly'\]"),
        ({"parameters": {**GOOD["parameters"], "youngs_modulus": 10**400}},
         r"field 'parameters.youngs_modulus': expected a finite number, got 1000"),
    ],
)
def test_instance_file_errors_name_entry_and_field(tmp_path, change, message):
    entry = {**GOOD, **change}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps([GOOD, entry]))
    with pytest.raises(ValueError, match=message):
        load_instance_file(path)


def test_instance_file_structure_errors(tmp_path):
    missing = tmp_path / "missing.yaml"
    missing.write_text("- {shape: sphere, material: jelly, seed: 1}\n")
    with pytest.raises(ValueError, match=r"entry 0 \(sphere\): missing field 'parameters'"):
        load_instance_file(missing)
    not_a_list = tmp_path / "dict.yaml"
    not_a_list.write_text("shape: sphere\n")
    with pytest.raises(ValueError, match="non-empty list"):
        load_instance_file(not_a_list)
    wrong_suffix = tmp_path / "instances.txt"
    wrong_suffix.write_text("[]")
    with pytest.raises(ValueError, match=r"\.yaml, \.yml or \.json"):
        load_instance_file(wrong_suffix)
    duplicate = tmp_path / "dup.json"
    duplicate.write_text(json.dumps([GOOD | {"episode_id": "a"}, GOOD | {"episode_id": "a", "seed": 2}]))
    with pytest.raises(ValueError, match="duplicate episode_id"):
        load_instance_file(duplicate)


def test_drawn_per_family_is_seeded_capped_and_in_benchmark_order():
    from ad_sim.instances import benchmark, drawn_per_family

    pool = [i.episode_id for i in benchmark("tiny", "unseen")]
    drawn = drawn_per_family("tiny", "unseen", 1, seed=3)
    assert [i.material for i in drawn] == ["jelly", "plasticine", "sand"]
    assert [i.episode_id for i in drawn] == [i.episode_id for i in drawn_per_family("tiny", "unseen", 1, seed=3)]
    every = drawn_per_family("tiny", "unseen", 10**6, seed=0, families=("sand",))
    ids = [i.episode_id for i in every]
    assert ids == [e for e in pool if "-sand-" in e]  # all of the family, in benchmark order
