"""Tests for phjax.motion.simulate: sensor model statistics and the synthetic head-motion generator."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import find_peaks, welch
from scipy.spatial.transform import Rotation

from phjax.quaternion import quat_conj, quat_mul, quat_to_rotvec
from phjax.motion.resample import finite_difference_velocities, interpolate_poses
from phjax.motion.simulate import SensorModel, simulate_measurements, synthetic_head_motion

NOISELESS = SensorModel(sigma_p=0.0, sigma_r=0.0, dropout=0.0)


@pytest.fixture(scope="module")
def head():
    return synthetic_head_motion(duration=20.0, rate=240.0, seed=3)


def _smooth_gt(duration=10.0, rate=200.0):
    t = np.arange(int(duration * rate) + 1) / rate
    p = np.stack([np.sin(t), np.cos(0.5 * t), 0.1 * t], -1)
    rv = np.stack([0.3 * np.sin(t), 0.5 * t, 0 * t], -1)
    q = Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]]
    return t, p, q


def test_sensor_model_defaults_and_module():
    m = SensorModel()
    assert isinstance(m, eqx.Module)
    assert (m.rate, m.sigma_p, m.dropout, m.jitter, m.latency) == (30.0, 0.005, 0.05, 0.0, 0.0)
    assert m.sigma_r == pytest.approx(np.pi / 180)


def test_deterministic_grid_and_dropouts():
    gt = _smooth_gt()
    a = simulate_measurements(7, *gt)
    b = simulate_measurements(jax.random.key(7), *gt)
    c = simulate_measurements(8, *gt)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(np.nan_to_num(a[1]), np.nan_to_num(c[1]))
    t, p, q = map(np.asarray, a)
    np.testing.assert_allclose(t, np.arange(301) / 30.0, atol=1e-12)  # 10 s at 30 Hz, ends included
    lost_p, lost_q = np.isnan(p).any(1), np.isnan(q).any(1)
    np.testing.assert_array_equal(lost_p, lost_q)
    assert np.isnan(p[lost_p]).all() and np.isfinite(t).all()
    # dropout count is Binomial(n, 0.05): within 5 standard deviations over 10 seeds
    n_lost = sum(np.isnan(simulate_measurements(s, *gt)[1][:, 0]).sum() for s in range(10))
    n = 10 * 301
    assert abs(n_lost - 0.05 * n) < 5 * np.sqrt(n * 0.05 * 0.95)


def test_noise_statistics_match_model():
    gt = _smooth_gt(duration=60.0)
    model = SensorModel(rate=100.0, sigma_p=0.01, sigma_r=0.02, dropout=0.0)
    t, p, q = simulate_measurements(0, *gt, model=model)
    p_true, q_true = interpolate_poses(*gt, t)
    dp = np.asarray(p - p_true)
    dr = np.asarray(quat_to_rotvec(quat_mul(q, quat_conj(q_true))))  # world-frame noise vector
    n = dp.size  # 3 * 6001 samples; relative std error of a std estimate ~ 1 / sqrt(2 n)
    for res, sigma in ((dp, 0.01), (dr, 0.02)):
        assert abs(res.std() / sigma - 1) < 5 / np.sqrt(2 * n)
        assert np.all(np.abs(res.mean(0)) < 5 * sigma / np.sqrt(res.shape[0]))
        assert abs(np.corrcoef(res.T)[0, 1]) < 5 / np.sqrt(res.shape[0])  # independent axes


def test_noiseless_samples_follow_ground_truth_with_latency_and_jitter():
    gt = _smooth_gt()
    model = SensorModel(rate=50.0, sigma_p=0.0, sigma_r=0.0, dropout=0.0, jitter=0.2, latency=0.035)
    t, p, q = map(np.asarray, simulate_measurements(1, *gt, model=model))
    sample_t = t - 0.035
    assert np.all(np.diff(t) > 0)
    assert sample_t[0] >= 0 and sample_t[-1] <= gt[0][-1] + 1e-12
    dev = (sample_t - np.arange(len(t)) / 50.0) * 50.0  # in periods
    assert np.abs(dev).max() <= 0.45 + 1e-9
    assert 0.15 < dev[1:-1].std() < 0.25
    p_true, q_true = map(np.asarray, interpolate_poses(*gt, sample_t))
    np.testing.assert_allclose(p, p_true, atol=1e-12)
    np.testing.assert_allclose(q, q_true, atol=1e-12)


def test_orientation_only_ground_truth_and_float32():
    t, p, q = _smooth_gt()
    tm, pm, qm = simulate_measurements(2, t, np.full_like(p, np.nan), q)
    lost = np.isnan(np.asarray(qm)).any(1)
    assert np.isnan(np.asarray(pm)).all()
    assert np.isfinite(np.asarray(qm)[~lost]).all() and (~lost).sum() > 250

    out = simulate_measurements(2, t.astype(np.float32), p.astype(np.float32), q.astype(np.float32))
    assert all(x.dtype == jnp.float32 for x in out)


def test_frames_inside_ground_truth_gaps_are_lost_not_made_up():
    """A frame whose instant lies strictly inside a ground-truth gap longer than ``max_gt_gap``
    (default: 0.1 s or 2.5 median steps, the evaluation's rule) is lost as a whole; before,
    the sensor "measured" a straight line across the gap. Frames at the gap's end samples,
    outside it, and with ``max_gt_gap=inf`` are measured as before."""
    t, p, q = _smooth_gt()  # 200 Hz for 10 s
    hole = (t > 3.0 + 1e-9) & (t < 3.5 - 1e-9)  # a 0.5 s gap: samples 3.0 and 3.5 bracket it
    gap = (t[~hole], p[~hole], q[~hole])
    tm, pm, qm = map(np.asarray, simulate_measurements(0, *gap, model=NOISELESS))
    inside = (tm > 3.0 + 1e-9) & (tm < 3.5 - 1e-9)
    assert inside.sum() == 14  # 3.0 < k / 30 < 3.5
    assert np.isnan(pm[inside]).all() and np.isnan(qm[inside]).all()
    assert np.isfinite(pm[~inside]).all() and np.isfinite(qm[~inside]).all()
    ref = [np.asarray(x) for x in interpolate_poses(*gap, tm[~inside])]
    np.testing.assert_allclose(pm[~inside], ref[0], atol=1e-12)
    np.testing.assert_allclose(qm[~inside], ref[1], atol=1e-12)
    # the gap's length against the limit: bridged when the limit is longer, lost when shorter
    for limit, lost in ((float("inf"), 0), (0.6, 0), (0.4, 14)):
        _, pl, ql = map(np.asarray, simulate_measurements(0, *gap, model=NOISELESS,
                                                          max_gt_gap=limit))
        assert np.isnan(ql).any(1).sum() == lost and np.isnan(pl).any(1).sum() == lost
    # orientation-only ground truth: its orientation gap loses the frame
    _, pl, ql = map(np.asarray, simulate_measurements(
        0, gap[0], np.full_like(gap[1], np.nan), gap[2], model=NOISELESS))
    assert np.isnan(pl).all() and np.isnan(ql).any(1).sum() == 14
    # position-only ground truth (NaN or zero quaternions, as the tracker accepts it):
    # likewise its position gap, and no other frame
    for none in (np.full_like(gap[2], np.nan), np.zeros_like(gap[2])):
        _, pl, ql = map(np.asarray, simulate_measurements(0, gap[0], gap[1], none,
                                                          model=NOISELESS))
        assert np.isnan(ql).all() and np.isnan(pl).any(1).sum() == 14
    # a gap in the positions only (orientation sampled throughout) loses the frame as a whole
    p_hole = p.copy()
    p_hole[hole] = np.nan
    _, pl, ql = map(np.asarray, simulate_measurements(0, t, p_hole, q, model=NOISELESS))
    assert np.isnan(ql).any(1).sum() == 14 and np.isnan(pl).any(1).sum() == 14
    # the default rule follows the ground truth's own rate: a 5 Hz trace (steps 0.2 s) keeps
    # every frame, since 2.5 steps (0.5 s) exceed its steps
    sparse = tuple(x[::40] for x in (t, p, q))
    _, pl, _ = map(np.asarray, simulate_measurements(0, *sparse, model=NOISELESS))
    assert np.isfinite(pl).all()
    with pytest.raises(ValueError, match="max_gt_gap must be positive"):
        simulate_measurements(0, t, p, q, max_gt_gap=0.0)


@pytest.mark.parametrize(
    "bad", [dict(rate=0.0), dict(dropout=1.0), dict(sigma_p=-1.0), dict(jitter=-0.1)]
)
def test_invalid_model_raises(bad):
    with pytest.raises(ValueError):
        simulate_measurements(0, *_smooth_gt(), model=SensorModel(**bad))


def test_mismatched_ground_truth_names_the_callers_shapes():
    """The error named the padded shapes ((64,), (65, 3), ...) or came from NumPy's concatenate."""
    t, p, q = _smooth_gt()
    with pytest.raises(ValueError, match=rf"got \({t.size - 1},\), \({t.size}, 3\)"):
        simulate_measurements(0, t[:-1], p, q)
    with pytest.raises(ValueError, match=rf"\({t.size}, 3\)$"):
        simulate_measurements(0, t, p, q[:, :3])


# --------------------------------------------------------------------------- synthetic head motion


def test_head_motion_shapes_determinism_and_unit_quaternions(head):
    t, p, q = head
    assert t.shape == (4801,) and p.shape == (4801, 3) and q.shape == (4801, 4)
    np.testing.assert_allclose(t[-1], 20.0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    assert np.all(np.sum(q[1:] * q[:-1], 1) > 0)  # hemisphere-continuous
    t2, p2, q2 = synthetic_head_motion(duration=20.0, rate=240.0, seed=3)
    np.testing.assert_array_equal(p, p2)
    assert not np.allclose(p, synthetic_head_motion(duration=20.0, seed=4)[1])


def test_head_motion_speeds_and_ranges():
    peaks = []
    for seed in range(4):
        t, p, q = synthetic_head_motion(duration=60.0, rate=240.0, seed=seed)
        _, w = finite_difference_velocities(t, p, q)
        speed = np.degrees(np.linalg.norm(np.asarray(w), axis=1))
        idx, _ = find_peaks(speed, height=30.0, distance=int(0.3 * 240))
        peaks.append(speed[idx])
        fwd = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply([0, 0, -1.0])
        elevation = np.degrees(np.arcsin(fwd[:, 1]))
        assert np.all(np.abs(elevation) < 32)  # pitch within about +-30 deg
        up = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply([0, 1.0, 0])
        assert np.degrees(np.arccos(up[:, 1])).max() < 40  # no extreme head tilts
        assert np.all(np.abs(p - p.mean(0)) < 0.25)  # seated: within +-25 cm
    peaks = np.concatenate(peaks)
    assert len(peaks) > 100  # roughly one gaze shift per 1.5 s
    assert peaks.max() <= 320  # up to ~300 deg/s (+ sway and tremor)
    assert 50 <= np.median(peaks) <= 150  # typical 50-150 deg/s
    assert np.mean(peaks > 150) > 0.05  # but some fast turns


def test_head_position_follows_neck_pivot_model(head):
    t, p, q = head
    offset = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply([0, 0.10, -0.08])
    torso = p - offset  # pivot + slow torso sway
    assert np.ptp(torso, axis=0).max() < 0.08  # a few cm of sway
    assert np.ptp(torso[:, 1]) < np.ptp(torso[:, 0])  # less vertical sway
    # torso sway is slow: its speed stays well below the head speed during turns
    v_torso = np.linalg.norm(np.diff(torso, axis=0), axis=1) * 240
    assert v_torso.max() < 0.1


def test_head_motion_is_c2_and_contains_tremor():
    # C2 with bounded jerk: the largest step in acceleration shrinks linearly with the step.
    def max_accel_step(rate):
        t, p, q = synthetic_head_motion(duration=20.0, rate=rate, seed=5)
        h = 1 / rate
        x = np.concatenate([p, q], 1)
        acc = np.diff(x, 2, axis=0) / h**2
        return np.abs(np.diff(acc, axis=0)).max()

    assert max_accel_step(960.0) < 0.3 * max_accel_step(240.0)

    t, p, q = synthetic_head_motion(duration=20.0, rate=240.0, seed=5)
    _, w = finite_difference_velocities(t, p, q)
    f, psd = welch(np.asarray(w), fs=240.0, nperseg=1024, axis=0)
    psd = psd.sum(1)
    tremor = psd[(f >= 8) & (f <= 12)].mean()
    assert tremor > 10 * psd[(f >= 15) & (f <= 40)].mean()
    # tremor amplitude: 8-12 Hz angular velocity RMS of 0.1-deg sinusoids ~ 2 pi f 0.1 deg / sqrt 2
    band_rms = np.sqrt(psd[(f >= 7) & (f <= 13)].sum() * (f[1] - f[0]))
    assert 3 < np.degrees(band_rms) < 20


def test_simulate_batch_equals_each_recording_alone():
    """A NaN-padded batch of ground truths: recording i is simulated alone with key i of the
    split key (or its own seed), results NaN-padded to the longest."""
    from phjax.batch import pad_recordings, unpad

    gts = [synthetic_head_motion(duration=d, rate=120.0, seed=i) for i, d in enumerate((1.0, 1.5))]
    t, p, q = pad_recordings(*zip(*gts))
    model = SensorModel(dropout=0.3, jitter=0.1)
    keys = jax.random.split(jax.random.key(7), 2)
    bt, bp, bq = simulate_measurements(7, t.reshape(1, 2, -1), p.reshape(1, 2, -1, 3),
                                       q.reshape(1, 2, -1, 4), model)
    assert bt.shape[:2] == (1, 2) and bp.shape == bt.shape + (3,)
    per_seed = simulate_measurements(np.array([3, 4]), t, p, q, model)
    for i, (gt, rec, rec_s) in enumerate(zip(gts, unpad(bt[0], bp[0], bq[0]),
                                             unpad(*per_seed))):
        for a, b in zip(rec, simulate_measurements(keys[i], *gt, model)):
            np.testing.assert_array_equal(a, np.asarray(b))
        for a, b in zip(rec_s, simulate_measurements(3 + i, *gt, model)):
            np.testing.assert_array_equal(a, np.asarray(b))
    assert np.isnan(np.asarray(bt[0, 0])).sum() == 15  # 31 vs 46 samples at 30 Hz
    with pytest.raises(ValueError, match="key_or_seed"):
        simulate_measurements(np.array([1, 2, 3]), t, p, q, model)


def test_lengths_in_one_size_class_share_one_program_and_equal_unpadded(head):
    """simulate_measurements and interpolate_poses pad to size classes: a second length in
    the same class compiles nothing (counted with JAX's compile events), and each result
    equals the computation on the caller's own shapes (the jitted interpolation core on the
    unpadded arrays, random draws of the unpadded length) to 1e-12 in float64."""
    import jax.monitoring

    from phjax import _sizes
    from phjax.motion import resample

    t, p, q = head  # 240 Hz; 2100 and 2600 rows share a class, and so do their samples
    model = SensorModel(jitter=0.3, dropout=0.2, latency=0.01)
    sizes = {(_sizes.size_class(n, _sizes.MIN_FRAMES),
              _sizes.size_class(int(n / 240 * 30) + 1, _sizes.MIN_RENDER)) for n in (2100, 2600)}
    assert len(sizes) == 1
    compiles = []

    def on_duration(event, duration, fun_name="", **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(fun_name)

    simulate_measurements(0, t[:2100], p[:2100], q[:2100], model)  # compiles the class
    interpolate_poses(t[:2100], p[:2100], q[:2100], t[:2100:7] + 1e-3, max_gap=0.01)
    jax.monitoring.register_event_duration_secs_listener(on_duration)
    try:
        mt, mp, mq = simulate_measurements(7, t[:2600], p[:2600], q[:2600], model)
        gp, gq = interpolate_poses(t[:2600], p[:2600], q[:2600], mt, max_gap=0.01)
    finally:
        jax.monitoring.unregister_event_duration_listener(on_duration)
    assert compiles == []
    # the reference on the unpadded shapes
    k_jit, k_p, k_r, k_drop = jax.random.split(jax.random.key(7), 4)
    n, m = 2600, mt.shape[0]
    s = t[0] + np.arange(m) / 30.0
    s = np.clip(s + np.clip(np.asarray(jax.random.normal(k_jit, (m,))) * 0.3, -0.45, 0.45) / 30,
                t[0], t[n - 1])
    np.testing.assert_allclose(np.asarray(mt), s + 0.01, rtol=0, atol=1e-12)
    rp, rq = resample._interpolate_poses(t[:n], p[:n], q[:n], s, None)
    rp = rp + 0.005 * jax.random.normal(k_p, (m, 3))
    rq = quat_mul(jax.vmap(_rotvec_quat)(np.deg2rad(1.0) * jax.random.normal(k_r, (m, 3))), rq)
    lost = np.asarray(jax.random.uniform(k_drop, (m,)) < 0.2)
    assert 0.1 < lost.mean() < 0.3
    np.testing.assert_array_equal(np.isnan(np.asarray(mp)).any(-1), lost)
    np.testing.assert_allclose(np.asarray(mp)[~lost], np.asarray(rp)[~lost], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(mq)[~lost], np.asarray(rq)[~lost], rtol=0, atol=1e-12)
    for got, ref in zip((gp, gq), resample._interpolate_poses(t[:n], p[:n], q[:n], mt, 0.01)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=0, atol=1e-12)
        assert np.isnan(np.asarray(got)).any() == np.isnan(np.asarray(ref)).any()


def _rotvec_quat(v):
    """``wxyz`` quaternion of a rotation vector (independent of phjax.quaternion)."""
    a = jnp.linalg.norm(v)
    return jnp.concatenate([jnp.cos(a / 2)[None], jnp.sinc(a / (2 * jnp.pi)) / 2 * v])


def test_epoch_times_in_float32_are_an_error_not_a_collapse():
    """Unix times (1.7e9 s) in float32 are rounded to 128 s: every measurement time came out
    equal, silently. The interpolation runs relative to the first time (so the result at
    relative times is unchanged) and times float32 cannot return are an error."""
    t, p, q = _smooth_gt()
    t32 = t.astype(np.float64)
    with pytest.raises(ValueError, match="pass times relative to the first"):
        simulate_measurements(0, t32 + 1.7e9, p.astype(np.float32), q.astype(np.float32))
    out = simulate_measurements(0, t32, p.astype(np.float32), q.astype(np.float32))
    assert np.all(np.diff(np.asarray(out[0])) > 0)


def test_head_motion_memory_is_linear_in_its_length():
    """``synthetic_head_motion`` built a (gaze segments, samples) profile: its memory grew as
    the square of the length (1.5 TiB for ``phjax track-rgbd synthetic:3000000``, found by
    review). An hour at 30 Hz (the dense profile alone: about 2.2 GB) now peaks at a few tens
    of MB (measured 38 MB; bound 150 MB); equal to the dense form to 6e-16 (checked when
    changed)."""
    import tracemalloc

    from phjax.motion.simulate import synthetic_head_motion

    tracemalloc.start()
    try:
        t, p, q = synthetic_head_motion(3600.0, 30.0, 0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert t.size == 108001 and np.isfinite(p).all() and np.isfinite(q).all()
    assert peak < 150e6, peak / 1e6
