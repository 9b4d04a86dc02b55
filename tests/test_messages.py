"""ad_sim.messages: stamps, message layouts, and one encoding for node (rclpy) and generate (mcap_ros2)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap_ros2._dynamic import generate_dynamic as deserialize_dynamic
from mcap_ros2._dynamic import serialize_dynamic
from sim_fixtures import as_plain, fabricated_episode

from ad_sim import materials, messages
from ad_sim.instances import quaternion_matrix
from ad_sim.rosbag import load_schema


def test_frame_stamps_follow_the_contract():
    assert messages.frame_stamp(0, 0) == 0
    assert messages.frame_stamp(0, 24) == 600_000_000
    assert messages.frame_stamp(2, 1) == 3_025_000_000
    assert messages.frame_stamp(1, 0, base_ns=7) == 1_500_000_007
    # Consecutive episodes are separated by a gap of more than 0.5 s.
    last = messages.frame_stamp(5, materials.FRAME_COUNT - 1)
    assert messages.frame_stamp(6, 0) - last > 500_000_000
    assert messages.stamp_dict(3_025_000_001) == {"sec": 3, "nanosec": 25_000_001}


def test_topics_and_qos():
    types = messages.topic_types(2)
    assert list(types) == [
        "/ad_sim/instance", "/ad_sim/view_0/mask", "/ad_sim/view_0/camera_info",
        "/ad_sim/view_1/mask", "/ad_sim/view_1/camera_info", "/ad_sim/particles",
    ]
    assert all(messages.is_simulator_topic(t) for t in types)
    assert messages.is_simulator_topic("/ad_sim/view_12/mask")
    for other in ("/ad_sim/view_x/mask", "/ad_sim/view_0/depth", "/other/particles", "/ad_estimator/estimate"):
        assert not messages.is_simulator_topic(other)
    assert messages.topic_qos("/ad_sim/instance")["durability"] == "transient_local"
    assert messages.topic_qos("/ad_sim/view_0/mask") == {
        "reliability": "reliable", "durability": "volatile", "history": "keep_last", "depth": messages.QOS_DEPTH,
    }


def test_particles_point_cloud_layout():
    episode = fabricated_episode(3)
    for frame in (0, 7):
        points = messages.particle_points(episode.positions, episode.deformation, frame)
        msg = messages.particles_message(points, 42, "ad_sim/world")
        assert [f["name"] for f in msg["fields"]] == ["x", "y", "z", "dx", "dy", "dz"] + [f"f{i}{j}" for i in range(3) for j in range(3)]
        assert [f["offset"] for f in msg["fields"]] == list(range(0, 60, 4))
        assert {f["datatype"] for f in msg["fields"]} == {7} and {f["count"] for f in msg["fields"]} == {1}
        assert (msg["point_step"], msg["row_step"], msg["width"], msg["height"]) == (60, 60 * 1024, 1024, 1)
        assert msg["is_dense"] and not msg["is_bigendian"] and msg["header"]["frame_id"] == "ad_sim/world"
        table = np.frombuffer(msg["data"], dtype="<f4").reshape(1024, 15)
        np.testing.assert_array_equal(table[:, :3], episode.positions[frame])
        expected = episode.positions[frame] - episode.positions[frame - 1] if frame else np.zeros((1024, 3))
        np.testing.assert_allclose(table[:, 3:6], expected, rtol=0, atol=1e-7)
        np.testing.assert_array_equal(table[:, 6:].reshape(1024, 3, 3), episode.deformation[frame])


def test_image_and_camera_info():
    episode = fabricated_episode(4, views=2)
    image = messages.mask_message(episode.masks[1, 3], 5, "ad_sim/view_1")
    assert (image["encoding"], image["height"], image["width"], image["step"]) == ("mono8", 128, 128, 128)
    assert image["data"] == episode.masks[1, 3].tobytes() and set(image["data"]) <= {0, 255}
    info = messages.camera_info_message(episode.cameras[1], 5, "ad_sim/view_1")
    K = np.array(info["k"]).reshape(3, 3)
    np.testing.assert_array_equal(K, episode.cameras[1].K)
    np.testing.assert_array_equal(np.array(info["p"]).reshape(3, 4)[:, :3], K)
    assert info["distortion_model"] == "plumb_bob" and info["d"] == [0.0] * 5
    assert info["r"] == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_rotation_quaternion_inverts_quaternion_matrix(q):
    q = np.array(q) / np.linalg.norm(q)
    back = np.array(messages.rotation_quaternion(quaternion_matrix(q)))
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9


def test_episode_messages_order_and_instance_content():
    episode = fabricated_episode(5, views=2, material="sand")
    items = list(messages.episode_messages(episode, 3))
    assert len(items) == 1 + 25 * (2 * 2 + 1)
    topic, stamp, instance = items[0]
    assert (topic, stamp) == ("/ad_sim/instance", messages.frame_stamp(3, 0))
    assert [t for t, _, _ in items[1:6]] == list(messages.topic_types(2))[1:]
    assert instance["episode_index"] == 3 and instance["material"] == "sand"
    assert instance["parameter_names"] == ["youngs_modulus", "poissons_ratio", "friction_angle"]
    assert instance["parameters"] == [1e5, 0.3, 0.5]
    assert (instance["frame_count"], instance["tracked_particle_count"]) == (25, 1024)
    assert instance["substeps_per_frame"] == episode.substeps_per_frame
    pose = episode.cameras[1].pose
    q = instance["camera_poses"][1]["orientation"]
    np.testing.assert_allclose(quaternion_matrix((q["x"], q["y"], q["z"], q["w"])), pose[:3, :3], atol=1e-12)
    stamps = [s for t, s, _ in items if t == "/ad_sim/particles"]
    assert stamps == [messages.frame_stamp(3, f) for f in range(25)]


@pytest.mark.ros
def test_rclpy_messages_serialise_to_what_generate_writes():
    """The node's rclpy messages and generate's encoded dicts are the same CDR content
    (Fast-CDR leaves alignment padding uninitialised, so compare decoded, and sizes)."""
    from rclpy.serialization import serialize_message

    from ad_sim.sim_node import to_ros_message

    episode = fabricated_episode(6, views=1)
    seen = set()
    for topic, _, data in messages.episode_messages(episode, 1):
        type_name = messages.topic_types(1)[topic]
        if type_name in seen:
            continue
        seen.add(type_name)
        schema = load_schema(type_name)
        encoded = serialize_dynamic(type_name, schema.definition)[type_name](data)
        from_rclpy = serialize_message(to_ros_message(type_name, data))
        assert len(from_rclpy) == len(encoded), type_name
        decode = deserialize_dynamic(type_name, schema.definition)[type_name]
        assert as_plain(decode(from_rclpy)) == as_plain(decode(encoded)) == as_plain(data), type_name
    assert seen == {messages.INSTANCE_TYPE, messages.IMAGE_TYPE, messages.CAMERA_INFO_TYPE, messages.POINT_CLOUD_TYPE}


@pytest.mark.ros
def test_node_conversion_rejects_unknown_fields():
    from ad_sim.sim_node import to_ros_message

    with pytest.raises(AttributeError):
        to_ros_message(messages.IMAGE_TYPE, {"no_such_field": 1})


# ---- mutation-testing audit (round 2)


def test_instance_message_carries_the_initial_state_and_camera_positions():
    """The ground truth's initial pose, velocity and camera poses are the episode's, field by field (only the
    camera orientations were checked: camera positions, the velocity's axes, the object's orientation and the
    gravity's sign could be wrong without a failing test)."""
    episode = fabricated_episode(7, views=3, material="jelly")
    _, _, instance = next(messages.episode_messages(episode, 0))
    for pose, camera in zip(instance["camera_poses"], episode.cameras, strict=True):
        p, q = pose["position"], pose["orientation"]
        np.testing.assert_array_equal([p["x"], p["y"], p["z"]], camera.pose[:3, 3])
        np.testing.assert_allclose(quaternion_matrix((q["x"], q["y"], q["z"], q["w"])), camera.pose[:3, :3], atol=1e-12)
    initial = instance["initial_pose"]
    p, q = initial["position"], initial["orientation"]
    np.testing.assert_array_equal([p["x"], p["y"], p["z"]], episode.instance.position())
    np.testing.assert_array_equal([q["x"], q["y"], q["z"], q["w"]], episode.instance.orientation)
    linear, angular = instance["initial_velocity"]["linear"], instance["initial_velocity"]["angular"]
    np.testing.assert_array_equal([linear["x"], linear["y"], linear["z"]], episode.instance.velocity)
    assert angular == {"x": 0.0, "y": 0.0, "z": 0.0}
    # Settings: gravity is the magnitude along -z in m/s^2 (positive), frames 25 ms apart, a 32^3 grid.
    assert instance["gravity"] == 9.8 and instance["frame_interval"] == 0.025 and instance["grid_resolution"] == 32
    assert instance["scale"] == 0.4 and instance["density"] == materials.DENSITY
    assert instance["particle_count"] == episode.particle_count


def test_header_stamp_of_encoded_messages_in_either_byte_order():
    """rosbag.header_stamp_ns reads the stamp after the 4-byte CDR encapsulation, whose second byte is the byte
    order (1: little endian): a mask message stamped 3.000000025 s gives 3_000_000_025 ns, as does its
    big-endian encoding; a nanosec of 1e9 or more is no time (999_999_999 is)."""
    import struct

    from ad_sim.rosbag import header_stamp_ns

    stamp = 3_000_000_025
    message = messages.mask_message(np.zeros((2, 2), np.uint8), stamp, "ad_sim/view_0")
    schema = load_schema(messages.IMAGE_TYPE)
    encoded = serialize_dynamic(messages.IMAGE_TYPE, schema.definition)[messages.IMAGE_TYPE](message)
    assert encoded[:2] == b"\x00\x01" and header_stamp_ns(encoded) == stamp
    assert header_stamp_ns(b"\x00\x00\x00\x00" + struct.pack(">iI", 3, 25)) == stamp
    assert header_stamp_ns(b"\x00\x01\x00\x00" + struct.pack("<iI", 7, 999_999_999)) == 7_999_999_999
    with pytest.raises(ValueError, match="cannot be a log time"):
        header_stamp_ns(b"\x00\x01\x00\x00" + struct.pack("<iI", 7, 1_000_000_000))
