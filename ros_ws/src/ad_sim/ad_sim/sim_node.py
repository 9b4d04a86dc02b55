"""`ros2 run ad_sim node`: plays simulated episodes on the simulator topics (SPEC 5).

Episodes are simulated in batches by a worker thread ahead of playback and published with
simulated stamps (ad_sim.messages.frame_stamp, base 0), paced by real_time_factor.

Flow control with real_time_factor 0 (as fast as possible): after each frame the node waits
until every matched reliable subscription has acknowledged what was published
(Publisher.wait_for_all_acked), so it never runs more than one frame ahead of a subscriber's
history; `ros2 run ad_sim record` subscribes with KEEP_ALL history, so an acknowledged sample is
never overwritten before it is written. Set wait_for_subscribers to N to start playing only
once every simulator topic has N matched subscriptions (e.g. a recorder started first).
"""

from __future__ import annotations

import array
import importlib
import math
import queue
import signal
import threading
import time

import rclpy
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from . import materials, messages

ACK_TIMEOUT = 10.0  # s to wait for subscribers' acknowledgements before warning and going on
SINGLE_INSTANCE_PARAMETERS = materials.PARAMETER_NAMES


def import_message_class(type_name: str):
    """rclpy message class of 'pkg/msg/Type'."""
    package, namespace, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{namespace}"), name)


def _element_class(message, field_name: str):
    """Message class of the elements of a sequence field of `message`."""
    slot_type = message.SLOT_TYPES[message.__slots__.index(f"_{field_name}")]
    element = slot_type.value_type
    return getattr(importlib.import_module(".".join(element.namespaces)), element.name)


def fill_message(message, data: dict):
    """Set the fields of an rclpy message from a messages.* dict (nested dicts, lists, bytes)."""
    for name, value in data.items():
        if isinstance(value, dict):
            fill_message(getattr(message, name), value)
        elif isinstance(value, (bytes, bytearray)):
            setattr(message, name, array.array("B", value))  # the fast path of uint8[] setters
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            cls = _element_class(message, name)
            setattr(message, name, [fill_message(cls(), item) for item in value])
        else:
            setattr(message, name, value)
    return message


def to_ros_message(type_name: str, data: dict):
    return fill_message(import_message_class(type_name)(), data)


