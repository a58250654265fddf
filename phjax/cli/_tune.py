"""``phjax tune`` (gradient-based tuning of the causal tracker) and the ``--config`` option.

:func:`add_config_argument` / :func:`config_from_args` give any command a ``--config
PARAMS.json`` option reading a configuration written by ``phjax tune`` (or
:func:`phjax.tracking.tuning.save_config`).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from ._common import (
    add_format_argument,
    add_output_argument,
    add_sensor_arguments,
    check_output,
    nonnegative_float,
    positive_float,
    positive_int,
    read_input,
    replaced_note,
)

__all__ = ["add_commands", "add_config_argument", "add_noise_argument", "config_from_args",
           "cmd_tune", "with_noise_from_args"]


def add_config_argument(parser) -> None:
    """Add ``--config PARAMS.json`` (tracker parameters from ``phjax tune``) to ``parser``."""
    parser.add_argument("--config", metavar="PARAMS.json", default=None,
                        help="tracker parameters (JSON written by 'phjax tune'); default: the "
                        "built-in defaults")


#: a tuned parameter that moved by more than this factor gets a warning
FAR_MOVE = 100.0


def _far_moves(start: dict, tuned: dict) -> dict:
    """``name -> factor`` of the parameters that moved by more than :data:`FAR_MOVE` (a
    ``log_`` parameter: by more than ``log(FAR_MOVE)``; a flat loss lets BFGS wander there)."""
    out = {}
    for k, v in tuned.items():
        a, b = float(start[k]), float(v)
        if "log_" in k.rsplit(".", 1)[-1]:
            factor = math.exp(min(abs(b - a), 700.0))
        elif a > 0 and b > 0:
            factor = max(a / b, b / a)
        else:
            continue
        if factor > FAR_MOVE:
            out[k] = factor
    return out


def config_from_args(args):
    """The :class:`~phjax.TrackerConfig` named by ``args.config`` (``None`` when not given).

    Raises:
        FileNotFoundError, ValueError: unreadable or invalid file (the CLI prints these).
    """
    path = getattr(args, "config", None)
    if not path:
        return None
    from ..tracking.tuning import load_config
    from ._common import MAX_LOOKAHEAD_MS

    config = load_config(path)
    ms = 1e3 * float(config.lookahead)
    if not 0.0 <= ms <= MAX_LOOKAHEAD_MS:  # the bound --lookahead has, for the same field
        raise ValueError(f"{path}: tracker.lookahead must be between 0 and "
                         f"{MAX_LOOKAHEAD_MS / 1e3:g} s, got {ms / 1e3:g}")
    return config


def _noise_value(text: str):
    """``'config'``, ``'auto'`` or ``(mm, deg)`` from a ``--measurement-noise`` value."""
    import argparse

    if text in ("config", "auto", "floor"):
        return text
    try:
        mm, deg = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'config', 'auto', 'floor' or 'MM,DEG', got {text!r}") from None
    if not (np.isfinite(mm) and np.isfinite(deg) and mm > 0 and deg > 0):
        raise argparse.ArgumentTypeError(f"stds must be positive and finite, got {text!r}")
    from ..tracking._config_ranges import CONFIG_RANGES

    # the configuration's range (SI: m, rad), beyond which the tracker fails; in the option's units
    low, high = CONFIG_RANGES["kalman.pos_meas_noise"]
    rlow, rhigh = CONFIG_RANGES["kalman.rot_meas_noise"]
    for name, x, lo, hi, unit in (("position", mm, low * 1e3, high * 1e3, "mm"),
                                  ("orientation", deg, np.degrees(rlow), np.degrees(rhigh), "deg")):
        if not lo <= x <= hi:
            raise argparse.ArgumentTypeError(
                f"{name} std {x:g} {unit} is out of range [{lo:.3g}, {hi:.3g}] {unit} (beyond it "
                f"the tracker fails or outputs NaN poses), got {text!r}")
    return mm, deg


def add_noise_argument(parser, has_config: bool = True) -> None:
    """Add ``--measurement-noise {config,auto,floor,MM,DEG}`` to ``parser`` (``has_config``:
    the command also has ``--config``)."""
    default = ("from --config or the built-in 5 mm / 1 deg sensor" if has_config
               else "the built-in 5 mm / 1 deg sensor")
    parser.add_argument(
        "--measurement-noise", metavar="NOISE", default="config", type=_noise_value,
        help=f"the filters' measurement noise: 'config' (default: {default}), 'auto' (estimated from the input poses themselves, "
        "phjax.tracking.estimate_measurement_noise: right for white noise such as a per-frame "
        "head-pose front-end; a SLAM estimate with frame-to-frame correlated errors is often "
        "better with the default), 'floor' (the configured noise, raised to that estimate "
        "where it is larger, never lowered: safe for a source of unknown noise) or 'MM,DEG' "
        "(position std in mm, orientation std in degrees)")


def with_noise_from_args(args, config, times, positions, quaternions):
    """``config`` (``None``: the defaults) with ``args.measurement_noise`` applied; returns the
    config and a one-line description of the noise used.

    Raises:
        ValueError: 'auto' on too few valid samples (the CLI prints it; 'floor' keeps the
            configured noise there).
    """
    from ..tracking.noise import estimate_measurement_noise, with_measurement_noise
    from ..tracking.tracker import TrackerConfig, _stream_filter

    value = getattr(args, "measurement_noise", "config")
    if value == "config":
        return config, None
    config = TrackerConfig() if config is None else config
    if value in ("auto", "floor"):
        try:
            noise = estimate_measurement_noise(times, positions, quaternions)
        except ValueError as e:
            if value == "floor":  # a floor over nothing: the configured noise, as documented
                return config, f"measurement noise: the configured (no estimate: {e})"
            raise ValueError(f"--measurement-noise {value}: cannot estimate the noise from this "
                             f"input ({e}); give it as MM,DEG") from None
        pos, rot = float(noise.pos_meas_noise), float(noise.rot_meas_noise)
        pos = pos if np.isfinite(pos) and pos > 0 else None
        rot = rot if np.isfinite(rot) and rot > 0 else None
        if pos is None and rot is None:
            if value == "floor":
                return config, ("measurement noise: the configured (too few consecutive valid "
                                "poses to estimate the input's)")
            raise ValueError(f"--measurement-noise {value}: the input has too few consecutive "
                             "valid poses to estimate the noise")
        how = "estimated from the input"
        if value == "floor":  # never below the configured noise (of the causal stream's filter)
            filt = _stream_filter(config)
            pos = max(float(filt.pos_meas_noise), pos) if pos is not None else None
            rot = max(float(filt.rot_meas_noise), rot) if rot is not None else None
            how = "the configured, raised to the input's estimate where larger"
    else:
        mm, deg = value
        pos, rot, how = mm / 1e3, float(np.deg2rad(deg)), "given"
    config = with_measurement_noise(config, pos=pos, rot=rot)
    desc = (f"measurement noise ({how}): "
            + (f"{pos * 1e3:.3g} mm" if pos is not None else "position default") + ", "
            + (f"{np.degrees(rot):.3g} deg" if rot is not None else "orientation default"))
    return config, desc


def _ratio(a, b) -> str:
    return "-" if not (np.isfinite(a) and np.isfinite(b) and b > 0) else f"{a / b:.3f}"


def cmd_tune(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from ..motion.simulate import SensorModel
    from ..tracking.tracker import TrackerConfig
    from ..tracking.tuning import (
        check_parameters,
        default_parameters,
        measured_recording,
        prepare_recordings,
        save_config,
        tune_tracker,
        tuning_data,
    )

    if args.max_steps < 1:
        raise ValueError(f"--max-steps must be >= 1, got {args.max_steps}")
    if args.measured and len(args.measured) != len(args.train):
        raise ValueError(f"--measured: give one measurement file per ground-truth file, got "
                         f"{len(args.measured)} for {len(args.train)}")
    if args.align and not args.measured:
        raise ValueError("--align needs --measured (simulated measurements are in the ground "
                         "truth's frame)")
    start = config_from_args(args)
    start = TrackerConfig() if start is None else start
    params = default_parameters(start) if not args.parameters else tuple(
        p.strip() for p in args.parameters.split(",") if p.strip())
    check_parameters(start, params)  # unknown names: one-line error before data preparation
    check_output(args.output, inputs=[*args.train, *(args.measured or [])])
    trajs = [read_input(f, args.format) for f in args.train]
    sensor = SensorModel(rate=args.camera_rate, sigma_p=args.sigma_p / 1e3,
                         sigma_r=float(np.deg2rad(args.sigma_r)), dropout=args.dropout,
                         jitter=args.jitter)
    t0 = time.perf_counter()
    first = f"; first {args.seconds:g} s" if args.seconds else ""
    if args.measured:
        recs = []
        for gt_file, gt, f in zip(args.train, trajs, args.measured):
            try:
                recs.append(measured_recording(gt, read_input(f, args.format, measurements=True),
                                               render_rate=args.rate, seconds=args.seconds,
                                               align=args.align))
            except ValueError as err:
                raise ValueError(f"{f} (against {gt_file}): {err}") from None
        data = tuning_data(recs)
        source = (f"measurements: {', '.join(Path(f).name for f in args.measured)}"
                  + (" (rigidly aligned to the ground truth)" if args.align else "")
                  + f"; render {args.rate:g} Hz{first}")
    else:
        data = prepare_recordings(trajs, sensor=sensor, render_rate=args.rate, seed=args.seed,
                                  seconds=args.seconds)
        source = (f"sensor: {args.camera_rate:g} Hz, sigma_p {args.sigma_p:g} mm, sigma_r "
                  f"{args.sigma_r:g} deg, dropout {100 * args.dropout:g} %, jitter "
                  f"{args.jitter:g}, seed {args.seed}; render {args.rate:g} Hz{first}")
    names = [Path(f).name for f in args.train]
    print(f"# phjax tune: {len(trajs)} recording(s), lambda {args.lam:g}")
    print(source)
    print(f"parameters: {', '.join(params)}")
    print(f"prepared in {time.perf_counter() - t0:.1f} s; the first step compiles the "
          "differentiated stream (about a minute)", flush=True)

    def progress(info):
        vals = "  ".join(f"{k}={v:.4g}" for k, v in info.parameters.items())
        print(f"step {info.step:3d}  loss {info.loss:.5f}  trial {info.trial_loss:.5f} "
              f"{'accepted' if info.accepted else 'rejected'}  "
              f"[{time.perf_counter() - t0:.1f} s]  {vals}", flush=True)

    config, res = tune_tracker(data, lam=args.lam, config=start, parameters=params,
                               max_steps=args.max_steps, rotation_weight=args.rotation_weight,
                               position_weight=args.position_weight, progress=progress)
    meta = {
        "tool": "phjax tune",
        "lambda": args.lam,
        "position_weight": args.position_weight,
        "rotation_weight": args.rotation_weight,
        "train": [str(f) for f in args.train],
        "seconds": args.seconds,
        "render_rate": args.rate,
        "measured": [str(f) for f in args.measured] if args.measured else None,
        "align": bool(args.align),
        "sensor": None if args.measured else {
            "rate": args.camera_rate, "sigma_p_mm": args.sigma_p, "sigma_r_deg": args.sigma_r,
            "dropout": args.dropout, "jitter": args.jitter, "seed": args.seed},
        "parameters": list(params),
        "status": res.message,
        "steps": res.num_steps,
        "loss": {"initial": res.initial_loss, "final": res.final_loss},
    }
    note = replaced_note(args.output)
    path = save_config(args.output, config, metadata=meta)
    print()
    print(f"{res.message} after {res.num_steps} steps ({res.num_accepted_steps} accepted); "
          f"loss {res.initial_loss:.5f} -> {res.final_loss:.5f} (the Kalman-CV reference scores "
          f"{1 + args.lam:g})")
    print()
    print("| parameter | start | tuned |")
    print("|---|---|---|")
    for k in res.parameters:
        print(f"| {k} | {res.initial_parameters[k]:.5g} | {res.parameters[k]:.5g} |")
    print()
    for k, factor in _far_moves(res.initial_parameters, res.parameters).items():
        print(f"phjax tune: warning: {k} moved by a factor of {factor:.3g} "
              f"({res.initial_parameters[k]:.5g} -> {res.parameters[k]:.5g}): the training data "
              "hardly determine it; tune on longer or more recordings (--seconds) or leave it "
              "out (--parameters)", file=sys.stderr)
    print("ratios to the Kalman-CV reference (start -> tuned)")
    print()
    print("| recording | pos RMSE | rot RMSE | pos jerk | rot jerk |")
    print("|---|---|---|---|---|")
    for i, name in enumerate(names):
        cells = [f"{_ratio(res.initial_terms[i, k], res.reference[i, k])} -> "
                 f"{_ratio(res.terms[i, k], res.reference[i, k])}" for k in range(4)]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print(f"\nwrote {path}{note}")
    return 0


def add_commands(sub) -> None:
    """Register ``phjax tune`` on the sub-parser collection ``sub``."""
    p = sub.add_parser(
        "tune", help="tune the causal tracker's parameters by gradient descent on recordings",
        description="Simulate the sensor on ground-truth trajectory files (or read the real "
        "pose streams given by --measured), differentiate the whole causal stream with respect "
        "to the tracker's parameters (by default the IMM "
        "filter's model noise densities and switch rate and the segment horizon; log "
        "parameterisation) and minimise RMSE + lambda x RMS jerk (position and "
        "rotation, each relative to the tuned Kalman constant-velocity extrapolation, so lambda "
        "is dimensionless and that baseline scores 1 + lambda) with optimistix BFGS. Writes a "
        "JSON configuration for --config of the other commands.")
    p.add_argument("train", nargs="+",
                   help="ground-truth trajectory file(s) (TUM, EuRoC, CSV, ...)")
    p.add_argument("--lambda", dest="lam", type=nonnegative_float, required=True,
                   help="weight of the jerk terms (0 = accuracy only; 1 = equal weight)")
    add_output_argument(p, "output JSON file (the tuned configuration)")
    add_format_argument(p)
    p.add_argument("--seconds", type=positive_float, default=None,
                   help="use only the first S seconds of each file")
    p.add_argument("--max-steps", type=positive_int, default=50, help="maximum BFGS steps (default 50)")
    p.add_argument("--parameters", default=None,
                   help="comma-separated parameters to tune (default, IMM filter: "
                   "imm.position_models.K.log_q and imm.rotation_models.K.log_q for every model "
                   "K, log_switch_rate, horizon; with a --config of the single-model filter: "
                   "pos_process_noise, rot_process_noise, pos_meas_noise, rot_meas_noise, "
                   "horizon). Names of every tunable parameter: "
                   "phjax.tracking.tuning.tunable_parameters()")
    p.add_argument("--position-weight", type=nonnegative_float, default=1.0,
                   help="weight of the position terms (default 1)")
    p.add_argument("--rotation-weight", type=nonnegative_float, default=1.0,
                   help="weight of the rotation terms (default 1)")
    add_config_argument(p)
    m = p.add_argument_group("real measurements (instead of the simulated sensor)")
    m.add_argument("--measured", nargs="+", metavar="EST", default=None,
                   help="pose-stream file(s) the tracker sees (e.g. a SLAM or head-pose "
                   "estimate), one per ground-truth file and in the same order, on the ground "
                   "truth's clock; the sensor options below, except --rate, are then unused")
    m.add_argument("--align", action="store_true",
                   help="move each --measured stream into its ground truth's frame by the rigid "
                   "transform that best maps its positions onto the ground truth (SE(3) "
                   "least squares, as evo's APE alignment); without it the frames must agree")
    g = p.add_argument_group("sensor model and rendering")
    add_sensor_arguments(g, "random seed of the sensor simulation")
    p.set_defaults(func=cmd_tune)
