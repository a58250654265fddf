"""Stored (exported) whole-recording programs (phjax.tracking._exported): same results as the
traced path, a later process loads instead of tracing, keys separate what must differ, and a
damaged file or a traced config falls back to the normal path."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np

import phjax as pj
from phjax.tracking import _exported
from phjax.tracking.tracker import TrackerConfig

REPO = Path(__file__).resolve().parents[2]


def _recording(n=150, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    p = 0.1 * np.stack([np.sin(t), np.cos(0.7 * t), 0.3 * t], -1) + 0.003 * rng.standard_normal((n, 3))
    p[::11] = np.nan
    q = np.asarray(pj.quat_from_rotvec(np.stack([0.4 * np.sin(t), 0.2 * t, 0 * t + 0.1], -1)))
    return t, p, q, np.arange(0.05, t[-1], 1 / 120)


def test_stored_program_gives_the_traced_result_and_is_reused(tmp_path):
    t, p, q, r = _recording()
    ref = pj.track(t, p, q, r)
    ref_off = pj.reconstruct(t, p, q, r)
    with _exported.exported_programs(tmp_path):
        got = pj.track(t, p, q, r)
        got_off = pj.reconstruct(t, p, q, r)
        files = sorted(x.name for x in tmp_path.iterdir())
        # another length in the same size class: the same program, no new file
        pj.track(t[:140], p[:140], q[:140], r[r < t[139]])
        assert sorted(x.name for x in tmp_path.iterdir()) == files
        # another config structure (single-model filter): another program
        pj.track(t, p, q, r, config=TrackerConfig(imm=None))
        assert len(list(tmp_path.iterdir())) == 3
    assert [f.split("-")[0] for f in files] == ["_reconstruct_core", "_track_core"]
    for a, b in zip((*ref, *ref_off), (*got, *got_off)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
    assert not _exported._LOADED  # released with the block


_SCRIPT = """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import phjax as pj
from phjax.tracking import _exported, tracker
if sys.argv[2] == "load":  # tracing the stream would now fail: the stored program must be used
    def no_trace(*a, **k):
        raise AssertionError("traced the tracker although its program is stored")
    tracker._update = no_trace
t = np.arange(150) / 30.0
p = 0.1 * np.stack([np.sin(t), np.cos(t), t], -1)
q = np.tile([1.0, 0, 0, 0], (150, 1))
with _exported.exported_programs(sys.argv[1]):
    out = pj.track(t, p, q, np.arange(0.05, 4.9, 1 / 120))
print(float(np.nansum(np.asarray(out[0]))))
"""


def test_a_later_process_loads_without_tracing(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    run = lambda mode: subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(tmp_path), mode], env=env, capture_output=True,
        text=True, timeout=600, check=False)
    first = run("store")
    assert first.returncode == 0, first.stderr[-2000:]
    second = run("load")
    assert second.returncode == 0, second.stderr[-2000:]
    assert first.stdout.split()[-1] == second.stdout.split()[-1]


def test_damaged_file_and_traced_config_fall_back(tmp_path):
    t, p, q, r = _recording(100, seed=1)
    ref = np.asarray(pj.track(t, p, q, r)[0])
    with _exported.exported_programs(tmp_path):
        pj.track(t, p, q, r)
        (path,) = list(tmp_path.iterdir())
        _exported._LOADED.clear()
        path.write_bytes(b"not a program")
        got = np.asarray(pj.track(t, p, q, r)[0])  # traced again and stored anew
        assert path.stat().st_size > 1000
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)

        # a traced config (inside jit, grad, vmap) takes the normal path: same result
        traced = jax.jit(lambda h: pj.track(t, p, q, r, config=TrackerConfig(horizon=h))[0])
        np.testing.assert_allclose(np.asarray(traced(0.028)), ref, rtol=0, atol=1e-13)
        assert len(list(tmp_path.iterdir())) == 1


def test_a_missing_serialiser_only_means_no_stored_program(tmp_path, monkeypatch):
    """Without flatbuffers (jax.export's serialiser; a core dependency, but an environment may
    lack it) the command line's stored programs are skipped: the result is the traced one and
    nothing is written (before, `phjax demo` ended in an ImportError traceback)."""
    t, p, q, r = _recording(100, seed=2)
    ref = np.asarray(pj.track(t, p, q, r)[0])

    def no_serialiser(self, *a, **k):
        raise ImportError("Please install 'flatbuffers' in order to use Exported serialization")

    monkeypatch.setattr(jax.export.Exported, "serialize", no_serialiser)
    with _exported.exported_programs(tmp_path):
        got = np.asarray(pj.track(t, p, q, r)[0])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)
    assert list(tmp_path.iterdir()) == []
