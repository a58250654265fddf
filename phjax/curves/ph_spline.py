"""C2 PH quintic splines through many points (offline), solved with optimistix.

A chain of first-order Hermite PH quintics (:func:`phjax.hermite_quintic`) is C1 at its joints.
A **C2** PH quintic spline through points ``p_0 .. p_N`` shares quaternion unknowns
``Z_0 .. Z_{N+1}`` between neighbouring segments: segment ``k = 1 .. N`` (from ``p_{k-1}`` to
``p_k``) uses the quadratic quaternion polynomial with Bernstein coefficients

    A0 = (Z_{k-1} + Z_k) / 2,    A1 = Z_k,    A2 = (Z_k + Z_{k+1}) / 2,

so ``A_k(1) = A_{k+1}(0)`` and ``A_k'(1) = A_{k+1}'(0)``: the hodograph ``r' = A i A*`` and its
derivative agree at every joint (C1 and C2 in the segment parameter, i.e. in time for equal
frame intervals). The unknowns must satisfy the interpolation equations
``int_0^1 A_k i A_k* dt = p_k - p_{k-1}`` (3 per segment) and optionally clamped end derivatives
``A_1(0) i A_1(0)* = d_start``, ``A_N(1) i A_N(1)* = d_end``. That leaves ``N + 2`` free
dimensions (4 fewer equations than unknowns per segment, minus the clamps), one of them the
trivial common phase ``Z_k -> Z_k exp(theta i)``. A clamp **at rest** (``|d|`` within the
feasibility tolerance of 0: a head at rest at that end) is solved as the equivalent ``A_1(0) = 0``
(``|A i A*| = |A|^2``; 4 linear equations, one free dimension fewer): the quadratic form has a
zero Jacobian there, on which Levenberg-Marquardt stalled (residual about ``1e-6``, ``FAILED``)
and no multipliers certify stationarity. Following ``../shared/docs/ph_math.md`` §6 they
are fixed by minimising the fairness measure ``sum_k |Z_{k-1} - 2 Z_k + Z_{k+1}|^2`` subject to
the equations; the common phase is fixed by one linear gauge condition (orthogonality of the
correction to the phase direction at the start).

Solver, inside one ``jit``, all optimistix with ``throw=False`` (a :class:`SplineStatus`
instead of exceptions): (1) a feasible point near the start by ``optimistix.least_squares`` with
:class:`optimistix.LevenbergMarquardt` on the equations (the damping makes the underdetermined
steps well posed); (2) the fairness under the equations by an augmented Lagrangian: each
subproblem ``|second differences of Z|^2 + mu |c(Z) + lam / mu|^2`` is a nonlinear
least-squares problem for Levenberg-Marquardt (warm-started, ``mu = 1e3`` on the scaled problem,
8 multiplier updates ``lam <- lam + mu c``); (3) a Levenberg-Marquardt projection back onto the
equations (to rounding). The result is judged by its residual and by first-order optimality
(KKT stationarity with least-squares multipliers). A plain Newton iteration on the KKT system
was tried first: it converges quadratically on smooth data (helix) but wanders on real and random
data (no globalisation), while the augmented Lagrangian reaches the same optimum on the helix and
converges on both. The start is the C1 Hermite PH chain with Catmull-Rom derivatives (``Z_k`` =
its middle coefficients, each segment's common phase aligned with its predecessor at the joint).
Data are scaled to unit mean chord first. The equations are written as quadratic forms
(``a i b*`` is a bilinear form with a constant ``3 x 4 x 4`` matrix, the displacement of a
segment one contraction over its stacked coefficients): the solver differentiates them in every
step, and the component-wise products traced about 3.5 x longer and compiled about 3 x longer
(``docs/results.md``). Jacobians are dense
(``O(N^2)`` memory, ``O(N^3)`` per step): intended for windows of up to a few hundred points
(chain clamped windows for long recordings, as ``experiments/c2_spline.py`` does).
"""

from __future__ import annotations

import enum
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from .._jit import filter_jit
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._misc import safe_norm
from .._np_quat import np_qconj, np_qmul
from .ph_quintic import PHQuintic, _from_coefficients, hermite_quintic

__all__ = ["SplineStatus", "SplineSolution", "ph_spline"]


