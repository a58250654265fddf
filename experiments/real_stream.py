"""A real 30 Hz pose stream: RGBDSLAM's estimate of TUM RGB-D fr1_xyz against its ground truth.

    python experiments/real_stream.py

evo's absolute pose error (translation part, RMSE, after an SE(3) Umeyama alignment of the
associated poses, ``max_diff`` 10 ms) of the raw estimate, of the causal phjax stream
(:func:`phjax.track`, single-model Kalman and IMM filter, default configs) and of the offline
reconstruction (:func:`phjax.reconstruct`), each evaluated at the estimate's own timestamps and,
for the causal streams, also at 120 Hz render times. Prints a Markdown table.
"""

from __future__ import annotations

import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from phjax import io  # noqa: E402
from phjax.datasets import shared_data_dir  # noqa: E402
from phjax.tracking.imm import IMMConfig  # noqa: E402
from phjax.tracking.tracker import TrackerConfig, reconstruct, track  # noqa: E402


def ape_rmse(gt, t, p, q) -> float:
    """evo APE (translation, RMSE, m) of poses ``(t, p, q wxyz)`` against ``gt``."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    ok = np.isfinite(p).all(1) & np.isfinite(q).all(1)
    ref = PoseTrajectory3D(positions_xyz=gt.positions, orientations_quat_wxyz=gt.quaternions,
                           timestamps=gt.times)
    est = PoseTrajectory3D(positions_xyz=p[ok], orientations_quat_wxyz=q[ok], timestamps=t[ok])
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def load():
    root = shared_data_dir()
    if root is None:
        raise FileNotFoundError("../shared/data not found")
    base = root / "tum_rgbd_groundtruth"
    return (io.read_tum(base / "fr1_xyz-groundtruth.txt"),
            io.read_tum(base / "estimates" / "fr1_xyz-rgbdslam_estimate.txt"))


def evaluate() -> dict[str, float]:
    gt, est = load()
    t, p, q = est.times, est.positions, est.quaternions
    r120 = np.arange(t[0], t[-1], 1 / 120)
    out = {"raw estimate": ape_rmse(gt, t, p, q)}
    for name, cfg in (("kalman", TrackerConfig(imm=None)), ("imm", TrackerConfig(imm=IMMConfig()))):
        pc, qc = (np.asarray(x) for x in track(t, p, q, t, config=cfg))
        out[f"phjax causal ({name}), at the frames"] = ape_rmse(gt, t, pc, qc)
        pr, qr = (np.asarray(x) for x in track(t, p, q, r120, config=cfg))
        out[f"phjax causal ({name}), 120 Hz"] = ape_rmse(gt, r120, pr, qr)
    po, qo = (np.asarray(x) for x in reconstruct(t, p, q, t))
    out["phjax offline (reconstruct), at the frames"] = ape_rmse(gt, t, po, qo)
    return out


def main() -> int:
    res = evaluate()
    print("| stream | APE RMSE [mm] |\n|---|---|")
    for k, v in res.items():
        print(f"| {k} | {v * 1e3:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
