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
loop can use :class:`phjax.TrackerStream` (a thin stateful wrapper of these two functions)
and, on a CPU, gets the lowest latency with JAX's asynchronous dispatch turned off at program
start (``jax.config.update("jax_cpu_enable_async_dispatch", False)``):
for calls this short the hand-off to a worker thread costs more than the computation (see
``benchmarks/bench_tracker.py``). Calling the pure functions directly, pass a config converted
once with :func:`tracker_config_arrays`.
Batch API: :func:`track` runs the causal stream over a recording in one ``lax.scan`` (the output
at render time ``tau`` depends only on measurements with ``t <= tau``), and :func:`reconstruct`
the offline version (RTS-smoothed states joined by PH quintic / C1 quaternion segments; gaps
longer than ``coast_time + stop_time`` bridged by coasting in from both sides). Both
also take NaN-padded batches of recordings, sharded over devices or not
(:mod:`phjax.tracking._batch`, padding rule in :mod:`phjax.batch`).

Conventions: times in seconds, positions in metres, quaternions wxyz, angular velocities in
rad/s in the world frame. Render times before the first valid measurement give NaN in the
causal stream (:func:`track`, :func:`tracker_sample`); :func:`reconstruct` holds the first
valid pose there.
"""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._jit import jit
from .._misc import FINITE, POSITIVE, any_traced, check_number_fields, filter_scan
from .._np_quat import np_valid_quaternions
from ..io import TrajectoryWarning
from .._sizes import unpad_rows
from . import _exported
from ._batch import run_batch
from ._config_ranges import out_of_range, range_message
from ._noise_core import NoiseMonitor, noise_monitor_init, noise_monitor_push, noise_monitor_std
from ._shapes import bounded_cache, pad_recording
from .imm import IMMConfig, imm_init, imm_predict_pose, imm_step, imm_uninitialized
from .kalman import (
    KalmanConfig,
    KalmanState,
    kalman_filter,
    kalman_init,
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
    quat_slerp,
    quat_to_rotvec,
)

__all__ = [
    "TrackerConfig",
    "TrackerState",
    "RenderSegment",
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
        rotation_horizon: the orientation's own settling time, s, or ``None`` (default) for
            ``horizon``. Position and orientation are independent streams (with ``adapt``
            nonzero both horizons take the same factor), so each can be as smooth as it
            needs: ``experiments/display_frontier.py`` chooses the two horizons by one rule,
            channel by channel, as the baselines' knobs are. Differentiable when set.
        adapt: adaptive settling (IMM only): each segment's horizon is
            ``horizon * exp(adapt (1 - 2 m))``, where ``m`` in [0, 1] is the expected mode index
            of the IMM (0: the quietest model certain, 1: the most agile one), averaged over
            position and orientation: longer, heavier smoothing for a still head, shorter
            settling in fast turns. Default 0 (fixed horizon).
        coast_time: after a segment ends without a new frame, keep moving with the end
            velocities for this long, s (default 0.1).
        stop_time: then let the velocities decay with this time constant, s (default 0.05).
        lookahead: display-time prediction, s (default 0): the pose rendered at time ``t`` is
            the one predicted for ``t + lookahead``, the moment the frame reaches the eye. Set
            it to the display's motion-to-photon latency minus what the consuming runtime
            already predicts (a VR runtime that predicts to its own display time needs 0; a
            renderer that draws the pose as received, 20-50 ms). The whole stream is shifted:
            each segment starts at the pose rendered at the camera frame and settles on the
            filter's prediction for ``t_k + lookahead + horizon``, so the stream stays C1 and
            coasts and stops as before. Differentiable like the other fields.
        noise_window: online measurement-noise floor (static; default 0: off). With ``n > 0``
            the causal stream measures the white noise of the measurements as it goes: the
            residuals of :func:`phjax.tracking.estimate_measurement_noise` (third divided
            differences of four consecutive frames), their mean square over about the last
            ``n`` (a running mean, then an exponential one), each clipped at three estimated
            stds so that a misaligned frame or a burst of motion moves it little. Each filter
            step uses the larger of that estimate and the configured ``pos_meas_noise`` /
            ``rot_meas_noise`` (once ``max(8, n // 4)`` residuals have been seen; the state
            depends on it: :func:`tracker_init` with this config). For sources whose noise is unknown
            (a webcam, another tracker): with a sensor noisier than configured the IMM takes
            the noise for manoeuvres and follows it (``experiments/sensitivity.py``). A
            floor, not a replacement: the estimate counts only the white part of the noise
            (a SLAM estimate's correlated error is not), so a configured value is never
            lowered; set it lower yourself for a precise sensor. 60 (2 s at 30 Hz) is a good
            value.
        reacquire: re-acquisition after a long loss (static; default ``False``). With
            ``True`` the first frame after the stream has stopped (more than ``coast_time +
            stop_time`` of the segment being rendered past its end, the gap
            :func:`reconstruct` bridges as a loss) starts the stream again at the filter's estimate at rest, as the first
            frame does: one jump to the re-acquired pose. By default the stream glides there
            from where it came to rest within one horizon (C1, no jump): after a 0.97 s loss
            of a walking head (TUM VI room2) that glide has 874, 526 and 152 mm of error in
            its first three 120 Hz samples, which doubles the recording's RMSE; in a 3 s face
            loss of the live test the jump is 5.6 cm where the glide moves at most 0.43 cm
            per sample. A choice between accuracy and continuity.
    """

    kalman: KalmanConfig = eqx.field(default_factory=KalmanConfig)
    imm: IMMConfig | None = eqx.field(default_factory=IMMConfig)
    horizon: float = 0.028
    rotation_horizon: float | None = None
    adapt: float = 0.0
    coast_time: float = 0.1
    stop_time: float = 0.05
    lookahead: float = 0.0
    noise_window: int = eqx.field(default=0, static=True)
    reacquire: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        # concrete values only (a traced config, e.g. inside jax.grad, is the caller's to keep
        # valid); a horizon or stop time of 0 divides by zero: NaN poses, not an error
        if self.rotation_horizon is not None:
            check_number_fields(self, (("rotation_horizon", *POSITIVE),))
        check_number_fields(self, (("horizon", *POSITIVE), ("stop_time", *POSITIVE),
                                   ("coast_time", lambda x: x >= 0, " >= 0"),
                                   ("adapt", *FINITE), ("lookahead", *FINITE)))
        if (not isinstance(self.noise_window, (int, np.integer)) or isinstance(
                self.noise_window, bool) or not (self.noise_window == 0 or self.noise_window >= 8)):
            raise ValueError("TrackerConfig.noise_window must be an integer, 0 (off) or >= 8 "
                             f"(residual windows), got {self.noise_window!r}")
        if not isinstance(self.reacquire, (bool, np.bool_)):
            raise ValueError(f"TrackerConfig.reacquire must be True or False, got "
                             f"{self.reacquire!r}")


