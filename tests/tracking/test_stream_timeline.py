"""``TrackerStream`` when host times jump (class docs, "Times that jump").

The filter applies a late measurement at its latest time, so one glitched timestamp far in the
future used to freeze the stream: every later measurement was applied at that time and the
render, at the real times, showed one pose until the source's clock caught up (never, for a
timestamp in the wrong unit). Same stream configuration as ``test_stream_review`` (default
config, float32, ``fast_start=False``): nothing new to compile.
"""

import jax
import numpy as np
import pytest
from test_stream_review import _finite, _started, meas  # noqa: F401 - the shared fixture

import phjax as pj
from phjax.live._runner import LiveStream
from phjax.tracking.stream import TIME_STEP_BACK


def _same_state(a, b):
    for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _after_outliers(meas, times, resume, stop=16):  # noqa: F811
    """Two streams started on 10 frames; the first is fed frame 10's pose at each of
    ``times``, then both frames ``resume .. stop - 1``."""
    t, p, q = meas
    s, ref = _started(meas, 10), _started(meas, 10)
    for bad in times:
        s.update(bad, p[10], q[10])
    for k in range(resume, stop):
        s.update(t[k], p[k], q[k])
        ref.update(t[k], p[k], q[k])
    return s, ref


def _sampled(s, taus):
    return [np.asarray(x) for x in s.sample(np.asarray(taus))]


@pytest.mark.parametrize("jump", [1e3, 2.0, -2.0, -50.0])
def test_one_outlying_time_is_forgotten(meas, jump):  # noqa: F811
    """A measurement stamped ``jump`` s off (ahead: a glitched timestamp; back: one from a
    stale buffer), the stream's clock otherwise steady, is dropped when the next measurement
    continues the time line: the stream is then exactly the stream that never saw it. (Ahead,
    it froze the stream before: every later measurement was applied at the glitched time.)"""
    t = meas[0]
    s, ref = _after_outliers(meas, [t[10] + jump], resume=11, stop=20)
    assert s.time_glitches == 1 and s.time_restarts == 0
    _same_state(s, ref)
    taus = t[19] + np.array([0.0, 0.01, 0.02])
    assert _finite(s, taus)
    for got, want in zip(_sampled(s, taus), _sampled(ref, taus)):
        np.testing.assert_array_equal(got, want)


def test_a_glitched_first_time_does_not_become_the_origin(meas):  # noqa: F811
    """A stream without a given origin takes the first update's time: an outlying first time
    (1e6 s, say a timestamp in microseconds) would put every later time 1e6 s before the
    origin, where float32 resolves only 0.06 s. Forgotten, the next time is the origin."""
    t, p, q = meas
    s = pj.TrackerStream(fast_start=False)
    ref = pj.TrackerStream(fast_start=False)
    s.update(1e6, p[0], q[0])
    for k in range(12):
        s.update(100.0 + t[k], p[k], q[k])
        ref.update(100.0 + t[k], p[k], q[k])
    assert s.time_glitches == 1 and s.origin == ref.origin == 100.0
    _same_state(s, ref)


def test_a_clock_that_goes_back_for_good_restarts_the_filter(meas):  # noqa: F811
    """A source whose clock starts again (a restarted camera driver, a file replayed in a
    loop): the stream used to stand still at the old time line's last pose. Now the filter
    starts again from the first measurement of the new time line, and the stream follows it."""
    t, p, q = meas
    s = _started(meas, 30)
    offset = np.array([0.2, 0.0, 0.0], np.float32)  # where the restarted source is
    for k in range(12):
        s.update(t[k], p[k] + offset, q[k])
    assert s.time_restarts == 1 and s.time_glitches == 0
    ref = _started((t, p + offset, q), 12)  # a stream that only saw the new time line
    _same_state(s, ref)
    pos = _sampled(s, [t[11]])[0][0]
    assert np.linalg.norm(pos - (p[11] + offset)) < 0.02


def test_late_measurements_within_the_tolerance_are_applied_as_before(meas):  # noqa: F811
    """Late measurements (a capture thread's reordering) are applied at the latest time, as
    the filter always did: not a jump of the time line."""
    t, p, q = meas
    s, skipped = _started(meas, 10), _started(meas, 10)
    for stream in (s, skipped):
        stream.update(t[10], p[10], q[10])
    s.update(t[10] - 0.9 * TIME_STEP_BACK, p[11], q[11])
    for stream in (s, skipped):
        stream.update(t[12], p[12], q[12])
    assert s.time_glitches == s.time_restarts == 0
    assert _finite(s, t[12] + 0.01)
    # the late frame was used: the stream differs from one that never saw it
    assert not np.array_equal(np.asarray(s.state.filter.x), np.asarray(skipped.state.filter.x))


