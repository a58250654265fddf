"""Pose interpolation on irregular, gappy measurement streams and finite-difference velocities.

Measurements are given as plain arrays ``times (N,)``, ``positions (N, 3)`` and ``quaternions
(N, 4)`` (``wxyz``). ``times`` must be finite and non-decreasing. A *dropped* measurement is a
row containing NaN; positions and orientations are treated as separate channels, so a row with
NaN position but a finite quaternion (orientation-only data) still contributes its orientation.

Invalid rows are skipped with a **mask approach** that keeps every shape static, so the functions
here are ``jit``/``vmap``/``grad``-compatible: for each query the bracketing valid samples are found
with ``searchsorted`` plus running ``cummax``/``cummin`` of the valid indices (no compaction).
Invalid rows are replaced by harmless finite values before any arithmetic, so gradients never see
NaN.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._jit import jit
from .._misc import any_traced, safe_div
from .._sizes import pad_samples, unpad_rows
from ..quaternion import quat_conj, quat_mul, quat_normalize, quat_slerp, quat_to_rotvec

__all__ = ["interpolate_poses", "finite_difference_velocities", "snap_to_frames", "valid_rows",
           "valid_quaternion_rows", "ground_truth_max_gap", "MIN_GT_GAP",
           "warn_sparse_ground_truth"]


def valid_rows(x: Float[ArrayLike, "n k"]) -> Bool[Array, " n"]:
    """``True`` for rows of ``x`` whose entries are all finite."""
    return jnp.all(jnp.isfinite(jnp.asarray(x)), axis=-1)


def valid_quaternion_rows(q: Float[ArrayLike, "n 4"]) -> Bool[Array, " n"]:
    """``True`` for quaternions that are finite and not zero (a zero quaternion is no
    orientation: normalising it would silently give the identity)."""
    q = jnp.asarray(q)
    ok = valid_rows(q)
    return ok & (jnp.sum(jnp.where(ok[..., None], q, 0) ** 2, axis=-1) > 0)


#: shortest ground-truth gap (s) that is never bridged by interpolation, whatever the rate
MIN_GT_GAP = 0.1


def ground_truth_max_gap(times: ArrayLike, max_gap: float | None = None) -> float:
    """The longest ground-truth gap (s) an evaluation interpolates over: ``max_gap`` if given,
    else :data:`MIN_GT_GAP` or 2.5 median sample steps, whichever is longer (a trace sampled
    at 10 Hz, e.g. AVTrack360, has steps of 0.101 s: with a fixed 0.1 s three quarters of its
    render samples went unscored).

    Arguments:
        times: ground-truth times (s), non-decreasing.
        max_gap: an explicit choice (returned as is).
    """
    if max_gap is not None:
        return float(max_gap)
    return max(MIN_GT_GAP, 2.5 * _median_step(times))


def _median_step(times) -> float:
    """The median positive step (s) between sample times (0 without one)."""
    steps = np.diff(np.asarray(times, np.float64))
    steps = steps[np.isfinite(steps) & (steps > 0)]
    return float(np.median(steps)) if steps.size else 0.0


def warn_sparse_ground_truth(gt_t, render, gp, gq) -> None:
    """One-line warnings (:class:`phjax.io.TrajectoryWarning`) for ground truth too sparse to
    score every render sample, or sampled so coarsely that its interpolation error is part of
    every RMSE (evaluation and tuning data).

    Arguments:
        gt_t: ground-truth times (s); render: render times; gp, gq: the ground truth
            interpolated there (NaN where not known).
    """
    import warnings

    from ..io import TrajectoryWarning

    step = _median_step(gt_t)
    if step > 0.05:
        warnings.warn(f"ground truth sampled at {1 / step:.3g} Hz: between its samples it is "
                      "interpolated (linear / slerp), and that error is part of every RMSE",
                      TrajectoryWarning, stacklevel=4)
    scored = np.mean(np.isfinite(gp).all(-1) | np.isfinite(gq).all(-1)) if render.size else 1.0
    if scored < 0.5:
        warnings.warn(f"only {100 * scored:.0f} % of the render samples have ground truth "
                      "(its gaps are longer than max_gt_gap): the metrics describe that part",
                      TrajectoryWarning, stacklevel=4)


def snap_to_frames(
    frame_times: Float[ArrayLike, " n"], query_times: Float[ArrayLike, " m"], atol: float = 1e-9
) -> np.ndarray:
    """``query_times`` with those that equal a frame time up to rounding set to that frame time.

    Every stream of phjax and every baseline shows a frame from its own timestamp on
    (``searchsorted(..., side="right")``: zero latency). A render clock built separately
    (``start + k / rate``) meets the frame clock (``t0 + j / camera_rate``) only up to rounding,
    so without this a render sample at a frame's instant sees that frame or the previous one by
    the last bit of the two sums, and the extrapolating baselines' RMSE moves by up to 7 % on
    aligned 30 / 120 Hz clocks. Use it on evaluation and tuning grids. NumPy on the host, in
    float64 (render grids are built there; float32 would round Unix timestamps by minutes).

    Arguments:
        frame_times: (n,) frame timestamps, finite and non-decreasing (float32 frame times,
            e.g. simulated without ``jax_enable_x64``, get float32's rounding tolerance).
        query_times: (m,) render times.
        atol: tolerance, s, added to 8 units of rounding (in ``frame_times``' dtype) of the
            frame time; the sum is capped at a tenth of the smallest frame interval.

    Returns:
        (m,) float64 render times, snapped.
    """
    t = np.asarray(frame_times)
    eps = np.finfo(t.dtype if np.issubdtype(t.dtype, np.floating) else np.float64).eps
    t = t.astype(np.float64)
    q = np.asarray(query_times, np.float64)
    if t.size == 0:
        return q
    j = np.searchsorted(t, q)
    before = t[np.maximum(j - 1, 0)]
    after = t[np.minimum(j, t.shape[0] - 1)]
    nearest = np.where(after - q < q - before, after, before)
    tol = atol + 8 * eps * np.abs(nearest)
    # never more than a tenth of the frame spacing (float32 rounding at hours of relative time)
    gaps = np.diff(t)
    gaps = gaps[gaps > 0]
    if gaps.size:
        tol = np.minimum(tol, 0.1 * gaps.min())
    return np.where(np.abs(nearest - q) <= tol, nearest, q)


def _bracket(
    valid: Bool[Array, " n"], k: Int[Array, " m"]
) -> tuple[Int[Array, " m"], Int[Array, " m"]]:
    """Indices of the last valid sample ``<= k`` and the first valid sample ``> k``.

    ``k`` is the index of the last sample with ``t <= query`` (``-1`` when none). Missing
    neighbours are reported as ``-1`` (no previous) and ``n`` (no next).
    """
    n = valid.shape[0]
    idx = jnp.arange(n)
    last = lax.cummax(jnp.where(valid, idx, -1), axis=0)
    first = lax.cummin(jnp.where(valid, idx, n), axis=0, reverse=True)
    prev = jnp.where(k >= 0, last[jnp.clip(k, 0, n - 1)], -1)
    nxt = jnp.where(k + 1 < n, first[jnp.clip(k + 1, 0, n - 1)], n)
    return prev, nxt


def _interp_weights(times, valid, k, query, max_gap):
    """Left/right sample indices, slerp/lerp fraction and an output-valid flag per query."""
    n = times.shape[0]
    prev, nxt = _bracket(valid, k)
    has_prev, has_next = prev >= 0, nxt < n
    # clamp: with only one neighbour use it on both sides (fraction becomes irrelevant)
    i0 = jnp.clip(jnp.where(has_prev, prev, nxt), 0, n - 1)
    i1 = jnp.clip(jnp.where(has_next, nxt, prev), 0, n - 1)
    t0, t1 = times[i0], times[i1]
    s = jnp.clip(safe_div(query - t0, t1 - t0), 0, 1)
    ok = has_prev | has_next
    if max_gap is not None:
        inside = has_prev & has_next & (query > t0) & (query < t1)
        # invalid rows from the first sample time or up to the last one: a gap at that end,
        # as long as those rows span (without one neighbour, t0 == t1 is the valid sample)
        head = ~has_prev & (query >= times[0]) & (query < t1) & (t1 - times[0] > max_gap)
        tail = ~has_next & (query > t0) & (query <= times[-1]) & (times[-1] - t0 > max_gap)
        ok = ok & ~(inside & (t1 - t0 > max_gap)) & ~head & ~tail
    return i0, i1, s, ok


def interpolate_poses(
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    quaternions: Float[ArrayLike, "n 4"],
    query_times: Float[ArrayLike, " m"],
    *,
    max_gap: float | Float[ArrayLike, ""] | None = None,
) -> tuple[Float[Array, "m 3"], Float[Array, "m 4"]]:
    """Linear position and slerp orientation interpolation at ``query_times``.

    Jitted. Called with concrete arrays (not inside ``jit``, ``vmap`` or ``grad``), the samples
    and the queries are padded to their size classes (:mod:`phjax._sizes`: the next power of
    two) so that inputs of other lengths reuse the compiled program; padding never changes a
    result (padded samples are invalid rows at the last time, padded queries are dropped).

    Arguments:
        times: measurement times, finite and non-decreasing.
        positions: positions; rows containing NaN are skipped (position channel only).
        quaternions: ``wxyz`` orientations (normalised here); NaN rows are skipped (orientation
            channel only). Slerp takes the shortest arc, so ``q``/``-q`` flips are harmless.
        query_times: where to interpolate (any order).
        max_gap: optional maximum spacing (s) between the two valid samples bracketing a query;
            a query strictly inside a longer gap gives NaN. Invalid rows at the start or the
            end of ``times`` are a gap too, as long as they span: a query among them gives NaN
            when that is longer (ground truth whose tracking was lost before its last row is
            not held there). Queries exactly at a valid sample and queries outside
            ``[times[0], times[-1]]`` are unaffected.

    Returns:
        ``(positions (m, 3), quaternions (m, 4))``. Queries before the first / after the last
        valid sample are clamped to that end pose (no extrapolation; with ``max_gap``, see
        there). A channel with no valid sample at all gives NaN.
    """
    shapes = [np.shape(x) for x in (times, positions, quaternions, query_times)]
    n = shapes[0][0] if len(shapes[0]) == 1 else -1
    if n < 1 or shapes[1] != (n, 3) or shapes[2] != (n, 4) or len(shapes[3]) != 1:
        raise ValueError(
            "expected times (n,), positions (n, 3), quaternions (n, 4) with n >= 1 and 1-D "
            f"query_times; got {shapes[0]}, {shapes[1]}, {shapes[2]}, {shapes[3]}"
        )
    if not any_traced(times) and np.any(np.diff(np.asarray(times)) < 0):
        raise ValueError("times must be non-decreasing (sort the samples first)")
    padded = pad_samples(times, positions, quaternions, query_times, max_gap)
    if padded is None:  # traced (or not floating point): the caller's shapes
        return _interpolate_poses(times, positions, quaternions, query_times, max_gap)
    m = shapes[3][0]
    p, q = _interpolate_poses(*padded, max_gap)  # (times relative to the first: pad_samples)
    return unpad_rows(p, m), unpad_rows(q, m)


@jit
def _interpolate_poses(times, positions, quaternions, query_times, max_gap):
    """:func:`interpolate_poses` on arrays of any (checked) shape, jitted."""
    times = jnp.asarray(times)
    positions = jnp.asarray(positions)
    quaternions = jnp.asarray(quaternions)
    query = jnp.asarray(query_times)
    k = jnp.searchsorted(times, query, side="right") - 1

    vp = valid_rows(positions)
    p = jnp.where(vp[:, None], positions, 0)
    i0, i1, s, ok = _interp_weights(times, vp, k, query, max_gap)
    s = s.astype(p.dtype)[:, None]
    p_out = p[i0] + s * (p[i1] - p[i0])
    p_out = jnp.where(ok[:, None], p_out, jnp.asarray(jnp.nan, p_out.dtype))

    vq = valid_quaternion_rows(quaternions)
    ident = jnp.asarray([1, 0, 0, 0], quaternions.dtype)
    q = quat_normalize(jnp.where(vq[:, None], quaternions, ident))
    i0, i1, s, ok = _interp_weights(times, vq, k, query, max_gap)
    q_out = quat_slerp(q[i0], q[i1], s.astype(q.dtype))
    q_out = jnp.where(ok[:, None], q_out, jnp.asarray(jnp.nan, q_out.dtype))
    return p_out, q_out


def _diff_weights(t: Float[Array, " n"]):
    """Second-order three-point first-derivative weights on a non-uniform grid (``n >= 3``).

    Returns ``(wm, w0, wp)`` for interior points (nodes ``i-1, i, i+1``) and the one-sided weights
    ``(a0, a1, a2)`` at the start (nodes ``0, 1, 2``) and ``(b0, b1, b2)`` at the end (nodes
    ``n-3, n-2, n-1``). All are exact for quadratics.
    """
    h = jnp.diff(t)
    h1, h2 = h[:-1], h[1:]
    hs = h1 + h2
    interior = (
        safe_div(-h2, h1 * hs),
        safe_div(h2 - h1, h1 * h2),
        safe_div(h1, h2 * hs),
    )
    g1, g2 = h[0], h[1]
    start = (
        safe_div(-(2 * g1 + g2), g1 * (g1 + g2)),
        safe_div(g1 + g2, g1 * g2),
        safe_div(-g1, g2 * (g1 + g2)),
    )
    e1, e2 = h[-2], h[-1]
    end = (
        safe_div(e2, e1 * (e1 + e2)),
        safe_div(-(e1 + e2), e1 * e2),
        safe_div(e1 + 2 * e2, e2 * (e1 + e2)),
    )
    return interior, start, end


@jit
def finite_difference_velocities(
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    quaternions: Float[ArrayLike, "n 4"],
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Linear and world-frame angular velocity by finite differences.

    Interior samples use the second-order three-point central formula for non-uniform spacing
    (exact for quadratics); the two end samples use second-order one-sided three-point formulas
    (first-order two-point differences when ``n == 2``). Angular velocity differentiates the
    rotation vectors ``phi_j = log(q_j q_i*)`` of the neighbours relative to sample ``i``
    (``d phi / dt = omega_world`` at ``t_i`` and ``d^2 phi / dt^2 = d omega / dt`` there, so the
    formula keeps its second order); the shortest-arc log makes it insensitive to ``q``/``-q``
    flips. The angular velocity ``omega`` satisfies ``dq/dt = 0.5 (0, omega) q``.

    Arguments:
        times: strictly increasing sample times (duplicate times give 0 weights, not inf).
        positions: positions ``(n, 3)``.
        quaternions: ``wxyz`` orientations ``(n, 4)`` (normalised here).

    Returns:
        ``(velocity (n, 3), angular_velocity (n, 3))`` in units/s and rad/s. Inputs must be free
        of NaN: a NaN row propagates to its neighbours' derivatives.
    """
    t = jnp.asarray(times)
    p = jnp.asarray(positions)
    q = quat_normalize(jnp.asarray(quaternions))
    n = t.shape[0]
    if n < 2 or p.shape != (n, 3) or q.shape != (n, 4):
        raise ValueError(
            "expected times (n,), positions (n, 3), quaternions (n, 4) with n >= 2; got "
            f"{t.shape}, {p.shape}, {q.shape}"
        )
    # consecutive world-frame relative rotation vectors: q_{i+1} = exp(d1_i / 2) q_i
    d1 = quat_to_rotvec(quat_mul(q[1:], quat_conj(q[:-1])))
    if n == 2:
        dt = (t[1] - t[0]).astype(p.dtype)
        v = safe_div(p[1] - p[0], dt)
        w = safe_div(d1[0], dt)
        return jnp.stack([v, v]), jnp.stack([w, w])
    (wm, w0, wp), (a0, a1, a2), (b0, b1, b2) = _diff_weights(t.astype(p.dtype))
    col = lambda x: x[:, None]  # noqa: E731
    v_int = col(wm) * p[:-2] + col(w0) * p[1:-1] + col(wp) * p[2:]
    v_start = a0 * p[0] + a1 * p[1] + a2 * p[2]
    v_end = b0 * p[-3] + b1 * p[-2] + b2 * p[-1]
    v = jnp.concatenate([v_start[None], v_int, v_end[None]])

    # rotation vectors of neighbours relative to the evaluation sample (phi_i = 0)
    d2_start = quat_to_rotvec(quat_mul(q[2], quat_conj(q[0])))
    d2_end = quat_to_rotvec(quat_mul(q[-3], quat_conj(q[-1])))
    w_int = -col(wm) * d1[:-1] + col(wp) * d1[1:]
    w_start = a1 * d1[0] + a2 * d2_start
    w_end = b0 * d2_end - b1 * d1[-1]
    w = jnp.concatenate([w_start[None], w_int.astype(v.dtype), w_end[None]])
    return v, w
