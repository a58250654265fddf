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
are left out (dropouts are not bridged), and so, for orientation, are windows with a zero
quaternion.

What it measures is the *white* (sample-to-sample independent) part of the noise. Slowly
varying errors (SLAM drift) are removed by the difference like the motion, so they are not
counted; errors correlated over a few frames are counted only in part. For such a source the
estimate is a lower bound of a good ``pos_meas_noise``: on RGBDSLAM's estimate the default 5 mm
gives a lower APE than the estimated 1.46 mm (``docs/frontier.md``, "Real SLAM stream").
Remaining motion adds the unit-norm ``k``-th difference of the trajectory, on a uniform grid
``x^(k) dt^k / ||Delta^k||`` (for ``k = 3``: ``x''' dt^3 / sqrt(20)``), negligible for head or
hand-held camera motion at 30 Hz (a jerk of 10 m/s^3 gives 0.08 mm).

The causal stream can also measure the noise as it runs: ``TrackerConfig(noise_window=n)``
computes the same residuals frame by frame (:mod:`phjax.tracking._noise_core`, shared with
this module) and raises the filters' measurement noise to their running winsorised RMS when it
exceeds the configured value (a floor, never lower: see the caveat above).

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
from .._misc import check_count
from ._noise_core import robust_std, window_residuals
from .tracker import TrackerConfig

__all__ = ["MeasurementNoise", "estimate_measurement_noise", "with_measurement_noise"]

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
    order = check_count(order, "order")
    n, k = t.shape[0], order
    if n < k + 1:
        raise ValueError(f"need at least order + 1 = {k + 1} samples, got {n}")
    dtype = jnp.result_type(t, p, q, jnp.float32)
    return _estimate(t.astype(dtype), p.astype(dtype), q.astype(dtype), k)


@functools.partial(jit, static_argnums=3)
def _estimate(t, p, q, k: int) -> MeasurementNoise:
    n = t.shape[0]
    idx = jnp.arange(n - k)[:, None] + jnp.arange(k + 1)[None, :]  # (w, k+1)
    res_p, p_ok, res_r, q_ok = window_residuals(t[idx], p[idx], q[idx])
    return MeasurementNoise(
        pos_std=robust_std(res_p, p_ok),
        rot_std=robust_std(res_r, q_ok),
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
