"""Small-vector algebra in struct-of-arrays form (private).

A vector or quaternion is a tuple of its components, each an array of the batch shape:
``(x, y, z)`` for a 3-vector, ``(w, x, y, z)`` for a quaternion (scalar first, Hamilton
product, as :mod:`phjax.quaternion`). Components may be Python floats where a constant is meant.

Why: XLA:CPU (with the classic emitters phjax selects) computes a value in a kernel of its own
when it cannot fuse it into all of its users: an expensive operation (square root, division,
``atan2``) with several users, or a value read at several indices, which is what the slices and
concatenations of the ``(..., 4)`` arrays of :mod:`phjax.quaternion` make of every quaternion
product. Compile time grows with the number of kernels (about 17 ms each) while the run time of
these tiny problems hardly depends on it. On components every operation is elementwise on one
shape, so chains of products, norms and ``where`` branches fuse; :func:`checkpoint` packs what a
step of a computation hands on into one kernel, and :func:`split` and :func:`stack` convert at
the boundaries.

The functions mirror :mod:`phjax.quaternion` and :mod:`phjax._misc` operation by operation (same
formulas, same order of the sums), so they agree to rounding, and they keep the NaN-safe
double-``where`` pattern of the ``safe_*`` helpers (finite values and gradients at zero vectors).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from .._misc import safe_atan2, safe_div, safe_sqrt

# --------------------------------------------------------------------------- conversion


def split(x) -> tuple:
    """Components of the last axis of ``x``: ``x[..., 0], x[..., 1], ...``."""
    x = jnp.asarray(x)
    return tuple(x[..., i] for i in range(x.shape[-1]))


def stack(c):
    """Inverse of :func:`split` (components broadcast to a common shape first)."""
    # stacked along a new leading axis, then moved last: XLA:CPU then computes the components
    # one after the other in loops of their own (for 2e5 quaternions several times faster than a
    # stack along the last axis, which interleaves them element by element)
    return jnp.moveaxis(jnp.stack(jnp.broadcast_arrays(*c), axis=0), 0, -1)


# --------------------------------------------------------------------------- linear algebra


def add(a, b) -> tuple:
    return tuple(x + y for x, y in zip(a, b))


def sub(a, b) -> tuple:
    return tuple(x - y for x, y in zip(a, b))


def neg(a) -> tuple:
    return tuple(-x for x in a)


def scale(s, a) -> tuple:
    """``s * a`` for a scalar (or batch-shaped) ``s``."""
    return tuple(s * x for x in a)


def where(cond, a, b) -> tuple:
    return tuple(jnp.where(cond, x, y) for x, y in zip(a, b))


def dot(a, b):
    """``sum_i a_i b_i``, summed left to right (as :func:`phjax._misc.dot_last`)."""
    acc = a[0] * b[0]
    for x, y in zip(a[1:], b[1:]):
        acc = acc + x * y
    return acc


def cross(a, b) -> tuple:
    """``a x b`` of 3-vectors (the formula of ``jnp.cross``)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)


def norm(a):
    """Euclidean norm, gradient 0 at the zero vector (:func:`phjax._misc.safe_norm`)."""
    return safe_sqrt(dot(a, a))


def normalize(a, fallback=None, floor=0.0) -> tuple:
    """``a / |a|``, ``fallback`` (default: ``a``, i.e. 0) where ``|a|^2 <= floor`` (default:
    where ``|a| = 0``); finite gradients (:func:`phjax._misc.safe_normalize`). A positive
    ``floor`` keeps them finite for vectors too small to normalise in the backward pass."""
    sq = dot(a, a)
    ok = sq > floor
    r = lax.rsqrt(jnp.where(ok, sq, 1))
    out = tuple(x * r for x in a)
    if fallback is None:
        return out
    return where(ok, out, fallback)


_PERP_A = (0.36, 0.48, 0.8)  # unit, generic
_PERP_B = (0.8, -0.6, 0.0)  # unit, perpendicular to _PERP_A


def perpendicular_candidates(u) -> tuple:
    """``(u x a, u x b)``, the candidates of :func:`unit_perpendicular`."""
    return cross(u, _PERP_A), cross(u, _PERP_B)


def unit_perpendicular(u, candidates=None) -> tuple:
    """A unit vector perpendicular to the unit vector ``u``: the rule of
    :func:`phjax._misc.unit_perpendicular` (``normalize(u x a)`` for a fixed generic ``a``,
    ``u x b`` within 30 degrees of ``+-a``). ``candidates``: :func:`perpendicular_candidates`
    of ``u`` if already computed."""
    ua, ub = perpendicular_candidates(u) if candidates is None else candidates
    use_a = norm(ua) >= 0.5
    return where(use_a, normalize(ua), normalize(ub))


