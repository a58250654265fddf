"""The streaming tracker, the batch track/reconstruct API and the C1 orientation curves."""

import re
import warnings
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import phjax as pj
from phjax.motion import resample, simulate
from phjax.tracking import tracker
from stream_checks import world_omega

EPS = 1e-6


@pytest.fixture(scope="module")
def head():
    t, p, q = simulate.synthetic_head_motion(duration=8.0, seed=1)
    mt, mp, mq = (np.asarray(x) for x in simulate.simulate_measurements(3, t, p, q))
    return t, p, q, mt, mp, mq


# ------------------------------------------------------------------- orientation curves
def test_quaternion_hermite_end_conditions_and_velocity():
    rng = np.random.default_rng(0)
    for _ in range(10):
        q0 = np.asarray(pj.quat_normalize(rng.normal(size=4)))
        q1 = np.asarray(pj.quat_normalize(rng.normal(size=4)))
        w0, w1 = rng.normal(size=(2, 3)) * 3
        T = rng.uniform(0.01, 0.5)
        c = pj.quaternion_hermite(q0, q1, w0, w1, T)
        np.testing.assert_allclose(c.rotation(0.0), q0, atol=1e-12)
        assert float(pj.quat_geodesic_distance(c.rotation(1.0), q1)) < 1e-7
        np.testing.assert_allclose(c.angular_velocity(0.0), w0, atol=1e-10)
        np.testing.assert_allclose(c.angular_velocity(1.0), w1, atol=1e-10)
        s = np.linspace(0.05, 0.95, 7)
        qs = np.asarray(c.rotation(s))
        np.testing.assert_allclose(np.linalg.norm(qs, axis=-1), 1, atol=1e-12)
        # angular velocity against finite differences of the rotation
        h = 1e-6
        dq = (np.asarray(c.rotation(s + h)) - np.asarray(c.rotation(s - h))) / (2 * h)
        om = 2 * np.asarray(pj.quat_mul(dq, pj.quat_conj(qs)))[:, 1:] / T
        np.testing.assert_allclose(om, c.angular_velocity(s), atol=1e-6 * (1 + np.abs(om).max()))
        # q1 and -q1 give the same curve
        c2 = pj.quaternion_hermite(q0, -q1, w0, w1, T)
        np.testing.assert_allclose(c2.rotation(s), qs, atol=1e-12)


def test_quaternion_hermite_degenerate_finite():
    q = np.array([1.0, 0, 0, 0])
    half_turn = np.array([0.0, 0, 0, 1])
    for q1, w in [(q, np.zeros(3)), (half_turn, np.zeros(3)), (half_turn, np.array([0, 0, 1e-9]))]:
        c = pj.quaternion_hermite(q, q1, w, w, 0.1)
        assert np.all(np.isfinite(np.asarray(c.rotation(np.linspace(0, 1, 5)))))
        g = jax.grad(lambda w, q1=q1: jnp.sum(
            pj.quaternion_hermite(q, q1, w, w, 0.1).rotation(0.3)))(jnp.asarray(w))
        assert np.all(np.isfinite(np.asarray(g)))
    # a zero-duration segment: angular velocity 0 (it divided by the duration: NaN)
    c = pj.quaternion_hermite(q, q, np.ones(3), np.zeros(3), 0.0)
    np.testing.assert_array_equal(np.asarray(c.angular_velocity(np.linspace(0, 1, 3))), 0.0)
    g = jax.grad(lambda d: jnp.sum(pj.quaternion_hermite(q, half_turn, np.ones(3), np.zeros(3),
                                                         d).angular_velocity(0.5)))(0.0)
    assert np.isfinite(float(g))


# ------------------------------------------------------------------------------ stream
def _one_sided(x, eps, side):
    """Second-order one-sided derivative at ``x[..., 0, :]`` from samples ``eps`` apart going
    ``side`` (+1 forward, -1 backward): ``x[..., k, :]`` is the sample at ``side * k * eps``."""
    return side * (-3 * x[..., 0, :] + 4 * x[..., 1, :] - x[..., 2, :]) / (2 * eps)


@pytest.mark.parametrize("lookahead,rotation_horizon", [(0.0, None), (0.04, None), (0.02, 0.05)])
def test_stream_is_c1_across_camera_frames(head, lookahead, rotation_horizon):
    """Position, velocity, orientation and the world-frame angular velocity *vector* are
    continuous across every camera frame (finite differences of ``track``'s samples; comparing
    angular speeds only would miss an angular velocity taken in the wrong frame), also when
    the stream shows the pose predicted for a later display time and when the orientation
    settles on a horizon of its own."""
    _, _, _, mt, mp, mq = head
    ok = np.isfinite(mp).all(-1)
    tb = mt[ok][2:-2]
    r = np.sort(np.concatenate([tb - 2 * EPS, tb - EPS, tb, tb + EPS]))
    cfg = pj.TrackerConfig(lookahead=lookahead, rotation_horizon=rotation_horizon)
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, config=cfg, dtype=jnp.float64))
    P, Q = P.reshape(-1, 4, 3), Q.reshape(-1, 4, 4)
    speed = np.linalg.norm((P[:, 3] - P[:, 2]) / EPS, axis=-1)
    vb, va = (P[:, 1] - P[:, 0]) / EPS, (P[:, 3] - P[:, 2]) / EPS
    assert np.abs(P[:, 2] - P[:, 1]).max() < 5 * EPS * (1 + speed.max())
    # velocity continuous up to the O(eps * acceleration) of one-sided differences; measured
    # 1.4e-4 / 1.7e-4 m/s (lookahead 0 / 40 ms) at a top speed of 0.28 m/s, bound 3.7x that
    assert np.linalg.norm(va - vb, axis=-1).max() < 5e-4 * (1 + speed.max())
    wb, wa = world_omega(Q[:, 0], Q[:, 1], EPS), world_omega(Q[:, 2], Q[:, 3], EPS)
    w_max = float(np.linalg.norm(wa, axis=-1).max())
    assert w_max > 0.5  # the head really turns at these frames
    # measured: 1.5e-4 rad/s (the O(eps * angular acceleration) of the differences); an angular
    # velocity taken in the body frame instead of the world frame jumps by up to 1.1 rad/s
    assert np.linalg.norm(wa - wb, axis=-1).max() < 1e-3 * (1 + w_max)
    assert np.asarray(pj.quat_geodesic_distance(Q[:, 1], Q[:, 2])).max() < 5 * EPS * (1 + w_max)


