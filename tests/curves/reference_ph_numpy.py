"""Independent NumPy reference for spatial PH quintic Hermite interpolants.

Written from the maths note (``docs/ph_math.md`` §1-§4), not from the phjax sources: every
quaternion product is an explicit Hamilton product, everything is vectorised over a batch of
segments (no Python loop over segments) and dtype-preserving (float32 in, float32 out).

Angle convention (the same as ``phjax.hermite_quintic`` with an explicit ``axis``):

* ``u`` is the given axis (normalised), ``exp(phi u) = cos(phi) + u sin(phi)``.
* ``fibre(x, phi) = sqrt|x| Q(x/|x|) exp(phi u)`` with ``Q(xhat)`` the unit quaternion taking
  ``u`` to ``xhat``: the bisector ``(xhat + u)/|xhat + u|`` when ``xhat . u > -1/2``, otherwise
  ``(xhat - u)/|xhat - u| * m`` with ``m`` a unit vector perpendicular to ``u``:
  ``normalize(u x a)`` for ``a = (0.36, 0.48, 0.8)``, or ``normalize(u x b)`` with
  ``b = (0.8, -0.6, 0)`` where ``|u x a| < 1/2`` (phjax ``_misc.unit_perpendicular`` as of this
  writing; pass ``perpendicular=`` to follow a different rule). ``fibre(0, phi) = 0``.
* ``A0 = fibre(d0, phi0)``, ``A2 = fibre(d1, phi2)``,
  ``g = 120 (p1 - p0) - 15 (d0 + d1) + 5 (A0 u A2* + A2 u A0*)``, ``B = fibre(g, phi1)``,
  ``A1 = B/4 - 3 (A0 + A2)/4``; the hodograph is ``r'(t) = A(t) u A*(t)``.

The quaternions returned here are in this *non-canonical* form (axis ``u``); phjax stores
``A_k R`` with ``R i R* = u``. The control points (and every geometric quantity) agree.

Evaluation functions follow the phjax layout: curves of batch shape ``B`` evaluated at
parameters of shape ``T`` give ``B + T (+ (3,))``. Curvature and torsion use the generic
formulas in ``r', r'', r'''`` (no PH structure), so they are an independent check.

Run ``python tests/curves/reference_ph_numpy.py`` for a self-check against phjax (float64).
"""

from __future__ import annotations

from math import comb

import numpy as np

__all__ = [
    "qmul",
    "qconj",
    "sandwich",
    "unit_perpendicular_np",
    "unit_perpendicular_argmin_np",
    "fibre_np",
    "hermite_quintic_np",
    "bernstein_basis",
    "position_np",
    "hodograph_np",
    "bezier_derivative_np",
    "speed_np",
    "speed_from_quaternions_np",
    "sigma_bernstein_np",
    "arc_length_np",
    "total_length_np",
    "curvature_np",
    "torsion_np",
]


# ------------------------------------------------------------------------------ quaternions
def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions stored ``wxyz`` (broadcasts over leading axes)."""
    p0, p1, p2, p3 = (p[..., i] for i in range(4))
    q0, q1, q2, q3 = (q[..., i] for i in range(4))
    return np.stack(
        [
            p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
            p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
            p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
            p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0,
        ],
        axis=-1,
    )


def qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate ``(w, -x, -y, -z)``."""
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def _pure(v: np.ndarray) -> np.ndarray:
    return np.concatenate([np.zeros_like(v[..., :1]), v], axis=-1)


