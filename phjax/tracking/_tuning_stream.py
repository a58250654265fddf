""":func:`stream_metrics`, the differentiable ``[E_p, E_r, J_p, J_r]`` of a rendered stream:
what the tuning loss (:mod:`phjax.tracking.tuning`) and its reference scores are made of. The
stream itself is :func:`phjax.track`'s scan (``tracker._scan_stream``).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._jit import jit
from .._misc import safe_div, safe_sqrt
from ..quaternion import quat_conj, quat_geodesic_distance, quat_mul, quat_normalize, quat_to_rotvec


@jit
def stream_metrics(
    render_times: Float[ArrayLike, " M"],
    positions: Float[ArrayLike, "M 3"],
    quaternions: Float[ArrayLike, "M 4"],
    gt_positions: Float[ArrayLike, "M 3"],
    gt_quaternions: Float[ArrayLike, "M 4"],
    mask: Bool[ArrayLike, " M"] | None = None,
) -> Float[Array, "4"]:
    """Differentiable ``[E_p, E_r, J_p, J_r]`` of a rendered stream (JAX twin of
    :mod:`phjax.evaluation.metrics`).

    ``E_p`` position RMSE (m) and ``E_r`` geodesic rotation RMSE (rad) over samples finite in
    both inputs; ``J_p`` RMS position jerk (m/s^3, ``6 x[t_i..t_{i+3}]``) and ``J_r`` RMS angular
    jerk (rad/s^3, three-point second derivative of the midpoint angular velocities
    ``log(q_{i+1} q_i*) / dt``) over windows of four consecutive finite estimate samples, exactly
    as :func:`phjax.evaluation.metrics.rms_jerk_position` / :func:`~phjax.evaluation.metrics.rms_jerk_rotation`.
    Samples with ``mask == False`` are ignored. A term with nothing to evaluate is 0 (values
    and gradients finite everywhere).

    Arguments:
        render_times: strictly increasing render times, s.
        positions, quaternions: the stream (NaN rows allowed).
        gt_positions, gt_quaternions: ground truth at the render times (NaN rows allowed).
        mask: optional samples to use.

    Returns:
        ``(4,)`` array ``[E_p, E_r, J_p, J_r]``.
    """
    t = jnp.asarray(render_times)
    p, q = jnp.asarray(positions), jnp.asarray(quaternions)
    gp, gq = jnp.asarray(gt_positions), jnp.asarray(gt_quaternions)
    dtype = jnp.result_type(p, q, gp, gq)
    t = t.astype(dtype)
    m = jnp.ones(t.shape, bool) if mask is None else jnp.asarray(mask, bool)

    def fin(x):
        return jnp.all(jnp.isfinite(x), axis=-1)

    ok_p, ok_q = m & fin(p), m & fin(q)
    ident = jnp.asarray([1.0, 0, 0, 0], dtype)
    p_s = jnp.where(ok_p[:, None], p, 0)
    q_s = quat_normalize(jnp.where(ok_q[:, None], q, ident))

    def rms(sq, ok):
        okf = ok.astype(dtype)
        return safe_sqrt(safe_div(jnp.sum(jnp.where(ok, sq, 0)), jnp.sum(okf)))

    e_ok = ok_p & fin(gp)
    e_p = rms(jnp.sum((p_s - jnp.where(e_ok[:, None], gp, 0)) ** 2, -1), e_ok)
    r_ok = ok_q & fin(gq)
    gq_s = quat_normalize(jnp.where(r_ok[:, None], gq, ident))
    e_r = rms(quat_geodesic_distance(q_s, gq_s) ** 2, r_ok)

    # third divided difference (the sample times are strictly increasing)
    d1 = (p_s[1:] - p_s[:-1]) / (t[1:] - t[:-1])[:, None]
    d2 = (d1[1:] - d1[:-1]) / (t[2:] - t[:-2])[:, None]
    d3 = (d2[1:] - d2[:-1]) / (t[3:] - t[:-3])[:, None]

    def win(ok):  # windows of four consecutive usable samples
        return ok[:-3] & ok[1:-2] & ok[2:-1] & ok[3:]

    j_p = rms(jnp.sum((6 * d3) ** 2, -1), win(ok_p))

    # angular velocity at interval midpoints, then its second derivative (3-point, non-uniform)
    mid = 0.5 * (t[1:] + t[:-1])
    w = quat_to_rotvec(quat_mul(q_s[1:], quat_conj(q_s[:-1]))) / (t[1:] - t[:-1])[:, None]
    h1, h2 = (mid[1:-1] - mid[:-2])[:, None], (mid[2:] - mid[1:-1])[:, None]
    dd = 2 * (w[:-2] / (h1 * (h1 + h2)) - w[1:-1] / (h1 * h2) + w[2:] / (h2 * (h1 + h2)))
    j_r = rms(jnp.sum(dd**2, -1), win(ok_q))
    return jnp.stack([e_p, e_r, j_p, j_r])
