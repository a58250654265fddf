"""Tracking commands of the ``phjax`` CLI: ``demo``, ``evaluate``, ``smooth``."""

from __future__ import annotations

import time

import numpy as np

from ._common import (
    BYTES_PER_CAMERA_FRAME,
    BYTES_PER_RENDER_SAMPLE,
    MAX_LOOKAHEAD_MS,
    OUTPUT_FORMATS,
    add_format_argument,
    add_output_argument,
    add_rate_argument,
    check_lookahead,
    add_sensor_arguments,
    check_fits,
    check_output,
    check_plot_output,
    check_trajectory_output,
    float_between,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    read_input,
    replaced_note,
)
from ._tune import add_config_argument, add_noise_argument

#: ``phjax demo``'s length of synthetic head motion, s, and its sample rate, Hz
DEMO_DURATION = 60.0
SYNTHETIC_RATE = 240.0


def _x64():
    import jax

    jax.config.update("jax_enable_x64", True)


def _sensor(args):
    from ..motion.simulate import SensorModel

    return SensorModel(rate=args.camera_rate, sigma_p=args.sigma_p / 1e3,
                       sigma_r=float(np.deg2rad(args.sigma_r)), dropout=args.dropout,
                       jitter=args.jitter)


def _methods_plot_path(plot: str):
    """The per-method figure written beside the frontier figure ``plot``."""
    from pathlib import Path

    p = Path(plot)
    return p.with_name(f"{p.stem}_methods{p.suffix or '.png'}")


def _run_evaluation(times, positions, quaternions, args, title: str, source=None) -> int:
    """Evaluate every method on a recording (``source``: its file, named in errors)."""
    import equinox as eqx

    from ..evaluation.display import compare_at_display, format_choices, plot_choices
    from ..evaluation.report import (
        LEGEND,
        default_methods,
        evaluate_recording,
        format_table,
        plot_evaluation,
    )
    from ..tracking.tracker import TrackerConfig
    from ._tune import config_from_args

    config = config_from_args(args) or TrackerConfig()
    config = eqx.tree_at(lambda c: c.lookahead, config, 0.0)  # the display times are set below
    if args.plot:
        args.plot = str(check_plot_output(args.plot))
        check_output(_methods_plot_path(args.plot), "plot")
    span = float(np.nanmax(times) - np.nanmin(times)) if len(times) else 0.0
    check_fits({f"--rate {args.rate:g} Hz over {span:.3g} s":
                (span * args.rate, BYTES_PER_RENDER_SAMPLE["evaluate"]),
                f"--camera-rate {args.camera_rate:g} Hz over {span:.3g} s":
                (span * args.camera_rate, BYTES_PER_CAMERA_FRAME)})
    lookaheads = (0.0,) + ((args.lookahead / 1e3,) if args.lookahead > 0 else ())
    t0 = time.perf_counter()
    try:
        result = evaluate_recording(times, positions, quaternions, sensor=_sensor(args),
                                    render_rate=args.rate, seed=args.seed,
                                    progress=not args.no_progress,
                                    methods=default_methods(config))
    except ValueError as e:  # a recording too short to score: name the file
        raise ValueError(f"{source}: {e}" if source else str(e)) from None
    comparison = compare_at_display(times, positions, quaternions, lookaheads=lookaheads,
                                    tracker_config=config, sensor=_sensor(args),
                                    render_rate=args.rate, seed=args.seed,
                                    at_render_time=result.metrics,
                                    progress=not args.no_progress)
    elapsed = time.perf_counter() - t0
    print(f"# {title}")
    print(f"sensor: {args.camera_rate:g} Hz, sigma_p {args.sigma_p:g} mm, sigma_r {args.sigma_r:g} deg, "
          f"dropout {100 * args.dropout:g} %, jitter {args.jitter:g}; render {args.rate:g} Hz; "
          f"seed {args.seed}; {elapsed:.1f} s")
    print()
    print("## What you choose between: phjax, and each predictor tuned or as smooth as phjax")
    print()
    print(format_choices(comparison))
    print()
    print("## Every method at its tuned setting (lookahead 0)")
    print()
    print(format_table(result.metrics, result.causal, legend=False))
    print()
    print(LEGEND)
    if args.plot:
        note = replaced_note(args.plot)
        path = plot_choices(comparison, args.plot)
        print(f"\nfrontier plot written to {path}{note}")
        extra = _methods_plot_path(args.plot)
        note = replaced_note(extra)
        path = plot_evaluation(result, extra)
        print(f"per-method plot (lookahead 0) written to {path}{note}")
    return 0


