"""Gradient-based tuning of the causal tracker: differentiate the whole stream, minimise with BFGS.

The causal stream of :func:`phjax.track` (a ``lax.scan`` of :func:`phjax.tracker_update` over
the camera frames, then :func:`phjax.tracker_sample` at the render times) is differentiable with
respect to every float leaf of :class:`phjax.TrackerConfig` that it uses: with the IMM filter
(the default) each motion model's log noise density, the log switch rate and the measurement
noise; with the single-model filter its noise densities and measurement noise; and for both the
segment ``horizon``, the coasting times and the initial stds. This module scores the stream on
recordings with known ground truth and tunes those leaves with ``optimistix.BFGS``
(:func:`tunable_parameters` lists them, :func:`default_parameters` gives the set tuned when
none is named).

**Data.** :func:`prepare_recordings` samples a ground-truth trajectory by a
:class:`phjax.SensorModel` with a fixed seed (so the loss is a deterministic, differentiable
function of the parameters), renders the stream at ``render_rate`` from the first valid frame
plus one camera period (as in :func:`phjax.evaluation.evaluate_recording`), and interpolates the
ground truth at the render times with :func:`phjax.motion.resample.interpolate_poses`
(samples inside ground-truth gaps longer than ``max_gt_gap`` are ignored; default
:func:`phjax.motion.resample.ground_truth_max_gap`: 0.1 s or 2.5 median ground-truth steps,
whichever is longer). :func:`tuning_data`
takes measurements that are already there instead (a real pose stream with its ground truth at
the render times; :func:`measured_recording` builds one from a recorded stream and its ground
truth, optionally aligning their frames) and does the rest, which both share: render samples
at a frame's instant see that frame (:func:`phjax.motion.resample.snap_to_frames`), times are
made relative to the first measurement and positions to the first ground-truth position (the
tracker is equivariant to both; this keeps float32 accurate), the reference stream below is
computed, and recordings are padded to common lengths (NaN frames after the end, masked render
samples) and stacked, so one compiled program serves them all (``jax.vmap``).

**Loss.** Per recording, four terms of the rendered stream (same definitions as
:mod:`phjax.evaluation.metrics`): position RMSE ``E_p`` (m), rotation RMSE ``E_r`` (geodesic angle, rad),
RMS position jerk ``J_p`` (m/s^3, six times the third divided difference of four consecutive
render samples) and RMS angular jerk ``J_r`` (rad/s^3, second difference of the midpoint
angular velocities). With ``normalize=True`` (default) each term is divided by the same term of
a reference stream on the same measurements, the Kalman constant-velocity extrapolation with the
tuned noise of :data:`phjax.tracking.baselines.TUNED` (:func:`phjax.tracking.baselines.kalman_extrapolation`), so
every term is dimensionless and ``lam`` is a pure trade-off weight::

    L_rec = [w_p (E_p / E_p_ref + lam J_p / J_p_ref) + w_r (E_r / E_r_ref + lam J_r / J_r_ref)]
            / (w_p + w_r)

and the loss is the mean of ``L_rec`` over recordings (orientation-only recordings have
``w_p = 0``). The reference baseline therefore scores exactly ``1 + lam``. With
``normalize=False`` the terms are in SI units (then ``lam`` has units and mixing position and
rotation is up to the weights).

**Parameters** are optimised in log space (``value = exp(y)``), which keeps them positive and
makes the problem scale free; leaves that are logarithms already (``log_*``: the IMM's model
densities ``log_q`` and ``log_switch_rate``), ``adapt`` and ``lookahead`` (any sign) are
optimised as they are. ``lookahead`` is not tuned by default: it is set from the display's
latency. Named in ``parameters`` it becomes the lead that best cancels the stream's lag against
the data's ground truth at the render times. Note that scaling all noise densities *and* measurement stds of
one channel by the same factor changes the filter only through the initial covariance, so
tuning process and measurement noise together leaves a nearly flat direction; BFGS copes, but
the individual values are less meaningful than their ratio.

Everything traced is NaN-safe: masked samples are replaced by finite values before any
arithmetic (double-``where`` pattern), so gradients are finite with dropped frames, render
times before the first measurement and ground-truth gaps. The code is dtype-generic:
``phjax tune`` works in float64 (``jax.config.update("jax_enable_x64", True)``), and in float32
(JAX's default) the loss terms of the IMM stream agree with float64 within 2e-5 and the
gradient within 1e-3, measured on 3 s and 30 s synthetic recordings (the 3 s case is tested;
times and positions are relative to each recording's start, which keeps the third differences
of the jerk terms accurate).

Cost: the first loss-and-gradient evaluation compiles the differentiated stream (the scan body
is large): for the single-model filter about 30 s of CPU in forward mode (the default), about
85 s in reverse mode; for the IMM filter about 40 s in forward mode (8 default parameters).
Later calls with the same data shapes and parameter names reuse it.
"""

# The implementation lives in private modules, one per job: _tuning_params (parameter names and
# paths), _tuning_data (recordings), _tuning_stream (the traceable stream and its metrics),
# _tuning_loss, _tuning_solve (problem and tune_tracker), _tuning_bfgs (the ask-tell BFGS driver)
# and _config_io (JSON). This module is the public face and keeps the documentation.
from ._config_io import (
    CONFIG_FORMAT,
    CONFIG_RANGES,
    CONFIG_VERSION,
    config_from_dict,
    config_to_dict,
    load_config,
    save_config,
)
from ._tuning_bfgs import _bfgs  # noqa: F401  (used by the tests)
from ._tuning_data import TuningData, measured_recording, prepare_recordings, tuning_data
from ._tuning_loss import loss_terms, tracker_loss
from ._tuning_params import (
    DEFAULT_PARAMETERS,
    check_parameters,
    default_parameters,
    tunable_parameters,
)
from ._tuning_solve import StepInfo, TuningProblem, TuningResult, make_problem, tune_tracker
from ._tuning_stream import stream_metrics

__all__ = [
    "DEFAULT_PARAMETERS",
    "CONFIG_FORMAT",
    "CONFIG_RANGES",
    "CONFIG_VERSION",
    "TuningData",
    "TuningProblem",
    "TuningResult",
    "StepInfo",
    "tunable_parameters",
    "default_parameters",
    "check_parameters",
    "prepare_recordings",
    "tuning_data",
    "measured_recording",
    "stream_metrics",
    "loss_terms",
    "tracker_loss",
    "make_problem",
    "tune_tracker",
    "config_to_dict",
    "config_from_dict",
    "save_config",
    "load_config",
]

