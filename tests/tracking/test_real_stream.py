"""A real 30 Hz SLAM pose stream (RGBDSLAM on TUM RGB-D fr1_xyz) against its ground truth:
evo's APE (translation RMSE after SE(3) alignment) of the offline reconstruction is lower than
the raw estimate's.

Measured (``experiments/real_stream.py``): raw 13.47 mm, offline 12.49 mm; the causal stream is
not yet below the raw estimate (IMM 14.24 mm at the frames, single-model 14.70 mm), so only the
offline claim is tested."""

from __future__ import annotations

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("evo")

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments"))


def test_offline_reconstruction_lowers_slam_ape():
    from phjax.tracking.tracker import reconstruct

    real_stream = pytest.importorskip("real_stream")
    try:
        gt, est = real_stream.load()
    except FileNotFoundError:
        pytest.skip("../shared/data (TUM RGB-D estimate) not available")
    t, p, q = est.times, est.positions, est.quaternions
    raw = real_stream.ape_rmse(gt, t, p, q)
    po, qo = (np.asarray(x) for x in reconstruct(t, p, q, t, dtype=jnp.float64))
    offline = real_stream.ape_rmse(gt, t, po, qo)
    assert 0.005 < raw < 0.05  # the estimate is a real, centimetre-level SLAM trajectory
    assert offline < 0.97 * raw, (offline, raw)
