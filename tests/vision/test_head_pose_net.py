"""Monocular head pose with opentrack's head-pose network (phjax.vision.monocular, method "net").

References are independent of the implementation: the AFLW2000-3D labels converted with scipy
(``../shared/data/aflw2000_3d_sample/SOURCE.md``), the Biwi ground truth of a calibrated camera,
and label-free image transformations (mirroring, in-plane rotation, scaling, YuNet's
landmarks). The networks are loaded once per module (shared data: ``head_pose_models``,
``yunet_face_detection``).
"""

from __future__ import annotations

import math
import shutil

import equinox as eqx
import numpy as np
import pytest
from conftest import shared_path, yunet_models
from scipy.io import loadmat
from scipy.spatial.transform import Rotation

from phjax.vision import HeadPoseStatus
from phjax.vision import face_detection as F
from phjax.vision.monocular import MonocularHeadPose, intrinsics_from_fov, ray_quaternion

cv2 = pytest.importorskip("cv2")
pytest.importorskip("onnxruntime")

IDS = ("00050", "00081", "00251", "00430", "00475", "00514", "00516", "01038", "01322",
       "02283", "02420", "02545", "02616", "03324", "03614", "04331")
P = np.diag([1.0, 1.0, -1.0])
S = np.diag([-1.0, 1.0, 1.0])  # mirror of the image's x axis


def label_matrix(pitch, yaw, roll):
    """AFLW2000-3D label -> head-to-image rotation matrix (SOURCE.md's convention)."""
    return P @ Rotation.from_euler("XYZ", [pitch, -yaw, roll]).as_matrix() @ P


def matrix(q_wxyz):
    w, x, y, z = q_wxyz
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def euler_deg(m):
    """(pitch, yaw, roll) in degrees of a head-to-image matrix (inverse of label_matrix)."""
    e = Rotation.from_matrix(P @ m @ P).as_euler("XYZ")
    return np.degrees([e[0], -e[1], e[2]])


def geodesic_deg(a, b):
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))


@pytest.fixture(scope="module")
def aflw():
    root = shared_path("aflw2000_3d_sample")
    out = []
    for i in IDS:
        mat = loadmat(root / f"image{i}.mat")
        out.append((i, cv2.imread(str(root / f"image{i}.jpg")), mat["Pose_Para"][0]))
    return out


@pytest.fixture(scope="module")
def detector():
    return F.FaceDetector("opencv", model_dir=yunet_models())


@pytest.fixture(scope="module")
def est(detector):
    """The single-image estimator of the 450 x 450 AFLW photos (no tracking)."""
    return MonocularHeadPose(intrinsics_from_fov(450, 450, 45.0), detector=detector,
                             model_dir=shared_path("head_pose_models"), track=False)


@pytest.fixture(scope="module")
def aflw_results(aflw, est):
    return [est.process(img) for _, img, _ in aflw]


# ------------------------------------------------------------------------------ accuracy
#: measured here (YuNet box x 0.975, one pass per image): MAE pitch / yaw / roll
#: 3.81 / 3.17 / 1.35 deg (mean 2.77), geodesic mean 5.53 deg, worst 10.0 deg (02545 / 03324);
#: on 2026-11-30 (same models and code path) 3.50 / 3.34 / 1.21 (mean 2.68), 5.32, 10.39.
#: Bounds: measured + 20 % + 0.3 deg (int8 kernels may differ slightly between CPUs).
MEASURED_MAE = np.array([3.81, 3.17, 1.35])
MEASURED_GEODESIC = (5.53, 10.0)


def _bound(x):
    return 1.2 * np.asarray(x) + 0.3


def test_aflw_accuracy_against_labels(aflw, aflw_results):
    errs, geo = [], []
    for (name, _, pose), r in zip(aflw, aflw_results):
        assert r.ok, (name, r.status)
        assert r.face_source == "detector" and r.method == "net"
        gt = label_matrix(*pose[:3])
        m = matrix(r.crop_quaternion)
        errs.append(np.abs(euler_deg(m) - np.degrees(pose[:3])))
        geo.append(geodesic_deg(gt, m))
    errs, geo = np.array(errs), np.array(geo)
    mae = errs.mean(0)
    print(f"\nAFLW sample: MAE pitch / yaw / roll {mae.round(2)} (mean {mae.mean():.2f}) deg; "
          f"geodesic mean {geo.mean():.2f}, max {geo.max():.2f} deg")
    assert (mae <= _bound(MEASURED_MAE)).all()
    assert mae.mean() <= min(_bound(MEASURED_MAE.mean()), 4.0)  # and the issue's acceptance
    assert geo.mean() <= _bound(MEASURED_GEODESIC[0])
    # no label here is extreme (all |angle| < 80 deg), so every image must be within 15 deg
    assert np.degrees(np.abs([p[:3] for _, _, p in aflw])).max() < 80.0
    assert geo.max() <= min(_bound(MEASURED_GEODESIC[1]), 15.0)


