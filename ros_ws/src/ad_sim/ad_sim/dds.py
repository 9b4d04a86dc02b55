"""ROS process set-up shared by the nodes: a Ctrl-C during their imports (quiet_interrupt), their command
line (non_ros_args), their parameters (declare_parameters, number), the rclpy message class of a type name and
the QoSProfile of a QoS description as bags hold them (message_class, qos_from_profile) and, for those that
publish the simulator's topics (simulator, replay), DDS writer settings (use_fast_heartbeat). It imports
nothing of ROS itself until a function needs it: the nodes import it first, before the imports it guards.

Reliable writers repair a lost sample and learn of acknowledgements at their heartbeats: every
3 s by default on Fast DDS. That caps paced playback and can hold a stream up for seconds after
one lost packet, so these nodes load a default writer profile with 20 ms heartbeats
(data/dds/fast_heartbeat.xml). ROS QoS still comes from each node.
"""
from __future__ import annotations

import contextlib
import difflib
import importlib
import os
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile

FAST_HEARTBEAT_PROFILE = Path(__file__).resolve().parent / "data" / "dds" / "fast_heartbeat.xml"
MAX_QOS_DEPTH = 2**31 - 1  # rclpy refuses a larger history depth (a TypeError from its rmw_qos_profile_t)
# QoS policies (the names of rclpy's ReliabilityPolicy, DurabilityPolicy and HistoryPolicy members) by rosbag2's
# names; older rosbag2 metadata stores the rmw enum values instead.
_RELIABILITY = {"reliable": "RELIABLE", "best_effort": "BEST_EFFORT", 1: "RELIABLE", 2: "BEST_EFFORT"}
_DURABILITY = {"transient_local": "TRANSIENT_LOCAL", "volatile": "VOLATILE", 1: "TRANSIENT_LOCAL", 2: "VOLATILE"}
_HISTORY = {"keep_last": "KEEP_LAST", "keep_all": "KEEP_ALL", 1: "KEEP_LAST", 2: "KEEP_ALL"}
_UNKNOWN_HISTORY = ("unknown", 3)  # RMW_QOS_POLICY_HISTORY_UNKNOWN, by name or enum value


class StartInterrupted(SystemExit, KeyboardInterrupt):
    """A Ctrl-C while a node executable imported its modules (quiet_interrupt): a SystemExit to the interpreter, which
    then exits with its status and no traceback, and still a KeyboardInterrupt to whoever imported the module in its
    own process and catches one (pytest, a notebook)."""


@contextlib.contextmanager
def quiet_interrupt(prog: str):
    """Around a node executable's imports (rclpy, numpy, ...: most of its first second), before its main() installs
    its signal handlers: a Ctrl-C there, which printed Python's KeyboardInterrupt traceback, exits with one line on
    stderr and status 0, as a Ctrl-C the node handles does (StartInterrupted). One in the initialisation of a C
    extension (onnxruntime's, rclpy's) comes out of its import as an ImportError that the KeyboardInterrupt caused.
    One whose KeyboardInterrupt Python swallows (raised in a __del__ or a weakref callback, as importlib's module
    locks have: "Exception ignored in ...") is remembered and stops the start when the imports end: it was lost, and
    the node ran on deaf to the Ctrl-C it had been sent."""
    interrupted = []

    def on_sigint(signum, frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    main_thread = threading.current_thread() is threading.main_thread()  # where Python runs signal handlers
    previous = signal.signal(signal.SIGINT, on_sigint) if main_thread else None
    try:
        yield
        if interrupted:
            raise KeyboardInterrupt
    except BaseException as exc:
        cause = exc
        while cause is not None and not isinstance(cause, KeyboardInterrupt):
            cause = cause.__cause__ or cause.__context__
        if cause is None or isinstance(exc, StartInterrupted):  # not a Ctrl-C, or one said already
            raise
        print(f"{prog}: interrupted while starting", file=sys.stderr, flush=True)
        raise StartInterrupted(0) from None
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, previous)


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


def node_cli(prog: str, description: str, parameters, argv: list[str] | None, epilog: str = "") -> None:
    """The command line of a node whose knobs are ROS parameters ((name, default, meaning) each): `--help`
    prints the description, every parameter with its default, and `epilog`, then exits; anything else outside
    `--ros-args ...` is a usage error (exit 2)."""
    import argparse
    import textwrap

    from rclpy.parameter import Parameter

    def shown(default) -> str:
        return "unset" if isinstance(default, Parameter.Type) else repr(default)

    name_width = max(len(name) for name, _, _ in parameters)
    table = [textwrap.fill(meaning, width=110, initial_indent=f"  {name:{name_width}s} {shown(default):>12}  ",
                           subsequent_indent=" " * (name_width + 17)) for name, default, meaning in parameters]
    parser = argparse.ArgumentParser(
        prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="ROS parameters (--ros-args -p name:=value), with their defaults:\n" + "\n".join(table) + epilog)
    parser.parse_args(non_ros_args(prog, sys.argv if argv is None else argv)[1:])


