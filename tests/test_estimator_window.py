"""ad_estimator.window: stamp-based slots, episode restarts, output policies (pure logic)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ad_estimator.parameters import PARAMETERS, model_window
from ad_estimator.window import LATE_FRAMES, FrameWindow, clip_output, clip_stamps

DT = 25_000_000  # ns
SIZE = (128, 128)


def frame(size=SIZE):
    return np.zeros(size, np.uint8)


def feed(window, stamps, size=SIZE):
    """Offer frames whose feature is their own stamp; returns every output."""
    outputs = []
    for s in stamps:
        outputs += window.add(s, frame(size), lambda _frame, _earlier, s=s: np.array([float(s)]))
    return outputs


def chosen(output):
    return [int(f[0]) if v else None for f, v in zip(output.features, output.valid)]


def reference_slots(stamps, t0, count, tolerance):
    """Brute force: per slot the nearest stamp within tolerance, ties to the earlier."""
    result = []
    for k in range(count):
        best = min(stamps, key=lambda s: (abs(s - (t0 + k * DT)), s))
        result.append(best if abs(best - (t0 + k * DT)) <= tolerance else None)
    return result


def test_exact_interval_gives_one_complete_estimate_at_frame_25():
    window = FrameWindow(0.025, 25, history=1)
    t0 = 1_500_000_000
    stamps = [t0 + k * DT for k in range(25)]
    assert feed(window, stamps[:24]) == []
    (out,) = feed(window, stamps[24:])
    assert out.complete and out.frames_used == 25
    assert chosen(out) == stamps
    assert (out.oldest_stamp_ns, out.newest_stamp_ns, out.episode_start_ns) == (t0, stamps[-1], t0)
    assert feed(window, [t0 + 25 * DT, t0 + 26 * DT]) == []  # the episode is over; no second estimate


def test_float_stamps_rounded_to_ns_still_settle_on_time():
    window = FrameWindow(0.025, 25, history=1)
    stamps = [int((1.5 * 3 + k * 0.025) * 1e9) for k in range(25)]  # float maths may lose a nanosecond
    outs = feed(window, stamps)
    assert len(outs) == 1 and outs[0].frames_used == 25


def test_30fps_camera_fills_every_slot_with_the_nearest_frame():
    window = FrameWindow(0.025, 25, history=1)
    stamps = [round(k * 1e9 / 30) for k in range(40)]
    (out,) = feed(window, stamps)
    assert out.complete and out.frames_used == 25
    assert chosen(out) == reference_slots(stamps, 0, 25, DT)
    for k, s in enumerate(chosen(out)):
        assert abs(s - k * DT) <= 1e9 / 60 + 1  # at most half the camera period away


def test_slow_camera_leaves_invalid_slots_instead_of_inventing_frames():
    window = FrameWindow(0.025, 25, history=1, slot_tolerance=0.5)
    stamps = [k * 100_000_000 for k in range(7)]  # 10 fps
    (out,) = feed(window, stamps)
    assert out.complete
    assert out.valid.tolist() == [k % 4 == 0 for k in range(25)]
    assert out.frames_used == 7
    assert np.all(out.features[~out.valid] == 0)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(1_000_000, 45_000_000), min_size=1, max_size=60),
       st.integers(0, 10**12), st.sampled_from([0.5, 1.0]))
def test_jittery_stamps_match_brute_force_nearest_frame(steps, t0, tolerance):
    window = FrameWindow(0.025, 25, history=1, gap_threshold=0.3, slot_tolerance=tolerance)
    stamps = list(np.cumsum([t0] + steps))
    outs = feed(window, stamps)
    outs += window.flush()
    last_slot = t0 + 24 * DT
    last = stamps[-1]
    reached = last >= last_slot - 1_000 or (last - t0 + DT // 2) // DT >= 24  # flush settles the last frame's slot
    # Exactly one estimate (the episode policy) iff the last slot was reached; it matches brute force.
    if reached:
        assert len(outs) == 1
        assert chosen(outs[0]) == reference_slots(stamps, t0, 25, tolerance * DT)
    else:
        assert outs == []


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(-50_000_000, 400_000_000), st.sampled_from([(128, 128), (64, 64)]),
                          st.booleans()), max_size=120),
       st.sampled_from(["episode", "anytime"]), st.integers(1, 5), st.integers(1, 25))
def test_random_streams_keep_invariants(events, policy, every_n, min_frames):
    """Any stamps, sizes and resets: no exception, well-formed outputs, encode at most once per frame
    (and once more for each frame of an episode's opening when its overtaken first frame restarts it)."""
    window = FrameWindow(0.025, 25, history=1, policy=policy, every_n=every_n, min_frames=min_frames)
    stamp = 10**9
    calls = 0
    for step, size, reset in events:
        if reset:
            window.reset()
        stamp += step

        def encode(_frame, _earlier, s=stamp):
            nonlocal calls
            calls += 1
            return np.array([float(s)])

        before, opening = calls, len(window._opening)
        for out in window.add(stamp, frame(size), encode):
            assert 1 <= len(out.valid) <= 25 and out.valid.any()
            assert out.features.shape == (len(out.valid), 1)
            assert out.oldest_stamp_ns <= out.newest_stamp_ns
            assert out.complete == (len(out.valid) == 25)
            used = [s for s in chosen(out) if s is not None]
            assert used == sorted(used)  # one frame may serve two neighbouring slots
            assert out.episode_start_ns <= out.oldest_stamp_ns
            if policy == "anytime":
                assert out.frames_used <= len(out.valid)
        assert calls - before <= 1 + opening
    assert window.stats.frames == len(events)


@pytest.mark.parametrize("cause", ["gap", "backwards", "size", "reset"])
def test_window_restarts(cause):
    window = FrameWindow(0.025, 25, history=1, gap_threshold=0.3)
    first = [k * DT for k in range(10)]
    assert feed(window, first) == []
    start = first[-1]
    size = SIZE
    if cause == "gap":
        start += 400_000_000
    elif cause == "backwards":
        start -= (LATE_FRAMES + 1) * DT  # further back than reordering goes: the stream started over
    elif cause == "size":
        start += DT
        size = (64, 64)
    else:
        window.reset()
        start += DT
    second = [start + k * DT for k in range(25)]
    (out,) = feed(window, second, size)
    assert chosen(out) == second  # the new episode starts at its own first frame
    assert out.episode == window.episodes == 2  # the first, cut short, gave no estimate but counts
    expected = {"gap": "gap", "backwards": "backwards", "size": "size"}.get(cause)
    if expected:
        assert window.stats.restarts[expected] == 1


def test_gap_below_threshold_does_not_restart_and_leaves_holes():
    window = FrameWindow(0.025, 25, history=1, gap_threshold=0.3, slot_tolerance=0.5)
    stamps = [k * DT for k in range(25) if not 5 <= k < 12]  # 0.2 s hole
    (out,) = feed(window, stamps)
    assert out.frames_used == 18 and not out.valid[5:12].any()
    assert "gap" not in window.stats.restarts


def test_duplicate_stamp_is_ignored():
    window = FrameWindow(0.025, 25, history=1)
    feed(window, [0, DT])
    calls = []
    window.add(DT, frame(), lambda *_: calls.append(1) or np.zeros(1, np.float32))
    assert calls == [] and window.stats.duplicates == 1


@pytest.mark.parametrize("order, late", [
    ([*range(10), 11, 10, *range(12, 25)], 1),  # two neighbours swapped upstream
    ([*range(10), 12, 10, 11, *range(13, 25)], 2),  # one frame overtaking two
    ([*range(15), 11, *range(15, 25)], 1),  # a frame sent again, LATE_FRAMES - 1 intervals late
    ([*range(15), 15 - LATE_FRAMES, *range(15, 25)], 1),  # exactly LATE_FRAMES intervals late: still late
    ([1, 0, *range(2, 25)], 0),  # swapped at the release: the episode starts again from frame 0
    ([2, 3, 1, 0, *range(4, 25)], 0),  # the first frames in any order, within LATE_FRAMES intervals
])
def test_a_frame_out_of_stamp_order_is_dropped_and_the_episode_goes_on(order, late):
    """A late frame once restarted the window: the episode was lost and a new one anchored mid-fall."""
    window = FrameWindow(0.025, 25, history=1)
    (out,) = feed(window, [k * DT for k in order])
    assert window.stats.late == late and window.episodes == 1 and out.episode_start_ns == 0
    assert out.complete and out.valid.all()  # each late frame's slot went to the in-order frame beside it
    assert window.stats.restarts == {"first": 1}


def test_anytime_policy_schedule():
    window = FrameWindow(0.025, 25, history=1, policy="anytime", min_frames=10, every_n=5)
    outs = feed(window, [k * DT for k in range(30)])
    assert [o.frames_used for o in outs] == [10, 15, 20, 25]
    assert [o.complete for o in outs] == [False, False, False, True]


def test_flush_emits_the_final_estimate_when_the_last_slot_was_left_pending():
    window = FrameWindow(0.025, 25, history=1)
    stamps = [k * DT - (2_000_000 if k == 24 else 0) for k in range(25)]  # last frame 2 ms early
    assert feed(window, stamps) == []  # a later frame could still be nearer to slot 24
    (out,) = window.flush()
    assert out.complete and chosen(out) == stamps
    assert window.flush() == []


def test_flush_does_not_repeat_the_last_frame_into_later_slots():
    window = FrameWindow(0.025, 25, history=1, policy="anytime", min_frames=1, every_n=25)
    outs = feed(window, [k * DT for k in range(18)]) + window.flush()
    assert len(outs[-1].valid) == 18 and chosen(outs[-1])[-1] == 17 * DT


def test_restart_flushes_the_previous_episode():
    window = FrameWindow(0.025, 25, history=1)
    stamps = [k * DT - (2_000_000 if k == 24 else 0) for k in range(25)]
    feed(window, stamps)
    outs = feed(window, [stamps[-1] + 10**9])
    assert len(outs) == 1 and outs[0].complete and outs[0].episode_start_ns == 0 and outs[0].episode == 1


def test_a_replayed_stream_is_a_new_episode_even_with_the_same_stamps():
    """A bag played in a loop: its stamps go back to the same start, and the episodes stay apart."""
    window = FrameWindow(0.025, 25, history=1)
    stamps = [k * DT for k in range(25)]
    outs = feed(window, stamps) + feed(window, stamps)
    assert [(o.episode_start_ns, o.episode) for o in outs] == [(0, 1), (0, 2)]
    assert window.stats.restarts["backwards"] == 1


def test_encode_only_for_frames_that_land_in_slots():
    window = FrameWindow(0.025, 25, history=1, slot_tolerance=0.1)
    calls = []
    for s in range(0, 26 * DT, DT // 5):  # 200 fps
        window.add(s, frame(), lambda *_, s=s: calls.append(s) or np.zeros(1, np.float32))
    assert calls == [k * DT for k in range(25)]


def labelled(label):
    """A frame that carries its label in every pixel."""
    return np.full(SIZE, label, np.int64)


def offer(window, stamp, label, seen):
    """Offer a labelled frame; notes (label, labels of the earlier frames) when it is encoded."""
    def encode(current, earlier):
        seen.append((int(current[0, 0]), [int(e[0, 0]) for e in earlier]))
        return np.zeros(1, np.float32)

    window.add(stamp, labelled(label), encode)


def kept_frames(window):
    """Slot -> label of the frame the window still keeps there."""
    return {k: int(s.frame[0, 0]) for k, s in enumerate(window._slots) if s is not None and s.frame is not None}


def test_encode_gets_the_frame_of_the_latest_earlier_filled_slot():
    """History 1, for frame encoders that also see the previous observed frame: none for
    an episode's first frame, slots left empty are skipped, a restart starts again from none."""
    window = FrameWindow(0.025, 25, history=1, slot_tolerance=0.4)
    seen = []
    for k in (0, 1, 2, 5, 6):  # slots 3 and 4 stay empty
        offer(window, k * DT, k, seen)
    offer(window, 6 * DT + 10**9, 46, seen)  # a gap: a new episode
    assert seen == [(0, []), (1, [0]), (2, [1]), (5, [2]), (6, [5]), (46, [])]


def test_encode_gets_the_frames_of_the_latest_history_filled_slots_newest_first():
    """history 3: fewer at the episode's start; a frame filling two slots (35, at 3.5 dt) is encoded
    with the frames before its first slot and is found once per slot by later frames; an empty
    slot (7) is skipped; a restart starts again from none. Only frames a later one can need are kept."""
    window = FrameWindow(0.025, 25, slot_tolerance=0.5, history=3)
    seen = []
    offer(window, 0, 0, seen)
    offer(window, DT, 1, seen)
    offer(window, 2 * DT, 2, seen)
    assert kept_frames(window) == {0: 0, 1: 1, 2: 2}  # not more than 3 settled ones yet
    offer(window, 3 * DT + DT // 2, 35, seen)
    assert kept_frames(window) == {1: 1, 2: 2, 3: 35, 4: 35}  # slot 4 is not settled
    for k in (5, 6, 8):
        offer(window, k * DT, k, seen)
    assert kept_frames(window) == {5: 5, 6: 6, 8: 8}
    assert seen == [(0, []), (1, [0]), (2, [1, 0]), (35, [2, 1, 0]), (5, [35, 35, 2]), (6, [5, 35, 35]),
                    (8, [6, 5, 35])]
    for k in range(9, 25):
        offer(window, k * DT, k, seen)
    assert kept_frames(window) == {}  # complete: no frame can come in any more
    seen.clear()
    offer(window, 30 * DT + 10**9, 100, seen)  # a gap: a new episode
    offer(window, 31 * DT + 10**9, 101, seen)
    assert seen == [(100, []), (101, [100])]


def test_history_0_passes_no_earlier_frames_and_keeps_only_unsettled_ones():
    window = FrameWindow(0.025, 25, history=0)
    seen = []
    for k in range(5):
        offer(window, k * DT, k, seen)
    assert seen == [(k, []) for k in range(5)]
    assert kept_frames(window) == {5: 4}  # frame 4 may still be the nearest to slot 5


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(1_000_000, 60_000_000), min_size=1, max_size=40),
       st.sampled_from([0.4, 0.5, 1.0]), st.integers(0, 4))
def test_earlier_frames_are_those_of_the_final_slots(steps, tolerance, history):
    """Jittery stamps: each frame that ends up in the window was encoded with the frames of the
    `history` latest filled slots before its first slot, as the window finally holds them; the
    window never keeps more settled frames than `history`."""
    window = FrameWindow(0.025, 25, slot_tolerance=tolerance, history=history, policy="anytime", min_frames=1)
    stamps = [int(s) for s in np.cumsum(steps)]
    seen = []
    outputs = []
    for stamp in stamps:
        seen_before = len(seen)
        outputs += window.add(stamp, labelled(stamp), lambda current, earlier: seen.append(
            (int(current[0, 0]), [int(e[0, 0]) for e in earlier])) or np.array([float(current[0, 0])]))
        settled_frames = [k for k in kept_frames(window) if k < window._settled]
        assert len(settled_frames) <= (0 if window._settled == 25 else history)
        assert len(seen) - seen_before <= 1
    outputs += window.flush()
    slots = chosen(outputs[-1])
    for label, earlier in seen:
        if label in slots:  # not displaced from all its slots by nearer later frames
            first = slots.index(label)
            assert earlier == [s for s in reversed(slots[:first]) if s is not None][:history]


def test_the_window_keeps_only_frames_a_later_frame_may_need():
    window = FrameWindow(0.025, 25, history=1)
    for k in range(10):
        window.add(k * DT, frame(), lambda *_: np.zeros(1, np.float32))
    kept = [k for k, slot in enumerate(window._slots) if slot is not None and slot.frame is not None]
    # Slot 9 is the latest settled one; slot 10 is not settled yet and holds frame 9 too (tolerance 1 dt).
    assert kept == [9, 10]
    for k in range(10, 25):
        window.add(k * DT, frame(), lambda *_: np.zeros(1, np.float32))
    assert all(slot.frame is None for slot in window._slots)  # complete: no frame can come in any more


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="policy"):
        FrameWindow(0.025, 25, history=1, policy="sometimes")
    with pytest.raises(ValueError, match="gap_threshold"):
        FrameWindow(0.025, 25, history=1, gap_threshold=0.01)
    with pytest.raises(ValueError, match="history is a number of earlier frames >= 0"):
        FrameWindow(0.025, 25, history=-1)
    for interval in (float("inf"), float("nan"), 0.0):
        with pytest.raises(ValueError, match="finite frame_interval > 0"):
            FrameWindow(interval, 25, history=1)


