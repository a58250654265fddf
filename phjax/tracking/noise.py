"""Measurement noise of a pose recording, estimated from the recording itself.

The filters' measurement noise (``pos_meas_noise`` / ``rot_meas_noise`` of
:class:`~phjax.tracking.imm.IMMConfig` and :class:`~phjax.tracking.kalman.KalmanConfig`) defaults
to the default sensor (5 mm, 1 degree per axis). A different pose source (a SLAM system, another
tracker) has a different noise level; :func:`estimate_measurement_noise` measures it from the
samples and :func:`with_measurement_noise` puts it into a :class:`~phjax.tracking.tracker.TrackerConfig`.

**Procedure.** For every run of ``order + 1`` consecutive samples at times ``t_0 < ... < t_k``
(``k = order``, default 3), the divided-difference weights ``c_j = 1 / prod_{m != j} (t_j - t_m)``
annihilate every polynomial of degree ``< k`` (for ``k = 3``: constant-acceleration motion), on
any spacing of the times. Scaled to unit norm (``sum c_j^2 = 1``), the residual ``r = sum_j c_j x_j``
of white noise with std ``sigma`` per channel is ``N(0, sigma^2)`` exactly, so the bias correction
is only the Gaussian MAD constant: ``sigma_hat = 1.4826 * median |r - median r|``. The median
makes it robust to the few windows where the motion is not locally polynomial (impacts, gaps).
Orientations use the world-frame rotation vectors ``log(q_j q_ref^-1)`` (``q_ref`` the second
sample of the window), matching the noise model ``q_meas = exp(n) q_true`` of
:class:`~phjax.motion.simulate.SensorModel`. Windows with a NaN sample or non-increasing times
are left out (dropouts are not bridged).

What it measures is the *white* (sample-to-sample independent) part of the noise. Slowly
varying errors (SLAM drift) are removed by the difference like the motion, so they are not
counted; errors correlated over a few frames are counted only in part. For such a source the
estimate is a lower bound of a good ``pos_meas_noise``: on RGBDSLAM's estimate the default 5 mm
gives a lower APE than the estimated 1.46 mm (``docs/realstream.md``).
Remaining motion adds the unit-norm ``k``-th difference of the trajectory, on a uniform grid
``x^(k) dt^k / ||Delta^k||`` (for ``k = 3``: ``x''' dt^3 / sqrt(20)``), negligible for head or
hand-held camera motion at 30 Hz (a jerk of 10 m/s^3 gives 0.08 mm).

Measured (``experiments/real_stream.py``, ``tests/tracking/test_noise.py``): on the default
simulated sensor it returns 5.06-5.29 mm / 0.91-1.01 deg (4 seeds), and the stream with it is
within 0.2 % of the default config's RMSE; on RGBDSLAM's fr1_xyz estimate 1.46 mm / 0.075 deg
(a maximum-likelihood fit of the IMM's innovations gives a similar 2.0 mm / 0.080 deg), on the
motion-capture ground truth 0.083 mm / 0.036 deg.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .._jit import jit
from ..quaternion import quat_conj, quat_mul, quat_to_rotvec
from .tracker import TrackerConfig

__all__ = ["MeasurementNoise", "estimate_measurement_noise", "with_measurement_noise"]

_MAD_TO_STD = 1.482602218505602  # 1 / Phi^-1(3/4): MAD of N(0, 1)


class MeasurementNoise(eqx.Module):
    """Per-channel white measurement noise of a pose recording.

    Attributes:
        pos_std: position noise std per world axis, m, ``(3,)``.
        rot_std: orientation noise std per world axis (rotation vector), rad, ``(3,)``.
        pos_windows: number of position windows used (0: ``pos_std`` is NaN).
        rot_windows: number of orientation windows used (0: ``rot_std`` is NaN).
    """

    pos_std: Float[Array, " 3"]
    rot_std: Float[Array, " 3"]
    pos_windows: Int[Array, ""]
    rot_windows: Int[Array, ""]

    @property
    def pos_meas_noise(self) -> Float[Array, ""]:
        """Isotropic position std (RMS over the axes), m: the filters' ``pos_meas_noise``."""
        return jnp.sqrt(jnp.mean(self.pos_std**2))

    @property
    def rot_meas_noise(self) -> Float[Array, ""]:
        """Isotropic orientation std (RMS over the axes), rad: the filters' ``rot_meas_noise``."""
        return jnp.sqrt(jnp.mean(self.rot_std**2))


def _robust_std(res: Float[Array, "w c"], ok: Float[Array, " w"]) -> Float[Array, " c"]:
    """Gaussian-consistent MAD per column over the rows where ``ok`` (NaN if none)."""
    r = jnp.where(ok[:, None], res, jnp.nan)
    med = jnp.nanmedian(r, axis=0)
    return _MAD_TO_STD * jnp.nanmedian(jnp.abs(r - med), axis=0)


