"""ad_estimator.cli: what the command-line tools share (staged writes, argparse types)."""
from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from ad_estimator import cli


def test_a_staged_text_write_that_fails_leaves_the_earlier_file_whole(tmp_path):
    """resim-psnr, baseline, the pipeline's summary and training's history write their JSON this way: a write
    stopped half way (a 1000-byte file size limit) leaves the earlier file as it was, and nothing beside it."""
    path = tmp_path / "result.json"
    cli.write_text_staged(path, "earlier")
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000)); "
            "from pathlib import Path; from ad_estimator import cli; "
            "cli.write_text_staged(Path(sys.argv[1]), 'x' * 5000)")
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "File too large" in proc.stderr
    assert path.read_text() == "earlier" and [p.name for p in tmp_path.iterdir()] == ["result.json"]
    cli.write_text_staged(path, "new")
    assert path.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_staged_moves_the_last_file_in_after_the_others(tmp_path, monkeypatch):
    """A model's head names its frame encoder: it goes in last, and the old head is removed first."""
    (tmp_path / "head.onnx").write_text("old head")
    moved = []
    replace = cli.os.replace
    monkeypatch.setattr(cli.os, "replace", lambda src, dst: (moved.append((dst.name, (tmp_path / "head.onnx").exists())),
                                                              replace(src, dst)))
    with cli.staged(tmp_path, last="head.onnx") as folder:
        for name in ("head.onnx", "a_encoder.onnx", "z_metrics.json"):
            (folder / name).write_text(f"new {name}")
    assert moved == [("a_encoder.onnx", False), ("z_metrics.json", False), ("head.onnx", False)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_encoder.onnx", "head.onnx", "z_metrics.json"]


@pytest.mark.parametrize("kind, good, bad", [
    (cli.count, {"0": 0, "12": 12}, ["-1", "1.5", "x", ""]),
    (cli.positive, {"1": 1, "7": 7}, ["0", "-3", "2e3"]),
    (cli.positive_number, {"0.5": 0.5, "3": 3.0}, ["0", "-1", "inf", "nan", "x"]),
    (cli.non_negative_number, {"0": 0.0, "1e-4": 1e-4}, ["-1e-9", "inf", "nan"]),
    (cli.fraction, {"0": 0.0, "0.25": 0.25}, ["1", "-0.1", "x"]),
    (cli.torch_device, {"cpu": "cpu", "cuda:1": "cuda:1"}, ["gpu", "cuda:", "cuda:x", "mps"]),
])
def test_argparse_types_take_what_they_say_and_name_what_they_refuse(kind, good, bad):
    for text, value in good.items():
        assert kind(text) == value
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError, match=repr(text).replace("(", r"\(")):
            kind(text)


@pytest.mark.parametrize("where", ["after the constructor", "inside the constructor, after its first draw"])
def test_a_ctrl_c_line_never_lands_on_an_open_progress_bar(capsys, monkeypatch, where):
    """A SIGINT while a bar is drawn and open: the message goes on a line of its own. After the constructor, the bar
    is alive in the traceback and nothing else closes it. Inside it, after its first draw (where estimate's Ctrl-C
    test sends its signal), tqdm's close() ends no line, as the bar is not fully made: the message was appended to
    the bar's line (that test's flake under load)."""
    from tqdm import tqdm

    if where.startswith("inside"):
        draw = tqdm.refresh

        def drawn_then_interrupted(self, *args, **kwargs):
            draw(self, *args, **kwargs)
            raise KeyboardInterrupt

        monkeypatch.setattr(tqdm, "refresh", drawn_then_interrupted)

    @cli.interruptible("tool")
    def main(argv):
        bar = tqdm(range(3), desc="bags", file=sys.stderr, mininterval=0)  # drawn, alive in the traceback
        raise KeyboardInterrupt(bar)

    assert main([]) == 130
    lines = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()
    assert lines[-1] == "tool: interrupted; nothing was written" and lines[-2].startswith("bags:"), lines


def test_a_relative_topic_is_taken_from_the_root_namespace():
    assert cli.topic("ad_sim/view_0/mask") == cli.topic("/ad_sim/view_0/mask") == "/ad_sim/view_0/mask"
    for bad in ("", "/", "//"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a topic name"):
            cli.topic(bad)