def _noise_min_count(config: TrackerConfig) -> int:
    """Residual windows the online noise floor needs before it is used."""
    return max(8, config.noise_window // 4)


#: The correction ``c(t)`` = rendered minus predicted pose decays like a critically damped
#: second-order system, ``c(t) = (c0 (1 + s) + c0' t) exp(-s)`` with ``s = t / T``; the time
#: constant is ``T = _SETTLE * horizon`` and the two pieces join at ``_KNOT * horizon``.
_SETTLE = 0.2
_KNOT = 0.4


class RenderSegment(eqx.Module):
    """Everything a render sample needs: the current segment and how to coast past its end.

    The curves are functions of *display time*: the pose rendered at time ``tau`` is the
    curves' pose at ``tau + lookahead``.

    Fields:
        started: whether a valid measurement has been seen (before that samples are NaN).
        start: ``(2, 2)`` start times of the segment's two pieces (display time), s, for
            position (row 0) and orientation (row 1): the channels settle on their own
            horizons (:attr:`TrackerConfig.rotation_horizon`).
        p_duration: ``(2,)`` durations of the two position pieces, s.
        curve: the two position pieces, a :class:`PHQuintic` batch of 2, each on its own
            parameter ``s = (t - start[0]) / p_duration``.
        rotation: the two orientation pieces, a :class:`QuaternionHermite` batch of 2 (its
            ``duration`` field holds the pieces' durations, s).
        p_end, v_end, q_end, w_end: end pose and velocities of the second piece (``q_end`` with
            the sign of its ``rotation(1)``); past the end the pose coasts from them.
        coast_time, stop_time, lookahead: those of the config of the last update, s.
    """

    started: Bool[Array, ""]
    start: Float[Array, "2 2"]
    p_duration: Float[Array, "2"]
    curve: PHQuintic
    rotation: QuaternionHermite
    p_end: Float[Array, "3"]
    v_end: Float[Array, "3"]
    q_end: Float[Array, "4"]
    w_end: Float[Array, "3"]
    coast_time: Float[Array, ""]
    stop_time: Float[Array, ""]
    lookahead: Float[Array, ""]

    @property
    def end(self) -> Float[Array, "2"]:
        """End times of the segment's position and orientation (of their second pieces,
        display time), s."""
        return self.start[:, 1] + jnp.stack([self.p_duration[1], self.rotation.duration[1]])

    def evaluate(self, tau: Float[ArrayLike, ""], velocities: bool = True):
        """Rendered pose at one render time ``tau``: the curves' pose at ``tau + lookahead``.

        Inside the segment the piece that covers ``tau`` (the second from its start on) is
        evaluated; past the end the pose moves with the end velocities for ``coast_time``, then
        the velocities decay with time constant ``stop_time`` (C1), so the pose comes to rest.

        Arguments:
            tau: render time, s (a scalar; ``jax.vmap`` for several), at or after the last
                update.
            velocities: also return the velocities (else ``None`` in their places).

        Returns:
            ``(position (3,), velocity (3,), quaternion (4,), angular velocity (3,))``, the
            angular velocity in the world frame, rad/s; NaN before the first valid measurement.
        """
        dtype = self.start.dtype
        tau = jnp.asarray(tau, dtype) + self.lookahead
        # the piece of each channel that covers tau (the second from its start on)
        i = (tau >= self.start[:, 1]).astype(jnp.int32)
        start = self.start[jnp.arange(2), i]
        curve = jax.tree.map(lambda x: x[i[0]], self.curve)
        rotation = jax.tree.map(lambda x: x[i[1]], self.rotation)
        dur_p = self.p_duration[i[0]]
        s_p = jnp.clip((tau - start[0]) / dur_p, 0, 1)
        s_r = jnp.clip((tau - start[1]) / rotation.duration, 0, 1)
        # past the end: coast, then come to rest smoothly (each channel from its own end)
        end = self.end
        delta = jnp.maximum(tau - end, 0)
        disp, factor = _coast(delta, self.coast_time, self.stop_time)
        inside = tau <= end
        nan = jnp.where(self.started, 0.0, jnp.nan).astype(dtype)
        p = jnp.where(inside[0], curve.position(s_p), self.p_end + disp[0] * self.v_end) + nan
        q_coast = quat_mul(quat_from_rotvec(disp[1] * self.w_end), self.q_end)
        q = jnp.where(inside[1], rotation.rotation(s_r), q_coast) + nan
        if not velocities:
            return p, None, q, None
        v = jnp.where(inside[0], curve.hodograph(s_p) / dur_p, factor[0] * self.v_end) + nan
        w = jnp.where(inside[1], rotation.angular_velocity(s_r), factor[1] * self.w_end) + nan
        return p, v, q, w


def _coast(delta, coast_time, stop_time):
    """Coasting after the last state, ``delta >= 0`` seconds on: the distance travelled in
    units of the end velocity (``delta`` for ``coast_time``, then ``stop_time (1 - decay)``)
    and the velocity factor (1, then ``decay = exp(-(delta - coast_time) / stop_time)``)."""
    decay = jnp.exp(-jnp.maximum(delta - coast_time, 0) / stop_time)
    disp = jnp.minimum(delta, coast_time) + stop_time * (1 - decay)
    return disp, jnp.where(delta > coast_time, decay, 1.0)


def _bridge(p_a, v_a, q_a, w_a, p_b, v_b, q_b, w_b, delta, dt, coast_time, stop_time):
    """The offline pose ``delta`` seconds into a gap of ``dt`` seconds between two states: each
    side coasts into the gap as the causal stream does (:func:`_coast`; backwards from the
    later state) and a smoothstep ``3 u^2 - 2 u^3`` of ``u = delta / dt`` blends the two
    (slerp for orientation). Position and velocity equal the states' at both ends (C1), and
    neither side moves further than ``coast_time + stop_time`` times its velocity."""
    d_a = _coast(delta, coast_time, stop_time)[0][..., None]
    d_b = _coast(dt - delta, coast_time, stop_time)[0][..., None]
    u = jnp.clip(delta / dt, 0, 1)
    blend = u * u * (3 - 2 * u)
    from_a = p_a + d_a * v_a
    from_b = p_b - d_b * v_b
    q_from_a = quat_mul(quat_from_rotvec(d_a * w_a), q_a)
    q_from_b = quat_mul(quat_from_rotvec(-d_b * w_b), q_b)
    return from_a + blend[..., None] * (from_b - from_a), quat_slerp(q_from_a, q_from_b, blend)


class TrackerState(eqx.Module):
    """State of the streaming tracker (a PyTree of arrays).

    Fields:
        filter: the Kalman (or IMM) filter state.
        segment: the render segment (:class:`RenderSegment`): all a render sample reads.
        noise: the online noise estimate (``TrackerConfig.noise_window > 0``), else ``None``.

    Properties (views): ``t0``, the render time of the last segment start (the last camera
    frame used), s; ``started``, whether a valid measurement has been seen (before that samples are
    NaN); ``duration`` (2, 2), the durations of the segment's two pieces, s, for position
    (row 0) and orientation (row 1);
    ``curve``, the two position pieces (a :class:`PHQuintic` batch of 2), each on its own
    parameter ``(t - start[0]) / duration[0]``; ``rotation``, the two orientation pieces (a
    :class:`QuaternionHermite` batch of 2).
    """

    filter: KalmanState
    segment: RenderSegment
    noise: NoiseMonitor | None = None

    @property
    def t0(self) -> Float[Array, ""]:
        return self.segment.start[0, 0] - self.segment.lookahead

    @property
    def started(self) -> Bool[Array, ""]:
        return self.segment.started

    @property
    def duration(self) -> Float[Array, "2 2"]:
        return jnp.stack([self.segment.p_duration, self.segment.rotation.duration])

    @property
    def curve(self) -> PHQuintic:
        return self.segment.curve

    @property
    def rotation(self) -> QuaternionHermite:
        return self.segment.rotation


def _make_state(config, kf, t0, duration, curve, rotation, started, ends, noise) -> TrackerState:
    """A :class:`TrackerState` whose segment starts at ``t0`` with two pieces per channel of
    ``duration`` (2, 2) (position, orientation).

    ``ends = (p_end, v_end, q_end, w_end)``: the end pose and velocities of the second piece,
    i.e. the Hermite data it was built from (``q_end`` with the sign of its ``rotation(1)``).
    """
    dtype = t0.dtype
    p_end, v_end, q_end, w_end = ends
    segment = RenderSegment(
        started=jnp.asarray(started), start=jnp.stack([jnp.full((2,), t0), t0 + duration[:, 0]],
                                                       axis=1),
        p_duration=duration[0], curve=curve,
        rotation=rotation, p_end=p_end, v_end=v_end, q_end=q_end, w_end=w_end,
        coast_time=jnp.asarray(config.coast_time, dtype),
        stop_time=jnp.asarray(config.stop_time, dtype),
        lookahead=jnp.asarray(config.lookahead, dtype))
    return TrackerState(kf, segment, noise)


def _segment(p0, v0, q0, w0, p1, v1, q1, w1, duration, rot_duration=None):
    """Position and orientation pieces of ``duration`` (the orientation's ``rot_duration``,
    default the same)."""
    dur = jnp.asarray(duration)[..., None]
    curve = hermite_quintic(p0, p1, v0 * dur, v1 * dur)
    rot = quaternion_hermite(q0, q1, w0, w1, duration if rot_duration is None else rot_duration)
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
    return _init(config, jnp.asarray(t, _float_dtype(dtype)))


@jit
def _init(config: TrackerConfig, t) -> TrackerState:
    """:func:`tracker_init` as one compiled program (run eagerly, its operations were compiled
    one by one: 85 compilations before a stream's first update)."""
    dtype = t.dtype
    kf = _filter_uninitialized(config, t, dtype)
    # a head at rest at the origin, written down rather than built by hermite_quintic (whose
    # ~80 kernels would be compiled into every program that starts a stream): the zero
    # quaternion polynomial is the still PH quintic, zero increments the constant rotation
    z3 = jnp.zeros((2, 3), dtype)
    z4 = jnp.zeros((2, 4), dtype)
    q = jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], dtype), (2, 4))
    dur = jnp.full((2, 2), 0.5, dtype)
    curve = PHQuintic(A0=z4, A1=z4, A2=z4, control_points=jnp.zeros((2, 6, 3), dtype))
    rot = QuaternionHermite(q0=q, w1=z3, w2=z3, w3=z3, duration=dur[1])
    noise = noise_monitor_init(dtype) if config.noise_window else None
    return _make_state(config, kf, t, dur, curve, rot, jnp.asarray(False),
                       (z3[0], z3[0], q[0], z3[0]), noise)


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


