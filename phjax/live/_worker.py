"""The camera front-end in a worker process, so that it cannot hold the render loop.

A camera source's per-frame work (reading the frame, face detection, head pose: 20-60 ms of
CPU) run in a thread of the render loop's process shares that process's interpreter with the
render thread: its CPU time, its Python sections under the global interpreter lock (GIL), its
objects (a full garbage collection of a process with JAX, phjax and the front-end loaded took
140 ms, a stall of every thread) and its crashes. :class:`WorkerSource` runs the source in a
separate Python process instead; only the measurements (a few numbers per frame) come back,
and the capture thread of :class:`phjax.live.LiveTracker` waits for them in a blocking read
that releases the GIL. Measured (``benchmarks/bench_live.py --modes worker thread``,
``benchmarks/README.md``): the front-end itself holds the GIL only briefly (OpenCV and JAX
release it; a 1 ms sleep loop beside it had a p99 gap of 4.5 ms instead of 2-3 ms), so at a
moderate load both placements kept the same deadlines; on a 2-core machine at load 6-9 the
worker missed fewer in 4 of 5 pairs of short rows (17-90 deadlines against 46-144).

The worker is a fresh interpreter running :func:`_main` (like
``multiprocessing``'s "spawn": JAX is not fork-safe), started with :mod:`subprocess` rather
than :mod:`multiprocessing` so that nothing of the caller's ``__main__`` is imported again: a
script that starts a :class:`~phjax.live.LiveTracker` at top level needs no
``if __name__ == "__main__"`` guard. It runs in its own session (a terminal's Ctrl-C reaches
the parent, which stops it), with the parent's JAX settings (``jax_enable_x64``, asynchronous
dispatch, the persistent compilation cache) and a lower priority (``nice``).

Protocol. The parent writes one JSON line to the worker's stdin (the source spec and options,
JAX settings), the worker opens the source (warm-up, frame rendering) and answers
``["ready", now, rate, name]`` on a pipe of its own (its file descriptor is the worker's
argument); ``run T0`` on stdin starts the capture
with the run's start time ``T0``; each frame's measurement comes back as one JSON line
``["m", t, position, quaternion, status, confidence, dropped, work]``; ``stop`` (or the end
of stdin: the parent is gone) ends the capture and the worker sends ``["end"]``. An exception
in the worker becomes ``["error", LINE]`` (a ``ValueError`` / ``OSError``: its message as is;
any other: ``"Type: message (file:line)"``) and a one-line
:class:`~phjax.live.SourceError` in the parent; a worker that dies without a word is reported
with its exit code. The worker's stdout goes to the parent's stderr (a stray ``print`` cannot
corrupt the protocol).

Clock. Capture times are ``time.perf_counter()`` of the worker, which is the same system-wide
monotonic clock as the parent's :class:`~phjax.live.RealClock` (``CLOCK_MONOTONIC`` on Linux,
``mach_absolute_time`` on macOS, ``QueryPerformanceCounter`` on Windows); the hand-shake
checks it (the worker's ``now`` must lie between the parent's launch and the reply).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import traceback

import numpy as np

from ._sources import Measurement, Source, SourceError

__all__ = ["WorkerSource"]

#: seconds :meth:`WorkerSource.close` waits for the worker to end by itself before terminating it
_STOP_WAIT = 3.0
#: the worker's program (``python -c``: ``-m`` would run this module a second time, beside
#: the copy that importing :mod:`phjax.live` loads)
_ENTRY = "import sys; from phjax.live._worker import _main; sys.exit(_main(int(sys.argv[1])))"
#: the JAX settings the worker copies from the parent
_JAX_SETTINGS = ("jax_enable_x64", "jax_cpu_enable_async_dispatch",
                 "jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")


def _jax_setting(config, name: str):
    """A JAX setting's value (JAX reads some through ``config.read``, others as attributes)."""
    try:
        return config.read(name)
    except AttributeError:
        return getattr(config, name)


def _one_line(e: BaseException) -> str:
    """``Type: first line of the message (file:line of the innermost frame)``."""
    msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
    where = ""
    tb = traceback.extract_tb(e.__traceback__) if e.__traceback__ is not None else []
    if tb:
        where = f" ({os.path.basename(tb[-1].filename)}:{tb[-1].lineno})"
    return f"{type(e).__name__}: {msg}{where}" if msg else f"{type(e).__name__}{where}"


