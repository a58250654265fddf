"""Live pose sources: what the capture thread reads, one measurement per camera frame.

Every source turns camera frames (or recorded poses) into :class:`Measurement` objects: the
capture time on the runner's clock and the head pose in the camera frame (NaN when the frame
gave none). :func:`open_source` parses the ``SOURCE`` argument of ``phjax live``:

``synthetic[:N[:SEED]]``
    the rendered synthetic head (:func:`phjax.vision.open_rgbd`; ``N >= 1`` frames,
    ``0 <= SEED < 2**32``: :func:`synthetic_spec`) at 30 Hz through the RGB-D front-end
    (:class:`phjax.vision.HeadPoseEstimator`). Rendering a frame takes 0.1-0.4 s of CPU, so
    :class:`SyntheticSource` renders the frames once, before the first run that needs them,
    into a frame cache (:func:`frame_cache_dir`; in memory, with a warning, when that folder
    cannot be made or a frame cannot be written to it) and plays them back like a camera.
an RGB-D recording
    any folder :func:`phjax.vision.open_rgbd` accepts (Biwi, TUM RGB-D, colour + depth),
    replayed at its own timestamps through the same front-end; a frame whose image is missing
    or cannot be read is a lost frame (``NO_FRAME``) and the replay goes on.
``webcam[:INDEX]`` (``INDEX`` 0-99) or a video file
    OpenCV ``VideoCapture``, colour only, monocular head pose
    (:class:`phjax.vision.monocular.MonocularHeadPose`: opentrack's head-pose network by
    default, YuNet landmarks + PnP with ``monocular="landmarks"``), each pose with a confidence
    that scales the filter's measurement noise; a file is replayed at its own timestamps (a
    header frame rate outside :data:`VIDEO_RATES` is taken as unknown: 30 Hz, with a warning).
    A ``SOURCE`` without a known ``kind:`` prefix that is neither a file nor a folder but looks
    like a path (``name.mp4``, ``dir/name``) is ``SOURCE: No such file or directory``.
``realsense[:SERIAL]``
    an Intel RealSense camera through ``pyrealsense2`` (the ``live`` extra): colour + depth
    aligned to colour, RGB-D front-end.
``poses:FILE``
    a pose file (any format :func:`phjax.io.read_trajectory` reads) replayed at its
    timestamps, no vision. A row with a position coordinate beyond :data:`MAX_POSITION_M`
    (10 m: not a head pose; a file in millimetres read as metres, a corrupt row) never reaches
    the tracker: it is replayed as a lost frame with the status ``OUT_OF_RANGE``; a file with
    fewer than 2 usable poses is a :class:`SourceError`.
``udp://[HOST]:PORT``
    another tracker's poses as opentrack UDP datagrams (:class:`phjax.live.UdpSource`),
    time-stamped on arrival, no vision.

Late frames are never queued: a source that falls behind its clock skips to the newest frame
due, so the tracker receives late or missing measurements, never a backlog (the frames lost
that way are counted in :attr:`Measurement.dropped`).

The sources with a vision front-end (:attr:`Source.front_end`) run, by default, in a worker
process (:class:`phjax.live.WorkerSource`, :mod:`phjax.live._worker`), where the front-end
cannot hold the render loop.
"""

from __future__ import annotations

import functools
import math
import os
import re
import shutil
import sys
import threading
import time
import warnings
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
    "SyntheticSource",
    "VideoSource",
    "frame_cache_dir",
    "open_source",
]


class SourceError(ValueError):
    """A source that cannot be opened: unknown kind, missing file or camera, missing package."""


#: synthetic seeds: ``0 <= SEED < 2**32`` (what every random generator of the renderer takes)
SEED_LIMIT = 2**32
#: webcam indices: ``0 <= INDEX < 100`` (OpenCV reads an index of 100 and above as a backend
#: code plus an index, and -1 as "any camera", which crashes it when there is none)
WEBCAM_INDEX_LIMIT = 100
#: frame rates a video file's header is trusted with, Hz (others: unknown, 30 Hz)
VIDEO_RATES = (1.0, 240.0)
#: the frame rate of a video file whose header gives none in :data:`VIDEO_RATES`, Hz
DEFAULT_VIDEO_RATE = 30.0
#: a position coordinate beyond this (m) is not a head pose: a ``poses:FILE`` row or a
#: ``udp://`` datagram (:data:`phjax.live._udp.MAX_POSITION_CM`) beyond it never reaches the
#: tracker (positions of 1e150 m made its stream non-finite: nothing was sent, silently)
MAX_POSITION_M = 10.0


_SYNTHETIC_USAGE = "use synthetic[:N[:SEED]] (N >= 1 frames, 0 <= SEED < 2**32)"


def synthetic_spec(spec: str) -> tuple[int, int]:
    """``(N, SEED)`` of a ``synthetic[:N[:SEED]]`` source (defaults 90 and 0), checked:
    integers, ``N >= 1``, ``0 <= SEED < 2**32`` (:data:`SEED_LIMIT`); the one check of
    ``phjax live``, ``phjax track-rgbd`` and :class:`SyntheticSource`.

    Raises:
        SourceError: one line naming the source and the accepted values.
    """
    kind, _, arg = str(spec).partition(":")
    try:
        values = [int(v) for v in arg.split(":")] if arg else []
    except ValueError:
        values = None
    if kind != "synthetic" or values is None or len(values) > 2:
        raise SourceError(f"bad synthetic source {spec!r}; {_SYNTHETIC_USAGE}")
    n, seed = values + [90, 0][len(values):]
    _check_synthetic(n, seed, spec)
    return n, seed


