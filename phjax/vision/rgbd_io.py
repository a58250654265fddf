"""RGB-D frame readers: Biwi Kinect head pose, TUM RGB-D folders, plain colour + depth pairs.

Every reader returns :class:`RGBDFrame` objects with one convention:

* ``color``: ``uint8 (H, W, 3)`` in **BGR** channel order (OpenCV's order; the face detectors
  of :mod:`phjax.vision.face_detection` take BGR).
* ``depth``: ``float32 (H, W)`` depth along the optical axis in **metres**, *registered to the
  colour image* (pixel ``(i, j)`` of ``depth`` belongs to pixel ``(i, j)`` of ``color``);
  ``0`` (or NaN) marks a missing measurement.
* ``intrinsics``: the :class:`CameraIntrinsics` of the colour camera (pinhole, pixels; pixel
  ``(row i, column j)`` has its centre at ``(u, v) = (j, i)``).
* ``timestamp``: seconds.

Formats
-------
``Biwi``
    ``frame_XXXXX_rgb.png`` (colour), ``frame_XXXXX_depth.bin`` (run-length depth, mm, see
    :func:`read_biwi_depth`), ``frame_XXXXX_pose.txt`` (head pose, see
    :func:`phjax.io.read_biwi_pose`), ``rgb.cal`` / ``depth.cal`` (see
    :func:`read_biwi_calibration`). Depth and colour come from different cameras (Kinect v1);
    :func:`register_depth` warps the depth into the colour camera with the calibrated
    extrinsics ``p_rgb = R p_depth + t`` (this direction was checked on the shared samples:
    the registered head silhouette lies on the image edges).
``TUM RGB-D``
    a folder with ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines), 16-bit PNG depth with
    5000 units per metre; colour and depth are associated by nearest timestamp
    (:func:`associate`). Intrinsics default to the Freiburg 1/2/3 calibration guessed from the
    folder name (ROS defaults otherwise).
``pairs``
    any colour image plus a 16-bit depth image (PNG or binary PGM, big-endian) with a depth
    scale and intrinsics (:func:`read_rgbd_pair`); :func:`read_slambook` reads the
    ``color/N.png``, ``depth/N.pgm``, ``pose.txt`` layout of the slambook2 chapter-5 data.

Depth images are 16-bit (``uint16``), ``int32`` or float, one channel: an 8-bit one is a
:class:`RGBDFormatError` naming the file, for a TUM or ``color/`` + ``depth/`` folder already
when it is opened (its first depth image is checked).

:func:`open_rgbd` detects the layout of a folder and returns a lazily loaded
:class:`RGBDSequence`. Malformed files raise :class:`RGBDFormatError` (a ``ValueError``) naming
the file and the problem. PNG decoding uses OpenCV when installed, else Pillow.
"""

from __future__ import annotations

import functools
import itertools
import math
import os
import re
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._jit import jit
from ..io import Trajectory, biwi_pose_to_quaternion, read_biwi_pose

__all__ = [
    "CameraIntrinsics",
    "RGBDFrame",
    "RGBDSequence",
    "RGBDFormatError",
    "BiwiCalibration",
    "TUM_INTRINSICS",
    "read_image",
    "read_pgm",
    "write_pgm",
    "read_biwi_depth",
    "write_biwi_depth",
    "read_biwi_calibration",
    "register_depth",
    "read_biwi_frame",
    "biwi_pose_in_color_frame",
    "read_biwi",
    "associate",
    "read_tum_rgbd",
    "write_tum_rgbd",
    "read_rgbd_pair",
    "read_pose_list",
    "read_slambook",
    "SLAMBOOK_INTRINSICS",
    "DEFAULT_FOLDER_FPS",
    "UNTIMED_LAYOUTS",
    "synthetic_rgbd",
    "open_rgbd",
    "rgbd_layout",
]

PathLike = str | os.PathLike


