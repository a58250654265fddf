"""Tune every method's parameters for the lowest RMSE on the development set; print the tables.

    python experiments/tune_baselines.py [--seconds 30] [--out results/tuning] [--horizon-only]

Protocol: each development sequence (``experiments/devset.py``, first ``--seconds`` of each) is
sampled by the default sensor model (30 Hz, 5 mm, 1 deg, 5 % dropouts, seed 0) and rendered at
120 Hz. Position and rotation parameters are tuned separately (the filter's position and
orientation parts are independent; One Euro is run with separate position / rotation settings).
The objective is the mean over sequences of RMSE relative to the raw-hold RMSE of the same
sequence (so that no sequence's scale dominates). Results: a Markdown report with the grids,
the chosen values and the phjax horizon trade-off (RMSE vs jerk).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from devset import load_devset  # noqa: E402

from phjax.tracking import baselines  # noqa: E402
from phjax.tracking.baselines import TUNED  # noqa: E402
from phjax.tracking.kalman import KalmanConfig  # noqa: E402
from phjax.evaluation.metrics import position_rmse, rms_jerk_position, rms_jerk_rotation, rotation_rmse_deg  # noqa: E402
from phjax.motion.resample import interpolate_poses, snap_to_frames  # noqa: E402
from phjax.motion.simulate import SensorModel, simulate_measurements  # noqa: E402
from phjax.tracking.tracker import TrackerConfig, track  # noqa: E402


def prepare(seqs, seed=0, rate=120.0):
    out = []
    for name, kind, t, p, q in seqs:
        t = t - t[0]
        mt, mp, mq = (np.asarray(x, np.float64) for x in simulate_measurements(seed, t, p, q, SensorModel()))
        ok = np.isfinite(mq).all(-1)
        # render samples at a frame's instant see that frame, whatever the rounding
        r = snap_to_frames(mt, np.arange(mt[ok][0] + 1 / 30, t[-1], 1 / rate))
        gp, gq = (np.asarray(x) for x in interpolate_poses(t, p, q, r, max_gap=0.1))
        out.append(dict(name=name, kind=kind, mt=mt, mp=mp, mq=mq, r=r, gp=gp, gq=gq,
                        has_pos=bool(np.isfinite(p).any())))
    return out


def scores(data, fn):
    rows = []
    for d in data:
        p, q = fn(d["mt"], d["mp"], d["mq"], d["r"])
        p, q = np.asarray(p), np.asarray(q)
        rows.append(dict(
            pos=position_rmse(p, d["gp"]).value if d["has_pos"] else np.nan,
            rot=rotation_rmse_deg(q, d["gq"]).value,
            jp=rms_jerk_position(d["r"], p).value if d["has_pos"] else np.nan,
            jr=rms_jerk_rotation(d["r"], q).value,
        ))
    return rows


def rel(rows, ref, key):
    v = np.array([r[key] / b[key] for r, b in zip(rows, ref)])
    return float(np.nanmean(v))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="length of each sequence used")
    ap.add_argument("--out", default="results/tuning", help="output folder")
    ap.add_argument("--horizon-only", action="store_true",
                    help="skip the baseline grids; trade-off curve of the default tracker's "
                         "horizon against the Kalman CV extrapolation with TUNED['kalman']")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = prepare(load_devset(max_seconds=args.seconds))
    ref = scores(data, baselines.hold)
    report = ["# Tuning on the development set", "",
              f"{len(data)} sequences, {args.seconds:g} s each, default sensor model, 120 Hz render.", ""]

    if args.horizon_only:
        d = TUNED["kalman"]
        return horizon_tradeoff(data, d["pos_process_noise"], d["rot_process_noise"], report, out)

    # Kalman CV: position and rotation noise densities (independent parts)
    qs_p = [0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0]
    qs_r = [0.1, 0.3, 1.0, 3.0, 10.0, 30.0]
    grid = {}
    for qp, qr in zip(qs_p + [qs_p[3]] * (len(qs_r)), [qs_r[2]] * len(qs_p) + qs_r):
        cfg = KalmanConfig(pos_process_noise=qp, rot_process_noise=qr)
        rows = scores(data, lambda t, p, q, r, cfg=cfg: baselines.kalman_extrapolation(t, p, q, r, config=cfg))
        grid[(qp, qr)] = (rel(rows, ref, "pos"), rel(rows, ref, "rot"))
        print(f"kalman qp={qp:g} qr={qr:g}: pos {grid[(qp, qr)][0]:.4f} rot {grid[(qp, qr)][1]:.4f}", flush=True)
    best_qp = min(qs_p, key=lambda v: grid[(v, qs_r[2])][0])
    best_qr = min(qs_r, key=lambda v: grid[(qs_p[3], v)][1])
    report += ["## Kalman CV extrapolation", "", "| q_pos | rel pos RMSE |", "|---|---|"]
    report += [f"| {v:g} | {grid[(v, qs_r[2])][0]:.4f} |" for v in qs_p]
    report += ["", "| q_rot | rel rot RMSE |", "|---|---|"]
    report += [f"| {v:g} | {grid[(qs_p[3], v)][1]:.4f} |" for v in qs_r]
    report += ["", f"chosen: pos_process_noise={best_qp:g}, rot_process_noise={best_qr:g}", ""]

    # One Euro: separate settings for position and rotation
    mc = [0.3, 1.0, 3.0, 10.0, 30.0]
    be = [0.0, 1.0, 10.0, 100.0]
    oe = {}
    for m, b in itertools.product(mc, be):
        rows = scores(data, lambda t, p, q, r, m=m, b=b: baselines.one_euro(t, p, q, r, min_cutoff=m, beta=b))
        oe[(m, b)] = (rel(rows, ref, "pos"), rel(rows, ref, "rot"))
        print(f"one-euro min_cutoff={m:g} beta={b:g}: pos {oe[(m, b)][0]:.4f} rot {oe[(m, b)][1]:.4f}", flush=True)
    best_oe_p = min(oe, key=lambda k: oe[k][0])
    best_oe_r = min(oe, key=lambda k: oe[k][1])
    report += ["## One Euro", "", "| min_cutoff | beta | rel pos RMSE | rel rot RMSE |", "|---|---|---|---|"]
    report += [f"| {k[0]:g} | {k[1]:g} | {v[0]:.4f} | {v[1]:.4f} |" for k, v in oe.items()]
    report += ["", f"chosen: position {best_oe_p}, rotation {best_oe_r}", ""]

    extra = dict(one_euro_position=dict(min_cutoff=best_oe_p[0], beta=best_oe_p[1]),
                 one_euro_rotation=dict(min_cutoff=best_oe_r[0], beta=best_oe_r[1]))
    return horizon_tradeoff(data, best_qp, best_qr, report, out, extra)


def horizon_tradeoff(data, best_qp, best_qr, report, out, extra=None):
    """The default tracker (IMM filter) at a range of horizons: RMSE and jerk ratios to the
    Kalman CV extrapolation with noise ``best_qp`` / ``best_qr``."""
    kcfg = KalmanConfig(pos_process_noise=best_qp, rot_process_noise=best_qr)
    kf_rows = scores(data, lambda t, p, q, r: baselines.kalman_extrapolation(t, p, q, r, config=kcfg))
    report += ["## phjax horizon trade-off (default IMM tracker)", "",
               "ratios to the tuned Kalman CV extrapolation, mean over sequences", "",
               "| horizon [s] | pos RMSE | rot RMSE | pos jerk | rot jerk |", "|---|---|---|---|---|"]
    trade = {}
    for h in [0.015, 0.02, 0.025, 0.028, 0.03, 0.035, 0.05, 0.067, 0.1]:
        cfg = TrackerConfig(horizon=h)
        rows = scores(data, lambda t, p, q, r, cfg=cfg: track(t, p, q, r, config=cfg))
        trade[h] = [rel(rows, kf_rows, k) for k in ("pos", "rot", "jp", "jr")]
        report.append(f"| {h:g} | " + " | ".join(f"{v:.3f}" for v in trade[h]) + " |")
        print(f"phjax horizon={h:g}: {trade[h]}", flush=True)
    report.append("")
    text = "\n".join(report)
    (out / "tuning.md").write_text(text)
    (out / "tuned.json").write_text(json.dumps(dict(
        kalman=dict(pos_process_noise=best_qp, rot_process_noise=best_qr), **(extra or {}),
        horizon_tradeoff={str(k): v for k, v in trade.items()},
    ), indent=2))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
