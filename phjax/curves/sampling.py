"""Batched sampling of PH quintic curves in one fused, jitted call.

* :func:`sample` returns fresh arrays. A batch sharded along axis 0 over a device mesh
  (:func:`phjax.batch.shard_batch`) is sampled on each device's part, the outputs sharded the
  same way.
* :func:`sample_into` writes into caller-provided buffers that it **donates** (the outputs reuse
  their memory): in a loop that samples batch after batch, no fresh output memory is touched,
  which matters on a CPU where every fresh page of a large output costs a page fault.
* :func:`sample_chunks` walks a batch too large to sample at once in chunks of fixed shape
  (one compiled program), reusing a small ring of donated buffers.

See ``benchmarks/bench_sampling.py`` for their throughput against a same-size memory fill.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._jit import jit
from .._misc import check_count, safe_div
from ..batch import _leading_sharding, _require_batch_sharded, _sharded_function
from .ph_quintic import PHQuintic

__all__ = ["sample", "sample_chunks", "sample_into"]

_BY = ("time", "arclength")


def _check_by(by):
    if by not in _BY:
        raise ValueError(f"by must be 'time' or 'arclength', got {by!r}")


def _check_curves(curves):
    if not isinstance(curves, PHQuintic):
        raise TypeError(f"curves must be a PHQuintic (phjax.hermite_quintic builds them), got "
                        f"{type(curves).__name__}")


def _check_n(n) -> int:
    """``n`` as the number of samples: an integer >= 1, not a float rounded down."""
    return check_count(n, "n", note=" (samples per curve)")


def _sample_impl(curves: PHQuintic, *, n: int, by: str, with_t: bool = True):
    """Parameters (``None`` unless ``with_t``) and points of every curve at ``n`` samples."""
    if by == "time":
        u = jnp.linspace(0, 1, n, dtype=curves.dtype)
        t = jnp.broadcast_to(u, curves.batch_shape + (n,)) if with_t else None
        return t, curves.position(u)
    t, points = _by_arclength(curves, n)
    return (t if with_t else None), points


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _by_arclength(curves: PHQuintic, n: int):
    """``(t, points)`` at ``n`` parameters uniformly spaced in arc length, per curve. A curve of
    length 0 (a point) has no arc-length parameter: it is sampled uniformly in ``t``."""
    u = jnp.linspace(0, 1, n, dtype=curves.dtype)
    length = curves.length[..., None]
    t = jnp.where(length > 0, curves.parameter_at_length(length * u), u)
    return t, curves.position(t)


@_by_arclength.defjvp
def _by_arclength_jvp(n, primals, tangents):
    """Implicit-function derivatives instead of those of the Newton loop: with ``e = u L -
    s(t)`` (0 at the solution) differentiated at fixed ``t``, ``dt = de / sigma(t)`` and
    ``dr = dr(t) + T(t) de`` with ``T`` the unit tangent. Where the speed ``sigma`` vanishes
    (a curve that stops in the middle or at an end) ``T`` has a finite limit (the ERF's
    tangent), so ``dr`` stays exact; ``dt`` is infinite there and returned as 0. (The
    derivatives through the loop were wrong at such a stop: off by 0.48 where central
    differences gave 0.58.) Only a derivative computes these terms: the values cost nothing."""
    (curves,), (dcurves,) = primals, tangents
    t, points = _by_arclength(curves, n)
    u = jnp.linspace(0, 1, n, dtype=curves.dtype)

    def residual_and_position(c):
        return c.length[..., None] * u - c.arc_length(t), c.position(t)

    _, (de, dpos) = jax.jvp(residual_and_position, (curves,), (dcurves,))
    de = jnp.where(curves.length[..., None] > 0, de, 0)
    tangent = curves.frame(t, "euler_rodrigues")[..., 0]
    return (t, points), (safe_div(de, curves.speed(t)), dpos + tangent * de[..., None])


_sample_jit = jit(_sample_impl, static_argnames=("n", "by", "with_t"))


def sample(
    curves: PHQuintic, n: int, by: Literal["time", "arclength"] = "time"
) -> tuple[Float[Array, "*batch n"], Float[Array, "*batch n 3"]]:
    """Sample every curve of a batch at ``n`` points.

    A batch whose arrays are sharded along axis 0 over a device mesh
    (:func:`phjax.batch.shard_batch`) runs on each device's part; the outputs are sharded the
    same way.

    Arguments:
        curves: a (batch of) :class:`PHQuintic`.
        n: number of samples per curve (static), including both ends.
        by: ``"time"`` for uniform parameter ``t``; ``"arclength"`` for points uniformly spaced
            in arc length (parameters from :meth:`PHQuintic.parameter_at_length`, the ends
            exactly at ``t = 0`` and ``1``; a curve of length 0 is sampled uniformly in ``t``).
            Its derivatives are the implicit-function ones (not the Newton loop's), finite
            for the points also where the speed vanishes.

    Returns:
        ``(t, points)`` with shapes ``(*batch, n)`` and ``(*batch, n, 3)``. ``t`` can be passed
        to the evaluation methods as is (each curve at its own parameters):
        ``curves.curvature(t)`` has shape ``(*batch, n)``, ``curves.frame(t)``
        ``(*batch, n, 3, 3)``.
    """
    _check_by(by)
    _check_curves(curves)
    static = {"n": _check_n(n), "by": by}
    sharding = _leading_sharding(curves) if curves.batch_shape else None
    if sharding is not None:
        _require_batch_sharded(curves, sharding, _SHARD_MESSAGE)
        return _sharded_function(_sample_impl, sharding, (curves,), static)(curves)
    return _sample_jit(curves, **static)


_SHARD_MESSAGE = ("a sharded batch of curves needs every one of its arrays split along axis 0 "
                  "on the same mesh: shard the curves with phjax.batch.shard_batch")


def _into_impl(curves, points, t, *, by):
    tt, pts = _sample_impl(curves, n=points.shape[-2], by=by, with_t=t is not None)
    return (None if t is None else tt.astype(t.dtype)), pts.astype(points.dtype)


# keep_unused: the buffers are only donated, never read; an unused argument would be pruned
# and its donation dropped
_into_jit = jit(_into_impl, static_argnames=("by",), donate_argnums=(1, 2), keep_unused=True)


def _check_float_dtype(name, dtype):
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"{name} must be floating point, got {dtype}")


def _check_buffer(name, buf, shape):
    if not isinstance(buf, jax.Array) or buf.shape != shape:
        raise ValueError(f"{name} must be a jax.Array of shape {shape}, got "
                         f"{type(buf).__name__} {getattr(buf, 'shape', None)}")
    _check_float_dtype(name, buf.dtype)
    if buf.is_deleted():
        raise ValueError(f"{name} was donated to an earlier call and is deleted: pass the array "
                         f"that call returned")


def sample_into(
    curves: PHQuintic,
    points: Float[Array, "*batch n 3"],
    t: Float[Array, "*batch n"] | None = None,
    *,
    by: Literal["time", "arclength"] = "time",
) -> tuple[Float[Array, "*batch n"] | None, Float[Array, "*batch n 3"]]:
    """:func:`sample` written into caller-provided buffers, which are donated.

    The buffers' memory is reused for the outputs (``jax.jit(..., donate_argnums=...)``), so
    a loop ``t, pts = sample_into(curves_k, pts, t)`` samples batch after batch without
    touching fresh memory; their contents are ignored. The buffers passed in are invalid
    afterwards (JAX raises on any use): keep the returned arrays. Buffers sharded along axis 0
    like the curves (:func:`phjax.batch.shard_batch`) are written on each device. Where a
    backend cannot reuse a buffer, JAX warns and the call still returns correct values.

    Arguments:
        curves: a (batch of) :class:`PHQuintic`.
        points: buffer ``(*batch, n, 3)``; ``n`` is the number of samples per curve.
        t: optional buffer ``(*batch, n)`` for the parameters (``None``: not computed).
        by: ``"time"`` or ``"arclength"``, as in :func:`sample`.

    Returns:
        ``(t, points)`` in the buffers' dtypes (``t`` is ``None`` when no buffer was given),
        equal to :func:`sample`'s.
    """
    _check_by(by)
    _check_curves(curves)
    b = curves.batch_shape
    if getattr(points, "ndim", 0) < 2 or points.shape[-2] < 1:
        raise ValueError(f"points must have shape (*batch, n, 3) with n >= 1, got "
                         f"{getattr(points, 'shape', type(points).__name__)}")
    n = points.shape[-2]
    _check_buffer("points", points, b + (n, 3))
    if t is not None:
        _check_buffer("t", t, b + (n,))
    sharding = _leading_sharding((curves, points, t)) if b else None
    if sharding is not None:
        args = (curves, points, t)
        _require_batch_sharded(args, sharding, _SHARD_MESSAGE + " (and the buffers with them)")
        return _sharded_function(_into_impl, sharding, args, {"by": by}, donate=(1, 2))(*args)
    return _into_jit(curves, points, t, by=by)


def _chunk_impl(curves, start, points, t, *, by):
    part = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, points.shape[0], 0), curves)
    return _into_impl(part, points, t, by=by)


_chunk_jit = jit(_chunk_impl, static_argnames=("by",), donate_argnums=(2, 3), keep_unused=True)


def sample_chunks(
    curves: PHQuintic,
    n: int,
    chunk: int,
    *,
    by: Literal["time", "arclength"] = "time",
    parameters: bool = False,
    buffers: int = 2,
    dtype=None,
) -> Iterator[tuple[int, Float[Array, " c n"] | None, Float[Array, "c n 3"]]]:
    """Sample a huge batch chunk by chunk into a ring of reused (donated) buffers.

    Every chunk has the same shape, so one program is compiled; the curves are sliced inside
    it. The last chunk, when ``chunk`` does not divide the batch, is sampled as the final full
    chunk of the batch and the rows already yielded are cut off (a slice of the buffer).

    The arrays yielded at step ``k`` live in the buffer that step ``k + buffers`` writes into
    (donated again): consume them (copy to the host, reduce, write to disk) before advancing
    the generator ``buffers`` times; a later access raises JAX's "Array has been deleted".

    Arguments:
        curves: a batch of :class:`PHQuintic` (flattened over its batch axes).
        n: samples per curve.
        chunk: curves per chunk (at most the batch size is used).
        by: ``"time"`` or ``"arclength"``, as in :func:`sample`.
        parameters: also yield the parameters ``t``.
        buffers: size of the buffer ring (>= 1).
        dtype: dtype of the buffers, floating point (default the curves' dtype).

    Yields:
        ``(start, t, points)``: the samples of flattened curves ``start .. start + len(points)``
        (``t`` is ``None`` unless ``parameters``), equal to :func:`sample`'s rows.
    """
    _check_by(by)
    _check_curves(curves)
    chunk, buffers = check_count(chunk, "chunk"), check_count(buffers, "buffers")
    n = _check_n(n)
    if dtype is not None:
        _check_float_dtype("dtype", jnp.dtype(dtype))
    b = curves.batch_shape
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(b):]), curves)
    total = flat.control_points.shape[0]
    if total == 0:
        return
    chunk = min(int(chunk), total)
    dtype = curves.dtype if dtype is None else dtype
    ring = [(jnp.zeros((chunk, n, 3), dtype),
             jnp.zeros((chunk, n), dtype) if parameters else None) for _ in range(int(buffers))]
    for k, start in enumerate(range(0, total, chunk)):
        s = min(start, total - chunk)
        pts, t = ring[k % len(ring)]
        t, pts = _chunk_jit(flat, s, pts, t, by=by)
        ring[k % len(ring)] = (pts, t)
        if s != start:  # final partial chunk: drop the rows of the previous chunk
            pts, t = pts[start - s:], None if t is None else t[start - s:]
        yield start, t, pts