def test_pitch_yaw_roll_is_the_label_convention(aflw, aflw_results):
    """The public conversion between crop quaternions and AFLW-convention angles agrees with
    scipy's (this file's ``label_matrix`` / ``euler_deg``) on the network's 16 poses, on the
    16 labels and on 2000 random poses (yaw within +-89 deg), and the two directions invert
    each other; a lost pose (NaN) gives NaN angles."""
    from phjax.vision import pitch_yaw_roll, quaternion_from_pitch_yaw_roll

    for (_, _, pose), r in zip(aflw, aflw_results):
        np.testing.assert_allclose(pitch_yaw_roll(r.crop_quaternion),
                                   euler_deg(matrix(r.crop_quaternion)), atol=1e-9)
        q = quaternion_from_pitch_yaw_roll(np.degrees(pose[:3].astype(np.float64)))
        np.testing.assert_allclose(matrix(q), label_matrix(*pose[:3]), atol=1e-12)
    rng = np.random.default_rng(5)
    angles = rng.uniform([-170, -89, -170], [170, 89, 170], (2000, 3))
    q = quaternion_from_pitch_yaw_roll(angles)
    assert q.shape == (2000, 4) and (q[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(pitch_yaw_roll(q), angles, atol=1e-9)
    np.testing.assert_allclose(pitch_yaw_roll(-3 * q[:5]), angles[:5], atol=1e-9)  # sign, scale
    assert np.isnan(pitch_yaw_roll(np.full(4, np.nan))).all()
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 4\)"):
        pitch_yaw_roll(np.zeros(3))
    # at yaw +-90 deg (gimbal lock) only pitch -+ roll is defined: roll 0, and the angles still
    # give the same rotation (they gave another one: (10, 90, 20) read back as (90, 90, 90))
    locked = np.array([[10, 90, 20], [10, -90, 20], [-170, 90, 35], [0, 90, 0]], np.float64)
    got = pitch_yaw_roll(quaternion_from_pitch_yaw_roll(locked))
    np.testing.assert_allclose(got[:, 1:], [[90, 0], [-90, 0], [90, 0], [90, 0]], atol=1e-6)
    for a, b in zip(locked, got):
        np.testing.assert_allclose(matrix(quaternion_from_pitch_yaw_roll(b)),
                                   matrix(quaternion_from_pitch_yaw_roll(a)), atol=1e-12)


def test_label_convention_is_the_only_one_that_fits(aflw, aflw_results):
    """The documented label -> rotation conversion fits; its plausible variants do not."""
    variants = {
        "documented": lambda p, y, r: label_matrix(p, y, r),
        "yaw not negated": lambda p, y, r: label_matrix(p, -y, r),
        "no axis flip": lambda p, y, r: Rotation.from_euler("XYZ", [p, -y, r]).as_matrix(),
        "transposed": lambda p, y, r: label_matrix(p, y, r).T,
        "extrinsic xyz": lambda p, y, r: P @ Rotation.from_euler("xyz", [p, -y, r]).as_matrix()
        @ P,
    }
    mean = {}
    for name, conv in variants.items():
        mean[name] = np.mean([geodesic_deg(conv(*pose[:3]), matrix(r.crop_quaternion))
                              for (_, _, pose), r in zip(aflw, aflw_results)])
    print({k: round(float(v), 1) for k, v in mean.items()})
    # measured: 5.5 deg documented; the variants 11.0 (extrinsic order: at moderate angles the
    # order is a second-order effect) to 69 deg
    assert mean["documented"] < 7.0
    for name, v in mean.items():
        if name != "documented":
            assert v > 1.6 * mean["documented"], name


# ---------------------------------------------------------------------- label-free checks
def test_mirror_negates_yaw_and_roll(aflw, aflw_results, est):
    """A mirrored photo shows the mirrored head: R' = S R S with S = diag(-1, 1, 1)."""
    errs = []
    for (_, img, _), r in zip(aflw, aflw_results):
        rm = est.process(np.ascontiguousarray(img[:, ::-1]))
        assert rm.ok
        errs.append(geodesic_deg(S @ matrix(r.crop_quaternion) @ S, matrix(rm.crop_quaternion)))
        # against the unmirrored pose (a wrong sign convention would fit this instead)
    print(f"mirror consistency: mean {np.mean(errs):.2f}, max {np.max(errs):.2f} deg")
    assert np.mean(errs) < 4.0 and np.max(errs) < 8.0  # measured 2.7 / 4.7


def test_in_plane_rotation_is_a_rotation_about_the_optical_axis(aflw, aflw_results, est):
    """The photo turned 20 deg counter-clockwise on screen (cv2's positive angle): the head
    turns by -20 deg about the image z axis (x right, y down, z into the scene)."""
    a = cv2.getRotationMatrix2D((224.5, 224.5), 20.0, 1.0)
    spins = []
    for (_, img, _), r in zip(aflw, aflw_results):
        rot = cv2.warpAffine(img, a, (450, 450), borderMode=cv2.BORDER_REPLICATE)
        rr = est.process(rot)
        assert rr.ok
        d = Rotation.from_matrix(matrix(rr.crop_quaternion) @ matrix(r.crop_quaternion).T)
        spins.append(np.degrees(d.as_rotvec()))
    spins = np.array(spins)
    print(f"in-plane 20 deg: rotation vectors mean {spins.mean(0).round(2)} deg")
    np.testing.assert_allclose(spins.mean(0), [0.0, 0.0, -20.0], atol=1.5)  # measured -20.4
    assert np.abs(spins[:, 2] + 20.0).max() < 3.5 and np.abs(spins[:, :2]).max() < 4.0


def test_facing_direction_agrees_with_the_nose(aflw_results):
    """Faces turned towards the image's left (forward vector -z_head with x < 0) have YuNet's
    nose tip left of the eye-mouth midline, and vice versa (no labels involved)."""
    checked = 0
    for r in aflw_results:
        fwd = matrix(r.crop_quaternion) @ np.array([0.0, 0.0, -1.0])
        lm = r.face.landmarks
        mid = 0.25 * (lm[0, 0] + lm[1, 0] + lm[3, 0] + lm[4, 0])
        if abs(fwd[0]) > 0.1:
            assert np.sign(lm[2, 0] - mid) == np.sign(fwd[0])
            checked += 1
    assert checked >= 10


def test_frontal_face_is_near_identity(aflw, aflw_results):
    """image00050's label is within 6 deg of frontal; the estimate within 8 deg of identity."""
    i = IDS.index("00050")
    assert np.degrees(np.abs(aflw[i][2][:3])).max() < 6.0
    assert geodesic_deg(np.eye(3), matrix(aflw_results[i].crop_quaternion)) < 8.0


def test_camera_frame_adds_the_viewing_ray(aflw_results):
    """quaternion = ray(position) * crop_quaternion, and the ray is the position's direction."""
    for r in aflw_results:
        q_ray = ray_quaternion(r.position)
        np.testing.assert_allclose(matrix(q_ray) @ [0, 0, 1.0],
                                   r.position / np.linalg.norm(r.position), atol=1e-12)
        np.testing.assert_allclose(matrix(r.quaternion), matrix(q_ray) @ matrix(r.crop_quaternion),
                                   atol=1e-9)
        assert r.quaternion[0] >= 0 and abs(np.linalg.norm(r.quaternion) - 1) < 1e-12


def test_biwi_absolute_pose_and_depth_on_a_calibrated_camera(detector):
    """Biwi (Kinect colour camera, calibrated; 3 frames of one subject): camera-frame
    orientation and the distance from the assumed 0.20 m head size."""
    from phjax._np_quat import np_qconj, np_qmul, np_rotvec
    from phjax.io import biwi_pose_to_quaternion, read_biwi_pose
    from phjax.vision import rgbd_io as R

    root = shared_path("biwi_kinect_head_pose_samples")
    cal = R.read_biwi_calibration(root / "rgb.cal")
    est = MonocularHeadPose(cal.intrinsics, detector=detector,
                            model_dir=shared_path("head_pose_models"), track=False)
    for n in ("00054", "00427", "unknown"):
        frame = R.read_biwi_frame(root, n)
        rot, t = R.biwi_pose_in_color_frame(*read_biwi_pose(root / f"frame_{n}_pose.txt"), cal)
        r = est.process(np.ascontiguousarray(frame.color[..., ::-1]))
        assert r.ok
        err = np.degrees(np.linalg.norm(np_rotvec(np_qmul(np_qconj(biwi_pose_to_quaternion(rot)),
                                                          r.quaternion))))
        ratio = np.linalg.norm(r.position) / np.linalg.norm(t)
        print(f"Biwi {n}: orientation error {err:.1f} deg, distance ratio {ratio:.3f}, "
              f"position error {1e3 * np.linalg.norm(r.position - t):.0f} mm")
        # measured 6.2 / 1.7 / 4.1 deg and distance ratios 0.943 / 0.969 / 0.983
        assert err < 8.0 and 0.90 < ratio < 1.03
        assert np.linalg.norm(r.position - t) < 0.08  # measured 40-65 mm


def test_with_intrinsics_shares_the_models_and_equals_a_fresh_estimator(aflw, est):
    """Another image size through ``with_intrinsics``: the same detector and network sessions
    (``phjax head-pose`` loads them once for a folder of mixed sizes), the same result as an
    estimator built for that size, and the original estimator unchanged."""
    intr = intrinsics_from_fov(640, 480, 60.0)
    other = est.with_intrinsics(intr)
    assert other.net is est.net and other.detector is est.detector
    assert other.intrinsics.shape == (480, 640) and est.intrinsics.shape == (450, 450)
    fresh = MonocularHeadPose(intr, detector=est.detector,
                              model_dir=shared_path("head_pose_models"), track=False)
    for _, img, _ in aflw[:3]:
        canvas = np.full((480, 640, 3), 128, np.uint8)
        canvas[15:465, 95:545] = img
        a, b = other.process(canvas), fresh.process(canvas)
        assert a.ok and a.status == b.status
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.quaternion, b.quaternion)
        assert est.process(img).ok and not est.process(canvas).ok  # wrong size for est


