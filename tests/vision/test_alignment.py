"""Tests for phjax.vision.alignment: closed-form weighted (similarity) alignment and RANSAC.

References are independent of the implementation (Horn's quaternion eigenvector method):
scipy's Kabsch (``Rotation.align_vectors``), a NumPy SVD implementation of Umeyama (1991),
numerical minimisation of the objective (``scipy.optimize.least_squares``), ground-truth
transforms, and central finite differences for gradients.

To keep the file fast, almost every call goes through a few module-level ``jax.jit`` functions
with a fixed number of points (``N``); special configurations are padded with zero-weight rows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from phjax.vision.alignment import (
    DEGENERATE,
    NOT_FINITE,
    OK,
    TOO_FEW_INLIERS,
    TOO_FEW_POINTS,
    AlignmentResult,
    AlignmentStatus,
    align,
    ransac_align,
    transform_points,
)

N = 8  # points per problem for align tests
M = 30  # points per problem for RANSAC tests

_align = jax.jit(align, static_argnames=("with_scale",))
_ransac = jax.jit(
    ransac_align, static_argnames=("num_iterations", "sample_size", "with_scale", "refine")
)

TETRA = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
SQUARE = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)


# ------------------------------------------------------------------------------- helpers
def objective(rot, t, s, src, tgt, w):
    r = s * src @ np.asarray(rot).T + t - tgt
    return float(np.sum(w * np.sum(r * r, axis=-1)))


def rot_angle(r_est, r_true):
    """Geodesic angle (rad) between two rotation matrices."""
    r_est = np.asarray(r_est, np.float64)
    return float(Rotation.from_matrix(r_est @ np.asarray(r_true).T).magnitude())


def pad(points, n=N, seed=0):
    """Pad a small configuration to ``n`` rows (random coordinates); returns points, weights."""
    k = len(points)
    extra = np.random.default_rng(seed).normal(size=(n - k, 3))
    return np.concatenate([points, extra]), np.concatenate([np.ones(k), np.zeros(n - k)])


def random_problem(seed, n=N, noise=0.0, reflect=False, planar=False, rotvec=None):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3))
    if planar:  # nearly planar cloud (tiny but non-zero thickness)
        src[:, 2] *= 1e-3
    rot = Rotation.from_rotvec(rotvec) if rotvec is not None else Rotation.random(random_state=rng)
    lin = rot.as_matrix()
    if reflect:
        lin = lin @ np.diag([1.0, 1.0, -1.0])
    t = rng.normal(size=3)
    tgt = src @ lin.T + t + noise * rng.normal(size=(n, 3))
    w = rng.uniform(0.2, 2.0, size=n)
    return src, tgt, w, rot.as_matrix(), t


def scipy_rotation(src, tgt, w):
    """Kabsch reference on weighted-centred points (scipy)."""
    mx = np.average(src, axis=0, weights=w)
    my = np.average(tgt, axis=0, weights=w)
    rot, _ = Rotation.align_vectors(tgt - my, src - mx, weights=w)
    return rot.as_matrix()


def umeyama_np(src, tgt, w, with_scale):
    """Umeyama (1991), weighted, via the SVD with the determinant correction (NumPy)."""
    wn = w / w.sum()
    mx, my = wn @ src, wn @ tgt
    xc, yc = src - mx, tgt - my
    cov = (yc * wn[:, None]).T @ xc  # Sigma_xy
    u, d, vt = np.linalg.svd(cov)
    sgn = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ sgn @ vt
    s = np.trace(np.diag(d) @ sgn) / np.sum(wn * np.sum(xc * xc, 1)) if with_scale else 1.0
    return rot, my - s * rot @ mx, s


def assert_identity(res: AlignmentResult):
    np.testing.assert_array_equal(np.asarray(res.rotation), np.broadcast_to(np.eye(3),
                                                                            res.rotation.shape))
    np.testing.assert_array_equal(np.asarray(res.quaternion)[..., 0], 1)
    np.testing.assert_array_equal(np.asarray(res.quaternion)[..., 1:], 0)
    np.testing.assert_array_equal(np.asarray(res.translation), 0)
    np.testing.assert_array_equal(np.asarray(res.scale), 1)
    assert np.isfinite(np.asarray(res.rms)).all()


# ----------------------------------------------------------------------- scipy (Kabsch)
@settings(max_examples=40)
@given(
    seed=st.integers(0, 2**31 - 1),
    kind=st.sampled_from(["generic", "half_turn", "reflected", "planar_reflected"]),
    noise=st.sampled_from([0.0, 0.05, 0.5]),
)
def test_rotation_matches_scipy_align_vectors(seed, kind, noise):
    rng = np.random.default_rng(seed + 1)
    rotvec = None
    if kind == "half_turn":
        axis = rng.normal(size=3)
        rotvec = np.pi * axis / np.linalg.norm(axis)
    src, tgt, w, _, _ = random_problem(
        seed, noise=noise, reflect=kind in ("reflected", "planar_reflected"),
        planar=kind == "planar_reflected", rotvec=rotvec,
    )
    res = _align(src, tgt, w)
    ref = scipy_rotation(src, tgt, w)
    assert int(res.status) == OK
    # conditioning of the rotation: relative gap of the top eigenvalue, (s2 + d s3) / s1
    mx, my = np.average(src, 0, weights=w), np.average(tgt, 0, weights=w)
    h = ((src - mx) * w[:, None]).T @ (tgt - my)
    sv = np.linalg.svd(h, compute_uv=False)
    rel_gap = (sv[1] + np.sign(np.linalg.det(h)) * sv[2]) / sv[0]
    tol = 1e-12 / max(rel_gap, 1e-6) + 1e-11
    np.testing.assert_allclose(np.asarray(res.rotation), ref, atol=tol)
    r = np.asarray(res.rotation)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-13)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-13)
    q = np.asarray(res.quaternion)
    assert q[0] >= 0
    # quaternion and matrix describe the same rotation (scipy uses xyzw)
    np.testing.assert_allclose(Rotation.from_quat(np.roll(q, -1)).as_matrix(), r, atol=1e-13)
    # translation completes the weighted optimum: residual has zero weighted mean
    resid = src @ r.T + np.asarray(res.translation) - tgt
    np.testing.assert_allclose(np.average(resid, axis=0, weights=w), 0, atol=1e-12)


def test_exact_half_turns_about_coordinate_axes():
    src = random_problem(3)[0]
    for axis in np.eye(3):
        rot = Rotation.from_rotvec(np.pi * axis).as_matrix()
        res = _align(src, src @ rot.T)
        assert int(res.status) == OK
        np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=1e-12)
        assert float(res.rms) < 1e-12


# ------------------------------------------------ Umeyama (NumPy SVD) and numerical optimum
@settings(max_examples=30)
@given(seed=st.integers(0, 2**31 - 1), with_scale=st.booleans(), reflect=st.booleans())
def test_matches_numpy_umeyama(seed, with_scale, reflect):
    src, tgt, w, _, _ = random_problem(seed, noise=0.3, reflect=reflect)
    res = _align(src, tgt, w, with_scale=with_scale)
    rot, t, s = umeyama_np(src, tgt, w, with_scale)
    # tolerance scaled by the conditioning of the rotation (small top gap after reflections)
    mx, my = np.average(src, 0, weights=w), np.average(tgt, 0, weights=w)
    sv = np.linalg.svd(((src - mx) * w[:, None]).T @ (tgt - my), compute_uv=False)
    tol = 1e-11 * sv[0] / max(sv[1] - sv[2], 1e-6 * sv[0])
    np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=tol)
    np.testing.assert_allclose(np.asarray(res.translation), t, atol=10 * tol)
    assert float(res.scale) == pytest.approx(s, rel=10 * tol)


@settings(max_examples=8)
@given(seed=st.integers(0, 2**31 - 1), with_scale=st.booleans())
def test_closed_form_is_no_worse_than_numerical_minimisation(seed, with_scale):
    """Levenberg-Marquardt on (rotation vector, translation, log scale) from several starts."""
    rng = np.random.default_rng(seed)
    src, tgt, w, _, _ = random_problem(seed, noise=0.3, reflect=bool(seed % 2))
    tgt[:2] += rng.normal(scale=3.0, size=(2, 3))  # a couple of outliers
    res = _align(src, tgt, w, with_scale=with_scale)
    assert int(res.status) == OK
    closed = objective(res.rotation, res.translation, float(res.scale), src, tgt, w)

    def residuals(p):
        s = np.exp(p[6]) if with_scale else 1.0
        rot = Rotation.from_rotvec(p[:3]).as_matrix()
        return (np.sqrt(w)[:, None] * (s * src @ rot.T + p[3:6] - tgt)).ravel()

    numeric = np.inf
    for _ in range(4):
        p0 = np.concatenate([Rotation.random(random_state=rng).as_rotvec(), rng.normal(size=3),
                             [0.0] if with_scale else []])
        sol = least_squares(residuals, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        numeric = min(numeric, 2 * sol.cost)
    assert closed <= numeric * (1 + 1e-9)
    # rms is the weighted RMS of exactly this objective
    assert float(res.rms) == pytest.approx(np.sqrt(closed / w.sum()), rel=1e-10)


@settings(max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), with_scale=st.booleans())
def test_closed_form_beats_random_perturbations(seed, with_scale):
    rng = np.random.default_rng(seed)
    src, tgt, w, _, _ = random_problem(seed, noise=0.4, reflect=bool(seed % 3 == 0))
    res = _align(src, tgt, w, with_scale=with_scale)
    rot, t, s = np.asarray(res.rotation), np.asarray(res.translation), float(res.scale)
    f0 = objective(rot, t, s, src, tgt, w)
    for eps in (1e-4, 1e-2, 0.3):
        for _ in range(20):
            dr = Rotation.from_rotvec(eps * rng.normal(size=3)).as_matrix()
            ds = np.exp(eps * rng.normal()) if with_scale else 1.0
            f1 = objective(dr @ rot, t + eps * rng.normal(size=3), s * ds, src, tgt, w)
            assert f0 <= f1 * (1 + 1e-12)


# --------------------------------------------------------------------------- Umeyama scale
@settings(max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), log_s=st.floats(-3, 3))
def test_umeyama_recovers_similarity_exactly(seed, log_s):
    src, _, w, rot, t = random_problem(seed)
    s = np.exp(log_s)
    tgt = s * src @ rot.T + t
    res = _align(src, tgt, w, with_scale=True)
    assert int(res.status) == OK
    assert float(res.scale) == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.translation), t, atol=1e-11 * max(1, s))
    np.testing.assert_allclose(np.asarray(transform_points(res, src)), tgt,
                               atol=1e-11 * max(1, s))
    assert float(res.rms) < 1e-11 * max(1, s)
    # without scale the rotation is still exact (centred clouds are only scaled)
    res1 = _align(src, tgt, w)
    np.testing.assert_allclose(np.asarray(res1.rotation), rot, atol=1e-12)
    assert float(res1.scale) == 1.0


def test_umeyama_scale_is_stationary_with_noise():
    """With noise the returned scale minimises the objective along the scale direction."""
    src, tgt, w, _, _ = random_problem(11, noise=0.2)
    tgt = 2.5 * tgt
    res = _align(src, tgt, w, with_scale=True)
    rot, t, s = np.asarray(res.rotation), np.asarray(res.translation), float(res.scale)
    h = 1e-6
    f = [objective(rot, t, s * np.exp(k * h), src, tgt, w) for k in (-1, 0, 1)]
    assert (f[2] - f[0]) / (2 * h) == pytest.approx(0.0, abs=1e-7 * f[1])
    assert f[1] <= min(f[0], f[2])


# -------------------------------------------------------------------------------- weights
def test_zero_weight_outliers_are_ignored():
    src, tgt, w, _, _ = random_problem(5, noise=0.1)
    tgt[6:] += 100.0
    w[6:] = 0.0
    rot, t, s = umeyama_np(src[:6], tgt[:6], w[:6], True)
    res = _align(src, tgt, w, with_scale=True)
    assert int(res.status) == OK
    np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.translation), t, atol=1e-12)
    assert float(res.scale) == pytest.approx(s, rel=1e-12)
    rms = np.sqrt(objective(rot, t, s, src[:6], tgt[:6], w[:6]) / w[:6].sum())
    assert float(res.rms) == pytest.approx(rms, rel=1e-10)
    assert int(res.num_inliers) == 6
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), np.arange(N) < 6)
    # only weight ratios matter, even for tiny weights
    res3 = _align(src, tgt, 1e-300 * w, with_scale=True)
    np.testing.assert_allclose(np.asarray(res3.rotation), rot, atol=1e-12)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_rows_are_missing_landmarks(bad):
    src, tgt, w, _, _ = random_problem(6, noise=0.1)
    rot, t, _ = umeyama_np(src[2:], tgt[2:], w[2:], False)
    src2, tgt2 = src.copy(), tgt.copy()
    src2[0, 1] = bad
    tgt2[1] = bad
    res = _align(src2, tgt2, w)
    assert int(res.status) == OK
    np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.translation), t, atol=1e-12)
    rms = np.sqrt(objective(rot, t, 1.0, src[2:], tgt[2:], w[2:]) / w[2:].sum())
    assert float(res.rms) == pytest.approx(rms, rel=1e-10)
    assert int(res.num_inliers) == N - 2
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), np.arange(N) >= 2)
    # a non-finite weight also marks a missing row
    w3 = w.copy()
    w3[:2] = bad
    res3 = _align(src, tgt, w3)
    np.testing.assert_allclose(np.asarray(res3.rotation), rot, atol=1e-12)
    # gradients are finite and vanish for the missing rows
    gs = _grad_scalar(src2, tgt2, w, True)
    assert all(np.isfinite(np.asarray(g)).all() for g in gs)
    np.testing.assert_array_equal(np.asarray(gs[0])[0], 0)
    np.testing.assert_array_equal(np.asarray(gs[1])[1], 0)


# ------------------------------------------------------------------------------ degenerate
def _status_cases():
    """name -> (source, target, weights, expected status), all with N rows."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(N, 3))
    line = np.linspace(0, 1, N)[:, None] * np.array([1.0, 2.0, -0.5]) + 0.3
    ones = np.ones(N)
    nan = np.full((N, 3), np.nan)
    nan_but_2 = nan.copy()
    nan_but_2[:2] = pts[:2]
    tet, tet_w = pad(TETRA)
    two_w = (np.arange(N) < 2).astype(float)
    return {
        "two_positive_weights": (pts, pts + 1, two_w, TOO_FEW_POINTS),
        "one_positive_weight": (pts, pts, (np.arange(N) < 1).astype(float), TOO_FEW_POINTS),
        "all_weights_zero": (pts, pts, np.zeros(N), TOO_FEW_POINTS),
        "negative_weights": (pts, pts, -ones, TOO_FEW_POINTS),
        "collinear": (line, line @ Rotation.random(random_state=1).as_matrix().T, ones,
                      DEGENERATE),
        "coincident_source": (np.ones((N, 3)), pts, ones, DEGENERATE),
        "coincident_target": (pts, np.ones((N, 3)), ones, DEGENERATE),
        # point reflection of a regular tetrahedron: every half turn is optimal
        "mirrored_tetrahedron": (tet, -tet, tet_w, DEGENERATE),
        "nan_everywhere": (nan, nan, ones, NOT_FINITE),
        "nan_leaves_two": (nan_but_2, pts, ones, NOT_FINITE),
        "inf_weights": (pts, pts, np.full(N, np.inf), NOT_FINITE),
    }


