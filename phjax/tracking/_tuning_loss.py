"""The tuning loss (:mod:`phjax.tracking.tuning`, whose docstring gives the formula): the four
terms of the causal stream on each recording (:func:`loss_terms`) and their weighted,
optionally normalised combination (:func:`tracker_loss`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._jit import jit
from .._misc import safe_div
from ._batch import _lost_padding_frames
from ._tuning_data import TuningData
from ._tuning_stream import stream_metrics
from .tracker import TrackerConfig, _scan_stream


@jit
def loss_terms(config: TrackerConfig, data: TuningData) -> Float[Array, "*R 4"]:
    """``[E_p, E_r, J_p, J_r]`` (m, rad, m/s^3, rad/s^3) of the causal stream on each recording.

    ``data`` may have any leading batch axes ``R`` (e.g. ``(sweeps, recordings)``) and follow
    the NaN padding rule of :mod:`phjax.batch`: NaN measurement times are lost frames after the
    recording's end, NaN render times are masked samples (values and gradients stay finite).
    Jitted (one program per data shape and configuration structure): called outside ``jit`` it
    ran op by op, 15 s a call on two 3-4 s recordings instead of 0.03 s.
    """
    b = data.times.shape[:-1]
    flat = jax.tree.map(lambda x, k: x.reshape((-1,) + x.shape[x.ndim - k:]), data,
                        TuningData(*_CORE_RANKS))

    def one(t, p, q, r, mask, gp, gq):
        t, p, q = _lost_padding_frames(t, p, q)
        r_ok = jnp.isfinite(r)
        # masked stand-ins for padded render times: increasing and after the real ones
        r_last = jnp.max(jnp.where(r_ok, r, -jnp.inf))
        r_last = jnp.where(jnp.isfinite(r_last), r_last, 0)
        r = jnp.where(r_ok, r, r_last + 1 + jnp.cumsum(~r_ok))
        sp, sq = _scan_stream(config, t, p, q, r)
        return stream_metrics(r, sp, sq, gp, gq, mask & r_ok)

    terms = jax.vmap(one)(flat.times, flat.positions, flat.quaternions, flat.render_times,
                          flat.render_mask, flat.gt_positions, flat.gt_quaternions)
    return terms.reshape(b + (4,))


#: core rank of each :class:`TuningData` field (the leading axes beyond it are batch axes)
_CORE_RANKS = (1, 2, 2, 1, 1, 2, 2, 1)


def _combine(terms, reference, lam, position_weight, rotation_weight, normalize):
    """Loss from per-recording terms (see the module docs)."""
    dtype = terms.dtype
    ref = reference.astype(dtype)
    avail = jnp.isfinite(ref) & (ref > 0)
    ref_s = jnp.where(avail, ref, 1)
    scaled = terms / ref_s if normalize else terms
    w_p = jnp.where(avail[:, 0] & avail[:, 2], position_weight, 0).astype(dtype)
    w_r = jnp.where(avail[:, 1] & avail[:, 3], rotation_weight, 0).astype(dtype)
    num = w_p * (scaled[:, 0] + lam * scaled[:, 2]) + w_r * (scaled[:, 1] + lam * scaled[:, 3])
    den = w_p + w_r
    used = den > 0
    per_rec = safe_div(num, den)
    return safe_div(jnp.sum(jnp.where(used, per_rec, 0)), jnp.sum(used.astype(dtype)))


def tracker_loss(
    config: TrackerConfig,
    data: TuningData,
    lam: Float[ArrayLike, ""] = 0.0,
    *,
    position_weight: Float[ArrayLike, ""] = 1.0,
    rotation_weight: Float[ArrayLike, ""] = 1.0,
    normalize: bool = True,
) -> Float[Array, ""]:
    """Accuracy + ``lam`` x smoothness of the causal stream, averaged over recordings.

    Differentiable (and ``jit``-able) with respect to the float leaves of ``config`` (and the
    data). See the module docs for the formula; with ``normalize=True`` the reference stream
    scores ``1 + lam``.

    Arguments:
        config: tracker configuration.
        data: recordings from :func:`prepare_recordings` (any leading batch axes, NaN padding
            as in :func:`loss_terms`); the mean runs over all of them.
        lam: weight of the jerk terms (dimensionless when normalised).
        position_weight, rotation_weight: weights of the position and rotation terms.
        normalize: divide each term by the reference stream's value.

    Returns:
        The scalar loss.
    """
    terms = loss_terms(config, data).reshape(-1, 4)
    return _combine(terms, data.reference.reshape(-1, 4), lam, position_weight, rotation_weight,
                    normalize)
