"""Helpers of the live tests (imported by them): a loopback UDP listener, a seeded YuNet model
cache, motion to replay (and as a pose file), process and polling helpers."""

from __future__ import annotations

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
