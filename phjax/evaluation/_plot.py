"""Small helpers shared by the evaluation figures."""

from __future__ import annotations

import numpy as np


def legend_on_first_labelled(axes, **kwargs) -> None:
    """Draw the legend on the first of ``axes`` that holds labelled artists (with
    orientation-only data the position panels are empty, and a legend there would only warn)."""
    for ax in np.ravel(axes):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(**kwargs)
            return
