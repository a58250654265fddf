"""Live path deadlines: frames in, packets out, intervals and ages for each source type.

    python benchmarks/bench_live.py [--seconds 60] [--rate 120] [--sources poses rgbd synthetic udp]
                                    [--modes worker thread] [--realtime no yes] [--model-dir DIR]

Each row runs ``phjax.live.LiveTracker`` in real time for ``--seconds`` (after its start-up),
sending to an opentrack listener on loopback, with one source:

* ``poses`` - a 30 Hz pose file replayed (``poses:FILE``; no front-end);
* ``rgbd`` - an RGB-D folder (TUM layout) of real Kinect frames: Biwi frame 54 of
  ``../shared/data/biwi_kinect_head_pose_samples`` (a static head), repeated at 30 Hz, read
  from PNG files and run through the RGB-D front-end;
* ``synthetic`` - the rendered synthetic head ``synthetic:N`` (30 Hz; its frames are rendered
  once into the frame cache, ``phjax.live.frame_cache_dir()``, on the first run: several
  minutes and 1.5 MB a frame for 60 s);
* ``udp`` - opentrack datagrams sent at 30 Hz to ``udp://127.0.0.1:PORT`` (only where
  ``phjax.live._udp`` exists).

``--modes``: ``worker`` (default) runs a vision source's frames and front-end in a worker
process (``phjax.live.WorkerSource``); ``thread`` runs them in the capture thread of the
render loop's process, as before the worker existed (the comparison). ``--realtime yes``
runs the render thread under ``SCHED_FIFO`` (needs ``CAP_SYS_NICE``; as ``phjax live
--realtime``).

Columns: camera frames in per second (measurements that reached the tracker) and frames
lost (late or without a pose); packets out per second; p50 / p99 / max interval between
packets (ms, send times); deadlines missed (skipped whole periods); the front-end's own time
per frame (p50, ms, measured where it runs); the measurement age (capture to stream update,
p50 / p99, ms) and the end-to-end age of the sent pose (capture of the newest applied frame
to the send, p50 / p99, ms). Targets (issue 30) are checked in the last column: packets >=
0.98 x rate (``n``), p99 interval <= 1.5 periods (``p``), no gap > 3 periods (``g``), age p50
<= front-end time + 10 ms (``a``); a letter marks a target missed. The load average (1 min,
before and after each row) is printed: on a shared machine the numbers include other users'
work.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_enable_async_dispatch", False)

import numpy as np

from phjax._np_quat import np_from_rotvec
from phjax.io import Trajectory, write_tum
from phjax.live import LiveTracker, open_source, opentrack_values
from _models import seeded_cache

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("PHJAX_SHARED_DATA", REPO.parent / "shared" / "data"))
SOURCES = ("poses", "rgbd", "synthetic", "udp")


def _has_udp() -> bool:
    try:
        import phjax.live._udp  # noqa: F401
    except ImportError:
        return False
    return True


class _Listener:
    """Counts datagrams on 127.0.0.1 (a thread blocked in recv, without the GIL)."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.count = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                self.sock.recv(256)
            except (TimeoutError, OSError):
                continue
            self.count += 1

    def close(self):
        time.sleep(0.1)
        self._stop.set()
        self._thread.join()
        self.sock.close()


def _motion(seconds: float, rate: float = 30.0):
    t = np.arange(int(rate * seconds)) / rate
    rv = np.radians(20) * np.sin(2 * np.pi * 0.3 * t)[:, None] * np.array([0.3, 1, 0.2])
    p = np.c_[0.03 * np.sin(2 * np.pi * 0.2 * t), 0.01 * np.sin(t), 0.7 + 0 * t]
    return t, p, np_from_rotvec(rv)


def _pose_file(folder: Path, seconds: float) -> str:
    path = folder / "poses.tum"
    write_tum(path, Trajectory(*_motion(seconds)))
    return f"poses:{path}"


def _rgbd_folder(folder: Path, seconds: float) -> str:
    """A TUM RGB-D folder: Biwi frame 54 (registered colour + depth) at 30 Hz."""
    import cv2

    from phjax.vision.rgbd_io import read_biwi_frame

    biwi = SHARED / "biwi_kinect_head_pose_samples"
    if not biwi.is_dir():
        raise SystemExit(f"bench_live: the rgbd row needs {biwi}")
    frame = read_biwi_frame(biwi, "00054")
    out = folder / "biwi54_tum"
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    cv2.imwrite(str(out / "rgb" / "54.png"), frame.color)
    depth = np.nan_to_num(frame.depth, nan=0.0)
    cv2.imwrite(str(out / "depth" / "54.png"), np.clip(np.round(depth * 5000), 0, 65535)
                .astype(np.uint16))
    n = int(30 * seconds)
    stamps = 1000.0 + np.arange(n) / 30.0
    (out / "rgb.txt").write_text("".join(f"{t:.6f} rgb/54.png\n" for t in stamps))
    (out / "depth.txt").write_text("".join(f"{t:.6f} depth/54.png\n" for t in stamps))
    return str(out)