def test_clip_output_restarts_on_a_size_change_as_a_stream_does():
    """Frame 5 of another size: the clip's output is that of the frames after it (the last restart)."""
    stamps = [k * DT for k in range(25)]
    masks = [frame((64, 64) if k == 5 else SIZE) for k in range(25)]
    out = clip_output(stamps, masks, lambda mask, _earlier: np.array([float(mask.shape[0])]), 0.025, 25,
                      history=1)
    assert out.episode_start_ns == out.oldest_stamp_ns == 6 * DT and len(out.valid) == 19 and out.valid.all()
    assert not out.complete and (out.features == 128.0).all()


def test_clip_stamps():
    assert clip_stamps([0, 0, 0], 0.025) == [0, DT, 2 * DT]
    assert clip_stamps([5, 40, 90], 0.025) == [5, 40, 90]
    with pytest.raises(ValueError, match="increasing"):
        clip_stamps([5, 4, 90], 0.025)


CLOCK = 1_700_000_000 * 10**9  # a camera's clock stamp


def marked(k: int, size=SIZE) -> np.ndarray:
    """Frame k's mask, which by_mark encodes as k."""
    return np.full(size, k, np.uint8)


def by_mark(mask, _earlier):
    return np.array([float(mask[0, 0])])


def test_clip_output_of_a_long_clip_converts_and_uses_its_first_slots_frames_only():
    """A 2 s clip whose object leaves the view after 1 s: frames past the last slot (0.6 s and its tolerance after
    the first) are neither converted nor encoded, and the output is that of the clip's first 0.6 s, complete, as the
    ~/estimate service gives. The library took masks only, which array_to_mask refused for the frames without an
    object, so a library user had to cut the clip to its first 0.6 s."""
    converted = []

    def convert(k):
        converted.append(k)
        if k >= 40:
            raise ValueError("no object pixel")
        return marked(k)

    stamps = [CLOCK + k * DT for k in range(80)]
    out = clip_output(stamps, list(range(80)), by_mark, 0.025, 25, history=1, convert=convert)
    assert converted == list(range(26))  # frame 25 (0.625 s) still lies within the last slot's reach
    assert out.complete and chosen(out) == list(range(25))
    assert (out.oldest_stamp_ns, out.newest_stamp_ns, out.oldest_frame, out.newest_frame) == (
        CLOCK, CLOCK + 24 * DT, 0, 24)
    first = clip_output(stamps[:25], [marked(k) for k in range(25)], by_mark, 0.025, 25, history=1)
    np.testing.assert_array_equal(out.features, first.features)
    assert (first.complete, first.newest_stamp_ns) == (True, out.newest_stamp_ns)
    unread = clip_output(stamps, [marked(k) if k < 40 else None for k in range(80)], by_mark, 0.025, 25, history=1)
    np.testing.assert_array_equal(unread.features, out.features)  # masks past the last slot are not read either