def _sample(segment: RenderSegment, t_render):
    """Pose of ``segment`` at render times of any shape (NaN before the first measurement)."""
    tau = jnp.asarray(t_render, segment.start.dtype)
    p, _, q, _ = jax.vmap(lambda x: segment.evaluate(x, velocities=False))(tau.reshape(-1))
    return p.reshape(tau.shape + (3,)), q.reshape(tau.shape + (4,))


_sample_render = jit(_sample)


def _filter_uninitialized(config: TrackerConfig, t, dtype):
    """The chosen filter's empty state (single-model Kalman or IMM)."""
    if config.imm is None:
        return kalman_uninitialized(config.kalman, t, dtype)
    return imm_uninitialized(config.imm, t, dtype)


#: the filter state's fields of each part (Kalman and IMM states name them alike)
_PART_FIELDS = (("x", "P", "pos_log_mu"), ("q", "w", "Pr", "rot_log_mu"))


def _filter_restart_part(config: TrackerConfig, state, part: int, position, quaternion):
    """``state`` with one part (0: position, 1: orientation) started again from a measurement
    of it (at rest, initial covariance, uniform IMM mode probabilities); the other part and
    the times unchanged. ``position`` / ``quaternion``: the measurement (only ``part``'s is
    read)."""
    dtype = state.t.dtype
    position = jnp.asarray(position, dtype) if part == 0 else jnp.zeros(3, dtype)
    quaternion = (jnp.asarray(quaternion, dtype) if part == 1
                  else jnp.asarray([1, 0, 0, 0], dtype))
    if config.imm is None:
        fresh = kalman_init(config.kalman, state.t, position, quaternion)
    else:
        fresh = imm_init(config.imm, state.t, position, quaternion)
    names = [n for n in _PART_FIELDS[part] if hasattr(state, n)]
    keep = [getattr(state, n) for n in names]
    new = [jnp.where(fresh.initialized, getattr(fresh, n), k) for n, k in zip(names, keep)]
    return eqx.tree_at(lambda s: [getattr(s, n) for n in names], state, new)


