"""Test configuration: float64 everywhere (library code stays dtype-generic), shared data paths."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import pytest
from hypothesis import HealthCheck, settings

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


def shared_path(*parts: str) -> Path:
    """Path inside ``../shared/data``; skips the test (with the reason) when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p} (expected ../shared/data beside the repository)")
    return p


@pytest.fixture
def shared_data() -> Path:
    return shared_path()


#: /proc/self/maps entries above which the compiled functions are dropped (Linux allows 65530)
_MAX_MAPPINGS = 40000


@pytest.fixture(autouse=True)
def _bounded_memory_mappings():
    """Drop JAX's compiled functions when the process nears Linux's limit of memory mappings.

    XLA:CPU maps the code of every compiled function into its own memory regions (about 1200
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
