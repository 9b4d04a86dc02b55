"""The benchmark scripts refuse a bad count, output path, model or device in one line (exit 2)
before any work: a paper-size or GPU run once simulated for minutes and then died on its --json
path with a traceback."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import warp as wp

from estimator_bags import write_test_bag

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def script(name: str):
    """A benchmark script imported by path (as `python benchmarks/<name>.py` runs it, with its own folder
    on sys.path for `common`)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


CASES = [
    ("camera_resolution", ["--instances", "0"], "argument --instances: expected a whole number >= 1, got '0'"),
    ("camera_resolution", ["--json", "/nonexistent/figures.json"], "the folder /nonexistent does not exist"),
    ("camera_resolution", ["--json", "{tmp}"], "{tmp} is a folder; give a file name, e.g. {tmp}/figures.json"),
    ("camera_resolution", ["--model", "{tmp}/missing.onnx"], "model file not found: {tmp}/missing.onnx"),
    ("mask_sensitivity", ["--json", "{tmp}"], "is a folder; give a file name"),
    ("sim_throughput", ["--instances", "-2"], "argument --instances: expected a whole number >= 1, got '-2'"),
    ("sim_throughput", ["--batch", "0"], "argument --batch: expected a whole number >= 1"),
    ("sim_throughput", ["--block-dim", "-4"], "argument --block-dim: expected a whole number >= 1"),
    ("sim_throughput", ["--device", "cpu", "--profile"],  # it printed an empty kernel table
     "--profile times each CUDA kernel; Warp records no kernel timings on cpu, so give --device cuda"),
    ("gpu_inference", ["--iterations", "0"], "argument --iterations: expected a whole number >= 1"),
    ("gpu_inference", ["--batch", "0"], "argument --batch: expected a whole number >= 1"),
    ("gpu_inference", ["--device", "gpu"], "argument --device: expected cpu, cuda or cuda:<index>, got 'gpu'"),
    ("gpu_inference", ["--device", "cpu", "--checkpoint", "{tmp}/missing.pt"], "--checkpoint: "),
    ("latency", ["--episodes", "0"], "argument --episodes: expected a whole number >= 1"),
    ("latency", ["--threads", "0"], "argument --threads: expected a whole number >= 1"),
    ("latency", ["--no-ros", "--model", "{tmp}/missing.onnx"], "model file not found: {tmp}/missing.onnx"),
    ("latency", ["--no-ros", "--bag", "{tmp}"], "--bag: bag folder {tmp} holds no .mcap file"),
    ("latency", ["--bag", "{tmp}"], "--bag: bag folder {tmp} holds no .mcap file"),  # ROS mode too, before any node
    ("mpm_device_check", ["--output", "{tmp}/x.npz", "--scenes", "0"], "argument --scenes: expected a whole number"),
    # A negative seed was a numpy traceback after the model had loaded.
    ("camera_resolution", ["--seed", "-1"], "argument --seed: expected a whole number >= 0, got '-1'"),
    ("mask_sensitivity", ["--seed", "-1"], "argument --seed: expected a whole number >= 0, got '-1'"),
    ("sim_throughput", ["--seed", "-1"], "argument --seed: expected a whole number >= 0, got '-1'"),
    ("sim_throughput", ["--episodes", "--seed", "-3"], "argument --seed: expected a whole number >= 0, got '-3'"),
    # --rate 0 started the node and then divided by it; -1 and nan published unpaced without a word.
    ("latency", ["--rate", "0"], "argument --rate: expected a number > 0, got '0'"),
    ("latency", ["--no-ros", "--rate", "-1"], "argument --rate: expected a number > 0, got '-1'"),
    ("latency", ["--no-ros", "--rate", "nan"], "argument --rate: expected a number > 0, got 'nan'"),
    ("latency", ["--no-ros", "--recover"], "--recover reads a damaged --bag; give --bag too"),
    # --output to a missing folder simulated first and then died writing.
    ("mpm_device_check", ["--output", "{tmp}/missing/x.npz", "--scenes", "1", "--frames", "2"],
     "argument --output: the folder {tmp}/missing does not exist"),
    ("mpm_device_check", ["--output", "{tmp}"], "argument --output: {tmp} is a folder; give a file name, e.g. {tmp}/cpu.npz"),
    # soak.py runs for minutes to hours: everything is checked before the node starts.
    ("soak", ["--minutes", "0"], "argument --minutes: expected a number > 0, got '0'"),
    ("soak", ["--interval", "nan"], "argument --interval: expected a number > 0, got 'nan'"),
    ("soak", ["--warmup", "-1"], "argument --warmup: expected a number >= 0, got '-1'"),
    ("soak", ["--minutes", "1", "--warmup", "55"], "--warmup 55 s leaves under two --interval (5 s) samples of a 60 s run"),
    ("soak", ["--minutes", "2", "--latency-window", "90"], "--latency-window 90 s is longer than the run after warm-up"),
    # Faster, the bag's 0.9 s pauses between episodes fall under the node's idle flush: not the node robots run.
    ("soak", ["--rate", "3"], "--rate 3: the bag's 0.9 s pauses between episodes would last 0.3 s, not longer than "
                              "the node's idle_flush (0.3 s); use --rate below 3"),
    ("soak", ["--bag", "{tmp}"], "--bag: bag folder {tmp} holds no .mcap file"),
    ("soak", ["--json", "{tmp}"], "{tmp} is a folder; give a file name, e.g. {tmp}/figures.json"),
    ("soak", ["--model", "{tmp}/missing.onnx"], "model file not found: {tmp}/missing.onnx"),
]
if not wp.is_cuda_available():  # a Warp device this machine lacks, before any simulation
    CASES += [(name, ["--device", "cuda"], "Warp device 'cuda' is not available: no CUDA GPU or driver")
              for name in ("camera_resolution", "mask_sensitivity", "sim_throughput")]
    CASES += [("mpm_device_check", ["--output", "{tmp}/x.npz", "--device", "cuda"], "Warp device 'cuda' is not available")]


