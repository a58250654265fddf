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
import os
import signal
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ._common import (
    Parser,
    add_format_argument,
    check_fits,
    format_user_error,
    positive_int,
    read_input,
)
from ._signals import finish_background_compilations

__all__ = ["build_parser"]


def _enable_x64():
    import jax

    jax.config.update("jax_enable_x64", True)


# ------------------------------------------------------------------------------ demo-curve
def _tum_hermite_data(path: Path | None, n_max: int, stride: int, fmt: str = "auto"):
    """Consecutive poses -> Hermite data (positions and finite-difference velocities x dt).

    ``path`` is read through :mod:`phjax.io` (lost frames, rows without a position, are
    skipped); ``None``: a synthetic random walk.
    """
    if path is not None:
        from ..io import TrajectoryFormatError

        traj = read_input(path, fmt)
        ok = np.isfinite(traj.positions).all(-1)
        times, pos = traj.times[ok][::stride], traj.positions[ok][::stride]
        if len(times) < 2:
            raise TrajectoryFormatError(
                f"{path}: {len(times)} pose(s) with a position"
                + (f" at --stride {stride}" if stride > 1 else "") + "; at least 2 are needed",
                path=path)
        source = f"{path} (every {stride}. pose)" if stride > 1 else str(path)
    else:
        rng = np.random.default_rng(0)
        times = np.arange(0, 30, 0.01 * stride)
        pos = np.cumsum(rng.normal(size=(times.size, 3)) * 0.002, axis=0)
        source = "synthetic random walk (no file given and the shared fr1_xyz data not found)"
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
    if args.input:
        path = Path(args.input)
    else:  # the shared fr1_xyz ground truth when present, else synthetic data (said so)
        root = shared_data_dir()
        path = None if root is None else root / "tum_rgbd_groundtruth" / "fr1_xyz-groundtruth.txt"
        path = path if path is not None and path.is_file() else None
    p0, p1, d0, d1, source = _tum_hermite_data(path, args.segments, args.stride, args.format)
    # parameters and points, float64 at most: two copies of each sampled point at once
    check_fits({f"--samples {args.samples} x {len(p0)} segments": (args.samples * len(p0), 64)},
               "lower --samples or --segments")
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
_EPILOG = """\
Compilation cache: the first run of a command compiles its JAX programs (seconds); they
are cached in $PHJAX_CACHE_DIR, else $XDG_CACHE_HOME/phjax/jax, else ~/.cache/phjax/jax, and
later runs load them (a one-line note on stderr says when a first run compiles); the traced
programs of track / reconstruct are kept there too (subfolder exported), so later runs also skip
tracing them. Opt out with --no-cache or PHJAX_NO_COMPILATION_CACHE=1; delete the folder to
clear it.

Bad input (a missing, empty or malformed file, a folder, too few poses, a rate <= 0, an unknown
format) ends with one line 'phjax <command>: error: ...' naming the file (and the line) on
stderr and exit status 2. A value that starts with '-' and a digit (--measurement-noise -5,1,
--intrinsics -5,...) is the option's value, checked by the option. Output files are named in
each command's --help; an existing file is replaced and the line naming the written file says
so."""


