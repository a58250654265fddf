"""Evaluate phjax and the baselines against ground truth under a simulated sensor.

A ground-truth trajectory is sampled by a :class:`phjax.motion.simulate.SensorModel` (30 Hz, 5 mm,
1 degree, 5 % dropouts by default); every method renders the pose at ``render_rate`` from those
measurements; :func:`phjax.evaluation.metrics.evaluate` scores each stream against the ground truth
interpolated to the render times (samples inside ground-truth gaps longer than ``max_gt_gap``
are ignored; default :func:`phjax.motion.resample.ground_truth_max_gap`: the larger of 0.1 s and
2.5 median ground-truth steps).

The baselines' parameters in :data:`TUNED` were chosen for the lowest RMSE on the development
set (grid searches of ``experiments/tune_baselines.py`` and ``experiments/frontier.py``; see
:data:`phjax.tracking.baselines.TUNED`), so that no baseline is handicapped.
:func:`format_table` marks the best causal value per column and compares phjax with the
strongest baseline of each column; :func:`plot_evaluation` draws RMSE vs jerk, the lags and a
zoom on the fastest motion.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .._np_quat import np_any_part
from ..motion.resample import (
    ground_truth_max_gap,
    interpolate_poses,
    snap_to_frames,
    warn_sparse_ground_truth,
)
from ..motion.simulate import SensorModel, simulate_measurements
from ..tracking import baselines
from ..tracking.baselines import TUNED
from ..tracking.kalman import KalmanConfig
from ..tracking.tracker import TrackerConfig, reconstruct, track
from ._plot import legend_on_first_labelled
from .metrics import LAG_RANGE
from .metrics import evaluate as evaluate_metrics

__all__ = [
    "LEGEND",
    "TUNED",
    "EvaluationResult",
    "Method",
    "best_per_column",
    "default_methods",
    "evaluate_recording",
    "format_table",
    "plot_evaluation",
]


def _one_euro_tuned(t, p, q, r):
    """One Euro with separately tuned position and rotation settings (then hold)."""
    pos, _ = baselines.one_euro(t, p, q, r, **TUNED["one_euro_position"])
    _, rot = baselines.one_euro(t, p, q, r, **TUNED["one_euro_rotation"])
    return pos, rot


def _one_euro_extrapolation_tuned(t, p, q, r):
    """One Euro + linear extrapolation with separately tuned position and rotation settings."""
    pos, _ = baselines.one_euro_extrapolation(t, p, q, r,
                                              **TUNED["one_euro_extrapolation_position"])
    _, rot = baselines.one_euro_extrapolation(t, p, q, r,
                                              **TUNED["one_euro_extrapolation_rotation"])
    return pos, rot


@dataclasses.dataclass(frozen=True)
class Method:
    """A pose-stream method with the common interface ``fn(t, p, q, render_t) -> (p, q)``.

    ``causal``: uses only measurements up to each render time (offline methods are not ranked
    against causal ones); ``baseline``: a competitor of phjax (``False`` for phjax's own
    streams and for references such as the raw hold).
    """

    name: str
    fn: Callable
    causal: bool
    baseline: bool = True


def default_methods(tracker_config: TrackerConfig | None = None) -> list[Method]:
    """phjax causal and offline, every tuned causal baseline, and two references.

    Causal baselines (parameters from :data:`TUNED`): Kalman CV extrapolation, fixed-gain
    alpha-beta extrapolation on R^3 x SO(3), LaViola's double exponential smoothing predictor
    (DESP), One Euro + hold, One Euro + linear extrapolation, snapshot interpolation, IMM
    extrapolation (the IMM filter without the PH stream). References
    (not ranked as baselines): raw hold (causal) and scipy's cubic spline (offline).
    """
    cfg = tracker_config if tracker_config is not None else TrackerConfig()
    kcfg = KalmanConfig(**TUNED["kalman"])
    scfg = KalmanConfig(**TUNED["snapshot"])
    return [
        Method("phjax (causal)", lambda t, p, q, r: track(t, p, q, r, config=cfg), True, False),
        Method("kalman-cv extrapolation", lambda t, p, q, r: baselines.kalman_extrapolation(
            t, p, q, r, config=kcfg), True),
        Method("alpha-beta extrapolation", lambda t, p, q, r: baselines.alpha_beta(
            t, p, q, r, **TUNED["alpha_beta"]), True),
        Method("desp extrapolation", lambda t, p, q, r: baselines.double_exponential(
            t, p, q, r, **TUNED["desp"]), True),
        Method("one-euro + hold", _one_euro_tuned, True),
        Method("one-euro + extrapolation", _one_euro_extrapolation_tuned, True),
        Method("snapshot interpolation", lambda t, p, q, r: baselines.snapshot_interpolation(
            t, p, q, r, config=scfg), True),
        Method("imm extrapolation", baselines.imm_extrapolation, True),
        Method("raw hold", baselines.hold, True, False),
        Method("phjax (offline)", lambda t, p, q, r: reconstruct(t, p, q, r, config=cfg), False,
               False),
        Method("cubic spline (scipy)", baselines.cubic_spline, False, False),
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
        baseline: method name -> whether it is a competing baseline (see :class:`Method`).
    """

    metrics: dict[str, dict]
    render_times: np.ndarray
    gt_positions: np.ndarray
    gt_quaternions: np.ndarray
    measurements: tuple[np.ndarray, np.ndarray, np.ndarray]
    streams: dict[str, tuple[np.ndarray, np.ndarray]]
    causal: dict[str, bool]
    baseline: dict[str, bool] = dataclasses.field(default_factory=dict)


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
    max_gt_gap: float | None = None,
) -> EvaluationResult:
    """Simulate measurements from a ground-truth trajectory and score every method.

    Render times run at ``render_rate`` from one camera period after the first valid frame;
    those that fall on a frame's timestamp are set to it exactly
    (:func:`phjax.motion.resample.snap_to_frames`), so every method has seen that frame there.

    Arguments:
        gt_times, gt_positions, gt_quaternions: ground truth (s, m (NaN for orientation-only),
            wxyz).
        sensor: sensor model (default :class:`SensorModel()`).
        render_rate: render rate, Hz.
        seed: random seed of the sensor simulation.
        methods: methods to run (default :func:`default_methods`).
        progress: show a progress bar (tqdm) over methods.
        max_gt_gap: ground-truth gaps longer than this (s) are excluded from the metrics, and
            the simulated sensor loses its frames there (default:
            :func:`phjax.motion.resample.ground_truth_max_gap`, 0.1 s or 2.5 median
            ground-truth steps).

    Returns:
        An :class:`EvaluationResult`.

    Raises:
        ValueError: ``render_rate`` not a positive finite number, ``methods`` empty or with a
            repeated name, a method returning other shapes than ``(m, 3)`` and ``(m, 4)`` for
            ``m`` render times (naming it), or a recording too short to score. An exception
            raised inside a method carries a note naming the method.

    Warns:
        phjax.io.TrajectoryWarning: sparse ground truth (see
            :func:`phjax.motion.resample.warn_sparse_ground_truth`), and one warning naming
            every table cell that no sample scored although the ground truth has that part (a
            stream that is NaN everywhere; lags when the render times span no more than the
            0.4 s lag search).
    """
    methods = default_methods() if methods is None else list(methods)
    if not methods:
        raise ValueError("methods is empty: give at least one Method to evaluate")
    names = [m.name for m in methods]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:  # the table has one row per name: a second one would replace the first
        raise ValueError(f"method names must be unique; repeated: {', '.join(map(repr, repeated))}")
    gt_t, gt_p, gt_q, (mt, mp, mq), render, origin = simulate_and_grid(
        gt_times, gt_positions, gt_quaternions, sensor=sensor, render_rate=render_rate, seed=seed,
        max_gt_gap=max_gt_gap)
    valid = np_any_part(mp, mq)
    gp, gq = interpolate_poses(gt_t, gt_p, gt_q, render,
                               max_gap=ground_truth_max_gap(gt_t, max_gt_gap))
    gp, gq = np.asarray(gp, np.float64), np.asarray(gq, np.float64)
    warn_sparse_ground_truth(gt_t, render, gp, gq)
    iterator = methods
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(methods, desc="methods", leave=False)
    metrics, streams, causal, baseline = {}, {}, {}, {}
    for m in iterator:
        try:
            p, q = m.fn(mt, mp, mq, render)
        except Exception as e:
            e.add_note(f"(in method {m.name!r} of evaluate_recording)")
            raise
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        if p.shape != (render.size, 3) or q.shape != (render.size, 4):
            raise ValueError(
                f"method {m.name!r} returned positions of shape {p.shape} and quaternions of "
                f"shape {q.shape}; expected ({render.size}, 3) and ({render.size}, 4), one row per "
                "render time")
        streams[m.name] = (p, q)
        causal[m.name] = m.causal
        baseline[m.name] = m.baseline
        metrics[m.name] = evaluate_metrics(render, p, q, gp, gq, boundary_times=mt[valid])
    _warn_unscored(metrics, render, gp, gq)
    return EvaluationResult(metrics, render + origin, gp, gq, (mt + origin, mp, mq), streams, causal,
                            baseline)


