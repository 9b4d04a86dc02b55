"""Helpers for the estimator's ROS tests: an isolated rclpy context, mask images, spinning."""
from __future__ import annotations

import os
import random
import threading
import time
from contextlib import contextmanager

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from sensor_msgs.msg import Image

from ad_estimator.window import ns_to_stamp


def random_domain() -> int:
    """For module-scoped contexts: above conftest's per-test domains (1..100), below Fast DDS's limit."""
    return random.Random(os.getpid() ^ time.time_ns()).randrange(101, 230)


_estimators: list = []  # EstimatorNodes started in the current ros_context: destroyed when it ends


def tracked(node):
    """`node` (an EstimatorNode), destroyed when the ros_context ends. Else its worker thread outlives the test
    and, flushing its idle window into the shut-down context later (idle_flush), logs errors in the middle of
    other tests: once it left a later test's log line missing."""
    _estimators.append(node)
    return node


@contextmanager
def ros_context(domain: int | None = None):
    """rclpy context on a random domain (parallel test runs on this machine do not see each other)
    and an executor spinning in a background thread, as in a running system."""
    context = Context()
    rclpy.init(context=context, domain_id=random_domain() if domain is None else domain)
    executor = MultiThreadedExecutor(num_threads=3, context=context)
    spinner = threading.Thread(target=spin_until_shutdown, args=(executor, context), daemon=True)
    spinner.start()
    try:
        yield context, executor
    finally:
        while _estimators:
            node = _estimators.pop()
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001 - a test destroyed it already
                pass
        rclpy.try_shutdown(context=context)
        spinner.join(timeout=5.0)
        executor.shutdown(timeout_sec=2.0)


def spin_until_shutdown(executor, context) -> None:
    while context.ok():
        try:
            executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - shutdown races surface as assorted rclpy errors
            if context.ok():
                raise
            return


def image_msg(mask: np.ndarray, stamp_ns: int, frame_id: str = "ad_sim/view_0", encoding: str = "mono8") -> Image:
    msg = Image()
    sec, nanosec = ns_to_stamp(stamp_ns)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = frame_id
    msg.height, msg.width = mask.shape[:2]
    msg.encoding = encoding
    msg.step = mask.strides[0]
    msg.data = np.ascontiguousarray(mask).tobytes()
    return msg


def wait_for(condition, timeout: float = 10.0) -> bool:
    """Poll ``condition`` while the background executor works."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()
