"""Synthetic RGB-D head sequences with ground truth, generated procedurally (no downloads).

A textured, head-shaped implicit surface (:class:`HeadModel`: an ellipsoidal skull with a nose,
eye sockets and eyeballs, brow ridge, cheekbones, lips, chin and ears; skin, hair, brows, eyes
and lips painted in a texture map with freckle-like spots for keypoint detectors) is ray cast
in front of a textured wall by a pinhole camera. Head motion comes from
:func:`phjax.synthetic_head_motion`. Colour and depth are registered (same camera), like an
aligned Kinect / TUM RGB-D frame.

Frames and conventions
----------------------
* **Camera frame**: ``x`` right, ``y`` down, ``z`` forward (optical axis), metres. Pixel
  ``(row i, column j)`` has its centre at ``(u, v) = (j, i)``; ``u = fx x / z + cx``.
* **Head frame** (model coordinates, as in :mod:`phjax.motion.simulate`): origin at the head centre
  (centre of the skull ellipsoid), ``x`` towards the subject's right ear, ``y`` up, ``-z``
  forward (out of the face).
* **Ground-truth pose**: ``head_position`` = head-frame origin in camera coordinates and
  ``head_quaternion`` (``wxyz``) rotating head-frame vectors into the camera frame, so a model
  point ``X`` appears at ``head_position + R(head_quaternion) X``. The subject faces the camera:
  at rest ``head_quaternion ~ (0, 0, 0, 1)`` (180 degrees about the optical axis).
* **World frame** of :func:`~phjax.motion.simulate.synthetic_head_motion` (``x`` right, ``y`` up,
  ``-z`` forward of the subject): the camera sits ``camera_distance`` in front of the resting
  eye position, looking back at the subject (camera axes ``(-x, -y, +z)`` of the world).
* ``color`` is **RGB** ``uint8`` (use ``color[..., ::-1]`` for OpenCV's BGR), ``depth`` is
  ``float32`` metres along ``z`` with ``0`` = invalid.

Rendering
---------
Per pixel a ray ``X(s) = s (x', y', 1)`` (so ``s`` is the depth) is intersected with the wall
plane analytically and with the head surface ``g(X) = |X| - R(X / |X|) = 0`` (``R`` the radial
function of the star-shaped head; ``g > 0`` outside) by uniform sampling between an outer and an
inner bounding ellipsoid followed by regula falsi (Illinois) refinement, all in JAX (``jit``,
float32), on a static-size window around the projected head (the static wall is rendered once
per sequence). Shading is Lambertian (normal = gradient of ``g``) with ambient light. A 640x480
frame with noise costs about 0.2 s of CPU time on a slow 2-core machine, 0.12 s of wall time
(XLA spreads it over the cores), after one compilation of about 7 s per image and window size.
The renderer compiles with ``phjax._jit.IMAGE_COMPILER_OPTIONS`` (XLA's fusion emitters and
full optimisation: 1.9 x faster than phjax's default options for this image-sized program,
and the same program under any ``XLA_FLAGS``).

Depth noise (``depth_noise=True``) follows a Kinect-v1-like model: Gaussian disparity noise
(so ``sigma_z = 1.425e-3 z^2`` m, Khoshelham & Elberink 2012), disparity quantisation in 1/8
pixel for a 7.5 cm baseline (depth steps ``~2.9e-3 z^2``), dropped pixels at depth
discontinuities (probability 0.5) and randomly (0.2 %), and a valid range of 0.4-4.5 m.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._jit import IMAGE_COMPILER_OPTIONS, jit
from .._np_quat import np_from_rotvec, np_qconj, np_qmul, np_rotvec
from .icp import PinholeIntrinsics
from ..quaternion import quat_rotate
from ..motion.simulate import _NECK_TO_EYES, synthetic_head_motion

__all__ = [
    "LANDMARK_NAMES",
    "HeadModel",
    "SyntheticRGBDFrame",
    "SyntheticRGBDSequence",
    "add_depth_noise",
    "render_rgbd",
    "synthetic_rgbd_sequence",
]

LANDMARK_NAMES = (
    "right_eye",  # subject's right eye (appears on the image left), pupil on the surface
    "left_eye",
    "nose_tip",
    "mouth_right",
    "mouth_left",
    "chin",
    "right_ear",
    "left_ear",
)

# camera axes in the world frame of synthetic_head_motion: (-x, -y, +z) = 180 deg about z
_Q_CAM_FROM_WORLD = np.array([0.0, 0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------- head model
def _direction(lon, lat):
    """Head-frame unit vector at longitude ``lon`` (towards +x, the subject's right) and
    latitude ``lat`` (up); ``(0, 0)`` is straight out of the face (``-z``)."""
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    return np.stack([np.sin(lon) * np.cos(lat), np.sin(lat), -np.cos(lon) * np.cos(lat)], -1)


def _lonlat(d):
    """Inverse of :func:`_direction` for (not necessarily unit) vectors (JAX, NaN-free)."""
    lon = jnp.arctan2(d[..., 0], -d[..., 2])
    lat = jnp.arctan2(d[..., 1], jnp.sqrt(d[..., 0] ** 2 + d[..., 2] ** 2))
    return lon, lat


# (lon, lat, sigma_lon, sigma_lat, amplitude m); mirrored features listed once with lon > 0
_BUMPS = [
    (0.00, -0.12, 0.07, 0.20, 0.011, False),   # nose ridge
    (0.00, -0.33, 0.10, 0.09, 0.020, False),   # nose tip
    (0.11, -0.38, 0.06, 0.05, 0.006, True),    # nostril wings
    (0.34, 0.06, 0.17, 0.10, -0.011, True),    # eye sockets
    (0.34, 0.05, 0.10, 0.06, 0.007, True),     # eyeballs
    (0.30, 0.25, 0.26, 0.07, 0.006, True),     # brow ridges
    (0.58, -0.15, 0.16, 0.12, 0.006, True),    # cheekbones
    (0.00, -0.555, 0.24, 0.06, 0.007, False),  # upper lip
    (0.00, -0.655, 0.20, 0.05, 0.006, False),  # lower lip
    (0.00, -0.92, 0.22, 0.12, 0.008, False),   # chin
    (1.57, 0.00, 0.10, 0.22, 0.022, True),     # ears
]

_EYE = (0.34, 0.05)
_NOSE_TIP = (0.0, -0.33)
_MOUTH_CORNER = (0.24, -0.60)
_CHIN = (0.0, -0.95)
_EAR = (1.57, 0.0)


def _bump_arrays():
    rows = []
    for lon, lat, su, sv, amp, mirror in _BUMPS:
        rows.append((lon, lat, su, sv, amp))
        if mirror:
            rows.append((-lon, lat, su, sv, amp))
    a = np.array(rows)
    lon, lat = a[:, 0], a[:, 1]
    centre = _direction(lon, lat)
    e1 = np.stack([np.cos(lon), np.zeros_like(lon), np.sin(lon)], -1)  # d/dlon
    e2 = np.stack([-np.sin(lon) * np.sin(lat), np.cos(lat), np.cos(lon) * np.sin(lat)], -1)
    return centre, e1, e2, 1 / a[:, 2:4], a[:, 4]


def _smoothstep(e0, e1, x):
    u = np.clip((x - e0) / (e1 - e0), 0, 1)
    return u * u * (3 - 2 * u)


def _make_texture(height: int = 512, width: int = 1024, seed: int = 7) -> np.ndarray:
    """Albedo map in longitude/latitude (rows: lat from +pi/2 down to -pi/2), float32 RGB."""
    rng = np.random.default_rng(seed)
    lat = (0.5 - (np.arange(height) + 0.5) / height) * np.pi
    lon = ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi
    lon, lat = np.meshgrid(lon, lat)
    alon = np.abs(lon)

    def value_noise(cells_x, cells_y, octave_seed):
        g = np.random.default_rng(octave_seed).uniform(-1, 1, (cells_y + 1, cells_x + 1))
        g[:, -1] = g[:, 0]  # periodic in longitude
        x = (lon / (2 * np.pi) + 0.5) * cells_x
        y = (0.5 - lat / np.pi) * cells_y
        i, j = np.clip(np.floor(y).astype(int), 0, cells_y - 1), np.floor(x).astype(int) % cells_x
        fy, fx = y - i, x - np.floor(x)
        fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
        top = g[i, j] * (1 - fx) + g[i, j + 1] * fx
        bot = g[i + 1, j] * (1 - fx) + g[i + 1, j + 1] * fx
        return top * (1 - fy) + bot * fy

    noise = sum(value_noise(8 * 2**k, 4 * 2**k, seed + k) * 0.5**k for k in range(5))
    skin = np.array([0.86, 0.64, 0.52])
    col = skin * (1 + 0.06 * noise[..., None])
    # rosy cheeks, slightly darker jaw
    for s in (1, -1):
        cheek = np.exp(-0.5 * (((lon - s * 0.55) / 0.18) ** 2 + ((lat + 0.28) / 0.14) ** 2))
        col = col * (1 - 0.08 * cheek[..., None]) + 0.08 * cheek[..., None] * np.array(
            [0.85, 0.45, 0.42])

    # freckles / pores: many small dark and light spots (keypoints for ORB / SIFT), drawn as
    # impulses convolved (FFT, periodic) with Gaussians of three sizes
    spots = np.zeros((height, width))
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    for sigma_px, count in ((1.2, 1800), (2.0, 900), (3.0, 300)):
        imp = np.zeros((height, width))
        ii = rng.integers(0, height, count)
        jj = rng.integers(0, width, count)
        np.add.at(imp, (ii, jj), rng.choice([-0.22, -0.14, 0.10], count))
        kern = np.exp(-2 * (np.pi * sigma_px) ** 2 * (fx * fx + fy * fy))  # unit-peak Gaussian
        spots += np.real(np.fft.ifft2(np.fft.fft2(imp) * kern)) * (2 * np.pi * sigma_px**2)
    col = col * (1 + np.clip(spots, -0.4, 0.3)[..., None])

    def paint(col, mask, colour):
        return col * (1 - mask[..., None]) + mask[..., None] * np.asarray(colour)

    def ellipse(lo, la, a, b, soft):
        r = np.sqrt(((lon - lo) / a) ** 2 + ((lat - la) / b) ** 2)
        return 1 - _smoothstep(1 - soft, 1 + soft, r)

    for s in (1, -1):
        # eyes: sclera, iris, pupil, upper lid line
        lo, la = s * _EYE[0], _EYE[1]
        col = paint(col, ellipse(lo, la, 0.12, 0.045, 0.15), [0.93, 0.92, 0.90])
        col = paint(col, ellipse(lo, la, 0.045, 0.045, 0.15), [0.30, 0.20, 0.12])
        col = paint(col, ellipse(lo, la, 0.02, 0.02, 0.2), [0.03, 0.03, 0.03])
        lid = ellipse(lo, la + 0.035, 0.13, 0.018, 0.3) * (lat > la)
        col = paint(col, 0.85 * lid, [0.25, 0.15, 0.12])
        # eyebrows: an arc above the eye
        arc = la + 0.19 - 0.35 * (lon - lo - s * 0.03) ** 2
        brow = (1 - _smoothstep(0.012, 0.03, np.abs(lat - arc))) * (np.abs(lon - lo) < 0.2)
        brow *= 1 - _smoothstep(0.14, 0.2, np.abs(lon - lo))
        col = paint(col, 0.9 * brow, [0.20, 0.12, 0.08])
        # nostrils
        col = paint(col, 0.9 * ellipse(s * 0.06, -0.40, 0.035, 0.02, 0.3), [0.30, 0.16, 0.14])
    # lips and the mouth line
    lips = ellipse(0.0, -0.60, 0.25, 0.07, 0.2)
    col = paint(col, 0.85 * lips, [0.70, 0.32, 0.32])
    mouth = (1 - _smoothstep(0.006, 0.014, np.abs(lat + 0.60 + 0.04 * lon**2))) * (
        1 - _smoothstep(0.20, 0.25, alon))
    col = paint(col, 0.9 * mouth, [0.25, 0.08, 0.08])
    # hair: cap above a hairline that falls towards the back of the head
    hairline = 0.62 - 0.25 * _smoothstep(0.6, 1.3, alon) - 0.6 * _smoothstep(1.7, 2.4, alon)
    hair = _smoothstep(-0.02, 0.04, lat - hairline - 0.03 * value_noise(64, 32, seed + 11))
    streaks = value_noise(256, 16, seed + 12) + 0.5 * value_noise(512, 32, seed + 13)
    hair_col = np.array([0.22, 0.14, 0.09]) * (1 + 0.35 * streaks[..., None])
    col = col * (1 - hair[..., None]) + hair[..., None] * hair_col
    return np.clip(col, 0, 1).astype(np.float32)


class HeadModel(eqx.Module):
    """A star-shaped, textured head surface (see the module docstring; head-frame metres).

    The surface is ``|X| = R(X / |X|)`` with ``R`` a base ellipsoid radius (longer at the back
    and bottom, a narrower jaw) plus anisotropic Gaussian bumps on the sphere of directions.

    Attributes:
        landmarks: ``(len(LANDMARK_NAMES), 3)`` surface landmarks (head frame), see
            :data:`LANDMARK_NAMES`.
        eye_centre: midpoint of the two eye landmarks (head frame); this is the point whose
            trajectory :func:`~phjax.motion.simulate.synthetic_head_motion` generates.
        texture: albedo in longitude/latitude, ``(512, 1024, 3)`` float32 in ``[0, 1]``.
    """

    axes: Float[Array, "5"]  # x, y up, y down, z front, z back (m)
    jaw_narrowing: float = eqx.field(static=True)
    bump_centre: Float[Array, "k 3"]
    bump_e1: Float[Array, "k 3"]
    bump_e2: Float[Array, "k 3"]
    bump_inv_sigma: Float[Array, "k 2"]
    bump_amp: Float[Array, " k"]
    inner_axes: Float[Array, "3"]
    outer_axes: Float[Array, "3"]
    landmarks: Float[Array, "l 3"]
    eye_centre: Float[Array, "3"]
    texture: Float[Array, "th tw 3"]

    def __init__(self, texture_seed: int = 7):
        self.axes = jnp.asarray([0.078, 0.112, 0.122, 0.097, 0.106], jnp.float32)
        self.jaw_narrowing = 0.15
        c, e1, e2, inv_s, amp = _bump_arrays()
        self.bump_centre = jnp.asarray(c, jnp.float32)
        self.bump_e1 = jnp.asarray(e1, jnp.float32)
        self.bump_e2 = jnp.asarray(e2, jnp.float32)
        self.bump_inv_sigma = jnp.asarray(inv_s, jnp.float32)
        self.bump_amp = jnp.asarray(amp, jnp.float32)
        # bounding ellipsoids: scale factors checked on a dense grid of directions
        lon, lat = np.meshgrid(np.linspace(-np.pi, np.pi, 721), np.linspace(-1.57, 1.57, 361))
        d = _direction(lon, lat).reshape(-1, 3)
        r = self._radius_xyz(d[:, 0], d[:, 1], d[:, 2], xp=np)
        ax = np.asarray(self.axes, np.float64)
        box = np.array([ax[0], max(ax[1], ax[2]), max(ax[3], ax[4])])
        inner0 = np.array([ax[0] * (1 - self.jaw_narrowing), min(ax[1], ax[2]), min(ax[3],
                                                                                  ax[4])])
        r_in = 1 / np.sqrt(np.sum((d / inner0) ** 2, -1))
        r_out = 1 / np.sqrt(np.sum((d / box) ** 2, -1))
        self.inner_axes = jnp.asarray(inner0 * 0.97 * np.min(r / r_in), jnp.float32)
        self.outer_axes = jnp.asarray(box * 1.03 * np.max(r / r_out), jnp.float32)
        lm_dirs = _direction(
            [_EYE[0], -_EYE[0], _NOSE_TIP[0], _MOUTH_CORNER[0], -_MOUTH_CORNER[0], _CHIN[0],
             _EAR[0], -_EAR[0]],
            [_EYE[1], _EYE[1], _NOSE_TIP[1], _MOUTH_CORNER[1], _MOUTH_CORNER[1], _CHIN[1],
             _EAR[1], _EAR[1]],
        )
        lm = self._radius_xyz(lm_dirs[:, 0], lm_dirs[:, 1], lm_dirs[:, 2], xp=np)[:, None] * lm_dirs
        self.landmarks = jnp.asarray(lm, jnp.float32)
        self.eye_centre = 0.5 * (self.landmarks[0] + self.landmarks[1])
        self.texture = jnp.asarray(_make_texture(seed=texture_seed))

    # -- geometry (JAX, broadcasting over leading axes)
    def _radius_xyz(self, x, y, z, xp=jnp):
        """Radial function of unit direction components (elementwise; the hot path). ``xp``:
        ``jax.numpy`` (traced, the arrays' dtype) or ``numpy`` (float64 reference)."""
        if xp is np:
            cast = lambda a: np.asarray(a, np.float64)
        else:
            cast = lambda a: a.astype(x.dtype)
        ax = cast(self.axes)
        ay = xp.where(y > 0, ax[1], ax[2])
        az = xp.where(z < 0, ax[3], ax[4])
        narrow = 1 - self.jaw_narrowing * xp.clip(-y, 0, 1) ** 2
        r = 1 / xp.sqrt((x / (ax[0] * narrow)) ** 2 + (y / ay) ** 2 + (z / az) ** 2)
        # bumps: compactly supported (1 - r^2 / 9)^4 ~ exp(-r^2 / 2) in tangent coordinates;
        # support 3 sigma < 90 degrees, so the front-hemisphere test w > 0 is continuous.
        # Unrolled elementwise code (structure of arrays) is several times faster on CPU than
        # a (points, 3) @ (3, bumps) product.
        c, amp, inv = cast(self.bump_centre), cast(self.bump_amp), cast(self.bump_inv_sigma)
        e1, e2 = cast(self.bump_e1) * inv[:, :1], cast(self.bump_e2) * inv[:, 1:]
        for k in range(c.shape[0]):
            w = c[k, 0] * x + c[k, 1] * y + c[k, 2] * z
            u = e1[k, 0] * x + e1[k, 1] * y + e1[k, 2] * z
            v = e2[k, 0] * x + e2[k, 1] * y + e2[k, 2] * z
            prof = xp.maximum(1 - (u * u + v * v) * (1 / 9), 0)
            prof = prof * prof
            r = r + amp[k] * xp.where(w > 0, prof * prof, 0)
        return r

    def _implicit_xyz(self, x, y, z):
        n = jnp.sqrt(jnp.maximum(x * x + y * y + z * z, 1e-30))
        return n - self._radius_xyz(x / n, y / n, z / n)

    def radius(self, d: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
        """Radial function ``R(d)`` (m) for directions ``d`` (normalised internally)."""
        d = jnp.asarray(d)
        d = d / jnp.sqrt(jnp.maximum(jnp.sum(d * d, -1, keepdims=True), 1e-30))
        return self._radius_xyz(d[..., 0], d[..., 1], d[..., 2])

    def implicit(self, points: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
        """``g(X) = |X| - R(X / |X|)`` (m, head frame): 0 on the surface, > 0 outside."""
        p = jnp.asarray(points)
        return self._implicit_xyz(p[..., 0], p[..., 1], p[..., 2])

    def surface_point(self, d: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
        """The surface point in direction ``d`` (head frame)."""
        d = jnp.asarray(d)
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        return self.radius(d)[..., None] * d

    def sample_surface(self, num: int, seed: int = 0, *, face_only: bool = False) -> np.ndarray:
        """``num`` surface points (head frame, float64 NumPy), uniform in direction; with
        ``face_only`` within 60 degrees of the face direction ``-z``."""
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(8 * num if face_only else num, 3))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        if face_only:
            d = d[-d[:, 2] > np.cos(np.deg2rad(60))][:num]
        return self.radius_np(d)[:, None] * d

    def radius_np(self, d: np.ndarray) -> np.ndarray:
        """Float64 NumPy twin of :meth:`radius`."""
        d = np.asarray(d, np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return self._radius_xyz(d[..., 0], d[..., 1], d[..., 2], xp=np)

    def implicit_np(self, points: np.ndarray) -> np.ndarray:
        """Float64 NumPy twin of :meth:`implicit`."""
        p = np.asarray(points, np.float64)
        return np.linalg.norm(p, axis=-1) - self.radius_np(p)

    def landmark(self, name: str) -> Float[Array, "3"]:
        """A landmark by name (see :data:`LANDMARK_NAMES`), head frame."""
        return self.landmarks[LANDMARK_NAMES.index(name)]


@functools.lru_cache(maxsize=4)
def _default_model(texture_seed: int = 7) -> HeadModel:
    return HeadModel(texture_seed)


# ------------------------------------------------------------------------------ rendering
def _ray_ellipsoid(o, d, axes):
    """Entry/exit parameters of rays ``o + s d`` through an axis-aligned ellipsoid."""
    oo, dd = o / axes, d / axes
    a = jnp.sum(dd * dd, -1)
    b = jnp.sum(oo * dd, -1)
    c = jnp.sum(oo * oo, -1) - 1
    disc = b * b - a * c
    hit = disc > 0
    sq = jnp.sqrt(jnp.where(hit, disc, 0))
    return (-b - sq) / a, (-b + sq) / a, hit


def _bilinear(tex, x, y, wrap_x: bool):
    """Sample ``tex (h, w, c)`` at continuous texel coordinates (centres at integers)."""
    h, w = tex.shape[:2]
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)
    if wrap_x:
        xa, xb = x0 % w, (x0 + 1) % w
    else:
        xa, xb = jnp.clip(x0, 0, w - 1), jnp.clip(x0 + 1, 0, w - 1)
    ya, yb = jnp.clip(y0, 0, h - 1), jnp.clip(y0 + 1, 0, h - 1)
    top = tex[ya, xa] * (1 - fx) + tex[ya, xb] * fx
    bot = tex[yb, xa] * (1 - fx) + tex[yb, xb] * fx
    return top * (1 - fy) + bot * fy


def _wall_texture(seed: int = 3, size: int = 256) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.array([0.78, 0.76, 0.71])
    g = rng.uniform(-1, 1, (size // 16 + 1, size // 16 + 1))
    yy, xx = np.meshgrid(np.arange(size) / 16, np.arange(size) / 16, indexing="ij")
    i, j = np.floor(yy).astype(int), np.floor(xx).astype(int)
    fy, fx = yy - i, xx - j
    low = (g[i, j] * (1 - fx) + g[i, j + 1] * fx) * (1 - fy) + (
        g[i + 1, j] * (1 - fx) + g[i + 1, j + 1] * fx) * fy
    fine = rng.uniform(-1, 1, (size, size))
    tex = base * (1 + 0.05 * low[..., None] + 0.03 * fine[..., None])
    # a few darker panels (picture frames) for texture on the background
    for _ in range(6):
        y0, x0 = rng.integers(0, size - 40, 2)
        hh, ww = rng.integers(15, 40, 2)
        tex[y0:y0 + hh, x0:x0 + ww] *= rng.uniform(0.6, 0.9)
    return np.clip(tex, 0, 1).astype(np.float32)


@functools.lru_cache(maxsize=1)
def _wall_tex() -> np.ndarray:
    return _wall_texture()


# unit vector towards the light (camera frame): above left of the camera
_LIGHT = np.array([-0.35, -0.55, -1.0]) / np.linalg.norm([-0.35, -0.55, -1.0])


@functools.partial(jit, static_argnames=("height", "width"),
                   options=IMAGE_COMPILER_OPTIONS)
def _wall_jit(wall_tex, intr, wall, *, height, width):
    """Colour (float, [0, 1]) and depth of the textured background plane ``n . X = d``."""
    f32 = jnp.float32
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    rx = ((jnp.arange(width, dtype=f32) - cx) / fx)[None, :]
    ry = ((jnp.arange(height, dtype=f32) - cy) / fy)[:, None]
    wn, wd = wall[:3], wall[3]
    depth = wd / (wn[0] * rx + wn[1] * ry + wn[2])
    wx, wy = depth * rx, depth * ry  # 8 mm texels in plane coordinates
    color = 0.9 * _bilinear(wall_tex, wx / 0.008 + 128, wy / 0.008 + 128, wrap_x=True)
    return color, depth


@functools.partial(jit, static_argnames=("crop", "n_march", "n_refine"),
                   options=IMAGE_COMPILER_OPTIONS)
def _render_jit(model, wall_color, wall_depth, position, quaternion, intr, crop_origin, *,
                crop, n_march, n_refine):
    """Composite the head, ray cast in a ``crop`` x ``crop`` window, over the wall images."""
    f32 = jnp.float32
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    color, depth = wall_color, wall_depth
    height, width = depth.shape

    # ---- head (static-size window)
    r0, c0 = crop_origin[0], crop_origin[1]
    ci = r0 + jnp.arange(crop, dtype=jnp.int32)
    cj = c0 + jnp.arange(crop, dtype=jnp.int32)
    ray = jnp.stack(jnp.broadcast_arrays(((cj.astype(f32) - cx) / fx)[None, :],
                                         ((ci.astype(f32) - cy) / fy)[:, None],
                                         jnp.ones((crop, crop), f32)), -1)  # (c, c, 3)
    q = quaternion
    q_inv = q * jnp.asarray([1, -1, -1, -1], f32)
    o_h = quat_rotate(q_inv, -position)  # camera centre in the head frame
    d_h = quat_rotate(q_inv[None, None], ray)  # (c, c, 3), not unit: s = depth
    s_out_in, s_out_out, hit_out = _ray_ellipsoid(o_h, d_h, model.outer_axes)
    s_in_in, _, hit_in = _ray_ellipsoid(o_h, d_h, model.inner_axes)
    s0 = jnp.maximum(s_out_in, 0.05)
    s1 = jnp.where(hit_in, s_in_in, s_out_out)
    dx, dy, dz = d_h[..., 0], d_h[..., 1], d_h[..., 2]

    def g_at(s):  # implicit function along the rays (structure of arrays), s (c, c, ...)
        ex = (...,) + (None,) * (s.ndim - 2)
        return model._implicit_xyz(o_h[0] + s * dx[ex], o_h[1] + s * dy[ex],
                                   o_h[2] + s * dz[ex])

    ts = jnp.linspace(0, 1, n_march, dtype=f32)
    ss = s0[..., None] + (s1 - s0)[..., None] * ts  # (c, c, n)
    g = g_at(ss)
    neg = g < 0
    k = jnp.argmax(neg, axis=-1)
    found = hit_out & jnp.any(neg, axis=-1) & (k > 0)
    k = jnp.maximum(k, 1)
    sa = jnp.take_along_axis(ss, (k - 1)[..., None], -1)[..., 0]
    sb = jnp.take_along_axis(ss, k[..., None], -1)[..., 0]
    ga = jnp.take_along_axis(g, (k - 1)[..., None], -1)[..., 0]
    gb = jnp.take_along_axis(g, k[..., None], -1)[..., 0]

    def refine(_, st):  # regula falsi, Illinois variant; bracket [a, b] with g(a) > 0 > g(b)
        sa, sb, ga, gb, side = st
        den = ga - gb
        sm = jnp.where(den != 0, (sb * ga - sa * gb) / jnp.where(den != 0, den, 1),
                       0.5 * (sa + sb))
        sm = jnp.clip(sm, jnp.minimum(sa, sb), jnp.maximum(sa, sb))
        gm = g_at(sm)
        pos = gm > 0
        # Illinois: halve the retained end's value when the same side is kept twice
        ga_new = jnp.where(pos, gm, jnp.where(side == -1, 0.5 * ga, ga))
        gb_new = jnp.where(pos, jnp.where(side == 1, 0.5 * gb, gb), gm)
        sa_new = jnp.where(pos, sm, sa)
        sb_new = jnp.where(pos, sb, sm)
        return sa_new, sb_new, ga_new, gb_new, jnp.where(pos, 1, -1).astype(jnp.int32)

    sa, sb, ga, gb, _ = jax.lax.fori_loop(
        0, n_refine, refine, (sa, sb, ga, gb, jnp.zeros(sa.shape, jnp.int32)))
    s_hit = jnp.where(jnp.abs(ga) < jnp.abs(gb), sa, sb)
    hx, hy, hz = o_h[0] + s_hit * dx, o_h[1] + s_hit * dy, o_h[2] + s_hit * dz
    g_hit, g_vjp = jax.vjp(model._implicit_xyz, hx, hy, hz)
    grads = g_vjp(jnp.ones_like(g_hit))  # elementwise function: per-pixel gradients
    head = found & (jnp.abs(g_hit) < 1e-4)
    n_h = jnp.stack(grads, -1)
    n_h = n_h / jnp.sqrt(jnp.maximum(jnp.sum(n_h * n_h, -1, keepdims=True), 1e-20))
    n_c = quat_rotate(q[None, None], n_h)
    lon, lat = _lonlat(jnp.stack([hx, hy, hz], -1))
    th, tw = model.texture.shape[:2]
    alb = _bilinear(model.texture, (lon / (2 * jnp.pi) + 0.5) * tw - 0.5,
                    (0.5 - lat / jnp.pi) * th - 0.5, wrap_x=True)
    light = jnp.asarray(_LIGHT, f32)
    lam = jnp.maximum(jnp.sum(n_c * light, -1), 0)  # `light`: unit vector towards the light
    head_col = alb * (0.35 + 0.75 * lam)[..., None]

    wall_crop_d = jax.lax.dynamic_slice(depth, (r0, c0), (crop, crop))
    zero = jnp.zeros((), jnp.int32)
    wall_crop_c = jax.lax.dynamic_slice(color, (r0, c0, zero), (crop, crop, 3))
    use = head & (s_hit < wall_crop_d)
    d_crop = jnp.where(use, s_hit, wall_crop_d)
    c_crop = jnp.where(use[..., None], head_col, wall_crop_c)
    depth = jax.lax.dynamic_update_slice(depth, d_crop, (r0, c0))
    color = jax.lax.dynamic_update_slice(color, c_crop, (r0, c0, zero))
    head_mask = jax.lax.dynamic_update_slice(jnp.zeros((height, width), bool), use, (r0, c0))
    return color, depth, head_mask


def _np_rotate(q, v):
    vq = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], -1)
    return np_qmul(np_qmul(q, vq), np_qconj(q))[..., 1:]


def _camera_from_head_np(positions_w, quats_w, eye_centre, camera_distance):
    """Head-origin pose in the camera frame from eye-centre world poses."""
    cam_pos = np.array([0.0, 1.20, -camera_distance])  # 0.8 m in front of the resting eyes
    q_c = np_qmul(_Q_CAM_FROM_WORLD, quats_w)
    head_w = positions_w - _np_rotate(quats_w, np.broadcast_to(eye_centre, positions_w.shape))
    p_c = _np_rotate(np.broadcast_to(_Q_CAM_FROM_WORLD, quats_w.shape), head_w - cam_pos)
    q_c = np.where(q_c[..., :1] < 0, -q_c, q_c)
    flips = np.sum(q_c[1:] * q_c[:-1], -1) < 0
    q_c = q_c * np.concatenate([[1.0], np.cumprod(np.where(flips, -1.0, 1.0))])[:, None]
    return p_c, q_c


_NOISE_STATIC = ("focal", "baseline", "sigma_disparity", "subpixel", "edge_threshold",
                 "edge_dropout", "dropout", "z_range")


@functools.partial(jit, static_argnames=_NOISE_STATIC)
def add_depth_noise(
    key: Array,
    depth: Float[ArrayLike, "h w"],
    *,
    focal: float = 525.0,
    baseline: float = 0.075,
    sigma_disparity: float | None = None,
    subpixel: float = 0.125,
    edge_threshold: float = 0.03,
    edge_dropout: float = 0.5,
    dropout: float = 0.002,
    z_range: tuple[float, float] = (0.4, 4.5),
) -> Float[Array, "h w"]:
    """Kinect-v1-like depth corruption (see the module docstring); ``0`` = invalid.

    Arguments:
        key: a JAX PRNG key.
        depth: clean depth (m), ``0`` = invalid.
        focal, baseline: stereo geometry of the structured-light sensor (px, m).
        sigma_disparity: disparity noise (px); default ``1.425e-3 * focal * baseline`` so that
            ``sigma_z = 1.425e-3 z^2``.
        subpixel: disparity quantisation step (px); 0 disables quantisation.
        edge_threshold: a pixel whose 4-neighbour depth differs by more than this (m) is on a
            depth edge and dropped with probability ``edge_dropout``.
        dropout: probability of a random missing pixel.
        z_range: valid measurement range (m).
    """
    z = jnp.asarray(depth, jnp.float32)
    fb = focal * baseline
    sig = 1.425e-3 * fb if sigma_disparity is None else sigma_disparity
    k1, k2, k3 = jax.random.split(key, 3)
    valid = z > 0
    disp = fb / jnp.where(valid, z, 1)
    disp = disp + sig * jax.random.normal(k1, z.shape, jnp.float32)
    if subpixel > 0:
        disp = jnp.round(disp / subpixel) * subpixel
    zn = fb / jnp.maximum(disp, 1e-6)
    pad = jnp.pad(z, 1, mode="edge")
    jump = jnp.max(jnp.stack([jnp.abs(pad[1:-1, :-2] - z), jnp.abs(pad[1:-1, 2:] - z),
                              jnp.abs(pad[:-2, 1:-1] - z), jnp.abs(pad[2:, 1:-1] - z)]), 0)
    u = jax.random.uniform(k2, z.shape, jnp.float32)
    drop = ((jump > edge_threshold) & (u < edge_dropout)) | (
        jax.random.uniform(k3, z.shape, jnp.float32) < dropout)
    ok = valid & ~drop & (zn >= z_range[0]) & (zn <= z_range[1])
    return jnp.where(ok, zn, 0)


def render_rgbd(
    head_position: Float[ArrayLike, "3"],
    head_quaternion: Float[ArrayLike, "4"],
    intrinsics: PinholeIntrinsics,
    *,
    width: int = 640,
    height: int = 480,
    model: HeadModel | None = None,
    wall: Float[ArrayLike, "4"] = (0.05, 0.0, 1.0, 1.8),
    crop: int | None = None,
    n_march: int = 24,
    n_refine: int = 10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one noise-free frame of the head at a camera-frame pose in front of a wall.

    Arguments:
        head_position, head_quaternion: head-frame origin and orientation (``wxyz``, head to
            camera) in the camera frame.
        intrinsics: pinhole intrinsics (pixels).
        width, height: image size.
        model: the :class:`HeadModel` (default: the standard head).
        wall: background plane ``(n, d)`` with ``n . X = d`` (camera frame, ``|n| = 1`` not
            required; the plane must lie in front of the camera).
        crop: side of the square window ray cast for the head (static; default: the head's
            projected bounding box for this pose).
        n_march, n_refine: uniform samples and regula-falsi iterations per ray.

    Returns:
        ``(color (h, w, 3) uint8 RGB, depth (h, w) float32 m, head_mask (h, w) bool)``.
    """
    model = _default_model() if model is None else model
    p = np.asarray(head_position, np.float64)
    q = np.asarray(head_quaternion, np.float64)
    k = np.array([float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx),
                  float(intrinsics.cy)])
    wall = np.asarray(wall, np.float64)
    wall = np.concatenate([wall[:3] / np.linalg.norm(wall[:3]), wall[3:] / np.linalg.norm(
        wall[:3])])
    bound = float(np.max(np.asarray(model.outer_axes)))
    if crop is None:
        crop = _crop_size(p[None], bound, k, width, height)
    origin = _crop_origin(p, k, crop, width, height)
    wall_color, wall_depth = _wall_jit(jnp.asarray(_wall_tex()), jnp.asarray(k, jnp.float32),
                                       jnp.asarray(wall, jnp.float32), height=height,
                                       width=width)
    color, depth, mask = _render_jit(
        model, wall_color, wall_depth, jnp.asarray(p, jnp.float32), jnp.asarray(q, jnp.float32),
        jnp.asarray(k, jnp.float32), jnp.asarray(origin, jnp.int32), crop=crop,
        n_march=n_march, n_refine=n_refine)
    color = np.asarray(jnp.clip(jnp.round(color * 255), 0, 255).astype(jnp.uint8))
    return color, np.asarray(depth, np.float32), np.asarray(mask)


def _crop_size(positions, bound, k, width, height) -> int:
    z = positions[:, 2]
    if np.any(z <= bound + 0.05):
        raise ValueError("the head must be in front of the camera (z > its bounding radius)")
    r_px = np.max(max(k[0], k[1]) * bound / np.sqrt(z * z - bound * bound))
    size = int(2 * np.ceil(r_px) + 8)
    size = -(-size // 32) * 32  # coarse sizes: most sequences share one compiled renderer
    return int(min(size, width, height))


def _crop_origin(p, k, crop, width, height) -> np.ndarray:
    u = k[0] * p[0] / p[2] + k[2]
    v = k[1] * p[1] / p[2] + k[3]
    c0 = int(np.clip(np.round(u - crop / 2), 0, width - crop))
    r0 = int(np.clip(np.round(v - crop / 2), 0, height - crop))
    return np.array([r0, c0])


@functools.partial(jit, static_argnames=("crop", "depth_noise", "focal", "noisy_color"),
                   options=IMAGE_COMPILER_OPTIONS)
def _frame_jit(model, wall_color, wall_depth, position, quaternion, intr, crop_origin, key,
               color_noise, *, crop, depth_noise, focal, noisy_color):
    """Render + sensor noise + 8-bit conversion in one compiled call."""
    color, clean, mask = _render_jit(model, wall_color, wall_depth, position, quaternion, intr,
                                     crop_origin, crop=crop, n_march=24, n_refine=10)
    k_d, k_c = jax.random.split(key)
    depth = add_depth_noise(k_d, clean, focal=focal) if depth_noise else clean
    color = color * 255
    if noisy_color:
        color = color + color_noise * jax.random.normal(k_c, color.shape, jnp.float32)
    color = jnp.clip(jnp.round(color), 0, 255).astype(jnp.uint8)
    return color, depth, clean, mask


# ----------------------------------------------------------------------------- sequences
@dataclasses.dataclass(frozen=True)
class SyntheticRGBDFrame:
    """One rendered frame with ground truth (NumPy arrays; camera frame, see module docs).

    Attributes:
        index: frame number; ``timestamp``: seconds.
        color: ``(h, w, 3)`` uint8 RGB. ``depth``: ``(h, w)`` float32 metres, 0 = invalid.
        head_mask: ``(h, w)`` bool, pixels showing the head (before depth noise).
        intrinsics: :class:`~phjax.vision.icp.PinholeIntrinsics`.
        head_position: ``(3,)`` head-frame origin in the camera frame (m).
        head_quaternion: ``(4,)`` ``wxyz``, head frame to camera frame.
        landmarks: ``(len(LANDMARK_NAMES), 3)`` landmark positions in the camera frame.
        landmarks_2d: ``(len(LANDMARK_NAMES), 2)`` their pixel coordinates ``(u, v)``.
        landmarks_visible: ``(len(LANDMARK_NAMES),)`` not occluded (per the clean depth)
            and inside the image.
    """

    index: int
    timestamp: float
    color: np.ndarray
    depth: np.ndarray
    head_mask: np.ndarray
    intrinsics: PinholeIntrinsics
    head_position: np.ndarray
    head_quaternion: np.ndarray
    landmarks: np.ndarray
    landmarks_2d: np.ndarray
    landmarks_visible: np.ndarray

    @property
    def landmark_names(self) -> tuple[str, ...]:
        return LANDMARK_NAMES

    def landmark(self, name: str) -> np.ndarray:
        """Camera-frame position of a named landmark."""
        return self.landmarks[LANDMARK_NAMES.index(name)]

    @property
    def eye_centre(self) -> np.ndarray:
        """Midpoint of the eye landmarks (camera frame)."""
        return 0.5 * (self.landmarks[0] + self.landmarks[1])


class SyntheticRGBDSequence:
    """A synthetic RGB-D head sequence; frames are rendered on access (indexing/iteration).

    Head motion: :func:`~phjax.motion.simulate.synthetic_head_motion` sampled at ``rate``, its
    orientation scaled by ``rotation_scale`` about the rest pose (``q -> exp(s log q)``, so the
    +-110 degree yaw range of seated VR motion becomes a face-to-camera range) with the eye
    position recomputed about the same neck pivot; the camera looks at the subject from
    ``camera_distance`` in front of the resting eyes (head centre at about 0.9 m).

    Arguments:
        num_frames: number of frames.
        rate: frame rate (Hz).
        seed: seed of the motion and the noise; the same seed gives identical frames.
        width, height: image size (pixels).
        depth_noise: apply :func:`add_depth_noise`.
        color_noise: std of additive Gaussian colour noise (8-bit units), 0 disables.
        fx, fy: focal lengths (px); the principal point is the image centre
            ``((width - 1) / 2, (height - 1) / 2)``.
        camera_distance: distance of the camera in front of the resting eye position (m).
        rotation_scale: scale of the head rotation (see above).
        wall: background plane ``(n, d)``, ``n . X = d``, camera frame.

    Attributes:
        timestamps, head_positions, head_quaternions: the ground-truth camera-frame poses,
            ``(n,)``, ``(n, 3)``, ``(n, 4)``.
        intrinsics: the camera intrinsics.
        model: the :class:`HeadModel`.
    """

    def __init__(
        self,
        num_frames: int = 90,
        rate: float = 30.0,
        seed: int = 0,
        width: int = 640,
        height: int = 480,
        depth_noise: bool = True,
        *,
        color_noise: float = 2.0,
        fx: float = 525.0,
        fy: float = 525.0,
        camera_distance: float = 0.8,
        rotation_scale: float = 0.5,
        wall: tuple[float, float, float, float] = (0.05, 0.0, 1.0, 1.8),
        model: HeadModel | None = None,
    ):
        if int(num_frames) < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        if not rate > 0:
            raise ValueError(f"rate must be positive, got {rate}")
        if int(width) < 16 or int(height) < 16:
            raise ValueError("width and height must be at least 16 pixels")
        self.num_frames, self.rate, self.seed = int(num_frames), float(rate), int(seed)
        self.width, self.height = int(width), int(height)
        self.depth_noise, self.color_noise = bool(depth_noise), float(color_noise)
        self.model = _default_model() if model is None else model
        self.intrinsics = PinholeIntrinsics(float(fx), float(fy), (self.width - 1) / 2,
                                            (self.height - 1) / 2)
        wall = np.asarray(wall, np.float64)
        self.wall = np.concatenate([wall[:3], wall[3:]]) / np.linalg.norm(wall[:3])

        # motion generated in whole 60 s blocks (the random schedule depends on the duration):
        # for one seed, sequences of up to 60 s share their motion (the shorter one is a prefix),
        # and so do those of 60-120 s, etc. Their frames may still differ: the size of the
        # rendered window (self.crop) depends on the whole sequence's head positions.
        duration = 60.0 * np.ceil(max(self.num_frames - 1, 1) / self.rate / 60.0)
        t, p_w, q_w = synthetic_head_motion(duration, self.rate, self.seed)
        t, p_w, q_w = t[: self.num_frames], p_w[: self.num_frames], q_w[: self.num_frames]
        # scale the rotation about the rest pose, keeping the neck pivot + torso sway
        pivot = p_w - _np_rotate(q_w, np.broadcast_to(_NECK_TO_EYES, p_w.shape))
        q_s = np_from_rotvec(float(rotation_scale) * np_rotvec(q_w))
        p_s = pivot + _np_rotate(q_s, np.broadcast_to(_NECK_TO_EYES, p_w.shape))
        eye = np.asarray(self.model.eye_centre, np.float64)
        self.timestamps = t
        self.head_positions, self.head_quaternions = _camera_from_head_np(
            p_s, q_s, eye, float(camera_distance))
        self._k = np.array([float(fx), float(fy), (self.width - 1) / 2, (self.height - 1) / 2])
        self._bound = float(np.max(np.asarray(self.model.outer_axes)))
        self.crop = _crop_size(self.head_positions, self._bound, self._k, self.width,
                               self.height)
        self._key = jax.random.key(self.seed)
        self._landmarks_h = np.asarray(self.model.landmarks, np.float64)
        self._wall_images = None

    def __len__(self) -> int:
        return self.num_frames

    def __iter__(self) -> Iterator[SyntheticRGBDFrame]:
        for i in range(self.num_frames):
            yield self[i]

    def __getitem__(self, index: int) -> SyntheticRGBDFrame:
        i = int(index)
        if i < 0:
            i += self.num_frames
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {index} out of range for {self.num_frames} frames")
        p, q = self.head_positions[i], self.head_quaternions[i]
        origin = _crop_origin(p, self._k, self.crop, self.width, self.height)
        if self._wall_images is None:  # the camera is static: render the wall once
            self._wall_images = _wall_jit(
                jnp.asarray(_wall_tex()), jnp.asarray(self._k, jnp.float32),
                jnp.asarray(self.wall, jnp.float32), height=self.height, width=self.width)
        color, depth, clean, mask = _frame_jit(
            self.model, *self._wall_images, jnp.asarray(p, jnp.float32),
            jnp.asarray(q, jnp.float32), jnp.asarray(self._k, jnp.float32),
            jnp.asarray(origin, jnp.int32),
            jax.random.fold_in(self._key, i), jnp.asarray(self.color_noise, jnp.float32),
            crop=self.crop,
            depth_noise=self.depth_noise, focal=float(self._k[0]),
            noisy_color=self.color_noise > 0)
        color = np.asarray(color)
        lm = p + _np_rotate(np.broadcast_to(q, (len(LANDMARK_NAMES), 4)), self._landmarks_h)
        uv = np.stack([self._k[0] * lm[:, 0] / lm[:, 2] + self._k[2],
                       self._k[1] * lm[:, 1] / lm[:, 2] + self._k[3]], -1)
        clean = np.asarray(clean)
        inside = (uv[:, 0] > -0.5) & (uv[:, 0] < self.width - 0.5) & (uv[:, 1] > -0.5) & (
            uv[:, 1] < self.height - 0.5)
        jj = np.clip(np.round(uv[:, 0]).astype(int), 0, self.width - 1)
        ii = np.clip(np.round(uv[:, 1]).astype(int), 0, self.height - 1)
        visible = inside & (clean[ii, jj] > lm[:, 2] - 0.01)
        return SyntheticRGBDFrame(
            index=i,
            timestamp=float(self.timestamps[i]),
            color=color,
            depth=np.asarray(depth, np.float32),
            head_mask=np.asarray(mask),
            intrinsics=self.intrinsics,
            head_position=p.copy(),
            head_quaternion=q.copy(),
            landmarks=lm,
            landmarks_2d=uv,
            landmarks_visible=visible,
        )


def synthetic_rgbd_sequence(
    num_frames: int = 90,
    rate: float = 30.0,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    depth_noise: bool = True,
    **kwargs,
) -> SyntheticRGBDSequence:
    """A :class:`SyntheticRGBDSequence` (see there for the arguments and conventions)."""
    return SyntheticRGBDSequence(num_frames, rate, seed, width, height, depth_noise, **kwargs)
