"""Gradient-based tuning of the causal tracker (phjax.tracking.tuning, phjax tune).

Compile budget: every test that needs the differentiated stream uses recordings of the same
shapes and one of two parameter sets (the single-model filter's defaults, ``KF``, and the IMM's
defaults), so each expensive program (loss + forward-mode gradient through the whole
``lax.scan``) is compiled once for the file and reused (the IMM one also by the CLI test).
"""

import argparse
import dataclasses
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import phjax as pj
from phjax import io
from phjax.evaluation import metrics
from phjax.tracking import tuning
from phjax.cli._tune import add_commands, add_config_argument, config_from_args
from phjax.tracking.baselines import kalman_extrapolation
from phjax.evaluation import TUNED

DURATION = 3.0  # s of synthetic head motion (the spec's "short sequence")
KF = pj.TrackerConfig(imm=None)  # the single-model filter


def _ground_truth():
    t, p, q = pj.synthetic_head_motion(duration=DURATION, rate=120.0, seed=4)
    return t, p, q


@pytest.fixture(scope="module")
def data():
    return tuning.prepare_recordings([_ground_truth()], seed=0)


@pytest.fixture(scope="module")
def problem(data):
    return tuning.make_problem(data, lam=0.3, config=KF)


def _y0(problem):
    return problem.params_from_config(pj.TrackerConfig(imm=None))


# --------------------------------------------------------------------------- loss and metrics
def test_terms_match_metrics_of_track_and_lambda0_is_rmse(data, problem):
    """The loss terms (own traceable stream + JAX metric twins) equal phjax.evaluation.metrics on the
    output of the public ``track``; with lam = 0 and no rotation the loss is the RMSE ratio."""
    prob0 = tuning.make_problem(data, lam=0.0, rotation_weight=0.0, config=KF)
    f, g, terms = prob0.value_and_grad(_y0(prob0))
    t, p, q, r = (np.asarray(x[0]) for x in (data.times, data.positions, data.quaternions,
                                             data.render_times))
    gp, gq = np.asarray(data.gt_positions[0]), np.asarray(data.gt_quaternions[0])
    real = np.asarray(data.render_mask[0])  # the padding to the size class is masked out
    assert not real.all()  # (this recording is padded: the mask matters)
    r, gp, gq = r[real], gp[real], gq[real]
    sp, sq = (np.asarray(x) for x in pj.track(t, p, q, r, config=pj.TrackerConfig(imm=None)))
    expected = [metrics.position_rmse(sp, gp).value,
                math.radians(metrics.rotation_rmse_deg(sq, gq).value),
                metrics.rms_jerk_position(r, sp).value, metrics.rms_jerk_rotation(r, sq).value]
    np.testing.assert_allclose(np.asarray(terms[0]), expected, rtol=1e-9)
    # reference terms: the tuned Kalman-CV extrapolation scored by phjax.evaluation.metrics
    rp, rq = (np.asarray(x) for x in kalman_extrapolation(t, p, q, r, config=pj.KalmanConfig(
        **TUNED["kalman"])))
    ref = [metrics.position_rmse(rp, gp).value,
           math.radians(metrics.rotation_rmse_deg(rq, gq).value),
           metrics.rms_jerk_position(r, rp).value, metrics.rms_jerk_rotation(r, rq).value]
    np.testing.assert_allclose(np.asarray(data.reference[0]), ref, rtol=1e-9)
    assert float(f) == pytest.approx(expected[0] / ref[0], rel=1e-9)
    # and the combination rule by hand, with jerk and rotation weights
    lam, wr = 0.7, 0.5
    prob = tuning.make_problem(data, lam=lam, rotation_weight=wr, config=KF)
    f2, _, _ = prob.value_and_grad(_y0(prob))
    e = np.asarray(expected) / np.asarray(ref)
    assert float(f2) == pytest.approx((e[0] + lam * e[2] + wr * (e[1] + lam * e[3])) / (1 + wr),
                                      rel=1e-9)
    assert np.all(np.isfinite(np.asarray(g)))


def test_stream_metrics_ignore_masked_and_nan_samples():
    rng = np.random.default_rng(0)
    r = np.cumsum(rng.uniform(0.005, 0.012, 60))
    p = np.cumsum(rng.normal(size=(60, 3)), 0) * 1e-3
    q = np.array(pj.quat_from_rotvec(rng.normal(size=(60, 3)) * 0.3))
    gp = p + rng.normal(size=p.shape) * 1e-3
    gq = np.array(pj.quat_from_rotvec(q[:, 1:] + rng.normal(size=(60, 3)) * 0.02))
    p[10] = np.nan
    gq[20] = np.nan
    mask = np.ones(60, bool)
    mask[40:] = False
    got = np.asarray(tuning.stream_metrics(r, p, q, gp, gq, mask))
    k = slice(0, 40)
    want = [metrics.position_rmse(p[k], gp[k]).value,
            math.radians(metrics.rotation_rmse_deg(q[k], gq[k]).value),
            metrics.rms_jerk_position(r[k], p[k]).value,
            metrics.rms_jerk_rotation(r[k], q[k]).value]
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # nothing to evaluate: zeros, not NaN
    none = np.asarray(tuning.stream_metrics(r, p * np.nan, q, gp, gq, np.zeros(60, bool)))
    np.testing.assert_array_equal(none, 0.0)


