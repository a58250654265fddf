"""``TrackerConfig.rotation_horizon``: the orientation settles on a horizon of its own.

Its gradient is checked against finite differences in
``test_tracker.py::test_gradient_through_track_wrt_config``, its C1 joins and correction law
beside the one-horizon stream's there, its coasting in ``tests/live/test_runner.py``."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import phjax as pj
from phjax.motion import simulate
from phjax.tracking import tracker, tuning
from phjax.tracking.imm import IMMConfig


@pytest.fixture(scope="module")
def head():
    t, p, q = simulate.synthetic_head_motion(duration=6.0, seed=3)
    mt, mp, mq = (np.asarray(x) for x in simulate.simulate_measurements(5, t, p, q))
    r = np.arange(0.2, 5.8, 1 / 120)
    return t, p, q, mt, mp, mq, r


@pytest.mark.parametrize("lookahead", [0.0, 0.02])
def test_each_channel_is_the_stream_of_its_own_horizon(head, lookahead):
    """With ``adapt`` 0 the channels are independent: the position of a stream with an
    orientation horizon of its own is that of the one-horizon stream, its orientation that of
    the one-horizon stream at the orientation's horizon (dropouts and lookahead included)."""
    *_, mt, mp, mq, r = head
    base = pj.TrackerConfig(lookahead=lookahead)

    def run(**kw):
        return tuple(np.asarray(x) for x in pj.track(mt, mp, mq, r, config=dataclasses.replace(
            base, **kw), dtype=jnp.float64))

    for h_rot in (0.012, 0.06):
        p2, q2 = run(rotation_horizon=h_rot)
        p1, _ = run()
        _, q1 = run(horizon=h_rot)
        np.testing.assert_allclose(p2, p1, rtol=0, atol=1e-12)
        np.testing.assert_allclose(q2, q1, rtol=0, atol=1e-12)
        # and it is another stream: the orientation moves by far more than round-off
        assert np.abs(q2 - np.asarray(run()[1])).max() > 1e-4


def test_rotation_horizon_equal_to_horizon_is_the_one_horizon_stream(head):
    *_, mt, mp, mq, r = head
    a = pj.track(mt, mp, mq, r, dtype=jnp.float64)
    b = pj.track(mt, mp, mq, r, config=pj.TrackerConfig(rotation_horizon=0.028),
                 dtype=jnp.float64)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-13)


def test_adaptive_factor_scales_both_horizons():
    """With ``adapt`` the IMM's mode factor multiplies both horizons: each channel's first
    piece lasts ``0.4 * its horizon * factor`` of the updated filter."""
    cfg = pj.TrackerConfig(imm=IMMConfig(), adapt=0.5, rotation_horizon=0.05)
    t, p, q = simulate.synthetic_head_motion(duration=3.0, seed=2)
    mt, mp, mq = (np.asarray(x) for x in simulate.simulate_measurements(1, t, p, q))
    st = pj.tracker_init(cfg, 0.0, jnp.float64)
    seen = 0
    for k in range(40):
        st = pj.tracker_update(cfg, st, mt[k] - mt[0], mp[k], mq[k])
        if k < 2 or not (np.isfinite(mp[k]).all() and np.isfinite(mq[k]).all()):
            continue
        f = float(tracker._adaptive_factor(cfg, st.filter, jnp.float64))
        np.testing.assert_allclose(np.asarray(st.duration)[:, 0],
                                   [0.4 * 0.028 * f, 0.4 * 0.05 * f], rtol=1e-12)
        seen += 1
    assert seen > 30


def test_float32_stream_is_finite_at_the_range_bounds(head):
    """At the bounds of ``CONFIG_RANGES["tracker.rotation_horizon"]`` the float32 stream gives
    finite poses."""
    *_, mt, mp, mq, r = head
    low, high = tuning.CONFIG_RANGES["tracker.rotation_horizon"]
    for h in (low, high, 0.05):
        P, Q = pj.track(mt, mp, mq, r, config=pj.TrackerConfig(rotation_horizon=h),
                        dtype=jnp.float32)
        assert np.isfinite(np.asarray(P)).all() and np.isfinite(np.asarray(Q)).all(), h


def test_config_files_tuning_names_and_bad_values(tmp_path):
    cfg = pj.TrackerConfig(rotation_horizon=0.05)
    tuning.save_config(tmp_path / "c.json", cfg)
    assert tuning.load_config(tmp_path / "c.json") == cfg
    d = tuning.config_to_dict(pj.TrackerConfig())
    assert d["tracker"]["rotation_horizon"] is None
    assert tuning.config_from_dict(d).rotation_horizon is None
    # a file written before the field existed reads as one horizon
    del d["tracker"]["rotation_horizon"]
    assert tuning.config_from_dict(d) == pj.TrackerConfig()
    for bad in ("0.05", True):
        with pytest.raises(ValueError, match="tracker.rotation_horizon has an invalid value"):
            tuning.config_from_dict({**d, "tracker": {**d["tracker"], "rotation_horizon": bad}})
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="TrackerConfig.rotation_horizon must be a finite "
                                             "number > 0"):
            pj.TrackerConfig(rotation_horizon=bad)
    # tuned beside the horizon once set; not a parameter of the one-horizon stream
    assert tuning.default_parameters(cfg)[-2:] == ("horizon", "rotation_horizon")
    assert "rotation_horizon" in tuning.default_parameters(dataclasses.replace(cfg, imm=None))
    assert "rotation_horizon" not in tuning.tunable_parameters(pj.TrackerConfig())
