"""Evaluation: metrics against ground truth, and the comparison of phjax with its baselines.

* :mod:`~phjax.evaluation.metrics`: RMSE (position, rotation), RMS jerk, curvature / torsion,
  velocity jumps, latency (velocity cross-correlation) and lag (shift minimising the RMSE).
* :mod:`~phjax.evaluation.report`: simulate a sensor on a ground-truth recording, run phjax and
  every baseline, score them, print the table and draw the figure (the ``phjax demo`` /
  ``phjax evaluate`` job).
* :mod:`~phjax.evaluation.display`: what a user chooses between at the display time (a
  lookahead): phjax, and each predictor at its tuned knob and as smooth as phjax (the frontier).
"""

from .display import compare_at_display, format_choices, plot_choices
from .metrics import (
    Lag,
    Latency,
    Metric,
    evaluate,
    latency,
    max_angular_velocity_jump,
    max_velocity_jump,
    mean_abs_curvature,
    mean_abs_torsion,
    position_rmse,
    rms_jerk_position,
    rms_jerk_rotation,
    rotation_rmse_deg,
    shift_lag,
)
from .report import (
    TUNED,
    EvaluationResult,
    Method,
    default_methods,
    evaluate_recording,
    format_table,
    plot_evaluation,
)

__all__ = [
    "TUNED",
    "EvaluationResult",
    "Lag",
    "Latency",
    "Method",
    "Metric",
    "compare_at_display",
    "default_methods",
    "evaluate",
    "evaluate_recording",
    "format_choices",
    "format_table",
    "latency",
    "max_angular_velocity_jump",
    "max_velocity_jump",
    "mean_abs_curvature",
    "mean_abs_torsion",
    "plot_choices",
    "plot_evaluation",
    "position_rmse",
    "rms_jerk_position",
    "rms_jerk_rotation",
    "rotation_rmse_deg",
    "shift_lag",
]
