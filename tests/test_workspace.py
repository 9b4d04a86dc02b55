"""The workspace as ROS 2 sees it: the ament index lookup `ros2 run` does, every ad_msgs type through
rclpy serialization, DDS between processes on the test's domain, package data at run time, and
setup.sh's CMake repair and idempotency."""

from __future__ import annotations

import array
import ast
import importlib.metadata
import importlib.util
import math
import os
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
INSTALL = REPO_ROOT / "ros_ws" / "install"
SRC = REPO_ROOT / "ros_ws" / "src"
ADRUN = REPO_ROOT / "scripts" / "adrun"

# Executables and their console-script entry points (SPEC section 4).
EXECUTABLES = {
    "ad_sim": {
        "node": "ad_sim.sim_node:main",
        "record": "ad_sim.record_node:main",
        "generate": "ad_sim.generate:main",
    },
    "ad_estimator": {
        "node": "ad_estimator.node:main",
        "replay": "ad_estimator.replay:main",
        "evaluate": "ad_estimator.evaluate:main",
        "estimate": "ad_estimator.estimate:main",
    },
}
PACKAGES = ["ad_msgs", *EXECUTABLES]
# Installed package data: package -> folder inside the python package.
PACKAGE_DATA = {"ad_sim": "data", "ad_estimator": "models"}

pytestmark = pytest.mark.ros


def run(command: list[str], timeout: float = 120, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, **kwargs)


# --- ament index: what `ros2 run <pkg> <exe>` looks up ------------------------------------------


@pytest.mark.parametrize("package", PACKAGES)
def test_ament_index_finds_package(package):
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    assert Path(get_package_prefix(package)) == INSTALL / package
    manifest = Path(get_package_share_directory(package)) / "package.xml"
    assert ElementTree.parse(manifest).getroot().findtext("name") == package


@pytest.mark.parametrize("package", list(EXECUTABLES))
def test_ament_index_finds_every_executable(package):
    # ros2run: prefix from the ament index, then the executables found under <prefix>/lib/<package>.
    from ament_index_python.packages import get_package_prefix

    libdir = Path(get_package_prefix(package)) / "lib" / package
    found = {path.name for path in libdir.iterdir() if path.is_file() and os.access(path, os.X_OK)}
    assert found == set(EXECUTABLES[package])


@pytest.mark.parametrize("package", list(EXECUTABLES))
def test_executables_point_at_their_modules(package):
    entry_points = {ep.name: ep.value for ep in importlib.metadata.distribution(package).entry_points}
    assert entry_points == EXECUTABLES[package]
    for target in entry_points.values():
        module = target.split(":")[0]
        assert importlib.util.find_spec(module) is not None, f"{module} missing"


def test_adrun_lists_and_rejects():
    listing = run([str(ADRUN), "ad_sim"])
    assert listing.returncode == 0, listing.stderr
    assert listing.stdout.split("\n")[:-1] == [f"ad_sim {name}" for name in sorted(EXECUTABLES["ad_sim"])]

    missing_exe = run([str(ADRUN), "ad_sim", "no_such_executable"])
    assert missing_exe.returncode == 1 and "no executable 'no_such_executable'" in missing_exe.stderr

    missing_package = run([str(ADRUN), "no_such_package", "node"])
    assert missing_package.returncode == 1 and "package 'no_such_package' not found" in missing_package.stderr


@pytest.mark.parametrize(
    "package, executable", [(package, exe) for package, exes in EXECUTABLES.items() for exe in exes]
)
def test_adrun_runs_executable_help(package, executable, ros_domain_id):
    # Every CLI answers --help; this also proves adrun finds and execs the installed script. On a
    # domain of its own, in case an executable starts a node instead.
    result = run([str(ADRUN), package, executable, "--help"], timeout=30)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "usage" in result.stdout.lower()


@pytest.mark.parametrize("package, executable", [("ad_sim", "node"), ("ad_sim", "record"), ("ad_estimator", "node"),
                                                 ("ad_estimator", "replay")])
