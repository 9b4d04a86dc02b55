"""`ros2 run ad_sim record`: records topics into a rosbag2-compatible MCAP bag (ad_sim.rosbag).

Subscribes raw (CDR bytes, no deserialisation) with KEEP_ALL history and the publishers'
reliability and durability (transient local for /ad_sim/instance), discovering topics as
they appear: by default every simulator topic under topic_prefix (any number of views),
or the `topics` parameter. Log time of a message is its header stamp (simulated time, so a
recording made at any speed equals `generate`'s bag) unless stamp_source is "receive" or the
stamp cannot be a log time (negative, or nanosec >= 1e9: then the receive time, with a warning);
publish time is always the receive wall time. SIGINT/SIGTERM finalise the bag after taking what
already arrived (for at most 2 s; a second signal skips that), and so does an error; a kill -9
leaves every flushed chunk readable (chunks are flushed every flush_period seconds). A bag that
cannot be written on (a full disk, a read-only file system) stops the recording with exit status 1
and an error naming the file; the bag keeps every chunk written before, as a kill -9 leaves it.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from datetime import datetime, timezone

from .dds import quiet_interrupt

with quiet_interrupt("ad_sim record"):  # a Ctrl-C before main() handles signals: no traceback
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.exceptions import ParameterException, ParameterUninitializedException
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from . import messages
    from .rosbag import BagError, BagWriteError, BagWriter, header_stamp_ns, load_schema, qos_profile, starts_with_header
    from .dds import declare_parameters, message_class, node_cli, number

DRAIN_IDLE = 0.3  # s without incoming work after a stop signal before the bag is closed
DRAIN_MAX = 2.0  # s at most of that draining: a topic that keeps publishing must not hold the stop off


def _duration(duration) -> dict:
    nanoseconds = duration.nanoseconds
    return {"sec": nanoseconds // 1_000_000_000, "nsec": nanoseconds % 1_000_000_000}


def offered_qos(endpoint_qos) -> dict:
    """rosbag2 description of a discovered publisher's QoS."""
    return qos_profile(
        reliability="reliable" if endpoint_qos.reliability == ReliabilityPolicy.RELIABLE else "best_effort",
        durability="transient_local" if endpoint_qos.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile",
        history="keep_all" if endpoint_qos.history == HistoryPolicy.KEEP_ALL else "keep_last",
        depth=endpoint_qos.depth,
        deadline=_duration(endpoint_qos.deadline),
        lifespan=_duration(endpoint_qos.lifespan),
        liveliness_lease_duration=_duration(endpoint_qos.liveliness_lease_duration),
    )


# ROS parameters: name, default, meaning (declared by RecordNode and listed by --help).
PARAMETERS = (
    ("output", "", "bag folder to write (~ is the home folder); empty: bags/record-<UTC time>"),
    ("topics", Parameter.Type.STRING_ARRAY, "topics to record (names relative to the root namespace too, as ROS resolves "
                                            "them); unset: every simulator topic under topic_prefix, as they appear"),
    ("topic_prefix", messages.DEFAULT_PREFIX, "prefix of the simulator topics"),
    ("max_bag_size", 0, "split .mcap files once one reaches this many bytes (it exceeds them by its last chunk, an "
                        "eighth of them and a message at most, and its summary); 0: never"),
    ("compression", "zstd", "chunk compression: zstd | lz4 | none"),
    ("stamp_source", "header", "log time of a message: header (its stamp, for types starting with a Header) | receive"),
    ("discovery_period", 0.2, "seconds between looks for new topics"),
    ("flush_period", 1.0, "seconds between chunk flushes (what a kill -9 can lose)"),
)


