"""Input from other trackers: opentrack's UDP datagrams (``udp://[HOST]:PORT``).

opentrack's "UDP over network" output (and AITrack, several phone apps, phjax's own
``opentrack://`` output) sends one datagram per pose: 48 bytes, six little-endian float64
``x, y, z`` (cm) and ``yaw, pitch, roll`` (degrees). :class:`UdpSource` receives them, turns
them into camera-frame poses with :func:`opentrack_pose` (the exact inverse of
:func:`phjax.live.opentrack_values`, so phjax's output read back by phjax is the same pose) and
time-stamps each one when it is read, on the runner's clock (the datagrams carry no time).

Axes (opentrack's, for a user facing the camera; see :mod:`phjax.live._outputs`): ``x`` + to
the user's left, ``y`` + up, ``z`` + away from the camera; ``yaw`` + turn right, ``pitch`` +
look up, ``roll`` + tilt left; intrinsic yaw, then pitch, then roll. In phjax's camera frame
(``x`` right in the image, ``y`` down, ``z`` forward) that is the position
``(x, -y, z) / 100`` m and the rotation ``R_y(yaw) R_x(-pitch) R_z(roll)``.

A datagram that is the wrong size, holds a NaN or an infinity, or a value beyond
:data:`MAX_POSITION_CM` / :data:`MAX_ANGLE_DEG` is dropped and counted by reason, with one
line saying what was wrong (at most one line per ``report_interval``); it never reaches the
tracker. When several datagrams wait in the socket (the capture thread was busy), only the
newest is used and the others are counted as ``superseded``: never a backlog, also when more
wait than one wake-up reads (:data:`_MAX_DRAIN`): the pose read is held while the reading goes
on, for at most :data:`_MAX_HOLD` (a sender faster than the reading still gives a measurement
that often).

Repeated poses. opentrack's pipeline sends a datagram every 4 ms (250 Hz) whatever its
tracker's frame rate, repeating the last pose until the tracker delivers the next one (with
its filter off). A repeat is not a new measurement: fed to the tracker at its arrival time it
would say that the head stood still and then jumped. So a datagram with exactly the values of
the previous one is skipped (counted as ``repeated``), and a new measurement is the first
datagram with new values, time-stamped on its arrival (at most 4 ms after opentrack got it).
Only when the same values come :data:`STILL_FRAMES` times as many times in a row as the
sender sends per frame (the median number of datagrams between changes) is the repeat taken as
a measurement, and again after as many more: the head is still and the tracker keeps seeing the
same pose (a dead zone, a noise-free tracker), and the filter is told so at about half the
sender's frame rate. The rule counts datagrams, not time, so a sender that stalls (no datagrams
for a while, then its last pose again) is not taken for a still head.
"""

from __future__ import annotations

import select
import socket
import struct
import sys
import time
import urllib.parse
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from .._np_quat import np_axis_quat, np_qmul, np_qnormalize
from ._sources import MAX_POSITION_M, Measurement, Source, SourceError
from ._url import url_extras, url_options, url_port

__all__ = [
    "DATAGRAM_SIZE",
    "MAX_ANGLE_DEG",
    "MAX_POSITION_CM",
    "STILL_FRAMES",
    "UdpSource",
    "opentrack_pose",
]

