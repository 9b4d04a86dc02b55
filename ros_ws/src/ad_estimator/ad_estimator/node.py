"""`ros2 run ad_estimator node`: online material estimation from one mask stream.

Thin ROS shell around ad_estimator.model (onnxruntime), .window (slots, episodes, output policy)
and .images (Image -> mask). Threads: the subscription callback only checks header fields and
puts the message in a bounded queue (full queue: the frame is dropped and counted); one worker
thread converts, encodes, runs the model and publishes. The ~/estimate clip service runs on a
companion node (<name>_clip) with an executor in a thread of its own (a long clip must not hold up
the subscription), with its own window, sharing the (thread-safe) onnxruntime sessions.

Topics: subscribes /ad_sim/view_0/mask (remap `mask:=...` or the full name), publishes
/ad_estimator/estimate (ad_msgs/MaterialEstimate, reliable) and /diagnostics every
diagnostics_period seconds (1 by default).
Services: ~/reset (std_srvs/Trigger), ~/estimate (ad_msgs/srv/EstimateMaterial).
"""
from __future__ import annotations

import atexit
import queue
import signal
import sys
import threading
import time
from collections import deque

from ad_sim.dds import quiet_interrupt

with quiet_interrupt("ad_estimator"):  # a Ctrl-C before main() handles signals: no traceback
    import numpy as np
    import rclpy
    from ad_msgs.msg import MaterialEstimate
    from ad_msgs.srv import EstimateMaterial
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
    from rclpy.duration import Duration
    from rclpy.node import Node
    from rclpy.qos import QoSPolicyKind, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger

    from ad_estimator.images import ImageRejected, check_header, image_to_mask
    from ad_estimator.model import BUNDLED_MODEL, TRAINED_EXTENT, Estimate, EstimatorModel, ModelError, object_extent
    from ad_estimator.parameters import DEFAULT_INPUT_TOPIC, PARAMETERS, RANGES, check_parameters, model_window
    from ad_estimator.window import WindowOutput, clip_output, ns_to_stamp, stamp_to_ns
    from ad_sim.dds import declare_parameters, node_cli, number

LOG_THROTTLE_S = 5.0
# At shutdown, in all (under the 5 s a launch system waits between SIGINT and SIGTERM): taking the frames delivered
# (until none came for FINISH_QUIET_S, at most FINISH_TAKE_S: a live camera never pauses), estimating the queued
# ones and flushing the window, then their delivery.
FINISH_TIMEOUT_S = 3.0
FINISH_QUIET_S = 0.3
FINISH_TAKE_S = 1.0
MAX_CLIP_FRAMES = 1000
# The executor thread runs much Python between callbacks; with the default 5 ms GIL switch
# interval the inference worker can wait that long for a frame just queued (measured: p95
# arrival->publish 4.2 ms at 5 ms, 1.6 ms at 0.5 ms, with a 0.3 ms model).
GIL_SWITCH_INTERVAL_S = 0.0005


def to_time(ns: int) -> Time:
    sec, nanosec = ns_to_stamp(ns)
    return Time(sec=sec, nanosec=nanosec)


def estimate_message(estimate: Estimate, window: WindowOutput, frame_id: str, model_id: str,
                     inference_time: float) -> MaterialEstimate:
    msg = MaterialEstimate()
    msg.header.stamp = to_time(window.newest_stamp_ns)
    msg.header.frame_id = frame_id
    msg.oldest_stamp = to_time(window.oldest_stamp_ns)
    msg.frames_used = window.frames_used
    msg.complete = window.complete
    msg.material = estimate.material
    msg.class_names = list(estimate.class_names)
    msg.class_probabilities = [float(p) for p in estimate.probabilities]
    msg.parameter_names = list(estimate.parameter_names)
    msg.parameters = [float(v) for v in estimate.parameters]
    msg.parameter_uncertainties = [float(v) for v in estimate.uncertainties]
    msg.model_id = model_id
    msg.inference_time = float(inference_time)
    return msg


