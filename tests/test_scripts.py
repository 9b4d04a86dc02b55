"""scripts/preview_episode.py and the GPU machine's shell scripts (gpu_paper.sh, gpu_ddp_check.sh): a bad
argument is one line and a nonzero exit before any work, never a traceback after the simulation or a shell's
own error. env.sh: a checkout moved or copied from where setup.sh set it up is refused, never run silently
with the other checkout's code."""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
import warp as wp

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def preview_episode():
    spec = importlib.util.spec_from_file_location("preview_episode", SCRIPTS / "preview_episode.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


PREVIEW_CASES = [
    (["--instances", "{tmp}/missing.yaml"], "--instances: cannot read {tmp}/missing.yaml: No such file or directory"),
    (["--instances", "{tmp}/bad.yaml"], "--instances: {tmp}/bad.yaml: not valid YAML: expected ',' or ']', but got ':' "
                                        "at line 2"),
    (["--instances", "{tmp}/notes.txt"], "--instances: {tmp}/notes.txt: instance files end in .yaml, .yml or .json"),
    (["-o", "{tmp}/sheet.jpgg"], "-o/--output: OpenCV cannot write 'sheet.jpgg'; give an image name such as episode.png"),
    (["-o", "{tmp}"], "-o/--output: {tmp} is a folder; give a file name, e.g. {tmp}/episode.png"),
    (["-o", "{tmp}/notes.txt/sheet.png"], "-o/--output: {tmp}/notes.txt is a file, not a folder"),
    (["--views", "-2"], "argument --views: expected a whole number >= 1, got '-2'"),
    (["--views", "0"], "argument --views: expected a whole number >= 1, got '0'"),
    (["--views", "100000000"], "--views must be in 1..16, got 100000000"),  # simulated until memory ran out
    (["--instances", "{tmp}/bad.yaml", "--split", "train"],
     "--size/--split choose a benchmark split; give them or --instances, not both"),
    (["--size", "small", "--instances", "{tmp}/bad.yaml"],
     "--size/--split choose a benchmark split; give them or --instances, not both"),
]
if not wp.is_cuda_available():  # was Warp's RuntimeError once the simulation started
    PREVIEW_CASES += [(["--device", "cuda"], "--device: Warp device 'cuda' is not available: no CUDA GPU or driver")]


@pytest.mark.parametrize("argv,expected", PREVIEW_CASES)
def test_preview_episode_refuses_a_bad_argument_before_simulating(tmp_path, capsys, argv, expected):
    (tmp_path / "bad.yaml").write_text("rosbag2_bagfile_information: [unclosed\n  : - x: {")
    (tmp_path / "notes.txt").write_text("- shape: box\n")
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(SystemExit) as exit_info:
        preview_episode().main(["-o", str(tmp_path / "sheet.png"), *[a.format(tmp=tmp_path) for a in argv]])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1].split(": error: ", 1)[1].startswith(expected.format(tmp=tmp_path)), err
    assert "Traceback" not in err and "simulating" not in err
    assert sorted(os.listdir(tmp_path)) == before  # nothing written


