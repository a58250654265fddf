"""Free-angle shape optimisation of PH quintic Hermite interpolants.

Every first-order Hermite problem ``(p0, p1, d0, d1)`` has a two-parameter family of PH quintic
interpolants, labelled by the free angles ``(phi0, phi2)`` of :func:`phjax.hermite_quintic`
(``phi1 = 0``). The family is the torus ``(phi0, phi2) in [-pi, pi)^2``, every curve once: a
common shift of all three angles leaves the curve unchanged, so with ``phi1`` fixed both remaining
angles matter. ``beta = phi2 - phi0`` alone fixes the closing quaternion and the arc length; the
common part ``alpha = (phi0 + phi2)/2`` (relative to ``phi1``) changes the shape at fixed
``beta``. :func:`optimize_shape` picks the member that minimises a shape measure, optionally
subject to bounds on curvature and torsion; :func:`grid_search_shape` is a dense-grid reference.

Objectives (``objective=``)
---------------------------
* ``"bending_energy"``: ``E = int kappa^2 ds = int kappa^2 sigma dt`` by Gauss-Legendre
  quadrature with ``num_nodes`` nodes (32: within 1e-6 of the exact integral even for looping
  random segments, 1e-14 on tracking data; with 64 nodes it is :meth:`PHQuintic.bending_energy`).
* ``"arc_length"``: the closed-form length. It depends on ``beta`` only, so the optimal
  ``alpha`` is not unique: one minimiser is returned.
* ``"torsion_energy"``: ``int (kappa^2 + w tau_e^2) ds`` with ``w = torsion_weight`` (default 1,
  the Frenet-frame rotation energy). Torsion is unbounded near inflections (``kappa -> 0``), where
  the Frenet frame is undefined, and quadrature then misses the spikes of ``tau^2``; it therefore
  enters damped, ``tau_e = tau kappa^2 / (kappa^2 + eps^2)`` with ``eps = torsion_eps / L``
  (``L`` the arc length, default ``torsion_eps = 0.3``): full weight where the segment turns
  visibly (``kappa L >> 0.3``), little on nearly straight segments (there ``E`` dominates). With
  the default the 32-node quadrature is within ~3e-4 of the integral on random segments; at
  ``torsion_eps = 1e-4`` it can miss near-inflection spikes by orders of magnitude.
* a callable ``objective(curve) -> scalar`` of one unbatched :class:`PHQuintic`, differentiable
  with JAX (traced once per distinct callable object).

Constraints
-----------
``max_t kappa(t) <= kappa_max`` and ``max_t |tau(t)| <= tau_max`` on ``t in [0, 1]``. Optimistix
has no inequality constraints; the bounds enter through an **augmented Lagrangian**. With the
squared ratios ``q(t) = kappa(t)^2 / kappa_max^2`` (and ``tau(t)^2 / tau_max^2``), ``[0, 1]`` is
cut into windows of 4 intervals of ``num_samples`` Chebyshev-Lobatto points (both ends included:
the curvature of Hermite segments usually peaks there), and each window gives one constraint
``g_w = log max_window q <= 0``, the window maximum refined by Newton's method in ``t``
(continuous, and smooth while the peak stays inside a window). Phase 1 minimises
``f / f_scale + sum_w (relu(lam_w + mu g_w)^2 - lam_w^2) / (2 mu)`` (``mu = penalty_weight``;
``f_scale``, the median ``|f|`` over the seed grid, makes it scale-free) in ``_ALM_ITERS = 4``
warm-started BFGS solves with multiplier updates ``lam_w = relu(lam_w + mu g_w)``; at convergence
the bounds hold exactly (no tightening margin), including optima where two peaks touch the bound.
Feasibility is then judged on the **real** ``max kappa`` and ``max |tau|`` over ``report_points``
uniform parameters, to relative tolerance ``constraint_rtol``. Segments that fail get phase 2,
which minimises the violation alone (a smooth maximum of ``log q`` over all samples: log-sum-exp
with exponent 128) and returns that **least-violating** curve with status
:attr:`ShapeStatus.INFEASIBLE` (or :attr:`ShapeStatus.FEASIBLE_ONLY` if that curve turns out
feasible). The constraint torsion is damped like the objective's but with ``eps = 1e-6 / L``
(real torsion except within a hair of an inflection). Torsion bounds are ill-conditioned on
nearly straight segments (tracking data), where ``tau`` of the interpolant is large and erratic:
expect ``INFEASIBLE`` there for moderate ``tau_max``.

Solver
------
Per segment the objective (with the phase-1 penalty at ``lam = 0``) is evaluated on a
``seed_grid x seed_grid`` grid of cell centres of the torus (16 quadrature nodes; only
``seed_grid`` closing quaternions, as they depend on ``beta`` only). The starts are the
closed-form near-optimal angles (:func:`phjax.near_optimal_angles`) and ``num_starts - 1`` grid
points, greedily the lowest periodic local minima (then the lowest other points), none within
one cell of a start already taken. ``optimistix.minimise`` with :class:`optimistix.BFGS`
(``throw=False``, gradients by forward mode) runs from every start (one ``jax.vmap`` over all
``segments x starts`` lanes, inside one jitted call) in coordinates preconditioned by the grid's finite-difference Hessian at the start (eigenvalue
magnitudes floored), so the first step is close to a Newton step; later augmented-Lagrangian
solves are preconditioned by the previous solve's inverse-Hessian estimate. The lowest value
wins (among ties up to rounding, a converged start) and its optimistix result maps to
:class:`ShapeStatus`. A vmapped ``while_loop`` runs until every lane stops, so ``max_steps``
bounds the cost of a batch. Measured (``benchmarks/bench_shape.py``): the median start converges
in about 10 steps; with the defaults 0.3-5 % of segments report ``MAX_STEPS`` (still the best
point found). With the default 8 starts the optimum was within 1e-6 of (or below) the dense grid on
every non-resting benchmark segment (512 each of random, TUM RGB-D, TUM VI and CWI VR
segments). The bounded solve costs about 8x the unbounded one. Energy objectives skip segments with a resting end
(:attr:`ShapeStatus.DEGENERATE`).

Gradients
---------
The solver itself is not differentiated (a ``jax.custom_jvp`` with zero derivative; under
``jax.grad`` it reuses the compiled solver). The returned angles carry **implicit-function-
theorem** derivatives (a second ``jax.custom_jvp``): ``d phi* = -H^-1 d(grad_phi F)`` with the
2x2 Hessian ``H`` of the objective that selected them, and with active bounds (``lam_w > 0``) the
bordered KKT system of ``f / f_scale + sum lam_w g_w`` with ``d g_w = 0``. The second derivatives
are central differences in ``phi`` of exact (reverse-mode) gradients (relative error about
``eps^(2/3)``: 1e-10 in float64; three times cheaper to compile than a forward-over-reverse
Hessian). So the curve, the objective value and the other record fields are differentiable with
respect to the Hermite data and the bounds; tested against central differences of re-solved
optima:

* no active bound: value and curve derivatives exact (to ~1e-6);
* active bound: the value's gradient is exact (envelope theorem: ``df = d_theta f + sum lam_w
  d_theta g_w``), including the derivative with respect to the bound (the shadow price); the
  curve's derivative holds the parameter ``t*`` of each active curvature peak fixed, which drops
  a second-order term when the peak is interior to its window (measured error up to ~0.5 %);
* ``INFEASIBLE`` (least violation): value and curve derivatives approximate in the same way
  (~0.3 % measured);
* where the system is singular or the (reduced) Hessian is not positive definite (an
  unconverged solve, a degenerate KKT point) and for ``DEGENERATE`` segments the angles are held
  fixed (zero derivative).

Conventions follow :func:`phjax.hermite_quintic`: the angles are reported for its default
(data-driven) axis, or for ``axis`` when given, so ``hermite_quintic(p0, p1, d0, d1, sol.phi0,
sol.phi2, axis=axis)`` rebuilds the curve. Library code is dtype-generic; in float32 the
Hermite construction loses 4-5 digits (see :mod:`phjax.curves.ph_quintic`) and the default tolerances
are looser. Each distinct batch size, dtype and static setting compiles once: measured on a
2-core machine about 7 s without bounds and 15 s with; a first ``jax.grad`` adds 5-10 s.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._jit import jit
from .._misc import any_traced, safe_div, safe_norm, safe_sqrt
from .ph_quintic import (
    PHQuintic,
    _cc_angles,
    _check_vec3,
    _ends,
    _Frame,
    _from_coefficients,
    _gauss_legendre,
    _is_tracer,
    _prepare,
    _qexp_i,
    _sandwich_i,
    _sym_i,
)
from ..quaternion import quat_mul

__all__ = ["Objective", "ShapeSolution", "ShapeStatus", "grid_search_shape", "optimize_shape"]

Objective = Literal["bending_energy", "arc_length", "torsion_energy"] | Callable[[PHQuintic], Any]
_NAMED = ("bending_energy", "arc_length", "torsion_energy")
_TORSION_EPS_CONSTRAINT = 1e-6  # constraints: eps = _TORSION_EPS_CONSTRAINT / L
_LSE_EXPONENT = 128.0  # phase 2: smooth max of log q_j
_Q_FLOOR = 1e-20  # q_j below this count as 0 in log q_j
_SEED_NODES = 16  # quadrature nodes of the seed grid (ranking only)
_PEAK_NEWTON = 3  # Newton steps refining the constraint peak in t
_ALM_ITERS = 4  # augmented-Lagrangian iterations (phase 1 with bounds)
_REST_RATIO = 1e-2  # energy objectives: end speed / segment scale below this -> DEGENERATE
_ALM_UPDATE = 0.05  # update the multipliers only where max g <= this
_OPTIONS = {"autodiff_mode": "fwd"}  # BFGS gradients by forward mode (2 angles)


class ShapeStatus(enum.IntEnum):
    """Per-segment status codes of :class:`ShapeSolution` (plain ``int`` values).

    * ``SUCCESS`` (0): converged; the bounds (if any) hold.
    * ``INFEASIBLE`` (1): the bounds could not be met (to ``constraint_rtol``); the
      least-violating curve found is returned.
    * ``MAX_STEPS`` (2): the best start reached ``max_steps`` before the convergence test
      passed; the best curve found is returned (the bounds hold).
    * ``FAILED`` (3): non-finite input data (angles 0, numeric record fields ``inf``; the curve
      propagates the NaN like :func:`phjax.hermite_quintic`) or another optimistix failure.
    * ``FEASIBLE_ONLY`` (4): the penalised solve ended infeasible but the least-violating curve
      meets the bounds; it is returned (feasible, objective not minimised).
    * ``DEGENERATE`` (5): energy objectives only: an end derivative is below ``1e-2`` of the
      segment scale ``|d0| + |d1| + |p1 - p0|`` (a resting end). The energy then diverges like
      the inverse end speed for every angle pair and its quadrature is unreliable (measured on
      random segments with 32 nodes: error up to 0.3 % at that ratio, 9 % at 1e-3, 100 % at
      1e-6), so the closed-form default angles are returned, unoptimised (and held fixed under
      differentiation). :func:`grid_search_shape` reports it for the same segments.
    """

    SUCCESS = 0
    INFEASIBLE = 1
    MAX_STEPS = 2
    FAILED = 3
    FEASIBLE_ONLY = 4
    DEGENERATE = 5


class ShapeSolution(eqx.Module):
    """Per-segment record of :func:`optimize_shape` / :func:`grid_search_shape` (batch ``*b``).

    Attributes:
        phi0, phi2: optimal free angles in ``[-pi, pi]`` (convention of
            :func:`phjax.hermite_quintic` with the same ``axis``), ``(*b,)``.
        status: :class:`ShapeStatus` codes, ``(*b,)`` int32.
        objective: objective value of the returned curve (unpenalised), ``(*b,)``.
        max_curvature: ``max kappa`` over the dense report grid, ``(*b,)``.
        max_torsion: ``max |tau|`` over the dense report grid, ``(*b,)``.
        max_violation: ``max(0, max_curvature/kappa_max - 1, max_torsion/tau_max - 1)`` (0
            without bounds), ``(*b,)``.
        feasible: ``max_violation <= constraint_rtol``, ``(*b,)`` bool.
        num_steps: optimistix steps of the solve that produced the angles (0 for the grid
            search), ``(*b,)`` int32.
    """

    phi0: Float[Array, "*b"]
    phi2: Float[Array, "*b"]
    status: Int[Array, "*b"]
    objective: Float[Array, "*b"]
    max_curvature: Float[Array, "*b"]
    max_torsion: Float[Array, "*b"]
    max_violation: Float[Array, "*b"]
    feasible: Bool[Array, "*b"]
    num_steps: Int[Array, "*b"]


# ------------------------------------------------------------------------------ one segment
class _Segment(eqx.Module):
    """One Hermite problem with its angle-independent parts precomputed (all arrays)."""

    p0: Array  # (3,)
    dp: Array  # (3,)
    dsum: Array  # (3,)
    a0: Array  # (4,) end quaternion at phi0 = 0
    a2: Array  # (4,)
    frame: _Frame
    kmax: Array  # () bound (inf: none)
    tmax: Array  # ()
    fscale: Array  # () objective scale (set by the seed grid)

    def ends(self, phi0, phi2):
        return quat_mul(self.a0, _qexp_i(phi0)), quat_mul(self.a2, _qexp_i(phi2))

    def closing(self, A0, A2):
        """``B = 3 A0 + 4 A1 + 3 A2`` (a function of ``phi2 - phi0`` only)."""
        g = 120 * self.dp - 15 * self.dsum + 5 * _sym_i(A0, A2)
        return self.frame.fib(g, jnp.zeros(g.shape[:-1], g.dtype))

    def coefficients(self, phi):
        A0, A2 = self.ends(phi[..., 0], phi[..., 1])
        B = self.closing(A0, A2)
        return A0, B / 4 - 3 * (A0 + A2) / 4, A2


def _make_segment(p0, p1, d0, d1, axis, kmax, tmax) -> _Segment:
    p0, p1, d0, d1, frame = _prepare(p0, p1, d0, d1, axis)
    a0, a2 = _ends(p0, p1, d0, d1, frame)
    dt = p0.dtype
    return _Segment(p0=p0, dp=p1 - p0, dsum=d0 + d1, a0=a0, a2=a2, frame=frame,
                    kmax=jnp.asarray(kmax, dt), tmax=jnp.asarray(tmax, dt),
                    fscale=jnp.ones((), dt))


def _vect_conj_mul_yz(a, b):
    """y, z components of ``vect(a* b)``."""
    a0, a1, a2, a3 = (a[..., k] for k in range(4))
    b0, b1, b2, b3 = (b[..., k] for k in range(4))
    return a0 * b2 - b0 * a2 + a1 * b3 - a3 * b1, a0 * b3 - b0 * a3 + a2 * b1 - a1 * b2


def _local(A0, A1, A2, t, torsion: bool):
    """``sigma``, ``rho = 4 (b_y^2 + b_z^2)`` and (optionally) ``N = (r' x r'') . r'''`` at the
    parameters ``t`` (n,), so that ``kappa^2 = rho / sigma^4`` and ``tau = N / (sigma^2 rho)``.

    With ``A = c0 + c1 t + c2 t^2``, ``b = vect(A* A') = vect(c0* c1) + 2 t vect(c0* c2) +
    t^2 vect(c1* c2)`` is quadratic (``c1* c1``, ``c2* c2`` are real) and ``sigma = |A|^2``
    quartic: Horner at the nodes, about 25 flops per node.
    """
    c0, c1, c2 = A0, 2 * (A1 - A0), A0 - 2 * A1 + A2
    dot = lambda x, y: jnp.sum(x * y, axis=-1)
    y0, z0 = _vect_conj_mul_yz(c0, c1)
    y1, z1 = _vect_conj_mul_yz(c0, c2)
    y2, z2 = _vect_conj_mul_yz(c1, c2)
    s0, s1, s4 = dot(c0, c0), 2 * dot(c0, c1), dot(c2, c2)
    s2, s3 = dot(c1, c1) + 2 * dot(c0, c2), 2 * dot(c1, c2)
    by = y0 + t * (2 * y1 + t * y2)
    bz = z0 + t * (2 * z1 + t * z2)
    sigma = s0 + t * (s1 + t * (s2 + t * (s3 + t * s4)))
    rho = 4 * (by * by + bz * bz)
    if not torsion:
        return sigma, rho, None
    # hodograph r' = sum_k e_k t^k with e_k from the products c_j i c_l*
    e0 = _sandwich_i(c0, c0)
    e1 = _sym_i(c0, c1)
    e2 = _sym_i(c0, c2) + _sandwich_i(c1, c1)
    e3 = _sym_i(c1, c2)
    e4 = _sandwich_i(c2, c2)
    tt = t[:, None]
    r1 = e0 + tt * (e1 + tt * (e2 + tt * (e3 + tt * e4)))
    r2 = e1 + tt * (2 * e2 + tt * (3 * e3 + tt * 4 * e4))
    r3 = 2 * e2 + tt * (6 * e3 + tt * 12 * e4)
    return sigma, rho, jnp.sum(jnp.cross(r1, r2) * r3, axis=-1)


def _length(A0, A1, A2):
    dot = lambda x, y: jnp.sum(x * y, axis=-1)
    return (dot(A0, A0) + dot(A0, A1) + (2 * dot(A1, A1) + dot(A0, A2)) / 3 + dot(A1, A2)
            + dot(A2, A2)) / 5


def _per_sigma(x, sigma, k: int):
    """``x / sigma^k`` as ``k`` divisions: the backward pass of a division by ``sigma^k``
    squares it (``sigma^2k``), which leaves float32's range near a resting end (a still head:
    NaN gradients for 1 mm segments), while each single division stays within it."""
    for _ in range(k):
        x = safe_div(x, sigma)
    return x


def _tau_reg_sq(sigma, rho, n, eps2):
    """``tau_e^2`` with ``tau_e = tau kappa^2/(kappa^2 + eps^2) = N / (sigma^2 (rho + eps^2
    sigma^4)) = (N / sigma^4) / (rho / sigma^2 + eps^2 sigma^2)``."""
    tau_e = safe_div(_per_sigma(n, sigma, 4), _per_sigma(rho, sigma, 2) + eps2 * sigma * sigma)
    return tau_e * tau_e


@functools.cache
def _lobatto(m: int) -> np.ndarray:
    return (1 - np.cos(np.pi * np.arange(m) / (m - 1))) / 2


def _wrap(phi):
    return phi - 2 * jnp.pi * jnp.round(phi / (2 * jnp.pi))


def _refine_window_peaks(logq, t, q):
    """Peak parameters of ``q`` (kinds, m), sampled at ``t`` (m,), in windows of 4 intervals.

    In each window the best sample is refined by the vertex of the parabola through it and its
    neighbours, then by ``_PEAK_NEWTON`` safeguarded Newton steps on ``d log q / dt = 0``
    (central differences of ``logq``, which maps parameters (kinds, windows, p) to ``log q``)
    inside the neighbours' bracket. Held fixed under differentiation (envelope theorem).

    Returns:
        ``(x, q_best)``: refined parameters and the best sampled value, both (kinds, windows).
    """
    sg = jax.lax.stop_gradient
    m = q.shape[1]
    nw = (m - 1) // 4
    first = 4 * jnp.arange(nw)
    qs = sg(q)
    J = first + jnp.argmax(qs[:, first[:, None] + jnp.arange(5)], axis=-1)  # (kinds, nw)
    lo = t[jnp.maximum(J - 1, first)]
    hi = t[jnp.minimum(J + 1, first + 4)]
    jc = jnp.clip(J, 1, m - 2)
    take = lambda i: jnp.take_along_axis(qs, i, -1)
    x0, x1, x2 = t[jc - 1], t[jc], t[jc + 1]
    d01 = (take(jc) - take(jc - 1)) / (x1 - x0)
    d12 = (take(jc + 1) - take(jc)) / (x2 - x1)
    curv = (d12 - d01) / (x2 - x0)
    ok = curv < 0
    x = jnp.clip(jnp.where(ok, 0.5 * (x0 + x1) - d01 / (2 * jnp.where(ok, curv, -1.0)), t[J]),
                 lo, hi)
    delta = float(np.finfo(t.dtype).eps) ** 0.25 * (hi - lo)

    def newton(_, x):
        h = logq(jnp.stack([x - delta, x, x + delta], -1))
        g1 = (h[..., 2] - h[..., 0]) / (2 * delta)
        g2 = (h[..., 2] - 2 * h[..., 1] + h[..., 0]) / (delta * delta)
        step = jnp.where(g2 < 0, -g1 / jnp.where(g2 < 0, g2, -1.0), 0.0)
        return jnp.clip(x + step, lo, hi)

    x = sg(jax.lax.fori_loop(0, _PEAK_NEWTON, newton, x))
    return x, jnp.take_along_axis(q, J, -1)


class _Config(eqx.Module):
    """Static problem configuration (hashable: a jit static argument)."""

    objective: Any = eqx.field(static=True)
    torsion_weight: float = eqx.field(static=True)
    torsion_eps: float = eqx.field(static=True)
    num_nodes: int = eqx.field(static=True)
    num_samples: int = eqx.field(static=True)
    penalty_weight: float = eqx.field(static=True)
    constrained_k: bool = eqx.field(static=True)
    constrained_t: bool = eqx.field(static=True)

    @property
    def constrained(self) -> bool:
        return self.constrained_k or self.constrained_t

    def measure(self, seg: _Segment, A0, A1, A2, num_nodes: int):
        """The (unpenalised) objective of one curve."""
        obj = self.objective
        if obj == "arc_length":
            return _length(A0, A1, A2)
        if not isinstance(obj, str):
            curve = _from_coefficients(seg.p0, A0, A1, A2)
            return jnp.asarray(obj(curve), seg.p0.dtype).reshape(())
        dt = seg.p0.dtype
        x, w = (jnp.asarray(a, dt) for a in _gauss_legendre(num_nodes))
        tors = obj == "torsion_energy"
        sigma, rho, n = _local(A0, A1, A2, x, tors)
        integrand = _per_sigma(rho, sigma, 3)  # kappa^2 sigma
        if tors:
            length = _length(A0, A1, A2)
            eps2 = safe_div(jnp.asarray(self.torsion_eps**2, dt), length * length)
            integrand = integrand + self.torsion_weight * _tau_reg_sq(sigma, rho, n, eps2) * sigma
        return jnp.sum(w * integrand)

    def _ratios_at(self, seg: _Segment, A0, A1, A2, t, factor):
        """Squared ratios ``kappa^2/kappa_b^2`` and ``tau_e^2/tau_b^2`` at ``t`` (n,) for bounds
        ``factor * (kappa_max, tau_max)``: shape ``(kinds, n)``."""
        dt = seg.p0.dtype
        sigma, rho, n = _local(A0, A1, A2, t, self.constrained_t)
        out = []
        if self.constrained_k:
            out.append(_per_sigma(rho, sigma, 4) / (factor * seg.kmax) ** 2)
        if self.constrained_t:
            length = _length(A0, A1, A2)
            eps2 = safe_div(jnp.asarray(_TORSION_EPS_CONSTRAINT**2, dt), length * length)
            out.append(_tau_reg_sq(sigma, rho, n, eps2) / (factor * seg.tmax) ** 2)
        return jnp.stack(out)

    def ratios(self, seg: _Segment, A0, A1, A2, factor: float = 1.0):
        """Squared ratios at the Chebyshev-Lobatto samples, ``(kinds, num_samples)``."""
        t = jnp.asarray(_lobatto(self.num_samples), seg.p0.dtype)
        return self._ratios_at(seg, A0, A1, A2, t, factor)

    def peaks(self, seg: _Segment, A0, A1, A2, with_params: bool = False):
        """``g[k, w] = log max q_k(t)`` over window ``w`` of the constraint samples, per bound
        kind ``k``: shape ``(kinds, windows)``, ``<= 0`` where the bound holds.

        The windows are consecutive groups of 4 sample intervals. In each, the best sample is
        refined by the vertex of the parabola through it and its neighbours and ``_PEAK_NEWTON``
        safeguarded Newton steps on ``d log q/dt = 0`` (central differences) inside the
        neighbours' bracket, so ``g`` is the continuous window maximum to rounding and
        continuous in the angles. Separate windows are separate constraints: an optimum where two
        peaks of ``kappa(t)`` touch the bound is a regular KKT point. The peak parameters are
        held fixed under differentiation (envelope theorem).
        """
        dt = seg.p0.dtype
        t = jnp.asarray(_lobatto(self.num_samples), dt)
        q = self._ratios_at(seg, A0, A1, A2, t, 1.0)  # (kinds, m)
        kinds = q.shape[0]
        coeffs = jax.lax.stop_gradient((A0, A1, A2))
        rows = jnp.arange(kinds)[:, None, None]

        def logq(x):  # (kinds, nw, p) -> log q of each point's own kind
            v = self._ratios_at(seg, *coeffs, x.ravel(), 1.0).reshape((kinds,) + x.shape)
            v = jnp.take_along_axis(v, jnp.broadcast_to(rows, (1,) + x.shape), 0)[0]
            return jnp.log(jnp.maximum(v, _Q_FLOOR))

        x, sample_max = _refine_window_peaks(logq, t, q)
        best = jnp.maximum(self.peaks_at(seg, A0, A1, A2, x), sample_max)
        g = jnp.log(jnp.maximum(best, _Q_FLOOR))
        return (g, x) if with_params else g

    def peaks_at(self, seg: _Segment, A0, A1, A2, x):
        """``q`` of each kind at its own peak parameters ``x`` (kinds, windows)."""
        kinds, nw = x.shape
        qp = self._ratios_at(seg, A0, A1, A2, x.ravel(), 1.0).reshape((kinds, kinds, nw))
        return jnp.take_along_axis(qp, jnp.broadcast_to(jnp.arange(kinds)[None, :, None],
                                                        (1, kinds, nw)), 0)[0]

    @property
    def kinds(self) -> int:
        return int(self.constrained_k) + int(self.constrained_t)

    @property
    def num_constraints(self) -> int:
        """Window constraints (kinds x windows), at least 1 (a dummy without bounds)."""
        return max(self.kinds * ((self.num_samples - 1) // 4), 1)

    def constraint(self, phi, seg: _Segment):
        """Window peaks ``g`` (see :meth:`peaks`), flattened: ``<= 0`` where feasible."""
        return self.peaks(seg, *seg.coefficients(phi)).ravel()

    def scaled_objective(self, phi, seg: _Segment):
        A = seg.coefficients(phi)
        return self.measure(seg, *A, self.num_nodes) / seg.fscale

    def violation(self, phi, seg: _Segment):
        """Phase 2: smooth maximum (log-sum-exp, exponent ``_LSE_EXPONENT``) of the window
        peaks ``g``."""
        return _smooth_max(self.constraint(phi, seg))

    def solve_objective(self, phi, seg: _Segment, lam, phase2):
        """What BFGS minimises: phase 1, the augmented Lagrangian ``f/f_scale + sum_w
        (relu(lam_w + mu g_w)^2 - lam_w^2)/(2 mu)`` (just ``f/f_scale`` without bounds); phase 2
        (``phase2`` true), the violation."""
        A = seg.coefficients(phi)
        f = self.measure(seg, *A, self.num_nodes) / seg.fscale
        if not self.constrained:
            return f
        g = self.peaks(seg, *A).ravel()
        return jnp.where(phase2, _smooth_max(g), f + _alm_term(g, lam, self.penalty_weight))

    def merit(self, phi, seg: _Segment, phase2):
        """Start selection: phase 1 ``f/f_scale + 1e6 relu(max g)^2`` (feasibility first),
        phase 2 the violation."""
        A = seg.coefficients(phi)
        f = self.measure(seg, *A, self.num_nodes) / seg.fscale
        if not self.constrained:
            return f
        g = self.peaks(seg, *A).ravel()
        gm = jnp.maximum(jnp.max(g), 0)
        return jnp.where(phase2, _smooth_max(g), f + 1e6 * gm * gm)


def _alm_term(g, lam, mu):
    return jnp.sum(jnp.maximum(lam + mu * g, 0) ** 2 - lam * lam) / (2 * mu)


def _smooth_max(g):
    return jax.nn.logsumexp(_LSE_EXPONENT * g) / _LSE_EXPONENT


# ---------------------------------------------------------------------- implicit gradients
def _theta(p0, p1, d0, d1, kmax, tmax):
    """The differentiable data of one segment as one vector (14,)."""
    return jnp.concatenate([p0, p1, d0, d1, jnp.stack([kmax, tmax])])


def _segment_from_theta(theta, axis, fscale):
    seg = _make_segment(theta[0:3], theta[3:6], theta[6:9], theta[9:12], axis, theta[12],
                        theta[13])
    return eqx.tree_at(lambda s: s.fscale, seg, fscale)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _implicit_angles(cfg: _Config, phi, theta, aux):
    """Identity on the optimal angles ``phi`` of the segment with data ``theta`` (14,); ``aux``
    = ``(axis, fscale, lam, phase2, peak parameters)`` carries no derivative. The JVP is the implicit-function
    theorem of the optimality conditions: ``dphi = -H^-1 (d grad_phi F/d theta) dtheta`` for an
    unconstrained optimum (``F`` the objective, or the violation in phase 2); with active bounds
    (``lam_w > 0``) the bordered KKT system of ``f/f_scale + sum lam_w g_w`` with ``dg_w = 0``.
    The second derivatives are evaluated with the primal (central differences in ``phi`` of
    exact gradients), so the tangent map is a small matrix product, cheap to compile and to
    transpose. Zero where the system is singular or the (reduced) Hessian is not positive
    definite."""
    return phi


@_implicit_angles.defjvp
def _implicit_angles_jvp(cfg, primals, tangents):
    phi, theta, aux = primals
    _, dtheta, _ = tangents
    axis, fscale, lam, phase2, tpk = aux
    dtype = phi.dtype
    dtheta = jnp.where(jnp.isfinite(theta), dtheta, 0)  # unused infinite bounds
    theta = jnp.where(jnp.isfinite(theta), theta, 1.0)  # (only finite primals below)
    split = lambda z: (z[:2], _segment_from_theta(z[2:], axis, fscale))
    z0 = jnp.concatenate([phi, theta])
    if cfg.constrained:
        active = (lam > 0) & ~phase2
        # window peaks with their parameters held at the solution's (exact first derivatives by
        # the envelope theorem; see the module docs for the second-order caveat)

        def con(z):
            x, s = split(z)
            return jnp.log(jnp.maximum(cfg.peaks_at(s, *s.coefficients(x), tpk), _Q_FLOOR)).ravel()

        def lag(z):
            x, s = split(z)
            g = con(z)
            return jnp.where(phase2, _smooth_max(g),
                             cfg.scaled_objective(x, s) + jnp.sum(jnp.where(active, lam, 0) * g))
    else:
        active = jnp.zeros((0,), bool)

        def lag(z):
            x, s = split(z)
            return cfg.scaled_objective(x, s)

    # the second derivatives needed, d(grad_z L)/d phi (16, 2), by central differences in phi
    # of exact (reverse-mode) gradients: four gradient evaluations compile ~3x faster than a
    # forward-over-reverse Hessian; relative error ~eps^(2/3) (1e-10 in float64)
    step = float(jnp.finfo(dtype).eps) ** (1 / 3)
    shifts = jnp.concatenate([jnp.eye(2, dtype=dtype), -jnp.eye(2, dtype=dtype)]) * step
    gz = jax.vmap(jax.grad(lag))(z0 + jnp.pad(shifts, ((0, 0), (0, z0.shape[0] - 2))))
    hz = ((gz[:2] - gz[2:]) / (2 * step)).T  # (16, 2): columns d/dphi_k
    ok = jnp.all(jnp.isfinite(hz))
    hz = jnp.where(ok, hz, 0)  # the tangent map below must not multiply by inf/NaN
    h = (hz[:2] + hz[:2].T) / 2
    dgrad = hz[2:].T @ dtheta
    k = active.shape[0]
    if k:
        # first derivatives of the (cheap) constraint values by central differences in z
        ez = jnp.eye(z0.shape[0], dtype=dtype) * step * jnp.maximum(1, jnp.abs(z0))
        cz = jax.vmap(con)(jnp.concatenate([z0 + ez, z0 - ez]))
        jz = ((cz[: z0.shape[0]] - cz[z0.shape[0]:]) / (2 * jnp.diag(ez))[:, None]).T  # (k, 16)
        ok &= jnp.all(jnp.isfinite(jz))
        jz = jnp.where(ok, jz, 0)
        gphi = jz[:, :2]
        dcon = jz[:, 2:] @ dtheta
        a = active.astype(dtype)
        top = jnp.concatenate([h, gphi.T * a], axis=1)
        bottom = jnp.concatenate([gphi * a[:, None], jnp.diag(1 - a)], axis=1)
        kinv = jnp.linalg.inv(jnp.concatenate([top, bottom], axis=0))
        ok &= jnp.all(jnp.isfinite(kinv))
        kinv = jnp.where(ok, kinv, 0)
        dphi = -(kinv @ jnp.concatenate([dgrad, a * dcon]))[:2]
        # one active constraint: the reduced Hessian on its tangent must be positive
        n_act = jnp.sum(active)
        ga = gphi[jnp.argmax(active)]
        tvec = jnp.stack([-ga[1], ga[0]])
        ok &= jnp.where(n_act >= 2, True, jnp.where(n_act == 1, tvec @ h @ tvec > 0, _pd(h)))
    else:
        ok &= _pd(h)
        det = jnp.where(ok, h[0, 0] * h[1, 1] - h[0, 1] ** 2, 1)
        dphi = -jnp.stack([h[1, 1] * dgrad[0] - h[0, 1] * dgrad[1],
                           h[0, 0] * dgrad[1] - h[0, 1] * dgrad[0]]) / det
    return phi, jnp.where(ok, dphi, 0)


def _pd(h):
    a, b, c = h[0, 0], h[0, 1], h[1, 1]
    det = a * c - b * b
    return (a > 0) & (det > 1e-12 * (a + c) ** 2) & jnp.isfinite(det)


# ------------------------------------------------------------------------------- reporting
def _report(seg: _Segment, A0, A1, A2, report_points: int, rtol: float):
    """Real ``max kappa``, ``max |tau|`` over uniform parameters; violation; feasibility."""
    t = jnp.linspace(0, 1, report_points, dtype=A0.dtype)
    sigma, rho, n = _local(A0, A1, A2, t, True)
    kap = jnp.max(_per_sigma(safe_sqrt(rho), sigma, 2))
    tau = jnp.max(jnp.abs(safe_div(_per_sigma(n, sigma, 4), _per_sigma(rho, sigma, 2))))
    vk = jnp.where(jnp.isinf(seg.kmax), 0, kap / seg.kmax - 1)
    vt = jnp.where(jnp.isinf(seg.tmax), 0, tau / seg.tmax - 1)
    viol = jnp.maximum(jnp.maximum(vk, vt), 0)
    return kap, tau, viol, viol <= rtol


# ------------------------------------------------------------------------------ the solver
def _seed_grid(cfg: _Config, seg: _Segment, grid: int):
    """Penalised objective F and violation V on the grid of cell centres; sets ``fscale``.

    The closing quaternion depends on ``phi2 - phi0`` only, so the grid needs ``grid`` of
    them (index ``(j - i) mod grid``), not ``grid^2``.
    """
    dt = seg.p0.dtype
    g = -jnp.pi + 2 * jnp.pi * (jnp.arange(grid, dtype=dt) + 0.5) / grid
    A0s, A2s = seg.ends(g, g)
    B = seg.closing(jnp.broadcast_to(A0s[0], A2s.shape), A2s)
    k = jnp.mod(jnp.arange(grid)[None, :] - jnp.arange(grid)[:, None], grid)
    A0 = jnp.broadcast_to(A0s[:, None], (grid, grid, 4))
    A2 = jnp.broadcast_to(A2s[None, :], (grid, grid, 4))
    A1 = B[k] / 4 - 3 * (A0 + A2) / 4
    A0, A1, A2 = (x.reshape(-1, 4) for x in (A0, A1, A2))
    f = jax.vmap(lambda a, b, c: cfg.measure(seg, a, b, c, _SEED_NODES))(A0, A1, A2)
    fmed = jnp.median(jnp.where(jnp.isfinite(f), jnp.abs(f), 0))
    seg = eqx.tree_at(lambda s: s.fscale, seg, jnp.where(fmed > 0, fmed, 1.0).astype(dt))
    F = f / seg.fscale
    V = jnp.zeros_like(F)
    if cfg.constrained:
        # window maxima of the samples (unrefined peaks)
        q = jax.vmap(lambda a, b, c: cfg.ratios(seg, a, b, c))(A0, A1, A2)  # (G^2, kinds, m)
        win = 4 * jnp.arange((cfg.num_samples - 1) // 4)[:, None] + jnp.arange(5)
        gw = jnp.log(jnp.maximum(jnp.max(q[..., win], axis=-1), _Q_FLOOR)).reshape(q.shape[0], -1)
        F = F + jax.vmap(lambda x: _alm_term(x, jnp.zeros_like(x), cfg.penalty_weight))(gw)
        V = jax.vmap(_smooth_max)(gw)
    P0, P2 = jnp.meshgrid(g, g, indexing="ij")
    phis = jnp.stack([P0.ravel(), P2.ravel()], -1)
    clean = lambda x: jnp.where(jnp.isfinite(x), x, jnp.inf).reshape(grid, grid)
    return seg, phis, clean(F), clean(V)


def _starts(F, phis, first, num_starts: int):
    """``first`` and ``num_starts - 1`` distinct grid points: greedily the lowest periodic
    local minima of ``F``, then the lowest other points, none in the 8-neighbourhood of a start
    already taken."""
    grid = F.shape[0]
    h = 2 * jnp.pi / grid
    is_min = jnp.ones(F.shape, bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                is_min &= F <= jnp.roll(F, (di, dj), axis=(0, 1))
    rank = jnp.argsort(jnp.argsort(F.ravel()))
    score = jnp.where(is_min.ravel(), rank, rank + grid * grid)
    big = 4 * grid * grid

    def near(p):
        return jnp.all(jnp.abs(_wrap(phis - p)) <= 1.5 * h, axis=-1)

    score = jnp.where(near(first), score + big, score)
    out = [first]
    for _ in range(num_starts - 1):
        i = jnp.argmin(score)
        out.append(phis[i])
        score = jnp.where(near(phis[i]), score + big, score)
    return jnp.stack(out)


def _grid_hessian(F, starts):
    """Second differences of the periodic grid ``F`` at the grid point nearest each start."""
    grid = F.shape[0]
    h = 2 * jnp.pi / grid
    r = lambda di, dj: jnp.roll(F, (di, dj), axis=(0, 1))
    haa = (r(1, 0) - 2 * F + r(-1, 0)) / h**2
    hbb = (r(0, 1) - 2 * F + r(0, -1)) / h**2
    hab = (r(-1, -1) - r(-1, 1) - r(1, -1) + r(1, 1)) / (4 * h**2)
    idx = jnp.mod(jnp.round((starts + jnp.pi) / h - 0.5).astype(jnp.int32), grid)
    i, j = idx[:, 0], idx[:, 1]
    row0 = jnp.stack([haa[i, j], hab[i, j]], -1)
    row1 = jnp.stack([hab[i, j], hbb[i, j]], -1)
    return jnp.stack([row0, row1], -2)


def _preconditioner(h):
    """``M`` with ``M^T |H| M ~ I`` for a symmetric 2x2 ``h`` (eigenvalue magnitudes floored
    at 1e-2 of the largest and 1e-6); the identity when ``h`` is not finite."""
    a, b, c = h[0, 0], (h[0, 1] + h[1, 0]) / 2, h[1, 1]
    th = 0.5 * jnp.arctan2(2 * b, a - c)
    cs, sn = jnp.cos(th), jnp.sin(th)
    l1 = jnp.abs(a * cs * cs + 2 * b * sn * cs + c * sn * sn)
    l2 = jnp.abs(a * sn * sn - 2 * b * sn * cs + c * cs * cs)
    floor = 1e-2 * jnp.maximum(l1, l2) + 1e-6
    r1, r2 = jax.lax.rsqrt(jnp.maximum(l1, floor)), jax.lax.rsqrt(jnp.maximum(l2, floor))
    m = jnp.stack([jnp.stack([cs * r1, -sn * r2]), jnp.stack([sn * r1, cs * r2])])
    return jnp.where(jnp.all(jnp.isfinite(m)), m, jnp.eye(2, dtype=m.dtype))


def _chol_preconditioner(hinv, fallback):
    """Lower-triangular ``L`` with ``L L^T = hinv`` (2x2); ``fallback`` unless positive
    definite and finite."""
    a, b, c = hinv[0, 0], (hinv[0, 1] + hinv[1, 0]) / 2, hinv[1, 1]
    ok = (a > 0) & jnp.isfinite(a) & jnp.isfinite(b) & jnp.isfinite(c)
    l00 = jnp.sqrt(jnp.where(ok, a, 1))
    l10 = b / l00
    r = c - l10 * l10
    ok &= r > 1e-12 * c
    l11 = jnp.sqrt(jnp.where(ok, r, 1))
    z = jnp.zeros_like(a)
    m = jnp.stack([jnp.stack([l00, z]), jnp.stack([l10, l11])])
    return jnp.where(ok, m, fallback)


def _solve_lane(cfg: _Config, seg: _Segment, phi0, lam, m, phase2, solver, max_steps):
    """One preconditioned BFGS solve (``phi = M y``) of one lane (segment x start)."""

    def fobj(phi):
        return cfg.solve_objective(phi, seg, lam, phase2)

    sol = optx.minimise(lambda y, mm: fobj(mm @ y), solver, jnp.linalg.solve(m, phi0), args=m,
                        max_steps=max_steps, throw=False, options=_OPTIONS)
    ok = sol.result == optx.RESULTS.successful
    maxed = sol.result == optx.RESULTS.nonlinear_max_steps_reached
    code = jnp.where(ok, ShapeStatus.SUCCESS,
                     jnp.where(maxed, ShapeStatus.MAX_STEPS, ShapeStatus.FAILED))
    phi = m @ sol.value
    good = jnp.isfinite(fobj(phi)) & jnp.all(jnp.isfinite(phi))
    phi = jnp.where(good, phi, phi0)
    hinv = m @ sol.state.f_info.hessian_inv.as_matrix() @ m.T
    g = cfg.constraint(phi, seg) if cfg.constrained else jnp.zeros_like(lam)
    return (phi, code.astype(jnp.int32), sol.stats["num_steps"].astype(jnp.int32),
            _chol_preconditioner(hinv, m), g)


def _phase(cfg: _Config, segs: _Segment, starts, hess, phase2, solver, max_steps):
    """Preconditioned BFGS from every start of every segment (one ``vmap`` over all
    ``segments x starts`` lanes); returns each segment's best ``(phi, lam, value, code, steps)``.
    ``phase2`` (a traced scalar) selects the violation objective of phase 2.

    The first solve is preconditioned by the seed-grid Hessian ``hess``. With bounds there are
    ``_ALM_ITERS`` augmented-Lagrangian iterations: each warm-starts BFGS at the previous angles,
    preconditioned by the previous solve's inverse-Hessian estimate, and then updates the
    multipliers ``lam = relu(lam + mu g)`` (phase 1 only, and only once ``max g <= 0.05``, so that
    an unconverged far-infeasible subproblem does not inflate them).
    """
    n, ns = starts.shape[:2]
    dtype = starts.dtype
    lanes = jax.tree.map(lambda x: jnp.repeat(x, ns, axis=0), segs)
    phi0 = starts.reshape(n * ns, 2)
    m0 = jax.vmap(_preconditioner)(hess.reshape(n * ns, 2, 2))
    lam0 = jnp.zeros((n * ns, cfg.num_constraints), dtype)
    mu = cfg.penalty_weight

    def outer(carry, _):
        phi, lam, m, _, steps = carry
        phi, code, k, m, g = jax.vmap(
            lambda s, p, lm, mm: _solve_lane(cfg, s, p, lm, mm, phase2, solver, max_steps))(
            lanes, phi, lam, m)
        if cfg.constrained:
            upd = (jnp.max(g, axis=-1, keepdims=True) <= _ALM_UPDATE) & ~phase2
            lam = jnp.where(upd, jnp.maximum(lam + mu * g, 0), lam)
            lam = jnp.where(jnp.isfinite(lam), lam, 0)
        return (phi, lam, m, code, steps + k), None

    init = (phi0, lam0, m0, jnp.full((n * ns,), ShapeStatus.FAILED, jnp.int32),
            jnp.zeros((n * ns,), jnp.int32))
    iters = _ALM_ITERS if cfg.constrained else 1
    (phi, lam, _, code, steps), _ = jax.lax.scan(outer, init, None, length=iters)
    vals = jax.vmap(lambda s, p: cfg.merit(p, s, phase2))(lanes, phi)
    vals = jnp.where(jnp.isfinite(vals), vals, jnp.inf)
    return jax.vmap(_best_start)(*(x.reshape((n, ns) + x.shape[1:])
                                   for x in (phi, lam, vals, code, steps)))


def _best_start(phis, lams, vals, codes, steps):
    """The lowest value; among starts within rounding of it, a converged one."""
    best_val = jnp.min(vals)
    tol = jnp.sqrt(jnp.finfo(vals.dtype).eps) * jnp.abs(best_val)
    close = vals <= best_val + tol
    code = jnp.min(jnp.where(close, codes, ShapeStatus.FAILED))
    best = jnp.argmin(jnp.where(close & (codes == code), vals, jnp.inf))
    return phis[best], lams[best], vals[best], codes[best], steps[best]


def _segments(p0, p1, d0, d1, kmax, tmax, axis):
    return jax.vmap(lambda a, b, c, d, km, tm, ax: _make_segment(a, b, c, d, ax, km, tm),
                    in_axes=(0, 0, 0, 0, 0, 0, None if axis is None else 0))(
        p0, p1, d0, d1, kmax, tmax, axis)


class _Settings(eqx.Module):
    """Static solver settings (hashable)."""

    cfg: _Config = eqx.field(static=True)
    num_starts: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    seed_grid: int = eqx.field(static=True)
    report_points: int = eqx.field(static=True)
    constraint_rtol: float = eqx.field(static=True)


def _degenerate_mask(cfg: _Config, finite, p0, p1, d0, d1):
    """The ``DEGENERATE`` segments of :func:`optimize_shape` and :func:`grid_search_shape`
    (one rule for both): energy objectives, finite data (``finite``, see :func:`_finite_mask`)
    with an end derivative below ``_REST_RATIO`` of the segment scale."""
    if cfg.objective not in ("bending_energy", "torsion_energy"):
        return jnp.zeros(p0.shape[:1], bool)
    n0, n1 = safe_norm(d0), safe_norm(d1)
    scale = n0 + n1 + safe_norm(p1 - p0)
    return (jnp.minimum(n0, n1) <= _REST_RATIO * scale) & finite


def _record(finite, rest, phi, status, objective, kap, tau, viol, feas, steps) -> ShapeSolution:
    """The :class:`ShapeSolution` of :func:`optimize_shape` and :func:`grid_search_shape` (one
    rule for both, so that the reference pair report the same status for the same segment):
    ``status`` of the solver, ``DEGENERATE`` where ``rest`` (:func:`_degenerate_mask`), and
    ``FAILED`` for non-finite data (``finite`` false), with angles 0 and numeric fields ``inf``.

    Arguments:
        finite, rest: ``(n,)`` bool masks.
        phi: ``(n, 2)`` angles; status, steps: ``(n,)`` integer codes and step counts.
        objective, kap, tau, viol, feas: ``(n,)`` value and report of the returned curves.
    """
    status = jnp.where(rest, ShapeStatus.DEGENERATE, status)
    status = jnp.where(finite, status, ShapeStatus.FAILED).astype(jnp.int32)
    phi = jnp.where(finite[:, None], phi, 0)
    bad = lambda x: jnp.where(finite, x, jnp.asarray(jnp.inf, x.dtype))
    return ShapeSolution(
        phi0=phi[:, 0], phi2=phi[:, 1], status=status, objective=bad(objective),
        max_curvature=bad(kap), max_torsion=bad(tau), max_violation=bad(viol),
        feasible=feas & finite, num_steps=steps.astype(jnp.int32))


def _cc_batch(p0, p1, d0, d1, axis):
    return jax.vmap(lambda a, b, c, d, x: jnp.stack(_cc_angles(
        a, b, c, d, None if x is None else _prepare(a, b, c, d, x)[-1])),
        in_axes=(0, 0, 0, 0, None if axis is None else 0))(p0, p1, d0, d1, axis)


def _finite_mask(p0, p1, d0, d1, kmax, tmax, axis):
    finite = jnp.all(jnp.isfinite(jnp.concatenate([p0, p1, d0, d1], -1)), -1)
    finite &= ~jnp.isnan(kmax) & ~jnp.isnan(tmax)
    if axis is not None:
        finite &= jnp.all(jnp.isfinite(axis), -1)
    return finite


@functools.partial(jit, static_argnums=0)
def _solve_jit(st: _Settings, p0, p1, d0, d1, kmax, tmax, axis):
    """The optimal angles (no derivatives): ``(phi, lam, phase2, fscale, peak parameters,
    code, steps)``."""
    cfg = st.cfg
    n, dtype = p0.shape[0], p0.dtype
    finite = _finite_mask(p0, p1, d0, d1, kmax, tmax, axis)
    clean = lambda x, fill=0.0: jnp.where(
        finite.reshape(finite.shape + (1,) * (x.ndim - 1)), x, fill)
    data = tuple(clean(x) for x in (p0, p1, d0, d1))
    ax = None if axis is None else clean(axis, 1.0)
    segs = _segments(*data, clean(kmax, 1.0), clean(tmax, 1.0), ax)
    cc = _cc_batch(*data, ax)
    rest = _degenerate_mask(cfg, finite, *data)
    segs, phis, F, V = jax.vmap(lambda s: _seed_grid(cfg, s, st.seed_grid))(segs)
    solver = optx.BFGS(rtol=st.rtol, atol=st.atol)

    def solve(grid, first, phase2):
        starts = jax.vmap(lambda f, p, c: _starts(f, p, c, st.num_starts))(grid, phis, first)
        hess = jax.vmap(_grid_hessian)(grid, starts)
        phi, lam, _, code, steps = _phase(cfg, segs, starts, hess, phase2, solver, st.max_steps)
        return phi, lam, code, steps

    no = jnp.zeros((n,), bool)
    if not cfg.constrained:
        phi, lam, code, steps = solve(F, cc, jnp.asarray(False))
        phase2 = no
    else:
        # p = 0: augmented Lagrangian from the closed form and the seed grid; p = 1: least
        # violation for the segments left infeasible (the same traced solve, run only if needed)
        def feasible(ph):
            def one(s, x):
                return _report(s, *s.coefficients(x), st.report_points, st.constraint_rtol)[3]
            return jax.vmap(one)(segs, ph)

        def body(carry, p):
            phi, lam, code, steps, todo, phase2 = carry
            is2 = p == 1
            new = jax.lax.cond(
                jnp.any(todo),
                lambda: solve(jnp.where(is2, V, F), jnp.where(is2, phi, cc), is2),
                lambda: (phi, lam, code, steps))
            upd = todo[:, None]
            phi = jnp.where(upd, new[0], phi)
            lam = jnp.where(upd, jnp.where(is2, 0, new[1]), lam)
            code = jnp.where(todo, new[2], code)
            steps = jnp.where(todo, new[3], steps)
            phase2 = phase2 | (todo & is2)
            todo = ~feasible(phi) & finite & ~rest & ~is2
            return (phi, lam, code, steps, todo, phase2), None

        init = (cc, jnp.zeros((n, cfg.num_constraints), dtype), jnp.zeros((n,), jnp.int32),
                jnp.zeros((n,), jnp.int32), jnp.ones((n,), bool), no)
        (phi, lam, code, steps, _, phase2), _ = jax.lax.scan(body, init, jnp.arange(2))
    phi = jnp.where(rest[:, None], cc, phi)
    code = jnp.where(rest, ShapeStatus.DEGENERATE, code)
    steps = jnp.where(rest, 0, steps)
    phi = jnp.where(finite[:, None], _wrap(phi), 0)
    lam = jnp.where(finite[:, None] & ~rest[:, None], lam, 0)
    if cfg.constrained:  # peak parameters of the window constraints at the solution
        tpk = jax.vmap(lambda s, x: cfg.peaks(s, *s.coefficients(x), with_params=True)[1])(
            segs, phi)
    else:
        tpk = jnp.zeros((n, 1, 1), dtype)
    return phi, lam, phase2 & finite, segs.fscale, tpk, code, steps


_SOLVER_CACHE: dict = {}  # (settings, input avals) -> compiled _solve_jit
_SOLVER_CACHE_SIZE = 16


def _solve_compiled(st: _Settings, *args):
    """:func:`_solve_jit` through an ahead-of-time compiled executable when the inputs are
    concrete. ``jax.grad`` evaluates :func:`_solve`'s JVP rule inside a transformation, where a
    plain ``jit`` call would compile the solver again; the cached executable avoids that."""
    if any_traced(args):
        return _solve_jit(st, *args)
    leaves = jax.tree.leaves(args)
    key = (st, args[-1] is None,
           tuple((x.shape, x.dtype, getattr(x, "sharding", None)) for x in leaves))
    exe = _SOLVER_CACHE.get(key)
    if exe is None:
        exe = _solve_jit.lower(st, *args).compile()
        if len(_SOLVER_CACHE) >= _SOLVER_CACHE_SIZE:
            _SOLVER_CACHE.pop(next(iter(_SOLVER_CACHE)))
        _SOLVER_CACHE[key] = exe
    return exe(*args)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _solve(st: _Settings, p0, p1, d0, d1, kmax, tmax, axis):
    """The solver as a function with zero derivative (the derivatives of the outputs come from
    :func:`_implicit_angles`)."""
    return _solve_compiled(st, p0, p1, d0, d1, kmax, tmax, axis)


@_solve.defjvp
def _solve_jvp(st, primals, tangents):
    out = _solve_compiled(st, *primals)
    zero = lambda x: (jnp.zeros_like(x) if jnp.issubdtype(x.dtype, jnp.inexact)
                      else np.zeros(x.shape, jax.dtypes.float0))
    return out, jax.tree.map(zero, out)


@functools.partial(jit, static_argnums=0)
def _outputs_jit(st: _Settings, p0, p1, d0, d1, kmax, tmax, axis, phi, lam, phase2, fscale,
                 tpk, code, steps):
    """Differentiable curve and record at the solver's angles (implicit-function derivatives)."""
    cfg = st.cfg
    finite = _finite_mask(p0, p1, d0, d1, kmax, tmax, axis)
    live = _segments(p0, p1, d0, d1, kmax, tmax, axis)
    live = eqx.tree_at(lambda s: s.fscale, live, jax.lax.stop_gradient(fscale))
    theta = jax.vmap(_theta)(p0, p1, d0, d1, kmax, tmax)
    ax = None if axis is None else jax.lax.stop_gradient(axis)
    rest = _degenerate_mask(cfg, finite, p0, p1, d0, d1)

    def finish(s, th, x, ph, lm, p2, tp, r):
        # resting (DEGENERATE) segments: the closed-form angles, held fixed under derivatives
        ph = jnp.where(r, ph, _implicit_angles(
            cfg, ph, th, (x, jax.lax.stop_gradient(s.fscale), lm, p2, tp)))
        A = s.coefficients(ph)
        f = cfg.measure(s, *A, cfg.num_nodes)
        return (ph, _from_coefficients(s.p0, *A), f) + _report(
            s, *A, st.report_points, st.constraint_rtol)

    phi, curve, f, kap, tau, viol, feas = jax.vmap(
        finish, in_axes=(0, 0, None if ax is None else 0, 0, 0, 0, 0, 0))(
        live, theta, ax, phi, lam, phase2, tpk, rest)
    status = jnp.where(phase2, jnp.where(feas, ShapeStatus.FEASIBLE_ONLY, ShapeStatus.INFEASIBLE),
                       jnp.where(feas, code, ShapeStatus.INFEASIBLE))
    return curve, _record(finite, rest, phi, status, f, kap, tau, viol, feas, steps)


# ---------------------------------------------------------------------------- public API
def _flatten_inputs(p0, p1, d0, d1, kappa_max, tau_max, axis):
    p0, p1, d0, d1 = (_check_vec3(n, jnp.asarray(x))
                      for n, x in zip(("p0", "p1", "d0", "d1"), (p0, p1, d0, d1)))
    dtype = jnp.result_type(float, p0, p1, d0, d1)
    shapes = [x.shape[:-1] for x in (p0, p1, d0, d1)]
    shapes += [jnp.shape(b) for b in (kappa_max, tau_max) if b is not None]
    if axis is not None:
        axis = _check_vec3("axis", jnp.asarray(axis)).astype(dtype)
        if not _is_tracer(axis) and not bool(jnp.all(safe_norm(axis) > 0)):
            raise ValueError("axis must be non-zero")
        shapes.append(axis.shape[:-1])
    try:
        batch = jnp.broadcast_shapes(*shapes)
    except ValueError as err:
        raise ValueError(f"batch shapes do not broadcast: {shapes}") from err
    flat = lambda x: jnp.broadcast_to(x.astype(dtype), batch + (3,)).reshape(-1, 3)
    vecs = [flat(x) for x in (p0, p1, d0, d1)]
    bounds = []
    for name, b in (("kappa_max", kappa_max), ("tau_max", tau_max)):
        if b is None:
            bounds.append(jnp.full(vecs[0].shape[:1], jnp.inf, dtype))
            continue
        b = jnp.asarray(b, dtype)
        if not _is_tracer(b) and not bool(jnp.all(b > 0)):
            raise ValueError(f"{name} must be positive, got {b}")
        bounds.append(jnp.broadcast_to(b, batch).reshape(-1))
    return batch, dtype, vecs, bounds, None if axis is None else flat(axis)


def _config(objective, torsion_weight, torsion_eps, num_nodes, num_samples, penalty_weight,
            constraint_rtol, kappa_max, tau_max):
    if isinstance(objective, str):
        if objective not in _NAMED:
            raise ValueError(f"unknown objective {objective!r}; use one of {_NAMED} or a callable")
    elif not callable(objective):
        raise TypeError(f"objective must be one of {_NAMED} or a callable, got {objective!r}")
    _check_int("num_nodes", num_nodes, 2)
    _check_int("num_samples", num_samples, 5)
    if (num_samples - 1) % 4:
        raise ValueError(f"num_samples must be 4 k + 1 (windows of 4 intervals), got {num_samples}")
    if not penalty_weight > 0:
        raise ValueError(f"penalty_weight must be positive, got {penalty_weight}")
    if not 0 <= constraint_rtol < 1:
        raise ValueError(f"constraint_rtol must be in [0, 1), got {constraint_rtol}")
    if not torsion_weight >= 0:
        raise ValueError(f"torsion_weight must be >= 0, got {torsion_weight}")
    if not torsion_eps > 0:
        raise ValueError(f"torsion_eps must be positive, got {torsion_eps}")
    return _Config(objective=objective, torsion_weight=float(torsion_weight),
                   torsion_eps=float(torsion_eps),
                   num_nodes=int(num_nodes), num_samples=int(num_samples),
                   penalty_weight=float(penalty_weight),
                   constrained_k=kappa_max is not None, constrained_t=tau_max is not None)


def _check_int(name, v, lo):
    if isinstance(v, bool) or int(v) != v or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")


def _unflatten(curve, sol, batch):
    curve = jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), curve)
    return curve, jax.tree.map(lambda x: x.reshape(batch), sol)