def test_clip_output_of_a_first_frame_stamped_0_and_the_others_with_the_clock():
    """The service's partial estimate from frame 0 (the others are days later: past the last slot). The library
    refused the clip with "gap_threshold must be a number of seconds up to 1e+06", a parameter never given."""
    stamps = [0] + [CLOCK + k * DT for k in range(1, 25)]
    out = clip_output(stamps, [marked(k) for k in range(25)], by_mark, 0.025, 25, history=1)
    assert out.complete and chosen(out) == [0, 0] + [None] * 23  # frame 0 also fills slot 1, within the tolerance
    assert (out.oldest_stamp_ns, out.newest_stamp_ns, out.episode_start_ns, out.newest_frame) == (0, 0, 0, 0)


@pytest.mark.parametrize("stamp", [0, CLOCK])
def test_clip_output_of_equal_stamps_gives_the_frames_own_stamp(stamp):
    """Frames all stamped alike lie on the model's interval for the slots only: the output's stamps are the frames'
    own, as the service's estimate carries them (the library gave the slot times, up to 0.6 s after every frame)."""
    for stamps in ([stamp] * 30, np.full(30, stamp, np.uint64)):
        out = clip_output(stamps, [marked(k) for k in range(30)], by_mark, 0.025, 25, history=1)
        assert out.complete and chosen(out) == list(range(25))
        assert (out.oldest_stamp_ns, out.newest_stamp_ns, out.episode_start_ns) == (stamp, stamp, stamp)
        assert (out.oldest_frame, out.newest_frame) == (0, 24)


