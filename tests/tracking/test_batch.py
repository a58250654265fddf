"""Batches of recordings through ``track`` / ``reconstruct`` (NaN padding), and the same batch
sharded over 4 simulated CPU devices (in a subprocess: the device count is fixed when JAX
starts) against the one-at-a-time results."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import phjax as pj

HERE = Path(__file__).resolve().parent
N_REC, N_FRAMES, N_PAD = 8, 150, 10


def _recordings():
    """8 recordings of 150 frames at 30 Hz with 20 % dropped frames (NaN rows); recording 5 is
    orientation-only, recording 6 position-only, recording 2 starts at an epoch time; render times per recording at
    120 Hz from before the first frame to past the last."""
    recs = []
    for i in range(N_REC):
        t, p, q = pj.synthetic_head_motion(duration=5.3, rate=120.0, seed=i)
        if i == 5:
            p = np.full_like(p, np.nan)
        if i == 6:
            q = np.full_like(q, np.nan)
        mt, mp, mq = (np.asarray(x, np.float64) for x in pj.simulate_measurements(
            i, t, p, q, pj.SensorModel(dropout=0.2)))
        mt, mp, mq = mt[:N_FRAMES], mp[:N_FRAMES], mq[:N_FRAMES]
        assert mt.size == N_FRAMES and np.isnan((mq if i != 6 else mp)[:, 0]).sum() > 10
        r = np.arange(-0.05, mt[-1] - mt[0] + 0.1, 1 / 120.0)[: 600 - 7 * i] + mt[0]
        if i == 2:
            mt, r = mt + 1.7e9, r + 1.7e9
        recs.append((mt, mp, mq, r))
    return recs


def test_pad_recordings_roundtrip_and_errors():
    recs = [(np.arange(n, dtype=float), np.ones((n, 3)) * n) for n in (3, 5, 1)]
    t, x = pj.pad_recordings(*zip(*recs), multiple_of=4)
    assert t.shape == (4, 5) and x.shape == (4, 5, 3)
    assert np.isnan(t[3]).all() and np.isnan(x[0, 3:]).all()
    back = pj.unpad(t, x)
    assert len(back) == 4 and back[3][0].size == 0
    for (a, b), (c, d) in zip(recs, back):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    with pytest.raises(ValueError, match="shorter"):
        pj.pad_recordings([np.zeros(3)], length=2)
    with pytest.raises(ValueError, match="same, non-zero"):
        pj.pad_recordings([np.zeros(3)], [])


def test_batch_input_errors():
    t = np.array([[0.0, 0.1, np.nan, 0.3]])
    p, q = np.zeros((1, 4, 3)), np.tile([1.0, 0, 0, 0], (1, 4, 1))
    with pytest.raises(ValueError, match="padding"):
        pj.track(t, p, q, np.zeros(3))
    t = np.array([[0.0, 0.2, 0.1, 0.3]])
    with pytest.raises(ValueError, match="strictly increasing"):
        pj.reconstruct(t, p, q, np.zeros(3))
    with pytest.raises(ValueError, match="expected times"):
        pj.track(t, p[:, :3], q, np.zeros(3))
    with pytest.raises(ValueError, match="render_times"):
        pj.track(t, p, q, np.zeros((2, 3)))


def _two_recordings(t0: float):
    """Two recordings of 100 and 150 frames at 30 Hz from ``t0`` (a smooth motion), render
    times at 120 Hz, padded into one batch."""
    recs = []
    for n in (100, 150):
        t = t0 + np.arange(n) / 30.0
        u = t - t0
        p = np.stack([np.sin(u), np.cos(u), 0.1 * u], -1)
        q = np.stack([np.cos(0.15 * u), 0 * u, np.sin(0.15 * u), 0 * u], -1)
        recs.append((t, p, q, t0 + np.arange(1 / 30, (n - 1) / 30, 1 / 120)))
    return recs, pj.pad_recordings(*[list(x) for x in zip(*recs)])


@pytest.mark.parametrize("fn", [pj.track, pj.reconstruct])
def test_float32_batch_of_epoch_times_equals_one_at_a_time(fn):
    """In float32 a batch made its times relative inside the program, after the float32
    conversion: Unix times failed ("not strictly increasing") and a 1e5 s offset moved the
    result by 6 mm. Now they are made relative on the host in float64, as for one recording:
    a batch equals each recording alone (measured up to 2.4e-6 m: float32 rounding of two
    differently compiled programs; bound 1e-5 m)."""
    for t0 in (1e5, 1.7e9):
        recs, batch = _two_recordings(t0)
        with jax.enable_x64(False):  # as users run it (the suite runs with x64 on)
            got = fn(*batch)
            wants = [fn(*rec) for rec in recs]
        for i, (rec, want) in enumerate(zip(recs, wants)):
            m = len(rec[3])
            np.testing.assert_allclose(np.asarray(got[0])[i, :m], np.asarray(want[0]),
                                       rtol=0, atol=1e-5)
            np.testing.assert_allclose(np.abs(np.sum(np.asarray(got[1])[i, :m]
                                                     * np.asarray(want[1]), -1)), 1, atol=1e-5)


def test_batches_in_one_size_class_compile_nothing_more():
    """A batch of other lengths in the same size class compiles nothing (was 22 small programs
    per new length: device-side checks, padding and slices; 0.5-0.9 s a call)."""
    import jax.monitoring

    recs, batch = _two_recordings(0.0)
    pj.track(*batch)
    shorter = pj.pad_recordings(*[[x[: len(x) - 7] for x in col] for col in zip(*recs)])
    compiles = []

    def on_duration(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    try:
        pj.track(*shorter)
    finally:
        jax.monitoring.unregister_event_duration_listener(on_duration)
    assert not compiles, f"{len(compiles)} programs compiled"


@pytest.mark.slow  # about 4 CPU minutes: six compilations of the tracker scan and the shape solver
def test_sharded_batch_equals_one_at_a_time(tmp_path):
    """A NaN-padded batch of 8 recordings sharded over 4 devices: ``track`` / ``reconstruct``
    outputs sharded over all 4 and equal to each recording run alone (1e-9, float64; padded
    render times NaN); ``sample`` / ``sample_into`` / ``optimize_shape`` keep the sharding."""
    recs = _recordings()
    times, pos, quat, render = pj.pad_recordings(*zip(*recs), length=(N_FRAMES + N_PAD,) * 3
                                                 + (None,))
    ref = {}
    for name, fn in (("track", pj.track), ("reconstruct", pj.reconstruct)):
        rp, rq = np.full(render.shape + (3,), np.nan), np.full(render.shape + (4,), np.nan)
        for i, (mt, mp, mq, r) in enumerate(recs):
            sp, sq = (np.asarray(x) for x in fn(mt, mp, mq, r))
            rp[i, :r.size], rq[i, :r.size] = sp, sq
        assert np.isnan(rp[5]).all() and np.isfinite(rq[5, 10:len(recs[5][3])]).all()
        assert np.isnan(rq[6]).all() and np.isfinite(rp[6, 10:len(recs[6][3])]).all()
        ref[name + "_p"], ref[name + "_q"] = rp, rq
    data = tmp_path / "batch.npz"
    np.savez(data, times=times, positions=pos, quaternions=quat, render_times=render, **ref)
    # the suite's XLA_FLAGS (compile options, -O0: tests/conftest.py) plus four host devices
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu",
               PYTHONPATH=str(HERE.parents[1]))
    proc = subprocess.run([sys.executable, str(HERE / "_sharded_check.py"), str(data)], env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    print(json.dumps(res))
    assert res["num_devices"] == 4
    assert "shard_batch" in res["partial_error"]
    for name in ("track", "reconstruct"):
        for out, dim in (("position", 3), ("quaternion", 4)):
            lay = res[name][out]
            assert lay["spec"][0] == "batch" and lay["devices"] == 4
            assert lay["shard_shapes"] == [[2, render.shape[1], dim]]
        assert res[name]["diff"] <= 1e-9, res[name]
    for name in ("sample_time", "sample_arclength"):
        for out in ("points", "t"):
            assert res[name][out]["spec"][0] == "batch" and res[name][out]["devices"] == 4
        assert res[name]["diff"] <= 1e-12
    assert "shard the curves with phjax.batch.shard_batch" in res["sample_into_partial_error"]
    assert res["sample_into"]["points"]["devices"] == 4 and res["sample_into"]["donated"]
    assert res["sample_into"]["diff"] <= 1e-12
    for out in ("control_points", "phi0"):
        assert res["optimize_shape"][out]["spec"][0] == "batch"
        assert res["optimize_shape"][out]["devices"] == 4
    assert res["optimize_shape"]["end_error"] <= 1e-12
