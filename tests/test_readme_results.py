"""The README's result tables say what the measured metrics files say (no hand-copied drift)."""

import json
import re
from pathlib import Path

import pytest

from ad_estimator.metrics import format_table

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results" / "paper"

SHIPPED = "**shipped**: streaming student, previous frame as a second input channel, full, 20 epochs"
CANDIDATE = "candidate, not shipped: 3 earlier frames as input channels, RegL1 weight 2.0, full, 20 epochs"
SHIPPED_NONE = "ablation of the shipped: without alignment (task loss only), 20 epochs"
SHIPPED_ALIGN_ONLY = "ablation of the shipped: alignment only (teacher's frozen predictor), 20 epochs"
PREVIOUS = "previous shipped: the same with one input channel (the current mask only)"
NONE_20 = "ablation of the previous shipped: without alignment (task loss only), 20 epochs"
NONE_10 = "ablation of the previous shipped: without alignment (task loss only), 10 epochs"
ALIGN_ONLY = "ablation of the previous shipped: alignment only (teacher's frozen predictor), 10 epochs"
ALIGN_1 = "variant of the previous shipped: alignment weight 1.0 instead of 0.1, 20 epochs"
RECIPE = "previous recipe (SPEC weights): streaming, full, 20 epochs"
# README section -> {row label (first cell) -> metrics file}
ROWS = {
    "### Unseen objects": {
        SHIPPED: "streaming_previous_frame20_unseen/metrics.json",
        CANDIDATE: "experiments/earlier_frames/h3reg2_unseen.json",
        SHIPPED_NONE: "ablation_previous_frame_none_20ep_unseen.json",
        SHIPPED_ALIGN_ONLY: "ablation_previous_frame_align_only_20ep_unseen.json",
        PREVIOUS: "streaming_full20_unseen/metrics.json",
        NONE_20: "ablation_none_20ep_unseen.json",
        NONE_10: "ablation_none_10ep_unseen.json",
        ALIGN_ONLY: "ablation_align_only_10ep_unseen.json",
        ALIGN_1: "experiments/align_weight1_full20_unseen.json",
        RECIPE: "experiments/previous_shipped_full20_unseen.json",
        "UniFormer-style clip student, full, 2 epochs (paper preset)": "uniformer_full2_unseen/metrics.json",
    },
    "### Seen objects": {
        SHIPPED: "streaming_previous_frame20_seen/metrics.json",
        CANDIDATE: "experiments/earlier_frames/h3reg2_seen.json",
        SHIPPED_NONE: "ablation_previous_frame_none_20ep_seen.json",
        SHIPPED_ALIGN_ONLY: "ablation_previous_frame_align_only_20ep_seen.json",
        PREVIOUS: "streaming_full20_seen/metrics.json",
        NONE_20: "ablation_none_20ep_seen.json",
        NONE_10: "ablation_none_10ep_seen.json",
        ALIGN_ONLY: "ablation_align_only_10ep_seen.json",
        ALIGN_1: "experiments/align_weight1_full20_seen.json",
        RECIPE: "experiments/previous_shipped_full20_seen.json",
    },
}
SHIPPED_REPORTS = "streaming_previous_frame20_{split}"


def cells(line: str) -> list[str]:
    """The cells of a Markdown table row."""
    return [c.strip() for c in line.strip("|").split("|")]


def measured(path: Path, frames: str = "25") -> list[str]:
    """The paper-convention row of a metrics file for `frames`, as the reports print it
    (ad_estimator.metrics.format_table), without its first (frames) cell."""
    metrics = json.loads(path.read_text())
    tables = metrics["frames"] if "frames" in metrics else {frames: metrics}
    for row in map(cells, format_table(tables).splitlines()[2:]):
        if row[0] == frames:
            return row[1:]
    raise AssertionError(f"{path} has no row for {frames} frames")


def table_rows(text: str, heading: str) -> dict[str, list[str]]:
    section = re.split(r"\n#{2,3} ", text.split(heading, 1)[1], maxsplit=1)[0]  # up to the next heading
    rows = {}
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            row = cells(line)
            rows[row[0]] = row[1:]
    return rows


@pytest.mark.parametrize("heading", list(ROWS))
def test_readme_tables_match_the_metrics_files(heading):
    rows = table_rows((ROOT / "README.md").read_text(), heading)
    for label, file in ROWS[heading].items():
        assert label in rows, f"README {heading!r} lost its row {label!r}"
        assert rows[label] == measured(RESULTS / file), f"README {heading!r} row {label!r} differs from {file}"


def test_readme_temporal_ood_table_matches_the_shipped_model():
    rows = table_rows((ROOT / "README.md").read_text(), "### Temporal OOD")
    path = RESULTS / SHIPPED_REPORTS.format(split="unseen") / "metrics.json"
    frames = [label for label in rows if re.fullmatch(r"\d+", label)]
    assert frames, "the temporal-OOD table has no rows"
    for k in frames:
        assert rows[k] == measured(path, k), f"K = {k}"


