"""Tests for phjax.vision.synthetic_rgbd: the procedural RGB-D head sequence.

Independent references: a brute-force NumPy ray cast of the model's implicit surface and the
wall plane (dense sampling + bisection, float64), the ground-truth poses and landmarks, the
world-frame trajectory of ``synthetic_head_motion``, and noise statistics of the Kinect model.
The end-to-end check runs projective point-to-plane ICP between rendered frames.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import YUNET_ONNX, yunet_models

from phjax import synthetic_head_motion
from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.vision.icp import backproject, estimate_normals, icp_projective
from phjax.vision.synthetic_rgbd import (
    LANDMARK_NAMES,
    HeadModel,
    SyntheticRGBDFrame,
    add_depth_noise,
    render_rgbd,
    synthetic_rgbd_sequence,
)

N_FRAMES = 61


def rotate(q, v):
    vq = np.concatenate([np.zeros(np.shape(v)[:-1] + (1,)), v], -1)
    q, vq = np.broadcast_arrays(q, vq)
    return np_qmul(np_qmul(q, vq), np_qconj(q))[..., 1:]


@pytest.fixture(scope="module")
def clean():
    return synthetic_rgbd_sequence(N_FRAMES, seed=0, depth_noise=False, color_noise=0.0)


@pytest.fixture(scope="module")
def noisy():
    return synthetic_rgbd_sequence(N_FRAMES, seed=0)


@pytest.fixture(scope="module")
def frames(clean, noisy):
    """A few rendered frames, shared by the tests: {(kind, index): frame}."""
    return {(kind, k): seq[k] for kind, seq in (("clean", clean), ("noisy", noisy))
            for k in (0, 45)}


# ------------------------------------------------------------------------------- structure
def test_shapes_dtypes_and_metadata(clean, frames):
    f = frames["clean", 45]
    assert isinstance(f, SyntheticRGBDFrame) and f.index == 45
    assert f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    assert f.head_mask.shape == (480, 640) and f.head_mask.dtype == bool
    assert f.timestamp == pytest.approx(45 / 30)
    k = f.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (525.0, 525.0, 319.5, 239.5)
    assert f.landmarks.shape == (len(LANDMARK_NAMES), 3)
    assert f.landmarks_2d.shape == (len(LANDMARK_NAMES), 2)
    assert np.linalg.norm(f.head_quaternion) == pytest.approx(1.0)
    assert len(clean) == N_FRAMES and clean.timestamps.shape == (N_FRAMES,)
    assert np.all((clean.head_positions[:, 2] > 0.7) & (clean.head_positions[:, 2] < 1.0))
    np.testing.assert_allclose(np.diff(clean.timestamps), 1 / 30)
    # every pixel has a depth (wall or head) without noise; the head covers a plausible area
    assert np.all(f.depth > 0)
    assert 4000 < f.head_mask.sum() < 20000
    np.testing.assert_allclose(f.landmark("nose_tip"), f.landmarks[2])
    np.testing.assert_allclose(f.eye_centre, (f.landmarks[0] + f.landmarks[1]) / 2)
    assert clean[-1].index == N_FRAMES - 1
    with pytest.raises(IndexError):
        clean[N_FRAMES]
    with pytest.raises(ValueError, match="num_frames"):
        synthetic_rgbd_sequence(0)


def test_iteration_yields_all_frames(clean):
    seq = synthetic_rgbd_sequence(2, seed=0, depth_noise=False, color_noise=0.0)
    assert seq.crop == clean.crop  # shares the compiled renderer
    frames = list(seq)
    assert [f.index for f in frames] == [0, 1]
    np.testing.assert_array_equal(frames[1].depth, clean[1].depth)


def test_determinism_by_seed(frames):
    again = synthetic_rgbd_sequence(N_FRAMES, seed=0)[45]
    f = frames["noisy", 45]
    np.testing.assert_array_equal(again.color, f.color)
    np.testing.assert_array_equal(again.depth, f.depth)
    other = synthetic_rgbd_sequence(N_FRAMES, seed=1)
    assert not np.allclose(other.head_quaternions[45], f.head_quaternion)
    # the noise differs per frame and is switched off cleanly
    clean = frames["clean", 45]
    valid = f.depth > 0
    assert 0.97 < valid.mean() < 1.0
    d = (f.depth - clean.depth)[valid & (clean.depth < 1.2)]
    assert 0.3e-3 < np.std(d) < 3e-3


# --------------------------------------------------------------------- geometry (clean)
def head_to_camera(frame, x):
    return frame.head_position + rotate(frame.head_quaternion, x)


def camera_to_head(frame, x):
    return rotate(np_qconj(frame.head_quaternion), x - frame.head_position)


@pytest.mark.parametrize("k", [0, 45])
def test_depth_lies_on_the_model_surface_and_the_wall(clean, frames, k):
    f = frames["clean", k]
    pts = np.asarray(backproject(f.depth.astype(np.float64), f.intrinsics))
    head = camera_to_head(f, pts[f.head_mask])
    assert np.max(np.abs(clean.model.implicit_np(head))) < 1e-5  # float32 rendering
    wall = pts[~f.head_mask]
    np.testing.assert_allclose(wall @ clean.wall[:3], clean.wall[3], atol=1e-5)


def reference_depth(seq, frame, ii, jj):
    """Brute-force float64 ray cast: 1 mm samples along each pixel ray, then bisection."""
    k = frame.intrinsics
    ray = np.stack([(jj - k.cx) / k.fx, (ii - k.cy) / k.fy, np.ones(len(ii))], -1)
    qi = np_qconj(frame.head_quaternion)
    o, d = rotate(qi, -frame.head_position), rotate(qi, ray)
    s = np.arange(0.6, 1.3, 0.001)
    g = seq.model.implicit_np(o + s[None, :, None] * d[:, None, :])
    neg = g < 0
    hit = neg.any(1)
    kk = np.argmax(neg, 1)
    a, b = s[np.maximum(kk - 1, 0)], s[kk]
    for _ in range(40):
        mid = 0.5 * (a + b)
        pos = seq.model.implicit_np(o + mid[:, None] * d) > 0
        a, b = np.where(pos, mid, a), np.where(pos, b, mid)
    s_head = np.where(hit, 0.5 * (a + b), np.inf)
    s_wall = seq.wall[3] / (ray @ seq.wall[:3])
    return np.minimum(s_head, s_wall), s_head < s_wall


@pytest.mark.parametrize("k", [0, 45])
def test_depth_matches_an_independent_ray_cast(clean, frames, k):
    f = frames["clean", k]
    rng = np.random.default_rng(k)
    ii, jj = np.nonzero(f.head_mask)
    pick = rng.integers(0, len(ii), 150)
    # head pixels plus random pixels of the head's bounding box (silhouettes, wall)
    bi = rng.integers(ii.min() - 10, ii.max() + 10, 150)
    bj = rng.integers(jj.min() - 10, jj.max() + 10, 150)
    ii, jj = np.r_[ii[pick], bi], np.r_[jj[pick], bj]
    expected, is_head = reference_depth(clean, f, ii, jj)
    err = np.abs(f.depth[ii, jj] - expected)
    agree = err < 1e-5
    assert agree.mean() >= 0.99  # rare misses: grazing rays exactly at the silhouette
    assert np.mean(f.head_mask[ii, jj] == is_head) >= 0.99
    assert np.all(agree | (np.abs(f.depth[ii, jj] - f.depth[np.clip(ii + 1, 0, 479), jj]) > 0.01)
                  | (np.abs(f.depth[ii, jj] - f.depth[ii, np.clip(jj + 1, 0, 639)]) > 0.01)
                  | (np.abs(f.depth[ii, jj] - f.depth[np.clip(ii - 1, 0, 479), jj]) > 0.01)
                  | (np.abs(f.depth[ii, jj] - f.depth[ii, np.clip(jj - 1, 0, 639)]) > 0.01))


def test_model_landmarks_and_bounds(clean):
    model = clean.model
    assert isinstance(model, HeadModel)
    lm = np.asarray(model.landmarks, np.float64)
    assert np.max(np.abs(model.implicit_np(lm))) < 1e-6  # on the surface
    pts = model.sample_surface(3000, seed=1)
    assert np.max(np.abs(model.implicit_np(pts))) < 1e-12
    # bounding ellipsoids used by the renderer enclose / are enclosed by the surface
    outer, inner = np.asarray(model.outer_axes), np.asarray(model.inner_axes)
    assert np.all(np.sum((pts / outer) ** 2, -1) < 1) and np.all(np.sum((pts / inner) ** 2, -1) > 1)
    # the float32 JAX radial function agrees with the float64 NumPy twin
    d = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
    np.testing.assert_allclose(model.radius(d.astype(np.float32)), model.radius_np(d), atol=1e-6)
    # anatomy: nose tip most forward, eyes symmetric and above the mouth, ears at the sides
    nose, reye, leye = lm[2], lm[0], lm[1]
    assert nose[2] < min(reye[2], lm[3][2]) - 0.02
    assert reye[0] > 0 > leye[0] and reye[1] > lm[3][1] + 0.05
    np.testing.assert_allclose(model.eye_centre, (lm[0] + lm[1]) / 2, atol=1e-7)
    assert lm[6][0] > 0.09 and lm[7][0] < -0.09
    face = model.sample_surface(500, seed=2, face_only=True)
    assert face.shape == (500, 3) and np.all(face[:, 2] < 0)


def test_eye_centre_follows_synthetic_head_motion(clean):
    """With rotation_scale=1 the model's eye centre moves exactly like the world trajectory of
    synthetic_head_motion, seen from a camera 0.8 m in front of the resting eyes."""
    seq = synthetic_rgbd_sequence(N_FRAMES, seed=0, rotation_scale=1.0)
    t, p_w, q_w = synthetic_head_motion(60.0, 30.0, 0)  # generated in 60 s blocks
    t, p_w, q_w = t[:N_FRAMES], p_w[:N_FRAMES], q_w[:N_FRAMES]
    eye_cam = seq.head_positions + rotate(seq.head_quaternions, np.asarray(
        seq.model.eye_centre, np.float64))
    q_cw = np.array([0.0, 0.0, 0.0, 1.0])
    expected = rotate(q_cw, p_w - np.array([0.0, 1.20, -0.8]))
    np.testing.assert_allclose(eye_cam, expected, atol=1e-6)
    rel = np_qmul(np_qconj(np_qmul(q_cw, q_w)), seq.head_quaternions)
    assert np.max(np.linalg.norm(np_rotvec(rel), axis=-1)) < 1e-9
    # the default halves the rotation angle about the rest pose
    ang_full = np.linalg.norm(np_rotvec(q_w), axis=-1)
    ang_half = np.linalg.norm(np_rotvec(np_qmul(np_qconj(q_cw), clean.head_quaternions)),
                              axis=-1)
    np.testing.assert_allclose(ang_half, ang_full / 2, atol=1e-9)


def test_landmarks_project_onto_the_painted_features(frames):
    for k in (0, 45):
        f = frames["clean", k]
        kk = f.intrinsics
        uv = np.stack([kk.fx * f.landmarks[:, 0] / f.landmarks[:, 2] + kk.cx,
                       kk.fy * f.landmarks[:, 1] / f.landmarks[:, 2] + kk.cy], -1)
        np.testing.assert_allclose(f.landmarks_2d, uv)
        face = [LANDMARK_NAMES.index(n) for n in ("right_eye", "left_eye", "nose_tip",
                                                  "mouth_right", "mouth_left")]
        assert np.all(f.landmarks_visible[face])
        px = np.round(f.landmarks_2d).astype(int)
        lum = f.color.astype(float) @ np.array([0.299, 0.587, 0.114])
        for e in (0, 1):  # pupils are dark, the skin between the eyes is bright
            assert lum[px[e, 1], px[e, 0]] < 60
        mid = np.round((f.landmarks_2d[0] + f.landmarks_2d[1]) / 2).astype(int)
        assert lum[mid[1], mid[0]] > 120
        for m in (3, 4):  # mouth corners: reddish lips
            r, g, b = f.color[px[m, 1], px[m, 0]].astype(int)
            assert r > g + 20 and r > b + 20
        # subject's right eye appears on the image left (the subject faces the camera)
        assert f.landmarks_2d[0, 0] < f.landmarks_2d[1, 0]
        # the depth at a visible landmark's pixel is the landmark's depth
        for n in face:
            z = f.depth[px[n, 1], px[n, 0]]
            assert abs(z - f.landmarks[n, 2]) < 3e-3, (k, LANDMARK_NAMES[n])


def test_render_rgbd_matches_the_sequence(clean, frames):
    f = frames["clean", 45]
    color, depth, mask = render_rgbd(f.head_position, f.head_quaternion, f.intrinsics,
                                     crop=clean.crop, wall=tuple(clean.wall))
    np.testing.assert_array_equal(depth, f.depth)
    np.testing.assert_array_equal(mask, f.head_mask)
    assert np.max(np.abs(color.astype(int) - f.color.astype(int))) <= 1
    with pytest.raises(ValueError, match="in front of the camera"):
        render_rgbd(np.array([0.0, 0.0, 0.1]), f.head_quaternion, f.intrinsics)


# -------------------------------------------------------------------------- noise model
def test_depth_noise_statistics():
    import jax

    key = jax.random.key(0)
    for z in (1.0, 2.0):
        depth = np.full((200, 300), z, np.float32)
        raw = np.asarray(add_depth_noise(key, depth, subpixel=0.0, dropout=0.0))
        assert np.all(raw > 0)
        assert np.std(raw) == pytest.approx(1.425e-3 * z**2, rel=0.05)
        assert abs(np.mean(raw) - z) < 1e-4 * z**2
        q = np.asarray(add_depth_noise(key, depth, dropout=0.0))
        disparity = 525.0 * 0.075 / q.astype(np.float64)
        np.testing.assert_allclose(disparity * 8, np.round(disparity * 8), atol=2e-3 * z)
        assert len(np.unique(q)) < 10  # quantised to a few levels
    depth = np.full((200, 300), 1.0, np.float32)
    depth[:, 150:] = 2.0  # a depth edge
    depth[:10, :10] = 0.0  # invalid stays invalid
    depth[10:20, :10] = 6.0  # beyond the range
    noisy = np.asarray(add_depth_noise(key, depth))
    assert np.all(noisy[:10, :10] == 0) and np.all(noisy[10:20, :10] == 0)
    edge = noisy[:, 149:151]
    assert 0.3 < np.mean(edge == 0) < 0.7
    interior = noisy[30:, 20:140]
    assert 0.0005 < np.mean(interior == 0) < 0.006


# ------------------------------------------------------------------------ end-to-end ICP
def head_points(frame, n, rng):
    """``n`` random head points (depth below 1.3 m) of a frame, in the camera frame."""
    pts = np.asarray(backproject(frame.depth, frame.intrinsics)).reshape(-1, 3)
    idx = np.flatnonzero(((frame.depth > 0) & (frame.depth < 1.3)).reshape(-1))
    return pts[rng.choice(idx, n, replace=False)]


def test_icp_between_frames_recovers_the_relative_head_pose(noisy, frames):
    import jax

    f0 = frames["noisy", 0]
    target = np.asarray(backproject(f0.depth, f0.intrinsics))
    normals = np.asarray(estimate_normals(target, radius=2))
    schedule = np.concatenate([np.geomspace(0.1, 0.01, 15), np.full(15, 0.01)])
    icp = jax.jit(lambda s, tp, tn, sched: icp_projective(
        s, tp, tn, f0.intrinsics, num_iterations=30, max_correspondence_distance=sched))

    def run(src):  # large arrays as arguments, not closed-over constants (slow to compile)
        return icp(src, target, normals, schedule)

    rng = np.random.default_rng(0)
    for k in (30, 45):
        fk = frames["noisy", k] if ("noisy", k) in frames else noisy[k]
        res = run(head_points(fk, 1000, rng))
        # ground truth: X0 = R0 Rk^T (Xk - pk) + p0
        q_rel = np_qmul(f0.head_quaternion, np_qconj(fk.head_quaternion))
        q_est = np.asarray(res.rotation, np.float64)
        ang = np.degrees(np.linalg.norm(np_rotvec(np_qmul(q_est, np_qconj(q_rel)))))
        moved = rotate(q_est, fk.head_position) + np.asarray(res.translation)
        err_mm = 1e3 * np.linalg.norm(moved - f0.head_position)  # at the head centre
        true_ang = np.degrees(np.linalg.norm(np_rotvec(q_rel)))
        assert int(res.status) == 0
        assert ang < 1.0 and err_mm < 5.0, (k, true_ang, ang, err_mm)
        assert int(res.num_inliers) > 900
    assert true_ang > 10  # the last pair really moved


# -------------------------------------------------------------------------------- YuNet
def test_yunet_detects_the_synthetic_face(frames):
    cv2 = pytest.importorskip("cv2")
    onnx = yunet_models() / YUNET_ONNX
    det = cv2.FaceDetectorYN.create(str(onnx), "", (640, 480), 0.5, 0.3, 10)
    for k in (0, 45):
        f = frames["noisy", k]
        _, faces = det.detect(np.ascontiguousarray(f.color[..., ::-1]))
        assert faces is not None and len(faces) == 1
        x, y, w, h = faces[0, :4]
        assert faces[0, -1] > 0.8
        eyes = faces[0, 4:8].reshape(2, 2)  # YuNet: subject's right eye first
        np.testing.assert_allclose(eyes, f.landmarks_2d[:2], atol=8.0)
        nose = f.landmarks_2d[2]
        assert x < nose[0] < x + w and y < nose[1] < y + h
