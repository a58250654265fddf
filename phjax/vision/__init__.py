"""Vision: head pose per camera frame from RGB-D (and the relative pose of whole frames).

The pipeline, in the order a frame goes through it:

* :mod:`~phjax.vision.rgbd_io`: readers (``open_rgbd``: Biwi, TUM RGB-D, colour + depth
  folders, ``synthetic``) and camera intrinsics.
* :mod:`~phjax.vision.face_detection`: YuNet face detection (OpenCV or kornia) and the model
  cache.
* :mod:`~phjax.vision.features`: keypoints, descriptor matching, lifting through depth.
* :mod:`~phjax.vision.alignment`: weighted Kabsch / Umeyama and RANSAC.
* :mod:`~phjax.vision.icp`: point-to-plane ICP (projective association, fixed budget).
* :mod:`~phjax.vision.head_pose`: ``HeadPoseEstimator`` (the whole front-end) and
  ``rgbd_relative_pose``.
* :mod:`~phjax.vision.synthetic_rgbd`: a rendered synthetic head with exact ground truth.
* :mod:`~phjax.vision.monocular`: head pose from colour alone (``MonocularHeadPose``:
  opentrack's head-pose network by default, YuNet landmarks + PnP as a fallback).

OpenCV, onnxruntime, kornia and torch are optional (the ``vision`` extra); they are imported
when used. The head-pose network's weights are for research / non-commercial use only (see
:mod:`~phjax.vision.monocular`).
"""

from .alignment import AlignmentResult, AlignmentStatus, align, ransac_align, transform_points
from .face_detection import FaceDetection, FaceDetector, seed_model_cache
from .head_pose import (
    DenseRefinement,
    HeadPoseConfig,
    HeadPoseEstimator,
    HeadPoseResult,
    HeadPoseStatus,
    rgbd_relative_pose,
)
from .icp import (
    IcpResult,
    IcpStatus,
    PinholeIntrinsics,
    backproject,
    estimate_normals,
    icp_point_to_plane,
    icp_projective,
)
from .monocular import (
    MonocularHeadPose,
    MonocularResult,
    face_model,
    intrinsics_from_fov,
    pitch_yaw_roll,
    quaternion_from_pitch_yaw_roll,
)
from .rgbd_io import CameraIntrinsics, RGBDFrame, RGBDSequence, open_rgbd
from .synthetic_rgbd import (
    HeadModel,
    SyntheticRGBDFrame,
    SyntheticRGBDSequence,
    add_depth_noise,
    render_rgbd,
    synthetic_rgbd_sequence,
)

__all__ = [
    "AlignmentResult",
    "AlignmentStatus",
    "CameraIntrinsics",
    "DenseRefinement",
    "FaceDetection",
    "FaceDetector",
    "HeadModel",
    "HeadPoseConfig",
    "HeadPoseEstimator",
    "HeadPoseResult",
    "HeadPoseStatus",
    "IcpResult",
    "IcpStatus",
    "MonocularHeadPose",
    "MonocularResult",
    "PinholeIntrinsics",
    "RGBDFrame",
    "RGBDSequence",
    "SyntheticRGBDFrame",
    "SyntheticRGBDSequence",
    "add_depth_noise",
    "align",
    "backproject",
    "estimate_normals",
    "face_model",
    "icp_point_to_plane",
    "icp_projective",
    "intrinsics_from_fov",
    "open_rgbd",
    "pitch_yaw_roll",
    "quaternion_from_pitch_yaw_roll",
    "ransac_align",
    "render_rgbd",
    "rgbd_relative_pose",
    "seed_model_cache",
    "synthetic_rgbd_sequence",
    "transform_points",
]
