"""phjax.evaluation.display: the equal-smoothness search and the tables (no tracking run)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from phjax.evaluation.display import (
    KNOB_BASELINES,
    Choice,
    DisplayComparison,
    KnobBaseline,
    _as_smooth,
    _scaled_imm,
    format_choices,
    plot_choices,
)
from phjax.tracking.imm import IMMConfig


def _fake(jerk_p, jerk_r, bounds=(1e-4, 1e3)):
    """A baseline whose 'stream' is its knobs: jerk per channel from the given functions, the
    RMSE falling as the knob grows (a jerkier filter follows better)."""
    b = KnobBaseline("fake", "k", (1.0, 1.0), bounds, lambda kp, kr, L: (kp, kr))

    def evaluate(knobs):
        kp, kr = knobs
        return {"jerk_position": jerk_p(kp), "jerk_rotation": jerk_r(kr),
                "position_rmse": 1.0 / (1 + kp), "rotation_rmse_deg": 1.0 / (1 + kr)}

    return b, evaluate


@pytest.mark.parametrize("targets", [(30.0, 700.0), (2.0, 0.1), (99.0, 101.0)])
def test_as_smooth_on_monotonic_power_laws(targets):
    b, evaluate = _fake(lambda k: 100 * k**0.5, lambda k: 100 * k**0.8)
    sweep = []
    (kp, kr), reached = _as_smooth(b, 0.0, evaluate, {"position": targets[0],
                                                          "rotation": targets[1]}, sweep)
    assert reached == (True, True)
    # the lowest RMSE at most that jerky is at the crossing; a power law is a straight line in
    # log-log, so regula falsi lands on it
    assert kp == pytest.approx((targets[0] / 100) ** 2, rel=1e-9)
    assert kr == pytest.approx((targets[1] / 100) ** (1 / 0.8), rel=1e-9)
    assert len(sweep) <= 9 + 2 * 2  # the log grid, then a few refinements per channel


def test_as_smooth_on_a_u_shaped_jerk():
    """An extrapolator's jerk falls, then rises again as its filter gets smoother: the knob is
    the most accurate of those at most as jerky as the target (the jerkier crossing here), and
    a target below the minimum is never reached (the smoothest knob is returned)."""
    b, evaluate = _fake(lambda k: 100 * (k + 1 / k), lambda k: 100 * (k + 1 / k), (1e-2, 1e2))
    (kp, kr), reached = _as_smooth(b, 0.0, evaluate, {"position": 150.0, "rotation": 500.0}, [])
    assert reached == (False, True)
    assert kp == pytest.approx(1.0, rel=1e-9)  # the grid's (and the true) minimum of the jerk
    k_hi = (5 + math.sqrt(21)) / 2  # k + 1/k = 5: the crossings 0.209 and 4.79
    assert kr == pytest.approx(k_hi, rel=0.01)
    assert 100 * (kr + 1 / kr) <= 500.0 * 1.01


def test_scaled_imm_scales_every_density():
    d = IMMConfig()
    s = _scaled_imm(0.1, 30.0)
    for a, b in zip(d.position_models, s.position_models):
        assert math.exp(b.log_q) == pytest.approx(0.1 * math.exp(a.log_q))
    for a, b in zip(d.rotation_models, s.rotation_models):
        assert math.exp(b.log_q) == pytest.approx(30.0 * math.exp(a.log_q))
    assert s.log_switch_rate == d.log_switch_rate


def test_knob_baselines_tuned_inside_their_search_range():
    for b in KNOB_BASELINES:
        assert b.bounds[0] < min(b.tuned) <= max(b.tuned) <= b.bounds[1], b.name


def _metrics(rmse_p, rmse_r, jp, jr, lag=0.01):
    return {"position_rmse": rmse_p, "rotation_rmse_deg": rmse_r, "jerk_position": jp,
            "jerk_rotation": jr, "lag_position": lag, "lag_rotation": lag}


def test_format_choices_rows_and_verdict():
    rows = [Choice("phjax (causal)", "phjax", (0.028, 0.028), _metrics(0.006, 1.5, 3000, 15000)),
            Choice("kalman-cv extrapolation", "tuned", (0.03, 1.0),
                   _metrics(0.0058, 1.4, 12000, 50000)),
            Choice("kalman-cv extrapolation", "equal smoothness", (0.001, 0.05),
                   _metrics(0.0075, 1.8, 3000, 15000)),
            Choice("alpha-beta extrapolation", "tuned", (0.5, 0.5),
                   _metrics(0.0059, 1.45, 12000, 50000)),
            Choice("alpha-beta extrapolation", "equal smoothness", (0.005, 0.005),
                   _metrics(0.0070, 2.2, 3000, 40000), reached=(True, False))]
    comp = DisplayComparison((0.0, 0.03), {0.0: rows, 0.03: rows}, {0.0: {}, 0.03: {}}, 0.028)
    text = format_choices(comp)
    assert "### Lookahead 0 ms" in text and "### Lookahead 30 ms" in text
    assert text.count("| **phjax (causal)** | horizon 28 ms | **6.00** |") == 2
    assert "|  | as smooth as phjax: alpha 0.005 / never (smoothest: alpha 0.005) |" in text
    assert "| kalman-cv extrapolation | tuned: noise x 0.03 / 1 |" in text
    # the verdict compares with the most accurate baseline at phjax's jerk, channel by channel,
    # and names those that never get as smooth
    assert ("position: phjax 6 mm, the most accurate baseline as smooth is alpha-beta "
            "extrapolation with 7 (phjax / it 0.86)") in text
    assert ("rotation: phjax 1.5 deg, the most accurate baseline as smooth is kalman-cv "
            "extrapolation with 1.8 (phjax / it 0.83); alpha-beta extrapolation never as smooth "
            "(at least 2.67x phjax's jerk)") in text
    # an orientation horizon of its own is named beside the position's
    own = [dataclasses.replace(rows[0], knobs=(0.028, 0.024)), *rows[1:]]
    text = format_choices(dataclasses.replace(comp, choices={0.0: own, 0.03: own}))
    assert text.count("| **phjax (causal)** | horizon 28 / 24 ms | **6.00** |") == 2


@pytest.mark.parametrize("has_pos", [True, False])
def test_plot_choices_writes_the_frontier(tmp_path, has_pos):
    pytest.importorskip("matplotlib")
    import warnings

    nan = float("nan")
    ph = _metrics(0.006 if has_pos else nan, 1.5, 3000 if has_pos else nan, 15000)
    sweep = [(k, k, _metrics(0.006 + 0.002 / k if has_pos else nan, 1.4 + 0.1 / k,
                             9000 + 1000 / k if has_pos else nan, 40000 + 4000 / k))
             for k in (0.1, 0.3, 1.0, 3.0)]
    rows = [Choice("phjax (causal)", "phjax", (0.028, 0.028), ph),
            Choice("kalman-cv extrapolation", "tuned", (1.0, 1.0), sweep[2][2]),
            Choice("kalman-cv extrapolation", "equal smoothness", (0.1, 0.1), sweep[0][2],
                   reached=(False, False))]
    comp = DisplayComparison((0.0, 0.03), {0.0: rows, 0.03: rows},
                             {L: {"kalman-cv extrapolation": sweep} for L in (0.0, 0.03)}, 0.028)
    with warnings.catch_warnings():  # orientation-only data: no empty-legend warning
        warnings.simplefilter("error", UserWarning)
        path = plot_choices(comp, tmp_path / "f.png")
    assert path.stat().st_size > 10_000
