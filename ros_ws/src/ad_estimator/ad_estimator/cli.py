"""What the command-line tools of ad_estimator, training and the benchmarks share."""
from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import shutil
import sys
import tempfile
from pathlib import Path


def count(text: str) -> int:
    """argparse type: a whole number >= 0."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return int(text)


def positive(text: str) -> int:
    """argparse type: a whole number >= 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def seed(text: str) -> int:
    """argparse type of --seed: what NumPy's global seed takes, 0 to 2**32 - 1 (beyond, NumPy fails later
    without naming the option)."""
    if not text.isdigit() or int(text) >= 2 ** 32:
        raise argparse.ArgumentTypeError(f"expected a whole number from 0 to {2 ** 32 - 1}, got {text!r}")
    return int(text)


def topic(text: str) -> str:
    """argparse type of a topic name in a bag: a relative name is taken from the root namespace, as a node
    there resolves it (bags hold fully qualified names)."""
    if not text.strip("/"):
        raise argparse.ArgumentTypeError(f"expected a topic name, got {text!r}")
    return text if text.startswith("/") else "/" + text


def _finite(text: str) -> float:
    try:
        return float(text) if math.isfinite(float(text)) else math.nan
    except ValueError:
        return math.nan


def positive_number(text: str) -> float:
    """argparse type: a finite number > 0."""
    if not _finite(text) > 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return float(text)


def non_negative_number(text: str) -> float:
    """argparse type: a finite number >= 0."""
    if not _finite(text) >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return float(text)


def fraction(text: str) -> float:
    """argparse type: a number in [0, 1)."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1), got {text!r}")
    return value


def torch_device(text: str) -> str:
    """argparse type: cpu, cuda or cuda:<index> (what the GPU benchmarks and training run on; any
    other torch device would fail only later, after the data has loaded)."""
    if text in ("cpu", "cuda") or (text.startswith("cuda:") and text[5:].isdigit()):
        return text
    raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:<index>, got {text!r}")


def torch_device_or_auto(text: str) -> str:
    """argparse type: auto (cuda if torch sees a GPU, else cpu) or a torch_device."""
    return text if text == "auto" else torch_device(text)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends "(default: X)" only where there is a default worth showing (not None, False or an
    empty list) and the help text does not already state it."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.default == [] \
                or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


@contextlib.contextmanager
def staged(folder: Path, last: str | None = None):
    """Yields a new folder inside `folder` (made if need be) to write output files in, under their final
    names; on success they are moved into `folder` (os.replace: atomic per file, and on one file system
    since the staging folder is inside it), so a failure or a kill half way (a full disk) leaves what
    `folder` held as it was, instead of a mix of new and old files. The file named `last` (a model's head,
    which names its frame encoder) is removed first and moved in after the others: a kill during the moves
    then leaves no head rather than an old head beside a new encoder."""
    folder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".partial-", dir=folder))
    try:
        yield staging
        if last is not None:
            (folder / last).unlink(missing_ok=True)
        for written in sorted(staging.iterdir(), key=lambda path: path.name == last):
            os.replace(written, folder / written.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def write_text_staged(path: Path, text: str) -> None:
    """path.write_text(text) through `staged`: a failed or killed write leaves the earlier file whole."""
    path = Path(path)
    with staged(path.parent) as folder:
        (folder / path.name).write_text(text)


def interruptible(prog: str):
    """Decorates a tool's main(argv) -> int: a Ctrl-C ends it with one line and status 130 instead of a
    traceback. For tools that write their output only at the end, through staged, so nothing is half written."""
    def decorate(main):
        @functools.wraps(main)
        def run(argv=None):
            try:
                return main(argv)
            except KeyboardInterrupt:
                from tqdm import tqdm

                # A bar the Ctrl-C left open (one made but not yet entered as a context manager) ends its line first.
                for bar in list(tqdm._instances):
                    drawn_in_init = getattr(bar, "sp", None) and not hasattr(bar, "last_print_t")
                    bar.close()
                    if drawn_in_init:  # interrupted in tqdm's __init__ after its first draw: close() ends no line
                        bar.fp.write("\n")
                print(f"{prog}: interrupted; nothing was written", file=sys.stderr)
                return 130
        return run
    return decorate
