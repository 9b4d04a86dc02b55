"""`ros2 run ad_sim node`: plays simulated episodes on the simulator topics (SPEC 5).

Episodes are simulated in batches by a worker thread ahead of playback and published with
simulated stamps (ad_sim.messages.frame_stamp, base 0), paced by real_time_factor.

Flow control (no loss to a reliable subscriber that keeps up on average): a reliable keep-last
writer drops its oldest sample when its history is full, even if a subscriber has not
acknowledged it. So before a topic's publisher holds qos_depth unacknowledged messages the node
waits for its subscribers' acknowledgements (Publisher.wait_for_all_acked); with
real_time_factor 0 this is what paces playback. `ros2 run ad_sim record` subscribes with
KEEP_ALL history, so an acknowledged sample is never overwritten before it is written.
Acknowledgements follow the writers' heartbeats (every 3 s by default on Fast DDS, which would
cap playback near one episode a second), so on Fast DDS the node loads a default writer profile
with 20 ms heartbeats (ad_sim/data/dds/fast_heartbeat.xml) unless FASTRTPS_DEFAULT_PROFILES_FILE
is set already: about 60 episodes/s reach the recorder (benchmarks/record_throughput.py).
QoS: reliable, keep-last qos_depth, volatile (a late subscriber gets the frames published after it joins), but the
ground truth (<topic_prefix>/instance) is transient local with depth 1: a late subscriber gets the episode now playing,
not the earlier ones.
With loop, the episodes of the first pass are kept in memory (up to loop_memory_mb) and replayed on the later
passes, with stamps that go on increasing, rather than simulated again.
Set wait_for_subscribers to N to start playing only once every simulator topic has N matched
subscriptions (e.g. a recorder started first).
A subscriber that dies without leaving (kill -9, a lost link) stays matched until DDS drops it at its
lease (20 s on Fast DDS). After ack_timeout seconds without its acknowledgements the node publishes on
without waiting on that topic again until its subscribers acknowledge again, so playback stalls for about
ack_timeout, not for the lease; a live subscriber that falls that far behind may lose messages meanwhile.
"""

from __future__ import annotations

import array
import importlib
import math
import queue
import re
import signal
import threading
import time

from .dds import quiet_interrupt

with quiet_interrupt("ad_sim node"):  # a Ctrl-C before main() handles signals: no traceback
    import rclpy
    from rclpy.duration import Duration
    from rclpy.exceptions import NameValidationException, ParameterException
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from . import materials, messages
    from .dds import (MAX_QOS_DEPTH, declare_parameters, message_class, node_cli, number, qos_from_profile,
                      use_fast_heartbeat)

LATE_RESTART = 0.5  # s behind schedule (simulation slower than real time) after which pacing restarts from now
ACK_TIMEOUT = 10.0  # s to wait for subscribers' acknowledgements before warning and going on (default)
ACK_SLICE = 0.1  # s between looks at the stop flag while waiting for acknowledgements
WORKER_JOIN_TIMEOUT = 10.0  # s; a stopped worker ends within one simulated frame, well under this
SINGLE_INSTANCE_PARAMETERS = materials.PARAMETER_NAMES
# A frame_id prefix: ROS-name characters in '/'-separated parts. tf2 refuses an empty id and a leading '/'; blanks,
# a trailing or doubled '/' and other characters made ids such as 'ad_sim//world' that tools cannot look up.
FRAME_PREFIX = re.compile(r"[A-Za-z0-9_]+(?:/[A-Za-z0-9_]+)*")


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
    return fill_message(message_class(type_name)(), data)


