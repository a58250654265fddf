"""Shared pieces of the ``phjax`` CLI: the one-line error path, argument types, input files read
through :mod:`phjax.io`, output-file checks, options shared by several commands.

User errors (bad arguments, missing / unreadable / malformed files, too little data) end in
:func:`phjax.cli.main` as ONE line on stderr, ``phjax <command>: error: <what>`` naming the file
(and the line for a malformed row), with exit status 2 and no traceback.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import warnings
from pathlib import Path

__all__ = [
    "check_lookahead",
    "overwritten_input",
    "Parser",
    "add_format_argument",
    "add_output_argument",
    "add_rate_argument",
    "add_sensor_arguments",
    "check_output",
    "check_plot_output",
    "check_trajectory_output",
    "float_between",
    "format_user_error",
    "nonnegative_float",
    "positive_float",
    "positive_int",
    "read_input",
    "replaced_note",
    "unit_interval",
]

#: input formats of :func:`phjax.io.read_trajectory` (``--format`` choices)
INPUT_FORMATS = ("auto", "tum", "euroc", "csv", "corbillon", "hachaj", "cwi", "avtrack360")
#: the largest --lookahead of the causal stream, ms: beyond it the prediction is mostly
#: guesswork (a head turns its speed around in ~0.2 s), and no display is that slow
MAX_LOOKAHEAD_MS = 200.0
#: output formats of :func:`phjax.io.write_trajectory` (``--out-format`` choices)
OUTPUT_FORMATS = ("auto", "tum", "csv", "euroc")


def check_lookahead(ms: float) -> float:
    """A ``--lookahead`` value in ms, checked against 0 .. :data:`MAX_LOOKAHEAD_MS` (a
    ``ValueError`` naming the bound otherwise); returns it in seconds."""
    if not (math.isfinite(ms) and 0.0 <= ms <= MAX_LOOKAHEAD_MS):
        raise ValueError(f"--lookahead must be between 0 and {MAX_LOOKAHEAD_MS:g} ms, got {ms:g} "
                         "(the display's motion-to-photon latency minus what the receiving "
                         "program predicts itself)")
    return ms / 1e3


#: a command-line word that is a value, never an option: '-' then a digit, or '-.' then a digit
#: (``-5``, ``-0.5,2``, ``-.5``, ``-1e3``); no phjax option starts that way
_NEGATIVE_VALUE = re.compile(r"-\.?\d")


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose usage errors are one line (exit status 2):
    ``phjax smooth: error: argument --rate: ... (see 'phjax smooth --help')``.

    A word that starts with ``-`` and a digit (``-5,1``, ``-0.5,2``, ``-.5``) is a value, as
    the option before it expects: argparse reads only a plain negative number (``-5``,
    ``-0.5``) that way and took ``--measurement-noise -5,1`` for two options ("expected one
    argument") instead of giving the option's own message. The commands' parsers are made by
    ``add_subparsers`` with this class, so every command reads values so."""

    #: the commands' parsers by name (set on the top-level parser)
    commands: dict[str, argparse.ArgumentParser] = {}

    def _parse_optional(self, arg_string):
        # argparse's private hook. From Python 3.11 to CPython's main branch (3.14, read on
        # 2026-11-30) its one caller, _parse_known_args, takes None as "a positional word"
        # (pattern 'A'); only the non-None return values changed between versions (a tuple,
        # then a list of tuples), and those come from argparse itself.
        if _NEGATIVE_VALUE.match(arg_string):
            return None  # a positional word: the value of the option before it
        return super()._parse_optional(arg_string)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _number(text: str, kind=float):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (rates, durations)."""
    x = _number(text)
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return x


#: accepted ``--fps`` (``phjax live``, ``phjax track-rgbd``): the frame rate of an RGB-D folder
#: whose frames carry no timestamps, Hz
FPS_RANGE = (0.1, 1000.0)


def float_between(low: float, high: float, unit: str = ""):
    """argparse type factory: a finite number in ``[low, high]`` (``unit`` ends the message:
    ``must be between 0.05 and 0.5 m, got 'inf'``)."""
    suffix = f" {unit}" if unit else ""

    def check(text: str) -> float:
        x = _number(text)
        if not (math.isfinite(x) and low <= x <= high):
            raise argparse.ArgumentTypeError(
                f"must be between {low:g} and {high:g}{suffix}, got {text!r}")
        return x

    check.__name__ = f"float in [{low:g}, {high:g}]"
    return check


def nonnegative_float(text: str) -> float:
    """argparse type: a finite number >= 0 (noise levels)."""
    x = _number(text)
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return x


def unit_interval(text: str) -> float:
    """argparse type: a fraction in ``[0, 1)`` (dropout)."""
    x = _number(text)
    if not 0 <= x < 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return x


def int_at_least(low: int):
    """argparse type factory: an integer ``>= low``."""
    def check(text: str) -> int:
        n = _number(text, int)
        if n < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}")
        return n

    check.__name__ = f"integer >= {low}"
    return check


#: argparse type: an integer >= 1 (counts, strides)
positive_int = int_at_least(1)
#: argparse type: an integer >= 0 (counts where 0 means off)
nonnegative_int = int_at_least(0)


def file_name(text: str) -> str:
    """argparse type: a non-empty file name."""
    if not text.strip():
        raise argparse.ArgumentTypeError("needs a file name")
    return text


#: the largest random seed (the one range of every seed: ``synthetic:N:SEED`` sources too)
MAX_SEED = 2**32 - 1


def seed_int(text: str) -> int:
    """argparse type: a random seed, an integer in ``[0, 2^32 - 1]``."""
    n = _number(text, int)
    if not 0 <= n <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an integer between 0 and 2^32 - 1, got {text!r}")
    return n


def format_user_error(err: BaseException) -> str:
    """The one-line message of a user error (``OSError``: ``FILE: reason``)."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        return f"{os.fspath(err.filename)}: {err.strerror}"
    text = str(err) or type(err).__name__
    return " ".join(text.split())  # one line, whatever the message held


