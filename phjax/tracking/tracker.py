"""Render-rate pose streams from camera-rate measurements.

The streaming tracker turns noisy, possibly missing pose measurements at camera rate into a
smooth pose at any render time:

* a Kalman filter (:mod:`phjax.tracking.kalman`) estimates position, velocity, orientation and angular
  velocity at each camera frame;
* at each frame ``t_k`` a new **segment** starts at the pose and velocity *currently rendered*
  (so the stream is C1 across camera frames: no jump in position, orientation or their
  velocities) and reaches the filter's prediction at ``t_k + horizon``. In between, the
  correction ``c`` (rendered minus predicted pose, and its rate) decays like a critically damped
  second-order system with time constant ``T = horizon / 5``,
  ``c(t) = (c0 (1 + s) + c0' (t - t_k)) exp(-s)``, ``s = (t - t_k) / T``: most of the
  correction is applied early, which halves the extra error of a symmetric (smoothstep-like)
  blend at the same jerk. The segment is two C1-joined pieces, each a PH quintic
  (:func:`phjax.hermite_quintic`, near-optimal free angles) for position and a C1 quaternion
  curve (:func:`phjax.quaternion_hermite`) for orientation: from the rendered state to the
  damped correction's state at ``t_k + 0.4 horizon`` (two time constants), then to the
  prediction at ``t_k + horizon`` with the predicted velocities;
* render samples inside the segment evaluate the two curves; past its end (dropped frames) the
  pose coasts with the end velocities for ``coast_time`` seconds, then the velocities decay with
  time constant ``stop_time`` (C1) so the pose comes to rest: it never runs away.

Streaming API (jitted, static shapes, no recompilation per frame): :func:`tracker_init`,
:func:`tracker_update` at camera rate, :func:`tracker_sample` at render rate. A host-side render
loop gets the lowest latency from :class:`phjax.TrackerStream` (the same update on a packed
state: few buffers cross the jit boundary) and, on a CPU, with JAX's asynchronous dispatch
turned off at program start (``jax.config.update("jax_cpu_enable_async_dispatch", False)``):
for calls this short the hand-off to a worker thread costs more than the computation (see
``benchmarks/bench_tracker.py``). Calling the pure functions directly, pass a config converted
once with :func:`tracker_config_arrays`.
Batch API: :func:`track` runs the causal stream over a recording in one ``lax.scan`` (the output
at render time ``tau`` depends only on measurements with ``t <= tau``), and :func:`reconstruct`
the offline version (RTS-smoothed states joined by PH quintic / C1 quaternion segments). Both
also take NaN-padded batches of recordings, sharded over devices or not
(:mod:`phjax.tracking._batch`, padding rule in :mod:`phjax.batch`).

Conventions: times in seconds, positions in metres, quaternions wxyz, angular velocities in
rad/s in the world frame. Render times before the first valid measurement give NaN.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._batch import run_batch
from .imm import IMMConfig, imm_predict_pose, imm_step, imm_uninitialized
from .kalman import (
    KalmanConfig,
    KalmanState,
    kalman_filter,
    kalman_step,
    kalman_uninitialized,
    predict_pose,
    rts_smooth,
)
from ..curves.orientation import QuaternionHermite, _hermite_factors, quaternion_hermite
from ..curves.ph_quintic import PHQuintic, hermite_quintic
from ..quaternion import (
    quat_conj,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_to_rotvec,
)

__all__ = [
    "TrackerConfig",
    "TrackerState",
    "tracker_init",
    "tracker_config_arrays",
    "tracker_update",
    "tracker_sample",
    "track",
    "reconstruct",
]


class TrackerConfig(eqx.Module):
    """Parameters of the tracker (float fields are differentiable PyTree leaves).

    Fields:
        kalman: the single-model filter's noise model (:class:`phjax.KalmanConfig`); used by the
            causal stream when ``imm`` is ``None``, and always by :func:`reconstruct` (RTS).
        imm: the interacting-multiple-model filter (:class:`phjax.tracking.imm.IMMConfig`) of
            the causal stream (default), or ``None`` for the single-model Kalman filter. On the
            development set (``experiments/frontier.py``, 14 recordings x 15 s, tuned on 7)
            the IMM stream has 5 % / 2.5 % lower position / rotation RMSE than the single-model
            stream at the same horizon (medians over all recordings).
        horizon: settling time of each correction, s: the stream reaches the filter's
            prediction ``horizon`` seconds after each camera frame. The main smoothness knob:
            longer is smoother (lower jerk), shorter follows the filter more closely. Default
            0.028 s (development set, 30 Hz camera, 120 Hz render: RMSE 1.037x / 1.044x and
            RMS jerk 0.290x / 0.293x of the filter's own constant-velocity extrapolation for
            position / rotation; see ``experiments/tune_baselines.py --horizon-only``).
        adapt: adaptive settling (IMM only): each segment's horizon is
            ``horizon * exp(adapt (1 - 2 m))``, where ``m`` in [0, 1] is the expected mode index
            of the IMM (0: the quietest model certain, 1: the most agile one), averaged over
            position and orientation: longer, heavier smoothing for a still head, shorter
            settling in fast turns. Default 0 (fixed horizon).
        coast_time: after a segment ends without a new frame, keep moving with the end
            velocities for this long, s (default 0.1).
        stop_time: then let the velocities decay with this time constant, s (default 0.05).
    """

    kalman: KalmanConfig = eqx.field(default_factory=KalmanConfig)
    imm: IMMConfig | None = eqx.field(default_factory=IMMConfig)
    horizon: float = 0.028
    adapt: float = 0.0
    coast_time: float = 0.1
    stop_time: float = 0.05


#: The correction ``c(t)`` = rendered minus predicted pose decays like a critically damped
#: second-order system, ``c(t) = (c0 (1 + s) + c0' t) exp(-s)`` with ``s = t / T``; the time
#: constant is ``T = _SETTLE * horizon`` and the two pieces join at ``_KNOT * horizon``.
_SETTLE = 0.2
_KNOT = 0.4


class TrackerState(eqx.Module):
    """State of the streaming tracker (a PyTree of arrays).

    Fields:
        filter: the Kalman filter state.
        render: everything a render sample needs, packed in three vectors (layouts ``_P``,
            ``_P``, ``_R``): per piece of the current segment its start, end, duration and
            reciprocal duration, the power basis of its position curve and its rotation curve
            with the norms and reciprocal norms of the increments; then ``started``, the end
            pose and velocities and the coasting parameters of the config of the last update.
            :func:`tracker_sample` passes these to a kernel of a few fused operations.
        shape: the PH form of the two position pieces, ``(2, 30)`` (layout ``_C``: quaternion
            coefficients ``A0, A1, A2`` and Bezier control points).

    The state is split into arrays of at most 64 elements on purpose: XLA's CPU runtime runs
    the kernels of a compiled function one after the other in the calling thread only when
    every buffer it touches has at most 512 bytes, and otherwise hands them to its thread pool,
    which costs several microseconds per kernel (measured: 11 small additions take 21 us
    sequentially, 87 us once one operand has 129 floats). Few arrays still cross the jit
    boundary (each output costs about 1.4 us).

    Properties (views): ``t0``, the time of the last segment start (the last camera frame
    used), s; ``started``, whether a valid measurement has been seen (before that samples are
    NaN); ``duration`` (2,), the durations of the segment's two pieces, s;
    ``curve``, the two position pieces (a :class:`PHQuintic` batch of 2), each on its own
    parameter ``(t - start) / duration``; ``rotation``, the two orientation pieces (a
    :class:`QuaternionHermite` batch of 2).
    """

    filter: KalmanState
    render: tuple[Float[Array, " P"], Float[Array, " P"], Float[Array, " R"]]
    shape: Float[Array, "2 30"]

    def _field(self, name):
        a, b = _P[name]
        return jnp.stack([self.render[0][a:b], self.render[1][a:b]])

    @property
    def t0(self) -> Float[Array, ""]:
        return self.render[0][_P["t0"][0]]

    @property
    def started(self) -> Bool[Array, ""]:
        return self.render[2][_R["started"][0]] > 0

    @property
    def duration(self) -> Float[Array, "2"]:
        return self._field("dur")[:, 0]

    @property
    def curve(self) -> PHQuintic:
        f = {k: self.shape[:, a:b] for k, (a, b) in _C.items()}
        return PHQuintic(A0=f["A0"], A1=f["A1"], A2=f["A2"], control_points=f["cp"].reshape(2, 6, 3))

    @property
    def rotation(self) -> QuaternionHermite:
        f = self._field
        return QuaternionHermite(q0=f("q0"), w1=f("w1"), w2=f("w2"), w3=f("w3"), duration=self.duration)


# layout of TrackerState.render: one block per piece, then the common part. The per-piece
# constants are precomputed at update time so that a sample costs few XLA ops: the reciprocal
# of the duration and, for each exponential of the rotation curve ``exp(b w)`` (``b >= 0``),
# the norm ``n = |w|`` and ``1/n`` (0 at 0), so that ``exp(b w) = (cos(b n), sin(b n)/n w)``
# needs one sin/cos of a small vector and no division.
_PIECE_LAYOUT = (("t0", 1), ("t_end", 1), ("dur", 1), ("inv_dur", 1), ("coef", 18), ("q0", 4),
                 ("w1", 3), ("w2", 3), ("w3", 3), ("n", 3), ("inv_n", 3))
_COMMON_LAYOUT = (("started", 1), ("p_end", 3), ("v_end", 3), ("q_end", 4), ("w_end", 3),
                  ("n_end", 1), ("inv_n_end", 1), ("coast", 1), ("stop", 1), ("inv_stop", 1))
_CURVE_LAYOUT = (("A0", 4), ("A1", 4), ("A2", 4), ("cp", 18))


def _offsets(layout):
    """``{name: (start, stop)}`` of the fields of a packed layout."""
    out, off = {}, 0
    for name, n in layout:
        out[name] = (off, off + n)
        off += n
    return out


_P = _offsets(_PIECE_LAYOUT)
_R = _offsets(_COMMON_LAYOUT)
_C = _offsets(_CURVE_LAYOUT)


def _vnorm_inv(v):
    """``(|v|, 1/|v|)`` of 3-vectors (``1/|v| = 0`` at 0), finite gradients at 0."""
    n2 = v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2]
    pos = n2 > 0
    n = jnp.where(pos, jnp.sqrt(jnp.where(pos, n2, 1)), 0)
    return n, jnp.where(pos, 1 / jnp.where(pos, n, 1), 0)


def _make_state(config, kf, t0, duration, curve, rotation, started, ends) -> TrackerState:
    """A :class:`TrackerState` with the packed render vectors of its two pieces.

    ``ends = (p_end, v_end, q_end, w_end)``: the end pose and velocities of the second piece,
    i.e. the Hermite data it was built from (``q_end`` with the sign of its ``rotation(1)``).
    """
    p_end, v_end, q_end, w_end = ends
    dtype = t0.dtype
    starts = (t0, t0 + duration[0])
    w_all = jnp.stack([rotation.w1, rotation.w2, rotation.w3], axis=1)  # (2, 3, 3)
    n, inv_n = _vnorm_inv(w_all)
    coef = curve._power(0)  # (2, 6, 3)

    def piece(i):  # built per piece: no temporary beyond 64 elements (see TrackerState)
        return jnp.concatenate([jnp.stack([starts[i], starts[i] + duration[i], duration[i],
                                           1 / duration[i]]), coef[i].reshape(18),
                                rotation.q0[i], w_all[i].reshape(9), n[i], inv_n[i]])

    n_end, inv_n_end = _vnorm_inv(w_end)
    stop = jnp.asarray(config.stop_time, dtype)
    parts = [started.astype(dtype)[None], p_end, v_end, q_end, w_end, (n_end / 2)[None],
             inv_n_end[None], jnp.asarray(config.coast_time, dtype)[None], stop[None],
             (1 / stop)[None]]
    common = jnp.concatenate([jnp.asarray(x, dtype) for x in parts])
    shape = jnp.concatenate([curve.A0, curve.A1, curve.A2, curve.control_points.reshape(2, 18)], -1)
    return TrackerState(kf, (piece(0), piece(1), common), shape)


def _segment(p0, v0, q0, w0, p1, v1, q1, w1, duration):
    dur = jnp.asarray(duration)[..., None]
    curve = hermite_quintic(p0, p1, v0 * dur, v1 * dur)
    rot = quaternion_hermite(q0, q1, w0, w1, duration)
    return curve, rot


def _rotation_end(q0, q1, w0, w1, duration):
    """``quaternion_hermite(q0, q1, w0, w1, duration).rotation(1)`` without evaluating it.

    The curve ends at ``q1`` or ``-q1``: ``-q1`` exactly when the middle factor was flipped to its
    shortest arc (the same factors as :func:`quaternion_hermite`, shared by XLA's CSE).
    """
    _, mid, _ = _hermite_factors(q0, q1, w0, w1, duration)
    return jnp.where(mid[..., :1] < 0, -q1, q1)


def _float_dtype(dtype):
    """``dtype``, or JAX's default float dtype for ``None``."""
    return jnp.zeros((), dtype=dtype if dtype is not None else float).dtype


def tracker_init(config: TrackerConfig | None = None, t: float = 0.0, dtype=None) -> TrackerState:
    """An empty tracker state (no measurement yet).

    Arguments:
        config: tracker configuration (default :class:`TrackerConfig()`).
        t: start time, s.
        dtype: floating dtype of the state (default: JAX's default float).

    Returns:
        A :class:`TrackerState` whose samples are NaN until the first valid update.
    """
    config = TrackerConfig() if config is None else config
    dtype = _float_dtype(dtype)
    kf = _filter_uninitialized(config, jnp.asarray(t, dtype), dtype)
    z3 = jnp.zeros((2, 3), dtype)
    q = jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], dtype), (2, 4))
    dur = jnp.full((2,), 0.5, dtype)
    curve, rot = _segment(z3, z3, q, z3, z3, z3, q, z3, dur)
    return _make_state(config, kf, jnp.asarray(t, dtype), dur, curve, rot, jnp.asarray(False),
                       (z3[0], z3[0], q[0], z3[0]))


