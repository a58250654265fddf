"""The command line, ``phjax <command>`` (or ``python -m phjax <command>``); see ``phjax --help``."""

from __future__ import annotations

import signal
import sys

from ._signals import cancel_deferred_interrupts, hold_sigint, hold_usr1

__all__ = ["build_parser", "main"]


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``phjax`` command; returns the exit status.

    JAX's persistent compilation cache is on while the command runs (see :mod:`._cache`).
    The one place where user errors become messages: a usage error (argparse) or any
    ``ValueError`` (including :class:`phjax.io.TrajectoryFormatError`) or ``OSError`` (missing
    file, folder, permissions) raised by a command prints ONE line
    ``phjax <command>: error: ...`` on stderr and returns 2; no traceback. Ctrl-C is one
    line from the first moment (``phjax: interrupted``, 130): the handler of
    :mod:`._signals` is installed before the command's own imports (NumPy, the parser, JAX),
    and SIGUSR1 is ignored until ``phjax live`` takes it.
    """
    sigint = hold_sigint()
    usr1 = hold_usr1()
    try:
        from ._main import _run

        return _run(argv, usr1)
    except KeyboardInterrupt:
        print("\nphjax: interrupted", file=sys.stderr)
        return 130
    finally:
        cancel_deferred_interrupts()
        if usr1 is not None:
            signal.signal(signal.SIGUSR1, usr1)
        if sigint is not None:
            signal.signal(signal.SIGINT, sigint)


def __getattr__(name: str):
    if name == "build_parser":  # imported on first use, as the command's modules are
        from ._main import build_parser

        return build_parser
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
