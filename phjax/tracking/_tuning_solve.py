"""Tuning as an optimisation problem (:mod:`phjax.tracking.tuning`): :class:`TuningProblem`
(the loss as a function of the log-parameters, with its compiled value and gradient),
:func:`make_problem`, and :func:`tune_tracker`, which minimises it with BFGS and reports a
:class:`TuningResult`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float
from .._jit import filter_jit
from .._misc import any_traced, check_count

from ._tuning_bfgs import _bfgs
from ._tuning_data import TuningData, prepare_recordings
from ._tuning_loss import _combine, loss_terms
from ._tuning_params import (
    _arrays_config,
    _check_positive,
    _get,
    _is_log,
    _leaf_values,
    _resolve,
    _with_values,
    default_parameters,
)
from .tracker import TrackerConfig


class TuningProblem(eqx.Module):
    """:func:`tracker_loss` as a function of log-parameters ``y``.

    ``y`` holds ``log(value)`` of each tuned leaf, except for leaves that are logarithms
    already (named ``log_*``, e.g. the IMM's ``log_q`` and ``log_switch_rate``) and ``adapt``
    (any sign), which ``y`` holds as they are.

    Fields:
        data: the recordings.
        config: base configuration (float leaves as arrays); the tuned leaves are replaced.
        names: names of the tuned leaves, as given (static).
        paths: their attribute paths (static).
        lam, position_weight, rotation_weight: loss weights (arrays, so changing them does not
            recompile).
        normalize: see :func:`tracker_loss` (static).
    """

    data: TuningData
    config: TrackerConfig
    names: tuple[str, ...] = eqx.field(static=True)
    paths: tuple[tuple[str | int, ...], ...] = eqx.field(static=True)
    lam: Float[Array, ""]
    position_weight: Float[Array, ""]
    rotation_weight: Float[Array, ""]
    normalize: bool = eqx.field(static=True, default=True)

    @property
    def parameters(self) -> tuple[str, ...]:
        """Names of the tuned leaves (order of the log-parameter vector)."""
        return self.names

    def params_from_config(self, config: TrackerConfig) -> Float[Array, " P"]:
        """Log-parameters of ``config``'s tuned leaves."""
        dtype = self.data.times.dtype
        return jnp.stack([jnp.asarray(_get(config, p), dtype) if _is_log(p)
                          else jnp.log(jnp.asarray(_get(config, p), dtype)) for p in self.paths])

    def config_from_params(self, y: Float[Array, " P"]) -> TrackerConfig:
        """The base configuration with the tuned leaves set from ``y`` (``exp(y)``, or ``y``
        itself for ``log_*`` leaves and ``adapt``)."""
        return _with_values(self.config, self.paths, _leaf_values(self.paths, y, jnp))

    def loss_and_terms(self, y: Float[Array, " P"]) -> tuple[Float[Array, ""], Float[Array, "R 4"]]:
        """:func:`tracker_loss` at log-parameters ``y`` and the :func:`loss_terms` it combines."""
        terms = loss_terms(self.config_from_params(y), self.data)
        loss = _combine(terms.reshape(-1, 4), self.data.reference.reshape(-1, 4), self.lam,
                        self.position_weight, self.rotation_weight, self.normalize)
        return loss, terms

    def loss(self, y: Float[Array, " P"]) -> Float[Array, ""]:
        """:func:`tracker_loss` at log-parameters ``y``."""
        return self.loss_and_terms(y)[0]

    def value_and_grad(
        self, y: Float[Array, " P"], autodiff_mode: str = "fwd"
    ) -> tuple[Float[Array, ""], Float[Array, " P"], Float[Array, "R 4"]]:
        """Loss, its gradient with respect to the log-parameters, and the per-recording
        :func:`loss_terms` (one program, jitted once per data shape and parameter set).

        Arguments:
            y: log-parameters.
            autodiff_mode: ``"fwd"`` (one JVP per parameter; the default: for the few
                parameters of a tracker it compiles about three times faster than reverse mode)
                or ``"bwd"`` (reverse mode; cheaper to run with many parameters).

        Returns:
            ``(loss, gradient (P,), terms (R, 4))``.
        """
        if autodiff_mode not in ("fwd", "bwd"):
            raise ValueError(f"autodiff_mode must be 'fwd' or 'bwd', got {autodiff_mode!r}")
        return _value_and_grad(self, jnp.asarray(y, self.data.times.dtype), autodiff_mode)


def make_problem(
    data: TuningData,
    *,
    lam: float = 0.0,
    config: TrackerConfig | None = None,
    parameters: Sequence[str] | None = None,
    position_weight: float = 1.0,
    rotation_weight: float = 1.0,
    normalize: bool = True,
) -> TuningProblem:
    """A :class:`TuningProblem` (validates the parameter names and positivity).

    ``config`` defaults to ``TrackerConfig()`` (the IMM filter), ``parameters`` to
    :func:`default_parameters` of the config; the other arguments as in :func:`tune_tracker`.
    """
    config = TrackerConfig() if config is None else config
    parameters = default_parameters(config) if parameters is None else parameters
    parameters = (parameters,) if isinstance(parameters, str) else tuple(parameters)
    paths = _resolve(config, parameters)
    _check_positive(config, paths)
    if not (float(lam) >= 0 and float(position_weight) >= 0 and float(rotation_weight) >= 0):
        raise ValueError("lam, position_weight and rotation_weight must be non-negative, got "
                         f"{lam}, {position_weight}, {rotation_weight}")
    _check_something_scored(data, float(position_weight), float(rotation_weight))
    dtype = data.times.dtype
    return TuningProblem(data, _arrays_config(config, dtype), parameters, paths,
                         jnp.asarray(lam, dtype),
                         jnp.asarray(position_weight, dtype), jnp.asarray(rotation_weight, dtype),
                         normalize)


def _check_something_scored(data: TuningData, position_weight: float, rotation_weight: float):
    """``ValueError`` when no recording scores a channel of positive weight (the loss would be
    0 whatever the parameters, and the solve "converge" at once)."""
    if any_traced(data.reference):
        return
    ref = np.asarray(data.reference).reshape(-1, 4)
    avail = np.isfinite(ref) & (ref > 0)
    n_pos = int(np.sum(avail[:, 0] & avail[:, 2]))
    n_rot = int(np.sum(avail[:, 1] & avail[:, 3]))
    if not ((n_pos and position_weight > 0) or (n_rot and rotation_weight > 0)):
        raise ValueError(
            f"nothing to tune against: position_weight {position_weight:g} (positions scored in "
            f"{n_pos} recording(s)), rotation_weight {rotation_weight:g} (orientations scored in "
            f"{n_rot}); give a positive weight to a channel the recordings score")


@filter_jit
def _value_and_grad(problem: TuningProblem, y, autodiff_mode: str):
    """``(loss, gradient, terms)`` at log-parameters ``y``."""
    if autodiff_mode == "fwd":
        # one JVP per parameter in a loop: compiles in about a third of the time of the reverse
        # mode (and faster than a vmapped JVP); the stream has few parameters
        basis = jnp.eye(y.shape[0], dtype=y.dtype)
        (f, terms), (g, _) = jax.lax.map(
            lambda v: jax.jvp(problem.loss_and_terms, (y,), (v,)), basis)
        return f[0], g, terms[0]
    (f, terms), g = jax.value_and_grad(problem.loss_and_terms, has_aux=True)(y)
    return f, g, terms


class StepInfo(NamedTuple):
    """Progress of one solver step (passed to the ``progress`` callback of :func:`tune_tracker`).

    Fields:
        step: 1-based step number.
        loss: loss at the current (last accepted) iterate.
        trial_loss: loss at the point evaluated in this step (NaN if not finite there).
        accepted: whether the line search accepted that point.
        step_size: line-search step size of the next trial.
        parameters: current (accepted) parameter values by name.
    """

    step: int
    loss: float
    trial_loss: float
    accepted: bool
    step_size: float
    parameters: dict[str, float]


@dataclasses.dataclass(frozen=True)
class TuningResult:
    """Outcome of :func:`tune_tracker`.

    Attributes:
        config: the tuned configuration (same as the first return value).
        result: the ``optimistix.RESULTS`` status (``successful`` on convergence,
            ``max_steps_reached`` when ``max_steps`` ran out, ...).
        num_steps: solver steps taken (= loss and gradient evaluations).
        num_accepted_steps: steps whose trial point the line search accepted.
        loss_history: loss of the current iterate after each step (``[0]`` is the initial loss).
        trial_losses: loss at each evaluated point.
        initial_loss, final_loss: loss of the start and of the returned configuration.
        initial_parameters, parameters: tuned values by name, before and after.
        initial_terms, terms: ``(R, 4)`` :func:`loss_terms` ``[E_p, E_r, J_p, J_r]`` per
            recording (m, rad, m/s^3, rad/s^3) at the start and at the result.
        reference: ``(R, 4)`` the same terms of the reference stream
            (:attr:`TuningData.reference`); ``terms / reference`` are the ratios the
            normalised loss combines.
    """

    config: TrackerConfig
    result: Any
    num_steps: int
    num_accepted_steps: int
    loss_history: np.ndarray
    trial_losses: np.ndarray
    initial_loss: float
    final_loss: float
    initial_parameters: dict[str, float]
    parameters: dict[str, float]
    initial_terms: np.ndarray
    terms: np.ndarray
    reference: np.ndarray

    @property
    def successful(self) -> bool:
        """Whether the solver converged (``result == optimistix.RESULTS.successful``)."""
        return bool(self.result == optx.RESULTS.successful)

    @property
    def message(self) -> str:
        """Short status: ``"converged"``, ``"max_steps_reached"`` or optimistix's message."""
        if self.successful:
            return "converged"
        if self.result == optx.RESULTS.max_steps_reached:
            return "max_steps_reached"
        return optx.RESULTS[self.result]


def _values(problem: TuningProblem, y) -> dict[str, float]:
    y = np.asarray(y, np.float64)
    return {n: float(v) for n, v in zip(problem.parameters, _leaf_values(problem.paths, y, np))}


def tune_tracker(
    recordings: TuningData | Sequence,
    *,
    lam: float = 0.3,
    config: TrackerConfig | None = None,
    parameters: Sequence[str] | None = None,
    max_steps: int = 50,
    rtol: float = 1e-3,
    atol: float = 1e-4,
    position_weight: float = 1.0,
    rotation_weight: float = 1.0,
    normalize: bool = True,
    progress: Callable[[StepInfo], None] | None = None,
    autodiff_mode: str = "fwd",
    **prepare_kwargs,
) -> tuple[TrackerConfig, TuningResult]:
    """Tune the tracker's parameters by BFGS on :func:`tracker_loss` (log parameterisation).

    ``optimistix.BFGS`` (Armijo backtracking) is stepped from Python: each step evaluates the
    loss and gradient at the solver's trial point with :meth:`TuningProblem.value_and_grad`
    (compiled once per data shape and parameter set, so calls with other ``lam``, weights or
    start values do not recompile) and hands them to ``solver.step``. Failures never raise:
    the status is in :attr:`TuningResult.result` (as ``optimistix.minimise(..., throw=False)``).
    A trial point with a non-finite loss or gradient counts as a failed evaluation and is
    rejected by the line search.

    Arguments:
        recordings: a :class:`TuningData`, or ground-truth trajectories passed to
            :func:`prepare_recordings` with ``prepare_kwargs`` (``sensor``, ``render_rate``,
            ``seed``, ``seconds``, ``reference_config``, ``max_gt_gap``, ``dtype``).
        lam: weight of the jerk terms (dimensionless, see the module docs).
        config: start configuration (default ``TrackerConfig()``, the IMM filter); untuned
            fields are kept.
        parameters: names of the float leaves to tune (see :func:`tunable_parameters`;
            default :func:`default_parameters` of ``config``).
        max_steps: maximum number of solver steps (loss and gradient evaluations).
        rtol, atol: BFGS termination tolerances (on the log-parameters and the loss).
        position_weight, rotation_weight, normalize: see :func:`tracker_loss`.
        progress: optional callback receiving a :class:`StepInfo` after every step.
        autodiff_mode: ``"fwd"`` or ``"bwd"``, see :meth:`TuningProblem.value_and_grad`.

    Returns:
        ``(config, result)``: the tuned :class:`~phjax.TrackerConfig` (Python floats) and a
        :class:`TuningResult`.

    Raises:
        ValueError: bad arguments, or a non-finite loss or gradient at the start.
    """
    # checked before the recordings are prepared (seconds of work); 1.5 ran a full tuning
    max_steps = check_count(max_steps, "max_steps")
    if isinstance(recordings, TuningData):
        if prepare_kwargs:
            raise ValueError(f"unexpected arguments {sorted(prepare_kwargs)} with prepared "
                             "TuningData")
        data = recordings
    else:
        data = prepare_recordings(recordings, **prepare_kwargs)
    base = TrackerConfig() if config is None else config
    problem = make_problem(data, lam=lam, config=base, parameters=parameters,
                           position_weight=position_weight, rotation_weight=rotation_weight,
                           normalize=normalize)
    y0 = problem.params_from_config(base)
    terms_seen = {}

    def on_step(step, y, loss, trial, accepted, step_size, terms):
        if accepted:
            terms_seen.setdefault("initial", terms)
            terms_seen["current"] = terms
        if progress is not None:
            progress(StepInfo(step, loss, trial, accepted, step_size, _values(problem, y)))

    y, result, steps, n_accepted, history, trials = _bfgs(
        lambda y: problem.value_and_grad(y, autodiff_mode), y0, max_steps=max_steps, rtol=rtol,
        atol=atol, callback=on_step)
    tuned = _with_values(base, problem.paths, list(_values(problem, y).values()))
    res = TuningResult(
        config=tuned,
        result=result,
        num_steps=steps,
        num_accepted_steps=n_accepted,
        loss_history=history,
        trial_losses=trials,
        initial_loss=history[0],
        final_loss=history[-1],
        initial_parameters=_values(problem, y0),
        parameters=_values(problem, y),
        initial_terms=np.asarray(terms_seen["initial"], np.float64),
        terms=np.asarray(terms_seen["current"], np.float64),
        reference=np.asarray(data.reference, np.float64),
    )
    return tuned, res