class Throttle:
    """At most one log line per key every `period` seconds, saying how many were suppressed. Called from the
    worker and from the clip service's thread, hence the lock."""

    def __init__(self, log, period: float = LOG_THROTTLE_S):
        self._log, self._period = log, period
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -1e9) < self._period:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                return
            extra = self._suppressed.pop(key, 0)
            self._last[key] = now
        self._log(message + (f" ({extra} more like this suppressed)" if extra else ""))


class EstimatorNode(Node):
    def __init__(self, **kwargs):
        super().__init__("ad_estimator", **kwargs)
        p = self._declare_parameters()
        self.model = EstimatorModel.load(p["model_path"] or BUNDLED_MODEL, threads=p["threads"],
                                         provider=p["execution_provider"])
        self.info = self.model.info
        self.slot_tolerance = p["slot_tolerance"]
        self.window = model_window(p, self.info)
        self.max_pixels = p["max_image_pixels"]
        self.threshold = self.info.input_threshold(p["mask_threshold"])
        self.idle_flush = p["idle_flush"]

        self.queue: queue.Queue = queue.Queue(maxsize=p["queue_size"])
        self.counters = dict(received=0, rejected=0, dropped=0, late=0, duplicate=0, processed=0, published=0,
                             errors=0, without_estimate=0, off_framing=0, incompatible_publishers=0,
                             cleared_by_reset=0)
        self.latencies: deque[float] = deque(maxlen=1000)  # arrival -> publish, seconds
        self.model_times: deque[float] = deque(maxlen=1000)
        self._period_counts = dict(received=0, published=0, dropped=0, rejected=0, late=0, duplicate=0, errors=0,
                                   without_estimate=0)
        self._lock = threading.Lock()  # counters and queue clearing
        self._generation = 0  # bumped by ~/reset; the worker resets its window when it sees a new one
        self._window_generation = 0
        # Held by ~/reset as it bumps the generation, and by the worker as it publishes: once ~/reset has answered,
        # no estimate of the episode it forgot goes out (one being computed then is discarded).
        self._reset_lock = threading.Lock()
        self._frame_id = ""  # of the last frame the worker processed: the camera of the episode it belongs to
        self._stop = threading.Event()
        self._closing = threading.Event()  # input has ended (finish): the worker empties the queue, flushes, stops
        self._finished = threading.Event()  # ... and it did
        self._last_frame_time = time.monotonic()
        self._unheard_publisher = False  # an incompatible publisher was seen and no frame has arrived since
        self._episode_off_framing = False  # the current episode was counted (and warned about) off framing
        self.warn = Throttle(self.get_logger().warning)

        reliability = ReliabilityPolicy.RELIABLE if p["reliable"] else ReliabilityPolicy.BEST_EFFORT
        input_qos = QoSProfile(depth=p["input_depth"], reliability=reliability,
                               history=qos_profile_sensor_data.history, durability=qos_profile_sensor_data.durability)
        self.publisher = self.create_publisher(
            MaterialEstimate, "~/estimate", QoSProfile(depth=10),
            event_callbacks=PublisherEventCallbacks(incompatible_qos=self.on_incompatible_subscription))
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.subscription = self.create_subscription(
            Image, self._input_topic(), self.on_image, input_qos,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self.on_incompatible_qos))
        self.input_topic = self.subscription.topic_name  # after any remap, the default topic's by its full name too
        self.create_service(Trigger, "~/reset", self.on_reset)
        self._serve_clips_apart()
        self.create_timer(p["diagnostics_period"], self.publish_diagnostics)
        self._diag_time = time.monotonic()
        self.worker = threading.Thread(target=self._work, name="ad_estimator_worker", daemon=True)
        self.worker.start()
        policy = p["output_policy"]
        if policy == "anytime":
            policy += f" (from {self.window.min_frames} frames, every {p['every_n']})"
        self.get_logger().info(
            f"model {self.info.model_id} ({self.info.kind}, {self.info.path}); input {self.input_topic} "
            f"({'reliable' if p['reliable'] else 'best effort'}); policy {policy}; output {self.publisher.topic_name}")
        if self.info.mask_levels == "coverage":  # what it needs: no 0/255 stream carries its grey edges
            self.get_logger().warning(
                "this model reads grey masks (ad.mask_levels coverage): it gets each pixel's level, and mask_threshold "
                "does not apply. Feed it camera masks larger than 128x128 (area-averaged here) or bags from "
                "`ad_sim.generate --coverage-masks`; the simulator node's 128x128 0/255 masks lack the grey edges "
                "it was trained on")

    # ------------------------------------------------------------------ set-up

    def _declare_parameters(self) -> dict:
        declare_parameters(self, [(name, default, text) for name, (default, text) in PARAMETERS.items()], RANGES)
        values = {name: number(self, name) if isinstance(default, float) else self.get_parameter(name).value
                  for name, (default, _) in PARAMETERS.items()}
        check_parameters(values)
        return values

    def _input_topic(self) -> str:
        """`mask` remapped if the user remapped it, else the simulator's first camera."""
        remapped = self.resolve_topic_name("mask")
        return DEFAULT_INPUT_TOPIC if remapped == self.resolve_topic_name("mask", only_expand=True) else remapped

    # ------------------------------------------------------------------ input

    def _count(self, name: str) -> None:
        with self._lock:
            self.counters[name] += 1
            if name in self._period_counts:
                self._period_counts[name] += 1

    def on_incompatible_qos(self, event) -> None:
        """A publisher on the input topic this subscription cannot hear (e.g. best effort, while
        reliable:=true): DDS delivers nothing from it, so say so and how to fix it."""
        with self._lock:
            self.counters["incompatible_publishers"] = event.total_count
        self._unheard_publisher = True  # until a frame arrives: then the camera was fixed
        policy = QoSPolicyKind(event.last_policy_kind)
        fix = ("set -p reliable:=false, or make the camera publish reliably" if policy == QoSPolicyKind.RELIABILITY
               else f"make the publisher's {policy.name.lower()} QoS compatible")
        self.get_logger().error(f"a publisher on {self.input_topic} offers QoS incompatible with this subscription "
                                f"({policy.name.lower()}): no frames from it will arrive; {fix}")

    def on_incompatible_subscription(self, event) -> None:
        """A subscription to the estimates this publisher cannot serve. rclpy's own warning named the topic `~/estimate`,
        as written in the code, whatever the namespace and remaps made of it, and said nothing of the fix."""
        policy = QoSPolicyKind(event.last_policy_kind)
        fix = {QoSPolicyKind.DURABILITY: "subscribe volatile: the estimates are not kept for late joiners (call the "
                                         "~/estimate service with a clip for an estimate now)"}.get(
            policy, "subscribe reliable or best effort, volatile, with no deadline or liveliness requirement")
        self.get_logger().warning(f"a subscription to {self.publisher.topic_name} asks for QoS this publisher (reliable, "
                                  f"volatile) does not offer ({policy.name.lower()}): it gets no estimates; {fix}")

    def on_image(self, msg: Image) -> None:
        """Subscription callback: header checks only, then the bounded queue."""
        arrival = time.perf_counter()
        if self._closing.is_set():  # the node is stopping: what the worker has is the last of the input
            return
        self._count("received")
        self._unheard_publisher = False
        try:
            check_header(msg.height, msg.width, msg.encoding, msg.step, self.max_pixels)
        except ImageRejected as exc:
            self._reject(exc)
            return
        try:
            self.queue.put_nowait((arrival, self._generation, msg))
        except queue.Full:
            self._count("dropped")
            self.warn("dropped", f"inference queue full ({self.queue.maxsize}): frame dropped")

    def _reject(self, exc: ImageRejected) -> None:
        self._count("rejected")
        self.warn(f"reject:{exc.kind}", f"frame rejected: {exc}")

    def handle_frame(self, msg: Image, arrival: float) -> list[MaterialEstimate]:
        """Convert, place on the window, estimate and publish what is due (the worker's job)."""
        try:
            mask = image_to_mask(msg, self.max_pixels, self.threshold)
            stamp = stamp_to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
        except ImageRejected as exc:
            self._reject(exc)
            return []
        except ValueError as exc:  # a malformed stamp
            self._reject(ImageRejected("stamp", str(exc)))
            return []
        encode_time = [0.0]

        def encode(frame, earlier):
            start = time.perf_counter()
            feature = self.model.encode(frame, earlier)
            encode_time[0] += time.perf_counter() - start  # an episode restarted from an overtaken frame re-encodes
            return feature

        episodes, last, start = self.window.episodes, self.window.last_stamp_ns, self.window.episode_start_ns
        late, duplicates = self.window.stats.late, self.window.stats.duplicates
        without_estimate = self.window.stats.without_estimate
        outputs = self.window.add(stamp, mask, encode)
        if self.window.stats.without_estimate != without_estimate:
            self._count("without_estimate")
            slots = self.window.stats.last_without_estimate_slots
            need = (f"the episode policy needs all {self.info.frame_count} (a frame lost at its start or end?); "
                    "output_policy:=anytime estimates from min_frames" if self.window.policy == "episode" else
                    f"the anytime policy needs min_frames ({self.window.min_frames})")
            self.warn("without_estimate", f"episode {episodes} ended with {slots} settled frame slots and no "
                                          f"estimate: {need}")
        if self.window.episodes != episodes:  # this frame started an episode
            self._episode_off_framing = self._check_framing(mask) is not None
        elif self.window.episode_start_ns != start:
            # The episode's true first frame, overtaken at the release: the window started the episode again from
            # it. The framing check is of the first frame (as the clip service's); the episode is counted once.
            if not self._episode_off_framing:
                self._episode_off_framing = self._check_framing(mask) is not None
        elif self.window.stats.late != late:
            self._count("late")
            self.warn("late", f"frame stamped {stamp / 1e9:.3f} s came after one stamped {last / 1e9:.3f} s: dropped "
                              "as late; frames must arrive in stamp order, so check what publishes or relays them")
        elif self.window.stats.duplicates != duplicates:
            self._count("duplicate")
            self.warn("duplicate", f"frame stamped {stamp / 1e9:.3f} s like the one before it: ignored; a camera "
                                   "that does not stamp its images gives no estimates, so stamp each mask with the "
                                   "capture time of its image")
        self._count("processed")
        previous_frame_id, self._frame_id = self._frame_id, msg.header.frame_id
        # This frame's encoding belongs to estimates of its own episode only: an estimate of the episode before that
        # this frame's restart flushed out was not made any slower by it, nor taken by its camera (frame_id).
        return [self._publish(out, msg.header.frame_id, arrival, encode_time[0]) if out.episode == self.window.episodes
                else self._publish(out, previous_frame_id, arrival, 0.0) for out in outputs]

    def _check_framing(self, frame) -> str | None:
        """Warn when an episode starts with the object framed unlike any training clip; the warning, if any."""
        extent = object_extent(frame)
        low, high = TRAINED_EXTENT
        if low <= extent <= high:
            return None
        self._count("off_framing")
        warning = (f"the object spans {extent:.0%} of the image side; training objects spanned {low:.0%} to "
                   f"{high:.0%} (the longer image side covering about 1.4 m at the object): frame the camera alike, "
                   "or expect larger errors (docs/estimator.md, Images)")
        self.warn("framing", f"an episode starts: {warning}")
        return warning

    def _publish(self, out: WindowOutput, frame_id: str, arrival: float | None, encode_time: float) -> MaterialEstimate:
        estimate = self.model.predict(out.features, out.valid)
        model_time = estimate.inference_time + encode_time
        msg = estimate_message(estimate, out, frame_id, self.info.model_id, model_time)
        with self._reset_lock:
            if self._window_generation != self._generation:  # ~/reset came meanwhile: this episode is forgotten
                return msg
            self.publisher.publish(msg)
        self._count("published")
        with self._lock:
            self.model_times.append(model_time)
            if arrival is not None:
                self.latencies.append(time.perf_counter() - arrival)
        if out.complete:  # one line per episode, so that a running node shows it works without ros2 topic echo
            self.get_logger().info(f"episode {out.episode}: {estimate.describe()} ({model_time * 1e3:.1f} ms)")
        return msg

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                arrival, generation, msg = self.queue.get(timeout=0.05)
            except queue.Empty:
                self._sync_reset(self._generation)
                idle = time.monotonic() - self._last_frame_time
                closing = self._closing.is_set()  # the end of the input, as an idle one's
                if self.idle_flush > 0 and (idle > self.idle_flush or closing) and self.window.active:
                    for out in self.window.flush():
                        self._guarded(self._publish, out, self._frame_id, None, 0.0)
                if closing:
                    self._finished.set()
                    return
                continue
            if generation != self._generation:  # queued as ~/reset cleared the queue: it belongs to the old window
                self._count("cleared_by_reset")
                continue
            self._sync_reset(generation)
            self._last_frame_time = time.monotonic()
            self._guarded(self.handle_frame, msg, arrival)

    def _sync_reset(self, generation: int) -> None:
        if generation != self._window_generation:
            self._window_generation = generation
            self.window.reset()

    def _guarded(self, function, *args):
        """Nothing a frame carries may kill the worker: log and count instead."""
        try:
            return function(*args)
        except Exception as exc:  # noqa: BLE001 - the worker must survive any bad frame
            self._count("errors")
            self.warn(f"error:{type(exc).__name__}", f"frame processing failed: {type(exc).__name__}: {exc}")
            return None

    # ------------------------------------------------------------------ services

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._reset_lock, self.queue.mutex:  # frames that arrived before the reset belong to the old window
            cleared = len(self.queue.queue)
            self.queue.queue.clear()
            self._generation += 1
        with self._lock:
            self.counters["cleared_by_reset"] += cleared
        response.success = True
        response.message = (f"window reset: {cleared} queued frame(s) discarded; "
                            "the next frame starts a new episode")
        return response

    def on_estimate(self, request: EstimateMaterial.Request,
                    response: EstimateMaterial.Response) -> EstimateMaterial.Response:
        try:
            response.estimate, framing = self.estimate_clip(list(request.frames))
            response.success = True
            notes = [framing] if framing else []  # the caller may never see the node's log
            if (used := response.estimate.frames_used) < self.info.frame_count:  # an estimate, but from less
                notes.insert(0, f"partial: {used} of the model's {self.info.frame_count} frame slots filled from "
                                f"{len(request.frames)} frames; slots are {self.info.frame_interval * 1e3:g} ms apart "
                                "from the first frame's stamp, and frames past the last slot are not used")
            response.message = "; ".join(notes)
        except ValueError as exc:  # bad clip (ImageRejected is one)
            response.success = False
            response.message = str(exc)
        except Exception as exc:  # noqa: BLE001 - a service error must not take the node down
            response.success = False
            response.message = f"estimation failed: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message)
        return response

    def estimate_clip(self, frames: list[Image]) -> tuple[MaterialEstimate, str | None]:
        """One estimate for a clip (oldest first), through the same slots as the stream, and the
        framing warning if its object is framed unlike training. The clip's use (its stamps, the frames
        past the last slot) is window.clip_output's, as for a library user; this checks what only a
        request has (its headers) and converts the frames clip_output uses."""
        if len(frames) > MAX_CLIP_FRAMES:
            raise ValueError(f"clip of {len(frames)} frames exceeds {MAX_CLIP_FRAMES}")
        stamps = []
        for i, frame in enumerate(frames):  # headers first: nothing is converted if any frame is bad
            try:
                check_header(frame.height, frame.width, frame.encoding, frame.step, self.max_pixels)
                stamps.append(stamp_to_ns(frame.header.stamp.sec, frame.header.stamp.nanosec))
            except ValueError as exc:  # ImageRejected, or a malformed stamp
                raise ValueError(f"frame {i}: {exc}") from exc
            if (frame.width, frame.height) != (frames[0].width, frames[0].height):
                # a stream would restart its window here; a clip is one episode of one camera
                raise ValueError(f"frame {i}: {frame.width}x{frame.height}, frame 0: {frames[0].width}x"
                                 f"{frames[0].height}; clip frames must all have the same size")
        masks = []  # those clip_output converts: the frames it uses

        def convert(frame: Image) -> np.ndarray:
            masks.append(image_to_mask(frame, self.max_pixels, self.threshold))
            return masks[-1]

        model_time = [0.0]

        def timed(function, *args):
            start = time.perf_counter()
            try:
                return function(*args)
            finally:
                model_time[0] += time.perf_counter() - start

        out = clip_output(stamps, frames, lambda *args: timed(self.model.encode, *args), self.info.frame_interval,
                          self.info.frame_count, slot_tolerance=self.slot_tolerance, history=self.info.previous_frames,
                          convert=convert)
        framing = self._check_framing(masks[0])
        estimate = timed(self.model.predict, out.features, out.valid)
        return estimate_message(estimate, out, frames[out.newest_frame].header.frame_id, self.info.model_id,
                                model_time[0]), framing

    # ------------------------------------------------------------------ diagnostics

    def statistics(self) -> dict:
        with self._lock:
            latencies = np.array(self.latencies)
            model_times = np.array(self.model_times)
            counters = dict(self.counters)
        pct = (lambda a, q: float(np.percentile(a, q)) * 1e3 if len(a) else float("nan"))
        return dict(counters, queue_depth=self.queue.qsize(), latency_p50_ms=pct(latencies, 50),
                    latency_p95_ms=pct(latencies, 95), latency_p99_ms=pct(latencies, 99),
                    model_time_p50_ms=pct(model_times, 50), window_restarts=dict(self.window.stats.restarts))

    def publish_diagnostics(self) -> None:
        now = time.monotonic()
        period = max(now - self._diag_time, 1e-6)
        self._diag_time = now
        with self._lock:
            recent = dict(self._period_counts)
            self._period_counts = dict.fromkeys(self._period_counts, 0)
        stats = self.statistics()
        status = DiagnosticStatus()
        status.name = f"{self.get_fully_qualified_name()}: material estimator"
        status.hardware_id = self.info.model_id
        problems = [f"{recent[k]} frames {k}" for k in ("dropped", "rejected", "late") if recent[k]]
        problems += [f"{recent['duplicate']} frames with a repeated stamp"] if recent["duplicate"] else []
        problems += [f"{recent['errors']} processing errors (see the log)"] if recent["errors"] else []
        problems += ([f"{recent['without_estimate']} episodes ended without an estimate"]
                     if recent["without_estimate"] else [])
        if self._unheard_publisher:
            problems.append(f"no frames; {stats['incompatible_publishers']} input publisher(s) with incompatible QoS seen")
        status.level = (DiagnosticStatus.ERROR if recent["errors"] else DiagnosticStatus.WARN if problems
                        else DiagnosticStatus.OK)
        status.message = "; ".join(problems) or "ok"
        values = {
            "model_id": self.info.model_id, "model_path": str(self.info.path), "input_topic": self.input_topic,
            "input_rate_hz": f"{recent['received'] / period:.2f}",
            "estimate_rate_hz": f"{recent['published'] / period:.2f}",
            "latency_p50_ms": f"{stats['latency_p50_ms']:.3f}", "latency_p95_ms": f"{stats['latency_p95_ms']:.3f}",
            "model_time_p50_ms": f"{stats['model_time_p50_ms']:.3f}",
            "frames_received": str(stats["received"]), "frames_rejected": str(stats["rejected"]),
            "frames_dropped": str(stats["dropped"]), "frames_late": str(stats["late"]),
            "frames_duplicate": str(stats["duplicate"]), "frames_cleared_by_reset": str(stats["cleared_by_reset"]),
            "estimates_published": str(stats["published"]),
            "processing_errors": str(stats["errors"]), "queue_depth": str(stats["queue_depth"]),
            "episodes_without_estimate": str(stats["without_estimate"]),
            "episodes_off_framing": str(stats["off_framing"]),
            "incompatible_publishers": str(stats["incompatible_publishers"]),
            "window_restarts": str(sum(v for k, v in stats["window_restarts"].items() if k != "first")),
        }
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diagnostics.publish(array)

    def _serve_clips_apart(self) -> None:
        """~/estimate on a companion node (<name>_clip) with a single-threaded executor in a thread of its own: a
        clip (up to MAX_CLIP_FRAMES large frames) takes seconds, and on the stream's executor it would hold up the
        subscription while the stream's frames are lost. (rclpy's MultiThreadedExecutor serves both too, but on a
        2-core CPU it raised the stream's p99 latency from 5-6 ms to 19-35 ms: benchmarks/latency.py.)"""
        service = self.resolve_service_name("~/estimate")  # the name the node's remaps give it, used as is
        self.clip_node = Node(f"{self.get_name()}_clip", namespace=self.get_namespace(), context=self.context,
                              use_global_arguments=False, start_parameter_services=False)
        self.clip_node.create_service(EstimateMaterial, service, self.on_estimate)
        self.clip_executor = SingleThreadedExecutor(context=self.context)
        self.clip_executor.add_node(self.clip_node)
        self.clip_server = threading.Thread(target=self._serve_clips, name="ad_estimator_clips", daemon=True)
        self.clip_server.start()

    def _serve_clips(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            try:
                self.clip_executor.spin_once(timeout_sec=0.1)
            except Exception as exc:  # noqa: BLE001 - the service must outlive one failed call while ROS runs
                if self._stop.is_set() or not self.context.ok():
                    return  # the context shut down under it: the node is going
                self._count("errors")
                self.warn(f"clip:{type(exc).__name__}", f"the clip service failed: {type(exc).__name__}: {exc}")

    def finish(self, timeout: float = FINISH_TIMEOUT_S) -> bool:
        """The end of the input (SIGINT, SIGTERM): the frames delivered so far are taken (they may still wait in the
        subscription for the executor, spinning meanwhile in another thread) and estimated, later ones are ignored;
        the window is flushed as when the input goes idle (unless idle_flush is 0), and the estimates' delivery to
        reliable subscribers is awaited; all of it within `timeout` s. Without this the last episode's estimate was
        lost at shutdown whenever it was still queued or waited for the idle flush (a launch file stopping the
        estimator as its camera or bag replay ended). True if all of it was done."""
        start = time.monotonic()
        deadline = start + timeout
        seen, quiet_since = self.counters["received"], start
        while time.monotonic() - quiet_since < FINISH_QUIET_S and time.monotonic() < min(deadline, start + FINISH_TAKE_S):
            time.sleep(0.01)
            if self.counters["received"] != seen:
                seen, quiet_since = self.counters["received"], time.monotonic()
        self._closing.set()
        done = self.worker.is_alive() and self._finished.wait(max(0.0, deadline - time.monotonic()))
        return self.publisher.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic()))) and done

    def destroy_node(self) -> None:
        self._stop.set()
        # The threads finish what they do (a clip call: up to 2 s more), whatever signal comes meanwhile (StopSignals):
        # a thread still in rclpy or onnxruntime when the interpreter exits aborts the process (C++ terminate).
        if self.worker.is_alive():
            self.worker.join(timeout=2.0)
        if self.clip_server.is_alive():
            self.clip_server.join(timeout=2.0)
        self.clip_executor.shutdown(timeout_sec=1.0)
        self.clip_node.destroy_node()
        super().destroy_node()