@pytest.mark.parametrize("rotation_horizon", [None, 0.045])
def test_segment_starts_at_the_rendered_state_and_correction_decays(head, rotation_horizon):
    """Each camera frame starts a segment at the pose, velocity and world angular velocity
    rendered just before it (taken from the *previous* state's samples by finite differences,
    not from the tracker's formulas); the correction c = rendered - predicted then follows the
    documented critically damped law (c0 (1 + s) + c0' t) exp(-s), s = t / (horizon / 5), at the
    knot (0.4 horizon), the stream is C1 there and reaches the prediction at the horizon; the
    orientation on its own ``rotation_horizon`` when one is set."""
    _, _, _, mt, mp, mq = head
    # the single-model filter: predict_pose below
    cfg = pj.TrackerConfig(imm=None, rotation_horizon=rotation_horizon)
    h = cfg.horizon
    T, t1 = h / 5, 0.4 * h
    hr = h if rotation_horizon is None else rotation_horizon
    Tr, t1r = hr / 5, 0.4 * hr
    e = np.exp(-2.0)  # s = t1 / T = 2
    eps = 1e-5
    steps = np.arange(3) * eps
    state = pj.tracker_init(cfg, 0.0, jnp.float64)
    checked = 0
    for k in range(30):
        t = mt[k] - mt[0]
        before = [np.asarray(x) for x in pj.tracker_sample(cfg, state, t - steps)]
        state = pj.tracker_update(cfg, state, t, mp[k], mq[k])
        if k < 3 or not np.isfinite(mp[k]).all() or not np.isfinite(mq[k]).all():
            continue
        after = [np.asarray(x) for x in pj.tracker_sample(cfg, state, t + steps)]
        # the start: pose equal to the rendered one, velocities equal (world frame)
        p_r, q_r = before[0][0], before[1][0]
        np.testing.assert_allclose(after[0][0], p_r, atol=1e-12)
        assert float(pj.quat_geodesic_distance(after[1][0], q_r)) < 1e-10
        v_r = _one_sided(before[0], eps, -1)
        v_a = _one_sided(after[0], eps, 1)
        w_r = 2 * np.asarray(pj.quat_mul(_one_sided(before[1], eps, -1), pj.quat_conj(q_r)))[1:]
        w_a = 2 * np.asarray(pj.quat_mul(_one_sided(after[1], eps, 1), pj.quat_conj(q_r)))[1:]
        # measured: 3.2e-6 m/s, 2.8e-6 rad/s (the O(eps^2) error of one-sided differences;
        # bound ~30x); an angular velocity taken in the body frame is off by up to 1 rad/s
        np.testing.assert_allclose(v_a, v_r, atol=1e-4 * (1 + np.abs(v_r).max()))
        np.testing.assert_allclose(w_a, w_r, atol=1e-4 * (1 + np.abs(w_r).max()))
        # the documented correction law at the knot, from those independent start values
        pk, qk, vk, wk = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t))
        p1, q1, v1, _ = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + t1))
        pT, _, _, _ = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + h))
        _, q1r, _, _ = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + t1r))
        _, qT, _, _ = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + hr))
        # samples on both sides of the knot (C1 only: one-sided differences)
        around = [np.asarray(x) for x in pj.tracker_sample(
            cfg, state, t + t1 + np.concatenate([-steps, steps]))]
        p_want = p1 + 3 * e * (p_r - pk) + 2 * e * T * (v_r - vk)
        np.testing.assert_allclose(around[0][3], p_want, atol=1e-9)
        vl = _one_sided(around[0][:3], eps, -1)
        vr = _one_sided(around[0][3:], eps, 1)
        v_want = v1 + (-2 * e / T) * (p_r - pk) - e * (v_r - vk)
        np.testing.assert_allclose(vr, v_want, atol=1e-4 * (1 + np.abs(v_want).max()))
        np.testing.assert_allclose(vl, vr, atol=1e-4 * (1 + np.abs(vr).max()))
        dq = np.asarray(pj.quat_mul(q_r, pj.quat_conj(qk)))
        dth = np.asarray(pj.quat_to_rotvec(dq if dq[0] >= 0 else -dq))
        q_want = np.asarray(pj.quat_mul(pj.quat_from_rotvec(3 * e * dth + 2 * e * Tr * (w_r - wk)),
                                        q1r))
        around_r = np.asarray(pj.tracker_sample(
            cfg, state, t + t1r + np.concatenate([-steps, steps]))[1])
        assert float(pj.quat_geodesic_distance(around_r[3], q_want)) < 1e-10
        q_k = around_r[3]
        wl = 2 * np.asarray(pj.quat_mul(_one_sided(around_r[:3], eps, -1), pj.quat_conj(q_k)))[1:]
        wr = 2 * np.asarray(pj.quat_mul(_one_sided(around_r[3:], eps, 1), pj.quat_conj(q_k)))[1:]
        np.testing.assert_allclose(wl, wr, atol=1e-4 * (1 + np.abs(wr).max()))
        # the prediction is reached at the horizon (each channel's own)
        p_h = np.asarray(pj.tracker_sample(cfg, state, t + h)[0])
        q_h = np.asarray(pj.tracker_sample(cfg, state, t + hr)[1])
        np.testing.assert_allclose(p_h, pT, atol=1e-12)
        assert float(pj.quat_geodesic_distance(q_h, qT)) < 1e-10
        checked += 1
    assert checked > 20


def test_track_equals_streaming_loop(head):
    """``track`` (one scan) equals the loop of ``tracker_update`` / ``tracker_sample``.

    Both paths run the same ``_update`` / ``RenderSegment.evaluate`` code, so this checks the scan's
    plumbing (causal selection of states, shapes, no recompilation), not the maths; the maths
    is covered independently by ``test_stream_is_c1_across_camera_frames`` and
    ``test_segment_starts_at_the_rendered_state_and_correction_decays`` (finite differences of
    the samples), ``test_causal_stream_against_kalman_extrapolation`` (ground truth) and the
    Kalman filter's tests against filterpy (tests/tracking/test_kalman.py)."""
    _, _, _, mt, mp, mq = head
    mt, mp, mq = mt[:40], mp[:40], mq[:40]
    r = np.linspace(mt[0], mt[-1] + 0.2, 173)
    cfg = pj.TrackerConfig(lookahead=0.02)  # the display-time shift travels in the state too
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, config=cfg, dtype=jnp.float64))
    origin = mt[0]
    state = pj.tracker_init(cfg, 0.0, jnp.float64)
    # compile both functions for the loop's argument types on a throw-away state first
    warm = pj.tracker_update(cfg, state, mt[0] - origin, mp[0], mq[0])
    pj.tracker_sample(cfg, warm, r[0] - origin)
    n_update, n_sample = tracker.tracker_update._cache_size(), tracker._sample_render._cache_size()
    out_p, out_q = [], []
    k = 0
    for tau in r - origin:
        while k < len(mt) and mt[k] - origin <= tau:
            state = pj.tracker_update(cfg, state, mt[k] - origin, mp[k], mq[k])
            k += 1
        p, q = pj.tracker_sample(cfg, state, tau)
        out_p.append(p)
        out_q.append(q)
    np.testing.assert_allclose(np.asarray(out_p), P, atol=1e-9)
    np.testing.assert_allclose(np.asarray(out_q), Q, atol=1e-9)
    # static shapes: no compilation for any of those frames (other tests in the same process
    # may have compiled other signatures before)
    assert tracker.tracker_update._cache_size() == n_update
    assert tracker._sample_render._cache_size() == n_sample


