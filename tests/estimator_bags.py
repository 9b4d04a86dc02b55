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
                   frame_stamp=messages.frame_stamp, ground_truth: bool = True, frames: int = 25,
                   fps: float | None = None, passes: int = 1, instance_schema=None) -> Path:
    """One view, falling-disc masks at the simulator's stamps, ground truth per episode.

    ``edit_mask(episode, frame, message)``, if given, returns the mask message to record instead
    (e.g. a damaged frame), or None to leave the frame out. ``frame_stamp(episode, frame)``: the stamp
    (ns; header and log time) of each mask frame, the simulator's by default (frame 0's is the episode's
    ground truth's). ``ground_truth=False``: the masks only (a recording without the instance topic).
    ``frames``: mask frames per episode; ``fps``: a camera of that rate instead of the simulator's 40 fps
    (frame k stamped k / fps after the episode's start). ``passes``: the episodes that many times over, as
    the simulator node with ``loop: true`` records them: the same episode ids, seeds and frames on each
    pass, with episode_index and stamps going on (episode numbers in ``edit_mask`` and ``frame_stamp``
    count on too). ``instance_schema``: an ad_sim.rosbag.MessageSchema to record the ground truth with (an
    older or foreign SimInstance definition), whose fields the ground truth messages are cut to."""
    instance_topic, mask_topic = messages.instance_topic(), messages.mask_topic(0)
    if fps is not None:
        frame_stamp = lambda index, frame, at=frame_stamp: at(index, 0) + round(frame * 1e9 / fps)  # noqa: E731
    with BagWriter(path, chunk_size=chunk_size) as writer:
        if ground_truth:
            writer.add_topic(instance_topic, messages.INSTANCE_TYPE,
                             [qos_profile(**messages.topic_qos(instance_topic))], schema=instance_schema)
        writer.add_topic(mask_topic, messages.IMAGE_TYPE, [qos_profile(**messages.topic_qos(mask_topic))])
        for index, (episode, (material, parameters)) in enumerate((e, ep) for _ in range(passes)
                                                                  for e, ep in enumerate(episodes)):
            start = frame_stamp(index, 0)
            if ground_truth:
                instance = instance_dict(episode, material, parameters, start) | {"episode_index": index}
                if instance_schema is not None:
                    instance = {k: v for k, v in instance.items() if _declares(instance_schema, k)}
                writer.write(instance_topic, start, instance)
            for frame, mask in enumerate(falling_masks(count=frames, seed=100 + episode)):
                stamp = frame_stamp(index, frame)
                message = messages.mask_message(mask, stamp, "ad_sim/view_0")
                if edit_mask is not None and (message := edit_mask(index, frame, message)) is None:
                    continue
                writer.write(mask_topic, stamp, message)
    return path


def _declares(schema, field: str) -> bool:
    """Whether the top-level message of `schema` (a ros2msg definition) declares `field`."""
    top = schema.definition.split("=" * 80)[0]
    return any(line.split("#")[0].split()[1:2] == [field] for line in top.splitlines())


def without_field(type_name: str, field: str):
    """The bag schema of `type_name` without its field `field`: an older or foreign definition of the type."""
    from ad_sim.rosbag import MessageSchema, load_schema

    schema = load_schema(type_name)
    top, delimiter, rest = schema.definition.partition("=" * 80)
    kept = [line for line in top.splitlines() if line.split("#")[0].split()[1:2] != [field]]
    assert len(kept) == len(top.splitlines()) - 1, f"{type_name} has no field {field}"
    return MessageSchema(schema.name, "\n".join(kept) + "\n" + delimiter + rest, "")


def damaged(episode, frame, edit):
    """edit_mask for write_test_bag: `edit` changes frame `frame` of episode `episode` in place."""
    def edit_mask(index, k, message):
        if (index, k) == (episode, frame):
            edit(message)
        return message
    return edit_mask