class SimPublishers:
    """Publishers of the simulator topics with the flow control described above."""

    def __init__(self, node: Node, views: int, prefix: str = messages.DEFAULT_PREFIX, depth: int = messages.QOS_DEPTH,
                 stop: threading.Event | None = None, ack_timeout: float = ACK_TIMEOUT):
        self.logger = node.get_logger()
        self.ack_timeout = ack_timeout
        self.stop = stop or threading.Event()  # once set, nobody waits for acknowledgements (a stopping node)
        self.by_topic = {}
        self.depths = {}
        for topic, type_name in messages.topic_types(views, prefix).items():
            # What the simulator offers on the topic, with this node's depth; but the transient-local ground truth
            # keeps its depth of 1 (messages.topic_qos: a late subscriber gets the episode now playing).
            offered = messages.topic_qos(topic, prefix)
            self.depths[topic] = offered["depth"] if offered["durability"] == "transient_local" else depth
            qos = qos_from_profile({"depth": self.depths[topic]}, default=offered)
            self.by_topic[topic] = (type_name, node.create_publisher(message_class(type_name), topic, qos))
        self.unacknowledged = dict.fromkeys(self.by_topic, 0)
        self.unresponsive = set()  # topics not waited on (beyond a slice) since a timeout, until they are acknowledged
        self.published = 0

    def publish(self, topic: str, data: dict) -> None:
        """Publish a messages.* dict on `topic`."""
        self.publish_message(topic, to_ros_message(self.by_topic[topic][0], data))

    def publish_message(self, topic: str, message) -> None:
        """Publish an rclpy message on `topic`, first waiting for acknowledgements if the window is full."""
        if self.unacknowledged[topic] >= self.depths[topic] - 1:  # (depth 1: every message waits for the previous one)
            self.wait_for_acks([topic])
        self.by_topic[topic][1].publish(message)
        self.unacknowledged[topic] += 1
        self.published += 1

    def wait_for_acks(self, topics=None) -> None:
        """Wait for the subscribers of `topics` (all by default) to acknowledge what was published, up to
        ack_timeout for all of them together, in slices, so that a stop (a Ctrl-C while a subscriber is gone
        or stalled) ends the wait within a slice. Once a topic lets the timeout pass, every topic is looked at
        for one slice only until its subscribers acknowledge again: the silent subscriber is likely a dead
        process, matched on every topic it subscribed to."""
        deadline = time.monotonic() + self.ack_timeout
        for topic in self.by_topic if topics is None else topics:
            while not self.by_topic[topic][1].wait_for_all_acked(Duration(seconds=ACK_SLICE)):
                if self.stop.is_set() or topic in self.unresponsive:
                    break
                if time.monotonic() >= deadline:
                    self.logger.warning(f"subscribers of {topic} did not acknowledge within {self.ack_timeout:g} s "
                                        "(did one die or stall?); publishing on without waiting for acknowledgements "
                                        "until they come again: a live subscriber this far behind may lose messages")
                    self.unresponsive.update(self.by_topic)
                    break
            else:
                if topic in self.unresponsive:
                    self.unresponsive.discard(topic)
                    if not self.unresponsive:
                        self.logger.info("every topic's subscribers acknowledge again (the silent one left or caught up)")
            self.unacknowledged[topic] = 0

    def matched(self, count: int) -> bool:
        """True once every topic has at least `count` matched subscriptions."""
        return all(publisher.get_subscription_count() >= count for _, publisher in self.by_topic.values())