def _check_synthetic(n: int, seed: int, spec: str) -> None:
    if n < 1:
        raise SourceError(f"bad synthetic source {spec!r}: N {n} frames; {_SYNTHETIC_USAGE}")
    if not 0 <= seed < SEED_LIMIT:
        raise SourceError(f"bad synthetic source {spec!r}: SEED {seed} out of range; "
                          f"{_SYNTHETIC_USAGE}")


def _webcam_index(index) -> int:
    """A webcam index checked against 0 .. :data:`WEBCAM_INDEX_LIMIT` - 1 (a SourceError
    otherwise: OpenCV crashes on -1 without a camera and fails on large ones)."""
    if not (isinstance(index, int) and 0 <= index < WEBCAM_INDEX_LIMIT):
        raise SourceError(f"bad webcam index {str(index)!r}; use webcam[:INDEX] with INDEX "
                          f"0-{WEBCAM_INDEX_LIMIT - 1}")
    return index


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
        dropped: camera frames lost just before this one (late: the front-end was still busy
            or the frame could not be read in time); counted in the runner's lost frames.
        work: seconds the front-end spent on this frame (NaN if not measured).
    """

    t: float
    position: np.ndarray
    quaternion: np.ndarray
    status: str = "OK"
    confidence: float = 1.0
    dropped: int = 0
    work: float = float("nan")

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
        front_end: each frame goes through a vision front-end (CPU-heavy work that
            :func:`open_source` runs in a worker process by default).
    """

    name = ""
    depth_free = False
    rate: float | None = None
    front_end = False

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
        times: ``(n,)`` s (finite, non-decreasing: a :class:`SourceError` otherwise);
            positions ``(n, 3)`` m; quaternions ``(n, 4)`` ``wxyz`` (NaN entries are missing
            measurements).
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
        # a NaN time made the real clock's sleep spin until the run was stopped, a time
        # before the previous one reached the tracker out of order
        if not np.isfinite(self.times).all() or np.any(np.diff(self.times) < 0):
            raise SourceError(f"{name}: the times must be finite and non-decreasing")
        self.name = name
        dt = np.diff(self.times)
        self.rate = float(1.0 / np.median(dt)) if n > 1 and np.median(dt) > 0 else None
        #: rows whose position is not a head pose (a coordinate beyond MAX_POSITION_M, or
        #: infinite): replayed as lost frames with the status ``"OUT_OF_RANGE"``
        with np.errstate(invalid="ignore"):
            self.out_of_range = np.any(np.isinf(self.positions)
                                       | (np.abs(self.positions) > MAX_POSITION_M), axis=-1)

    def out_of_range_text(self) -> str:
        """What :attr:`out_of_range` drops, one line (``""`` when nothing): how many rows,
        the bound and the largest coordinate."""
        bad = int(np.count_nonzero(self.out_of_range))
        if not bad:
            return ""
        return (f"{bad} of {self.times.shape[0]} rows hold a position beyond "
                f"+-{MAX_POSITION_M:g} m, not a head pose (largest |coordinate| "
                f"{float(np.nanmax(np.abs(self.positions[self.out_of_range]))):.3g} m; "
                "positions are read in metres)")

    @classmethod
    def from_file(cls, path, format: str = "auto") -> PoseReplaySource:
        """The poses of a file (``FILE`` or ``FILE#NAME``) in a :mod:`phjax.io` ``format``
        (``phjax live --format``)."""
        from ..io import read_trajectory_spec, split_trajectory_name

        spec, _ = split_trajectory_name(path)  # FILE#NAME: one of several (CWI, AVTrack360)
        if not Path(spec).exists():
            raise SourceError(f"pose file not found: {spec}")
        if Path(spec).is_dir():
            raise SourceError(f"{spec}: a folder (poses:FILE takes a pose file)")
        # the reader's warnings (a unit warning for positions of 1e150 m) only for a file that
        # is replayed: an unusable one ends in one line that says it all
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                traj = read_trajectory_spec(path, format, syntax="poses:FILE#NAME")
            except ValueError as e:  # a bad file, or FILE#NAME missing / wrong: one line
                raise SourceError(str(e).replace("pass format= one of",
                                                 "pass --format, one of")) from None
        if traj.num_samples < 2:  # as phjax smooth: one pose is no motion to replay
            raise SourceError(f"{path}: {traj.num_samples} pose(s); a replay needs at least 2")
        source = cls(traj.times, traj.positions, traj.quaternions, name=f"poses {path}")
        posed = np.isfinite(traj.quaternions).all(-1) | np.isfinite(traj.positions).all(-1)
        usable = int(np.count_nonzero(posed & ~source.out_of_range))
        if usable < 2:  # nothing the tracker could follow: it sent nothing and said nothing
            lost = int(np.count_nonzero(~posed))
            why = [source.out_of_range_text()] + (
                [f"{lost} lost frame(s) (no position and no orientation)"] if lost else [])
            raise SourceError(f"{path}: {'; '.join(w for w in why if w)}; {usable} usable "
                              "pose(s), a replay needs at least 2")
        for w in caught:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return source

    def run(self, clock, t0, stop, emit) -> None:
        t_first = self.times[0]
        for i in range(self.times.shape[0]):
            t = t0 + (self.times[i] - t_first)
            clock.sleep_until(t, stop)
            if stop.is_set():
                return
            if self.out_of_range[i]:  # never to the tracker: a lost frame, counted by reason
                emit(Measurement(t, *_nan_pose(), status="OUT_OF_RANGE"))
            else:
                emit(Measurement(t, self.positions[i], self.quaternions[i]))