def tracker_config_arrays(config: TrackerConfig | None = None, dtype=None) -> TrackerConfig:
    """The config with its numeric leaves as device arrays: convert once, outside the loop.

    :func:`tracker_update` traces the config, so Python-float leaves are converted to device
    arrays on every call (about 1.5 us each on a CPU). Same results as the original config.

    Arguments:
        config: tracker configuration (default :class:`TrackerConfig()`).
        dtype: floating dtype of the leaves; use the state's (default: JAX's default float).

    Returns:
        A :class:`TrackerConfig` whose leaves are 0-d arrays.
    """
    config = TrackerConfig() if config is None else config
    dtype = _float_dtype(dtype)
    return jax.tree.map(lambda x: jnp.asarray(x, dtype), config)


def _evaluate(config: TrackerConfig, state: TrackerState, tau, velocities: bool = True):
    """Rendered position, velocity, orientation, angular velocity at time(s) ``tau``
    (velocities are ``None`` when not requested)."""
    return _eval_render(state.render, tau, velocities)


def _qmul_c(a, b):
    """Hamilton product on component tuples ``(w, x, y, z)`` (same association as quat_mul)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    w = aw * bw - (ax * bx + ay * by + az * bz)
    x = aw * bx + bw * ax + (ay * bz - az * by)
    y = aw * by + bw * ay + (az * bx - ax * bz)
    z = aw * bz + bw * az + (ax * by - ay * bx)
    return w, x, y, z


def _rotate_c(q, v):
    """Vector part of ``q v q*`` for a unit quaternion and a vector, on component tuples."""
    w, ux, uy, uz = q
    vx, vy, vz = v
    tx, ty, tz = 2 * (uy * vz - uz * vy), 2 * (uz * vx - ux * vz), 2 * (ux * vy - uy * vx)
    return (vx + w * tx + (uy * tz - uz * ty), vy + w * ty + (uz * tx - ux * tz),
            vz + w * tz + (ux * ty - uy * tx))


def _eval_render(render, tau, velocities: bool = True):
    """Pose (and velocities) of the packed render vectors ``(first piece, second piece,
    common)`` at time(s) ``tau`` (layouts ``_P`` and ``_R``).

    Selects the piece that covers ``tau`` (the second from its start on), then evaluates it
    on scalar components with the transcendental functions of one sample gathered in one sin,
    one cos and one exp, so that XLA compiles it to a handful of fused kernels.
    """
    first, second, common = render
    dtype = common.dtype
    tau = jnp.asarray(tau, dtype)
    pc = jnp.where((tau >= second[0])[..., None], second, first)  # (*T, piece size)
    r = {k: common[a:b] for k, (a, b) in _R.items()}
    g = lambda k, i=0: r[k][i]  # noqa: E731
    gp = lambda k, i=0: pc[..., _P[k][0] + i]  # noqa: E731
    t0, inv_dur = gp("t0"), gp("inv_dur")
    t_end = second[_P["t_end"][0]]
    coast, stop, inv_stop = g("coast"), g("stop"), g("inv_stop")
    s = jnp.clip((tau - t0) * inv_dur, 0, 1)
    # beyond the segment end: coast, then come to rest smoothly
    delta = jnp.maximum(tau - t_end, 0)
    decay = jnp.exp(-jnp.maximum(delta - coast, 0) * inv_stop)
    disp = jnp.minimum(delta, coast) + stop * (1 - decay)
    inside = tau <= t_end
    nan = jnp.where(g("started") > 0, 0.0, jnp.nan).astype(dtype)
    # rotation curve q(s) = exp(b3 w3) exp(b2 w2) exp(b1 w1) q0; coasting exp(w_end disp / 2) q_end
    cs = 1 - s
    b = (1 - cs * cs * cs, s * s * (3 - 2 * s), s * s * s)
    ang = jnp.stack([b[0] * gp("n", 0), b[1] * gp("n", 1), b[2] * gp("n", 2),
                     disp * g("n_end")], -1)
    sin, cos = jnp.sin(ang), jnp.cos(ang)
    ws = [tuple(gp(k, i) for i in range(3)) for k in ("w1", "w2", "w3")]
    exps = []
    for j in range(3):
        k = jnp.where(gp("n", j) > 0, sin[..., j] * gp("inv_n", j), b[j])
        exps.append((cos[..., j],) + tuple(k * x for x in ws[j]))
    q_in = tuple(gp("q0", i) for i in range(4))
    for e in exps:
        q_in = _qmul_c(e, q_in)
    w_end = tuple(g("w_end", i) for i in range(3))
    k_end = jnp.where(g("n_end") > 0, sin[..., 3] * g("inv_n_end"), disp / 2)
    e_end = (cos[..., 3],) + tuple(k_end * x for x in w_end)
    q_out = _qmul_c(e_end, tuple(g("q_end", i) for i in range(4)))
    q = jnp.stack([jnp.where(inside, a, c) + nan for a, c in zip(q_in, q_out)], -1)
    # position: Horner on the power basis
    sv = s[..., None]
    a0 = _P["coef"][0]
    c = [pc[..., a0 + 3 * j:a0 + 3 * j + 3] for j in range(6)]
    p_in = c[5]
    for j in range(4, -1, -1):
        p_in = p_in * sv + c[j]
    p_out = r["p_end"] + r["v_end"] * disp[..., None]
    p = jnp.where(inside[..., None], p_in, p_out) + nan
    if not velocities:
        return p, None, q, None
    v_in = 5 * c[5]
    for j in range(4, 0, -1):
        v_in = v_in * sv + j * c[j]
    factor = jnp.where(delta > coast, decay, 1.0)[..., None]
    v = jnp.where(inside[..., None], v_in * inv_dur[..., None], r["v_end"] * factor) + nan
    # world angular velocity: q' q* = d3 w3 + E3 (d2 w2) E3* + E3 E2 (d1 w1) E2* E3* (per unit s)
    d = (3 * cs * cs, 6 * s * cs, 3 * s * s)
    e32 = _qmul_c(exps[2], exps[1])
    om2 = _rotate_c(exps[2], tuple(d[1] * x for x in ws[1]))
    om1 = _rotate_c(e32, tuple(d[0] * x for x in ws[0]))
    om = [d[2] * ws[2][i] + om2[i] + om1[i] for i in range(3)]
    w_in = jnp.stack([2 * x * inv_dur for x in om], -1)
    w = jnp.where(inside[..., None], w_in, r["w_end"] * factor) + nan
    return p, v, q, w


@jax.jit
def _sample_render(render, t_render):
    p, _, q, _ = _eval_render(render, t_render, velocities=False)
    return p, q


def _filter_uninitialized(config: TrackerConfig, t, dtype):
    """The chosen filter's empty state (single-model Kalman or IMM)."""
    if config.imm is None:
        return kalman_uninitialized(config.kalman, t, dtype)
    return imm_uninitialized(config.imm, t, dtype)


