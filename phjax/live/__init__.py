"""Live tracking: a camera (or a recording) in, smooth render-rate poses out to opentrack / OSC.

* :mod:`~phjax.live._sources`: :func:`open_source` and the sources (synthetic head, RGB-D
  recordings, webcam / video files with a monocular head pose, RealSense, pose files).
* :mod:`~phjax.live._outputs`: :func:`open_output` (``opentrack://``, ``osc://``), the TUM log
  and :func:`opentrack_values` (opentrack's units and axis conventions).
* :mod:`~phjax.live._runner`: :class:`LiveTracker` (capture thread + render loop on absolute
  deadlines) and :class:`LiveStream` (the tracker stream with late measurements).
* :mod:`~phjax.live._clock`: :class:`RealClock` and the discrete-event :class:`VirtualClock`.

The command line is ``phjax live SOURCE --output URL ...``; see ``docs/live.md``.
"""

from ._clock import RealClock, VirtualClock
from ._outputs import (
    OPENTRACK_PORT,
    OSC_ADDRESS,
    OSC_PORT,
    OpenTrackOutput,
    OscOutput,
    Output,
    OutputError,
    TumLog,
    open_output,
    opentrack_values,
)
from ._runner import LiveStream, LiveTracker, Sample, live_tracker_config
from ._sources import (
    Measurement,
    PoseReplaySource,
    RealSenseSource,
    RGBDReplaySource,
    Source,
    SourceError,
    VideoSource,
    open_source,
)

__all__ = [
    "OPENTRACK_PORT",
    "OSC_ADDRESS",
    "OSC_PORT",
    "LiveStream",
    "LiveTracker",
    "Measurement",
    "OpenTrackOutput",
    "OscOutput",
    "Output",
    "OutputError",
    "PoseReplaySource",
    "RGBDReplaySource",
    "RealClock",
    "RealSenseSource",
    "Sample",
    "Source",
    "SourceError",
    "TumLog",
    "VideoSource",
    "VirtualClock",
    "live_tracker_config",
    "open_output",
    "open_source",
    "opentrack_values",
]