@pytest.mark.parametrize("stamps, masks, error, message", [
    ([], [], ValueError, r"^empty clip: send at least one frame$"),
    ([0, DT], [frame()], ValueError, r"^2 stamps for 1 frames: give one stamp per frame$"),
    ([0, 25e6], [frame(), frame()], TypeError, r"^frame 1: a stamp is a whole number of nanoseconds, got float "
                                               r"25000000.0; from seconds: round\(t \* 1e9\)$"),
    ([0, DT, DT], [frame()] * 3, ValueError, r"^frame 2: stamp 0.025000000 s is not after frame 1's \(0.025000000 "
                                             r"s\); clip stamps must be strictly increasing"),
])
def test_clip_output_refuses_a_clip_it_cannot_use_saying_why(stamps, masks, error, message):
    """An empty clip failed with an IndexError, as many stamps as masks went unnoticed (the extra ones were
    dropped), and a float stamp's error did not name the frame."""
    with pytest.raises(error, match=message):
        clip_output(stamps, masks, by_mark, 0.025, 25, history=1)


def test_clip_output_restarts_on_a_size_change_among_the_frames_it_uses_only():
    """A size change within the slots' reach restarts the window, whose slots then reach 0.6 s past that frame; one
    past the last slot is not used (nor converted), as no frame there is: the output is the first episode's."""
    stamps = [CLOCK + k * DT for k in range(60)]
    for change, (start, episode) in ((20, (20, 2)), (30, (0, 1))):
        converted = []

        def convert(k, change=change):
            converted.append(k)
            return marked(k, (64, 64) if k >= change else SIZE)

        out = clip_output(stamps, list(range(60)), by_mark, 0.025, 25, history=1, convert=convert)
        assert out.complete and chosen(out) == list(range(start, start + 25)), change
        assert (out.episode, out.episode_start_ns, out.oldest_frame, out.newest_frame) == (
            episode, stamps[start], start, start + 24)
        assert converted == list(range(start + 26))


