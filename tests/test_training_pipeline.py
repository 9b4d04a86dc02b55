"""`python -m training`: every subcommand has --help; the pipeline goes from bags to an installed,
evaluated ONNX model and re-running it resumes instead of redoing."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from ad_estimator.model import EstimatorModel
from training.__main__ import main
from training.synthetic import write_synthetic_bag

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ("cache", "teacher", "student", "export", "evaluate", "evaluate-teacher", "pipeline")


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert "--seed" in capsys.readouterr().out or command in ("cache", "evaluate", "evaluate-teacher")


def _not_json(constant: str):
    raise AssertionError(f"{constant} is not JSON (jq, browsers and strict parsers refuse it)")


@pytest.mark.parametrize("argv", [["teacher", "--device", "gpu"], ["student", "--epochs", "0"],
                                  ["teacher", "--threads", "-3"], ["student", "--val-fraction", "1.5"],
                                  ["teacher", "--batch-size", "0"], ["pipeline", "--device", "gpu"],
                                  ["teacher", "--seed", "-1"], ["student", "--seed", "4294967296"],
                                  ["export", "--seed", "-1"], ["pipeline", "--seed", "-3"],
                                  ["baseline", "--seed", "-1"], ["resim-psnr", "--seed", "-2"]])
def test_bad_training_options_are_refused_before_any_work(argv, capsys):
    """Each once got as far as torch (a traceback), trained nothing with exit 0, or was accepted."""
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--bags", "b", "--out", "o"] if argv[0] not in ("pipeline", "baseline", "resim-psnr") else argv)
    assert exit_info.value.code == 2
    assert f"argument {argv[1]}: expected" in capsys.readouterr().err


def test_an_out_that_is_a_folder_or_a_file_is_one_line(tmp_path, capsys):
    """An --out that cannot be what the command writes: one line naming it, exit 1, nothing written."""
    (tmp_path / "models").mkdir()
    assert main(["export", "--checkpoint", str(tmp_path / "best.pt"), "--out", str(tmp_path / "models")]) == 1
    assert capsys.readouterr().err == (f"python -m training export: --out {tmp_path / 'models'} is a folder; give the "
                                       f"model's file name, e.g. {tmp_path / 'models' / 'student.onnx'}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models"]
    bag = write_synthetic_bag(tmp_path / "bags" / "train", 4, views=1, seed=3)
    (tmp_path / "afile").write_text("")
    assert main(["teacher", "--bags", str(bag), "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "afile"),
                 "--size", "tiny", "--epochs", "1", "--device", "cpu", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("python -m training teacher: [Errno 17] File exists") and "afile" in err[-1]


def test_ctrl_c_while_the_pipeline_generates_bags_is_an_interrupt_not_a_failure(tmp_path, monkeypatch, capsys):
    import ad_sim.generate

    monkeypatch.setattr(ad_sim.generate, "main", lambda argv: 130)  # what generate returns on Ctrl-C
    assert main(["pipeline", "--size", "tiny", "--data", str(tmp_path / "bags"), "--out", str(tmp_path / "run"),
                 "--device", "cpu", "--no-progress"]) == 130
    assert "interrupted" in capsys.readouterr().err


@pytest.mark.parametrize("device, generated_on", [("cpu", "cpu"), ("cuda:1", "cuda:1"), ("auto", "cuda")])
def test_bags_are_generated_on_the_device_asked_for(tmp_path, monkeypatch, device, generated_on):
    """--device auto and cuda:<index> generated the bags on the CPU, silently (only "cuda" reached generate)."""
    import ad_sim.generate
    import torch

    asked = []
    monkeypatch.setattr(ad_sim.generate, "main", lambda argv: asked.append(argv) or 130)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # as on a GPU machine: auto means cuda
    assert main(["pipeline", "--size", "tiny", "--data", str(tmp_path / "bags"), "--out", str(tmp_path / "run"),
                 "--device", device, "--no-progress"]) == 130
    assert [argv[argv.index("--device") + 1] for argv in asked] == [generated_on]
    assert "--quiet" in asked[0]  # --no-progress reaches generate's bars too


def _pipeline_bags(tmp_path) -> Path:
    data = tmp_path / "bags"
    for i, split in enumerate(("train", "seen", "unseen")):
        bag = write_synthetic_bag(data / "tiny" / split / f"{split}-0of1", 9 if split == "train" else 6,
                                  views=2 if split == "train" else 1, seed=10 + i, split=split)
        (bag / "DONE").write_text("{}\n")  # what ad_sim.generate leaves in a finished shard
    return data


def test_pipeline_end_to_end_and_resume(tmp_path, capsys):
    data = _pipeline_bags(tmp_path)
    args = ["pipeline", "--size", "tiny", "--data", str(data), "--out", str(tmp_path / "run"), "--cache",
            str(tmp_path / "cache"), "--teacher-epochs", "1", "--student-epochs", "1", "--ablations", "full",
            "--install", str(tmp_path / "installed"), "--device", "cpu", "--no-progress"]
    assert main(args) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text(), parse_constant=_not_json)
    assert set(summary["students"]) == {"full"}
    for name in ("default.onnx", "default.frame.onnx", "default.metrics.json"):
        assert (tmp_path / "installed" / name).is_file(), name
    metrics = json.loads((tmp_path / "installed" / "default.metrics.json").read_text())
    assert metrics["training"]["ablation"] == "full"
    assert set(metrics["evaluation"]) == {"seen", "unseen"}
    assert 0.0 <= metrics["evaluation"]["unseen"]["full"]["accuracy"] <= 1.0
    assert set(metrics["evaluation"]["unseen"]["temporal_ood_regl1"]) == {"24", "22", "18", "15"}
    report = (tmp_path / "run" / "reports" / "streaming_full_unseen" / "report.md").read_text()
    assert "| frames | jelly Acc" in report
    # The installed copy is self-contained: the estimator loads it by its new name.
    model = EstimatorModel.load(tmp_path / "installed" / "default.onnx")
    assert model.info.frame_encoder.name == "default.frame.onnx"
    out = capsys.readouterr().out
    assert "| 25 |" in out and "| 15 |" in out  # the paper table with temporal-OOD rows was printed
    _assert_summary_figures_are_each_splits(summary, tmp_path / "run", data / "tiny", tmp_path / "cache")
    # Re-running finds every stage done: no epoch is trained again.
    assert main(args) == 0
    assert "epoch=1" not in capsys.readouterr().out
    # Evaluating again with chosen prefix lengths and threads scores just those (25 always).
    onnx_path = tmp_path / "run" / "models" / "streaming_full.onnx"
    report_dir = tmp_path / "few_frames"
    assert main(["evaluate", "--model", str(onnx_path), "--bags", str(data / "tiny" / "unseen"), "--cache",
                 str(tmp_path / "cache"), "--out", str(report_dir), "--frames", "15,20", "14", "--threads", "2",
                 "--no-progress"]) == 0
    assert set(json.loads((report_dir / "metrics.json").read_text())["frames"]) == {"25", "20", "15", "14"}
    # Per-episode predictions beside the report, in ad_estimator.evaluate's field names: they give its figures.
    predictions = json.loads((report_dir / "predictions.json").read_text())
    assert set(predictions["frames"]) == {"25", "20", "15", "14"}
    episodes = predictions["frames"]["25"]
    assert len(episodes) == 6 and len({e["episode_id"] for e in episodes}) == 6
    correct = sum(e["material"] == e["true_material"] for e in episodes)
    assert correct / 6 == json.loads((report_dir / "metrics.json").read_text())["frames"]["25"]["accuracy"]
    assert all(len(e["raw_parameters"]) == len(predictions["parameter_names"]) == 4 for e in episodes)
    # The summary is recorded next to the model unless --no-record; a corrupt record fails before the work.
    record = onnx_path.with_name("streaming_full.metrics.json")
    assert "unseen" in json.loads(record.read_text())["evaluation"]
    record.write_text("{")
    evaluate_again = ["evaluate", "--model", str(onnx_path), "--bags", str(data / "tiny" / "unseen"), "--cache",
                      str(tmp_path / "cache"), "--out", str(tmp_path / "again"), "--no-progress"]
    capsys.readouterr()
    assert main(evaluate_again) == 1
    err = capsys.readouterr().err
    assert str(record) in err and "--no-record" in err and "Traceback" not in err
    assert not (tmp_path / "again").exists()
    assert main([*evaluate_again, "--no-record"]) == 0
    assert record.read_text() == "{" and (tmp_path / "again" / "report.md").is_file()


def test_pipeline_installs_the_last_student_trained_when_there_is_no_full_one(tmp_path, capsys):
    """--install's help: the `full` student, or else the last trained; it had installed the first."""
    data = _pipeline_bags(tmp_path)
    assert main(["pipeline", "--size", "tiny", "--data", str(data), "--out", str(tmp_path / "run"), "--cache",
                 str(tmp_path / "cache"), "--teacher-epochs", "1", "--student-epochs", "1", "--ablations",
                 "none,align_only", "--install", str(tmp_path / "installed"), "--device", "cpu", "--no-progress"]) == 0
    metrics = json.loads((tmp_path / "installed" / "default.metrics.json").read_text())
    assert metrics["training"]["ablation"] == "align_only"
    installed = EstimatorModel.load(tmp_path / "installed" / "default.onnx").model_id
    assert installed == EstimatorModel.load(tmp_path / "run" / "models" / "streaming_align_only.onnx").model_id


