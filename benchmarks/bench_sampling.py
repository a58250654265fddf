"""Sampling at memory speed: ``sample`` vs donated buffers vs chunks, against a memory fill.

Usage (from the repository root)::

    python benchmarks/bench_sampling.py [--curves 100000] [--samples 100] [--devices 1,2,4]
                                        [--dtype float32|float64] [--repeats 5] [--quick]

Prints Markdown tables:

* ``throughput`` (one device): samples/s (one sample = one 3-D point) of
  :func:`phjax.sample` (fresh output arrays on every call, parameters included, as the API
  returns them), :func:`phjax.sample_into` (points written into a donated buffer that the
  next call reuses) and :func:`phjax.sample_chunks` (the batch in 8 chunks through a ring of
  two donated buffers), next to the **memory fill** measured in the same run: a jitted
  ``jnp.full_like`` into a donated buffer of the points' byte size (a pure write of the same
  number of bytes into memory that is already mapped). "fill" columns convert its bytes/s to
  samples/s (``3 * itemsize`` bytes per sample); "of fill" = samples/s / fill samples/s.
* ``scaling``: ``sample_into`` with the curves and the buffer sharded over a 1-D mesh of
  1, 2, 4 devices (:func:`phjax.batch.shard_batch`), each count in a child process. On a CPU
  the devices are simulated (``XLA_FLAGS=--xla_force_host_platform_device_count=d``, which
  splits the host's cores between the devices); on a GPU the first ``d`` real devices are
  used and counts above the number of GPUs are skipped. Each row also measures the sharded
  fill (same bytes, same sharding) and the speed-up over one device.

Timings: ``time.perf_counter`` around calls blocked with ``block_until_ready`` after two
warm-up calls; "best" is the minimum over ``--repeats``, "median" the median. Compile time is
excluded. On a shared machine absolute numbers are noisy: compare ratios within a run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--curves", type=int, default=100_000, help="number of curves")
    p.add_argument("--samples", type=int, default=100, help="samples per curve")
    p.add_argument("--devices", default="1,2,4", help="device counts of the scaling table")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="1e4 curves, 3 repeats (smoke test)")
    p.add_argument("--worker", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick:
        args.curves, args.repeats = 10_000, 3
    args.devices = [int(d) for d in args.devices.split(",") if d.strip()]
    return args


def _setup(dtype):
    import jax

    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    return jax


def _curves(n_curves, dtype):
    import jax.numpy as jnp

    import phjax as pj

    rng = np.random.default_rng(0)
    ends = [jnp.asarray(rng.normal(size=(n_curves, 3)), dtype) for _ in range(4)]
    return pj.hermite_quintic(*ends)


def _time(fn, repeats):
    """Best and median seconds of ``fn()`` (which blocks) after two warm-up calls."""
    fn()
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), float(np.median(ts))


def _fill_runner(shape, dtype, sharding=None):
    """A blocked call writing a donated buffer of ``shape`` (the memory-fill reference)."""
    import jax
    import jax.numpy as jnp

    # keep_unused: the buffer is only donated, never read (an unused argument would be pruned
    # and the fill would write fresh memory on every call)
    fill = jax.jit(lambda b: jnp.full_like(b, 1.0), donate_argnums=0, keep_unused=True,
                   out_shardings=sharding)
    state = {"buf": jnp.zeros(shape, dtype) if sharding is None
             else jax.device_put(jnp.zeros(shape, dtype), sharding)}

    def run():
        old = state["buf"]
        state["buf"] = fill(old)
        state["buf"].block_until_ready()
        assert old.is_deleted()  # written in place

    return run


def throughput(args):
    jax = _setup(args.dtype)
    import jax.numpy as jnp

    import phjax as pj

    dtype = jnp.dtype(args.dtype)
    curves = _curves(args.curves, dtype)
    n, total = args.samples, args.curves * args.samples
    shape = (args.curves, n, 3)
    rows = []

    def run_sample():
        jax.block_until_ready(pj.sample(curves, n))

    state = {"pts": jnp.zeros(shape, dtype)}

    def run_into():
        _, state["pts"] = pj.sample_into(curves, state["pts"])
        state["pts"].block_until_ready()

    chunk = -(-args.curves // 8)

    def run_chunks():
        for _, _, p in pj.sample_chunks(curves, n, chunk):
            p.block_until_ready()

    fill = _time(_fill_runner(shape, dtype), args.repeats)
    fill_rate = total / fill[0]
    for name, fn in (("phjax.sample (fresh output)", run_sample),
                     ("phjax.sample_into (donated buffer)", run_into),
                     ("phjax.sample_chunks (8 chunks, 2 buffers)", run_chunks),
                     ("memory fill (donated jnp.full_like)", None)):
        best, med = fill if fn is None else _time(fn, args.repeats)
        rows.append((name, best, med, total / best, total / best / fill_rate))
    print(f"\n## throughput: {args.curves} curves x {n} samples, {args.dtype}, "
          f"{jax.devices()[0].platform} ({len(jax.devices())} device(s) visible, 1 used)\n")
    print(f"points buffer {np.prod(shape) * dtype.itemsize / 2**20:.1f} MiB; "
          f"fill = {fill_rate / 1e6:.1f} M samples/s "
          f"({fill_rate * 3 * dtype.itemsize / 1e9:.2f} GB/s)\n")
    print("| method | best ms | median ms | M samples/s | of fill |")
    print("|---|---:|---:|---:|---:|")
    for name, best, med, rate, frac in rows:
        print(f"| {name} | {1e3 * best:.2f} | {1e3 * med:.2f} | {rate / 1e6:.1f} | {100 * frac:.0f} % |")


def worker(args):
    """One row of the scaling table (run in a child process with ``d`` devices)."""
    jax = _setup(args.dtype)
    import jax.numpy as jnp

    import phjax as pj

    d = args.worker
    devices = jax.devices()
    if len(devices) < d:
        print(json.dumps({"devices": d, "available": len(devices)}))
        return
    dtype = jnp.dtype(args.dtype)
    mesh = pj.batch_mesh(devices[:d])
    sharding = pj.batch.batch_sharding(mesh)
    curves = pj.shard_batch(_curves(args.curves, dtype), mesh)
    shape = (args.curves, args.samples, 3)
    state = {"pts": jax.device_put(jnp.zeros(shape, dtype), sharding)}

    def run_into():
        _, state["pts"] = pj.sample_into(curves, state["pts"])
        state["pts"].block_until_ready()

    best, med = _time(run_into, args.repeats)
    fill, _ = _time(_fill_runner(shape, dtype, sharding), args.repeats)
    assert len({s.device for s in state["pts"].addressable_shards}) == d
    print(json.dumps({"devices": d, "available": len(devices), "best": best, "median": med,
                      "fill": fill, "platform": devices[0].platform,
                      "spec": str(state["pts"].sharding.spec)}))


def scaling(args):
    import jax

    platform_name = jax.devices()[0].platform
    total = args.curves * args.samples
    print(f"\n## scaling: sample_into sharded over a 1-D mesh, {args.curves} curves x "
          f"{args.samples} samples, {args.dtype}, {platform_name}"
          f"{' (simulated devices)' if platform_name == 'cpu' else ''}\n")
    print("| devices | best ms | median ms | M samples/s | speed-up | sharded fill M samples/s "
          "| of fill |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    base = None
    for d in args.devices:
        if args.curves % d:
            print(f"| {d} | (skipped: {args.curves} curves do not split into {d}) |||||")
            continue
        env = dict(os.environ)
        if platform_name == "cpu":
            flags = env.get("XLA_FLAGS", "")
            env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={d}".strip()
        cmd = [sys.executable, __file__, "--worker", str(d), "--curves", str(args.curves),
               "--samples", str(args.samples), "--dtype", args.dtype,
               "--repeats", str(args.repeats)]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"| {d} | (failed: {proc.stderr.strip().splitlines()[-1][:80]}) |||||")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        if "best" not in r:
            print(f"| {d} | (skipped: {r['available']} device(s) available) |||||")
            continue
        base = r["best"] if base is None else base
        print(f"| {d} | {1e3 * r['best']:.2f} | {1e3 * r['median']:.2f} | "
              f"{total / r['best'] / 1e6:.1f} | {base / r['best']:.2f} | "
              f"{total / r['fill'] / 1e6:.1f} | {100 * r['fill'] / r['best']:.0f} % |")


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        worker(args)
        return
    import jax

    print("# bench_sampling")
    print(f"\nmachine: {platform.machine()}, {os.cpu_count()} CPUs, load "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}; python {platform.python_version()}, "
          f"jax {jax.__version__}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}; "
          f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '')!r}")
    throughput(args)
    scaling(args)


if __name__ == "__main__":
    main()