def _warn_unscored(metrics: dict[str, dict], render: np.ndarray, gp: np.ndarray,
                   gq: np.ndarray) -> None:
    """One :class:`phjax.io.TrajectoryWarning` naming the table cells that no sample scored
    although the ground truth has that part (the table shows ``-`` there): a method whose
    stream is NaN everywhere, or lags on a render span shorter than the lag search range."""
    import warnings

    from ..io import TrajectoryWarning

    known = {"pos": bool(np.isfinite(gp).all(-1).any()),
             "rot": bool(np.isfinite(gq).all(-1).any())}
    missing = {}
    for name, m in metrics.items():
        cols = [head for key, head, _ in _COLUMNS
                if known[head[:3]] and m.get(key + "_n", 1) == 0]
        if cols:
            missing[name] = cols
    if not missing:
        return
    lo, hi = LAG_RANGE
    span = float(render[-1] - render[0]) if render.size else 0.0
    why = ""
    if span <= hi - lo and any("lag" in c for cols in missing.values() for c in cols):
        why = (f"; the lag search ({1e3 * lo:g} to {1e3 * hi:g} ms) needs more than "
               f"{hi - lo:g} s of render samples, these span {span:.3g} s")
    what = "; ".join(f"{n} ({', '.join(c)})" for n, c in missing.items())
    warnings.warn(f"no sample scored (shown as '-') for {what}{why}", TrajectoryWarning,
                  stacklevel=3)


