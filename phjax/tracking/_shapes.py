"""Size classes: one compiled program per size class of recording, not one per length.

Every new array shape compiles a program again (seconds for a tracker scan), so the
whole-recording entry points (:func:`phjax.track`, :func:`phjax.reconstruct`, the causal
baselines) pad their inputs to a **size class**: the next power of two of the number of frames
(at least :data:`MIN_FRAMES`) and of render times (at least :data:`MIN_RENDER`). Recordings of
300 to 512 frames share one program, 513 to 1024 the next. Padding never changes a result:

* padding frames come after every real frame and after every render time, as lost frames
  (NaN measurements), so a causal method never shows them and a filter only predicts through
  them; methods that interpolate between frames (the offline reconstruction) are given render
  times clamped to the last real frame (``hold_end``), which is what they show there anyway;
* padded render times are evaluated and dropped.

The compiled programs a process keeps are bounded as well (:func:`bounded_cache`): XLA:CPU maps
each compiled program's code into its own memory regions, and a process has a limited number.
"""

from __future__ import annotations

import numpy as np

# the size classes themselves (shared with phjax.motion): MIN_FRAMES, MIN_RENDER, size_class
from .._sizes import MIN_FRAMES, MIN_RENDER, size_class

__all__ = ["MIN_FRAMES", "MIN_RENDER", "MAX_COMPILED_SHAPES", "bounded_cache", "pad_recording",
           "size_class"]

#: time step (s) between padding frames, after the last real frame and the last render time
PAD_STEP = 1.0
#: compiled versions (input shapes) kept per entry point, see :func:`bounded_cache`
MAX_COMPILED_SHAPES = 16

_COMPILED_KEYS: dict = {}


def pad_recording(times, positions, quaternions, render_times, *, hold_end: bool = False):
    """One recording (host arrays, times sorted and relative) padded to its size class.

    Arguments:
        times, positions, quaternions: ``(N,)``, ``(N, 3)``, ``(N, 4)`` float64 NumPy arrays.
        render_times: ``(M,)`` render times.
        hold_end: clamp the render times to the last frame's time (for methods that
            interpolate between frames and hold the end pose after the last one).

    Returns:
        ``(times, positions, quaternions, render_times)`` of lengths ``size_class(N)`` and
        ``size_class(M)``: padding frames are lost frames ``PAD_STEP`` apart after both the last
        frame and the last render time; padded render times repeat the first frame's time.
    """
    n, m = times.shape[0], render_times.shape[0]
    nb, mb = size_class(n, MIN_FRAMES), size_class(m, MIN_RENDER)
    if hold_end:
        render_times = np.minimum(render_times, times[-1])
    start = max(times[-1], render_times.max(initial=times[-1]))
    pad_t = start + PAD_STEP * np.arange(1, nb - n + 1)
    nan = np.full((nb - n, 1), np.nan)
    return (np.concatenate([times, pad_t]),
            np.concatenate([positions, np.broadcast_to(nan, (nb - n, 3))]),
            np.concatenate([quaternions, np.broadcast_to(nan, (nb - n, 4))]),
            np.concatenate([render_times, np.full(mb - m, times[0])]))


def bounded_cache(core, key) -> None:
    """Keep at most :data:`MAX_COMPILED_SHAPES` compiled versions of the jitted ``core``.

    XLA:CPU maps the code of each compiled program into memory regions of its own
    (``/proc/self/maps``), released only with the executable; Linux allows a process 65530 of
    them (``vm.max_map_count``), then mmap fails inside XLA's compiler and the process dies
    (reproduced with the limit lowered to 8000). One compiled tracker scan maps 258-260 regions
    with phjax's compiler options (fusion emitters off; jaxlib 0.10.2, 120-500 frames; ~925 with
    them, about 1200 when the bound was 4), so the bound of 16 versions keeps one entry
    point below ~4200 regions while a process that alternates between a few configurations
    and size classes (a test run, a notebook) keeps them all. Before a new version would exceed
    the bound, ``core``'s compilation cache is cleared.
    """
    keys = _COMPILED_KEYS.setdefault(core, set())
    if key not in keys and max(len(keys), core._cache_size()) >= MAX_COMPILED_SHAPES:
        core.clear_cache()
        keys.clear()
    keys.add(key)
