"""Tracker latency and throughput, against named baselines, in one run.

    python benchmarks/bench_tracker.py [--minutes 10] [--repeats 2000]

Tables:
1. Streaming latency (jitted, CPU, after warm-up; median and p90 over ``--repeats`` calls) with
   JAX's default asynchronous dispatch: ``tracker_update`` (one camera frame; config of Python
   floats, and converted once with ``tracker_config_arrays``), ``tracker_sample`` (one render
   time), and the same two calls of the real-time driver ``TrackerStream`` (state and config
   packed into a few vectors: few buffers cross the jit boundary), against the jit dispatch
   floor (``jit(lambda x: x + 1)``). Targets: update <= 50 us, sample <= 10 us.
2. The same in a child process with ``jax_cpu_enable_async_dispatch=False`` (computations run
   in the calling thread instead of being handed to a worker thread; must be set before the
   first computation, hence the subprocess).
3. Whole-recording throughput: ``phjax.track`` over a ``--minutes`` recording at 30 Hz rendered
   at 120 Hz, against the NumPy One Euro loop (``one_euro_numpy``), the JAX One Euro scan, the
   Kalman CV extrapolation and raw hold; times and ratios to the NumPy One Euro baseline.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import phjax as pj
from phjax.tracking import baselines
from phjax.motion import simulate
from phjax.tracking import tracker


def _median_us(fn, repeats):
    fn()  # warm-up / compile
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts) * 1e6
    return float(np.median(ts)), float(np.percentile(ts, 90))


def _latency(repeats):
    """Rows ``(call, median us, p90 us, target)`` of the streaming latency table."""
    cfg = pj.TrackerConfig()
    cfg_arrays = pj.tracker_config_arrays(cfg)
    state = pj.tracker_init(cfg)
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.normal(size=3) * 0.01, jnp.float32)
    q = jnp.asarray([1.0, 0, 0, 0], jnp.float32)
    state = pj.tracker_update(cfg, state, 0.0, p, q)
    box = {"s": state, "t": 0.0}

    def upd(c):
        def fn():
            box["t"] += 1 / 30
            box["s"] = pj.tracker_update(c, box["s"], box["t"], p, q)
            jax.block_until_ready(box["s"])
        return fn

    def smp():
        jax.block_until_ready(pj.tracker_sample(cfg, box["s"], box["t"] + 0.004))

    t_dev = jnp.asarray(0.004, jnp.float32)

    def smp_dev():
        jax.block_until_ready(pj.tracker_sample(cfg, box["s"], t_dev))

    stream = pj.TrackerStream(cfg, dtype=jnp.float32)
    stream.update(0.0, p, q)
    sbox = {"t": 0.0}

    def stream_upd():
        sbox["t"] += 1 / 30
        stream.update(sbox["t"], p, q)
        jax.block_until_ready(stream._packed)

    def stream_smp():
        jax.block_until_ready(stream.sample(t_dev))

    floor = jax.jit(lambda x: x + 1)
    x0 = jnp.zeros(())

    def flo():
        jax.block_until_ready(floor(x0))

    return [("jit dispatch floor", *_median_us(flo, repeats), "-"),
            ("tracker_update (camera frame, config of Python floats)", *_median_us(upd(cfg), repeats), "<= 50"),
            ("tracker_update (camera frame, `tracker_config_arrays(config)`)",
             *_median_us(upd(cfg_arrays), repeats), "<= 50"),
            ("tracker_sample (render sample, Python float time)", *_median_us(smp, repeats), "<= 10"),
            ("tracker_sample (render sample, device-array time)", *_median_us(smp_dev, repeats), "<= 10"),
            ("`TrackerStream.update` (camera frame, packed state)", *_median_us(stream_upd, repeats), "<= 50"),
            ("`TrackerStream.sample` (render sample, device-array time)", *_median_us(stream_smp, repeats), "<= 10")]


def _print_latency(rows, title):
    print(f"{title}\n\n| call | median [us] | p90 [us] | target [us] |\n|---|---|---|---|")
    for name, med, p90, target in rows:
        print(f"| {name} | {med:.1f} | {p90:.1f} | {target} |")
    print(f"\n(update compiled {tracker.tracker_update._cache_size()}x, "
          f"sample {tracker._sample_render._cache_size()}x)\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="recording length for table 3")
    ap.add_argument("--repeats", type=int, default=2000, help="calls per latency row")
    ap.add_argument("--sync-dispatch", action="store_true",
                    help="only the latency table, with jax_cpu_enable_async_dispatch=False")
    args = ap.parse_args(argv)
    if args.sync_dispatch:  # must precede the process's first computation
        jax.config.update("jax_cpu_enable_async_dispatch", False)
        _print_latency(_latency(args.repeats), "2. Streaming latency, synchronous dispatch "
                       "(`jax.config.update(\"jax_cpu_enable_async_dispatch\", False)`)")
        return 0
    print(f"# phjax tracker benchmark (jax {jax.__version__}, {os.cpu_count()} CPUs, "
          f"dtype {jnp.zeros(()).dtype})\n")
    _print_latency(_latency(args.repeats), "1. Streaming latency, JAX's default (asynchronous) dispatch")
    sys.stdout.flush()
    subprocess.run([sys.executable, __file__, "--sync-dispatch", "--repeats", str(args.repeats)], check=True)

    dur = args.minutes * 60
    gt_t, gt_p, gt_q = simulate.synthetic_head_motion(duration=dur, rate=120.0, seed=0)
    mt, mp, mq = (np.asarray(x, np.float64) for x in simulate.simulate_measurements(0, gt_t, gt_p, gt_q))
    render = np.arange(mt[0], mt[-1], 1 / 120)
    methods = [
        ("one_euro_numpy (NumPy loop, baseline)", lambda: baselines.one_euro_numpy(mt, mp, mq, render, min_cutoff=1.0, beta=1.0)),
        ("phjax.track (causal stream)", lambda: pj.track(mt, mp, mq, render)),
        ("phjax.reconstruct (offline)", lambda: pj.reconstruct(mt, mp, mq, render)),
        ("one_euro (JAX scan)", lambda: baselines.one_euro(mt, mp, mq, render, min_cutoff=1.0, beta=1.0)),
        ("kalman_extrapolation", lambda: baselines.kalman_extrapolation(mt, mp, mq, render)),
        ("hold", lambda: baselines.hold(mt, mp, mq, render)),
    ]
    print(f"3. Whole recording: {args.minutes:g} min, {len(mt)} frames at 30 Hz -> {len(render)} render samples at 120 Hz\n")
    print("| method | first call [s] | warm [s] | frames/s | x NumPy One Euro |\n|---|---|---|---|---|")
    base = None
    for name, fn in methods:
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        warm = min(_timed(fn) for _ in range(3))
        base = warm if base is None else base
        print(f"| {name} | {first:.2f} | {warm:.3f} | {len(mt) / warm:,.0f} | {base / warm:.2f} |")
    return 0


def _timed(fn):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0


if __name__ == "__main__":
    raise SystemExit(main())
