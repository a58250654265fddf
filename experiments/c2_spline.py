"""C2 PH quintic spline vs the C1 Hermite chain for offline reconstruction, on the dev set.

    python experiments/c2_spline.py [--quick | --smoke] [--seconds 20] [--window 60] [--out results/c2_spline]

Protocol: each development sequence with positions (``experiments/devset.py``; TUM RGB-D, TUM VI,
CWI) is sampled by the default sensor model (30 Hz, 5 mm, 1 deg, 5 % dropouts, seed 0); the
Kalman filter + RTS smoother of ``phjax.reconstruct`` gives positions and velocities at every
camera frame. Three offline position reconstructions through the same smoothed states, rendered
at 120 Hz:

* ``C1 chain``: ``phjax.reconstruct`` (one Hermite PH quintic per frame interval, end
  derivatives = smoothed velocity x interval; C1 at every frame);
* ``C2 spline``: :func:`phjax.curves.ph_spline` through the smoothed positions in windows of
  ``--window`` intervals, each window clamped at both ends to the smoothed velocity x interval
  (C2 inside windows, C1 at window joints);
* ``cubic spline (scipy)`` through the raw measurements (the offline baseline of the tracker
  issue).

Reported per sequence and as the mean ratio to the C1 chain: position RMSE against the
ground truth and RMS jerk of the rendered positions (``phjax.evaluation.metrics``), feasibility-phase
Levenberg-Marquardt steps and the
largest equation residual of the spline solves, and how many window solves ended
``NOT_FAIREST`` (a valid C2 interpolant whose fairness did not reach stationarity).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from devset import load_devset  # noqa: E402
from tune_baselines import prepare  # noqa: E402

from phjax.tracking import baselines  # noqa: E402
from phjax.tracking.kalman import KalmanConfig, kalman_filter, rts_smooth  # noqa: E402
from phjax.evaluation.metrics import position_rmse, rms_jerk_position  # noqa: E402
from phjax.curves.ph_quintic import PHQuintic  # noqa: E402
from phjax.curves.ph_spline import SplineStatus, ph_spline  # noqa: E402
from phjax.tracking.tracker import reconstruct  # noqa: E402


def smoothed_states(mt, mp, mq):
    filtered, _ = kalman_filter(KalmanConfig(), mt, mp, mq)
    sm = rts_smooth(KalmanConfig(), filtered)
    return np.asarray(sm.x[:, :3]), np.asarray(sm.x[:, 3:6]), np.asarray(sm.initialized)


def c2_render(t, p, v, r, window):
    """C2 spline in windows of ``window`` intervals through (t, p), clamped to v; render at r."""
    n = len(t) - 1
    starts = list(range(0, n, window))
    fields = {"A0": np.zeros((n, 4)), "A1": np.zeros((n, 4)), "A2": np.zeros((n, 4)),
              "control_points": np.zeros((n, 6, 3))}
    steps, resid, bad, not_fairest = [], [], 0, 0
    for s in starts:
        e = min(s + window, n)
        if e - s < 2:  # a 1-interval tail: a Hermite segment would do; join it to the window
            s = max(0, e - 2)
        dt0, dt1 = t[s + 1] - t[s], t[e] - t[e - 1]
        curves, sol = ph_spline(p[s:e + 1], v[s] * dt0, v[e] * dt1)
        steps.append(int(sol.num_steps))
        resid.append(float(sol.residual))
        bad += not bool(sol.ok)
        not_fairest += int(sol.status) == SplineStatus.NOT_FAIREST
        for name, arr in fields.items():  # a later window overrides an overlapped tail
            arr[s:e] = np.asarray(getattr(curves, name))
    idx = np.clip(np.searchsorted(t, r, side="right") - 1, 0, n - 1)
    u = np.clip((r - t[idx]) / (t[idx + 1] - t[idx]), 0, 1)
    segs = PHQuintic(**{k: jnp.asarray(v[idx]) for k, v in fields.items()})
    out = np.asarray(jax.vmap(lambda c, x: c.position(x))(segs, jnp.asarray(u)))
    return out, steps, resid, bad, not_fairest


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 sequences, 8 s each")
    ap.add_argument("--smoke", action="store_true", help="1 sequence, 3 s (the test suite's run)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each sequence used")
    ap.add_argument("--window", type=int, default=60, help="frame intervals per spline window")
    ap.add_argument("--out", default="results/c2_spline", help="output folder")
    args = ap.parse_args(argv)
    seconds = 3.0 if args.smoke else 8.0 if args.quick else args.seconds
    seqs = [s for s in load_devset(max_seconds=seconds) if np.isfinite(s[3]).any()]
    if args.smoke:
        seqs = seqs[:1]
    elif args.quick:
        seqs = seqs[:1] + seqs[7:8] + seqs[-1:]
    data = prepare(seqs)
    rows = []
    t_start = time.perf_counter()
    for d in data:
        r, gp = d["r"], d["gp"]
        ok_gt = np.isfinite(gp).all(-1)
        p_c1, _ = reconstruct(d["mt"], d["mp"], d["mq"], r)
        p, v, init = smoothed_states(d["mt"], d["mp"], d["mq"])
        first = int(np.argmax(init))
        p_c2, steps, resid, bad, nf = c2_render(d["mt"][first:], p[first:], v[first:],
                                            r, args.window)
        p_cs, _ = baselines.cubic_spline(d["mt"], d["mp"], d["mq"], r)
        row = {"name": d["name"], "windows": len(steps), "max steps": max(steps),
               "max residual": max(resid), "failed": bad, "not fairest": nf}
        for key, est in (("c1", p_c1), ("c2", p_c2), ("cs", p_cs)):
            est = np.asarray(est)
            row[f"rmse_{key}"] = position_rmse(est[ok_gt], gp[ok_gt]).value
            row[f"jerk_{key}"] = rms_jerk_position(r, est).value
        rows.append(row)
        print(f"{d['name']:32s} rmse mm C1 {1e3 * row['rmse_c1']:.3f} C2 {1e3 * row['rmse_c2']:.3f}"
              f" spline {1e3 * row['rmse_cs']:.3f} | jerk C1 {row['jerk_c1']:.2f} C2 "
              f"{row['jerk_c2']:.2f} spline {row['jerk_cs']:.1f} | steps <= {row['max steps']},"
              f" residual <= {row['max residual']:.1e}", flush=True)
    elapsed = time.perf_counter() - t_start
    ratio = {k: float(np.mean([r[f"{k}_c2"] / r[f"{k}_c1"] for r in rows])) for k in ("rmse", "jerk")}
    ratio_cs = {k: float(np.mean([r[f"{k}_cs"] / r[f"{k}_c1"] for r in rows]))
                for k in ("rmse", "jerk")}
    lines = ["# C2 PH spline vs C1 Hermite chain (offline)", "",
             f"{len(rows)} sequences x {seconds:g} s, default sensor, 120 Hz render, windows of "
             f"{args.window} intervals; {elapsed:.0f} s wall.", "",
             "| sequence | pos RMSE C1 [mm] | C2 [mm] | scipy spline [mm] | RMS jerk C1 [m/s^3] | "
             "C2 | scipy spline | LM steps (max) | residual (max) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['name']} | {1e3 * r['rmse_c1']:.3f} | {1e3 * r['rmse_c2']:.3f} | "
                     f"{1e3 * r['rmse_cs']:.3f} | {r['jerk_c1']:.3f} | {r['jerk_c2']:.3f} | "
                     f"{r['jerk_cs']:.1f} | {r['max steps']} | {r['max residual']:.1e} |")
    lines += ["", f"mean ratio C2 / C1: RMSE {ratio['rmse']:.3f}, jerk {ratio['jerk']:.3f}; "
              f"scipy spline / C1: RMSE {ratio_cs['rmse']:.3f}, jerk {ratio_cs['jerk']:.1f}; "
              f"window solves: {sum(r['windows'] for r in rows)}, not interpolating (failed): "
              f"{sum(r['failed'] for r in rows)}, NOT_FAIREST (valid C2 interpolant, fairness "
              f"not stationary): {sum(r['not fairest'] for r in rows)}"]
    text = "\n".join(lines)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "c2_spline.md").write_text(text + "\n")
    print("\n" + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