@jax.jit
def _sum_outputs(res):
    return jnp.sum(res.rotation) + jnp.sum(res.translation) + jnp.sum(res.scale) + jnp.sum(res.rms)


@pytest.mark.parametrize("with_scale", [False, True])
def test_status_codes_give_finite_identity(with_scale):
    cases = _status_cases()
    src = np.stack([c[0] for c in cases.values()])
    tgt = np.stack([c[1] for c in cases.values()])
    w = np.stack([c[2] for c in cases.values()])
    res = _align(src, tgt, w, with_scale=with_scale)  # one batched call
    got = [AlignmentStatus.name(s) for s in np.asarray(res.status)]
    want = [AlignmentStatus.name(c[3]) for c in cases.values()]
    assert got == want
    assert not np.asarray(res.ok).any()
    assert_identity(res)
    gs = jax.jit(jax.grad(lambda s, t, w: _sum_outputs(align(s, t, w, with_scale=with_scale)),
                          argnums=(0, 1, 2)))(src, tgt, w)
    assert all(np.isfinite(np.asarray(g)).all() for g in gs)


def test_too_few_points_by_shape():
    pts = np.random.default_rng(1).normal(size=(2, 3))
    res = _align(pts, pts + 1.0)
    assert int(res.status) == TOO_FEW_POINTS
    assert_identity(res)


