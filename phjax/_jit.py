"""How phjax compiles: ``jax.jit`` with XLA options chosen for compile time (one place).

phjax's programs are many small element-wise operations on 3- and 4-vectors (quaternions, 3 x 3
covariances), so XLA:CPU spends most of a compilation generating and optimising one machine
kernel per fusion (about 460 of them in one tracker update). XLA:CPU's newer MLIR "fusion
emitters" take about 1.7 x as long per kernel as the classic LLVM IR emitters for these
programs, with no faster code: the tracker update compiled in 14 s of CPU time instead of 24 s
with the same latency, and large ``hermite_quintic`` batches ran 1.5 x faster
(``benchmarks/bench_startup.py``, ``benchmarks/README.md``). :func:`jit` is ``jax.jit`` with
those emitters turned off for the program it compiles; nothing global changes (other programs in
the process, ``XLA_FLAGS``). Other backends reject the CPU option, so there it is plain
``jax.jit`` (on an H200 every jitted entry point failed with "No such compile option" before).
The synthetic head's renderer, one large image program, is the exception: it adds
:data:`IMAGE_COMPILER_OPTIONS` (``jit(options=...)``), with which it runs 1.9 x faster.

:class:`Tiered` serves real-time callers (:class:`phjax.TrackerStream`): its first call compiles
the program at XLA's ``-O0`` (about 40 % less compile time, calls about 20 % slower) and
compiles the optimised program in a background thread, which the calls use once it is ready.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

import equinox as eqx
import jax

try:  # JAX's own test for "not inside a trace" (private; a public fallback below)
    from jax._src.core import trace_state_clean as _top_level
except ImportError:  # pragma: no cover - depends on the JAX version
    def _top_level() -> bool:
        return not isinstance(jax.numpy.zeros(()), jax.core.Tracer)

try:  # the persistent cache's write threshold, settable per thread (private)
    from jax._src.config import persistent_cache_min_compile_time_secs as _min_cache_time
except ImportError:  # pragma: no cover - depends on the JAX version
    _min_cache_time = None


def _no_cache_writes():
    """A block in which this thread's compilations read JAX's persistent compilation cache
    but never write it (the threshold of compile time for a write is infinite in this thread
    only; other threads keep theirs). Without the private setting: no change."""
    if _min_cache_time is None:  # pragma: no cover - depends on the JAX version
        return contextlib.nullcontext()
    return _min_cache_time(float("inf"))

__all__ = ["COMPILER_OPTIONS", "FAST_COMPILER_OPTIONS", "IMAGE_COMPILER_OPTIONS", "Tiered",
           "extra_compiler_options", "filter_jit", "jit"]

#: XLA options of every program phjax compiles (see the module docs)
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
#: the options of :class:`Tiered`'s first program: LLVM's optimisation off
FAST_COMPILER_OPTIONS = {**COMPILER_OPTIONS, "xla_backend_optimization_level": 0}
#: the options of image-sized programs (the synthetic head's renderer), added over the others:
#: XLA's fusion emitters and full optimisation. A frame's program is a few large element-wise
#: fusions over hundreds of thousands of pixels, where the fusion emitters' code runs 1.9 x
#: faster (a 640x480 frame: 0.24 instead of 0.46 s of CPU time, compiled in the same time); at
#: ``-O0`` (the test suite's level, see ``tests/conftest.py``) it took 1.3 s. Fixed here, so a
#: rendered frame is the same program whatever the process's ``XLA_FLAGS``.
IMAGE_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": True,
                          "xla_backend_optimization_level": 3}


#: XLA:CPU options added to :data:`COMPILER_OPTIONS` while :func:`extra_compiler_options` is
#: active (one dict for the process: the threads a block starts compile with them too)
_EXTRA_OPTIONS: dict = {}


@contextlib.contextmanager
def extra_compiler_options(**options):
    """Programs that :func:`jit` compiles inside the block add ``options`` to
    :data:`COMPILER_OPTIONS` (CPU backend; each set of options is its own jitted function, so
    nothing compiled outside the block is reused or replaced). For the test suite, which
    compiles at XLA's ``-O0`` and runs its few run-time-heavy tests with
    ``xla_backend_optimization_level=3`` (XLA's default, as users run). Not thread-safe
    against a second block; nested blocks restore the outer options."""
    previous = dict(_EXTRA_OPTIONS)
    _EXTRA_OPTIONS.update(options)
    try:
        yield
    finally:
        _EXTRA_OPTIONS.clear()
        _EXTRA_OPTIONS.update(previous)


class _Jitted:
    """A function jitted twice: with :data:`COMPILER_OPTIONS` when called at top level (it is
    then the program XLA compiles), plainly inside another trace (JAX accepts compiler options
    only on the outermost ``jit``; the outer program's options apply). The options are XLA:CPU
    options, which other backends reject: on a GPU or TPU default backend the top-level version
    is plain ``jax.jit`` too (decided at the first call, so importing phjax does not start a
    backend). Attributes such as ``lower``, ``trace``, ``clear_cache`` are the top-level
    version's. ``options`` are the function's own, added over the others."""

    def __init__(self, fun, kwargs, options=None):
        self._fun, self._kwargs, self._options = fun, kwargs, dict(options or {})
        self._nested = jax.jit(fun, **kwargs)
        self._top_jits = {}  # by the extra options in effect (see extra_compiler_options)
        functools.update_wrapper(self, fun)

    @property
    def _top(self):
        key = tuple(sorted(_EXTRA_OPTIONS.items())) if _EXTRA_OPTIONS else ()
        top = self._top_jits.get(key)
        if top is None:
            options = ({**COMPILER_OPTIONS, **_EXTRA_OPTIONS, **self._options}
                       if jax.default_backend() == "cpu" else None)
            top = self._top_jits[key] = (
                jax.jit(self._fun, compiler_options=options, **self._kwargs)
                if options else self._nested)
        return top

    def __call__(self, *args, **kwargs):
        return (self._top if _top_level() else self._nested)(*args, **kwargs)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._top, name)

    def clear_cache(self) -> None:
        for top in self._top_jits.values():
            top.clear_cache()
        self._nested.clear_cache()


def jit(fun=None, /, *, options: dict | None = None, **kwargs):
    """``jax.jit(fun, **kwargs)`` compiled with :data:`COMPILER_OPTIONS`; usable as a
    decorator, bare or through ``functools.partial(jit, static_argnames=...)``.

    Arguments:
        options: XLA:CPU options of this function's program, added over
            :data:`COMPILER_OPTIONS` and :func:`extra_compiler_options` (e.g.
            :data:`IMAGE_COMPILER_OPTIONS`).
    """
    if fun is None:
        return functools.partial(jit, options=options, **kwargs)
    return _Jitted(fun, kwargs, options)


def filter_jit(fun):
    """``eqx.filter_jit(fun)`` compiled with :data:`COMPILER_OPTIONS`: array leaves of the
    arguments are traced, every other leaf (Python scalars, strings, functions, static Module
    fields) is static and must be hashable. Use it for functions that take Modules (problems,
    solvers, curves): ``eqx.filter_jit`` itself takes no compiler options, and the programs
    it compiles for the tuner (the differentiated stream) are phjax's largest."""

    def run(static, treedef, dynamic):
        leaves = [d if s is _DYNAMIC else s for s, d in zip(static, _fill(static, dynamic))]
        args, kwargs = jax.tree.unflatten(treedef, leaves)
        return fun(*args, **kwargs)

    jitted = jit(run, static_argnums=(0, 1))

    @functools.wraps(fun)
    def wrapper(*args, **kwargs):
        leaves, treedef = jax.tree.flatten((args, kwargs))
        static = tuple(_DYNAMIC if eqx.is_array(x) else x for x in leaves)
        dynamic = [x for x in leaves if eqx.is_array(x)]
        return jitted(static, treedef, dynamic)

    return wrapper


class _Dynamic:
    """Placeholder of a traced leaf in :func:`filter_jit`'s static part."""

    def __repr__(self) -> str:
        return "<dynamic>"


_DYNAMIC = _Dynamic()


def _fill(static, dynamic):
    """``dynamic``'s leaves at the ``_DYNAMIC`` positions of ``static``, ``None`` elsewhere."""
    it = iter(dynamic)
    return [next(it) if s is _DYNAMIC else None for s in static]


def _tiering_pays() -> bool:
    """Whether :class:`Tiered` compiles twice: on a CPU backend, unless ``XLA_FLAGS`` already
    compiles everything at ``-O0`` (the test suite): the second program would be the same."""
    flags = os.environ.get("XLA_FLAGS", "")
    return (jax.default_backend() == "cpu"
            and "xla_backend_optimization_level=0" not in flags.replace("--", ""))


class Tiered:
    """A jitted function for a real-time caller that calls it with one input signature:
    quick to the first result, fully optimised soon after.

    The first call traces and lowers the program once, compiles it with
    :data:`FAST_COMPILER_OPTIONS` (XLA:CPU at ``-O0``: the tracker update compiles in about
    60 % of the time and runs about 20 % slower) and starts a thread that compiles the same
    lowered program with :data:`COMPILER_OPTIONS`; later calls use whichever program is newest.
    The background compilation runs in XLA without Python's lock (measured: a Python loop in
    the calling thread kept running with p99 gaps of 0.04 ms) and reads JAX's persistent
    compilation cache but does not write it (serialising the program for the cache holds the
    lock for 130-200 ms, a stall of a live render loop), and a process that exits before it
    ends waits for it. Calls with another input signature (other dtypes or shapes) take
    the plain jitted path, which also reports bad inputs. On other backends, or when
    ``XLA_FLAGS`` already compiles at ``-O0``, it is the plain jitted function.

    Arguments:
        jitted: the function, jitted with :func:`jit`.
    """

    def __init__(self, jitted):
        self._jitted = jitted
        self._program = None
        self._thread = None
        self._lock = threading.Lock()
        #: the exception of the background compilation, if it failed (the fast program stays)
        self.error: BaseException | None = None

    @property
    def optimized(self) -> bool:
        """Whether calls run the fully optimised program (or plain jit, not tiered)."""
        return self._program is not None and (self._thread is None or not self._thread.is_alive())

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the background compilation (if any); returns :attr:`optimized`."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.optimized

    def __call__(self, *args):
        if self._program is None:
            with self._lock:  # two threads calling first compile once
                if self._program is None:
                    self._start(args)
        program = self._program
        if program is self._jitted:
            return program(*args)
        try:
            return program(*args)
        except TypeError:  # not the signature it was compiled for: the general path
            return self._jitted(*args)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._jitted, name)

    def _start(self, args) -> None:
        """Compile the fast program (set before the thread starts, so the optimised one,
        set by the thread, is never overwritten) and start the background compilation."""
        if not _tiering_pays():
            self._program = self._jitted
            return
        lowered = self._jitted.trace(*args).lower()
        self._program = lowered.compile(FAST_COMPILER_OPTIONS)

        def optimise():
            try:
                # Writing the program to JAX's persistent compilation cache serialises it
                # while holding Python's lock: 130-200 ms for the tracker update, and
                # phjax live's render loop sent nothing for 150-390 ms (18-47 periods at
                # 120 Hz) on a first run with an empty cache. So the optimised program is
                # compiled here on every run (the tracker update: 3-4 s of one core, while
                # the fast one serves); the cache is still read.
                with _no_cache_writes():
                    self._program = lowered.compile(COMPILER_OPTIONS)
            # pragma: no cover - XLA failing on a program it compiled; the fast one runs on
            except Exception as e:  # noqa: BLE001
                self.error = e

        self._thread = threading.Thread(target=optimise, name=COMPILE_THREAD)
        self._thread.start()


#: the name of :class:`Tiered`'s background compilation threads
COMPILE_THREAD = "phjax-compile"


def background_compilations() -> list[threading.Thread]:
    """:class:`Tiered`'s background compilations still running (a process that exits waits
    for them: they run in XLA, which must not be torn down under them)."""
    return [th for th in threading.enumerate() if th.name == COMPILE_THREAD and th.is_alive()]
