"""The XML launch files the packages install (share/<pkg>/launch/). This machine has no `ros2 launch`
(no launch packages on PyPI), so these tests check the files' structure against what a launch run
would need: every <node> names an installed executable, every <param> is one that node declares
(read from the same table the node declares them from) with a value of the declared type, every
$(var X) has an <arg>, argument defaults are the nodes' own defaults, and remaps land on SPEC 5's
topics. Two tests start the nodes with the command lines `ros2 launch` would give them (launch_ros:
-r __node:=name, a --params-file of the <param> values, -r from:=to): the estimator alone, and the
sim_estimator pipeline up to an estimate of its first episode.

Checks return lists of problems, so that test_checks_catch_broken_launch_files can show that each
one fails on a broken copy of a launch file."""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import math
import os
import re
import signal
import subprocess
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
import yaml

from ros_procs import wait_for_log

REPO_ROOT = Path(__file__).resolve().parents[1]
INSTALL = REPO_ROOT / "ros_ws" / "install"
SRC = REPO_ROOT / "ros_ws" / "src"

# package -> the launch files it ships (README, "Launch files").
LAUNCH_FILES = {
    "ad_estimator": ["estimator.launch.xml", "sim_estimator.launch.xml"],
    "ad_sim": ["sim.launch.xml"],
}
ALL_FILES = [(package, name) for package, names in LAUNCH_FILES.items() for name in names]
# SPEC 5: the node's remappable input name -> its default topic.
SPEC_REMAPS = {("ad_estimator", "node"): {"mask": "/ad_sim/view_0/mask"}}
# Tags launch_xml and launch_ros know that these files may use.
KNOWN_TAGS = {"arg", "node", "include", "group", "let", "set_env", "unset_env", "timer", "executable",
              "set_parameter", "set_remap", "log"}
# Substitutions of the XML frontend ($(arg x) is ROS 1's spelling and not one of them).
KNOWN_SUBSTITUTIONS = {"var", "env", "find-pkg-share", "find-pkg-prefix", "find-exec", "command", "eval",
                       "dirname", "anon"}
SUBSTITUTION = re.compile(r"\$\(([\w-]+)(?:\s+([^)]*))?\)")
pytestmark = pytest.mark.ros


def installed(package: str, name: str) -> Path:
    return INSTALL / package / "share" / package / "launch" / name


def parse(path: Path) -> ElementTree.Element:
    return ElementTree.parse(path).getroot()


def launch_args(root) -> dict[str, ElementTree.Element]:
    return {arg.get("name"): arg for arg in root.iter("arg")}


def substitute(text: str, root, overrides: dict[str, str] | None = None) -> str:
    """`text` with each $(var X) replaced by the argument's given value or default (KeyError: no <arg>
    or no value)."""
    args = launch_args(root)

    def value(match):
        if match.group(1) != "var":
            raise KeyError(f"only $(var ...) is resolved here, not {match.group(0)}")
        name = (match.group(2) or "").strip()
        if overrides and name in overrides:
            return overrides[name]
        if name not in args or args[name].get("default") is None:
            raise KeyError(name)
        return args[name].get("default")

    return SUBSTITUTION.sub(value, text)


def typed(text: str):
    """A <param value> as launch_ros types it (launch_ros.utilities.evaluate_parameters): YAML rules. An empty
    value loads as None, which some launch_ros versions refuse (TypeError), so this check asks for a string
    that may be empty to be quoted, as launch_ros's docstring advises for substitutions that must stay strings."""
    value = yaml.safe_load(text)
    if value is None:
        raise TypeError(f"launch_ros may refuse the parameter value {text!r} (YAML null); quote it: '...'")
    return value


def declared_parameters(package: str, executable: str) -> dict:
    """name -> default of the parameters the executable's node declares: the PARAMETERS table of the
    module its console script runs, which the node passes to ad_sim.dds.declare_parameters."""
    entry_points = {ep.name: ep.value for ep in importlib.metadata.distribution(package).entry_points
                    if ep.group == "console_scripts"}
    module = importlib.import_module(entry_points[executable].split(":")[0])
    table = module.PARAMETERS
    if isinstance(table, dict):  # ad_estimator: name -> (default, description)
        return {name: default for name, (default, _) in table.items()}
    return {name: default for name, default, _ in table}  # ad_sim: (name, default, description)


