"""Review tests of phjax.vision.alignment at unusual inputs (float32 users).

* Rows with weight 0 are ignored whatever finite value they hold (a 1e20 or float32-max
  placeholder for a missing landmark): they made ``0 * inf = NaN`` in the scale and the RMS,
  with status ``OK``.
* A large common offset (1e4 m, float32): the fit is evaluated relative to a usable point, so
  it keeps the resolution of the points themselves (before: 6.5e-5 rad rotation error for a
  10 cm cloud, 0.13 rad for a 1 mm one, and RANSAC kept 1 of 30 exact inliers with status OK).

References: NumPy's SVD solution (Umeyama 1991) in float64 on the same float32-rounded inputs.
One batched program per function (``with_scale=True``), one gradient program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from phjax.vision.alignment import OK, align, ransac_align

N = 8
M = 30
F32_MAX = float(np.finfo(np.float32).max)

_align_s = jax.jit(lambda s, t, w: align(s, t, w, with_scale=True))


def umeyama64(src, tgt, w, with_scale=True):
    """Weighted Umeyama with the determinant correction, float64 NumPy SVD."""
    src, tgt, w = (np.asarray(a, np.float64) for a in (src, tgt, w))
    keep = w > 0
    src, tgt, w = src[keep], tgt[keep], w[keep]
    wn = w / w.sum()
    mx, my = wn @ src, wn @ tgt
    xc, yc = src - mx, tgt - my
    u, d, vt = np.linalg.svd((yc * wn[:, None]).T @ xc)
    sgn = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ sgn @ vt
    s = np.trace(np.diag(d) @ sgn) / np.sum(wn * np.sum(xc * xc, 1)) if with_scale else 1.0
    rms = np.sqrt(np.sum(wn * np.sum((s * src @ rot.T + my - s * rot @ mx - tgt) ** 2, 1)))
    return rot, my - s * rot @ mx, s, rms


def _cases():
    """float32 problems (N rows): name -> (source, target, weights)."""
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(N, 3))
    rot = Rotation.random(random_state=5).as_matrix()
    tgt = pts @ rot.T + np.array([0.3, -0.2, 0.5]) + 0.01 * rng.normal(size=(N, 3))
    w = rng.uniform(0.5, 1.5, N)
    w0 = w.copy()
    w0[0] = 0.0
    huge_s, huge_t = pts.copy(), tgt.copy()
    huge_s[0], huge_t[0] = 1e20, -1e20
    max_s, max_t = pts.copy(), tgt.copy()
    max_s[0], max_t[0] = F32_MAX, -F32_MAX
    cases = {"zero_weight_1e20": (huge_s, huge_t, w0), "zero_weight_f32_max": (max_s, max_t, w0)}
    for spread in (0.1, 0.001):  # a head / a tiny marker cluster 10 km from the origin
        cases[f"offset_1e4_spread_{spread}"] = (1e4 + spread * pts,
                                                1e4 + spread * tgt + 0.01, w)
    return {k: tuple(np.asarray(a, np.float32) for a in v) for k, v in cases.items()}


def test_float32_zero_weight_placeholders_and_large_offsets():
    cases = _cases()
    src, tgt, w = (np.stack([c[i] for c in cases.values()]) for i in range(3))
    res = _align_s(src, tgt, w)
    for i, name in enumerate(cases):
        rot, t, s, rms = umeyama64(src[i], tgt[i], w[i])
        assert int(res.status[i]) == OK, name
        got = np.asarray(res.rotation[i], np.float64)
        err = Rotation.from_matrix(got @ rot.T).magnitude()
        # measured after the fix: <= 9e-7 rad, scale 5e-7, rms 1e-7 relative (before: scale
        # and rms NaN for the placeholders; 6.5e-5 and 0.13 rad at the offset)
        assert err < 1e-5, (name, err)
        assert abs(float(res.scale[i]) - s) < 1e-5 * s, (name, float(res.scale[i]), s)
        assert abs(float(res.rms[i]) - rms) < 1e-4 * rms + 1e-6, (name, float(res.rms[i]), rms)
        # translation to float32 resolution of the offset (ulp(3e4) = 2e-3)
        np.testing.assert_allclose(np.asarray(res.translation[i], np.float64), t,
                                   atol=2e-6 * (1 + np.abs(t).max()), err_msg=name)
        assert int(res.num_inliers[i]) == int(np.sum(w[i] > 0))

    # gradients stay finite with the placeholders (the rows are ignored: zero gradient)
    def loss(s, t, ww):
        r = align(s, t, ww, with_scale=True)
        return jnp.sum(r.rotation) + jnp.sum(r.translation) + jnp.sum(r.scale) + jnp.sum(r.rms)

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(src[:2], tgt[:2], w[:2])
    for g in grads:
        assert np.isfinite(np.asarray(g)).all()
    np.testing.assert_array_equal(np.asarray(grads[0])[:, 0], 0)
    np.testing.assert_array_equal(np.asarray(grads[1])[:, 0], 0)


def test_ransac_float32_large_offset_keeps_its_inliers():
    rng = np.random.default_rng(8)
    src = rng.normal(scale=0.08, size=(M, 3))
    rot = Rotation.random(random_state=rng).as_matrix()
    tgt = src @ rot.T + np.array([0.01, 0.02, -0.03])
    tgt[:5] += 0.1  # five gross outliers
    off = np.array([1e4, -2e4, 5e3])
    src32, tgt32 = np.float32(src + off), np.float32(tgt + off)
    res = jax.jit(lambda k, s, t: ransac_align(k, s, t, threshold=0.003))(
        jax.random.key(0), src32, tgt32)
    expected = np.arange(M) >= 5
    # before: status OK with num_inliers 1 (residuals rounded at the 1e4 offset)
    assert int(res.status) == OK
    np.testing.assert_array_equal(np.asarray(res.inlier_mask), expected)
    assert int(res.num_inliers) == M - 5
    r_ref, t_ref, _, rms_ref = umeyama64(src32[5:], tgt32[5:], np.ones(M - 5), False)
    err = Rotation.from_matrix(np.asarray(res.rotation, np.float64) @ r_ref.T).magnitude()
    assert err < 1e-5, err
    # the inputs are rounded to 1e-3 m: the residual RMS is that, not the rounding of the fit
    assert abs(float(res.rms) - rms_ref) < 1e-4 * rms_ref + 1e-6, (float(res.rms), rms_ref)
    np.testing.assert_allclose(np.asarray(res.translation, np.float64), t_ref,
                               atol=2e-6 * (1 + np.abs(t_ref).max()))
