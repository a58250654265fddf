"""Evaluation semantics of the curve classes: the last axis of ``t`` is the sample axis, its
leading axes broadcast against the curve batch (``(T,)``: the same parameters on every curve,
``batch + (T,)``: each curve at its own, no outer product); scalars; clear errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj

KINDS = ("rmf", "euler_rodrigues", "frenet")


def _curves(shape, seed=0):
    rng = np.random.default_rng(seed)
    p0, p1, d0, d1 = rng.normal(size=(4,) + tuple(shape) + (3,))
    return pj.hermite_quintic(p0, p1, d0, d1)


def _evaluations(c, t, names=None):
    """The parameter-taking methods of PHQuintic at ``t`` (``parameter_at_length`` at the lengths
    ``t * L``; at ``t * min(L)`` for a scalar ``t``); ``names`` selects a subset (compiling all
    of them for one more shape costs seconds)."""
    t = jnp.asarray(t)
    lengths = c.length[..., None] if t.ndim else jnp.min(c.length)
    methods = {
        "position": lambda: c.position(t),
        "hodograph": lambda: c.hodograph(t),
        "quaternion_polynomial": lambda: c.quaternion_polynomial(t),
        "speed": lambda: c.speed(t),
        "arc_length": lambda: c.arc_length(t),
        "parameter_at_length": lambda: c.parameter_at_length(t * lengths),
        "curvature": lambda: c.curvature(t),
        "torsion": lambda: c.torsion(t),
        "rmf_angle": lambda: c.rmf_angle(t),
        "frame_quaternion[rmf]": lambda: c.frame_quaternion(t, "rmf"),
    }
    for kind in KINDS:
        methods[f"frame[{kind}]"] = lambda kind=kind: c.frame(t, kind)
    names = methods if names is None else names
    return {k: np.asarray(methods[k]()) for k in names}


SOME = ("position", "curvature", "parameter_at_length", "frame[rmf]")
_TRAILING = {"position": (3,), "hodograph": (3,), "quaternion_polynomial": (4,),
             "frame_quaternion[rmf]": (4,)}
_TRAILING.update({f"frame[{k}]": (3, 3) for k in KINDS})


def _slice(c, idx):
    return jax.tree.map(lambda x: x[idx], c)


def test_sample_parameters_give_per_curve_shapes_for_1000_curves():
    """The issue's case: t from ``sample`` evaluates each curve at its own parameters."""
    n, m = 1000, 100
    curves = _curves((n,))
    for by in ("time", "arclength"):
        t, pts = pj.sample(curves, m, by=by)
        assert t.shape == (n, m)
        assert curves.curvature(t).shape == (n, m)
        assert curves.frame(t, "rmf").shape == (n, m, 3, 3)
        np.testing.assert_allclose(curves.position(t), pts, atol=1e-13)
    # the same T parameters on every curve, and scalars
    assert curves.curvature(jnp.linspace(0, 1, 7)).shape == (n, 7)
    assert curves.frame(jnp.linspace(0, 1, 7)).shape == (n, 7, 3, 3)
    assert curves.curvature(0.5).shape == (n,)
    assert curves.frame(0.5).shape == (n, 3, 3)


def test_per_curve_parameters_equal_a_loop_over_single_curves():
    batch = (2, 3)
    rng = np.random.default_rng(1)
    c = _curves(batch, seed=2)
    t = rng.uniform(0, 1, size=batch + (4,))
    t[..., 0] = 0.0  # the ends and an exact 1 are in the set
    t.flat[-1] = 1.0
    got = _evaluations(c, t)
    for idx in np.ndindex(*batch):
        ref = _evaluations(_slice(c, idx), t[idx])
        for name, v in got.items():
            assert v.shape == batch + (4,) + _TRAILING.get(name, ()), name
            np.testing.assert_allclose(v[idx], ref[name], rtol=1e-12, atol=1e-12, err_msg=name)


