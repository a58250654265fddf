"""Tests for phjax.tracking.baselines: hold, One Euro (JAX and NumPy), linear/slerp and cubic
splines, the extrapolators' display-time prediction (``lookahead``) against NumPy loops."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from phjax.tracking.baselines import (
    alpha_beta,
    cubic_spline,
    double_exponential,
    hold,
    imm_extrapolation,
    kalman_extrapolation,
    linear_slerp,
    one_euro,
    one_euro_extrapolation,
    one_euro_numpy,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)
from phjax.tracking.imm import IMMConfig
from phjax.tracking.kalman import KalmanConfig, kalman_filter
from phjax.tracking.models import ConstantVelocity
from phjax.quaternion import quat_geodesic_distance, quat_to_matrix
from phjax.motion.resample import interpolate_poses

N, M = 40, 97  # fixed shapes so that jit compiles once per function


def _angle(a, b):
    return np.asarray(quat_geodesic_distance(jnp.asarray(a), jnp.asarray(b)))


def _stream(seed, n=N, drop=0.15):
    """Irregular noisy measurements with NaN rows, sign flips and an orientation-only row."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.06, n))
    p = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    r = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.1, size=(n, 3)), axis=0))
    q = r.as_quat()[:, [3, 0, 1, 2]]
    q[rng.random(n) < 0.3] *= -1
    lost = rng.random(n) < drop
    lost[0] = True  # the stream starts with a dropped frame
    p[lost] = np.nan
    q[lost] = np.nan
    p[n // 2] = np.nan  # orientation-only sample
    render = np.sort(rng.uniform(t[0] - 0.05, t[-1] + 0.05, M))
    return t, p, q, render


def _compress(t, x):
    ok = np.isfinite(x).all(1)
    return t[ok], x[ok]


# ------------------------------------------------------------------------------------------ hold


@settings(max_examples=10)
@given(st.integers(0, 10_000))
def test_hold_matches_bruteforce_and_is_causal(seed):
    t, p, q, r = _stream(seed)
    hp, hq = map(np.asarray, hold(t, p, q, r))
    for j, tau in enumerate(r):
        for x, out in ((p, hp), (q, hq)):
            ok = np.flatnonzero(np.isfinite(x).all(1) & (t <= tau))
            if ok.size == 0:
                assert np.isnan(out[j]).all()
            else:
                np.testing.assert_array_equal(out[j], x[ok[-1]])
    # perturbing measurements after t_cut leaves outputs at render times before t_cut unchanged
    cut = t[N // 3]
    p2, q2 = p.copy(), q.copy()
    p2[t > cut] += 1.0
    q2[t > cut] = q2[t > cut][:, [1, 0, 3, 2]]
    hp2, hq2 = map(np.asarray, hold(t, p2, q2, r))
    early = r < t[N // 3 + 1]
    np.testing.assert_array_equal(hp2[early], hp[early])
    np.testing.assert_array_equal(hq2[early], hq[early])
    assert not np.allclose(np.nan_to_num(hp2[~early]), np.nan_to_num(hp[~early]))


# ------------------------------------------------------------------------------------- One Euro


def test_one_euro_beta0_is_first_order_lowpass_on_a_step():
    dt, fc = 0.01, 2.0
    t = np.arange(N) * dt
    x = np.where(t >= 0.1, 1.0, 0.0)
    p = np.stack([x, -2 * x, 0 * x], -1)
    angle = 0.8 * x
    q = Rotation.from_rotvec(np.outer(angle, [0, 0, 1.0])).as_quat()[:, [3, 0, 1, 2]]
    alpha = 1 / (1 + 1 / (2 * np.pi * fc) / dt)
    ref = lfilter([alpha], [1, -(1 - alpha)], x, zi=[0.0])[0]  # y_k = a x_k + (1 - a) y_{k-1}
    k = np.arange(N)
    closed = np.where(t >= 0.1, 1 - (1 - alpha) ** (k - 9), 0.0)  # step at sample 10
    np.testing.assert_allclose(ref, closed, atol=1e-12)
    for fn in (one_euro, one_euro_numpy):
        fp, fq = map(np.asarray, fn(t, p, q, t, min_cutoff=fc, beta=0.0, d_cutoff=3.0))
        np.testing.assert_allclose(fp[:, 0], ref, atol=1e-12)
        np.testing.assert_allclose(fp[:, 1], -2 * ref, atol=1e-12)
        rv = Rotation.from_quat(fq[:, [1, 2, 3, 0]]).as_rotvec()
        np.testing.assert_allclose(rv[:, 2], 0.8 * ref, atol=1e-12)
        np.testing.assert_allclose(rv[:, :2], 0, atol=1e-12)


@settings(max_examples=10)
@given(st.integers(0, 10_000), st.floats(0.1, 5.0), st.floats(0.0, 2.0), st.floats(0.2, 5.0))
def test_one_euro_jax_equals_numpy_reference(seed, min_cutoff, beta, d_cutoff):
    t, p, q, r = _stream(seed)
    kw = dict(min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff)
    jp, jq = map(np.asarray, one_euro(t, p, q, r, **kw))
    npp, npq = one_euro_numpy(t, p, q, r, **kw)
    np.testing.assert_array_equal(np.isnan(jp), np.isnan(npp))
    np.testing.assert_array_equal(np.isnan(jq), np.isnan(npq))
    np.testing.assert_allclose(jp, npp, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(jq, npq, atol=1e-9, equal_nan=True)


def test_one_euro_skips_nan_rows_and_is_sign_invariant():
    t, p, q, r = _stream(11)
    kw = dict(min_cutoff=1.5, beta=0.7)
    fp, fq = map(np.asarray, one_euro(t, p, q, r, **kw))
    # same as running on the valid rows only (each channel separately)
    tp, pp = _compress(t, p)
    tq, qq = _compress(t, q)
    cp, _ = one_euro_numpy(tp, pp, np.tile([1.0, 0, 0, 0], (len(tp), 1)), r, **kw)
    _, cq = one_euro_numpy(tq, np.zeros((len(tq), 3)), qq, r, **kw)
    np.testing.assert_allclose(fp, cp, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(fq, cq, atol=1e-12, equal_nan=True)
    # q -> -q on any input row does not change the filtered rotation
    flip = np.where(np.random.default_rng(0).random(N) < 0.5, -1.0, 1.0)[:, None]
    _, fq2 = map(np.asarray, one_euro(t, p, q * flip, r, **kw))
    ok = np.isfinite(fq).all(1)
    np.testing.assert_array_equal(ok, np.isfinite(fq2).all(1))
    np.testing.assert_array_less(_angle(fq[ok], fq2[ok]), 1e-9)
    # causal: NaN before the first valid measurement
    assert np.isnan(fp[r < tp[0]]).all() and np.isfinite(fp[r >= tp[0]]).all()


def test_one_euro_is_differentiable_in_its_parameters_and_float32():
    t, p, q, r = _stream(5)

    def loss(params):
        fp, fq = one_euro(t, p, q, r, min_cutoff=params[0], beta=params[1], d_cutoff=params[2])
        return jnp.nansum(fp**2) + jnp.nansum(fq[:, 1:] ** 2)

    params = jnp.array([1.0, 0.5, 1.0])
    g = jax.grad(loss)(params)
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    eps = 1e-6
    fd = (loss(params.at[0].add(eps)) - loss(params.at[0].add(-eps))) / (2 * eps)
    assert float(g[0]) == pytest.approx(float(fd), rel=1e-5)

    f32 = [x.astype(np.float32) for x in (t, p, q, r)]
    fp32, fq32 = one_euro(*f32, min_cutoff=1.0, beta=0.5)
    assert fp32.dtype == jnp.float32 and fq32.dtype == jnp.float32
    fp64, _ = one_euro_numpy(*f32, min_cutoff=1.0, beta=0.5)
    np.testing.assert_allclose(fp32, fp64, atol=1e-4, equal_nan=True)


# ----------------------------------------------------------------------------- offline methods


def test_linear_slerp_is_interpolate_poses():
    t, p, q, r = _stream(2)
    a = linear_slerp(t, p, q, r, max_gap=0.1)
    b = interpolate_poses(t, p, q, r, max_gap=0.1)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_cubic_spline_reproduces_cubic_and_interpolates_rotations_smoothly():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.05, 0.2, 12))
    c = rng.normal(size=(4, 3))

    def cubic(s):
        return c[0] + np.outer(s, c[1]) + np.outer(s**2, c[2]) + np.outer(s**3, c[3])

    rv = np.cumsum(rng.normal(scale=0.3, size=(12, 3)), axis=0)
    q = Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]]
    q[::3] *= -1
    p = cubic(t)
    p[5] = np.nan  # skipped
    q[7] = np.nan
    r = np.linspace(t[0], t[-1], 2001)
    sp, sq = cubic_spline(t, p, q, r)
    np.testing.assert_allclose(sp, cubic(r), atol=1e-10)  # not-a-knot splines reproduce cubics
    kp, kq = cubic_spline(t, p, q, t)
    keep = np.isfinite(q).all(1)
    np.testing.assert_array_less(_angle(kq[keep], q[keep]), 1e-9)  # interpolates the knots
    # smooth: angular velocity has no jumps (C2 spline), consecutive steps change by O(h^2)
    rel = Rotation.from_quat(sq[1:, [1, 2, 3, 0]]) * Rotation.from_quat(sq[:-1, [1, 2, 3, 0]]).inv()
    w = rel.as_rotvec() / (r[1] - r[0])
    assert np.abs(np.diff(w, axis=0)).max() < 0.05 * np.abs(w).max()
    assert np.all(np.sum(sq[1:] * sq[:-1], 1) > 0)  # hemisphere-continuous output
    # clamped outside the range, NaN without data, constant with a single sample
    ep, eq = cubic_spline(t, p, q, [t[0] - 1, t[-1] + 1])
    np.testing.assert_allclose(ep, p[[0, -1]], atol=1e-12)
    op, oq = cubic_spline(t, np.full_like(p, np.nan), q, r[:5])
    assert np.isnan(op).all() and np.isfinite(oq).all()
    one = np.full_like(p, np.nan)
    one[3] = p[3]
    np.testing.assert_allclose(cubic_spline(t, one, q, r[:4])[0], np.tile(p[3], (4, 1)))


def test_quaternion_order_conversions():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_array_equal(xyzw_to_wxyz(wxyz_to_xyzw(q)), q)
    np.testing.assert_array_equal(wxyz_to_xyzw(xyzw_to_wxyz(q)), q)
    np.testing.assert_array_equal(wxyz_to_xyzw(jnp.asarray(q)), wxyz_to_xyzw(q))
    m_scipy = Rotation.from_quat(wxyz_to_xyzw(q)).as_matrix()
    np.testing.assert_allclose(np.asarray(quat_to_matrix(q)), m_scipy, atol=1e-12)
    back = xyzw_to_wxyz(Rotation.from_matrix(m_scipy).as_quat())  # same rotation, sign may differ
    back *= np.sign(np.sum(back * q, axis=1, keepdims=True))
    np.testing.assert_allclose(back, q, atol=1e-12)


# ---------------------------------------------------------------------------- common interface


def _all_methods():
    return {
        "hold": hold,
        "one_euro": lambda *a: one_euro(*a, min_cutoff=1.0, beta=0.3),
        "one_euro_numpy": lambda *a: one_euro_numpy(*a, min_cutoff=1.0, beta=0.3),
        "linear_slerp": linear_slerp,
        "cubic_spline": cubic_spline,
    }


@pytest.mark.parametrize("name", list(_all_methods()))
def test_common_interface_and_sign_flips(name):
    fn = _all_methods()[name]
    t, p, q, r = _stream(21)
    out_p, out_q = map(np.asarray, fn(t, p, q, r))
    assert out_p.shape == (M, 3) and out_q.shape == (M, 4)
    causal = name in ("hold", "one_euro", "one_euro_numpy")
    tp0 = t[np.isfinite(p).all(1)][0]
    assert np.isnan(out_p[r < tp0]).all() == causal or not np.any(r < tp0)
    assert np.isfinite(out_p[r >= tp0]).all() and np.isfinite(out_q[r >= tp0]).all()
    np.testing.assert_allclose(np.linalg.norm(out_q[r >= tp0], axis=1), 1, atol=1e-9)
    # q -> -q input flips leave every output rotation unchanged
    flip = np.where(np.random.default_rng(1).random(N) < 0.5, -1.0, 1.0)[:, None]
    _, out_q2 = map(np.asarray, fn(t, p, q * flip, r))
    ok = np.isfinite(out_q).all(1)
    np.testing.assert_array_less(_angle(out_q[ok], out_q2[ok]), 1e-7)


# ---------------------------------------------------------------- display-time prediction


def _np_plus_minus(rot: bool):
    """Independent (scipy) group operations of one channel: ``plus(x, d)``, ``minus(z, x)``."""
    if not rot:
        return (lambda x, d: x + d), (lambda z, x: z - x)

    def R(q):
        return Rotation.from_quat(wxyz_to_xyzw(np.asarray(q)))

    return ((lambda q, d: xyzw_to_wxyz((Rotation.from_rotvec(d) * R(q)).as_quat())),
            (lambda z, q: (R(z) * R(q).inv()).as_rotvec()))


def _np_extrapolate(t, rows, render, lookahead, rot):
    """``plus(x_i, v_i (tau + lookahead - t_i))`` from the latest valid row ``i`` with
    ``t_i <= tau`` (rows: per measurement ``(valid, x, v)``), NaN before the first; a loop."""
    plus, _ = _np_plus_minus(rot)
    out = np.full((len(render), 4 if rot else 3), np.nan)
    for j, tau in enumerate(render):
        done = [i for i in range(len(t)) if t[i] <= tau and rows[i][0]]
        if done:
            i = done[-1]
            out[j] = plus(rows[i][1], rows[i][2] * (tau + lookahead - t[i]))
    return out


def _np_alpha_beta_rows(t, z, alpha, rot):
    """Alpha-beta filter states after every measurement, a plain loop (Benedict-Bordner beta)."""
    plus, minus = _np_plus_minus(rot)
    beta = alpha**2 / (2 - alpha)
    rows, c, x, v, tp = [], 0, None, None, None
    for i in range(len(t)):
        ok = np.all(np.isfinite(z[i]))
        if ok:
            zi = z[i] / np.linalg.norm(z[i]) if rot else z[i]
            if c == 0:
                x, v = zi, np.zeros(3)
            elif c == 1:
                x, v = zi, minus(zi, x) / (t[i] - tp)
            else:
                xp = plus(x, v * (t[i] - tp))
                r = minus(zi, xp)
                x, v = plus(xp, alpha * r), v + beta * r / (t[i] - tp)
            c, tp = c + 1, t[i]
        rows.append((ok, x, v))
    return rows


def _np_one_euro_rows(t, z, min_cutoff, beta, d_cutoff, rot):
    """One Euro states (estimate and its filtered derivative) after every measurement, a loop."""
    plus, minus = _np_plus_minus(rot)

    def alpha(te, fc):
        return 2 * np.pi * fc * te / (2 * np.pi * fc * te + 1)

    rows, x, dx, tp = [], None, None, None
    for i in range(len(t)):
        ok = np.all(np.isfinite(z[i]))
        if ok:
            zi = z[i] / np.linalg.norm(z[i]) if rot else z[i]
            if x is None:
                x, dx = zi, np.zeros(3)
            else:
                te = t[i] - tp
                e = minus(zi, x)
                dx = dx + alpha(te, d_cutoff) * (e / te - dx)
                x = plus(x, alpha(te, min_cutoff + beta * np.linalg.norm(dx)) * e)
            tp = t[i]
        rows.append((ok, x, dx))
    return rows


def _check_lookahead(out, ref_p, ref_q):
    out_p, out_q = map(np.asarray, out)
    np.testing.assert_array_equal(np.isnan(out_p), np.isnan(ref_p))
    np.testing.assert_allclose(out_p, ref_p, atol=1e-10)
    ok = np.isfinite(ref_q).all(1)
    np.testing.assert_array_equal(np.isfinite(out_q).all(1), ok)
    assert _angle(out_q[ok], ref_q[ok]).max() < 1e-9


@pytest.mark.parametrize("lookahead", [0.0, 0.02, 0.05])
def test_alpha_beta_lookahead_equals_numpy_loop(lookahead):
    t, p, q, r = _stream(31)
    out = alpha_beta(t, p, q, r, alpha=0.4, lookahead=lookahead)
    ref = [_np_extrapolate(t, _np_alpha_beta_rows(t, x, 0.4, rot), r, lookahead, rot)
           for x, rot in ((p, False), (q, True))]
    _check_lookahead(out, *ref)


def _np_desp(t, z, a, render, lookahead, alpha_beta_start=True):
    """LaViola's DESP (2003) as printed, on a regular frame clock (period ``t[1] - t[0]``):
    ``S1 = a z + (1 - a) S1``, ``S2 = a S1 + (1 - a) S2`` per frame, the render time ``tau``
    shows ``(2 + a f / (1 - a)) S1 - (1 + a f / (1 - a)) S2`` with ``f`` the frames from the
    latest frame to ``tau + lookahead``. Frame 0 sets ``S1 = S2 = z0``; with
    ``alpha_beta_start`` frame 1 sets the state that the alpha-beta start (velocity from the
    first two frames) stands for, ``S1 = z1 - b (1 - a) / a``, ``S2 = S1 - b (1 - a) / a`` with
    ``b = z1 - z0`` per frame, else LaViola's recursion runs from frame 1 on."""
    period = t[1] - t[0]
    b = z[1] - z[0]
    s0 = (z[1] - b * (1 - a) / a, z[1] - 2 * b * (1 - a) / a) if alpha_beta_start else None
    s1 = s2 = z[0]
    states = [(s1, s2)]
    for i in range(1, len(t)):
        if i == 1 and s0 is not None:
            s1, s2 = s0
        else:
            s1 = a * z[i] + (1 - a) * s1
            s2 = a * s1 + (1 - a) * s2
        states.append((s1, s2))
    out = np.full((len(render), z.shape[1]), np.nan)
    for j, tau in enumerate(render):
        k = np.searchsorted(t, tau, side="right") - 1
        if k >= 0:
            g = a * (tau + lookahead - t[k]) / period / (1 - a)
            out[j] = (2 + g) * states[k][0] - (1 + g) * states[k][1]
    return out


@pytest.mark.parametrize("a,lookahead", [(0.15, 0.0), (0.4, 0.02), (0.7, 0.05)])
def test_double_exponential_is_laviolas_desp(a, lookahead):
    """Positions against a loop of LaViola's DESP formulas (30 Hz frames, render times between
    and on frames), started from the state that the alpha-beta start stands for
    (:func:`_np_desp`). From LaViola's own start (``S1 = S2 = z0``) the difference decays as
    ``(1 - a)^k``."""
    rng = np.random.default_rng(5)
    n = 60
    t = 0.3 + np.arange(n) / 30.0
    p = np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0) + rng.normal(scale=0.002,
                                                                             size=(n, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    render = np.sort(np.concatenate([t[::3], rng.uniform(t[0] - 0.05, t[-1] + 0.05, M - 20)]))
    out = np.asarray(double_exponential(t, p, q, render, alpha=a, lookahead=lookahead)[0])
    ref = _np_desp(t, p, a, render, lookahead)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)
    # LaViola's start: the difference shrinks as (1 - a)^k (x 50 margin on its first value)
    own = _np_desp(t, p, a, render, lookahead, alpha_beta_start=False)
    k = np.clip(np.searchsorted(t, render, side="right") - 1, 0, None)
    late = render >= t[1]
    diff = np.linalg.norm(out - own, axis=1)[late]
    bound = 50 * np.linalg.norm(p[1] - p[0]) * (2 + a * 2 / (1 - a)) * (1 - a) ** k[late]
    assert np.all(diff <= bound + 1e-12)


def test_double_exponential_orientation_is_laviolas_to_first_order():
    """Orientation: alpha-beta on SO(3) with DESP's gains against LaViola's component-wise
    DESP of the quaternions (normalised) on a slow rotation, 1 deg per frame at 30 Hz, the same
    start: they agree to a small fraction of the rotation of one frame (measured 2.3e-3 deg
    in float64; 6.5e-3 deg at 2 deg per frame, 0.05 deg at 4 deg; bound 5e-3 deg)."""
    n, a = 60, 0.4
    t = np.arange(n) / 30.0
    rng = np.random.default_rng(6)
    rv = np.cumsum(np.radians(1.0) * np.tile([0.3, 0.8, 0.5], (n, 1)) / np.sqrt(0.98), axis=0)
    q = Rotation.from_rotvec(rv + rng.normal(scale=np.radians(0.05), size=(n, 3))).as_quat()
    q = q[:, [3, 0, 1, 2]]
    p = np.zeros((n, 3))
    render = t[2:] + 0.5 / 120
    out = np.asarray(double_exponential(t, p, q, render, alpha=a)[1])
    # the alpha-beta start in quaternion components: level q1, trend q1 - q0 per frame
    ref = _np_desp(t, q, a, render, 0.0)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    err = np.degrees(_angle(out, ref))
    assert err.max() < 5e-3, err.max()


def test_double_exponential_refuses_a_gain_outside_0_1():
    t, p, q, r = _stream(34)
    for a in (0.0, 1.0, -0.2):
        with pytest.raises(ValueError, match="alpha must be in"):
            double_exponential(t, p, q, r, alpha=a)


@pytest.mark.parametrize("lookahead", [0.0, 0.02, 0.05])
def test_one_euro_extrapolation_lookahead_equals_numpy_loop(lookahead):
    t, p, q, r = _stream(32)
    kw = {"min_cutoff": 0.8, "beta": 3.0, "d_cutoff": 1.5}
    out = one_euro_extrapolation(t, p, q, r, lookahead=lookahead, **kw)
    ref = [_np_extrapolate(t, _np_one_euro_rows(t, x, rot=rot, **kw), r, lookahead, rot)
           for x, rot in ((p, False), (q, True))]
    _check_lookahead(out, *ref)


@pytest.mark.parametrize("lookahead", [0.0, 0.02, 0.05])
def test_kalman_extrapolation_lookahead_predicts_from_the_latest_filter_state(lookahead):
    """The filter's states (``kalman_filter``), extrapolated by a NumPy loop to ``tau +
    lookahead`` from the latest measurement row at or before ``tau``; the single-model IMM
    extrapolation gives the same."""
    t, p, q, r = _stream(33)
    cfg = KalmanConfig(pos_process_noise=0.1, rot_process_noise=1.0)
    st_ = kalman_filter(cfg, jnp.asarray(t), jnp.asarray(p), jnp.asarray(q))[0]
    ts, x, qs, ws, init = (np.asarray(a) for a in (st_.t, st_.x, st_.q, st_.w, st_.initialized))
    pos_rows = [(init[i], x[i, :3], x[i, 3:6]) for i in range(len(t))]
    rot_rows = [(init[i], qs[i], ws[i]) for i in range(len(t))]
    # the states' own times (a NaN row predicts the state to its time)
    ref = [_np_extrapolate(ts, rows, r, lookahead, rot)
           for rows, rot in ((pos_rows, False), (rot_rows, True))]
    _check_lookahead(kalman_extrapolation(t, p, q, r, config=cfg, lookahead=lookahead), *ref)
    icfg = IMMConfig(position_models=(ConstantVelocity.from_q(0.1),),
                     rotation_models=(ConstantVelocity.from_q(1.0),))
    _check_lookahead(imm_extrapolation(t, p, q, r, config=icfg, lookahead=lookahead), *ref)


@pytest.mark.parametrize("name", ["kalman", "imm", "alpha_beta", "desp", "one_euro_x"])
def test_lookahead_is_causal_and_shifts_the_prediction(name):
    """Measurements after ``tau`` never change the pose shown at ``tau``, whatever the
    lookahead; between two frames a lookahead ``L`` at ``tau`` equals no lookahead at
    ``tau + L`` (the same state, predicted to the same time)."""
    fn = {"kalman": kalman_extrapolation, "imm": imm_extrapolation,
          "alpha_beta": lambda *a, **k: alpha_beta(*a, alpha=0.5, **k),
          "desp": lambda *a, **k: double_exponential(*a, alpha=0.4, **k),
          "one_euro_x": lambda *a, **k: one_euro_extrapolation(*a, min_cutoff=1.0, beta=1.0, **k)
          }[name]
    t, p, q, r = _stream(34, drop=0.0)
    lookahead = 0.05
    cut = t[N // 2]
    p2, q2 = p.copy(), q.copy()
    p2[t > cut] += 1.0
    q2[t > cut] = Rotation.random((t > cut).sum(), random_state=0).as_quat()[:, [3, 0, 1, 2]]
    a = [np.asarray(x) for x in fn(t, p, q, r, lookahead=lookahead)]
    b = [np.asarray(x) for x in fn(t, p2, q2, r, lookahead=lookahead)]
    before = r <= cut
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x[before], y[before])
    # render times with no frame in (tau, tau + L]: same as lookahead 0 at tau + L
    k0 = np.searchsorted(t, r, side="right")
    k1 = np.searchsorted(t, r + lookahead, side="right")
    same = (k0 == k1) & (k0 > 2)
    assert same.sum() > 5
    c = [np.asarray(x) for x in fn(t, p, q, r[same] + lookahead)]
    np.testing.assert_allclose(a[0][same], c[0], atol=1e-10)
    assert _angle(a[1][same], c[1]).max() < 1e-9
    assert np.abs(a[0][same] - np.asarray(fn(t, p, q, r[same])[0])).max() > 1e-4  # it moved


def test_jax_baselines_share_one_program_per_size_class_and_equal_unpadded():
    """hold, One Euro, alpha-beta and One Euro + extrapolation pad eager calls to size
    classes: a recording of another length in the class compiles nothing (JAX's compile
    events) and each output equals the jitted function on the unpadded arrays (float64, exact
    NaN pattern, 1e-12), render times before the first and after the last frame included."""
    import jax.monitoring

    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.02, 0.05, 150))
    p = np.cumsum(rng.normal(0, 0.01, (150, 3)), 0)
    q = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (150, 3)), 0)).as_quat()[:, [3, 0, 1, 2]]
    p[rng.random(150) < 0.2] = np.nan  # dropouts, separately per channel
    q[rng.random(150) < 0.2] = np.nan
    methods = [(hold, {}), (one_euro, {"min_cutoff": 0.7, "beta": 0.2}),
               (alpha_beta, {"alpha": 0.4, "lookahead": 0.02}),
               (one_euro_extrapolation, {"min_cutoff": 1.5, "lookahead": 0.03})]
    compiles = []

    def on_duration(event, duration, fun_name="", **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(fun_name)

    def render(n):
        return np.linspace(t[0] - 0.1, t[n - 1] + 0.2, 2 * n + 11)

    for fn, kw in methods:  # compile the class (70 frames, 151 render times; 120 and 251 next)
        fn(t[:70], p[:70], q[:70], render(70), **kw)
    jax.monitoring.register_event_duration_secs_listener(on_duration)
    try:
        got = [fn(t[:120], p[:120], q[:120], render(120), **kw) for fn, kw in methods]
    finally:
        jax.monitoring.unregister_event_duration_listener(on_duration)
    assert compiles == []
    for (fn, kw), out in zip(methods, got):
        ref = fn.__wrapped__(t[:120], p[:120], q[:120], render(120), **kw)  # the jitted function
        for a, b in zip(out, ref):
            a, b = np.asarray(a), np.asarray(b)
            assert a.shape == b.shape and np.isnan(a).any()  # before the first frame
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_epoch_times_in_float32_equal_relative_times():
    """Found by probing: with epoch times (1.7e9 s) in the default float32, alpha-beta, One Euro
    and hold were 180 mm / 120 degrees off the same recording with relative times (float32
    spacing 128 s there); the Kalman and IMM extrapolations were already exact. Every baseline
    now runs on times relative to the first one."""
    import phjax as pj

    t, p, q = pj.synthetic_head_motion(duration=3.0, seed=3)
    mt, mp, mq = (np.asarray(x, np.float64) for x in pj.simulate_measurements(0, t, p, q))
    mt = mt - mt[0]
    r = np.arange(0.05, mt[-1], 1 / 120)
    for fn in (alpha_beta, one_euro, one_euro_extrapolation, hold):
        with jax.enable_x64(False):  # the default: float64 NumPy times become float32
            a = [np.asarray(x, np.float64) for x in fn(mt, mp, mq, r)]
            b = [np.asarray(x, np.float64) for x in fn(mt + 1.7e9, mp, mq, r + 1.7e9)]
        assert np.abs(a[0] - b[0]).max() < 1e-4, fn.__name__
        assert np.degrees(np.asarray(quat_geodesic_distance(a[1], b[1]))).max() < 0.05, fn