def test_clip_output_converts_every_used_frame_before_encoding_and_names_the_one_refused():
    encoded = []

    def convert(k):
        if k == 10:
            raise ValueError("no object pixel in this mono8 mask")
        return marked(k)

    with pytest.raises(ValueError, match=r"^frame 10: no object pixel in this mono8 mask$"):
        clip_output([k * DT for k in range(25)], list(range(25)), lambda *args: encoded.append(1) or by_mark(*args),
                    0.025, 25, history=1, convert=convert)
    assert encoded == []


def test_min_frames_matters_to_the_anytime_policy_only():
    # A model with fewer frame slots than the anytime default still gets an episode window.
    assert FrameWindow(0.025, 12, history=0).min_frames == 12
    with pytest.raises(ValueError, match="min_frames"):
        FrameWindow(0.025, 12, history=0, policy="anytime")
    assert FrameWindow(0.025, 12, history=0, policy="anytime", min_frames=12).min_frames == 12


def test_an_episode_that_ends_without_an_estimate_is_counted():
    window = FrameWindow(0.025, 25, history=1)
    feed(window, [k * DT for k in range(1, 25)])  # frame 0 lost: 24 slots
    assert window.stats.without_estimate == 0  # it could still go on
    (out,) = feed(window, [10**9 + k * DT for k in range(25)])
    assert window.stats.without_estimate == 1 and out.episode == 2
    feed(window, [3 * 10**9])  # the second had its estimate
    assert window.stats.without_estimate == 1


def test_a_frame_further_back_than_late_frames_starts_over():
    window = FrameWindow(0.025, 25, history=1)
    feed(window, [k * DT for k in range(15)])
    feed(window, [(14 - LATE_FRAMES - 1) * DT])
    assert window.stats.late == 0 and window.stats.restarts["backwards"] == 1


def test_a_straggler_of_the_episode_before_is_late_not_a_restart():
    """A frame of the previous episode arriving after the next one's first frame once restarted the
    window twice (backwards, then by gap) and cost the new episode."""
    window = FrameWindow(0.025, 25, history=1)
    feed(window, [k * DT for k in range(20)])
    second = [10**9 + k * DT for k in range(25)]
    (out,) = feed(window, second[:1] + [19 * DT - DT] + second[1:])
    assert window.stats.late == 1 and window.episodes == 2 and chosen(out) == second
    assert window.stats.restarts == {"first": 1, "gap": 1}


def test_episodes_without_estimate_under_the_anytime_policy_and_their_slots():
    window = FrameWindow(0.025, 25, history=1, policy="anytime", min_frames=15)
    feed(window, [k * DT for k in range(10)])
    feed(window, [10**9])
    assert window.stats.without_estimate == 1 and window.stats.last_without_estimate_slots == 10


# --- An independent model of the documented rules (README "Episodes"/"Output", docs/estimator.md "Frames,
# slots and episodes"), compared with FrameWindow on random streams.

SETTLE_EPS = 1_000  # ns: a stamp this close before a slot time counts as at it (float stamps)


