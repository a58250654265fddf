"""Tracker latency and throughput, against named baselines, in one run.

    python benchmarks/bench_tracker.py [--minutes 10] [--repeats 2000] [--compare /work/main]

Tables:
1. Streaming latency (jitted, CPU, float32, after warm-up; median and p99 over ``--repeats``
   calls) of one camera update and one render sample, with the default config (IMM filter),
   the single-model config (``TrackerConfig(imm=None)``) and the config of ``phjax live``
   (``phjax.live.live_tracker_config()``: single model, innovation gate, the online noise
   floor ``noise_window=60``): the real-time driver
   ``TrackerStream.update`` / ``.sample`` and the pure jitted ``tracker_update`` (config
   converted once with ``tracker_config_arrays``) / ``tracker_sample``, each with JAX's default
   asynchronous dispatch and with ``jax_cpu_enable_async_dispatch=False`` (computations in the
   calling thread; must be set before the first computation, hence one child process per
   setting), next to the jit dispatch floor (``jit(lambda x: x + 1)``). Targets: update
   <= 200 us, sample <= 20 us (issue 16: ample for a 30 Hz camera and a 250 Hz renderer); the
   ratio column is median / target. With ``--compare ROOT`` the same child processes also run
   on the phjax package of another checkout (e.g. the previous hand-packed state), so the two
   versions are measured in one run under the same load.
2. Whole-recording throughput: ``phjax.track`` over a ``--minutes`` recording at 30 Hz rendered
   at 120 Hz, against the NumPy One Euro loop (``one_euro_numpy``), the JAX One Euro scan, the
   Kalman CV extrapolation and raw hold; times and ratios to the NumPy One Euro baseline.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

TARGET_US = {"update": 200.0, "sample": 20.0}


def _stats_us(fn, repeats):
    """``(median, p99)`` in us of ``repeats`` calls of ``fn`` after two warm-up calls."""
    fn()
    fn()
    ts = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts[i] = time.perf_counter() - t0
    ts *= 1e6
    return float(np.median(ts)), float(np.percentile(ts, 99))


def _config_rows(name, cfg, p, q, t_dev, repeats):
    """Latency rows of the stream and the pure functions for one config."""
    import phjax as pj

    cfg_arrays = pj.tracker_config_arrays(cfg, jnp.float32)
    box = {"s": pj.tracker_update(cfg_arrays, pj.tracker_init(cfg, 0.0, jnp.float32), 0.0, p, q),
           "t": 0.0}

    def upd():
        box["t"] += 1 / 30
        box["s"] = pj.tracker_update(cfg_arrays, box["s"], box["t"], p, q)
        jax.block_until_ready(box["s"])

    def smp():
        jax.block_until_ready(pj.tracker_sample(cfg_arrays, box["s"], t_dev))

    stream = pj.TrackerStream(cfg, dtype=jnp.float32)
    stream.update(0.0, p, q)
    if hasattr(stream, "wait_compiled"):  # fast start: time the optimised program
        stream.wait_compiled()
    sbox = {"t": 0.0}
    # what the stream holds: its state (the previous hand-packed version: its vectors)
    held = (lambda: stream._packed) if hasattr(stream, "_packed") else (lambda: stream.state)

    def stream_upd():
        sbox["t"] += 1 / 30
        stream.update(sbox["t"], p, q)
        jax.block_until_ready(held())

    def stream_smp():
        jax.block_until_ready(stream.sample(t_dev))

    return [(name, "`TrackerStream.update`", "update", *_stats_us(stream_upd, repeats)),
            (name, "`TrackerStream.sample` (one time)", "sample", *_stats_us(stream_smp, repeats)),
            (name, "`tracker_update` (config arrays)", "update", *_stats_us(upd, repeats)),
            (name, "`tracker_sample` (one time)", "sample", *_stats_us(smp, repeats))]


def _latency_rows(repeats):
    """``[(config, call, kind, median us, p99 us)]`` for the default and single-model configs."""
    import phjax as pj

    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.normal(size=3) * 0.01, jnp.float32)
    q = jnp.asarray([1.0, 0, 0, 0], jnp.float32)
    t_dev = jnp.asarray(0.004, jnp.float32)
    floor = jax.jit(lambda x: x + 1)
    x0 = jnp.zeros((), jnp.float32)
    rows = [("-", "jit dispatch floor", "-",
             *_stats_us(lambda: jax.block_until_ready(floor(x0)), repeats))]
    from phjax.live import live_tracker_config

    live = live_tracker_config()  # what phjax live runs: single model, gate, noise floor
    for name, cfg in (("default (IMM)", pj.TrackerConfig()),
                      ("single model (imm=None)", pj.TrackerConfig(imm=None)),
                      (f"live (single model, noise_window={live.noise_window})", live)):
        rows += _config_rows(name, cfg, p, q, t_dev, repeats)
    return rows


def _child_latency(root, sync, repeats):
    """Latency rows measured in a child process on the phjax package under ``root``."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, os.path.abspath(__file__), "--latency-child", "--repeats", str(repeats)]
    if sync:
        cmd.append("--sync-dispatch")
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True, cwd=root)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if not res["phjax"].startswith(root):
        raise RuntimeError(f"the child imported {res['phjax']}, not the phjax under {root}")
    return [tuple(r) for r in res["rows"]]


