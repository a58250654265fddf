"""The struct-of-arrays helpers behind the PH and orientation curves (``phjax.curves._components``)
against the array functions of ``phjax.quaternion`` / ``phjax._misc`` and numpy; the fibre map's
defining property; the kernel budget that is their reason to exist."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import phjax as pj
from phjax import quaternion as Q
from phjax._misc import safe_norm, safe_normalize, unit_perpendicular
from phjax.curves import _components as C
from phjax.curves import ph_quintic

B = 3  # rows per example (one compiled program per helper)
# components with exact zeros, units and ties mixed in (degenerate rows: zero vectors, axes)
elem = st.one_of(st.floats(-3.0, 3.0, allow_nan=False, width=64), st.sampled_from([0.0, 1.0, -1.0]))
vecs = arrays(np.float64, (B, 3), elements=elem)
quats = arrays(np.float64, (B, 4), elements=elem)
angles = arrays(np.float64, (B,), elements=st.floats(-7.0, 7.0, allow_nan=False, width=64))


def comps(f):
    """``f`` on component tuples, as a jitted function of arrays."""
    return jax.jit(lambda *xs: C.stack(f(*(C.split(x) for x in xs))))


def close(a, b, rtol=1e-13, atol=1e-13):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)


_qmul = comps(C.qmul)
_qmul_pure = comps(C.qmul_pure)
_qconj = comps(C.qconj)
_qmul_i = comps(C.qmul_i)
_qmul_exp_i = jax.jit(lambda q, phi: C.stack(C.qmul_exp_i(C.split(q), phi)))
_cross = comps(C.cross)
_sandwich = comps(C.sandwich_i)
_sym = comps(C.sym_i)
_dot = jax.jit(lambda a, b: C.dot(C.split(a), C.split(b)))
_norm = jax.jit(lambda a: C.norm(C.split(a)))
_normalize = comps(C.normalize)
_normalize_fb = comps(lambda a, fb: C.normalize(a, fallback=fb))
_perp = comps(C.unit_perpendicular)
_qexp = comps(C.qexp)
_qlog = comps(C.qlog)
_unit_fibre = comps(ph_quintic._unit_fibre)


def _pure(v):
    return jnp.concatenate([jnp.zeros_like(v[..., :1]), v], axis=-1)


@given(quats, quats, vecs, vecs, angles)
def test_quaternion_products_match_phjax_quaternion(p, q, u, v, phi):
    close(_qmul(p, q), Q.quat_mul(p, q))
    close(_qconj(q), Q.quat_conj(q))
    close(_qmul_pure(u, v), Q.quat_mul(_pure(u), _pure(v)))
    close(_qmul_i(q), Q.quat_mul(q, jnp.array([0.0, 1.0, 0.0, 0.0])))
    exp_i = jnp.stack([jnp.cos(phi), jnp.sin(phi), 0 * phi, 0 * phi], -1)
    close(_qmul_exp_i(q, phi), Q.quat_mul(q, exp_i))


@given(quats, quats, vecs, vecs)
def test_vector_helpers_match_numpy_and_sandwich(a, b, u, v):
    close(_cross(u, v), np.cross(u, v))
    close(_dot(u, v), np.sum(u * v, axis=-1))
    i = jnp.array([1.0, 0.0, 0.0])
    close(_sandwich(a, b), Q.quat_sandwich(a, i, b))
    close(_sym(a, b), Q.quat_sandwich(a, i, b) + Q.quat_sandwich(b, i, a))
    # the array wrappers the spline and shape modules use
    close(ph_quintic._sandwich_i(a, b), Q.quat_sandwich(a, i, b))
    close(ph_quintic._sym_i(a, b), _sym(a, b))


@given(vecs, vecs)
def test_norm_and_normalize_match_safe_helpers(v, fb):
    v = np.concatenate([np.zeros((1, 3)), v[1:]])  # a zero row always
    close(_norm(v), safe_norm(v))
    close(_normalize(v), safe_normalize(v))
    close(_normalize_fb(v, fb), safe_normalize(v, fallback=fb))


def test_normalize_gradients_match_and_are_finite_at_zero():
    v = jnp.array([[0.0, 0.0, 0.0], [3.0, -4.0, 12.0], [1e-200, 0.0, 0.0]])
    fb = jnp.array([0.0, 0.0, 1.0])
    w = jnp.array([0.3, -1.1, 2.0])
    for ours, ref in ((lambda x: jnp.sum(_normalize_fb(x, jnp.broadcast_to(fb, x.shape)) * w),
                       lambda x: jnp.sum(safe_normalize(x, fallback=fb) * w)),
                      (lambda x: jnp.sum(_norm(x)), lambda x: jnp.sum(safe_norm(x)))):
        g, g_ref = jax.grad(ours)(v), jax.grad(ref)(v)
        assert np.all(np.isfinite(np.asarray(g)))
        close(g, g_ref)


@given(vecs)
def test_unit_perpendicular_matches_the_array_rule(v):
    u = np.where(np.linalg.norm(v, axis=-1, keepdims=True) > 1e-3, v, [0.0, 0.0, 1.0])
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    m = _perp(u)
    close(m, unit_perpendicular(u))
    close(np.sum(np.asarray(m) * u, axis=-1), 0.0, atol=1e-14)


@given(vecs, quats)
def test_exp_and_log_match_phjax_quaternion(v, q):
    close(_qexp(v), Q.quat_exp(v))
    q = np.where(np.linalg.norm(q, axis=-1, keepdims=True) > 1e-3, q, [1.0, 0, 0, 0])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    close(_qlog(q), Q.quat_log(q))


def test_exp_log_at_special_points_values_and_gradients():
    # identity, the small-angle series of log, a 180-degree turn, a zero rotation vector
    q = jnp.array([[1.0, 0, 0, 0], [np.cos(1e-6), np.sin(1e-6), 0, 0], [0.0, 0, 1, 0]])
    close(_qlog(q), Q.quat_log(q))
    v = jnp.array([[0.0, 0, 0], [1e-9, 0, 0], [0.0, np.pi, 0]])
    close(_qexp(v), Q.quat_exp(v))
    for ours, ref, x in ((_qlog, Q.quat_log, q), (_qexp, Q.quat_exp, v)):
        g = jax.grad(lambda y, f=ours: jnp.sum(jnp.sin(f(y))))(x)
        g_ref = jax.grad(lambda y, f=ref: jnp.sum(jnp.sin(f(y))))(x)
        assert np.all(np.isfinite(np.asarray(g)))
        close(g, g_ref)


# ------------------------------------------------------------------------------ checkpoint
@pytest.mark.parametrize("batch", [(), (2,), (5, 30)])
@pytest.mark.parametrize("sizes", [(3,), (4, 4), (3, 4, 3, 1, 1)])  # one row, two rows of 8
def test_checkpoint_returns_its_input_and_passes_gradients(batch, sizes):
    rng = np.random.default_rng(sum(sizes))
    flat = jnp.asarray(rng.normal(size=(sum(sizes),) + batch))

    def groups(x):
        out, i = [], 0
        for n in sizes:
            out.append(tuple(x[i + k] for k in range(n)))
            i += n
        return out

    f = jax.jit(lambda x: C.checkpoint(*groups(x)))
    out = f(flat)
    assert len(out) == len(sizes) and [len(v) for v in out] == list(sizes)
    np.testing.assert_array_equal(np.concatenate([np.stack(v) for v in out]), np.asarray(flat))
    w = jnp.arange(flat.size, dtype=flat.dtype).reshape(flat.shape)
    g = jax.grad(lambda x: sum(jnp.sum(c * wi) for c, wi in zip(
        [c for v in C.checkpoint(*groups(x)) for c in v], w)))(flat)
    np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    # under vmap (the shape module batches the construction this way)
    vm = jax.vmap(lambda x: jnp.stack([c for v in C.checkpoint(*groups(x)) for c in v]), 1, 1)
    np.testing.assert_array_equal(np.asarray(vm(flat.reshape(flat.shape[:1] + (-1,)))),
                                  np.asarray(flat.reshape(flat.shape[:1] + (-1,))))


def test_checkpoint_broadcasts_constants_and_limits_size():
    x = jnp.arange(2.0)
    (a,), (b, c) = C.checkpoint((x,), (1.0, x * 2))
    np.testing.assert_array_equal(np.asarray(a), [0.0, 1.0])
    np.testing.assert_array_equal(np.asarray(b), [1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(c), [0.0, 2.0])
    with pytest.raises(ValueError, match="65"):
        C.checkpoint(tuple(x for _ in range(65)))


# ------------------------------------------------------------------------------ the fibre
@given(vecs, vecs, vecs)
def test_unit_fibre_rotates_u_onto_xhat_on_both_branches(x, u, m_seed):
    def unit(a, fallback):
        n = np.linalg.norm(a, axis=-1, keepdims=True)
        return np.where(n > 1e-3, a / np.where(n > 0, n, 1), fallback)

    u = unit(u, [0.0, 0.0, 1.0])
    xhat = unit(x, -u)  # the antiparallel case (second branch) included
    xhat[0] = -u[0]
    m = np.asarray(unit_perpendicular(u))
    q = _unit_fibre(xhat, u, m)
    close(np.linalg.norm(q, axis=-1), 1.0, atol=1e-13)
    close(Q.quat_rotate(q, u), xhat, atol=1e-13)


@jax.jit
def _fibre_check(p0, p1, d0, d1, x, axis):
    """``fib(x) i fib(x)*`` in the frame built from the data (``axis=None``) or a given axis
    (module level: one program per axis kind for all examples, not one per example)."""
    _, _, _, _, frame = ph_quintic._prepare(p0, p1, d0, d1, axis)
    a = frame.fib(x, jnp.zeros(x.shape[:-1]))
    return ph_quintic._sandwich_i(a, a)


@given(vecs, vecs, vecs, vecs)
def test_fibre_map_solves_the_pythagorean_equation(p0, p1, d0, d1):
    """``fib(x) i fib(x)* = x`` in every frame the construction builds (data-driven and a
    given axis), for the data's own vectors and zero."""
    check = _fibre_check
    for x in (d0, d1 - p0, np.zeros_like(d0)):
        close(check(p0, p1, d0, d1, x, None), x, atol=1e-12)
        close(check(p0, p1, d0, d1, x, jnp.array([0.3, -1.0, 0.2])), x, atol=1e-12)