def _filter_step(config: TrackerConfig, state, t, position, quaternion):
    if config.imm is None:
        return kalman_step(config.kalman, state, t, position, quaternion)
    return imm_step(config.imm, state, t, position, quaternion)


def _filter_predict(config: TrackerConfig, state, t):
    """``(position, quaternion, velocity, angular velocity)`` predicted to ``t >= state.t``."""
    if config.imm is None:
        p, q, v, w = predict_pose(config.kalman, state, t)
    else:
        p, q, v, w = imm_predict_pose(config.imm, state, t)
    return p, quat_normalize(q), v, w


def _adaptive_factor(config: TrackerConfig, kf, dtype):
    """Horizon factor ``exp(adapt (1 - 2 m))`` from the IMM's mode probabilities: ``m`` in
    [0, 1] is the expected mode index (models in the order of the config, quietest first),
    scaled to [0, 1] and averaged over position and orientation; 1 for the Kalman filter."""
    if config.imm is None:
        return jnp.ones((), dtype)

    def expected(log_mu):
        k = log_mu.shape[0]
        return jnp.exp(log_mu) @ jnp.linspace(0.0, 1.0, k, dtype=dtype) if k > 1 else 0.5

    m = 0.5 * (expected(kf.pos_log_mu) + expected(kf.rot_log_mu))
    return jnp.exp(jnp.asarray(config.adapt, dtype) * (1 - 2 * m))


