"""Size classes: array lengths rounded up so that inputs of many lengths share one program.

Every new array shape makes JAX trace and XLA compile a program again. Entry points that take
recordings of any length pad them to a **size class**, the next power of two (at least a
minimum), so that lengths 300 to 512 share one compiled program and 513 to 1024 the next.
Used by :mod:`phjax.tracking` (whole recordings), :func:`phjax.motion.resample.interpolate_poses`,
:func:`phjax.simulate_measurements` and the JAX baselines (:func:`pad_samples`,
:func:`unpad_rows`).
"""

from __future__ import annotations

import jax
import numpy as np
from jaxtyping import Array

from ._misc import any_traced

__all__ = ["MIN_FRAMES", "MIN_RENDER", "pad_samples", "size_class", "unpad_rows"]

#: smallest size classes (frames or samples, render or query times): short inputs share one
MIN_FRAMES = 64
MIN_RENDER = 256


def size_class(n: int, minimum: int) -> int:
    """The size class of ``n`` items: the next power of two, at least ``minimum``."""
    return max(int(minimum), 1 << max(int(n) - 1, 0).bit_length())


def pad_samples(times, positions, quaternions, query_times, *others):
    """Samples and queries padded to their size classes, as NumPy arrays (``None`` when any
    argument, ``others`` included, is traced or an array is not floating point).

    Padded samples repeat the last time with NaN position and orientation (invalid rows after
    every real one: no query sees them); padded queries are the first sample time (their
    results are to be dropped). See :func:`phjax.motion.resample.interpolate_poses`. Unlike
    :func:`phjax.tracking._shapes.pad_recording`, whose padding frames come after every render
    time (the tracker's filter steps through lost frames, so they must follow what is shown),
    nothing here reads an invalid row, and repeating the last time keeps the arrays' dtype
    and holds for any query (NaN included).

    Times and queries come back relative to the first sample time, subtracted in their own
    precision (every caller depends on time differences only; epoch times of 1.7e9 s in the
    float32 of a jitted call would be 128 s apart).

    Returns:
        ``(times (nb,), positions (nb, 3), quaternions (nb, 4), query_times (mb,))`` or ``None``.
    """
    if any_traced(times, positions, quaternions, query_times, others):
        return None
    t, p, q, r = (np.asarray(x) for x in (times, positions, quaternions, query_times))
    if not all(np.issubdtype(x.dtype, np.floating) for x in (t, p, q, r)):
        return None
    if t.size and np.isfinite(t[0]):
        t, r = t - t[0], r - t[0]
    n, m = t.shape[0], r.shape[0]
    dn, dm = size_class(n, MIN_FRAMES) - n, size_class(m, MIN_RENDER) - m
    return (np.concatenate([t, np.full(dn, t[-1], t.dtype)]),
            np.concatenate([p, np.full((dn, 3), np.nan, p.dtype)]),
            np.concatenate([q, np.full((dn, 4), np.nan, q.dtype)]),
            np.concatenate([r, np.full(dm, t[0], r.dtype)]))


def unpad_rows(x: Array, m: int) -> Array:
    """The first ``m`` rows of a result computed on padded inputs (sliced on the host and put
    back with ``device_put``: a slice of a JAX array, or ``jnp.asarray`` of a NumPy array,
    compiles a small program for every length)."""
    if any_traced(x):  # computed from traced parameters (jax.grad of a call)
        return x[:m]
    return jax.device_put(np.asarray(x)[:m])