# ------------------------------------------------------------------------------- RGB-D
class RGBDReplaySource(Source):
    """An RGB-D sequence (:class:`phjax.vision.RGBDSequence`) paced at its timestamps and run
    through :class:`phjax.vision.HeadPoseEstimator`.

    Arguments:
        sequence: the frames (e.g. ``phjax.vision.open_rgbd("synthetic:240")``).
        model_dir: YuNet model cache (see :mod:`phjax.vision.face_detection`).
        estimator: a ready estimator (default: one with the default config).

    On the real clock a camera thread reads each frame (the camera's work) and hands it over
    at its timestamp through a one-frame buffer; the front-end takes the newest frame whenever
    it is free, so reading frame ``i + 1`` overlaps the pose of frame ``i``, and a frame that
    arrives while the front-end is busy replaces the waiting one (counted in
    :attr:`Measurement.dropped`): never a backlog. On a :class:`~phjax.live.VirtualClock`
    reading and processing take no time and one thread does both.
    """

    front_end = True

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
        self.unreadable = 0  # frames that could not be read (NO_FRAME measurements)
        self.read_error: str | None = None  # the first of their errors

    def open(self) -> None:
        from ..vision.head_pose import HeadPoseEstimator

        if self.estimator is None:
            self.estimator = _with_models(lambda: HeadPoseEstimator(
                self.sequence.intrinsics, model_dir=self.model_dir))
        # warm-up: compile the front-end's stages (the first frame starts a reference, the
        # next ones are aligned to it) and the renderer of a synthetic sequence; a frame that
        # cannot be read is skipped here as during the run (a lost frame)
        warm, error = 0, None
        for i in range(min(10, len(self.sequence))):
            try:
                frame = self.sequence[i]
            except (OSError, ValueError) as e:
                error = error or e
                continue
            self.estimator.process_frame(frame)
            warm += 1
            if warm == 3:
                break
        if warm == 0 and error is not None:
            raise SourceError(f"{self.name}: no readable frame among the first "
                              f"{min(10, len(self.sequence))}: {error}")
        self.estimator.reset()

    def _times(self) -> np.ndarray:
        rel = np.asarray(self.sequence.timestamps, np.float64)
        return rel - rel[0]

    def _process(self, clock, t_capture: float, frame, dropped: int) -> Measurement:
        if frame is None:  # could not be read (a missing or damaged image): a lost frame
            return Measurement(t_capture, *_nan_pose(), status="NO_FRAME", dropped=dropped)
        t_work = clock.now()
        r = self.estimator.process_frame(frame)
        return Measurement(t_capture, r.position, r.quaternion, r.status.name,
                           dropped=dropped, work=clock.now() - t_work)

    def run(self, clock, t0, stop, emit) -> None:
        if clock.virtual:
            self._run_sequential(clock, t0, stop, emit)
            return
        box = _NewestFrame()
        quit_ = threading.Event()
        camera = threading.Thread(target=self._camera, args=(clock, t0, quit_, box),
                                  name="phjax-live-camera", daemon=True)
        camera.start()
        try:
            while not stop.is_set():
                got = box.take(stop)
                if got is None:
                    break
                (t_capture, frame), dropped = got
                emit(self._process(clock, t_capture, frame, dropped))
        finally:
            quit_.set()
            camera.join()
        if box.error is not None:
            raise box.error

    def _camera(self, clock, t0, quit_: threading.Event, box: _NewestFrame) -> None:
        """Read each frame (the one due when reading ends: late frames are skipped) and hand
        it over at its timestamp."""
        try:
            for t, frame, skipped in self._frames_on_time(clock, t0, quit_):
                box.put((t, frame), skipped)
        except BaseException as e:  # noqa: BLE001 - raised by run() in the front-end thread
            box.close(e)
        else:
            box.close()

    def _frames_on_time(self, clock, t0, stop: threading.Event):
        """Yield ``(timestamp, frame, skipped)`` at each frame's timestamp, as a camera would.

        Loading a frame is the camera's work, not the front-end's: the frame that will be due
        when loading ends is loaded (the ``skipped`` ones before it are never read), then
        delivered at its timestamp. Stops at the end of the sequence or when ``stop`` is set."""
        rel = self._times()
        n, i, load_est = rel.shape[0], 0, 0.0
        while i < n and not stop.is_set():
            t_start = clock.now()
            due = int(np.searchsorted(rel, t_start - t0 + load_est, side="right")) - 1
            skipped = max(0, min(due, n - 1) - i)
            i += skipped
            try:
                frame = self.sequence[i]
            except (OSError, ValueError) as e:  # a missing or damaged image: lost, go on
                frame = None
                self.unreadable += 1
                self.read_error = self.read_error or f"{type(e).__name__}: {e}"
            load_est = 0.7 * load_est + 0.3 * (clock.now() - t_start)
            clock.sleep_until(t0 + rel[i], stop)
            if stop.is_set():
                return
            yield t0 + rel[i], frame, skipped
            i += 1

    def _run_sequential(self, clock, t0, stop, emit) -> None:
        for t, frame, skipped in self._frames_on_time(clock, t0, stop):
            emit(self._process(clock, t, frame, skipped))


class _NewestFrame:
    """A camera's one-frame buffer between the camera thread and the front-end: a frame that
    arrives before the front-end took the previous one replaces it (that one is dropped)."""

    def __init__(self):
        self._cv = threading.Condition()
        self._item = None
        self._dropped = 0
        self._closed = False
        self.error: BaseException | None = None

    def put(self, item, skipped: int = 0) -> None:
        with self._cv:
            self._dropped += skipped + (self._item is not None)
            self._item = item
            self._cv.notify()

    def close(self, error: BaseException | None = None) -> None:
        with self._cv:
            self._closed = True
            self.error = error
            self._cv.notify()

    def take(self, stop: threading.Event):
        """``(item, frames dropped since the last take)``, or ``None`` once the camera has
        ended (and its last frame was taken) or ``stop`` is set."""
        with self._cv:
            while self._item is None and not self._closed and not stop.is_set():
                self._cv.wait(0.05)
            if self._item is None or stop.is_set():
                return None
            got = (self._item, self._dropped)
            self._item, self._dropped = None, 0
            return got


