"""The README's result tables say what the measured metrics files say (no hand-copied drift)."""

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

from ad_estimator.metrics import (_SHORT, Predictions, error_by_true_value, format_calibration, format_table,
                                  table_cell, uncertainty_calibration)
from ad_sim.materials import FRAME_COUNT

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results" / "paper"

SHIPPED = "**shipped**: streaming student, 3 earlier frames as input channels, RegL1 weight 2.0, full, 20 epochs"
SHIPPED_NONE = "ablation of the shipped: without alignment (task loss only), 20 epochs"
SHIPPED_ALIGN_ONLY = "ablation of the shipped: alignment only (teacher's frozen predictor), 20 epochs"
PREVIOUS = "previous shipped: 1 earlier frame as input channel, RegL1 weight 1.0, full, 20 epochs"
PREVIOUS_NONE = "ablation of the previous shipped: without alignment (task loss only), 20 epochs"
PREVIOUS_ALIGN_ONLY = "ablation of the previous shipped: alignment only (teacher's frozen predictor), 20 epochs"
BEFORE = "shipped before that: the current mask only (no earlier frame), full, 20 epochs"
# README section -> {row label (first cell) -> metrics file}
ROWS = {
    f"### {title}": {
        SHIPPED: f"streaming_earlier3_reg2_{split}/metrics.json",
        SHIPPED_NONE: f"ablation_earlier3_reg2_none_20ep_{split}.json",
        SHIPPED_ALIGN_ONLY: f"ablation_earlier3_reg2_align_only_20ep_{split}.json",
        PREVIOUS: f"streaming_previous_frame20_{split}/metrics.json",
        PREVIOUS_NONE: f"ablation_previous_frame_none_20ep_{split}.json",
        PREVIOUS_ALIGN_ONLY: f"ablation_previous_frame_align_only_20ep_{split}.json",
        BEFORE: f"streaming_full20_{split}/metrics.json",
    } | ({"UniFormer-style clip student, full, 2 epochs (paper preset)": "uniformer_full2_unseen/metrics.json"}
         if split == "unseen" else {})
    for title, split in (("Unseen objects", "unseen"), ("Seen objects", "seen"))
}
SHIPPED_REPORTS = "streaming_earlier3_reg2_{split}"


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


def test_the_estimator_runtime_reproduces_the_shipped_report():
    """The bundled model run through the robot's code path (ad_estimator.evaluate: MCAP masks,
    the node's preprocessing and frame window) on the regenerated unseen split gives the report's
    accuracies, and its errors differ from the report's (training-side evaluation) by rounding only."""
    runtime = json.loads((RESULTS / SHIPPED_REPORTS.format(split="unseen") / "estimator_runtime.json").read_text())
    report = json.loads((RESULTS / SHIPPED_REPORTS.format(split="unseen") / "metrics.json").read_text())
    a, b = runtime["frames"]["25"], report["frames"]["25"]
    assert a["confusion"] == b["confusion"]
    assert a["regl1"] == pytest.approx(b["regl1"], abs=5e-4)
    for family, errors in b["families"].items():
        for subset in ("correct", "all"):
            for name, value in errors[subset].items():
                assert a["families"][family][subset][name] == pytest.approx(value, abs=5e-4), (family, subset, name)


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
    assert rows["shipped streaming student, 64 random unseen instances"][0] == expected


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
    "unseen, `pf` (shipped after this section)": "streaming_previous_frame20_unseen/metrics.json",
    "unseen, `w1` (`full`, one input channel)": "streaming_full20_unseen/metrics.json",
    "unseen, `none20`": "ablation_none_20ep_unseen.json",
    "seen, `pf`": "streaming_previous_frame20_seen/metrics.json",
    "seen, `w1`": "streaming_full20_seen/metrics.json",
    "seen, `none20`": "ablation_none_20ep_seen.json",
}


