"""Synthetic head motion and a simple pose-sensor model (noise, dropouts, jitter, latency).

Conventions: ``wxyz`` quaternions rotating head-frame vectors into the world frame; world axes
``x`` right, ``y`` up, ``-z`` forward (OpenXR / OpenGL); metres, seconds, radians.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._jit import jit
from .._np_quat import np_from_rotvec as _np_from_rotvec
from .._np_quat import np_qconj as _np_qconj
from .._np_quat import np_qmul as _np_qmul
from .._sizes import MIN_RENDER, pad_samples, size_class, unpad_rows
from ..quaternion import quat_from_rotvec, quat_mul
from .resample import (ground_truth_max_gap, interpolate_poses, valid_quaternion_rows,
                       valid_rows)

__all__ = ["SensorModel", "simulate_measurements", "synthetic_head_motion"]


class SensorModel(eqx.Module):
    """Pose sensor (e.g. a camera-based head tracker) producing noisy, lossy samples.

    Attributes:
        rate: nominal sample rate (Hz).
        sigma_p: position noise, iid ``N(0, sigma_p^2)`` per component (m).
        sigma_r: orientation noise: rotation vector ``n`` with iid ``N(0, sigma_r^2)``
            components (rad), applied in the world frame as ``q_meas = exp(n) q_true``.
        dropout: probability that a frame is lost (its row becomes NaN, its time is kept).
        jitter: std of the timestamp jitter as a fraction of the period; each offset is clipped
            to ``+-0.45`` periods so the times stay strictly increasing.
        latency: delay (s) between the instant a pose is sampled and its timestamp: the sample
            stamped ``t`` shows the ground truth at ``t - latency``.
    """

    rate: float = 30.0
    sigma_p: float = 0.005
    sigma_r: float = float(np.deg2rad(1.0))
    dropout: float = 0.05
    jitter: float = 0.0
    latency: float = 0.0


def _as_key(key_or_seed) -> Array:
    """A ``jax.random`` key from an integer seed (0-d integer arrays included) or a key (typed,
    or a raw ``uint32`` key of shape ``(2,)``); anything else is a ``ValueError``."""
    if isinstance(key_or_seed, (int, np.integer)):
        return jax.random.key(int(key_or_seed))
    dtype, shape = getattr(key_or_seed, "dtype", None), np.shape(key_or_seed)
    if dtype is not None:
        if jnp.issubdtype(dtype, jax.dtypes.prng_key) and shape == ():
            return key_or_seed
        if dtype == np.uint32 and shape == (2,):  # a raw key (jax.random.PRNGKey)
            return key_or_seed
        if jnp.issubdtype(dtype, jnp.integer) and shape == ():
            return jax.random.key(int(key_or_seed))
    raise ValueError(f"key_or_seed must be an integer seed or a jax.random key; got "
                     f"{getattr(dtype, 'name', type(key_or_seed).__name__)} of shape {shape}")


def _check_model(model: SensorModel) -> None:
    """One-line ``ValueError`` naming the first field of ``model`` out of its range."""
    vals = {f: float(getattr(model, f))
            for f in ("rate", "sigma_p", "sigma_r", "dropout", "jitter", "latency")}
    for field, v in vals.items():
        if not np.isfinite(v):
            raise ValueError(f"SensorModel.{field} must be finite, got {v}")
    if not vals["rate"] > 0:
        raise ValueError(f"SensorModel.rate must be positive, got {vals['rate']}")
    if not 0 <= vals["dropout"] < 1:
        raise ValueError(f"SensorModel.dropout must be in [0, 1), got {vals['dropout']}")
    for field in ("sigma_p", "sigma_r", "jitter"):
        if vals[field] < 0:
            raise ValueError(f"SensorModel.{field} must be non-negative, got {vals[field]}")


def simulate_measurements(
    key_or_seed: int | Array,
    gt_times: Float[ArrayLike, " n"],
    gt_positions: Float[ArrayLike, "n 3"],
    gt_quaternions: Float[ArrayLike, "n 4"],
    model: SensorModel = SensorModel(),
    *,
    max_gt_gap: float | None = None,
) -> tuple[Float[Array, " m"], Float[Array, "m 3"], Float[Array, "m 4"]]:
    """Sample a ground-truth trajectory with the sensor ``model``.

    Sampling instants form the grid ``s_k = t_0 + k / rate`` (``k = 0, 1, ...`` while
    ``s_k <= t_end`` of the ground truth), optionally jittered (clipped to the ground-truth
    range). The ground truth is interpolated there with :func:`~phjax.motion.resample.interpolate_poses`
    (linear / slerp; NaN ground-truth rows are skipped), noise is added, and each frame is
    dropped with probability ``dropout`` (NaN row). Returned timestamps are ``s_k + latency``.

    **Ground-truth gaps.** An instant strictly inside a gap between valid ground-truth samples
    longer than ``max_gt_gap`` (default :func:`~phjax.motion.resample.ground_truth_max_gap`,
    the rule the evaluation uses to leave such gaps unscored) gives a lost frame (NaN row):
    the motion there is unknown, and a straight line through the gap would hand the filters
    an easy, made-up motion to predict. ``max_gt_gap=float("inf")`` interpolates across every
    gap. Positions and orientations are checked each where the ground truth has them.

    Orientation-only ground truth (NaN positions) gives NaN positions and noisy orientations.
    Deterministic for a given key / integer seed and dtype (JAX draws different samples in
    float32 and float64). Not ``jit``-able as a whole (the number of
    samples depends on the ground-truth time range); the per-sample work is one jitted program
    per size class (:mod:`phjax._sizes`) of the ground truth and of the number of samples, so
    recordings of other lengths reuse it.

    **Batches**: ground truth with leading batch axes ``B`` (``gt_times (*B, n)``), NaN-padded
    to a common length (padding rule of :mod:`phjax.batch`: NaN times are padding). Recording
    ``i`` (row-major over ``B``) is simulated alone with key ``i`` of
    ``jax.random.split(key, prod(B))`` (a single key or seed), or with its own key / seed when
    ``key_or_seed`` has shape ``B``; the results are NaN-padded to the longest (padding
    frames have NaN times, as :func:`phjax.track` expects).

    Arguments:
        key_or_seed: a ``jax.random`` key (typed, or a raw ``uint32`` one) or an integer
            seed, 0-d integer arrays included (for batches also one per recording).
        gt_times, gt_positions, gt_quaternions: ground truth (``wxyz``), times non-decreasing,
            ``(*B, n)``, ``(*B, n, 3)``, ``(*B, n, 4)``.
        model: the :class:`SensorModel` (shared by a batch).
        max_gt_gap: the longest ground-truth gap (s) a frame may be interpolated across (see
            above; for a batch, one value or the default rule per recording).

    Returns:
        ``(times (*B, m), positions (*B, m, 3), quaternions (*B, m, 4))`` in the ground-truth
        dtype.

    Raises:
        ValueError: naming the field, for a :class:`SensorModel` field that is not finite or
            out of its range, a ground truth with no valid position or orientation sample, a
            key that is neither a seed nor a key, or times that ``gt_times``' own dtype or the
            result dtype cannot resolve to a hundredth of the camera period.
    """
    if np.ndim(gt_times) > 1:
        return _simulate_batch(key_or_seed, gt_times, gt_positions, gt_quaternions, model,
                               max_gt_gap)
    gt_t = np.asarray(gt_times, dtype=np.float64)
    if gt_t.ndim != 1 or gt_t.size == 0 or not np.all(np.isfinite(gt_t)):
        raise ValueError("gt_times must be a non-empty 1-D array of finite times")
    if np.any(np.diff(gt_t) < 0):
        raise ValueError("gt_times must be sorted")
    _check_model(model)
    rate, jitter = float(model.rate), float(model.jitter)
    max_gap = ground_truth_max_gap(gt_t, max_gt_gap)
    if not max_gap > 0:  # NaN included
        raise ValueError(f"max_gt_gap must be positive (inf: no limit), got {max_gt_gap}")
    # host arrays: jnp.asarray of a NumPy array compiles a small program for every shape
    gt_p, gt_q = np.asarray(gt_positions), np.asarray(gt_quaternions)
    if gt_p.shape != (gt_t.size, 3) or gt_q.shape != (gt_t.size, 4):
        raise ValueError(f"expected gt_times (n,), gt_positions (n, 3), gt_quaternions (n, 4); "
                         f"got {gt_t.shape}, {gt_p.shape}, {gt_q.shape}")
    dtype = jnp.result_type(gt_p, gt_q, jnp.float32)
    # host check of what _measure's valid_rows / valid_quaternion_rows find (no pose at all
    # would silently give a recording of lost frames)
    q_fin = np.isfinite(gt_q).all(-1)
    q_ok = q_fin & (np.sum(np.where(q_fin[:, None], gt_q, 0).astype(dtype) ** 2, -1) > 0)
    if not (np.isfinite(gt_p).all(-1).any() or q_ok.any()):
        raise ValueError("the ground truth has no valid position or orientation sample (all "
                         "NaN / infinite, quaternions zero)")

    t0, t1 = gt_t[0], gt_t[-1]
    m = int(np.floor((t1 - t0) * rate + 1e-9)) + 1
    k_jit, k_p, k_r, k_drop = jax.random.split(_as_key(key_or_seed), 4)
    period = 1.0 / rate
    sample_t = t0 + np.arange(m) * period
    # One program per size class, not per length: the ground truth and the sampling instants
    # are padded (pad_samples) and every random draw is made for the padded length. With JAX's
    # partitionable Threefry (its default) a draw's first m values do not depend on its length,
    # so the result equals the unpadded computation.
    mb = size_class(m, MIN_RENDER)
    if jitter > 0:
        offs = np.asarray(jax.random.normal(k_jit, (mb,)), dtype=np.float64)[:m] * jitter
        sample_t = np.clip(sample_t + np.clip(offs, -0.45, 0.45) * period, t0, t1)

    # the interpolation relative to the first ground-truth time (epoch times would be rounded
    # to minutes in float32); the returned times must resolve the sampling in ``dtype``
    # and the caller's gt_times must have resolved them: float32 epoch times with float64
    # poses were rounded to 128 s before the call (a 10 s recording became one frame)
    last = max(abs(t0), abs(t1)) + abs(float(model.latency))
    t_dtype = np.asarray(gt_times).dtype
    for dt, what, at in ((dtype, "returned", last), (t_dtype, "given", max(abs(t0), abs(t1)))):
        if np.issubdtype(dt, np.floating) and np.spacing(np.asarray(at, dt)) > 1e-2 * period:
            raise ValueError(
                f"times up to {at:.6g} s cannot be {what} in {np.dtype(dt).name} to a "
                f"hundredth of the camera period; pass times relative to the first (t - t[0]) "
                "or enable jax_enable_x64")
    gt = pad_samples((gt_t - t0).astype(dtype), gt_p.astype(dtype), gt_q.astype(dtype),
                     (sample_t - t0).astype(dtype))
    p_meas, q_meas = _measure(*gt, k_p, k_r, k_drop, *(jnp.asarray(float(x), dtype) for x in (
        model.sigma_p, model.sigma_r, model.dropout, max_gap)))
    times = jax.device_put(np.asarray(sample_t + float(model.latency), dtype))
    return times, unpad_rows(p_meas, m), unpad_rows(q_meas, m)


@jit
def _measure(gt_t, gt_p, gt_q, sample_t, k_p, k_r, k_drop, sigma_p, sigma_r, dropout, max_gap):
    """The sensor at the sampling instants ``sample_t``: interpolated ground truth, noise,
    dropouts and frames lost in ground-truth gaps longer than ``max_gap`` (jitted;
    :func:`simulate_measurements` pads to size classes)."""
    m, dtype = sample_t.shape[0], gt_p.dtype
    p_true, q_true = interpolate_poses(gt_t, gt_p, gt_q, sample_t, max_gap=max_gap)
    # a frame in a gap of either channel the ground truth has is lost as a whole (a sensor
    # that loses track loses the pose); a channel the ground truth lacks is NaN everywhere
    # (a channel counts where interpolate_poses finds a valid sample: zero quaternions do not)
    has_p = jnp.any(valid_rows(gt_p))
    has_q = jnp.any(valid_quaternion_rows(gt_q))
    in_gap = ((has_p & jnp.any(jnp.isnan(p_true), axis=-1))
              | (has_q & jnp.any(jnp.isnan(q_true), axis=-1)))
    p_meas = p_true + sigma_p * jax.random.normal(k_p, (m, 3), dtype)
    noise = sigma_r * jax.random.normal(k_r, (m, 3), dtype)
    q_meas = quat_mul(quat_from_rotvec(noise), q_true)
    lost = (jax.random.uniform(k_drop, (m,), dtype) < dropout) | in_gap
    nan = jnp.asarray(jnp.nan, dtype)
    return jnp.where(lost[:, None], nan, p_meas), jnp.where(lost[:, None], nan, q_meas)


def _batch_keys(key_or_seed, batch: tuple[int, ...]) -> list:
    """One key per recording of a batch (row-major)."""
    r = int(np.prod(batch))
    if isinstance(key_or_seed, (int, np.integer)):
        return list(jax.random.split(jax.random.key(int(key_or_seed)), r))
    k = jnp.asarray(key_or_seed)
    if jnp.issubdtype(k.dtype, jax.dtypes.prng_key):
        if k.shape == ():
            return list(jax.random.split(k, r))
        if k.shape == batch:
            return list(k.reshape(-1))
    elif jnp.issubdtype(k.dtype, jnp.integer) and k.shape == batch:
        return [jax.random.key(int(x)) for x in np.asarray(k).reshape(-1)]
    raise ValueError(f"key_or_seed must be a seed, a key, or seeds / keys of the batch shape "
                     f"{batch}; got {getattr(k, 'dtype', type(k))} of shape {k.shape}")


def _simulate_batch(key_or_seed, gt_times, gt_positions, gt_quaternions, model, max_gt_gap):
    """:func:`simulate_measurements` of each recording of a NaN-padded batch, padded again."""
    from ..batch import pad_recordings

    t_dtype = np.asarray(gt_times).dtype  # checked per recording (see the single case)
    if not np.issubdtype(t_dtype, np.floating):
        t_dtype = np.dtype(np.float64)
    t = np.asarray(gt_times, np.float64)
    p, q = jnp.asarray(gt_positions), jnp.asarray(gt_quaternions)
    b, n = t.shape[:-1], t.shape[-1]
    if p.shape != b + (n, 3) or q.shape != b + (n, 4):
        raise ValueError("expected gt_times (*B, n), gt_positions (*B, n, 3), gt_quaternions "
                         f"(*B, n, 4); got {t.shape}, {p.shape}, {q.shape}")
    dtype = jnp.result_type(p, q, jnp.float32)
    keys = _batch_keys(key_or_seed, b)
    t, pn, qn = t.reshape(-1, n), np.asarray(p).reshape(-1, n, 3), np.asarray(q).reshape(-1, n, 4)
    outs = []
    for i in range(t.shape[0]):
        keep = np.isfinite(t[i])
        if not keep.any():
            raise ValueError(f"recording {i} of the batch has no ground-truth time")
        outs.append([np.asarray(x, np.float64) for x in simulate_measurements(
            keys[i], t[i][keep].astype(t_dtype), pn[i][keep].astype(dtype),
            qn[i][keep].astype(dtype), model,
            max_gt_gap=max_gt_gap)])
    mt, mp, mq = pad_recordings(*zip(*outs))
    m = mt.shape[-1]
    return (jnp.asarray(mt.reshape(b + (m,)), dtype), jnp.asarray(mp.reshape(b + (m, 3)), dtype),
            jnp.asarray(mq.reshape(b + (m, 4)), dtype))


# ----------------------------------------------------------------------------------------------
# synthetic head motion
# ----------------------------------------------------------------------------------------------

_NECK_TO_EYES = np.array([0.0, 0.10, -0.08])  # head frame: 10 cm up, 8 cm forward of the pivot
_PIVOT = np.array([0.0, 1.10, 0.08])  # seated neck pivot (eyes at (0, 1.20, 0) when at rest)


def _min_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


def _axis_quat(angle: np.ndarray, axis: int) -> np.ndarray:
    q = np.zeros(angle.shape + (4,))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


def _sum_of_sines(t, rng, n, f_lo, f_hi, amp):
    """Sum of ``n`` sinusoids with log-uniform frequencies in ``[f_lo, f_hi]`` Hz, random phases
    and amplitudes ``amp * U(0.5, 1) / sqrt(n)``."""
    f = np.exp(rng.uniform(np.log(f_lo), np.log(f_hi), n))
    ph = rng.uniform(0, 2 * np.pi, n)
    a = amp * rng.uniform(0.5, 1.0, n) / np.sqrt(n)
    return np.sum(a[:, None] * np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]), axis=0)


def _gaze_schedule(duration: float, rng: np.random.Generator):
    """Movement segments ``(start, length, d_yaw, d_pitch, d_roll)`` in seconds and radians."""
    segs = []
    yaw, pitch, roll = 0.0, np.deg2rad(-3.0), 0.0
    t = rng.uniform(0.3, 1.5)
    pending_return = None
    while t < duration:
        if pending_return is not None:
            dy, dp, dr = pending_return
            pending_return = None
        else:
            amp = np.deg2rad(10 + 80 * rng.uniform() ** 1.5)
            toward_centre = rng.uniform() < 0.5 + 0.45 * min(abs(yaw) / np.deg2rad(90), 1.0)
            sign = -np.sign(yaw) if (toward_centre and yaw != 0) else rng.choice([-1.0, 1.0])
            if abs(yaw + sign * amp) > np.deg2rad(110):
                sign = -sign
            dy = sign * amp
            new_pitch = rng.normal(np.deg2rad(-3), np.deg2rad(8))
            dp = np.clip(new_pitch, np.deg2rad(-25), np.deg2rad(20)) - pitch
            dr = np.clip(rng.normal(0, np.deg2rad(2.5)), np.deg2rad(-8), np.deg2rad(8)) - roll
        total = np.sqrt(dy * dy + dp * dp + dr * dr)
        v_peak = np.deg2rad(np.clip(110 * np.exp(0.45 * rng.normal()), 40, 300))
        length = float(np.clip(1.875 * total / v_peak, 0.3, 1.2))  # min-jerk peak = 1.875 A / T
        segs.append((t, length, dy, dp, dr))
        yaw, pitch, roll = yaw + dy, pitch + dp, roll + dr
        t += length
        if rng.uniform() < 0.3:  # look back and forth: return after a short fixation
            pending_return = (-dy, -dp, -dr)
            t += rng.uniform(0.3, 1.0)
            continue
        fix = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
        if fix > 1.2 and rng.uniform() < 0.35:  # a nod inside a long fixation
            depth = min(np.deg2rad(rng.uniform(8, 20)), pitch + np.deg2rad(30))
            t_down = rng.uniform(0.3, 0.6)
            t_nod = t + rng.uniform(0.1, 0.3)
            segs.append((t_nod, t_down, 0.0, -depth, 0.0))
            segs.append((t_nod + t_down + rng.uniform(0.1, 0.3), t_down, 0.0, depth, 0.0))
            fix = max(fix, 2 * t_down + 0.7)
        t += fix
    return np.array(segs, dtype=np.float64).reshape(-1, 5)


def synthetic_head_motion(
    duration: float = 60.0, rate: float = 240.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seated VR head motion: gaze shifts, fixations, nods, sway and tremor (ground truth).

    Model (all random choices from ``numpy.random.default_rng(seed)``):

    * **Gaze shifts.** Fixations (log-uniform 0.3-3 s) alternate with joint yaw/pitch/roll
      movements following minimum-jerk profiles ``10u^3 - 15u^4 + 6u^5``. Yaw amplitude
      ``10 + 80 U^1.5`` degrees (more small turns than large), direction biased towards the
      centre and yaw kept within +-110 deg; new pitch target ``N(-3, 8)`` deg clipped to
      [-25, 20]; new roll target ``N(0, 2.5)`` deg clipped to +-8. The peak speed is drawn
      log-normally (median 110 deg/s, clipped to 40-300 deg/s) and sets the duration
      ``T = 1.875 A / v_peak`` clipped to 0.3-1.2 s, so peaks stay <= 300 deg/s (typically
      50-150 deg/s). With probability 0.3 a turn is undone after a 0.3-1 s fixation
      (looking back and forth).
    * **Nods.** In 35% of fixations longer than 1.2 s: pitch down 8-20 deg (kept above -30 deg)
      over 0.3-0.6 s, hold 0.1-0.3 s, and back up.
    * **Sway.** Slow angular sway: per axis a sum of 3 sinusoids, 0.05-0.5 Hz, ~0.6 deg total.
      Torso translation: per axis 3 sinusoids, 0.05-0.5 Hz, ~2 cm horizontally and 0.5 cm
      vertically.
    * **Tremor.** Per axis one 8-12 Hz sinusoid of amplitude 0.1 deg, amplitude-modulated at
      0.1-0.3 Hz between 50 and 100%.
    * **Kinematics.** ``q = q_y(yaw) q_x(pitch) q_z(roll) exp(sway + tremor)`` (head-frame
      perturbation); the eye-centre position is ``pivot + torso_sway + R(q) (0, 0.10, -0.08)``
      with the neck pivot 10 cm below and 8 cm behind the eyes (``pivot = (0, 1.10, 0.08)`` m).

    Every component is C2 (minimum-jerk segments have zero velocity and acceleration at both
    ends; the sinusoids are smooth), so the ground truth is C2 in position and orientation.

    Returns:
        ``(times (n,), positions (n, 3), quaternions (n, 4))`` as float64 NumPy arrays with
        ``times = arange(n) / rate``, ``n = round(duration * rate) + 1`` (from 0 to
        ``duration`` rounded to the nearest sample; duration and rate positive and finite);
        quaternions are ``wxyz``,
        hemisphere-continuous.
    """
    if not (0 < duration < np.inf and 0 < rate < np.inf):
        raise ValueError(f"duration and rate must be positive and finite, got {duration}, {rate}")
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate

    segs = _gaze_schedule(duration, rng)
    # the segments follow each other (a nod lies inside the fixation after a turn): at each
    # time the ones before the last started are complete and it is under way. Memory linear
    # in n (a (segments, n) profile grew as n^2: 1.5 TiB for 3 million frames)
    segs = np.concatenate([[[-1.0, 1.0, 0.0, 0.0, 0.0]], segs])  # a still one before t = 0
    last = np.searchsorted(segs[:, 0], t, side="right") - 1
    done = np.concatenate([np.zeros((1, 3)), np.cumsum(segs[:, 2:], axis=0)])
    seg = segs[last]
    angles = done[last] + _min_jerk((t - seg[:, 0]) / seg[:, 1])[:, None] * seg[:, 2:]
    yaw, roll = angles[:, 0], angles[:, 2]
    pitch = np.deg2rad(-3.0) + angles[:, 1]

    sway = np.stack([_sum_of_sines(t, rng, 3, 0.05, 0.5, np.deg2rad(0.6)) for _ in range(3)], -1)
    tremor = []
    for _ in range(3):
        f = rng.uniform(8, 12)
        fm, pm, ph = rng.uniform(0.1, 0.3), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
        am = 0.75 + 0.25 * np.sin(2 * np.pi * fm * t + pm)
        tremor.append(np.deg2rad(0.1) * am * np.sin(2 * np.pi * f * t + ph))
    perturb = sway + np.stack(tremor, -1)

    q = _np_qmul(_np_qmul(_axis_quat(yaw, 1), _axis_quat(pitch, 0)), _axis_quat(roll, 2))
    q = _np_qmul(q, _np_from_rotvec(perturb))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    flips = np.sum(q[1:] * q[:-1], axis=-1) < 0
    q *= np.concatenate([[1.0], np.cumprod(np.where(flips, -1.0, 1.0))])[:, None]

    torso = np.stack(
        [
            _sum_of_sines(t, rng, 3, 0.05, 0.5, 0.02),
            _sum_of_sines(t, rng, 3, 0.05, 0.5, 0.005),
            _sum_of_sines(t, rng, 3, 0.05, 0.5, 0.02),
        ],
        -1,
    )
    offset = _np_qmul(_np_qmul(q, np.concatenate([[0.0], _NECK_TO_EYES])), _np_qconj(q))[:, 1:]
    positions = _PIVOT + torso + offset
    return t, positions, q
