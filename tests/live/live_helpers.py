"""Helpers of the live tests (imported by them): a loopback UDP listener, a seeded YuNet model
cache, motion to replay (and as a pose file), process and polling helpers."""

from __future__ import annotations

import os
import socket
import threading
import time

import pytest
from conftest import shared_path


class UdpListener:
    """Receives datagrams on 127.0.0.1 in a thread: ``(arrival time, bytes)`` pairs."""

    def __init__(self, keep: bool = True):
        self.keep = keep
        self.count = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.packets: list[tuple[float, bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            self.count += 1
            if self.keep:
                self.packets.append((time.perf_counter(), data))

    def close(self):
        time.sleep(0.1)  # let the last datagrams arrive
        self._stop.set()
        self._thread.join()
        self.sock.close()


@pytest.fixture
def listener():
    ls = UdpListener()
    yield ls
    if not ls._stop.is_set():
        ls.close()


@pytest.fixture(scope="session")
def model_cache(tmp_path_factory):
    """A YuNet model cache seeded from ../shared/data (skips without it)."""
    from phjax.vision import face_detection as F

    src = shared_path("yunet_face_detection")
    cache = tmp_path_factory.mktemp("models")
    F.seed_model_cache(src, cache)
    return cache


def angle_steps(a):
    """Absolute differences of consecutive angles (degrees), wrap-around aware."""
    import numpy as np

    d = np.diff(np.asarray(a, np.float64), axis=0)
    return np.abs((d + 180.0) % 360.0 - 180.0)


def smooth_motion(n: int, rate: float, seed: int = 0):
    """``n`` poses at ``rate`` Hz of a smooth head-like motion (sums of sines), camera frame:
    ``(times, positions, quaternions)``; a cheap stand-in for long replays."""
    import numpy as np

    from phjax._np_quat import np_from_rotvec

    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    f = rng.uniform(0.05, 0.6, (2, 3))
    ph = rng.uniform(0, 2 * np.pi, (2, 3))
    p = np.array([0.0, 0.0, 0.7]) + 0.03 * np.sin(2 * np.pi * f[0] * t[:, None] + ph[0])
    rv = np.radians(15.0) * np.sin(2 * np.pi * f[1] * t[:, None] + ph[1])
    return t, p, np_from_rotvec(rv)


def write_pose_file(path, n: int, rate: float = 30.0, seed: int = 0):
    """``smooth_motion(n, rate, seed)`` written as a TUM file at ``path``; returns the motion."""
    from phjax.io import Trajectory, write_tum

    t, p, q = smooth_motion(n, rate, seed)
    write_tum(path, Trajectory(t, p, q))
    return t, p, q


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux ``/proc``; elsewhere a signal
    0 probe)."""
    import os

    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
    except OSError:
        pass
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def wait_until(predicate, timeout: float, poll: float = 0.05) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` seconds have passed (bounded)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll)
    return bool(predicate())


#: the stall probe's process: pinned to one CPU, real-time priority where allowed, it wakes
#: every millisecond and records each wake-up that came more than THRESHOLD late; it ends when
#: its stdin closes (or after its time limit), printing what it saw as JSON
_PROBE = r"""
import json, os, select, sys, time
cpu, threshold, limit = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
try:
    os.sched_setaffinity(0, {cpu})
except OSError:
    pass
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(2))
    fifo = True
except (OSError, AttributeError):
    fifo = False
gaps = []
print("ready", flush=True)
last = start = time.perf_counter()
while not select.select([sys.stdin], [], [], 0.001)[0] and last - start < limit:
    now = time.perf_counter()
    if now - last > threshold:
        gaps.append((last, now))
    last = now
print(json.dumps({"cpu": cpu, "fifo": fifo, "gaps": gaps}), flush=True)
"""


def _steal_seconds() -> float:
    """CPU time stolen from this (virtual) machine by its host so far (``/proc/stat``; 0
    elsewhere)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


class StallProbe:
    """An independent witness of host stalls for the real-time tests: one small process per
    CPU this process may use, pinned to it and at real-time priority where allowed
    (``SCHED_FIFO``; root on Linux), wakes every millisecond. A wake-up more than
    ``threshold`` seconds late is a moment that CPU ran nothing of ours: the host descheduled
    the virtual machine's vCPU, a cgroup quota throttled it, or a long stretch of kernel work
    could not be preempted (measured on an idle 2-core VM: gaps of 4-17 ms only while the
    run starts, none during it). The tracker's own user-space work (the GIL, its threads at
    their priorities) cannot delay a real-time process, so a long render interval the probe
    did not see is the tracker's.

    Use as a context manager around the run; then :meth:`covered` tells which intervals
    (``time.perf_counter`` times) a probe gap of at least ``min_gap`` overlaps, and
    :meth:`summary` is one line for the test's output.
    """

    def __init__(self, threshold: float = 0.004, limit: float = 600.0):
        import subprocess
        import sys

        self.threshold = threshold
        self.cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
        self._steal0 = _steal_seconds()
        self._procs = [subprocess.Popen([sys.executable, "-c", _PROBE, str(c), str(threshold),
                                         str(limit)], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True) for c in self.cpus]
        for p in self._procs:
            assert p.stdout.readline().strip() == "ready"
        self.fifo = False
        self.gaps: list[tuple[float, float]] = []
        self.steal = 0.0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def stop(self) -> None:
        import json

        fifo = []
        for p in self._procs:
            if p.poll() is not None and p.stdout.closed:
                continue
            try:
                out, _ = p.communicate("", timeout=10)
            except Exception:  # noqa: BLE001 - a probe that cannot report saw nothing
                p.kill()
                p.wait()
                continue
            lines = out.strip().splitlines()
            if lines:
                seen = json.loads(lines[-1])
                fifo.append(seen["fifo"])
                self.gaps += [tuple(g) for g in seen["gaps"]]
        self.fifo = bool(fifo) and all(fifo)
        self.gaps.sort()
        self.steal = _steal_seconds() - self._steal0

    def covered(self, starts, ends, min_gap: float):
        """For each interval ``[starts[i], ends[i]]``: whether a probe gap of at least
        ``min_gap`` seconds overlaps it (an array of bools)."""
        import numpy as np

        g = np.array([gap for gap in self.gaps if gap[1] - gap[0] >= min_gap]).reshape(-1, 2)
        s, e = np.asarray(starts)[:, None], np.asarray(ends)[:, None]
        return np.any((g[None, :, 0] < e) & (g[None, :, 1] > s), axis=1)

    def summary(self) -> str:
        lengths = [1e3 * (b - a) for a, b in self.gaps]
        return (f"host stall probe ({'SCHED_FIFO' if self.fifo else 'normal priority'}, CPUs "
                f"{self.cpus}): {len(lengths)} gaps over {1e3 * self.threshold:.0f} ms"
                + (f", longest {max(lengths):.1f} ms, {sum(lengths):.0f} ms in all"
                   if lengths else "") + f"; steal {1e3 * self.steal:.0f} ms")
