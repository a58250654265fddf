"""The white-noise residuals of pose samples, shared by the offline estimate
(:func:`phjax.tracking.estimate_measurement_noise`) and the causal stream's online noise floor
(``TrackerConfig.noise_window``, :class:`NoiseMonitor`).

A window of ``k + 1`` consecutive samples gives one residual per channel: the unit-norm
``k``-th divided difference, which removes every polynomial motion of degree ``< k`` and leaves
``N(0, sigma^2)`` of white noise with std ``sigma`` (the procedure is in
:mod:`phjax.tracking.noise`). A robust (MAD) std over many windows estimates ``sigma``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..quaternion import quat_conj, quat_mul, quat_to_rotvec

#: 1 / Phi^-1(3/4): the MAD of N(0, 1)
MAD_TO_STD = 1.482602218505602

#: samples per window of the online monitor (order 3: constant-acceleration motion removed)
WINDOW = 4


def window_residuals(
    t: Float[Array, "*W k1"], p: Float[Array, "*W k1 3"], q: Float[Array, "*W k1 4"]
) -> tuple[Float[Array, "*W 3"], Bool[Array, "*W"], Float[Array, "*W 3"], Bool[Array, "*W"]]:
    """Position and orientation residuals of windows of ``k + 1`` samples.

    Arguments:
        t: times of each window, s (any origin; NaN allowed).
        p: positions, m (NaN = missing).
        q: orientations wxyz (NaN = missing; sign irrelevant).

    Returns:
        ``(res_p, p_ok, res_r, q_ok)``: the unit-norm divided differences of the positions and
        of the world-frame rotation vectors ``log(q_j q_ref^-1)`` (``q_ref`` the window's
        second sample), and whether each window is usable (finite samples, increasing times,
        and for orientation no zero quaternion).
        Residuals of unusable windows are finite placeholders.
    """
    dtype = t.dtype
    k1 = t.shape[-1]
    tw = t - t[..., :1]  # window-relative times (the weights use differences only)
    t_ok = jnp.all(jnp.isfinite(tw), axis=-1) & jnp.all(jnp.diff(tw, axis=-1) > 0, axis=-1)
    tw = jnp.where(t_ok[..., None], tw, jnp.arange(k1, dtype=dtype))  # safe dummy spacing
    diff = tw[..., :, None] - tw[..., None, :]
    eye = jnp.eye(k1, dtype=bool)
    c = 1.0 / jnp.prod(jnp.where(eye, 1.0, diff), axis=-1)  # divided-difference weights
    c = c / jnp.linalg.norm(c, axis=-1, keepdims=True)

    p_ok = t_ok & jnp.all(jnp.isfinite(p), axis=(-2, -1))
    res_p = jnp.einsum("...j,...jc->...c", c, jnp.where(p_ok[..., None, None], p, 0))

    q_ok = t_ok & jnp.all(jnp.isfinite(q), axis=(-2, -1)) & jnp.all(
        jnp.sum(jnp.where(jnp.isfinite(q), q, 0) ** 2, axis=-1) > 0, axis=-1)
    q = jnp.where(q_ok[..., None, None], q, jnp.array([1, 0, 0, 0], dtype))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    rv = quat_to_rotvec(quat_mul(q, quat_conj(q[..., 1:2, :])))  # world frame
    res_r = jnp.einsum("...j,...jc->...c", c, rv)
    return res_p, p_ok, res_r, q_ok


def robust_std(res: Float[Array, "w c"], ok: Bool[Array, " w"]) -> Float[Array, " c"]:
    """Gaussian-consistent MAD per column over the rows where ``ok`` (NaN if none)."""
    r = jnp.where(ok[:, None], res, jnp.nan)
    med = jnp.nanmedian(r, axis=0)
    return MAD_TO_STD * jnp.nanmedian(jnp.abs(r - med), axis=0)


#: residuals beyond this many (estimated) stds are clipped in the online estimate
CLIP = 3.0
#: E[min(Z^2, CLIP^2)] for Z ~ N(0, 1): the online estimate's bias correction
_CLIPPED_SECOND_MOMENT = 0.99500728


class NoiseMonitor(eqx.Module):
    """The causal stream's running measurement-noise estimate (``TrackerConfig.noise_window``).

    Per axis a running mean (the first ``n`` residuals), then an exponential mean over about
    ``n`` residuals, of the squared residuals, each clipped at :data:`CLIP` times the larger
    of the current estimate and the configured std (winsorised, so that a burst of
    unmodelled motion moves it little) and divided by the clipping's bias. O(1) per frame:
    a running median (the offline estimate's) costs a sort per update.

    Fields:
        t, p, q: the last :data:`WINDOW` measurements, oldest first (NaN: lost or not yet seen).
        var_p, var_r: the per-axis variance estimates, m^2 / rad^2 (0 before any residual).
        count_p, count_r: residuals used so far.
    """

    t: Float[Array, " 4"]
    p: Float[Array, "4 3"]
    q: Float[Array, "4 4"]
    var_p: Float[Array, " 3"]
    var_r: Float[Array, " 3"]
    count_p: Int[Array, ""]
    count_r: Int[Array, ""]


def noise_monitor_init(dtype) -> NoiseMonitor:
    """An empty monitor."""
    nan = lambda *s: jnp.full(s, jnp.nan, dtype)  # noqa: E731
    zero = jnp.zeros((), jnp.int32)
    return NoiseMonitor(nan(WINDOW), nan(WINDOW, 3), nan(WINDOW, 4), jnp.zeros(3, dtype),
                        jnp.zeros(3, dtype), zero, zero)


def noise_monitor_push(mon: NoiseMonitor, n: int, t, position, quaternion, pos_std, rot_std
                       ) -> NoiseMonitor:
    """``mon`` after one measurement (NaN parts: lost; a window with one is not used).

    Arguments:
        mon: the monitor.
        n: the number of residuals it averages over (``TrackerConfig.noise_window``).
        t, position, quaternion: the measurement.
        pos_std, rot_std: the configured stds (the clipping's scale before the estimate
            exceeds them). ``phjax.live``'s per-frame ``noise_scale`` arrives here scaled, so
            a doubtful frame's residual is clipped more loosely (one residual of about
            ``n``), and its filter step uses ``max(scaled std, estimate)``.
    """
    shift = lambda buf, x: jnp.concatenate([buf[1:], x[None]])  # noqa: E731
    t_, p_, q_ = shift(mon.t, t), shift(mon.p, position), shift(mon.q, quaternion)
    res_p, p_ok, res_r, q_ok = window_residuals(t_, p_, q_)

    def update(var, count, res, ok, std):
        a = 1.0 / jnp.minimum(count + 1, n).astype(var.dtype)
        scale2 = jnp.maximum(var, jnp.asarray(std, var.dtype) ** 2)
        r2 = jnp.minimum(res**2, CLIP**2 * scale2) / _CLIPPED_SECOND_MOMENT
        return jnp.where(ok, var + a * (r2 - var), var), count + ok.astype(count.dtype)

    vp, cp = update(mon.var_p, mon.count_p, res_p, p_ok, pos_std)
    vr, cr = update(mon.var_r, mon.count_r, res_r, q_ok, rot_std)
    return NoiseMonitor(t_, p_, q_, vp, vr, cp, cr)


def noise_monitor_std(mon: NoiseMonitor, min_count: int, xp=jnp
                      ) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Isotropic position (m) and orientation (rad) noise std (the RMS over the axes); 0 while
    fewer than ``min_count`` residuals were used (the caller takes the larger of this and the
    configured noise, so 0 means "no estimate yet"). ``xp=numpy`` computes it on the host
    (a status display: no JAX dispatch or compilation)."""

    def iso(var, count):
        v = xp.mean(xp.asarray(var))
        est = xp.sqrt(xp.maximum(v, xp.finfo(v.dtype).tiny))  # a finite gradient at 0
        return xp.where(xp.asarray(count) >= min_count, est, 0.0)

    return iso(mon.var_p, mon.count_p), iso(mon.var_r, mon.count_r)
