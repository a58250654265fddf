"""The accuracy / smoothness / lag frontier measured at the display time (issue 30).

    python experiments/display_frontier.py [--lookaheads 0 20 50] [--seconds 15] [--quick]
                                           [--out results/display_frontier] [--render-phase 0.5]
                                           [--draws 3] [--draw K] [--noise-seed shared]
                                           [--tune-one-euro-dcutoff] [--tune-alpha-beta-beta]
                                           [--all-rooms]
                                           [--data DIR | --recordings FILE [FILE ...]]

A headset or game shows a frame some 20-50 ms after the pose is read; every method here predicts
the pose for the *display time* ``tau + L`` (``L`` = the lookahead) from the measurements up to
the render time ``tau``, and is scored against the ground truth at ``tau + L``.

Protocol: that of ``experiments/frontier.py`` (its docstring), at each lookahead separately.

* **Data.** The development set (``experiments/devset.py``): the first ``--seconds`` (15) of each
  development recording (those shorter are skipped), default sensor model (30 Hz, 5 mm, 1 deg,
  5 % dropouts; each recording its own seed, from its name: ``devset.sensor_seed``;
  ``--noise-seed shared`` gives every recording the same one, the protocol of the tables before
  2026-12-01, under which train and test share one noise and dropout sequence), 120 Hz render clock
  aligned with the camera clock (render samples at a
  frame's instant see that frame; ``--render-phase f`` offsets the render clock by ``f`` render
  periods, ``0.5`` being halfway between, as independent clocks are on average); the first
  second is warm-up and not scored. ``--data DIR``
  reads a folder laid out like ``../shared/data``; ``--recordings`` reads any trajectory files
  (:func:`phjax.io.read_trajectory`, format detected), so the same checks run on recordings we
  do not have. ``--quick``: every third development recording.
* **Split.** Recordings sorted by name, alternately *train* (even index) and *test* (odd).
  Every knob is chosen on train; results on test, on all and on the TUM VI rooms of the test
  split (``--all-rooms``: every room, train ones included, as in the tables before 2026-12-01).
* **Methods**, each predicting to the same display time ``tau + L``
  (``lookahead`` of :mod:`phjax.tracking.baselines`): Kalman CV extrapolation (knob: process
  noise scale), alpha-beta extrapolation (alpha), One Euro + extrapolation (``(min_cutoff,
  beta)``; constant-velocity extrapolation of the One Euro output by its own filtered
  derivative), the IMM extrapolation (phjax's own filter without the stream; model-set grid:
  centre, spread, switch rate), and the phjax stream with ``TrackerConfig.lookahead = L``. The
  raw hold (the latest measurement, no prediction) is the reference that normalises RMSE.
* **Tuning** at each lookahead, on train only: each baseline's knob, position and orientation
  separately, is the grid value with the lowest mean over train recordings of RMSE / raw-hold
  RMSE. The phjax stream uses the Kalman CV noise and the IMM model set tuned at the same
  lookahead (the IMM's per channel, as in ``frontier.py``); its horizon is the one with the
  lowest train RMSE (mean of position and rotation, relative to hold) among the horizons whose
  mean train RMS jerk is at most one third of the tuned Kalman CV extrapolation's (same
  lookahead) for both position and orientation. The stream with a horizon per channel
  (``TrackerConfig.rotation_horizon``) takes each channel's horizon by the same rule on that
  channel alone, as the baselines' knobs are chosen; it is run with both horizons and checked
  to equal the one-horizon sweep read channel by channel.
* **Metrics** per recording: RMSE against the truth at ``tau + L`` (mm, deg), RMS jerk of the
  rendered stream, and lag = the shift ``d`` minimising the RMSE between the stream at ``tau``
  and the truth at ``tau + L - d`` (positive: behind the display time). Ratios: per recording,
  median over the recordings of the split.
* **Sensor draws.** The whole protocol, tuning included, runs for ``--draws`` (3) draws of the
  simulated noise and dropouts (seeds + ``--draw``, ``--draw + 1``, ...); the target table
  gives each ratio per draw, its mean and a 95 % Student t interval over the draws (the
  sensor's randomness on these recordings; the choice of recordings is not in it). A
  difference between two variants smaller than that spread is not a finding.
* **Target** (issue 30): at 20 and 50 ms, phjax RMSE <= 1.00 x the strongest *external* baseline
  (Kalman CV, alpha-beta, One Euro + extrapolation: per metric the one with the largest ratio)
  at jerk <= 1/3 of the tuned Kalman CV's; the IMM extrapolation's ratio (phjax's own filter) is
  stated beside it. Nothing is tuned to the target.

Outputs in ``--out``: ``display_frontier.md`` (the target table over draws), and per draw in
``draw_K/``: ``display_frontier.md`` (every table), ``display_frontier.csv`` (every run),
``display_frontier.png`` (RMSE vs jerk per lookahead, test split), ``tuned.json``; the first
draw's csv, figure and tuned knobs are copied to ``--out`` too. With one draw (``--draws 1``,
``--smoke``) its files are written to ``--out`` directly. ``draw_K/`` folders of an earlier
run that are not this run's draws are removed.
"""

from __future__ import annotations

import argparse
import dataclasses
import csv
import json
import math
import pickle
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import frontier as F  # noqa: E402
from devset import (  # noqa: E402
    add_sensor_arguments,
    load_devset,
    sensor_note,
    simulate_recordings,
)

from phjax.io import TrajectoryWarning  # noqa: E402
from phjax.motion.resample import (  # noqa: E402
    interpolate_poses,
    snap_to_frames,
    warn_sparse_ground_truth,
)
from phjax.tracking import baselines  # noqa: E402
from phjax.tracking.imm import IMMConfig  # noqa: E402
from phjax.tracking.kalman import KalmanConfig  # noqa: E402
from phjax.tracking.tracker import TrackerConfig, track  # noqa: E402

RATE, RENDER, WARMUP, LAGS = F.RATE, F.RENDER, F.WARMUP, F.LAGS
#: horizons of the phjax stream (s): the frontier's grid, extended towards heavy smoothing
HORIZONS = F.HORIZONS + [0.1, 0.125]
#: the external baselines (the IMM extrapolation is phjax's own filter)
EXTERNAL = ("kalman-cv extrapolation", "alpha-beta extrapolation", "desp extrapolation",
            "one-euro + extrapolation")
IMM = "imm extrapolation"
STREAM = "phjax stream"
#: the stream as shipped (default TrackerConfig: default IMM, horizon 28 ms) with the lookahead
DEFAULT = "phjax stream, default config"
#: the stream with a horizon per channel (``TrackerConfig.rotation_horizon``), each chosen by
#: the jerk rule on its own channel from the same sweep (the channels are independent with
#: ``adapt`` 0), then run with both horizons set and checked against the sweep's reading
PER_CHANNEL = "phjax stream, horizon per channel"
#: the summary key of the target rows read with means over recordings (see ``report``)
MEAN = "phjax stream, means over recordings"
#: the per-channel stream's channels may differ from the sweep's reading by round-off only
#: (relative; the maths is the same, the two horizons' instants are sums taken in another
#: order)
PER_CHANNEL_TOL = 1e-6


