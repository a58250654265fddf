"""RMS jerk and velocity jumps of the rendered streams against the render rate.

    python experiments/jerk_vs_render_rate.py [--duration 10] [--rates 120 480 1920 7680]

The README quickstart's recording (synthetic head motion, seed 0, default sensor: 30 Hz, 5 mm,
1 deg, 5 % dropouts) is rendered by the causal stream, the offline reconstruction and the Kalman
CV extrapolation at several render rates; the metrics of :mod:`phjax.evaluation.metrics` are
computed on each. A stream that is C1 has velocity jumps that vanish as the rate grows (what
remains at a coarse rate is the one-sided stencils' error); its RMS jerk grows with the rate
where the acceleration steps (C1, not C2).
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import phjax as pj
from phjax.evaluation import metrics
from phjax.tracking import baselines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=10.0, help="length of the motion, s")
    ap.add_argument("--rates", type=float, nargs="+", default=[120, 480, 1920, 7680])
    args = ap.parse_args(argv)
    gt_t, gt_p, gt_q = pj.synthetic_head_motion(duration=args.duration)
    t, p, q = (np.asarray(x) for x in pj.simulate_measurements(0, gt_t, gt_p, gt_q,
                                                               pj.SensorModel(rate=30.0)))
    frames = t[np.isfinite(p).all(-1)]
    methods = {"phjax (causal)": pj.track, "phjax (offline)": pj.reconstruct,
               "kalman-cv extrapolation": baselines.kalman_extrapolation}
    print("| render rate [Hz] | method | RMS jerk [m/s^3] | max velocity jump [m/s] | "
          "median velocity jump [m/s] |")
    print("|---|---|---|---|---|")
    for rate in args.rates:
        r = np.arange(0.1, args.duration, 1 / rate)
        for name, fn in methods.items():
            pos = np.asarray(fn(t, p, q, r)[0], np.float64)
            jerk = metrics.rms_jerk_position(r, pos).value
            jump = metrics.max_velocity_jump(r, pos, frames).value
            left, right = metrics._boundary_windows(r, np.isfinite(pos).all(-1), frames)
            jumps = np.linalg.norm(metrics._one_sided(r, pos, right, right[:, 0])
                                   - metrics._one_sided(r, pos, left, left[:, -1]), axis=-1)
            print(f"| {rate:g} | {name} | {jerk:.4g} | {jump:.4g} | {np.median(jumps):.4g} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