def optimize_shape(
    p0: Float[ArrayLike, "*batch 3"],
    p1: Float[ArrayLike, "*batch 3"],
    d0: Float[ArrayLike, "*batch 3"],
    d1: Float[ArrayLike, "*batch 3"],
    *,
    objective: Objective = "bending_energy",
    kappa_max: Float[ArrayLike, "*batch"] | None = None,
    tau_max: Float[ArrayLike, "*batch"] | None = None,
    num_starts: int = 8,
    max_steps: int = 16,
    rtol: float | None = None,
    atol: float | None = None,
    penalty_weight: float = 1e3,
    constraint_rtol: float = 1e-3,
    torsion_weight: float = 1.0,
    torsion_eps: float = 0.3,
    seed_grid: int = 12,
    num_nodes: int = 32,
    num_samples: int = 33,
    report_points: int = 257,
    axis: Float[ArrayLike, "*batch 3"] | None = None,
) -> tuple[PHQuintic, ShapeSolution]:
    """Optimal free angles of PH quintic Hermite interpolants (batched; one jitted call).

    See the module docs for the objectives, the constraint handling and the solver.

    Arguments:
        p0, p1: end points ``(*batch, 3)``; d0, d1: end derivatives ``r'(0)``, ``r'(1)``
            (velocities times the segment duration). Broadcast together.
        objective: ``"bending_energy"``, ``"arc_length"``, ``"torsion_energy"`` or a callable
            ``curve -> scalar``.
        kappa_max, tau_max: optional bounds on ``max kappa`` and ``max |tau|`` (positive;
            broadcast against the batch).
        num_starts: BFGS starts per segment (the closed-form angles + ``num_starts - 1`` seed-grid
            minima). Default 8: with 4, 2 of 512 CWI head-trace segments ended in a basin up to
            0.5 % above the dense-grid optimum; 8 costs about 20 % more time than 4.
        max_steps: optimistix step limit per start (the cost of the batch scales with it).
        rtol, atol: BFGS tolerances on the preconditioned angles and the scale-free objective
            (default ``1e-6, 1e-8`` in float64, ``1e-3, 1e-4`` in float32).
        penalty_weight: augmented-Lagrangian penalty ``mu`` (scale-free units).
        constraint_rtol: relative tolerance of the feasibility test.
        torsion_weight: ``w`` of ``"torsion_energy"``.
        torsion_eps: torsion damping ``eps L`` of ``"torsion_energy"``.
        seed_grid: points per side of the seed grid over the angle torus.
        num_nodes: Gauss-Legendre nodes of the energy integrals.
        num_samples: Chebyshev-Lobatto constraint samples (``4 k + 1``).
        report_points: uniform parameters of ``max_curvature`` and ``max_torsion``.
        axis: angle convention as in :func:`phjax.hermite_quintic` (default: data-driven).

    Returns:
        ``(curves, solution)``: the optimal :class:`PHQuintic` (batch shape ``batch``) and the
        :class:`ShapeSolution` record.

    Sharding: inputs sharded along axis 0 over a device mesh (:func:`phjax.batch.shard_batch`;
    shard every batched input) are solved on each device's part and the outputs come back
    sharded the same way; unsharded inputs (e.g. scalar bounds) are replicated.

    Raises:
        ValueError: (outside ``jit``) for bad shapes, unknown objectives, non-positive bounds or
            out-of-range settings.
    """
    cfg = _config(objective, torsion_weight, torsion_eps, num_nodes, num_samples, penalty_weight,
                  constraint_rtol, kappa_max, tau_max)
    for name, v, lo in (("num_starts", num_starts, 1), ("max_steps", max_steps, 1),
                        ("seed_grid", seed_grid, 3), ("report_points", report_points, 2)):
        _check_int(name, v, lo)
    batch, dtype, vecs, bounds, axis = _flatten_inputs(p0, p1, d0, d1, kappa_max, tau_max, axis)
    eps = float(jnp.finfo(dtype).eps)
    rtol = (1e-6 if eps < 1e-10 else 1e-3) if rtol is None else float(rtol)
    atol = (1e-8 if eps < 1e-10 else 1e-4) if atol is None else float(atol)
    st = _Settings(cfg=cfg, num_starts=int(num_starts), max_steps=int(max_steps), rtol=rtol,
                   atol=atol, seed_grid=int(seed_grid), report_points=int(report_points),
                   constraint_rtol=float(constraint_rtol))
    data = (*vecs, *bounds, axis)
    solved = _solve(st, *data)
    return _unflatten(*_outputs_jit(st, *data, *solved), batch)


