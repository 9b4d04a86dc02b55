"""What to simulate: the Instance record, the benchmark splits (SPEC 7) and instance files (SPEC 4).

No ROS here. Everything random about an instance (pose, drop height, velocity, cameras,
particle sampling) comes from numpy Generator(PCG64(seed)), so an instance is reproduced
exactly from its fields. Benchmark seeds come from numpy SeedSequence over stable integer
codes (never Python's salted hash()), so benchmarks are identical on every machine.
"""

from __future__ import annotations

import functools
import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import materials, mpm
from .render import Camera, sample_cameras

SPLITS = ("train", "seen", "unseen", "custom")
BENCHMARK_SPLITS = ("train", "seen", "unseen")

# The normalised mesh ([-0.5, 0.5]^3, longest side 1) is scaled by SCALE into the unit-cube
# domain. At particle spacing dx/2 = 1/64 this gives ~9k particles for the sphere, ~16k for the
# box and 1-4k for most everyday objects (thin ones get a finer lattice, see episode.py). Any
# rotation of it (at most SCALE * sqrt(3) across) fits between the walls.
SCALE = 0.4
PARTICLE_SPACING = 0.5 * mpm.DX
# Ground and walls: the solver's boundary layer is BOUNDARY_CELLS grid cells thick on every side.
BOUNDARY = mpm.GROUND_Z
WALL_MARGIN = 0.02  # keep the object this far from the walls at t = 0
DROP_GAP = (0.05, 0.25)  # object's lowest point above the ground at t = 0 (less if the ceiling is near)
XY_JITTER = 0.1  # centre of the object within +-XY_JITTER of the domain's middle
HORIZONTAL_SPEED = 0.2  # m/s, largest initial horizontal speed
DOWNWARD_SPEED = (0.0, 0.5)  # m/s, initial downward speed

TRAIN_VIEWS = 4
EVALUATION_VIEWS = 1
# Most cameras an episode may have (instance files, `generate --views`, the sim node's `views`): four times the
# training rig. Each view is 25 renders, 400 KB of masks per episode and two more topics; a mistyped 100000000
# was taken and failed later, out of memory, when the cameras or the node's publishers were made.
MAX_VIEWS = 16

_SPLIT_CODES = {name: code for code, name in enumerate(SPLITS)}
_PARAMETER_STREAM = 1  # second PCG64 stream of a seed, for benchmark parameters


