"""Does *non-linear* prediction beat the IMM at display-time horizons, on the development set?

    python experiments/nonlinear_predictor.py [--seconds 15] [--taps 12 24] [--seeds 3]
        [--out results/nonlinear_predictor] [--quick] [--noise-seed shared] [--draw K]

``docs/frontier.md`` shows that a C1 render stream is bounded by its predictor's error one camera
period (33 ms) plus the display lookahead ahead, that the IMM extrapolation would have to be some
4-7 % better for the product target, and (``predictor_bound.py``) that no linear predictor
fitted on train gets there. This study asks the same of small neural networks.

Protocol (the data, sensor, split and instants of ``predictor_bound.py``, whose functions it
imports): the first ``--seconds`` of each development recording, the default sensor (30 Hz,
5 mm, 1 deg, 5 % dropouts; a sensor seed per recording, ``--noise-seed`` and ``--draw`` as
there); recordings sorted by name, alternately train / test. At
every camera frame ``k`` (after a 1 s warm-up) whose last ``N`` frames all arrived, the target
is the ground truth ``h`` after the frame, as an offset from the newest measurement (position;
rotation in the world tangent space at the newest measurement, ``log(g q_k^-1)``). Horizons:
``h`` = one camera period + lookahead (33 + 0, 33 + 20, 33 + 50 ms: what a C1 stream shows at a
frame's instant), and the render phases 0-3 at lookahead 0 (0-25 ms, as in
``predictor_bound.py``). The filters are queried at ``mt[k]`` with ``lookahead = h``, so a
prediction past the next frame never sees it (for ``h`` < 33 ms this equals
``predictor_bound.extrapolations``, which is used there).

Predictors, each scored at the same instants:

* **Kalman CV** (tuned, :data:`phjax.tracking.baselines.TUNED`) and **IMM** (default
  :class:`~phjax.tracking.imm.IMMConfig`) extrapolation: the references.
* **FIR (train)**: ``predictor_bound``'s least-squares FIR on the ``N - 1`` lag offsets (one
  weight per tap for all axes), fitted on all train recordings, each weighted by the inverse of
  its Kalman CV error.
* **FIR + IMM (train)**: the same with the IMM's predicted offset as an extra tap (linear
  stacking: the control for the residual network).
* **MLP**: a small network on the lag offsets, made rotation-equivariant by expressing them in a
  frame built from the window itself (``e1`` along the least-squares velocity of the last 4
  frames, ``e2`` along the part of the quadratic-fit acceleration of the last 6 frames
  orthogonal to it, ``e3 = e1 x e2``) and scale-normalised by their RMS ``s`` (plus the sensor
  noise); inputs ``R^T X / s`` and ``log(s / sigma)``, output the offset in that frame
  divided by ``s``; a linear skip plus two GELU layers of :data:`HIDDEN` units.
* **MLP residual on IMM**: the same network with the IMM's predicted offset (in the frame,
  divided by ``s``) as three more inputs; its output is a correction added to the IMM's offset
  (zero-initialised last layers: it starts *as* the IMM).

Training (fixed before looking at any result; nothing is tuned on test): the train recordings
only; the last quarter of each train recording's instants is the validation part (a gap of
``N + 3`` frames before it, so no window straddles), the rest is fitted. Loss: squared offset
error in physical units, each recording weighted by the inverse square of its Kalman CV error
(the FIR's weighting). Adam (:data:`LR`), minibatches of :data:`BATCH`, at most
:data:`MAX_STEPS` steps; the validation loss every :data:`EVAL_EVERY` steps, stop after
:data:`PATIENCE` evaluations without improvement and keep the best parameters (step 0
included). Seeds 0 .. ``--seeds - 1`` (initialisation and minibatches). One change after a
first run: the evaluation period was 100 steps there, but the validation loss (train split)
bottomed out at 40-300 steps and the stopping steps were mostly 0-200, so it is 10 steps now
(patience 30 evaluations = 300 steps; it was 10 x 100 = 1000); nothing else was changed. The
FIRs have no stopping rule and are fitted on all train instants, the networks on the fitted
three quarters. The references keep their 0-lookahead settings at every horizon (as
``predictor_bound.py``; ``display_frontier.py`` re-tunes them per lookahead).

Scores: per-recording RMSE (position mm; rotation deg, the angle between the predicted and true
orientation, for every method); medians over recordings of per-recording RMSE ratios against
the Kalman CV and the IMM, per split. Network rows give mean +- standard deviation over seeds
of that median. Outputs in ``--out``: ``nonlinear_predictor.md`` (tables, sample and parameter
counts, the early-stopping steps) and ``nonlinear_predictor.csv`` (every recording, method and
seed).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

sys.path.insert(0, str(Path(__file__).resolve().parent))
from devset import add_sensor_arguments, sensor_note  # noqa: E402
from predictor_bound import (  # noqa: E402  (also enables jax x64)
    RATE,
    RENDER,
    extrapolations,
    fit_fir,
    lag_features,
    prepare,
    rotation_features,
)

from phjax._np_quat import np_from_rotvec, np_qconj, np_qmul, np_rotvec  # noqa: E402
from phjax.motion.resample import interpolate_poses  # noqa: E402
from phjax.motion.simulate import SensorModel  # noqa: E402
from phjax.tracking import baselines  # noqa: E402

#: Hidden layer widths of the networks.
HIDDEN = (32, 32)
#: Adam learning rate, minibatch size, step limit, evaluation period and patience (evaluations).
LR, BATCH, MAX_STEPS, EVAL_EVERY, PATIENCE = 1e-3, 256, 6000, 10, 30
#: Fraction of each train recording's instants (the last ones) used for early stopping.
VAL_FRACTION = 0.25
#: Warm-up before the first scored frame, s (as ``predictor_bound.measure``).
WARMUP = 1.0
#: Lookaheads (ms) added to one camera period, and the render phases (at lookahead 0).
LOOKAHEADS_MS = (0.0, 20.0, 50.0)
PHASES = (0, 1, 2, 3)
CHANNELS = ("position", "rotation")
METHODS = ("kalman_cv", "imm", "fir", "fir_imm", "mlp", "mlp_residual")
NETS = ("mlp", "mlp_residual")


@dataclass(frozen=True)
class Horizon:
    """A prediction horizon: ``phase`` render periods plus ``lookahead`` s after the frame."""

    label: str
    seconds: float
    phase: int | None  # render phase (h < one camera period), else None


def horizons(quick: bool) -> list[Horizon]:
    """The camera-period horizons (33 ms + lookahead) and, unless ``quick``, the render phases."""
    out = [Horizon(f"33+{la:g} ms", 1.0 / RATE + la / 1e3, None) for la in LOOKAHEADS_MS]
    if quick:
        return out[:2]
    return out + [Horizon(f"phase {p} ({1e3 * p / RENDER:.1f} ms)", p / RENDER, p)
                  for p in PHASES]


# ------------------------------------------------------------------------------------------------
# data: targets, references and features
# ------------------------------------------------------------------------------------------------


def extrapolations_ahead(d: dict, hz: Horizon):
    """Ground truth ``h`` after every frame and the Kalman CV / IMM predictions for it from the
    state at that frame: ``((gp, gq), (kp, kq), (ip, iq))``. Render phases use
    ``predictor_bound.extrapolations``; longer horizons query the filters at the frame with
    ``lookahead = h`` (a render time at ``mt + h`` would already see the next frame)."""
    if hz.phase is not None:
        return extrapolations(d, hz.phase)
    args = (d["mt"], d["mp"], d["mq"], d["mt"])
    return tuple(tuple(np.asarray(x) for x in pair) for pair in (
        interpolate_poses(d["t"], d["p"], d["q"], d["mt"] + hz.seconds),
        baselines.kalman_extrapolation(*args, lookahead=hz.seconds),
        baselines.imm_extrapolation(*args, lookahead=hz.seconds)))


@dataclass
class Samples:
    """One recording's scored instants for one channel and horizon.

    ``x``: lag offsets ``(m, 3, N - 1)``; ``y``: true offset ``(m, 3)``; ``imm`` / ``kf``: the
    references' predicted offsets ``(m, 3)``; ``base``: the newest measurement ``(m, 3)`` or
    ``(m, 4)``; ``truth``: the true pose at ``t_k + h``; ``k``: frame indices."""

    rec: int
    channel: str
    k: np.ndarray
    x: np.ndarray
    y: np.ndarray
    imm: np.ndarray
    kf: np.ndarray
    base: np.ndarray
    truth: np.ndarray

    @property
    def train(self) -> bool:
        """The alternate split of ``predictor_bound``: even recordings (by name) train."""
        return self.rec % 2 == 0


def _rot_offset(q: np.ndarray, base: np.ndarray) -> np.ndarray:
    """World tangent offset ``log(q base^-1)``."""
    return np_rotvec(np_qmul(q, np_qconj(base)))


def collect(data: list[dict], taps: int, hz: Horizon) -> list[Samples]:
    """:class:`Samples` of every recording and channel at horizon ``hz`` (the filters' outputs are
    cached in each recording's dict)."""
    out = []
    for i, d in enumerate(data):
        key = ("ahead", hz.label)
        if key not in d:
            d[key] = extrapolations_ahead(d, hz)
        (gp, gq), (kp, kq), (ip, iq) = d[key]
        first = int(np.searchsorted(d["mt"], d["mt"][0] + WARMUP))
        if d["has_pos"]:
            k, x = lag_features(d["mp"], np.isfinite(d["mp"]).all(-1), taps, first)
            keep = np.isfinite(gp[k]).all(-1) & np.isfinite(ip[k]).all(-1)
            k, x, b = k[keep], x[keep], d["mp"][k[keep]]
            out.append(Samples(i, "position", k, x, gp[k] - b, ip[k] - b, kp[k] - b, b, gp[k]))
        k, x = rotation_features(d["mq"], np.isfinite(d["mq"]).all(-1), taps, first)
        keep = np.isfinite(gq[k]).all(-1) & np.isfinite(iq[k]).all(-1)
        k, x, b = k[keep], x[keep], d["mq"][k[keep]]
        out.append(Samples(i, "rotation", k, x, _rot_offset(gq[k], b), _rot_offset(iq[k], b),
                           _rot_offset(kq[k], b), b, gq[k]))
    return out


def rmse(s: Samples, offset: np.ndarray) -> float:
    """RMSE of a predicted offset ``(m, 3)``: mm (position) or deg (angle between orientations)."""
    if s.channel == "position":
        e = np.linalg.norm(s.base + offset - s.truth, axis=-1) * 1e3
    else:
        pred = np_qmul(np_from_rotvec(offset), s.base)
        e = np.degrees(np.linalg.norm(np_rotvec(np_qmul(pred, np_qconj(s.truth))), axis=-1))
    return float(np.sqrt(np.mean(e * e)))


def local_frame(x: np.ndarray) -> np.ndarray:
    """Rotation ``R (m, 3, 3)`` (columns ``e1, e2, e3``) of each window ``x (m, 3, N - 1)``:
    ``e1`` along the least-squares velocity of the last 4 frames, ``e2`` along the orthogonal
    part of the quadratic-fit acceleration of the last ``min(N, 6)`` frames. Equivariant:
    rotating the window rotates the frame."""
    pts = np.concatenate([np.zeros(x.shape[:2] + (1,)), x], axis=-1)  # offsets at t = 0, -1, ..
    t = -np.arange(pts.shape[-1], dtype=float)
    m = min(pts.shape[-1], 6)
    design = np.stack([np.ones(m), t[:m], t[:m] ** 2], axis=1)
    acc = pts[..., :m] @ np.linalg.pinv(design)[2]  # (n, 3)
    tv = t[:4] - t[:4].mean()
    vel = pts[..., :4] @ (tv / np.sum(tv * tv))
    e1 = _unit(vel, np.array([1.0, 0.0, 0.0]))
    e2 = _unit(acc - np.sum(acc * e1, -1, keepdims=True) * e1, None, e1)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=-1)