# ----------------------------------------------------------------------------------- types
class CameraIntrinsics(eqx.Module):
    """Pinhole intrinsics of an image (pixels) with its size.

    ``u = fx x / z + cx``, ``v = fy y / z + cy``; pixel ``(row i, column j)`` has its centre at
    ``(u, v) = (j, i)``. ``fx, fy, cx, cy`` are PyTree leaves (changing them does not recompile
    a jitted function); ``width`` and ``height`` are static. Accepted wherever
    :mod:`phjax.vision.icp` expects intrinsics.
    """

    fx: Float[ArrayLike, ""]
    fy: Float[ArrayLike, ""]
    cx: Float[ArrayLike, ""]
    cy: Float[ArrayLike, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def checked(self) -> CameraIntrinsics:
        """These intrinsics, after a host-side check (outside ``jit``): finite ``cx, cy``,
        finite positive ``fx, fy``, positive ``width, height``.

        Raises:
            ValueError: with the offending values.
        """
        f = np.array([float(self.fx), float(self.fy)])
        c = np.array([float(self.cx), float(self.cy)])
        if not (np.isfinite(f).all() and (f > 0).all() and np.isfinite(c).all()
                and self.width > 0 and self.height > 0):
            raise ValueError(
                "camera intrinsics need finite fx, fy > 0, finite cx, cy and a positive size; "
                f"got fx={f[0]:g} fy={f[1]:g} cx={c[0]:g} cy={c[1]:g} "
                f"size={self.width}x{self.height}")
        return self

    @property
    def matrix(self) -> Float[np.ndarray, "3 3"]:
        """The 3x3 calibration matrix ``K`` (NumPy float64)."""
        return np.array([[float(self.fx), 0, float(self.cx)], [0, float(self.fy), float(self.cy)],
                         [0, 0, 1]])

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``."""
        return (self.height, self.width)

    def scaled(self, sx: float, sy: float | None = None) -> CameraIntrinsics:
        """Intrinsics of the image resized by ``(sx, sy)`` (pixel-centre convention kept)."""
        sy = sx if sy is None else sy
        return CameraIntrinsics(
            fx=float(self.fx) * sx, fy=float(self.fy) * sy,
            cx=(float(self.cx) + 0.5) * sx - 0.5, cy=(float(self.cy) + 0.5) * sy - 0.5,
            width=round(self.width * sx), height=round(self.height * sy),
        )

    @classmethod
    def from_matrix(cls, k: ArrayLike, width: int, height: int) -> CameraIntrinsics:
        """From a 3x3 calibration matrix (zero skew)."""
        k = np.asarray(k, dtype=np.float64)
        if k.shape != (3, 3):
            raise ValueError(f"intrinsic matrix must be 3x3, got shape {k.shape}")
        return cls(fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]),
                   width=int(width), height=int(height))


class RGBDFrame(NamedTuple):
    """One registered colour + depth frame.

    Attributes:
        color: ``uint8 (H, W, 3)`` image, **BGR** channel order.
        depth: ``float32 (H, W)`` depth in metres registered to ``color``; 0 or NaN = missing.
        intrinsics: :class:`CameraIntrinsics` of the colour camera.
        timestamp: seconds.
        name: an identifier (file stem or frame id).
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: CameraIntrinsics
    timestamp: float = 0.0
    name: str = ""


class RGBDFormatError(ValueError):
    """A malformed RGB-D file or folder; the message names the file and the problem."""

    def __init__(self, path: PathLike | None, what: str):
        super().__init__(f"{os.fspath(path)}: {what}" if path is not None else what)
        self.path = path


def _read_text(path: Path) -> str:
    """A text file's contents (UTF-8); any other bytes are a :class:`RGBDFormatError`."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise RGBDFormatError(path, f"not a UTF-8 text file (byte {e.start}: "
                              f"{e.object[e.start:e.start + 1]!r})") from None


class RGBDSequence(Sequence):
    """A lazily loaded sequence of :class:`RGBDFrame` (list-like: ``len``, index, iterate).

    Attributes:
        timestamps: ``(n,)`` frame times, s.
        intrinsics: the colour camera's intrinsics (shared by all frames).
        name: a description of the source.
        ground_truth: optional :class:`phjax.io.Trajectory` at the frame times (NaN rows where
            unknown), in the **colour camera frame** for head poses (Biwi) or as camera poses
            ``T_wc`` (TUM, slambook); see ``ground_truth_kind``.
        ground_truth_kind: ``"head"``, ``"camera"`` or ``None``.
    """

    def __init__(self, loaders: Sequence[Callable[[], RGBDFrame]], timestamps: ArrayLike,
                 intrinsics: CameraIntrinsics, name: str = "",
                 ground_truth: Trajectory | None = None, ground_truth_kind: str | None = None):
        self._loaders = list(loaders)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.intrinsics = intrinsics
        self.name = name
        self.ground_truth = ground_truth
        self.ground_truth_kind = ground_truth_kind

    def __len__(self) -> int:
        return len(self._loaders)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            idx = range(*i.indices(len(self)))
            gt = None if self.ground_truth is None else Trajectory(
                *(np.asarray(a)[i] for a in self.ground_truth))
            return RGBDSequence([self._loaders[k] for k in idx], self.timestamps[i],
                                self.intrinsics, self.name, gt, self.ground_truth_kind)
        return self._loaders[i]()

    def __iter__(self) -> Iterator[RGBDFrame]:
        for load in self._loaders:
            yield load()

    def __repr__(self) -> str:
        return f"RGBDSequence({self.name!r}, {len(self)} frames)"


# ------------------------------------------------------------------------------ image files
_JPEG_SOI, _PNG_SIGNATURE = b"\xff\xd8", b"\x89PNG\r\n\x1a\n"


def _jpeg_complete(data: bytes) -> bool:
    """Whether a JPEG's marker segments reach its end-of-image marker (``FFD9``) within
    ``data``. Segments are skipped by their lengths (an EXIF thumbnail's own end marker lies
    inside one) and entropy-coded data up to the next marker that is not a stuffed ``FF00`` or a
    restart marker; bytes after the end marker (a phone's appended video) are not read. A
    layout this walk does not understand counts as complete (the decoder then judges it)."""
    pos, n = 2, len(data)
    while pos + 1 < n:
        if data[pos] != 0xFF:
            return True  # not a marker where one belongs: the decoder's call
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte before a marker
            pos += 1
        elif marker == 0xD9:
            return True
        elif marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            pos += 2
        else:
            if pos + 3 >= n:
                return False
            pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
            if marker == 0xDA:  # a scan: entropy-coded data up to the next real marker
                while True:
                    pos = data.find(b"\xff", pos)
                    if pos < 0 or pos + 1 >= n:
                        return False
                    following = data[pos + 1]
                    if following != 0x00 and not 0xD0 <= following <= 0xD7:
                        break
                    pos += 2
    return False


def _png_complete(data: bytes) -> bool:
    """Whether a PNG's chunks (length, type, data, CRC) reach its ``IEND`` chunk within
    ``data``."""
    pos, n = len(_PNG_SIGNATURE), len(data)
    while pos + 8 <= n:
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        pos += 12 + length
        if kind == b"IEND":
            return pos <= n
    return False


def _truncated(data: bytes) -> bool:
    """Whether a JPEG or PNG file ends before its image does (an interrupted copy or download);
    other formats are left to the decoder. Checked before decoding: libjpeg and libpng print
    their own lines on stderr when they meet the early end."""
    if data.startswith(_JPEG_SOI):
        return not _jpeg_complete(data)
    if data.startswith(_PNG_SIGNATURE):
        return not _png_complete(data)
    return False


def read_image(path: PathLike, *, unchanged: bool = False) -> np.ndarray:
    """Read an image file: colour as ``uint8 (H, W, 3)`` BGR, or ``unchanged`` (e.g. 16-bit).

    Uses OpenCV when installed, else Pillow. Binary PGM files (8/16-bit) are read by
    :func:`read_pgm` (no dependency). A JPEG or PNG file that ends before its image does (an
    interrupted copy) is an error before any decoding.

    Raises:
        FileNotFoundError: missing file.
        RGBDFormatError: the file is empty, truncated or cannot be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    if path.suffix.lower() in (".pgm", ".ppm") and unchanged:
        return read_pgm(path)
    raw = path.read_bytes()
    if not raw:
        raise RGBDFormatError(path, "empty file, not an image")
    if _truncated(raw):
        raise RGBDFormatError(path, "truncated: the file ends before its image does "
                                    "(an interrupted copy or download?)")
    try:
        import cv2
    except ImportError:
        cv2 = None
    if cv2 is not None:
        flag = cv2.IMREAD_UNCHANGED if unchanged else cv2.IMREAD_COLOR
        img = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), flag)
        if img is None:
            raise RGBDFormatError(path, "not a readable image")
        return img
    try:
        from PIL import Image
    except ImportError as e:  # pragma: no cover - environment dependent
        raise ImportError("reading PNG images needs opencv-python-headless or Pillow "
                          "(pip install 'phjax[vision]')") from e
    try:
        with Image.open(path) as im:
            if unchanged:
                arr = np.asarray(im)
                return arr[..., ::-1].copy() if arr.ndim == 3 else arr
            return np.asarray(im.convert("RGB"))[..., ::-1].copy()
    except OSError as e:
        raise RGBDFormatError(path, f"not a readable image ({e})") from e


