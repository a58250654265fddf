"""Batches of recordings for :func:`phjax.track` and :func:`phjax.reconstruct`.

A layer around the one-recording programs of :mod:`phjax.tracking.tracker`: each recording of a
NaN-padded batch (padding rule in :mod:`phjax.batch`) is normalised inside the compiled program
(times relative to its first frame, padding frames turned into lost frames after its end,
orientation-only recordings tracked at a fixed point) and the one-recording core runs under
``jax.vmap``; a batch sharded along axis 0 runs under ``jax.shard_map``, one part per device.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import jit
from .._misc import any_traced
from ..batch import _leading_sharding, _sharded_function
from ._shapes import MIN_FRAMES, MIN_RENDER, PAD_STEP, bounded_cache, size_class


def _lost_padding_frames(times, positions, quaternions):
    """One recording's padding frames (NaN times, trailing) as lost frames (NaN measurements)
    ``PAD_STEP`` apart after its last real frame (finite values and gradients)."""
    valid = jnp.isfinite(times)
    n_valid = jnp.sum(valid)
    t_last = jnp.where(n_valid > 0, times[jnp.maximum(n_valid - 1, 0)], 0)
    k = jnp.arange(times.shape[0]) - n_valid + 1
    t = jnp.where(valid, times, t_last + PAD_STEP * k)
    nan = jnp.asarray(jnp.nan, positions.dtype)
    return (t, jnp.where(valid[:, None], positions, nan),
            jnp.where(valid[:, None], quaternions, nan))


def _fill_padding(times, positions, quaternions, dtype):
    """One padded recording as the core expects it: times relative to the first frame, the
    padding frames (NaN time) turned into lost frames ``PAD_STEP`` apart after the last real
    one, orientation-only data at a fixed point, position-only data at the identity orientation.
    Returns the arrays, the time origin, the last real time (relative), the number of real
    frames and the flags ``(orientation_only, position_only)``."""
    valid = jnp.isfinite(times)
    n_valid = jnp.sum(valid)
    origin = jnp.where(n_valid > 0, times[0], 0)  # padding is trailing: frame 0 is real
    t = times - origin
    t_last = jnp.where(n_valid > 0, t[jnp.maximum(n_valid - 1, 0)], 0)
    k = jnp.arange(times.shape[0]) - n_valid + 1
    t = jnp.where(valid, t, t_last + PAD_STEP * k).astype(dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    p = jnp.where(valid[:, None], positions.astype(dtype), nan)
    q = jnp.where(valid[:, None], quaternions.astype(dtype), nan)
    p_ok = jnp.all(jnp.isfinite(p), -1, keepdims=True)
    q_ok = jnp.all(jnp.isfinite(q), -1, keepdims=True) & (
        jnp.sum(jnp.where(jnp.isfinite(q), q, 0) ** 2, -1, keepdims=True) > 0)
    orientation_only = ~jnp.any(p_ok)
    position_only = ~orientation_only & ~jnp.any(q_ok)
    p = jnp.where(orientation_only, jnp.where(q_ok, jnp.zeros_like(p), nan), p)
    identity = jnp.asarray([1, 0, 0, 0], dtype)
    q = jnp.where(position_only, jnp.where(p_ok, identity, nan), q)
    return t, p, q, origin, t_last.astype(dtype), n_valid, (orientation_only, position_only)


def _one(core, hold_end, config, times, positions, quaternions, render_times, dtype):
    """``core`` (the one-recording program of ``track`` or ``reconstruct``) on one padded
    recording, traceable; ``hold_end``: the core interpolates between frames, so render times
    are clamped to the last real frame."""
    t, p, q, origin, t_last, n_valid, (orientation_only, position_only) = _fill_padding(
        times, positions, quaternions, dtype)
    r_ok = jnp.isfinite(render_times)
    r = jnp.where(r_ok, render_times - origin, 0).astype(dtype)
    # hold the end pose past the last real frame: never interpolate into the padding
    out_p, out_q = core(config, t, p, q, jnp.minimum(r, t_last) if hold_end else r)
    bad = (~r_ok | (n_valid == 0))[:, None]
    nan = jnp.asarray(jnp.nan, dtype)
    return (jnp.where(bad | orientation_only, nan, out_p),
            jnp.where(bad | position_only, nan, out_q))


def _local(config, times, positions, quaternions, render_times, *, core, hold_end, dtype):
    """The batch (or one device's part of it): flatten the batch axes, ``vmap`` the core."""
    b, n = times.shape[:-1], times.shape[-1]
    shared = render_times.ndim == 1
    m = render_times.shape[-1]
    flat = (times.reshape(-1, n), positions.reshape(-1, n, 3), quaternions.reshape(-1, n, 4),
            render_times if shared else render_times.reshape(-1, m))
    one = functools.partial(_one, core, hold_end, dtype=jnp.dtype(dtype))
    p, q = jax.vmap(one, in_axes=(None, 0, 0, 0, None if shared else 0))(config, *flat)
    return p.reshape(b + (m, 3)), q.reshape(b + (m, 4))


_local_jit = jit(_local, static_argnames=("core", "hold_end", "dtype"))


def _flags(xp, times, render_times):
    """Flags of bad batch input (``xp``: NumPy or jax.numpy): a real frame after padding,
    times not strictly increasing, infinite times, infinite render times."""
    nan = xp.isnan(times)
    after_pad = xp.any(nan[..., :-1] & ~nan[..., 1:])
    dt = xp.diff(times, axis=-1)
    not_increasing = xp.any(~nan[..., 1:] & ~(dt > 0))
    return xp.stack([after_pad, not_increasing, xp.any(xp.isinf(times)),
                     xp.any(xp.isinf(render_times))])


#: :func:`_flags` of device arrays, without copying them to the host
_check_values = jit(functools.partial(_flags, jnp))


def _pad_to_class(xp, times, positions, quaternions, render_times):
    """A padded batch padded further, to its size class (NaN frames and render times)."""
    n, m = times.shape[-1], render_times.shape[-1]
    dn, dm = size_class(n, MIN_FRAMES) - n, size_class(m, MIN_RENDER) - m

    def pad(x, axis, k):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, k)
        return xp.pad(x, widths, constant_values=np.nan)

    return (pad(times, -1, dn), pad(positions, -2, dn), pad(quaternions, -2, dn),
            pad(render_times, -1, dm)), m


