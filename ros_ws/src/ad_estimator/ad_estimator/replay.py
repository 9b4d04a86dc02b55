"""`ros2 run ad_estimator replay BAG`: publish a recorded bag's topics with their recorded timing.

For machines without rosbag2. Messages go out as the recorded CDR bytes (rclpy publishes
serialized bytes as they are), so stamps and content are exactly the bag's. Each topic is
published with the QoS it was recorded with (offered_qos_profiles in metadata.yaml; ground truth
transient local), pacing follows the log times divided by --rate. With --clock, /clock carries the
bag's time (each message's log time, before the message), as `ros2 bag play --clock` does, for
nodes run with use_sim_time.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

from ad_sim.dds import quiet_interrupt

with quiet_interrupt("replay"):  # a Ctrl-C before main() handles signals: no traceback
    import rclpy
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from tqdm import tqdm

    from ad_estimator.cli import HelpFormatter, topic
    from ad_estimator.window import ns_to_stamp
    from ad_sim import messages
    from ad_sim.dds import message_class, non_ros_args, qos_from_profile, use_fast_heartbeat
    from ad_sim.rosbag import BagError, BagReader, one_line_warnings, parse_offered_qos_profiles

# time.sleep raises OverflowError past about 292 years (and --rate 1e-300 makes any gap that long): --delay is
# kept to a day and --rate to 1000 times slower than recorded; the pacing sleeps go in steps of at most a day,
# so that even a bag with a gap of centuries between log times waits rather than fails.
MAX_DELAY_S = 86400.0
MIN_RATE = 0.001
MAX_SLEEP_S = 86400.0


def qos_from_recorded(topic: str, profiles) -> QoSProfile:
    """QoSProfile for a topic from rosbag2's offered_qos_profiles (a list, or the YAML string older bags hold).

    Its first profile, with the topic's default for what it lacks (ad_sim.dds.qos_from_profile). Anything that
    cannot be used (the whole, or a setting) takes the default with a warning naming the topic: a bag recorded
    elsewhere still plays, with the rest of its recorded QoS."""
    # Used when a bag has no metadata.yaml (a lone .mcap), and for what its offered_qos_profiles leave out or make
    # unusable: what the simulator offers.
    default = messages.topic_qos(topic)
    unusable = []
    try:
        profiles = parse_offered_qos_profiles(profiles)
    except ValueError as exc:
        unusable.append(str(exc))
        profiles = []
    qos = qos_from_profile(profiles[0] if profiles else {}, default, unusable)
    if unusable:
        used = ", ".join(policy.name.lower() for policy in (qos.reliability, qos.durability, qos.history))
        warnings.warn(f"unusable QoS for {topic} in metadata.yaml ({', '.join(unusable)}); replaying it as {used}"
                      f"{f', depth {qos.depth}' if qos.history == HistoryPolicy.KEEP_LAST else ''} (the default for "
                      "what was unusable)")
    return qos


def recorded_topics(reader: BagReader) -> dict[str, tuple[str, QoSProfile]]:
    """topic -> (type, QoS): as metadata.yaml lists it, else (no metadata.yaml, or one that leaves the topic out)
    the files' type with the simulator's defaults."""
    listed = {entry["topic_metadata"]["name"]: entry["topic_metadata"]
              for entry in (reader.metadata or {}).get("topics_with_message_count", [])}
    result = {topic: (type_name, qos_from_recorded(topic, None))
              for topic, type_name in reader.topics().items() if topic not in listed}
    for name, meta in listed.items():
        result[name] = (meta["type"], qos_from_recorded(name, meta.get("offered_qos_profiles")))
    return result


class Replayer:
    """Publishers for a bag's topics and the paced publishing loop."""

    def __init__(self, node: Node, bag: Path, topics: list[str] | None = None, recover: bool = False,
                 clock: bool = False):
        self.node = node
        self.reader = BagReader(bag, raw=True, topics=topics, recover=recover)
        available = recorded_topics(self.reader)
        wanted = topics or sorted(available)
        if missing := [t for t in wanted if t not in available]:
            raise BagError(f"bag {bag} has no topic(s) {missing}; it has {sorted(available)}")
        if clock and "/clock" in wanted:
            raise BagError(f"bag {bag} holds /clock itself; replay it as recorded, without --clock")
        # rclpy's and rclcpp's time sources subscribe best effort with depth 1
        self.clock = node.create_publisher(Clock, "/clock", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)) if clock else None
        self.last_clock = None
        self.publishers = {t: node.create_publisher(message_class(available[t][0]), t, available[t][1])
                           for t in wanted}
        self.total = sum(e["message_count"] for e in (self.reader.metadata or {}).get("topics_with_message_count", [])
                         if e["topic_metadata"]["name"] in self.publishers) or None
        self.published = 0

    def wait_for_subscribers(self, topics: list[str], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        for topic in topics:
            if topic not in self.publishers:
                raise BagError(f"--wait-for {topic}: not a replayed topic; name one of the bag's topics "
                               f"({', '.join(sorted(self.publishers))}), as recorded, even if remapped")
            while self.publishers[topic].get_subscription_count() == 0:
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"no subscriber on {topic} after {timeout:.1f} s; is the subscriber running with the same "
                        f"ROS_DOMAIN_ID ({os.environ.get('ROS_DOMAIN_ID', 'unset: 0')}) and discovery range "
                        f"(ROS_AUTOMATIC_DISCOVERY_RANGE {os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'unset')})?")
                time.sleep(0.01)

    def run(self, rate: float, progress: bool = True) -> int:
        """Publish every message at first_wall + (log_time - first_log) / rate; returns the count."""
        start_wall = start_log = None
        # closed on an error too (a bag with nothing readable fails once read), so the error gets a line of its own
        with tqdm(total=self.total, unit="msg", desc="replay", disable=None if progress else True, file=sys.stderr) as bar:
            for topic, log_time, data in self.reader:
                if start_log is None:
                    start_wall, start_log = time.monotonic(), log_time
                due = start_wall + (log_time - start_log) / 1e9 / rate
                while (delay := due - time.monotonic()) > 0:
                    time.sleep(min(delay, MAX_SLEEP_S))
                if not rclpy.ok(context=self.node.context):  # a signal (SIGTERM) shut ROS down: stopped, not done
                    raise ExternalShutdownException
                if self.clock is not None and log_time != self.last_clock:  # the time first, then what happened at it
                    sec, nanosec = ns_to_stamp(log_time)
                    self.clock.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))
                    self.last_clock = log_time
                self.publishers[topic].publish(bytes(data))
                self.published += 1
                bar.update()
        return self.published

    def wait_for_acknowledgments(self, timeout: float) -> bool:
        """Reliable subscribers got everything (so exiting now loses nothing)."""
        deadline = time.monotonic() + timeout
        return all(p.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic())))
                   for p in self.publishers.values())


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ros2 run ad_estimator replay",
        formatter_class=HelpFormatter,
        description="Publish a rosbag2 MCAP bag's topics with their recorded timing and QoS "
                    "(for machines without rosbag2). ROS arguments (remapping) go after --ros-args.")
    parser.add_argument("bag", type=Path, help="bag folder (metadata.yaml + .mcap files) or a single .mcap")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (2 = twice as fast)")
    parser.add_argument("--topics", nargs="+", type=topic, help="replay only these topics (default: all)")
    parser.add_argument("--wait-for", nargs="+", type=topic, default=[], metavar="TOPIC",
                        help="before starting, wait until each of these topics has a subscriber (the bag's topic "
                             "names, as --topics takes them, even when remapped with --ros-args -r)")
    parser.add_argument("--wait-timeout", type=float, default=30.0, help="seconds to wait for --wait-for")
    parser.add_argument("--delay", type=float, default=0.5,
                        help="seconds between creating publishers and the first message (discovery)")
    parser.add_argument("--loop", action="store_true",
                        help="play the bag again each time it ends, until stopped (Ctrl-C); its stamps start over "
                             "too, which the estimator takes as a new episode")
    parser.add_argument("--clock", action="store_true",
                        help="publish the bag's time on /clock (each message's log time, before the message), for "
                             "nodes run with use_sim_time; with --loop it goes back at each pass")
    parser.add_argument("--recover", action="store_true",
                        help="play truncated or damaged files (a killed recorder) up to their last complete chunk")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if not args.rate >= MIN_RATE:
        parser.error(f"--rate must be at least {MIN_RATE} (a second of the bag in about 17 minutes)")
    if not 0 <= args.delay <= MAX_DELAY_S:
        parser.error(f"--delay must be a number of seconds from 0 to {MAX_DELAY_S:.0f} (a day)")
    if not args.wait_timeout >= 0:
        parser.error("--wait-timeout must be a number of seconds >= 0")
    return args


