"""Episode -> simulator messages (SPEC 5, docs/architecture.md "Bag layout"), as plain dicts.

The one source of truth for what the simulator node publishes and what `generate` writes:
the node converts these dicts into rclpy messages, generate encodes them straight to CDR.
No ROS import here, and no Warp at import: the estimator's tools read the topic names, QoS and stamps.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from . import families

EPISODE_PERIOD = 1.5  # s between episode starts in a stream: 0.6 s of frames, then a gap > 0.5 s
DEFAULT_PREFIX = "/ad_sim"
DEFAULT_FRAME_PREFIX = "ad_sim"

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
INSTANCE_TYPE = "ad_msgs/msg/SimInstance"

# PointCloud2 layout of the tracked particles: position, frame displacement, F row-major.
POINT_FIELDS = ("x", "y", "z", "dx", "dy", "dz", *(f"f{i}{j}" for i in range(3) for j in range(3)))
POINT_FIELD_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
POINT_STEP = 4 * len(POINT_FIELDS)
# QoS of the simulator topics: reliable keep-last QOS_DEPTH; ground truth is transient local with depth 1, so that a
# late subscriber gets the episode now playing (not the last QOS_DEPTH episodes: a late recorder's bag began with
# that many episodes without frames).
QOS_DEPTH = 100


def frame_stamp(episode_index: int, frame: int, base_ns: int = 0) -> int:
    """Stamp (ns) of frame `frame` of episode `episode_index` in a stream starting at base_ns."""
    episode_start = round(episode_index * EPISODE_PERIOD * 1e9)
    return base_ns + episode_start + round(frame * families.FRAME_INTERVAL * 1e9)


def stamp_dict(stamp_ns: int) -> dict:
    return {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}


def _header(stamp_ns: int, frame_id: str) -> dict:
    return {"stamp": stamp_dict(stamp_ns), "frame_id": frame_id}


# ---------------------------------------------------------------------------- topics


def instance_topic(prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/instance"


def mask_topic(view: int, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/view_{view}/mask"


def camera_info_topic(view: int, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/view_{view}/camera_info"


def particles_topic(prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/particles"


def topic_types(views: int, prefix: str = DEFAULT_PREFIX) -> dict[str, str]:
    """Every simulator topic of a stream with `views` cameras -> its message type, in publication order."""
    types = {instance_topic(prefix): INSTANCE_TYPE}
    for view in range(views):
        types[mask_topic(view, prefix)] = IMAGE_TYPE
        types[camera_info_topic(view, prefix)] = CAMERA_INFO_TYPE
    types[particles_topic(prefix)] = POINT_CLOUD_TYPE
    return types


def is_simulator_topic(topic: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """True for the topics the simulator publishes (any number of views)."""
    if topic in (instance_topic(prefix), particles_topic(prefix)):
        return True
    head, _, tail = topic.rpartition("/")
    view = head[len(prefix) + len("/view_") :] if head.startswith(f"{prefix}/view_") else ""
    return view.isdigit() and tail in ("mask", "camera_info")


def topic_qos(topic: str, prefix: str = DEFAULT_PREFIX) -> dict:
    """QoS the simulator offers on `topic` (reliability, durability, history, depth)."""
    if topic == instance_topic(prefix):
        return {"reliability": "reliable", "durability": "transient_local", "history": "keep_last", "depth": 1}
    return {"reliability": "reliable", "durability": "volatile", "history": "keep_last", "depth": QOS_DEPTH}


# ---------------------------------------------------------------------------- messages


def rotation_quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(v) for v in q)


def _pose(position, orientation) -> dict:
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in orientation)
    return {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def instance_message(episode, episode_index: int, stamp_ns: int, frame_prefix: str = DEFAULT_FRAME_PREFIX) -> dict:
    """ad_msgs/SimInstance: the episode's ground truth and simulation settings."""
    from . import materials  # the simulator's constants: here, so that importing this module loads no Warp
    from .instances import SCALE

    instance = episode.instance
    names = [n for n in families.PARAMETER_NAMES if n in instance.parameters]
    vx, vy, vz = (float(v) for v in instance.velocity)
    return {
        "header": _header(stamp_ns, f"{frame_prefix}/world"),
        "episode_id": instance.episode_id,
        "episode_index": int(episode_index),
        "split": instance.split,
        "shape": instance.shape,
        "material": instance.material,
        "parameter_names": names,
        "parameters": [float(instance.parameters[n]) for n in names],
        "seed": int(instance.seed),
        "initial_pose": _pose(instance.position(), instance.orientation),
        "initial_velocity": {"linear": {"x": vx, "y": vy, "z": vz}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
        "scale": float(SCALE),
        "camera_poses": [_pose(c.pose[:3, 3], rotation_quaternion(c.pose[:3, :3])) for c in episode.cameras],
        "grid_resolution": int(materials.GRID_RESOLUTION),
        "frame_interval": float(families.FRAME_INTERVAL),
        "frame_count": int(episode.positions.shape[0]),
        "substeps_per_frame": int(episode.substeps_per_frame),
        "gravity": float(materials.GRAVITY),
        "density": float(materials.DENSITY),
        "particle_count": int(episode.particle_count),
        "tracked_particle_count": int(episode.positions.shape[1]),
    }


def mask_message(mask: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    """sensor_msgs/Image mono8 of one mask frame (values 0/255)."""
    mask = np.ascontiguousarray(mask, dtype=np.uint8)
    height, width = mask.shape
    return {
        "header": _header(stamp_ns, frame_id),
        "height": height,
        "width": width,
        "encoding": "mono8",
        "is_bigendian": 0,
        "step": width,
        "data": mask.tobytes(),
    }


def camera_info_message(camera, stamp_ns: int, frame_id: str) -> dict:
    """sensor_msgs/CameraInfo of a distortion-free pinhole camera (P = K [I | 0])."""
    K = np.asarray(camera.K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "header": _header(stamp_ns, frame_id),
        "height": int(camera.height),
        "width": int(camera.width),
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [float(v) for v in K.ravel()],
        "r": [float(v) for v in np.eye(3).ravel()],
        "p": [float(v) for v in P.ravel()],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def particle_points(positions: np.ndarray, deformation: np.ndarray, frame: int) -> np.ndarray:
    """(N, 15) float32 rows x y z dx dy dz f00..f22 of one frame (displacement 0 at frame 0)."""
    position = positions[frame]
    displacement = position - positions[frame - 1] if frame > 0 else np.zeros_like(position)
    count = position.shape[0]
    return np.concatenate([position, displacement, deformation[frame].reshape(count, 9)], axis=1).astype("<f4")


def particles_message(points: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    """sensor_msgs/PointCloud2 of the tracked particles (one row, little endian float32)."""
    count = points.shape[0]
    return {
        "header": _header(stamp_ns, frame_id),
        "height": 1,
        "width": count,
        "fields": [
            {"name": name, "offset": 4 * i, "datatype": POINT_FIELD_FLOAT32, "count": 1} for i, name in enumerate(POINT_FIELDS)
        ],
        "is_bigendian": False,
        "point_step": POINT_STEP,
        "row_step": POINT_STEP * count,
        "data": np.ascontiguousarray(points, dtype="<f4").tobytes(),
        "is_dense": True,
    }


def episode_messages(
    episode,
    episode_index: int,
    *,
    prefix: str = DEFAULT_PREFIX,
    frame_prefix: str = DEFAULT_FRAME_PREFIX,
    base_ns: int = 0,
) -> Iterator[tuple[str, int, dict]]:
    """(topic, stamp_ns, message dict) of one episode in publication order: the instance, then
    per frame each view's mask and camera info, then the particles."""
    frames = episode.positions.shape[0]
    start = frame_stamp(episode_index, 0, base_ns)
    yield instance_topic(prefix), start, instance_message(episode, episode_index, start, frame_prefix)
    world = f"{frame_prefix}/world"
    for frame in range(frames):
        stamp = frame_stamp(episode_index, frame, base_ns)
        for view, camera in enumerate(episode.cameras):
            optical = f"{frame_prefix}/view_{view}"
            yield mask_topic(view, prefix), stamp, mask_message(episode.masks[view, frame], stamp, optical)
            yield camera_info_topic(view, prefix), stamp, camera_info_message(camera, stamp, optical)
        points = particle_points(episode.positions, episode.deformation, frame)
        yield particles_topic(prefix), stamp, particles_message(points, stamp, world)
