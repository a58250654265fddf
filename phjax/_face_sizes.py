"""Accepted assumed face sizes of the webcam front-end: one definition for
:class:`phjax.vision.monocular.MonocularHeadPose` and ``phjax live --head-size / --ipd``
(a module without imports, so that the command line's parser stays light). Values outside
are typing errors (millimetres, a missing decimal point) and gave inf / NaN poses."""

#: accepted assumed vertical head size, m
HEAD_SIZE_RANGE = (0.05, 0.5)
#: accepted assumed inter-pupillary distance, m
IPD_RANGE = (0.03, 0.1)
