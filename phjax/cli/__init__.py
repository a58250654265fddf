"""The command line, ``phjax <command>`` (or ``python -m phjax <command>``); see ``phjax --help``."""

from __future__ import annotations

import signal
import sys

from ._signals import cancel_deferred_interrupts, hold_sigint

__all__ = ["build_parser", "main"]


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``phjax`` command; returns the exit status (see
    :func:`phjax.cli._main.main`). Ctrl-C is one line from the first moment: the safe handler
    is installed before the command's own imports (NumPy and the parser: a tenth of a second,
    where a Ctrl-C printed Python's traceback)."""
    previous = hold_sigint()
    try:
        from ._main import main as run

        return run(argv)
    except KeyboardInterrupt:  # deferred through the imports, raised before run's own handling
        print("\nphjax: interrupted", file=sys.stderr)
        return 130
    finally:
        cancel_deferred_interrupts()
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def __getattr__(name: str):
    if name == "build_parser":  # imported on first use, as the command's modules are
        from ._main import build_parser

        return build_parser
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
