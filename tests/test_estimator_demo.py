"""The README's main job (scripts/demo.py): real simulator node -> estimator node, estimates beside ground truth."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

from estimator_models import build_streaming_model

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.ros


def test_demo_prints_estimates_beside_ground_truth(tmp_path, ros_domain_id):
    model = build_streaming_model(tmp_path)  # the bundled model's quality is training's business
    result = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "demo.py"), "--episodes", "2", "--model", str(model),
         "--logs", str(tmp_path / "logs"), "--timeout", "240"],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("unseen-")]
    assert len(rows) == 2, result.stdout
    for row in rows:
        name, truth, estimate = row.split(" | ")
        assert name.split()[0].split("-")[-2] == truth.split()[0]  # the episode's material, as ground truth
        assert re.search(r"^(jelly|plasticine|sand) +\(p=[01]\.\d\d\) .*\[25 frames, [\d.]+ ms\]$", estimate)
    assert "accuracy" in result.stdout