def test_config_arrays_and_small_state_buffers(head):
    """``tracker_config_arrays`` gives the updates of the float config (one compile each for
    all frames); every state array has at most 64 elements (XLA's CPU runtime runs a call's
    kernels in the calling thread only when every buffer has at most 512 bytes)."""
    _, _, _, mt, mp, mq = head
    cfg = pj.TrackerConfig(imm=None)  # the IMM state has (3, 6, 6) covariances
    cfga = pj.tracker_config_arrays(cfg, jnp.float64)
    assert all(isinstance(x, jax.Array) and x.dtype == jnp.float64 for x in jax.tree.leaves(cfga))
    s1 = s2 = pj.tracker_init(cfg, 0.0, jnp.float64)
    n0 = tracker.tracker_update._cache_size()
    for k in range(25):
        t = mt[k] - mt[0]
        s1 = pj.tracker_update(cfg, s1, t, mp[k], mq[k])
        s2 = pj.tracker_update(cfga, s2, t, mp[k], mq[k])
        for a, b in zip(jax.tree.leaves(s1), jax.tree.leaves(s2)):
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-12, atol=1e-12)
        if np.all(np.isfinite(mp[k])) or np.all(np.isfinite(mq[k])):
            assert float(s2.t0) == pytest.approx(t) and bool(s2.started)
    assert tracker.tracker_update._cache_size() - n0 <= 2
    assert max(x.size for x in jax.tree.leaves(s2)) <= 64


def test_causality(head):
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0], mt[-1], 500)
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    cut = mt[len(mt) // 2]
    mp2, mq2 = mp.copy(), mq.copy()
    later = mt > cut
    mp2[later] += 0.3
    mq2[later] = np.asarray(pj.quat_mul(pj.quat_from_rotvec(np.array([0.0, 1.0, 0.0])), mq2[later]))
    P2, Q2 = (np.asarray(x) for x in pj.track(mt, mp2, mq2, r, dtype=jnp.float64))
    before = r <= cut
    np.testing.assert_array_equal(P2[before], P[before])
    np.testing.assert_array_equal(Q2[before], Q[before])
    assert np.abs(P2[~before] - P[~before]).max() > 0.01


def test_nan_before_first_measurement_and_coasting_stops(head):
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0] - 0.1, mt[-1] + 2.0, 900)
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    early = r < mt[0]
    assert np.all(np.isnan(P[early])) and np.all(np.isfinite(P[~early]))
    # long after the last frame the pose has come to rest (bounded coast): measured steps of
    # 6e-12 m between samples a second on, and 7.4 mm from the last measurement (the coast
    # plus the filter's estimate against a 5 mm-noise measurement); bounds 1e-9 m and 2 cm
    tail = r > mt[-1] + 1.0
    assert np.abs(np.diff(P[tail], axis=0)).max() < 1e-9
    assert np.abs(P[tail][-1] - mp[np.isfinite(mp).all(-1)][-1]).max() < 0.02


def test_orientation_only_input(head):
    """Data without positions (a 3-DoF orientation tracker) is tracked in orientation, equal
    to the same orientations with a fixed position (the channels are independent), and
    reports NaN positions; a frozen or identity orientation would fail the comparison. The
    fixed position is lost where the orientation is (a frame with a valid position rebuilds
    the segment from the rotation's prediction, which differs from coasting by up to 2e-6)."""
    _, _, _, mt, _, mq = head
    r = np.linspace(mt[0], mt[-1], 200)
    fixed = np.where(np.isfinite(mq).all(-1, keepdims=True), [0.1, -0.2, 0.6], np.nan)
    for fn in (pj.track, pj.reconstruct):
        P, Q = (np.asarray(x) for x in fn(mt, np.full((len(mt), 3), np.nan), mq, r,
                                           dtype=jnp.float64))
        _, Q0 = (np.asarray(x) for x in fn(mt, fixed, mq, r, dtype=jnp.float64))
        assert np.all(np.isnan(P)) and np.all(np.isfinite(Q))
        np.testing.assert_allclose(Q, Q0, rtol=0, atol=1e-12)
        assert np.ptp(Q, axis=0).max() > 0.05  # the head turns: not a constant orientation


@pytest.mark.parametrize("missing", ["nan", "zero"])
def test_position_only_input_tracks_the_position(head, missing):
    """Data without a valid orientation (NaN or zero quaternions: a 3-DoF position tracker) is
    tracked in position, equal to the same positions with a fixed orientation (the channels
    are independent), and reports NaN quaternions; before this the whole output was NaN."""
    _, _, _, mt, mp, _ = head
    r = np.linspace(mt[0], mt[-1], 200)
    fixed = np.tile([1.0, 0, 0, 0], (len(mt), 1))
    none = np.full_like(fixed, np.nan) if missing == "nan" else np.zeros_like(fixed)
    for fn in (pj.track, pj.reconstruct):
        P, Q = (np.asarray(x) for x in fn(mt, mp, none, r, dtype=jnp.float64))
        P0, _ = (np.asarray(x) for x in fn(mt, mp, fixed, r, dtype=jnp.float64))
        assert np.all(np.isnan(Q)) and np.all(np.isfinite(P))
        np.testing.assert_allclose(P, P0, rtol=0, atol=1e-12)


@st.composite
def messy_stream(draw):
    n = draw(st.sampled_from([12, 32]))  # few shapes: few compilations
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    t = np.cumsum(rng.uniform(0.0, 0.07, size=n))
    kind = draw(st.sampled_from(["still", "turn180", "random"]))
    if kind == "still":
        p = np.zeros((n, 3)) + rng.normal(size=3)
        q = np.tile([1.0, 0, 0, 0], (n, 1))
    elif kind == "turn180":
        ang = np.linspace(0, np.pi, n)
        p = np.stack([np.cos(ang), np.sin(ang), 0 * ang], -1) * 0.1
        q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], -1)
        q[-1] = [0.0, 0, 0, 1]  # exactly 180 degrees
    else:
        p = np.cumsum(rng.normal(size=(n, 3)) * 0.01, 0)
        q = np.array(pj.quat_from_rotvec(np.cumsum(rng.normal(size=(n, 3)) * 0.1, 0)))
    flips = rng.uniform(size=n) < 0.3
    q[flips] *= -1
    drop = rng.uniform(size=n) < draw(st.floats(0, 0.5))
    drop[0] = False
    p[drop] = np.nan
    q[drop & (rng.uniform(size=n) < 0.5)] = np.nan
    if draw(st.booleans()) and n > 3:
        t[2] = t[1]  # duplicate timestamp
    if draw(st.booleans()) and n > 5:
        t[[3, 4]] = t[[4, 3]]  # out of order
    return t, p, q


