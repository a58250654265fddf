"""The live config's stream with and without the online noise floor, on noisier sensors.

    python experiments/live_noise_floor.py        # about 1 min

Synthetic head motion (``phjax.motion.synthetic_head_motion``, 30 s, seeds 3, 6, 7), sampled by
the simulated sensor at 30 Hz with 5 % dropouts and noise 5 mm / 1 deg, 10 mm / 2 deg and
20 mm / 3 deg, rendered at 120 Hz by :func:`phjax.track` with the config of ``phjax live``
(:func:`phjax.live.live_tracker_config`: single-model filter with its innovation gate,
assuming 5 mm / 1 deg): with the floor off (``noise_window=0``), on (the live default, 60), and
told the true noise (``with_measurement_noise``). Prints the position RMSE (mm) and the
ratios, the table of ``docs/live.md`` ("Measurement noise").
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from phjax.live import live_tracker_config  # noqa: E402
from phjax.motion.simulate import (  # noqa: E402
    SensorModel,
    simulate_measurements,
    synthetic_head_motion,
)
from phjax.tracking import track  # noqa: E402
from phjax.tracking.noise import with_measurement_noise  # noqa: E402

SEEDS = (3, 6, 7)
SENSORS = ((0.005, 1.0), (0.010, 2.0), (0.020, 3.0))


def position_rmse(config, meas, render, gp) -> float:
    p, _ = track(*meas, render, config=config)
    return float(np.sqrt(np.mean(np.sum((np.asarray(p) - gp) ** 2, axis=1))))


def main(argv=None) -> int:
    argparse.ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    on = live_tracker_config()
    off = dataclasses.replace(on, noise_window=0)
    print("| sensor | seed | off [mm] | on / off | on / told |\n|---|---|---|---|---|")
    for sp, sr in SENSORS:
        told = with_measurement_noise(off, pos=sp, rot=math.radians(sr))
        for seed in SEEDS:
            gt = synthetic_head_motion(30.0, seed=seed)
            meas = [np.asarray(x) for x in simulate_measurements(
                seed, *gt, SensorModel(sigma_p=sp, sigma_r=math.radians(sr), dropout=0.05))]
            render = np.arange(meas[0][0] + 1.0, gt[0][-1], 1 / 120)
            gp = np.stack([np.interp(render, gt[0], gt[1][:, i]) for i in range(3)], 1)
            r_off, r_on, r_told = (position_rmse(c, meas, render, gp) for c in (off, on, told))
            print(f"| {sp * 1e3:g} mm / {sr:g} deg | {seed} | {r_off * 1e3:.2f} | "
                  f"{r_on / r_off:.3f} | {r_on / r_told:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
