"""Placing frames on the model's frame slots by their stamps, episode segmentation, output policy.

Pure logic (no ROS, no onnxruntime), shared by the node, its EstimateMaterial service, evaluate
and the latency benchmark, so that live and offline paths see exactly the same slots.

Resampling rule. An episode starts at the stamp t0 of its first frame; slot k (k < frame_count)
sits at t0 + k * dt, dt the model's frame interval. Each slot takes the received frame whose stamp
is nearest to the slot time, provided it is within ``slot_tolerance * dt`` (ties go to the earlier
frame). A slot no frame comes near stays empty and is passed to the model as invalid (``valid``
mask), never invented. So a 40 fps camera fills every slot exactly, a 30 fps or jittery camera
gets the nearest frames (time error at most half its frame period), a camera slower than
1 / (2 * tolerance * dt) leaves gaps. Slot k is final ("settled") once a frame stamped at or after
its time arrived (no later frame can be nearer); estimates only ever use settled slots, so the
estimate at 25 frames is due the moment the frame for the last slot arrives. ``flush()`` (no more
frames are coming: end of stream, idle input) settles the slots up to the one nearest to the last
frame, so a clip of K frames on the interval gives exactly K slots.

Frames. The caller offers each frame with an ``encode(frame, earlier)`` function, called once if
the frame lands in a slot. ``earlier`` holds the frames of the latest ``history`` filled slots
before it in the same episode, newest first: fewer at the episode's start, none for its first
frame. It is for models whose frame encoder also sees earlier observed frames (``history`` is then
the model's ``previous_frames``, required: a wrong one gives plausible but wrong estimates);
others ignore it. A frame that fills several slots (a slow camera, a dropped frame) is encoded
once, with the frames before its first slot; a later frame finds it once per slot it fills, as the
model's head sees it. The window keeps only the frames a later frame can still need as one of its
earlier ones.

Episodes. The window restarts (its next frame becomes frame 0) on a stamp more than
``gap_threshold`` seconds after the last frame's, on a stamp more than LATE_FRAMES frame intervals
(or ``gap_threshold``, if shorter) before it (a stream or a bag starting over), on a change of
image size and on ``reset()``. A frame less far back arrived out of order (reordered upstream):
every slot it could fill is settled already or nearer to the later frame, so it is dropped and
counted as late, and the episode goes on; so is a frame that far behind the last one of the episode
before (a straggler across a restart) when it is further back than that from the last frame too,
as after a gap restart (after a size change it restarts the window again; after a stream starting
over it is a frame of the new episode, or a gap). A frame stamped before the episode's first one,
within that reach, is the episode's true first frame overtaken at the release: the episode starts
again from it, with the frames it has (all kept until then), unless its last slot is settled
already (possible for models of at most LATE_FRAMES + 1 slots): its estimate is out, so the frame
is late. A stream that starts over after at most LATE_FRAMES frames cannot be told from reordering
by stamps; its first frames are then taken as late. A frame with the same stamp as the previous
one is a duplicate and ignored (a camera that does not stamp its images gives nothing but
duplicates). The model expects frame 0 at the release of the object, so the window is anchored
at the episode start; once the episode's last slot is settled, further frames are ignored until a
restart.

Output policy. ``episode``: one estimate per episode when all frame_count slots are settled.
``anytime``: an estimate when min_frames slots are settled, then each time ``every_n`` more are,
always one when the window is complete, and one on flush if slots were settled since the last.
"""
from __future__ import annotations

import math
import operator
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

