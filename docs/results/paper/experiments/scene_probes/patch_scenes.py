"""Patch a private copy of instances.py for the scene probes of sections 18 and 19: upright | pose_per_shape | fixed_motion."""
import pathlib, sys

variant, path = sys.argv[1], pathlib.Path(sys.argv[2])
text = path.read_text()
edits = {
    # every instance upright (the mesh's own orientation); the seed's stream advances as before,
    # so drop gap, offset, velocity, cameras and particles are the benchmark's
    "upright": [("        self.orientation = _random_quaternion(rng)\n",
                 "        _random_quaternion(rng); self.orientation = (0.0, 0.0, 0.0, 1.0)  # probe: upright\n")],
    # orientation, drop gap, offset and velocity drawn from the shape alone (one pose per shape);
    # cameras and particles still from the instance's seed, as in the benchmark
    "pose_per_shape": [
        ("        rng = np.random.Generator(np.random.PCG64(self.seed))\n        self.orientation",
         "        rng = np.random.Generator(np.random.PCG64(zlib.crc32(self.shape.encode())))  # probe\n        self.orientation"),
        ("        self.camera_seed = int(rng.integers(0, 2**63))\n",
         "        rng = np.random.Generator(np.random.PCG64(self.seed)); rng.uniform(size=9)  # probe\n"
         "        self.camera_seed = int(rng.integers(0, 2**63))\n")],
    # orientation random as in the benchmark; drop gap, offset and velocity the same for every instance
    # (the middle of their ranges, straight down); the seed's stream advances as before
    "fixed_motion": [("        self.camera_seed = int(rng.integers(0, 2**63))\n",
                      "        self.drop_gap, self.jitter, self.velocity = 0.15, (0.0, 0.0), (0.0, 0.0, -0.25)  # probe\n"
                      "        self.camera_seed = int(rng.integers(0, 2**63))\n")],
}
edits["upright_fixed_motion"] = edits["upright"] + edits["fixed_motion"]
edits = edits[variant]
for old, new in edits:
    assert text.count(old) == 1, (variant, old)
    text = text.replace(old, new)
path.write_text(text)
print(f"patched {path} for {variant}")
