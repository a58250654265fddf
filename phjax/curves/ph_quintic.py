"""Spatial Pythagorean-hodograph (PH) quintics: first-order Hermite construction and closed-form
evaluation (position, hodograph, speed, arc length and its inverse, curvature, torsion, bending
energy, Frenet / Euler-Rodrigues / rotation-minimising frames).

Mathematics: ``docs`` note *Spatial PH quintics for phjax* (corrected forms of Farouki et al.).

Conventions
-----------
* Quaternions are ``wxyz`` (scalar first), Hamilton product.
* A curve is stored in *canonical form*: its hodograph is ``r'(t) = A(t) i A*(t)`` with the
  quadratic quaternion polynomial ``A(t) = A0 (1-t)^2 + A1 2(1-t)t + A2 t^2`` and ``i = (0,1,0,0)``.
* **Free angles.** Construction uses the reference axis ``u`` = unit first end derivative
  ``d0/|d0|`` (falling back to ``d1/|d1|``, then to the chord direction, then to ``x`` when those
  vanish), or a user-given ``axis``. The end coefficients are the fibre solutions
  ``A0 = sqrt|d0| Q(d0) exp(phi0 u)`` and ``A2 = sqrt|d1| Q(d1) exp(phi2 u)`` where ``Q(d)`` is the
  unit quaternion with ``Q u Q* = d/|d|`` (the bisector ``(d/|d| + u)/|d/|d| + u|`` when
  ``d.u > -1/2``, otherwise the other branch ``(d/|d| - u)/|...| * m`` with a fixed unit ``m`` that
  is perpendicular to ``u``). ``phi1 = 0`` by default; shifting ``phi0, phi1, phi2`` together
  leaves the curve unchanged, so the family has two parameters. With ``u = d0/|d0|`` a fixed angle
  pair is rotation-covariant (rotating the data rotates the curve).
* **Default angles** (``phi0 = phi2 = None``): the closed-form near-optimal "CC" choice of Farouki,
  Giannelli, Manni & Sestini (CAGD 2008), see :func:`near_optimal_angles`. It is a geometric
  criterion, so the default curve does not depend on the angle convention or its branch switch.
* **Degenerate data.** A zero end derivative gives ``A0 = 0`` (or ``A2 = 0``), still an exact
  interpolant; at such an end the speed is 0 and the curve has a cusp-like end (curvature grows
  like ``1/t^2`` as ``t -> 0``, so the bending energy is unbounded). Where the speed ``sigma(t)``
  is exactly 0, ``curvature`` and ``torsion`` return 0 and ``frame`` returns the limiting frame
  (the ERF of ``A'(t)``; the Frenet frame's limit from ``A'`` and ``A''``, as at every speed
  below ``eps`` of the curve's scale), or the identity for a point curve. Torsion returns 0
  where curvature is 0.
  NaN inputs propagate to NaN outputs (no exception inside ``jit``); wrong shapes raise
  ``ValueError`` at trace time.
* Values **and gradients** are finite at all the singular points (zero derivatives, ``p0 = p1``,
  antiparallel end derivatives, directions at ``-u``). At a zero end derivative the exact
  interpolant varies like ``sqrt|d|`` (not differentiable); the gradient returned there is the
  finite one obtained by treating ``sqrt|d|`` as having zero derivative at 0.

Evaluation semantics
--------------------
The evaluation methods take parameters ``t`` whose **last axis is the sample axis** and whose
**leading axes broadcast against the curve batch** ``B`` (NumPy rules, like a generalised ufunc
with signature ``(curve),(T)->(T)``):

* ``t`` of shape ``(T,)``: every curve at the same ``T`` parameters, result ``B + (T,)``;
* ``t`` of shape ``B + (T,)`` (e.g. the ``t`` returned by :func:`phjax.sample`): each curve at its
  own ``T`` parameters, result ``B + (T,)`` -- no outer product;
* in general ``t`` of shape ``S + (T,)``: result ``broadcast(B, S) + (T,)``;
* scalar ``t``: every curve at that parameter, result ``B``.

Vector- and matrix-valued methods append ``(3,)``, ``(4,)`` or ``(3, 3)``. Shapes whose leading
axes do not broadcast against ``B`` raise ``ValueError`` (at trace time). One parameter per curve
is ``t[..., None]`` (shape ``B + (1,)``).
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .._jit import filter_jit, jit
from .._misc import (
    any_traced,
    check_count,
    check_last_axis,
    dot_last,
    safe_atan2,
    safe_div,
    safe_norm,
    safe_sqrt,
    sum_last,
)
from .._misc import _UNROLL_SIZE
from ..quaternion import quat_conj, quat_mul, quat_normalize, quat_to_matrix
from . import _components as _c

__all__ = ["PHQuintic", "hermite_quintic", "near_optimal_angles", "FrameKind"]

FrameKind = Literal["frenet", "euler_rodrigues", "rmf"]

# Bernstein -> power basis matrices: power[j] = sum_k M[j, k] bern[k]
def _bern_to_power(n: int) -> np.ndarray:
    from math import comb

    m = np.zeros((n + 1, n + 1))
    for j in range(n + 1):
        for k in range(j + 1):
            m[j, k] = comb(n, j) * comb(j, k) * (-1) ** (j - k)
    return m


_M5 = _bern_to_power(5)
#: torsion is 0 where the curve bends less than this many eps of its size and distance from
#: the origin (PHQuintic.torsion)
_STRAIGHT_NOISE = 8.0
_M4 = _bern_to_power(4)
_GL_NODES = {}
_CC_REGULARISATION = 0.1  # see _cc_angles
_TABLE = 32  # intervals of the arc-length inversion start table


def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [0, 1]."""
    n = check_count(n, "num_nodes")
    if n not in _GL_NODES:
        x, w = np.polynomial.legendre.leggauss(n)
        _GL_NODES[n] = ((x + 1) / 2, w / 2)
    return _GL_NODES[n]


# ----------------------------------------------------------------------------------- helpers
def _jit_method(fn):
    """``eqx.filter_jit`` for an evaluation method: the parameter array is converted to an
    array of the curve's dtype first (so Python floats do not become static), other
    non-array arguments (frame kind, node counts) are static."""
    jitted = filter_jit(fn)

    @functools.wraps(fn)
    def wrapper(self, t, *args, **kwargs):
        return jitted(self, jnp.asarray(t, dtype=self.dtype), *args, **kwargs)

    return wrapper


def _qexp_i(phi):
    """exp(phi i) = cos(phi) + i sin(phi)."""
    z = jnp.zeros_like(phi)
    return jnp.stack([jnp.cos(phi), jnp.sin(phi), z, z], axis=-1)


def _sandwich_i(a, b):
    """Vector part of ``a i b*`` (closed form of the quaternion product)."""
    return _c.stack(_c.sandwich_i(_c.split(a), _c.split(b)))


def _sym_i(a, b):
    """``a i b* + b i a*`` (a pure vector)."""
    return _c.stack(_c.sym_i(_c.split(a), _c.split(b)))


_EX = (1.0, 0.0, 0.0)  # x axis (components)


def _unit_fibre(xhat, u, m=None):
    """Unit quaternion ``Q`` with ``Q u Q* = xhat`` for unit vectors ``xhat``, ``u`` (components).

    Bisector branch when ``xhat . u > -1/2`` (denominator >= 1), otherwise the product of the
    bisector of ``(xhat, -u)`` with a unit vector ``m`` perpendicular to ``u`` (denominator
    >= sqrt(3); default :func:`unit_perpendicular`). Both are exact; the angle origin jumps by a
    phase at the switch.
    """
    c = _c.dot(xhat, u)
    main = c > -0.5
    # 1/|xhat + u| on the bisector branch, 1/|xhat - u| on the other (the square >= 1 either way)
    rho = lax.rsqrt(jnp.where(main, 2 + 2 * c, 2 - 2 * c))
    n1 = _c.scale(rho, _c.add(xhat, u))
    n2 = _c.scale(rho, _c.sub(xhat, u))
    m = _c.unit_perpendicular(u) if m is None else m
    return _c.where(main, (0.0,) + n1, _c.qmul_pure(n2, m))


