"""Interacting-multiple-model (IMM) pose filter: position IMM and error-state orientation IMM.

One IMM cycle (Blom and Bar-Shalom) over ``K`` motion models (:mod:`phjax.tracking.models`)
with Markov mode switching:

1. **Mixing.** With prior mode probabilities ``mu_i`` and the transition matrix ``M[i, j]``
   (probability of switching from mode ``i`` to ``j`` during the step): ``cbar_j = sum_i M_ij mu_i``,
   ``omega_ij = M_ij mu_i / cbar_j``, mixed initial conditions
   ``x0_j = sum_i omega_ij x_i``, ``P0_j = sum_i omega_ij (P_i + (x_i - x0_j)(x_i - x0_j)^T)``.
2. **Mode-matched filtering.** Each model predicts ``x0_j`` with its own ``F_j, Q_j`` and updates
   with the measurement (Joseph form), giving the Gaussian log-likelihood ``l_j`` of its
   innovation.
3. **Mode probabilities**, in log space (nothing underflows):
   ``log mu_j <- log cbar_j + l_j - logsumexp_k(log cbar_k + l_k)``, where ``log cbar`` is itself a
   ``logsumexp``. A missing measurement (NaN) is predict only: ``mu <- cbar``.
4. **Combination** (output only): ``x = sum_j mu_j x_j``,
   ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)^T)``.

The switching model is continuous in time: the probability of staying in a mode for ``dt``
seconds is ``exp(-lambda dt)`` (``lambda`` = ``exp(log_switch_rate)``), the rest is spread evenly
over the other modes, so variable frame intervals and dropped frames are handled exactly.

**Position** is a linear IMM (per axis the models of :mod:`phjax.tracking.models`, all embedded in
the state of the highest order, ``H = [I 0]``). **Orientation** is an error-state IMM: each model
``j`` has a nominal orientation ``q_j`` (wxyz), angular velocity ``w_j`` (world frame) and the
covariance ``Pr_j`` of its world-frame error state ``[dtheta, dw]`` (as in
:mod:`phjax.tracking.kalman`). Mixing and combination happen in the tangent space of a reference
orientation ``q_ref`` (the nominal of the most probable mode): model ``i`` becomes the vector
``s_i = [log(q_i q_ref^-1), w_i]`` with covariance transported by
``diag(J_l^-1(delta_i), I)``; after mixing, each model is re-centred at
``q0_j = exp(delta0_j) q_ref`` with its covariance transported back by ``diag(J_l(delta0_j), I)``
(first order, like the error-state reset). Prediction and update are the single-model
error-state Kalman maths of :mod:`phjax.tracking.kalman` with the model's own noise density.
Orientation models must be constant-velocity models.

Position and orientation have their own mode probabilities (a head may turn fast while its
position is still). Everything is jittable, vmappable and differentiable (``jnp.where``
selections only; finite values and gradients when a mode probability underflows to zero).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.nn import logsumexp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._jit import jit
from .._misc import FINITE, POSITIVE, check_number_fields
from ..quaternion import quat_conj, quat_from_rotvec, quat_mul, quat_normalize
from .kalman import (
    _MEASUREMENT_FIELDS,
    _block,
    _canonical_rotvec,
    _clamped_time,
    _extrapolate_derivatives,
    _filter_scan,
    _initial_moments,
    _inject,
    _joseph_update,
    _linear_predict,
    _measurement_validity,
    _rot_matrices,
    _rot_predict,
    _rot_update,
    _select,
    _so3_left_jacobian_inv,
    _spd_inverse,
    _sym,
    _turn,
)
from .models import ConstantAcceleration, ConstantVelocity

__all__ = [
    "IMMConfig",
    "IMMInfo",
    "IMMState",
    "imm_combine",
    "imm_estimate",
    "imm_filter",
    "imm_init",
    "imm_linear_step",
    "imm_mixing",
    "imm_predict_pose",
    "imm_step",
    "imm_uninitialized",
]

_LOG_2PI = math.log(2 * math.pi)


#: Default model sets: three CV models, centre density times 40^-1, 40^0, 40^1 (three decades),
#: tuned on the training half of the development set (``experiments/frontier.py``).
_SPREAD = 40.0


def _default_position_models():
    return tuple(ConstantVelocity.from_q(0.009 * _SPREAD**k) for k in (-1, 0, 1))


def _default_rotation_models():
    return tuple(ConstantVelocity.from_q(0.09 * _SPREAD**k) for k in (-1, 0, 1))


class IMMConfig(eqx.Module):
    """Model set and noise of the IMM pose filter (float fields are differentiable leaves).

    Fields:
        position_models: tuple of :class:`~phjax.tracking.models.ConstantVelocity` /
            :class:`~phjax.tracking.models.ConstantAcceleration` (position, m).
        rotation_models: tuple of :class:`~phjax.tracking.models.ConstantVelocity`
            (orientation, white angular acceleration, rad^2/s^3).
        log_switch_rate: log of the rate ``lambda`` (1/s) of leaving the current mode
            (default ``log 1``: a mode lasts 1 s on average).
        pos_meas_noise: position measurement std per axis, m (default 0.005).
        rot_meas_noise: orientation measurement std per world axis, rad (default 1 degree).
        init_pos_vel_std, init_pos_acc_std, init_rot_vel_std: initial velocity (m/s),
            acceleration (m/s^2) and angular velocity (rad/s) std.

    Defaults: three CV models per part, densities 2.25e-4, 9e-3, 0.36 m^2/s^3 (position) and
    2.25e-3, 0.09, 3.6 rad^2/s^3 (orientation), switch rate 1/s: the grid point (centre, spread,
    rate) with the lowest extrapolation RMSE on the training half of the development set
    (``experiments/frontier.py``).
    """

    position_models: tuple = eqx.field(default_factory=_default_position_models)
    rotation_models: tuple = eqx.field(default_factory=_default_rotation_models)
    log_switch_rate: float = 0.0
    pos_meas_noise: float = 0.005
    rot_meas_noise: float = math.radians(1.0)
    init_pos_vel_std: float = 0.5
    init_pos_acc_std: float = 3.0
    init_rot_vel_std: float = 1.0

    def __post_init__(self):
        if len(self.position_models) < 1 or len(self.rotation_models) < 1:
            raise ValueError("IMMConfig needs at least one position and one rotation model")
        for m in self.position_models:
            if not isinstance(m, (ConstantVelocity, ConstantAcceleration)):
                raise TypeError(f"position models must be CV / CA models, got {type(m).__name__}")
        for m in self.rotation_models:
            if not isinstance(m, ConstantVelocity):
                raise TypeError("rotation models must be ConstantVelocity models, got "
                                 f"{type(m).__name__}")
        check_number_fields(self, [("log_switch_rate", *FINITE)] + [
            (name, *POSITIVE) for name in _MEASUREMENT_FIELDS])

    @property
    def order(self) -> int:
        """Derivatives in the common position state (2: ``[p, v]``, 3: ``[p, v, a]``)."""
        return max(m.order for m in self.position_models)


class IMMState(eqx.Module):
    """State of the IMM pose filter (a PyTree of arrays).

    Fields:
        t: time of the estimate, s.
        pos_log_mu: (K,) log mode probabilities of the position models.
        x: (K, 3 order) per-model position states ``[p, v, (a)]``.
        P: (K, 3 order, 3 order) their covariances.
        rot_log_mu: (Kr,) log mode probabilities of the orientation models.
        q: (Kr, 4) per-model nominal orientations (wxyz).
        w: (Kr, 3) per-model angular velocities, rad/s, world frame.
        Pr: (Kr, 6, 6) per-model error-state covariances.
        initialized: whether the state holds an estimate.
        last_update: time of the last accepted measurement.

    Use :func:`imm_estimate` for the combined (mixed) estimate; ``mu`` / ``rot_mu`` are the mode
    probabilities.
    """

    t: Float[Array, ""]
    pos_log_mu: Float[Array, " K"]
    x: Float[Array, "K nx"]
    P: Float[Array, "K nx nx"]
    rot_log_mu: Float[Array, " Kr"]
    q: Float[Array, "Kr 4"]
    w: Float[Array, "Kr 3"]
    Pr: Float[Array, "Kr 6 6"]
    initialized: Bool[Array, ""]
    last_update: Float[Array, ""]

    @property
    def mu(self) -> Float[Array, " K"]:
        """Position mode probabilities."""
        return jnp.exp(self.pos_log_mu)

    @property
    def rot_mu(self) -> Float[Array, " Kr"]:
        """Orientation mode probabilities."""
        return jnp.exp(self.rot_log_mu)


class IMMInfo(eqx.Module):
    """Diagnostics of one :func:`imm_step` (zeros where a part is missing or on initialisation).

    Fields:
        pos_innovation, rot_innovation: (3,) mixture innovations
            ``sum_j cbar_j y_j`` (m; rotation vector, rad).
        pos_innovation_cov, rot_innovation_cov: (3, 3) mixture innovation covariances
            ``sum_j cbar_j (S_j + (y_j - y)(y_j - y)^T)``.
        pos_nis, rot_nis: normalised innovation squared of the mixture (about chi-square, 3 dof).
        pos_loglik, rot_loglik: per-model innovation log-likelihoods.
        pos_valid, rot_valid, pos_used, rot_used, initialized_now: as in
            :class:`phjax.KalmanInfo` (no gating).
    """

    pos_innovation: Float[Array, "3"]
    rot_innovation: Float[Array, "3"]
    pos_innovation_cov: Float[Array, "3 3"]
    rot_innovation_cov: Float[Array, "3 3"]
    pos_nis: Float[Array, ""]
    rot_nis: Float[Array, ""]
    pos_loglik: Float[Array, " K"]
    rot_loglik: Float[Array, " Kr"]
    pos_valid: Bool[Array, ""]
    rot_valid: Bool[Array, ""]
    pos_used: Bool[Array, ""]
    rot_used: Bool[Array, ""]
    initialized_now: Bool[Array, ""]


# ---------------------------------------------------------------------------- generic IMM maths


def _log_transition(log_rate, dt, k: int, dtype):
    """``log M`` (k, k) of the continuous-time switching model over ``dt`` (see module docs)."""
    if k == 1:
        return jnp.zeros((1, 1), dtype)
    x = jnp.exp(jnp.asarray(log_rate, dtype)) * dt
    leave = -jnp.expm1(-x)
    tiny = jnp.finfo(dtype).tiny
    log_leave = jnp.log(jnp.maximum(leave, tiny)) - math.log(k - 1)
    return jnp.where(jnp.eye(k, dtype=bool), -x, log_leave)


def imm_mixing(
    log_mu: Float[ArrayLike, " K"], log_transition: Float[ArrayLike, "K K"]
) -> tuple[Float[Array, " K"], Float[Array, "K K"]]:
    """Predicted mode probabilities and mixing weights, in log space.

    Arguments:
        log_mu: (K,) log mode probabilities (``-inf`` allowed for all but one).
        log_transition: (K, K) ``log M``, ``M[i, j]`` = P(mode j at the end | mode i at the start).

    Returns:
        ``(log_cbar (K,), omega (K, K))`` with ``omega[i, j] = M_ij mu_i / cbar_j`` (columns sum
        to one).
    """
    a = jnp.asarray(log_transition) + jnp.asarray(log_mu)[:, None]
    log_cbar = logsumexp(a, axis=0)
    return log_cbar, jnp.exp(a - log_cbar[None, :])


def _mix(omega, xs, ps):
    """Mixed initial conditions ``x0_j, P0_j`` (weights ``omega[:, j]``)."""
    x0 = omega.T @ xs
    d = xs[None, :, :] - x0[:, None, :]  # (j, i, n)
    p0 = jnp.einsum("ij,iab->jab", omega, ps) + jnp.einsum("ij,jia,jib->jab", omega, d, d)
    return x0, _sym(p0)


def imm_combine(
    log_mu: Float[ArrayLike, " K"], xs: Float[ArrayLike, "K n"], ps: Float[ArrayLike, "K n n"]
) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Combined estimate ``x = sum mu_j x_j``, ``P = sum mu_j (P_j + d_j d_j^T)``."""
    mu = jnp.exp(jnp.asarray(log_mu))
    x0, p0 = _mix(mu[:, None], jnp.asarray(xs), jnp.asarray(ps))
    return x0[0], p0[0]


