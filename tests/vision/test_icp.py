"""Tests for phjax.vision.icp: point-to-plane ICP (nearest-neighbour and projective association),
back-projection and normal estimation.

References are independent of the implementation: known rigid motions of analytic surfaces,
analytic plane / sphere normals, and a point-to-point ICP built from scipy (``cKDTree`` nearest
neighbours + the SVD Kabsch solution) for the convergence comparison. To keep the file fast,
problems have fixed sizes and go through a few module-level ``jax.jit`` functions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from phjax import align
from phjax.vision.icp import (
    DEGENERATE,
    NOT_CONVERGED,
    OK,
    TOO_FEW_CORRESPONDENCES,
    IcpResult,
    IcpStatus,
    PinholeIntrinsics,
    backproject,
    estimate_normals,
    icp_point_to_plane,
    icp_projective,
)

H, W = 40, 50
K = PinholeIntrinsics(100.0, 100.0, (W - 1) / 2, (H - 1) / 2)
SCHEDULE = np.concatenate([np.geomspace(0.1, 0.02, 10), np.full(20, 0.02)])


# --------------------------------------------------------------------------------- scenes
def bumpy_depth(h=H, w=W, k=K):
    """A smooth, well-conditioned (non-symmetric) surface seen by the camera, ~0.8 m away."""
    a = (np.arange(w) - k.cx) / k.fx
    b = (np.arange(h)[:, None] - k.cy) / k.fy
    return (0.8 + 0.04 * np.sin(6 * a + 1) * np.cos(5 * b)
            + 0.03 * np.exp(-((a - 0.1) ** 2 + (b + 0.05) ** 2) / 0.01) + 0.05 * a * b)


def motion(rotvec, shift, centre):
    """``(q wxyz, t)`` of the rotation ``rotvec`` about ``centre`` followed by ``shift``."""
    r = Rotation.from_rotvec(rotvec)
    q = np.roll(r.as_quat(), 1)
    t = centre - r.apply(centre) + shift
    return q, t


def inverse_apply(q, t, y):
    """Source points ``s`` with ``R s + t = y``."""
    r = Rotation.from_quat(np.roll(q, -1))
    return r.inv().apply(y - t)


def pose_errors(res: IcpResult, q, t):
    r_est = Rotation.from_quat(np.roll(np.asarray(res.rotation, np.float64), -1))
    r_true = Rotation.from_quat(np.roll(q, -1))
    ang = (r_est * r_true.inv()).magnitude()
    return ang, float(np.linalg.norm(np.asarray(res.translation, np.float64) - t))


TARGET = np.asarray(backproject(bumpy_depth(), K))  # (H, W, 3)
NORMALS = np.asarray(estimate_normals(TARGET))
CENTRE = TARGET.reshape(-1, 3).mean(0)
Q1, T1 = motion(np.deg2rad(8.0) * np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5]),
                np.array([0.02, -0.015, 0.01]), CENTRE)
SOURCE1 = inverse_apply(Q1, T1, TARGET.reshape(-1, 3))

_nn = jax.jit(icp_point_to_plane, static_argnames=("num_iterations", "loss", "chunk_size",
                                                  "pixel_loss", "pixel_gate"))
_proj = jax.jit(icp_projective, static_argnames=("num_iterations", "loss"))


def run_nn(src, tgt=None, nrm=None, *, num_iterations=30, **kw):
    """NN ICP with every array argument given explicitly, so that calls with the same shapes,
    loss and iteration budget share one compilation."""
    tgt = TARGET.reshape(-1, 3) if tgt is None else tgt
    nrm = NORMALS.reshape(-1, 3) if nrm is None else nrm
    dtype = np.asarray(src).dtype
    kw.setdefault("source_valid", np.ones(len(src), bool))
    kw.setdefault("target_valid", np.ones(len(tgt), bool))
    kw.setdefault("initial_rotation", np.array([1.0, 0, 0, 0], dtype))
    kw.setdefault("initial_translation", np.zeros(3, dtype))
    dist = np.asarray(kw.pop("max_correspondence_distance", SCHEDULE[:num_iterations]), dtype)
    kw["max_correspondence_distance"] = np.broadcast_to(dist, (num_iterations,))
    kw["tolerance"] = jnp.asarray(kw.get("tolerance", 1e-4), dtype)
    kw["loss_scale"] = jnp.asarray(kw.get("loss_scale", 0.005), dtype)
    return _nn(src, tgt, nrm, num_iterations=num_iterations, **kw)


def run_proj(src, **kw):
    """Projective ICP onto ``TARGET`` (one compilation per dtype)."""
    dtype = np.asarray(src).dtype
    kw.setdefault("source_valid", np.ones(len(src), bool))
    kw.setdefault("initial_rotation", np.array([1.0, 0, 0, 0], dtype))
    kw.setdefault("initial_translation", np.zeros(3, dtype))
    kw["tolerance"] = jnp.asarray(kw.get("tolerance", 1e-4), dtype)
    return _proj(src, TARGET.astype(dtype), NORMALS.astype(dtype), K, num_iterations=30,
                 max_correspondence_distance=SCHEDULE.astype(dtype), **kw)


# ------------------------------------------------------------------------ depth utilities
def test_backproject_inverts_projection_and_marks_invalid():
    depth = bumpy_depth()
    depth[3, 4] = 0.0
    depth[5, 6] = np.nan
    depth[7, 8] = -1.0
    p = np.asarray(backproject(depth, K))
    assert p.shape == (H, W, 3) and np.all(np.isfinite(p))
    for i, j in [(3, 4), (5, 6), (7, 8)]:
        np.testing.assert_array_equal(p[i, j], 0.0)
    valid = p[..., 2] > 0
    assert valid.sum() == H * W - 3
    uv = np.asarray(K.project(p))
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    np.testing.assert_allclose(uv[valid, 0], jj[valid], atol=1e-9)
    np.testing.assert_allclose(uv[valid, 1], ii[valid], atol=1e-9)
    np.testing.assert_allclose(p[valid, 2], depth[valid])
    # a tuple of intrinsics works the same; K matrix matches
    p2 = backproject(depth, (K.fx, K.fy, K.cx, K.cy))
    np.testing.assert_array_equal(p, p2)
    np.testing.assert_allclose(K.matrix, [[100, 0, K.cx], [0, 100, K.cy], [0, 0, 1]])
    with pytest.raises(ValueError, match="intrinsics"):
        backproject(depth, (1.0, 2.0))


def plane_depth(n, d, h=H, w=W, k=K):
    """Depth image of the plane ``n . X = d``."""
    a = (np.arange(w) - k.cx) / k.fx
    b = (np.arange(h)[:, None] - k.cy) / k.fy
    return d / (n[0] * a + n[1] * b + n[2])


def test_normals_of_a_plane_are_exact_and_face_the_camera():
    n = np.array([0.2, -0.3, 1.0])
    n /= np.linalg.norm(n)
    depth = plane_depth(n, 0.9)
    depth[10, 10] = 0.0  # a hole: its neighbours fall back to one-sided differences
    normals = np.asarray(estimate_normals(backproject(depth, K)))
    valid = np.any(normals != 0, axis=-1)
    assert not valid[10, 10] and valid.sum() == H * W - 1  # borders use one-sided differences
    np.testing.assert_allclose(normals[valid], np.broadcast_to(-n, (valid.sum(), 3)), atol=1e-9)


def sphere_normal_errors(k, h, w):
    """Angles (deg) between estimated and radial normals of a sphere seen by camera ``k``."""
    centre = np.array([0.02, -0.01, 1.0])
    radius = 0.25
    a = (np.arange(w) - k.cx) / k.fx
    b = (np.arange(h)[:, None] - k.cy) / k.fy
    ray = np.stack(np.broadcast_arrays(a, b, np.ones_like(b)), -1)
    qa = np.sum(ray * ray, -1)  # first intersection of s * ray with the sphere
    qb = -2 * ray @ centre
    qc = centre @ centre - radius**2
    disc = qb * qb - 4 * qa * qc
    s = np.where(disc > 0, (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa), 0.0)
    pts = np.asarray(backproject(s, k))
    normals = np.asarray(estimate_normals(pts))
    valid = np.any(normals != 0, -1)
    assert valid.sum() > 0.3 * h * w
    assert not np.any(valid & (s == 0))
    radial = (pts - centre) / radius
    cosang = np.sum(normals[valid] * radial[valid], -1)
    assert np.all(cosang > 0.9)  # outward (towards the camera) everywhere, incl. grazing
    view = -np.sum(radial[valid] * ray[valid], -1) / np.linalg.norm(ray[valid], axis=-1)
    return np.degrees(np.arccos(np.clip(cosang[view > 0.5], -1, 1)))


def test_normals_of_a_sphere_are_radial_and_converge_with_resolution():
    coarse = sphere_normal_errors(K, H, W)  # pixel pitch 1 cm on a 25 cm sphere
    fine_k = PinholeIntrinsics(400.0, 400.0, (4 * W - 1) / 2, (4 * H - 1) / 2)
    fine = sphere_normal_errors(fine_k, 4 * H, 4 * W)  # 2.5 mm pitch
    assert np.max(coarse) < 3.0
    assert np.max(fine) < np.max(coarse) / 3  # first-order (one-pixel chords) or better


def test_normals_do_not_mix_across_depth_discontinuities_and_stay_finite():
    n = np.array([0.0, 0.0, 1.0])
    depth = plane_depth(n, 0.8)
    depth[:, W // 2:] = plane_depth(np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1), 1.5)[:, W // 2:]
    depth[0, :5] = np.nan
    depth[-1, :] = np.inf
    pts = backproject(depth, K)
    normals = np.asarray(estimate_normals(pts))
    assert np.all(np.isfinite(normals))
    left = normals[1:-1, : W // 2]
    np.testing.assert_allclose(left[np.any(left != 0, -1)], [[0, 0, -1]] * np.sum(
        np.any(left != 0, -1)), atol=1e-9)
    assert np.all(normals[-1] == 0) and np.all(normals[0, :5] == 0)
    # larger radius: same exact normal on the plane
    n2 = np.asarray(estimate_normals(pts, radius=3))
    left2 = n2[1:-1, : W // 2]
    np.testing.assert_allclose(left2[np.any(left2 != 0, -1)][:, 2], -1, atol=1e-9)
    with pytest.raises(ValueError, match="radius"):
        estimate_normals(pts, radius=0)
    with pytest.raises(ValueError, match="shape"):
        estimate_normals(np.zeros((4, 3)))


# ------------------------------------------------------------------------------ ICP: exact
def test_nearest_neighbour_icp_recovers_a_known_motion_exactly():
    res = run_nn(SOURCE1, tolerance=1e-10)
    ang, dt = pose_errors(res, Q1, T1)
    assert int(res.status) == OK, IcpStatus.name(int(res.status))
    assert ang < 1e-8 and dt < 1e-8
    assert int(res.num_inliers) == H * W and float(res.rmse) < 1e-8
    assert int(res.num_iterations) < 30
    assert float(res.rotation[0]) >= 0
    np.testing.assert_allclose(res.transform(SOURCE1), TARGET.reshape(-1, 3), atol=1e-8)
    np.testing.assert_allclose(res.rotation_matrix, Rotation.from_quat(np.roll(Q1, -1))
                               .as_matrix(), atol=1e-8)


def test_default_tolerance_still_gives_micrometre_accuracy():
    res = run_nn(SOURCE1)  # default tolerance 0.1 mm: the last Gauss-Newton step is quadratic
    ang, dt = pose_errors(res, Q1, T1)
    assert int(res.status) == OK and ang < 1e-6 and dt < 1e-6


def test_projective_icp_recovers_a_known_motion_exactly():
    q, t = motion(np.deg2rad(3.0) * np.array([0.6, 0.0, 0.8]), np.array([0.01, 0.005, -0.01]),
                  CENTRE)
    src = inverse_apply(q, t, TARGET.reshape(-1, 3))
    res = run_proj(src, tolerance=1e-10)
    ang, dt = pose_errors(res, q, t)
    assert int(res.status) == OK
    assert ang < 1e-8 and dt < 1e-8 and int(res.num_inliers) == H * W


def test_initial_guess_is_used():
    # start at the solution: converges immediately; start far off with a tight gate: fails
    res = run_nn(SOURCE1, initial_rotation=Q1, initial_translation=T1,
                 max_correspondence_distance=1e-3)
    assert int(res.status) == OK and int(res.num_iterations) == 1
    ang, dt = pose_errors(res, Q1, T1)
    assert ang < 1e-9 and dt < 1e-9


@settings(max_examples=8)
@given(
    axis=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2),
    angle=st.floats(0.0, np.deg2rad(10.0)),
    shift=st.tuples(*[st.floats(-0.03, 0.03)] * 3),
)
def test_property_recovers_random_rigid_motions(axis, angle, shift):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    q, t = motion(angle * axis, np.asarray(shift), CENTRE)
    res = run_nn(inverse_apply(q, t, TARGET.reshape(-1, 3)), tolerance=1e-10)
    ang, dt = pose_errors(res, q, t)
    assert int(res.status) == OK and ang < 1e-6 and dt < 1e-6


# ------------------------------------------------------------------------------ ICP: noise
def test_noisy_data_recovers_the_motion_to_sensor_accuracy():
    rng = np.random.default_rng(1)
    depth = bumpy_depth() + rng.normal(0, 1e-3, (H, W))
    tgt = np.asarray(backproject(depth, K))
    nrm = np.asarray(estimate_normals(tgt, radius=2))
    src = SOURCE1 + rng.normal(0, 1e-3, SOURCE1.shape)
    for loss in ("l2", "huber"):
        res = run_nn(src, tgt.reshape(-1, 3), nrm.reshape(-1, 3), loss=loss,
                     loss_scale=0.002)
        ang, dt = pose_errors(res, Q1, T1)
        # measured (both losses): OK, 0.087 deg and 0.77-0.81 mm (1 mm noise on both clouds);
        # bounds about 2.3x
        assert int(res.status) == OK
        assert np.degrees(ang) < 0.2 and dt < 1.8e-3, (loss, np.degrees(ang), dt)
        assert 5e-4 < float(res.rmse) < 3e-3


def test_robust_loss_rejects_outliers():
    rng = np.random.default_rng(2)
    src = SOURCE1.copy()
    bad = rng.random(len(src)) < 0.25  # a quarter of the points displaced 8-15 mm
    off = rng.uniform(0.008, 0.015, bad.sum()) * rng.choice([-1, 1], bad.sum())
    src[bad] = src[bad] + off[:, None] * np.array([0.0, 0.0, 1.0])
    res = {loss: run_nn(src, loss=loss, loss_scale=0.003) for loss in ("l2", "huber", "cauchy")}
    err = {k: pose_errors(v, Q1, T1) for k, v in res.items()}
    for loss in ("huber", "cauchy"):
        assert err[loss][0] < 0.5 * err["l2"][0] and err[loss][1] < 0.5 * err["l2"][1]
    # and absolutely (measured: l2 0.87 deg / 1.18 mm, huber 0.27 deg / 0.41 mm, cauchy
    # 0.070 deg / 0.087 mm; bounds 1.5x)
    for loss, deg, metres in (("huber", 0.4, 6e-4), ("cauchy", 0.1, 1.3e-4)):
        assert int(res[loss].status) == OK
        assert np.degrees(err[loss][0]) < deg and err[loss][1] < metres, (loss, err[loss])
    # Tukey's redescending loss rejects everything far away: from the identity no point has a
    # positive weight (too few correspondences); from a nearby start it removes the outliers
    far = run_nn(src, loss="tukey", loss_scale=0.003)
    assert int(far.status) in (TOO_FEW_CORRESPONDENCES, DEGENERATE)
    np.testing.assert_array_equal(far.rotation, [1, 0, 0, 0])
    near = run_nn(src, loss="tukey", loss_scale=0.003, initial_rotation=res["cauchy"].rotation,
                  initial_translation=res["cauchy"].translation)
    ang, dt = pose_errors(near, Q1, T1)
    assert int(near.status) == OK and ang < 1e-6 and dt < 1e-6


# ---------------------------------------------------------------- fixed point pairs (sparse)
def pair_problem(q, t, n=40, noise=0.0, seed=3):
    """``n`` points near the surface mapped by ``(q, t)`` (+ noise), and positive weights."""
    rng = np.random.default_rng(seed)
    s = CENTRE + rng.normal(0, 0.1, (n, 3))
    y = Rotation.from_quat(np.roll(q, -1)).apply(s) + t + rng.normal(0, noise, (n, 3))
    return s, y, rng.uniform(0.2, 2.0, n) * 1e4


def test_point_pairs_alone_are_the_weighted_kabsch_problem():
    # no dense correspondence (every source point masked): the objective is sum w |R s + t - y|^2
    s, y, w = pair_problem(Q1, T1, noise=0.01)
    w[::7] = 0  # unused pairs
    ref = align(s, y, w)
    none = np.zeros(len(SOURCE1), bool)
    for res in (run_nn(SOURCE1, source_valid=none, point_pairs=(s, y, w), tolerance=1e-12),
                run_proj(SOURCE1, source_valid=none, point_pairs=(s, y, w), tolerance=1e-12)):
        assert int(res.status) == OK and int(res.num_inliers) == 0
        np.testing.assert_allclose(res.rotation, ref.quaternion, atol=1e-10)
        np.testing.assert_allclose(res.translation, ref.translation, atol=1e-10)
    # the pairs alone must number at least min_correspondences
    few = run_nn(SOURCE1, source_valid=none, point_pairs=(s[:5], y[:5], w[:5]))
    assert int(few.status) == TOO_FEW_CORRESPONDENCES


def test_point_pairs_join_the_dense_objective():
    # dense data consistent with (Q1, T1), pairs with a motion 1 degree / 1 cm away
    extra = Rotation.from_rotvec(np.deg2rad(1.0) * np.array([0.0, 0.6, 0.8]))
    q2 = np.roll((extra * Rotation.from_quat(np.roll(Q1, -1))).as_quat(), 1)
    t2 = T1 + np.array([0.01, 0, 0])
    s, y, w = pair_problem(q2, t2)
    rng = np.random.default_rng(4)
    a = rng.normal(size=(len(s), 3, 3))
    info = w[:, None, None] * (np.einsum("kij,klj->kil", a, a) + 0.1 * np.eye(3))  # anisotropic
    sigma = 2e-3
    errs = []
    for scale in (1e-9, 1.0, 1e9):
        res = run_nn(SOURCE1, point_pairs=(s, y, info), pair_weight=scale, dense_sigma=sigma,
                     tolerance=1e-12,
                     num_iterations=40, max_correspondence_distance=0.05)
        assert int(res.status) == OK
        errs.append((pose_errors(res, Q1, T1), pose_errors(res, q2, t2)))
        if scale == 1.0:
            # stationary point of the joint cost with the final correspondences (independent
            # solver: scipy least squares over a rotation vector and a translation)
            from scipy.optimize import least_squares

            tree = cKDTree(TARGET.reshape(-1, 3))
            rot0 = Rotation.from_quat(np.roll(np.asarray(res.rotation), -1))
            _, idx = tree.query(rot0.apply(SOURCE1) + np.asarray(res.translation))
            yt, nt = TARGET.reshape(-1, 3)[idx], NORMALS.reshape(-1, 3)[idx]

            def resid(p):
                rot = Rotation.from_rotvec(p[:3]) * rot0  # noqa: B023
                x = rot.apply(SOURCE1) + p[3:]
                xp = rot.apply(s) + p[3:]
                chol = np.linalg.cholesky(info)  # e^T info e = |chol^T e|^2
                return np.concatenate([np.sum(nt * (x - yt), -1) / sigma,  # noqa: B023
                                       np.einsum("kij,ki->kj", chol, xp - y).ravel()])

            x0 = np.concatenate([np.zeros(3), np.asarray(res.translation)])
            sol = least_squares(resid, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
            assert np.linalg.norm(sol.x[:3]) < 1e-9 and np.linalg.norm(sol.x[3:] - x0[3:]) < 1e-9
    # tiny pair weights: the dense motion; huge: the pairs' motion; in between: neither
    (d_lo, p_lo), (d_mid, p_mid), (d_hi, p_hi) = errs
    assert d_lo[0] < 1e-6 and d_lo[1] < 1e-6
    assert p_hi[0] < 1e-6 and p_hi[1] < 1e-6
    assert min(d_mid[1], p_mid[1]) > 1e-4
    # a robust pair loss on the Mahalanobis distance drops pairs far off
    s, y, w = pair_problem(Q1, T1)
    w = w * 100  # sigma 0.7-2.2 mm
    bad = np.arange(len(s)) % 5 == 0
    y_bad = y + bad[:, None] * np.array([0.0, 0.05, 0.0])  # 5 cm off
    none = np.zeros(len(SOURCE1), bool)
    q0, t0 = np.roll(Rotation.from_rotvec([0.0, 0.002, 0.0]).as_quat(), 1), T1 + 5e-4
    q0 = np.roll((Rotation.from_quat(np.roll(q0, -1)) * Rotation.from_quat(np.roll(Q1, -1)))
                 .as_quat(), 1)
    kw = dict(source_valid=none, num_iterations=30, tolerance=1e-12, initial_rotation=q0,
              initial_translation=t0)
    tgt, nrm = TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3)
    res = icp_point_to_plane(SOURCE1, tgt, nrm, point_pairs=(s, y_bad, w), pair_loss="tukey",
                             pair_loss_scale=4.685, **kw)
    assert int(res.status) == OK
    ang, dt = pose_errors(res, Q1, T1)
    assert ang < 1e-9 and dt < 1e-9
    plain = icp_point_to_plane(SOURCE1, tgt, nrm, point_pairs=(s, y_bad, w), **kw)
    assert pose_errors(plain, Q1, T1)[1] > 1e-3
    with pytest.raises(ValueError, match="loss"):
        icp_point_to_plane(SOURCE1, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3),
                           point_pairs=(s, y, w), pair_loss="l1")
    with pytest.raises(ValueError, match="dense_sigma"):
        icp_point_to_plane(SOURCE1, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3),
                           dense_sigma=0.01)
    with pytest.raises(ValueError, match="point_pairs"):
        icp_point_to_plane(SOURCE1, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3),
                           point_pairs=(s, y, w[:-1]))


def pixel_problem(q, t, n=60, noise=0.0, seed=5):
    """``n`` 3-D points near the surface and their pixels in the target camera ``K`` after the
    motion ``(q, t)`` (+ pixel noise)."""
    rng = np.random.default_rng(seed)
    s = CENTRE + rng.normal(0, 0.1, (n, 3))
    x = Rotation.from_quat(np.roll(q, -1)).apply(s) + t
    uv = np.stack([K.fx * x[:, 0] / x[:, 2] + K.cx, K.fy * x[:, 1] / x[:, 2] + K.cy], -1)
    return s, uv + rng.normal(0, noise, uv.shape)


def test_pixel_pairs_alone_are_the_pnp_problem():
    # no dense correspondence: the objective is the reprojection error, i.e. PnP. Noise-free
    # pixels give the exact motion; with 1 px noise the minimiser equals cv2.solvePnP's
    # (SOLVEPNP_ITERATIVE, Levenberg-Marquardt on the same cost, its own initialisation) to
    # cv2's convergence tolerance.
    import cv2

    none = np.zeros(len(SOURCE1), bool)
    kw = dict(source_valid=none, tolerance=1e-12, pixel_intrinsics=K)
    s, uv = pixel_problem(Q1, T1)
    res = run_nn(SOURCE1, pixel_pairs=(s, uv, np.ones(len(s))), **kw)
    assert int(res.status) == OK and int(res.num_inliers) == 0
    ang, dt = pose_errors(res, Q1, T1)
    assert ang < 1e-10 and dt < 1e-10
    s, uv = pixel_problem(Q1, T1, noise=1.0)
    kmat = np.asarray(K.matrix, np.float64)
    ok, rvec, tvec = cv2.solvePnP(s, uv, kmat, None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    q_cv = np.roll(Rotation.from_rotvec(rvec.ravel()).as_quat(), 1)
    for res in (run_nn(SOURCE1, pixel_pairs=(s, uv, np.full(len(s), 4.0)), **kw),
                run_proj(SOURCE1, pixel_pairs=(s, uv, np.ones(len(s))), source_valid=none,
                         tolerance=1e-12)):  # icp_projective: its intrinsics by default
        assert int(res.status) == OK
        ang, dt = pose_errors(res, q_cv, tvec.ravel())
        # (cv2 stops its Levenberg-Marquardt after 20 steps or a relative change of FLT_EPSILON)
        assert ang < 1e-5 and dt < 1e-5, (ang, dt)
        assert pose_errors(res, Q1, T1)[1] > 1e-4  # the noise moved the optimum
    few = run_nn(SOURCE1, pixel_pairs=(s[:5], uv[:5], np.ones(5)), **kw)
    assert int(few.status) == TOO_FEW_CORRESPONDENCES
    with pytest.raises(ValueError, match="pixel_intrinsics"):
        icp_point_to_plane(SOURCE1, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3),
                           pixel_pairs=(s, uv, np.ones(len(s))))
    with pytest.raises(ValueError, match="pixel_pairs"):
        icp_point_to_plane(SOURCE1, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3),
                           pixel_pairs=(s, uv[:, :1], np.ones(len(s))), pixel_intrinsics=K)
    with pytest.raises(ValueError, match="loss"):
        run_nn(SOURCE1, pixel_pairs=(s, uv, np.ones(len(s))), pixel_loss="l1", **kw)


def test_pixel_pairs_join_the_dense_objective_and_gate_outliers():
    # dense data consistent with (Q1, T1), pixels of a motion 1 degree / 1 cm away, anisotropic
    # 2x2 information: the result is the stationary point of the joint cost
    from scipy.optimize import least_squares

    extra = Rotation.from_rotvec(np.deg2rad(1.0) * np.array([0.0, 0.6, 0.8]))
    q2 = np.roll((extra * Rotation.from_quat(np.roll(Q1, -1))).as_quat(), 1)
    t2 = T1 + np.array([0.01, 0, 0])
    s, uv = pixel_problem(q2, t2)
    rng = np.random.default_rng(6)
    a = rng.normal(size=(len(s), 2, 2))
    info = np.einsum("kij,klj->kil", a, a) + 0.1 * np.eye(2)
    sigma = 2e-3
    res = run_nn(SOURCE1, pixel_pairs=(s, uv, info), pixel_intrinsics=K, dense_sigma=sigma,
                 tolerance=1e-12, num_iterations=40, max_correspondence_distance=0.05)
    assert int(res.status) == OK
    assert min(pose_errors(res, Q1, T1)[1], pose_errors(res, q2, t2)[1]) > 1e-4
    tree = cKDTree(TARGET.reshape(-1, 3))
    rot0 = Rotation.from_quat(np.roll(np.asarray(res.rotation), -1))
    _, idx = tree.query(rot0.apply(SOURCE1) + np.asarray(res.translation))
    yt, nt = TARGET.reshape(-1, 3)[idx], NORMALS.reshape(-1, 3)[idx]
    chol = np.linalg.cholesky(info)

    def resid(p):
        rot = Rotation.from_rotvec(p[:3]) * rot0
        x = rot.apply(SOURCE1) + p[3:]
        xp = rot.apply(s) + p[3:]
        e = np.stack([K.fx * xp[:, 0] / xp[:, 2] + K.cx, K.fy * xp[:, 1] / xp[:, 2] + K.cy],
                     -1) - uv
        return np.concatenate([np.sum(nt * (x - yt), -1) / sigma,
                               np.einsum("kij,ki->kj", chol, e).ravel()])

    x0 = np.concatenate([np.zeros(3), np.asarray(res.translation)])
    sol = least_squares(resid, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert np.linalg.norm(sol.x[:3]) < 1e-9 and np.linalg.norm(sol.x[3:] - x0[3:]) < 1e-9
    # every fifth pixel 30 px off (wrong matches): a gated Tukey loss drops them (the gate
    # follows the distance schedule: 0.1 m at 0.8 m is 12.5 px, then 3 px at the end) and
    # the motion is exact; an L2 pixel term is pulled away
    s, uv = pixel_problem(Q1, T1)
    uv_bad = uv + (np.arange(len(s)) % 5 == 0)[:, None] * np.array([30.0, 0.0])
    kw = dict(pixel_intrinsics=K, dense_sigma=1e-3, tolerance=1e-12)
    res = run_nn(SOURCE1, pixel_pairs=(s, uv_bad, np.ones(len(s))), pixel_loss="tukey",
                 pixel_loss_scale=3.0, pixel_gate=True, **kw)
    assert int(res.status) == OK
    ang, dt = pose_errors(res, Q1, T1)
    assert ang < 1e-9 and dt < 1e-9
    plain = run_nn(SOURCE1, pixel_pairs=(s, uv_bad, np.ones(len(s))), **kw)
    assert pose_errors(plain, Q1, T1)[1] > 1e-4


# -------------------------------------------------------------- point-to-plane vs point-to-point
def corner_scene(n, rng):
    """Random points on three orthogonal faces of a box corner (plane-rich), with normals."""
    face = rng.integers(0, 3, n)
    uv = rng.uniform(0.0, 0.3, (n, 2))
    pts = np.zeros((n, 3))
    nrm = np.zeros((n, 3))
    for f in range(3):
        m = face == f
        others = [a for a in range(3) if a != f]
        pts[np.ix_(m, others)] = uv[m]
        nrm[m, f] = 1.0
    return pts + np.array([-0.1, -0.1, 0.7]), nrm


def point_to_point_icp(src, tgt, iters, gate):
    """Reference point-to-point ICP (scipy KD-tree + SVD Kabsch); returns (R, t) per iter."""
    tree = cKDTree(tgt)
    rot, t = np.eye(3), np.zeros(3)
    out = []
    for k in range(iters):
        x = src @ rot.T + t
        d, idx = tree.query(x)
        m = d < gate[k]
        a, b = x[m], tgt[idx[m]]
        ca, cb = a.mean(0), b.mean(0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        dr = vt.T @ np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        rot, t = dr @ rot, dr @ (t - ca) + cb
        out.append((rot.copy(), t.copy()))
    return out


def test_point_to_plane_converges_faster_than_point_to_point_on_planes():
    rng = np.random.default_rng(3)
    tgt, nrm = corner_scene(H * W, rng)
    src_world, _ = corner_scene(H * W, rng)  # an independent sampling of the same surfaces
    q, t = motion(np.deg2rad(5.0) * np.array([0.48, 0.6, 0.64]), np.array([0.02, -0.01, 0.015]),
                  tgt.mean(0))
    src = inverse_apply(q, t, src_world)
    r_true = Rotation.from_quat(np.roll(q, -1)).as_matrix()
    ref = point_to_point_icp(src, tgt, 8, np.full(8, 0.1))
    p2p_err = [np.linalg.norm(r @ CENTRE + tt - (r_true @ CENTRE + t)) for r, tt in ref]
    res = run_nn(src, tgt, nrm, num_iterations=3, max_correspondence_distance=0.1, tolerance=0.0)
    p2pl_err = np.linalg.norm(np.asarray(res.rotation_matrix) @ CENTRE
                              + np.asarray(res.translation) - (r_true @ CENTRE + t))
    # point-to-plane is (up to pairs straddling an edge of the box) exact after 3 steps;
    # point-to-point slides slowly along the planes: still millimetres off after 8 steps
    assert int(res.num_iterations) == 3
    assert p2pl_err < 3e-4
    assert p2p_err[-1] > 2e-3 and p2p_err[-1] > 10 * p2pl_err


# -------------------------------------------------------------------------- ICP: failures
def test_a_single_plane_is_degenerate_and_returns_the_initial_guess():
    n = np.array([0.1, 0.2, 1.0])
    n /= np.linalg.norm(n)
    tgt = np.asarray(backproject(plane_depth(n, 0.8), K))
    nrm = np.asarray(estimate_normals(tgt))
    src = tgt.reshape(-1, 3) + 0.003 * n
    q0 = np.array([1.0, 0.001, 0.0, 0.0])
    q0 /= np.linalg.norm(q0)
    res = run_nn(src, tgt.reshape(-1, 3), nrm.reshape(-1, 3), initial_rotation=q0,
                 initial_translation=np.array([0.001, 0.0, 0.0]))
    assert int(res.status) == DEGENERATE
    np.testing.assert_allclose(res.rotation, q0, atol=1e-15)
    np.testing.assert_allclose(res.translation, [0.001, 0, 0], atol=1e-15)
    assert float(res.conditioning) < 1e-10
    for leaf in jax.tree_util.tree_leaves(res):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64)))


def test_a_sphere_is_degenerate_in_rotation():
    rng = np.random.default_rng(4)
    d = rng.normal(size=(H * W, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = -np.abs(d[:, 2])
    centre = np.array([0.0, 0.0, 0.9])
    tgt = centre + 0.1 * d
    res = run_nn(tgt + 0.002, tgt, d, max_correspondence_distance=0.02)
    assert int(res.status) == DEGENERATE


def test_no_valid_points_gives_too_few_correspondences_with_finite_values():
    src = SOURCE1
    for kwargs in ({"source_valid": np.zeros(len(src), bool)},
                   {"target_valid": np.zeros(H * W, bool)}):
        res = run_nn(src, **kwargs)
        assert int(res.status) == TOO_FEW_CORRESPONDENCES
        np.testing.assert_array_equal(res.rotation, [1, 0, 0, 0])
        np.testing.assert_array_equal(res.translation, [0, 0, 0])
        assert int(res.num_inliers) == 0 and float(res.rmse) == 0
        assert np.all(np.isfinite(np.asarray(res.conditioning)))
    # all-NaN source and a target out of reach behave the same
    res = run_nn(np.full_like(src, np.nan))
    assert int(res.status) == TOO_FEW_CORRESPONDENCES
    res = run_nn(src + 10.0)
    assert int(res.status) == TOO_FEW_CORRESPONDENCES
    res = run_proj(src, source_valid=np.zeros(len(src), bool))
    assert int(res.status) == TOO_FEW_CORRESPONDENCES


def test_an_empty_target_is_like_a_fully_masked_one():
    # an empty target (0 points / a 0x0 depth image), as an empty source: no dense
    # correspondence, so only the pairs count (the weighted Kabsch problem of align) and
    # without pairs the status is TOO_FEW_CORRESPONDENCES with the initial guess returned
    s, y, w = pair_problem(Q1, T1, noise=0.01)
    ref = align(s, y, w)
    src = SOURCE1[:50]
    empty, empty_img = np.zeros((0, 3)), np.zeros((0, 0, 3))
    for fit in (lambda **kw: icp_point_to_plane(src, empty, empty, **kw),
                lambda **kw: icp_projective(src, empty_img, empty_img, K, **kw)):
        res = fit(point_pairs=(s, y, w), tolerance=1e-12, num_iterations=30)
        assert int(res.status) == OK and int(res.num_inliers) == 0
        np.testing.assert_allclose(res.rotation, ref.quaternion, atol=1e-10)
        np.testing.assert_allclose(res.translation, ref.translation, atol=1e-10)
        res = fit()
        assert int(res.status) == TOO_FEW_CORRESPONDENCES and int(res.num_inliers) == 0
        np.testing.assert_array_equal(res.rotation, [1, 0, 0, 0])
        np.testing.assert_array_equal(res.translation, [0, 0, 0])
        assert float(res.rmse) == 0 and not np.any(np.asarray(res.inlier_mask))


def test_max_correspondence_distance_must_be_positive():
    tgt, nrm = TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3)
    for bad in (-0.02, 0.0, np.nan, np.inf, [0.1, -0.1, 0.1]):
        with pytest.raises(ValueError, match="max_correspondence_distance must be finite"):
            icp_point_to_plane(SOURCE1, tgt, nrm, num_iterations=3,
                               max_correspondence_distance=bad)
        with pytest.raises(ValueError, match="max_correspondence_distance must be finite"):
            icp_projective(SOURCE1, TARGET, NORMALS, K, num_iterations=3,
                           max_correspondence_distance=bad)
    # a negative damping made the step's system indefinite (TOO_FEW_CORRESPONDENCES with
    # thousands of inliers: found by review)
    for bad in (-1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="damping must be finite and >= 0"):
            icp_point_to_plane(SOURCE1, tgt, nrm, num_iterations=3, damping=bad)
        with pytest.raises(ValueError, match="damping must be finite and >= 0"):
            icp_projective(SOURCE1, TARGET, NORMALS, K, num_iterations=3, damping=bad)
    # traced (inside jit) a distance <= 0 or NaN accepts no correspondence; a valid one works
    for d, status in ((-0.1, TOO_FEW_CORRESPONDENCES), (np.nan, TOO_FEW_CORRESPONDENCES),
                      (0.1, OK)):
        res = run_nn(SOURCE1, max_correspondence_distance=np.full(30, d))
        assert int(res.status) == status, (d, IcpStatus.name(res.status))
        assert (int(res.num_inliers) > 0) == (status == OK)


def test_project_never_puts_points_off_the_front_on_a_pixel():
    rng = np.random.default_rng(7)
    p = rng.normal(0, 1, (200, 3))
    uv = np.asarray(K.project(p))
    front = p[:, 2] > 0
    np.testing.assert_allclose(uv[front, 0], K.fx * p[front, 0] / p[front, 2] + K.cx,
                               rtol=1e-12)
    np.testing.assert_allclose(uv[front, 1], K.fy * p[front, 1] / p[front, 2] + K.cy,
                               rtol=1e-12)
    # behind the camera and on its plane (z = 0): off every image (rounded pixel < 0)
    behind = np.concatenate([p[~front], [[0.1, 0.2, 0.0], [0.0, 0.0, 0.0]]])
    uv_b = np.asarray(K.project(behind))
    assert np.all(np.round(uv_b) < 0)
    g = jax.grad(lambda x: jnp.sum(K.project(x)))(jnp.asarray(behind))
    assert np.all(np.isfinite(np.asarray(g)))


def test_budget_exhaustion_reports_not_converged():
    res = run_nn(SOURCE1, num_iterations=3, max_correspondence_distance=0.1, tolerance=0.0)
    assert int(res.status) == NOT_CONVERGED and int(res.num_iterations) == 3
    ang, _ = pose_errors(res, Q1, T1)
    assert ang < np.deg2rad(8.0) / 2  # it did improve on the initial guess


def test_nan_rows_and_masked_padding_are_ignored():
    rng = np.random.default_rng(5)
    keep = np.ones(H * W, bool)
    keep[rng.choice(H * W, 400, replace=False)] = False
    base = run_nn(SOURCE1, source_valid=keep, tolerance=1e-10)
    src = SOURCE1.copy()
    drop = np.flatnonzero(~keep)
    src[drop[:200]] = np.nan  # non-finite rows are ignored even when marked valid ...
    src[drop[200:]] = rng.normal(size=(200, 3))  # ... and masked rows whatever they hold
    valid = keep.copy()
    valid[drop[:200]] = True
    res = run_nn(src, source_valid=valid, tolerance=1e-10)
    np.testing.assert_allclose(res.rotation, base.rotation, atol=1e-12)
    np.testing.assert_allclose(res.translation, base.translation, atol=1e-12)
    assert int(res.num_inliers) == int(base.num_inliers) == keep.sum()
    assert not np.any(np.asarray(res.inlier_mask)[~keep])
    ang, dt = pose_errors(res, Q1, T1)
    assert ang < 1e-8 and dt < 1e-8


# ----------------------------------------------------------------------------- jax semantics
def test_vmap_equals_loop_and_chunking_does_not_matter():
    motions = [motion(np.deg2rad(a) * np.array(ax) / np.linalg.norm(ax), np.array(s), CENTRE)
               for a, ax, s in [(4, [1, 0, 0], [0.01, 0, 0]), (7, [0, 1, 1], [0, -0.02, 0.01]),
                                (2, [1, 1, 1], [0.0, 0.0, 0.0])]]
    srcs = np.stack([inverse_apply(q, t, TARGET.reshape(-1, 3)) for q, t in motions])
    batched = jax.jit(jax.vmap(lambda s: icp_point_to_plane(
        s, TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3), num_iterations=30,
        max_correspondence_distance=SCHEDULE)))(srcs)
    assert batched.rotation.shape == (3, 4) and batched.inlier_mask.shape == (3, H * W)
    for b in range(3):
        single = run_nn(srcs[b])
        for x, y in zip(jax.tree_util.tree_leaves(batched), jax.tree_util.tree_leaves(single)):
            np.testing.assert_allclose(np.asarray(x)[b], y, rtol=0, atol=1e-12)
    # chunk size is an implementation detail (incl. a chunk that does not divide n)
    other = run_nn(srcs[1], chunk_size=333)
    np.testing.assert_allclose(other.rotation, np.asarray(batched.rotation)[1], atol=1e-12)


def test_float32_works():
    src = SOURCE1.astype(np.float32)
    res = run_nn(src, TARGET.reshape(-1, 3).astype(np.float32),
                 NORMALS.reshape(-1, 3).astype(np.float32))
    assert res.rotation.dtype == jnp.float32 and res.translation.dtype == jnp.float32
    assert res.rmse.dtype == jnp.float32
    ang, dt = pose_errors(res, Q1, T1)
    assert int(res.status) == OK and ang < 1e-4 and dt < 1e-4
    resp = run_proj(src, initial_rotation=Q1.astype(np.float32),
                    initial_translation=(T1 + 1e-3).astype(np.float32))
    assert resp.translation.dtype == jnp.float32 and int(resp.status) == OK
    assert pose_errors(resp, Q1, T1)[1] < 1e-4


def test_status_names_and_input_validation():
    assert IcpStatus.name(OK) == "OK" and IcpStatus.name(DEGENERATE) == "DEGENERATE"
    tgt, nrm = TARGET.reshape(-1, 3), NORMALS.reshape(-1, 3)
    with pytest.raises(ValueError, match="source"):
        icp_point_to_plane(np.zeros((5, 2)), tgt, nrm)
    with pytest.raises(ValueError, match="target_normals"):
        icp_point_to_plane(SOURCE1, tgt, nrm[:-1])
    with pytest.raises(ValueError, match="loss"):
        icp_point_to_plane(SOURCE1, tgt, nrm, loss="l1")
    with pytest.raises(ValueError, match="max_correspondence_distance"):
        icp_point_to_plane(SOURCE1, tgt, nrm, num_iterations=5,
                           max_correspondence_distance=np.ones(4))
    with pytest.raises(ValueError, match="source_valid"):
        icp_point_to_plane(SOURCE1, tgt, nrm, source_valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="initial_rotation"):
        icp_point_to_plane(SOURCE1, tgt, nrm, initial_rotation=np.ones(3))
    with pytest.raises(ValueError, match="target_points"):
        icp_projective(SOURCE1, tgt, nrm, K)
    with pytest.raises(ValueError, match="target_valid"):
        icp_projective(SOURCE1, TARGET, NORMALS, K, target_valid=np.ones((2, 2), bool))
