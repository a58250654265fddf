"""Signals of the ``phjax`` command: Ctrl-C (``KeyboardInterrupt``, raised only where that is
safe), SIGUSR1 held until ``phjax live`` takes it, and Ctrl-C / SIGTERM held while a
background compilation finishes.

Light on purpose (no NumPy, no JAX at import): the command installs its handlers before
importing anything else.
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading

__all__ = [
    "cancel_deferred_interrupts",
    "defer_interrupt",
    "finish_background_compilations",
    "hold_sigint",
    "hold_signals",
    "hold_usr1",
    "on_interrupt",
]


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


def hold_usr1():
    """Ignore SIGUSR1 while the command starts; returns the previous handler (or None).

    ``phjax live`` re-centres on SIGUSR1 once its own handler is installed; before that the
    signal's default action killed the process (status 138) when a script sent it early."""
    if not hasattr(signal, "SIGUSR1") or threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    return signal.SIG_DFL if previous is None else previous  # None: set outside Python


def _holder(prog: str):
    """A SIGINT / SIGTERM handler that does nothing but say, once, that a background
    compilation is being finished (when one runs)."""
    said = False

    def hold(signum, frame):
        nonlocal said
        from .._jit import background_compilations

        if not said and background_compilations():
            print(f"{prog}: finishing a background compilation, a few seconds",
                  file=sys.stderr, flush=True)
            said = True

    hold.holds = True  # marks a holder: finish_background_compilations keeps it (says once)
    return hold


def hold_signals(prog: str) -> None:
    """Hold Ctrl-C and SIGTERM off (:func:`_holder`) in the main thread, until the caller
    restores its handlers: for the end of a command whose optimised program may still be
    compiling in the background (see :func:`finish_background_compilations`)."""
    if threading.current_thread() is threading.main_thread():
        handler = _holder(prog)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, handler)


def finish_background_compilations(prog: str) -> None:
    """Wait for phjax's background compilations (:class:`phjax._jit.Tiered`: a few seconds of
    one core after an early stop) with Ctrl-C and SIGTERM held off, then restore the
    handlers found. The interpreter waits for them at exit in any case, and a Ctrl-C that
    interrupts that wait aborts the process from inside XLA (``terminate called``); a signal
    here says what is happening, once."""
    from .._jit import background_compilations

    threads = background_compilations()
    if not threads or threading.current_thread() is not threading.main_thread():
        return
    found = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    if not getattr(found[signal.SIGINT], "holds", False):  # already held: say it once
        hold_signals(prog)
    try:
        for th in threads:
            th.join()
    finally:
        for sig, handler in found.items():
            signal.signal(sig, handler)
