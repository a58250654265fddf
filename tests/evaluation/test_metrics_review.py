"""Review tests of phjax.evaluation.metrics: edge cases and independent NumPy / scipy references
(each defect test failed on the code before its fix)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from phjax.batch import pad_recordings
from phjax.evaluation import metrics


def _wxyz(r: Rotation) -> np.ndarray:
    return r.as_quat()[..., [3, 0, 1, 2]]


def _recording(n=60, h=0.01):
    t = np.arange(n) * h
    p = np.stack([np.sin(3 * t), np.cos(2 * t), t**2], -1)
    q = _wxyz(Rotation.from_rotvec(np.stack([t, 0.5 * t, np.sin(t)], -1)))
    return t, p, q


def test_velocity_jumps_of_an_empty_recording_are_nan_not_an_error():
    """A recording without samples (an all-NaN recording that ``pad_recordings(...,
    multiple_of=k)`` adds to a batch) with shared boundary times raised ``IndexError`` in
    :func:`max_velocity_jump`, :func:`max_angular_velocity_jump` and so in :func:`evaluate`
    (of the whole batch); the documented result is ``Metric(nan, 0)``."""
    t, p, q = _recording()
    b = t[5:-5:7] + 1e-4  # shared by every recording
    e0 = np.zeros(0)
    for fn, rows in ((metrics.max_velocity_jump, np.zeros((0, 3))),
                     (metrics.max_angular_velocity_jump, np.zeros((0, 4)))):
        res = fn(e0, rows, b)
        assert math.isnan(res.value) and res.count == 0, fn.__name__
    tb, pb, qb = pad_recordings([t], [p], [q], multiple_of=2)
    out = metrics.evaluate(tb, pb, qb, pb, qb, b)
    alone = metrics.evaluate(t, p, q, p, q, b)
    for name, v in alone.items():
        assert out[name].shape == (2,)
        np.testing.assert_allclose(out[name][0], v, rtol=1e-12, equal_nan=True)
        if name.endswith("_n"):
            assert out[name][1] == 0, name
        else:
            assert math.isnan(out[name][1]), name


def test_rotation_error_near_half_a_turn_and_of_the_negated_quaternion():
    """Errors up to 180 deg (and past it: the other way round is shorter) against scipy's
    magnitude, with any sign of either quaternion; ``-q`` against ``q`` is no error."""
    rng = np.random.default_rng(4)
    r_gt = Rotation.random(8, random_state=5)
    axes = rng.normal(size=(8, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.pi + np.array([-1e-3, -1e-6, 0.0, 1e-6, 1e-3, -0.5, 0.5, 2.0])
    r_est = Rotation.from_rotvec(axes * angles[:, None]) * r_gt
    ref = np.degrees((r_est * r_gt.inv()).magnitude())  # in [0, 180]
    q_est, q_gt = _wxyz(r_est), _wxyz(r_gt)
    for s_est, s_gt in ((1, 1), (-1, 1), (1, -1)):
        for i in range(8):  # one sample at a time: each error, not only their RMS
            res = metrics.rotation_rmse_deg(s_est * q_est[i:i + 1], s_gt * q_gt[i:i + 1])
            assert res.count == 1
            assert res.value == pytest.approx(ref[i], abs=1e-7)
    assert metrics.rotation_rmse_deg(-q_gt, q_gt).value == pytest.approx(0.0, abs=1e-6)
    assert metrics.rotation_rmse_deg(-q_gt, q_gt).count == 8


def _brute_shift_lag(t, est, gt, lags, kind):
    """Every shift of ``lags`` scored: the truth interpolated by ``np.interp`` (positions) or
    scipy's ``Slerp`` over its finite samples (rotations), NaN where a bracketing sample is
    not finite or outside ``[t_0, t_-1]``; scored samples: estimate finite and shifted truth
    finite at every shift; the lowest RMSE refined by a parabola through its neighbours' mean
    squared errors."""
    good = np.isfinite(gt).all(-1)
    shifted = []
    for d in lags:
        s = t - d
        i = np.clip(np.searchsorted(t, s, side="right") - 1, 0, t.size - 2)
        ok = (s >= t[0]) & (s <= t[-1]) & good[i] & good[i + 1]
        g = np.full(gt.shape, np.nan)
        if kind == "position":
            g[ok] = np.stack([np.interp(s[ok], t[good], gt[good, j]) for j in range(3)], -1)
        else:
            slerp = Slerp(t[good], Rotation.from_quat(gt[good][:, [1, 2, 3, 0]]))
            g[ok] = _wxyz(slerp(s[ok]))
        shifted.append(g)
    shifted = np.stack(shifted)
    use = np.isfinite(est).all(-1) & np.isfinite(shifted).all(-1).all(0)
    if kind == "position":
        err = np.linalg.norm(shifted[:, use] - est[use], axis=-1)
    else:
        e = Rotation.from_quat(est[use][:, [1, 2, 3, 0]])
        err = np.stack([np.degrees((Rotation.from_quat(g[use][:, [1, 2, 3, 0]]) * e.inv())
                                   .magnitude()) for g in shifted])
    rmse = np.sqrt(np.mean(err**2, axis=-1))
    k = int(np.argmin(rmse))
    lag = lags[k]
    if 0 < k < lags.size - 1:
        c = rmse[k - 1:k + 2] ** 2
        den = c[0] - 2 * c[1] + c[2]
        lag += 0.5 * (c[0] - c[2]) / den * (lags[1] - lags[0]) if den > 0 else 0.0
    return lag, rmse[k], int(use.sum())


def test_shift_lag_with_gaps_on_an_uneven_grid_against_brute_force():
    """Uneven sample times, NaN gaps in the truth and lost estimate frames, sign flips of the
    truth's quaternions, a delay that is no multiple of the sample period or of the grid step:
    lag, RMSE and count equal every shift scored by an independent reference, and the lag is
    the delay (positive: estimate behind)."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.6, 1.4, 700)) / 120
    f, ph = rng.uniform(0.2, 1.5, (2, 3, 3))

    def sig(s):
        return np.sin(2 * np.pi * f[None] * s[:, None, None] + ph[None]).sum(-1)

    lags = np.arange(-0.1, 0.3 + 1e-3, 0.002)
    delay = 0.0437
    gt = 0.1 * sig(t)
    est = 0.1 * sig(t - delay) + rng.normal(0, 1e-3, gt.shape)
    gt[300:330] = np.nan
    est[::29] = np.nan
    gq = _wxyz(Rotation.from_rotvec(0.5 * sig(t)))
    eq = _wxyz(Rotation.from_rotvec(0.5 * sig(t - delay) + rng.normal(0, 1e-2, gt.shape)))
    gq[500:520] = np.nan
    gq[::3] *= -1
    eq[::31] = np.nan
    for e, g, kind in ((est, gt, "position"), (eq, gq, "rotation")):
        got = metrics.shift_lag(t, e, g)
        lag, rmse, count = _brute_shift_lag(t, e, g, lags, kind)
        assert got.count == count, kind
        assert got.value == pytest.approx(lag, abs=1e-9), kind
        assert got.rmse == pytest.approx(rmse, rel=1e-9), kind
        assert abs(got.value - delay) < 1e-3, kind