def node_name_of(package: str, executable: str) -> str:
    """The node's own name, as its code passes it to rclpy (`super().__init__("...")`)."""
    entry_points = {ep.name: ep.value for ep in importlib.metadata.distribution(package).entry_points
                    if ep.group == "console_scripts"}
    source = Path(importlib.util.find_spec(entry_points[executable].split(":")[0]).origin).read_text()
    names = set(re.findall(r'super\(\)\.__init__\("([\w]+)"', source))
    assert len(names) == 1, f"{package} {executable}: node names {names}"
    return names.pop()


def same_type(value, default) -> bool:
    """Whether a node that declared `default` takes `value` (floats are declared with dynamic typing
    and take ints, ad_sim.dds.declare_parameters; bool is not an int here)."""
    if isinstance(default, float):
        return type(value) in (int, float)
    return type(value) is type(default)


# --- checks: each returns the problems it finds --------------------------------------------------


def structure_problems(root) -> list[str]:
    problems = [] if root.tag == "launch" else [f"root element <{root.tag}>, not <launch>"]
    problems += [f"unknown tag <{child.tag}>" for child in root if child.tag not in KNOWN_TAGS]
    names = []
    for node in root.iter("node"):
        for attribute in ("pkg", "exec", "name"):
            if not node.get(attribute):
                problems.append(f"<node> without {attribute}=: {node.attrib}")
        names.append(node.get("name"))
        for child in node:
            if child.tag not in ("param", "remap"):
                problems.append(f"<node {node.get('name')}> has <{child.tag}>")
            elif child.tag == "param" and (child.get("name") is None or child.get("value") is None):
                problems.append(f"<param> needs name= and value=: {child.attrib}")
            elif child.tag == "remap" and (child.get("from") is None or child.get("to") is None):
                problems.append(f"<remap> needs from= and to=: {child.attrib}")
    problems += [f"two nodes named {name}" for name in set(names) if names.count(name) > 1]
    return problems


def executable_problems(root) -> list[str]:
    """ros2 launch finds a node's executable as ros2 run does: <prefix of pkg>/lib/<pkg>/<exec>; the
    node keeps its own name (parameter files such as config/anytime.yaml are keyed by it)."""
    problems = []
    for node in root.iter("node"):
        package, executable = node.get("pkg"), node.get("exec")
        path = INSTALL / package / "lib" / package / executable
        if not (path.is_file() and os.access(path, os.X_OK)):
            problems.append(f"{package} {executable}: no executable {path}")
            continue
        own = node_name_of(package, executable)
        if node.get("name") != own:
            problems.append(f"{package} {executable} is named {node.get('name')!r}, not its own {own!r}")
    return problems


def parameter_problems(root) -> list[str]:
    """Every <param> is declared by its node, and its value (defaults substituted) has the declared type."""
    problems = []
    for node in root.iter("node"):
        package, executable = node.get("pkg"), node.get("exec")
        declared = declared_parameters(package, executable)
        for param in node.iter("param"):
            name = param.get("name")
            if name not in declared:
                problems.append(f"{package} {executable} declares no parameter {name!r}")
                continue
            try:
                value = typed(substitute(param.get("value"), root))
            except KeyError as missing:
                problems.append(f"{name}: no value for {missing}")
                continue
            except TypeError as refused:
                problems.append(f"{name}: {refused}")
                continue
            if not same_type(value, declared[name]):
                problems.append(f"{package} {executable} {name}: {value!r} ({type(value).__name__}), declared "
                                f"{type(declared[name]).__name__} ({declared[name]!r})")
    return problems


def argument_problems(root) -> list[str]:
    """Every $(var X) has an <arg name=X>, every <arg> is used, every substitution is one the XML
    frontend knows, and an argument's default is one of its <choice>s."""
    problems = []
    args = launch_args(root)
    used = set()
    for element in root.iter():
        for attribute, text in element.attrib.items():
            for match in SUBSTITUTION.finditer(text):
                kind, name = match.group(1), (match.group(2) or "").strip()
                if kind not in KNOWN_SUBSTITUTIONS:
                    problems.append(f"<{element.tag} {attribute}=...>: unknown substitution $({kind} ...)")
                elif kind == "var":
                    used.add(name)
                    if name not in args:
                        problems.append(f"$(var {name}) in <{element.tag} {attribute}=...> has no <arg name={name!r}>")
    problems += [f"<arg {name}> is never used" for name in set(args) - used]
    for name, arg in args.items():
        choices = [choice.get("value") for choice in arg.iter("choice")]
        if choices and arg.get("default") not in choices:
            problems.append(f"<arg {name}> default {arg.get('default')!r} is not among its choices {choices}")
    return problems


