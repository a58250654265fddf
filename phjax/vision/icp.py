"""Point-to-plane ICP for depth data: nearest-neighbour and projective association.

Finds the rigid transform ``x -> R x + t`` that moves a *source* point set onto a *target*
surface given as points with unit normals, by minimising the point-to-plane cost

    ``sum_i w_i (n_i . (R s_i + t - y_i))^2``

over correspondences ``s_i <-> (y_i, n_i)`` that are re-established every iteration (Chen &
Medioni 1992; Rusinkiewicz & Levoy 2001; Newcombe et al. 2011, KinectFusion).

Two association strategies share the same solver:

* :func:`icp_point_to_plane`: brute-force nearest neighbour in 3-D. Every iteration costs
  ``O(N M)`` time (one ``(chunk_size, M)`` block of squared distances at a time, fused
  elementwise code) and ``O(chunk_size M)`` memory: a few nanoseconds per pair on a CPU core,
  i.e. about 0.1 s per iteration for ``N = M = 5000``. Fine for up to a few thousand points.
* :func:`icp_projective`: projective data association on an organised target (a depth image):
  each transformed source point is projected with the pinhole intrinsics and paired with the
  target point stored at that pixel. ``O(N)`` per iteration; the standard choice for real-time
  RGB-D tracking when the motion between frames is small.

Solver
------
Each iteration linearises the residual ``r_i = n_i . (x_i - y_i)`` (``x_i`` the currently
transformed source point) in a small rotation ``theta`` about the weighted centroid ``c`` of the
correspondences and a translation ``delta``:
``r_i + (x_i - c) x n_i . theta + n_i . delta``. The rotation columns are divided by the RMS
radius ``L`` of the points about ``c`` so that the 6x6 Gauss-Newton matrix ``A = J^T W J`` is
dimensionless and its conditioning is scale-free. ``A`` is eigendecomposed (``eigh``):

* if ``lambda_min <= degenerate_rtol * lambda_max`` the problem is rank deficient (a plane, a
  sphere, a cylinder, collinear points) and the iteration stops with status ``DEGENERATE``;
* otherwise the step solves ``(A + mu I) x = -J^T W r`` with a tiny Levenberg damping
  ``mu = damping * lambda_max``. The rotation is applied exactly (``quat_from_rotvec``), so the
  iterate stays a proper rigid transform.

Local frames
------------
The iteration does not work in the caller's coordinates but relative to one usable source
point ``o_s`` (the first; else the first usable source point of the pairs below) and, with
nearest-neighbour association, its image under the initial guess ``o_y = R_0 o_s + t_0``: the
points, residuals, centroids, normal equations and the returned ``rmse`` are those of
``s - o_s`` and ``y - o_y``, and the transform is converted at the start (``t_local = t_0 +
R_0 o_s - o_y``) and at the end (``t = t_local + (o_y - o_s) - (R - I) o_s``, with ``(R - I)
o_s`` evaluated without cancellation). The optimum does not depend on the origins (no
gradient flows through them, ``jax.lax.stop_gradient``), but a large common offset no longer
costs accuracy beyond the rounding of the inputs and of the returned translation themselves.
Measured with the scene 1e4 m from the origin in ``float32`` (the inputs are then rounded to
about 1 mm): before, the rounding of ``R s + t`` in the caller's frame swamped the steps and
both modes ended ``NOT_CONVERGED`` after 30 iterations (3.1e-3 and 4.4e-3 rad rotation error,
rmse 6.3e-4 and 6.2e-4 m; the figures vary with XLA's options; the optimum of these rounded
inputs has 2.4e-3 and 1.1e-3 rad, rmse 3.9e-4 and 2.8e-4 m); now both converge in 2-3
iterations to the ``float64`` solution of the same inputs within 4e-8 rad, as near the origin.
:func:`icp_projective` and the reprojection pairs project points in the target camera frame,
so there the target side is not shifted (``o_y = 0``; only the source is, e.g. a model in a
far world frame): a target far from its own camera is not a depth image.

Robust losses (``"huber"``, ``"cauchy"``, ``"tukey"``) are applied by iteratively reweighted
least squares with scale ``loss_scale`` (metres). Correspondences farther apart than
``max_correspondence_distance`` (3-D distance), with an invalid point on either side, or with a
zero target normal are rejected. The loop (``lax.while_loop``) runs at most ``num_iterations``
Gauss-Newton steps and stops early when the step moves the points by less than ``tolerance``
(``|(L theta, delta)|``, metres). Shapes are static; the functions are ``jit``- and
``vmap``-compatible (vmap over frames/problems), dtype-generic, and never produce NaN/inf values
for finite inputs, even when every point is invalid. (Derivatives through ICP are not supported:
the correspondence search is discrete and the loop is a ``while_loop``.)

Fixed point pairs (sparse + dense)
---------------------------------
``point_pairs=(s_k, y_k, w_k)`` adds fixed point-to-point correspondences (e.g. feature matches
lifted to 3-D, the RANSAC inliers) to the same Gauss-Newton objective, as in RGB-D odometry
with sparse and dense terms:

    ``sum_i (rho_i / sigma^2) (n_i . (R s_i + t - y_i))^2 + sum_k e_k^T W_k e_k``,
    ``e_k = R s_k + t - y_k``

Each pair contributes three rows, the point-to-plane rows with normals ``e_x, e_y, e_z``.
``W_k`` are information matrices (inverse covariances, 1/m^2; a scalar weight ``w_k`` means
``w_k I``) and ``sigma`` the noise std of a dense
residual (``dense_sigma``, by default estimated every iteration as the IRLS scale
``sqrt(sum rho_i r_i^2 / sum rho_i)``, ``rho_i`` the robust weights), so both terms are weighted
by their noise. Without dense correspondences the objective is the weighted point-to-point
(Kabsch) problem of :func:`phjax.align`. Without ``point_pairs`` the iteration is the plain
ICP above (weights need no scale: the step does not depend on it).

Reprojection pairs (sparse 2-D + dense)
---------------------------------------
``pixel_pairs=(s_k, uv_k, W_k)`` adds fixed 3-D -> pixel correspondences instead (or as well):
a source point ``s_k`` (e.g. a keypoint of the source frame lifted through its depth) and the
pixel ``uv_k`` where its match was observed in the target camera. The residual is the
reprojection error ``e_k = pi(R s_k + t) - uv_k`` (px) with information ``W_k`` (1/px^2), the
sparse term of RGB-D odometry: it uses the accurate lateral position of the match in the target
image and no target depth. Row ``m`` of its Jacobian is a point-to-plane row with the
(non-unit) "normal" ``g_m = d pi_m / d x``, so it joins the same normal equations. Without
dense correspondences the objective is a weighted PnP problem (as ``cv2.solvePnP``,
``SOLVEPNP_ITERATIVE``; unlike PnP, a good initial guess is needed). A robust ``pixel_loss``
with ``pixel_gate=True`` re-selects the matches every iteration: the scale of the loss
follows the dense correspondence distance (projected at the point's depth), so all putative
matches can be passed and a wrong initial consensus is not locked in.

Status codes (:class:`IcpStatus`)
---------------------------------
* ``OK`` (0): converged (last step shorter than ``tolerance``).
* ``TOO_FEW_CORRESPONDENCES`` (1): fewer than ``min_correspondences`` inliers in some iteration.
* ``DEGENERATE`` (2): rank-deficient normal equations (see above).
* ``NOT_CONVERGED`` (3): the iteration budget ran out; the last iterate is returned.

For ``TOO_FEW_CORRESPONDENCES`` and ``DEGENERATE`` the returned transform is the *initial
guess* (the caller's prediction), never a partial update along unobservable directions.

Conventions: ``wxyz`` quaternions (Hamilton); the transform maps source coordinates into target
coordinates. Camera frames are ``x`` right, ``y`` down, ``z`` forward (optical axis); pixel
``(row i, column j)`` has its centre at ``(u, v) = (j, i)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._misc import any_traced, safe_div, safe_normalize, safe_sqrt
from ..quaternion import quat_from_rotvec, quat_mul, quat_normalize, quat_rotate, quat_to_matrix

__all__ = [
    "IcpResult",
    "IcpStatus",
    "PinholeIntrinsics",
    "backproject",
    "estimate_normals",
    "icp_point_to_plane",
    "icp_projective",
]

OK = 0
TOO_FEW_CORRESPONDENCES = 1
DEGENERATE = 2
NOT_CONVERGED = 3

_LOSSES = ("l2", "huber", "cauchy", "tukey")


class IcpStatus:
    """Integer status codes of :class:`IcpResult` (plain ``int`` constants)."""

    OK = OK
    TOO_FEW_CORRESPONDENCES = TOO_FEW_CORRESPONDENCES
    DEGENERATE = DEGENERATE
    NOT_CONVERGED = NOT_CONVERGED

    names = ("OK", "TOO_FEW_CORRESPONDENCES", "DEGENERATE", "NOT_CONVERGED")

    @classmethod
    def name(cls, code: int) -> str:
        """Name of a (concrete) status code, e.g. ``IcpStatus.name(2) == "DEGENERATE"``."""
        return cls.names[int(code)]


class PinholeIntrinsics(eqx.Module):
    """Pinhole camera intrinsics (pixels): ``u = fx x / z + cx``, ``v = fy y / z + cy``.

    Pixel ``(row i, column j)`` has its centre at ``(u, v) = (j, i)``. The fields are PyTree
    leaves, so a batch of cameras can be ``vmap``-ped. Functions taking intrinsics also accept
    any object with ``fx, fy, cx, cy`` attributes or a sequence ``(fx, fy, cx, cy)``.
    """

    fx: Float[ArrayLike, ""]
    fy: Float[ArrayLike, ""]
    cx: Float[ArrayLike, ""]
    cy: Float[ArrayLike, ""]

    @property
    def matrix(self) -> Float[Array, "3 3"]:
        """The 3x3 calibration matrix ``K``."""
        fx, fy, cx, cy = (jnp.asarray(v) for v in (self.fx, self.fy, self.cx, self.cy))
        z = jnp.zeros_like(fx)
        o = jnp.ones_like(fx)
        return jnp.stack([jnp.stack([fx, z, cx]), jnp.stack([z, fy, cy]), jnp.stack([z, z, o])])

    def project(self, points: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixel coordinates ``(u, v)`` of camera-frame points.

        A point not in front of the camera (``z <= 0``) has no image and gives ``(-1, -1)``,
        outside every image (pixel centres lie at ``u, v >= 0``), so it never samples a pixel.
        Values and gradients are finite for finite points.
        """
        p = jnp.asarray(points)
        fx, fy, cx, cy = _intrinsics(self, p.dtype)
        z = p[..., 2]
        front = z > 0
        zs = jnp.where(front, z, 1)
        uv = jnp.stack([fx * p[..., 0] / zs + cx, fy * p[..., 1] / zs + cy], axis=-1)
        return jnp.where(front[..., None], uv, -1)


