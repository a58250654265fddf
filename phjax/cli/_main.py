"""Command-line interface: ``phjax <command>`` (or ``python -m phjax <command>``).

Commands:
    demo         the main job: evaluate the causal stream, the offline reconstruction and every
                 baseline on the bundled synthetic head motion (or a file) and write a plot;
                 ``--rgbd N``: the end-to-end path on the synthetic RGB-D head.
    evaluate     the same on a ground-truth trajectory file.
    smooth       render a recorded (noisy) pose file at a given rate, causal or offline.
    demo-curve   PH quintic demo: a batch of curves from consecutive poses of a TUM recording.
    tune         tune the tracker's parameters by gradient on recordings (JSON for --config).
    track-rgbd   head pose per RGB-D frame (Biwi / TUM / colour+depth folder / synthetic), then
                 the smooth render-rate stream.
    live         live tracking: camera / recording in, smooth poses out to opentrack / OSC.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["main", "build_parser"]


def _enable_x64():
    import jax

    jax.config.update("jax_enable_x64", True)


# ------------------------------------------------------------------------------ demo-curve
def _tum_hermite_data(path: Path | None, n_max: int, stride: int):
    """Consecutive poses -> Hermite data (positions and finite-difference velocities x dt)."""
    if path is not None and path.exists():
        data = np.loadtxt(path)
        times, pos = data[::stride, 0], data[::stride, 1:4]
        source = f"{path} (every {stride}. pose)"
    else:
        rng = np.random.default_rng(0)
        times = np.arange(0, 30, 0.01 * stride)
        pos = np.cumsum(rng.normal(size=(times.size, 3)) * 0.002, axis=0)
        source = "synthetic random walk (shared data not found)"
    times, pos = times[: n_max + 1], pos[: n_max + 1]
    vel = np.gradient(pos, times, axis=0)
    dt = np.diff(times)[:, None]
    return pos[:-1], pos[1:], vel[:-1] * dt, vel[1:] * dt, source


def cmd_demo_curve(args) -> int:
    import jax
    import jax.numpy as jnp

    import phjax as pj

    from ..datasets import shared_data_dir

    if args.x64:
        _enable_x64()
    root = shared_data_dir()
    path = Path(args.input) if args.input else (
        root / "tum_rgbd_groundtruth" / "fr1_xyz-groundtruth.txt" if root else None
    )
    p0, p1, d0, d1, source = _tum_hermite_data(path, args.segments, args.stride)
    build = jax.jit(pj.hermite_quintic)
    t0 = time.perf_counter()
    curves = jax.block_until_ready(build(p0, p1, d0, d1))
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    curves = jax.block_until_ready(build(p0, p1, d0, d1))
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, pts = jax.block_until_ready(pj.sample(curves, args.samples))
    t_first_sample = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, pts = jax.block_until_ready(pj.sample(curves, args.samples))
    t_sample = time.perf_counter() - t0
    u = jnp.linspace(0.02, 0.98, 25)
    kappa = np.asarray(curves.curvature(u))
    tau = np.asarray(curves.torsion(u))
    length = np.asarray(curves.length)
    ends_ok = bool(np.allclose(np.asarray(curves.position(1.0)), p1, atol=1e-5))
    print(f"source: {source}")
    print(f"segments: {len(p0)}   dtype: {curves.dtype}   end points interpolated: {ends_ok}")
    print(f"arc length per segment [mm]: mean {1e3 * length.mean():.3f}  max {1e3 * length.max():.3f}"
          f"  total {length.sum():.3f} m")
    print(f"curvature [1/m]: median {np.median(kappa):.3g}  p95 {np.percentile(kappa, 95):.3g}")
    print(f"|torsion| [1/m]: median {np.median(np.abs(tau)):.3g}  p95 {np.percentile(np.abs(tau), 95):.3g}")
    print(f"construct: {1e3 * t_build:.2f} ms ({len(p0) / t_build / 1e6:.2f} M segments/s; "
          f"first call incl. compile {t_first:.2f} s)")
    print(f"sample {args.samples}/segment: {1e3 * t_sample:.2f} ms "
          f"({pts.shape[0] * pts.shape[1] / t_sample / 1e6:.1f} M points/s; first call {t_first_sample:.2f} s)")
    return 0


# ------------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="phjax",
        description="Smooth, predictive head and camera tracking with PH quintics (JAX).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo-curve", help="PH quintics from consecutive poses of a TUM trajectory",
                       description="Build a batch of PH quintic Hermite segments between "
                       "consecutive poses (finite-difference velocities) of "
                       "../shared/data/tum_rgbd_groundtruth/fr1_xyz (or a TUM file you name; "
                       "synthetic data if neither exists) and print arc length, curvature, "
                       "torsion and timing.")
    p.add_argument("input", nargs="?", help="TUM trajectory file (default: fr1_xyz ground truth)")
    p.add_argument("--segments", type=int, default=100000, help="maximum number of segments")
    p.add_argument("--stride", type=int, default=1, help="use every STRIDE-th pose")
    p.add_argument("--samples", type=int, default=100, help="samples per segment for timing")
    p.add_argument("--x64", action="store_true", help="compute in float64")
    p.set_defaults(func=cmd_demo_curve)

    from . import _live, _rgbd, _tracking, _tune

    _tracking.add_commands(sub)
    _tune.add_commands(sub)
    _rgbd.add_commands(sub)
    _live.add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``phjax`` command."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"phjax {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