def _random_quaternion(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """Uniformly distributed rotation (Shoemake 1992), as (x, y, z, w)."""
    u1, u2, u3 = rng.uniform(0.0, 1.0, size=3)
    a, b = math.sqrt(1.0 - u1), math.sqrt(u1)
    return (
        a * math.sin(2 * math.pi * u2),
        a * math.cos(2 * math.pi * u2),
        b * math.sin(2 * math.pi * u3),
        b * math.cos(2 * math.pi * u3),
    )


def quaternion_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@functools.lru_cache(maxsize=None)
def _mesh_vertices(shape: str) -> np.ndarray:
    from .shapes import load_mesh

    return np.asarray(load_mesh(shape).vertices, dtype=np.float64)


@functools.lru_cache(maxsize=1)
def shape_names() -> frozenset[str]:
    from .shapes import list_shapes

    return frozenset(info.name for info in list_shapes())


@dataclass
class Instance:
    """One episode to simulate. Fields after `views` are drawn from `seed` at construction.

    Pose, velocity, cameras and particles depend on (shape, seed) only: the same instance with
    another material or parameters (re-simulation of a prediction) starts from the same state.
    """

    episode_id: str
    split: str  # train | seen | unseen | custom
    shape: str
    material: str
    parameters: dict[str, float]  # SI units, radians; the family's parameters incl. fixed ones
    seed: int
    views: int = 1
    orientation: tuple[float, float, float, float] = field(init=False)  # unit quaternion (x, y, z, w)
    drop_gap: float = field(init=False)  # lowest point above the ground at t = 0 (position() caps it)
    jitter: tuple[float, float] = field(init=False)  # x/y offset of the object's centre from the middle
    velocity: tuple[float, float, float] = field(init=False)  # initial velocity (m/s)
    camera_seed: int = field(init=False)
    sampling_seed: int = field(init=False)  # particle sampling and FPS start

    def __post_init__(self):
        rng = np.random.Generator(np.random.PCG64(self.seed))
        self.orientation = _random_quaternion(rng)
        self.drop_gap = float(rng.uniform(*DROP_GAP))
        self.jitter = tuple(float(v) for v in rng.uniform(-XY_JITTER, XY_JITTER, size=2))
        heading = rng.uniform(0.0, 2.0 * math.pi)
        speed = HORIZONTAL_SPEED * math.sqrt(rng.uniform(0.0, 1.0))  # uniform over the disc
        down = rng.uniform(*DOWNWARD_SPEED)
        self.velocity = (speed * math.cos(heading), speed * math.sin(heading), -down)
        self.camera_seed = int(rng.integers(0, 2**63))
        self.sampling_seed = int(rng.integers(0, 2**63))

    def rotation(self) -> np.ndarray:
        return quaternion_matrix(self.orientation)

    def position(self) -> np.ndarray:
        """World position of the scaled mesh's origin at t = 0 (loads the shape's mesh)."""
        posed = SCALE * _mesh_vertices(self.shape) @ self.rotation().T
        low, high = posed.min(axis=0), posed.max(axis=0)
        wall_low, wall_high = BOUNDARY + WALL_MARGIN, 1.0 - BOUNDARY - WALL_MARGIN
        origin = 0.5 + np.array(self.jitter) - 0.5 * (low[:2] + high[:2])  # puts the bounding box centre at 0.5 + jitter
        xy = np.clip(origin, wall_low - low[:2], wall_high - high[:2])
        # Tall poses get a smaller gap so that the top stays below the ceiling's boundary layer.
        gap = min(self.drop_gap, wall_high - BOUNDARY - (high[2] - low[2]))
        return np.array([xy[0], xy[1], BOUNDARY + gap - low[2]])

    def pose(self) -> np.ndarray:
        """(4, 4) transform from the scaled mesh frame to the world at t = 0."""
        transform = np.eye(4)
        transform[:3, :3] = self.rotation()
        transform[:3, 3] = self.position()
        return transform

    def cameras(self, views: int | None = None) -> list[Camera]:
        """The instance's cameras (128x128); the first k views do not depend on how many are asked."""
        rng = np.random.Generator(np.random.PCG64(self.camera_seed))
        return sample_cameras(rng, self.views if views is None else views)


# ---------------------------------------------------------------------------- benchmark


@dataclass(frozen=True)
class BenchmarkSize:
    """Instances per (shape, family) for each split, and how many shapes of each split list."""

    per_pair: dict[str, int]
    shapes: int | None  # first n shapes of each split list; None = all


# paper: SPEC 7 (9000 / 900 / 900). tiny: 6 episodes per split (2 shapes x 3 families), CI.
# small: 360 / 90 / 90 on all 60 shapes (4 training instances per (shape, family), one in each
# test split). On CPU an episode takes 2.5-6 s (one core, 25 frames, measured on small's splits),
# so small's 540 episodes generate in ~40 min on one core (two shards: ~20 min) and a student
# trains on them on 2 CPU cores within the hour.
BENCHMARK_SIZES = {
    "paper": BenchmarkSize({"train": 100, "seen": 10, "unseen": 10}, None),
    "small": BenchmarkSize({"train": 4, "seen": 1, "unseen": 1}, None),
    "tiny": BenchmarkSize({"train": 1, "seen": 1, "unseen": 1}, 2),
}


def instance_seed(split: str, shape: str, family: str, index: int, base_seed: int = 0) -> int:
    """Stable 63-bit seed of benchmark instance `index` of (split, shape, family)."""
    entropy = [base_seed, _SPLIT_CODES[split], zlib.crc32(shape.encode()), materials.FAMILY_CODES[family], index]
    low, high = np.random.SeedSequence(entropy).generate_state(2, dtype=np.uint32)
    return (int(high) << 32 | int(low)) & (2**63 - 1)


def benchmark_shapes(split: str, size: str) -> list[str]:
    """Shapes of a benchmark split: train shapes for train/seen, unseen shapes for unseen."""
    from .shapes import list_shapes

    names = [info.name for info in list_shapes("unseen" if split == "unseen" else "train")]
    limit = BENCHMARK_SIZES[size].shapes
    return names if limit is None else names[:limit]


def benchmark(size: str, split: str, base_seed: int = 0) -> list[Instance]:
    """The instances of a benchmark split, in a fixed order (shape, family, index)."""
    if size not in BENCHMARK_SIZES:
        raise ValueError(f"unknown benchmark size {size!r}; expected one of {sorted(BENCHMARK_SIZES)}")
    if split not in BENCHMARK_SPLITS:
        raise ValueError(f"unknown benchmark split {split!r}; expected one of {BENCHMARK_SPLITS}")
    count = BENCHMARK_SIZES[size].per_pair[split]
    views = TRAIN_VIEWS if split == "train" else EVALUATION_VIEWS
    out = []
    for shape in benchmark_shapes(split, size):
        for family in materials.FAMILIES:
            for index in range(count):
                seed = instance_seed(split, shape, family, index, base_seed)
                rng = np.random.Generator(np.random.PCG64([seed, _PARAMETER_STREAM]))
                out.append(
                    Instance(
                        episode_id=f"{split}-{shape}-{family}-{index:04d}",
                        split=split,
                        shape=shape,
                        material=family,
                        parameters=materials.sample_parameters(family, rng),
                        seed=seed,
                        views=views,
                    )
                )
    return out


# ------------------------------------------------------------------------ instance files

_REQUIRED_FIELDS = ("shape", "material", "parameters", "seed")
_OPTIONAL_FIELDS = ("views", "episode_id", "split")
# Relative slack on range checks so that values written with a few digits at a range's edge pass.
_RANGE_SLACK = 1e-9
# What an instance file cannot set: it is drawn from the seed (the hint of an unknown-field error).
_DRAWN_FROM_SEED = "pose, orientation, drop height, velocity, cameras and particles are drawn from 'seed'"


def _did_you_mean(value, choices) -> str:
    """' (did you mean 'x'?)' for the choice nearest to `value` (case ignored), or ''."""
    import difflib

    if not isinstance(value, str):
        return ""
    lowered = {str(c).lower(): c for c in choices}
    close = difflib.get_close_matches(value.lower(), list(lowered), n=1, cutoff=0.6)
    return f" (did you mean {lowered[close[0]]!r}?)" if close else ""


class _Mapping(dict):
    """A mapping read from an instance file; `repeated` names its keys written more than once (YAML and JSON
    keep the last one without a word)."""

    repeated: tuple = ()


def _json_object(pairs) -> _Mapping:
    out, repeated = _Mapping(), []
    for key, value in pairs:
        if key in out and key not in repeated:
            repeated.append(key)
        out[key] = value
    out.repeated = tuple(repeated)
    return out


def _check_repeated(mapping, where: str, prefix: str = "") -> None:
    repeated = getattr(mapping, "repeated", ())
    if repeated:
        raise ValueError(f"{where}: field {prefix + str(repeated[0])!r}: given twice in one mapping; give each field once")



def drawn_per_family(size: str, split: str, per_family: int, seed: int,
                     families=materials.FAMILIES) -> list[Instance]:
    """`per_family` instances of each family (at most all of them), drawn from a benchmark split by
    one generator seeded with `seed` across the families in order; each family's in benchmark order."""
    rng = np.random.default_rng(seed)
    pool = benchmark(size, split)
    chosen = []
    for family in families:
        of_family = [inst for inst in pool if inst.material == family]
        picks = rng.choice(len(of_family), size=min(per_family, len(of_family)), replace=False)
        chosen += [of_family[i] for i in sorted(picks)]
    return chosen

def _finite_number(value) -> bool:
    """An int or float that is finite as a float (an int too large for one overflows, and is no number here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _validate_parameters(family: str, given, where: str) -> dict[str, float]:
    if not isinstance(given, dict):
        raise ValueError(f"{where}: field 'parameters' must be a mapping of name -> value, got {given!r}")
    _check_repeated(given, where, "parameters.")
    ranges = materials.FAMILY_RANGES[family]
    out = {}
    for name, value in given.items():
        if name not in materials.PARAMETER_NAMES:
            raise ValueError(
                f"{where}: field {'parameters.' + str(name)!r}: unknown parameter{_did_you_mean(name, materials.PARAMETER_NAMES)}; "
                f"expected names from {materials.PARAMETER_NAMES}"
            )
        if name not in ranges:
            raise ValueError(
                f"{where}: field 'parameters.{name}': {family} has no such parameter; "
                f"it takes {list(materials.FAMILY_PARAMETERS[family])}"
            )
        if not _finite_number(value):
            raise ValueError(f"{where}: field 'parameters.{name}': expected a finite number, got {value!r}")
        spec = ranges[name]
        if isinstance(spec, tuple):
            low, high, _ = spec
            if not low * (1 - _RANGE_SLACK) <= value <= high * (1 + _RANGE_SLACK):
                unit = ""
                if name == "friction_angle":
                    unit = " (radians)"
                    if low <= math.radians(value) <= high:
                        unit += f"; {value} degrees is {math.radians(value):.4f} rad"
                raise ValueError(f"{where}: field 'parameters.{name}': {value} is outside {family}'s range [{low}, {high}]{unit}")
        elif not math.isclose(value, spec, rel_tol=1e-6):
            raise ValueError(f"{where}: field 'parameters.{name}': {family} fixes it at {spec}, got {value}")
        out[name] = float(value)
    missing = [n for n in materials.SAMPLED_PARAMETERS[family] if n not in out]
    if missing:
        raise ValueError(f"{where}: field 'parameters': missing {missing} (SI units, radians for friction_angle)")
    return materials.full_parameters(family, out)


def instance_from_entry(entry, index: int, source: str) -> Instance:
    where = f"{source}: entry {index}"
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: expected a mapping with fields {list(_REQUIRED_FIELDS)}, got {entry!r}")
    if "shape" in entry:  # as every text from the file, by repr: a newline in it split the one-line error
        where += f" ({entry['shape']!r})"
    _check_repeated(entry, where)
    allowed = _REQUIRED_FIELDS + _OPTIONAL_FIELDS
    unknown = sorted(set(entry) - set(allowed), key=str)
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown}{_did_you_mean(unknown[0], allowed)}; allowed: "
                         f"{list(allowed)} ({_DRAWN_FROM_SEED})")
    for name in _REQUIRED_FIELDS:
        if name not in entry:
            raise ValueError(f"{where}: missing field '{name}'")
    shape, material = entry["shape"], entry["material"]
    if not isinstance(shape, str) or shape not in shape_names():  # (a list is not even hashable)
        raise ValueError(f"{where}: field 'shape': unknown shape {shape!r}{_did_you_mean(shape, shape_names())}; "
                         "`generate --list-shapes` lists them")
    if not isinstance(material, str) or material not in materials.FAMILIES:
        raise ValueError(f"{where}: field 'material': unknown material {material!r}{_did_you_mean(material, materials.FAMILIES)}; "
                         f"expected one of {materials.FAMILIES}")
    seed = entry["seed"]
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**64:
        raise ValueError(f"{where}: field 'seed': expected an integer in [0, 2^64), got {seed!r}")
    views = entry.get("views", EVALUATION_VIEWS)
    if isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= MAX_VIEWS:
        raise ValueError(f"{where}: field 'views': expected an integer in [1, {MAX_VIEWS}], got {views!r}")
    split = entry.get("split", "custom")
    if split not in SPLITS:
        raise ValueError(f"{where}: field 'split': expected one of {SPLITS}, got {split!r}{_did_you_mean(split, SPLITS)}")
    episode_id = entry.get("episode_id", f"{split}-{shape}-{material}-{index:04d}")
    if not isinstance(episode_id, str) or not episode_id:
        raise ValueError(f"{where}: field 'episode_id': expected a non-empty string, got {episode_id!r}")
    if not episode_id.isprintable():  # a newline, tab or invisible character broke one-line logs and bag metadata
        raise ValueError(f"{where}: field 'episode_id': expected one line of printable characters (no newlines, tabs, "
                         f"control or invisible characters; the plain space is fine), got {episode_id!r}")
    return Instance(
        episode_id=episode_id,
        split=split,
        shape=shape,
        material=material,
        parameters=_validate_parameters(material, entry["parameters"], where),
        seed=seed,
        views=views,
    )


def _yaml_loader():
    """SafeLoader that also reads 1.5e6 as a float (PyYAML's YAML 1.1 rules want 1.5e+6), records keys
    given twice in a mapping (see _Mapping), and refuses YAML 1.1's octal (010 = 8) and base-60 (1:30 = 90)
    numbers, which read silently as other numbers than the ones written."""
    import re

    import yaml
    from yaml.constructor import ConstructorError, SafeConstructor

    class Loader(yaml.SafeLoader):
        def construct_yaml_map(self, node):
            data = _Mapping()
            yield data
            keys, repeated = set(), []
            for key_node, _ in node.value:  # before merge keys (<<) are flattened in: they may be overridden
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node)
                try:
                    if key in keys and key not in repeated:
                        repeated.append(key)
                    keys.add(key)
                except TypeError:  # unhashable: construct_mapping says so
                    pass
            data.update(self.construct_mapping(node))
            data.repeated = tuple(repeated)

        def _unambiguous(self, node, construct):
            text = self.construct_scalar(node)
            digits = text.replace("_", "").lstrip("+-")
            value = construct(self, node)
            if ":" in digits:
                problem = f"{text!r} is read by YAML 1.1 as the base 60 number {value} (write {value}; quote a name)"
            elif re.fullmatch(r"0[0-7]+", digits):
                problem = (f"{text!r} is read by YAML 1.1 as the octal number {value} (write {value}, or "
                           f"{int(digits)} without the leading zero; quote a name)")
            else:
                return value
            raise ConstructorError(None, None, problem, node.start_mark)

        def construct_yaml_int(self, node):
            return self._unambiguous(node, SafeConstructor.construct_yaml_int)

        def construct_yaml_float(self, node):
            return self._unambiguous(node, SafeConstructor.construct_yaml_float)

    Loader.add_constructor("tag:yaml.org,2002:map", Loader.construct_yaml_map)
    Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_yaml_int)
    Loader.add_constructor("tag:yaml.org,2002:float", Loader.construct_yaml_float)
    _add_float_resolver(Loader)
    return Loader


def _add_float_resolver(cls) -> None:
    """Floats as the instance-file loader reads them (1.5e6 too): on its Loader, and on the Dumper of
    write_instance_file, which then quotes a string that would read back as one (an id '1e5')."""
    import re

    cls.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(
            r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
            |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
            |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
            |[-+]?\.(?:inf|Inf|INF)
            |\.(?:nan|NaN|NAN))$""",
            re.X,
        ),
        list("-+0123456789."),
    )