def test_nearly_collinear_is_ok_above_tolerance():
    line = np.linspace(0, 1, N)[:, None] * np.array([1.0, 2.0, -0.5])
    line[2, 2] += 1e-3
    rot = Rotation.random(random_state=4).as_matrix()
    res = _align(line, line @ rot.T)
    assert int(res.status) == OK
    np.testing.assert_allclose(np.asarray(res.rotation), rot, atol=1e-9)
    assert int(_align(line, line @ rot.T, degenerate_rtol=1e-2).status) == DEGENERATE


def test_status_names_and_broadcast_batch():
    assert AlignmentStatus.name(TOO_FEW_INLIERS) == "TOO_FEW_INLIERS"
    assert [getattr(AlignmentStatus, n) for n in AlignmentStatus.names] == [0, 1, 2, 3, 4]
    src, tgt, _, _, _ = random_problem(2)
    srcs = np.stack([src, np.zeros_like(src), np.full_like(src, np.nan)])
    res = _align(srcs, tgt)  # target (and default weights) broadcast over the batch
    np.testing.assert_array_equal(np.asarray(res.status), [OK, DEGENERATE, NOT_FINITE])
    assert res.rotation.shape == (3, 3, 3) and res.inlier_mask.shape == (3, N)
    assert res.status.dtype == jnp.int32


