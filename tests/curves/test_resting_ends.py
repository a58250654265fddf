"""Resting ends (a zero end derivative: the head is still there) across phjax.curves: the Frenet
frame's limit at the end, C2 splines clamped at rest, and one status for the shape pair.

Each test failed on the code before the fix (checked by running this file against it):
* ``frame("frenet")`` at the resting end, and below the speed threshold (``t = 1e-9``), returned
  the Euler-Rodrigues frame (its normal up to 1.3 off the limit) and a gradient that jumped there;
* ``ph_spline`` clamped to a zero derivative stalled in Levenberg-Marquardt: FAILED (residual
  1.15e-6 on the random points) or NOT_FAIREST (residual 9.2e-7, stationarity 0.02 on the helix);
* ``grid_search_shape`` reported SUCCESS where ``optimize_shape`` reported DEGENERATE.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import assert_central_differences

import phjax as pj
from phjax.curves import ph_spline
from phjax.curves.ph_spline import SplineStatus
from phjax.curves.shape import ShapeStatus, grid_search_shape, optimize_shape


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ------------------------------------------------------------------------ Frenet frame
def _resting_segments(end: int, n: int = 16, seed: int = 0):
    """``n`` random Hermite problems with ``d0 = 0`` (``end = 0``) or ``d1 = 0`` (``end = 1``)."""
    p0, p1, d0, d1 = np.random.default_rng(seed + end).normal(size=(4, n, 3))
    return (p0, p1, 0 * d0, d1) if end == 0 else (p0, p1, d0, 0 * d1)


def _bezier_limit_frame(P, end: int):
    """Frenet frame at a resting end from the control points alone (independent of ``A``).

    At a zero of ``A`` the hodograph vanishes to second order, so ``P0 = P1 = P2`` (or
    ``P3 = P4 = P5``); the first non-vanishing derivatives are ``r'''`` (tangent) and ``r''''``
    (``r''' x r''''`` gives the binormal): at ``t = 0`` along ``P3 - P2`` and
    ``(P3 - P2) x (P4 - P3)``, at ``t = 1`` along ``P3 - P2`` and ``(P2 - P1) x (P3 - P2)``."""
    if end == 0:
        t, b = P[:, 3] - P[:, 2], np.cross(P[:, 3] - P[:, 2], P[:, 4] - P[:, 3])
    else:
        t, b = P[:, 3] - P[:, 2], np.cross(P[:, 2] - P[:, 1], P[:, 3] - P[:, 2])
    t, b = _unit(t), _unit(b)
    return np.stack([t, np.cross(b, t), b], -1)


@pytest.mark.parametrize("end", [0, 1])
def test_frenet_frame_at_a_resting_end_is_the_limit(end):
    data = _resting_segments(end)
    c = pj.hermite_quintic(*data)
    P = np.asarray(c.control_points)
    # a resting end: two repeated control points
    rest = P[:, :3] if end == 0 else P[:, 3:]
    np.testing.assert_array_equal(rest, np.broadcast_to(rest[:, :1], rest.shape))
    side = 1.0 if end == 0 else -1.0
    # at the end, below the speed threshold (1e-9: sigma ~ 1e-18 < eps S), and above it (1e-7)
    t = end + side * np.array([0.0, 1e-9, 1e-7])
    F = np.asarray(c.frame(jnp.asarray(t), "frenet"))  # (n, 3, 3, 3)
    near = F[:, 2]
    # the reference of the note: the frame an O(1e-7) step inside, where r' x r'' is regular
    np.testing.assert_allclose(F[:, 0], near, atol=1e-6)
    np.testing.assert_allclose(F[:, 1], near, atol=1e-6)
    # and the limit from the Bezier form, independent of the preimage A
    np.testing.assert_allclose(F[:, 0], _bezier_limit_frame(P, end), atol=1e-12)
    # a rotation, and not the ERF (the old answer at the end)
    f0 = F[:, 0]
    np.testing.assert_allclose(f0.transpose(0, 2, 1) @ f0, np.broadcast_to(np.eye(3), f0.shape),
                               atol=1e-12)
    erf = np.asarray(c.frame(jnp.asarray(float(end)), "euler_rodrigues"))
    np.testing.assert_allclose(f0[..., 0], erf[..., 0], atol=1e-12)  # same tangent
    assert np.median(np.abs(f0[..., 1] - erf[..., 1]).max(-1)) > 1e-2
    # the quaternion form follows the matrix
    q = c.frame_quaternion(jnp.asarray([float(end)]), "frenet")[:, 0]
    np.testing.assert_allclose(np.asarray(pj.quaternion.quat_to_matrix(q)), f0, atol=1e-12)


@pytest.mark.parametrize("end", [0, 1])
def test_frenet_limit_gradients_are_finite_and_match_differences(end):
    """Gradients of the end frame with respect to the Hermite data (the resting end kept at
    rest, so the end frame is the limit for every perturbation: a smooth function) against
    central differences; finite gradients with respect to the curve's coefficients; jit, vmap
    and float32."""
    p0, p1, d0, d1 = (x[0] for x in _resting_segments(end, n=1, seed=3))
    w = jnp.asarray(np.random.default_rng(5).normal(size=(3, 3)))
    te = float(end)

    def f(p1, dmove, t):
        args = (p0, p1, d0, dmove) if end == 0 else (p0, p1, dmove, d1)
        return jnp.sum(w * pj.hermite_quintic(*args).frame(t, "frenet"))

    dmove = d1 if end == 0 else d0
    g = jax.grad(f, argnums=(0, 1))(jnp.asarray(p1), jnp.asarray(dmove), jnp.asarray(te))
    h = 1e-6
    for k, (arg, base) in enumerate(((0, p1), (1, dmove))):
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            args = [p1, dmove]
            up, dn = list(args), list(args)
            up[arg], dn[arg] = base + e, base - e
            fd = (float(f(*up, te)) - float(f(*dn, te))) / (2 * h)
            assert abs(float(g[k][i]) - fd) <= 1e-6 * (1 + abs(fd)), (k, i, g[k][i], fd)
    # the gradient is continuous into the curve (t = 1e-9 inside uses the same limit; 1e-7
    # the regular formula)
    for dt in (1e-9, 1e-7):
        gi = jax.grad(f, argnums=(0, 1))(jnp.asarray(p1), jnp.asarray(dmove),
                                         jnp.asarray(te + (dt if end == 0 else -dt)))
        for a, b in zip(gi, g):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)
    # with respect to the curve itself (A0, A1, A2, control points)
    c = pj.hermite_quintic(*_resting_segments(end, n=4))
    gc = jax.grad(lambda c: jnp.sum(w * c.frame(jnp.asarray([te]), "frenet")))(c)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(gc))
    # jit + vmap over curves, each at its own parameters
    tt = jnp.asarray(np.tile([te, 0.5], (4, 1)))
    fv = jax.jit(jax.vmap(lambda c, t: c.frame(t, "frenet")))(c, tt)
    np.testing.assert_allclose(np.asarray(fv), np.asarray(c.frame(tt, "frenet")), atol=1e-14)
    # float32: the same limit to float32 accuracy, finite gradients
    c32 = pj.hermite_quintic(*(jnp.asarray(x, jnp.float32) for x in _resting_segments(end, n=4)))
    f32 = np.asarray(c32.frame(jnp.asarray([te], jnp.float32), "frenet"))
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, np.asarray(c.frame(jnp.asarray([te]), "frenet")), atol=1e-4)
    g32 = jax.grad(lambda c: jnp.sum(w.astype(jnp.float32)
                                     * c.frame(jnp.asarray([te], jnp.float32), "frenet")))(c32)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g32))


# ---------------------------------------------------------------------------- C2 spline
def _helix(n=8, h=0.25, s0=0.3):
    s = s0 + h * np.arange(n + 1)
    pts = np.stack([np.cos(s), np.sin(s), s / 2], -1)
    der = h * np.stack([-np.sin(s), np.cos(s), np.full_like(s, 0.5)], -1)
    return pts, der


def _check_c2_interpolant(curves, sol, pts, tol=1e-10):
    """SUCCESS (feasible and stationary), interpolation and C2 joints (as test_ph_spline)."""
    assert int(sol.status) == SplineStatus.SUCCESS and bool(sol.ok), (
        int(sol.status), float(sol.residual), float(sol.stationarity))
    assert float(sol.residual) <= 1e-6 and float(sol.stationarity) <= 1e-6
    P = np.asarray(curves.control_points)
    scale = np.abs(pts).max()
    np.testing.assert_allclose(P[:, 0], pts[:-1], atol=tol * scale)
    np.testing.assert_allclose(P[:, 5], pts[1:], atol=tol * scale)
    d_end, d_start = 5 * (P[:-1, 5] - P[:-1, 4]), 5 * (P[1:, 1] - P[1:, 0])
    a_end = 20 * (P[:-1, 5] - 2 * P[:-1, 4] + P[:-1, 3])
    a_start = 20 * (P[1:, 2] - 2 * P[1:, 1] + P[1:, 0])
    assert np.abs(P[:-1, 5] - P[1:, 0]).max() <= tol * scale
    assert np.abs(d_end - d_start).max() <= 10 * tol * scale
    assert np.abs(a_end - a_start).max() <= 100 * tol * scale


@pytest.mark.parametrize("data", ["helix", "random"])
def test_spline_clamped_at_rest_succeeds_like_a_moving_clamp(data):
    if data == "helix":
        pts, der = _helix()
    else:
        pts = np.cumsum(np.random.default_rng(1).normal(size=(9, 3)), 0)
        der = np.gradient(pts, axis=0)
    z = np.zeros(3)
    # the non-degenerate behaviour: clamped to moving ends
    curves, sol = ph_spline(pts, der[0], der[-1])
    _check_c2_interpolant(curves, sol, pts)
    # one end at rest, the other, both (the same compiled solver: the clamps are data)
    for ds, de in ((z, der[-1]), (der[0], z), (z, z)):
        curves, sol = ph_spline(pts, ds, de)
        _check_c2_interpolant(curves, sol, pts)
        P = np.asarray(curves.control_points)
        np.testing.assert_allclose(5 * (P[0, 1] - P[0, 0]), ds, atol=1e-12)
        np.testing.assert_allclose(5 * (P[-1, 5] - P[-1, 4]), de, atol=1e-12)
        t = jnp.asarray([0.0, 1.0])
        np.testing.assert_allclose(np.asarray(curves.hodograph(t))[[0, -1], [0, 1]], [ds, de],
                                   atol=1e-12)
        # the resting ends' A vanish to rounding (A(0) = 0 is what the solver meets)
        A = np.asarray(curves.quaternion_polynomial(t))
        for rest, a in ((ds, A[0, 0]), (de, A[-1, 1])):
            if not np.any(rest):
                assert np.abs(a).max() <= 1e-12


def test_spline_at_rest_is_the_constrained_optimum_with_derivatives():
    """The fairness at rest against an independent constrained solve (scipy SLSQP with the
    equivalent linear clamp), and the implicit-function gradient against central differences."""
    from scipy.optimize import minimize

    from phjax.curves.ph_spline import _coefficients, _displacement, _fairness

    pts, _ = _helix(6, 0.3)
    z = np.zeros(3)
    curves, sol = ph_spline(pts, z, z)
    _check_c2_interpolant(curves, sol, pts)
    scale = np.mean(np.linalg.norm(np.diff(pts, axis=0), axis=1))
    dp = jnp.asarray(np.diff(pts, axis=0) / scale)
    shape = sol.Z.shape

    def cons(v):
        A0, A1, A2 = _coefficients(v.reshape(shape))
        return jnp.concatenate([(_displacement(A0, A1, A2) - dp).reshape(-1), A0[0], A2[-1]])

    fair = lambda v: _fairness(v.reshape(shape))
    z0 = np.asarray(sol.Z).reshape(-1) / np.sqrt(scale)
    # start SLSQP away from the returned optimum (perturbed), in the same gauge
    rng = np.random.default_rng(1)
    ref = minimize(lambda v: float(fair(jnp.asarray(v))), z0 + 0.05 * rng.normal(size=z0.shape),
                   jac=lambda v: np.asarray(jax.grad(fair)(jnp.asarray(v))), method="SLSQP",
                   constraints=[{"type": "eq", "fun": lambda v: np.asarray(cons(jnp.asarray(v))),
                                 "jac": lambda v: np.asarray(jax.jacfwd(cons)(jnp.asarray(v)))}],
                   options={"maxiter": 500, "ftol": 1e-15})
    assert ref.success and np.abs(np.asarray(cons(jnp.asarray(ref.x)))).max() <= 1e-10
    assert float(sol.fairness) <= ref.fun * (1 + 1e-9)
    assert abs(float(sol.fairness) - ref.fun) <= 1e-7 * ref.fun

    def f(points):
        c, _ = ph_spline(points, z, z)
        return jnp.sum(c.position(jnp.asarray([0.3, 0.7])) * jnp.asarray([1.0, -2.0, 0.5]))

    g = np.asarray(jax.grad(f)(jnp.asarray(pts)))
    assert np.all(np.isfinite(g))
    assert_central_differences(f, pts, g, [(0, 1), (2, 0), (3, 2), (6, 1)])


def test_spline_at_rest_float32():
    pts, der = _helix()
    pts, der = pts.astype(np.float32), der.astype(np.float32)
    z = np.zeros(3, np.float32)
    curves, sol = ph_spline(pts, z, z)
    assert int(sol.status) == SplineStatus.SUCCESS and curves.control_points.dtype == jnp.float32
    P = np.asarray(curves.control_points, np.float64)
    np.testing.assert_allclose(P[:, 0], pts[:-1], atol=1e-5)
    np.testing.assert_allclose(P[:, 5], pts[1:], atol=1e-5)
    np.testing.assert_allclose(P[[0, 0, -1, -1], [0, 1, 4, 5]], P[[0, 0, -1, -1], [1, 2, 5, 3]],
                               atol=1e-6)  # P0 = P1 = P2 and P3 = P4 = P5: at rest


# ------------------------------------------------------------------------ shape pair
def test_shape_pair_reports_the_same_status_for_resting_ends():
    """optimize_shape and grid_search_shape on a batch mixing moving segments, resting ends
    (d0 = 0, d1 = 0, both, an end speed at 1e-3 of the segment) and a non-finite one: the same
    status elementwise, and at the DEGENERATE segments the same (closed-form) curve."""
    p0, p1, d0, d1 = np.random.default_rng(7).normal(size=(4, 8, 3))
    d0[1] = 0.0
    d1[2] = 0.0
    d0[3] = d1[3] = 0.0
    d1[4] *= 1e-3 * (np.linalg.norm(p1[4] - p0[4]) + np.linalg.norm(d0[4])) / np.linalg.norm(d1[4])
    p0[5, 2] = np.nan
    data = (p0, p1, d0, d1)
    c_opt, opt = optimize_shape(*data, max_steps=64)
    c_grid, grid = grid_search_shape(*data, n=24, refine=4)
    s_opt, s_grid = np.asarray(opt.status), np.asarray(grid.status)
    rest = np.array([1, 2, 3, 4])
    assert np.all(s_opt[rest] == ShapeStatus.DEGENERATE)
    assert s_opt[5] == ShapeStatus.FAILED
    assert np.all(s_opt[[0, 6, 7]] == ShapeStatus.SUCCESS)
    np.testing.assert_array_equal(s_grid, s_opt)
    # the DEGENERATE curve of both is the closed form's
    cc = np.stack(pj.near_optimal_angles(*(x[rest] for x in data)), -1)
    for sol in (opt, grid):
        np.testing.assert_allclose(np.stack([sol.phi0, sol.phi2], -1)[rest], cc, atol=1e-12)
    np.testing.assert_allclose(np.asarray(c_grid.control_points)[rest],
                               np.asarray(c_opt.control_points)[rest], atol=1e-12)
    np.testing.assert_allclose(np.asarray(grid.objective)[rest], np.asarray(opt.objective)[rest],
                               rtol=1e-9)
    # the non-finite segment: the same record (angles 0, numeric fields inf, infeasible)
    for sol in (opt, grid):
        assert np.asarray(sol.phi0)[5] == 0 and np.isinf(np.asarray(sol.objective)[5])
        assert not np.asarray(sol.feasible)[5]