def _intrinsics(intrinsics: Any, dtype) -> tuple[Array, Array, Array, Array]:
    if all(hasattr(intrinsics, a) for a in ("fx", "fy", "cx", "cy")):
        vals = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    else:
        try:
            vals = tuple(intrinsics)
        except TypeError:
            vals = ()
        if len(vals) != 4:
            raise ValueError(
                "intrinsics must have attributes fx, fy, cx, cy or be a sequence (fx, fy, cx, cy)"
            )
    return tuple(jnp.asarray(v, dtype) for v in vals)  # type: ignore[return-value]


def _float_dtype(*arrays) -> Any:
    return jnp.result_type(*(jnp.asarray(a).dtype for a in arrays), jnp.float32)


# ----------------------------------------------------------------------------- depth images
def backproject(
    depth: Float[ArrayLike, "*b h w"], intrinsics: Any
) -> Float[Array, "*b h w 3"]:
    """Organised point cloud of a depth image in the camera frame.

    Arguments:
        depth: depth along the optical axis (``z``, metres); ``0`` or non-finite = invalid.
        intrinsics: :class:`PinholeIntrinsics` (or ``(fx, fy, cx, cy)``).

    Returns:
        Points ``(x, y, z)`` per pixel with ``x = (j - cx) z / fx``, ``y = (i - cy) z / fy``.
        Invalid pixels give the origin ``(0, 0, 0)`` (so ``z > 0`` is the validity test).
    """
    depth = jnp.asarray(depth)
    if depth.ndim < 2:
        raise ValueError(f"depth must have shape (..., h, w), got {tuple(depth.shape)}")
    dtype = _float_dtype(depth)
    fx, fy, cx, cy = _intrinsics(intrinsics, dtype)
    z = depth.astype(dtype)
    z = jnp.where(jnp.isfinite(z) & (z > 0), z, 0)
    h, w = z.shape[-2:]
    j = jnp.arange(w, dtype=dtype)
    i = jnp.arange(h, dtype=dtype)[:, None]
    x = (j - cx) * z / fx
    y = (i - cy) * z / fy
    return jnp.stack([x, y, z], axis=-1)


def _shift(a: Array, offset: int, axis: int, fill) -> Array:
    """``out[k] = a[k + offset]`` along ``axis`` (``fill`` outside)."""
    n = a.shape[axis]
    idx = jnp.clip(jnp.arange(n) + offset, 0, n - 1)
    out = jnp.take(a, idx, axis=axis)
    inside = (jnp.arange(n) + offset >= 0) & (jnp.arange(n) + offset < n)
    shape = [1] * a.ndim
    shape[axis] = n
    return jnp.where(inside.reshape(shape), out, fill)


def estimate_normals(
    points: Float[ArrayLike, "h w 3"],
    *,
    radius: int = 1,
    max_depth_jump: float = 0.05,
) -> Float[Array, "h w 3"]:
    """Unit surface normals of an organised (camera-frame) point cloud from image neighbours.

    The tangents are finite differences to the neighbours ``radius`` pixels away along the image
    rows and columns (central differences; one-sided where one neighbour is invalid or across a
    depth discontinuity), and the normal is their normalised cross product, oriented towards the
    camera (``n . p < 0``).

    Arguments:
        points: organised points ``(h, w, 3)`` (e.g. from :func:`backproject`); a pixel is valid
            when its coordinates are finite and ``z > 0``.
        radius: neighbour distance in pixels (static); larger values smooth noisy depth.
        max_depth_jump: a neighbour is ignored when its depth differs by more than
            ``max_depth_jump * radius * z`` (relative depth discontinuity).

    Returns:
        Normals ``(h, w, 3)``; the zero vector where no normal can be estimated (invalid pixel,
        or no valid neighbour in one of the two directions). Values are always finite.
    """
    p = jnp.asarray(points)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (h, w, 3), got {tuple(p.shape)}")
    if int(radius) < 1:
        raise ValueError(f"radius must be >= 1, got {radius}")
    p = p.astype(_float_dtype(p))
    valid = jnp.all(jnp.isfinite(p), axis=-1) & (p[..., 2] > 0)
    p = jnp.where(valid[..., None], p, 0)
    z = p[..., 2]
    k = int(radius)

    def tangent(axis: int) -> tuple[Array, Array]:
        nxt = _shift(p, k, axis, 0)
        prv = _shift(p, -k, axis, 0)
        ok_n = _shift(valid, k, axis, False) & valid
        ok_p = _shift(valid, -k, axis, False) & valid
        lim = max_depth_jump * k * z
        ok_n = ok_n & (jnp.abs(nxt[..., 2] - z) <= lim)
        ok_p = ok_p & (jnp.abs(prv[..., 2] - z) <= lim)
        d = jnp.where(
            (ok_n & ok_p)[..., None],
            nxt - prv,
            jnp.where(ok_n[..., None], nxt - p, jnp.where(ok_p[..., None], p - prv, 0)),
        )
        return d, ok_n | ok_p

    du, ok_u = tangent(1)
    dv, ok_v = tangent(0)
    n = jnp.cross(du, dv)
    n = jnp.where(jnp.sum(n * p, axis=-1, keepdims=True) > 0, -n, n)
    n = safe_normalize(n)
    return jnp.where((valid & ok_u & ok_v)[..., None], n, 0)


