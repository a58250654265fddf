"""Accuracy, smoothness and latency metrics for rendered pose streams.

All metrics are evaluated in **float64 NumPy**, independently of JAX's x64 flag: third derivatives
by finite differences are far below float32 resolution. Inputs may be NumPy or JAX arrays.

Batches: every metric also takes a batch of recordings, its array arguments with the same
leading axes ``B`` (``times (*B, n)``, ``est (*B, n, 3)``, ...), NaN-padded to a common length
(padding rule of :mod:`phjax.batch`: a NaN time marks a padding row, which is cut off;
``boundary_times`` may be shared ``(b,)`` or per recording ``(*B, b)`` with NaN padding). Each
recording is evaluated alone (a loop in NumPy); a :class:`Metric` / :class:`Latency` then holds
arrays of shape ``B`` and :func:`evaluate` returns a dict of such arrays.

NaN handling: every metric ignores samples (or finite-difference windows) that touch a NaN row of
either input and reports how many were used. A metric with nothing to evaluate returns
``Metric(nan, 0)`` instead of raising, so orientation-only data (NaN positions) yields NaN
position metrics.

Conventions: quaternions are ``wxyz``; angular velocities are world-frame (``dq/dt = 0.5 w q``);
finite-difference derivatives use local polynomial stencils on the actual (possibly non-uniform)
sample times, so no uniform grid is assumed; times must be strictly increasing.
"""

from __future__ import annotations

import functools
import inspect
import math
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Float

from .._np_quat import np_from_rotvec as _np_from_rotvec
from .._np_quat import np_qconj as _np_qconj
from .._np_quat import np_qmul as _np_qmul
from .._np_quat import np_valid_quaternions
from .._np_quat import np_qnormalize as _np_qnormalize
from .._np_quat import np_rotvec as _np_rotvec

__all__ = [
    "Lag",
    "Latency",
    "Metric",
    "evaluate",
    "latency",
    "max_angular_velocity_jump",
    "max_velocity_jump",
    "mean_abs_curvature",
    "mean_abs_torsion",
    "position_rmse",
    "rms_jerk_position",
    "rms_jerk_rotation",
    "rotation_rmse_deg",
    "shift_lag",
]


class Metric(NamedTuple):
    """A scalar metric and the number of samples (or windows) it was computed from (arrays of
    the batch shape for a batch of recordings)."""

    value: float
    count: int


class Latency(NamedTuple):
    """Estimated lag (s, positive = estimate behind), peak normalised correlation, samples used."""

    value: float
    correlation: float
    count: int


class Lag(NamedTuple):
    """Time shift (s, positive = estimate behind) minimising the RMSE against the shifted ground
    truth, the RMSE at the best grid shift (m or deg), and the number of samples used."""

    value: float
    rmse: float
    count: int


_NAN = Metric(float("nan"), 0)


# ----------------------------------------------------------------------------------------------
# float64 NumPy quaternion helpers (wxyz); also used by the NumPy reference baselines
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------