def test_unreadable_params_file_is_one_line(package, executable, tmp_path, ros_domain_id):
    """The ROS nodes: ROS arguments rcl cannot parse give one line and exit 2, not a traceback."""
    result = run([str(ADRUN), package, executable, "--ros-args", "--params-file", str(tmp_path / "none.yaml")],
                 timeout=30)
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip() == (f"ros2 run {package} {executable}: Failed to parse ROS arguments: Couldn't "
                                     f"parse params file: '--params-file {tmp_path / 'none.yaml'}'. Error: Error "
                                     "opening YAML file"), result.stderr


# --- messages through rclpy serialization -------------------------------------------------------


def same(a, b) -> bool:
    """Field-by-field equality of ROS messages, NaN equal to NaN."""
    if hasattr(type(a), "get_fields_and_field_types"):
        return type(a) is type(b) and all(
            same(getattr(a, field), getattr(b, field)) for field in a.get_fields_and_field_types()
        )
    if isinstance(a, (list, tuple, array.array, bytes)) or type(a).__name__ == "ndarray":
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return a == b


def assert_round_trip(message) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    message_type = type(message)
    default = message_type()
    restored = deserialize_message(serialize_message(message), message_type)
    for field in message_type.get_fields_and_field_types():
        sent, got = getattr(message, field), getattr(restored, field)
        assert not same(sent, getattr(default, field)), f"{message_type.__name__}.{field} left at its default"
        assert same(sent, got), f"{message_type.__name__}.{field}: sent {sent!r}, got {got!r}"


def stamp(sec: int, nanosec: int):
    from builtin_interfaces.msg import Time

    return Time(sec=sec, nanosec=nanosec)


def pose(x: float, y: float, z: float):
    from geometry_msgs.msg import Point, Pose, Quaternion

    return Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=0.5, y=-0.5, z=0.5, w=0.5))


def material_estimate():
    from ad_msgs.msg import MaterialEstimate
    from std_msgs.msg import Header

    return MaterialEstimate(
        header=Header(stamp=stamp(12, 600_000_000), frame_id="ad_sim/view_0"),
        oldest_stamp=stamp(12, 0),
        frames_used=25,
        complete=True,
        material="plasticine",
        class_names=["jelly", "plasticine", "sand"],
        class_probabilities=[0.125, 0.75, 0.125],  # exact in float32
        parameter_names=["youngs_modulus", "poissons_ratio", "yield_stress", "friction_angle"],
        parameters=[2.5e5, 0.41, 3.2e3, math.nan],
        parameter_uncertainties=[1.5e4, 0.02, 4.0e2, math.nan],
        model_id="student-test-0001",
        inference_time=0.0042,
    )


def sim_instance():
    from ad_msgs.msg import SimInstance
    from geometry_msgs.msg import Twist, Vector3
    from std_msgs.msg import Header

    return SimInstance(
        header=Header(stamp=stamp(4, 500_000_000), frame_id="ad_sim/world"),
        episode_id="unseen-sphere-jelly-0003",
        episode_index=3,
        split="unseen",
        shape="sphere",
        material="jelly",
        parameter_names=["youngs_modulus", "poissons_ratio"],
        parameters=[1.5e6, 0.2],
        seed=2**63 + 12345,  # uses the full uint64 width
        initial_pose=pose(0.5, 0.45, 0.6),
        initial_velocity=Twist(linear=Vector3(x=0.1, y=0.0, z=-0.5), angular=Vector3(x=0.0, y=2.0, z=0.0)),
        scale=0.35,
        camera_poses=[pose(1.5, 0.5, 0.8), pose(-0.5, 0.5, 0.8)],
        grid_resolution=32,
        frame_interval=0.025,
        frame_count=25,
        substeps_per_frame=120,
        gravity=9.8,
        density=1000.0,
        particle_count=21_734,
        tracked_particle_count=1024,
    )


def mask_image(value: int, sec: int):
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    return Image(
        header=Header(stamp=stamp(sec, 25_000_000), frame_id="camera"),
        height=2,
        width=3,
        encoding="mono8",
        is_bigendian=0,
        step=3,
        data=[0, value, 0, value, value, 0],
    )


def test_material_estimate_round_trips():
    assert_round_trip(material_estimate())


def test_sim_instance_round_trips():
    assert_round_trip(sim_instance())


def test_estimate_material_request_round_trips():
    from ad_msgs.srv import EstimateMaterial

    assert_round_trip(EstimateMaterial.Request(frames=[mask_image(255, 1), mask_image(128, 2)]))


