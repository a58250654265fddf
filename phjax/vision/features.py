"""Keypoints in an image region, descriptor matching, and lifting to 3-D through depth.

Detection (:func:`detect_keypoints`) runs OpenCV's ORB (default) or SIFT on a crop around a
region of interest and returns **fixed-size, padded** arrays (:class:`Keypoints`), so that the
JAX stages after it compile once: :func:`match_descriptors` (brute-force distances as one
matrix product, Lowe's ratio test and a mutual-nearest check, all jitted), and
:func:`lift_keypoints` (back-projection through a depth image with invalid and edge depth
rejected).

Descriptors
-----------
* ORB: 256-bit binary strings stored as ``uint8 (K, 32)``; the Hamming distance is computed
  from the ``+-1`` expansion of the bits, ``d = (256 - a . b) / 2`` (exact in float32).
* SIFT: ``float32 (K, 128)``; Euclidean distance.

Depth validity (:func:`lift_keypoints`)
---------------------------------------
A keypoint's depth ``z`` (nearest pixel) is accepted when it is finite, within
``[min_depth, max_depth]``, and the 3x3 neighbourhood is a surface, not an edge: at least
``min_valid`` of its 9 pixels valid and ``max |z_nb - z| <= edge_abs + edge_rel z^2`` over them
(the ``z^2`` term follows the depth noise / quantisation of triangulating sensors such as the
Kinect).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._jit import jit

__all__ = [
    "Keypoints",
    "Matches",
    "detect_keypoints",
    "match_descriptors",
    "lift_keypoints",
    "expand_box",
    "METHODS",
]

METHODS = ("orb", "sift")


def _require(module: str):
    """Import an optional dependency with an actionable error message."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{module} is needed here; install the vision extra: "
                          "pip install 'phjax[vision]' (opencv-python-headless, kornia, torch)"
                          ) from e


class Keypoints(NamedTuple):
    """Fixed-size (padded) keypoints of one image.

    Attributes:
        uv: ``float32 (K, 2)`` pixel coordinates ``(u, v)`` in the full image (0 where padded).
        descriptors: ``uint8 (K, 32)`` (ORB) or ``float32 (K, 128)`` (SIFT); 0 where padded.
        valid: ``bool (K,)``, ``False`` for padding.
        method: ``"orb"`` or ``"sift"``.
    """

    uv: np.ndarray
    descriptors: np.ndarray
    valid: np.ndarray
    method: str

    @property
    def count(self) -> int:
        """Number of real (non-padded) keypoints."""
        return int(np.count_nonzero(self.valid))


class Matches(NamedTuple):
    """Result of :func:`match_descriptors` for each query descriptor ``i``.

    Attributes:
        index: ``(Ka,)`` index of the matched train descriptor (0 where ``valid`` is false).
        valid: ``(Ka,)`` the match passed every test.
        distance: ``(Ka,)`` distance to the best train descriptor (inf where none).
    """

    index: Int[Array, " ka"]
    valid: Bool[Array, " ka"]
    distance: Float[Array, " ka"]


def expand_box(box: ArrayLike, scale: float, shape: tuple[int, int]) -> np.ndarray:
    """Scale an ``(x, y, w, h)`` box about its centre and clip it to an image ``(H, W)``.

    Returns:
        ``int (x0, y0, x1, y1)`` (exclusive end), possibly empty.
    """
    x, y, w, h = (float(v) for v in np.asarray(box, np.float64).reshape(4))
    cx, cy = x + 0.5 * w, y + 0.5 * h
    hw, hh = 0.5 * w * scale, 0.5 * h * scale
    x0 = int(np.clip(np.floor(cx - hw), 0, shape[1]))
    y0 = int(np.clip(np.floor(cy - hh), 0, shape[0]))
    x1 = int(np.clip(np.ceil(cx + hw), 0, shape[1]))
    y1 = int(np.clip(np.ceil(cy + hh), 0, shape[0]))
    return np.asarray([x0, y0, max(x1, x0), max(y1, y0)])