# docs/results/paper/experiments/README.md, section 6: row label -> metrics file
SECTION_6 = {
    "unseen, `pf` (`full`, shipped then)": "streaming_previous_frame20_unseen/metrics.json",
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
SECTION_7 = {f"{split}, `pf` (1 earlier frame, shipped then)": f"streaming_previous_frame20_{split}/metrics.json"
             for split in ("seen", "unseen")} | {
    f"{split}, `{run}` ({what})": (f"streaming_earlier3_reg2_{split}/metrics.json" if run == "h3reg2"
                                   else f"experiments/earlier_frames/{run}_{split}.json")
    for split in ("seen", "unseen") for run, what in EARLIER_FRAMES.items()}


# Sections 8 to 10 of docs/results/paper/experiments/README.md compare with the shipped run (seed 0) in rows
# labelled alike.
SHIPPED_SEED_0 = {
    f"{split}, `h3reg2`, seed 0 (**shipped**)": f"streaming_earlier3_reg2_{split}/metrics.json" for split in ("seen", "unseen")
}

# docs/results/paper/experiments/README.md, section 8: row label -> metrics file
SEED_RUNS = {"h3reg2_s1": "`h3reg2`, seed 1", "h3reg2_s2": "`h3reg2`, seed 2", "pf_s1": "`pf`, seed 1",
             "pf_s2": "`pf`, seed 2", "pfreg2": "1 earlier frame, RegL1 weight 2.0", "h3reg3": "3, RegL1 weight 3.0"}
SECTION_8 = SHIPPED_SEED_0 | {f"{split}, `pf`, seed 0": f"streaming_previous_frame20_{split}/metrics.json" for split in ("seen", "unseen")} | {
    f"{split}, {what}": f"experiments/seeds/{run}_{split}.json" for split in ("seen", "unseen") for run, what in SEED_RUNS.items()
} | {f"{split}, `h3reg2`, {ablation}": f"ablation_earlier3_reg2_{ablation}_20ep_{split}.json"
     for split in ("seen", "unseen") for ablation in ("none", "align_only")}


def shipped_and_variants(folder: str, runs: dict[str, str]) -> dict[str, str]:
    """Rows of a section that compares the shipped run with single-seed variants in experiments/<folder>/."""
    return SHIPPED_SEED_0 | {f"{split}, `{run}` ({what})": f"experiments/{folder}/{run}_{split}.json"
                             for split in ("seen", "unseen") for run, what in runs.items()}


# docs/results/paper/experiments/README.md, section 9: row label -> metrics file
SECTION_9 = shipped_and_variants("underfit_check", {
    "selreg": "selected on RegL1", "deep6": "6 temporal blocks", "widet": "temporal width 384",
    "pool8": "8x8 map, not pooled", "nodrop": "no dropout", "fullclips": "full clips only",
    "combo2": "no dropout, 8x8 map", "combo3": "and full clips"})
# section 10
SECTION_10 = shipped_and_variants("regularisation", {
    "drop2": "dropout 0.2", "drop3": "dropout 0.3", "wd1e2": "weight decay 1e-2", "wd5e2": "weight decay 5e-2",
    "shift8": "shift up to 8 px", "zoom10": "zoom ±10%", "aug": "shift 8 px and zoom 10%",
    "augreg": "and dropout 0.2, weight decay 1e-2"}) | {
    f"{split}, the teacher (particle trajectories)": f"experiments/regularisation/teacher_{split}.json"
    for split in ("seen", "unseen")}
# section 11
SECTION_11 = shipped_and_variants("long_teacher", {
    "t30_s0": "30-epoch teacher", "t30_s1": "30-epoch teacher, seed 1", "t30_align03": "and alignment weight 0.3",
    "t30_align1": "and alignment weight 1.0"}) | {
    "unseen, the 10-epoch teacher (section 10)": "experiments/regularisation/teacher_unseen.json"} | {
    f"unseen, the 30-epoch teacher, best of epochs 1-{10 * stop} (epoch {best})":
    f"experiments/long_teacher/teacher30_stop{stop}_unseen.json" for stop, best in ((1, 10), (2, 15), (3, 29))}


# section 13
SECTION_13 = shipped_and_variants("uniformer128", {"uni128": "UniFormer, 20 epochs, batch 4 x 32"}) | {
    f"{split}, `t30_s0` (streaming, the same teacher, section 11)": f"experiments/long_teacher/t30_s0_{split}.json"
    for split in ("seen", "unseen")} | {
    "unseen, `uni20` (6 epochs, section 12; CPU-regenerated split)": "experiments/uniformer20/uni20_unseen.json",
    "unseen, `uni128`, scored here on the CPU-regenerated split": "experiments/uniformer128/uni128_unseen_cpu.json"}


# section 14: the learning curve (unseen only)
LEARNING_CURVE = {"q25": "1/4: 2,250 instances, 80 epochs", "h50": "1/2: 4,500 instances, 40 epochs",
                  "d2": "2x: 18,000 instances, 10 epochs"}
SECTION_14 = {"unseen, `h3reg2`, seed 0 (**shipped**)": SHIPPED_SEED_0["unseen, `h3reg2`, seed 0 (**shipped**)"]} | {
    f"unseen, `{run}` ({what})": f"experiments/learning_curve/{run}_unseen.json" for run, what in LEARNING_CURVE.items()
} | {"unseen, `t30_s0` (1x: 9,000 instances, 20 epochs, section 11)": "experiments/long_teacher/t30_s0_unseen.json",
     "unseen, `t30_s1` (1x, seed 1, section 11)": "experiments/long_teacher/t30_s1_unseen.json"}

# docs/results/paper/experiments/README.md, section 15: grey masks, against section 8's binary runs
GREY_RUNS = {"grey_s0": "grey masks, none, seed 0", "grey_s1": "grey masks, none, seed 1"}
SECTION_15 = {"unseen, `h3reg2`, seed 0 (**shipped**)": SHIPPED_SEED_0["unseen, `h3reg2`, seed 0 (**shipped**)"],
              "unseen, `h3reg2`, none (binary masks, section 8)": "ablation_earlier3_reg2_none_20ep_unseen.json"} | {
    f"unseen, `{run}` ({what})": f"experiments/grey_masks/{run}_unseen.json" for run, what in GREY_RUNS.items()}

# section 16: the same instances thrown down harder, against section 8's runs on the benchmark's scenes
FAST_RUNS = {"fast_s0": "harder impacts, none, seed 0", "fast_s1": "harder impacts, none, seed 1"}
SECTION_16 = {"unseen, `h3reg2`, seed 0 (**shipped**)": SHIPPED_SEED_0["unseen, `h3reg2`, seed 0 (**shipped**)"],
              "unseen, `h3reg2`, none (benchmark scenes, section 8)": "ablation_earlier3_reg2_none_20ep_unseen.json"} | {
    f"unseen, `{run}` ({what})": f"experiments/fast_impacts/{run}_unseen.json" for run, what in FAST_RUNS.items()}

# section 17: averaging seeds and mirrored clips, scored by averaging/average.py on a regenerated seen and unseen
AVERAGED = {"n1": "`n1` (`h3reg2` without alignment, seed 1)", "n2": "`n2` (`h3reg2` without alignment, seed 2)",
            "shipped_mirror": "the shipped model and its mirrored clip (2 views)",
            "avg3": "the average of the 3 (shipped, `n1`, `n2`)",
            "avg3_mirror": "the average of the 3 and their mirrored clips (6 views)"}
SECTION_17 = SHIPPED_SEED_0 | {f"{split}, {what}": f"experiments/averaging/{run}_{split}.json"
                               for run, what in AVERAGED.items() for split in ("seen", "unseen")}


@pytest.mark.parametrize("heading,rows_to_files", [("## 4. ", SECTION_4), ("## 5. ", SECTION_5), ("## 6. ", SECTION_6),
                                                   ("## 7. ", SECTION_7), ("## 8. ", SECTION_8), ("## 9. ", SECTION_9),
                                                   ("## 10. ", SECTION_10), ("## 11. ", SECTION_11),
                                                   ("## 13. ", SECTION_13), ("## 14. ", SECTION_14),
                                                   ("## 15. ", SECTION_15), ("## 16. ", SECTION_16),
                                                   ("## 17. ", SECTION_17)])
def test_experiments_tables_match_the_metrics_files(heading, rows_to_files):
    rows = table_rows((RESULTS / "experiments" / "README.md").read_text(), heading)
    for label, file in rows_to_files.items():
        assert label in rows, f"experiments {heading!r} lost its row {label!r}"
        assert rows[label] == measured(RESULTS / file), f"experiments {heading!r} row {label!r} differs from {file}"


CAMERAS = ("object 1.33x larger", "object 0.8x smaller", "mask grown by 2 px of 512", "mask shrunk by 2 px of 512",
           "every 4th frame lost", "10% of frames lost at random")


def check_camera_rows(rows: dict[str, list[str]], runs: dict[str, Path]) -> None:
    """A section's camera-benchmark rows ("<camera>, <run>") are the saved runs, and its sensitivity table
    ("<camera>": one column per run) is each camera against the run's own simulator-mask RegL1."""
    results = {name: json.loads(path.read_text())["results"] for name, path in runs.items()}
    for name, result in results.items():
        for camera in ("128x128 (simulator)", *CAMERAS):
            expected = cells(format_table({"25": result[camera]}).splitlines()[2])[1:]
            assert rows[f"{camera}, {name}"] == expected, (camera, name)
    for camera in CAMERAS:
        assert rows[camera] == [f"{r[camera]['regl1'] - r['128x128 (simulator)']['regl1']:+.3f}"
                                for r in results.values()], camera


def section_rows(number: int) -> dict[str, list[str]]:
    """Every table row of an experiments section by its first cell, also tables indented in a list item."""
    section = re.split(r"\n## ", (RESULTS / "experiments" / "README.md").read_text().split(f"## {number}. ", 1)[1])[0]
    return {cells(line.strip())[0]: cells(line.strip())[1:] for line in section.splitlines()
            if line.strip().startswith("| ")}


def epoch_rows(history: str) -> list[dict]:
    return json.loads((RESULTS / "experiments" / history).read_text())


def test_experiments_section_12_tables_are_the_saved_runs():
    """Section 12: the camera-benchmark rows are the shipped model's and uni20's saved runs, and
    the epoch table is the two histories."""
    rows = section_rows(12)
    check_camera_rows(rows, {"shipped `h3reg2`": ROOT / "docs" / "results" / "camera_resolution_paper_unseen_20.json",
                             "`uni20`": RESULTS / "experiments" / "uniformer20" / "camera_uni20_paper_unseen_20.json"})
    for label, file in (("unseen, shipped `h3reg2` (CPU-regenerated split)", "shipped_unseen_cpu.json"),
                        ("unseen, `uni20` (CPU-regenerated split)", "uni20_unseen.json")):
        assert rows[label] == measured(RESULTS / "experiments" / "uniformer20" / file), label
    uni, streaming = epoch_rows("uniformer20/uni20.history.json"), epoch_rows("long_teacher/t30_s0.history.json")
    assert len(uni) == 6
    for u, t in zip(uni, streaming):
        assert rows[str(u["epoch"])] == [f"{u['val_regl1']:.3f}", f"{u['val_acc']:.3f}",
                                         f"{t['val_regl1']:.3f}", f"{t['val_acc']:.3f}"]


def test_experiments_section_13_tables_are_the_saved_runs():
    """Section 13: the epoch table is uni128's and t30_s0's histories, all 20 epochs, and the
    camera-benchmark rows are the saved runs of the shipped model, uni20 and uni128."""
    rows = section_rows(13)
    uni, streaming = epoch_rows("uniformer128/uni128.history.json"), epoch_rows("long_teacher/t30_s0.history.json")
    assert len(uni) == len(streaming) == 20
    for u, t in zip(uni, streaming):
        assert rows[str(u["epoch"])] == [f"{u[k]:.3f}" for k in ("train_regl1", "val_regl1", "val_acc", "val_ce")] + [
            f"{t[k]:.3f}" for k in ("train_regl1", "val_regl1", "val_acc")], u["epoch"]
    check_camera_rows(rows, {
        "shipped `h3reg2`": ROOT / "docs" / "results" / "camera_resolution_paper_unseen_20.json",
        "`uni20`": RESULTS / "experiments" / "uniformer20" / "camera_uni20_paper_unseen_20.json",
        "`uni128`": RESULTS / "experiments" / "uniformer128" / "camera_uni128_paper_unseen_20.json"})


def test_readme_calibration_table_is_the_runtime_checks():
    """The README's uncertainty-calibration table is what the bundled model's saved runtime
    predictions give."""
    folder = RESULTS / SHIPPED_REPORTS.format(split="unseen")
    saved = json.loads((folder / "estimator_runtime_predictions.json").read_text())
    assert saved["model_id"] == json.loads((ROOT / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models"
                                            / "default.metrics.json").read_text())["model_id"]
    section = format_calibration(uncertainty_calibration(Predictions.from_episodes(saved["frames"]["25"])))
    expected = [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| family")]
    readme = (ROOT / "README.md").read_text().split("### Uncertainty calibration", 1)[1].split("\n### ", 1)[0]
    assert expected and all(line in readme.splitlines() for line in expected)


def test_experiments_error_by_true_value_table_is_the_saved_predictions():
    """Section 11's error-by-true-value table: the shipped model's and the 30-epoch teacher's
    columns are what error_by_true_value gives on their saved per-episode predictions."""
    from training.evaluate import read_predictions

    heading = "### Error by true value: what the student has and has not learnt"
    section = (RESULTS / "experiments" / "README.md").read_text().split(heading, 1)[1].split("\n## ", 1)[0]
    rows = [cells(line) for line in section.splitlines() if line.startswith("| ") and not line.startswith("| family")]
    shipped, teacher = (error_by_true_value(read_predictions(RESULTS / file)[0][FRAME_COUNT]) for file in (
        f"{SHIPPED_REPORTS.format(split='unseen')}/estimator_runtime_predictions.json",
        "experiments/long_teacher/teacher30_unseen_predictions.json"))
    names = {short: name for name, short in _SHORT.items()}
    assert [(family, names[short]) for family, short, *_ in rows] == [
        (family, name) for family, parameters in shipped.items() for name in parameters]
    for family, short, *values in rows:
        s, t = shipped[family][names[short]], teacher[family][names[short]]
        assert values[:5] == [table_cell(v) for v in (s["all"], s["correlation"], t["all"], t["correlation"],
                                                       s["constant_guess"])], (family, short)


def test_estimator_doc_camera_table_is_the_benchmarks_files():
    """docs/estimator.md's camera table: the figures of benchmarks/camera_resolution.py's saved runs."""
    def load(name):
        return json.loads((ROOT / "docs" / "results" / f"camera_resolution_paper_unseen_20{name}.json").read_text())

    now, stretched, before = load(""), load("_stretched"), load("_before_fix")
    rows = {cells(line)[0]: cells(line)[1:] for line in (ROOT / "docs" / "estimator.md").read_text().splitlines()
            if line.startswith("| 512x")}
    four_three = "512x384 camera (4:3)"
    assert rows["512x512"] == [
        f"RegL1 {before['results']['512x512 camera']['regl1']:.3f}; estimates "
        f"{before['regl1_between_estimates']:.3f} apart from the simulator masks'",
        f"RegL1 {now['results']['512x512 camera']['regl1']:.3f}; identical"]
    assert now["against_simulator_masks"]["512x512 camera"]["regl1_between_estimates"] == 0.0
    old, new = (f["against_simulator_masks"][four_three] for f in (stretched, now))
    assert rows["512x384 (4:3)"] == [
        f"RegL1 {stretched['results'][four_three]['regl1']:.3f}; same family {old['same_family']:.3f}; "
        f"{old['regl1_between_estimates']:.3f} apart",
        f"RegL1 {now['results'][four_three]['regl1']:.3f}; same family {new['same_family']:.3f}; "
        f"{new['regl1_between_estimates']:.3f} apart"]


def test_estimator_doc_framing_table_is_the_benchmarks_file():
    now = json.loads((ROOT / "docs" / "results" / "camera_resolution_paper_unseen_20.json").read_text())
    rows = {cells(line)[0]: cells(line)[1:] for line in (ROOT / "docs" / "estimator.md").read_text().splitlines()
            if line.startswith(("| as in training", "| object ", "| grown ", "| shrunk ", "| every 4th",
                                "| 10% at"))}
    def phi(result):
        return f"{result['families']['sand']['correct']['friction_angle']:.2f}°"

    simulator = now["results"]["128x128 (simulator)"]
    assert rows["as in training"] == [f"{simulator['regl1']:.3f}", "", "", phi(simulator)]
    for framing in ("object 1.33x larger", "object 0.8x smaller"):
        result, against = now["results"][framing], now["against_simulator_masks"][framing]
        assert rows[framing] == [f"{result['regl1']:.3f}", f"{against['same_family']:.3f}",
                                 f"{against['regl1_between_estimates']:.3f}", phi(result)]
    for row, camera in (("grown by 2 px of 512", "mask grown by 2 px of 512"),
                        ("shrunk by 2 px of 512", "mask shrunk by 2 px of 512"),
                        ("every 4th frame", "every 4th frame lost"), ("10% at random", "10% of frames lost at random")):
        result, against = now["results"][camera], now["against_simulator_masks"][camera]
        assert rows[row] == [f"{result['regl1']:.3f}", f"{against['same_family']:.3f}",
                             f"{against['regl1_between_estimates']:.3f}"]


ZOOM = RESULTS / "experiments" / "framing_zoom"


def zoom_cameras() -> dict[str, tuple[dict, dict]]:
    """Per camera of camera_resolution.py: (result, against the simulator's masks) of the shipped model's and the
    --zoom 0.35 student's runs of section 20, by model."""
    runs = {name: json.loads((ZOOM / f"camera_{name}.json").read_text()) for name in ("shipped", "zoom35")}
    return {name: {camera: (result, run["against_simulator_masks"].get(camera, {}))
                   for camera, result in run["results"].items()} for name, run in runs.items()}


def test_estimator_doc_zoom_table_is_section_20s_files():
    runs = zoom_cameras()
    rows = {cells(line)[0]: cells(line)[1:] for line in (ROOT / "docs" / "estimator.md").read_text().splitlines()
            if line.startswith("| framed ")}
    for label, camera in (("framed as in training", "128x128 (simulator)"), ("framed 1.33x larger", CAMERAS[0]),
                          ("framed 0.8x smaller", CAMERAS[1])):
        (shipped, _), (zoom, against) = runs["shipped"][camera], runs["zoom35"][camera]
        between = [f"{against[k]:.3f}" for k in ("same_family", "regl1_between_estimates")] if against else ["", ""]
        assert rows[label] == [f"{shipped['regl1']:.3f}", f"{zoom['regl1']:.3f}", *between], label


def test_experiments_section_20_tables_are_the_saved_runs():
    """Section 20: the unseen row is the --zoom 0.35 report, the no-zoom mean is section 8's and 17's three
    seeds, and the camera table is both models' camera_resolution.py runs."""
    rows = section_rows(20)
    assert rows["without alignment, `--zoom 0.35`"] == measured(ZOOM / "zoom35_unseen.json")
    seeds = [RESULTS / "ablation_earlier3_reg2_none_20ep_unseen.json",
             *(RESULTS / "experiments" / "averaging" / f"n{i}_unseen.json" for i in (1, 2))]
    mean = np.mean([json.loads(f.read_text())["frames"]["25"]["regl1"] for f in seeds])
    assert rows["without alignment, no zoom (3 seeds, mean RegL1)"] == [""] * 9 + [f"{mean:.3f}"]
    runs = zoom_cameras()
    for label, camera in (("128x128 (the simulator's masks)", "128x128 (simulator)"),
                          ("512x384 (4:3)", "512x384 camera (4:3)"), *((c, c) for c in CAMERAS)):
        expected = []
        for name in ("shipped", "zoom35"):
            result, against = runs[name][camera]
            expected += [f"{result['regl1']:.3f}", f"{against['regl1_between_estimates']:.3f}" if against else ""]
        assert rows[label] == expected, label
    assert f"Validation RegL1 at epoch 20: {epoch_rows('framing_zoom/zoom35.history.json')[-1]['val_regl1']:.3f}" in \
        (RESULTS / "experiments" / "README.md").read_text()


def test_experiments_section_14_fit_table_is_the_histories():
    """Section 14: each run's fit (the selected epoch by SPEC's score, training and validation at the end and at
    that epoch) is its history, and its unseen RegL1 its metrics file."""
    rows = section_rows(14)
    runs = {run: f"learning_curve/{run}" for run in LEARNING_CURVE} | {
        run: f"long_teacher/{run}" for run in ("t30_s0", "t30_s1")}
    for run, stem in runs.items():
        history = epoch_rows(f"{stem}.history.json")
        best, last = min(history, key=lambda r: r["val_score"]), history[-1]
        unseen = json.loads((RESULTS / "experiments" / f"{stem}_unseen.json").read_text())["frames"]["25"]
        assert rows[f"`{run}`"] == [str(len(history)), str(best["epoch"])] + [f"{v:.3f}" for v in (
            last["train_regl1"], last["train_ce"], best["val_regl1"], min(r["val_regl1"] for r in history),
            best["val_ce"], last["val_ce"], unseen["regl1"])], run


@pytest.mark.parametrize("section,folder,runs,baseline", [
    (15, "grey_masks", GREY_RUNS, "`h3reg2`, none (binary, section 8)"),
    (16, "fast_impacts", FAST_RUNS, "`h3reg2`, none (benchmark scenes, section 8)"),
    (17, "averaging", ("n1", "n2"), "`h3reg2`, none (section 8)")])
def test_experiments_fit_tables_are_the_histories(section, folder, runs, baseline):
    """Sections 15 to 17: each run's selected epoch (SPEC's score), its validation figures there, its
    lowest validation RegL1 and its training RegL1 at the last epoch are its history's."""
    rows = section_rows(section)
    histories = {baseline: json.loads((RESULTS / "streaming_earlier3_reg2_none.history.json").read_text())} | {
        f"`{run}`": epoch_rows(f"{folder}/{run}.history.json") for run in runs}
    for label, history in histories.items():
        best, last = min(history, key=lambda r: r["val_score"]), history[-1]
        assert len(history) == 20, label
        assert rows[label] == [f"epoch {best['epoch']}"] + [f"{v:.3f}" for v in (
            best["val_acc"], best["val_regl1"], min(r["val_regl1"] for r in history), last["train_regl1"])], label


def test_experiments_section_17_error_table_is_the_saved_errors():
    """Section 17's error table (mean errors, their correlations, the shapes' share) is what
    averaging/errors.py makes of the saved per-clip errors, and those errors average to the
    metrics files' RegL1-level figures (the average of the 3 is the avg3 run's own errors)."""
    spec = importlib.util.spec_from_file_location("errors", RESULTS / "experiments" / "averaging" / "errors.py")
    errors = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(errors)
    clips = json.loads((RESULTS / "experiments" / "averaging" / "unseen_errors.json").read_text())
    table = errors.table(clips)
    rows = section_rows(17)
    for line in table[2:]:
        first, *rest = cells(line)
        assert rows[first] == rest, first
    assert len(clips) == 900
    for run in errors.RUNS:  # jelly E over all jelly clips, as the run's metrics file has it
        mean = np.mean([abs(c["errors"][run]["youngs_modulus"]) for c in clips.values() if c["family"] == "jelly"])
        saved = json.loads((RESULTS / "experiments" / "averaging" / f"{run}_unseen.json").read_text())
        assert mean == pytest.approx(saved["frames"]["25"]["families"]["jelly"]["all"]["youngs_modulus"], abs=1e-5), run


def test_readme_paper_regl1_paragraph_is_what_the_rows_imply():
    """The README's reading of the paper's RegL1 cell: the RegL1 that the paper's row and the shipped row
    imply (regl1_from_errors) over each family's ranges and over the union, in ln and log10 units."""
    from ad_estimator.metrics import family_ranges, regl1_from_errors
    from ad_sim.materials import PARAMETER_RANGES

    readme = (ROOT / "README.md").read_text()
    rows = table_rows(readme, "### Unseen objects")
    names = {"jelly": ("youngs_modulus", "poissons_ratio"),
             "plasticine": ("youngs_modulus", "poissons_ratio", "yield_stress"), "sand": ("friction_angle",)}
    columns = {("jelly", "youngs_modulus"): 1, ("jelly", "poissons_ratio"): 2, ("plasticine", "youngs_modulus"): 4,
               ("plasticine", "poissons_ratio"): 5, ("plasticine", "yield_stress"): 6, ("sand", "friction_angle"): 8}

    def cells_of(label):
        return {f: {n: float(rows[label][columns[f, n]]) for n in ns} for f, ns in names.items()}

    paper, shipped = cells_of("paper, Ours (Full)"), cells_of(next(r for r in rows if r.startswith("**shipped**")))
    union = {f: {n: PARAMETER_RANGES[n] for n in r} for f, r in family_ranges().items()}
    paragraph = readme.split("**The paper's RegL1 cell is not in SPEC 8's units.**", 1)[1].split("\n\n", 1)[0]
    paragraph = " ".join(paragraph.split())
    figures = {"gives 0.082, not 0.067": regl1_from_errors(paper),
               "log10 errors it gives 0.103": regl1_from_errors(paper, log_base=10),
               "(the union), 0.060 (ln)": regl1_from_errors(paper, union),
               "or 0.076 (log10)": regl1_from_errors(paper, union, log_base=10),
               "shipped row gives 0.150": regl1_from_errors(shipped)}
    for text, value in figures.items():
        assert text in paragraph, text
        assert text.split("0.", 1)[1][:3] == f"{value:.3f}"[2:], (text, value)
    assert rows["paper, Ours (Full)"][-1] == "0.067"


# --------------------------------------------------------------------------- figures the tests above did not tie

MODELS = ROOT / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models"
BASELINE = ROOT / "docs" / "results" / "baseline_paper_unseen_32_h200.json"


def test_readme_temporal_ood_table_has_every_k_of_spec_8():
    """SPEC 8's temporal OOD is K in {24, 22, 18, 15}: the README's table has the full clip and each of them
    (the test above checks the rows it finds; a row dropped from the table would pass it)."""
    from ad_estimator.metrics import TEMPORAL_OOD_FRAMES

    assert TEMPORAL_OOD_FRAMES == (24, 22, 18, 15)
    rows = table_rows((ROOT / "README.md").read_text(), "### Temporal OOD")
    assert [label for label in rows if re.fullmatch(r"\d+", label)] == ["25", "24", "22", "18", "15"]


def test_readme_baseline_row_is_the_baseline_json():
    """The per-scene CMA-ES row of the unseen table is the baseline JSON's metrics (its Acc cells, 1 by
    construction, are written as 1)."""
    rows = table_rows((ROOT / "README.md").read_text(), "### Unseen objects")
    saved = json.loads(BASELINE.read_text())
    expected = cells(format_table({"25": saved["metrics"]}).splitlines()[2])[1:]
    row = rows["per-scene CMA-ES baseline (true family given; 32 random instances)"]
    assert len(row) == len(expected)
    assert [float(c) for c in row] == [float(c) for c in expected]
    assert saved["config"]["instances"] == len(saved["fits"]) == 32 and saved["config"]["split"] == "unseen"


# README "Re-simulation PSNR" row label -> its JSON (docs/results/paper/...)
PSNR_ROWS = {
    "shipped streaming student, 64 random unseen instances": "resim_psnr_shipped_unseen_64.json",
    "previous shipped student (1 earlier frame), the same 64 instances": "resim_psnr_previous_frame_unseen_64.json",
    "the student shipped before that (the current mask only), the same 64 instances":
        "resim_psnr_full20_unseen_64.json",
    "an older shipped student (SPEC loss weights), the same 64 instances":
        "experiments/previous_shipped_resim_psnr_unseen_64.json",
    "variant with alignment weight 1.0 (not shipped), the same 64 instances":
        "experiments/align_weight1_resim_psnr_unseen_64.json",
}


def psnr_text(psnr: dict) -> str:
    f = psnr["families"]
    return (f"median {psnr['median']:.1f}, mean {psnr['mean']:.1f} (jelly {f['jelly']:.1f}, "
            f"plasticine {f['plasticine']:.1f}, sand {f['sand']:.1f})")


def test_readme_psnr_table_is_the_saved_runs():
    """Every row of the re-simulation PSNR table is its JSON; the students' rows are on the same 64
    instances; each JSON's summary is its own episodes' PSNRs; the baseline row is the baseline JSON."""
    rows = table_rows((ROOT / "README.md").read_text(), "### Re-simulation PSNR")
    episodes = None
    for label, file in PSNR_ROWS.items():
        result = json.loads((RESULTS / file).read_text())
        assert rows[label][0] == psnr_text(result["psnr"]), label
        psnr = np.array([e["psnr"] for e in result["episodes"]])
        assert result["psnr"]["median"] == pytest.approx(np.median(psnr)) and result["psnr"]["mean"] == pytest.approx(
            psnr.mean()), file
        for family, value in result["psnr"]["families"].items():
            assert value == pytest.approx(psnr[[e["true_material"] == family for e in result["episodes"]]].mean())
        ids = [e["episode_id"] for e in result["episodes"]]
        assert episodes is None or ids == episodes, file
        episodes = ids
    baseline = json.loads(BASELINE.read_text())
    row = rows["per-scene CMA-ES baseline, 10 generations x 16 candidates, 32 random unseen instances"]
    assert row[0] == f"median {baseline['psnr']['median']:.1f} (mean {baseline['psnr']['mean']:.1f}, capped at 100)"
    assert row[1].startswith(f"{baseline['seconds_per_instance']:.2f} s on an H200")
    assert (baseline["config"]["generations"], baseline["config"]["popsize"]) == (10, 16)


# MODEL_CARD "Measured" row label -> metrics file
CARD_ROWS = {"unseen (900)": "streaming_earlier3_reg2_unseen/metrics.json",
             "seen (900)": "streaming_earlier3_reg2_seen/metrics.json",
             "previous bundled model, unseen (1 earlier frame, RegL1 weight 1.0)":
                 "streaming_previous_frame20_unseen/metrics.json"}


def test_model_card_measured_table_and_psnr_are_the_metrics_files():
    """The model card's table (the bundled model's figures a user reads first) and its PSNR sentence say
    what the reports say; only its model id was tied before."""
    card = (MODELS / "MODEL_CARD.md").read_text()
    rows = table_rows(card, "## Measured")
    for label, file in CARD_ROWS.items():
        assert rows[label] == measured(RESULTS / file), label
    shipped = json.loads((RESULTS / PSNR_ROWS["shipped streaming student, 64 random unseen instances"]).read_text())
    previous = json.loads((RESULTS / "resim_psnr_previous_frame_unseen_64.json").read_text())
    text = " ".join(card.split())
    assert (f"Re-simulation PSNR on 64 unseen instances: median {shipped['psnr']['median']:.1f} dB, mean "
            f"{shipped['psnr']['mean']:.1f} (the previous model's: median {previous['psnr']['median']:.1f}, mean "
            f"{previous['psnr']['mean']:.1f}, on the same instances)") in text


def test_the_runtime_metrics_are_the_runtime_predictions_scored_again():
    """estimator_runtime.json (the check the shipped report is held to) is exactly what compute_metrics
    gives on the saved per-episode predictions next to it, every cell."""
    from ad_estimator.metrics import compute_metrics

    folder = RESULTS / SHIPPED_REPORTS.format(split="unseen")
    saved = json.loads((folder / "estimator_runtime_predictions.json").read_text())
    # The file has no "parameter_names": its raw_parameters are in PARAMETER_NAMES order.
    scored = compute_metrics(Predictions.from_episodes(saved["frames"]["25"]))
    runtime = json.loads((folder / "estimator_runtime.json").read_text())["frames"]["25"]
    assert scored["n"] == runtime["n"] == 900 and scored["confusion"] == runtime["confusion"]
    assert scored["regl1"] == pytest.approx(runtime["regl1"], abs=1e-12)
    for family, entry in runtime["families"].items():
        assert scored["families"][family]["acc"] == pytest.approx(entry["acc"], abs=1e-12)
        for subset in ("correct", "all"):
            for name, value in entry[subset].items():
                assert scored["families"][family][subset][name] == pytest.approx(value, abs=1e-12), (family, name)
