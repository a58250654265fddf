"""Head pose from a colour image alone: a learned head-pose network (default) or five landmarks
and PnP (fallback).

:class:`MonocularHeadPose` has two methods:

``method="net"`` (default)
    opentrack's head-pose network (``head-pose-0.4-small-int8.onnx``, run with onnxruntime;
    see :mod:`phjax.vision._head_pose_net`). A face box comes from YuNet
    (:class:`phjax.vision.face_detection.FaceDetector`; or opentrack's head localizer with
    ``detector="localizer"``), scaled about its centre by :data:`DETECTOR_BOX_SCALE` (the median
    ratio of the network's own box to the detector's box, measured without labels on the shared
    AFLW2000-3D sample: 0.975 for YuNet, 0.892 for the localizer). From a grey crop of that box
    the network gives the head's rotation, its centre and size in pixels, a face box and the
    predicted uncertainty of both. In a video the next frame is cropped at the network's own box
    of this frame (no detector); the detector runs again when that track is lost: the
    network's rotation uncertainty above ``max_rotation_std`` (measured: 1.6-3.2 degrees on
    faces, 13-45 degrees on face-free crops), or the head centre outside the frame.
``method="landmarks"``
    the earlier front end: YuNet's five landmarks (the subject's right eye, left eye, nose tip,
    right and left mouth corner) and the perspective-n-point problem (``cv2.solvePnP``: SQPnP
    for the first frame or after a loss, then Levenberg-Marquardt from the previous pose)
    against :func:`face_model`, a generic adult face scaled by an assumed inter-pupillary
    distance. On the shared AFLW sample it reads frontal faces as looking up by ~18 degrees and
    rejects poses at large yaw (``benchmarks/bench_monocular.py``); kept as an explicit option.

Rotation convention
-------------------
The result's ``quaternion`` (``wxyz``) rotates **head-frame** vectors into the **camera frame**
(``x`` right in the image, ``y`` down, ``z`` forward out of the camera). The head frame has the
camera's axes when the subject squarely faces the camera (identity = facing the camera): ``x``
towards the subject's left (the image's right), ``y`` down (chin), ``z`` into the head.

The network's ``quat`` output ``(x, y, z, w)`` uses the same head and image axes, but relative
to the viewing ray through the face (the pose as seen in the crop: a face at the image edge
looking into the lens reads as the identity). So

    q_camera = q_ray * (w, x, y, z)_network,

where ``q_ray`` is the smallest rotation taking the optical axis ``(0, 0, 1)`` to the ray
through the head centre (as opentrack does); the crop-relative rotation is kept as
``crop_quaternion``. That network convention is the AFLW2000-3D label convention: with the
labels' pitch, yaw, roll (radians, ``Pose_Para``) and ``P = diag(1, 1, -1)``,

    R_crop = P * Rotation.from_euler("XYZ", [pitch, -yaw, roll]) * P

(scipy, intrinsic axes): positive pitch = the face looks up, positive yaw = it turns towards
the image's left (the subject's right), positive roll = it tilts clockwise in the image.
:func:`pitch_yaw_roll` and :func:`quaternion_from_pitch_yaw_roll` convert between the two (the
angles single-image head-pose benchmarks report their MAE in).
Verified in ``tests/vision/test_head_pose_net.py``: against the 16 labelled images of the
shared AFLW sample, and without labels, mirrored and rotated images change yaw / roll with
the signs above, and the predicted facing direction agrees with the label-free nose-tip offset.

Position
--------
Net: the network's head centre ``(u, v)`` and its head size ``s`` (px; about half the head's
vertical extent, as opentrack reads it) give ``z = fy * head_size / (2 s)`` with an assumed
vertical head size ``head_size`` (default :data:`DEFAULT_HEAD_SIZE` = 0.20 m, opentrack's
``HEAD_SIZE_MM``), then ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``: the head's centre in
metres. Landmarks: the origin of :func:`face_model` (9 cm behind the pupils), scaled by the
assumed inter-pupillary distance. Either way the distance is only as good as the assumed size
(a 5 % error in it is a 5 % error in distance). Measured (docs/results.md,
``benchmarks/bench_monocular.py``): on three Biwi frames of a calibrated camera the network's
distance was 2-6 % short at 0.9 m; on the AFLW photos its size-implied scale scattered by 5 %
(std; -9 % to +9 %) around the labels' fitted face scale.

Confidence
----------
The network's uncertainty outputs (lower-triangular scale factors of the rotation-vector and of
the centre / size covariance) give ``rotation_std`` (RMS over the axes, rad) and
``position_std`` (m per axis, the covariance of ``(u, v, s)`` through the projection above)
per frame, and ``confidence``: an inverse-variance weight relative to a well-seen face,
``min(1, (3 deg / rotation_std)^2, (5 % / relative size std)^2)`` (:data:`CONFIDENCE_REFERENCE`;
on the AFLW faces the network predicts 1.6-3.2 degrees and 2-5 %). ``phjax live`` divides the
measurement noise of the filter (:data:`MONOCULAR_NOISE`) by ``sqrt(confidence)`` for that
frame, so a doubtful frame counts less instead of jerking the stream. The landmark method has
no per-frame uncertainty: its confidence is the fraction of the face inside the image, 1 for a
face wholly in view: the smaller of the area fractions inside the image of YuNet's box and of
the face's extent around the landmarks (their box grown on every side by half the eye-to-mouth
distance, :data:`LANDMARK_FACE_MARGIN`; a box wholly outside is ``ALIGNMENT_FAILED``). A face
cut off by the image edge has landmarks guessed beyond what the detector saw (a chin cut off
read a face up to 2.2 times as far away) and so counts less. Measured on the AFLW photos
shifted down by 150-200 px (chin and mouth leaving the frame): 0.60-0.96; unshifted: 1.

Face model (:func:`face_model`, landmark method)
------------------------------------------------
Points in metres in the head frame. Its origin is ``center_depth`` (default ``1.43 ipd``, 9 cm
for a 63 mm inter-pupillary distance) behind the midpoint of the pupils, near the head's centre.
With ``d = ipd``, relative to the pupils' midpoint (x, y, z):

=================  =====================  ===================
right eye (pupil)  ``(-d/2, 0, 0)``
left eye           ``(+d/2, 0, 0)``
nose tip           ``(0, 0.70 d, -0.40 d)``  44 mm below, 25 mm in front
right mouth corner ``(-0.40 d, 1.08 d, 0)``  25 mm to the side, 68 mm below
left mouth corner  ``(+0.40 d, 1.08 d, 0)``
=================  =====================  ===================

The proportions are rounded adult averages of the anthropometric literature (Farkas, 1994:
inter-pupillary distance ~63 mm, mouth width ~50 mm, pupil line to nose tip ~44 mm, nasal tip
protrusion ~25 mm, pupil line to the mouth corners ~68 mm).

Licence of the network weights
------------------------------
opentrack's neural-net tracker code is ISC-licensed, but its weights were trained partly on
data licensed for non-commercial or research use only (WFLW / LaPa extensions, CC BY-NC 4.0;
Microsoft FaceSynthetics, research-only). Treat ``head-pose-0.4-small-int8.onnx`` and
``head-localizer.onnx`` as **research / non-commercial use only**; for commercial use choose
``method="landmarks"`` (YuNet: MIT / Apache-2.0).
"""