def _relative_on_host(times, render_times):
    """Times and render times relative to each recording's first frame, in float64 on the
    host (absolute epoch times keep their precision when the program runs in float32); render
    times per recording then."""
    origin = np.where(np.isfinite(times[..., :1]), times[..., :1], 0.0)
    render = np.broadcast_to(render_times, times.shape[:-1] + render_times.shape[-1:])
    return times - origin, render - origin


def run_batch(core, config, times, positions, quaternions, render_times, dtype, hold_end=False):
    """Validate a padded batch (shapes on the host, values with one small reduction), then run
    the compiled batch program of the one-recording ``core`` (``shard_map`` over the mesh if
    the inputs are batch-sharded; else padded to the batch's size class first).

    Host inputs (NumPy arrays, lists) are checked, made relative to each recording's first
    time in float64 and padded on the host: one compiled program per size class and dtype,
    whatever the lengths in it. Device arrays (``jax.Array``, sharded or not) stay there."""
    inputs = (times, positions, quaternions, render_times)
    on_host = not any(isinstance(x, jax.Array) for x in inputs)
    xp = np if on_host else jnp
    times, positions, quaternions, render_times = (
        np.asarray(x, np.float64) if on_host else jnp.asarray(x) for x in inputs)
    b, n = times.shape[:-1], times.shape[-1]
    if positions.shape != b + (n, 3) or quaternions.shape != b + (n, 4):
        raise ValueError("expected times (*B, N), positions (*B, N, 3), quaternions (*B, N, 4); "
                         f"got {times.shape}, {positions.shape}, {quaternions.shape}")
    if render_times.ndim != 1 and render_times.shape[:-1] != b:
        raise ValueError(f"render_times must be (M,) or (*B, M) with B = {b}, "
                         f"got shape {render_times.shape}")
    if n < 1:
        raise ValueError("need at least one measurement")
    flags = np.asarray(_flags(np, times, render_times) if on_host
                       else _check_values(times, render_times))
    for bad, msg in zip(flags, ("padding (NaN times) must come after every real frame",
                                "measurement times must be strictly increasing in each recording",
                                "measurement times must be finite or NaN (padding)",
                                "render times must be finite or NaN (padding)")):
        if bad:
            raise ValueError(msg)
    dtype = jnp.dtype(jnp.zeros((), float).dtype if dtype is None else dtype).name
    if on_host:
        times, render_times = _relative_on_host(times, render_times)
    args = (config, times, positions, quaternions, render_times)
    sharding = _leading_sharding(args[1:])
    if sharding is not None:
        from ..batch import _require_batch_sharded

        need = args[1:4] if render_times.ndim == 1 else args[1:]
        _require_batch_sharded(need, sharding,
                               "a sharded batch needs times, positions, quaternions (and per-"
                               "recording render times) all sharded along axis 0 on the same "
                               "mesh: shard them together with phjax.batch.shard_batch")
    static = {"core": core, "hold_end": hold_end, "dtype": dtype}
    if sharding is not None:
        fn = _sharded_function(_local, sharding, args, static)
    else:
        fn = _local_jit
        padded, m = _pad_to_class(xp, *args[1:])
        if on_host:  # one transfer in the program's dtype (the times are relative now)
            padded = tuple(jax.device_put(x.astype(dtype)) for x in padded)
        args = (config, *padded)
    key = (jax.tree.structure(config), core, dtype, tuple((a.shape, a.dtype) for a in args[1:]))
    bounded_cache(fn, key)
    if sharding is not None:
        return fn(*args)
    p, q = fn(*args, **static)
    if any_traced(p):  # computed from traced parameters (jax.grad of a call)
        return p[..., :m, :], q[..., :m, :]
    # sliced on the host: a slice of a device array compiles a program for every length
    return tuple(jax.device_put(np.asarray(x)[..., :m, :]) for x in (p, q))