class RecordNode(Node):
    def __init__(self):
        super().__init__("ad_sim_record")
        declare_parameters(self, PARAMETERS)
        get = lambda name: self.get_parameter(name).value  # noqa: E731
        periods = {name: number(self, name) for name in ("discovery_period", "flush_period")}
        for name, seconds in periods.items():
            if not 0 < seconds < math.inf:
                raise ValueError(f"{name} must be a positive number of seconds, got {seconds}")
        output = os.path.expanduser(get("output")) or f"bags/record-{datetime.now(timezone.utc):%Y%m%d-%H%M%S}"
        # Discovery lists fully qualified names: "chatter" (or a remapped name) is recorded as ROS resolves it.
        try:
            self.wanted = {self._resolve("topics", t) for t in get("topics") if t}
        except ParameterUninitializedException:
            self.wanted = set()
        prefix = get("topic_prefix").rstrip("/")
        self.prefix = self._resolve("topic_prefix", prefix) if prefix else ""
        self.stamp_source = get("stamp_source")
        if self.stamp_source not in ("header", "receive"):
            raise BagError(f"stamp_source must be 'header' or 'receive', got {self.stamp_source!r}")
        self.writer = BagWriter(output, max_bag_size=get("max_bag_size"), compression=get("compression"))
        self.received: dict[str, int] = {}
        self.written: dict[str, int] = {}
        self.subscriptions_by_topic = {}
        self.unrecordable: set[str] = set()
        self.error: BagWriteError | None = None  # the bag cannot be written on: the recording stops
        self._unflushed = False
        self.create_timer(periods["discovery_period"], self.discover)
        self.create_timer(periods["flush_period"], self.flush)
        self.get_logger().info(
            f"recording {'topics ' + ', '.join(sorted(self.wanted)) if self.wanted else 'simulator topics under ' + self.prefix} to {output}"
        )

    def _resolve(self, parameter: str, name: str) -> str:
        try:
            return self.resolve_topic_name(name)
        except RCLError as exc:  # its message ends in a C source location
            raise ValueError(f"{parameter}: {name!r} is not a topic name ({str(exc).split(', at ')[0]})") from None

    def _wanted(self, topic: str) -> bool:
        return topic in self.wanted if self.wanted else messages.is_simulator_topic(topic, self.prefix)

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subscriptions_by_topic or topic in self.unrecordable or not self._wanted(topic):
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far
            try:
                self._subscribe(topic, types[0], publishers)
            except BagWriteError as exc:
                self._failed(exc)
                return
            except (BagError, ImportError, AttributeError) as exc:  # no definition or typesupport here
                self.unrecordable.add(topic)
                self.get_logger().error(f"cannot record {topic} [{types[0]}]: {exc}")

    def _subscribe(self, topic: str, type_name: str, publishers) -> None:
        # Both can fail (no definition or typesupport here): before the topic enters the bag.
        schema = load_schema(type_name)
        subscribed_class = message_class(type_name)
        use_header = self.stamp_source == "header" and starts_with_header(schema.definition)
        # Like rosbag2: offer what every publisher can match, with a history that never drops.
        reliable = all(info.qos_profile.reliability == ReliabilityPolicy.RELIABLE for info in publishers)
        latched = all(info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for info in publishers)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_ALL,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )
        self.writer.add_topic(topic, type_name, [offered_qos(info.qos_profile) for info in publishers], schema)
        self.received[topic] = self.written[topic] = 0

        unusable_stamp_warned = False
        # Ground truth stamped at or before the episode before: a new simulator run, which stamps its episodes
        # from 0 s again, so that its frames and the earlier run's share stamps and cannot be told apart.
        episode_starts = topic == messages.instance_topic(self.prefix) and use_header
        last_start = None

        def on_message(data: bytes) -> None:
            nonlocal unusable_stamp_warned, last_start
            received_ns = time.time_ns()
            self.received[topic] += 1
            log_time = received_ns
            if use_header:
                try:
                    log_time = header_stamp_ns(data)
                except ValueError as exc:  # recorded all the same: a bag loses no message a publisher sent
                    if not unusable_stamp_warned:
                        self.get_logger().warning(f"{topic}: {exc}; recording it, and any later such message on "
                                                  "the topic, at its receive time")
                        unusable_stamp_warned = True
            if episode_starts:
                if last_start is not None and log_time <= last_start:
                    self.get_logger().warning(
                        f"{topic}: an episode stamped {log_time / 1e9:.3f} s, not after the one before "
                        f"({last_start / 1e9:.3f} s): a new simulator run? Each run stamps its episodes from 0 s, so "
                        "in one bag its episodes and the earlier run's share stamps and mix; stop this recorder "
                        "and record each run into its own bag")
                last_start = log_time
            try:
                self.writer.write(topic, log_time, data, publish_time_ns=received_ns)
            except BagWriteError as exc:  # a full disk, ...: the writer stopped, and so does the recording
                self._failed(exc)
                return
            except (BagError, OSError) as exc:  # this message only: keep counting, say why it is lost
                self.get_logger().error(f"message on {topic} not written: {exc}", throttle_duration_sec=5.0)
                return
            self.written[topic] += 1
            self._unflushed = True

        self.subscriptions_by_topic[topic] = self.create_subscription(
            subscribed_class, topic, on_message, qos, raw=True
        )
        self.get_logger().info(f"subscribed to {topic} [{type_name}]")

    def flush(self) -> None:
        if self._unflushed and self.error is None:
            try:
                self.writer.flush()
            except BagWriteError as exc:
                self._failed(exc)
            self._unflushed = False

    def _failed(self, exc: BagWriteError) -> None:
        """The bag cannot be written on: said once; main() stops the recording and exits with status 1."""
        if self.error is None:
            self.error = exc
            self.get_logger().error(f"recording stopped: {exc}")

    def close(self) -> None:
        try:
            self.writer.close()
        except BagWriteError as exc:
            self._failed(exc)
        for topic, lost in self.writer.lost.items():  # counted as written, but the failed write lost them
            self.written[topic] -= lost
        self.get_logger().info(
            f"bag {self.writer.path}: received {sum(self.received.values())}, "
            f"written {sum(self.written.values())} messages on {len(self.written)} topics"
        )
        for topic in sorted(self.written):
            self.get_logger().info(f"  {topic}: in {self.received[topic]} out {self.written[topic]}")