def _check_vec3(name: str, x) -> Array:
    x = check_last_axis(x, 3, name)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):  # a complex curve has no PH form here
        raise TypeError(f"{name} must be real, got {x.dtype}")
    return x


def _float_dtype(*xs):
    return jnp.result_type(float, *xs)


# The construction works on component tuples (``phjax.curves._components``: ``(w, x, y, z)`` of
# batch-shaped arrays) in steps that each end in one ``_c.checkpoint`` (one XLA kernel for what the
# next steps need): XLA:CPU then compiles it to a few kernels instead of one per quaternion
# product and per vector component (compile time grows with the number of kernels). The
# array-valued ``_sandwich_i``, ``_sym_i``, ``_Frame.fib``, ``_prepare``, ``_ends``, ``_cc_angles``
# and ``_from_coefficients`` wrap it for other modules.
class _Data(NamedTuple):
    """What several steps use of one Hermite problem's data ``p0, p1, d0, d1`` (components),
    divided by their scale ``s`` (see :func:`_data`)."""

    d1: tuple  # d1
    dp: tuple  # p1 - p0
    w: tuple  # 3 (p1 - p0) - (d0 + d1), the CC target (see _cc_angles_c)
    g0: tuple  # 120 (p1 - p0) - 15 (d0 + d1), the data part of the closing condition
    d0hat: tuple  # d0/|d0| where d0 != 0
    d1hat: tuple  # d1/|d1| where d1 != 0
    axis: tuple  # data-driven axis: d0/|d0|, else d1/|d1|, else (p1 - p0)/|p1 - p0|, else x
    n0: Array  # |d0|
    n1: Array  # |d1|
    scale: Array  # |p1 - p0| + |d0| + |d1| (1, or 0 for negligible data)
    root: Array  # sqrt(s): the coefficients of the given data are root times those of these

    def unit(self, k: int, fallback) -> tuple:
        """``d_k / |d_k|`` (``k`` = 0, 1), ``fallback`` where ``d_k = 0``."""
        return _c.where((self.n0, self.n1)[k] > 0, (self.d0hat, self.d1hat)[k], fallback)


def _data(p0, p1, d0, d1) -> _Data:
    """:class:`_Data` of the arrays ``p0, p1, d0, d1`` ``(..., 3)``, computed in one kernel.

    The data are divided by their scale ``s = |p1 - p0| + |d0| + |d1|`` (``root`` is
    ``sqrt(s)``). The interpolant is homogeneous, data ``lambda (p1 - p0, d0, d1)`` giving the
    coefficients ``sqrt(lambda) A``, so the construction runs on data of scale 1 and its
    gradients stay finite however small the data are (a head coasting to rest has velocities
    decaying to ``1e-100`` and less; at that scale the backward pass of the square roots and
    normalisations overflowed). Data with ``s <= tiny^(1/4)`` (``tiny`` the dtype's smallest
    normal number: ``s`` below about ``1e-77`` in float64, ``3e-10`` in float32) give the
    constant curve. An end derivative with ``|d_k| <= eps^1.5 s`` (``eps`` of the dtype) is set
    to exact zero: the curve depends on ``d_k`` like ``sqrt|d_k|``, so its derivative grows like
    ``|d_k|^(-1/2)`` and the backward pass overflows well before ``d_k = 0``; the curve moves by
    less than about ``eps^0.75 s`` and the gradient with respect to ``d_k`` is 0, as at
    ``d_k = 0``. NaN data give NaN.
    """
    info = jnp.finfo(p0.dtype)
    # the differences as arrays: XLA then computes them inside the kernel (a component shared
    # by several later square roots would be a kernel of its own)
    dp, d0, d1 = (_c.split(x) for x in (p1 - p0, d0, d1))
    norms = [_c.norm(x) for x in (dp, d0, d1)]
    s = norms[0] + norms[1] + norms[2]
    s = jnp.where(jnp.isnan(sum(dp) + sum(d0) + sum(d1)), jnp.nan, s)  # (norms drop NaN)
    ok = ~(s <= float(info.tiny) ** 0.25)
    s = jnp.where(ok, s, 1)
    inv, root = jnp.where(ok, 1 / s, 0), jnp.where(ok, jnp.sqrt(s), 0)
    bound = float(info.eps) ** 1.5
    # double where: a dropped derivative is never normalised, so no overflow reaches gradients
    d0, d1 = (_c.where(~(n * inv <= bound), _c.scale(inv, x), (0.0, 0.0, 0.0))
              for n, x in zip(norms[1:], (d0, d1)))
    # the scaled data in one kernel (shared by every later value; a component with several
    # users outside a kernel would be a kernel of its own)
    d0, d1, dp, (root,) = _c.checkpoint(d0, d1, _c.scale(inv, dp), (root,))
    dsum = _c.add(d0, d1)
    w = _c.sub(_c.scale(3, dp), dsum)
    g0 = tuple(120 * a - 15 * b for a, b in zip(dp, dsum))
    n0, n1 = _c.norm(d0), _c.norm(d1)
    scale = _c.norm(dp) + n0 + n1
    d0hat, d1hat = _c.normalize(d0), _c.normalize(d1)
    axis = _c.where(n0 > 0, d0hat, _c.where(n1 > 0, d1hat, _c.normalize(dp, fallback=_EX, floor=1e-18)))
    *vecs, (n0,), (n1,), (scale,) = _c.checkpoint(dp, w, g0, d0hat, d1hat, axis, (n0,), (n1,),
                                                  (scale,))
    return _Data(d1, *vecs, n0, n1, scale, root)


class _Frame(eqx.Module):
    """Fibre map for one Hermite problem: ``fib(x, phase)`` in canonical (axis ``i``) form.

    The fields are component tuples (batch-shaped arrays, see ``_components``)."""

    u: tuple  # 3 components: construction axis
    r: tuple  # 4 components: unit quaternion with r i r* = u
    m: tuple  # 3 components: unit vector perpendicular to u for the second fibre branch

    def fib_c(self, x, phase=None):
        """``sqrt|x| Q(x) r exp(phase i)`` for a vector ``x`` given as components (``phase``
        ``None``: 0), with ``Q(x) = Q(u)`` where ``x = 0``."""
        return self.fib_unit(_c.norm(x), _c.normalize(x, fallback=self.u), phase)

    def fib_unit(self, n, xhat, phase=None):
        """:meth:`fib_c` of the vector ``n xhat`` (``xhat`` = ``u`` where ``n = 0``)."""
        q = _c.qmul(_unit_fibre(xhat, self.u, self.m), self.r)
        if phase is not None:
            q = _c.qmul_exp_i(q, phase)
        return _c.scale(safe_sqrt(n), q)

    def fib(self, x, phase):
        """:meth:`fib_c` on arrays: ``x`` ``(..., 3)``, result ``(..., 4)``."""
        return _c.stack(self.fib_c(_c.split(x), phase))


def _validate(p0, p1, d0, d1):
    """The data as arrays of one float dtype and one shape ``(..., 3)``."""
    p0, p1, d0, d1 = (_check_vec3(n, x) for n, x in zip(("p0", "p1", "d0", "d1"), (p0, p1, d0, d1)))
    dtype = _float_dtype(p0, p1, d0, d1)
    p0, p1, d0, d1 = (x.astype(dtype) for x in (p0, p1, d0, d1))
    return jnp.broadcast_arrays(p0, p1, d0, d1)


def _prepare(p0, p1, d0, d1, axis):
    """Validated data arrays and the :class:`_Frame` of ``axis`` (``None``: data-driven)."""
    p0, p1, d0, d1 = _validate(p0, p1, d0, d1)
    data = _data(p0, p1, d0, d1)
    return p0, p1, d0, d1, _data_frame(data) if axis is None else _axis_frame(data, axis)