def _settle(s):
    """Critically damped decay at ``s`` time constants: weights of the initial offset and of
    the initial rate (per time constant) and their derivatives (per time constant)."""
    e = jnp.exp(-s)
    return (1 + s) * e, -s * e, s * e, (1 - s) * e


def _update(config: TrackerConfig, state: TrackerState, t, position, quaternion):
    # shapes are static: checked once per compilation, not per call
    for name, x, shape in (("t", t, ()), ("position", position, (3,)), ("quaternion", quaternion, (4,))):
        if jnp.shape(x) != shape:
            raise ValueError(f"tracker update: {name} must have shape {shape}, got {jnp.shape(x)}")
    dtype = state.render[2].dtype
    t = jnp.maximum(jnp.asarray(t, dtype), state.filter.t)  # late measurements: applied now
    position = jnp.asarray(position, dtype)
    quaternion = jnp.asarray(quaternion, dtype)
    was_init = state.filter.initialized
    p_r, v_r, q_r, w_r = _eval_render(state.render, t)
    kf, info = _filter_step(config, state.filter, t, position, quaternion)
    used = info.pos_used | info.rot_used
    h = jnp.asarray(config.horizon, dtype) * _adaptive_factor(config, kf, dtype)
    tc = _SETTLE * h  # time constant of the correction
    t1 = _KNOT * h  # the knot between the two pieces
    # the filter's estimate at t (kf.t == t: its mean, normalised as predict_pose would)
    p_k, q_k, v_k, w_k = _filter_predict(config, kf, t)
    p_1, q_1, v_1, w_1 = _filter_predict(config, kf, t + t1)
    p_T, q_T, v_T, w_T = _filter_predict(config, kf, t + h)
    # first frame: start at the filter's estimate at rest
    z = jnp.zeros(3, dtype)
    fresh = ~was_init
    p_r = jnp.where(fresh, p_k, p_r)
    v_r = jnp.where(fresh, z, v_r)
    q_r = jnp.where(fresh, q_k, q_r)
    w_r = jnp.where(fresh, z, w_r)
    # the correction (rendered minus predicted) decays critically damped; the knot carries it
    a, da, b, db = _settle(jnp.asarray(_KNOT / _SETTLE, dtype))
    dp, dv = p_r - p_k, v_r - v_k
    p_m = p_1 + a * dp + b * tc * dv
    v_m = v_1 + da / tc * dp + db * dv
    dq = quat_mul(q_r, quat_conj(q_k))
    dth = quat_to_rotvec(jnp.where(dq[..., :1] < 0, -dq, dq))  # shortest arc
    dw = w_r - w_k
    q_m = quat_mul(quat_from_rotvec(a * dth + b * tc * dw), q_1)
    w_m = w_1 + da / tc * dth + db * dw
    st = lambda x, y: jnp.stack([x, y])  # noqa: E731
    dur = st(t1, h - t1)
    curve, rot = _segment(st(p_r, p_m), st(v_r, v_m), st(q_r, q_m), st(w_r, w_m),
                          st(p_m, p_T), st(v_m, v_T), st(q_m, q_T), st(w_m, w_T), dur)
    q_end = _rotation_end(q_m, q_T, w_m, w_T, h - t1)
    rebuild = used & kf.initialized
    new = _make_state(config, kf, t, dur, curve, rot, state.started | kf.initialized,
                      (p_T, v_T, q_end, w_T))
    keep = eqx.tree_at(lambda x: x.filter, state, kf)
    return jax.tree.map(lambda a, b: jnp.where(rebuild, a, b), new, keep)