def accepted_values() -> dict[str, set[str]]:
    """Parameters that take one of a few values -> those values, as the launch argument spells them."""
    from ad_estimator.window import POLICIES
    from ad_sim.instances import BENCHMARK_SIZES, BENCHMARK_SPLITS

    return {"output_policy": set(POLICIES), "size": set(BENCHMARK_SIZES), "split": set(BENCHMARK_SPLITS)}


def default_problems(root) -> list[str]:
    """A launch argument that sets a parameter has the node's own default, so that launching with no
    arguments behaves as `ros2 run` does; its <choice>s are exactly the values the node accepts."""
    problems = []
    args = launch_args(root)
    accepted = accepted_values()
    for node in root.iter("node"):
        declared = declared_parameters(node.get("pkg"), node.get("exec"))
        for param in node.iter("param"):
            name, match = param.get("name"), re.fullmatch(r"('?)\$\(var (\w+)\)\1", param.get("value") or "")
            if not match or name not in declared or match.group(2) not in args:
                continue  # a fixed value, or a problem the other checks report
            arg = args[match.group(2)]
            # quoted ('$(var X)'): the argument stays a string
            default = arg.get("default") or "" if match.group(1) else typed(arg.get("default") or "")
            own = declared[name]
            if not (default == own or (isinstance(own, float) and math.isnan(own) and default != default)):
                problems.append(f"<arg {arg.get('name')}> default {default!r} is not {node.get('exec')}'s {name} "
                                f"default {own!r}")
            choices = {choice.get("value") for choice in arg.iter("choice")}
            expected = {"true", "false"} if isinstance(own, bool) else accepted.get(name)
            if expected is not None and choices != expected:
                problems.append(f"<arg {arg.get('name')}> choices {sorted(choices)}, the node takes {sorted(expected)}")
    return problems


def remap_problems(root) -> list[str]:
    """Remaps rename a name the node really uses (SPEC 5), their default target is SPEC's default topic,
    and where the file also starts the simulator, a topic it publishes."""
    from ad_sim import messages

    problems = []
    nodes = [(node.get("pkg"), node.get("exec")) for node in root.iter("node")]
    simulator_topics = set(messages.topic_types(1)) if ("ad_sim", "node") in nodes else None
    for node in root.iter("node"):
        remappable = SPEC_REMAPS.get((node.get("pkg"), node.get("exec")), {})
        for remap in node.iter("remap"):
            source, target = remap.get("from"), substitute(remap.get("to"), root)
            if source not in remappable:
                problems.append(f"{node.get('exec')} remaps {source!r}, not one of its names {sorted(remappable)}")
            elif target != remappable[source]:
                problems.append(f"{source} -> {target!r} by default, SPEC's default is {remappable[source]!r}")
            if simulator_topics is not None and target not in simulator_topics:
                problems.append(f"{source} -> {target!r}: the simulator publishes no such topic")
    return problems


CHECKS = [structure_problems, executable_problems, parameter_problems, argument_problems, default_problems,
          remap_problems]


# --- the shipped files -----------------------------------------------------------------------------


@pytest.mark.parametrize("package", list(LAUNCH_FILES))
def test_launch_files_are_installed(package):
    """colcon installs every launch/*.launch.xml of the package to share/<pkg>/launch (setup.py data_files)."""
    source = sorted(path.name for path in (SRC / package / "launch").glob("*.launch.xml"))
    assert source == sorted(LAUNCH_FILES[package])
    for name in source:
        path = installed(package, name)
        assert path.is_file(), f"{path} missing: run ./setup.sh (colcon build)"
        assert path.read_bytes() == (SRC / package / "launch" / name).read_bytes()


@pytest.mark.parametrize("check", CHECKS, ids=lambda check: check.__name__)
@pytest.mark.parametrize("package, name", ALL_FILES, ids=lambda value: value)
def test_launch_file(package, name, check):
    assert check(parse(installed(package, name))) == []