def _with_models(make):
    """Run a constructor that loads YuNet; a missing model file becomes a SourceError."""
    from ..vision.face_detection import ModelNotFoundError

    try:
        return make()
    except ModelNotFoundError as e:
        raise SourceError(str(e).splitlines()[0] + " (set --model-dir or $PHJAX_MODEL_DIR)"
                          ) from None


# ------------------------------------------------------------------------------- synthetic
#: environment variable: the folder of the synthetic head's rendered frames, or ``off``
FRAME_CACHE_ENV = "PHJAX_FRAME_CACHE"
#: depth resolution of the frame cache, m (the simulated sensor's own steps are >= 0.46 mm)
CACHE_DEPTH_STEP = 1e-4
#: a frame folder of another renderer version (another phjax, JAX or NumPy) that no run has
#: used for this long is removed when the synthetic head is next opened, s
STALE_FRAME_FOLDER_AGE = 30 * 86400.0
#: names of the frame folders and of the files in them (frames, and a frame being written)
_FRAME_FOLDER = re.compile(r"synthetic-[0-9a-f]{16}")
_FRAME_FILE = re.compile(r"[0-9a-f]{24}\.bin|\.[0-9a-f]{24}\.bin\.\d+\.\d+\.tmp")


def frame_cache_dir() -> Path | None:
    """The folder of the rendered synthetic head's frames: ``$PHJAX_FRAME_CACHE``, else
    ``$XDG_CACHE_HOME/phjax/frames``, else ``~/.cache/phjax/frames``; ``None`` when
    ``$PHJAX_FRAME_CACHE`` is ``off`` (or ``0``, ``no``, ``false``): the frames are then
    rendered for each run and kept in memory (as :class:`SyntheticSource` also does, with a
    warning, when the folder cannot be made: a file in its path)."""
    value = os.environ.get(FRAME_CACHE_ENV, "").strip()
    if value.lower() in ("off", "0", "no", "false"):
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path("~/.cache").expanduser())
    return Path(base) / "phjax" / "frames"


@functools.cache
def _renderer_key() -> str:
    """A digest of the code a synthetic frame comes from: the renderer and the head motion
    (:mod:`phjax.vision.synthetic_rgbd`, :mod:`phjax.motion.simulate`,
    :func:`phjax.vision.rgbd_io.synthetic_rgbd`), its XLA options (they change the rounding of
    a pixel) and JAX's and NumPy's versions (a change renders the frames anew). Computed once
    per process (the code it digests is loaded once): every frame read names its file by it,
    and reading and hashing the sources took 0.9 ms, as long as reading the frame."""
    import hashlib
    import inspect

    import jax

    from .._jit import IMAGE_COMPILER_OPTIONS
    from ..motion import simulate
    from ..vision import rgbd_io, synthetic_rgbd

    h = hashlib.sha256()
    for mod in (synthetic_rgbd, simulate):
        h.update(Path(mod.__file__).read_bytes())
    h.update(inspect.getsource(rgbd_io.synthetic_rgbd).encode())
    h.update(repr(sorted(IMAGE_COMPILER_OPTIONS.items())).encode())
    h.update(f"jax {jax.__version__} numpy {np.__version__}".encode())
    return h.hexdigest()[:16]


def _frame_keys(seq) -> list[str]:
    """One digest per frame of a :class:`phjax.vision.SyntheticRGBDSequence`: of everything
    the frame is rendered from (its index and seed, which draw its noise; its head pose; the
    camera, image and window size, wall, noise settings). Frames with equal keys are equal,
    whatever the sequence's length (the motion of a seed depends on the length: sequences
    of different lengths share only some frames)."""
    import hashlib

    k = seq.intrinsics
    base = hashlib.sha256(repr((seq.seed, seq.width, seq.height, seq.crop, seq.depth_noise,
                                seq.color_noise, float(k.fx), float(k.fy), float(k.cx),
                                float(k.cy))).encode())
    base.update(np.asarray(seq.wall, np.float64).tobytes())
    keys = []
    for i in range(len(seq)):
        h = base.copy()
        h.update(i.to_bytes(8, "little"))
        h.update(np.asarray(seq.head_positions[i], np.float64).tobytes())
        h.update(np.asarray(seq.head_quaternions[i], np.float64).tobytes())
        keys.append(h.hexdigest()[:24])
    return keys