def test_depth_follows_the_apparent_head_size(aflw, detector):
    """A photo shown at half size on a 640 x 480 canvas reads twice as far away; the distance
    is proportional to the assumed head size; lateral position follows the image position."""
    intr = intrinsics_from_fov(640, 480, 60.0)
    kw = {"detector": detector, "model_dir": shared_path("head_pose_models"), "track": False}
    est = MonocularHeadPose(intr, **kw)
    big = MonocularHeadPose(intr, head_size=0.25, **kw)
    ratios = []
    for _, img, _ in aflw[:6]:
        full = np.full((480, 640, 3), 128, np.uint8)
        full[15:465, 95:545] = img
        half = np.full((480, 640, 3), 128, np.uint8)
        half[120:345, 300:525] = cv2.resize(img, (225, 225), interpolation=cv2.INTER_AREA)
        a, b, c = est.process(full), est.process(half), big.process(full)
        assert a.ok and b.ok and c.ok
        ratios.append(b.position[2] / a.position[2])
        np.testing.assert_allclose(c.position, 1.25 * a.position, rtol=1e-9)
        assert b.position[0] > a.position[0] + 0.05  # the half-size photo sits to the right
    print(f"distance ratio half / full size: {np.round(ratios, 3)}")
    assert np.all(np.abs(np.array(ratios) - 2.0) < 0.2)


