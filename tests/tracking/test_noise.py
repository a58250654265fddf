"""Measurement noise estimated from a recording (phjax.tracking.noise)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from phjax.motion.simulate import SensorModel, simulate_measurements, synthetic_head_motion
from phjax.quaternion import quat_conj, quat_mul, quat_to_rotvec
from phjax.tracking.noise import estimate_measurement_noise, with_measurement_noise
from phjax.tracking.tracker import TrackerConfig


def _identity_quats(n):
    return np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("scale", [1.0, 0.2])
def test_recovers_simulated_sensor_noise(seed, scale):
    """Default sensor (5 mm, 1 deg, 5 % dropouts) on synthetic head motion, and 5x less noise:
    the isotropic stds come back within 10 %, every axis within 20 %."""
    gt = synthetic_head_motion(30.0, seed=seed)
    sp, sr = 0.005 * scale, math.radians(1.0) * scale
    meas = simulate_measurements(seed, *gt, SensorModel(sigma_p=sp, sigma_r=sr))
    nz = estimate_measurement_noise(*meas)
    assert abs(float(nz.pos_meas_noise) / sp - 1) < 0.10
    assert abs(float(nz.rot_meas_noise) / sr - 1) < 0.10
    np.testing.assert_array_less(np.abs(np.asarray(nz.pos_std) / sp - 1), 0.20)
    np.testing.assert_array_less(np.abs(np.asarray(nz.rot_std) / sr - 1), 0.20)
    # dropouts remove the windows that contain them, and only those
    lost = ~np.isfinite(np.asarray(meas[1])).all(1)
    windows = np.lib.stride_tricks.sliding_window_view(lost, 4).any(1)
    assert int(nz.pos_windows) == int((~windows).sum()) < len(lost) - 3


def test_white_noise_on_irregular_times_is_unbiased():
    """Pure white noise (no motion) on strongly irregular sample times: the unit-norm weights
    make the residual N(0, sigma^2) whatever the spacing, so the MAD estimate is unbiased."""
    rng = np.random.default_rng(3)
    n = 20000
    t = np.cumsum(rng.uniform(0.005, 0.06, n))
    sigma = np.array([0.002, 0.004, 0.008])
    p = rng.normal(size=(n, 3)) * sigma
    nz = estimate_measurement_noise(t, p, _identity_quats(n))
    np.testing.assert_allclose(np.asarray(nz.pos_std), sigma, rtol=0.03)
    np.testing.assert_allclose(np.asarray(nz.rot_std), 0.0, atol=1e-15)


@settings(max_examples=25)
@given(seed=st.integers(0, 2**31 - 1), order=st.integers(1, 4))
def test_annihilates_polynomials_below_order(seed, order):
    """Noise-free polynomial motion of degree < order on random times gives zero residuals
    (position and orientation), degree == order does not."""
    rng = np.random.default_rng(seed)
    n = 40
    t = 100.0 + np.cumsum(rng.uniform(0.01, 0.05, n))
    s = t - t[0]
    coef = rng.normal(size=(order + 1, 3))
    low = sum(coef[j] * s[:, None] ** j for j in range(order))
    high = low + coef[order] * s[:, None] ** order
    a = 0.3 * rng.normal(size=order)  # rotation angle about z, polynomial of degree < order
    ang = sum(a[j] * s ** j for j in range(order))
    q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], axis=1)
    nz = estimate_measurement_noise(t, low, q, order=order)
    np.testing.assert_allclose(np.asarray(nz.pos_std), 0.0, atol=1e-9 * (1 + np.abs(low).max()))
    np.testing.assert_allclose(np.asarray(nz.rot_std), 0.0, atol=1e-9)
    assert np.all(np.asarray(estimate_measurement_noise(t, high, q, order=order).pos_std) > 0)


def test_matches_null_space_reference():
    """Independent reference: per window the residual is the projection on the (scipy) null
    space of the Vandermonde matrix; the MAD std of those residuals (world-frame rotation
    vectors relative to the window's second sample for orientation) matches."""
    rng = np.random.default_rng(7)
    n, k = 300, 3
    t = np.cumsum(rng.uniform(0.02, 0.045, n))
    p = np.cumsum(rng.normal(size=(n, 3)) * 0.01, axis=0)
    rv = np.cumsum(rng.normal(size=(n, 3)) * 0.02, axis=0)
    q = np.asarray(jax.vmap(lambda v: jnp.concatenate([jnp.cos(jnp.linalg.norm(v) / 2)[None],
                                                       jnp.sinc(jnp.linalg.norm(v) / 2 / jnp.pi)
                                                       * v / 2]))(jnp.asarray(rv)))
    windows = np.arange(n - k)[:, None] + np.arange(k + 1)
    qw_all = q[windows]
    rv_all = np.asarray(quat_to_rotvec(quat_mul(qw_all, quat_conj(qw_all[:, 1:2]))))
    res_p, res_r = [], []
    for i in range(n - k):
        tw = t[i:i + k + 1] - t[i]
        c = scipy.linalg.null_space(np.vander(tw, k, increasing=True).T)[:, 0]
        c *= np.sign(c[-1])  # the divided difference's sign: positive weight on the last sample
        res_p.append(c @ p[i:i + k + 1])
        res_r.append(c @ rv_all[i])

    def mad(r):
        r = np.asarray(r)
        return 1.482602218505602 * np.median(np.abs(r - np.median(r, 0)), 0)

    nz = estimate_measurement_noise(t, p, q)
    np.testing.assert_allclose(np.asarray(nz.pos_std), mad(res_p), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(nz.rot_std), mad(res_r), rtol=1e-9)


def test_missing_parts_and_jit():
    """Orientation-only data: NaN position stds with zero windows, orientation still estimated;
    NaN times and non-increasing times drop their windows; jit gives the same result."""
    rng = np.random.default_rng(0)
    n = 200
    t = np.arange(n) / 30.0
    p = rng.normal(size=(n, 3)) * 0.003
    q = _identity_quats(n)
    q[:, 1:] = rng.normal(size=(n, 3)) * 0.005
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    nz = estimate_measurement_noise(t, np.full((n, 3), np.nan), q)
    assert int(nz.pos_windows) == 0 and np.all(np.isnan(np.asarray(nz.pos_std)))
    assert int(nz.rot_windows) == n - 3 and np.all(np.isfinite(np.asarray(nz.rot_std)))
    t2 = t.copy()
    t2[50] = np.nan
    t2[100] = t2[99]
    nz2 = estimate_measurement_noise(t2, p, q)
    assert int(nz2.pos_windows) == n - 3 - 4 - 3  # 4 windows hold t[50]; 3 hold the pair 99/100
    jit = jax.jit(estimate_measurement_noise, static_argnames="order")(t2, p, q)
    np.testing.assert_allclose(np.asarray(jit.pos_std), np.asarray(nz2.pos_std), rtol=1e-12)
    none = estimate_measurement_noise(t, np.full((n, 3), np.nan), np.full((n, 4), np.nan))
    assert np.all(np.isnan(np.asarray(none.rot_std))) and int(none.rot_windows) == 0


def test_bad_input_clear_errors():
    t, p, q = np.arange(10.0), np.zeros((10, 3)), _identity_quats(10)
    with pytest.raises(ValueError, match="expected times"):
        estimate_measurement_noise(t, p[:, :2], q)
    with pytest.raises(ValueError, match="expected times"):
        estimate_measurement_noise(t[:9], p, q)
    with pytest.raises(ValueError, match="order must be"):
        estimate_measurement_noise(t, p, q, order=0)
    with pytest.raises(ValueError, match="at least order"):
        estimate_measurement_noise(t[:3], p[:3], q[:3])
    with pytest.raises(ValueError, match="pos_meas_noise must be"):
        with_measurement_noise(TrackerConfig(), pos=-1.0)
    with pytest.raises(ValueError, match="rot_meas_noise must be"):
        with_measurement_noise(TrackerConfig(), rot=float("nan"))


def test_with_measurement_noise_sets_both_filters():
    rng = np.random.default_rng(1)
    n = 300
    t = np.arange(n) / 30.0
    nz = estimate_measurement_noise(t, rng.normal(size=(n, 3)) * 0.002, _identity_quats(n))
    cfg = with_measurement_noise(TrackerConfig(), nz, rot=0.02)
    assert cfg.imm.pos_meas_noise == cfg.kalman.pos_meas_noise == pytest.approx(
        float(nz.pos_meas_noise))
    assert cfg.imm.rot_meas_noise == cfg.kalman.rot_meas_noise == 0.02
    # noise-free orientation: a zero std is rejected (the caller supplies one, as above)
    assert float(nz.rot_meas_noise) == 0.0
    with pytest.raises(ValueError, match="rot_meas_noise"):
        with_measurement_noise(TrackerConfig(), nz)
    cfg = with_measurement_noise(TrackerConfig(imm=None), nz, rot=0.01)
    assert cfg.imm is None and cfg.kalman.rot_meas_noise == 0.01
    assert cfg.horizon == TrackerConfig().horizon


def test_cli_smooth_measurement_noise_auto(tmp_path):
    """``phjax smooth --measurement-noise auto`` estimates the noise of the file it reads (a
    simulated 2 mm / 0.5 deg sensor) and prints it; the stream differs from the default's."""
    import subprocess
    import sys

    import phjax as pj
    from phjax.io import Trajectory, read_trajectory, write_trajectory

    t, p, q = pj.synthetic_head_motion(duration=6.0, seed=3)
    sensor = pj.SensorModel(sigma_p=0.002, sigma_r=float(np.deg2rad(0.5)), dropout=0.0)
    mt, mp, mq = (np.asarray(x, np.float64) for x in pj.simulate_measurements(1, t, p, q, sensor))
    src = tmp_path / "meas.txt"
    write_trajectory(src, Trajectory(mt, mp, mq))
    outs = {}
    for noise in ("auto", "config"):
        out = tmp_path / f"{noise}.txt"
        r = subprocess.run([sys.executable, "-m", "phjax", "smooth", str(src), "-o", str(out),
                            "--measurement-noise", noise, "--no-cache"],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        outs[noise] = read_trajectory(out).positions
        if noise == "auto":
            line = next(x for x in r.stdout.splitlines() if x.startswith("measurement noise"))
            mm = float(line.split(":")[1].split("mm")[0])
            assert 1.6 < mm < 2.4, line  # the simulated 2 mm, within 20 %
    assert np.max(np.abs(outs["auto"] - outs["config"])) > 1e-5


@pytest.mark.parametrize("sigma_mm", [2.0, 20.0])
def test_measurement_noise_floor_choice(sigma_mm):
    """``--measurement-noise floor``: the configured noise where the file's white noise is
    lower (a 2 mm sensor: the config's 5 mm, unchanged), the estimate where it is higher
    (20 mm: as 'auto')."""
    import argparse

    import phjax as pj
    from phjax.cli._tune import with_noise_from_args

    t, p, q = pj.synthetic_head_motion(duration=6.0, seed=3)
    sensor = pj.SensorModel(sigma_p=sigma_mm / 1e3, sigma_r=float(np.deg2rad(sigma_mm / 4)),
                            dropout=0.0)
    meas = [np.asarray(x, np.float64) for x in pj.simulate_measurements(1, t, p, q, sensor)]
    got = {}
    for value in ("floor", "auto"):
        cfg, desc = with_noise_from_args(argparse.Namespace(measurement_noise=value), None,
                                         *meas)
        got[value] = (float(cfg.imm.pos_meas_noise), float(cfg.imm.rot_meas_noise))
        assert cfg.kalman.pos_meas_noise == cfg.imm.pos_meas_noise and desc
    if sigma_mm < 5:
        assert got["floor"] == pytest.approx((0.005, math.radians(1.0)))
        assert got["auto"][0] < 0.003
    else:
        assert got["floor"] == got["auto"] and got["auto"][0] > 0.015
