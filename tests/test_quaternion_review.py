"""Review of the quaternion module at degenerate inputs: non-unit inputs,
second derivatives at the identity, against NumPy / scipy / analytic references."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import phjax as pj


def _unit(rng, n, k=4):
    d = rng.normal(size=(n, k))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_log_of_a_scaled_quaternion_has_the_angle_of_its_direction():
    """The vector part of ``log q`` is ``atan2(|v|, w) v / |v|`` for any positive scale of ``q``
    (the general formula is scale-free), but the small-angle series was chosen by ``|v| < 1e-4``
    whatever ``w``: ``quat_log([1e-5, 5e-5, 0, 0])`` gave ``[-36.67, 0, 0]`` instead of
    ``[1.3734, 0, 0]`` (``quat_to_rotvec`` -73.3 instead of 2.747)."""
    axis = np.array([0.36, 0.48, 0.8])
    ang = np.array([1e-9, 1e-6, 1e-3, 0.05, 0.3, 1.3734, 3.0])  # half angles
    scale = np.array([1e-5, 1e-3, 0.5, 2.0, 1e3])
    a, c = np.meshgrid(ang, scale, indexing="ij")
    q = c[..., None] * np.concatenate([np.cos(a)[..., None], np.sin(a)[..., None] * axis], -1)
    ref = a[..., None] * axis
    np.testing.assert_allclose(np.asarray(pj.quat_log(q)), ref, rtol=1e-13, atol=0)
    np.testing.assert_allclose(np.asarray(pj.quat_to_rotvec(-q[:-1])), 2 * ref[:-1], rtol=1e-13, atol=0)
    np.testing.assert_allclose(np.asarray(pj.quat_log(np.array([1e-5, 5e-5, 0, 0]))),
                               [np.arctan2(5e-5, 1e-5), 0, 0], rtol=1e-14)


def test_second_derivatives_of_the_exponential_at_the_identity():
    """The scalar part ``cos(|w| / 2)`` went through the NaN-safe norm, whose gradient is 0 at
    the zero vector: its Hessian at ``w = 0`` was 0 instead of ``-I / 4`` (Newton steps or
    Laplace approximations from the identity saw a flat rotation)."""
    hess = jax.jacfwd(jax.jacrev(pj.quat_from_rotvec))
    pts = np.array([[0.0, 0, 0], [1e-9, -2e-9, 5e-10], [1e-4, 2e-4, -3e-4], [0.3, -0.2, 0.5]])
    ident = jnp.asarray([1.0, 0, 0, 0])
    d2 = lambda w: pj.quat_geodesic_distance(ident, pj.quat_from_rotvec(w)) ** 2  # noqa: E731
    h, h_d2 = jax.jit(lambda p: (jax.vmap(hess)(p), jax.hessian(d2)(p[1])))(pts)
    h = np.asarray(h)  # (point, 4, 3, 3)

    def ref_hess(w):  # from scipy's quaternion of the rotation vector, by central differences
        def quat(x):
            x = Rotation.from_rotvec(x).as_quat()
            return np.concatenate([x[3:], x[:3]])
        e, step = np.eye(3), 1e-4
        out = np.zeros((4, 3, 3))
        for i in range(3):
            for j in range(3):
                out[:, i, j] = (quat(w + step * (e[i] + e[j])) - quat(w + step * (e[i] - e[j]))
                                - quat(w - step * (e[i] - e[j])) + quat(w - step * (e[i] + e[j]))
                                ) / (4 * step * step)
        return out

    for w, hw in zip(pts, h):
        np.testing.assert_allclose(hw, ref_hess(w), rtol=0, atol=1e-6)
    # the geodesic distance squared near the identity: curvature 2 I per unit rotation vector
    np.testing.assert_allclose(np.asarray(h_d2), 2 * np.eye(3), atol=1e-6)


def test_degenerate_pairs_stay_finite_and_exact():
    """Checks that held before the review, in one program: ``q`` against ``+-q`` and nearly
    opposite, slerp at and beyond its ends, in float32 and float64."""
    rng = np.random.default_rng(1)
    q0 = _unit(rng, 1)[0]
    axis = np.array([0.36, 0.48, 0.8])
    angles = np.array([0.0, 1e-8, 1e-4, 1.0, np.pi - 1e-6])
    dq = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], -1)
    q1 = np.asarray(pj.quat_mul(q0, dq))
    signs = np.array([1.0, -1.0])
    ts = np.array([0.0, 0.3, 1.0, -0.5, 1.5])

    def one(q1, s, t):
        dist = pj.quat_geodesic_distance(q0, s * q1)
        g_dist = jax.grad(lambda b: pj.quat_geodesic_distance(q0, b))(s * q1)
        out = pj.quat_slerp(q0, s * q1, t)
        g_t = jax.jacfwd(pj.quat_slerp, argnums=2)(q0, s * q1, t)
        weights = jnp.asarray([0.3, -0.5, 0.7, 0.2], out.dtype)  # a generic scalar of the output
        g_ends = jax.grad(lambda a, b: jnp.sum(pj.quat_slerp(a, b, t) * weights), argnums=(0, 1))(
            jnp.asarray(q0, out.dtype), s * q1)
        return dist, g_dist, out, g_t, g_ends

    f = jax.jit(jax.vmap(jax.vmap(jax.vmap(one, (None, None, 0)), (None, 0, None)), (0, None, None)))
    for dtype in (np.float64, np.float32):
        dist, g_dist, out, g_t, g_ends = f(q1.astype(dtype), signs.astype(dtype), ts.astype(dtype))
        for x in (dist, g_dist, out, g_t, *g_ends):
            assert np.all(np.isfinite(np.asarray(x)))
        tol = 1e-12 if dtype == np.float64 else 1e-6
        np.testing.assert_allclose(np.asarray(dist)[:, :, 0], np.broadcast_to(angles[:, None], (5, 2)),
                                   atol=tol)
        # slerp is q0 exp(t log dq) for either sign of q1, also outside [0, 1]
        rv = (angles[:, None, None] * ts[None, :, None] * axis).reshape(-1, 3)
        ref = Rotation.from_quat(np.roll(q0, -1)) * Rotation.from_rotvec(rv)
        got = np.asarray(out, np.float64)  # (angle, sign, t, 4)
        for si in range(2):
            mine = Rotation.from_quat(np.roll(got[:, si].reshape(-1, 4), -1, axis=-1))
            assert (mine.inv() * ref).magnitude().max() < (1e-10 if dtype == np.float64 else 2e-6)
        # d slerp / dt at t = 0 is q0 (0, log dq)
        ref_dt = np.asarray(pj.quat_mul(q0, np.concatenate([np.zeros((5, 1)), angles[:, None] / 2 * axis], -1)))
        np.testing.assert_allclose(np.asarray(g_t, np.float64)[:, 0, 0], ref_dt, atol=10 * tol)


def test_numpy_normalisation_of_tiny_huge_zero_and_non_finite_quaternions():
    """``np_qnormalize`` (metrics, baselines, the head-pose front-ends, every live output)
    divided by the plain norm: a quaternion of 1e-200 or 1e200 (squared norm out of float64's
    range) became NaN / zero with a NumPy warning. Scaled first, they are unit quaternions;
    zero and non-finite ones are NaN, without a warning."""
    import warnings

    from phjax._np_quat import np_qnormalize

    rng = np.random.default_rng(5)
    u = rng.normal(size=(6, 4))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for scale in (1e-200, 1e-5, 1.0, 3e7, 1e200):
            np.testing.assert_allclose(np_qnormalize(scale * u), u, rtol=1e-14, atol=1e-15)
        bad = np.array([[0.0, 0, 0, 0], [np.nan, 0, 0, 1], [np.inf, 0, 0, 0], [1.0, -np.inf, 0, 0]])
        assert np.isnan(np_qnormalize(bad)).all()
        mixed = np_qnormalize(np.stack([u[0], bad[0]]))
        np.testing.assert_allclose(mixed[0], u[0], rtol=1e-15)
        assert np.isnan(mixed[1]).all()
        f32 = np_qnormalize(u.astype(np.float32) * np.float32(1e-30))
        assert f32.dtype == np.float32
        np.testing.assert_allclose(f32, u, rtol=2e-6, atol=1e-7)
