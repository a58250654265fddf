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
        ``(t, points)`` with shapes ``(*batch, n)`` and ``(*batch, n, 3)``. ``t`` can be passed
        to the evaluation methods as is (each curve at its own parameters):
        ``curves.curvature(t)`` has shape ``(*batch, n)``, ``curves.frame(t)``
        ``(*batch, n, 3, 3)``.
    """
    if by not in ("time", "arclength"):
        raise ValueError(f"by must be 'time' or 'arclength', got {by!r}")
    u = jnp.linspace(0, 1, n, dtype=curves.dtype)
    if by == "time":
        t = jnp.broadcast_to(u, curves.batch_shape + (n,))
        return t, curves.position(u)
    t = curves.parameter_at_length(curves.length[..., None] * u)  # (*batch, n): per curve
    return t, curves.position(t)
