"""Whole-recording programs stored as exported StableHLO, so a later process skips the tracing.

JAX's persistent compilation cache stores compiled executables, but its key is a hash of the
*lowered* program: a new process still traces ``track``'s scan in Python and lowers it (about
1.3 s of a warm ``phjax smooth``, more than the run) before it can look the executable up.
Inside :func:`exported_programs` the whole-recording entry points (:func:`phjax.track`,
:func:`phjax.reconstruct`, through ``tracker._run_recording``) also store the program they
trace with :mod:`jax.export` in a folder and later load it from there: a deserialised program
is lowered without running phjax's Python code, and its compiled executable then comes from the
persistent cache.

A stored program is used only for exactly what produced it: the file name is a digest of
phjax's source files, the JAX and jaxlib versions, the backend, the compile options, the entry
point, the config's structure (its static fields included) and the shapes and dtypes of every
input. Anything else (a changed source file, another config structure or size class) traces
anew and stores another file. Calls whose config holds tracers (``jax.grad`` through
``track``) take the normal path. The command line turns this on with its compilation cache
(``phjax.cli._cache.compilation_cache``); nothing else does.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import jax
import jax.numpy as jnp

from .._jit import COMPILER_OPTIONS, jit
from .._misc import any_traced
from ._shapes import MAX_COMPILED_SHAPES

__all__ = ["call", "exported_programs"]

_STATE: dict = {"folder": None}
#: deserialised (or exported) programs of this process, newest last; bounded like
#: :func:`phjax.tracking._shapes.bounded_cache` (each holds a compiled executable)
_LOADED: collections.OrderedDict = collections.OrderedDict()


@contextlib.contextmanager
def exported_programs(folder: str | os.PathLike) -> Iterator[Path]:
    """Store and load the whole-recording programs in ``folder`` inside the ``with`` block.

    Arguments:
        folder: where the exported programs are kept (created on the first write).

    Yields:
        The folder as a :class:`~pathlib.Path`.
    """
    previous = _STATE["folder"]
    _STATE["folder"] = Path(folder)
    try:
        yield _STATE["folder"]
    finally:
        _STATE["folder"] = previous
        _LOADED.clear()


@functools.cache
def _source_digest() -> str:
    """A digest of every Python source file of the phjax package (computed once)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _key(name: str, treedef, leaves, args) -> str:
    import jaxlib

    h = hashlib.sha256()
    for part in (_source_digest(), jax.__version__, jaxlib.__version__, jax.default_backend(),
                 repr(sorted(COMPILER_OPTIONS.items())), name, repr(treedef),
                 repr([(jnp.shape(x), jnp.result_type(x).name) for x in [*leaves, *args]])):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:32]


def _write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (a whole file or none, also across processes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def call(core, config, args):
    """``core(config, *args)`` through a stored program, or ``None`` when not enabled here.

    Arguments:
        core: a jitted whole-recording core (``tracker._track_core`` / ``_reconstruct_core``).
        config: its config (a PyTree whose float leaves take the dtype of ``args``).
        args: its array arguments.

    Returns:
        ``core``'s outputs, or ``None`` outside :func:`exported_programs` or when the config
        holds tracers (then call ``core`` itself).
    """
    folder = _STATE["folder"]
    if folder is None:
        return None
    dtype = jnp.result_type(args[0])
    if any_traced(config):
        return None
    leaves, treedef = jax.tree.flatten(config)
    # Python floats become arrays of the recording's dtype: the values the traced core sees
    leaves = [jnp.asarray(x, dtype) if isinstance(x, float) else jnp.asarray(x) for x in leaves]
    fun = core.__wrapped__
    key = _key(fun.__name__, treedef, leaves, args)
    program = _LOADED.get(key)
    if program is None:
        path = folder / f"{fun.__name__}-{key}.jaxexport"
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except FileNotFoundError:
            exported = None
        except Exception:  # noqa: BLE001 - a damaged or foreign file (flatbuffers raises
            exported = None  # struct.error and others): a cache never fails the computation
        if exported is None:  # not stored yet (or unreadable): trace, store
            on_leaves = jax.jit(lambda ls, *a: fun(jax.tree.unflatten(treedef, ls), *a))
            exported = jax.export.export(on_leaves)(leaves, *args)
            # a cache never fails the computation: an unwritable folder, or no flatbuffers
            # (jax.export's serialiser) in this environment, only means no stored program
            with contextlib.suppress(OSError, ImportError):
                _write(path, exported.serialize())
        program = jit(exported.call)
        _LOADED[key] = program
        while len(_LOADED) > MAX_COMPILED_SHAPES:
            _LOADED.popitem(last=False)
    else:
        _LOADED.move_to_end(key)
    return program(leaves, *args)
