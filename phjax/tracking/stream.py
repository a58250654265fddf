"""A real-time driver of the streaming tracker: a stateful object for host-side render loops.

:func:`phjax.tracker_update` and :func:`phjax.tracker_sample` are pure functions over
:class:`phjax.TrackerConfig` / :class:`phjax.TrackerState` PyTrees; that is the form for
``jit``, ``vmap``, ``grad`` and ``lax.scan``. :class:`TrackerStream` holds the current state
and the config (converted once to device arrays of the state's dtype, see
:func:`phjax.tracker_config_arrays`) as flat lists of their leaves and calls the same update
and sample code jitted on those lists, so its results are theirs without flattening the nested
modules in Python on every call; ``stream.state`` gives or replaces the :class:`TrackerState`
at any time.

The first update compiles quickly and less optimised, and the optimised program replaces it a
few seconds later from a background compilation (:class:`phjax._jit.Tiered`;
``fast_start=False`` compiles the optimised program at once, :meth:`TrackerStream.wait_compiled`
waits for it).

For the lowest latency on a CPU turn off JAX's asynchronous dispatch at program start
(``jax.config.update("jax_cpu_enable_async_dispatch", False)``); ``benchmarks/bench_tracker.py``
measures both settings against the targets (update <= 200 us, sample <= 20 us).

Inside ``jit`` / ``scan`` use the pure functions (``phjax.track`` is the whole-recording scan).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._jit import Tiered, jit
from .._np_quat import np_valid_quaternions
from ._noise_core import noise_monitor_std
from .tracker import (
    check_config,
    TrackerConfig,
    TrackerState,
    _filter_restart_part,
    _noise_min_count,
    _sample,
    _stream_filter,
    _update,
    tracker_config_arrays,
    tracker_init,
)

__all__ = ["PARTIAL_FRAMES", "TIME_STEP_BACK", "TrackerStream"]

#: a host measurement time this far (s) before the stream's latest one breaks its time line
#: (see :class:`TrackerStream`, "Times that jump"): late measurements within it are applied
#: at the latest time, as the filter does with any late measurement
TIME_STEP_BACK = 0.5

#: measurements with one part of the pose (and the other never seen) after which a stream takes
#: the missing part as fixed (:class:`TrackerStream`): a third of a second at 30 Hz, so that a
#: frame that lost only its position at the start does not pin a 6-DoF source to the origin
PARTIAL_FRAMES = 10


@functools.cache
def _on_leaves(fn, config_def, state_def):
    """``jit(fn)`` on the flat leaf lists of a config and a state of the given structures,
    returning the new state's leaves: the stream keeps its PyTrees flattened, so a call does not
    flatten and rebuild the nested equinox modules in Python (about a quarter of an update's
    time on a CPU, see ``benchmarks/README.md``)."""
    def on_leaves(config_leaves, state_leaves, *args):
        config = jax.tree.unflatten(config_def, config_leaves)
        state = jax.tree.unflatten(state_def, state_leaves)
        return jax.tree.leaves(fn(config, state, *args))

    return jit(on_leaves)


@functools.cache
def _tiered_on_leaves(fn, config_def, state_def, dtype):
    """:func:`_on_leaves` compiled fast first, optimised in the background (one per dtype:
    a :class:`~phjax._jit.Tiered` program serves one input signature)."""
    return Tiered(_on_leaves(fn, config_def, state_def))


def _wait_optimised(program, timeout: float | None) -> bool:
    """Wait for a :class:`~phjax._jit.Tiered` program's optimised compilation (``True`` at
    once for a plain jitted one); returns whether it runs the optimised program."""
    return program.wait(timeout) if isinstance(program, Tiered) else True


def _update_timed(config: TrackerConfig, state: TrackerState, t, position, quaternion):
    """:func:`~phjax.tracking.tracker._update`, except that a time that is not finite in the
    state's dtype (a NaN or inf ``jax.Array`` time, which the stream cannot check on the host
    without waiting for the device) leaves the state as it was: it would make the render
    segment NaN (inf: for good)."""
    new = _update(config, state, t, position, quaternion)
    ok = jnp.isfinite(jnp.asarray(t, state.segment.start.dtype))
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, state)


@functools.cache
def _sample_on_leaves(segment_def):
    """``jit(_sample)`` on the flat leaf list of a render segment."""
    return jit(lambda leaves, t: _sample(jax.tree.unflatten(segment_def, leaves), t))


class TrackerStream:
    """Stateful real-time driver of the streaming tracker (host-side render loops).

    ``update`` feeds a camera-rate measurement (:func:`phjax.tracker_update`), ``sample``
    renders (:func:`phjax.tracker_sample`), with the same results. Shapes are static: nothing
    recompiles per frame. The state is replaced atomically by an update, so a capture thread
    may update while a render thread samples.

    Arguments:
        config: tracker configuration (default :class:`phjax.TrackerConfig()`).
        t: start time, s: the origin of the state's times (default: the first update's time).
            Host times (Python floats, NumPy values) are given to :meth:`update` and
            :meth:`sample` as they come (absolute epoch times too) and subtracted from the
            origin in float64 before the float32 state sees them, which would round a time of
            1.7e9 s to 128 s. A ``jax.Array`` time is taken as relative to the origin already
            (0 unless ``t`` was given) and passed on unchanged; such an update also skips the
            one-part completion below (its position and quaternion go to the filter as
            given; one that is not finite leaves the state unchanged, as the host cannot
            check it without waiting for the device). The state's times still grow with
            uptime: in float32, constant motion at 0.2 m/s and 60 deg/s is rendered within
            0.3 mm / 0.1 deg after 4 h and 2.5 mm / 0.75 deg after 24 h (measured); for longer
            sessions start a new stream (or use float64).
        dtype: floating dtype of the state (default float32, the real-time precision; float64
            needs ``jax_enable_x64``).
        fast_start: compile the first update quickly (XLA ``-O0``: on a 2-core CPU 2.2 s
            instead of 3.7 s, the update 20 % slower) and the optimised program in a
            background thread, used from the update after it is ready (a few seconds; one CPU
            core busy meanwhile). ``False``: the optimised program at once.

    **Sources that measure one part of the pose.** The filter starts from a whole pose. When
    :data:`PARTIAL_FRAMES` applied measurements (not those the time line below drops) have
    brought an orientation but never a position (a 3-DoF head tracker, an orientation-only
    trace), the stream takes the position to be the
    origin from then on (and the identity orientation for position-only sources), so that it
    starts and renders that part fixed instead of waiting forever; :attr:`measured_parts` says
    which parts have been measured. When the missing part is measured later, the filter
    starts that part again from its first measurement (the estimate it had was of the
    placeholder) and the stream moves there within a horizon; the other part goes on
    unchanged. A source that measures both from the start (or within those frames) is not
    affected. :func:`phjax.track` reports the never-measured part as NaN
    instead.

    **Times that jump.** The filter applies a late measurement at its latest time, so one
    host time far in the future (a glitched camera timestamp) used to hold every later
    measurement at that time: the stream stood still until the source's clock caught up,
    possibly never. A host time more than :data:`TIME_STEP_BACK` before the latest one
    breaks the time line. When the latest measurement had jumped more than that ahead of the
    one before it and this one continues the time line before the jump, the latest is
    forgotten (the state goes back to what it was before it). Otherwise this one is held
    until the next measurement: one that continues the old time line drops it (a late or
    stale frame), one that continues the new, earlier one means the source's clock went back
    for good (a restarted or looping source), and the filter starts again from the held
    measurement (the rendered pose jumps to it; without a given ``t`` the origin moves to
    it; the parts measured, :attr:`measured_parts`, are counted again from there).
    Forgotten and dropped measurements are counted in :attr:`time_glitches`, restarts
    in :attr:`time_restarts` (a first measurement that the next two contradict is a glitch).
    Until the next measurement, one far ahead shows the pose at rest where the stream was
    going. A ``jax.Array`` time is not checked (that would wait for the device).

    Example::

        stream = phjax.TrackerStream()
        stream.update(t_frame, position, quaternion)      # camera thread, NaN when lost
        p, q = stream.sample(t_render)                      # render loop
    """

    def __init__(self, config: TrackerConfig | None = None, t: float | None = None,
                 dtype=jnp.float32, fast_start: bool = True):
        config = check_config(config)
        state = tracker_init(config, 0.0, dtype)
        #: the time (s) the state's times are relative to (``t``, else the first update's time)
        self.origin: float | None = None if t is None else float(t)
        #: the floating dtype of the state
        self.dtype = state.segment.start.dtype
        self._fast_start = fast_start
        self._scalar = np.dtype(self.dtype).type
        self._max = float(np.finfo(self.dtype).max)
        self._state_def = jax.tree.structure(state)
        self._segment_def = jax.tree.structure(state.segment)
        self._n_filter = len(jax.tree.leaves(state.filter))  # the segment's leaves follow
        self._n_segment = len(jax.tree.leaves(state.segment))
        self._seen = [False, False]  # position, orientation measured
        self._partial = 0  # measurements with one part only, while the other is unseen
        self._origin_given = t is not None
        #: host measurements forgotten as outlying times, and restarts of the time line
        #: (class docs, "Times that jump")
        self.time_glitches = 0
        self.time_restarts = 0
        self.set_config(config)
        self.state = state

    @property
    def measured_parts(self) -> tuple[bool, bool]:
        """``(position, orientation)``: whether a valid one has been measured so far."""
        return self._seen[0], self._seen[1]

    def _complete(self, leaves, position: np.ndarray, quaternion: np.ndarray):
        """``(leaves, position, quaternion)`` for a host measurement about to be applied to the
        state ``leaves``: the never-measured part of a one-part source filled in (the origin /
        the identity; class docs), and that part of the filter started again when it is
        measured at last; else unchanged. Counts the measurement towards
        :data:`PARTIAL_FRAMES`: called only for measurements that are applied (not for one the
        time line holds or drops)."""
        if self._seen[0] and self._seen[1]:  # a 6-DoF source (shapes: _host_measurement)
            return leaves, position, quaternion
        p_ok = bool(np.isfinite(position).all())
        q_ok = bool(np_valid_quaternions(quaternion))
        filled = 0 if self._seen[1] else 1  # the part filled in, if any: the unseen one
        filled_ok = p_ok if filled == 0 else q_ok
        self._seen[0] |= p_ok
        self._seen[1] |= q_ok
        if self._partial >= PARTIAL_FRAMES and filled_ok:
            # the filled-in part is measured at last: the filter's estimate of it was of the
            # placeholder, so that part starts again from this measurement (at rest); the
            # stream moves to it within a horizon, C1, and the other part goes on unchanged
            self._partial = 0
            state = jax.tree.unflatten(self._state_def, leaves)
            kf = _filter_restart_part(self.config, state.filter, filled, position, quaternion)
            return jax.tree.leaves(eqx.tree_at(lambda s: s.filter, state, kf)), position, quaternion
        other_seen = self._seen[0] if q_ok else self._seen[1]
        if p_ok != q_ok and not other_seen:  # one part only, and the other never seen
            self._partial += 1
            if self._partial >= PARTIAL_FRAMES:
                if q_ok:
                    position = np.zeros(3, position.dtype)
                else:
                    quaternion = np.array([1, 0, 0, 0], quaternion.dtype)
        return leaves, position, quaternion

    def set_config(self, config: TrackerConfig) -> None:
        """Use another config (one of the same structure does not recompile).

        Raises:
            ValueError: a config whose filter has another state (IMM or not, other model
                counts or orders): its state cannot continue this stream's (start a new
                stream, or set :attr:`state` from ``tracker_init`` of that config).
        """
        check_config(config)
        if hasattr(self, "_leaves") and jax.tree.structure(
                tracker_init(config, 0.0, self.dtype)) != self._state_def:
            raise ValueError("set_config: this config's filter state has another structure "
                             "than the stream's (IMM or not, model count or order, "
                             "noise_window on or off); start a new TrackerStream for it")
        leaves, self._config_def = jax.tree.flatten(tracker_config_arrays(config, self.dtype))
        self._update = self._program(_update_timed)
        self._config_leaves = leaves
        self.config = config

    def _program(self, fn):
        """``fn(config, state, *args)`` jitted on this stream's leaf lists, compiled fast first
        when ``fast_start`` is on (:class:`phjax._jit.Tiered`)."""
        if self._fast_start:
            return _tiered_on_leaves(fn, self._config_def, self._state_def, self.dtype)
        return _on_leaves(fn, self._config_def, self._state_def)

    def _host_time(self, t) -> float:
        """A host measurement time checked as :meth:`_relative` does (setting the origin when
        unset), as a Python float."""
        self._relative(t)
        return float(t)

    def _host_measurement(self, position, quaternion) -> tuple[np.ndarray, np.ndarray]:
        """Host position and quaternion in the stream's dtype, their shapes checked here (a
        measurement held by the time line is applied later, see :meth:`_feed`)."""
        position, quaternion = (np.asarray(position, self.dtype),
                                np.asarray(quaternion, self.dtype))
        for name, x, shape in (("position", position, (3,)), ("quaternion", quaternion, (4,))):
            if x.shape != shape:
                raise ValueError(f"tracker update: {name} must have shape {shape}, got {x.shape}")
        return position, quaternion

    def _relative(self, t) -> np.floating:
        """A host time relative to :attr:`origin` (set by the first call when unset), in the
        state's dtype."""
        if np.ndim(t) != 0:
            raise ValueError(f"tracker update: t must have shape (), got {np.shape(t)}")
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"tracker update: t must be finite, got {t}")
        origin = t if self.origin is None else self.origin
        if abs(t - origin) > self._max:  # would be inf in the state's dtype
            raise ValueError(f"tracker update: t must be within the range of {np.dtype(self.dtype)} "
                             f"from the stream's origin {origin}, got {t}")
        self.origin = origin
        return self._scalar(t - origin)

    @property
    def state(self) -> TrackerState:
        """The current :class:`phjax.TrackerState` (settable: the stream continues from it); its
        times are relative to :attr:`origin`."""
        return jax.tree.unflatten(self._state_def, self._leaves)

    @state.setter
    def state(self, value: TrackerState) -> None:
        leaves, treedef = jax.tree.flatten(value)
        if treedef != self._state_def:
            raise ValueError("state: not a TrackerState of this stream's filter and structure")
        self._leaves = leaves
        self._latest = None  # the latest host measurement time: unknown for a given state
        # (leaves, latest time, (measured parts, partial count)) before the latest measurement
        self._before = None
        self._pending = None  # (time, position, quaternion) held: far before the time line

    def _feed(self, t_host: float, position, quaternion, step) -> None:
        """Apply a host measurement at host time ``t_host`` (absolute) with
        ``step(leaves, t_relative, position, quaternion) -> leaves``, keeping the time line
        (class docs, "Times that jump"). The state is replaced once, at the end: a render
        thread never sees an intermediate one (a restarted filter before its first update
        renders NaN)."""
        tol = TIME_STEP_BACK
        rel = t_host - self.origin
        leaves, latest, before = self._leaves, self._latest, self._before
        pending, self._pending = self._pending, None
        back = latest is not None and rel < latest - tol
        if (back and before is not None and before[1] is not None
                and latest - before[1] > tol and rel >= before[1] - tol):
            # the latest measurement jumped ahead of the time line this one continues
            self.time_glitches += 1
            self._seen, self._partial = list(before[2][0]), before[2][1]
            leaves, latest, before, back = before[0], before[1], None, False
        elif back and pending is not None and rel >= pending[0] - self.origin - tol:
            # two measurements on a new, earlier time line: the source's clock went back; a
            # time line of one measurement (the stream's first) was that measurement's glitch
            if before is not None and before[1] is None:
                self.time_glitches += 1
            else:
                self.time_restarts += 1
            if not self._origin_given:  # the new time line keeps float32's resolution
                self.origin = pending[0]
            leaves = jax.tree.leaves(tracker_init(
                self.config, self._scalar(pending[0] - self.origin), self.dtype))
            # the filter starts again, and so does the count of the parts measured (a
            # glitched first measurement's parts were never measured)
            self._seen, self._partial = [False, False], 0
            leaves, latest, before = self._step(leaves, None, *pending, step)
            pending, back = None, False
        if pending is not None:
            self.time_glitches += 1  # held, and the time line went on without it: dropped
        if back:  # far before the time line: held until the next measurement tells
            self._pending = (t_host, np.array(position), np.array(quaternion))
        else:
            leaves, latest, before = self._step(leaves, latest, t_host, position, quaternion,
                                                step)
        self._leaves, self._latest, self._before = leaves, latest, before

    def _step(self, leaves, latest, t_host: float, position, quaternion, step):
        """``(new leaves, new latest time, (leaves, latest, counts))`` of one update (the
        one-part completion, :meth:`_complete`, applied here: ``counts`` are its counters
        before it)."""
        counts = (tuple(self._seen), self._partial)
        rel = t_host - self.origin
        filled, position, quaternion = self._complete(leaves, position, quaternion)
        new = step(filled, self._scalar(rel), position, quaternion)
        return new, (rel if latest is None else max(latest, rel)), (leaves, latest, counts)

    def update(self, t: Float[ArrayLike, ""], position: Float[ArrayLike, "3"],
               quaternion: Float[ArrayLike, "4"]) -> None:
        """Feed one camera-rate measurement (as :func:`phjax.tracker_update`).

        Arguments:
            t: measurement time, s (a ``jax.Array``: relative to :attr:`origin`, see the
                class docs).
            position: measured position, m (NaN if missing).
            quaternion: measured orientation wxyz (NaN if missing; sign irrelevant).

        Raises:
            ValueError: a host ``t`` that is not finite, or beyond the range of the state's
                dtype from :attr:`origin` (inf in the state); a measurement of another shape.
        """
        if not isinstance(t, jax.Array):  # host values: one input signature for every call
            t_host = self._host_time(t)
            position, quaternion = self._host_measurement(position, quaternion)
            self._feed(t_host, position, quaternion, functools.partial(
                self._update, self._config_leaves))
            return
        # device values: relative to the origin already (0 unless set)
        self.origin = 0.0 if self.origin is None else self.origin
        # host measurements (lists, float64) in the stream's dtype: one input signature
        position, quaternion = (x if isinstance(x, jax.Array) else np.asarray(x, self.dtype)
                                for x in (position, quaternion))
        self._leaves = self._update(self._config_leaves, self._leaves, t, position, quaternion)
        self._latest = self._before = self._pending = None  # a device time: unknown on the host

    def measurement_noise(self) -> tuple[float, float]:
        """The position (m) and orientation (rad) measurement stds of the next filter step:
        the configured ones, raised by the online noise floor
        (``TrackerConfig.noise_window``) where its estimate is larger. Computed on the host
        (no JAX call): cheap enough for a status display."""
        filt = _stream_filter(self.config)
        pos, rot = float(filt.pos_meas_noise), float(filt.rot_meas_noise)
        noise = self.state.noise
        if noise is None:
            return pos, rot
        est_p, est_r = noise_monitor_std(noise, _noise_min_count(self.config), xp=np)
        return max(pos, float(est_p)), max(rot, float(est_r))

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Wait until updates run the optimised program (see ``fast_start``).

        Arguments:
            timeout: the longest wait, s (default: until it is ready).

        Returns:
            Whether updates now run the optimised program (``True`` before the first update
            only when ``fast_start`` is off).
        """
        return _wait_optimised(self._update, timeout)

    def sample(self, t_render: Float[ArrayLike, "*T"]) -> tuple[Float[Array, "*T 3"], Float[Array, "*T 4"]]:
        """Rendered pose at render time(s) ``t_render`` (as :func:`phjax.tracker_sample`; a
        ``jax.Array`` is relative to :attr:`origin`, a host value absolute like the updates').

        Returns:
            ``(position (*T, 3), quaternion (*T, 4))``; NaN before the first valid measurement.

        Raises:
            ValueError: a host time that is not finite, or beyond the range of the state's
                dtype from :attr:`origin` (a ``jax.Array`` is not checked: that would wait for
                the device).
        """
        if not isinstance(t_render, jax.Array):
            origin, m = self.origin or 0.0, self._max
            if isinstance(t_render, float):  # a render loop's time: the fast path
                rel = t_render - origin
                ok = -m <= rel <= m  # False for NaN
            else:
                rel = np.asarray(t_render, np.float64) - origin
                ok = bool((np.abs(rel) <= m).all())
            if not ok:  # NaN, inf, or inf in the state's dtype
                raise ValueError(f"tracker sample: t_render must be finite and within the range of "
                                 f"{np.dtype(self.dtype)} from the stream's origin, got {t_render}")
            t_render = np.asarray(rel, self.dtype)
        segment = self._leaves[self._n_filter:self._n_filter + self._n_segment]
        return _sample_on_leaves(self._segment_def)(segment, t_render)