class SplineStatus(enum.IntEnum):
    """Status codes of :class:`SplineSolution` (plain ``int`` values).

    * ``SUCCESS`` (0): the equations hold (``residual`` <= 1e-6 in float64, 1e-3 in float32)
      and the fairness measure is stationary under them (``stationarity`` below the same
      tolerance).
    * ``MAX_STEPS`` (1): the feasibility phase reached its step limit without meeting the
      equations; the last iterate is returned (it does not interpolate to tolerance).
    * ``FAILED`` (2): non-finite input, or the equations could not be met; the returned curves
      may contain NaN.
    * ``NOT_FAIREST`` (3): a valid C2 interpolant (equations hold to tolerance), but the fairness
      optimisation did not reach stationarity: the fairest feasible point found is returned.
    """

    SUCCESS = 0
    MAX_STEPS = 1
    FAILED = 2
    NOT_FAIREST = 3


class SplineSolution(eqx.Module):
    """Record of :func:`ph_spline`.

    Attributes:
        status: :class:`SplineStatus` code, int32 scalar.
        residual: largest violation of the interpolation / clamping equations, in units of the
            mean chord length (``|c| / mean |p_k - p_{k-1}|``).
        fairness: ``sum_k |Z_{k-1} - 2 Z_k + Z_{k+1}|^2`` of the scaled problem.
        stationarity: first-order optimality of the fairness under the equations,
            ``max |grad S + J^T lam| / (1 + max |grad S|)`` with least-squares multipliers.
        num_steps: Levenberg-Marquardt steps of the feasibility phase.
        ok: the curves interpolate to tolerance and are C2 (``SUCCESS`` or ``NOT_FAIREST``).
        Z: the quaternion unknowns ``Z_0 .. Z_{N+1}`` in world units, ``(N + 2, 4)``.
    """

    status: Int[Array, ""]
    residual: Float[Array, ""]
    fairness: Float[Array, ""]
    stationarity: Float[Array, ""]
    num_steps: Int[Array, ""]
    ok: Bool[Array, ""]
    Z: Float[Array, "n 4"]


def _coefficients(Z):
    return (Z[:-2] + Z[1:-1]) / 2, Z[1:-1], (Z[1:-1] + Z[2:]) / 2


@functools.cache
def _sandwich_matrix() -> np.ndarray:
    """``M[j, p, q]``: component ``j`` of the vector part of ``e_p i e_q*`` (``wxyz`` basis
    quaternions ``e``): ``a i b* = einsum("p,jpq,q->j", a, M, b)``, a bilinear form."""
    e = np.eye(4)
    prod = np_qmul(np_qmul(e[:, None], np.array([0.0, 1.0, 0.0, 0.0])), np_qconj(e[None, :]))
    return np.moveaxis(prod[..., 1:], -1, 0)  # (3, 4, 4), entries 0 and +-1


#: weights of ``a i b*`` for the Bernstein coefficient pairs ``(A_m, A_n)`` in
#: ``int_0^1 A i A* dt``: the hodograph's Bernstein coefficients
#: ``A0 i A0*, (A0 i A1* + A1 i A0*) / 2, (A0 i A2* + 4 A1 i A1* + A2 i A0*) / 6, ...``
#: summed and divided by 5
_DISPLACEMENT_WEIGHTS = np.array([[1.0, 1 / 2, 1 / 6], [1 / 2, 2 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]]) / 5


def _sandwich(a, b):
    """Vector part of ``a i b*`` as one contraction (a few traced operations where the
    component form takes dozens: the solver differentiates it many times)."""
    return jnp.einsum("...p,jpq,...q->...j", a, jnp.asarray(_sandwich_matrix(), a.dtype), b)


def _displacement(A0, A1, A2):
    """``int_0^1 A i A* dt`` = sum of the hodograph's Bernstein coefficients / 5, as one
    quadratic form in the stacked coefficients (as :func:`_sandwich`)."""
    A = jnp.stack([A0, A1, A2], -2)  # (..., 3, 4)
    W = jnp.asarray(_DISPLACEMENT_WEIGHTS, A.dtype)
    return jnp.einsum("...mp,mn,jpq,...nq->...j", A, W,
                      jnp.asarray(_sandwich_matrix(), A.dtype), A)


def _fairness(Z):
    return jnp.sum((Z[:-2] - 2 * Z[1:-1] + Z[2:]) ** 2)


def _times_i(a):
    """The Hamilton product ``a i`` (wxyz): the direction of the common phase at ``a``."""
    return jnp.stack([-a[..., 1], a[..., 0], a[..., 3], -a[..., 2]], -1)