def _largest_measured_steps(t, p, q):
    """Largest distance and rotation angle between consecutive complete measurements (in time
    order; the first of duplicate timestamps, as ``track`` keeps)."""
    order = np.argsort(t, kind="stable")
    t, p, q = t[order], p[order], q[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) & np.isfinite(p).all(-1) & np.isfinite(q).all(-1)
    p, q = p[keep], q[keep] / np.linalg.norm(q[keep], axis=-1, keepdims=True)
    if len(p) < 2:
        return 0.0, 0.0
    d = np.linalg.norm(np.diff(p, axis=0), axis=-1).max()
    a = np.asarray(pj.quat_geodesic_distance(q[1:], q[:-1])).max()
    return float(d), float(a)


@given(messy_stream())
@settings(max_examples=25, deadline=None)
def test_robust_to_messy_input(data):
    t, p, q = data
    r = np.linspace(np.min(t), np.max(t) + 0.3, 97)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for fn in (pj.track, pj.reconstruct):
                P, Q = (np.asarray(x) for x in fn(t, p, q, r, dtype=jnp.float64))
                first = np.min(t[np.isfinite(p).all(-1) & np.isfinite(q).all(-1)])
                after = r >= first
                assert np.all(np.isfinite(P[after])) and np.all(np.isfinite(Q[after]))
                np.testing.assert_allclose(np.linalg.norm(Q[after], axis=-1), 1, atol=1e-9)
                # no jumps: a step between consecutive render samples is at most a few times
                # the largest step between consecutive measurements (position and orientation)
                step = np.linalg.norm(np.diff(P[after], axis=0), axis=-1).max()
                turn = np.asarray(pj.quat_geodesic_distance(Q[after][1:], Q[after][:-1])).max()
                # (measured over these examples: at most 1.11x / 1.17x the largest measured
                # step + 1 mm / 1 mrad; bounds 1.5x that)
                m_step, m_turn = _largest_measured_steps(t, p, q)
                assert step < 1.5 * 1.11 * (m_step + 1e-3), (fn.__name__, step, m_step)
                assert turn < 1.5 * 1.17 * (m_turn + 1e-3), (fn.__name__, turn, m_turn)


def test_q_sign_flips_do_not_change_the_stream(head):
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0], mt[-1], 300)
    flips = np.where(np.arange(len(mt)) % 3 == 0, -1.0, 1.0)[:, None]
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    P2, Q2 = (np.asarray(x) for x in pj.track(mt, mp, mq * flips, r, dtype=jnp.float64))
    np.testing.assert_allclose(P2, P, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(Q2 * Q, -1)), 1, atol=1e-9)


def test_gradient_through_track_wrt_config(head):
    """``jax.grad`` through the public :func:`phjax.track`: the recording is padded to its size
    class with lost frames 1 s apart and has a 12 s dropout, so the stream coasts to rest
    (velocities decaying to ~1e-100) and the IMM predicts for seconds. Both made the gradient
    NaN (in the unused segment built at a lost frame, then in the segment after the dropout)
    until the PH construction ran on data of scale 1. The derivatives in the horizon, the
    lookahead and an orientation horizon of its own are checked against central
    differences."""
    _, _, _, mt, mp, mq = head
    k = 40
    mt = np.concatenate([mt[:k], mt[k:k + 20] + 12.0]) - mt[0]
    mp, mq = np.concatenate([mp[:k], mp[k:k + 20]]), np.concatenate([mq[:k], mq[k:k + 20]])
    r = np.concatenate([np.arange(0.05, mt[k - 1], 1 / 60), np.arange(mt[k], mt[-1], 1 / 60)])
    gt = np.asarray(pj.track(mt, mp, mq, r, dtype=jnp.float64)[0]) + 0.001

    def loss(horizon, lookahead, rotation_horizon):
        cfg = pj.TrackerConfig(horizon=horizon, lookahead=lookahead,
                               rotation_horizon=rotation_horizon)
        P, Q = pj.track(mt, mp, mq, r, config=cfg, dtype=jnp.float64)
        return jnp.mean((P - gt) ** 2) + jnp.mean(Q[:, 1] ** 2)

    x = np.array([0.05, 0.02, 0.035])
    g = jax.grad(loss, argnums=(0, 1, 2))(*x)
    assert all(np.isfinite(float(v)) and float(v) != 0 for v in g), g
    h = 1e-6
    num = [(loss(*(x + h * e)) - loss(*(x - h * e))) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(np.asarray(g, float), np.asarray(num, float), rtol=1e-4)


def test_head_at_rest_values_and_gradients_finite():
    """A head at rest: every angular velocity is exactly zero (rotation increments of the
    curves, coasting rotation), where ``|w|`` has no derivative. The rendered pose and its
    velocities (what the next update starts from) inside both pieces, while coasting and
    after stopping, and their gradients with respect to the render segment stay finite."""
    import equinox as eqx

    cfg = pj.TrackerConfig(imm=None)
    p0 = jnp.asarray([0.1, -0.2, 0.5])
    q0 = jnp.asarray([1.0, 0.0, 0.0, 0.0])
    taus = 2 / 30 + jnp.asarray([0.0, 0.005, 0.02, 0.1, 0.2, 1.0])
    st = pj.tracker_init(cfg, 0.0, jnp.float64)
    for k in range(3):
        st = pj.tracker_update(cfg, st, k / 30, p0, q0)
    seg = st.segment
    np.testing.assert_array_equal(np.asarray(seg.rotation.w1), 0.0)  # really at rest
    np.testing.assert_array_equal(np.asarray(seg.w_end), 0.0)

    @eqx.filter_jit
    def loss(seg):
        p, v, q, w = jax.vmap(seg.evaluate)(taus)
        return jnp.sum(p) + jnp.sum(v) + jnp.sum(q * jnp.arange(4.0)) + jnp.sum(w), (p, q)

    (_, (P, Q)), g = eqx.filter_value_and_grad(loss, has_aux=True)(seg)
    np.testing.assert_allclose(np.asarray(P), np.broadcast_to(p0, P.shape), atol=1e-12)
    np.testing.assert_allclose(np.abs(np.asarray(Q)[:, 0]), 1.0, atol=1e-12)
    leaves = jax.tree.leaves(g)
    assert len(leaves) >= 15
    for x in leaves:
        assert np.all(np.isfinite(np.asarray(x)))
    # the rotation increments and the coasting angular velocity do get gradients
    assert np.abs(np.asarray(g.rotation.w2)).max() > 0
    assert np.abs(np.asarray(g.w_end)).max() > 0


def test_float32_stream_close_to_float64(head):
    """float32 (the real-time precision) against float64: positions and orientations.
    Measured: 3.5e-6 m and 7.2e-7 rad at most; bounds 3x (float32 rounding differs between
    CPUs and XLA versions)."""
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0], mt[-1], 300)
    P, Q = pj.track(mt, mp, mq, r, dtype=jnp.float32)
    P64, Q64 = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    assert P.dtype == jnp.float32 and Q.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(P))) and np.all(np.isfinite(np.asarray(Q)))
    assert np.abs(np.asarray(P, np.float64) - P64).max() < 3 * 3.5e-6
    angle = np.asarray(pj.quat_geodesic_distance(np.asarray(Q, np.float64), Q64))
    assert angle.max() < 3 * 7.2e-7


