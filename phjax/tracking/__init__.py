"""Tracking: from camera-rate poses to a smooth, predictive render-rate stream.

* :mod:`~phjax.tracking.kalman`: the pose Kalman filter (linear position filter, error-state
  orientation filter), RTS smoother, prediction.
* :mod:`~phjax.tracking.tracker`: the causal stream (``tracker_update`` / ``tracker_sample``),
  ``track`` (causal, whole recording) and ``reconstruct`` (offline).
* :mod:`~phjax.tracking.stream`: ``TrackerStream``, the real-time driver of the same stream.
* :mod:`~phjax.tracking.baselines`: the methods phjax is compared with (One Euro, hold, Kalman
  extrapolation, splines).
* :mod:`~phjax.tracking.tuning`: gradient tuning of the tracker on recordings.
"""

from .baselines import (
    TUNED,
    cubic_spline,
    hold,
    kalman_extrapolation,
    linear_slerp,
    one_euro,
    one_euro_numpy,
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
from .stream import TrackerStream
from .tracker import (
    TrackerConfig,
    TrackerState,
    reconstruct,
    track,
    tracker_config_arrays,
    tracker_init,
    tracker_sample,
    tracker_update,
)
from .tuning import TuningResult, load_config, save_config, tracker_loss, tune_tracker

__all__ = [
    "KalmanConfig",
    "KalmanInfo",
    "KalmanState",
    "TUNED",
    "TrackerConfig",
    "TrackerState",
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
]