def parse_cli(argv: list[str]) -> None:
    """--help, and usage errors for anything outside --ros-args."""
    node_cli(
        "ros2 run ad_estimator node",
        "Online material estimation from one mask stream with an ONNX student "
        "(publishes ad_msgs/MaterialEstimate on /ad_estimator/estimate).",
        [(name, default, text) for name, (default, text) in PARAMETERS.items()], argv,
        epilog=f"\n\nTopics:\n  subscribes {DEFAULT_INPUT_TOPIC} (sensor_msgs/Image masks; remap the input with"
        "\n             --ros-args -r mask:=/camera/mask)"
        "\n  publishes  /ad_estimator/estimate (ad_msgs/MaterialEstimate), /diagnostics (every diagnostics_period)"
        "\nServices (~/ under the node name, default ad_estimator):"
        "\n  /ad_estimator/reset     std_srvs/Trigger: forget the current episode; the next frame starts a new one"
        "\n  /ad_estimator/estimate  ad_msgs/srv/EstimateMaterial: one estimate for a clip of frames in the request"
        "\n\nExit status 1 if the model cannot be loaded.")


def make_executor(context=None) -> SingleThreadedExecutor:
    """The node's executor (the clip service has its own: EstimatorNode._serve_clips_apart)."""
    return SingleThreadedExecutor(context=context)


