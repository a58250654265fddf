"""Head pose per RGB-D frame: face detection, keypoints + landmarks, robust alignment, ICP.

:class:`HeadPoseEstimator` turns a stream of registered colour + depth frames into head poses
(position in metres and ``wxyz`` orientation, both in the colour camera's frame: ``x`` right,
``y`` down, ``z`` forward) with a per-frame :class:`HeadPoseStatus`. A bad frame gives a NaN
pose and a status, never an exception.

Pipeline of one frame
---------------------
1. **Face region.** YuNet (:class:`phjax.vision.face_detection.FaceDetector`) on a downscaled copy
   (every ``detect_interval`` frames). Without a detection the region is *tracked*: the
   current keyframe's face points projected with the last pose; failing that it is taken
   from depth (the top of the nearest depth blob, :func:`head_box_from_depth`).
2. **Observations** (fixed shapes, so the JAX stages compile once): up to ``max_keypoints``
   ORB/SIFT keypoints in the face box (:func:`phjax.vision.features.detect_keypoints`), the five
   landmarks, both lifted to 3-D through the depth (invalid, out-of-range and depth-edge
   pixels rejected), and an organised ``crop_grid x crop_grid`` point cloud with normals of a
   ``crop_size``-metre square around the face.
3. **Candidates** for the motion keyframe -> frame (camera-frame points ``p' = R p + t``):
   (a) RANSAC (:func:`phjax.ransac_align`) on the descriptor matches (ratio test + mutual
   check, :func:`phjax.vision.features.match_descriptors`) together with the landmark pairs;
   (b) the weighted Kabsch fit of the landmark pairs alone; (c) the prediction from the last
   pose.
4. **Refinement.** Point-to-plane ICP (:func:`phjax.vision.icp.icp_projective`, or the
   nearest-neighbour variant) of the keyframe's face points (within ``face_radius`` of the
   face centre: the rigid part of the face, without hair, ears and neck) onto the frame's
   organised cloud, with a coarse-to-fine correspondence distance. It starts from the first
   valid candidate (a, then b, then c); only if that result fails the checks is ICP run from
   all candidates at once (``vmap`` inside ``lax.cond``) and the one with the most inliers
   (discounted by its residual) kept. Checks: the inlier fraction and RMS residual
   (``min_overlap``, ``max_rmse``) and the landmark gate (the motion must carry the
   keyframe's 3-D landmarks to within ``landmark_gate`` RMS of the frame's: point-to-plane
   ICP can otherwise slide to a wrong minimum along the face surface).
5. **Absolute pose** ``R = R_rel R_kf``, ``t = R_rel t_kf + t_rel`` through the keyframe's pose.
   The first good frame is keyframe 0; its pose is ``reference_pose`` if given, else the
   identity orientation at the face centre pushed ``head_center_offset`` metres back along the
   viewing ray (a point near the head's rotation centre). A new keyframe is added when the
   head has turned more than ``keyframe_angle`` from the nearest keyframe (up to
   ``max_keyframes``); each frame is aligned to the keyframe nearest in orientation to the
   last pose, which keeps large rotations trackable without chaining every frame.
6. **Re-acquisition.** A reference started without a detected face (depth fallback: possibly
   furniture, when the camera starts before the user sits down) is provisional: the first
   detected face that does not align to it starts a new reference there. A confirmed reference
   is replaced after ``reacquire_after`` failed alignments in a row (the user or the camera
   moved too far), keeping the last orientation.

The JAX part of a frame is two jitted calls (observations; matching + RANSAC + ICP) on padded
arrays (keypoints, landmarks, crop grid and keyframe cloud have static sizes), so there is no
recompilation per frame; the static argument holds only the settings those stages use, so a
host-side setting (detector backend, keyframe policy) does not recompile them either. Depth is
processed in float32.
"""

from __future__ import annotations

import enum
import functools
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._jit import jit
from .._np_quat import np_qconj, np_qmul, np_qnormalize, np_rotvec, np_valid_quaternions
from .alignment import OK as ALIGN_OK
from .alignment import align, ransac_align
from .features import (
    Keypoints,
    _require,
    detect_keypoints,
    expand_box,
    lift_keypoints,
    match_descriptors,
)
from .icp import IcpStatus, backproject, estimate_normals, icp_point_to_plane, icp_projective
from ..quaternion import quat_rotate
from .rgbd_io import CameraIntrinsics, RGBDFrame

__all__ = [
    "HeadPoseStatus",
    "HeadPoseConfig",
    "HeadPoseResult",
    "HeadPoseEstimator",
    "DenseRefinement",
    "RelativePose",
    "head_box_from_depth",
    "rgbd_relative_pose",
]


class HeadPoseStatus(enum.IntEnum):
    """Per-frame status of :class:`HeadPoseEstimator` (``OK`` = a pose was estimated)."""

    OK = 0
    NO_FACE = 1  #: no face box from the detector, the tracker or the depth image
    NO_DEPTH = 2  #: too little valid depth in the frame or in the face region
    #: no pose: too few feature matches for RANSAC and too few landmarks to the keyframe, and
    #: the refinement from the predicted pose did not pass the checks either (blur, occlusion,
    #: a featureless or turned-away face)
    TOO_FEW_MATCHES = 3
    #: no pose: correspondences gave a candidate, but no refined candidate passed the overlap /
    #: residual / landmark checks
    ALIGNMENT_FAILED = 4
    #: colour / depth arrays of the wrong shape or type, bad intrinsics, or a non-finite time
    INVALID_INPUT = 5


@dataclass(frozen=True)
class HeadPoseConfig:
    """Settings of :class:`HeadPoseEstimator` (frozen, hashable: static under ``jit``).

    Face region: ``backend`` (``"opencv"`` / ``"kornia"``), ``detect_width`` (px of the
    downscaled detector input), ``detect_interval`` (run the detector every n-th frame; track
    the box in between), ``min_face_score`` (``None``: the backend's default,
    :data:`phjax.vision.face_detection.DEFAULT_SCORE_THRESHOLD`), ``depth_fallback`` (take the
    face box from depth, :func:`head_box_from_depth`, when neither the detector nor the tracker
    gives one), ``box_scale`` (enlargement of the face box for
    keypoints).

    Keypoints: ``feature_method`` (``"orb"`` / ``"sift"``), ``max_keypoints`` (static K),
    ``fast_threshold`` (ORB), ``ratio`` (Lowe), depth limits ``min_depth`` / ``max_depth`` (m),
    depth-edge test ``edge_abs + edge_rel z^2`` (m).

    Alignment: ``ransac_iterations``, ``ransac_threshold`` (m), ``min_feature_inliers`` (fewer
    RANSAC inliers: candidate (a) is not used), ``landmark_weight`` (relative to a keypoint),
    ``landmark_gate`` (m: an ICP result that leaves the RMS distance of the keyframe's moved
    landmarks to the frame's above this is discarded, when >= 3 landmark pairs exist).

    ICP: ``icp`` (``"projective"``, ``"nearest"`` or ``"none"``), ``icp_iterations``,
    ``icp_max_distance`` (start, end) of a geometric coarse-to-fine schedule (m),
    ``face_radius`` (source points of a keyframe, m), ``target_radius`` (target points, m),
    ``crop_size`` (side of the target crop, m), ``crop_grid`` (static G: G x G samples),
    ``cloud_points`` (static N of the source cloud), acceptance ``min_overlap`` (inlier
    fraction of the source) and ``max_rmse`` (m).

    Pose: ``keyframe_angle`` (deg), ``max_keyframes``, ``head_center_offset`` (m),
    ``min_valid_depth`` (valid depth pixels needed in a frame), ``seed``.

    Re-acquisition: ``reacquire_after`` (frames). A reference (keyframe 0) started without a
    detected face (from the depth fallback or the tracked box: it may be furniture) is
    provisional until a frame with a detected face aligns to it; a detected face that fails to
    align to a provisional reference starts a new one at once. A confirmed reference is replaced
    after ``reacquire_after`` failed alignments in a row, at the next one with a detected face
    (0: never). A new reference keeps the last confirmed orientation (or the start rule's),
    also when the frame that drops the old one has too little depth to start it (NO_DEPTH):
    the next frame that can starts it with that orientation, never by the first-frame rule
    (``reference_pose``).
    """

    backend: str = "opencv"
    detect_width: int | None = 320
    detect_interval: int = 1
    min_face_score: float | None = None
    depth_fallback: bool = True
    box_scale: float = 1.1
    feature_method: str = "orb"
    max_keypoints: int = 384
    fast_threshold: int = 7
    ratio: float = 0.8
    min_depth: float = 0.25
    max_depth: float = 2.5
    edge_abs: float = 0.01
    edge_rel: float = 0.01
    ransac_iterations: int = 128
    ransac_threshold: float = 0.008
    min_feature_inliers: int = 8
    landmark_weight: float = 1.0
    landmark_gate: float = 0.025
    icp: str = "projective"
    icp_iterations: int = 25
    icp_max_distance: tuple[float, float] = (0.02, 0.005)
    face_radius: float = 0.065
    target_radius: float = 0.13
    crop_size: float = 0.32
    crop_grid: int = 96
    cloud_points: int = 1024
    min_overlap: float = 0.4
    max_rmse: float = 0.005
    keyframe_angle: float = 20.0
    max_keyframes: int = 16
    head_center_offset: float = 0.08
    min_valid_depth: int = 200
    seed: int = 0
    reacquire_after: int = 30

    def __post_init__(self):
        if self.backend not in ("opencv", "kornia"):
            raise ValueError(f"backend must be 'opencv' or 'kornia', got {self.backend!r}")
        if self.feature_method not in ("orb", "sift"):
            raise ValueError(f"feature_method must be 'orb' or 'sift', got {self.feature_method!r}")
        if self.icp not in ("projective", "nearest", "none"):
            raise ValueError(f"icp must be 'projective', 'nearest' or 'none', got {self.icp!r}")
        if self.detect_interval < 1:
            raise ValueError("detect_interval must be >= 1")
        if self.reacquire_after < 0:
            raise ValueError("reacquire_after must be >= 0 (0: never)")
        for name in ("max_keypoints", "crop_grid", "cloud_points", "ransac_iterations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1")


