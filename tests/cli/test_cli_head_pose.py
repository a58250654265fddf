"""``phjax head-pose``: the monocular front-end on photos, scored against the AFLW2000-3D
labels."""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest
from conftest import shared_path
from scipy.io import loadmat

from phjax.cli import main

pytest.importorskip("cv2", reason="the vision extra (OpenCV)")
pytest.importorskip("onnxruntime", reason="the vision extra (onnxruntime)")

#: the network's MAE pitch / yaw / roll on these photos (tests/vision/test_head_pose_net.py),
#: with the same bound: measured + 20 % + 0.3 deg
MEASURED_MAE = np.array([3.81, 3.17, 1.35])


@pytest.fixture
def models(tmp_path):
    from phjax.vision.face_detection import seed_model_cache

    cache = tmp_path / "models"
    for folder in ("yunet_face_detection", "head_pose_models"):
        seed_model_cache(shared_path(folder), cache)
    return cache


def _label_angles(mat_file) -> np.ndarray:
    """AFLW label (pitch, yaw, roll) in degrees (the convention ``pitch_yaw_roll`` returns,
    checked against scipy in tests/vision/test_head_pose_net.py)."""
    return np.degrees(loadmat(mat_file)["Pose_Para"][0, :3].astype(np.float64))


def test_a_folder_of_photos_gives_one_row_each(tmp_path, models, capfd):
    """The 16 labelled photos, an unreadable file and a truncated photo (an interrupted copy)
    in one folder (a text file beside them is not an image and is skipped): 16 poses whose
    angles have the network's accuracy against the labels, two INVALID_INPUT rows with one
    warning line each and nothing from the image libraries (captured at the file descriptor:
    libjpeg and libpng print there), the CSV equal to the printed table."""
    src = shared_path("aflw2000_3d_sample")
    photos = tmp_path / "photos"
    photos.mkdir()
    for jpg in sorted(src.glob("*.jpg")):
        shutil.copy(jpg, photos / jpg.name)
    (photos / "broken.png").write_bytes(b"not an image")
    photo = (src / "image00050.jpg").read_bytes()
    (photos / "truncated.jpg").write_bytes(photo[:len(photo) // 2])
    (photos / "notes.txt").write_text("skipped")
    out = tmp_path / "poses.csv"
    rc = main(["head-pose", str(photos), "-o", str(out), "--model-dir", str(models)])
    printed = capfd.readouterr()
    assert rc == 0, printed.err
    # (OpenCV's own log lines, silenced by phjax's command line through OPENCV_LOG_LEVEL
    # before cv2 is first imported, may come from the tests before this one in this process)
    assert [line for line in printed.err.splitlines() if not line.startswith("[ WARN")] == [
        f"phjax: warning: {photos / 'broken.png'}: not a readable image",
        f"phjax: warning: {photos / 'truncated.jpg'}: truncated: the file ends before its "
        "image does (an interrupted copy or download?)"]
    assert "16 of 18 images with a head pose" in printed.out
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["image"].split("/")[-1] for r in rows] == sorted(
        ["broken.png", "truncated.jpg"] + [p.name for p in src.glob("*.jpg")])
    for unread in (rows[0], rows[-1]):
        assert unread["status"] == "INVALID_INPUT" and unread["yaw_deg"] == "nan"
    errs = []
    for r in rows[1:-1]:
        assert r["status"] == "OK", r
        got = np.array([float(r[k]) for k in ("pitch_deg", "yaw_deg", "roll_deg")])
        errs.append(np.abs(got - _label_angles(src / r["image"].split("/")[-1].replace(
            ".jpg", ".mat"))))
        z = float(r["z_m"])
        assert 0.15 < z < 0.6, r  # 450 px photos at 60 degrees: faces 0.2-0.4 m away
        assert f"{float(r['yaw_deg']):6.1f}" in printed.out
    mae = np.mean(errs, axis=0)
    print("MAE pitch / yaw / roll", mae.round(2))
    assert (mae <= 1.2 * MEASURED_MAE + 0.3).all()


@pytest.mark.parametrize("argv, message", [
    (["head-pose", "no_such_photo.jpg"], "no_such_photo.jpg: No such file or directory"),
    (["head-pose", "{empty}"], "no images in this folder"),
    (["head-pose", "{nested}"], "no images in this folder (.jpg, .jpeg, .png, .bmp, .tif, .tiff, "
                                ".webp); its subfolders are not searched: name them"),
    (["head-pose", "{photo}", "--fov", "500"],
     "argument --fov: must be between 10 and 170 degrees, got '500'"),
    (["head-pose", "{photo}", "--head-size", "20"], "argument --head-size"),
    (["head-pose", "{photo}", "--ipd", "63"], "argument --ipd: must be between 0.03 and 0.1 m"),
    (["head-pose", "{photo}", "-o", "/nonexistent/dir/p.csv"], "/nonexistent/dir"),
    # "phjax head-pose -o photos/*.jpg": the shell puts the first photo after -o
    (["head-pose", "-o", "{photo}", "{photo}"],
     "image00050.jpg: the output is a CSV table, not an image (did the shell expand a pattern"),
])
def test_bad_input_is_one_line_and_status_2(tmp_path, capsys, argv, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "nested" / "day1").mkdir(parents=True)
    photo = shared_path("aflw2000_3d_sample", "image00050.jpg")
    argv = [a.format(empty=tmp_path / "empty", nested=tmp_path / "nested", photo=photo)
            for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err


def test_missing_models_name_the_cache(tmp_path, capsys):
    photo = shared_path("aflw2000_3d_sample", "image00050.jpg")
    assert main(["head-pose", str(photo), "--model-dir", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not found in" in err and "none" in err, err
    assert err.endswith("pass --model-dir FOLDER (a folder holding the model files, e.g. "
                        "../shared/data/yunet_face_detection) or --download-models"), err


def test_photos_of_other_sizes_share_the_loaded_models(tmp_path, models, capsys, monkeypatch):
    """A photo and the same photo on a larger canvas: each gets its own camera model (the
    canvas one reads farther to the side, the same angles) from one network session."""
    import cv2

    from phjax.vision import _head_pose_net

    loads = []
    original = _head_pose_net.HeadPoseNet.__init__

    def counted(self, *args, **kwargs):
        loads.append(1)
        original(self, *args, **kwargs)

    monkeypatch.setattr(_head_pose_net.HeadPoseNet, "__init__", counted)
    photo = cv2.imread(str(shared_path("aflw2000_3d_sample", "image00050.jpg")))
    canvas = np.full((480, 640, 3), 128, np.uint8)
    canvas[15:465, 190:640] = photo  # the face moves 190 px to the right of the centre
    cv2.imwrite(str(tmp_path / "a.png"), photo)
    cv2.imwrite(str(tmp_path / "b.png"), canvas)
    out = tmp_path / "poses.csv"
    assert main(["head-pose", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(out),
                 "--model-dir", str(models)]) == 0
    assert "2 of 2 images with a head pose" in capsys.readouterr().out
    assert len(loads) == 1
    with open(out, newline="") as f:
        a, b = list(csv.DictReader(f))
    for k in ("pitch_deg", "yaw_deg", "roll_deg"):  # the same face: angles within 3 deg
        assert abs(float(a[k]) - float(b[k])) < 3.0, (k, a, b)
    assert float(b["x_m"]) > float(a["x_m"]) + 0.03, (a, b)


def test_the_output_is_never_an_input_and_rows_are_written_as_they_come(tmp_path, models,
                                                                        capsys):
    """An input named as the output (any suffix) is refused before anything is written; the
    table has one LF-terminated line per image; the landmark method solves each photo on its
    own (the same angles alone and after another photo)."""
    photo = shared_path("aflw2000_3d_sample", "image00050.jpg")
    odd = tmp_path / "photo.dat"  # an image under another suffix, named directly
    shutil.copy(photo, odd)
    before = odd.read_bytes()
    assert main(["head-pose", str(odd), "-o", str(odd), "--model-dir", str(models)]) == 2
    assert "is the input" in capsys.readouterr().err
    assert odd.read_bytes() == before
    other = shared_path("aflw2000_3d_sample", "image00081.jpg")
    rows = {}
    for name, inputs in (("alone", [photo]), ("after", [other, photo])):
        out = tmp_path / f"{name}.csv"
        assert main(["head-pose", *map(str, inputs), "-o", str(out), "--method", "landmarks",
                     "--model-dir", str(models)]) == 0
        raw = out.read_bytes()
        assert b"\r" not in raw and raw.count(b"\n") == len(inputs) + 1
        with open(out, newline="") as f:
            rows[name] = list(csv.DictReader(f))[-1]
    assert rows["alone"]["status"] == "OK"
    assert {k: v for k, v in rows["alone"].items() if k != "image"} == {
        k: v for k, v in rows["after"].items() if k != "image"}