class DocumentedWindow:
    """Outputs are (slot stamps or None, complete, episode, episode start)."""

    def __init__(self, dt, count, gap, tolerance, policy, min_frames, every_n):
        self.dt, self.count, self.gap, self.tol = dt, count, gap, tolerance
        self.reach = min(gap, LATE_FRAMES * dt)  # "4 frame intervals (0.1 s, or gap_threshold if shorter)"
        self.policy, self.every_n = policy, every_n
        self.min_frames = min_frames if policy == "anytime" else count
        self.late = self.duplicates = self.without_estimate = 0
        self.restarts = {}
        self.ep = None  # the current episode
        self.previous_last = None  # the last stamp of the episode before (None after a reset)

    def _start(self, stamp, size, reason, frames=()):
        if reason:
            self.restarts[reason] = self.restarts.get(reason, 0) + 1
        self.ep = dict(t0=stamp, size=size, last=stamp, frames=[], slots=[], emitted=0, done=False)
        return [out for s in (stamp, *frames) for out in self._accept(s)]

    def _settle(self, upto):  # slots settle in order; each takes the nearest frame received so far
        ep = self.ep
        for k in range(len(ep["slots"]), min(upto, self.count)):
            t = ep["t0"] + k * self.dt
            near = [s for s in ep["frames"] if abs(s - t) <= self.tol]
            ep["slots"].append(min(near, key=lambda s: (abs(s - t), s)) if near else None)  # ties: earlier

    def _accept(self, stamp):
        ep = self.ep
        ep["last"] = stamp
        if ep["done"]:  # after its last slot the episode ignores frames
            return []
        ep["frames"].append(stamp)
        self._settle((stamp - ep["t0"] + SETTLE_EPS) // self.dt + 1)  # slot k: once a frame at t0 + k dt came
        return self._due(final=False)

    def _due(self, final):
        ep, n = self.ep, len(self.ep["slots"])
        if n < self.min_frames or n <= ep["emitted"]:
            return []
        if n < self.count and (self.policy == "episode" or not (
                final or ep["emitted"] == 0 or n - ep["emitted"] >= self.every_n)):
            return []
        ep["emitted"], ep["done"] = n, n == self.count
        return [(tuple(ep["slots"]), n == self.count, sum(self.restarts.values()), ep["t0"])]

    def flush(self):  # the slots up to the one nearest to the last frame (a half: the later) settle
        if self.ep is None or self.ep["done"]:
            return []
        self._settle(math.floor((self.ep["last"] - self.ep["t0"]) / self.dt + 0.5) + 1)
        return self._due(final=True)

    def reset(self):
        self.ep = self.previous_last = None

    def add(self, stamp, size):
        ep = self.ep
        if ep is None:
            return self._start(stamp, size, "first")
        back = ep["last"] - stamp
        reason = ("size" if size != ep["size"] else "backwards" if back > self.reach
                  else "gap" if -back > self.gap else None)
        if reason == "backwards" and self.previous_last is not None and 0 <= self.previous_last - stamp <= self.reach:
            self.late += 1  # a straggler of the episode before
            return []
        if reason:
            outputs = self.flush()  # the episode before ends: what is due goes out
            self.without_estimate += not ep["emitted"]
            self.previous_last = ep["last"]
            return outputs + self._start(stamp, size, reason)
        if back == 0:
            self.duplicates += 1
        elif stamp < ep["t0"] and not ep["done"]:  # its true first frame, overtaken: again from it
            return self._start(stamp, size, None, ep["frames"])
        elif back > 0:  # reordered; after its estimate, a frame before the episode's first is late too
            self.late += 1
        else:
            return self._accept(stamp)
        return []


def random_events(rng, dt, n):
    """("frame", stamp, size), ("reset",), ("flush",): jitter, drops, duplicates, reordering, stamps going
    back by less and more than LATE_FRAMES intervals, gaps around 0.3 s, size changes, huge stamps."""
    base = int(rng.choice([0, 10**9 - 3 * dt, 17 * 10**9 - 1, (2**31 - 1) * 10**9,
                           int(rng.integers(1, 2**31)) * 10**9 + int(rng.integers(0, 10**9))]))
    stamp, size, events = base, (8, 8), []
    for _ in range(n):
        r = rng.random()
        if r < 0.55:  # on time, or jittered by up to a third of the interval
            step = dt + int(rng.integers(-dt // 3, dt // 3 + 1)) * int(rng.random() < 0.4)
        elif r < 0.62:  # between slots, frames lost, sub-microsecond steps
            step = int(rng.choice([dt // 2, dt * 4 // 3, 2 * dt, 2 * dt + dt // 2, 1, 999, 1000, 1001]))
        elif r < 0.67:
            step = 0
        elif r < 0.77:  # reordered: 1..4 intervals back, and just past LATE_FRAMES
            step = -int(rng.integers(1, 5)) * dt + int(rng.choice([0, 0, -1, 1, -dt // 2]))
        elif r < 0.82:  # a stream or bag starting over
            step = -int(rng.choice([5 * dt, 10 * dt, 10**9, stamp - base]))
        elif r < 0.9:  # gaps around the threshold, and long pauses
            step = int(rng.choice([100_000_000, 110_000_000, 290_000_000, 300_000_000, 300_000_001, 310_000_000,
                                   5 * 10**9]))
        elif r < 0.93:
            events.append(("reset",))
            continue
        elif r < 0.96:
            events.append(("flush",))
            continue
        else:
            size, step = ((4, 8) if size == (8, 8) else (8, 8)), dt
        stamp += step
        events.append(("frame", stamp, size))
    return events


def compare_with_documented_rules(seed):
    """None, or the first event at which FrameWindow and DocumentedWindow disagree."""
    rng = np.random.default_rng(seed)
    dt = int(rng.choice([25_000_000, 33_333_333]))
    count = int(rng.choice([25, 25, 25, 6, 3]))
    gap = float(rng.choice([0.3, 0.3, 0.11, 0.06]))
    tolerance = float(rng.choice([1.0, 1.0, 0.5, 0.4, 2.0]))
    if gap * 1e9 <= tolerance * dt:
        tolerance = 1.0
    policy = str(rng.choice(["episode", "anytime"]))
    min_frames, every_n = int(rng.integers(1, count + 1)), int(rng.integers(1, 7))
    window = FrameWindow(dt / 1e9, count, gap_threshold=gap, slot_tolerance=tolerance, policy=policy,
                         every_n=every_n, min_frames=min_frames, history=1)
    documented = DocumentedWindow(window.interval_ns, count, window.gap_ns, window.tolerance_ns, policy, min_frames,
                                  every_n)
    events = random_events(rng, dt, int(rng.integers(1, 120)))
    stamps = [e[1] if e[0] == "frame" else None for e in events]

    def slots(outputs):  # features carry the event index: float stamps would lose nanoseconds
        return [(tuple(stamps[int(f[0])] if v else None for f, v in zip(o.features, o.valid)), o.complete,
                 o.episode, o.episode_start_ns) for o in outputs]

    for i, event in enumerate(events):
        if event[0] == "reset":
            window.reset(), documented.reset()
            got = want = []
        elif event[0] == "flush":
            got, want = slots(window.flush()), documented.flush()
        else:
            got = slots(window.add(event[1], np.zeros(event[2]), lambda _f, _e, i=i: np.array([float(i)])))
            want = documented.add(event[1], event[2])
        stats = (window.stats.late, window.stats.duplicates, window.stats.without_estimate,
                 dict(window.stats.restarts))
        expected = (documented.late, documented.duplicates, documented.without_estimate, documented.restarts)
        if got != want or stats != expected:
            return {"seed": seed, "events": events[:i + 1], "outputs": (got, want), "stats": (stats, expected)}
    return None


def test_the_window_follows_the_documented_rules_on_random_streams():
    failures = [f for f in map(compare_with_documented_rules, range(1000)) if f]
    assert not failures, min(failures, key=lambda f: len(f["events"]))


def test_a_frame_before_a_complete_episode_is_late_not_a_second_estimate():
    """A model of 3 slots completes within LATE_FRAMES intervals: a frame stamped before the episode's
    first one then came after its estimate. It once restarted the episode and sent a second complete
    estimate for it (the episode policy's one estimate per episode)."""
    window = FrameWindow(0.025, 3, history=1)
    (out,) = feed(window, [DT, 2 * DT, 3 * DT])
    assert out.complete and out.episode_start_ns == DT
    assert feed(window, [0]) == [] and window.stats.late == 1 and window.episodes == 1
    assert feed(window, [3 * DT + 10**9 + k * DT for k in range(3)])[0].episode == 2


def test_epoch_float_stamps_fill_every_slot():
    """Stamps from float seconds near 1.7e9 or 2**31 s are off by a few hundred ns either way."""
    for base in (1.7e9, 1.7e9 + 0.9875, 2**31 - 1.3):
        for convert in (int, round):
            for fps, last in ((40, 24), (30, 18)):
                window = FrameWindow(0.025, 25, history=1)
                outs = [(k, o) for k in range(40) for o in feed(window, [convert((base + k / fps) * 1e9)])]
                assert [(k, o.frames_used, o.complete) for k, o in outs] == [(last, 25, True)]


class RecordingModel:
    """What estimate and evaluate need of a model: features are the frame's index, predict records."""

    def __init__(self, frame_count=25):
        self.info = SimpleNamespace(frame_interval=0.025, frame_count=frame_count, previous_frames=1,
                                    input_threshold=lambda threshold=127: threshold)
        self.calls = []

    def encode(self, mask, earlier):
        return np.array([float(mask.flat[0])])

    def predict(self, features, valid):
        self.calls.append(tuple(int(f[0]) if v else None for f, v in zip(features, valid)))
        return SimpleNamespace(material="jelly", probabilities=np.ones(4) / 4, parameters=np.zeros(2),
                               raw_parameters=np.zeros(2), raw_uncertainties=np.zeros(2), uncertainties=np.zeros(2))


def node_window_outputs(model, values, frames):
    """The node's worker: model_window, window.add per frame, the idle flush when the input pauses."""
    window = model_window(values, model.info)
    outputs, previous_log = [], None
    for log_time, stamp, mask in frames:
        if values["idle_flush"] > 0 and previous_log is not None and log_time - previous_log > values["idle_flush"] * 1e9:
            outputs += window.flush()
        previous_log = log_time
        outputs += window.add(stamp, mask, model.encode)
    return outputs + window.flush()


@pytest.mark.filterwarnings("ignore")  # estimate warns about the late and repeated stamps, as it should
def test_estimate_makes_the_node_windows_decisions(monkeypatch):
    """estimate.estimate_bag on random streams (log pauses included) gives the node's window outputs."""
    from ad_estimator import estimate

    rng = np.random.default_rng(7)
    for policy in ("episode", "anytime"):
        values = {name: default for name, (default, _) in PARAMETERS.items()} | {"output_policy": policy}
        for _ in range(40):
            events = [e for e in random_events(rng, DT, 150) if e[0] == "frame"]
            frames, log_time = [], 0
            for i, (_, stamp, size) in enumerate(events):
                log_time += int(rng.choice([DT, DT, 0, 10**9]))
                frames.append((log_time, stamp, np.full(size, i)))
            images = [(log, SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(
                sec=stamp // 10**9, nanosec=stamp % 10**9)), mask=mask)) for log, stamp, mask in frames]
            monkeypatch.setattr(estimate, "mask_frames", lambda *_: iter(images))
            monkeypatch.setattr(estimate, "image_to_mask", lambda image, *_: image.mask)
            model = RecordingModel()
            rows = estimate.estimate_bag(model, "bag", "/mask", values)
            expected = node_window_outputs(RecordingModel(), values, frames)
            assert [(r.output.episode, r.output.episode_start_ns, r.output.complete) for r in rows] == \
                   [(o.episode, o.episode_start_ns, o.complete) for o in expected]
            assert model.calls == [tuple(int(f[0]) if v else None for f, v in zip(o.features, o.valid))
                                   for o in expected]


def test_evaluate_makes_the_node_windows_decisions_for_an_episode_in_stamp_order():
    """evaluate.predict_episode (clip_output) on an episode's frames, jittered, some lost, in stamp order and
    without a gap over gap_threshold: the node's complete estimate (episode policy), or, for the first K
    frames, its anytime window flushed after them. With a gap over gap_threshold inside an episode the node
    restarts its window and evaluate does not (docs/estimator.md, "Replay and evaluate")."""
    from ad_estimator import evaluate

    rng = np.random.default_rng(11)
    instance = SimpleNamespace(episode_id=1, material="jelly", parameter_names=("a", "b"), parameters=[0.0, 0.0])
    for _ in range(100):
        stamps, stamp = [], int(rng.integers(0, 2**31)) * 10**9
        while stamp - (stamps or [stamp])[0] < 0.7e9:
            stamps.append(stamp)
            stamp += int(rng.choice([DT, DT, DT, 2 * DT, 3 * DT])) + int(rng.integers(-DT // 3, DT // 3))
        masks = [np.full(SIZE, i) for i in range(len(stamps))]
        frames = [(s, None) for s in stamps]
        for k, policy in ((len(stamps), "episode"), (int(rng.integers(1, 25)), "anytime")):
            model = RecordingModel()
            evaluate.predict_episode(model, "bag", instance, frames, k, masks=masks)
            values = {name: default for name, (default, _) in PARAMETERS.items()} | {
                "output_policy": policy, "min_frames": 1, "every_n": 25}
            (*_, last) = node_window_outputs(RecordingModel(), values, [(0, s, m) for s, m in zip(stamps[:k], masks)])
            assert model.calls == [tuple(int(f[0]) if v else None for f, v in zip(last.features, last.valid))]
    gap = [k * DT + (400_000_000 if k >= 10 else 0) for k in range(30)]
    model = RecordingModel()
    evaluate.predict_episode(model, "bag", instance, [(s, None) for s in gap], 30,
                             masks=[np.full(SIZE, i) for i in range(30)])
    assert model.calls[0][:10] == tuple(range(10))  # the node's window would have restarted at frame 10


# --------------------------------------------------------------------------- mutation-testing audit


def test_header_stamps_convert_to_nanoseconds_and_back_exactly():
    from ad_estimator.window import ns_to_stamp, stamp_text, stamp_to_ns

    assert stamp_to_ns(1, 999_999_999) == 1_999_999_999
    assert stamp_to_ns(1_700_000_000, 25_000_000) == 1_700_000_000_025_000_000
    for nanosec in (1_000_000_000, 1_500_000_000, -1):  # no time: read as is it shifted the frame by seconds
        with pytest.raises(ValueError, match="not below 1e9"):
            stamp_to_ns(1, nanosec)
    assert ns_to_stamp(1_999_999_999) == (1, 999_999_999)
    assert ns_to_stamp(-1) == (-1, 999_999_999)  # a header's nanosec is never negative
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_025_000_000):
        assert stamp_to_ns(*ns_to_stamp(ns)) == ns
    assert stamp_text(1_000_000_005) == "1.000000005"
    assert stamp_text(2**62 + 1) == "4611686018.427387905"  # exact, unlike a float of seconds


def test_parameter_checks_take_the_ends_of_each_range_and_refuse_past_them():
    from ad_estimator.parameters import check_parameters

    check_parameters({"mask_threshold": 0, "idle_flush": 0.0, "diagnostics_period": 0.01, "queue_size": 1000,
                      "threads": 1, "min_frames": 1, "every_n": 1})
    check_parameters({"mask_threshold": 254})
    for values, message in [({"mask_threshold": 255}, "mask_threshold is a pixel value in 0..254"),  # nothing is > 255
                            ({"mask_threshold": -1}, "mask_threshold"),
                            ({"min_frames": 0}, "min_frames must be positive"),
                            ({"every_n": 0}, "every_n must be positive"),
                            ({"queue_size": 1001}, "queue_size must be at most 1000"),
                            ({"idle_flush": -0.1}, "idle_flush is seconds"),
                            ({"idle_flush": math.nan}, "idle_flush is seconds"),
                            ({"diagnostics_period": 0.009}, "diagnostics_period is seconds")]:
        with pytest.raises(ValueError, match=message):
            check_parameters(values)
