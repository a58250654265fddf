"""Gradient-based tuning of the causal tracker: differentiate the whole stream, minimise with BFGS.

The causal stream of :func:`phjax.track` (a ``lax.scan`` of :func:`phjax.tracker_update` over
the camera frames, then :func:`phjax.tracker_sample` at the render times) is differentiable with
respect to every float leaf of :class:`phjax.TrackerConfig` that it uses: with the IMM filter
(the default) each motion model's log noise density, the log switch rate and the measurement
noise; with the single-model filter its noise densities and measurement noise; and for both the
segment ``horizon``, the coasting times and the initial stds. This module scores the stream on
recordings with known ground truth and tunes those leaves with ``optimistix.BFGS``
(:func:`tunable_parameters` lists them, :func:`default_parameters` gives the set tuned when
none is named).

**Data.** :func:`prepare_recordings` samples a ground-truth trajectory by a
:class:`phjax.SensorModel` with a fixed seed (so the loss is a deterministic, differentiable
function of the parameters), renders the stream at ``render_rate`` from the first valid frame
plus one camera period (as in :func:`phjax.evaluation.evaluate_recording`), and interpolates the
ground truth at the render times with :func:`phjax.motion.resample.interpolate_poses`
(``max_gap`` 0.1 s: samples inside longer ground-truth gaps are ignored). :func:`tuning_data`
takes measurements that are already there instead (a real pose stream with its ground truth at
the render times; :func:`measured_recording` builds one from a recorded stream and its ground
truth, optionally aligning their frames) and does the rest, which both share: render samples
at a frame's instant see that frame (:func:`phjax.motion.resample.snap_to_frames`), times are
made relative to the first measurement and positions to the first ground-truth position (the
tracker is equivariant to both; this keeps float32 accurate), the reference stream below is
computed, and recordings are padded to common lengths (NaN frames after the end, masked render
samples) and stacked, so one compiled program serves them all (``jax.vmap``).

**Loss.** Per recording, four terms of the rendered stream (same definitions as
:mod:`phjax.evaluation.metrics`): position RMSE ``E_p`` (m), rotation RMSE ``E_r`` (geodesic angle, rad),
RMS position jerk ``J_p`` (m/s^3, six times the third divided difference of four consecutive
render samples) and RMS angular jerk ``J_r`` (rad/s^3, second difference of the midpoint
angular velocities). With ``normalize=True`` (default) each term is divided by the same term of
a reference stream on the same measurements, the Kalman constant-velocity extrapolation with the
tuned noise of :data:`phjax.tracking.baselines.TUNED` (:func:`phjax.tracking.baselines.kalman_extrapolation`), so
every term is dimensionless and ``lam`` is a pure trade-off weight::

    L_rec = [w_p (E_p / E_p_ref + lam J_p / J_p_ref) + w_r (E_r / E_r_ref + lam J_r / J_r_ref)]
            / (w_p + w_r)

and the loss is the mean of ``L_rec`` over recordings (orientation-only recordings have
``w_p = 0``). The reference baseline therefore scores exactly ``1 + lam``. With
``normalize=False`` the terms are in SI units (then ``lam`` has units and mixing position and
rotation is up to the weights).

**Parameters** are optimised in log space (``value = exp(y)``), which keeps them positive and
makes the problem scale free; leaves that are logarithms already (``log_*``: the IMM's model
densities ``log_q`` and ``log_switch_rate``) and ``adapt`` (any sign) are optimised as they
are. Note that scaling all noise densities *and* measurement stds of
one channel by the same factor changes the filter only through the initial covariance, so
tuning process and measurement noise together leaves a nearly flat direction; BFGS copes, but
the individual values are less meaningful than their ratio.

Everything traced is NaN-safe: masked samples are replaced by finite values before any
arithmetic (double-``where`` pattern), so gradients are finite with dropped frames, render
times before the first measurement and ground-truth gaps. The code is dtype-generic:
``phjax tune`` works in float64 (``jax.config.update("jax_enable_x64", True)``), and in float32
(JAX's default) the loss terms of the IMM stream agree with float64 within 2e-5 and the
gradient within 1e-3, measured on 3 s and 30 s synthetic recordings (the 3 s case is tested;
times and positions are relative to each recording's start, which keeps the third differences
of the jerk terms accurate).

Cost: the first loss-and-gradient evaluation compiles the differentiated stream (the scan body
is large): for the single-model filter about 30 s of CPU in forward mode (the default), about
85 s in reverse mode; for the IMM filter about 40 s in forward mode (8 default parameters).
Later calls with the same data shapes and parameter names reuse it.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from .._misc import safe_div, safe_sqrt
from .imm import IMMConfig
from .kalman import KalmanConfig
from .models import ConstantAcceleration, ConstantVelocity
from ..quaternion import quat_conj, quat_geodesic_distance, quat_mul, quat_normalize, quat_to_rotvec
from ..motion.simulate import SensorModel
from ._batch import _lost_padding_frames
from .tracker import TrackerConfig, tracker_init, tracker_sample, tracker_update

__all__ = [
    "DEFAULT_PARAMETERS",
    "CONFIG_FORMAT",
    "CONFIG_VERSION",
    "TuningData",
    "TuningProblem",
    "TuningResult",
    "StepInfo",
    "tunable_parameters",
    "default_parameters",
    "check_parameters",
    "prepare_recordings",
    "tuning_data",
    "measured_recording",
    "stream_metrics",
    "loss_terms",
    "tracker_loss",
    "make_problem",
    "tune_tracker",
    "config_to_dict",
    "config_from_dict",
    "save_config",
    "load_config",
]

#: Parameters tuned by default for the single-model filter (``TrackerConfig(imm=None)``): its
#: noise model and the segment horizon. For the IMM see :func:`default_parameters`.
DEFAULT_PARAMETERS: tuple[str, ...] = (
    "pos_process_noise",
    "rot_process_noise",
    "pos_meas_noise",
    "rot_meas_noise",
    "horizon",
)

#: ``"format"`` tag and version of the JSON written by :func:`save_config`.
CONFIG_FORMAT = "phjax.TrackerConfig"
CONFIG_VERSION = 1


# ------------------------------------------------------------------------------ parameters
def _is_float_leaf(x) -> bool:
    return isinstance(x, float) or eqx.is_inexact_array(x)


def _key(k) -> str | int | None:
    """A path entry: attribute name, tuple index, or ``None`` for anything else."""
    if isinstance(k, jax.tree_util.GetAttrKey):
        return k.name
    if isinstance(k, jax.tree_util.SequenceKey):
        return k.idx
    return None


def _unused(config: TrackerConfig) -> set:
    """Float leaves the causal stream never reads with this configuration (zero gradient)."""
    unused = set()
    if config.imm is not None:  # only phjax.reconstruct reads the single-model section
        unused.add("kalman")
    else:
        unused.add("adapt")  # adaptive settling reads the IMM's mode probabilities
    if (config.kalman if config.imm is None else config.imm).order < 3:
        unused.add("init_pos_acc_std")  # no acceleration in the state
    return unused


def _leaf_paths(config: TrackerConfig) -> list[tuple[str | int, ...]]:
    """Paths (attribute names and model indices) of the float leaves the causal stream uses:
    with an IMM filter not the single-model ``kalman`` section, with the single-model filter
    not ``adapt``, without acceleration models not ``init_pos_acc_std``."""
    unused = _unused(config)
    paths = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(config)[0]:
        keys = tuple(_key(k) for k in path)
        if not _is_float_leaf(leaf) or None in keys or unused & set(keys):
            continue
        paths.append(keys)
    return paths


def _dotted(path) -> str:
    return ".".join(str(k) for k in path)


def _names(paths) -> list[str]:
    """Short name (last attribute) when unique, else the dotted path."""
    last = [p[-1] for p in paths]
    return [p[-1] if last.count(p[-1]) == 1 else _dotted(p) for p in paths]


def _float_leaf_paths(config: TrackerConfig) -> dict[str, tuple[str | int, ...]]:
    """Paths of the float leaves by name: the dotted path always, the short name when unique."""
    paths = _leaf_paths(config)
    out = {_dotted(p): p for p in paths}
    out.update(zip(_names(paths), paths))
    return out


def _is_log(path) -> bool:
    """Leaves tuned as they are (any sign): logarithms already (``log_*``) and ``adapt``."""
    return str(path[-1]).startswith("log_") or path[-1] == "adapt"


def tunable_parameters(config: TrackerConfig | None = None) -> tuple[str, ...]:
    """Names of the float leaves of a tracker configuration that the causal stream uses.

    Discovered from the PyTree, so new float fields appear automatically. Short names
    (``"horizon"``, ``"log_switch_rate"``) are used when unique, dotted paths otherwise
    (``"imm.position_models.0.log_q"``: the first position model of the IMM); both forms are
    accepted wherever a parameter name is expected. With the IMM filter (the default) the
    single-model ``kalman`` leaves are not listed (the causal stream does not use them).

    Arguments:
        config: the configuration (default ``TrackerConfig()``, the IMM filter).

    Returns:
        The names, in PyTree order.
    """
    return tuple(_names(_leaf_paths(TrackerConfig() if config is None else config)))


def default_parameters(config: TrackerConfig | None = None) -> tuple[str, ...]:
    """The parameters :func:`tune_tracker` tunes when none are named.

    * single-model filter: :data:`DEFAULT_PARAMETERS` (its process and measurement noise, the
      horizon);
    * IMM filter: every model's ``log_q`` (position and rotation), ``log_switch_rate`` and the
      ``horizon``. The measurement noise stays as configured: it is a property of the sensor
      (known, or estimated with :func:`phjax.tracking.noise.estimate_measurement_noise`), and
      tuned together with the process noise it leaves a nearly flat direction. Tuning may
      reorder the models' densities; ``TrackerConfig.adapt`` assumes the quietest model first.

    Arguments:
        config: the configuration (default ``TrackerConfig()``).

    Returns:
        Parameter names accepted by :func:`make_problem` and :func:`tune_tracker`.
    """
    config = TrackerConfig() if config is None else config
    if config.imm is None:
        return DEFAULT_PARAMETERS
    models = [f"imm.{part}.{i}.log_q" for part in ("position_models", "rotation_models")
              for i in range(len(getattr(config.imm, part)))]
    return (*models, "log_switch_rate", "horizon")


def _resolve(config: TrackerConfig, parameters: Sequence[str]) -> tuple[tuple, ...]:
    """Attribute / index paths of the named parameters (validated)."""
    if isinstance(parameters, str):
        parameters = (parameters,)
    paths = _float_leaf_paths(config)
    unknown = [p for p in parameters if p not in paths]
    if unknown:
        hint = ""
        if config.imm is not None and set(unknown) & set(tunable_parameters(
                TrackerConfig(imm=None, kalman=config.kalman))):
            hint = (" (single-model filter parameters: this configuration uses the IMM; "
                    "TrackerConfig(imm=None) selects the single-model filter)")
        raise ValueError(f"unknown tracker parameter(s) {unknown}{hint}; tunable float leaves "
                         f"are {list(tunable_parameters(config))}")
    if len(parameters) == 0:
        raise ValueError("no parameter to tune")
    resolved = tuple(paths[p] for p in parameters)
    if len(set(resolved)) != len(resolved):
        raise ValueError(f"parameters named twice: {list(parameters)}")
    return resolved


def check_parameters(config: TrackerConfig, parameters: Sequence[str]) -> tuple[str, ...]:
    """Validate parameter names for ``config`` (as :func:`make_problem` does, without data).

    Arguments:
        config: the configuration to tune.
        parameters: names (short or dotted, see :func:`tunable_parameters`).

    Returns:
        The names as a tuple.

    Raises:
        ValueError: unknown, repeated or no names.
    """
    parameters = (parameters,) if isinstance(parameters, str) else tuple(parameters)
    _resolve(config, parameters)
    return parameters


def _get(tree, path):
    for key in path:
        tree = tree[key] if isinstance(key, int) else getattr(tree, key)
    return tree


def _with_values(config: TrackerConfig, paths, values) -> TrackerConfig:
    return eqx.tree_at(lambda c: [_get(c, p) for p in paths], config, list(values))


def _arrays_config(config: TrackerConfig, dtype) -> TrackerConfig:
    """``config`` with every float leaf a 0-d array of ``dtype`` (dynamic under ``filter_jit``)."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype) if _is_float_leaf(x) else x, config)