# --------------------------------------------------------------------- statuses, tracking
def test_bad_input_gives_a_clear_status(est, detector):
    r = est.process(np.zeros((450, 450), np.uint8))
    assert r.status == HeadPoseStatus.INVALID_INPUT and not r.ok
    assert np.isnan(r.position).all() and np.isnan(r.quaternion).all() and r.confidence == 0
    assert est.process(np.zeros((480, 640, 3), np.uint8)).status == HeadPoseStatus.INVALID_INPUT
    assert est.process(np.zeros((450, 450, 3), np.float32)).status == \
        HeadPoseStatus.INVALID_INPUT
    assert est.process(np.full((450, 450, 3), 128, np.uint8)).status == HeadPoseStatus.NO_FACE
    # a NaN time (its pose was OK, stamped NaN: found by review)
    assert est.process(np.full((450, 450, 3), 128, np.uint8), float("nan")).status == \
        HeadPoseStatus.INVALID_INPUT
    noise = np.random.default_rng(0).integers(0, 256, (450, 450, 3), dtype=np.uint8)
    assert est.process(noise).status == HeadPoseStatus.NO_FACE

    class FakeDetector:  # a "face" box on a face-free image: the network's uncertainty rejects it
        def detect(self, image):
            return [F.FaceDetection(np.array([150, 120, 160, 200], np.float32),
                                    np.zeros((5, 2), np.float32), 0.9)]

    fake = MonocularHeadPose(est.intrinsics, detector=FakeDetector(),
                             model_dir=shared_path("head_pose_models"))
    r = fake.process(np.full((450, 450, 3), 90, np.uint8))
    assert r.status == HeadPoseStatus.ALIGNMENT_FAILED and r.face_box is not None
    with pytest.raises(ValueError, match="method"):
        MonocularHeadPose(est.intrinsics, method="pnp", detector=detector)
    with pytest.raises(ValueError, match="landmark"):
        MonocularHeadPose(est.intrinsics, method="landmarks", detector="localizer")
    # unusable intrinsics are refused when built, not a NaN pose reported as OK later
    k = est.intrinsics
    for bad in (eqx.tree_at(lambda c: c.fx, k, np.nan), eqx.tree_at(lambda c: c.fy, k, 0.0),
                eqx.tree_at(lambda c: c.cx, k, np.inf), eqx.tree_at(lambda c: c.fx, k, -500.0)):
        for method in ("net", "landmarks"):
            with pytest.raises(ValueError, match="intrinsics need finite fx, fy > 0"):
                MonocularHeadPose(bad, method=method, detector=detector)
    with pytest.raises(ValueError, match="image size must be positive"):
        intrinsics_from_fov(0, 0)


