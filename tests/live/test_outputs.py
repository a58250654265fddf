"""Outputs: opentrack packet format and axes, OSC messages, the TUM log, URL parsing."""

from __future__ import annotations

import socket
import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from live_helpers import listener  # noqa: F401
from scipy.spatial.transform import Rotation

from phjax.io import read_tum
from phjax.live import (
    OpenTrackOutput,
    OscOutput,
    OutputError,
    TumLog,
    open_output,
    opentrack_values,
)

# camera axes in the user's (forward, up, right) frame: F = -z, U = -y, R = -x
_PERM = np.array([[0, 0, -1], [0, -1, 0], [-1, 0, 0]], float)


def _camera_quat(yaw, pitch, roll):
    """Camera-frame head quaternion (wxyz) with the documented opentrack angles, built with
    scipy: R_user = Ry(-yaw) Rz(pitch) Rx(-roll) in (F, U, R) coordinates."""
    r_user = Rotation.from_euler("YZX", [-yaw, pitch, -roll], degrees=True).as_matrix()
    m = _PERM.T @ r_user @ _PERM
    x, y, z, w = Rotation.from_matrix(m).as_quat()
    return np.array([w, x, y, z])


@given(st.floats(-170, 170), st.floats(-80, 80), st.floats(-170, 170))
def test_opentrack_angles_match_scipy(yaw, pitch, roll):
    q = _camera_quat(yaw, pitch, roll)
    v = opentrack_values([0.1, -0.2, 0.7], q)
    np.testing.assert_allclose(v[:3], [10.0, 20.0, 70.0], atol=1e-9)
    np.testing.assert_allclose(v[3:], [yaw, pitch, roll], atol=1e-6)
    v2 = opentrack_values([0.1, -0.2, 0.7], -q)  # sign of q is irrelevant
    np.testing.assert_allclose(v2, v, atol=1e-9)


def _rot(axis, deg):
    r = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float))
    x, y, z, w = r.as_quat()
    return np.array([w, x, y, z])


def test_opentrack_physical_directions():
    """The documented meanings, from camera-frame motions of a head facing the camera."""
    # turning to the user's right: the face (-z of the camera, towards it) swings towards the
    # user's right, which is the camera's -x: rotation about the camera's y (down) axis
    fwd = _rot([0, 1, 0], 20)
    face_dir = Rotation.from_quat(np.r_[fwd[1:], fwd[:1]]).apply([0, 0, -1])
    assert face_dir[0] < 0  # towards camera -x = the user's right
    assert opentrack_values(np.zeros(3), fwd)[3] == pytest.approx(20, abs=1e-9)
    # looking up: the face direction gets a -y (up) component
    up = _rot([-1, 0, 0], 15)
    assert Rotation.from_quat(np.r_[up[1:], up[:1]]).apply([0, 0, -1])[1] < 0
    assert opentrack_values(np.zeros(3), up)[4] == pytest.approx(15, abs=1e-9)
    # tilting to the user's left (right ear up): the head's up (-y) leans to the user's left
    # (+x of the camera)
    tilt = _rot([0, 0, 1], 10)
    head_up = Rotation.from_quat(np.r_[tilt[1:], tilt[:1]]).apply([0, -1, 0])
    assert head_up[0] > 0
    assert opentrack_values(np.zeros(3), tilt)[5] == pytest.approx(10, abs=1e-9)
    # translation: x = camera x (the user's left), y up, z away from the camera
    np.testing.assert_allclose(opentrack_values([0.01, 0.02, 0.5], [1, 0, 0, 0])[:3],
                               [1.0, -2.0, 50.0], atol=1e-12)


def test_opentrack_datagram(listener):  # noqa: F811
    out = open_output(f"opentrack://127.0.0.1:{listener.port}")
    assert isinstance(out, OpenTrackOutput)
    q = _camera_quat(12.0, -5.0, 3.0)
    for k in range(5):
        out.send(k / 120, np.array([0.01 * k, 0.0, 0.6]), q)
    out.close()
    listener.close()
    assert [len(d) for _, d in listener.packets] == [48] * 5
    vals = np.array([struct.unpack("<6d", d) for _, d in listener.packets])
    np.testing.assert_allclose(vals[:, 3:], [[12.0, -5.0, 3.0]] * 5, atol=1e-9)
    np.testing.assert_allclose(vals[:, 0], [0, 1, 2, 3, 4], atol=1e-12)
    assert out.sock.fileno() == -1


def test_osc_message(listener):  # noqa: F811
    from pythonosc.osc_message import OscMessage

    out = open_output(f"osc://127.0.0.1:{listener.port}")
    assert isinstance(out, OscOutput)
    out.send(1.5, np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.0, 0.0, 0.0]))
    out.close()
    listener.close()
    (_, data), = listener.packets
    msg = OscMessage(data)
    assert msg.address == "/phjax/pose"
    np.testing.assert_allclose(msg.params, [1.5, 0.1, 0.2, 0.3, 1, 0, 0, 0], atol=1e-6)