class StopSignals:
    """SIGINT and SIGTERM (what launch sends) as a request to stop: the node then finishes its input (finish)
    before the context goes. rclpy's own handlers shut the context down at once, and the estimates of frames
    still queued or of the window not yet flushed were lost. A later signal cuts that wait short (KeyboardInterrupt,
    raised only inside `interruptible`), or skips it if it came before (during start-up, say), and is otherwise
    ignored: the clean-up is short (its waits have time limits) and must run to its end. Raised wherever the main
    thread was, a third Ctrl-C (or launch's SIGTERM after its SIGINT) came out of rclpy destroying the node as a
    traceback, or of a thread left in rclpy as an abort."""

    def __init__(self):
        self.requested = threading.Event()
        self.repeated = False  # a later signal came
        self._interruptible = False  # set by the main thread while a later signal may cut its wait short

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self)

    def __call__(self, signum, frame) -> None:
        if not self.requested.is_set():
            self.requested.set()
            return
        self.repeated = True
        if self._interruptible:
            self._interruptible = False  # one KeyboardInterrupt: none while it is being handled
            raise KeyboardInterrupt

    def interruptible(self, wait) -> None:
        """wait(), cut short by a later signal; not begun if one came already."""
        try:  # (set and cleared inside: a signal just before or after wait() is caught here too)
            self._interruptible = True
            if not self.repeated:
                wait()
            self._interruptible = False
        except KeyboardInterrupt:
            pass
        finally:
            self._interruptible = False

    def ignore(self) -> None:
        """Once the clean-up is done: the interpreter's exit puts back the default action (death by the signal) of
        every signal with a Python handler, though not of an ignored one."""
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