from __future__ import annotations

import copy
import math
import numbers
import time
from typing import Any, NamedTuple

import numpy as np

from .._face_sizes import HEAD_SIZE_RANGE, IPD_RANGE  # also phjax live's ranges
from .._np_quat import np_axis_quat, np_qconj, np_qmul, np_qnormalize, np_reflect_z
from .face_detection import FaceDetection, FaceDetector
from .head_pose import HeadPoseStatus
from .rgbd_io import CameraIntrinsics

__all__ = [
    "CONFIDENCE_REFERENCE",
    "DEFAULT_HEAD_SIZE",
    "DEFAULT_IPD",
    "DETECTOR_BOX_SCALE",
    "HEAD_SIZE_RANGE",
    "IPD_RANGE",
    "LANDMARK_FACE_MARGIN",
    "METHODS",
    "MONOCULAR_NOISE",
    "MonocularHeadPose",
    "MonocularResult",
    "face_model",
    "intrinsics_from_fov",
    "pitch_yaw_roll",
    "quaternion_from_pitch_yaw_roll",
    "ray_quaternion",
]

#: default assumed inter-pupillary distance, m (adult average)
DEFAULT_IPD = 0.063
#: default assumed vertical head size, m (opentrack's ``HEAD_SIZE_MM``)
DEFAULT_HEAD_SIZE = 0.20
#: measurement noise of monocular poses for the tracker: position std (m), rotation std (rad),
#: for a frame of confidence 1
MONOCULAR_NOISE = (0.015, math.radians(3.0))
#: rotation std (rad) and relative size std of a well-seen face: confidence 1 at or below them
CONFIDENCE_REFERENCE = (math.radians(3.0), 0.05)
#: face-box scale from each detector's box to the pose network's own box (module docs)
DETECTOR_BOX_SCALE = {"yunet": 0.975, "localizer": 0.892}
#: the estimation methods
METHODS = ("net", "landmarks")

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
    if not (ipd > 0 and math.isfinite(ipd)):
        raise ValueError(f"ipd must be positive and finite, got {ipd}")
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
    if not (int(width) > 0 and int(height) > 0):
        raise ValueError(f"image size must be positive, got {width}x{height}")
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return CameraIntrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2,
                            width=int(width), height=int(height))