def test_sim_estimator_mirrors_the_demo():
    """sim_estimator.launch.xml starts what scripts/demo.py starts, with the parameters it passes."""
    root = parse(installed("ad_estimator", "sim_estimator.launch.xml"))
    assert sorted((node.get("pkg"), node.get("exec")) for node in root.iter("node")) == [
        ("ad_estimator", "node"), ("ad_sim", "node")]
    demo = (REPO_ROOT / "scripts" / "demo.py").read_text()
    passed = set(re.findall(r'"(\w+):=\{', demo))  # f"-p", f"size:={args.size}", ...
    assert passed == {"model_path", "size", "split", "real_time_factor"}, passed
    assert {param.get("name") for param in root.iter("param")} == passed
    estimator_params = {param.get("name") for node in root.iter("node") if node.get("pkg") == "ad_estimator"
                        for param in node.iter("param")}
    assert estimator_params == {"model_path"}


BROKEN = {
    # id: (file, text replaced, replacement, the check that must object, words of its problem)
    "misspelt-parameter": ("estimator.launch.xml", '<param name="min_frames"', '<param name="min_frame"',
                           parameter_problems, "declares no parameter 'min_frame'"),
    "undeclared-var": ("estimator.launch.xml", 'value="$(var threads)"', 'value="$(var thread)"', argument_problems,
                       "has no <arg name='thread'>"),
    "ros1-arg-substitution": ("estimator.launch.xml", 'value="$(var threads)"', 'value="$(arg threads)"',
                              argument_problems, "unknown substitution $(arg"),
    "wrong-type": ("estimator.launch.xml", '<arg name="reliable" default="false"',
                   '<arg name="reliable" default="maybe"',
                   parameter_problems, "'maybe' (str), declared bool"),
    "default-drift": ("estimator.launch.xml", '<arg name="every_n" default="5"', '<arg name="every_n" default="1"',
                      default_problems, "is not node's every_n default 5"),
    "wrong-choice": ("estimator.launch.xml", '<choice value="anytime"/>', '<choice value="any"/>', default_problems,
                     "the node takes ['anytime', 'episode']"),
    "remap-off-spec": ("estimator.launch.xml", 'default="/ad_sim/view_0/mask"', 'default="/ad_sim/view_0/masks"',
                       remap_problems, "SPEC's default is '/ad_sim/view_0/mask'"),
    "remap-unknown-name": ("estimator.launch.xml", '<remap from="mask"', '<remap from="image"', remap_problems,
                           "remaps 'image'"),
    "missing-executable": ("estimator.launch.xml", 'exec="node"', 'exec="nodes"', executable_problems, "no executable"),
    "renamed-node": ("estimator.launch.xml", 'name="ad_estimator"', 'name="estimator"', executable_problems,
                     "not its own 'ad_estimator'"),
    "unpublished-topic": ("sim_estimator.launch.xml", '<remap from="mask" to="/ad_sim/view_0/mask"/>',
                          '<remap from="mask" to="/ad_sim/view_1/mask"/>', remap_problems,
                          "the simulator publishes no such topic"),
    "fixed-value-wrong-type": ("sim.launch.xml", '<param name="real_time_factor" value="$(var real_time_factor)"/>',
                               '<param name="real_time_factor" value="fast"/>', parameter_problems,
                               "'fast' (str), declared float"),
    "missing-choice": ("sim.launch.xml", '<choice value="paper"/>', '', default_problems,
                       "the node takes ['paper', 'small', 'tiny']"),
    "unknown-tag": ("sim.launch.xml", '<arg name="views"', '<argument name="views"', structure_problems,
                    "unknown tag <argument>"),
    "empty-value-unquoted": ("estimator.launch.xml", 'value="\'$(var model_path)\'"', 'value="$(var model_path)"',
                             parameter_problems, "launch_ros may refuse the parameter value ''"),
}


@pytest.mark.parametrize("name, old, new, check, words", BROKEN.values(), ids=BROKEN.keys())
def test_checks_catch_broken_launch_files(tmp_path, name, old, new, check, words):
    """Each check objects to a launch file broken the way it guards against (the tests above can fail)."""
    package = next(package for package, names in LAUNCH_FILES.items() if name in names)
    text = installed(package, name).read_text()
    assert old in text
    broken = tmp_path / name
    broken.write_text(text.replace(old, new))
    problems = check(parse(broken))
    assert any(words in problem for problem in problems), problems


# --- the estimator started as ros2 launch would start it ----------------------------------------


