"""DDS settings shared by the nodes that publish the simulator's topics (simulator, replay).

Reliable writers repair a lost sample and learn of acknowledgements at their heartbeats: every
3 s by default on Fast DDS. That caps paced playback and can hold a stream up for seconds after
one lost packet, so these nodes load a default writer profile with 20 ms heartbeats
(data/dds/fast_heartbeat.xml). ROS QoS still comes from each node.
"""
from __future__ import annotations

import os
from pathlib import Path

FAST_HEARTBEAT_PROFILE = Path(__file__).resolve().parent / "data" / "dds" / "fast_heartbeat.xml"


def use_fast_heartbeat() -> None:
    """Before rclpy.init: on Fast DDS (the default RMW), make reliable writers heartbeat every 20 ms,
    unless a profiles file is set already."""
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        if not os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") and not os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE"):
            os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FAST_HEARTBEAT_PROFILE)