def test_offline_reconstruction_is_smooth_and_accurate(head):
    from phjax.tracking import baselines
    from phjax.evaluation import metrics
    from phjax.motion import resample

    t, p, q, mt, mp, mq = head
    r = np.arange(mt[0] + 0.1, mt[-1] - 0.1, 1 / 120)
    gp, gq = (np.asarray(x) for x in resample.interpolate_poses(t, p, q, r))
    P, Q = (np.asarray(x) for x in pj.reconstruct(mt, mp, mq, r, dtype=jnp.float64))
    Pc, Qc = baselines.cubic_spline(mt, mp, mq, r)
    # regression bounds 1.5x the measured ratios to SciPy's C2 cubic spline (position / rotation
    # RMSE 0.384 / 0.502, RMS jerk 0.0042 / 0.0045); a 2.7x worse reconstruction fails
    jerk = (metrics.rms_jerk_position(r, P).value / metrics.rms_jerk_position(r, Pc).value,
            metrics.rms_jerk_rotation(r, Q).value / metrics.rms_jerk_rotation(r, Qc).value)
    rmse = (metrics.position_rmse(P, gp).value / metrics.position_rmse(Pc, gp).value,
            metrics.rotation_rmse_deg(Q, gq).value / metrics.rotation_rmse_deg(Qc, gq).value)
    assert rmse[0] < 1.5 * 0.384 and rmse[1] < 1.5 * 0.502, rmse
    assert jerk[0] < 1.5 * 0.0042 and jerk[1] < 1.5 * 0.0045, jerk


@pytest.mark.parametrize("gap", [0.5, 300.0])
def test_offline_reconstruction_bridges_a_long_gap_without_made_up_motion(head, gap):
    """A gap longer than ``coast_time + stop_time`` (0.15 s) in the measurements: each side
    coasts into it and the two are blended, so the rendered position stays within
    ``(coast_time + stop_time) x`` the end speeds of the chord between the end poses (before,
    a 300 s gap swung 27 m and 180 degrees: the segment's end derivatives were velocity x gap),
    and position and orientation stay C1 at both ends of the gap (one-sided differences)."""
    t, p, q, mt, mp, mq = head
    k = mt.size // 2
    mt = np.concatenate([mt[:k], mt[k:] + gap])
    ta, tb = mt[k - 1], mt[k]
    h = 1e-6
    r = np.concatenate([[ta - h, ta, ta + h], np.linspace(ta, tb, 4001)[1:-1], [tb - h, tb, tb + h]])
    P, Q = (np.asarray(x) for x in pj.reconstruct(mt, mp, mq, r, dtype=jnp.float64))
    assert np.isfinite(P).all() and np.isfinite(Q).all()
    va, vb = (P[2] - P[1]) / h, (P[-1] - P[-2]) / h
    np.testing.assert_allclose((P[1] - P[0]) / h, va, rtol=1e-3, atol=1e-5)  # C1 at ta
    np.testing.assert_allclose((P[-2] - P[-3]) / h, vb, rtol=1e-3, atol=1e-5)  # C1 at tb
    a, b = P[1], P[-2]
    u = np.clip((P - a) @ (b - a) / max((b - a) @ (b - a), 1e-30), 0, 1)
    off_chord = np.linalg.norm(P - (a + u[:, None] * (b - a)), axis=-1)
    assert off_chord.max() <= 0.15 * max(np.linalg.norm(va), np.linalg.norm(vb)) + 1e-6
    wa = np.asarray(pj.quat_to_rotvec(pj.quat_mul(Q[2], pj.quat_conj(Q[1])))) / h
    wa_before = np.asarray(pj.quat_to_rotvec(pj.quat_mul(Q[1], pj.quat_conj(Q[0])))) / h
    np.testing.assert_allclose(wa_before, wa, rtol=1e-3, atol=1e-4)
    turn = np.asarray(pj.quat_geodesic_distance(Q[1], Q[3:-3]))
    span = float(pj.quat_geodesic_distance(Q[1], Q[-2]))
    assert turn.max() <= span + 0.15 * 2 * max(np.linalg.norm(wa), 1.0) + 1e-6


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_reconstruct_of_sparse_frames_with_large_turns_is_finite(dtype):
    """Found by probing: frames 10 s apart, each at a random orientation (float32) gave NaN
    quaternions over the last segment: the smoother smoothed the last measured state against
    its own uninformative prediction (a 10 s step of an uncertain spin). At and after the last
    measurement the filtered state is now taken as it is, as RTS defines it."""
    rng = np.random.default_rng(1)
    n = 16
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = np.arange(n) * 10.0
    P, Q = (np.asarray(x) for x in pj.reconstruct(t, rng.standard_normal((n, 3)), q,
                                                  np.linspace(0, 150, 50), dtype=dtype))
    assert np.isfinite(P).all() and np.isfinite(Q).all()
    np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1, atol=1e-5)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_gradients_across_long_pauses_stay_finite_and_bounded(dtype):
    """Found by probing: bursts of three frames (6 degree jitter) 150 s to 3 h apart. The
    constant-velocity turn over each pause (many turns) is chaotic in the angular velocity,
    and its exact derivative grew ~dt per pause: reconstruct's quaternion gradient reached
    3e9 (float64) after three 150 s pauses, and the smoother's skipped step over a 3 h pause
    gave float32 NaN through the select. Now the turn's gradient is cut across pauses longer
    than SMOOTH_MAX_GAP (values unchanged) and a skipped smoother step computes nothing.
    Then reconstruct gave <= 37, the Kalman stream <= 48, but the IMM stream (the default) 4e3
    (float64) and NaN (float32, 1000 s pauses): the orientation ceiling kept the angle-rate
    correlation of many turns (see the IMM test of the rate after a pause). Measured now, both
    dtypes: reconstruct <= 19, the Kalman and IMM streams <= 28 (the IMM tested in float32);
    bound 100."""
    rng = np.random.default_rng(0)
    n = 12
    p = rng.standard_normal((n, 3)) * 0.01
    q = np.tile([1.0, 0, 0, 0], (n, 1)) + rng.standard_normal((n, 4)) * 0.05
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cases = [(pj.reconstruct, None), (pj.track, pj.TrackerConfig(imm=None))]
    if dtype == jnp.float32:  # the IMM in the dtype that failed worst (its compile costs 30 s)
        cases.append((pj.track, None))
    for fn, config in cases:
        @jax.jit
        @partial(jax.grad, argnums=(0, 1))
        def grads(pp, qq, t, r, fn=fn, config=config):
            P, Q = fn(t, pp, qq, r, dtype=dtype, config=config)
            return jnp.sum(P ** 2) + jnp.sum(Q[..., 1:] ** 2)

        for gap in (150.0, 1e3, 1e4):  # one program for all
            t = np.cumsum(np.r_[0, np.where(np.arange(n - 1) % 3 == 1, gap, 1 / 30)])
            r = np.linspace(0, t[-1], 40)
            for g in grads(jnp.asarray(p, dtype), jnp.asarray(q, dtype), t, r):
                g = np.asarray(g)
                assert np.isfinite(g).all() and np.abs(g).max() < 100, (gap, fn.__name__)