def test_shared_parameters_equal_broadcast_per_curve_parameters():
    batch = (2, 3)
    c = _curves(batch, seed=3)
    t = np.linspace(0, 1, 4)
    shared = _evaluations(c, t)
    per_curve = _evaluations(c, np.broadcast_to(t, batch + (4,)))
    partial = _evaluations(c, np.broadcast_to(t, batch[-1:] + (4,)), SOME)  # (3, 4) broadcasts
    for name in shared:
        assert shared[name].shape == batch + (4,) + _TRAILING.get(name, ()), name
        np.testing.assert_allclose(per_curve[name], shared[name], rtol=1e-13, atol=1e-13,
                                   err_msg=name)
        if name in partial:
            np.testing.assert_allclose(partial[name], shared[name], rtol=1e-13, atol=1e-13,
                                       err_msg=name)


def test_scalar_parameter_and_single_parameter_per_curve():
    rng = np.random.default_rng(4)
    c = _curves((6,), seed=5)
    scalar = _evaluations(c, 0.3, SOME)
    column = _evaluations(c, np.full((6, 1), 0.3), SOME)
    for name in scalar:
        assert scalar[name].shape == (6,) + _TRAILING.get(name, ()), name
        if name != "parameter_at_length":  # scalar: at 0.3 min(L); column: at 0.3 L per curve
            np.testing.assert_allclose(column[name][:, 0], scalar[name], rtol=1e-13, atol=1e-13)
    s0 = 0.3 * float(np.min(np.asarray(c.length)))
    np.testing.assert_allclose(c.parameter_at_length(np.full((6, 1), s0))[:, 0],
                               scalar["parameter_at_length"], rtol=1e-13, atol=1e-13)
    # one parameter per curve: t[..., None], equal to vmap over the curves
    s = rng.uniform(0, 1, 6)
    np.testing.assert_allclose(c.position(s[:, None])[:, 0],
                               jax.vmap(lambda cc, x: cc.position(x))(c, s), atol=1e-14)


def test_single_curve_keeps_any_parameter_shape():
    c = _curves((), seed=6)
    t = np.random.default_rng(7).uniform(0, 1, size=(3, 4, 5))
    got = _evaluations(c, t, SOME)
    for name, v in got.items():
        assert v.shape == (3, 4, 5) + _TRAILING.get(name, ()), name
    np.testing.assert_allclose(got["curvature"][1, 2], np.asarray(c.curvature(t[1, 2])), rtol=1e-13)


def test_per_curve_parameters_under_jit_and_grad():
    c = _curves((8,), seed=8)
    t, _ = pj.sample(c, 5)
    f = jax.jit(lambda cc, tt: cc.frame(tt, "rmf"))
    np.testing.assert_allclose(f(c, t), c.frame(t, "rmf"), atol=1e-14)
    g = jax.grad(lambda tt: jnp.sum(c.curvature(tt)))(t)
    assert g.shape == t.shape and np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("shape", [(2, 4), (5, 4), (3, 5, 4), (6, 2, 4)])
def test_parameters_that_do_not_broadcast_raise(shape):
    c = _curves((6,), seed=9)
    t = np.full(shape, 0.5)
    for method in (c.position, c.curvature, c.frame, c.rmf_angle, c.parameter_at_length):
        with pytest.raises(ValueError, match=r"sample axis.*broadcast against the batch shape"):
            method(t)


def test_orientation_curves_follow_the_same_rule():
    rng = np.random.default_rng(10)
    q0, q1 = pj.quat_normalize(rng.normal(size=(2, 4, 4)))
    w0, w1 = rng.normal(size=(2, 4, 3))
    r = pj.quaternion_hermite(q0, q1, w0, w1, 0.1)
    s = rng.uniform(0, 1, size=(4, 7))
    both = jax.jit(lambda rr, ss: (rr.rotation(ss), rr.angular_velocity(ss)))  # one compile
    q, w = both(r, s)
    assert q.shape == (4, 7, 4) and w.shape == (4, 7, 3)
    for k in range(4):
        qk, wk = both(jax.tree.map(lambda x, k=k: x[k], r), s[k])
        np.testing.assert_allclose(q[k], qk, atol=1e-13)
        np.testing.assert_allclose(w[k], wk, atol=1e-12)
    assert r.rotation(np.linspace(0, 1, 7)).shape == (4, 7, 4)
    assert r.rotation(0.5).shape == (4, 4)
    with pytest.raises(ValueError, match="sample axis"):
        r.rotation(np.zeros((3, 7)))