# ---------------------------------------------------------------------------------- results
class IcpResult(eqx.Module):
    """Result of :func:`icp_point_to_plane` / :func:`icp_projective` (a PyTree).

    The transform maps source coordinates into target coordinates: ``y ~ R(rotation) s +
    translation``. Batch dimensions appear in front when the solver is ``vmap``-ped.

    Attributes:
        rotation: unit quaternion ``wxyz`` with ``w >= 0``, ``(4,)``.
        translation: ``(3,)``.
        status: :class:`IcpStatus` code (``int32``).
        rmse: RMS point-to-plane residual over the inliers of the returned transform (0 when
            there are none).
        num_inliers: number of accepted correspondences at the returned transform.
        num_iterations: Gauss-Newton steps taken.
        inlier_mask: accepted source points at the returned transform, ``(n,)``.
        conditioning: ``lambda_min / lambda_max`` of the (scaled) normal equations in the last
            iteration (0 if none was formed); compare with ``degenerate_rtol``.
    """

    rotation: Float[Array, "*b 4"]
    translation: Float[Array, "*b 3"]
    status: Int[Array, "*b"]
    rmse: Float[Array, "*b"]
    num_inliers: Int[Array, "*b"]
    num_iterations: Int[Array, "*b"]
    inlier_mask: Bool[Array, "*b n"]
    conditioning: Float[Array, "*b"]

    @property
    def ok(self) -> Bool[Array, "*b"]:
        """``status == OK``."""
        return self.status == OK

    @property
    def rotation_matrix(self) -> Float[Array, "*b 3 3"]:
        """The rotation as a matrix."""
        return quat_to_matrix(self.rotation)

    def transform(self, points: Float[ArrayLike, "*b n 3"]) -> Float[Array, "*b n 3"]:
        """Apply ``R p + t`` to points (batch dimensions broadcast)."""
        p = jnp.asarray(points)
        return quat_rotate(self.rotation[..., None, :], p) + self.translation[..., None, :]


# -------------------------------------------------------------------------------- the solver
def _robust_weight(r: Array, loss: str, scale: Array) -> Array:
    if loss == "l2":
        return jnp.ones_like(r)
    a = jnp.abs(r) / scale
    if loss == "huber":
        return jnp.where(a <= 1, 1, 1 / jnp.where(a <= 1, 1, a))
    if loss == "cauchy":
        return 1 / (1 + a * a)
    return jnp.where(a < 1, (1 - a * a) ** 2, 0)  # tukey


class _Assoc(eqx.Module):
    """Correspondences of the (transformed) source points."""

    y: Array  # target points (n, 3)
    nrm: Array  # target normals (n, 3)
    ok: Array  # accepted (n,)


def _residuals(x, assoc: _Assoc):
    r = jnp.sum(assoc.nrm * (x - assoc.y), axis=-1)
    return jnp.where(assoc.ok, r, 0)


class _Rows(NamedTuple):
    """One block of linearised residual rows of the Gauss-Newton problem.

    Every residual kind is written as rows ``e_j = g_j . x + const`` of a transformed point
    ``x = R s + t`` with a "normal" ``g_j``: point-to-plane rows (``g`` = target normal, one row
    per point), point-to-point pairs (``g`` = the unit axes, three rows) and reprojection
    pairs (``g`` = the rows of the projection Jacobian, two rows). ``weight`` is the scalar
    metric weight (1/m^2) of each point for the centroid ``c`` and the scale ``L`` of the
    rotation part; ``count`` the number of points it contributes.
    """

    points: Array  # (k, 3): transformed points x
    normals: Array  # (k, j, 3): g of each row
    info: Array  # (k, j, j): weights of the rows (robust weight x information)
    residuals: Array  # (k, j): e
    weight: Array  # (k,): scalar metric weight
    count: Array  # int32


def _dense_rows(x, assoc: _Assoc, loss, loss_scale, dense_sigma, scaled: bool) -> _Rows:
    """Point-to-plane rows. ``scaled``: weight by ``1 / sigma^2`` (the units of the sparse
    pairs), with ``sigma = dense_sigma`` or the robust-weighted RMS residual."""
    r = _residuals(x, assoc)
    w = jnp.where(assoc.ok, _robust_weight(r, loss, loss_scale), 0)
    count = jnp.sum(w > 0, dtype=jnp.int32)  # (Tukey's loss gives outliers weight 0)
    if scaled:
        var = (safe_div(jnp.sum(w * r * r), jnp.sum(w)) if dense_sigma is None
               else jnp.asarray(dense_sigma, x.dtype) ** 2)
        w = jnp.where(var > 0, safe_div(w, var), 0)
    nrm = jnp.where(assoc.ok[:, None], assoc.nrm, 0)
    x = jnp.where(assoc.ok[:, None], x, 0)
    return _Rows(x, nrm[:, None, :], w[:, None, None], r[:, None], w, count)


def _pair_rows(q, t, pairs, loss, loss_scale, gate, weight, max_dist) -> _Rows:
    """Point-to-point rows ``R ps + t - pt`` (three per pair, information ``pinfo``)."""
    ps, pt, pinfo = pairs
    xp = quat_rotate(q, ps) + t
    ep = xp - pt
    # robust weight of the Mahalanobis distance, then the relative weight
    maha = safe_sqrt(jnp.einsum("ki,kij,kj->k", ep, pinfo, ep))
    trace = jnp.trace(pinfo, axis1=-2, axis2=-1)
    sc = jnp.asarray(loss_scale, xp.dtype)
    if gate:  # the correspondence distance in noise units
        sc = jnp.maximum(sc, max_dist * safe_sqrt(trace / 3))
    rho = jnp.where(trace > 0, _robust_weight(maha, loss, sc), 0)
    info = (weight * rho)[:, None, None] * pinfo
    pw = jnp.trace(info, axis1=-2, axis2=-1) / 3
    eye = jnp.broadcast_to(jnp.eye(3, dtype=xp.dtype), ps.shape[:1] + (3, 3))
    return _Rows(xp, eye, info, ep, pw, jnp.sum(pw > 0, dtype=jnp.int32))


