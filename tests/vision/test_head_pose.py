"""RGB-D head pose front-end: features, per-frame statuses, Biwi and slambook acceptance."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np
import pytest
from conftest import shared_path, yunet_models
from hypothesis import given, settings
from hypothesis import strategies as st

from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.io import biwi_pose_to_quaternion, read_biwi_pose
from phjax.vision import face_detection as F
from phjax.vision import features as Fe
from phjax.vision import head_pose as H
from phjax.vision import rgbd_io as R

BIWI = ("biwi_kinect_head_pose_samples",)
NAMES = ("00054", "00427", "unknown")


def _angle_deg(q0, q1):
    return float(np.degrees(np.linalg.norm(np_rotvec(np_qmul(np_qconj(q0), q1)))))


# -------------------------------------------------------------------------------- features
def _popcount_distance(a, b):
    x = np.bitwise_xor(a[:, None, :], b[None, :, :])
    return np.unpackbits(x, axis=-1).sum(-1).astype(float)


def _match_reference(d, qv, tv, ratio, mutual):
    d = np.where(qv[:, None] & tv[None, :], d, np.inf)
    out = []
    for i in range(d.shape[0]):
        if not qv[i] or not np.isfinite(d[i]).any():
            out.append(-1)
            continue
        j = int(np.argmin(d[i]))
        rest = np.delete(d[i], j)
        second = rest.min() if rest.size else np.inf
        ok = d[i, j] < ratio * second or not np.isfinite(second)
        if mutual:
            ok = ok and int(np.argmin(d[:, j])) == i
        out.append(j if ok else -1)
    return np.asarray(out)


@settings(max_examples=30)
@given(st.integers(1, 30), st.integers(1, 30), st.integers(0, 2**31 - 1),
       st.sampled_from([0.7, 0.9, 1.0]), st.booleans())
def test_match_descriptors_hamming_reference(na, nb, seed, ratio, mutual):
    # fixed padded shapes (one compilation); na / nb real rows, the rest masked out
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    k = min(na, nb) // 2
    b[:k] = a[:k] ^ (rng.uniform(size=(k, 32)) < 0.05).astype(np.uint8)
    qv = (rng.uniform(size=30) < 0.9) & (np.arange(30) < na)
    tv = (rng.uniform(size=30) < 0.9) & (np.arange(30) < nb)
    d = _popcount_distance(a, b)
    m = Fe.match_descriptors(a, b, qv, tv, ratio=ratio, mutual=mutual)
    ref = _match_reference(d, qv, tv, ratio, mutual)
    # distance ties make argmin ambiguous; compare where the best distance is unique
    dd = np.where(qv[:, None] & tv[None, :], d, np.inf)
    unique = np.array([np.sum(row == row.min()) == 1 for row in dd])
    got = np.where(np.asarray(m.valid), np.asarray(m.index), -1)
    np.testing.assert_array_equal(got[unique], ref[unique])
    best = np.min(dd, axis=1)
    np.testing.assert_array_equal(np.asarray(m.distance)[qv], best[qv])


def test_match_descriptors_l2():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(20, 128)).astype(np.float32)
    perm = rng.permutation(20)
    b = a[perm] + 0.01 * rng.normal(size=(20, 128)).astype(np.float32)
    m = Fe.match_descriptors(a, b, metric="l2")
    assert np.asarray(m.valid).all()
    np.testing.assert_array_equal(perm[np.asarray(m.index)], np.arange(20))


def test_match_descriptors_l2_non_finite_rows_are_invalid_only_themselves():
    # a NaN / inf in one descriptor invalidates that row only: the same matches as when the
    # row is masked out (and every other row still matches its noisy copy)
    rng = np.random.default_rng(4)
    a = rng.uniform(0, 255, (12, 128)).astype(np.float32)
    b = a + rng.normal(0, 1, a.shape).astype(np.float32)
    a[3, 7], a[8, 0], b[5, 100] = np.nan, np.inf, -np.inf
    qv, tv = np.ones(12, bool), np.ones(12, bool)
    qv[[3, 8]], tv[5] = False, False
    m = Fe.match_descriptors(a, b, metric="l2")
    ref = Fe.match_descriptors(a, b, qv, tv, metric="l2")
    np.testing.assert_array_equal(np.asarray(m.valid), np.asarray(ref.valid))
    np.testing.assert_array_equal(np.asarray(m.index), np.asarray(ref.index))
    expect = qv & (np.arange(12) != 5)  # query 5's partner is the invalid train row
    np.testing.assert_array_equal(np.asarray(m.valid), expect)
    np.testing.assert_array_equal(np.asarray(m.index)[expect], np.arange(12)[expect])
    assert not np.isnan(np.asarray(m.distance)).any()


def test_lift_keypoints_non_finite_pixels_give_zero_points_and_finite_gradients():
    import jax
    import jax.numpy as jnp

    k = R.CameraIntrinsics(500.0, 500.0, 32.0, 24.0, width=64, height=48)
    depth = jnp.ones((48, 64))
    uv = jnp.array([[10.0, 10.0], [np.nan, 5.0], [np.inf, 5.0], [5.0, -np.inf]])
    pts, ok = Fe.lift_keypoints(uv, depth, k, np.array([True, True, False, True]))
    np.testing.assert_array_equal(np.asarray(ok), [True, False, False, False])
    np.testing.assert_array_equal(np.asarray(pts)[1:], 0.0)
    np.testing.assert_allclose(np.asarray(pts)[0], [(10 - 32) / 500, (10 - 24) / 500, 1.0])
    g_uv, g_d = jax.grad(lambda u, d: jnp.sum(Fe.lift_keypoints(u, d, k)[0]),
                         argnums=(0, 1))(uv, depth)
    assert np.isfinite(np.asarray(g_uv)).all() and np.isfinite(np.asarray(g_d)).all()
    np.testing.assert_array_equal(np.asarray(g_uv)[1:], 0.0)
    np.testing.assert_allclose(np.asarray(g_uv)[0], [1 / 500, 1 / 500])


def test_lift_keypoints_reference_and_rejections():
    k = R.CameraIntrinsics(500.0, 510.0, 31.5, 23.5, width=64, height=48)
    depth = np.full((48, 64), 1.5, np.float32)
    depth[:, 40:] = 2.5  # a depth step at column 40
    depth[10, 10] = 0  # a hole
    depth[30:33, 5:8] = 9.0  # out of range
    uv = np.array([[20.2, 30.7], [39.0, 20.0], [40.0, 20.0], [10.0, 10.0], [6.0, 31.0],
                   [50.0, 40.0], [0.0, 0.0]], np.float32)
    pts, ok = Fe.lift_keypoints(uv, depth, k, np.array([1, 1, 1, 1, 1, 1, 0], bool),
                                max_depth=8.0)
    ok = np.asarray(ok)
    np.testing.assert_array_equal(ok, [True, False, False, False, False, True, False])
    z = 1.5
    np.testing.assert_allclose(np.asarray(pts)[0], [(20.2 - 31.5) * z / 500, (30.7 - 23.5) * z
                                                    / 510, z], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pts)[5, 2], 2.5)
    assert np.all(np.asarray(pts)[~ok] == 0)
    # NaN depth counts as missing
    depth[40, 50] = np.nan
    _, ok2 = Fe.lift_keypoints(uv[5:6], depth, k)
    assert not bool(np.asarray(ok2)[0])


def test_detect_keypoints_padding_and_box():
    img = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    kp = Fe.detect_keypoints(img, (40, 30, 50, 40), max_keypoints=64)
    assert kp.uv.shape == (64, 2) and kp.descriptors.shape == (64, 32)
    assert 0 < kp.count <= 64 and kp.valid[: kp.count].all() and not kp.valid[kp.count:].any()
    u, v = kp.uv[kp.valid].T
    assert (u >= 39).all() and (u <= 91).all() and (v >= 29).all() and (v <= 71).all()
    empty = Fe.detect_keypoints(img, (500, 500, 10, 10), max_keypoints=8)
    assert empty.count == 0
    sift = Fe.detect_keypoints(img, None, method="sift", max_keypoints=32)
    assert sift.descriptors.dtype == np.float32 and sift.descriptors.shape == (32, 128)


# ------------------------------------------------------------------------------ Biwi setup
@pytest.fixture(scope="module")
def biwi():
    root = shared_path(*BIWI)
    cal = R.read_biwi_calibration(root / "rgb.cal")
    frames, gt = {}, {}
    for n in NAMES:
        frames[n] = R.read_biwi_frame(root, n)
        r, t = R.biwi_pose_in_color_frame(*read_biwi_pose(root / f"frame_{n}_pose.txt"), cal)
        gt[n] = (biwi_pose_to_quaternion(r), t)
    return frames, gt


@pytest.fixture(scope="module")
def detectors(tmp_path_factory):
    cache = tmp_path_factory.mktemp("models")
    mp = pytest.MonkeyPatch()
    mp.setenv("TORCH_HOME", str(tmp_path_factory.mktemp("torch")))
    F.seed_model_cache(yunet_models(), cache)
    dets = {b: F.FaceDetector(b, model_dir=cache) for b in F.BACKENDS}
    yield dets
    mp.undo()


def test_biwi_pose_convention(biwi):
    """Biwi: p_cam = R x_head + t, so frame a -> b moves camera points by R_b R_a^T."""
    frames, gt = biwi
    from scipy.spatial import cKDTree

    def cloud(f):
        v, u = np.nonzero(f.depth > 0)
        z = f.depth[v, u].astype(float)
        k = f.intrinsics
        return np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], 1)

    a, b = "00054", "unknown"
    pa, pb = cloud(frames[a]), cloud(frames[b])
    ra, ta = H._np_qmatrix(gt[a][0]), gt[a][1]
    rb, tb = H._np_qmatrix(gt[b][0]), gt[b][1]
    face = pa[np.linalg.norm(pa - ta, axis=1) < 0.1]
    tree = cKDTree(pb)
    d_conv = tree.query((face - ta) @ ra @ rb.T + tb)[0]
    d_transposed = tree.query((face - ta) @ ra.T @ rb + tb)[0]
    assert np.median(d_conv) < 0.003
    assert np.median(d_transposed) > 0.01


#: Biwi acceptance, measured per backend over the six ordered pairs of different frames:
#: largest rotation error (deg) and position error (m); the bounds are 1.5x these (kornia's
#: 4.08 deg is the 62.5 deg turn 00054 -> 00427; its other pairs are within 1.61 deg).
#: A bias of 1.5 deg / 8 mm in every estimated pose fails them.
BIWI_MEASURED = {"opencv": (2.16, 0.00205), "kornia": (4.08, 0.00236)}


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_biwi_relative_pose_acceptance(biwi, detectors, backend):
    """Every ordered pair: reference = frame a with its ground-truth pose, estimate frame b
    (the GT head centre of a carried by the estimated motion must land on b's centre); the
    same frame again gives the reference pose back (measured: exactly)."""
    frames, gt = biwi
    cfg = H.HeadPoseConfig(backend=backend)
    rot, pos = [], []
    for a in NAMES:
        for b in NAMES:
            est = H.HeadPoseEstimator(frames[a].intrinsics, cfg, detector=detectors[backend],
                                      reference_pose=gt[a])
            r0 = est.process_frame(frames[a])
            assert r0.ok and r0.is_keyframe and r0.face_source == "detector"
            r = est.process_frame(frames[b])
            assert r.status == H.HeadPoseStatus.OK, (a, b, r)
            assert r.face is not None and r.face.landmarks.shape == (5, 2)
            err = (_angle_deg(gt[b][0], r.quaternion), float(np.linalg.norm(r.position - gt[b][1])))
            if a == b:  # identity: bounds far below any real error (measured 0)
                assert err[0] < 1e-3 and err[1] < 1e-6, (a, err)
            else:
                rot.append(err[0])
                pos.append(err[1])
    print(f"{backend}: rotation error max {max(rot):.3f} deg, position error max "
          f"{1000 * max(pos):.2f} mm")
    rot_max, pos_max = BIWI_MEASURED[backend]
    assert max(rot) < 1.5 * rot_max, rot
    assert max(pos) < 1.5 * pos_max, pos


def test_synthetic_sequence_end_to_end_accuracy(detectors):
    """Acceptance: the package's rendered RGB-D head (exact ground truth, 60 frames at 30 Hz)
    through the front-end (OpenCV backend) and the causal 120 Hz stream against the ground
    truth. The target is 2 deg / 1 cm; measured per frame 0.218 deg / 0.25 mm RMSE and rendered
    as below; the regression bounds are 1.5x those. The rendering and the front-end run 60
    frames, compiled at XLA's default level (as the ``optimised`` marker would); the three
    ``track`` calls run once each and keep the suite's ``-O0``."""
    import phjax as pj
    from phjax._jit import extra_compiler_options
    from phjax.evaluation.metrics import position_rmse
    from phjax.evaluation.metrics import rotation_rmse_deg as rotation_rmse
    from phjax.motion.resample import interpolate_poses

    with extra_compiler_options(xla_backend_optimization_level=3):
        seq = R.open_rgbd("synthetic:60:3")
        gt = seq.ground_truth
        est = H.HeadPoseEstimator(seq.intrinsics, detector=detectors["opencv"],
                                  reference_pose=(gt.quaternions[0], gt.positions[0]))
        res = [est.process_frame(seq[i]) for i in range(len(seq))]
    assert all(r.ok for r in res)
    times = np.array([r.timestamp for r in res])
    pos = np.array([r.position for r in res])
    quat = np.array([r.quaternion for r in res])
    per_frame = (position_rmse(pos, gt.positions[:60]).value,
                 rotation_rmse(quat, gt.quaternions[:60]).value)
    print("per frame: position RMSE {:.5f} m, rotation RMSE {:.3f} deg".format(*per_frame))
    assert per_frame[0] < 1.5 * 0.00025 and per_frame[1] < 1.5 * 0.218, per_frame
    render = np.arange(times[0], times[-1], 1 / 120)
    gp, gq = (np.asarray(x) for x in interpolate_poses(gt.times[:60], gt.positions[:60],
                                                       gt.quaternions[:60], render))
    # The front-end's noise (0.25 mm / 0.2 deg per frame) is far below the default sensor's
    # (5 mm / 1 deg) that the filters assume. With the noise estimated from the front-end's
    # own poses (phjax.tracking.estimate_measurement_noise) the IMM follows the motion instead
    # of smoothing it away. Measured: single-model filter 0.41 mm / 0.281 deg; default IMM
    # 1.77 mm / 0.537 deg; IMM with the estimated noise (0.10 mm / 0.105 deg)
    # 0.32 mm / 0.263 deg, the best of the three; bounds 1.5x.
    noise = pj.estimate_measurement_noise(times, pos, quat)
    print("estimated front-end noise: {:.3f} mm, {:.3f} deg".format(
        1e3 * float(noise.pos_meas_noise), float(np.degrees(noise.rot_meas_noise))))
    tuned = pj.with_measurement_noise(pj.TrackerConfig(), noise)
    for config, bound in [(pj.TrackerConfig(imm=None), (0.00041, 0.281)),
                          (pj.TrackerConfig(), (0.00177, 0.537)),
                          (tuned, (0.00032, 0.263))]:
        P, Q = (np.asarray(x) for x in pj.track(times, pos, quat, render, config=config,
                                                 dtype=np.float64))
        stream = (position_rmse(P, gp).value, rotation_rmse(Q, gq).value)
        print("120 Hz stream: position RMSE {:.5f} m, rotation RMSE {:.3f} deg".format(*stream))
        assert stream[0] < 1.5 * bound[0] and stream[1] < 1.5 * bound[1], (config.imm, stream)


def test_status_on_bad_frames_and_recovery(biwi, detectors):
    frames, _ = biwi
    f = frames["00054"]
    est = H.HeadPoseEstimator(f.intrinsics, detector=detectors["opencv"])
    black = np.zeros_like(f.color)
    cases = [
        ((black, np.zeros_like(f.depth)), H.HeadPoseStatus.NO_DEPTH),  # empty frame
        ((f.color, np.zeros_like(f.depth)), H.HeadPoseStatus.NO_DEPTH),  # zero depth
        ((f.color, np.full_like(f.depth, np.nan)), H.HeadPoseStatus.NO_DEPTH),
        ((f.color[:, :100], f.depth), H.HeadPoseStatus.INVALID_INPUT),  # shape mismatch
        ((f.color.astype(np.float32), f.depth), H.HeadPoseStatus.INVALID_INPUT),
        ((None, f.depth), H.HeadPoseStatus.INVALID_INPUT),
    ]
    cases.append(((f.color, f.depth), H.HeadPoseStatus.INVALID_INPUT))  # at a NaN time:
    for k, ((color, depth), status) in enumerate(cases):  # (it was OK, stamped NaN)
        r = est.process(color, depth, float("nan") if k == len(cases) - 1 else 0.0)
        assert r.status == status and not r.ok
        assert np.isnan(r.position).all() and np.isnan(r.quaternion).all()
    assert est.num_keyframes == 0
    # no face in the image and no depth fallback: NO_FACE
    est2 = H.HeadPoseEstimator(f.intrinsics, H.HeadPoseConfig(depth_fallback=False),
                               detector=detectors["opencv"])
    r = est2.process(black, f.depth, 0.0)
    assert r.status == H.HeadPoseStatus.NO_FACE and np.isnan(r.position).all()
    # too little valid depth (a few pixels): NO_DEPTH
    speck = np.zeros_like(f.depth)
    speck[200:205, 300:305] = 0.9
    assert est2.process(f.color, speck, 0.0).status == H.HeadPoseStatus.NO_DEPTH
    # the stream goes on: a good frame becomes the reference, then a bad frame, then good
    assert est.process_frame(f).ok
    assert est.process(black, np.zeros_like(f.depth), 1.0).status == H.HeadPoseStatus.NO_DEPTH
    r = est.process_frame(frames["unknown"])
    assert r.ok and r.keyframe == 0


def test_per_frame_intrinsics_are_checked_like_the_constructors(biwi, detectors):
    # invalid per-frame intrinsics give INVALID_INPUT (as a wrong size always did), not a
    # misleading alignment status or an exception; (fx, fy, cx, cy) works as the full record
    frames, _ = biwi
    f = frames["00054"]
    k = f.intrinsics
    est = H.HeadPoseEstimator(k, detector=detectors["opencv"])
    for bad in (R.CameraIntrinsics(0.0, k.fy, k.cx, k.cy, k.width, k.height),
                R.CameraIntrinsics(np.nan, k.fy, k.cx, k.cy, k.width, k.height),
                R.CameraIntrinsics(k.fx, k.fy, k.cx, np.inf, k.width, k.height),
                R.CameraIntrinsics(k.fx, k.fy, k.cx, k.cy, k.width // 2, k.height // 2),
                (k.fx, k.fy, k.cx), "abcd"):
        r = est.process(f.color, f.depth, 0.0, bad)
        assert r.status == H.HeadPoseStatus.INVALID_INPUT and np.isnan(r.position).all()
    assert est.num_keyframes == 0
    ref = est.process(f.color, f.depth, 0.0, k)
    est.reset()
    r = est.process(f.color, f.depth, 0.0, (k.fx, k.fy, k.cx, k.cy))
    assert ref.ok and r.ok
    np.testing.assert_array_equal(r.position, ref.position)
    np.testing.assert_array_equal(r.quaternion, ref.quaternion)


def test_relative_pose_rejects_frames_of_mismatched_sizes():
    k = R.CameraIntrinsics(500.0, 500.0, 31.5, 23.5, width=64, height=48)
    good = R.RGBDFrame(np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32), k)
    for bad in (good._replace(depth=good.depth[:24]), good._replace(color=good.color[:, :32]),
                good._replace(intrinsics=k.scaled(0.5))):
        with pytest.raises(ValueError, match="frame_a: depth .* sizes"):
            H.rgbd_relative_pose(bad, good, refine=None)
        with pytest.raises(ValueError, match="frame_b: depth .* sizes"):
            H.rgbd_relative_pose(good, bad, refine=None)


def test_black_colour_with_depth_uses_tracking_or_depth(biwi, detectors):
    frames, gt = biwi
    f = frames["00054"]
    est = H.HeadPoseEstimator(f.intrinsics, detector=detectors["opencv"], reference_pose=gt[
        "00054"])
    r0 = est.process(np.zeros_like(f.color), f.depth, 0.0)  # no detector face: depth blob
    assert r0.ok and r0.face_source == "depth" and r0.face is None
    r1 = est.process(np.zeros_like(f.color), f.depth, 0.1)  # tracked box, ICP only
    assert r1.face_source == "tracked"
    # the same frame again: identity (measured 4e-7 deg / 1e-8 m; was allowed 1 deg / 5 mm)
    print("same frame twice, ICP only: {:.2e} deg, {:.2e} m".format(
        _angle_deg(r1.quaternion, gt["00054"][0]), np.linalg.norm(r1.position - gt["00054"][1])))
    assert r1.ok and _angle_deg(r1.quaternion, gt["00054"][0]) < 1e-3
    np.testing.assert_allclose(r1.position, gt["00054"][1], atol=1e-6)


def test_reference_started_without_a_face_gives_way_to_a_detected_face(biwi, detectors):
    """A first frame without a face (the slambook room: the depth fallback takes a piece of
    furniture as the head) made keyframe 0, and no real face was ever tracked after it
    (ALIGNMENT_FAILED on every face frame, found by probing): a reference started without a
    detected face is provisional, and the first detected face that does not fit it starts a new
    reference there, after which the face is tracked."""
    frames, gt = biwi
    room = R.open_rgbd(shared_path("rgbd_frames_slambook2_ch5"))[0]
    est = H.HeadPoseEstimator(room.intrinsics, detector=detectors["opencv"])
    r0 = est.process_frame(room)
    assert r0.ok and r0.face is None and r0.face_source == "depth"  # provisional
    r1 = est.process_frame(frames["00054"])
    assert r1.ok and r1.is_keyframe and r1.keyframe == 0 and r1.face_source == "detector"
    assert est.num_keyframes == 1
    rs = [est.process_frame(frames[n]) for n in ("00427", "00054", "unknown")]
    assert all(r.ok for r in rs), [r.status for r in rs]
    # back at the reference frame after a 30 degree turn: the reference pose again, within the
    # keyframe-revisit bound of test_no_recompilation_and_keyframes (measured 2.5 deg, 1.7 mm)
    assert _angle_deg(rs[1].quaternion, r1.quaternion) < 3
    np.testing.assert_allclose(rs[1].position, r1.position, atol=5e-3)


def test_a_frame_without_correspondences_is_too_few_matches(biwi, detectors):
    """A featureless grey image over a flat wall at the head's distance, after a face reference:
    no keypoint matches and no landmarks (no RANSAC or landmark candidate), and the refinement
    from the predicted pose fails its checks, so the frame is ``TOO_FEW_MATCHES`` (before, every
    failed frame with a prediction was ``ALIGNMENT_FAILED``: the status was never reported), a
    NaN pose; the next face frame is tracked again. A frame whose correspondences do give a
    candidate but fail the checks stays ``ALIGNMENT_FAILED``
    (test_confirmed_reference_is_replaced_after_reacquire_after_failures)."""
    frames, gt = biwi
    f = frames["00054"]
    est = H.HeadPoseEstimator(f.intrinsics, detector=detectors["opencv"])
    assert est.process_frame(f).ok
    wall = np.where(f.depth > 0, np.median(f.depth[f.depth > 0]), 0).astype(np.float32)
    r = est.process_frame(f._replace(color=np.full_like(f.color, 128), depth=wall))
    assert r.status == H.HeadPoseStatus.TOO_FEW_MATCHES and not r.ok
    assert r.num_matches == 0 and np.isnan(r.position).all() and np.isnan(r.quaternion).all()
    assert est.process_frame(frames["00427"]).ok


def test_confirmed_reference_is_replaced_after_reacquire_after_failures(biwi, detectors,
                                                                        monkeypatch):
    """A reference confirmed by a detected face survives failed alignments until
    ``reacquire_after`` of them in a row; then the next failed frame with a detected face starts
    a new reference that keeps the last orientation. A success in between restarts the count;
    ``reacquire_after=0`` never replaces it."""
    frames, gt = biwi
    f = frames["00054"]
    for n, expect_new in [(3, True), (0, False)]:
        est = H.HeadPoseEstimator(f.intrinsics, H.HeadPoseConfig(reacquire_after=n),
                                  detector=detectors["opencv"], reference_pose=gt["00054"])
        assert est.process_frame(f).ok
        good = est.process_frame(frames["00427"])
        assert good.ok
        real = est._align_to_keyframe
        fail = [True]

        def forced(fr, idx, real=real, fail=fail):
            kf_i, e = real(fr, idx)
            return kf_i, (eqx.tree_at(lambda x: x.accepted, e, np.bool_(False)) if fail[0]
                          else e)

        monkeypatch.setattr(est, "_align_to_keyframe", forced)
        statuses = [est.process_frame(frames["00427"]).status for _ in range(2)]
        assert statuses == [H.HeadPoseStatus.ALIGNMENT_FAILED] * 2
        fail[0] = False
        assert est.process_frame(frames["00427"]).ok  # restarts the count
        fail[0] = True
        rs = [est.process_frame(frames["00427"]) for _ in range(3)]
        if expect_new:
            assert [r.ok for r in rs] == [False, False, True]
            assert rs[2].is_keyframe and rs[2].keyframe == 0 and est.num_keyframes == 1
            # the new reference keeps the last orientation (the last good pose's)
            assert _angle_deg(rs[2].quaternion, good.quaternion) < 0.5
        else:
            assert not any(r.ok for r in rs) and est.num_keyframes >= 1


def test_non_finite_detector_box_is_no_detection(biwi):
    """A detector passed in that gives a NaN or infinite box (or NaN landmarks) raised
    ``ValueError: cannot convert float NaN to integer`` out of ``process``; such a box is no
    detection (the depth fallback takes over) and NaN landmarks are unused."""
    frames, _ = biwi
    f = frames["00054"]

    class Fixed:
        def __init__(self, box, lm):
            self.face = F.FaceDetection(np.asarray(box, np.float32), np.asarray(lm, np.float32), 0.9)

        def detect(self, image):
            return [self.face]

    good_box = [250, 150, 150, 180]
    for box, lm, source in [([np.nan] * 4, np.zeros((5, 2)), "depth"),
                            ([0, 0, np.inf, np.inf], np.zeros((5, 2)), "depth"),
                            (good_box, np.full((5, 2), np.nan), "detector")]:
        est = H.HeadPoseEstimator(f.intrinsics, detector=Fixed(box, lm))
        rs = [est.process_frame(frames[n]) for n in NAMES]
        assert rs[0].ok and rs[0].face_source == source, (box, rs[0])
        assert all(np.isfinite(r.position).all() or not r.ok for r in rs)


def test_head_box_from_depth(biwi):
    frames, gt = biwi
    for n in NAMES:
        f = frames[n]
        x, y, w, h = H.head_box_from_depth(f.depth, f.intrinsics)
        t = gt[n][1]
        u = f.intrinsics.fx * t[0] / t[2] + f.intrinsics.cx
        v = f.intrinsics.fy * t[1] / t[2] + f.intrinsics.cy
        assert x < u < x + w and y < v < y + h
    assert H.head_box_from_depth(np.zeros((48, 64), np.float32), frames[NAMES[0]].intrinsics
                                 ) is None


def test_no_recompilation_and_keyframes(biwi, detectors):
    frames, _ = biwi
    est = H.HeadPoseEstimator(frames["00054"].intrinsics, H.HeadPoseConfig(keyframe_angle=15),
                              detector=detectors["opencv"])
    seq = ["unknown", "00054", "00427", "unknown", "00427", "00054", "unknown"]
    res = [est.process_frame(frames[n]) for n in seq[:2]]
    sizes = (H._estimate._cache_size(), H._observe._cache_size())
    res += [est.process_frame(frames[n]) for n in seq[2:]]
    assert all(r.ok for r in res), [r.status for r in res]
    assert est.num_keyframes >= 2  # the 30-35 degree turns add keyframes
    # static shapes: new keyframes and frames never trigger a recompilation
    assert (H._estimate._cache_size(), H._observe._cache_size()) == sizes
    # revisiting a view is consistent with its first estimate (keyframes avoid drift)
    assert _angle_deg(res[0].quaternion, res[3].quaternion) < 3
    assert _angle_deg(res[1].quaternion, res[5].quaternion) < 3
    assert np.isfinite(res[-1].timings["total"])


def test_config_validation():
    with pytest.raises(ValueError, match="icp"):
        H.HeadPoseConfig(icp="gicp")
    with pytest.raises(ValueError, match="feature_method"):
        H.HeadPoseConfig(feature_method="akaze")
    with pytest.raises(ValueError, match="backend"):
        H.HeadPoseConfig(backend="dlib")


# -------------------------------------------------------------------------- slambook pairs
@pytest.mark.optimised
def test_slambook_relative_camera_poses():
    """Default rgbd_relative_pose (RANSAC + joint dense / reprojection refinement): all four
    consecutive pairs within 3 deg and 5 cm of the given poses, the same pose for the RANSAC
    seeds 0, 1, 4, 6 (before refinement seeds 0/1/4/5/6 are 8.6-18 cm off on 1 -> 2, seed 6
    20 cm on 3 -> 4; all of 0-7 agreed when measured, these four are the ones RANSAC alone gets
    most wrong). RANSAC alone (refine=None, seed 0) on 2-3, 3-4, 4-5 as well."""
    seq = R.open_rgbd(shared_path("rgbd_frames_slambook2_ch5"))
    for i in range(4):
        rels = [H.rgbd_relative_pose(seq[i], seq[i + 1], seed=s) for s in (0, 1, 4, 6)]
        for rel in rels:
            assert rel.status == 0 and rel.refined and rel.icp_status in (0, 3), (i, rel)
            rot, trans = _slambook_pair_errors(seq, i, rel)
            assert rot < 3.0, (i, rot)
            assert trans < 0.05, (i, trans)
        for rel in rels[1:]:
            assert _angle_deg(rel.quaternion, rels[0].quaternion) < 0.05
            assert np.linalg.norm(rel.translation - rels[0].translation) < 0.002
        if i >= 1:
            rel = H.rgbd_relative_pose(seq[i], seq[i + 1], refine=None)
            assert rel.status == 0 and rel.num_inliers >= 15 and not rel.refined
            rot, trans = _slambook_pair_errors(seq, i, rel)
            assert rot < 3.0 and trans < 0.05, (i, rot, trans)


def _slambook_pair_errors(seq, i, rel):
    gt = seq.ground_truth
    ri, rj = H._np_qmatrix(gt.quaternions[i]), H._np_qmatrix(gt.quaternions[i + 1])
    r_true, t_true = rj.T @ ri, rj.T @ (gt.positions[i] - gt.positions[i + 1])
    return (_angle_deg(biwi_pose_to_quaternion(r_true), rel.quaternion),
            float(np.linalg.norm(rel.translation - t_true)))


@pytest.mark.optimised
def test_slambook_dense_refinement():
    """refine="icp": seed-independent on all four pairs; 1-2, 2-3, 4-5 within 3 deg / 5 cm;
    refine="joint" (seed 0): the same, 3-4 closer to the given pose than "icp".

    On 3 -> 4 the depth-consistent motion lies about 7.5 cm from the given (approximate) pose;
    cv2.Odometry's depth ICP lands there too (7.2 cm), so that pair is held to a looser bound.
    Seeds 0, 2, 6 give three different RANSAC answers before refinement (1-2: 8.6 / 4.9 cm,
    3-4: 3.0 / 20 cm).
    """
    seq = R.open_rgbd(shared_path("rgbd_frames_slambook2_ch5"))
    for i in range(4):
        rels = [H.rgbd_relative_pose(seq[i], seq[i + 1], seed=s, refine="icp") for s in (0, 2, 6)]
        for rel in rels:
            assert rel.status == 0 and rel.refined and rel.icp_status in (0, 3), (i, rel)
            assert rel.icp_inliers > 2000 and rel.icp_rmse < 0.006, (i, rel)
            rot, trans = _slambook_pair_errors(seq, i, rel)
            assert rot < 3.0, (i, rot)
            assert trans < (0.10 if i == 2 else 0.05), (i, trans)
        for rel in rels[1:]:  # the same answer whatever the RANSAC seed
            assert _angle_deg(rel.quaternion, rels[0].quaternion) < 0.2
            assert np.linalg.norm(rel.translation - rels[0].translation) < 0.005
        # joint dense + feature refinement (noise-model weights): the RANSAC inliers pull 3 -> 4
        # towards the given pose (4.1-5.7 cm for seeds 0-7 instead of 7.3-7.5), not always
        # within 5 cm
        joint = H.rgbd_relative_pose(seq[i], seq[i + 1], seed=0, refine="joint")
        assert joint.status == 0 and joint.refined and joint.icp_status in (0, 3), (i, joint)
        rot, trans = _slambook_pair_errors(seq, i, joint)
        assert rot < 3.0, (i, rot)
        assert trans < (0.07 if i == 2 else 0.05), (i, trans)
        if i == 2:
            assert trans < _slambook_pair_errors(seq, i, rels[0])[1] - 0.005
    with pytest.raises(ValueError, match="refine"):
        H.rgbd_relative_pose(seq[0], seq[1], refine="gicp")
    with pytest.raises(ValueError, match="level"):
        H.DenseRefinement(iterations=(10,))
    with pytest.raises(ValueError, match="feature_weight"):
        H.DenseRefinement(feature_weight=-1.0)
    with pytest.raises(ValueError, match="feature_residual"):
        H.DenseRefinement(feature_residual="plane")
    with pytest.raises(ValueError, match="feature_matches"):
        H.DenseRefinement(feature_matches="some")


def test_slambook_reprojection_refinement_depth_window():
    """The depth-window correction of the default refinement is what brings 3 -> 4 within
    5 cm: with independent dense residuals (depth_window=None) the same refinement is still
    seed-independent but lands 5.4 cm from the given pose (the dense depth alone 7.5 cm); the
    correction moves it towards the feature evidence (3-D pairs of refine="joint" too)."""
    seq = R.open_rgbd(shared_path("rgbd_frames_slambook2_ch5"))
    default = H._REFINE_PRESETS["reproj"]
    assert default.depth_window == (9, 7)
    assert [default.feature_factor(ss) for _, ss in default.levels] == [1.0, 63 / 16, 63 / 4]
    assert H.DenseRefinement(depth_window=None).feature_factor(1) == 1.0
    independent = dataclasses.replace(default, depth_window=None)
    rels = [H.rgbd_relative_pose(seq[2], seq[3], seed=s, refine=independent) for s in (0, 6)]
    for rel in rels:
        assert rel.refined and rel.icp_status in (0, 3)
    assert np.linalg.norm(rels[1].translation - rels[0].translation) < 0.002
    rot, trans = _slambook_pair_errors(seq, 2, rels[0])
    assert rot < 3.0 and 0.05 < trans < 0.06, trans
    corrected = _slambook_pair_errors(seq, 2, H.rgbd_relative_pose(seq[2], seq[3]))[1]
    assert corrected < trans - 0.005
    with pytest.raises(ValueError, match="depth_window"):
        H.DenseRefinement(depth_window=(9, 0))


# ----------------------------------------------------------------------------------- CLI
def test_reference_pose_must_be_a_finite_pose():
    """A NaN, zero or wrongly shaped reference made every pose NaN, reported as OK (found by
    review); now a one-line ValueError when the estimator is made or reset."""
    for ref, match in [((np.full(4, np.nan), np.zeros(3)), "finite with a non-zero"),
                       ((np.zeros(4), np.zeros(3)), "finite with a non-zero"),
                       ((np.array([1.0, 0, 0, 0]), np.full(3, np.inf)), "finite"),
                       ((np.zeros(3), np.zeros(3)), r"shapes \(3,\) and \(3,\)"),
                       (np.zeros(7), "must be")]:
        with pytest.raises(ValueError, match=match):
            H.HeadPoseEstimator(detector=False, reference_pose=ref)
    est = H.HeadPoseEstimator(detector=False, reference_pose=([2.0, 0, 0, 0], [0, 0, 0.5]))
    with pytest.raises(ValueError, match="finite"):
        est.reset((np.full(4, np.nan), np.zeros(3)))


def test_cli_track_rgbd_keeps_going_past_bad_frames_and_guards_the_recording(tmp_path,
                                                                            capsys):
    """Found by review of ``phjax track-rgbd``:

    * ``-o`` / ``--raw`` naming a file of the source folder replaced the recording's own files
      (a Biwi pose file, a TUM ``rgb.txt``): refused before any work;
    * a TUM ``rgb.txt`` listing frames out of time order gave an empty stream (exit 0): the
      reader now orders the frames by time;
    * one missing image ended the run and discarded every pose: now that frame is lost, with
      one warning line;
    * colour images without a face still gave "OK" poses from the depth fallback (23-87 deg
      off): an error when the detector never found a face.
    """
    import argparse
    import shutil
    from pathlib import Path

    from phjax.cli import _rgbd
    from phjax.io import read_trajectory

    cache = tmp_path / "models"
    F.seed_model_cache(yunet_models(), cache)
    parser = argparse.ArgumentParser(prog="phjax")
    _rgbd.add_commands(parser.add_subparsers(dest="command", required=True))
    biwi = tmp_path / "biwi"
    shutil.copytree(shared_path(*BIWI), biwi)
    pose_file = biwi / "frame_00054_pose.txt"
    before = pose_file.read_bytes()
    for argv in (["-o", str(pose_file)], ["-o", str(tmp_path / "o.tum"), "--raw", str(pose_file)]):
        args = parser.parse_args(["track-rgbd", str(biwi), *argv, "--no-progress"])
        with pytest.raises(ValueError, match="a file of the recording"):
            args.func(args)
    assert pose_file.read_bytes() == before
    # the Biwi frames as a TUM folder, rgb.txt rotated (out of order), one image missing
    seq = R.read_biwi(biwi)
    tum = tmp_path / "tum"
    R.write_tum_rgbd(tum, list(seq))
    body = [ln for ln in (tum / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    (tum / "rgb.txt").write_text("\n".join(body[1:] + body[:1]) + "\n")  # out of order
    (tum / body[1].split()[1]).unlink()  # the second frame in time
    assert R.open_rgbd(tum)[0].name == Path(body[0].split()[1]).stem  # the earliest first
    i = seq.intrinsics
    out, raw = tmp_path / "head.tum", tmp_path / "raw.tum"
    args = parser.parse_args(["track-rgbd", str(tum), "-o", str(out), "--raw", str(raw),
                              "--intrinsics", f"{i.fx},{i.fy},{i.cx},{i.cy}", "--model-dir",
                              str(cache), "--no-progress", "--rate", "60"])
    assert args.func(args) == 0
    printed = capsys.readouterr()
    assert "status:" in printed.out and "INVALID_INPUT 1" in printed.out, printed.out
    assert [ln for ln in printed.err.splitlines() if "warning: frame 1:" in ln], printed.err
    per_frame = read_trajectory(raw)
    assert np.all(np.diff(per_frame.times) > 0) and per_frame.num_samples == 2
    assert read_trajectory(out).num_samples > 5
    # no face in any colour image: the depth fallback's "head" is not reported
    for png in biwi.glob("*_rgb.png"):
        R._write_png(png, np.full((480, 640, 3), 128, np.uint8))
    args = parser.parse_args(["track-rgbd", str(biwi), "-o", str(out), "--model-dir",
                              str(cache), "--no-progress"])
    with pytest.raises(ValueError, match="found no face in any of the 3 frames"):
        args.func(args)


def test_cli_track_rgbd(tmp_path, monkeypatch, capsys):
    import argparse

    from phjax.cli import _rgbd
    from phjax.io import read_trajectory

    cache = tmp_path / "models"
    F.seed_model_cache(yunet_models(), cache)
    parser = argparse.ArgumentParser(prog="phjax")
    _rgbd.add_commands(parser.add_subparsers(dest="command", required=True))
    out, raw = tmp_path / "head.tum", tmp_path / "raw.tum"
    args = parser.parse_args(["track-rgbd", str(shared_path(*BIWI)), "-o", str(out), "--raw",
                              str(raw), "--rate", "60", "--model-dir", str(cache),
                              "--no-progress", "--gt-reference"])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "status: OK 3" in text and "rotation relative to the first good frame" in text
    traj = read_trajectory(out)
    dt = np.diff(traj.times)
    np.testing.assert_allclose(dt, 1 / 60, rtol=1e-6)
    assert np.isfinite(traj.positions).all() and traj.num_samples > 700
    per_frame = read_trajectory(raw)
    assert per_frame.num_samples == 3
    # the raw poses start at the ground-truth reference
    gt = R.read_biwi(shared_path(*BIWI)).ground_truth
    np.testing.assert_allclose(per_frame.positions[0], gt.positions[0], atol=1e-9)
    bad = parser.parse_args(["track-rgbd", str(tmp_path), "-o", str(out), "--no-progress"])
    with pytest.raises(R.RGBDFormatError):
        bad.func(bad)


def test_cli_track_rgbd_depth_scale_and_intrinsics(tmp_path, capsys):
    """A TUM-layout folder of millimetre depth with its own camera (the Biwi frames rewritten):
    the default scale (5000 / m) finds no usable depth and says which option sets it;
    ``--depth-scale 1000 --intrinsics ...`` gives the poses of the Biwi folder itself (within
    the millimetre rounding of the rewritten depth); both options are refused for a Biwi
    folder, which carries its own calibration."""
    import argparse

    from phjax.cli import _rgbd
    from phjax.io import read_trajectory

    cache = tmp_path / "models"
    F.seed_model_cache(yunet_models(), cache)
    parser = argparse.ArgumentParser(prog="phjax")
    _rgbd.add_commands(parser.add_subparsers(dest="command", required=True))
    biwi = R.read_biwi(shared_path(*BIWI))
    folder = tmp_path / "my_camera"
    R.write_tum_rgbd(folder, list(biwi), depth_scale=1000.0)
    k = biwi.intrinsics
    own = f"{float(k.fx)},{float(k.fy)},{float(k.cx)},{float(k.cy)}"

    def run(source, *extra):
        raw = tmp_path / "raw.tum"
        args = parser.parse_args(["track-rgbd", str(source), "-o", str(tmp_path / "o.tum"),
                                  "--raw", str(raw), "--model-dir", str(cache), "--no-progress",
                                  *extra])
        return args.func(args), raw

    with pytest.raises(ValueError, match="--depth-scale sets them"):
        run(folder, "--intrinsics", own)
    assert run(folder, "--depth-scale", "1000", "--intrinsics", own)[0] == 0
    assert "status: OK 3" in capsys.readouterr().out
    mine = read_trajectory(tmp_path / "raw.tum")
    assert run(shared_path(*BIWI))[0] == 0
    ref = read_trajectory(tmp_path / "raw.tum")
    np.testing.assert_allclose(mine.positions, ref.positions, atol=3e-3)
    with pytest.raises(ValueError, match="only for TUM RGB-D and color/ \\+ depth/ folders"):
        run(shared_path(*BIWI), "--depth-scale", "1000")
