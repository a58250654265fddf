"""The studies in experiments/: bootstrap, difficulty, path curvature, the fixed-shape excerpt
protocol, and each study end to end in --smoke mode."""

from __future__ import annotations

import csv
import itertools
import math
import sys

import numpy as np
import pytest
from conftest import REPO, shared_path
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(REPO / "experiments"))

import common as C  # noqa: E402

# ----------------------------------------------------------------------------------------------
# bootstrap
# ----------------------------------------------------------------------------------------------


def test_bootstrap_matches_scipy_percentile():
    scipy_stats = pytest.importorskip("scipy.stats")
    x = np.random.default_rng(1).gamma(2.0, 1.0, size=150)
    mean, lo, hi = C.bootstrap_ci(x, n_boot=20000, seed=3)
    ref = scipy_stats.bootstrap((x,), np.mean, n_resamples=20000, method="percentile",
                                confidence_level=0.95, random_state=4).confidence_interval
    width = ref.high - ref.low
    assert mean == pytest.approx(x.mean())
    assert abs(lo - ref.low) < 0.05 * width and abs(hi - ref.high) < 0.05 * width


def test_bootstrap_normal_theory():
    x = np.random.default_rng(0).normal(3.0, 2.0, size=4000)
    mean, lo, hi = C.bootstrap_ci(x, n_boot=4000, seed=0)
    half = 1.959964 * x.std(ddof=1) / np.sqrt(x.size)
    assert (hi - lo) / 2 == pytest.approx(half, rel=0.08)
    assert (lo + hi) / 2 == pytest.approx(mean, abs=0.1 * half)


def test_cluster_bootstrap_of_duplicated_values_equals_iid_bootstrap_of_groups():
    # every value repeated 5 times in its own group: the cluster bootstrap must ignore the
    # duplication (same draws as the iid bootstrap of the 40 distinct values), while treating
    # the 200 rows as independent would shrink the interval by about sqrt(5)
    x = np.random.default_rng(2).normal(size=40)
    rows, groups = np.repeat(x, 5), np.repeat(np.arange(40), 5)
    assert C.bootstrap_ci(rows, groups=groups, seed=9) == pytest.approx(C.bootstrap_ci(x, seed=9))
    _, lo, hi = C.bootstrap_ci(rows, seed=9)
    _, glo, ghi = C.bootstrap_ci(x, seed=9)
    assert (hi - lo) < 0.6 * (ghi - glo)


def test_bootstrap_ratio_of_means():
    rng = np.random.default_rng(4)
    b = rng.uniform(1, 2, size=60)
    groups = np.repeat(np.arange(20), 3)
    assert C.bootstrap_ratio_ci(2 * b, b, groups=groups) == pytest.approx((2.0, 2.0, 2.0))
    a = b + rng.normal(0, 0.3, size=60)
    a[5] = np.nan  # dropped pairwise
    r, lo, hi = C.bootstrap_ratio_ci(a, b, n_boot=4000, seed=1)
    ok = np.isfinite(a)
    assert r == pytest.approx(a[ok].mean() / b[ok].mean())
    assert lo < r < hi
    # the delta-method standard error of a ratio of means, as an independent reference
    d = a[ok] - r * b[ok]
    se = d.std(ddof=1) / np.sqrt(ok.sum()) / b[ok].mean()
    assert (hi - lo) / 2 == pytest.approx(1.96 * se, rel=0.15)


@settings(max_examples=30)
@given(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=40), st.integers(0, 2**31 - 1))
def test_bootstrap_interval_properties(values, seed):
    x = np.asarray(values + [np.nan])
    a = C.bootstrap_ci(x, n_boot=300, seed=seed)
    assert a == C.bootstrap_ci(x, n_boot=300, seed=seed)  # deterministic by seed
    mean, lo, hi = a
    finite = np.asarray(values)
    assert mean == pytest.approx(finite.mean(), abs=1e-9)
    assert finite.min() - 1e-9 <= lo <= hi <= finite.max() + 1e-9
    assert np.isnan(C.bootstrap_ci([np.nan])[0])


# ----------------------------------------------------------------------------------------------
# difficulty
# ----------------------------------------------------------------------------------------------


def _circle_motion(omega, radius, duration=3.0, rate=120.0, wobble=0.0):
    """Rotation about z at angular speed ``omega (1 + wobble sin t)``; position on a circle of
    the given radius."""
    t = np.arange(0, duration, 1 / rate)
    ang = omega * (t + wobble * (1 - np.cos(t)))
    q = np.stack([np.cos(ang / 2), 0 * t, 0 * t, np.sin(ang / 2)], -1)
    p = radius * np.stack([np.cos(ang), np.sin(ang), 0 * t], -1)
    return t, p, q


def test_difficulty_features_exact_on_uniform_circular_motion():
    omega, radius = 2.0, 0.3
    f = C.difficulty_features(*_circle_motion(omega, radius))
    span = round(0.04 * 120) / 120  # the velocity span in samples of the 120 Hz stream
    chord = np.sinc(omega * span / (2 * np.pi))  # chord / arc of the circle over that span
    assert f["angular_speed"] == pytest.approx(omega, rel=1e-9)
    assert f["angular_accel"] == pytest.approx(0.0, abs=1e-8)
    assert f["linear_speed"] == pytest.approx(omega * radius * chord, rel=1e-9)
    assert f["linear_accel"] == pytest.approx(omega**2 * radius, rel=2e-3)


def test_difficulty_ordering_and_normalisation():
    scales = np.array([3.0, 0.5, 2.0, 1.0, 4.0])
    feats = np.array([list(C.difficulty_features(*_circle_motion(s, 0.2, wobble=0.5)).values())
                      for s in scales])
    score = C.difficulty_scores(feats)
    ranks = C.difficulty_ranks(score)
    assert np.array_equal(ranks, np.argsort(np.argsort(scales)))  # faster = more difficult
    # dimensionless: a feature's unit does not matter; unavailable features are skipped
    rescaled = feats * np.array([1.0, 1e3, 1e-2, 7.0])
    assert np.allclose(C.difficulty_scores(rescaled), score)
    no_pos = feats.copy()
    no_pos[:, 2:] = np.nan
    assert np.array_equal(C.difficulty_ranks(C.difficulty_scores(no_pos)), ranks)
    assert C.difficulty_ranks(np.array([2.0, np.nan, 1.0])).tolist() == [1, 2, 0]