@pytest.mark.parametrize("gap", [None, 3600.0, 86400.0])
def test_reconstruct_in_float32_across_padding_and_pauses(head, gap):
    """Found by probing (float32, the default): the size-class padding (lost frames 1 s apart
    after the end) let the orientation covariance grow until the smoother's Cholesky gave
    NaN, which the backward pass carried into every real frame (a 20 s recording batched
    with a 10 min one: all orientations NaN); a pause of 10 min put the orientations before
    it up to 180 degrees off (1 h: NaN) and a day's pause the positions after it 14 km off.
    Now the smoother leaves out the tail after the last measurement and steps longer than
    SMOOTH_MAX_GAP, and a prediction models at most MAX_PREDICT_STEP. Measured: no NaN,
    rotation error at most 3.5 deg, position 7 mm (bounds 2x)."""
    t, p, q, mt, mp, mq = head
    if gap is None:  # 8 s batched with a recording 40x longer: 2.5 hours of padding frames
        long_t = np.arange(mt.size * 40) / 30.0
        long = (long_t, np.zeros((long_t.size, 3)), np.tile([1.0, 0, 0, 0], (long_t.size, 1)))
        r = mt[5:] + 0.004
        times, pos, quat, rend = pj.pad_recordings([mt, long[0]], [mp, long[1]],
                                                   [mq, long[2]], [r, r])
        P, Q = (np.asarray(x)[0, :r.size]
                for x in pj.reconstruct(times, pos, quat, rend, dtype=jnp.float32))
        truth_t = r
    else:
        k = mt.size // 2
        mt = np.concatenate([mt[:k], mt[k:] + gap])
        r = mt[5:] + 0.004
        P, Q = (np.asarray(x) for x in pj.reconstruct(mt, mp, mq, r, dtype=jnp.float32))
        truth_t = np.where(r > mt[k - 1] + 0.5 * gap, r - gap, r)
        keep = (r < mt[k - 1]) | (r > mt[k])
        P, Q, truth_t = P[keep], Q[keep], truth_t[keep]
    assert np.isfinite(P).all() and np.isfinite(Q).all()
    gp, gq = (np.asarray(x) for x in resample.interpolate_poses(t, p, q, truth_t))
    assert np.linalg.norm(P - gp, axis=-1).max() < 0.015
    assert np.degrees(np.asarray(pj.quat_geodesic_distance(Q, gq))).max() < 7.0


def test_causal_stream_against_kalman_extrapolation(head):
    """The causal stream against the usual predictive baseline (the same filter's
    constant-velocity extrapolation, which jumps at every frame) and the ground truth.
    Measured (default IMM config, baseline with its default ``TUNED["kalman"]``, render samples
    at a frame's instant snapped onto it): RMSE 0.991x / 1.021x the baseline's (6.46 mm /
    1.60 deg), RMS jerk 0.257x / 0.292x (position / rotation). Bounds: RMSE ratio + 0.03,
    absolute RMSE and jerk ratio 1.5x measured."""
    from phjax.tracking import baselines
    from phjax.evaluation import metrics
    from phjax.motion import resample

    t, p, q, mt, mp, mq = head
    r = resample.snap_to_frames(mt, np.arange(mt[0] + 0.1, mt[-1] - 0.1, 1 / 120))
    gp, gq = (np.asarray(x) for x in resample.interpolate_poses(t, p, q, r))
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    Pk, Qk = (np.asarray(x) for x in baselines.kalman_extrapolation(mt, mp, mq, r))
    rmse = (metrics.position_rmse(P, gp).value, metrics.rotation_rmse_deg(Q, gq).value)
    base = (metrics.position_rmse(Pk, gp).value, metrics.rotation_rmse_deg(Qk, gq).value)
    assert rmse[0] < 1.5 * 0.00646 and rmse[1] < 1.5 * 1.60, rmse
    assert rmse[0] / base[0] < 0.991 + 0.03 and rmse[1] / base[1] < 1.021 + 0.03, (rmse, base)
    jerk = (metrics.rms_jerk_position(r, P).value / metrics.rms_jerk_position(r, Pk).value,
            metrics.rms_jerk_rotation(r, Q).value / metrics.rms_jerk_rotation(r, Qk).value)
    assert jerk[0] < 1.5 * 0.257 and jerk[1] < 1.5 * 0.292, jerk