# ------------------------------------------------------------------------------ orientation
@given(quats, vecs, vecs, vecs, st.floats(0.0, 1.0))
def test_orientation_curve_matches_the_array_quaternion_formulas(q, w1, w2, w3, s):
    """``rotation`` and ``angular_velocity`` against the same formulas written with
    :mod:`phjax.quaternion` (the module docs), angular velocity also against differences."""
    q = np.where(np.linalg.norm(q, axis=-1, keepdims=True) > 1e-3, q, [1.0, 0, 0, 0])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    T = np.array([0.1, 0.5, 2.0])
    curve = pj.QuaternionHermite(q0=jnp.asarray(q), w1=jnp.asarray(w1), w2=jnp.asarray(w2),
                                 w3=jnp.asarray(w3), duration=jnp.asarray(T))

    def ref(s):
        c = 1 - s
        b = (1 - c**3, s * s * (3 - 2 * s), s**3)
        r = q
        for bj, w in zip(b, (w1, w2, w3)):
            r = Q.quat_mul(Q.quat_exp(bj * w), r)
        return r

    close(_rotation(curve, s), ref(s), atol=1e-13)
    h = 1e-6
    dq = (ref(s + h) - ref(s - h)) / (2 * h)
    omega = 2 * np.asarray(Q.quat_mul(dq, Q.quat_conj(ref(s))))[..., 1:] / T[:, None]
    close(_angular_velocity(curve, s), omega, rtol=1e-6, atol=1e-6 * (1 + np.abs(omega).max()))