def messages_published(replayer: Replayer, loop: bool) -> str:
    """'N of TOTAL messages' so far; the total is per pass (so not with --loop), and unknown without metadata.yaml."""
    of = f" of {replayer.total}" if replayer.total and not loop else ""
    return f"{replayer.published}{of} messages"


def main(args=None) -> int:
    argv = sys.argv if args is None else args
    options = parse_args(non_ros_args("ros2 run ad_estimator replay", argv)[1:])
    one_line_warnings()
    use_fast_heartbeat()  # acknowledgements (and the wait for them at the end) in ms, not at 3 s heartbeats
    rclpy.init(args=argv)
    node = replayer = None
    acknowledging = False  # everything is published; the last wait is for reliable subscribers' acknowledgements
    try:
        node = Node("ad_replay")
        replayer = Replayer(node, options.bag, options.topics, options.recover, options.clock)
        replayer.wait_for_subscribers(options.wait_for, options.wait_timeout)
        time.sleep(options.delay)
        count = replayer.run(options.rate, progress=not options.quiet)
        while options.loop and rclpy.ok(context=node.context):
            played, count = count, replayer.run(options.rate, progress=not options.quiet)
            if count == played:  # nothing to play: looping would only spin
                break
        acknowledging = True
        acked = replayer.wait_for_acknowledgments(5.0)
        print(f"replay: published {count} messages from {options.bag}"
              + ("" if count else " (it holds none on the replayed topics)")
              + ("" if acked else " (some reliable subscribers did not acknowledge everything)"), file=sys.stderr)
    except (BagError, TimeoutError) as exc:
        # a bag damaged part way: what went out before it is part of the outcome
        stopped = "" if replayer is None or not replayer.published else \
            f"stopped after {messages_published(replayer, options.loop)} from {options.bag}: "
        print(f"replay: {stopped}{exc}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException, RCLError) as exc:
        # Stopping a replay early is a normal way to end it; an RCLError is one too once a signal (SIGTERM, or
        # SIGINT without Python's handler) has shut the context down under a publish or the wait for acks.
        if isinstance(exc, RCLError) and rclpy.ok():
            raise
        if acknowledging:  # nothing was left to publish: only the wait for acknowledgements was cut short
            print(f"replay: published {count} messages from {options.bag}; interrupted while waiting for reliable "
                  "subscribers' acknowledgements (all published)", file=sys.stderr)
        elif replayer is not None:
            print(f"replay: stopped after {messages_published(replayer, options.loop)} from {options.bag}",
                  file=sys.stderr)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
