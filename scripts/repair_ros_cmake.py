#!/usr/bin/env python3
"""Repair the CMake exports of the ROS 2 Jazzy PyPI wheels inside a virtual environment.

The wheels were built in a manylinux container and their exported CMake targets name that
machine's Python and NumPy include directories (/opt/python/cp311-cp311/...). CMake refuses
imported targets whose include directories do not exist, so every rosidl package build fails.
This rewrites those paths to the running interpreter's real ones. Idempotent: a repaired file
no longer contains the build machine's paths and is left alone.
"""
import argparse
import sysconfig
from pathlib import Path

import numpy

BUILD_MACHINE_PYTHON_INCLUDE = "/opt/python/cp311-cp311/include/python3.11"
BUILD_MACHINE_NUMPY_INCLUDE = "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"


def replacements() -> dict[str, str]:
    return {
        BUILD_MACHINE_NUMPY_INCLUDE: numpy.get_include(),
        BUILD_MACHINE_PYTHON_INCLUDE: sysconfig.get_paths()["include"],
    }


def repair(prefix: Path) -> list[Path]:
    """Rewrite every exported *.cmake file under prefix; return the files changed."""
    mapping = replacements()
    changed = []
    for path in sorted(prefix.glob("share/*/cmake/*.cmake")) + sorted(prefix.glob("lib/cmake/**/*.cmake")):
        text = path.read_text()
        fixed = text
        for old, new in mapping.items():
            fixed = fixed.replace(old, new)
        if fixed != text:
            path.write_text(fixed)
            changed.append(path)
    return changed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("prefix", type=Path, help="install prefix of the ROS wheels (the virtual environment)")
    args = parser.parse_args()
    if not (args.prefix / "share" / "ament_cmake_core").is_dir():
        raise SystemExit(f"{args.prefix} holds no ROS 2 wheels (share/ament_cmake_core missing): install requirements.txt first")
    for old, new in replacements().items():
        if not Path(new).is_dir():
            raise SystemExit(f"include directory {new} (replacing {old}) does not exist: install the Python headers and numpy")
    changed = repair(args.prefix)
    print(f"repaired {len(changed)} CMake export file(s) under {args.prefix}")


if __name__ == "__main__":
    main()
