"""RGB-D folders without timestamps (Biwi, ``color/`` + ``depth/``) play at a frame rate: 30 Hz
by default, ``fps`` / ``--fps`` otherwise. A ``color/`` + ``depth/`` folder was timed 0, 1, 2 s,
so ``phjax live`` played a camera capture at one frame a second."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli, shared_path
from test_sources_review import _Estimator, _tum_folder

from phjax.live import VirtualClock
from phjax.live._sources import RGBDReplaySource, SourceError, open_source
from phjax.vision import rgbd_io as R

cv2 = pytest.importorskip("cv2")


def _pairs(folder: Path, n: int) -> Path:
    """A ``color/`` + ``depth/`` folder of ``n`` tiny frames named 1..n."""
    (folder / "color").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i in range(1, n + 1):
        cv2.imwrite(str(folder / "color" / f"{i}.png"), np.full((8, 8, 3), 100, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), np.full((8, 8), 1000, np.uint16))
    return folder


def test_a_pairs_folder_is_timed_at_30_hz_unless_told():
    root = shared_path("rgbd_frames_slambook2_ch5")
    seq = R.read_slambook(root)
    np.testing.assert_allclose(seq.timestamps, np.arange(5) / 30.0, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(seq.ground_truth.times, seq.timestamps)
    assert seq[3].timestamp == seq.timestamps[3]
    keyframes = R.open_rgbd(root, fps=1.0)  # slambook's frames are keyframes seconds apart
    np.testing.assert_array_equal(keyframes.timestamps, np.arange(5.0))
    assert keyframes[4].timestamp == 4.0


@pytest.mark.parametrize("fps", [0, -30, float("nan"), float("inf"), 1001, "fast", None, True])
def test_a_frame_rate_that_cannot_time_frames_is_refused(tmp_path, fps):
    folder = _pairs(tmp_path / "pairs", 2)
    with pytest.raises(ValueError, match=r"^fps must be a"):
        R.read_slambook(folder, fps=fps)
    with pytest.raises(ValueError, match=r"^fps must be a"):
        R.read_biwi(tmp_path, fps=fps)  # checked before the folder is read


def test_live_plays_a_pairs_folder_at_its_frame_rate(tmp_path):
    folder = _pairs(tmp_path / "pairs", 6)
    for fps, step in ((None, 1 / 30), (15.0, 1 / 15)):
        src = open_source(str(folder), worker=False, fps=fps)
        assert isinstance(src, RGBDReplaySource)
        assert src.rate == pytest.approx(1 / step, rel=1e-12)
        src.estimator = _Estimator()
        src.open()
        clock = VirtualClock()
        out: list = []
        t0 = clock.now()
        src.run(clock, t0, threading.Event(), out.append)
        assert [m.status for m in out] == ["OK"] * 6
        # each frame delivered at its time on the source's clock (a camera's pace)
        np.testing.assert_allclose([m.t - t0 for m in out], step * np.arange(6), atol=1e-9)


def test_fps_for_a_source_with_its_own_times_is_refused(tmp_path):
    tum = _tum_folder(tmp_path / "tum", 2)
    with pytest.raises(SourceError, match="a TUM RGB-D folder plays at its own timestamps"):
        open_source(str(tum), worker=False, fps=30.0)
    poses = tmp_path / "p.tum"
    poses.write_text("0 0 0 0.5 0 0 0 1\n0.1 0 0 0.5 0 0 0 1\n")
    for spec in (f"poses:{poses}", "synthetic:4", "udp://127.0.0.1:0"):
        with pytest.raises(SourceError, match="is for RGB-D folders without timestamps"):
            open_source(spec, worker=False, fps=30.0)


def test_cli_fps_errors_are_one_line(tmp_path, capsys):
    poses = tmp_path / "p.tum"
    poses.write_text("0 0 0 0.5 0 0 0 1\n0.1 0 0 0.5 0 0 0 1\n")
    rc, out, err = run_cli(capsys, ["live", f"poses:{poses}", "--fps", "30"])
    assert_one_line_error(rc, out, err, "phjax live: error: ", "is for RGB-D folders without "
                          "timestamps")
    rc, out, err = run_cli(capsys, ["live", str(_pairs(tmp_path / "pairs", 2)), "--fps", "0"])
    assert_one_line_error(rc, out, err, "argument --fps: must be between 0.1 and 1000 Hz, got '0'")
    tum = _tum_folder(tmp_path / "tum", 2)
    rc, out, err = run_cli(capsys, ["track-rgbd", str(tum), "-o", str(tmp_path / "o.tum"),
                                    "--fps", "15"])
    assert_one_line_error(rc, out, err, "phjax track-rgbd: error: --fps: only for folders whose "
                          "frames carry no timestamps")
    assert not (tmp_path / "o.tum").exists()