def _as64(x: ArrayLike) -> np.ndarray:
    """``x`` as float64; rows of 4 are ``wxyz`` quaternions here, and a zero one (no
    orientation: it normalises to nothing) becomes a NaN row, skipped like one."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim >= 2 and x.shape[-1] == 4:
        x = np.where(np_valid_quaternions(x)[..., None], x, np.nan)
    return x


def _finite_rows(x: np.ndarray) -> np.ndarray:
    return np.all(np.isfinite(x), axis=-1)


def _check_times(t: np.ndarray, n: int) -> None:
    if t.shape != (n,):
        raise ValueError(f"times must have shape ({n},), got {t.shape}")
    if n > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("times must be finite and strictly increasing")


def _fd_weights(offsets: np.ndarray, order: int) -> np.ndarray:
    """Finite-difference weights for the ``order``-th derivative at offset 0.

    ``sum_j w_j f(t + d_j)`` is exact for polynomials of degree ``< m`` (``m`` = number of
    offsets). Batched over leading axes; offsets are rescaled to ``[-1, 1]`` before the
    Vandermonde solve for conditioning.
    """
    d = np.asarray(offsets, dtype=np.float64)
    m = d.shape[-1]
    scale = np.max(np.abs(d), axis=-1, keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    s = d / scale
    k = np.arange(m)
    fact = np.array([math.factorial(i) for i in range(m)], dtype=np.float64)
    vander = s[..., None, :] ** k[:, None] / fact[:, None]  # [..., k, j] = s_j^k / k!
    rhs = np.zeros(d.shape[:-1] + (m, 1))
    rhs[..., order, 0] = 1.0
    w = np.linalg.solve(vander, rhs)[..., 0]
    return w / scale**order


def _windows(n: int, size: int) -> np.ndarray:
    """Index windows ``[i, i + size)`` for ``i = 0 .. n - size``, shape ``(n - size + 1, size)``."""
    return np.arange(n - size + 1)[:, None] + np.arange(size)[None, :]


def _stencil_derivatives(t: np.ndarray, x: np.ndarray, orders: tuple[int, ...], size: int = 5):
    """Derivatives at the centres of all ``size``-point windows whose rows are all finite.

    Returns ``(centre_indices, [deriv_order (c, d) for each order])``.
    """
    n = t.shape[0]
    if n < size:
        return np.zeros(0, dtype=int), [np.zeros((0,) + x.shape[1:]) for _ in orders]
    win = _windows(n, size)
    ok = np.all(_finite_rows(x)[win], axis=1)
    win = win[ok]
    c = size // 2
    centre = win[:, c]
    offs = t[win] - t[centre][:, None]
    out = []
    for order in orders:
        w = _fd_weights(offs, order)
        out.append(np.einsum("wj,wjd->wd", w, x[win]))
    return centre, out


def _angular_velocity_midpoints(t: np.ndarray, q: np.ndarray):
    """World-frame angular velocity between consecutive samples, at the interval midpoints."""
    return _span_velocity(t, q, 1, "rotation")


def _span_velocity(t: np.ndarray, x: np.ndarray, span: int, kind: str):
    """Mean (angular) velocity over ``[t_i, t_{i+span}]``, placed at the interval midpoint."""
    dt = (t[span:] - t[:-span])[:, None]
    if kind == "position":
        d = x[span:] - x[:-span]
    else:
        q = _np_qnormalize(x)
        d = _np_rotvec(_np_qmul(q[span:], _np_qconj(q[:-span])))
    return 0.5 * (t[span:] + t[:-span]), d / dt


# ----------------------------------------------------------------------------------------------
# batches of recordings
# ----------------------------------------------------------------------------------------------

#: core rank of each kind of batched argument: per-frame rows, frame times, a set of times
_CORE = {"rows": 2, "times": 1, "set": 1}


def _stack_results(results, batch):
    first = results[0]
    if isinstance(first, dict):
        return {k: np.array([r[k] for r in results]).reshape(batch) for k in first}
    return type(first)(*(np.array(v).reshape(batch) for v in zip(*results)))


def _over_recordings(**kinds: str):
    """Let a metric take NaN-padded batches of recordings (see the module docs).

    ``kinds`` maps argument names to ``"rows"`` (``(*B, n, d)``), ``"times"`` (``(*B, n)``: a
    NaN time marks a padding row of every ``rows`` argument) or ``"set"`` (``(b,)`` shared or
    ``(*B, b)``, NaN entries dropped). The first named argument decides whether the call is
    batched; then the metric runs once per recording and the results are stacked.
    """

    def wrap(fn):
        sig = inspect.signature(fn)
        names = list(kinds)

        @functools.wraps(fn)
        def batched(*args, **kwargs):
            bound = sig.bind(*args, **kwargs)
            first = np.asarray(bound.arguments[names[0]])
            extra = first.ndim - _CORE[kinds[names[0]]]
            if extra <= 0:
                return fn(*args, **kwargs)
            batch = first.shape[:extra]
            r = int(np.prod(batch))
            flat = {}
            for name in names:
                v = bound.arguments.get(name)
                if v is None:
                    continue
                v = np.asarray(v, np.float64)
                if v.shape[:extra] == batch and v.ndim == _CORE[kinds[name]] + extra:
                    flat[name] = v.reshape((r,) + v.shape[extra:])
                elif kinds[name] == "set" and v.ndim == 1:
                    flat[name] = np.broadcast_to(v, (r,) + v.shape)
                else:
                    raise ValueError(f"{name}: shape {v.shape} does not match the batch shape "
                                     f"{batch}")
            time_name = next((k for k in names if kinds[k] == "times"), None)
            results = []
            for i in range(r):
                keep = None if time_name is None else np.isfinite(flat[time_name][i])
                if keep is not None and not np.all(keep[:keep.sum()]):
                    raise ValueError(f"recording {i}: padding (NaN times) must come after "
                                     "every real row")
                for name, v in flat.items():
                    x = v[i]
                    if kinds[name] == "set":
                        x = x[np.isfinite(x)]
                    elif keep is not None:
                        x = x[keep]
                    bound.arguments[name] = x
                results.append(fn(*bound.args, **bound.kwargs))
            return _stack_results(results, batch)

        return batched

    return wrap


# ----------------------------------------------------------------------------------------------
# accuracy
# ----------------------------------------------------------------------------------------------


def _common_rows(est, gt):
    """``est`` and ``gt`` as float64 (same shape, else ``ValueError``), the mask of rows finite
    in both and its count."""
    est, gt = _as64(est), _as64(gt)
    if est.shape != gt.shape:
        raise ValueError(f"shape mismatch: {est.shape} vs {gt.shape}")
    ok = _finite_rows(est) & _finite_rows(gt)
    return est, gt, ok, int(ok.sum())


@_over_recordings(est="rows", gt="rows")
def position_rmse(est: Float[ArrayLike, "n 3"], gt: Float[ArrayLike, "n 3"]) -> Metric:
    """Root-mean-square Euclidean position error (m) over rows finite in both inputs."""
    est, gt, ok, n = _common_rows(est, gt)
    if n == 0:
        return _NAN
    err = np.sum((est[ok] - gt[ok]) ** 2, axis=-1)
    return Metric(float(np.sqrt(np.mean(err))), n)


def _geodesic_angle(q_est: np.ndarray, q_gt: np.ndarray) -> np.ndarray:
    dq = _np_qmul(_np_qconj(_np_qnormalize(q_est)), _np_qnormalize(q_gt))
    return 2 * np.arctan2(np.linalg.norm(dq[..., 1:], axis=-1), np.abs(dq[..., 0]))


@_over_recordings(q_est="rows", q_gt="rows")
def rotation_rmse_deg(q_est: Float[ArrayLike, "n 4"], q_gt: Float[ArrayLike, "n 4"]) -> Metric:
    """RMS geodesic rotation error in degrees (angle of ``q_est* q_gt``; sign-invariant)."""
    q_est, q_gt, ok, n = _common_rows(q_est, q_gt)
    if n == 0:
        return _NAN
    ang = _geodesic_angle(q_est[ok], q_gt[ok])
    return Metric(float(np.degrees(np.sqrt(np.mean(ang**2)))), n)


# ----------------------------------------------------------------------------------------------
# smoothness
# ----------------------------------------------------------------------------------------------


@_over_recordings(times="times", positions="rows")
def rms_jerk_position(times: Float[ArrayLike, " n"], positions: Float[ArrayLike, "n 3"]) -> Metric:
    """RMS magnitude of the third derivative of position (m/s^3).

    Each window of four consecutive finite samples gives ``6 x[t_i, ..., t_{i+3}]`` (six times
    the third divided difference, i.e. the jerk of the interpolating cubic): exact for cubics on
    any spacing, second-order accurate on a uniform grid. ``count`` = windows used.

    The value belongs to the stream *as sampled*: compare methods at the same sample rate. A
    stream that is only C1 (acceleration steps, e.g. at camera frames) has no finite continuous
    RMS jerk, so its value grows with the sample rate; a jerk that lasts only a few sample
    periods is smoothed by the four-sample stencil.
    """
    t, x = _as64(times), _as64(positions)
    _check_times(t, x.shape[0])
    if x.shape[0] < 4:
        return _NAN
    win = _windows(x.shape[0], 4)
    win = win[np.all(_finite_rows(x)[win], axis=1)]
    if win.shape[0] == 0:
        return _NAN
    w = _fd_weights(t[win] - t[win[:, :1]], 3)
    jerk = np.einsum("wj,wjd->wd", w, x[win])
    return Metric(float(np.sqrt(np.mean(np.sum(jerk**2, axis=-1)))), int(win.shape[0]))


@_over_recordings(times="times", quaternions="rows")
def rms_jerk_rotation(
    times: Float[ArrayLike, " n"], quaternions: Float[ArrayLike, "n 4"]
) -> Metric:
    """RMS magnitude of the angular jerk ``d^2 omega / dt^2`` (rad/s^3), world frame.

    The angular velocity between consecutive samples is ``log(q_{i+1} q_i*) / dt`` (shortest arc,
    so sign flips are harmless) placed at the interval midpoint; its second derivative uses the
    three-point non-uniform stencil on those midpoints. Each value needs four consecutive finite
    quaternions (``count`` = such windows). Exact for a fixed axis with cubic angle on a uniform
    grid.
    """
    t, q = _as64(times), _as64(quaternions)
    _check_times(t, q.shape[0])
    if q.shape[0] < 4:
        return _NAN
    m, w = _angular_velocity_midpoints(t, q)
    ok = np.all(_finite_rows(w)[_windows(w.shape[0], 3)], axis=1)
    win = _windows(w.shape[0], 3)[ok]
    if win.shape[0] == 0:
        return _NAN
    wts = _fd_weights(m[win] - m[win[:, 1:2]], 2)
    jerk = np.einsum("wj,wjd->wd", wts, w[win])
    return Metric(float(np.sqrt(np.mean(np.sum(jerk**2, axis=-1)))), int(win.shape[0]))


def _curve_derivatives(times, positions):
    t, x = _as64(times), _as64(positions)
    _check_times(t, x.shape[0])
    _, (d1, d2, d3) = _stencil_derivatives(t, x, (1, 2, 3), size=5)
    return d1, d2, d3


@_over_recordings(times="times", positions="rows")
def mean_abs_curvature(
    times: Float[ArrayLike, " n"], positions: Float[ArrayLike, "n 3"], *, min_speed: float = 1e-3
) -> Metric:
    """Mean curvature ``|r' x r''| / |r'|^3`` (1/m) of the sampled path.

    Derivatives come from centred five-point stencils on the actual sample times (exact for
    quartic paths); windows containing NaN are skipped. Samples with speed below
    ``min_speed`` (m/s, default 1 mm/s) are skipped: there the curvature of a nearly stationary
    path is dominated by noise (and undefined at rest). ``count`` = samples used. Unweighted mean
    over samples (not per arc length).
    """
    d1, d2, _ = _curve_derivatives(times, positions)
    speed = np.linalg.norm(d1, axis=-1)
    ok = speed >= min_speed
    if not np.any(ok):
        return _NAN
    kappa = np.linalg.norm(np.cross(d1[ok], d2[ok]), axis=-1) / speed[ok] ** 3
    return Metric(float(np.mean(kappa)), int(ok.sum()))


@_over_recordings(times="times", positions="rows")
def mean_abs_torsion(
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    *,
    min_speed: float = 1e-3,
    min_cross: float = 1e-6,
) -> Metric:
    """Mean ``|(r' x r'') . r'''| / |r' x r''|^2`` (1/m) of the sampled path.

    Same stencils as :func:`mean_abs_curvature`. Skips samples with speed below ``min_speed``
    (m/s) or ``|r' x r''|`` below ``min_cross`` (m^2/s^3, default 1e-6): torsion is undefined on
    straight segments (zero curvature). ``count`` = samples used.
    """
    d1, d2, d3 = _curve_derivatives(times, positions)
    cross = np.cross(d1, d2)
    cn = np.linalg.norm(cross, axis=-1)
    ok = (np.linalg.norm(d1, axis=-1) >= min_speed) & (cn >= min_cross)
    if not np.any(ok):
        return _NAN
    tau = np.abs(np.sum(cross[ok] * d3[ok], axis=-1)) / cn[ok] ** 2
    return Metric(float(np.mean(tau)), int(ok.sum()))


def _one_sided(t, x, idx, boundary_value_index, local=None):
    """Second-order one-sided derivative at sample ``boundary_value_index`` from rows ``idx``
    of ``x`` (or of the window values ``local(x, idx, boundary_value_index)``, ``(b, 3, d)``)."""
    e = boundary_value_index
    w = _fd_weights(t[idx] - t[e][:, None], 1)
    return np.einsum("bj,bjd->bd", w, x[idx] if local is None else local(x, idx, e))


def _max_jump(times, x, boundary_times, local=None) -> Metric:
    """Largest ``|D(b+) - D(b-)|`` over the boundaries of :func:`_boundary_windows`, ``D`` the
    :func:`_one_sided` derivative at the window's sample nearest to ``b``."""
    t, x = _as64(times), _as64(x)
    _check_times(t, x.shape[0])
    if t.shape[0] < 3:  # no three samples on a side (and no index to clip to when empty)
        return _NAN
    left, right = _boundary_windows(t, _finite_rows(x), boundary_times)
    if left.shape[0] == 0:
        return _NAN
    jump = np.linalg.norm(_one_sided(t, x, right, right[:, 0], local)
                          - _one_sided(t, x, left, left[:, -1], local), axis=-1)
    return Metric(float(np.max(jump)), int(left.shape[0]))


def _boundary_windows(t, valid, boundary_times):
    """For each boundary the 3 samples ending at the last ``t <= b`` and starting at the first
    ``t >= b`` (a sample exactly at ``b`` belongs to both), and which boundaries have both."""
    b = _as64(boundary_times).reshape(-1)
    n = t.shape[0]
    last = np.searchsorted(t, b, side="right") - 1  # last index with t <= b
    first = np.searchsorted(t, b, side="left")  # first index with t >= b
    left = last[:, None] + np.arange(-2, 1)[None, :]
    right = first[:, None] + np.arange(0, 3)[None, :]
    ok = (left[:, 0] >= 0) & (right[:, -1] < n)
    left, right = np.clip(left, 0, n - 1), np.clip(right, 0, n - 1)
    ok &= np.all(valid[left], axis=1) & np.all(valid[right], axis=1)
    return left[ok], right[ok]


@_over_recordings(times="times", positions="rows", boundary_times="set")
def max_velocity_jump(
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    boundary_times: Float[ArrayLike, " b"],
) -> Metric:
    """Largest ``|v(b+) - v(b-)|`` (m/s) over the boundary times ``b`` (e.g. camera frames).

    ``v(b-)`` is the second-order one-sided (three-point) derivative at the last render sample
    with ``t <= b`` using it and the two samples before; ``v(b+)`` likewise at the first sample
    with ``t >= b`` and the two after. Exact for piecewise-quadratic paths with the kink at
    ``b``; for a smooth path the value is ``O(a dt)`` when ``b`` falls between samples (the
    straddling interval is skipped), plus the stencils' truncation error ``O(j dt^2)`` (``j``:
    the jerk near ``b``): a C1 stream whose acceleration changes within a few samples shows a
    "jump" that shrinks with the sample spacing (see ``docs/results.md``). Boundaries without
    three finite samples on each side are ignored; ``count`` = boundaries used.
    """
    return _max_jump(times, positions, boundary_times)


@_over_recordings(times="times", quaternions="rows", boundary_times="set")
def max_angular_velocity_jump(
    times: Float[ArrayLike, " n"],
    quaternions: Float[ArrayLike, "n 4"],
    boundary_times: Float[ArrayLike, " b"],
) -> Metric:
    """Largest jump of the world-frame angular velocity (rad/s) at the boundary times.

    As :func:`max_velocity_jump`, differentiating the rotation vectors ``log(q_j q_e*)`` of the
    three samples on each side relative to the end sample ``e`` at the boundary.
    """
    def rotvecs(q, idx, e):  # window rows are finite
        return _np_rotvec(_np_qmul(_np_qnormalize(q[idx]), _np_qconj(_np_qnormalize(q[e]))[:, None]))

    return _max_jump(times, quaternions, boundary_times, rotvecs)


# ----------------------------------------------------------------------------------------------
# latency
# ----------------------------------------------------------------------------------------------


def _lag_inputs(times, est, gt, kind):
    """Checked float64 ``(t, est, gt, kind)`` of :func:`latency` / :func:`shift_lag` (``kind``
    from the width ``d`` when ``None``)."""
    t, e, g = _as64(times), _as64(est), _as64(gt)
    if e.shape != g.shape or e.ndim != 2:
        raise ValueError(f"est and gt must have the same (n, d) shape, got {e.shape}, {g.shape}")
    _check_times(t, e.shape[0])
    if kind is None:
        kind = {3: "position", 4: "rotation"}.get(e.shape[1])
    if kind not in ("position", "rotation"):
        raise ValueError("kind must be 'position' or 'rotation' (or d must be 3 or 4)")
    return t, e, g, kind


def _parabola_vertex(c: np.ndarray, maximum: bool) -> float:
    """Offset (in grid steps) of the vertex of the parabola through ``c = (c_-1, c_0, c_1)`` from
    the middle point; 0 when the parabola does not open the right way for a ``maximum`` /
    minimum or a value is not finite."""
    den = c[0] - 2 * c[1] + c[2]
    if not np.all(np.isfinite(c)) or not (den < 0 if maximum else den > 0):
        return 0.0
    return float(0.5 * (c[0] - c[2]) / den)


#: :func:`_grid_minimum` scores every ``_COARSE``-th point of its grid, then the whole grid
#: within ``_COARSE`` points of the ``_CANDIDATES`` lowest local minima of those
_COARSE = 5
_CANDIDATES = 3


def _grid_minimum(size: int, score) -> tuple[np.ndarray, int]:
    """The lowest value of ``score`` over the grid points ``0 .. size - 1``, searched coarse to
    fine, and the values scored.

    ``score(ks)`` returns the (non-NaN) values at the grid points ``ks``. Every ``_COARSE``-th
    point is scored, then every point within ``_COARSE`` of the three lowest local minima of
    those, then downhill until the best point's neighbours are scored (a parabola through them
    refines it). This is the minimum over the whole grid whenever the values have no dip
    narrower than ``_COARSE`` points beside their lowest ones: so for the RMSE curves of
    :func:`shift_lag`, smooth at the grid's scale (the motion changes little within a few ms of
    shift), but not for :func:`latency`'s correlation of raw velocities, which can have several
    near-equal peaks. About a third of a 200-point grid is scored.

    Returns:
        ``(values, k)``: the values (NaN where not scored) and the index of the lowest.
    """
    values = np.full(size, np.nan)  # NaN: not scored

    def fill(ks) -> None:
        ks = np.unique(np.asarray(ks, dtype=int))
        ks = ks[np.isnan(values[ks])]
        if ks.size:
            values[ks] = score(ks)

    coarse = np.unique(np.r_[np.arange(0, size, _COARSE), size - 1])
    fill(coarse)
    vc = values[coarse]
    low = np.r_[True, vc[1:] <= vc[:-1]] & np.r_[vc[:-1] <= vc[1:], True]
    for c in coarse[low][np.argsort(vc[low], kind="stable")][:_CANDIDATES]:
        fill(np.arange(max(c - _COARSE, 0), min(c + _COARSE, size - 1) + 1))
    while True:
        k = int(np.nanargmin(values))
        todo = [j for j in (k - 1, k + 1) if 0 <= j < size and np.isnan(values[j])]
        if not todo:
            return values, k
        fill(todo)


@_over_recordings(times="times", est="rows", gt="rows")
def latency(
    times: Float[ArrayLike, " n"],
    est: Float[ArrayLike, "n d"],
    gt: Float[ArrayLike, "n d"],
    max_lag: float = 0.5,
    *,
    window: float | None = None,
    kind: str | None = None,
) -> Latency:
    """Lag of ``est`` behind ``gt`` by cross-correlating their velocities.

    Velocities are differences over ``s`` samples placed at interval midpoints: linear velocity
    ``(x_{i+s} - x_i) / (t_{i+s} - t_i)`` for positions (``d == 3``), world-frame angular velocity
    ``log(q_{i+s} q_i*) / (t_{i+s} - t_i)`` for quaternions (``d == 4``); ``kind="position"`` /
    ``"rotation"`` overrides the shape rule. ``s = 1`` by default; ``window`` (s) sets
    ``s = round(window / h)``, a box filter of width ``window`` on both velocities that suppresses
    noise and staircase (hold) artefacts without moving the peak of a pure delay.
    For candidate lags ``L = k h`` (``h`` = median spacing, ``|L| <= max_lag``) the estimate
    velocity is linearly interpolated at ``m + L`` and the normalised (mean-removed, summed over
    components) correlation with the ground-truth velocity at ``m`` is computed over samples
    finite in both. The best integer lag is refined by a parabola through its neighbours
    (not refined at the ends of the search range).

    Returns:
        ``Latency(lag, correlation, count)``; positive lag = estimate behind (``est(t) ~
        gt(t - lag)``). NaN with count 0 when fewer than 4 common samples exist.

    Cost ``O(n * max_lag / h)`` (one ``np.interp`` per candidate lag; every lag is scored: on
    raw velocities the correlation can have several near-equal peaks, and a coarse-to-fine
    search as in :func:`shift_lag` picked another one in 1 of 384 real streams). For a
    zero-order-hold staircase the estimate is about half the hold period minus half a render
    period (velocity samples sit at interval midpoints).
    """
    t, e, g, kind = _lag_inputs(times, est, gt, kind)
    nan = Latency(float("nan"), float("nan"), 0)
    if t.shape[0] < 4:
        return nan
    h = float(np.median(np.diff(t)))
    span = 1 if window is None else max(1, round(window / h))
    if span >= t.shape[0]:
        return nan
    m, ve = _span_velocity(t, e, span, kind)
    _, vg = _span_velocity(t, g, span, kind)
    kmax = max(1, round(max_lag / h))
    lags = np.arange(-kmax, kmax + 1) * h
    corr = np.full(lags.shape, np.nan)
    counts = np.zeros(lags.shape, dtype=int)
    g_ok = _finite_rows(vg)
    for i, lag in enumerate(lags):
        shifted = np.stack(
            [np.interp(m + lag, m, vc, left=np.nan, right=np.nan) for vc in ve.T], axis=-1
        )
        ok = g_ok & _finite_rows(shifted)
        cnt = int(ok.sum())
        if cnt < 3:
            continue
        a = shifted[ok] - shifted[ok].mean(axis=0)
        b = vg[ok] - vg[ok].mean(axis=0)
        den = np.sqrt(np.sum(a * a) * np.sum(b * b))
        if den > 0:
            corr[i] = np.sum(a * b) / den
            counts[i] = cnt
    if not np.any(np.isfinite(corr)):
        return nan
    k = int(np.nanargmax(corr))
    lag = lags[k]
    if 0 < k < len(lags) - 1:
        lag += _parabola_vertex(corr[k - 1 : k + 2], maximum=True) * h
    return Latency(float(lag), float(corr[k]), int(counts[k]))


#: candidate shifts of :func:`shift_lag` evaluated together
_LAG_CHUNK = 16


def _interpolant(t: np.ndarray, x: np.ndarray, kind: str):
    """``s -> x(s)``: ``x`` (sampled at ``t``) interpolated at the times ``s``, linear for
    positions, slerp for quaternions, between consecutive samples; NaN outside ``[t_0, t_-1]``
    or when a bracketing sample is NaN. What does not depend on ``s`` (each pair of samples'
    rotation) is computed once, here (:func:`shift_lag` asks ~200 shifts of every sample)."""
    n = t.shape[0]
    if kind != "position":
        # slerp(a, b, u) = exp(u log(b a*)) a, with log(b a*) per pair of consecutive samples
        x = _np_qnormalize(x)
        step = _np_rotvec(_np_qmul(x[1:], _np_qconj(x[:-1])))

    def at(s: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(t, s, side="right") - 1, 0, n - 2)
        u = ((s - t[i]) / (t[i + 1] - t[i]))[..., None]
        inside = (s >= t[0]) & (s <= t[-1])
        if kind == "position":
            a, b = x[i], x[i + 1]
            y = a + u * (b - a)
        else:
            y = _np_qmul(_np_from_rotvec(u * step[i]), x[i])
        return np.where(inside[..., None], y, np.nan)

    return at


def _finite_at_every_shift(t: np.ndarray, good: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Whether the interpolant of :func:`_interpolant` (samples at ``t``, finite where ``good``)
    is finite at ``t - d`` for every shift ``d`` of ``lags``: inside ``[t_0, t_-1]`` and both
    bracketing samples finite (found for every shift, as the interpolant finds them, only when
    some sample is not finite)."""
    ok = (t - lags.max() >= t[0]) & (t - lags.min() <= t[-1])
    if good.all() or not good.any():  # (an orientation-only recording's positions: none)
        return ok & good.any()
    n = t.shape[0]
    for c in range(0, lags.size, _LAG_CHUNK):
        s = t[None, :] - lags[c:c + _LAG_CHUNK, None]
        i = np.clip(np.searchsorted(t, s, side="right") - 1, 0, n - 2)
        ok &= np.all(good[i] & good[i + 1], axis=0)
    return ok


@_over_recordings(times="times", est="rows", gt="rows")
def shift_lag(
    times: Float[ArrayLike, " n"],
    est: Float[ArrayLike, "n d"],
    gt: Float[ArrayLike, "n d"],
    *,
    min_lag: float = -0.1,
    max_lag: float = 0.3,
    step: float = 0.002,
    kind: str | None = None,
) -> Lag:
    """Lag of ``est`` behind ``gt``: the shift ``d`` minimising ``RMSE(est(tau), gt(tau - d))``.

    The ground truth (given at the same times as the estimate) is interpolated at ``tau - d``
    (linear for positions, ``d == 3``; slerp for wxyz quaternions, ``d == 4``; ``kind``
    overrides) for ``d`` on a grid of ``step`` from ``min_lag`` to ``max_lag`` (s). The error
    is the Euclidean distance (m) or the geodesic angle (deg). Every candidate is scored on the
    same samples: those finite in ``est`` whose shifted ground truth is finite for every ``d``.
    The best grid value is refined by a parabola through the mean squared errors at it and its
    neighbours (near its minimum the MSE of a shifted copy is a parabola in ``d``, the RMSE a
    V whose parabola leant up to 0.2 ms towards the grid point); at an end of the grid the end
    is returned (the true lag may lie beyond it).

    The grid is searched coarse to fine (:func:`_grid_minimum`: every 5th shift, then the whole
    grid around the lowest of those, ~60 of the default grid's 201 shifts), which finds the
    whole grid's minimum unless ``RMSE(d)`` has a dip narrower than 5 steps (10 ms by default)
    beside its lowest ones.

    Unlike :func:`latency` (velocity cross-correlation) this is the lag a viewer sees: how far
    back in time the ground truth best matches the stream, including any constant offset.

    Returns:
        ``Lag(lag, rmse_at_lag, count)``; positive lag = estimate behind. NaN with count 0 when
        fewer than 3 samples can be scored; a NaN lag when every shift scores the same (the
        ground truth does not move over the scored samples: a still head has no lag).
    """
    t, e, g, kind = _lag_inputs(times, est, gt, kind)
    if not (step > 0 and min_lag < max_lag):
        raise ValueError("need step > 0 and min_lag < max_lag")
    nan = Lag(float("nan"), float("nan"), 0)
    if t.shape[0] < 4:
        return nan
    lags = np.arange(min_lag, max_lag + 0.5 * step, step)
    ok = _finite_rows(e) & _finite_at_every_shift(t, _finite_rows(g), lags)
    count = int(ok.sum())
    if count < 3:
        return nan
    with np.errstate(invalid="ignore", divide="ignore"):  # pairs with a NaN sample: unused
        gt_at = _interpolant(t, g, kind)
    t, e = t[ok], e[ok]  # the scored samples

    def rmse_at(ks):
        """The RMSE at the shifts ``lags[ks]``, a few shifts at a time (the ``(shifts, n, d)``
        temporaries of all ~200 shifts at once are ~50 MB each)."""
        out = np.empty(len(ks))
        for c in range(0, len(ks), _LAG_CHUNK):
            kc = ks[c:c + _LAG_CHUNK]
            shifted = gt_at(t[None, :] - lags[kc, None])
            if kind == "position":
                err = np.linalg.norm(shifted - e, axis=-1)
            else:
                err = np.degrees(_geodesic_angle(shifted, e[None]))
            out[c:c + _LAG_CHUNK] = np.sqrt(np.mean(err**2, axis=-1))
        return out

    rmse, k = _grid_minimum(lags.size, rmse_at)
    if np.nanmax(rmse) - rmse[k] <= 1e-9 * np.nanmax(rmse):
        return Lag(float("nan"), float(rmse[k]), count)  # the truth does not move: no lag
    lag = float(lags[k])
    if 0 < k < len(lags) - 1:
        lag += _parabola_vertex(rmse[k - 1 : k + 2] ** 2, maximum=False) * step
    return Lag(lag, float(rmse[k]), count)


# ----------------------------------------------------------------------------------------------
# everything at once
# ----------------------------------------------------------------------------------------------


#: the shifts (s) :func:`evaluate` searches for the lag (:func:`shift_lag`) by default
LAG_RANGE = (-0.1, 0.3)


@_over_recordings(times="times", est_pos="rows", est_quat="rows", gt_pos="rows",
                  gt_quat="rows", boundary_times="set")
def evaluate(
    times: Float[ArrayLike, " n"],
    est_pos: Float[ArrayLike, "n 3"],
    est_quat: Float[ArrayLike, "n 4"],
    gt_pos: Float[ArrayLike, "n 3"],
    gt_quat: Float[ArrayLike, "n 4"],
    boundary_times: Float[ArrayLike, " b"] | None = None,
    *,
    max_lag: float = 0.5,
    latency_window: float | None = 0.1,
    lag_range: tuple[float, float] = LAG_RANGE,
) -> dict[str, float]:
    """All metrics of an estimated pose stream against ground truth at the same render times.

    Returns a flat dict of floats; each metric ``name`` has a sample count ``name + "_n"``:

    * ``position_rmse`` (m), ``rotation_rmse_deg`` (deg);
    * ``jerk_position`` (m/s^3), ``jerk_rotation`` (rad/s^3) of the estimate, and
      ``jerk_position_gt``, ``jerk_rotation_gt`` of the ground truth for reference;
    * ``curvature``, ``torsion`` (1/m) of the estimated path (thresholds as in
      :func:`mean_abs_curvature`, :func:`mean_abs_torsion`);
    * ``velocity_jump`` (m/s), ``angular_velocity_jump`` (rad/s) at ``boundary_times``
      (NaN when not given);
    * ``latency_position``, ``latency_rotation`` (s) with ``..._corr`` (peak correlation), from
      :func:`latency` with ``max_lag`` and ``window=latency_window`` (0.1 s velocity box filter
      by default, which makes the estimate robust to measurement noise and hold staircases);
    * ``lag_position``, ``lag_rotation`` (s) with ``..._rmse`` (m / deg): the shift minimising
      the RMSE against the shifted ground truth (:func:`shift_lag`, shifts in ``lag_range``).

    Metrics without usable samples (e.g. position metrics of orientation-only data) are NaN
    with count 0.
    """
    out: dict[str, float] = {}

    def put(name, res):
        out[name] = res.value
        if isinstance(res, Latency):
            out[name + "_corr"] = res.correlation
        if isinstance(res, Lag):
            out[name + "_rmse"] = res.rmse
        out[name + "_n"] = res.count

    put("position_rmse", position_rmse(est_pos, gt_pos))
    put("rotation_rmse_deg", rotation_rmse_deg(est_quat, gt_quat))
    put("jerk_position", rms_jerk_position(times, est_pos))
    put("jerk_rotation", rms_jerk_rotation(times, est_quat))
    put("jerk_position_gt", rms_jerk_position(times, gt_pos))
    put("jerk_rotation_gt", rms_jerk_rotation(times, gt_quat))
    put("curvature", mean_abs_curvature(times, est_pos))
    put("torsion", mean_abs_torsion(times, est_pos))
    if boundary_times is None:
        put("velocity_jump", _NAN)
        put("angular_velocity_jump", _NAN)
    else:
        put("velocity_jump", max_velocity_jump(times, est_pos, boundary_times))
        put("angular_velocity_jump", max_angular_velocity_jump(times, est_quat, boundary_times))
    lat = {"max_lag": max_lag, "window": latency_window}
    put("latency_position", latency(times, est_pos, gt_pos, kind="position", **lat))
    put("latency_rotation", latency(times, est_quat, gt_quat, kind="rotation", **lat))
    rng = {"min_lag": lag_range[0], "max_lag": lag_range[1]}
    put("lag_position", shift_lag(times, est_pos, gt_pos, kind="position", **rng))
    put("lag_rotation", shift_lag(times, est_quat, gt_quat, kind="rotation", **rng))
    return out
