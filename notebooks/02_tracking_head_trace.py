# %% [markdown]
# # Tracking a real VR head trace
#
# Jupytext percent notebook (open with Jupyter + jupytext, or run as a script:
# `python notebooks/02_tracking_head_trace.py`). A real 6-DoF head trajectory (CWI navigation
# data: a participant walking around a point-cloud human in VR) is sampled by the simulated
# camera (30 Hz, 5 mm, 1 deg, 5 % dropouts) and rendered at 120 Hz by the phjax stream and the
# baselines; we compare accuracy, smoothness and latency and look at the rendered samples between
# two camera frames. Without `../shared/data` it falls back to the synthetic head motion.
# Set `PHJAX_NOTEBOOK_FIGURES=dir` to save the figures.

# %%
import os
import sys
import tempfile
import warnings

import jax
import numpy as np

import phjax as pj
from phjax import io
from phjax.datasets import shared_data_dir
from phjax.evaluation import default_methods, evaluate_recording, format_table, plot_evaluation

jax.config.update("jax_enable_x64", True)

# %% [markdown]
# ## The trace
# The most mobile participant of the CWI "loot" content (highest median walking speed over the
# first 20 s among the traces at least 20 s long; Unity coordinates converted to a right-handed
# frame by `phjax.io.read_cwi`; the data have no timestamps: 30 Hz per row is the documented
# assumption). We keep 20 s.

# %%
root = shared_data_dir()
cwi = None if root is None else root / "vr_cwi_6dof_navigation" / "H2_loot_nav.csv"
if cwi is not None and cwi.exists():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        people = io.read_cwi(cwi)

    def median_speed(tr, seconds=20.0):
        sel = tr.times - tr.times[0] <= seconds
        x, tt = tr.positions[sel], tr.times[sel]
        return float(np.median(np.linalg.norm(np.diff(x, axis=0), axis=-1) / np.diff(tt)))

    long_enough = [k for k in people if people[k].times[-1] - people[k].times[0] >= 20.0]
    who = max(long_enough, key=lambda k: median_speed(people[k]))
    traj = people[who]
    source = f"CWI H2 (loot), participant {who}"
else:
    traj = io.Trajectory(*pj.synthetic_head_motion(duration=20.0, rate=120.0, seed=3))
    source = "synthetic head motion (shared data not found)"
t = traj.times - traj.times[0]
keep = t <= 20.0
t, p, q = t[keep], traj.positions[keep], traj.quaternions[keep]
speed = np.linalg.norm(np.diff(p, axis=0), axis=-1) / np.diff(t)
print(f"{source}: {t.size} samples over {t[-1]:.1f} s, median walking speed "
      f"{np.median(speed):.2f} m/s, height {np.median(p[:, 1]):.2f} m")

# %% [markdown]
# ## Stream vs baselines
# `evaluate_recording` simulates the camera and runs each method on the same measurements:
# the causal phjax stream (`pj.track`: IMM filter + a segment of two C1-joined PH quintic /
# quaternion pieces per camera frame), the causal baselines (Kalman constant-velocity extrapolation, One Euro filter
# then hold, raw hold) and SciPy's offline cubic spline for reference.

# %%
wanted = ["phjax (causal)", "kalman-cv extrapolation", "one-euro + hold", "raw hold",
          "cubic spline (scipy)"]
methods = [m for m in default_methods() if m.name in wanted]
res = evaluate_recording(t, p, q, methods=methods, render_rate=120.0, seed=0)
print(format_table(res.metrics, res.causal))

# %%
m = res.metrics
ph, kf = m["phjax (causal)"], m["kalman-cv extrapolation"]
print(f"phjax / Kalman CV: position RMSE {ph['position_rmse'] / kf['position_rmse']:.2f}x, "
      f"position jerk {ph['jerk_position'] / kf['jerk_position']:.2f}x, "
      f"max velocity jump {ph['velocity_jump'] / kf['velocity_jump']:.2f}x")
assert ph["jerk_position"] < kf["jerk_position"]  # the stream is smoother than extrapolation
assert ph["velocity_jump"] < kf["velocity_jump"]  # and C1 across camera frames

# %% [markdown]
# ## Between two camera frames
# A zoom on 0.4 s: the camera frames (grey dots), the hold's staircase, the extrapolator's
# saw-tooth (a jump at every frame) and the phjax stream, which starts every segment at the
# rendered pose and velocity and therefore has no jump.

# %%
out = os.environ.get("PHJAX_NOTEBOOK_FIGURES")
in_jupyter = "ipykernel" in sys.modules  # executed as a notebook: figures shown inline
if in_jupyter and not out:
    out = tempfile.mkdtemp()
if out:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plot_evaluation(res, os.path.join(out, "02_evaluation.png"))
    rt = res.render_times - res.render_times[0]
    mt, mp, _ = res.measurements
    mt = mt - res.render_times[0]
    v = np.linalg.norm(np.gradient(res.gt_positions, rt, axis=0), axis=-1)
    mid = rt[np.nanargmax(np.convolve(np.nan_to_num(v), np.ones(48), "same"))]
    win = (rt > mid - 0.2) & (rt < mid + 0.2)
    axis = int(np.nanargmax(np.nanstd(res.gt_positions[win], axis=0)))
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(rt[win], res.gt_positions[win, axis], "k", lw=2, label="ground truth")
    mw = (mt > mid - 0.2) & (mt < mid + 0.2)
    ax.plot(mt[mw], mp[mw, axis], "o", color="0.5", label="camera frames (noisy)")
    for name, col in [("raw hold", "#7f8fa6"), ("kalman-cv extrapolation", "#1f3fbf"),
                      ("phjax (causal)", "#d62728")]:
        ax.plot(rt[win], res.streams[name][0][win, axis], ".-", ms=3, lw=1, color=col, label=name)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"position {'xyz'[axis]} [m]")
    ax.set_title("rendered samples at 120 Hz between 30 Hz camera frames (fastest 0.4 s)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "02_between_frames.png"), dpi=110)
    plt.close(fig)
    if not in_jupyter:  # (a notebook's own temporary folder is no use to a reader)
        print("figures written to", out)
    if in_jupyter:
        from IPython.display import Image, display

        for name in ("02_evaluation.png", "02_between_frames.png",):
            display(Image(os.path.join(out, name)))
