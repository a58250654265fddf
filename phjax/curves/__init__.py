"""Curves: the spatial Pythagorean-hodograph (PH) quintic and the curves built from it.

* :mod:`~phjax.curves.ph_quintic`: first-order Hermite PH quintics (``hermite_quintic``,
  ``PHQuintic``): closed-form arc length, curvature, torsion, bending energy and frames.
* :mod:`~phjax.curves.sampling`: batched sampling (uniform in parameter or arc length), into
  donated buffers, in chunks.
* :mod:`~phjax.curves.shape`: free-angle optimisation under curvature / torsion limits.
* :mod:`~phjax.curves.ph_spline`: the offline C2 PH quintic spline.
* :mod:`~phjax.curves.orientation`: C1 quaternion Hermite curves for orientation.
"""

from .orientation import QuaternionHermite, quaternion_hermite
from .ph_quintic import FrameKind, PHQuintic, hermite_quintic, near_optimal_angles
from typing import TYPE_CHECKING

from .._lazy import lazy_exports
from .ph_spline import SplineSolution, SplineStatus, ph_spline  # optimistix on first use
from .sampling import sample, sample_chunks, sample_into

if TYPE_CHECKING:  # imported on first use (optimistix), see phjax._lazy
    from .shape import Objective, ShapeSolution, ShapeStatus, grid_search_shape, optimize_shape

__getattr__, __dir__ = lazy_exports(__name__, {
    "shape": ("Objective", "ShapeSolution", "ShapeStatus", "grid_search_shape", "optimize_shape"),
})

__all__ = [
    "FrameKind",
    "Objective",
    "PHQuintic",
    "QuaternionHermite",
    "ShapeSolution",
    "ShapeStatus",
    "SplineSolution",
    "SplineStatus",
    "grid_search_shape",
    "hermite_quintic",
    "near_optimal_angles",
    "optimize_shape",
    "ph_spline",
    "quaternion_hermite",
    "sample",
    "sample_chunks",
    "sample_into",
]