# --------------------------------------------------------------------------------------- data
def load_recordings(seconds: float, data: Path | None = None,
                    files: list[str] | None = None) -> list[tuple]:
    """``(name, kind, t, p, q)`` ground-truth windows: the first ``seconds`` of each recording,
    from ``files`` (any :func:`phjax.io.read_trajectory` format; kind ``"file"``), else the
    development set under ``data`` (default ``../shared/data``)."""
    if files:
        from phjax.io import read_trajectory_spec, split_trajectory_name

        out, seen = [], {}
        for f in files:
            tr = read_trajectory_spec(f)  # FILE or FILE#NAME, as on phjax's command line
            path, name = split_trajectory_name(f)
            key = (Path(path).resolve(), name)
            if key in seen:  # the same data on both sides of the split would score tuning
                raise ValueError(f"{f}: given twice (also as {seen[key]})")
            seen[key] = f
            sel = tr.times < tr.times[0] + seconds
            out.append((Path(path).stem + (f"#{name}" if name else ""), "file",
                        tr.times[sel], tr.positions[sel], tr.quaternions[sel]))
        # two files of one stem (a.txt, a.csv, or one name in two folders): the names given
        stems = [o[0] for o in out]
        return [(o[0] if stems.count(o[0]) == 1 else str(f),) + o[1:]
                for o, f in zip(out, files)]
    return [s[:5] for s in load_devset(max_seconds=seconds, root=data)]


def simulate(seqs, seconds: float, quick: bool = False, seeding: str = "per-recording",
             draw: int = 0) -> list[dict]:
    """The default sensor on each window at :data:`RATE` (``devset.simulate_recordings``: a
    seed per recording from its name plus ``draw``, or ``draw`` for all with ``shared``)."""
    return simulate_recordings(seqs, seconds, RATE, quick, seeding, draw)


def prepare(recs: list[dict], seconds: float, lookaheads: list[float],
            phase: float = 0.0) -> list[dict]:
    """Render times (cut to one common length, offset by ``phase`` render periods from the
    camera clock) and, per lookahead ``L``, the ground truth at ``tau + L`` and at
    ``tau + L - d`` for every candidate lag ``d`` (:data:`LAGS`)."""
    m = int((seconds - 1.0 - WARMUP - 0.2) * RENDER)
    out = []
    for rec in recs:
        t, p, q, mt = rec["t"], rec["p"], rec["q"], rec["mt"]
        r = snap_to_frames(mt, mt[0] + WARMUP + (np.arange(m) + phase) / RENDER)
        truth = {}
        for L in lookaheads:
            gp, gq = (np.asarray(x) for x in interpolate_poses(t, p, q, r + L, max_gap=0.1))
            sp, sq = (np.asarray(x) for x in interpolate_poses(
                t, p, q, (r[None, :] + L - LAGS[:, None]).ravel(), max_gap=0.1))
            truth[L] = dict(gp=gp, gq=gq, sp=sp.reshape(len(LAGS), m, 3),
                            sq=sq.reshape(len(LAGS), m, 4))
        with warnings.catch_warnings(record=True) as caught:  # said per recording, once
            warnings.simplefilter("always", TrajectoryWarning)
            first = truth[lookaheads[0]]
            warn_sparse_ground_truth(t, r, first["gp"], first["gq"])
        for w in caught:
            print(f"warning: {rec['name']}: {w.message}", flush=True)
        out.append(dict(name=rec["name"], kind=rec["kind"], mt=mt, mp=rec["mp"], mq=rec["mq"],
                        r=r, has_pos=rec["has_pos"], truth=truth))
    out.sort(key=lambda d: d["name"])
    return out


def run(data, fn, L):
    """Score ``fn(t, p, q, r)`` on every recording against the truth at the display time."""
    return [F.score(dict(d, **d["truth"][L]), *fn(d["mt"], d["mp"], d["mq"], d["r"]))
            for d in data]


# ------------------------------------------------------------------------------------ methods
def _thin(grid, small: bool):
    """Every third value of ``grid`` when ``small`` (smoke runs)."""
    return grid[::3] if small else grid


#: One Euro's derivative cutoffs (Hz) swept with ``--tune-one-euro-dcutoff`` (else 1 Hz, the
#: library default: the cutoff of the velocity the extrapolation uses)
D_CUTOFFS = (0.3, 1.0, 2.0, 3.0, 5.0)
#: alpha-beta's gains swept
ALPHAS = [0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.65, 0.8]
#: alpha-beta's velocity gains swept with ``--tune-alpha-beta-beta``, as multiples of the
#: Benedict-Bordner ``beta = alpha^2 / (2 - alpha)`` (else 1: that beta; every one of them is
#: inside the filter's stability region ``beta < 4 - 2 alpha`` for the alphas swept)
AB_BETAS = (0.25, 0.5, 1.0, 2.0, 4.0)


def _alpha_beta(L: float):
    """knob -> fn(t, p, q, r) of alpha-beta extrapolation to ``L`` ahead: the knob is ``alpha``
    (Benedict-Bordner beta) or ``(alpha, beta / Benedict-Bordner beta)``."""
    def make(k):
        a, f = (k, None) if np.ndim(k) == 0 else k
        beta = None if f is None else f * a * a / (2 - a)
        return lambda t, p, q, r: baselines.alpha_beta(t, p, q, r, alpha=a, beta=beta,
                                                       lookahead=L)
    return make


def baseline_methods(L: float, small: bool = False, dcutoff: bool = False,
                     ab_beta: bool = False) -> dict:
    """name -> (knob grid, knob -> fn(t, p, q, r)), every method predicting ``L`` ahead (the
    grids of ``frontier.py``; ``small``: every third value, for smoke runs; ``dcutoff``: One
    Euro's knob is ``(min_cutoff, beta, d_cutoff)`` over :data:`D_CUTOFFS` too; ``ab_beta``:
    alpha-beta's knob is ``(alpha, beta factor)`` over :data:`AB_BETAS` too)."""
    def kalman(s):
        cfg = KalmanConfig(pos_process_noise=0.03 * s, rot_process_noise=0.3 * s)
        return lambda t, p, q, r: baselines.kalman_extrapolation(t, p, q, r, config=cfg,
                                                                 lookahead=L)

    def imm(k):
        cfg = F._imm_config(0.03 * k[0], 0.3 * k[0], k[1], k[2])
        return lambda t, p, q, r: baselines.imm_extrapolation(t, p, q, r, config=cfg,
                                                              lookahead=L)

    return {
        "kalman-cv extrapolation": (_thin(F.SCALES, small), kalman),
        "alpha-beta extrapolation": (
            _thin([(a, f) for a in ALPHAS for f in AB_BETAS] if ab_beta else ALPHAS, small),
            _alpha_beta(L)),
        "desp extrapolation": (
            _thin(F.DESP_AS, small),
            lambda a: (lambda t, p, q, r: baselines.double_exponential(t, p, q, r, alpha=a,
                                                                       lookahead=L))),
        "one-euro + extrapolation": (
            _thin([(m, b, d) for m, b in F.ONE_EURO for d in D_CUTOFFS] if dcutoff
                  else F.ONE_EURO, small),
            lambda k: (lambda t, p, q, r: baselines.one_euro_extrapolation(
                t, p, q, r, min_cutoff=k[0], beta=k[1], d_cutoff=k[2] if len(k) > 2 else 1.0,
                lookahead=L))),
        IMM: (_thin(F.IMM_GRID, small), imm),
    }


