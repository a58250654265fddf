"""Batched sampling of PH quintic curves in one fused, jitted call."""

from __future__ import annotations

from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .ph_quintic import PHQuintic

__all__ = ["sample"]


@partial(jax.jit, static_argnames=("n", "by"))
def sample(
    curves: PHQuintic, n: int, by: Literal["time", "arclength"] = "time"
) -> tuple[Float[Array, "*batch n"], Float[Array, "*batch n 3"]]:
    """Sample every curve of a batch at ``n`` points.

    Arguments:
        curves: a (batch of) :class:`PHQuintic`.
        n: number of samples per curve (static), including both ends.
        by: ``"time"`` for uniform parameter ``t``; ``"arclength"`` for points uniformly spaced
            in arc length (parameters from :meth:`PHQuintic.parameter_at_length`).

    Returns:
        ``(t, points)`` with shapes ``(*batch, n)`` and ``(*batch, n, 3)``.
    """
    if by not in ("time", "arclength"):
        raise ValueError(f"by must be 'time' or 'arclength', got {by!r}")
    u = jnp.linspace(0, 1, n, dtype=curves.dtype)
    if by == "time":
        t = jnp.broadcast_to(u, curves.batch_shape + (n,))
        return t, curves.position(u)
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(curves.batch_shape):]), curves)

    def one(c):
        tc = c.parameter_at_length(c.length * u)
        return tc, c.position(tc)

    t, pts = jax.vmap(one)(flat)
    return t.reshape(curves.batch_shape + (n,)), pts.reshape(curves.batch_shape + (n, 3))
