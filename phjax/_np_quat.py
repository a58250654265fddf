"""Float64 NumPy twins of a few quaternion operations (wxyz), for the I/O, metric and baseline
code that works outside JAX (so its precision does not depend on JAX's x64 setting)."""

from __future__ import annotations

import numpy as np


def np_qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product (``w = a b - u.v``, ``(x, y, z) = a v + b u + u x v``), written per
    component: ``np.cross`` on large batches costs as much as the rest of the product."""
    a, u1, u2, u3 = (p[..., k] for k in range(4))
    b, v1, v2, v3 = (q[..., k] for k in range(4))
    return np.stack([a * b - (u1 * v1 + u2 * v2 + u3 * v3),
                     a * v1 + b * u1 + (u2 * v3 - u3 * v2),
                     a * v2 + b * u2 + (u3 * v1 - u1 * v3),
                     a * v3 + b * u3 + (u1 * v2 - u2 * v1)], axis=-1)


def np_any_part(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(...)`` whether each pose of ``p (..., 3)``, ``q (..., 4)`` has a finite position or a
    finite orientation: a measured frame of one-part (3-DoF or position-only) data too."""
    return np.isfinite(np.asarray(q)).all(-1) | np.isfinite(np.asarray(p)).all(-1)


def np_valid_quaternions(q: np.ndarray) -> np.ndarray:
    """``(...)`` whether each quaternion of ``q (..., 4)`` is a measurement the filter uses:
    finite and of non-zero norm (as ``phjax.tracking.kalman``'s own check)."""
    q = np.asarray(q)
    finite = np.isfinite(q).all(-1)
    return finite & (np.sum(np.where(finite[..., None], q, 0.0) ** 2, -1) > 0)


def np_qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def np_reflect_z(q: np.ndarray) -> np.ndarray:
    """The rotation ``S R S`` for ``S = diag(1, 1, -1)`` (a frame with ``z`` flipped):
    ``(w, -x, -y, z)``."""
    return q * np.array([1.0, -1.0, -1.0, 1.0])


def np_qnormalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (last axis); NaN where a quaternion has no orientation (zero, or not
    finite), without NumPy's warnings. ``q / |q|`` where the squared norm is in the dtype's
    range (so normal inputs round exactly as a plain division does); a tiny or huge quaternion
    (squared norm beyond the smallest or largest float) is scaled by its largest component
    first instead of becoming a division by zero or by infinity."""
    q = np.asarray(q)
    if not np.issubdtype(q.dtype, np.floating):
        q = q.astype(np.float64)
    info = np.finfo(q.dtype)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore", under="ignore"):
        n = np.linalg.norm(q, axis=-1, keepdims=True)
        plain = (n > np.sqrt(info.tiny) / info.eps) & (n < np.sqrt(info.max) * info.eps)
        scale = np.max(np.abs(q), axis=-1, keepdims=True)
        ok = np.isfinite(scale) & (scale > 0)
        s = q / np.where(ok & ~plain, scale, 1)  # q itself where plain: its norm is n
        return np.where(ok, s / np.linalg.norm(s, axis=-1, keepdims=True), np.nan)


def np_rotvec(q: np.ndarray) -> np.ndarray:
    """Shortest-arc rotation vector (angle in ``[0, pi]`` times axis) of unit quaternions."""
    q = np.where(q[..., :1] < 0, -q, q)
    n = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2 * np.arctan2(n, q[..., :1])
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(n > 1e-12, angle / np.where(n > 0, n, 1), 2.0)
    return scale * q[..., 1:]


def np_from_rotvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternion of rotation vectors (angle ``|r|`` about ``r / |r|``)."""
    half = 0.5 * np.linalg.norm(r, axis=-1, keepdims=True)
    sinc = np.sinc(half / np.pi)  # sin(half) / half
    return np.concatenate([np.cos(half), 0.5 * sinc * r], axis=-1)


def np_axis_quat(axis: int, angle: np.ndarray) -> np.ndarray:
    """Quaternions of rotations by ``angle`` (rad) about basis axis 0/1/2."""
    angle = np.asarray(angle, dtype=np.float64)
    q = np.zeros(angle.shape + (4,))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


def np_hemisphere(q: np.ndarray) -> np.ndarray:
    """NumPy twin of :func:`phjax.quaternion.quat_hemisphere_continuity` along axis 0."""
    if q.shape[0] < 2:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    s = np.concatenate([[1.0], np.cumprod(np.where(dots < 0, -1.0, 1.0))])
    return q * s[:, None]
