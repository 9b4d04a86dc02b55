"""python -m training {cache,teacher,student,export,evaluate,evaluate-teacher,report,pipeline,baseline,resim-psnr,compare}"""
from __future__ import annotations

import argparse
import logging
import os
import sys


def _cache_parser(p: argparse.ArgumentParser) -> None:
    from ad_estimator.cli import positive

    p.description = "Decode bags into the array cache (done on demand by every stage; this just does it first)."
    p.add_argument("--bags", required=True, help="folder of .mcap bags (searched recursively)")
    p.add_argument("--cache", default=".cache/training", help="array cache folder (keyed by bag content)")
    # positive: a size below 1 failed in cv2.resize with an assertion traceback
    p.add_argument("--input-size", type=positive, nargs=2, metavar=("H", "W"), action="append", default=[],
                   help="also cache the videos resized for a student of this input size (repeatable)")
    p.add_argument("--coverage", action="store_true",
                   help="keep the masks' grey levels, for students trained with --set mask_levels=coverage (bags "
                        "from ad_sim.generate --coverage-masks; cached in a <bag key>-coverage folder beside the "
                        "thresholded one)")


def _cache_run(args) -> None:
    from training import data

    ds = data.load_dataset(args.bags, args.cache, coverage=args.coverage)
    for size in args.input_size:
        data.resized_videos(ds, tuple(size))
    counts = {f: int((ds.labels == i).sum()) for i, f in enumerate(("jelly", "plasticine", "sand"))}
    levels = " (grey masks)" if args.coverage else ""
    print(f"{len(ds)} instances {counts}, {ds.num_videos} videos{levels}, {len(ds.shards)} bags cached in {args.cache}")


def main(argv: list[str] | None = None) -> int:
    from ad_estimator.cli import HelpFormatter
    from ad_sim.rosbag import one_line_warnings
    from training import (baseline, compare, engine, evaluate, export, pipeline, resim_psnr, train_student,
                          train_teacher)

    one_line_warnings()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    parser = argparse.ArgumentParser(prog="python -m training", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    commands = {
        "cache": (_cache_parser, _cache_run, "decode bags into the array cache"),
        "teacher": (train_teacher.build_parser, train_teacher.run, "Stage I: train the trajectory teacher"),
        "student": (train_student.build_parser, train_student.run, "Stage II: train a video student"),
        "export": (export.build_parser, export.run, "export a student to ONNX with metadata"),
        "evaluate": (evaluate.build_parser, evaluate.run, "evaluate an ONNX student on bags"),
        "evaluate-teacher": (train_teacher.build_eval_parser, train_teacher.run_eval,
                             "evaluate a teacher on bags' particle trajectories (a reference for its students)"),
        "report": (evaluate.build_report_parser, evaluate.run_report,
                   "rebuild an evaluation report from a saved predictions.json"),
        "pipeline": (pipeline.build_parser, pipeline.run, "bags (generated if missing) -> exported, evaluated model"),
        "baseline": (baseline.build_parser, baseline.run, "per-scene CMA-ES baseline over re-simulated masks"),
        "resim-psnr": (resim_psnr.build_parser, resim_psnr.run, "re-simulation PSNR of a student's estimates on bags"),
        "compare": (compare.build_parser, compare.run, "compare groups of evaluated runs (e.g. seeds of two recipes)"),
    }
    for name, (build, _, help_text) in commands.items():
        build(sub.add_parser(name, help=help_text, formatter_class=HelpFormatter))
    args = parser.parse_args(argv)
    try:
        commands[args.command][1](args)
    except (ValueError, OSError) as exc:
        # What a user can fix (bad paths, flags, models, bags; ModelError and BagError are
        # ValueErrors; an --out that is a file or a folder): one line. AD_DEBUG=1 keeps the
        # traceback for developers.
        if os.environ.get("AD_DEBUG"):
            raise
        print(f"python -m training {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"python -m training {args.command}: interrupted (training runs resume from last.pt when run "
              "again)", file=sys.stderr)
        return 130
    finally:
        engine.close_runtime()
    return 0


if __name__ == "__main__":
    sys.exit(main())
