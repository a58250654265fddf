"""Where live poses go: opentrack ("UDP over network"), OSC, and a TUM log of what was sent.

Every output receives the pose the render loop sends: time ``t`` (s since the start of the
run), position (m) and orientation (``wxyz``) of the head in the **camera frame** (``x`` right
in the image, ``y`` down, ``z`` forward out of the camera), after centring. In that frame a head
with the identity orientation squarely faces the camera (the RGB-D front-end's first frame and
the monocular face model are both defined that way).

opentrack
---------
One datagram per sample: 48 bytes, six little-endian float64 ``x, y, z`` (cm) and ``yaw,
pitch, roll`` (degrees), the layout opentrack's "UDP over network" input reads (it drops a
datagram with a NaN, so none is ever sent). Axes follow opentrack's own camera trackers
(``tracker-pt``, ``tracker-neuralnet``), for a user facing the camera:

* ``x`` + : the head moves to the user's **left** (the camera's right), ``x = x_cam``;
* ``y`` + : up, ``y = -y_cam``;
* ``z`` + : away from the camera (the user leans back), ``z = z_cam``;
* ``yaw`` + : the head turns to the user's **right**;
* ``pitch`` + : the head looks **up**;
* ``roll`` + : the head tilts to the user's **left** (right ear up).

The angles are intrinsic yaw (about the up axis), then pitch (about the head's right axis),
then roll (about its forward axis): with the user's forward, up and right axes ``F, U, R``
(``F = -z_cam``, ``U = -y_cam``, ``R = -x_cam``) the head rotation is
``R_U(-yaw) R_R(pitch) R_F(-roll)``. opentrack's mapping window can invert any axis.

OSC
---
One message per sample, address ``/phjax/pose``, eight float32 arguments
``t, x, y, z, qw, qx, qy, qz`` (s, m, camera frame as above; the quaternion scaled to unit
norm), sent with python-osc.

Either output counts a pose it cannot send in ``out_of_range`` and sends nothing for it: a
value beyond the format, a NaN, or a quaternion without an orientation (zero).

Log
---
``--log FILE``: a TUM file (``t x y z qx qy qz qw``) with one line per sample of exactly the
pose given to the outputs (every other output's values are functions of it).
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import urllib.parse
from pathlib import Path

import numpy as np

from .._np_quat import np_qnormalize
from ._url import url_extras, url_options, url_port

__all__ = [
    "OPENTRACK_PORT",
    "OSC_ADDRESS",
    "OSC_PORT",
    "OpenTrackOutput",
    "OscOutput",
    "Output",
    "OutputError",
    "TumLog",
    "open_output",
    "opentrack_values",
]

#: opentrack's default "UDP over network" port
OPENTRACK_PORT = 4242
#: default port of ``osc://HOST`` (a common OSC default)
OSC_PORT = 9000
#: the OSC address of every pose message
OSC_ADDRESS = "/phjax/pose"

_PACK = struct.Struct("<6d")


class OutputError(ValueError):
    """A bad output URL, an unresolvable host, a port that cannot be used."""


def _unit(quaternion) -> np.ndarray:
    """``quaternion`` (``(4,)``) as a float64 unit quaternion; NaN when it has no orientation
    (zero or not finite; :func:`phjax._np_quat.np_qnormalize`)."""
    return np_qnormalize(np.asarray(quaternion, np.float64))


def opentrack_values(position, quaternion) -> np.ndarray:
    """``(x, y, z, yaw, pitch, roll)`` in opentrack's units and axes (see the module docs).

    Arguments:
        position: ``(3,)`` camera-frame position, m.
        quaternion: ``(4,)`` camera-frame orientation ``wxyz`` (identity: facing the camera).

    Returns:
        ``(6,)`` float64: cm and degrees; the angles are NaN when ``quaternion`` has no
        orientation (zero, or not finite).
    """
    p = np.asarray(position, np.float64)
    w, x, y, z = _unit(quaternion)
    # rotation matrix (camera frame)
    m = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    # user frame (F, U, R) = (-z, -y, -x) of the camera; same map for the head's axes
    perm = np.array([[0, 0, -1], [0, -1, 0], [-1, 0, 0]], np.float64)
    r = perm @ m @ perm.T  # columns: head forward, up, right in (F, U, R) coordinates
    # r = Ry(-yaw) Rz(pitch) Rx(-roll) with (x, y, z) = (F, U, R)
    f = r[:, 0]
    yaw = math.atan2(f[2], f[0])
    pitch = math.atan2(f[1], math.hypot(f[0], f[2]))
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    ry_t = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])  # Ry(-yaw)^T = Ry(yaw)
    rz_t = np.array([[cp, sp, 0], [-sp, cp, 0], [0, 0, 1]])  # Rz(pitch)^T
    a = rz_t @ ry_t @ r  # = Rx(-roll)
    roll = -math.atan2(a[2, 1], a[1, 1])
    out = np.empty(6)
    out[0], out[1], out[2] = 100 * p[0], -100 * p[1], 100 * p[2]
    out[3], out[4], out[5] = math.degrees(yaw), math.degrees(pitch), math.degrees(roll)
    return out


class Output:
    """Base class: ``send(t, position, quaternion)`` per sample, ``close()`` at the end."""

    url = ""

    def send(self, t: float, position: np.ndarray, quaternion: np.ndarray) -> None:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"


def _url_host(host: str) -> str:
    """``host`` as written in a URL (an IPv6 address in brackets, as the parser reads it)."""
    return f"[{host}]" if ":" in host else host


def _resolve(host: str, port: int, what: str):
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as e:
        raise OutputError(f"{what}: cannot resolve host {host!r} ({e})") from None
    return infos[0]


def _udp_socket(host: str, port: int, what: str, from_port: int | None) -> socket.socket:
    family, type_, proto, _, addr = _resolve(host, port, what)
    sock = socket.socket(family, type_, proto)
    try:
        if from_port is not None:
            try:
                sock.bind(("", from_port) if family == socket.AF_INET else ("::", from_port))
            except OSError as e:
                raise OutputError(f"{what}: cannot use local port {from_port} ({e.strerror})"
                                  ) from None
        try:
            sock.connect(addr)
        except OSError as e:  # e.g. a broadcast address (needs SO_BROADCAST): name the output
            raise OutputError(f"{what}: cannot send there ({e.strerror or e})") from None
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    return sock


class _UdpOutput(Output):
    def __init__(self, host: str, port: int, from_port: int | None, url: str):
        self.url = url
        self.host, self.port = host, port
        self.sock = _udp_socket(host, port, url, from_port)
        self.sent = 0
        self.send_errors = 0
        #: poses not sent because a value does not fit the format (float32 OSC beyond 3.4e38,
        #: opentrack's centimetres beyond float64) or is not a pose (NaN, a zero quaternion):
        #: never sent as inf or NaN
        self.out_of_range = 0

    def _fits(self, values, dtype) -> bool:
        """Whether ``values`` are finite in ``dtype`` (else counted in :attr:`out_of_range`)."""
        with np.errstate(over="ignore"):
            ok = bool(np.isfinite(np.asarray(values, np.float64).astype(dtype)).all())
        self.out_of_range += not ok
        return ok

    def _send(self, data: bytes) -> None:
        try:
            self.sock.send(data)
            self.sent += 1
        except OSError:  # nobody listening yet (ICMP refused), buffer full: the sample is lost
            self.send_errors += 1

    def close(self) -> None:
        self.sock.close()


class OpenTrackOutput(_UdpOutput):
    """opentrack's "UDP over network" input: 48-byte datagrams (see the module docs).

    Arguments:
        host, port: where opentrack listens (default port 4242).
        from_port: optional local port to send from (``None``: any free port).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = OPENTRACK_PORT,
                 from_port: int | None = None):
        super().__init__(host, port, from_port, f"opentrack://{_url_host(host)}:{port}")

    def send(self, t, position, quaternion) -> None:
        with np.errstate(over="ignore"):  # beyond float64 in cm: inf, counted below
            values = opentrack_values(position, quaternion)
        if self._fits(values, np.float64):
            self._send(_PACK.pack(*values))