class SyntheticSource(RGBDReplaySource):
    """The rendered synthetic head (``synthetic[:N[:SEED]]``) at 30 Hz through the RGB-D
    front-end, from frames rendered before the run.

    Rendering a frame costs 0.1-0.4 s of CPU time (ray casting,
    :mod:`phjax.vision.synthetic_rgbd`): rendered during the run, only a few frames per
    second would reach the front-end. :meth:`open` therefore renders the frames that are not
    in the frame cache yet (on all CPU cores, one line on ``report`` before and after) and
    stores them (:func:`frame_cache_dir`: 8-bit BGR colour and depth in steps of
    :data:`CACHE_DEPTH_STEP`, 1.5 MB a frame at 640 x 480, one file per frame named by a
    digest of what it is rendered from, so a frame is rendered once for every ``N`` that
    shows it, and a change of the renderer's code or of JAX renders it anew). Playing them
    back reads a frame in about a millisecond, as a camera delivers it. Each renderer version
    has its own folder; :meth:`open` marks this one as used and removes the folders of other
    versions unused for 30 days (:data:`STALE_FRAME_FOLDER_AGE`, one line on ``report``).
    Delete the folder to free the space sooner.

    Arguments:
        num_frames, seed: as :func:`phjax.vision.open_rgbd` ``("synthetic:N:SEED")``.
        model_dir: YuNet model cache.
        estimator: a ready estimator (default: one with the default config).
        cache: the cache folder (``True``, default: :func:`frame_cache_dir`); ``None`` or
            ``False``: keep the rendered frames in memory for this run only (also when the
            folder cannot be made, e.g. ``$PHJAX_FRAME_CACHE`` names a file: one warning line
            on ``report``).
        threads: rendering threads (default: one per CPU core).
        report: called with the one-line messages about rendering (default: print them on
            stderr).
    """

    def __init__(self, num_frames: int = 90, seed: int = 0, *, model_dir=None,
                 estimator=None, cache: str | os.PathLike | bool | None = True,
                 threads: int | None = None,
                 report: Callable[[str], None] | None = None):
        _check_synthetic(int(num_frames), int(seed), f"synthetic:{num_frames}:{seed}")
        self.num_frames, self.seed = int(num_frames), int(seed)
        self.name = f"synthetic head ({self.num_frames} frames, seed {self.seed})"
        self.model_dir = model_dir
        self.estimator = estimator
        self.sequence = None
        self.rate = 30.0
        self.cache = frame_cache_dir() if cache is True else (
            Path(cache) if cache not in (None, False) else None)
        self._cache_from_env = cache is True and bool(os.environ.get(FRAME_CACHE_ENV, "").strip())
        self.threads = threads
        self.report = report if report is not None else (
            lambda line: print(line, file=sys.stderr, flush=True))
        self._memory: dict[str, bytes] = {}
        self.rendered = 0  # frames rendered by the last open() (the others came from the cache)
        self.unreadable, self.read_error = 0, None
        self._unwritten: OSError | None = None  # why a frame could not go to the cache

    @property
    def folder(self) -> Path | None:
        """The folder of this renderer's frames in the cache (``None`` without a cache)."""
        if self.cache is None:
            return None
        return self.cache / f"synthetic-{_renderer_key()}"

    def open(self) -> None:
        from ..vision.rgbd_io import RGBDSequence, synthetic_rgbd
        from ..vision.synthetic_rgbd import synthetic_rgbd_sequence

        rendered = synthetic_rgbd(self.num_frames, self.seed)  # frames rendered on access
        self._keys = _frame_keys(synthetic_rgbd_sequence(self.num_frames, seed=self.seed))
        intr = rendered.intrinsics
        self._shape = (int(intr.height), int(intr.width))
        folder = self.folder
        if folder is not None:
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as e:  # e.g. $PHJAX_FRAME_CACHE names a file: render in memory
                what = f"${FRAME_CACHE_ENV}={self.cache}" if self._cache_from_env else (
                    f"frame cache {self.cache}")
                self.report(f"synthetic head: warning: {what} is unusable "
                            f"({e.strerror or type(e).__name__}); rendering the frames in "
                            "memory for this run")
                self.cache = None
        if self.folder is not None:
            self._mark_used_and_prune()
        missing = [i for i in range(self.num_frames) if self._read(i) is None]
        self.rendered = len(missing)
        if missing:
            self._render(rendered, missing)
        stamps = np.asarray(rendered.timestamps, np.float64)
        self.sequence = RGBDSequence(
            [functools.partial(self._load, i, float(stamps[i]), intr)
             for i in range(self.num_frames)], stamps, intr, rendered.name,
            rendered.ground_truth, rendered.ground_truth_kind)
        super().open()

    def _mark_used_and_prune(self) -> None:
        """Mark this renderer's frame folder as used now (its time stamp) and remove the
        folders of other renderer versions that no run has used for
        :data:`STALE_FRAME_FOLDER_AGE` (each is 1.5 MB a frame, and a new phjax or JAX renders
        into a new one). Only folders named and filled as this class writes them are removed
        (a folder of the user's in the cache is kept); one report line when something was."""
        folder = self.folder
        try:
            os.utime(folder)
        except OSError:
            return
        now, removed, freed = time.time(), 0, 0
        for other in self.cache.glob("synthetic-*"):
            try:
                if (other.name == folder.name or not _FRAME_FOLDER.fullmatch(other.name)
                        or not other.is_dir()
                        or now - other.stat().st_mtime < STALE_FRAME_FOLDER_AGE):
                    continue
                files = list(other.iterdir())
                if not all(f.is_file() and _FRAME_FILE.fullmatch(f.name) for f in files):
                    continue  # not only frames: not ours to remove
                size = sum(f.stat().st_size for f in files)
            except OSError:
                continue
            shutil.rmtree(other, ignore_errors=True)
            if not other.exists():
                removed, freed = removed + 1, freed + size
        if removed:
            self.report(f"synthetic head: removed {removed} frame folder(s) of other renderer "
                        f"versions unused for {STALE_FRAME_FOLDER_AGE / 86400:.0f} days from "
                        f"{self.cache} ({freed / 2**20:.0f} MB)")

    def _path(self, i: int) -> Path:
        return self.folder / f"{self._keys[i]}.bin"

    def _read(self, i: int) -> bytes | np.ndarray | None:
        kept = self._memory.get(self._keys[i])
        if self.cache is None or kept is not None:
            return kept
        h, w = self._shape
        path = self._path(i)
        try:
            if path.stat().st_size != h * w * 5:
                return None
            return np.fromfile(path, np.uint8)
        except OSError:
            return None

    def _store(self, i: int, frame) -> None:
        depth = np.nan_to_num(np.asarray(frame.depth, np.float64), nan=0.0)
        steps = np.round(depth / CACHE_DEPTH_STEP)
        steps = np.where((steps >= 0) & (steps <= 65535), steps, 0).astype("<u2")
        data = np.ascontiguousarray(frame.color, np.uint8).tobytes() + steps.tobytes()
        if self.cache is None:
            self._memory[self._keys[i]] = data
            return
        path = self._path(i)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)  # atomic: a reader never sees half a frame
        except OSError as e:  # a read-only or full cache: this run keeps the frame in memory
            self._memory[self._keys[i]] = data
            self._unwritten = self._unwritten or e
            try:
                tmp.unlink()
            except OSError:
                pass

    def _render(self, rendered, missing: list[int]) -> None:
        from concurrent.futures import ThreadPoolExecutor

        where = f"into {self.folder}" if self.folder is not None else "in memory"
        mb = len(missing) * self._shape[0] * self._shape[1] * 5 / 2**20
        self.report(f"synthetic head: rendering {len(missing)} of {self.num_frames} frames once "
                    f"({mb:.0f} MB {where})"
                    + ("; later runs read them" if self.folder is not None else ""))
        t = time.perf_counter()
        self._store(missing[0], rendered[missing[0]])  # compiles the renderer
        threads = self.threads or os.cpu_count() or 1
        # JAX runs each render without the GIL: the threads use all cores
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for _ in pool.map(lambda i: self._store(i, rendered[i]), missing[1:]):
                pass
        self.report(f"synthetic head: rendered {len(missing)} frames in "
                    f"{time.perf_counter() - t:.0f} s")
        if self._unwritten is not None:
            kept = sum(self._keys[i] in self._memory for i in missing)
            e = self._unwritten
            self.report(f"synthetic head: warning: {kept} frame(s) could not be written to "
                        f"{self.folder} ({e.strerror or type(e).__name__}); kept in memory "
                        "for this run")

    def _load(self, i: int, timestamp: float, intrinsics):
        from ..vision.rgbd_io import RGBDFrame

        data = self._read(i)
        if data is None:
            raise SourceError(f"{self.name}: frame {i} is missing from the frame cache "
                              f"{self.folder}")
        h, w = self._shape
        buf = np.frombuffer(data, np.uint8)
        color = buf[: h * w * 3].reshape(h, w, 3)
        depth = buf[h * w * 3:].view("<u2").reshape(h, w).astype(np.float32) * np.float32(
            CACHE_DEPTH_STEP)
        return RGBDFrame(color, depth, intrinsics, timestamp, f"synthetic_{i:05d}")


