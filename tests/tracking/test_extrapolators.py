"""Causal extrapolating baselines: alpha-beta on R^3 x SO(3), One Euro + extrapolation,
snapshot interpolation, IMM extrapolation."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from phjax.quaternion import quat_geodesic_distance
from phjax.tracking.baselines import (
    alpha_beta,
    imm_extrapolation,
    kalman_extrapolation,
    one_euro,
    one_euro_extrapolation,
    snapshot_interpolation,
)
from phjax.tracking.imm import IMMConfig
from phjax.tracking.kalman import KalmanConfig
from phjax.tracking.models import ConstantVelocity

N, M = 45, 150


def _cv_motion(seed, drop=0.15):
    """Irregular frame times, linear positions, constant world angular velocity, dropouts."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.02, 0.045, N))
    p0, v = rng.normal(size=3), rng.normal(scale=0.5, size=3)
    w = rng.normal(scale=1.0, size=3)
    r0 = Rotation.from_rotvec(rng.normal(size=3))
    p = p0 + t[:, None] * v
    q = (Rotation.from_rotvec(t[:, None] * w) * r0).as_quat()[:, [3, 0, 1, 2]]
    q[rng.random(N) < 0.3] *= -1
    gone = rng.random(N) < drop
    gone[:3] = False
    mp, mq = p.copy(), q.copy()
    mp[gone] = np.nan
    mq[rng.random(N) < drop] = np.nan
    mq[:3] = q[:3]
    r = np.sort(rng.uniform(t[0] - 0.05, t[-1] + 0.05, M))

    def truth(tau):
        return p0 + tau[:, None] * v, (Rotation.from_rotvec(tau[:, None] * w) * r0).as_quat()[:, [3, 0, 1, 2]]

    return t, mp, mq, r, truth


def _angle(a, b):
    return np.asarray(quat_geodesic_distance(jnp.asarray(a), jnp.asarray(b)))


@pytest.mark.parametrize("alpha", [0.3, 0.8])
def test_alpha_beta_exact_on_constant_velocity(alpha):
    t, mp, mq, r, truth = _cv_motion(0)
    p, q = (np.asarray(x) for x in alpha_beta(t, mp, mq, r, alpha=alpha))
    gp, gq = truth(r)
    # exact once both channels have two valid samples
    vp = np.isfinite(mp).all(1)
    vq = np.isfinite(mq).all(1)
    ok = (r >= t[vp][1]) & (r >= t[vq][1])
    assert ok.sum() > 100
    np.testing.assert_allclose(p[ok], gp[ok], atol=1e-9)
    assert _angle(q[ok], gq[ok]).max() < 1e-9
    assert np.isnan(p[r < t[0]]).all() and np.isnan(q[r < t[0]]).all()


def _causality(fn, seed=1):
    t, mp, mq, r, _ = _cv_motion(seed)
    rng = np.random.default_rng(seed)
    mp = mp + 0.01 * rng.normal(size=mp.shape)
    cut = t[N // 2]
    mp2, mq2 = mp.copy(), mq.copy()
    later = t >= cut
    mp2[later] += rng.normal(size=(later.sum(), 3))
    mq2[later] = Rotation.random(later.sum(), random_state=seed).as_quat()[:, [3, 0, 1, 2]]
    a = [np.asarray(x) for x in fn(t, mp, mq, r)]
    b = [np.asarray(x) for x in fn(t, mp2, mq2, r)]
    before = r < cut
    assert before.sum() > 20
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x[before], y[before])
        assert not np.allclose(x[~before], y[~before], equal_nan=True)
        assert np.isfinite(x[r >= t[2]]).all()


@pytest.mark.parametrize("name", ["alpha_beta", "one_euro_x", "snapshot", "imm"])
def test_causal(name):
    fn = {
        "alpha_beta": lambda *a: alpha_beta(*a, alpha=0.5),
        "one_euro_x": lambda *a: one_euro_extrapolation(*a, min_cutoff=1.0, beta=1.0),
        "snapshot": lambda *a: snapshot_interpolation(*a),
        "imm": lambda *a: imm_extrapolation(*a),
    }[name]
    _causality(fn)