def estimate_measurement_noise(
    times: Float[ArrayLike, " n"],
    positions: Float[ArrayLike, "n 3"],
    quaternions: Float[ArrayLike, "n 4"],
    order: int = 3,
) -> MeasurementNoise:
    """Estimate the white measurement noise of a pose recording from the recording itself.

    Robust (MAD) std of the unit-norm divided differences of ``order + 1`` consecutive samples
    (see the module docstring for the procedure and its bias correction). Static shapes, ``jit``-
    and ``vmap``-able (``order`` static); NaN rows (dropouts) are skipped per part, so a recording
    with NaN positions still gives an orientation estimate.

    Arguments:
        times: sample times, s, increasing (NaN rows allowed).
        positions: positions, m, ``(n, 3)`` (NaN = missing).
        quaternions: orientations ``wxyz``, ``(n, 4)`` (NaN = missing).
        order: number of samples per window minus one; motion polynomials of degree
            ``< order`` are removed exactly (3: constant acceleration).

    Returns:
        :class:`MeasurementNoise` with per-axis stds and the window counts; a part with no
        complete window has NaN stds and count 0.

    Raises:
        ValueError: wrong shapes, ``order < 1`` or fewer than ``order + 1`` samples (checked on
            shapes only, so also under ``jit``).
    """
    t = jnp.asarray(times)
    p = jnp.asarray(positions)
    q = jnp.asarray(quaternions)
    if t.ndim != 1 or p.shape != (t.shape[0], 3) or q.shape != (t.shape[0], 4):
        raise ValueError(
            f"expected times (n,), positions (n, 3), quaternions (n, 4); got {t.shape}, "
            f"{p.shape}, {q.shape}")
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an integer >= 1, got {order!r}")
    n, k = t.shape[0], order
    if n < k + 1:
        raise ValueError(f"need at least order + 1 = {k + 1} samples, got {n}")
    dtype = jnp.result_type(t, p, q, jnp.float32)
    return _estimate(t.astype(dtype), p.astype(dtype), q.astype(dtype), k)


@functools.partial(jit, static_argnums=3)
def _estimate(t, p, q, k: int) -> MeasurementNoise:
    n, dtype = t.shape[0], t.dtype
    idx = jnp.arange(n - k)[:, None] + jnp.arange(k + 1)[None, :]  # (w, k+1)
    tw = t[idx] - t[idx[:, :1]]  # window-relative times (the weights use differences only)
    t_ok = jnp.all(jnp.isfinite(tw), axis=1) & jnp.all(jnp.diff(tw, axis=1) > 0, axis=1)
    tw = jnp.where(t_ok[:, None], tw, jnp.arange(k + 1, dtype=dtype))  # safe dummy spacing
    diff = tw[:, :, None] - tw[:, None, :]
    eye = jnp.eye(k + 1, dtype=bool)
    c = 1.0 / jnp.prod(jnp.where(eye, 1.0, diff), axis=-1)  # divided-difference weights
    c = c / jnp.linalg.norm(c, axis=1, keepdims=True)

    pw = p[idx]  # (w, k+1, 3)
    p_ok = t_ok & jnp.all(jnp.isfinite(pw), axis=(1, 2))
    res_p = jnp.einsum("wj,wjc->wc", c, jnp.where(p_ok[:, None, None], pw, 0))

    qw = q[idx]  # (w, k+1, 4)
    q_ok = t_ok & jnp.all(jnp.isfinite(qw), axis=(1, 2))
    qw = jnp.where(q_ok[:, None, None], qw, jnp.array([1, 0, 0, 0], dtype))
    qw = qw / jnp.linalg.norm(qw, axis=-1, keepdims=True)
    rv = quat_to_rotvec(quat_mul(qw, quat_conj(qw[:, 1:2, :])))  # world-frame, (w, k+1, 3)
    res_r = jnp.einsum("wj,wjc->wc", c, rv)

    return MeasurementNoise(
        pos_std=_robust_std(res_p, p_ok),
        rot_std=_robust_std(res_r, q_ok),
        pos_windows=jnp.sum(p_ok),
        rot_windows=jnp.sum(q_ok),
    )


def with_measurement_noise(
    config: TrackerConfig,
    noise: MeasurementNoise | None = None,
    *,
    pos: float | None = None,
    rot: float | None = None,
) -> TrackerConfig:
    """``config`` with the measurement noise of both filters (IMM and single-model) replaced.

    Arguments:
        config: the tracker configuration to start from.
        noise: an estimate from :func:`estimate_measurement_noise` (its RMS-over-axes stds).
        pos, rot: explicit position (m) / orientation (rad) stds; override ``noise``.

    Returns:
        A new :class:`~phjax.tracking.tracker.TrackerConfig` (the IMM part only if it has one).

    Raises:
        ValueError: a std that is not finite and positive (outside ``jit``).
    """
    if noise is not None:
        pos = float(noise.pos_meas_noise) if pos is None else pos
        rot = float(noise.rot_meas_noise) if rot is None else rot
    vals = {}
    for name, v in (("pos_meas_noise", pos), ("rot_meas_noise", rot)):
        if v is None:
            continue
        if not (jnp.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and positive, got {v}")
        vals[name] = v
    kalman = dataclasses.replace(config.kalman, **vals)
    imm = None if config.imm is None else dataclasses.replace(config.imm, **vals)
    return dataclasses.replace(config, kalman=kalman, imm=imm)
