"""Tracker latency and throughput, against named baselines, in one run.

    python benchmarks/bench_tracker.py [--minutes 10] [--repeats 200]

Tables:
1. Streaming latency (jitted, CPU, after warm-up; median and p90 over ``--repeats`` calls):
   ``tracker_update`` (one camera frame) and ``tracker_sample`` (one render time), against the
   jit dispatch floor (``jit(lambda x: x + 1)``). Targets: update <= 50 us, sample <= 10 us.
2. Whole-recording throughput: ``phjax.track`` over a ``--minutes`` recording at 30 Hz rendered
   at 120 Hz, against the NumPy One Euro loop (``one_euro_numpy``), the JAX One Euro scan, the
   Kalman CV extrapolation and raw hold; times and ratios to the NumPy One Euro baseline.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import phjax as pj
from phjax import baselines, simulate, tracker


def _median_us(fn, repeats):
    fn()  # warm-up / compile
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts) * 1e6
    return float(np.median(ts)), float(np.percentile(ts, 90))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args(argv)
    print(f"# phjax tracker benchmark (jax {jax.__version__}, {os.cpu_count()} CPUs, "
          f"dtype {jnp.zeros(()).dtype})\n")

    cfg = pj.TrackerConfig()
    state = pj.tracker_init(cfg)
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.normal(size=3) * 0.01, jnp.float32)
    q = jnp.asarray([1.0, 0, 0, 0], jnp.float32)
    state = pj.tracker_update(cfg, state, 0.0, p, q)
    box = {"s": state, "t": 0.0}

    def upd():
        box["t"] += 1 / 30
        box["s"] = pj.tracker_update(cfg, box["s"], box["t"], p, q)
        jax.block_until_ready(box["s"].t0)

    def smp():
        out = pj.tracker_sample(cfg, box["s"], box["t"] + 0.004)
        jax.block_until_ready(out)

    t_dev = jnp.asarray(0.004, jnp.float32)

    def smp_dev():
        out = pj.tracker_sample(cfg, box["s"], t_dev)
        jax.block_until_ready(out)

    floor = jax.jit(lambda x: x + 1)
    x0 = jnp.zeros(())

    def flo():
        jax.block_until_ready(floor(x0))

    rows = [("jit dispatch floor", *_median_us(flo, args.repeats), "-"),
            ("tracker_update (camera frame)", *_median_us(upd, args.repeats), "<= 50"),
            ("tracker_sample (render sample, Python float time)", *_median_us(smp, args.repeats), "<= 10"),
            ("tracker_sample (render sample, device-array time)", *_median_us(smp_dev, args.repeats), "<= 10")]
    print("| call | median [us] | p90 [us] | target [us] |\n|---|---|---|---|")
    for name, med, p90, target in rows:
        print(f"| {name} | {med:.1f} | {p90:.1f} | {target} |")
    print(f"\n(update compiled {tracker.tracker_update._cache_size()}x, "
          f"sample {tracker._sample_render._cache_size()}x over {args.repeats + 1} calls)\n")

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
    print(f"recording: {args.minutes:g} min, {len(mt)} frames at 30 Hz -> {len(render)} render samples at 120 Hz\n")
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