def test_evaluate_rejects_bad_prefix_lengths(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "m.onnx", "--bags", "b", "--frames", "0,30"])
    assert exit_info.value.code == 2 and "--frames [0, 30]: each K must be in 1..25" in capsys.readouterr().err


def test_user_errors_are_one_line_without_traceback(tmp_path, capsys, monkeypatch):
    """Missing model, missing bags, masks-only bags (no particles), missing teacher: exit 1 and one
    line that says what is wrong and what to do; AD_DEBUG=1 re-raises for developers."""
    monkeypatch.delenv("AD_DEBUG", raising=False)
    masks_only = REPO / "bags" / "samples" / "unseen-masks-0of1"
    model = REPO / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models" / "default.onnx"
    cases = [
        (["evaluate", "--model", str(tmp_path / "missing.onnx"), "--bags", str(masks_only)], "model file not found"),
        (["cache", "--bags", str(tmp_path / "nothing"), "--cache", str(tmp_path / "c")], "nothing does not exist"),
        (["cache", "--bags", str(tmp_path), "--cache", str(tmp_path / "c")], "generate some with"),
        (["evaluate", "--model", str(model), "--bags", str(masks_only), "--cache", str(tmp_path / "c"),
          "--no-progress"], "--skip-particles"),
        (["export", "--checkpoint", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "m.onnx")], "missing.pt"),
        (["evaluate", "--model", str(tmp_path), "--bags", str(masks_only)], "is a folder, not a model file"),
    ]
    for argv, expected in cases:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert "Traceback" not in err and expected in err.splitlines()[-1], (argv, err)
        assert err.splitlines()[-1].startswith(f"python -m training {argv[0]}: ")
    monkeypatch.setenv("AD_DEBUG", "1")
    with pytest.raises(FileNotFoundError):
        main(cases[1][0])