@functools.lru_cache(maxsize=8)
def _cv_detector(method: str, max_keypoints: int, fast_threshold: int):
    cv2 = _require("cv2")

    if method == "orb":
        return cv2.ORB_create(nfeatures=max_keypoints, scaleFactor=1.2, nlevels=6,
                              edgeThreshold=15, fastThreshold=fast_threshold, patchSize=31)
    return cv2.SIFT_create(nfeatures=max_keypoints)


def detect_keypoints(
    image: np.ndarray,
    box: ArrayLike | None = None,
    *,
    method: str = "orb",
    max_keypoints: int = 512,
    box_scale: float = 1.0,
    fast_threshold: int = 7,
    mask: np.ndarray | None = None,
) -> Keypoints:
    """Detect keypoints (OpenCV ORB or SIFT) in a region and pad them to ``max_keypoints``.

    Detection runs on a crop around the region (with a 32-pixel margin so descriptors near the
    region's border are complete), which is much faster than a masked full-image search.

    Arguments:
        image: ``uint8 (H, W, 3)`` BGR or ``(H, W)`` grey image.
        box: region ``(x, y, w, h)`` in pixels (``None`` = whole image).
        method: ``"orb"`` (default) or ``"sift"``.
        max_keypoints: the fixed size K of the output (the strongest keypoints are kept).
        box_scale: enlarge the box about its centre by this factor.
        fast_threshold: ORB's FAST threshold (lower finds more corners on low-texture faces).
        mask: optional ``(H, W)`` mask; only keypoints where it is non-zero are kept.

    Returns:
        :class:`Keypoints` with ``K = max_keypoints`` rows.
    """
    cv2 = _require("cv2")

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 BGR or grey image, got {img.dtype} {img.shape}")
    h, w = img.shape
    k = int(max_keypoints)
    dim, ddt = (32, np.uint8) if method == "orb" else (128, np.float32)
    uv = np.zeros((k, 2), np.float32)
    desc = np.zeros((k, dim), ddt)
    valid = np.zeros(k, bool)
    if box is None:
        x0, y0, x1, y1 = 0, 0, w, h
    else:
        x0, y0, x1, y1 = expand_box(box, box_scale, (h, w))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return Keypoints(uv, desc, valid, method)
    m = 32
    cx0, cy0, cx1, cy1 = max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h)
    crop = img[cy0:cy1, cx0:cx1]
    roi = np.zeros(crop.shape, np.uint8)
    roi[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0] = 255
    if mask is not None:
        roi &= (np.asarray(mask)[cy0:cy1, cx0:cx1] != 0).astype(np.uint8) * 255
    det = _cv_detector(method, k, int(fast_threshold))
    kps, des = det.detectAndCompute(crop, roi)
    if des is None or len(kps) == 0:
        return Keypoints(uv, desc, valid, method)
    resp = np.asarray([kp.response for kp in kps])
    order = np.argsort(-resp, kind="stable")[:k]
    n = order.size
    pts = np.asarray([kps[i].pt for i in order], np.float32)
    uv[:n] = pts + np.asarray([cx0, cy0], np.float32)
    desc[:n] = np.asarray(des)[order].astype(ddt)
    valid[:n] = True
    return Keypoints(uv, desc, valid, method)


# ------------------------------------------------------------------------------------ matching
def _pairwise_distance(a: Array, b: Array, metric: str) -> Array:
    if metric == "hamming":
        bits_a = jnp.unpackbits(a.astype(jnp.uint8), axis=-1).astype(jnp.float32) * 2 - 1
        bits_b = jnp.unpackbits(b.astype(jnp.uint8), axis=-1).astype(jnp.float32) * 2 - 1
        nbits = bits_a.shape[-1]
        return 0.5 * (nbits - bits_a @ bits_b.T)
    a = a.astype(jnp.float32)
    b = b.astype(jnp.float32)
    d2 = (jnp.sum(a * a, -1)[:, None] + jnp.sum(b * b, -1)[None, :] - 2 * a @ b.T)
    return jnp.sqrt(jnp.maximum(d2, 0))