def test_lookahead_is_tunable_from_zero_and_not_tuned_by_default(data):
    """``lookahead`` (default 0) is a tunable leaf optimised as it is (a log-space parameter
    could not start at 0), and the default parameter sets leave it fixed."""
    assert "lookahead" in tuning.tunable_parameters()
    assert "lookahead" not in tuning.default_parameters()
    assert "lookahead" not in tuning.default_parameters(KF)
    prob = tuning.make_problem(data, config=KF, parameters=("horizon", "lookahead"))
    y = np.asarray(prob.params_from_config(pj.TrackerConfig(imm=None, lookahead=0.0)))
    np.testing.assert_allclose(y, [math.log(KF.horizon), 0.0])
    back = prob.config_from_params(jnp.asarray([math.log(0.03), -0.01]))
    assert math.isclose(float(back.horizon), 0.03) and math.isclose(float(back.lookahead), -0.01)


# --------------------------------------------------------------------------------- gradients
def test_gradient_matches_central_differences(problem):
    """d loss / d log(parameter) for every tuned parameter vs central differences (float64).

    At a generic point the two agree to ~1e-8. At the default horizon (0.025 s = 3 render
    periods, and the render grid is aligned with the camera frames) every segment end falls on
    a render sample: the loss is C1 but not C2 in the horizon there, central differences
    converge only at O(h), and the AD value is their limit.
    """

    def central(y0, h):
        out = []
        for i in range(y0.shape[0]):
            e = jnp.zeros_like(y0).at[i].set(h)
            out.append((float(problem.value_and_grad(y0 + e)[0])
                        - float(problem.value_and_grad(y0 - e)[0])) / (2 * h))
        return np.asarray(out)

    generic = pj.TrackerConfig(imm=None, horizon=0.0287, kalman=pj.KalmanConfig(
        pos_process_noise=0.021, rot_process_noise=0.37, pos_meas_noise=0.0061,
        rot_meas_noise=0.013))
    y0 = problem.params_from_config(generic)
    g = np.asarray(problem.value_and_grad(y0)[1])
    fd = central(y0, 1e-4)
    assert np.all(np.abs(fd) > 1e-3), fd  # every parameter matters on this recording
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    y0 = _y0(problem)
    g = np.asarray(problem.value_and_grad(y0)[1])
    np.testing.assert_allclose(g, central(y0, 1e-6), rtol=1e-5)


@pytest.mark.parametrize("filt", ["kalman", "imm"])
def test_gradients_finite_with_dropouts_nan_start_and_gt_gaps(data, filt):
    """Lost frames (including the first ones, so early render samples are NaN) and ground-truth
    gaps: the loss and every gradient stay finite (both filters, their default parameters)."""
    rng = np.random.default_rng(1)
    n, m = data.times.shape[1], data.render_times.shape[1]
    lost = rng.uniform(size=n) < 0.3
    lost[:6] = True  # the stream is NaN before the first valid frame
    pos = jnp.where(lost[None, :, None], jnp.nan, data.positions)
    quat = jnp.where(lost[None, :, None], jnp.nan, data.quaternions)
    gap = np.zeros(m, bool)
    gap[100:130] = True
    gp = jnp.where(gap[None, :, None], jnp.nan, data.gt_positions)
    gq = jnp.where(gap[None, :, None], jnp.nan, data.gt_quaternions)
    bad = dataclasses.replace(data, positions=pos, quaternions=quat, gt_positions=gp,
                              gt_quaternions=gq)
    sp, _ = pj.track(*(np.asarray(x[0]) for x in (bad.times, pos, quat, bad.render_times)))
    assert np.isnan(np.asarray(sp)[0]).all()  # masked NaN samples really occur
    cfg = KF if filt == "kalman" else pj.TrackerConfig()
    prob = tuning.make_problem(bad, lam=0.3, config=cfg)
    f, g, terms = prob.value_and_grad(prob.params_from_config(cfg))
    assert np.isfinite(float(f)) and np.all(np.isfinite(np.asarray(g)))
    assert np.all(np.isfinite(np.asarray(terms))) and np.any(np.asarray(g) != 0)


