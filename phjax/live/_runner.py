"""The live runner: a capture thread feeding the tracker, a render loop sending poses.

Two threads share one :class:`phjax.tracking.TrackerStream`:

* **capture**: the source's measurements (camera rate), then a stream update. A source with
  a vision front-end (frames, face detection, head pose) runs by default in a worker process
  (:class:`phjax.live.WorkerSource`), and the capture thread only waits for its measurements
  in a blocking read that releases Python's GIL: the front-end's work (its CPU time, its
  Python sections, its garbage collections) cannot hold the render thread;
* **render**: at absolute deadlines ``t_k = t0 + k / rate`` (no drift: a late wake-up does not
  delay the next deadline; deadlines missed by a whole period are skipped and counted) it
  samples the stream at ``t_k`` and sends the pose to every output. The rate is at most
  :data:`MAX_RATE`.

The threads only exchange the stream's state (replaced atomically by an update) and a
few numbers, so a slow or failed frame is a late or missing measurement and never stalls the
render loop.

Timing figures (:meth:`LiveTracker.stats`, :meth:`LiveTracker.status_line`): the
*measurement age* is the time from a frame's capture to the stream update that applies it
(the front-end's latency); the *sent age* is the time from the capture of the newest applied
frame to the sending of a pose (measurement age plus the time since the update);
``Sample.age`` is the pose's render time minus that capture time.

Late measurements. A camera frame taken at ``t_c`` reaches the tracker at ``t_a > t_c``
(rendering, face detection, pose estimation). :meth:`LiveStream.update_late` runs the Kalman
filter with the measurement at its true time ``t_c`` but starts the new render segment at
``t_a`` from the pose being rendered then (a plain update at ``t_c`` would start the segment in
the past, so the correction it applies over the elapsed ``t_a - t_c`` would appear at once as
a jump). It is the tracker's own update with the render segment's start moved to ``t_a``: the
segment is built from the posterior at ``t_c`` predicted forward, and that posterior is the
filter's new state, so the next measurement is filtered at its own capture time. The first
measurement is a plain update (nothing has been rendered before it).

Adaptive settling. When measurements arrive less often than the tracker's ``horizon`` (a slow
front-end), a correction applied within ``horizon`` would be a visible step. With
``adaptive=True`` the runner sets ``horizon`` (and a ``rotation_horizon`` of its own, if the
config has one) to the measured interval between good
measurements (its running mean, or the last interval if longer, as after a lost face; at least
the configured value, at most 0.5 s) and ``coast_time`` to 1.5 times the horizon, never below
the configured value; the config is replaced only when the horizon moves by more than 15 % (a
longer horizon was tried: 1.5 intervals made the prediction overshoot more and the steps no
smaller), so the stream settles on each prediction just before the next measurement and
does not stop between measurements (changing these values does not recompile).

Per-frame confidence. A measurement's ``confidence`` (a monocular pose's predicted
uncertainty, :class:`phjax.vision.monocular.MonocularResult`) divides the filter's measurement
noise by ``sqrt(confidence)`` for that measurement alone (at least :data:`MIN_CONFIDENCE`): a
doubtful frame counts less instead of jerking the stream (changing the noise does not
recompile).

Never NaN: before the first good measurement nothing is sent; afterwards a non-finite sample
(none is expected) is replaced by the last good one. A lost face makes the stream coast, then
come to rest (``coast_time``, ``stop_time`` of :class:`phjax.TrackerConfig`).

Centring (as opentrack does): the pose at the first sample (``center=True``) or at the next
sample after :meth:`LiveTracker.center` becomes the origin: orientation ``q_c^-1 q``, position
``R_c^T (p - p_c)`` (the head's own axes at the centre pose become the reference axes).
"""

from __future__ import annotations

import gc
import math
import os
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Self

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._live_defaults import LIVE_NOISE_WINDOW
from .._np_quat import np_qconj, np_qmul, np_qnormalize
from ..tracking.kalman import KalmanConfig
from ..tracking.stream import TrackerStream, _wait_optimised
from ..tracking.tracker import TrackerConfig, _stream_filter, _update
from ._clock import RealClock, VirtualClock
from ._outputs import Output, TumLog, open_output
from ._sources import Measurement, Source, open_source
from ._worker import WorkerSource

__all__ = ["MAX_RATE", "MIN_CONFIDENCE", "LiveStream", "LiveTracker", "Sample",
           "live_tracker_config"]

