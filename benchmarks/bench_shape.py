"""Benchmarks for phjax.curves.shape: free-angle optimisation of PH quintic Hermite segments.

Usage (from the repository root)::

    python benchmarks/bench_shape.py [--quick] [--dtype float32|float64|both] [--only SECTIONS]

Prints Markdown tables:

* ``throughput``: solves per second of :func:`phjax.optimize_shape` for a batch of 1e4 segments
  (consecutive-pose segments of the TUM RGB-D trajectories) after compilation, without and with
  a curvature bound, next to the closed-form default angles (``hermite_quintic``) and the
  dense-grid reference (``grid_search_shape``, on 512 segments); compile time separately.
* ``quality``: on consecutive-pose segments of real trajectories (TUM RGB-D, TUM VI, CWI 6-DoF
  VR), the bending energy of the optimal curve against (a) the paper's fixed angles
  ``phi0 = phi2 = -pi/2`` with ``axis = [1, 0, 0]`` and (b) the package default (the
  near-optimal closed form); all energies from ``PHQuintic.bending_energy(64)`` of the returned
  curves; float64.
* ``grid``: agreement with the dense-grid reference on a subsample (float64).

Segments: ``p_k, p_{k+1}`` and ``d = v dt`` with the velocities of
``phjax.motion.resample.finite_difference_velocities``; segments with a non-finite value or a time gap
longer than 5 median steps are dropped. Timings use ``time.perf_counter`` after warm-up and
``block_until_ready``; "best" is the minimum over repeats.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SECTIONS = ("throughput", "quality", "grid")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="reduced sizes (smoke test)")
    p.add_argument("--dtype", choices=("float32", "float64", "both"), default="both",
                   help="dtype(s) of the throughput section (quality/grid are float64)")
    p.add_argument("--only", default=",".join(SECTIONS),
                   help=f"comma-separated subset of {','.join(SECTIONS)}")
    p.add_argument("--segments", type=int, default=10_000, help="batch size of the throughput run")
    p.add_argument("--data", default=None,
                   help="shared data directory (default: phjax.datasets.shared_data_dir(), i.e. "
                        "$PHJAX_SHARED_DATA or ../shared/data)")
    args = p.parse_args(argv)
    if args.data is None:
        from phjax.datasets import shared_data_dir

        found = shared_data_dir()
        args.data = str(found if found is not None else ROOT.parent / "shared" / "data")
    args.only = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = [s for s in args.only if s not in SECTIONS]
    if bad:
        p.error(f"unknown section(s) {bad}; choose from {SECTIONS}")
    return args


ARGS = parse_args()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # float32 runs use float32 arrays

import jax.numpy as jnp  # noqa: E402

import phjax  # noqa: E402
from phjax.motion.resample import finite_difference_velocities  # noqa: E402
from phjax.curves.shape import ShapeStatus, grid_search_shape, optimize_shape  # noqa: E402

DATA = Path(ARGS.data)


# ------------------------------------------------------------------------------- utilities
def table(header, rows):
    align = ["---:" if i else ":---" for i in range(len(header))]
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def fmt_rate(x):
    for unit, s in (("M", 1e6), ("k", 1e3)):
        if x >= s:
            return f"{x / s:.3g} {unit}"
    return f"{x:.3g}"


def block(x):
    return jax.block_until_ready(x)


def best_time(fn, repeats):
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), float(np.median(ts))


def segments(traj, max_gap=5.0):
    """Consecutive-pose Hermite data ``(p0, p1, d0, d1)`` of a trajectory (float64)."""
    t, p = np.asarray(traj.times, float), np.asarray(traj.positions, float)
    ok = np.all(np.isfinite(p), axis=-1)
    t, p, q = t[ok], p[ok], np.asarray(traj.quaternions)[ok]
    v, _ = finite_difference_velocities(t, p, q)
    v = np.asarray(v)
    dt = np.diff(t)
    keep = (dt > 0) & (dt <= max_gap * np.median(dt))
    d = dt[:, None]
    seg = np.stack([p[:-1], p[1:], v[:-1] * d, v[1:] * d])[:, keep]
    return seg[:, np.all(np.isfinite(seg), axis=(0, 2))]


def datasets():
    """{name: (segments, description)} for the available shared trajectories."""
    out = {}
    tum = DATA / "tum_rgbd_groundtruth"
    if tum.exists():
        for f in sorted(tum.glob("*-groundtruth.txt")):
            name = f.name.replace("-groundtruth.txt", "")
            out[f"TUM RGB-D {name}"] = segments(phjax.io.read_tum(f))
    vi = DATA / "tum_vi_room_groundtruth"
    if vi.exists():
        for f in sorted(vi.glob("room*_mocap_groundtruth.csv")):
            out[f"TUM VI {f.name.split('_')[0]}"] = segments(phjax.io.read_euroc(f))
    cwi = DATA / "vr_cwi_6dof_navigation"
    if cwi.exists():
        for f in sorted(cwi.glob("H*_nav.csv")):
            parts = phjax.io.read_cwi(f)
            seg = np.concatenate([segments(tr) for tr in parts.values()], axis=1)
            out[f"CWI VR {f.name.split('_')[0]} ({len(parts)} users)"] = seg
    return out


def pad_to(seg, n):
    """Pad a (4, m, 3) batch to (4, n, 3) by repeating the first segment (fixed compile)."""
    m = seg.shape[1]
    if m >= n:
        return seg[:, :n]
    return np.concatenate([seg, np.repeat(seg[:, :1], n - m, axis=1)], axis=1)


def in_chunks(fn, seg, chunk):
    """Apply ``fn`` to fixed-size chunks (one compile) and concatenate the first m results."""
    m = seg.shape[1]
    outs = []
    for s in range(0, m, chunk):
        part = seg[:, s:s + chunk]
        res = fn(pad_to(part, chunk))
        k = part.shape[1]
        outs.append(jax.tree.map(lambda x, k=k: np.asarray(x)[:k], res))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *outs)


def header():
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = "n/a"
    machine = (f"- machine: {platform.machine()} `{platform.platform()}`, os.cpu_count() = "
               f"{os.cpu_count()}, usable cores = {cores}, load average at start = {load[0]:.2f}")
    mode = (f"- mode {'quick' if ARGS.quick else 'full'}; XLA_FLAGS = "
            f"`{os.environ.get('XLA_FLAGS', '')}`")
    versions = (f"- python {platform.python_version()}, jax {jax.__version__}, "
                f"device {jax.devices()[0]}")
    return f"{machine}\n{versions}\n{mode}"


# ------------------------------------------------------------------------------ sections
def section_throughput(all_data):
    n = ARGS.segments // 10 if ARGS.quick else ARGS.segments
    pool = np.concatenate([s for k, s in all_data.items() if k.startswith("TUM RGB-D")], axis=1) \
        if any(k.startswith("TUM RGB-D") for k in all_data) else \
        np.random.default_rng(0).normal(scale=0.01, size=(4, n, 3))
    idx = np.random.default_rng(1).choice(pool.shape[1], size=n, replace=pool.shape[1] < n)
    seg64 = pool[:, idx]
    dtypes = ["float32", "float64"] if ARGS.dtype == "both" else [ARGS.dtype]
    repeats = 2 if ARGS.quick else 5
    rows = []
    for dt in dtypes:
        seg = jnp.asarray(seg64.astype(dt))
        base = jax.jit(phjax.hermite_quintic)
        tb, _ = best_time(lambda seg=seg, base=base: block(base(*seg)), repeats)
        t0 = time.perf_counter()
        _, sol = block(optimize_shape(*seg))
        compile_s = time.perf_counter() - t0
        t_best, t_med = best_time(lambda seg=seg: block(optimize_shape(*seg)), repeats)
        status = np.bincount(np.asarray(sol.status), minlength=len(ShapeStatus))
        rows.append([dt, "bending energy", f"{n:.0e}", fmt_rate(n / t_best),
                     f"{t_best:.2f}", f"{t_med:.2f}", f"{compile_s:.1f}",
                     f"{np.median(np.asarray(sol.num_steps)):.0f}",
                     f"{status[ShapeStatus.MAX_STEPS] / n:.1%}", fmt_rate(n / tb)])
        # a curvature bound: 0.9 x the unconstrained optimum's max curvature. The bound is active
        # everywhere and mostly infeasible (the energy optimum nearly minimises max kappa as
        # well), so this row times the worst case: 4 augmented-Lagrangian solves + phase 2.
        kmax = 0.9 * np.asarray(sol.max_curvature, dtype=dt)
        t0 = time.perf_counter()
        _, solb = block(optimize_shape(*seg, kappa_max=kmax))
        compile_b = time.perf_counter() - t0
        tb_best, tb_med = best_time(
            lambda seg=seg, kmax=kmax: block(optimize_shape(*seg, kappa_max=kmax)),
            max(1, repeats // 2))
        status = np.bincount(np.asarray(solb.status), minlength=len(ShapeStatus))
        rows.append([dt, "same, kappa <= 0.9 max kappa*", f"{n:.0e}", fmt_rate(n / tb_best),
                     f"{tb_best:.2f}", f"{tb_med:.2f}", f"{compile_b:.1f}",
                     f"{np.median(np.asarray(solb.num_steps)):.0f}",
                     (f"{status[ShapeStatus.MAX_STEPS] / n:.1%} (infeasible "
                      f"{status[ShapeStatus.INFEASIBLE] / n:.0%})"), ""])
    # the grid reference for scale
    m = 128 if ARGS.quick else 512
    segg = jnp.asarray(seg64[:, :m])
    t0 = time.perf_counter()
    block(grid_search_shape(*segg))
    cg = time.perf_counter() - t0
    tg, _ = best_time(lambda: block(grid_search_shape(*segg)), 1)
    rows.append([str(segg.dtype), "grid_search_shape (64^2 + 8 x 9^2)", f"{m}", fmt_rate(m / tg),
                 f"{tg:.2f}", "", f"{cg:.1f}", "", "", ""])
    print(f"\n## Throughput ({n:.0e} consecutive-pose TUM RGB-D segments per call)\n")
    print(table(["dtype", "problem", "segments", "solves/s", "best s", "median s", "compile s",
                 "median steps", "MAX_STEPS", "hermite_quintic (CC) segments/s"], rows))
    print("\nDefaults: 8 starts (closed form + 7 seed-grid minima of a 12 x 12 grid), "
          "max_steps = 16 BFGS steps per start (per augmented-Lagrangian iteration with a bound, "
          "4 iterations). 'compile s' is the first call (trace + compile + run). MAX_STEPS: "
          "share of segments whose best start stopped at max_steps (its value is still the best "
          "found).")


def section_quality(all_data):
    per = 1000 if ARGS.quick else None
    chunk = 4096
    rows = []
    rng = np.random.default_rng(2)
    for name, seg in all_data.items():
        if per is not None and seg.shape[1] > per:
            seg = seg[:, np.sort(rng.choice(seg.shape[1], per, replace=False))]
        curve_o, sol = in_chunks(lambda s: optimize_shape(*s), seg, chunk)
        e_opt = np.asarray(jax.tree.map(jnp.asarray, curve_o).bending_energy(64))
        e_cc = in_chunks(lambda s: phjax.hermite_quintic(*s).bending_energy(64), seg, chunk)
        e_pa = in_chunks(lambda s: phjax.hermite_quintic(
            *s, -np.pi / 2, -np.pi / 2, axis=[1.0, 0, 0]).bending_energy(64), seg, chunk)
        stat = np.asarray(sol.status)
        rest = stat == ShapeStatus.DEGENERATE
        ok = np.isfinite(e_opt) & (e_opt > 0) & np.isfinite(e_cc) & np.isfinite(e_pa) & ~rest
        r_pa, r_cc = e_pa[ok] / e_opt[ok], e_cc[ok] / e_opt[ok]
        rows.append([name, f"{ok.sum()} ({rest.sum()})", f"{np.median(r_pa):.3g}",
                     f"{np.percentile(r_pa, 90):.3g}", f"{np.median(r_cc):.6f}",
                     f"{np.percentile(r_cc, 90):.4f}", f"{np.mean(r_cc > 1.01):.1%}",
                     f"{np.min(r_cc):.9f}", f"{np.mean(stat == ShapeStatus.MAX_STEPS):.1%}"])
    print("\n## Bending energy: fixed angles and closed form vs the optimum (float64)\n")
    print(table(["trajectory", "segments (resting)", "paper / opt median", "paper / opt p90",
                 "default / opt median", "default / opt p90", "default > 1.01 opt",
                 "min default / opt", "MAX_STEPS"], rows))
    print("\nRatios of bending energies `PHQuintic.bending_energy(64)`: 'paper' = phi0 = phi2 = "
          "-pi/2 with axis = [1, 0, 0] (Amamra's choice); 'default' = the package default "
          "(FGMS08 near-optimal closed form); 'opt' = `optimize_shape` (bending energy). A ratio "
          "> 1 is the factor by which the optimum is smoother. `min default / opt` < 1 would "
          "mean the optimiser lost to its own start. Segments with a resting end "
          "(ShapeStatus.DEGENERATE: an end speed < 1 % of the segment scale, e.g. repeated "
          "positions of a parked robot) are excluded (count in brackets): their energy diverges "
          "for every angle pair.")


def section_grid(all_data):
    m = 128 if ARGS.quick else 512
    rows = []
    rng = np.random.default_rng(3)
    sets = {"random (looping)": rng.normal(size=(4, m, 3))}
    for name, seg in all_data.items():
        if name.startswith(("TUM RGB-D fr1_desk", "TUM VI room1", "CWI VR H1")):
            sets[name] = seg[:, np.sort(rng.choice(seg.shape[1], min(m, seg.shape[1]),
                                                   replace=False))]
    for name, seg in sets.items():
        seg = pad_to(seg, m)
        _, sol = optimize_shape(*seg)
        _, ref = grid_search_shape(*seg)
        rel = (np.asarray(sol.objective) - np.asarray(ref.objective)) / np.abs(np.asarray(
            ref.objective))
        # resting-end segments are returned unoptimised by design (ShapeStatus.DEGENERATE)
        keep = np.asarray(sol.status) != int(ShapeStatus.DEGENERATE)
        rel = rel[keep]
        rows.append([name, f"{keep.sum()} ({m - keep.sum()})", f"{np.mean(rel <= 1e-6):.1%}",
                     f"{np.max(rel):.2e}", f"{np.median(rel):.2e}"])
    print("\n## Agreement with the dense grid (float64)\n")
    print(table(["segments", "n (resting)", "optimum <= grid (1 + 1e-6)", "max rel. excess",
                 "median rel. excess"], rows))
    print("\nGrid: 64 x 64 cell centres of the angle torus, then 8 zoom levels of 9 x 9 "
          "(spacing x 0.375 per level). Negative excess: the optimiser is below the grid. "
          "Segments with a resting end (ShapeStatus.DEGENERATE, count in brackets) are "
          "excluded: they return the closed-form angles unoptimised.")


def main():
    t_start = time.perf_counter()
    print(f"# phjax shape optimisation benchmarks\n\n{header()}")
    data = datasets()
    if not data:
        print("\n(shared data not found: quality and grid sections use random data only)")
    for name in SECTIONS:
        if name in ARGS.only:
            globals()[f"section_{name}"](data)
            sys.stdout.flush()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"\nTotal wall time {time.perf_counter() - t_start:.0f} s; load average at end "
          f"{load[0]:.2f}.")


if __name__ == "__main__":
    main()