def launch_command(package: str, name: str, node_index: int, overrides: dict[str, str], params_file: Path) -> list[str]:
    """The command line launch_ros gives a <node> of the file: its executable, `--ros-args`, the node
    name, its <param>s as a parameter file keyed by the node's name, and its remaps."""
    root = parse(installed(package, name))
    node = list(root.iter("node"))[node_index]
    params = {param.get("name"): typed(substitute(param.get("value"), root, overrides)) for param in node.iter("param")}
    params_file.write_text(yaml.safe_dump({f"/{node.get('name')}": {"ros__parameters": params}}))
    command = [str(INSTALL / node.get("pkg") / "lib" / node.get("pkg") / node.get("exec")), "--ros-args",
               "-r", f"__node:={node.get('name')}", "--params-file", str(params_file)]
    for remap in node.iter("remap"):
        command += ["-r", f"{remap.get('from')}:={substitute(remap.get('to'), root, overrides)}"]
    return command


def start_node(command: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    return subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env)


def stop_nodes(processes: list[subprocess.Popen]) -> None:
    """SIGINT (what ros2 launch sends on Ctrl-C), then a kill after 30 s."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes:
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@pytest.mark.parametrize("overrides, expected", [
    ({}, r"input /ad_sim/view_0/mask \(best effort\); policy episode; output /ad_estimator/estimate"),
    ({"mask_topic": "/camera/object_mask", "output_policy": "anytime", "min_frames": "12", "every_n": "3",
      "reliable": "true"},
     r"input /camera/object_mask \(reliable\); policy anytime \(from 12 frames, every 3\); "
     r"output /ad_estimator/estimate"),
], ids=["defaults", "arguments"])
def test_estimator_launch_command_starts_the_node(tmp_path, ros_domain_id, overrides, expected):
    """estimator.launch.xml's node, started with the command line ros2 launch builds from it, comes up
    with the bundled model and what the arguments say (its start-up log line), and stops on SIGINT."""
    log = tmp_path / "node.log"
    process = start_node(launch_command("ad_estimator", "estimator.launch.xml", 0, overrides, tmp_path / "params.yaml"),
                         log)
    try:
        line = wait_for_log(log, r"model .*; input .*", process, timeout=60).group(0)
        assert re.search(expected, line), line
        assert "ad_estimator/models/" in line  # the bundled model (model_path empty)
    finally:
        stop_nodes([process])
    assert process.returncode == 0, log.read_text()


def test_sim_estimator_launch_commands_give_estimates(tmp_path, rclpy_context):
    """sim_estimator.launch.xml's two nodes, started together as ros2 launch starts them, give an estimate
    of the simulator's first episode (matched as scripts/demo.py does: the estimate's oldest stamp is the
    episode's SimInstance stamp), so the estimator is listening before the simulator publishes."""
    import rclpy
    from ad_msgs.msg import MaterialEstimate, SimInstance
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    listener = rclpy.create_node("launch_test_listener", context=rclpy_context)
    instances, estimates = [], []
    listener.create_subscription(SimInstance, "/ad_sim/instance", instances.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
    listener.create_subscription(MaterialEstimate, "/ad_estimator/estimate", estimates.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(listener)

    def stamp(time) -> int:
        return time.sec * 1_000_000_000 + time.nanosec

    def first_episode_estimate():
        first = [stamp(instance.header.stamp) for instance in instances if instance.episode_index == 0]
        return next((estimate for estimate in estimates if stamp(estimate.oldest_stamp) in first), None)

    name = "sim_estimator.launch.xml"
    nodes = list(parse(installed("ad_estimator", name)).iter("node"))
    logs = [tmp_path / f"{node.get('pkg')}.log" for node in nodes]
    processes = [start_node(launch_command("ad_estimator", name, index, {}, tmp_path / f"params{index}.yaml"), log)
                 for index, log in enumerate(logs)]
    try:
        deadline = time.monotonic() + 180
        while first_episode_estimate() is None and time.monotonic() < deadline:
            assert all(process.poll() is None for process in processes), [log.read_text()[-2000:] for log in logs]
            executor.spin_once(timeout_sec=0.1)
    finally:
        stop_nodes(processes)
        executor.shutdown()
        listener.destroy_node()
    estimate = first_episode_estimate()
    assert estimate is not None, (f"no estimate of episode 0 within 180 s ({len(instances)} instances, "
                                  f"{len(estimates)} estimates)\n" + "\n".join(log.read_text()[-2000:] for log in logs))
    first = next(instance for instance in instances if instance.episode_index == 0)
    assert first.split == "unseen" and estimate.frames_used == 25  # the defaults: tiny unseen, episode policy
    assert all(process.returncode == 0 for process in processes), [log.read_text()[-2000:] for log in logs]
