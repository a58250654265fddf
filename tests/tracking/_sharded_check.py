"""Sharded batch check, run by ``test_batch.py`` in a fresh process with 4 simulated CPU devices.

Usage: ``XLA_FLAGS=--xla_force_host_platform_device_count=4 python _sharded_check.py data.npz``.
Reads a NaN-padded batch of recordings and the one-at-a-time results of ``track`` and
``reconstruct`` (computed by the test in its own process), runs the batch sharded over a 1-D mesh
of all devices through ``track``, ``reconstruct``, ``sample``, ``sample_into`` and
``optimize_shape``, and prints one JSON line: per output its sharding (partition spec, devices
holding a shard, shard shapes) and the largest difference from the reference (for
``optimize_shape``: the largest distance of the curves' ends from the end points).
"""

from __future__ import annotations

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import phjax as pj


def layout(x) -> dict:
    shards = x.addressable_shards
    return {"spec": [None if a is None else str(a) for a in x.sharding.spec],
            "devices": len({s.device for s in shards}),
            "shard_shapes": sorted({tuple(s.data.shape) for s in shards})}


def diff(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        return float("inf")
    return float(np.nanmax(np.abs(a - b))) if np.isfinite(a).any() else 0.0


def main(path: str) -> None:
    d = np.load(path)
    mesh = pj.batch_mesh()
    out = {"num_devices": len(jax.devices())}
    batch = pj.shard_batch((d["times"], d["positions"], d["quaternions"], d["render_times"]), mesh)
    for name, fn in (("track", pj.track), ("reconstruct", pj.reconstruct)):
        p, q = fn(*batch)
        out[name] = {"position": layout(p), "quaternion": layout(q),
                     "diff": max(diff(p, d[name + "_p"]), diff(q, d[name + "_q"]))}
    try:  # only part of the batch sharded: a clear error, before any compilation
        pj.track(batch[0], d["positions"], d["quaternions"], d["render_times"])
        out["partial_error"] = ""
    except ValueError as err:
        out["partial_error"] = str(err)
    rng = np.random.default_rng(1)
    ends = [rng.normal(size=(8, 3)) for _ in range(4)]
    curves = pj.hermite_quintic(*ends)
    sharded = pj.shard_batch(curves, mesh)
    for by in ("time", "arclength"):
        t_ref, p_ref = pj.sample(curves, 17, by=by)
        t, p = pj.sample(sharded, 17, by=by)
        out["sample_" + by] = {"points": layout(p), "t": layout(t),
                               "diff": max(diff(p, p_ref), diff(t, t_ref))}
    try:  # replicated curves into a sharded buffer: an error (it returned the batch 4 times)
        pj.sample_into(curves, pj.shard_batch(jnp.zeros((8, 17, 3)), mesh))
        out["sample_into_partial_error"] = ""
    except ValueError as err:
        out["sample_into_partial_error"] = str(err)
    buf = pj.shard_batch(jnp.zeros((8, 17, 3)), mesh)
    _, p = pj.sample_into(sharded, buf)
    out["sample_into"] = {"points": layout(p), "diff": diff(p, pj.sample(curves, 17)[1]),
                          "donated": bool(buf.is_deleted())}
    # optimize_shape: sharded like its inputs, and the curves interpolate the end data
    c, s = pj.optimize_shape(*pj.shard_batch(tuple(jnp.asarray(e) for e in ends), mesh),
                             num_starts=2, max_steps=8)
    cp = np.asarray(c.control_points)
    out["optimize_shape"] = {"control_points": layout(c.control_points), "phi0": layout(s.phi0),
                             "end_error": float(max(np.abs(cp[:, 0] - ends[0]).max(),
                                                    np.abs(cp[:, -1] - ends[1]).max()))}
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