def test_shape_errors():
    with pytest.raises(ValueError, match="shape"):
        align(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="same number"):
        align(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="weights"):
        align(np.zeros((4, 3)), np.zeros((4, 3)), np.ones(3))
    with pytest.raises(ValueError, match="broadcast"):
        align(np.zeros((2, 4, 3)), np.zeros((3, 4, 3)))
    with pytest.raises(ValueError, match="sample_size"):
        ransac_align(jax.random.key(0), np.zeros((4, 3)), np.zeros((4, 3)), sample_size=2)
    with pytest.raises(ValueError, match="shape"):
        transform_points(align(np.eye(3), np.eye(3)), np.zeros(3))


# ------------------------------------------------------------------------- batching / vmap
def test_batch_and_vmap_equal_single_calls():
    probs = [random_problem(s, noise=0.1) for s in range(5)]
    src, tgt, w = (np.stack([p[i] for p in probs]) for i in range(3))
    batched = _align(src, tgt, w, with_scale=True)
    vm = jax.jit(jax.vmap(lambda a, b, c: align(a, b, c, with_scale=True)))(src, tgt, w)
    for i in range(5):
        one = _align(src[i], tgt[i], w[i], with_scale=True)
        for field in ("rotation", "translation", "scale", "rms", "quaternion", "status"):
            ref = np.asarray(getattr(one, field))
            np.testing.assert_allclose(np.asarray(getattr(batched, field))[i], ref, atol=1e-13)
            np.testing.assert_allclose(np.asarray(getattr(vm, field))[i], ref, atol=1e-13)
    # transform_points broadcasts the result's batch against the points' batch
    out = transform_points(batched, src)
    for i in range(5):
        r, t, s = umeyama_np(src[i], tgt[i], w[i], True)
        np.testing.assert_allclose(np.asarray(out[i]), s * src[i] @ r.T + t, atol=1e-12)


