"""opentrack's neural-net head pose (ONNX through onnxruntime): crop, inference, decoding.

Two networks of opentrack's ``tracker-neuralnet`` (M. Welter; models in
``opentrack/opentrack``, ``tracker-neuralnet/models``), found in the model cache
(:func:`phjax.vision.face_detection.model_path`):

* :class:`HeadPoseNet` (``head-pose-0.4-small-int8.onnx``): from a grey face crop, the head's
  rotation, its centre and size in the image, a face box and the predicted uncertainty of the
  rotation and of the centre / size.
* :class:`HeadLocalizer` (``head-localizer.onnx``): one head box and a score for a whole frame.

The crop and the input scaling follow opentrack's ``model_adapters.cpp``: a square patch of side
``int(1.05 max(w, h))`` about the box centre (``cv2.getRectSubPix``, edge pixels repeated outside
the frame), area-resized to 129 x 129, brightness-normalised (``x = pixel * a - 0.5`` with
``a = 0.45 / max(5, b)`` where the patch's 90th-percentile grey level ``b`` is below 127, else
``1 / 255``). Network positions are in half-patch units (``-1..1`` spans the patch), converted
to pixels as ``centre + 0.5 * side * v``.

Rotation convention of the network's ``quat`` output (``x, y, z, w``): it rotates head-frame
vectors into the image frame (``x`` right, ``y`` down, ``z`` into the scene) and is the identity
for a face squarely facing the viewer, *as seen in the crop* (relative to the viewing ray through
the face, not to the camera's optical axis). That is the AFLW2000-3D label convention, checked on
the shared AFLW sample in ``tests/vision/test_head_pose_net.py``.

The int8 network does not run in OpenCV's DNN module (4.14 and 5.0 both stop with an error in a
``Gather`` layer); onnxruntime (the ``vision`` extra) runs it. Weights: research /
non-commercial use only (see :mod:`phjax.vision.face_detection`).
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from .face_detection import HEAD_LOCALIZER_ONNX, HEAD_POSE_ONNX, model_path

__all__ = ["HeadLocalizer", "HeadPoseNet", "NetFace", "crop_input", "normalize_brightness"]

#: side of the pose network's square input, px
INPUT_SIZE = 129
#: the crop's side over the larger side of the face box
CROP_SCALE = 1.05
#: localizer input (width, height), px
LOCALIZER_INPUT = (288, 224)


def _onnxruntime():
    try:
        import onnxruntime
    except ImportError as e:
        raise ImportError("the monocular head-pose network needs onnxruntime; install the "
                          "vision extra: pip install 'phjax[vision]'") from e
    return onnxruntime


def onnx_session(path: str | os.PathLike, threads: int = 1) -> Any:
    """An onnxruntime CPU session with ``threads`` intra-op threads (one inter-op thread).

    One thread is the default: on the 2-core development machine two threads made the pose
    network slower, not faster (``benchmarks/bench_monocular.py``; docs/results.md).
    """
    ort = _onnxruntime()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3  # errors only
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def normalize_brightness(patch: np.ndarray) -> np.ndarray:
    """opentrack's input scaling of a ``uint8`` patch: ``float32``, about ``-0.5 .. 0.5``.

    ``b`` is the grey level at the 90th percentile (the first level whose cumulative count
    exceeds ``int(0.9 n)``); a dark patch (``b < 127``) is stretched by ``0.45 / max(5, b)``,
    any other by ``1 / 255``; then 0.5 is subtracted.
    """
    hist = np.bincount(patch.ravel(), minlength=256)
    level = int(np.argmax(np.cumsum(hist) > int(patch.size * 0.9)))
    scale = 0.45 / max(5, level) if level < 127 else 1.0 / 255.0
    return patch.astype(np.float32) * np.float32(scale) - np.float32(0.5)


def crop_input(grey: np.ndarray, box: Any) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The network input for face box ``(x, y, w, h)`` (px) in a ``uint8`` grey image.

    Returns:
        ``(input (1, 1, 129, 129) float32, patch centre (2,) px, patch side px)``, or ``None``
        for a box whose patch would be empty.
    """
    cv2 = _cv2()
    x, y, w, h = (float(v) for v in box)
    if not (np.isfinite([x, y, w, h]).all() and w > 0 and h > 0):
        return None
    side = int(max(w, h) * CROP_SCALE)
    if side < 2:
        return None
    rows, cols = grey.shape[:2]
    centre = np.array([min(max(x + 0.5 * w, 0.0), cols), min(max(y + 0.5 * h, 0.0), rows)])
    patch = cv2.getRectSubPix(grey, (side, side), (float(centre[0]), float(centre[1])))
    patch = cv2.resize(patch, (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_AREA)
    return normalize_brightness(patch)[None, None], centre, side


def _cv2():
    from .features import _require

    return _require("cv2")


class NetFace(NamedTuple):
    """One output of :class:`HeadPoseNet` in pixels of the full image.

    Attributes:
        quaternion: ``(4,)`` ``wxyz`` (``w >= 0``), head frame -> image frame *as seen in the
            crop*; identity = facing the viewer (module docs).
        center: ``(2,)`` the head centre ``(u, v)``, px.
        size: the network's head size, px (about half the head's vertical extent).
        box: ``(4,)`` the network's face box ``x, y, w, h``, px (the crop of the next frame).
        rotation_cov: ``(3, 3)`` covariance of the rotation error as a rotation vector in the
            head frame (``q_true = q * exp(r)``), rad^2.
        center_size_cov: ``(3, 3)`` covariance of ``(u, v, size)``, px^2.
        patch_center: ``(2,)`` centre of the crop, px; ``patch_side``: its side, px.
    """

    quaternion: np.ndarray
    center: np.ndarray
    size: float
    box: np.ndarray
    rotation_cov: np.ndarray
    center_size_cov: np.ndarray
    patch_center: np.ndarray
    patch_side: int

    @property
    def rotation_std(self) -> float:
        """RMS over the three axes of the predicted rotation std, rad."""
        return float(np.sqrt(max(np.trace(self.rotation_cov), 0.0) / 3.0))


class HeadPoseNet:
    """opentrack's head-pose network on a face box (module docs).

    Arguments:
        model_dir: model cache (default :func:`phjax.vision.face_detection.model_dir`).
        threads: onnxruntime intra-op threads.
        download: fetch the model into the cache when missing.

    Raises:
        ModelNotFoundError: the model file is not in the cache.
        ImportError: onnxruntime or OpenCV is not installed.
    """

    def __init__(self, model_dir: Any = None, *, threads: int = 1, download: bool = False):
        _cv2()
        self.session = onnx_session(model_path(HEAD_POSE_ONNX, model_dir, download=download),
                                    threads)
        self._input = self.session.get_inputs()[0].name
        self._outputs = [o.name for o in self.session.get_outputs()]
        need = {"quat", "pos_size", "box", "rotaxis_scales_tril", "pos_size_scales_tril"}
        if not need <= set(self._outputs):
            raise ValueError(f"head-pose model lacks outputs {sorted(need - set(self._outputs))}")

    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Raw outputs (by name) for one ``(1, 1, 129, 129) float32`` input."""
        return dict(zip(self._outputs, self.session.run(self._outputs, {self._input: x})))

    def __call__(self, grey: np.ndarray, box: Any) -> NetFace | None:
        """The head in face box ``(x, y, w, h)`` of a ``uint8 (H, W)`` grey image, or ``None``
        when the box gives no patch or the outputs are not finite."""
        crop = crop_input(grey, box)
        if crop is None:
            return None
        x, centre, side = crop
        out = self.run(x)
        half = 0.5 * side
        qx, qy, qz, qw = (float(v) for v in out["quat"][0])
        q = np.array([qw, qx, qy, qz])
        norm = float(np.linalg.norm(q))
        pos = out["pos_size"][0].astype(np.float64)
        b = out["box"][0].astype(np.float64)
        lr = out["rotaxis_scales_tril"][0].astype(np.float64)
        lp = out["pos_size_scales_tril"][0].astype(np.float64) * half
        values = np.concatenate([q, pos, b, lr.ravel(), lp.ravel()])
        if not (np.isfinite(values).all() and norm > 0.5):
            return None
        q = q / norm
        if q[0] < 0:
            q = -q
        box_px = np.array([centre[0] + half * b[0], centre[1] + half * b[1],
                           half * (b[2] - b[0]), half * (b[3] - b[1])])
        return NetFace(q, centre + half * pos[:2], float(half * pos[2]), box_px, lr @ lr.T,
                       lp @ lp.T, centre, side)


class HeadLocalizer:
    """opentrack's whole-frame head localizer: one head box and a score per frame.

    The frame (grey) is area-resized to 288 x 224 and scaled to ``pixel / 255 - 0.5``; the
    output is a logit and the box corners in ``-1..1`` over the frame. As in opentrack a box is
    accepted with a score (sigmoid of the logit) above ``score_threshold`` and both sides
    larger than ``min_size`` px.

    Arguments: as :class:`HeadPoseNet`, plus ``score_threshold`` and ``min_size``.
    """

    def __init__(self, model_dir: Any = None, *, threads: int = 1, download: bool = False,
                 score_threshold: float = 0.5, min_size: float = 32.0):
        self._cv2 = _cv2()
        self.session = onnx_session(
            model_path(HEAD_LOCALIZER_ONNX, model_dir, download=download), threads)
        self._input = self.session.get_inputs()[0].name
        self.score_threshold = float(score_threshold)
        self.min_size = float(min_size)

    def locate(self, grey: np.ndarray) -> tuple[float, np.ndarray]:
        """``(score, box x, y, w, h px)`` of a ``uint8 (H, W)`` grey frame (no threshold)."""
        cv2 = self._cv2
        rows, cols = grey.shape[:2]
        small = cv2.resize(grey, LOCALIZER_INPUT, interpolation=cv2.INTER_AREA)
        x = small.astype(np.float32) * np.float32(1.0 / 255.0) - np.float32(0.5)
        out = self.session.run(None, {self._input: x[None, None]})[0].reshape(-1)
        score = float(1.0 / (1.0 + np.exp(-float(out[0]))))
        x0, y0, x1, y1 = (0.5 * (float(v) + 1.0) for v in out[1:5])
        return score, np.array([x0 * cols, y0 * rows, (x1 - x0) * cols, (y1 - y0) * rows])

    def __call__(self, grey: np.ndarray) -> tuple[float, np.ndarray] | None:
        """``(score, box)`` when a head is found (thresholds above), else ``None``."""
        score, box = self.locate(grey)
        if not (score > self.score_threshold and np.isfinite(box).all()
                and box[2] > self.min_size and box[3] > self.min_size):
            return None
        return score, box
