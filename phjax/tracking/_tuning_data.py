"""Recordings for the tuning loss (:mod:`phjax.tracking.tuning`): :class:`TuningData` and the
functions that build it, from ground truth with simulated measurements
(:func:`prepare_recordings`) or from given measurements (:func:`tuning_data`,
:func:`measured_recording`), with the reference stream's scores and the padding to common lengths.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._np_quat import np_any_part, np_valid_quaternions
from ..motion.simulate import SensorModel
from ._tuning_stream import stream_metrics
from .kalman import KalmanConfig
from .tracker import complete_one_part


class TuningData(eqx.Module):
    """Recordings prepared for the loss, padded to common lengths and stacked (axis 0 = recording).

    The common lengths are rounded up to size classes (:mod:`phjax.tracking._shapes`), so data
    sets of different lengths share one compiled loss and gradient.

    Built by :func:`prepare_recordings` (simulated measurements) or :func:`tuning_data` (given
    measurements). Times are relative to each recording's first measurement, positions to its
    first known ground-truth position at a render time.

    Fields:
        times: ``(R, N)`` measurement times, s (padding: lost frames after the end).
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
    max_gt_gap: float | None = None,
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
        max_gt_gap: render samples inside ground-truth gaps longer than this (s) are ignored,
            and the simulated sensor loses its frames there (default:
            :func:`phjax.motion.resample.ground_truth_max_gap`).
        dtype: floating dtype of the arrays (default: JAX's default float).

    Returns:
        A :class:`TuningData`.
    """
    from ..motion.resample import (
        ground_truth_max_gap,
        interpolate_poses,
        snap_to_frames,
        warn_sparse_ground_truth,
    )
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
        frames = simulate_measurements(seed + i, t, p, q, sensor, max_gt_gap=max_gt_gap)
        mt, mp, mq = (np.asarray(x, np.float64) for x in frames)
        ok = np_any_part(mp, mq)
        if not ok.any():
            raise ValueError(f"recording {i}: the simulated sensor produced no valid measurement")
        start = mt[ok][0] + 1.0 / float(sensor.rate)
        # snapped with the simulated times' own rounding (float32 without jax_enable_x64)
        r = snap_to_frames(np.asarray(frames[0]), np.arange(start, t[-1], 1.0 / render_rate))
        if r.size < 4:
            raise ValueError(f"recording {i} is too short ({t[-1]:.3g} s) for the jerk terms")
        gp, gq = interpolate_poses(t, p, q, r, max_gap=ground_truth_max_gap(t, max_gt_gap))
        warn_sparse_ground_truth(t, r, np.asarray(gp), np.asarray(gq))
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
    if not (np_valid_quaternions(q).any() or np.isfinite(p).all(-1).any()):
        raise ValueError(f"recording {i}: no valid measurement (position or orientation)")
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
    max_gt_gap: float | None = None,
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
        max_gt_gap: ground truth inside gaps longer than this (s) is unknown (NaN) (default:
            :func:`phjax.motion.resample.ground_truth_max_gap`).

    Returns:
        ``(times, positions, quaternions, render_times, gt_positions, gt_quaternions)``.

    Raises:
        ValueError: malformed input, no overlap with the ground truth, or too few render
            samples.
    """
    from ..motion.resample import ground_truth_max_gap, interpolate_poses, warn_sparse_ground_truth
    from ..quaternion import quat_mul

    gt_t, gt_p, gt_q = _as_traj(ground_truth)
    t, p, q = _as_traj(measurements, "measurement")
    max_gt_gap = ground_truth_max_gap(gt_t, max_gt_gap)
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
    ok = np_any_part(p, q)
    if not ok.any():
        raise ValueError("measurements: no valid measurement (position or orientation)")
    frame = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    start = max(t[ok][0] + frame, gt_t[0])
    r = np.arange(start, min(t[-1], gt_t[-1]), 1.0 / render_rate)
    if r.size < 4:
        raise ValueError(f"measurements and ground truth overlap for too short a time "
                         f"({max(0.0, min(t[-1], gt_t[-1]) - start):.3g} s) for the jerk terms")
    gp, gq = (np.asarray(x, np.float64)
              for x in interpolate_poses(gt_t - o, gt_p, gt_q, r - o, max_gap=max_gt_gap))
    warn_sparse_ground_truth(gt_t, r, gp, gq)
    return t, p, q, r, gp, gq


#: the fewest render samples with ground truth that make a recording's channel count in the loss
MIN_SCORED = 8


def _pad_render(r, length, *rows):
    """Render times ``r`` padded to ``length`` (continued with the mean render period: rounding
    of one difference would grow with the index), the mask of the real samples, and ``rows``
    (per render sample) padded with NaN."""
    pad = length - r.size
    period = (r[-1] - r[0]) / (r.size - 1)
    return (np.concatenate([r, r[-1] + period * np.arange(1, pad + 1)]), np.arange(length) < r.size,
            *(np.concatenate([x, np.full((pad, x.shape[1]), np.nan)]) for x in rows))


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
        A :class:`TuningData` (recordings padded to common lengths, rounded up to size classes, and stacked).
    """
    from ._shapes import MIN_FRAMES, MIN_RENDER, size_class
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
        mp, mq, (orientation_only, position_only) = complete_one_part(mp, mq)  # as track does
        rp, rq = (np.asarray(x, np.float64)
                  for x in kalman_extrapolation(mt, mp, mq, r, config=reference_config))
        if orientation_only:
            rp = np.full_like(rp, np.nan)
        if position_only:
            rq = np.full_like(rq, np.nan)
        # on the render samples padded to their size class (masked out): one compiled
        # stream_metrics per class, not per recording length
        rr, mask, *rows = _pad_render(r, size_class(r.size, MIN_RENDER), rp, rq, gp, gq)
        ref = np.asarray(stream_metrics(rr, *rows, mask=mask), np.float64)
        ref = np.where(ref > 0, ref, np.nan)
        # a channel scored at too few render samples (ground truth sparser than its gap limit)
        # does not steer the loss: a single sample's error said nothing and was taken at face
        # value
        for channel, known in ((0, np.isfinite(gp).all(-1)), (1, np.isfinite(gq).all(-1))):
            if known.sum() < MIN_SCORED:
                ref[[channel, channel + 2]] = np.nan
        recs.append((mt, mp, mq, r, gp, gq, ref))
    usable = [np.isfinite(x[6][[0, 2]]).all() or np.isfinite(x[6][[1, 3]]).all() for x in recs]
    if not any(usable):
        raise ValueError(f"no recording has ground truth at {MIN_SCORED} or more render samples "
                         "in a channel the reference stream can score (a still head, or ground "
                         "truth sparser than max_gt_gap): nothing to tune against")
    # common lengths rounded up to their size classes (phjax.tracking._shapes): data sets of
    # different lengths share one compiled loss and gradient
    n = size_class(max(x[0].size for x in recs), MIN_FRAMES)
    m = size_class(max(x[3].size for x in recs), MIN_RENDER)
    cols = [[] for _ in range(8)]
    for mt, mp, mq, r, gp, gq, ref in recs:
        pad_n = n - mt.size
        # padding frames come 1 s after the last real frame and render time; padding render
        # samples (the only ones that may reach them) are masked out
        t_pad = max(mt[-1], r[-1]) + 1.0 + np.arange(pad_n)
        cols[0].append(np.concatenate([mt, t_pad]))
        cols[1].append(np.concatenate([mp, np.full((pad_n, 3), np.nan)]))
        cols[2].append(np.concatenate([mq, np.full((pad_n, 4), np.nan)]))
        for k, x in zip((3, 4, 5, 6), _pad_render(r, m, gp, gq)):
            cols[k].append(x)
        cols[7].append(ref)
    dtype = jnp.zeros((), float).dtype if dtype is None else dtype
    arr = [jnp.asarray(np.stack(c), bool if k == 4 else dtype) for k, c in enumerate(cols)]
    return TuningData(*arr)