class _Version(argparse.Action):
    """``--version``: ``phjax X (jax Y, jaxlib Z)`` from the installed distributions, looked up
    only when asked (the lookups take ~30 ms, which every other command would pay at start-up)
    and without importing JAX."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib import metadata

        from .. import __version__

        def installed(name):
            try:
                return metadata.version(name)
            except metadata.PackageNotFoundError:
                return "not installed"

        print(f"phjax {__version__} (jax {installed('jax')}, jaxlib {installed('jaxlib')})")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="phjax",
        description="Smooth, predictive head and camera tracking with PH quintics (JAX).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--no-cache", action="store_true",
                        help="do not use JAX's persistent compilation cache (see below)")
    parser.add_argument("--version", action=_Version,
                        help="show phjax's, JAX's and jaxlib's versions and exit")
    sub = parser.add_subparsers(dest="command", required=True)
    parser.commands = sub.choices  # name -> the command's parser

    p = sub.add_parser("demo-curve", help="PH quintics from consecutive poses of a TUM trajectory",
                       description="Build a batch of PH quintic Hermite segments between "
                       "consecutive poses (finite-difference velocities) of a trajectory file "
                       "you name (read with phjax.io; rows without a position are skipped), by "
                       "default ../shared/data/tum_rgbd_groundtruth/fr1_xyz (synthetic data when "
                       "no file is named and that one is absent), and print arc length, "
                       "curvature, torsion and timing. Writes no file.")
    p.add_argument("input", nargs="?", help="trajectory file (TUM, EuRoC, CSV; default: the "
                   "fr1_xyz ground truth)")
    add_format_argument(p)
    p.add_argument("--segments", type=positive_int, default=100000,
                   help="maximum number of segments")
    p.add_argument("--stride", type=positive_int, default=1, help="use every STRIDE-th pose")
    p.add_argument("--samples", type=positive_int, default=100,
                   help="samples per segment for timing")
    p.add_argument("--x64", action="store_true", help="compute in float64")
    p.set_defaults(func=cmd_demo_curve)

    from . import _head_pose, _live, _rgbd, _tracking, _tune

    _tracking.add_commands(sub)
    _tune.add_commands(sub)
    _rgbd.add_commands(sub)
    _head_pose.add_commands(sub)
    _live.add_commands(sub)
    for command in sub.choices.values():  # also accepted after the command name
        command.add_argument("--no-cache", action="store_true", default=argparse.SUPPRESS,
                             help="do not use JAX's persistent compilation cache "
                             "(see 'phjax --help')")
    return parser


def _quiet_opencv() -> None:
    """OpenCV's and FFmpeg's own log lines (``[ WARN ...] setPreferableTarget ...`` on every
    vision run, ``moov atom not found`` before the command's one-line error) off, unless the
    user set their levels; set before ``cv2`` is imported, and inherited by the worker
    process."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


def _run(argv: list[str] | None, usr1) -> int:
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
        if extra:  # named by the command they were given to, as its other usage errors
            parser.commands.get(getattr(args, "command", None), parser).error(f"unrecognized arguments: {' '.join(extra)}")
    except SystemExit as stop:  # --help (0) or a usage error (2, its line already printed)
        return stop.code if isinstance(stop.code, int) else 2
    if usr1 is not None and args.command != "live":  # only live handles it (once started)
        signal.signal(signal.SIGUSR1, usr1)  # (put back again, harmlessly, by main)
    from ..io import TrajectoryWarning
    from ._cache import cache_disabled, compilation_cache

    _quiet_opencv()

    enabled = not cache_disabled(args.no_cache)
    with warnings.catch_warnings(), compilation_cache(enabled, args.command) as cache:
        previous = warnings.showwarning

        def one_line(message, category, filename, lineno, file=None, line=None):
            # trajectory warnings (unsorted / duplicate timestamps) as one line each
            if issubclass(category, TrajectoryWarning):
                print(f"phjax: warning: {message}", file=sys.stderr if file is None else file)
            else:
                previous(message, category, filename, lineno, file, line)

        warnings.showwarning = one_line
        try:
            status = args.func(args)
            if status == 0:
                cache.mark_ran()
            return status
        except (ValueError, OSError) as err:
            print(f"phjax {args.command}: error: {format_user_error(err)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # Ctrl-C: one line, the shell's status for SIGINT
            print(f"\nphjax {args.command}: interrupted", file=sys.stderr)
            # before the interpreter's exit waits for them, where a second Ctrl-C aborts
            finish_background_compilations(f"phjax {args.command}")
            return 130
        except (MemoryError, RuntimeError) as err:  # larger than this machine's memory
            if not isinstance(err, MemoryError) and "RESOURCE_EXHAUSTED" not in str(err):
                raise  # XLA's out of memory is a RuntimeError; any other is a bug
            print(f"phjax {args.command}: error: out of memory ({format_user_error(err)}); "
                  "lower --rate or shorten the input", file=sys.stderr)
            return 2


if __name__ == "__main__":
    from phjax.cli import main

    raise SystemExit(main())
