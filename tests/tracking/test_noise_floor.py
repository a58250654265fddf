"""The causal stream's online measurement-noise floor (``TrackerConfig.noise_window``)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import phjax
from phjax.motion.simulate import SensorModel, simulate_measurements, synthetic_head_motion
from phjax.tracking import TrackerConfig, track
from phjax.tracking._noise_core import noise_monitor_std
from phjax.tracking.noise import estimate_measurement_noise, with_measurement_noise
from phjax.tracking.tracker import _noise_min_count
from phjax.tracking.tuning import config_from_dict, config_to_dict


def _recording(seconds, sigma_p, sigma_r, seed=0, dropout=0.05):
    gt = synthetic_head_motion(seconds, seed=seed)
    meas = simulate_measurements(seed, *gt, SensorModel(sigma_p=sigma_p, sigma_r=sigma_r,
                                                        dropout=dropout))
    render = np.arange(meas[0][0] + 1.0, gt[0][-1], 1 / 120)
    gp = np.stack([np.interp(render, gt[0], gt[1][:, i]) for i in range(3)], 1)
    return [np.asarray(x) for x in meas], render, gp


def _rmse(config, meas, render, gp):
    p, _ = track(*meas, render, config=config)
    return float(np.sqrt(np.mean(np.sum((np.asarray(p) - gp) ** 2, axis=1))))


def _final_monitor(config, meas):
    stream = phjax.TrackerStream(config, dtype=jnp.float64, fast_start=False)
    for t, p, q in zip(*meas):
        stream.update(t, p, q)
    return stream.state.noise


@pytest.mark.parametrize("seed", [0, 1])
def test_online_estimate_agrees_with_the_offline_estimate(seed):
    """Sensor 4x / 3x noisier than configured, 60 s: the monitor's running estimate (a
    winsorised mean over ~400 windows) agrees with estimate_measurement_noise (a median over
    every window of the recording, an independent robust estimator) within 8 % (measured
    within 4.6 % on seeds 0-3; the running mean's own sampling error is ~3.5 %)."""
    meas, _, _ = _recording(60.0, 0.02, math.radians(3.0), seed=seed)
    config = TrackerConfig(noise_window=400)
    mon = _final_monitor(config, meas)
    pos, rot = (float(x) for x in noise_monitor_std(mon, _noise_min_count(config)))
    offline = estimate_measurement_noise(*meas)
    assert abs(pos / float(offline.pos_meas_noise) - 1) < 0.08, (pos, offline)
    assert abs(rot / float(offline.rot_meas_noise) - 1) < 0.08, (rot, offline)
    # what a status display reads: the same numbers from the host, max'ed with the config
    stream = phjax.TrackerStream(config, dtype=jnp.float64, fast_start=False)
    stream.state = dataclasses.replace(stream.state, noise=mon)
    assert stream.measurement_noise() == pytest.approx((pos, rot), rel=1e-12)
    assert phjax.TrackerStream().measurement_noise() == pytest.approx(
        (0.005, math.radians(1.0)))
    # dropouts: a window with a lost frame is not counted (as offline)
    assert int(mon.count_p) == int(offline.pos_windows)
    assert int(mon.count_r) == int(offline.rot_windows)


def test_gross_errors_move_the_estimate_little():
    """2 % of the frames 0.2 m / 30 deg off (misaligned front-end frames) in 10 mm / 2 deg
    noise: the winsorised running estimate stays within 25 % of the median-based offline one
    (measured 1.14 / 1.10 of it for position / orientation; a plain running mean of the
    squared residuals gives 1.64 / 1.52)."""
    meas, _, _ = _recording(60.0, 0.01, math.radians(2.0), seed=8, dropout=0.0)
    rng = np.random.default_rng(8)
    bad = rng.choice(len(meas[0]), size=len(meas[0]) // 50, replace=False)
    p, q = meas[1].copy(), meas[2].copy()
    p[bad] += rng.normal(size=(len(bad), 3)) * 0.2 / math.sqrt(3)
    q[bad] = np.asarray(phjax.quaternion.quat_mul(
        phjax.quaternion.quat_from_rotvec(np.tile([math.radians(30.0), 0, 0], (len(bad), 1))),
        q[bad]))
    meas = [meas[0], p, q]
    config = TrackerConfig(noise_window=400)
    pos, rot = (float(x) for x in noise_monitor_std(_final_monitor(config, meas),
                                                     _noise_min_count(config)))
    offline = estimate_measurement_noise(*meas)
    assert abs(pos / float(offline.pos_meas_noise) - 1) < 0.25, (pos, offline)
    assert abs(rot / float(offline.rot_meas_noise) - 1) < 0.25, (rot, offline)


@pytest.mark.parametrize("which", ["default", "live"])
def test_a_noisier_sensor_is_smoothed_as_its_noise_needs(which):
    """20 mm / 3 deg sensor, filters configured for 5 mm / 1 deg. The default IMM takes the
    noise for manoeuvres; the live config's single-model filter rejects most frames at its
    innovation gate (130 mm RMSE). With the floor the stream's position RMSE is within 8 % of
    the stream told the true noise (measured 1.002-1.012x on seeds 3, 6, 7 for the default,
    1.000-1.008x for the live config) and below 0.6x (default; measured 0.48-0.49x) / 0.3x
    (live; measured 0.13-0.16x) of the stream without it."""
    from phjax.live import live_tracker_config

    meas, render, gp = _recording(30.0, 0.02, math.radians(3.0), seed=3)
    on = TrackerConfig(noise_window=60) if which == "default" else live_tracker_config()
    off = dataclasses.replace(on, noise_window=0)
    without = _rmse(off, meas, render, gp)
    floor = _rmse(on, meas, render, gp)
    told = _rmse(with_measurement_noise(off, pos=0.02, rot=math.radians(3.0)), meas, render, gp)
    assert floor < 1.08 * told, (floor, told)
    assert floor < (0.6 if which == "default" else 0.3) * without, (floor, without)


@pytest.mark.parametrize("imm", [True, False])
def test_a_floor_never_lowers_the_configured_noise(imm):
    """A sensor 5x more precise than configured: the estimate stays below the configured
    noise, so the stream equals the stream without the floor (to rounding)."""
    meas, render, _ = _recording(20.0, 0.001, math.radians(0.2), seed=4)
    base = TrackerConfig() if imm else dataclasses.replace(TrackerConfig(), imm=None)
    a = track(*meas, render, config=base)
    b = track(*meas, render, config=dataclasses.replace(base, noise_window=60))
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-12)
    mon = _final_monitor(dataclasses.replace(base, noise_window=60), meas)
    pos, rot = noise_monitor_std(mon, 15)
    assert 0 < float(pos) < 0.002 and 0 < float(rot) < math.radians(0.4)


def test_gradients_finite_at_degenerate_inputs():
    """A still head measured without noise (every residual 0: the estimate's root at 0), a lost
    first frame and dropouts: the gradients with respect to every float field and to the
    measurements are finite; on a moving head with 10 mm noise (twice the configured: the
    estimate is the floor's active side once it has 8 residuals) the one of the configured
    measurement noise is still nonzero (the warm-up frames and the clipping scale use it)."""
    n = 90
    t = np.arange(n) / 30.0
    p = np.tile([0.1, 0.0, 0.5], (n, 1))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    p[0] = q[0] = np.nan
    p[[10, 11, 40]] = np.nan
    rng = np.random.default_rng(0)
    p_moving = p + np.outer(np.sin(t), [0.05, 0.0, 0.0]) + rng.normal(0, 0.01, p.shape)
    render = np.arange(0.1, t[-1], 1 / 120)

    def loss(cfg, pos):
        out_p, out_q = track(t, pos, q, render, config=cfg)
        return jnp.nansum(out_p**2) + jnp.nansum(out_q**2)

    # the floor's code is the same for both filters; the single-model one compiles faster
    cfg = TrackerConfig(imm=None, noise_window=16)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))  # one program for both recordings
    for pos in (p, p_moving):
        g_cfg, g_pos = grad(cfg, jnp.asarray(pos))
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(g_cfg))
        if pos is p_moving:  # (a still head measured exactly is tracked exactly, whatever R)
            assert float(g_cfg.kalman.pos_meas_noise) != 0
        ok = np.isfinite(pos).all(1)
        assert np.isfinite(np.asarray(g_pos)[ok]).all()