def _write_png(path: PathLike, img: np.ndarray) -> None:
    try:
        import cv2

        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise RGBDFormatError(path, "PNG encoding failed")
        Path(path).write_bytes(buf.tobytes())
    except ImportError:  # pragma: no cover - environment dependent
        from PIL import Image

        arr = img[..., ::-1] if img.ndim == 3 else img
        Image.fromarray(np.ascontiguousarray(arr)).save(path)


_PGM_TOKEN = re.compile(rb"\s*(?:#[^\n]*\n\s*)*(\S+)")


def read_pgm(path: PathLike) -> np.ndarray:
    """Read a binary (``P5``) PGM image: ``uint8`` or ``uint16`` (16-bit is big-endian).

    Raises:
        RGBDFormatError: not a binary PGM, bad header, or truncated data.
    """
    path = Path(path)
    data = path.read_bytes()
    pos, tokens = 0, []
    for _ in range(4):
        m = _PGM_TOKEN.match(data, pos)
        if m is None:
            raise RGBDFormatError(path, "truncated PGM header")
        tokens.append(m.group(1))
        pos = m.end()
    if tokens[0] != b"P5":
        raise RGBDFormatError(path, f"not a binary PGM (magic {tokens[0][:8]!r}, expected b'P5')")
    try:
        w, h, maxval = (int(t) for t in tokens[1:])
    except ValueError as e:
        raise RGBDFormatError(path, f"bad PGM header {b' '.join(tokens)!r}") from e
    if w <= 0 or h <= 0 or not 0 < maxval < 65536:
        raise RGBDFormatError(path, f"bad PGM size/maxval {w}x{h}, {maxval}")
    pos += 1  # exactly one whitespace byte after maxval
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    n = w * h * dtype.itemsize
    if len(data) - pos < n:
        raise RGBDFormatError(path, f"truncated PGM data: {len(data) - pos} bytes, expected {n}")
    return np.frombuffer(data, dtype, count=w * h, offset=pos).reshape(h, w).astype(
        np.uint16 if maxval > 255 else np.uint8)


def write_pgm(path: PathLike, image: np.ndarray) -> None:
    """Write a ``uint8`` / ``uint16`` 2-D array as binary PGM (16-bit big-endian)."""
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PGM needs a 2-D uint8/uint16 array, got {image.dtype} {image.shape}")
    maxval = 255 if image.dtype == np.uint8 else 65535
    header = f"P5\n{image.shape[1]} {image.shape[0]}\n{maxval}\n".encode()
    body = image.astype(">u2").tobytes() if maxval > 255 else image.tobytes()
    Path(path).write_bytes(header + body)


def _color(path: PathLike) -> np.ndarray:
    img = read_image(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] < 3:
        raise RGBDFormatError(path, f"expected a colour image, got shape {img.shape}")
    return np.ascontiguousarray(img[..., :3])


def _check_depth(path: PathLike, raw: np.ndarray) -> None:
    """A depth image must be one channel of 16-bit (``uint16``), ``int32`` or float values.

    Raises:
        RGBDFormatError: an 8-bit image (256 levels are not a depth measurement: an 8-bit
            export or a visualisation, whose every frame ended as ``NO_DEPTH``), several
            channels or another type.
    """
    if raw.ndim == 2 and raw.dtype == np.uint8:
        raise RGBDFormatError(path, "an 8-bit depth image; depth must be 16-bit (uint16, e.g. "
                              "millimetres) or float (an 8-bit export or a visualisation holds "
                              "no usable depth)")
    if raw.ndim != 2 or not (raw.dtype in (np.uint16, np.int32) or raw.dtype.kind == "f"):
        raise RGBDFormatError(path, f"expected a single-channel 16-bit or float depth image, "
                              f"got {raw.dtype} {raw.shape}")


def _depth_image(path: PathLike, scale: float) -> np.ndarray:
    """A depth image (:func:`_check_depth`) in metres, ``scale`` units per metre."""
    raw = read_image(path, unchanged=True)
    _check_depth(path, raw)
    return (raw.astype(np.float32) / np.float32(scale)).astype(np.float32)


def _check_first_depth(path: PathLike) -> None:
    """:func:`_check_depth` for a sequence's first depth image, when the sequence is opened:
    an 8-bit depth folder fails at once instead of ending every frame as ``NO_DEPTH``. A
    missing or damaged file is left to its frame (the readers' callers lose that frame)."""
    try:
        raw = read_image(path, unchanged=True)
    except (OSError, RGBDFormatError):
        return
    _check_depth(path, raw)


# -------------------------------------------------------------------------------------- Biwi
_BIWI_MAX_SIZE = 1 << 14