def test_estimate_material_response_round_trips():
    from ad_msgs.srv import EstimateMaterial

    assert_round_trip(EstimateMaterial.Response(success=True, message="ok", estimate=material_estimate()))


# --- DDS on the fixture's domain ------------------------------------------------------------------

PUBLISHER = textwrap.dedent(
    """
    import sys, time, rclpy
    sys.path.insert(0, sys.argv[1])
    from test_workspace import sim_instance
    from ad_msgs.msg import SimInstance
    rclpy.init()
    node = rclpy.create_node("workspace_test_publisher")
    publisher = node.create_publisher(SimInstance, "/workspace_test/instance", 10)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        publisher.publish(sim_instance())
        time.sleep(0.1)
    """
)


def test_rclpy_context_receives_from_another_process(rclpy_context, ros_domain_id):
    import rclpy
    from ad_msgs.msg import SimInstance
    from rclpy.executors import SingleThreadedExecutor

    assert rclpy_context.get_domain_id() == ros_domain_id == int(os.environ["ROS_DOMAIN_ID"])
    node = rclpy.create_node("workspace_test_listener", context=rclpy_context)
    received = []
    node.create_subscription(SimInstance, "/workspace_test/instance", received.append, 10)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    publisher = subprocess.Popen([sys.executable, "-c", PUBLISHER, str(Path(__file__).parent)])
    try:
        deadline = time.monotonic() + 25
        while not received and time.monotonic() < deadline and publisher.poll() is None:
            executor.spin_once(timeout_sec=0.1)
    finally:
        publisher.terminate()
        publisher.wait(timeout=10)
        executor.shutdown()
        node.destroy_node()
    assert received, "no SimInstance arrived from the publisher process within 25 s"
    assert same(received[0], sim_instance())


def test_ros_domain_is_held_exclusively(ros_domain_id):
    from conftest import DOMAIN_LOCK_DIR

    # Another process (a concurrent test run) cannot claim the domain while this test holds it.
    probe = f"import fcntl; fcntl.flock(open({str(DOMAIN_LOCK_DIR / f'{ros_domain_id}.lock')!r}, 'w'), fcntl.LOCK_EX | fcntl.LOCK_NB)"
    result = run([sys.executable, "-c", probe], timeout=30)
    assert result.returncode != 0 and "BlockingIOError" in result.stderr


# --- package data as found at run time ------------------------------------------------------------


@pytest.mark.parametrize("package", list(PACKAGE_DATA))
def test_package_data_found_at_runtime(package):
    # A fresh interpreter with only the sourced environment, as an executable would run.
    folder = PACKAGE_DATA[package]
    probe = textwrap.dedent(
        f"""
        import importlib.resources, os, {package}
        root = importlib.resources.files("{package}") / "{folder}"
        found = []
        def walk(node, prefix):
            for child in node.iterdir():
                name = prefix + child.name
                if child.is_dir():
                    walk(child, name + "/")
                elif "__pycache__" not in name:
                    found.append(name)
        if root.is_dir():
            walk(root, "")
        print(os.path.realpath({package}.__file__))
        print(*sorted(found), sep="\\n")
        """
    )
    result = run([sys.executable, "-c", probe], cwd="/")
    assert result.returncode == 0, result.stderr
    module_file, *found = result.stdout.strip().split("\n")
    source = SRC / package / package
    assert Path(module_file) == source / "__init__.py", "symlink install should run the source tree"
    expected = sorted(
        str(path.relative_to(source / folder))
        for path in (source / folder).rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    )
    assert [name for name in found if name] == expected


# --- setup.sh -----------------------------------------------------------------------------------