POLICIES = ("episode", "anytime")
DEFAULT_GAP_THRESHOLD = 0.3  # s; episodes in a simulator stream are > 0.5 s apart, frames 0.025 s
DEFAULT_SLOT_TOLERANCE = 1.0  # frame intervals
# Anytime policy: the bundled model's unseen RegL1 is 0.161 from 15 frames, 0.226 from 10 (README, temporal OOD).
DEFAULT_MIN_FRAMES = 15
DEFAULT_EVERY_N = 5  # anytime policy: then an estimate every 5 frames (0.125 s at 40 fps)
# Reordering upstream (say, a segmentation pipeline with parallel workers) delivers a frame at most this many
# frame intervals late; a stamp further back than that is a stream or bag starting over.
LATE_FRAMES = 4
# Stamps closer than this to a slot time count as at it (float stamps such as 1.5 + 3 * 0.025).
SETTLE_EPSILON_NS = 1_000

# encode(frame, earlier frames of the episode, newest first) -> the frame's feature
Encode = Callable[[np.ndarray, "list[np.ndarray]"], np.ndarray]

RESTART_FIRST = "first"
RESTART_GAP = "gap"
RESTART_BACKWARDS = "backwards"
RESTART_SIZE = "size"


@dataclass
class WindowOutput:
    """The settled slots of one episode when an estimate is due."""

    features: np.ndarray  # (n, *feature_shape); zeros where invalid
    valid: np.ndarray  # (n,) bool
    complete: bool  # all frame_count slots settled
    oldest_stamp_ns: int  # stamp of the frame in the first valid slot
    newest_stamp_ns: int  # stamp of the frame in the last valid slot
    episode_start_ns: int  # t0: stamp of the episode's first frame
    episode: int  # which episode of the window's stream: 1 for the first one started, 2 for the next, ...

    @property
    def frames_used(self) -> int:
        return int(self.valid.sum())


@dataclass
class _Slot:
    stamp_ns: int
    error_ns: int
    feature: np.ndarray
    frame: np.ndarray | None  # None once no later frame can need it as an earlier one


@dataclass
class WindowStats:
    frames: int = 0  # frames offered
    ignored: int = 0  # frames after the episode's end, frames between slots
    late: int = 0  # frames older than the last one by at most LATE_FRAMES intervals: out of order, dropped
    duplicates: int = 0  # frames stamped like the previous one
    without_estimate: int = 0  # episodes that ended (the next one started) without any estimate
    last_without_estimate_slots: int = 0  # the settled slots of the latest of those
    restarts: Counter = field(default_factory=Counter)  # by reason


MAX_SECONDS = 1e6  # bound of the window's durations in seconds (11.6 days), far inside int64 nanoseconds