def _udp_sender(port_of, seconds: float, stop: threading.Event) -> threading.Thread:
    """Sends opentrack datagrams at 30 Hz (absolute schedule) once the port is known."""
    t, p, q = _motion(seconds)
    pack = struct.Struct("<6d")

    def run():
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        while port_of() is None and not stop.is_set():
            time.sleep(0.01)
        start = time.perf_counter()
        for i in range(t.size):
            delay = start + t[i] - time.perf_counter()
            if stop.wait(max(delay, 0.0)):
                break
            sock.sendto(pack.pack(*opentrack_values(p[i], q[i])), ("127.0.0.1", port_of()))
        sock.close()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def run_row(name: str, spec: str, *, rate: float, seconds: float, worker: bool,
            realtime: bool, model_dir, capture_nice: int | None = 5) -> dict:
    listener = _Listener()
    sends, e2e = [], []
    stop_sender = threading.Event()
    sender = None
    if name == "udp":
        from phjax.live._udp import UdpSource

        source = UdpSource("127.0.0.1", 0, report=lambda line: None)
    else:
        source = open_source(spec, model_dir=model_dir, worker=worker)

    def on_sample(s):
        now = time.perf_counter()
        sends.append(now)
        if np.isfinite(s.age):
            e2e.append(now - (lt.t0 + s.t - s.age))

    lt = LiveTracker(source, [f"opentrack://127.0.0.1:{listener.port}"], rate=rate,
                     duration=seconds, realtime=realtime, callback=on_sample,
                     capture_nice=capture_nice)
    load0 = os.getloadavg()[0]
    try:
        lt.start()
        if name == "udp":
            sender = _udp_sender(lambda: source.port or None, seconds + 1, stop_sender)
        lt.run()
    finally:
        stop_sender.set()
        if sender is not None:
            sender.join()
        listener.close()
    s = lt.stats()
    iv = np.diff(sends)
    period = 1.0 / rate
    applied = lt.applied_ages.values()
    work = lt.work_times.values()
    fe = float(np.median(work)) if work.size else 0.0
    row = {
        "source": name, "mode": ("worker" if worker else "thread") if lt.source.front_end
        else "-", "rt": realtime and lt.realtime_active, "load": (load0, os.getloadavg()[0]),
        "fps": lt.frames / s["elapsed"], "lost": s["lost"],
        "out": listener.count / s["elapsed"], "sent": lt.sent, "received": listener.count,
        "iv50": 1e3 * np.median(iv), "iv99": 1e3 * np.percentile(iv, 99),
        "ivmax": 1e3 * iv.max(), "missed": lt.missed_deadlines, "fe": 1e3 * fe,
        "age50": 1e3 * np.median(applied), "age99": 1e3 * np.percentile(applied, 99),
        "e2e50": 1e3 * np.median(e2e), "e2e99": 1e3 * np.percentile(e2e, 99),
    }
    misses = ""
    if row["out"] < 0.98 * rate:
        misses += "n"
    if row["iv99"] > 1e3 * 1.5 * period:
        misses += "p"
    if row["ivmax"] > 1e3 * 3 * period:
        misses += "g"
    if row["age50"] > row["fe"] + 10.0:
        misses += "a"
    row["targets"] = misses or "ok"
    return row


HEADER = ("| source | front-end | realtime | load | frames in/s | lost | packets/s | interval "
          "p50 / p99 / max (ms) | missed | front-end p50 (ms) | age p50 / p99 (ms) | sent age "
          "p50 / p99 (ms) | targets |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def format_row(r: dict) -> str:
    return (f"| {r['source']} | {r['mode']} | {'yes' if r['rt'] else 'no'} | "
            f"{r['load'][0]:.1f}-{r['load'][1]:.1f} | {r['fps']:.1f} | {r['lost']} | "
            f"{r['out']:.1f} | {r['iv50']:.2f} / {r['iv99']:.2f} / {r['ivmax']:.1f} | "
            f"{r['missed']} | {r['fe']:.0f} | {r['age50']:.0f} / {r['age99']:.0f} | "
            f"{r['e2e50']:.0f} / {r['e2e99']:.0f} | {r['targets']} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="length of each row, s")
    ap.add_argument("--rate", type=float, default=120.0, help="render rate, Hz")
    ap.add_argument("--sources", nargs="+", choices=SOURCES, default=list(SOURCES))
    ap.add_argument("--modes", nargs="+", choices=("worker", "thread"), default=["worker"],
                    help="where a vision source's front-end runs (see above)")
    ap.add_argument("--realtime", nargs="+", choices=("no", "yes"), default=["no"])
    ap.add_argument("--model-dir", default=None,
                    help="model cache (YuNet; seeded from the shared data when it lacks it)")
    ap.add_argument("--capture-nice", type=int, default=5,
                    help="niceness increment of the front-end (LiveTracker capture_nice)")
    args = ap.parse_args()
    sources = [s for s in args.sources if s != "udp" or _has_udp()]
    model_dir = args.model_dir
    if {"rgbd", "synthetic"} & set(sources):
        model_dir = seeded_cache(model_dir)
    tmp = Path(tempfile.mkdtemp(prefix="phjax-bench-live-"))
    rows = []
    try:
        specs = {"poses": lambda: _pose_file(tmp, args.seconds + 5),
                 "rgbd": lambda: _rgbd_folder(tmp, args.seconds + 5),
                 "synthetic": lambda: f"synthetic:{int(30 * (args.seconds + 3))}",
                 "udp": lambda: "udp"}
        for name in sources:
            spec = specs[name]()
            modes = args.modes if name in ("rgbd", "synthetic") else ["worker"]
            for realtime in args.realtime:
                for mode in modes:
                    row = run_row(name, spec, rate=args.rate, seconds=args.seconds,
                                  worker=mode == "worker", realtime=realtime == "yes",
                                  model_dir=model_dir,
                                  capture_nice=args.capture_nice)
                    print(format_row(row), file=sys.stderr, flush=True)
                    rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nlive path, {args.seconds:g} s per row at {args.rate:g} Hz, {os.cpu_count()} CPUs, "
          f"load average (1 min) before-after each row")
    print(HEADER)
    for r in rows:
        print(format_row(r))


if __name__ == "__main__":
    main()