def _loglik(nis, log_det, m: int):
    """Gaussian log-likelihood of an ``m``-dimensional innovation from its NIS and log det S."""
    return -0.5 * (nis + log_det + m * _LOG_2PI)


def _kf_update(x, p, h, r, y):
    """The Kalman update and the model's Gaussian log-likelihood of ``y``; returns
    ``(x, P, S, nis, loglik)``."""
    x_new, p_new, s, nis, log_det = _joseph_update(x, p, h, r, y)
    return x_new, p_new, s, nis, _loglik(nis, log_det, y.shape[0])


def _mixture_innovation(log_cbar, ys, ss):
    """Mixture innovation, its covariance and NIS from per-model innovations ``ys``, ``S``."""
    y, s = imm_combine(log_cbar, ys, ss)
    s_inv, _ = _spd_inverse(s)
    return y, s, y @ s_inv @ y


def _mode_update(log_cbar, loglik, valid):
    """Posterior log mode probabilities. A measurement no model can explain (every likelihood
    -inf or NaN: a garbage pose of 1e18 m in float32, or an innovation covariance that rounding
    left indefinite) leaves the predicted probabilities as they are: normalising it gave
    -inf - (-inf) = NaN, and the probabilities stayed NaN for good."""
    ll = jnp.where(valid, loglik, 0)
    ll = jnp.where(jnp.isnan(ll), -jnp.inf, ll)
    a = log_cbar + ll
    norm = logsumexp(a)
    ok = jnp.isfinite(norm)
    return jnp.where(ok, a - jnp.where(ok, norm, 0), log_cbar), jnp.where(ok, ll, 0)