@pytest.mark.parametrize("landmarks", [
    [[225.0, 225.0]] * 5,                                            # all in one point
    [[225.0 + 0.01 * i, 225.0 + 0.01 * (i % 2)] for i in range(5)],  # within a pixel
    [[np.nan, 1.0]] * 5,                                             # NaN
])
def test_landmark_method_on_degenerate_landmarks_is_a_status(landmarks):
    """SQPnP asserts on landmarks without spread (a face a few pixels wide in a 1080p frame, or
    NaN from a detector passed in): that was a cv2.error out of ``process`` (a live run ended
    with status 1); it is ALIGNMENT_FAILED, and the next good frame is estimated again."""
    class Fixed:
        lm = np.asarray(landmarks, np.float32)

        def detect(self, image):
            return [F.FaceDetection(np.array([150, 120, 160, 200], np.float32), self.lm, 0.9)]

    est = MonocularHeadPose(intrinsics_from_fov(450, 450), method="landmarks", detector=Fixed())
    r = est.process(np.zeros((450, 450, 3), np.uint8))
    assert r.status == HeadPoseStatus.ALIGNMENT_FAILED and np.isnan(r.position).all()
    Fixed.lm = np.array([[200, 200], [250, 200], [225, 230], [205, 260], [245, 260]], np.float32)
    assert est.process(np.zeros((450, 450, 3), np.uint8)).ok


def test_missing_model_names_the_cache(tmp_path, detector):
    with pytest.raises(F.ModelNotFoundError, match="head-pose-0.4-small-int8.onnx"):
        MonocularHeadPose(intrinsics_from_fov(450, 450), detector=detector, model_dir=tmp_path)
    # seeding the cache from a folder copies the network (and ignores other files)
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(shared_path("head_pose_models", "head-pose-0.4-small-int8.onnx"), src / "hp.onnx")
    (src / "other.txt").write_text("x")
    out = F.seed_model_cache(src, tmp_path / "cache")
    assert [p.name for p in out] == ["head-pose-0.4-small-int8.onnx"]
    assert F.model_path("head-pose", tmp_path / "cache").is_file()


