"""The real-time driver ``TrackerStream``: same stream as the pure functions, packed state."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj
from phjax.motion import simulate
from phjax.tracking import stream
from phjax.tracking import tracker


@pytest.fixture(scope="module")
def meas():
    t, p, q = simulate.synthetic_head_motion(duration=4.0, seed=2)
    mt, mp, mq = (np.array(x) for x in simulate.simulate_measurements(5, t, p, q))
    mp[7:12] = np.nan  # a gap of several frames
    mq[9] = np.nan
    return mt - mt[0], mp, mq


def _comparable(state, exact: bool):
    """The state leaves to compare. With ``exact`` (float64) all of them, the reciprocal norms
    of the rotation increments multiplied by the norms (``1/|w|`` of a rounding-sized ``w``
    differs between two compiled programs; the products, all a sample uses, do not). Otherwise
    (float32) the filter only: rounding differences of the two programs move the free angles
    of nearly straight PH pieces and the high power-basis coefficients (the samples below are
    compared instead)."""
    def fix(v, layout):
        v = np.array(v, np.float64)
        (a, b), (c, d) = layout["n"], layout["inv_n"]
        v[c:d] = v[c:d] * v[a:b]
        return v

    if not exact:
        return jax.tree.leaves(state.filter)
    pieces = [fix(v, tracker._P) for v in state.render[:2]]
    R = {"n": tracker._R["n_end"], "inv_n": tracker._R["inv_n_end"]}
    return jax.tree.leaves(state.filter) + pieces + [fix(state.render[2], R), state.shape]


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("model", ["cv", "ca"])
def test_stream_equals_pure_functions(meas, dtype, model):
    """Every update and the samples between frames equal tracker_update / tracker_sample.

    The packed stream and ``tracker_update`` share the maths (``_update``, ``_eval_render``):
    this checks the packing (layouts, dtypes, no recompilation), not the tracker; the maths is
    tested independently in tests/tracking/test_tracker.py (finite-difference continuity of the
    world-frame velocities, segment starts, accuracy against ground truth and the Kalman
    baseline) and tests/tracking/test_kalman.py (filterpy)."""
    mt, mp, mq = meas
    cfg = pj.TrackerConfig(kalman=pj.KalmanConfig(model=model), imm=None, horizon=0.035)
    s = pj.TrackerStream(cfg, dtype=dtype)
    ref = pj.tracker_init(cfg, 0.0, dtype)
    tol = 1e-12 if dtype == jnp.float64 else 2e-5
    fn = stream._compiled_update(s._config_layout, s._layout)
    n0 = fn._cache_size()
    p_nan, _ = s.sample(0.01)
    assert np.all(np.isnan(np.asarray(p_nan)))  # nothing measured yet
    for k in range(40):
        s.update(float(mt[k]), mp[k], mq[k])
        ref = pj.tracker_update(cfg, ref, mt[k], mp[k], mq[k])
        for a, b in zip(jax.tree.leaves(s.state), jax.tree.leaves(ref)):
            assert a.dtype == b.dtype and a.shape == b.shape
        exact = dtype == jnp.float64
        for a, b in zip(_comparable(s.state, exact), _comparable(ref, exact)):
            np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                       rtol=tol, atol=tol)
        taus = mt[k] + np.array([0.0, 0.004, 0.013, 0.031, 0.2])
        P, Q = s.sample(jnp.asarray(taus, dtype))
        Pr, Qr = pj.tracker_sample(cfg, ref, jnp.asarray(taus, dtype))
        assert P.dtype == dtype and P.shape == (5, 3) and Q.shape == (5, 4)
        np.testing.assert_allclose(np.asarray(P), np.asarray(Pr), rtol=tol, atol=tol)
        np.testing.assert_allclose(np.asarray(Q), np.asarray(Qr), rtol=tol, atol=tol)
        assert np.all(np.isfinite(np.asarray(P))) and np.all(np.isfinite(np.asarray(Q)))
    # static shapes: the 40 frames (Python-float times, NumPy measurements) compiled once
    assert fn._cache_size() - n0 <= 1


def test_stream_packing_layout_and_state_round_trip(meas):
    """Packed vectors hold at most 64 elements (512 bytes of float64: XLA's CPU runtime runs
    the kernels in the calling thread), the config is one vector, booleans survive, and the
    state setter / getter round-trip exactly."""
    mt, mp, mq = meas
    # single-model filter: the IMM's (3, 6, 6) covariances are leaves of 108 elements
    cfg = pj.TrackerConfig(imm=None)
    s = pj.TrackerStream(cfg, dtype=jnp.float64)
    assert len(s._cvec) == 1 and s._cvec[0].shape == (len(jax.tree.leaves(cfg)),)
    assert all(v.ndim == 1 and v.size <= 64 for v in s._packed)
    assert len(s._packed) <= len(jax.tree.leaves(s.state)) // 2
    assert not bool(s.state.started) and s.state.filter.initialized.dtype == jnp.bool_
    s.update(0.0, mp[0], mq[0])
    st = s.state
    assert bool(st.started) and bool(st.filter.initialized)
    s2 = pj.TrackerStream(cfg, dtype=jnp.float64)
    s2.state = st
    for a, b in zip(jax.tree.leaves(s2.state), jax.tree.leaves(st)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the render vectors are passed to the sample kernel without unpacking
    for i, r in zip(s._render_at, st.render):
        np.testing.assert_array_equal(np.asarray(s._packed[i]), np.asarray(r))


def test_layout_round_trips_integer_and_bool_leaves():
    tree = {"b": jnp.array([True, False]), "i": jnp.arange(3, dtype=jnp.int32),
            "x": jnp.linspace(0.0, 1.0, 70, dtype=jnp.float32).reshape(7, 10), "y": jnp.float32(2.5)}
    lay = stream._Layout(tree, jnp.float32)
    packed = lay.pack(tree)
    assert [v.size for v in packed] == [5, 70, 1]  # 70 > 64 elements: a vector of its own
    out = lay.unpack(packed)
    for k in tree:
        assert out[k].dtype == (tree[k].dtype if k in "bi" else jnp.float32)
        np.testing.assert_array_equal(np.asarray(out[k]), np.asarray(tree[k]))


def test_stream_is_the_track_scan(meas):
    """The stream sampled at render times equals ``phjax.track`` (causal: the last update at or
    before each render time). Same maths on both sides (see
    ``test_stream_equals_pure_functions`` for where the maths itself is tested)."""
    mt, mp, mq = meas
    r = np.arange(0.0, mt[-1], 1 / 120)
    P_ref, Q_ref = (np.asarray(x) for x in pj.track(mt, mp, mq, r, dtype=jnp.float64))
    s = pj.TrackerStream(dtype=jnp.float64)
    P, Q = np.zeros_like(P_ref), np.zeros_like(Q_ref)
    k = 0
    for j, tau in enumerate(r):
        while k < len(mt) and mt[k] <= tau:
            s.update(mt[k], mp[k], mq[k])
            k += 1
        p, q = s.sample(tau)
        P[j], Q[j] = np.asarray(p), np.asarray(q)
    np.testing.assert_allclose(P, P_ref, atol=1e-12)
    np.testing.assert_allclose(Q, Q_ref, atol=1e-12)


@pytest.mark.parametrize("bad", [dict(position=np.zeros(4)), dict(quaternion=np.ones(3)),
                                 dict(t=np.zeros(2)), dict(position=0.5)])
def test_bad_shapes_raise_clear_errors(bad):
    args = dict(t=0.0, position=np.zeros(3), quaternion=np.array([1.0, 0, 0, 0])) | bad
    s = pj.TrackerStream(dtype=jnp.float64)
    with pytest.raises(ValueError, match="must have shape"):
        s.update(args["t"], args["position"], args["quaternion"])
    with pytest.raises(ValueError, match="must have shape"):
        pj.tracker_update(pj.TrackerConfig(), pj.tracker_init(), args["t"], args["position"],
                          args["quaternion"])
