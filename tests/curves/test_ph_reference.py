"""phjax against the independent NumPy re-derivation (tests/curves/reference_ph_numpy.py) from the note."""

import numpy as np
import pytest

import phjax as pj
import reference_ph_numpy as ref


@pytest.mark.parametrize("branch", ["generic", "second_branch"])
def test_control_points_and_closed_forms_match_numpy_reference(branch):
    rng = np.random.default_rng(21)
    n = 500
    p0, p1, d0, d1 = rng.normal(size=(4, n, 3))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    if branch == "second_branch":
        d1 = -axis * rng.uniform(0.5, 2, size=(n, 1)) + 0.1 * rng.normal(size=(n, 3))
    phi0, phi1, phi2 = rng.uniform(-np.pi, np.pi, size=(3, n))
    A0, A1, A2, P = ref.hermite_quintic_np(p0, p1, d0, d1, phi0, phi1, phi2, axis,
                                           perpendicular=ref.data_perpendicular_np(p0, p1, d1))
    c = pj.hermite_quintic(p0, p1, d0, d1, phi0, phi2, phi1=phi1, axis=axis)
    scale = 1 + np.abs(P).max(axis=(-1, -2), keepdims=True)
    np.testing.assert_allclose(np.asarray(c.control_points) / scale, P / scale, atol=1e-12)
    t = np.linspace(0, 1, 9)
    np.testing.assert_allclose(c.position(t), ref.position_np(P, t), atol=1e-11)
    np.testing.assert_allclose(c.arc_length(t), ref.arc_length_np(A0, A1, A2, t), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(c.length, ref.total_length_np(A0, A1, A2), rtol=1e-12)
    ti = np.linspace(0.1, 0.9, 5)
    kap = ref.curvature_np(P, ti)
    np.testing.assert_allclose(c.curvature(ti), kap, rtol=1e-8, atol=1e-10)
    good = kap > 1e-3
    # measured: at most 1.4e-11 relative (generic) / 6.0e-12 (second branch); bound ~70x
    np.testing.assert_allclose(np.asarray(c.torsion(ti))[good], ref.torsion_np(P, ti)[good],
                               rtol=1e-9, atol=1e-12)