# ----------------------------------------------------------------------------- grid search
def _grid_values(cfg: _Config, seg: _Segment, g0, g2):
    """Objective and max squared ratio (real bounds) on the product grid, row by row."""

    def row(a):
        phis = jnp.stack([jnp.full_like(g2, a), g2], -1)
        A = jax.vmap(seg.coefficients)(phis)
        f = jax.vmap(lambda *c: cfg.measure(seg, *c, cfg.num_nodes))(*A)
        if not cfg.constrained:
            return f, jnp.zeros_like(f)
        return f, jax.vmap(lambda *c: jnp.max(cfg.peaks(seg, *c)))(*A)

    return jax.lax.map(row, g0)


def _grid_pick(f, q, g0, g2):
    feas = q <= 0
    key = jnp.where(jnp.any(feas), jnp.where(feas, f, jnp.inf), q)
    i = jnp.argmin(jnp.where(jnp.isnan(key), jnp.inf, key).ravel())
    return jnp.stack([g0[i // g2.shape[0]], g2[i % g2.shape[0]]])


@functools.partial(jit, static_argnums=(0, 8, 9, 10, 11))
def _grid_jit(cfg, p0, p1, d0, d1, kmax, tmax, axis, n, refine, report_points, constraint_rtol):
    dtype = p0.dtype
    k = jnp.arange(-4, 5, dtype=dtype)
    finite = _finite_mask(p0, p1, d0, d1, kmax, tmax, axis)
    rest = _degenerate_mask(cfg, finite, p0, p1, d0, d1)
    # resting (DEGENERATE) segments: the closed-form angles, as optimize_shape returns them
    cc = jax.lax.stop_gradient(_cc_batch(p0, p1, d0, d1, axis))

    def one(seg, r, cc):
        g = -jnp.pi + 2 * jnp.pi * (jnp.arange(n, dtype=dtype) + 0.5) / n
        best = _grid_pick(*_grid_values(cfg, seg, g, g), g, g)

        def zoom(carry, _):
            best, h = carry
            h = 0.375 * h
            g0, g2 = best[0] + k * h, best[1] + k * h
            return (_grid_pick(*_grid_values(cfg, seg, g0, g2), g0, g2), h), None

        h0 = jnp.asarray(2 * np.pi / n, dtype)
        (best, _), _ = jax.lax.scan(zoom, (best, h0), None, length=refine)
        phi = _wrap(jnp.where(r, cc, best))
        A = seg.coefficients(phi)
        f = cfg.measure(seg, *A, cfg.num_nodes)
        return (phi, _from_coefficients(seg.p0, *A), f) + _report(
            seg, *A, report_points, constraint_rtol)

    phi, curve, f, kap, tau, viol, feas = jax.vmap(one)(
        _segments(p0, p1, d0, d1, kmax, tmax, axis), rest, cc)
    status = jnp.where(feas, ShapeStatus.SUCCESS, ShapeStatus.INFEASIBLE)
    return curve, _record(finite, rest, phi, status, f, kap, tau, viol, feas,
                          jnp.zeros(status.shape, jnp.int32))


def grid_search_shape(
    p0: Float[ArrayLike, "*batch 3"],
    p1: Float[ArrayLike, "*batch 3"],
    d0: Float[ArrayLike, "*batch 3"],
    d1: Float[ArrayLike, "*batch 3"],
    *,
    n: int = 64,
    refine: int = 8,
    objective: Objective = "bending_energy",
    kappa_max: Float[ArrayLike, "*batch"] | None = None,
    tau_max: Float[ArrayLike, "*batch"] | None = None,
    constraint_rtol: float = 1e-3,
    torsion_weight: float = 1.0,
    torsion_eps: float = 0.3,
    num_nodes: int = 32,
    num_samples: int = 33,
    report_points: int = 257,
    axis: Float[ArrayLike, "*batch 3"] | None = None,
) -> tuple[PHQuintic, ShapeSolution]:
    """Dense-grid reference for :func:`optimize_shape` (derivative-free, vectorised).

    The objective is evaluated on the ``n x n`` cell centres of the angle torus; the best point
    is then refined ``refine`` times on a ``9 x 9`` grid spanning ``+-1.5`` cells of the previous
    level (the spacing shrinks by 0.375 per level). With bounds, a point is feasible when
    ``kappa`` and ``tau_e`` at the ``num_samples`` Chebyshev-Lobatto points are within the
    **untightened** bounds; the best feasible point wins, else the point with the smallest
    maximal ratio (least violation). Objective definitions and keywords as in
    :func:`optimize_shape`. ``status`` is ``SUCCESS`` or ``INFEASIBLE`` (judged like
    :func:`optimize_shape`, on the dense report grid), and by the same rule as
    :func:`optimize_shape` (one shared code path) ``DEGENERATE`` for a resting end under an
    energy objective (the closed-form angles are returned, as there) and ``FAILED`` for
    non-finite data; ``num_steps`` is 0.

    Cost: ``n^2 + 81 refine`` objective evaluations per segment; memory ``O(n)`` per segment
    (the grid is scanned row by row).

    Returns:
        ``(curves, solution)`` as :func:`optimize_shape`.
    """
    cfg = _config(objective, torsion_weight, torsion_eps, num_nodes, num_samples, 1.0,
                  constraint_rtol, kappa_max, tau_max)
    _check_int("n", n, 2)
    _check_int("refine", refine, 0)
    _check_int("report_points", report_points, 2)
    batch, _, vecs, bounds, axis = _flatten_inputs(p0, p1, d0, d1, kappa_max, tau_max, axis)
    curve, sol = _grid_jit(cfg, *vecs, *bounds, axis, int(n), int(refine), int(report_points),
                           float(constraint_rtol))
    return _unflatten(curve, sol, batch)