def tuned_imm(kp, kr) -> IMMConfig:
    """The IMM with the position models of the position-tuned grid point and the rotation
    models of the rotation-tuned one (switch rate: their geometric mean), as ``frontier.py``."""
    (sp, spp, rp), (sr, spr, rr) = kp, kr
    return IMMConfig(position_models=F._imm_config(0.03 * sp, 1.0, spp, 1.0).position_models,
                     rotation_models=F._imm_config(1.0, 0.3 * sr, spr, 1.0).rotation_models,
                     log_switch_rate=math.log(math.sqrt(rp * rr)))


def measure(data, L: float, train: list[int], log=print, small: bool = False,
            options: dict | None = None, dcutoff: bool = False, ab_beta: bool = False) -> dict:
    """Every method's sweep at lookahead ``L``, its tuned knob and the stream's operating
    point (``small``: thinned grids, for smoke runs; ``options``: ``TrackerConfig`` fields of
    the swept stream, e.g. ``{"reacquire": True}``; the shipped default's row keeps none).
    Returns ``dict(runs={(method, knob): rows}, tuned={method: (pos knob, rot knob)},
    hold=rows, stream_config=TrackerConfig)``; the per-channel stream's horizons are
    ``tuned[PER_CHANNEL]``."""
    options = options or {}
    t0 = time.time()
    hold = run(data, baselines.hold, L)
    runs, tuned = {}, {}
    for name, (grid, make) in baseline_methods(L, small, dcutoff, ab_beta).items():
        for k in grid:
            runs[(name, k)] = run(data, make(k), L)
        tuned[name] = tuple(
            min(grid, key=lambda k: F._nan_inf(F.rel_mean(runs[(name, k)], hold, key, train)))
            for key in ("pos", "rot"))
        log(f"L = {1e3 * L:g} ms: {name} tuned {tuned[name]} ({time.time() - t0:.0f} s)")
    kf = tuned["kalman-cv extrapolation"]
    kf_cfg = KalmanConfig(pos_process_noise=0.03 * kf[0], rot_process_noise=0.3 * kf[1])
    kf_p, kf_r = runs[("kalman-cv extrapolation", kf[0])], runs[("kalman-cv extrapolation", kf[1])]
    base = TrackerConfig(kalman=kf_cfg, imm=tuned_imm(*tuned[IMM]), lookahead=L, **options)
    horizons = _thin(HORIZONS, small)
    for h in horizons:
        cfg = dataclasses.replace(base, horizon=h)  # every other field kept
        runs[(STREAM, h)] = run(data, lambda t, p, q, r, c=cfg: track(t, p, q, r, config=c), L)
    h = F.horizon_rule(lambda h: runs[(STREAM, h)], horizons, kf_p, kf_r, hold, train, log)
    tuned[STREAM] = (h, h)
    res = dict(runs=runs, tuned=tuned, hold=hold)
    add_per_channel(res, train)
    hp, hr = tuned[PER_CHANNEL]
    own = dataclasses.replace(base, horizon=hp, rotation_horizon=hr)
    check_per_channel(run(data, lambda t, p, q, r: track(t, p, q, r, config=own), L),
                      runs[(STREAM, hp)], runs[(STREAM, hr)])
    log(f"L = {1e3 * L:g} ms: per channel {hp} / {hr} (TrackerConfig.rotation_horizon run, "
        "equal to the sweep's reading)")
    d = TrackerConfig(lookahead=L)
    runs[(DEFAULT, d.horizon)] = run(data, lambda t, p, q, r: track(t, p, q, r, config=d), L)
    tuned[DEFAULT] = (d.horizon, d.horizon)
    log(f"L = {1e3 * L:g} ms: phjax stream horizon {h} ({time.time() - t0:.0f} s)")
    return dict(runs=runs, tuned=tuned, hold=hold,
                stream_config=dataclasses.replace(base, horizon=h))


# ---------------------------------------------------------------------------------- analysis
def add_per_channel(res, train: list[int]) -> None:
    """Add :data:`PER_CHANNEL` to ``res``: the stream's sweep with the position horizon chosen
    by the jerk rule on position alone (``frontier.horizon_rule`` on that channel) and the
    rotation horizon likewise, as every baseline's knob is chosen per channel; a channel no
    train recording measures keeps the one-horizon rule's choice."""
    kf = res["tuned"]["kalman-cv extrapolation"]
    kf_p, kf_r = (res["runs"][("kalman-cv extrapolation", k)] for k in kf)
    hs = sorted(h for (m, h) in res["runs"] if m == STREAM)
    picks = []
    for ch, ref, jkey in (("pos", kf_p, "jp"), ("rot", kf_r, "jr")):
        if math.isnan(F.rel_mean(res["runs"][(STREAM, hs[0])], ref, jkey, train)):
            picks.append(res["tuned"][STREAM][0])  # not measured on train: at no horizon
            continue
        picks.append(F.horizon_rule(lambda h: res["runs"][(STREAM, h)], hs, kf_p, kf_r,
                                    res["hold"], train, log=lambda _: None, channels=(ch,)))
    for h in hs:
        res["runs"][(PER_CHANNEL, h)] = res["runs"][(STREAM, h)]
    res["tuned"][PER_CHANNEL] = tuple(picks)


def check_per_channel(own, pos_rows, rot_rows) -> None:
    """``RuntimeError`` unless the stream run with two horizons (rows ``own``) has the
    position scores of the one-horizon stream at the position horizon (``pos_rows``) and the
    rotation scores of the one at the rotation horizon (``rot_rows``), recording by recording,
    to :data:`PER_CHANNEL_TOL`: the per-channel rows of the report are read off the sweep."""
    for a, p, r in zip(own, pos_rows, rot_rows, strict=True):
        for keys, ref in ((("pos", "jp"), p), (("rot", "jr"), r)):  # RMSE and jerk
            for k in keys:
                x, y = a[k], ref[k]
                if not (x == y or (math.isnan(x) and math.isnan(y))
                        or abs(x - y) <= PER_CHANNEL_TOL * max(abs(y), 1e-9)):
                    raise RuntimeError(f"per-channel stream: {k} = {x!r}, the sweep's {y!r}")


