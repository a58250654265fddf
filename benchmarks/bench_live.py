"""Live runner timing: render-interval jitter and sample age while the front-end works.

    python benchmarks/bench_live.py [--seconds 8] [--rates 120 250] [--model-dir DIR] [--realtime]

For each render rate, ``phjax.live.LiveTracker`` runs (real clock, one opentrack output to a
loopback listener) on two sources:

* ``synthetic`` - the rendered synthetic head through the RGB-D front-end (face detection,
  keypoints, RANSAC, ICP: the capture thread keeps a CPU core busy), paced at 30 Hz;
* ``poses`` - a pose replay at 30 Hz (no vision: the render loop alone), for comparison.

Columns: frames the front-end finished per second, samples sent per second, render interval
p50 / p99 / max (ms), jitter p50 / p99 (|interval - 1/rate|, ms), deadlines missed (skipped
whole periods), and the sample age p50 / p99 (ms): render time minus the capture time of the
newest camera frame whose pose the sample is based on (so it includes the front-end's latency).
The machine's load average is printed: on a shared machine the numbers include other users'
work.
"""

from __future__ import annotations

import argparse
import os
import socket
import threading

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_enable_async_dispatch", False)

import numpy as np

from phjax.live import LiveTracker, PoseReplaySource, open_source


def _listener():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    stop = threading.Event()

    def run():
        while not stop.is_set():
            try:
                sock.recv(256)
            except (TimeoutError, OSError):
                continue

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return sock.getsockname()[1], lambda: (stop.set(), th.join(), sock.close())


def _poses(seconds: float):
    t = np.arange(int(30 * (seconds + 2))) / 30.0
    rv = np.radians(20) * np.sin(2 * np.pi * 0.3 * t)[:, None] * np.array([0, 1, 0])
    ang = np.linalg.norm(rv, axis=1)
    q = np.c_[np.cos(ang / 2), np.sin(ang / 2)[:, None] * rv / np.maximum(ang, 1e-12)[:, None]]
    p = np.c_[0.02 * np.sin(t), np.zeros_like(t), 0.7 + 0 * t]
    return PoseReplaySource(t, p, q, name="poses")


def run(source, rate: float, seconds: float, realtime: bool = False) -> dict:
    port, close = _listener()
    lt = LiveTracker(source, [f"opentrack://127.0.0.1:{port}"], rate=rate, duration=seconds,
                     realtime=realtime)
    try:
        lt.run()
    finally:
        close()
    iv = lt.intervals.values()
    age = lt.ages.values()
    s = lt.stats()
    period = 1.0 / rate
    jit = np.abs(iv - period)
    ok = s["status"].get("OK", 0)
    return {
        "fps": ok / seconds, "sent": lt.sent / seconds,
        "p50": 1e3 * np.median(iv), "p99": 1e3 * np.percentile(iv, 99), "max": 1e3 * iv.max(),
        "j50": 1e3 * np.median(jit), "j99": 1e3 * np.percentile(jit, 99),
        "missed": lt.missed_deadlines, "a50": 1e3 * np.median(age),
        "a99": 1e3 * np.percentile(age, 99),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[120.0, 250.0])
    ap.add_argument("--model-dir", default=None, help="YuNet model cache")
    ap.add_argument("--realtime", action="store_true",
                    help="render thread under SCHED_FIFO (as phjax live --realtime)")
    args = ap.parse_args()
    n_frames = int(30 * (args.seconds + 2)) + 3
    rows = []
    for rate in args.rates:
        for name in ("synthetic", "poses"):
            src = (open_source(f"synthetic:{n_frames}", model_dir=args.model_dir)
                   if name == "synthetic" else _poses(args.seconds))
            rows.append((rate, name, run(src, rate, args.seconds, args.realtime)))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\nlive runner, {args.seconds:g} s per row, {os.cpu_count()} CPUs, load average "
          f"{load:.1f}, realtime {args.realtime}")
    print(f"{'rate':>5} {'source':>9} {'poses/s':>7} {'sent/s':>7} {'iv p50':>7} {'iv p99':>7} "
          f"{'iv max':>7} {'jit p50':>7} {'jit p99':>7} {'missed':>6} {'age p50':>7} "
          f"{'age p99':>7}")
    for rate, name, r in rows:
        print(f"{rate:5.0f} {name:>9} {r['fps']:7.1f} {r['sent']:7.1f} {r['p50']:7.2f} "
              f"{r['p99']:7.2f} {r['max']:7.2f} {r['j50']:7.3f} {r['j99']:7.2f} "
              f"{r['missed']:6d} {r['a50']:7.0f} {r['a99']:7.0f}")


if __name__ == "__main__":
    main()