def read_biwi_depth(path: PathLike) -> Float[np.ndarray, "h w"]:
    """Decode a Biwi ``*_depth.bin`` file to metres.

    Format (little-endian): ``int32 width, int32 height``, then blocks ``int32 num_empty``
    (zero pixels to skip), ``int32 num_full``, ``num_full`` x ``int16`` depth in mm, row-major,
    until ``width * height`` pixels are filled.

    Returns:
        ``float32 (height, width)`` depth in metres, 0 where empty.

    Raises:
        RGBDFormatError: bad size, negative run, overflow of the image, truncation, or
            trailing bytes.
    """
    path = Path(path)
    buf = path.read_bytes()
    if len(buf) < 8:
        raise RGBDFormatError(path, f"Biwi depth file too short ({len(buf)} bytes)")
    w, h = (int(v) for v in np.frombuffer(buf, "<i4", count=2))
    if not (0 < w <= _BIWI_MAX_SIZE and 0 < h <= _BIWI_MAX_SIZE):
        raise RGBDFormatError(path, f"bad Biwi depth image size {w}x{h}")
    total = w * h
    out = np.zeros(total, np.int16)
    pos, filled = 8, 0
    while filled < total:
        if pos + 8 > len(buf):
            raise RGBDFormatError(path, f"truncated at byte {pos}: {filled} of {total} pixels")
        empty, full = (int(v) for v in np.frombuffer(buf, "<i4", count=2, offset=pos))
        pos += 8
        if empty < 0 or full < 0 or filled + empty + full > total:
            raise RGBDFormatError(
                path, f"bad run at byte {pos - 8}: num_empty={empty}, num_full={full} with "
                f"{filled} of {total} pixels filled")
        filled += empty
        if pos + 2 * full > len(buf):
            raise RGBDFormatError(path, f"truncated run of {full} values at byte {pos}")
        out[filled:filled + full] = np.frombuffer(buf, "<i2", count=full, offset=pos)
        pos += 2 * full
        filled += full
    if pos != len(buf):
        raise RGBDFormatError(path, f"{len(buf) - pos} trailing bytes after {total} pixels")
    depth = out.reshape(h, w).astype(np.float32) * np.float32(1e-3)
    depth[depth < 0] = 0
    return depth


