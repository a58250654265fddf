"""Test configuration: float64 everywhere (library code stays dtype-generic), shared data paths."""

from __future__ import annotations

import gc
import os
import shutil
import tempfile
from pathlib import Path

from phjax._jit import COMPILER_OPTIONS  # imports JAX, does not start its backend

# Programs the tests build themselves around library calls (jax.grad of a loss, jax.jit of a
# test function) are compiled with the library's options too: JAX takes compiler options only on
# the outermost jit, and a differentiated stream compiled with XLA:CPU's default emitters took
# 182 s of CPU time instead of 78 s. XLA reads XLA_FLAGS when its backend starts (below, on
# first use); subprocesses inherit it.
os.environ["XLA_FLAGS"] = " ".join(
    [os.environ.get("XLA_FLAGS", ""), *(f"--{k}={str(v).lower()}" for k, v in COMPILER_OPTIONS.items())]
).strip()

#: XLA flag of the parallel pass (see pytest_configure)
TEST_OPT_LEVEL = "--xla_backend_optimization_level=0"


def _pin_xdist_worker() -> None:
    """Give each xdist worker its own share of the CPU cores (before JAX's backend starts).

    XLA:CPU sizes its thread pools from the process's CPU affinity and runs a program's
    independent kernels and dense linear algebra on them. Two workers that each use every core
    oversubscribe the machine, and the runtime's threads then wait on each other's preempted
    peers: measured on 2 cores, the PH-spline real-window and helix tests beside the C2-spline
    smoke test took 221 s of wall time unpinned and 34 s / 25 s pinned one core each (19 s and
    25 s when run alone). Processes a test starts inherit the share. Serial runs (no xdist)
    keep every core.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if not worker.startswith("gw") or count < 2 or not hasattr(os, "sched_setaffinity"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    if count > len(cpus):  # more workers than cores: sharing is unavoidable, leave it to the OS
        return
    share = len(cpus) // count
    index = int(worker[2:]) % count
    os.sched_setaffinity(0, cpus[index * share:(index + 1) * share])
    if share == 1:
        # XLA:CPU splits a program's LLVM module into parts compiled on parallel threads; on a
        # single core that only adds the splitting. Measured on one core at the parallel
        # pass's -O0: track's scan compiled in 2.7-2.9 s instead of 3.9-4.2 s, jax.grad through
        # it 17.8-19.0 s instead of 26.6-27.9 s (with two cores at XLA's default level the
        # split pays: 4.6 s instead of 6.8 s, so users and the serial pass keep it)
        os.environ["XLA_FLAGS"] = " ".join(
            [os.environ.get("XLA_FLAGS", ""), SINGLE_CORE_CODEGEN]).strip()


#: XLA flag of a test worker pinned to one core (see _pin_xdist_worker)
SINGLE_CORE_CODEGEN = "--xla_cpu_parallel_codegen_split_count=1"


_pin_xdist_worker()

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

jax.config.update("jax_enable_x64", True)
# CLI calls in tests do not write JAX's persistent compilation cache into the user's home
# (tests/cli/test_cli_cache.py turns it on, in a temporary folder)
os.environ.setdefault("PHJAX_NO_COMPILATION_CACHE", "1")

settings.register_profile(
    "phjax",
    deadline=None,
    max_examples=int(os.environ.get("PHJAX_HYPOTHESIS_EXAMPLES", "60")),
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
settings.load_profile("phjax")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("PHJAX_SHARED_DATA", REPO.parent / "shared" / "data"))


#: environment switch (set by ``.ci/run``): missing shared data is an error, not a skip
REQUIRE_SHARED_DATA = "PHJAX_REQUIRE_SHARED_DATA"


def shared_data_required() -> bool:
    """Whether ``$PHJAX_REQUIRE_SHARED_DATA`` is set to a true value (anything but ``""``/``0``)."""
    return os.environ.get(REQUIRE_SHARED_DATA, "").strip().lower() not in ("", "0", "false", "no")


def shared_path(*parts: str) -> Path:
    """Path inside ``../shared/data`` (or ``$PHJAX_SHARED_DATA``).

    When it is absent the test is skipped with the reason, or fails (an error in a fixture)
    when ``$PHJAX_REQUIRE_SHARED_DATA=1``: CI sets that, so a missing data set cannot turn the
    real-data tests into silent skips.
    """
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared data not found: {p} (expected ../shared/data beside the repository)"
        if shared_data_required():
            pytest.fail(f"{msg}; {REQUIRE_SHARED_DATA} is set, so this is an error", pytrace=False)
        pytest.skip(msg)
    return p


YUNET_ONNX = "face_detection_yunet_2023mar.onnx"
#: the files of :data:`phjax.vision.face_detection.MODELS` (ONNX for OpenCV, weights for kornia)
YUNET_FILES = (YUNET_ONNX, "yunet_final.pth")


def yunet_models() -> Path:
    """A folder holding the YuNet model files (for tests that need the detector, not the data).

    ``../shared/data/yunet_face_detection`` when present, else the user's model cache
    (``$PHJAX_MODEL_DIR`` or ``~/.cache/phjax/models``) when it holds both model files; otherwise
    the shared folder's rule applies (skip, or error with ``$PHJAX_REQUIRE_SHARED_DATA``).
    The files are checked against their SHA-256 where they are seeded into a test's cache.
    """
    shared = SHARED_DATA / "yunet_face_detection"
    if shared.is_dir():
        return shared
    cache = Path(os.environ.get("PHJAX_MODEL_DIR") or Path.home() / ".cache" / "phjax" / "models")
    if all((cache / name).is_file() for name in YUNET_FILES):
        return cache
    return shared_path("yunet_face_detection")


#: the persistent compilation cache shared by this run's processes (set by the controller)
TEST_CACHE = "PHJAX_TEST_CACHE_DIR"


def pytest_configure(config):
    """One persistent compilation cache for the whole run: the controller (or a run without
    xdist) makes a fresh folder, its xdist workers and every Python process a test starts
    inherit it through the environment, so a program compiled by one process is loaded, not
    compiled, by the others. Fresh per run: no
    result of an earlier run (or of other code) is reused. Removed at the end of the run."""
    if config.getoption("markexpr", "") != SERIAL and TEST_OPT_LEVEL not in os.environ["XLA_FLAGS"]:
        # Most of the suite's time is XLA compiling small programs once. Outside the serial
        # (real-time) pass the machine code is generated without LLVM's optimisations: the
        # same HLO, optimised by XLA as for users, compiles about a third faster and runs
        # slower; results agree to rounding (tests/test_jit.py compares a tracked recording
        # with the default level to 1e-12). Set here, before JAX's backend starts; the
        # processes tests start inherit it. Benchmarks and users keep XLA's default level.
        os.environ["XLA_FLAGS"] = f"{os.environ['XLA_FLAGS']} {TEST_OPT_LEVEL}"
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ[TEST_CACHE] = tempfile.mkdtemp(prefix="phjax-test-jax-cache-")
        config._phjax_cache_owner = True
        # the Python processes tests start (README, notebooks, experiments, the CLI) read JAX's
        # own variables at start-up and share the same cache
        os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ[TEST_CACHE]
        os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.1"
        # the live source's rendered-head frames (phjax.live._sources.FRAME_CACHE_ENV): a
        # folder of this run, never the user's ~/.cache (removed with the compilation cache)
        os.environ["PHJAX_FRAME_CACHE"] = os.path.join(os.environ[TEST_CACHE], "frames")
    import phjax

    phjax.enable_compilation_cache(os.environ[TEST_CACHE])
    # Tracing and lowering (a fifth of the suite's time) allocate millions of short-lived
    # objects, and Python's cyclic collector then runs every 700 allocations over the whole
    # heap of imported modules. Fewer young-generation collections and the imported objects
    # frozen out of the collector's scans: jax.grad of track traced and lowered in 4.9-6.7 s
    # instead of 6.6-8.1 s (five runs each, one core). Test processes only; phjax never
    # changes the collector of a user's process.
    gc.freeze()
    gc.set_threshold(50_000, 50, 50)


def pytest_unconfigure(config):
    if getattr(config, "_phjax_cache_owner", False):
        shutil.rmtree(os.environ.pop(TEST_CACHE, ""), ignore_errors=True)
        for name in ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
                     "PHJAX_FRAME_CACHE"):
            os.environ.pop(name, None)


#: the marker of tests that must have the machine to themselves (see pytest_collection_modifyitems)
SERIAL = "serial"

#: the folder that holds every ``serial`` test: the serial pass collects only it
SERIAL_DIR = Path(__file__).resolve().parent / "live"


def pytest_ignore_collect(collection_path, config):
    """The serial pass (``pytest -m serial``) collects only :data:`SERIAL_DIR`: importing and
    collecting the other 1 100 tests only to deselect them cost it about 7 s of its ~80 s.
    ``pytest_collection_modifyitems`` checks in every other run that no ``serial`` test lives
    elsewhere (it would silently never run)."""
    if config.getoption("markexpr", "") != SERIAL or collection_path.is_dir():
        return None
    if collection_path.suffix == ".py" and SERIAL_DIR not in collection_path.resolve().parents:
        return True
    return None


def pytest_collection_modifyitems(config, items):
    """Skip ``serial`` tests inside an xdist worker: they run alone, in a second pass.

    A real-time test (the live acceptance run: a 30 fps camera thread and a 120 Hz sender)
    measures the machine as well as the code when another worker compiles beside it; on 2
    cores its camera once fell to 5 fps. The README's test command therefore runs
    ``pytest -n 2`` and then ``pytest -m serial`` in one process, and these tests skip, with
    that reason, in the parallel pass.
    """
    misplaced = [item.nodeid for item in items if item.get_closest_marker(SERIAL)
                 and SERIAL_DIR not in Path(str(item.path)).resolve().parents]
    if misplaced:
        raise pytest.UsageError(f"serial tests outside {SERIAL_DIR} (the serial pass collects "
                                f"only that folder): {', '.join(misplaced)}")
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    skip = pytest.mark.skip(reason="timing-sensitive: runs alone in the serial pass "
                                   "(python -m pytest -q -m serial)")
    for item in items:
        if item.get_closest_marker(SERIAL):
            item.add_marker(skip)


#: the marker of run-time-heavy tests that compile at XLA's default level
#: (see pytest_runtest_protocol)
OPTIMISED = "optimised"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """``optimised`` tests compile phjax's programs with LLVM's optimisations on (XLA's default
    level 3, as users run them) although the parallel pass compiles at ``-O0``
    (pytest_configure), from their fixtures' set-up to their teardown: they spend their time
    running a few programs many times (the RGB-D front-end on many frames, an hour of live
    frames), where ``-O0`` code is 2-3.5 x slower (measured: the slambook relative poses
    69 s at ``-O0``, 37 s optimised; the rendered head sequence 87 / 53 s; the dense
    refinement 40 / 24 s). Programs a test jits itself (``jax.jit``) keep the process's
    level."""
    if item.get_closest_marker(OPTIMISED) is None:
        yield
        return
    from phjax._jit import extra_compiler_options

    with extra_compiler_options(xla_backend_optimization_level=3):
        yield


@pytest.fixture
def shared_data() -> Path:
    return shared_path()


#: /proc/self/maps entries above which the compiled functions are dropped (Linux allows 65530)
_MAX_MAPPINGS = 40000


@pytest.fixture(autouse=True)
def _bounded_memory_mappings():
    """Drop JAX's compiled functions when the process nears Linux's limit of memory mappings.

    XLA:CPU maps the code of every compiled function into its own memory regions (about 260
    for one compiled tracker scan) until the function is dropped; a test worker compiles
    hundreds of functions, and one that reached ``vm.max_map_count`` crashed inside XLA's
    compiler (segfault or abort, about once per full run before this fixture).
    """
    yield
    if mapping_count() > _MAX_MAPPINGS:
        jax.clear_caches()


def mapping_count() -> int:
    """Memory mappings of this process (lines of ``/proc/self/maps``; 0 where that is absent)."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return 0
    with maps.open("rb") as f:
        return sum(1 for _ in f)