def imm_linear_step(
    log_mu: Float[ArrayLike, " K"],
    xs: Float[ArrayLike, "K n"],
    ps: Float[ArrayLike, "K n n"],
    log_transition: Float[ArrayLike, "K K"],
    fs: Float[ArrayLike, "K n n"],
    qs: Float[ArrayLike, "K n n"],
    h: Float[ArrayLike, "m n"],
    r: Float[ArrayLike, "m m"],
    z: Float[ArrayLike, " m"],
):
    """One linear IMM cycle: mixing, per-model predict and update, mode probabilities.

    Equivalent to filterpy's ``IMMEstimator.predict()`` followed by ``update(z)``.

    Arguments:
        log_mu: (K,) log mode probabilities before the step.
        xs, ps: (K, n) per-model states and (K, n, n) covariances.
        log_transition: (K, K) log switching matrix of the step.
        fs, qs: (K, n, n) per-model transitions and process noises.
        h, r: measurement matrix (m, n) and noise (m, m), shared.
        z: (m,) measurement; any NaN = predict only.

    Returns:
        ``(log_mu, xs, ps, info)`` with ``info = (log_cbar, loglik (K,), y, S, nis)``
        (mixture innovation, covariance and NIS; zero log-likelihoods when ``z`` is missing).
    """
    xs, ps, z = jnp.asarray(xs), jnp.asarray(ps), jnp.asarray(z)
    h, r = jnp.asarray(h, xs.dtype), jnp.asarray(r, xs.dtype)
    valid = jnp.all(jnp.isfinite(z))
    log_cbar, omega = imm_mixing(log_mu, log_transition)
    x0, p0 = _mix(omega, xs, ps)
    xp, pp = jax.vmap(_linear_predict)(x0, p0, fs, qs)
    y = jnp.where(valid, z, 0)[None, :] - xp @ h.T
    xu, pu, s, _, ll = jax.vmap(_kf_update, (0, 0, None, None, 0))(xp, pp, h, r, y)
    log_mu_new, ll = _mode_update(log_cbar, ll, valid)
    xs_new = jnp.where(valid, xu, xp)
    ps_new = jnp.where(valid, pu, pp)
    ym, sm, nis = _mixture_innovation(log_cbar, y, s)
    return log_mu_new, xs_new, ps_new, (log_cbar, ll, ym, sm, nis)


