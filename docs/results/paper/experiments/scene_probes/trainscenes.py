"""Writes the instance file of section 18's training-scene probe: each seen-split instance's parameters,
simulated in the scene of the training instance of the same shape, family and index (its seed: the same
pose, velocity, particles and view 0). Run from the repository root after `source env.sh`:
python docs/results/paper/experiments/scene_probes/trainscenes.py OUT.yaml"""
import sys

from ad_sim import instances

scenes = []
for seen in instances.benchmark("paper", "seen"):
    index = int(seen.episode_id.rsplit("-", 1)[1])
    seed = instances.instance_seed("train", seen.shape, seen.material, index)
    scenes.append(instances.Instance(f"trainscene-{seen.shape}-{seen.material}-{index:04d}", "custom", seen.shape,
                                     seen.material, dict(seen.parameters), seed, 1))
instances.write_instance_file(scenes, sys.argv[1])
