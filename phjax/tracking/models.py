"""Motion models of the interacting-multiple-model filter (:mod:`phjax.tracking.imm`).

A model is an equinox Module holding the **logarithm** of the spectral density of its white
driving noise (so that gradient-based tuning stays in the positive range and its steps are
relative). Two models, per axis, as in :mod:`phjax.tracking.kalman`:

* :class:`ConstantVelocity`: state ``[p, v]``, white acceleration of density ``q`` [m^2/s^3]
  (position) or white angular acceleration [rad^2/s^3] (orientation, error state).
* :class:`ConstantAcceleration`: state ``[p, v, a]``, white jerk of density ``q`` [m^2/s^5]
  (position only).

An IMM mixes states of one common layout, so :meth:`position_matrices` returns the model's
transition and process noise embedded in a state of ``order`` derivatives (``order`` at least the
model's): the derivatives a model does not carry are set to zero with zero noise (the usual
state augmentation of CV inside a CV/CA IMM).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._misc import check_number_fields
from .kalman import _pos_matrices

__all__ = ["ConstantAcceleration", "ConstantVelocity", "MotionModel"]


class _Model(eqx.Module):
    log_q: float

    order: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        # (a NaN log_q gave NaN poses, silently; log_q = 100 overflows exp in float32)
        check_number_fields(self, (("log_q", lambda x: np.abs(x) <= 80, " within +-80"),))

    @property
    def q(self) -> Float[Array, ""]:
        """Spectral density of the driving noise, ``exp(log_q)``."""
        return jnp.exp(jnp.asarray(self.log_q))

    def position_matrices(
        self, dt: Float[ArrayLike, ""], order: int | None = None
    ) -> tuple[Float[Array, "n n"], Float[Array, "n n"]]:
        """Transition ``F`` and process noise ``Q`` of the 3-D position state.

        Arguments:
            dt: time step, s (``>= 0``).
            order: derivatives in the (common) state, at least ``self.order``; default
                ``self.order``. Layout by derivative: ``[p, v, (a)]``, 3 entries each.

        Returns:
            ``(F, Q)``, each ``(3 order, 3 order)``.
        """
        order = self.order if order is None else order
        if order < self.order:
            raise ValueError(f"state order {order} < model order {self.order}")
        dt = jnp.asarray(dt)
        f1, q1 = _pos_matrices(self.order, dt)
        pad = order - self.order
        f1 = jnp.pad(f1, ((0, pad), (0, pad)))
        q1 = jnp.pad(q1, ((0, pad), (0, pad)))
        eye = jnp.eye(3, dtype=dt.dtype)
        return jnp.kron(f1, eye), self.q.astype(dt.dtype) * jnp.kron(q1, eye)


class ConstantVelocity(_Model):
    """Constant velocity, white acceleration noise.

    Fields:
        log_q: natural log of the acceleration spectral density (m^2/s^3 for position,
            rad^2/s^3 for orientation).
    """

    order: int = eqx.field(static=True, default=2)

    @classmethod
    def from_q(cls, q: float) -> "ConstantVelocity":
        """The model with spectral density ``q`` (> 0)."""
        return cls(log_q=_log_q(q))


class ConstantAcceleration(_Model):
    """Constant acceleration, white jerk noise (position only).

    Fields:
        log_q: natural log of the jerk spectral density, m^2/s^5.
    """

    order: int = eqx.field(static=True, default=3)

    @classmethod
    def from_q(cls, q: float) -> "ConstantAcceleration":
        """The model with spectral density ``q`` (> 0)."""
        return cls(log_q=_log_q(q))


def _log_q(q) -> float:
    if not (isinstance(q, (int, float)) and math.isfinite(q) and q > 0):
        raise ValueError(f"a spectral density q must be a finite number > 0, got {q!r}")
    return math.log(q)


MotionModel = ConstantVelocity | ConstantAcceleration