def test_evaluate_says_when_not_every_episode_was_scored(tmp_path, capsys):
    """bags/samples: 2 episodes with particles, 6 masks-only ones that this evaluation cannot use.
    It scores the 2 and says, last, that the others were left out and which command scores them."""
    bundled = REPO / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models"
    for name in ("default.onnx", "default.frame.onnx"):  # a copy: this evaluation records next to the model
        shutil.copy(bundled / name, tmp_path / name)
    model = tmp_path / "default.onnx"
    for record in (["--no-record"], []):  # decoding the bags, then from the cache
        assert main(["evaluate", "--model", str(model), "--bags", str(REPO / "bags" / "samples"), "--cache",
                     str(tmp_path / "c"), "--out", str(tmp_path / "r"), "--no-progress", *record]) == 0
        last = capsys.readouterr().err.splitlines()[-1]
        assert "only 2 complete episodes" in last and "ros2 run ad_estimator evaluate" in last, last
        source = json.loads((tmp_path / "r" / "predictions.json").read_text())
        assert source["episodes"] == 2
        assert any("unseen-masks-0of1 holds no complete episode" in p for p in source["source_problems"])
    recorded = json.loads((tmp_path / "default.metrics.json").read_text())["evaluation"]["samples"]
    assert recorded["episodes"] == 2 and recorded["source_problems"] == source["source_problems"]