def _phase_to(target, a):
    """The phase ``theta`` with ``a exp(theta i)`` closest to ``target`` (as cos, sin)."""
    s, c = jnp.sum(target * _times_i(a), -1), jnp.sum(target * a, -1)
    n = jnp.hypot(s, c)
    ok = n > 0
    return jnp.where(ok, c / jnp.where(ok, n, 1), 1.0), jnp.where(ok, s / jnp.where(ok, n, 1), 0.0)


def _rotate_phase(a, cs, sn):
    return cs[..., None] * a + sn[..., None] * _times_i(a)


def _initial(p, d_start, d_end, clamp_start, clamp_end):
    """Start: the C1 Hermite PH chain with Catmull-Rom derivatives (the given clamps at the
    ends), each segment's common phase turned so that its ``A0`` continues the previous ``A2``
    (the same fibre: C1 joint), ``Z_k = A1`` of segment ``k`` and the outer ``Z`` from the end
    coefficients."""
    d = jnp.concatenate([p[1:2] - p[:1], (p[2:] - p[:-2]) / 2, p[-1:] - p[-2:-1]], 0)
    if clamp_start:
        d = d.at[0].set(d_start)
    if clamp_end:
        d = d.at[-1].set(d_end)
    c = hermite_quintic(p[:-1], p[1:], d[:-1], d[1:])

    def body(prev_a2, seg):
        a0, a1, a2 = seg
        cs, sn = _phase_to(prev_a2, a0)
        a0, a1, a2 = (_rotate_phase(x, cs, sn) for x in (a0, a1, a2))
        return a2, (a0, a1, a2)

    _, (A0, A1, A2) = lax.scan(body, c.A0[0], (c.A0, c.A1, c.A2))
    return jnp.concatenate([(2 * A0[:1] - A1[:1]), A1, (2 * A2[-1:] - A1[-1:])], 0)


_ALM_ITERS = 8


def _tolerance(dtype) -> float:
    """Feasibility and stationarity tolerance of the scaled problem (unit mean chord)."""
    return 1e-6 if dtype == jnp.float64 else 1e-3


def _at_rest(d):
    """Whether the clamped end derivative ``d`` (scaled problem) counts as zero: ``|d|`` within
    the feasibility tolerance, so that the resting end ``A(0) = 0`` meets ``A(0) i A(0)* = d``
    to tolerance (see :func:`_clamp_rows`)."""
    return safe_norm(d) <= _tolerance(d.dtype)


def _start(dp, ds, de, clamp_start, clamp_end):
    """:func:`_initial` of the scaled problem (a clamp at rest as exact zero)."""
    p = jnp.concatenate([jnp.zeros((1, 3), dp.dtype), jnp.cumsum(dp, 0)], 0)
    zero = lambda d: jnp.where(_at_rest(d), 0, d)
    return _initial(p, zero(ds), zero(de), clamp_start, clamp_end)


def _clamp_rows(a, d, rest):
    """The clamp ``a i a* = d`` of an end coefficient ``a`` as 4 rows, regular at the solution.

    ``|a i a*| = |a|^2``, so at rest (``rest``: ``d`` counts as 0) the clamp is ``a = 0``: 4
    linear rows. Its 3 quadratic rows have a Jacobian ``2 (a i x* + x i a*)`` that vanishes
    there: Levenberg-Marquardt then converges sublinearly (its damping dominates the vanishing
    curvature; the residual stalled near ``1e-6``, FAILED) and the multipliers that certify
    stationarity do not exist (NOT_FAIREST). Otherwise the 3 quadratic rows and a zero row
    (:func:`_padding` marks it)."""
    quad = _sandwich(a, a) - d
    return jnp.where(rest, a, jnp.concatenate([quad, jnp.zeros_like(quad[:1])]))


def _clamps(Z, ds, de, clamp_start, clamp_end):
    """``(end coefficient, clamped derivative)`` of each clamped end, start first."""
    A0, _, A2 = _coefficients(Z)
    return [(a, d) for on, a, d in ((clamp_start, A0[0], ds), (clamp_end, A2[-1], de)) if on]


def _interpolation(Z, dp):
    """The interpolation equations ``int_0^1 A_k i A_k* dt - (p_k - p_{k-1})``, flat."""
    return (_displacement(*_coefficients(Z)) - dp).reshape(-1)