class OscOutput(_UdpOutput):
    """OSC messages ``/phjax/pose t x y z qw qx qy qz`` (float32) over UDP, via python-osc.

    Arguments:
        host, port: the OSC server (default port 9000).
        from_port: optional local port to send from.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = OSC_PORT,
                 from_port: int | None = None):
        try:
            from pythonosc.osc_message_builder import OscMessageBuilder
        except ImportError:
            raise OutputError("osc:// needs python-osc (pip install 'phjax[live]')") from None
        self._builder = OscMessageBuilder
        super().__init__(host, port, from_port, f"osc://{_url_host(host)}:{port}")

    def send(self, t, position, quaternion) -> None:
        values = [t, *np.asarray(position, np.float64), *_unit(quaternion)]
        if not self._fits(values, np.float32):
            return
        b = self._builder(address=OSC_ADDRESS)
        for v in values:
            b.add_arg(float(v), "f")
        self._send(b.build().dgram)


class TumLog(Output):
    """A TUM file of every sent pose (``t x y z qx qy qz qw``, shortest round-trip floats).

    :meth:`send` only queues the pose: a thread of the log's own formats and writes the lines
    every ``flush_interval`` seconds, and :meth:`close` writes the rest, so that a write held
    up by the disk (a page under writeback, a slow or network file system) never holds up the
    render loop that sends. A failed write (a full disk) is raised, naming the log, by the
    next :meth:`send` or by :meth:`close`; the lines not written then are lost.

    Arguments:
        path: the file (created or truncated).
        flush_interval: seconds between writes.
    """

    def __init__(self, path, flush_interval: float = 1.0):
        self.url = str(path)
        try:
            self._f = open(Path(path), "w", encoding="utf-8", newline="\n")  # noqa: SIM115 (closed in close())
        except OSError as e:
            raise OutputError(f"cannot write the log {path}: {e.strerror}") from None
        self._f.write("# timestamp tx ty tz qx qy qz qw\n")
        self._flush_interval = flush_interval
        self._rows: list[tuple] = []
        self._lock = threading.Lock()  # the queued rows
        self._error: OutputError | None = None
        self._closing = threading.Event()
        self.lines = 0
        self._writer = threading.Thread(target=self._write_main, name="phjax-live-log",
                                        daemon=True)
        self._writer.start()

    def send(self, t, position, quaternion) -> None:
        if self._error is not None:
            raise self._error
        p = np.asarray(position, np.float64)
        q = np.asarray(quaternion, np.float64)
        with self._lock:
            self._rows.append((float(t), *p.tolist(), *q[[1, 2, 3, 0]].tolist()))
        self.lines += 1

    def _write_main(self) -> None:
        while not self._closing.wait(self._flush_interval):
            if not self._write():
                return

    def _write(self) -> bool:
        """Write the queued rows and flush; False (the error kept) if that failed."""
        with self._lock:  # held for the swap only: a send never waits for the disk
            rows, self._rows = self._rows, []
        if self._error is not None or self._f.closed:
            return False
        try:
            self._f.write("".join(" ".join(map(repr, row)) + "\n" for row in rows))
            self._f.flush()
        except OSError as e:
            self._error = OutputError(f"cannot write the log {self.url}: {e.strerror or e}")
            return False
        return True

    def close(self) -> None:
        self._closing.set()
        if self._writer.is_alive() and self._writer is not threading.current_thread():
            self._writer.join()
        if self._f.closed:
            return
        self._write()  # the writer has ended: the file is this thread's now
        try:
            self._f.close()
        except OSError:  # the flush of what a failed write left in the buffer
            pass
        if self._error is not None:  # the last lines are lost: say so
            raise self._error


def _port(text: str | None, default: int, url: str) -> int:
    if text is None or text == "":
        return default
    try:
        port = int(text)
    except ValueError:
        raise OutputError(f"{url}: bad port {text!r}") from None
    if not 1 <= port <= 65535:
        raise OutputError(f"{url}: port {port} out of range 1-65535")
    return port


def open_output(url: str) -> Output:
    """An output from its URL.

    * ``opentrack://HOST[:PORT]`` (default port 4242);
    * ``osc://HOST[:PORT]`` (default port 9000);
    * either with ``?from=PORT`` to send from a fixed local port.

    Raises:
        OutputError: unknown scheme, missing host, bad or unusable port, unresolvable host.
    """
    try:
        parsed = urllib.parse.urlsplit(url)
    except ValueError as e:  # "Invalid IPv6 URL", without the URL
        raise OutputError(f"{url}: {e}") from None
    scheme = parsed.scheme.lower()
    if scheme not in ("opentrack", "osc"):
        raise OutputError(f"unknown output {url!r}; use opentrack://HOST[:PORT] or "
                          "osc://HOST[:PORT]")
    host = parsed.hostname
    port = url_port(parsed, url, OutputError)
    port_text = None if port is None else str(port)
    if not host:
        raise OutputError(f"{url}: missing host")
    if parsed.path not in ("", "/"):
        raise OutputError(f"{url}: unexpected path {parsed.path!r}")
    url_extras(parsed, url, OutputError)
    query = url_options(parsed, url, ("from",), OutputError)
    from_port = _port(query["from"][-1], 0, url) if "from" in query else None
    if scheme == "opentrack":
        return OpenTrackOutput(host, _port(port_text, OPENTRACK_PORT, url), from_port)
    return OscOutput(host, _port(port_text, OSC_PORT, url), from_port)
