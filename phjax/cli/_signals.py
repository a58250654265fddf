"""Ctrl-C for the ``phjax`` command: ``KeyboardInterrupt``, raised only where that is safe.

Light on purpose (no NumPy, no JAX): the command installs it before importing anything else.
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading

__all__ = ["cancel_deferred_interrupts", "defer_interrupt", "hold_sigint", "on_interrupt"]


def _in_gc_callback(frame) -> bool:
    """Whether ``frame`` runs inside a garbage-collector callback (XLA registers one)."""
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


def _in_import(frame) -> bool:
    """Whether ``frame`` runs inside an ``import`` (a module's code, or a C extension's
    initialisation calling back into Python)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _in_jax(frame) -> bool:
    """Whether the code running at ``frame`` is JAX's: JAX's own frame, or the standard
    library called by it (the backend's start reads the installed packages' metadata). A
    compilation checks for signals while it runs; a function of phjax's being traced is not
    JAX's code (an exception there unwinds the trace as any error does)."""
    stdlib = os.path.dirname(os.__file__) + os.sep  # (os.py: the standard library's folder)

    def standard(filename: str) -> bool:
        return filename.startswith("<") or (filename.startswith(stdlib) and not any(
            part in filename for part in ("site-packages", "dist-packages")))

    while frame is not None and standard(frame.f_code.co_filename):
        frame = frame.f_back
    if frame is None:
        return False
    for name in ("jax", "jaxlib"):
        folder = os.path.dirname(getattr(sys.modules.get(name), "__file__", None) or "")
        if folder and frame.f_code.co_filename.startswith(folder + os.sep):
            return True
    return False


def defer_interrupt(signum: int, frame) -> bool:
    """For a signal handler about to raise (Ctrl-C): whether the exception must wait, and if
    so, the signal is sent again 20 ms later (until the handler may raise).

    Raised inside an import, the exception crashed the process when it interrupted a C
    extension's initialisation half-way (``jaxlib``: SIGSEGV, status -11); raised inside a
    garbage-collector callback, Python printed and dropped it (the command ran on as if no
    Ctrl-C had come); raised in JAX's code, it could stop an XLA compilation half-way, and
    the process crashed as it exited (SIGSEGV after ``phjax smooth: interrupted``), or stop
    the backend's start half-way, and the process waited a minute for its watchdog thread
    before it exited. A running XLA program is not interrupted either way: Python handles the
    signal after it."""
    if not (_in_import(frame) or _in_gc_callback(frame) or _in_jax(frame)):
        return False
    again = threading.Timer(0.02, os.kill, (os.getpid(), signum))
    again.daemon = True
    _DEFERRED[:] = [t for t in _DEFERRED if not t.finished.is_set()] + [again]
    again.start()
    return True


#: signals :func:`defer_interrupt` is to send again (``phjax.cli.main`` cancels those left
#: when the command has ended: the Ctrl-C came as it finished)
_DEFERRED: list[threading.Timer] = []


def cancel_deferred_interrupts() -> None:
    """Cancel the signals :func:`defer_interrupt` has yet to send again."""
    while _DEFERRED:
        _DEFERRED.pop().cancel()


def on_interrupt(signum, frame):
    """The command's SIGINT handler until one of its own takes over: Python's
    ``KeyboardInterrupt``, raised where that is safe (:func:`defer_interrupt`)."""
    if not defer_interrupt(signum, frame):
        raise KeyboardInterrupt


def hold_sigint():
    """Ctrl-C raises ``KeyboardInterrupt`` only where that is safe (:func:`on_interrupt`: not
    inside an import, a gc callback or JAX's code, where it crashed the process or was
    dropped); returns the previous handler (or None: not the main thread, or a SIGINT ignored
    or handled by the caller, which keeps it)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.default_int_handler:  # ignored (nohup, '&'), or a caller's own
        return None
    signal.signal(signal.SIGINT, on_interrupt)
    return previous