def match_descriptors(
    query: ArrayLike,
    train: ArrayLike,
    query_valid: Bool[ArrayLike, " ka"] | None = None,
    train_valid: Bool[ArrayLike, " kb"] | None = None,
    *,
    metric: str = "hamming",
    ratio: float = 0.8,
    mutual: bool = True,
    max_distance: float | None = None,
) -> Matches:
    """Brute-force nearest-neighbour matching with Lowe's ratio test and a mutual check.

    Query ``i`` matches train ``j = argmin_j d(i, j)`` when ``d_best < ratio * d_second``
    (the second-best train descriptor; skipped when fewer than two train descriptors are valid),
    ``i`` is also the nearest query of ``j`` (``mutual``), and ``d_best <= max_distance``.
    Jittable (``metric``, ``mutual`` static); padded rows are excluded by the masks.

    Arguments:
        query: ``(Ka, D)`` descriptors (``uint8`` packed bits for ``"hamming"``).
        train: ``(Kb, D)`` descriptors.
        query_valid, train_valid: masks of real (non-padded) rows (default all). Rows with a
            non-finite value are invalid too (``"l2"``).
        metric: ``"hamming"`` (ORB) or ``"l2"`` (SIFT).
        ratio: ratio-test threshold (``1`` disables it).
        mutual: require mutual nearest neighbours.
        max_distance: absolute distance limit (``None`` = none).

    Returns:
        :class:`Matches` over the query rows.
    """
    if metric not in ("hamming", "l2"):
        raise ValueError(f"metric must be 'hamming' or 'l2', got {metric!r}")
    return _match(jnp.asarray(query), jnp.asarray(train),
                  None if query_valid is None else jnp.asarray(query_valid, bool),
                  None if train_valid is None else jnp.asarray(train_valid, bool),
                  metric, ratio, mutual, max_distance)


@functools.partial(jit, static_argnames=("metric", "mutual"))
def _match(query, train, query_valid, train_valid, metric, ratio, mutual, max_distance):
    ka, kb = query.shape[0], train.shape[0]
    qv = jnp.ones(ka, bool) if query_valid is None else query_valid
    tv = jnp.ones(kb, bool) if train_valid is None else train_valid
    if ka == 0 or kb == 0:
        return Matches(jnp.zeros(ka, jnp.int32), jnp.zeros(ka, bool), jnp.full(ka, jnp.inf))
    if metric == "l2":  # a non-finite descriptor is invalid (its NaN distances would win argmin)
        qv = qv & jnp.all(jnp.isfinite(query), axis=-1)
        tv = tv & jnp.all(jnp.isfinite(train), axis=-1)
    d = _pairwise_distance(query, train, metric)
    d = jnp.where(qv[:, None] & tv[None, :] & ~jnp.isnan(d), d, jnp.inf)
    # best and second best by two min-reductions (lax.top_k followed by slicing is lowered to
    # a full row sort on CPU, ~15x slower here)
    idx = jnp.argmin(d, axis=1).astype(jnp.int32)
    best = jnp.min(d, axis=1)
    second = jnp.min(jnp.where(jnp.arange(kb)[None, :] == idx[:, None], jnp.inf, d), axis=1)
    ratio_ok = (best < ratio * second) | ~jnp.isfinite(second)
    ok = qv & jnp.isfinite(best) & ratio_ok
    if mutual:
        back = jnp.argmin(d, axis=0)  # nearest query of each train row
        ok = ok & (back[idx] == jnp.arange(ka))
    if max_distance is not None:
        ok = ok & (best <= max_distance)
    return Matches(jnp.where(ok, idx, 0), ok, best)


