"""phjax's jit wrappers (phjax._jit): compile options on CPU only, nested use, filter_jit."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from phjax import _jit


def test_cpu_options_only_on_a_cpu_backend(monkeypatch):
    """XLA:CPU options are rejected by other backends ("No such compile option" on an H200):
    with a GPU default backend the top-level program is plain jax.jit."""
    f = _jit.jit(lambda x: jnp.sin(x) * 2)
    assert float(f(0.5)) == float(jnp.sin(0.5) * 2)
    assert f._top_jit is not f._nested  # this machine: a CPU backend, options on
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


def test_the_suites_optimisation_level_does_not_change_results(tmp_path):
    """The parallel test pass compiles with LLVM's optimisations off (tests/conftest.py, for
    compile time); users run XLA's default level. A recording tracked both ways (float64, lost
    frames, a fresh process each) agrees to 1e-12 m / quaternion units (measured: 1.4e-15)."""
    import os
    import subprocess
    import sys

    from conftest import TEST_OPT_LEVEL

    results = {}
    for name, flags in (("default", ""), ("suite", TEST_OPT_LEVEL)):
        env = dict(os.environ)
        base = env.get("XLA_FLAGS", "").replace(TEST_OPT_LEVEL, "").strip()
        env["XLA_FLAGS"] = f"{base} {flags}".strip()
        env.pop("JAX_COMPILATION_CACHE_DIR", None)  # compile, do not load the other's program
        out = tmp_path / f"{name}.npy"
        subprocess.run([sys.executable, "-c", _TRACK_SCRIPT, str(out)], env=env, check=True,
                       timeout=300)
        results[name] = np.load(out)
    a, b = results["default"], results["suite"]
    finite = np.isfinite(a)
    assert finite.sum() > 0.9 * a.size and np.array_equal(finite, np.isfinite(b))
    assert np.abs(a[finite] - b[finite]).max() <= 1e-12