# ------------------------------------------------------------------------------------ solver
def test_ask_tell_bfgs_matches_optimistix_minimise():
    """The ask-tell loop takes exactly the steps of optimistix.minimise with BFGS."""

    def fn(y, args):
        return (1 - y[0]) ** 2 + 5 * (y[1] - y[0] ** 2) ** 2 + 0.5 * (y[2] - 0.3) ** 2

    y0 = jnp.asarray([-1.0, 1.5, 2.0])
    sol = optx.minimise(fn, optx.BFGS(rtol=1e-7, atol=1e-9), y0, max_steps=200, throw=False)

    def vg(y):
        return (*jax.value_and_grad(fn)(y, None), None)

    y, result, steps, _, hist, _ = tuning._bfgs(vg, y0, max_steps=200, rtol=1e-7, atol=1e-9)
    assert result == sol.result == optx.RESULTS.successful
    assert steps == int(sol.stats["num_steps"])
    np.testing.assert_allclose(np.asarray(y), np.asarray(sol.value), rtol=1e-12, atol=1e-12)
    assert np.all(np.diff(hist) <= 1e-15)  # accepted losses never increase
    _, result, steps, *_ = tuning._bfgs(vg, y0, max_steps=3, rtol=1e-7, atol=1e-9)
    assert steps == 3 and result == optx.RESULTS.max_steps_reached


def test_tuning_decreases_loss_from_bad_start(data):
    bad = pj.TrackerConfig(imm=None, kalman=pj.KalmanConfig(pos_process_noise=3.0, rot_process_noise=30.0,
                                                  pos_meas_noise=0.05, rot_meas_noise=0.002),
                           horizon=0.2)
    seen = []
    # 20 steps: from this start BFGS overshoots once (step 10) and backtracks for ~8 steps;
    # with 40 steps it reaches 0.60 x the initial loss (measured)
    cfg, res = tuning.tune_tracker(data, lam=0.3, config=bad, max_steps=20, progress=seen.append)
    assert res.num_steps == len(seen) == len(res.loss_history) <= 20
    assert [s.step for s in seen] == list(range(1, res.num_steps + 1))
    assert res.final_loss < 0.8 * res.initial_loss
    assert np.all(np.diff(res.loss_history) <= 0)
    assert res.result in (optx.RESULTS.successful, optx.RESULTS.max_steps_reached)
    assert isinstance(cfg, pj.TrackerConfig) and cfg == res.config
    assert cfg.kalman.pos_process_noise == pytest.approx(res.parameters["pos_process_noise"])
    assert cfg.coast_time == bad.coast_time  # untuned fields kept
    # the reported loss is the loss of the returned configuration
    prob = tuning.make_problem(data, lam=0.3, config=cfg)
    f, _, terms = prob.value_and_grad(prob.params_from_config(cfg))
    assert float(f) == pytest.approx(res.final_loss, rel=1e-9)
    np.testing.assert_allclose(res.terms, np.asarray(terms), rtol=1e-9)


def test_parameter_discovery_and_validation(data):
    names = tuning.tunable_parameters(KF)
    for n in tuning.DEFAULT_PARAMETERS + ("coast_time", "stop_time", "init_pos_vel_std"):
        assert n in names
    assert "model" not in names and "gate_nis" not in names  # static fields are not tunable
    assert tuning.default_parameters(KF) == tuning.DEFAULT_PARAMETERS
    with pytest.raises(ValueError, match="unknown tracker parameter"):
        tuning.make_problem(data, parameters=("horizon", "not_a_field"))
    with pytest.raises(ValueError, match="horizon must be a finite number > 0"):
        tuning.make_problem(data, config=pj.TrackerConfig(horizon=0.0), parameters=("horizon",))
    prob = tuning.make_problem(data, config=KF, parameters=("kalman.pos_meas_noise", "stop_time"))
    cfg = prob.config_from_params(jnp.log(jnp.asarray([0.01, 0.2])))
    assert float(cfg.kalman.pos_meas_noise) == pytest.approx(0.01)
    assert float(cfg.stop_time) == pytest.approx(0.2)
    with pytest.raises(ValueError, match="autodiff_mode"):
        prob.value_and_grad(jnp.zeros(2), "sideways")


# ------------------------------------------------------------------------------------- IMM
def test_imm_parameters_are_discovered_and_log_leaves_tuned_as_they_are(data):
    """With the IMM (the default filter) every model density and the switch rate are tunable,
    the single-model ``kalman`` leaves (unused by the causal stream) are not, and ``log_*``
    leaves enter the parameter vector as they are (any sign)."""
    names = tuning.tunable_parameters()
    models = [f"imm.{part}.{i}.log_q" for part in ("position_models", "rotation_models")
              for i in range(3)]
    for n in models + ["log_switch_rate", "pos_meas_noise", "rot_meas_noise", "horizon"]:
        assert n in names
    assert not any(n.startswith("kalman.") for n in names) and "pos_process_noise" not in names
    assert tuning.default_parameters() == (*models, "log_switch_rate", "horizon")
    cfg = pj.TrackerConfig(imm=dataclasses.replace(pj.TrackerConfig().imm,
                                                   log_switch_rate=math.log(0.5)))
    prob = tuning.make_problem(data, config=cfg, parameters=("imm.rotation_models.2.log_q",
                                                             "log_switch_rate", "pos_meas_noise"))
    y = np.asarray(prob.params_from_config(cfg))
    np.testing.assert_allclose(y, [cfg.imm.rotation_models[2].log_q, math.log(0.5),
                                   math.log(cfg.imm.pos_meas_noise)], rtol=1e-15)
    back = prob.config_from_params(jnp.asarray([1.5, -2.0, math.log(0.007)]))
    assert float(back.imm.rotation_models[2].log_q) == 1.5
    assert float(back.imm.log_switch_rate) == -2.0
    assert float(back.imm.pos_meas_noise) == pytest.approx(0.007)
    with pytest.raises(ValueError, match="single-model filter parameters"):
        tuning.make_problem(data, parameters=("pos_process_noise",))  # the Kalman's, not used
    # leaves the stream never reads are not offered; adapt (any sign) is tuned as it is
    assert "init_pos_acc_std" not in names and "adapt" in names
    kf_names = tuning.tunable_parameters(KF)
    assert "adapt" not in kf_names and "init_pos_acc_std" not in kf_names
    assert "init_pos_acc_std" in tuning.tunable_parameters(
        pj.TrackerConfig(imm=None, kalman=pj.KalmanConfig(model="ca")))
    prob = tuning.make_problem(data, parameters=("adapt",))  # starts at 0: no log
    assert float(prob.params_from_config(pj.TrackerConfig())[0]) == 0.0
    assert float(prob.config_from_params(jnp.asarray([-0.4])).adapt) == -0.4
    assert tuning.check_parameters(pj.TrackerConfig(), "horizon") == ("horizon",)