@pytest.mark.parametrize("split", ["seen", "unseen"])
def test_the_shipped_reports_are_the_bundled_models(split):
    """The reports the README quotes were made with the bundled weights: the evaluation recorded
    next to the bundled model is the same, and the model card names the bundled model id."""
    models = ROOT / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models"
    bundled = json.loads((models / "default.metrics.json").read_text())
    report = json.loads((RESULTS / SHIPPED_REPORTS.format(split=split) / "metrics.json").read_text())
    assert bundled["evaluation"][split]["full"] == report["frames"]["25"]
    assert f"`{bundled['model_id']}`" in (models / "MODEL_CARD.md").read_text()


def test_readme_psnr_row_is_the_bundled_models():
    """The README's re-simulation PSNR row of the shipped student quotes its JSON, which was made
    with the bundled model."""
    models = ROOT / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models"
    result = json.loads((RESULTS / "resim_psnr_shipped_unseen_64.json").read_text())
    assert result["model_id"] == json.loads((models / "default.metrics.json").read_text())["model_id"]
    assert len(result["episodes"]) == 64
    psnr = result["psnr"]
    families = psnr["families"]
    expected = (f"median {psnr['median']:.1f}, mean {psnr['mean']:.1f} (jelly {families['jelly']:.1f}, "
                f"plasticine {families['plasticine']:.1f}, sand {families['sand']:.1f})")
    rows = table_rows((ROOT / "README.md").read_text(), "### Re-simulation PSNR")
    assert rows["shipped streaming student (previous frame), 64 random unseen instances"][0] == expected


# docs/results/paper/experiments/README.md, section 4: row label -> metrics file
SECTION_4 = {
    "unseen, shipped (`full`, 20 epochs)": "streaming_full20_unseen/metrics.json",
    "unseen, `none`, 10 epochs": "ablation_none_10ep_unseen.json",
    "unseen, `align_only`, 10 epochs": "ablation_align_only_10ep_unseen.json",
    "unseen, `a1`, 20 epochs": "experiments/align_weight1_full20_unseen.json",
    "unseen, previous recipe `none`, 10 epochs": "experiments/previous_recipe_ablation_none_10ep_unseen.json",
    "unseen, previous recipe `align_only`, 10 epochs": "experiments/previous_recipe_ablation_align_only_10ep_unseen.json",
    "seen, shipped": "streaming_full20_seen/metrics.json",
    "seen, `none`": "ablation_none_10ep_seen.json",
    "seen, `align_only`": "ablation_align_only_10ep_seen.json",
    "seen, `a1`": "experiments/align_weight1_full20_seen.json",
}


# docs/results/paper/experiments/README.md, section 5: row label -> metrics file
SECTION_5 = {
    "unseen, `pf` (**shipped now**)": "streaming_previous_frame20_unseen/metrics.json",
    "unseen, `w1` (`full`, one input channel)": "streaming_full20_unseen/metrics.json",
    "unseen, `none20`": "ablation_none_20ep_unseen.json",
    "seen, `pf`": "streaming_previous_frame20_seen/metrics.json",
    "seen, `w1`": "streaming_full20_seen/metrics.json",
    "seen, `none20`": "ablation_none_20ep_seen.json",
}


# docs/results/paper/experiments/README.md, section 6: row label -> metrics file
SECTION_6 = {
    "unseen, `pf` (`full`, **shipped**)": "streaming_previous_frame20_unseen/metrics.json",
    "unseen, `pfnone`": "ablation_previous_frame_none_20ep_unseen.json",
    "unseen, `pfalign`": "ablation_previous_frame_align_only_20ep_unseen.json",
    "seen, `pf`": "streaming_previous_frame20_seen/metrics.json",
    "seen, `pfnone`": "ablation_previous_frame_none_20ep_seen.json",
    "seen, `pfalign`": "ablation_previous_frame_align_only_20ep_seen.json",
}


# docs/results/paper/experiments/README.md, section 7: row label -> metrics file
EARLIER_FRAMES = {"h1lr3": "1 earlier frame, lr 3e-4", "h2": "2 earlier frames", "h3": "3 earlier frames",
                  "h3lr3": "3, lr 3e-4", "h5": "5 earlier frames", "h3wide": "3, channels 24-192",
                  "h3reg2": "3, RegL1 weight 2.0", "h3lr3wide": "3, lr 3e-4, channels 24-192"}
SECTION_7 = {f"{split}, `pf` (1 earlier frame, **shipped**)": f"streaming_previous_frame20_{split}/metrics.json"
             for split in ("seen", "unseen")} | {
    f"{split}, `{run}` ({what})": f"experiments/earlier_frames/{run}_{split}.json"
    for split in ("seen", "unseen") for run, what in EARLIER_FRAMES.items()}


@pytest.mark.parametrize("heading,rows_to_files", [("## 4. ", SECTION_4), ("## 5. ", SECTION_5), ("## 6. ", SECTION_6),
                                                   ("## 7. ", SECTION_7)])
def test_experiments_tables_match_the_metrics_files(heading, rows_to_files):
    rows = table_rows((RESULTS / "experiments" / "README.md").read_text(), heading)
    for label, file in rows_to_files.items():
        assert label in rows, f"experiments {heading!r} lost its row {label!r}"
        assert rows[label] == measured(RESULTS / file), f"experiments {heading!r} row {label!r} differs from {file}"
