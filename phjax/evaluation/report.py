"""Evaluate phjax and the baselines against ground truth under a simulated sensor.

A ground-truth trajectory is sampled by a :class:`phjax.motion.simulate.SensorModel` (30 Hz, 5 mm,
1 degree, 5 % dropouts by default); every method renders the pose at ``render_rate`` from those
measurements; :func:`phjax.evaluation.metrics.evaluate` scores each stream against the ground truth
interpolated to the render times (samples inside ground-truth gaps longer than 0.1 s are
ignored).

The baselines' parameters in :data:`TUNED` were chosen for the lowest RMSE on the development
set (``python experiments/tune_baselines.py``, grid search; see that script), so that no
baseline is handicapped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..tracking import baselines
from ..tracking.baselines import TUNED
from ..tracking.kalman import KalmanConfig
from .metrics import evaluate as evaluate_metrics
from ..motion.resample import interpolate_poses
from ..motion.simulate import SensorModel, simulate_measurements
from ..tracking.tracker import TrackerConfig, reconstruct, track

__all__ = [
    "Method",
    "TUNED",
    "default_methods",
    "EvaluationResult",
    "evaluate_recording",
    "format_table",
    "plot_evaluation",
]

def _one_euro_tuned(t, p, q, r):
    """One Euro with separately tuned position and rotation settings (then hold)."""
    pos, _ = baselines.one_euro(t, p, q, r, **TUNED["one_euro_position"])
    _, rot = baselines.one_euro(t, p, q, r, **TUNED["one_euro_rotation"])
    return pos, rot


@dataclasses.dataclass(frozen=True)
class Method:
    """A pose-stream method with the common interface ``fn(t, p, q, render_t) -> (p, q)``."""

    name: str
    fn: Callable
    causal: bool


def default_methods(tracker_config: TrackerConfig | None = None) -> list[Method]:
    """phjax causal and offline, and every baseline with its tuned parameters."""
    cfg = tracker_config if tracker_config is not None else TrackerConfig()
    kcfg = KalmanConfig(**TUNED["kalman"])
    return [
        Method("phjax (causal)", lambda t, p, q, r: track(t, p, q, r, config=cfg), True),
        Method("kalman-cv extrapolation", lambda t, p, q, r: baselines.kalman_extrapolation(
            t, p, q, r, config=kcfg), True),
        Method("one-euro + hold", _one_euro_tuned, True),
        Method("raw hold", baselines.hold, True),
        Method("phjax (offline)", lambda t, p, q, r: reconstruct(t, p, q, r, config=cfg), False),
        Method("cubic spline (scipy)", baselines.cubic_spline, False),
        Method("linear + slerp", baselines.linear_slerp, False),
    ]


@dataclasses.dataclass
class EvaluationResult:
    """Per-method metrics and the streams (for plots).

    Attributes:
        metrics: method name -> dict of :func:`phjax.evaluation.metrics.evaluate` values.
        render_times, gt_positions, gt_quaternions: the evaluation grid and ground truth there.
        measurements: ``(times, positions, quaternions)`` from the sensor model.
        streams: method name -> ``(positions, quaternions)`` at the render times.
        causal: method name -> whether it is causal.
    """

    metrics: dict[str, dict]
    render_times: np.ndarray
    gt_positions: np.ndarray
    gt_quaternions: np.ndarray
    measurements: tuple[np.ndarray, np.ndarray, np.ndarray]
    streams: dict[str, tuple[np.ndarray, np.ndarray]]
    causal: dict[str, bool]


def evaluate_recording(
    gt_times,
    gt_positions,
    gt_quaternions,
    *,
    sensor: SensorModel | None = None,
    render_rate: float = 120.0,
    seed: int = 0,
    methods: list[Method] | None = None,
    progress: bool = False,
    max_gt_gap: float = 0.1,
) -> EvaluationResult:
    """Simulate measurements from a ground-truth trajectory and score every method.

    Arguments:
        gt_times, gt_positions, gt_quaternions: ground truth (s, m (NaN for orientation-only),
            wxyz).
        sensor: sensor model (default :class:`SensorModel()`).
        render_rate: render rate, Hz.
        seed: random seed of the sensor simulation.
        methods: methods to run (default :func:`default_methods`).
        progress: show a progress bar (tqdm) over methods.
        max_gt_gap: ground-truth gaps longer than this (s) are excluded from the metrics.

    Returns:
        An :class:`EvaluationResult`.
    """
    sensor = SensorModel() if sensor is None else sensor
    methods = default_methods() if methods is None else methods
    gt_times = np.asarray(gt_times, np.float64)
    origin = gt_times[0]
    gt_t = gt_times - origin
    gt_p = np.asarray(gt_positions, np.float64)
    gt_q = np.asarray(gt_quaternions, np.float64)
    mt, mp, mq = (np.asarray(x, np.float64) for x in simulate_measurements(seed, gt_t, gt_p, gt_q, sensor))
    valid = np.isfinite(mq).all(-1)
    if not np.any(valid):
        raise ValueError("the simulated sensor produced no valid measurement")
    start = mt[valid][0] + 1.0 / sensor.rate  # let every method see at least one frame
    render = np.arange(start, gt_t[-1], 1.0 / render_rate)
    gp, gq = interpolate_poses(gt_t, gt_p, gt_q, render, max_gap=max_gt_gap)
    gp, gq = np.asarray(gp, np.float64), np.asarray(gq, np.float64)
    iterator = methods
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(methods, desc="methods", leave=False)
    metrics, streams, causal = {}, {}, {}
    for m in iterator:
        p, q = m.fn(mt, mp, mq, render)
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        streams[m.name] = (p, q)
        causal[m.name] = m.causal
        metrics[m.name] = evaluate_metrics(render, p, q, gp, gq, boundary_times=mt[valid])
    return EvaluationResult(metrics, render + origin, gp, gq, (mt + origin, mp, mq), streams, causal)


_COLUMNS = [
    ("position_rmse", "pos RMSE [mm]", 1e3, "{:.2f}"),
    ("rotation_rmse_deg", "rot RMSE [deg]", 1.0, "{:.3f}"),
    ("jerk_position", "jerk pos [m/s^3]", 1.0, "{:.1f}"),
    ("jerk_rotation", "jerk rot [rad/s^3]", 1.0, "{:.1f}"),
    ("curvature", "mean kappa [1/m]", 1.0, "{:.1f}"),
    ("torsion", "mean abs tau [1/m]", 1.0, "{:.1f}"),
    ("velocity_jump", "max vel jump [m/s]", 1.0, "{:.3f}"),
    ("latency_position", "latency pos [ms]", 1e3, "{:.1f}"),
    ("latency_rotation", "latency rot [ms]", 1e3, "{:.1f}"),
]


def format_table(metrics: dict[str, dict], causal: dict[str, bool] | None = None) -> str:
    """Markdown table of :class:`EvaluationResult.metrics` (NaN shown as ``-``)."""
    head = ["method", "causal"] + [c[1] for c in _COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in metrics.items():
        cells = [name, "" if causal is None else ("yes" if causal[name] else "no")]
        for key, _, scale, fmt in _COLUMNS:
            v = m.get(key, np.nan)
            cells.append("-" if v is None or not np.isfinite(v) else fmt.format(scale * v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_evaluation(result: EvaluationResult, path: str | Path, methods: list[str] | None = None) -> Path:
    """PNG with the trajectory, the error over time and the jerk of the rendered streams."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._np_quat import np_qconj as _np_qconj
    from .._np_quat import np_qmul as _np_qmul
    from .._np_quat import np_rotvec as _np_rotvec

    default = ["phjax (causal)", "kalman-cv extrapolation", "one-euro + hold", "phjax (offline)",
               "cubic spline (scipy)"]
    names = methods or [n for n in default if n in result.streams] or list(result.streams)
    t = result.render_times - result.render_times[0]
    mid = t[len(t) // 2]
    win = (t > mid - 2) & (t < mid + 2)  # 4 s window for the trajectory panel
    fig, axes = plt.subplots(2, 2, figsize=(13, 8))
    has_pos = np.isfinite(result.gt_positions).any()
    ax = axes[0, 0]
    if has_pos:
        ax.plot(t[win], result.gt_positions[win, 0], "k", lw=2, label="ground truth x")
        mt, mp, _ = result.measurements
        mt = mt - result.render_times[0]
        mw = (mt > mid - 2) & (mt < mid + 2)
        ax.plot(mt[mw], mp[mw, 0], ".", color="0.5", ms=4, label="measured x")
        for n in names:
            ax.plot(t[win], result.streams[n][0][win, 0], lw=1, label=n)
        ax.set_ylabel("x [m]")
    else:
        ang = np.linalg.norm(_np_rotvec(result.gt_quaternions), axis=-1)
        ax.plot(t[win], np.degrees(ang[win]), "k", lw=2, label="ground truth |rotation|")
        for n in names:
            ang_n = np.linalg.norm(_np_rotvec(result.streams[n][1][win]), axis=-1)
            ax.plot(t[win], np.degrees(ang_n), lw=1, label=n)
        ax.set_ylabel("rotation angle [deg]")
    ax.set_title("trajectory (4 s window)")
    ax.set_xlabel("time [s]")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    for n in names:
        if has_pos:
            err = np.linalg.norm(result.streams[n][0] - result.gt_positions, axis=-1) * 1e3
            ax.plot(t, err, lw=0.8, label=n)
            ax.set_ylabel("position error [mm]")
    ax.set_title("position error over time")
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    for n in names:
        dq = _np_qmul(_np_qconj(result.gt_quaternions), result.streams[n][1])
        err = np.degrees(np.linalg.norm(_np_rotvec(dq), axis=-1))
        ax.plot(t, err, lw=0.8, label=n)
    ax.set_ylabel("rotation error [deg]")
    ax.set_xlabel("time [s]")
    ax.set_title("rotation error over time")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    dt = np.median(np.diff(t))
    for n in names:
        x = result.streams[n][0] if has_pos else np.asarray(_np_rotvec(result.streams[n][1]))
        jerk2 = np.sum(np.diff(x, 3, axis=0) ** 2, axis=-1) / dt**6
        k = max(int(round(0.25 / dt)), 1)  # rolling RMS over 0.25 s
        ok = np.isfinite(jerk2)
        rms = np.sqrt(np.convolve(np.where(ok, jerk2, 0), np.ones(k), "same")
                      / np.maximum(np.convolve(ok, np.ones(k), "same"), 1))
        ax.semilogy(t[3:], np.maximum(rms, 1e-3), lw=0.8, label=n)
    ax.set_ylabel("RMS jerk, 0.25 s window [m/s^3]" if has_pos else "RMS d^3 rotvec/dt^3 [rad/s^3]")
    ax.set_xlabel("time [s]")
    ax.set_title("jerk of the rendered stream")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
