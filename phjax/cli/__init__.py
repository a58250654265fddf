"""The command line, ``phjax <command>`` (or ``python -m phjax <command>``); see ``phjax --help``."""

from ._main import build_parser, main

__all__ = ["build_parser", "main"]
