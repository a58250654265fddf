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


@jit
def _check_values(times, render_times):
    """Flags of bad batch input: a real frame after padding, times not strictly increasing,
    infinite times, infinite render times."""
    nan = jnp.isnan(times)
    after_pad = jnp.any(nan[..., :-1] & ~nan[..., 1:])
    dt = jnp.diff(times, axis=-1)
    not_increasing = jnp.any(~nan[..., 1:] & ~(dt > 0))
    return jnp.stack([after_pad, not_increasing, jnp.any(jnp.isinf(times)),
                      jnp.any(jnp.isinf(render_times))])


def _as_array(x):
    return x if isinstance(x, jax.Array) else jnp.asarray(np.asarray(x))


def _pad_to_class(times, positions, quaternions, render_times):
    """A padded batch padded further, to its size class (NaN frames and render times)."""
    n, m = times.shape[-1], render_times.shape[-1]
    dn, dm = size_class(n, MIN_FRAMES) - n, size_class(m, MIN_RENDER) - m

    def pad(x, axis, k):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, k)
        return jnp.pad(x, widths, constant_values=jnp.nan)

    return (pad(times, -1, dn), pad(positions, -2, dn), pad(quaternions, -2, dn),
            pad(render_times, -1, dm)), m


def run_batch(core, config, times, positions, quaternions, render_times, dtype, hold_end=False):
    """Validate a padded batch (shapes on the host, values with one small reduction), then run
    the compiled batch program of the one-recording ``core`` (``shard_map`` over the mesh if
    the inputs are batch-sharded; else padded to the batch's size class first)."""
    times, positions, quaternions, render_times = (
        _as_array(x) for x in (times, positions, quaternions, render_times))
    b, n = times.shape[:-1], times.shape[-1]
    if positions.shape != b + (n, 3) or quaternions.shape != b + (n, 4):
        raise ValueError("expected times (*B, N), positions (*B, N, 3), quaternions (*B, N, 4); "
                         f"got {times.shape}, {positions.shape}, {quaternions.shape}")
    if render_times.ndim != 1 and render_times.shape[:-1] != b:
        raise ValueError(f"render_times must be (M,) or (*B, M) with B = {b}, "
                         f"got shape {render_times.shape}")
    if n < 1:
        raise ValueError("need at least one measurement")
    flags = np.asarray(_check_values(times, render_times))
    for bad, msg in zip(flags, ("padding (NaN times) must come after every real frame",
                                "measurement times must be strictly increasing in each recording",
                                "measurement times must be finite or NaN (padding)",
                                "render times must be finite or NaN (padding)")):
        if bad:
            raise ValueError(msg)
    dtype = jnp.dtype(jnp.zeros((), float).dtype if dtype is None else dtype).name
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
        padded, m = _pad_to_class(*args[1:])
        args = (config, *padded)
    key = (jax.tree.structure(config), core, dtype, tuple((a.shape, a.dtype) for a in args[1:]))
    bounded_cache(fn, key)
    if sharding is not None:
        return fn(*args)
    p, q = fn(*args, **static)
    return p[..., :m, :], q[..., :m, :]
