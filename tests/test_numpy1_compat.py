"""ad_sim and ad_estimator run on a robot's system ROS 2 Jazzy with Ubuntu's NumPy 1.26.4
(requirements-runtime.txt), while this venv has NumPy 2: nothing here would notice a NumPy-2-only call
until a robot ran it. These tests scan the libraries' sources for the NumPy 2 additions and keyword
changes that NumPy 1.26 does not have or treats otherwise.
"""
from __future__ import annotations

import ast
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = [REPO_ROOT / "ros_ws/src/ad_sim/ad_sim", REPO_ROOT / "ros_ws/src/ad_estimator/ad_estimator"]

# Names added in NumPy 2.x (release notes 2.0-2.3): AttributeError on NumPy 1.26.
NUMPY2_ONLY = {
    "trapezoid", "concat", "pow", "acos", "acosh", "asin", "asinh", "atan", "atanh", "atan2",
    "bitwise_left_shift", "bitwise_right_shift", "bitwise_invert", "bitwise_count", "permute_dims",
    "matrix_transpose", "vecdot", "isdtype", "astype", "unique_all", "unique_counts", "unique_inverse",
    "unique_values", "cumulative_sum", "cumulative_prod", "unstack", "matvec", "vecmat", "long", "ulong",
    "strings",
}
NUMPY2_ONLY_LINALG = {"vector_norm", "matrix_norm", "vecdot", "matrix_transpose", "outer", "cross", "diagonal",
                      "trace", "svdvals"}
# Keywords of numpy functions that NumPy 1.26 lacks (asarray's copy, sort's stable, device) or reads
# otherwise (np.array(copy=False) copies when it must on 1.x and raises on 2.x).
NUMPY2_KEYWORDS = {"copy", "stable", "device"}
# ndarray attributes added in NumPy 2 (not `device`: Warp arrays and options have one too).
NUMPY2_ARRAY_ATTRIBUTES = {"mT"}


def numpy2_only_uses(source: str, filename: str = "<source>") -> list[str]:
    """`file:line: what` for each NumPy-2-only use in `source` (numpy imported as any name)."""
    tree = ast.parse(source, filename)
    aliases, linalg_aliases = set(), set()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "numpy":
                    aliases.add(alias.asname or "numpy")
                elif alias.name == "numpy.linalg" and alias.asname:
                    linalg_aliases.add(alias.asname)
        elif isinstance(node, ast.ImportFrom) and node.module in ("numpy", "numpy.linalg") and node.level == 0:
            names = NUMPY2_ONLY if node.module == "numpy" else NUMPY2_ONLY_LINALG
            found += [f"{filename}:{node.lineno}: from {node.module} import {a.name}"
                      for a in node.names if a.name in names]
            if node.module == "numpy":
                linalg_aliases |= {a.asname or a.name for a in node.names if a.name == "linalg"}

    def numpy_path(expr) -> list[str] | None:
        """['np', 'linalg', 'norm'] for np.linalg.norm with np an alias of numpy, else None."""
        parts = []
        while isinstance(expr, ast.Attribute):
            parts.append(expr.attr)
            expr = expr.value
        if isinstance(expr, ast.Name) and (expr.id in aliases or expr.id in linalg_aliases):
            return ([expr.id] if expr.id in aliases else ["numpy", "linalg"]) + parts[::-1]
        return None

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            path = numpy_path(node)
            if path is not None and len(path) == 2 and path[1] in NUMPY2_ONLY:
                found.append(f"{filename}:{node.lineno}: numpy.{path[1]}")
            elif path is not None and len(path) == 3 and path[1] == "linalg" and path[2] in NUMPY2_ONLY_LINALG:
                found.append(f"{filename}:{node.lineno}: numpy.linalg.{path[2]}")
            elif path is None and node.attr in NUMPY2_ARRAY_ATTRIBUTES and isinstance(node.ctx, ast.Load):
                found.append(f"{filename}:{node.lineno}: .{node.attr} (ndarray attribute of NumPy 2)")
        elif isinstance(node, ast.Call) and numpy_path(node.func) is not None:
            found += [f"{filename}:{node.lineno}: numpy.{'.'.join(numpy_path(node.func)[1:])}({k.arg}=...)"
                      for k in node.keywords if k.arg in NUMPY2_KEYWORDS]
    return found


def test_the_scan_finds_numpy2_only_uses():
    snippet = """
import numpy as np
from numpy import trapezoid
import numpy.linalg as la
a = np.trapezoid([1, 2])
b = np.asarray(a, copy=False)
c = np.linalg.vector_norm(a)
d = la.matrix_norm(a)
e = np.sort(a, stable=True)
f = a.mT
g = np.trapz([1, 2]) + np.asarray(a).astype(np.float32, copy=False).sum() + np.linalg.norm(a)
"""
    found = numpy2_only_uses(snippet)
    assert {line.split(": ", 1)[1] for line in found} == {
        "from numpy import trapezoid", "numpy.trapezoid", "numpy.asarray(copy=...)", "numpy.linalg.vector_norm",
        "numpy.linalg.matrix_norm", "numpy.sort(stable=...)", ".mT (ndarray attribute of NumPy 2)"}


def test_libraries_use_nothing_numpy_1_26_lacks():
    """requirements-runtime.txt pins numpy 1.26.4 (the robot's system ROS is built against NumPy 1.x)."""
    found = []
    for package in PACKAGES:
        for source in sorted(package.rglob("*.py")):
            found += numpy2_only_uses(source.read_text(), str(source.relative_to(REPO_ROOT)))
    assert not found, "NumPy 2 only (the robot runs NumPy 1.26.4, requirements-runtime.txt):\n" + "\n".join(found)


def test_runtime_requirements_keep_numpy_1():
    lines = (REPO_ROOT / "requirements-runtime.txt").read_text().splitlines()
    pins = dict(line.split("==", 1) for line in lines if "==" in line and not line.lstrip().startswith("#"))
    assert pins["numpy"].startswith("1.26."), pins["numpy"]
    assert "torch" not in pins