# ROS parameters: name, default, meaning (declared by SimNode and listed by --help).
PARAMETERS = (
    ("instances", "", "instance file (YAML/JSON, SPEC 4); empty: the single instance if `shape` is set, else the benchmark"),
    ("size", "tiny", "benchmark size: tiny | small | paper"),
    ("split", "unseen", "benchmark split: train | seen | unseen"),
    ("seed", 0, "base seed of the benchmark"),
    ("shape", "", "single instance: shape name (with material, its parameters and instance_seed)"),
    ("material", "jelly", "single instance: jelly | plasticine | sand"),
    *((name, math.nan, "single instance: parameter in SI units, radians for friction_angle") for name in SINGLE_INSTANCE_PARAMETERS),
    ("instance_seed", 0, "single instance: seed of pose, velocity, views and sampling"),
    ("real_time_factor", 1.0, "playback speed over simulated time; 0: as fast as subscribers acknowledge"),
    ("views", 0, "cameras published per episode; 0: the instances' own (4 train, 1 evaluation)"),
    ("coverage_masks", False, "mask pixels hold their area coverage of the 512x512 render (0..255, grey edges) "
                              "instead of 0/255, for a grey-mask model (ad.mask_levels coverage); > 127 is the binary mask"),
    ("device", "cpu", "Warp device: cpu | cuda | cuda:<n>"),
    ("batch", 4, "episodes simulated per batch, ahead of playback"),
    ("loop", False, "start over after the last episode, replaying the episodes simulated if they take at most "
                    "loop_memory_mb, else simulating them again"),
    # The default keeps the small benchmark's train split (360 episodes, 4 views: 1.03 GB); paper's splits are
    # simulated again on every pass (docs/simulator.md).
    ("loop_memory_mb", 1024, "with loop: MiB of the first pass's episodes kept to replay them (an episode: 1.2 MB + "
                             "0.4 MB per view); a pass that takes more is simulated again each time; 0: never kept"),
    ("topic_prefix", messages.DEFAULT_PREFIX, "prefix of the topics"),
    ("frame_id", messages.DEFAULT_FRAME_PREFIX, "prefix of the frame ids: <frame_id>/world, <frame_id>/view_<k>; "
                                                "letters, digits and '_' in parts joined by '/' (robot1/ad_sim)"),
    ("qos_depth", messages.QOS_DEPTH, "keep-last depth of the publishers (the flow control window); the transient-local "
                                                 "instance topic keeps 1, the episode now playing, for a late subscriber"),
    ("wait_for_subscribers", 0, "start playing once every topic has this many subscriptions"),
    ("ack_timeout", ACK_TIMEOUT, "s to wait for reliable subscribers' acknowledgements before publishing on without them"),
)
# For `ros2 param describe` (ad_sim.dds.declare_parameters); SimNode checks the values itself.
RANGES = {"loop_memory_mb": (0, 2**63 - 1)}


