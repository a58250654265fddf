"""Bad input to the live frame sources: lost frames are counted, never the end of the run."""

from __future__ import annotations

import errno
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from phjax.live import RealClock, VirtualClock
from phjax.live._sources import (
    PoseReplaySource,
    RGBDReplaySource,
    SourceError,
    SyntheticSource,
    open_source,
)

cv2 = pytest.importorskip("cv2")


class _Estimator:
    """A front-end that takes no time: one OK pose per frame."""

    def __init__(self):
        self.frames = 0

    def process_frame(self, frame):
        self.frames += 1
        return SimpleNamespace(position=np.array([0.0, 0.0, 0.5]),
                               quaternion=np.array([1.0, 0.0, 0.0, 0.0]),
                               status=SimpleNamespace(name="OK"))

    def reset(self):
        pass


def _tum_folder(folder: Path, n: int) -> Path:
    """A TUM RGB-D folder of ``n`` tiny frames at 30 Hz."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, depth = [], []
    for i in range(n):
        t = 100.0 + i / 30.0
        cv2.imwrite(str(folder / "rgb" / f"{i}.png"), np.full((8, 8, 3), 100, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), np.full((8, 8), 1000, np.uint16))
        rgb.append(f"{t:.6f} rgb/{i}.png")
        depth.append(f"{t + 1e-4:.6f} depth/{i}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth) + "\n")
    return folder


def _run(source, clock) -> list:
    out: list = []
    done = threading.Event()
    errors: list = []

    def target():
        try:
            source.run(clock, clock.now(), threading.Event(), out.append)
        except BaseException as e:  # noqa: BLE001 - asserted below
            errors.append(e)
        finally:
            done.set()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    assert done.wait(30.0), "the replay did not end"
    thread.join(5.0)
    assert not errors, errors
    return out


@pytest.mark.parametrize("clock", [VirtualClock, RealClock])
def test_an_unreadable_image_in_an_rgbd_folder_is_a_lost_frame_not_the_end(tmp_path, clock):
    """A missing colour image and a damaged depth image in the middle of a recording ended the
    run with 'FileNotFoundError: image not found: .../rgb/4.png': the rest was never played."""
    folder = _tum_folder(tmp_path / "rec", 8)
    (folder / "rgb" / "4.png").unlink()
    (folder / "depth" / "5.png").write_bytes(b"not a png")
    source = open_source(str(folder), worker=False)
    assert isinstance(source, RGBDReplaySource)
    source.estimator = _Estimator()
    source.open()
    out = _run(source, clock())
    # every frame of the recording delivered or counted as lost, the last one delivered
    assert len(out) + sum(m.dropped for m in out) == 8
    assert out[-1].status == "OK" and np.isfinite(out[-1].position).all()
    assert all(m.status in ("OK", "NO_FRAME") for m in out)
    for m in out:
        if m.status == "NO_FRAME":
            assert not m.ok
    if clock is VirtualClock:  # exact timing: each frame on its own
        assert [m.status for m in out] == ["OK"] * 4 + ["NO_FRAME"] * 2 + ["OK"] * 2
        assert source.unreadable == 2 and "rgb/4.png" in source.read_error


def test_an_unreadable_first_frame_is_skipped_by_the_warm_up(tmp_path):
    """The warm-up read frames 0-2 unguarded: a bad frame 1 refused the whole recording."""
    folder = _tum_folder(tmp_path / "rec", 6)
    (folder / "rgb" / "1.png").unlink()
    source = open_source(str(folder), worker=False)
    source.estimator = est = _Estimator()
    source.open()
    assert est.frames == 3
    # no readable frame at all (emptied after the folder was opened): one line
    source = open_source(str(folder), worker=False)
    source.estimator = _Estimator()
    for i in range(6):
        (folder / "rgb" / f"{i}.png").write_bytes(b"")
    with pytest.raises(SourceError, match=r"no readable frame among the first 6: .*0\.png"):
        source.open()


def test_an_rgbd_folder_of_one_frame_plays_it(tmp_path):
    source = open_source(str(_tum_folder(tmp_path / "rec", 1)), worker=False)
    source.estimator = _Estimator()
    source.open()
    assert source.rate is None
    out = _run(source, VirtualClock())
    assert [m.status for m in out] == ["OK"]


@pytest.mark.parametrize("times", [[0.0, float("nan"), 0.2], [0.0, 0.2, 0.1],
                                   [0.0, float("inf"), 0.2]])
def test_pose_replay_times_must_be_finite_and_non_decreasing(times):
    """A NaN time made RealClock.sleep_until poll forever (nothing more emitted) until the run
    was stopped; a decreasing one reached the tracker out of order."""
    n = len(times)
    with pytest.raises(SourceError, match="times must be finite and non-decreasing"):
        PoseReplaySource(times, np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)))


def test_pose_file_out_of_order_repeated_and_epoch_times_play_from_the_start(tmp_path):
    """Checked fine: a file's rows are sorted, repeats dropped (with the reader's warning),
    and an epoch clock plays from the run's start; a NaN row is a lost frame."""
    path = tmp_path / "p.txt"
    t0 = 1.7e9
    rows = [(t0, 0.1), (t0 + 0.066, 0.3), (t0 + 0.033, 0.2), (t0 + 0.033, 0.25), (t0 + 0.1, 0.4)]
    path.write_text("".join(f"{t:.4f} {x} 0 0.5 0 0 0 1\n" for t, x in rows)
                    + f"{t0 + 0.133:.4f} nan nan nan nan nan nan nan\n")
    with pytest.warns(Warning):
        source = open_source(f"poses:{path}", worker=False)
    out = _run(source, VirtualClock())
    assert [round(m.t, 3) for m in out] == [0.0, 0.033, 0.066, 0.1, 0.133]
    assert [m.position[0] for m in out[:4]] == [0.1, 0.2, 0.3, 0.4]
    assert not out[4].ok


