"""A real 30 Hz pose stream: RGBDSLAM's estimate of TUM RGB-D fr1_xyz against its ground truth.

    python experiments/real_stream.py        # Markdown table (about 3 min on 1 CPU core)
    python experiments/real_stream.py --ml   # also the maximum-likelihood IMM noise (+1 min)
    python experiments/real_stream.py --tune # also gradient tuning on the stream (+6 min)

evo's absolute pose error (:class:`evo.core.metrics.APE`, translation part, after evo's SE(3)
Umeyama alignment ``PoseTrajectory3D.align(correct_scale=False)`` of the poses associated by
``evo.core.sync.associate_trajectories(max_diff=0.01)``) of

* the raw estimate,
* the causal phjax stream (:func:`phjax.track`, IMM and single-model filters) at the estimate's
  own timestamps and at 120 Hz render times,
* the causal IMM filter without the stream (its posterior at each frame,
  :func:`phjax.tracking.imm_extrapolation` at the frame times),
* the raw estimate held at 120 Hz (what a renderer fed the raw poses would show),
* the offline reconstruction (:func:`phjax.reconstruct`) at the estimate's timestamps,

each with the default configuration (sensor noise 5 mm / 1 degree) and with the measurement
noise estimated from the recording itself (:func:`phjax.tracking.estimate_measurement_noise`,
put into the config by :func:`phjax.tracking.with_measurement_noise`) and, with ``--ml``, with
maximum-likelihood IMM noise (:func:`ml_imm_config`). No number in it is tuned to this file.
evo's RMSE, mean and std (the APE of the raw estimate has std 6.07 mm, the "6.1 mm" of issue 16)
are printed.

With ``--tune``, :func:`tune_split` tunes the tracker by gradient on the real stream itself
(:func:`phjax.tracking.tuning.measured_recording` moves the estimate into the ground truth's frame
by an SE(3) alignment like evo's, :func:`phjax.tracking.tuning.tuning_data`,
:func:`phjax.tune_tracker`) on the first half of the recording and
scores the default and the tuned configuration on the second half, each term relative to the
tuned Kalman CV extrapolation on the same half.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from phjax import io
from phjax.datasets import shared_data_dir
from phjax.tracking.imm import IMMConfig
from phjax.tracking.noise import estimate_measurement_noise, with_measurement_noise
from phjax.tracking.tracker import TrackerConfig, reconstruct, track

MAX_DIFF = 0.01  # s, evo association tolerance (TUM's evaluate_ate uses 0.02: 13.473 mm instead)


def ape_stats(gt, t, p, q, max_diff: float = MAX_DIFF) -> dict[str, float]:
    """evo APE statistics (translation part, m: rmse, mean, median, std, max) of ``(t, p, q wxyz)``
    against the ground truth ``gt`` after SE(3) alignment."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    ok = np.isfinite(p).all(1) & np.isfinite(q).all(1)
    ref = PoseTrajectory3D(positions_xyz=gt.positions, orientations_quat_wxyz=gt.quaternions,
                           timestamps=gt.times)
    est = PoseTrajectory3D(positions_xyz=p[ok], orientations_quat_wxyz=q[ok], timestamps=t[ok])
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    s = ape.get_all_statistics()
    return {k: float(s[k]) for k in ("rmse", "mean", "median", "std", "max")}


def ape_rmse(gt, t, p, q) -> float:
    """evo APE (translation, RMSE, m) of poses ``(t, p, q wxyz)`` against ``gt``."""
    return ape_stats(gt, t, p, q)["rmse"]


def load():
    root = shared_data_dir()
    if root is None:
        raise FileNotFoundError("../shared/data not found")
    base = root / "tum_rgbd_groundtruth"
    return (io.read_tum(base / "fr1_xyz-groundtruth.txt"),
            io.read_tum(base / "estimates" / "fr1_xyz-rgbdslam_estimate.txt"))