def ros_qos(qos: dict) -> QoSProfile:
    """rclpy QoSProfile of a messages.topic_qos() description."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if qos["history"] == "keep_all" else HistoryPolicy.KEEP_LAST,
        depth=qos["depth"],
        reliability=ReliabilityPolicy.RELIABLE if qos["reliability"] == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos["durability"] == "transient_local" else DurabilityPolicy.VOLATILE,
    )


class SimNode(Node):
    def __init__(self, stop: threading.Event):
        super().__init__("ad_sim")
        self.stop = stop
        p = self.declare_parameter
        p("instances", "")  # instance file; empty: the benchmark below, or the single instance if `shape` is set
        p("size", "tiny")
        p("split", "unseen")
        p("seed", 0)  # base seed of the benchmark
        p("shape", "")  # single instance: shape, material, its parameters (SI, radians) and instance_seed
        p("material", "jelly")
        for name in SINGLE_INSTANCE_PARAMETERS:
            p(name, math.nan)
        p("instance_seed", 0)
        p("real_time_factor", 1.0)
        p("views", 0)  # cameras per episode; 0: the instances' own (4 train, 1 evaluation)
        p("device", "cpu")
        p("batch", 4)  # episodes simulated per batch
        p("loop", False)
        p("topic_prefix", messages.DEFAULT_PREFIX)
        p("frame_id", messages.DEFAULT_FRAME_PREFIX)  # prefix of frame ids: <frame_id>/world, <frame_id>/view_<k>
        p("qos_depth", messages.QOS_DEPTH)
        p("wait_for_subscribers", 0)
        self.param = lambda name: self.get_parameter(name).value
        self.rate = float(self.param("real_time_factor"))
        if self.rate < 0:
            raise ValueError("real_time_factor must be >= 0 (0 = as fast as possible)")
        self.prefix = self.param("topic_prefix").rstrip("/")
        self.instances = self._load_instances()
        self.views = int(self.param("views")) or max(instance.views for instance in self.instances)
        self.publishers_by_topic = {}
        for topic, type_name in messages.topic_types(self.views, self.prefix).items():
            qos = dict(messages.topic_qos(topic, self.prefix), depth=int(self.param("qos_depth")))
            self.publishers_by_topic[topic] = (type_name, self.create_publisher(import_message_class(type_name), topic, ros_qos(qos)))
        self.published = 0
        self.episodes = queue.Queue(maxsize=2 * int(self.param("batch")))

    def _load_instances(self) -> list:
        from . import instances as library

        if self.param("instances"):
            found = library.load_instance_file(self.param("instances"))
        elif self.param("shape"):
            parameters = {n: self.param(n) for n in SINGLE_INSTANCE_PARAMETERS if not math.isnan(self.param(n))}
            entry = {"shape": self.param("shape"), "material": self.param("material"), "parameters": parameters, "seed": self.param("instance_seed")}
            # The same validation as an instance-file entry (instances owns it).
            found = [library._instance_from_entry(entry, 0, "node parameters")]
        else:
            found = library.benchmark(self.param("size"), self.param("split"), int(self.param("seed")))
        if not found:
            raise ValueError("no instances to play")
        return found

    # -- simulation worker

    def simulate_ahead(self) -> None:
        """Worker thread: simulate batches and queue their episodes (None after the last one)."""
        from .episode import simulate_batch

        batch = int(self.param("batch"))
        views = int(self.param("views")) or None
        try:
            while not self.stop.is_set():
                for start in range(0, len(self.instances), batch):
                    for episode in simulate_batch(self.instances[start : start + batch], device=self.param("device"), views=views):
                        while not self.stop.is_set():
                            try:
                                self.episodes.put(episode, timeout=0.1)
                                break
                            except queue.Full:
                                pass
                    if self.stop.is_set():
                        return
                if not self.param("loop"):
                    break
        except Exception as exc:  # report and end playback rather than hang the publisher
            self.get_logger().error(f"simulation failed: {type(exc).__name__}: {exc}")
            self.stop.set()
        finally:
            self.episodes.put(None)

    # -- playback

    def _wait_for_subscribers(self) -> None:
        wanted = int(self.param("wait_for_subscribers"))
        if wanted <= 0:
            return
        self.get_logger().info(f"waiting for {wanted} subscription(s) on each of {len(self.publishers_by_topic)} topics")
        while not self.stop.is_set():
            if all(pub.get_subscription_count() >= wanted for _, pub in self.publishers_by_topic.values()):
                return
            time.sleep(0.05)

    def _wait_for_acks(self) -> None:
        for topic, (_, publisher) in self.publishers_by_topic.items():
            if not publisher.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)):
                self.get_logger().warning(f"subscribers of {topic} did not acknowledge within {ACK_TIMEOUT} s")

    def _sleep_until(self, wall: float) -> None:
        while not self.stop.is_set():
            remaining = wall - time.monotonic()
            if remaining <= 0:
                return
            self.stop.wait(min(remaining, 0.1))

    def play(self) -> None:
        worker = threading.Thread(target=self.simulate_ahead, name="simulate", daemon=True)
        worker.start()
        self._wait_for_subscribers()
        frame_prefix = self.param("frame_id")
        index = 0
        clock_start = None  # wall time of stamp 0 when paced
        while not self.stop.is_set():
            try:
                episode = self.episodes.get(timeout=0.1)
            except queue.Empty:
                continue
            if episode is None:
                break
            instance = episode.instance
            values = ", ".join(f"{k}={v:.4g}" for k, v in instance.parameters.items())
            self.get_logger().info(f"episode {index}: {instance.episode_id} ({instance.shape}, {instance.material}: {values})")
            last_stamp = None
            for topic, stamp, data in messages.episode_messages(episode, index, prefix=self.prefix, frame_prefix=frame_prefix):
                if self.stop.is_set():
                    break
                if stamp != last_stamp:  # a new frame
                    if last_stamp is not None and self.rate == 0:
                        self._wait_for_acks()
                    if self.rate > 0:
                        if clock_start is None or time.monotonic() > clock_start + stamp / 1e9 / self.rate + 0.5:
                            clock_start = time.monotonic() - stamp / 1e9 / self.rate  # start, or fell behind
                        self._sleep_until(clock_start + stamp / 1e9 / self.rate)
                    last_stamp = stamp
                type_name, publisher = self.publishers_by_topic[topic]
                publisher.publish(to_ros_message(type_name, data))
                self.published += 1
            index += 1
        self._wait_for_acks()
        self.get_logger().info(f"published {index} episode(s), {self.published} messages")


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = None
    try:
        node = SimNode(stop)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, name="spin", daemon=True)
        spinner.start()
        node.play()
        executor.shutdown(timeout_sec=1.0)
    except ValueError as exc:
        print(f"ad_sim node: {exc}")
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
