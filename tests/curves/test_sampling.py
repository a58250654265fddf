"""``sample_into`` (donated buffers) and ``sample_chunks`` against ``sample``."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj


def _curves(shape, seed=0):
    rng = np.random.default_rng(seed)
    return pj.hermite_quintic(*(rng.normal(size=shape + (3,)) for _ in range(4)))


@pytest.mark.parametrize("by", ["time", "arclength"])
def test_sample_into_equals_sample_and_donates(by):
    curves = _curves((3, 4))
    t_ref, p_ref = pj.sample(curves, 9, by=by)
    pts, t = jnp.full((3, 4, 9, 3), 7.0), jnp.full((3, 4, 9), 7.0)
    t_out, p_out = pj.sample_into(curves, pts, t, by=by)
    np.testing.assert_allclose(np.asarray(p_out), np.asarray(p_ref), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(t_out), np.asarray(t_ref), rtol=0, atol=1e-14)
    assert pts.is_deleted() and t.is_deleted()  # the buffers were donated
    # reuse the returned arrays as the next buffers, without the parameters
    t2, p2 = pj.sample_into(_curves((3, 4), seed=1), p_out, by=by)
    assert t2 is None and p_out.is_deleted()
    np.testing.assert_allclose(np.asarray(p2), np.asarray(pj.sample(_curves((3, 4), 1), 9,
                                                                     by=by)[1]), rtol=0, atol=1e-14)


def test_sample_into_buffer_dtype_and_errors():
    curves = _curves((5,))
    _, p = pj.sample_into(curves, jnp.zeros((5, 4, 3), jnp.float32))
    assert p.dtype == jnp.float32
    np.testing.assert_allclose(p, pj.sample(curves, 4)[1], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        pj.sample_into(curves, jnp.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="jax.Array"):
        pj.sample_into(curves, np.zeros((5, 4, 3)))
    with pytest.raises(ValueError, match="t must"):
        pj.sample_into(curves, jnp.zeros((5, 4, 3)), jnp.zeros((5, 3)))
    with pytest.raises(ValueError, match="by must"):
        pj.sample_into(curves, jnp.zeros((5, 4, 3)), by="space")
    # sample: an array instead of curves, and a fractional count (silently rounded down)
    with pytest.raises(TypeError, match="curves must be a PHQuintic"):
        pj.sample(np.zeros((5, 3)), 5)
    for n in (2.5, 0, True):
        with pytest.raises(ValueError, match="n must be an integer >= 1"):
            pj.sample(curves, n)


@pytest.mark.parametrize(("chunk", "buffers"), [(4, 2), (7, 1), (50, 3)])
@pytest.mark.parametrize("by", ["time", "arclength"])
def test_sample_chunks_cover_the_batch(chunk, buffers, by):
    curves = _curves((2, 11))
    t_ref, p_ref = (np.asarray(x).reshape((22,) + x.shape[2:])
                    for x in pj.sample(curves, 6, by=by))
    p_out, t_out = np.full_like(p_ref, np.nan), np.full_like(t_ref, np.nan)
    starts = []
    for start, t, p in pj.sample_chunks(curves, 6, chunk, by=by, parameters=True,
                                        buffers=buffers):
        starts.append(start)
        assert np.isnan(p_out[start:start + len(p)]).all()  # each curve exactly once
        p_out[start:start + len(p)], t_out[start:start + len(p)] = np.asarray(p), np.asarray(t)
    assert starts == list(range(0, 22, min(chunk, 22)))
    np.testing.assert_allclose(p_out, p_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(t_out, t_ref, rtol=0, atol=1e-14)


def test_sample_chunks_reuses_buffers():
    curves = _curves((6,))
    gen = pj.sample_chunks(curves, 5, 2, buffers=2)
    _, t, first = next(gen)
    assert t is None
    next(gen)
    next(gen)  # the third chunk is written into the first chunk's buffer
    assert first.is_deleted()
    with pytest.raises(ValueError, match=">= 1"):
        next(pj.sample_chunks(curves, 5, 0))


@pytest.mark.parametrize("call, message", [
    (lambda: pj.pad_recordings([np.arange(3.0)], multiple_of=0), "multiple_of must be"),
    (lambda: pj.pad_recordings([np.arange(3.0)] * 3, multiple_of=2.5), "multiple_of must be"),
    (lambda: pj.ph_spline(jnp.array([[0.0, 0, 0], [1, 0, 0], [2, 1, 0]]), d_start=[1.0, 0]),
     "d_start must be a 3-vector"),
    (lambda: list(pj.sample_chunks(_curves((2,)), 2.5, 1)), "n must be an integer"),
    (lambda: list(pj.sample_chunks(_curves((2,)), 4, 1.5)), "chunk must be an integer"),
    (lambda: pj.quat_hemisphere_continuity(jnp.array([1.0, 0, 0, 0])),
     "sequence of quaternions"),
])
def test_bad_arguments_name_themselves(call, message):
    """Found by probing: ZeroDivisionError, a silent round-down of 2.5, reshape and JAX shape
    TypeErrors, an IndexError; each is now a ValueError naming the argument."""
    with pytest.raises(ValueError, match=message):
        call()
