"""The benchmark scripts refuse a bad count, output path, model or device in one line (exit 2)
before any work: a paper-size or GPU run once simulated for minutes and then died on its --json
path with a traceback."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import warp as wp

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