def configs(t, p, q) -> dict[str, TrackerConfig]:
    """The default IMM / single-model configs, the same with data-estimated noise, and the IMM
    with the online noise floor (``TrackerConfig.noise_window``)."""
    noise = estimate_measurement_noise(t, p, q)
    out = {}
    for name, base in (("imm", TrackerConfig(imm=IMMConfig())), ("kalman", TrackerConfig(imm=None))):
        out[f"{name}, default noise"] = base
        out[f"{name}, estimated noise"] = with_measurement_noise(base, noise)
    out["imm, online noise floor 60"] = TrackerConfig(imm=IMMConfig(), noise_window=60)
    return out


def ml_imm_config(t, p, q, base: IMMConfig | None = None) -> IMMConfig:
    """Maximum-likelihood IMM noise (experimental): BFGS (optimistix) over the log measurement
    stds and a common log scale of each part's model spectral densities, maximising the
    Gaussian (moment-matched mixture) innovation log-likelihood of :func:`imm_filter`."""
    import math

    import jax.numpy as jnp
    import optimistix as optx

    from phjax.tracking.imm import imm_filter
    from phjax.tracking.models import ConstantVelocity

    base = IMMConfig() if base is None else base
    t0, pj, qj = jnp.asarray(t - t[0]), jnp.asarray(p), jnp.asarray(q)

    def make(th):
        pm = tuple(ConstantVelocity(log_q=m.log_q + th[1]) for m in base.position_models)
        rm = tuple(ConstantVelocity(log_q=m.log_q + th[3]) for m in base.rotation_models)
        return dataclasses.replace(base, position_models=pm, rotation_models=rm,
                                   pos_meas_noise=jnp.exp(th[0]), rot_meas_noise=jnp.exp(th[2]))

    def loglik(y, s, m):
        s = jnp.where(m[:, None, None], s, jnp.eye(3, dtype=s.dtype))
        chol = jnp.linalg.cholesky(s)
        z = jax.scipy.linalg.solve_triangular(chol, y[..., None], lower=True)[..., 0]
        ll = -0.5 * jnp.sum(z**2, -1) - jnp.sum(jnp.log(jnp.diagonal(chol, 0, -2, -1)), -1)
        return jnp.sum(jnp.where(m, ll, 0.0))

    def nll(th, _):
        _, info = imm_filter(make(th), t0, pj, qj)
        mp = info.pos_used & ~info.initialized_now
        mr = info.rot_used & ~info.initialized_now
        return -(loglik(info.pos_innovation, info.pos_innovation_cov, mp)
                 + loglik(info.rot_innovation, info.rot_innovation_cov, mr)) / t0.shape[0]

    th0 = jnp.array([math.log(base.pos_meas_noise), 0.0, math.log(base.rot_meas_noise), 0.0])
    sol = optx.minimise(jax.jit(nll), optx.BFGS(rtol=1e-6, atol=1e-8), th0, max_steps=200)
    return make(sol.value)


#: parameters of :func:`tune_split`: the IMM defaults and the measurement noise (the SLAM
#: estimate's noise is not the default sensor's)
TUNE_PARAMETERS = ("imm.pos_meas_noise", "imm.rot_meas_noise")


def tune_split(steps: int = 20, lams=(0.3, 0.0)) -> dict[str, tuple]:
    """Tune on the first half of the stream for each ``lambda``, score on the second (see the
    module docstring).

    Returns:
        ``{"default": (terms, None), "tuned, lambda L": (terms, parameters), ...}``: the test
        half's ``[E_p, E_r, J_p, J_r]`` divided by the Kalman CV reference's, and the tuned
        parameter values.
    """
    from phjax.tracking import tuning

    gt, est = load()
    # the whole stream in the ground truth's frame (one rigid transform), then split in time
    t, p, q, *_ = tuning.measured_recording(gt, est, align=True)
    first = t < 0.5 * (t[0] + t[-1])
    train, test = (tuning.tuning_data([tuning.measured_recording(gt, (t[k], p[k], q[k]))])
                   for k in (first, ~first))
    start = TrackerConfig()
    params = tuning.default_parameters(start) + TUNE_PARAMETERS

    def score(cfg):
        return np.asarray(tuning.loss_terms(cfg, test)[0] / test.reference[0])

    out = {"default": (score(start), None)}
    for lam in lams:  # one compilation serves every lambda
        tuned, res = tuning.tune_tracker(train, lam=lam, config=start, parameters=params,
                                         max_steps=steps)
        print(f"lambda {lam:g}: tuned on the first half ({res.message}, {res.num_steps} steps, "
              f"train loss {res.initial_loss:.4f} -> {res.final_loss:.4f})", flush=True)
        out[f"tuned, lambda {lam:g}"] = (score(tuned), res.parameters)
    return out


