"""A real-time driver of the streaming tracker: a stateful object for host-side render loops.

:func:`phjax.tracker_update` and :func:`phjax.tracker_sample` are pure functions over
:class:`phjax.TrackerConfig` / :class:`phjax.TrackerState` PyTrees; that is the form for
``jit``, ``vmap``, ``grad`` and ``lax.scan``. :class:`TrackerStream` holds the current state
and the config (converted once to device arrays of the state's dtype, see
:func:`phjax.tracker_config_arrays`) and calls those two compiled functions, so its results
are theirs; ``stream.state`` gives or replaces the :class:`TrackerState` at any time.

For the lowest latency on a CPU turn off JAX's asynchronous dispatch at program start
(``jax.config.update("jax_cpu_enable_async_dispatch", False)``); ``benchmarks/bench_tracker.py``
measures both settings against the targets (update <= 200 us, sample <= 20 us).

Inside ``jit`` / ``scan`` use the pure functions (``phjax.track`` is the whole-recording scan).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .tracker import (
    TrackerConfig,
    TrackerState,
    tracker_config_arrays,
    tracker_init,
    tracker_sample,
    tracker_update,
)

__all__ = ["TrackerStream"]


class TrackerStream:
    """Stateful real-time driver of the streaming tracker (host-side render loops).

    ``update`` feeds a camera-rate measurement (:func:`phjax.tracker_update`), ``sample``
    renders (:func:`phjax.tracker_sample`). Shapes are static: nothing recompiles per frame.
    Replacing :attr:`state` is atomic, so a capture thread may update while a render thread
    samples.

    Arguments:
        config: tracker configuration (default :class:`phjax.TrackerConfig()`).
        t: start time, s.
        dtype: floating dtype of the state (default float32, the real-time precision; float64
            needs ``jax_enable_x64``).

    Example::

        stream = phjax.TrackerStream()
        stream.update(t_frame, position, quaternion)      # camera thread, NaN when lost
        p, q = stream.sample(t_render)                      # render loop
    """

    #: the current state (settable: the stream continues from the given state)
    state: TrackerState

    def __init__(self, config: TrackerConfig | None = None, t: float = 0.0, dtype=jnp.float32):
        self.config = TrackerConfig() if config is None else config
        self.state = tracker_init(self.config, t, dtype)
        #: the floating dtype of the state
        self.dtype = self.state.segment.start.dtype
        self._config = tracker_config_arrays(self.config, self.dtype)

    def update(self, t: Float[ArrayLike, ""], position: Float[ArrayLike, "3"],
               quaternion: Float[ArrayLike, "4"]) -> None:
        """Feed one camera-rate measurement (as :func:`phjax.tracker_update`).

        Arguments:
            t: measurement time, s.
            position: measured position, m (NaN if missing).
            quaternion: measured orientation wxyz (NaN if missing; sign irrelevant).
        """
        self.state = tracker_update(self._config, self.state, t, position, quaternion)

    def sample(self, t_render: Float[ArrayLike, "*T"]) -> tuple[Float[Array, "*T 3"], Float[Array, "*T 4"]]:
        """Rendered pose at render time(s) ``t_render`` (as :func:`phjax.tracker_sample`).

        Returns:
            ``(position (*T, 3), quaternion (*T, 4))``; NaN before the first valid measurement.
        """
        return tracker_sample(self._config, self.state, t_render)
