"""Pose Kalman filter with variable time steps (position: linear KF, orientation: error-state KF).

The state has two independent parts, filtered with separate covariances:

* **Position** ``x``: a linear Kalman filter with a continuous white-noise model of the highest
  derivative, per axis. ``model="cv"``: ``x = [p, v]`` (6,), white acceleration noise of spectral
  density ``q`` [m^2/s^3]. ``model="ca"``: ``x = [p, v, a]`` (9,), white jerk noise [m^2/s^5].
  The layout is by derivative (``[px, py, pz, vx, vy, vz, ...]``), so ``F = F1 (x) I3`` and
  ``Q = q Q1 (x) I3`` with the 1-D matrices ``F1[i, j] = dt^(j-i) / (j-i)!`` and
  ``Q1[i, j] = dt^(2n-1-i-j) / ((2n-1-i-j) (n-1-i)! (n-1-j)!)`` (``n`` = 2 or 3), i.e. the familiar
  ``[[dt^3/3, dt^2/2], [dt^2/2, dt]]`` for CV and ``[[dt^5/20, dt^4/8, dt^3/6], ...]`` for CA.
* **Orientation** ``(q, w)``: nominal unit quaternion ``q`` (wxyz) and angular velocity ``w``
  (rad/s, **world frame**), propagated as ``q(t + dt) = exp(w dt) q(t)`` (``exp`` = rotation
  vector to quaternion). The 6-D error state ``[dtheta, dw]`` is a world-frame (left)
  perturbation ``q_true = exp(dtheta) q``, ``w_true = w + dw`` with covariance ``Pr``.

Orientation error propagation (first order, exact for constant nominal ``w`` over the step).
From ``exp(dtheta') = exp((w + dw) dt) exp(dtheta) exp(-w dt)``, with ``phi = w dt``,
``exp(phi) exp(a) exp(-phi) = exp(R(phi) a)`` and ``exp(phi + b) ~ exp(J_l(phi) b) exp(phi)``::

    dtheta' = R(phi) dtheta + J_l(phi) dt dw,        dw' = dw + noise
    F = [[R(phi), J_l(phi) dt], [0, I]] = expm(A dt),  A = [[[w]x, I], [0, 0]]

with ``R(phi) = I + sin(t)/t [phi]x + (1-cos t)/t^2 [phi]x^2`` and the left Jacobian
``J_l(phi) = I + (1-cos t)/t^2 [phi]x + (t-sin t)/t^3 [phi]x^2`` (``t = |phi|``). The process
noise is white angular acceleration of spectral density ``q_r`` [rad^2/s^3]; its discrete
covariance ``Q_r = int_0^dt expm(A s) G q_r G^T expm(A s)^T ds`` (``G = [0; I]``) is evaluated in
closed form for the same linearised model::

    Q_tt = q_r (dt^3/3 I + d2 dt^3 [phi]x^2)
    Q_tw = q_r (dt^2/2 I + d1 dt^2 [phi]x^2 + c2 dt^2 [phi]x),     Q_ww = q_r dt I

with ``c2 = (t - sin t)/t^3``, ``d1 = (1/2 - (1-cos t)/t^2)/t^2``, ``d2 = (1/3 - 2 c2)/t^2``
(Taylor series near ``t = 0``, where it reduces to the usual ``[[dt^3/3, dt^2/2], [dt^2/2, dt]]``).

Orientation update: the measurement is ``q_meas = exp(n) q_true`` with world-frame noise
``n ~ N(0, sigma^2 I)``; the innovation is the shortest-arc rotation vector of
``q_meas q^-1`` (identical for ``q_meas`` and ``-q_meas``, with a deterministic tie-break at exactly
180 degrees) and ``H = [I 0]``. After the update the error mean ``dtheta`` is injected
(``q <- exp(dtheta) q``, renormalised; ``w <- w + dw``) and the covariance is reset with the
Jacobian of ``dtheta_new = log(exp(dtheta + e) exp(-dtheta)) ~ J_l(dtheta) e``, i.e.
``Pr <- G Pr G^T`` with ``G = diag(J_l(dtheta), I)``. Covariance updates use the Joseph form and
are symmetrised.

Conventions and behaviour:

* ``dt = t - state.t`` is clamped to ``[0, MAX_PREDICT_STEP]`` (60 s): predicting to an
  earlier (or NaN) time is a no-op and the state time never decreases (a late measurement is
  therefore applied at ``state.t``); a longer gap is modelled as 60 s of motion. The orientation
  error covariance has ceilings (:data:`ROT_STD_CEILING`: about pi rad, 4 pi rad/s; past the
  angle's the orientation becomes unknown and uncorrelated with the rate).
* Missing data: a position with any NaN (or inf, or a component beyond ``max^(1/4)`` of the
  dtype: 1.4e9 m in float32) skips the position update; a quaternion with any
  NaN/inf or zero norm skips the orientation update. Selection uses ``jnp.where`` only, so every
  function is jittable, vmappable and has finite gradients (w.r.t. the noise parameters) with
  missing data.
* An uninitialised state (``initialized == False``) is only moved in time by
  :func:`kalman_predict`; :func:`kalman_update` initialises it from the first measurement whose
  position **and** quaternion are both valid.
* Library code is dtype-generic: the pose dtype is that of the measurements passed to
  :func:`kalman_init`; the time dtype is that of ``t`` (use relative times in float32).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float

from .._jit import jit
from .._misc import POSITIVE, check_number_fields, dot_last, filter_scan
from ..quaternion import quat_conj, quat_from_rotvec, quat_mul, quat_normalize, quat_to_rotvec

__all__ = [
    "KalmanConfig",
    "KalmanState",
    "KalmanInfo",
    "kalman_init",
    "kalman_uninitialized",
    "kalman_predict",
    "kalman_update",
    "kalman_step",
    "kalman_filter",
    "rts_smooth",
    "predict_pose",
]

_ORDER = {"cv": 2, "ca": 3}
# Defaults for the highest-derivative spectral density, see the KalmanConfig docstring.
_DEFAULT_POS_Q = {"cv": 0.03, "ca": 20.0}


#: the measurement-noise and initial-uncertainty fields (all > 0) that :class:`KalmanConfig`
#: and :class:`phjax.tracking.imm.IMMConfig` share; KalmanConfig adds its process noises
_MEASUREMENT_FIELDS = ("pos_meas_noise", "rot_meas_noise", "init_pos_vel_std",
                       "init_pos_acc_std", "init_rot_vel_std")


class KalmanConfig(eqx.Module):
    """Noise model of the pose filter (float fields are differentiable PyTree leaves).

    The spectral densities are heuristics for a seated/standing user's head, from
    ``q ~ sigma^2 tau`` (RMS of the driving derivative ``sigma``, correlation time ``tau``);
    tune them on recorded data.

    Fields:
        model: ``"cv"`` (constant velocity) or ``"ca"`` (constant acceleration) position model.
            Static.
        pos_process_noise: spectral density of the white highest derivative. CV: acceleration,
            m^2/s^3, default 0.03 (lowest prediction RMSE on the development set with a 30 Hz,
            5 mm sensor: ``experiments/tune_baselines.py``). CA: jerk, m^2/s^5, default 20.0
            (RMS jerk ~9 m/s^3 over ~0.25 s). ``None`` picks the default of ``model``.
        pos_meas_noise: position measurement std per axis, m (default 0.005).
        rot_process_noise: angular-acceleration spectral density, rad^2/s^3 (default 0.3,
            the single-model tracker's; tuned like ``pos_process_noise`` with a 1 degree sensor
            before render samples at a frame's instant were made to see that frame: on that
            grid the Kalman CV extrapolation baseline does best with 1.0,
            :data:`phjax.tracking.baselines.TUNED`).
        rot_meas_noise: orientation measurement std per (world) axis, rad (default 1 degree).
        init_pos_vel_std: initial velocity std, m/s (default 0.5).
        init_pos_acc_std: initial acceleration std (CA only), m/s^2 (default 3.0).
        init_rot_vel_std: initial angular-velocity std, rad/s (default 1.0).
        gate_nis: if set, a position or orientation measurement whose normalised innovation
            squared (chi-square with 3 dof under the model) exceeds it is rejected, e.g. 16.27
            (p = 0.001). Static; default ``None`` (no gating).
        gate_reset: with a gate, a part (position or orientation) whose valid measurements
            have all been rejected for longer than this, s, is re-initialised from the next
            valid one (``KalmanState.part_updates``): a filter that diverged (e.g. initialised
            from one stray first pose, then coasting on a wrong velocity) or a real jump in
            the input (a tracker re-centred or re-acquiring the face elsewhere) is taken up
            again instead of being rejected for ever. Static; default 0.25.
    """

    model: str = eqx.field(static=True, default="cv")
    pos_process_noise: float | None = None
    pos_meas_noise: float = 0.005
    rot_process_noise: float = 0.3
    rot_meas_noise: float = math.radians(1.0)
    init_pos_vel_std: float = 0.5
    init_pos_acc_std: float = 3.0
    init_rot_vel_std: float = 1.0
    gate_nis: float | None = eqx.field(static=True, default=None)
    gate_reset: float = eqx.field(static=True, default=0.25)

    def __post_init__(self):
        if self.model not in _ORDER:
            raise ValueError(f"KalmanConfig.model must be 'cv' or 'ca', got {self.model!r}")
        if self.gate_nis is not None and not float(self.gate_nis) > 0:
            raise ValueError(f"KalmanConfig.gate_nis must be positive or None, got {self.gate_nis}")
        if not float(self.gate_reset) >= 0:
            raise ValueError(f"KalmanConfig.gate_reset must be >= 0 s, got {self.gate_reset}")
        if self.pos_process_noise is None:
            self.pos_process_noise = _DEFAULT_POS_Q[self.model]
        # (NaN, 0 or negative noise gave NaN poses, silently)
        check_number_fields(self, [(name, *POSITIVE) for name in (
            "pos_process_noise", "rot_process_noise", *_MEASUREMENT_FIELDS)])

    @property
    def order(self) -> int:
        """Number of position derivatives in the state (2 for CV, 3 for CA)."""
        return _ORDER[self.model]


class KalmanState(eqx.Module):
    """Filter state (a PyTree of arrays; stack/vmap freely).

    Fields:
        t: time of the estimate, s.
        x: position state ``[p, v]`` (CV, (6,)) or ``[p, v, a]`` (CA, (9,)).
        P: covariance of ``x``.
        q: nominal orientation, unit quaternion wxyz.
        w: angular velocity, rad/s, world frame (``q(t + dt) = exp(w dt) q(t)``).
        Pr: (6, 6) covariance of the error state ``[dtheta, dw]``
            (``q_true = exp(dtheta) q``, ``w_true = w + dw``).
        initialized: whether the state holds an estimate.
        last_update: time of the last accepted measurement (creation time while uninitialised).
        part_updates: (2,) the same per part: position, orientation (the gate's reset,
            :attr:`KalmanConfig.gate_reset`).
    """

    t: Float[Array, ""]
    x: Float[Array, " nx"]
    P: Float[Array, "nx nx"]
    q: Float[Array, "4"]
    w: Float[Array, "3"]
    Pr: Float[Array, "6 6"]
    initialized: Bool[Array, ""]
    last_update: Float[Array, ""]
    part_updates: Float[Array, "2"]


class KalmanInfo(eqx.Module):
    """Diagnostics of one :func:`kalman_update`.

    Innovations, their covariances and NIS are those of the prior state. Innovations and NIS
    are zero when the part is missing or when the call initialised the filter
    (``initialized_now``); the innovation covariance is then the prior's ``S`` (missing part)
    or the measurement noise ``R`` (initialisation). All are reported (not zero) for
    measurements rejected by the gate.

    Fields:
        pos_innovation, rot_innovation: (3,) innovations (m; rotation vector, rad).
        pos_innovation_cov, rot_innovation_cov: (3, 3) innovation covariances ``S``.
        pos_nis, rot_nis: ``y^T S^-1 y`` (chi-square, 3 dof, under the model).
        pos_valid, rot_valid: the measurement part was present (finite).
        pos_used, rot_used: the part was applied (valid and passed the gate, or initialised).
        initialized_now: this call initialised the filter.
    """

    pos_innovation: Float[Array, "3"]
    rot_innovation: Float[Array, "3"]
    pos_innovation_cov: Float[Array, "3 3"]
    rot_innovation_cov: Float[Array, "3 3"]
    pos_nis: Float[Array, ""]
    rot_nis: Float[Array, ""]
    pos_valid: Bool[Array, ""]
    rot_valid: Bool[Array, ""]
    pos_used: Bool[Array, ""]
    rot_used: Bool[Array, ""]
    initialized_now: Bool[Array, ""]


# ----------------------------------------------------------------------------------------------
# helpers


def _float_dtype(*xs) -> jnp.dtype:
    dt = jnp.result_type(*xs)
    return dt if jnp.issubdtype(dt, jnp.inexact) else jnp.result_type(float)


def _select(pred, a, b):
    """``where(pred, a, b)`` leaf-wise over two PyTrees of the same structure."""
    return jax.tree.map(lambda u, v: jnp.where(pred, u, v), a, b)


def _sym(p):
    return 0.5 * (p + jnp.swapaxes(p, -1, -2))


def _hat(v):
    z = jnp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    m = jnp.stack([z, -w, y, w, z, -x, -y, x, z], axis=-1)
    return m.reshape(v.shape[:-1] + (3, 3))


def _block(a, b, c, d):
    return jnp.concatenate([jnp.concatenate([a, b], -1), jnp.concatenate([c, d], -1)], -2)


def _series_coeffs(start: int, scale: float = 1.0, terms: int = 10) -> np.ndarray:
    # scale * sum_k (-1)^k x^k / (2k + start)!  in x = theta^2, highest power first (polyval);
    # 10 terms: truncation error < 1/21! for x < 1
    return np.array([scale * (-1) ** k / math.factorial(2 * k + start) for k in range(terms)][::-1])


_C0, _C1, _C2 = _series_coeffs(1), _series_coeffs(2), _series_coeffs(3)
_D1, _D2 = _series_coeffs(4), _series_coeffs(5, scale=2.0)


def _horner_const(coeffs, x):
    """Polynomial with constant coefficients (highest power first) by Horner's rule, unrolled
    (``jnp.polyval`` runs a loop: several kernels on XLA:CPU)."""
    acc = float(coeffs[0])
    for c in coeffs[1:]:
        acc = acc * x + float(c)
    return acc


def _so3_coeffs(theta2):
    """``(c0, c1, c2, d1, d2)`` of ``theta^2`` (Taylor series for ``theta < 1``), NaN-safe.

    ``c0 = sin t / t``, ``c1 = (1 - cos t) / t^2``, ``c2 = (t - sin t) / t^3``,
    ``d1 = (1/2 - c1) / t^2``, ``d2 = (1/3 - 2 c2) / t^2``.
    """
    small = theta2 < 1
    x = jnp.where(small, theta2, 0)
    series = [_horner_const(c, x) for c in (_C0, _C1, _C2, _D1, _D2)]
    t2 = jnp.where(small, 1, theta2)
    t = jnp.sqrt(t2)
    s, c = jnp.sin(t), jnp.cos(t)
    c0 = s / t
    c1 = (1 - c) / t2
    c2 = (t - s) / (t2 * t)
    d1 = (0.5 - c1) / t2
    d2 = (1 / 3 - 2 * c2) / t2
    return tuple(jnp.where(small, a, b) for a, b in zip(series, (c0, c1, c2, d1, d2)))


def _so3_left_jacobian(phi):
    """Left Jacobian ``J_l(phi)`` of SO(3) (``exp(phi + b) ~ exp(J_l b) exp(phi)``)."""
    k = _hat(phi)
    _, c1, c2, _, _ = _so3_coeffs(jnp.sum(phi * phi, -1))
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye + c1[..., None, None] * k + c2[..., None, None] * (k @ k)


#: ``sum_n |B_2n| / (2n)! x^(n-1)`` (Bernoulli numbers B_2 .. B_20), highest power first: the
#: series of ``(1 - (t/2) cot(t/2)) / t^2`` in ``x = t^2`` (terms shrink ~40x per power of x).
_E = np.array([
    1 / 6, 1 / 30, 1 / 42, 1 / 30, 5 / 66, 691 / 2730, 7 / 6, 3617 / 510, 43867 / 798,
    174611 / 330,
]) / np.array([math.factorial(2 * n) for n in range(1, 11)])
_E = _E[::-1]


def _so3_left_jacobian_inv(phi):
    """Inverse left Jacobian in closed form, ``J_l^-1(phi) = I - [phi]x / 2 + e [phi]x^2``
    with ``e = (1 - c0 / (2 c1)) / t^2`` (``= (1 - (t/2) cot(t/2)) / t^2``; Taylor series for
    ``t < 1``), for rotation vectors with ``t = |phi| < 2 pi``."""
    k = _hat(phi)
    theta2 = jnp.sum(phi * phi, -1)
    c0, c1, _, _, _ = _so3_coeffs(theta2)
    small = theta2 < 1
    e = jnp.where(small, _horner_const(_E, jnp.where(small, theta2, 0)),
                  (1 - c0 / (2 * c1)) / jnp.where(small, 1, theta2))
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye - 0.5 * k + e[..., None, None] * (k @ k)


def _spd_inverse(s):
    """Inverse and log-determinant of symmetric positive-definite matrices ``s`` (..., m, m).

    3 x 3 (every innovation covariance of the pose filters) in closed form: the adjugate (row
    ``i`` of the cofactor matrix is ``r_(i+1) x r_(i+2)``) over the determinant, a few fused
    XLA kernels instead of LAPACK calls and their wrappers (about 15 us less per tracker update
    on a CPU, ``benchmarks/bench_tracker.py``). Other sizes by Cholesky.
    """
    if s.shape[-1] != 3:
        chol = jnp.linalg.cholesky(s)
        eye = jnp.broadcast_to(jnp.eye(s.shape[-1], dtype=s.dtype), s.shape)
        log_det = 2 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), -1)
        return jsl.cho_solve((chol, True), eye), log_det
    cof = jnp.cross(jnp.roll(s, -1, -2), jnp.roll(s, -2, -2))
    det = dot_last(s[..., 0, :], cof[..., 0, :])
    return cof / det[..., None, None], jnp.log(det)


def _hemisphere_sign(q):
    """``+-1`` mapping ``q`` to a canonical representative of ``{q, -q}``.

    ``sign(w)``; at exactly 180 degrees (``w == 0``) the sign of the largest-magnitude vector
    component, so the choice is sign-invariant there too.
    """
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    ax, ay, az = jnp.abs(x), jnp.abs(y), jnp.abs(z)
    # the first component of largest magnitude (argmax's tie rule), as selects (no reduction)
    sv = jnp.sign(jnp.where((ax >= ay) & (ax >= az), x, jnp.where(ay >= az, y, z)))
    return jnp.where(w != 0, jnp.sign(w), jnp.where(sv != 0, sv, 1)).astype(q.dtype)


def _canonical_rotvec(dq):
    """Shortest-arc rotation vector of ``dq``, identical for ``dq`` and ``-dq``."""
    return quat_to_rotvec(dq * _hemisphere_sign(dq)[..., None])


def _pos_matrices(order: int, dt):
    """1-D transition ``F1`` and unit-density process noise ``Q1`` of the ``order``-state model."""
    fact = np.vectorize(math.factorial)
    i, j = np.meshgrid(np.arange(order), np.arange(order), indexing="ij")
    ef = np.where(j >= i, j - i, 0)  # F1[i, j] = dt^(j-i) / (j-i)!  (upper triangle)
    cf = np.where(j >= i, 1.0 / fact(ef), 0.0)
    eq = 2 * order - 1 - i - j  # Q1[i, j] = dt^eq / (eq (n-1-i)! (n-1-j)!)
    cq = 1.0 / (eq * fact(order - 1 - i) * fact(order - 1 - j))
    pw = jnp.stack([dt**k for k in range(2 * order)])  # integer powers: grad-safe at dt = 0
    return pw[ef] * jnp.asarray(cf, dt.dtype), pw[eq] * jnp.asarray(cq, dt.dtype)


def _pos_model(config: KalmanConfig, dt):
    f1, q1 = _pos_matrices(config.order, dt)
    eye = jnp.eye(3, dtype=dt.dtype)
    qd = jnp.asarray(config.pos_process_noise, dt.dtype)
    return jnp.kron(f1, eye), qd * jnp.kron(q1, eye)


def _rot_model(config: KalmanConfig, w, dt):
    """Error-state transition ``F`` (6, 6) and process noise ``Q`` (6, 6) (see module docs)."""
    return _rot_matrices(config.rot_process_noise, w, dt)


def _turn(w, dt):
    """The rotation vector ``w dt`` of a prediction over ``dt``, with its gradient cut across a
    gap longer than :data:`SMOOTH_MAX_GAP`: there the turn (often many turns) is chaotic in
    ``w``, and its exact derivative grew ~``dt`` per gap (1e9 after three 150 s gaps),
    swamping a tuning gradient. The value is kept; the two sides of such a gap are
    differentiated apart, as the smoother smooths them apart."""
    turn = w * dt
    return jnp.where(dt > SMOOTH_MAX_GAP, lax.stop_gradient(turn), turn)


def _rot_matrices(rot_process_noise, w, dt):
    """:func:`_rot_model` for the angular-acceleration spectral density ``rot_process_noise``."""
    phi = _turn(w, dt)
    k = _hat(phi)
    k2 = k @ k
    c0, c1, c2, d1, d2 = _so3_coeffs(jnp.sum(phi * phi))
    eye = jnp.eye(3, dtype=w.dtype)
    zero = jnp.zeros((3, 3), w.dtype)
    rot = eye + c0 * k + c1 * k2
    jl = eye + c1 * k + c2 * k2
    f = _block(rot, jl * dt, zero, eye)
    qr = jnp.asarray(rot_process_noise, w.dtype)
    dt2, dt3 = dt * dt, dt * dt * dt
    q_tt = dt3 / 3 * eye + d2 * dt3 * k2
    q_tw = dt2 / 2 * eye + d1 * dt2 * k2 + c2 * dt2 * k
    q = qr * _block(q_tt, q_tw, q_tw.T, dt * eye)
    return f, _sym(q)


#: the longest step (s) one prediction models: the state's time advances over any gap, but
#: the motion and the covariance growth over a longer one are those of this step. After a day
#: without frames the constant-velocity prediction had put the position 14 km away, with a
#: covariance whose float32 update could not bring it back.
MAX_PREDICT_STEP = 60.0


def _clamped_time(state: KalmanState, t):
    """``(t_new, dt)``: the new time (``t``, or the state's own for a NaN or earlier ``t``)
    and the step modelled, at most :data:`MAX_PREDICT_STEP`."""
    t = jnp.asarray(t, state.t.dtype)
    t_new = jnp.where(t > state.t, t, state.t)  # NaN or earlier t -> no-op
    dt = jnp.minimum(t_new - state.t, MAX_PREDICT_STEP)
    return t_new, dt.astype(state.x.dtype)


def _measurement_validity(position, quaternion, dtype):
    p = jnp.asarray(position, dtype)
    qm = jnp.asarray(quaternion, dtype)
    if p.shape != (3,) or qm.shape != (4,):
        raise ValueError(
            f"expected position of shape (3,) and quaternion of shape (4,), got {p.shape} and "
            f"{qm.shape} (use jax.vmap for batches)"
        )
    # a position component beyond max^(1/4) of the dtype (1.4e9 m in float32) is no
    # measurement either: its innovation's square overflows, and one such frame (1e18 m) made
    # the IMM's states and probabilities NaN for good
    bound = float(jnp.finfo(dtype).max) ** 0.25
    fin_p, fin_q = jnp.isfinite(p) & (jnp.abs(p) <= bound), jnp.isfinite(qm)  # no reductions
    pos_valid = fin_p[0] & fin_p[1] & fin_p[2]
    rot_valid = fin_q[0] & fin_q[1] & fin_q[2] & fin_q[3] & (dot_last(qm, qm) > 0)
    return p, qm, pos_valid, rot_valid


def _initial_moments(config, t, position, quaternion):
    """Mean and diagonal covariance of a state initialised from one pose measurement (shared by
    :func:`kalman_init` and :func:`phjax.tracking.imm.imm_init`; ``config`` needs ``order`` and
    the ``*_meas_noise`` / ``init_*_std`` fields).

    Returns ``(t, x, q, var, var_r, valid)``: the time, the position-block state (measured
    position, zero derivatives), the orientation (normalised, ``w >= 0``), the variances of the
    position block and of the orientation / angular-velocity block, and whether both parts of
    the measurement are valid (if not: zero position and identity orientation).
    """
    position, quaternion, t = jnp.asarray(position), jnp.asarray(quaternion), jnp.asarray(t)
    dtype = _float_dtype(position, quaternion)
    t = jnp.asarray(t, _float_dtype(t))
    p, qm, pos_valid, rot_valid = _measurement_validity(position, quaternion, dtype)
    valid = pos_valid & rot_valid
    p = jnp.where(valid, p, 0)
    qm = quat_normalize(jnp.where(valid, qm, jnp.asarray([1, 0, 0, 0], dtype)))
    qm = qm * _hemisphere_sign(qm)
    n = config.order
    x = jnp.concatenate([p, jnp.zeros(3 * (n - 1), dtype)])
    stds = [config.pos_meas_noise, config.init_pos_vel_std, config.init_pos_acc_std][:n]
    var = jnp.concatenate([jnp.full(3, jnp.asarray(s, dtype) ** 2, dtype) for s in stds])
    var_r = jnp.concatenate([jnp.full(3, jnp.asarray(config.rot_meas_noise, dtype) ** 2, dtype),
                             jnp.full(3, jnp.asarray(config.init_rot_vel_std, dtype) ** 2, dtype)])
    return t, x, qm, var, var_r, valid


# ----------------------------------------------------------------------------------------------
# public API


def kalman_init(
    config: KalmanConfig,
    t: Float[ArrayLike, ""],
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> KalmanState:
    """Initialise the filter from one pose measurement.

    Arguments:
        config: noise model.
        t: measurement time, s.
        position: (3,) position, m.
        quaternion: (4,) orientation, wxyz (normalised here; sign canonicalised to ``w >= 0``).

    Returns:
        A state at the measured pose with zero velocities, position covariance
        ``pos_meas_noise^2``, velocity (and acceleration) covariance from the ``init_*_std``
        fields and orientation covariance ``rot_meas_noise^2``. If either part of the measurement
        is missing (NaN) the returned state has ``initialized == False`` (and the same
        covariances, identity orientation and zero position).
    """
    t, x, qm, var, var_r, valid = _initial_moments(config, t, position, quaternion)
    return KalmanState(
        t=t,
        x=x,
        P=jnp.diag(var),
        q=qm,
        w=jnp.zeros(3, x.dtype),
        Pr=jnp.diag(var_r),
        initialized=valid,
        last_update=t,
        part_updates=jnp.stack([t, t]),
    )


def kalman_uninitialized(
    config: KalmanConfig, t: Float[ArrayLike, ""], dtype=None
) -> KalmanState:
    """An uninitialised state at time ``t`` (pose dtype ``dtype``, default: default float).

    The first valid measurement passed to :func:`kalman_update` initialises it.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    nan = jnp.asarray(jnp.nan, dtype)
    return kalman_init(config, t, jnp.full(3, nan), jnp.full(4, nan))


def kalman_predict(
    config: KalmanConfig, state: KalmanState, t: Float[ArrayLike, ""]
) -> KalmanState:
    """Propagate the state to time ``t`` (``dt = max(t - state.t, 0)``; NaN ``t`` is a no-op).

    Arguments:
        config: noise model.
        state: current state.
        t: target time, s. Earlier than ``state.t``: the state is returned unchanged.

    Returns:
        The predicted state (uninitialised states only have their time advanced).
    """
    t_new, dt = _clamped_time(state, t)
    x, p = _linear_predict(state.x, state.P, *_pos_model(config, dt))
    q, pr = _rot_predict(state.q, state.w, state.Pr, *_rot_model(config, state.w, dt), dt)
    pred = KalmanState(t_new, x, p, q, state.w, pr, state.initialized, state.last_update,
                       state.part_updates)
    moved = eqx.tree_at(lambda s: s.t, state, t_new)
    return _select(state.initialized, pred, moved)


def _joseph_update(x, p, h, r, y):
    """Kalman update of ``(x, P)`` with innovation ``y``, measurement matrix ``H`` and noise
    ``R``, covariance in Joseph form; returns ``(x, P, S, nis, log det S)``."""
    s = _sym(h @ p @ h.T + r)
    s_inv, log_det = _spd_inverse(s)
    gain = (p @ h.T) @ s_inv
    x_new = x + gain @ y
    ikh = jnp.eye(x.shape[0], dtype=x.dtype) - gain @ h
    p_new = _sym(ikh @ p @ ikh.T + gain @ r @ gain.T)
    return x_new, p_new, s, y @ s_inv @ y, log_det


def _measure_first3(n: int, dtype):
    """``H = [I3 0]``: the measurement matrix of a state whose first three entries are measured."""
    return jnp.eye(3, n, dtype=dtype)


# One model's Kalman maths, shared by the filter below and, vmapped over its models, by the IMM
# (phjax.tracking.imm): linear prediction, and the error-state orientation prediction / update.


def _linear_predict(x, p, f, q):
    """``x <- F x``, ``P <- F P F^T + Q`` (symmetrised)."""
    return f @ x, _sym(f @ p @ f.T + q)


#: ceilings of the orientation error state's standard deviations: angle (rad) and angular
#: velocity (rad/s). An angle uncertainty beyond pi says nothing more, and without a ceiling a
#: long loss (minutes without frames) grew Pr past 1e9 in float32, where rounding left it
#: indefinite: the IMM's likelihoods became NaN for good (25 min away from the camera) and the
#: single filter was 18 degrees off 5 s after the face came back. The angle's is a soft ceiling
#: (:func:`_rot_predict`: its variance stays below twice the square), the rate's a hard one.
ROT_STD_CEILING = (float(np.pi), 4 * float(np.pi))


def _rot_predict(q, w, pr, f, qn, dt):
    """Error-state orientation prediction over ``dt`` with the error-state transition ``F`` and
    process noise ``Q`` (:func:`_rot_matrices`): ``q <- exp(w dt) q`` (normalised),
    ``Pr <- F Pr F^T + Q`` (module docs), then the ceilings (:data:`ROT_STD_CEILING`, ``c_a``
    and ``c_w``), no change while every standard deviation is below its ceiling:

    * **Angle**: where the largest angle variance ``v`` exceeds ``c_a^2``, with
      ``s = c_a^2 / v``, ``Pr <- s Pr + (1 - s) diag(c_a^2 I, Pr_ww)``: a blend towards "the
      orientation is unknown, whatever the rate" (isotropic, uncorrelated with the rate; the
      rate block is unchanged). A scaling that kept the correlation (a congruence) kept what the
      linearisation of many turns leaves, an angle covariance of rank ~1 and a rate gain of
      ``rho std_w / pi``: one frame after a 150 s pause set the rate from a wrapped innovation
      (98 rad/s, more than a 30 Hz stream resolves; the IMM never recovered), and in float32 the
      innovation covariance of the next frames was too ill-conditioned to invert (NaN
      gradients). The blend is positive definite (a positive combination of two) and continuous
      at the ceiling; angle variances stay below ``2 c_a^2``.
    * **Rate**: ``D Pr D`` with ``D = diag(I, min(1, c_w / std_w))`` (a congruence)."""
    pr = _sym(f @ pr @ f.T + qn)
    c_angle, c_rate = (jnp.asarray(c, pr.dtype) for c in ROT_STD_CEILING)
    angle = jnp.arange(6) < 3
    var = jnp.diagonal(pr)
    v = jnp.max(var[:3])
    s = jnp.where(v > c_angle**2, c_angle**2 / jnp.where(v > c_angle**2, v, 1), 1)
    # the blend: the rate block kept, the rest scaled by s, (1 - s) c_a^2 on the angle diagonal
    rate_block = ~angle[:, None] & ~angle[None, :]
    pr = jnp.where(rate_block, pr, s * pr) + (1 - s) * c_angle**2 * jnp.diag(angle.astype(pr.dtype))
    over = ~angle & (var > c_rate**2)  # (rate variances: unchanged by the blend)
    d = jnp.where(over, c_rate * jax.lax.rsqrt(jnp.where(over, var, 1)), 1)
    return quat_normalize(quat_mul(quat_from_rotvec(_turn(w, dt)), q)), pr * d[:, None] * d[None, :]


def _inject(dtheta, q, pr):
    """Inject the error mean ``dtheta`` into ``q`` (``q <- exp(dtheta) q``, normalised) and reset
    the covariance with ``G = diag(J_l(dtheta), I)``: ``Pr <- G Pr G^T``."""
    dtype = q.dtype
    g = _block(_so3_left_jacobian(dtheta), jnp.zeros((3, 3), dtype), jnp.zeros((3, 3), dtype),
               jnp.eye(3, dtype=dtype))
    return quat_normalize(quat_mul(quat_from_rotvec(dtheta), q)), _sym(g @ pr @ g.T)


def _rot_update(q, w, pr, q_meas, valid, r):
    """Error-state orientation update with a measured orientation (module docs).

    Returns ``(q, w, Pr, y, S, nis, log det S)``: the updated nominal, angular velocity and
    covariance (apply them only where the measurement is used), the innovation (zero when
    ``valid`` is false: a safe substitute keeps values and gradients finite) and its covariance,
    NIS and log-determinant.
    """
    q_safe = quat_normalize(jnp.where(valid, q_meas, q))
    y = jnp.where(valid, _canonical_rotvec(quat_mul(q_safe, quat_conj(q))), 0)
    err, pr_new, s, nis, log_det = _joseph_update(jnp.zeros(6, q.dtype), pr,
                                                  _measure_first3(6, q.dtype), r, y)
    q_new, pr_new = _inject(err[:3], q, pr_new)
    return q_new, w + err[3:], pr_new, y, s, nis, log_det


def kalman_update(
    config: KalmanConfig,
    state: KalmanState,
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> tuple[KalmanState, KalmanInfo]:
    """Measurement update with a pose measured at ``state.t``.

    Arguments:
        config: noise model.
        state: predicted state (at the measurement time).
        position: (3,) measured position, m; any NaN skips the position part.
        quaternion: (4,) measured orientation (wxyz, any sign/norm); any NaN or a zero norm
            skips the orientation part.

    Returns:
        ``(state, info)``. An uninitialised state is initialised from the measurement instead
        (when both parts are valid). ``state.last_update`` is set to ``state.t`` when any part
        was applied.
    """
    dtype = state.x.dtype
    p_meas, q_meas, pos_valid, rot_valid = _measurement_validity(position, quaternion, dtype)
    gate = config.gate_nis

    # position part (safe substitute for missing data -> zero innovation, finite gradients)
    r_pos = jnp.asarray(config.pos_meas_noise, dtype) ** 2 * jnp.eye(3, dtype=dtype)
    y_pos = jnp.where(pos_valid, p_meas, state.x[:3]) - state.x[:3]
    h_pos = _measure_first3(state.x.shape[0], dtype)
    x_upd, p_upd, s_pos, nis_pos, _ = _joseph_update(state.x, state.P, h_pos, r_pos, y_pos)
    pos_ok = pos_valid if gate is None else pos_valid & (nis_pos <= gate)

    # orientation part (error state, H = [I 0])
    r_rot = jnp.asarray(config.rot_meas_noise, dtype) ** 2 * jnp.eye(3, dtype=dtype)
    q_upd, w_upd, pr_upd, y_rot, s_rot, nis_rot, _ = _rot_update(
        state.q, state.w, state.Pr, q_meas, rot_valid, r_rot)
    rot_ok = rot_valid if gate is None else rot_valid & (nis_rot <= gate)
    if gate is not None:  # a part rejected for longer than gate_reset starts again
        stale = state.t - state.part_updates > config.gate_reset
        pos_reset, rot_reset = pos_valid & ~pos_ok & stale[0], rot_valid & ~rot_ok & stale[1]
        fresh = kalman_init(config, state.t, p_meas, q_meas)  # the parts' initial moments
        x_upd = jnp.where(pos_reset, fresh.x, x_upd)
        p_upd = jnp.where(pos_reset, fresh.P, p_upd)
        q_upd = jnp.where(rot_reset, fresh.q, q_upd)
        w_upd = jnp.where(rot_reset, fresh.w, w_upd)
        pr_upd = jnp.where(rot_reset, fresh.Pr, pr_upd)
        pos_ok, rot_ok = pos_ok | pos_reset, rot_ok | rot_reset

    updated = KalmanState(
        t=state.t,
        x=jnp.where(pos_ok, x_upd, state.x),
        P=jnp.where(pos_ok, p_upd, state.P),
        q=jnp.where(rot_ok, q_upd, state.q),
        w=jnp.where(rot_ok, w_upd, state.w),
        Pr=jnp.where(rot_ok, pr_upd, state.Pr),
        initialized=state.initialized,
        last_update=jnp.where(pos_ok | rot_ok, state.t, state.last_update),
        part_updates=jnp.where(jnp.stack([pos_ok, rot_ok]), state.t, state.part_updates),
    )
    return _finish(config, state, state.t, updated, p_meas, q_meas, (pos_valid, rot_valid),
                   (pos_ok, rot_ok), (y_pos, y_rot), (s_pos, s_rot), (r_pos, r_rot), (nis_pos, nis_rot))


def _finish(config, state, t, updated, p_meas, q_meas, valid, ok, innovation, cov, r, nis):
    """The step's result: ``updated`` for an initialised ``state``, else a state initialised
    from the measurement at ``t``; and the :class:`KalmanInfo` (pairs: position, orientation)."""
    init = kalman_init(config, t, p_meas, q_meas)
    init_time = jnp.where(init.initialized, t, state.last_update)
    init = eqx.tree_at(lambda s: (s.last_update, s.part_updates), init,
                       (init_time, jnp.stack([init_time, init_time])))
    was_init = state.initialized
    new_state = _select(was_init, updated, init)
    init_now = ~was_init & init.initialized
    zero3 = jnp.zeros(3, updated.x.dtype)
    zero = jnp.zeros((), updated.x.dtype)
    info = KalmanInfo(
        pos_innovation=jnp.where(was_init, innovation[0], zero3),
        rot_innovation=jnp.where(was_init, innovation[1], zero3),
        pos_innovation_cov=jnp.where(was_init, cov[0], r[0]),
        rot_innovation_cov=jnp.where(was_init, cov[1], r[1]),
        pos_nis=jnp.where(was_init & valid[0], nis[0], zero),
        rot_nis=jnp.where(was_init & valid[1], nis[1], zero),
        pos_valid=valid[0],
        rot_valid=valid[1],
        pos_used=jnp.where(was_init, ok[0], init_now),
        rot_used=jnp.where(was_init, ok[1], init_now),
        initialized_now=init_now,
    )
    return new_state, info


@jit
def kalman_step(
    config: KalmanConfig,
    state: KalmanState,
    t: Float[ArrayLike, ""],
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> tuple[KalmanState, KalmanInfo]:
    """:func:`kalman_predict` to ``t`` followed by :func:`kalman_update` (jitted; scan body)."""
    return kalman_update(config, kalman_predict(config, state, t), position, quaternion)



@jit
def kalman_filter(
    config: KalmanConfig,
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    quaternions: Float[ArrayLike, "n 4"],
    initial_state: KalmanState | None = None,
) -> tuple[KalmanState, KalmanInfo]:
    """Filter a measurement sequence with ``lax.scan`` over :func:`kalman_step`.

    Arguments:
        config: noise model.
        times: (n,) measurement times, s (non-decreasing; earlier times are applied at the
            current filter time, see :func:`kalman_predict`).
        positions: (n, 3) positions, NaN rows/entries for missing data.
        quaternions: (n, 4) orientations (wxyz, any sign), NaN for missing data.
        initial_state: state to continue from; default: uninitialised at ``times[0]``, so the
            first measurement with both parts valid initialises the filter.

    Returns:
        ``(states, infos)`` stacked over the ``n`` measurements (posterior after each one).
    """
    return _filter_scan("kalman_filter", kalman_step, kalman_uninitialized, config, times,
                        positions, quaternions, initial_state)


def _filter_scan(name, step, uninitialized, config, times, positions, quaternions,
                 initial_state):
    """``lax.scan`` of a filter's ``step`` over a measurement sequence (shared by
    :func:`kalman_filter` and :func:`phjax.tracking.imm.imm_filter`): shapes checked, the pose
    dtype taken from the measurements, an uninitialised start at ``times[0]`` by default."""
    times = jnp.asarray(times)
    dtype = _float_dtype(positions, quaternions)
    positions = jnp.asarray(positions, dtype)
    quaternions = jnp.asarray(quaternions, dtype)
    n = times.shape[0] if times.ndim == 1 else -1
    if times.ndim != 1 or positions.shape != (n, 3) or quaternions.shape != (n, 4) or n < 1:
        raise ValueError(
            f"{name} expects times (n,), positions (n, 3), quaternions (n, 4) with n >= 1; "
            f"got {times.shape}, {positions.shape}, {quaternions.shape}"
        )
    if initial_state is None:
        initial_state = uninitialized(config, times[0], dtype)

    def body(state, inputs):
        state, info = step(config, state, *inputs)
        return state, (state, info)

    _, (states, infos) = filter_scan(body, initial_state, (times, positions, quaternions))
    return states, infos


#: the longest step (s) between consecutive states that :func:`rts_smooth` smooths across
SMOOTH_MAX_GAP = 5.0


@jit
def rts_smooth(config: KalmanConfig, filtered_states: KalmanState) -> KalmanState:
    """Rauch-Tung-Striebel smoother for the output of :func:`kalman_filter`.

    The one-step predictions are recomputed from consecutive filtered states (so ``config``
    must be the one used for filtering). Position: the exact linear RTS recursion.
    Orientation: a multiplicative (error-state) RTS. For step ``k`` the error coordinates are
    those of the filtered nominal ``(q_k, w_k)`` (mean zero, covariance ``Pr_k``); the prediction
    ``q_k^- = exp(w_k dt) q_k`` with ``F_k, Q_k`` linearised at ``w_k``; the smoothed state at
    ``k+1`` is expressed around the prediction as
    ``e = [rotvec(q^s_{k+1} (q_{k+1}^-)^-1), w^s_{k+1} - w_k]`` with covariance transported by
    ``diag(J_l(e_theta)^-1, I)``; then ``C = Pr_k F^T (Pr^-)^-1``, ``delta = C e``,
    ``P = Pr_k + C (P^s - Pr^-) C^T``, and ``delta`` is injected into ``(q_k, w_k)`` with the
    same reset Jacobian as the update. Approximations: first-order (linearisation about the
    filtered, not the smoothed, trajectory; no iteration) and first-order covariance transport.
    Uninitialised filtered states, and those after the last accepted measurement (nothing to
    smooth with), are passed through unchanged; a step longer than :data:`SMOOTH_MAX_GAP` (a
    pause) is not smoothed across: the two sides are smoothed apart.

    Arguments:
        config: noise model used for filtering.
        filtered_states: states stacked over time (leading axis), e.g. from
            :func:`kalman_filter`.

    Returns:
        Smoothed states stacked over time (``t``, ``initialized``, ``last_update`` unchanged).
    """
    if filtered_states.x.ndim != 2:
        raise ValueError("rts_smooth expects states stacked along a leading time axis")
    last = jax.tree.map(lambda a: a[-1], filtered_states)
    rest = jax.tree.map(lambda a: a[:-1], filtered_states)
    dtype = filtered_states.x.dtype
    eye3 = jnp.eye(3, dtype=dtype)
    zero3 = jnp.zeros((3, 3), dtype)

    final_update = last.last_update

    def body(nxt_in: KalmanState, cur: KalmanState):
        dt_in = jnp.maximum(nxt_in.t - cur.t, 0).astype(dtype)
        # After the last accepted measurement there is nothing to smooth with: the filtered
        # state is the smoothed one (exactly), so a state is smoothed only against a next one
        # at or before that measurement's time (smoothing the last measured state against its
        # own prediction over a 10 s gap gave float32 NaN), and the recursion through a long
        # tail of lost frames (the size-class padding: 1 s apart) is left out: in float32 its
        # covariances lost positive-definiteness and the Cholesky's NaN reached every real
        # frame. Likewise across a pause longer than SMOOTH_MAX_GAP: the prediction over it (a
        # rotation w dt of many turns, a position v dt of km) linearises nothing, and
        # smoothing with it put the poses before a 5 min pause up to 180 degrees off; the two
        # sides are smoothed apart.
        use = (cur.initialized & nxt_in.initialized & (nxt_in.t <= final_update)
               & (dt_in <= SMOOTH_MAX_GAP))
        # a state left as filtered is smoothed (unused) against itself over dt = 0: the step
        # it skips gave NaN (float32, a 3 h gap) that the select passed on to gradients
        nxt = _select(use, nxt_in, cur)
        dt = jnp.where(use, dt_in, 0)
        # position: exact linear RTS
        f, qmat = _pos_model(config, dt)
        x_pred, p_pred = _linear_predict(cur.x, cur.P, f, qmat)
        gain = jsl.cho_solve((jnp.linalg.cholesky(p_pred), True), f @ cur.P).T
        x_s = cur.x + gain @ (nxt.x - x_pred)
        p_s = _sym(cur.P + gain @ (nxt.P - p_pred) @ gain.T)
        # orientation: multiplicative RTS in the error coordinates of the filtered state
        fr, qr = _rot_model(config, cur.w, dt)
        q_pred, pr_pred = _rot_predict(cur.q, cur.w, cur.Pr, fr, qr, dt)
        e_theta = _canonical_rotvec(quat_mul(nxt.q, quat_conj(q_pred)))
        e = jnp.concatenate([e_theta, nxt.w - cur.w])
        jinv = _so3_left_jacobian_inv(e_theta)
        tr = _block(jinv, zero3, zero3, eye3)
        p_next = tr @ nxt.Pr @ tr.T
        gain_r = jsl.cho_solve((jnp.linalg.cholesky(pr_pred), True), fr @ cur.Pr).T
        delta = gain_r @ e
        pr_s = cur.Pr + gain_r @ (p_next - pr_pred) @ gain_r.T
        q_s, pr_s = _inject(delta[:3], cur.q, pr_s)
        smoothed = KalmanState(
            cur.t, x_s, p_s, q_s, cur.w + delta[3:], pr_s, cur.initialized, cur.last_update,
            cur.part_updates,
        )
        out = _select(use, smoothed, cur)
        return out, out

    _, sm = lax.scan(body, last, rest, reverse=True)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]], 0), sm, last)