def read_input(path, format: str = "auto", *, min_poses: int = 2, measurements: bool = False):
    """Read a trajectory file through :func:`phjax.io.read_trajectory` for a command.

    Files that hold several trajectories (CWI navigation CSVs: one per participant; AVTrack360
    JSONs: one per video) are named ``FILE#NAME`` (``H1_longdress_nav.csv#P01_V1``,
    ``subject10_head_rotation.json#6.mp4``); without ``#NAME`` the error lists the names.

    Arguments:
        path: the file named on the command line (``FILE`` or ``FILE#NAME``).
        format: ``"auto"`` or a :mod:`phjax.io` format name.
        min_poses: the least number of samples with a valid position or quaternion (lost
            frames do not count).
        measurements: the rows go to the filters as measurements (``smooth``, ``tune
            --measured``), which start from a whole pose: a file that measures both parts but
            never in one row is an error (a ground truth, sampled by the simulated sensor, is
            not checked).

    Returns:
        The :class:`~phjax.io.Trajectory`. A file with one part alone (no valid position, or
        no valid orientation, in any row) is read, with a
        :class:`~phjax.io.TrajectoryWarning` naming the part the results will lack.

    Raises:
        FileNotFoundError, IsADirectoryError: no such file / a folder.
        phjax.io.TrajectoryFormatError: empty, undetectable, malformed, too short, or both
            parts measured but never in one row.
    """
    import numpy as np

    from ..io import (
        TrajectoryFormatError,
        TrajectoryWarning,
        read_trajectory_spec,
        split_trajectory_name,
    )

    spec, _ = split_trajectory_name(path)
    p = Path(spec)
    if not p.exists():
        raise FileNotFoundError(2, "No such file or directory", spec)
    if p.is_dir():
        raise IsADirectoryError(21, "Is a directory (expected a trajectory file)", spec)
    try:
        traj = read_trajectory_spec(path, format)
    except TrajectoryFormatError as e:  # name the command line's option, not the keyword
        if "pass format= one of" not in str(e):
            raise
        raise TrajectoryFormatError(str(e).replace("pass format= one of", "pass --format, one of"),
                                    path=path) from None
    q_ok, p_ok = np.isfinite(traj.quaternions).all(-1), np.isfinite(traj.positions).all(-1)
    n = int(np.count_nonzero(q_ok | p_ok))
    if n < min_poses:
        lost = traj.num_samples - n
        raise TrajectoryFormatError(
            f"{os.fspath(path)}: {n} pose(s)" + (f" ({lost} lost frame(s))" if lost else "")
            + f"; at least {min_poses} are needed", path=path)
    if measurements and p_ok.any() and q_ok.any() and not (p_ok & q_ok).any():
        raise TrajectoryFormatError(
            f"{os.fspath(path)}: no row holds both a position and an orientation "
            f"({int(p_ok.sum())} position-only, {int(q_ok.sum())} orientation-only rows); the "
            "filters start from a whole pose: merge the parts into one row per time, or give "
            "one part alone", path=path)
    for part, ok, other in (("position", p_ok, "orientation"), ("orientation", q_ok, "position")):
        if not ok.any():  # one part alone is allowed, but not silently
            warnings.warn(f"{os.fspath(path)}: no row holds a valid {part} ({other} only); the "
                          f"results have no {part} (NaN in written files, '-' in tables)",
                          TrajectoryWarning, stacklevel=2)
    return traj