def _stream_filter(config: TrackerConfig) -> KalmanConfig | IMMConfig:
    """The config of the filter the causal stream runs: the IMM's, or the single model's."""
    return config.kalman if config.imm is None else config.imm


def _noise_floor(config: TrackerConfig, noise: NoiseMonitor) -> TrackerConfig:
    """``config`` whose filter (the one the stream runs) has measurement noise no lower than
    the monitor's estimate."""
    pos, rot = noise_monitor_std(noise, _noise_min_count(config))
    filt = _stream_filter(config)
    filt = dataclasses.replace(
        filt, pos_meas_noise=jnp.maximum(jnp.asarray(filt.pos_meas_noise, pos.dtype), pos),
        rot_meas_noise=jnp.maximum(jnp.asarray(filt.rot_meas_noise, rot.dtype), rot))
    if config.imm is None:
        return dataclasses.replace(config, kalman=filt)
    return dataclasses.replace(config, imm=filt)


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


def _horizons(config: TrackerConfig, dtype) -> Float[Array, "2"]:
    """The configured horizons of position and orientation, s."""
    rot = config.horizon if config.rotation_horizon is None else config.rotation_horizon
    return jnp.stack([jnp.asarray(config.horizon, dtype), jnp.asarray(rot, dtype)])


def _settle(s):
    """Critically damped decay at ``s`` time constants: weights of the initial offset and of
    the initial rate (per time constant) and their derivatives (per time constant)."""
    e = jnp.exp(-s)
    return (1 + s) * e, -s * e, s * e, (1 - s) * e