class WorkerSource(Source):
    """A source whose capture and front-end run in a worker process (module docs).

    Arguments:
        local: the same source built in this process (not opened): its ``name``,
            ``depth_free`` and ``rate`` describe the worker's source.
        spec, options: :func:`phjax.live.open_source`'s ``SOURCE`` string and keyword
            arguments (JSON-serialisable), with which the worker builds the source.
        nice: niceness increment of the worker (Unix; ``None``: unchanged). By default the
            front-end yields a busy CPU to the render loop.

    Real clock only (a :class:`~phjax.live.VirtualClock` cannot be shared between processes:
    use ``open_source(..., worker=False)`` there).
    """

    front_end = True

    def __init__(self, local: Source, spec: str, options: dict, *, nice: int | None = 5):
        self.local_name = local.name
        self.name = local.name
        self.depth_free = local.depth_free
        self.rate = local.rate
        self.spec = str(spec)
        self.options = {k: (os.fspath(v) if isinstance(v, os.PathLike) else v)
                        for k, v in options.items()}
        self.nice = nice
        self.proc: subprocess.Popen | None = None
        self._rx = None
        self._launched_at = None
        self._ready = False
        self._stdin_lock = threading.Lock()

    # ------------------------------------------------------------------ parent side
    def launch(self) -> None:
        """Start the worker process (returns at once; :meth:`open` waits until it is ready).

        :class:`~phjax.live.LiveTracker` launches the worker before compiling its own
        stream, so that both warm up at the same time."""
        if self.proc is not None:
            return
        import jax

        settings = {name: _jax_setting(jax.config, name) for name in _JAX_SETTINGS}
        if settings["jax_compilation_cache_dir"] is not None:
            settings["jax_compilation_cache_dir"] = os.fspath(
                settings["jax_compilation_cache_dir"])
        r, w = os.pipe()
        try:
            env = dict(os.environ)
            # the worker imports this very package (also when it is not installed)
            root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
            env["PYTHONPATH"] = os.pathsep.join(
                [root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
            self._launched_at = time.perf_counter()
            self.proc = subprocess.Popen(
                [sys.executable, "-c", _ENTRY, str(w)], stdin=subprocess.PIPE,
                stdout=2, pass_fds=(w,), env=env, start_new_session=True)
        except BaseException:
            os.close(r)
            raise
        finally:
            os.close(w)
        self._rx = os.fdopen(r, "rb")
        self._send(json.dumps({"spec": self.spec, "options": self.options, "jax": settings,
                               "nice": self.nice}))

    def open(self) -> None:
        """Launch the worker if needed and wait until its source is open and warmed up (which
        includes rendering the synthetic head's frames on their first use).

        Raises:
            SourceError: the worker could not open the source (its one-line reason) or ended.
        """
        self.launch()
        rec = self._receive()
        if rec is None:
            raise SourceError(f"{self.name}: {self._death()}")
        if rec[0] == "error":
            raise SourceError(rec[1])
        if rec[0] != "ready":
            raise SourceError(f"{self.name}: unexpected message from the worker: {rec!r}")
        now = time.perf_counter()
        if not self._launched_at <= rec[1] <= now:
            raise SourceError(f"{self.name}: the worker's clock differs from this process's "
                              f"(worker {rec[1]:.3f} s, here {self._launched_at:.3f}-{now:.3f}"
                              " s); use open_source(..., worker=False)")
        self.rate = rec[2]
        self.name = rec[3]
        self._ready = True

    def run(self, clock, t0, stop, emit) -> None:
        if clock.virtual:
            raise SourceError(f"{self.name}: a worker source runs in real time; use "
                              "open_source(..., worker=False) with a VirtualClock")
        if not self._ready:
            raise SourceError(f"{self.name}: run() before open()")
        self._send(f"run {float(t0)!r}")
        done = threading.Event()

        def forward_stop():  # stop (set by the runner, e.g. from a signal handler) -> worker
            while not done.is_set():
                if stop.wait(0.05):
                    self._send("stop")
                    return

        watcher = threading.Thread(target=forward_stop, name="phjax-live-worker-stop",
                                   daemon=True)
        watcher.start()
        try:
            while True:
                rec = self._receive()
                if rec is None:
                    if stop.is_set():
                        return
                    raise SourceError(f"{self.name}: {self._death()}")
                kind = rec[0]
                if kind == "m":
                    _, t, p, q, status, conf, dropped, work = rec
                    emit(Measurement(t, np.asarray(p, np.float64), np.asarray(q, np.float64),
                                     status, conf, dropped, work))
                elif kind == "end":
                    return
                elif kind == "error":
                    raise SourceError(rec[1])
        finally:
            done.set()
            watcher.join()

    def close(self) -> None:
        """Stop the worker: ask, wait up to 3 s, then terminate (and kill) it; no orphan."""
        proc, self.proc = self.proc, None
        if proc is not None:
            self._send("stop", proc)
            try:
                proc.stdin.close()
            except OSError:
                pass
            try:
                proc.wait(_STOP_WAIT)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(2.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if self._rx is not None:
            self._rx.close()
            self._rx = None
        self._ready = False

    @property
    def pid(self) -> int | None:
        """The worker's process id (``None`` before :meth:`launch` and after :meth:`close`)."""
        return None if self.proc is None else self.proc.pid

    def _send(self, line: str, proc=None) -> None:
        proc = proc or self.proc
        if proc is None or proc.stdin is None or proc.stdin.closed:
            return
        with self._stdin_lock:
            try:
                proc.stdin.write(line.encode() + b"\n")
                proc.stdin.flush()
            except (OSError, ValueError):  # the worker is gone: reported by the reader
                pass

    def _receive(self):
        """The next record, or ``None`` at the end of the pipe (the worker has exited)."""
        rx = self._rx
        if rx is None:
            return None
        try:
            line = rx.readline()  # blocks without holding the GIL
        except (OSError, ValueError):
            return None
        if not line:
            return None
        return json.loads(line)

    def _death(self) -> str:
        proc = self.proc
        code = None
        if proc is not None:
            try:
                code = proc.wait(2.0)
            except subprocess.TimeoutExpired:
                pass
        how = f"exit code {code}" if code is not None and code >= 0 else (
            f"signal {-code}" if code is not None else "still running")
        return f"the front-end worker ended without a reply ({how})"


# ------------------------------------------------------------------------------ worker side
def _main(fd: int) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us
    out = os.fdopen(fd, "w", buffering=1)
    lock = threading.Lock()
    stop = threading.Event()
    go = threading.Event()
    start = {}

    def send(rec) -> None:
        with lock:
            try:
                out.write(json.dumps(rec) + "\n")
            except (OSError, ValueError):  # the parent is gone
                stop.set()
                raise SystemExit(0) from None

    cfg = json.loads(sys.stdin.readline() or "null")
    if cfg is None:
        return 0

    def read_commands():
        for line in sys.stdin:
            cmd = line.split()
            if cmd and cmd[0] == "run":
                start["t0"] = float(cmd[1])
                go.set()
            elif cmd and cmd[0] == "stop":
                break
        # "stop", or the end of stdin: the parent closed it or is gone
        stop.set()
        go.set()
        if "t0" not in start:  # still opening (e.g. rendering frames): nothing to finish
            os._exit(0)

    threading.Thread(target=read_commands, name="phjax-worker-commands", daemon=True).start()
    if cfg.get("nice") and hasattr(os, "nice"):
        try:
            os.nice(int(cfg["nice"]))
        except OSError:
            pass
    source = None
    try:
        import jax

        for name, value in cfg["jax"].items():
            if value is not None:
                jax.config.update(name, value)
        from ._clock import RealClock
        from ._sources import open_source

        source = open_source(cfg["spec"], worker=False, **cfg["options"])
        source.open()
        clock = RealClock()
        send(["ready", clock.now(), source.rate, source.name])
        go.wait()
        if stop.is_set():
            return 0

        def emit(m: Measurement) -> None:
            send(["m", float(m.t), np.asarray(m.position, float).tolist(),
                  np.asarray(m.quaternion, float).tolist(), str(m.status),
                  float(m.confidence), int(m.dropped), float(m.work)])

        source.run(clock, start["t0"], stop, emit)
        send(["end"])
        return 0
    except SystemExit:
        raise
    except BaseException as e:  # noqa: BLE001 - reported to the parent in one line
        # a user error (bad file, bad option: ValueError, OSError) reads as in the command
        # line's own process; anything else names its type and place
        msg = str(e) if isinstance(e, (ValueError, OSError)) else _one_line(e)
        send(["error", msg.strip().splitlines()[0] if msg.strip() else type(e).__name__])
        return 1
    finally:
        if source is not None:
            with contextlib.suppress(Exception):  # after an error, the first one counts
                source.close()