def _check_positive(config: TrackerConfig, paths) -> None:
    for p in paths:
        v = _get(config, p)
        if not _is_log(p) and not np.all(np.asarray(v) > 0):
            raise ValueError(f"{_dotted(p)} = {v}: tuned parameters must be positive "
                             "(they are optimised in log space)")


# ------------------------------------------------------------------------------------ data
class TuningData(eqx.Module):
    """Recordings prepared for the loss, padded to common lengths and stacked (axis 0 = recording).

    Built by :func:`prepare_recordings` (simulated measurements) or :func:`tuning_data` (given
    measurements). Times are relative to each recording's first measurement, positions to its
    first known ground-truth position at a render time.

    Fields:
        times: ``(R, N)`` measurement times, s (padding: NaN frames after the end).
        positions: ``(R, N, 3)`` measured positions, m (NaN = lost frame).
        quaternions: ``(R, N, 4)`` measured orientations, wxyz.
        render_times: ``(R, M)`` render times, s.
        render_mask: ``(R, M)`` render samples that count (``False`` for padding).
        gt_positions: ``(R, M, 3)`` ground truth at the render times (NaN in ground-truth gaps
            and for orientation-only recordings).
        gt_quaternions: ``(R, M, 4)`` ground-truth orientations at the render times.
        reference: ``(R, 4)`` ``[E_p, E_r, J_p, J_r]`` of the reference stream (m, rad, m/s^3,
            rad/s^3), NaN where a term is unavailable (e.g. positions of orientation-only data).
    """

    times: Float[Array, "R N"]
    positions: Float[Array, "R N 3"]
    quaternions: Float[Array, "R N 4"]
    render_times: Float[Array, "R M"]
    render_mask: Bool[Array, "R M"]
    gt_positions: Float[Array, "R M 3"]
    gt_quaternions: Float[Array, "R M 4"]
    reference: Float[Array, "R 4"]

    @property
    def num_recordings(self) -> int:
        return int(self.times.shape[0])