def _axis_frame(data: _Data, axis) -> _Frame:
    """:class:`_Frame` of a user-given ``axis`` array."""
    shape = data.n0.shape
    axis = _check_vec3("axis", axis).astype(data.n0.dtype)
    if not _is_tracer(axis) and not bool(jnp.all(safe_norm(axis) > 0)):
        raise ValueError("axis must be non-zero")
    u = _c.normalize(_c.split(jnp.broadcast_to(axis, shape + (3,))), fallback=_EX)
    return _make_frame(u, data)


def _data_frame(data: _Data) -> _Frame:
    """Data-driven axis: d0/|d0|, else d1/|d1|, else the chord direction, else x."""
    return _make_frame(data.axis, data)


def _make_frame(u, data: _Data) -> _Frame:
    """Frame for axis ``u`` (components). The second-branch direction ``m`` comes from the data
    (the part of ``(p1 - p0) + d1`` perpendicular to ``u``, smooth except where that part
    vanishes; then that of ``p1 - p0``, then of ``d1``) so that fixed angles stay
    rotation-covariant; only when all data are parallel to ``u`` is a fixed rule used."""
    d1, dp = data.d1, data.dp
    # the parts of the data vectors perpendicular to u and the fixed rule's candidates, one kernel
    perp = lambda v: _c.sub(v, _c.scale(_c.dot(v, u), u))
    # (projected twice: one projection leaves rounding noise along u of eps |v|, which a part
    # of size sqrt(eps) |v| turns into a direction sqrt(eps) off the perpendicular)
    *vps, ua, ub = _c.checkpoint(*(perp(perp(v)) for v in (d1, dp, _c.add(dp, d1))),
                                 *_c.perpendicular_candidates(u))
    m = _c.unit_perpendicular(u, (ua, ub))
    # first data vector (in this order) with a part perpendicular to u: (p1 - p0) + d1, then
    # p1 - p0, then d1 (the sum cancels when d1 = -(p1 - p0), found by hypothesis)
    # A part is used when it is well above its rounding noise (eps of the data's scale): below
    # sqrt(eps) its direction is noise, and in float32 a part of 1e-8 made m parallel to u (the
    # curve then missed its end point by up to the chord). (The data have scale 1 or 0: a
    # negligible part is not normalised, so its gradient stays finite.)
    floor = jnp.sqrt(jnp.finfo(jnp.result_type(u[0])).eps)
    for vp in vps:
        ok = _c.norm(vp) > floor * data.scale
        m = _c.where(ok, _c.normalize(vp, floor=1e-18), m)
    return _Frame(*_c.checkpoint(u, _unit_fibre(u, _EX), m))


def _sample_axes(batch: tuple[int, ...], shape: tuple[int, ...], name: str = "t") -> int:
    """Number of sample axes (0 for a scalar, else 1) of parameters of ``shape`` evaluated on a
    curve batch ``batch``: the last axis of the parameters is the sample axis and the leading
    ones must broadcast against ``batch`` (``ValueError`` otherwise)."""
    if len(shape) == 0:
        return 0
    try:
        np.broadcast_shapes(tuple(batch), tuple(shape[:-1]))
    except ValueError:
        raise ValueError(
            f"{name} of shape {tuple(shape)} does not fit curves of batch shape {tuple(batch)}: the "
            f"last axis of {name} is the sample axis and its leading axes {tuple(shape[:-1])} must "
            f"broadcast against the batch shape; use shape (T,) for the same parameters on every "
            f"curve or ({''.join(f'{n}, ' for n in batch)}T) for per-curve parameters"
        ) from None
    return 1


def _is_tracer(x) -> bool:
    return any_traced(x)


