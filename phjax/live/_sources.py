"""Live pose sources: what the capture thread reads, one measurement per camera frame.

Every source turns camera frames (or recorded poses) into :class:`Measurement` objects: the
capture time on the runner's clock and the head pose in the camera frame (NaN when the frame
gave none). :func:`open_source` parses the ``SOURCE`` argument of ``phjax live``:

``synthetic[:N[:SEED]]``
    the rendered synthetic head (:func:`phjax.vision.open_rgbd`), paced at its frame rate and
    run through the RGB-D front-end (:class:`phjax.vision.HeadPoseEstimator`). Rendering is
    treated as the camera's work (the frame due when rendering ends is rendered, then
    delivered at its timestamp), but it still takes CPU time (~0.1-0.2 s a frame), so on a
    small machine the front-end sees only a few frames per second: the others are skipped,
    as late frames of a real camera would be.
an RGB-D recording
    any folder :func:`phjax.vision.open_rgbd` accepts (Biwi, TUM RGB-D, colour + depth),
    replayed at its own timestamps through the same front-end.
``webcam[:INDEX]`` or a video file
    OpenCV ``VideoCapture``, colour only, monocular head pose
    (:class:`phjax.vision.monocular.MonocularHeadPose`: opentrack's head-pose network by
    default, YuNet landmarks + PnP with ``monocular="landmarks"``), each pose with a confidence
    that scales the filter's measurement noise; a file is replayed at its frame rate.
``realsense[:SERIAL]``
    an Intel RealSense camera through ``pyrealsense2`` (the ``live`` extra): colour + depth
    aligned to colour, RGB-D front-end.
``poses:FILE``
    a pose file (any format :func:`phjax.io.read_trajectory` reads) replayed at its
    timestamps, no vision.

Late frames are never queued: a source that falls behind its clock skips to the newest frame
due, so the tracker receives late or missing measurements, never a backlog.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "Measurement",
    "PoseReplaySource",
    "RGBDReplaySource",
    "RealSenseSource",
    "Source",
    "SourceError",
    "VideoSource",
    "open_source",
]


class SourceError(ValueError):
    """A source that cannot be opened: unknown kind, missing file or camera, missing package."""


@dataclass
class Measurement:
    """One camera frame's head pose.

    Attributes:
        t: capture time on the runner's clock, s.
        position: ``(3,)`` camera-frame position, m (NaN if missing).
        quaternion: ``(4,)`` ``wxyz`` (NaN if missing).
        status: the front-end's status name (``"OK"``, ``"NO_FACE"``, ...).
        confidence: weight of the pose in ``(0, 1]`` (the monocular network's uncertainty,
            :class:`phjax.vision.monocular.MonocularResult`); the runner divides the filter's
            measurement noise by its square root for this measurement.
    """

    t: float
    position: np.ndarray
    quaternion: np.ndarray
    status: str = "OK"
    confidence: float = 1.0

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.quaternion).all() or np.isfinite(self.position).all())


Emit = Callable[[Measurement], None]


class Source:
    """Base class of live sources.

    Attributes:
        name: a description.
        depth_free: the poses come from colour alone (larger measurement noise).
        rate: nominal frame rate, Hz (``None`` if unknown).
    """

    name = ""
    depth_free = False
    rate: float | None = None

    def open(self) -> None:
        """Acquire the device / files and warm up (compile) the front-end."""

    def run(self, clock, t0: float, stop: threading.Event, emit: Emit) -> None:
        """Capture until the end of the source or until ``stop`` is set, calling ``emit``
        once per frame; capture times are on ``clock`` with ``t0`` the start of the run."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device."""


def _nan_pose():
    return np.full(3, np.nan), np.full(4, np.nan)


