"""python -m training compare (training/compare.py): groups of real metrics files, hand-computed spreads,
one-line errors."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from training.__main__ import main

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "paper"
SEEDS = RESULTS / "experiments" / "seeds"
REAL = json.loads((SEEDS / "h3reg2_s1_unseen.json").read_text())


def _metrics(path: Path, regl1: float, sand_phi: float | None = 3.5) -> Path:
    """A real metrics file with its 25-frame RegL1 and sand phi error replaced."""
    metrics = json.loads(json.dumps(REAL))
    metrics["frames"]["25"]["regl1"] = regl1
    metrics["frames"]["25"]["families"]["sand"]["correct"]["friction_angle"] = sand_phi
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(metrics))
    return path


def _rows(table_lines: list[str]) -> dict[str, dict[str, str]]:
    """Markdown table -> {first cell: {header: cell}} (the last row wins for a repeated first cell)."""
    header, *rows = ([c.strip() for c in line.strip().strip("|").split("|")] for line in table_lines
                     if line.startswith("|") and not line.startswith("|---"))
    return {row[0]: dict(zip(header, row)) for row in rows}


def test_groups_of_runs_give_mean_sd_every_run_and_differences(tmp_path, capsys):
    a = [0.150, 0.155, 0.162]
    b = [0.160, 0.171]
    files_a = [_metrics(tmp_path / "a_s0" / "metrics.json", a[0]), _metrics(tmp_path / "a_s1.json", a[1]),
               _metrics(tmp_path / "a_s2.json", a[2], sand_phi=None)]  # a run where no sand clip qualified
    files_b = [_metrics(tmp_path / "b_s0.json", b[0]), _metrics(tmp_path / "b_s1.json", b[1])]
    file_c = _metrics(tmp_path / "c.json", 0.140)
    out = tmp_path / "out"
    assert main(["compare", "--group", f"A={tmp_path / 'a_s0'},{files_a[1]},{files_a[2]}",  # a report folder
                 "--group", f"B={files_b[0]}, {files_b[1]}", "--group", f"C={file_c}", "--out", str(out)]) == 0
    md = (out / "compare.md").read_text()
    assert capsys.readouterr().out.startswith(md)
    group_table, run_table = md.split("Every run:")
    groups = _rows(group_table.splitlines())
    assert groups["A"]["RegL1"] == f"{np.mean(a):.3f} ± {np.std(a, ddof=1):.3f}" and groups["A"]["n"] == "3"
    assert groups["B"]["RegL1"] == f"{np.mean(b):.3f} ± {np.std(b, ddof=1):.3f}"
    assert groups["C"]["RegL1"] == "0.140" and groups["C"]["n"] == "1"  # one run: its plain value
    assert groups["A"]["sand phi"] == "n/a" and groups["B"]["sand phi"] == "3.500 ± 0.000"
    jelly_e = REAL["frames"]["25"]["families"]["jelly"]["correct"]["youngs_modulus"]
    assert groups["A"]["jelly E"] == f"{jelly_e:.3f} ± 0.000"  # the same in every run
    runs = [line for line in run_table.splitlines() if line.startswith("| ") and not line.startswith("| group")]
    assert [line.split(" | ")[1] for line in runs] == ["a_s0/metrics.json", *(f"{tmp_path.name}/{f.name}" for f in
                                                        (*files_a[1:], *files_b, file_c))]
    # B - A: difference of means with its Welch standard error; 2 of A's runs lie below both B runs.
    se = math.sqrt(np.var(a, ddof=1) / 3 + np.var(b, ddof=1) / 2)
    assert (f"- B: mean difference {np.mean(b) - np.mean(a):+.4f} (B − A), Welch standard error {se:.4f}; "
            "2 of 3 A runs are below every B run") in md
    assert "- C: mean difference -0.0157 (C − A), Welch standard error n/a; 0 of 3 A runs" in md

    result = json.loads((out / "compare.json").read_text())
    assert result["frames"] == 25 and result["which"] == "correct"
    assert result["groups"]["A"]["mean"]["RegL1"] == pytest.approx(np.mean(a))
    assert result["groups"]["A"]["sd"]["RegL1"] == pytest.approx(np.std(a, ddof=1))
    assert result["groups"]["A"]["mean"]["sand phi"] is None
    assert result["groups"]["C"]["n"] == 1 and result["groups"]["C"]["sd"]["RegL1"] is None
    assert [r["RegL1"] for r in result["groups"]["B"]["runs"]] == b
    assert result["groups"]["A"]["runs"][0]["path"] == str(files_a[0])
    (b_vs_a, c_vs_a) = result["differences"]
    assert b_vs_a["regl1_mean_difference"] == pytest.approx(np.mean(b) - np.mean(a))
    assert b_vs_a["welch_standard_error"] == pytest.approx(se) and b_vs_a["first_runs_below_every_run"] == 2
    assert c_vs_a["welch_standard_error"] is None
    assert (out / "compare.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")


def test_one_group_of_one_run_and_the_all_clips_convention(tmp_path):
    out = tmp_path / "out"
    assert main(["compare", "--group", f"only={SEEDS / 'pf_s1_unseen.json'}", "--which", "all", "--frames", "18",
                 "--out", str(out), "--title", "pf seed 1"]) == 0
    md = (out / "compare.md").read_text()
    entry = json.loads((SEEDS / "pf_s1_unseen.json").read_text())["frames"]["18"]
    only = _rows(md.split("Every run:")[0].splitlines())["only"]
    assert only["RegL1"] == f"{entry['regl1']:.3f}"
    assert only["jelly E"] == f"{entry['families']['jelly']['all']['youngs_modulus']:.3f}"
    assert md.startswith("# pf seed 1\n") and "over all clips" in md and "RegL1 against" not in md


def test_three_seeds_of_h3reg2_against_three_of_pf_on_unseen(tmp_path):
    """The repository's seed runs: the shipped recipe (3 earlier frames, RegL1 weight 2) against the previous one."""
    h3reg2 = [RESULTS / "streaming_earlier3_reg2_unseen", SEEDS / "h3reg2_s1_unseen.json",
              SEEDS / "h3reg2_s2_unseen.json"]
    pf = [RESULTS / "streaming_previous_frame20_unseen", SEEDS / "pf_s1_unseen.json", SEEDS / "pf_s2_unseen.json"]
    assert main(["compare", "--group", "h3reg2=" + ",".join(map(str, h3reg2)),
                 "--group", "pf=" + ",".join(map(str, pf)), "--out", str(tmp_path)]) == 0
    groups = json.loads((tmp_path / "compare.json").read_text())["groups"]
    assert round(groups["h3reg2"]["mean"]["RegL1"], 3) == 0.155
    assert round(groups["pf"]["mean"]["RegL1"], 3) == 0.162


