r"""Trajectory file I/O (NumPy, float64, outside ``jit``).

Every reader returns a :class:`Trajectory` (or a dict of them) holding **seconds**, **metres** and
unit quaternions in phjax's **wxyz** (scalar-first, Hamilton) order, whatever the file uses. All
readers

- sort the samples by time (stable; a :class:`TrajectoryWarning` says how many were out of order),
- drop samples whose timestamp exactly repeats an earlier one (keeping the first in file order,
  with a warning that says how many were dropped),
- warn (:class:`TrajectoryUnitWarning`) when the times or positions look like another unit than
  seconds and metres: a median interval between poses outside 0.1 ms - 1 s (milliseconds or
  nanoseconds read as seconds), a median speed above 20 m/s (millimetres or centimetres read as
  metres), for files of 10 poses or more; the values are used as read,
- normalise the quaternions and flip signs so that consecutive quaternions have non-negative dot
  products (``q`` and ``-q`` are the same rotation; interpolators need the continuous choice),
- raise :class:`TrajectoryFormatError` (a ``ValueError``) for malformed input, naming the file,
  the 1-based line number and what was wrong (column count, non-numeric token -- Python's digit
  grouping ``1_000`` included --, non-finite time, infinite value, zero-norm quaternion), and
  for empty, undetectable or non-text (not UTF-8) files. Lines end at ``\n``, ``\r\n`` or
  ``\r`` (a form feed is whitespace, not a line break).
  A missing file or a directory raises the usual ``OSError`` (``FileNotFoundError``,
  ``IsADirectoryError``).

**Lost frames.** A NaN in a row's position or quaternion (or both) marks that part of the sample
as missing -- a lost frame, as the tracker (:func:`phjax.track`), the resampler and the metrics
treat it. Every reader keeps such a row with its timestamp and makes the whole part NaN (a
partial NaN quaternion becomes ``(nan, nan, nan, nan)``); every writer writes ``nan``, so a lost
frame survives a round trip. Orientation-only formats give all-NaN positions. Times must be
finite, and infinite values and zero quaternions are errors (use ``nan`` for missing data).

Formats
-------
========================  ==========================================================================
``read_tum``              TUM RGB-D text: ``t tx ty tz qx qy qz qw`` (space separated, ``#``
                          comments); ``t`` seconds, ``t*`` metres, quaternion **scalar last**.
``read_euroc``            EuRoC / TUM-VI CSV: ``t, px, py, pz, qw, qx, qy, qz`` with a ``#`` header;
                          ``t`` integer **nanoseconds**, metres, quaternion **scalar first**;
                          also EuRoC's 17-column state estimate (velocity, biases ignored).
``read_csv``              CSV with a header naming the columns ``t,x,y,z,qw,qx,qy,qz`` (phjax's own;
                          any order, common spellings such as ``timestamp,tx,ty,tz,qx,qy,qz,qw``,
                          commas, semicolons or tabs; ``x,y,z`` may be omitted together);
                          seconds, metres.
``read_corbillon``        Corbillon et al. (MMSys 2018) head traces: header
                          ``timestamp viewpoint w x y z``; seconds, quaternion scalar first;
                          orientation only (``viewpoint`` is discarded).
``read_hachaj``           Hachaj head-gesture logs: ``q;<t_ms>;x,y,z,w,`` lines (``v;`` lines,
                          derived Euler angles, are ignored); Unix **milliseconds**, scalar last;
                          orientation only.
``read_cwi``              CWI 6-DoF navigation CSV (Subramanyam et al., ACM MM 2020): Unity
                          positions in metres and Unity Euler angles in **degrees**, no timestamps
                          (``t = ViewFrame / rate``); converted to a right-handed frame, see below.
``read_avtrack360``       AVTrack360 JSON (Fremerey et al., MMSys 2018): integer-degree
                          pitch/yaw/roll, ``sec`` playback seconds; orientation only; see below.
``read_biwi_pose``        Biwi Kinect head pose ``*_pose.txt``: 3x3 rotation rows, blank line,
                          translation in **millimetres** -> ``(R, t)`` with ``t`` in metres.
========================  ==========================================================================

Writers: :func:`write_tum`, :func:`write_euroc`, :func:`write_csv` and :func:`write_trajectory`
(chosen by extension). Floats are written with Python's shortest round-trip ``repr``, so reading a
written file reproduces every float exactly; EuRoC times are rounded to whole nanoseconds.

Time precision: float64 seconds since the Unix epoch (~1.5e9 s) have a resolution of ~0.24 us, so
EuRoC nanosecond timestamps lose their sub-microsecond digits when converted (nothing is
subtracted, to keep absolute times comparable across files). That is far below any tracker's
timing accuracy.

VR frame conventions
--------------------
``read_cwi`` and ``read_avtrack360`` return orientations in one right-handed, **y-up** head/world
convention (OpenGL-style): world ``x`` right, ``y`` up, ``z`` towards the viewer's initial back;
the head frame has ``x`` right, ``y`` up and looks along its **-z** axis. The quaternion maps
head-frame vectors into the world, so the gaze direction is ``rotate(q, (0, 0, -1))``.
Corbillon and Hachaj quaternions are returned in their recording's own (undocumented) world frame.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from jaxtyping import Float

from ._np_quat import np_axis_quat as _np_axis_quat
from ._np_quat import np_hemisphere as _np_hemisphere
from ._np_quat import np_qmul as _np_quat_mul
from ._np_quat import np_reflect_z as _np_reflect_z

__all__ = [
    "Trajectory",
    "TrajectoryFormatError",
    "TrajectoryWarning",
    "TrajectoryUnitWarning",
    "read_tum",
    "read_euroc",
    "read_csv",
    "read_corbillon",
    "read_hachaj",
    "read_cwi",
    "read_avtrack360",
    "read_biwi_pose",
    "biwi_pose_to_quaternion",
    "read_trajectory",
    "split_trajectory_name",
    "read_trajectory_spec",
    "detect_format",
    "write_tum",
    "write_euroc",
    "write_csv",
    "write_trajectory",
    "unity_euler_to_quaternion",
    "avtrack360_euler_to_quaternion",
]

PathLike = str | os.PathLike

_ZERO_NORM = 1e-12  # quaternions with a smaller norm are rejected as "zero"
_ROTATION_TOL = 1e-3  # Biwi: max |R^T R - I| and |det R - 1|


def _scaled_norm(q: np.ndarray) -> np.ndarray:
    """Norm over the last axis that neither overflows nor underflows (components like 1e200
    are a valid direction; NaN rows stay NaN)."""
    m = np.max(np.abs(q), axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = q / np.where(m > 0, m, 1.0)[..., None]
    return m * np.linalg.norm(unit, axis=-1)


# ----------------------------------------------------------------------------------------------
# Trajectory, errors
# ----------------------------------------------------------------------------------------------


class Trajectory(NamedTuple):
    """A timed pose sequence (a JAX pytree with three array leaves).

    Attributes:
        times: ``(n,)`` sample times in seconds (float64, strictly increasing from the readers).
        positions: ``(n, 3)`` positions in metres; NaN rows where unknown (lost frames; all
            NaN for orientation-only sources).
        quaternions: ``(n, 4)`` unit quaternions, ``wxyz``, hemisphere-continuous (consecutive
            valid rows have dot products ``>= 0``) from the readers; NaN rows are lost frames.

    ``len(traj)`` is 3 (the tuple's fields, as for any NamedTuple, which keeps pytree and
    unpacking semantics intact); the number of samples is :attr:`num_samples`.
    """

    times: Float[np.ndarray, " n"]
    positions: Float[np.ndarray, "n 3"]
    quaternions: Float[np.ndarray, "n 4"]

    @property
    def num_samples(self) -> int:
        """Number of samples ``n``."""
        return int(np.shape(self.times)[0])

    def has_positions(self) -> bool:
        """Whether any position coordinate is finite (``False`` for orientation-only data).

        Uses concrete values: call it outside ``jit``.
        """
        return bool(np.any(np.isfinite(np.asarray(self.positions))))

    @classmethod
    def from_arrays(
        cls,
        times: Float[Any, " n"],
        quaternions: Float[Any, "n 4"],
        positions: Float[Any, "n 3"] | None = None,
    ) -> Trajectory:
        """Build a canonical trajectory from arrays (same clean-up as the readers).

        Arguments:
            times: ``(n,)`` seconds, finite.
            quaternions: ``(n, 4)`` ``wxyz``, non-zero (normalised here); NaN rows are lost
                frames.
            positions: ``(n, 3)`` metres, NaN rows are lost frames; ``None`` for orientation
                only.

        Returns:
            A :class:`Trajectory` sorted by time, duplicates dropped (with a warning),
            quaternions normalised and hemisphere-continuous.
        """
        t, p, q = _validate_arrays(times, positions, quaternions)
        return _canonicalise(t, p, q, "<arrays>", check_units=False)


class TrajectoryFormatError(ValueError):
    """A trajectory file is malformed. The message names the file, the line and the problem.

    Attributes:
        path: the file (or ``None``).
        line: 1-based line number (or ``None`` when the problem has no single line).
    """

    def __init__(self, message: str, *, path: PathLike | None = None, line: int | None = None):
        super().__init__(message)
        self.path = path
        self.line = line


class TrajectoryWarning(UserWarning):
    """Recoverable irregularities in a trajectory file (unsorted or duplicate timestamps, times
    or positions that look like another unit)."""


class TrajectoryUnitWarning(TrajectoryWarning):
    """A file's times or positions look like another unit than seconds and metres (see the
    module docs); the values are used as read. Filter this category to silence it for data
    that really is that slow, fast or large."""


def _err(path: PathLike, line: int | None, what: str) -> TrajectoryFormatError:
    loc = f"{os.fspath(path)}" + (f", line {line}" if line is not None else "")
    return TrajectoryFormatError(f"{loc}: {what}", path=path, line=line)


# ----------------------------------------------------------------------------------------------
# NumPy quaternion helpers (float64 regardless of JAX's x64 flag)
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Parsing helpers
# ----------------------------------------------------------------------------------------------


def _read_lines(path: PathLike) -> list[str]:
    r"""The file's lines, broken at ``\n``, ``\r\n`` and ``\r`` only (``str.splitlines`` also
    breaks at form feeds, ``\x1c``-``\x1e``, ``\x85`` and ``\u2028``, which would shift the line
    numbers of the messages and split a row whose numbers a form feed separates)."""
    try:
        with open(path, encoding="utf-8-sig") as f:  # universal newlines: \r\n, \r -> \n
            return f.read().split("\n")
    except UnicodeDecodeError as e:
        raise _err(path, None, f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None


def _data_lines(lines: list[str], comment: str | None = "#") -> list[tuple[int, str]]:
    """``(1-based line number, stripped text)`` of non-blank, non-comment lines."""
    out = []
    for i, line in enumerate(lines, 1):
        s = line.strip()
        if s and not (comment and s.startswith(comment)):
            out.append((i, s))
    return out


def _float_table(
    path: PathLike,
    linenos: list[int],
    rows: list[list[str]],
    names: list[str],
    file_columns: list[int] | None = None,
) -> np.ndarray:
    """Parse string rows into an ``(n, len(names))`` float64 table with line-aware errors.

    ``file_columns`` (1-based) names the file columns the entries came from, for messages.
    """
    ncols = len(names)
    for ln, r in zip(linenos, rows):
        if len(r) != ncols:
            raise _err(
                path, ln, f"expected {ncols} columns ({' '.join(names)}), found {len(r)}"
            )
    if not rows:
        raise _err(path, None, "no data lines")
    # Python and NumPy read digit-group underscores ('1_5' is 15): no trajectory format writes
    # numbers so, and such a token is a typo or a field joined by '_', so it is refused
    underscores = any("_" in tok for r in rows for tok in r)
    if not underscores:
        try:
            return np.array(rows, dtype=np.float64).reshape(len(rows), ncols)
        except ValueError:
            pass
    for ln, r in zip(linenos, rows):
        for j, tok in enumerate(r):
            try:
                if "_" in tok:
                    raise ValueError(tok)
                float(tok)
            except ValueError:
                col = file_columns[j] if file_columns else j + 1
                raise _err(
                    path, ln, f"non-numeric value {tok!r} in column {col} ({names[j]})"
                ) from None
    # NumPy and Python disagree on some exotic token; fall back to Python's parser.
    return np.array([[float(tok) for tok in r] for r in rows], dtype=np.float64)


def _check_values(
    path: PathLike,
    linenos: list[int],
    t: np.ndarray,
    p: np.ndarray | None,
    q: np.ndarray,
    labels: tuple[str, str, str] = ("timestamp", "position", "quaternion"),
) -> None:
    """Reject non-finite times, infinite positions / quaternions and zero quaternions (NaN
    positions and quaternions are lost frames)."""

    def first(mask: np.ndarray) -> int | None:
        idx = np.flatnonzero(mask)
        return linenos[idx[0]] if idx.size else None

    if (ln := first(~np.isfinite(t))) is not None:
        raise _err(path, ln, f"non-finite {labels[0]}")
    if p is not None and (ln := first(np.any(np.isinf(p), axis=-1))) is not None:
        raise _err(path, ln, f"infinite {labels[1]} (use nan for a missing position)")
    if (ln := first(np.any(np.isinf(q), axis=-1))) is not None:
        raise _err(path, ln, f"infinite {labels[2]} (use nan for a lost frame)")
    zero = ~np.any(np.isnan(q), axis=-1) & (_scaled_norm(q) < _ZERO_NORM)
    if (ln := first(zero)) is not None:
        raise _err(path, ln, f"zero-norm {labels[2]}")


def split_trajectory_name(spec: PathLike) -> tuple[str, str | None]:
    """``(path, name)`` of a command line's ``FILE#NAME`` (the trajectory ``NAME`` of a file
    holding several, see :func:`read_trajectory`); ``(spec, None)`` when ``spec`` is an existing
    file or has no ``#``."""
    spec = os.fspath(spec)
    if "#" in spec and not os.path.exists(spec):
        path, name = spec.rsplit("#", 1)
        return path, name
    return spec, None


