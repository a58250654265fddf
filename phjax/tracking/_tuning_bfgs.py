"""``optimistix.BFGS`` stepped from Python by ask-tell (:func:`_bfgs`): the loss and gradient
come from a separately compiled function, so the solver step stays small to compile. Used by
:func:`phjax.tracking.tuning.tune_tracker`; nothing here knows about the tracker.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array
from .._jit import filter_jit


# Ask-tell with optimistix: BFGS evaluates its objective only at ``state.y_eval`` (the trial
# point chosen by the previous step), so the loss and gradient there are computed beforehand by
# the separately compiled ``_value_and_grad`` and handed to the solver step as ``args``. The
# solver step then compiles in about a second instead of inlining the whole differentiated
# stream, and the expensive program is compiled once and shared with
# :meth:`TuningProblem.value_and_grad`. Evaluating the told objective anywhere else gives NaN
# (so a change of that protocol would be loud, not silently wrong).
class _Told(eqx.Module):
    y: Array
    f: Array
    g: Array


@jax.custom_jvp
def _told_value(y, told_y, told_f, told_g):
    return jnp.where(jnp.all(y == told_y), told_f, jnp.nan)


@_told_value.defjvp
def _told_value_jvp(primals, tangents):
    y, told_y, told_f, told_g = primals
    return _told_value(y, told_y, told_f, told_g), jnp.dot(told_g, tangents[0])


def _told_objective(y, told: _Told):
    return _told_value(y, told.y, told.f, told.g), None


_OPTIONS: dict[str, Any] = {}
_TAGS: frozenset = frozenset()


@filter_jit
def _solver_init(solver, y):
    told = _Told(y, jnp.zeros((), y.dtype), jnp.zeros_like(y))
    f_struct = jax.ShapeDtypeStruct((), y.dtype)
    return solver.init(_told_objective, y, told, _OPTIONS, f_struct, None, _TAGS)


@filter_jit
def _solver_step(solver, y, state, told):
    y, state, _ = solver.step(_told_objective, y, told, _OPTIONS, state, _TAGS)
    done, result = solver.terminate(_told_objective, y, told, _OPTIONS, state, _TAGS)
    return y, state, done, result


def _bfgs(value_and_grad, y0, *, max_steps, rtol, atol, callback=None):
    """Minimise with ``optimistix.BFGS`` by ask-tell stepping (see ``_Told``).

    ``value_and_grad(y) -> (f, g, aux)`` is called once per step at the solver's trial point;
    ``callback(step, y, loss, trial_loss, accepted, step_size, aux)`` after every step.

    Returns:
        ``(y, result, steps, num_accepted, loss_history, trial_losses)``.
    """
    solver = optx.BFGS(rtol=rtol, atol=atol)
    y = jnp.asarray(y0)
    state = _solver_init(solver, y)
    history, trials = [], []
    done, result, steps = False, optx.RESULTS.successful, 0
    while steps < max_steps and not done:
        y_eval = state.y_eval
        f, g, aux = value_and_grad(y_eval)
        finite = bool(jnp.isfinite(f) & jnp.all(jnp.isfinite(g)))
        if steps == 0 and not finite:
            raise ValueError(f"the loss or its gradient at the start is not finite (loss "
                             f"{float(f)}, gradient {np.asarray(g)})")
        told = _Told(y_eval, jnp.where(finite, f, jnp.nan), jnp.where(finite, g, 0))
        accepted_before = int(state.num_accepted_steps)
        y, state, done, result = _solver_step(solver, y, state, told)
        steps += 1
        done = bool(done)
        accepted = int(state.num_accepted_steps) > accepted_before
        history.append(float(state.f_info.f))
        trials.append(float(f) if finite else float("nan"))
        if callback is not None:
            callback(steps, y, history[-1], trials[-1], accepted,
                     float(state.search_state.step_size), aux)
    if not done:
        result = optx.RESULTS.max_steps_reached
    return (y, result, steps, int(state.num_accepted_steps), np.asarray(history),
            np.asarray(trials))