def test_preview_episode_writes_its_contact_sheet_into_a_new_folder(tmp_path, capsys):
    out = tmp_path / "new" / "sheet.png"
    assert preview_episode().main(["--views", "2", "-o", str(out)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == str(out)  # after Warp's kernel-load lines
    import cv2
    sheet = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert sheet.shape == (24 + 2 * (128 + 2), 25 * (128 + 2))  # caption, 2 views x 25 frames of 128x128


def run_script(name: str, *args: str, path: str | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if path is not None:
        env["PATH"] = path
    return subprocess.run(["/bin/bash", str(SCRIPTS / name), *args], capture_output=True, text=True, env=env,
                          timeout=60)


def test_gpu_paper_pack_without_work_is_a_usage_error():
    result = run_script("gpu_paper.sh", "--pack")  # was "$1: unbound variable" (exit 1)
    assert result.returncode == 2
    assert result.stderr == "gpu_paper.sh: --pack needs WORK, the folder of an earlier run: --pack WORK [RESULTS]\n"


def test_gpu_paper_pack_of_a_missing_or_empty_work_fails_and_makes_nothing(tmp_path):
    result = run_script("gpu_paper.sh", "--pack", str(tmp_path / "missing"))  # exited 0 without an archive
    assert result.returncode == 1
    assert result.stderr == (f"gpu_paper.sh: --pack: {tmp_path}/missing does not exist; give the WORK folder of an "
                             "earlier run\n")
    assert os.listdir(tmp_path) == []  # no WORK/bags, WORK/run, WORK/results made for it
    (tmp_path / "empty").mkdir()
    result = run_script("gpu_paper.sh", "--pack", str(tmp_path / "empty"))
    assert result.returncode == 1 and "gpu_paper.sh: --pack: nothing to pack in" in result.stderr
    assert os.listdir(tmp_path / "empty") == []


def test_gpu_paper_pack_archives_what_a_run_left(tmp_path):
    work = tmp_path / "work"
    (work / "run" / "models").mkdir(parents=True)
    (work / "run" / "models" / "streaming_full.onnx").write_text("model")
    (work / "run" / "teacher").mkdir()
    (work / "run" / "teacher" / "best.pt").write_text("teacher")
    (work / "run" / "train.log").write_text("log")
    results = tmp_path / "results"
    result = run_script("gpu_paper.sh", "--pack", str(work), str(results))
    assert result.returncode == 0, result.stderr
    with tarfile.open(results / "results.tar.gz") as archive:
        assert {"run/models/streaming_full.onnx", "run/train.log"} <= set(archive.getnames())
    assert (results / "teacher.pt").read_text() == "teacher"


def _bin_without_nvidia_smi(tmp_path: Path) -> Path:
    """A PATH of the few commands gpu_ddp_check.sh runs before its GPU check, and no nvidia-smi."""
    folder = tmp_path / "bin"
    folder.mkdir()
    for command in ("dirname", "wc", "sed"):
        (folder / command).symlink_to(shutil.which(command))
    return folder


def test_gpu_ddp_check_without_nvidia_smi_says_what_it_needs(tmp_path):
    folder = _bin_without_nvidia_smi(tmp_path)
    result = run_script("gpu_ddp_check.sh", str(tmp_path / "work"), path=str(folder))
    assert result.returncode == 1  # was bash's "nvidia-smi: command not found" (exit 127) and nothing else
    assert result.stderr == ("gpu_ddp_check.sh: nvidia-smi not found: this check runs on a machine with 2 or more "
                             "NVIDIA GPUs and their driver\n")
    assert not (tmp_path / "work").exists()


@pytest.mark.parametrize("fake, found", [("echo 0", 1), ("echo 'NVIDIA-SMI has failed' >&2; exit 9", 0)])
def test_gpu_ddp_check_needs_two_gpus(tmp_path, fake, found):
    folder = _bin_without_nvidia_smi(tmp_path)
    (folder / "nvidia-smi").write_text(f"#!/bin/sh\n{fake}\n")
    (folder / "nvidia-smi").chmod(0o755)
    result = run_script("gpu_ddp_check.sh", str(tmp_path / "work"), path=str(folder))
    assert result.returncode == 1
    assert result.stderr == f"gpu_ddp_check.sh: needs 2 or more GPUs, found {found}\n"
    assert not (tmp_path / "work").exists()


def build_shapes():
    import sys

    spec = importlib.util.spec_from_file_location("build_shapes", SCRIPTS / "build_shapes.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["build_shapes"] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("catalog, expected", [
    ('{"version": 1, "shapes": [', "catalog.json is not valid JSON: Expecting value"),  # was JSONDecodeError
    ('{"version": 1}', "does not have the layout `build` writes"),  # was KeyError: 'shapes'
])
def test_build_shapes_verify_reports_a_broken_catalogue(tmp_path, capsys, catalog, expected):
    module = build_shapes()
    shutil.copytree(module.SHAPES_DIR, tmp_path / "shapes")
    assert module.main(["verify", "--shapes-dir", str(tmp_path / "shapes")]) == 0
    (tmp_path / "shapes" / module.CATALOG_FILE).write_text(catalog)
    assert module.main(["verify", "--shapes-dir", str(tmp_path / "shapes")]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("verify: ") and expected in line, line


def test_build_shapes_refuses_a_cache_that_is_a_file_before_building(tmp_path, capsys, monkeypatch):
    module = build_shapes()
    monkeypatch.setattr(module, "build", lambda *a: pytest.fail("built before --cache was checked"))
    (tmp_path / "cache").write_text("")
    with pytest.raises(SystemExit) as exit_info:
        module.main(["build", "--cache", str(tmp_path / "cache"), "--shapes-dir", str(tmp_path / "shapes")])
    assert exit_info.value.code == 2  # was FileExistsError once the synthetic shapes were made
    assert capsys.readouterr().err.splitlines()[-1].endswith(
        f"error: --cache: {tmp_path / 'cache'} is a file; give a folder for the downloaded packages")


def _checkout_as_setup_leaves_it(folder: Path) -> Path:
    """What env.sh reads of a checkout that setup.sh set up: a real venv (its activate names the path it was made at)
    and colcon's install tree, whose local_setup.sh names the path it was built at and whose setup.bash here stands
    for the code that tree runs: the built checkout's, through links to its ros_ws/build and its venv."""
    install = folder / "ros_ws" / "install"
    install.mkdir(parents=True)
    shutil.copy(SCRIPTS.parent / "env.sh", folder / "env.sh")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(folder / ".venv")], check=True, timeout=60)
    (install / "local_setup.sh").write_text(f'_colcon_prefix_sh_COLCON_CURRENT_PREFIX="{install}"\n')  # as colcon
    (install / "setup.bash").write_text(f'export AD_TEST_CODE="{folder}"\n')
    (install / ".ad-venv").write_text(f"{folder / '.venv'}\n")
    return folder


def _source_env(checkout: Path, **env: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if k not in ("VENV", "VIRTUAL_ENV", "AD_TEST_CODE", "AD_ROOT")}
    return subprocess.run(["bash", "-c", f'source "{checkout}/env.sh"; '
                                         'echo "rc=$? code=${AD_TEST_CODE:-} venv=${VIRTUAL_ENV:-}"'],
                          capture_output=True, text=True, env={**clean, **env}, timeout=60)


def test_env_sh_refuses_a_checkout_moved_or_copied_from_elsewhere(tmp_path):
    """A checkout copied to c while b, where it was set up, still existed: c's env.sh returned 0 and ran b's code
    with b's venv, silently (colcon's install tree and the venv's scripts name b). Moved from b: the venv's missing
    activate failed it, but not saying why. Either way setup.sh again is the remedy (it makes both anew)."""
    b = _checkout_as_setup_leaves_it(tmp_path / "b")
    assert _source_env(b).stdout == f"rc=0 code={b} venv={b / '.venv'}\n"
    (tmp_path / "link").symlink_to(b)  # the same checkout through a symbolic link: still itself
    assert _source_env(tmp_path / "link").stdout == f"rc=0 code={b} venv={b / '.venv'}\n"

    c = tmp_path / "c"
    shutil.copytree(b, c, symlinks=True)
    copied = _source_env(c)
    assert copied.stdout == "rc=1 code= venv=\n", copied  # was rc=0, b's code and venv
    assert copied.stderr == (f"env.sh: ros_ws/install was built in {b}, not in this checkout (moved or copied?), and "
                             f"would run the code there or fail: run {c}/setup.sh again, which makes it anew here\n")
    b.rename(tmp_path / "d")  # moved: the old path is gone
    moved = _source_env(tmp_path / "d")
    assert moved.stdout == "rc=1 code= venv=\n" and f"ros_ws/install was built in {b}, not in" in moved.stderr, moved

    # Set up anew in c (what setup.sh does there), but VENV names a venv copied from where it was made.
    shutil.rmtree(c)
    _checkout_as_setup_leaves_it(c)
    assert _source_env(c).stdout == f"rc=0 code={c} venv={c / '.venv'}\n"
    shutil.copytree(c / ".venv", tmp_path / "venv", symlinks=True)
    other = _source_env(c, VENV=str(tmp_path / "venv"))
    assert other.stdout == "rc=1 code= venv=\n", other
    assert f"env.sh: the venv {tmp_path / 'venv'} was made at {c / '.venv'} (moved or copied?)" in other.stderr


@pytest.mark.ros
def test_colcon_names_where_it_built_the_workspace_as_env_sh_reads_it():
    """env.sh's moved-checkout check reads this line of colcon's local_setup.sh (the test above writes its like):
    a colcon that wrote it otherwise would turn the check off without a word."""
    install = SCRIPTS.parent / "ros_ws" / "install"
    prefix = "_colcon_prefix_sh_COLCON_CURRENT_PREFIX="
    lines = [line for line in (install / "local_setup.sh").read_text().splitlines() if line.startswith(prefix)]
    assert len(lines) == 1 and lines[0][len(prefix)] == lines[0][-1] == '"', lines
    assert os.path.samefile(lines[0][len(prefix) + 1:-1], install)  # the checkout may be reached through a link


def test_env_sh_reads_the_venv_path_of_a_newer_pythons_activate(tmp_path):
    """CPython 3.12.8 and 3.13.1 on (CVE-2024-9287) write the venv's path shell-quoted, so unquoted when it needs no
    quotes, and first in a Cygwin branch: `VIRTUAL_ENV=$(cygpath /path)`. env.sh took that line for the path the venv
    was made at and refused every checkout set up with such a Python as "moved or copied"."""
    b = _checkout_as_setup_leaves_it(tmp_path / "b")
    activate = b / ".venv" / "bin" / "activate"
    venv = b / ".venv"
    text = activate.read_text()
    assert f'VIRTUAL_ENV="{venv}"\n' in text
    activate.write_text(text.replace(f'VIRTUAL_ENV="{venv}"\n', (
        'case "$(uname)" in\n'
        '    CYGWIN*|MSYS*|MINGW*)\n'
        f'        VIRTUAL_ENV=$(cygpath {venv})\n'
        '        export VIRTUAL_ENV\n'
        '        ;;\n'
        '    *)\n'
        f'        export VIRTUAL_ENV={venv}\n'
        '        ;;\n'
        'esac\n')))
    assert _source_env(b).stdout == f"rc=0 code={b} venv={venv}\n"