# ------------------------------------------------------------------------------- poses
class PoseReplaySource(Source):
    """Recorded poses replayed at their timestamps (relative to the first), no vision.

    Arguments:
        times: ``(n,)`` s (non-decreasing); positions ``(n, 3)`` m; quaternions ``(n, 4)``
            ``wxyz`` (NaN entries are missing measurements).
        name: a description.
    """

    def __init__(self, times, positions, quaternions, name: str = "poses"):
        self.times = np.asarray(times, np.float64)
        self.positions = np.asarray(positions, np.float64)
        self.quaternions = np.asarray(quaternions, np.float64)
        n = self.times.shape[0]
        if n < 1 or self.positions.shape != (n, 3) or self.quaternions.shape != (n, 4):
            raise SourceError(f"{name}: need n >= 1 times with (n, 3) positions and (n, 4) "
                              "quaternions")
        self.name = name
        dt = np.diff(self.times)
        self.rate = float(1.0 / np.median(dt)) if n > 1 and np.median(dt) > 0 else None

    @classmethod
    def from_file(cls, path) -> PoseReplaySource:
        from ..io import read_trajectory

        path = Path(path)
        if not path.is_file():
            raise SourceError(f"pose file not found: {path}")
        traj = read_trajectory(path)
        return cls(traj.times, traj.positions, traj.quaternions, name=f"poses {path}")

    def run(self, clock, t0, stop, emit) -> None:
        t_first = self.times[0]
        for i in range(self.times.shape[0]):
            t = t0 + (self.times[i] - t_first)
            clock.sleep_until(t, stop)
            if stop.is_set():
                return
            emit(Measurement(t, self.positions[i], self.quaternions[i]))


# ------------------------------------------------------------------------------- RGB-D
class RGBDReplaySource(Source):
    """An RGB-D sequence (:class:`phjax.vision.RGBDSequence`) paced at its timestamps and run
    through :class:`phjax.vision.HeadPoseEstimator`.

    Arguments:
        sequence: the frames (e.g. ``phjax.vision.open_rgbd("synthetic:240")``).
        model_dir: YuNet model cache (see :mod:`phjax.vision.face_detection`).
        estimator: a ready estimator (default: one with the default config).
    """

    def __init__(self, sequence, *, model_dir=None, estimator=None, name: str | None = None):
        self.sequence = sequence
        self.name = name or getattr(sequence, "name", "RGB-D sequence")
        self.model_dir = model_dir
        self.estimator = estimator
        stamps = np.asarray(sequence.timestamps, np.float64)
        if stamps.shape[0] < 1:
            raise SourceError(f"{self.name}: no frames")
        dt = np.diff(stamps)
        self.rate = float(1.0 / np.median(dt)) if dt.size and np.median(dt) > 0 else None

    def open(self) -> None:
        from ..vision.head_pose import HeadPoseEstimator

        if self.estimator is None:
            self.estimator = _with_models(lambda: HeadPoseEstimator(
                self.sequence.intrinsics, model_dir=self.model_dir))
        # warm-up: compile the front-end's stages (the first frame starts a reference, the
        # next ones are aligned to it) and the renderer of a synthetic sequence
        for i in range(min(3, len(self.sequence))):
            self.estimator.process_frame(self.sequence[i])
        self.estimator.reset()

    def run(self, clock, t0, stop, emit) -> None:
        # Loading a frame (rendering the synthetic head, reading files) is the camera's work,
        # not the front-end's: the frame that will be due when loading ends is loaded, then
        # delivered at its timestamp, so the measured latency is the front-end's.
        rel = np.asarray(self.sequence.timestamps, np.float64)
        rel = rel - rel[0]
        n, i, load_est = rel.shape[0], 0, 0.0
        while i < n and not stop.is_set():
            t_start = clock.now()
            due = int(np.searchsorted(rel, t_start - t0 + load_est, side="right")) - 1
            i = max(i, min(due, n - 1))
            frame = self.sequence[i]
            load_est = 0.7 * load_est + 0.3 * (clock.now() - t_start)
            clock.sleep_until(t0 + rel[i], stop)
            if stop.is_set():
                return
            r = self.estimator.process_frame(frame)
            emit(Measurement(t0 + rel[i], r.position, r.quaternion, r.status.name))
            i += 1