# ----------------------------------------------------------------------------------------------
# path curvature / torsion
# ----------------------------------------------------------------------------------------------


def test_path_curvature_torsion_of_a_helix_and_its_hold():
    a, b = 0.3, 0.1
    c = np.hypot(a, b)
    s = np.linspace(0, 4, 20001)
    x = np.stack([a * np.cos(s / c), a * np.sin(s / c), b * s / c], -1)
    kappa, tau = C.path_curvature_torsion(x)
    assert kappa == pytest.approx(a / c**2, rel=1e-3) and tau == pytest.approx(b / c**2, rel=1e-3)
    # a zero-order hold repeats samples: the staircase is the polyline through the held poses
    coarse = x[::200]
    held = np.repeat(coarse, 4, axis=0)
    assert C.path_curvature_torsion(held) == pytest.approx(C.path_curvature_torsion(coarse))
    # NaN rows are skipped, a straight line has no curvature and no torsion
    held[7] = np.nan
    assert np.isfinite(C.path_curvature_torsion(held)).all()
    line = np.linspace(0, 1, 50)[:, None] * np.array([1.0, 2.0, 3.0])
    k, t = C.path_curvature_torsion(line)
    assert k == pytest.approx(0, abs=1e-9) and np.isnan(t)
    # a planar zigzag: turning pi/2 per corner, no torsion
    zig = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 1, 0], [2, 2, 0.0]])
    k, t = C.path_curvature_torsion(zig)
    assert k == pytest.approx(3 * np.pi / 2 / 4) and t == pytest.approx(0, abs=1e-12)


# ----------------------------------------------------------------------------------------------
# windows and the padded excerpt protocol
# ----------------------------------------------------------------------------------------------


def _fake_recordings():
    from phjax import synthetic_head_motion

    recs = {}
    for d, dur in (("head", 30.0), ("object", 12.0), ("camera", 20.0)):
        t, p, q = synthetic_head_motion(duration=dur, rate=100.0, seed=len(d))
        if d == "object":  # a ground-truth gap of 2 s
            keep = (t < 5) | (t > 7)
            t, p, q = t[keep], p[keep], q[keep]
        recs[d] = [C.Recording(f"{d}-{i}", d, f"src{i}", t, p, q, "measured") for i in range(2)]
    return recs


def test_draw_windows_deterministic_and_inside_the_recordings():
    recs = _fake_recordings()
    proto = C.Protocol()
    w1 = C.draw_windows(recs, 30, seed=5, protocol=proto)
    assert w1 == C.draw_windows(recs, 30, seed=5, protocol=proto)
    assert w1 != C.draw_windows(recs, 30, seed=6, protocol=proto)
    assert len(w1) == 90 and len({w.uid for w in w1}) == 90
    for w in w1:
        rec = recs[w.dataset][w.recording]
        assert proto.min_len <= w.duration <= proto.max_len
        assert w.start >= proto.warmup and w.start + w.duration <= rec.times[-1] + 1e-9
        if w.dataset == "object":  # gap of 2 s inside [5, 7]: never more than 10 % of a window
            overlap = max(0.0, min(w.start + w.duration, 7) - max(w.start, 5))
            assert overlap <= 0.1 * w.duration + 0.02
    # stratified: each source of a benchmark gets half the windows
    assert sum(w.source == "src0" for w in w1 if w.dataset == "head") == 15


def test_padded_excerpt_gives_the_unpadded_result():
    from phjax import SensorModel, track
    from phjax.tracking.baselines import cubic_spline

    recs = _fake_recordings()
    proto = C.Protocol()
    shapes = C.Shapes.for_protocol(proto)
    w = C.draw_windows(recs, 3, seed=1, protocol=proto)[0]
    ex = C.make_excerpt(recs[w.dataset][w.recording], w, sensor=SensorModel(), render_rate=120.0,
                        seed=0, protocol=proto, shapes=shapes)
    assert ex.times.shape == (shapes.frames,) and ex.render.shape == (shapes.render,)
    assert np.all(np.diff(ex.times) > 0)
    n = ex.n_render
    assert n == pytest.approx(w.duration * 120, abs=1.01)
    assert np.all(ex.render[:n] < ex.window_end) and ex.render[n] >= ex.window_end
    real = np.isfinite(ex.quaternions).all(-1)
    last = np.flatnonzero(real).max() + 1
    assert np.all(~real[last:]) and last < shapes.frames  # padding rows are dropped frames
    assert ex.times[last - 1] <= ex.window_end + proto.tail + 1e-9
    # offline: the NaN padding rows are exactly like absent rows
    p1, q1 = (np.asarray(a) for a in cubic_spline(ex.times[:last], ex.positions[:last],
                                                  ex.quaternions[:last], ex.render[:n]))
    p2, q2 = (np.asarray(a)[:n] for a in cubic_spline(ex.times, ex.positions, ex.quaternions,
                                                      ex.render))
    assert np.max(np.abs(p1 - p2)) < 1e-12 and np.max(np.abs(q1 - q2)) < 1e-12
    # causal: the rendered window does not depend on the padding rows at all (here replaced by
    # arbitrary poses), so it equals the unpadded stream; same shapes, no recompilation
    other_p, other_q = ex.positions.copy(), ex.quaternions.copy()
    other_p[last:] = 5.0
    other_q[last:] = [0.0, 1.0, 0.0, 0.0]
    a = [np.asarray(x)[:n] for x in track(ex.times, ex.positions, ex.quaternions, ex.render)]
    b = [np.asarray(x)[:n] for x in track(ex.times, other_p, other_q, ex.render)]
    assert ex.render[n - 1] < ex.times[last]
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    # the ground truth at the render times is the recording interpolated there
    rec = recs[w.dataset][w.recording]
    t_abs = ex.render[:n] + (w.start - ex.window_start)
    assert np.allclose(ex.gt_positions[:n, 0], np.interp(t_abs, rec.times, rec.positions[:, 0]),
                       atol=1e-12)


