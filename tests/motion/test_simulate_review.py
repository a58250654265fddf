"""Review tests for phjax.motion.simulate: bad sensor fields, ground truth, keys and durations
are one-line ValueErrors naming what is wrong, not silent NaNs or errors from deep inside."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from test_simulate import _smooth_gt  # the same smooth ground truth (and its compiled sizes)

from phjax.motion.simulate import SensorModel, simulate_measurements, synthetic_head_motion


@pytest.mark.parametrize("field", ["rate", "sigma_p", "sigma_r", "jitter", "latency"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_sensor_fields_are_named_errors(field, value):
    """Before: rate=inf raised OverflowError from int(); NaN / inf sigma_p or sigma_r gave NaN
    rows silently; jitter=NaN was silently no jitter and jitter=inf every offset at the clip;
    latency NaN / inf gave NaN / inf times."""
    with pytest.raises(ValueError, match=rf"SensorModel\.{field}\b"):
        simulate_measurements(0, *_smooth_gt(), model=SensorModel(**{field: value}))


def test_ground_truth_without_any_pose_is_an_error():
    """Before: positions and orientations both NaN (or zero quaternions) gave a recording of
    NaN frames with no warning."""
    t, p, q = _smooth_gt()
    for none_q in (np.full_like(q, np.nan), np.zeros_like(q)):
        with pytest.raises(ValueError, match="no valid position or orientation"):
            simulate_measurements(0, t, np.full_like(p, np.nan), none_q)


def test_bad_key_is_a_value_error_and_integer_arrays_are_seeds():
    """Before: a float seed or a 0-d integer array raised JAX's TypeError "invalid PRNG key
    data"."""
    gt = _smooth_gt()
    for bad in (7.0, "7", np.zeros(3, np.uint32)):
        with pytest.raises(ValueError, match="key_or_seed"):
            simulate_measurements(bad, *gt)
    ref = simulate_measurements(7, *gt)
    for seed in (np.array(7), jax.numpy.array(7), jax.random.key(7)):
        for a, b in zip(simulate_measurements(seed, *gt), ref):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    legacy = simulate_measurements(jax.random.PRNGKey(7), *gt)  # raw uint32 key still works
    assert legacy[0].shape == ref[0].shape


def test_float32_epoch_times_with_float64_poses_are_an_error_not_a_collapse():
    """Before: Unix times given in float32 (rounded to 128 s) with float64 poses were accepted
    and the 10 s recording came out as a single frame."""
    t, p, q = _smooth_gt()
    t32 = (t + 1.7e9).astype(np.float32)
    with pytest.raises(ValueError, match="pass times relative to the first"):
        simulate_measurements(0, t32, p, q)
    with pytest.raises(ValueError, match="pass times relative to the first"):  # a batch
        simulate_measurements(0, t32[None], p[None], q[None])
    out = simulate_measurements(0, t.astype(np.float32), p, q)  # relative float32 times: fine
    assert out[0].shape == (301,)


@pytest.mark.parametrize("kw", [dict(duration=float("inf")), dict(rate=float("inf"))])
def test_head_motion_non_finite_duration_or_rate_is_a_value_error(kw):
    """Before: OverflowError "cannot convert float infinity to integer"."""
    with pytest.raises(ValueError, match="finite"):
        synthetic_head_motion(**kw)
