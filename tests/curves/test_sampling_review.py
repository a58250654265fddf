"""Review of ``phjax.sample`` / ``sample_into`` / ``sample_chunks`` at degenerate inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import phjax as pj

# rows: resting at both ends, generic, a point (length 0), stopping in the middle (speed 0 at
# t = 1/2), long
_DATA = np.array([
    [[0, 0, 0], [1, 0.2, 0], [0, 0, 0], [0, 0, 0]],
    [[0.1, 0.2, -0.3], [1, 2, 0.5], [2, -1, 0.3], [0.5, 1, -2]],
    [[1, 2, 3], [1, 2, 3], [0, 0, 0], [0, 0, 0]],
    [[0, 0, 0], [1, 0, 0], [3, 0, 0], [3, 0, 0]],
    [[0, 0, 0], [1e6, 0, 0], [1e6, 1e5, 0], [1e6, 0, 0]],
])


def _curves(dtype):
    return pj.hermite_quintic(*(jnp.asarray(_DATA[:, k], dtype) for k in range(4)))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_arclength_samples_end_exactly_at_0_and_1(dtype):
    """Found: the last sample of a curve resting at its end was at t = 0.99679 in float32
    (0.999995 in float64), of the generic curve at 1 - 3e-15, and every sample of a point curve
    at t = 0.9752; the inversion put s = L at 1 - cbrt(rounding) where s(t) ~ (1 - t)^3."""
    c = _curves(dtype)
    t, p = pj.sample(c, 9, by="arclength")
    t = np.asarray(t)
    assert (t[:, 0] == 0).all() and (t[:, -1] == 1).all()
    assert (np.diff(t, axis=-1) > 0).all()
    ends = np.asarray(c.control_points)[:, [0, 5]]
    scale = np.abs(ends).max(axis=(1, 2), keepdims=True)
    assert (np.abs(np.asarray(p)[:, [0, -1]] - ends) <= 8 * np.finfo(dtype).eps * scale).all()
    np.testing.assert_array_equal(t[2], np.linspace(0, 1, 9, dtype=dtype))  # point: uniform


def test_arclength_gradient_where_the_curve_stops_in_the_middle():
    """Found: at a curve whose speed is 0 at t = 1/2 (row 3), the gradient of the middle
    arc-length sample with respect to the curve's coefficients was off by up to 0.48 (83%)
    from central differences; it was differentiated through the Newton loop, whose last steps
    there are bisections. Now the implicit gradient ``dp = dr + T (d(u L) - ds(t))``."""
    c = jax.tree.map(lambda x: x[np.array([1, 3])], _curves(jnp.float64))
    x0, unravel = ravel_pytree(c)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(2, 9, 3)))

    def f(x):  # (dt/dx is infinite at the stop: t of the generic curve only)
        t, p = pj.sample(unravel(x), 9, by="arclength")
        return jnp.sum(w * p) + jnp.sum(t[0])

    grad = np.asarray(jax.jit(jax.grad(f))(x0))
    h = 1e-6
    steps = jnp.concatenate([h * jnp.eye(x0.size), -h * jnp.eye(x0.size)])
    values = np.asarray(jax.jit(jax.vmap(f))(x0 + steps))
    fd = (values[:x0.size] - values[x0.size:]) / (2 * h)
    # (central differences at the stop are off by O(h^(1/3)) there: 4e-5)
    np.testing.assert_allclose(grad, fd, atol=2e-4)


def test_bad_inputs_name_themselves():
    """Found: ``n=None`` gave int()'s TypeError, ``sample_into`` / ``sample_chunks`` of an array
    an AttributeError, a buffer with ``n = 0`` returned empty samples (``sample`` refuses n=0),
    ``sample_chunks(dtype=int32)`` silently returned points truncated to integers, and a
    donated buffer passed again reached XLA ("Invalid buffer passed to Execute()")."""
    c = _curves(jnp.float64)
    with pytest.raises(ValueError, match="n must be an integer >= 1"):
        pj.sample(c, None)
    with pytest.raises(TypeError, match="curves must be a PHQuintic"):
        pj.sample_into(np.zeros((5, 3)), jnp.zeros((5, 4, 3)))
    with pytest.raises(TypeError, match="curves must be a PHQuintic"):
        next(pj.sample_chunks(np.zeros((5, 3)), 4, 2))
    with pytest.raises(ValueError, match="n >= 1"):
        pj.sample_into(c, jnp.zeros((5, 0, 3)))
    with pytest.raises(ValueError, match="dtype must be floating point"):
        next(pj.sample_chunks(c, 4, 2, dtype=jnp.int32))
    buf = jnp.zeros((5, 9, 3))
    pj.sample_into(c, buf, by="arclength")
    with pytest.raises(ValueError, match="points was donated"):
        pj.sample_into(c, buf, by="arclength")