_PACK = struct.Struct("<6d")
#: bytes of one opentrack datagram (six float64)
DATAGRAM_SIZE = _PACK.size
#: a position coordinate beyond this (cm, 10 m: the bound of ``poses:FILE`` rows too,
#: :data:`phjax.live._sources.MAX_POSITION_M`) is not a head pose: the datagram is dropped
MAX_POSITION_CM = 100.0 * MAX_POSITION_M
#: an angle beyond this (degrees) is not a head pose: the datagram is dropped
MAX_ANGLE_DEG = 360.0
#: the fields of a datagram, in order
FIELDS = ("x", "y", "z", "yaw", "pitch", "roll")
#: drop reasons (keys of ``UdpSource.dropped``)
REASONS = ("wrong size", "non-finite", "out of range")
#: a pose repeated for this many of the sender's frames is a still head (module docs)
STILL_FRAMES = 2.0
#: datagrams per frame before they are measured (opentrack: 250 Hz for a 30 Hz tracker)
DEFAULT_DATAGRAMS_PER_FRAME = 8
#: datagrams further apart than this (s; opentrack repeats every 4 ms) are one per frame
REPEAT_INTERVAL = 0.012
#: changes of the values whose intervals and datagram counts give the sender's frame (medians)
_FRAME_WINDOW = 15
#: senders remembered (a new one is reported; a sender using a new port per datagram would
#: otherwise grow the set without bound)
_MAX_SENDERS = 64
#: most datagrams read per wake-up of the read loop (the newest valid one is used; when
#: more wait, it is held and the reading goes on, see :data:`_MAX_HOLD`)
_MAX_DRAIN = 256
#: longest time (s) a pose is held back while a backlog larger than :data:`_MAX_DRAIN` is read
#: (the newest pose is then taken): bounds the gap between measurements when a sender sends
#: faster than they can be read
_MAX_HOLD = 0.1
#: receive buffer: larger datagrams are truncated to this and reported as the wrong size
_RECV_BYTES = 65536


