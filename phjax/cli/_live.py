"""Live command of the ``phjax`` CLI: ``live``."""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import threading
from pathlib import Path

from .._face_sizes import HEAD_SIZE_RANGE, IPD_RANGE
from .._live_defaults import LIVE_NOISE_WINDOW
from ._common import (
    add_format_argument,
    check_lookahead,
    file_name,
    FPS_RANGE,
    float_between,
    nonnegative_int,
    overwritten_input,
    positive_float,
    replaced_note,
)
from ._signals import defer_interrupt, finish_background_compilations, hold_signals

#: accepted ``--fov`` (horizontal field of view, degrees; ``--head-size`` and ``--ipd``: the
#: library's ranges): values outside are typing errors (a missing decimal point), and the
#: monocular front-end turned them into NaN or zero poses
FOV_RANGE = (10.0, 170.0)


def _hz(rate: float) -> str:
    return f"{rate:.1f} Hz" if math.isfinite(rate) else "- Hz"


class _Interrupted(BaseException):  # not caught by a library's "except Exception"
    """A stop signal while ``phjax live`` is still starting (its name as the message)."""


def _abandon(lt, source) -> None:
    """Release what a start that did not finish holds: the tracker's threads and worker, or
    the opened source (its socket, its worker process)."""
    try:
        if lt is not None:
            lt.stop(timeout=2.0)
        elif source is not None:
            source.close()
    except Exception:  # noqa: BLE001 - best effort on the way out; the first error is reported
        pass


def noise_window(text: str) -> int:
    """argparse type of ``--noise-window``: 0 (off) or an integer >= 8."""
    n = nonnegative_int(text)
    if 0 < n < 8:
        raise argparse.ArgumentTypeError(f"must be 0 (off) or an integer >= 8, got {text!r}")
    return n


