"""What a user chooses between: phjax and each baseline at the display time, tuned and at equal
smoothness.

A renderer shows a pose some milliseconds after it was computed (motion-to-photon latency); a
predictor can aim at that *display time* (the ``lookahead`` of :class:`phjax.TrackerConfig` and of
the extrapolating baselines in :mod:`phjax.tracking.baselines`). At each lookahead ``L``,
:func:`compare_at_display` scores, against the ground truth at ``tau + L``:

* the phjax causal stream (the given :class:`~phjax.TrackerConfig` with ``lookahead = L``);
* each knob baseline (:data:`KNOB_BASELINES`: Kalman CV extrapolation, alpha-beta extrapolation,
  One Euro + extrapolation, and the IMM extrapolation, phjax's own filter without the stream)
  at its tuned knob (:data:`phjax.tracking.baselines.TUNED`; for the IMM its default model set),
  predicting to the same display time;
* the same baselines **as smooth as phjax** (the frontier at phjax's smoothness): per
  channel, the knob with the lowest RMSE among those whose RMS jerk on this recording is at
  most phjax's (within 1 %; a log-spaced sweep of the knob, the crossings of phjax's jerk
  refined by regula falsi), then its RMSE and lag there. The tuned baselines are 3-4 times as
  jerky as the stream, so comparing their RMSE with the stream's compares different points of
  the accuracy / smoothness trade-off. An extrapolator's jerk is not monotonic in its knob (a
  smoother filter predicts worse, so its jumps at the camera frames grow again), and some
  never get as smooth as phjax: then the row shows the smoothest knob seen, marked.

:func:`format_choices` prints the tables, :func:`plot_choices` draws the frontier (RMSE against
jerk for each baseline's knob sweep, its tuned and as-smooth knobs, phjax's operating point).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import equinox as eqx
import numpy as np

from ..motion.resample import ground_truth_max_gap, interpolate_poses
from ..motion.simulate import SensorModel
from ..tracking import baselines
from ..tracking.baselines import TUNED
from ..tracking.imm import IMMConfig
from ..tracking.kalman import KalmanConfig
from ..tracking.tracker import TrackerConfig, track
from ._plot import legend_on_first_labelled
from .metrics import (
    position_rmse,
    rms_jerk_position,
    rms_jerk_rotation,
    rotation_rmse_deg,
    shift_lag,
)

__all__ = [
    "KNOB_BASELINES",
    "Choice",
    "DisplayComparison",
    "KnobBaseline",
    "compare_at_display",
    "format_choices",
    "plot_choices",
]

_CHANNELS = ("position", "rotation")


def _split_channels(fn_p, fn_r):
    """A method whose position comes from ``fn_p`` and orientation from ``fn_r`` (every
    baseline filters the two channels independently)."""
    def fn(t, p, q, r):
        if fn_p is fn_r:
            return fn_p(t, p, q, r)
        return fn_p(t, p, q, r)[0], fn_r(t, p, q, r)[1]
    return fn


@dataclasses.dataclass(frozen=True)
class KnobBaseline:
    """A causal baseline with one smoothing knob per channel.

    Attributes:
        name: method name (as in :func:`phjax.evaluation.default_methods`).
        knob: what the knob is, written before its value in the table (``"noise x"``).
        tuned: ``(position, rotation)`` knob values at the tuned setting.
        bounds: the knob range of the equal-smoothness search (searched on a log scale; the
            range of the knob grids of ``experiments/frontier.py``, from heavy smoothing to
            light).
        make: ``(position knob, rotation knob, lookahead) -> fn(t, p, q, r)``.
    """

    name: str
    knob: str
    tuned: tuple[float, float]
    bounds: tuple[float, float]
    make: Callable[[float, float, float], Callable]


def _kalman(kp, kr, L):
    """The Kalman CV extrapolation with the tuned process noise times ``kp`` / ``kr``."""
    k = TUNED["kalman"]
    cfg = KalmanConfig(**(k | {"pos_process_noise": kp * k["pos_process_noise"],
                               "rot_process_noise": kr * k["rot_process_noise"]}))
    return lambda t, p, q, r: baselines.kalman_extrapolation(t, p, q, r, config=cfg, lookahead=L)


def _gain(method):
    """``make`` of a baseline whose knob is its own gain ``alpha`` (alpha-beta's alpha,
    LaViola's DESP ``a``)."""
    def make(kp, kr, L):
        def one(a):
            return lambda t, p, q, r: method(t, p, q, r, alpha=a, lookahead=L)
        return one(kp) if kp == kr else _split_channels(one(kp), one(kr))
    return make


def _one_euro_x(kp, kr, L):
    """One Euro + extrapolation with both cutoff parameters (``min_cutoff``, ``beta``) of the
    tuned setting times ``kp`` (position) / ``kr`` (rotation): the cutoff ``min_cutoff + beta
    |speed|`` scales by the knob at every speed."""
    def one(s, tuned):
        return lambda t, p, q, r: baselines.one_euro_extrapolation(
            t, p, q, r, min_cutoff=s * tuned["min_cutoff"], beta=s * tuned["beta"], lookahead=L)
    return _split_channels(one(kp, TUNED["one_euro_extrapolation_position"]),
                           one(kr, TUNED["one_euro_extrapolation_rotation"]))


def _scaled_imm(sp: float, sr: float) -> IMMConfig:
    """The default IMM with every position model's density times ``sp`` and every rotation
    model's times ``sr``."""
    d = IMMConfig()

    def scale(models, s):
        return tuple(eqx.tree_at(lambda m: m.log_q, m, m.log_q + math.log(s)) for m in models)

    return eqx.tree_at(lambda c: (c.position_models, c.rotation_models), d,
                       (scale(d.position_models, sp), scale(d.rotation_models, sr)))


def _imm(sp, sr, L):
    cfg = _scaled_imm(sp, sr)
    return lambda t, p, q, r: baselines.imm_extrapolation(t, p, q, r, config=cfg, lookahead=L)


#: The baselines of the comparison, each with its knob: the Kalman CV's process noise, the One
#: Euro's two cutoff parameters and the IMM's model densities as multiples of their tuned
#: values (:data:`phjax.tracking.baselines.TUNED`; the IMM: its default model set), alpha-beta's
#: alpha and LaViola's DESP ``a`` themselves.
KNOB_BASELINES: tuple[KnobBaseline, ...] = (
    KnobBaseline("kalman-cv extrapolation", "noise x", (1.0, 1.0), (1e-3, 30.0), _kalman),
    KnobBaseline("alpha-beta extrapolation", "alpha", (TUNED["alpha_beta"]["alpha"],) * 2,
                 (0.02, 1.0), _gain(baselines.alpha_beta)),
    KnobBaseline("desp extrapolation", "a", (TUNED["desp"]["alpha"],) * 2, (0.01, 0.9),
                 _gain(baselines.double_exponential)),
    KnobBaseline("one-euro + extrapolation", "cutoffs x", (1.0, 1.0), (1e-3, 30.0),
                 _one_euro_x),
    KnobBaseline("imm extrapolation", "densities x", (1.0, 1.0), (1e-3, 30.0), _imm),
)


@dataclasses.dataclass
class Choice:
    """One row of the comparison: a method at one setting.

    Attributes:
        method: method name.
        setting: ``"phjax"``, ``"tuned"`` or ``"equal smoothness"``.
        knobs: ``(position, rotation)`` knob values (phjax: its horizons, the rotation's
            ``rotation_horizon`` or the same ``horizon``).
        metrics: ``position_rmse`` (m), ``rotation_rmse_deg``, ``jerk_position``,
            ``jerk_rotation``, ``lag_position``, ``lag_rotation`` (s, behind the display time).
        reached: per channel, whether some knob got as smooth as phjax (equal smoothness;
            otherwise the knob is the smoothest one seen).
    """

    method: str
    setting: str
    knobs: tuple[float, float]
    metrics: dict[str, float]
    reached: tuple[bool, bool] = (True, True)


@dataclasses.dataclass
class DisplayComparison:
    """Result of :func:`compare_at_display`.

    Attributes:
        lookaheads: the display-time lookaheads, s.
        choices: lookahead -> rows (phjax first, then per baseline tuned and equal smoothness).
        sweeps: lookahead -> method -> list of ``(position knob, rotation knob, metrics)`` of
            every knob the search evaluated (RMSE and jerk only), in evaluation order.
        horizon: phjax's horizon, s (position; the rotation's is ``choices[L][0].knobs[1]``).
    """

    lookaheads: tuple[float, ...]
    choices: dict[float, list[Choice]]
    sweeps: dict[float, dict[str, list]]
    horizon: float


def _score(render, p, q, gp, gq, *, lag: bool = True) -> dict[str, float]:
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    out = {"position_rmse": position_rmse(p, gp).value,
           "rotation_rmse_deg": rotation_rmse_deg(q, gq).value,
           "jerk_position": rms_jerk_position(render, p).value,
           "jerk_rotation": rms_jerk_rotation(render, q).value}
    if lag:
        out["lag_position"] = shift_lag(render, p, gp, kind="position").value
        out["lag_rotation"] = shift_lag(render, q, gq, kind="rotation").value
    return out


_JERK = {"position": "jerk_position", "rotation": "jerk_rotation"}
_RMSE = {"position": "position_rmse", "rotation": "rotation_rmse_deg"}


def _as_smooth(b: KnobBaseline, L: float, evaluate, targets: dict[str, float], sweep: list,
               points: int = 9, refine: int = 4, tol: float = 0.01):
    """Per channel, the knob with the lowest RMSE among those whose RMS jerk is at most
    ``targets[channel]`` (the frontier at that smoothness; within ``tol``, relative in log),
    and whether any knob got there.

    The jerk of an extrapolator is not monotonic in its knob: smoothing the filter lowers the
    noise in its jumps at the camera frames but makes its prediction errors, hence the jumps,
    larger, until the filter hardly moves at all. So the search sweeps ``points`` log-spaced
    knobs over ``b.bounds``, locates every crossing of the target between neighbours and
    refines each by regula falsi (Illinois) on log jerk against log knob (up to ``refine``
    steps, until within ``tol``, relative in log); the candidates are the refined crossings and
    the grid knobs below the target. Where no knob gets there, the knob of the smallest jerk
    seen is returned, with ``False``. ``evaluate(fn) -> metrics`` (no lag); every evaluation is
    appended to ``sweep``.

    Returns:
        ``((position knob, rotation knob), (position reached, rotation reached))``.
    """
    def run(kp, kr):
        m = evaluate(b.make(float(kp), float(kr), L))
        sweep.append((float(kp), float(kr), m))
        return m

    def f(m, ch):  # log jerk above the target (NaN when unusable)
        j = m.get(_JERK[ch], math.nan)
        return math.log(j / targets[ch]) if j > 0 and targets[ch] > 0 else math.nan

    xs = np.linspace(*(math.log(v) for v in b.bounds), points)
    grid = [run(math.exp(x), math.exp(x)) for x in xs]
    out, reached = {}, {}
    for i, ch in enumerate(_CHANNELS):
        fs = [f(m, ch) for m in grid]
        cands = [(x, m) for x, m, v in zip(xs, grid, fs) if v <= tol]  # NaN compares False
        for j in range(points - 1):
            (xa, fa), (xc, fc) = (xs[j], fs[j]), (xs[j + 1], fs[j + 1])
            if not (np.isfinite(fa) and np.isfinite(fc) and (fa <= 0) != (fc <= 0)):
                continue
            last = None
            for _ in range(refine):
                x = xa - fa * (xc - xa) / (fc - fa)
                m = run(math.exp(x), math.exp(x))  # the other channel: one more point
                v = f(m, ch)
                if not np.isfinite(v):
                    break
                if v <= tol:
                    cands.append((x, m))
                if abs(v) < tol:
                    break
                # Illinois: the end kept twice in a row has its value halved (no stagnation)
                side = (v <= 0) == (fa <= 0)  # replaces the a end
                if side:
                    xa, fa, fc = x, v, fc / 2 if last is True else fc
                else:
                    xc, fc, fa = x, v, fa / 2 if last is False else fa
                last = side
        good = [(x, m) for x, m in cands if np.isfinite(m.get(_RMSE[ch], math.nan))]
        reached[ch] = bool(good)
        if good:
            out[ch] = min(good, key=lambda xm: xm[1][_RMSE[ch]])[0]
        else:  # not reached: the smoothest knob seen
            seen = [(math.log(kp if i == 0 else kr), m) for kp, kr, m in sweep]
            seen = [(x, v) for x, m in seen if np.isfinite(v := f(m, ch))]
            out[ch] = min(seen, key=lambda xv: xv[1])[0] if seen else xs[0]
    return ((math.exp(out["position"]), math.exp(out["rotation"])),
            (reached["position"], reached["rotation"]))


def compare_at_display(
    gt_times,
    gt_positions,
    gt_quaternions,
    *,
    lookaheads: Sequence[float] = (0.0, 0.03),
    tracker_config: TrackerConfig | None = None,
    sensor: SensorModel | None = None,
    render_rate: float = 120.0,
    seed: int = 0,
    baselines_: Sequence[KnobBaseline] = KNOB_BASELINES,
    max_gt_gap: float | None = None,
    at_render_time: dict[str, dict] | None = None,
    progress: bool = False,
) -> DisplayComparison:
    """phjax against each knob baseline at the display time: tuned and at equal smoothness.

    The sensor simulation and render grid are those of
    :func:`phjax.evaluation.evaluate_recording` (same seed, same measurements). At each
    lookahead ``L`` every method shows at render time ``tau`` its pose predicted for ``tau + L``
    and is scored against the ground truth at ``tau + L`` (render samples whose ``tau + L`` is
    past the ground truth's end are not scored).

    Arguments:
        gt_times, gt_positions, gt_quaternions: ground truth (s, m (NaN for orientation-only),
            wxyz).
        lookaheads: display-time lookaheads, s.
        tracker_config: phjax's configuration (default :class:`TrackerConfig()`); its
            ``lookahead`` is replaced by each of ``lookaheads``.
        sensor, render_rate, seed, max_gt_gap: as in :func:`~phjax.evaluation.evaluate_recording`.
        baselines_: the knob baselines (default :data:`KNOB_BASELINES`).
        at_render_time: metrics already computed by
            :func:`~phjax.evaluation.evaluate_recording` on the same recording, sensor, seed
            and render rate (its ``metrics``), with ``tracker_config`` for ``"phjax (causal)"``
            and the baselines at their tuned settings (:func:`default_methods`): used at
            lookahead 0 instead of scoring those streams again (the lag is the slow part).
        progress: show a progress bar over lookaheads and baselines.

    Returns:
        A :class:`DisplayComparison`.
    """
    from .report import simulate_and_grid

    cfg0 = TrackerConfig() if tracker_config is None else tracker_config
    gt_t, gt_p, gt_q, (mt, mp, mq), render, _ = simulate_and_grid(
        gt_times, gt_positions, gt_quaternions, sensor=sensor, render_rate=render_rate, seed=seed,
        max_gt_gap=max_gt_gap)
    steps = [(L, b) for L in lookaheads for b in (None, *baselines_)]
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc="display-time comparison", leave=False)
    choices: dict[float, list[Choice]] = {}
    sweeps: dict[float, dict[str, list]] = {}
    for L, b in steps:
        gp, gq = (np.array(x, np.float64) for x in  # a copy: written below
                  interpolate_poses(gt_t, gt_p, gt_q, render + L,
                                    max_gap=ground_truth_max_gap(gt_t, max_gt_gap)))
        past = render + L > gt_t[-1]
        gp[past], gq[past] = np.nan, np.nan

        def evaluate(fn, lag=False, gp=gp, gq=gq):
            return _score(render, *fn(mt, mp, mq, render), gp, gq, lag=lag)

        known = (at_render_time or {}) if L == 0 else {}
        if b is None:  # phjax first: its jerk is every baseline's target
            cfg = eqx.tree_at(lambda c: c.lookahead, cfg0, L)
            m = known.get("phjax (causal)") or evaluate(
                lambda t, p, q, r, cfg=cfg: track(t, p, q, r, config=cfg), lag=True)
            rot_h = cfg0.horizon if cfg0.rotation_horizon is None else cfg0.rotation_horizon
            choices[L] = [Choice("phjax (causal)", "phjax", (cfg0.horizon, rot_h), m)]
            sweeps[L] = {}
            continue
        target = {ch: choices[L][0].metrics[_JERK[ch]] for ch in _CHANNELS}
        tuned = known.get(b.name) or evaluate(b.make(*b.tuned, L), lag=True)
        sweeps[L][b.name] = []
        knobs, reached = _as_smooth(b, L, evaluate, target, sweeps[L][b.name])
        equal = tuned if knobs == b.tuned else evaluate(b.make(*knobs, L), lag=True)
        choices[L] += [Choice(b.name, "tuned", b.tuned, tuned),
                       Choice(b.name, "equal smoothness", knobs, equal, reached)]
    return DisplayComparison(tuple(lookaheads), choices, sweeps, float(cfg0.horizon))