_JAX_FIELDS = ("min_depth", "max_depth", "edge_abs", "edge_rel", "ratio", "ransac_iterations",
               "ransac_threshold", "min_feature_inliers", "landmark_weight", "landmark_gate",
               "icp", "icp_iterations", "icp_max_distance", "face_radius", "target_radius",
               "crop_grid", "cloud_points", "min_overlap", "max_rmse", "seed")


@dataclass(frozen=True)
class _JaxConfig:
    """The settings the jitted stages depend on (their static argument), so that changing a
    host-side setting (detector backend, keyframe policy, ...) does not recompile them."""

    min_depth: float
    max_depth: float
    edge_abs: float
    edge_rel: float
    ratio: float
    ransac_iterations: int
    ransac_threshold: float
    min_feature_inliers: int
    landmark_weight: float
    landmark_gate: float
    icp: str
    icp_iterations: int
    icp_max_distance: tuple[float, float]
    face_radius: float
    target_radius: float
    crop_grid: int
    cloud_points: int
    min_overlap: float
    max_rmse: float
    seed: int

    @classmethod
    def of(cls, cfg: HeadPoseConfig) -> _JaxConfig:
        vals = {k: getattr(cfg, k) for k in _JAX_FIELDS}
        vals["icp_max_distance"] = tuple(float(v) for v in cfg.icp_max_distance)
        return cls(**vals)


class HeadPoseResult(NamedTuple):
    """Head pose of one frame (colour camera frame; NaN pose unless ``status == OK``).

    Attributes:
        timestamp: s.
        position: ``(3,)`` head origin, m.
        quaternion: ``(4,)`` head orientation ``wxyz`` (``w >= 0``).
        status: :class:`HeadPoseStatus`.
        face: the :class:`~phjax.vision.face_detection.FaceDetection` used (``None`` if the box came
            from tracking or depth, or no face).
        face_source: ``"detector"``, ``"tracked"``, ``"depth"`` or ``"none"``.
        face_box: ``(4,)`` ``x, y, w, h`` of the face region (``None`` if none).
        num_matches: descriptor matches to the keyframe.
        num_inliers: RANSAC inliers (matches + landmarks) of candidate (a).
        icp_inliers: ICP correspondences of the accepted result; ``icp_rmse`` its RMS
            point-to-plane residual (m).
        candidate: the winning candidate ``"ransac"``, ``"landmarks"``, ``"prediction"`` or
            ``""``.
        keyframe: index of the keyframe used (-1 if none); ``is_keyframe``: this frame
            became a keyframe.
        timings: seconds per stage (``detect``, ``features``, ``jax``, ``total``).
    """

    timestamp: float
    position: np.ndarray
    quaternion: np.ndarray
    status: HeadPoseStatus
    face: Any = None
    face_source: str = "none"
    face_box: np.ndarray | None = None
    num_matches: int = 0
    num_inliers: int = 0
    icp_inliers: int = 0
    icp_rmse: float = float("nan")
    candidate: str = ""
    keyframe: int = -1
    is_keyframe: bool = False
    timings: dict | None = None

    @property
    def ok(self) -> bool:
        """``status == OK``."""
        return self.status == HeadPoseStatus.OK


_CANDIDATES = ("ransac", "landmarks", "prediction")


# ---------------------------------------------------------------------------- NumPy helpers
def _np_qmatrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _np_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    return float(np.linalg.norm(np_rotvec(np_qmul(np_qconj(q0), q1))))


def _canon(q: np.ndarray) -> np.ndarray:
    q = np_qnormalize(np.asarray(q, np.float64))
    return -q if q[0] < 0 else q


def _nan_pose() -> tuple[np.ndarray, np.ndarray]:
    return np.full(3, np.nan), np.full(4, np.nan)