def rows_of(res, name, ch):
    """Per-recording rows of ``name`` at its knob tuned for channel ``ch`` ("p" / "r")."""
    return res["runs"][(name, res["tuned"][name][0 if ch == "p" else 1])]


#: the statistics over recordings of the reports: ``name -> (ratio, difference)``; the target
#: is read on the median (robust to one recording), the mean is the statistic of the tuning and
#: the jerk rule (``frontier.rel_mean``) and is reported beside it
STATISTICS = {"median": (F.med_ratio, F.med_diff), "mean": (F.mean_ratio, F.mean_diff)}


def strongest(res, name, key, idx, among=EXTERNAL, stat: str = "median"):
    """``(ratio, baseline)``: the largest per-recording ratio ``name`` / baseline of ``key``
    over ``idx`` (median, or ``stat`` of :data:`STATISTICS`) among the tuned baselines
    ``among`` (NaN, "-" when none is finite)."""
    ch = "p" if key == "pos" else "r"
    ratio = STATISTICS[stat][0]
    rs = {b: ratio(rows_of(res, name, ch), rows_of(res, b, ch), key, idx) for b in among}
    rs = {b: v for b, v in rs.items() if np.isfinite(v)}
    if not rs:
        return math.nan, "-"
    b = max(rs, key=rs.get)
    return rs[b], b


def target_rows(res, idx, stream=STREAM, stat: str = "median") -> dict:
    """The target's numbers on ``idx``: ``stream`` and the IMM extrapolation against the
    strongest external baseline (position, rotation), the stream's jerk relative to the tuned
    Kalman CV and its lag minus the Kalman CV's (ms); each the median over the recordings of
    the per-recording ratio or difference (or ``stat`` of :data:`STATISTICS`)."""
    kf = "kalman-cv extrapolation"
    ratio, diff = STATISTICS[stat]
    out = {}
    for key in ("pos", "rot"):
        out[f"phjax_{key}"] = strongest(res, stream, key, idx, stat=stat)
        out[f"imm_{key}"] = strongest(res, IMM, key, idx, stat=stat)
    for key, ch in (("jp", "p"), ("jr", "r")):
        out[key] = ratio(rows_of(res, stream, ch), rows_of(res, kf, ch), key, idx)
    for key, ch in (("lag_p", "p"), ("lag_r", "r")):
        out[key] = diff(rows_of(res, stream, ch), rows_of(res, kf, ch), key, idx)
    return out


def at_jerk_third(res, idx) -> dict:
    """Per channel (``"pos"``, ``"rot"``): ``(ratio, horizon)`` where the stream's horizon sweep
    crosses a median jerk of 1/3 of the tuned Kalman CV's on ``idx`` (log-linear interpolation
    between the horizons around the first crossing); ``ratio`` is the RMSE ratio against the
    strongest external baseline there. ``(nan, nan)`` if the sweep does not cross."""
    hs = sorted(k for (m, k) in res["runs"] if m == STREAM)
    rows = [target_rows(dict(res, tuned=dict(res["tuned"], **{STREAM: (h, h)})), idx)
            for h in hs]
    out = {}
    for key, jkey in (("pos", "jp"), ("rot", "jr")):
        out[key] = (math.nan, math.nan)
        for (h0, a), (h1, b) in zip(zip(hs, rows), zip(hs[1:], rows[1:])):
            j0, j1 = a[jkey], b[jkey]
            if j0 > j1 > 0 and j0 >= 1 / 3 >= j1:
                w = math.log(3 * j0) / math.log(j0 / j1)
                out[key] = (a[f"phjax_{key}"][0] + w * (b[f"phjax_{key}"][0]
                                                        - a[f"phjax_{key}"][0]),
                            math.exp(math.log(h0) + w * math.log(h1 / h0)))
                break
    return out


def equal_smoothness(res, train, idx) -> dict:
    """Each baseline at the knob with the lowest train RMSE among those whose mean train jerk
    (relative to the tuned Kalman CV) is at most the phjax stream's at its operating point, per
    channel: ``{(baseline, key): (knob, ratio phjax / it, lag difference) or (None, min jerk,
    phjax jerk)}``."""
    out = {}
    kf = "kalman-cv extrapolation"
    for b in (*EXTERNAL, IMM):
        for key, jkey, lkey, ch in (("pos", "jp", "lag_p", "p"), ("rot", "jr", "lag_r", "r")):
            ref = rows_of(res, kf, ch)
            limit = F.rel_mean(rows_of(res, STREAM, ch), ref, jkey, train)
            grid = [k for (n, k) in res["runs"] if n == b]
            jerks = {k: F.rel_mean(res["runs"][(b, k)], ref, jkey, train) for k in grid}
            ok = [k for k in grid if jerks[k] <= limit]
            if not ok:
                out[(b, key)] = (None, min(jerks.values()), limit)
                continue
            k = min(ok, key=lambda k: F._nan_inf(
                F.rel_mean(res["runs"][(b, k)], res["hold"], key, train)))
            phj = rows_of(res, STREAM, ch)
            out[(b, key)] = (k, F.med_ratio(phj, res["runs"][(b, k)], key, idx),
                             F.med_diff(phj, res["runs"][(b, k)], lkey, idx))
    return out