def opentrack_pose(values) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame pose of opentrack values (the inverse of :func:`phjax.live.opentrack_values`).

    Arguments:
        values: ``(6,)`` ``x, y, z`` (cm), ``yaw, pitch, roll`` (degrees), opentrack's axes.

    Returns:
        ``(position, quaternion)``: ``(3,)`` m and ``(4,)`` ``wxyz`` (unit, ``w >= 0``).
    """
    v = np.asarray(values, np.float64)
    position = np.array([v[0], -v[1], v[2]]) / 100.0
    yaw, pitch, roll = np.radians(v[3:6])
    # user axes (forward, up, right) = (-z, -y, -x) of the camera: R_U(-yaw) R_R(pitch)
    # R_F(-roll) in user coordinates is R_y(yaw) R_x(-pitch) R_z(roll) in camera coordinates
    q = np_qmul(np_qmul(np_axis_quat(1, yaw), np_axis_quat(0, -pitch)), np_axis_quat(2, roll))
    q = np_qnormalize(q)
    return position, (-q if q[0] < 0 else q)


def _stderr_report(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _is_local(ip: str, family: int) -> bool:
    """Whether ``ip`` is an address of this machine (a socket can bind to it)."""
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.bind((ip, 0))
        return True
    except OSError:
        return False


class UdpSource(Source):
    """opentrack UDP datagrams received on a local port (module docs).

    Arguments:
        host: local address to listen on (default ``0.0.0.0``: every interface, as opentrack's
            own "UDP over network" input; ``127.0.0.1``: this machine only).
        port: local UDP port (0: any free port, read :attr:`port` after :meth:`open`).
        depth_free: the sending tracker is a monocular (webcam) one: the live tracker then
            uses the larger monocular measurement noise (``?noise=monocular`` in the spec).
        poll: seconds between checks of the stop event while no datagram arrives.
        report: called with one line per report (default: print to stderr).
        report_interval: at least this many seconds between two reports, s.

    Attributes:
        received: datagrams read; ``dropped``: a :class:`collections.Counter` of the dropped
            ones by reason (:data:`REASONS`); ``repeated``: valid ones skipped as a repeat of
            the previous pose (module docs); ``superseded``: poses replaced by a newer one read
            at the same wake-up; ``emitted``: measurements given to the tracker; ``at_stop``:
            poses read as the run stopped (not given to it). Every received datagram is in
            exactly one of ``emitted``, ``repeated``, ``superseded``, ``at_stop``, ``dropped``.
    """

    def __init__(self, host: str = "0.0.0.0", port: int = 0, *, depth_free: bool = False,
                 poll: float = 0.05, report: Callable[[str], None] | None = None,
                 report_interval: float = 1.0):
        if not 0 <= int(port) <= 65535:
            raise SourceError(f"udp: port {port} out of range 0-65535")
        self.host, self.port = host, int(port)
        self.depth_free = bool(depth_free)
        self.poll = float(poll)
        self.report = report if report is not None else _stderr_report
        self.report_interval = float(report_interval)
        self.sock: socket.socket | None = None
        self.received = 0
        self.emitted = 0
        self.superseded = 0
        self.repeated = 0
        self.at_stop = 0
        self.dropped: Counter = Counter()
        self.last_sender: str | None = None
        #: the senders seen (host:port; the latest :data:`_MAX_SENDERS`, oldest first)
        self.senders: dict[str, None] = {}
        self._last_sender_report: float | None = None
        self._unreported_senders = 0
        self._last_values: np.ndarray | None = None  # of the last valid datagram
        self._last_change: float | None = None  # arrival of the last new values
        self._since_change = 0  # valid datagrams since the last new values
        self._since_taken = 0  # valid datagrams since the last measurement taken
        self._change_intervals: deque = deque(maxlen=_FRAME_WINDOW)
        self._change_counts: deque = deque(maxlen=_FRAME_WINDOW)
        self._arrival_intervals: deque = deque(maxlen=_FRAME_WINDOW)  # of valid datagrams
        self._last_arrival: float | None = None
        self._last_report: float | None = None
        self._unreported = 0

    @property
    def name(self) -> str:  # the port is known after open() when 0 was asked for
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opentrack UDP udp://{host}:{self.port}"

    @classmethod
    def from_spec(cls, spec: str, **kwargs) -> UdpSource:
        """A source from ``udp://[HOST]:PORT[?noise=rgbd|monocular]`` (HOST default
        ``0.0.0.0``; an IPv6 address in brackets).

        Arguments:
            spec: the ``SOURCE`` argument.
            kwargs: passed to the constructor.

        Raises:
            SourceError: a missing or bad port, an unknown option.
        """
        usage = "use udp://[HOST]:PORT, e.g. udp://127.0.0.1:5005"
        try:
            parsed = urllib.parse.urlsplit(spec)
        except ValueError as e:  # "Invalid IPv6 URL", without the URL
            raise SourceError(f"{spec}: {e}; {usage}") from None
        port = url_port(parsed, spec, SourceError)
        if port is None:
            raise SourceError(f"{spec}: missing port; {usage}")
        if parsed.path not in ("", "/"):
            raise SourceError(f"{spec}: unexpected path {parsed.path!r}; {usage}")
        url_extras(parsed, spec, SourceError)
        query = url_options(parsed, spec, ("noise",), SourceError)
        noise = query.get("noise", ["rgbd"])[-1]
        if noise not in ("rgbd", "monocular"):
            raise SourceError(f"{spec}: noise must be rgbd or monocular, got {noise!r}")
        return cls(parsed.hostname or "0.0.0.0", port, depth_free=noise == "monocular",
                   **kwargs)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Bind the socket (a port in use or an unknown address is a :class:`SourceError`)."""
        if self.sock is not None:
            return
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM,
                                       flags=socket.AI_PASSIVE)
        except (socket.gaierror, UnicodeError) as e:
            raise SourceError(f"{self.name}: cannot resolve {self.host!r} ({e})") from None
        family, type_, proto, _, addr = infos[0]
        sock = socket.socket(family, type_, proto)
        try:
            sock.bind(addr)
            sock.setblocking(False)
        except OSError as e:
            sock.close()
            raise SourceError(f"{self.name}: cannot listen ({e.strerror or e})") from None
        self.sock = sock
        self.port = sock.getsockname()[1]

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def check_outputs(self, outputs) -> None:
        """A :class:`SourceError` when one of ``outputs`` (opened, UDP) sends to this source's
        own socket: the stream would read its own poses back as measurements and drift away
        (``udp://:4242`` with ``-o opentrack://127.0.0.1:4242``, opentrack's port for both).
        Nothing to check before :meth:`open`."""
        if self.sock is None:
            return
        host, port = self.sock.getsockname()[:2]
        for out in outputs:
            sock = getattr(out, "sock", None)
            try:
                peer = sock.getpeername()[:2] if sock is not None else None
            except OSError:
                continue
            if peer is None or peer[1] != port:
                continue
            if host in ("0.0.0.0", "::") or host == peer[0]:
                if _is_local(peer[0], sock.family):
                    raise SourceError(
                        f"{getattr(out, 'url', out)} sends to port {port}, where this run's "
                        f"source listens ({self.name}): the stream would read its own poses "
                        "back and drift away; send to another port")

    # ------------------------------------------------------------------ reading
    def run(self, clock, t0, stop, emit) -> None:
        if getattr(clock, "virtual", False):
            raise SourceError(f"{self.name}: a UDP source needs the real clock (datagrams "
                              "arrive in real time)")
        if self.sock is None:
            self.open()
        sock = self.sock
        # a pose read while more datagrams waited (a backlog larger than _MAX_DRAIN): held, and
        # replaced by a newer one, until the socket is empty or it was held _MAX_HOLD
        held, held_since = None, None
        try:
            while not stop.is_set():
                try:
                    wait = 0.0 if held is not None else self.poll  # held: read on at once
                    ready, _, _ = select.select([sock], [], [], wait)
                except (OSError, ValueError):  # closed under us (stop timed out): end quietly
                    if stop.is_set() or self.sock is None:
                        return
                    raise
                more = False
                if ready:
                    held, more = self._drain(sock, clock, stop, held)
                if held is None or stop.is_set():
                    continue
                if more:
                    held_since = clock.now() if held_since is None else held_since
                    if clock.now() - held_since < _MAX_HOLD:
                        continue
                t, position, quaternion = held
                held, held_since = None, None
                self.emitted += 1
                emit(Measurement(t, position, quaternion))
        finally:
            if held is not None:
                self.at_stop += 1  # the run has ended: counted, not applied

    def _drain(self, sock, clock, stop, newest=None):
        """Read the waiting datagrams (at most ``_MAX_DRAIN``): ``(newest, more)``, the newest
        valid pose as ``(t, position, quaternion)`` (``newest`` when none is newer, None if
        neither) and whether more datagrams may wait (the limit was reached)."""
        for _ in range(_MAX_DRAIN):
            try:
                data, addr = sock.recvfrom(_RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                return newest, False
            except ConnectionResetError:  # Windows: an ICMP error of an earlier send
                continue
            except OSError:
                if stop.is_set() or self.sock is None:
                    return newest, False
                raise
            t = clock.now()
            self.received += 1
            sender = f"{addr[0]}:{addr[1]}"
            values = self._check(data, sender)
            if values is None:
                continue
            if self.last_sender is not None and sender != self.last_sender \
                    and sender not in self.senders:
                self._new_sender(sender)
            self.senders.pop(sender, None)
            self.senders[sender] = None
            if len(self.senders) > _MAX_SENDERS:
                del self.senders[next(iter(self.senders))]
            self.last_sender = sender
            if not self._is_measurement(t, values):
                self.repeated += 1
                continue
            if newest is not None:
                self.superseded += 1
            newest = (t, *opentrack_pose(values))
        return newest, True

    @property
    def frame_interval(self) -> float:
        """The sender's frame interval: the median time between changes of the values, s
        (NaN before two changes)."""
        if not self._change_intervals:
            return float("nan")
        return float(np.median(self._change_intervals))

    @property
    def datagrams_per_frame(self) -> float:
        """The median number of datagrams between changes of the values; before two changes,
        :data:`DEFAULT_DATAGRAMS_PER_FRAME` (opentrack's repeats), or 1 when the datagrams
        come further apart than :data:`REPEAT_INTERVAL` (a sender that sends once per frame:
        taken for opentrack, a still head at the start was measured at 2 Hz, and the motion
        that followed lagged by about 100 ms)."""
        if self._change_counts:
            return float(np.median(self._change_counts))
        if len(self._arrival_intervals) >= 3 \
                and np.median(self._arrival_intervals) > REPEAT_INTERVAL:
            return 1.0
        return float(DEFAULT_DATAGRAMS_PER_FRAME)

    def _is_measurement(self, t: float, values: np.ndarray) -> bool:
        """Whether a valid datagram read at ``t`` is a new measurement (module docs)."""
        last = self._last_values
        self._last_values = values
        if self._last_arrival is not None:
            self._arrival_intervals.append(t - self._last_arrival)
        self._last_arrival = t
        self._since_change += 1
        self._since_taken += 1
        if last is None or not np.array_equal(values, last):
            if self._last_change is not None:
                self._change_intervals.append(t - self._last_change)
                self._change_counts.append(self._since_change)
            self._last_change = t
            self._since_change = self._since_taken = 0
            return True
        if self._since_taken >= STILL_FRAMES * self.datagrams_per_frame:
            self._since_taken = 0
            return True
        return False

    def _check(self, data: bytes, sender: str) -> np.ndarray | None:
        """The six values of a valid datagram, or None (dropped, counted, reported)."""
        n = len(data)
        if n != DATAGRAM_SIZE:
            hint = " (six float32? opentrack sends float64)" if n == 24 else ""
            return self._drop("wrong size", sender, f"{n} bytes, expected {DATAGRAM_SIZE} (six "
                              f"little-endian float64: x y z cm, yaw pitch roll deg){hint}")
        values = np.array(_PACK.unpack(data))
        bad = ~np.isfinite(values)
        if bad.any():
            what = ", ".join(f"{FIELDS[i]} = {values[i]}" for i in np.flatnonzero(bad))
            return self._drop("non-finite", sender, f"non-finite value ({what})")
        limits = np.array([MAX_POSITION_CM] * 3 + [MAX_ANGLE_DEG] * 3)
        over = np.abs(values) > limits
        if over.any():
            what = ", ".join(f"{FIELDS[i]} = {values[i]:.6g} {'cm' if i < 3 else 'deg'}"
                             for i in np.flatnonzero(over))
            return self._drop("out of range", sender, f"value out of range ({what}; limits "
                              f"+-{MAX_POSITION_CM:g} cm, +-{MAX_ANGLE_DEG:g} deg)")
        return values

    def _new_sender(self, sender: str) -> None:
        """Say that poses come from a new sender (a restarted tracker, or two sending to one
        port, whose poses then interleave), at most once per ``report_interval``."""
        now = time.monotonic()
        if self._last_sender_report is not None \
                and now - self._last_sender_report < self.report_interval:
            self._unreported_senders += 1
            return
        more = (f"; {self._unreported_senders} other new senders since the last report (a "
                "sender that sends each datagram from a new port?)"
                if self._unreported_senders else "")
        self._last_sender_report, self._unreported_senders = now, 0
        self.report(f"phjax live: {self.name}: poses now from {sender} (before: "
                    f"{self.last_sender}){more}; if two trackers send to this port, their "
                    "poses are mixed into one stream: give each its own port")

    def _drop(self, reason: str, sender: str, what: str) -> None:
        self.dropped[reason] += 1
        now = time.monotonic()
        if self._last_report is not None and now - self._last_report < self.report_interval:
            self._unreported += 1
            return
        more = f"; {self._unreported} more since the last report" if self._unreported else ""
        self._last_report, self._unreported = now, 0
        self.report(f"phjax live: {self.name}: dropped a datagram from {sender}: {what} "
                    f"[dropped so far: {self.dropped_text()}{more}]")

    # ------------------------------------------------------------------ statistics
    def dropped_text(self) -> str:
        """The drop counts, e.g. ``"3 (2 wrong size, 1 non-finite)"`` (``"0"`` if none)."""
        total = sum(self.dropped.values())
        if not total:
            return "0"
        parts = ", ".join(f"{self.dropped[r]} {r}" for r in REASONS if self.dropped[r])
        return f"{total} ({parts})"

    def stats(self) -> dict:
        """Counts so far: ``received``, ``emitted``, ``repeated``, ``superseded``, ``at_stop``,
        ``dropped``
        (total) and ``dropped_by_reason`` (a dict over :data:`REASONS`), ``last_sender`` and
        ``frame_interval`` (s, the sender's, :attr:`frame_interval`) and
        ``datagrams_per_frame`` (:attr:`datagrams_per_frame`)."""
        return {
            "received": self.received,
            "emitted": self.emitted,
            "repeated": self.repeated,
            "superseded": self.superseded,
            "at_stop": self.at_stop,
            "dropped": sum(self.dropped.values()),
            "dropped_by_reason": {r: self.dropped[r] for r in REASONS},
            "last_sender": self.last_sender,
            "frame_interval": self.frame_interval,
            "datagrams_per_frame": self.datagrams_per_frame,
        }