# ----------------------------------------------------------------------------- gradients
_A = np.arange(9.0).reshape(3, 3) / 9 - 0.4
_B = np.array([0.3, -0.7, 0.2])


def _scalar(src, tgt, w, with_scale=True, use_rms=True):
    r = align(src, tgt, w, with_scale=with_scale)
    out = jnp.sum(r.rotation * _A) + jnp.dot(r.translation, _B) + r.scale
    return out + r.rms if use_rms else out


_scalar_jit = jax.jit(_scalar, static_argnames=("with_scale", "use_rms"))
_grad_scalar = jax.jit(jax.grad(_scalar, argnums=(0, 1, 2)), static_argnames=("with_scale",
                                                                               "use_rms"))


def _gradient_configs():
    rng = np.random.default_rng(1)
    rot = Rotation.random(random_state=2).as_matrix()
    gen = rng.normal(size=(N, 3))
    tet, tet_w = pad(TETRA)
    sq, sq_w = pad(SQUARE)
    ones = np.ones(N)
    return {
        "generic": (gen, gen @ rot.T + 0.5 + 0.1 * rng.normal(size=(N, 3)), ones),
        "identical": (gen, gen, ones),
        "identical_tetra": (tet, tet, tet_w),
        "identical_square": (sq, sq, sq_w),
        "rotated_tetra": (tet, tet @ rot.T + 0.5, tet_w),
        "rotated_square": (sq, sq @ rot.T + 0.5, sq_w),
        "half_turn_tetra": (tet, tet @ np.diag([1.0, -1.0, -1.0]), tet_w),
    }


@pytest.mark.parametrize("with_scale", [False, True])
def test_gradients_finite_at_generic_identical_and_symmetric_configurations(with_scale):
    cfg = _gradient_configs()
    src, tgt, w = (np.stack([c[i] for c in cfg.values()]) for i in range(3))
    assert (np.asarray(_align(src, tgt, w).status) == OK).all()

    def total(s, t, ww):
        return jnp.sum(jax.vmap(lambda a, b, c: _scalar(a, b, c, with_scale))(s, t, ww))

    grads = jax.jit(jax.grad(total, argnums=(0, 1, 2)))(src, tgt, w)
    for name, *g in zip(cfg, *grads):
        assert all(np.isfinite(np.asarray(x)).all() for x in g), name
    jf = jax.jit(jax.jacfwd(total, argnums=1))(src, tgt, w)  # forward mode too
    assert np.isfinite(np.asarray(jf)).all()


def _central_fd_check(src, tgt, w, use_rms, argnums, rtol):
    rng = np.random.default_rng(7)
    args = [np.asarray(a, float) for a in (src, tgt, w)]
    grads = _grad_scalar(*args, True, use_rms)
    h = 1e-6
    for arg in argnums:
        for _ in range(3):
            d = rng.normal(size=args[arg].shape)
            plus, minus = list(args), list(args)
            plus[arg] = args[arg] + h * d
            minus[arg] = args[arg] - h * d
            fd = (float(_scalar_jit(*plus, True, use_rms))
                  - float(_scalar_jit(*minus, True, use_rms))) / (2 * h)
            an = float(np.sum(np.asarray(grads[arg]) * d))
            assert an == pytest.approx(fd, rel=rtol, abs=1e-7)