#: the fewest render samples an evaluation scores (a third difference for jerk, a few shifts
#: for lag)
MIN_RENDER_SAMPLES = 8


def simulate_and_grid(gt_times, gt_positions, gt_quaternions, *,
                      sensor: SensorModel | None = None, render_rate: float = 120.0,
                      seed: int = 0, max_gt_gap: float | None = None):
    """The measurements and render grid of :func:`evaluate_recording`.

    Times are shifted to start at the first ground-truth sample; render times run at
    ``render_rate`` from one camera period after the first valid frame to the last ground-truth
    time, snapped onto coincident frame times.

    Returns:
        ``(gt_times, gt_positions, gt_quaternions, (times, positions, quaternions), render,
        origin)``: float64 arrays, times relative to ``origin`` (the first ground-truth time).
    """
    sensor = SensorModel() if sensor is None else sensor
    rate = float(render_rate)
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"render_rate must be a positive, finite rate in Hz, got {render_rate}")
    gt_times = np.asarray(gt_times, np.float64)
    origin = gt_times[0]
    gt_t = gt_times - origin
    gt_p = np.asarray(gt_positions, np.float64)
    gt_q = np.asarray(gt_quaternions, np.float64)
    frames = simulate_measurements(seed, gt_t, gt_p, gt_q, sensor, max_gt_gap=max_gt_gap)
    mt, mp, mq = (np.asarray(x, np.float64) for x in frames)
    valid = np_any_part(mp, mq)
    if not np.any(valid):
        raise ValueError("the simulated sensor produced no valid measurement")
    start = mt[valid][0] + 1.0 / sensor.rate  # let every method see at least one frame
    # a sample at a frame's own instant sees that frame, whatever the rounding of the clocks
    render = snap_to_frames(mt, np.arange(start, gt_t[-1], 1.0 / render_rate))
    if render.size < MIN_RENDER_SAMPLES:
        raise ValueError(
            f"the recording is too short to evaluate: {gt_t[-1]:.3g} s, of which "
            f"{max(gt_t[-1] - start, 0):.3g} s after the first simulated frame and one camera "
            f"period ({render.size} render samples at {render_rate:g} Hz; jerk and lag need "
            f"{MIN_RENDER_SAMPLES})")
    return gt_t, gt_p, gt_q, (mt, mp, mq), np.asarray(render, np.float64), origin