@pytest.mark.parametrize("delay", [0.0015, 0.0237, 0.0415, -0.0113])
def test_shift_lag_of_a_noise_free_delayed_copy_is_the_delay(delay):
    """Without noise the RMSE against the shift is a V (|d - delay| x the speed), and the
    parabola through the RMSE at the best grid point and its neighbours leant towards that
    grid point: 1.5, 23.7, 41.5, -11.3 ms came out up to 0.17 ms off. Through the mean squared
    errors (a parabola near the minimum) the delay is recovered to 10 us; positions and
    rotations, 120 Hz, the default 2 ms grid."""
    t = np.arange(0, 10, 1 / 120)
    f, ph = np.random.default_rng(11).uniform(0.2, 1.2, (2, 3, 3))

    def sig(s):
        return np.sin(2 * np.pi * f[None] * s[:, None, None] + ph[None]).sum(-1)

    pos = metrics.shift_lag(t, 0.1 * sig(t - delay), 0.1 * sig(t))
    rot = metrics.shift_lag(t, _wxyz(Rotation.from_rotvec(0.3 * sig(t - delay))),
                            _wxyz(Rotation.from_rotvec(0.3 * sig(t))))
    assert abs(pos.value - delay) < 1e-5 and abs(rot.value - delay) < 1e-5, (pos, rot)