def write_biwi_depth(path: PathLike, depth: Float[ArrayLike, "h w"]) -> None:
    """Encode depth in metres (0 / NaN = empty) as a Biwi ``*_depth.bin`` file (mm, int16)."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be 2-D, got shape {d.shape}")
    mm = np.where(np.isfinite(d), np.rint(d * 1e3), 0)
    if np.any((mm < 0) | (mm > 32767)):
        raise ValueError("depth must lie in [0, 32.767] m for the Biwi int16 mm format")
    flat = mm.astype(np.int16).ravel()
    full = flat != 0
    # maximal runs of empty / valid pixels; a block is (a run of zeros, the run of values after)
    change = np.flatnonzero(np.diff(full.astype(np.int8))) + 1
    runs = list(itertools.pairwise([0, *change.tolist(), flat.size]))
    parts = [np.asarray([d.shape[1], d.shape[0]], "<i4").tobytes()]
    k = 0
    while k < len(runs):
        a, b = runs[k]
        empty = 0
        if not full[a]:
            empty, k = b - a, k + 1
            a, b = runs[k] if k < len(runs) else (b, b)
        parts.append(np.asarray([empty, b - a], "<i4").tobytes())
        parts.append(flat[a:b].astype("<i2").tobytes())
        k += 1
    Path(path).write_bytes(b"".join(parts))


class BiwiCalibration(NamedTuple):
    """A Biwi ``*.cal`` file.

    Attributes:
        intrinsics: :class:`CameraIntrinsics` of the camera.
        distortion: 4 distortion coefficients (all zero in the database).
        rotation: 3x3 ``R`` and ``translation``: the extrinsics relative to the depth camera,
            ``p_camera = R p_depth + t`` (identity / zero for ``depth.cal``).
        translation: metres.
    """

    intrinsics: CameraIntrinsics
    distortion: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


def read_biwi_calibration(path: PathLike) -> BiwiCalibration:
    """Read a Biwi ``rgb.cal`` / ``depth.cal``: K (3x3), distortion (4), R (3x3), t (mm), size.

    Raises:
        RGBDFormatError: not exactly 27 numbers, non-finite values, or a bad K / R.
    """
    path = Path(path)
    toks = _read_text(path).split()
    try:
        vals = np.asarray([float(t) for t in toks], dtype=np.float64)
    except ValueError as e:
        raise RGBDFormatError(path, f"non-numeric token in calibration file ({e})") from e
    if vals.size != 27:
        raise RGBDFormatError(path, f"expected 27 numbers (K 9, distortion 4, R 9, t 3, "
                              f"size 2), found {vals.size}")
    if not np.all(np.isfinite(vals)):
        raise RGBDFormatError(path, "non-finite value")
    k = vals[:9].reshape(3, 3)
    r = vals[13:22].reshape(3, 3)
    t = vals[22:25] * 1e-3
    w, h = vals[25:27]
    if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]):
        raise RGBDFormatError(path, f"bad intrinsic matrix {k.tolist()}")
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(r) - 1) > 1e-3:
        raise RGBDFormatError(path, "extrinsic rotation is not a rotation matrix")
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise RGBDFormatError(path, f"bad image size {w} x {h}")
    return BiwiCalibration(CameraIntrinsics.from_matrix(k, int(w), int(h)), vals[9:13], r, t)


@jit
def _register(depth, src_k, dst_k, rotation, translation, dst_zero):
    h, w = depth.shape
    hh, ww = dst_zero.shape
    dtype = depth.dtype
    fx, fy, cx, cy = (src_k[i] for i in range(4))
    z = jnp.where(jnp.isfinite(depth) & (depth > 0), depth, 0)
    jj = jnp.arange(w, dtype=dtype)
    ii = jnp.arange(h, dtype=dtype)[:, None]
    p = jnp.stack([(jj - cx) * z / fx, (ii - cy) * z / fy, z], axis=-1).reshape(-1, 3)
    q = p @ rotation.T.astype(dtype) + translation.astype(dtype)
    qz = q[:, 2]
    ok = (z.reshape(-1) > 0) & (qz > 0)
    qzs = jnp.where(ok, qz, 1)
    u = jnp.round(dst_k[0] * q[:, 0] / qzs + dst_k[2])
    v = jnp.round(dst_k[1] * q[:, 1] / qzs + dst_k[3])
    ok = ok & (u >= 0) & (u < ww) & (v >= 0) & (v < hh)
    idx = jnp.where(ok, v.astype(jnp.int32) * ww + u.astype(jnp.int32), hh * ww)
    buf = jnp.full((hh * ww,), jnp.inf, dtype).at[idx].min(qz, mode="drop")
    return jnp.where(jnp.isfinite(buf), buf, 0).reshape(hh, ww)


def register_depth(
    depth: Float[ArrayLike, "h w"],
    depth_intrinsics: CameraIntrinsics,
    color_intrinsics: CameraIntrinsics,
    rotation: Float[ArrayLike, "3 3"],
    translation: Float[ArrayLike, 3],
) -> Float[Array, "H W"]:
    """Warp a depth image into another (colour) camera: forward projection with a z-buffer.

    Every valid depth pixel is back-projected, moved by ``p_color = R p_depth + t`` and
    projected to the nearest colour pixel; where several land on one pixel the nearest wins
    (scatter-min). Jitted; the output shape is the colour image's.

    Arguments:
        depth: depth in metres, 0 / NaN = missing.
        depth_intrinsics, color_intrinsics: the two cameras.
        rotation, translation: extrinsics ``p_color = R p_depth + t`` (metres).

    Returns:
        Depth in metres along the colour camera's axis, 0 where no depth pixel landed.
    """
    depth = jnp.asarray(depth)
    dtype = jnp.result_type(depth.dtype, jnp.float32)
    ks = [jnp.asarray([k.fx, k.fy, k.cx, k.cy], dtype) for k in (depth_intrinsics,
                                                                  color_intrinsics)]
    zero = jnp.zeros(color_intrinsics.shape, jnp.bool_)
    return _register(depth.astype(dtype), ks[0], ks[1], jnp.asarray(rotation, dtype),
                     jnp.asarray(translation, dtype), zero)


def _biwi_paths(folder: Path, frame: str | int) -> tuple[Path, Path, Path]:
    if isinstance(frame, int):
        frame = f"{frame:05d}"
    stem = folder / f"frame_{frame}"
    return (stem.with_name(stem.name + "_rgb.png"), stem.with_name(stem.name + "_depth.bin"),
            stem.with_name(stem.name + "_pose.txt"))


def read_biwi_frame(folder: PathLike, frame: str | int, *, register: bool = True,
                    timestamp: float | None = None) -> RGBDFrame:
    """Read one Biwi frame (``frame_<id>_rgb.png`` + ``_depth.bin``) with depth registered.

    Arguments:
        folder: the folder with the frame files and ``rgb.cal`` / ``depth.cal``.
        frame: frame id, e.g. ``54``, ``"00054"`` or ``"unknown"``.
        register: warp the depth into the colour camera (:func:`register_depth`); otherwise the
            raw depth-camera image is returned (and ``intrinsics`` are still the colour ones).
        timestamp: seconds (default: frame number / 30 Hz, 0 for non-numeric ids).

    Returns:
        An :class:`RGBDFrame` (BGR colour, depth in metres in the colour camera).
    """
    folder = Path(folder)
    rgb_path, depth_path, _ = _biwi_paths(folder, frame)
    rgb_cal = read_biwi_calibration(folder / "rgb.cal")
    depth_cal = read_biwi_calibration(folder / "depth.cal")
    color = _color(rgb_path)
    depth = read_biwi_depth(depth_path)
    if depth.shape != depth_cal.intrinsics.shape:
        raise RGBDFormatError(depth_path, f"depth size {depth.shape} differs from depth.cal "
                              f"{depth_cal.intrinsics.shape}")
    if color.shape[:2] != rgb_cal.intrinsics.shape:
        raise RGBDFormatError(rgb_path, f"image size {color.shape[:2]} differs from rgb.cal "
                              f"{rgb_cal.intrinsics.shape}")
    if register:
        rot = rgb_cal.rotation @ depth_cal.rotation.T
        trans = rgb_cal.translation - rot @ depth_cal.translation
        depth = np.asarray(register_depth(depth, depth_cal.intrinsics, rgb_cal.intrinsics,
                                          rot, trans), dtype=np.float32)
    stem = rgb_path.name[: -len("_rgb.png")]
    if timestamp is None:
        fid = stem[len("frame_"):]
        timestamp = int(fid) / 30.0 if fid.isdigit() else 0.0
    return RGBDFrame(color, depth, rgb_cal.intrinsics, float(timestamp), stem)


def biwi_pose_in_color_frame(
    rotation: Float[ArrayLike, "3 3"], translation: Float[ArrayLike, 3],
    calibration: BiwiCalibration,
) -> tuple[Float[np.ndarray, "3 3"], Float[np.ndarray, 3]]:
    """Move a Biwi head pose (``p_depth = R x_head + t``, metres) into the colour camera.

    Arguments:
        rotation, translation: the pose from :func:`phjax.io.read_biwi_pose` (t in metres).
        calibration: ``rgb.cal`` (:func:`read_biwi_calibration`).

    Returns:
        ``(R_c, t_c)`` with ``p_color = R_c x_head + t_c``.
    """
    r_e, t_e = calibration.rotation, calibration.translation
    return r_e @ np.asarray(rotation, np.float64), r_e @ np.asarray(translation, np.float64) + t_e


def _frame_sort_key(fid: str) -> tuple[int, float, str]:
    return (0, float(fid), "") if fid.isdigit() else (1, 0.0, fid)


#: the frame rate (Hz) of folders whose frames carry no timestamps (Biwi, ``color/`` +
#: ``depth/``), as of a video file whose header gives none
DEFAULT_FOLDER_FPS = 30.0
#: the :func:`rgbd_layout` names of those folders: their readers take ``fps``
UNTIMED_LAYOUTS = ("biwi", "pairs")


def _check_fps(fps) -> float:
    """``fps`` as a float, or a ``ValueError`` saying why it cannot time the frames."""
    try:
        value = float(fps) if not isinstance(fps, (bool, np.bool_)) else math.nan
    except (TypeError, ValueError):
        raise ValueError(f"fps must be a number of frames per second, got {fps!r}") from None
    if not (math.isfinite(value) and 0 < value <= 1000):
        raise ValueError(f"fps must be a frame rate in (0, 1000] Hz, got {fps!r}")
    return value


def read_biwi(folder: PathLike, *, fps: float = DEFAULT_FOLDER_FPS) -> RGBDSequence:
    """All Biwi frames of a folder as a lazily loaded :class:`RGBDSequence`.

    Frames are ordered by number (non-numeric ids such as ``unknown`` last); times are
    ``number / fps``, non-numeric frames continue after the last at ``1 / fps`` steps. The
    ground truth (``*_pose.txt`` where present) is given as head poses in the colour camera.

    Raises:
        ValueError: ``fps`` is not a frame rate in (0, 1000] Hz.
    """
    fps = _check_fps(fps)
    folder = Path(folder)
    ids = sorted((p.name[len("frame_"):-len("_rgb.png")] for p in folder.glob("frame_*_rgb.png")),
                 key=_frame_sort_key)
    if not ids:
        raise RGBDFormatError(folder, "no frame_*_rgb.png files (not a Biwi folder)")
    for name in ("rgb.cal", "depth.cal"):
        if not (folder / name).is_file():
            raise RGBDFormatError(folder, f"missing {name}")
    times, last = [], -1.0 / fps
    for fid in ids:
        t = int(fid) / fps if fid.isdigit() else last + 1.0 / fps
        times.append(t)
        last = t
    cal = read_biwi_calibration(folder / "rgb.cal")
    pos = np.full((len(ids), 3), np.nan)
    quat = np.full((len(ids), 4), np.nan)
    for k, fid in enumerate(ids):
        pose_path = _biwi_paths(folder, fid)[2]
        if pose_path.is_file():
            r, t = biwi_pose_in_color_frame(*read_biwi_pose(pose_path), cal)
            pos[k], quat[k] = t, biwi_pose_to_quaternion(r)
    gt = Trajectory(np.asarray(times), pos, quat) if np.isfinite(pos).any() else None
    loaders = [lambda fid=fid, t=t: read_biwi_frame(folder, fid, timestamp=t)
               for fid, t in zip(ids, times)]
    return RGBDSequence(loaders, times, cal.intrinsics, f"Biwi {folder}", gt,
                        "head" if gt is not None else None)


# ------------------------------------------------------------------------------------- TUM
#: Colour camera intrinsics of the TUM RGB-D benchmark (fx, fy, cx, cy), by sensor; "ros" are the
#: defaults of the ROS OpenNI driver (used for the undistorted/registered data as well).
TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
    "ros": (525.0, 525.0, 319.5, 239.5),
}


def _read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    if not path.is_file():
        raise RGBDFormatError(path.parent, f"missing {path.name}")
    times, names = [], []
    for lineno, line in enumerate(_read_text(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) < 2:
            raise RGBDFormatError(path, f"line {lineno}: expected 'timestamp filename', got {s!r}")
        try:
            t = float(parts[0])
        except ValueError as e:
            raise RGBDFormatError(path, f"line {lineno}: bad timestamp {parts[0]!r}") from e
        if not np.isfinite(t):
            raise RGBDFormatError(path, f"line {lineno}: non-finite timestamp")
        times.append(t)
        names.append(parts[1])
    if not times:
        raise RGBDFormatError(path, "no entries")
    return np.asarray(times), names


def associate(times_a: ArrayLike, times_b: ArrayLike, max_difference: float = 0.02
              ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one association of two timestamp lists by nearest time (TUM ``associate.py`` rule).

    Candidate pairs with ``|t_a - t_b| <= max_difference`` are accepted greedily in order of
    increasing time difference, each entry used at most once.

    Returns:
        ``(idx_a, idx_b)`` index arrays of the matched pairs, sorted by ``idx_a``.
    """
    ta = np.asarray(times_a, np.float64)
    tb = np.asarray(times_b, np.float64)
    if ta.size == 0 or tb.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    order_b = np.argsort(tb, kind="stable")
    tbs = tb[order_b]
    # candidates: every b within the window of each a (windows are small in practice)
    lo = np.searchsorted(tbs, ta - max_difference, side="left")
    hi = np.searchsorted(tbs, ta + max_difference, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(ta.size), counts)
    jb = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)]) if counts.sum() else \
        np.zeros(0, int)
    diff = np.abs(ta[ia] - tbs[jb])
    order = np.lexsort((jb, ia, diff))
    used_a = np.zeros(ta.size, bool)
    used_b = np.zeros(tb.size, bool)
    out_a, out_b = [], []
    for k in order:  # greedy; O(number of candidate pairs)
        a, b = ia[k], jb[k]
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            out_a.append(a)
            out_b.append(order_b[b])
    out_a, out_b = np.asarray(out_a, int), np.asarray(out_b, int)
    s = np.argsort(out_a)
    return out_a[s], out_b[s]