# ----------------------------------------------------------------------------------------------
# the studies end to end (--smoke)
# ----------------------------------------------------------------------------------------------

SMOKE_METHODS = ["phjax (causal)", "kalman-cv extrapolation", "raw hold", "cubic spline (scipy)"]


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_fig1_smoke(tmp_path):
    shared_path("tum_rgbd_groundtruth")
    import fig1

    out = tmp_path / "fig1"
    assert fig1.main(["--smoke", "--out", str(out), "--no-progress", "--n-boot", "500",
                      "--methods", ",".join(SMOKE_METHODS)]) == 0
    rows = _rows(out / "per_window.csv")
    assert {r["method"] for r in rows} == set(SMOKE_METHODS)
    assert len(rows) == 12 * len(SMOKE_METHODS)
    for key in C.FIG1_METRICS:
        assert key in rows[0]
    for r in rows:
        assert float(r["rotation_rmse_deg"]) > 0
        if r["dataset"] != "head" or r["position_source"] != "none":
            assert float(r["position_rmse"]) > 0 and float(r["curvature_path"]) >= 0
    for d in C.DATASETS:  # ranks are a permutation, ordered by the difficulty score
        win = {r["window"]: (int(r["rank"]), float(r["difficulty"])) for r in rows
               if r["dataset"] == d}
        ranks = sorted(win.values())
        assert [rk for rk, _ in ranks] == list(range(4))
        assert all(a[1] <= b[1] for a, b in itertools.pairwise(ranks))
    stats = _rows(out / "summary_stats.csv")
    assert len(stats) >= 3 * len(SMOKE_METHODS) * len(C.ALL_METRICS)
    for s in stats:
        m, lo, hi = float(s["mean"]), float(s["ci_low"]), float(s["ci_high"])
        if np.isfinite(m):
            assert lo <= m + 1e-12 and m <= hi + 1e-12
    diffs = _rows(out / "paired_differences.csv")
    assert {d["baseline"] for d in diffs} == set(SMOKE_METHODS[1:])
    for name in ("fig1.png", "fig1_advantage.png"):
        assert (out / name).stat().st_size > 20_000
    text = (out / "summary.md").read_text()
    assert "Paired differences" in text and "| camera | phjax (causal) |" in text


def test_sensitivity_smoke(tmp_path):
    shared_path("tum_rgbd_groundtruth")
    import sensitivity

    out = tmp_path / "sens"
    assert sensitivity.main(["--smoke", "--out", str(out), "--no-progress", "--n-boot", "300"]) == 0
    rows = _rows(out / "per_window.csv")
    assert len(rows) == 3 * len(sensitivity.conditions()) * 2
    stats = _rows(out / "summary_stats.csv")
    n_levels = sum(len(f.levels) for f in sensitivity.FACTORS)
    assert len(stats) == n_levels * 3 * len(sensitivity.METRICS)
    for s in stats:
        g, lo, hi = float(s["geo_mean_ratio"]), float(s["ci_low"]), float(s["ci_high"])
        assert 0 < lo <= g * (1 + 1e-12) and g <= hi * (1 + 1e-12)
    # more camera noise raises the error of both methods (same windows, same noise draws)
    by = {}
    for r in rows:
        if r["method"] == "kalman-cv extrapolation" and float(r["rate"]) == 30 and \
                float(r["dropout"]) == 0.05 and float(r["jitter"]) == 0 and float(r["render"]) == 120:
            by.setdefault(float(r["sigma_p"]), []).append(float(r["rotation_rmse_deg"]))
    assert np.mean(by[0.002]) < np.mean(by[0.005]) < np.mean(by[0.02])
    assert (out / "sensitivity.png").stat().st_size > 20_000


def test_processing_time_smoke(tmp_path):
    import processing_time

    out = tmp_path / "pt"
    assert processing_time.main(["--smoke", "--out", str(out), "--no-progress"]) == 0
    rows = _rows(out / "per_n.csv")
    assert len(rows) == 4
    for r in rows:
        assert float(r["best_s"]) > 0 and float(r["best_s"]) <= float(r["median_s"])
    assert (out / "processing_time.png").stat().st_size > 20_000
    assert "log-log exponent" in (out / "summary.md").read_text()


def test_c2_spline_smoke(tmp_path):
    shared_path("tum_rgbd_groundtruth")
    import c2_spline

    out = tmp_path / "c2"
    assert c2_spline.main(["--smoke", "--window", "30", "--out", str(out)]) == 0
    text = (out / "c2_spline.md").read_text()
    row = [line for line in text.splitlines() if line.startswith("| fr1_desk")][0]
    cells = [c.strip() for c in row.strip("|").split("|")]
    rmse_c1, rmse_c2, rmse_cs = (float(c) for c in cells[1:4])
    # both PH reconstructions run through the same smoothed states: the C2 spline stays within
    # a few percent of the C1 chain and both beat the cubic spline through the raw measurements
    assert abs(rmse_c2 / rmse_c1 - 1) < 0.05 and rmse_c1 < rmse_cs and rmse_c2 < rmse_cs
    assert float(cells[8]) < 1e-9  # equation residual of the window solves
    assert "not interpolating (failed): 0" in text


# ----------------------------------------------------------------------------------------------
# the linear-prediction bound (predictor_bound.py)
# ----------------------------------------------------------------------------------------------


