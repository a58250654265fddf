"""Face detection with YuNet: OpenCV (``cv2.FaceDetectorYN``, ONNX) or kornia (torch) backend.

Both backends run the same network (YuNet, Yu et al., "YuNet: a tiny millisecond-level face
detector", Machine Intelligence Research 2023) and return the same :class:`FaceDetection`:
a box ``(x, y, w, h)``, five landmarks and a score, in pixels of the **full-resolution** input.
The landmarks are, in this order, the subject's right eye, left eye, nose tip, right mouth corner
and left mouth corner (the subject's right eye appears on the image's left).

For speed the image is downscaled before detection (``detect_width``, default 320 px, about
5 ms per 320x240 frame with OpenCV instead of ~20-36 ms at 640x480) and the results are scaled
back. Images are ``uint8 (H, W, 3)`` **BGR** (OpenCV order) for both backends; the kornia
backend converts to the RGB ``[0, 255]`` input that ``kornia.contrib.FaceDetector`` expects.

Plausibility check
------------------
Every detection of either backend passes one check (:func:`plausible_detection`, on the
downscaled image the network saw) before it is returned:

* its numbers are finite and its box is at least :data:`MIN_BOX_PX` px wide and high;
* at most :data:`MAX_OUTSIDE_FRACTION` (a quarter) of the box's width and of its height lie
  outside the image (measured: YuNet's boxes of real faces cut off by the image edge reach
  at most 13 % past it, on the 16 AFLW2000-3D photos shifted down by 100-250 px);
* the grey pixels inside the box are spatially correlated: the lag-1 autocorrelation
  (horizontal and vertical neighbours, averaged) is at least :data:`MIN_PIXEL_CORRELATION`
  (0.5). Natural images, faces included, are smooth at the detector's scale; pixel noise is
  not. Measured at the default ``detect_width``: 0.86-0.997 on real and synthetic faces
  (the 16 AFLW photos, rotated in the image plane by up to 45 degrees, shifted, cropped to
  close-ups that fill the frame, or with Gaussian noise of std 40 added; 3 Biwi frames; the
  synthetic head of :mod:`phjax.vision.synthetic_rgbd`), at most 0.18 on the kornia
  backend's false detections in uniform, Gaussian and salt-and-pepper noise (240x320 to
  720x1280, square and portrait frames included).

The check exists because the kornia weights report a face covering most of a square or
portrait frame of pixel noise with a score up to 0.999, higher than on many real faces, and
those false faces have face-like landmarks (the network's prior) and boxes only 0-4 % past
the image edge, so neither the score nor the landmark geometry can reject them. A
structured, smooth non-face pattern (a coarse checkerboard) can still pass it.

Model files
-----------
The weights are not bundled. They live in a cache directory (:func:`model_dir`: the
``model_dir`` argument, else ``$PHJAX_MODEL_DIR``, else ``~/.cache/phjax/models``) and are
verified by SHA-256 before use:

* ``face_detection_yunet_2023mar.onnx`` (OpenCV backend), from the OpenCV Zoo;
* ``yunet_final.pth`` (kornia backend), from ``kornia/data``. kornia itself looks for it in the
  torch hub cache (``$TORCH_HOME/hub/checkpoints/yunet_final.pth``); we place a verified copy
  there when it is missing (so kornia never downloads) and load our cached state dict into the
  network explicitly;
* ``head-pose-0.4-small-int8.onnx`` and ``head-localizer.onnx`` (the monocular head pose of
  :mod:`phjax.vision.monocular`), from ``opentrack/opentrack`` (``tracker-neuralnet/models``).
  The code is ISC-licensed but the weights were trained partly on data licensed for
  non-commercial or research use only: **use them for research / non-commercial purposes only**.

:func:`download_model` fetches a file with ``urllib`` (only when asked: ``download=True`` or
``phjax.vision.face_detection.download_model(...)``); :func:`seed_model_cache` copies the files from a
local folder (any file whose SHA-256 matches a known model, whatever its name).
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os
import shutil
import tempfile
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._misc import check_count
from .features import _require

__all__ = [
    "FaceDetection",
    "ModelFile",
    "YUNET_ONNX",
    "YUNET_KORNIA",
    "MODELS",
    "HEAD_POSE_ONNX",
    "HEAD_LOCALIZER_ONNX",
    "KNOWN_MODELS",
    "ModelNotFoundError",
    "model_dir",
    "sha256_file",
    "model_path",
    "download_model",
    "seed_model_cache",
    "FaceDetector",
    "BACKENDS",
    "DEFAULT_SCORE_THRESHOLD",
    "MAX_OUTSIDE_FRACTION",
    "MIN_BOX_PX",
    "MIN_PIXEL_CORRELATION",
    "plausible_detection",
]

BACKENDS = ("opencv", "kornia")
#: Default minimum detection score per backend (the two backends' scores are not comparable).
DEFAULT_SCORE_THRESHOLD = {"opencv": 0.6, "kornia": 0.9}
#: plausibility check (module docs): largest fraction of a box's width / height outside the
#: image (real faces at the edge: at most 0.13)
MAX_OUTSIDE_FRACTION = 0.25
#: plausibility check: smallest lag-1 autocorrelation of the grey pixels in the box at the
#: detection resolution (real faces 0.86-0.997; false faces in pixel noise at most 0.18)
MIN_PIXEL_CORRELATION = 0.5
#: plausibility check: smallest box side at the detection resolution, px (the correlation
#: needs pixels; YuNet's smallest anchor is 10 px)
MIN_BOX_PX = 4.0
#: candidates each backend keeps before its non-maximum suppression
_PRE_NMS_TOP_K = 5000


# --------------------------------------------------------------------------------- result type
class FaceDetection(NamedTuple):
    """One detected face (pixels of the full-resolution image).

    Attributes:
        box: ``(4,)`` ``x, y, w, h`` (top-left corner, width, height), float32.
        landmarks: ``(5, 2)`` ``(u, v)`` of right eye, left eye, nose tip, right mouth corner,
            left mouth corner (the subject's right/left), float32.
        score: detection confidence in ``[0, 1]``.
    """

    box: np.ndarray
    landmarks: np.ndarray
    score: float

    @property
    def center(self) -> np.ndarray:
        """Box centre ``(u, v)``."""
        return self.box[:2] + 0.5 * self.box[2:]

    def scaled(self, sx: float, sy: float | None = None) -> FaceDetection:
        """The detection in an image resized by ``(sx, sy)`` (pixel centres kept)."""
        sy = sx if sy is None else sy
        s = np.asarray([sx, sy], np.float32)
        xy = (self.box[:2] + 0.5) * s - 0.5
        lm = (self.landmarks + 0.5) * s - 0.5
        return FaceDetection(np.concatenate([xy, self.box[2:] * s]).astype(np.float32),
                             lm.astype(np.float32), float(self.score))

    def to_array(self) -> np.ndarray:
        """The 15 numbers ``x, y, w, h, (u, v) x 5, score`` (OpenCV's row layout)."""
        return np.concatenate([self.box, self.landmarks.ravel(), [self.score]]).astype(
            np.float32)

    @classmethod
    def from_array(cls, row: Any) -> FaceDetection:
        """From OpenCV's 15-number row ``x, y, w, h, landmarks..., score``."""
        row = np.asarray(row, np.float32)
        if row.shape[-1] < 15:
            raise ValueError(f"a detection row needs 15 numbers, got {row.shape[-1]}")
        return cls(row[:4].copy(), row[4:14].reshape(5, 2).copy(), float(row[14]))


# ------------------------------------------------------------------------------------- models
@dataclass(frozen=True)
class ModelFile:
    """A downloadable model file with its checksum."""

    name: str
    filename: str
    sha256: str
    size: int
    urls: tuple[str, ...]
    licence: str = ""


YUNET_ONNX = ModelFile(
    name="yunet-onnx",
    filename="face_detection_yunet_2023mar.onnx",
    sha256="8f2383e4dd3cfbb4553ea8718107fc0423210dc964f9f4280604804ed2552fa4",
    size=232589,
    urls=(
        ("https://github.com/opencv/opencv_zoo/raw/main/models/face_detection_yunet/"
         "face_detection_yunet_2023mar.onnx"),
    ),
    licence="MIT (OpenCV Zoo) / Apache-2.0 (ShiqiYu/libfacedetection.train)",
)
YUNET_KORNIA = ModelFile(
    name="yunet-kornia",
    filename="yunet_final.pth",
    sha256="ee0a3035c5cbfc9484a31332223c9fd9c0ddcdb7c46b6a19e558ed393b6f2c67",
    size=405729,
    urls=(
        "https://github.com/kornia/data/raw/main/yunet_final.pth",
        "https://huggingface.co/kornia/yunet/resolve/main/yunet_final.pth",
    ),
    licence="Apache-2.0 (kornia)",
)
MODELS = {"opencv": YUNET_ONNX, "kornia": YUNET_KORNIA}

_OPENTRACK_RAW = "https://github.com/opentrack/opentrack/raw/{}/tracker-neuralnet/models/{}"
_OPENTRACK_LICENCE = ("code ISC (opentrack tracker-neuralnet); weights trained partly on "
                      "non-commercial data: research / non-commercial use only")
#: opentrack's head-pose network (:mod:`phjax.vision.monocular`), int8-quantised ONNX
HEAD_POSE_ONNX = ModelFile(
    name="head-pose",
    filename="head-pose-0.4-small-int8.onnx",
    sha256="fc887eda67f45621c1ed1ed12b8d23531880d0e830ea6bc431b659ff12877820",
    size=3529912,
    urls=(_OPENTRACK_RAW.format("766808196cf63ddf9ceb102fba193582daceb9de",
                                "head-pose-0.4-small-int8.onnx"),),
    licence=_OPENTRACK_LICENCE,
)
#: opentrack's whole-frame head localizer (optional detector of :mod:`phjax.vision.monocular`)
HEAD_LOCALIZER_ONNX = ModelFile(
    name="head-localizer",
    filename="head-localizer.onnx",
    sha256="f26679fe5e01a08dab0b3b9b586b613c68622775e0b8e14ddae53f30391f7402",
    size=279403,
    urls=(_OPENTRACK_RAW.format("f009bb52cab7bf3884b8a9b3a326aa9ce84d6299",
                                "head-localizer.onnx"),),
    licence=_OPENTRACK_LICENCE,
)
#: every model file the cache knows (YuNet and the monocular head-pose models): looked up by
#: name, copied by :func:`seed_model_cache`
KNOWN_MODELS = (YUNET_ONNX, YUNET_KORNIA, HEAD_POSE_ONNX, HEAD_LOCALIZER_ONNX)


class ModelNotFoundError(FileNotFoundError):
    """A model file is missing from the cache (the message says how to get it)."""


def model_dir(path: str | os.PathLike | None = None) -> Path:
    """The model cache directory: ``path``, else ``$PHJAX_MODEL_DIR``, else
    ``~/.cache/phjax/models`` (not created here)."""
    if path is not None:
        return Path(path).expanduser()
    env = os.environ.get("PHJAX_MODEL_DIR")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "phjax" / "models"


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _model(model: ModelFile | str) -> ModelFile:
    if isinstance(model, ModelFile):
        return model
    for m in KNOWN_MODELS:
        if model in (m.name, m.filename):
            return m
    if model in MODELS:
        return MODELS[model]
    raise ValueError(f"unknown model {model!r}; known: {[m.name for m in KNOWN_MODELS]}")


def _instructions(m: ModelFile, directory: Path) -> str:
    return (f"model file {m.filename} not found in {directory}. Get it with "
            f"phjax.vision.face_detection.download_model({m.name!r}) (downloads {m.urls[0]}), or "
            f"download it yourself into that folder (sha256 {m.sha256}), or copy it from a "
            f"local folder with phjax.vision.face_detection.seed_model_cache(FOLDER); the folder can be "
            f"set with $PHJAX_MODEL_DIR.")


def model_path(model: ModelFile | str, directory: str | os.PathLike | None = None, *,
               download: bool = False) -> Path:
    """Path of a verified model file in the cache.

    Arguments:
        model: a :class:`ModelFile` of :data:`KNOWN_MODELS` or a model name / file name.
        directory: the cache directory (default :func:`model_dir`).
        download: fetch it (:func:`download_model`) when missing.

    Raises:
        ModelNotFoundError: missing (and ``download`` is false).
        ValueError: the cached file's SHA-256 does not match.
    """
    m = _model(model)
    d = model_dir(directory)
    p = d / m.filename
    if not p.is_file():
        if not download:
            raise ModelNotFoundError(_instructions(m, d))
        return download_model(m, d)
    digest = sha256_file(p)
    if digest != m.sha256:
        raise ValueError(f"{p}: sha256 {digest} does not match the expected {m.sha256}; delete "
                         "the file and fetch it again")
    return p


def download_model(model: ModelFile | str, directory: str | os.PathLike | None = None, *,
                   timeout: float = 60.0) -> Path:
    """Download a model file into the cache (tries each URL; verifies SHA-256; atomic rename).

    Raises:
        OSError: every URL failed (the last error is chained).
        ValueError: the downloaded bytes have the wrong SHA-256.
    """
    m = _model(model)
    d = model_dir(directory)
    d.mkdir(parents=True, exist_ok=True)
    last: Exception | None = None
    for url in m.urls:
        fd, tmp = tempfile.mkstemp(dir=d, prefix=f".{m.filename}.", suffix=".part")
        try:
            with os.fdopen(fd, "wb") as out, urllib.request.urlopen(url, timeout=timeout) as r:
                shutil.copyfileobj(r, out)
            digest = sha256_file(tmp)
            if digest != m.sha256:
                raise ValueError(f"{url}: sha256 {digest} != expected {m.sha256}")
            final = d / m.filename
            os.replace(tmp, final)
            return final
        except (OSError, ValueError) as e:
            last = e
            if os.path.exists(tmp):
                os.unlink(tmp)
    raise OSError(f"could not download {m.filename} from {list(m.urls)}") from last


def seed_model_cache(from_dir: str | os.PathLike, directory: str | os.PathLike | None = None
                     ) -> list[Path]:
    """Copy known model files from a local folder into the cache (no network).

    Every regular file in ``from_dir`` whose size and SHA-256 match a known model
    (:data:`KNOWN_MODELS`) is copied to
    the cache under the model's canonical file name (so e.g. ``kornia_yunet_final.pth`` becomes
    ``yunet_final.pth``).

    Returns:
        The cached paths (one per model found).

    Raises:
        FileNotFoundError: ``from_dir`` is not a folder.
    """
    src = Path(from_dir)
    if not src.is_dir():
        raise FileNotFoundError(f"not a folder: {src}")
    d = model_dir(directory)
    by_size = {m.size: m for m in KNOWN_MODELS}
    out = []
    for p in sorted(src.iterdir()):
        if not p.is_file():
            continue
        m = by_size.get(p.stat().st_size)
        if m is None or sha256_file(p) != m.sha256:
            continue
        d.mkdir(parents=True, exist_ok=True)
        dst = d / m.filename
        if not (dst.is_file() and sha256_file(dst) == m.sha256):
            fd, tmp = tempfile.mkstemp(dir=d, prefix=f".{m.filename}.", suffix=".part")
            os.close(fd)
            shutil.copyfile(p, tmp)
            os.replace(tmp, dst)
        out.append(dst)
    return out


# ------------------------------------------------------------------------------------ backends
def _real(x: Any) -> bool:
    """A real number (not a bool) that is finite."""
    return (isinstance(x, numbers.Real) and not isinstance(x, bool)
            and math.isfinite(float(x)))


def _check_image(image: Any) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 (H, W, 3) BGR image, got {img.dtype} {img.shape}")
    return img


class _OpenCVYuNet:
    def __init__(self, path: Path, score_threshold: float, nms_threshold: float):
        cv2 = _require("cv2")
        self._cv2 = cv2
        self._det = cv2.FaceDetectorYN.create(str(path), "", (320, 240), score_threshold,
                                              nms_threshold, _PRE_NMS_TOP_K)
        self._size: tuple[int, int] = (320, 240)

    def __call__(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        out = []
        for img in images:
            size = (img.shape[1], img.shape[0])
            if size != self._size:
                self._det.setInputSize(size)
                self._size = size
            _, faces = self._det.detect(img)
            out.append(np.zeros((0, 15), np.float32) if faces is None
                       else np.asarray(faces, np.float32).reshape(-1, 15))
        return out


_KORNIA_MIN_SIZE = 64


class _KorniaYuNet:
    def __init__(self, path: Path, score_threshold: float, nms_threshold: float,
                 device: str, torch_threads: int | None):
        torch = _require("torch")
        _require("kornia")
        if torch_threads is not None:
            torch.set_num_threads(int(torch_threads))

        _place_in_torch_hub(path)
        from kornia.contrib import FaceDetector as _KFD

        self._torch = torch
        self._det = _KFD(top_k=_PRE_NMS_TOP_K, confidence_threshold=score_threshold,
                         nms_threshold=nms_threshold, keep_top_k=_PRE_NMS_TOP_K)
        state = torch.load(str(path), map_location="cpu", weights_only=True)
        self._det.model.load_state_dict(state, strict=True)
        self._det = self._det.to(device).eval()
        self._device = device

    def __call__(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        torch = self._torch
        shapes = {img.shape for img in images}
        groups: dict[tuple, list[int]] = {s: [] for s in shapes}
        for i, img in enumerate(images):
            groups[img.shape].append(i)
        out: list[np.ndarray | None] = [None] * len(images)
        with torch.inference_mode():
            for idx in groups.values():
                # BGR uint8 -> RGB float [0, 255], (B, 3, H, W); kornia flips back to BGR
                batch = np.stack([images[i][..., ::-1] for i in idx])
                h, w = batch.shape[1:3]
                if h < _KORNIA_MIN_SIZE or w < _KORNIA_MIN_SIZE:
                    # the network's pooling needs 64 px; zero padding (bottom, right) keeps
                    # every pixel's coordinates and adds no face
                    batch = np.pad(batch, ((0, 0), (0, max(_KORNIA_MIN_SIZE - h, 0)),
                                           (0, max(_KORNIA_MIN_SIZE - w, 0)), (0, 0)))
                x = torch.from_numpy(np.ascontiguousarray(batch)).to(self._device)
                x = x.permute(0, 3, 1, 2).float()
                dets = self._det(x)
                for i, d in zip(idx, dets):
                    d = d.detach().cpu().numpy().astype(np.float32).reshape(-1, 15)
                    row = d.copy()  # kornia: x1, y1, x2, y2 -> x, y, w, h
                    row[:, 2:4] = d[:, 2:4] - d[:, 0:2]
                    out[i] = row
        return out  # type: ignore[return-value]


def _lag1_correlation(grey: np.ndarray) -> float:
    """Mean of the horizontal and vertical lag-1 autocorrelation of a 2-D array (NaN if flat)."""
    c = grey.astype(np.float64)
    c = c - c.mean()
    var = float(np.mean(c * c))
    if not var > 0:
        return float("nan")
    return 0.5 * (float(np.mean(c[:, 1:] * c[:, :-1])) + float(np.mean(c[1:] * c[:-1]))) / var


def plausible_detection(face: FaceDetection, image: np.ndarray) -> bool:
    """Whether a detection passes the plausibility check of the module docs.

    Arguments:
        face: a detection in pixels of ``image``.
        image: the ``uint8 (H, W, 3)`` BGR image it was found in (in :class:`FaceDetector`:
            the downscaled copy the network saw).
    """
    box = np.asarray(face.box, np.float64)
    if not (np.isfinite(box).all() and np.isfinite(face.landmarks).all()
            and math.isfinite(face.score)):
        return False
    x, y, w, h = box
    if not (w >= MIN_BOX_PX and h >= MIN_BOX_PX):
        return False
    img_h, img_w = image.shape[:2]
    x0, y0, x1, y1 = max(x, 0.0), max(y, 0.0), min(x + w, img_w), min(y + h, img_h)
    if (w - (x1 - x0)) > MAX_OUTSIDE_FRACTION * w or (h - (y1 - y0)) > MAX_OUTSIDE_FRACTION * h:
        return False
    r0, r1 = int(math.floor(y0)), int(math.ceil(y1))
    c0, c1 = int(math.floor(x0)), int(math.ceil(x1))
    crop = image[r0:r1, c0:c1]
    if crop.shape[0] < 2 or crop.shape[1] < 2:
        return False
    grey = crop.astype(np.float64) @ np.array([0.114, 0.587, 0.299])  # BGR -> luma
    return bool(_lag1_correlation(grey) >= MIN_PIXEL_CORRELATION)


def _place_in_torch_hub(path: Path) -> None:
    """Put a verified ``yunet_final.pth`` where kornia's torch-hub loader looks, if missing."""
    import torch

    dst = Path(torch.hub.get_dir()) / "checkpoints" / YUNET_KORNIA.filename
    if dst.is_file():
        return  # kornia loads it; our verified state dict is loaded over it afterwards
    dst.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=dst.parent, prefix=".yunet_final.", suffix=".part")
    os.close(fd)
    shutil.copyfile(path, tmp)
    os.replace(tmp, dst)


class FaceDetector:
    """YuNet face detector (OpenCV or kornia backend) on a downscaled copy of the image.

    Arguments:
        backend: ``"opencv"`` (default; ``cv2.FaceDetectorYN``) or ``"kornia"``
            (``kornia.contrib.FaceDetector``, torch; batched).
        model_dir: model cache directory (default :func:`model_dir`).
        detect_width: a wider image is downscaled to this width (aspect kept) before
            detection (a narrower one is not enlarged); ``None`` = full resolution.
        score_threshold: minimum score of a detection (default
            :data:`DEFAULT_SCORE_THRESHOLD` of the backend). The backends score differently:
            OpenCV's is 0.87-0.95 on faces and below 0.4 on blank and noise images; kornia's
            ``sqrt(cls * iou)`` is 0.85-1.0 on faces but up to 0.999 on uniform, Gaussian and
            salt-and-pepper noise in square and portrait frames (a box over most of the
            image), so no threshold separates them there: the plausibility check of the
            module docs rejects those boxes (for both backends). The OpenCV backend is the
            default. A number in ``[0, 1]``.
        nms_threshold: IoU threshold of the non-maximum suppression, in ``(0, 1]``.
        top_k: maximum number of faces returned per image (the best-scoring plausible ones;
            the same meaning for both backends), an integer ``>= 1``.
        download: download the model if it is missing from the cache.
        device: torch device of the kornia backend.
        torch_threads: kornia backend: ``torch.set_num_threads`` value (process-wide), or
            ``None`` to leave torch's setting alone. The default 1 is deliberate: on a
            2-core machine whose cores are shared with JAX's thread pool, 2 intra-op threads
            made every torch op wait ~10 ms (0.6 s per 320x240 frame instead of 33 ms).

    Raises:
        ValueError: an argument is out of range.
        ModelNotFoundError: the model file is not cached (and ``download`` is false).
        ImportError: the backend's package is not installed.
    """

    def __init__(self, backend: str = "opencv", *, model_dir: str | os.PathLike | None = None,
                 detect_width: int | None = 320, score_threshold: float | None = None,
                 nms_threshold: float = 0.3, top_k: int = 20, download: bool = False,
                 device: str = "cpu", torch_threads: int | None = 1):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if detect_width is not None and int(detect_width) < 32:
            raise ValueError(f"detect_width must be >= 32 or None, got {detect_width}")
        if score_threshold is None:
            score_threshold = DEFAULT_SCORE_THRESHOLD[backend]
        if not _real(score_threshold) or not 0.0 <= float(score_threshold) <= 1.0:
            raise ValueError(f"score_threshold must be a number in [0, 1], got {score_threshold!r}")
        if not _real(nms_threshold) or not 0.0 < float(nms_threshold) <= 1.0:
            raise ValueError(f"nms_threshold must be a number in (0, 1], got {nms_threshold!r}")
        top_k = check_count(top_k, "top_k")
        self.backend = backend
        self.detect_width = None if detect_width is None else int(detect_width)
        self.score_threshold = float(score_threshold)
        self.nms_threshold = float(nms_threshold)
        self.top_k = int(top_k)
        path = model_path(MODELS[backend], model_dir, download=download)
        if backend == "opencv":
            self._impl: Any = _OpenCVYuNet(path, self.score_threshold, self.nms_threshold)
        else:
            self._impl = _KorniaYuNet(path, self.score_threshold, self.nms_threshold, device,
                                      torch_threads)

    def _resize(self, img: np.ndarray) -> tuple[np.ndarray, float, float]:
        h, w = img.shape[:2]
        if self.detect_width is None or self.detect_width >= w:
            return img, 1.0, 1.0
        cv2 = _require("cv2")

        nw = self.detect_width
        nh = max(round(h * nw / w), 1)
        small = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        return small, w / nw, h / nh

    def detect_batch(self, images: Sequence[np.ndarray]) -> list[list[FaceDetection]]:
        """Detect faces in several images (one network batch per image size with kornia).

        Returns:
            One list per image: at most ``top_k`` faces that pass the plausibility check
            (module docs), sorted by decreasing score.
        """
        imgs = [_check_image(im) for im in images]
        small, scales = [], []
        for im in imgs:
            s, sx, sy = self._resize(im)
            small.append(s)
            scales.append((sx, sy))
        rows = self._impl(small)
        out = []
        for r, s, (sx, sy) in zip(rows, small, scales):
            faces = [f for f in (FaceDetection.from_array(x) for x in r)
                     if plausible_detection(f, s)]
            faces.sort(key=lambda f: -f.score)
            faces = faces[:self.top_k]
            if sx != 1.0 or sy != 1.0:
                faces = [f.scaled(sx, sy) for f in faces]
            out.append(faces)
        return out

    def detect(self, image: np.ndarray) -> list[FaceDetection]:
        """Faces in one ``uint8 (H, W, 3)`` BGR image, sorted by decreasing score."""
        return self.detect_batch([image])[0]

    def __repr__(self) -> str:
        return f"FaceDetector(backend={self.backend!r}, detect_width={self.detect_width})"
