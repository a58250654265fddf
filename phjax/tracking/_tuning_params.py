"""Parameter paths of :mod:`phjax.tracking.tuning`: which float leaves of a
:class:`~phjax.TrackerConfig` the causal stream uses, their names (short or dotted), validation of
the names given, and reading and writing leaves by path, with the log parameterisation (``log_*``
leaves and ``adapt`` as they are, the others as ``exp(y)``).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .tracker import TrackerConfig, _stream_filter

#: Parameters tuned by default for the single-model filter (``TrackerConfig(imm=None)``): its
#: noise model and the segment horizon. For the IMM see :func:`default_parameters`.
DEFAULT_PARAMETERS: tuple[str, ...] = (
    "pos_process_noise",
    "rot_process_noise",
    "pos_meas_noise",
    "rot_meas_noise",
    "horizon",
)


def _is_float_leaf(x) -> bool:
    return isinstance(x, float) or eqx.is_inexact_array(x)


def _key(k) -> str | int | None:
    """A path entry: attribute name, tuple index, or ``None`` for anything else."""
    if isinstance(k, jax.tree_util.GetAttrKey):
        return k.name
    if isinstance(k, jax.tree_util.SequenceKey):
        return k.idx
    return None


def _unused(config: TrackerConfig) -> set:
    """Float leaves the causal stream never reads with this configuration (zero gradient)."""
    unused = set()
    if config.imm is not None:  # only phjax.reconstruct reads the single-model section
        unused.add("kalman")
    else:
        unused.add("adapt")  # adaptive settling reads the IMM's mode probabilities
    if _stream_filter(config).order < 3:
        unused.add("init_pos_acc_std")  # no acceleration in the state
    return unused


def _leaf_paths(config: TrackerConfig) -> list[tuple[str | int, ...]]:
    """Paths (attribute names and model indices) of the float leaves the causal stream uses:
    with an IMM filter not the single-model ``kalman`` section, with the single-model filter
    not ``adapt``, without acceleration models not ``init_pos_acc_std``."""
    unused = _unused(config)
    paths = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(config)[0]:
        keys = tuple(_key(k) for k in path)
        if not _is_float_leaf(leaf) or None in keys or unused & set(keys):
            continue
        paths.append(keys)
    return paths


def _dotted(path) -> str:
    return ".".join(str(k) for k in path)


def _names(paths) -> list[str]:
    """Short name (last attribute) when unique, else the dotted path."""
    last = [p[-1] for p in paths]
    return [p[-1] if last.count(p[-1]) == 1 else _dotted(p) for p in paths]


def _float_leaf_paths(config: TrackerConfig) -> dict[str, tuple[str | int, ...]]:
    """Paths of the float leaves by name: the dotted path always, the short name when unique."""
    paths = _leaf_paths(config)
    out = {_dotted(p): p for p in paths}
    out.update(zip(_names(paths), paths))
    return out


#: leaves tuned as they are (any sign, zero allowed) rather than in log space
_LINEAR = ("adapt", "lookahead")


def _is_log(path) -> bool:
    """Leaves tuned as they are (any sign): logarithms already (``log_*``), ``adapt`` and
    ``lookahead`` (0 by default; tuned, it becomes the lead that best cancels the stream's lag
    against the ground truth of the data, which :func:`tune_tracker` scores at the render
    times)."""
    return str(path[-1]).startswith("log_") or path[-1] in _LINEAR


def tunable_parameters(config: TrackerConfig | None = None) -> tuple[str, ...]:
    """Names of the float leaves of a tracker configuration that the causal stream uses.

    Discovered from the PyTree, so new float fields appear automatically. Short names
    (``"horizon"``, ``"log_switch_rate"``) are used when unique, dotted paths otherwise
    (``"imm.position_models.0.log_q"``: the first position model of the IMM); both forms are
    accepted wherever a parameter name is expected. With the IMM filter (the default) the
    single-model ``kalman`` leaves are not listed (the causal stream does not use them).

    Arguments:
        config: the configuration (default ``TrackerConfig()``, the IMM filter).

    Returns:
        The names, in PyTree order.
    """
    if config is not None and not isinstance(config, TrackerConfig):
        raise TypeError(f"config must be a phjax.TrackerConfig, got {type(config).__name__}")
    return tuple(_names(_leaf_paths(TrackerConfig() if config is None else config)))


def default_parameters(config: TrackerConfig | None = None) -> tuple[str, ...]:
    """The parameters :func:`tune_tracker` tunes when none are named.

    * single-model filter: :data:`DEFAULT_PARAMETERS` (its process and measurement noise, the
      horizon);
    * IMM filter: every model's ``log_q`` (position and rotation), ``log_switch_rate`` and the
      ``horizon``; with ``rotation_horizon`` set, that too. The measurement noise stays as configured: it is a property of the sensor
      (known, or estimated with :func:`phjax.tracking.noise.estimate_measurement_noise`), and
      tuned together with the process noise it leaves a nearly flat direction. Tuning may
      reorder the models' densities; ``TrackerConfig.adapt`` assumes the quietest model first.

    Arguments:
        config: the configuration (default ``TrackerConfig()``).

    Returns:
        Parameter names accepted by :func:`make_problem` and :func:`tune_tracker`.
    """
    config = TrackerConfig() if config is None else config
    # an orientation horizon of its own is tuned beside the horizon
    own = ("rotation_horizon",) if config.rotation_horizon is not None else ()
    if config.imm is None:
        return (*DEFAULT_PARAMETERS, *own)
    models = [f"imm.{part}.{i}.log_q" for part in ("position_models", "rotation_models")
              for i in range(len(getattr(config.imm, part)))]
    return (*models, "log_switch_rate", "horizon", *own)


def _resolve(config: TrackerConfig, parameters: Sequence[str]) -> tuple[tuple, ...]:
    """Attribute / index paths of the named parameters (validated)."""
    if isinstance(parameters, str):
        parameters = (parameters,)
    paths = _float_leaf_paths(config)
    unknown = [p for p in parameters if p not in paths]
    if unknown:
        hint = ""
        if config.imm is not None and set(unknown) & set(tunable_parameters(
                TrackerConfig(imm=None, kalman=config.kalman))):
            hint = (" (single-model filter parameters: this configuration uses the IMM; "
                    "TrackerConfig(imm=None) selects the single-model filter)")
        raise ValueError(f"unknown tracker parameter(s) {unknown}{hint}; tunable float leaves "
                         f"are {list(tunable_parameters(config))}")
    if len(parameters) == 0:
        raise ValueError("no parameter to tune")
    resolved = tuple(paths[p] for p in parameters)
    if len(set(resolved)) != len(resolved):
        raise ValueError(f"parameters named twice: {list(parameters)}")
    return resolved


def check_parameters(config: TrackerConfig, parameters: Sequence[str]) -> tuple[str, ...]:
    """Validate parameter names for ``config`` (as :func:`make_problem` does, without data).

    Arguments:
        config: the configuration to tune.
        parameters: names (short or dotted, see :func:`tunable_parameters`).

    Returns:
        The names as a tuple.

    Raises:
        ValueError: unknown, repeated or no names.
    """
    parameters = (parameters,) if isinstance(parameters, str) else tuple(parameters)
    _resolve(config, parameters)
    return parameters


def _get(tree, path):
    for key in path:
        tree = tree[key] if isinstance(key, int) else getattr(tree, key)
    return tree


def _with_values(config: TrackerConfig, paths, values) -> TrackerConfig:
    return eqx.tree_at(lambda c: [_get(c, p) for p in paths], config, list(values))


def _arrays_config(config: TrackerConfig, dtype) -> TrackerConfig:
    """``config`` with every float leaf a 0-d array of ``dtype`` (dynamic under ``filter_jit``)."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype) if _is_float_leaf(x) else x, config)


def _check_positive(config: TrackerConfig, paths) -> None:
    for p in paths:
        v = _get(config, p)
        if not _is_log(p) and not np.all(np.asarray(v) > 0):
            raise ValueError(f"{_dotted(p)} = {v}: tuned parameters must be positive "
                             "(they are optimised in log space)")


def _leaf_values(paths, y, xp):
    """Leaf values from log-parameters ``y`` (``xp``: ``jnp`` inside traces, ``np`` outside)."""
    return [y[i] if _is_log(p) else xp.exp(y[i]) for i, p in enumerate(paths)]