def test_evaluate_on_the_train_split_is_warned_about(tmp_path, capsys):
    """Scores on the split models are trained on flatter them: evaluate says so in one line, and only then."""
    model = REPO / "ros_ws" / "src" / "ad_estimator" / "ad_estimator" / "models" / "default.onnx"
    errors = {}
    for split in ("unseen", "train"):
        bags = write_synthetic_bag(tmp_path / "bags" / split, 3, views=1, seed=4, split=split)
        assert main(["evaluate", "--model", str(model), "--bags", str(bags), "--cache", str(tmp_path / "c"),
                     "--out", str(tmp_path / split), "--frames", "25", "--no-record", "--no-progress"]) == 0
        errors[split] = capsys.readouterr().err
    assert "train split" not in errors["unseen"]
    assert errors["train"].splitlines()[-1:] == [
        f"warning: 3 of the 3 instances scored under {tmp_path / 'bags' / 'train'} are from the benchmark's train "
        "split, which models are trained on, so these scores do not measure generalisation; evaluate on the seen "
        "or unseen split (for example bags/paper/unseen)"]


def test_an_install_that_fails_half_way_leaves_the_installed_model_whole(tmp_path, monkeypatch):
    """install() writes the renamed pair and metrics in a staging folder and renames them in, head last:
    a failure while writing the head (here onnx.save raising) leaves the earlier install as it was."""
    import onnx

    from estimator_models import build_streaming_model
    from training import pipeline

    installed = tmp_path / "models"
    for seed, model_id in ((0, "first"), (1, "second")):
        (tmp_path / model_id).mkdir()
        head = build_streaming_model(tmp_path / model_id, seed=seed, model_id=model_id)
        (tmp_path / model_id / "student.metrics.json").write_text(json.dumps({"model_id": model_id}))
    pipeline.install(tmp_path / "first" / "student.onnx", tmp_path / "first" / "student.metrics.json", installed)
    before = {p.name: p.read_bytes() for p in installed.iterdir()}
    assert sorted(before) == ["default.frame.onnx", "default.metrics.json", "default.onnx"]
    assert EstimatorModel.load(installed / "default.onnx").model_id == "first"
    save = onnx.save

    def fail_on_the_head(model, path, *args, **kwargs):
        if Path(path).name == "default.onnx":
            raise OSError(28, "No space left on device")
        return save(model, path, *args, **kwargs)

    monkeypatch.setattr(onnx, "save", fail_on_the_head)
    with pytest.raises(OSError, match="No space left"):
        pipeline.install(head, tmp_path / "second" / "student.metrics.json", installed)
    assert {p.name: p.read_bytes() for p in installed.iterdir()} == before  # no staging folder left either
    monkeypatch.setattr(onnx, "save", save)
    pipeline.install(head, tmp_path / "second" / "student.metrics.json", installed)
    assert EstimatorModel.load(installed / "default.onnx").model_id == "second"
    assert sorted(p.name for p in installed.iterdir()) == sorted(before)


