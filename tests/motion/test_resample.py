"""Tests for phjax.motion.resample: interpolation with NaN rows / gaps and finite-difference velocities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from phjax.quaternion import quat_from_rotvec, quat_geodesic_distance, quat_mul
from phjax.motion.resample import finite_difference_velocities, interpolate_poses, snap_to_frames


def _wxyz(r: Rotation) -> np.ndarray:
    return r.as_quat()[..., [3, 0, 1, 2]]


def _random_stream(seed, n=12):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.2, n))
    p = rng.normal(size=(n, 3))
    q = _wxyz(Rotation.random(n, random_state=seed))
    return rng, t, p, q


def _angle(a, b):
    return np.asarray(quat_geodesic_distance(jnp.asarray(a), jnp.asarray(b)))


@settings(max_examples=15)
@given(st.integers(0, 10_000))
def test_matches_numpy_interp_and_scipy_slerp_with_nan_rows_and_flips(seed):
    rng, t, p, q = _random_stream(seed)
    p_in, q_in = p.copy(), q.copy()
    q_in[rng.random(len(t)) < 0.5] *= -1  # hemisphere flips must not matter
    drop_p = rng.random(len(t)) < 0.25
    drop_q = rng.random(len(t)) < 0.25
    drop_p[[0, -1]] = drop_q[[0, -1]] = False
    p_in[drop_p] = np.nan
    q_in[drop_q, 2] = np.nan  # a single NaN component invalidates the row
    query = np.sort(rng.uniform(t[0], t[-1], 40))

    p_out, q_out = interpolate_poses(t, p_in, q_in, query)

    kp = ~drop_p
    p_ref = np.stack([np.interp(query, t[kp], p[kp, c]) for c in range(3)], -1)
    np.testing.assert_allclose(p_out, p_ref, atol=1e-12)
    kq = ~drop_q
    q_ref = _wxyz(Slerp(t[kq], Rotation.from_quat(q[kq][:, [1, 2, 3, 0]]))(query))
    np.testing.assert_array_less(_angle(q_out, q_ref), 1e-9)
    np.testing.assert_allclose(np.linalg.norm(q_out, axis=-1), 1, atol=1e-12)


def test_exact_for_linear_motion_and_constant_angular_velocity():
    t = np.array([0.0, 0.1, 0.35, 0.4, 1.0])
    v, p0 = np.array([0.3, -1.0, 2.0]), np.array([1.0, 2.0, 3.0])
    w = np.array([0.2, -0.5, 1.1])  # rad/s, fixed axis
    q0 = _wxyz(Rotation.from_rotvec([0.3, 0.2, -0.1]))
    pos = lambda s: p0 + np.outer(s, v)  # noqa: E731
    quat = lambda s: np.asarray(quat_mul(quat_from_rotvec(np.outer(s, w)), q0))  # noqa: E731
    query = np.linspace(0, 1, 37)
    p_out, q_out = interpolate_poses(t, pos(t), quat(t), query)
    np.testing.assert_allclose(p_out, pos(query), atol=1e-12)
    np.testing.assert_array_less(_angle(q_out, quat(query)), 1e-7)


def test_knots_clamping_and_no_valid_rows():
    _, t, p, q = _random_stream(1, n=6)
    p_out, q_out = interpolate_poses(t, p, q, t)
    np.testing.assert_allclose(p_out, p, atol=1e-12)
    np.testing.assert_array_less(_angle(q_out, q), 1e-7)

    p_out, q_out = interpolate_poses(t, p, q, np.array([t[0] - 5, t[-1] + 5]))
    np.testing.assert_allclose(p_out, p[[0, -1]], atol=1e-12)
    np.testing.assert_array_less(_angle(q_out, q[[0, -1]]), 1e-7)

    # orientation-only data: NaN positions everywhere -> NaN positions, orientations fine
    p_out, q_out = interpolate_poses(t, np.full_like(p, np.nan), q, t[:3])
    assert np.all(np.isnan(p_out)) and np.all(np.isfinite(q_out))
    # a single valid row gives a constant pose
    p1 = np.full_like(p, np.nan)
    p1[2] = p[2]
    p_out, _ = interpolate_poses(t, p1, q, np.linspace(t[0] - 1, t[-1] + 1, 9))
    np.testing.assert_allclose(p_out, np.broadcast_to(p[2], (9, 3)))


def test_zero_quaternion_is_skipped_like_nan():
    """A zero quaternion row (no orientation) was normalised to the identity and interpolated
    as a real sample: one ground-truth row 89 degrees off, and the raw-hold RMSE of an
    evaluation 1.90 -> 7.31 deg (found by probing). It is skipped like a NaN row."""
    _, t, p, q = _random_stream(3, n=8)
    query = np.linspace(t[0], t[-1], 23)
    qz, qn = q.copy(), q.copy()
    qz[3], qn[3] = 0.0, np.nan
    _, with_zero = interpolate_poses(t, p, qz, query)
    _, with_nan = interpolate_poses(t, p, qn, query)
    np.testing.assert_array_equal(np.asarray(with_zero), np.asarray(with_nan))
    assert np.isfinite(np.asarray(with_zero)).all()


def test_max_gap_gives_nan_strictly_inside_long_gaps():
    t = np.arange(10) * 0.1
    p = np.stack([t, 2 * t, -t], -1)
    q = _wxyz(Rotation.from_rotvec(np.outer(t, [0, 0, 1])))
    p[4:6] = np.nan  # gap (0.3, 0.6) of 0.3 s in positions only
    query = np.array([t[3], 0.31, 0.45, 0.59, t[6], 0.65, -1.0, 2.0])
    p_out, q_out = map(np.asarray, interpolate_poses(t, p, q, query, max_gap=0.25))
    assert np.all(np.isnan(p_out[1:4]))
    np.testing.assert_allclose(p_out[[0, 4, 5]][:, 0], [0.3, 0.6, 0.65], atol=1e-12)
    np.testing.assert_allclose(p_out[6:, 0], [0.0, 0.9], atol=1e-12)  # clamped, not NaN
    assert np.all(np.isfinite(q_out))  # the orientation channel has no gap
    # a looser threshold interpolates across the gap
    p_out, _ = interpolate_poses(t, p, q, query, max_gap=0.35)
    np.testing.assert_allclose(p_out[:6, 0], query[:6], atol=1e-12)


def test_jit_vmap_grad_and_float32():
    _, t, p, q = _random_stream(3, n=8)
    p[3] = np.nan
    query = jnp.linspace(t[0], t[-1], 11)

    def loss(pos, qt):
        po, qo = interpolate_poses(t, pos, q, qt, max_gap=0.5)
        return jnp.nansum(po**2) + jnp.nansum(qo[:, 1:] ** 2)

    gp, gqt = jax.grad(loss, argnums=(0, 1))(jnp.asarray(p), query)
    assert np.all(np.isfinite(gp)) and np.all(np.isfinite(gqt))
    assert np.all(gp[3] == 0)  # the dropped row has no influence

    batch = jax.vmap(lambda s: interpolate_poses(t, p + s, q, query)[0])(jnp.arange(3.0))
    np.testing.assert_allclose(batch[2] - batch[0], 2.0, atol=1e-12)

    p32, q32 = interpolate_poses(t.astype(np.float32), p.astype(np.float32), q.astype(np.float32),
                                 np.asarray(query, np.float32))
    assert p32.dtype == jnp.float32 and q32.dtype == jnp.float32
    p64, q64 = interpolate_poses(t, p, q, query)
    np.testing.assert_allclose(p32, p64, atol=1e-5)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        interpolate_poses(np.zeros(3), np.zeros((3, 2)), np.zeros((3, 4)), np.zeros(2))
    with pytest.raises(ValueError):
        finite_difference_velocities(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 4)))
    # unsorted samples gave wrong values silently ([0, 0, 0] for a line through the queries)
    t = np.linspace(0, 1, 5)
    with pytest.raises(ValueError, match="times must be non-decreasing"):
        interpolate_poses(t[::-1], np.stack([t[::-1]] * 3, -1), np.tile([1.0, 0, 0, 0], (5, 1)),
                          [0.1, 0.3])


def test_velocities_exact_for_quadratics_on_nonuniform_grid():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.01, 0.1, 15))
    a, b, c = rng.normal(size=(3, 3))
    p = a + np.outer(t, b) + np.outer(t**2, c)
    # fixed axis, quadratic angle: angular velocity (2 c0 t + b0) n, exact for the stencil
    n_ax = np.array([1.0, 2.0, -2.0]) / 3
    ang = 0.3 + 1.5 * t - 2.0 * t**2
    q = _wxyz(Rotation.from_rotvec(np.outer(ang, n_ax)))
    q[rng.random(len(t)) < 0.5] *= -1
    v, w = finite_difference_velocities(t, p, q)
    np.testing.assert_allclose(v, b + 2 * np.outer(t, c), atol=1e-9)
    np.testing.assert_allclose(w, np.outer(1.5 - 4.0 * t, n_ax), atol=1e-9)

    v2, w2 = finite_difference_velocities(t[:2], p[:2], q[:2])
    np.testing.assert_allclose(v2[0], (p[1] - p[0]) / (t[1] - t[0]))


def test_world_frame_angular_velocity_of_composed_rotation():
    """q(t) = Rz(a t) Rx(b t) has world-frame omega = a e_z + Rz(a t) b e_x."""
    a, b = 1.3, -0.7
    t = np.sort(np.concatenate([np.linspace(0, 2, 2001), [0.0005, 1.0003]]))
    rz = Rotation.from_rotvec(np.outer(a * t, [0, 0, 1]))
    rot = rz * Rotation.from_rotvec(np.outer(b * t, [1, 0, 0]))
    _, w = finite_difference_velocities(t, np.zeros((len(t), 3)), _wxyz(rot))
    ref = a * np.array([0, 0, 1.0]) + rz.apply([b, 0, 0])
    np.testing.assert_allclose(w, ref, atol=1e-5)


@pytest.mark.parametrize("t0", [0.0, 0.37, 1.3e9])
def test_snap_to_frames_makes_coincident_clocks_exact(t0):
    """A 120 Hz render clock and a 30 Hz frame clock built as separate sums meet every 4th
    sample only up to rounding (either side); after snapping they meet exactly, every other
    sample is untouched, and a searchsorted(side="right") then sees the frame at its instant."""
    frames = t0 + np.arange(90) / 30.0
    render = frames[1] + np.arange(300) / 120.0
    coincide = np.arange(300) % 4 == 0
    off = render[coincide] - frames[1 + np.arange(coincide.sum())]
    assert t0 or np.any(off != 0)  # the sums do round differently
    snapped = snap_to_frames(frames, render)
    np.testing.assert_array_equal(snapped[coincide], frames[1:1 + coincide.sum()])
    np.testing.assert_array_equal(snapped[~coincide], render[~coincide])
    seen = np.searchsorted(frames, snapped, side="right") - 1
    np.testing.assert_array_equal(seen[coincide], 1 + np.arange(coincide.sum()))
    assert snapped.dtype == np.float64


def test_snap_to_frames_float32_frame_times_and_far_samples():
    frames32 = (np.arange(40) / np.float32(30.0)).astype(np.float32)  # e.g. simulated without x64
    render = np.float64(1 / 30) + np.arange(100) / 120.0
    snapped = snap_to_frames(frames32, render)
    np.testing.assert_array_equal(snapped[::4], frames32[1:26].astype(np.float64))
    # 1 us off a frame (float64 frames): a real offset, not rounding
    np.testing.assert_array_equal(snap_to_frames(np.array([0.0, 1.0]), [1.0 + 1e-6]), [1.0 + 1e-6])
    # before the first and after the last frame
    np.testing.assert_array_equal(snap_to_frames(np.array([1.0, 2.0]), [0.5, 2.5]), [0.5, 2.5])


def test_snap_to_frames_tolerance_is_capped_and_empty_frames_pass_through():
    # float32 frame times at 10^4 s: 8 units of rounding (~8 ms) would exceed a 120 Hz render
    # period; the cap (a tenth of the frame interval) keeps the other samples where they are
    frames64 = 1e4 + np.arange(40) / 30.0
    frames32 = frames64.astype(np.float32)
    render = frames64[1] + np.arange(100) / 120.0
    snapped = snap_to_frames(frames32, render)
    moved = snapped != render
    assert np.all(np.diff(snapped) > 0)
    np.testing.assert_array_equal(np.flatnonzero(moved) % 4, 0)
    np.testing.assert_array_equal(snapped[::4], frames32[1:26].astype(np.float64))
    np.testing.assert_array_equal(snap_to_frames(np.zeros(0), [1.0, 2.0]), [1.0, 2.0])


def test_epoch_times_interpolate_as_relative_ones():
    """Interpolation runs relative to the first sample time: with Unix times (1.7e9 s) the
    float32 program rounded every time to 128 s (metres off on a TUM recording)."""
    t = np.linspace(0, 2, 61)
    p = np.stack([np.sin(t), np.cos(t), t], -1)
    q = np.tile([1.0, 0, 0, 0], (61, 1))
    r = np.linspace(0.1, 1.9, 37)
    rel = np.asarray(interpolate_poses(t, p, q, r)[0])
    epoch = np.asarray(interpolate_poses(t + 1.7e9, p, q, r + 1.7e9)[0])
    np.testing.assert_allclose(epoch, rel, atol=1e-5)


def test_max_gap_counts_invalid_rows_at_either_end_as_a_gap():
    """Ground truth whose tracking was lost before its last row (or found only after its
    first): the evaluation scored render samples there against the held end pose. With
    ``max_gap`` the invalid rows at an end are a gap as long as they span (NaN when longer,
    held when shorter, as inside); queries outside ``[times[0], times[-1]]`` stay clamped."""
    t = np.arange(10) * 0.1
    p = np.stack([t, 2 * t, -t], -1)
    q = _wxyz(Rotation.from_rotvec(np.outer(t, [0, 0, 1])))
    p[8:] = np.nan  # positions lost for the last 0.2 s (0.7 .. 0.9)
    q[:3] = 0.0  # orientations found at 0.3 s (zero rows are invalid)
    query = np.array([0.0, 0.15, t[3], 0.5, t[7], 0.75, 0.9, -1.0, 2.0])
    p_out, q_out = map(np.asarray, interpolate_poses(t, p, q, query, max_gap=0.15))
    assert np.isnan(p_out[[5, 6]]).all() and np.isfinite(p_out[[0, 1, 2, 3, 4, 7, 8]]).all()
    np.testing.assert_allclose(p_out[[4, 7, 8], 0], [0.7, 0.0, 0.7], atol=1e-12)
    assert np.isnan(q_out[[0, 1]]).all() and np.isfinite(q_out[2:]).all()  # -1.0: clamped
    # gaps shorter than max_gap at the ends are held, as before
    p_out, q_out = map(np.asarray, interpolate_poses(t, p, q, query, max_gap=0.35))
    np.testing.assert_allclose(p_out[[5, 6], 0], [0.7, 0.7], atol=1e-12)
    assert np.isfinite(q_out).all()
    # without max_gap every end is clamped
    p_out, q_out = map(np.asarray, interpolate_poses(t, p, q, query))
    assert np.isfinite(p_out).all() and np.isfinite(q_out).all()