def test_live_stream_late_updates_keep_the_time_line_too(meas):  # noqa: F811
    t, p, q = meas
    s = LiveStream(fast_start=False, dtype=np.float32)
    for k in range(10):
        s.update_late(t[k], t[k] + 0.02, p[k], q[k])
    s.update_late(t[10] + 500.0, t[10] + 0.02, p[10], q[10])
    for k in range(11, 14):
        s.update_late(t[k], t[k] + 0.02, p[k], q[k])
    assert s.time_glitches == 1
    assert _finite(s, t[13] + 0.03)
    pos = _sampled(s, [t[13] + 0.02])[0][0]
    assert np.linalg.norm(pos - p[13]) < 0.02


def test_a_frame_just_over_the_tolerance_late_is_dropped_not_the_good_one(meas):  # noqa: F811
    """At a steady rate a frame 0.52 s late fits the older time line: it made the stream
    forget the good frame before it (found in review). A late frame is now held and dropped
    when the next one continues the time line; the good frame stays."""
    t = meas[0]
    s, ref = _after_outliers(meas, [t[9] - (TIME_STEP_BACK + 0.02)], resume=10)
    assert s.time_glitches == 1 and s.time_restarts == 0
    _same_state(s, ref)


def test_two_bad_times_in_a_row_are_both_dropped(meas):  # noqa: F811
    """One frame 1000 s ahead, then one 100 s behind, then the good frames: the filter
    restarted from the stale one (and the outlier ahead went uncounted)."""
    t = meas[0]
    s, ref = _after_outliers(meas, [t[10] + 1000.0, t[10] - 100.0], resume=11)
    assert s.time_glitches == 2 and s.time_restarts == 0
    _same_state(s, ref)


def test_a_held_measurement_is_checked_and_copied(meas):  # noqa: F811
    """A measurement held by the time line is applied later: its shape is checked when it
    comes (it raised on the next call, after that call's frame was lost) and it is copied (a
    camera loop that reuses its buffer overwrote it)."""
    t, p, q = meas
    s = _started(meas, 30)
    with pytest.raises(ValueError, match=r"position must have shape \(3,\), got \(2,\)"):
        s.update(t[0], p[0][:2], q[0])
    buf_p, buf_q = p[0].copy(), q[0].copy()
    s.update(t[0], buf_p, buf_q)  # held: the clock went back
    buf_p[:], buf_q[:] = 9.0, 0.0  # the camera loop reuses its buffers
    s.update(t[1], p[1], q[1])  # the new time line: the filter restarts from the held frame
    assert s.time_restarts == 1
    ref = _started(meas, 2)
    _same_state(s, ref)


@pytest.mark.parametrize("jump", [-50.0, 1e3])
def test_a_dropped_measurement_does_not_count_for_a_one_part_source(meas, jump):  # noqa: F811
    """An orientation-only source (a 3-DoF tracker) gets its position fixed at the origin
    after ``PARTIAL_FRAMES`` frames. One frame with a glitched time that also carries a
    position (held, then dropped by the time line; or forgotten, far ahead) used to count as
    the position being measured before the time line decided: the placeholder was then never
    used, and the stream never started (NaN forever). Now only applied measurements count:
    the stream is exactly the one that never saw the glitch."""
    t, p, q = meas
    nan = np.full(3, np.nan, np.float32)
    s = pj.TrackerStream(fast_start=False)
    ref = pj.TrackerStream(fast_start=False)
    for k in range(16):
        if k == 3:
            s.update(t[2] + jump, p[3], q[3])  # a whole pose, at a glitched time
        s.update(t[k], nan, q[k])
        ref.update(t[k], nan, q[k])
    assert s.time_glitches == 1
    assert s.measured_parts == ref.measured_parts == (False, True)
    _same_state(s, ref)
    pos, quat = _sampled(s, [t[15]])
    np.testing.assert_array_equal(pos, np.zeros((1, 3), np.float32))  # the origin
    assert np.isfinite(quat).all()


def test_a_glitched_first_measurement_or_a_restart_counts_the_parts_again(meas):  # noqa: F811
    """Found in review: (1) a whole pose at a glitched *first* time, then an orientation-only
    source: the glitch is dropped when the new time line restarts the filter, but its position
    still counted as measured, so the position placeholder was never used (NaN forever). (2) A
    6-DoF source whose clock restarts as an orientation-only one: likewise. A restart now
    counts the measured parts again, so both streams equal one that saw only the new line."""
    t, p, q = meas
    nan = np.full(3, np.nan, np.float32)
    first = pj.TrackerStream(fast_start=False)
    first.update(1e3, p[0], q[0])  # a glitched first time, with a whole pose
    restarted = _started(meas, 30)  # a 6-DoF source ...
    ref = pj.TrackerStream(fast_start=False)
    for k in range(14):  # ... whose clock starts again, orientation only
        for s in (first, restarted, ref):
            s.update(t[k], nan, q[k])
    assert (first.time_glitches, first.time_restarts) == (1, 0)
    assert restarted.time_restarts == 1
    for s in (first, restarted):
        assert s.measured_parts == ref.measured_parts == (False, True)
        _same_state(s, ref)
        pos, quat = _sampled(s, [t[13]])
        np.testing.assert_array_equal(pos, np.zeros((1, 3), np.float32))
        assert np.isfinite(quat).all()
