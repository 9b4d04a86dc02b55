#!/usr/bin/env python3
"""The main job: the simulator feeds the estimator (bundled model) on unseen shapes; each estimate
is printed beside the episode's ground truth.

Starts `ad_estimator node` and then `ad_sim node` (scripts/adrun, i.e. what `ros2 run` runs), listens
to /ad_estimator/estimate and /ad_sim/instance, matches each estimate to its episode by the stamp
of the episode's first frame, prints a line per episode and a summary, and exits after --episodes
episodes. Run it through scripts/demo.sh (set-up included) or, in a sourced environment, directly.
"""
from __future__ import annotations

import argparse
import math
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ad_estimator import metrics
from ad_estimator.cli import non_negative_number, positive, positive_number
from ad_estimator.window import stamp_to_ns
from ad_sim.families import FRAME_COUNT, FRAME_INTERVAL

ROOT = Path(__file__).resolve().parents[1]
ADRUN = ROOT / "scripts" / "adrun"
EPISODE_SPAN_NS = round(FRAME_COUNT * FRAME_INTERVAL * 1e9)  # from an episode's first frame's stamp to past its last
SHORT = {"youngs_modulus": ("E", "Pa"), "poissons_ratio": ("nu", ""), "yield_stress": ("yield", "Pa"),
         "friction_angle": ("phi", "deg")}


def fmt(name: str, value: float, sigma: float | None = None) -> str:
    label, unit = SHORT.get(name, (name, ""))
    if unit == "deg":
        value, sigma = math.degrees(value), (None if sigma is None else math.degrees(sigma))
    text = f"{label}={value:.3g}"
    if sigma is not None and math.isfinite(sigma) and sigma > 0:
        text += f"±{sigma:.2g}"
    return text + (f" {unit}" if unit else "")


def truth_text(instance) -> str:
    return f"{instance.material:10s} " + " ".join(
        fmt(n, v) for n, v in zip(instance.parameter_names, instance.parameters))


def estimate_text(estimate, truth_names) -> str:
    probability = dict(zip(estimate.class_names, estimate.class_probabilities))[estimate.material]
    values = {n: (v, s) for n, v, s in zip(estimate.parameter_names, estimate.parameters,
                                             estimate.parameter_uncertainties) if not math.isnan(v)}
    # the family's own parameters, in ground truth order where they match it
    order = [n for n in truth_names if n in values] + [n for n in values if n not in truth_names]
    return f"{estimate.material:10s} (p={probability:.2f}) " + " ".join(fmt(n, *values[n]) for n in order)


def stamp_ns(stamp) -> int:
    return stamp_to_ns(stamp.sec, stamp.nanosec)


class Listener:
    """Collects ground truth and estimates; pairs each estimate with the episode whose frames its oldest frame
    lies among (the instance is stamped with the episode's first frame, which the estimator may not have had).

    At most `limit` rows (--episodes): the simulator plays on until it is stopped, and with real_time_factor 0
    estimates arrive faster than the main loop looks, so more rows were printed than asked for, some after the
    summary (and the summary counted them)."""

    def __init__(self, node, limit: int | None = None):
        from ad_msgs.msg import MaterialEstimate, SimInstance
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.limit = limit
        self.instances, self.pending, self.rows = {}, [], []
        self.lock = threading.Lock()
        node.create_subscription(SimInstance, "/ad_sim/instance", self.on_instance,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        node.create_subscription(MaterialEstimate, "/ad_estimator/estimate", self.on_estimate,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))

    def on_instance(self, msg):
        with self.lock:
            self.instances[stamp_ns(msg.header.stamp)] = msg
            self._pair()

    def on_estimate(self, msg):
        with self.lock:
            self.pending.append(msg)
            self._pair()

    def episode_of(self, stamp: int):
        """The instance whose episode's frames span `stamp`, or None (not received yet)."""
        starts = [start for start in self.instances if start <= stamp < start + EPISODE_SPAN_NS]
        return self.instances[max(starts)] if starts else None

    def _pair(self):
        for estimate in list(self.pending):
            if self.limit is not None and len(self.rows) >= self.limit:
                return
            instance = self.episode_of(stamp_ns(estimate.oldest_stamp))
            if instance is not None:
                self.pending.remove(estimate)
                self.rows.append((instance, estimate))
                print(f"{instance.episode_id:34s} {instance.shape:14s} | {truth_text(instance):54s} | "
                      f"{estimate_text(estimate, list(instance.parameter_names))}  "
                      f"[{estimate.frames_used} frames, {estimate.inference_time * 1e3:.2f} ms]", flush=True)


