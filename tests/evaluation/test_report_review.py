"""Bad input to evaluate_recording (phjax.evaluation.report): one clear error or warning each."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import phjax as pj
from phjax.evaluation import report
from phjax.evaluation.report import Method
from phjax.io import TrajectoryWarning


@pytest.fixture(scope="module")
def motion():
    # the size class of tests/evaluation/test_report.py (4 s at 120 Hz), whose programs it shares
    t, p, q = pj.synthetic_head_motion(duration=4.0, rate=120.0, seed=2)
    return np.asarray(t), np.asarray(p), np.asarray(q)


def _hold():
    return [m for m in report.default_methods() if m.name == "raw hold"]


@pytest.mark.parametrize("rate", [0.0, -10.0, float("nan"), float("inf")])
def test_render_rate_must_be_positive_and_finite(motion, rate):
    """0 Hz was a ZeroDivisionError (after simulating the sensor), -10 Hz "the recording is too
    short to evaluate: 4 s" (it is not), NaN / inf NumPy's "arange: cannot compute length" /
    "Maximum allowed size exceeded"."""
    with pytest.raises(ValueError, match=r"^render_rate must be a positive, finite rate in Hz, "
                       r"got (0.0|-10.0|nan|inf)$"):
        report.evaluate_recording(*motion, render_rate=rate, methods=_hold())


def test_no_methods_and_repeated_names_are_refused(motion):
    """``methods=[]`` printed a table without a row; two methods of one name kept only the
    second's metrics (the table has one row per name)."""
    with pytest.raises(ValueError, match="methods is empty"):
        report.evaluate_recording(*motion, methods=[])
    with pytest.raises(ValueError, match="method names must be unique; repeated: 'raw hold'"):
        report.evaluate_recording(*motion, methods=_hold() + _hold())


def test_a_method_of_the_wrong_shape_or_failing_is_named(motion):
    """A stream one row short was NumPy's "shape mismatch: (475, 3) vs (476, 3)" from the
    metrics, naming neither the method nor what was expected; an exception inside a method did
    not say which method raised."""
    def short(t, p, q, r):
        return np.zeros((r.size - 1, 3)), np.tile([1.0, 0, 0, 0], (r.size - 1, 1))

    with pytest.raises(ValueError, match=r"method 'short' returned positions of shape \(\d+, 3\)"
                       r" and quaternions of shape \(\d+, 4\); expected"):
        report.evaluate_recording(*motion, methods=[Method("short", short, True)])

    def boom(t, p, q, r):
        raise RuntimeError("kaboom")

    with pytest.raises(RuntimeError, match="kaboom") as info:
        report.evaluate_recording(*motion, methods=[Method("boom", boom, True)])
    assert "method 'boom'" in " ".join(getattr(info.value, "__notes__", []))


def test_a_nan_stream_is_said_and_the_table_still_renders(motion):
    """A method returning NaN everywhere gave a row of '-' and nothing else: no sign that the
    method, not the metric, failed. Now one warning names it and its columns."""
    def nan(t, p, q, r):
        return np.full((r.size, 3), np.nan), np.full((r.size, 4), np.nan)

    with pytest.warns(TrajectoryWarning, match=r"no sample scored \(shown as '-'\) for nan "
                      r"\(pos RMSE \[mm\], rot RMSE \[deg\], pos jerk"):
        res = report.evaluate_recording(*motion, methods=_hold() + [Method("nan", nan, True)])
    table = report.format_table(res.metrics, res.causal, res.baseline)
    assert "| nan | yes | - | - | - | - | - | - |" in table
    assert "| raw hold | yes | **" in table


def test_lags_of_a_short_recording_are_said(motion):
    """Just over the minimum (9 to 21 render samples, 0.1-0.2 s): RMSE and jerk are scored but
    no lag (the shift search spans 0.4 s), and the lag columns were '-' without a word; the
    too-short error even says "jerk and lag need 8" samples. A full recording warns nothing."""
    t, p, q = motion
    n = 25  # 0.2 s
    with pytest.warns(TrajectoryWarning, match=r"raw hold \(pos lag \[ms\], rot lag \[ms\]\); "
                      r"the lag search \(-100 to 300 ms\) needs more than 0.4 s"):
        res = report.evaluate_recording(t[:n], p[:n], q[:n], methods=_hold())
    assert np.isfinite(res.metrics["raw hold"]["position_rmse"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", TrajectoryWarning)
        report.evaluate_recording(t, p, q, methods=_hold())