def evaluate(ml: bool = False) -> dict[str, dict]:
    """evo APE statistics of every stream (see the module docstring)."""
    from phjax.tracking.baselines import hold, imm_extrapolation

    gt, est = load()
    t, p, q = est.times, est.positions, est.quaternions
    r120 = np.arange(t[0], t[-1], 1 / 120)
    out = {"raw estimate, at the frames": ape_stats(gt, t, p, q)}
    ph, qh = (np.asarray(x) for x in hold(t, p, q, r120))
    out["raw estimate held (zero-order hold), 120 Hz"] = ape_stats(gt, r120, ph, qh)
    cfgs = configs(t, p, q)
    if ml:
        cfgs["imm, maximum-likelihood noise"] = TrackerConfig(imm=ml_imm_config(t, p, q))
    for name, cfg in cfgs.items():
        pc, qc = (np.asarray(x) for x in track(t, p, q, t, config=cfg))
        out[f"causal stream ({name}), at the frames"] = ape_stats(gt, t, pc, qc)
        pr, qr = (np.asarray(x) for x in track(t, p, q, r120, config=cfg))
        out[f"causal stream ({name}), 120 Hz"] = ape_stats(gt, r120, pr, qr)
        if cfg.noise_window:  # the floor is the stream's (the filter alone has none)
            continue
        if cfg.imm is not None:  # the IMM filter alone: its posterior at the frames
            pf, qf = (np.asarray(x) for x in imm_extrapolation(t, p, q, t, config=cfg.imm))
            out[f"causal IMM filter without the stream ({name}), at the frames"] = ape_stats(
                gt, t, pf, qf)
        else:  # reconstruct uses cfg.kalman
            po, qo = (np.asarray(x) for x in reconstruct(t, p, q, t, config=cfg))
            out[f"offline ({name.split(', ')[1]}), at the frames"] = ape_stats(gt, t, po, qo)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ml", action="store_true",
                    help="also the maximum-likelihood IMM noise (about 1 min more)")
    ap.add_argument("--tune", action="store_true",
                    help="also tune the tracker by gradient on the stream's first half and "
                    "score it on the second (about 6 min more)")
    args = ap.parse_args(argv)
    _, est = load()
    noise = estimate_measurement_noise(est.times, est.positions, est.quaternions)
    print("estimated white measurement noise per axis: position "
          + " / ".join(f"{x * 1e3:.2f}" for x in np.asarray(noise.pos_std)) + " mm, orientation "
          + " / ".join(f"{x:.3f}" for x in np.rad2deg(np.asarray(noise.rot_std))) + " deg "
          f"(RMS {float(noise.pos_meas_noise) * 1e3:.2f} mm, "
          f"{np.rad2deg(float(noise.rot_meas_noise)):.3f} deg)\n")
    res = evaluate(ml=args.ml)
    print("| stream | APE RMSE [mm] | mean | std | max |\n|---|---|---|---|---|")
    for k, v in res.items():
        print(f"| {k} | {v['rmse'] * 1e3:.2f} | {v['mean'] * 1e3:.2f} | {v['std'] * 1e3:.2f} "
              f"| {v['max'] * 1e3:.1f} |")
    if args.tune:
        out = tune_split()
        print("\nsecond half, phjax / tuned Kalman CV extrapolation\n\n"
              "| config | pos RMSE | rot RMSE | pos jerk | rot jerk |\n|---|---|---|---|---|")
        for name, (v, _) in out.items():
            print(f"| {name} | " + " | ".join(f"{x:.3f}" for x in v) + " |")
        for name, (_, params) in out.items():
            if params:
                print(f"\n{name}:", {k: float(f"{v:.4g}") for k, v in params.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