def _update(config: TrackerConfig, state: TrackerState, t, position, quaternion, t_render=None):
    """:func:`tracker_update`; ``t_render`` (default ``t``): the time the new render segment
    starts, later than ``t`` for a measurement that arrives late (``phjax.live.LiveStream``).
    The filter runs at ``t`` and the segment is built from its predictions; the first
    measurement starts its segment at ``t`` (nothing was rendered before it)."""
    # shapes are static: checked once per compilation, not per call
    for name, x, shape in (("t", t, ()), ("position", position, (3,)), ("quaternion", quaternion, (4,))):
        if jnp.shape(x) != shape:
            raise ValueError(f"tracker update: {name} must have shape {shape}, got {jnp.shape(x)}")
    dtype = state.segment.start.dtype
    t = jnp.maximum(jnp.asarray(t, dtype), state.filter.t)  # late measurements: applied now
    position = jnp.asarray(position, dtype)
    quaternion = jnp.asarray(quaternion, dtype)
    was_init = state.filter.initialized
    if t_render is not None:
        t_render = jnp.where(was_init, jnp.maximum(jnp.asarray(t_render, dtype), t), t)
    else:
        t_render = t
    p_r, v_r, q_r, w_r = state.segment.evaluate(t_render)  # the pose shown at t_render
    noise = state.noise
    if (noise is None) != (config.noise_window == 0):
        raise ValueError(
            f"tracker update: the state was made for another TrackerConfig.noise_window (the "
            f"config has {config.noise_window}, the state {'no' if noise is None else 'a'} "
            "noise monitor); start it with tracker_init(config)")
    filter_config = config
    if noise is not None:  # the online noise floor (TrackerConfig.noise_window)
        filt = _stream_filter(config)
        noise = noise_monitor_push(noise, config.noise_window, t, position, quaternion,
                                   filt.pos_meas_noise, filt.rot_meas_noise)
        filter_config = _noise_floor(config, noise)
    kf, info = _filter_step(filter_config, state.filter, t, position, quaternion)
    u = t_render + jnp.asarray(config.lookahead, dtype)  # the display time of that pose
    used = info.pos_used | info.rot_used
    # the horizons of position and orientation
    h = _horizons(config, dtype) * _adaptive_factor(config, kf, dtype)
    tc = _SETTLE * h  # time constants of the corrections
    t1 = _KNOT * h  # the knots between the two pieces
    # the filter's predictions for the display time u (its mean when the lookahead is 0), the
    # knots and the ends (the same instants for both channels with one horizon)
    times = jnp.stack([u, u + t1[0], u + h[0], u + t1[1], u + h[1]])
    if config.rotation_horizon is None:
        times = times[:3]
    pred = jax.vmap(lambda tau: _filter_predict(config, kf, tau))(times)
    rot = jnp.array([0, -2, -1])  # orientation: the first instant and its own knot and end
    (p_k, p_1, p_T), (v_k, v_1, v_T) = pred[0][:3], pred[2][:3]
    (q_k, q_1, q_T), (w_k, w_1, w_T) = pred[1][rot], pred[3][rot]
    # first frame (and, with config.reacquire, the first after the stream has stopped): start
    # at the filter's estimate at rest
    z = jnp.zeros(3, dtype)
    fresh = ~was_init
    if config.reacquire:  # stopped: past the coasting of the segment as it was rendered
        rest = state.segment.coast_time + state.segment.stop_time
        fresh = fresh | (u - jnp.max(state.segment.end) > rest)
    p_r = jnp.where(fresh, p_k, p_r)
    v_r = jnp.where(fresh, z, v_r)
    q_r = jnp.where(fresh, q_k, q_r)
    w_r = jnp.where(fresh, z, w_r)
    # the correction (rendered minus predicted) decays critically damped; the knot carries it
    a, da, b, db = _settle(jnp.asarray(_KNOT / _SETTLE, dtype))
    dp, dv = p_r - p_k, v_r - v_k
    p_m = p_1 + a * dp + b * tc[0] * dv
    v_m = v_1 + da / tc[0] * dp + db * dv
    dq = quat_mul(q_r, quat_conj(q_k))
    dth = quat_to_rotvec(jnp.where(dq[..., :1] < 0, -dq, dq))  # shortest arc
    dw = w_r - w_k
    q_m = quat_mul(quat_from_rotvec(a * dth + b * tc[1] * dw), q_1)
    w_m = w_1 + da / tc[1] * dth + db * dw
    st = lambda x, y: jnp.stack([x, y])  # noqa: E731
    dur = jnp.stack([t1, h - t1], axis=1)  # (channel, piece)
    curve, rot = _segment(st(p_r, p_m), st(v_r, v_m), st(q_r, q_m), st(w_r, w_m),
                          st(p_m, p_T), st(v_m, v_T), st(q_m, q_T), st(w_m, w_T), dur[0], dur[1])
    q_end = _rotation_end(q_m, q_T, w_m, w_T, dur[1, 1])
    rebuild = used & kf.initialized
    new = _make_state(config, kf, u, dur, curve, rot, state.started | kf.initialized,
                      (p_T, v_T, q_end, w_T), noise)
    keep = dataclasses.replace(state, filter=kf, noise=noise)
    return jax.tree.map(lambda a, b: jnp.where(rebuild, a, b), new, keep)


