"""Review of the live path's network ends: a ``udp://`` backlog larger than one read of the
socket, and the outputs given a quaternion without an orientation (zero, or whose squared norm
leaves float64's range)."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest
from live_helpers import listener  # noqa: F401

from phjax._np_quat import np_axis_quat
from phjax.live import OpenTrackOutput, OscOutput, RealClock, opentrack_values
from phjax.live import _udp as udp
from phjax.live._udp import UdpSource, opentrack_pose

PACK = struct.Struct("<6d")


def _backlog_run(n: int) -> tuple[UdpSource, list]:
    """``n`` datagrams of new poses (x = 0 .. n-1 cm) queued before the read loop starts (the
    capture thread was held up), then the loop runs until all are read."""
    src = UdpSource("127.0.0.1", 0, report=lambda line: None)
    src.open()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    got, stop = [], threading.Event()
    th = threading.Thread(target=src.run, args=(RealClock(), 0.0, stop, got.append))
    try:
        for i in range(n):
            tx.sendto(PACK.pack(i, 0, 60, 0, 0, 0), ("127.0.0.1", src.port))
        th.start()
        deadline = time.monotonic() + 10.0
        while (src.received < n or not got) and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(0.02)
    finally:
        stop.set()
        if th.is_alive():
            th.join(5.0)
        tx.close()
        src.close()
    assert not th.is_alive()
    return src, got


def test_a_backlog_larger_than_one_read_gives_only_the_newest(monkeypatch):
    """A backlog of more datagrams than one wake-up reads (``_MAX_DRAIN``, 256: a socket
    buffer holds more, 600 of opentrack's with a 1 MiB buffer) gave one measurement per 256
    datagrams, each stamped on reading but up to a second old: the filter saw the head jump back
    and forth within milliseconds. Only the newest is a measurement, as documented."""
    monkeypatch.setattr(udp, "_MAX_DRAIN", 8)
    monkeypatch.setattr(udp, "_MAX_HOLD", 60.0)  # no liveness bound on a loaded machine
    src, got = _backlog_run(40)
    s = src.stats()
    assert s["received"] == 40 and s["dropped"] == 0
    assert [round(m.position[0] * 100, 9) for m in got] == [39.0], s  # was [7, 15, 23, 31, 39]
    assert s["emitted"] == 1 and s["superseded"] == 39
    parts = ("emitted", "repeated", "superseded", "at_stop", "dropped")
    assert sum(s[k] for k in parts) == s["received"]


def test_a_held_pose_is_taken_after_the_hold_bound(monkeypatch):
    """A sender faster than the reading never empties the socket: the held pose is taken after
    ``_MAX_HOLD`` (here 0: after every full read), so the stream never stalls."""
    monkeypatch.setattr(udp, "_MAX_DRAIN", 8)
    monkeypatch.setattr(udp, "_MAX_HOLD", 0.0)
    src, got = _backlog_run(40)
    xs = [round(m.position[0] * 100, 9) for m in got]
    assert xs == [7.0, 15.0, 23.0, 31.0, 39.0], src.stats()
    s = src.stats()
    assert sum(s[k] for k in ("emitted", "repeated", "superseded", "at_stop")) == 40


@pytest.mark.parametrize("scale", [0.0, 1e-200, 1e200])
def test_an_output_given_no_orientation_sends_nothing_wrong(listener, scale):  # noqa: F811
    """A zero quaternion (no orientation) raised ZeroDivisionError in ``OpenTrackOutput.send``
    (a crash of the render loop) and went out over OSC as ``qw qx qy qz = 0 0 0 0``; a tiny
    one (1e-200: its squared norm underflows) raised too; a huge one (1e200: the squared norm
    overflows) was sent as the identity (yaw = pitch = roll = 0) instead of its rotation, and
    over OSC not at all. Now a quaternion without an orientation is counted in
    ``out_of_range`` and not sent, and any other is sent as its unit quaternion."""
    q90 = np_axis_quat(0, np.pi / 2)  # a head looking down 90 degrees (pitch -90)
    p = np.array([0.01, 0.02, 0.6])
    ot = OpenTrackOutput("127.0.0.1", listener.port)
    osc = OscOutput("127.0.0.1", listener.port)
    try:
        for out in (ot, osc):
            out.send(0.5, p, scale * np.array([1.0, 1.0, 0.0, 0.0]))
            out.send(1.0, p, np.zeros(4))
            assert out.out_of_range == 1 + (scale == 0.0), type(out).__name__
    finally:
        ot.close()
        osc.close()
        listener.close()
    from pythonosc.osc_message import OscMessage

    data = [d for _, d in listener.packets]
    assert [len(d) for d in data] == ([] if scale == 0.0 else [48, 56])
    if scale:
        v = PACK.unpack(data[0])
        np.testing.assert_allclose(v[4], -90.0, atol=1e-6)  # was 0 for 1e200
        _, q = opentrack_pose(v)
        np.testing.assert_allclose(abs(np.dot(q, q90)), 1.0, atol=1e-12)
        np.testing.assert_allclose(OscMessage(data[1]).params,
                                   [0.5, *p, *q90], atol=1e-6)


def test_opentrack_values_of_no_orientation_are_nan():
    """``opentrack_values`` of a zero quaternion: NaN angles (not sendable), not an error."""
    v = opentrack_values([0.0, 0.0, 0.6], np.zeros(4))
    np.testing.assert_allclose(v[:3], [0.0, 0.0, 60.0])
    assert np.isnan(v[3:]).all()