# ------------------------------------------------------------------------------------- output
def _horizons(knobs) -> str:
    """phjax's horizon, or its position / rotation horizons when they differ, in ms."""
    h = [f"{1e3 * float(k):g}" for k in knobs]
    return f"{h[0]} ms" if h[0] == h[1] else f"{h[0]} / {h[1]} ms"


def _num(v: float) -> str:
    if v is None or not np.isfinite(v):
        return "-"
    a = abs(v)
    return f"{v:.0f}" if a >= 100 else f"{v:.1f}" if a >= 10 else f"{v:.2f}"


def _knob(v: float) -> str:
    return f"{v:.3g}"


#: (metric key, header, scale to the shown unit)
_COLS = (("position_rmse", "pos RMSE [mm]", 1e3), ("jerk_position", "pos jerk [m/s^3]", 1.0),
         ("lag_position", "pos lag [ms]", 1e3), ("rotation_rmse_deg", "rot RMSE [deg]", 1.0),
         ("jerk_rotation", "rot jerk [rad/s^3]", 1.0), ("lag_rotation", "rot lag [ms]", 1e3))

#: the lines printed under the tables
CHOICES_LEGEND = (
    "Every method shows at render time tau the pose it predicts for tau + lookahead and is "
    "scored against the ground truth there. Knobs: Kalman CV process noise, One Euro cutoffs "
    "(min_cutoff and beta) and IMM model densities as multiples of the tuned ones, alpha-beta's "
    "alpha, DESP's a (LaViola's double exponential smoothing). 'tuned': the knob tuned for the "
    "lowest RMSE on the development set (lookahead 0); "
    "'as smooth as phjax': per channel, the knob with the lowest RMSE among those whose RMS "
    "jerk on this recording is at most phjax's (within 1 %; the accuracy / smoothness frontier "
    "at phjax's smoothness); 'never': no knob gets that smooth (shown: the smoothest one). "
    "Lag = shift minimising the RMSE against the shifted ground truth, ms behind the display "
    "time. Lower is better.")


