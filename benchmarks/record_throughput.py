"""Throughput of the simulator topics through DDS into `ros2 run ad_sim record`, and of generate's writer.

Publishes pre-built episodes (numpy data, no simulation) with the simulator node's publishers
and flow control as fast as they go, into the recorder started as `ros2 run` would; prints
messages/s, MB/s and episodes/s, the recorder's in/out counts, and for comparison the rate of
writing the same episodes straight to a bag (generate's path, no DDS).

    source env.sh && python benchmarks/record_throughput.py --episodes 20 --views 1
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "ros_ws" / "src" / "ad_sim"),
                str(ROOT / "ros_ws" / "src" / "ad_estimator")]  # tests: its ROS process helpers

from ros_procs import recorder_counts, ros_domain, start, stop  # noqa: E402
from sim_fixtures import fabricated_episode  # noqa: E402

from ad_sim import messages  # noqa: E402
from ad_sim.generate import write_episodes  # noqa: E402
from ad_sim.rosbag import BagReader, BagWriter  # noqa: E402
from ad_estimator.cli import positive  # noqa: E402






def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=positive, default=20, help="episodes to publish (default %(default)s)")
    parser.add_argument("--views", type=positive, default=1, help="cameras per episode (default %(default)s)")
    parser.add_argument("--keep", action="store_true", help="keep the bags and the recorder's log (path printed)")
    parser.add_argument("--slow-heartbeat", action="store_true", help="keep Fast DDS's 3 s heartbeat (what the node avoids)")
    args = parser.parse_args(argv)
    domain = ros_domain(parser)

    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from tqdm import tqdm

    from ad_sim.dds import use_fast_heartbeat
    from ad_sim.sim_node import SimPublishers, to_ros_message

    if not args.slow_heartbeat:
        use_fast_heartbeat()  # as the simulator node does

    episodes = [fabricated_episode(i % 7, args.views) for i in range(args.episodes)]
    items = [item for i, e in enumerate(episodes) for item in messages.episode_messages(e, i)]
    types = messages.topic_types(args.views)
    work = Path(tempfile.mkdtemp(prefix="record_throughput-"))

    start_time = time.perf_counter()
    with BagWriter(work / "direct") as writer:
        write_episodes(writer, episodes, 0)
    direct = time.perf_counter() - start_time
    size = sum(f.stat().st_size for f in (work / "direct").glob("*.mcap"))

    start_time = time.perf_counter()
    converted = [(topic, to_ros_message(types[topic], data)) for topic, _, data in items]
    conversion = time.perf_counter() - start_time

    os.environ["ROS_DOMAIN_ID"] = str(domain)  # for the recorder
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("throughput", context=context)
    publishers = SimPublishers(node, args.views)
    recorder = start("record", domain, work / "record.log", output=str(work / "recorded"))
    try:  # the recorder is stopped whatever happens here (it outlived a failed run)
        while not publishers.matched(1):
            if recorder.poll() is not None:
                raise SystemExit((work / "record.log").read_text())
            time.sleep(0.05)
        start_time = time.perf_counter()
        for topic, message in tqdm(converted, desc="publish", unit="msg"):
            publishers.publish_message(topic, message)
        publishers.wait_for_acks()
        through_dds = time.perf_counter() - start_time
        time.sleep(0.5)
    finally:
        stop(recorder, signal.SIGINT)
    received, written = recorder_counts((work / "record.log").read_text())
    in_bag = sum(1 for _ in BagReader(work / "recorded", raw=True))
    node.destroy_node()
    context.try_shutdown()

    megabytes = size / 1e6
    print(f"{args.episodes} episodes, {args.views} view(s), {len(items)} messages, {megabytes:.1f} MB of MCAP (zstd)")
    print(f"generate's writer (dicts -> CDR -> MCAP): {len(items) / direct:8.0f} msg/s {args.episodes / direct:6.1f} episodes/s")
    print(f"node's dict -> rclpy conversion:          {len(items) / conversion:8.0f} msg/s {args.episodes / conversion:6.1f} episodes/s")
    print(
        f"publish -> DDS -> record (acknowledged):   {len(items) / through_dds:8.0f} msg/s {args.episodes / through_dds:6.1f} episodes/s "
        f"{megabytes / through_dds:6.1f} MB/s (compressed)"
    )
    print(f"recorder in {received}, out {written}, in bag {in_bag}, published {len(items)}")
    if args.keep:
        print(f"kept in {work}")
    else:
        shutil.rmtree(work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