def _with_models(make):
    """Run a constructor that loads YuNet; a missing model file becomes a SourceError."""
    from ..vision.face_detection import ModelNotFoundError

    try:
        return make()
    except ModelNotFoundError as e:
        raise SourceError(str(e).splitlines()[0] + " (set --model-dir or $PHJAX_MODEL_DIR)"
                          ) from None


# ------------------------------------------------------------------------------- video
class VideoSource(Source):
    """``cv2.VideoCapture`` (a webcam index or a video file), monocular head pose.

    Arguments:
        target: camera index (int) or video file path.
        ipd: assumed inter-pupillary distance, m (landmark method).
        fov: horizontal field of view of the camera, degrees (intrinsics of an uncalibrated
            camera; ignored when ``intrinsics`` is given).
        intrinsics: a :class:`phjax.vision.CameraIntrinsics` of the frames.
        model_dir: model cache (YuNet, the head-pose network).
        monocular: ``"net"`` (default: opentrack's head-pose network) or ``"landmarks"``
            (YuNet's five landmarks + PnP); see :mod:`phjax.vision.monocular`.
        head_size: assumed vertical head size, m (net method; default 0.20).

    A file is replayed at its frame rate (late frames skipped); a camera delivers frames at its
    own rate and each frame's capture time is its arrival time.
    """

    depth_free = True

    def __init__(self, target, *, ipd: float | None = None, fov: float = 60.0,
                 intrinsics=None, model_dir=None, monocular: str = "net",
                 head_size: float | None = None):
        from ..vision.monocular import METHODS

        if monocular not in METHODS:
            raise SourceError(f"monocular method must be one of {METHODS}, got {monocular!r}")
        self.monocular, self.head_size = monocular, head_size
        self.target = target
        self.is_file = not isinstance(target, int)
        self.name = f"video file {target}" if self.is_file else f"webcam {target}"
        self.ipd, self.fov, self.intrinsics, self.model_dir = ipd, fov, intrinsics, model_dir
        self.cap = None
        self.estimator = None

    def open(self) -> None:
        try:
            import cv2
        except ImportError:
            raise SourceError("webcam / video sources need OpenCV (pip install "
                              "'phjax[vision]')") from None
        from ..vision.monocular import (
            DEFAULT_HEAD_SIZE,
            DEFAULT_IPD,
            MonocularHeadPose,
            intrinsics_from_fov,
        )

        if self.is_file and not Path(self.target).is_file():
            raise SourceError(f"video file not found: {self.target}")
        cap = cv2.VideoCapture(str(self.target) if self.is_file else int(self.target))
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"cannot open {self.name}")
        ok, frame = cap.read()
        if not ok or frame is None:
            cap.release()
            raise SourceError(f"{self.name}: no frame could be read")
        self.cap = cap
        self._first = frame
        h, w = frame.shape[:2]
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.rate = fps if fps > 0 else None
        intr = self.intrinsics if self.intrinsics is not None else intrinsics_from_fov(
            w, h, self.fov)
        ipd = DEFAULT_IPD if self.ipd is None else self.ipd
        head = DEFAULT_HEAD_SIZE if self.head_size is None else self.head_size
        try:
            self.estimator = _with_models(lambda: MonocularHeadPose(
                intr, ipd, method=self.monocular, head_size=head, model_dir=self.model_dir))
        except (ImportError, SourceError) as e:  # a missing model or onnxruntime
            self.close()
            raise SourceError(str(e)) from None
        self.estimator.process(frame, 0.0)  # warm-up
        self.estimator.reset()

    def run(self, clock, t0, stop, emit) -> None:
        if self.is_file:
            self._run_file(clock, t0, stop, emit)
            return
        frame = self._first
        t = clock.now()
        while not stop.is_set():
            r = self.estimator.process(frame, t - t0)
            emit(Measurement(t, r.position, r.quaternion, r.status.name, r.confidence))
            ok, frame = self.cap.read()
            t = clock.now()
            if not ok:
                raise SourceError(f"{self.name}: the camera stopped delivering frames")

    def _run_file(self, clock, t0, stop, emit) -> None:
        period = 1.0 / (self.rate or 30.0)
        frame, index = self._first, 0
        while not stop.is_set():
            clock.sleep_until(t0 + index * period, stop)
            if stop.is_set():
                return
            due = math.floor((clock.now() - t0) / period + 1e-9)
            while index < due:  # late: skip frames (grab does not decode them into arrays)
                if not self.cap.grab():
                    return
                index += 1
                frame = None
            if frame is None:
                ok, frame = self.cap.retrieve()
                if not ok:
                    return
            t = t0 + index * period
            r = self.estimator.process(frame, t - t0)
            emit(Measurement(t, r.position, r.quaternion, r.status.name, r.confidence))
            ok, frame = self.cap.read()
            index += 1
            if not ok:
                return

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