# --------------------------------------------------------------------------- quaternions


def qmul(p, q) -> tuple:
    """Hamilton product ``p q`` (the formula of :func:`phjax.quaternion.quat_mul`)."""
    a, u = p[0], p[1:]
    b, v = q[0], q[1:]
    w = a * b - dot(u, v)
    uv = cross(u, v)
    return (w,) + tuple(a * vi + b * ui + ci for ui, vi, ci in zip(u, v, uv))


def qmul_pure(u, v) -> tuple:
    """Product of the pure quaternions ``(0, u) (0, v) = (-u.v, u x v)``."""
    return (-dot(u, v),) + cross(u, v)


def qconj(q) -> tuple:
    return (q[0], -q[1], -q[2], -q[3])


def qmul_exp_i(q, phi) -> tuple:
    """``q exp(phi i)`` with ``exp(phi i) = cos(phi) + i sin(phi)``."""
    c, s = jnp.cos(phi), jnp.sin(phi)
    w, x, y, z = q
    return (w * c - x * s, x * c + w * s, y * c + z * s, z * c - y * s)


def qmul_i(q) -> tuple:
    """``q i``."""
    w, x, y, z = q
    return (-x, w, z, -y)


def sandwich_i(a, b) -> tuple:
    """Vector part of ``a i b*``."""
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    x = a0 * b0 + a1 * b1 - a2 * b2 - a3 * b3
    y = a0 * b3 + a1 * b2 + a2 * b1 + a3 * b0
    z = -a0 * b2 + a1 * b3 - a2 * b0 + a3 * b1
    return (x, y, z)


def sym_i(a, b) -> tuple:
    """``a i b* + b i a*`` (a pure vector)."""
    return add(sandwich_i(a, b), sandwich_i(b, a))


def qexp(v) -> tuple:
    """``exp`` of the pure quaternion ``v``: ``(cos|v|, sin|v| v/|v|)``
    (:func:`phjax.quaternion.quat_exp`)."""
    n = norm(v)
    sinc = jnp.sinc(n / jnp.pi)  # sin(n)/n, smooth at 0
    return (jnp.cos(n),) + scale(sinc, v)


def qlog(q) -> tuple:
    """Logarithm ``theta * axis`` of a unit quaternion (:func:`phjax.quaternion.quat_log`)."""
    w, v = q[0], q[1:]
    n = norm(v)
    theta = safe_atan2(n, w)
    # theta / n -> (1 - n^2 / (3 w^2)) / w as n -> 0 with w > 0 (series avoids 0/0)
    series = (w > 0) & (n < 1e-4)
    w_safe = jnp.where(series, w, 1)
    ratio_series = (1 - n * n / (3 * w_safe * w_safe)) / w_safe
    ratio = jnp.where(series, ratio_series, safe_div(theta, n))
    return scale(ratio, v)


# --------------------------------------------------------------------------- kernel boundaries


def checkpoint(*vecs) -> tuple:
    """The component tuples ``vecs`` unchanged, computed into one buffer (one XLA kernel).

    XLA:CPU does not duplicate an expensive operation (square root, division, ``atan2``) into
    several kernels, nor, in general, a value computed from two arrays whose users it cannot all
    fuse: such a value that several later steps share becomes a kernel of its own, one per
    component. Stacked into one array, the components that a step of the computation hands on
    are one kernel: XLA:CPU keeps a concatenation with several users in memory, and
    ``lax.optimization_barrier`` stops its simplifier from folding the slices of the stack back
    into the components. The array is ``(rows, 8) + batch``: XLA:CPU fuses a concatenation of
    at most 8 operands only and merges nested concatenations along one axis into one, and
    along leading axes it computes every component in a loop of its own (each component
    evaluates its whole formula, so a stack along the last axis, which interleaves them element
    by element, is several times slower for large batches).
    """
    flat = [x for v in vecs for x in v]
    n = len(flat)
    if n > 64:
        raise ValueError(f"checkpoint of {n} components; at most 64 (8 rows of 8)")
    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in flat))
    dtype = jnp.result_type(*flat)
    flat = [jnp.broadcast_to(jnp.asarray(x, dtype), shape) for x in flat]
    if n <= 8:
        packed = lax.optimization_barrier(jnp.stack(flat))
        get = lambda i: packed[i]
    else:
        flat += [jnp.zeros(shape, dtype)] * (-n % 8)
        rows = [jnp.stack(flat[i:i + 8]) for i in range(0, len(flat), 8)]
        packed = lax.optimization_barrier(jnp.stack(rows))
        get = lambda i: packed[i // 8, i % 8]
    out, i = [], 0
    for v in vecs:
        out.append(tuple(get(i + k) for k in range(len(v))))
        i += len(v)
    return tuple(out)
