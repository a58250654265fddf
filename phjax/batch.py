"""Batches of recordings: NaN padding to a common length, sharding over a 1-D device mesh.

**Padding rule.** A batch of recordings is a set of arrays with leading batch axes ``*B``:
``times (*B, N)``, ``positions (*B, N, 3)``, ``quaternions (*B, N, 4)``, and for the batch entry
points also ``render_times (*B, M)``. Shorter recordings are padded at the end with NaN
(:func:`pad_recordings`):

* a frame whose **time** is NaN is a padding frame; it counts as a lost frame (like a frame
  with NaN position and orientation) and never moves the stream. Padding frames must come
  after every real frame of their recording;
* a NaN **render time** gives a NaN sample (position and quaternion);
* a recording made only of padding gives NaN everywhere.

The batched entry points (:func:`phjax.track`, :func:`phjax.reconstruct`,
:func:`phjax.simulate_measurements`, the metrics of :mod:`phjax.evaluation.metrics`, the tuning
loss) give each recording the result it would get alone, trimmed of its padding.

**Sharding.** :func:`batch_mesh` builds a 1-D mesh over the devices (axis ``"batch"``) and
:func:`shard_batch` places the arrays of a PyTree on it, split along axis 0. The batched entry
points (:func:`phjax.track`, :func:`phjax.reconstruct`, :func:`phjax.sample`,
:func:`phjax.optimize_shape`) recognise arguments sharded that way and run one program per
device on its own part of the batch (``jax.shard_map``): no data crosses devices and the
outputs come back sharded the same way. Arguments that are not sharded along the batch axis
(configs, shared render times, scalars) are replicated on every device. On several hosts
(``jax.distributed.initialize()``), :func:`shard_local_batch` assembles the global batch
from each process's own recordings.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike

from ._jit import jit
from ._misc import check_count

__all__ = [
    "BATCH_AXIS",
    "batch_mesh",
    "batch_sharding",
    "pad_recordings",
    "recording_lengths",
    "shard_batch",
    "shard_local_batch",
    "unpad",
]

#: Name of the mesh axis along which :func:`batch_mesh` / :func:`shard_batch` split a batch.
BATCH_AXIS = "batch"


# ------------------------------------------------------------------------------------ padding
def pad_recordings(*columns: Sequence[ArrayLike], length: int | Sequence[int] | None = None,
                   multiple_of: int = 1) -> tuple[np.ndarray, ...]:
    """Stack recordings of different lengths into NaN-padded batch arrays.

    Arguments:
        *columns: one sequence per quantity, each with one array per recording, e.g.
            ``pad_recordings(times_list, positions_list, quaternions_list, render_times_list)``.
            Each column is padded on its own along axis 0 (render times may be longer than
            the frames); the trailing axes must agree within a column.
        length: padded length of axis 0, one for every column or one per column (default:
            the longest array of each column).
        multiple_of: pad the number of recordings with all-NaN recordings up to a multiple of
            this (e.g. the number of devices of a mesh, see :func:`shard_batch`).

    Returns:
        One float64 array per column, ``(R, N_column, ...)``, NaN after each recording's end
        (the padding rule of :mod:`phjax.batch`).
    """
    if not columns:
        raise ValueError("pad_recordings needs at least one column")
    n_rec = len(columns[0])
    if n_rec == 0 or any(len(c) != n_rec for c in columns):
        raise ValueError("every column needs the same, non-zero number of recordings")
    if length is None or np.ndim(length) == 0:
        length = [length] * len(columns)
    if len(length) != len(columns):
        raise ValueError(f"length: expected one value per column ({len(columns)}), got {length}")
    multiple_of = check_count(multiple_of, "multiple_of")
    r = -(-n_rec // multiple_of) * multiple_of
    out = []
    for k, (col, n) in enumerate(zip(columns, length)):
        arrs = [np.asarray(a, np.float64) for a in col]
        for i, a in enumerate(arrs):
            if a.ndim == 0 or a.shape[1:] != arrs[0].shape[1:]:
                raise ValueError(f"column {k}, recording {i}: shape {a.shape} does not match "
                                 f"(n, *{arrs[0].shape[1:]})")
        longest = max(a.shape[0] for a in arrs)
        n = longest if n is None else int(n)
        if n < longest:
            raise ValueError(f"column {k}: length {n} is shorter than its longest recording "
                             f"({longest})")
        arr = np.full((r, n) + arrs[0].shape[1:], np.nan)
        for i, a in enumerate(arrs):
            arr[i, :a.shape[0]] = a
        out.append(arr)
    return tuple(out)


def recording_lengths(times: ArrayLike) -> np.ndarray:
    """Number of real (non-padding) frames of each recording of a padded batch ``(*B, N)``."""
    return np.sum(np.isfinite(np.asarray(times)), axis=-1)


def unpad(times: ArrayLike, *columns: ArrayLike) -> list[tuple[np.ndarray, ...]]:
    """Split a padded batch back into recordings (NumPy, flattened over the batch axes).

    Arguments:
        times: ``(*B, N)`` padded times (NaN = padding).
        *columns: arrays ``(*B, N, ...)`` of the same batch.

    Returns:
        For each recording (row-major over ``B``) the tuple ``(times, *columns)`` trimmed to
        its real frames.
    """
    t = np.asarray(times)
    b = t.shape[:-1]
    t = t.reshape((-1, t.shape[-1]))
    cols = [np.asarray(c).reshape((t.shape[0],) + np.shape(c)[len(b):]) for c in columns]
    out = []
    for i in range(t.shape[0]):
        keep = np.isfinite(t[i])
        out.append((t[i][keep],) + tuple(c[i][keep] for c in cols))
    return out


# ----------------------------------------------------------------------------------- sharding
def batch_mesh(devices: Sequence | None = None, axis_name: str = BATCH_AXIS) -> Mesh:
    """A 1-D device mesh for batch parallelism.

    Arguments:
        devices: the devices (default ``jax.devices()``: every device of every process).
        axis_name: name of the mesh axis (default ``"batch"``).

    Returns:
        A :class:`jax.sharding.Mesh` of shape ``(len(devices),)`` with an ``Auto`` axis (JAX
        inserts the communication that ordinary operations on sharded results need).
    """
    devices = jax.devices() if devices is None else list(devices)
    if len(devices) == 0:
        raise ValueError("batch_mesh needs at least one device")
    # Auto (not Explicit) axis: ordinary indexing and reductions of sharded results just work
    return jax.make_mesh((len(devices),), (axis_name,), axis_types=(AxisType.Auto,),
                         devices=devices)


def batch_sharding(mesh: Mesh | None = None, axis_name: str | None = None) -> NamedSharding:
    """The sharding that splits axis 0 of an array over ``mesh`` (default :func:`batch_mesh`).

    ``axis_name`` defaults to the mesh's first axis.
    """
    mesh = batch_mesh() if mesh is None else mesh
    axis = mesh.axis_names[0] if axis_name is None else axis_name
    return NamedSharding(mesh, PartitionSpec(axis))


def _n_shards(sharding: NamedSharding) -> int:
    """Number of parts axis 0 is split into (the product of the mesh axes it is split over)."""
    axes = sharding.spec[0]
    axes = axes if isinstance(axes, tuple) else (axes,)
    return int(np.prod([sharding.mesh.shape[a] for a in axes]))


def _check_divisible(shape, n_shards, what):
    if len(shape) == 0 or shape[0] % n_shards:
        raise ValueError(f"{what}: batch axis of shape {tuple(shape)} does not split into "
                         f"{n_shards} equal parts (pad it: pad_recordings(..., "
                         f"multiple_of={n_shards}))")


def shard_batch(tree, mesh: Mesh | None = None, axis_name: str | None = None):
    """Place every array of a PyTree on ``mesh``, split along axis 0 (the batch axis).

    Arguments:
        tree: arrays (NumPy or JAX) with a common leading batch axis whose length is a
            multiple of the mesh size; ``None`` leaves stay ``None``.
        mesh: the mesh (default :func:`batch_mesh` over all devices).
        axis_name: mesh axis to split along (default: the mesh's first axis).

    Returns:
        The same PyTree of ``jax.Array`` with sharding ``NamedSharding(mesh, P(axis_name))``.
    """
    sharding = batch_sharding(mesh, axis_name)
    n = _n_shards(sharding)
    for leaf in jax.tree.leaves(tree):
        _check_divisible(np.shape(leaf), n, "shard_batch")
    return jax.device_put(tree, sharding)


def shard_local_batch(tree, mesh: Mesh | None = None, axis_name: str | None = None):
    """Assemble a global batch sharded over all hosts from each process's local part.

    For multi-process runs (``jax.distributed.initialize()``): each process passes its own
    recordings (the same local batch size on every process, a multiple of its local device
    count); the result is one global array per leaf, axis 0 the concatenation over processes
    (``jax.make_array_from_process_local_data``). With one process it equals
    :func:`shard_batch`.
    """
    sharding = batch_sharding(mesh, axis_name)
    n_local = len(sharding.mesh.local_devices)
    for leaf in jax.tree.leaves(tree):
        _check_divisible(np.shape(leaf), n_local, "shard_local_batch")
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, x), tree)


def _leading_sharding(tree) -> NamedSharding | None:
    """The :class:`NamedSharding` of the first array leaf split along axis 0 over more than one
    device (``None`` when no leaf is: the input is not batch-sharded)."""
    for leaf in jax.tree.leaves(tree):
        s = getattr(leaf, "sharding", None)
        if (isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer)
                and isinstance(s, NamedSharding) and len(s.spec) > 0 and s.spec[0] is not None
                and s.num_devices > 1):
            return s
    return None


def _is_batch_sharded(leaf, sharding: NamedSharding) -> bool:
    s = getattr(leaf, "sharding", None)
    return (isinstance(leaf, jax.Array) and isinstance(s, NamedSharding) and s.mesh == sharding.mesh
            and len(s.spec) > 0 and s.spec[0] == sharding.spec[0])


def _require_batch_sharded(tree, sharding: NamedSharding, message: str) -> None:
    """``ValueError(message)`` unless every array leaf of ``tree`` is split along ``sharding``'s
    batch axis on its mesh (a replicated leaf beside split ones would be taken whole on every
    device: outputs with the batch repeated once per device)."""
    leaves = [x for x in jax.tree.leaves(tree) if isinstance(x, jax.Array)]
    if not all(_is_batch_sharded(x, sharding) for x in leaves):
        raise ValueError(message)


@functools.lru_cache(maxsize=64)
def _shard_mapped(fn: Callable, mesh: Mesh, axis, in_tree, batched: tuple, static: tuple,
                  donate: tuple = ()):
    """``jax.jit(jax.shard_map(fn))`` with batched leaves split along ``axis``, the rest
    replicated, every output leaf split along ``axis`` (cached: one jitted function per
    layout, one compiled program per shape)."""
    fn = functools.partial(fn, **dict(static))
    spec = PartitionSpec(axis)
    in_specs = jax.tree.unflatten(in_tree, [spec if b else PartitionSpec() for b in batched])

    def flat_fn(*args):
        return fn(*args)

    return jit(jax.shard_map(flat_fn, mesh=mesh, in_specs=tuple(in_specs), out_specs=spec,
                             check_vma=False), donate_argnums=donate, keep_unused=bool(donate))


def _sharded_function(fn: Callable, sharding: NamedSharding, args: tuple, static: dict,
                      donate: tuple = ()):
    """The jitted ``shard_map`` of ``fn`` for ``args``: array leaves sharded along
    ``sharding``'s batch axis are split, every other leaf is replicated (it must be a JAX type:
    arrays, numbers, ``None``); every output leaf keeps the batch axis first and comes back
    split the same way. ``static`` values must be hashable and ``fn`` a module-level function
    (both key the cache); ``donate``: positions of ``args`` whose buffers the call may reuse.
    Call the result with ``*args``."""
    leaves, tree = jax.tree.flatten(args)
    batched = tuple(_is_batch_sharded(x, sharding) for x in leaves)
    for x, b in zip(leaves, batched):
        if b:
            _check_divisible(x.shape, _n_shards(sharding), "sharded batch")
    return _shard_mapped(fn, sharding.mesh, sharding.spec[0], tree, batched,
                         tuple(sorted(static.items())), tuple(donate))


def run_sharded(fn: Callable, sharding: NamedSharding, *args, **static):
    """``fn(*args, **static)`` run once per device on its part of the batch (see
    :func:`_sharded_function`)."""
    return _sharded_function(fn, sharding, args, static)(*args)
