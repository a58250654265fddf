"""The main job's table and figure (phjax.evaluation.report): best values, ratios, the plot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from phjax.evaluation import report
from phjax.evaluation.report import LEGEND, EvaluationResult, format_table, plot_evaluation


def _m(pos, rot, jp, jr, lp, lr):
    return {"position_rmse": pos, "rotation_rmse_deg": rot, "jerk_position": jp,
            "jerk_rotation": jr, "lag_position": lp, "lag_rotation": lr}


METRICS = {
    "phjax (causal)": _m(0.0070, 1.50, 300.0, 900.0, 0.012, -0.004),
    "kalman-cv extrapolation": _m(0.0072, 1.40, 1200.0, 5000.0, 0.009, 0.006),
    "one-euro + extrapolation": _m(0.0068, 1.60, 1500.0, 800.0, -0.003, 0.020),
    "raw hold": _m(0.0090, 2.00, 5000.0, 9000.0, 0.020, 0.020),
    "phjax (offline)": _m(0.0030, 0.70, 8.0, 30.0, 0.000, 0.000),
}
CAUSAL = {n: n != "phjax (offline)" for n in METRICS}


def _rows(text):
    """Markdown rows of the first table: name -> cells."""
    out = {}
    for line in text.splitlines():
        if not line.startswith("| ") or line.startswith("| method"):
            if out and not line.startswith("|"):
                break
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out


def test_table_marks_the_best_causal_value_per_column():
    text = format_table(METRICS, CAUSAL)
    rows = _rows(text)
    bold = {name: [i for i, c in enumerate(cells[1:]) if c.startswith("**")]
            for name, cells in rows.items()}
    # columns: pos RMSE, rot RMSE, pos jerk, rot jerk, pos lag, rot lag (lag: closest to 0)
    assert bold["one-euro + extrapolation"] == [0, 3, 4]
    assert bold["kalman-cv extrapolation"] == [1]
    assert bold["phjax (causal)"] == [2, 5]
    assert bold["raw hold"] == []
    assert bold["phjax (offline)"] == []  # best everywhere, but offline: never ranked
    assert rows["phjax (offline)"][0] == "no (offline)"
    assert rows["one-euro + extrapolation"][1] == "**6.80**"  # mm
    assert LEGEND in text


def test_ratio_rows_compare_phjax_with_the_strongest_baseline_of_each_column():
    text = format_table(METRICS, CAUSAL)
    lines = {ln.split("|")[1].strip(): [c.strip() for c in ln.strip("|").split("|")[1:]]
             for ln in text.splitlines()
             if ln.startswith(("| strongest", "| its", "| phjax (causal) / it"))}
    strongest = lines["strongest baseline"]
    # raw hold and phjax streams are not baselines; offline methods never count
    assert strongest == ["one-euro + extrapolation", "kalman-cv extrapolation",
                         "kalman-cv extrapolation", "one-euro + extrapolation",
                         "one-euro + extrapolation", "kalman-cv extrapolation"]
    ratio = lines["phjax (causal) / it"]
    assert float(ratio[0]) == pytest.approx(7.0 / 6.8, abs=1e-3)
    assert float(ratio[1]) == pytest.approx(1.5 / 1.4, abs=1e-3)
    assert float(ratio[2]) == pytest.approx(300 / 1200, abs=1e-3)
    assert float(ratio[3]) == pytest.approx(900 / 800, abs=1e-3)
    assert ratio[4] == "+15.0 ms" and ratio[5] == "-10.0 ms"  # lag: difference


def test_table_handles_nan_columns_ties_and_no_legend():
    m = {"a": _m(np.nan, 1.0, 5.0, 5.0, 0.01, np.nan), "b": _m(np.nan, 1.0, 6.0, 5.0, -0.01,
                                                               np.nan)}
    text = format_table(m, legend=False)
    rows = _rows(text)
    assert rows["a"][1] == "-" and rows["b"][1] == "-" and "**" not in rows["a"][6]
    assert rows["a"][2] == "**1.00**" and rows["b"][2] == "**1.00**"  # tie: both
    assert rows["a"][5] == "**10.0**" and rows["b"][5] == "**-10.0**"  # |lag| tie
    assert LEGEND not in text


def _result(has_pos=True):
    t = np.arange(0, 6, 1 / 120)
    gp = np.stack([0.1 * np.sin(2 * t), 0.05 * np.cos(3 * t), 0.02 * t], -1)
    gq = Rotation.from_rotvec(np.stack([0.3 * np.sin(t), 0.2 * np.sin(2 * t), 0 * t], -1))
    gq = gq.as_quat()[:, [3, 0, 1, 2]]
    if not has_pos:
        gp = np.full_like(gp, np.nan)
    rng = np.random.default_rng(0)
    streams, causal, baseline = {}, {}, {}
    for i, name in enumerate(["phjax (causal)", "kalman-cv extrapolation", "one-euro + hold",
                              "phjax (offline)"]):
        streams[name] = (gp + rng.normal(0, 1e-3 * (i + 1), gp.shape), gq)
        causal[name] = name != "phjax (offline)"
        baseline[name] = not name.startswith("phjax")
    metrics = {n: _m(1e-3 * (i + 1), 0.5 * (i + 1), 100.0 * (i + 1), 300.0, 0.01 * i, 0.005)
               for i, n in enumerate(streams)}
    mt = t[::4]
    return EvaluationResult(metrics, t + 100.0, gp, gq, (mt + 100.0, gp[::4], gq[::4]), streams,
                            causal, baseline)


@pytest.mark.parametrize("has_pos", [True, False])
def test_plot_is_written_with_the_four_panels(tmp_path, monkeypatch, has_pos):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    seen = []
    original = Figure.savefig

    def spy(self, *args, **kwargs):
        seen.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    import warnings

    with warnings.catch_warnings():  # no matplotlib warning, e.g. an empty legend without positions
        warnings.simplefilter("error", UserWarning)
        path = plot_evaluation(_result(has_pos), tmp_path / "eval.png")
    assert path.exists() and path.stat().st_size > 10_000
    (fig,) = seen
    axes = fig.axes
    assert len(axes) == 4
    assert axes[0].get_xscale() == "log" and axes[1].get_xscale() == "log"
    assert "lag" in axes[2].get_title() and "zoom" in axes[3].get_title()
    # the zoom shows ground truth, measurements, two baselines and phjax, phjax drawn last
    labels = [ln.get_label() for ln in axes[3].get_lines()]
    assert labels[0] == "ground truth" and labels[-1] == "phjax (causal)"
    assert {"kalman-cv extrapolation", "one-euro + hold"} <= set(labels)
    assert "phjax (offline)" not in labels
    zoom = axes[3].get_lines()[0].get_xdata()
    assert 0.9 < zoom[-1] - zoom[0] <= 1.0 + 1e-9


def test_zoom_window_is_centred_on_the_fastest_motion():
    t = np.arange(0, 10, 0.01)
    x = np.stack([np.tanh(5 * (t - 7.3)), 0 * t, 0 * t], -1)  # one fast step at 7.3 s
    win = report._zoom_window(t, x, 1.0)
    assert t[win][0] == pytest.approx(6.8, abs=0.03) and t[win][-1] == pytest.approx(7.8, abs=0.03)
    x = np.stack([np.tanh(20 * (t - 0.1)), 0 * t, 0 * t], -1)  # at the start: clipped inside
    win = report._zoom_window(t, x, 1.0)
    assert t[win][0] == pytest.approx(0.0) and t[win][-1] == pytest.approx(1.0)


# ------------------------------------------------------------------------ sparse ground truth


def test_ground_truth_gap_rule():
    from phjax.motion.resample import MIN_GT_GAP, ground_truth_max_gap

    assert ground_truth_max_gap(np.arange(100) * 0.01) == MIN_GT_GAP  # 100 Hz
    assert ground_truth_max_gap(np.arange(50) * 0.101) == pytest.approx(2.5 * 0.101)  # ~10 Hz
    assert ground_truth_max_gap(np.arange(50) * 0.101, 0.05) == 0.05  # explicit
    assert ground_truth_max_gap(np.zeros(3)) == MIN_GT_GAP  # no step at all


def test_sparse_ground_truth_is_scored_and_said():
    """Ground truth at 10 Hz (AVTrack360's rate, steps of 0.101 s) had every render sample in a
    "gap" longer than the fixed 0.1 s: a quarter of them scored (one in 2788 at 5 Hz), in a
    table that looked normal (found by probing). Now the gap limit follows the ground truth's
    own step, every sample is scored, and a one-line warning says the ground truth is
    interpolated; 120 Hz ground truth gives no warning."""
    import warnings

    import phjax as pj
    from phjax.io import TrajectoryWarning

    t, p, q = pj.synthetic_head_motion(duration=4.0, rate=120.0, seed=2)
    sparse = slice(None, None, 12)  # 10 Hz
    methods = [m for m in report.default_methods() if m.name == "raw hold"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dense = report.evaluate_recording(t, p, q, methods=methods)
    assert not [w for w in caught if issubclass(w.category, TrajectoryWarning)]
    with pytest.warns(TrajectoryWarning, match="ground truth sampled at 9.9 Hz"):
        res = report.evaluate_recording(t[sparse] * 1.01, p[sparse], q[sparse], methods=methods)
    n = res.metrics["raw hold"]["position_rmse_n"]
    assert n == np.isfinite(res.gt_positions).all(-1).sum() == res.render_times.size
    assert dense.metrics["raw hold"]["position_rmse_n"] == dense.render_times.size
