"""C1 orientation interpolation between two orientations with given angular velocities.

A cumulative cubic Bezier curve on the unit quaternions (Kim, Kim & Shin 1995), written with
world-frame (left) increments:

    q(s) = exp(b3(s) w3) exp(b2(s) w2) exp(b1(s) w1) q0,    s in [0, 1],

with the cumulative cubic Bernstein functions ``b1 = 1 - (1 - s)^3``, ``b2 = 3 s^2 - 2 s^3``,
``b3 = s^3`` and pure-quaternion increments ``w1 = T w0 / 6``, ``w3 = T w1 / 6`` (``T`` the
segment duration, ``w0``, ``w1`` world-frame angular velocities in rad/s) and
``w2 = log(exp(-w3) q1 q0* exp(-w1))`` taken along the shortest arc. Then ``q(0) = q0``,
``q(1) = q1`` (as a rotation: ``q1`` or ``-q1``), the angular velocity is ``w0`` at ``s = 0`` and
``w1`` at ``s = 1`` (so consecutive segments join C1), and ``|q(s)| = 1`` exactly, being a
product of unit quaternions. With zero angular velocities it reduces to slerp with a smooth
(cubic ease) timing; values and gradients are finite at zero rotation and at 180-degree turns.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._misc import check_last_axis, safe_div
from . import _components as _c
from .ph_quintic import _sample_axes

__all__ = ["QuaternionHermite", "quaternion_hermite"]


class QuaternionHermite(eqx.Module):
    """A (batch of) C1 orientation curve(s) on ``s in [0, 1]`` (see the module docs).

    Attributes:
        q0: start orientation, ``(*B, 4)`` wxyz.
        w1, w2, w3: pure-quaternion increments (3-vectors, half-angle convention), ``(*B, 3)``.
        duration: physical duration ``T`` of the segment, s, ``(*B,)``.
    """

    q0: Float[Array, "*batch 4"]
    w1: Float[Array, "*batch 3"]
    w2: Float[Array, "*batch 3"]
    w3: Float[Array, "*batch 3"]
    duration: Float[Array, "*batch"]

    def _basis(self, s):
        s = jnp.asarray(s, self.q0.dtype)
        c = 1 - s
        b = (1 - c**3, s * s * (3 - 2 * s), s**3)
        db = (3 * c * c, 6 * s * c, 3 * s * s)
        return b, db

    def _ex(self, x, k):
        nb = x.ndim - 1
        return x.reshape(x.shape[:nb] + (1,) * k + x.shape[nb:])

    def _prep_s(self, s):
        s = jnp.asarray(s, self.q0.dtype)
        return s, _sample_axes(self.duration.shape, s.shape, "s")

    def rotation(self, s: Float[ArrayLike, "*#batch S"]) -> Float[Array, "*batch S 4"]:
        """Unit quaternion ``q(s)``.

        ``s`` follows the rule of :class:`PHQuintic`: its last axis is the sample axis and its
        leading axes broadcast against the batch (``(S,)``: the same parameters on every curve;
        ``batch + (S,)``: per-curve parameters; scalar: result ``batch + (4,)``).
        """
        s, k = self._prep_s(s)
        q = _c.split(self._ex(self.q0, k))
        for e in self._exps(s, k):
            q = _c.qmul(e, q)
        return _c.stack(q)

    def _exps(self, s, k):
        """``exp(b_j(s) w_j)``, ``j = 1, 2, 3``, as components, computed in one XLA kernel
        (``_components.checkpoint``; shared by :meth:`rotation` and :meth:`angular_velocity`)."""
        b, _ = self._basis(s)
        ws = (self.w1, self.w2, self.w3)
        return _c.checkpoint(*(_c.qexp(_c.scale(bj, _c.split(self._ex(w, k))))
                               for bj, w in zip(b, ws)))

    def angular_velocity(self, s: Float[ArrayLike, "*#batch S"]) -> Float[Array, "*batch S 3"]:
        """World-frame angular velocity (rad/s, physical time) at ``s`` (shapes as
        :meth:`rotation`; 0 on a segment of zero duration)."""
        s, k = self._prep_s(s)
        _, (d1, d2, d3) = self._basis(s)
        w1, w2, w3 = (_c.split(self._ex(w, k)) for w in (self.w1, self.w2, self.w3))
        _, e2, e3 = self._exps(s, k)
        # q' q* = d3 w3 + E3 (d2 w2) E3* + E3 E2 (d1 w1) E2* E3*  (world frame, per unit s)
        def rot(e, v):
            return _c.qmul(_c.qmul(e, (0.0,) + v), _c.qconj(e))[1:]

        omega = _c.add(_c.add(_c.scale(d3, w3), rot(e3, _c.scale(d2, w2))),
                       rot(_c.qmul(e3, e2), _c.scale(d1, w1)))
        dur = self.duration.reshape(self.duration.shape + (1,) * k)
        # a zero-duration segment has no rate of its own: 0, with finite gradients
        return _c.stack(tuple(safe_div(2 * x, dur) for x in omega))


def _hermite_factors(q0, q1, w0, w1, duration):
    """``(a, mid, c)``: the first and last increments ``a = T w0 / 6``, ``c = T w1 / 6`` of
    :func:`quaternion_hermite` (its fields ``w1``, ``w3``) and the middle rotation
    ``mid = exp(-c) q1 q0* exp(-a)`` before its shortest-arc flip (``duration`` ``T``
    broadcasts with ``w0``)."""
    a = duration * w0 / 6
    c = duration * w1 / 6
    return a, _c.stack(_middle(*(_c.split(x) for x in (q0, q1, a, c)))), c


def _middle(q0, q1, a, c):
    """``exp(-c) q1 q0* exp(-a)`` on components."""
    rel = _c.qmul(q1, _c.qconj(q0))
    return _c.qmul(_c.qmul(_c.qexp(_c.neg(c)), rel), _c.qexp(_c.neg(a)))


def quaternion_hermite(
    q0: Float[ArrayLike, "*batch 4"],
    q1: Float[ArrayLike, "*batch 4"],
    w0: Float[ArrayLike, "*batch 3"],
    w1: Float[ArrayLike, "*batch 3"],
    duration: Float[ArrayLike, "*batch"],
) -> QuaternionHermite:
    """C1 orientation curve from ``q0`` (angular velocity ``w0``) to ``q1`` (``w1``).

    Arguments:
        q0, q1: end orientations, unit quaternions wxyz (``q1`` and ``-q1`` give the same curve).
        w0, w1: world-frame angular velocities at the ends, rad/s.
        duration: segment duration ``T`` in seconds (the parameter ``s = (t - t0) / T``).

    Returns:
        A :class:`QuaternionHermite`.
    """
    q0, q1, w0, w1 = (check_last_axis(x, n, name) for x, n, name in (
        (q0, 4, "q0"), (q1, 4, "q1"), (w0, 3, "w0"), (w1, 3, "w1")))
    dtype = jnp.result_type(float, q0, q1, w0, w1)
    q0, q1, w0, w1 = (x.astype(dtype) for x in (q0, q1, w0, w1))
    duration = jnp.asarray(duration, dtype)
    a = duration[..., None] * w0 / 6
    c = duration[..., None] * w1 / 6
    mid = _middle(*(_c.split(x) for x in (q0, q1, a, c)))
    mid = _c.where(mid[0] < 0, _c.neg(mid), mid)  # shortest arc
    b = _c.stack(_c.qlog(mid))
    batch = jnp.broadcast_shapes(q0.shape[:-1], b.shape[:-1], duration.shape)
    return QuaternionHermite(
        q0=jnp.broadcast_to(q0, batch + (4,)),
        w1=jnp.broadcast_to(a, batch + (3,)),
        w2=jnp.broadcast_to(b, batch + (3,)),
        w3=jnp.broadcast_to(c, batch + (3,)),
        duration=jnp.broadcast_to(duration, batch),
    )