@jit
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
        ``t`` (C1 continuity) and ends at the filter's prediction for
        ``t + lookahead + horizon`` (the horizon adapted when ``adapt != 0``),
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
    del config  # the coasting parameters in effect are stored in the segment
    return _sample_render(state.segment, t_render)


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
        warnings.warn("measurement times are not sorted; sorting them", TrajectoryWarning,
                      stacklevel=3)
    times, positions, quaternions = times[order], positions[order], quaternions[order]
    dup = np.concatenate([[False], np.diff(times) == 0])
    if np.any(dup):
        warnings.warn(f"dropping {int(dup.sum())} measurement(s) with duplicate timestamps "
                      "(keeping the first)", TrajectoryWarning, stacklevel=3)
        times, positions, quaternions = times[~dup], positions[~dup], quaternions[~dup]
    # quaternions of any norm: those far from unit scaled (host side, float64) so that their
    # squares neither underflow nor overflow in float32 (a norm of 1e-19 made every output NaN)
    q_ok = np_valid_quaternions(quaternions)
    big = np.max(np.abs(np.where(q_ok[:, None], quaternions, 1.0)), -1, keepdims=True)
    far = (big < 1e-6) | (big > 1e6)
    quaternions = np.where(far, quaternions / big, quaternions)
    _warn_unused_parts(times, positions, quaternions)
    positions, quaternions, one_part = complete_one_part(positions, quaternions)
    origin = times[0]
    return times - origin, positions, quaternions, render_times - origin, one_part


def _warn_unused_parts(times, positions, quaternions) -> None:
    """A :class:`~phjax.io.TrajectoryWarning` for measurements the filters cannot use: they
    start from the first whole pose (position and orientation both measured; a recording that
    measures only one part is tracked as such, see :func:`complete_one_part`), so one-part rows
    before it are lost, and a recording whose rows each hold only one part gives all NaN."""
    p_ok = np.isfinite(positions).all(-1)
    q_ok = np_valid_quaternions(quaternions)
    if not (p_ok.any() and q_ok.any()):
        if not (p_ok.any() or q_ok.any()):
            warnings.warn("no measurement holds a valid position or orientation: the output "
                          "is all NaN", TrajectoryWarning, stacklevel=4)
        return  # one part alone: tracked as such
    whole = p_ok & q_ok
    if not whole.any():
        warnings.warn(
            f"no measurement holds both a position and an orientation "
            f"({int(p_ok.sum())} position-only, {int(q_ok.sum())} orientation-only): the "
            "filters start from a whole pose, so the output is all NaN (merge the parts into "
            "one row per time, or give one part alone)", TrajectoryWarning, stacklevel=4)
        return
    first = int(np.argmax(whole))
    early = int(np.count_nonzero(p_ok[:first] | q_ok[:first]))
    if early:
        warnings.warn(
            f"{early} one-part measurement(s) before the first whole pose (position and "
            f"orientation both measured, {times[first] - times[0]:.3g} s after the first "
            "measurement) are not used: the filters start from a whole pose",
            TrajectoryWarning, stacklevel=4)


def complete_one_part(positions: np.ndarray, quaternions: np.ndarray):
    """One-part data made whole for the filter, which initialises from a whole pose: with no
    measured position, a fixed point where the orientation is measured; with no measured
    orientation, the identity where the position is (NumPy, host side).

    Returns:
        ``(positions, quaternions, (orientation_only, position_only))``; the caller reports
        the missing part as NaN.
    """
    p_ok = np.isfinite(positions).all(-1, keepdims=True)
    q_ok = np_valid_quaternions(quaternions)[:, None]
    orientation_only = not np.any(p_ok)
    position_only = not orientation_only and not np.any(q_ok)
    if orientation_only:
        positions = np.broadcast_to(np.where(q_ok, 0.0, np.nan), positions.shape).copy()
    if position_only:
        quaternions = np.where(p_ok, np.array([1.0, 0.0, 0.0, 0.0]), np.nan)
    return positions, quaternions, (orientation_only, position_only)


