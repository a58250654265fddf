"""Tracking: from camera-rate poses to a smooth, predictive render-rate stream.

* :mod:`~phjax.tracking.imm`: the interacting-multiple-model pose filter over the motion models
  of :mod:`~phjax.tracking.models` (constant velocity / acceleration).
* :mod:`~phjax.tracking.kalman`: the pose Kalman filter (linear position filter, error-state
  orientation filter), RTS smoother, prediction.
* :mod:`~phjax.tracking.tracker`: the causal stream (``tracker_update`` / ``tracker_sample``),
  ``track`` (causal, whole recording) and ``reconstruct`` (offline).
* :mod:`~phjax.tracking.stream`: ``TrackerStream``, the real-time driver of the same stream.
* :mod:`~phjax.tracking.baselines`: the methods phjax is compared with (One Euro, hold, Kalman
  and IMM extrapolation, alpha-beta, LaViola's double exponential smoothing, splines).
* :mod:`~phjax.tracking.tuning`: gradient tuning of the tracker on recordings.
* :mod:`~phjax.tracking.noise`: measurement noise of a recording, estimated from the recording.
"""

from .baselines import (
    TUNED,
    alpha_beta,
    cubic_spline,
    double_exponential,
    hold,
    imm_extrapolation,
    kalman_extrapolation,
    linear_slerp,
    one_euro,
    one_euro_extrapolation,
    one_euro_numpy,
    snapshot_interpolation,
)
from .imm import (
    IMMConfig,
    IMMInfo,
    IMMState,
    imm_estimate,
    imm_filter,
    imm_init,
    imm_predict_pose,
    imm_step,
    imm_uninitialized,
)
from .kalman import (
    KalmanConfig,
    KalmanInfo,
    KalmanState,
    kalman_filter,
    kalman_init,
    kalman_predict,
    kalman_step,
    kalman_update,
    predict_pose,
    rts_smooth,
)
from .models import ConstantAcceleration, ConstantVelocity
from .noise import MeasurementNoise, estimate_measurement_noise, with_measurement_noise
from .stream import TrackerStream
from .tracker import (
    RenderSegment,
    TrackerConfig,
    TrackerState,
    reconstruct,
    track,
    tracker_config_arrays,
    tracker_init,
    tracker_sample,
    tracker_update,
)
from typing import TYPE_CHECKING

from .._lazy import lazy_exports

if TYPE_CHECKING:  # imported on first use (optimistix), see phjax._lazy
    from .tuning import (
        TuningResult,
        default_parameters,
        load_config,
        save_config,
        tracker_loss,
        tunable_parameters,
        tune_tracker,
    )

__getattr__, __dir__ = lazy_exports(__name__, {
    "tuning": ("TuningResult", "default_parameters", "load_config", "save_config",
               "tracker_loss", "tunable_parameters", "tune_tracker"),
})

__all__ = [
    "MeasurementNoise",
    "estimate_measurement_noise",
    "with_measurement_noise",
    "ConstantAcceleration",
    "ConstantVelocity",
    "IMMConfig",
    "IMMInfo",
    "IMMState",
    "alpha_beta",
    "double_exponential",
    "imm_estimate",
    "imm_extrapolation",
    "imm_filter",
    "imm_init",
    "imm_predict_pose",
    "imm_step",
    "imm_uninitialized",
    "one_euro_extrapolation",
    "snapshot_interpolation",
    "KalmanConfig",
    "KalmanInfo",
    "KalmanState",
    "TUNED",
    "TrackerConfig",
    "TrackerState",
    "RenderSegment",
    "TrackerStream",
    "TuningResult",
    "cubic_spline",
    "hold",
    "kalman_extrapolation",
    "kalman_filter",
    "kalman_init",
    "kalman_predict",
    "kalman_step",
    "kalman_update",
    "linear_slerp",
    "load_config",
    "one_euro",
    "one_euro_numpy",
    "predict_pose",
    "reconstruct",
    "rts_smooth",
    "save_config",
    "track",
    "tracker_config_arrays",
    "tracker_init",
    "tracker_loss",
    "tracker_sample",
    "tracker_update",
    "tune_tracker",
    "tunable_parameters",
    "default_parameters",
]