@jax.jit
def tracker_update(
    config: TrackerConfig,
    state: TrackerState,
    t: Float[ArrayLike, ""],
    position: Float[ArrayLike, "3"],
    quaternion: Float[ArrayLike, "4"],
) -> TrackerState:
    """Feed one camera-rate measurement.

    Arguments:
        config: tracker configuration.
        state: current state.
        t: measurement time, s (a time earlier than the filter's is applied at the filter's time).
        position: measured position, m (NaN if missing).
        quaternion: measured orientation wxyz (NaN if missing; sign irrelevant).

    Returns:
        The new state. The next render segment starts at the pose and velocity rendered at
        ``t`` (C1 continuity) and ends at the filter's prediction for ``t + horizon``,
        applying the correction like a critically damped system (see the module docs). A frame
        with no valid part only advances the filter (the stream keeps coasting).
    """
    return _update(config, state, t, position, quaternion)


def tracker_sample(
    config: TrackerConfig, state: TrackerState, t_render: Float[ArrayLike, "*T"]
) -> tuple[Float[Array, "*T 3"], Float[Array, "*T 4"]]:
    """Rendered pose at render time(s) ``t_render >= `` the last update time.

    Arguments:
        config: tracker configuration (kept for symmetry with :func:`tracker_update`; the
            coasting parameters in effect are those of the config of the last update).
        state: current state.
        t_render: render time(s), s, any shape (pass a device array in a render loop to avoid
            a host-to-device conversion per call).

    Returns:
        ``(position, quaternion)`` with shapes ``(*T, 3)`` and ``(*T, 4)``; NaN before the first
        valid measurement.
    """
    # one compiled kernel on the packed render vector (few arguments: low dispatch cost)
    del config  # the coasting parameters were packed at the last update
    return _sample_render(state.render, t_render)


