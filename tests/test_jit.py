"""phjax's jit wrappers (phjax._jit): compile options on CPU only, nested use, filter_jit."""

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from phjax import _jit


def test_cpu_options_only_on_a_cpu_backend(monkeypatch):
    """XLA:CPU options are rejected by other backends ("No such compile option" on an H200):
    with a GPU default backend the top-level program is plain jax.jit."""
    f = _jit.jit(lambda x: jnp.sin(x) * 2)
    assert float(f(0.5)) == float(jnp.sin(0.5) * 2)
    assert f._top is not f._nested  # this machine: a CPU backend, options on
    g = _jit.jit(lambda x: x + 1)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert g._top is g._nested


def test_nested_and_differentiated_calls():
    """Inside another trace (jit, grad, vmap) the plain version runs (JAX allows compiler
    options only on the outermost jit)."""
    f = _jit.jit(lambda x: jnp.sin(x) * 2)
    assert np.isclose(float(jax.jit(lambda x: f(x) + 1)(0.3)), 2 * np.sin(0.3) + 1)
    assert np.isclose(float(jax.grad(f)(0.3)), 2 * np.cos(0.3))
    np.testing.assert_allclose(jax.vmap(f)(jnp.arange(3.0)), 2 * np.sin(np.arange(3.0)))


def test_extra_compiler_options_compile_their_own_program():
    """Inside extra_compiler_options a jitted function compiles once more, with the options
    added (an unknown option reaches XLA and is rejected); outside, the first program is
    still used; nested blocks restore the outer options."""
    f = _jit.jit(lambda x: jnp.cos(x) * 3)
    x = jnp.asarray(0.25)
    base = float(f(x))
    first = f._top
    with _jit.extra_compiler_options(xla_backend_optimization_level=3):
        assert float(f(x)) == pytest.approx(base, rel=1e-12)
        block = f._top
        assert block is not first and block._cache_size() == 1  # a program of its own
        with (_jit.extra_compiler_options(xla_no_such_phjax_option=True),
              pytest.raises(Exception, match="xla_no_such_phjax_option")):
            f(x)
        assert _jit._EXTRA_OPTIONS == {"xla_backend_optimization_level": 3}
        float(f(x))
        assert f._top is block and block._cache_size() == 1  # reused
    assert _jit._EXTRA_OPTIONS == {}
    float(f(x))
    assert f._top is first and first._cache_size() == 1  # the first program again


def test_a_functions_own_options_come_last(monkeypatch):
    """``jit(options=...)``: the function's own XLA options are added over COMPILER_OPTIONS and
    over an extra_compiler_options block (they reach XLA: an unknown one is rejected by
    name); the synthetic head's renderer compiles with IMAGE_COMPILER_OPTIONS, so its frames
    are the same program under the suite's -O0 as for users."""
    seen = []
    real_jit = jax.jit

    def spy(fun, **kwargs):
        seen.append(kwargs.get("compiler_options"))
        return real_jit(fun, **kwargs)

    f = _jit.jit(lambda x: x * 2, options={"xla_backend_optimization_level": 3})
    monkeypatch.setattr(jax, "jit", spy)
    with _jit.extra_compiler_options(xla_backend_optimization_level=0,
                                     xla_cpu_enable_fast_math=False):
        assert float(f(jnp.asarray(1.5))) == 3.0
    assert seen == [{**_jit.COMPILER_OPTIONS, "xla_cpu_enable_fast_math": False,
                     "xla_backend_optimization_level": 3}]
    monkeypatch.setattr(jax, "jit", real_jit)
    bad = _jit.jit(lambda x: x + 1, options={"xla_no_such_phjax_option": True})
    with pytest.raises(Exception, match="xla_no_such_phjax_option"):
        bad(jnp.asarray(1.0))

    from phjax.vision import synthetic_rgbd

    for name in ("_wall_jit", "_render_jit", "_frame_jit"):
        assert getattr(synthetic_rgbd, name)._options == _jit.IMAGE_COMPILER_OPTIONS, name