def load_repair_module():
    spec = importlib.util.spec_from_file_location("repair_ros_cmake", REPO_ROOT / "scripts" / "repair_ros_cmake.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_repair_rewrites_build_machine_include_paths(tmp_path):
    repair = load_repair_module()
    export = tmp_path / "share" / "some_msgs" / "cmake" / "export_some_msgs__rosidl_generator_pyExport.cmake"
    export.parent.mkdir(parents=True)
    export.write_text(
        f'INTERFACE_INCLUDE_DIRECTORIES "{repair.BUILD_MACHINE_PYTHON_INCLUDE};{repair.BUILD_MACHINE_NUMPY_INCLUDE}"\n'
    )
    assert repair.repair(tmp_path) == [export]
    directories = export.read_text().split('"')[1].split(";")
    assert len(directories) == 2 and all(Path(d).is_dir() for d in directories)
    assert Path(directories[0], "Python.h").is_file()
    assert Path(directories[1], "numpy", "arrayobject.h").is_file()
    assert repair.repair(tmp_path) == []  # idempotent


def test_venv_cmake_exports_are_repaired():
    prefix = Path(sys.prefix)
    stale = [
        path
        for path in prefix.glob("share/*/cmake/*.cmake")
        if "/opt/python/cp311-cp311" in path.read_text()
    ]
    assert not stale, f"setup.sh left build-machine paths in {stale[:3]}"


def test_setup_rerun_skips_everything():
    started = time.monotonic()
    result = run(["bash", str(REPO_ROOT / "setup.sh")], timeout=600)
    elapsed = time.monotonic() - started
    assert result.returncode == 0, result.stderr[-2000:]
    assert "up to date: requirements.txt" in result.stdout
    assert "up to date: ros_ws build" in result.stdout
    assert elapsed < 30, f"a re-run took {elapsed:.1f} s"


def test_setup_refuses_a_path_with_a_space_before_doing_anything(tmp_path):
    """colcon's generated setup scripts cannot take such a path: setup.sh finished "complete", and then every
    command that sources env.sh failed (exit 127)."""
    checkout = tmp_path / "my checkout"
    checkout.mkdir()
    (checkout / "setup.sh").write_bytes((REPO_ROOT / "setup.sh").read_bytes())
    result = run(["bash", str(checkout / "setup.sh")], timeout=60)
    assert result.returncode == 1 and "a space in the checkout's or the venv's path" in result.stderr, result.stderr
    assert sorted(p.name for p in checkout.iterdir()) == ["setup.sh"]  # no venv, no build


@pytest.mark.parametrize("quoted", [True, False])  # Python 3.11.11 and later write the path unquoted
def test_setup_makes_anew_only_its_own_venv_when_it_was_made_elsewhere(tmp_path, quoted):
    """A moved checkout's venv names its old path in every script; setup.sh makes it anew, but only one it made
    itself (its .ad-setup stamps): a user's VENV is never deleted. One made here is kept, however quoted."""
    checkout, venv = tmp_path / "checkout", tmp_path / "venv"
    checkout.mkdir()
    (checkout / "setup.sh").write_bytes((REPO_ROOT / "setup.sh").read_bytes())
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)

    def setup(made_at: Path) -> subprocess.CompletedProcess:
        (venv / "bin" / "activate").write_text(f'VIRTUAL_ENV="{made_at}"\n' if quoted else f"VIRTUAL_ENV={made_at}\n")
        # The checkout has no requirements.txt: setup.sh stops at step 2, after the venv step.
        return run(["bash", str(checkout / "setup.sh")], env={**os.environ, "VENV": str(venv)}, timeout=120)

    refused = setup(tmp_path / "elsewhere")
    assert refused.returncode == 1 and "and not by setup.sh: remove it, or set VENV=elsewhere" in refused.stderr
    assert (venv / "bin" / "activate").exists()  # a venv setup.sh did not make: left alone
    (venv / ".ad-setup").mkdir()
    kept = setup(venv)
    assert "making it anew" not in kept.stdout and (venv / ".ad-setup").is_dir(), kept.stdout
    remade = setup(tmp_path / "elsewhere")
    assert f"{venv} was made at {tmp_path / 'elsewhere'} (moved?): making it anew" in remade.stdout, remade.stdout
    assert f"creating virtual environment {venv}" in remade.stdout and (venv / "bin" / "pip").exists()