class FrameWindow:
    """Online episode window; see the module docstring for the rules."""

    def __init__(self, frame_interval: float, frame_count: int, gap_threshold: float = DEFAULT_GAP_THRESHOLD,
                 slot_tolerance: float = DEFAULT_SLOT_TOLERANCE, policy: str = "episode", every_n: int = 1,
                 min_frames: int = DEFAULT_MIN_FRAMES,
                 *, history: int):
        if policy not in POLICIES:
            raise ValueError(f"output policy must be one of {POLICIES}, got {policy!r}")
        if history < 0:
            raise ValueError(f"history is a number of earlier frames >= 0, got {history}")
        if not 0 < frame_interval < math.inf or frame_count < 1 or every_n < 1 or (
                policy == "anytime" and not 1 <= min_frames <= frame_count):
            raise ValueError("need a finite frame_interval > 0, frame_count >= 1, every_n >= 1, "
                             "and for the anytime policy 1 <= min_frames <= frame_count")
        if not 0 < slot_tolerance <= 2:
            raise ValueError("slot_tolerance is a fraction of the frame interval in (0, 2]")
        self.interval_ns = int(round(frame_interval * 1e9))
        if not gap_threshold <= MAX_SECONDS:  # stamps are int64 ns; NaN fails here too
            raise ValueError(f"gap_threshold must be a number of seconds up to {MAX_SECONDS:g}, got {gap_threshold}")
        if not gap_threshold * 1e9 > self.interval_ns * slot_tolerance:
            raise ValueError("gap_threshold must exceed slot_tolerance * frame_interval")
        self.frame_count = frame_count
        self.gap_ns = int(round(gap_threshold * 1e9))
        self.late_ns = min(self.gap_ns, LATE_FRAMES * self.interval_ns)
        self.tolerance_ns = int(round(slot_tolerance * self.interval_ns))
        self.policy = policy
        self.every_n = every_n
        self.min_frames = min_frames if policy == "anytime" else frame_count
        self.history = history
        self.stats = WindowStats()
        self.reset()

    @property
    def episodes(self) -> int:
        """Episodes started: each one's first frame counts exactly one restart (its reason, or "first")."""
        return sum(self.stats.restarts.values())

    def reset(self) -> None:
        """Forget the current episode; the next frame starts a new one."""
        self._clear_episode()
        self._previous_last_ns: int | None = None  # the last stamp of the episode before, for stragglers

    def _clear_episode(self) -> None:
        self._start_ns: int | None = None
        self._last_ns: int | None = None
        self._size: tuple | None = None
        self._slots: list[_Slot | None] = [None] * self.frame_count
        self._settled = 0  # slots 0.._settled-1 are final
        self._emitted = 0  # settled count at the last estimate (0 = none yet)
        self._done = False
        self._opening: list[tuple[int, np.ndarray, Encode]] = []  # frames within late_ns of the start

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the newest frame of the current episode (None before its first)."""
        return self._last_ns

    @property
    def episode_start_ns(self) -> int | None:
        """Stamp of the current episode's first frame (None before its first): it moves back, the episode count
        staying, when the true first frame arrives overtaken."""
        return self._start_ns

    @property
    def active(self) -> bool:
        """An episode has started and its final estimate is not out yet."""
        return self._start_ns is not None and not self._done

    def _restart(self, reason: str) -> list[WindowOutput]:
        outputs = self.flush() if self._start_ns is not None else []
        if self._start_ns is not None and not self._emitted:
            self.stats.without_estimate += 1
            self.stats.last_without_estimate_slots = self._settled
        self.stats.restarts[reason] += 1
        self._previous_last_ns = self._last_ns
        self._clear_episode()
        return outputs

    def _restart_from(self, stamp_ns: int, frame: np.ndarray, encode: Encode) -> list[WindowOutput]:
        """The episode's true first frame came after others (swapped at the release): the episode
        starts again from it, with its frames so far (all within late_ns of its start, so kept)."""
        frames = [(stamp_ns, frame, encode), *self._opening]
        self._clear_episode()
        return [out for frame_args in frames for out in self._offer(*frame_args)]

    def add(self, stamp_ns: int, frame: np.ndarray, encode: Encode) -> list[WindowOutput]:
        """Offer one frame (stamp: whole ns, a Python or NumPy integer); ``encode(frame, earlier)`` is
        called only if it lands in a slot.

        Returns the estimates due now: usually none; the previous episode's last one when this frame
        restarts the window (see flush); at most one for the current episode.
        """
        stamp_ns = whole_ns(stamp_ns, "stamp_ns")
        self.stats.frames += 1
        size = frame.shape
        outputs: list[WindowOutput] = []
        if self._start_ns is None:
            self.stats.restarts[RESTART_FIRST] += 1
        elif size != self._size:
            outputs = self._restart(RESTART_SIZE)
        elif self._last_ns - stamp_ns > self.late_ns:
            if self._previous_last_ns is not None and 0 <= self._previous_last_ns - stamp_ns <= self.late_ns:
                self.stats.late += 1  # a straggler of the episode before
                return outputs
            outputs = self._restart(RESTART_BACKWARDS)
        elif stamp_ns < self._start_ns and not self._done:  # once complete, the episode's estimate is out
            return self._restart_from(stamp_ns, frame, encode)
        elif stamp_ns < self._last_ns:
            self.stats.late += 1
            return outputs
        elif stamp_ns - self._last_ns > self.gap_ns:
            outputs = self._restart(RESTART_GAP)
        elif stamp_ns == self._last_ns:
            self.stats.duplicates += 1
            return outputs
        return outputs + self._offer(stamp_ns, frame, encode)

    def _offer(self, stamp_ns: int, frame: np.ndarray, encode: Encode) -> list[WindowOutput]:
        """Place a frame that continues (or starts) the current episode; the estimates then due."""
        if self._start_ns is None:
            self._start_ns, self._size = stamp_ns, frame.shape
        if stamp_ns - self._start_ns <= self.late_ns:
            self._opening.append((stamp_ns, frame, encode))
        self._last_ns = stamp_ns
        if self._done:
            self.stats.ignored += 1
            return []
        self._place(stamp_ns, frame, encode)
        offset = stamp_ns - self._start_ns + SETTLE_EPSILON_NS
        self._settled = min(self.frame_count, max(self._settled, offset // self.interval_ns + 1))
        self._forget_frames()
        return self._due(final=False)

    def _place(self, stamp_ns: int, frame: np.ndarray, encode: Encode) -> None:
        rel = stamp_ns - self._start_ns
        first = max(self._settled, -((self.tolerance_ns - rel) // self.interval_ns))  # ceil((rel - tol) / dt)
        last = min(self.frame_count - 1, (rel + self.tolerance_ns) // self.interval_ns)
        feature = None
        for k in range(first, last + 1):
            error = abs(rel - k * self.interval_ns)
            slot = self._slots[k]
            if slot is None or error < slot.error_ns:
                if feature is None:
                    feature = encode(frame, self._earlier_frames(k))
                self._slots[k] = _Slot(stamp_ns, error, feature, frame)
        if feature is None:
            self.stats.ignored += 1

    def _earlier_frames(self, k: int) -> list[np.ndarray]:
        """The frames of the latest ``history`` filled slots before slot k, newest first."""
        filled = [s for s in reversed(self._slots[:k]) if s is not None]
        return [s.frame for s in filled[:self.history]]

    def _forget_frames(self) -> None:
        """Later frames land at or after the first unsettled slot, so of the settled slots only the
        latest ``history`` filled ones can still hold an earlier frame; none can once the episode is
        complete."""
        filled = [s for s in self._slots[:self._settled] if s is not None]
        complete = self._settled == self.frame_count
        kept = 0 if complete else self.history
        for slot in filled[:max(0, len(filled) - kept)]:
            slot.frame = None

    def flush(self) -> list[WindowOutput]:
        """No more frames are coming for now: settle up to the last frame's slot, emit what is then due.

        Safe to call at any time (e.g. when input went idle): frames that still come later continue
        the episode, only an estimate already emitted is not repeated."""
        if not self.active:
            return []
        # Up to the slot nearest to the last frame: later slots would only repeat that frame.
        nearest = (self._last_ns - self._start_ns + self.interval_ns // 2) // self.interval_ns
        self._settled = max(self._settled, min(self.frame_count, nearest + 1))
        return self._due(final=True)

    def _due(self, final: bool) -> list[WindowOutput]:
        n = self._settled
        complete = n == self.frame_count
        if n <= self._emitted or n < self.min_frames:
            return []
        if self.policy == "episode":
            due = complete
        else:
            due = complete or final or self._emitted == 0 or n - self._emitted >= self.every_n
        if not due:
            return []
        output = self._output(n)
        if output is None:
            return []
        self._emitted = n
        self._done = complete
        return [output]

    def _output(self, n: int) -> WindowOutput | None:
        slots = self._slots[:n]
        used = [s for s in slots if s is not None]
        if not used:
            return None
        shape = used[0].feature.shape
        features = np.zeros((n, *shape), used[0].feature.dtype)
        valid = np.zeros(n, bool)
        for k, slot in enumerate(slots):
            if slot is not None:
                features[k] = slot.feature
                valid[k] = True
        return WindowOutput(features, valid, n == self.frame_count, used[0].stamp_ns, used[-1].stamp_ns,
                            self._start_ns, self.episodes)


def stamp_to_ns(sec: int, nanosec: int) -> int:
    """builtin_interfaces/Time -> ns; ValueError for a nanosec of a second or more, which is no time (read as
    is, it shifted the frame by seconds, and near the end of int32 seconds the published stamp wrapped)."""
    if not 0 <= int(nanosec) < 1_000_000_000:
        raise ValueError(f"stamp nanosec {nanosec} is not below 1e9 (a malformed header stamp)")
    return int(sec) * 1_000_000_000 + int(nanosec)


def ns_to_stamp(ns: int) -> tuple[int, int]:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return sec, nanosec


def clip_stamps(stamps_ns: list[int], frame_interval: float) -> list[int]:
    """Stamps for a clip given in one call: its own if strictly increasing; all equal (unstamped,
    e.g. zero) means consecutive frames on the model's interval. Anything else is an error."""
    if len(stamps_ns) > 1 and all(s == stamps_ns[0] for s in stamps_ns):
        step = int(round(frame_interval * 1e9))
        return [stamps_ns[0] + k * step for k in range(len(stamps_ns))]
    for i in range(1, len(stamps_ns)):
        if stamps_ns[i] <= stamps_ns[i - 1]:
            raise ValueError(f"frame {i}: stamp {stamp_text(stamps_ns[i])} s is not after frame {i - 1}'s "
                             f"({stamp_text(stamps_ns[i - 1])} s); clip stamps must be strictly increasing, oldest "
                             "first (or all equal: frames on the model's interval)")
    return list(stamps_ns)