def test_values_beyond_the_format_are_counted_not_sent(listener):  # noqa: F811
    """A position beyond float32 (OSC) or beyond float64 in centimetres (opentrack) is not sent
    as inf and does not end the run (OSC raised OverflowError): counted in ``out_of_range``."""
    osc = open_output(f"osc://127.0.0.1:{listener.port}")
    ot = open_output(f"opentrack://127.0.0.1:{listener.port}")
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for out, big in ((osc, 1e39), (ot, 1e307)):
        out.send(0.0, np.array([big, 0.0, 0.0]), q)
        out.send(0.1, np.array([1.0, 0.0, 0.0]), q)
        assert out.out_of_range == 1 and out.sent == 1
        out.close()
    listener.close()
    assert len(listener.packets) == 2


def test_tum_log_round_trip(tmp_path):
    log = TumLog(tmp_path / "x.tum")
    rng = np.random.default_rng(0)
    q = rng.normal(size=(4, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    p = rng.normal(size=(4, 3))
    for k in range(4):
        log.send(k * 0.25, p[k], q[k])
    log.close()
    traj = read_tum(tmp_path / "x.tum")
    np.testing.assert_array_equal(traj.times, [0, 0.25, 0.5, 0.75])
    np.testing.assert_array_equal(traj.positions, p)
    np.testing.assert_allclose(np.abs(np.sum(traj.quaternions * q, -1)), 1.0, atol=1e-12)
    raw = np.loadtxt(tmp_path / "x.tum")  # exactly the values sent (qx qy qz qw)
    np.testing.assert_array_equal(raw[:, 4:], np.c_[q[:, 1:], q[:, :1]])


class _SlowFile:
    """A text file whose writes block until ``release`` is set (a disk held up), then fail
    with ENOSPC once ``full`` is set."""

    def __init__(self, f):
        import threading

        self.f, self.release, self.full, self.writes = f, threading.Event(), False, 0

    def write(self, text):
        assert self.release.wait(10)
        if self.full:
            raise OSError(28, "No space left on device")
        self.writes += 1
        return self.f.write(text)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_tum_log_never_holds_up_the_sender(tmp_path):
    """A write held up by the disk (here 0.3 s and more) does not hold up ``send``: the lines
    are written by the log's thread, all of them, in order; a later failure (a full disk) is
    raised by the next ``send`` and by ``close``, naming the log (was: written and flushed in
    the render thread, which waited for the disk)."""
    import time

    log = TumLog(tmp_path / "x.tum", flush_interval=0.02)
    slow = log._f = _SlowFile(log._f)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    worst = 0.0
    for k in range(40):
        t = time.perf_counter()
        log.send(k / 120, np.array([k * 1e-3, 0.0, 0.0]), q)
        worst = max(worst, time.perf_counter() - t)
        time.sleep(1 / 120)  # 0.33 s: the writer is blocked in its first write all along
    assert worst < 0.05 and slow.writes == 0
    slow.release.set()
    log.close()
    traj = read_tum(tmp_path / "x.tum")
    np.testing.assert_array_equal(traj.times, np.arange(40) / 120)
    np.testing.assert_array_equal(traj.positions[:, 0], np.arange(40) * 1e-3)

    log = TumLog(tmp_path / "y.tum", flush_interval=0.01)
    slow = log._f = _SlowFile(log._f)
    slow.full = True
    slow.release.set()
    log.send(0.0, np.zeros(3), q)
    time.sleep(0.2)  # the writer's write failed
    with pytest.raises(OutputError, match=r"cannot write the log .*y\.tum: No space left"):
        log.send(0.01, np.zeros(3), q)
    with pytest.raises(OutputError, match="No space left"):
        log.close()


@pytest.mark.parametrize("url, msg", [
    ("http://127.0.0.1:4242", "unknown output"),
    ("opentrack://", "missing host"),
    ("opentrack://127.0.0.1:abc", "bad port"),
    ("opentrack://127.0.0.1:0", "out of range"),
    ("opentrack://[::1", r"opentrack://\[::1: Invalid IPv6 URL"),
    ("opentrack://255.255.255.255", "opentrack://255.255.255.255:4242: cannot send there"),
    ("osc://127.0.0.1:70000", "bad port"),
    ("osc://host.invalid", "cannot resolve"),
    ("opentrack://127.0.0.1:4242/path", "unexpected path"),
    ("opentrack://127.0.0.1:4242?to=1", "unknown option"),
    ("opentrack://user:pw@127.0.0.1", "unexpected user or password"),  # were ignored
    ("osc://127.0.0.1:9000#x", "unexpected fragment #x"),
])
def test_bad_urls(url, msg):
    with pytest.raises(OutputError, match=msg):
        open_output(url)


def test_default_ports_and_port_in_use():
    out = open_output("opentrack://localhost")
    assert out.port == 4242
    out.close()
    out = open_output("osc://127.0.0.1")
    assert out.port == 9000
    out.close()
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("", 0))
    try:
        with pytest.raises(OutputError, match="cannot use local port"):
            open_output(f"opentrack://127.0.0.1:4242?from={busy.getsockname()[1]}")
    finally:
        busy.close()


def test_send_without_listener_is_not_an_error():
    """Nobody listening (ICMP port unreachable): the sample is lost, the sender goes on."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    out = OpenTrackOutput("127.0.0.1", port)
    for _ in range(5):
        out.send(0.0, np.zeros(3), np.array([1.0, 0, 0, 0]))
    assert out.sent + out.send_errors == 5
    out.close()
