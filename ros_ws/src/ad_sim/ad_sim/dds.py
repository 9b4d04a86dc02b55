"""ROS process set-up shared by the nodes: their command line (non_ros_args), their parameters
(declare_parameters, number) and, for those that publish the simulator's topics (simulator,
replay), DDS writer settings (use_fast_heartbeat).

Reliable writers repair a lost sample and learn of acknowledgements at their heartbeats: every
3 s by default on Fast DDS. That caps paced playback and can hold a stream up for seconds after
one lost packet, so these nodes load a default writer profile with 20 ms heartbeats
(data/dds/fast_heartbeat.xml). ROS QoS still comes from each node.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from rcl_interfaces.msg import ParameterDescriptor

FAST_HEARTBEAT_PROFILE = Path(__file__).resolve().parent / "data" / "dds" / "fast_heartbeat.xml"
MAX_QOS_DEPTH = 2**31 - 1  # rclpy refuses a larger history depth (a TypeError from its rmw_qos_profile_t)


def use_fast_heartbeat() -> None:
    """Before rclpy.init: on Fast DDS (the default RMW), make reliable writers heartbeat every 20 ms,
    unless a profiles file is set already."""
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        if not os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") and not os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE"):
            os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FAST_HEARTBEAT_PROFILE)


def non_ros_args(prog: str, argv: list[str]) -> list[str]:
    """argv without its `--ros-args ...` part. ROS arguments rcl cannot parse (e.g. a --params-file
    that cannot be read) exit with a one-line error and status 2, as argparse does for the others."""
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.utilities import remove_ros_args

    try:
        return remove_ros_args(argv)
    except rclpy_implementation.RCLInvalidROSArgsError as exc:
        reason = str(exc).split(", at ")[0]  # rcl appends its C source locations
        print(f"{prog}: {reason}", file=sys.stderr)
        raise SystemExit(2) from None


def declare_parameters(node, parameters) -> None:
    """Declares (name, default, meaning) parameters, read-only: they are read once, at start, so a
    change at run time (`ros2 param set`) is refused instead of accepted and ignored. Those with a
    float default take ints as well (`real_time_factor:=0`, `idle_flush:=0`): read them with `number`."""
    for name, default, meaning in parameters:
        node.declare_parameter(name, default, ParameterDescriptor(
            description=meaning, read_only=True, dynamic_typing=isinstance(default, float)))


def number(node, name: str) -> float:
    """A float parameter's value; ValueError naming the parameter if it is not a number."""
    value = node.get_parameter(name).value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return float(value)
