"""A real-time driver of the streaming tracker: lowest-latency camera updates and render samples.

:func:`phjax.tracker_update` and :func:`phjax.tracker_sample` are pure functions over
:class:`phjax.TrackerConfig` / :class:`phjax.TrackerState` PyTrees; that is the form for
``jit``, ``vmap``, ``grad`` and ``lax.scan``. In a render loop that calls them from Python,
most of a call's cost is not the arithmetic but crossing the jit boundary: flattening the
equinox config and state (Python code, run on every call) and handing each of their ~22 leaves
to XLA. :class:`TrackerStream` holds the same state packed into six vectors of at most 64
elements and the config in one vector, and calls one compiled function on those arrays, so a
camera update costs the arithmetic plus a handful of buffers. The results are those of
:func:`phjax.tracker_update` / :func:`phjax.tracker_sample` (same code, same compiled
arithmetic): ``stream.state`` gives the :class:`TrackerState` at any time.

Why at most 64 elements per vector: XLA's CPU runtime runs the kernels of a call one after the
other in the calling thread only when every buffer has at most 512 bytes (64 float64 values);
larger buffers send the kernels to its thread pool, which costs microseconds each (see
:class:`phjax.TrackerState`).

For the lowest latency on a CPU also turn off JAX's asynchronous dispatch at program start
(``jax.config.update("jax_cpu_enable_async_dispatch", False)``; ``benchmarks/bench_tracker.py``
measures both).

This is a stateful Python object for the host-side render loop; inside ``jit`` / ``scan`` use
the pure functions (``phjax.track`` is the whole-recording scan).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .tracker import TrackerConfig, TrackerState, _sample_render, _update, tracker_init

__all__ = ["TrackerStream"]

#: largest number of elements of one packed vector (512 bytes of float64)
_CHUNK = 64


class _Layout:
    """How a PyTree of arrays is packed into a few flat vectors of one float dtype.

    Consecutive leaves share a vector while it stays within ``_CHUNK`` elements (a larger leaf
    gets a vector of its own); leaves listed in ``alone`` always get their own vector, so that
    they can be passed on without unpacking. Floating leaves come back in the packed dtype;
    boolean and integer leaves round-trip exactly (stored as 0/1 and small integers).
    """

    def __init__(self, tree, dtype, alone=()):
        leaves, self.treedef = jax.tree.flatten(tree)
        self.dtype = jnp.dtype(dtype)
        self.meta = tuple((tuple(np.shape(x)), jnp.asarray(x).dtype) for x in leaves)
        alone_ids = {id(x) for x in alone}
        groups, open_size = [], None  # open_size: elements of the last vector, None: closed
        for i, (x, (shape, _)) in enumerate(zip(leaves, self.meta)):
            n = math.prod(shape)
            if id(x) in alone_ids:
                groups.append((i,))
                open_size = None
            elif open_size is not None and open_size + n <= _CHUNK:
                groups[-1] += (i,)
                open_size += n
            else:
                groups.append((i,))
                open_size = n
        self.groups = tuple(groups)

    def pack(self, tree) -> tuple[Array, ...]:
        leaves = jax.tree.leaves(tree)
        return tuple(
            jnp.concatenate([jnp.ravel(jnp.asarray(leaves[i])).astype(self.dtype) for i in g])
            if len(g) > 1 else jnp.ravel(jnp.asarray(leaves[g[0]])).astype(self.dtype)
            for g in self.groups)

    def unpack(self, vectors):
        leaves = [None] * len(self.meta)
        for g, v in zip(self.groups, vectors):
            off = 0
            for i in g:
                shape, dt = self.meta[i]
                n = math.prod(shape)
                x = v[off:off + n].reshape(shape)
                off += n
                if dt == jnp.bool_:
                    x = x > 0
                elif jnp.issubdtype(dt, jnp.integer):
                    x = jnp.round(x).astype(dt)
                leaves[i] = x  # floating leaves keep the packed dtype
        return jax.tree.unflatten(self.treedef, leaves)

    def position(self, leaf_index: int) -> int:
        """Index of the vector that holds leaf ``leaf_index`` (alone)."""
        for k, g in enumerate(self.groups):
            if g == (leaf_index,):
                return k
        raise ValueError(f"leaf {leaf_index} does not have a vector of its own")


#: compiled packed updates, one per (config layout, state layout) signature
_COMPILED: dict = {}


def _compiled_update(config_layout: _Layout, state_layout: _Layout):
    key = (config_layout.treedef, tuple(config_layout.meta), config_layout.dtype,
           state_layout.treedef, tuple(state_layout.meta), state_layout.groups, state_layout.dtype)
    fn = _COMPILED.get(key)
    if fn is None:
        def packed_update(cvec, svecs, t, position, quaternion):
            config = config_layout.unpack(cvec)
            state = state_layout.unpack(svecs)
            return state_layout.pack(_update(config, state, t, position, quaternion))

        fn = _COMPILED[key] = jax.jit(packed_update)
    return fn


class TrackerStream:
    """Stateful real-time driver of the streaming tracker (host-side render loops).

    ``update`` feeds a camera-rate measurement (:func:`phjax.tracker_update`), ``sample``
    renders (:func:`phjax.tracker_sample`); both call one compiled function on packed arrays
    (see the module docs). Shapes are static: nothing recompiles per frame.

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

    def __init__(self, config: TrackerConfig | None = None, t: float = 0.0, dtype=jnp.float32):
        self.config = TrackerConfig() if config is None else config
        state = tracker_init(self.config, t, dtype)
        dtype = state.render[2].dtype
        self._config_layout = _Layout(self.config, dtype)
        self._cvec = self._config_layout.pack(self.config)
        self._layout = _Layout(state, dtype, alone=state.render)
        leaves = jax.tree.leaves(state)
        ids = [next(i for i, x in enumerate(leaves) if x is r) for r in state.render]
        self._render_at = tuple(self._layout.position(i) for i in ids)
        self._packed = self._layout.pack(state)
        self._update = _compiled_update(self._config_layout, self._layout)

    @property
    def state(self) -> TrackerState:
        """The current :class:`phjax.TrackerState` (unpacked copy)."""
        return self._layout.unpack(self._packed)

    @state.setter
    def state(self, value: TrackerState) -> None:
        self._packed = self._layout.pack(value)

    def update(self, t: Float[ArrayLike, ""], position: Float[ArrayLike, "3"],
               quaternion: Float[ArrayLike, "4"]) -> None:
        """Feed one camera-rate measurement (as :func:`phjax.tracker_update`).

        Arguments:
            t: measurement time, s.
            position: measured position, m (NaN if missing).
            quaternion: measured orientation wxyz (NaN if missing; sign irrelevant).
        """
        self._packed = self._update(self._cvec, self._packed, t, position, quaternion)

    def sample(self, t_render: Float[ArrayLike, "*T"]) -> tuple[Float[Array, "*T 3"], Float[Array, "*T 4"]]:
        """Rendered pose at render time(s) ``t_render`` (as :func:`phjax.tracker_sample`).

        Returns:
            ``(position (*T, 3), quaternion (*T, 4))``; NaN before the first valid measurement.
        """
        packed = self._packed
        return _sample_render(tuple(packed[i] for i in self._render_at), t_render)