def cmd_live(args) -> int:
    ms = args.lookahead
    check_lookahead(ms)
    tty = sys.stderr.isatty()
    source = lt = None
    running = False
    center_asked = False
    stop_asked = None
    previous = {}

    def on_stop(signum, frame):
        nonlocal stop_asked
        if not running:  # still starting (frames rendering, compiling): abandon the start
            stop_asked = signal.Signals(signum).name  # checked again once started
            if not defer_interrupt(signum, frame):  # (an import, a gc callback, JAX: later)
                raise _Interrupted(stop_asked)
            return
        lt.request_stop()
        if signum == signal.SIGINT:  # a second Ctrl-C interrupts the wait at once
            signal.signal(signal.SIGINT, signal.default_int_handler)

    def on_usr1(signum, frame):
        nonlocal center_asked
        if running:
            lt.center()
        else:  # re-centre as soon as the run starts
            center_asked = True

    if threading.current_thread() is threading.main_thread():
        # installed before the start, which can take a minute (a signal then ended in a
        # traceback, or killed the process for SIGUSR1); SIGINT even where it was inherited as
        # ignored (a job started with '&' from a script), so that 'kill -INT' still stops it
        previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, on_stop)
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, on_stop)
        if hasattr(signal, "SIGUSR1"):
            previous[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, on_usr1)

    def restore():
        for sig, handler in previous.items():
            signal.signal(sig, handler)

    # the capture thread's reports (a UDP source's malformed datagrams) and the main thread's
    # lines, one at a time: held until the start line, then each on a line of its own
    say_lock, held, started = threading.Lock(), [], False

    def report(line: str) -> None:
        with say_lock:
            if not started:
                held.append(line)
            else:
                print(("\n" + line) if tty and not args.quiet else line, file=sys.stderr,
                      flush=True)

    try:
        if args.log and Path(args.log).suffix.lower() not in ("", ".tum", ".txt"):
            raise ValueError(f"--log {args.log}: the log is a TUM file (t x y z qx qy qz qw, "
                             "space-separated); name it .tum or .txt")
        if args.log and overwritten_input(args.log, [args.source]) is not None:
            raise ValueError(f"--log {args.log}: is the replayed pose file; writing the log "
                             "would destroy it: name another file")
        import jax

        jax.config.update("jax_enable_x64", True)
        jax.config.update("jax_cpu_enable_async_dispatch", False)
        from ..live import LiveTracker, PoseReplaySource, live_tracker_config, open_source
        from ..live._udp import UdpSource

        source = open_source(args.source, model_dir=args.model_dir, ipd=args.ipd, fov=args.fov,
                             monocular=args.monocular, head_size=args.head_size,
                             format=args.format, fps=args.fps)
        dropped = source.out_of_range_text() if isinstance(source, PoseReplaySource) else ""
        if dropped:
            report(f"phjax live: warning: {args.source.removeprefix('poses:')}: {dropped}: "
                   "replayed as lost frames (OUT_OF_RANGE in the status line)")
        if isinstance(source, UdpSource):
            source.report = report  # from the capture thread
            source.open()  # a port in use fails now, not after the tracker's compilation
        config = dataclasses.replace(live_tracker_config(source.depth_free),
                                     lookahead=ms / 1e3, noise_window=args.noise_window,
                                     reacquire=args.reacquire)
        replaced = replaced_note(args.log) if args.log else ""  # before the log is opened
        lt = LiveTracker(source, args.output or [], rate=args.rate, duration=args.duration,
                         log=args.log, center=args.center, realtime=args.realtime,
                         config=config)
        lt.start()
        if stop_asked:
            raise _Interrupted(stop_asked)
        running = True
    except _Interrupted as e:
        _abandon(lt, source)
        finish_background_compilations("phjax live")
        restore()
        print(f"phjax live: stopped by {e} during the start; nothing was sent", file=sys.stderr)
        return 0
    except (ValueError, OSError) as e:  # SourceError and OutputError among them
        _abandon(lt, source)
        finish_background_compilations("phjax live")
        restore()
        print(f"phjax live: error: {e}", file=sys.stderr)
        return 2
    if center_asked:
        lt.center()
    outs = ", ".join(o.url for o in lt.outputs) or "none"
    with say_lock:  # the start line first, then the reports that came while starting
        print(f"phjax live: {lt.source.name} -> {outs} at {args.rate:g} Hz"
              + (f", lookahead {ms:g} ms" if ms else "")
              + (f", log {args.log}{replaced}" if args.log else ""), file=sys.stderr, flush=True)
        for line in held:
            print(line, file=sys.stderr, flush=True)
        held.clear()
        started = True

    def status(line: str) -> None:
        if args.quiet:
            return
        with say_lock:
            print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr,
                  flush=True)

    try:
        lt.run(status=status, status_interval=args.status_interval)
    except KeyboardInterrupt:  # a second Ctrl-C: do not wait long for a hanging camera read
        lt.stop(timeout=2.0)
    except Exception as e:  # noqa: BLE001 - a failing camera at run time
        print(f"\nphjax live: error: {e}", file=sys.stderr)
        finish_background_compilations("phjax live")
        restore()
        return 1
    except BaseException:
        restore()
        raise
    # the run is over: a Ctrl-C from now on (one sent at the summary line, as a user who sees
    # it might) must not raise while the optimised program may still be compiling, or the
    # interpreter's exit is interrupted in its wait for it (XLA aborts the process); held
    # until the wait below, then the previous handlers come back
    hold_signals("phjax live")
    if tty and not args.quiet:
        print(file=sys.stderr)
    s = lt.stats()
    print(f"phjax live: sent {s['sent']} poses in {s['elapsed']:.2f} s "
          f"({_hz(s['sent_hz'])}), {s['frames']} camera frames",
          file=sys.stderr)
    unread = s["status"].get("NO_FRAME", 0)
    if unread:
        print(f"phjax live: {unread} of {s['frames']} camera frames could not be read (a "
              "missing, damaged or undecodable image) and were lost", file=sys.stderr)
    for url, n in s["send_errors"].items():
        if n:
            print(f"phjax live: {url}: {n} of {s['sent']} packets could not be sent (nothing "
                  "listening on that port, or the network refused them)", file=sys.stderr)
    for url, n in s["out_of_range"].items():
        if n:
            print(f"phjax live: {url}: {n} of {s['sent']} poses not sent: a value beyond what "
                  "the format holds (OSC float32: 3.4e38) or no orientation", file=sys.stderr)
    if isinstance(lt.source, UdpSource):
        u = lt.source.stats()
        frame = (f"sender's frame interval {1e3 * u['frame_interval']:.1f} ms, "
                 f"{u['datagrams_per_frame']:g} datagrams per frame"
                 if math.isfinite(u["frame_interval"]) else "sender's frame interval unknown")
        print(f"phjax live: udp: {u['received']} datagrams received: {u['emitted']} poses "
              f"used, {u['repeated']} repeats of the last pose skipped, {u['superseded']} "
              f"superseded by a newer one, "
              + (f"{u['at_stop']} read as the run stopped, " if u["at_stop"] else "")
              + f"dropped {lt.source.dropped_text()}; {frame}",
              file=sys.stderr)
    finish_background_compilations("phjax live")
    restore()
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser(
        "live", help="live head tracking: camera in, smooth poses out to opentrack / OSC",
        description="Track a head live and send smooth render-rate poses. A worker process "
        "runs SOURCE's frames through the head-pose front-end (pose files and UDP input need "
        "none) and a capture thread feeds the streaming tracker; "
        "a render loop samples it at --rate on absolute deadlines and sends each pose to every "
        "--output (and to --log). SOURCE: synthetic[:N[:SEED]] (the rendered test head), an "
        "RGB-D folder (Biwi, TUM RGB-D, color/+depth/), webcam[:INDEX] or a video file "
        "(monocular: opentrack's head-pose network, or --monocular landmarks; a file plays at "
        "its own timestamps, at 30 fps when its header's frame rate is outside 1-240), "
        "realsense[:SERIAL] (pyrealsense2), poses:FILE (replay a pose file; rows with a "
        "position beyond 10 m, not a head pose, are replayed as lost frames and counted "
        "OUT_OF_RANGE, and a file of fewer than 2 usable poses is an error), "
        "udp://[HOST]:PORT (another tracker's opentrack UDP datagrams: x y z cm, yaw pitch "
        "roll deg; HOST default 0.0.0.0; add ?noise=monocular for a webcam tracker). Stops at "
        "the end of the source, after --duration, on Ctrl-C or SIGTERM; SIGUSR1 re-centres. "
        "Axes: see docs/live.md.")
    p.add_argument("source", help="synthetic[:N[:SEED]] (N >= 1, 0 <= SEED < 2**32) | RGB-D "
                   "folder | webcam[:INDEX] (INDEX 0-99) | video file | realsense[:SERIAL] | "
                   "poses:FILE | udp://[HOST]:PORT")
    add_format_argument(p, "format of a poses:FILE source")
    p.add_argument("--output", "-o", action="append", metavar="URL",
                   help="opentrack://HOST[:PORT] (default port 4242; 48-byte datagrams of six "
                   "float64: x y z cm, yaw pitch roll deg) or osc://HOST[:PORT] (default 9000; "
                   "/phjax/pose t x y z qw qx qy qz); repeatable")
    p.add_argument("--rate", type=float, default=120.0,
                   help="render rate, Hz (default 120; at most 1000: each pose is predicted and "
                   "sent on its own deadline)")
    p.add_argument("--duration", type=positive_float, default=None,
                   help="stop after this many seconds (a positive finite number; default: end "
                   "of the source / Ctrl-C). Longer than the source: after its end the stream "
                   "coasts to rest and the held pose is sent until then")
    p.add_argument("--log", type=file_name, default=None, metavar="FILE.tum",
                   help="write every sent pose to this TUM file (.tum or .txt; an existing "
                   "one is replaced, and the start line says so)")
    p.add_argument("--lookahead", type=float, default=0.0, metavar="MS",
                   help="display-time prediction, ms (default 0, at most 200): send the pose "
                   "predicted for MS after the render time. Set it to the display's "
                   "motion-to-photon latency minus what the receiving program already predicts "
                   "(a VR runtime that predicts to its own display time: 0; a game that draws "
                   "the pose as received: its latency, typically 20-50)")
    p.add_argument("--noise-window", type=noise_window, default=LIVE_NOISE_WINDOW, metavar="N",
                   help="online measurement-noise floor: the filter's measurement noise is "
                   "raised to the white noise measured over the last N frames when that is "
                   f"larger (default {LIVE_NOISE_WINDOW}, 2 s at 30 FPS; 0: off, the configured "
                   "noise only; else at least 8). A source noisier than assumed (a webcam, "
                   "another tracker) is then smoothed as much as its noise needs")
    p.add_argument("--reacquire", action="store_true",
                   help="after a loss long enough for the stream to come to rest (coast time "
                   "+ stop time, 0.15 s by default, past its last segment), jump to the "
                   "re-acquired pose at once instead of gliding there within one horizon "
                   "from where it stopped (TrackerConfig.reacquire)")
    p.add_argument("--center", action="store_true",
                   help="the first pose becomes the origin (SIGUSR1 re-centres at any time)")
    p.add_argument("--monocular", choices=("net", "landmarks"), default="net",
                   help="monocular sources: 'net' (default; opentrack's head-pose network, "
                   "research / non-commercial weights) or 'landmarks' (YuNet's five landmarks "
                   "+ PnP)")
    p.add_argument("--head-size", type=float_between(*HEAD_SIZE_RANGE, "m"), default=None,
                   metavar="M",
                   help="monocular 'net': assumed vertical head size, m (default 0.20; "
                   f"{HEAD_SIZE_RANGE[0]:g}-{HEAD_SIZE_RANGE[1]:g})")
    p.add_argument("--ipd", type=float_between(*IPD_RANGE, "m"), default=None, metavar="M",
                   help="monocular 'landmarks': assumed inter-pupillary distance, m (default "
                   f"0.063; {IPD_RANGE[0]:g}-{IPD_RANGE[1]:g})")
    p.add_argument("--fov", type=float_between(*FOV_RANGE, "degrees"), default=60.0,
                   metavar="DEG",
                   help="monocular sources: horizontal field of view of the camera, degrees "
                   f"(default 60; {FOV_RANGE[0]:g}-{FOV_RANGE[1]:g})")
    p.add_argument("--fps", type=float_between(*FPS_RANGE, "Hz"), default=None, metavar="FPS",
                   help="frame rate of an RGB-D folder whose frames carry no timestamps (Biwi, "
                   "color/ + depth/; default 30; slambook's keyframes: 1); TUM RGB-D folders "
                   "and video files play at their own timestamps")
    p.add_argument("--model-dir", default=None,
                   help="model cache: YuNet, the head-pose network (default $PHJAX_MODEL_DIR "
                   "or ~/.cache/phjax/models)")
    p.add_argument("--status-interval", type=positive_float, default=1.0,
                   help="seconds between status lines (default 1)")
    p.add_argument("--realtime", action="store_true",
                   help="run the render loop with real-time scheduling (SCHED_FIFO; Linux, "
                   "needs CAP_SYS_NICE or an rtprio limit; best effort): keeps the deadlines "
                   "on a busy CPU")
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.set_defaults(func=cmd_live)