def test_one_euro_extrapolation_is_one_euro_at_frames_and_linear_between():
    t, mp, mq, _, _ = _cv_motion(2, drop=0.0)
    mp = mp + 0.01 * np.random.default_rng(2).normal(size=mp.shape)
    kw = dict(min_cutoff=0.7, beta=2.0)
    p, q = (np.asarray(x) for x in one_euro_extrapolation(t, mp, mq, t, **kw))
    hp, hq = (np.asarray(x) for x in one_euro(t, mp, mq, t, **kw))
    np.testing.assert_allclose(p, hp, atol=1e-12)
    assert _angle(q, hq).max() < 1e-9
    # three render times inside one frame interval: zero second difference (linear in tau)
    k = N // 2
    tau = t[k] + np.array([0.2, 0.5, 0.8]) * (t[k + 1] - t[k])
    pe, _ = (np.asarray(x) for x in one_euro_extrapolation(t, mp, mq, tau, **kw))
    np.testing.assert_allclose(pe[0] - 2 * pe[1] + pe[2], 0, atol=1e-12)
    assert np.abs(pe[2] - pe[0]).max() > 1e-4  # it does move between frames


def test_snapshot_interpolates_one_period_late():
    """With a filter that trusts the measurements (tiny measurement noise, large process
    noise) the output is the linear / slerp interpolation of the measurements at tau - delay."""
    t, mp, mq, r, truth = _cv_motion(3, drop=0.0)
    cfg = KalmanConfig(pos_process_noise=1e6, rot_process_noise=1e6, pos_meas_noise=1e-7,
                       rot_meas_noise=1e-7)
    delay = 0.03
    p, q = (np.asarray(x) for x in snapshot_interpolation(t, mp, mq, r, config=cfg, delay=delay))
    k = np.searchsorted(t, r, side="right") - 1
    s = np.minimum(r - delay, t[np.clip(k, 0, None)])
    ok = (k >= 0) & (s >= t[0])
    gp, gq = truth(s[ok])  # linear / constant-rate motion: interpolation is exact
    np.testing.assert_allclose(p[ok], gp, atol=1e-6)
    assert _angle(q[ok], gq).max() < 1e-5
    # slerp of the measurements equals the truth too (scipy reference on one interval)
    sl = Slerp(t[:2], Rotation.from_quat(mq[:2][:, [1, 2, 3, 0]]))
    mid = sl([0.5 * (t[0] + t[1])]).as_quat()[:, [3, 0, 1, 2]]
    assert _angle(mid, truth(np.array([0.5 * (t[0] + t[1])]))[1]).max() < 1e-9


def test_imm_extrapolation_single_model_equals_kalman():
    t, mp, mq, r, _ = _cv_motion(4)
    mp = mp + 0.005 * np.random.default_rng(4).normal(size=mp.shape)
    kcfg = KalmanConfig(pos_process_noise=0.1, rot_process_noise=1.0)
    icfg = IMMConfig(position_models=(ConstantVelocity.from_q(0.1),),
                     rotation_models=(ConstantVelocity.from_q(1.0),))
    a = [np.asarray(x) for x in kalman_extrapolation(t, mp, mq, r, config=kcfg)]
    b = [np.asarray(x) for x in imm_extrapolation(t, mp, mq, r, config=icfg)]
    np.testing.assert_allclose(b[0], a[0], atol=1e-10)
    ok = np.isfinite(a[1]).all(1)
    assert _angle(b[1][ok], a[1][ok]).max() < 1e-9
    np.testing.assert_array_equal(np.isnan(a[0]), np.isnan(b[0]))


def test_snapshot_default_is_the_tuned_snapshot_baseline():
    """Called without a config, snapshot interpolation is the tuned method the evaluation
    reports (it used the Kalman CV's tuned noise, 0.03 / 1.0 instead of 0.09 / 3.0)."""
    from phjax.evaluation.report import default_methods

    t, mp, mq, _, _ = _cv_motion(4)
    r = np.arange(t[0], t[-1], 1 / 120)
    method = next(m for m in default_methods() if m.name == "snapshot interpolation")
    for got, want in zip(snapshot_interpolation(t, mp, mq, r), method.fn(t, mp, mq, r)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
