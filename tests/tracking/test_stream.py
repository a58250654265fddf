"""The real-time driver ``TrackerStream``: same stream as the pure functions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj
from phjax.motion import simulate
from phjax.tracking import tracker


@pytest.fixture(scope="module")
def meas():
    t, p, q = simulate.synthetic_head_motion(duration=4.0, seed=2)
    mt, mp, mq = (np.array(x) for x in simulate.simulate_measurements(5, t, p, q))
    mp[7:12] = np.nan  # a gap of several frames
    mq[9] = np.nan
    return mt - mt[0], mp, mq


def _comparable(state, exact: bool):
    """The state leaves to compare: all of them in float64; in float32 the filter only
    (rounding differences of the two compiled programs move the free angles of nearly
    straight PH pieces; the samples below are compared instead)."""
    return jax.tree.leaves(state) if exact else jax.tree.leaves(state.filter)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("model", ["cv", "ca"])
def test_stream_equals_pure_functions(meas, dtype, model):
    """Every update and the samples between frames equal tracker_update / tracker_sample.

    The stream runs the same code (``_update``, ``RenderSegment.evaluate``) on the leaves of
    its config and state: this checks the wrapper (dtypes, no recompilation), not the tracker;
    the maths is
    tested independently in tests/tracking/test_tracker.py (finite-difference continuity of the
    world-frame velocities, segment starts, accuracy against ground truth and the Kalman
    baseline) and tests/tracking/test_kalman.py (filterpy)."""
    mt, mp, mq = meas
    cfg = pj.TrackerConfig(kalman=pj.KalmanConfig(model=model), imm=None, horizon=0.035)
    s = pj.TrackerStream(cfg, dtype=dtype)
    ref = pj.tracker_init(cfg, 0.0, dtype)
    tol = 1e-12 if dtype == jnp.float64 else 2e-5
    fn = tracker.tracker_update
    p_nan, _ = s.sample(0.01)
    assert np.all(np.isnan(np.asarray(p_nan)))  # nothing measured yet
    for k in range(40):
        s.update(float(mt[k]), mp[k], mq[k])
        ref = pj.tracker_update(cfg, ref, mt[k], mp[k], mq[k])
        if k == 0:  # compiled for the argument types of the loop
            n0 = fn._cache_size(), s._update._cache_size()
        for a, b in zip(jax.tree.leaves(s.state), jax.tree.leaves(ref)):
            assert a.dtype == b.dtype and a.shape == b.shape
        exact = dtype == jnp.float64
        for a, b in zip(_comparable(s.state, exact), _comparable(ref, exact)):
            np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                       rtol=tol, atol=tol)
        taus = mt[k] + np.array([0.0, 0.004, 0.013, 0.031, 0.2])
        P, Q = s.sample(jnp.asarray(taus, dtype))
        Pr, Qr = pj.tracker_sample(cfg, ref, jnp.asarray(taus, dtype))
        assert P.dtype == dtype and P.shape == (5, 3) and Q.shape == (5, 4)
        np.testing.assert_allclose(np.asarray(P), np.asarray(Pr), rtol=tol, atol=tol)
        np.testing.assert_allclose(np.asarray(Q), np.asarray(Qr), rtol=tol, atol=tol)
        assert np.all(np.isfinite(np.asarray(P))) and np.all(np.isfinite(np.asarray(Q)))
    # static shapes: no compilation after the first frame (Python-float times, NumPy measurements)
    assert (fn._cache_size(), s._update._cache_size()) == n0


def test_fast_start_stream_equals_the_optimised_one(meas, monkeypatch):
    """``fast_start`` (the default): the first update runs a program compiled at -O0 and the
    optimised one takes over when its background compilation ends; the stream's samples agree
    with an optimised-from-the-start stream (float32 rounding) before, across and after the
    switch. (The suite compiles everything at -O0, where tiering is off: forced on here.)"""
    from phjax import _jit
    from phjax.tracking import stream as stream_mod

    monkeypatch.setattr(_jit, "_tiering_pays", lambda: True)
    stream_mod._tiered_on_leaves.cache_clear()  # not a program made with tiering off
    try:
        mt, mp, mq = meas
        cfg = pj.TrackerConfig(imm=None)
        a = pj.TrackerStream(cfg, dtype=jnp.float32)
        b = pj.TrackerStream(cfg, dtype=jnp.float32, fast_start=False)
        assert b.wait_compiled()
        switched = None
        for k in range(40):
            a.update(float(mt[k]), mp[k], mq[k])
            b.update(float(mt[k]), mp[k], mq[k])
            if k == 0:
                assert a._update._program is not a._update._jitted  # the fast program
            if switched is None and a._update.optimized:
                switched = k
            if k == 20:
                assert a.wait_compiled(120)
            taus = jnp.asarray(mt[k] + np.array([0.0, 0.004, 0.013, 0.031]), jnp.float32)
            for x, y in zip(a.sample(taus), b.sample(taus)):
                np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2e-5, atol=2e-5)
        assert a._update.error is None and switched is not None
    finally:
        stream_mod._tiered_on_leaves.cache_clear()


def test_stream_config_arrays_and_state_round_trip(meas):
    """The stream's config leaves are arrays of the state's dtype (converted once), booleans
    stay booleans, and the state setter / getter round-trip exactly."""
    _, mp, mq = meas
    cfg = pj.TrackerConfig()
    s = pj.TrackerStream(cfg, dtype=jnp.float64)
    assert s.dtype == jnp.float64
    assert all(isinstance(x, jax.Array) and x.dtype == jnp.float64 for x in s._config_leaves)
    assert not bool(s.state.started) and s.state.started.dtype == jnp.bool_
    assert s.state.filter.initialized.dtype == jnp.bool_
    s.update(0.0, mp[0], mq[0])
    st = s.state
    assert bool(st.started) and bool(st.filter.initialized)
    s2 = pj.TrackerStream(cfg, dtype=jnp.float64)
    s2.state = st
    for a, b in zip(jax.tree.leaves(s2.state), jax.tree.leaves(st)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    taus = jnp.asarray([0.0, 0.01, 0.5])
    for a, b in zip(s2.sample(taus), s.sample(taus)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("dtype,rotation_horizon", [(jnp.float64, None), (jnp.float32, None),
                                                    (jnp.float64, 0.05), (jnp.float32, 0.012)])
def test_stream_sample_is_the_curve_objects_evaluation(meas, dtype, rotation_horizon):
    """Inside the segment a sample is the ``PHQuintic`` / ``QuaternionHermite`` piece that
    covers the time, evaluated at ``(t - start) / duration`` of its channel (the second piece
    from its start on); past the end it coasts from the end pose: position
    ``p_end + v_end dt`` and orientation ``exp(w_end dt / 2) q_end`` (rotation vector
    ``w_end dt``, checked with SciPy) during ``coast_time``. With a ``rotation_horizon`` of its
    own the orientation's pieces last ``0.4`` and ``0.6`` of it, the position's of ``horizon``."""
    from scipy.spatial.transform import Rotation

    mt, mp, mq = meas
    config = pj.TrackerConfig(rotation_horizon=rotation_horizon)
    h = np.array([config.horizon, rotation_horizon or config.horizon])
    s = pj.TrackerStream(config, dtype=dtype)
    tol = 1e-12 if dtype == jnp.float64 else 2e-6
    for k in range(12):
        s.update(float(mt[k]), mp[k], mq[k])
        st = s.state
        if not bool(st.started):
            continue
        t0, dur = float(st.t0), np.asarray(st.duration, np.float64)
        np.testing.assert_allclose(dur, np.stack([0.4 * h, 0.6 * h], axis=1), rtol=10 * tol)
        starts = np.asarray(st.segment.start, np.float64)  # (channel, piece)
        np.testing.assert_allclose(starts[:, 0], t0, rtol=tol)
        for i in range(2):
            for ch in range(2):
                for frac in (0.0, 0.3, 0.999):
                    tau = starts[ch, i] + frac * dur[ch, i]
                    u = (jnp.asarray(tau, dtype) - st.segment.start[ch, i]) / st.duration[ch, i]
                    p, q = s.sample(jnp.asarray(tau, dtype))
                    if ch == 0:
                        piece = jax.tree.map(lambda x, i=i: x[i], st.curve)
                        np.testing.assert_allclose(np.asarray(p), np.asarray(piece.position(u)),
                                                   rtol=tol, atol=tol)
                    else:
                        rot = jax.tree.map(lambda x, i=i: x[i], st.rotation)
                        np.testing.assert_allclose(np.asarray(q), np.asarray(rot.rotation(u)),
                                                   rtol=tol, atol=tol)
        seg = st.segment
        dt = 0.5 * float(seg.coast_time)
        end = starts[:, 1] + dur[:, 1]
        p = np.asarray(s.sample(jnp.asarray(end[0] + dt, dtype))[0], np.float64)
        np.testing.assert_allclose(p, np.asarray(seg.p_end) + dt * np.asarray(seg.v_end),
                                   atol=10 * tol)
        q = np.asarray(s.sample(jnp.asarray(end[1] + dt, dtype))[1], np.float64)
        q_end = np.asarray(seg.q_end, np.float64)
        r = Rotation.from_rotvec(dt * np.asarray(seg.w_end, np.float64)) * Rotation.from_quat(
            q_end[[1, 2, 3, 0]])
        expected = r.as_quat()[[3, 0, 1, 2]]
        expected *= np.sign(expected @ q)
        np.testing.assert_allclose(q, expected, atol=10 * tol + (1e-6 if dtype == jnp.float32 else 0))


def test_stream_is_the_track_scan(meas):
    """The stream sampled at render times equals ``phjax.track`` (causal: the last update at or
    before each render time). Same maths on both sides (see
    ``test_stream_equals_pure_functions`` for where the maths itself is tested)."""
    mt, mp, mq = meas
    r = np.arange(0.0, mt[-1], 1 / 120)
    P_ref, Q_ref = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    s = pj.TrackerStream(dtype=jnp.float64)
    P, Q = np.zeros_like(P_ref), np.zeros_like(Q_ref)
    k = 0
    for j, tau in enumerate(r):
        while k < len(mt) and mt[k] <= tau:
            s.update(mt[k], mp[k], mq[k])
            k += 1
        p, q = s.sample(tau)
        P[j], Q[j] = np.asarray(p), np.asarray(q)
    np.testing.assert_allclose(P, P_ref, atol=1e-12)
    np.testing.assert_allclose(Q, Q_ref, atol=1e-12)


@pytest.mark.parametrize("bad", [dict(position=np.zeros(4)), dict(quaternion=np.ones(3)),
                                 dict(t=np.zeros(2)), dict(position=0.5)])
def test_bad_shapes_raise_clear_errors(bad):
    args = dict(t=0.0, position=np.zeros(3), quaternion=np.array([1.0, 0, 0, 0])) | bad
    s = pj.TrackerStream(dtype=jnp.float64)
    with pytest.raises(ValueError, match="must have shape"):
        s.update(args["t"], args["position"], args["quaternion"])
    with pytest.raises(ValueError, match="must have shape"):
        pj.tracker_update(pj.TrackerConfig(), pj.tracker_init(), args["t"], args["position"],
                          args["quaternion"])


def test_one_part_sources_start_after_partial_frames_with_the_other_part_fixed():
    """An orientation-only (3-DoF) source rendered NaN forever (the filter starts from a whole
    pose); now after ``PARTIAL_FRAMES`` such frames the position is the origin and the
    orientation is tracked, as the stream of the same orientations with zero positions does
    from then on. Likewise position-only sources at the identity. A 6-DoF source whose first
    frames lost one part is not pinned: it equals the stream that never saw those frames."""
    from phjax.tracking.stream import PARTIAL_FRAMES

    # every frame measured (no dropouts), so that the frame that starts each stream is known
    t, p, q = (np.asarray(x, np.float32)[::4] for x in simulate.synthetic_head_motion(
        duration=1.0, rate=120.0, seed=4))
    k = PARTIAL_FRAMES
    r = t[k + 5] + 0.01
    nan_p, nan_q = np.full(3, np.nan, np.float32), np.full(4, np.nan, np.float32)
    for part in ("orientation", "position"):
        s, ref = pj.TrackerStream(t=0.0), pj.TrackerStream(t=0.0)  # one time origin
        for i in range(k + 6):
            if part == "orientation":
                s.update(t[i], nan_p, q[i])
                if i >= k - 1:
                    ref.update(t[i], np.zeros(3, np.float32), q[i])
            else:
                s.update(t[i], p[i], nan_q)
                if i >= k - 1:
                    ref.update(t[i], p[i], np.array([1, 0, 0, 0], np.float32))
            if i == k - 2:  # one frame short: still waiting
                assert np.isnan(np.asarray(s.sample(t[i] + 0.01)[0])).all()
        got, want = (np.asarray(x) for x in s.sample(r)), (np.asarray(x) for x in ref.sample(r))
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        assert s.measured_parts == ((False, True) if part == "orientation" else (True, False))
    s, ref = pj.TrackerStream(t=0.0), pj.TrackerStream(t=0.0)
    for i in range(k + 6):
        s.update(t[i], nan_p if i < k - 1 else p[i], q[i])
        if i >= k - 1:
            ref.update(t[i], p[i], q[i])
    for a, b in zip(s.sample(r), ref.sample(r)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert s.measured_parts == (True, True)


@pytest.mark.parametrize("imm", [True, False])
@pytest.mark.parametrize("late", ["position", "orientation"])
def test_a_part_measured_after_it_was_filled_in_starts_again_there(late, imm):
    """A source whose position (orientation) comes only after ``PARTIAL_FRAMES`` frames, when
    the stream had filled in the origin (identity): the filter's estimate of that part was of
    the placeholder, and the first real measurement swung it past the truth (position 0.6 m
    from the origin: rendered 0.80 m, 0.3 s to settle). Now that part starts again from the
    measurement at rest: the stream reaches it within a horizon (C1, no overshoot) while the
    other part renders exactly what a stream that never lost the part renders."""
    from phjax.tracking.stream import PARTIAL_FRAMES

    t, p, q = (np.asarray(x, np.float64)[::4] for x in simulate.synthetic_head_motion(
        duration=1.5, rate=120.0, seed=4))
    p = p + np.array([0.3, 0.1, 0.6])  # far from the origin
    m = PARTIAL_FRAMES + 5  # the first frame with the late part
    cfg = pj.TrackerConfig() if imm else pj.TrackerConfig(imm=None)
    s, ref = pj.TrackerStream(cfg, t=0.0), pj.TrackerStream(cfg, t=0.0)
    part = 0 if late == "position" else 1
    r_got, r_ref = [], []
    for i in range(len(t)):
        meas = [p[i], q[i]]
        if i < m:
            meas[part] = np.full(meas[part].shape, np.nan)
        s.update(t[i], *meas)
        if i >= PARTIAL_FRAMES - 1:  # where ``s`` starts, with the placeholder
            fill = [np.zeros(3), np.array([1.0, 0, 0, 0])][part]
            ref.update(t[i], *[meas[0], meas[1]] if i >= m else
                       [fill if j == part else meas[j] for j in (0, 1)])
        if i >= m:
            r = t[i] + np.arange(4) / 120.0
            r_got.append([np.asarray(x) for x in s.sample(r)])
            r_ref.append([np.asarray(x) for x in ref.sample(r)])
    got = [np.concatenate([g[k] for g in r_got]) for k in (0, 1)]
    want = [np.concatenate([g[k] for g in r_ref]) for k in (0, 1)]
    truth_p = p[m:].repeat(4, 0)
    truth_q = q[m:].repeat(4, 0)
    if part == 0:
        np.testing.assert_allclose(got[1], want[1], atol=1e-12)  # orientation unaffected
        err = np.linalg.norm(got[0] - truth_p, axis=-1)
    else:
        np.testing.assert_allclose(got[0], want[0], atol=1e-12)  # position unaffected
        dots = np.abs(np.sum(got[1] * truth_q, axis=-1)).clip(max=1)
        err = np.rad2deg(2 * np.arccos(dots))
    # from the placeholder (1.46 m / 2.9 deg away) straight to the truth within a horizon,
    # then on it: measured at most 1.1 mm / 0.26 deg from two camera frames on (before: 0.2 m
    # past it, 0.3 s to settle)
    assert np.all(np.diff(err[:4]) < 0) and err[1:].max() < err[0]
    assert err[8:].max() < (0.005 if part == 0 else 1.0)


def test_epoch_times_in_a_float32_stream_equal_relative_times(meas):
    """Times are taken relative to the stream's origin (the first update's time) in float64
    before the float32 state sees them: a stream fed Unix epoch times equals one fed times
    from 0 (float32 rounds 1.7e9 s to 128 s: the stream rendered 0.14 m where it should
    render 0.29 m before)."""
    t, p, q = (np.asarray(x) for x in meas[:3])
    epoch = 1.7e9 + 0.123
    a, b = pj.TrackerStream(), pj.TrackerStream(t=0.0)
    for i in range(40):
        a.update(epoch + t[i], p[i], q[i])
        b.update(t[i], p[i], q[i])
    assert a.origin == epoch + t[0] and b.origin == 0.0
    r = t[39] + np.array([0.0, 0.004, 0.02])
    for x, y in zip(a.sample(epoch + r), b.sample(r)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=2e-6)
    assert np.isfinite(np.asarray(a.sample(epoch + r)[0])).all()


def test_non_finite_times_and_other_filter_structures_are_refused(meas):
    """Found by probing: a NaN or inf update time became the origin (or a step) and the stream
    was NaN for good, where track refuses such times; set_config accepted a config of another
    filter structure (IMM -> single Kalman) and every later update failed deep in JAX."""
    t, p, q = meas
    s = pj.TrackerStream(fast_start=False)
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="t must be finite"):
            s.update(bad, p[0], q[0])
    assert s.origin is None  # nothing was taken from the bad calls
    for k in range(5):
        s.update(t[k], p[k], q[k])
    with pytest.raises(ValueError, match="another structure"):
        s.set_config(pj.TrackerConfig(imm=None))
    s.set_config(pj.TrackerConfig(horizon=0.05))  # same structure: accepted
    s.update(t[5], p[5], q[5])
    assert np.isfinite(np.asarray(s.sample(t[5] + 0.01)[0])).all()