_rotation = jax.jit(lambda c, s: c.rotation(s))
_angular_velocity = jax.jit(lambda c, s: c.angular_velocity(s))


# ------------------------------------------------------------------------------ kernel budget
def _kernels(fn, *args):
    text = jax.jit(fn).lower(*args).compile(compiler_options={"xla_cpu_use_fusion_emitters": False})
    entry = text.as_text().split("ENTRY")[-1]
    return len(re.findall(r" fusion\(", entry))


def test_small_batches_compile_to_few_kernels():
    """The point of the component form: the tracker's batch of 2 segments. Before it, the
    Hermite construction compiled to 117 XLA:CPU kernels and the orientation curve with its
    evaluation to 57; the bounds leave room for XLA changes but catch a regression to per-product
    or per-component kernels."""
    f32 = jnp.float32
    v = jnp.ones((2, 3), f32)
    assert _kernels(lambda a, b, c, d: pj.hermite_quintic(a, b, c, d), v, v, v, v) <= 24
    q, d = jnp.ones((2, 4), f32), jnp.ones((2,), f32)

    def orientation(q0, q1, w0, w1, d, s):
        r = jax.tree.map(lambda x: x[0], pj.quaternion_hermite(q0, q1, w0, w1, d))
        return r.rotation(s), r.angular_velocity(s)

    assert _kernels(orientation, q, q, v, v, d, f32(0.3)) <= 20