def _guess_tum_intrinsics(folder: Path, shape: tuple[int, int]) -> CameraIntrinsics:
    name = folder.resolve().name.lower()
    key = next((k for k in ("freiburg1", "freiburg2", "freiburg3") if k in name), None)
    if key is None:
        m = re.search(r"fr([123])", name)
        key = f"freiburg{m.group(1)}" if m else "ros"
    fx, fy, cx, cy = TUM_INTRINSICS[key]
    return CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=shape[1], height=shape[0])


def read_tum_rgbd(folder: PathLike, *,
                  intrinsics: CameraIntrinsics | Sequence[float] | None = None,
                  max_difference: float = 0.02, depth_scale: float = 5000.0) -> RGBDSequence:
    """A TUM RGB-D folder (``rgb.txt``, ``depth.txt``, images) as a lazy :class:`RGBDSequence`.

    Arguments:
        folder: the sequence folder.
        intrinsics: colour intrinsics, or ``(fx, fy, cx, cy)`` for the images' size (default:
            Freiburg 1/2/3 values guessed from the folder name, e.g.
            ``rgbd_dataset_freiburg1_xyz``; ROS defaults otherwise).
        max_difference: association window, s.
        depth_scale: depth units per metre (5000 for TUM).

    Returns:
        The associated frames in time order (``rgb.txt`` may list them in any order),
        timestamped with the colour image time. ``groundtruth.txt``
        (camera poses ``T_wc``), if present, becomes the ground truth, taken at the nearest
        time within ``max_difference`` of each frame (NaN rows otherwise).
    """
    folder = Path(folder)
    t_rgb, rgb_names = _read_list(folder / "rgb.txt")
    t_dep, dep_names = _read_list(folder / "depth.txt")
    ia, ib = associate(t_rgb, t_dep, max_difference)
    if ia.size == 0:
        raise RGBDFormatError(folder, f"no colour/depth pair within {max_difference} s")
    order = np.argsort(t_rgb[ia], kind="stable")  # in time order, however rgb.txt lists them
    ia, ib = ia[order], ib[order]
    first = _color(folder / rgb_names[ia[0]])
    _check_first_depth(folder / dep_names[ib[0]])
    if intrinsics is None:
        intrinsics = _guess_tum_intrinsics(folder, first.shape[:2])
    elif not isinstance(intrinsics, CameraIntrinsics):
        intrinsics = CameraIntrinsics(*[float(v) for v in intrinsics], width=first.shape[1],
                                      height=first.shape[0])
    times = t_rgb[ia]

    def load(a: int, b: int) -> RGBDFrame:
        color = _color(folder / rgb_names[a])
        depth = _depth_image(folder / dep_names[b], depth_scale)
        if depth.shape != color.shape[:2]:
            raise RGBDFormatError(folder / dep_names[b], f"depth size {depth.shape} differs from "
                                  f"colour {color.shape[:2]}")
        return RGBDFrame(color, depth, intrinsics, float(t_rgb[a]), Path(rgb_names[a]).stem)

    gt = None
    gt_path = folder / "groundtruth.txt"
    if gt_path.is_file():
        from ..io import read_tum

        traj = read_tum(gt_path)
        j, k = associate(times, traj.times, max_difference)
        pos = np.full((times.size, 3), np.nan)
        quat = np.full((times.size, 4), np.nan)
        pos[j], quat[j] = traj.positions[k], traj.quaternions[k]
        gt = Trajectory(times, pos, quat)
    loaders = [lambda a=a, b=b: load(a, b) for a, b in zip(ia, ib)]
    return RGBDSequence(loaders, times, intrinsics, f"TUM RGB-D {folder}", gt,
                        "camera" if gt is not None else None)