def run_cli(capsys, argv) -> tuple[int, str, str]:
    """``phjax`` (in-process ``phjax.cli.main``) on ``argv``: ``(exit status, stdout,
    stderr)``. ``main`` returns its status; a ``SystemExit`` is taken as the status too."""
    from phjax.cli import main

    try:
        rc = main([str(a) for a in argv])
    except SystemExit as stop:
        rc = stop.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_line_error(rc, out, err, *parts) -> None:
    """Exit status 2 and one line ``phjax ...: error: ...`` on stderr holding every one of
    ``parts``, and no traceback anywhere."""
    assert rc == 2, (rc, out, err)
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1, err
    assert lines[0].startswith("phjax") and ": error: " in lines[0], err
    assert "Traceback" not in out + err
    for part in parts:
        assert part in lines[0], (part, err)


def assert_central_differences(f, x, grad, indices, h: float = 1e-6, rtol: float = 1e-6) -> None:
    """``grad`` (the gradient of the scalar ``f`` at the array ``x``) at each index of
    ``indices`` against the central difference ``(f(x + h e) - f(x - h e)) / 2h``, within
    ``rtol * (1 + |difference|)``."""
    import numpy as np

    x = np.asarray(x, float)
    for idx in indices:
        a, b = x.copy(), x.copy()
        a[idx] += h
        b[idx] -= h
        fd = (float(f(jax.numpy.asarray(a))) - float(f(jax.numpy.asarray(b)))) / (2 * h)
        assert abs(grad[idx] - fd) <= rtol * (1 + abs(fd)), (idx, grad[idx], fd)