def sandwich(a: np.ndarray, u: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Vector part of ``A u B*`` for quaternions ``A``, ``B`` and a 3-vector ``u``."""
    return qmul(qmul(a, _pure(u)), qconj(b))[..., 1:]


def _sym(a, u, b):
    """``A u B* + B u A*`` (a pure vector)."""
    return sandwich(a, u, b) + sandwich(b, u, a)


def _dot(x, y, keepdims=False):
    return np.sum(x * y, axis=-1, keepdims=keepdims)


# --------------------------------------------------------------------------- construction
_PERP_A = (0.36, 0.48, 0.8)  # unit, generic
_PERP_B = (0.8, -0.6, 0.0)  # unit, perpendicular to _PERP_A


def unit_perpendicular_np(u: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector ``u``.

    ``normalize(u x a)``, or ``normalize(u x b)`` where ``|u x a| < 1/2`` (``u`` within 30 degrees
    of ``+-a``); ``a``, ``b`` as in the module docstring.
    """
    ua = np.cross(u, np.asarray(_PERP_A, u.dtype))
    ub = np.cross(u, np.asarray(_PERP_B, u.dtype))
    c = np.where(np.linalg.norm(ua, axis=-1, keepdims=True) >= 0.5, ua, ub)
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


def data_perpendicular_np(p0, p1, d1):
    """phjax's second-branch rule: ``m`` = the unit part of ``(p1 - p0) + d1`` perpendicular to
    ``u`` (data-derived, so fixed angles stay rotation-covariant); :func:`unit_perpendicular_np`
    where that part vanishes. Returns a rule ``u -> m`` for ``perpendicular=``."""

    def rule(u):
        v = (np.asarray(p1) - np.asarray(p0)) + np.asarray(d1)
        vp = v - _dot(v, u, keepdims=True) * u
        scale = (np.linalg.norm(np.asarray(p1) - np.asarray(p0), axis=-1, keepdims=True)
                 + np.linalg.norm(d1, axis=-1, keepdims=True))
        n = np.linalg.norm(vp, axis=-1, keepdims=True)
        ok = n > 1e-9 * scale
        return np.where(ok, vp / np.where(ok, n, 1), unit_perpendicular_np(u))

    return rule


def unit_perpendicular_argmin_np(u: np.ndarray) -> np.ndarray:
    """Alternative rule ``normalize(u x e_k)`` with ``k = argmin_k |u_k|`` (earlier phjax rule)."""
    k = np.argmin(np.abs(u), axis=-1)
    c = np.cross(u, np.eye(3, dtype=u.dtype)[k])
    return c / np.linalg.norm(c, axis=-1, keepdims=True)


def _unit_fibre(xhat: np.ndarray, u: np.ndarray, perpendicular=unit_perpendicular_np) -> np.ndarray:
    """Unit quaternion ``Q`` with ``Q u Q* = xhat`` (two branches, see module docstring)."""
    c = _dot(xhat, u, keepdims=True)
    main = c > -0.5
    s1 = xhat + u
    s2 = xhat - u
    # |xhat + u| >= 1 on the main branch, |xhat - u| >= sqrt(3) on the other: no 0/0 selected
    with np.errstate(invalid="ignore", divide="ignore"):
        n1 = s1 / np.linalg.norm(s1, axis=-1, keepdims=True)
        n2 = s2 / np.linalg.norm(s2, axis=-1, keepdims=True)
    m = perpendicular(u)
    alt = qmul(_pure(n2), _pure(m))
    return np.where(main, _pure(n1), alt)


def fibre_np(x: np.ndarray, phi: np.ndarray, u: np.ndarray,
             perpendicular=unit_perpendicular_np) -> np.ndarray:
    """``sqrt|x| Q(x/|x|) exp(phi u)``: a solution of ``A u A* = x`` (0 for ``x = 0``).

    Arguments:
        x: vectors ``(..., 3)``; phi: angles ``(...)``; u: unit axes ``(..., 3)``.
        perpendicular: rule ``u -> m`` for the second branch (unit vectors perpendicular to u).

    Returns:
        Quaternions ``(..., 4)``.
    """
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    pos = n > 0
    xhat = np.where(pos, x / np.where(pos, n, 1), u)
    q = _unit_fibre(xhat, u, perpendicular)
    e = np.concatenate([np.cos(phi)[..., None], np.sin(phi)[..., None] * u], axis=-1)
    return np.sqrt(n) * qmul(q, e)


def hermite_quintic_np(p0, p1, d0, d1, phi0, phi1, phi2, axis, *,
                       perpendicular=unit_perpendicular_np):
    """PH quintic Hermite interpolant (note §3) for a batch of segments.

    Arguments:
        p0, p1: end points ``(N, 3)`` (any common batch shape; broadcast).
        d0, d1: end derivatives ``r'(0)``, ``r'(1)``, ``(N, 3)``.
        phi0, phi1, phi2: free angles, scalars or ``(N,)``.
        axis: axis ``u``, ``(3,)`` or ``(N, 3)`` (normalised here; must be non-zero).
        perpendicular: rule ``u -> m`` (unit, perpendicular to ``u``) of the second fibre branch;
            it only changes the angle origin where a direction has ``xhat . u <= -1/2``.

    Returns:
        ``(A0, A1, A2, P)``: quaternion coefficients ``(N, 4)`` (non-canonical, hodograph
        ``A u A*``) and Bezier control points ``(N, 6, 3)``.
    """
    dtype = np.result_type(*(np.asarray(x) for x in (p0, p1, d0, d1)), np.float32)
    p0, p1, d0, d1, u = (np.asarray(x, dtype=dtype) for x in (p0, p1, d0, d1, axis))
    p0, p1, d0, d1, u = np.broadcast_arrays(p0, p1, d0, d1, u)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    batch = p0.shape[:-1]
    phi0, phi1, phi2 = (np.broadcast_to(np.asarray(f, dtype=dtype), batch)
                        for f in (phi0, phi1, phi2))

    A0 = fibre_np(d0, phi0, u, perpendicular)
    A2 = fibre_np(d1, phi2, u, perpendicular)
    g = 120 * (p1 - p0) - 15 * (d0 + d1) + 5 * _sym(A0, u, A2)
    B = fibre_np(g, phi1, u, perpendicular)
    A1 = B / 4 - 3 * (A0 + A2) / 4

    P = np.empty(batch + (6, 3), dtype=dtype)
    P[..., 0, :] = p0
    P[..., 1, :] = P[..., 0, :] + sandwich(A0, u, A0) / 5
    P[..., 2, :] = P[..., 1, :] + _sym(A0, u, A1) / 10
    P[..., 3, :] = P[..., 2, :] + (_sym(A0, u, A2) + 4 * sandwich(A1, u, A1)) / 30
    P[..., 4, :] = P[..., 3, :] + _sym(A1, u, A2) / 10
    P[..., 5, :] = P[..., 4, :] + sandwich(A2, u, A2) / 5
    return A0, A1, A2, P


# ----------------------------------------------------------------------------- evaluation
def bernstein_basis(n: int, t) -> np.ndarray:
    """Bernstein basis ``C(n,k) (1-t)^(n-k) t^k``, shape ``t.shape + (n + 1,)``."""
    t = np.asarray(t)
    if not np.issubdtype(t.dtype, np.floating):
        t = t.astype(float)
    # integer powers by repeated products (exact for t = 0, 1 and dtype-preserving)
    tp = [np.ones_like(t)]
    sp = [np.ones_like(t)]
    for _ in range(n):
        tp.append(tp[-1] * t)
        sp.append(sp[-1] * (1 - t))
    return np.stack([comb(n, k) * sp[n - k] * tp[k] for k in range(n + 1)], axis=-1)


def _as_t(t, dtype):
    return np.asarray(t, dtype=dtype)


def _eval_bezier(coef: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Evaluate Bezier coefficients ``(*B, n+1, 3)`` at ``t`` (shape T): ``(*B, *T, 3)``."""
    n = coef.shape[-2] - 1
    basis = bernstein_basis(n, t.reshape(-1))  # (M, n+1)
    out = np.matmul(basis, coef)  # (*B, M, 3)
    return out.reshape(coef.shape[:-2] + t.shape + (coef.shape[-1],))


def _power_coefficients(P: np.ndarray) -> np.ndarray:
    """Power-basis coefficients ``c_j`` (``r = sum c_j t^j``) of quintic control points."""
    m = np.zeros((6, 6))
    for j in range(6):
        for k in range(j + 1):
            m[j, k] = comb(5, j) * comb(j, k) * (-1) ** (j - k)
    return np.einsum("jk,...kd->...jd", m.astype(P.dtype), P)


def position_np(P: np.ndarray, t, method: str = "bernstein") -> np.ndarray:
    """Points ``r(t)`` of quintic Bezier curves.

    Arguments:
        P: control points ``(*B, 6, 3)``; t: parameters (any shape ``T``).
        method: ``"bernstein"`` (basis matrix times control points, one batched matmul) or
            ``"horner"`` (power basis, vectorised Horner's rule).

    Returns:
        ``(*B, *T, 3)``.
    """
    t = _as_t(t, P.dtype)
    if method == "bernstein":
        return _eval_bezier(P, t)
    if method != "horner":
        raise ValueError(f"unknown method {method!r}")
    c = _power_coefficients(P)  # (*B, 6, 3)
    nb = c.ndim - 2
    c = c.reshape(c.shape[:nb] + (1,) * t.ndim + c.shape[nb:])
    tt = t[..., None]
    acc = c[..., 5, :] * tt
    for j in range(4, 0, -1):
        acc += c[..., j, :]
        acc *= tt
    acc += c[..., 0, :]
    return acc


def bezier_derivative_np(P: np.ndarray, t, order: int = 1) -> np.ndarray:
    """``order``-th derivative of the Bezier curve (forward differences of the control points)."""
    t = _as_t(t, P.dtype)
    n = P.shape[-2] - 1
    coef = P
    scale = 1
    for r in range(order):
        coef = coef[..., 1:, :] - coef[..., :-1, :]
        scale *= n - r
    return scale * _eval_bezier(coef, t)


def hodograph_np(P: np.ndarray, t) -> np.ndarray:
    """``r'(t)``, shape ``(*B, *T, 3)``."""
    return bezier_derivative_np(P, t, 1)


def speed_np(P: np.ndarray, t) -> np.ndarray:
    """``|r'(t)|`` from the control points (generic, no PH structure), shape ``(*B, *T)``."""
    return np.linalg.norm(hodograph_np(P, t), axis=-1)


def speed_from_quaternions_np(A0, A1, A2, t) -> np.ndarray:
    """``sigma(t) = |A(t)|^2`` (note §2), shape ``(*B, *T)``."""
    A = np.stack([A0, A1, A2], axis=-2)
    t = _as_t(t, A.dtype)
    a = _eval_bezier(A, t)
    return np.sum(a * a, axis=-1)


def sigma_bernstein_np(A0, A1, A2) -> np.ndarray:
    """Quartic Bernstein coefficients of ``sigma`` (note §4.1), shape ``(*B, 5)``."""
    return np.stack(
        [_dot(A0, A0), _dot(A0, A1), (2 * _dot(A1, A1) + _dot(A0, A2)) / 3, _dot(A1, A2),
         _dot(A2, A2)],
        axis=-1,
    )


def total_length_np(A0, A1, A2) -> np.ndarray:
    """Total arc length ``L = (sigma0 + ... + sigma4)/5``, shape ``(*B,)``."""
    return np.sum(sigma_bernstein_np(A0, A1, A2), axis=-1) / 5


def arc_length_np(A0, A1, A2, t) -> np.ndarray:
    """Arc length ``s(t)``, a quintic with Bernstein coefficients ``s_k = sum_{j<k} sigma_j / 5``.

    Returns:
        ``(*B, *T)``.
    """
    sig = sigma_bernstein_np(A0, A1, A2)
    s = np.concatenate([np.zeros_like(sig[..., :1]), np.cumsum(sig, axis=-1) / 5], axis=-1)
    t = _as_t(t, s.dtype)
    return _eval_bezier(s[..., None], t)[..., 0]


def _r123(P, t):
    return (bezier_derivative_np(P, t, k) for k in (1, 2, 3))


def curvature_np(P: np.ndarray, t) -> np.ndarray:
    """``kappa = |r' x r''| / |r'|^3`` (0 where ``r' = 0``), shape ``(*B, *T)``."""
    d1, d2, _ = _r123(P, t)
    num = np.linalg.norm(np.cross(d1, d2), axis=-1)
    den = np.linalg.norm(d1, axis=-1) ** 3
    ok = den > 0
    return np.where(ok, num / np.where(ok, den, 1), 0)


def torsion_np(P: np.ndarray, t) -> np.ndarray:
    """``tau = (r' x r'') . r''' / |r' x r''|^2`` (0 where ``r' x r'' = 0``), shape ``(*B, *T)``."""
    d1, d2, d3 = _r123(P, t)
    c = np.cross(d1, d2)
    den = _dot(c, c)
    ok = den > 0
    return np.where(ok, _dot(c, d3) / np.where(ok, den, 1), 0)


# ----------------------------------------------------------------------------- self-check
def _self_check(n: int = 2000, seed: int = 0) -> None:  # pragma: no cover - manual tool
    """Compare with phjax (float64) and check the interpolation conditions; prints max errors."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import phjax

    rng = np.random.default_rng(seed)
    p0, p1, d0, d1 = (rng.normal(size=(n, 3)) for _ in range(4))
    # a quarter of the directions at or beyond -u (other branch), some exactly -u, some zero
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    q = n // 4
    d0[:q] = -axis[:q] * rng.uniform(0.2, 2, size=(q, 1)) + 0.3 * rng.normal(size=(q, 3))
    d1[q : 2 * q] = -axis[q : 2 * q] * 1.5
    d0[2 * q : 2 * q + 10] = 0
    phi0, phi1, phi2 = (rng.uniform(-np.pi, np.pi, n) for _ in range(3))
    from phjax._misc import unit_perpendicular

    print("max |m_np - m_phjax|              ",
          np.abs(unit_perpendicular_np(axis) - np.asarray(unit_perpendicular(axis))).max())
    A0, A1, A2, P = hermite_quintic_np(p0, p1, d0, d1, phi0, phi1, phi2, axis)
    c = phjax.hermite_quintic(p0, p1, d0, d1, phi0, phi2, phi1=phi1, axis=axis)
    t = np.linspace(0, 1, 7)
    scale = 1 + np.abs(P).max()
    print("max |P_np - P_phjax|              ",
          np.abs(P - np.asarray(c.control_points)).max() / scale)
    print("max |P5 - p1|, |r'(0) - d0|, ...  ", max(np.abs(P[:, 5] - p1).max(),
          np.abs(hodograph_np(P, 0.0) - d0).max(), np.abs(hodograph_np(P, 1.0) - d1).max()))
    A = lambda tt: A0 * (1 - tt) ** 2 + 2 * A1 * (1 - tt) * tt + A2 * tt**2  # noqa: E731
    u = axis
    hod = np.stack([sandwich(A(x), u, A(x)) for x in t], axis=1)
    print("max |r' - A u A*|                 ", np.abs(hod - hodograph_np(P, t)).max())
    print("max |speed - sigma|               ",
          np.abs(speed_np(P, t) - speed_from_quaternions_np(A0, A1, A2, t)).max())
    x, w = np.polynomial.legendre.leggauss(20)
    quad = np.sum(speed_np(P, (x + 1) / 2) * w / 2, axis=-1)
    print("max |L - quadrature|              ", np.abs(total_length_np(A0, A1, A2) - quad).max())
    for name, mine, theirs in [
        ("position", position_np(P, t), c.position(t)),
        ("position horner", position_np(P, t, "horner"), c.position(t)),
        ("arc_length", arc_length_np(A0, A1, A2, t), c.arc_length(t)),
        ("curvature", curvature_np(P, t[1:-1]), c.curvature(t[1:-1])),
        ("torsion", torsion_np(P, t[1:-1]), c.torsion(t[1:-1])),
    ]:
        err = np.abs(mine - np.asarray(theirs)) / (1 + np.abs(mine))
        print(f"max rel |{name} np - phjax|".ljust(35), np.nanmax(err[2 * q + 10 :]))


if __name__ == "__main__":  # pragma: no cover
    _self_check()