#: the highest render rate, Hz: one pose per millisecond. A shorter period is below the
#: render loop's own wake-up and send time on a desktop OS (it would miss most deadlines)
#: and above any display's refresh rate.
MAX_RATE = 1000.0
#: the smallest confidence a measurement is given (its noise is at most 10 times the config's)
MIN_CONFIDENCE = 0.01
#: the config fields scaled by a measurement's noise scale (also inside an IMM config)
_MEAS_NOISE_FIELDS = ("pos_meas_noise", "rot_meas_noise")


# ------------------------------------------------------------------------------- stream
def _late_update(config: TrackerConfig, state, t_meas, t_now, position, quaternion):
    """Filter at the capture time ``t_meas``, render segment from ``t_now`` (module docs)."""
    return _update(config, state, t_meas, position, quaternion, t_now)


class LiveStream(TrackerStream):
    """:class:`phjax.tracking.TrackerStream` with late measurements and a settable config.

    Arguments: as :class:`phjax.tracking.TrackerStream` (``fast_start`` applies to
    :meth:`update_late`, the update a live run uses), except two defaults: ``t`` is 0.0 (times
    are relative to the run's start, the origin is not the first update's time) and ``dtype``
    is float64 when ``jax_enable_x64`` is on, else float32.
    """

    def __init__(self, config: TrackerConfig | None = None, t: float = 0.0, dtype=None,
                 fast_start: bool = True):
        if dtype is None:
            dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
        super().__init__(config, t, dtype, fast_start)

    def wait_compiled(self, timeout: float | None = None) -> bool:
        """Wait until :meth:`update_late` runs the optimised program (see ``fast_start``).

        Arguments:
            timeout: the longest wait, s (default: until it is ready).

        Returns:
            Whether late updates now run the optimised program.
        """
        return _wait_optimised(self._late, timeout)

    def set_config(self, config: TrackerConfig) -> None:
        """Use another config of the same structure (no recompilation)."""
        super().set_config(config)
        self._late = self._program(_late_update)
        paths = jax.tree_util.tree_flatten_with_path(config)[0]
        self._noise_leaves = [i for i, (path, _) in enumerate(paths)
                              if getattr(path[-1], "name", None) in _MEAS_NOISE_FIELDS]

    def update_late(self, t_measured: float, t_now: float, position, quaternion,
                    noise_scale: float = 1.0) -> None:
        """Feed a measurement taken at ``t_measured`` that arrives at ``t_now`` (module docs).

        Arguments:
            t_measured: capture time, s.
            t_now: current time (the new render segment starts here), s.
            position: ``(3,)`` m, NaN if missing; quaternion: ``(4,)`` ``wxyz``, NaN if missing.
            noise_scale: factor on the measurement noise stds (``pos_meas_noise``,
                ``rot_meas_noise``) for this measurement only.
        """
        dt = self._scalar  # the state's NumPy scalar type (TrackerStream)
        config = self._config_leaves
        if noise_scale != 1.0:
            config = list(config)
            for i in self._noise_leaves:
                config[i] = config[i] * dt(noise_scale)
        t_host = self._host_time(t_measured)  # sets the origin when unset
        self._relative(t_now)  # checked now; taken relative to the origin when applied
        position, quaternion = self._host_measurement(position, quaternion)
        self._feed(t_host, position, quaternion, lambda leaves, t, p, q: self._late(
            config, leaves, t, self._relative(t_now), p, q))


#: innovation gate of live configs: chi-square, 3 dof, p = 0.001
LIVE_GATE_NIS = 16.27


def live_tracker_config(depth_free: bool = False, base: TrackerConfig | None = None
                        ) -> TrackerConfig:
    """The tracker config of a live source.

    ``base`` (default: :class:`TrackerConfig` with the single-model Kalman filter
    (``imm=None``) and its innovation gate :data:`LIVE_GATE_NIS`, so that a gross front-end
    error, e.g. a misaligned frame, is rejected instead of swinging the view; the IMM filter
    has no gate yet; and the online noise floor, ``noise_window`` :data:`LIVE_NOISE_WINDOW`),
    with the monocular measurement noise
    (:data:`phjax.vision.monocular.MONOCULAR_NOISE`) when the poses come from colour alone.
    A given ``base`` keeps its own filter and gate (the monocular noise applies to the
    single-model filter).
    """
    if base is None:
        base = TrackerConfig(kalman=KalmanConfig(gate_nis=LIVE_GATE_NIS), imm=None,
                             noise_window=LIVE_NOISE_WINDOW)
    if not depth_free:
        return base
    from ..vision.monocular import MONOCULAR_NOISE

    k = base.kalman
    kalman = KalmanConfig(model=k.model, pos_process_noise=k.pos_process_noise,
                          pos_meas_noise=max(float(k.pos_meas_noise), MONOCULAR_NOISE[0]),
                          rot_process_noise=k.rot_process_noise,
                          rot_meas_noise=max(float(k.rot_meas_noise), MONOCULAR_NOISE[1]),
                          init_pos_vel_std=k.init_pos_vel_std,
                          init_pos_acc_std=k.init_pos_acc_std,
                          init_rot_vel_std=k.init_rot_vel_std, gate_nis=k.gate_nis,
                          gate_reset=k.gate_reset)
    return eqx.tree_at(lambda c: c.kalman, base, kalman)