def _demo_rgbd(args) -> int:
    """End to end on the package's synthetic RGB-D head: front-end, tracker, accuracy."""
    import tempfile
    from pathlib import Path

    from ..datasets import shared_data_dir
    from ..vision import face_detection
    from ._rgbd import cmd_track_rgbd

    try:
        face_detection.model_path(face_detection.YUNET_ONNX)
    except face_detection.ModelNotFoundError:
        shared = shared_data_dir()
        src = None if shared is None else shared / "yunet_face_detection"
        if src is not None and src.is_dir():
            cached = face_detection.seed_model_cache(src)
            print(f"model cache seeded from {src}: {', '.join(p.name for p in cached)}")
        else:
            print("YuNet model not in the cache: downloading it (sha256-checked)")
            face_detection.download_model(face_detection.YUNET_ONNX)
    out = Path(args.plot).with_suffix(".tum") if args.plot else Path(tempfile.gettempdir()) / "phjax_demo_rgbd.tum"
    check_output(out)
    from ._main import build_parser  # track-rgbd's own defaults for everything not set here

    ns = build_parser().parse_args(
        ["track-rgbd", f"synthetic:{args.rgbd}:{args.seed}", "-o", str(out),
         "--rate", repr(args.rate), "--gt-reference"] + (["--no-progress"] if args.no_progress
                                                          else []))
    print(f"# phjax demo --rgbd: {args.rgbd} synthetic RGB-D frames (640x480, 30 Hz) -> head pose -> "
          f"{args.rate:g} Hz stream")
    return cmd_track_rgbd(ns)


def cmd_demo(args) -> int:
    _x64()
    if args.duration is not None and (args.input or args.rgbd):  # it was ignored without a word
        raise ValueError("--duration sets the length of the synthetic motion; "
                         + ("--rgbd N sets the number of frames" if args.rgbd else
                            "with an input file the whole file is used")
                         + " (leave out --duration)")
    if args.rgbd:
        return _demo_rgbd(args)
    if args.input:
        traj = read_input(args.input, args.format)
        return _run_evaluation(traj.times, traj.positions, traj.quaternions, args,
                               f"phjax demo on {args.input}", args.input)
    from ..motion.simulate import synthetic_head_motion

    duration = DEMO_DURATION if args.duration is None else args.duration
    # before the motion is made (--duration 1e9 ran out of memory making it); the render
    # rate's own check follows in _run_evaluation
    check_fits({f"--duration {duration:g} s of synthetic motion ({SYNTHETIC_RATE:g} Hz)":
                (duration * SYNTHETIC_RATE, BYTES_PER_RENDER_SAMPLE["evaluate"])},
               "shorten --duration")
    t, p, q = synthetic_head_motion(duration=duration, rate=SYNTHETIC_RATE, seed=args.seed)
    return _run_evaluation(t, p, q, args, f"phjax demo: synthetic head motion ({duration:g} s)")


def cmd_evaluate(args) -> int:
    _x64()
    traj = read_input(args.ground_truth, args.format)
    return _run_evaluation(traj.times, traj.positions, traj.quaternions, args,
                           f"phjax evaluate {args.ground_truth}", args.ground_truth)


#: a gap between poses longer than this (s) is named by smooth: it is output as held rows
LONG_GAP = 10.0


