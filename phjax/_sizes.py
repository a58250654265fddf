"""Size classes: array lengths rounded up so that inputs of many lengths share one program.

Every new array shape makes JAX trace and XLA compile a program again. Entry points that take
recordings of any length pad them to a **size class**, the next power of two (at least a
minimum), so that lengths 300 to 512 share one compiled program and 513 to 1024 the next.
Used by :mod:`phjax.tracking` (whole recordings), :func:`phjax.motion.resample.interpolate_poses`
and :func:`phjax.simulate_measurements`.
"""

from __future__ import annotations

__all__ = ["MIN_FRAMES", "MIN_RENDER", "size_class"]

#: smallest size classes (frames or samples, render or query times): short inputs share one
MIN_FRAMES = 64
MIN_RENDER = 256


def size_class(n: int, minimum: int) -> int:
    """The size class of ``n`` items: the next power of two, at least ``minimum``."""
    return max(int(minimum), 1 << max(int(n) - 1, 0).bit_length())