# --------------------------------------------------------------------------------------- depth
def _depth_at(depth: Array, uv: Array) -> tuple[Array, Array]:
    """Nearest-pixel depth and the 3x3 neighbourhood (``(K,)``, ``(K, 9)``); 0 outside."""
    h, w = depth.shape
    u = jnp.round(uv[..., 0]).astype(jnp.int32)
    v = jnp.round(uv[..., 1]).astype(jnp.int32)
    du = jnp.asarray([-1, 0, 1, -1, 0, 1, -1, 0, 1], jnp.int32)
    dv = jnp.asarray([-1, -1, -1, 0, 0, 0, 1, 1, 1], jnp.int32)
    uu = u[..., None] + du
    vv = v[..., None] + dv
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    nb = depth[jnp.clip(vv, 0, h - 1), jnp.clip(uu, 0, w - 1)]
    nb = jnp.where(inside & jnp.isfinite(nb), nb, 0)
    return nb[..., 4], nb


def lift_keypoints(
    uv: Float[ArrayLike, "k 2"],
    depth: Float[ArrayLike, "h w"],
    intrinsics: Any,
    valid: Bool[ArrayLike, " k"] | None = None,
    *,
    min_depth: float = 0.2,
    max_depth: float = 8.0,
    edge_abs: float = 0.01,
    edge_rel: float = 0.01,
    min_valid: int = 7,
) -> tuple[Float[Array, "k 3"], Bool[Array, " k"]]:
    """Back-project pixels through a (registered) depth image, rejecting bad depth.

    Arguments:
        uv: pixel coordinates ``(u, v)``; non-finite rows are not ``ok``.
        depth: depth in metres (0 / NaN = missing), registered to the image of ``uv``.
        intrinsics: an object with ``fx, fy, cx, cy`` (e.g. ``CameraIntrinsics``).
        valid: input mask (padding), default all.
        min_depth, max_depth: accepted depth range, m.
        edge_abs, edge_rel: depth-edge test ``max |z_nb - z| <= edge_abs + edge_rel z^2`` over
            the valid pixels of the 3x3 neighbourhood.
        min_valid: minimum number of valid pixels in the 3x3 neighbourhood (holes next to a
            pixel usually mean an occlusion boundary).

    Returns:
        ``(points (K, 3), ok (K,))`` camera-frame points (0 where not ``ok``).
    """
    uv = jnp.asarray(uv)
    depth = jnp.asarray(depth)
    dtype = jnp.result_type(uv.dtype, depth.dtype, jnp.float32)
    k = uv.shape[0]
    valid = jnp.ones(k, bool) if valid is None else jnp.asarray(valid, bool)
    fx, fy, cx, cy = (jnp.asarray(getattr(intrinsics, a), dtype) for a in ("fx", "fy", "cx",
                                                                           "cy"))
    return _lift(uv.astype(dtype), depth.astype(dtype), valid, fx, fy, cx, cy,
                 min_depth, max_depth, edge_abs, edge_rel, min_valid)


@jit
def _lift(uv, depth, valid, fx, fy, cx, cy, min_depth, max_depth, edge_abs, edge_rel, min_valid):
    valid = valid & jnp.all(jnp.isfinite(uv), axis=-1)
    uv = jnp.where(valid[..., None], uv, 0)  # (finite values and gradients where not ok)
    z, nb = _depth_at(depth, uv)
    nb_ok = (nb >= min_depth) & (nb <= max_depth)
    spread = jnp.max(jnp.where(nb_ok, jnp.abs(nb - z[..., None]), 0), axis=-1)
    ok = (valid & nb_ok[..., 4] & (jnp.sum(nb_ok, axis=-1) >= min_valid)
          & (spread <= edge_abs + edge_rel * z * z))
    zs = jnp.where(ok, z, 0)
    pts = jnp.stack([(uv[..., 0] - cx) * zs / fx, (uv[..., 1] - cy) * zs / fy, zs], axis=-1)
    return pts, ok