def write_tum_rgbd(folder: PathLike, frames: Sequence[RGBDFrame], *,
                   depth_scale: float = 5000.0) -> None:
    """Write frames as a TUM RGB-D folder (``rgb/``, ``depth/`` PNGs, ``rgb.txt``, ``depth.txt``).

    Depth is stored as 16-bit PNG with ``depth_scale`` units per metre (values clipped to
    ``[0, 65535]``; NaN written as 0). Depth images get the colour timestamp + 1e-4 s.
    """
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines = ["# color images", "# timestamp filename"]
    dep_lines = ["# depth maps", "# timestamp filename"]
    for f in frames:
        t = f"{f.timestamp:.6f}"
        td = f"{f.timestamp + 1e-4:.6f}"
        _write_png(folder / "rgb" / f"{t}.png", np.ascontiguousarray(f.color))
        d = np.nan_to_num(np.asarray(f.depth, np.float64), nan=0.0)
        raw = np.clip(np.rint(d * depth_scale), 0, 65535).astype(np.uint16)
        _write_png(folder / "depth" / f"{td}.png", raw)
        rgb_lines.append(f"{t} rgb/{t}.png")
        dep_lines.append(f"{td} depth/{td}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n", encoding="utf-8")
    (folder / "depth.txt").write_text("\n".join(dep_lines) + "\n", encoding="utf-8")


# ----------------------------------------------------------------------------------- pairs
def read_rgbd_pair(color_path: PathLike, depth_path: PathLike, intrinsics: CameraIntrinsics
                   | Sequence[float], *, depth_scale: float = 1000.0, timestamp: float = 0.0
                   ) -> RGBDFrame:
    """A registered colour image + 16-bit depth image (PNG or binary PGM).

    Arguments:
        color_path, depth_path: the two images (same size).
        intrinsics: :class:`CameraIntrinsics` or ``(fx, fy, cx, cy)``.
        depth_scale: depth units per metre (1000 = millimetres).
        timestamp: seconds.
    """
    color = _color(color_path)
    depth = _depth_image(depth_path, depth_scale)
    if depth.shape != color.shape[:2]:
        raise RGBDFormatError(depth_path, f"depth size {depth.shape} differs from colour "
                              f"{color.shape[:2]}")
    if not isinstance(intrinsics, CameraIntrinsics):
        vals = [float(v) for v in intrinsics]
        if len(vals) != 4:
            raise ValueError("intrinsics must be CameraIntrinsics or (fx, fy, cx, cy)")
        intrinsics = CameraIntrinsics(*vals, width=color.shape[1], height=color.shape[0])
    return RGBDFrame(color, depth, intrinsics, float(timestamp), Path(color_path).stem)