def test_gradient_matches_central_differences_generic():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(N, 3))
    rot = Rotation.random(random_state=3).as_matrix()
    tgt = 1.3 * src @ rot.T + 0.2 * rng.normal(size=(N, 3))
    w = rng.uniform(0.5, 1.5, size=N)
    _central_fd_check(src, tgt, w, use_rms=True, argnums=(0, 1, 2), rtol=1e-6)


def test_gradient_matches_central_differences_symmetric():
    """At a regular tetrahedron the singular values repeat but the transform is smooth."""
    rot = Rotation.random(random_state=8).as_matrix()
    tet, tet_w = pad(TETRA)
    _central_fd_check(tet, tet @ rot.T + 0.1, tet_w, use_rms=False, argnums=(0, 1), rtol=1e-6)


# --------------------------------------------------------------------------------- float32
def test_float32_accuracy():
    rng = np.random.default_rng(9)
    src = rng.uniform(-1, 1, size=(10, N, 3))
    rots = Rotation.random(10, random_state=rng).as_matrix()
    t = rng.normal(size=(10, 3))
    tgt = np.einsum("bij,bnj->bni", rots, src) + t[:, None, :]
    res = _align(jnp.asarray(src, jnp.float32), jnp.asarray(tgt, jnp.float32))
    assert res.rotation.dtype == jnp.float32 and res.rms.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(res.status), OK)
    worst = max(rot_angle(res.rotation[i], rots[i]) for i in range(10))
    assert worst < 1e-4
    np.testing.assert_allclose(np.asarray(res.translation), t, atol=1e-5)


def test_float32_large_coordinates_do_not_overflow():
    # the same similarity problem as test_float32_accuracy, in units 1e19 / 1e25 times smaller:
    # squared coordinates exceed float32's range (3.4e38) but the fit is scale-free, so the
    # result keeps the float32 accuracy of unit coordinates (measured at 1, 1e19 and 1e25:
    # rotation <= 1.1e-6 rad, scale 5e-7, translation / unit 4.4e-7, rms / unit 1.5e-6; bounds
    # about 10x that)
    rng = np.random.default_rng(9)
    src = rng.uniform(-1, 1, size=(10, N, 3))
    rots = Rotation.random(10, random_state=rng).as_matrix()
    t = rng.normal(size=(10, 3))
    tgt = 1.5 * np.einsum("bij,bnj->bni", rots, src) + t[:, None, :]
    for unit in (1e19, 1e25):
        res = _align(jnp.asarray(src * unit, jnp.float32), jnp.asarray(tgt * unit, jnp.float32),
                     with_scale=True)
        np.testing.assert_array_equal(np.asarray(res.status), OK)
        assert max(rot_angle(res.rotation[i], rots[i]) for i in range(10)) < 1e-5
        np.testing.assert_allclose(np.asarray(res.scale), 1.5, atol=5e-6)
        np.testing.assert_allclose(np.asarray(res.translation) / unit, t, atol=5e-6)
        assert np.all(np.asarray(res.rms) / unit < 2e-5)
        # one point 10x farther out: a finite residual (no overflow in its square)
        far = src[0] * unit
        far[0] = 10 * unit
        one = _align(jnp.asarray(far, jnp.float32), jnp.asarray(tgt[0] * unit, jnp.float32))
        assert np.isfinite(float(one.rms)) and float(one.rms) > 0
    g = jax.grad(lambda a: _align(a, a * 2, with_scale=True).rms
                 + jnp.sum(_align(a, a * 2, with_scale=True).rotation))(
        jnp.asarray(src[0] * 1e19, jnp.float32))
    assert np.all(np.isfinite(np.asarray(g)))


# ---------------------------------------------------------------------------------- RANSAC
def _ransac_problem(seed, n=M, outlier_frac=0.4, noise=2e-4):
    """Head-sized landmark cloud (m), 0.2 mm noise, gross outliers displaced by 2-30 cm."""
    rng = np.random.default_rng(seed)
    src = rng.normal(scale=0.08, size=(n, 3))
    rot = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(scale=0.5, size=3)
    tgt = src @ rot.T + t + noise * rng.normal(size=(n, 3))
    n_out = int(round(outlier_frac * n))
    out = rng.choice(n, size=n_out, replace=False)
    d = rng.normal(size=(n_out, 3))
    tgt[out] += d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.02, 0.3, (n_out, 1))
    inlier = np.ones(n, bool)
    inlier[out] = False
    return src, tgt, rot, t, inlier


ONES = np.ones(M)