@pytest.fixture(scope="module")
def imm_problem(data):
    return tuning.make_problem(data, lam=0.3)


def test_imm_gradient_matches_central_differences(imm_problem):
    """d loss / d parameter through the IMM stream, every default IMM parameter (six model
    log-densities, the log switch rate, the log horizon) vs central differences, at a generic
    point (horizon off the render grid, see the single-model test)."""
    prob = imm_problem
    y0 = prob.params_from_config(pj.TrackerConfig(horizon=0.0287)) + jnp.linspace(-0.2, 0.2, 8)
    g = np.asarray(prob.value_and_grad(y0)[1])
    h, fd = 1e-5, []
    for i in range(y0.shape[0]):
        e = jnp.zeros_like(y0).at[i].set(h)
        fd.append((float(prob.value_and_grad(y0 + e)[0])
                   - float(prob.value_and_grad(y0 - e)[0])) / (2 * h))
    fd = np.asarray(fd)
    assert np.all(np.isfinite(g)) and np.all(np.abs(fd) > 1e-6), fd  # every parameter matters
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-8)


def test_imm_loss_and_gradient_in_float32(imm_problem):
    """Users who keep JAX's default float32 get the float64 loss terms within 2e-5 and the
    gradient within 1e-3 (the IMM stream, default parameters, a generic point)."""
    data32 = tuning.prepare_recordings([_ground_truth()], seed=0, dtype=jnp.float32)
    prob32 = tuning.make_problem(data32, lam=0.3)
    y = imm_problem.params_from_config(pj.TrackerConfig(horizon=0.0287))
    f32, g32, t32 = prob32.value_and_grad(y.astype(jnp.float32))
    f64, g64, t64 = imm_problem.value_and_grad(y)
    assert f32.dtype == g32.dtype == t32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(t32, np.float64), np.asarray(t64), rtol=2e-5)
    assert float(f32) == pytest.approx(float(f64), rel=2e-5)
    g64 = np.asarray(g64)
    np.testing.assert_allclose(np.asarray(g32, np.float64), g64, rtol=1e-3,
                               atol=1e-3 * np.abs(g64).max())


def test_tune_imm_from_bad_start_and_save_load(data, imm_problem, tmp_path):
    """Tuning the default (IMM) tracker from a poor start (densities 20x off, long horizon)
    lowers the loss below the default configuration's in 8 steps, changes the model densities
    and round-trips through the JSON file."""
    imm = pj.TrackerConfig().imm
    bad = pj.TrackerConfig(horizon=0.08, imm=dataclasses.replace(
        imm, position_models=tuple(type(m)(log_q=m.log_q + 3) for m in imm.position_models),
        rotation_models=tuple(type(m)(log_q=m.log_q - 3) for m in imm.rotation_models)))
    cfg, res = tuning.tune_tracker(data, lam=0.3, config=bad, max_steps=8)
    default_loss = float(imm_problem.value_and_grad(
        imm_problem.params_from_config(pj.TrackerConfig()))[0])
    assert res.final_loss < min(0.95 * res.initial_loss, default_loss), (
        res.initial_loss, res.final_loss, default_loss)
    assert cfg.imm.position_models[1].log_q != bad.imm.position_models[1].log_q
    assert res.parameters["imm.position_models.1.log_q"] == cfg.imm.position_models[1].log_q
    assert res.initial_parameters["log_switch_rate"] == 0.0  # log values reported as they are
    assert cfg.imm.pos_meas_noise == bad.imm.pos_meas_noise  # not tuned by default
    tuning.save_config(tmp_path / "imm.json", cfg)
    assert tuning.load_config(tmp_path / "imm.json") == cfg