# ------------------------------------------------------------------------------- RealSense
def _import_realsense():
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise SourceError(f"realsense sources need pyrealsense2 (pip install 'phjax[live]'): "
                          f"{e}") from None
    return rs


class RealSenseSource(Source):
    """An Intel RealSense camera (colour + depth aligned to colour) through pyrealsense2.

    Arguments:
        serial: the camera's serial number (default: the first camera).
        width, height, fps: stream settings for both streams.
        frames: instead of a camera, any object with ``wait_for_frames(timeout_ms)`` returning
            a ``pyrealsense2.composite_frame`` (e.g. a ``pyrealsense2.syncer`` fed by a
            ``software_device``); then ``depth_scale`` (m per unit) is taken from the depth
            frames' sensor if possible, else from the argument.
        depth_scale: metres per depth unit when it cannot be read (default 0.001).
        model_dir: YuNet model cache.
        timeout: seconds to wait for a frame before counting it as lost.
    """

    def __init__(self, serial: str | None = None, *, width: int = 640, height: int = 480,
                 fps: int = 30, frames=None, depth_scale: float = 0.001, model_dir=None,
                 timeout: float = 1.0):
        self.serial, self.width, self.height, self.fps = serial, width, height, fps
        self.rate = float(fps)
        self.frames, self.depth_scale, self.model_dir = frames, depth_scale, model_dir
        self.timeout = timeout
        self.name = f"RealSense {serial or '(first camera)'}"
        self.pipeline = None
        self.align = None
        self.estimator = None
        self.intrinsics = None

    def open(self) -> None:
        rs = _import_realsense()
        self._rs = rs
        if self.frames is None:
            try:
                devices = list(rs.context().query_devices())
            except RuntimeError as e:
                raise SourceError(f"cannot query RealSense devices: {e}") from None
            serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
            if not serials:
                raise SourceError("no RealSense camera found")
            if self.serial is not None and self.serial not in serials:
                raise SourceError(f"no RealSense camera with serial {self.serial} "
                                  f"(found: {', '.join(serials)})")
            cfg = rs.config()
            cfg.enable_device(self.serial or serials[0])
            cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.bgr8,
                              self.fps)
            cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16,
                              self.fps)
            self.pipeline = rs.pipeline()
            try:
                profile = self.pipeline.start(cfg)
            except RuntimeError as e:
                self.pipeline = None
                raise SourceError(f"cannot start {self.name}: {e}") from None
            self.depth_scale = profile.get_device().first_depth_sensor().get_depth_scale()
            self.frames = self.pipeline
        self.align = rs.align(rs.stream.color)

    def _to_frame(self, fs):
        """``(color BGR, depth m, intrinsics)`` of a frameset, or None if incomplete."""
        from ..vision.rgbd_io import CameraIntrinsics

        rs = self._rs
        try:
            fs = self.align.process(fs)
        except RuntimeError:
            pass  # no extrinsics (already registered streams): use the frames as they are
        color, depth = fs.get_color_frame(), fs.get_depth_frame()
        if not color or not depth:
            return None
        c = np.asanyarray(color.get_data())
        d = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_scale)
        if c.shape[:2] != d.shape:
            return None
        if self.intrinsics is None:
            k = color.profile.as_video_stream_profile().get_intrinsics()
            self.intrinsics = CameraIntrinsics(fx=k.fx, fy=k.fy, cx=k.ppx, cy=k.ppy,
                                               width=k.width, height=k.height)
        if color.profile.format() == rs.format.rgb8:
            c = c[..., ::-1]
        return np.ascontiguousarray(c), d

    def run(self, clock, t0, stop, emit) -> None:
        from ..vision.head_pose import HeadPoseEstimator

        while not stop.is_set():
            try:
                fs = self.frames.wait_for_frames(int(1000 * self.timeout))
            except RuntimeError:  # timeout: a lost frame
                p, q = _nan_pose()
                emit(Measurement(clock.now(), p, q, "NO_FRAME"))
                continue
            t = clock.now()
            frame = self._to_frame(fs)
            if frame is None:
                p, q = _nan_pose()
                emit(Measurement(t, p, q, "INVALID_INPUT"))
                continue
            if self.estimator is None:
                self.estimator = _with_models(lambda: HeadPoseEstimator(
                    self.intrinsics, model_dir=self.model_dir))
            r = self.estimator.process(frame[0], frame[1], t - t0, self.intrinsics)
            emit(Measurement(t, r.position, r.quaternion, r.status.name))

    def close(self) -> None:
        if self.pipeline is not None:
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass
            self.pipeline = None