def format_choices(comp: DisplayComparison,
                   baselines_: Sequence[KnobBaseline] = KNOB_BASELINES) -> str:
    """Markdown tables of :func:`compare_at_display`: per lookahead, phjax, then each baseline
    tuned and as smooth as phjax, and a line comparing phjax with the most accurate baseline at
    its smoothness (per channel)."""
    lines = []
    label = {b.name: b.knob for b in baselines_}
    head = ["method", "setting (pos / rot)"] + [c[1] for c in _COLS]
    for L in comp.lookaheads:
        rows = comp.choices[L]
        ph = rows[0].metrics
        lines += [f"### Lookahead {1e3 * L:g} ms" + (" (the pose for the render time)" if L == 0
                                                     else " (the pose for the display time)"),
                  "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for c in rows:
            if c.setting == "phjax":
                name, setting = f"**{c.method}**", f"horizon {_horizons(c.knobs)}"
            elif c.setting == "tuned":
                name = c.method
                setting = f"tuned: {label[c.method]} {_knob(c.knobs[0])} / {_knob(c.knobs[1])}"
            else:
                name = ""
                setting = "as smooth as phjax: " + " / ".join(
                    f"{label[c.method]} {_knob(k)}" if ok
                    else f"never (smoothest: {label[c.method]} {_knob(k)})"
                    for k, ok in zip(c.knobs, c.reached))
            cells = [_num(scale * c.metrics.get(key, np.nan)) for key, _, scale in _COLS]
            if c.setting == "phjax":
                cells = [f"**{s}**" for s in cells]
            lines.append("| " + " | ".join([name, setting] + cells) + " |")
        lines.append("")
        equal = [c for c in rows if c.setting == "equal smoothness"]
        verdict = []
        for ch, key, unit, scale in (("position", "position_rmse", "mm", 1e3),
                                     ("rotation", "rotation_rmse_deg", "deg", 1.0)):
            i = _CHANNELS.index(ch)
            if not np.isfinite(ph.get(key, np.nan)):
                continue
            ok = [c for c in equal if c.reached[i] and np.isfinite(c.metrics.get(key, np.nan))]
            never = [c for c in equal if not c.reached[i]
                     and np.isfinite(c.metrics.get(_JERK[ch], np.nan))]
            text = f"{ch}: phjax {scale * ph[key]:.3g} {unit}"
            if ok:
                best = min(ok, key=lambda c: c.metrics[key])
                ratio = _ratio(ph[key], best.metrics[key])
                text += (f", the most accurate baseline as smooth is {best.method} with "
                         f"{scale * best.metrics[key]:.3g} (phjax / it {ratio:.2f})")
            if never:
                least = _ratio(min(c.metrics[_JERK[ch]] for c in never), ph[_JERK[ch]])
                text += (f"; {', '.join(c.method for c in never)} never as smooth (at least "
                         f"{least:.2f}x phjax's jerk)")
            verdict.append(text)
        if verdict:
            lines += [f"At phjax's smoothness, lookahead {1e3 * L:g} ms: " + "; ".join(verdict)
                      + ".", ""]
    lines.append(CHOICES_LEGEND)
    return "\n".join(lines)


def _ratio(a: float, b: float) -> float:
    """``a / b`` for the verdict line: 1 when both are 0 (a still head without noise), inf
    when only ``b`` is."""
    if b == 0:
        return 1.0 if a == 0 else float("inf")
    return a / b


def plot_choices(comp: DisplayComparison, path: str | Path) -> Path:
    """PNG of the frontier at each lookahead (columns), position and rotation (rows): RMSE
    against RMS jerk for every knob the equal-smoothness search evaluated (one line per
    baseline, in knob order), the tuned knob (circle), the knob as smooth as phjax (filled
    square; open: the smoothest knob of one that never gets there) and phjax (red star, with a
    dotted line at its jerk). Lower left is better."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(comp.lookaheads)
    fig, axes = plt.subplots(2, n, figsize=(6.2 * n, 9), squeeze=False)
    for j, L in enumerate(comp.lookaheads):
        rows = comp.choices[L]
        ph = rows[0].metrics
        for i, (ch, rk, jk, scale, unit, junit) in enumerate((
                ("position", "position_rmse", "jerk_position", 1e3, "mm", "m/s^3"),
                ("rotation", "rotation_rmse_deg", "jerk_rotation", 1.0, "deg", "rad/s^3"))):
            ax = axes[i, j]
            ref = scale * ph[rk] if np.isfinite(ph.get(rk, np.nan)) else np.nan
            marks = []  # (x, y, marker, filled, colour): drawn once the limits are known
            lows = [ref]
            for c, (name, sweep) in enumerate(comp.sweeps[L].items()):
                colour = f"C{c if c < 3 else c + 1}"  # C3 (red) is phjax's
                pts = np.array([[kp if i == 0 else kr, m[jk], scale * m[rk]]
                                for kp, kr, m in sweep], float).reshape(-1, 3)
                pts = pts[np.all(np.isfinite(pts), axis=1)]
                pts = pts[np.argsort(pts[:, 0])]  # in knob order (the jerk is not monotonic)
                if len(pts):
                    ax.plot(pts[:, 1], pts[:, 2], "-", lw=1.2, color=colour, label=name,
                            alpha=0.8)
                    lows.append(pts[:, 2].min())
                for c_ in rows[1:]:
                    if c_.method == name:
                        marks.append((c_.metrics[jk], scale * c_.metrics[rk],
                                      "o" if c_.setting == "tuned" else "s",
                                      c_.setting == "equal smoothness" and c_.reached[i],
                                      colour))
            lows = [y for y in lows if np.isfinite(y)]
            if lows and np.isfinite(ref) and ref > 0:  # the choices' region; far-off points on the edge
                top = 2.5 * ref
                ax.set_ylim(0.8 * min(lows), top)
            else:
                top = np.inf
            off = 0
            for x, y, marker, filled, colour in marks:
                if not (np.isfinite(x) and np.isfinite(y)):
                    continue
                if y > top:  # off the scale: a triangle on the edge, its value beside it
                    ax.plot(x, 0.97 * top, "^", ms=8, color=colour, clip_on=False)
                    ax.annotate(f"{y:.3g} {unit}", (x, 0.97 * top), textcoords="offset points",
                                xytext=(5, -11 - 9 * off), fontsize=7, color=colour)
                    off += 1
                    continue
                ax.plot(x, y, marker, ms=8, color=colour,
                        mfc=colour if marker == "s" and filled else "none")
            if np.isfinite(ph.get(jk, np.nan)) and np.isfinite(ref):
                ax.axvline(ph[jk], color="C3", ls=":", lw=1)
                ax.plot(ph[jk], ref, "*", ms=16, color="C3", zorder=5,
                        label=f"phjax (horizon {1e3 * rows[0].knobs[i]:g} ms)")
            else:
                ax.text(0.5, 0.5, f"no {ch} data", ha="center", va="center",
                        transform=ax.transAxes)
            log = ph.get(jk, np.nan) > 0  # a still, noise-free head has no jerk to log-scale
            if log:
                ax.set_xscale("log")
            ax.set_xlabel(f"{ch} RMS jerk [{junit}]" + (" (log)" if log else ""))
            ax.set_ylabel(f"{ch} RMSE [{unit}] at the display time")
            ax.set_title(f"{ch}, lookahead {1e3 * L:g} ms")
            ax.grid(True, which="both", alpha=0.3)
    legend_on_first_labelled(axes, fontsize=7, loc="upper right")
    fig.suptitle("RMSE at the display time against RMS jerk; lower left is better. Each line "
                 "sweeps a baseline's knob; circle = its tuned knob; filled square = its best "
                 "knob as smooth as phjax\n(dotted line); open square = its smoothest knob when "
                 "none is as smooth; triangle = off the scale; star = phjax.", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