@pytest.mark.parametrize("outlier_frac", [0.3, 0.5])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ransac_recovers_pose_with_gross_outliers(seed, outlier_frac):
    src, tgt, rot, t, inlier = _ransac_problem(seed, outlier_frac=outlier_frac)
    res = _ransac(jax.random.key(seed), src, tgt, ONES, threshold=0.003)
    assert int(res.status) == OK
    assert rot_angle(res.rotation, rot) < np.deg2rad(0.5)
    assert np.linalg.norm(np.asarray(res.translation) - t) < 1e-3
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), inlier)
    assert int(res.num_inliers) == inlier.sum()
    # refit on the inliers = least squares on the true inlier set
    r_ls, t_ls, _ = umeyama_np(src[inlier], tgt[inlier], ONES[inlier], False)
    np.testing.assert_allclose(np.asarray(res.rotation), r_ls, atol=1e-10)
    np.testing.assert_allclose(np.asarray(res.translation), t_ls, atol=1e-10)
    assert float(res.rms) < 1e-3
    # plain least squares is ruined by the outliers (the test problem is not trivial)
    assert rot_angle(umeyama_np(src, tgt, ONES, False)[0], rot) > np.deg2rad(0.5)


@pytest.mark.parametrize("refine", [True, False])
def test_ransac_threshold_just_inside_and_just_outside(refine):
    """Outliers displaced by 0.9 and 1.1 thresholds: exactly the first count as inliers.

    The gross-outlier problems above (2-30 cm at a 3 mm threshold) would pass with a threshold
    three times too large; here a threshold off by more than ~10 %, or a residual compared
    squared, changes the inlier set."""
    rng = np.random.default_rng(11)
    tau = 0.004
    src = rng.normal(scale=0.08, size=(M, 3))
    rot = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(scale=0.5, size=3)
    tgt = src @ rot.T + t
    d = rng.normal(size=(M, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    order = rng.permutation(M)
    inside, outside = order[:5], order[5:13]
    tgt[inside] += 0.9 * tau * d[inside]
    tgt[outside] += 1.1 * tau * d[outside]
    expected = np.ones(M, bool)
    expected[outside] = False
    # the displaced points weigh little, so that the refit on all inliers stays close to the
    # true transform (five full-weight points 0.9 thresholds off moved it by up to 0.2
    # thresholds); the inlier test itself ignores weights
    w = ONES.copy()
    w[order[:13]] = 0.01
    # the problem is what it claims under the independent least-squares fit on the expected
    # inliers too (what the refit returns): the inside points stay inside, the others outside
    r_ls, t_ls, _ = umeyama_np(src[expected], tgt[expected], w[expected], False)
    resid = np.linalg.norm(src @ r_ls.T + t_ls - tgt, axis=1)
    assert resid[inside].max() < 0.95 * tau and resid[outside].min() > 1.05 * tau

    res = _ransac(jax.random.key(0), src, tgt, w, threshold=tau, refine=refine)
    assert int(res.status) == OK
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), expected)
    assert int(res.num_inliers) == expected.sum()
    assert rot_angle(res.rotation, rot) < np.deg2rad(0.2)
    if refine:
        np.testing.assert_allclose(np.asarray(res.rotation), r_ls, atol=1e-10)
        np.testing.assert_allclose(np.asarray(res.translation), t_ls, atol=1e-10)
    # sensitivity: a threshold 20 % larger takes the outside points in, 20 % smaller drops
    # the inside ones
    wide = _ransac(jax.random.key(0), src, tgt, w, threshold=1.2 * tau, refine=refine)
    assert np.asarray(wide.inlier_mask)[outside].all()
    narrow = _ransac(jax.random.key(0), src, tgt, w, threshold=0.8 * tau, refine=refine)
    assert not np.asarray(narrow.inlier_mask)[inside].any()
    assert np.asarray(narrow.inlier_mask).sum() == M - 13


def test_ransac_without_refine_with_scale_and_larger_samples():
    src, tgt, rot, t, inlier = _ransac_problem(4, outlier_frac=0.3)
    tgt = 1.5 * tgt
    kw = dict(threshold=0.005, with_scale=True, refine=False, sample_size=4)
    res = _ransac(jax.random.key(1), src, tgt, ONES, **kw)
    assert int(res.status) == OK
    assert rot_angle(res.rotation, rot) < np.deg2rad(0.5)
    assert float(res.scale) == pytest.approx(1.5, rel=1e-2)
    assert np.asarray(res.inlier_mask)[~inlier].sum() == 0
    # without refine the transform is a minimal-sample fit, so it depends on the key
    other = _ransac(jax.random.key(2), src, tgt, ONES, **kw)
    assert not np.array_equal(np.asarray(res.rotation), np.asarray(other.rotation))


