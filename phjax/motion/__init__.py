"""Motion: synthetic head motion, the simulated pose sensor, and resampling of trajectories.

* :mod:`~phjax.motion.simulate`: ``synthetic_head_motion`` (a neck-pivot head model) and
  ``SensorModel`` / ``simulate_measurements`` (camera rate, noise, dropouts, jitter).
* :mod:`~phjax.motion.resample`: pose interpolation at arbitrary times (linear / slerp, gap
  aware) and finite-difference velocities.
"""

from .resample import finite_difference_velocities, interpolate_poses, snap_to_frames, valid_rows
from .simulate import SensorModel, simulate_measurements, synthetic_head_motion

__all__ = [
    "SensorModel",
    "finite_difference_velocities",
    "interpolate_poses",
    "simulate_measurements",
    "snap_to_frames",
    "synthetic_head_motion",
    "valid_rows",
]