def test_lag_features_skip_incomplete_windows_and_hold_offsets():
    import predictor_bound as pb

    x = np.arange(10.0)[:, None] * np.array([[1.0, -2.0]])
    ok = np.ones(10, bool)
    ok[6] = False
    k, f = pb.lag_features(x, ok, taps=3)
    assert k.tolist() == [2, 3, 4, 5, 9]  # every window touching index 6 is left out
    assert f.shape == (5, 2, 2)
    np.testing.assert_allclose(f[0], [[-1.0, -2.0], [2.0, 4.0]])  # x[1] - x[2], x[0] - x[2]


def test_fir_is_exact_on_constant_velocity_and_the_oracle_never_loses():
    import predictor_bound as pb

    rng = np.random.default_rng(0)
    dt, h = 1 / 30, 0.025
    t = np.arange(200) * dt
    x = np.stack([0.3 * t + 1.0, -0.7 * t, 0.05 * t], -1)
    k, f = pb.lag_features(x, np.ones(200, bool), taps=5)
    y = 0 * x[k] + np.array([0.3, -0.7, 0.05]) * h  # constant velocity: offset v h
    w = pb.fit_fir([f], [y])
    np.testing.assert_allclose(f @ w, y, atol=1e-12)
    # on noisy data the weights fitted on a recording beat any others there (least squares)
    xn = x + 0.005 * rng.standard_normal(x.shape)
    k, fn = pb.lag_features(xn, np.ones(200, bool), taps=5)
    yn = x[k] + np.array([0.3, -0.7, 0.05]) * h - xn[k]
    own = pb.fit_fir([fn], [yn])
    for other in (w, np.zeros_like(w), own + 0.01 * rng.standard_normal(own.shape)):
        assert pb._rms_norm(fn @ own - yn) <= pb._rms_norm(fn @ other - yn) + 1e-15


def test_rotation_features_are_tangent_offsets_from_the_newest():
    import predictor_bound as pb

    from phjax._np_quat import np_from_rotvec

    w = np.array([0.0, 0.0, 0.5])  # rad per sample about z
    q = np_from_rotvec(np.arange(8)[:, None] * w)
    _, f = pb.rotation_features(q, np.ones(8, bool), taps=4)
    np.testing.assert_allclose(f[0], -np.outer(w, [1, 2, 3]), atol=1e-12)


def test_predictor_bound_smoke(tmp_path):
    shared_path("tum_rgbd_groundtruth")
    import predictor_bound as pb

    out = tmp_path / "pb"
    assert pb.main(["--smoke", "--out", str(out)]) == 0
    rows = _rows(out / "predictor_bound.csv")
    assert {r["channel"] for r in rows} == {"position", "rotation"}
    for r in rows:
        vals = [float(r[k]) for k in ("kalman_cv", "imm", "fir_train", "fir_oracle")]
        assert all(np.isfinite(v) and v > 0 for v in vals), r
        # the oracle is fitted on the scored recording: never worse than the train fit there
        assert float(r["fir_oracle"]) <= float(r["fir_train"]) * (1 + 1e-9), r
    assert "FIR oracle / IMM" in (out / "predictor_bound.md").read_text()


# ----------------------------------------------------------------------------------------------
# non-linear prediction (nonlinear_predictor.py)
# ----------------------------------------------------------------------------------------------