@pytest.mark.parametrize("group, content, expected", [
    ("A={tmp}/missing.json", None, "{tmp}/missing.json does not exist; pass a metrics.json"),
    ("A={tmp}", None, "{tmp}/metrics.json does not exist"),  # a folder without a report
    ("A={tmp}/bad.json", b"{not json", "{tmp}/bad.json is not valid JSON"),
    ("A={tmp}/bad.json", b"\xff\xfe\x00", "{tmp}/bad.json is not valid JSON"),
    ("A={tmp}/bad.json", b"[1, 2]", "{tmp}/bad.json has no \"frames\" object, so it is not a metrics file"),
    ("A={tmp}/bad.json", b'{"frames": {"25": {"regl1": 0.1}}}', "{tmp}/bad.json: its 25-frame metrics lack"),
    ("A={tmp}/bad.json", b'{"frames": {"24": {}}}', "{tmp}/bad.json has no entry for 25 frames (it has 24); "
                                                     "choose one of those with --frames"),
    ("A", None, "--group 'A': expected NAME=PATH[,PATH...]"),
    ("={tmp}/x.json", None, "--group '={tmp}/x.json': expected NAME=PATH[,PATH...]"),
    ("A={tmp}/x.json,", None, "--group 'A={tmp}/x.json,': expected NAME=PATH[,PATH...]"),
])
def test_a_bad_group_or_file_is_one_line_naming_it_and_exit_status_1(tmp_path, capsys, group, content, expected):
    if content is not None:
        (tmp_path / "bad.json").write_bytes(content)
    assert main(["compare", "--group", group.format(tmp=tmp_path), "--out", str(tmp_path / "out")]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("python -m training compare: " + expected.format(tmp=tmp_path))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("edit, expected", [
    (lambda m: m["frames"]["25"].update(regl1=[1]), '"frames"["25"]["regl1"] is a list, not a number'),
    (lambda m: m["frames"]["25"].update(regl1="abc"), '"frames"["25"]["regl1"] is "abc", not a number'),
    (lambda m: m["frames"]["25"].update(regl1=True), '"frames"["25"]["regl1"] is true, not a number'),
    (lambda m: m["frames"]["25"]["families"]["sand"].update(acc="0.5"),
     '"frames"["25"]["families"]["sand"]["acc"] is "0.5", not a number'),
    (lambda m: m["frames"].update({"25": []}), '"frames"["25"] is a list, not an object'),
    (lambda m: m["frames"]["25"]["families"].update(jelly=None),
     '"frames"["25"]["families"]["jelly"] is null, not an object'),
    (lambda m: m["frames"]["25"]["families"]["sand"].update(correct="x"),
     '"frames"["25"]["families"]["sand"]["correct"] is "x", not an object'),
    (lambda m: m["frames"]["25"]["families"].pop("sand"),
     'its 25-frame metrics lack "frames"["25"]["families"]["sand"]'),
])
def test_a_metric_that_is_not_a_number_is_named_by_file_and_field(tmp_path, capsys, edit, expected):
    """A metrics value of the wrong JSON type was a TypeError traceback, or a message naming neither file nor
    field ("could not convert string to float", "lack list indices must be integers ...")."""
    bad = _metrics(tmp_path / "bad.json", 0.15)
    metrics = json.loads(bad.read_text())
    edit(metrics)
    bad.write_text(json.dumps(metrics))
    assert main(["compare", "--group", f"A={_metrics(tmp_path / 'a.json', 0.15)}", "--group", f"B={bad}",
                 "--out", str(tmp_path / "out")]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (f"python -m training compare: {bad}: {expected}; pass a metrics.json written by python -m "
                    "training evaluate, or its report folder")
    assert not (tmp_path / "out").exists()


def test_a_repeated_group_name_is_refused(tmp_path, capsys):
    run = str(_metrics(tmp_path / "a.json", 0.15))
    assert main(["compare", "--group", f"A={run}", "--group", f" A ={run}", "--out", str(tmp_path / "out")]) == 1
    assert capsys.readouterr().err.strip() == (f"python -m training compare: --group ' A ={run}': the name 'A' is "
                                               "already used by another --group; give each group its own name")


def test_registered_as_a_training_subcommand_with_help(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--help"])
    assert exit_info.value.code == 0
    assert "--group NAME=PATH[,PATH...]" in capsys.readouterr().out


def test_a_run_without_regl1_and_an_unwritable_out_are_clear(tmp_path, capsys):
    lacking = _metrics(tmp_path / "lacking.json", 0.15)
    metrics = json.loads(lacking.read_text())
    metrics["frames"]["25"]["regl1"] = None
    lacking.write_text(json.dumps(metrics))
    out = tmp_path / "out"
    assert main(["compare", "--group", f"A={_metrics(tmp_path / 'a.json', 0.15)}", "--group", f"B={lacking}",
                 "--out", str(out)]) == 0
    assert "mean difference n/a" in (out / "compare.md").read_text()
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    capsys.readouterr()
    assert main(["compare", "--group", f"A={lacking}", "--out", str(blocked)]) == 1
    err = capsys.readouterr().err.strip()
    assert str(blocked) in err and len(err.splitlines()) == 1


def test_a_report_that_cannot_be_written_leaves_the_earlier_one_whole(tmp_path):
    """The report is written in a staging folder and moved in once complete: under a file size limit that
    stops it at the plot, the earlier report's files are all as they were, and nothing is left over."""
    import subprocess
    import sys

    out = tmp_path / "out"
    groups = ["--group", f"A={_metrics(tmp_path / 'a.json', 0.15)}", "--group", f"B={_metrics(tmp_path / 'b.json', 0.16)}"]
    assert main(["compare", *groups, "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["compare.json", "compare.md", "compare.png"] and len(before["compare.png"]) > 8000
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (8000, 8000)); "
            "from training.__main__ import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "compare", *groups, "--title", "another", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and f"--out {out}: cannot write the report there" in proc.stderr, proc.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_every_run_says_how_many_clips_it_scored_and_a_mismatch_is_said(tmp_path):
    """Runs scored on different numbers of clips (other bags, or episodes left out) do not compare: each
    run's row gives its clips and compare.md says when they differ (before: nothing told them apart)."""
    same, other = _metrics(tmp_path / "a.json", 0.15), _metrics(tmp_path / "b.json", 0.16)
    metrics = json.loads(other.read_text())
    metrics["frames"]["25"]["n"] = 450
    other.write_text(json.dumps(metrics))
    assert main(["compare", "--group", f"A={same}", "--group", f"B={other}", "--out", str(tmp_path / "out")]) == 0
    md = (tmp_path / "out" / "compare.md").read_text()
    runs = _rows(md.split("Every run:")[1].split("\n\n")[1].splitlines())
    assert (runs["A"]["clips"], runs["B"]["clips"]) == (str(REAL["frames"]["25"]["n"]), "450")
    assert f"scored different numbers of clips** (450, {REAL['frames']['25']['n']})" in md
    assert main(["compare", "--group", f"A={same}", "--group", f"B={same}", "--out", str(tmp_path / "same")]) == 0
    assert "different numbers of clips" not in (tmp_path / "same" / "compare.md").read_text()


# ---- mutation-testing audit (round 2)


def test_a_run_tied_with_the_best_run_of_another_group_is_not_below_it(tmp_path):
    """"first runs below every run" counts the reference's runs strictly below the other group's best: a run
    equal to it is not below it (0.160 against a group whose best run is 0.160)."""
    files_a = [_metrics(tmp_path / "a0.json", 0.150), _metrics(tmp_path / "a1.json", 0.160)]
    files_b = [_metrics(tmp_path / "b0.json", 0.160), _metrics(tmp_path / "b1.json", 0.170)]
    out = tmp_path / "out"
    assert main(["compare", "--group", "A=" + ",".join(map(str, files_a)), "--group", "B=" + ",".join(map(str, files_b)),
                 "--out", str(out)]) == 0
    (difference,) = json.loads((out / "compare.json").read_text())["differences"]
    assert difference["first_runs_below_every_run"] == 1 and difference["first_runs"] == 2
    assert "1 of 2 A runs are below every B run" in (out / "compare.md").read_text()
