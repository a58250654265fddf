"""Tests for phjax.evaluation.metrics against closed forms and independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from phjax.evaluation import metrics
from phjax.evaluation.metrics import (
    evaluate,
    latency,
    max_angular_velocity_jump,
    max_velocity_jump,
    mean_abs_curvature,
    mean_abs_torsion,
    position_rmse,
    rms_jerk_position,
    rms_jerk_rotation,
    rotation_rmse_deg,
)


def _wxyz(r: Rotation) -> np.ndarray:
    return r.as_quat()[..., [3, 0, 1, 2]]


def _helix(t, a=0.7, b=0.3):
    return np.stack([a * np.cos(t), a * np.sin(t), b * t], -1)


# ------------------------------------------------------------------------------------- accuracy


@settings(max_examples=30)
@given(st.integers(0, 10_000))
def test_position_rmse_matches_direct_formula_and_ignores_nan_rows(seed):
    rng = np.random.default_rng(seed)
    est, gt = rng.normal(size=(2, 50, 3))
    est[rng.random(50) < 0.2, 1] = np.nan
    gt[rng.random(50) < 0.2] = np.nan
    ok = ~np.isnan(est).any(1) & ~np.isnan(gt).any(1)
    res = position_rmse(est, gt)
    assert res.count == ok.sum()
    ref = np.sqrt(np.mean(np.sum((est[ok] - gt[ok]) ** 2, 1)))
    assert res.value == pytest.approx(ref, rel=1e-12)


def test_rmse_matches_evo_ape():
    pytest.importorskip("evo.core")
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(0)
    n = 40
    t = np.arange(n) * 0.1
    gt = rng.normal(size=(n, 3))
    est = gt + 0.01 * rng.normal(size=(n, 3))
    r = Rotation.random(n, random_state=1)
    q_gt = _wxyz(r)
    q_est = _wxyz(Rotation.from_rotvec(0.05 * rng.normal(size=(n, 3))) * r)
    traj_ref = PoseTrajectory3D(positions_xyz=gt, orientations_quat_wxyz=q_gt, timestamps=t)
    traj_est = PoseTrajectory3D(positions_xyz=est, orientations_quat_wxyz=q_est, timestamps=t)
    rmse = evo_metrics.StatisticsType.rmse
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    assert position_rmse(est, gt).value == pytest.approx(ape.get_statistic(rmse), rel=1e-9)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
    ape.process_data((traj_ref, traj_est))
    assert rotation_rmse_deg(q_est, q_gt).value == pytest.approx(ape.get_statistic(rmse), rel=1e-6)


@settings(max_examples=30)
@given(st.integers(0, 10_000))
def test_rotation_rmse_matches_scipy_and_is_sign_invariant(seed):
    rng = np.random.default_rng(seed)
    r_gt = Rotation.random(60, random_state=seed)
    r_est = Rotation.from_rotvec(rng.normal(scale=0.5, size=(60, 3))) * r_gt
    q_est, q_gt = _wxyz(r_est), _wxyz(r_gt)
    q_est[rng.random(60) < 0.5] *= -1
    q_est[3] = np.nan
    ang = (r_est.inv() * r_gt).magnitude()
    ref = np.degrees(np.sqrt(np.mean(np.delete(ang, 3) ** 2)))
    res = rotation_rmse_deg(q_est, q_gt)
    assert res.count == 59
    assert res.value == pytest.approx(ref, rel=1e-9)


def test_zero_quaternion_rows_are_skipped():
    """A zero quaternion is no orientation: skipped like a NaN row (it gave a NaN metric)."""
    rng = np.random.default_rng(2)
    q_gt = Rotation.random(20, random_state=3).as_quat()[:, [3, 0, 1, 2]]
    q_est = q_gt + 0.01 * rng.normal(size=q_gt.shape)
    zero, nan = q_est.copy(), q_est.copy()
    zero[5], nan[5] = 0.0, np.nan
    a, b = rotation_rmse_deg(zero, q_gt), rotation_rmse_deg(nan, q_gt)
    assert a.count == b.count == 19 and a.value == b.value and math.isfinite(a.value)
    t = np.arange(20) * 0.01
    assert metrics.rms_jerk_rotation(t, zero) == metrics.rms_jerk_rotation(t, nan)


def test_no_valid_rows_gives_nan_not_error():
    nan = np.full((5, 3), np.nan)
    res = position_rmse(nan, np.zeros((5, 3)))
    assert math.isnan(res.value) and res.count == 0
    with pytest.raises(ValueError):
        position_rmse(np.zeros((4, 3)), np.zeros((5, 3)))


# ------------------------------------------------------------------------------------- jerk


@settings(max_examples=20)
@given(st.integers(0, 10_000))
def test_jerk_of_cubic_is_constant_on_any_grid(seed):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.005, 0.05, 40))
    c = rng.normal(size=(4, 3))
    x = c[0] + np.outer(t, c[1]) + np.outer(t**2, c[2]) + np.outer(t**3, c[3])
    res = rms_jerk_position(t, x)
    assert res.count == 37
    assert res.value == pytest.approx(6 * np.linalg.norm(c[3]), rel=1e-6)
    # t^3 along one axis: jerk 6
    cube = np.stack([t**3, 0 * t, 0 * t], -1)
    assert rms_jerk_position(t, cube).value == pytest.approx(6, rel=1e-6)


def test_jerk_of_helix_and_nan_windows():
    a, b = 0.7, 0.3
    t = np.linspace(0, 10, 20001)
    x = _helix(t, a, b)  # |r'''| = a
    assert rms_jerk_position(t, x).value == pytest.approx(a, rel=1e-5)
    x[100] = np.nan
    res = rms_jerk_position(t, x)
    assert res.count == len(t) - 3 - 4  # the four windows touching row 100 are skipped
    assert res.value == pytest.approx(a, rel=1e-5)


def test_rotation_jerk_of_cubic_angle_and_sign_flips():
    t = np.linspace(0, 1, 501)
    axis = np.array([2.0, -1.0, 2.0]) / 3
    q = _wxyz(Rotation.from_rotvec(np.outer(t**3, axis)))  # |omega''| = 6
    q[::7] *= -1
    res = rms_jerk_rotation(t, q)
    assert res.count == len(t) - 3
    assert res.value == pytest.approx(6.0, rel=1e-6)
    # constant angular velocity has no angular jerk
    q = _wxyz(Rotation.from_rotvec(np.outer(2.0 * t, axis)))
    assert rms_jerk_rotation(t, q).value < 1e-6


def test_rotation_jerk_matches_analytic_for_composed_rotation():
    """q = Rz(a t) Rx(b t): omega(t) = a e_z + b Rz(a t) e_x, so |omega''| = a^2 |b|."""
    a, b = 1.5, 0.8
    t = np.linspace(0, 3, 6001)
    rz = Rotation.from_rotvec(np.outer(a * t, [0, 0, 1]))
    rot = rz * Rotation.from_rotvec(np.outer(b * t, [1, 0, 0]))
    assert rms_jerk_rotation(t, _wxyz(rot)).value == pytest.approx(a * a * b, rel=1e-4)


# ------------------------------------------------------------------------------ curvature, torsion


@pytest.mark.parametrize("a,b", [(0.7, 0.3), (0.2, 1.0)])
def test_helix_curvature_and_torsion(a, b):
    rng = np.random.default_rng(0)
    t = np.linspace(0, 6, 6001)
    t[1:-1] += rng.uniform(-0.2, 0.2, len(t) - 2) * 1e-3  # non-uniform samples
    x = _helix(t, a, b)
    k = mean_abs_curvature(t, x)
    tau = mean_abs_torsion(t, x)
    assert k.count == tau.count == len(t) - 4
    assert k.value == pytest.approx(a / (a * a + b * b), rel=1e-4)
    assert tau.value == pytest.approx(b / (a * a + b * b), rel=1e-4)


def test_curvature_thresholds_skip_stationary_and_straight_samples():
    t = np.linspace(0, 1, 101)
    still = np.zeros((101, 3))
    assert mean_abs_curvature(t, still).count == 0
    line = np.stack([t, 2 * t, 0 * t], -1)
    k = mean_abs_curvature(t, line)
    assert k.count == 97 and k.value < 1e-9
    assert mean_abs_torsion(t, line).count == 0  # torsion undefined on a straight line


# ------------------------------------------------------------------------------- velocity jumps


@pytest.mark.parametrize("kink", [0.5, 0.5037])  # on a sample / between samples
def test_velocity_jump_of_known_kink(kink):
    t = np.linspace(0, 1, 101)
    v1, v2 = np.array([1.0, 0.0, 0.5]), np.array([-0.5, 2.0, 0.5])
    x = np.where((t < kink)[:, None], np.outer(t, v1), kink * v1 + np.outer(t - kink, v2))
    res = max_velocity_jump(t, x, [0.2, kink, 0.8])
    assert res.count == 3
    assert res.value == pytest.approx(np.linalg.norm(v2 - v1), rel=1e-9)
    # a smooth path has a small jump (O(a dt) at most)
    y = _helix(t)
    assert max_velocity_jump(t, y, [0.2, 0.5037]).value < 0.7 * 2 * (t[1] - t[0])
    # boundaries without three samples on a side are ignored
    assert max_velocity_jump(t, x, [-1.0, 0.005, 2.0]).count == 0


def test_angular_velocity_jump_of_known_kink():
    t = np.linspace(0, 1, 101)
    w1, w2 = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    r1 = Rotation.from_rotvec(np.outer(np.minimum(t, 0.5), w1))
    r2 = Rotation.from_rotvec(np.outer(np.maximum(t - 0.5, 0), w2))
    q = _wxyz(r2 * r1)  # world-frame omega switches from w1 to w2 at t = 0.5
    res = max_angular_velocity_jump(t, q, [0.5])
    assert res.count == 1
    assert res.value == pytest.approx(np.linalg.norm(w2 - w1), rel=1e-6)


# ------------------------------------------------------------------------------------- latency


@pytest.mark.parametrize("delay", [0.0437, -0.021, 0.0])
def test_latency_recovers_delay_of_a_copy(delay):
    h = 1 / 500
    t = np.arange(0, 20, h)
    rng = np.random.default_rng(1)
    f, ph = rng.uniform(0.1, 2, (2, 3, 4))

    def sig(s):
        arg = 2 * np.pi * f[None] * s[:, None, None] + ph[None]  # (n, 3, 4)
        return np.sin(arg).sum(-1)

    gt, est = sig(t), sig(t - delay)
    est[500:520] = np.nan
    res = latency(t, est, gt, max_lag=0.2)
    assert abs(res.value - delay) < h
    assert res.correlation > 0.99

    # rotations: angular velocity of a delayed orientation signal
    rq = _wxyz(Rotation.from_rotvec(0.5 * sig(t)))
    rq_est = _wxyz(Rotation.from_rotvec(0.5 * sig(t - delay)))
    res = latency(t, rq_est, rq, max_lag=0.2, window=0.02)
    assert abs(res.value - delay) < h


def test_latency_of_hold_staircase_is_about_half_a_period():
    h = 1 / 1000
    t = np.arange(0, 20, h)
    period = 0.05
    gt = np.stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 0.3 * t), 0 * t], -1)
    held = gt[(np.floor(t / period + 1e-9) * period / h).round().astype(int)]
    res = latency(t, held, gt, max_lag=0.2, window=0.1)
    assert abs(res.value - period / 2) < 2 * h


# ------------------------------------------------------------------------------------- evaluate


def test_evaluate_keys_values_and_orientation_only():
    t = np.linspace(0, 2, 401)
    gt_p = _helix(t)
    gt_q = _wxyz(Rotation.from_rotvec(np.outer(np.sin(t), [0, 1.0, 0])))
    est_p = gt_p + 0.001
    out = evaluate(t, est_p, gt_q, gt_p, gt_q, boundary_times=t[::10] + 1e-4)
    assert out["position_rmse"] == pytest.approx(0.001 * np.sqrt(3))
    assert out["rotation_rmse_deg"] == pytest.approx(0.0, abs=1e-6)
    assert out["position_rmse_n"] == 401
    assert out["curvature"] == pytest.approx(0.7 / (0.49 + 0.09), rel=1e-4)
    assert abs(out["latency_position"]) < 1e-3
    for k, v in out.items():
        assert np.isfinite(v), k

    nan_p = np.full_like(gt_p, np.nan)
    out = evaluate(t, nan_p, gt_q, nan_p, gt_q)
    pos_keys = ("position_rmse", "jerk_position", "curvature", "torsion", "velocity_jump")
    for k in pos_keys + ("latency_position",):
        assert math.isnan(out[k]) and out[k + "_n"] == 0
    assert np.isfinite(out["rotation_rmse_deg"]) and np.isfinite(out["jerk_rotation"])


def test_evaluate_puts_each_metric_of_the_estimate_under_its_key():
    """Each key holds its metric of the *estimate* (the ground truth's only under ``..._gt``):
    with a noisy, lagging estimate every smoothness metric differs between the two, so a
    swapped key or a metric computed on the ground truth fails (the metrics themselves are
    tested against closed forms above)."""
    rng = np.random.default_rng(8)
    t = np.linspace(0, 2, 401)
    gt_p = _helix(t)
    gt_q = _wxyz(Rotation.from_rotvec(np.outer(np.sin(t), [0, 1.0, 0])))
    est_p = _helix(t - 0.02) + 1e-4 * rng.normal(size=gt_p.shape)
    est_q = _wxyz(Rotation.from_rotvec(np.outer(np.sin(t - 0.03), [0, 1.0, 0])
                                       + 1e-3 * rng.normal(size=(t.size, 3))))
    b = t[::10] + 1e-4
    out = evaluate(t, est_p, est_q, gt_p, gt_q, boundary_times=b)
    lat = {"max_lag": 0.5, "window": 0.1}
    rng_ = {"min_lag": -0.1, "max_lag": 0.3}
    expect = {
        "position_rmse": position_rmse(est_p, gt_p),
        "rotation_rmse_deg": rotation_rmse_deg(est_q, gt_q),
        "jerk_position": rms_jerk_position(t, est_p),
        "jerk_rotation": rms_jerk_rotation(t, est_q),
        "jerk_position_gt": rms_jerk_position(t, gt_p),
        "jerk_rotation_gt": rms_jerk_rotation(t, gt_q),
        "curvature": mean_abs_curvature(t, est_p),
        "torsion": mean_abs_torsion(t, est_p),
        "velocity_jump": max_velocity_jump(t, est_p, b),
        "angular_velocity_jump": max_angular_velocity_jump(t, est_q, b),
        "latency_position": latency(t, est_p, gt_p, kind="position", **lat),
        "latency_rotation": latency(t, est_q, gt_q, kind="rotation", **lat),
        "lag_position": metrics.shift_lag(t, est_p, gt_p, kind="position", **rng_),
        "lag_rotation": metrics.shift_lag(t, est_q, gt_q, kind="rotation", **rng_),
    }
    for k, res in expect.items():
        assert out[k] == pytest.approx(res.value, rel=1e-12, abs=1e-15), k
        assert out[k + "_n"] == res.count, k
    # the estimate's smoothness metrics are not the ground truth's
    for k, fn, gt in (("jerk_position", rms_jerk_position, gt_p),
                      ("jerk_rotation", rms_jerk_rotation, gt_q),
                      ("curvature", mean_abs_curvature, gt_p),
                      ("torsion", mean_abs_torsion, gt_p)):
        assert abs(out[k] - fn(t, gt).value) > 0.01 * abs(fn(t, gt).value), k
    # a lagging estimate: both lag estimates see it (20 / 30 ms behind)
    assert out["lag_position"] == pytest.approx(0.02, abs=0.005)
    assert out["lag_rotation"] == pytest.approx(0.03, abs=0.005)


def test_fd_weights_reproduce_polynomial_derivatives():
    rng = np.random.default_rng(3)
    d = np.sort(rng.uniform(-1, 1, (10, 5)), axis=1) * 0.1
    c = rng.normal(size=5)
    f = sum(c[k] * d**k for k in range(5))
    for order in range(4):
        w = metrics._fd_weights(d, order)
        np.testing.assert_allclose(np.sum(w * f, 1), math.factorial(order) * c[order], rtol=1e-7)


def test_metrics_take_nan_padded_batches():
    """Every metric on a padded batch (2 x 2 recordings) equals the metric of each recording
    alone; padding rows are cut off, boundary times may be shared or per recording."""
    from phjax.batch import pad_recordings

    rng = np.random.default_rng(3)
    recs = []
    for n in (40, 55, 61, 33):
        t = np.cumsum(rng.uniform(0.005, 0.012, n))
        p = np.stack([np.sin(3 * t), np.cos(2 * t), t**2], -1) + 1e-4 * rng.normal(size=(n, 3))
        q = Rotation.from_rotvec(np.stack([t, 0.5 * t, np.sin(t)], -1)).as_quat()[:, [3, 0, 1, 2]]
        g = p + 1e-3 * rng.normal(size=(n, 3))
        gq = (Rotation.from_rotvec(0.01 * rng.normal(size=(n, 3)))
              * Rotation.from_quat(q[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
        b = t[5:-5:7] + 1e-4
        recs.append((t, p, q, g, gq, b))
    t, p, q, g, gq, b = (x.reshape((2, 2) + x.shape[1:]) for x in pad_recordings(*zip(*recs)))
    cases = [
        (metrics.position_rmse, lambda r: (r[1], r[3]), (p, g)),
        (metrics.rotation_rmse_deg, lambda r: (r[2], r[4]), (q, gq)),
        (metrics.rms_jerk_position, lambda r: (r[0], r[1]), (t, p)),
        (metrics.rms_jerk_rotation, lambda r: (r[0], r[2]), (t, q)),
        (metrics.mean_abs_curvature, lambda r: (r[0], r[1]), (t, p)),
        (metrics.mean_abs_torsion, lambda r: (r[0], r[1]), (t, p)),
        (metrics.max_velocity_jump, lambda r: (r[0], r[1], r[5]), (t, p, b)),
        (metrics.max_angular_velocity_jump, lambda r: (r[0], r[2], recs[0][5]),
         (t, q, recs[0][5])),
        (metrics.latency, lambda r: (r[0], r[1], r[3]), (t, p, g)),
    ]
    for fn, pick, batch_args in cases:
        res = fn(*batch_args)
        for k, r in enumerate(recs):
            alone = fn(*pick(r))
            for field_b, field_a in zip(res, alone):
                assert np.shape(field_b) == (2, 2)
                np.testing.assert_allclose(np.asarray(field_b).reshape(4)[k], field_a,
                                           rtol=1e-12, equal_nan=True)
    ev = metrics.evaluate(t, p, q, g, gq, b)
    for k, r in enumerate(recs):
        alone = metrics.evaluate(*r[:5], r[5])
        for name, v in alone.items():
            np.testing.assert_allclose(ev[name].reshape(4)[k], v, rtol=1e-12, equal_nan=True)
    bad = t.copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="padding"):
        metrics.rms_jerk_position(bad, p)


# ------------------------------------------------------------------------------ shift lag (RMSE)


@pytest.mark.parametrize("delay", [0.0237, -0.0113, 0.0])
def test_shift_lag_recovers_a_known_delay(delay):
    """A stream that is the ground truth ``delay`` seconds late (plus white noise) has that lag,
    positions and rotations; grid 2 ms, render 120 Hz, so the parabola must interpolate."""
    h = 1 / 120
    t = np.arange(0, 20, h)
    rng = np.random.default_rng(3)
    f, ph = rng.uniform(0.1, 1.5, (2, 3, 3))

    def sig(s):
        return np.sin(2 * np.pi * f[None] * s[:, None, None] + ph[None]).sum(-1)  # (n, 3)

    gt, est = 0.1 * sig(t), 0.1 * sig(t - delay)
    est = est + rng.normal(0, 1e-3, est.shape)
    est[700:720] = np.nan
    res = metrics.shift_lag(t, est, gt)
    assert abs(res.value - delay) < 1e-3
    assert res.rmse == pytest.approx(1e-3 * np.sqrt(3), rel=0.1)  # the noise is what remains
    assert res.count < t.size - 20

    rq = _wxyz(Rotation.from_rotvec(0.5 * sig(t)))
    rq_est = _wxyz(Rotation.from_rotvec(0.5 * sig(t - delay)))
    res = metrics.shift_lag(t, -rq_est, rq)  # sign-invariant
    assert abs(res.value - delay) < 1e-3
    unshifted = rotation_rmse_deg(rq_est, rq).value
    assert res.rmse <= unshifted + 1e-12
    if delay != 0:
        assert res.rmse < 0.2 * unshifted  # what is left: <= 1 ms of grid offset, slerp error


def test_shift_lag_of_a_still_truth_is_nan():
    """A still head scores alike at every shift: the lag was the grid's lower end (-100 ms),
    shown in bold as the best lag of every method. Now NaN (the rmse and count still given)."""
    t = np.arange(0, 5, 1 / 120)
    rng = np.random.default_rng(0)
    gt = np.tile([0.1, 0.2, 0.6], (t.size, 1))
    res = metrics.shift_lag(t, gt + rng.normal(0, 1e-3, gt.shape), gt)
    assert np.isnan(res.value) and res.count > 500 and res.rmse == pytest.approx(1.7e-3, rel=0.1)
    q = np.tile([0.9, 0.1, 0.3, 0.3], (t.size, 1)) / np.linalg.norm([0.9, 0.1, 0.3, 0.3])
    assert np.isnan(metrics.shift_lag(t, q, q).value)
    moving = gt.copy()
    moving[:, 0] += 0.01 * np.sin(t)  # any motion: a lag again
    assert abs(metrics.shift_lag(t, moving, moving).value) < 1e-3


def test_shift_lag_of_a_hold_and_against_brute_force():
    """A zero-order hold lags by the mean age of the held sample (here 30 Hz held on a 120 Hz
    grid: ages 0, 1, 2, 3 render periods, mean 1.5 h; the RMSE of a sawtooth error is least at
    its mean); the value equals a brute-force minimum over exactly shifted ground truth on a
    fine grid (independent of the interpolation)."""
    h = 1 / 120
    t = np.arange(0, 20, h)

    def g(s):
        return np.stack([np.sin(1.3 * s), 0.5 * np.cos(0.7 * s), 0 * s], -1)

    period = 1 / 30
    held = g(np.floor(t / period + 1e-9) * period)
    res = metrics.shift_lag(t, held, g(t), step=0.001)
    fine = np.arange(-0.05, 0.1, 1e-4)
    sel = (t > 0.2) & (t < 19.7)
    brute = [np.sqrt(np.mean(np.sum((held[sel] - g(t[sel] - d)) ** 2, -1))) for d in fine]
    assert res.value == pytest.approx(fine[int(np.argmin(brute))], abs=5e-4)
    assert abs(res.value - 1.5 * h) < 1e-3


def _full_grid_lag(t, est, gt, lags, kind):
    """Reference for :func:`metrics.shift_lag`: every shift of the grid scored, the ground truth
    interpolated by NumPy (positions) or scipy's ``Slerp`` (rotations); the same scored samples
    (estimate finite, shifted truth finite at every shift) and parabola refinement (through
    the mean squared errors)."""
    from scipy.spatial.transform import Slerp

    s = t[None, :] - lags[:, None]  # (shifts, n)
    inside = (s >= t[0]) & (s <= t[-1])
    i = np.clip(np.searchsorted(t, s, side="right") - 1, 0, t.size - 2)
    good = np.isfinite(gt).all(-1)
    finite = inside & good[i] & good[i + 1]
    ok = np.isfinite(est).all(-1) & finite.all(0)
    if kind == "position":
        shifted = np.stack([np.stack([np.interp(row, t, gt[:, j]) for j in range(3)], -1)
                            for row in s[:, ok]])
        err = np.linalg.norm(shifted - est[ok], axis=-1)
    else:
        slerp = Slerp(t, Rotation.from_quat(gt[:, [1, 2, 3, 0]]))
        e = Rotation.from_quat(est[ok][:, [1, 2, 3, 0]])
        err = np.stack([np.degrees((slerp(row) * e.inv()).magnitude()) for row in s[:, ok]])
    rmse = np.sqrt(np.mean(err**2, axis=-1))
    k = int(np.argmin(rmse))
    lag = lags[k]
    if 0 < k < lags.size - 1:
        c = rmse[k - 1:k + 2] ** 2  # the MSE's parabola
        den = c[0] - 2 * c[1] + c[2]
        lag += 0.5 * (c[0] - c[2]) / den * (lags[1] - lags[0]) if den > 0 else 0.0
    return lag, rmse[k], int(ok.sum())


def test_shift_lag_finds_the_full_grid_minimum_on_real_streams(shared_data):
    """The coarse-to-fine search scores ~60 of the 201 shifts; on the streams that the
    evaluation scores (phjax, the Kalman CV extrapolation, a hold, One Euro filters from smooth
    to sluggish; TUM fr1_desk, 15 s, positions and rotations) its
    lag, RMSE and count equal those of every shift scored (an independent reference), also with
    frames lost in the estimate and a gap in the ground truth, and at the grid's end."""
    import phjax as pj
    from phjax import io
    from phjax.tracking import baselines

    tr = io.read_tum(shared_data / "tum_rgbd_groundtruth" / "fr1_desk-groundtruth.txt")
    sel = tr.times <= tr.times[0] + 15
    gt_t, gt_p, gt_q = tr.times[sel] - tr.times[0], tr.positions[sel], tr.quaternions[sel]
    r = np.arange(0.2, 14.8, 1 / 120)
    rp, rq = (np.asarray(x) for x in pj.motion.interpolate_poses(gt_t, gt_p, gt_q, r))
    lags = np.arange(-0.1, 0.3 + 1e-3, 0.002)  # shift_lag's default grid
    mt, mp, mq = pj.simulate_measurements(1, gt_t, gt_p, gt_q)
    cases = [pj.track(mt, mp, mq, r), baselines.kalman_extrapolation(mt, mp, mq, r),
             baselines.hold(mt, mp, mq, r)]
    cases += [baselines.one_euro(mt, mp, mq, r, min_cutoff=c) for c in (0.05, 1.0, 10.0)]
    far = int(0.35 * 120)  # 350 ms late: beyond the grid's end
    cases.append((np.roll(rp, far, 0), np.roll(rq, far, 0)))
    gap_p = rp.copy()
    gap_p[600:660] = np.nan  # half a second of lost ground truth
    for n, (sp, sq) in enumerate(cases):
        sp, sq = np.array(sp), np.array(sq)
        sp[np.arange(sp.shape[0]) % 37 == 5] = np.nan  # lost frames in the estimate
        for est, gt, kind in ((sp, rp, "position"), (sq, rq, "rotation"), (sp, gap_p, "position")):
            got = metrics.shift_lag(r, est, gt)
            ref = _full_grid_lag(r, est, gt, lags, kind)
            assert got.count == ref[2], (n, kind)
            assert got.value == pytest.approx(ref[0], abs=1e-9), (n, kind, got, ref)
            assert got.rmse == pytest.approx(ref[1], rel=1e-9), (n, kind, got, ref)
    assert metrics.shift_lag(r, *cases[-1][:1], rp).value == pytest.approx(0.3)  # grid end


def test_shift_lag_edge_cases_and_evaluate_keys():
    t = np.linspace(0, 1, 5)
    nan = np.full((5, 3), np.nan)
    assert metrics.shift_lag(t, nan, nan).count == 0
    with pytest.raises(ValueError, match="same"):
        metrics.shift_lag(t, np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="step"):
        metrics.shift_lag(t, np.zeros((5, 3)), np.zeros((5, 3)), step=0.0)
    tt = np.linspace(0, 2, 241)
    p = _helix(tt)
    q = _wxyz(Rotation.from_rotvec(np.outer(np.sin(tt), [0, 1.0, 0])))
    out = evaluate(tt, p, q, p, q)
    assert abs(out["lag_position"]) < 1e-4 and abs(out["lag_rotation"]) < 1e-4
    assert out["lag_position_rmse"] < 1e-9


def test_velocity_jump_of_a_c1_stream_is_truncation_error_that_vanishes_with_spacing():
    """A C1 path with acceleration steps at the knots (cubic Hermite pieces, like a stream
    re-planned at every camera frame) has no velocity jump; sampled at a quarter of the knot
    period the one-sided stencils still report one of order ``jerk * h^2``, which shrinks with
    the spacing (the artefact behind the large 120 Hz values of a C1 stream), and the RMS jerk
    grows with the sample rate (the acceleration steps), while inside the pieces it is exact."""
    from scipy.interpolate import CubicHermiteSpline

    rng = np.random.default_rng(0)
    period = 1 / 30
    knots = np.arange(0, 2 + 1e-9, period)
    spline = CubicHermiteSpline(knots, rng.normal(0, 2e-3, (knots.size, 3)),
                                rng.normal(0, 0.1, (knots.size, 3)))
    jerk_pieces = np.linalg.norm(spline.c[0] * 6, axis=-1)  # constant jerk per piece
    boundaries = knots[5:-5] + 1e-4  # between samples, as camera frames are
    jumps, rms = [], []
    for n in (4, 64, 1024):
        t = np.arange(0, 2, period / n)
        x = spline(t)
        jumps.append(max_velocity_jump(t, x, boundaries).value)
        rms.append(rms_jerk_position(t, x).value)
        h = period / n
        assert jumps[-1] <= 2 * jerk_pieces.max() * h**2 + 2 * np.abs(spline(t, 2)).max() * h
    assert jumps[0] > 30 * jumps[2]
    assert rms[0] < rms[1] < rms[2]
    # away from the knots the metric is exact: one piece sampled alone
    t = np.linspace(knots[10] + 1e-3, knots[11] - 1e-3, 50)
    assert rms_jerk_position(t, spline(t)).value == pytest.approx(jerk_pieces[10], rel=1e-6)


def test_evaluate_recording_of_position_only_ground_truth():
    """Ground truth without orientations (NaN quaternions) is scored on its positions; it
    ended in "the simulated sensor produced no valid measurement" (a frame counted as valid
    only with a quaternion)."""
    from phjax.evaluation import evaluate_recording
    from phjax.evaluation.report import default_methods

    t = np.linspace(0, 3, 301)
    q = np.full((t.size, 4), np.nan)
    res = evaluate_recording(t, _helix(t), q, methods=default_methods()[:1])
    m = next(iter(res.metrics.values()))
    assert np.isfinite(m["position_rmse"]) and m["position_rmse"] < 0.02
    assert np.isnan(m["rotation_rmse_deg"])
