# %% [markdown]
# # Tuning the causal tracker by differentiating the whole stream
#
# Jupytext percent notebook (open with Jupyter + jupytext, or run as a script:
# `python notebooks/03_tuning.py`). The causal stream of `phjax.track` is one `lax.scan` over
# the camera frames followed by render-rate sampling, so the accuracy and smoothness of the
# rendered poses are differentiable functions of the tracker's parameters (by default the IMM
# filter's model noise densities and switch rate, and the segment horizon). This notebook
# differentiates them on a short synthetic recording, checks
# the gradient against finite differences, takes a few BFGS steps and traces the
# accuracy / smoothness frontier for three values of the trade-off weight lambda.
# Set `PHJAX_NOTEBOOK_FIGURES=dir` to save the figure. (The first gradient compiles the
# differentiated stream, which takes most of the run time.)

# %%
import os
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import phjax as pj
from phjax.tracking import tuning

jax.config.update("jax_enable_x64", True)
t_start = time.perf_counter()

# %% [markdown]
# ## A short recording
# Two seconds of synthetic seated-VR head motion, sampled by the default sensor (30 Hz, 5 mm,
# 1 degree, 5 % dropouts, fixed seed) and rendered at 120 Hz. The loss terms of every
# configuration are divided by those of the tuned Kalman constant-velocity extrapolation on the
# same measurements, so that baseline scores exactly `1 + lambda`.

# %%
gt = pj.synthetic_head_motion(duration=2.0, rate=120.0, seed=7)
data = tuning.prepare_recordings([gt], seed=0)
# the arrays are padded to size classes (lost frames and masked render samples after the end),
# so that recordings of other lengths reuse the compiled loss
valid = np.isfinite(np.asarray(data.positions)).all(-1).sum()
print(f"measured poses: {int(valid)} of {data.times.shape[1]} frames (dropouts and padding lost); "
      f"scored render samples: {int(data.render_mask.sum())} of {data.render_times.shape[1]}")
print("reference [pos RMSE mm, rot RMSE deg, pos jerk m/s^3, rot jerk rad/s^3]:",
      np.round(np.asarray(data.reference[0]) * [1e3, np.degrees(1), 1, 1], 3))

# %% [markdown]
# ## The gradient through the stream
# Parameters are optimised in log space, so the gradient below is
# `d loss / d log(parameter)`: the change of the loss per relative change of the parameter (the
# IMM's `log_q` and `log_switch_rate` are logarithms already).

# %%
problem = tuning.make_problem(data, lam=0.3)
y0 = problem.params_from_config(pj.TrackerConfig())
loss0, grad0, terms0 = problem.value_and_grad(y0)
print(f"loss at the hand-set default: {float(loss0):.4f} (Kalman-CV scores 1.3)")
for name, g in zip(problem.parameters, np.asarray(grad0)):
    label = name if name.split(".")[-1].startswith("log_") else f"log {name}"
    print(f"  d loss / d {label:28s} {g:+.5f}")
# central difference for the first parameter (the quietest position model's density)
h = 1e-5
e = jnp.zeros_like(y0).at[0].set(h)
fd = (float(problem.value_and_grad(y0 + e)[0]) - float(problem.value_and_grad(y0 - e)[0])) / (2 * h)
print(f"central difference for {problem.parameters[0]}: {fd:+.5f}")
assert abs(fd - float(grad0[0])) < 1e-4 * abs(fd) + 1e-9

# %% [markdown]
# ## A few BFGS steps
# `tune_tracker` steps `optimistix.BFGS` with the loss and gradient of the stream; the status
# is reported, not raised (like `optimistix.minimise(..., throw=False)`).

# %%
config, result = tuning.tune_tracker(
    data, lam=0.3, max_steps=6,
    progress=lambda s: print(f"step {s.step}: loss {s.loss:.4f} "
                             f"({'accepted' if s.accepted else 'rejected'})"))
print(result.message)
for k in result.parameters:
    print(f"  {k:28s} {result.initial_parameters[k]:.4g} -> {result.parameters[k]:.4g}")
assert result.final_loss < result.initial_loss

# %% [markdown]
# ## The frontier
# Larger lambda buys smoothness (lower jerk) with accuracy (higher RMSE). Three values, a few
# steps each, on this tiny recording (in-sample; see `experiments/tuning_frontier.py` for the
# held-out evaluation on real trajectories).

# %%
frontier = {}
for lam in (0.0, 0.3, 3.0):
    _, res = tuning.tune_tracker(data, lam=lam, max_steps=6)
    frontier[lam] = res.terms[0] / res.reference[0]
    print(f"lambda {lam:g}: pos RMSE x{frontier[lam][0]:.3f}, rot RMSE x{frontier[lam][1]:.3f}, "
          f"pos jerk x{frontier[lam][2]:.3f}, rot jerk x{frontier[lam][3]:.3f} (of Kalman-CV)")
assert frontier[3.0][2] < frontier[0.0][2]  # more weight on jerk, smoother stream
print(f"notebook run time {time.perf_counter() - t_start:.0f} s")

# %%
out = os.environ.get("PHJAX_NOTEBOOK_FIGURES")
in_jupyter = "ipykernel" in sys.modules  # executed as a notebook: figures shown inline
if in_jupyter and not out:
    out = tempfile.mkdtemp()
if out:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    for a, (kx, ky, title) in zip(ax, [(2, 0, "position"), (3, 1, "rotation")]):
        lams = sorted(frontier)
        a.plot([frontier[lam][kx] for lam in lams], [frontier[lam][ky] for lam in lams], "o-",
               label="tuned")
        for lam in lams:
            a.annotate(f"lambda={lam:g}", (frontier[lam][kx], frontier[lam][ky]), fontsize=8)
        a.plot([1], [1], "ks", label="Kalman-CV extrapolation")
        a.set_xscale("log")
        a.set_xlabel(f"RMS {title} jerk / Kalman-CV")
        a.set_ylabel(f"{title} RMSE / Kalman-CV")
        a.legend()
    os.makedirs(out, exist_ok=True)
    fig.savefig(os.path.join(out, "tuning_frontier.png"), dpi=100)
    if in_jupyter:
        from IPython.display import Image, display

        for name in ("tuning_frontier.png",):
            display(Image(os.path.join(out, name)))
