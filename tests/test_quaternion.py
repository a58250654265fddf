"""Quaternion algebra against scipy's Rotation (xyzw) and algebraic identities."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

import phjax as pj

finite = st.floats(-1.0, 1.0, allow_nan=False, width=64)
quat4 = arrays(np.float64, (4,), elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)
vec3 = arrays(np.float64, (3,), elements=st.floats(-3.0, 3.0, allow_nan=False, width=64))


def to_scipy(q):
    q = np.asarray(q)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def from_scipy(r):
    x = r.as_quat()
    return np.concatenate([x[..., 3:], x[..., :3]], axis=-1)


@given(quat4, quat4)
def test_mul_matches_scipy_composition(a, b):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    ours = to_scipy(pj.quat_mul(a, b))
    ref = to_scipy(a) * to_scipy(b)
    assert (ours.inv() * ref).magnitude() < 1e-12


@given(quat4, vec3)
def test_rotate_and_matrix_match_scipy(q, v):
    q = q / np.linalg.norm(q)
    np.testing.assert_allclose(pj.quat_rotate(q, v), to_scipy(q).apply(v), atol=1e-12)
    np.testing.assert_allclose(pj.quat_to_matrix(q), to_scipy(q).as_matrix(), atol=1e-12)
    # the sandwich product with the same quaternion is the scaled rotation
    np.testing.assert_allclose(pj.quat_sandwich(q, v, q), to_scipy(q).apply(v), atol=1e-12)


@given(quat4)
def test_matrix_roundtrip_including_half_turns(q):
    q = q / np.linalg.norm(q)
    back = pj.quat_from_matrix(pj.quat_to_matrix(q))
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1]])
def test_from_matrix_exact_half_turns(axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    r = Rotation.from_rotvec(np.pi * axis)
    q = pj.quat_from_matrix(r.as_matrix())
    assert (to_scipy(q).inv() * r).magnitude() < 1e-12


@given(vec3)
def test_rotvec_exp_log(w):
    w = np.asarray(w)
    if np.linalg.norm(w) >= np.pi:
        w = w / np.linalg.norm(w) * (np.pi - 1e-3)
    q = pj.quat_from_rotvec(w)
    np.testing.assert_allclose(q, from_scipy(Rotation.from_rotvec(w)) * np.sign(q[0]), atol=1e-12)
    np.testing.assert_allclose(pj.quat_to_rotvec(q), w, atol=1e-10)
    np.testing.assert_allclose(pj.quat_to_rotvec(-q), w, atol=1e-10)


@given(quat4, quat4, st.floats(0, 1))
def test_slerp_matches_scipy(a, b, t):
    from scipy.spatial.transform import Slerp

    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    ref = Slerp([0, 1], to_scipy(np.stack([a, b])))([t])[0]
    ours = to_scipy(pj.quat_slerp(a, b, t))
    assert (ours.inv() * ref).magnitude() < 1e-9
    # shortest arc: independent of the sign of b
    np.testing.assert_allclose(
        to_scipy(pj.quat_slerp(a, -b, t)).as_matrix(), ours.as_matrix(), atol=1e-9
    )


@given(quat4, quat4)
def test_geodesic_distance_matches_scipy(a, b):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    ref = (to_scipy(a).inv() * to_scipy(b)).magnitude()
    assert abs(float(pj.quat_geodesic_distance(a, b)) - ref) < 1e-7
    assert abs(float(pj.quat_geodesic_distance(a, -b)) - ref) < 1e-7


def test_hemisphere_continuity_removes_flips():
    rng = np.random.default_rng(0)
    w = np.cumsum(rng.normal(size=(200, 3)) * 0.05, axis=0)
    q = from_scipy(Rotation.from_rotvec(w))
    signs = rng.choice([-1.0, 1.0], size=(200, 1))
    fixed = np.asarray(pj.quat_hemisphere_continuity(q * signs))
    assert np.all(np.sum(fixed[1:] * fixed[:-1], axis=-1) >= 0)
    np.testing.assert_allclose(np.abs(fixed), np.abs(q), atol=0)
    assert np.array_equal(fixed[0], q[0] * signs[0])


def test_gradients_finite_at_singular_points():
    f = lambda w: jnp.sum(pj.quat_to_rotvec(pj.quat_from_rotvec(w)) ** 2)  # noqa: E731
    for w in [np.zeros(3), np.array([np.pi, 0, 0]), np.array([1e-9, 0, 0])]:
        g = jax.grad(f)(jnp.asarray(w))
        assert np.all(np.isfinite(g))
    g = jax.grad(lambda q: pj.quat_geodesic_distance(q, jnp.array([1.0, 0, 0, 0])))(
        jnp.array([1.0, 0, 0, 0])
    )
    assert np.all(np.isfinite(g))
    g = jax.grad(lambda q: jnp.sum(pj.quat_normalize(q)))(jnp.zeros(4))
    assert np.all(np.isfinite(g))


def test_float32_stays_float32():
    q = jnp.asarray([0.5, 0.5, 0.5, 0.5], jnp.float32)
    for out in [pj.quat_mul(q, q), pj.quat_to_matrix(q), pj.quat_log(q), pj.quat_slerp(q, q, 0.3)]:
        assert out.dtype == jnp.float32


def test_wrong_last_axis_is_a_clear_error_and_integers_are_floats():
    """A quaternion with 3 entries (or a vector with 4) was silently misread (quat_log of a
    3-vector gave 2 numbers, quat_exp of a 4-vector 5) or failed deep inside JAX."""
    bad = [(lambda: pj.quat_log(np.ones(3)), "q must have shape \\(..., 4\\), got shape \\(3,\\)"),
           (lambda: pj.quat_exp(np.ones(4)), "v must have shape \\(..., 3\\)"),
           (lambda: pj.quat_to_matrix(np.ones(3)), "q must have shape"),
           (lambda: pj.quat_mul(np.ones((5, 3)), np.ones((5, 4))), "p must have shape"),
           (lambda: pj.quat_rotate(np.ones(4), np.ones(4)), "v must have shape"),
           (lambda: pj.quat_from_matrix(np.ones(3)), "m must have shape \\(..., 3, 3\\)"),
           (lambda: pj.quat_slerp(np.ones(4), np.ones(3), 0.5), "q1 must have shape"),
           (lambda: pj.quat_from_rotvec(np.ones(2)), "w must have shape"),
           (lambda: pj.quaternion_hermite(np.ones(3), np.ones(4), np.zeros(3), np.zeros(3), 0.1),
            "q0 must have shape"),
           (lambda: pj.quaternion_hermite(np.ones(4), np.ones(4), np.zeros(4), np.zeros(3), 0.1),
            "w0 must have shape")]
    for call, message in bad:
        with pytest.raises(ValueError, match=message):
            call()
    with pytest.raises(ValueError, match="q must have shape"):  # also when traced
        jax.jit(pj.quat_log)(np.ones(3))
    np.testing.assert_array_equal(np.asarray(pj.quat_normalize(np.array([2, 0, 0, 0]))),
                                  [1.0, 0, 0, 0])


def test_each_function_is_one_compiled_program_when_called_eagerly():
    """Called outside ``jit``, a function runs as one compiled program per input shape: before,
    its 10-30 array operations were each dispatched (and, for a new shape, compiled) on their
    own (measured, float32, one pair: ``quat_geodesic_distance`` took 3.2 ms a call and 1.6 s
    for the first, jitted 14 us and 0.46 s). A second call compiles nothing."""
    compiles = []

    def listener(name, _duration, **_):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append(name)

    rng = np.random.default_rng(0)
    q, r = rng.normal(size=(2, 3, 7, 4))  # a batch shape no other test uses
    v, m = rng.normal(size=(3, 7, 3)), np.asarray(pj.quat_to_matrix(q))
    calls = [(pj.quat_mul, (q, r)), (pj.quat_conj, (q,)), (pj.quat_inv, (q,)),
             (pj.quat_normalize, (q,)), (pj.quat_rotate, (q, v)), (pj.quat_sandwich, (q, v, r)),
             (pj.quat_to_matrix, (r,)), (pj.quat_from_matrix, (m,)), (pj.quat_exp, (v,)),
             (pj.quat_log, (q,)), (pj.quat_from_rotvec, (v,)), (pj.quat_to_rotvec, (q,)),
             (pj.quat_slerp, (q, r, np.full((3, 7), 0.3))), (pj.quat_geodesic_distance, (q, r)),
             (pj.quat_hemisphere_continuity, (q,))]
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        for fn, args in calls:
            before = len(compiles)
            first = np.asarray(fn(*args))
            assert len(compiles) - before <= 1, fn.__name__  # (0: compiled by another test)
            before = len(compiles)
            np.testing.assert_array_equal(np.asarray(fn(*args)), first)
            assert len(compiles) == before, fn.__name__
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
