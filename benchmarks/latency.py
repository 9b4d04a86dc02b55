#!/usr/bin/env python3
"""Estimator latency: frame arrival -> estimate published (p50/p95/p99) and model time.

ROS mode (default): the estimator node runs in this process exactly as in production (its
executor thread + inference worker); a separate process publishes 128x128 mono8 masks at the
simulator's stamps and pace (40 fps x --rate). Latency is the node's own measurement from the
subscription callback's entry to the return of publish(); the end-to-end figure adds DDS both
ways (frame publish in the other process -> estimate received here; same host clock).

--no-ros: only image conversion + window + model, in a loop (for machines without ROS, e.g. the
GPU machine: PYTHONPATH=ros_ws/src/ad_estimator:ros_ws/src/ad_sim python benchmarks/latency.py --no-ros).

Policy 'anytime' with every_n=1 (default) times an estimate at every frame (one frame encoding +
the temporal head, the streaming student's steady state); 'episode' times the 25th frame only.

Run: source env.sh && python benchmarks/latency.py [--model M] [--episodes 20]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "ros_ws" / "src" / "ad_estimator"), str(ROOT / "ros_ws" / "src" / "ad_sim")]

from ad_estimator.cli import HelpFormatter, positive, positive_number  # noqa: E402
from ad_estimator.images import MAX_IMAGE_PIXELS, ImageRejected, image_to_mask  # noqa: E402
from ad_estimator.model import BUNDLED_MODEL, PROVIDERS, EstimatorModel  # noqa: E402
from ad_estimator.parameters import PARAMETERS as NODE  # noqa: E402
from ad_estimator.window import FrameWindow  # noqa: E402
from ad_sim.rosbag import BagError, one_line_warnings  # noqa: E402
from common import falling_disc_clips, json_out, load_model, percentiles  # noqa: E402  (benchmarks/, the script's folder)

TOPIC = "/latency_benchmark/mask"
FRAME_NS = 25_000_000
EPISODE_NS = 1_500_000_000


def episode_masks(bag: Path | None, count: int, recover: bool = False) -> list[np.ndarray]:
    """Mask clips (25, H, W) uint8: from a bag's first camera if given (its levels as recorded, so a grey-mask
    bag stays grey; the estimator converts them as the node does), else a synthetic falling disc.
    `recover`: read what is readable of a damaged bag (a killed recorder's), with a warning."""
    if bag is None:
        return list(falling_disc_clips(count))
    from ad_estimator.evaluate import episode_frames
    clips = [np.stack([image_to_mask(m, MAX_IMAGE_PIXELS, None) for _, m in frames])
             for _, frames in episode_frames(bag, recover=recover)]
    if not clips:
        raise ValueError(f"{bag} holds no episode with mask frames (recorded from the simulator?)")
    return [clips[i % len(clips)] for i in range(count)]


class FakeImage:
    """What the window/conversion code reads from a sensor_msgs/Image, without ROS."""

    def __init__(self, mask: np.ndarray):
        self.height, self.width = mask.shape
        self.step, self.encoding, self.is_bigendian = self.width, "mono8", 0
        self.data = mask.tobytes()


def run_no_ros(args, model: EstimatorModel) -> dict:
    latencies, model_times = [], []
    for clip in episode_masks(args.bag, args.episodes, args.recover):
        window = FrameWindow(model.info.frame_interval, model.info.frame_count, policy=args.policy,
                             every_n=args.every_n, min_frames=args.min_frames, history=model.info.previous_frames)
        for k, mask in enumerate(clip):
            image = FakeImage(mask)
            encode_time = [0.0]

            def encode(converted, earlier):
                encode_start = time.perf_counter()
                feature = model.encode(converted, earlier)
                encode_time[0] = time.perf_counter() - encode_start
                return feature

            start = time.perf_counter()
            converted = image_to_mask(image, MAX_IMAGE_PIXELS, model.info.input_threshold())
            for out in window.add(k * FRAME_NS, converted, encode):
                model_start = time.perf_counter()
                model.predict(out.features, out.valid)
                # as the node reports it: this frame's encoding + the temporal head (or the clip)
                model_times.append(time.perf_counter() - model_start + encode_time[0])
                latencies.append(time.perf_counter() - start)
    return {"latency": percentiles(latencies), "model_time": percentiles(model_times)}


def publish_frames(args) -> None:
    """The other process: publish masks at the simulator's stamps, paced at 40 fps x rate."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("latency_benchmark_camera")
    publisher = node.create_publisher(Image, TOPIC, QoSProfile(depth=25, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)
    sent = {}
    for e, clip in enumerate(episode_masks(args.bag, args.episodes, args.recover)):
        start = time.monotonic()
        for k, mask in enumerate(clip):
            target = start + k * 0.025 / args.rate
            time.sleep(max(0.0, target - time.monotonic()))
            stamp = e * EPISODE_NS + k * FRAME_NS
            msg = Image(height=mask.shape[0], width=mask.shape[1], encoding="mono8", step=mask.shape[1],
                        data=mask.tobytes())
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            msg.header.frame_id = "benchmark"
            sent[stamp] = time.time()
            publisher.publish(msg)
        time.sleep(0.35)  # a gap in wall time too, as between simulator episodes
    print(json.dumps(sent))
    node.destroy_node()
    rclpy.shutdown()


def run_ros(args) -> dict:
    import rclpy
    from ad_msgs.msg import MaterialEstimate
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from ad_estimator.node import GIL_SWITCH_INTERVAL_S, EstimatorNode, make_executor

    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # as the node's main() does
    # The node's INFO lines (one per episode) would mix into the figures' output: warnings and errors only.
    # A log level is a global ROS argument, read by rclpy.init; a node's own cli_args leave logging as it is.
    rclpy.init(args=["latency", "--ros-args", "--log-level", "warn"])
    node = EstimatorNode(parameter_overrides=[
        Parameter("model_path", value=str(args.model)), Parameter("threads", value=args.threads),
        Parameter("output_policy", value=args.policy), Parameter("every_n", value=args.every_n),
        Parameter("min_frames", value=args.min_frames), Parameter("queue_size", value=64)],
        cli_args=["--ros-args", "-r", f"mask:={TOPIC}"])
    received = {}
    listener = rclpy.create_node("latency_benchmark_listener")
    listener.create_subscription(
        MaterialEstimate, "/ad_estimator/estimate",
        lambda m: received.setdefault(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, time.time()),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    executor = make_executor()  # as the node's main()
    executor.add_node(node)
    executor.add_node(listener)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    command = [sys.executable, __file__, "--publish", "--episodes", str(args.episodes), "--rate", str(args.rate)]
    if args.bag:
        command += ["--bag", str(args.bag)] + (["--recover"] if args.recover else [])
    camera = subprocess.run(command, capture_output=True, text=True, env=os.environ, timeout=600)
    if camera.returncode != 0:
        raise SystemExit(f"publisher failed:\n{camera.stderr}")
    time.sleep(0.5)
    sent = {int(k): v for k, v in json.loads(camera.stdout.strip().splitlines()[-1]).items()}
    stats = node.statistics()
    with node._lock:
        latencies, model_times = list(node.latencies), list(node.model_times)
    end_to_end = [received[s] - sent[s] for s in received if s in sent]
    executor.shutdown()
    node.destroy_node()
    listener.destroy_node()
    rclpy.try_shutdown()
    return {"latency": percentiles(latencies), "model_time": percentiles(model_times),
            "end_to_end_dds": percentiles(end_to_end),
            "frames": {k: stats[k] for k in ("received", "dropped", "rejected", "published")}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter,
                                     epilog="Target: p50 < 3.83 ms on a 2-core CPU with the streaming student.")
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: bundled)")
    parser.add_argument("--bag", type=Path, default=None, help="take masks from this bag (default: synthetic)")
    parser.add_argument("--recover", action="store_true",
                        help="--bag: read what is readable of a damaged bag (a killed recorder's), with a warning")
    parser.add_argument("--episodes", type=positive, default=20, help="episodes of 25 frames")
    parser.add_argument("--policy", choices=["anytime", "episode"], default="anytime",
                        help="output policy (the node's output_policy; default: anytime, which with the defaults "
                             "--every-n 1 --min-frames 1 times an estimate at every frame from frame 1, unlike the "
                             f"node's defaults: output_policy {NODE['output_policy'][0]}, "
                             f"every_n {NODE['every_n'][0]}, min_frames {NODE['min_frames'][0]}); "
                             "episode times the 25th frame only")
    parser.add_argument("--every-n", type=positive, default=1,
                        help="anytime: an estimate every N more frames "
                             f"(default: 1, every frame; the node's: {NODE['every_n'][0]})")
    parser.add_argument("--min-frames", type=positive, default=1,
                        help="anytime: frames before the first estimate "
                             f"(default: 1, from frame 1; the node's: {NODE['min_frames'][0]})")
    parser.add_argument("--rate", type=positive_number, default=1.0,
                        help="publishing speed factor (ROS mode): frames at 40 fps x RATE")
    parser.add_argument("--threads", type=positive, default=1, help="onnxruntime intra-op threads")
    parser.add_argument("--provider", choices=sorted(PROVIDERS), default="cpu",
                        help="onnxruntime execution provider (cuda needs onnxruntime-gpu; ROS mode: cpu only)")
    parser.add_argument("--no-ros", action="store_true", help="time conversion + window + model only")
    parser.add_argument("--json", type=json_out, default=None, help="also write the figures here")
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    one_line_warnings()  # the bag reader's warnings (--recover) as one line each
    if args.recover and args.bag is None:
        parser.error("--recover reads a damaged --bag; give --bag too")
    if args.publish:
        publish_frames(args)
        return 0
    if args.provider != "cpu" and not args.no_ros:
        parser.error("--provider cuda is measured with --no-ros (the node's execution_provider parameter does the same)")
    model = load_model(parser, args.model, threads=args.threads, provider=args.provider)
    if args.bag is not None:  # read before any timing, so that a bad bag is one line here
        try:
            episode_masks(args.bag, 1, args.recover)
        except (BagError, ImageRejected, ValueError) as exc:
            parser.error(f"--bag: {exc}")
    result = run_no_ros(args, model) if args.no_ros else run_ros(args)
    result["setup"] = {"model": str(args.model), "model_id": model.model_id, "kind": model.info.kind,
                       "mode": "no-ros" if args.no_ros else "ros", "rate": None if args.no_ros else args.rate,
                       "policy": args.policy, "every_n": args.every_n,
                       "min_frames": args.min_frames,
                       "episodes": args.episodes, "threads": args.threads, "provider": args.provider, "cpu": platform.processor() or
                       platform.machine(), "cpu_count": os.cpu_count()}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