def main(args: list[str] | None = None) -> None:
    stop, stop_now = threading.Event(), threading.Event()  # a second Ctrl-C skips the draining

    def on_signal(*_):
        (stop_now if stop.is_set() else stop).set()

    for sig in (signal.SIGINT, signal.SIGTERM):  # first: from here on a signal stops the node (before: quiet_interrupt)
        signal.signal(sig, on_signal)
    node_cli("ros2 run ad_sim record", __doc__, PARAMETERS, args)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        if stop.is_set():  # stopped while starting: no empty bag left behind
            return
        node = RecordNode()
        try:
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            while not stop.is_set() and node.error is None:
                executor.spin_once(timeout_sec=0.1)
            # Take what already arrived before closing the bag, until DRAIN_IDLE s pass with nothing new. The timers
            # stop first (close() writes the last chunk), and the drain ends only after a wait that took nothing: a
            # slow flush on a busy machine passed for quiet input and closed the bag on messages still waiting.
            for timer in node.timers:
                timer.cancel()
            idle_since, seen = time.monotonic(), sum(node.received.values())
            give_up = idle_since + DRAIN_MAX
            while time.monotonic() < give_up and not stop_now.is_set() and node.error is None:
                executor.spin_once(timeout_sec=0.05)
                if sum(node.received.values()) != seen:
                    idle_since, seen = time.monotonic(), sum(node.received.values())
                elif time.monotonic() - idle_since >= DRAIN_IDLE:
                    break
        finally:  # after an error too: closing writes the chunk in memory and the summaries readers need
            node.close()
        if node.error is not None:
            print(f"ad_sim record: {node.error} (-p output:=...)")
            raise SystemExit(1)
    except (ValueError, ParameterException) as exc:  # bad parameters (a BagError is a ValueError)
        print(f"ad_sim record: {exc}")
        raise SystemExit(2) from None
    except OSError as exc:  # an output folder that cannot be made
        print(f"ad_sim record: cannot write the bag: {exc}; pass another -p output:=...")
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