def _residuals(Z, dp, ds, de, clamp_start, clamp_end):
    """The interpolation and clamp equations as stated (``A i A* = d`` at a clamped end),
    whose largest violation is the reported ``residual``."""
    clamps = [_sandwich(a, a) - d for a, d in _clamps(Z, ds, de, clamp_start, clamp_end)]
    return jnp.concatenate([_interpolation(Z, dp), *clamps])


def _constraints(Z, dp, ds, de, Z0, clamp_start, clamp_end):
    """The equations the solver meets: interpolation, each clamp as :func:`_clamp_rows`, then
    the gauge row (no motion along the common phase of the start ``Z0``)."""
    clamps = [_clamp_rows(a, d, _at_rest(d))
              for a, d in _clamps(Z, ds, de, clamp_start, clamp_end)]
    gauge = jnp.sum((Z - Z0) * _times_i(Z0))[None]
    return jnp.concatenate([_interpolation(Z, dp), *clamps, gauge])


def _padding(n, ds, de, clamp_start, clamp_end):
    """Mask of the rows of :func:`_constraints` that are identically zero (the fourth row of a
    clamp not at rest)."""
    rows = [jnp.zeros(3 * n, bool)]
    rows += [jnp.zeros(4, bool).at[3].set(~_at_rest(d))
             for on, d in ((clamp_start, ds), (clamp_end, de)) if on]
    return jnp.concatenate(rows + [jnp.zeros(1, bool)])


def _multipliers(Z, cons):
    zf = Z.reshape(-1)
    J = jax.jacfwd(lambda v: cons(v.reshape(Z.shape)))(zf)
    g = jax.grad(lambda v: _fairness(v.reshape(Z.shape)))(zf)
    lam = jnp.linalg.lstsq(J.T, -g)[0]
    stationarity = jnp.max(jnp.abs(g + J.T @ lam)) / (1 + jnp.max(jnp.abs(g)))
    return lam, jnp.where(jnp.isfinite(stationarity), stationarity, jnp.inf)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _core(dp, ds, de, settings):
    """Unknowns ``Z`` (scaled problem) and the solver record; see the module docstring."""
    import optimistix as optx  # on first use: import phjax stays light

    clamp_start, clamp_end, max_steps, rtol, atol = settings
    dtype = dp.dtype
    n = dp.shape[0]
    Z0 = lax.stop_gradient(_start(dp, ds, de, clamp_start, clamp_end))

    def constraints(Z):
        return _constraints(Z, dp, ds, de, Z0, clamp_start, clamp_end)

    tol = _tolerance(dtype)

    def max_resid(Z):
        r = jnp.max(jnp.abs(_residuals(Z, dp, ds, de, clamp_start, clamp_end)))
        return jnp.where(jnp.isfinite(r), r, jnp.inf)

    lm = optx.LevenbergMarquardt(rtol=rtol, atol=atol * 1e-2)

    # phase 1: a feasible point (interpolation + clamps) near the start
    def resid_ls(z, _):
        return constraints(z.reshape(n + 2, 4))[:-1]

    ls = optx.least_squares(resid_ls, lm, Z0.reshape(-1), max_steps=4 * max_steps, throw=False)
    Z1 = ls.value.reshape(n + 2, 4)
    Z1 = jnp.where(jnp.all(jnp.isfinite(Z1)), Z1, Z0)

    # phase 2: augmented Lagrangian, each subproblem nonlinear least squares
    mu = 1e3

    def alm_resid(z, lam):
        Z = z.reshape(n + 2, 4)
        return jnp.concatenate([(Z[:-2] - 2 * Z[1:-1] + Z[2:]).reshape(-1),
                                jnp.sqrt(mu) * (constraints(Z) + lam / mu)])

    def alm_step(_, carry):
        z, lam = carry
        # early subproblems may stop at their step limit: the warm starts finish the job
        r = optx.least_squares(alm_resid, lm, z, args=lam, max_steps=2 * max_steps, throw=False)
        return r.value, lam + mu * constraints(r.value.reshape(n + 2, 4))

    m = constraints(Z1).shape[0]
    z, _ = lax.fori_loop(0, _ALM_ITERS, alm_step, (Z1.reshape(-1), jnp.zeros(m, dtype)))
    # phase 3: projection back onto the equations (the penalised optimum is O(1/mu) off)
    pr = optx.least_squares(resid_ls, lm, z, max_steps=2 * max_steps, throw=False)
    Z2 = pr.value.reshape(n + 2, 4)
    r1, r2 = max_resid(Z1), max_resid(Z2)
    use2 = ((r2 <= jnp.maximum(tol, r1)) & jnp.all(jnp.isfinite(Z2))
            & (_fairness(Z2) <= _fairness(Z1) * (1 + 1e-9)))
    Z = jnp.where(use2, Z2, Z1)
    residual = jnp.where(use2, r2, r1)
    feasible = residual <= tol
    _, stationarity = _multipliers(Z, constraints)
    # (judged on the point returned, whichever phase gave it: straight-line data are fairest
    # at the feasible start already, fairness 0, and were NOT_FAIREST)
    status = jnp.where(feasible & (stationarity <= tol), int(SplineStatus.SUCCESS),
                       jnp.where(feasible, int(SplineStatus.NOT_FAIREST),
                                 jnp.where(ls.result == optx.RESULTS.max_steps_reached,
                                           int(SplineStatus.MAX_STEPS),
                                           int(SplineStatus.FAILED))))
    finite = (jnp.all(jnp.isfinite(dp)) & jnp.all(jnp.isfinite(ds)) & jnp.all(jnp.isfinite(de))
              & jnp.all(jnp.isfinite(Z)))
    status = jnp.where(finite, status, int(SplineStatus.FAILED)).astype(jnp.int32)
    steps = jnp.asarray(ls.stats["num_steps"], jnp.int32)
    return Z, (status, residual, _fairness(Z), stationarity, steps)