def test_local_frame_is_a_rotation_and_rotation_equivariant():
    """The networks see the lag offsets in a frame built from the window itself: rotating the
    window rotates the frame (so the local inputs do not change), also for a straight,
    unaccelerated window (the second axis from the fallback) and a still one."""
    import nonlinear_predictor as nl
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    x = rng.standard_normal((20, 3, 11))
    x[0] = np.outer([1.0, 2.0, -0.5], -np.arange(1, 12))  # straight line, constant velocity
    x[1] = 0.0                                             # still
    for r in Rotation.random(3, random_state=2).as_matrix():
        f, fr = nl.local_frame(x), nl.local_frame(np.einsum("ab,nbt->nat", r, x))
        np.testing.assert_allclose(np.einsum("nab,nbc->nac", f.transpose(0, 2, 1), f),
                                   np.broadcast_to(np.eye(3), f.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(f), 1.0, atol=1e-12)
        np.testing.assert_allclose(fr[2:], r @ f[2:], atol=1e-9)
        np.testing.assert_allclose(fr[0, :, 0], r @ f[0, :, 0], atol=1e-12)


def test_networks_start_at_zero_output():
    """Zero-initialised output layer and skip: the plain network starts at a zero offset and
    the residual one *as* the IMM (early stopping may keep step 0)."""
    import jax
    import nonlinear_predictor as nl

    p = nl.init_params(jax.random.PRNGKey(0), 34)
    z = np.random.default_rng(0).standard_normal((50, 34))
    assert np.all(np.asarray(nl.apply(p, z)) == 0)
    assert nl.n_params(p) == 34 * 32 + 32 + 32 * 32 + 32 + 32 * 3 + 3 + 34 * 3


def test_nonlinear_predictor_smoke(tmp_path):
    shared_path("tum_rgbd_groundtruth")
    import nonlinear_predictor as nl

    out = tmp_path / "nl"
    assert nl.main(["--quick", "--taps", "12", "--out", str(out)]) == 0
    rows = _rows(out / "nonlinear_predictor.csv")
    assert {r["channel"] for r in rows} == {"position", "rotation"}
    assert {r["method"] for r in rows} == set(nl.METHODS)
    assert {r["split"] for r in rows} == {"train", "test"}
    assert all(np.isfinite(float(r["rmse"])) and float(r["rmse"]) > 0 for r in rows)
    assert "Networks" in (out / "nonlinear_predictor.md").read_text()


# ----------------------------------------------------------------------------------------------
# the frontier at the display time (display_frontier.py)
# ----------------------------------------------------------------------------------------------


def test_display_frontier_smoke_on_named_recordings(tmp_path):
    """The display-time frontier on recordings named by path (as on data we do not have):
    tables for each lookahead, and the truth really is taken at the display time (the raw
    hold, which does not predict, is exactly 20 ms later against it at 20 ms; the phjax stream
    predicts, so it is far less late)."""
    files = [shared_path("tum_rgbd_groundtruth", f"{n}-groundtruth.txt")
             for n in ("fr1_xyz", "fr1_desk")]
    files.append(shared_path("tum_vi_room_groundtruth", "room1_mocap_groundtruth.csv"))
    import json

    import display_frontier as dfr

    out = tmp_path / "df"
    assert dfr.main(["--smoke", "--out", str(out), "--recordings", *map(str, files)]) == 0
    text = (out / "display_frontier.md").read_text()
    assert "## Target: phjax / strongest external baseline" in text
    assert "| 20 ms | test |" in text and "| 0 ms | all |" in text
    assert "## Lookahead 20 ms" in text and "At equal smoothness" in text
    assert "### The stream's frontier where its jerk is 1/3 of the Kalman CV's" in text
    assert "120 Hz render aligned with the camera clock" in text
    assert "The stream with a horizon per channel (`TrackerConfig.rotation_horizon`)" in text
    rows = _rows(out / "display_frontier.csv")
    tuned = json.loads((out / "tuned.json").read_text())
    h20 = tuned["20 ms"]["phjax stream"][0]

    def get(method, L, key, knob=None):
        return {r["recording"]: float(r[key]) for r in rows if r["method"] == method
                and r["lookahead_ms"] == L and (knob is None or r["knob"] == knob)}

    for key in ("pos_lag_ms", "rot_lag_ms"):
        h0, h20_ = get("raw hold", "0", key), get("raw hold", "20", key)
        assert len(h0) == 3
        inside = [rec for rec in h0 if -30 < h0[rec] < 100]  # not at an end of the lag grid
        assert len(inside) >= 2
        for rec in inside:
            assert h20_[rec] == pytest.approx(h0[rec] + 20.0, abs=1e-3)
    stream = get("phjax stream", "20", "pos_lag_ms", h20)
    hold20 = get("raw hold", "20", "pos_lag_ms")
    assert np.median(list(stream.values())) < np.median(list(hold20.values())) - 10.0
    rmse0, rmse20 = get("raw hold", "0", "pos_rmse_mm"), get("raw hold", "20", "pos_rmse_mm")
    assert all(rmse20[k] > rmse0[k] for k in rmse0)
    assert (out / "display_frontier.png").stat().st_size > 20_000


def test_display_frontier_over_sensor_draws_agrees_with_each_draw(tmp_path):
    """With several sensor draws the top table gives, per draw, the numbers of that draw's own
    report (tuned and scored separately), their mean, and the draws where the target holds;
    --report-only rebuilds the same table from the saved scores."""
    import re

    import display_frontier as dfr

    files = [str(shared_path("tum_rgbd_groundtruth", f"{n}-groundtruth.txt"))
             for n in ("fr1_xyz", "fr1_desk")]
    out = tmp_path / "df"
    assert dfr.main(["--smoke", "--draws", "2", "--draw", "5", "--out", str(out),
                     "--recordings", *files]) == 0
    top = (out / "display_frontier.md").read_text()
    assert "sensor draws [5, 6]" in top
    row = next(line for line in top.splitlines() if line.startswith("| 20 ms | test |"))
    cells = row.split(" | ")
    per = re.findall(r"(\d\.\d{3}) \w+", cells[2])  # phjax pos RMSE per draw
    assert len(per) == 2
    mean = float(cells[2].split()[0])
    assert mean == pytest.approx(np.mean([float(v) for v in per]), abs=1.1e-3)
    for k, v in zip((5, 6), per):
        own = (out / f"draw_{k}" / "display_frontier.md").read_text()
        assert "Sensor draw %d: each recording its own seed" % k in own
        mine = next(line for line in own.splitlines() if line.startswith("| 20 ms | test |"))
        assert mine.split(" | ")[2].startswith(v)  # the draw's own target table
    import pickle

    saved = pickle.load(open(out / "results.pkl", "rb"))
    met = 0
    for run in saved["draws"]:  # the target on the unrounded ratios
        _, splits = dfr._split(run["data"], False)
        tr = dfr.target_rows(run["results"][0.02], splits["test"])
        met += dfr._met([tr["phjax_pos"][0], tr["phjax_rot"][0]])
    assert row.rstrip(" |").endswith(f"{met} of 2")
    assert "read with the mean over recordings of each per-recording ratio" in top
    assert (out / "draw_6" / "display_frontier.png").is_file()
    for f in ("display_frontier.csv", "tuned.json"):
        assert (out / f).read_text() == (out / "draw_5" / f).read_text()
    (out / "draw_9").mkdir()  # a folder of an earlier run's draws: removed
    assert dfr.main(["--report-only", "--out", str(out)]) == 0
    again = (out / "display_frontier.md").read_text()
    assert again.split("Wall time")[0] == top.split("Wall time")[0]
    assert not (out / "draw_9").exists() and (out / "draw_6").is_dir()
    # a pickle of one draw as written before 2026-12-01: its own protocol options kept
    old = tmp_path / "old"
    old.mkdir()
    first = saved["draws"][0]
    with open(old / "results.pkl", "wb") as fh:
        pickle.dump(dict(data=first["data"], results=first["results"], wall=1.0,
                         seconds=saved["seconds"], render_phase=0.0,
                         protocol=dict(noise_seed="shared", seed_offset=2,
                                       tune_one_euro_dcutoff=True, rooms_test_only=False)), fh)
    assert dfr.main(["--report-only", "--out", str(old)]) == 0
    text = (old / "display_frontier.md").read_text()
    assert "One Euro d_cutoff tuned" in text and "TUM VI rooms of both splits" in text
    assert "Sensor draw 2: seed 2 for every recording" in text


def test_display_frontier_target_rows_median_and_mean():
    """The target rows take the median over recordings of each per-recording ratio, and the
    second reading the mean, each against the baseline whose statistic is the largest: on three
    recordings where the two statistics pick different baselines."""
    import display_frontier as dfr

    def rows(*pos):
        return [dict(pos=p, rot=1.0, jp=1.0, jr=1.0, lag_p=0.0, lag_r=0.0) for p in pos]

    kf, ab, de, oe = dfr.EXTERNAL
    runs = {(dfr.STREAM, 0.028): rows(1.0, 1.0, 1.0), (dfr.IMM, 1): rows(1.0, 1.0, 1.0),
            (kf, 1): rows(1.0, 1.0, 1.0),           # ratios 1, 1, 1: median 1, mean 1
            (ab, 1): rows(0.95, 0.95, 2.0),         # 1.053, 1.053, 0.5: median 1.053, mean 0.868
            (de, 1): rows(1.02, 1.02, 0.5),         # 0.980, 0.980, 2: median 0.980, mean 1.320
            (oe, 1): rows(2.0, 2.0, 2.0)}
    tuned = {m: (k, k) for (m, k) in runs}
    res = dict(runs=runs, tuned=tuned)
    med = dfr.target_rows(res, [0, 1, 2])
    assert med["phjax_pos"] == (pytest.approx(1 / 0.95), ab)
    mean = dfr.target_rows(res, [0, 1, 2], stat="mean")
    assert mean["phjax_pos"] == (pytest.approx((2 / 1.02 + 2) / 3), de)
    assert med["jp"] == mean["jp"] == 1.0 and med["lag_p"] == mean["lag_p"] == 0.0


def test_display_frontier_alpha_beta_beta_knob():
    """``--tune-alpha-beta-beta``: alpha-beta's knob becomes ``(alpha, factor)``, the velocity
    gain ``factor`` times Benedict-Bordner's; factor 1 is the default filter, another factor
    another filter; without the option the grid is the alphas alone."""
    import display_frontier as dfr

    import phjax as pj

    grid, make = dfr.baseline_methods(0.02)["alpha-beta extrapolation"]
    assert grid == dfr.ALPHAS
    grid_b, make_b = dfr.baseline_methods(0.02, ab_beta=True)["alpha-beta extrapolation"]
    assert len(grid_b) == len(dfr.ALPHAS) * len(dfr.AB_BETAS) and (0.5, 1.0) in grid_b
    assert all(f * a * a / (2 - a) < 4 - 2 * a for a, f in grid_b)  # stable
    t, p, q = pj.synthetic_head_motion(duration=2.0, seed=0)
    mt, mp, mq = (np.asarray(x) for x in pj.simulate_measurements(0, t, p, q))
    r = np.arange(0.2, 1.9, 1 / 120)
    ref = [np.asarray(x) for x in make(0.5)(mt, mp, mq, r)]
    same = [np.asarray(x) for x in make_b((0.5, 1.0))(mt, mp, mq, r)]
    other = [np.asarray(x) for x in make_b((0.5, 4.0))(mt, mp, mq, r)]
    for a, b, c in zip(ref, same, other):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)
        assert np.abs(c - a).max() > 1e-4


