"""phjax: smooth, predictive head and camera tracking in JAX.

Pose per camera frame, Kalman prediction, and render-rate motion reconstruction with spatial
Pythagorean-hodograph (PH) quintics. See the README for an overview.
"""

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

__version__ = "0.1.0"

__all__ = [
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