@pytest.mark.parametrize("name,argv,expected", CASES)
def test_a_bad_argument_is_one_line_before_any_work(name, argv, expected, tmp_path, capsys):
    module = script(name)
    with pytest.raises(SystemExit) as exit_info:
        module.main([a.format(tmp=tmp_path) for a in argv])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert expected.format(tmp=tmp_path) in err
    assert "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == []  # nothing written


def test_mpm_device_check_refuses_to_compare_different_runs(tmp_path, capsys):
    module = script("mpm_device_check")
    assert module.main(["--output", str(tmp_path / "a.npz"), "--scenes", "1", "--frames", "2"]) == 0
    assert module.main(["--output", str(tmp_path / "b.npz"), "--scenes", "2", "--frames", "2"]) == 0
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--compare", str(tmp_path / "a.npz"), str(tmp_path / "b.npz")])
    assert exit_info.value.code == 2
    assert "hold different runs (scenes, families or frames differ)" in capsys.readouterr().err
    assert module.main(["--compare", str(tmp_path / "a.npz"), str(tmp_path / "a.npz")]) == 0
    assert "max |dx| 0.00e+00 m" in capsys.readouterr().out


def test_mpm_device_check_names_the_file_it_writes(tmp_path, capsys):
    """numpy appends .npz to a name without it: the file is named so, and the line says so."""
    module = script("mpm_device_check")
    assert module.main(["--output", str(tmp_path / "cpu"), "--scenes", "1", "--frames", "2"]) == 0
    assert sorted(os.listdir(tmp_path)) == ["cpu.npz"]
    assert capsys.readouterr().out.startswith(f"wrote {tmp_path}/cpu.npz: 1 scenes, 2 frames on cpu")


def _npz_without_families(path):
    import numpy as np
    np.savez(path, x0=np.zeros((2, 3)), F0=np.zeros((2, 3, 3)))


@pytest.mark.parametrize("make,expected", [
    (lambda path: path.write_bytes(b""), "is not a file written by mpm_device_check.py --output (it is empty)"),  # EOFError
    (lambda path: path.write_bytes(b"PK\x03\x04 not a zip"), "(not an .npz file)"),  # BadZipFile
    (lambda path: path.write_text("some text"), "(not an .npz file)"),  # numpy spoke of pickled data
    (_npz_without_families, "(it has no 'families' array)"),  # KeyError
])
def test_mpm_device_check_compares_only_its_own_files(tmp_path, capsys, make, expected):
    module = script("mpm_device_check")
    assert module.main(["--output", str(tmp_path / "good.npz"), "--scenes", "1", "--frames", "2"]) == 0
    bad = tmp_path / "bad.npz"
    make(bad)
    capsys.readouterr()
    for pair in ([bad, tmp_path / "good.npz"], [tmp_path / "good.npz", bad]):
        with pytest.raises(SystemExit) as exit_info:
            module.main(["--compare", *map(str, pair)])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert f"error: {bad} is not a file written by mpm_device_check.py --output" in err
        assert expected in err and "Traceback" not in err