def test_lookahead_shows_the_pose_predicted_for_the_display_time(head):
    """``lookahead`` L: the pose rendered at ``tau`` is the one predicted for ``tau + L``.

    Exact on motion the filter predicts exactly (constant velocity and angular velocity, no
    noise; measured at L = 30 ms: 2.7e-6 m, 2.2e-5 rad, bounds about 4x). On the simulated
    head (noisy, lost frames), scored against the truth at ``tau + L`` beside the plain stream
    scored there (what a display showing the plain stream L late sees), at L = 40 ms: rotation
    RMSE 0.961x (prediction pays), position 1.12x (the head translates slowly against 5 mm of
    measurement noise: extrapolating the noisy velocity 40 ms ahead costs more than it gains;
    the comparison with every tuned baseline at the same display time is
    ``experiments/frontier.py``). Bounds: rotation < 1, position < 1.25."""
    from phjax.evaluation import metrics
    from phjax.motion import resample

    t = np.arange(90) / 30.0
    v, spin = np.array([0.3, -0.1, 0.05]), 0.8
    p = t[:, None] * v
    q = np.stack([np.cos(spin * t / 2), 0 * t, np.sin(spin * t / 2), 0 * t], -1)
    r = np.linspace(1.0, t[-1], 241)
    for lookahead in (0.02, 0.05):
        P, Q = (np.asarray(x) for x in pj.track(t, p, q, r, dtype=jnp.float64,
                                                config=pj.TrackerConfig(lookahead=lookahead)))
        u = r + lookahead
        assert np.abs(P - u[:, None] * v).max() < 1e-5
        angle = 2 * np.arctan2(Q[:, 2], Q[:, 0])
        assert np.abs(angle - spin * u).max() < 1e-4

    t, p, q, mt, mp, mq = head
    lookahead = 0.04
    r = np.arange(mt[0] + 0.5, mt[-1] - 0.5, 1 / 120)
    gp, gq = (np.asarray(x) for x in resample.interpolate_poses(t, p, q, r + lookahead))
    P0, Q0 = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64,
                                            config=pj.TrackerConfig(lookahead=lookahead)))
    ratio = (metrics.position_rmse(P, gp).value / metrics.position_rmse(P0, gp).value,
             metrics.rotation_rmse_deg(Q, gq).value / metrics.rotation_rmse_deg(Q0, gq).value)
    assert ratio[1] < 1.0 and ratio[0] < 1.25, ratio