def predict_pose(
    config: KalmanConfig, state: KalmanState, t: Float[ArrayLike, ""]
) -> tuple[Float[Array, "3"], Float[Array, "4"], Float[Array, "3"], Float[Array, "3"]]:
    """Predicted mean pose at time ``t`` (no covariance; ``dt`` clamped at 0 like predict).

    Arguments:
        config: noise model (only ``model`` is used).
        state: current state (meaningless if ``state.initialized`` is False).
        t: time, s (``jax.vmap`` over ``t`` for several render times).

    Returns:
        ``(position, quaternion, velocity, angular_velocity)`` at ``t``.
    """
    _, dt = _clamped_time(state, t)
    p, v = _extrapolate_derivatives([state.x[3 * i : 3 * i + 3] for i in range(config.order)], dt)
    q = quat_normalize(quat_mul(quat_from_rotvec(_turn(state.w, dt)), state.q))
    return p, q, v, state.w


def _extrapolate_derivatives(xs, dt):
    """Position and velocity ``dt`` later from the derivative vectors ``xs = [p, v, (a)]``
    (highest one constant): ``x_i(t) = sum_k dt^(k-i) / (k-i)! x_k``, written out (a dot is a
    kernel of its own on CPU). Shared by :func:`predict_pose` and the IMM's prediction."""
    n = len(xs)
    return [sum((dt ** (k - i) / math.factorial(k - i) * xs[k] for k in range(i + 1, n)), xs[i])
            for i in range(2)]