def _frame(value: int, shape=(2, 3)):
    return SimpleNamespace(color=np.full(shape + (3,), value, np.uint8),
                           depth=np.full(shape, 0.5, np.float32))


def test_a_frame_cache_that_cannot_be_written_keeps_the_frames_in_memory(tmp_path,
                                                                        monkeypatch):
    """A read-only (or full) cache folder: writing the first frame raised
    'OSError: [Errno 30] Read-only file system' out of open(); the frames now stay in memory
    for the run, with one warning line."""
    from phjax.vision.rgbd_io import CameraIntrinsics

    lines: list[str] = []
    src = SyntheticSource(2, 0, cache=tmp_path, estimator=_Estimator(), report=lines.append)
    src._keys, src._shape = ["a" * 24, "b" * 24], (2, 3)
    src.folder.mkdir(parents=True)

    def read_only(self, data):
        raise OSError(errno.EROFS, "Read-only file system", str(self))

    monkeypatch.setattr(Path, "write_bytes", read_only)
    src._render([_frame(7), _frame(9)], [0, 1])
    assert lines[-1] == (f"synthetic head: warning: 2 frame(s) could not be written to "
                         f"{src.folder} (Read-only file system); kept in memory for this run")
    assert list(src.folder.iterdir()) == []  # no half-written file left behind
    intr = CameraIntrinsics(fx=2.0, fy=2.0, cx=1.0, cy=1.0, width=3, height=2)
    frame = src._load(1, 0.0, intr)
    assert (frame.color == 9).all() and np.allclose(frame.depth, 0.5)


def test_a_partial_cache_file_is_rendered_again(tmp_path):
    """Checked fine: a cache file of the wrong size (a partial write) reads as missing."""
    src = SyntheticSource(1, 0, cache=tmp_path, estimator=_Estimator(), report=lambda _: None)
    src._keys, src._shape = ["c" * 24], (2, 3)
    src.folder.mkdir(parents=True)
    src._path(0).write_bytes(bytes(7))
    assert src._read(0) is None
    src._store(0, _frame(5))
    assert src._read(0) is not None and src._path(0).stat().st_size == 2 * 3 * 5