def test_bad_input_messages():
    with pytest.raises(ValueError, match="expected times"):
        pj.track(np.zeros(3), np.zeros((3, 2)), np.zeros((3, 4)), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        pj.track(np.array([0.0, np.nan]), np.zeros((2, 3)), np.ones((2, 4)), np.zeros(2))


def test_compiled_shapes_are_bounded(head, monkeypatch):
    """Each size class compiles the scan; at most ``MAX_COMPILED_SHAPES`` stay compiled, so
    many classes in one process do not exhaust its memory mappings (XLA:CPU maps ~260
    regions per compiled stream; Linux allows 65530), and results do not change."""
    from conftest import mapping_count

    from phjax._jit import jit
    from phjax.tracking import _shapes

    _, _, _, mt, mp, mq = head
    monkeypatch.setattr(_shapes, "MAX_COMPILED_SHAPES", 2)
    # track's core with a cache (and bookkeeping) of its own, dropped after the test:
    # evicting from the shared one made the worker's later tests trace and load it again
    core = jit(tracker._track_core.__wrapped__)
    monkeypatch.setattr(tracker, "_track_core", core)
    monkeypatch.setattr(_shapes, "_COMPILED_KEYS", {})

    r = np.linspace(mt[0], mt[10], 50)
    cv = pj.TrackerConfig(imm=None)  # the single-model filter: the same cache, a smaller program
    outs, counts = [], []
    for n in (12, 100, 200, 12):  # size classes 64, 128, 256, 64
        outs.append(np.asarray(pj.track(mt[:n], mp[:n], mq[:n], r, config=cv, dtype=jnp.float64)[0]))
        counts.append(mapping_count())
        assert core._cache_size() <= 2 and len(_shapes._COMPILED_KEYS[core]) <= 2
    np.testing.assert_array_equal(outs[3], outs[0])  # recompiled after eviction: same result
    if counts[0]:  # Linux: /proc/self/maps exists
        assert counts[1] > counts[0] and counts[2] < counts[1]  # the third shape evicted two


def test_lengths_in_one_size_class_share_one_program_and_equal_unpadded(head):
    """Recordings of different lengths in one size class run on one compiled program (no
    compilation for the second: counted with JAX's compile events), and padding changes no
    result: each equals the core run on the unpadded arrays (float64, 1e-12)."""
    import jax.monitoring

    from phjax.tracking import _shapes

    _, _, _, mt, mp, mq = head
    compiles = []

    def on_duration(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    r = np.linspace(mt[0] + 0.05, mt[90] + 0.3, 333)  # also past the shorter recording's end
    assert _shapes.size_class(70, _shapes.MIN_FRAMES) == _shapes.size_class(90, _shapes.MIN_FRAMES)
    pj.track(mt[:70], mp[:70], mq[:70], r, dtype=jnp.float64)  # compiles the class if needed
    jax.monitoring.register_event_duration_secs_listener(on_duration)
    try:
        for fn, checked in ((pj.track, 90), (pj.reconstruct, 70)):
            for n in (70, 90):
                got = fn(mt[:n], mp[:n], mq[:n], r, dtype=jnp.float64)
                if n != checked:
                    continue
                compiled = len(compiles)
                hold = fn is pj.reconstruct
                core = tracker._reconstruct_core if hold else tracker._track_core
                t0 = mt[0]
                ref = core(pj.TrackerConfig(), *(jnp.asarray(x) for x in (mt[:n] - t0, mp[:n], mq[:n])),
                           jnp.asarray((np.minimum(r, mt[n - 1]) if hold else r) - t0))
                for a, b in zip(got, ref):
                    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)
                del compiles[compiled:]  # the unpadded reference compiles; padding must not
    finally:
        jax.monitoring.unregister_event_duration_listener(on_duration)
    # one compile at most: reconstruct's class (track's was compiled before listening)
    assert len(compiles) <= 1, compiles


def test_unsorted_and_duplicate_times_warn_as_trajectory_warnings():
    """``track`` sorts and de-duplicates with a :class:`phjax.io.TrajectoryWarning` (which the
    command line prints as one ``phjax: warning:`` line), not a bare ``UserWarning``."""
    from phjax.io import TrajectoryWarning

    t = np.array([0.0, 1 / 30, 1 / 30, 3 / 30, 2 / 30, 4 / 30])
    p = np.zeros((6, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (6, 1))
    with pytest.warns(TrajectoryWarning) as rec:
        pj.track(t, p, q, np.linspace(0, 0.13, 5))
    assert {str(w.message).split(";")[0].split(" (")[0] for w in rec} == {
        "measurement times are not sorted", "dropping 1 measurement(s) with duplicate timestamps"}


def test_measurements_the_filters_cannot_use_are_named():
    """The filters start from a whole pose (position and orientation both measured): one-part
    rows before the first one, rows that each hold one part, and a recording of lost frames
    are each named by a :class:`phjax.io.TrajectoryWarning` (they were silent: an all-NaN
    output, or the first seconds missing)."""
    from phjax.io import TrajectoryWarning

    t = np.arange(6) / 30
    p = np.zeros((6, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (6, 1))
    nan3, nan4 = np.full(3, np.nan), np.full(4, np.nan)
    r = np.linspace(0, 0.16, 5)
    late = q.copy()
    late[:2] = nan4
    merged_p, merged_q = p.copy(), q.copy()
    merged_p[1::2], merged_q[::2] = nan3, nan4
    cases = {
        "2 one-part measurement(s) before the first whole pose (position and orientation both "
        "measured, 0.0667 s after": (p, late),
        "no measurement holds both a position and an orientation (3 position-only, "
        "3 orientation-only)": (merged_p, merged_q),
        "no measurement holds a valid position or orientation": (p * np.nan, q * np.nan),
    }
    for message, (pp, qq) in cases.items():
        with pytest.warns(TrajectoryWarning, match=re.escape(message)):
            pj.track(t, pp, qq, r)
    with warnings.catch_warnings():  # whole poses, or one part alone: nothing to say
        warnings.simplefilter("error")
        for pp, qq in ((p, q), (p * np.nan, q), (p, q * np.nan)):
            pj.track(t, pp, qq, r)


def test_quaternions_of_any_norm_in_float32(head):
    """Quaternions scaled by 1e-30 ... 1e30 give the unit quaternions' stream in float32 (a norm
    of 1e-19 made every output NaN, positions included: its square underflows). (The program
    of test_float32_stream_close_to_float64: same data shapes.)"""
    _, _, _, t, p, q = head
    r = np.linspace(t[0], t[-1], 300)
    P0, Q0 = (np.asarray(x) for x in pj.track(t, p, q, r, dtype=jnp.float32))
    for scale in (1e-30, 1e-19, 1e19, 1e30):
        P, Q = (np.asarray(x) for x in pj.track(t, p, q * scale, r, dtype=jnp.float32))
        np.testing.assert_allclose(P, P0, rtol=0, atol=1e-6, err_msg=str(scale))
        np.testing.assert_allclose(Q, Q0, rtol=0, atol=1e-6, err_msg=str(scale))


def test_config_values_the_stream_cannot_use_are_refused():
    """A horizon or stop time of 0 divides by zero (NaN at every frame instant / after every
    segment end); strings and NaN are refused too. Traced values are not checked (gradients
    through the config keep working)."""
    for kw in ({"horizon": 0.0}, {"horizon": -0.01}, {"stop_time": 0.0}, {"coast_time": -1.0},
               {"horizon": "0.03"}, {"lookahead": float("nan")}, {"adapt": float("inf")}):
        name = next(iter(kw))
        with pytest.raises(ValueError, match=f"TrackerConfig.{name} must be a finite number"):
            pj.TrackerConfig(**kw)
    g = jax.grad(lambda h: pj.TrackerConfig(horizon=h).horizon * 2.0)(0.03)
    assert float(g) == 2.0


def test_filter_config_values_that_give_nan_poses_are_refused():
    """Found by probing: NaN or non-positive noise in KalmanConfig / IMMConfig, a NaN switch
    rate or model log_q, log_q = 100 (exp overflows in float32) all gave 100 % NaN output
    silently; from_q(0) was a 'math domain error'. Arrays (sweeps) are checked elementwise;
    traced values are not checked."""
    from phjax.tracking import IMMConfig, KalmanConfig
    from phjax.tracking.models import ConstantVelocity

    cases = [(KalmanConfig, {"pos_meas_noise": 0.0}), (KalmanConfig, {"rot_process_noise": -1.0}),
             (KalmanConfig, {"pos_process_noise": float("nan")}),
             (KalmanConfig, {"init_rot_vel_std": np.array([1.0, 0.0])}),
             (IMMConfig, {"log_switch_rate": float("nan")}), (IMMConfig, {"rot_meas_noise": 0.0}),
             (ConstantVelocity, {"log_q": 100.0}), (ConstantVelocity, {"log_q": float("nan")})]
    for cls, kw in cases:
        with pytest.raises(ValueError, match=f"{cls.__name__}.{next(iter(kw))} must be a finite"):
            cls(**kw)
    with pytest.raises(ValueError, match="spectral density q must be"):
        ConstantVelocity.from_q(0.0)
    KalmanConfig(pos_meas_noise=np.array([0.005, 0.01]))  # a sweep of valid values
    g = jax.grad(lambda r: KalmanConfig(pos_meas_noise=r).pos_meas_noise * 3.0)(0.005)
    assert float(g) == 3.0


@pytest.mark.parametrize("fn", [pj.track, pj.reconstruct])
def test_track_and_reconstruct_under_jit_vmap_and_grad(head, fn):
    """Inside a transformation the recording is used as given (no host-side padding):
    ``jit(vmap(...))`` over four recordings gives the host path's result for each; ``jit(grad)``
    through it is finite and matches central differences (two of the four recordings). Before,
    every transformation ended in a TracerArrayConversionError. One compiled program per
    transformation (jit and vmap together, the gradient in one program)."""
    t, p, q, mt, mp, mq = head
    keep = np.isfinite(mp).all(-1) & np.isfinite(mq).all(-1)
    mt, mp, mq = mt[keep][:60], mp[keep][:60], mq[keep][:60]
    r = np.linspace(mt[0], mt[-1] + 0.05, 97)
    ref = [np.asarray(x) for x in fn(mt, mp, mq, r, dtype=jnp.float64)]
    h, x_axis = 1e-6, np.eye(3)[0]
    batch = np.stack([mp, mp + 0.01, mp + h * x_axis, mp - h * x_axis])
    P, Q = (np.asarray(a) for a in
            jax.jit(jax.vmap(lambda p_: fn(mt, p_, mq, r, dtype=jnp.float64)))(batch))
    np.testing.assert_allclose(P[0], ref[0], atol=1e-12)
    np.testing.assert_allclose(Q[0], ref[1], atol=1e-12)
    np.testing.assert_allclose(P[1], ref[0] + 0.01, atol=1e-9)

    def loss(x):
        return jnp.sum(fn(mt, jnp.asarray(mp).at[:, 0].add(x), mq, r,
                          dtype=jnp.float64)[0][:, 0] ** 2)

    g = float(jax.jit(jax.grad(loss))(0.0))
    central = (np.sum(P[2][:, 0] ** 2) - np.sum(P[3][:, 0] ** 2)) / (2 * h)
    assert np.isfinite(g) and g == pytest.approx(central, rel=1e-5)


def test_a_config_that_is_not_a_tracker_config_is_a_type_error():
    """A dict (e.g. a loaded JSON) ended in "'dict' object has no attribute 'imm'"."""
    t, p, q = [0.0, 0.1], np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1))
    for call in (lambda c: pj.track(t, p, q, [0.05], config=c),
                 lambda c: pj.reconstruct(t, p, q, [0.05], config=c),
                 lambda c: pj.TrackerStream(c)):
        with pytest.raises(TypeError, match="config must be a phjax.TrackerConfig .*config_from"):
            call({"horizon": 0.03})
