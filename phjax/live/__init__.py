"""Live tracking: a camera (or a recording) in, smooth render-rate poses out to opentrack / OSC.

* :mod:`~phjax.live._sources`: :func:`open_source` and the sources (synthetic head, RGB-D
  recordings, webcam / video files with a monocular head pose, RealSense, pose files).
* :mod:`~phjax.live._outputs`: :func:`open_output` (``opentrack://``, ``osc://``), the TUM log
  and :func:`opentrack_values` (opentrack's units and axis conventions).
* :mod:`~phjax.live._runner`: :class:`LiveTracker` (capture thread + render loop on absolute
  deadlines) and :class:`LiveStream` (the tracker stream with late measurements).
* :mod:`~phjax.live._udp`: :class:`UdpSource` (``udp://``: another tracker's opentrack UDP
  datagrams in) and :func:`opentrack_pose` (the inverse of :func:`opentrack_values`).
* :mod:`~phjax.live._worker`: :class:`WorkerSource`, a source's frames and vision front-end in
  a worker process (the default of :func:`open_source` for camera sources), so that they
  cannot hold the render loop.
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
from ._runner import MAX_RATE, LiveStream, LiveTracker, Sample, live_tracker_config
from ._sources import (
    Measurement,
    PoseReplaySource,
    RealSenseSource,
    RGBDReplaySource,
    Source,
    SourceError,
    SyntheticSource,
    VideoSource,
    frame_cache_dir,
    open_source,
)
from ._udp import UdpSource, opentrack_pose
from ._worker import WorkerSource

__all__ = [
    "MAX_RATE",
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
    "SyntheticSource",
    "TumLog",
    "UdpSource",
    "VideoSource",
    "VirtualClock",
    "WorkerSource",
    "frame_cache_dir",
    "live_tracker_config",
    "open_output",
    "open_source",
    "opentrack_pose",
    "opentrack_values",
]
