"""Review of :meth:`phjax.vision.head_pose.HeadPoseEstimator.process` on bad and unusual frames
(one Biwi frame, one shape, one compiled set of stages)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_path, yunet_models

from phjax.io import biwi_pose_to_quaternion, read_biwi_pose
from phjax.vision import face_detection as F
from phjax.vision import head_pose as H
from phjax.vision import rgbd_io as R


@pytest.fixture(scope="module")
def biwi(tmp_path_factory):
    """Biwi frame 00054 with its ground-truth head pose (colour camera frame), and a detector.
    (A real frame read from disk: rendering the synthetic head compiles its renderer, 5-9 s,
    more than these tests may take.)"""
    root = shared_path("biwi_kinect_head_pose_samples")
    cache = tmp_path_factory.mktemp("models")
    F.seed_model_cache(yunet_models(), cache)
    cal = R.read_biwi_calibration(root / "rgb.cal")
    r, t = R.biwi_pose_in_color_frame(*read_biwi_pose(root / "frame_00054_pose.txt"), cal)
    return (R.read_biwi_frame(root, "00054"), (biwi_pose_to_quaternion(r), t),
            F.FaceDetector("opencv", model_dir=cache))


@pytest.mark.parametrize("t", ["abc", np.array([0.0, 1.0]), 10**400, object()],
                         ids=["str", "array", "huge_int", "object"])
def test_a_timestamp_that_is_not_a_number_is_invalid_input(biwi, t):
    # (it raised ValueError / TypeError / OverflowError from float(t); a NaN time was already
    # INVALID_INPUT). Checked before any stage runs: no frame content is processed.
    f, _, det = biwi
    est = H.HeadPoseEstimator(f.intrinsics, detector=det)
    r = est.process(f.color, f.depth, t)
    assert r.status == H.HeadPoseStatus.INVALID_INPUT and np.isnan(r.timestamp)
    assert np.isnan(r.position).all() and np.isnan(r.quaternion).all()
    assert est.num_keyframes == 0


def test_reacquisition_on_a_frame_without_face_depth_keeps_the_orientation_rule(biwi):
    """A confirmed reference is dropped for re-acquisition (here after ``reacquire_after=1``
    failure) on a frame whose face has almost no depth, so no new reference can be made there
    (NO_DEPTH). The next good frame, with the head 60 px (~10 cm) to the right, started a
    reference by the *first-frame* rule: the constructor's ``reference_pose``, i.e. frame 0's
    position and orientation exactly, reported OK 10 cm from the head. It must start it by the
    re-acquisition rule: the kept orientation, at this frame's face."""
    f, gt, det = biwi
    est = H.HeadPoseEstimator(f.intrinsics, H.HeadPoseConfig(reacquire_after=1), detector=det,
                              reference_pose=gt)
    r0 = est.process_frame(f)
    assert r0.ok and r0.face_source == "detector"
    x, y, w, h = (int(v) for v in r0.face_box)
    holed = f.depth.copy()  # no depth on the face but a 3 x 5 speck at its centre
    holed[y - 40:y + h + 40, x - 40:x + w + 40] = 0
    u, v = x + w // 2, y + h // 2
    holed[v:v + 3, u:u + 5] = f.depth[v:v + 3, u:u + 5]
    r1 = est.process(f.color, holed, 0.1)
    assert r1.status == H.HeadPoseStatus.NO_DEPTH and r1.face_source == "detector"
    assert est.num_keyframes == 0
    s = 60  # the same head 60 px to the right: x + s z / fx in the camera frame
    color, depth = np.zeros_like(f.color), np.zeros_like(f.depth)
    color[:, s:], depth[:, s:] = f.color[:, :-s], f.depth[:, :-s]
    r2 = est.process(color, depth, 0.2)
    assert r2.ok and r2.is_keyframe and r2.face_source == "detector"
    # where a reference started at this frame sits (the start rule: the face centre pushed
    # back along the ray), with the orientation kept from frame 0
    fresh = H.HeadPoseEstimator(f.intrinsics, detector=det).process(color, depth, 0.0)
    assert fresh.ok
    np.testing.assert_allclose(r2.position, fresh.position, atol=1e-6)
    np.testing.assert_allclose(r2.quaternion, r0.quaternion, atol=1e-12)
    assert np.linalg.norm(r2.position - r0.position) > 0.05  # (it was r0's, 0 m away)
