"""The development set: ground-truth trajectories from ../shared/data (loaders for every format).

Each entry is ``(name, kind, times, positions, quaternions)``; ``kind`` is ``"camera"`` (TUM
RGB-D), ``"object"`` (TUM VI hand-held rig) or ``"head"`` (VR head traces; orientation only
except CWI, which has positions). Long recordings are cut into windows of ``max_seconds``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from phjax import io
from phjax.datasets import shared_data_dir


def _window(name, kind, traj, max_seconds, max_windows):
    t, p, q = traj.times, traj.positions, traj.quaternions
    out = []
    start = t[0]
    k = 0
    while start < t[-1] and k < max_windows:
        sel = (t >= start) & (t < start + max_seconds)
        if sel.sum() > 50:
            out.append((f"{name}#{k}", kind, t[sel], p[sel], q[sel]))
            k += 1
        start += max_seconds
    return out


def load_devset(max_seconds: float = 30.0, max_windows: int = 1, root: Path | None = None):
    """Load the development set (raises FileNotFoundError when ../shared/data is absent).

    Names are short (``fr1_xyz#0``, ``room1#0``); where two files would share one (a folder
    laid out like ../shared/data with other recordings), those take their file's stem
    instead, so that every window has its own name (the split is by sorted name)."""
    root = shared_data_dir() if root is None else root
    if root is None:
        raise FileNotFoundError("../shared/data not found (set PHJAX_SHARED_DATA)")
    seqs, sources = [], []

    def add(name, kind, traj, source):
        windows = _window(name, kind, traj, max_seconds, max_windows)
        seqs.extend(windows)
        sources.extend([(name, source)] * len(windows))

    for f in sorted((root / "tum_rgbd_groundtruth").glob("*-groundtruth.txt")):
        add(f.name.split("-")[0], "camera", io.read_tum(f), f.stem)
    for f in sorted((root / "tum_vi_room_groundtruth").glob("*.csv")):
        add(f.stem.split("_")[0], "object", io.read_euroc(f), f.stem)
    for f in sorted((root / "vr_corbillon_multiviewpoint360").glob("user*_quaternion.txt")):
        add("corbillon-" + f.stem.split("_")[0], "head", io.read_corbillon(f), f.stem)
    seg = root / "vr_hachaj_head_gestures" / "segment_continuous.log"
    if seg.exists():
        add("hachaj-continuous", "head", io.read_hachaj(seg), seg.stem)
    cwi = sorted((root / "vr_cwi_6dof_navigation").glob("H*_nav.csv"))
    for f in cwi:
        parts = io.read_cwi(f)
        for pid in sorted(parts)[:2]:
            add(f"cwi-{f.stem.split('_')[0]}-{pid}", "head", parts[pid], f"{f.stem}-{pid}")
    files_of = {}
    for name, source in sources:
        files_of.setdefault(name, set()).add(source)
    return [((source + w[0][len(name):]) if len(files_of[name]) > 1 else w[0],) + w[1:]
            for w, (name, source) in zip(seqs, sources)]


#: the simulated sensor's seeding: ``per-recording`` (default) seeds each recording from its name,
#: so recordings draw independent noise and dropouts; ``shared`` gives every recording the same
#: seed (the protocol of the tables published before 2026-12-01: train and test then share one
#: noise and dropout sequence)
SEEDINGS = ("per-recording", "shared")


def sensor_seed(name: str, seeding: str = "per-recording", draw: int = 0) -> int:
    """The simulated sensor's seed for recording ``name`` in draw ``draw``: a CRC-32 of the name
    plus ``draw`` (``per-recording``), or ``draw`` for every recording (``shared``)."""
    import zlib

    if seeding not in SEEDINGS:
        raise ValueError(f"seeding must be one of {SEEDINGS}, got {seeding!r}")
    return (zlib.crc32(name.encode()) if seeding == "per-recording" else 0) + int(draw)


def simulate_recordings(seqs, seconds: float, rate: float = 30.0, quick: bool = False,
                        seeding: str = "per-recording", draw: int = 0) -> list[dict]:
    """Measure ground-truth windows ``(name, kind, t, p, q)`` with the default sensor model at
    ``rate`` (seed :func:`sensor_seed`), origin at each window's first sample, cut to
    ``int((seconds - 1) * rate)`` frames; windows with fewer frames are skipped (said on
    stdout); ``quick``: every third window. Returns dicts with ``name, kind, t, p, q`` (ground
    truth), ``mt, mp, mq`` (frames) and ``has_pos``, in the order given."""
    from phjax.motion.simulate import SensorModel, simulate_measurements

    seqs = seqs[::3] if quick else seqs
    n = int((seconds - 1.0) * rate)
    out = []
    for name, kind, t, p, q in seqs:
        t = np.asarray(t, np.float64) - t[0]
        mt, mp, mq = (np.asarray(x, np.float64)
                      for x in simulate_measurements(sensor_seed(name, seeding, draw), t, p, q,
                                                     SensorModel(rate=rate)))
        if mt.shape[0] < n:
            print(f"skip {name}: {t[-1]:.3g} s, {mt.shape[0]} camera frames (needs {n}: "
                  f"{seconds:g} s at {rate:g} Hz)")
            continue
        out.append(dict(name=name, kind=kind, t=t, p=np.asarray(p, np.float64),
                        q=np.asarray(q, np.float64), mt=mt[:n], mp=mp[:n], mq=mq[:n],
                        has_pos=bool(np.isfinite(p).any())))
    return out


def simulated_devset(seconds: float, quick: bool = False, rate: float = 30.0,
                     seeding: str = "per-recording", draw: int = 0):
    """The development set as the frontier studies see it: the first ``seconds`` of each
    recording through :func:`simulate_recordings` (devset order)."""
    return simulate_recordings([s[:5] for s in load_devset(max_seconds=seconds)], seconds, rate,
                               quick, seeding, draw)


def sensor_note(seeding: str, draw: int) -> str:
    """The sensor draw a report rests on, in one sentence (its header)."""
    return (f"Sensor draw {draw}: " + ("each recording its own seed (its name's CRC-32 + "
            f"{draw})" if seeding == "per-recording" else f"seed {draw} for every recording "
            "(--noise-seed shared: all share one noise and dropout sequence)") + ".")


def _draw(text: str) -> int:
    """``--draw``: a non-negative integer."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer of at least 0, got {text!r}")
    return value


def add_sensor_arguments(ap) -> None:
    """``--noise-seed`` and ``--draw``: the sensor-draw options every frontier study shares."""
    ap.add_argument("--noise-seed", choices=SEEDINGS, default="per-recording",
                    help="the simulated sensor's seeding: one seed per recording from its name "
                    "(default: independent noise and dropouts) or 'shared' (seed = draw for "
                    "every recording, the protocol of the tables before 2026-12-01)")
    ap.add_argument("--draw", type=_draw, default=0,
                    help="added to every recording's sensor seed: another draw of the noise and "
                    "dropouts under the same protocol (default 0)")


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(description="List the development set's recordings "
                            "(python experiments/devset.py).").parse_args()
    for name, kind, t, p, _q in load_devset():
        print(f"{name:40s} {kind:7s} {t[-1] - t[0]:6.1f} s  {len(t):6d} samples  "
              f"positions: {np.isfinite(p).any()}")