def report(data, results: dict, names, train, splits, seconds, wall,
           phase: float = 0.0) -> tuple[str, dict]:
    cols = [("pos", "p"), ("rot", "r"), ("jp", "p"), ("jr", "r"), ("lag_p", "p"), ("lag_r", "r")]
    order = [*EXTERNAL, IMM, STREAM, DEFAULT]
    lines = ["# Accuracy / smoothness / lag frontier at the display time", "",
             f"{len(data)} recordings x {seconds:g} s (first second warm-up), default sensor "
             "(30 Hz, 5 mm, 1 deg, 5 % dropouts), 120 Hz render "
             + ("aligned with the camera clock" if phase == 0 else
                f"offset {phase:g} render periods from the camera clock") + ". Every "
             "method shows at render time tau the pose predicted for tau + L and is scored "
             "against the truth at tau + L. Train (tuning): "
             + ", ".join(names[i] for i in train) + ". Test: "
             + ", ".join(names[i] for i in splits["test"]) + ".", "",
             "Each method at its knob tuned on train at the same lookahead (lowest RMSE; phjax: "
             "lowest RMSE among the horizons with jerk <= 1/3 of the tuned Kalman CV). Medians "
             "over recordings; RMSE in mm / deg; jerk in m/s^3 / rad/s^3; lag in ms behind the "
             "display time.", ""]
    # the target, all lookaheads in one table
    header = ["| lookahead | split | phjax pos RMSE | phjax rot RMSE | IMM extrap. pos RMSE | "
              "IMM extrap. rot RMSE | pos jerk / KF | rot jerk / KF | pos lag - KF | "
              "rot lag - KF | horizon |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += ["## Target: phjax / strongest external baseline", "",
              "Median of per-recording RMSE ratios against the external baseline (Kalman CV, "
              "alpha-beta, LaViola's DESP, One Euro + extrapolation) with the largest ratio, "
              "named; beside it the same for the IMM extrapolation (phjax's own filter, no stream). Jerk: phjax / "
              "tuned Kalman CV; lag: phjax - Kalman CV, ms. Target at 20 and 50 ms: RMSE <= "
              "1.00 at jerk <= 1/3.", "",
              *header]
    short = {"kalman-cv extrapolation": "Kalman CV", "alpha-beta extrapolation": "alpha-beta",
             "desp extrapolation": "DESP", "one-euro + extrapolation": "One Euro + extrap."}
    summary = {}

    def rc(v):  # "-": no recording of the split measures the channel
        return f"{v[0]:.3f} ({short.get(v[1], v[1])})" if np.isfinite(v[0]) else "-"

    def num(x, spec):
        return format(x, spec) if np.isfinite(x) else "-"

    def target_line(L, split, tr, horizons):  # one row of the target tables
        return (f"| {1e3 * L:g} ms | {split} | {rc(tr['phjax_pos'])} | {rc(tr['phjax_rot'])} | "
                f"{rc(tr['imm_pos'])} | {rc(tr['imm_rot'])} | {num(tr['jp'], '.3f')} | "
                f"{num(tr['jr'], '.3f')} | {num(tr['lag_p'], '+.1f')} | "
                f"{num(tr['lag_r'], '+.1f')} | "
                + " / ".join(f"{h:g}" for h in dict.fromkeys(horizons)) + " s |")

    for stream in (STREAM, DEFAULT, PER_CHANNEL):
        if stream == DEFAULT:
            lines += ["", "The stream as shipped (default `TrackerConfig`: default IMM and Kalman "
                      "noise, horizon 28 ms) with only the lookahead set, against the same tuned "
                      "baselines:", "", *header]
        if stream == PER_CHANNEL:
            lines += ["", "The stream with a horizon per channel (`TrackerConfig.rotation_horizon`),"
                      " each chosen by the jerk rule on its own channel (as the baselines' knobs "
                      "are; the channels are independent with `adapt` 0, so the rows are the "
                      "sweep's, and the run with both horizons set equals them); the horizon "
                      "column gives position / rotation:", "", *header]
        for L, res in results.items():
            if stream == PER_CHANNEL and PER_CHANNEL not in res["tuned"]:
                add_per_channel(res, train)
            for split, idx in splits.items():
                if not idx:
                    continue
                tr = target_rows(res, idx, stream)
                summary[(stream, L, split)] = tr
                lines.append(target_line(L, split, tr, res["tuned"][stream]))
    lines += ["", "### The stream's frontier where its jerk is 1/3 of the Kalman CV's", "",
              "The rule above keeps the *train* jerk within 1/3; on another split the jerk "
              "ratio at that horizon differs. This reads the stream's horizon sweep on each "
              "split at a jerk of exactly 1/3 of the tuned Kalman CV's, per channel "
              "(log-linear interpolation between the two horizons around the crossing): the "
              "RMSE ratio against the strongest external baseline there, and the horizon. A "
              "description of the curve, not a tuned setting.", "",
              "| lookahead | split | pos RMSE at pos jerk 1/3 | rot RMSE at rot jerk 1/3 |",
              "|---|---|---|---|"]
    for L, res in results.items():
        for split, idx in splits.items():
            if idx and not split.startswith("TUM VI rooms"):
                cross = at_jerk_third(res, idx)
                cells = [f"{r:.3f} (horizon {1e3 * h:.1f} ms)" if np.isfinite(r) else "-"
                         for r, h in (cross["pos"], cross["rot"])]
                summary[("jerk 1/3", L, split)] = cross
                lines.append(f"| {1e3 * L:g} ms | {split} | " + " | ".join(cells) + " |")
    lines += ["", "### The target with means instead of medians", "",
              "The tables above take the median over recordings of each per-recording ratio "
              "(robust to one recording); the tuning and the jerk rule take the mean over the "
              "train recordings. The same target rows with the mean over recordings of each "
              "ratio (jerk: ratio; lag: difference), the strongest baseline chosen on the "
              "mean. A second reading of the same runs, not a target.", "", *header]
    for L, res in results.items():
        for split, idx in splits.items():
            if idx:
                tr = target_rows(res, idx, STREAM, stat="mean")
                summary[(MEAN, L, split)] = tr
                lines.append(target_line(L, split, tr, res["tuned"][STREAM]))
    lines.append("")
    for L, res in results.items():
        lines += [f"## Lookahead {1e3 * L:g} ms", ""]
        for split, idx in splits.items():
            if not idx:
                continue
            vals = {m: [F.med(rows_of(res, m, ch), key, idx) for key, ch in cols] for m in order}
            lines += [f"### {split}", "",
                      "| method | knob (pos / rot) | pos RMSE | rot RMSE | pos jerk | rot jerk | "
                      "pos lag | rot lag |", "|---|---|---|---|---|---|---|---|"]
            for m in order:
                cells = [f"{v:+.1f}" if key.startswith("lag") else f"{v:.3g}"
                         for v, (key, _) in zip(vals[m], cols)]
                kn = res["tuned"][m]
                lines.append(f"| {m} | {kn[0]} / {kn[1]} | " + " | ".join(cells) + " |")
            lines.append("")
        eq = equal_smoothness(res, train, splits["test"] or splits["all"])
        lines += ["### At equal smoothness (test split)", "",
                  "Each baseline's knob re-chosen on train: lowest RMSE among the knob values "
                  "whose mean train jerk (relative to the tuned Kalman CV) is at most the phjax "
                  "stream's. Ratio phjax / baseline (median of per-recording ratios); lag "
                  "difference phjax - baseline, ms.", "",
                  "| baseline | pos: knob | pos RMSE ratio | pos lag diff | rot: knob | "
                  "rot RMSE ratio | rot lag diff |", "|---|---|---|---|---|---|---|"]
        for b in (*EXTERNAL, IMM):
            cells = []
            for key in ("pos", "rot"):
                k, a, c = eq[(b, key)]
                if k is None and not np.isfinite(c):  # no recording measures the channel
                    cells += ["-", "no data", ""]
                else:
                    cells += (["not reached", f"min jerk {a:.2f} (phjax {c:.2f})", ""]
                              if k is None else [str(k), f"{a:.3f}", f"{c:+.1f}"])
            lines.append(f"| {b} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [f"Wall time {wall:.0f} s.", ""]
    return "\n".join(lines), summary


def write_csv(path, data, results, train):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["lookahead_ms", "method", "knob", "recording", "kind", "split", "pos_rmse_mm",
                    "rot_rmse_deg", "pos_jerk", "rot_jerk", "pos_lag_ms", "rot_lag_ms"])
        for L, res in results.items():
            for (m, k), rows in list(res["runs"].items()) + [(("raw hold", "-"), res["hold"])]:
                if m == PER_CHANNEL:  # the swept stream's rows again
                    continue
                for i, r in enumerate(rows):
                    w.writerow([f"{1e3 * L:g}", m, k, data[i]["name"], data[i]["kind"],
                                "train" if i in train else "test", r["pos"], r["rot"], r["jp"],
                                r["jr"], r["lag_p"], r["lag_r"]])


