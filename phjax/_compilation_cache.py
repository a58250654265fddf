"""JAX's persistent compilation cache for phjax's users: one call, never at import.

A compiled program is written to a folder and loaded, instead of compiled, by every later
process that needs the same program (same shapes, dtype, config structure, JAX version): a
script or notebook that tracks recordings pays the compilation once per machine, not once per
run. The ``phjax`` command turns the cache on by itself (:mod:`phjax.cli._cache`); library
users call :func:`enable_compilation_cache` at the top of their program.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["MIN_COMPILE_SECONDS", "cache_dir", "enable_compilation_cache"]

#: programs that took less than this to compile are not written to the cache (JAX's default,
#: 1 s, would leave out most of the tracker's and the evaluation's programs)
MIN_COMPILE_SECONDS = 0.1


def cache_dir() -> Path:
    """The default cache folder: ``$PHJAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/phjax/jax``, else
    ``~/.cache/phjax/jax``."""
    if os.environ.get("PHJAX_CACHE_DIR"):
        return Path(os.environ["PHJAX_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path("~/.cache").expanduser())
    return Path(base) / "phjax" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None, *,
                             min_compile_time: float = MIN_COMPILE_SECONDS) -> Path:
    """Turn on JAX's persistent compilation cache for this process (every program, phjax's or
    not, that takes at least ``min_compile_time`` seconds to compile).

    Arguments:
        path: the cache folder (created on the first write); default :func:`cache_dir`.
        min_compile_time: programs compiled faster than this are not stored, s.

    Returns:
        The folder in use.

    Example::

        import phjax
        phjax.enable_compilation_cache()    # later runs load the tracker instead of compiling
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    folder = Path(path).expanduser() if path is not None else cache_dir()
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time))
    cc.reset_cache()  # a cache that another folder initialised earlier in this process
    return folder