def test_display_frontier_horizon_per_channel_follows_each_channels_jerk_rule():
    """The per-channel reading of the stream's sweep: position takes the best train position
    RMSE among the horizons whose train position jerk is within 1/3 of the Kalman CV's,
    rotation likewise on its own jerk (here 30 and 20 ms, where the one-horizon rule, bound by
    both channels, takes 30 ms for both); a channel no train recording measures keeps the
    one-horizon choice; the rows are the sweep's own."""
    import display_frontier as dfr

    def rows(pos, rot, jp, jr):
        return [dict(pos=pos, rot=rot, jp=jp, jr=jr) for _ in range(3)]

    kf = "kalman-cv extrapolation"
    sweep = {0.02: rows(0.5, 0.5, 1.2, 0.9), 0.03: rows(0.6, 0.6, 0.9, 0.6),
             0.04: rows(0.7, 0.7, 0.5, 0.3)}
    res = dict(hold=rows(1.0, 1.0, 1.0, 1.0),
               runs={(kf, 1.0): rows(1.0, 1.0, 3.0, 3.0)}
               | {(dfr.STREAM, h): r for h, r in sweep.items()},
               tuned={kf: (1.0, 1.0), dfr.STREAM: (0.03, 0.03)})
    dfr.add_per_channel(res, [0, 1])
    assert res["tuned"][dfr.PER_CHANNEL] == (0.03, 0.02)
    assert dfr.rows_of(res, dfr.PER_CHANNEL, "r") is sweep[0.02]
    for h in sweep:  # no rotation measured on train: the rule's one horizon
        for r in sweep[h]:
            r["jr"] = math.nan
    del res["tuned"][dfr.PER_CHANNEL]
    dfr.add_per_channel(res, [0, 1])
    assert res["tuned"][dfr.PER_CHANNEL] == (0.03, 0.03)


def test_stream_filter_choice_takes_each_channels_best_pair_within_the_jerk_rule():
    """The joint choice of IMM grid point and horizon: per channel, the pair with the lowest
    train RMSE (relative to the hold) among those whose train jerk is within 1/3 of the tuned
    Kalman CV's on that channel; only train recordings count; with no pair within the rule, the
    longest horizon."""
    import display_frontier as dfr
    import stream_filter_choice as sfc

    def rows(pos, rot, jp, jr, test_pos=None):
        out = [dict(pos=pos, rot=rot, jp=jp, jr=jr) for _ in range(3)]
        if test_pos is not None:  # recording 2 is not on train: it must not count
            out[2]["pos"] = test_pos
        return out

    kf = "kalman-cv extrapolation"
    res = dict(hold=rows(1.0, 1.0, 1.0, 1.0), runs={(kf, 1.0): rows(1.0, 1.0, 3.0, 3.0)},
               tuned={kf: (1.0, 1.0)})
    a, b = (1.0, 15.0, 1.0), (0.3, 40.0, 1.0)
    sweep = {(a, 0.02): rows(0.50, 0.50, 1.5, 1.2),   # jerk over 1/3 x 3 in both
             (a, 0.03): rows(0.60, 0.70, 0.9, 0.6),
             (b, 0.03): rows(0.65, 0.55, 0.6, 0.8, test_pos=0.01),
             (b, 0.04): rows(0.70, 0.60, 0.5, 0.3)}
    assert sfc.choose(sweep, res, [0, 1], "p") == (a, 0.03)
    assert sfc.choose(sweep, res, [0, 1], "r") == (b, 0.03)
    assert dfr.rows_of(res, kf, "r") is res["runs"][(kf, 1.0)]
    for r in sweep.values():  # nothing within the rule: the smoothest horizon
        for x in r:
            x["jp"] = 5.0
    assert sfc.choose(sweep, res, [0, 1], "p") == (b, 0.04)