def _warn_long_gap(name, traj, rate: float) -> None:
    """A one-line warning for the longest gap between poses when it exceeds :data:`LONG_GAP`
    (a paused recording: the stream coasts to rest and then writes the held pose at ``rate``
    until the next pose; ten hours were 4.3 million identical rows, unannounced)."""
    import warnings

    from .._np_quat import np_any_part
    from ..io import TrajectoryWarning

    t = traj.times[np_any_part(traj.positions, traj.quaternions)]
    if t.size < 2:
        return
    gaps = np.diff(t)
    k = int(np.argmax(gaps))
    if gaps[k] > LONG_GAP:
        warnings.warn(f"{name}: no pose for {gaps[k]:.4g} s after t = {t[k]:.6f} s (median "
                      f"interval {1e3 * np.median(gaps):.3g} ms): the stream comes to rest and "
                      f"holds the last pose through the gap, about {gaps[k] * rate:.0f} rows",
                      TrajectoryWarning, stacklevel=2)


def cmd_smooth(args) -> int:
    _x64()
    from .._np_quat import np_any_part
    from ..io import Trajectory, write_trajectory
    from ..tracking.tracker import reconstruct, track
    from ._tune import config_from_args, with_noise_from_args

    check_trajectory_output(args.output, args.out_format, "--out-format", inputs=[args.input])
    config = config_from_args(args)
    if args.lookahead is not None:
        lookahead = check_lookahead(args.lookahead)
        if args.offline:
            raise ValueError("--lookahead predicts the causal stream's display time; the offline "
                             "reconstruction (--offline) has no lookahead")
        import equinox as eqx

        from ..tracking.tracker import TrackerConfig

        config = eqx.tree_at(lambda c: c.lookahead, TrackerConfig() if config is None else config,
                             lookahead)
    traj = read_input(args.input, args.format, measurements=True)
    span = float(traj.times[-1] - traj.times[0])
    check_fits({f"--rate {args.rate:g} Hz over {span:.3g} s":
                (span * args.rate, BYTES_PER_RENDER_SAMPLE["smooth"])})
    _warn_long_gap(args.input, traj, args.rate)
    config, noise = with_noise_from_args(args, config, traj.times, traj.positions,
                                         traj.quaternions)
    if noise:
        print(noise)
    render = np.arange(traj.times[0], traj.times[-1], 1.0 / args.rate)

    fn = reconstruct if args.offline else track
    t0 = time.perf_counter()
    p, q = fn(traj.times, traj.positions, traj.quaternions, render, config=config)
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    ok = np_any_part(p, q)  # one-part data: that part
    out = Trajectory(render[ok], p[ok], q[ok])
    note = replaced_note(args.output)
    write_trajectory(args.output, out, format=args.out_format)
    print(f"{'offline' if args.offline else 'causal'} stream: {traj.num_samples} poses -> "
          f"{out.num_samples} at {args.rate:g} Hz in {time.perf_counter() - t0:.2f} s; "
          f"wrote {args.output}{note}")
    return 0


def _sensor_args(p, rgbd: bool = False):
    add_sensor_arguments(p.add_argument_group("sensor model and rendering"))
    p.add_argument("--lookahead", type=float_between(0.0, MAX_LOOKAHEAD_MS, "ms"), default=30.0,
                   metavar="MS",
                   help="the display latency to compare at besides 0, ms (default 30, at most "
                   f"{MAX_LOOKAHEAD_MS:g}: a frame "
                   "shown 30 ms after the pose is read; every method then predicts the pose for "
                   "that display time and is scored against the truth there; 0: only the "
                   "comparison at the render time)")
    p.add_argument("--plot", default="phjax_evaluation.png", metavar="PNG",
                   help="output: the PNG plot of the accuracy / smoothness frontier at each "
                   "lookahead, and beside it PNG_methods.png (every method's RMSE, jerk and "
                   "lag, and a zoom on the fastest motion) (default phjax_evaluation.png in the "
                   "current folder; '' for none); existing files are replaced (the output says so)"
                   + ("; with --rgbd no plot is drawn and the render-rate stream goes to this "
                      "path with the suffix .tum (default phjax_evaluation.tum; a temporary "
                      "file with --plot '')" if rgbd else ""))
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_argument(p)


