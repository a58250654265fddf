"""JAX's persistent compilation cache for the ``phjax`` command (never at library import).

The first run of a command compiles its JAX programs (tens of seconds on a laptop CPU); the
compiled executables are stored in a folder under the user's cache and later runs load them
instead of compiling. Folder: ``$PHJAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/phjax/jax``, else
``~/.cache/phjax/jax``. Opt out with ``--no-cache`` or ``PHJAX_NO_COMPILATION_CACHE=1``. The
programs of :func:`phjax.track` / :func:`phjax.reconstruct` are also stored traced, in the
subfolder ``exported`` (:mod:`phjax.tracking._exported`): a later run loads them without
tracing phjax's Python code, which the compilation cache alone cannot skip (its key is the
traced program).

Only :func:`phjax.cli.main` turns the cache on, for the duration of one command, and restores
JAX's previous settings afterwards (so calling ``main`` from Python leaves no global change).
Before the first compilation of a command's first successful run with this JAX version (an
empty marker file ``.phjax-ran-<command>-jax<version>`` in the folder records later ones) one
line on stderr says that compiling takes a while.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from .._compilation_cache import MIN_COMPILE_SECONDS, cache_dir, enable_compilation_cache

__all__ = ["MIN_COMPILE_SECONDS", "CacheSession", "cache_dir", "cache_disabled",
           "compilation_cache"]

_CONFIG = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")


def cache_disabled(no_cache: bool = False) -> bool:
    """Whether the cache is off: ``--no-cache`` or ``PHJAX_NO_COMPILATION_CACHE`` set to
    anything but ``""``, ``0``, ``false``, ``no``, ``off``."""
    env = os.environ.get("PHJAX_NO_COMPILATION_CACHE", "").strip().lower()
    return bool(no_cache) or env not in ("", "0", "false", "no", "off")


class CacheSession:
    """The cache of one command: ``path`` (``None`` when off) and :meth:`mark_ran`."""

    def __init__(self, path: Path | None, marker: Path | None):
        self.path = path
        self._marker = marker

    def mark_ran(self) -> None:
        """Record a successful run of the command (no more first-run note); only when the
        command wrote to the cache folder, which is never created for it."""
        if self._marker is not None and self._marker.parent.is_dir():
            with contextlib.suppress(OSError):
                self._marker.touch()


@contextlib.contextmanager
def compilation_cache(enabled: bool = True, command: str = "phjax",
                      hint: bool = True) -> Iterator[CacheSession]:
    """Turn JAX's persistent compilation cache on for the ``with`` block.

    Arguments:
        enabled: ``False``: change nothing (the session's ``path`` is ``None``).
        command: the command's name, for the first-run note.
        hint: print one line on stderr before the first compilation of a command that has not
            run successfully with this cache folder and JAX version (compiling takes a while).

    Yields:
        A :class:`CacheSession`; the cache folder is created by JAX on the first write.
    """
    if not enabled:
        yield CacheSession(None, None)
        return
    import jax
    import jax.monitoring
    from jax.experimental.compilation_cache import compilation_cache as cc

    path = cache_dir()
    marker = path / f".phjax-ran-{command}-jax{jax.__version__}"
    previous = {name: getattr(jax.config, name) for name in _CONFIG}
    state = {"hinted": not hint or marker.exists()}

    def on_event(event: str, **_):
        if event == "/jax/compilation_cache/compile_requests_use_cache" and not state["hinted"]:
            state["hinted"] = True
            print(f"phjax: compiling (first run of '{command}'; cached in {path}, later runs "
                  "start faster) ...", file=sys.stderr, flush=True)

    from ..tracking._exported import exported_programs

    enable_compilation_cache(path)
    jax.monitoring.register_event_listener(on_event)
    try:
        with exported_programs(path / "exported"):
            yield CacheSession(path, marker)
    finally:
        jax.monitoring.unregister_event_listener(on_event)
        for name, value in previous.items():
            jax.config.update(name, value)
        cc.reset_cache()