def check_config(config) -> TrackerConfig:
    """``TypeError`` (outside jit) unless ``config`` is a :class:`TrackerConfig` or ``None``;
    ``ValueError`` naming the first concrete field outside its range
    (:data:`phjax.tracking.tuning.CONFIG_RANGES`, the ranges of configuration files),
    beyond which the stream gives NaN poses (a measurement std of 1e30 m did, silently).

    Returns:
        ``config``, or ``TrackerConfig()`` for ``None`` (passed to the jitted cores as
        arguments like any other configuration: one program for the default and for every
        configuration of the same structure, tuned values or another horizon).
    """
    if config is not None and not isinstance(config, TrackerConfig):
        hint = (" (phjax.tracking.tuning.config_from_dict reads one from a dict)"
                if isinstance(config, dict) else "")
        raise TypeError(f"config must be a phjax.TrackerConfig{hint}, got "
                        f"{type(config).__name__}")
    if config is None:
        return TrackerConfig()
    bad = out_of_range(config)
    if bad:
        field, key, value = bad[0]
        raise ValueError("TrackerConfig." + range_message(field.removeprefix("tracker."), key,
                                                          value))
    return config


def _run_traced(core, config, times, positions, quaternions, render_times, dtype):
    """``track`` / ``reconstruct`` inside a JAX transformation: the recording(s) as given, with
    no host-side sorting, de-duplication, padding or checks (times must be finite and strictly
    increasing; one-part data is not completed), through the same jitted core, vmapped over
    the batch axes; times relative to each recording's first."""
    dtype = _float_dtype(dtype)
    t, p, q, r = (jnp.asarray(x, dtype) for x in (times, positions, quaternions, render_times))
    batch = t.shape[:-1]
    r = jnp.broadcast_to(r, batch + r.shape[-1:])

    def one(t, p, q, r):
        return core(config, t - t[0], p, q, r - t[0])

    for _ in batch:
        one = jax.vmap(one)
    return one(t, p, q, r)


def _run_recording(core, config, times, positions, quaternions, render_times, dtype,
                   hold_end=False):
    """Validate and normalise a recording (outside jit), pad it to its size class
    (:mod:`phjax.tracking._shapes`: one compiled program per class, not per length) and run the
    jitted ``core`` on it. ``hold_end``: the core interpolates between frames (render times past
    the last frame are clamped to it)."""
    t, p, q, r, (orientation_only, position_only) = _prepare_recording(
        times, positions, quaternions, render_times)
    m = r.shape[0]
    t, p, q, r = pad_recording(t, p, q, r, hold_end=hold_end)
    dtype = jnp.zeros((), float).dtype if dtype is None else dtype
    args = [jnp.asarray(x, dtype) for x in (t, p, q, r)]
    out = _exported.call(core, config, args)  # a stored program (the command line), or None
    if out is None:
        bounded_cache(core, (jax.tree.structure(config), tuple(a.shape for a in args),
                             args[0].dtype))
        out = core(config, *args)
    out_p, out_q = out
    if orientation_only:
        out_p = jnp.full_like(out_p, jnp.nan)
    if position_only:
        out_q = jnp.full_like(out_q, jnp.nan)
    # sliced on the host: a slice of the JAX array would compile a program for every length
    return unpad_rows(out_p, m), unpad_rows(out_q, m)


def _scan_stream(config, times, positions, quaternions, render_times):
    """The causal render-rate stream on prepared (sorted, de-duplicated, relative) arrays,
    traceable in the data and the config: ``lax.scan`` of :func:`tracker_update` over the
    measurements, then the render segment of the latest measurement with ``t <= tau`` sampled
    at each render time; NaN before the first valid measurement. The one scan of the tracker
    behind :func:`track` (jitted as ``_track_core``) and the tuning loss
    (:mod:`phjax.tracking._tuning_loss`)."""
    dtype = times.dtype
    state0 = tracker_init(config, times[0], dtype)

    def body(state, meas):
        t, p, q = meas
        new = _update(config, state, t, p, q)
        return new, new.segment  # only what a render sample reads is stacked and gathered

    _, segments = filter_scan(body, state0, (times, positions, quaternions))
    sel, before = _latest_states(times, segments, render_times)
    p, _, q, _ = jax.vmap(lambda seg, tau: seg.evaluate(tau, velocities=False))(sel, render_times)
    nan = jnp.where(before, jnp.nan, 0.0)[:, None].astype(dtype)
    return p + nan, q + nan