def check_output(path, what: str = "output", inputs=()) -> Path:
    """Fail early (before any computation) when ``path`` cannot be written: its folder is
    missing or it is a folder, or it is one of the command's ``inputs`` (files named on the
    command line, ``FILE#NAME`` included), which writing it would destroy."""
    p = Path(path)
    if p.is_dir():
        article = "an" if what[:1] in "aeiou" else "a"
        raise IsADirectoryError(21, f"Is a directory (expected {article} {what} file name)",
                                str(path))
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(2, f"No such folder for the {what} file", str(parent))
    given = overwritten_input(path, inputs)
    if given is not None:
        named = "" if os.fspath(given) == os.fspath(path) else f" {given}"
        raise ValueError(f"{path}: is the input file{named}; writing the {what} would destroy "
                         "it: name another file")
    return p


def overwritten_input(path, inputs):
    """The one of ``inputs`` (files named on the command line, ``FILE#NAME`` included, or a
    ``poses:FILE`` source) that writing ``path`` would replace, else ``None``."""
    from ..io import split_trajectory_name

    p = Path(path)
    if not p.exists():
        return None
    for given in inputs:
        source = Path(split_trajectory_name(os.fspath(given).removeprefix("poses:"))[0])
        if source.exists() and source.resolve() == p.resolve():
            return given
    return None


#: figure formats by file extension (matplotlib's savefig)
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".eps", ".ps", ".tif",
                 ".tiff", ".webp")


def check_plot_output(path) -> Path:
    """:func:`check_output` for a figure: a name without an extension gets ``.png`` (as
    matplotlib would write it, so that the messages name the real file); an extension
    matplotlib cannot write is an error before any work."""
    p = Path(path)
    if p.is_dir():  # a folder, not the name of a file to put in it
        return check_output(p, "plot")
    if not p.suffix:
        p = p.with_name(p.name + ".png")
    elif p.suffix.lower() not in PLOT_SUFFIXES:
        raise ValueError(f"{path}: cannot write a figure as {p.suffix!r}; use one of "
                         f"{', '.join(PLOT_SUFFIXES)}")
    return check_output(p, "plot")


def check_trajectory_output(path, format: str = "auto", option: str | None = None,
                            inputs=()) -> Path:
    """:func:`check_output` for a trajectory file, whose format must also follow from its
    extension (``.tum`` / ``.txt`` / ``.csv``) or from ``option`` (e.g. ``--out-format``),
    checked before any work; the error names the command line's ways, not the library's."""
    from ..io import _writer_format

    try:
        _writer_format(path, format)
    except ValueError as e:
        ways = f"pass {option} tum, euroc or csv, or " if option else ""
        raise ValueError(str(e).split("; pass format=")[0]
                         + f"; {ways}name the file .tum, .txt or .csv") from None
    return check_output(path, inputs=inputs)