def _print_latency(results, labels):
    """``results[(label, sync)]`` = rows; one table row per (config, call, dispatch)."""
    cols = "".join(f" {lab} median [us] | {lab} p99 [us] |" for lab in labels)
    print(f"| config | call | dispatch |{cols} target [us] | median / target |")
    print("|---|---|---|" + "---|---|" * len(labels) + "---|---|")
    first = results[(labels[0], False)]
    for i, (cfg, call, kind, _, _) in enumerate(first):
        for sync in (False, True):
            vals = [results[(lab, sync)][i] for lab in labels]
            assert all(v[:3] == (cfg, call, kind) for v in vals)
            cells = "".join(f" {v[3]:.1f} | {v[4]:.1f} |" for v in vals)
            target = TARGET_US.get(kind)
            ratio = f"{vals[0][3] / target:.2f}" if target else "-"
            print(f"| {cfg} | {call} | {'sync' if sync else 'async'} |{cells} "
                  f"{target if target else '-'} | {ratio} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="recording length for table 2")
    ap.add_argument("--repeats", type=int, default=2000, help="calls per latency row (>= 2000 for a p99)")
    ap.add_argument("--compare", metavar="ROOT", default=None,
                    help="also measure the latency of the phjax package under ROOT (another checkout)")
    ap.add_argument("--latency-only", action="store_true", help="skip table 2")
    ap.add_argument("--latency-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--sync-dispatch", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.latency_child:  # one dispatch setting per process: set before the first computation
        if args.sync_dispatch:
            jax.config.update("jax_cpu_enable_async_dispatch", False)
        import phjax

        print(json.dumps({"phjax": os.path.dirname(phjax.__file__), "rows": _latency_rows(args.repeats)}))
        return 0
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    roots = {"this": here}
    if args.compare:
        roots["compared"] = os.path.abspath(args.compare)
    print(f"# phjax tracker benchmark (jax {jax.__version__}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}, float32)\n")
    if args.compare:
        print(f"`this`: {here}; `compared`: {roots['compared']}\n")
    results = {(lab, sync): _child_latency(root, sync, args.repeats)
               for lab, root in roots.items() for sync in (False, True)}
    print(f"1. Streaming latency ({args.repeats} calls per row; load average after: "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())})\n")
    _print_latency(results, list(roots))
    print()
    sys.stdout.flush()
    if args.latency_only:
        return 0

    import phjax as pj
    from phjax.motion import simulate
    from phjax.tracking import baselines

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
    print(f"2. Whole recording: {args.minutes:g} min, {len(mt)} frames at 30 Hz -> {len(render)} render samples at 120 Hz\n")
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
