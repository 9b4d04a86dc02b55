"""The README's result tables say what the measured metrics files say (no hand-copied drift)."""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results" / "paper"

# README section -> {row label (first cell) -> metrics file}
ROWS = {
    "### Unseen objects": {
        "**shipped**: streaming student, full, 20 epochs": "streaming_full20_unseen/metrics.json",
        "streaming, without alignment, 10 epochs": "ablation_none_10ep_unseen.json",
        "streaming, alignment only, 10 epochs": "ablation_align_only_10ep_unseen.json",
        "UniFormer-style clip student, full, 2 epochs (paper preset)": "uniformer_full2_unseen/metrics.json",
    },
    "### Seen objects": {
        "**shipped**: streaming student, full, 20 epochs": "streaming_full20_seen/metrics.json",
        "streaming, without alignment, 10 epochs": "ablation_none_10ep_seen.json",
        "streaming, alignment only, 10 epochs": "ablation_align_only_10ep_seen.json",
    },
}
COLUMNS = [("jelly", "acc"), ("jelly", "youngs_modulus"), ("jelly", "poissons_ratio"),
           ("plasticine", "acc"), ("plasticine", "youngs_modulus"), ("plasticine", "poissons_ratio"),
           ("plasticine", "yield_stress"), ("sand", "acc"), ("sand", "friction_angle"), (None, "regl1")]


def measured(metrics: dict) -> list[float]:
    """The paper-convention row (errors over correctly classified clips) of a metrics table."""
    families = metrics["families"]
    return [metrics["regl1"] if family is None else
            families[family]["acc"] if key == "acc" else families[family]["correct"][key]
            for family, key in COLUMNS]


def table_rows(text: str, heading: str) -> dict[str, list[str]]:
    section = text.split(heading, 1)[1].split("\n### ", 1)[0]
    rows = {}
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def load_table(path: Path, frames: str = "25") -> dict:
    metrics = json.loads(path.read_text())
    return metrics["frames"][frames] if "frames" in metrics else metrics


@pytest.mark.parametrize("heading", list(ROWS))
def test_readme_tables_match_the_metrics_files(heading):
    rows = table_rows((ROOT / "README.md").read_text(), heading)
    for label, file in ROWS[heading].items():
        assert label in rows, f"README {heading!r} lost its row {label!r}"
        expected = [f"{value:.3f}" for value in measured(load_table(RESULTS / file))]
        assert rows[label] == expected, f"README {heading!r} row {label!r} differs from {file}"


def test_readme_temporal_ood_table_matches_the_shipped_model():
    rows = table_rows((ROOT / "README.md").read_text(), "### Temporal OOD")
    path = RESULTS / "streaming_full20_unseen" / "metrics.json"
    frames = [label for label in rows if re.fullmatch(r"\d+", label)]
    assert frames, "the temporal-OOD table has no rows"
    for k in frames:
        assert rows[k] == [f"{value:.3f}" for value in measured(load_table(path, k))], f"K = {k}"
