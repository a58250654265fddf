"""``TrackerStream`` with bad host input: found by probing the real-time API (review).

One stream configuration (the default config, float32, ``fast_start=False``) for all tests, so
that its update and sample programs compile once.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj
from phjax.motion import simulate


@pytest.fixture(scope="module")
def meas():
    t, p, q = (np.asarray(x) for x in simulate.synthetic_head_motion(
        duration=1.0, rate=30.0, seed=3))
    return t - t[0], p.astype(np.float32), q.astype(np.float32)


def _started(meas, n=8):
    t, p, q = meas
    s = pj.TrackerStream(t=0.0, fast_start=False)
    for k in range(n):
        s.update(t[k], p[k], q[k])
    return s


def _finite(s, tau):
    return all(np.isfinite(np.asarray(x)).all() for x in s.sample(tau))


def test_host_times_beyond_the_float32_range_are_refused(meas):
    """A host time that is finite in float64 but not in the float32 state (1e39 s: a
    timestamp in the wrong unit) passed the finiteness check, became inf in the state and the
    stream rendered NaN for good (with only a NumPy overflow warning). Now it is refused and
    nothing of it is taken."""
    t, p, q = meas
    s = _started(meas)
    before = [np.asarray(x) for x in jax.tree.leaves(s.state)]
    with pytest.raises(ValueError, match="t must be within the range of float32"):
        s.update(1e39, p[8], q[8])
    for a, b in zip(jax.tree.leaves(s.state), before):
        np.testing.assert_array_equal(np.asarray(a), b)
    s.update(t[8], p[8], q[8])
    assert _finite(s, t[8] + 0.01)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39, [0.1, np.nan]])
def test_sample_at_a_non_finite_host_time_is_refused(meas, bad):
    """``sample(nan)`` of a running stream returned a NaN pose without a word (the stream must
    never render NaN): now a ValueError, as update's times; the stream samples on after it."""
    t = meas[0]
    s = _started(meas)
    with pytest.raises(ValueError, match="t_render must be finite"):
        s.sample(bad)
    assert _finite(s, t[7] + 0.01)


def test_device_time_update_takes_host_measurements_like_host_times(meas):
    """With a ``jax.Array`` time the position and quaternion were passed on as given: a list
    failed deep inside JAX (``TracerArrayConversionError``) and float64 NumPy measurements
    compiled a second update program in a float32 stream. Now host measurements are converted
    to the stream's dtype on both paths: same result as the host-time update, no compilation."""
    t, p, q = meas
    a, b = _started(meas, 7), _started(meas, 7)
    a.update(jnp.asarray(t[7], jnp.float32), p[7], q[7])  # the signature of float32 input
    n = a._update._cache_size()
    a.update(jnp.asarray(t[8], jnp.float32), p[8].tolist(), q[8].tolist())
    a.update(jnp.asarray(t[9], jnp.float32), p[9].astype(np.float64), q[9].astype(np.float64))
    assert a._update._cache_size() == n
    for k in (7, 8, 9):
        b.update(t[k], p[k], q[k])
    for x, y in zip(a.sample(t[9] + 0.01), b.sample(t[9] + 0.01)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_device_time_leaves_the_stream_as_it_was(meas, bad):
    """A NaN ``jax.Array`` time made the render segment NaN (the stream rendered NaN until
    later updates happened to wash it out); an inf one set the filter's time to inf and the
    stream rendered NaN for good. Such an update now leaves the state unchanged (checking it
    on the host would wait for the device): the stream renders on and takes the next frame."""
    t, p, q = meas
    s, ref = _started(meas), _started(meas)
    s.update(jnp.asarray(bad, jnp.float32), p[8], q[8])
    for a, b in zip(jax.tree.leaves(s.state), jax.tree.leaves(ref.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    s.update(t[8], p[8], q[8])
    ref.update(t[8], p[8], q[8])
    for x, y in zip(s.sample(t[8] + 0.01), ref.sample(t[8] + 0.01)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert _finite(s, t[8] + 0.01)