def _yaml_problem(error) -> str:
    """A PyYAML error on one line: what is wrong and where (its own text spans several, quoting the file)."""
    import yaml

    if isinstance(error, yaml.MarkedYAMLError):
        problem = error.problem or error.context
        mark = error.problem_mark or error.context_mark
        if problem and mark:
            return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return " ".join(str(error).split())


def load_instance_file(path: str | Path) -> list[Instance]:
    """Instances of a YAML (.yaml/.yml) or JSON (.json) file: a list of entries (SPEC 4; docs/simulator.md
    describes the fields).

    Raises ValueError naming the file, the entry and field of the first problem found, on one line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:  # its own message does not name the file
        raise ValueError(f"{path}: not UTF-8 text ({error})") from None
    if path.suffix.lower() == ".json":
        try:
            entries = json.loads(text, object_pairs_hook=_json_object)
        except json.JSONDecodeError as error:
            raise ValueError(f"{path}: not valid JSON: {error}") from None
    elif path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            entries = yaml.load(text, Loader=_yaml_loader())
        except yaml.YAMLError as error:
            raise ValueError(f"{path}: not valid YAML: {_yaml_problem(error)}") from None
    else:
        raise ValueError(f"{path}: instance files end in .yaml, .yml or .json")
    if not isinstance(entries, list) or not entries:
        got = "a mapping (write one entry as a list of one: '- shape: ...')" if isinstance(entries, dict) else repr(entries)
        raise ValueError(f"{path}: expected a non-empty list of entries (shape, material, parameters, seed), got {got}")
    instances = [instance_from_entry(entry, i, str(path)) for i, entry in enumerate(entries)]
    first: dict[str, int] = {}
    for index, instance in enumerate(instances):
        earlier = first.setdefault(instance.episode_id, index)
        if earlier != index:
            raise ValueError(f"{path}: duplicate episode_id {instance.episode_id!r} in entries {earlier} and {index}; "
                             "episode ids must be unique")
    return instances


def instance_entry(instance: Instance) -> dict:
    """The instance-file entry of an instance: what load_instance_file reads back as an equal Instance."""
    return {
        "episode_id": instance.episode_id,
        "split": instance.split,
        "shape": instance.shape,
        "material": instance.material,
        "parameters": {name: float(value) for name, value in instance.parameters.items()},
        "seed": int(instance.seed),
        "views": int(instance.views),
    }


def write_instance_file(instances, path: str | Path) -> None:
    """Writes instances as an instance file, JSON or YAML by the file's suffix; floats are written with
    Python's repr, so they read back bit-exactly. An instance the file could not hold (parameters outside the
    family's ranges, say, as a re-simulated prediction may have) raises load_instance_file's error, and
    nothing is written."""
    path = Path(path)
    entries = [instance_entry(instance) for instance in instances]
    for index, entry in enumerate(entries):
        instance_from_entry(entry, index, f"{path} (not written)")
    if path.suffix.lower() == ".json":
        text = json.dumps(entries, indent=1, ensure_ascii=False) + "\n"
    elif path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        class Dumper(yaml.SafeDumper):
            pass

        _add_float_resolver(Dumper)
        text = yaml.dump(entries, Dumper=Dumper, sort_keys=False, allow_unicode=True, width=1000)
    else:
        raise ValueError(f"{path}: instance files end in .yaml, .yml or .json")
    path.write_text(text, encoding="utf-8")
