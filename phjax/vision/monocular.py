"""Head pose from a colour image alone: YuNet's five landmarks and PnP against a face model.

:class:`MonocularHeadPose` detects the face with YuNet
(:class:`phjax.vision.face_detection.FaceDetector`), takes its five landmarks (the subject's
right eye, left eye, nose tip, right and left mouth corner) and solves the perspective-n-point
problem (``cv2.solvePnP``: SQPnP for the first frame or after a loss, then Levenberg-Marquardt
from the previous pose) against :func:`face_model`, a generic adult face scaled by an assumed
inter-pupillary distance.

Without depth the distance to the camera comes only from the face's apparent size, so it is as
good as the assumed inter-pupillary distance (a 5 % error in it is a 5 % error in distance) and
noisier than lateral position; the live tracker gives these poses a larger measurement noise
(:data:`MONOCULAR_NOISE`).

Face model (:func:`face_model`)
-------------------------------
Points in metres, in the **head frame**, whose axes are the camera's when the subject squarely
faces the camera: ``x`` towards the subject's left (the image's right), ``y`` down, ``z`` away
from the camera (into the head). Its origin is ``center_depth`` (default ``1.43 ipd``, 9 cm for
a 63 mm inter-pupillary distance) behind the midpoint of the pupils, near the head's centre,
so that turning the head moves the origin little. With ``d = ipd``, relative to the pupils'
midpoint (x, y, z):

=================  =====================  ===================
right eye (pupil)  ``(-d/2, 0, 0)``
left eye           ``(+d/2, 0, 0)``
nose tip           ``(0, 0.70 d, -0.40 d)``  44 mm below, 25 mm in front
right mouth corner ``(-0.40 d, 1.08 d, 0)``  25 mm to the side, 68 mm below
left mouth corner  ``(+0.40 d, 1.08 d, 0)``
=================  =====================  ===================

The proportions are rounded adult averages of the anthropometric literature (Farkas, 1994:
inter-pupillary distance ~63 mm, mouth width ~50 mm, pupil line to nose tip ~44 mm, nasal tip
protrusion ~25 mm, pupil line to the mouth corners ~68 mm); an individual face differs by
several millimetres, which shows up as a small, pose-dependent rotation error (measured on the
synthetic head, whose face has other proportions, in ``tests/live/test_monocular.py``).
The pose is ``(position, quaternion)``: the model origin in the camera frame and the rotation
of head-frame vectors into the camera frame (``wxyz``); the identity means facing the camera.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .._np_quat import np_qnormalize
from .face_detection import FaceDetector
from .head_pose import HeadPoseResult, HeadPoseStatus
from .rgbd_io import CameraIntrinsics

__all__ = [
    "DEFAULT_IPD",
    "MONOCULAR_NOISE",
    "MonocularHeadPose",
    "face_model",
    "intrinsics_from_fov",
]

#: default assumed inter-pupillary distance, m (adult average)
DEFAULT_IPD = 0.063
#: measurement noise of monocular poses for the tracker: position std (m), rotation std (rad)
MONOCULAR_NOISE = (0.015, math.radians(3.0))

# face model in units of the inter-pupillary distance (see the module docs)
_MODEL = np.array([
    [-0.5, 0.0, 0.0],    # right eye
    [0.5, 0.0, 0.0],     # left eye
    [0.0, 0.70, -0.40],  # nose tip
    [-0.40, 1.08, 0.0],  # right mouth corner
    [0.40, 1.08, 0.0],   # left mouth corner
])


def face_model(ipd: float = DEFAULT_IPD, center_depth: float | None = None) -> np.ndarray:
    """The five model points (m, head frame; order of YuNet's landmarks).

    Arguments:
        ipd: inter-pupillary distance, m.
        center_depth: distance of the head-frame origin behind the pupils' midpoint, m
            (default ``1.43 ipd``).

    Returns:
        ``(5, 3)`` float64.
    """
    if not ipd > 0:
        raise ValueError(f"ipd must be positive, got {ipd}")
    depth = 1.43 * ipd if center_depth is None else float(center_depth)
    return _MODEL * float(ipd) - np.array([0.0, 0.0, depth])


def intrinsics_from_fov(width: int, height: int, fov_deg: float = 60.0) -> CameraIntrinsics:
    """Pinhole intrinsics of an uncalibrated camera from its horizontal field of view.

    Arguments:
        width, height: image size, px.
        fov_deg: horizontal field of view, degrees (typical webcams: 55-70).
    """
    if not 1.0 < fov_deg < 179.0:
        raise ValueError(f"field of view must be in (1, 179) degrees, got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return CameraIntrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2,
                            width=int(width), height=int(height))


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """``wxyz`` of a rotation matrix (Shepperd's method, ``w >= 0``)."""
    tr = np.trace(r)
    i = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if i == 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif i == 1:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif i == 2:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np_qnormalize(np.asarray(q))
    return q if q[0] >= 0 else -q


class MonocularHeadPose:
    """Head pose per colour frame from YuNet landmarks and PnP (see the module docs).

    Arguments:
        intrinsics: the camera's intrinsics (see :func:`intrinsics_from_fov` for an
            uncalibrated webcam).
        ipd: assumed inter-pupillary distance, m (default 0.063).
        detector: a :class:`FaceDetector` (default: the OpenCV backend from the model cache
            ``model_dir``).
        model_dir: model cache directory for the default detector.
        max_reprojection: a pose whose RMS landmark reprojection error exceeds this fraction
            of the inter-pupillary distance in pixels is rejected (status ALIGNMENT_FAILED).

    ``process(color_bgr, t)`` returns a :class:`phjax.vision.HeadPoseResult` (NaN pose and a
    status when there is no face or PnP fails; never raises for bad frame content).
    """

    def __init__(self, intrinsics: CameraIntrinsics, ipd: float = DEFAULT_IPD, *,
                 detector: Any = None, model_dir: Any = None, max_reprojection: float = 0.25):
        import cv2

        self._cv2 = cv2
        self.intrinsics = intrinsics
        self.ipd = float(ipd)
        self.model = face_model(self.ipd)
        self.max_reprojection = float(max_reprojection)
        self.detector = detector if detector is not None else FaceDetector(
            "opencv", model_dir=model_dir)
        self._k = np.asarray(intrinsics.matrix, np.float64)
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        """Forget the previous pose (the next frame is solved from scratch)."""
        self._last = None

    def _nan(self, t, status, **kw) -> HeadPoseResult:
        return HeadPoseResult(float(t), np.full(3, np.nan), np.full(4, np.nan), status, **kw)

    def process(self, color: Any, t: float = 0.0) -> HeadPoseResult:
        """Head pose in one ``uint8 (H, W, 3)`` BGR frame taken at time ``t`` (s)."""
        cv2 = self._cv2
        t_start = time.perf_counter()
        color = np.asarray(color)
        if (color.ndim != 3 or color.shape[-1] != 3 or color.dtype != np.uint8
                or color.shape[:2] != self.intrinsics.shape):
            return self._nan(t, HeadPoseStatus.INVALID_INPUT)
        faces = self.detector.detect(color)
        if not faces:
            self._last = None
            return self._nan(t, HeadPoseStatus.NO_FACE)
        face = max(faces, key=lambda f: f.score)
        uv = np.asarray(face.landmarks, np.float64).reshape(5, 1, 2)
        obj = self.model.reshape(5, 1, 3)
        if self._last is None:
            ok, rvec, tvec = cv2.solvePnP(obj, uv, self._k, None, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                rvec, tvec = cv2.solvePnPRefineLM(obj, uv, self._k, None, rvec, tvec)
        else:
            rvec, tvec = (x.copy() for x in self._last)
            ok, rvec, tvec = cv2.solvePnP(obj, uv, self._k, None, rvec, tvec,
                                          useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()) or tvec[2] <= 0:
            self._last = None
            return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, face=face,
                             face_source="detector", face_box=face.box)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, self._k, None)
        rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, -1))))
        eye_px = float(np.linalg.norm(uv[1, 0] - uv[0, 0]))
        if rms > self.max_reprojection * max(eye_px, 1.0):
            self._last = None
            return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, face=face,
                             face_source="detector", face_box=face.box)
        self._last = (rvec, tvec)
        r, _ = cv2.Rodrigues(rvec)
        q = _quat_from_matrix(r)
        return HeadPoseResult(float(t), np.asarray(tvec, np.float64).ravel(), q,
                              HeadPoseStatus.OK, face=face, face_source="detector",
                              face_box=face.box,
                              timings={"total": time.perf_counter() - t_start})