def test_ransac_deterministic_for_fixed_key():
    src, tgt, _, _, _ = _ransac_problem(5)
    a = _ransac(jax.random.key(3), src, tgt, ONES, threshold=0.003)
    b = _ransac(jax.random.key(3), src, tgt, ONES, threshold=0.003)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_ransac_vmap_over_frames_equals_loop_and_no_recompilation():
    probs = [_ransac_problem(10 + i) for i in range(8)]
    src = np.stack([p[0] for p in probs])
    tgt = np.stack([p[1] for p in probs])
    w = np.ones((8, M))
    keys = jax.random.split(jax.random.key(0), 8)
    traces = []

    @jax.jit
    def frames(keys, src, tgt, w):
        traces.append(1)
        return jax.vmap(lambda k, s, t, ww: ransac_align(k, s, t, ww, threshold=0.003))(
            keys, src, tgt, w)

    batched = frames(keys, src, tgt, w)
    for i in range(8):
        one = _ransac(keys[i], src[i], tgt[i], w[i], threshold=0.003)
        assert int(batched.status[i]) == int(one.status) == OK
        np.testing.assert_array_equal(np.asarray(batched.inlier_mask[i]),
                                      np.asarray(one.inlier_mask))
        np.testing.assert_allclose(np.asarray(batched.rotation[i]), np.asarray(one.rotation),
                                   atol=1e-12)
        np.testing.assert_allclose(np.asarray(batched.translation[i]),
                                   np.asarray(one.translation), atol=1e-12)
        assert rot_angle(one.rotation, probs[i][2]) < np.deg2rad(0.5)
    # same shapes, new data and keys: no retrace / recompilation
    frames(jax.random.split(jax.random.key(1), 8), src[::-1].copy(), tgt[::-1].copy(), w)
    assert len(traces) == 1
    assert frames._cache_size() == 1
    # the module-level jitted ransac is not recompiled for new data / thresholds either
    n0 = _ransac._cache_size()
    _ransac(keys[0], src[1], tgt[1], w[1], threshold=0.003)
    _ransac(keys[1], src[2], tgt[2], w[2], threshold=0.004)
    assert _ransac._cache_size() == n0


def test_ransac_native_batch_dims_with_single_key():
    probs = [_ransac_problem(30 + i) for i in range(3)]
    src = np.stack([p[0] for p in probs])
    tgt = np.stack([p[1] for p in probs])
    res = _ransac(jax.random.key(2), src, tgt, ONES, threshold=0.003)
    np.testing.assert_array_equal(np.asarray(res.status), OK)
    for i in range(3):
        assert rot_angle(res.rotation[i], probs[i][2]) < np.deg2rad(0.5)
        np.testing.assert_array_equal(np.asarray(res.inlier_mask[i]), probs[i][4])


def test_ransac_ignores_missing_and_zero_weight_points():
    src, tgt, rot, t, inlier = _ransac_problem(6, outlier_frac=0.3)
    w = ONES.copy()
    src[0] = np.nan
    w[1] = 0.0
    res = _ransac(jax.random.key(0), src, tgt, w, threshold=0.003)
    assert int(res.status) == OK
    expected = inlier.copy()
    expected[:2] = False
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), expected)
    assert rot_angle(res.rotation, rot) < np.deg2rad(0.5)
    g = jax.jit(jax.grad(
        lambda s, t: _sum_outputs(ransac_align(jax.random.key(0), s, t, w, threshold=0.003)),
        argnums=(0, 1)))(src, tgt)
    assert all(np.isfinite(np.asarray(x)).all() for x in g)


def test_ransac_status_codes():
    src, tgt, _, _, _ = _ransac_problem(7, outlier_frac=0.0, noise=0.01)
    # threshold far below the noise: minimal-sample fits do not even fit their own points
    res = _ransac(jax.random.key(0), src, tgt, ONES, threshold=1e-7)
    assert int(res.status) == TOO_FEW_INLIERS
    assert_identity(res)
    assert int(res.num_inliers) < 3
    line = np.linspace(0, 1, M)[:, None] * np.array([1.0, 0.5, 0.2])
    res = _ransac(jax.random.key(0), line, line + 1.0, ONES, threshold=0.01)
    assert int(res.status) == DEGENERATE
    assert_identity(res)
    res = _ransac(jax.random.key(0), src, tgt, (np.arange(M) < 2).astype(float), threshold=0.01)
    assert int(res.status) == TOO_FEW_POINTS
    assert_identity(res)
    res = _ransac(jax.random.key(0), np.full_like(src, np.nan), tgt, ONES, threshold=0.01)
    assert int(res.status) == NOT_FINITE
    assert_identity(res)
    # fewer points than the sample size (static shape): clipped sample, TOO_FEW_POINTS
    res = ransac_align(jax.random.key(0), src[:2], tgt[:2], threshold=0.01, num_iterations=2)
    assert int(res.status) == TOO_FEW_POINTS
    assert_identity(res)