def summary(rows) -> str:
    """Accuracy, and the paper's parameter errors over the correctly classified episodes."""
    if not rows:
        return "no estimates"
    correct = sum(i.material == e.material for i, e in rows)
    pairs: dict[str, list[tuple[float, float]]] = {}
    for instance, estimate in rows:
        if instance.material != estimate.material:
            continue
        predicted = dict(zip(estimate.parameter_names, estimate.parameters))
        true = dict(zip(instance.parameter_names, instance.parameters))
        for name in metrics.family_ranges()[instance.material]:  # sampled parameters only
            pairs.setdefault(name, []).append((predicted.get(name, math.nan), true[name]))
    kinds = {"log_mae": "log-MAE", "mae_deg": "MAE deg", "mae": "MAE"}
    parts = [f"{SHORT[n][0]} {kinds[metrics.ERROR_KIND[n]]} "
             f"{metrics.parameter_error(n, *np.array(v, dtype=float).T):.3f}" for n, v in pairs.items()]
    return f"accuracy {correct}/{len(rows)}; over correctly classified: " + (", ".join(parts) or "-")


def start(*command: str, log_path: Path) -> subprocess.Popen:
    with open(log_path, "w") as log:  # the child keeps its own copy of the file
        return subprocess.Popen([str(ADRUN), *command], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="./run_demo.sh", description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=positive, default=6, help="stop after this many estimates (tiny unseen has 6)")
    parser.add_argument("--size", default="tiny", choices=["tiny", "small", "paper"], help="benchmark size")
    parser.add_argument("--split", default="unseen", choices=["train", "seen", "unseen"])
    parser.add_argument("--real-time-factor", type=non_negative_number, default=1.0,
                        help="simulator pacing (0: as fast as it can; the estimator subscribes best effort)")
    parser.add_argument("--model", default="", help="ONNX model for the estimator (default: bundled)")
    parser.add_argument("--timeout", type=positive_number, default=900.0, help="give up after this many seconds")
    parser.add_argument("--logs", type=Path, default=ROOT / "reports" / "demo", help="node logs go here")
    args = parser.parse_args(argv)
    # The log folder before any node starts: a file of that name, or a folder that cannot be made, is one line.
    if args.logs.exists() and not args.logs.is_dir():
        parser.error(f"--logs: {args.logs} is a file; give a folder for the node logs")
    try:
        args.logs.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parser.error(f"--logs: cannot make the folder {args.logs}: {exc.strerror or exc}")

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randrange(1, 100)))
    # Ctrl-C is ours, as in the sim and record nodes: KeyboardInterrupt in this thread, and the
    # finally block stops everything. Installed explicitly, because a shell without job control
    # starts background jobs with SIGINT ignored, and rclpy's own handler could shut the context
    # down without raising anything here.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    node = rclpy.create_node("ad_demo")
    listener = Listener(node, args.episodes)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()

    model_args = ["--ros-args", "-p", f"model_path:={args.model}"] if args.model else []
    estimator = start("ad_estimator", "node", *model_args, log_path=args.logs / "estimator.log")
    simulator = None
    deadline = time.monotonic() + args.timeout
    status = 0
    try:
        while node.count_publishers("/ad_estimator/estimate") == 0:
            if estimator.poll() is not None:
                raise RuntimeError(f"the estimator exited ({estimator.returncode}):\n"
                                   + (args.logs / "estimator.log").read_text())
            if time.monotonic() > deadline:
                raise RuntimeError("the estimator did not come up")
            time.sleep(0.1)
        print(f"estimator up; starting the simulator ({args.size}/{args.split}, real_time_factor "
              f"{args.real_time_factor}); logs in {args.logs}", flush=True)
        simulator = start("ad_sim", "node", "--ros-args", "-p", f"size:={args.size}", "-p", f"split:={args.split}",
                          "-p", f"real_time_factor:={args.real_time_factor}", log_path=args.logs / "simulator.log")
        print(f"{'episode':34s} {'shape':14s} | {'ground truth':54s} | estimate", flush=True)
        while len(listener.rows) < args.episodes:
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out after {args.timeout:.0f} s with {len(listener.rows)} estimates")
            if simulator.poll() is not None:
                time.sleep(2.0)  # the last estimate may still be on its way
                if len(listener.rows) < args.episodes:
                    print(f"the simulator finished ({simulator.returncode}) after {len(listener.rows)} episodes; "
                          f"see {args.logs / 'simulator.log'}", flush=True)
                break
            if estimator.poll() is not None:
                raise RuntimeError(f"the estimator exited ({estimator.returncode}); see {args.logs / 'estimator.log'}")
            time.sleep(0.1)
        with listener.lock:  # not in the middle of the executor thread printing the last row
            print(summary(listener.rows), flush=True)
        status = 0 if listener.rows else 1
    except RuntimeError as exc:
        print(f"demo: {exc}", file=sys.stderr)
        status = 1
    except KeyboardInterrupt:
        print(f"demo: interrupted after {len(listener.rows)} estimates; stopping the nodes", file=sys.stderr)
        status = 130
    finally:
        for proc in (simulator, estimator):
            if proc is not None:
                stop(proc)
        executor.shutdown()
        spinner.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == "__main__":
    sys.exit(main())
