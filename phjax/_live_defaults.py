"""Defaults of the live tracker shared by :func:`phjax.live.live_tracker_config` and
``phjax live``'s options (a module without imports, so that the command line's parser stays
light)."""

#: ``TrackerConfig.noise_window`` of live configs: a live source's noise is not known in advance
#: (a webcam, another tracker over UDP), so the filter's measurement noise is raised to what the
#: last ~2 s of frames show when that is more than the configured value
LIVE_NOISE_WINDOW = 60
