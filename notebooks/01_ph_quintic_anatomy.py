# %% [markdown]
# # Anatomy of a spatial PH quintic
#
# Jupytext percent notebook (open with Jupyter + jupytext, or run as a script:
# `python notebooks/01_ph_quintic_anatomy.py`). It builds a first-order Hermite PH quintic,
# checks the Pythagorean-hodograph property, compares the Frenet, Euler-Rodrigues and
# rotation-minimising frames across an inflection, and maps the bending energy over the two free
# angles (the landscape the near-optimal default and the optimiser work on).
# Set `PHJAX_NOTEBOOK_FIGURES=dir` to save the figures.

# %%
import os
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

import phjax as pj

jax.config.update("jax_enable_x64", True)

# %% [markdown]
# ## Construction and the PH property

# %%
p0, p1 = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.4, 0.2])
d0, d1 = np.array([1.0, 1.0, 0.0]), np.array([1.0, -0.8, 0.5])
c = pj.hermite_quintic(p0, p1, d0, d1)
t = np.linspace(0, 1, 201)
h = np.asarray(c.hodograph(t))
sigma = np.asarray(c.speed(t))
print("end conditions:", np.allclose(c.position(1.0), p1), np.allclose(c.hodograph(0.0), d0))
print("max | |r'| - sigma |:", np.abs(np.linalg.norm(h, axis=-1) - sigma).max())
print("arc length (exact polynomial):", float(c.length))

# %% [markdown]
# ## Frames across an inflection
# A planar S-curve has an inflection (kappa = 0): the Frenet frame flips by pi there, the ERF and
# the RMF stay continuous.

# %%
s_curve = pj.hermite_quintic([0.0, 0, 0], [2.0, 0, 0], [1.0, 1.0, 0], [1.0, 1.0, 0])
ts = np.linspace(0.05, 0.95, 181)
flips = {}
for kind in ("frenet", "euler_rodrigues", "rmf"):
    F = np.asarray(s_curve.frame(ts, kind))
    normal = F[..., :, 1]
    flips[kind] = float(np.min(np.sum(normal[1:] * normal[:-1], axis=-1)))
print("min cos between consecutive normals:", flips)
assert flips["frenet"] < 0 < flips["rmf"]

# %% [markdown]
# ## The (phi0, phi2) landscape
# Bending energy of the interpolants over the free angles (phi1 = 0), the paper's -pi/2 choice
# (u = i) and the package default.

# %%
phi = np.linspace(-np.pi, np.pi, 73)
P0, P2 = np.meshgrid(phi, phi, indexing="ij")
fam = jax.jit(pj.hermite_quintic)(p0, p1, d0, d1, jnp.asarray(P0), jnp.asarray(P2))
energy = np.asarray(fam.bending_energy())
default = float(c.bending_energy())
paper = float(pj.hermite_quintic(p0, p1, d0, d1, -np.pi / 2, -np.pi / 2, axis=[1.0, 0, 0]).bending_energy())
print(f"grid minimum {energy.min():.3f}, default {default:.3f}, paper's -pi/2 {paper:.3f}")
assert default <= 1.5 * energy.min()

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
    pts = np.asarray(c.position(t))
    ax[0].plot(pts[:, 0], pts[:, 1], label="default PH quintic")
    ax[0].plot(*np.asarray(c.control_points)[:, :2].T, "o--", color="0.6", label="control polygon")
    ax[0].legend()
    ax[0].set_aspect("equal")
    im = ax[1].pcolormesh(phi, phi, np.log10(energy).T, shading="auto")
    fig.colorbar(im, ax=ax[1], label="log10 bending energy")
    ax[1].set_xlabel("phi0")
    ax[1].set_ylabel("phi2")
    os.makedirs(out, exist_ok=True)
    fig.savefig(os.path.join(out, "ph_anatomy.png"), dpi=100)
    if in_jupyter:
        from IPython.display import Image, display

        for name in ("ph_anatomy.png",):
            display(Image(os.path.join(out, name)))
