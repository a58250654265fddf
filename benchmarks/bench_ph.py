"""Benchmarks for phjax PH quintics: construction, sampling, latency, scaling.

Usage (from the repository root)::

    python benchmarks/bench_ph.py [--quick] [--dtype float32|float64] [--only SECTIONS]

Prints Markdown tables. Every ratio compares numbers measured in the same run (same machine
state): phjax against the independent NumPy reference (``tests/curves/reference_ph_numpy.py``),
scipy's ``CubicHermiteSpline`` and the memory-write rate of an output-sized array. Timings use
``time.perf_counter`` after warm-up (and ``block_until_ready`` for JAX); "best" is the minimum
and "median" the median over the repeats. Compile time is excluded from throughput and reported
separately. See ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "curves"))

SECTIONS = ("construction", "sampling", "latency", "scaling")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="reduced sizes (smoke test, < 60 s)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--only", default=",".join(SECTIONS),
                   help=f"comma-separated subset of {','.join(SECTIONS)}")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    args.only = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = [s for s in args.only if s not in SECTIONS]
    if bad:
        p.error(f"unknown section(s) {bad}; choose from {SECTIONS}")
    return args


ARGS = parse_args()

import jax  # noqa: E402

if ARGS.dtype == "float64":
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import scipy  # noqa: E402
from scipy.interpolate import CubicHermiteSpline  # noqa: E402

import phjax  # noqa: E402
from reference_ph_numpy import data_perpendicular_np, hermite_quintic_np, position_np  # noqa: E402

DTYPE = np.dtype(ARGS.dtype)


# ------------------------------------------------------------------------------- utilities
@dataclass
class Timing:
    best: float  # s
    median: float  # s
    repeats: int
    minflt: float  # minor page faults per call (Linux; 0 where unavailable)


def _minflt() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def bench(fn, *, budget: float = 1.0, min_repeats: int = 3, max_repeats: int = 50,
          warmup: int = 2) -> Timing:
    """Time ``fn()`` (which must block until its result is ready) after ``warmup`` calls.

    Repeats until ``budget`` seconds are spent (at least ``min_repeats``, at most ``max_repeats``).
    """
    for _ in range(warmup):
        fn()
    times, faults = [], []
    spent = 0.0
    while len(times) < min_repeats or (spent < budget and len(times) < max_repeats):
        f0 = _minflt()
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        faults.append(_minflt() - f0)
        times.append(dt)
        spent += dt
    return Timing(min(times), float(np.median(times)), len(times), float(np.median(faults)))


def latency(fn, calls: int) -> tuple[float, float]:
    """Median and 90th percentile (s) of single calls after warm-up."""
    for _ in range(max(50, calls // 10)):
        fn()
    ts = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter()
        fn()
        ts[i] = time.perf_counter() - t0
    return float(np.median(ts)), float(np.percentile(ts, 90))


def block(x):
    return jax.block_until_ready(x)


def table(header: list[str], rows: list[list], align: str | None = None) -> str:
    align = align or "l" + "r" * (len(header) - 1)
    sep = ["---:" if a == "r" else ":---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def fmt_rate(x: float) -> str:
    for unit, s in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= s:
            return f"{x / s:.3g} {unit}"
    return f"{x:.3g}"


def fmt_ratio(r: float) -> str:
    return f"{r:.0f}" if r >= 10 else f"{r:.2g}"


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.3g}"


def hermite_data(n_seg: int, seed: int):
    """A long random C1 path: knots ``x`` (n+1, 3) and derivatives ``v`` (n+1, 3) per unit step.

    Segment k interpolates (x[k], x[k+1], v[k], v[k+1]) on t in [0, 1] (also the data of a
    piecewise cubic Hermite spline with integer knots).
    """
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(scale=0.1, size=(n_seg + 1, 3)), axis=0)
    v = np.gradient(x, axis=0) + rng.normal(scale=0.03, size=x.shape)
    return x.astype(DTYPE), v.astype(DTYPE)


def hermite_batch(n_seg: int, seed: int):
    x, v = hermite_data(n_seg, seed)
    return x[:-1], x[1:], v[:-1], v[1:]


def header_info() -> str:
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("n/a",) * 3
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = "n/a"
    lines = [
        f"- machine: {platform.machine()} {platform.processor() or ''} `{platform.platform()}`, "
        f"os.cpu_count() = {os.cpu_count()}, usable cores = {affinity}, "
        f"load average at start = {load[0]:.2f}, {load[1]:.2f}, {load[2]:.2f}",
        f"- python {platform.python_version()}, jax {jax.__version__}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}, device {jax.devices()[0]}",
        f"- dtype {DTYPE} (jax_enable_x64 = {jax.config.jax_enable_x64}), mode "
        f"{'quick' if ARGS.quick else 'full'}",
        f"- XLA_FLAGS = `{os.environ.get('XLA_FLAGS', '')}`, GLIBC_TUNABLES = "
        f"`{os.environ.get('GLIBC_TUNABLES', '')}`",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- construction
def section_construction():
    sizes = [10**3, 10**4] if ARGS.quick else [10**3, 10**4, 10**5, 10**6]
    budget = 0.3 if ARGS.quick else 1.5
    rows = []
    f_default = jax.jit(lambda p0, p1, d0, d1: phjax.hermite_quintic(p0, p1, d0, d1))
    f_fixed = jax.jit(lambda p0, p1, d0, d1, a, b: phjax.hermite_quintic(p0, p1, d0, d1, a, b))

    def np_fixed(p0, p1, d0, d1, a, b):
        # same work as phjax with fixed angles and its default axis u = d0/|d0|
        u = d0 / np.linalg.norm(d0, axis=-1, keepdims=True)
        return hermite_quintic_np(p0, p1, d0, d1, a, 0.0, b, u,
                                  perpendicular=data_perpendicular_np(p0, p1, d1))

    for n in sizes:
        np_args = hermite_batch(n, ARGS.seed)
        rng = np.random.default_rng(ARGS.seed + 1)
        phis = tuple(rng.uniform(-np.pi, np.pi, size=n).astype(DTYPE) for _ in range(2))
        jx_args = tuple(jax.device_put(a) for a in np_args)
        jx_phis = tuple(jax.device_put(a) for a in phis)
        res = {}
        for name, f, args in (("default", f_default, jx_args),
                              ("fixed", f_fixed, jx_args + jx_phis)):
            t0 = time.perf_counter()
            comp = f.lower(*args).compile()
            ct = time.perf_counter() - t0
            res[name] = (bench(lambda: block(comp(*args)), budget=budget), ct)  # noqa: B023 (timed now)
        res["numpy"] = (bench(lambda: np_fixed(*np_args, *phis), budget=budget), 0.0)  # noqa: B023
        # same curves? (fixed angles, same axis convention)
        p_np = np_fixed(*np_args, *phis)[3]
        p_jx = np.asarray(comp(*jx_args, *jx_phis).control_points)
        err = np.abs(p_np - p_jx).max() / (1 + np.abs(p_np).max())
        tn = res["numpy"][0].best
        rows.append([
            f"{n:.0e}",
            fmt_rate(n / res["default"][0].best), f"{res['default'][1]:.1f}",
            fmt_rate(n / res["fixed"][0].best), f"{res['fixed'][1]:.1f}",
            fmt_rate(n / tn),
            f"{tn / res['default'][0].best:.2f}", f"{tn / res['fixed'][0].best:.2f}",
            f"{err:.1e}",
        ])
    print("\n## Construction throughput (segments/s, best of repeats)\n")
    print(table(
        ["segments", "phjax default (CC angles)", "compile s", "phjax fixed angles", "compile s",
         "NumPy fixed angles", "ratio default/NumPy", "ratio fixed/NumPy", "max rel |P diff|"],
        rows))
    print("\nphjax: `jax.jit(phjax.hermite_quintic)` on device arrays, output blocked; NumPy: "
          "`hermite_quintic_np` (vectorised, same fixed angles, axis d0/|d0| computed inside). "
          "Ratios > 1: phjax faster. Last column: control-point agreement phjax vs NumPy "
          "(fixed angles) relative to the data scale.")


# ------------------------------------------------------------------------------- sampling
def section_sampling():
    n_seg = 10**4 if ARGS.quick else 10**5
    n = 100
    budget = 0.5 if ARGS.quick else 2.0
    total = n_seg * n
    x, v = hermite_data(n_seg, ARGS.seed)
    curves = block(jax.jit(phjax.hermite_quintic)(x[:-1], x[1:], v[:-1], v[1:]))
    P = np.asarray(curves.control_points)
    u_np = np.linspace(0, 1, n, dtype=DTYPE)
    u_jx = jnp.asarray(u_np)
    out_shape = (n_seg, n, 3)
    rows: list[tuple[str, Timing, str]] = []

    # phjax (sample is jitted with static n)
    t_time = bench(lambda: block(phjax.sample(curves, n)), budget=budget)
    t_arc = bench(lambda: block(phjax.sample(curves, n, by="arclength")), budget=budget)
    pts = np.asarray(phjax.sample(curves, n)[1])
    assert np.allclose(pts[:, 0], x[:-1], atol=1e-3) and np.allclose(pts[:, -1], x[1:], atol=1e-3)
    rows.append(("phjax `sample(curves, 100)`", t_time, "returns t (N,n) and points (N,n,3)"))
    rows.append(("phjax `sample(..., by='arclength')`", t_arc, "12 Newton steps per point"))

    # diagnostics: points only; points into a donated (reused) output buffer
    pos = jax.jit(lambda c: c.position(u_jx))
    rows.append(("diag: jit `curves.position(u)` (no t array)",
                 bench(lambda: block(pos(curves)), budget=budget), "fresh output"))
    pos_into = jax.jit(lambda buf, c: c.position(u_jx), donate_argnums=0, keep_unused=True)
    state = {"buf": jnp.zeros(out_shape, DTYPE)}

    def run_into():
        state["buf"] = block(pos_into(state["buf"], curves))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows.append(("diag: same, output into a donated buffer", bench(run_into, budget=budget),
                     "no fresh allocation"))

    # NumPy reference evaluation of the same control points
    rows.append(("NumPy Bernstein (basis @ P)", bench(lambda: position_np(P, u_np), budget=budget),
                 "batched matmul (n,6)@(N,6,3)"))
    rows.append(("NumPy Horner (power basis)", bench(lambda: position_np(P, u_np, "horner"),
                                                      budget=budget), "in-place, (N,n,3)"))

    # scipy cubic Hermite spline over the long curve with the same end data
    knots = np.arange(n_seg + 1, dtype=np.float64)
    t_eval = (np.arange(n_seg, dtype=np.float64)[:, None] + u_np.astype(np.float64)).ravel()
    t0 = time.perf_counter()
    splines = [CubicHermiteSpline(knots, x[:, k], v[:, k]) for k in range(3)]
    build = time.perf_counter() - t0
    t_sc = bench(lambda: [s(t_eval) for s in splines], budget=budget, min_repeats=3, max_repeats=5,
                 warmup=1)
    rows.append(("scipy CubicHermiteSpline, 3 scalar splines", t_sc,
                 f"float64 output; build {build * 1e3:.0f} ms (excluded)"))
    spline_v = CubicHermiteSpline(knots, x, v)
    rows.append(("scipy CubicHermiteSpline, one (N+1,3) spline",
                 bench(lambda: spline_v(t_eval), budget=budget, min_repeats=3, max_repeats=5,
                       warmup=1), "float64 output"))

    # memory-write references for the output-sized array
    arr = np.empty(out_shape, DTYPE)
    t_fill = bench(lambda: arr.fill(1.0), budget=budget)
    rows.append(("memory write: `arr.fill(1.0)` (warm array)", t_fill, "reference for the target"))
    rows.append(("memory write: `np.ones` (fresh array)", bench(lambda: np.ones(out_shape, DTYPE),
                                                               budget=budget), ""))
    xla_fill = jax.jit(lambda s: jnp.broadcast_to(s, out_shape) + 0)
    one = jnp.asarray(1.0, DTYPE)
    rows.append(("memory write: XLA fill (fresh output)", bench(lambda: block(xla_fill(one)),
                                                              budget=budget), ""))

    print(f"\n## Sampling throughput ({n_seg:.0e} segments x {n} samples = {total:.0e} 3-D points, "
          f"{DTYPE})\n")
    out = []
    for name, t, note in rows:
        rate = total / t.best
        out.append([name, fmt_ms(t.best), fmt_ms(t.median), fmt_rate(rate) + "/s",
                    f"{fmt_ratio(100 * t_fill.best / t.best)} %",
                    f"{fmt_ratio(t_sc.best / t.best)}x",
                    f"{t.minflt:.0f}", note])
    print(table(["method", "best ms", "median ms", "samples/s", "vs memory write", "vs scipy",
                 "page faults/call", "note"], out, "lrrrrrrl"))
    frac = t_fill.best / t_time.best
    spd = t_sc.best / t_time.best
    print(f"\nTargets: phjax `sample` at {100 * frac:.0f} % of the memory-write rate "
          "(target >= 25 %: "
          f"{'met' if frac >= 0.25 else 'NOT met'}); {spd:.1f}x scipy (target >= 20x: "
          f"{'met' if spd >= 20 else 'NOT met'}). One sample = one 3-D point; 'vs memory write' = "
          "rate / rate of `arr.fill` on a warm output-sized array; 'vs scipy' = speed-up over the "
          "3 scalar splines. `diag:` rows are diagnostics, not library API.")


# -------------------------------------------------------------------------------- latency
def section_latency():
    calls = 300 if ARGS.quick else 3000
    rng = np.random.default_rng(ARGS.seed)
    a_np = [rng.normal(size=3).astype(DTYPE) for _ in range(4)]
    a = [jax.device_put(x) for x in a_np]
    t = jnp.asarray(0.37, DTYPE)
    f_def = jax.jit(lambda p0, p1, d0, d1, t: phjax.hermite_quintic(p0, p1, d0, d1).position(t))
    f_fix = jax.jit(lambda p0, p1, d0, d1, t: phjax.hermite_quintic(p0, p1, d0, d1, 0.0, 0.0)
                    .position(t))
    f_triv = jax.jit(lambda t: t + 1)

    def np_one():
        u = a_np[2] / np.linalg.norm(a_np[2])
        P = hermite_quintic_np(*(x[None] for x in a_np), 0.0, 0.0, 0.0, u[None])[3]
        return position_np(P, 0.37)

    rows = []
    for name, fn in (
        ("phjax jit: construct (default CC angles) + position(t)", lambda: block(f_def(*a, t))),
        ("phjax jit: construct (fixed angles) + position(t)", lambda: block(f_fix(*a, t))),
        ("jit dispatch floor: `jit(lambda t: t + 1)`", lambda: block(f_triv(t))),
        ("NumPy reference: construct + position (N = 1)", np_one),
    ):
        med, p90 = latency(fn, calls)
        rows.append([name, f"{med * 1e6:.1f}", f"{p90 * 1e6:.1f}"])
    n_ops = f_def.lower(*a, t).compile().as_text().split("ENTRY")[-1].count("fusion(")
    print(f"\n## Single-curve latency ({calls} calls after warm-up, inputs already on device)\n")
    print(table(["call", "median µs", "p90 µs"], rows))
    med = float(rows[0][1])
    print(f"\nTarget <= 50 µs (default angles): {'met' if med <= 50 else 'NOT met'} "
          f"({med:.1f} µs). "
          f"The compiled default program has {n_ops} fusions/kernels in its entry computation.")


# -------------------------------------------------------------------------------- scaling
def section_scaling():
    n_seg = 10**4
    ns = [10, 30, 100] if ARGS.quick else [10, 30, 100, 300, 1000]
    budget = 0.3 if ARGS.quick else 1.0
    x, v = hermite_data(n_seg, ARGS.seed)
    curves = block(jax.jit(phjax.hermite_quintic)(x[:-1], x[1:], v[:-1], v[1:]))
    res = {"time": [], "arclength": []}
    faults = {"time": [], "arclength": []}
    for n in ns:
        for by in res:
            tm = bench(lambda: block(phjax.sample(curves, n, by=by)), budget=budget)  # noqa: B023
            res[by].append(tm.best)
            faults[by].append(tm.minflt)
    rows = []
    for i, n in enumerate(ns):
        rows.append([n, f"{n_seg * n * 3 * DTYPE.itemsize / 2**20:.3g}"]
                    + sum(([fmt_ms(res[by][i]), f"{res[by][i] / (n_seg * n) * 1e9:.2f}",
                            f"{faults[by][i]:.0f}"] for by in res), []))
    print(f"\n## Scaling with samples per segment ({n_seg:.0e} segments, `phjax.sample`, best)\n")
    print(table(["n", "points MiB", "time ms", "ns/sample", "page faults/call", "arclength ms",
                 "ns/sample", "page faults/call"], rows))
    fit_rows = []
    nsa = np.asarray(ns, float)
    for by, ts in res.items():
        ts = np.asarray(ts)
        slope, icpt = np.polyfit(nsa, ts, 1)
        expo = np.polyfit(np.log(nsa), np.log(ts), 1)[0]
        big = nsa >= 100
        expo_big = np.polyfit(np.log(nsa[big]), np.log(ts[big]), 1)[0] if big.sum() >= 2 else np.nan
        fit_rows.append([by, f"{slope * 1e6:.3g}", f"{icpt * 1e3:.3g}", f"{expo:.2f}",
                         f"{expo_big:.2f}" if np.isfinite(expo_big) else "n/a"])
    print()
    print(table(["by", "linear slope µs per (sample/segment)", "intercept ms",
                 "log-log exponent (all n)", "exponent (n >= 100)"], fit_rows))
    print("\nLinear least-squares fit time = intercept + slope * n, and the slope of log(time) vs "
          "log(n); exponent 1 = linear scaling (fixed per-call costs pull the all-n exponent "
          "below 1).")


def main():
    t_start = time.perf_counter()
    print(f"# phjax PH quintic benchmarks\n\n{header_info()}")
    for name in SECTIONS:
        if name in ARGS.only:
            globals()[f"section_{name}"]()
            sys.stdout.flush()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"\nTotal wall time {time.perf_counter() - t_start:.0f} s; load average at end "
          f"{load[0]:.2f}. Timings on a shared machine are noisy: compare ratios within one run.")


if __name__ == "__main__":
    main()