class SimNode(Node):
    def __init__(self, stop: threading.Event):
        super().__init__("ad_sim")
        self.stop = stop
        declare_parameters(self, PARAMETERS, RANGES)
        self.param = lambda name: self.get_parameter(name).value
        self.rate = number(self, "real_time_factor")
        if not 0 <= self.rate < math.inf:
            raise ValueError(f"real_time_factor must be a finite number >= 0 (0 = as fast as possible), got {self.rate}")
        for name, least in (("seed", 0), ("instance_seed", 0), ("batch", 1), ("qos_depth", 1),
                            ("wait_for_subscribers", 0), ("loop_memory_mb", 0)):
            if self.param(name) < least:
                raise ValueError(f"{name} must be >= {least}, got {self.param(name)}")
        from .instances import MAX_VIEWS  # (the bound of instance files' views too)

        if not 0 <= self.param("views") <= MAX_VIEWS:
            raise ValueError(f"views must be in 0..{MAX_VIEWS} (0: the instances' own), got {self.param('views')}")
        ack_timeout = number(self, "ack_timeout")
        if not 0 < ack_timeout < math.inf:
            raise ValueError(f"ack_timeout must be > 0 (seconds), got {ack_timeout}")
        if self.param("qos_depth") > MAX_QOS_DEPTH:  # rclpy would fail inside its QoS struct
            raise ValueError(f"qos_depth must be <= {MAX_QOS_DEPTH}, got {self.param('qos_depth')}")
        self.frame_prefix = self.param("frame_id")
        if not FRAME_PREFIX.fullmatch(self.frame_prefix):
            raise ValueError("frame_id must be parts of letters, digits and '_' joined by single '/', e.g. ad_sim or "
                             "robot1/ad_sim (no blanks, no '/' at either end: it prefixes <frame_id>/world), "
                             f"got {self.frame_prefix!r}")
        if self.param("device") != "cpu":  # (Warp always has its CPU; checking starts Warp, with its banner)
            from .mpm import check_device

            check_device(self.param("device"), use_cpu="-p device:=cpu")  # now, not when the first batch simulates
        self.prefix = self.param("topic_prefix").rstrip("/")
        self.instances = self._load_instances()
        self.views = self.param("views") or max(instance.views for instance in self.instances)
        self.sim_publishers = SimPublishers(self, self.views, self.prefix, self.param("qos_depth"), stop, ack_timeout)
        self.episodes = queue.Queue(maxsize=2 * self.param("batch"))
        self.worker = threading.Thread(target=self.simulate_ahead, name="simulate", daemon=True)
        self.failed = False

    def _load_instances(self) -> list:
        from . import instances as library

        if self.param("instances"):
            found = library.load_instance_file(self.param("instances"))
        elif self.param("shape"):
            values = {n: number(self, n) for n in SINGLE_INSTANCE_PARAMETERS}
            parameters = {n: v for n, v in values.items() if not math.isnan(v)}
            entry = {"shape": self.param("shape"), "material": self.param("material"), "parameters": parameters, "seed": self.param("instance_seed")}
            # The same validation as an instance-file entry (instances owns it).
            found = [library.instance_from_entry(entry, 0, "node parameters")]
        else:
            found = library.benchmark(self.param("size"), self.param("split"), self.param("seed"))
        if not found:
            raise ValueError("no instances to play")
        return found

    # -- simulation worker

    def simulate_ahead(self) -> None:
        """Worker thread: simulate batches and queue their episodes (None after the last one). With loop, the
        later passes queue the first pass's episodes again if they were kept (loop_memory_mb)."""
        from .episode import simulate_batch
        from .mpm import Cancelled

        batch = self.param("batch")
        views = self.param("views") or None
        loop = self.param("loop")
        limit = self.param("loop_memory_mb")
        kept, kept_bytes = ([] if loop and limit else None), 0  # the first pass's episodes; None: not kept
        if loop and not limit:
            self.get_logger().info("loop: loop_memory_mb is 0, so each pass simulates them again")
        try:
            while not self.stop.is_set():
                if kept:  # a later pass
                    self._queue(kept)
                    continue
                for start in range(0, len(self.instances), batch):
                    episodes = simulate_batch(self.instances[start : start + batch], device=self.param("device"),
                                              views=views, coverage_masks=self.param("coverage_masks"),
                                              cancelled=self.stop.is_set)
                    if kept is not None:
                        kept += episodes
                        kept_bytes += sum(e.positions.nbytes + e.deformation.nbytes + e.masks.nbytes for e in episodes)
                        if kept_bytes > limit << 20:
                            self.get_logger().info(f"loop: the episodes of a pass take more than loop_memory_mb ({limit} "
                                                   "MiB); each pass simulates them again instead of replaying them")
                            kept = None
                    self._queue(episodes)
                    if self.stop.is_set():
                        return
                if not loop:
                    break
                if kept:
                    self.get_logger().info(f"loop: the later passes replay the {len(kept)} episode(s) simulated "
                                           f"({kept_bytes / 1e6:.0f} MB kept)")
        except Cancelled:  # the node is stopping
            pass
        except Exception as exc:  # report and end playback (exit 1) rather than hang the publisher
            # The episodes simulated before stay queued ahead of the end marker and are played whole: a stop here
            # cut the episode playing short (a truncated episode in a recording) and dropped the rest.
            self.get_logger().error(f"simulation failed: {type(exc).__name__}: {exc}; playing what was simulated "
                                    f"before ({self.episodes.qsize()} episode(s) queued), then exiting with status 1")
            self.failed = True
        finally:
            self._queue([None])  # the end marker, unless the node is stopping (then nobody reads it)

    def _queue(self, episodes) -> None:
        """Put episodes into the playback queue, waiting for room; gives up when the node stops."""
        for episode in episodes:
            while not self.stop.is_set():
                try:
                    self.episodes.put(episode, timeout=0.1)
                    break
                except queue.Full:
                    pass

    # -- playback

    def _wait_for_subscribers(self) -> None:
        wanted = self.param("wait_for_subscribers")
        if wanted <= 0:
            return
        self.get_logger().info(f"waiting for {wanted} subscription(s) on each of {len(self.sim_publishers.by_topic)} topics")
        while not self.stop.is_set() and not self.sim_publishers.matched(wanted):
            time.sleep(0.05)

    def _sleep_until(self, wall: float) -> None:
        while not self.stop.is_set():
            remaining = wall - time.monotonic()
            if remaining <= 0:
                return
            self.stop.wait(min(remaining, 0.1))

    def play(self) -> None:
        self.worker.start()
        self._wait_for_subscribers()
        index = 0  # episodes started; `played` counts those published whole
        played = 0
        clock_start = None  # wall time of stamp 0 when paced
        while not self.stop.is_set():
            try:
                episode = self.episodes.get(timeout=0.1)
            except queue.Empty:
                continue
            if episode is None:
                break
            last_stamp = None
            # Said before its first frame's wait, not between the wait and the publish: a log call there
            # delayed the frames (the first ones came 0.1 to 0.17 s late, in a burst, while the worker simulated).
            self._log_episode(index, episode.instance)
            for topic, stamp, data in messages.episode_messages(episode, index, prefix=self.prefix, frame_prefix=self.frame_prefix):
                if self.rate > 0 and stamp != last_stamp:  # a new frame: wait for its wall time
                    offset = stamp / 1e9 / self.rate
                    if clock_start is None or time.monotonic() > clock_start + offset + LATE_RESTART:
                        clock_start = time.monotonic() - offset  # first frame, or the simulation fell behind
                    self._sleep_until(clock_start + offset)
                if self.stop.is_set():  # (a stop ends the wait early: publish nothing ahead of its time)
                    break
                last_stamp = stamp
                self.sim_publishers.publish(topic, data)
            else:
                played += 1
            if last_stamp is not None:  # an episode the stop came before is not begun, nor cut short
                index += 1
        self.sim_publishers.wait_for_acks()
        cut = f" (episode {index - 1} cut short by the stop)" if index > played else ""
        self.get_logger().info(f"published {played} episode(s){cut}, {self.sim_publishers.published} messages")

    def _log_episode(self, index: int, instance) -> None:
        values = ", ".join(f"{k}={v:.4g}" for k, v in instance.parameters.items())
        self.get_logger().info(f"episode {index}: {instance.episode_id} ({instance.shape}, {instance.material}: {values})")

    def stop_worker(self) -> None:
        """Ends the simulation worker before the node goes: a daemon thread still inside Warp when the
        interpreter finalises is killed there, and its C++ frames abort the process ("terminate called
        without an active exception"). It ends within a simulated frame or a queue timeout."""
        self.stop.set()
        if self.worker.is_alive():
            self.worker.join(timeout=WORKER_JOIN_TIMEOUT)
        if self.worker.is_alive():
            self.get_logger().warning(f"the simulation worker did not end within {WORKER_JOIN_TIMEOUT} s")


def main(args: list[str] | None = None) -> None:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):  # first: from here on a signal stops the node (before: quiet_interrupt)
        signal.signal(sig, lambda *_: stop.set())
    node_cli("ros2 run ad_sim node", __doc__, PARAMETERS, args)
    use_fast_heartbeat()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = SimNode(stop)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, name="spin")
        spinner.start()
        node.play()
        executor.shutdown(timeout_sec=1.0)
        spinner.join()
        if node.failed:
            raise SystemExit(1)
    except (OSError, ValueError, ParameterException) as exc:  # bad parameters or instance file
        print(f"ad_sim node: {exc}", flush=True)
        raise SystemExit(2) from None
    except NameValidationException as exc:  # e.g. topic_prefix; its message has a third line, a caret
        print(f"ad_sim node: {' '.join(line.strip() for line in str(exc).splitlines()[:2])}", flush=True)
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.stop_worker()
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