def test_bags_generated_with_another_seed_are_refused_not_used(tmp_path, monkeypatch, capsys):
    """`pipeline --seed 1` generates the seed-1 benchmark into an empty --data, but trained on seed-0 bags that an
    earlier run had left there, without a word: the same command gave other models depending on the disk."""
    import ad_sim.generate
    from ad_sim.rosbag import BagWriter

    from training import train_teacher

    data = tmp_path / "bags"
    for split in ("train", "seen", "unseen"):
        folder = data / "tiny" / split / f"{split}-0of1"
        with BagWriter(folder, custom_data={"generator": "ad_sim.generate", "shard": "0/1", "size": "tiny",
                                            "split": split, "seed": "0"}):
            pass
        (folder / "DONE").write_text("{}\n")
    generated = []
    monkeypatch.setattr(ad_sim.generate, "main", lambda argv: generated.append(argv) or 0)

    def training_starts(args):
        raise KeyboardInterrupt  # (exit 130): stands for the training the bags were used for

    monkeypatch.setattr(train_teacher, "run", training_starts)
    args = ["pipeline", "--size", "tiny", "--out", str(tmp_path / "run"), "--device", "cpu", "--no-progress"]
    assert main([*args, "--data", str(data), "--seed", "1"]) == 1
    err = capsys.readouterr().err
    assert "generated with --seed 0" in err and "--data-seed 0" in err and "Traceback" not in err
    assert generated == [] and not (tmp_path / "run").exists()
    # The same bags, asked for by their seed (training seed 1 on the seed-0 benchmark), or with their own seed:
    assert main([*args, "--data", str(data), "--seed", "1", "--data-seed", "0"]) == 130
    assert main([*args, "--data", str(data), "--seed", "0"]) == 130
    assert generated == []
    # An empty --data is generated with the seed asked for, as before.
    assert main([*args, "--data", str(tmp_path / "empty"), "--seed", "1"]) == 130
    assert [argv[argv.index("--seed") + 1] for argv in generated] == ["1", "1", "1"]


def test_a_data_seed_that_recorded_bags_cannot_confirm_is_said_naming_them(tmp_path, monkeypatch, capsys):
    """Bags recorded through topics (`ad_sim record`: BagWriter without generate's settings in metadata.yaml) carry
    no benchmark seed. `--data-seed 3` on them passed without a word, as if they were the seed-3 benchmark; it is
    said now, naming them, and they are still used as they are (no seed is assumed for them). Without
    --data-seed nothing was asked to be checked: no warning."""
    import ad_sim.generate

    from training import pipeline, train_teacher

    data = tmp_path / "bags"
    recorded = [write_synthetic_bag(data / "tiny" / split / "recorded", 2, views=1, split=split)
                for split in ("train", "seen", "unseen")]
    monkeypatch.setattr(ad_sim.generate, "main", lambda argv: pytest.fail(f"generated beside recorded bags: {argv}"))

    def training_starts(args):
        raise KeyboardInterrupt  # (exit 130): stands for the training the bags were used for

    monkeypatch.setattr(train_teacher, "run", training_starts)
    args = ["pipeline", "--size", "tiny", "--data", str(data), "--out", str(tmp_path / "run"), "--device", "cpu",
            "--no-progress"]
    assert main([*args, "--data-seed", "3"]) == 130
    err = capsys.readouterr().err
    assert (f"warning: --data-seed 3 cannot be checked for 3 bag(s) under {data}: they record no benchmark seed "
            "(recorded through topics, or generated from an instance file), so they are used as they are, whatever "
            f"seed they came from: {', '.join(map(str, recorded))}") in err, err
    assert main(args) == 130
    assert "--data-seed" not in capsys.readouterr().err
    assert pipeline.check_data_seed(data / "tiny" / "train", 3) == [recorded[0]]