#: working memory per item of the commands' arrays, bytes (generous: inputs, outputs, the
#: scan's stacked states and every method's copy in an evaluation)
BYTES_PER_RENDER_SAMPLE = {"smooth": 512, "evaluate": 4096}
BYTES_PER_CAMERA_FRAME = 16384


def _memory_bytes() -> int | None:
    """Physical memory of this machine, bytes (``None`` where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return None


def check_fits(counts: dict[str, tuple[float, int]],
               advice: str = "lower the rate or shorten the recording") -> None:
    """Fail before any work (``ValueError``: one line, exit status 2) when the arrays a command
    would make need more than half of this machine's memory, instead of running out of it.

    Arguments:
        counts: what (e.g. ``"--rate 1e+09 Hz over 30 s"``) -> (number of items, bytes each).
        advice: what to do instead (the message's end).
    """
    total = _memory_bytes()
    if total is None:
        return
    need = sum(n * b for n, b in counts.values())
    if need > total / 2:
        what = max(counts, key=lambda k: counts[k][0] * counts[k][1])
        n = counts[what][0]
        raise ValueError(f"{what} makes {n:.3g} samples: about {need / 2**30:,.4g} GiB of "
                         f"memory, more than half of this machine's {total / 2**30:.0f} GiB; "
                         + advice)


def model_not_found(err: Exception, example: str) -> FileNotFoundError:
    """The library's missing-model error (a ``ModelNotFoundError``) with the command line's own
    remedies instead of its Python ones: ``--model-dir`` (``example``: a folder holding the
    files) or ``--download-models``."""
    first = str(err).splitlines()[0].split(". Get it with")[0]
    return type(err)(f"{first}: pass --model-dir FOLDER (a folder holding the model files, "
                     f"e.g. {example}) or --download-models")


def replaced_note(path) -> str:
    """``" (replaced the existing file)"`` when ``path`` exists, else ``""``: the commands
    overwrite their outputs and say so on the line that names the written file."""
    return " (replaced the existing file)" if Path(path).is_file() else ""


# ----------------------------------------------------------------------------------------------
# options shared by several commands


def add_format_argument(parser, what: str = "input format") -> None:
    """``--format`` (a :mod:`phjax.io` input format, default ``auto``); ``what`` starts its help."""
    parser.add_argument("--format", default="auto", choices=INPUT_FORMATS,
                        help=f"{what} (default auto)")


def add_output_argument(parser, what: str) -> None:
    """Required ``-o/--output``: ``what`` starts its help, which adds that an existing file is
    replaced."""
    parser.add_argument("-o", "--output", required=True,
                        help=f"{what}; an existing file is replaced (the output says so)")


def add_rate_argument(parser, what: str = "render rate") -> None:
    """``--rate`` in Hz (default 120); ``what`` starts its help."""
    parser.add_argument("--rate", type=positive_float, default=120.0,
                        help=f"{what}, Hz (default 120)")


def add_sensor_arguments(parser, seed_help: str = "random seed (default 0)") -> None:
    """The render rate ``--rate`` and the simulated sensor's options
    (:class:`phjax.motion.simulate.SensorModel`): ``--camera-rate`` (Hz), ``--sigma-p`` (mm),
    ``--sigma-r`` (deg), ``--dropout``, ``--jitter`` and ``--seed``, on ``parser`` (a parser or
    an argument group)."""
    add_rate_argument(parser)
    parser.add_argument("--camera-rate", type=positive_float, default=30.0,
                        help="measurement rate, Hz (default 30)")
    parser.add_argument("--sigma-p", type=nonnegative_float, default=5.0,
                        help="position noise std, mm (default 5)")
    parser.add_argument("--sigma-r", type=nonnegative_float, default=1.0,
                        help="rotation noise std per axis, deg (default 1)")
    parser.add_argument("--dropout", type=unit_interval, default=0.05,
                        help="fraction of lost frames (default 0.05)")
    parser.add_argument("--jitter", type=nonnegative_float, default=0.0,
                        help="timestamp jitter, fraction of the period")
    parser.add_argument("--seed", type=seed_int, default=0, help=seed_help)