def test_display_frontier_refuses_unusable_recordings_in_one_line(tmp_path, capsys):
    """A missing file or a file of several trajectories ended in a traceback; FILE#NAME
    names one (as on phjax's command line); a split whose train half has no positions (the
    position knobs untuned: "target met" numbers from the first grid values) is refused."""
    import display_frontier as dfr

    xyz = str(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    cwi = str(shared_path("vr_cwi_6dof_navigation", "H1_longdress_nav.csv"))
    corb = tmp_path / "a_head.txt"  # sorts first: the train half, orientation only
    corb.write_bytes(shared_path("vr_corbillon_multiviewpoint360",
                                 "user1_quaternion.txt").read_bytes())
    corb = str(corb)
    for files, message in (([str(tmp_path / "nope.txt"), xyz], "No such file"),
                           ([cwi, xyz], "name one as FILE#NAME"),
                           ([corb, xyz], "no train recording has positions")):
        try:
            rc = dfr.main(["--smoke", "--out", str(tmp_path / "o"), "--recordings", *files])
        except SystemExit as stop:  # a bad recording: before any work
            rc = stop.code
        assert rc == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    seqs = dfr.load_recordings(15.0, files=[cwi + "#P01_V1", xyz])
    assert [s[0] for s in seqs] == ["H1_longdress_nav#P01_V1", "fr1_xyz-groundtruth"]


def test_display_frontier_render_phase_offsets_the_render_clock():
    """``--render-phase 0.5`` moves every render sample half a render period later, so none
    falls on a camera frame's instant (on the aligned clock every fourth does), and the truth is
    still taken at the display time ``tau + L``."""
    import display_frontier as dfr

    from phjax.motion.resample import interpolate_poses
    from phjax.motion.simulate import synthetic_head_motion

    t, p, q = (np.asarray(x) for x in synthetic_head_motion(duration=6.0, seed=3))
    recs = dfr.simulate([("synthetic", "file", t, p, q)], 5.0)
    aligned, offset = (dfr.prepare(recs, 5.0, [0.02], phase)[0] for phase in (0.0, 0.5))
    np.testing.assert_allclose(offset["r"] - aligned["r"], 0.5 / dfr.RENDER, rtol=0, atol=1e-9)
    mt = recs[0]["mt"]
    on_frame = lambda r: np.min(np.abs(r[:, None] - mt[None, :]), axis=1) < 1e-9  # noqa: E731
    assert on_frame(aligned["r"]).mean() == pytest.approx(0.25, abs=0.02)
    assert not on_frame(offset["r"]).any()
    gp, _ = interpolate_poses(t, p, q, offset["r"] + 0.02, max_gap=0.1)
    np.testing.assert_allclose(offset["truth"][0.02]["gp"], np.asarray(gp), rtol=0, atol=1e-12)


def test_frontier_studies_draw_independent_sensor_noise_per_recording():
    """Until 2026-12-01 every frontier study simulated each recording with seed 0: every
    recording then had the same dropout frames and the same noise sequence, so train and test
    shared them (found in an audit). Now each recording is seeded from its name (fixed,
    reproducible) by default, ``draw`` draws again, and ``shared`` keeps the old protocol; the
    display-time study and the dev-set studies use the one simulator."""
    import devset
    import display_frontier as dfr

    from phjax.motion.simulate import synthetic_head_motion

    t, p, q = (np.asarray(x) for x in synthetic_head_motion(duration=6.0, seed=3))
    seqs = [(name, "file", t, p, q) for name in ("a", "b")]

    def lost(recs):
        return [np.flatnonzero(~np.isfinite(r["mp"]).all(-1)) for r in recs]

    def noise(recs):
        return [r["mp"][np.isfinite(r["mp"]).all(-1)][:50] for r in recs]

    shared = dfr.simulate(seqs, 5.0, seeding="shared")
    np.testing.assert_array_equal(*lost(shared))
    np.testing.assert_array_equal(*noise(shared))  # same truth, same draw: identical frames
    own = dfr.simulate(seqs, 5.0)  # the default
    assert not np.array_equal(*noise(own))
    again = devset.simulate_recordings(seqs, 5.0, dfr.RATE)  # one simulator
    np.testing.assert_array_equal(noise(own)[0], noise(again)[0])  # fixed per recording
    other = dfr.simulate(seqs, 5.0, draw=1)
    assert not np.array_equal(noise(own)[0], noise(other)[0])
    assert devset.sensor_seed("a", "shared") == 0 and devset.sensor_seed("a", "shared", 2) == 2
    assert devset.sensor_seed("a") != devset.sensor_seed("b")
    assert devset.sensor_seed("a", draw=1) == devset.sensor_seed("a") + 1
    with pytest.raises(ValueError, match="seeding"):
        devset.sensor_seed("a", "per-file")
    import argparse

    ap = argparse.ArgumentParser()
    devset.add_sensor_arguments(ap)
    args = ap.parse_args(["--draw", "2"])
    assert (args.draw, args.noise_seed) == (2, "per-recording")
    for bad in ("-1", "1.5"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--draw", bad])


def test_display_frontier_interval_over_draws():
    """The target table over sensor draws: mean and 95 % Student t interval (scipy's), NaN
    draws left out, no interval from one draw; a draw meets the target only when every
    measured ratio is at most 1."""
    import display_frontier as dfr
    from scipy import stats

    v = [1.062, 1.056, 1.032]
    m, lo, hi = dfr.draw_interval(v + [math.nan])
    ref = stats.t.interval(0.95, len(v) - 1, loc=np.mean(v), scale=stats.sem(v))
    np.testing.assert_allclose([m, lo, hi], [np.mean(v), *ref], rtol=0, atol=2e-6)
    m1, lo1, hi1 = dfr.draw_interval([0.98])
    assert m1 == 0.98 and math.isnan(lo1) and math.isnan(hi1)
    assert all(math.isnan(x) for x in dfr.draw_interval([math.nan]))
    assert dfr._met([0.99, 1.0]) and not dfr._met([0.99, 1.001])
    assert dfr._met([0.99, math.nan]) and not dfr._met([math.nan, math.nan])
    assert not dfr._met([0.9, math.inf])


def test_every_script_parses_its_arguments():
    """Every runnable script in ``experiments/`` and ``benchmarks/`` builds an ``argparse``
    parser, so that ``--help`` prints usage instead of starting the study (``real_stream.py``
    read ``sys.argv`` by hand and ran its 16 s study on ``--help``)."""
    import ast

    scripts = sorted([*(REPO / "experiments").glob("*.py"), *(REPO / "benchmarks").glob("*.py")])
    runnable = []
    for path in scripts:
        tree = ast.parse(path.read_text())
        main_guard = any(isinstance(n, ast.If) and "__main__" in ast.unparse(n.test)
                         for n in tree.body)
        if main_guard:
            runnable.append(path.name)
            calls = {ast.unparse(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
            assert calls & {"argparse.ArgumentParser", "ArgumentParser"}, path
    assert len(runnable) >= 20, runnable


def test_horizon_rule_ignores_a_channel_no_recording_measures():
    """Orientation-only recordings (the VR head traces) have NaN position scores: every
    horizon failed the position half of the jerk rule and the longest (125 ms) was taken
    silently, worse than the raw hold. A channel without data neither constrains nor scores."""
    import frontier

    nan = float("nan")
    kf = [dict(jp=nan, jr=1.0)]
    hold = [dict(pos=nan, rot=1.0)]
    rows = {h: [dict(jp=nan, jr=j, pos=nan, rot=e)] for h, j, e in
            ((0.02, 0.5, 0.8), (0.028, 0.3, 0.85), (0.035, 0.25, 0.9), (0.125, 0.05, 1.2))}
    said = []
    pick = frontier.horizon_rule(rows.get, sorted(rows), kf, kf, hold, [0], said.append)
    assert pick == 0.028 and not said
    both = {h: [dict(r[0], jp=r[0]["jr"], pos=r[0]["rot"])] for h, r in rows.items()}
    kf2, hold2 = [dict(jp=1.0, jr=1.0)], [dict(pos=1.0, rot=1.0)]
    assert frontier.horizon_rule(both.get, sorted(rows), kf2, kf2, hold2, [0], said.append) == 0.028
    none = {h: [dict(r[0], jr=1.0)] for h, r in rows.items()}  # no horizon meets the rule
    assert frontier.horizon_rule(none.get, sorted(rows), kf, kf, hold, [0], said.append) == 0.125
    assert len(said) == 1 and "taking the longest" in said[0]


def test_frontier_lag_scores_every_shift_on_the_same_samples():
    """The studies' lag (frontier._lag, as phjax.evaluation.shift_lag) scores every candidate
    shift on the samples finite at every shift. Ten samples whose error is |d - 20 ms| put the
    lag at 20 ms; an eleventh with a large error where its shifted ground truth exists and none
    inside a ground-truth gap (the shifts from 50 ms on) is left out, where scoring each shift
    on its own finite samples (the rule before 2026-12-01) moved the lag into the gap."""
    import frontier

    lags = frontier.LAGS
    err = np.abs(lags[:, None] - 0.02) * np.ones((1, 11))
    err[:, 10] = np.where(lags < 0.05, 1.0, np.nan)
    assert frontier._lag(err) == pytest.approx(0.02, abs=1e-9)
    own = np.array([np.sqrt(np.nanmean(e ** 2)) for e in err])  # each shift's finite samples
    assert lags[np.argmin(own)] >= 0.05
    assert np.isnan(frontier._lag(np.full((len(lags), 2), 0.1)))  # under 3 samples


def test_display_frontier_stream_options_reach_the_swept_stream(tmp_path, monkeypatch, capsys):
    """``--stream-option FIELD=VALUE`` (JSON values) are TrackerConfig fields of the swept
    stream; an unknown field or a value that is not JSON is one line and exit 2, before any
    work."""
    import display_frontier as dfr

    xyz = str(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    desk = str(shared_path("tum_rgbd_groundtruth", "fr1_desk-groundtruth.txt"))
    for bad, message in (("horizonn=0.03", "a TrackerConfig field"),
                         ("reacquire", "a TrackerConfig field"),
                         ("noise_window=sixty", "VALUE must be JSON"),
                         ("noise_window=-3", "noise_window must be an integer")):
        with pytest.raises(SystemExit) as stop:
            dfr.main(["--smoke", "--stream-option", bad, "--recordings", xyz, desk])
        assert stop.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert message in err[-1] and bad.split("=")[0] in err[-1], err
    seen = []

    class Measured(Exception):
        pass

    def measure(data, L, train, log=print, small=False, options=None, dcutoff=False,
                ab_beta=False):
        seen.append(options)
        raise Measured

    monkeypatch.setattr(dfr, "measure", measure)
    with pytest.raises(Measured):
        dfr.main(["--smoke", "--out", str(tmp_path / "o"), "--stream-option", "reacquire=true",
                  "--stream-option", "noise_window=60", "--recordings", xyz, desk])
    assert seen == [{"reacquire": True, "noise_window": 60}]