# ------------------------------------------------------------------------------ pose filter


def _stack_position_models(config: IMMConfig, dt):
    n = config.order
    mats = [m.position_matrices(dt, n) for m in config.position_models]
    return jnp.stack([f for f, _ in mats]), jnp.stack([q for _, q in mats])


def _rot_qs(config: IMMConfig, dtype):
    return jnp.stack([m.q.astype(dtype) for m in config.rotation_models])


def imm_init(
    config: IMMConfig,
    t: Float[ArrayLike, ""],
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> IMMState:
    """Initialise every model from one pose measurement (uniform mode probabilities).

    Arguments:
        config: model set.
        t: measurement time, s.
        position: (3,) position, m.
        quaternion: (4,) orientation wxyz (any sign / norm).

    Returns:
        The state at the measured pose with zero velocities (``initialized == False`` if either
        part is missing; then identity orientation and zero position).
    """
    t, x, qm, var, var_r, valid = _initial_moments(config, t, position, quaternion)
    dtype, n = x.dtype, config.order
    k, kr = len(config.position_models), len(config.rotation_models)
    return IMMState(
        t=t,
        pos_log_mu=jnp.full(k, -math.log(k), dtype),
        x=jnp.broadcast_to(x, (k, 3 * n)),
        P=jnp.broadcast_to(jnp.diag(var), (k, 3 * n, 3 * n)),
        rot_log_mu=jnp.full(kr, -math.log(kr), dtype),
        q=jnp.broadcast_to(qm, (kr, 4)),
        w=jnp.zeros((kr, 3), dtype),
        Pr=jnp.broadcast_to(jnp.diag(var_r), (kr, 6, 6)),
        initialized=valid,
        last_update=t,
    )


def imm_uninitialized(config: IMMConfig, t: Float[ArrayLike, ""], dtype=None) -> IMMState:
    """An uninitialised state at ``t``; the first valid measurement initialises it."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    nan = jnp.asarray(jnp.nan, dtype)
    return imm_init(config, t, jnp.full(3, nan), jnp.full(4, nan))


def _tangent(q, ref, cov=None):
    """Rotation vectors of ``q`` (K, 4) around ``ref`` and, optionally, error-state covariances
    (K, 6, 6) transported into that tangent space."""
    delta = _canonical_rotvec(quat_mul(q, quat_conj(ref)[None, :]))
    if cov is None:
        return delta, None
    z3 = jnp.zeros((3, 3), q.dtype)
    eye = jnp.eye(3, dtype=q.dtype)
    t = jax.vmap(lambda d: _block(_so3_left_jacobian_inv(d), z3, z3, eye))(delta)
    return delta, jnp.einsum("kab,kbc,kdc->kad", t, cov, t)


def _recentre(delta, ref, cov):
    """Orientations ``exp(delta) ref`` and covariances transported back to their error states
    (the error-state injection of :mod:`phjax.tracking.kalman`, per model)."""
    return jax.vmap(_inject, (0, None, 0))(delta, ref, cov)


def _reference(log_mu, q):
    return q[jnp.argmax(log_mu)]


def _rot_step(config, state, dt, q_meas, rot_valid, r_rot):
    """Error-state IMM cycle of the orientation (see module docs)."""
    dtype = state.q.dtype
    kr = state.q.shape[0]
    log_cbar, omega = imm_mixing(state.rot_log_mu,
                                 _log_transition(config.log_switch_rate, dt, kr, dtype))
    ref = _reference(state.rot_log_mu, state.q)
    delta, cov = _tangent(state.q, ref, state.Pr)
    s0, p0 = _mix(omega, jnp.concatenate([delta, state.w], -1), cov)
    q0, p0 = _recentre(s0[:, :3], ref, p0)
    w0 = s0[:, 3:]
    # per model: kalman.py's error-state prediction (the model's density) and update
    fr, qr = jax.vmap(_rot_matrices, (0, 0, None))(_rot_qs(config, dtype), w0, dt)
    qp, pp = jax.vmap(_rot_predict, (0, 0, 0, 0, 0, None))(q0, w0, p0, fr, qr, dt)
    qu, wu, pu, y, s, nis_k, log_det = jax.vmap(_rot_update, (0, 0, 0, None, None, None))(
        qp, w0, pp, q_meas, rot_valid, r_rot)
    ll = _loglik(nis_k, log_det, y.shape[-1])
    log_mu, ll = _mode_update(log_cbar, ll, rot_valid)
    ym, sm, nis = _mixture_innovation(log_cbar, y, s)
    q_new = jnp.where(rot_valid, qu, qp)
    w_new = jnp.where(rot_valid, wu, w0)
    pr_new = jnp.where(rot_valid, pu, pp)
    return log_mu, q_new, w_new, pr_new, (ll, ym, sm, nis)


def imm_step(
    config: IMMConfig,
    state: IMMState,
    t: Float[ArrayLike, ""],
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> tuple[IMMState, IMMInfo]:
    """Predict to ``t`` (``dt`` clamped at 0) and update with a pose measured at ``t``.

    Arguments:
        config: model set.
        state: current state (an uninitialised state is initialised by the first measurement
            with both parts valid).
        t: measurement time, s.
        position: (3,) position, m; any NaN: the position part only predicts.
        quaternion: (4,) orientation wxyz (any sign); NaN or zero norm: the orientation part
            only predicts.

    Returns:
        ``(state, info)``.
    """
    t_new, dt = _clamped_time(state, t)
    dtype = state.x.dtype
    p_meas, q_meas, pos_valid, rot_valid = _measurement_validity(position, quaternion, dtype)
    # position: linear IMM
    k = state.x.shape[0]
    fs, qs = _stack_position_models(config, dt)
    h = jnp.eye(3, state.x.shape[1], dtype=dtype)
    r_pos = jnp.asarray(config.pos_meas_noise, dtype) ** 2 * jnp.eye(3, dtype=dtype)
    z = jnp.where(pos_valid, p_meas, jnp.nan)
    log_mu, xs, ps, (_, ll_p, y_p, s_p, nis_p) = imm_linear_step(
        state.pos_log_mu, state.x, state.P,
        _log_transition(config.log_switch_rate, dt, k, dtype), fs, qs, h, r_pos, z)
    # orientation: error-state IMM
    r_rot = jnp.asarray(config.rot_meas_noise, dtype) ** 2 * jnp.eye(3, dtype=dtype)
    rot_log_mu, q, w, pr, (ll_r, y_r, s_r, nis_r) = _rot_step(
        config, state, dt, q_meas, rot_valid, r_rot)
    updated = IMMState(t_new, log_mu, xs, ps, rot_log_mu, q, w, pr, state.initialized,
                       jnp.where(pos_valid | rot_valid, t_new, state.last_update))
    init = imm_init(config, t_new, p_meas, q_meas)
    init = eqx.tree_at(lambda s: s.last_update, init,
                       jnp.where(init.initialized, t_new, state.last_update))
    was = state.initialized
    new = _select(was, updated, init)
    init_now = ~was & init.initialized
    z3 = jnp.zeros(3, dtype)
    zero = jnp.zeros((), dtype)
    info = IMMInfo(
        pos_innovation=jnp.where(was & pos_valid, y_p, z3),
        rot_innovation=jnp.where(was & rot_valid, y_r, z3),
        pos_innovation_cov=jnp.where(was, s_p, r_pos),
        rot_innovation_cov=jnp.where(was, s_r, r_rot),
        pos_nis=jnp.where(was & pos_valid, nis_p, zero),
        rot_nis=jnp.where(was & rot_valid, nis_r, zero),
        pos_loglik=jnp.where(was, ll_p, 0),
        rot_loglik=jnp.where(was, ll_r, 0),
        pos_valid=pos_valid,
        rot_valid=rot_valid,
        pos_used=jnp.where(was, pos_valid, init_now),
        rot_used=jnp.where(was, rot_valid, init_now),
        initialized_now=init_now,
    )
    return new, info


@jit
def imm_filter(
    config: IMMConfig,
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    quaternions: Float[ArrayLike, "n 4"],
    initial_state: IMMState | None = None,
) -> tuple[IMMState, IMMInfo]:
    """Filter a measurement sequence (``lax.scan`` over :func:`imm_step`).

    Arguments:
        config: model set.
        times: (n,) measurement times, s (non-decreasing).
        positions: (n, 3) positions (NaN = missing).
        quaternions: (n, 4) orientations wxyz (NaN = missing).
        initial_state: default: uninitialised at ``times[0]``.

    Returns:
        ``(states, infos)`` stacked over the measurements (posterior after each).
    """
    return _filter_scan("imm_filter", imm_step, imm_uninitialized, config, times, positions,
                        quaternions, initial_state)


class IMMEstimate(eqx.Module):
    """Combined (mode-probability-weighted) estimate of an :class:`IMMState`.

    Fields:
        x, P: combined position state ``[p, v, (a)]`` and covariance.
        q: combined orientation (wxyz), w: angular velocity (world), Pr: (6, 6) covariance of
            the error state ``[dtheta, dw]`` around ``q``.
    """

    x: Float[Array, " nx"]
    P: Float[Array, "nx nx"]
    q: Float[Array, "4"]
    w: Float[Array, "3"]
    Pr: Float[Array, "6 6"]


def imm_estimate(state: IMMState) -> IMMEstimate:
    """The combined estimate (position: linear mixture; orientation: mixture in the tangent
    space of the most probable model's orientation, re-centred)."""
    x, p = imm_combine(state.pos_log_mu, state.x, state.P)
    ref = _reference(state.rot_log_mu, state.q)
    delta, cov = _tangent(state.q, ref, state.Pr)
    s, pr = imm_combine(state.rot_log_mu, jnp.concatenate([delta, state.w], -1), cov)
    q, pr = _recentre(s[None, :3], ref, pr[None])
    return IMMEstimate(x, p, q[0], s[3:], pr[0])


def imm_predict_pose(
    config: IMMConfig, state: IMMState, t: Float[ArrayLike, ""]
) -> tuple[Float[Array, "3"], Float[Array, "4"], Float[Array, "3"], Float[Array, "3"]]:
    """Combined mean pose predicted to ``t`` (``dt`` clamped at 0): each model's mean is
    extrapolated with its own transition and the means are mixed with the current mode
    probabilities (orientation in the tangent space, as :func:`imm_estimate`).

    Returns:
        ``(position, quaternion, velocity, angular_velocity)``.
    """
    _, dt = _clamped_time(state, t)
    # the position prediction is linear: mix the models' derivatives, then extrapolate once (no
    # (K, n, n) transitions); a CV model in a CA state ignores its acceleration entry
    mu = jnp.exp(state.pos_log_mu)
    ca = jnp.asarray([m.order == 3 for m in config.position_models], mu.dtype)
    weights = [mu, mu, mu * ca][:config.order]
    p, v = _extrapolate_derivatives(
        [w @ state.x[:, 3 * i : 3 * i + 3] for i, w in enumerate(weights)], dt)
    qs = quat_normalize(quat_mul(quat_from_rotvec(_turn(state.w, dt)), state.q))
    ref = _reference(state.rot_log_mu, qs)
    delta, _ = _tangent(qs, ref)
    mur = jnp.exp(state.rot_log_mu)
    q = quat_normalize(quat_mul(quat_from_rotvec(mur @ delta), ref))
    return p, q, v, mur @ state.w
