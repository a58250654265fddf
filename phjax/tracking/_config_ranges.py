"""The range of each float field of a :class:`phjax.TrackerConfig` (one table for configuration
files and for configurations built in Python).

Beyond these ranges the float32 stream overflows or underflows to NaN poses (measured field by
field); a value inside them may still be a bad choice, but it is a finite one.
:func:`phjax.tracking.tuning.load_config` refuses a file whose values lie outside them, and
:func:`phjax.track`, :func:`phjax.reconstruct` and :class:`phjax.TrackerStream` refuse such a
configuration (outside JAX transformations: traced values are the caller's to keep valid).
"""

from __future__ import annotations

import numpy as np

from .._misc import any_traced

#: Range ``(low, high)`` of each float field of a configuration file (``"imm.log_q"``: every
#: motion model's ``log_q``). Measured on the float32 stream: ten times beyond ``high`` (or
#: below ``low``) gives NaN poses for some field (e.g. a measurement std of 1e12, a horizon of
#: 1e30, ``log_q`` 60), at these bounds every field alone gives finite poses.
_POSITIVE = (1e-12, 1e6)
CONFIG_RANGES = {
    **{f"tracker.{n}": _POSITIVE for n in ("horizon", "rotation_horizon", "stop_time")},
    "tracker.coast_time": (0.0, 1e6),
    "tracker.lookahead": (-1e6, 1e6),
    "tracker.adapt": (-20.0, 20.0),
    "tracker.noise_window": (0, 1_000_000),
    **{f"kalman.{n}": _POSITIVE for n in (
        "pos_process_noise", "pos_meas_noise", "rot_process_noise", "rot_meas_noise",
        "init_pos_vel_std", "init_pos_acc_std", "init_rot_vel_std")},
    **{f"imm.{n}": _POSITIVE for n in (
        "pos_meas_noise", "rot_meas_noise", "init_pos_vel_std", "init_pos_acc_std",
        "init_rot_vel_std")},
    "imm.log_q": (-50.0, 50.0),
}


def out_of_range(config) -> list[tuple[str, str, object]]:
    """``(field, key, value)`` of every concrete float field of ``config`` (a
    :class:`phjax.TrackerConfig`) outside :data:`CONFIG_RANGES` (``key``: its entry there;
    ``field``: e.g. ``"tracker.horizon"``, ``"imm.position_models[1].log_q"``)."""
    found = []

    def check(field, key, value):
        if value is None or any_traced(value):
            return
        low, high = CONFIG_RANGES[key]
        x = np.asarray(value, np.float64)
        if not np.all((x >= low) & (x <= high)):  # NaN too
            found.append((field, key, value))

    imm = config.imm
    for key in CONFIG_RANGES:
        section, name = key.split(".")
        if section == "tracker":
            check(key, key, getattr(config, name))
        elif section == "kalman":
            check(key, key, getattr(config.kalman, name))
        elif imm is not None and name == "log_q":
            for group in ("position_models", "rotation_models"):
                for i, model in enumerate(getattr(imm, group)):
                    check(f"imm.{group}[{i}].log_q", key, model.log_q)
        elif imm is not None:
            check(key, key, getattr(imm, name))
    return found


def range_message(field: str, key: str, value) -> str:
    """The one-line reason of an :func:`out_of_range` entry."""
    low, high = CONFIG_RANGES[key]
    return (f"{field} = {value!r} is out of range [{low:g}, {high:g}] (beyond it the tracker "
            "fails or outputs NaN poses)")
