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
        ({"shape": "teapot-x"}, r"entry 1 \('teapot-x'\): field 'shape': unknown shape"),
        ({"material": "rubber"}, r"entry 1 \('sphere'\): field 'material': unknown material"),
        ({"parameters": {**GOOD["parameters"], "stiffness": 1.0}}, r"entry 1 \('sphere'\): field 'parameters.stiffness': unknown parameter"),
        ({"parameters": {**GOOD["parameters"], "friction_angle": 0.3}}, r"field 'parameters.friction_angle': plasticine has no such parameter"),
        ({"parameters": {**GOOD["parameters"], "youngs_modulus": 1e7}}, r"field 'parameters.youngs_modulus': 10000000.0 is outside"),
        ({"parameters": {"youngs_modulus": 1e5, "poissons_ratio": 0.4}}, r"field 'parameters': missing \['yield_stress'\]"),
        ({"material": "sand", "parameters": {"friction_angle": 30.0}}, r"parameters.friction_angle': 30.0 is outside .* \(radians\)"),
        ({"material": "sand", "parameters": {"friction_angle": 0.5, "youngs_modulus": 2e5}}, r"sand fixes it at 100000.0"),
        ({"seed": -1}, r"field 'seed': expected an integer"),
        ({"views": 0}, r"field 'views': expected an integer in \[1, 16\], got 0"),
        ({"views": 100000000}, r"field 'views': expected an integer in \[1, 16\], got 100000000"),  # failed later, out of memory
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
    with pytest.raises(ValueError, match=r"entry 0 \('sphere'\): missing field 'parameters'"):
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


@pytest.mark.parametrize("episode_id", ["two\nlines", "tab\there", "bell\x07", "zero\u200bwidth", "line\u2028break",
                                        "lone\ud800surrogate"])
def test_episode_ids_with_control_or_invisible_characters_are_refused(tmp_path, episode_id):
    """They were taken, and broke the node's one-line episode logs and the bag's metadata; the error is one line."""
    from ad_sim.instances import write_instance_file

    path = tmp_path / "ids.json"
    path.write_text(json.dumps([GOOD, GOOD | {"episode_id": episode_id, "seed": 2}]))
    with pytest.raises(ValueError, match=r"ids.json: entry 1 \('sphere'\): field 'episode_id': expected one line of "
                                         r"printable characters") as caught:
        load_instance_file(path)
    assert "\n" not in str(caught.value) and str(caught.value).endswith(f"got {episode_id!r}")
    bad = Instance(episode_id=episode_id, split="custom", shape="box", material="jelly",
                   parameters={"youngs_modulus": 1e5, "poissons_ratio": 0.3}, seed=1)
    with pytest.raises(ValueError, match=r"\(not written\): entry 0 \('box'\): field 'episode_id'"):
        write_instance_file([bad], tmp_path / "out.yaml")


def test_drawn_per_family_is_seeded_capped_and_in_benchmark_order():
    from ad_sim.instances import benchmark, drawn_per_family

    pool = [i.episode_id for i in benchmark("tiny", "unseen")]
    drawn = drawn_per_family("tiny", "unseen", 1, seed=3)
    assert [i.material for i in drawn] == ["jelly", "plasticine", "sand"]
    assert [i.episode_id for i in drawn] == [i.episode_id for i in drawn_per_family("tiny", "unseen", 1, seed=3)]
    every = drawn_per_family("tiny", "unseen", 10**6, seed=0, families=("sand",))
    ids = [i.episode_id for i in every]
    assert ids == [e for e in pool if "-sand-" in e]  # all of the family, in benchmark order


# ------------------------------------------------------------- instance files written by hand (audit)

SOFT = "shape: sphere, material: jelly, parameters: {youngs_modulus: 1.0e+5, poissons_ratio: 0.3}"


