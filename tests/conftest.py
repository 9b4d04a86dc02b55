"""Shared fixtures and markers.

- `ros` marker: the test needs the built workspace (ad_msgs typesupport, ament index). Such tests
  FAIL with instructions when it is missing; they never skip.
- `ros_domain_id`: a ROS domain that no other test on this machine holds while this one runs,
  exported as ROS_DOMAIN_ID so that subprocesses started by the test (nodes via scripts/adrun)
  join it. Every test that starts a node must use it (or `rclpy_context`, which does).
- `rclpy_context`: an initialised rclpy Context on that domain.
"""

from __future__ import annotations

import importlib
import itertools
import os
import signal
from functools import lru_cache
from pathlib import Path

import pytest
from ros_procs import DOMAIN_COUNT, DOMAIN_LOCK_DIR, hold_domain

REPO_ROOT = Path(__file__).resolve().parents[1]
WORKSPACE_INSTALL = REPO_ROOT / "ros_ws" / "install"
BUILD_HINT = "run ./setup.sh and source env.sh first (scripts/test.sh does both)"

# DDS discovery stays on this machine; before any rclpy import initialises a context.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# A shell without job control starts its background commands with SIGINT ignored (`./scripts/test.sh &`,
# nohup in a script), and every process the tests start inherits that: the tests that send Ctrl-C to a tool
# then saw it run on to the end. A handler of our own is not inherited across exec; the default one comes back.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# Tests take domains in turn from the run's ROS_DOMAIN_ID (scripts/test.sh picks a random one), so that a
# node left over from one test cannot talk to the next, each holding its domain's lock (ros_procs.hold_domain).
_RUN_DOMAIN = int(os.environ.get("ROS_DOMAIN_ID", os.getpid() % DOMAIN_COUNT + 1))
_domains = (((_RUN_DOMAIN - 1 + offset) % DOMAIN_COUNT) + 1 for offset in itertools.count())


@lru_cache(maxsize=None)
def workspace_problem() -> str | None:
    """Why the ROS workspace cannot be used from this process, or None when it can."""
    if not (WORKSPACE_INSTALL / "setup.bash").is_file():
        return f"ros_ws is not built ({WORKSPACE_INSTALL}/setup.bash missing): {BUILD_HINT}"
    prefixes = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    if str(WORKSPACE_INSTALL / "ad_msgs") not in prefixes:
        return f"the ros_ws environment is not sourced (AMENT_PREFIX_PATH lacks {WORKSPACE_INSTALL}/ad_msgs): {BUILD_HINT}"
    for module in ("rclpy", "ad_msgs.msg", "ad_msgs.srv"):
        try:
            importlib.import_module(module)
        except ImportError as error:
            return f"cannot import {module} ({error}): {BUILD_HINT}"
    return None


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("ros") is not None:
        problem = workspace_problem()
        if problem is not None:
            pytest.fail(problem, pytrace=False)


@pytest.fixture
def ros_domain_id(monkeypatch: pytest.MonkeyPatch):
    """A ROS domain for this test alone, exported as ROS_DOMAIN_ID for the subprocesses it starts."""
    for _ in range(DOMAIN_COUNT):
        domain = next(_domains)
        if (lock := hold_domain(domain)) is None:
            continue  # another test or benchmark on this machine is using it
        with lock:
            monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
            yield domain
        return
    pytest.fail(f"all {DOMAIN_COUNT} ROS domains are held by running tests (locks in {DOMAIN_LOCK_DIR})")


@pytest.fixture
def rclpy_context(ros_domain_id: int):
    """An initialised rclpy Context on this test's own domain; shut down afterwards.

    Create nodes and executors with `context=rclpy_context`.
    """
    problem = workspace_problem()
    if problem is not None:
        pytest.fail(problem, pytrace=False)
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain_id)
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture
def ros(ros_domain_id: int):
    """(context, executor): an rclpy context on this test's domain with an executor spinning in a background
    thread, as in a running system (estimator_ros.ros_context)."""
    from estimator_ros import ros_context

    with ros_context(ros_domain_id) as (context, executor):
        yield context, executor
