"""NaN-safe elementwise helpers (the double-``where`` pattern).

Each helper returns finite values *and* finite gradients at its singular point, so that
``jax.grad`` through degenerate inputs (zero vectors, coincident points) never yields NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float


def check_number_fields(obj, rules) -> None:
    """``ValueError`` naming ``Class.field`` for a field that is not a finite number (array)
    satisfying its rule; traced values are skipped (inside ``jit``, ``vmap`` or ``grad`` they
    are the caller's to keep valid). ``rules``: ``(name, predicate, " > 0")`` triples, the
    predicate applied to a float64 array of the value."""
    cls = type(obj).__name__
    for name, ok, rule in rules:
        value = getattr(obj, name)
        if any_traced(value):
            continue
        try:
            x = None if isinstance(value, (str, bytes)) else np.asarray(value, np.float64)
        except (TypeError, ValueError):
            x = None
        if x is None or not (np.isfinite(x).all() and np.all(ok(x))):
            raise ValueError(f"{cls}.{name} must be a finite number{rule}, got {value!r}")


def check_count(value, name: str, minimum: int = 1, note: str = "") -> int:
    """``value`` as an ``int`` count (samples, steps, an order), or a ``ValueError`` naming
    ``name``: an integer value >= ``minimum`` (an ``int``, a NumPy integer, a float or 0-d
    array with an integer value); never a bool, a string, or a fraction rounded down.
    ``note`` follows the rule in the message (e.g. ``" (samples per curve)"``)."""
    try:
        ok = not isinstance(value, (bool, np.bool_, str, bytes)) and int(value) == value
    except (TypeError, ValueError, OverflowError):  # None, several values, inf, nan
        ok = False
    if not ok or int(value) < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}{note}, got {value!r}")
    return int(value)


POSITIVE = (lambda x: x > 0, " > 0")
FINITE = (lambda x: x == x, "")


def any_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a JAX tracer: the call runs inside ``jax.jit``,
    ``vmap`` or ``grad``, where host-side checks, padding and caches cannot look at values."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees))


def check_last_axis(x: ArrayLike, n: int, name: str) -> Array:
    """``x`` as an array whose last axis has ``n`` entries (``ValueError`` naming ``name``
    otherwise; a check of the static shape, so also inside ``jit``)."""
    x = jnp.asarray(x)
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got shape {tuple(x.shape)}")
    return x


def safe_sqrt(x: ArrayLike) -> Array:
    """``sqrt(max(x, 0))`` with gradient 0 (not inf) at ``x <= 0``."""
    x = jnp.asarray(x)
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1)), 0)


#: arrays up to this many elements get unrolled sums in :func:`sum_last`
_UNROLL_SIZE = 64


def sum_last(x: Float[ArrayLike, "... n"], keepdims: bool = False) -> Array:
    """Sum over the last axis; for small arrays as a chain of adds.

    Same value as ``jnp.sum(x, axis=-1)``. XLA:CPU runs every reduction as a kernel of its own
    (measured: ~0.5-1 us per call on tiny arrays, against ~0.03 us for a fused add), so on small
    arrays (at most ``_UNROLL_SIZE`` elements, last axis at most 8) the sum is written as adds,
    which keeps small jitted functions such as a tracker update fast. Large batches keep the
    reduction: there XLA would recompute the unrolled operands once per component.
    """
    x = jnp.asarray(x)
    n = x.shape[-1]
    if n == 0 or n > 8 or x.size > _UNROLL_SIZE:
        return jnp.sum(x, axis=-1, keepdims=keepdims)
    acc = x[..., 0]
    for i in range(1, n):
        acc = acc + x[..., i]
    return acc[..., None] if keepdims else acc


def dot_last(x: Float[ArrayLike, "... n"], y: Float[ArrayLike, "... n"], keepdims: bool = False) -> Array:
    """Inner product over the last axis (:func:`sum_last` of ``x * y``)."""
    return sum_last(jnp.asarray(x) * jnp.asarray(y), keepdims)


def safe_norm(x: Float[ArrayLike, "... n"], axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm with gradient 0 at the zero vector."""
    x = jnp.asarray(x)
    if axis in (-1, x.ndim - 1):
        return safe_sqrt(sum_last(x * x, keepdims))
    return safe_sqrt(jnp.sum(x * x, axis=axis, keepdims=keepdims))


def safe_div(num: ArrayLike, den: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """``num / den`` where ``den != 0``, else ``fallback``; gradients stay finite."""
    num, den = jnp.asarray(num), jnp.asarray(den)
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1), fallback)