# -------------------------------------------------------------------------------------- JSON
_pos = st.floats(1e-6, 1e3, allow_nan=False)


@settings(max_examples=30)
@given(model=st.sampled_from(["cv", "ca"]), gate=st.one_of(st.none(), _pos),
       values=st.lists(_pos, min_size=10, max_size=10))
def test_save_load_roundtrip(tmp_path_factory, model, gate, values):
    k = pj.KalmanConfig(model=model, pos_process_noise=values[0], pos_meas_noise=values[1],
                        rot_process_noise=values[2], rot_meas_noise=values[3],
                        init_pos_vel_std=values[4], init_pos_acc_std=values[5],
                        init_rot_vel_std=values[6], gate_nis=gate)
    cfg = pj.TrackerConfig(kalman=k, horizon=values[7], coast_time=values[8], stop_time=values[9])
    path = tmp_path_factory.mktemp("cfg") / "params.json"
    tuning.save_config(path, cfg, metadata={"lambda": 0.3})
    back = tuning.load_config(path)
    assert back == cfg
    d = json.loads(path.read_text())
    assert d["version"] == tuning.CONFIG_VERSION and d["metadata"] == {"lambda": 0.3}
    # every field of both configs is written
    assert set(d["kalman"]) == {f.name for f in dataclasses.fields(pj.KalmanConfig)}
    assert set(d["tracker"]) | {"kalman", "imm"} == {f.name for f in dataclasses.fields(pj.TrackerConfig)}


def test_save_load_roundtrip_imm(tmp_path):
    from phjax.tracking.imm import IMMConfig
    from phjax.tracking.models import ConstantAcceleration, ConstantVelocity

    imm = IMMConfig(position_models=(ConstantVelocity.from_q(0.01), ConstantAcceleration.from_q(7.0)),
                    rotation_models=(ConstantVelocity.from_q(0.2),), log_switch_rate=0.3,
                    pos_meas_noise=0.004)
    for cfg in (pj.TrackerConfig(imm=imm, horizon=0.04), pj.TrackerConfig(imm=None)):
        tuning.save_config(tmp_path / "c.json", cfg)
        assert tuning.load_config(tmp_path / "c.json") == cfg
    d = tuning.config_to_dict(pj.TrackerConfig(imm=imm))
    d["imm"]["position_models"][0]["model"] = "xyz"
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="invalid imm section"):
        tuning.load_config(tmp_path / "bad.json")


def test_load_config_errors(tmp_path):
    good = tuning.config_to_dict(pj.TrackerConfig())
    cases = [
        ({**good, "version": 99}, "unsupported configuration version"),
        ({**good, "format": "something"}, "not a phjax tracker configuration"),
        ({**good, "extra": 1}, "unknown top-level"),
        ({**good, "kalman": {**good["kalman"], "pos_noise": 1.0}},
         r"unknown kalman field.*pos_noise"),
        ({**good, "tracker": {**good["tracker"], "horizn": 1.0}}, r"unknown tracker field.*horizn"),
        ({**good, "tracker": {**good["tracker"], "horizon": [1, 2]}}, "invalid value"),
        ({**good, "kalman": {**good["kalman"], "model": "xyz"}}, "invalid configuration"),
    ]
    for d, msg in cases:
        path = tmp_path / "c.json"
        path.write_text(json.dumps(d))
        with pytest.raises(ValueError, match=msg):
            tuning.load_config(path)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        tuning.load_config(tmp_path / "bad.json")
    (tmp_path / "bin.json").write_bytes(b'{"format": "\xff"}')  # the file named, one line
    with pytest.raises(ValueError, match=r"bin.json: not a JSON text file \(byte 12 is not UTF-8"):
        tuning.load_config(tmp_path / "bin.json")
    partial = {"format": tuning.CONFIG_FORMAT, "version": 1, "tracker": {"horizon": 0.05}}
    # defaults fill in; no "imm" section: the single-model stream (files from before the IMM)
    assert tuning.config_from_dict(partial) == pj.TrackerConfig(horizon=0.05, imm=None)


# --------------------------------------------------------------------------------------- CLI
def _cli(argv):
    parser = argparse.ArgumentParser(prog="phjax")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_tune_writes_config_that_load_config_reads(tmp_path, capsys):
    t, p, q = _ground_truth()
    train = tmp_path / "train.csv"
    io.write_csv(train, io.Trajectory(t + 100.0, p, q))
    out = tmp_path / "params.json"
    assert _cli(["tune", str(train), "--lambda", "0.5", "-o", str(out), "--max-steps", "3"]) == 0
    text = capsys.readouterr().out
    assert "step   1" in text and "step   3" in text and "wrote" in text
    cfg = tuning.load_config(out)
    meta = json.loads(out.read_text())["metadata"]
    assert meta["lambda"] == 0.5 and meta["steps"] == 3 and meta["train"] == [str(train)]
    assert cfg.horizon != pj.TrackerConfig().horizon  # it moved
    assert cfg.imm is not None and cfg.imm != pj.TrackerConfig().imm  # the default: the IMM
    # --config of the other commands
    parser = argparse.ArgumentParser()
    add_config_argument(parser)
    assert config_from_args(parser.parse_args(["--config", str(out)])) == cfg
    assert config_from_args(parser.parse_args([])) is None
    with pytest.raises(FileNotFoundError):
        config_from_args(parser.parse_args(["--config", str(tmp_path / "missing.json")]))


