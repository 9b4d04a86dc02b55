#!/usr/bin/env python3
"""Soak: the estimator node's memory and latency over a long run, fed by `replay --loop` of a bag.

Robots run the node for hours: a container that grows with each frame or episode, or latency that
creeps up, shows only over many episodes. This starts the node (`scripts/adrun ad_estimator node`,
its defaults: episode policy, idle flush) and `replay BAG --loop --rate R` on the caller's ROS_DOMAIN_ID
(unset: a domain of its own, one that no test or benchmark on this machine holds), and every --interval
seconds samples the node's RSS (VmRSS of /proc/<pid>/status) and its latest /diagnostics (rates,
latency p50/p95 of its last 1000 estimates, counters). This process also listens to the masks and the
estimates: the end-to-end latency (mask received here -> estimate received here, the same DDS hop both ways)
gives p50/p99 over the first and the last minutes of the run.

The figures (JSON on stdout, and --json): RSS after --warmup and at the end, its growth per 1000
episodes (a least-squares line through the samples after warm-up, against estimates published) and
per hour, estimates published, latency at the start vs the end. Allocator warm-up (a few MiB in the
first minutes) is what --warmup leaves out; a steady slope after it is a leak.

--rate: the bag's pause between episodes, divided by the rate, must stay longer than the node's
idle_flush (0.3 s), so that the node still sees each episode end as on a robot (the default bag's
0.9 s pauses: --rate below 3).

Run: source env.sh && python benchmarks/soak.py [--minutes 10] [--rate 2.5] [--json soak.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "ros_ws" / "src" / "ad_estimator"),
                str(ROOT / "ros_ws" / "src" / "ad_sim")]  # tests: its ROS process helpers

from ad_estimator.cli import HelpFormatter, non_negative_number, positive_number  # noqa: E402
from ad_estimator.model import BUNDLED_MODEL  # noqa: E402
from ad_estimator.parameters import DEFAULT_IDLE_FLUSH, DEFAULT_INPUT_TOPIC  # noqa: E402
from ad_sim.rosbag import BagError, BagReader, one_line_warnings  # noqa: E402
from common import json_out, load_model, percentiles  # noqa: E402  (benchmarks/, the script's folder)
from ros_procs import ADRUN, ros_domain  # noqa: E402

DEFAULT_BAG = ROOT / "bags" / "samples" / "unseen-masks-0of1"
ESTIMATE_TOPIC = "/ad_estimator/estimate"




def bag_timing(bag: Path) -> dict:
    """The bag's mask frames: count, episodes (stamp gaps over 0.1 s) and the shortest pause between them (log
    time), so that the rate can be checked before anything starts. BagError for a bag without mask frames."""
    reader = BagReader(bag, raw=True, topics=[DEFAULT_INPUT_TOPIC])
    if DEFAULT_INPUT_TOPIC not in reader.topics():
        raise BagError(f"bag {bag} has no {DEFAULT_INPUT_TOPIC} (the node's input); it has {sorted(reader.topics())}")
    times = np.array([log_time for _, log_time, _ in reader], np.int64)
    if len(times) < 2:
        raise BagError(f"bag {bag} holds {len(times)} mask frame(s) on {DEFAULT_INPUT_TOPIC}: nothing to soak with")
    gaps = np.diff(times) / 1e9
    pauses = gaps[gaps > 0.1]
    return {"frames": int(len(times)), "episodes": int(len(pauses) + 1),
            "duration_s": float((times[-1] - times[0]) / 1e9),
            "min_pause_s": float(pauses.min()) if len(pauses) else None}


def vm_rss_mib(pid: int) -> float | None:
    """VmRSS of a process in MiB (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


class Listener:
    """In this process: the node's /diagnostics (latest values), and the masks' and estimates' arrival times."""

    def __init__(self, domain: int):
        import rclpy
        from ad_msgs.msg import MaterialEstimate
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import Image

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node("soak_listener", context=self.context)
        self.lock = threading.Lock()
        self.diagnostics: dict[str, str] = {}
        self.diagnostics_count = 0
        self.mask_arrival: dict[int, float] = {}  # stamp -> arrival; the bag's ~150 stamps, repeated each pass
        self.latencies: list[tuple[float, float]] = []  # (arrival of the estimate, end-to-end seconds)
        self.estimates = 0
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.node.create_subscription(Image, DEFAULT_INPUT_TOPIC, self._on_mask, qos_profile_sensor_data)
        self.node.create_subscription(MaterialEstimate, ESTIMATE_TOPIC, self._on_estimate,
                                      QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context shut down under it at the end
            pass

    @staticmethod
    def _ns(stamp) -> int:
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def _on_mask(self, msg) -> None:
        self.mask_arrival[self._ns(msg.header.stamp)] = time.monotonic()

    def _on_estimate(self, msg) -> None:
        now = time.monotonic()
        sent = self.mask_arrival.get(self._ns(msg.header.stamp))
        with self.lock:
            self.estimates += 1
            if sent is not None and 0 <= now - sent < 5.0:  # not one of the pass before (stamps repeat)
                self.latencies.append((now, now - sent))

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if "material estimator" in status.name:
                with self.lock:
                    self.diagnostics = {kv.key: kv.value for kv in status.values}
                    self.diagnostics_count += 1

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def start_process(args: list[str], log: Path, domain: int) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    return subprocess.Popen([str(ADRUN), *args], stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=ROOT)


def stop_process(process: subprocess.Popen, timeout: float = 20.0) -> int:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            return process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()


def number(values: dict, key: str) -> float | None:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return None


def fit_per(x, y, per: float) -> float | None:
    """Slope of the least-squares line of y on x, times `per` (None with fewer than 3 distinct x)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(set(x.tolist())) < 3:
        return None
    return float(np.polyfit(x, y, 1)[0] * per)


def summarize(samples: list[dict], latencies: list[tuple[float, float]], warmup: float, window: float) -> dict:
    after = [s for s in samples if s["t_s"] >= warmup and s["rss_mib"] is not None]
    if len(after) < 2:
        raise SystemExit("soak: fewer than 2 samples after the warm-up; run longer or sample more often")
    first, last = after[0], after[-1]
    episodes = [s["estimates_published"] for s in after]
    start_lat = [d for t, d in latencies if first["t_mono"] <= t < first["t_mono"] + window]
    end_lat = [d for t, d in latencies if last["t_mono"] - window <= t <= last["t_mono"]]
    rss = [s["rss_mib"] for s in after]
    return {
        "rss_mib": {"start": first["rss_mib"], "end": last["rss_mib"], "min": min(rss), "max": max(rss),
                    "growth_per_1000_episodes": fit_per(episodes, rss, 1000.0),
                    "growth_per_hour": fit_per([s["t_s"] for s in after], rss, 3600.0),
                    "growth_start_to_end": last["rss_mib"] - first["rss_mib"]},
        "replay_rss_mib": {"start": first["replay_rss_mib"], "end": last["replay_rss_mib"]},
        "episodes": {"after_warmup": last["estimates_published"] - first["estimates_published"],
                     "estimates_published": last["estimates_published"],
                     "episodes_started": last["episodes_started"],
                     "estimates_received_here": last["estimates_received_here"]},
        "frames": {k: last[k] for k in ("frames_received", "frames_dropped", "frames_rejected", "frames_late",
                                        "processing_errors", "episodes_without_estimate")},
        "node_latency_ms": {  # the node's own: arrival -> publish, p50/p95 of its last 1000 estimates
            "start": {"p50": first["latency_p50_ms"], "p95": first["latency_p95_ms"]},
            "end": {"p50": last["latency_p50_ms"], "p95": last["latency_p95_ms"]}},
        "end_to_end_latency": {"window_s": window, "start": percentiles(start_lat), "end": percentiles(end_lat)},
        "rates_hz": {"input_start": first["input_rate_hz"], "input_end": last["input_rate_hz"],
                     "estimates_start": first["estimate_rate_hz"], "estimates_end": last["estimate_rate_hz"]},
    }


def run(args, domain: int, work: Path) -> dict:
    node_log, replay_log = work / "node.log", work / "replay.log"
    node = start_process(["ad_estimator", "node", "--ros-args", "-p", f"model_path:={args.model}"], node_log, domain)
    listener = replay = None
    samples, latencies = [], []
    try:
        deadline = time.monotonic() + 60
        while "[INFO]" not in node_log.read_text():  # its start-up line: the model is loaded
            if node.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"soak: the node did not start:\n{node_log.read_text()}")
            time.sleep(0.1)
        listener = Listener(domain)
        replay = start_process(["ad_estimator", "replay", str(args.bag), "--loop", "--rate", str(args.rate), "--quiet",
                                "--wait-for", DEFAULT_INPUT_TOPIC], replay_log, domain)
        start = time.monotonic()
        end = start + args.minutes * 60
        next_sample, next_progress = start, start + 60
        while (now := time.monotonic()) < end:
            if node.poll() is not None or replay.poll() is not None:
                which, log = (("node", node_log) if node.poll() is not None else ("replay", replay_log))
                raise SystemExit(f"soak: the {which} exited (status {(node.poll(), replay.poll())}):\n"
                                 f"{log.read_text()[-3000:]}")
            if now >= next_sample:
                with listener.lock:
                    diag = dict(listener.diagnostics)
                    received_here = listener.estimates
                sample = {"t_s": round(now - start, 2), "t_mono": now, "rss_mib": vm_rss_mib(node.pid),
                          "replay_rss_mib": vm_rss_mib(replay.pid), "estimates_received_here": received_here}
                for key in ("estimates_published", "frames_received", "frames_dropped", "frames_rejected",
                            "frames_late", "processing_errors", "episodes_without_estimate", "window_restarts"):
                    sample[key] = int(number(diag, key) or 0)
                sample["episodes_started"] = sample.pop("window_restarts") + (1 if sample["frames_received"] else 0)
                for key in ("latency_p50_ms", "latency_p95_ms", "model_time_p50_ms", "input_rate_hz",
                            "estimate_rate_hz"):
                    sample[key] = number(diag, key)
                samples.append(sample)
                next_sample += args.interval
            if now >= next_progress:
                s = samples[-1]
                print(f"soak: {s['t_s'] / 60:5.1f} min  RSS {s['rss_mib']:.1f} MiB  {s['estimates_published']} "
                      f"estimates  p50 {s['latency_p50_ms']} ms", file=sys.stderr, flush=True)
                next_progress += 60
            time.sleep(min(0.2, max(0.0, min(next_sample, end) - time.monotonic())))
    finally:
        if replay is not None:
            stop_process(replay)
        node_status = stop_process(node)
        if listener is not None:
            latencies = list(listener.latencies)
            listener.close()
    if node_status != 0:
        print(f"soak: the node exited with {node_status}:\n{node_log.read_text()[-2000:]}", file=sys.stderr)
    summary = summarize(samples, latencies, args.warmup, args.latency_window)
    summary["node_exit"] = node_status
    summary["node_shutdown_line"] = next((line for line in node_log.read_text().splitlines()
                                          if "shutting down" in line), None)
    summary["samples"] = [{k: v for k, v in s.items() if k != "t_mono"} for s in samples]
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    parser.add_argument("--bag", type=Path, default=DEFAULT_BAG, help="bag replayed in a loop (masks on "
                        f"{DEFAULT_INPUT_TOPIC})")
    parser.add_argument("--minutes", type=positive_number, default=10.0, help="length of the run")
    parser.add_argument("--rate", type=positive_number, default=2.5,
                        help="replay speed factor; the bag's pauses between episodes / RATE must exceed the node's "
                             f"idle_flush ({DEFAULT_IDLE_FLUSH:g} s)")
    parser.add_argument("--interval", type=positive_number, default=5.0, help="seconds between samples")
    parser.add_argument("--warmup", type=non_negative_number, default=60.0,
                        help="seconds left out of the start figures and the fit (allocator warm-up)")
    parser.add_argument("--latency-window", type=positive_number, default=60.0,
                        help="seconds at the start (after warm-up) and at the end over which end-to-end latency "
                             "percentiles are taken")
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: bundled)")
    parser.add_argument("--keep", action="store_true", help="keep the node's and the replay's logs (path printed)")
    parser.add_argument("--json", type=json_out, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    one_line_warnings()
    seconds = args.minutes * 60
    if args.warmup + 2 * args.interval > seconds:
        parser.error(f"--warmup {args.warmup:g} s leaves under two --interval ({args.interval:g} s) samples of a "
                     f"{seconds:g} s run; run longer (--minutes) or warm up less")
    if args.latency_window > seconds - args.warmup:
        parser.error(f"--latency-window {args.latency_window:g} s is longer than the run after warm-up "
                     f"({seconds - args.warmup:g} s)")
    try:
        timing = bag_timing(args.bag)
    except (BagError, OSError) as exc:
        parser.error(f"--bag: {exc}")
    if timing["min_pause_s"] is not None and timing["min_pause_s"] / args.rate <= DEFAULT_IDLE_FLUSH:
        parser.error(f"--rate {args.rate:g}: the bag's {timing['min_pause_s']:g} s pauses between episodes would last "
                     f"{timing['min_pause_s'] / args.rate:.3g} s, not longer than the node's idle_flush "
                     f"({DEFAULT_IDLE_FLUSH:g} s); use --rate below {timing['min_pause_s'] / DEFAULT_IDLE_FLUSH:g}")
    model = load_model(parser, args.model)
    args.model = args.model.resolve()
    domain = ros_domain(parser)

    work = Path(tempfile.mkdtemp(prefix="soak-"))
    print(f"soak: {args.minutes:g} min on ROS domain {domain}, {args.bag} x{args.rate:g} in a loop "
          f"({timing['episodes']} episodes a pass of {timing['duration_s']:.1f} s), logs in {work}",
          file=sys.stderr, flush=True)
    result = run(args, domain, work)
    result["setup"] = {"bag": str(args.bag), "bag_timing": timing, "rate": args.rate, "minutes": args.minutes,
                       "interval_s": args.interval, "warmup_s": args.warmup, "model": str(args.model),
                       "model_id": model.model_id, "domain": domain,
                       "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count()}
    samples = result.pop("samples")
    rss, lat = result["rss_mib"], result["end_to_end_latency"]
    growth = rss["growth_per_1000_episodes"]
    print(f"RSS {rss['start']:.1f} -> {rss['end']:.1f} MiB over {result['episodes']['after_warmup']} episodes after "
          f"warm-up ({result['episodes']['estimates_published']} estimates in all): "
          f"{'n/a' if growth is None else f'{growth:+.2f}'} MiB per 1000 episodes, "
          f"{'n/a' if rss['growth_per_hour'] is None else format(rss['growth_per_hour'], '+.2f')} MiB/h",
          file=sys.stderr)
    print(f"end-to-end latency p50/p99: start {lat['start'].get('p50_ms', float('nan')):.2f}/"
          f"{lat['start'].get('p99_ms', float('nan')):.2f} ms, end {lat['end'].get('p50_ms', float('nan')):.2f}/"
          f"{lat['end'].get('p99_ms', float('nan')):.2f} ms", file=sys.stderr)
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(dict(result, samples=samples), indent=2))
    if args.keep:
        print(f"soak: logs kept in {work}", file=sys.stderr)
    else:
        for path in work.iterdir():
            path.unlink()
        work.rmdir()
    return 0


if __name__ == "__main__":
    sys.exit(main())