def _pixel_rows(q, t, pix, loss, loss_scale, gate, weight, max_dist, oy) -> _Rows:
    """Reprojection rows ``pi(R ps + t) - uv`` (two per pair, px, information ``qinfo``).

    ``q, t, ps`` are in the solver's local frames (see :func:`_local_origins`): the points are
    projected at ``x + oy`` (the target camera frame); the rows keep the local ``x``.
    """
    qs, quv, qinfo, (pfx, pfy, pcx, pcy) = pix
    x_local = quat_rotate(q, qs) + t
    xq = x_local + oy
    zq = xq[:, 2]
    front = zq > 1e-6
    iz = jnp.where(front, 1 / jnp.where(front, zq, 1), 0)
    eq = jnp.stack([pfx * xq[:, 0] * iz + pcx, pfy * xq[:, 1] * iz + pcy], -1) - quv
    mq = safe_sqrt(jnp.einsum("ki,kij,kj->k", eq, qinfo, eq))
    sq = jnp.trace(qinfo, axis1=-2, axis2=-1) / 2  # scalar information, 1/px^2
    f_over_z = 0.5 * (pfx + pfy) * iz
    sc = jnp.asarray(loss_scale, xq.dtype)
    if gate:  # the correspondence distance seen at the point's depth, noise units
        sc = jnp.maximum(sc, max_dist * f_over_z * safe_sqrt(sq))
    rho = jnp.where(front & (sq > 0), _robust_weight(mq, loss, sc), 0)
    info = (weight * rho)[:, None, None] * qinfo
    # d(u, v)/dx: rows g_u, g_v of the projection Jacobian (1/m -> px)
    zero = jnp.zeros_like(iz)
    g = jnp.stack([jnp.stack([pfx * iz, zero, -pfx * xq[:, 0] * iz * iz], -1),
                   jnp.stack([zero, pfy * iz, -pfy * xq[:, 1] * iz * iz], -1)], axis=1)
    # scalar metric weights (1/m^2) for c and L: information times (f / z)^2
    qw = jnp.trace(info, axis1=-2, axis2=-1) / 2 * f_over_z**2
    return _Rows(x_local, g, info, eq, qw, jnp.sum(qw > 0, dtype=jnp.int32))


def _gauss_newton_step(q, t, blocks: list[_Rows], degenerate_rtol, damping):
    """One damped Gauss-Newton step over all residual rows, in centred, scaled coordinates.

    The unknowns are ``(L theta, delta)`` about the weighted centroid ``c``: a rotation
    ``theta`` about ``c`` and a translation ``delta``, with the rotation scaled by the RMS
    radius ``L`` of the points so both parts have units of metres. A row with normal ``g`` has
    the Jacobian row ``[(x - c) x g / L, g]``.

    Returns:
        ``(q_new, t_new, step length, good, conditioning)``: ``good`` is ``False`` for a
        degenerate system (``lambda_min <= degenerate_rtol lambda_max``), whose step is 0.
    """
    wsum = sum(jnp.sum(b.weight) for b in blocks)
    c = safe_div(sum(jnp.einsum("k,ki->i", b.weight, b.points) for b in blocks), wsum)
    msq = sum(jnp.einsum("k,ki,ki->", b.weight, b.points - c, b.points - c) for b in blocks)
    ell = safe_sqrt(safe_div(msq, wsum))
    ell = jnp.where(ell > 0, ell, 1)
    amat, bvec = 0.0, 0.0
    for b in blocks:
        xc = (b.points - c)[:, None, :]
        jac = jnp.concatenate([jnp.cross(xc, b.normals) / ell, b.normals], axis=-1)  # (k,j,6)
        amat = amat + jnp.einsum("kji,kjm,kml->il", jac, b.info, jac)
        bvec = bvec - jnp.einsum("kji,kjm,km->i", jac, b.info, b.residuals)
    lam, vec = jnp.linalg.eigh(amat)
    lam_max = lam[-1]
    cond = safe_div(lam[0], lam_max)
    good = (lam_max > 0) & (cond > degenerate_rtol)
    denom = lam + damping * lam_max
    denom = jnp.where(good & (denom > 0), denom, 1)
    sol = jnp.where(good, vec @ ((vec.T @ bvec) / denom), 0)
    theta, delta = sol[:3] / ell, sol[3:]
    dq = quat_from_rotvec(theta)
    q_new = quat_normalize(quat_mul(dq, q))
    t_new = quat_rotate(dq, t - c) + c + delta
    return q_new, t_new, jnp.sqrt(jnp.sum(sol * sol)), good, cond