def _unit(v: np.ndarray, fallback: np.ndarray | None, e1: np.ndarray | None = None) -> np.ndarray:
    """Unit vectors of ``v``; degenerate rows get ``fallback`` or a vector orthogonal to ``e1``."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if fallback is None:
        alt = np.cross(e1, np.where(np.abs(e1[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        alt /= np.linalg.norm(alt, axis=-1, keepdims=True)
    else:
        alt = np.broadcast_to(fallback, v.shape)
    return np.where(n > 1e-12, v / np.where(n > 0, n, 1.0), alt)


def net_inputs(s: Samples, residual: bool, sigma: float):
    """Network inputs and target scaling of one recording: ``(z, frame, scale)``, ``z (m, F)``
    the lag offsets in the local frame over ``scale``, ``log(scale / sigma)`` and (``residual``)
    the IMM's offset in the frame over ``scale``."""
    frame = local_frame(s.x)
    scale = np.sqrt(np.mean(s.x ** 2, axis=(1, 2))) + sigma
    local = np.einsum("nab,nat->nbt", frame, s.x) / scale[:, None, None]
    parts = [local.reshape(len(scale), -1), np.log(scale / sigma)[:, None]]
    if residual:
        parts.append(np.einsum("nab,na->nb", frame, s.imm) / scale[:, None])
    return np.concatenate(parts, axis=1), frame, scale


