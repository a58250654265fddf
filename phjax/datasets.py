"""Locating the shared third-party recordings (``../shared/data`` beside the repository).

The data are never copied into the repository. Search order: the ``PHJAX_SHARED_DATA``
environment variable, then ``shared/data`` beside (or above) the current directory and the
installed package.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data_dir"]


def shared_data_dir() -> Path | None:
    """The shared data folder, or ``None`` if it cannot be found."""
    env = os.environ.get("PHJAX_SHARED_DATA")
    if env:
        p = Path(env)
        return p if p.is_dir() else None
    starts = [Path.cwd(), Path(__file__).resolve().parent]
    for start in starts:
        for base in [start, *start.parents]:
            cand = base / "shared" / "data"
            if cand.is_dir():
                return cand
            cand = base.parent / "shared" / "data"
            if cand.is_dir():
                return cand
    return None
