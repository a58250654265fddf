"""Ctrl-C while a command starts: never raised where it would crash the process or be lost."""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time

import pytest

from phjax.cli import _signals

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGUSR2"), reason="needs POSIX signals")


@pytest.fixture
def usr2_count():
    """SIGUSR2 counted (the stand-in for Ctrl-C, so that nothing here raises in pytest)."""
    got = []
    previous = signal.signal(signal.SIGUSR2, lambda s, f: got.append(time.monotonic()))
    yield got
    _signals.cancel_deferred_interrupts()
    signal.signal(signal.SIGUSR2, previous)


def _wait_for(got, n, timeout=2.0):
    end = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        time.sleep(0.005)  # the handler runs between these bytecodes


def test_an_interrupt_inside_an_import_is_sent_again_after_it(tmp_path, monkeypatch, usr2_count):
    """Inside an import (here a module's own code; in the CLI, jaxlib's initialisation, where
    a KeyboardInterrupt crashed the process with SIGSEGV) the handler must not raise: the
    signal is deferred and comes again 20 ms later; outside an import it is not deferred."""
    (tmp_path / "phjax_probe_mod.py").write_text(
        "import signal, sys\n"
        "from phjax.cli._signals import defer_interrupt\n"
        "DEFERRED = defer_interrupt(signal.SIGUSR2, sys._getframe())\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    t0 = time.monotonic()
    import phjax_probe_mod

    assert phjax_probe_mod.DEFERRED
    _wait_for(usr2_count, 1)
    assert len(usr2_count) == 1 and 0.015 <= usr2_count[0] - t0 < 1.0
    sys.modules.pop("phjax_probe_mod")
    assert not _signals.defer_interrupt(signal.SIGUSR2, sys._getframe())
    time.sleep(0.1)
    assert len(usr2_count) == 1


def test_an_interrupt_inside_a_gc_callback_is_sent_again_after_it(usr2_count):
    """Raised inside a garbage-collector callback (XLA registers one), Python printed and
    dropped the KeyboardInterrupt, and the command ran on (seen in CI: ``phjax live`` sent
    its poses after a Ctrl-C in its first half second)."""
    seen = []

    def callback(phase, info):
        if phase == "start" and not seen:
            seen.append(_signals.defer_interrupt(signal.SIGUSR2, sys._getframe()))

    gc.callbacks.append(callback)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(callback)
    assert seen == [True]
    _wait_for(usr2_count, 1)
    assert len(usr2_count) == 1


def test_main_restores_the_handler_and_cancels_what_is_pending(usr2_count, monkeypatch):
    """``phjax.cli.main`` installs the safe Ctrl-C handler for the command only (then the
    caller's is back) and cancels a deferred signal still pending when the command has
    ended."""
    import phjax.cli._main as cli_main

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are the main thread's")
    before = signal.getsignal(signal.SIGINT)
    inside, timers = [], []

    def command(argv, usr1):
        inside.append(signal.getsignal(signal.SIGINT))
        timers.append(threading.Timer(10.0, lambda: None))
        _signals._DEFERRED.append(timers[0])
        timers[0].start()
        return 0

    monkeypatch.setattr(cli_main, "_run", command)
    from phjax.cli import main  # the entry point: the handler before the command's imports

    assert main([]) == 0
    assert inside == [_signals.on_interrupt if before is signal.default_int_handler else before]
    assert signal.getsignal(signal.SIGINT) is before
    assert not _signals._DEFERRED and timers[0].finished.is_set()  # cancelled


def test_an_interrupt_in_jax_code_is_sent_again_after_it(usr2_count):
    """In JAX's own code (a compilation checks for signals while it runs) the handler must
    not raise: a KeyboardInterrupt there stopped an XLA compilation half-way, and the process
    crashed as it exited (SIGSEGV after ``phjax smooth: interrupted``, 3-4 s into the
    command, with an empty compilation cache)."""
    import jax

    frames = []
    jax.tree_util.tree_map(lambda x: frames.append(sys._getframe(1)), [0])
    assert "jax" in frames[0].f_code.co_filename  # a frame of jax's tree_util
    assert _signals.defer_interrupt(signal.SIGUSR2, frames[0])
    _wait_for(usr2_count, 1)
    assert len(usr2_count) == 1