#: (metric key, header, scale to the shown unit); lower is better, lag: closer to zero
_COLUMNS = [
    ("position_rmse", "pos RMSE [mm]", 1e3),
    ("rotation_rmse_deg", "rot RMSE [deg]", 1.0),
    ("jerk_position", "pos jerk [m/s^3]", 1.0),
    ("jerk_rotation", "rot jerk [rad/s^3]", 1.0),
    ("lag_position", "pos lag [ms]", 1e3),
    ("lag_rotation", "rot lag [ms]", 1e3),
]
_LAGS = ("lag_position", "lag_rotation")

#: the line printed under the table
LEGEND = ("Lower is better (lag: closer to 0); **bold** = best causal method per column; offline "
          "methods use future frames and are not ranked. RMSE against ground truth; jerk = RMS "
          "third derivative of the rendered stream; lag = time shift minimising the RMSE against "
          "the shifted ground truth (positive = behind).")


def _num(v: float) -> str:
    if v is None or not np.isfinite(v):
        return "-"
    a = abs(v)
    return f"{v:.0f}" if a >= 100 else f"{v:.1f}" if a >= 10 else f"{v:.2f}"


def _value(m: dict, key: str, scale: float) -> float:
    v = m.get(key, np.nan)
    return np.nan if v is None else scale * float(v)


def _badness(key: str, v: float) -> float:
    return abs(v) if key in _LAGS else v


def best_per_column(metrics: dict[str, dict], names: list[str]) -> dict[str, set[str]]:
    """Metric key -> the methods among ``names`` with the best value of that column (lowest;
    lag: closest to zero; ties all count; NaN never wins)."""
    out = {}
    for key, _, scale in _COLUMNS:
        vals = {n: _badness(key, _value(metrics[n], key, scale)) for n in names}
        vals = {n: v for n, v in vals.items() if np.isfinite(v)}
        if not vals:
            out[key] = set()
            continue
        lo = min(vals.values())
        out[key] = {n for n, v in vals.items() if np.isclose(v, lo, rtol=1e-9, atol=1e-12)}
    return out


