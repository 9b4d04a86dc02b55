"""Bags for the estimator's replay/evaluate tests, written with ad_sim.rosbag's BagWriter."""
from __future__ import annotations

import math
from pathlib import Path

from ad_sim import messages
from ad_sim.rosbag import BagWriter, qos_profile
from estimator_models import falling_masks

# (material, parameters) of the episodes of a test bag
EPISODES = [
    ("jelly", {"youngs_modulus": 2.0e5, "poissons_ratio": 0.3}),
    ("plasticine", {"youngs_modulus": 1.0e5, "poissons_ratio": 0.4, "yield_stress": 3000.0}),
    ("sand", {"youngs_modulus": 1.0e5, "poissons_ratio": 0.3, "friction_angle": math.radians(30.0)}),
]


def instance_dict(index: int, material: str, parameters: dict, stamp_ns: int) -> dict:
    pose = {"position": {"x": 0.5, "y": 0.5, "z": 0.5}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": {"stamp": messages.stamp_dict(stamp_ns), "frame_id": "ad_sim/world"},
        "episode_id": f"test-disc-{material}-{index:04d}", "episode_index": index, "split": "custom",
        "shape": "disc", "material": material, "parameter_names": list(parameters),
        "parameters": [float(v) for v in parameters.values()], "seed": index,
        "initial_pose": pose, "initial_velocity": {"linear": zero, "angular": zero}, "scale": 0.35,
        "camera_poses": [pose], "grid_resolution": 32, "frame_interval": 0.025, "frame_count": 25,
        "substeps_per_frame": 50, "gravity": 9.8, "density": 1000.0, "particle_count": 1000,
        "tracked_particle_count": 1024,
    }


def write_test_bag(path: Path, episodes=EPISODES, chunk_size: int = 1024 * 1024, edit_mask=None,
                   frame_stamp=messages.frame_stamp, ground_truth: bool = True) -> Path:
    """One view, falling-disc masks at the simulator's stamps, ground truth per episode.

    ``edit_mask(episode, frame, message)``, if given, returns the mask message to record instead
    (e.g. a damaged frame), or None to leave the frame out. ``frame_stamp(episode, frame)``: the stamp
    (ns; header and log time) of each mask frame, the simulator's by default (frame 0's is the episode's
    ground truth's). ``ground_truth=False``: the masks only (a recording without the instance topic)."""
    instance_topic, mask_topic = messages.instance_topic(), messages.mask_topic(0)
    with BagWriter(path, chunk_size=chunk_size) as writer:
        if ground_truth:
            writer.add_topic(instance_topic, messages.INSTANCE_TYPE,
                             [qos_profile(**messages.topic_qos(instance_topic))])
        writer.add_topic(mask_topic, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(mask_topic))])
        for index, (material, parameters) in enumerate(episodes):
            start = frame_stamp(index, 0)
            if ground_truth:
                writer.write(instance_topic, start, instance_dict(index, material, parameters, start))
            for frame, mask in enumerate(falling_masks(seed=100 + index)):
                stamp = frame_stamp(index, frame)
                message = messages.mask_message(mask, stamp, "ad_sim/view_0")
                if edit_mask is not None and (message := edit_mask(index, frame, message)) is None:
                    continue
                writer.write(mask_topic, stamp, message)
    return path


def damaged(episode, frame, edit):
    """edit_mask for write_test_bag: `edit` changes frame `frame` of episode `episode` in place."""
    def edit_mask(index, k, message):
        if (index, k) == (episode, frame):
            edit(message)
        return message
    return edit_mask