def main(args=None) -> int:
    stop = StopSignals()
    stop.install()  # first: a signal from here on stops the start-up (before, ad_sim.dds.quiet_interrupt)
    atexit.register(stop.ignore)  # at the interpreter's exit: an in-process caller of main keeps its signals
    parse_cli(sys.argv if args is None else args)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = executor = spinner = None
    try:
        # A signal during start-up ends it with the step in progress (the model loads in one call into onnxruntime,
        # which a signal cannot cut short), and the node exits: it never spun, so it took no input to finish.
        if not stop.requested.is_set():
            node = EstimatorNode()
        if stop.requested.is_set():
            return 0
        executor = make_executor()
        executor.add_node(node)
        failure = []  # what ended the executor's thread, raised here as when it spun on this one

        def spin():
            try:
                executor.spin()
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                failure.append(exc)
                stop.requested.set()

        spinner = threading.Thread(target=spin, name="ad_estimator_spin", daemon=True)
        spinner.start()
        while not stop.requested.wait(0.5) and rclpy.ok() and spinner.is_alive():
            pass
        if failure:
            raise failure[0]
        if rclpy.ok():
            stop.interruptible(node.finish)
    except (ModelError, ValueError, ParameterException) as exc:
        print(f"ad_estimator: {exc}", file=sys.stderr)
        return 1
    except ExternalShutdownException:
        pass  # the context shut down under the executor: a clean exit
    except RCLError:
        if rclpy.ok():
            raise
        # the context shut down while rclpy was still setting something up: also clean
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if spinner is not None:
            spinner.join(timeout=1.0)
        if node is not None:
            # print, not the ROS logger: it must come out whatever state the context is in
            print(f"ad_estimator: shutting down: {node.statistics()}", file=sys.stderr, flush=True)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