# ------------------------------------------------------------------------------- video
class VideoSource(Source):
    """``cv2.VideoCapture`` (a webcam index or a video file), monocular head pose.

    Arguments:
        target: camera index (int, 0-99: :data:`WEBCAM_INDEX_LIMIT`) or video file path.
        ipd: assumed inter-pupillary distance, m (landmark method).
        fov: horizontal field of view of the camera, degrees (intrinsics of an uncalibrated
            camera; ignored when ``intrinsics`` is given).
        intrinsics: a :class:`phjax.vision.CameraIntrinsics` of the frames (its size must be
            the frames' size).
        model_dir: model cache (YuNet, the head-pose network).
        monocular: ``"net"`` (default: opentrack's head-pose network) or ``"landmarks"``
            (YuNet's five landmarks + PnP); see :mod:`phjax.vision.monocular`.
        head_size: assumed vertical head size, m (net method; default 0.20).
        estimator: a ready front-end with ``process(frame, t)`` and ``reset()`` (default: a
            :class:`phjax.vision.monocular.MonocularHeadPose` from the options above).
        report: called with one-line warnings (default: print them on stderr).

    A file is replayed at its frames' own timestamps (OpenCV's ``CAP_PROP_POS_MSEC``; a step
    outside 1/480 s .. 2 s is replaced by the frame period). Its frame rate is the header's
    when within :data:`VIDEO_RATES` (1-240 Hz); any other (0, 1000, 1e6, 1e-6 fps: a broken
    or a high-speed header) is taken as unknown: the file is played at 30 Hz
    (:data:`DEFAULT_VIDEO_RATE`) with one warning line. Late frames are skipped (counted in
    :attr:`Measurement.dropped`; the last frame is always delivered; a frame that cannot be
    decoded is a ``NO_FRAME`` measurement); a read error before the header's frame count ends
    the replay with the warning ``video ended at frame N of M (read error)``. A camera
    delivers frames at its own rate and each frame's capture time is its arrival time.

    Raises:
        SourceError: (on :meth:`open`) a missing file, a camera or file that cannot be opened
            or read, intrinsics of another image size than the frames'.
    """

    depth_free = True
    front_end = True

    def __init__(self, target, *, ipd: float | None = None, fov: float = 60.0,
                 intrinsics=None, model_dir=None, monocular: str = "net",
                 head_size: float | None = None, estimator=None,
                 report: Callable[[str], None] | None = None):
        from ..vision.monocular import METHODS

        if monocular not in METHODS:
            raise SourceError(f"monocular method must be one of {METHODS}, got {monocular!r}")
        self.monocular, self.head_size = monocular, head_size
        self.is_file = not isinstance(target, (int, np.integer))
        self.target = target if self.is_file else _webcam_index(int(target))
        self.name = f"video file {target}" if self.is_file else f"webcam {target}"
        self.ipd, self.fov, self.intrinsics, self.model_dir = ipd, fov, intrinsics, model_dir
        self.report = report if report is not None else (
            lambda line: print(line, file=sys.stderr, flush=True))
        self.cap = None
        self.estimator = estimator
        self.frame_count = 0  # the header's frame count of a file (0: unknown)

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
        if self.intrinsics is not None and (int(self.intrinsics.width),
                                            int(self.intrinsics.height)) != (w, h):
            self.close()
            raise SourceError(f"{self.name}: the intrinsics are for {self.intrinsics.width}x"
                              f"{self.intrinsics.height} images, the frames are {w}x{h}")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        plausible = math.isfinite(fps) and VIDEO_RATES[0] <= fps <= VIDEO_RATES[1]
        if self.is_file:
            count = float(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0)
            self.frame_count = int(count) if math.isfinite(count) and count > 0 else 0
            self._stamps = plausible  # the stamps share the header's time base
            self._pos_msec = cv2.CAP_PROP_POS_MSEC
            self._stamp0 = self._stamp()
            if not plausible:
                self.report(f"{self.name}: warning: the frame rate in its header ({fps:g} fps) "
                            f"is outside {VIDEO_RATES[0]:g}-{VIDEO_RATES[1]:g} fps; taken as "
                            f"unknown, playing it at {DEFAULT_VIDEO_RATE:g} fps")
            self.rate = fps if plausible else DEFAULT_VIDEO_RATE
        else:
            self.rate = fps if plausible else None
        if self.estimator is None:
            intr = self.intrinsics if self.intrinsics is not None else intrinsics_from_fov(
                w, h, self.fov)
            ipd = DEFAULT_IPD if self.ipd is None else self.ipd
            head = DEFAULT_HEAD_SIZE if self.head_size is None else self.head_size
            try:
                self.estimator = _with_models(lambda: MonocularHeadPose(
                    intr, ipd, method=self.monocular, head_size=head,
                    model_dir=self.model_dir))
            except (ImportError, ValueError) as e:  # a missing or corrupt model, onnxruntime
                self.close()  # the capture released
                raise SourceError(str(e).splitlines()[0]) from None
        self.estimator.process(frame, 0.0)  # warm-up
        self.estimator.reset()

    def run(self, clock, t0, stop, emit) -> None:
        if self.is_file:
            self._run_file(clock, t0, stop, emit)
            return
        frame = self._first
        t = clock.now()
        while not stop.is_set():
            emit(self._process(clock, t0, t, frame, 0))
            ok, frame = self.cap.read()
            t = clock.now()
            if not ok:
                raise SourceError(f"{self.name}: the camera stopped delivering frames")

    def _stamp(self) -> float:
        """The time of the frame just grabbed, s (OpenCV's, NaN when it gives none)."""
        try:
            return float(self.cap.get(self._pos_msec)) / 1e3
        except (TypeError, ValueError):
            return float("nan")

    def _next_time(self, t_prev: float, raw_prev: float, period: float) -> tuple[float, float]:
        """``(play time, raw stamp)`` of the frame just grabbed: the previous play time plus
        the step of the stream's own stamps when that step is a plausible frame interval,
        else plus ``period``."""
        raw = self._stamp() if self._stamps else float("nan")
        step = raw - raw_prev
        if math.isfinite(step) and 0.5 / VIDEO_RATES[1] <= step <= 2.0 / VIDEO_RATES[0]:
            return t_prev + step, raw
        return t_prev + period, raw

    def _run_file(self, clock, t0, stop, emit) -> None:
        """Each frame at its time; a frame is skipped, undecoded (``grab``), when the next one
        is already due, except the last one; every frame of the file is either delivered or
        counted as lost."""
        period = 1.0 / self.rate
        count = self.frame_count
        frame, index, t_rel, raw = self._first, 0, 0.0, self._stamp0
        skipped = 0
        while not stop.is_set():
            # frame `index` (decoded, or only grabbed when frame is None) plays at t0 + t_rel
            last = count > 0 and index >= count - 1
            if not last and clock.now() >= t0 + t_rel + period - 1e-9:
                skipped += 1  # late: the next frame is due already
            else:
                if frame is None:
                    ok, frame = self.cap.retrieve()
                    frame = frame if ok else None
                clock.sleep_until(t0 + t_rel, stop)
                if stop.is_set():
                    return
                if frame is None:  # grabbed but not decodable: a lost frame, go on
                    self._lost(t0 + t_rel, skipped + 1, emit)
                else:
                    emit(self._process(clock, t0, t0 + t_rel, frame, skipped))
                skipped = 0
            if not self.cap.grab():  # the end of the file, or a read error before it
                if index + 1 < count:
                    self._read_error(index + 1, count)
                self._lost(t0 + t_rel, skipped, emit)
                return
            index += 1
            frame = None
            t_rel, raw = self._next_time(t_rel, raw, period)

    def _read_error(self, frames: int, count: int) -> None:
        self.report(f"{self.name}: warning: video ended at frame {frames} of {count} "
                    "(read error)")

    def _lost(self, t: float, frames: int, emit) -> None:
        """Count ``frames`` as lost (skipped at the end of the replay, or not decodable): one
        measurement without a pose (``NO_FRAME``) carrying the others as dropped."""
        if frames > 0:
            p, q = _nan_pose()
            emit(Measurement(t, p, q, "NO_FRAME", 0.0, dropped=frames - 1))

    def _process(self, clock, t0: float, t: float, frame, dropped: int) -> Measurement:
        t_work = clock.now()
        r = self.estimator.process(frame, t - t0)
        return Measurement(t, r.position, r.quaternion, r.status.name, r.confidence,
                           dropped=dropped, work=clock.now() - t_work)

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
            ``software_device``); ``depth_scale`` is then used as given and must match the
            frames' depth unit (a real camera's scale is read from its depth sensor).
        depth_scale: metres per depth unit of ``frames`` (default 0.001; a real camera's
            own scale is used instead).
        model_dir: YuNet model cache.
        timeout: seconds to wait for a frame before counting it as lost.

    Unlike the other front-end sources, :meth:`open` does not warm up the front-end: its
    intrinsics come with the first frame, so the head-pose front-end is built and compiled
    while that frame is processed (the first measurement arrives a few seconds late; in a
    :class:`phjax.live.WorkerSource`, the default, the render loop is not held meanwhile).
    """

    front_end = True

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
            t_work = clock.now()
            r = self.estimator.process(frame[0], frame[1], t - t0, self.intrinsics)
            emit(Measurement(t, r.position, r.quaternion, r.status.name,
                             work=clock.now() - t_work))

    def close(self) -> None:
        if self.pipeline is not None:
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass
            self.pipeline = None


# ------------------------------------------------------------------------------- parsing
#: suffixes of the pose files phjax.io reads: never a video (``poses:FILE`` replays them)
_POSE_FILE_SUFFIXES = (".txt", ".tum", ".csv", ".json")


def open_source(spec: str, *, model_dir=None, ipd: float | None = None, fov: float = 60.0,
                monocular: str = "net", head_size: float | None = None,
                worker: bool = True, format: str = "auto", fps: float | None = None) -> Source:
    """A :class:`Source` from the ``SOURCE`` argument of ``phjax live`` (see the module docs).

    ``ipd``, ``fov``, ``monocular`` and ``head_size`` apply to webcam / video sources
    (:class:`VideoSource`), ``format`` (a :mod:`phjax.io` format, default by the file's
    content) to ``poses:FILE``, ``fps`` (frames per second, default
    :data:`phjax.vision.rgbd_io.DEFAULT_FOLDER_FPS`) to RGB-D folders whose frames carry no
    timestamps (Biwi, ``color/`` + ``depth/``; every other source plays at its own times).
    With ``worker=True`` (default) a source with a vision front-end
    (:attr:`Source.front_end`: synthetic, RGB-D folders, webcam / video, RealSense) is
    returned as a :class:`phjax.live.WorkerSource`: its frames and front-end run in a worker
    process, where they cannot hold the render loop (real clock only; pass ``worker=False``
    with a :class:`~phjax.live.VirtualClock`).

    Raises:
        SourceError: unknown source, missing file, bad number.
    """
    if worker:
        options = {"model_dir": model_dir, "ipd": ipd, "fov": fov, "monocular": monocular,
                   "head_size": head_size}
        local = open_source(spec, worker=False, format=format, fps=fps, **options)
        if not local.front_end:
            return local
        from ._worker import WorkerSource

        return WorkerSource(local, str(spec), {**options, "fps": fps})
    spec = str(spec)
    if fps is not None and not Path(spec).is_dir():
        raise SourceError(f"{spec}: fps / --fps is for RGB-D folders without timestamps (Biwi, "
                          "color/ + depth/); this source plays at its own times")
    kind, _, arg = spec.partition(":")
    kind = kind.lower() if kind.lower() in ("synthetic", "webcam", "realsense", "udp",
                                            "poses") else kind  # URL schemes: any case
    if kind == "synthetic":
        return SyntheticSource(*synthetic_spec(spec), model_dir=model_dir)
    if kind == "webcam":
        try:
            index = int(arg) if arg else 0
        except ValueError:
            index = arg
        return VideoSource(_webcam_index(index), ipd=ipd, fov=fov, model_dir=model_dir,
                           monocular=monocular, head_size=head_size)
    if kind == "realsense":
        return RealSenseSource(arg or None, model_dir=model_dir)
    if kind == "udp":
        from ._udp import UdpSource

        return UdpSource.from_spec(spec)
    if kind == "poses":
        if not arg:
            raise SourceError("poses: needs a file, poses:FILE")
        try:
            return PoseReplaySource.from_file(arg, format)
        except ValueError as e:
            raise SourceError(str(e)) from None
    path = Path(spec)
    if path.is_dir():
        from ..vision.rgbd_io import UNTIMED_LAYOUTS, open_rgbd, rgbd_layout

        try:
            if fps is not None and rgbd_layout(path) not in UNTIMED_LAYOUTS:
                raise SourceError(f"{spec}: a TUM RGB-D folder plays at its own timestamps "
                                  "(rgb.txt); fps / --fps is for Biwi and color/ + depth/ "
                                  "folders")
            seq = open_rgbd(path, **({"fps": fps} if fps is not None else {}))
        except ValueError as e:
            raise SourceError(str(e)) from None
        return RGBDReplaySource(seq, model_dir=model_dir, name=f"RGB-D recording {path}")
    if path.is_file():
        if path.suffix.lower() in _POSE_FILE_SUFFIXES:  # FFmpeg would "play" a text file
            raise SourceError(f"{spec}: a pose file is replayed with poses:{spec} (a file "
                              "named alone is played as a video)")
        return VideoSource(os.fspath(path), ipd=ipd, fov=fov, model_dir=model_dir,
                           monocular=monocular, head_size=head_size)
    if path.suffix or os.sep in spec or (os.altsep and os.altsep in spec):
        # no kind: prefix, and it looks like a file or folder name
        raise SourceError(f"{spec}: No such file or directory")
    raise SourceError(f"unknown source {spec!r}: use synthetic[:N[:SEED]], an RGB-D folder, "
                      "webcam[:INDEX], a video file, realsense[:SERIAL], poses:FILE or "
                      "udp://[HOST]:PORT")