# ---------------------------------------------------------------------------------- batch API
def _prepare_recording(times, positions, quaternions, render_times):
    times = np.asarray(times, np.float64)
    positions = np.asarray(positions, np.float64)
    quaternions = np.asarray(quaternions, np.float64)
    render_times = np.asarray(render_times, np.float64)
    n = times.shape[0] if times.ndim == 1 else -1
    if times.ndim != 1 or positions.shape != (n, 3) or quaternions.shape != (n, 4):
        raise ValueError(
            "expected times (N,), positions (N, 3), quaternions (N, 4); got "
            f"{times.shape}, {positions.shape}, {quaternions.shape}"
        )
    if render_times.ndim != 1:
        raise ValueError(f"render_times must be 1-D, got shape {render_times.shape}")
    if n < 1:
        raise ValueError("need at least one measurement")
    if not np.all(np.isfinite(times)):
        raise ValueError("measurement times must be finite")
    if not np.all(np.isfinite(render_times)):
        raise ValueError("render times must be finite")
    order = np.argsort(times, kind="stable")
    if np.any(order != np.arange(n)):
        warnings.warn("measurement times are not sorted; sorting them", stacklevel=3)
    times, positions, quaternions = times[order], positions[order], quaternions[order]
    dup = np.concatenate([[False], np.diff(times) == 0])
    if np.any(dup):
        warnings.warn(f"dropping {int(dup.sum())} measurement(s) with duplicate timestamps "
                      "(keeping the first)", stacklevel=3)
        times, positions, quaternions = times[~dup], positions[~dup], quaternions[~dup]
    orientation_only = not np.any(np.isfinite(positions))
    if orientation_only:
        # the filter needs a position to initialise: track a fixed point, report NaN positions
        positions = np.where(np.isfinite(quaternions).all(-1, keepdims=True), 0.0, np.nan)
        positions = np.broadcast_to(positions, (times.shape[0], 3)).copy()
    origin = times[0]
    return times - origin, positions, quaternions, render_times - origin, orientation_only