def test_float32_stream_and_config_round_trip():
    meas, render, gp = _recording(10.0, 0.02, math.radians(3.0), seed=5)
    cfg = TrackerConfig(noise_window=60)
    p32, q32 = track(*meas, render, config=cfg, dtype=jnp.float32)
    p64, _ = track(*meas, render, config=cfg)
    assert p32.dtype == jnp.float32 and np.isfinite(np.asarray(p32)).all()
    np.testing.assert_allclose(np.asarray(p32), np.asarray(p64), atol=2e-4)
    assert config_from_dict(config_to_dict(cfg)).noise_window == 60
    assert config_from_dict(config_to_dict(TrackerConfig())).noise_window == 0


@pytest.mark.parametrize("bad", [-1, 3, 7, 2.5, True, "60", None])
def test_bad_noise_window_is_a_clear_error(bad):
    with pytest.raises(ValueError, match=r"TrackerConfig.noise_window must be an integer, 0 "
                                         r"\(off\) or >= 8"):
        TrackerConfig(noise_window=bad)


def test_live_configs_use_the_floor():
    from phjax._live_defaults import LIVE_NOISE_WINDOW
    from phjax.live import live_tracker_config

    assert live_tracker_config().noise_window == LIVE_NOISE_WINDOW == 60
    assert live_tracker_config(depth_free=True).noise_window == LIVE_NOISE_WINDOW
    assert live_tracker_config(base=TrackerConfig()).noise_window == 0


def test_state_and_config_must_agree():
    """The monitor is part of the state: a state made without it (or with it) and a config
    with it (or without) is a clear error, not a silent floor of 0 or a crash."""
    from phjax.tracking import tracker_init, tracker_update

    p, q = np.zeros(3), np.array([1.0, 0, 0, 0])
    for made, used in ((TrackerConfig(), TrackerConfig(noise_window=60)),
                       (TrackerConfig(noise_window=60), TrackerConfig())):
        with pytest.raises(ValueError, match="the state was made for another "
                                             "TrackerConfig.noise_window"):
            tracker_update(used, tracker_init(made), 0.0, p, q)
    stream = phjax.TrackerStream()
    with pytest.raises(ValueError, match="noise_window on or off"):
        stream.set_config(TrackerConfig(noise_window=60))
    stream.set_config(TrackerConfig(horizon=0.05))  # the same structure: accepted