READ_ONLY_CONSTRAINT = "read once at start (read-only): restart the node to change it"


def declare_parameters(node, parameters, ranges: dict | None = None) -> None:
    """Declares (name, default, meaning) parameters, read-only: they are read once, at start, so a
    change at run time (`ros2 param set`) is refused instead of accepted and ignored. Those with a
    float default take ints as well (`real_time_factor:=0`, `idle_flush:=0`): read them with `number`.

    `ranges` (name -> (least, most)) go into the descriptors that `ros2 param describe` (describe_parameters)
    shows, as integer or floating-point ranges by the default's type. They are for the reader: the node checks
    the values itself, with messages that say what a parameter means (rclpy would refuse an out-of-range
    value at declaration, before that check, with its own words, and only a value of the default's type)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    for name, default, meaning in parameters:
        node.declare_parameter(name, default, ParameterDescriptor(
            description=meaning, read_only=True, dynamic_typing=isinstance(default, float),
            additional_constraints=READ_ONLY_CONSTRAINT))
    for name, (least, most) in (ranges or {}).items():
        descriptor = node.describe_parameter(name)  # the node's own descriptor: what describe_parameters serves
        if isinstance(least, float) or isinstance(most, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(least), to_value=float(most))]
        else:
            descriptor.integer_range = [IntegerRange(from_value=int(least), to_value=int(most))]
    # rclpy ignores values given for parameters a node does not declare: a typo (`min_frame:=10`) would
    # silently leave the default. A warning, not an error: one params file may serve several nodes (`/**`).
    unknown = sorted(set(getattr(node, "_parameter_overrides", {})) - set(node._parameters))
    for name in unknown:
        close = difflib.get_close_matches(name, [p[0] for p in parameters], n=1)
        hint = f"did you mean {close[0]}? " if close else ""
        node.get_logger().warning(f"ignoring parameter {name!r}: this node has none of that name ({hint}--help lists them)")


def number(node, name: str) -> float:
    """A float parameter's value; ValueError naming the parameter if it is not a number."""
    value = node.get_parameter(name).value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return float(value)


def message_class(type_name: str):
    """'pkg/msg/Type' -> the rclpy message class (the package must be installed and sourced)."""
    from .rosbag import BagError, split_type  # here: every node imports this module, few need the bag reader

    package, namespace, name = split_type(type_name)
    try:
        return getattr(importlib.import_module(f"{package}.{namespace}"), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f"message type {type_name} is not available here ({exc}); source the workspace "
                       "that provides it (ros_ws/install/setup.bash)") from exc


def qos_from_profile(profile: dict, default: dict, unusable: list[str] | None = None) -> QoSProfile:
    """rclpy QoSProfile of a QoS description as rosbag2 writes it (reliability, durability, history by name or rmw
    enum value, depth), e.g. one of a topic's offered_qos_profiles, or messages.topic_qos().

    A setting it lacks takes the one of `default` (a complete, usable description). History unknown with depth 0,
    what rosbag2 records for the publishers it discovers, takes the default history and depth too. Any other
    setting that cannot be used (malformed, system default or unknown, depth 0 with keep_last) takes the default
    as well, and is described in `unusable`."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if profile.get("history") in _UNKNOWN_HISTORY and profile.get("depth") == 0:
        # The middleware does not say: the default keep_last depth is meant, not a problem to report on every
        # topic of every such bag.
        profile = {k: v for k, v in profile.items() if k not in ("history", "depth")}
    problems = [] if unusable is None else unusable

    def setting(name, table, policy):
        value = profile.get(name, default[name])
        # bool is an int to Python (True would read as enum value 1); a list or mapping is not hashable
        if isinstance(value, (str, int)) and not isinstance(value, bool) and value in table:
            return policy[table[value]]
        problems.append(f"{name} {value!r}")
        return policy[table[default[name]]]

    reliability = setting("reliability", _RELIABILITY, ReliabilityPolicy)
    durability = setting("durability", _DURABILITY, DurabilityPolicy)
    history, depth = setting("history", _HISTORY, HistoryPolicy), profile.get("depth", default["depth"])
    if not (isinstance(depth, int) and not isinstance(depth, bool) and 0 < depth <= MAX_QOS_DEPTH):
        if history == HistoryPolicy.KEEP_LAST:  # keep_all has no use for a depth
            problems.append(f"depth {depth!r}")
        depth = default["depth"]
    return QoSProfile(reliability=reliability, durability=durability, history=history, depth=depth)
