"""Rigid (and similarity) alignment of matched 3-D point sets, with a RANSAC front end.

Given matched points ``source[i] -> target[i]`` with weights ``w[i] >= 0``, :func:`align` finds
the rotation ``R``, translation ``t`` and (optionally) scale ``s`` minimising

    ``sum_i w_i |s R source_i + t - target_i|^2``

(the weighted problem of Umeyama, IEEE TPAMI 1991; with ``s = 1`` it is the Kabsch / Wahba
problem). :func:`ransac_align` wraps it in a fixed-budget, fully vectorised RANSAC loop for
landmark sets with gross outliers.

Method
------
After removing the weighted centroids, the optimal rotation maximises ``tr(R H)`` with the
cross-covariance ``H = sum_i w_i x_i y_i^T`` (``x``, ``y`` the centred source / target points).
We compute it with **Horn's quaternion method** (JOSA A 1987): ``q^T N(H) q = tr(R(q) H)`` for a
symmetric traceless 4x4 matrix ``N(H)``, so the optimal unit quaternion is the eigenvector of the
largest eigenvalue ``lambda_1`` of ``N`` (``jnp.linalg.eigh``). Compared with the SVD route
(``R = V diag(1, 1, det) U^T``) this

* always yields a proper rotation; the reflection correction is built in (the eigenvalues of
  ``N`` are ``+-sigma_1 +- sigma_2 +- d sigma_3`` with ``d = sign det H``, and ``lambda_1`` is
  exactly Umeyama's optimum ``sigma_1 + sigma_2 + d sigma_3``), and
* has a gradient that only depends on the gap ``lambda_1 - lambda_2 = 2 (sigma_2 + d sigma_3)``.
  That gap stays positive at symmetric configurations (regular tetrahedron, square, exactly
  aligned identical sets) where singular values of ``H`` repeat and the SVD's gradient contains
  ``1 / (sigma_i^2 - sigma_j^2)`` and becomes NaN.

JAX's own ``eigh`` derivative still couples *all* eigenvector pairs, so repeated *lower*
eigenvalues (e.g. ``3c, -c, -c, -c`` for a tetrahedron) would give ``0 * inf = NaN`` in reverse
mode. We therefore wrap ``eigh`` in a ``custom_jvp`` whose coupling coefficients
``1 / (lambda_j - lambda_i)`` are set to 0 for numerically equal eigenvalues; the coupling of
the top eigenvector to the others is exact whenever its eigenvalue is simple, which is the
``OK`` status condition below. The rule is recursive, so higher derivatives use it too.

The singular values of ``H`` (``jnp.linalg.svd``, no gradient) are used only to detect
degenerate configurations. The scale is ``s = lambda_1 / sum_i w_i |x_i|^2`` and the
translation ``t = ybar - s R xbar``.

All sums, residuals and RANSAC inlier tests are evaluated relative to one usable point of each
set (the first of largest weight; the origin does not change the optimum, and the derivatives
stay exact), so a large common offset costs no accuracy beyond the rounding of the inputs
themselves: a 10 cm cloud 1e4 m from the origin in ``float32`` gives a rotation to about 1e-6
rad (6.5e-5 rad with the sums taken in the caller's frame, and RANSAC lost its inliers).

Missing data and status codes
-----------------------------
Rows with a non-finite source/target coordinate or weight, and rows with weight ``<= 0``, are
*unusable* and are ignored (treated as weight 0: missing landmarks never poison the result,
also when a zero-weight row holds a huge finite placeholder such as ``1e20`` or the ``float32``
maximum).
The solver never raises inside ``jit``; it reports a status code (:class:`AlignmentStatus`),
checked in this order:

* ``NOT_FINITE`` (3): the input contained non-finite values **and** fewer than 3 usable points
  remain (the missing values are what makes the problem unsolvable; e.g. NaN everywhere).
* ``TOO_FEW_POINTS`` (1): fewer than 3 usable points (e.g. 2 points, or all weights zero).
* ``DEGENERATE`` (2): the rotation is not determined: ``sigma_1 = 0`` (coincident points or zero
  total weight), ``sigma_2 <= rtol sigma_1`` (collinear points), or the top eigenvalue of ``N``
  is not simple, ``lambda_1 - lambda_2 = 2 (sigma_2 + d sigma_3) <= rtol sigma_1`` (a continuum
  of optimal rotations, e.g. the mirror image of a regular tetrahedron). ``rtol`` defaults to ``sqrt(eps)`` of the
  dtype: below it the rotation would be determined to worse than ``sqrt(eps)`` anyway.
* ``TOO_FEW_INLIERS`` (4, RANSAC only): the best hypothesis has fewer than 3 inliers.

For any non-``OK`` status the returned transform is the identity (``R = I``, ``t = 0``,
``s = 1``). Values and gradients are finite for every input (double-``where`` guards).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .._misc import safe_div, safe_norm, safe_sqrt
from ..quaternion import quat_to_matrix

__all__ = [
    "AlignmentStatus",
    "AlignmentResult",
    "align",
    "ransac_align",
    "transform_points",
    "OK",
    "TOO_FEW_POINTS",
    "DEGENERATE",
    "NOT_FINITE",
    "TOO_FEW_INLIERS",
]

OK = 0
TOO_FEW_POINTS = 1
DEGENERATE = 2
NOT_FINITE = 3
TOO_FEW_INLIERS = 4


class AlignmentStatus:
    """Integer status codes of :class:`AlignmentResult` (plain ``int`` constants)."""

    OK = OK
    TOO_FEW_POINTS = TOO_FEW_POINTS
    DEGENERATE = DEGENERATE
    NOT_FINITE = NOT_FINITE
    TOO_FEW_INLIERS = TOO_FEW_INLIERS

    names = ("OK", "TOO_FEW_POINTS", "DEGENERATE", "NOT_FINITE", "TOO_FEW_INLIERS")

    @classmethod
    def name(cls, code: int) -> str:
        """Name of a (concrete) status code, e.g. ``AlignmentStatus.name(2) == "DEGENERATE"``."""
        return cls.names[int(code)]


class AlignmentResult(eqx.Module):
    """Result of :func:`align` / :func:`ransac_align` (a PyTree; batch shape ``*b``).

    The transform maps source points to target points: ``target ~ scale * rotation @ p +
    translation``. For a non-``OK`` status it is the identity.

    Attributes:
        rotation: rotation matrices, ``(*b, 3, 3)``.
        quaternion: the same rotations as unit quaternions ``wxyz`` with ``w >= 0``, ``(*b, 4)``.
        translation: ``(*b, 3)``.
        scale: ``(*b,)``; 1 unless ``with_scale=True``.
        rms: weighted RMS residual ``sqrt(sum w r^2 / sum w)`` of the returned transform over
            the points of ``inlier_mask`` (0 when the mask is empty), ``(*b,)``.
        num_inliers: number of points in ``inlier_mask``, ``(*b,)``.
        inlier_mask: :func:`align`: the usable (finite, positive-weight) points;
            :func:`ransac_align`: the usable points within ``threshold`` of the returned
            transform (for a non-``OK`` status: the best hypothesis' inliers), ``(*b, n)``.
        status: :class:`AlignmentStatus` codes, ``(*b,)``.
    """

    rotation: Float[Array, "*b 3 3"]
    quaternion: Float[Array, "*b 4"]
    translation: Float[Array, "*b 3"]
    scale: Float[Array, "*b"]
    rms: Float[Array, "*b"]
    num_inliers: Int[Array, "*b"]
    inlier_mask: Bool[Array, "*b n"]
    status: Int[Array, "*b"]

    @property
    def ok(self) -> Bool[Array, "*b"]:
        """``status == OK``."""
        return self.status == OK


# ----------------------------------------------------------------------- safe eigendecomposition
@jax.custom_jvp
def _safe_eigh(n: Float[Array, "*b k k"]) -> tuple[Float[Array, "*b k"], Float[Array, "*b k k"]]:
    """``jnp.linalg.eigh`` (ascending) whose derivative ignores couplings of equal eigenvalues."""
    lam, v = jnp.linalg.eigh(n)
    return lam, v


@_safe_eigh.defjvp
def _safe_eigh_jvp(primals, tangents):
    (n,), (dn,) = primals, tangents
    lam, v = _safe_eigh(n)
    dn = (dn + jnp.swapaxes(dn, -1, -2)) / 2
    vt_dn_v = jnp.swapaxes(v, -1, -2) @ dn @ v
    dlam = jnp.diagonal(vt_dn_v, axis1=-2, axis2=-1)
    diff = lam[..., None, :] - lam[..., :, None]  # diff[i, j] = lam_j - lam_i
    eps = jnp.finfo(lam.dtype).eps
    tol = 8 * eps * jnp.max(jnp.abs(lam), axis=-1)[..., None, None]
    distinct = jnp.abs(diff) > tol
    f = jnp.where(distinct, 1 / jnp.where(distinct, diff, 1), 0)
    dv = v @ (f * vt_dn_v)
    return (lam, v), (dlam, dv)


def _horn_matrix(h: Float[Array, "*b 3 3"]) -> Float[Array, "*b 4 4"]:
    """Horn's symmetric 4x4 matrix with ``q^T N q = tr(R(q) h)`` for ``h = sum x y^T``."""
    sxx, sxy, sxz = h[..., 0, 0], h[..., 0, 1], h[..., 0, 2]
    syx, syy, syz = h[..., 1, 0], h[..., 1, 1], h[..., 1, 2]
    szx, szy, szz = h[..., 2, 0], h[..., 2, 1], h[..., 2, 2]
    a, b, c = syz - szy, szx - sxz, sxy - syx
    rows = [
        [sxx + syy + szz, a, b, c],
        [a, sxx - syy - szz, sxy + syx, szx + sxz],
        [b, sxy + syx, -sxx + syy - szz, syz + szy],
        [c, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


# ------------------------------------------------------------------------------ core solver
class _Fit(eqx.Module):
    rotation: Array
    quaternion: Array
    translation: Array
    scale: Array
    ok: Array


def _fit(src, tgt, w, with_scale: bool, rtol) -> _Fit:
    """Weighted closed-form fit on finite ``src``/``tgt`` with weights ``w >= 0`` (batched)."""
    dtype = src.dtype
    total = jnp.sum(w, axis=-1)
    has_w = total > 0
    total_safe = jnp.where(has_w, total, 1)[..., None]
    wn = w / total_safe  # normalised weights (sum 1, or all 0)
    mu_x = jnp.einsum("...n,...ni->...i", wn, src)
    mu_y = jnp.einsum("...n,...ni->...i", wn, tgt)
    # centred points divided by their largest coordinate if above 1 (the rotation does not
    # change, the scale is corrected below): the second moments cannot overflow (float32 ~1e19)
    xc = src - mu_x[..., None, :]
    yc = tgt - mu_y[..., None, :]
    mx, my = _max_abs(xc, wn), _max_abs(yc, wn)
    xc, yc = _bound_unused(xc / mx[..., None, None], wn), _bound_unused(yc / my[..., None, None], wn)
    h = jnp.einsum("...n,...ni,...nj->...ij", wn, xc, yc)
    var_x = jnp.einsum("...n,...ni,...ni->...", wn, xc, xc)

    # degeneracy tests on the (gradient-free) singular values: the Horn spectrum is
    # +-s1 +- s2 +- d s3 (d = sign det h), so its top gap is lambda_1 - lambda_2 = 2 (s2 + d s3)
    h_ng = jax.lax.stop_gradient(h)
    sv = jnp.linalg.svd(h_ng, compute_uv=False)  # descending
    det = jnp.sum(h_ng[..., 0, :] * jnp.cross(h_ng[..., 1, :], h_ng[..., 2, :]), axis=-1)
    d = jnp.where(det < 0, -1, 1).astype(dtype)
    s1, s2, s3 = sv[..., 0], sv[..., 1], sv[..., 2]
    gap = 2 * (s2 + d * s3)
    ok = has_w & (s1 > 0) & (s2 > rtol * s1) & (gap > rtol * s1)
    n_mat = _horn_matrix(h)

    # where-safe: a well-separated stand-in matrix (top eigenvector = identity quaternion)
    n_id = jnp.diag(jnp.asarray([1, 0, 0, 0], dtype))
    n_use = jnp.where(ok[..., None, None], n_mat, n_id)
    lam, vecs = _safe_eigh(n_use)
    lam1 = lam[..., 3]
    q = vecs[..., :, 3]
    q = jnp.where(q[..., :1] < 0, -q, q)
    ident = jnp.asarray([1, 0, 0, 0], dtype)
    q = jnp.where(ok[..., None], q, ident)
    rot = quat_to_matrix(q)
    if with_scale:
        scale = jnp.where(ok, safe_div(lam1, var_x, 1.0) * my / mx, 1.0).astype(dtype)
    else:
        scale = jnp.ones_like(lam1)
    t = mu_y - scale[..., None] * jnp.einsum("...ij,...j->...i", rot, mu_x)
    t = jnp.where(ok[..., None], t, 0)
    return _Fit(rot, q, t, scale, ok)


def _apply(rot, t, s, p):
    return s[..., None, None] * (p @ jnp.swapaxes(rot, -1, -2)) + t[..., None, :]


def _max_abs(x, w):
    """``max |x|`` over the rows with ``w > 0``, at least 1, without gradient: a divisor that
    only scales large values down (so no row, used or not, grows and overflows)."""
    m = jnp.max(jnp.where((w > 0)[..., None], jnp.abs(x), 0), axis=(-2, -1), initial=1)
    return jax.lax.stop_gradient(m)


def _bound_unused(x, w):
    """Clip the rows with ``w <= 0`` (ignored, but holding any finite value, e.g. a 1e20 or
    ``float32`` max placeholder) to ``+-2**(maxexp/4)``: their products with each other stay
    finite, so ``0 * x * y`` is 0 and never ``0 * inf = NaN``. Used rows (``|x| <= 1`` after
    :func:`_max_abs`) and the derivatives with respect to zero weights of all sensible rows
    are unchanged."""
    big = 2.0 ** (jnp.finfo(x.dtype).maxexp // 4)
    return jnp.where((w > 0)[..., None], x, jnp.clip(x, -big, big))


def _local_frame(src, tgt, w):
    """Coordinates relative to a usable point (the first of largest weight), without gradient.

    All sums, residuals and inlier tests are evaluated in these coordinates: with a large
    common offset (e.g. 1e4 m in ``float32``) the centroid and the residuals of the original
    coordinates lose the points' own resolution (measured: 6.5e-5 rad rotation error for a
    10 cm cloud at 1e4 m, and RANSAC inliers lost). Returns ``(src - ox, tgt - oy, ox, oy)``;
    the rotation and scale do not depend on the origins, and the translation in the caller's
    frame is :func:`_global_translation`, so all derivatives are exact.
    """
    idx = jnp.argmax(w, axis=-1)[..., None, None]
    ox = jax.lax.stop_gradient(jnp.take_along_axis(src, idx, axis=-2))
    oy = jax.lax.stop_gradient(jnp.take_along_axis(tgt, idx, axis=-2))
    # ignored rows (w = 0) bounded too: the derivatives with respect to their weights (which
    # grow with their distance) stay finite and do not turn every other derivative into NaN
    src_l, tgt_l = _bound_unused(src - ox, w), _bound_unused(tgt - oy, w)
    return src_l, tgt_l, ox[..., 0, :], oy[..., 0, :]


def _global_translation(rot, t, s, ox, oy, ok):
    """Translation of ``x -> s R x + t`` (fitted in :func:`_local_frame` coordinates) in the
    caller's frame: ``t + oy - s R ox``; 0 where not ``ok``."""
    tg = (oy - s[..., None] * jnp.einsum("...ij,...j->...i", rot, ox)) + t
    return jnp.where(ok[..., None], tg, 0)


def _weighted_rms(rot, t, s, src, tgt, w):
    r = _apply(rot, t, s, src) - tgt
    m = _max_abs(r, w)  # (no overflow in r^2)
    total = jnp.sum(w, axis=-1)
    r = _bound_unused(r / m[..., None, None], w)
    sse = jnp.einsum("...n,...ni,...ni->...", w, r, r)
    return m * safe_sqrt(safe_div(sse, total))


def _prepare(source, target, weights):
    """Validate shapes (outside jit), broadcast, and choose the floating dtype."""
    source, target = jnp.asarray(source), jnp.asarray(target)
    for name, x in (("source", source), ("target", target)):
        if x.ndim < 2 or x.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (..., n, 3), got shape {tuple(x.shape)}")
    if source.shape[-2] != target.shape[-2]:
        raise ValueError(
            f"source and target must hold the same number of points, got {source.shape[-2]} "
            f"and {target.shape[-2]}"
        )
    n = source.shape[-2]
    dtype = jnp.result_type(source.dtype, target.dtype, jnp.float32)
    weights = jnp.ones((n,), dtype) if weights is None else jnp.asarray(weights)
    if weights.ndim < 1 or weights.shape[-1] != n:
        raise ValueError(f"weights must have shape (..., {n}), got shape {tuple(weights.shape)}")
    try:
        batch = jnp.broadcast_shapes(source.shape[:-2], target.shape[:-2], weights.shape[:-1])
    except ValueError as e:
        raise ValueError(
            f"batch shapes do not broadcast: source {tuple(source.shape)}, target "
            f"{tuple(target.shape)}, weights {tuple(weights.shape)}"
        ) from e
    source = jnp.broadcast_to(source.astype(dtype), batch + (n, 3))
    target = jnp.broadcast_to(target.astype(dtype), batch + (n, 3))
    weights = jnp.broadcast_to(weights.astype(dtype), batch + (n,))
    return source, target, weights, dtype


def _sanitize(source, target, weights):
    """Zero out non-finite rows; weights normalised to max 1. Returns usable mask and flags."""
    finite = (
        jnp.all(jnp.isfinite(source), axis=-1)
        & jnp.all(jnp.isfinite(target), axis=-1)
        & jnp.isfinite(weights)
    )
    src = jnp.where(finite[..., None], source, 0)
    tgt = jnp.where(finite[..., None], target, 0)
    # weights >= 0 keep their gradient (also at 0); only > 0 counts as a usable point
    w = jnp.where(finite & (weights >= 0), weights, 0)
    usable = w > 0
    w = safe_div(w, jnp.max(w, axis=-1, keepdims=True, initial=0))  # avoids over/underflow
    count = jnp.sum(usable, axis=-1, dtype=jnp.int32)
    status = jnp.where(
        count >= 3, OK, jnp.where(jnp.all(finite, axis=-1), TOO_FEW_POINTS, NOT_FINITE)
    ).astype(jnp.int32)
    return src, tgt, w, usable, count, status


def _rtol(rtol, dtype):
    return math.sqrt(float(jnp.finfo(dtype).eps)) if rtol is None else rtol


# ------------------------------------------------------------------------------------ public
def align(
    source: Float[ArrayLike, "*b n 3"],
    target: Float[ArrayLike, "*b n 3"],
    weights: Float[ArrayLike, "*b n"] | None = None,
    *,
    with_scale: bool = False,
    degenerate_rtol: float | None = None,
) -> AlignmentResult:
    """Weighted least-squares rigid (or similarity) transform mapping ``source`` onto ``target``.

    Minimises ``sum_i w_i |s R source_i + t - target_i|^2`` over rotations ``R``, translations
    ``t`` and (if ``with_scale``) scales ``s > 0``, in closed form (see the module docstring).
    Batch dimensions broadcast. Safe under ``jit``, ``vmap`` and ``grad``.

    Arguments:
        source: points ``(*b, n, 3)``.
        target: matched points ``(*b, n, 3)``.
        weights: non-negative weights ``(*b, n)`` (default all 1). Only their ratios matter.
            Rows with non-finite coordinates/weights or weight ``<= 0`` are ignored.
        with_scale: also estimate an isotropic scale (Umeyama); otherwise ``s = 1``.
        degenerate_rtol: relative tolerance of the ``DEGENERATE`` test (default
            ``sqrt(eps)`` of the dtype).

    Returns:
        An :class:`AlignmentResult`; ``inlier_mask`` / ``num_inliers`` describe the usable
        points, ``rms`` is the weighted RMS residual over them.

    Raises:
        ValueError: (at trace time) for wrong shapes.
    """
    source, target, weights, dtype = _prepare(source, target, weights)
    rtol = _rtol(degenerate_rtol, dtype)
    src, tgt, w, usable, count, status = _sanitize(source, target, weights)
    src, tgt, ox, oy = _local_frame(src, tgt, w)
    fit = _fit(src, tgt, w, with_scale, rtol)
    status = jnp.where((status == OK) & ~fit.ok, DEGENERATE, status).astype(jnp.int32)
    rms = _weighted_rms(fit.rotation, fit.translation, fit.scale, src, tgt, w)
    return AlignmentResult(
        rotation=fit.rotation,
        quaternion=fit.quaternion,
        translation=_global_translation(fit.rotation, fit.translation, fit.scale, ox, oy,
                                        fit.ok),
        scale=fit.scale,
        rms=rms,
        num_inliers=count,
        inlier_mask=usable,
        status=status,
    )


def ransac_align(
    key: PRNGKeyArray,
    source: Float[ArrayLike, "*b n 3"],
    target: Float[ArrayLike, "*b n 3"],
    weights: Float[ArrayLike, "*b n"] | None = None,
    *,
    num_iterations: int = 64,
    threshold: float | Float[ArrayLike, ""] = 0.01,
    sample_size: int = 3,
    with_scale: bool = False,
    refine: bool = True,
    degenerate_rtol: float | None = None,
) -> AlignmentResult:
    """Robust alignment with a fixed-budget RANSAC (all hypotheses evaluated at once).

    Each of the ``num_iterations`` hypotheses is fitted (weighted, :func:`align`'s solver) to
    ``sample_size`` distinct usable points drawn without replacement with probability
    proportional to their weights (Gumbel top-k). A point is an inlier of a hypothesis when
    its residual ``|s R source_i + t - target_i| < threshold``. The best hypothesis has the
    most inliers, ties broken by the smaller sum of inlier residuals; hypotheses whose sample
    is degenerate are discarded. With ``refine`` the transform is refitted (weighted) on all
    inliers of the best hypothesis. No Python loop over hypotheses; ``vmap`` over frames works
    (one key per frame), and leading batch dimensions are also supported with a single key.

    Arguments:
        key: a JAX PRNG key.
        source: points ``(*b, n, 3)``.
        target: matched points ``(*b, n, 3)``.
        weights: non-negative weights ``(*b, n)`` (default all 1); see :func:`align`.
        num_iterations: number of hypotheses (static).
        threshold: inlier distance (same unit as the points, e.g. metres).
        sample_size: points per hypothesis (static, ``>= 3``; clipped to ``n``).
        with_scale: also estimate an isotropic scale.
        refine: refit on all inliers of the best hypothesis.
        degenerate_rtol: see :func:`align`.

    Returns:
        An :class:`AlignmentResult`. ``inlier_mask`` holds the usable points within
        ``threshold`` of the returned transform and ``rms`` is the weighted RMS residual over
        them. Status ``TOO_FEW_INLIERS`` when the best hypothesis has fewer than 3 inliers,
        ``DEGENERATE`` when no sample (or the inlier set of the refit) is non-degenerate.

    Raises:
        ValueError: (at trace time) for wrong shapes or ``sample_size < 3``,
            ``num_iterations < 1``.
    """
    if int(sample_size) < 3:
        raise ValueError(f"sample_size must be >= 3, got {sample_size}")
    if int(num_iterations) < 1:
        raise ValueError(f"num_iterations must be >= 1, got {num_iterations}")
    if isinstance(threshold, (int, float)) and not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    source, target, weights, dtype = _prepare(source, target, weights)
    rtol = _rtol(degenerate_rtol, dtype)
    src, tgt, w, usable, count, status = _sanitize(source, target, weights)
    src, tgt, ox, oy = _local_frame(src, tgt, w)
    batch, n = src.shape[:-2], src.shape[-2]
    k = min(int(sample_size), n)
    threshold = jnp.asarray(threshold, dtype)

    # --- sampling: Gumbel top-k on log-weights = weighted sampling without replacement
    w_s = jax.lax.stop_gradient(w)
    logits = jnp.where(usable, jnp.log(jnp.where(usable, w_s, 1)), -jnp.inf)
    g = jax.random.gumbel(key, batch + (num_iterations, n), dtype)
    _, idx = jax.lax.top_k(logits[..., None, :] + g, k)  # (*b, iters, k)
    hs = jnp.take_along_axis(src[..., None, :, :], idx[..., None], axis=-2)
    ht = jnp.take_along_axis(tgt[..., None, :, :], idx[..., None], axis=-2)
    hw = jnp.take_along_axis(w[..., None, :], idx, axis=-1)
    hyp = _fit(hs, ht, hw, with_scale, rtol)  # batch (*b, iters)

    # --- scoring, all hypotheses x all points
    res = safe_norm(_apply(hyp.rotation, hyp.translation, hyp.scale, src[..., None, :, :])
                    - tgt[..., None, :, :])  # (*b, iters, n)
    inl = usable[..., None, :] & (res < threshold) & hyp.ok[..., None]
    n_inl = jnp.sum(inl, axis=-1, dtype=jnp.int32)
    cost = jnp.sum(jnp.where(inl, res, 0), axis=-1)
    best_count = jnp.max(n_inl, axis=-1)
    cost = jnp.where(n_inl == best_count[..., None], cost, jnp.inf)
    best = jnp.argmin(cost, axis=-1)  # (*b,)
    any_valid = jnp.any(hyp.ok, axis=-1)

    def pick(x):  # select the best hypothesis along the iteration axis
        nb = len(batch)
        ix = best.reshape(batch + (1,) * (x.ndim - nb))
        return jnp.take_along_axis(x, ix, axis=nb).squeeze(nb)

    best_inl = jax.lax.stop_gradient(pick(inl))
    status = jnp.where((status == OK) & ~any_valid, DEGENERATE, status)
    status = jnp.where((status == OK) & (best_count < 3), TOO_FEW_INLIERS, status)

    if refine:
        fit = _fit(src, tgt, w * best_inl, with_scale, rtol)
        status = jnp.where((status == OK) & ~fit.ok, DEGENERATE, status)
        rot, q, t, s = fit.rotation, fit.quaternion, fit.translation, fit.scale
    else:
        rot, q, t, s = (pick(x) for x in (hyp.rotation, hyp.quaternion, hyp.translation,
                                          hyp.scale))
    status = status.astype(jnp.int32)
    ok = status == OK
    rot = jnp.where(ok[..., None, None], rot, jnp.eye(3, dtype=dtype))
    q = jnp.where(ok[..., None], q, jnp.asarray([1, 0, 0, 0], dtype))
    t = jnp.where(ok[..., None], t, 0)
    s = jnp.where(ok, s, 1)

    final_res = safe_norm(_apply(rot, t, s, src) - tgt)
    mask = jnp.where(ok[..., None], usable & (final_res < threshold), best_inl)
    mask = jax.lax.stop_gradient(mask)
    rms = _weighted_rms(rot, t, s, src, tgt, w * mask)
    return AlignmentResult(
        rotation=rot,
        quaternion=q,
        translation=_global_translation(rot, t, s, ox, oy, ok),
        scale=s,
        rms=rms,
        num_inliers=jnp.sum(mask, axis=-1, dtype=jnp.int32),
        inlier_mask=mask,
        status=status,
    )


def transform_points(
    result: AlignmentResult, points: Float[ArrayLike, "*b m 3"]
) -> Float[Array, "*b m 3"]:
    """Apply ``s R p + t`` of an :class:`AlignmentResult` to points.

    Arguments:
        result: an alignment result with batch shape ``*b``.
        points: points ``(*b, m, 3)`` (batch dimensions broadcast against the result's).

    Returns:
        The transformed points, ``(*b, m, 3)``.
    """
    points = jnp.asarray(points)
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., m, 3), got shape {tuple(points.shape)}")
    return _apply(result.rotation, result.translation, result.scale, points)