#: compiled versions (recording shapes) kept per batch entry point, see :func:`_bounded_cache`
_MAX_COMPILED_SHAPES = 4
_COMPILED_KEYS: dict = {}


def _bounded_cache(core, key) -> None:
    """Keep at most ``_MAX_COMPILED_SHAPES`` compiled versions of the jitted ``core``.

    Every recording length compiles the whole scan again, and XLA:CPU maps the code of one
    compiled stream into about 1200 memory regions (``/proc/self/maps``, float64 track),
    which are released only with the executable. Linux allows a process 65530 of them
    (``vm.max_map_count``), i.e. about 50 distinct lengths; then mmap fails inside XLA's
    compiler and the process dies (reproduced with the limit lowered to 8000: LLVM "Cannot
    allocate memory", segfault at the sixth length). Before a new shape would exceed the
    bound, ``core``'s compilation cache is cleared.
    """
    keys = _COMPILED_KEYS.setdefault(core, set())
    if key not in keys and max(len(keys), core._cache_size()) >= _MAX_COMPILED_SHAPES:
        core.clear_cache()
        keys.clear()
    keys.add(key)


def _run_recording(core, config, times, positions, quaternions, render_times, dtype):
    """Validate and normalise a recording (outside jit), run a jitted ``core`` on it."""
    t, p, q, r, orientation_only = _prepare_recording(times, positions, quaternions, render_times)
    dtype = jnp.zeros((), float).dtype if dtype is None else dtype
    args = [jnp.asarray(x, dtype) for x in (t, p, q, r)]
    _bounded_cache(core, (jax.tree.structure(config), tuple(a.shape for a in args), args[0].dtype))
    out_p, out_q = core(config, *args)
    if orientation_only:
        out_p = jnp.full_like(out_p, jnp.nan)
    return out_p, out_q


@jax.jit
def _track_core(config, times, positions, quaternions, render_times):
    config = TrackerConfig() if config is None else config
    dtype = times.dtype
    state0 = tracker_init(config, times[0], dtype)

    def body(state, meas):
        t, p, q = meas
        new = _update(config, state, t, p, q)
        return new, new.render  # only what a render sample reads is stacked and gathered

    _, renders = jax.lax.scan(body, state0, (times, positions, quaternions))
    sel, before = _latest_states(times, renders, render_times)
    p, _, q, _ = jax.vmap(lambda r, tau: _eval_render(r, tau, velocities=False))(sel, render_times)
    nan = jnp.where(before, jnp.nan, 0.0)[:, None].astype(dtype)
    return p + nan, q + nan


def _latest_states(times, states, render_times):
    """For each render time the stacked state of the last measurement with ``t <= tau``
    (causal), and whether ``tau`` precedes every measurement."""
    idx = jnp.searchsorted(times, render_times, side="right") - 1
    return jax.tree.map(lambda x: x[jnp.maximum(idx, 0)], states), idx < 0


