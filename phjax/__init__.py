"""phjax: smooth, predictive head and camera tracking in JAX.

Pose per camera frame, Kalman prediction, and render-rate motion reconstruction with spatial
Pythagorean-hodograph (PH) quintics. See the README for an overview.
"""

from . import io
from .alignment import AlignmentResult, AlignmentStatus, align, ransac_align, transform_points
from .kalman import (
    KalmanConfig,
    KalmanInfo,
    KalmanState,
    kalman_filter,
    kalman_init,
    kalman_predict,
    kalman_step,
    kalman_update,
    predict_pose,
    rts_smooth,
)
from .orientation import QuaternionHermite, quaternion_hermite
from .ph_quintic import FrameKind, PHQuintic, hermite_quintic, near_optimal_angles
from .quaternion import (
    quat_conj,
    quat_exp,
    quat_from_matrix,
    quat_from_rotvec,
    quat_geodesic_distance,
    quat_hemisphere_continuity,
    quat_identity,
    quat_inv,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_sandwich,
    quat_slerp,
    quat_to_matrix,
    quat_to_rotvec,
)
from .sampling import sample
from .simulate import SensorModel, simulate_measurements, synthetic_head_motion
from .tracker import (
    TrackerConfig,
    TrackerState,
    reconstruct,
    track,
    tracker_init,
    tracker_sample,
    tracker_update,
)

__version__ = "0.1.0"

__all__ = [
    "io",
    "AlignmentResult",
    "AlignmentStatus",
    "align",
    "ransac_align",
    "transform_points",
    "KalmanConfig",
    "KalmanInfo",
    "KalmanState",
    "kalman_filter",
    "kalman_init",
    "kalman_predict",
    "kalman_step",
    "kalman_update",
    "predict_pose",
    "rts_smooth",
    "QuaternionHermite",
    "quaternion_hermite",
    "SensorModel",
    "simulate_measurements",
    "synthetic_head_motion",
    "TrackerConfig",
    "TrackerState",
    "reconstruct",
    "track",
    "tracker_init",
    "tracker_sample",
    "tracker_update",
    "FrameKind",
    "PHQuintic",
    "hermite_quintic",
    "near_optimal_angles",
    "sample",
    "quat_conj",
    "quat_exp",
    "quat_from_matrix",
    "quat_from_rotvec",
    "quat_geodesic_distance",
    "quat_hemisphere_continuity",
    "quat_identity",
    "quat_inv",
    "quat_log",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "quat_sandwich",
    "quat_slerp",
    "quat_to_matrix",
    "quat_to_rotvec",
]