def plot(out: Path, results: dict, idx: list[int]):
    """RMSE vs jerk at each lookahead (columns), position and rotation (rows), medians over
    ``idx``: each line sweeps one method's knob (tuple knobs: the first component, the rest at
    the position-tuned value), circles = tuned on train, the star = the phjax operating point."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # plot extra not installed
        print("matplotlib not installed: no figure")
        return
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(2, len(results), figsize=(5.2 * len(results), 8.5), squeeze=False)
    for j, (L, res) in enumerate(results.items()):
        for i, (key, jkey, unit) in enumerate((("pos", "jp", "position RMSE [mm]"),
                                              ("rot", "jr", "rotation RMSE [deg]"))):
            ax = axes[i, j]
            ys = []
            for c, m in enumerate((*EXTERNAL, IMM, STREAM)):
                t_p = res["tuned"][m][0 if key == "pos" else 1]
                knobs = [k for (n, k) in res["runs"] if n == m]
                if isinstance(t_p, tuple):
                    knobs = [k for k in knobs if k[1:] == t_p[1:]]
                pts = np.array([[F.med(res["runs"][(m, k)], jkey, idx),
                                 F.med(res["runs"][(m, k)], key, idx)] for k in knobs])
                mine = m == STREAM
                colour = "C3" if mine else f"C{c if c < 3 else c + 1}"  # red: phjax alone
                ax.plot(pts[:, 0], pts[:, 1], "o-", ms=3, lw=2.5 if mine else 1.2,
                        color=colour, label=m)
                best = [F.med(res["runs"][(m, t_p)], jkey, idx),
                        F.med(res["runs"][(m, t_p)], key, idx)]
                ax.plot(*best, "*" if mine else "o", ms=14 if mine else 9,
                        mfc=colour if mine else "none", color=colour)
                ys += [v for v in pts[:, 1] if np.isfinite(v)]
            ax.set_xscale("log")
            if ys:  # zoom on the region where the methods differ (heavily smoothed ends cut)
                ax.set_ylim(0.9 * min(ys), 1.6 * min(ys))
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel(("position" if key == "pos" else "angular") + " RMS jerk "
                          + ("[m/s^3]" if key == "pos" else "[rad/s^3]"))
            ax.set_ylabel(unit)
            ax.set_title(f"lookahead {1e3 * L:g} ms")
            ax.grid(alpha=0.3, which="both")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Display-time prediction, test split, median over recordings; each line sweeps "
                 "a knob, circles = tuned on train, star = phjax operating point (jerk <= 1/3 of "
                 "the tuned Kalman CV); lower-left is better", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "display_frontier.png", dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lookaheads", type=float, nargs="+", default=[0.0, 20.0, 50.0],
                    help="display-time lookaheads, ms")
    ap.add_argument("--seconds", type=float, default=15.0, help="window per recording, s")
    ap.add_argument("--out", default="results/display_frontier", help="output folder")
    ap.add_argument("--quick", action="store_true",
                    help="every third development recording (not with --recordings)")
    ap.add_argument("--report-only", action="store_true",
                    help="redo the tables and the figure from results.pkl in --out")
    ap.add_argument("--smoke", action="store_true",
                    help="a smoke run: --quick, 5 s, lookaheads 0 and 20 ms, "
                    "every third knob value")
    ap.add_argument("--render-phase", type=float, default=0.0,
                    help="offset of the render clock from the camera clock, in render periods "
                    "(0: aligned, render samples at a frame's instant see it; 0.5: halfway "
                    "between, as with independent clocks on average)")
    ap.add_argument("--stream-option", action="append", default=[], metavar="FIELD=VALUE",
                    help="a TrackerConfig field of the swept phjax stream (repeatable; JSON "
                    "values), e.g. reacquire=true or noise_window=60: the options measured on "
                    "the same split as the default (the 'as shipped' row keeps the defaults)")
    add_sensor_arguments(ap)
    ap.add_argument("--draws", type=int, default=None,
                    help="sensor draws (--draw, --draw + 1, ...): the whole protocol, tuning "
                    "included, is repeated for each and the target table gives every ratio's "
                    "mean and 95 %% interval over the draws (default 3; 1 with --smoke)")
    ap.add_argument("--tune-one-euro-dcutoff", action="store_true",
                    help="tune One Euro's derivative cutoff too (over 0.3-5 Hz; default: fixed "
                    "at the library's 1 Hz)")
    ap.add_argument("--tune-alpha-beta-beta", action="store_true",
                    help="tune alpha-beta's velocity gain too (0.25-4 x the Benedict-Bordner "
                    "beta; default: that beta)")
    ap.add_argument("--all-rooms", action="store_true",
                    help="the 'TUM VI rooms' rows over every room, train ones included (the "
                    "tables before 2026-12-01; default: the test split's rooms only)")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--data", type=Path, default=None,
                     help="a folder laid out like ../shared/data (default: ../shared/data)")
    src.add_argument("--recordings", nargs="+", metavar="FILE",
                     help="ground-truth trajectory files instead of the development set")
    args = ap.parse_args(argv)
    if args.smoke:
        args.quick, args.seconds, args.lookaheads = True, 5.0, [0.0, 20.0]
    if args.seconds < 3.5:
        ap.error("--seconds must be at least 3.5 (1 s warm-up, 1 s cut)")
    if any(not 0 <= L <= 200 for L in args.lookaheads):
        ap.error("--lookaheads must lie in 0-200 ms")
    if not 0 <= args.render_phase < 1:
        ap.error("--render-phase must lie in [0, 1) render periods")
    if args.draws is None:
        args.draws = 1 if args.smoke else 3
    if not 1 <= args.draws <= 20:
        ap.error("--draws must lie in 1-20")
    out = Path(args.out)
    options = {}
    for item in args.stream_option:
        field, sep, value = item.partition("=")
        if not sep or field not in {f.name for f in dataclasses.fields(TrackerConfig)}:
            ap.error(f"--stream-option {item!r}: expected FIELD=VALUE with a TrackerConfig field")
        try:
            options[field] = json.loads(value)
        except json.JSONDecodeError:
            ap.error(f"--stream-option {item!r}: VALUE must be JSON (true, 60, 0.5)")
    try:  # the configuration's own checks (noise_window=-1), before any work
        TrackerConfig(**options)
    except (TypeError, ValueError) as e:
        ap.error(f"--stream-option: {e}")
    draws = list(range(args.draw, args.draw + args.draws))
    t0 = time.time()
    if args.report_only:
        if not (out / "results.pkl").is_file():
            ap.error(f"--report-only: no saved scores in {out} (results.pkl); run without it "
                     "first, with the same --out")
        with open(out / "results.pkl", "rb") as fh:
            saved = pickle.load(fh)
        print(f"--report-only: the saved run's lookaheads, draws, --seconds and --render-phase "
              f"({out / 'results.pkl'}); other options are not used", flush=True)
        if "draws" not in saved:  # a run of one draw before 2026-12-01 (shared seeds)
            old = dict(saved.get("protocol", {}))
            old.setdefault("noise_seed", "shared")
            old.setdefault("rooms_test_only", False)  # every room, before the option existed
            saved = dict(saved, draws=[dict(draw=old.pop("seed_offset", 0), data=saved["data"],
                                            results=saved["results"], wall=saved["wall"])],
                         protocol=old)
        runs = saved["draws"]
        args.seconds, args.render_phase = saved["seconds"], saved.get("render_phase", 0.0)
        for name, value in saved.get("protocol", {}).items():  # the run's own protocol options
            if name == "rooms_test_only":  # a run before 2026-12-01
                name, value = "all_rooms", not value
            setattr(args, name, value)
    else:
        lookaheads = [L / 1e3 for L in args.lookaheads]
        if args.data is not None and not args.data.is_dir():
            ap.error(f"--data {args.data}: no such folder (a folder laid out like ../shared/data)")
        try:
            seqs = load_recordings(args.seconds, args.data, args.recordings)
        except (OSError, ValueError) as e:  # a missing or unreadable recording: one line
            from phjax.cli._common import format_user_error

            print(f"display_frontier.py: error: {format_user_error(e)}", file=sys.stderr)
            raise SystemExit(2) from None
        runs = []
        for k in draws:
            recs = simulate(seqs, args.seconds, args.quick and not args.recordings,
                            seeding=args.noise_seed, draw=k)
            if len(recs) < 2:
                where = (f" ({len(seqs)} read" + (
                    f" from --data {args.data}: its development-set folders, see "
                    "experiments/devset.py" if not args.recordings else "") + ")")
                ap.error(f"need at least 2 recordings of {args.seconds:g} s (got "
                         f"{len(recs)}{where})")
            data = prepare(recs, args.seconds, lookaheads, args.render_phase)
            if k == draws[0] and (rc := _check_channels(data)) != 0:
                return rc
            if len(draws) > 1:
                print(f"sensor draw {k} ({draws.index(k) + 1} of {len(draws)})", flush=True)
            t1 = time.time()
            results = {L: measure(data, L, _split(data, False)[0], small=args.smoke,
                                  options=options, dcutoff=args.tune_one_euro_dcutoff,
                                  ab_beta=args.tune_alpha_beta_beta)
                       for L in lookaheads}
            runs.append(dict(draw=k, data=[{key: d[key] for key in ("name", "kind")}
                                           for d in data],
                             results=results, wall=time.time() - t1))
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "results.pkl", "wb") as fh:  # the scores, for --report-only
            pickle.dump({"draws": runs, "wall": time.time() - t0, "seconds": args.seconds,
                         "render_phase": args.render_phase,
                         "protocol": {k: getattr(args, k) for k in (
                             "noise_seed", "tune_one_euro_dcutoff", "tune_alpha_beta_beta",
                             "all_rooms")}}, fh)
    protocol = [x for x, on in (
        ("sensor seed shared by every recording (--noise-seed shared)",
         args.noise_seed == "shared"),
        ("One Euro d_cutoff tuned", args.tune_one_euro_dcutoff),
        ("alpha-beta beta tuned", args.tune_alpha_beta_beta),
        ("TUM VI rooms of both splits (--all-rooms)", args.all_rooms)) if on]
    head = ""
    if options:
        head += (f"Swept stream with {', '.join(f'{k}={v!r}' for k, v in options.items())} "
                 "(--stream-option).\n\n")
    if protocol:
        head += f"Protocol options: {', '.join(protocol)}.\n\n"
    import shutil

    here = {f"draw_{r['draw']}" for r in runs} if len(runs) > 1 else set()
    for stale in out.glob("draw_*"):  # another run's draws: not this run's results
        if stale.is_dir() and stale.name[5:].isdigit() and stale.name not in here:
            shutil.rmtree(stale)
    summaries = []
    for run_ in runs:
        where = out if len(runs) == 1 else out / f"draw_{run_['draw']}"
        where.mkdir(parents=True, exist_ok=True)
        text, summary = write_draw(where, run_, args, head)
        summaries.append(summary)
        if len(runs) == 1:
            print(text)
    if len(runs) > 1:
        text = head + draws_report(runs, summaries, args.seconds, args.render_phase,
                                   saved["wall"] if args.report_only else time.time() - t0)
        (out / "display_frontier.md").write_text(text)
        print(text)
        # the figure, the per-recording scores and the tuned knobs of the first draw at the
        # top level too
        for f in ("display_frontier.png", "display_frontier.csv", "tuned.json"):
            if (out / f"draw_{runs[0]['draw']}" / f).exists():
                shutil.copyfile(out / f"draw_{runs[0]['draw']}" / f, out / f)
    return 0


def _split(data, all_rooms: bool):
    """``(train, splits)``: even indices train; the reported splits' indices (the TUM VI rooms
    of the test split, or every room with ``all_rooms``)."""
    train = [i for i in range(len(data)) if i % 2 == 0]
    splits = {"test": [i for i in range(len(data)) if i % 2 == 1],
              "all": list(range(len(data))),
              "TUM VI rooms" + ("" if all_rooms else ", test"): [
                  i for i, d in enumerate(data) if d["kind"] == "object"
                  and (i % 2 == 1 or all_rooms)]}
    return train, splits


def _check_channels(data) -> int:
    """2 (said on stderr) when a channel is measured but by no train recording; 0 otherwise."""
    names = [d["name"] for d in data]
    train, splits = _split(data, False)
    print(f"{len(data)} recordings; train {[names[i] for i in train]}", flush=True)
    for part, key in (("positions", "mp"), ("orientations", "mq")):
        has = [bool(np.isfinite(d[key]).all(-1).any()) for d in data]
        if any(has) and not any(has[i] for i in train):  # its knobs could not be tuned
            print(f"display_frontier.py: error: no train recording has {part} (train: "
                  f"{', '.join(names[i] for i in train)}; recordings are split "
                  "alternately by sorted name); add recordings with them or rename",
                  file=sys.stderr)
            return 2
        if any(has) and not any(has[i] for i in splits["test"]):
            print(f"note: no test recording has {part}: the test split's {part} columns "
                  "are '-'", flush=True)
    return 0


def write_draw(out: Path, run_: dict, args, head: str) -> tuple[str, dict]:
    """One draw's tables, csv, tuned settings and figure in ``out``; ``(text, summary)``."""
    data, results = run_["data"], run_["results"]
    names = [d["name"] for d in data]
    train, splits = _split(data, args.all_rooms)
    text, summary = report(data, results, names, train, splits, args.seconds, run_["wall"],
                           args.render_phase)
    text = head + sensor_note(args.noise_seed, run_["draw"]) + "\n\n" + text
    (out / "display_frontier.md").write_text(text)
    write_csv(out / "display_frontier.csv", data, results, train)

    def imm_json(imm):
        return {"position_q": [float(x.q) for x in imm.position_models],
                "rotation_q": [float(x.q) for x in imm.rotation_models],
                "switch_rate": math.exp(float(imm.log_switch_rate))}

    (out / "tuned.json").write_text(json.dumps(
        {f"{1e3 * L:g} ms": {m: [str(k) for k in v] for m, v in res["tuned"].items()}
         | {"imm_config": imm_json(res["stream_config"].imm)} for L, res in results.items()},
        indent=2))
    plot(out, results, splits["test"] or splits["all"])
    return text, summary