def track(
    times: Float[ArrayLike, "*B N"],
    positions: Float[ArrayLike, "*B N 3"],
    quaternions: Float[ArrayLike, "*B N 4"],
    render_times: Float[ArrayLike, "*B M"],
    *,
    config: TrackerConfig | None = None,
    dtype=None,
) -> tuple[Float[Array, "*B M 3"], Float[Array, "*B M 4"]]:
    """Causal render-rate stream over a whole recording (one ``lax.scan``), or a batch of them.

    Equivalent to calling :func:`tracker_update` for each measurement and
    :func:`tracker_sample` at each render time: the output at ``tau`` uses only measurements
    with ``t <= tau``. Each new pair of lengths ``(N, M)`` (batch shape included) compiles the
    scan (seconds); at most four shapes stay compiled (more would exhaust the process's memory
    mappings, see ``_bounded_cache``).

    **Batches** (leading axes ``B``, one compiled program for the whole batch): recordings
    NaN-padded to a common length ``N`` (:func:`phjax.batch.pad_recordings`). Padding rule: a
    NaN time is a padding frame, counted as a lost frame after the recording's end (padding
    must follow every real frame); a NaN render time gives a NaN sample; ``render_times`` may
    be ``(M,)``, shared by every recording. Each recording gets its one-recording result. In a
    batch, times must already be strictly increasing (an error, not a warning). Inputs sharded
    along axis 0 (:func:`phjax.batch.shard_batch`) run on each device's part of the batch and
    the outputs come back sharded the same way.

    Arguments:
        times: measurement times, s (one recording: sorted and de-duplicated here with a
            warning if needed; internally relative to the first time, so absolute epoch times
            are fine).
        positions: measured positions, m; NaN rows are missing frames. If every position is
            NaN (orientation-only data) the orientation is tracked and positions are NaN.
        quaternions: measured orientations wxyz; NaN rows are missing frames.
        render_times: times at which to render, s (any order).
        config: tracker configuration (default :class:`TrackerConfig()`), shared by the batch.
        dtype: computation dtype (default: JAX's default float; pass ``jnp.float64`` with x64
            enabled for double precision).

    Returns:
        ``(positions (*B, M, 3), quaternions (*B, M, 4))``; NaN before the first valid
        measurement (and at padded render times).
    """
    if jnp.ndim(times) > 1:
        return run_batch("track", config, times, positions, quaternions, render_times, dtype)
    return _run_recording(_track_core, config, times, positions, quaternions, render_times, dtype)


@jax.jit
def _reconstruct_core(config, times, positions, quaternions, render_times):
    config = TrackerConfig() if config is None else config
    dtype = times.dtype
    filtered, _ = kalman_filter(config.kalman, times, positions, quaternions)
    sm = rts_smooth(config.kalman, filtered)
    p = sm.x[:, :3]
    v = sm.x[:, 3:6]
    q = quat_normalize(sm.q)
    w = sm.w
    ok = sm.initialized
    n = times.shape[0]
    if n == 1:
        pr = jnp.broadcast_to(p[0], render_times.shape + (3,))
        qr = jnp.broadcast_to(q[0], render_times.shape + (4,))
        nan = jnp.where(ok[0], 0.0, jnp.nan).astype(dtype)
        return pr + nan, qr + nan
    dt = jnp.diff(times)
    curves, rots = _segment(p[:-1], v[:-1], q[:-1], w[:-1], p[1:], v[1:], q[1:], w[1:], dt)
    first = jnp.argmax(ok)
    tau = jnp.maximum(render_times, times[first])
    idx = jnp.clip(jnp.searchsorted(times, tau, side="right") - 1, 0, n - 2)
    s = jnp.clip((tau - times[idx]) / dt[idx], 0, 1)
    cs = jax.tree.map(lambda x: x[idx], curves)
    rs = jax.tree.map(lambda x: x[idx], rots)
    pr = jax.vmap(lambda c, x: c.position(x))(cs, s)
    qr = jax.vmap(lambda c, x: c.rotation(x))(rs, s)
    nan = jnp.where(jnp.any(ok), 0.0, jnp.nan).astype(dtype)
    return pr + nan, qr + nan


def reconstruct(
    times: Float[ArrayLike, "*B N"],
    positions: Float[ArrayLike, "*B N 3"],
    quaternions: Float[ArrayLike, "*B N 4"],
    render_times: Float[ArrayLike, "*B M"],
    *,
    config: TrackerConfig | None = None,
    dtype=None,
) -> tuple[Float[Array, "*B M 3"], Float[Array, "*B M 4"]]:
    """Offline reconstruction: RTS-smoothed states joined by C1 PH quintic / quaternion segments.

    Not causal (uses the whole recording). Same arguments, conventions, batches (NaN padding
    rule) and sharding as :func:`track`; render times outside the measurement span hold the
    end poses (before the first valid measurement: its pose; after the last real frame of a
    padded recording: its pose).

    Returns:
        ``(positions (*B, M, 3), quaternions (*B, M, 4))``.
    """
    if jnp.ndim(times) > 1:
        return run_batch("reconstruct", config, times, positions, quaternions, render_times, dtype)
    return _run_recording(_reconstruct_core, config, times, positions, quaternions, render_times, dtype)