def safe_normalize(
    x: Float[ArrayLike, "... n"], fallback: Float[ArrayLike, "... n"] | None = None
) -> Array:
    """``x / |x|``; where ``|x| == 0`` return ``fallback`` (default: ``x`` itself, i.e. 0)."""
    x = jnp.asarray(x)
    # x * rsqrt(|x|^2): the root's only user is the product, so XLA fuses the whole function
    # into one kernel (a norm with two users, the test and the division, is a kernel of its own)
    sq = sum_last(x * x, keepdims=True)
    ok = sq > 0
    out = x * lax.rsqrt(jnp.where(ok, sq, 1))
    if fallback is None:
        return out
    return jnp.where(ok, out, jnp.broadcast_to(jnp.asarray(fallback, out.dtype), out.shape))


def safe_atan2(y: ArrayLike, x: ArrayLike) -> Array:
    """``atan2(y, x)`` returning 0 with zero gradient at (and within the smallest normal number
    of) the origin.

    The arguments are scaled by a power of two (exact) to magnitude ~1 before ``atan2``, so that
    the derivative ``(x dy - y dx) / (x^2 + y^2)`` does not overflow for tiny arguments (in
    float32 ``x^2 + y^2`` underflows from ``|x|, |y| ~ 1e-19`` on); the angle is invariant under
    the scaling, so the scale carries no gradient.
    """
    y, x = jnp.asarray(y), jnp.asarray(x)
    m = jnp.maximum(jnp.abs(x), jnp.abs(y))
    ok = m >= jnp.finfo(jnp.result_type(float, m)).tiny
    _, e = jnp.frexp(lax.stop_gradient(jnp.where(ok, m, 1)))
    scale = jnp.ldexp(jnp.ones_like(m), -e)
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0) * scale, jnp.where(ok, x, 1) * scale), 0)


def unit_perpendicular(u: Float[ArrayLike, "... 3"]) -> Array:
    """A unit vector perpendicular to the unit vector ``u``.

    ``normalize(u x a)`` for a fixed generic direction ``a``, switching to a second direction
    ``b`` (perpendicular to ``a``) within 30 degrees of ``+-a``. The result is smooth in ``u``
    except on that cone, which no coordinate axis or coordinate plane touches.
    """
    u = jnp.asarray(u)
    a = jnp.asarray([0.36, 0.48, 0.8], u.dtype)  # unit, generic
    b = jnp.asarray([0.8, -0.6, 0.0], u.dtype)  # unit, perpendicular to a
    ua = jnp.cross(u, jnp.broadcast_to(a, u.shape))
    ub = jnp.cross(u, jnp.broadcast_to(b, u.shape))
    use_a = safe_norm(ua, keepdims=True) >= 0.5
    return safe_normalize(jnp.where(use_a, ua, ub))


def filter_scan(step, init, xs):
    """``lax.scan(step, init, xs)`` of a filter over its measurements, with the step under
    ``jax.checkpoint``: the same values and gradients, but the reverse pass recomputes each
    step from its carry instead of storing every intermediate value of every step. For the
    tracker's scan (:func:`phjax.track`, the tuning loss) this makes gradients cheaper to
    compile at an unchanged run time. Measured on the project's 2-core CPU, one fresh process
    per run (``benchmarks/bench_startup.py --only grad``, with ``--root`` on the code before):
    ``jax.grad`` of a loss of ``track`` (300 frames, float32) compiled in 45.6 s instead of
    60.6 s (1813 instead of 2697 fusions) and its first call took 56 s instead of 75 s; run
    times moved by -22 % to +8 % in seven comparisons (the machine's noise); the tuning loss's
    first value and gradient is unchanged (27.5 / 28.4 s). Values and gradients agree to
    4e-14 (relative).
    """
    return lax.scan(jax.checkpoint(step), init, xs)