def whole_ns(stamp, subject: str) -> int:
    """A stamp as a Python int of nanoseconds; TypeError naming `subject` for anything else (a float). A NumPy
    integer is taken as its value: kept, a uint64 wrapped in differences (every frame went "backwards")."""
    try:
        return operator.index(stamp)
    except TypeError:
        raise TypeError(f"{subject} is a whole number of nanoseconds, got {type(stamp).__name__} {stamp!r}; "
                        "from seconds: round(t * 1e9)") from None


def stamp_text(ns: int) -> str:
    """A stamp as sec.nanosec, exactly (a float of ns since 1970 rounds them)."""
    sec, nanosec = ns_to_stamp(ns)
    return f"{sec}.{nanosec:09d}"


@dataclass
class ClipOutput(WindowOutput):
    """clip_output's answer: a WindowOutput whose stamps are the clip's own (those of a clip stamped all alike too),
    and which of the clip's frames they are."""

    oldest_frame: int = 0  # index in the clip of the frame in the first valid slot
    newest_frame: int = 0  # ... in the last valid slot


def clip_output(stamps_ns: Sequence[int], masks: Sequence, encode: Encode,
                frame_interval: float, frame_count: int, *, history: int,
                slot_tolerance: float = DEFAULT_SLOT_TOLERANCE,
                convert: Callable[[object], np.ndarray] | None = None) -> ClipOutput:
    """The slots of a whole clip (oldest first), as one episode: what the stream would give at its
    last frame, settled as at the end of a stream. The one code path of the node's EstimateMaterial
    service, evaluate and library users, so that all of them get the same slots for the same clip.
    ``history``: earlier frames an encoding reads (the model's ``info.previous_frames``), required
    because a wrong one gives a plausible but wrong estimate.

    Stamps (whole ns) must increase strictly, or be all equal: frames on the model's interval
    (clip_stamps); the output's stamps are then the frames' own, not the slot times. Any clip
    length: slots reach ``(frame_count - 1) * frame_interval`` plus the slot tolerance past the
    first frame's stamp, and the frames after that are used in no slot: they are neither converted
    nor encoded (the first of them only settles the slots, so the output is complete), so a long clip
    whose object leaves the view later, or whose first frame is stamped 0 and the others with the
    clock (then a partial output from frame 0), gets its output. ``masks`` are the frames' masks, or,
    with ``convert``, anything ``convert(frame)`` makes a mask of (e.g. images.array_to_mask), called
    for the used frames only, all of them before any encoding; its ValueError (ImageRejected) comes
    out as a ValueError naming the frame ("frame 3: ...").

    As in a stream, a change of image size among the frames used restarts the window: the output is
    then that of the frames from the last change on (its episode_start_ns says where), whose slots
    reach as far past that frame. A frame past the last slot is not used, whatever its size: the
    output is then that of the episode before it (a stream would go on to another episode).

    Errors (ValueError, TypeError for a stamp that is no whole number, each naming the frame at
    fault): an empty clip, as many stamps as masks not given, stamps that repeat or go back, a
    frame ``convert`` refuses.
    """
    stamps_ns, masks = list(stamps_ns), list(masks)
    if len(stamps_ns) != len(masks):
        raise ValueError(f"{len(stamps_ns)} stamps for {len(masks)} frames: give one stamp per frame")
    if not len(masks):
        raise ValueError("empty clip: send at least one frame")
    stamps = [whole_ns(stamp, f"frame {i}: a stamp") for i, stamp in enumerate(stamps_ns)]
    slot_stamps = clip_stamps(stamps, frame_interval)  # ValueError naming the frame out of order
    # Never a gap restart: each frame placed lies within (frame_count + 1) intervals of the one before it.
    gap_threshold = min(MAX_SECONDS, (frame_count + 2) * frame_interval)
    window = FrameWindow(frame_interval, frame_count, gap_threshold=gap_threshold, slot_tolerance=slot_tolerance,
                         policy="anytime", every_n=frame_count, min_frames=1, history=history)
    # Frames past the last slot's reach are used in no slot: the first of them only settles the slots (complete),
    # the rest change nothing. So they are neither converted nor placed, and the first one is put just past the
    # reach, with an empty mask of the last used frame's size: a stamp days later (a first frame stamped 0, the
    # others with the clock) would otherwise be out of the window's range. The reach is the current episode's: a
    # frame of another size than the one before it starts the episode again (the window restarts there).
    span_ns = (frame_count - 1) * window.interval_ns + window.tolerance_ns
    used_masks: list[np.ndarray] = []
    reach_ns = slot_stamps[0] + span_ns
    for i, (stamp, frame) in enumerate(zip(slot_stamps, masks)):
        if stamp > reach_ns:
            break
        if convert is None:
            mask = frame
        else:
            try:
                mask = convert(frame)
            except ValueError as exc:  # ImageRejected is one
                raise ValueError(f"frame {i}: {exc}") from exc
        if used_masks and np.shape(mask) != np.shape(used_masks[-1]):
            reach_ns = stamp + span_ns
        used_masks.append(mask)
    used = len(used_masks)
    placed = slot_stamps[:used]
    if used < len(slot_stamps):
        used_masks.append(np.zeros_like(used_masks[-1]))  # encoded never: it lands in no slot
        placed.append(reach_ns + 1)
    outputs = []
    for stamp, mask in zip(placed, used_masks):
        outputs += window.add(stamp, mask, encode)
    outputs += window.flush()
    out = outputs[-1]  # the episode's first frame fills slot 0: there is an output
    index = {stamp: i for i, stamp in enumerate(slot_stamps[:used])}
    oldest, newest = index[out.oldest_stamp_ns], index[out.newest_stamp_ns]
    # The frames' own stamps: those of a clip of equal stamps, spread on the model's interval for the slots only,
    # are no capture time (they lay up to 0.6 s after all of them).
    return ClipOutput(out.features, out.valid, out.complete, stamps[oldest], stamps[newest],
                      stamps[index[out.episode_start_ns]], out.episode, oldest_frame=oldest, newest_frame=newest)