def test_confidence_falls_on_an_occluded_face(aflw, aflw_results, est):
    """The lower half of the face covered (a hand, a mask): larger predicted uncertainty,
    lower confidence (or no pose)."""
    clean, occl = [], []
    for (_, img, _), r in zip(aflw, aflw_results):
        x, y, w, h = r.face_box.astype(int)
        im = img.copy()
        im[y + h // 2:y + h, x:x + w] = 0
        ro = est.process(im)
        clean.append((r.confidence, math.degrees(r.rotation_std)))
        occl.append((ro.confidence, math.degrees(ro.rotation_std) if ro.ok else np.inf))
        if ro.ok:
            assert np.all(np.isfinite(ro.position_std)) and ro.rotation_std > 0
    clean, occl = np.array(clean), np.array(occl)
    print(f"confidence clean {clean[:, 0].mean():.2f} -> occluded {occl[:, 0].mean():.2f}; "
          f"rotation std median {np.median(clean[:, 1]):.1f} -> {np.median(occl[:, 1]):.1f} deg")
    assert clean[:, 0].mean() > 0.95  # measured 0.99
    assert occl[:, 0].mean() < clean[:, 0].mean() - 0.3
    assert np.median(occl[:, 1]) > 1.5 * np.median(clean[:, 1])
    assert (occl[:, 1] > clean[:, 1]).mean() >= 0.8


def test_video_tracks_the_box_and_redetects_after_a_loss(aflw, detector):
    """A photo moving 8 px a frame on a 640 x 480 canvas, three blank frames, the photo back
    elsewhere: detector, then tracked crops; NO_FACE while blank; detector again."""
    intr = intrinsics_from_fov(640, 480, 60.0)
    est = MonocularHeadPose(intr, detector=detector, model_dir=shared_path("head_pose_models"))
    img = cv2.resize(aflw[0][1], (300, 300), interpolation=cv2.INTER_AREA)

    def frame(x0, y0):
        f = np.full((480, 640, 3), 128, np.uint8)
        if x0 is not None:
            f[y0:y0 + 300, x0:x0 + 300] = img
        return f

    plan = [(20 + 8 * i, 90) for i in range(10)] + [(None, 0)] * 3 + [(300, 150)] * 4
    results = [est.process(frame(*p), i / 30) for i, p in enumerate(plan)]
    sources = [r.face_source for r in results]
    assert sources == ["detector"] + ["tracked"] * 9 + ["none"] * 3 + ["detector"] + \
        ["tracked"] * 3
    assert [r.status for r in results[10:13]] == [HeadPoseStatus.NO_FACE] * 3
    ok = [r for r in results if r.ok]
    assert len(ok) == 14
    # the crop-relative pose of the same photo hardly changes while tracked
    crop = np.array([euler_deg(matrix(r.crop_quaternion)) for r in results[:10]])
    assert np.abs(crop - crop[0]).max() < 3.0
    # the head moves right by 8 px a frame: 8 z / f metres
    x = np.array([r.position[0] for r in results[:10]])
    z = np.mean([r.position[2] for r in results[:10]])
    step = np.diff(x).mean()
    assert step == pytest.approx(8 * z / float(intr.fx), rel=0.15)
    est.reset()
    assert est.process(frame(300, 150)).face_source == "detector"


def test_localizer_detector(aflw):
    """opentrack's head localizer instead of YuNet finds every AFLW face; same accuracy
    class (measured geodesic mean 5.3 deg)."""
    est = MonocularHeadPose(intrinsics_from_fov(450, 450), detector="localizer",
                            model_dir=shared_path("head_pose_models"), track=False)
    geo = []
    for _, img, pose in aflw:
        r = est.process(img)
        assert r.ok and r.face_source == "localizer" and r.face is None
        geo.append(geodesic_deg(label_matrix(*pose[:3]), matrix(r.crop_quaternion)))
    print(f"localizer boxes: geodesic mean {np.mean(geo):.2f}, max {np.max(geo):.2f} deg")
    assert np.mean(geo) < 7.0 and np.max(geo) < 13.0
    assert est.process(np.full((450, 450, 3), 128, np.uint8)).status == HeadPoseStatus.NO_FACE


def test_landmark_fallback_is_still_available(aflw, detector):
    """The five-point PnP path stays selectable (and is what the network replaced: larger
    errors on the same photos, measured geodesic mean 17.8 deg on its 14 poses)."""
    est = MonocularHeadPose(intrinsics_from_fov(450, 450, 45.0), method="landmarks",
                            detector=detector)
    geo = []
    for _, img, pose in aflw:
        r = est.process(img)
        est.reset()
        if r.ok:
            assert r.method == "landmarks" and r.confidence == 1.0
            geo.append(geodesic_deg(label_matrix(*pose[:3]), matrix(r.crop_quaternion)))
    assert len(geo) >= 12 and np.mean(geo) > 10.0


# ------------------------------------------------------------- argument ranges, noise, edges
def test_assumed_sizes_are_range_checked(detector):
    """head_size=inf (or 1e300) gave status OK with an infinite position and a NaN quaternion;
    sizes outside the CLI's ranges (head 0.05-0.5 m, ipd 0.03-0.1 m) are refused when built."""
    from phjax.vision.monocular import HEAD_SIZE_RANGE, IPD_RANGE

    assert HEAD_SIZE_RANGE == (0.05, 0.5) and IPD_RANGE == (0.03, 0.1)
    intr = intrinsics_from_fov(450, 450)
    for bad in (float("inf"), 1e300, float("nan"), 0.0, -0.2, 0.049, 0.51, 200.0, "0.2", None):
        with pytest.raises(ValueError, match="head_size must be between 0.05 and 0.5 m"):
            MonocularHeadPose(intr, head_size=bad, detector=detector)
    for bad in (float("inf"), float("nan"), 0.0, 0.029, 0.11, 63.0):
        with pytest.raises(ValueError, match="ipd must be between 0.03 and 0.1 m"):
            MonocularHeadPose(intr, ipd=bad, method="landmarks", detector=detector)
    for kw in ({"max_rotation_std": float("nan")}, {"max_rotation_std": 0.0},
               {"max_reprojection": float("inf")}, {"max_reprojection": -1.0}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            MonocularHeadPose(intr, method="landmarks", detector=detector, **kw)
    # the ends of the ranges are accepted
    for size in HEAD_SIZE_RANGE:
        for ipd in IPD_RANGE:
            MonocularHeadPose(intr, ipd=ipd, head_size=size, method="landmarks",
                              detector=detector)


def test_landmark_method_with_kornia_finds_no_face_in_noise(tmp_path, monkeypatch):
    """The kornia detector's false faces in square noise frames became OK poses with
    confidence 1 (8 of 10 frames); they are dropped by the detector's plausibility check."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    cache = tmp_path / "models"
    F.seed_model_cache(yunet_models(), cache)
    est = MonocularHeadPose(intrinsics_from_fov(450, 450), method="landmarks",
                            detector=F.FaceDetector("kornia", model_dir=cache))
    rng = np.random.default_rng(0)
    for _ in range(10):
        est.reset()
        r = est.process(rng.integers(0, 256, (450, 450, 3), dtype=np.uint8))
        assert r.status == HeadPoseStatus.NO_FACE and r.confidence == 0.0


def test_landmark_confidence_falls_for_a_face_cut_off_by_the_image_edge(aflw, detector):
    """A face shifted down until its mouth and chin leave the frame read up to 2.2 times as far
    away with confidence 1. Its confidence is now the fraction of the face inside the image:
    measured 1 unshifted, 0.60-0.87 at 200 px down (13 poses; the others NO_FACE /
    ALIGNMENT_FAILED); bounds 0.9 and a mean below 0.8 (measured 0.74)."""
    est = MonocularHeadPose(intrinsics_from_fov(450, 450, 45.0), method="landmarks",
                            detector=detector)
    shifted, far = [], []
    for _, img, _ in aflw:
        est.reset()
        r0 = est.process(img)
        est.reset()
        r = est.process(cv2.warpAffine(img, np.float32([[1, 0, 0], [0, 1, 200]]), (450, 450)))
        if r0.ok:
            assert r0.confidence == 1.0
        if r.ok:
            assert 0.0 < r.confidence <= 0.9
            shifted.append(r.confidence)
            if r0.ok and r.position[2] > 1.3 * r0.position[2]:
                far.append(r.confidence)
    print(f"confidence of faces cut off at the bottom: {np.round(shifted, 2)}")
    assert len(shifted) >= 10 and np.mean(shifted) < 0.8
    assert far  # the distance error this guards against happens here