def test_env_sh_in_a_shell_with_set_u_and_with_a_broken_venv():
    """Sourced under `set -u`, colcon's setup.bash killed the calling shell (COLCON_TRACE unbound); with a venv
    that is gone, env.sh returned 0 and left the system Python."""
    env = {k: v for k, v in os.environ.items() if k != "VENV"}
    sourced = run(["bash", "-c", f'set -u; source "{REPO_ROOT}/env.sh"; case $- in *u*) echo still-u;; esac; '
                                 'python -c "import ad_msgs, sys; print(sys.prefix)"'], env=env, timeout=60)
    venv = (INSTALL / ".ad-venv").read_text().strip()  # the venv the workspace was built with
    assert sourced.returncode == 0 and sourced.stdout.split() == ["still-u", venv], sourced
    broken = run(["bash", "-c", f'source "{REPO_ROOT}/env.sh"; echo "rc=$?"'], env={**env, "VENV": "/nonexistent"},
                 timeout=60)
    assert broken.stdout.strip() == "rc=1", broken
    assert "env.sh: the environment is incomplete (venv /nonexistent): run" in broken.stderr, broken


def test_run_demo_takes_relative_paths_from_the_callers_directory(tmp_path, ros_domain_id):
    """run_demo.sh changed to the checkout first: `--logs mylogs` went into the checkout, and a relative
    --model was not found."""
    result = run([str(REPO_ROOT / "run_demo.sh"), "--episodes", "1", "--logs", "mylogs"], cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "mylogs").iterdir()) == ["estimator.log", "simulator.log"]
    assert not (REPO_ROOT / "mylogs").exists()


def _third_party_imports(package_dir: Path) -> set[str]:
    """Top-level modules a package imports (at module level or inside functions), stdlib excluded."""
    names = set()
    for source in package_dir.rglob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names)


def test_runtime_requirements_cover_every_import():
    """A robot with system ROS installs requirements-runtime.txt only: everything ad_sim and
    ad_estimator import, ROS's own packages aside, must be pinned there."""
    lines = (REPO_ROOT / "requirements-runtime.txt").read_text().splitlines()
    runtime = {line.split("==")[0].lower() for line in lines if "==" in line and not line.startswith("#")}
    distributions = importlib.metadata.packages_distributions()
    packages = {"ad_sim", "ad_estimator", "ad_msgs"}
    needed = set()
    for package in ("ad_sim", "ad_estimator"):
        for module in _third_party_imports(REPO_ROOT / "ros_ws/src" / package / package) - packages:
            owners = distributions.get(module, [])
            assert owners, f"{package} imports {module}, which no installed distribution provides"
            # ROS's own (/opt/ros/jazzy has them) are the ros-jazzy-* wheels of this venv: run it here, not on a robot.
            if not any(owner.startswith("ros-") for owner in owners):
                needed |= set(owners)
    assert "libigl" in needed and "onnxruntime" in needed  # the scan found the imports
    missing = {name for name in needed if name.lower() not in runtime}
    assert not missing, f"imported but not in requirements-runtime.txt: {sorted(missing)}"


# rosdep keys (rosdistro's python.yaml) of the libraries that have one; those without come from
# requirements-runtime.txt alone (test_runtime_requirements_cover_every_import).
ROSDEP_KEYS = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml", "tqdm": "python3-tqdm",
               "cv2": "python3-opencv", "matplotlib": "python3-matplotlib"}
NO_ROSDEP_KEY = {"onnxruntime", "warp", "trimesh", "igl", "mcap", "mcap_ros2"}


@pytest.mark.parametrize("package", ["ad_sim", "ad_estimator"])
def test_package_xml_declares_everything_the_package_imports(package):
    """`rosdep install --from-paths ros_ws/src` on a robot installs what package.xml declares: ad_sim imported tqdm
    and ad_estimator matplotlib (evaluate's plots) without declaring them."""
    manifest = ElementTree.parse(REPO_ROOT / "ros_ws/src" / package / "package.xml").getroot()
    declared = {e.text for tag in ("depend", "exec_depend") for e in manifest.iter(tag)}
    distributions = importlib.metadata.packages_distributions()
    for module in sorted(_third_party_imports(REPO_ROOT / "ros_ws/src" / package / package) - {package}):
        ros_package = module in ("ad_sim", "ad_msgs") or any(
            owner.startswith("ros-") for owner in distributions.get(module, []))
        if ros_package:
            assert module in declared, f"{package} imports the ROS package {module}: add <exec_depend>{module}"
        elif module in ROSDEP_KEYS:
            assert ROSDEP_KEYS[module] in declared, f"{package} imports {module}: add <exec_depend>{ROSDEP_KEYS[module]}"
        else:
            assert module in NO_ROSDEP_KEY, f"{package} imports {module}: declare its rosdep key, or list it here"