@_core.defjvp
def _core_jvp(settings, primals, tangents):
    """Implicit-function derivative of the constrained optimum: differentiate the KKT system
    ``grad S + J^T lam = 0, c = 0`` (the gauge row fixed) at the returned point."""
    dp, ds, de = primals
    tdp, tds, tde = tangents
    clamp_start, clamp_end = settings[0], settings[1]
    Z, aux = _core(dp, ds, de, settings)
    shape = Z.shape
    Z0 = _start(dp, ds, de, clamp_start, clamp_end)

    def cons(zf, data):
        return _constraints(zf.reshape(shape), *data, Z0, clamp_start, clamp_end)

    data = (dp, ds, de)
    lam, _ = _multipliers(Z, lambda Zm: cons(Zm.reshape(-1), data))
    zf = Z.reshape(-1)

    def grad_lag(zv, data):
        return jax.grad(lambda v: _fairness(v.reshape(shape)) + jnp.dot(lam, cons(v, data)))(zv)

    H = jax.jacfwd(grad_lag)(zf, data)
    J = jax.jacfwd(cons)(zf, data)
    # an identically zero row (_padding) gets the equation lam_row = 0 (else K is singular)
    pad = jnp.diag(_padding(dp.shape[0], ds, de, clamp_start, clamp_end).astype(H.dtype))
    K = jnp.block([[H, J.T], [J, -pad]])
    tdata = (tdp, tds, tde)
    _, rhs_g = jax.jvp(lambda d: grad_lag(zf, d), (data,), (tdata,))
    _, rhs_c = jax.jvp(lambda d: cons(zf, d), (data,), (tdata,))
    # a singular KKT matrix (no unique optimum) gives zero derivatives rather than NaN; the
    # test uses primal values only, so the rule stays linear (and transposable) in the tangents
    sign, logdet = jnp.linalg.slogdet(K)
    kok = (sign != 0) & jnp.isfinite(logdet) & jnp.all(jnp.isfinite(K))
    K = jnp.where(kok, K, jnp.eye(K.shape[0], dtype=K.dtype))
    sol = jnp.linalg.solve(K, -jnp.concatenate([rhs_g, rhs_c]))
    dZ = jnp.where(kok, sol[:zf.shape[0]].reshape(shape), 0.0)
    aux_t = jax.tree.map(lambda x: jnp.zeros_like(x) if jnp.issubdtype(x.dtype, jnp.floating)
                         else np.zeros(x.shape, jax.dtypes.float0), aux)
    return (Z, aux), (dZ, aux_t)