# ------------------------------------------------------------------------------ depth region
def head_box_from_depth(
    depth: np.ndarray, intrinsics: CameraIntrinsics, *, min_depth: float = 0.25,
    max_depth: float = 2.5, band: float = 0.35, head_size: tuple[float, float] = (0.17, 0.23),
) -> np.ndarray | None:
    """A head box from depth alone: the top of the nearest connected depth blob.

    The nearest valid depth (1st percentile) defines a band ``[z_near, z_near + band]``; the
    largest connected component of the band is taken as the person and the head as a
    ``head_size`` (width, height, m) box centred on the component's columns just below its top
    row, sized at the component's median depth.

    Returns:
        ``(x, y, w, h)`` or ``None`` if there is no valid depth.
    """
    cv2 = _require("cv2")
    d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0)
    valid = (d >= min_depth) & (d <= max_depth)
    if np.count_nonzero(valid) < 50:
        return None
    z_near = float(np.percentile(d[valid], 1.0))
    near = (valid & (d <= z_near + band)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(near, connectivity=8)
    if n <= 1:
        return None
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    blob = labels == k
    z_med = float(np.median(d[blob]))
    w_px = head_size[0] * float(intrinsics.fx) / z_med
    h_px = head_size[1] * float(intrinsics.fy) / z_med
    top = int(stats[k, cv2.CC_STAT_TOP])
    rows = blob[top:int(top + 0.5 * h_px) + 1]
    cols = np.nonzero(rows)[1]
    if cols.size == 0:
        return None
    cx = float(np.median(cols))
    return np.asarray([cx - 0.5 * w_px, top, w_px, h_px], np.float32)


# ---------------------------------------------------------------------------- JAX structures
class _Frame(eqx.Module):
    """Observations of one frame (fixed shapes)."""

    kp_points: Array  # (K, 3)
    kp_ok: Array  # (K,)
    descriptors: Array  # (K, D)
    lm_points: Array  # (5, 3)
    lm_ok: Array  # (5,)
    grid: Array  # (G, G, 3) organised crop cloud
    normals: Array  # (G, G, 3)
    grid_ok: Array  # (G, G) valid target points (within target_radius of the centre)
    crop_k: Array  # (4,) fx, fy, cx, cy of the crop grid
    centre: Array  # (3,) face centre estimate
    centre_ok: Array  # ()


class _Keyframe(eqx.Module):
    """A reference view: observations plus its absolute head pose."""

    kp_points: Array
    kp_ok: Array
    descriptors: Array
    lm_points: Array
    lm_ok: Array
    cloud: Array  # (N, 3) face points
    cloud_ok: Array  # (N,)
    quaternion: Array  # (4,)
    position: Array  # (3,)


class _Estimate(eqx.Module):
    quaternion: Array  # (4,) relative rotation keyframe -> frame
    translation: Array  # (3,)
    candidate: Array  # () index into _CANDIDATES, -1 = none
    any_measured: Array  # () a RANSAC or landmark candidate existed
    num_matches: Array
    num_inliers: Array
    icp_inliers: Array
    icp_rmse: Array
    overlap: Array
    accepted: Array


def _frame_arrays(depth, k4, kp_uv, kp_valid, desc, lm_uv, lm_valid, crop, cfg: _JaxConfig):
    """Lift keypoints/landmarks and build the organised crop (jitted inside ``_observe``)."""
    dtype = depth.dtype
    fx, fy, cx, cy = k4[0], k4[1], k4[2], k4[3]
    intr = _K(fx, fy, cx, cy)
    lift = functools.partial(lift_keypoints, min_depth=cfg.min_depth, max_depth=cfg.max_depth,
                             edge_abs=cfg.edge_abs, edge_rel=cfg.edge_rel)
    kp_p, kp_ok = lift(kp_uv, depth, intr, kp_valid)
    lm_p, lm_ok = lift(lm_uv, depth, intr, lm_valid)
    # organised crop: G x G nearest-pixel samples starting at crop[:2] with step crop[2]
    g = cfg.crop_grid
    h, w = depth.shape
    steps = jnp.arange(g, dtype=dtype)
    u = jnp.round(crop[0] + crop[2] * steps)
    v = jnp.round(crop[1] + crop[2] * steps)
    inside = ((u >= 0) & (u < w))[None, :] & ((v >= 0) & (v < h))[:, None]
    z = depth[jnp.clip(v, 0, h - 1).astype(jnp.int32)[:, None],
              jnp.clip(u, 0, w - 1).astype(jnp.int32)[None, :]]
    z = jnp.where(inside & jnp.isfinite(z) & (z >= cfg.min_depth) & (z <= cfg.max_depth), z, 0)
    pts = jnp.stack([(u[None, :] - cx) * z / fx, (v[:, None] - cy) * z / fy, z], axis=-1)
    nrm = estimate_normals(pts, radius=1, max_depth_jump=0.05)
    crop_k = jnp.stack([fx / crop[2], fy / crop[2], (cx - crop[0]) / crop[2],
                        (cy - crop[1]) / crop[2]])
    # face centre: mean of the lifted landmarks, else the crop centre ray at the median depth
    n_lm = jnp.sum(lm_ok)
    lm_mean = jnp.sum(jnp.where(lm_ok[:, None], lm_p, 0), 0) / jnp.maximum(n_lm, 1)
    zc = z[g // 4: 3 * g // 4, g // 4: 3 * g // 4].reshape(-1)
    zc_ok = zc > 0
    n_c = jnp.sum(zc_ok)
    z_sorted = jnp.sort(jnp.where(zc_ok, zc, jnp.inf))
    z_med = z_sorted[jnp.maximum(n_c // 2, 0)]
    uc = crop[0] + crop[2] * (g - 1) / 2
    vc = crop[1] + crop[2] * (g - 1) / 2
    z_med = jnp.where(n_c > 0, z_med, 0)
    ray_pt = jnp.stack([(uc - cx) * z_med / fx, (vc - cy) * z_med / fy, z_med])
    centre = jnp.where(n_lm >= 2, lm_mean, ray_pt)
    centre_ok = (n_lm >= 2) | (n_c > 0)
    near = jnp.sum((pts - centre) ** 2, axis=-1) <= cfg.target_radius ** 2
    grid_ok = (z > 0) & near & (jnp.sum(nrm * nrm, axis=-1) > 0)
    return _Frame(kp_p, kp_ok, desc, lm_p, lm_ok, pts, nrm, grid_ok, crop_k, centre, centre_ok)


class _K(NamedTuple):
    fx: Any
    fy: Any
    cx: Any
    cy: Any


@functools.partial(jit, static_argnames=("cfg",))
def _observe(depth, k4, kp_uv, kp_valid, desc, lm_uv, lm_valid, crop, cfg):
    return _frame_arrays(depth, k4, kp_uv, kp_valid, desc, lm_uv, lm_valid, crop, cfg)


@functools.partial(jit, static_argnames=("cfg",))
def _make_keyframe(frame: _Frame, quaternion, position, index, cfg) -> _Keyframe:
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed + 1), index)
    pts = frame.grid.reshape(-1, 3)
    ok = ((frame.grid[..., 2] > 0) & (jnp.sum(frame.normals ** 2, -1) > 0)).reshape(-1)
    ok = ok & (jnp.sum((pts - frame.centre) ** 2, -1) <= cfg.face_radius ** 2)
    n = min(cfg.cloud_points, pts.shape[0])
    prio = jnp.where(ok, jax.random.uniform(key, ok.shape), -1.0)
    val, idx = jax.lax.top_k(prio, n)
    cloud = pts[idx]
    cloud_ok = val >= 0
    if n < cfg.cloud_points:
        pad = cfg.cloud_points - n
        cloud = jnp.concatenate([cloud, jnp.zeros((pad, 3), cloud.dtype)])
        cloud_ok = jnp.concatenate([cloud_ok, jnp.zeros(pad, bool)])
    return _Keyframe(frame.kp_points, frame.kp_ok, frame.descriptors, frame.lm_points,
                     frame.lm_ok, jnp.where(cloud_ok[:, None], cloud, 0), cloud_ok,
                     quaternion, position)


def _schedule(cfg: _JaxConfig, dtype) -> Array:
    a, b = cfg.icp_max_distance
    n = max(cfg.icp_iterations, 1)
    return jnp.asarray(np.geomspace(a, b, n), dtype)


@functools.partial(jit, static_argnames=("cfg", "metric"))
def _estimate(kf: _Keyframe, fr: _Frame, pred_q, pred_t, has_pred, index, cfg, metric
              ) -> _Estimate:
    dtype = fr.kp_points.dtype
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), index)
    # --- candidate (a): descriptor matches + landmarks, RANSAC
    m = match_descriptors(kf.descriptors, fr.descriptors, kf.kp_ok, fr.kp_ok, metric=metric,
                          ratio=cfg.ratio, mutual=True)
    ok_m = m.valid & kf.kp_ok & fr.kp_ok[m.index]
    src = jnp.concatenate([kf.kp_points, kf.lm_points])
    tgt = jnp.concatenate([fr.kp_points[m.index], fr.lm_points])
    lm_pair = kf.lm_ok & fr.lm_ok
    w = jnp.concatenate([ok_m.astype(dtype), cfg.landmark_weight * lm_pair.astype(dtype)])
    rs = ransac_align(key, src, tgt, w, num_iterations=cfg.ransac_iterations,
                      threshold=cfg.ransac_threshold)
    ok_a = (rs.status == ALIGN_OK) & (rs.num_inliers >= cfg.min_feature_inliers)
    # --- candidate (b): landmarks only
    la = align(kf.lm_points, fr.lm_points, lm_pair.astype(dtype))
    ok_b = (la.status == ALIGN_OK) & (jnp.sum(lm_pair) >= 4) & (la.rms < 0.02)
    # --- candidate (c): prediction
    qs = jnp.stack([rs.quaternion, la.quaternion, pred_q])
    ts = jnp.stack([rs.translation, la.translation, pred_t])
    cand_ok = jnp.stack([ok_a, ok_b, has_pred])
    n_src = jnp.sum(kf.cloud_ok)
    if cfg.icp == "none":
        best = jnp.argmax(cand_ok[:2])  # ransac preferred
        found = jnp.any(cand_ok[:2])
        q = qs[best]
        t = ts[best]
        inl = jnp.asarray(0, jnp.int32)
        rmse = jnp.asarray(jnp.nan, dtype)
        overlap = jnp.asarray(jnp.nan, dtype)
        accepted = found
        cand = jnp.where(found, best, -1)
    else:
        sched = _schedule(cfg, dtype)
        if cfg.icp == "projective":
            def run(q0, t0):
                return icp_projective(kf.cloud, fr.grid, fr.normals, _K(*fr.crop_k),
                                      source_valid=kf.cloud_ok, target_valid=fr.grid_ok,
                                      initial_rotation=q0, initial_translation=t0,
                                      num_iterations=cfg.icp_iterations,
                                      max_correspondence_distance=sched, tolerance=1e-5)
        else:  # brute-force nearest neighbours on every other grid sample (O(N M) per step)
            tgt_pts = fr.grid[::2, ::2].reshape(-1, 3)
            tgt_n = fr.normals[::2, ::2].reshape(-1, 3)
            tgt_ok = fr.grid_ok[::2, ::2].reshape(-1)

            def run(q0, t0):
                return icp_point_to_plane(kf.cloud, tgt_pts, tgt_n, source_valid=kf.cloud_ok,
                                          target_valid=tgt_ok, initial_rotation=q0,
                                          initial_translation=t0,
                                          num_iterations=cfg.icp_iterations,
                                          max_correspondence_distance=sched, tolerance=1e-5)

        n_lm = jnp.sum(lm_pair)
        tau = sched[-1]

        def judge(res):
            """Acceptance and ranking of ICP results (batched over candidates)."""
            icp_ok = (res.status == IcpStatus.OK) | (res.status == IcpStatus.NOT_CONVERGED)
            # landmark gate: point-to-plane ICP can slide along the face; a result that moves
            # the keyframe's landmarks far from the frame's is a wrong local minimum
            moved = (quat_rotate(res.rotation[..., None, :], kf.lm_points)
                     + res.translation[..., None, :])
            lm_d2 = jnp.sum((moved - fr.lm_points) ** 2, axis=-1)
            lm_rms = jnp.sqrt(jnp.sum(jnp.where(lm_pair, lm_d2, 0), -1) / jnp.maximum(n_lm, 1))
            usable = icp_ok & ((n_lm < 3) | (lm_rms <= cfg.landmark_gate))
            overlap = res.num_inliers.astype(dtype) / jnp.maximum(n_src, 1).astype(dtype)
            passed = usable & (overlap >= cfg.min_overlap) & (res.rmse <= cfg.max_rmse)
            quality = 1 - jnp.minimum(res.rmse / tau, 1) ** 2
            return usable, passed, overlap, res.num_inliers.astype(dtype) * quality

        # the first valid candidate in the order ransac, landmarks, prediction is refined; only
        # if its result fails the checks are all candidates refined (vmap) and the best kept
        first = jnp.argmax(cand_ok)
        res1 = run(qs[first], ts[first])
        _, passed1, _, _ = judge(res1)

        def single(_):
            return res1, first

        def every(_):
            res = jax.vmap(run)(qs, ts)
            usable, _, _, score = judge(res)
            best = jnp.argmax(jnp.where(usable & cand_ok, score, -jnp.inf))
            return jax.tree_util.tree_map(lambda x: x[best], res), best

        res, best = jax.lax.cond(passed1 & cand_ok[first], single, every, None)
        usable, passed, overlap, _ = judge(res)
        found = cand_ok[best] & usable
        q, t = res.rotation, res.translation
        inl, rmse = res.num_inliers, res.rmse
        accepted = found & passed
        cand = jnp.where(found, best, -1)
    return _Estimate(q, t, cand, ok_a | ok_b, jnp.sum(ok_m), rs.num_inliers, inl, rmse, overlap,
                     accepted)


