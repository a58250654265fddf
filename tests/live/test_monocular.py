"""Monocular head pose (YuNet landmarks + PnP) and the video source, on a video file written
from frames of the synthetic head."""

from __future__ import annotations

import numpy as np
import pytest
from live_helpers import model_cache  # noqa: F401

from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.live import LiveTracker, SourceError, VideoSource, VirtualClock, open_source
from phjax.vision import CameraIntrinsics
from phjax.vision.monocular import MonocularHeadPose, face_model, intrinsics_from_fov

cv2 = pytest.importorskip("cv2")

STRIDE, N, FPS = 5, 24, 6.0  # every 5th frame of 120 at 30 Hz: 4 s of motion at 6 frames/s
Q_FLIP = np.array([0.0, 0.0, 0.0, 1.0])  # synthetic head frame -> "facing the camera" frame


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    from phjax.vision import synthetic_rgbd_sequence

    seq = synthetic_rgbd_sequence(N * STRIDE, depth_noise=False)
    path = tmp_path_factory.mktemp("video") / "head.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS,
                             (seq.width, seq.height))
    assert writer.isOpened()
    for i in range(0, N * STRIDE, STRIDE):
        writer.write(np.ascontiguousarray(seq[i].color[..., ::-1]))
    writer.release()
    k = seq.intrinsics
    intr = CameraIntrinsics(fx=float(k.fx), fy=float(k.fy), cx=float(k.cx), cy=float(k.cy),
                            width=seq.width, height=seq.height)
    gt = np_qmul(seq.head_quaternions[::STRIDE][:N], Q_FLIP)
    return path, intr, gt, seq.head_positions[::STRIDE][:N]


def _angle(a, b):
    return np.degrees(np.linalg.norm(np_rotvec(np_qmul(a, np_qconj(b))), axis=-1))


def test_face_model_and_intrinsics():
    m = face_model(0.063)
    np.testing.assert_allclose(np.linalg.norm(m[1] - m[0]), 0.063)
    np.testing.assert_allclose(face_model(0.07)[:, :2] / 0.07, m[:, :2] / 0.063)
    k = intrinsics_from_fov(640, 480, 60.0)
    np.testing.assert_allclose(2 * np.degrees(np.arctan(320 / float(k.fx))), 60.0)
    with pytest.raises(ValueError):
        face_model(0.0)


def test_monocular_rotation_vs_ground_truth(video, model_cache):  # noqa: F811
    path, intr, gt, gt_pos = video
    est = MonocularHeadPose(intr, model_dir=model_cache)
    cap = cv2.VideoCapture(str(path))
    q, p = [], []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        r = est.process(frame, len(q) / FPS)
        q.append(r.quaternion)
        p.append(r.position)
    cap.release()
    q, p = np.array(q), np.array(p)
    assert len(q) == N
    ok = np.isfinite(q).all(1)
    assert ok.sum() >= N - 2
    # rotation relative to the first frame (camera frame), independent of the face model's
    # rest orientation
    rel_e = np_qmul(q[ok], np_qconj(q[ok][:1]))
    rel_g = np_qmul(gt[ok], np_qconj(gt[ok][:1]))
    err = _angle(rel_e, rel_g)
    moved = _angle(rel_g, np.array([1.0, 0, 0, 0]))
    print(f"\nmonocular: relative rotation error median {np.median(err):.2f} max "
          f"{err.max():.2f} deg (head turned up to {moved.max():.1f} deg); absolute "
          f"{np.median(_angle(q[ok], gt[ok])):.1f} deg; distance error median "
          f"{1e3 * np.median(np.abs(p[ok, 2] - gt_pos[ok, 2])):.0f} mm")
    assert moved.max() > 40.0
    # Measured here (YuNet's landmarks sit 3-20 px from the synthetic face's own landmark
    # points, the nose worst): errors below ~7.5 deg while the head has turned less than
    # 20 deg, growing to ~25 deg at a 52 deg turn (five landmarks underestimate large turns)
    small = moved < 20.0
    assert np.median(err[small]) < 5.0 and err[small].max() < 9.0
    # large turns: the right direction and at least half of the angle
    big = moved > 30.0
    rv_e, rv_g = np_rotvec(rel_e[big]), np_rotvec(rel_g[big])
    cos = np.sum(rv_e * rv_g, 1) / np.linalg.norm(rv_e, axis=1) / np.linalg.norm(rv_g, axis=1)
    assert cos.min() > 0.8
    assert (np.linalg.norm(rv_e, axis=1) > 0.5 * np.linalg.norm(rv_g, axis=1)).all()
    # absolute orientation at rest: measured 25 deg off, mostly pitch from YuNet's nose point
    # 13-20 px away from this face's nose tip (centring, as opentrack does, removes it)
    assert _angle(q[ok][:1], gt[ok][:1])[0] < 30.0


def test_video_source_through_live_tracker(video, model_cache, tmp_path):  # noqa: F811
    path, intr, _, _ = video
    src = VideoSource(str(path), intrinsics=intr, model_dir=model_cache)
    lt = LiveTracker(src, rate=60.0, clock=VirtualClock(), log=tmp_path / "v.tum")
    got = []
    lt.callback = got.append
    lt.run()
    assert lt.frames == N and lt.status_counts["OK"] >= N - 2
    assert lt.base_config.kalman.pos_meas_noise == pytest.approx(0.015)  # depth-free noise
    pos = np.array([s.position for s in got])
    assert np.isfinite(pos).all() and len(got) > 0.9 * 60 * (N - 1) / FPS


def test_video_and_webcam_errors(tmp_path):
    with pytest.raises(SourceError, match="cannot open webcam"):
        VideoSource(97).open()
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video")
    with pytest.raises(SourceError):
        open_source(str(bad)).open()
