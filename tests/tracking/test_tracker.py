"""The streaming tracker, the batch track/reconstruct API and the C1 orientation curves."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import phjax as pj
from phjax.motion import simulate
from phjax.tracking import tracker

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
        g = jax.grad(lambda w: jnp.sum(pj.quaternion_hermite(q, q1, w, w, 0.1).rotation(0.3)))(jnp.asarray(w))
        assert np.all(np.isfinite(np.asarray(g)))


# ------------------------------------------------------------------------------ stream
def test_stream_is_c1_across_camera_frames(head):
    _, _, _, mt, mp, mq = head
    ok = np.isfinite(mp).all(-1)
    tb = mt[ok][2:-2]
    r = np.sort(np.concatenate([tb - 2 * EPS, tb - EPS, tb, tb + EPS]))
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    P, Q = P.reshape(-1, 4, 3), Q.reshape(-1, 4, 4)
    speed = np.linalg.norm((P[:, 3] - P[:, 2]) / EPS, axis=-1)
    vb, va = (P[:, 1] - P[:, 0]) / EPS, (P[:, 3] - P[:, 2]) / EPS
    assert np.abs(P[:, 2] - P[:, 1]).max() < 5 * EPS * (1 + speed.max())
    # velocity continuous up to the O(eps * acceleration) of one-sided differences
    assert np.linalg.norm(va - vb, axis=-1).max() < 1e-3 * (1 + speed.max())
    wb = pj.quat_geodesic_distance(Q[:, 0], Q[:, 1]) / EPS
    wa = pj.quat_geodesic_distance(Q[:, 2], Q[:, 3]) / EPS
    assert np.abs(np.asarray(wa - wb)).max() < 1e-3 * (1 + float(np.max(wa)))
    assert np.asarray(pj.quat_geodesic_distance(Q[:, 1], Q[:, 2])).max() < 5 * EPS * (1 + float(np.max(wa)))


def test_correction_decays_critically_damped(head):
    """After a frame the rendered-minus-predicted pose follows (c0 (1 + s) + c0' t) exp(-s),
    s = t / (horizon / 5), at the knot (0.4 horizon), is C1 there, and is 0 at the horizon."""
    _, _, _, mt, mp, mq = head
    cfg = pj.TrackerConfig(imm=None)  # the single-model filter: predict_pose below
    h = cfg.horizon
    T, t1 = h / 5, 0.4 * h
    state = pj.tracker_init(cfg, 0.0, jnp.float64)
    checked = 0
    for k in range(30):
        t = mt[k] - mt[0]
        p_r, v_r, q_r, w_r = (np.asarray(x) for x in tracker._evaluate(cfg, state, t))
        state = pj.tracker_update(cfg, state, t, mp[k], mq[k])
        if k < 3 or not np.isfinite(mp[k]).all() or not np.isfinite(mq[k]).all():
            continue
        pk, qk, vk, wk = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t))
        p1, q1, v1, w1 = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + t1))
        pT, qT, _, _ = (np.asarray(x) for x in pj.predict_pose(cfg.kalman, state.filter, t + h))
        e = np.exp(-2.0)
        want = p1 + 3 * e * (p_r - pk) + 2 * e * T * (v_r - vk)
        p_m, v_m, q_m, w_m = (np.asarray(x) for x in tracker._evaluate(cfg, state, t + t1))
        np.testing.assert_allclose(p_m, want, atol=1e-12)
        np.testing.assert_allclose(v_m, v1 + (-2 * e / T) * (p_r - pk) - e * (v_r - vk), atol=1e-9)
        dth = np.asarray(pj.quat_to_rotvec(pj.quat_mul(q_r, pj.quat_conj(qk))))
        q_want = np.asarray(pj.quat_mul(pj.quat_from_rotvec(3 * e * dth + 2 * e * T * (w_r - wk)), q1))
        assert float(pj.quat_geodesic_distance(q_m, q_want)) < 1e-10
        # C1 across the knot between the two pieces
        eps = 1e-7
        pa, va, qa, wa = (np.asarray(x) for x in tracker._evaluate(cfg, state, t + t1 - eps))
        pb, vb, qb, wb = (np.asarray(x) for x in tracker._evaluate(cfg, state, t + t1 + eps))
        np.testing.assert_allclose(va, vb, atol=1e-4 * (1 + np.abs(va).max()))
        np.testing.assert_allclose(wa, wb, atol=1e-4 * (1 + np.abs(wa).max()))
        np.testing.assert_allclose(pb - pa, 2 * eps * va, atol=1e-9)
        # the prediction is reached at the horizon
        p_h, _, q_h, _ = (np.asarray(x) for x in tracker._evaluate(cfg, state, t + h))
        np.testing.assert_allclose(p_h, pT, atol=1e-12)
        assert float(pj.quat_geodesic_distance(q_h, qT)) < 1e-10
        checked += 1
    assert checked > 20


def test_track_equals_streaming_loop(head):
    _, _, _, mt, mp, mq = head
    mt, mp, mq = mt[:40], mp[:40], mq[:40]
    r = np.linspace(mt[0], mt[-1] + 0.2, 173)
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    cfg = pj.TrackerConfig()
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
    # long after the last frame the pose has come to rest (bounded coast)
    tail = r > mt[-1] + 1.0
    assert np.abs(np.diff(P[tail], axis=0)).max() < 1e-6
    assert np.abs(P[tail][-1] - mp[np.isfinite(mp).all(-1)][-1]).max() < 0.2


def test_orientation_only_input(head):
    _, _, _, mt, _, mq = head
    r = np.linspace(mt[0], mt[-1], 200)
    P, Q = pj.track(mt, np.full((len(mt), 3), np.nan), mq, r)
    assert np.all(np.isnan(np.asarray(P)))
    assert np.all(np.isfinite(np.asarray(Q)))


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
                # no jumps: consecutive render samples stay close (bounded speed)
                step = np.linalg.norm(np.diff(P[after], axis=0), axis=-1)
                assert step.max() < 1.0


def test_q_sign_flips_do_not_change_the_stream(head):
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0], mt[-1], 300)
    flips = np.where(np.arange(len(mt)) % 3 == 0, -1.0, 1.0)[:, None]
    P, Q = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    P2, Q2 = (np.asarray(x) for x in pj.track(mt, mp, mq * flips, r, dtype=jnp.float64))
    np.testing.assert_allclose(P2, P, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(Q2 * Q, -1)), 1, atol=1e-9)


def test_gradient_through_track_wrt_config(head):
    _, _, _, mt, mp, mq = head
    mt, mp, mq = mt[:30] - mt[0], mp[:30], mq[:30]
    r = jnp.linspace(0.05, mt[-1], 60)
    gt = np.asarray(pj.track(mt, mp, mq, np.asarray(r), dtype=jnp.float64)[0]) + 0.001

    def loss(cfg):
        P, _ = tracker._track_core(cfg, *(jnp.asarray(x) for x in (mt, mp, mq)), r)
        return jnp.mean((P - gt) ** 2)

    cfg = pj.TrackerConfig(horizon=0.05)
    g = jax.grad(loss)(cfg)
    leaves = jax.tree.leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    assert abs(float(g.horizon)) > 0
    # horizon derivative against central finite differences
    h = 1e-6
    num = (loss(pj.TrackerConfig(horizon=0.05 + h)) - loss(pj.TrackerConfig(horizon=0.05 - h))) / (2 * h)
    np.testing.assert_allclose(float(g.horizon), float(num), rtol=1e-4)


def test_float32_stream_finite(head):
    _, _, _, mt, mp, mq = head
    r = np.linspace(mt[0], mt[-1], 300)
    P, Q = pj.track(mt, mp, mq, r, dtype=jnp.float32)
    P64, _ = pj.track(mt, mp, mq, r, dtype=jnp.float64)
    assert P.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(P)))
    assert np.abs(np.asarray(P, np.float64) - np.asarray(P64)).max() < 1e-3


def test_offline_reconstruction_is_smooth_and_accurate(head):
    from phjax.tracking import baselines
    from phjax.evaluation import metrics
    from phjax.motion import resample

    t, p, q, mt, mp, mq = head
    r = np.arange(mt[0] + 0.1, mt[-1] - 0.1, 1 / 120)
    gp, gq = (np.asarray(x) for x in resample.interpolate_poses(t, p, q, r))
    P, Q = (np.asarray(x) for x in pj.reconstruct(mt, mp, mq, r, dtype=jnp.float64))
    Pc, Qc = baselines.cubic_spline(mt, mp, mq, r)
    assert metrics.rms_jerk_position(r, P).value < metrics.rms_jerk_position(r, Pc).value
    assert metrics.position_rmse(P, gp).value <= 1.05 * metrics.position_rmse(Pc, gp).value
    assert metrics.rotation_rmse_deg(Q, gq).value <= 1.05 * metrics.rotation_rmse_deg(Qc, gq).value


def test_bad_input_messages():
    with pytest.raises(ValueError, match="expected times"):
        pj.track(np.zeros(3), np.zeros((3, 2)), np.zeros((3, 4)), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        pj.track(np.array([0.0, np.nan]), np.zeros((2, 3)), np.ones((2, 4)), np.zeros(2))


def test_compiled_shapes_are_bounded(head, monkeypatch):
    """Each recording length compiles the scan; at most ``_MAX_COMPILED_SHAPES`` stay compiled,
    so many lengths in one process do not exhaust its memory mappings (XLA:CPU maps ~1200
    regions per compiled stream; Linux allows 65530), and results do not change."""
    from conftest import mapping_count

    _, _, _, mt, mp, mq = head
    monkeypatch.setattr(tracker, "_MAX_COMPILED_SHAPES", 2)
    tracker._track_core.clear_cache()
    tracker._COMPILED_KEYS.pop(tracker._track_core, None)

    r = np.linspace(mt[0], mt[10], 50)
    outs, counts = [], []
    for n in (12, 13, 14, 12):
        outs.append(np.asarray(pj.track(mt[:n], mp[:n], mq[:n], r, dtype=jnp.float64)[0]))
        counts.append(mapping_count())
        assert tracker._track_core._cache_size() <= 2
    np.testing.assert_array_equal(outs[3], outs[0])  # recompiled after eviction: same result
    if counts[0]:  # Linux: /proc/self/maps exists
        assert counts[1] > counts[0] and counts[2] < counts[1]  # the third shape evicted two