# ------------------------------------------------------------------------------- runner
@dataclass(frozen=True)
class Sample:
    """One sent pose.

    Attributes:
        t: render time, s since the start of the run.
        position: ``(3,)`` m; quaternion: ``(4,)`` ``wxyz`` (after centring: what was sent).
        age: ``t`` minus the capture time of the newest measurement applied, s.
    """

    t: float
    position: np.ndarray
    quaternion: np.ndarray
    age: float


class _Ring:
    """The last ``n`` values of a float series (bounded memory)."""

    def __init__(self, n: int = 8192):
        self.a = np.full(n, np.nan)
        self.i = 0

    def add(self, x: float) -> None:
        self.a[self.i % self.a.shape[0]] = x
        self.i += 1

    def values(self) -> np.ndarray:
        v = self.a if self.i >= self.a.shape[0] else self.a[: self.i]
        return v[np.isfinite(v)]


def _percentile(v: np.ndarray, q: float) -> float:
    return float(np.percentile(v, q)) if v.size else float("nan")


class LiveTracker:
    """Run a live source through the tracker and send the poses to outputs.

    Arguments:
        source: a :class:`phjax.live.Source` or a ``phjax live`` SOURCE string.
        outputs: :class:`phjax.live.Output` objects or URLs (``opentrack://HOST:PORT``,
            ``osc://HOST:PORT``).
        rate: render rate, Hz, in ``(0, MAX_RATE]`` (:data:`MAX_RATE`: 1000; default 120).
        duration: stop after this many seconds (default: ``linger`` seconds after the source
            ends, or on :meth:`stop`).
        log: path of a TUM log of every sent pose.
        center: make the first sent pose the origin (see :meth:`center`).
        config: tracker config (default :func:`live_tracker_config` of the source).
        adaptive: adapt the settling time to the measurement rate (module docs).
        clock: :class:`RealClock` (default) or :class:`VirtualClock`.
        callback: called with each :class:`Sample` in the render thread (keep it short).
        model_dir, ipd, fov: passed to :func:`phjax.live.open_source` for a string source.
        worker: run a string source's vision front-end in a worker process
            (:class:`phjax.live.WorkerSource`; always off with a :class:`VirtualClock`).
        switch_interval: Python's thread switch interval while running, s (default 0.5 ms:
            the render thread gets the GIL within that time of its deadline; restored at
            :meth:`stop`); ``None`` leaves it alone. On the real clock the objects alive at
            the start are also exempted from Python's cyclic garbage collector for the run
            (``gc.freeze``, undone at :meth:`stop`): a full collection of the ~300 000
            objects of a process with JAX, phjax and a front-end loaded took 140 ms, a stall
            of every thread; afterwards it scans only the objects made during the run.
        render_nice, capture_nice: niceness increments (Linux, best effort: raising a
            priority needs ``CAP_SYS_NICE`` and is skipped without it; ``None``: unchanged).
            ``render_nice`` is the render thread's, and the capture thread's when the source
            does no heavy work in this process (a worker source, a pose replay): a thread
            that holds the GIL must not wait behind other programs while the render thread
            waits for the GIL. ``capture_nice`` is the front-end's: the worker process's, or
            the capture thread's when the front-end runs in it. By default the render loop
            gets a little more of a busy CPU than the front-end.
        realtime: run the render thread with the real-time policy ``SCHED_FIFO`` (Linux,
            best effort: needs ``CAP_SYS_NICE`` or an ``rtprio`` limit; ``realtime_active``
            says whether it took effect). On a busy CPU this keeps the render deadlines when
            ordinary priorities do not; the thread sleeps between samples (a few % of a core).
        linger: without ``duration``, keep rendering this long after the source ends, s
            (default 0.5).

    Use as a context manager (``start`` / ``stop``) and iterate :meth:`samples`, read
    :attr:`latest`, or pass a ``callback``::

        with phjax.live.LiveTracker("synthetic:240", ["opentrack://127.0.0.1:4242"],
                                    rate=120, duration=5) as lt:
            for s in lt.samples():
                print(s.t, s.position, s.quaternion)
    """

    def __init__(self, source: Source | str, outputs: Sequence[Output | str] = (), *,
                 rate: float = 120.0, duration: float | None = None, log=None,
                 center: bool = False, config: TrackerConfig | None = None,
                 adaptive: bool = True, clock=None, callback: Callable[[Sample], None] | None
                 = None, model_dir=None, ipd: float | None = None, fov: float = 60.0,
                 switch_interval: float | None = 5e-4, linger: float = 0.5,
                 render_nice: int | None = -5, capture_nice: int | None = 5,
                 realtime: bool = False, worker: bool = True):
        rate = float(rate)
        if not (math.isfinite(rate) and 0 < rate <= MAX_RATE):
            raise ValueError(f"rate must be in (0, {MAX_RATE:g}] Hz, got {rate:g}: one pose is "
                             "sent per period, and a period under 1 ms is shorter than the "
                             "render loop's own wake-up and send time")
        if duration is not None and not duration > 0:
            raise ValueError(f"duration must be positive, got {duration}")
        self.rate, self.duration = rate, duration
        self.clock = RealClock() if clock is None else clock
        if self.clock.virtual and isinstance(source, WorkerSource):
            raise ValueError("a worker source runs in real time: use open_source(..., "
                             "worker=False) with a VirtualClock")
        self.callback = callback
        self.adaptive = adaptive
        self.linger = float(linger)
        self.render_nice, self.capture_nice = render_nice, capture_nice
        self.realtime = bool(realtime) and not self.clock.virtual
        self.realtime_active = False
        self.switch_interval = None if self.clock.virtual else switch_interval
        self._outputs: list[Output] = []
        self._log = None
        self.source = None
        try:
            self.source = source if isinstance(source, Source) else open_source(
                source, model_dir=model_dir, ipd=ipd, fov=fov,
                worker=worker and not self.clock.virtual)
            for out in outputs:
                self._outputs.append(out if isinstance(out, Output) else open_output(out))
            if log is not None:
                self._log = TumLog(log)
            self._check_feedback()
        except BaseException:
            self._close_outputs(raise_first=False)
            raise
        self.base_config = config if config is not None else live_tracker_config(
            self.source.depth_free)
        self._config_used = self.base_config
        self.stream = LiveStream(self.base_config)
        self._center_flag = bool(center)
        self._center_request = False
        self._center = None
        self._stop = threading.Event()
        self._finished = threading.Event()
        self._render_done = threading.Event()
        self._threads: list[threading.Thread] = []
        self._queues: list[queue.Queue] = []
        self._started = False
        self._closed = False
        self._gc_frozen = False
        self.error: BaseException | None = None
        # statistics (written by one thread each)
        self.status_counts: Counter = Counter()
        self.frames = 0
        self.dropped = 0
        self.no_pose: Counter = Counter()  # frames without a pose, by front-end status
        self.sent = 0
        self._sent_at_t0 = 0  # the send at the start's deadline (rates count those after it)
        self.missed_deadlines = 0
        self.waiting = 0
        self.held = 0
        self.intervals = _Ring()
        self.ages = _Ring()
        self.applied_ages = _Ring()
        self.sent_ages = _Ring()
        self.work_times = _Ring(1024)
        self.frame_times = _Ring(256)
        self._status_prev = None
        self.latest: Sample | None = None
        self._last_capture = None
        self._last_ok_t = None
        self._interval_ema = None
        self._last_good = None
        self._last_send = None
        self.t0 = None
        self._end_time = None
        self._t_render_end = None
        self.k = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LiveTracker:
        """Open the source (warm-up included), compile the stream and start both threads.

        A worker source is launched first, so that its warm-up runs while the stream
        compiles."""
        if self._started:
            raise RuntimeError("a LiveTracker can be started once")
        if self._closed:  # stop() before start() closed the outputs (and the source)
            raise RuntimeError("this LiveTracker was stopped before it started; make a new one")
        self._started = True
        try:
            if isinstance(self.source, WorkerSource):
                self.source.nice = self.capture_nice
                self.source.launch()
            self._warm_up()
            self.source.open()
            self._check_feedback()
        except BaseException:
            self._cleanup()
            raise
        if self.switch_interval is not None:
            self._old_switch = sys.getswitchinterval()
            sys.setswitchinterval(self.switch_interval)
        if not self.clock.virtual:
            gc.collect()
            gc.freeze()
            self._gc_frozen = True
        self.t0 = self.clock.now()
        if self.duration is not None:
            self._end_time = self.t0 + float(self.duration)
        self._threads = [threading.Thread(target=self._capture_main, name="phjax-live-capture",
                                          daemon=True),
                         threading.Thread(target=self._render_main, name="phjax-live-render",
                                          daemon=True)]
        for _ in self._threads:
            self.clock.register()  # registered before start: the virtual clock waits for both
        for th in self._threads:
            th.start()
        return self

    def _check_feedback(self) -> None:
        """A UDP source must not receive this tracker's own outputs (checked once its socket
        is open: here, or in :meth:`start`)."""
        check = getattr(self.source, "check_outputs", None)
        if check is not None:
            check(self._outputs)

    def _warm_up(self) -> None:
        s = LiveStream(self.base_config)
        p, q = np.zeros(3), np.array([1.0, 0, 0, 0])
        s.update_late(0.0, 0.01, p, q)
        s.update_late(0.02, 0.03, p, q)
        np.asarray(s.sample(0.04)[0])

    def stop(self, timeout: float | None = None) -> None:
        """Stop both threads, close the outputs, the log and the source (idempotent).

        Arguments:
            timeout: seconds to wait for each thread (default: until it ends). A thread still
                running then (a camera read hanging in its driver) is left behind (it is a
                daemon thread) and everything is closed all the same.
        """
        self.request_stop()
        if isinstance(self.clock, VirtualClock):
            self.clock.wake()
        for th in self._threads:
            th.join(timeout)
        self._cleanup()

    def request_stop(self) -> None:
        """Ask the run to end (returns at once; safe in a signal handler): both threads leave
        their loops at their next wake-up, :meth:`run` then stops and returns."""
        self._stop.set()

    def _cleanup(self) -> None:
        if self._closed:
            return
        self._closed = True
        # everything is closed and restored even when a close fails (a full disk under the
        # log: the source's socket or worker stayed open); the first error is raised after
        errors = self._close_outputs(raise_first=False)
        try:
            if self.source is not None:
                self.source.close()
        except Exception as e:  # noqa: BLE001 - raised below, after the rest is restored
            errors.append(e)
        if getattr(self, "_old_switch", None) is not None:
            sys.setswitchinterval(self._old_switch)
            self._old_switch = None
        if self._gc_frozen:
            gc.unfreeze()
            self._gc_frozen = False
        for q in self._queues:
            try:
                q.put_nowait(None)
            except queue.Full:
                pass
        self._finished.set()
        if errors:
            raise errors[0]

    def _close_outputs(self, raise_first: bool = True) -> list[Exception]:
        """Close every output and the log, each even if another failed; the errors (the first
        one raised when ``raise_first``)."""
        errors = []
        for close in [o.close for o in self._outputs] + (
                [self._log.close] if self._log is not None else []):
            try:
                close()
            except Exception as e:  # noqa: BLE001 - collected, see above
                errors.append(e)
        if errors and raise_first:
            raise errors[0]
        return errors

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the run ends by itself (duration, end of source); True if it ended."""
        return self._render_done.wait(timeout)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._started and not self._closed and any(t.is_alive() for t in self._threads)

    def center(self) -> None:
        """Make the pose of the next sample the origin."""
        self._center_request = True

    @property
    def outputs(self) -> list[Output]:
        return list(self._outputs)

    # ------------------------------------------------------------------ capture thread
    def _capture_main(self) -> None:
        in_process = self.source.front_end and not isinstance(self.source, WorkerSource)
        _renice(self.capture_nice if in_process else self.render_nice)
        try:
            self.source.run(self.clock, self.t0, self._stop, self._on_measurement)
        except BaseException as e:  # noqa: BLE001 - reported by run() / the CLI
            self.error = e
            self._stop.set()
        finally:
            if self._end_time is None:
                self._end_time = self.clock.now() + self.linger
            self.clock.unregister()

    def _on_measurement(self, m: Measurement) -> None:
        now = self.clock.now()
        self.frames += 1
        self.dropped += int(m.dropped)
        self.status_counts[m.status] += 1
        self.frame_times.add(m.t)
        self.work_times.add(m.work)
        ok = m.ok
        if not ok:
            self.no_pose[m.status if m.status != "OK" else "no pose"] += 1
        if ok and self.adaptive:
            self._adapt(m.t)
        scale = 1.0 / math.sqrt(max(min(float(m.confidence), 1.0), MIN_CONFIDENCE)) if ok \
            else 1.0
        self.stream.update_late(m.t - self.t0, max(now, m.t) - self.t0,
                                np.asarray(m.position, np.float64),
                                np.asarray(m.quaternion, np.float64), scale)
        if ok:
            self._last_capture = m.t
            self.applied_ages.add(self.clock.now() - m.t)

    def _adapt(self, t: float) -> None:
        if self._last_ok_t is not None:
            dt = min(max(t - self._last_ok_t, 0.0), 1.0)
            self._interval_ema = dt if self._interval_ema is None else (
                0.8 * self._interval_ema + 0.2 * dt)
            base = self.base_config
            # the typical interval, or this one if longer (re-acquisition after a loss: the
            # larger correction is spread over a longer time)
            def adapted(h):
                return min(max(float(h), self._interval_ema, dt), 0.5)

            horizon = adapted(base.horizon)
            used = self._config_used
            moved = abs(horizon - float(used.horizon)) > 0.15 * float(used.horizon)
            if base.rotation_horizon is None:
                fields, values = (lambda c: (c.horizon, c.coast_time)), (horizon,)
            else:  # an orientation horizon of its own adapts in the same way
                rot = adapted(base.rotation_horizon)
                moved |= abs(rot - float(used.rotation_horizon)) > 0.15 * float(
                    used.rotation_horizon)
                fields = lambda c: (c.horizon, c.rotation_horizon, c.coast_time)  # noqa: E731
                values = (horizon, rot)
            if moved:
                coast = max(float(base.coast_time), 1.5 * max(values))
                cfg = eqx.tree_at(fields, base, (*values, coast))
                self.stream.set_config(cfg)
                self._config_used = cfg
        self._last_ok_t = t

    # ------------------------------------------------------------------ render thread
    def _render_main(self) -> None:
        _renice(self.render_nice)
        if self.realtime:
            self.realtime_active = _set_fifo()
        clock, period = self.clock, 1.0 / self.rate
        try:
            while not self._stop.is_set():
                t_k = self.t0 + self.k * period
                end = self._end_time
                if end is not None and t_k > end + 1e-9:
                    # the run lasts its duration even when the rate's period is longer than
                    # what is left of it (rates of 1 Hz and below)
                    clock.sleep_until(end, self._stop)
                    break
                clock.sleep_until(t_k, self._stop)
                if self._stop.is_set():
                    break
                late = clock.now() - t_k
                if late >= period:  # whole periods missed: skip them (no backlog, no drift)
                    skip = int(late / period)
                    self.k += skip
                    self.missed_deadlines += skip
                    t_k = self.t0 + self.k * period
                self._render_one(t_k)
                self.k += 1
        except BaseException as e:  # noqa: BLE001
            self.error = e
        finally:
            self._t_render_end = self.clock.now()
            self._stop.set()
            self.clock.unregister()
            self._render_done.set()

    def _render_one(self, t_k: float) -> None:
        p, q = self.stream.sample(t_k - self.t0)
        p = np.asarray(p, np.float64)
        q = np.asarray(q, np.float64)
        if np.isfinite(p).all() and np.isfinite(q).all():
            self._last_good = (p, q)
        elif self._last_good is None:
            self.waiting += 1
            return
        else:
            p, q = self._last_good
            self.held += 1
        if self._center_request or (self._center_flag and self._center is None):
            self._center = (p.copy(), q.copy())
            self._center_request = False
        if self._center is not None:
            pc, qc = self._center
            qi = np_qconj(qc)
            q = np_qmul(qi, q)
            d = p - pc
            p = _rotate(qi, d)
        q = np_qnormalize(q)  # finite and non-zero here: the held or the centred pose
        ts = t_k - self.t0
        for out in self._outputs:
            out.send(ts, p, q)
        if self._log is not None:
            self._log.send(ts, p, q)
        now = self.clock.now()
        if self._last_send is not None:
            self.intervals.add(now - self._last_send)
        self._last_send = now
        capture = self._last_capture
        age = t_k - capture if capture is not None else float("nan")
        self.ages.add(age)
        self.sent_ages.add(now - capture if capture is not None else float("nan"))
        self.sent += 1
        if t_k == self.t0:
            self._sent_at_t0 = 1
        s = Sample(ts, p, q, age)
        self.latest = s
        if self.callback is not None:
            self.callback(s)
        for qu in self._queues:
            try:
                qu.put_nowait(s)
            except queue.Full:
                pass

    # ------------------------------------------------------------------ consumers
    def samples(self, maxsize: int = 1024) -> Iterator[Sample]:
        """Iterate over the sent samples until the run ends (a slow consumer loses samples
        once ``maxsize`` are queued, never the render loop's time)."""
        qu: queue.Queue = queue.Queue(maxsize=maxsize)
        self._queues.append(qu)
        try:
            while True:
                try:
                    s = qu.get(timeout=0.1)
                except queue.Empty:
                    if self._finished.is_set() or (self._render_done.is_set() and qu.empty()):
                        return
                    continue
                if s is None:
                    return
                yield s
        finally:
            self._queues.remove(qu)

    def run(self, status: Callable[[str], None] | None = None, status_interval: float = 1.0
            ) -> None:
        """Start, block until the run ends (duration, end of source, Ctrl-C), stop.

        Arguments:
            status: called with :meth:`status_line` every ``status_interval`` seconds.
            status_interval: seconds between status lines (wall clock; default 1.0).

        Raises:
            the capture or render thread's exception, if one ended the run.
        """
        if not self._started:
            self.start()
        try:
            next_status = time.monotonic() + status_interval
            while not self._render_done.wait(0.1):
                if status is not None and time.monotonic() >= next_status:
                    status(self.status_line())
                    next_status += status_interval
        finally:
            self.stop()
        if status is not None:
            status(self.status_line())
        if self.error is not None:
            raise self.error

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict:
        """Counts so far and timing statistics over a recent window (the last 8192 samples and
        measurements, the last 256 frames for the camera rate, the last 1024 front-end times).

        Keys: ``elapsed`` (s), ``frames`` (measurements received), ``status`` (their counts
        by front-end status), ``dropped`` (camera frames lost before reaching the front-end),
        ``no_pose`` (frames without a pose, by status), ``lost`` (``dropped`` plus the
        ``no_pose`` counts), ``camera_fps``, ``sent``, ``sent_hz`` (the poses sent after the
        start's deadline per second of ``elapsed``), ``missed_deadlines``, ``waiting``
        (deadlines before the first pose), ``held`` (a non-finite sample replaced by the last
        good one), ``render_hz``, ``interval_p50`` / ``_p99`` / ``_max`` (between sends, s),
        ``age_p50`` / ``_p99`` (``Sample.age``), ``applied_age_p50`` / ``_p99`` (capture to
        stream update), ``sent_age_p50`` / ``_p99`` (capture to send), ``front_end_p50`` (the
        front-end's time per frame; NaN if the source does not say), ``horizon``,
        ``rotation_horizon`` (the orientation's: ``horizon`` unless the config sets its own)
        and ``lookahead`` (s, of the config in use), ``noise`` (the filter's position / orientation
        measurement stds now, m / rad: :meth:`TrackerStream.measurement_noise`) and
        ``noise_raised`` (whether the online noise floor has raised them above the configured
        ones: the source is noisier than assumed), ``send_errors`` (per output URL: packets the
        network refused, e.g. nothing listening on that port), ``out_of_range`` (per output
        URL: poses not sent because a value does not fit its format).
        """
        iv = self.intervals.values()
        ages = self.ages.values()
        applied = self.applied_ages.values()
        sent_ages = self.sent_ages.values()
        work = self.work_times.values()
        ft = self.frame_times.values()
        end = self._t_render_end if self._t_render_end is not None else self.clock.now()
        elapsed = (end - self.t0) if self.t0 is not None else 0.0
        cam = (ft.size - 1) / (ft.max() - ft.min()) if ft.size > 1 and ft.max() > ft.min() \
            else float("nan")
        noise = self.stream.measurement_noise()
        base = _stream_filter(self._config_used)
        raised = (noise[0] > float(base.pos_meas_noise) or noise[1] > float(base.rot_meas_noise))
        return {
            "elapsed": elapsed,
            "frames": self.frames,
            "status": dict(self.status_counts),
            "dropped": self.dropped,
            "no_pose": dict(self.no_pose),
            "lost": self.dropped + sum(self.no_pose.values()),
            "camera_fps": float(cam),
            "sent": self.sent,
            "sent_hz": (self.sent - self._sent_at_t0) / elapsed if elapsed > 0 else float("nan"),
            "missed_deadlines": self.missed_deadlines,
            "waiting": self.waiting,
            "held": self.held,
            "render_hz": float(1.0 / np.mean(iv)) if iv.size else float("nan"),
            "interval_p50": _percentile(iv, 50),
            "interval_p99": _percentile(iv, 99),
            "interval_max": float(iv.max()) if iv.size else float("nan"),
            "age_p50": _percentile(ages, 50),
            "age_p99": _percentile(ages, 99),
            "applied_age_p50": _percentile(applied, 50),
            "applied_age_p99": _percentile(applied, 99),
            "sent_age_p50": _percentile(sent_ages, 50),
            "sent_age_p99": _percentile(sent_ages, 99),
            "front_end_p50": _percentile(work, 50),
            "horizon": float(self._config_used.horizon),
            "rotation_horizon": float(self._config_used.horizon
                                      if self._config_used.rotation_horizon is None
                                      else self._config_used.rotation_horizon),
            "lookahead": float(self._config_used.lookahead),
            "noise": noise,
            "noise_raised": raised,
            "send_errors": {o.url: int(getattr(o, "send_errors", 0)) for o in self._outputs},
            "out_of_range": {o.url: int(getattr(o, "out_of_range", 0)) for o in self._outputs},
        }

    def status_line(self) -> str:
        """One line of what a user watches: input frames per second and output poses per
        second since the previous call (or the start), lost frames (total, by reason), the
        measurement and sent ages (medians, recent window), the render interval's 99th
        percentile and missed deadlines, the lookahead in use, and, when the online noise
        floor has raised the filter's measurement noise (a source noisier than assumed), that
        noise::

            t   12.0 s | in 29.9 fps, lost 4 (late 1, NO_FACE 3) | out 120.0 Hz, p99 8.9 ms,
            missed 0 | age 24 ms, sent 41 ms | lookahead 20 ms | noise 18 mm, 2.9 deg

        (one line; wrapped here).
        """
        s = self.stats()
        now = self._t_render_end if self._t_render_end is not None else self.clock.now()
        prev = self._status_prev if self._status_prev is not None else (
            self.t0 if self.t0 is not None else now, 0, self._sent_at_t0)
        span = now - prev[0]
        fps = (self.frames - prev[1]) / span if span > 0 else float("nan")
        hz = (self.sent - prev[2]) / span if span > 0 else float("nan")
        self._status_prev = (now, self.frames, self.sent)
        reasons = ([f"late {s['dropped']}"] if s["dropped"] else []) + [
            f"{k} {v}" for k, v in sorted(s["no_pose"].items())]
        lost = f"lost {s['lost']}" + (f" ({', '.join(reasons)})" if reasons else "")
        failed = sum(s["send_errors"].values())
        return (f"t {s['elapsed']:6.1f} s | in {fps:5.1f} fps, {lost} | out {hz:6.1f} Hz, "
                + (f"failed {failed}, " if failed else "")
                + f"p99 {_ms(s['interval_p99'], 1)}, missed {s['missed_deadlines']} | "
                f"age {_ms(s['applied_age_p50'])}, sent {_ms(s['sent_age_p50'])} | "
                f"lookahead {1e3 * s['lookahead']:.0f} ms"
                + (f" | noise {1e3 * s['noise'][0]:.0f} mm, {math.degrees(s['noise'][1]):.1f} deg"
                   if s["noise_raised"] else ""))


def _ms(seconds: float, digits: int = 0) -> str:
    return f"{1e3 * seconds:.{digits}f} ms" if math.isfinite(seconds) else "-"


def _renice(increment: int | None) -> None:
    """Change the calling thread's nice value by ``increment`` (Linux; errors ignored)."""
    if not increment or not hasattr(os, "setpriority") or not hasattr(threading, "get_native_id"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
    except OSError:
        pass


def _set_fifo() -> bool:
    """Put the calling thread under ``SCHED_FIFO`` (lowest real-time priority); True if done."""
    if not hasattr(os, "sched_setscheduler") or not hasattr(threading, "get_native_id"):
        return False
    try:
        os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    return True


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate the 3-vector ``v`` by the unit quaternion ``q`` (wxyz)."""
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)
