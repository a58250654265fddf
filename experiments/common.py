"""Shared machinery of the studies (``fig1.py``, ``sensitivity.py``): data, windows, difficulty,
the fixed-shape window evaluator, the method registry and the bootstrap.

Protocol (see ``experiments/README.md`` for the reasoning):

* **Recordings** of three benchmarks from ``../shared/data`` (:func:`load_recordings`): *head*
  (VR head traces: Corbillon, AVTrack360, Hachaj, CWI), *object* (TUM VI hand-held rig, rooms
  1-3) and *camera* (TUM RGB-D). Orientation-only head traces get positions from a rigid neck
  model (:func:`neck_model_positions`), flagged per row in the outputs.
* **Windows** of 2-5 s drawn at random (seeded) from the recordings (:func:`draw_windows`),
  stratified by source for the head benchmark.
* **Excerpt protocol**: each window is evaluated on an excerpt of its recording that starts
  ``warmup`` (1 s) before the window and ends ``tail`` (0.5 s) after it (or at the recording's
  end). The sensor model samples the excerpt, every method runs on the excerpt's measurements
  (causal methods restart at the excerpt start; the warm-up removes their start-up transient),
  and the metrics are computed over the window only. Every excerpt is padded to one fixed shape
  (:class:`Shapes`) so each jitted method compiles once for all windows, rates and studies.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from phjax import io
from phjax.datasets import shared_data_dir
from phjax.evaluation import Method, default_methods
from phjax.evaluation.metrics import (
    evaluate,
    mean_abs_curvature,
    mean_abs_torsion,
    position_rmse,
    rms_jerk_position,
    rms_jerk_rotation,
    rotation_rmse_deg,
)
from phjax.motion.resample import ground_truth_max_gap, interpolate_poses
from phjax.motion.simulate import SensorModel, simulate_measurements

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ("head", "object", "camera")
HEAD_SOURCES = ("corbillon", "avtrack360", "hachaj", "cwi")

#: Head frame (x right, y up, -z forward) offset of the eyes from the neck pivot, m (the same
#: model as :func:`phjax.synthetic_head_motion`).
NECK_TO_EYES = np.array([0.0, 0.10, -0.08])
NECK_PIVOT = np.array([0.0, 1.10, 0.08])


# ----------------------------------------------------------------------------------------------
# recordings
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Recording:
    """One ground-truth recording (times in s from its start, m, wxyz)."""

    name: str
    dataset: str
    source: str
    times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    position_source: str  # "measured" or "neck model"

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def max_gap(self, protocol: Protocol) -> float:
        """Longest ground-truth gap (s) bridged by interpolation: ``protocol.max_gt_gap`` or 2.5
        median sample steps, whichever is larger (AVTrack360 is sampled at ~10 Hz)."""
        return max(protocol.max_gt_gap, ground_truth_max_gap(self.times))


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector(s) ``v`` by unit quaternion(s) ``q`` (wxyz), NumPy float64."""
    w, u = q[..., :1], q[..., 1:]
    uv = np.cross(u, v)
    return v + 2 * w * uv + 2 * np.cross(u, uv)