def add_commands(sub) -> None:
    p = sub.add_parser(
        "demo", help="the main job: evaluate phjax and the baselines on the bundled synthetic head motion",
        description="Simulate a camera-rate sensor from a ground-truth head motion (by default the "
        "package's synthetic seated-VR head motion; or a trajectory file you name), run the causal "
        "phjax stream, the offline reconstruction and every tuned causal baseline (Kalman CV "
        "extrapolation, alpha-beta extrapolation, LaViola's DESP extrapolation, One Euro + hold, "
        "One Euro + extrapolation, snapshot interpolation, IMM extrapolation; references: raw "
        "hold, scipy cubic spline). "
        "First table: what you choose between, at lookahead 0 and at a display latency "
        "(--lookahead, default 30 ms; every method predicts to the display time): phjax, and "
        "each predictor (Kalman CV, alpha-beta, DESP, One Euro + extrapolation, the IMM "
        "extrapolation) at its tuned knob and at the knob with the lowest RMSE among those at "
        "most as jerky as phjax (the accuracy / smoothness frontier at phjax's smoothness; "
        "'never' where no knob is that smooth), with RMSE, jerk and lag. Second table: every method at its tuned setting (RMSE, RMS jerk, lag; best "
        "causal value per column in bold). Writes the frontier plot (RMSE vs jerk per knob, "
        "each lookahead; --plot, default phjax_evaluation.png) and the per-method plot beside "
        "it (phjax_evaluation_methods.png); with --rgbd the render-rate stream "
        "phjax_evaluation.tum instead.")
    p.add_argument("input", nargs="?", help="optional ground-truth trajectory file (TUM, EuRoC, CSV, ...)")
    add_format_argument(p, "format of INPUT")
    p.add_argument("--duration", type=positive_float, default=None,
                   help=f"length of the synthetic motion, s (default {DEMO_DURATION:g}; not with "
                   "INPUT)")
    p.add_argument("--rgbd", type=nonnegative_int, default=0, metavar="N",
                   help="instead: the end-to-end path on N frames of the package's synthetic RGB-D "
                   "head (YuNet + features + depth + ICP head pose, then the tracker); the YuNet "
                   "model is taken from the cache, seeded from ../shared/data when present, else "
                   "downloaded")
    _sensor_args(p, rgbd=True)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("evaluate", help="metrics of phjax and every baseline on a ground-truth file",
                       description="Like 'demo' on a ground-truth trajectory file: print the "
                       "comparison at lookahead 0 and at --lookahead (each predictor tuned and "
                       "as smooth as phjax), the metrics table of phjax and every tuned "
                       "baseline (best causal value per column in bold), and write the frontier "
                       "plot (--plot, default phjax_evaluation.png) and the per-method plot "
                       "beside it. Where the ground truth has a gap longer than 0.1 s (or 2.5 "
                       "of its median steps), the simulated sensor loses its frames and the "
                       "render samples there are not scored.")
    p.add_argument("ground_truth", help="ground-truth trajectory (TUM .txt, EuRoC/TUM-VI .csv, phjax .csv)")
    add_format_argument(p)
    _sensor_args(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("smooth", help="render a recorded pose stream at a given rate",
                       description="Read measured poses (any phjax.io format; a row whose "
                       "position and/or quaternion is NaN is a lost frame for that part and is "
                       "bridged by the tracker), run the causal phjax stream (or the offline "
                       "reconstruction with --offline) and write the poses at --rate to OUTPUT "
                       "(the causal stream leaves out render times before the first valid "
                       "pose; --offline holds that pose there). At least 2 "
                       "poses are needed.")
    p.add_argument("input", help="measured trajectory file")
    add_output_argument(p, "output file (.txt/.tum = TUM, .csv = plain CSV; see --out-format)")
    add_rate_argument(p, "output rate")
    p.add_argument("--offline", action="store_true", help="offline reconstruction (uses the future)")
    p.add_argument("--lookahead", type=nonnegative_float, default=None, metavar="MS",
                   help="display-time prediction of the causal stream, ms: the pose written for "
                   f"time t is the one predicted for t + MS (at most {MAX_LOOKAHEAD_MS:g}; "
                   "default: the --config's, else 0)")
    add_format_argument(p)
    p.add_argument("--out-format", default="auto", choices=OUTPUT_FORMATS,
                   help="output format (default auto: by the extension of OUTPUT)")
    add_config_argument(p)
    add_noise_argument(p)
    p.set_defaults(func=cmd_smooth)