class _Scaled(eqx.Module):
    scale: jax.Array
    name: str = eqx.field(static=True)


def test_filter_jit_traces_arrays_and_keeps_the_rest_static():
    calls = []

    @_jit.filter_jit
    def f(m, x, power=2, label="a"):
        calls.append(label)  # runs at trace time only
        return m.scale * x**power

    m = _Scaled(jnp.asarray(3.0), "s")
    assert float(f(m, jnp.asarray(2.0))) == 12.0
    assert float(f(_Scaled(jnp.asarray(4.0), "s"), jnp.asarray(1.0))) == 4.0  # no retrace
    assert len(calls) == 1
    assert float(f(m, jnp.asarray(2.0), power=3, label="b")) == 24.0  # static: retraced
    assert calls == ["a", "b"]
    g = jax.grad(lambda s: f(_Scaled(s, "s"), jnp.asarray(2.0)))(jnp.asarray(1.0))
    assert float(g) == 4.0


_TRACK_SCRIPT = """
import sys, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import phjax
t = np.arange(300) / 30.0
rng = np.random.default_rng(0)
p = 0.1 * np.stack([np.sin(t), np.cos(0.7 * t), 0.3 * t], -1) + 0.005 * rng.standard_normal((300, 3))
p[::17] = np.nan
q = np.asarray(phjax.quat_from_rotvec(np.stack([0.5 * np.sin(t), 0.2 * t, 0.1 + 0 * t], -1)))
out = phjax.track(t, p, q, np.arange(1200) / 120.0)
np.save(sys.argv[1], np.concatenate([np.asarray(out[0]), np.asarray(out[1])], -1))
"""


def _users_environment() -> dict:
    """This process's environment for a Python process that compiles as users do: without
    the suite's ``-O0`` (tests/conftest.py) and without the run's shared compilation cache
    (it compiles its programs rather than loading another process's)."""
    from conftest import TEST_OPT_LEVEL

    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace(TEST_OPT_LEVEL, "").strip()
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    return env


def test_the_suites_optimisation_level_does_not_change_results(tmp_path):
    """The parallel test pass compiles with LLVM's optimisations off (tests/conftest.py, for
    compile time); users run XLA's default level. A recording tracked both ways (float64, lost
    frames, a fresh process each) agrees to 1e-12 m / quaternion units (measured: 1.4e-15)."""
    import subprocess
    import sys

    from conftest import TEST_OPT_LEVEL

    results = {}
    for name, flags in (("default", ""), ("suite", TEST_OPT_LEVEL)):
        env = _users_environment()  # each compiles; neither loads the other's program
        env["XLA_FLAGS"] = f"{env['XLA_FLAGS']} {flags}".strip()
        out = tmp_path / f"{name}.npy"
        subprocess.run([sys.executable, "-c", _TRACK_SCRIPT, str(out)], env=env, check=True,
                       timeout=300)
        results[name] = np.load(out)
    a, b = results["default"], results["suite"]
    finite = np.isfinite(a)
    assert finite.sum() > 0.9 * a.size and np.array_equal(finite, np.isfinite(b))
    assert np.abs(a[finite] - b[finite]).max() <= 1e-12


def _tiered(monkeypatch, fun):
    """A :class:`_jit.Tiered` program that tiers here (the suite's XLA_FLAGS compile at -O0,
    where tiering is off: both programs would be the same)."""
    monkeypatch.setattr(_jit, "_tiering_pays", lambda: True)
    return _jit.Tiered(_jit.jit(fun))


def _poly(x, y):
    if x.shape[-1] != 3:  # an error raised at trace time, like the tracker's shape checks
        raise ValueError(f"x must have 3 components, got {x.shape}")
    return jnp.sin(x) @ jnp.cos(y) + jnp.linalg.norm(x * y)