def read_pose_list(path: PathLike) -> Trajectory:
    """Poses ``tx ty tz qx qy qz qw`` one per line (no timestamps; slambook ``pose.txt``).

    Returns:
        A :class:`phjax.io.Trajectory` with times ``0, 1, 2, ...`` (line index), positions and
        ``wxyz`` quaternions as stored (not made hemisphere-continuous).
    """
    path = Path(path)
    rows = []
    for lineno, line in enumerate(_read_text(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 7:
            raise RGBDFormatError(path, f"line {lineno}: expected 7 values 'tx ty tz qx qy qz "
                                  f"qw', got {len(parts)}")
        try:
            vals = [float(v) for v in parts]
        except ValueError as e:
            raise RGBDFormatError(path, f"line {lineno}: {e}") from e
        q = np.asarray(vals[3:])
        if not np.all(np.isfinite(vals)) or np.linalg.norm(q) < 1e-9:
            raise RGBDFormatError(path, f"line {lineno}: non-finite value or zero quaternion")
        rows.append(vals)
    if not rows:
        raise RGBDFormatError(path, "no poses")
    a = np.asarray(rows)
    q = a[:, [6, 3, 4, 5]]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return Trajectory(np.arange(len(a), dtype=np.float64), a[:, :3], q)


#: Intrinsics of the slambook2 chapter-5 RGB-D frames (``joinMap.cpp``; NYU Depth v2 Kinect).
SLAMBOOK_INTRINSICS = (518.0, 519.0, 325.5, 253.5)


def read_slambook(folder: PathLike, *, intrinsics: CameraIntrinsics | Sequence[float] =
                  SLAMBOOK_INTRINSICS, depth_scale: float = 1000.0,
                  fps: float = DEFAULT_FOLDER_FPS) -> RGBDSequence:
    """A ``color/`` + ``depth/`` folder, as the slambook2 ``ch5/rgbd`` layout: ``color/N.png``,
    ``depth/N.pgm`` (or ``.png``), optional ``pose.txt``.

    The files carry no timestamps: frames are ordered by ``N`` and timed ``k / fps`` (the
    ``k``-th frame; 30 Hz by default, as a camera capture). The slambook2 frames are keyframes
    taken seconds apart, not a video: ``fps=1`` plays them a second apart. ``pose.txt``
    (camera-to-world ``T_wc``, metres) becomes the ground truth (kind ``"camera"``).

    Raises:
        RGBDFormatError: a missing depth image, an unreadable first image, a bad ``pose.txt``.
        ValueError: ``fps`` is not a frame rate in (0, 1000] Hz.
    """
    fps = _check_fps(fps)
    folder = Path(folder)
    colors = sorted((folder / "color").glob("*.png"), key=lambda p: (len(p.stem), p.stem))
    if not colors:
        raise RGBDFormatError(folder, "no color/*.png files")
    pairs = []
    for c in colors:
        cands = [folder / "depth" / f"{c.stem}{ext}" for ext in (".pgm", ".png")]
        d = next((p for p in cands if p.is_file()), None)
        if d is None:
            raise RGBDFormatError(folder, f"no depth image for {c.name} (depth/{c.stem}.pgm|png)")
        pairs.append((c, d))
    first = _color(colors[0])
    _check_first_depth(pairs[0][1])
    if not isinstance(intrinsics, CameraIntrinsics):
        intrinsics = CameraIntrinsics(*[float(v) for v in intrinsics], width=first.shape[1],
                                      height=first.shape[0])
    times = np.arange(len(pairs), dtype=np.float64) / fps
    gt = None
    if (folder / "pose.txt").is_file():
        poses = read_pose_list(folder / "pose.txt")
        if poses.num_samples != len(pairs):
            raise RGBDFormatError(folder / "pose.txt", f"{poses.num_samples} poses for "
                                  f"{len(pairs)} frames")
        gt = Trajectory(times, poses.positions, poses.quaternions)
    loaders = [lambda c=c, d=d, t=t: read_rgbd_pair(c, d, intrinsics, depth_scale=depth_scale,
                                                    timestamp=t)
               for (c, d), t in zip(pairs, times)]
    return RGBDSequence(loaders, times, intrinsics, f"slambook {folder}", gt,
                        "camera" if gt is not None else None)


# ------------------------------------------------------------------------------- synthetic
def synthetic_rgbd(num_frames: int = 90, seed: int = 0, **kwargs: Any) -> RGBDSequence:
    """The rendered synthetic head sequence of :mod:`phjax.vision.synthetic_rgbd` as an
    :class:`RGBDSequence` (BGR colour, :class:`CameraIntrinsics`, head-pose ground truth).

    Keyword arguments go to :func:`phjax.vision.synthetic_rgbd.synthetic_rgbd_sequence` (e.g.
    ``rate``, ``width``, ``height``, ``depth_noise``). Frames are rendered on access.
    """
    from .synthetic_rgbd import synthetic_rgbd_sequence

    seq = synthetic_rgbd_sequence(int(num_frames), seed=int(seed), **kwargs)
    k = seq.intrinsics
    intr = CameraIntrinsics(fx=float(k.fx), fy=float(k.fy), cx=float(k.cx), cy=float(k.cy),
                            width=seq.width, height=seq.height)

    def load(i: int) -> RGBDFrame:
        f = seq[i]
        return RGBDFrame(np.ascontiguousarray(f.color[..., ::-1]), f.depth, intr,
                         f.timestamp, f"synthetic_{i:05d}")

    gt = Trajectory(np.asarray(seq.timestamps, np.float64), np.asarray(seq.head_positions),
                    np.asarray(seq.head_quaternions))
    return RGBDSequence([functools.partial(load, i) for i in range(len(seq))], seq.timestamps,
                        intr, f"synthetic head (seed {seed})", gt, "head")


# --------------------------------------------------------------------------------- detection
def rgbd_layout(source: PathLike) -> str:
    """The layout :func:`open_rgbd` reads ``source`` as: ``"synthetic"``, ``"biwi"``,
    ``"tum"`` or ``"pairs"`` (a ``color/`` + ``depth/`` folder).

    Raises:
        FileNotFoundError: the path does not exist.
        RGBDFormatError: the layout is not recognised.
    """
    if isinstance(source, str) and (source == "synthetic" or source.startswith("synthetic:")):
        return "synthetic"
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"RGB-D source not found: {path}")
    if path.is_dir():
        if any(path.glob("frame_*_rgb.png")):
            return "biwi"
        if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
            return "tum"
        if (path / "color").is_dir() and (path / "depth").is_dir():
            return "pairs"
    raise RGBDFormatError(path, "unrecognised RGB-D source (expected a Biwi, TUM RGB-D or "
                          "color/ + depth/ folder)")


def open_rgbd(source: PathLike, **kwargs: Any) -> RGBDSequence:
    """Open an RGB-D source, detecting its layout.

    * a folder with ``frame_*_rgb.png`` + ``*.cal``: Biwi (:func:`read_biwi`);
    * a folder with ``rgb.txt`` and ``depth.txt``: TUM RGB-D (:func:`read_tum_rgbd`);
    * a folder with ``color/`` and ``depth/``: slambook-style pairs (:func:`read_slambook`);
    * ``"synthetic"`` or ``"synthetic:N"`` / ``"synthetic:N:SEED"``: N rendered frames of the
      synthetic head (:func:`synthetic_rgbd`; default 90 frames, seed 0).

    Keyword arguments go to the reader.

    Raises:
        FileNotFoundError: the path does not exist.
        RGBDFormatError: the layout is not recognised.
    """
    layout = rgbd_layout(source)
    if layout == "synthetic":
        parts = str(source).split(":")[1:]
        try:
            vals = [int(v) for v in parts]
        except ValueError as e:
            raise ValueError(f"bad synthetic source {source!r}; use synthetic[:N[:SEED]]") from e
        if len(vals) > 2:
            raise ValueError(f"bad synthetic source {source!r}; use synthetic[:N[:SEED]]")
        return synthetic_rgbd(*vals, **kwargs)
    reader = {"biwi": read_biwi, "tum": read_tum_rgbd, "pairs": read_slambook}[layout]
    return reader(Path(source), **kwargs)