def test_cli_tune_on_a_real_slam_stream(tmp_path, capsys):
    """phjax tune GT --measured EST --align: TUM fr1_xyz's RGBDSLAM estimate (another frame,
    real noise) against its ground truth; the horizon is tuned, the metadata say so."""
    from conftest import shared_path

    base = shared_path("tum_rgbd_groundtruth")
    gt = base / "fr1_xyz-groundtruth.txt"
    est = base / "estimates" / "fr1_xyz-rgbdslam_estimate.txt"
    out = tmp_path / "params.json"
    argv = ["tune", str(gt), "--measured", str(est), "--align", "--lambda", "0.3", "-o",
            str(out), "--max-steps", "2", "--seconds", "3", "--parameters", "horizon"]
    assert _cli(argv) == 0
    text = capsys.readouterr().out
    assert "rigidly aligned" in text and "step   2" in text and "fr1_xyz-groundtruth.txt" in text
    meta = json.loads(out.read_text())["metadata"]
    assert meta["measured"] == [str(est)] and meta["align"] and meta["sensor"] is None
    assert tuning.load_config(out).horizon != pj.TrackerConfig().horizon


def test_loss_terms_take_batch_axes_and_nan_padding():
    """The loss on the same recordings with extra leading axes and with NaN padding (padding
    frames with NaN times, padded render times NaN) equals the loss on the prepared data."""
    gts = [pj.synthetic_head_motion(duration=d, rate=120.0, seed=s) for s, d in ((0, 1.0),
                                                                                 (1, 1.4))]
    data = tuning.prepare_recordings(gts)
    r_max = jnp.max(jnp.where(data.render_mask, data.render_times, -jnp.inf), axis=1)
    pad_frames = data.times > r_max[:, None] + 0.5
    assert bool(jnp.any(pad_frames)) and not bool(jnp.all(data.render_mask))
    nan_padded = eqx.tree_at(
        lambda d: (d.times, d.render_times), data,
        (jnp.where(pad_frames, jnp.nan, data.times),
         jnp.where(data.render_mask, data.render_times, jnp.nan)))
    stacked = jax.tree.map(lambda x: x[None], nan_padded)  # (1, 2, ...)
    cfg = pj.TrackerConfig()

    @jax.jit  # the four values in one program
    def both(a, b):
        return (tuning.loss_terms(cfg, a), tuning.loss_terms(cfg, b), tuning.tracker_loss(cfg, a),
                tuning.tracker_loss(cfg, b))

    terms, terms_b, loss, loss_b = both(data, stacked)
    assert terms_b.shape == (1, 2, 4) and bool(jnp.all(jnp.isfinite(terms)))
    np.testing.assert_allclose(terms_b[0], terms, rtol=1e-12)
    np.testing.assert_allclose(loss_b, loss, rtol=1e-12)
    # a padded batch of ground truths prepares the same data
    padded = pj.pad_recordings(*zip(*gts))
    same = tuning.prepare_recordings(padded)
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(data)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# ------------------------------------------------------------------ given measurements (real)
def _simulated(gt, seed, rate=120.0):
    """What prepare_recordings simulates, as tuning_data's input."""
    t, p, q = (np.asarray(x) for x in gt)
    t = t - t[0]
    mt, mp, mq = (np.asarray(x) for x in pj.simulate_measurements(seed, t, p, q, pj.SensorModel()))
    ok = np.isfinite(mq).all(-1)
    r = np.arange(mt[ok][0] + 1 / 30, t[-1], 1 / rate)
    gp, gq = (np.asarray(x) for x in pj.motion.resample.interpolate_poses(t, p, q, r, max_gap=0.1))
    return mt, mp, mq, r, gp, gq


def test_nothing_to_tune_against_is_an_error():
    """Ground truth sparser than the gap limit, or a still head (reference error zero): the
    loss was 0 / 0 = 0 and ``phjax tune`` reported "converged" and wrote the start config
    (found by probing). Now a ValueError; a channel scored at fewer than MIN_SCORED render
    samples does not count."""
    from phjax.tracking._tuning_data import MIN_SCORED

    t, p, q = _ground_truth()
    thin = slice(None, None, 60)  # 2 Hz ground truth, gaps of 0.5 s > the 0.1 s asked for
    from phjax.io import TrajectoryWarning

    with pytest.raises(ValueError, match="nothing to tune against"), \
            pytest.warns(TrajectoryWarning):  # sampled at 2 Hz; 1 % of the samples scored
        tuning.prepare_recordings([(t[thin], p[thin], q[thin])], max_gt_gap=0.1)
    still = (t, np.zeros_like(p), np.tile([1.0, 0, 0, 0], (t.size, 1)))
    sensor = pj.SensorModel(sigma_p=0.0, sigma_r=0.0, dropout=0.0)
    with pytest.raises(ValueError, match="nothing to tune against"):
        tuning.prepare_recordings([still], sensor=sensor)
    assert MIN_SCORED >= 4