#: two-sided 95 % Student t quantiles by degrees of freedom (the interval over sensor draws)
_T95 = {1: 12.7062, 2: 4.3027, 3: 3.1824, 4: 2.7764, 5: 2.5706, 6: 2.4469, 7: 2.3646,
        8: 2.3060, 9: 2.2622, 10: 2.2281, 11: 2.2010, 12: 2.1788, 13: 2.1604, 14: 2.1448,
        15: 2.1314, 16: 2.1199, 17: 2.1098, 18: 2.1009, 19: 2.0930}


def draw_interval(values) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean over draws and its 95 % Student t interval (NaN bounds
    with one draw; the finite values only)."""
    v = np.asarray([x for x in values if np.isfinite(x)], float)
    if v.size == 0:
        return math.nan, math.nan, math.nan
    m = float(v.mean())
    if v.size < 2:
        return m, math.nan, math.nan
    half = _T95[v.size - 1] * float(v.std(ddof=1)) / math.sqrt(v.size)
    return m, m - half, m + half


def _met(ratios) -> bool:
    """The target on one draw: every measured (not NaN) ratio at most 1.00, and at least one
    measured."""
    got = [v for v in ratios if not math.isnan(v)]
    return bool(got) and all(v <= 1.0 for v in got)


def draws_report(runs, summaries, seconds, phase, wall) -> str:
    """The target table over sensor draws: per lookahead and split, each ratio's value in every
    draw, its mean and 95 % interval over the draws, and in how many draws the target holds."""
    short = {"kalman-cv extrapolation": "KF", "alpha-beta extrapolation": "ab",
             "desp extrapolation": "DE", "one-euro + extrapolation": "1e", "-": "-"}
    ks = [r["draw"] for r in runs]
    data = runs[0]["data"]
    lines = ["# Accuracy / smoothness / lag frontier at the display time, over sensor draws", "",
             f"{len(data)} recordings x {seconds:g} s, the protocol of each draw's report "
             f"(`draw_K/display_frontier.md`), repeated for sensor draws {ks} (the simulated "
             "noise and dropouts; recordings, split and grids fixed; every knob re-tuned on "
             "train in each draw). Render clock " + ("aligned with the camera clock" if phase == 0
                                                     else f"offset {phase:g} render periods")
             + ".", "",
             "Each cell: mean over draws [95 % Student t interval over draws] and the values "
             "per draw (strongest external baseline per draw: KF Kalman CV, ab alpha-beta, DE "
             "LaViola's DESP, 1e One Euro + extrapolation). RMSE columns are phjax (or the IMM extrapolation) / "
             "strongest external baseline; jerk / tuned Kalman CV; lag - Kalman CV, ms. The "
             "interval covers the sensor's randomness on these recordings, not the choice of "
             "recordings. Target at 20 and 50 ms: RMSE <= 1.00 at jerk <= 1/3; 'met' counts "
             "the draws where both RMSE ratios are <= 1.00.", "",
             "| lookahead | split | phjax pos RMSE | phjax rot RMSE | IMM extrap. pos | "
             "IMM extrap. rot | pos jerk / KF | rot jerk / KF | pos lag - KF | rot lag - KF | "
             "met |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    header = lines[-2:]
    for table in (STREAM, PER_CHANNEL, MEAN):
        if table == PER_CHANNEL:
            lines += ["", "The stream with a horizon per channel (`TrackerConfig.rotation_horizon`;"
                      " each by the jerk rule on its own channel, as the baselines' knobs are "
                      "chosen; see each draw's report):", "", *header]
        if table == MEAN:
            lines += ["", "The first table read with the mean over recordings of each "
                      "per-recording ratio instead of the median (the statistic of the tuning "
                      "and the jerk rule; a second reading, not the target; see each draw's "
                      "report):", "", *header]
        for (stream, L, split) in summaries[0]:
            if stream != table:
                continue
            rows = [s[(stream, L, split)] for s in summaries]
            cells = []
            for key, spec in (("phjax_pos", ".3f"), ("phjax_rot", ".3f"), ("imm_pos", ".3f"),
                              ("imm_rot", ".3f"), ("jp", ".3f"), ("jr", ".3f"),
                              ("lag_p", "+.1f"), ("lag_r", "+.1f")):
                vals = [r[key][0] if isinstance(r[key], tuple) else r[key] for r in rows]
                m, lo, hi = draw_interval(vals)
                if not np.isfinite(m):
                    cells.append("-")
                    continue
                per = ", ".join(
                    (format(v, spec) + (f" {short.get(r[key][1], r[key][1])}"
                                        if isinstance(r[key], tuple) else ""))
                    if np.isfinite(v) else "-" for v, r in zip(vals, rows))
                ci = f" [{lo:{spec}}, {hi:{spec}}]" if np.isfinite(lo) else ""
                cells.append(f"{m:{spec}}{ci}<br>({per})")
            met = sum(_met([r[k][0] for k in ("phjax_pos", "phjax_rot")]) for r in rows)
            lines.append(f"| {1e3 * L:g} ms | {split} | " + " | ".join(cells)
                         + f" | {met} of {len(rows)} |")
    lines += ["", f"Wall time {wall:.0f} s (all draws)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