#: median interval between poses (s) outside which a file's times are taken for another unit
_INTERVAL_RANGE = (1e-4, 1.0)
#: median speed (m/s) above which a file's positions are taken for millimetres or centimetres:
#: heads and hand-held cameras move at 0.03-1.2 m/s (median) in every recording of
#: ``../shared/data``; the same motion in centimetres is 3-120 "m/s"
_SPEED_LIMIT = 20.0
#: files with fewer poses are not checked for their units
_UNIT_MIN_POSES = 10


def _caller_level() -> int:
    """The ``stacklevel`` of a warning raised in this module that points at the first frame
    outside it (the user's call of ``read_trajectory``, ``read_csv``, ...), however many of
    this module's functions lie between."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename == __file__:
        frame, level = frame.f_back, level + 1
    return level


def _unit_warnings(t: np.ndarray, p: np.ndarray, source: str) -> None:
    """A :class:`TrajectoryUnitWarning` when the sorted times or the positions look like another
    unit than the seconds and metres the file is read in: the median interval between poses
    outside 0.1 ms - 1 s (milliseconds or nanoseconds read as seconds make a 30 Hz tracker a
    0.03 Hz or 3e7 Hz one) or a median speed above 20 m/s (millimetres or centimetres). Files
    of fewer than :data:`_UNIT_MIN_POSES` poses are not checked (a few frames picked from a
    sequence, as the Biwi samples' three, are far apart in time)."""
    if t.size < _UNIT_MIN_POSES:
        return
    interval = float(np.median(np.diff(t)))
    lo, hi = _INTERVAL_RANGE
    if not lo <= interval <= hi:
        warnings.warn(
            f"{source}: the median interval between poses is {interval:.3g} s "
            f"({1 / interval:.3g} Hz); times are read in seconds: are they in "
            f"{'milliseconds, microseconds or nanoseconds' if interval > hi else 'another unit'}?",
            TrajectoryUnitWarning, stacklevel=_caller_level())
        return  # speeds in a wrong time unit say nothing about the positions
    ok = np.all(np.isfinite(p), axis=-1)
    if np.count_nonzero(ok) < 3:
        return
    speed = float(np.median(np.linalg.norm(np.diff(p[ok], axis=0), axis=-1) / np.diff(t[ok])))
    if speed > _SPEED_LIMIT:
        warnings.warn(
            f"{source}: the median speed is {speed:.3g} m/s; positions are read in metres: "
            "are they in millimetres or centimetres?", TrajectoryUnitWarning,
            stacklevel=_caller_level())


def _canonicalise(t: np.ndarray, p: np.ndarray, q: np.ndarray, source: str, *,
                  check_units: bool = True) -> Trajectory:
    """Sort by time, drop duplicate times, normalise and make quaternions continuous; for a
    file (``check_units``), warn when its times or positions look like another unit."""
    n_desc = int(np.count_nonzero(np.diff(t) < 0))
    if n_desc:
        warnings.warn(
            f"{source}: {n_desc} timestamp(s) out of order; samples sorted by time",
            TrajectoryWarning,
            stacklevel=_caller_level(),
        )
    order = np.argsort(t, kind="stable")
    t, p, q = t[order], p[order], q[order]
    keep = np.concatenate([[True], np.diff(t) != 0])
    n_dup = int(keep.size - np.count_nonzero(keep))
    if n_dup:
        warnings.warn(
            f"{source}: dropped {n_dup} sample(s) with duplicate timestamps "
            "(kept the first occurrence in file order)",
            TrajectoryWarning,
            stacklevel=_caller_level(),
        )
        t, p, q = t[keep], p[keep], q[keep]
    if check_units:
        _unit_warnings(t, p, source)
    p = np.where(np.any(np.isnan(p), axis=-1, keepdims=True), np.nan, p)
    lost = np.any(np.isnan(q), axis=-1)
    q = np.where(lost[:, None], np.nan, q)
    if not np.all(lost):  # continuity across lost frames: between consecutive valid rows
        qv = q[~lost]
        # quaternions already unit to rounding (every file phjax writes) are kept as they are,
        # so that reading a written file gives back every float (normalising again moves them
        # by up to 2e-16); the others are normalised (scaled first: no overflow in the norm)
        with np.errstate(over="ignore"):  # huge components: not unit, normalised below
            unit = np.abs(np.sum(qv * qv, axis=-1) - 1) <= 8 * np.finfo(np.float64).eps
        scaled = qv / np.max(np.abs(qv), axis=-1, keepdims=True)
        normed = scaled / np.linalg.norm(scaled, axis=-1, keepdims=True)
        q[~lost] = _np_hemisphere(np.where(unit[:, None], qv, normed))
    return Trajectory(
        np.ascontiguousarray(t, dtype=np.float64),
        np.ascontiguousarray(p, dtype=np.float64),
        np.ascontiguousarray(q, dtype=np.float64),
    )


def _validate_arrays(times, positions, quaternions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.asarray(times, dtype=np.float64)
    q = np.asarray(quaternions, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"times must have shape (n,), got {t.shape}")
    n = t.shape[0]
    if q.shape != (n, 4):
        raise ValueError(f"quaternions must have shape ({n}, 4), got {q.shape}")
    p = np.full((n, 3), np.nan) if positions is None else np.asarray(positions, dtype=np.float64)
    if p.shape != (n, 3):
        raise ValueError(f"positions must have shape ({n}, 3), got {p.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("times must be finite")
    if np.any(np.isinf(q)):
        raise ValueError("quaternions must not be infinite (use nan for a lost frame)")
    if np.any(np.isinf(p)):
        raise ValueError("positions must not be infinite (use nan for missing)")
    if np.any(~np.any(np.isnan(q), axis=-1) & (_scaled_norm(q) < _ZERO_NORM)):
        raise ValueError("quaternions must be non-zero (use nan for a lost frame)")
    return t, p, q


# ----------------------------------------------------------------------------------------------
# Readers
# ----------------------------------------------------------------------------------------------

_TUM_NAMES = ["t", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
_EUROC_NAMES = ["t_ns", "px", "py", "pz", "qw", "qx", "qy", "qz"]
_CSV_NAMES = ["t", "x", "y", "z", "qw", "qx", "qy", "qz"]
_CORBILLON_HEADER = ["timestamp", "viewpoint", "w", "x", "y", "z"]


def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM RGB-D trajectory ``t tx ty tz qx qy qz qw`` (s, m, scalar-last quaternion).

    Arguments:
        path: text file; whitespace separated, ``#`` starts a comment line.

    Returns:
        The :class:`Trajectory` (quaternions reordered to ``wxyz``).
    """
    data = _data_lines(_read_lines(path))
    linenos = [ln for ln, _ in data]
    a = _float_table(path, linenos, [s.split() for _, s in data], _TUM_NAMES)
    t, p, q = a[:, 0], a[:, 1:4], a[:, [7, 4, 5, 6]]
    _check_values(path, linenos, t, p, q)
    return _canonicalise(t, p, q, os.fspath(path))


def _split_csv(s: str, sep: str = ",") -> list[str]:
    return [tok.strip() for tok in s.split(sep)]


def _csv_separator(header: str) -> str:
    """The column separator of a CSV header line: a comma, else a semicolon, else a tab."""
    return next((sep for sep in (",", ";", "\t") if sep in header), ",")


#: columns of EuRoC's ``state_groundtruth_estimate0/data.csv``: the 8 of the pose, then
#: velocity (3), gyroscope bias (3) and accelerometer bias (3)
_EUROC_STATE_COLUMNS = 17


def read_euroc(path: PathLike) -> Trajectory:
    """Read a EuRoC / TUM-VI ground-truth CSV ``t[ns], px, py, pz, qw, qx, qy, qz`` (or
    EuRoC's 17-column state estimate, whose velocity and bias columns are ignored).

    Arguments:
        path: CSV file; lines starting with ``#`` (the header) are skipped.

    Returns:
        The :class:`Trajectory`; times in float64 seconds since the same epoch as the file
        (integer nanoseconds are split into whole seconds and a fraction before conversion, so
        the only loss is float64's resolution at the result's magnitude, ~0.24 us at 1.5e9 s).
    """
    data = _data_lines(_read_lines(path))
    linenos = [ln for ln, _ in data]
    rows = [_split_csv(s) for _, s in data]
    if rows and len(rows[0]) == _EUROC_STATE_COLUMNS:
        # the state estimate (state_groundtruth_estimate0/data.csv): the pose, then velocity
        # and IMU biases, which a trajectory has no use for
        for ln, r in zip(linenos, rows):
            if len(r) != _EUROC_STATE_COLUMNS:
                raise _err(path, ln, f"expected {_EUROC_STATE_COLUMNS} columns (EuRoC state "
                                     f"estimate: pose, velocity, biases), found {len(r)}")
        rows = [r[:len(_EUROC_NAMES)] for r in rows]
    a = _float_table(path, linenos, rows, _EUROC_NAMES)
    t = a[:, 0] * 1e-9
    try:  # exact integer nanoseconds when every timestamp is an integer literal
        ns = np.array([r[0] for r in rows], dtype=np.int64)
    except (ValueError, OverflowError):
        ns = None
    if ns is not None:
        t = (ns // 10**9).astype(np.float64) + (ns % 10**9).astype(np.float64) * 1e-9
    p, q = a[:, 1:4], a[:, 4:8]
    _check_values(path, linenos, t, p, q)
    return _canonicalise(t, p, q, os.fspath(path))


#: column names ``read_csv`` accepts for each quantity, compared after removing a unit in
#: brackets and lower-casing and removing everything but letters and digits (``Pos_X``,
#: ``pos.x`` and ``pos x [m]`` are all ``posx``)
_CSV_ALIASES = {
    "t": ("t", "time", "times", "timestamp", "stamp", "ts", "seconds"),
    **{c: (c, f"t{c}", f"p{c}", f"pos{c}", f"position{c}", f"translation{c}")
       for c in ("x", "y", "z")},
    **{f"q{c}": (f"q{c}", f"quat{c}", f"quaternion{c}", f"orientation{c}", f"rotation{c}",
                 f"rot{c}") for c in "wxyz"},
}
_CSV_ROLE = {alias: role for role, names in _CSV_ALIASES.items() for alias in names}
#: the quantities a CSV header must name (the positions may be absent together)
_CSV_REQUIRED = ("t", "qw", "qx", "qy", "qz")
#: a unit in a CSV column name: ``t [s]``, ``x (mm)``, ``x_[m]``, ``q_w []``
_CSV_UNIT = re.compile(r"[\[(]([^\])]*)[\])]\s*$")
#: the units read_csv converts (to seconds and metres); the quaternion's unit must be empty
_CSV_UNITS = {"t": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "ns": 1e-9},
              "x": {"m": 1.0, "cm": 1e-2, "mm": 1e-3}}
#: column names of the nanoseconds beside whole seconds (ROS's ``sec`` / ``nanosec`` pair)
_CSV_NANOSECONDS = ("nsec", "nsecs", "nanosec", "nanosecs", "nanoseconds", "ns")
#: empty fields and the missing-value words of spreadsheets and pandas, read as NaN
_CSV_MISSING = ("", "na", "n/a", "nan", "null", "none")


def _csv_unit(name: str) -> str | None:
    """The unit in brackets at the end of a column name (``None`` without one)."""
    m = _CSV_UNIT.search(name)
    return m.group(1).strip().lower() if m else None


def _csv_key(name: str) -> str:
    name = _CSV_UNIT.sub("", name)
    return "".join(ch for ch in name.lower() if ch.isalnum())


def _is_csv_header(line: str) -> bool:
    """Whether ``line`` names the columns :func:`read_csv` needs (any accepted separator)."""
    named = {_CSV_ROLE.get(_csv_key(c)) for c in _split_csv(line, _csv_separator(line))}
    return set(_CSV_REQUIRED) <= named


def _csv_roles(names: list[str]) -> dict[str, int]:
    """Column index of each quantity that ``names`` (a CSV header) holds; raises ``ValueError``
    naming two columns that both name one quantity, or a seconds / nanoseconds pair."""
    found: dict[str, int] = {}
    for i, name in enumerate(names):
        role = _CSV_ROLE.get(_csv_key(name))
        if role is None:
            continue
        if role in found:
            raise ValueError(f"columns {names[found[role]]!r} and {name!r} both name {role!r}")
        found[role] = i
    nanos = [n for n in names if _csv_key(n) in _CSV_NANOSECONDS]
    if "t" in found and nanos:
        raise ValueError(f"{names[found['t']]!r} beside {nanos[0]!r} looks like whole seconds "
                         "and nanoseconds: combine them into one time column in seconds")
    return found


def _csv_scale(name: str, role: str) -> float:
    """The factor to seconds / metres of column ``name`` (``role`` t, x, y, z, q*) from its
    unit in brackets; raises ``ValueError`` for a unit read_csv does not convert."""
    unit = _csv_unit(name)
    if unit is None:
        return 1.0
    if role.startswith("q"):
        if unit in ("", "-", "1"):
            return 1.0
        raise ValueError(f"column {name!r}: a quaternion has no unit")
    table = _CSV_UNITS["t" if role == "t" else "x"]
    if unit not in table:
        raise ValueError(f"column {name!r}: unit {unit!r} is not one of {sorted(table)}")
    return table[unit]


def _excel_separator(line: str) -> str | None:
    """The separator that Excel's first line ``sep=;`` names, else ``None``."""
    return line[4] if len(line) == 5 and line.lower().startswith("sep=") else None


def _csv_header_line(lines: list[str], data: list[tuple[int, str]]) -> tuple[int, str] | None:
    """``(line number, text)`` of a CSV file's header (``lines``; ``data``: its non-comment
    lines): its first non-comment line when that names the columns, else the last ``#``
    comment line before the data when that does (``#t,x,y,z,qw,qx,qy,qz``) with its separator
    in the first data line, else ``None``."""
    if _is_csv_header(data[0][1]):
        return data[0]
    for i in range(data[0][0] - 1, 0, -1):
        s = lines[i - 1].strip()
        if s.startswith("#"):
            text = s.lstrip("#").strip()
            named = _is_csv_header(text) and _csv_separator(text) in data[0][1]
            return (i, text) if named else None
    return None


def read_csv(path: PathLike) -> Trajectory:
    """Read a CSV file with a header naming its columns (phjax's own:
    ``t,x,y,z,qw,qx,qy,qz``), in any order, separated by commas (or semicolons or tabs, as the
    header is).

    Names are matched case-insensitively with everything but letters and digits removed, and
    common spellings are accepted: time ``t``, ``time``, ``timestamp``, ``stamp``, ``ts``;
    position ``x``, ``tx``, ``px``, ``pos_x``, ``position_x`` (and ``y``, ``z``); quaternion
    ``qw``, ``quat_w``, ``orientation_w``, ``rotation_w`` (and ``x``, ``y``, ``z``). The
    quaternion is read by name, so scalar-first and scalar-last files both work. A unit in
    brackets at the end of a name is converted: ``t [ms]`` (``s``, ``ms``, ``us``, ``ns``),
    ``x (mm)`` (``m``, ``cm``, ``mm``). The position columns may all be absent (orientation
    only: positions become NaN); other columns are ignored. ``#`` lines are comments; the
    header may be one (``#t,x,y,z,qw,qx,qy,qz``, the last comment line before the data).
    Empty fields and ``NA`` / ``null`` / ``None`` are missing values (NaN: a lost frame).
    Spreadsheet exports: Excel's first line ``sep=;`` names the separator, and with a
    separator other than the comma a decimal comma is read (``1,5`` is 1.5).

    Arguments:
        path: CSV file (seconds, metres).

    Returns:
        The :class:`Trajectory`.
    """
    lines = _read_lines(path)
    data = _data_lines(lines)
    forced = _excel_separator(data[0][1]) if data else None
    if forced:
        data = data[1:]
    if not data:
        raise _err(path, None, "empty file (expected a header t,x,y,z,qw,qx,qy,qz)")
    hline, header = _csv_header_line(lines, data) or data[0]
    sep = forced or _csv_separator(header)
    names = _split_csv(header, sep)
    if all(map(_is_number, names)):
        raise _err(path, hline, "the first line is numbers, not a header: name the columns in "
                                "a first line (t,x,y,z,qw,qx,qy,qz in any order)")
    try:
        roles = _csv_roles(names)
    except ValueError as e:
        raise _err(path, hline, str(e)) from None
    have_pos = [c in roles for c in ("x", "y", "z")]
    if any(have_pos) and not all(have_pos):
        raise _err(path, hline, "header must name all of x,y,z or none of them")
    wanted = [*_CSV_REQUIRED] + (["x", "y", "z"] if all(have_pos) else [])
    missing = [c for c in wanted if c not in roles]
    if missing:
        raise _err(
            path, hline,
            f"header {header!r} lacks column(s) {missing} (expected t,x,y,z,qw,qx,qy,qz)",
        )
    idx = [roles[c] for c in wanted]
    try:
        scale = np.array([_csv_scale(names[i], c) for i, c in zip(idx, wanted)])
    except ValueError as e:
        raise _err(path, hline, str(e)) from None
    body = [(ln, s) for ln, s in data if ln > hline]
    linenos = [ln for ln, _ in body]
    rows = []
    for ln, s in body:
        r = _split_csv(s, sep)
        if len(r) != len(names):
            raise _err(path, ln, f"expected {len(names)} columns ({header}), found {len(r)}")
        if sep != ",":  # a decimal comma (spreadsheets in many locales: 1,5 with ; between)
            r = [tok.replace(",", ".") for tok in r]
        rows.append([("nan" if r[i].lower() in _CSV_MISSING else r[i]) for i in idx])
    a = _float_table(path, linenos, rows, wanted, [i + 1 for i in idx]) * scale
    t, q = a[:, 0], a[:, 1:5]
    p = a[:, 5:8] if all(have_pos) else np.full((len(t), 3), np.nan)
    _check_values(path, linenos, t, p, q)
    return _canonicalise(t, p, q, os.fspath(path))


def read_corbillon(path: PathLike) -> Trajectory:
    """Read a Corbillon et al. head trace ``timestamp viewpoint w x y z`` (with that header).

    Arguments:
        path: space-separated text file (seconds, scalar-first quaternion).

    Returns:
        An orientation-only :class:`Trajectory` (NaN positions); the ``viewpoint`` column is
        dropped and the frequent ``q``/``-q`` sign flips of the raw file are removed.
    """
    data = _data_lines(_read_lines(path), comment=None)
    if not data or data[0][1].lower().split() != _CORBILLON_HEADER:
        ln = data[0][0] if data else None
        raise _err(path, ln, f"expected the header {' '.join(_CORBILLON_HEADER)!r}")
    body = data[1:]
    linenos = [ln for ln, _ in body]
    a = _float_table(path, linenos, [s.split() for _, s in body], _CORBILLON_HEADER)
    t, q = a[:, 0], a[:, 2:6]
    _check_values(path, linenos, t, None, q)
    return _canonicalise(t, np.full((len(t), 3), np.nan), q, os.fspath(path))


def read_hachaj(path: PathLike) -> Trajectory:
    """Read a Hachaj head-gesture log: ``q;<t_ms>;x,y,z,w,`` lines; ``v;`` lines are ignored.

    Arguments:
        path: ``;``-separated text (Unix milliseconds, scalar-last quaternion; the trailing comma
            is optional).

    Returns:
        An orientation-only :class:`Trajectory` (times in seconds, NaN positions).
    """
    names = ["t_ms", "qx", "qy", "qz", "qw"]
    linenos, rows = [], []
    for ln, s in _data_lines(_read_lines(path), comment=None):
        parts = s.split(";")
        tag = parts[0].strip()
        if tag == "v":
            continue
        if tag != "q":
            raise _err(path, ln, f"unknown record type {tag!r} (expected 'q;' or 'v;')")
        if len(parts) != 3:
            raise _err(path, ln, f"expected 'q;<t_ms>;x,y,z,w', found {len(parts)} ';'-fields")
        comps = _split_csv(parts[2])
        if comps and comps[-1] == "":
            comps = comps[:-1]
        if len(comps) != 4:
            raise _err(path, ln, f"expected 4 quaternion components, found {len(comps)}")
        linenos.append(ln)
        rows.append([parts[1].strip()] + comps)
    a = _float_table(path, linenos, rows, names)
    t, q = a[:, 0] * 1e-3, a[:, [4, 1, 2, 3]]
    _check_values(path, linenos, t, None, q)
    return _canonicalise(t, np.full((len(t), 3), np.nan), q, os.fspath(path))


def unity_euler_to_quaternion(
    rx: Float[Any, "*batch"], ry: Float[Any, "*batch"], rz: Float[Any, "*batch"]
) -> Float[np.ndarray, "*batch 4"]:
    """Unity Euler angles (degrees) -> right-handed ``wxyz`` quaternion (phjax's VR convention).

    Unity (left-handed, ``x`` right, ``y`` up, ``z`` forward) composes
    ``R_u = R_y(ry) R_x(rx) R_z(rz)`` (roll about ``z`` first, then pitch about ``x``, then yaw
    about ``y``, all about the fixed axes; positive ``rx`` looks down, positive ``ry`` turns
    right). phjax maps Unity coordinates to a right-handed frame by flipping ``z``:
    ``(x, y, z)_rh = (x, y, -z)_unity``, i.e. ``S = diag(1, 1, -1)``. The rotation becomes
    ``R = S R_u S`` (a proper rotation, ``det = +1``), whose quaternion is
    ``(w, -x, -y, z)`` of Unity's ``q_u = q_y q_x q_z``. Unity's forward ``+z`` is ``-z`` here,
    so the gaze direction is ``R @ (0, 0, -1)``.

    Arguments:
        rx, ry, rz: Unity ``eulerAngles`` in degrees (any wrap, e.g. 0..360).

    Returns:
        ``(*batch, 4)`` unit quaternions ``wxyz`` (float64).
    """
    rx, ry, rz = (np.deg2rad(np.asarray(a, dtype=np.float64)) for a in (rx, ry, rz))
    qu = _np_quat_mul(
        _np_quat_mul(_np_axis_quat(1, ry), _np_axis_quat(0, rx)), _np_axis_quat(2, rz)
    )
    return _np_reflect_z(qu)


def read_cwi(
    path: PathLike, participant: str | None = None, rate: float = 30.0
) -> dict[str, Trajectory] | Trajectory:
    """Read a CWI 6-DoF navigation CSV (``FrameNumber,HMDPX,...,Participant,Dataset,ViewFrame``).

    Positions are converted from Unity (left-handed, y up) by ``(x, y, -z)`` and rotations by
    :func:`unity_euler_to_quaternion` (see there for the exact convention). The files carry no
    timestamps: ``t = ViewFrame / rate`` seconds, assuming one sample per rendered frame at
    ``rate`` Hz (an assumption of the dataset description, not a measured clock).

    Arguments:
        path: the CSV file.
        participant: e.g. ``"P01_V1"`` to return only that participant's trajectory.
        rate: assumed sample rate in Hz.

    Returns:
        ``{participant: Trajectory}`` in file order, or one :class:`Trajectory`.
    """
    if not rate > 0:
        raise ValueError(f"rate must be positive, got {rate}")
    data = _data_lines(_read_lines(path), comment=None)
    if not data:
        raise _err(path, None, "empty file")
    hline, header = data[0]
    names = _split_csv(header)
    need = ["HMDPX", "HMDPY", "HMDPZ", "HMDRX", "HMDRY", "HMDRZ", "ViewFrame"]
    missing = [c for c in need + ["Participant"] if c not in names]
    if missing:
        raise _err(path, hline, f"header lacks column(s) {missing}")
    idx = [names.index(c) for c in need]
    ip = names.index("Participant")
    linenos, rows, who = [], [], []
    for ln, s in data[1:]:
        r = _split_csv(s)
        if len(r) != len(names):
            raise _err(path, ln, f"expected {len(names)} columns ({header}), found {len(r)}")
        linenos.append(ln)
        rows.append([r[i] for i in idx])
        who.append(r[ip])
    a = _float_table(path, linenos, rows, need, [i + 1 for i in idx])
    bad = ~np.isfinite(a[:, 6]) | np.any(np.isinf(a[:, :6]), axis=-1)  # NaN: a lost frame
    if np.any(bad):
        ln = linenos[int(np.flatnonzero(bad)[0])]
        raise _err(path, ln, "non-finite ViewFrame or infinite position/angle")
    q = unity_euler_to_quaternion(a[:, 3], a[:, 4], a[:, 5])
    t = a[:, 6] / rate
    p = a[:, :3] * np.array([1.0, 1.0, -1.0])
    who_arr = np.asarray(who)
    order = list(dict.fromkeys(who))
    if participant is not None:
        if participant not in order:
            raise ValueError(f"{os.fspath(path)}: no participant {participant!r}; have {order}")
        order = [participant]
    out = {}
    for name in order:
        m = who_arr == name
        out[name] = _canonicalise(t[m], p[m], q[m], f"{os.fspath(path)} [{name}]")
    return out[participant] if participant is not None else out


def avtrack360_euler_to_quaternion(
    pitch: Float[Any, "*batch"], yaw: Float[Any, "*batch"], roll: Float[Any, "*batch"]
) -> Float[np.ndarray, "*batch 4"]:
    """AVTrack360 pitch/yaw/roll (degrees) -> right-handed ``wxyz`` quaternion.

    Convention (phjax's VR frame: ``x`` right, ``y`` up, gaze along ``-z``): yaw about the
    vertical ``y`` axis, then pitch about the head's new ``x`` (right) axis, then roll about the
    head's new gaze axis (intrinsic y-x-z): ``q = q_y(-yaw) q_x(-pitch) q_z(-roll)``. The signs
    follow the dataset README: turning left is negative yaw, looking up is negative pitch and
    tilting the head to the left is negative roll, so positive yaw turns the gaze to ``+x``,
    positive pitch lowers it, and positive roll tilts the head's up-axis towards ``+x``.

    Arguments:
        pitch, yaw, roll: angles in degrees.

    Returns:
        ``(*batch, 4)`` unit quaternions ``wxyz`` (float64).
    """
    pitch, yaw, roll = (np.deg2rad(np.asarray(a, dtype=np.float64)) for a in (pitch, yaw, roll))
    return _np_quat_mul(
        _np_quat_mul(_np_axis_quat(1, -yaw), _np_axis_quat(0, -pitch)), _np_axis_quat(2, -roll)
    )


def read_avtrack360(path: PathLike) -> dict[str, Trajectory]:
    """Read an AVTrack360 head-rotation JSON (one subject, several videos).

    Arguments:
        path: JSON ``{"data": [{"filename", "pitch_yaw_roll_data_hmd": [{pitch, yaw, roll,
            sec}, ...]}, ...]}``; angles in degrees, ``sec`` playback seconds.

    Returns:
        ``{video filename: Trajectory}`` (orientation only, NaN positions), angles converted with
        :func:`avtrack360_euler_to_quaternion`; a ``NaN`` angle is a lost frame. Structural
        errors are located by JSON path (syntax errors by line number); a file without videos
        (``"data": []``) is an error.
    """
    try:
        with open(path, encoding="utf-8-sig") as f:
            doc = json.load(f)
    except json.JSONDecodeError as e:
        raise _err(path, e.lineno, f"invalid JSON: {e.msg}") from None
    except UnicodeDecodeError as e:
        raise _err(path, None, f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except RecursionError:  # json's parser recurses once per [ or {
        raise _err(path, None, "invalid JSON: nested too deeply") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("data"), list):
        raise _err(path, None, "expected a JSON object with a 'data' list")
    if not doc["data"]:
        raise _err(path, None, "no videos in 'data' (expected objects with a 'filename' and "
                               "a 'pitch_yaw_roll_data_hmd' list)")
    out: dict[str, Trajectory] = {}
    for i, video in enumerate(doc["data"]):
        where = f"data[{i}]"
        if not isinstance(video, dict) or not isinstance(video.get("filename"), str):
            raise _err(path, None, f"{where}: expected an object with a 'filename' string")
        name = video["filename"]
        if name in out:
            raise _err(path, None, f"{where}: duplicate filename {name!r}")
        samples = video.get("pitch_yaw_roll_data_hmd")
        if not isinstance(samples, list) or not samples:
            raise _err(path, None, f"{where}: expected a non-empty 'pitch_yaw_roll_data_hmd' list")
        vals = np.empty((len(samples), 4))
        for j, s in enumerate(samples):
            for k, key in enumerate(("sec", "pitch", "yaw", "roll")):
                v = s.get(key) if isinstance(s, dict) else None
                lost = key != "sec" and isinstance(v, float) and math.isnan(v)
                if (isinstance(v, bool) or not isinstance(v, (int, float))
                        or not (lost or (abs(v) < 1e300 and math.isfinite(v)))):
                    raise _err(
                        path, None,
                        f"{where}.pitch_yaw_roll_data_hmd[{j}]: missing or non-finite {key!r}",
                    )
                vals[j, k] = v
        q = avtrack360_euler_to_quaternion(vals[:, 1], vals[:, 2], vals[:, 3])
        out[name] = _canonicalise(
            vals[:, 0], np.full((len(samples), 3), np.nan), q, f"{os.fspath(path)} [{name}]"
        )
    return out


def read_biwi_pose(path: PathLike) -> tuple[Float[np.ndarray, "3 3"], Float[np.ndarray, "3"]]:
    """Read a Biwi Kinect head pose ``*_pose.txt``: 3 rows of R, blank line, translation in mm.

    Arguments:
        path: the pose file.

    Returns:
        ``(R, t)``: the 3x3 head rotation in the depth-camera frame, as stored, and the head
        centre in **metres** in that frame. ``R`` is checked to be a rotation (orthonormal and
        ``det = 1`` to 1e-3).
    """
    data = _data_lines(_read_lines(path), comment="#")
    if len(data) != 4:
        raise _err(
            path, data[4][0] if len(data) > 4 else None,
            f"expected 4 non-blank lines (3 rotation rows, 1 translation), found {len(data)}",
        )
    linenos = [ln for ln, _ in data]
    a = _float_table(path, linenos, [s.split() for _, s in data], ["c1", "c2", "c3"])
    bad = ~np.all(np.isfinite(a), axis=1)
    if np.any(bad):
        raise _err(path, linenos[int(np.flatnonzero(bad)[0])], "non-finite value")
    r, t_mm = a[:3], a[3]
    ortho = np.abs(r.T @ r - np.eye(3)).max()
    det = np.linalg.det(r)
    if ortho > _ROTATION_TOL or abs(det - 1) > _ROTATION_TOL:
        raise _err(
            path, linenos[0],
            f"lines {linenos[0]}-{linenos[2]} are not a rotation matrix "
            f"(max |R^T R - I| = {ortho:.2e}, det = {det:.6f})",
        )
    return r, t_mm * 1e-3


def biwi_pose_to_quaternion(rotation: Float[Any, "*batch 3 3"]) -> Float[np.ndarray, "*batch 4"]:
    """Unit quaternion (``wxyz``, ``w >= 0``) of a rotation matrix such as Biwi's ``R``.

    Shepperd's method in NumPy float64 (the best-conditioned of the four formulas is used),
    followed by normalisation, so slightly non-orthonormal annotated matrices are fine.

    Arguments:
        rotation: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 4)`` quaternions with ``quat_to_matrix(q) ~= rotation``.
    """
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must have shape (..., 3, 3), got {m.shape}")
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    diag = np.stack(  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    k = np.argmax(diag, axis=-1)
    dk = np.take_along_axis(diag, k[..., None], -1)[..., 0]  # 4 q_k^2, the largest
    a = m[..., 2, 1] - m[..., 1, 2]
    b = m[..., 0, 2] - m[..., 2, 0]
    c = m[..., 1, 0] - m[..., 0, 1]
    d = m[..., 0, 1] + m[..., 1, 0]
    e = m[..., 0, 2] + m[..., 2, 0]
    f = m[..., 1, 2] + m[..., 2, 1]
    cands = np.stack(
        [
            np.stack([dk, a, b, c], -1),
            np.stack([a, dk, d, e], -1),
            np.stack([b, d, dk, f], -1),
            np.stack([c, e, f, dk], -1),
        ],
        axis=-2,
    )  # row k equals 4 q_k q: all four products with the largest component
    q = np.take_along_axis(cands, k[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


# ----------------------------------------------------------------------------------------------
# Dispatch
# ----------------------------------------------------------------------------------------------

_READERS = {
    "tum": read_tum,
    "euroc": read_euroc,
    "csv": read_csv,
    "corbillon": read_corbillon,
    "hachaj": read_hachaj,
}


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def detect_format(path: PathLike) -> str:
    """Guess a file's format from its first lines (at least 20 non-blank ones and the first
    that is not a ``#`` comment, however long the comment header) and ``.json`` extension.

    Returns one of ``"tum"``, ``"euroc"``, ``"csv"``, ``"corbillon"``, ``"hachaj"``, ``"cwi"``,
    ``"avtrack360"``; raises :class:`TrajectoryFormatError` for an empty, comments-only or
    non-text file or when nothing matches.
    """
    head: list[str] = []  # the first 20 non-blank lines, and on to the first non-# one
    data = False  # whether head holds a line that is not a # comment
    try:
        with open(path, encoding="utf-8-sig") as f:
            for line in f:
                s = line.strip()
                if s:
                    head.append(s)
                    data = data or not s.startswith("#")
                if len(head) >= 20 and data:
                    break
    except UnicodeDecodeError as e:
        raise _err(path, None, f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    if not head:
        raise _err(path, None, "empty file, cannot detect its format")
    if not data:  # comments only: no format would read a row from it
        raise _err(path, None, "no data lines (only # comments)")
    first = head[0]
    if Path(path).suffix.lower() == ".json" or first.startswith(("{", "[")):
        return "avtrack360"
    if first.startswith(("q;", "v;")):
        return "hachaj"
    if first.lower().split() == _CORBILLON_HEADER:
        return "corbillon"
    toks = _split_csv(first)
    if "HMDRX" in toks and "Participant" in toks:
        return "cwi"
    numbered = _data_lines(head)
    if numbered and _excel_separator(numbered[0][1]):  # Excel's "sep=;" line: a CSV
        return "csv"
    if numbered:
        if _csv_header_line(head, numbered):  # a header (or a # one) naming the columns
            return "csv"
        s = numbered[0][1]
        toks = _split_csv(s) if "," in s else s.split()
        numeric = all(map(_is_number, toks))
        if "," in s and numeric and len(toks) in (8, _EUROC_STATE_COLUMNS) and toks[0].lstrip(
                "+-").isdigit():
            return "euroc"
        if "," not in s and numeric and len(toks) == 8:
            return "tum"
        if "," in s and numeric and len(toks) >= 4:
            raise _err(path, None, "comma-separated numbers without a header: name the "
                                   "columns in a first line (t,x,y,z,qw,qx,qy,qz in any "
                                   "order; lines starting with # are comments), or separate "
                                   "them by spaces for TUM's t tx ty tz qx qy qz qw")
    raise _err(
        path, None,
        f"cannot detect the trajectory format from its first lines; "
        f"pass format= one of {sorted(_READERS)}",
    )


def read_trajectory(path: PathLike, format: str = "auto", name: str | None = None) -> Trajectory:
    """Read one trajectory from a file, detecting the format when ``format="auto"``.

    Arguments:
        path: the file.
        format: ``"auto"`` or one of ``"tum"``, ``"euroc"``, ``"csv"``, ``"corbillon"``,
            ``"hachaj"``, ``"cwi"``, ``"avtrack360"``.
        name: for the files that hold several trajectories, the one to read: a CWI
            navigation CSV's participant (``"P01_V1"``), an AVTrack360 JSON's video
            (``"6.mp4"``); required there (the error lists the names), not allowed elsewhere.
            :func:`read_cwi` / :func:`read_avtrack360` read them all.

    Returns:
        The :class:`Trajectory` (warnings about the file's other trajectories are not shown).
    """
    fmt = detect_format(path) if format == "auto" else format
    if fmt in ("cwi", "avtrack360"):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            several = read_cwi(path) if fmt == "cwi" else read_avtrack360(path)
        if name not in several:
            names = list(several)
            shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8
                                            else "")
            what = (f"no trajectory named {name!r}" if name is not None
                    else f"{'an' if fmt == 'avtrack360' else 'a'} {fmt} file holding "
                         f"{len(names)} trajectories")
            raise _err(path, None, f"{what}; pass name= one of: {shown}")
        for w in seen:  # the selected trajectory's warnings only
            if f"[{name}]" in str(w.message):
                warnings.warn(w.message, w.category, stacklevel=_caller_level())
        return several[name]
    if name is not None:
        raise _err(path, None, f"name= selects one of several trajectories (CWI, AVTrack360 "
                   f"files); this is a {fmt} file holding one")
    if fmt not in _READERS:
        raise ValueError(
            f"{os.fspath(path)}: unknown format {format!r}; expected 'auto' or one of "
            f"{sorted(_READERS)}"
        )
    return _READERS[fmt](path)



def read_trajectory_spec(spec: PathLike, format: str = "auto",
                         syntax: str = "FILE#NAME") -> Trajectory:
    """:func:`read_trajectory` of a command line's ``FILE`` or ``FILE#NAME``
    (:func:`split_trajectory_name`), its errors spelling the choice of a trajectory as
    ``syntax`` (``FILE#NAME``, ``poses:FILE#NAME``) instead of the keyword ``name=``."""
    path, name = split_trajectory_name(spec)
    try:
        return read_trajectory(path, format, name)
    except TrajectoryFormatError as e:
        text = str(e).replace("pass name= one of:", f"name one as {syntax}, NAME one of:")
        text = text.replace("name= selects", f"{syntax} selects")
        if text == str(e):
            raise
        raise TrajectoryFormatError(text, path=e.path, line=e.line) from None

# ----------------------------------------------------------------------------------------------
# Writers
# ----------------------------------------------------------------------------------------------


def _writable(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t, p, q = traj
    return _validate_arrays(t, p, q)


def _format_rows(cols: list[np.ndarray], sep: str) -> str:
    table = np.column_stack(cols).tolist()  # Python floats -> shortest round-trip repr
    return "".join(sep.join(map(repr, row)) + "\n" for row in table)


def _write_text(path: PathLike, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)


def write_tum(path: PathLike, traj: Trajectory) -> None:
    """Write ``t tx ty tz qx qy qz qw`` lines (TUM RGB-D format, scalar-last) with a ``#`` header.

    NaN positions and quaternions (lost frames) are written as ``nan``. Floats use the shortest
    exact ``repr``.
    """
    t, p, q = _writable(traj)
    text = "# timestamp tx ty tz qx qy qz qw\n" + _format_rows([t, p, q[:, 1:], q[:, :1]], " ")
    _write_text(path, text)


def write_euroc(path: PathLike, traj: Trajectory) -> None:
    """Write a EuRoC / TUM-VI CSV (integer nanoseconds, metres, scalar-first quaternion).

    Times are rounded to the nearest nanosecond (whole seconds and fraction handled separately
    so epoch times keep their precision); |t| must be below ~9.2e9 s (int64 nanoseconds). Lost
    frames (NaN) are written as ``nan``.
    """
    t, p, q = _writable(traj)
    if np.any(np.abs(t) >= 9.2e9):
        raise ValueError("EuRoC times must satisfy |t| < 9.2e9 s (int64 nanoseconds)")
    sec = np.floor(t)
    frac_ns = np.rint((t - sec) * 1e9).astype(np.int64)
    ns = sec.astype(np.int64) * 10**9 + frac_ns
    header = (
        "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],"
        "q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
    )
    body = np.column_stack([p, q]).tolist()
    lines = [f"{n}," + ",".join(map(repr, row)) + "\n" for n, row in zip(ns.tolist(), body)]
    _write_text(path, header + "".join(lines))


def write_csv(path: PathLike, traj: Trajectory) -> None:
    """Write phjax's plain CSV with header ``t,x,y,z,qw,qx,qy,qz`` (s, m, ``wxyz``; lost frames
    as ``nan``)."""
    t, p, q = _writable(traj)
    _write_text(path, ",".join(_CSV_NAMES) + "\n" + _format_rows([t, p, q], ","))


_WRITERS = {"tum": write_tum, "euroc": write_euroc, "csv": write_csv}


def write_trajectory(path: PathLike, traj: Trajectory, format: str = "auto") -> None:
    """Write ``traj`` choosing the format from ``format`` or the extension.

    Arguments:
        path: ``.txt`` / ``.tum`` -> TUM; ``.csv`` -> plain CSV (``format="euroc"`` for EuRoC).
        traj: the :class:`Trajectory`.
        format: ``"auto"``, ``"tum"``, ``"euroc"`` or ``"csv"``.
    """
    writer = _WRITERS[_writer_format(path, format)]
    try:
        writer(path, traj)
    except OSError as e:  # a full disk says "No space left on device" without the file
        if e.filename is None and e.errno is not None:
            raise OSError(e.errno, e.strerror, os.fspath(path)) from e
        raise


def _writer_format(path: PathLike, format: str = "auto") -> str:
    """The writer :func:`write_trajectory` uses for ``path`` and ``format`` (``ValueError`` when
    there is none; the CLI checks this before computing)."""
    fmt = format
    if fmt == "auto":
        ext = Path(path).suffix.lower()
        fmt = {".txt": "tum", ".tum": "tum", ".csv": "csv"}.get(ext)
        if fmt is None:
            raise ValueError(
                f"{os.fspath(path)}: cannot choose a format from the extension {ext!r}; "
                "pass format='tum', 'euroc' or 'csv'"
            )
    if fmt not in _WRITERS:
        raise ValueError(f"unknown format {format!r}; expected 'auto' or one of {sorted(_WRITERS)}")
    return fmt