def test_no_weight_on_a_scored_channel_is_an_error(data):
    """An orientation-only recording tuned with rotation_weight 0 (or both weights 0): the loss
    was 0 whatever the parameters and tune_tracker reported "converged" with the start config
    (found by probing). Now a ValueError naming the weights and what is scored."""
    t, p, q = _ground_truth()
    rot_only = tuning.prepare_recordings([(t, np.full_like(p, np.nan), q)])
    with pytest.raises(ValueError, match=r"nothing to tune against: position_weight 1 \(positions "
                       r"scored in 0 recording\(s\)\), rotation_weight 0 \(orientations scored in 1\)"):
        tuning.tune_tracker(rot_only, rotation_weight=0.0, max_steps=2)
    with pytest.raises(ValueError, match="nothing to tune against"):
        tuning.make_problem(data, position_weight=0.0, rotation_weight=0.0)
    tuning.make_problem(data, position_weight=0.0)  # orientation alone is something


def test_tuning_data_of_simulated_frames_equals_prepare_recordings(data):
    got = tuning.tuning_data([_simulated(_ground_truth(), 0)])
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(data)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)


def test_tuning_data_is_relative_so_unix_times_and_far_positions_survive_float32():
    """A recording at Unix time 1.3e9 s, 100 m from the origin, prepares the same relative
    arrays and reference terms as at the origin, also in float32 (no 128 s rounding of
    float32 timestamps, no 8 um position steps)."""
    rec = _simulated(pj.synthetic_head_motion(duration=1.5, rate=120.0, seed=2), 1)
    t0, x0 = 1.3e9, np.array([100.0, -40.0, 7.0])
    far = (rec[0] + t0, rec[1] + x0, rec[2], rec[3] + t0, rec[4] + x0, rec[5])
    near = tuning.tuning_data([rec])
    for dtype, tol in ((jnp.float64, 1e-6), (jnp.float32, 2e-5)):
        got = tuning.tuning_data([far], dtype=dtype)
        assert got.times.dtype == dtype
        for name in ("times", "positions", "render_times", "gt_positions"):
            np.testing.assert_allclose(np.asarray(getattr(got, name), np.float64),
                                       np.asarray(getattr(near, name)), atol=tol, err_msg=name)
        np.testing.assert_allclose(np.asarray(got.reference, np.float64), near.reference,
                                   rtol=1e-3, err_msg=dtype.__name__)


def test_tuning_data_orientation_only_and_errors():
    rec = list(_simulated(pj.synthetic_head_motion(duration=1.0, rate=120.0, seed=3), 0))
    rec[1] = np.full_like(rec[1], np.nan)
    rec[4] = np.full_like(rec[4], np.nan)
    d = tuning.tuning_data([tuple(rec)])
    # a fixed point where the orientation is measured; no position reference
    ok = np.isfinite(rec[2]).all(-1)
    np.testing.assert_array_equal(np.asarray(d.positions[0][:ok.size][ok]), 0.0)
    ref = np.asarray(d.reference[0])
    assert np.isnan(ref[[0, 2]]).all() and np.isfinite(ref[[1, 3]]).all()
    # position only (phjax tune refused it: "the simulated sensor produced no valid
    # measurement"): a fixed orientation where the position is measured; no rotation reference
    full = list(_simulated(pj.synthetic_head_motion(duration=1.0, rate=120.0, seed=3), 0))
    full[2] = np.full_like(full[2], np.nan)
    full[5] = np.full_like(full[5], np.nan)
    d = tuning.tuning_data([tuple(full)])
    ok = np.isfinite(full[1]).all(-1)
    np.testing.assert_array_equal(np.asarray(d.quaternions[0][:ok.size][ok]),
                                  np.tile([1.0, 0, 0, 0], (ok.sum(), 1)))
    ref = np.asarray(d.reference[0])
    assert np.isnan(ref[[1, 3]]).all() and np.isfinite(ref[[0, 2]]).all()
    cases = [
        ([], "at least one recording"),
        ([tuple(rec[:5])], "expected (times"),
        ([(rec[0], rec[1][:-1], *rec[2:])], "shapes must be"),
        ([(rec[0][::-1], *rec[1:])], "non-decreasing"),
        ([(*rec[:3], rec[3][:3], rec[4][:3], rec[5][:3])], "at least 4"),
        ([(*rec[:3], rec[3][::-1], *rec[4:])], "strictly increasing"),
        ([(rec[0], rec[1], rec[2] * np.nan, *rec[3:])], "no valid measurement"),
    ]
    for recs, message in cases:
        with pytest.raises(ValueError, match=message.replace("(", r"\(")):
            tuning.tuning_data(recs)