@filter_jit
def _solve(points, d_start, d_end, clamp_start: bool, clamp_end: bool, max_steps: int,
           rtol, atol):
    dp_world = jnp.diff(points, axis=0)
    scale = jnp.mean(safe_norm(dp_world))
    scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
    settings = (clamp_start, clamp_end, max_steps, rtol, atol)
    Z, (status, residual, fairness, stationarity, steps) = _core(
        dp_world / scale, d_start / scale, d_end / scale, settings)
    ok = (status == SplineStatus.SUCCESS) | (status == SplineStatus.NOT_FAIREST)
    Zw = Z * jnp.sqrt(scale)
    A0, A1, A2 = _coefficients(Zw)
    curves = _from_coefficients(points[:-1], A0, A1, A2)
    return curves, SplineSolution(status, residual, fairness, stationarity, steps, ok, Zw)


def ph_spline(
    points: Float[ArrayLike, "n 3"],
    d_start: Float[ArrayLike, "3"] | None = None,
    d_end: Float[ArrayLike, "3"] | None = None,
    *,
    max_steps: int = 32,
    rtol: float | None = None,
    atol: float | None = None,
) -> tuple[PHQuintic, SplineSolution]:
    """C2 PH quintic spline interpolating ``points`` (offline; one segment per consecutive pair).

    Arguments:
        points: ``(N + 1, 3)`` points, ``N >= 2``, finite.
        d_start, d_end: optional clamped end derivatives with respect to the segment parameter
            (velocity x segment duration). Omitted ends are free (the fairness measure decides).
            A clamp within the feasibility tolerance of 0 (``1e-6`` of the mean chord in
            float64, ``1e-3`` in float32) is an end at rest, ``A(0) = 0`` exactly (the residual
            reports the ``|d|`` this leaves); its derivative with respect to that ``d`` is 0, as
            :func:`phjax.hermite_quintic` treats a zero end derivative.
        max_steps: step scale of the Levenberg-Marquardt solves: the feasibility solve runs
            up to ``4 * max_steps`` steps, each augmented-Lagrangian subproblem and the final
            projection up to ``2 * max_steps``.
        rtol, atol: Levenberg-Marquardt tolerances (default ``1e-10, 1e-12`` in float64,
            ``1e-5, 1e-6`` in float32), on the scaled problem (the solver's absolute tolerance
            is ``atol / 100``).

    Returns:
        ``(curves, solution)``: a batch of ``N`` :class:`PHQuintic` (segment ``k`` from
        ``points[k]`` to ``points[k + 1]`` on ``t in [0, 1]``; C2 across joints) and a
        :class:`SplineSolution` (status, residual, fairness, steps, ``ok``, the unknowns ``Z``).

    Raises:
        ValueError: fewer than 3 points or a wrong shape (checked outside ``jit``). Non-finite
            points give status ``FAILED`` (no exception inside the solver).
    """
    pts = jnp.asarray(points)
    if not jnp.issubdtype(pts.dtype, jnp.floating):
        pts = pts.astype(jnp.zeros(()).dtype)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"ph_spline: points must have shape (n, 3), got {pts.shape}")
    if pts.shape[0] < 3:
        raise ValueError(f"ph_spline: need at least 3 points (2 segments), got {pts.shape[0]}")
    if int(max_steps) < 1:
        raise ValueError(f"ph_spline: max_steps must be >= 1, got {max_steps}")
    f64 = pts.dtype == jnp.float64
    rtol = (1e-10 if f64 else 1e-5) if rtol is None else rtol
    atol = (1e-12 if f64 else 1e-6) if atol is None else atol
    z3 = jnp.zeros(3, pts.dtype)
    for name, d in (("d_start", d_start), ("d_end", d_end)):
        if d is not None and np.shape(d) != (3,):
            raise ValueError(f"ph_spline: {name} must be a 3-vector, got shape {np.shape(d)}")
    ds = z3 if d_start is None else jnp.asarray(d_start, pts.dtype)
    de = z3 if d_end is None else jnp.asarray(d_end, pts.dtype)
    args = (d_start is not None, d_end is not None, int(max_steps), float(rtol), float(atol))
    if pts.dtype != jnp.float64 and jax.config.jax_enable_x64:
        # optimistix's Levenberg-Marquardt promotes its damping to float64 when x64 is on and
        # then mixes dtypes; solve such float32 input with x64 switched off locally (the
        # float32 computation users get without x64)
        with jax.enable_x64(False):
            return _solve(pts, ds, de, *args)
    return _solve(pts, ds, de, *args)
