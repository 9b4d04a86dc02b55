"""Running the ad_sim executables as `ros2 run` would (scripts/adrun) and reading their logs."""

from __future__ import annotations

import argparse
import fcntl
import os
import random
import re
import signal
import subprocess
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
ADRUN = REPO_ROOT / "scripts" / "adrun"
_started: list[subprocess.Popen] = []
# Domains 1..100 are valid for DDS on Linux whatever the participant count. Whoever uses one on this machine
# (a test, a benchmark) holds a lock file for it, so that concurrent runs never share one.
DOMAIN_COUNT = 100
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "ad-ros-domain-locks"


def hold_domain(domain: int):
    """The open, locked lock file of ROS domain `domain` (keep it open while using the domain; the kernel drops
    the lock when the process dies), or None if another process on this machine holds it."""
    DOMAIN_LOCK_DIR.mkdir(exist_ok=True)
    lock = open(DOMAIN_LOCK_DIR / f"{domain}.lock", "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.close()
        return None
    return lock


MAX_DOMAIN_ID = 232  # the largest ROS domain whose DDS ports fit (Fast DDS, default port mapping)
_held_domains = []  # the lock files of the domains this process took (ros_domain): held until it exits


def ros_domain(parser: argparse.ArgumentParser) -> int:
    """The caller's ROS_DOMAIN_ID if set (shared machines give each user one), else one of 1..100 that no test or
    benchmark on this machine holds (ros_procs.hold_domain), held from now on; parser.error (one line, exit 2)
    for one that is not a domain, or when every one is held, before any work."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        for domain in random.sample(range(1, DOMAIN_COUNT + 1), DOMAIN_COUNT):
            if (lock := hold_domain(domain)) is not None:
                _held_domains.append(lock)
                return domain
        parser.error(f"all ROS domains 1..{DOMAIN_COUNT} are held by tests or benchmarks on this machine (locks in "
                     f"{DOMAIN_LOCK_DIR}); set ROS_DOMAIN_ID")
    if not text.isdigit() or int(text) > MAX_DOMAIN_ID:
        parser.error(f"ROS_DOMAIN_ID must be a ROS domain, a whole number 0..{MAX_DOMAIN_ID} (e.g. 62), got {text!r}")
    return int(text)


def start(executable: str, domain: int, log: Path, **params) -> subprocess.Popen:
    """Start `ad_sim <executable>` with ROS parameters on ROS domain `domain`, output to `log`."""
    args = [str(ADRUN), "ad_sim", executable, "--ros-args"]
    for name, value in params.items():
        if isinstance(value, bool):
            value = str(value).lower()
        elif isinstance(value, (list, tuple)):
            value = "[" + ",".join(f"'{v}'" for v in value) + "]"
        args += ["-p", f"{name}:={value}"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    process = subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT)
    _started.append(process)
    return process


def kill_leftovers() -> None:
    """Kill the processes start() launched that still run (a test failed before stopping them)."""
    while _started:
        process = _started.pop()
        if process.poll() is None:
            process.kill()
            process.wait()


def wait_for_log(log: Path, pattern: str, process: subprocess.Popen, timeout: float = 60.0) -> re.Match:
    """Wait until `log` has a line matching `pattern` (fails early if the process died)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        match = re.search(pattern, log.read_text())
        if match:
            return match
        if process.poll() is not None:
            raise AssertionError(f"process exited with {process.returncode} before logging {pattern!r}:\n{log.read_text()}")
        time.sleep(0.05)
    raise AssertionError(f"no {pattern!r} within {timeout} s:\n{log.read_text()}")


def stop(process: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
    """Send `sig` and wait for the exit code."""
    process.send_signal(sig)
    try:
        return process.wait(timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise AssertionError(f"process ignored signal {sig} for {timeout} s") from None


def recorder_counts(log: str) -> tuple[int, int]:
    """(received, written) from the recorder's exit log."""
    match = re.search(r"received (\d+), written (\d+) messages", log)
    assert match, f"recorder did not log its counts:\n{log}"
    return int(match.group(1)), int(match.group(2))


IMPORTING_RCLPY = re.compile(r"^import time:.*\|\s+rclpy\b", re.M)  # Python's import-time report: an rclpy module came in


def interrupt_while_starting(args: list[str], log: Path, delay: float, timeout: float = 60.0) -> tuple[int, list[str]]:
    """Start `args` (a node executable, as from scripts/adrun) with Python's import-time report on, send SIGINT `delay`
    s after the report says the first rclpy module was imported (deep in the imports that come before the node handles
    signals: most of its first second), and return its exit status and its output lines less the report's."""
    env = dict(os.environ, PYTHONPROFILEIMPORTTIME="1", PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    process = subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT)
    _started.append(process)
    deadline = time.monotonic() + timeout
    while not IMPORTING_RCLPY.search(log.read_text()):
        if process.poll() is not None or time.monotonic() > deadline:
            raise AssertionError(f"{args[1:3]} imported no rclpy module (exit status {process.poll()}):\n{log.read_text()}")
        time.sleep(0.002)
    time.sleep(delay)
    status = stop(process, signal.SIGINT, timeout)
    return status, [line for line in log.read_text().splitlines() if not line.startswith("import time:")]