def format_table(
    metrics: dict[str, dict],
    causal: dict[str, bool] | None = None,
    baseline: dict[str, bool] | None = None,
    *,
    reference: str = "phjax (causal)",
    legend: bool = True,
) -> str:
    """Markdown table of per-method metrics, the best causal value per column in bold.

    Arguments:
        metrics: method name -> dict of :func:`phjax.evaluation.metrics.evaluate` values.
        causal: method name -> causal (default: every method causal); offline methods are shown
            but never marked best.
        baseline: method name -> competing baseline (default: causal methods whose name does
            not start with ``phjax`` and is not ``raw hold``).
        reference: the method compared with the strongest baseline of each column.
        legend: append the line saying what the numbers mean and, when ``reference`` and a
            baseline are present, the ratio table.

    Returns:
        The table (NaN shown as ``-``).
    """
    causal = {n: True for n in metrics} if causal is None else causal
    if baseline is None:
        baseline = {n: causal.get(n, True) and not n.startswith("phjax") and n != "raw hold"
                    for n in metrics}
    ranked = [n for n in metrics if causal.get(n, True)]
    best = best_per_column(metrics, ranked)
    head = ["method", "causal"] + [c[1] for c in _COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in metrics.items():
        cells = [name, "yes" if causal.get(name, True) else "no (offline)"]
        for key, _, scale in _COLUMNS:
            s = _num(_value(m, key, scale))
            cells.append(f"**{s}**" if name in best[key] else s)
        lines.append("| " + " | ".join(cells) + " |")
    if not legend:
        return "\n".join(lines)
    lines += ["", LEGEND]
    bases = [n for n in metrics if baseline.get(n, False) and causal.get(n, True)]
    if reference in metrics and bases:
        strongest = best_per_column(metrics, bases)
        row_b, row_v, row_r = ["strongest baseline"], ["its value"], [f"{reference} / it"]
        for key, _, scale in _COLUMNS:
            b = sorted(strongest[key])
            if not b:
                row_b.append("-"), row_v.append("-"), row_r.append("-")
                continue
            vb = _value(metrics[b[0]], key, scale)
            vr = _value(metrics[reference], key, scale)
            row_b.append(", ".join(b))
            row_v.append(_num(vb))
            if key in _LAGS:
                row_r.append("-" if not np.isfinite(vr - vb) else f"{vr - vb:+.1f} ms")
            else:
                row_r.append("-" if not (np.isfinite(vr) and vb > 0) else f"{vr / vb:.3f}")
        lines += ["", f"{reference} against the strongest causal baseline of each column "
                  "(ratio < 1: phjax better; lag: difference in ms):",
                  "", "| " + " | ".join([""] + [c[1] for c in _COLUMNS]) + " |",
                  "|" + "---|" * (len(_COLUMNS) + 1)]
        lines += ["| " + " | ".join(r) + " |" for r in (row_b, row_v, row_r)]
    return "\n".join(lines)


def _zoom_window(t: np.ndarray, x: np.ndarray, width: float) -> np.ndarray:
    """Boolean mask of the ``width``-second window centred on the fastest motion of ``x``."""
    ok = np.all(np.isfinite(x), axis=-1)
    speed = np.full(t.shape, 0.0)
    d = np.linalg.norm(np.diff(x, axis=0), axis=-1) / np.diff(t)
    speed[1:] = np.where(np.isfinite(d), d, 0.0)
    h = float(np.median(np.diff(t)))
    k = max(round(0.25 / h), 1)
    smooth = np.convolve(speed * ok, np.ones(k) / k, "same")
    lo = t[0] + width / 2
    hi = max(t[-1] - width / 2, lo)
    centre = float(np.clip(t[int(np.argmax(smooth))], lo, hi))
    return (t >= centre - width / 2) & (t <= centre + width / 2)


def plot_evaluation(
    result: EvaluationResult, path: str | Path, methods: list[str] | None = None,
    zoom: float = 1.0,
) -> Path:
    """PNG of the comparison: the frontier, the lag and a zoom where the methods differ.

    Four panels: position RMSE vs position jerk and rotation RMSE vs angular jerk (one marker
    per method, log jerk axis; lower left is better); the lag of every method (position and
    rotation); a ``zoom``-second window around the fastest ground-truth motion of one coordinate
    (the one moving most there) with the ground truth, the measurements, phjax (causal) and the
    two causal baselines with the lowest RMSE. phjax is drawn last in red.

    Arguments:
        result: from :func:`evaluate_recording`.
        path: output PNG.
        methods: methods shown in the RMSE / jerk and lag panels (default: all).
        zoom: width of the zoom window, s.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._np_quat import np_rotvec as _np_rotvec

    names = [n for n in (methods or list(result.metrics)) if n in result.metrics]
    ref = "phjax (causal)"
    causal = {n: result.causal.get(n, True) for n in names}
    is_base = {n: result.baseline.get(n, causal[n] and not n.startswith("phjax")) for n in names}
    others = [n for n in names if n != ref]
    palette = ["C0", "C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9", "olive", "teal", "navy"]
    rest = [n for n in others if n != "phjax (offline)"]
    colours = {n: palette[i % len(palette)] for i, n in enumerate(rest)}
    colours |= {ref: "C3", "phjax (offline)": "darkred"}
    order = others + ([ref] if ref in names else [])  # phjax drawn last

    def label(n):
        return n if causal[n] or "offline" in n else f"{n} [offline]"

    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    for ax, (rk, jk, scale, unit, junit) in zip(
            axes[0], (("position_rmse", "jerk_position", 1e3, "mm", "m/s^3"),
                      ("rotation_rmse_deg", "jerk_rotation", 1.0, "deg", "rad/s^3"))):
        pts = {n: (result.metrics[n].get(jk, np.nan), scale * result.metrics[n].get(rk, np.nan))
               for n in order}
        pts = {n: v for n, v in pts.items() if np.isfinite(v[0]) and np.isfinite(v[1]) and v[0] > 0}
        drawn = bool(pts)
        # the RMSE axis spans the causal methods; an offline method below it sits on the edge
        ys = [v[1] for n, v in pts.items() if causal[n]] or [v[1] for v in pts.values()] or [0.0]
        pad = 0.08 * (max(ys) - min(ys)) + 1e-9
        floor = min(ys) - pad
        for n, (x, y) in pts.items():
            mine = n == ref
            below = y < floor
            ax.scatter([x], [max(y, floor + 0.15 * pad)], s=180 if mine else 60,
                       marker="*" if mine else ("v" if below else "o"),
                       facecolors=colours[n] if causal[n] else "none", edgecolors=colours[n],
                       zorder=5 if mine else 3, label=label(n), clip_on=False)
            if mine or below:
                text = f"{n}" + (f": {y:.3g} {unit} (below the axis)" if below else "")
                ax.annotate(text, (x, max(y, floor + 0.15 * pad)), textcoords="offset points",
                            xytext=(6, 5), fontsize=7, color=colours[n],
                            fontweight="bold" if mine else "normal")
        ax.set_ylim(floor, max(ys) + pad)
        ax.set_xscale("log")
        ax.set_xlabel(f"RMS jerk [{junit}] (log)")
        ax.set_ylabel(f"RMSE [{unit}]")
        kind = "position" if rk.startswith("position") else "rotation"
        ax.set_title(f"{kind}: accuracy vs smoothness (lower left is better)")
        if not drawn:
            ax.text(0.5, 0.5, f"no {kind} data", ha="center", va="center", transform=ax.transAxes)
        ax.grid(True, which="both", alpha=0.3)
    legend_on_first_labelled(axes[0], fontsize=7, loc="best")

    ax = axes[1, 0]
    y = np.arange(len(order))
    for off, key, hatch, what in ((-0.2, "lag_position", None, "position"),
                                  (0.2, "lag_rotation", "//", "rotation")):
        vals = [1e3 * result.metrics[n].get(key, np.nan) for n in order]
        ax.barh(y + off, np.nan_to_num(vals), height=0.4, color=[colours[n] for n in order],
                hatch=hatch, edgecolor="k", linewidth=0.5, label=what)
    ax.set_yticks(y, [label(n) for n in order], fontsize=8)
    for tick, n in zip(ax.get_yticklabels(), order):
        if n == ref:
            tick.set_fontweight("bold")
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel("lag [ms] (shift minimising RMSE vs shifted ground truth; + = behind)")
    ax.set_title("lag per method (plain: position, hatched: rotation)")
    ax.legend(fontsize=7)
    ax.grid(True, axis="x", alpha=0.3)

    ax = axes[1, 1]
    t = result.render_times - result.render_times[0]
    mt, mp, mq = result.measurements
    mt = mt - result.render_times[0]
    has_pos = bool(np.isfinite(result.gt_positions).any())
    if has_pos:
        gt_x, rk, unit, scale = result.gt_positions, "position_rmse", "mm", 1e3

        def coord(p, q):
            return p
        meas = mp
    else:
        rk, unit, scale = "rotation_rmse_deg", "deg", np.degrees(1.0)

        def coord(p, q):
            return np.asarray(_np_rotvec(np.where(np.isfinite(q), q, np.nan)))
        gt_x = coord(None, result.gt_quaternions)
        meas = coord(None, mq)
    win = _zoom_window(t, gt_x, zoom)
    axis = int(np.nanargmax(np.nanmax(gt_x[win], 0) - np.nanmin(gt_x[win], 0)))
    comps = "xyz"[axis]
    lo, hi = t[win][0], t[win][-1]
    mw = (mt >= lo) & (mt <= hi)
    ax.plot(t[win], scale * gt_x[win, axis], color="k", lw=2.5, label="ground truth", zorder=2)
    ax.plot(mt[mw], scale * meas[mw, axis], "o", color="0.55", ms=4, label="measurements",
            zorder=2)
    bases = [n for n in names if causal[n] and is_base[n] and n in result.streams]
    bases = sorted(bases, key=lambda n: result.metrics[n].get(rk, np.inf))[:2]
    for n in bases:
        ax.plot(t[win], scale * coord(*result.streams[n])[win, axis], color=colours[n], lw=1.2,
                ls="--", label=n, zorder=3)
    if ref in result.streams:
        ax.plot(t[win], scale * coord(*result.streams[ref])[win, axis], color="C3", lw=2.2,
                label=ref, zorder=4)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{comps} [{unit}]" if has_pos else f"rotation vector {comps} [{unit}]")
    ax.set_title(f"zoom: {zoom:g} s around the fastest motion ({comps})")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)

    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
