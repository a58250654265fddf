"""A real 30 Hz SLAM pose stream (RGBDSLAM on TUM RGB-D fr1_xyz) against its ground truth, with
evo's APE (translation part, SE(3) Umeyama alignment, association ``max_diff`` 10 ms).

Measured (``python experiments/real_stream.py``, default config): raw estimate 13.47 mm RMSE
(evo's *std* statistic of the same errors is 6.07 mm: the "6.1 mm" of issue 16); raw estimate
held at 120 Hz 14.52; causal IMM filter posterior at the frames 13.17; causal stream at 120 Hz
14.03 (at the frames 14.24); offline 12.49. The causal stream is below the raw estimate held at
the render rate and the causal filter is below the raw estimate, but the stream is still 4 %
above the raw estimate at its own frame times (the stream shows each frame's correction only
over the following ``horizon``); that gap is bounded here, not closed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import shared_path

pytest.importorskip("evo")

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))
real_stream = pytest.importorskip("real_stream")


@pytest.fixture(scope="module")
def data():
    base = shared_path("tum_rgbd_groundtruth")
    from phjax import io

    gt = io.read_tum(base / "fr1_xyz-groundtruth.txt")
    est = io.read_tum(base / "estimates" / "fr1_xyz-rgbdslam_estimate.txt")
    t, p, q = est.times, est.positions, est.quaternions
    return gt, (t, p, q), real_stream.ape_stats(gt, t, p, q)


def test_raw_estimate_ape_and_the_issues_number(data):
    """evo's APE of the raw estimate is centimetre-level; its std statistic (not the RMSE) is
    the 6.1 mm quoted in issue 16."""
    _, _, raw = data
    assert 0.010 < raw["rmse"] < 0.020
    np.testing.assert_allclose(raw["std"] ** 2, raw["rmse"] ** 2 - raw["mean"] ** 2, rtol=1e-9)
    assert abs(raw["std"] - 0.0061) < 0.0001


def test_causal_filter_and_stream_against_raw(data):
    """Default config: the causal IMM filter (posterior at each frame) is below the raw
    estimate (measured 13.17 vs 13.47 mm); the causal 120 Hz stream is below the raw estimate
    held at 120 Hz (14.03 vs 14.52 mm) and at most 6 % above the raw estimate at its frame
    times (measured +4.2 %)."""
    from phjax.tracking.baselines import hold, imm_extrapolation
    from phjax.tracking.tracker import TrackerConfig, track

    gt, (t, p, q), raw = data
    cfg = TrackerConfig()
    pf, qf = (np.asarray(x) for x in imm_extrapolation(t, p, q, t, config=cfg.imm))
    filt = real_stream.ape_rmse(gt, t, pf, qf)
    r120 = np.arange(t[0], t[-1], 1 / 120)
    ph, qh = (np.asarray(x) for x in hold(t, p, q, r120))
    held = real_stream.ape_rmse(gt, r120, ph, qh)
    ps, qs = (np.asarray(x) for x in track(t, p, q, r120, config=cfg, dtype=jnp.float64))
    stream = real_stream.ape_rmse(gt, r120, ps, qs)
    assert filt < 0.99 * raw["rmse"], (filt, raw["rmse"])
    assert stream < 0.98 * held, (stream, held)
    assert stream < 1.06 * raw["rmse"], (stream, raw["rmse"])


def test_offline_reconstruction_lowers_slam_ape(data):
    """Offline (RTS + PH segments): 12.49 vs 13.47 mm measured."""
    from phjax.tracking.tracker import reconstruct

    gt, (t, p, q), raw = data
    po, qo = (np.asarray(x) for x in reconstruct(t, p, q, t, dtype=jnp.float64))
    offline = real_stream.ape_rmse(gt, t, po, qo)
    assert offline < 0.95 * raw["rmse"], (offline, raw["rmse"])


def test_estimated_noise_separates_slam_from_mocap(data):
    """The recording's own white noise: the SLAM estimate is millimetre-level (measured 1.46 mm,
    0.075 deg RMS over axes), the motion-capture ground truth an order of magnitude below
    (0.083 mm, 0.036 deg), far below the default sensor's 5 mm / 1 deg."""
    from phjax.tracking.noise import estimate_measurement_noise

    gt, (t, p, q), _ = data
    slam = estimate_measurement_noise(t, p, q)
    mocap = estimate_measurement_noise(gt.times, gt.positions, gt.quaternions)
    assert 0.0005 < float(slam.pos_meas_noise) < 0.004
    assert float(mocap.pos_meas_noise) < 0.2 * float(slam.pos_meas_noise)
    assert np.degrees(float(slam.rot_meas_noise)) < 0.5


def test_tuning_data_on_the_real_stream_scores_like_track(data):
    """The estimate moved into the ground truth's frame by measured_recording's rigid
    alignment (checked against evo's APE), 8 s of it as tuning_data: the loss terms equal
    phjax.evaluation.metrics of the public ``track`` at the render times (at the file's 1.3e9 s
    Unix times), the reference terms those of the tuned Kalman CV extrapolation."""
    import math

    from phjax.evaluation import TUNED, metrics
    from phjax.motion.resample import interpolate_poses
    from phjax.tracking import tuning
    from phjax.tracking.baselines import kalman_extrapolation
    from phjax.tracking.kalman import KalmanConfig
    from phjax.tracking.tracker import TrackerConfig, track

    gt, (t, p, q), raw = data
    # phjax's rigid alignment (phjax.vision.alignment.align) agrees with evo's: the aligned
    # estimate's error against the ground truth at its own times is the APE of evo
    t, p, q, r, gp, gq = tuning.measured_recording(gt, (t, p, q), align=True)
    at_frames, _ = interpolate_poses(gt.times, gt.positions, gt.quaternions, t)
    err = np.linalg.norm(p - np.asarray(at_frames), axis=-1)
    assert np.sqrt(np.mean(err**2)) == pytest.approx(raw["rmse"], rel=0.02)
    t, p, q, r, gp, gq = tuning.measured_recording(gt, (t, p, q), seconds=8.0)
    d = tuning.tuning_data([(t, p, q, r, gp, gq)])
    cfg = TrackerConfig()
    terms = np.asarray(tuning.loss_terms(cfg, d)[0])
    sp, sq = (np.asarray(x) for x in track(t, p, q, r, config=cfg, dtype=jnp.float64))
    ok = np.isfinite(gp).all(-1)
    score = lambda sp, sq: [metrics.position_rmse(sp[ok], gp[ok]).value,  # noqa: E731
                            math.radians(metrics.rotation_rmse_deg(sq[ok], gq[ok]).value),
                            metrics.rms_jerk_position(r, sp).value,
                            metrics.rms_jerk_rotation(r, sq).value]
    expected = score(sp, sq)
    np.testing.assert_allclose(terms[:2], expected[:2], rtol=1e-6)
    # jerk: third differences of track's output at 1.3e9 s carry rounding; tuning_data's are
    # relative to the first frame
    np.testing.assert_allclose(terms[2:], expected[2:], rtol=1e-4)
    rp, rq = (np.asarray(x) for x in kalman_extrapolation(
        t, p, q, r, config=KalmanConfig(**TUNED["kalman"])))
    np.testing.assert_allclose(np.asarray(d.reference[0][:2]), score(rp, rq)[:2], rtol=1e-6)
    # real SLAM noise is centimetre level (the raw APE is 13.5 mm over the whole file)
    assert 0.005 < terms[0] < 0.05 and np.isfinite(terms).all()
    print("phjax / Kalman CV terms:", terms / np.asarray(d.reference[0]))