def test_measured_recording_aligns_a_rigidly_moved_stream():
    """A stream measured in another frame (rotated 70 degrees, shifted 2 m, 1 mm noise):
    ``align=True`` moves it back onto the ground truth; the render times lie inside both."""
    t, p, q = pj.synthetic_head_motion(duration=2.0, rate=120.0, seed=5)
    t, p, q = (np.asarray(x) for x in (t, p, q))
    rng = np.random.default_rng(0)
    k = slice(None, None, 4)  # 30 Hz frames
    qr = np.asarray(pj.quat_from_rotvec(np.array([0.3, -1.0, 0.6]) * math.radians(70) / 1.2))
    rot = np.asarray(pj.quat_to_matrix(qr))
    shift = np.array([2.0, -1.0, 0.5])
    mq = np.asarray(pj.quat_mul(qr, q[k]))
    # exact without noise
    _, ap, aq, *_ = tuning.measured_recording((t, p, q), (t[k], p[k] @ rot.T + shift, mq),
                                              align=True)
    np.testing.assert_allclose(ap, p[k], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(aq * q[k], -1)), 1.0, atol=1e-12)
    # with 1 mm noise (1.7 mm RMS in 3-D) on a 4 cm head motion
    mp = (p[k] + rng.normal(scale=1e-3, size=p[k].shape)) @ rot.T + shift
    mt, ap, aq, r, gp, gq = tuning.measured_recording((t, p, q), (t[k], mp, mq), align=True)
    assert np.sqrt(np.mean(np.sum((ap - p[k]) ** 2, -1))) < 2e-3
    assert r[0] >= mt[0] + 1 / 30 - 1e-9 and r[-1] <= min(mt[-1], t[-1])
    np.testing.assert_allclose(np.diff(r), 1 / 120, rtol=1e-9)
    assert np.isfinite(gp).all() and np.isfinite(gq).all()
    # without align the stream is taken as it is
    same = tuning.measured_recording((t, p, q), (t[k], mp, mq))
    np.testing.assert_array_equal(same[1], mp)
    for kwargs, message in (
            (dict(measurements=(t[k] + 10.0, mp, mq)), "overlap for too short"),
            (dict(measurements=(t[k], mp * np.nan, mq), align=True), "rigid transform"),
            (dict(measurements=(t[k], mp * np.nan, mq * np.nan)), "no valid measurement")):
        with pytest.raises(ValueError, match=message):
            tuning.measured_recording((t, p, q), **kwargs)


def test_tuning_data_drops_repeated_measurement_times_like_track():
    rec = list(_simulated(pj.synthetic_head_motion(duration=1.0, rate=120.0, seed=6), 0))
    k = 5
    dup = [np.insert(x, k + 1, x[k], axis=0) for x in rec[:3]]  # frame k repeated
    dup[1][k + 1] += 0.01  # a different pose at the same time: the first one counts
    a = tuning.tuning_data([tuple(rec)])
    b = tuning.tuning_data([(*dup, *rec[3:])])
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="measurement times must be finite and strictly"):
        tuning.measured_recording(tuple(rec[:3]), tuple(dup))


def test_measured_recording_with_unix_times_without_x64(tmp_path):
    """Without jax_enable_x64 (JAX's default) the ground truth at the render times is still
    right for 1.3e9 s Unix timestamps: the interpolation sees relative times."""
    import subprocess
    import sys

    code = """
import numpy as np
from phjax.tracking import tuning
t = 1.3e9 + np.arange(0, 3.0, 0.01)
v = np.array([0.3, -0.2, 0.1])
p = (t - t[0])[:, None] * v
q = np.tile([1.0, 0.0, 0.0, 0.0], (t.size, 1))
k = slice(0, None, 3)
mt, mp, mq, r, gp, gq = tuning.measured_recording((t, p, q), (t[k], p[k], q[k]))
print(np.abs(gp - (r - t[0])[:, None] * v).max())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "JAX_ENABLE_X64": "0"})
    assert out.returncode == 0, out.stderr
    assert float(out.stdout.strip().splitlines()[-1]) < 1e-5  # float32 at 1 m: ~1e-7


def test_far_moves_of_tuned_parameters_are_flagged():
    """A one-second window let BFGS take log_switch_rate from 0 to -31 and write it without a
    word; moves beyond a factor of 100 (log parameters: beyond log 100) are now warned of."""
    from phjax.cli._tune import _far_moves

    start = {"log_switch_rate": 0.0, "horizon": 0.028, "imm.rotation_models.2.log_q": 1.28,
             "kalman.pos_meas_noise": 0.005}
    tuned = {"log_switch_rate": -31.1, "horizon": 0.03, "imm.rotation_models.2.log_q": 3.0,
             "kalman.pos_meas_noise": 0.9}
    far = _far_moves(start, tuned)
    assert set(far) == {"log_switch_rate", "kalman.pos_meas_noise"}
    assert far["log_switch_rate"] == pytest.approx(np.exp(31.1))
    assert far["kalman.pos_meas_noise"] == pytest.approx(180.0)