# ---------------------------------------------------------------------------------- estimator
def _checked_reference(reference_pose) -> tuple[np.ndarray, np.ndarray]:
    """``(quaternion, position)`` as float64 arrays, or a ``ValueError`` naming the problem."""
    try:
        q, p = (np.asarray(x, np.float64) for x in reference_pose)
    except (TypeError, ValueError):
        raise ValueError("reference_pose must be (quaternion wxyz (4,), position m (3,)), got "
                         f"{reference_pose!r}") from None
    if q.shape != (4,) or p.shape != (3,):
        raise ValueError(f"reference_pose must be (quaternion (4,), position (3,)), got shapes "
                         f"{q.shape} and {p.shape}")
    if not (np_valid_quaternions(q) and np.isfinite(p).all()):
        raise ValueError(f"reference_pose must be finite with a non-zero quaternion, got "
                         f"quaternion {q} and position {p}")
    return q, p


class HeadPoseEstimator:
    """Stateful RGB-D head pose front-end (see the module docstring for the pipeline).

    Arguments:
        intrinsics: colour camera intrinsics (may also be given per frame).
        config: :class:`HeadPoseConfig`.
        detector: a :class:`phjax.vision.face_detection.FaceDetector` (default: one for
            ``config.backend``, from the model cache ``model_dir``); pass ``False`` to run
            without a detector (face regions from depth / tracking only).
        model_dir: model cache directory for the default detector.
        reference_pose: ``(quaternion wxyz, position m)`` of the head in the first accepted
            frame (camera frame); default: identity at the face centre (see module docstring).

    Example:
        >>> est = HeadPoseEstimator(frame.intrinsics)                        # doctest: +SKIP
        >>> res = est.process(frame.color, frame.depth, frame.timestamp)     # doctest: +SKIP
        >>> res.status, res.position, res.quaternion                         # doctest: +SKIP
    """

    def __init__(self, intrinsics: CameraIntrinsics | None = None,
                 config: HeadPoseConfig | None = None, *, detector: Any = None,
                 model_dir: Any = None, reference_pose: tuple[Any, Any] | None = None):
        self.config = HeadPoseConfig() if config is None else config
        self._jcfg = _JaxConfig.of(self.config)
        self.intrinsics = None if intrinsics is None else intrinsics.checked()
        if detector is None:
            from .face_detection import FaceDetector

            detector = FaceDetector(self.config.backend, model_dir=model_dir,
                                    detect_width=self.config.detect_width,
                                    score_threshold=self.config.min_face_score)
        self.detector = detector or None
        self._reference_pose = None
        self.reset(reference_pose)

    # ------------------------------------------------------------------ state
    def reset(self, reference_pose: tuple[Any, Any] | None = None) -> None:
        """Forget all keyframes and the last pose (``reference_pose`` as in the constructor).

        Raises:
            ValueError: a ``reference_pose`` that is not a finite quaternion (4,) of non-zero
                norm and a finite position (3,): it made every pose NaN, reported as OK.
        """
        if reference_pose is not None:
            self._reference_pose = _checked_reference(reference_pose)
        self._forget_keyframes()
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        #: orientation a re-acquired reference starts with (None: the first-frame rule)
        self._keep_q: np.ndarray | None = None
        self._frame_index = 0

    def _forget_keyframes(self) -> None:
        self.keyframes: list[_Keyframe] = []
        self._kf_quats: list[np.ndarray] = []
        self._confirmed = False  # keyframe 0 made from, or aligned with, a detected face
        self._failed_run = 0  # failed alignments in a row

    @property
    def num_keyframes(self) -> int:
        """Number of keyframes so far."""
        return len(self.keyframes)

    # ------------------------------------------------------------------ helpers
    def _result(self, t, status, **kw) -> HeadPoseResult:
        p, q = _nan_pose()
        return HeadPoseResult(float(t), p, q, HeadPoseStatus(status), **kw)

    def _tracked_box(self, intr: CameraIntrinsics) -> np.ndarray | None:
        if self._last is None or not self.keyframes:
            return None
        kf_i = self._nearest_keyframe(self._last[0])
        kf = self.keyframes[kf_i]
        cloud = np.asarray(kf.cloud)[np.asarray(kf.cloud_ok)]
        if cloud.shape[0] < 10:
            return None
        q_kf, t_kf = np.asarray(kf.quaternion, np.float64), np.asarray(kf.position, np.float64)
        q, t = self._last
        r_rel = _np_qmatrix(q) @ _np_qmatrix(q_kf).T
        p = cloud @ r_rel.T + (t - r_rel @ t_kf)
        p = p[p[:, 2] > 0.05]
        if p.shape[0] < 10:
            return None
        u = float(intr.fx) * p[:, 0] / p[:, 2] + float(intr.cx)
        v = float(intr.fy) * p[:, 1] / p[:, 2] + float(intr.cy)
        x0, x1, y0, y1 = u.min(), u.max(), v.min(), v.max()
        if x1 < 0 or y1 < 0 or x0 >= intr.width or y0 >= intr.height:
            return None
        return np.asarray([x0, y0, x1 - x0, y1 - y0], np.float32)

    def _nearest_keyframe(self, q: np.ndarray) -> int:
        angles = [_np_angle(q, qk) for qk in self._kf_quats]
        return int(np.argmin(angles))

    def _crop(self, depth: np.ndarray, box: np.ndarray, intr: CameraIntrinsics
              ) -> np.ndarray | None:
        """Crop origin (u0, v0) and step of the G x G grid around the face box."""
        cfg = self.config
        x0, y0, x1, y1 = expand_box(box, 0.6, depth.shape)
        patch = depth[y0:y1, x0:x1]
        zs = patch[(patch >= cfg.min_depth) & (patch <= cfg.max_depth)]
        if zs.size < 10:
            return None
        z = float(np.median(zs))
        side_px = cfg.crop_size * float(intr.fx) / z
        step = side_px / (cfg.crop_grid - 1)
        uc = box[0] + 0.5 * box[2]
        vc = box[1] + 0.5 * box[3]
        return np.asarray([uc - 0.5 * side_px, vc - 0.5 * side_px, step], np.float32)

    # ------------------------------------------------------------------ main entry
    def process_frame(self, frame: RGBDFrame) -> HeadPoseResult:
        """:meth:`process` on an :class:`~phjax.vision.rgbd_io.RGBDFrame`."""
        return self.process(frame.color, frame.depth, frame.timestamp, frame.intrinsics)

    def process(self, color: Any, depth: Any, t: float | None = None,
                intrinsics: Any = None) -> HeadPoseResult:
        """Estimate the head pose in one registered RGB-D frame.

        Arguments:
            color: ``uint8 (H, W, 3)`` BGR image.
            depth: ``(H, W)`` depth in metres registered to ``color`` (0 / NaN = missing).
            t: timestamp, s (default: frame index / 30).
            intrinsics: colour intrinsics (default: the constructor's): a
                :class:`~phjax.vision.rgbd_io.CameraIntrinsics` of the frame's size, or
                ``(fx, fy, cx, cy)`` (a sequence or an object with these attributes).

        Returns:
            A :class:`HeadPoseResult`; never raises for bad frame content: wrong colour /
            depth arrays and missing or invalid intrinsics (not finite ``fx, fy > 0``, finite
            ``cx, cy``; another image size) and a non-finite or non-numeric ``t`` give
            ``INVALID_INPUT`` (the result then has a NaN ``timestamp``).
        """
        t_start = time.perf_counter()
        cfg = self.config
        idx = self._frame_index
        self._frame_index += 1
        try:
            t = idx / 30.0 if t is None else float(t)
        except (TypeError, ValueError, OverflowError):  # not a number (it raised): no time
            t = float("nan")
        intr = intrinsics if intrinsics is not None else self.intrinsics
        checked = self._checked_inputs(color, depth, intr)
        if checked is None or not math.isfinite(t):  # a NaN time made an OK pose at NaN
            return self._result(t, HeadPoseStatus.INVALID_INPUT)
        color, depth, intr = checked
        n_valid = int(np.count_nonzero((depth >= cfg.min_depth) & (depth <= cfg.max_depth)))
        if n_valid < cfg.min_valid_depth:
            return self._result(t, HeadPoseStatus.NO_DEPTH)
        timings: dict[str, float] = {}

        # --- 1. face region
        t0 = time.perf_counter()
        face, source, box = self._find_face(color, depth, intr, idx)
        timings["detect"] = time.perf_counter() - t0
        if box is None:
            return self._result(t, HeadPoseStatus.NO_FACE, timings=timings)
        crop = self._crop(depth, box, intr)
        if crop is None:
            return self._result(t, HeadPoseStatus.NO_DEPTH, face=face, face_source=source,
                                face_box=box, timings=timings)

        # --- 2. observations: keypoints and landmarks, lifted with depth
        t0 = time.perf_counter()
        kps, lm_uv, lm_valid = self._features(color, face, box)
        timings["features"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        k4 = np.asarray([intr.fx, intr.fy, intr.cx, intr.cy], np.float32)
        fr = _observe(depth, k4, kps.uv, kps.valid, kps.descriptors, lm_uv, lm_valid, crop,
                      self._jcfg)
        common = {"face": face, "face_source": source, "face_box": box}

        # --- 3. first frame: reference keyframe
        def start_reference():
            q_ref, p_ref = self._start_reference(fr, idx, face is not None, self._keep_q)
            if q_ref is None:
                return self._result(t, HeadPoseStatus.NO_DEPTH, timings=timings, **common)
            timings["jax"] = time.perf_counter() - t0
            timings["total"] = time.perf_counter() - t_start
            return HeadPoseResult(t, p_ref.copy(), q_ref.copy(), HeadPoseStatus.OK, keyframe=0,
                                  is_keyframe=True, timings=timings, **common)

        if not self.keyframes:
            return start_reference()

        # --- 4. align to the nearest keyframe
        kf_i, est = self._align_to_keyframe(fr, idx)
        timings["jax"] = time.perf_counter() - t0
        info = {"num_matches": int(est.num_matches), "num_inliers": int(est.num_inliers),
                "icp_inliers": int(est.icp_inliers), "icp_rmse": float(est.icp_rmse),
                "candidate": _CANDIDATES[int(est.candidate)] if int(est.candidate) >= 0 else "",
                "keyframe": kf_i}
        if not bool(est.accepted):
            self._failed_run += 1
            n = cfg.reacquire_after
            if face is not None and (not self._confirmed or (n and self._failed_run >= n)):
                # a face the reference does not fit: start again at it, keeping the orientation
                # until a confirmed reference is made (this frame may have too little depth for
                # one: the next frame must not start by the first-frame rule, reference_pose)
                if self._confirmed and self._last is not None:
                    self._keep_q = self._last[0]
                self._forget_keyframes()
                return start_reference()
            # what failed: the correspondences (no RANSAC / landmark candidate) or the alignment
            status = (HeadPoseStatus.ALIGNMENT_FAILED if bool(est.any_measured)
                      else HeadPoseStatus.TOO_FEW_MATCHES)
            timings["total"] = time.perf_counter() - t_start
            return self._result(t, status, timings=timings, **common, **info)
        self._failed_run = 0
        self._confirmed = self._confirmed or face is not None
        if self._confirmed:
            self._keep_q = None

        # --- 5. absolute pose, keyframes
        kf = self.keyframes[kf_i]
        q_kf = np.asarray(kf.quaternion, np.float64)
        p_kf = np.asarray(kf.position, np.float64)
        q_rel = np.asarray(est.quaternion, np.float64)
        t_rel = np.asarray(est.translation, np.float64)
        q_abs = _canon(np_qmul(q_rel, q_kf))
        p_abs = _np_qmatrix(q_rel) @ p_kf + t_rel
        self._last = (q_abs, p_abs)
        is_kf = self._maybe_add_keyframe(fr, q_abs, p_abs, idx, face is not None,
                                         float(est.overlap))
        timings["total"] = time.perf_counter() - t_start
        return HeadPoseResult(t, p_abs, q_abs, HeadPoseStatus.OK, is_keyframe=is_kf,
                              timings=timings, **common, **info)

    # --- the parts of :meth:`process`

    def _checked_inputs(self, color: Any, depth: Any, intr: Any):
        """``(color, depth, intrinsics)`` as uint8 BGR, float32 metres (NaN -> 0) and checked
        :class:`CameraIntrinsics` of the frame's size, or None if invalid."""
        try:
            color = np.asarray(color)
            depth = np.asarray(depth, dtype=np.float32)
            bad = (color.ndim != 3 or color.shape[-1] != 3 or color.dtype != np.uint8
                   or depth.shape != color.shape[:2] or intr is None)
            if not bad:
                if not isinstance(intr, CameraIntrinsics):  # (fx, fy, cx, cy) or attributes
                    vals = ([getattr(intr, a) for a in ("fx", "fy", "cx", "cy")]
                            if hasattr(intr, "fx") else list(intr))
                    fx, fy, cx, cy = (float(v) for v in vals)
                    intr = CameraIntrinsics(fx, fy, cx, cy, width=depth.shape[1],
                                            height=depth.shape[0])
                bad = intr.checked().shape != depth.shape
        except (TypeError, ValueError, AttributeError):
            bad = True
        if bad:
            return None
        return color, np.where(np.isfinite(depth), depth, 0).astype(np.float32), intr

    def _find_face(self, color: np.ndarray, depth: np.ndarray, intr: CameraIntrinsics,
                   idx: int):
        """``(face, source, box)``: the detector every ``detect_interval`` frames (or when
        lost), else the box tracked from the last pose, else the depth fallback."""
        cfg = self.config
        face, source, box = None, "none", None
        if self.detector is not None and (idx % cfg.detect_interval == 0 or self._last is None):
            # (a detector passed in may give a non-finite box: no face)
            faces = [f for f in self.detector.detect(color) if np.isfinite(f.box).all()]
            if faces:
                face = faces[0]
                box, source = face.box, "detector"
        if box is None:
            box = self._tracked_box(intr)
            source = "tracked" if box is not None else source
        if box is None and cfg.depth_fallback:
            box = head_box_from_depth(depth, intr, min_depth=cfg.min_depth,
                                      max_depth=cfg.max_depth)
            source = "depth" if box is not None else source
        return face, source, (None if box is None else np.asarray(box, np.float32))

    def _features(self, color: np.ndarray, face, box: np.ndarray):
        """Keypoints in the face box and the detector's five landmarks (if detected)."""
        cfg = self.config
        kps: Keypoints = detect_keypoints(color, box, method=cfg.feature_method,
                                          max_keypoints=cfg.max_keypoints,
                                          box_scale=cfg.box_scale,
                                          fast_threshold=cfg.fast_threshold)
        if face is not None:
            lm_uv = face.landmarks.astype(np.float32)
            lm_valid = np.isfinite(lm_uv).all(-1)
            lm_uv = np.where(lm_valid[:, None], lm_uv, 0).astype(np.float32)
        else:
            lm_uv, lm_valid = np.zeros((5, 2), np.float32), np.zeros(5, bool)
        return kps, lm_uv, lm_valid

    def _start_reference(self, fr, idx: int, detected: bool, q_keep=None):
        """Make the first keyframe (from a detected face or not; with orientation ``q_keep``
        when re-acquiring); ``(q_ref, p_ref)``, or ``(None, None)`` without depth."""
        cfg = self.config
        if not bool(fr.centre_ok):
            return None, None
        if self._reference_pose is not None and q_keep is None:
            q_ref = _canon(np.asarray(self._reference_pose[0], np.float64))
            p_ref = np.asarray(self._reference_pose[1], np.float64)
        else:
            c = np.asarray(fr.centre, np.float64)
            q_ref = np.asarray([1.0, 0, 0, 0]) if q_keep is None else _canon(q_keep)
            p_ref = c + cfg.head_center_offset * c / max(np.linalg.norm(c), 1e-9)
        kf = _make_keyframe(fr, jnp.asarray(q_ref, np.float32), jnp.asarray(p_ref, np.float32),
                            np.int32(idx), self._jcfg)
        if int(jnp.sum(kf.cloud_ok)) < 30:
            return None, None
        self.keyframes.append(kf)
        self._kf_quats.append(q_ref)
        self._last = (q_ref, p_ref)
        self._confirmed = detected or self.detector is None
        if self._confirmed:
            self._keep_q = None
        return q_ref, p_ref

    def _align_to_keyframe(self, fr, idx: int):
        """Align the frame to the keyframe nearest the last pose (:func:`_estimate`), with
        the last pose as the prediction; ``(keyframe index, estimate)``."""
        q_last, p_last = self._last if self._last is not None else (self._kf_quats[0], None)
        kf_i = self._nearest_keyframe(q_last)
        kf = self.keyframes[kf_i]
        q_kf = np.asarray(kf.quaternion, np.float64)
        p_kf = np.asarray(kf.position, np.float64)
        if self._last is not None:
            q_pred = np_qmul(q_last, np_qconj(q_kf))
            t_pred = p_last - _np_qmatrix(q_pred) @ p_kf
            has_pred = True
        else:
            q_pred, t_pred, has_pred = np.asarray([1.0, 0, 0, 0]), np.zeros(3), False
        metric = "hamming" if self.config.feature_method == "orb" else "l2"
        est = _estimate(kf, fr, jnp.asarray(q_pred, np.float32), jnp.asarray(t_pred, np.float32),
                        np.bool_(has_pred), np.int32(idx), self._jcfg, metric)
        return kf_i, jax.device_get(est)

    def _maybe_add_keyframe(self, fr, q_abs, p_abs, idx: int, has_face: bool,
                            overlap: float) -> bool:
        """Add a keyframe when the head has turned ``keyframe_angle`` from every keyframe
        (with a detected face and good overlap, up to ``max_keyframes``)."""
        cfg = self.config
        nearest = min(_np_angle(q_abs, qk) for qk in self._kf_quats)
        if (np.degrees(nearest) > cfg.keyframe_angle and len(self.keyframes) < cfg.max_keyframes
                and has_face and overlap >= 1.25 * cfg.min_overlap):
            new = _make_keyframe(fr, jnp.asarray(q_abs, np.float32),
                                 jnp.asarray(p_abs, np.float32), np.int32(idx), self._jcfg)
            if int(jnp.sum(new.cloud_ok)) >= 30:
                self.keyframes.append(new)
                self._kf_quats.append(q_abs)
                return True
        return False

    def run(self, frames: Iterable[RGBDFrame], *, progress: bool = False
            ) -> list[HeadPoseResult]:
        """Process a sequence of frames (optionally with a tqdm progress bar)."""
        it = frames
        if progress:
            try:
                from tqdm.auto import tqdm

                it = tqdm(frames, total=len(frames) if hasattr(frames, "__len__") else None,
                          unit="frame")
            except ImportError:
                pass
        return [self.process_frame(f) for f in it]


# ------------------------------------------------------------------------- generic RGB-D pair
class RelativePose(NamedTuple):
    """Rigid motion between two RGB-D frames: points of ``a`` map to ``b`` as ``R p + t``.

    For a static scene and a moving camera, ``R, t`` is ``T_b^-1 T_a`` of the camera-to-world
    poses ``T``. ``status`` is an :class:`phjax.vision.alignment.AlignmentStatus` code of the feature
    RANSAC. The ``icp_*`` fields describe the optional dense refinement (``icp_status`` is an
    :class:`phjax.vision.icp.IcpStatus` code of the last pyramid level, ``-1`` when no refinement
    ran; ``icp_inliers`` / ``icp_rmse`` its correspondences and RMS point-to-plane residual,
    m); ``refined`` tells whether the returned motion is the refined one.
    """

    quaternion: np.ndarray
    translation: np.ndarray
    status: int
    num_matches: int
    num_inliers: int
    refined: bool = False
    icp_status: int = -1
    icp_inliers: int = 0
    icp_rmse: float = float("nan")

    @property
    def rotation(self) -> np.ndarray:
        """The rotation matrix."""
        return _np_qmatrix(self.quaternion)


@dataclass(frozen=True)
class DenseRefinement:
    """Settings of the dense ICP stage of :func:`rgbd_relative_pose` (``refine="icp"``).

    Point-to-plane ICP with projective association (:func:`phjax.vision.icp.icp_projective`) of
    frame ``a``'s depth points onto frame ``b``'s organised cloud, coarse to fine: level ``k``
    subsamples ``b``'s depth image by ``levels[k][0]`` (target cloud, normals from image
    neighbours ``normal_radius`` samples away) and ``a``'s by ``levels[k][1]`` (source points),
    runs ``iterations[k]`` Gauss-Newton steps with the correspondence distance decreasing
    geometrically over ``distances[k] = (start, end)`` (m), and hands its motion to the next
    level. ``loss`` / ``loss_scale`` (m): robust loss of the residuals (the redescending Tukey
    loss ignores the parts of the scene seen by one frame only); depths beyond ``max_depth``
    (m) are not used (Kinect noise grows like ``z^2``).

    ``feature_weight`` (``refine="joint"``: 1.0; ``None``: dense only) adds the feature
    RANSAC's inliers as fixed point pairs to every level's Gauss-Newton objective
    (``point_pairs`` of :func:`phjax.vision.icp.icp_projective`), each weighted by the inverse
    covariance of its 3-D difference: lifted keypoints have ``pixel_noise`` (px) on ``u, v``
    and ``depth_noise z^2`` (m) along the ray in both frames (Kinect v1, Khoshelham & Elberink
    2012). The dense residuals are weighted by ``1 / sigma^2``, ``sigma`` their IRLS scale
    estimate, so ``feature_weight = 1`` weighs both terms by their noise models alone (with
    the correlation correction of ``depth_window`` below); larger values trust the features
    more.

    ``feature_residual="pixel"`` uses 2-D reprojection residuals instead (``pixel_pairs`` of
    :func:`phjax.vision.icp.icp_projective`): ``a``'s lifted keypoint, moved by the motion and
    projected into ``b``, against the matched keypoint's pixel there, with the covariance
    ``pixel_noise^2 I`` plus ``a``'s lifted covariance propagated through the projection (at
    the RANSAC motion). It relies on ``b``'s accurate pixel position instead of its noisy far
    depth. ``feature_matches="all"`` passes every descriptor match (ratio test + mutual
    check), not only the RANSAC inliers, with a Tukey loss of scale ``feature_loss_scale``
    (standard deviations) that is widened to the dense correspondence distance of the
    current iteration (``pair_gate`` / ``pixel_gate``): matches are re-selected every
    iteration as the schedule shrinks, so a wrong RANSAC consensus is not locked in.

    ``depth_window = (w, h)`` (pixels; ``None``: independent residuals) corrects the dense
    term's information for correlated depth noise: a Kinect-class structured-light sensor
    computes each depth value by matching a correlation window of about 9 x 9 or 9 x 7 IR
    pixels (ROS ``kinect_calibration`` technical notes), so neighbouring depths share most of
    their error and a level whose source points are ``s`` pixels apart has about
    ``max(1, w h / s^2)`` times fewer independent dense residuals than points. The feature
    terms' weight is multiplied by that factor per level (default ``(9, 7)``, the smaller
    window: the least correction; ``levels`` default: factors 1, 3.9 and 15.75).
    """

    levels: tuple[tuple[int, int], ...] = ((4, 8), (2, 4), (1, 2))
    iterations: tuple[int, ...] = (15, 10, 8)
    distances: tuple[tuple[float, float], ...] = ((0.2, 0.05), (0.05, 0.02), (0.02, 0.01))
    loss: str = "tukey"
    loss_scale: float = 0.03
    max_depth: float = 6.0
    normal_radius: int = 2
    feature_weight: float | None = None
    depth_noise: float = 1.425e-3
    pixel_noise: float = 1.0
    feature_residual: str = "point"
    feature_matches: str = "inliers"
    feature_loss_scale: float = 3.0
    depth_window: tuple[int, int] | None = (9, 7)

    def __post_init__(self):
        if self.feature_residual not in ("point", "pixel"):
            raise ValueError("feature_residual must be 'point' or 'pixel', got "
                             f"{self.feature_residual!r}")
        if self.feature_matches not in ("inliers", "all"):
            raise ValueError("feature_matches must be 'inliers' or 'all', got "
                             f"{self.feature_matches!r}")
        if self.feature_weight is not None and not self.feature_weight >= 0:
            raise ValueError(f"feature_weight must be None or >= 0, got {self.feature_weight}")
        if not (len(self.levels) == len(self.iterations) == len(self.distances) >= 1):
            raise ValueError("levels, iterations and distances need one entry per level")
        for st, ss in self.levels:
            if int(st) < 1 or int(ss) < 1:
                raise ValueError(f"strides must be >= 1, got {(st, ss)}")
        if self.depth_window is not None and (len(self.depth_window) != 2
                                              or min(self.depth_window) < 1):
            raise ValueError(f"depth_window must be None or (width, height) >= 1 pixels, got "
                             f"{self.depth_window!r}")

    def feature_factor(self, source_stride: int) -> float:
        """Factor on the feature terms' weight at a level whose source points are
        ``source_stride`` pixels apart (the dense residuals per depth correlation window)."""
        if self.depth_window is None:
            return 1.0
        w, h = self.depth_window
        return max(1.0, w * h / source_stride ** 2)


#: the named refinements of :func:`rgbd_relative_pose`
_REFINE_PRESETS = {
    "reproj": DenseRefinement(feature_weight=1.0, feature_residual="pixel", feature_matches="all"),
    "icp": DenseRefinement(),
    "joint": DenseRefinement(feature_weight=1.0),
}


@functools.partial(jit, static_argnames=("metric", "iterations", "depth_power",
                                             "max_matches"))
def _pair_core(key, pa, oka, da, pb, okb, db, ratio, threshold, metric, iterations, depth_power,
               max_matches):
    m = match_descriptors(da, db, oka, okb, metric=metric, ratio=ratio, mutual=True)
    ok = m.valid & oka & okb[m.index]
    # compact: the matched rows first (static size), so RANSAC scores only real candidates
    order = jnp.argsort(~ok, stable=True)[:max_matches]
    src = pa[order]
    tgt = pb[m.index[order]]
    ok = ok[order]
    z = jnp.maximum(src[:, 2], tgt[:, 2])
    w = jnp.where(ok, 1.0 / jnp.maximum(z, 1e-3) ** depth_power, 0)
    # hypotheses are drawn with probability ~ w (near points first); the refit is weighted
    res = ransac_align(key, src, tgt, w, num_iterations=iterations, threshold=threshold)
    return res, jnp.sum(ok), src, tgt


def _lifted_covariance(p: np.ndarray, intr, cfg: DenseRefinement) -> np.ndarray:
    """Covariances ``(k, 3, 3)`` of keypoints lifted to 3-D, ``p = z K^-1 (u, v, 1)``: pixel
    noise ``cfg.pixel_noise`` (px) on ``u, v`` and depth noise ``cfg.depth_noise z^2`` (m)."""
    z = np.maximum(p[:, 2], 1e-6)
    su = cfg.pixel_noise * z / intr.fx
    sv = cfg.pixel_noise * z / intr.fy
    sz = cfg.depth_noise * z ** 2
    ray = p / z[:, None]  # dp/dz
    cov = sz[:, None, None] ** 2 * ray[:, :, None] * ray[:, None, :]
    cov[:, 0, 0] += su ** 2
    cov[:, 1, 1] += sv ** 2
    return cov


@functools.partial(jit, static_argnames=("cfg",))
def _dense_refine(depth_a, depth_b, k4, q0, t0, schedules, pairs, cfg: DenseRefinement):
    """Coarse-to-fine projective point-to-plane ICP of ``a``'s depth onto ``b``'s (with the
    fixed feature pairs in every level, or None: ``pairs = (src, tgt, information)``, ``tgt``
    3-D points or pixels of ``b`` as ``cfg.feature_residual``)."""
    robust = cfg.feature_matches == "all"
    sparse = {}
    if pairs is not None and cfg.feature_residual == "point":
        sparse = {"point_pairs": pairs, "pair_loss": "tukey" if robust else "l2",
                  "pair_loss_scale": cfg.feature_loss_scale, "pair_gate": robust}
    elif pairs is not None:
        sparse = {"pixel_pairs": pairs, "pixel_intrinsics": k4,
                  "pixel_loss": "tukey" if robust else "l2",
                  "pixel_loss_scale": cfg.feature_loss_scale, "pixel_gate": robust}
    def clip(d):
        return jnp.where(jnp.isfinite(d) & (d > 0) & (d <= cfg.max_depth), d, 0)

    depth_a, depth_b = clip(depth_a), clip(depth_b)
    q, t, res = q0, t0, None
    for (st, ss), it, sched in zip(cfg.levels, cfg.iterations, schedules):
        if sparse:  # correlated depth noise: fewer independent dense residuals than points
            sparse["pair_weight" if "point_pairs" in sparse else "pixel_weight"] = \
                cfg.feature_factor(ss)
        # pixel (i, j) of a stride-s subsampling is pixel (s i, s j): u / s = (fx / s) x / z + cx / s
        kt = k4 / st
        tp = backproject(depth_b[::st, ::st], kt)
        tn = estimate_normals(tp, radius=cfg.normal_radius)
        sp = backproject(depth_a[::ss, ::ss], k4 / ss).reshape(-1, 3)
        res = icp_projective(sp, tp, tn, kt, source_valid=sp[:, 2] > 0, initial_rotation=q,
                             initial_translation=t, num_iterations=int(it),
                             max_correspondence_distance=sched, loss=cfg.loss,
                             loss_scale=cfg.loss_scale, **sparse)
        # a failed level (too few correspondences, degenerate) returns its initial guess
        q, t = res.rotation, res.translation
    return q, t, res.status, res.num_inliers, res.rmse


def rgbd_relative_pose(
    frame_a: RGBDFrame, frame_b: RGBDFrame, *, box_a: Any = None, box_b: Any = None,
    method: str = "orb", max_keypoints: int = 4000, ratio: float = 0.8,
    ransac_threshold: float = 0.03, ransac_iterations: int = 1024, max_matches: int = 512,
    depth_power: float = 4.0,
    min_depth: float = 0.3, max_depth: float = 8.0, edge_abs: float = 0.01,
    edge_rel: float = 0.01, fast_threshold: int = 10, seed: int = 0,
    refine: str | DenseRefinement | None = "reproj",
) -> RelativePose:
    """Rigid motion between two registered RGB-D frames from keypoint matches lifted to 3-D.

    Keypoints (optionally in boxes) are matched (ratio test + mutual check), lifted through
    depth (invalid / edge depth rejected) and aligned with RANSAC; the final refit weights each
    inlier by ``1 / z^depth_power`` (triangulation depth noise grows like ``z^2``, so its
    variance like ``z^4``).

    ``refine`` adds a dense stage started from the RANSAC motion (skipped when RANSAC failed;
    its result is kept only when the last level reports ``OK`` or ``NOT_CONVERGED``, budget
    used up, the normal case; otherwise the RANSAC motion is returned, ``refined=False``):
    coarse-to-fine point-to-plane ICP (:func:`phjax.vision.icp.icp_projective`, JAX) of all of
    ``a``'s depth onto ``b``'s, with a shrinking correspondence distance and a Tukey loss, and
    the feature matches in the same Gauss-Newton objective (see :class:`DenseRefinement`):

    * ``"reproj"`` (default): 2-D reprojection residuals of *all* descriptor matches (``b``'s
      accurate pixel positions instead of its noisy far depth; ``pixel_pairs`` of
      :func:`phjax.vision.icp.icp_projective`) with a Tukey loss whose gate shrinks with the dense
      distance schedule, so matches are re-selected every iteration and a wrong RANSAC
      consensus does not lock in; both terms weighted by their noise models, the dense one
      corrected for the sensor's depth correlation window (``depth_window``).
    * ``"joint"``: the RANSAC inliers as 3-D point pairs with lifted-keypoint covariances.
    * ``"icp"``: the dense depth alone (converges to the *depth-consistent* motion).
    * ``None``: RANSAC alone (fastest; depends on the seed when few matches are consistent).

    Measured on the slambook2 frames (Kinect, 0.2-0.7 m baselines, RANSAC seeds 0-7, errors
    against the given, approximate poses; ``experiments/slambook_refinement.py``): the default
    gives the same pose for every seed, 1 -> 2 1.23 degrees / 3.2 cm, 2 -> 3 0.70 / 2.8,
    3 -> 4 0.67 / 4.6, 4 -> 5 0.19 / 1.7; RANSAC alone 1.4-4.7 degrees / 4.9-18 cm on 1 -> 2 and
    2.9-20 cm on 3 -> 4; ``"icp"`` 7.3-7.5 cm on 3 -> 4 (``cv2.Odometry`` DEPTH lands 7.2 cm
    from the given pose as well, its colour odometry 1-3 cm: there the depth and the given
    pose disagree); without the correlation correction (``depth_window=None``) ``"reproj"``
    gives 5.4 cm on 3 -> 4, ``"joint"`` 6.1-6.5 cm (4.1-5.7 cm with it). The refinement adds
    about 0.1-0.2 s per pair on 2 shared CPU cores (after a one-off compilation; RANSAC alone
    0.13-0.2 s).

    Returns:
        A :class:`RelativePose` mapping points of ``a`` into ``b``.

    Raises:
        ValueError: for a bad ``refine``, different intrinsics with ``refine``, or a frame
            whose depth, colour image and intrinsics differ in size.
    """
    for name, fr in (("frame_a", frame_a), ("frame_b", frame_b)):
        color, depth = np.shape(fr.color), np.shape(fr.depth)
        size = tuple(getattr(fr.intrinsics, "shape", depth))
        if len(depth) != 2 or depth != color[:2] or size != depth:
            raise ValueError(f"{name}: depth {depth}, colour {color} and intrinsics {size} "
                             "sizes (height, width) differ")
    if isinstance(refine, str):
        if refine not in _REFINE_PRESETS:
            raise ValueError("refine must be None, 'reproj', 'icp', 'joint' or a "
                             f"DenseRefinement, got {refine!r}")
        refine = _REFINE_PRESETS[refine]
    elif refine is not None and not isinstance(refine, DenseRefinement):
        raise ValueError("refine must be None, 'reproj', 'icp', 'joint' or a DenseRefinement, "
                         f"got {refine!r}")
    kw = {"method": method, "max_keypoints": max_keypoints, "fast_threshold": fast_threshold}
    ka = detect_keypoints(frame_a.color, box_a, **kw)
    kb = detect_keypoints(frame_b.color, box_b, **kw)
    lk = {"min_depth": min_depth, "max_depth": max_depth, "edge_abs": edge_abs,
          "edge_rel": edge_rel}
    pa, oka = lift_keypoints(ka.uv, frame_a.depth, frame_a.intrinsics, ka.valid, **lk)
    pb, okb = lift_keypoints(kb.uv, frame_b.depth, frame_b.intrinsics, kb.valid, **lk)
    res, n, fsrc, ftgt = _pair_core(
        jax.random.PRNGKey(seed), pa, oka, jnp.asarray(ka.descriptors), pb, okb,
                        jnp.asarray(kb.descriptors), ratio, ransac_threshold,
                        "hamming" if method == "orb" else "l2", int(ransac_iterations),
                        float(depth_power), min(int(max_matches), int(max_keypoints)))
    res = jax.device_get(res)
    q = _canon(np.asarray(res.quaternion, np.float64))
    t = np.asarray(res.translation, np.float64)
    out = RelativePose(q, t, int(res.status), int(n), int(res.num_inliers))
    if refine is None or int(res.status) != ALIGN_OK:
        return out
    intr = frame_b.intrinsics
    if (frame_a.intrinsics.fx, frame_a.intrinsics.fy, frame_a.intrinsics.cx,
            frame_a.intrinsics.cy) != (intr.fx, intr.fy, intr.cx, intr.cy):
        raise ValueError("refine needs both frames taken with the same intrinsics")
    dt = jnp.float32
    k4 = jnp.asarray([intr.fx, intr.fy, intr.cx, intr.cy], dt)
    schedules = tuple(jnp.asarray(np.geomspace(d0, d1, int(it)), dt)
                      for (d0, d1), it in zip(refine.distances, refine.iterations))
    pairs = None
    if refine.feature_weight is not None:
        # the RANSAC inliers (or all matches), weighted by the inverse covariance of their
        # 3-D difference or of their reprojection error in b
        fsrc, ftgt = np.asarray(fsrc, np.float64), np.asarray(ftgt, np.float64)
        use = (fsrc[:, 2] > 0) & (ftgt[:, 2] > 0) & (np.arange(len(fsrc)) < int(n))
        if refine.feature_matches == "inliers":
            use &= np.asarray(res.inlier_mask)
        rot = _np_qmatrix(q)
        cov_a = rot @ _lifted_covariance(fsrc, intr, refine) @ rot.T
        if refine.feature_residual == "point":
            cov = cov_a + _lifted_covariance(ftgt, intr, refine)
            eye, tgt = np.eye(3), ftgt
        else:  # pixels of b: a's covariance through the projection + b's pixel noise
            x = fsrc @ rot.T + t
            z = np.maximum(x[:, 2], 1e-6)
            jac = np.zeros((len(x), 2, 3))
            jac[:, 0, 0] = intr.fx / z
            jac[:, 0, 2] = -intr.fx * x[:, 0] / z ** 2
            jac[:, 1, 1] = intr.fy / z
            jac[:, 1, 2] = -intr.fy * x[:, 1] / z ** 2
            eye = np.eye(2)
            cov = jac @ cov_a @ jac.transpose(0, 2, 1) + refine.pixel_noise ** 2 * eye
            zb = np.maximum(ftgt[:, 2], 1e-6)  # b's keypoint pixels (exact: p = z K^-1 uv1)
            tgt = np.stack([intr.fx * ftgt[:, 0] / zb + intr.cx,
                            intr.fy * ftgt[:, 1] / zb + intr.cy], -1)
        use &= np.isfinite(cov).all(axis=(1, 2))
        cov = np.where(use[:, None, None], cov, eye)
        info = np.where(use[:, None, None], refine.feature_weight * np.linalg.inv(cov), 0)
        pairs = (jnp.asarray(fsrc, dt), jnp.asarray(tgt, dt), jnp.asarray(info, dt))
    rq, rt, status, inl, rmse = jax.device_get(_dense_refine(
        jnp.asarray(frame_a.depth, dt), jnp.asarray(frame_b.depth, dt), k4,
        jnp.asarray(q, dt), jnp.asarray(t, dt), schedules, pairs, refine))
    good = int(status) in (IcpStatus.OK, IcpStatus.NOT_CONVERGED)
    if good:
        q, t = _canon(np.asarray(rq, np.float64)), np.asarray(rt, np.float64)
    return out._replace(quaternion=q, translation=t, refined=good, icp_status=int(status),
                        icp_inliers=int(inl), icp_rmse=float(rmse))