def _as_traj(rec, name="ground-truth"):
    t, p, q = (np.asarray(x, np.float64) for x in (rec[0], rec[1], rec[2]))
    if t.ndim != 1 or p.shape != (t.shape[0], 3) or q.shape != (t.shape[0], 4) or t.size < 2:
        raise ValueError(f"each {name} recording must be (times (n,), positions (n, 3), "
                         "quaternions (n, 4)) "
                         f"with n >= 2; got shapes {t.shape}, {p.shape}, {q.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError(f"{name} times must be finite and strictly increasing")
    return t, p, q


def prepare_recordings(
    ground_truths: Sequence,
    *,
    sensor: SensorModel | None = None,
    render_rate: float = 120.0,
    seed: int = 0,
    seconds: float | None = None,
    reference_config: KalmanConfig | None = None,
    max_gt_gap: float = 0.1,
    dtype=None,
) -> TuningData:
    """Simulate measurements from ground-truth trajectories and stack them for :func:`tracker_loss`.

    Arguments:
        ground_truths: sequence of ``(times, positions, quaternions)`` (e.g.
            :class:`phjax.io.Trajectory`), or one NaN-padded batch ``(times (R, n),
            positions (R, n, 3), quaternions (R, n, 4))`` (:func:`phjax.batch.pad_recordings`);
            NaN positions = orientation-only.
        sensor: the :class:`~phjax.SensorModel` (default ``SensorModel()``: 30 Hz, 5 mm,
            1 degree, 5 % dropouts).
        render_rate: render rate, Hz.
        seed: recording ``i`` is sampled with seed ``seed + i`` (deterministic loss).
        seconds: keep only the first ``seconds`` of each recording (``None``: all).
        reference_config: Kalman noise of the reference stream used for normalisation (default
            the tuned values :data:`phjax.tracking.baselines.TUNED` ``["kalman"]``).
        max_gt_gap: render samples inside ground-truth gaps longer than this (s) are ignored.
        dtype: floating dtype of the arrays (default: JAX's default float).

    Returns:
        A :class:`TuningData`.
    """
    from ..motion.resample import interpolate_poses, snap_to_frames
    from ..motion.simulate import simulate_measurements

    sensor = SensorModel() if sensor is None else sensor
    if not render_rate > 0:
        raise ValueError(f"render_rate must be positive, got {render_rate}")
    if (isinstance(ground_truths, tuple) and len(ground_truths) == 3
            and np.ndim(ground_truths[0]) == 2):  # a NaN-padded batch (times (R, n), ...)
        from ..batch import unpad

        ground_truths = unpad(*ground_truths)
    if len(ground_truths) == 0:
        raise ValueError("need at least one recording")
    recs = []
    for i, rec in enumerate(ground_truths):
        t, p, q = _as_traj(rec)
        t = t - t[0]
        if seconds is not None:
            keep = t <= seconds
            t, p, q = t[keep], p[keep], q[keep]
        frames = simulate_measurements(seed + i, t, p, q, sensor)
        mt, mp, mq = (np.asarray(x, np.float64) for x in frames)
        ok = np.isfinite(mq).all(-1)
        if not ok.any():
            raise ValueError(f"recording {i}: the simulated sensor produced no valid measurement")
        start = mt[ok][0] + 1.0 / float(sensor.rate)
        # snapped with the simulated times' own rounding (float32 without jax_enable_x64)
        r = snap_to_frames(np.asarray(frames[0]), np.arange(start, t[-1], 1.0 / render_rate))
        if r.size < 4:
            raise ValueError(f"recording {i} is too short ({t[-1]:.3g} s) for the jerk terms")
        gp, gq = interpolate_poses(t, p, q, r, max_gap=max_gt_gap)
        recs.append((mt, mp, mq, r, gp, gq))
    return tuning_data(recs, reference_config=reference_config, dtype=dtype)


def _as_measured(i, rec):
    """Checked float64 arrays of one recording of :func:`tuning_data`: render times snapped
    onto coincident frame times (with the frame times' own rounding), repeated measurement
    times dropped (the first kept, as :func:`phjax.track` does)."""
    from ..motion.resample import snap_to_frames

    if len(rec) != 6:
        raise ValueError(f"recording {i}: expected (times, positions, quaternions, render_times, "
                         f"gt_positions, gt_quaternions), got {len(rec)} items")
    t, p, q, r, gp, gq = (np.asarray(x, np.float64) for x in rec)
    n, m = t.shape[0] if t.ndim == 1 else -1, r.shape[0] if r.ndim == 1 else -1
    if (n < 1 or p.shape != (n, 3) or q.shape != (n, 4) or m < 0 or gp.shape != (m, 3)
            or gq.shape != (m, 4)):
        raise ValueError(f"recording {i}: shapes must be times (n,), positions (n, 3), "
                         "quaternions (n, 4), render_times (m,), gt_positions (m, 3), "
                         f"gt_quaternions (m, 4); got {t.shape}, {p.shape}, {q.shape}, "
                         f"{r.shape}, {gp.shape}, {gq.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise ValueError(f"recording {i}: measurement times must be finite and non-decreasing")
    if m < 4 or not np.all(np.isfinite(r)) or np.any(np.diff(r) <= 0):
        raise ValueError(f"recording {i}: render times must be finite, strictly increasing and "
                         f"at least 4 (for the jerk terms); got {m}")
    if not (np.isfinite(q).all(-1) & (np.linalg.norm(q, axis=-1) > 0)).any():
        raise ValueError(f"recording {i}: no valid orientation measurement")
    r = snap_to_frames(np.asarray(rec[0]), r)
    first = np.concatenate([[True], np.diff(t) > 0])
    return t[first], p[first], q[first], r, gp, gq


def measured_recording(
    ground_truth,
    measurements,
    *,
    render_rate: float = 120.0,
    seconds: float | None = None,
    align: bool = False,
    max_gt_gap: float = 0.1,
) -> tuple[np.ndarray, ...]:
    """One recording of :func:`tuning_data` from a real pose stream and its ground truth.

    Arguments:
        ground_truth: ``(times, positions, quaternions)`` (e.g. :class:`phjax.io.Trajectory`
            of a motion-capture file; NaN positions = orientation only).
        measurements: ``(times, positions, quaternions)`` of the stream the tracker will see
            (e.g. a SLAM or head-pose estimate), on the ground truth's clock.
        render_rate: render rate, Hz; render times run from one median frame interval after
            the first valid measurement to the last measurement, inside the ground truth.
        seconds: keep only the first ``seconds`` of the measurements (``None``: all).
        align: first move the measurements into the ground truth's frame by the rigid
            transform that best maps their positions onto the ground truth interpolated at
            their times (:func:`phjax.vision.alignment.align`; evo's SE(3) Umeyama alignment),
            applied to positions and orientations. Without it they must be in that frame.
        max_gt_gap: ground truth inside gaps longer than this (s) is unknown (NaN).

    Returns:
        ``(times, positions, quaternions, render_times, gt_positions, gt_quaternions)``.

    Raises:
        ValueError: malformed input, no overlap with the ground truth, or too few render
            samples.
    """
    from ..motion.resample import interpolate_poses
    from ..quaternion import quat_mul

    gt_t, gt_p, gt_q = _as_traj(ground_truth)
    t, p, q = _as_traj(measurements, "measurement")
    if seconds is not None:
        keep = t - t[0] <= seconds
        t, p, q = t[keep], p[keep], q[keep]
    # JAX sees times relative to the ground truth's start (Unix times in float32 would be
    # rounded to minutes when jax_enable_x64 is off)
    o = gt_t[0]
    if align:
        from ..vision.alignment import AlignmentStatus
        from ..vision.alignment import align as rigid_fit

        at_t, _ = interpolate_poses(gt_t - o, gt_p, gt_q, t - o, max_gap=max_gt_gap)
        inside = (t >= gt_t[0]) & (t <= gt_t[-1])
        fit = rigid_fit(p, np.where(inside[:, None], np.asarray(at_t), np.nan))
        if int(fit.status) != AlignmentStatus.OK:
            raise ValueError("align: the measured positions do not determine a rigid transform "
                             "onto the ground truth (too few, or collinear, overlapping poses)")
        rot, trans, qr = (np.asarray(x, np.float64)
                          for x in (fit.rotation, fit.translation, fit.quaternion))
        p = p @ rot.T + trans
        q = np.asarray(quat_mul(qr, q), np.float64)
    ok = np.isfinite(q).all(-1)
    if not ok.any():
        raise ValueError("measurements: no valid orientation")
    frame = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    start = max(t[ok][0] + frame, gt_t[0])
    r = np.arange(start, min(t[-1], gt_t[-1]), 1.0 / render_rate)
    if r.size < 4:
        raise ValueError(f"measurements and ground truth overlap for too short a time "
                         f"({max(0.0, min(t[-1], gt_t[-1]) - start):.3g} s) for the jerk terms")
    gp, gq = (np.asarray(x, np.float64)
              for x in interpolate_poses(gt_t - o, gt_p, gt_q, r - o, max_gap=max_gt_gap))
    return t, p, q, r, gp, gq


def tuning_data(
    recordings: Sequence,
    *,
    reference_config: KalmanConfig | None = None,
    dtype=None,
) -> TuningData:
    """Stack recordings whose measurements are given (real or simulated) for :func:`tracker_loss`.

    Use it to tune on a real pose stream (e.g. a SLAM or face-tracking estimate expressed in
    the ground truth's frame); :func:`prepare_recordings` simulates the measurements instead.
    Times are made relative to each recording's first measurement and positions to its first
    known ground-truth position (the tracker is equivariant to both; this keeps float32 and
    the jerk terms accurate with e.g. Unix timestamps). Render times that equal a frame time up
    to rounding are set to it (:func:`phjax.motion.resample.snap_to_frames`), so a sample
    rendered at a frame's own instant sees that frame.

    Arguments:
        recordings: sequence of ``(times (n,), positions (n, 3), quaternions (n, 4),
            render_times (m,), gt_positions (m, 3), gt_quaternions (m, 4))``: the camera-rate
            measurements in s, m, wxyz (non-decreasing times, repeats dropped as by
            :func:`phjax.track`; NaN = lost frame; positions all
            NaN = orientation only, tracked as a fixed point like :func:`phjax.track`), the
            render times (strictly increasing, at least 4) and the ground truth at them (NaN
            where unknown: those samples do not count).
        reference_config: Kalman noise of the reference stream used for normalisation (default
            the tuned values :data:`phjax.tracking.baselines.TUNED` ``["kalman"]``).
        dtype: floating dtype of the arrays (default: JAX's default float).

    Returns:
        A :class:`TuningData` (recordings padded to common lengths and stacked).
    """
    from .baselines import TUNED, kalman_extrapolation

    if reference_config is None:
        reference_config = KalmanConfig(**TUNED["kalman"])
    if len(recordings) == 0:
        raise ValueError("need at least one recording")
    recs = []
    for i, rec in enumerate(recordings):
        mt, mp, mq, r, gp, gq = _as_measured(i, rec)
        t0 = mt[0]
        mt, r = mt - t0, r - t0
        has_pos = np.isfinite(mp).any()
        known = np.isfinite(gp).all(-1)
        origin = gp[np.argmax(known)] if known.any() else (
            mp[np.argmax(np.isfinite(mp).all(-1))] if has_pos else np.zeros(3))
        mp, gp = mp - origin, gp - origin
        if not has_pos:  # orientation only: track a fixed point (as track does)
            ok = np.isfinite(mq).all(-1)
            mp = np.where(ok[:, None], 0.0, np.nan) * np.ones((1, 3))
        rp, rq = (np.asarray(x, np.float64)
                  for x in kalman_extrapolation(mt, mp, mq, r, config=reference_config))
        if not has_pos:
            rp = np.full_like(rp, np.nan)
        ref = np.asarray(stream_metrics(r, rp, rq, gp, gq), np.float64)
        recs.append((mt, mp, mq, r, gp, gq, np.where(ref > 0, ref, np.nan)))
    n = max(x[0].size for x in recs)
    m = max(x[3].size for x in recs)
    cols = [[] for _ in range(8)]
    for mt, mp, mq, r, gp, gq, ref in recs:
        pad_n, pad_m = n - mt.size, m - r.size
        # padding frames come 1 s after the last real frame and render time; padding render
        # samples (the only ones that may reach them) are masked out
        t_pad = max(mt[-1], r[-1]) + 1.0 + np.arange(pad_n)
        cols[0].append(np.concatenate([mt, t_pad]))
        cols[1].append(np.concatenate([mp, np.full((pad_n, 3), np.nan)]))
        cols[2].append(np.concatenate([mq, np.full((pad_n, 4), np.nan)]))
        cols[3].append(np.concatenate([r, r[-1] + (r[-1] - r[-2]) * np.arange(1, pad_m + 1)]))
        cols[4].append(np.arange(m) < r.size)
        cols[5].append(np.concatenate([gp, np.full((pad_m, 3), np.nan)]))
        cols[6].append(np.concatenate([gq, np.full((pad_m, 4), np.nan)]))
        cols[7].append(ref)
    dtype = jnp.zeros((), float).dtype if dtype is None else dtype
    arr = [jnp.asarray(np.stack(c), bool if k == 4 else dtype) for k, c in enumerate(cols)]
    return TuningData(*arr)


# ------------------------------------------------------------------------------ the stream
def _stream(config: TrackerConfig, times, positions, quaternions, render_times):
    """The causal stream of :func:`phjax.track` on prepared (sorted, de-duplicated) arrays,
    traceable in the data: ``lax.scan`` of :func:`tracker_update`, then :func:`tracker_sample`
    of the latest state with ``t <= tau``. NaN before the first valid measurement."""
    state0 = tracker_init(config, times[0], times.dtype)

    def body(state, meas):
        new = tracker_update(config, state, *meas)
        return new, new

    _, states = jax.lax.scan(body, state0, (times, positions, quaternions))
    idx = jnp.searchsorted(times, render_times, side="right") - 1
    sel = jax.tree.map(lambda x: x[jnp.maximum(idx, 0)], states)
    p, q = jax.vmap(lambda s, tau: tracker_sample(config, s, tau))(sel, render_times)
    nan = jnp.where(idx < 0, jnp.nan, 0.0)[:, None].astype(p.dtype)
    return p + nan, q + nan


# ----------------------------------------------------------------------------------- terms
@jax.jit
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


def loss_terms(config: TrackerConfig, data: TuningData) -> Float[Array, "*R 4"]:
    """``[E_p, E_r, J_p, J_r]`` (m, rad, m/s^3, rad/s^3) of the causal stream on each recording.

    ``data`` may have any leading batch axes ``R`` (e.g. ``(sweeps, recordings)``) and follow
    the NaN padding rule of :mod:`phjax.batch`: NaN measurement times are lost frames after the
    recording's end, NaN render times are masked samples (values and gradients stay finite).
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
        sp, sq = _stream(config, t, p, q, r)
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


class TuningProblem(eqx.Module):
    """:func:`tracker_loss` as a function of log-parameters ``y``.

    ``y`` holds ``log(value)`` of each tuned leaf, except for leaves that are logarithms
    already (named ``log_*``, e.g. the IMM's ``log_q`` and ``log_switch_rate``) and ``adapt``
    (any sign), which ``y`` holds as they are.

    Fields:
        data: the recordings.
        config: base configuration (float leaves as arrays); the tuned leaves are replaced.
        names: names of the tuned leaves, as given (static).
        paths: their attribute paths (static).
        lam, position_weight, rotation_weight: loss weights (arrays, so changing them does not
            recompile).
        normalize: see :func:`tracker_loss` (static).
    """

    data: TuningData
    config: TrackerConfig
    names: tuple[str, ...] = eqx.field(static=True)
    paths: tuple[tuple[str | int, ...], ...] = eqx.field(static=True)
    lam: Float[Array, ""]
    position_weight: Float[Array, ""]
    rotation_weight: Float[Array, ""]
    normalize: bool = eqx.field(static=True, default=True)

    @property
    def parameters(self) -> tuple[str, ...]:
        """Names of the tuned leaves (order of the log-parameter vector)."""
        return self.names

    def params_from_config(self, config: TrackerConfig) -> Float[Array, " P"]:
        """Log-parameters of ``config``'s tuned leaves."""
        dtype = self.data.times.dtype
        return jnp.stack([jnp.asarray(_get(config, p), dtype) if _is_log(p)
                          else jnp.log(jnp.asarray(_get(config, p), dtype)) for p in self.paths])

    def config_from_params(self, y: Float[Array, " P"]) -> TrackerConfig:
        """The base configuration with the tuned leaves set from ``y`` (``exp(y)``, or ``y``
        itself for ``log_*`` leaves and ``adapt``)."""
        return _with_values(self.config, self.paths, _leaf_values(self.paths, y, jnp))

    def loss_and_terms(self, y: Float[Array, " P"]) -> tuple[Float[Array, ""], Float[Array, "R 4"]]:
        """:func:`tracker_loss` at log-parameters ``y`` and the :func:`loss_terms` it combines."""
        terms = loss_terms(self.config_from_params(y), self.data)
        loss = _combine(terms.reshape(-1, 4), self.data.reference.reshape(-1, 4), self.lam,
                        self.position_weight, self.rotation_weight, self.normalize)
        return loss, terms

    def loss(self, y: Float[Array, " P"]) -> Float[Array, ""]:
        """:func:`tracker_loss` at log-parameters ``y``."""
        return self.loss_and_terms(y)[0]

    def value_and_grad(
        self, y: Float[Array, " P"], autodiff_mode: str = "fwd"
    ) -> tuple[Float[Array, ""], Float[Array, " P"], Float[Array, "R 4"]]:
        """Loss, its gradient with respect to the log-parameters, and the per-recording
        :func:`loss_terms` (one program, jitted once per data shape and parameter set).

        Arguments:
            y: log-parameters.
            autodiff_mode: ``"fwd"`` (one JVP per parameter; the default: for the few
                parameters of a tracker it compiles about three times faster than reverse mode)
                or ``"bwd"`` (reverse mode; cheaper to run with many parameters).

        Returns:
            ``(loss, gradient (P,), terms (R, 4))``.
        """
        if autodiff_mode not in ("fwd", "bwd"):
            raise ValueError(f"autodiff_mode must be 'fwd' or 'bwd', got {autodiff_mode!r}")
        return _value_and_grad(self, jnp.asarray(y, self.data.times.dtype), autodiff_mode)


def make_problem(
    data: TuningData,
    *,
    lam: float = 0.0,
    config: TrackerConfig | None = None,
    parameters: Sequence[str] | None = None,
    position_weight: float = 1.0,
    rotation_weight: float = 1.0,
    normalize: bool = True,
) -> TuningProblem:
    """A :class:`TuningProblem` (validates the parameter names and positivity).

    ``config`` defaults to ``TrackerConfig()`` (the IMM filter), ``parameters`` to
    :func:`default_parameters` of the config; the other arguments as in :func:`tune_tracker`.
    """
    config = TrackerConfig() if config is None else config
    parameters = default_parameters(config) if parameters is None else parameters
    parameters = (parameters,) if isinstance(parameters, str) else tuple(parameters)
    paths = _resolve(config, parameters)
    _check_positive(config, paths)
    if not (float(lam) >= 0 and float(position_weight) >= 0 and float(rotation_weight) >= 0):
        raise ValueError("lam and the weights must be non-negative")
    dtype = data.times.dtype
    return TuningProblem(data, _arrays_config(config, dtype), parameters, paths,
                         jnp.asarray(lam, dtype),
                         jnp.asarray(position_weight, dtype), jnp.asarray(rotation_weight, dtype),
                         normalize)


def _leaf_values(paths, y, xp):
    """Leaf values from log-parameters ``y`` (``xp``: ``jnp`` inside traces, ``np`` outside)."""
    return [y[i] if _is_log(p) else xp.exp(y[i]) for i, p in enumerate(paths)]


# ---------------------------------------------------------------------------------- solving
@eqx.filter_jit
def _value_and_grad(problem: TuningProblem, y, autodiff_mode: str):
    """``(loss, gradient, terms)`` at log-parameters ``y``."""
    if autodiff_mode == "fwd":
        # one JVP per parameter in a loop: compiles in about a third of the time of the reverse
        # mode (and faster than a vmapped JVP); the stream has few parameters
        basis = jnp.eye(y.shape[0], dtype=y.dtype)
        (f, terms), (g, _) = jax.lax.map(
            lambda v: jax.jvp(problem.loss_and_terms, (y,), (v,)), basis)
        return f[0], g, terms[0]
    (f, terms), g = jax.value_and_grad(problem.loss_and_terms, has_aux=True)(y)
    return f, g, terms


# Ask-tell with optimistix: BFGS evaluates its objective only at ``state.y_eval`` (the trial
# point chosen by the previous step), so the loss and gradient there are computed beforehand by
# the separately compiled ``_value_and_grad`` and handed to the solver step as ``args``. The
# solver step then compiles in about a second instead of inlining the whole differentiated
# stream, and the expensive program is compiled once and shared with
# :meth:`TuningProblem.value_and_grad`. Evaluating the told objective anywhere else gives NaN
# (so a change of that protocol would be loud, not silently wrong).
class _Told(eqx.Module):
    y: Array
    f: Array
    g: Array


@jax.custom_jvp
def _told_value(y, told_y, told_f, told_g):
    return jnp.where(jnp.all(y == told_y), told_f, jnp.nan)


@_told_value.defjvp
def _told_value_jvp(primals, tangents):
    y, told_y, told_f, told_g = primals
    return _told_value(y, told_y, told_f, told_g), jnp.dot(told_g, tangents[0])


def _told_objective(y, told: _Told):
    return _told_value(y, told.y, told.f, told.g), None


_OPTIONS: dict[str, Any] = {}
_TAGS: frozenset = frozenset()


@eqx.filter_jit
def _solver_init(solver, y):
    told = _Told(y, jnp.zeros((), y.dtype), jnp.zeros_like(y))
    f_struct = jax.ShapeDtypeStruct((), y.dtype)
    return solver.init(_told_objective, y, told, _OPTIONS, f_struct, None, _TAGS)


@eqx.filter_jit
def _solver_step(solver, y, state, told):
    y, state, _ = solver.step(_told_objective, y, told, _OPTIONS, state, _TAGS)
    done, result = solver.terminate(_told_objective, y, told, _OPTIONS, state, _TAGS)
    return y, state, done, result


def _bfgs(value_and_grad, y0, *, max_steps, rtol, atol, callback=None):
    """Minimise with ``optimistix.BFGS`` by ask-tell stepping (see ``_Told``).

    ``value_and_grad(y) -> (f, g, aux)`` is called once per step at the solver's trial point;
    ``callback(step, y, loss, trial_loss, accepted, step_size, aux)`` after every step.

    Returns:
        ``(y, result, steps, num_accepted, loss_history, trial_losses)``.
    """
    solver = optx.BFGS(rtol=rtol, atol=atol)
    y = jnp.asarray(y0)
    state = _solver_init(solver, y)
    history, trials = [], []
    done, result, steps = False, optx.RESULTS.successful, 0
    while steps < max_steps and not done:
        y_eval = state.y_eval
        f, g, aux = value_and_grad(y_eval)
        finite = bool(jnp.isfinite(f) & jnp.all(jnp.isfinite(g)))
        if steps == 0 and not finite:
            raise ValueError(f"the loss or its gradient at the start is not finite (loss "
                             f"{float(f)}, gradient {np.asarray(g)})")
        told = _Told(y_eval, jnp.where(finite, f, jnp.nan), jnp.where(finite, g, 0))
        accepted_before = int(state.num_accepted_steps)
        y, state, done, result = _solver_step(solver, y, state, told)
        steps += 1
        done = bool(done)
        accepted = int(state.num_accepted_steps) > accepted_before
        history.append(float(state.f_info.f))
        trials.append(float(f) if finite else float("nan"))
        if callback is not None:
            callback(steps, y, history[-1], trials[-1], accepted,
                     float(state.search_state.step_size), aux)
    if not done:
        result = optx.RESULTS.max_steps_reached
    return (y, result, steps, int(state.num_accepted_steps), np.asarray(history),
            np.asarray(trials))


class StepInfo(NamedTuple):
    """Progress of one solver step (passed to the ``progress`` callback of :func:`tune_tracker`).

    Fields:
        step: 1-based step number.
        loss: loss at the current (last accepted) iterate.
        trial_loss: loss at the point evaluated in this step (NaN if not finite there).
        accepted: whether the line search accepted that point.
        step_size: line-search step size of the next trial.
        parameters: current (accepted) parameter values by name.
    """

    step: int
    loss: float
    trial_loss: float
    accepted: bool
    step_size: float
    parameters: dict[str, float]


@dataclasses.dataclass(frozen=True)
class TuningResult:
    """Outcome of :func:`tune_tracker`.

    Attributes:
        config: the tuned configuration (same as the first return value).
        result: the ``optimistix.RESULTS`` status (``successful`` on convergence,
            ``max_steps_reached`` when ``max_steps`` ran out, ...).
        num_steps: solver steps taken (= loss and gradient evaluations).
        num_accepted_steps: steps whose trial point the line search accepted.
        loss_history: loss of the current iterate after each step (``[0]`` is the initial loss).
        trial_losses: loss at each evaluated point.
        initial_loss, final_loss: loss of the start and of the returned configuration.
        initial_parameters, parameters: tuned values by name, before and after.
        initial_terms, terms: ``(R, 4)`` :func:`loss_terms` ``[E_p, E_r, J_p, J_r]`` per
            recording (m, rad, m/s^3, rad/s^3) at the start and at the result.
        reference: ``(R, 4)`` the same terms of the reference stream
            (:attr:`TuningData.reference`); ``terms / reference`` are the ratios the
            normalised loss combines.
    """

    config: TrackerConfig
    result: Any
    num_steps: int
    num_accepted_steps: int
    loss_history: np.ndarray
    trial_losses: np.ndarray
    initial_loss: float
    final_loss: float
    initial_parameters: dict[str, float]
    parameters: dict[str, float]
    initial_terms: np.ndarray
    terms: np.ndarray
    reference: np.ndarray

    @property
    def successful(self) -> bool:
        """Whether the solver converged (``result == optimistix.RESULTS.successful``)."""
        return bool(self.result == optx.RESULTS.successful)

    @property
    def message(self) -> str:
        """Short status: ``"converged"``, ``"max_steps_reached"`` or optimistix's message."""
        if self.successful:
            return "converged"
        if self.result == optx.RESULTS.max_steps_reached:
            return "max_steps_reached"
        return optx.RESULTS[self.result]


def _values(problem: TuningProblem, y) -> dict[str, float]:
    y = np.asarray(y, np.float64)
    return {n: float(v) for n, v in zip(problem.parameters, _leaf_values(problem.paths, y, np))}


def tune_tracker(
    recordings: TuningData | Sequence,
    *,
    lam: float = 0.3,
    config: TrackerConfig | None = None,
    parameters: Sequence[str] | None = None,
    max_steps: int = 50,
    rtol: float = 1e-3,
    atol: float = 1e-4,
    position_weight: float = 1.0,
    rotation_weight: float = 1.0,
    normalize: bool = True,
    progress: Callable[[StepInfo], None] | None = None,
    autodiff_mode: str = "fwd",
    **prepare_kwargs,
) -> tuple[TrackerConfig, TuningResult]:
    """Tune the tracker's parameters by BFGS on :func:`tracker_loss` (log parameterisation).

    ``optimistix.BFGS`` (Armijo backtracking) is stepped from Python: each step evaluates the
    loss and gradient at the solver's trial point with :meth:`TuningProblem.value_and_grad`
    (compiled once per data shape and parameter set, so calls with other ``lam``, weights or
    start values do not recompile) and hands them to ``solver.step``. Failures never raise:
    the status is in :attr:`TuningResult.result` (as ``optimistix.minimise(..., throw=False)``).
    A trial point with a non-finite loss or gradient counts as a failed evaluation and is
    rejected by the line search.

    Arguments:
        recordings: a :class:`TuningData`, or ground-truth trajectories passed to
            :func:`prepare_recordings` with ``prepare_kwargs`` (``sensor``, ``render_rate``,
            ``seed``, ``seconds``, ``reference_config``, ``max_gt_gap``, ``dtype``).
        lam: weight of the jerk terms (dimensionless, see the module docs).
        config: start configuration (default ``TrackerConfig()``, the IMM filter); untuned
            fields are kept.
        parameters: names of the float leaves to tune (see :func:`tunable_parameters`;
            default :func:`default_parameters` of ``config``).
        max_steps: maximum number of solver steps (loss and gradient evaluations).
        rtol, atol: BFGS termination tolerances (on the log-parameters and the loss).
        position_weight, rotation_weight, normalize: see :func:`tracker_loss`.
        progress: optional callback receiving a :class:`StepInfo` after every step.
        autodiff_mode: ``"fwd"`` or ``"bwd"``, see :meth:`TuningProblem.value_and_grad`.

    Returns:
        ``(config, result)``: the tuned :class:`~phjax.TrackerConfig` (Python floats) and a
        :class:`TuningResult`.

    Raises:
        ValueError: bad arguments, or a non-finite loss or gradient at the start.
    """
    if isinstance(recordings, TuningData):
        if prepare_kwargs:
            raise ValueError(f"unexpected arguments {sorted(prepare_kwargs)} with prepared "
                             "TuningData")
        data = recordings
    else:
        data = prepare_recordings(recordings, **prepare_kwargs)
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    base = TrackerConfig() if config is None else config
    problem = make_problem(data, lam=lam, config=base, parameters=parameters,
                           position_weight=position_weight, rotation_weight=rotation_weight,
                           normalize=normalize)
    y0 = problem.params_from_config(base)
    terms_seen = {}

    def on_step(step, y, loss, trial, accepted, step_size, terms):
        if accepted:
            terms_seen.setdefault("initial", terms)
            terms_seen["current"] = terms
        if progress is not None:
            progress(StepInfo(step, loss, trial, accepted, step_size, _values(problem, y)))

    y, result, steps, n_accepted, history, trials = _bfgs(
        lambda y: problem.value_and_grad(y, autodiff_mode), y0, max_steps=max_steps, rtol=rtol,
        atol=atol, callback=on_step)
    tuned = _with_values(base, problem.paths, list(_values(problem, y).values()))
    res = TuningResult(
        config=tuned,
        result=result,
        num_steps=steps,
        num_accepted_steps=n_accepted,
        loss_history=history,
        trial_losses=trials,
        initial_loss=history[0],
        final_loss=history[-1],
        initial_parameters=_values(problem, y0),
        parameters=_values(problem, y),
        initial_terms=np.asarray(terms_seen["initial"], np.float64),
        terms=np.asarray(terms_seen["current"], np.float64),
        reference=np.asarray(data.reference, np.float64),
    )
    return tuned, res


# ------------------------------------------------------------------------------------ JSON
def _jsonable(v):
    if v is None or isinstance(v, (bool, int, str)):
        return v
    a = np.asarray(v)
    if a.ndim == 0:
        return a.item()
    return a.tolist()


def _field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def config_to_dict(config: TrackerConfig, metadata: dict | None = None) -> dict:
    """JSON-ready dict of every :class:`~phjax.TrackerConfig` and :class:`~phjax.KalmanConfig`
    field (format tag, version, ``"tracker"`` and ``"kalman"`` sections, optional
    ``"metadata"``)."""
    tracker = {n: _jsonable(getattr(config, n))
               for n in _field_names(TrackerConfig) if n not in ("kalman", "imm")}
    kalman = {n: _jsonable(getattr(config.kalman, n)) for n in _field_names(KalmanConfig)}
    out = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, "tracker": tracker, "kalman": kalman,
           "imm": _imm_to_dict(config.imm)}
    if metadata:
        out["metadata"] = json.loads(json.dumps(metadata, default=_jsonable))
    return out


_MODEL_KINDS = {"cv": ConstantVelocity, "ca": ConstantAcceleration}


def _imm_to_dict(imm: IMMConfig | None) -> dict | None:
    """The IMM section: models as ``{"model": "cv" | "ca", "log_q": log density}`` and the
    other :class:`IMMConfig` fields; ``None`` for the single-model filter."""
    if imm is None:
        return None

    def models(ms):
        return [{"model": "cv" if isinstance(m, ConstantVelocity) else "ca",
                 "log_q": _jsonable(m.log_q)} for m in ms]

    rest = {n: _jsonable(getattr(imm, n)) for n in _field_names(IMMConfig)
            if n not in ("position_models", "rotation_models")}
    return {"position_models": models(imm.position_models),
            "rotation_models": models(imm.rotation_models), **rest}


def _imm_from_dict(sec, source: str) -> IMMConfig | None:
    if sec is None:
        return None
    if not isinstance(sec, dict):
        raise ValueError(f"{source}: 'imm' must be an object or null")
    sec = dict(sec)
    try:
        kw = {}
        for key in ("position_models", "rotation_models"):
            if key in sec:
                kw[key] = tuple(_MODEL_KINDS[m["model"]](log_q=float(m["log_q"]))
                                for m in sec.pop(key))
        return IMMConfig(**kw, **sec)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid imm section: {err}") from err


def config_from_dict(d: dict, source: str = "<dict>") -> TrackerConfig:
    """Inverse of :func:`config_to_dict` (missing fields take their defaults; a missing ``"imm"``
    section means the single-model filter, as in files written before the IMM existed).

    Raises:
        ValueError: wrong format tag or version, unknown sections or fields, bad values.
    """
    if not isinstance(d, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(d).__name__}")
    if d.get("format") != CONFIG_FORMAT:
        raise ValueError(f"{source}: not a phjax tracker configuration (format "
                         f"{d.get('format')!r}, expected {CONFIG_FORMAT!r})")
    version = d.get("version")
    if version != CONFIG_VERSION:
        raise ValueError(f"{source}: unsupported configuration version {version!r} "
                         f"(this phjax reads version {CONFIG_VERSION})")
    extra = set(d) - {"format", "version", "tracker", "kalman", "imm", "metadata"}
    if extra:
        raise ValueError(f"{source}: unknown top-level key(s) {sorted(extra)}")
    sections = {}
    for key, cls, skip in (("tracker", TrackerConfig, {"kalman", "imm"}),
                           ("kalman", KalmanConfig, set())):
        sec = d.get(key, {})
        if not isinstance(sec, dict):
            raise ValueError(f"{source}: '{key}' must be an object")
        known = [n for n in _field_names(cls) if n not in skip]
        unknown = set(sec) - set(known)
        if unknown:
            raise ValueError(f"{source}: unknown {key} field(s) {sorted(unknown)}; known: {known}")
        for name, value in sec.items():
            scalar = value is None or isinstance(value, (int, float, str))
            if isinstance(value, bool) or not scalar:
                raise ValueError(f"{source}: {key}.{name} has an invalid value {value!r}")
        sections[key] = sec
    try:
        kalman = KalmanConfig(**sections["kalman"])
        # no "imm" section: a file from before the IMM, i.e. the single-model stream
        imm = _imm_from_dict(d.get("imm"), source)
        return TrackerConfig(kalman=kalman, imm=imm, **sections["tracker"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid configuration: {err}") from err


def save_config(
    path: str | os.PathLike, config: TrackerConfig, metadata: dict | None = None
) -> Path:
    """Write ``config`` (all fields, versioned) as JSON; ``metadata`` is stored alongside.

    Returns:
        The path written.
    """
    path = Path(path)
    path.write_text(json.dumps(config_to_dict(config, metadata), indent=2) + "\n")
    return path


def load_config(path: str | os.PathLike) -> TrackerConfig:
    """Read a configuration written by :func:`save_config` (or ``phjax tune``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not valid JSON, wrong format/version, unknown fields or bad values.
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err
    return config_from_dict(d, str(path))