def neck_model_positions(quaternions: np.ndarray) -> np.ndarray:
    """Eye positions of a head rotating about a neck pivot: ``pivot + R(q) (0, 0.10, -0.08)``."""
    q = np.asarray(quaternions, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return NECK_PIVOT + rotate(q, np.broadcast_to(NECK_TO_EYES, q.shape[:-1] + (3,)))


def _rec(name, dataset, source, traj, neck_model) -> Recording:
    t = np.asarray(traj.times, np.float64)
    p = np.asarray(traj.positions, np.float64)
    q = np.asarray(traj.quaternions, np.float64)
    src = "measured"
    if not np.isfinite(p).any():
        if neck_model:
            p, src = neck_model_positions(q), "neck model"
        else:
            src = "none"
    return Recording(name, dataset, source, t - t[0], p, q, src)


def load_recordings(root: Path | None = None, *, neck_model: bool = True) -> dict[str, list[Recording]]:
    """All recordings of the three benchmarks, ``{dataset: [Recording, ...]}``.

    Raises ``FileNotFoundError`` when the shared data folder is absent.
    """
    root = shared_data_dir() if root is None else Path(root)
    if root is None or not root.is_dir():
        raise FileNotFoundError("../shared/data not found (set PHJAX_SHARED_DATA)")
    out: dict[str, list[Recording]] = {d: [] for d in DATASETS}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # readers warn about repeated / unsorted timestamps
        for f in sorted((root / "tum_rgbd_groundtruth").glob("*-groundtruth.txt")):
            out["camera"].append(_rec(f.name.split("-")[0], "camera", "tum-rgbd", io.read_tum(f),
                                      neck_model))
        for f in sorted((root / "tum_vi_room_groundtruth").glob("*.csv")):
            out["object"].append(_rec(f.stem.split("_")[0], "object", "tum-vi", io.read_euroc(f),
                                      neck_model))
        for f in sorted((root / "vr_corbillon_multiviewpoint360").glob("user*_quaternion.txt")):
            out["head"].append(_rec("corbillon-" + f.stem.split("_")[0], "head", "corbillon",
                                    io.read_corbillon(f), neck_model))
        for f in sorted((root / "vr_avtrack360").glob("*.json")):
            for video, traj in io.read_avtrack360(f).items():
                out["head"].append(_rec(f"avtrack360-{video}", "head", "avtrack360", traj,
                                        neck_model))
        hachaj = root / "vr_hachaj_head_gestures"
        for f in sorted(hachaj.glob("*.log")) + sorted(hachaj.glob("*/*.log")):
            rel = f.relative_to(hachaj).with_suffix("").as_posix()
            out["head"].append(_rec(f"hachaj-{rel}", "head", "hachaj", io.read_hachaj(f),
                                    neck_model))
        for f in sorted((root / "vr_cwi_6dof_navigation").glob("H*_nav.csv")):
            for pid, traj in io.read_cwi(f).items():
                out["head"].append(_rec(f"cwi-{f.stem.split('_')[0]}-{pid}", "head", "cwi", traj,
                                        neck_model))
    return out


# ----------------------------------------------------------------------------------------------
# windows
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Protocol:
    """Window lengths and the excerpt around each window (s)."""

    min_len: float = 2.0
    max_len: float = 5.0
    warmup: float = 1.0
    tail: float = 0.5
    max_gt_gap: float = 0.1
    min_coverage: float = 0.9

    @property
    def max_excerpt(self) -> float:
        return self.warmup + self.max_len + self.tail


@dataclasses.dataclass(frozen=True)
class Window:
    """A window ``[start, start + duration)`` (s from the recording's start) of a recording."""

    uid: int  # unique id inside the study; seeds the window's sensor simulation
    dataset: str
    source: str
    recording: int  # index into the dataset's recording list
    name: str
    start: float
    duration: float

    @property
    def block(self) -> str:
        """Bootstrap cluster: recording and 10-s block of the start (overlapping windows of one
        recording are not independent; resampling blocks keeps the CI honest)."""
        return f"{self.name}@{int(self.start // 10)}"


def _coverage(t: np.ndarray, a: float, b: float, max_gap: float) -> float:
    """Fraction of ``[a, b]`` covered by ground-truth intervals no longer than ``max_gap``."""
    i0 = max(np.searchsorted(t, a, side="right") - 1, 0)
    i1 = min(np.searchsorted(t, b, side="left") + 1, len(t))
    tt = t[i0:i1]
    lo, hi = np.maximum(tt[:-1], a), np.minimum(tt[1:], b)
    ok = np.diff(tt) <= max_gap
    return float(np.sum(np.clip(hi - lo, 0, None)[ok]) / (b - a))


def _split(n: int, k: int) -> list[int]:
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def draw_windows(
    recordings: dict[str, list[Recording]],
    n_per_dataset: int,
    seed: int,
    protocol: Protocol = Protocol(),
    datasets: Sequence[str] = DATASETS,
) -> list[Window]:
    """Draw ``n_per_dataset`` windows per dataset (seeded, deterministic).

    Per window: a length ``U(min_len, max_len)``; a recording with probability proportional to
    its usable span (``duration - warmup - length``; head windows are first split evenly over
    the four sources); a start uniform in ``[warmup, duration - length]``. Windows where the
    ground truth covers less than ``min_coverage`` of the time with gaps ``<= max_gt_gap`` are
    redrawn (gaps: :meth:`Recording.max_gap`).
    """
    rng = np.random.default_rng(seed)
    out: list[Window] = []
    uid = 0
    for d in datasets:
        recs = recordings[d]
        sources = sorted({r.source for r in recs}, key=lambda s: (
            HEAD_SOURCES.index(s) if s in HEAD_SOURCES else 99, s))
        for src, n_src in zip(sources, _split(n_per_dataset, len(sources))):
            idx = [i for i, r in enumerate(recs) if r.source == src]
            got, tries = 0, 0
            while got < n_src:
                tries += 1
                if tries > 200 * (n_src + 1):
                    raise RuntimeError(f"cannot draw windows from {d}/{src}")
                length = float(rng.uniform(protocol.min_len, protocol.max_len))
                span = np.array([recs[i].duration - protocol.warmup - length for i in idx])
                w = np.clip(span, 0, None)
                if w.sum() <= 0:
                    continue
                j = idx[int(rng.choice(len(idx), p=w / w.sum()))]
                start = float(protocol.warmup + rng.uniform(0, span[idx.index(j)]))
                r = recs[j]
                if _coverage(r.times, start, start + length, r.max_gap(protocol)) < protocol.min_coverage:
                    continue
                out.append(Window(uid, d, src, j, r.name, start, length))
                uid += 1
                got += 1
    return out


# ----------------------------------------------------------------------------------------------
# difficulty
# ----------------------------------------------------------------------------------------------

DIFFICULTY_FEATURES = ("angular_speed", "angular_accel", "linear_speed", "linear_accel")


def _rotvec(q):
    q = np.where(q[..., :1] < 0, -q, q)
    n = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    ang = 2 * np.arctan2(n, q[..., :1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 1e-12, ang / np.where(n > 0, n, 1), 2.0) * q[..., 1:]


def _qmul(p, q):
    a, u, b, v = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    return np.concatenate([a * b - np.sum(u * v, -1, keepdims=True),
                           a * v + b * u + np.cross(u, v)], -1)


def difficulty_features(times, positions, quaternions, span: float = 0.04) -> dict[str, float]:
    """Mean angular speed (rad/s), angular acceleration (rad/s^2), linear speed (m/s) and linear
    acceleration (m/s^2) of a ground-truth stream.

    Velocities are differences over ``span`` seconds (``k = round(span / h)`` samples,
    ``h`` the median spacing), accelerations differences of those velocities over another
    ``k`` samples, which keeps the mocap noise of 100 Hz ground truth (~1 mm) from dominating
    the accelerations. NaN rows (ground-truth gaps) are skipped; a feature without samples is NaN.
    """
    t = np.asarray(times, np.float64)
    p = np.asarray(positions, np.float64)
    q = np.asarray(quaternions, np.float64)
    if t.size < 3:
        return {k: float("nan") for k in DIFFICULTY_FEATURES}
    h = float(np.median(np.diff(t)))
    k = max(1, round(span / h))
    if t.size <= 2 * k:
        k = max(1, (t.size - 1) // 2)
    dt = (t[k:] - t[:-k])[:, None]
    conj = q[:-k] * np.array([1.0, -1, -1, -1])
    w = _rotvec(_qmul(q[k:], conj)) / dt
    v = (p[k:] - p[:-k]) / dt
    tm = 0.5 * (t[k:] + t[:-k])
    dtm = (tm[k:] - tm[:-k])[:, None]
    aw = (w[k:] - w[:-k]) / dtm
    av = (v[k:] - v[:-k]) / dtm

    def mean_norm(x):
        n = np.linalg.norm(x, axis=-1)
        n = n[np.isfinite(n)]
        return float(np.mean(n)) if n.size else float("nan")

    return dict(angular_speed=mean_norm(w), angular_accel=mean_norm(aw),
                linear_speed=mean_norm(v), linear_accel=mean_norm(av))


def difficulty_scores(features: np.ndarray) -> np.ndarray:
    """Difficulty of each window: the mean over the available features of ``f / median(f)``.

    Arguments:
        features: ``(n_windows, n_features)``; NaN = feature unavailable for that window.

    Returns:
        ``(n_windows,)`` scores (dimensionless, 1 = a typical window on every feature).
    """
    f = np.asarray(features, np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(f, axis=0)
        norm = f / np.where(med > 0, med, np.nan)
        return np.nanmean(norm, axis=1)


def difficulty_ranks(scores: np.ndarray) -> np.ndarray:
    """0-based rank from the least (0) to the most difficult window (ties by order)."""
    s = np.asarray(scores, np.float64)
    order = np.argsort(np.where(np.isfinite(s), s, np.inf), kind="stable")
    ranks = np.empty(s.size, int)
    ranks[order] = np.arange(s.size)
    return ranks


# ----------------------------------------------------------------------------------------------
# bootstrap
# ----------------------------------------------------------------------------------------------


def bootstrap_ci(
    values,
    *,
    groups=None,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Mean and percentile bootstrap confidence interval of the mean.

    With ``groups`` (one label per value) the bootstrap resamples whole groups with replacement
    (cluster bootstrap; the statistic is the mean over all values of the drawn groups), which
    keeps the interval honest when values within a group are correlated. NaN values are dropped.

    Returns:
        ``(mean, lower, upper)``; NaNs when no value is finite.
    """
    x = np.asarray(values, np.float64).ravel()
    g = np.arange(x.size) if groups is None else np.asarray(groups).ravel()
    if g.shape != x.shape:
        raise ValueError("groups must have one label per value")
    ok = np.isfinite(x)
    x, g = x[ok], g[ok]
    if x.size == 0:
        return (float("nan"),) * 3
    _, inv = np.unique(g, return_inverse=True)
    sums = np.bincount(inv, weights=x)
    sizes = np.bincount(inv).astype(np.float64)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, sums.size, size=(n_boot, sums.size))
    stats = sums[draws].sum(axis=1) / sizes[draws].sum(axis=1)
    a = (1 - level) / 2
    lo, hi = np.quantile(stats, [a, 1 - a])
    return float(x.mean()), float(lo), float(hi)


def bootstrap_ratio_ci(
    numerator,
    denominator,
    *,
    groups=None,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Ratio of means ``mean(numerator) / mean(denominator)`` of paired values and its
    percentile bootstrap CI (pairs resampled together; whole groups with ``groups``).

    Pairs with a NaN on either side are dropped. Used for relative differences
    ``mean(a - b) / mean(b) = ratio - 1``, whose interval then accounts for the uncertainty of
    both means (and stays above -100 % for non-negative metrics).
    """
    a = np.asarray(numerator, np.float64).ravel()
    b = np.asarray(denominator, np.float64).ravel()
    g = np.arange(a.size) if groups is None else np.asarray(groups).ravel()
    if not (a.shape == b.shape == g.shape):
        raise ValueError("numerator, denominator and groups must have the same length")
    ok = np.isfinite(a) & np.isfinite(b)
    a, b, g = a[ok], b[ok], g[ok]
    if a.size == 0 or b.sum() == 0:
        return (float("nan"),) * 3
    _, inv = np.unique(g, return_inverse=True)
    sa, sb = np.bincount(inv, weights=a), np.bincount(inv, weights=b)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, sa.size, size=(n_boot, sa.size))
    with np.errstate(divide="ignore", invalid="ignore"):
        stats = sa[draws].sum(axis=1) / sb[draws].sum(axis=1)
    q = (1 - level) / 2
    lo, hi = np.nanquantile(stats, [q, 1 - q])
    return float(a.sum() / b.sum()), float(lo), float(hi)


# ----------------------------------------------------------------------------------------------
# methods
# ----------------------------------------------------------------------------------------------


def _reconstruct_optimised_angles(times, positions, quaternions, render_times, config=None):
    """``phjax.reconstruct`` with bending-energy-optimal free angles (``phjax.curves.shape``).

    Mirrors the library's offline reconstruction with public functions only: RTS-smoothed
    Kalman states, one position segment per frame interval with the angles of
    :func:`phjax.curves.shape.optimize_shape` (``objective="bending_energy"``) instead of the
    closed-form near-optimal default, evaluated at the render times exactly as
    :func:`phjax.reconstruct` does; orientations are :func:`phjax.reconstruct`'s (the angles
    only change the position curve). Positions NaN when the input has none.
    """
    from phjax import TrackerConfig, reconstruct

    cfg = TrackerConfig() if config is None else config
    _, q_out = reconstruct(times, positions, quaternions, render_times, config=cfg)
    t = np.asarray(times, np.float64)
    p_in = np.asarray(positions, np.float64)
    if not np.isfinite(p_in).any():
        return np.full((np.shape(render_times)[0], 3), np.nan), q_out
    return _optimised_positions(cfg, t - t[0], p_in, np.asarray(quaternions, np.float64),
                                np.asarray(render_times, np.float64) - t[0]), q_out


@jax.jit
def _optimised_positions(cfg, t, p, q, r):
    import jax.numpy as jnp

    from phjax import kalman_filter, rts_smooth
    from phjax.curves.shape import optimize_shape

    sm = rts_smooth(cfg.kalman, kalman_filter(cfg.kalman, t, p, q)[0])
    x, v, ok = sm.x[:, :3], sm.x[:, 3:6], sm.initialized
    dt = jnp.diff(t)
    curves, _ = optimize_shape(x[:-1], x[1:], v[:-1] * dt[:, None], v[1:] * dt[:, None])
    n = t.shape[0]
    tau = jnp.maximum(r, t[jnp.argmax(ok)])
    idx = jnp.clip(jnp.searchsorted(t, tau, side="right") - 1, 0, n - 2)
    s = jnp.clip((tau - t[idx]) / dt[idx], 0, 1)
    cs = jax.tree.map(lambda a: a[idx], curves)
    out = jax.vmap(lambda c, u: c.position(u))(cs, s)
    return out + jnp.where(jnp.any(ok), 0.0, jnp.nan)


def _tuned_phi_methods() -> list[Method]:
    """phjax offline with optimised free angles, when the library has ``phjax.curves.shape``."""
    try:
        import phjax.curves.shape  # noqa: F401
    except ImportError:
        return []
    return [Method("phjax (offline, optimised angles)", _reconstruct_optimised_angles, False)]


#: Extra method providers, each ``() -> list[Method]``; append one entry to add a method.
EXTRA_METHODS: list[Callable[[], list[Method]]] = [_tuned_phi_methods]


#: Methods left out of ``--quick``/``--smoke`` runs unless named (their compilation alone takes
#: minutes on 2 cores).
SLOW_METHODS = {"phjax (offline, optimised angles)"}


def study_methods(names: Sequence[str] | None = None, *, include_slow: bool = True) -> list[Method]:
    """``phjax.evaluation.default_methods()`` plus every :data:`EXTRA_METHODS` entry, optionally
    restricted to ``names`` (in that order; unknown names raise ``ValueError``) or, without
    names and ``include_slow=False``, without :data:`SLOW_METHODS`."""
    methods = list(default_methods())
    for provider in EXTRA_METHODS:
        methods += provider()
    if names is None:
        return [m for m in methods if include_slow or m.name not in SLOW_METHODS]
    by_name = {m.name: m for m in methods}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; available: {list(by_name)}")
    return [by_name[n] for n in names]


def is_phjax(name: str) -> bool:
    return name.startswith("phjax")


def method_style(name: str, index: int = 0) -> dict:
    """Matplotlib style: phjax in reds (as the paper), baselines in blues/greys."""
    fixed = {
        "phjax (causal)": dict(color="#d62728", ls="-", lw=2.0),
        "phjax (offline)": dict(color="#8c1515", ls="--", lw=1.6),
        "phjax (offline, optimised angles)": dict(color="#ff7f0e", ls=":", lw=1.6),
        "kalman-cv extrapolation": dict(color="#1f3fbf", ls="-", lw=1.6),
        "one-euro + hold": dict(color="#5fa2dd", ls="-", lw=1.2),
        "raw hold": dict(color="#7f8fa6", ls="-", lw=1.0),
        "cubic spline (scipy)": dict(color="#17becf", ls="--", lw=1.2),
        "linear + slerp": dict(color="#4b6584", ls=":", lw=1.2),
        "ground truth": dict(color="black", ls=":", lw=1.2),
    }
    if name in fixed:
        return fixed[name]
    reds, blues = ["#ff7f0e", "#e377c2", "#bcbd22"], ["#9467bd", "#2ca02c", "#8c564b"]
    pal = reds if is_phjax(name) else blues
    return dict(color=pal[index % len(pal)], ls="-.", lw=1.2)


# ----------------------------------------------------------------------------------------------
# fixed-shape window evaluation
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Shapes:
    """Static array sizes shared by every excerpt (one compilation per method per process).

    ``gt``: ground-truth rows of an excerpt (padded); ``frames``: sensor frames (enough for
    ``max_rate``); ``render``: render samples of the longest window at ``max_render``.
    """

    gt: int = 2304
    frames: int = 400
    render: int = 736
    max_rate: float = 60.0
    max_render: float = 144.0

    @staticmethod
    def for_protocol(protocol: Protocol, max_rate: float = 60.0, max_render: float = 144.0,
                     gt_rate: float = 320.0) -> Shapes:
        def up(n, m=16):  # round up to a multiple of m
            return int(math.ceil(n / m) * m)

        return Shapes(
            gt=up(protocol.max_excerpt * gt_rate + 2, 256),
            frames=up(protocol.max_excerpt * max_rate + 2),
            render=up(protocol.max_len * max_render + 2),
            max_rate=max_rate,
            max_render=max_render,
        )


@dataclasses.dataclass
class Excerpt:
    """Measurements and render grid of one window, padded to :class:`Shapes`.

    ``times/positions/quaternions`` are the sensor frames (rows after the excerpt's end are NaN:
    dropped frames for every method); ``render`` the render times (the first ``n_render`` are
    inside the window); ``gt_positions/gt_quaternions`` the ground truth at ``render`` (NaN in
    ground-truth gaps longer than ``max_gt_gap``). Times are relative to the excerpt start.
    """

    times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    render: np.ndarray
    n_render: int
    gt_positions: np.ndarray
    gt_quaternions: np.ndarray
    window_start: float
    window_end: float


def make_excerpt(
    rec: Recording,
    window: Window,
    *,
    sensor: SensorModel,
    render_rate: float,
    seed: int,
    protocol: Protocol,
    shapes: Shapes,
) -> Excerpt:
    """Simulate the sensor on the window's excerpt and build the padded arrays (fixed shapes).

    The sensor key is ``fold_in(key(seed), window.uid)``, so a window sees the same noise
    realisation in every condition of a study (common random numbers).
    """
    if float(sensor.rate) > shapes.max_rate + 1e-9 or render_rate > shapes.max_render + 1e-9:
        raise ValueError(f"rate {sensor.rate} / render rate {render_rate} exceed the shapes' "
                         f"capacity ({shapes.max_rate}, {shapes.max_render})")
    t = rec.times
    a = window.start - protocol.warmup
    b = min(window.start + window.duration + protocol.tail, t[-1])
    sel = (t >= a) & (t <= b)
    gt_t, gt_p, gt_q = t[sel], rec.positions[sel], rec.quaternions[sel]
    n = gt_t.size
    if n + 1 > shapes.gt:
        raise ValueError(f"excerpt of {window.name} has {n} ground-truth rows > {shapes.gt - 1}")
    origin = gt_t[0]
    rate = float(sensor.rate)
    t_pad = (shapes.frames - 1) / rate  # simulate_measurements then yields exactly `frames` rows
    pt = np.full(shapes.gt, origin + t_pad)
    pt[:n] = gt_t
    pp = np.full((shapes.gt, 3), np.nan)
    pp[:n] = gt_p
    pq = np.full((shapes.gt, 4), np.nan)
    pq[:n] = gt_q
    pt = pt - origin
    key = jax.random.fold_in(jax.random.key(seed), window.uid)
    mt, mp, mq = (np.array(x, np.float64) for x in simulate_measurements(
        key, pt, pp, pq, sensor, max_gt_gap=rec.max_gap(protocol)))
    if mt.shape[0] != shapes.frames:
        raise AssertionError(f"expected {shapes.frames} frames, got {mt.shape[0]}")
    beyond = mt > (gt_t[-1] - origin) + 1e-9
    mp[beyond] = np.nan
    mq[beyond] = np.nan
    ws, we = window.start - origin, window.start + window.duration - origin
    render = ws + np.arange(shapes.render) / render_rate
    n_render = int(np.sum(render < we))
    gp, gq = interpolate_poses(pt, pp, pq, render, max_gap=rec.max_gap(protocol))
    return Excerpt(mt, mp, mq, render, n_render, np.asarray(gp, np.float64),
                   np.asarray(gq, np.float64), ws, we)


def run_methods(ex: Excerpt, methods: Sequence[Method], timings: dict | None = None
                ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every method's render stream inside the window: ``{name: (positions, quaternions)}``.

    ``timings``: optional dict; each method's wall time (s, results on the host) is appended to
    ``timings[name]``.
    """
    out = {}
    n = ex.n_render
    for m in methods:
        t0 = time.perf_counter()
        p, q = m.fn(ex.times, ex.positions, ex.quaternions, ex.render)
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        if timings is not None:
            timings.setdefault(m.name, []).append(time.perf_counter() - t0)
        out[m.name] = (p[:n], q[:n])
    return out


def path_curvature_torsion(positions, *, min_step: float = 1e-9, min_turn: float = 1e-6
                           ) -> tuple[float, float]:
    """Mean curvature and torsion of the rendered path as a polyline, per unit arc length.

    The rendered stream is what the viewer sees: the polyline through the render-rate
    positions. With the non-zero steps ``d_i = x_{i+1} - x_i`` (steps shorter than ``min_step``
    m, e.g. the repeated samples of a zero-order hold, are removed) the discrete curvature is the
    total turning angle ``sum angle(d_i, d_{i+1})`` and the discrete torsion the total rotation
    of the binormal line between consecutive corners, ``sum angle(b_j, +-b_{j+1})`` (in
    ``[0, pi/2]``, so a planar path, inflections included, has zero torsion) with ``b = d_i x
    d_{i+1} / |...|`` at the vertices that turn by more than ``min_turn`` rad (straight runs
    between kinks have no binormal), each divided by the path length ``sum |d_i|``. For a smooth curve sampled finely these converge to the arc-length
    means of ``kappa`` and ``|tau|``; unlike pointwise finite-difference curvature they also
    count the kinks and jumps of piecewise-constant or piecewise-linear streams (a hold's
    staircase, an extrapolator's saw-tooth), where the pointwise curvature is zero between
    kinks and undefined at them. NaN rows split nothing: steps touching them are dropped.

    Returns:
        ``(curvature, torsion)`` in 1/m; NaN when the path has fewer than 2 (3) usable steps.
    """
    x = np.asarray(positions, np.float64)
    d = np.diff(x, axis=0)
    d = d[np.isfinite(d).all(-1)]
    n = np.linalg.norm(d, axis=-1)
    d, n = d[n > min_step], n[n > min_step]
    if d.shape[0] < 2:
        return float("nan"), float("nan")
    length = float(n.sum())
    u = d / n[:, None]
    cross = np.cross(u[:-1], u[1:])
    turn = np.arctan2(np.linalg.norm(cross, axis=-1), np.sum(u[:-1] * u[1:], axis=-1))
    kappa = float(turn.sum() / length)
    corner = np.linalg.norm(cross, axis=-1) > min_turn  # sin(turn): reversals have no binormal
    if corner.sum() < 2:
        return kappa, float("nan")
    b = cross[corner]
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    twist = np.arctan2(np.linalg.norm(np.cross(b[:-1], b[1:]), axis=-1),
                       np.abs(np.sum(b[:-1] * b[1:], axis=-1)))
    return kappa, float(twist.sum() / length)


#: Metrics of the studies (key, label, unit). ``curvature_path``/``torsion_path`` are
#: :func:`path_curvature_torsion` (the figure's curvature and torsion); ``curvature``/``torsion``
#: are phjax.evaluation.metrics' pointwise means (kept in the CSV; see experiments/README.md).
FIG1_METRICS = {
    "position_rmse": ("position RMSE", "m"),
    "curvature_path": ("mean curvature", "1/m"),
    "torsion_path": ("mean abs torsion", "1/m"),
    "rotation_rmse_deg": ("rotation RMSE", "deg"),
}
EXTRA_METRICS = {
    "jerk_position": ("RMS jerk (position)", "m/s^3"),
    "jerk_rotation": ("RMS angular jerk", "rad/s^3"),
    "latency_position": ("latency (position)", "s"),
    "latency_rotation": ("latency (rotation)", "s"),
    "curvature": ("pointwise mean curvature", "1/m"),
    "torsion": ("pointwise mean abs torsion", "1/m"),
}
ALL_METRICS = {**FIG1_METRICS, **EXTRA_METRICS}


def window_metrics(ex: Excerpt, p: np.ndarray, q: np.ndarray, *, full: bool = True,
                   max_lag: float = 0.25) -> dict[str, float]:
    """Metrics of one stream over the window.

    ``full=True``: :func:`phjax.evaluation.metrics.evaluate` (RMSEs, curvature, torsion, jerks, velocity
    jumps at the camera frames, latencies with ``max_lag``). ``full=False``: only RMSEs and jerks
    (cheap; the sensitivity study).
    """
    n = ex.n_render
    r, gp, gq = ex.render[:n], ex.gt_positions[:n], ex.gt_quaternions[:n]
    if full:
        valid = np.isfinite(ex.quaternions).all(-1)
        bt = ex.times[valid & (ex.times >= r[0]) & (ex.times <= r[-1])]
        out = evaluate(r, p, q, gp, gq, boundary_times=bt, max_lag=max_lag)
        out["curvature_path"], out["torsion_path"] = path_curvature_torsion(p)
        return out
    return dict(
        position_rmse=position_rmse(p, gp).value,
        rotation_rmse_deg=rotation_rmse_deg(q, gq).value,
        jerk_position=rms_jerk_position(r, p).value,
        jerk_rotation=rms_jerk_rotation(r, q).value,
    )


def ground_truth_metrics(ex: Excerpt) -> dict[str, float]:
    """Path metrics of the ground truth itself over the window (reference values)."""
    n = ex.n_render
    r, gp, gq = ex.render[:n], ex.gt_positions[:n], ex.gt_quaternions[:n]
    kappa, tau = path_curvature_torsion(gp)
    return dict(curvature_path=kappa, torsion_path=tau,
                curvature=mean_abs_curvature(r, gp).value, torsion=mean_abs_torsion(r, gp).value,
                jerk_position=rms_jerk_position(r, gp).value,
                jerk_rotation=rms_jerk_rotation(r, gq).value)


# ----------------------------------------------------------------------------------------------
# output helpers
# ----------------------------------------------------------------------------------------------


def git_state() -> str:
    """Commit of the repository and whether the library has uncommitted changes."""
    import subprocess

    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True,
                                  timeout=10, check=False).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--", "phjax")
    return f"commit {head}" + (" + uncommitted library changes" if dirty else "")


def environment_line() -> str:
    return (f"python {platform.python_version()}, jax {jax.__version__}, numpy {np.__version__}, "
            f"{os.cpu_count()} cores, x64={jax.config.jax_enable_x64}, {git_state()}, "
            f"{time.strftime('%Y-%m-%d %H:%M')}")


def fmt(x: float, digits: int = 3) -> str:
    """Compact number: 3 significant digits, ``-`` for NaN."""
    if x is None or not np.isfinite(x):
        return "-"
    if x == 0:
        return "0"
    mag = abs(x)
    if 1e-3 <= mag < 1e5:
        return f"{x:.{max(digits - 1 - math.floor(math.log10(mag)), 0)}f}"
    return f"{x:.{digits - 1}e}"


def fmt_ci(mean: float, lo: float, hi: float) -> str:
    return f"{fmt(mean)} [{fmt(lo)}, {fmt(hi)}]"


def progress(iterable, enabled: bool, **kw):
    if not enabled:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, **kw)


def write_csv(path: Path, rows: list[dict]) -> None:
    import csv

    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def read_csv(path: Path) -> list[dict]:
    import csv

    with open(path, newline="") as f:
        return list(csv.DictReader(f))