def test_tiered_switches_to_the_optimised_program(monkeypatch):
    f = _tiered(monkeypatch, _poly)
    x, y = np.array([0.1, 0.2, 0.3], np.float32), np.array([0.4, 0.5, 0.6], np.float32)
    expected = float(_poly(jnp.asarray(x), jnp.asarray(y)))
    assert np.isclose(float(f(x, y)), expected, rtol=1e-6)
    fast = f._program
    assert fast is not f._jitted and f._thread is not None and f._thread.name == "phjax-compile"
    assert f.wait(60) and f.optimized and f.error is None
    assert f._program is not fast and not f._thread.daemon  # an exit waits for it
    assert np.isclose(float(f(x, y)), expected, rtol=1e-6)
    # another signature (float64 inputs, another shape) takes the general jitted path
    assert np.isclose(float(f(x.astype(np.float64), y.astype(np.float64))), expected, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(f(np.ones((2, 3)), np.ones(3))),
                               np.asarray(_poly(jnp.ones((2, 3)), jnp.ones(3))), rtol=1e-6)
    with pytest.raises(ValueError, match="3 components"):
        f(np.ones(4), np.ones(4))
    assert f._program is not fast  # still the optimised program for the first signature


def test_tiered_is_plain_jit_where_it_cannot_pay(monkeypatch):
    """Under XLA_FLAGS at -O0 (this suite) or on another backend there is one program."""
    f = _jit.Tiered(_jit.jit(_poly))
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    assert float(f(np.ones(3), np.ones(3))) == pytest.approx(float(_poly(jnp.ones(3), jnp.ones(3))))
    assert f._program is f._jitted and f._thread is None and f.optimized and f.wait()
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert not _jit._tiering_pays()


_EXIT_SCRIPT = """
import numpy as np, phjax
s = phjax.TrackerStream(phjax.TrackerConfig(imm=None))
s.update(0.0, np.zeros(3), np.array([1.0, 0, 0, 0]))
print("optimized before exit:", s.wait_compiled(timeout=0))
"""


def test_a_process_exiting_during_the_background_compilation_ends_cleanly():
    """A script that exits right after a stream's first update (its optimised program still
    compiling) ends with status 0: a daemon thread inside XLA's compiler aborted the process
    at exit ("terminate called ...", signal 6), so the thread is not a daemon."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _EXIT_SCRIPT], env=_users_environment(),
                       capture_output=True, check=False, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "optimized before exit: False" in r.stdout  # it did exit during the compilation
    assert "terminate" not in r.stderr


_STALL_SCRIPT = """
import json, os, sys, time
import numpy as np, phjax
phjax.enable_compilation_cache(sys.argv[1])
s = phjax.TrackerStream(phjax.TrackerConfig(imm=None))
s.update(0.0, np.zeros(3), np.array([1.0, 0, 0, 0]))
entries = len(os.listdir(sys.argv[1]))  # the fast program's, written by the first update
gaps, last = [], time.perf_counter()
while not s.wait_compiled(timeout=0):  # a render loop at 1 kHz beside the background compile
    time.sleep(0.001)
    now = time.perf_counter()
    gaps.append(now - last)
    last = now
print(json.dumps({"before": entries, "after": len(os.listdir(sys.argv[1])),
                  "loops": len(gaps), "max_gap": max(gaps)}))
"""


def test_the_background_compilation_never_holds_a_render_loop(tmp_path):
    """With JAX's persistent compilation cache on (the CLI's default), the background
    compilation wrote the optimised tracker program to the cache from its thread, and
    serialising it held Python's lock: a loop in the calling thread stalled 100-133 ms
    (phjax live's render loop: 150-390 ms, once, on a first run). It now reads the cache but
    writes nothing (measured: largest gap 5-8 ms, alone on one core or on two)."""
    import json
    import subprocess
    import sys

    cache = tmp_path / "jax-cache"
    r = subprocess.run([sys.executable, "-c", _STALL_SCRIPT, str(cache)],
                       env=_users_environment(), capture_output=True, check=False, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["before"] >= 1 and res["loops"] > 100, res  # the cache is on and was in use
    assert res["after"] == res["before"], res  # nothing written from the background thread
    assert res["max_gap"] < 0.05, res  # 50 ms: 6-10 x the measured gaps, half the stall's
