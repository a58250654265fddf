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