def test_latency_reads_a_damaged_bag_with_recover(tmp_path, capsys):
    """The bad-bag message names --recover, and latency.py has it (it had not)."""
    module = script("latency")
    bag = write_test_bag(tmp_path / "bag")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n  : - x: {")
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--no-ros", "--episodes", "1", "--bag", str(bag)])
    assert exit_info.value.code == 2 and "pass --recover" in capsys.readouterr().err
    with pytest.warns(UserWarning, match="metadata.yaml is unreadable"):
        assert module.main(["--no-ros", "--episodes", "1", "--bag", str(bag), "--recover",
                            "--json", str(tmp_path / "figures.json")]) == 0
    figures = json.loads((tmp_path / "figures.json").read_text())
    assert figures["latency"]["n"] == 25 and figures["setup"]["rate"] is None  # no pacing without ROS


@pytest.mark.ros
def test_latency_records_its_rate_and_keeps_the_nodes_info_lines_out(tmp_path, ros_domain_id):
    out = tmp_path / "figures.json"
    result = subprocess.run([sys.executable, str(BENCHMARKS / "latency.py"), "--episodes", "1", "--rate", "4",
                             "--json", str(out)], capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr
    figures = json.loads(out.read_text())
    assert figures["setup"]["mode"] == "ros" and figures["setup"]["rate"] == 4.0
    assert figures["frames"]["published"] == 25
    assert "[INFO]" not in result.stderr, result.stderr  # the node's per-episode lines (--log-level warn)


def test_record_throughput_refuses_a_bad_ros_domain_id_before_any_work(tmp_path):
    env = {**os.environ, "ROS_DOMAIN_ID": "abc", "TMPDIR": str(tmp_path)}
    result = subprocess.run([sys.executable, str(BENCHMARKS / "record_throughput.py"), "--episodes", "1"],
                            capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 2, result.stderr
    assert "error: ROS_DOMAIN_ID must be a ROS domain, a whole number 0..232 (e.g. 62), got 'abc'" in result.stderr
    assert "Traceback" not in result.stderr and os.listdir(tmp_path) == []  # no work folder made


def test_the_ros_benchmarks_take_a_free_domain_of_1_to_100_when_none_is_set(monkeypatch, tmp_path):
    """As tests/conftest.py does (domains past 101 are not valid for DDS on Linux with many participants), and one
    that no test or benchmark on this machine holds: it could cross-talk with a test run's nodes. record_throughput
    and soak take it from ros_procs.ros_domain."""
    import argparse

    import ros_procs

    assert script("record_throughput").ros_domain is script("soak").ros_domain is ros_procs.ros_domain
    monkeypatch.setattr(ros_procs, "DOMAIN_LOCK_DIR", tmp_path)  # this test's own set of locks
    monkeypatch.setattr(ros_procs, "_held_domains", [])
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    held = [ros_procs.hold_domain(d) for d in range(1, 100)]  # all but 100, as other processes would
    assert ros_procs.ros_domain(argparse.ArgumentParser()) == 100
    assert ros_procs.hold_domain(100) is None  # and it holds it now
    with pytest.raises(SystemExit):
        ros_procs.ros_domain(argparse.ArgumentParser())  # none left: one line, exit 2
    for lock in held + ros_procs._held_domains:
        lock.close()
    monkeypatch.setenv("ROS_DOMAIN_ID", "62")
    assert ros_procs.ros_domain(argparse.ArgumentParser()) == 62


@pytest.mark.parametrize("name", sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem != "common"))
def test_each_script_starts_from_the_repository_root_without_pythonpath(name):
    """As the docs run them (python benchmarks/<name>.py, also on the GPU machine without env.sh):
    each script puts what it imports on its own path."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run([sys.executable, f"benchmarks/{name}.py", "--help"], cwd=BENCHMARKS.parent, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "usage:" in result.stdout


def test_the_documented_scripts_are_executable():
    for path in BENCHMARKS.glob("*.py"):
        if path.read_text().startswith("#!"):
            assert os.access(path, os.X_OK), f"{path.name} has a shebang but is not executable"