def ray_quaternion(direction: Any) -> np.ndarray:
    """``wxyz`` of the smallest rotation taking the optical axis ``(0, 0, 1)`` to ``direction``
    (a camera-frame vector with positive ``z``)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    axis = np.array([-d[1], d[0], 0.0])  # (0, 0, 1) x d
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    half = 0.5 * math.atan2(s, float(d[2]))
    return np.concatenate([[math.cos(half)], math.sin(half) * axis / s])


def quaternion_from_pitch_yaw_roll(angles: Any) -> np.ndarray:
    """Crop-relative head rotation (``wxyz``, as :attr:`MonocularResult.crop_quaternion`) of
    head-pose angles in the AFLW2000-3D / 300W-LP label convention (module docs).

    Arguments:
        angles: ``(..., 3)`` pitch, yaw, roll in degrees (positive pitch: the face looks up;
            yaw: it turns towards the image's left; roll: it tilts clockwise in the image).

    Returns:
        ``(..., 4)`` unit quaternions ``wxyz`` with ``w >= 0``.
    """
    a = np.radians(np.asarray(angles, np.float64))
    if a.shape[-1:] != (3,):
        raise ValueError(f"angles must have shape (..., 3) (pitch, yaw, roll), got {a.shape}")
    q = np_qmul(np_qmul(np_axis_quat(0, a[..., 0]), np_axis_quat(1, -a[..., 1])),
                np_axis_quat(2, a[..., 2]))
    return _positive_w(np_reflect_z(q))


def pitch_yaw_roll(quaternion: Any) -> np.ndarray:
    """Head-pose angles in the AFLW2000-3D / 300W-LP label convention (the one Hopenet, FSA-Net
    and 6DRepNet report MAE in) of a crop-relative head rotation: the inverse of
    :func:`quaternion_from_pitch_yaw_roll`.

    Arguments:
        quaternion: ``(..., 4)`` ``wxyz``, e.g. :attr:`MonocularResult.crop_quaternion` (the
            rotation as seen in the face's crop; the camera-frame ``quaternion`` adds the
            viewing ray, which the labels of a single photo do not have). Normalised here.

    Returns:
        ``(..., 3)`` pitch, yaw, roll in degrees (yaw within +-90, pitch and roll within
        +-180); NaN for a NaN quaternion (no pose).
    """
    q = np.asarray(quaternion, np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternion must have shape (..., 4) (wxyz), got {q.shape}")
    w, x, y, z = np.moveaxis(np_reflect_z(np_qnormalize(q)), -1, 0)
    # intrinsic x-y-z angles (a, b, c) of R = Rx(a) Ry(b) Rz(c), from its matrix entries
    sb = np.clip(2 * (x * z + w * y), -1.0, 1.0)
    b = np.arcsin(sb)
    a = np.arctan2(-2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    c = np.arctan2(-2 * (x * y - w * z), 1 - 2 * (y * y + z * z))
    # gimbal lock (yaw +-90 deg): only pitch -+ roll is defined and both atan2 above are of
    # rounding noise; roll 0 and the pitch from the entries that still hold the rotation
    lock = np.abs(sb) > 1 - 1e-12
    a = np.where(lock, np.arctan2(np.sign(sb) * 2 * (x * y + w * z), 1 - 2 * (x * x + z * z)), a)
    c = np.where(lock, 0.0, c)
    return np.degrees(np.stack([a, -b, c], axis=-1)) + 0.0  # (no negative zeros)


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


def _number_between(x: Any, lo: float, hi: float) -> bool:
    """A finite real number (not a bool or a string) in ``[lo, hi]``."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        return False
    v = float(x)
    return math.isfinite(v) and lo <= v <= hi


def _box_inside_fraction(box: Any, shape: tuple[int, int]) -> float:
    """Fraction of the area of box ``(x, y, w, h)`` inside an image of ``shape`` ``(H, W)``."""
    x, y, w, h = (float(v) for v in box)
    if not (w > 0 and h > 0):
        return 0.0
    iw = max(min(x + w, shape[1]) - max(x, 0.0), 0.0)
    ih = max(min(y + h, shape[0]) - max(y, 0.0), 0.0)
    return iw * ih / (w * h)


#: landmark method: the face's extent is the box around its five landmarks grown on every side
#: by this fraction of the eye-to-mouth distance (the forehead, cheeks and chin; module docs)
LANDMARK_FACE_MARGIN = 0.5


def _landmark_extent(landmarks: np.ndarray) -> np.ndarray:
    """``(x, y, w, h)``: the landmarks' box grown by :data:`LANDMARK_FACE_MARGIN` times the
    distance from the eyes' midpoint to the mouth corners' midpoint."""
    lm = np.asarray(landmarks, np.float64).reshape(5, 2)
    m = LANDMARK_FACE_MARGIN * float(np.linalg.norm(lm[3:].mean(0) - lm[:2].mean(0)))
    lo, hi = lm.min(0) - m, lm.max(0) + m
    return np.concatenate([lo, hi - lo])


def _positive_w(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` with ``w >= 0``."""
    q = np_qnormalize(q)
    return np.where(q[..., :1] < 0, -q, q)


class MonocularResult(NamedTuple):
    """Head pose of one colour frame (NaN pose unless ``status == OK``).

    Attributes:
        timestamp: s.
        position: ``(3,)`` head origin in the camera frame, m.
        quaternion: ``(4,)`` ``wxyz`` (``w >= 0``), head frame -> camera frame (module docs).
        status: :class:`phjax.vision.HeadPoseStatus` (``OK``, ``NO_FACE``,
            ``ALIGNMENT_FAILED``, ``INVALID_INPUT``).
        confidence: weight of the frame for a filter in ``[0, 1]`` (0 without a pose; module
            docs; landmark method: the fraction of the face inside the image).
        rotation_std: predicted rotation std (RMS over the axes), rad (NaN: not predicted).
        position_std: ``(3,)`` predicted position std per camera axis, m (NaN: not predicted).
        crop_quaternion: ``(4,)`` the rotation relative to the viewing ray through the head
            (as AFLW2000-3D labels and the network give it).
        face: the :class:`~phjax.vision.face_detection.FaceDetection` of this frame (``None``
            when the box was tracked or came from the localizer).
        face_source: ``"detector"`` (YuNet), ``"localizer"``, ``"tracked"`` (the network's box
            of the previous frame) or ``"none"``.
        face_box: ``(4,)`` ``x, y, w, h`` of the box the pose was computed in (``None`` if none).
        method: ``"net"`` or ``"landmarks"``.
        timings: seconds per stage (``detect``, ``net`` / ``pnp``, ``total``).
    """

    timestamp: float
    position: np.ndarray
    quaternion: np.ndarray
    status: HeadPoseStatus
    confidence: float = 0.0
    rotation_std: float = float("nan")
    position_std: np.ndarray | None = None
    crop_quaternion: np.ndarray | None = None
    face: FaceDetection | None = None
    face_source: str = "none"
    face_box: np.ndarray | None = None
    method: str = "net"
    timings: dict | None = None

    @property
    def ok(self) -> bool:
        """``status == OK``."""
        return self.status == HeadPoseStatus.OK


class MonocularHeadPose:
    """Head pose per colour frame (see the module docs).

    Arguments:
        intrinsics: the camera's intrinsics (see :func:`intrinsics_from_fov` for an
            uncalibrated webcam).
        ipd: assumed inter-pupillary distance, m (landmark method; default 0.063; within
            :data:`IPD_RANGE`, 0.03-0.1).
        method: ``"net"`` (default) or ``"landmarks"`` (the five-point PnP fallback).
        head_size: assumed vertical head size, m (net method; default 0.20; within
            :data:`HEAD_SIZE_RANGE`, 0.05-0.5).
        detector: ``"yunet"`` (default), ``"localizer"`` (opentrack's head localizer; net
            method only) or a ready :class:`FaceDetector`.
        model_dir: model cache of YuNet and the networks (default
            :func:`phjax.vision.face_detection.model_dir`: ``$PHJAX_MODEL_DIR``).
        track: net method: crop the next frame at this frame's network box (re-detect only
            when the track is lost); ``False`` runs the detector on every frame.
        max_rotation_std: net method: a pose whose predicted rotation std exceeds this (rad,
            default 8 degrees) is not a face (status ``ALIGNMENT_FAILED`` after a detection;
            after a tracked crop the detector is tried on the same frame).
        max_reprojection: landmark method: a pose whose RMS landmark reprojection error exceeds
            this fraction of the inter-pupillary distance in pixels is rejected (status
            ``ALIGNMENT_FAILED``).
        threads: onnxruntime intra-op threads.

    ``process(color_bgr, t)`` returns a :class:`MonocularResult` (NaN pose and a status when
    there is no face or the pose fails its checks; never raises for bad frame content).

    Raises:
        ValueError: an argument is out of range (``ipd``, ``head_size`` outside their ranges;
            ``max_rotation_std``, ``max_reprojection`` not finite and positive).
        ModelNotFoundError: a model file is not in the cache.
        ImportError: OpenCV or (net method) onnxruntime is not installed.
    """

    def __init__(self, intrinsics: CameraIntrinsics, ipd: float = DEFAULT_IPD, *,
                 method: str = "net", head_size: float = DEFAULT_HEAD_SIZE,
                 detector: Any = "yunet", model_dir: Any = None, track: bool = True,
                 max_rotation_std: float = math.radians(8.0), max_reprojection: float = 0.25,
                 threads: int = 1):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        for name, value, (lo, hi) in (("head_size", head_size, HEAD_SIZE_RANGE),
                                      ("ipd", ipd, IPD_RANGE)):
            if not _number_between(value, lo, hi):
                raise ValueError(f"{name} must be between {lo:g} and {hi:g} m, got {value!r}")
        for name, value in (("max_rotation_std", max_rotation_std),
                            ("max_reprojection", max_reprojection)):
            if not _number_between(value, 0.0, math.inf) or not value > 0:
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")
        if detector is None:
            detector = "yunet"
        if isinstance(detector, str) and detector not in DETECTOR_BOX_SCALE:
            raise ValueError(f"detector must be one of {tuple(DETECTOR_BOX_SCALE)} or a "
                             f"FaceDetector, got {detector!r}")
        if method == "landmarks" and detector == "localizer":
            raise ValueError("the landmark method needs YuNet's landmarks, not the localizer")
        from .features import _require

        self._cv2 = _require("cv2")
        self._set_intrinsics(intrinsics)
        self.method = method
        self.ipd = float(ipd)
        self.model = face_model(self.ipd)
        self.head_size = float(head_size)
        self.track = bool(track)
        self.max_rotation_std = float(max_rotation_std)
        self.max_reprojection = float(max_reprojection)
        self.localizer = None
        self.detector = None
        if detector == "localizer":
            from ._head_pose_net import HeadLocalizer

            self.localizer = HeadLocalizer(model_dir, threads=threads)
            self.detector_kind = "localizer"
        else:
            self.detector = (FaceDetector("opencv", model_dir=model_dir)
                             if isinstance(detector, str) else detector)
            self.detector_kind = "yunet"
        self.net = None
        if method == "net":
            from ._head_pose_net import HeadPoseNet

            self.net = HeadPoseNet(model_dir, threads=threads)
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # landmark method: PnP pose
        self._box: np.ndarray | None = None  # net method: the crop of the next frame

    def _set_intrinsics(self, intrinsics: CameraIntrinsics) -> None:
        self.intrinsics = intrinsics.checked()
        self._k = np.asarray(self.intrinsics.matrix, np.float64)
        self._fx, self._fy = float(self.intrinsics.fx), float(self.intrinsics.fy)
        self._cx, self._cy = float(self.intrinsics.cx), float(self.intrinsics.cy)

    def reset(self) -> None:
        """Forget the previous frame (the next frame is detected / solved from scratch)."""
        self._last = None
        self._box = None

    def with_intrinsics(self, intrinsics: CameraIntrinsics) -> MonocularHeadPose:
        """The same estimator for another camera (or image size), sharing the loaded models.

        Arguments:
            intrinsics: the other camera's pinhole model.

        Returns:
            A new estimator with every other setting of this one and no previous frame; its
            detector and network sessions are this one's (loaded once for a folder of photos
            of mixed sizes).
        """
        other = copy.copy(self)
        other._set_intrinsics(intrinsics)
        other.reset()
        return other

    def _nan(self, t, status, **kw) -> MonocularResult:
        return MonocularResult(float(t), np.full(3, np.nan), np.full(4, np.nan), status,
                               position_std=np.full(3, np.nan),
                               crop_quaternion=np.full(4, np.nan), method=self.method, **kw)

    def process(self, color: Any, t: float = 0.0) -> MonocularResult:
        """Head pose in one ``uint8 (H, W, 3)`` BGR frame taken at time ``t`` (s; a non-finite
        ``t``, like a frame of another shape or type, gives ``INVALID_INPUT``)."""
        color, t = np.asarray(color), float(t)
        if (color.ndim != 3 or color.shape[-1] != 3 or color.dtype != np.uint8
                or color.shape[:2] != self.intrinsics.shape or not np.isfinite(t)):
            return self._nan(t, HeadPoseStatus.INVALID_INPUT)
        if self.method == "net":
            return self._process_net(color, t)
        return self._process_landmarks(color, t)

    # ------------------------------------------------------------------------------ net
    def _detect(self, color: np.ndarray, grey: np.ndarray):
        """``(box scaled for the network, FaceDetection or None, source)`` or ``None``."""
        if self.localizer is not None:
            found = self.localizer(grey)
            if found is None:
                return None
            box, face, source = found[1], None, "localizer"
        else:
            faces = self.detector.detect(color)
            if not faces:
                return None
            face = max(faces, key=lambda f: f.score)
            box, source = np.asarray(face.box, np.float64), "detector"
        k = DETECTOR_BOX_SCALE[self.detector_kind]
        centre = box[:2] + 0.5 * box[2:]
        return np.concatenate([centre - 0.5 * k * box[2:], k * box[2:]]), face, source

    def _plausible(self, nf) -> bool:
        if nf is None or not nf.rotation_std <= self.max_rotation_std or not nf.size > 2.0:
            return False
        h, w = self.intrinsics.shape
        u, v = nf.center
        return bool(0.0 <= u < w and 0.0 <= v < h)

    def _process_net(self, color: np.ndarray, t: float) -> MonocularResult:
        cv2 = self._cv2
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        grey = cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
        nf, face, source, box = None, None, "tracked", self._box
        if self.track and box is not None:
            t0 = time.perf_counter()
            nf = self.net(grey, box)
            timings["net"] = time.perf_counter() - t0
            if not self._plausible(nf):
                nf = None
        self._box = None
        if nf is None:
            t0 = time.perf_counter()
            found = self._detect(color, grey)
            timings["detect"] = time.perf_counter() - t0
            if found is None:
                return self._nan(t, HeadPoseStatus.NO_FACE, timings=timings)
            box, face, source = found
            t0 = time.perf_counter()
            nf = self.net(grey, box)
            timings["net"] = timings.get("net", 0.0) + time.perf_counter() - t0
            if not self._plausible(nf):
                return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, face=face,
                                 face_source=source, face_box=box, timings=timings)
        if self.track and nf.box[2] > 2.0 and nf.box[3] > 2.0:
            self._box = nf.box
        position, position_cov = self._position(nf)
        q = _positive_w(np_qmul(ray_quaternion(position), nf.quaternion))
        rel_size_std = math.sqrt(max(nf.center_size_cov[2, 2], 0.0)) / nf.size
        rot_ref, size_ref = CONFIDENCE_REFERENCE
        confidence = min(1.0, (rot_ref / max(nf.rotation_std, 1e-12)) ** 2,
                         (size_ref / max(rel_size_std, 1e-12)) ** 2)
        timings["total"] = time.perf_counter() - t_start
        return MonocularResult(float(t), position, q, HeadPoseStatus.OK, float(confidence),
                               nf.rotation_std, np.sqrt(np.maximum(np.diag(position_cov), 0.0)),
                               nf.quaternion, face, source, np.asarray(box, np.float64),
                               "net", timings)

    def _position(self, nf) -> tuple[np.ndarray, np.ndarray]:
        """Head centre (m, camera frame) from the network's centre and size, and its
        covariance (first-order propagation of the ``(u, v, size)`` covariance)."""
        (u, v), s = nf.center, nf.size
        fx, fy = self._fx, self._fy
        z = fy * 0.5 * self.head_size / s
        x, y = (u - self._cx) / fx * z, (v - self._cy) / fy * z
        jac = np.array([[z / fx, 0.0, -x / s], [0.0, z / fy, -y / s], [0.0, 0.0, -z / s]])
        return np.array([x, y, z]), jac @ nf.center_size_cov @ jac.T

    # ------------------------------------------------------------------------ landmarks
    def _process_landmarks(self, color: np.ndarray, t: float) -> MonocularResult:
        cv2 = self._cv2
        t_start = time.perf_counter()
        faces = self.detector.detect(color)
        t_det = time.perf_counter() - t_start
        if not faces:
            self._last = None
            return self._nan(t, HeadPoseStatus.NO_FACE, timings={"detect": t_det})
        face = max(faces, key=lambda f: f.score)
        uv = np.asarray(face.landmarks, np.float64).reshape(5, 1, 2)
        obj = self.model.reshape(5, 1, 3)
        ok, rvec, tvec = False, None, None
        try:  # SQPnP asserts on degenerate points (all landmarks within a pixel, NaN)
            if not np.isfinite(uv).all():
                pass
            elif self._last is None:
                ok, rvec, tvec = cv2.solvePnP(obj, uv, self._k, None, flags=cv2.SOLVEPNP_SQPNP)
                if ok:
                    rvec, tvec = cv2.solvePnPRefineLM(obj, uv, self._k, None, rvec, tvec)
            else:
                rvec, tvec = (x.copy() for x in self._last)
                ok, rvec, tvec = cv2.solvePnP(obj, uv, self._k, None, rvec, tvec,
                                              useExtrinsicGuess=True,
                                              flags=cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            ok = False
        failed = {"face": face, "face_source": "detector", "face_box": face.box,
                  "timings": {"detect": t_det}}
        if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()) or tvec[2] <= 0:
            self._last = None
            return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, **failed)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, self._k, None)
        rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, -1))))
        eye_px = float(np.linalg.norm(uv[1, 0] - uv[0, 0]))
        if rms > self.max_reprojection * max(eye_px, 1.0):
            self._last = None
            return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, **failed)
        shape = self.intrinsics.shape
        confidence = min(_box_inside_fraction(face.box, shape),
                         _box_inside_fraction(_landmark_extent(uv), shape))
        if not confidence > 0:  # a box wholly outside the image (a detector passed in)
            self._last = None
            return self._nan(t, HeadPoseStatus.ALIGNMENT_FAILED, **failed)
        self._last = (rvec, tvec)
        r, _ = cv2.Rodrigues(rvec)
        q = _quat_from_matrix(r)
        position = np.asarray(tvec, np.float64).ravel()
        crop = _positive_w(np_qmul(np_qconj(ray_quaternion(position)), q))
        total = time.perf_counter() - t_start
        return MonocularResult(float(t), position, q, HeadPoseStatus.OK, confidence, float("nan"),
                               np.full(3, np.nan), crop, face, "detector",
                               np.asarray(face.box, np.float64), "landmarks",
                               {"detect": t_det, "pnp": total - t_det, "total": total})