def _rotate_minus_identity(q: Array, v: Array) -> Array:
    """``R(q) v - v``, without the cancellation of ``quat_rotate(q, v) - v`` for a large ``v``
    (its rounding is that of the result, not of ``|v|``)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2 * jnp.cross(u, v)
    return w * t + jnp.cross(u, t)


def _local_origins(src, src_ok, q0, t0, pairs, pix, shift_target: bool):
    """Origins ``(ox, oy)`` of the frames :func:`_run_icp` solves in (no gradient).

    ``ox`` is the first usable source point (dense source first, then the sources of
    ``point_pairs`` and ``pixel_pairs``; 0 if there is none). ``oy`` is its image under the
    initial guess, ``R0 ox + t0`` (rounded), when the target may be shifted
    (``shift_target``: nearest-neighbour association), else 0: projective association and
    reprojection need target-camera coordinates. All points, residuals and sums of the
    iteration are then relative to these origins (``s - ox``, ``y - oy``), so a large common
    offset costs no accuracy beyond the rounding of the inputs themselves.
    """
    dtype = src.dtype
    pts, oks = [src], [src_ok]
    if pairs is not None:
        pts.append(pairs[0])
        oks.append(jnp.trace(pairs[2], axis1=-2, axis2=-1) > 0)
    if pix is not None:
        pts.append(pix[0])
        oks.append(jnp.trace(pix[2], axis1=-2, axis2=-1) > 0)
    pts, ok = jnp.concatenate(pts), jnp.concatenate(oks)
    if pts.shape[0] == 0:
        ox = jnp.zeros(3, dtype)
    else:
        ox = jnp.where(jnp.any(ok), pts[jnp.argmax(ok)], 0)
    ox = jax.lax.stop_gradient(ox)
    if not shift_target:
        return ox, jnp.zeros(3, dtype)
    # ox + (R0 ox - ox + t0): the displacement first, so oy keeps the resolution of ox
    oy = jax.lax.stop_gradient(ox + (t0 + _rotate_minus_identity(q0, ox)))
    return ox, oy


def _run_icp(associate, src, src_ok, q0, t0, dist, *, num_iterations, loss, loss_scale,
             tolerance, degenerate_rtol, damping, min_correspondences, pairs=None,
             dense_sigma=None, pair_weight=1.0, pair_loss="l2", pair_loss_scale=3.0,
             pair_gate=False, pix=None, pixel_weight=1.0, pixel_loss="l2",
             pixel_loss_scale=3.0, pixel_gate=False, origins=None) -> IcpResult:
    """Gauss-Newton loop shared by both association strategies (single problem).

    ``origins = (ox, oy)`` (:func:`_local_origins`; default both 0): the loop works in local
    frames, source ``s - ox`` and target ``y - oy``; ``associate`` must take and return points
    of the local target frame (its target shifted by ``oy``). The transform is converted
    from and to the caller's frames here: ``t_local = t + R ox - oy``.

    ``pairs = (ps, pt, pinfo)``: fixed point-to-point correspondences (already sanitised,
    information matrices ``pinfo`` (k, 3, 3) in 1/m^2, 0 = unused) whose residuals
    ``R ps + t - pt`` join the normal equations (times ``pair_weight`` and the robust weight
    of their Mahalanobis distance);
    the dense residuals are then weighted by ``robust weight / sigma^2`` with ``sigma =
    dense_sigma`` or, when ``None``, the IRLS scale estimate of the current iteration.
    ``pix = (ps, uv, pinfo, (fx, fy, cx, cy))``: fixed 3-D -> pixel correspondences whose
    reprojection residuals ``pi(R ps + t) - uv`` (px, information ``pinfo`` (k, 2, 2) in
    1/px^2) join likewise. ``*_gate``: the robust scale of a pair is at least the current
    correspondence distance ``dist[i]`` in the pair's noise units (see the public docstrings).
    """
    dtype = src.dtype
    sparse = pairs is not None or pix is not None
    if origins is None:
        ox = oy = jnp.zeros(3, dtype)
    else:
        ox, oy = origins
    # local frames: s - ox -> y - oy (exact differences for points near the origins)
    src = jnp.where(src_ok[:, None], src - ox, 0)
    if pairs is not None:
        used = (jnp.trace(pairs[2], axis1=-2, axis2=-1) > 0)[:, None]
        pairs = (jnp.where(used, pairs[0] - ox, 0), jnp.where(used, pairs[1] - oy, 0), pairs[2])
    if pix is not None:
        used = (jnp.trace(pix[2], axis1=-2, axis2=-1) > 0)[:, None]
        pix = (jnp.where(used, pix[0] - ox, 0),) + tuple(pix[1:])
    t_init = t0
    t0 = (t0 + _rotate_minus_identity(q0, ox)) + (ox - oy)

    def step(q, t, i):
        x = quat_rotate(q, src) + t
        a = associate(x, dist[i])
        a = _Assoc(a.y, a.nrm, a.ok & src_ok & (dist[i] > 0))
        blocks = [_dense_rows(x, a, loss, loss_scale, dense_sigma, scaled=sparse)]
        if pairs is not None:
            blocks.append(_pair_rows(q, t, pairs, pair_loss, pair_loss_scale, pair_gate,
                                     pair_weight, dist[i]))
        if pix is not None:
            blocks.append(_pixel_rows(q, t, pix, pixel_loss, pixel_loss_scale, pixel_gate,
                                      pixel_weight, dist[i], oy))
        count = sum(b.count for b in blocks)
        q_new, t_new, step_len, good, cond = _gauss_newton_step(q, t, blocks, degenerate_rtol,
                                                                damping)
        too_few = count < min_correspondences
        status = jnp.where(too_few, TOO_FEW_CORRESPONDENCES, jnp.where(good, OK, DEGENERATE))
        converged = step_len <= tolerance
        return q_new, t_new, status.astype(jnp.int32), converged, jnp.where(too_few, 0, cond)

    def cond_fun(state):
        i, _, _, _, done, _ = state
        return (i < num_iterations) & ~done

    def body_fun(state):
        i, q, t, _, _, _ = state
        q_new, t_new, status, converged, cond = step(q, t, i)
        failed = status != OK
        q = jnp.where(failed, q, q_new)
        t = jnp.where(failed, t, t_new)
        done = failed | converged
        status = jnp.where(failed | converged, status, NOT_CONVERGED).astype(jnp.int32)
        return i + 1, q, t, status, done, cond

    init = (jnp.asarray(0, jnp.int32), q0, t0, jnp.asarray(NOT_CONVERGED, jnp.int32),
            jnp.asarray(num_iterations <= 0), jnp.asarray(0, dtype))
    n_it, q, t, status, _, cond = jax.lax.while_loop(cond_fun, body_fun, init)
    failed = (status == TOO_FEW_CORRESPONDENCES) | (status == DEGENERATE)
    q = jnp.where(failed, q0, q)
    t = jnp.where(failed, t0, t)
    q = jnp.where(q[:1] < 0, -q, q)

    x = quat_rotate(q, src) + t
    a = associate(x, dist[-1])
    ok = a.ok & src_ok & (dist[-1] > 0)
    r = _residuals(x, _Assoc(a.y, a.nrm, ok))
    count = jnp.sum(ok, dtype=jnp.int32)
    rmse = safe_sqrt(safe_div(jnp.sum(r * r), count.astype(dtype)))
    # back to the caller's frames: t = t_local + oy - R ox; a failure returns the initial
    # guess exactly as given
    t_out = t + ((oy - ox) - _rotate_minus_identity(q, ox))
    t_out = jnp.where(failed, t_init, t_out)
    return IcpResult(
        rotation=q,
        translation=t_out,
        status=status,
        rmse=rmse,
        num_inliers=count,
        num_iterations=n_it,
        inlier_mask=ok,
        conditioning=cond,
    )


def _check_points(name: str, x: Array, ndim: int = 2) -> None:
    if x.ndim != ndim or x.shape[-1] != 3:
        shape = "(n, 3)" if ndim == 2 else "(h, w, 3)"
        raise ValueError(f"{name} must have shape {shape}, got {tuple(x.shape)}")


def _common_setup(source, source_valid, initial_rotation, initial_translation,
                  max_correspondence_distance, num_iterations, loss, loss_scale, dtype,
                  damping):
    if loss not in _LOSSES:
        raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}")
    if not any_traced(damping) and not (np.isfinite(damping) and damping >= 0):
        # a negative one made the step's system indefinite: TOO_FEW_CORRESPONDENCES with
        # thousands of inliers
        raise ValueError(f"damping must be finite and >= 0, got {damping!r}")
    if int(num_iterations) < 0:
        raise ValueError(f"num_iterations must be >= 0, got {num_iterations}")
    n = source.shape[0]
    src = source.astype(dtype)
    src_ok = jnp.all(jnp.isfinite(src), axis=-1)
    if source_valid is not None:
        sv = jnp.asarray(source_valid)
        if sv.shape != (n,):
            raise ValueError(f"source_valid must have shape ({n},), got {tuple(sv.shape)}")
        src_ok = src_ok & sv.astype(bool)
    src = jnp.where(src_ok[:, None], src, 0)
    q0 = (jnp.asarray([1, 0, 0, 0], dtype) if initial_rotation is None
          else jnp.asarray(initial_rotation, dtype))
    t0 = jnp.zeros(3, dtype) if initial_translation is None else jnp.asarray(initial_translation,
                                                                             dtype)
    if q0.shape != (4,) or t0.shape != (3,):
        raise ValueError(
            f"initial_rotation must have shape (4,) and initial_translation (3,), got "
            f"{tuple(q0.shape)} and {tuple(t0.shape)}"
        )
    q0 = quat_normalize(q0)
    if not any_traced(max_correspondence_distance):
        d = np.asarray(max_correspondence_distance, np.float64)
        if not (np.isfinite(d).all() and (d > 0).all()):
            raise ValueError("max_correspondence_distance must be finite and > 0, got "
                             f"{max_correspondence_distance!r}")
    dist = jnp.asarray(max_correspondence_distance, dtype)
    n_dist = max(int(num_iterations), 1)
    if dist.ndim == 0:
        dist = jnp.broadcast_to(dist, (n_dist,))
    elif dist.shape != (n_dist,):
        raise ValueError(
            "max_correspondence_distance must be a scalar or have shape (num_iterations,), got "
            f"{tuple(dist.shape)}"
        )
    return src, src_ok, q0, t0, dist, jnp.asarray(loss_scale, dtype)


def _check_loss(loss: str) -> str:
    if loss not in _LOSSES:
        raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}")
    return loss


def _prepare_pairs(point_pairs, dense_sigma, dtype):
    """Sanitise ``point_pairs = (source, target, weights)``: non-finite rows get weight 0;
    scalar weights become information matrices ``w I``."""
    if point_pairs is None:
        return None
    try:
        ps, pt, pw = (jnp.asarray(a) for a in point_pairs)
    except (TypeError, ValueError):
        raise ValueError("point_pairs must be a tuple (source, target, weights)") from None
    _check_points("point_pairs source", ps)
    k = ps.shape[0]
    if pt.shape != ps.shape or pw.shape not in ((k,), (k, 3, 3)):
        raise ValueError(
            f"point_pairs need shapes (k, 3), (k, 3), (k,) or (k, 3, 3), got {tuple(ps.shape)}, "
            f"{tuple(pt.shape)}, {tuple(pw.shape)}"
        )
    ps, pt, pw = ps.astype(dtype), pt.astype(dtype), pw.astype(dtype)
    if pw.ndim == 1:
        good = jnp.isfinite(pw) & (pw > 0)
        pw = pw[:, None, None] * jnp.eye(3, dtype=dtype)
    else:  # symmetric positive semi-definite with a positive trace
        pw = 0.5 * (pw + jnp.swapaxes(pw, -1, -2))
        good = jnp.all(jnp.isfinite(pw), axis=(-2, -1)) & (jnp.trace(pw, axis1=-2, axis2=-1) > 0)
    ok = good & jnp.all(jnp.isfinite(ps), axis=-1) & jnp.all(jnp.isfinite(pt), axis=-1)
    return (jnp.where(ok[:, None], ps, 0), jnp.where(ok[:, None], pt, 0),
            jnp.where(ok[:, None, None], pw, 0))


def _prepare_pixels(pixel_pairs, intrinsics, dtype):
    """Sanitise ``pixel_pairs = (source, uv, weights)``: non-finite rows get weight 0; scalar
    weights become information matrices ``w I`` (2x2)."""
    if pixel_pairs is None:
        return None
    if intrinsics is None:
        raise ValueError("pixel_pairs need pixel_intrinsics (the target camera's)")
    try:
        ps, uv, pw = (jnp.asarray(a) for a in pixel_pairs)
    except (TypeError, ValueError):
        raise ValueError("pixel_pairs must be a tuple (source, uv, weights)") from None
    _check_points("pixel_pairs source", ps)
    k = ps.shape[0]
    if uv.shape != (k, 2) or pw.shape not in ((k,), (k, 2, 2)):
        raise ValueError(
            f"pixel_pairs need shapes (k, 3), (k, 2), (k,) or (k, 2, 2), got {tuple(ps.shape)}, "
            f"{tuple(uv.shape)}, {tuple(pw.shape)}"
        )
    ps, uv, pw = ps.astype(dtype), uv.astype(dtype), pw.astype(dtype)
    if pw.ndim == 1:
        good = jnp.isfinite(pw) & (pw > 0)
        pw = pw[:, None, None] * jnp.eye(2, dtype=dtype)
    else:
        pw = 0.5 * (pw + jnp.swapaxes(pw, -1, -2))
        good = jnp.all(jnp.isfinite(pw), axis=(-2, -1)) & (jnp.trace(pw, axis1=-2, axis2=-1) > 0)
    ok = good & jnp.all(jnp.isfinite(ps), axis=-1) & jnp.all(jnp.isfinite(uv), axis=-1)
    return (jnp.where(ok[:, None], ps, 0), jnp.where(ok[:, None], uv, 0),
            jnp.where(ok[:, None, None], pw, 0), _intrinsics(intrinsics, dtype))


def _sparse_kwargs(point_pairs, dense_sigma, pair_weight, pair_loss, pair_loss_scale, pair_gate,
                   pixel_pairs, pixel_intrinsics, pixel_weight, pixel_loss, pixel_loss_scale,
                   pixel_gate, dtype) -> dict:
    if point_pairs is None and pixel_pairs is None and dense_sigma is not None:
        raise ValueError("dense_sigma is only used together with point_pairs or pixel_pairs")
    return {"pairs": _prepare_pairs(point_pairs, dense_sigma, dtype), "dense_sigma": dense_sigma,
            "pair_weight": pair_weight, "pair_loss": _check_loss(pair_loss),
            "pair_loss_scale": pair_loss_scale, "pair_gate": bool(pair_gate),
            "pix": _prepare_pixels(pixel_pairs, pixel_intrinsics, dtype),
            "pixel_weight": pixel_weight, "pixel_loss": _check_loss(pixel_loss),
            "pixel_loss_scale": pixel_loss_scale, "pixel_gate": bool(pixel_gate)}


def _prepare_target(target: Array, normals: Array, target_valid, dtype):
    """Valid target points and unit normals (invalid rows zeroed) and the validity mask."""
    m = target.shape[0]
    tgt = target.astype(dtype)
    nrm = normals.astype(dtype)
    tgt_ok = jnp.all(jnp.isfinite(tgt), axis=-1) & jnp.all(jnp.isfinite(nrm), axis=-1)
    tgt_ok = tgt_ok & (jnp.sum(nrm * nrm, axis=-1) > 0)
    if target_valid is not None:
        tv = jnp.asarray(target_valid)
        if tv.shape != (m,):
            raise ValueError(f"target_valid must have shape ({m},), got {tuple(tv.shape)}")
        tgt_ok = tgt_ok & tv.astype(bool)
    tgt = jnp.where(tgt_ok[:, None], tgt, 0)
    nrm = jnp.where(tgt_ok[:, None], safe_normalize(nrm), 0)
    return tgt, nrm, tgt_ok


def _nearest_neighbour_associator(tgt: Array, nrm: Array, tgt_ok: Array, n: int,
                                  chunk_size: int):
    """``associate(x, max_dist)`` for :func:`_run_icp`: brute-force nearest target point.

    Squared distances are computed one chunk of ``chunk_size`` source points at a time
    (memory ``O(chunk M)``) in coordinates centred on the target, for an accurate
    ``|x|^2 - 2 x.y + |y|^2`` expansion in float32.
    """
    dtype = tgt.dtype
    m = tgt.shape[0]
    centre = safe_div(jnp.sum(tgt, axis=0), jnp.sum(tgt_ok).astype(dtype))
    tgt_c = jnp.where(tgt_ok[:, None], tgt - centre, 0)
    half_sq = jnp.where(tgt_ok, 0.5 * jnp.sum(tgt_c * tgt_c, axis=-1), jnp.inf)
    # bounds of |y|^2 / 2 and |y| over the valid targets, for the rounding tolerance below
    sq_max = jnp.max(jnp.where(tgt_ok, half_sq, 0), initial=0)
    r_max = jnp.sqrt(2 * sq_max)
    eps = jnp.finfo(dtype).eps
    chunk = min(chunk_size, max(n, 1))
    n_blocks = -(-n // chunk) if n else 0

    def block(xb):  # argmin_j |xb - y_j|^2 = argmin_j (|y_j|^2 / 2 - xb . y_j)
        # elementwise products (fused) instead of a K=3 matmul, and min + masked index min
        # instead of argmin (a variadic reduction, several times slower on CPU). XLA computes
        # ``d`` once inside each of the two reductions, and the two copies may round
        # differently (contracted multiply-adds in one kernel and not in the other; seen with
        # LLVM's optimisations off): the index is therefore the first ``j`` within a bound of
        # the rounding error of ``d`` of the minimum, a nearest neighbour up to rounding, and
        # never "no index" (which had sent 24 of 2000 exact points to the last target).
        d = half_sq[None, :] - (xb[:, None, 0] * tgt_c[None, :, 0]
                                + xb[:, None, 1] * tgt_c[None, :, 1]
                                + xb[:, None, 2] * tgt_c[None, :, 2])
        best = jnp.min(d, axis=-1, keepdims=True)
        norm = jnp.sqrt(xb[:, 0] ** 2 + xb[:, 1] ** 2 + xb[:, 2] ** 2)[:, None]
        tol = 16 * eps * (sq_max + norm * r_max)
        idx = jnp.min(jnp.where(d <= best + tol, jnp.arange(m, dtype=jnp.int32), m), axis=-1)
        return jnp.minimum(idx, m - 1)

    def nearest(x: Array) -> Array:
        xc = x - centre
        if n_blocks <= 1:
            return block(xc)
        pad = n_blocks * chunk - n
        xp = jnp.concatenate([xc, jnp.zeros((pad, 3), dtype)]).reshape(n_blocks, chunk, 3)
        return jax.lax.map(block, xp).reshape(-1)[:n]

    def associate(x: Array, max_dist: Array) -> _Assoc:
        if n == 0 or m == 0:
            return _Assoc(jnp.zeros_like(x), jnp.zeros_like(x), jnp.zeros(n, bool))
        idx = nearest(x)
        y, nn = tgt[idx], nrm[idx]
        d2 = jnp.sum((x - y) ** 2, axis=-1)
        return _Assoc(y, nn, tgt_ok[idx] & (d2 <= max_dist * max_dist))

    return associate


def icp_point_to_plane(
    source: Float[ArrayLike, "n 3"],
    target: Float[ArrayLike, "m 3"],
    target_normals: Float[ArrayLike, "m 3"],
    *,
    source_valid: Bool[ArrayLike, " n"] | None = None,
    target_valid: Bool[ArrayLike, " m"] | None = None,
    initial_rotation: Float[ArrayLike, "4"] | None = None,
    initial_translation: Float[ArrayLike, "3"] | None = None,
    num_iterations: int = 20,
    max_correspondence_distance: float | Float[ArrayLike, " iters"] = 0.02,
    loss: str = "l2",
    loss_scale: float = 0.005,
    tolerance: float = 1e-4,
    degenerate_rtol: float = 1e-3,
    damping: float = 1e-9,
    min_correspondences: int = 10,
    chunk_size: int = 256,
    point_pairs: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    dense_sigma: float | None = None,
    pair_weight: float = 1.0,
    pair_loss: str = "l2",
    pair_loss_scale: float = 3.0,
    pair_gate: bool = False,
    pixel_pairs: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    pixel_intrinsics: Any = None,
    pixel_weight: float = 1.0,
    pixel_loss: str = "l2",
    pixel_loss_scale: float = 3.0,
    pixel_gate: bool = False,
) -> IcpResult:
    """Point-to-plane ICP with brute-force nearest-neighbour correspondences.

    Complexity per iteration: ``O(N M)`` time, ``O(min(N, chunk_size) M)`` memory (squared
    distances of one chunk of source points to all target points). Use :func:`icp_projective`
    for organised targets (depth images). See the module docstring for the method.

    Arguments:
        source: source points ``(n, 3)``; non-finite rows are ignored.
        target: target points ``(m, 3)``; non-finite rows are ignored. ``m = 0`` is allowed
            (no dense correspondence: only ``point_pairs`` / ``pixel_pairs`` count).
        target_normals: unit normals at the target points ``(m, 3)`` (zero = no normal: the
            point is ignored), e.g. from :func:`estimate_normals`.
        source_valid, target_valid: optional masks for padded point sets.
        initial_rotation, initial_translation: initial guess of the transform (``wxyz``
            quaternion, default identity; translation, default 0).
        num_iterations: maximum number of Gauss-Newton steps (static).
        max_correspondence_distance: rejection distance (m); a scalar or one value per
            iteration (a coarse-to-fine schedule). The final inlier set uses the last value.
            Must be finite and ``> 0`` (``ValueError``); a traced value ``<= 0`` or NaN
            (inside ``jit``) accepts no correspondence (``TOO_FEW_CORRESPONDENCES`` unless
            the pairs suffice).
        loss: ``"l2"``, ``"huber"``, ``"cauchy"`` or ``"tukey"`` (IRLS; static).
        loss_scale: scale of the robust loss (m).
        tolerance: convergence threshold on the step length ``|(L theta, delta)|`` (m). The
            default, 0.1 mm, is far below depth-sensor noise; with noisy data the discrete
            correspondences make smaller steps oscillate instead of converging.
        degenerate_rtol: ``DEGENERATE`` when ``lambda_min <= degenerate_rtol * lambda_max`` of
            the scaled normal equations (see ``IcpResult.conditioning``: about 0.1 for a
            face, 0 for an exact plane or sphere). This catches exactly or nearly degenerate
            geometry only: noisy *estimated* normals fill the null space, e.g. a plane with
            Kinect-like noise at 0.9 m gives 0.02-0.2 (normal radius 4-1 px).
        damping: Levenberg damping relative to ``lambda_max``.
        min_correspondences: fewer inliers give ``TOO_FEW_CORRESPONDENCES`` (the pairs of
            ``point_pairs`` / ``pixel_pairs`` with positive weight count as inliers too).
        chunk_size: source points per block of the distance computation (static).
        point_pairs: optional fixed point-to-point correspondences ``(source (k, 3), target
            (k, 3), weights (k,))``, e.g. matched features lifted to 3-D: the cost gains
            ``sum_k weights_k |R source_k + t - target_k|^2`` (see "Fixed point pairs" in the
            module docstring). ``weights`` are inverse variances per coordinate (1/m^2),
            ``(k,)``, or information matrices (inverse covariances of the residual ``R
            source_k - target_k``) ``(k, 3, 3)``, for anisotropic noise; non-finite rows and
            weights ``<= 0`` (zero trace) are ignored. With the default ``pair_loss="l2"``
            the pairs are not robustified (pass inliers, e.g. of :func:`phjax.ransac_align`);
            a robust ``pair_loss`` (below) down-weights or drops them every iteration.
        dense_sigma: with ``point_pairs`` or ``pixel_pairs`` (a ``ValueError`` without
            either): the noise std (m) of a unit-weight point-to-plane
            residual; ``None`` (default) estimates it every iteration as the robust-weighted
            RMS residual (the usual IRLS scale estimate).
        pair_weight: relative weight of the pairs (multiplies ``weights``; 1 = both terms
            weighted by their noise models alone).
        pair_loss, pair_loss_scale: robust loss of the pairs' Mahalanobis distances
            ``sqrt(e_k^T W_k e_k)`` (dimensionless; e.g. ``"tukey"`` with scale 3 drops pairs
            more than 3 standard deviations off), re-evaluated every iteration. Default
            ``"l2"``: every pair counts.
        pair_gate: with a robust ``pair_loss``: the loss scale of pair ``k`` is at least the
            current ``max_correspondence_distance`` in its noise units, ``d_i sqrt(tr W_k /
            3)``, so a coarse-to-fine distance schedule shrinks the gate with the dense term's.
        pixel_pairs: optional fixed 3-D -> pixel correspondences ``(source (k, 3), uv (k, 2),
            weights)``: source points and their observed pixels ``(u, v)`` in the target
            camera; the cost gains the reprojection terms ``sum_k e_k^T W_k e_k``, ``e_k =
            pi(R source_k + t) - uv_k`` (px, ``pi`` the pinhole projection with
            ``pixel_intrinsics``), the sparse term of RGB-D odometry (see "Reprojection
            pairs" in the module docstring). ``weights``: inverse pixel variances (1/px^2)
            ``(k,)`` or information matrices ``(k, 2, 2)``; non-finite rows, weights ``<= 0``
            and points behind the camera are ignored.
        pixel_intrinsics: the target camera's intrinsics for ``pixel_pairs`` (required here;
            :func:`icp_projective` defaults to its ``intrinsics``).
        pixel_weight, pixel_loss, pixel_loss_scale: as ``pair_weight``, ``pair_loss``,
            ``pair_loss_scale`` for the reprojection residuals (Mahalanobis distance
            ``sqrt(e_k^T W_k e_k)``, dimensionless).
        pixel_gate: with a robust ``pixel_loss``: the loss scale of pair ``k`` is at least the
            current ``max_correspondence_distance`` seen at the point's depth, ``d_i f / z_k
            sqrt(tr W_k / 2)`` (``f = (fx + fy) / 2``): wide while the dense term is coarse,
            ``pixel_loss_scale`` at the end, so that matches are re-selected every iteration.

    Returns:
        An :class:`IcpResult` mapping source into target coordinates.

    Raises:
        ValueError: (at trace time) for wrong shapes or options.
    """
    source, target, normals = (jnp.asarray(a) for a in (source, target, target_normals))
    _check_points("source", source)
    _check_points("target", target)
    if normals.shape != target.shape:
        raise ValueError(
            f"target_normals must have the shape of target {tuple(target.shape)}, got "
            f"{tuple(normals.shape)}"
        )
    if int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    dtype = _float_dtype(source, target, normals)
    src, src_ok, q0, t0, dist, scale = _common_setup(
        source, source_valid, initial_rotation, initial_translation,
        max_correspondence_distance, num_iterations, loss, loss_scale, dtype, damping)
    tgt, nrm, tgt_ok = _prepare_target(target, normals, target_valid, dtype)
    sparse = _sparse_kwargs(point_pairs, dense_sigma, pair_weight, pair_loss, pair_loss_scale,
                            pair_gate, pixel_pairs, pixel_intrinsics, pixel_weight, pixel_loss,
                            pixel_loss_scale, pixel_gate, dtype)
    # solve relative to a source point and its predicted image (module docstring)
    ox, oy = _local_origins(src, src_ok, q0, t0, sparse["pairs"], sparse["pix"],
                            shift_target=True)
    tgt = jnp.where(tgt_ok[:, None], tgt - oy, 0)
    associate = _nearest_neighbour_associator(tgt, nrm, tgt_ok, src.shape[0], int(chunk_size))

    return _run_icp(
        associate, src, src_ok, q0, t0, dist,
        num_iterations=int(num_iterations), loss=loss, loss_scale=scale,
        tolerance=tolerance, degenerate_rtol=degenerate_rtol,
        damping=damping, min_correspondences=int(min_correspondences),
        origins=(ox, oy), **sparse,
    )


def icp_projective(
    source: Float[ArrayLike, "n 3"],
    target_points: Float[ArrayLike, "h w 3"],
    target_normals: Float[ArrayLike, "h w 3"],
    intrinsics: Any,
    *,
    source_valid: Bool[ArrayLike, " n"] | None = None,
    target_valid: Bool[ArrayLike, "h w"] | None = None,
    initial_rotation: Float[ArrayLike, "4"] | None = None,
    initial_translation: Float[ArrayLike, "3"] | None = None,
    num_iterations: int = 20,
    max_correspondence_distance: float | Float[ArrayLike, " iters"] = 0.02,
    loss: str = "l2",
    loss_scale: float = 0.005,
    tolerance: float = 1e-4,
    degenerate_rtol: float = 1e-3,
    damping: float = 1e-9,
    min_correspondences: int = 10,
    point_pairs: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    dense_sigma: float | None = None,
    pair_weight: float = 1.0,
    pair_loss: str = "l2",
    pair_loss_scale: float = 3.0,
    pair_gate: bool = False,
    pixel_pairs: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    pixel_intrinsics: Any = None,
    pixel_weight: float = 1.0,
    pixel_loss: str = "l2",
    pixel_loss_scale: float = 3.0,
    pixel_gate: bool = False,
) -> IcpResult:
    """Point-to-plane ICP with projective data association on an organised target.

    Each source point, transformed into the target camera frame, is projected with
    ``intrinsics`` and paired with the target point at the nearest pixel (``O(N)`` per
    iteration). Suited to consecutive depth frames (small motion, good initial guess).

    Arguments:
        source: source points ``(n, 3)`` (e.g. ``backproject(depth_k)[mask]`` or the
            reshaped organised cloud with ``source_valid``); non-finite rows are ignored.
        target_points: organised target cloud ``(h, w, 3)`` in the target camera frame
            (e.g. :func:`backproject`); valid where finite and ``z > 0``; may be empty
            (``h w = 0``: no dense correspondence).
        target_normals: ``(h, w, 3)`` unit normals (zero = none), e.g. :func:`estimate_normals`.
        intrinsics: the target camera's :class:`PinholeIntrinsics` (or ``(fx, fy, cx, cy)``).
        target_valid: optional ``(h, w)`` mask (e.g. a face region).
        Other arguments: as :func:`icp_point_to_plane`.

    Returns:
        An :class:`IcpResult` mapping source coordinates into the target camera frame.

    Raises:
        ValueError: (at trace time) for wrong shapes or options.
    """
    source, tp, tn = (jnp.asarray(a) for a in (source, target_points, target_normals))
    _check_points("source", source)
    _check_points("target_points", tp, ndim=3)
    if tn.shape != tp.shape:
        raise ValueError(
            f"target_normals must have the shape of target_points {tuple(tp.shape)}, got "
            f"{tuple(tn.shape)}"
        )
    dtype = _float_dtype(source, tp, tn)
    src, src_ok, q0, t0, dist, scale = _common_setup(
        source, source_valid, initial_rotation, initial_translation,
        max_correspondence_distance, num_iterations, loss, loss_scale, dtype, damping)
    fx, fy, cx, cy = _intrinsics(intrinsics, dtype)
    h, w = tp.shape[:2]
    tgt = tp.astype(dtype).reshape(-1, 3)
    nrm = tn.astype(dtype).reshape(-1, 3)
    tgt_ok = (jnp.all(jnp.isfinite(tgt), axis=-1) & jnp.all(jnp.isfinite(nrm), axis=-1)
              & (tgt[:, 2] > 0) & (jnp.sum(nrm * nrm, axis=-1) > 0))
    if target_valid is not None:
        tv = jnp.asarray(target_valid)
        if tv.shape != (h, w):
            raise ValueError(f"target_valid must have shape ({h}, {w}), got {tuple(tv.shape)}")
        tgt_ok = tgt_ok & tv.reshape(-1).astype(bool)
    tgt = jnp.where(tgt_ok[:, None], tgt, 0)
    nrm = jnp.where(tgt_ok[:, None], safe_normalize(nrm), 0)
    n = src.shape[0]

    def associate(x: Array, max_dist: Array) -> _Assoc:
        if n == 0 or h * w == 0:
            return _Assoc(jnp.zeros_like(x), jnp.zeros_like(x), jnp.zeros(n, bool))
        z = x[:, 2]
        front = z > 0
        zs = jnp.where(front, z, 1)
        u = jnp.clip(jnp.round(fx * x[:, 0] / zs + cx), -1, w)
        v = jnp.clip(jnp.round(fy * x[:, 1] / zs + cy), -1, h)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = (jnp.clip(v, 0, h - 1).astype(jnp.int32) * w
               + jnp.clip(u, 0, w - 1).astype(jnp.int32))
        y, nn = tgt[idx], nrm[idx]
        d2 = jnp.sum((x - y) ** 2, axis=-1)
        return _Assoc(y, nn, inside & tgt_ok[idx] & (d2 <= max_dist * max_dist))

    sparse = _sparse_kwargs(point_pairs, dense_sigma, pair_weight, pair_loss, pair_loss_scale,
                            pair_gate, pixel_pairs,
                            intrinsics if pixel_intrinsics is None else pixel_intrinsics,
                            pixel_weight, pixel_loss, pixel_loss_scale, pixel_gate, dtype)
    # the source relative to one of its points; the target stays in the camera frame, where
    # the points are projected (module docstring)
    origins = _local_origins(src, src_ok, q0, t0, sparse["pairs"], sparse["pix"],
                             shift_target=False)
    return _run_icp(
        associate, src, src_ok, q0, t0, dist,
        num_iterations=int(num_iterations), loss=loss, loss_scale=scale,
        tolerance=tolerance, degenerate_rtol=degenerate_rtol,
        damping=damping, min_correspondences=int(min_correspondences),
        origins=origins, **sparse,
    )