# ------------------------------------------------------------------------------- parsing
def open_source(spec: str, *, model_dir=None, ipd: float | None = None, fov: float = 60.0,
                monocular: str = "net", head_size: float | None = None) -> Source:
    """A :class:`Source` from the ``SOURCE`` argument of ``phjax live`` (see the module docs).

    ``ipd``, ``fov``, ``monocular`` and ``head_size`` apply to webcam / video sources
    (:class:`VideoSource`).

    Raises:
        SourceError: unknown source, missing file, bad number.
    """
    spec = str(spec)
    kind, _, arg = spec.partition(":")
    if kind == "synthetic":
        from ..vision.rgbd_io import open_rgbd

        try:
            seq = open_rgbd(spec)
        except ValueError as e:
            raise SourceError(str(e)) from None
        return RGBDReplaySource(seq, model_dir=model_dir)
    if kind == "webcam":
        try:
            index = int(arg) if arg else 0
        except ValueError:
            raise SourceError(f"bad webcam index {arg!r}; use webcam[:INDEX]") from None
        return VideoSource(index, ipd=ipd, fov=fov, model_dir=model_dir, monocular=monocular,
                           head_size=head_size)
    if kind == "realsense":
        return RealSenseSource(arg or None, model_dir=model_dir)
    if kind == "poses":
        if not arg:
            raise SourceError("poses: needs a file, poses:FILE")
        try:
            return PoseReplaySource.from_file(arg)
        except ValueError as e:
            raise SourceError(str(e)) from None
    path = Path(spec)
    if path.is_dir():
        from ..vision.rgbd_io import open_rgbd

        try:
            seq = open_rgbd(path)
        except ValueError as e:
            raise SourceError(str(e)) from None
        return RGBDReplaySource(seq, model_dir=model_dir, name=f"RGB-D recording {path}")
    if path.is_file():
        return VideoSource(os.fspath(path), ipd=ipd, fov=fov, model_dir=model_dir,
                           monocular=monocular, head_size=head_size)
    raise SourceError(f"unknown source {spec!r}: use synthetic[:N[:SEED]], an RGB-D folder, "
                      "webcam[:INDEX], a video file, realsense[:SERIAL] or poses:FILE")