def net_target(s: Samples, residual: bool, frame: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """What the network outputs for ``s``: the true offset (less the IMM's, if ``residual``) in
    the local frame, over ``scale``."""
    y = s.y - s.imm if residual else s.y
    return np.einsum("nab,na->nb", frame, y) / scale[:, None]


def net_offset(s: Samples, residual: bool, out: np.ndarray, frame: np.ndarray,
               scale: np.ndarray) -> np.ndarray:
    """Predicted offset in the world from the network output ``out (m, 3)``."""
    offset = np.einsum("nab,nb->na", frame, out) * scale[:, None]
    return s.imm + offset if residual else offset


# ------------------------------------------------------------------------------------------------
# the network
# ------------------------------------------------------------------------------------------------

Params = dict[str, list[tuple[jax.Array, jax.Array]] | jax.Array]


def init_params(key: jax.Array, n_in: int, hidden: tuple[int, ...] = HIDDEN) -> Params:
    """MLP ``n_in -> hidden -> 3`` (LeCun-normal hidden layers, zero output layer) plus a
    zero linear skip ``n_in -> 3``: the network starts at a zero output."""
    sizes = (n_in,) + hidden
    keys = jax.random.split(key, len(hidden))
    layers = [(jax.random.normal(k, (a, b)) / math.sqrt(a), jnp.zeros(b))
              for k, a, b in zip(keys, sizes[:-1], sizes[1:])]
    layers.append((jnp.zeros((sizes[-1], 3)), jnp.zeros(3)))
    return {"layers": layers, "skip": jnp.zeros((n_in, 3))}


def n_params(p: Params) -> int:
    """Number of scalar parameters."""
    return int(sum(x.size for x in jax.tree_util.tree_leaves(p)))


def apply(p: Params, z: jax.Array) -> jax.Array:
    """Network output ``(m, 3)`` for standardised inputs ``z (m, F)``."""
    h = z
    for w, b in p["layers"][:-1]:
        h = jax.nn.gelu(h @ w + b)
    w, b = p["layers"][-1]
    return h @ w + b + z @ p["skip"]


def _loss(p: Params, z, y, w) -> jax.Array:
    """Weighted mean squared error (``w`` already holds the scale and recording weights)."""
    return jnp.mean(w * jnp.sum((apply(p, z) - y) ** 2, axis=-1))


_OPT = optax.adam(LR)


@jax.jit
def _train_chunk(p: Params, state, key: jax.Array, z, y, w):
    """:data:`EVAL_EVERY` Adam steps on random minibatches of ``(z, y, w)``."""
    def step(carry, k):
        p, state = carry
        idx = jax.random.randint(k, (BATCH,), 0, z.shape[0])
        g = jax.grad(_loss)(p, z[idx], y[idx], w[idx])
        upd, state = _OPT.update(g, state, p)
        return (optax.apply_updates(p, upd), state), None

    (p, state), _ = jax.lax.scan(step, (p, state), jax.random.split(key, EVAL_EVERY))
    return p, state


_val_loss = jax.jit(_loss)


@dataclass
class Fitted:
    """A trained network: parameters, input standardisation, best step and validation loss."""

    params: Params
    mean: np.ndarray
    std: np.ndarray
    step: int
    val: float

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """Network output for raw inputs ``z``."""
        return np.asarray(apply(self.params, jnp.asarray((z - self.mean) / self.std)))


def train_net(seed: int, fit: tuple[np.ndarray, ...], val: tuple[np.ndarray, ...]) -> Fitted:
    """Adam with early stopping on ``val``; ``fit`` and ``val`` are ``(z, y, w)``, ``w`` the
    per-sample loss weights (normalised here by their mean over ``fit``)."""
    mean, std = fit[0].mean(0), fit[0].std(0) + 1e-9
    wscale = fit[2].mean()
    zf, yf, wf = (jnp.asarray(a) for a in ((fit[0] - mean) / std, fit[1], fit[2] / wscale))
    zv, yv, wv = (jnp.asarray(a) for a in ((val[0] - mean) / std, val[1], val[2] / wscale))
    key, init = jax.random.split(jax.random.key(seed))
    p = init_params(init, zf.shape[1])
    state = _OPT.init(p)
    best = (float(_val_loss(p, zv, yv, wv)), 0, p)
    bad = 0
    for step in range(EVAL_EVERY, MAX_STEPS + 1, EVAL_EVERY):
        key, sub = jax.random.split(key)
        p, state = _train_chunk(p, state, sub, zf, yf, wf)
        v = float(_val_loss(p, zv, yv, wv))
        if v < best[0]:
            best, bad = (v, step, p), 0
        else:
            bad += 1
            if bad >= PATIENCE:
                break
    return Fitted(best[2], mean, std, best[1], best[0])


# ------------------------------------------------------------------------------------------------
# the study
# ------------------------------------------------------------------------------------------------


def _split_fit_val(s: Samples, taps: int) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks of the fitted and validation instants of a train recording (the last
    :data:`VAL_FRACTION` of its instants, after a gap of ``taps + 3`` frames)."""
    cut = s.k[int(len(s.k) * (1.0 - VAL_FRACTION))]
    return s.k < cut - taps - 3, s.k >= cut


def measure(data: list[dict], taps: int, hz: Horizon, seeds: int,
            log: list[dict]) -> list[dict]:
    """Per recording, channel, method and seed, the RMSE at horizon ``hz`` (rows of the csv);
    appends each trained network's sample and parameter counts and stopping step to ``log``."""
    rows = []
    sensor = SensorModel()
    for ch in CHANNELS:
        mine = [s for s in collect(data, taps, hz) if s.channel == ch]
        train = [s for s in mine if s.train]
        if not train:
            continue
        kf_err = {s.rec: rmse(s, s.kf) for s in mine}
        rw = {s.rec: 1.0 / kf_err[s.rec] for s in mine}  # recording weight (as predictor_bound)
        w_fir = fit_fir([s.x for s in train], [s.y for s in train], [rw[s.rec] for s in train])
        w_stk = fit_fir([np.concatenate([s.x, s.imm[..., None]], -1) for s in train],
                        [s.y for s in train], [rw[s.rec] for s in train])
        preds: dict[tuple[str, int], dict[int, np.ndarray]] = {}
        for s in mine:
            preds.setdefault(("kalman_cv", -1), {})[s.rec] = s.kf
            preds.setdefault(("imm", -1), {})[s.rec] = s.imm
            preds.setdefault(("fir", -1), {})[s.rec] = s.x @ w_fir
            preds.setdefault(("fir_imm", -1), {})[s.rec] = (
                np.concatenate([s.x, s.imm[..., None]], -1) @ w_stk)
        sigma = sensor.sigma_p if ch == "position" else sensor.sigma_r
        counts = dict(
            fitted=int(sum(_split_fit_val(s, taps)[0].sum() for s in train)),
            validation=int(sum(_split_fit_val(s, taps)[1].sum() for s in train)),
            train=sum(len(s.k) for s in train), test=sum(len(s.k) for s in mine if not s.train))
        for net in NETS:
            residual = net == "mlp_residual"
            prepared = {s.rec: net_inputs(s, residual, sigma) for s in mine}
            parts = {"fit": [], "val": []}
            for s in train:
                z, frame, scale = prepared[s.rec]
                y = net_target(s, residual, frame, scale)
                w = (rw[s.rec] * scale) ** 2
                for name, m in zip(("fit", "val"), _split_fit_val(s, taps)):
                    parts[name].append((z[m], y[m], w[m]))
            fit, val = ([np.concatenate(c) for c in zip(*parts[n])] for n in ("fit", "val"))
            for seed in range(seeds):
                model = train_net(seed, fit, val)
                log.append(dict(channel=ch, taps=taps, horizon=hz.label, network=net, seed=seed,
                                params=n_params(model.params), step=model.step, **counts))
                for s in mine:
                    z, frame, scale = prepared[s.rec]
                    preds.setdefault((net, seed), {})[s.rec] = net_offset(
                        s, residual, model(z), frame, scale)
        for (method, seed), by_rec in preds.items():
            for s in mine:
                rows.append(dict(recording=data[s.rec]["name"],
                                 split="train" if s.train else "test", channel=ch, taps=taps,
                                 horizon=hz.label, horizon_ms=round(1e3 * hz.seconds, 2),
                                 method=method, seed=seed, n=len(s.k),
                                 rmse=rmse(s, by_rec[s.rec])))
    return rows


def _median_ratios(rows: list[dict], method: str, ref: str) -> list[float]:
    """Per seed, the median over recordings of ``rmse(method) / rmse(ref)``."""
    ref_err = {r["recording"]: r["rmse"] for r in rows if r["method"] == ref}
    out = []
    for seed in sorted({r["seed"] for r in rows if r["method"] == method}):
        ratios = [r["rmse"] / ref_err[r["recording"]] for r in rows
                  if r["method"] == method and r["seed"] == seed]
        out.append(float(np.median(ratios)))
    return out


def _fmt(values: list[float]) -> str:
    if not values:
        return "–"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{np.mean(values):.3f} ± {np.std(values, ddof=1):.3f}"


def summarise(rows: list[dict]) -> str:
    """Markdown tables: median ratios vs the Kalman CV and vs the IMM, per channel, taps,
    horizon and split."""
    order = {h: i for i, h in enumerate(dict.fromkeys(r["horizon"] for r in rows))}
    keys = sorted({(r["channel"], r["taps"], r["horizon"]) for r in rows},
                  key=lambda c: (c[0], c[1], order[c[2]]))
    out = []
    for ref, title in (("kalman_cv", "Kalman CV"), ("imm", "IMM")):
        methods = [m for m in METHODS if m != ref]
        out += [f"**Median per-recording RMSE ratio / {title}** (networks: mean ± sd over "
                "seeds)", "",
                "| channel | N | horizon | split | recs | median KF RMSE | "
                + " | ".join(methods) + " |", "|---" * (6 + len(methods)) + "|"]
        for ch, taps, hz in keys:
            for split in ("test", "train"):
                sel = [r for r in rows if (r["channel"], r["taps"], r["horizon"]) == (ch, taps, hz)
                       and r["split"] == split]
                kf = [r["rmse"] for r in sel if r["method"] == "kalman_cv"]
                unit = "mm" if ch == "position" else "deg"
                cells = [_fmt(_median_ratios(sel, m, ref)) for m in methods]
                out.append(f"| {ch} | {taps} | {hz} | {split} | {len(kf)} | "
                           f"{np.median(kf):.2f} {unit} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def summarise_training(log: list[dict]) -> str:
    """Markdown table of the trained networks: instants, parameters, stopping steps per seed."""
    out = ["| channel | N | horizon | network | train instants (fitted / validation) | "
           "test instants | parameters | best step per seed |", "|---" * 8 + "|"]
    groups: dict[tuple, list[dict]] = {}
    for e in log:
        groups.setdefault((e["channel"], e["taps"], e["horizon"], e["network"]), []).append(e)
    for (ch, taps, hz, net), es in groups.items():
        e = es[0]
        out.append(f"| {ch} | {taps} | {hz} | {net} | {e['train']} ({e['fitted']} / "
                   f"{e['validation']}) | {e['test']} | {e['params']} | "
                   + " / ".join(str(x["step"]) for x in es) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0, help="window per recording, s")
    ap.add_argument("--taps", type=int, nargs="+", default=[12, 24],
                    help="window lengths N (frames, >= 6)")
    ap.add_argument("--seeds", type=int, default=3, help="network seeds 0 .. SEEDS - 1")
    ap.add_argument("--out", default="results/nonlinear_predictor", help="output folder")
    ap.add_argument("--quick", action="store_true",
                    help="every third recording, 8 s, 33 + 0 / 20 ms only, one seed")
    add_sensor_arguments(ap)
    args = ap.parse_args(argv)
    if min(args.taps) < 6:
        ap.error("--taps must be at least 6")
    if args.quick:
        args.seconds, args.seeds = 8.0, 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = prepare(args.seconds, args.quick, args.noise_seed, args.draw)
    print(f"{len(data)} recordings", flush=True)
    rows, log = [], []
    for taps in args.taps:
        for hz in horizons(args.quick):
            rows += measure(data, taps, hz, args.seeds, log)
            print(f"taps {taps}, {hz.label} done ({time.perf_counter() - start:.0f} s)",
                  flush=True)
    with open(out / "nonlinear_predictor.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    table = summarise(rows)
    elapsed = time.perf_counter() - start
    report = (
        "# Non-linear prediction vs the IMM (median of per-recording RMSE ratios)\n\n"
        f"`python experiments/nonlinear_predictor.py --seconds {args.seconds:g} --taps "
        f"{' '.join(map(str, args.taps))} --seeds {args.seeds}"
        f"{' --quick' if args.quick else ''}`: {len(data)} recordings, {elapsed:.0f} s. "
        + sensor_note(args.noise_seed, args.draw) + "\n\n"
        + table + "\n**Networks** (fitted on the train recordings' fitted instants, stopped on "
        "their validation instants; best step 0 = the initial network: zero output, or the IMM "
        "itself for the residual)\n\n" + summarise_training(log) + "\n")
    (out / "nonlinear_predictor.md").write_text(report)
    print(table)
    print(f"{elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
