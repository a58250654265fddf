"""Review tests of phjax.tracking.baselines: repeated timestamps (alpha-beta, snapshot
interpolation's default delay), snapshot interpolation against a NumPy loop, One Euro against
the published algorithm written as in the paper (one scalar filter per coordinate)."""

from __future__ import annotations

import math
import warnings

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from phjax.quaternion import quat_geodesic_distance
from phjax.tracking.baselines import alpha_beta, one_euro, snapshot_interpolation
from phjax.tracking.kalman import KalmanConfig, kalman_filter

N, M = 40, 97  # the sizes of test_baselines.py (same size classes: no new compilation)


def _stream(seed, n=N, drop=0.15):
    """Irregular noisy measurements with lost frames (the first one), q / -q flips and an
    orientation-only frame, and render times around them."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.06, n))
    p = np.cumsum(rng.normal(scale=0.02, size=(n, 3)), axis=0)
    rv = np.cumsum(rng.normal(scale=0.1, size=(n, 3)), axis=0)
    q = Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]]
    q *= np.where(rng.random(n) < 0.3, -1.0, 1.0)[:, None]
    lost = rng.random(n) < drop
    lost[0] = True
    p[lost], q[lost] = np.nan, np.nan
    p[n // 2] = np.nan
    return t, p, q, np.sort(rng.uniform(t[0] - 0.05, t[-1] + 0.05, M))


def _angle(a, b):
    return np.asarray(quat_geodesic_distance(jnp.asarray(a), jnp.asarray(b)))


def test_alpha_beta_ignores_repeated_timestamps():
    """Found in review: a measurement at the time of the previous one (``Te = 0``) was applied:
    at the second sample it set the velocity to 0 (no two-point start), later it pulled the
    estimate a second time (gain ``1 - (1 - alpha)^2``): 50 mm / 15.4 degrees off the same
    stream without the repeats here (24 mm / 9.6 degrees with exact repeats). Now skipped, as in ``one_euro`` (the first is kept)."""
    t, p, q, r = _stream(31)
    whole = np.flatnonzero(np.isfinite(p).all(1) & np.isfinite(q).all(1))
    rep = whole[[0, 1, 10, 20]]  # the first valid frame (a repeat: second sample), later ones
    idx = np.sort(np.concatenate([np.arange(len(t)), rep]))
    extra = np.zeros(len(idx), bool)
    extra[1:] = idx[1:] == idx[:-1]  # the inserted repeats (after their original)
    td, pd, qd = t[idx], p[idx].copy(), q[idx].copy()
    rot = Rotation.from_rotvec([0.0, 0.2, 0.1])
    pd[extra] += [0.05, -0.03, 0.02]  # other values at the same time
    qd[extra] = (rot * Rotation.from_quat(qd[extra][:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    for lookahead in (0.0, 0.03):
        a = [np.asarray(x) for x in alpha_beta(td, pd, qd, r, alpha=0.4, lookahead=lookahead)]
        b = [np.asarray(x) for x in alpha_beta(t, p, q, r, alpha=0.4, lookahead=lookahead)]
        np.testing.assert_array_equal(np.isnan(a[0]), np.isnan(b[0]))
        np.testing.assert_allclose(a[0], b[0], atol=1e-12)
        ok = np.isfinite(b[1]).all(1)
        np.testing.assert_array_equal(np.isfinite(a[1]).all(1), ok)
        assert _angle(a[1][ok], b[1][ok]).max() < 1e-9


def _np_snapshot(t, p, q, r, cfg, delay):
    """Snapshot interpolation as a loop: the filter's states (``kalman_filter``) interpolated
    (linear / slerp) at ``tau - delay`` clamped to ``[first filtered frame, latest frame <=
    tau]``; NaN before the first filtered frame."""
    st = kalman_filter(cfg, jnp.asarray(t - t[0]), jnp.asarray(p), jnp.asarray(q))[0]
    x, qs, init = (np.asarray(a) for a in (st.x, st.q, st.initialized))
    first = int(np.argmax(init))
    out_p, out_q = np.full((len(r), 3), np.nan), np.full((len(r), 4), np.nan)
    for j, tau in enumerate(r):
        k = np.searchsorted(t, tau, side="right") - 1
        if k < 0 or tau < t[first]:
            continue
        s = max(min(tau - delay, t[k]), t[first])
        i = np.searchsorted(t, s, side="right") - 1
        if i == len(t) - 1 or t[i] == s:
            out_p[j], out_q[j] = x[i, :3], qs[i]
            continue
        w = (s - t[i]) / (t[i + 1] - t[i])
        out_p[j] = (1 - w) * x[i, :3] + w * x[i + 1, :3]
        slerp = Slerp([0.0, 1.0], Rotation.from_quat(qs[[i, i + 1]][:, [1, 2, 3, 0]]))
        out_q[j] = slerp([w]).as_quat()[0][[3, 0, 1, 2]]
    return out_p, out_q


def test_snapshot_interpolation_equals_numpy_loop_is_causal_and_default_delay():
    """Snapshot interpolation (untested before) against a loop, render times at the frames
    included; perturbing later frames changes nothing earlier. Found in review: the default
    delay was the median of the raw time differences, 0 with every frame repeated (67 mm /
    16 degrees off); now the median interval of the distinct times (the filter drops repeats)."""
    t, p, q, r = _stream(40)
    t, p, q = t[:30], p[:30], q[:30]
    r = np.sort(np.concatenate([r[:67], t]))  # 97 render times, 30 of them at the frames
    cfg = KalmanConfig(pos_process_noise=0.1, rot_process_noise=1.0)
    out = [np.asarray(x) for x in snapshot_interpolation(t, p, q, r, config=cfg, delay=0.03)]
    ref = _np_snapshot(t, p, q, r, cfg, 0.03)
    for a, b in zip(out, ref):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(out[0], ref[0], atol=1e-12)
    ok = np.isfinite(ref[1]).all(1)
    assert ok.sum() > 50 and _angle(out[1][ok], ref[1][ok]).max() < 1e-9
    # causal
    cut = t[15]
    p2, q2 = p.copy(), q.copy()
    p2[t > cut] += 1.0
    q2[t > cut] = Rotation.random((t > cut).sum(), random_state=0).as_quat()[:, [3, 0, 1, 2]]
    out2 = [np.asarray(x) for x in snapshot_interpolation(t, p2, q2, r, config=cfg, delay=0.03)]
    for a, b in zip(out, out2):
        np.testing.assert_array_equal(a[r <= cut], b[r <= cut])
    # default delay: one camera period, also with every frame repeated
    default = [np.asarray(x) for x in snapshot_interpolation(t, p, q, r, config=cfg)]
    explicit = snapshot_interpolation(t, p, q, r, config=cfg, delay=float(np.median(np.diff(t))))
    for a, b in zip(default, explicit):
        np.testing.assert_array_equal(a, np.asarray(b))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "dropping 30 measurement(s) with duplicate timestamps"
        rep = snapshot_interpolation(np.repeat(t, 2), np.repeat(p, 2, 0), np.repeat(q, 2, 0), r,
                                     config=cfg)
    for a, b in zip(default, rep):
        np.testing.assert_array_equal(a, np.asarray(b))


class _PaperLowPass:
    def __init__(self):
        self.hat = None

    def __call__(self, x, a):
        self.hat = x if self.hat is None else a * x + (1 - a) * self.hat
        return self.hat


class _PaperOneEuro:
    """Casiez, Roussel & Vogel (CHI 2012), Algorithm 1, with timestamps: ``dx = (x -
    xfilt.hatxprev) * rate``, ``edx = dxfilt(dx, alpha(rate, dcutoff))``, ``cutoff = mincutoff +
    beta |edx|``, ``xfilt(x, alpha(rate, cutoff))``, ``alpha = 1 / (1 + tau rate)``."""

    def __init__(self, min_cutoff, beta, d_cutoff):
        self.mc, self.beta, self.dc = min_cutoff, beta, d_cutoff
        self.x, self.dx, self.last = _PaperLowPass(), _PaperLowPass(), None

    @staticmethod
    def alpha(rate, cutoff):
        return 1 / (1 + rate / (2 * math.pi * cutoff))

    def __call__(self, x, t):
        if self.last is None:
            self.last = t
            self.dx(0.0, 1.0)
            return self.x(x, 1.0)
        rate = 1 / (t - self.last)
        self.last = t
        edx = self.dx((x - self.x.hat) * rate, self.alpha(rate, self.dc))
        return self.x(x, self.alpha(rate, self.mc + self.beta * abs(edx)))


def test_one_euro_equals_the_paper_algorithm_on_uneven_steps_and_dropouts():
    """Motion along one axis (position) and about one fixed axis (orientation, angle below
    pi), so the filter reduces to the paper's scalar filter; frame intervals from 5 to 200 ms,
    dropped frames (the rate from the previous valid frame), q / -q flips."""
    rng = np.random.default_rng(0)
    n = 40
    t = np.cumsum(rng.choice([0.005, 0.033, 0.08, 0.2], n))
    xs = np.cumsum(rng.normal(0, 0.05, n))
    ang = np.cumsum(rng.normal(0, 0.2, n))
    axis = np.array([0.0, 0.6, 0.8])
    lost = rng.random(n) < 0.2
    lost[0] = True
    p = np.zeros((n, 3))
    p[:, 1] = xs
    q = Rotation.from_rotvec(np.outer(ang, axis)).as_quat()[:, [3, 0, 1, 2]]
    q[rng.random(n) < 0.4] *= -1
    p[lost], q[lost] = np.nan, np.nan
    fp, fq = map(np.asarray, one_euro(t, p, q, t, min_cutoff=0.7, beta=2.0, d_cutoff=1.3))
    fx, fa = _PaperOneEuro(0.7, 2.0, 1.3), _PaperOneEuro(0.7, 2.0, 1.3)
    ref_x, ref_a, lx, la = np.full(n, np.nan), np.full(n, np.nan), np.nan, np.nan
    for i in range(n):
        if not lost[i]:
            lx, la = fx(xs[i], t[i]), fa(ang[i], t[i])
        ref_x[i], ref_a[i] = lx, la
    np.testing.assert_array_equal(np.isnan(fp[:, 1]), np.isnan(ref_x))
    np.testing.assert_allclose(fp[:, 1], ref_x, atol=1e-12)
    ok = ~np.isnan(ref_a)
    rv = Rotation.from_quat(fq[ok][:, [1, 2, 3, 0]]).as_rotvec()
    np.testing.assert_allclose(rv @ axis, ref_a[ok], atol=1e-12)
    np.testing.assert_allclose(np.cross(rv, axis), 0, atol=1e-12)