@jit
def _track_core(config, times, positions, quaternions, render_times):
    return _scan_stream(config, times, positions, quaternions, render_times)


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
    with ``t <= tau``. Inputs are padded to a size class (the next power of two of ``N`` and
    of ``M``, :mod:`phjax.tracking._shapes`), so recordings of different lengths in one class
    share one compiled program and the results equal the unpadded ones; at most
    :data:`~phjax.tracking._shapes.MAX_COMPILED_SHAPES` (16) classes and configuration
    structures stay compiled (more would exhaust the process's memory mappings, see
    :func:`phjax.tracking._shapes.bounded_cache`).

    **Batches** (leading axes ``B``, one compiled program for the whole batch): recordings
    NaN-padded to a common length ``N`` (:func:`phjax.batch.pad_recordings`). Padding rule: a
    NaN time is a padding frame, counted as a lost frame after the recording's end (padding
    must follow every real frame); a NaN render time gives a NaN sample; ``render_times`` may
    be ``(M,)``, shared by every recording. Each recording gets its one-recording result. In a
    batch, times must already be strictly increasing (an error, not a warning). Inputs sharded
    along axis 0 (:func:`phjax.batch.shard_batch`) run on each device's part of the batch and
    the outputs come back sharded the same way.

    **Inside** ``jax.jit``, ``jax.vmap`` or ``jax.grad`` (any input a tracer) the recordings
    are used as given, without the host-side steps: times finite and strictly increasing, no
    padding frames, no size classes, one-part data not completed; the results equal the host
    path's for such data.

    Arguments:
        times: measurement times, s (one recording: sorted and de-duplicated here with a
            warning if needed; internally relative to the first time, so absolute epoch times
            are fine).
        positions: measured positions, m; rows with a NaN or an infinity are missing
            frames. If every position is NaN (orientation-only data) the orientation is
            tracked and positions are NaN.
        quaternions: measured orientations wxyz, any sign and norm; rows with a NaN or an
            infinity, or of zero norm, are missing frames. If no orientation is valid
            (position-only data) the position is tracked and the quaternions are NaN.
            Otherwise the filters start at the first row holding both parts: one-part rows
            before it, or a recording whose rows each hold one part, are named by a
            :class:`phjax.io.TrajectoryWarning`.
        render_times: times at which to render, s (any order).
        config: tracker configuration (default :class:`TrackerConfig()`), shared by the batch.
        dtype: computation dtype (default: JAX's default float; pass ``jnp.float64`` with x64
            enabled for double precision).

    Returns:
        ``(positions (*B, M, 3), quaternions (*B, M, 4))``; NaN before the first valid
        measurement (and at padded render times).

    Raises:
        TypeError: ``config`` is not a :class:`TrackerConfig`.
        ValueError: a config field outside its range
            (:data:`phjax.tracking.tuning.CONFIG_RANGES`; not checked when traced), or
            recording arrays of the wrong shapes, no measurement, non-finite times.
    """
    config = check_config(config)
    if any_traced(times, positions, quaternions, render_times):
        return _run_traced(_track_core, config, times, positions, quaternions, render_times,
                           dtype)
    if np.ndim(times) > 1:
        return run_batch(_track_core, config, times, positions, quaternions, render_times, dtype)
    return _run_recording(_track_core, config, times, positions, quaternions, render_times, dtype)


@jit
def _reconstruct_core(config, times, positions, quaternions, render_times):
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
    # a gap longer than the causal stream's coasting is bridged without a made-up excursion
    # (the segment's end derivatives are velocity x gap: a 300 s gap would swing metres)
    gap = dt[idx]
    long_gap = gap > config.coast_time + config.stop_time
    pb, qb = _bridge(p[idx], v[idx], q[idx], w[idx], p[idx + 1], v[idx + 1], q[idx + 1],
                     w[idx + 1], s * gap, gap, config.coast_time, config.stop_time)
    pr = jnp.where(long_gap[:, None], pb, pr)
    qr = jnp.where(long_gap[:, None], qb, qr)
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

    Not causal (uses the whole recording). A gap between measurements longer than
    ``config.coast_time + config.stop_time`` (0.15 s by default: lost frames, a paused
    recording) is bridged without made-up motion: from each side the pose moves into the gap
    as the causal stream coasts (``coast_time`` with that side's velocity, then coming to rest
    over ``stop_time``), and a smoothstep blends the two sides (slerp for orientation); the
    pose stays C1. Same arguments, conventions, batches (NaN padding
    rule) and sharding as :func:`track`; render times outside the measurement span hold the
    end poses (before the first valid measurement: its pose; after the last real frame of a
    padded recording: its pose).

    Returns:
        ``(positions (*B, M, 3), quaternions (*B, M, 4))``.
    """
    config = check_config(config)
    if any_traced(times, positions, quaternions, render_times):
        return _run_traced(_reconstruct_core, config, times, positions, quaternions,
                           render_times, dtype)
    if np.ndim(times) > 1:
        return run_batch(_reconstruct_core, config, times, positions, quaternions, render_times,
                         dtype, hold_end=True)
    return _run_recording(_reconstruct_core, config, times, positions, quaternions, render_times,
                          dtype, hold_end=True)