# ------------------------------------------------------------------------------ the curve
class PHQuintic(eqx.Module):
    """A (batch of) spatial PH quintic(s) on ``t in [0, 1]`` in canonical form ``r' = A i A*``.

    Evaluation (:meth:`position`, :meth:`hodograph`, :meth:`quaternion_polynomial`,
    :meth:`speed`, :meth:`arc_length`, :meth:`parameter_at_length`, :meth:`curvature`,
    :meth:`torsion`, :meth:`rmf_angle`, :meth:`frame`, :meth:`frame_quaternion`): the last axis
    of ``t`` is the sample axis, its leading axes broadcast against the batch shape ``B``.
    ``t`` of shape ``(T,)`` evaluates every curve at the same ``T`` parameters, ``t`` of shape
    ``B + (T,)`` each curve at its own; both give ``B + (T,)`` (then ``(3,)``, ``(4,)`` or
    ``(3, 3)`` for vector / quaternion / frame values). A scalar ``t`` gives ``B``. For
    ``curves`` of batch ``(N,)``::

        t, points = phjax.sample(curves, 100)   # t: (N, 100)
        curves.curvature(t)                     # (N, 100)
        curves.frame(t, "rmf")                  # (N, 100, 3, 3)
        curves.position(jnp.linspace(0, 1, 5))  # (N, 5, 3)

    Leading axes that do not broadcast against ``B`` raise ``ValueError``.

    Attributes:
        A0, A1, A2: Bernstein coefficients of the quaternion polynomial ``A(t)``, shape ``(*B, 4)``.
        control_points: Bezier control points ``P0..P5``, shape ``(*B, 6, 3)``.
    """

    A0: Float[Array, "*batch 4"]
    A1: Float[Array, "*batch 4"]
    A2: Float[Array, "*batch 4"]
    control_points: Float[Array, "*batch 6 3"]

    # -------------------------------------------------------------- structural helpers
    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch shape ``B`` of the curve array."""
        return self.control_points.shape[:-2]

    @property
    def dtype(self):
        return self.control_points.dtype

    def _prep_t(self, t, name: str = "t"):
        """``(t, k)``: the parameters as an array and the number ``k`` (0 or 1) of sample axes
        to insert between the coefficients' batch and core axes (see the class docs)."""
        t = jnp.asarray(t, dtype=self.dtype)
        return t, _sample_axes(self.batch_shape, t.shape, name)

    def _ex(self, x, k: int, core: int):
        """Insert ``k`` singleton axes between the batch axes and the ``core`` trailing axes."""
        nb = x.ndim - core
        return x.reshape(x.shape[:nb] + (1,) * k + x.shape[nb:])

    def _power(self, k: int):
        """Power-basis position coefficients ``c0..c5`` with ``k`` parameter axes inserted."""
        cp = self.control_points
        if cp.size > _UNROLL_SIZE:
            c = jnp.einsum("jk,...kd->...jd", _M5.astype(self.dtype), cp)
        else:  # few curves: multiply-adds that fuse (a dot is a kernel of its own)
            pts = [cp[..., i, :] for i in range(6)]
            c = jnp.stack([sum((float(_M5[j, i]) * pts[i] for i in range(1, j + 1)),
                               float(_M5[j, 0]) * pts[0]) for j in range(6)], axis=-2)
        return self._ex(c, k, 2)

    def _A(self, t, k: int):
        a0, a1, a2 = (self._ex(a, k, 1) for a in (self.A0, self.A1, self.A2))
        s = 1 - t[..., None]
        tt = t[..., None]
        return a0 * s * s + 2 * a1 * s * tt + a2 * tt * tt

    def _dA(self, t, k: int):
        a0, a1, a2 = (self._ex(a, k, 1) for a in (self.A0, self.A1, self.A2))
        tt = t[..., None]
        return 2 * ((a1 - a0) * (1 - tt) + (a2 - a1) * tt)

    def _derivs(self, t, k: int):
        """r', r'', r''' from the preimage: ``r' = A i A*``, ``r'' = 2 vect(A i A'*)``,
        ``r''' = 2 vect(A' i A'* + A i A''*)`` (``A''`` constant). No position enters: from
        the control points the derivatives were differences of absolute points and lost digits
        with the curve's distance from the origin (13 % of the hodograph at 100 m in float32,
        and the torsion with it)."""
        a, da = self._A(t, k), self._dA(t, k)
        a0, a1, a2 = (self._ex(x, k, 1) for x in (self.A0, self.A1, self.A2))
        dda = jnp.broadcast_to(2 * (a0 - 2 * a1 + a2), da.shape)
        unit_i = jnp.array([0.0, 1.0, 0.0, 0.0], a.dtype)
        ai, dai = quat_mul(a, unit_i), quat_mul(da, unit_i)
        d1 = quat_mul(ai, quat_conj(a))[..., 1:]
        d2 = 2 * quat_mul(ai, quat_conj(da))[..., 1:]
        d3 = 2 * (quat_mul(dai, quat_conj(da)) + quat_mul(ai, quat_conj(dda)))[..., 1:]
        return d1, d2, d3

    # --------------------------------------------------------------------- evaluation
    @_jit_method
    def position(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T 3"]:
        """Curve points ``r(t)`` (Horner's rule on the power basis)."""
        t, k = self._prep_t(t)
        c = self._power(k)
        tt = t[..., None]
        acc = c[..., 5, :]
        for j in range(4, -1, -1):
            acc = acc * tt + c[..., j, :]
        return acc

    @_jit_method
    def hodograph(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T 3"]:
        """Derivative ``r'(t)`` with respect to the curve parameter."""
        t, k = self._prep_t(t)
        return self._derivs(t, k)[0]

    @_jit_method
    def quaternion_polynomial(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T 4"]:
        """The preimage ``A(t)`` (so that ``r'(t) = A(t) i A*(t)``)."""
        t, k = self._prep_t(t)
        return self._A(t, k)

    @_jit_method
    def speed(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T"]:
        """Parametric speed ``sigma(t) = |r'(t)| = |A(t)|^2`` (a quartic polynomial)."""
        t, k = self._prep_t(t)
        a = self._A(t, k)
        return dot_last(a, a)

    def _sigma_bern(self):
        a0, a1, a2 = self.A0, self.A1, self.A2
        dot = dot_last
        return jnp.stack(
            [dot(a0, a0), dot(a0, a1), (2 * dot(a1, a1) + dot(a0, a2)) / 3, dot(a1, a2), dot(a2, a2)],
            axis=-1,
        )

    @property
    def length(self) -> Float[Array, "*batch"]:
        """Total arc length ``L = (sigma0 + ... + sigma4) / 5``."""
        return sum_last(self._sigma_bern()) / 5

    def _arc_power(self, k: int):
        sig = self._sigma_bern()
        s_bern = jnp.concatenate([jnp.zeros_like(sig[..., :1]), jnp.cumsum(sig, axis=-1) / 5], -1)
        c = jnp.einsum("jk,...k->...j", _M5.astype(self.dtype), s_bern)
        return self._ex(c, k, 1)

    @_jit_method
    def arc_length(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T"]:
        """Exact arc length ``s(t) = int_0^t sigma`` (a quintic polynomial)."""
        t, k = self._prep_t(t)
        return _horner_scalar(self._arc_power(k), t)

    @_jit_method
    def parameter_at_length(
        self, s: Float[ArrayLike, "*#batch S"], num_iterations: int = 12
    ) -> Float[Array, "*batch S"]:
        """Inverse of :meth:`arc_length`: the parameter ``t`` with ``s(t) = s`` (clipped to
        ``[0, L]``; ``s <= 0`` gives exactly 0, ``s >= L`` exactly 1, and a curve of length 0
        gives 0).

        A 33-point inverse-interpolation table gives the start; then ``num_iterations``
        bracketed Newton steps (bisection when Newton leaves the bracket) converge to machine
        precision (1e-12 relative in float64). Fixed iteration count: jit-friendly.

        Raises:
            ValueError: ``num_iterations`` not an integer >= 0 (0: the table's start).
        """
        if isinstance(num_iterations, bool) or not isinstance(num_iterations, (int, np.integer)) \
                or num_iterations < 0:
            raise ValueError(f"num_iterations must be an integer >= 0, got {num_iterations!r}")
        s, k = self._prep_t(s, "s")
        c = self._arc_power(k)
        length = self.length.reshape(self.batch_shape + (1,) * k)
        shape = jnp.broadcast_shapes(self.batch_shape + (1,) * k, s.shape)
        return _invert_arclength(self, c, length, jnp.broadcast_to(s, shape), k, num_iterations)

    def _curv_parts(self, t, k):
        a = self._A(t, k)
        da = self._dA(t, k)
        sigma = dot_last(a, a)
        b = quat_mul(quat_conj(a), da)[..., 1:]
        return a, da, sigma, b

    @_jit_method
    def curvature(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T"]:
        """Curvature ``kappa = 2 sqrt(b_y^2 + b_z^2) / sigma^2`` with ``b = vect(A* A')``
        (0 where ``sigma = 0``)."""
        t, k = self._prep_t(t)
        sigma, bn2 = self._kappa_parts(t, k)
        return safe_div(2 * safe_sqrt(bn2), sigma)

    def _scale(self):
        """The curve's scale ``|A0|^2 + |A1|^2 + |A2|^2`` (a length: the hodograph's size)."""
        return sum(dot_last(a, a) for a in (self.A0, self.A1, self.A2))

    def _moving(self, speed, k: int):
        """Whether ``speed`` (at parameters with ``k`` sample axes) is above ``eps`` of the
        curve's :meth:`_scale`: below it (a cusp, a resting end) the derivatives are rounding
        noise."""
        return speed > jnp.finfo(self.dtype).eps * self._ex(self._scale()[..., None], k, 1)[..., 0]

    def _kappa_parts(self, t, k):
        """``(sigma, |vect(A* A')_yz|^2 / sigma^2)``: the curvature is ``2 sqrt(.) / sigma``.
        In units of the speed, as :meth:`torsion`: the raw quotient's backward pass divides by
        ``sigma^3``, which overflows near a resting end in float32 (NaN gradients from 1e-4 m
        on)."""
        _, _, sigma, b = self._curv_parts(t, k)
        bn = safe_div(b, sigma[..., None])
        return sigma, bn[..., 1] ** 2 + bn[..., 2] ** 2

    @_jit_method
    def torsion(self, t: Float[ArrayLike, "*#batch T"]) -> Float[Array, "*batch T"]:
        """Torsion ``tau = (r' x r'') . r''' / |r' x r''|^2`` with ``|r' x r''|^2 = sigma^2 rho``,
        ``rho = 4 (b_y^2 + b_z^2)``. 0 (gradient 0) where the curve is straight to rounding:
        ``max(|b_y|, |b_z|)`` at most ``8 eps (S + P)``, with ``S = |A0|^2 + |A1|^2 + |A2|^2``
        the curve's scale and ``P`` the largest control-point coordinate (the bending that
        rounding the data gives a straight segment far from the origin; there the osculating
        plane, and so the torsion, is noise: a straight 3 mm segment 1.6 m from the origin had
        torsions of 1e5-5e6 1/m). Near a cusp (speed below ``eps S``) the value is kept and
        its gradient is zero: the true gradient there overflows. NaN data gives NaN."""
        t, k = self._prep_t(t)
        _, _, sigma, b = self._curv_parts(t, k)
        derivs = self._derivs(t, k)
        # the bending that rounding the data alone gives a straight segment: eps relative to
        # its size and to its distance from the origin (the chord p1 - p0 is a difference of
        # absolute points)
        far = jnp.max(jnp.abs(self.control_points), axis=(-2, -1))
        noise = _STRAIGHT_NOISE * jnp.finfo(self.dtype).eps * (self._scale() + far)
        noise = self._ex(noise[..., None], k, 1)[..., 0]
        curved = jnp.maximum(jnp.abs(b[..., 1]), jnp.abs(b[..., 2])) > noise
        curved = curved | jnp.isnan(b[..., 1] + b[..., 2])  # NaN data: NaN, not 0

        def tau(sigma, b, derivs):
            # in units of the speed (each factor O(1) at any data scale: the quotient's backward
            # pass of the raw form divides by sigma^4 rho^2 ~ s^8, which overflows for tiny data)
            e1, e2, e3 = (safe_div(d, sigma[..., None]) for d in derivs)
            bn = safe_div(b, sigma[..., None])
            rho = 4 * (bn[..., 1] ** 2 + bn[..., 2] ** 2)
            return safe_div(dot_last(jnp.cross(e1, e2), e3), rho * sigma)

        # Near a cusp the torsion grows like 1/speed^2 and its gradient's intermediates
        # overflow (NaN): there the value is kept and the gradient is zero, the regular formula
        # seeing a well-conditioned stand-in (a unit helix).
        ok = self._moving(sigma, k) & curved
        okv = ok[..., None]
        helix = (jnp.array([1.0, 0.0, 1.0]), jnp.array([0.0, 1.0, 0.0]), jnp.array([-1.0, 0.0, 0.0]))
        regular = tau(jnp.where(ok, sigma, 1), jnp.where(okv, b, jnp.array([0.0, 1.0, 0.0], b.dtype)),
                      [jnp.where(okv, d, h.astype(d.dtype)) for d, h in zip(derivs, helix)])
        at_cusp = jnp.where(curved, lax.stop_gradient(tau(sigma, b, derivs)), 0)
        return jnp.where(ok, regular, at_cusp)

    @filter_jit
    def bending_energy(self, num_nodes: int = 64) -> Float[Array, "*batch"]:
        """Bending energy ``int kappa^2 ds = int kappa^2 sigma dt`` (Gauss-Legendre quadrature)."""
        x, w = _gauss_legendre(num_nodes)
        sig, bn2 = self._kappa_parts(jnp.asarray(x, self.dtype), 1)
        # kappa^2 sigma = 4 bn2 / sigma (one division: finite gradients near a resting end)
        return jnp.sum(safe_div(4 * bn2, sig) * w.astype(self.dtype), axis=-1)

    @_jit_method
    def rmf_angle(self, t: Float[ArrayLike, "*#batch T"], num_nodes: int = 16) -> Float[Array, "*batch T"]:
        """Rotation of the RMF normal plane relative to the ERF: ``theta(t) = -2 int_0^t b_x/sigma``
        (``theta(0) = 0``).

        Near a cusp (the speed dips to ``sigma_min`` at ``t*``) the integrand is a peak of width
        ``w = sqrt(2 sigma_min / sigma''(t*))`` and area up to ``pi``, which a fixed rule misses
        (24 Gauss nodes: 124 degrees off at a speed ratio of 5e-5). The integral is therefore a
        composite Gauss-Legendre rule (``num_nodes`` per panel) on panels graded geometrically
        from ``t*``: ``[t* - w, t* + w]``, then ``t* +- w 2^j`` out to the ends (28 levels),
        where every panel is as wide as its distance to the peak, and the uniform panels
        ``[i/16, (i+1)/16]`` (a second, wider dip). Measured against adaptive quadrature
        (``scipy.integrate.quad``, float64): 3e-12 rad at that speed ratio (4e-9 with 12 nodes
        per panel, 1e-7 with 10) and below 1e-11 on random curves.
        """
        t, k = self._prep_t(t)
        x, w = (jnp.asarray(a, self.dtype) for a in _gauss_legendre(num_nodes))

        def integrand(tn, axes):
            # b_x / sigma = vect(Ahat* A')_x / |A| with Ahat = A / |A|: one division by |A| at a
            # time. The quotient b_x / |A|^2 near a zero end derivative (|A|^2 ~ 1e-20 on the
            # panels graded towards it) had a backward pass through 1 / |A|^4, inf in float32
            a, da = self._A(tn, axes), self._dA(tn, axes)
            norm = safe_norm(a, keepdims=True)
            bx = quat_mul(quat_conj(safe_div(a, norm)), da)[..., 1]
            return safe_div(bx, norm[..., 0])

        edges = lax.stop_gradient(self._rmf_panels())  # (*B, P + 1)
        lo, hi = edges[..., :-1], edges[..., 1:]
        span = hi - lo
        panels = span * jnp.sum(integrand(lo[..., None] + span[..., None] * x, 2) * w, -1)
        cum = jnp.concatenate([jnp.zeros_like(panels[..., :1]), jnp.cumsum(panels, -1)], -1)
        # the panel holding t: the full panels before it, then a partial one
        e = self._ex(edges, k, 1)
        j = jnp.clip(jnp.sum(e[..., 1:-1] <= t[..., None], -1), 0, lo.shape[-1] - 1)
        e = jnp.broadcast_to(e, j.shape + e.shape[-1:])
        left = jnp.take_along_axis(e, j[..., None], -1)[..., 0]
        before = jnp.take_along_axis(jnp.broadcast_to(self._ex(cum, k, 1), e.shape),
                                     j[..., None], -1)[..., 0]
        part = (t - left) * jnp.sum(
            integrand(left[..., None] + (t - left)[..., None] * x, k + 1) * w, -1)
        return -2 * (before + part)

    def _rmf_panels(self):
        """Sorted panel edges ``(*B, 2 K + 17)`` in ``[0, 1]`` for :meth:`rmf_angle`: graded
        from the speed's minimum ``t*`` (65-point grid, then Newton on ``sigma'``) with the peak
        width ``w`` (clipped to ``[2^-K, 1/16]``), and the uniform edges ``i/16``."""
        levels = 28
        sig = jnp.einsum("jk,...k->...j", _M4.astype(self.dtype), self._sigma_bern())  # power
        d1 = sig[..., 1:] * jnp.arange(1, 5, dtype=self.dtype)
        d2 = d1[..., 1:] * jnp.arange(1, 4, dtype=self.dtype)
        grid = jnp.linspace(0, 1, 65, dtype=self.dtype)
        ts = grid[jnp.argmin(_horner4(sig[..., None, :], grid), -1)]
        for _ in range(4):
            g1, g2 = _horner3(d1, ts), _horner2(d2, ts)
            ts = jnp.clip(jnp.where(g2 > 0, ts - safe_div(g1, g2), ts), 0, 1)
        smin, g2 = _horner4(sig, ts), _horner2(d2, ts)
        width = jnp.where(g2 > 0, safe_sqrt(safe_div(2 * jnp.maximum(smin, 0), g2)), 1.0)
        width = jnp.clip(width, 2.0 ** -levels, 1 / 16)
        off = width[..., None] * 2.0 ** jnp.arange(levels, dtype=self.dtype)
        uniform = jnp.broadcast_to(jnp.linspace(0, 1, 17, dtype=self.dtype),
                                   ts.shape + (17,))  # (a wider dip elsewhere: 1/16 panels)
        edges = jnp.concatenate([ts[..., None] - off[..., ::-1], ts[..., None] + off, uniform], -1)
        return jnp.sort(jnp.clip(edges, 0, 1), axis=-1)

    @_jit_method
    def frame(self, t: Float[ArrayLike, "*#batch T"], kind: FrameKind = "rmf") -> Float[Array, "*batch T 3 3"]:
        """Adapted orthonormal frame with columns (tangent, normal, binormal).

        Arguments:
            t: curve parameters, shape ``(T,)``, ``batch + (T,)`` or scalar (see the class docs).
            kind: ``"euler_rodrigues"`` (ERF, rational, orientation ``A/|A|``), ``"rmf"``
                (rotation-minimising: the ERF turned about the tangent by :meth:`rmf_angle`, equal
                to the ERF at ``t = 0``) or ``"frenet"`` (undefined where ``kappa = 0``: there the
                ERF normal is used; flips across inflections; at a zero of the speed, e.g. a
                resting end, its one-sided limit, the same from both sides: tangent
                ``h0/|h0|``, binormal along ``h0 x h1`` with ``h0 = A' i A'*``,
                ``h1 = (A' i A''* + A'' i A'*)/2``).

        Returns:
            Rotation matrices of shape ``(*batch, T, 3, 3)``.
        """
        return quat_to_matrix(self.frame_quaternion(t, kind)) if kind != "frenet" else self._frenet(t)

    @_jit_method
    def frame_quaternion(self, t: Float[ArrayLike, "*#batch T"], kind: FrameKind = "rmf") -> Float[Array, "*batch T 4"]:
        """The frame of :meth:`frame` as a unit quaternion ``wxyz``."""
        if kind not in ("frenet", "euler_rodrigues", "rmf"):
            raise ValueError(f"unknown frame kind {kind!r}; use 'frenet', 'euler_rodrigues' or 'rmf'")
        if kind == "frenet":
            from ..quaternion import quat_from_matrix

            return quat_from_matrix(self._frenet(t))
        t, k = self._prep_t(t)
        q = self._erf_quat(t, k)
        if kind == "rmf":
            th = self.rmf_angle(t)
            q = quat_mul(q, _qexp_i(th / 2))
        return q

    def _erf_quat(self, t, k):
        a = self._A(t, k)
        da = self._dA(t, k)
        sigma = dot_last(a, a, keepdims=True)
        return jnp.where(sigma > 0, quat_normalize(a), quat_normalize(da))

    def _binormal_at_zero(self, t, k):
        """``(h0 x h1, |h0| |h1|)``: the direction that ``r' x r''`` tends to at a zero ``t*``
        of ``A`` (a resting end, a cusp), and its scale.

        With ``A(t) = a s + c s^2``, ``s = t - t*``, ``a = A'(t*)``, ``c = A''/2``: ``r' = s^2 h0
        + s^3 h1 + O(s^4)`` and ``r'' = 2 s h0 + 3 s^2 h1 + O(s^3)`` with ``h0 = a i a*``,
        ``h1 = a i c* + c i a*``, so ``r' x r'' = s^4 h0 x h1 + O(s^5)`` on both sides of
        ``t*`` (``A'(t)`` stands for ``a``: the direction is then ``O(s)`` off)."""
        da = self._dA(t, k)
        a0, a1, a2 = (self._ex(x, k, 1) for x in (self.A0, self.A1, self.A2))
        h0, h1 = _sandwich_i(da, da), _sym_i(da, jnp.broadcast_to(a0 - 2 * a1 + a2, da.shape))
        return jnp.cross(h0, h1), safe_norm(h0, keepdims=True) * safe_norm(h1, keepdims=True)

    def _frenet(self, t):
        t, k = self._prep_t(t)
        erf = quat_to_matrix(self._erf_quat(t, k))
        d1, d2, _ = self._derivs(t, k)
        tangent = erf[..., :, 0]
        # r' x r'', or at a speed below eps of the curve's scale (a resting end, a cusp: there
        # r' and r'' are rounding noise) its limit direction (the ERF's tangent is the limit
        # of r'/|r'| there)
        moving = self._moving(safe_norm(d1), k)[..., None]
        at_zero, zero_scale = self._binormal_at_zero(t, k)
        bvec = jnp.where(moving, jnp.cross(d1, d2), at_zero)
        # the part perpendicular to the tangent in use (the ERF's)
        bvec = bvec - dot_last(bvec, tangent, keepdims=True) * tangent
        nb = safe_norm(bvec, keepdims=True)
        # relative threshold: |r' x r''| tiny compared with |r'||r''| means kappa ~ 0 (there
        # the ERF's binormal is used)
        scale = jnp.where(moving, safe_norm(d1, keepdims=True) * safe_norm(d2, keepdims=True),
                          zero_scale)
        ok = nb > 1e-12 * scale
        binormal = jnp.where(ok, bvec / jnp.where(ok, nb, 1), erf[..., :, 2])
        normal = jnp.cross(binormal, tangent)
        return jnp.stack([tangent, normal, binormal], axis=-1)


def _horner_scalar(c, t):
    acc = c[..., 5]
    for j in range(4, -1, -1):
        acc = acc * t + c[..., j]
    return acc


def _invert_arclength(curve: PHQuintic, c, length, s, k, num_iterations):
    dtype = curve.dtype
    s = jnp.clip(s, 0, length)
    # coarse table for the starting guess
    grid = jnp.linspace(0, 1, _TABLE + 1, dtype=dtype)
    table = _horner_scalar(curve._arc_power(0)[..., None, :], grid)  # (*B, 17)
    tab = table.reshape(curve.batch_shape + (1,) * k + (_TABLE + 1,))
    # piecewise-linear inverse interpolation of the monotone table
    sb = s
    tb = jnp.broadcast_to(tab, s.shape + (_TABLE + 1,))
    j = jnp.clip(jnp.sum(tb[..., 1:-1] <= sb[..., None], axis=-1), 0, _TABLE - 1)
    lo_s = jnp.take_along_axis(tb, j[..., None], -1)[..., 0]
    hi_s = jnp.take_along_axis(tb, (j + 1)[..., None], -1)[..., 0]
    lo_t = j.astype(dtype) / _TABLE
    frac = jnp.clip(safe_div(sb - lo_s, hi_s - lo_s, 0.5), 0, 1)
    # at an end where the speed vanishes (resting head) s(t) grows like t^3: invert that model
    sig_end = curve._sigma_bern()
    rest0 = (sig_end[..., 0] <= 1e-6 * sig_end.max(axis=-1)).reshape(curve.batch_shape + (1,) * k)
    rest1 = (sig_end[..., 4] <= 1e-6 * sig_end.max(axis=-1)).reshape(curve.batch_shape + (1,) * k)
    frac = jnp.where((j == 0) & rest0, _cube_root(frac), frac)
    frac = jnp.where((j == _TABLE - 1) & rest1, 1 - _cube_root(1 - frac), frac)
    t = lo_t + frac / _TABLE
    lo, hi = lo_t, lo_t + 1 / _TABLE
    sig_c = curve._sigma_bern()
    sig_p = jnp.einsum("jk,...k->...j", _M4.astype(dtype), sig_c)
    sig_p = sig_p.reshape(curve.batch_shape + (1,) * k + (5,))

    def newton(_, carry):
        # Newton step, bisection when it would leave the bracket
        t, lo, hi = carry
        f = _horner_scalar(c, t) - sb
        lo = jnp.where(f < 0, t, lo)
        hi = jnp.where(f > 0, t, hi)
        sig = _horner4(sig_p, t)
        tn = t - safe_div(f, sig, 0.0)
        bad = (tn < lo) | (tn > hi) | (sig <= 0)
        return jnp.where(f == 0, t, jnp.where(bad, (lo + hi) / 2, tn)), lo, hi

    lo, hi = jnp.broadcast_to(lo, t.shape), jnp.broadcast_to(hi, t.shape)
    t, _, _ = jax.lax.fori_loop(0, num_iterations, newton, (t, lo, hi))
    # the ends exactly: the polynomial's s(1) and `length` differ by rounding, and where the
    # speed vanishes at an end (s(t) ~ (1 - t)^3) that rounding put t = L at 1 - eps^(1/3)
    # (0.9968 in float32, 0.999995 in float64); s <= 0 wins (a point curve gives 0)
    return jnp.where(s <= 0, 0, jnp.where(s >= length, 1, t)).astype(dtype)


def _cube_root(x):
    """x^(1/3) for x in [0, 1] (exp/log: much cheaper than cbrt on XLA:CPU)."""
    pos = x > 0
    return jnp.where(pos, jnp.exp(jnp.log(jnp.where(pos, x, 1)) / 3), 0)


def _horner2(c, t):
    return c[..., 0] + t * (c[..., 1] + t * c[..., 2])


def _horner3(c, t):
    acc = c[..., 3]
    for j in range(2, -1, -1):
        acc = acc * t + c[..., j]
    return acc


def _horner4(c, t):
    acc = c[..., 4]
    for j in range(3, -1, -1):
        acc = acc * t + c[..., j]
    return acc


# ------------------------------------------------------------------------- construction
def _ends(p0, p1, d0, d1, frame: _Frame):
    """End coefficients ``A0``, ``A2`` at ``phi0 = phi2 = 0`` (arrays ``(..., 4)``)."""
    data = _data(p0, p1, d0, d1)
    return tuple(_c.stack(_c.scale(data.root, a)) for a in _ends_c(data, frame))


def _ends_c(data: _Data, frame: _Frame, *more):
    """:func:`_ends` on components, and the component tuples ``more`` (one kernel)."""
    return _c.checkpoint(*(frame.fib_unit(n, data.unit(k, frame.u))
                           for k, n in enumerate((data.n0, data.n1))), *more)


def near_optimal_angles(
    p0: Float[ArrayLike, "*batch 3"],
    p1: Float[ArrayLike, "*batch 3"],
    d0: Float[ArrayLike, "*batch 3"],
    d1: Float[ArrayLike, "*batch 3"],
    *,
    axis: Float[ArrayLike, "*batch 3"] | None = None,
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """The closed-form near-optimal free angles ("CC" choice of Farouki et al. 2008).

    ``beta = phi2 - phi0`` makes ``v(beta) = A0 u A2* + A2 u A0* = e cos(beta) + f sin(beta)``
    point along ``w = 3(p1 - p0) - (d0 + d1)`` (least-squares coefficients of ``w`` in the basis
    ``e, f``, Tikhonov-regularised by ``0.1 tr(G)/2`` so that the choice is continuous at aligned
    tangents where the published rule jumps; the plane of ``v`` is orthogonal to
    ``d1/|d1| - d0/|d0|``, so the projection of the published rule is implicit); then ``alpha = (phi0 + phi2)/2`` minimises
    ``|A1 - (A0 + A2)/2|^2`` (zero exactly when the quintic is a degree-elevated PH cubic), with
    ``phi1 = 0``. The rule is geometric: the resulting curve does not depend on ``axis``.
    Helix test of the note: deviation 2.8e-4 at h = 0.8 and 6.5e-9 at h = 0.05 (order 4).
    Known limit: equal end derivatives ``d0 = d1 = d`` with ``(3 (p1 - p0) - 2 d) . d < 0``
    leave ``alpha`` undetermined; the rule then picks one member by a fixed convention, which is
    not rotation-covariant (fixed angles are).

    Arguments:
        p0, p1: end points; d0, d1: end derivatives ``r'(0)``, ``r'(1)``.
        axis: construction axis (default: the data-driven axis, see module docs).

    Returns:
        ``(phi0, phi2)`` in the convention of :func:`hermite_quintic` with the same ``axis``.
    """
    return _near_optimal_jit(*(jnp.asarray(x) for x in (p0, p1, d0, d1)), axis)


@jit
def _near_optimal_jit(p0, p1, d0, d1, axis):
    data = _data(*_validate(p0, p1, d0, d1))
    dframe = _data_frame(data)
    frame = None if axis is None else _axis_frame(data, axis)
    return _cc_angles_c(data, dframe, _cc_inputs(data, dframe), frame)


def _cc_angles(p0, p1, d0, d1, frame=None):
    """:func:`_cc_angles_c` on arrays ``(..., 3)``."""
    data = _data(p0, p1, d0, d1)
    dframe = _data_frame(data)
    return _cc_angles_c(data, dframe, _cc_inputs(data, dframe), frame)


def _cc_inputs(data: _Data, dframe: _Frame):
    """``(a0, a2, e, f)`` of :func:`_cc_angles_c` (one kernel): the end coefficients in the
    data-driven frame ``dframe`` (its ``_ends_c``) and the basis ``e``, ``f`` of ``v(beta)``."""
    u = dframe.u
    # With u = d0/|d0| we have Q(d0) = u (a pure quaternion), so e = 2s vect(Q1) and
    # f = 2s vect(u Q1*); on the bisector branch f = -2s u x (d1hat - u) / |d1hat + u|, written so
    # that it is exactly 0 for aligned tangents (no rounding noise to amplify). When d0 = 0, s = 0.
    d1hat = data.unit(1, u)
    q1 = _unit_fibre(d1hat, u, dframe.m)
    s2 = 2 * safe_sqrt(data.n0 * data.n1)
    e = _c.scale(s2, q1[1:])
    main = _c.dot(d1hat, u) > -0.5
    den = jnp.maximum(_c.norm(_c.add(d1hat, u)), 1.0)
    f_main = tuple(-x / den for x in _c.cross(u, _c.sub(d1hat, u)))
    f_alt = _c.qmul((0.0,) + u, _c.qconj(q1))[1:]
    f = _c.scale(s2, _c.where(main, f_main, f_alt))
    return _ends_c(data, dframe, e, f)


def _cc_angles_c(data: _Data, dframe: _Frame, inputs, frame: _Frame | None = None):
    """CC angles in the convention of ``frame`` (``None``: the data-driven convention), on
    components (one kernel); ``dframe`` is ``_data_frame(data)`` and ``inputs`` its
    :func:`_cc_inputs`.

    They are computed in the data-driven convention (``u = d0/|d0|``), where ``e`` and ``f`` below
    have closed forms without cancellation (``f`` is exactly 0 for aligned tangents), and then
    converted to ``frame``'s convention when that differs.
    """
    # v(beta) = A0 u A2* + A2 u A0* = e cos(beta) + f sin(beta), an ellipse in the plane
    # orthogonal to m = (d1/|d1| - d0/|d0|)/|...|, so the note's projection of w along m is
    # implicit. beta puts v(beta) along w = 3(p1 - p0) - (d0 + d1): the coefficients of w in the
    # basis (e, f) by regularised least squares, (G + lam tr(G)/2 I)^-1 (e.w, f.w) with the Gram
    # matrix G. lam = 0 is the published rule ((w.f)/|f|^2, (w.e)/|e|^2 when e is orthogonal to
    # f); it is discontinuous at aligned tangents (|f| -> 0; measured: a 1e-7 change of the data
    # moved the curve by 0.065), the common case in tracking. lam = 0.1 makes it continuous and
    # is better on real data (TUM fr1_desk at 33 Hz: median bending energy 1.0000003 x the
    # grid-search optimum, against 1.010 for lam = 0), equal on random data (median 1.015 x).
    # The regularisation is invariant under the angle convention, so the curve is geometric.
    # e and f: see _cc_inputs.
    a0, a2, e, f = inputs
    w, dot = data.w, _c.dot
    gee, gff, gef = dot(e, e), dot(f, f), dot(e, f)
    be, bf = dot(e, w), dot(f, w)
    # w orthogonal to the plane of v (all data on one line): beta is undetermined and (be, bf)
    # are rounding noise, which would pick it (and the curve's shape) by the order of the
    # arithmetic; exact zeros pick beta = 0 whatever the orientation of the data
    noise2 = (64 * float(jnp.finfo(gee.dtype).eps)) ** 2 * dot(w, w) * (gee + gff)  # squared
    line = (be * be <= noise2) & (bf * bf <= noise2)
    be, bf = jnp.where(line, 0, be), jnp.where(line, 0, bf)
    reg = _CC_REGULARISATION * (gee + gff) / 2
    beta = safe_atan2((gee + reg) * bf - gef * be, (gff + reg) * be - gef * bf)
    # alpha minimises F = |A1 - (A0 + A2)/2|^2 = |B - 5 c exp(alpha i)|^2 / 16 with
    # c = a0 exp(-beta i/2) + a2 exp(beta i/2): maximise <B, c exp(alpha i)>.
    half = beta / 2
    a0b = _c.qmul_exp_i(a0, -half)
    a2b = _c.qmul_exp_i(a2, half)
    g = _closing_data(data, a0b, a2b)
    bq = dframe.fib_c(g)
    c = _c.add(a0b, a2b)
    alpha = safe_atan2(dot(bq, _c.qmul_i(c)), dot(bq, c))
    phi0, phi2 = alpha - half, alpha + half
    if frame is None:
        return tuple(x[0] for x in _c.checkpoint((phi0,), (phi2,)))
    # convert to frame's convention: the same curve has B_frame = B_data exp(gamma i)
    A0 = _c.qmul_exp_i(a0, phi0)
    A2 = _c.qmul_exp_i(a2, phi2)
    ph = _c.qmul(_c.qconj(bq), frame.fib_c(g))
    gamma = safe_atan2(ph[1], ph[0])
    t0, t2 = _ends_c(data, frame)
    q0 = _c.qmul(_c.qconj(t0), _c.qmul_exp_i(A0, gamma))
    q2 = _c.qmul(_c.qconj(t2), _c.qmul_exp_i(A2, gamma))
    phi0, phi2 = safe_atan2(q0[1], q0[0]), safe_atan2(q2[1], q2[0])
    return tuple(x[0] for x in _c.checkpoint((phi0,), (phi2,)))


def _closing_data(data: _Data, A0, A2):
    """``g = 120 (p1 - p0) - 15 (d0 + d1) + 5 (A0 i A2* + A2 i A0*)`` (components, one kernel),
    so that the closing quaternion ``B = 3 A0 + 4 A1 + 3 A2`` solves ``B i B* = g``."""
    return _c.checkpoint(tuple(a + 5 * b for a, b in zip(data.g0, _c.sym_i(A0, A2))))[0]


def hermite_quintic(
    p0: Float[ArrayLike, "*batch 3"],
    p1: Float[ArrayLike, "*batch 3"],
    d0: Float[ArrayLike, "*batch 3"],
    d1: Float[ArrayLike, "*batch 3"],
    phi0: Float[ArrayLike, "*batch"] | None = None,
    phi2: Float[ArrayLike, "*batch"] | None = None,
    *,
    phi1: Float[ArrayLike, "*batch"] = 0.0,
    axis: Float[ArrayLike, "*batch 3"] | None = None,
) -> PHQuintic:
    """First-order Hermite PH quintic interpolant on ``t in [0, 1]``.

    ``r(0) = p0``, ``r(1) = p1``, ``r'(0) = d0``, ``r'(1) = d1``. For a segment spanning physical
    time ``[Ta, Tb]`` pass velocities times ``(Tb - Ta)`` as ``d0``, ``d1``.

    Arguments:
        p0, p1: end points, shape ``(*batch, 3)`` (broadcast together).
        d0, d1: end derivatives, shape ``(*batch, 3)``.
        phi0, phi2: free angles (rad) of ``A0`` and ``A2`` relative to the construction axis
            (see the module docs). Both ``None`` (default): the near-optimal closed-form choice
            of :func:`near_optimal_angles`.
        phi1: angle of the closing quaternion (redundant: a common shift of all three angles
            leaves the curve unchanged). Default 0.
        axis: reference axis ``u`` (default: ``d0/|d0|`` with fallbacks; ``[1, 0, 0]`` reproduces
            the classical ``u = i`` convention, e.g. the paper's ``phi0 = phi2 = -pi/2``).

    Returns:
        A :class:`PHQuintic` with batch shape ``batch``.

    Values and gradients are finite for zero, tiny and antiparallel data in float32 and
    float64: an end derivative below ``eps^1.5`` of the data's scale
    ``|p1 - p0| + |d0| + |d1|`` is treated as zero (the curve moves by at most about
    ``eps^0.75`` of that scale), data of scale below ``tiny^(1/4)`` give the constant curve, and
    NaN data give a NaN curve.
    """
    if (phi0 is None) != (phi2 is None):
        raise ValueError("give both phi0 and phi2, or neither (for the near-optimal default)")
    p0, p1, d0, d1 = (jnp.asarray(x) for x in (p0, p1, d0, d1))
    if axis is not None:
        axis = _check_vec3("axis", axis)
        if not _is_tracer(axis) and not bool(jnp.all(safe_norm(axis) > 0)):
            raise ValueError("axis must be non-zero")
    return _hermite_jit(p0, p1, d0, d1, phi0, phi2, phi1, axis)


def _hermite_impl(p0, p1, d0, d1, phi0, phi2, phi1, axis) -> PHQuintic:
    p0, p1, d0, d1 = (_check_vec3(n, x) for n, x in zip(("p0", "p1", "d0", "d1"), (p0, p1, d0, d1)))
    shapes = [x.shape[:-1] for x in (p0, p1, d0, d1)]
    shapes += [jnp.shape(x) for x in (phi0, phi1, phi2) if x is not None]
    try:
        batch = jnp.broadcast_shapes(*shapes)
    except ValueError as err:
        raise ValueError(f"hermite_quintic: batch shapes do not broadcast: {shapes}") from err
    p0, p1, d0, d1 = (jnp.broadcast_to(x, batch + (3,)) for x in (p0, p1, d0, d1))
    p0, p1, d0, d1 = _validate(p0, p1, d0, d1)
    dtype = p0.dtype
    data = _data(p0, p1, d0, d1)
    frame = _data_frame(data) if axis is None else _axis_frame(data, axis)
    ends = None
    if phi0 is None:
        dframe = frame if axis is None else _data_frame(data)
        inputs = _cc_inputs(data, dframe)  # with the ends in the data-driven frame
        phi0, phi2 = _cc_angles_c(data, dframe, inputs, None if axis is None else frame)
        if axis is None:
            ends = inputs[:2]
    phi0, phi1, phi2 = (jnp.broadcast_to(jnp.asarray(x, dtype), batch) for x in (phi0, phi1, phi2))
    a0, a2 = _ends_c(data, frame) if ends is None else ends
    A0 = _c.qmul_exp_i(a0, phi0)
    A2 = _c.qmul_exp_i(a2, phi2)
    B = frame.fib_c(_closing_data(data, A0, A2), phi1)
    A1 = tuple(b / 4 - 3 * (x + y) / 4 for b, x, y in zip(B, A0, A2))
    A0, A1, A2 = (_c.scale(data.root, a) for a in (A0, A1, A2))  # back to the data's scale
    return _from_coefficients_c(_c.split(p0), A0, A1, A2)


_hermite_jit = jit(_hermite_impl)


def _from_coefficients(p0, A0, A1, A2) -> PHQuintic:
    """The curve of ``p0 (..., 3)`` and the quaternion coefficients ``A0, A1, A2 (..., 4)``."""
    return _from_coefficients_c(*(_c.split(x) for x in (p0, A0, A1, A2)))


def _from_coefficients_c(p0, A0, A1, A2) -> PHQuintic:
    """:func:`_from_coefficients` on components."""
    # the coefficients are outputs and feed every control point: one kernel computes them
    arrays = lax.optimization_barrier(tuple(_c.stack(a) for a in (A0, A1, A2)))
    A0, A1, A2 = (_c.split(a) for a in arrays)
    sym, sw = _c.sym_i, _c.sandwich_i
    h0 = sw(A0, A0)
    h1 = tuple(x / 2 for x in sym(A0, A1))
    h2 = tuple((x + 4 * y) / 6 for x, y in zip(sym(A0, A2), sw(A1, A1)))
    h3 = tuple(x / 2 for x in sym(A1, A2))
    h4 = sw(A2, A2)
    # control points P_{k+1} = P_k + h_k / 5 as running sums (elementwise adds fuse; a cumsum
    # is a kernel of its own)
    pts = [p0]
    for h in (h0, h1, h2, h3, h4):
        pts.append(tuple(p + x / 5 for p, x in zip(pts[-1], h)))
    cp = jnp.stack([_c.stack(p) for p in pts], axis=-2)
    return PHQuintic(*arrays, control_points=cp)