def _assert_summary_figures_are_each_splits(summary: dict, run: Path, data: Path, cache: Path) -> None:
    """summary.json's seen and unseen figures are each split's own: the teacher's are its predictions on that
    split's bags, recomputed here, and the full student's report on a split scored that split's episodes and
    gives its summary entries (a split's bags swapped for the other's would go unnoticed by their keys alone)."""
    from ad_estimator.metrics import compute_metrics
    from training import data as training_data
    from training.train_teacher import load_teacher, teacher_predictions

    teacher = load_teacher(run / "teacher" / "best.pt")
    for split in ("seen", "unseen"):
        ds = training_data.load_dataset(data / split, cache, progress=False)
        expected = compute_metrics(teacher_predictions(teacher, ds, "cpu"))
        for key in ("accuracy", "regl1"):
            assert summary["teacher_metrics"][split][key] == pytest.approx(expected[key], rel=1e-6), (split, key)
        report = run / "reports" / f"streaming_full_{split}"
        scored = json.loads((report / "predictions.json").read_text())["frames"]["25"]
        assert sorted(e["episode_id"] for e in scored) == sorted(ds.episode_ids), split
        metrics = json.loads((report / "metrics.json").read_text())["frames"]["25"]
        for key in ("accuracy", "regl1"):
            assert summary["students"]["full"][f"{split}_{key}"] == pytest.approx(metrics[key], rel=1e-9), (split, key)


def test_the_pipeline_trains_each_stage_with_the_sizes_recipe_and_its_own_options(tmp_path, monkeypatch):
    """The per-size recipe (epochs, batch sizes, learning rate) and the pipeline's --seed, --val-fraction and
    --kind reach the teacher and the students. The end-to-end test runs `tiny` with explicit epochs, seed 0 and
    the streaming student, where a default of the wrong stage, the stages' own seed 0 or a student of the default
    kind would give the same run: here `small`, seed 3 and the UniFormer-style student."""
    import torch

    from training import engine, train_student, train_teacher
    from training.models.teacher import TEACHER_PRESETS, Teacher

    data = tmp_path / "bags"
    for i, split in enumerate(("train", "seen", "unseen")):
        write_synthetic_bag(data / "small" / split / "recorded", 3, views=1, seed=10 + i, split=split)
    teacher = tmp_path / "teacher.pt"
    engine.save_checkpoint(teacher, {"model": Teacher(TEACHER_PRESETS["tiny"]).state_dict(),
                                     "meta": {"config": TEACHER_PRESETS["tiny"].to_dict()}})
    stages = {}

    def teacher_stage(args):
        stages["teacher"] = args
        return teacher

    def student_stage(args):
        stages["student"] = args
        raise KeyboardInterrupt  # (exit 130): the students' training is not what this test is about

    monkeypatch.setattr(train_teacher, "run", teacher_stage)
    monkeypatch.setattr(train_student, "run", student_stage)
    assert main(["pipeline", "--size", "small", "--data", str(data), "--out", str(tmp_path / "run"), "--cache",
                 str(tmp_path / "cache"), "--seed", "3", "--val-fraction", "0.3", "--kind", "uniformer",
                 "--device", "cpu", "--no-progress"]) == 130
    shared = dict(size="small", lr=5e-4, seed=3, val_fraction=0.3, device="cpu", cache=str(tmp_path / "cache"))
    for stage, expected in (("teacher", dict(epochs=80, batch_size=16, out=str(tmp_path / "run" / "teacher"))),
                            ("student", dict(epochs=20, batch_size=32, kind="uniformer", ablation="full",
                                             teacher=str(teacher), out=str(tmp_path / "run" / "uniformer_full")))):
        args = vars(stages[stage])
        assert {key: args[key] for key in {**shared, **expected}} == {**shared, **expected}, stage
        assert args["bags"] == str(data / "small" / "train")
