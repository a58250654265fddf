"""Configuration files (``save_config`` / ``load_config`` / ``phjax ... --config``): values
that load but make the tracker NaN, wrongly typed fields, damaged files and safe writing."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

import phjax as pj
from phjax.tracking import tuning
from phjax.tracking.imm import IMMConfig
from phjax.tracking.models import ConstantAcceleration, ConstantVelocity

GOOD = tuning.config_to_dict(pj.TrackerConfig())


def _write(path: Path, d) -> Path:
    path.write_text(d if isinstance(d, str) else json.dumps(d))
    return path


def _with(section, field, value, imm=True):
    d = copy.deepcopy(GOOD)
    if not imm:
        d["imm"] = None
    d[section][field] = value
    return d


# each of these loaded before and gave NaN poses (float32 stream)
@pytest.mark.parametrize("section, field, value, imm", [
    ("tracker", "horizon", 1e308, True),
    ("tracker", "stop_time", 1e308, True),
    ("tracker", "adapt", 1e308, True),
    ("tracker", "lookahead", 1e308, True),
    ("kalman", "pos_meas_noise", 1e308, False),
    ("kalman", "init_pos_vel_std", 1e200, False),
    ("imm", "init_pos_vel_std", 1e308, True),
    ("imm", "pos_meas_noise", 1e300, True),
])
def test_load_config_rejects_values_that_make_the_tracker_nan(tmp_path, section, field, value, imm):
    path = _write(tmp_path / "c.json", _with(section, field, value, imm))
    with pytest.raises(ValueError, match=rf"c\.json: {section}\.{field} = .* out of range"):
        tuning.load_config(path)


def test_load_config_rejects_a_log_q_that_makes_the_tracker_nan(tmp_path):
    d = copy.deepcopy(GOOD)
    d["imm"]["position_models"][0]["log_q"] = 60.0  # the model's own check allows +-80
    with pytest.raises(ValueError, match=r"imm\.position_models\[0\]\.log_q = 60.0 is out of"):
        tuning.load_config(_write(tmp_path / "c.json", d))
    d["imm"]["position_models"][0]["log_q"] = 50.0  # the bound itself loads
    assert tuning.load_config(_write(tmp_path / "c.json", d)).imm.position_models[0].log_q == 50


def test_load_config_noise_window_too_large(tmp_path):
    # loaded, then the tracker raised OverflowError (a traceback in the CLI)
    path = _write(tmp_path / "c.json", _with("tracker", "noise_window", 10**21))
    with pytest.raises(ValueError, match=r"tracker\.noise_window = 10+ is out of range"):
        tuning.load_config(path)


@pytest.mark.parametrize("mutate, msg", [
    (lambda d: d["imm"].update(pos_meas_noise=[0.001, 0.002]),  # loaded: a broadcast error later
     r"imm\.pos_meas_noise has an invalid value \[0\.001, 0\.002\]"),
    (lambda d: d["imm"]["position_models"][0].update(log_q="1"),  # loaded as 1.0
     r"imm\.position_models\[0\]\.log_q has an invalid value '1'"),
    (lambda d: d["imm"]["rotation_models"][1].update(log_q=True),  # loaded as 1.0
     r"imm\.rotation_models\[1\]\.log_q has an invalid value True"),
    (lambda d: d["imm"]["position_models"][0].update(log_qq=-3.0),  # silently ignored
     r"imm\.position_models\[0\] must be an object with the keys"),
    (lambda d: d["imm"]["position_models"][0].update(model=["cv"]),  # (unhashable)
     r"imm\.position_models\[0\]\.model must be one of \['ca', 'cv'\], got \['cv'\]"),
    (lambda d: d["kalman"].update(gate_reset="x"),  # "could not convert string to float"
     r"kalman\.gate_reset has an invalid value 'x'"),
    (lambda d: d["tracker"].update(horizon="0.05"),
     r"horizon.*'0\.05'"),  # (named before too, in other words)
])
def test_load_config_wrong_types_name_the_field(tmp_path, mutate, msg):
    d = copy.deepcopy(GOOD)
    mutate(d)
    with pytest.raises(ValueError, match=msg):
        tuning.load_config(_write(tmp_path / "c.json", d))


def test_load_config_imm_error_names_the_file_once(tmp_path):
    path = _write(tmp_path / "c.json", _with("imm", "pos_meas_noise", -1.0))
    with pytest.raises(ValueError, match="IMMConfig.pos_meas_noise") as info:
        tuning.load_config(path)
    assert str(info.value).count("c.json") == 1, info.value


def test_load_config_duplicate_keys(tmp_path):
    text = ('{"format": "phjax.TrackerConfig", "version": 1, '
            '"tracker": {"horizon": 0.05, "horizon": 0.2}}')  # the last one won, silently
    with pytest.raises(ValueError, match=r"c\.json: .*duplicate key\(s\) \['horizon'\]"):
        tuning.load_config(_write(tmp_path / "c.json", text))


def test_load_config_deeply_nested_json(tmp_path):
    path = _write(tmp_path / "c.json", "[" * 100_000 + "]" * 100_000)  # was RecursionError
    with pytest.raises(ValueError, match=r"c\.json: .*nested too deeply"):
        tuning.load_config(path)


def test_load_config_utf8_byte_order_mark(tmp_path):
    cfg = pj.TrackerConfig(horizon=0.05)
    path = tmp_path / "c.json"  # as Windows editors save it
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(tuning.config_to_dict(cfg)).encode())
    assert tuning.load_config(path) == cfg


def test_save_load_roundtrip_every_section_and_range_edges(tmp_path):
    imm = IMMConfig(position_models=(ConstantVelocity(log_q=-50.0),
                                     ConstantAcceleration(log_q=50.0)),
                    rotation_models=(ConstantVelocity.from_q(0.1 + 0.2),), log_switch_rate=-0.7,
                    pos_meas_noise=1e-12, init_pos_vel_std=1e6)
    cfgs = [pj.TrackerConfig(imm=imm, noise_window=60, reacquire=True, lookahead=0.03,
                             adapt=-20.0, horizon=1 / 3, coast_time=0.0),
            pj.TrackerConfig(imm=None, kalman=pj.KalmanConfig(
                model="ca", gate_nis=16.27, gate_reset=0.5, pos_process_noise=1e6,
                rot_meas_noise=1e-12), stop_time=1e6, noise_window=1_000_000)]
    for cfg in cfgs:
        path = tuning.save_config(tmp_path / "c.json", cfg, metadata={"note": "x"})
        assert tuning.load_config(path) == cfg
    assert [p.name for p in tmp_path.iterdir()] == ["c.json"]  # no temporary file left


def test_save_config_rejects_what_load_config_would(tmp_path):
    path = tmp_path / "c.json"
    with pytest.raises(ValueError, match=r"tracker\.horizon = 1e\+30 is out of range"):
        tuning.save_config(path, pj.TrackerConfig(horizon=1e30))
    assert not path.exists()


def test_save_config_argument_types(tmp_path):
    path = tmp_path / "c.json"
    with pytest.raises(TypeError, match="config must be a phjax.TrackerConfig, got dict"):
        tuning.save_config(path, {"horizon": 0.05})  # was AttributeError
    with pytest.raises(TypeError, match=r"c\.json: metadata is not JSON-serialisable"):
        tuning.save_config(path, pj.TrackerConfig(), metadata={"x": object()})  # "Circular..."
    assert not path.exists()


def test_save_config_keeps_the_old_file_when_writing_fails(tmp_path, monkeypatch):
    path = tuning.save_config(tmp_path / "c.json", pj.TrackerConfig(horizon=0.05))
    before = path.read_text()

    def half_then_fail(self, text, *args, **kwargs):  # a full disk, a crash mid-write
        with open(self, "w") as f:
            f.write(text[: len(text) // 2])
        raise OSError(28, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", half_then_fail)
    with pytest.raises(OSError, match="No space left"):
        tuning.save_config(path, pj.TrackerConfig(horizon=0.07))
    monkeypatch.undo()
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.json"]


@pytest.mark.parametrize("text, parts", [
    ("[" * 100_000 + "]" * 100_000, ["nested too deeply"]),  # was a RecursionError traceback
    (json.dumps(_with("tracker", "noise_window", 10**21)), ["tracker.noise_window"]),  # Overflow
    ('{"format": "phjax.TrackerConfig", "version": 1, "tracker": {"horizon": 0.05, '
     '"horizon": 1e308}}', ["duplicate key"]),
    (json.dumps(_with("tracker", "horizon", 1e308)), ["tracker.horizon", "out of range"]),
])
def test_cli_damaged_config_is_one_line(tmp_path, capsys, text, parts):
    path = _write(tmp_path / "params.json", text)
    rc, out, err = run_cli(capsys, ["demo", "--config", path, "--duration", "1", "--plot", ""])
    assert_one_line_error(rc, out, err, "phjax demo", "params.json", *parts)


@pytest.mark.parametrize("max_steps", [1.5, "3", 0, True])
def test_tune_tracker_checks_max_steps_before_any_work(max_steps):
    """``max_steps=1.5`` ran a full tuning, ``"3"`` failed with a comparison TypeError, and 0
    was refused only after the recordings were prepared (seconds): a recording that cannot
    be prepared (one pose) shows the check comes first."""
    one_pose = (np.zeros(1), np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]))
    with pytest.raises(ValueError, match="max_steps must be an integer >= 1"):
        pj.tune_tracker([one_pose], max_steps=max_steps)


def test_tunable_parameters_of_a_non_config_is_a_type_error():
    """A string gave ``AttributeError`` from deep inside the PyTree walk."""
    from phjax.tracking import tunable_parameters

    with pytest.raises(TypeError, match="config must be a phjax.TrackerConfig, got str"):
        tunable_parameters("x")


def test_non_finite_metadata_is_written_as_json_null(tmp_path):
    """Metadata holding NaN or inf (a tuning loss that could not be computed, a rotation RMSE of
    a position-only recording) was written as the bare ``NaN`` / ``Infinity`` Python allows:
    not JSON, rejected by ``jq``, JavaScript and strict parsers. They are ``null`` now."""
    meta = {"loss": float("nan"), "rmse": [1.5, float("inf"), np.float32("nan")],
            "nested": {"lag": -float("inf"), "ok": 2.0}, "steps": 3, "name": "NaN"}
    path = tuning.save_config(tmp_path / "c.json", pj.TrackerConfig(), metadata=meta)
    text = path.read_text()

    def strict(token):
        raise ValueError(f"non-standard JSON number {token}")

    d = json.loads(text, parse_constant=strict)  # what a standard JSON reader accepts
    assert d["metadata"] == {"loss": None, "rmse": [1.5, None, None],
                             "nested": {"lag": None, "ok": 2.0}, "steps": 3, "name": "NaN"}
    assert tuning.load_config(path) == pj.TrackerConfig()
    # configuration fields keep their round trip: an infinite gate (never reset) saves and loads
    gated = pj.TrackerConfig(imm=None, kalman=pj.KalmanConfig(gate_nis=9.0,
                                                              gate_reset=float("inf")))
    tuning.save_config(tmp_path / "g.json", gated, metadata={"x": float("nan")})
    assert tuning.load_config(tmp_path / "g.json") == gated


@pytest.mark.parametrize("make, field", [
    (lambda: pj.TrackerConfig(imm=None, kalman=pj.KalmanConfig(pos_meas_noise=1e30)),
     r"TrackerConfig\.kalman\.pos_meas_noise = 1e\+30 is out of range \[1e-12, 1e\+06\]"),
    (lambda: pj.TrackerConfig(horizon=1e30), r"TrackerConfig\.horizon = 1e\+30"),
    (lambda: pj.TrackerConfig(rotation_horizon=1e30), r"TrackerConfig\.rotation_horizon = 1e\+30"),
    (lambda: pj.TrackerConfig(imm=IMMConfig(position_models=(ConstantVelocity(log_q=60.0),),
                                            rotation_models=(ConstantVelocity(log_q=-5.0),))),
     r"TrackerConfig\.imm\.position_models\[0\]\.log_q = 60\.0 is out of range \[-50, 50\]"),
])
def test_configs_built_in_python_obey_the_file_ranges(make, field, tmp_path):
    """The ranges of configuration files (CONFIG_RANGES: beyond them the float32 stream gives
    NaN poses) held for files only: ``track`` with a measurement std of 1e30 m built in Python
    rendered every position as NaN without a word. ``track``,
    ``reconstruct`` and ``TrackerStream`` now refuse such a config, naming the field."""
    t = np.arange(30) / 30.0
    p, q = np.zeros((30, 3)), np.tile([1.0, 0, 0, 0], (30, 1))
    cfg = make()
    for call in (lambda: pj.track(t, p, q, t, config=cfg),
                 lambda: pj.reconstruct(t, p, q, t, config=cfg),
                 lambda: pj.TrackerStream(cfg)):
        with pytest.raises(ValueError, match=field):
            call()
    with pytest.raises(ValueError, match="out of range"):  # and the file, as before
        tuning.save_config(tmp_path / "c.json", cfg)


def test_the_range_check_skips_traced_configs():
    """Inside ``jax.grad`` the config's values are traced: the check leaves them to the caller
    (gradient tuning steps through values the host never sees)."""
    import jax

    from phjax.tracking._config_ranges import out_of_range

    seen = []

    def f(h):
        seen.append(out_of_range(pj.TrackerConfig(horizon=h)))
        return h

    jax.grad(f)(1e30)
    assert seen == [[]]
    assert [b[0] for b in out_of_range(pj.TrackerConfig(horizon=1e30))] == ["tracker.horizon"]