@pytest.mark.parametrize(
    "name, text, message",
    [
        # a key given twice was silently the last one
        ("twice.yaml", "- {shape: sphere, material: jelly, parameters: {youngs_modulus: 1.0e+5, poissons_ratio: 0.3, "
         "poissons_ratio: 0.25}, seed: 1}\n", r"entry 0 \('sphere'\): field 'parameters.poissons_ratio': given twice"),
        ("twice.yaml", f"- {{{SOFT}, seed: 1}}\n- {{{SOFT}, seed: 2, seed: 3}}\n", r"entry 1 \('sphere'\): field 'seed': given twice"),
        ("twice.json", json.dumps([GOOD])[:-2] + ', "seed": 5}]', r"entry 0 \('sphere'\): field 'seed': given twice"),
        ("twice.json", '[{"shape": "sphere", "material": "jelly", "parameters": {"youngs_modulus": 1e5, '
         '"poissons_ratio": 0.3, "poissons_ratio": 0.25}, "seed": 1}]', r"field 'parameters.poissons_ratio': given twice"),
        # YAML 1.1 reads 010 as 8 and 1:30 as 90: silently another seed than the one written
        ("octal.yaml", f"- {{{SOFT}, seed: 010}}\n", r"octal.yaml: not valid YAML: '010' is read by YAML 1.1 as the octal number 8 .* at line 1, column"),
        ("base60.yaml", f"- {{{SOFT}, seed: 1:30}}\n", r"base60.yaml: not valid YAML: .*1:30.* base 60 .*90.* at line 1"),
        ("base60.yaml", f"- {{{SOFT}, seed: 1, views: 1:00.5}}\n", r"not valid YAML: .*1:00.5.* base 60"),
        # near misses name what was probably meant
        ("near.yaml", f"- {{{SOFT.replace('sphere', 'spher')}, seed: 1}}\n", r"unknown shape 'spher'.*did you mean 'sphere'"),
        ("near.yaml", f"- {{{SOFT.replace('jelly', 'Jelly')}, seed: 1}}\n", r"unknown material 'Jelly'.*did you mean 'jelly'"),
        ("near.yaml", f"- {{{SOFT.replace('youngs_modulus', 'youngs_modulous')}, seed: 1}}\n",
         r"field 'parameters.youngs_modulous': unknown parameter.*did you mean 'youngs_modulus'"),
        ("near.yaml", f"- {{{SOFT}, sead: 1}}\n", r"unknown field\(s\) \['sead'\].*did you mean 'seed'"),
        ("near.yaml", f"- {{{SOFT}, seed: 1, split: Train}}\n", r"field 'split'.*got 'Train'.*did you mean 'train'"),
        # degrees where radians are expected
        ("degrees.yaml", "- {shape: box, material: sand, parameters: {friction_angle: 30}, seed: 1}\n",
         r"friction_angle': 30 is outside .*\(radians\); 30 degrees is 0.5236 rad"),
        # keys of mixed types were a TypeError traceback (sorting 1 and 'colour')
        ("mixed.yaml", f"- {{{SOFT}, seed: 1, 1: x, colour: red}}\n", r"entry 0 \('sphere'\): unknown field\(s\) \[1, 'colour'\]"),
        ("mapping.yaml", "shape: sphere\nmaterial: jelly\nparameters: {youngs_modulus: 1.0e+5, poissons_ratio: 0.3}\nseed: 1\n", r"non-empty list .*got a mapping \(write one entry as a list of one"),
        # pose and velocity are not fields: they come from the seed
        ("pose.yaml", f"- {{{SOFT}, seed: 1, velocity: [0, 0, -1]}}\n", r"unknown field\(s\) \['velocity'\].*drawn from 'seed'"),
    ],
)
def test_hand_written_mistakes_are_one_line_errors(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as caught:
        load_instance_file(path)
    assert "\n" not in str(caught.value) and str(path) in str(caught.value)


PARAMETERS = "parameters: {youngs_modulus: 1.0e+5, poissons_ratio: 0.3}"


@pytest.mark.parametrize(
    "text, shown",
    [
        # the shape names the entry in every error of it
        (f'- {{shape: "sph\\nere", material: jelly, {PARAMETERS}, seed: 1}}\n',
         r"entry 0 ('sph\nere'): field 'shape': unknown shape 'sph\nere'"),
        (f'- {{shape: sphere, material: jelly, {PARAMETERS}, "x\\ny": 1, "x\\ny": 2, seed: 1}}\n',
         r"entry 0 ('sphere'): field 'x\ny': given twice"),
        ('- {shape: sphere, material: jelly, parameters: {"a\\nb": 1, "a\\nb": 2}, seed: 1}\n',
         r"field 'parameters.a\nb': given twice"),
        ('- {shape: sphere, material: jelly, parameters: {"youngs\\nmodulus": 1.0e+5}, seed: 1}\n',
         r"field 'parameters.youngs\nmodulus': unknown parameter"),
        (f'- {{shape: sphere, material: jelly, {PARAMETERS}, seed: !!int "1:30\\n"}}\n',
         r"not valid YAML: '1:30\n' is read by YAML 1.1 as the base 60 number 90"),
    ],
    ids=["shape", "field-twice", "parameter-twice", "unknown-parameter", "tagged-number"],
)
def test_text_from_the_file_is_escaped_in_its_one_line_errors(tmp_path, text, shown):
    """A newline in a shape, a field name or a number's text split the error in two lines."""
    path = tmp_path / "newlines.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as caught:
        load_instance_file(path)
    assert "\n" not in str(caught.value), str(caught.value)
    assert shown in str(caught.value)


def test_yaml_merge_keys_and_plain_numbers_still_load(tmp_path):
    path = tmp_path / "anchors.yaml"
    path.write_text(f"- &soft {{{SOFT}, seed: 1}}\n- {{<<: *soft, seed: 2, episode_id: '10:30'}}\n- {{<<: *soft, seed: 0}}\n"
                    f"- {{<<: *soft, seed: 0x10, views: 2}}\n")
    instances = load_instance_file(path)
    assert [(i.seed, i.views) for i in instances] == [(1, 1), (2, 1), (0, 1), (16, 2)]
    assert instances[1].episode_id == "10:30" and instances[1].parameters == instances[0].parameters


def test_yaml_syntax_error_is_one_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("- {shape: sphere, material: jelly, seed: 1\n  : x\n")
    with pytest.raises(ValueError, match=r"broken.yaml: not valid YAML: expected ',' or '}', but got ':' at line 2") as caught:
        load_instance_file(path)
    assert "\n" not in str(caught.value)


def test_duplicate_ids_name_both_entries(tmp_path, monkeypatch):
    from ad_sim import instances as library

    path = tmp_path / "many.json"
    path.write_text(json.dumps([{"episode_id": f"e{i}"} for i in range(1000)] + [{"episode_id": "e7"}]))
    # only the file-level checks: each entry becomes a stand-in with its id
    monkeypatch.setattr(library, "instance_from_entry", lambda entry, index, source: type("I", (), entry)())
    with pytest.raises(ValueError, match=r"duplicate episode_id 'e7' in entries 7 and 1000"):
        load_instance_file(path)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_written_instance_files_read_back_bit_exactly(tmp_path, suffix):
    from ad_sim.instances import write_instance_file

    originals = benchmark("tiny", "unseen") + benchmark("tiny", "train")
    edge = Instance(episode_id="é 🍮 yes", split="custom", shape="box", material="jelly",
                    parameters={"youngs_modulus": 1.5e6 * (1 + 1e-12), "poissons_ratio": 0.1 + 0.2}, seed=2**64 - 1, views=3)
    originals.append(edge)
    path = tmp_path / f"out{suffix}"
    write_instance_file(originals, path)
    again = load_instance_file(path)
    assert again == originals
    for a, b in zip(again, originals):
        assert [(k, v.hex()) for k, v in a.parameters.items()] == [(k, v.hex()) for k, v in b.parameters.items()]


def test_instance_files_are_read_as_utf8_whatever_the_locale(tmp_path):
    """Under a C locale (no UTF-8 mode) a valid UTF-8 file was refused as 'not UTF-8 text'."""
    import os
    import subprocess
    import sys

    path = tmp_path / "unicode.yaml"
    path.write_text(f"- {{{SOFT}, seed: 1, episode_id: 'gelée-🍮'}}\n", encoding="utf-8")
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
    code = "import sys; from ad_sim.instances import load_instance_file; print(ascii(load_instance_file(sys.argv[1])[0].episode_id))"
    done = subprocess.run([sys.executable, "-c", code, str(path)], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == ascii("gelée-🍮")


def test_an_instance_a_file_cannot_hold_is_not_written(tmp_path):
    from ad_sim.instances import write_instance_file

    stiff = Instance(episode_id="stiff", split="custom", shape="box", material="jelly",
                     parameters={"youngs_modulus": 1e7, "poissons_ratio": 0.3}, seed=1)
    path = tmp_path / "out.yaml"
    with pytest.raises(ValueError, match=r"out.yaml \(not written\): entry 1 \('box'\): field 'parameters.youngs_modulus'"):
        write_instance_file([make(1), stiff], path)
    assert not path.exists()


def test_written_ids_that_the_loader_reads_as_numbers_are_quoted(tmp_path):
    """The loader reads 1e5 (no sign in the exponent) as a float, PyYAML's dumper does not: an id like '1e5' was
    written unquoted and the file did not read back ("field 'episode_id': expected a non-empty string")."""
    from ad_sim.instances import write_instance_file

    originals = [Instance(episode_id=name, split="custom", shape="box", material="jelly",
                          parameters={"youngs_modulus": 1e5, "poissons_ratio": 0.3}, seed=i)
                 for i, name in enumerate(["1e5", "2.5e3", "1_000E3", "-4e2", ".5e1", "10:30", "010", "yes"])]
    path = tmp_path / "ids.yaml"
    write_instance_file(originals, path)
    assert load_instance_file(path) == originals


# ------------------------------------------------------------------------- mutation-testing audit


def test_benchmark_instances_are_those_the_committed_sample_bag_recorded():
    """bags/samples/unseen-masks-0of1 is `generate --size tiny --split unseen` (bags/samples/make.sh): its
    recorded instances pin down what a benchmark is (seeds, parameters, pose, velocity), so that a change to
    how seeds or draws are made, which silently moves every benchmark, fails here."""
    from pathlib import Path

    from ad_sim.rosbag import BagReader, group_episodes

    bag = Path(__file__).resolve().parents[1] / "bags" / "samples" / "unseen-masks-0of1"
    recorded = [e.instance for e in group_episodes(BagReader(bag, topics=["/ad_sim/instance"]))]
    expected = benchmark("tiny", "unseen")
    assert [r.episode_id for r in recorded] == [i.episode_id for i in expected]
    for r, instance in zip(recorded, expected):
        assert r.seed == instance.seed and r.material == instance.material and r.shape == instance.shape
        assert dict(zip(r.parameter_names, r.parameters)) == instance.parameters
        pose, velocity = r.initial_pose, r.initial_velocity.linear
        assert (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w) == instance.orientation
        assert (pose.position.x, pose.position.y, pose.position.z) == tuple(instance.position())
        assert (velocity.x, velocity.y, velocity.z) == instance.velocity


def test_horizontal_velocity_is_uniform_over_the_disc():
    """Uniform over the disc of radius HORIZONTAL_SPEED: a quarter of the speeds lie below half of it (a
    uniform speed would put half there), E[speed^2] = HORIZONTAL_SPEED^2 / 2, and every heading alike."""
    from ad_sim.instances import HORIZONTAL_SPEED

    velocities = np.array([make(seed).velocity for seed in range(4000)])
    speed = np.hypot(velocities[:, 0], velocities[:, 1])
    assert speed.max() <= HORIZONTAL_SPEED
    assert np.mean(speed <= HORIZONTAL_SPEED / 2) == pytest.approx(0.25, abs=0.03)
    assert np.mean(speed**2) == pytest.approx(HORIZONTAL_SPEED**2 / 2, rel=0.05)
    assert np.abs(velocities[:, :2].mean(axis=0)).max() < 0.01


@pytest.mark.parametrize("shape", ["hammer", "cone", "torus"])
def test_drop_pose_centres_the_objects_bounding_box_at_the_jittered_middle(shape):
    """XY_JITTER: the centre of the object's (posed) bounding box is within +-XY_JITTER of the domain's
    middle, exactly at 0.5 + jitter wherever the walls leave room for it there."""
    from ad_sim.instances import XY_JITTER

    vertices = np.asarray(shapes.load_mesh(shape).vertices)
    unclipped = 0
    for seed in range(20):
        instance = make(seed, shape)
        pose = instance.pose()
        posed = SCALE * vertices @ pose[:3, :3].T + pose[:3, 3]
        low, high = posed[:, :2].min(axis=0), posed[:, :2].max(axis=0)
        centre, target, half = (low + high) / 2, 0.5 + np.array(instance.jitter), (high - low) / 2
        assert np.all(np.abs(centre - 0.5) <= XY_JITTER + 1e-9)
        room = (target - half >= BOUNDARY + WALL_MARGIN) & (target + half <= 1 - BOUNDARY - WALL_MARGIN)
        np.testing.assert_allclose(centre[room], target[room], atol=1e-9)
        unclipped += room.sum()
    assert unclipped > 20  # the exact case was checked


def test_drawn_per_family_keeps_benchmark_order_within_each_family():
    from ad_sim.instances import drawn_per_family

    pool = [i.episode_id for i in benchmark("small", "unseen")]
    for seed in range(3):
        drawn = [i.episode_id for i in drawn_per_family("small", "unseen", 6, seed=seed)]
        assert len(drawn) == 18 and len(set(drawn)) == 18
        for family in materials.FAMILIES:
            of_family = [e for e in drawn if f"-{family}-" in e]
            assert len(of_family) == 6 and of_family == sorted(of_family, key=pool.index), (seed, family)
