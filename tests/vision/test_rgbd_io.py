"""RGB-D readers: Biwi depth/calibration/registration, TUM RGB-D folders, PGM pairs, slambook."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_path
from hypothesis import given, settings
from hypothesis import strategies as st

from phjax.vision import rgbd_io as R
from phjax.io import read_biwi_pose

BIWI = ("biwi_kinect_head_pose_samples",)
SLAM = ("rgbd_frames_slambook2_ch5",)
FRAMES = ("00054", "00427", "unknown")


# ------------------------------------------------------------------------------ intrinsics
def test_intrinsics_checked():
    good = R.CameraIntrinsics(525.0, 525.0, 319.5, 239.5, width=640, height=480)
    assert good.checked() is good
    for kw in ({"fx": np.nan}, {"fy": 0.0}, {"fx": -1.0}, {"cx": np.inf}, {"width": 0},
               {"height": -1}):
        args = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "width": 640,
                "height": 480, **kw}
        with pytest.raises(ValueError, match="intrinsics need finite fx, fy > 0"):
            R.CameraIntrinsics(**args).checked()


def test_intrinsics_scaled_keeps_pixel_centres():
    k = R.CameraIntrinsics(500.0, 510.0, 319.5, 239.5, width=640, height=480)
    p = np.array([0.1, -0.05, 1.3])
    u = k.fx * p[0] / p[2] + k.cx
    v = k.fy * p[1] / p[2] + k.cy
    s = k.scaled(0.5)
    us = s.fx * p[0] / p[2] + s.cx
    vs = s.fy * p[1] / p[2] + s.cy
    # resizing by 1/2 maps pixel centre u to (u + 0.5) / 2 - 0.5
    np.testing.assert_allclose([us, vs], [(u + 0.5) / 2 - 0.5, (v + 0.5) / 2 - 0.5], atol=1e-9)
    assert (s.width, s.height) == (320, 240)
    np.testing.assert_allclose(R.CameraIntrinsics.from_matrix(k.matrix, 640, 480).matrix,
                               k.matrix)


# ---------------------------------------------------------------------------- Biwi depth
@settings(max_examples=25)
@given(st.integers(1, 40), st.integers(1, 30), st.floats(0, 1), st.integers(0, 2**31 - 1))
def test_biwi_depth_round_trip(tmp_path_factory, h, w, frac, seed):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.4, 4.0, (h, w)) * (rng.uniform(size=(h, w)) < frac)
    path = tmp_path_factory.mktemp("biwi") / "d_depth.bin"
    R.write_biwi_depth(path, depth)
    back = R.read_biwi_depth(path)
    assert back.shape == (h, w) and back.dtype == np.float32
    np.testing.assert_allclose(back, np.rint(depth * 1000) / 1000, atol=1e-6)
    np.testing.assert_array_equal(back == 0, depth == 0)


def test_biwi_depth_samples():
    root = shared_path(*BIWI)
    for f in FRAMES:
        d = R.read_biwi_depth(root / f"frame_{f}_depth.bin")
        assert d.shape == (480, 640)
        valid = d[d > 0]
        assert 69_000 < valid.size < 74_000  # SOURCE.md: ~71 k pixels on the person
        assert 0.79 < valid.min() and valid.max() < 1.04


def _write(path, *chunks):
    path.write_bytes(b"".join(np.asarray(c[1], c[0]).tobytes() for c in chunks))


@pytest.mark.parametrize("chunks, message", [
    ([("<i4", [4, 2]), ("<i4", [1, 2]), ("<i2", [800, 900])], "truncated at byte"),
    ([("<i4", [0, 2])], "bad Biwi depth image size"),
    ([("<i4", [4, 2]), ("<i4", [6, 4]), ("<i2", [1, 2, 3, 4])], "bad run"),
    ([("<i4", [2, 1]), ("<i4", [0, 2]), ("<i2", [1, 2]), ("<i4", [0])], "trailing bytes"),
    ([("<i4", [4, 1]), ("<i4", [0, 4]), ("<i2", [1, 2])], "truncated run"),
    ([("<i4", [4, 1]), ("<i4", [-1, 2])], "bad run"),
])
def test_biwi_depth_malformed(tmp_path, chunks, message):
    p = tmp_path / "x_depth.bin"
    _write(p, *chunks)
    with pytest.raises(R.RGBDFormatError, match=message) as e:
        R.read_biwi_depth(p)
    assert str(p) in str(e.value)
    (tmp_path / "short.bin").write_bytes(b"\x01\x00")
    with pytest.raises(R.RGBDFormatError, match="too short"):
        R.read_biwi_depth(tmp_path / "short.bin")


def test_biwi_calibration(tmp_path):
    cal = R.read_biwi_calibration(shared_path(*BIWI, "rgb.cal"))
    assert (cal.intrinsics.fx, cal.intrinsics.cx, cal.intrinsics.cy) == (517.679, 320, 240.5)
    np.testing.assert_allclose(cal.translation, [-0.0240198, 0.0058896, -0.0132308])
    dcal = R.read_biwi_calibration(shared_path(*BIWI, "depth.cal"))
    assert dcal.intrinsics.fx == 575.816
    np.testing.assert_array_equal(dcal.rotation, np.eye(3))
    text = shared_path(*BIWI, "rgb.cal").read_text()
    (tmp_path / "short.cal").write_text(text.rsplit("640", 1)[0])
    with pytest.raises(R.RGBDFormatError, match="expected 27 numbers"):
        R.read_biwi_calibration(tmp_path / "short.cal")
    (tmp_path / "word.cal").write_text(text.replace("517.679", "fx", 1))
    with pytest.raises(R.RGBDFormatError, match="non-numeric"):
        R.read_biwi_calibration(tmp_path / "word.cal")
    (tmp_path / "rot.cal").write_text(text.replace("0.999947", "2.0", 1))
    with pytest.raises(R.RGBDFormatError, match="not a rotation"):
        R.read_biwi_calibration(tmp_path / "rot.cal")


# ------------------------------------------------------------------------------ registration
def _register_reference(depth, kd, kc, rot, trans):
    """Independent forward warp with a per-pixel Python z-buffer."""
    out = np.zeros((kc.height, kc.width))
    for i, j in zip(*np.nonzero(depth > 0)):
        z = depth[i, j]
        p = np.array([(j - kd.cx) * z / kd.fx, (i - kd.cy) * z / kd.fy, z])
        q = rot @ p + trans
        u = int(np.round(kc.fx * q[0] / q[2] + kc.cx))
        v = int(np.round(kc.fy * q[1] / q[2] + kc.cy))
        if 0 <= u < kc.width and 0 <= v < kc.height and (out[v, u] == 0 or q[2] < out[v, u]):
            out[v, u] = q[2]
    return out


@settings(max_examples=10)
@given(st.integers(0, 2**31 - 1))
def test_register_depth_matches_reference(seed):
    rng = np.random.default_rng(seed)
    kd = R.CameraIntrinsics(60.0, 62.0, 15.5, 11.5, width=32, height=24)
    kc = R.CameraIntrinsics(55.0, 54.0, 16.0, 12.0, width=30, height=26)
    depth = rng.uniform(0.5, 2.0, (24, 32)) * (rng.uniform(size=(24, 32)) < 0.7)
    a = rng.normal(size=3) * 0.05
    c, s = np.cos(a[2]), np.sin(a[2])
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    trans = rng.normal(size=3) * 0.03
    got = np.asarray(R.register_depth(depth.astype(np.float64), kd, kc, rot, trans))
    ref = _register_reference(depth, kd, kc, rot, trans)
    # rounding ties at exactly .5 could differ; compare where the reference is unambiguous
    assert np.mean(np.isclose(got, ref, atol=1e-9)) > 0.99


def test_register_depth_identity():
    k = R.CameraIntrinsics(500.0, 500.0, 20.0, 15.0, width=40, height=30)
    d = np.random.default_rng(0).uniform(0.5, 3, (30, 40)).astype(np.float32)
    d[5:9, 7:20] = 0
    out = np.asarray(R.register_depth(d, k, k, np.eye(3), np.zeros(3)))
    np.testing.assert_allclose(out, d, rtol=1e-6)


def test_biwi_registration_direction():
    """The registered silhouette lies on the colour image's edges only for p_rgb = R p + t."""
    import cv2

    root = shared_path(*BIWI)
    rgb, dep = R.read_biwi_calibration(root / "rgb.cal"), R.read_biwi_calibration(
        root / "depth.cal")
    raw = R.read_biwi_depth(root / "frame_00054_depth.bin")
    grey = cv2.imread(str(root / "frame_00054_rgb.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    grad = np.hypot(cv2.Sobel(grey, cv2.CV_64F, 1, 0), cv2.Sobel(grey, cv2.CV_64F, 0, 1))

    def edge_strength(rot, trans):
        d = np.asarray(R.register_depth(raw, dep.intrinsics, rgb.intrinsics, rot, trans))
        m = cv2.morphologyEx((d > 0).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5)))
        edge = m - cv2.erode(m, np.ones((3, 3), np.uint8))
        return grad[edge > 0].mean()

    right = edge_strength(rgb.rotation, rgb.translation)
    inverse = edge_strength(rgb.rotation.T, -rgb.rotation.T @ rgb.translation)
    assert right > 2 * inverse


def test_read_biwi_sequence_and_ground_truth():
    root = shared_path(*BIWI)
    seq = R.open_rgbd(root)
    assert len(seq) == 3 and seq.ground_truth_kind == "head"
    np.testing.assert_allclose(seq.timestamps[:2], [54 / 30, 427 / 30])
    assert seq.timestamps[2] > seq.timestamps[1]  # 'unknown' continues after the last number
    f = seq[0]
    assert f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    assert 50_000 < np.count_nonzero(f.depth) < 75_000
    cal = R.read_biwi_calibration(root / "rgb.cal")
    r, t = read_biwi_pose(root / "frame_00054_pose.txt")
    _, tc = R.biwi_pose_in_color_frame(r, t, cal)
    np.testing.assert_allclose(seq.ground_truth.positions[0], tc)
    np.testing.assert_allclose(tc, cal.rotation @ t + cal.translation)
    # the head centre projects inside the face region, near the registered depth's face
    u = f.intrinsics.fx * tc[0] / tc[2] + f.intrinsics.cx
    v = f.intrinsics.fy * tc[1] / tc[2] + f.intrinsics.cy
    assert 280 < u < 370 and 160 < v < 270
    assert len(seq[1:]) == 2 and seq[1:].ground_truth.positions.shape == (2, 3)


# ------------------------------------------------------------------------------------- TUM
def _associate_reference(ta, tb, max_diff):
    cands = sorted((abs(a - b), i, j) for i, a in enumerate(ta) for j, b in enumerate(tb)
                   if abs(a - b) <= max_diff)
    ua, ub, out = set(), set(), []
    for _, i, j in cands:
        if i not in ua and j not in ub:
            ua.add(i)
            ub.add(j)
            out.append((i, j))
    return sorted(out)


@settings(max_examples=40)
@given(st.lists(st.floats(0, 5), max_size=25), st.lists(st.floats(0, 5), max_size=25),
       st.sampled_from([0.02, 0.2, 1.0]))
def test_associate_matches_greedy_reference(ta, tb, max_diff):
    ia, ib = R.associate(ta, tb, max_diff)
    got = list(zip(ia.tolist(), ib.tolist()))
    ref = _associate_reference(ta, tb, max_diff)
    # ties in |difference| may be resolved differently; the pair costs must agree
    cost = lambda pairs: sorted(round(abs(ta[i] - tb[j]), 12) for i, j in pairs)
    assert len(got) == len(ref) and cost(got) == cost(ref)
    assert len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib)


def _frames(n=3, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    k = R.CameraIntrinsics(30.0, 30.0, 15.5, 11.5, width=w, height=h)
    out = []
    for i in range(n):
        color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        depth = (rng.uniform(0.5, 5.0, (h, w)) * (rng.uniform(size=(h, w)) < 0.8)).astype(
            np.float32)
        out.append(R.RGBDFrame(color, depth, k, 100.0 + i / 30, str(i)))
    return out


def test_tum_round_trip(tmp_path):
    frames = _frames()
    folder = tmp_path / "rgbd_dataset_freiburg2_test"
    R.write_tum_rgbd(folder, frames)
    seq = R.open_rgbd(folder)
    assert len(seq) == 3 and seq.ground_truth is None
    assert (seq.intrinsics.fx, seq.intrinsics.cy) == R.TUM_INTRINSICS["freiburg2"][::3]
    for a, b in zip(frames, seq):
        np.testing.assert_array_equal(b.color, a.color)
        np.testing.assert_allclose(b.depth, a.depth, atol=0.5 / 5000 + 1e-7)
        assert b.timestamp == pytest.approx(a.timestamp, abs=1e-6)
    own = R.CameraIntrinsics(1.0, 2.0, 3.0, 4.0, width=32, height=24)
    assert R.read_tum_rgbd(folder, intrinsics=own).intrinsics is own
    # TUM ground truth is attached by timestamp
    (folder / "groundtruth.txt").write_text(
        "# t tx ty tz qx qy qz qw\n100.0 1 2 3 0 0 0 1\n200 0 0 0 0 0 0 1\n")
    gt = R.read_tum_rgbd(folder).ground_truth
    np.testing.assert_allclose(gt.positions[0], [1, 2, 3])
    assert np.isnan(gt.positions[2]).all()


def test_tum_malformed(tmp_path):
    folder = tmp_path / "seq"
    R.write_tum_rgbd(folder, _frames(2))
    (folder / "depth.txt").unlink()
    with pytest.raises(R.RGBDFormatError):
        R.read_tum_rgbd(folder)
    R.write_tum_rgbd(folder, _frames(2))
    (folder / "rgb.txt").write_text("# header\n100.0\n")
    with pytest.raises(R.RGBDFormatError, match="line 2: expected 'timestamp filename'"):
        R.read_tum_rgbd(folder)
    (folder / "rgb.txt").write_text("abc rgb/x.png\n")
    with pytest.raises(R.RGBDFormatError, match="bad timestamp"):
        R.read_tum_rgbd(folder)
    (folder / "rgb.txt").write_text("500.0 rgb/x.png\n")
    with pytest.raises(R.RGBDFormatError, match="no colour/depth pair"):
        R.read_tum_rgbd(folder)
    (folder / "rgb.txt").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(R.RGBDFormatError, match=r"rgb.txt: not a UTF-8 text file \(byte 0"):
        R.read_tum_rgbd(folder)


# ----------------------------------------------------------------------------- PGM / pairs
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_pgm_round_trip(tmp_path, dtype):
    img = np.random.default_rng(1).integers(0, np.iinfo(dtype).max, (7, 5)).astype(dtype)
    R.write_pgm(tmp_path / "a.pgm", img)
    back = R.read_pgm(tmp_path / "a.pgm")
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, img)
    if dtype == np.uint16:  # big-endian on disk
        raw = (tmp_path / "a.pgm").read_bytes()
        assert raw[-2:] == int(img[-1, -1]).to_bytes(2, "big")


def test_pgm_malformed(tmp_path):
    p = tmp_path / "b.pgm"
    p.write_bytes(b"P2\n2 2\n255\n1 2 3 4")
    with pytest.raises(R.RGBDFormatError, match="not a binary PGM"):
        R.read_pgm(p)
    p.write_bytes(b"P5\n4 4\n65535\n" + b"\x00" * 10)
    with pytest.raises(R.RGBDFormatError, match="truncated PGM data"):
        R.read_pgm(p)
    p.write_bytes(b"P5\n# comment\n4 x\n255\n")
    with pytest.raises(R.RGBDFormatError, match="bad PGM header"):
        R.read_pgm(p)
    p.write_bytes(b"P5\n4")
    with pytest.raises(R.RGBDFormatError, match="truncated PGM header"):
        R.read_pgm(p)


def test_slambook_frames():
    import cv2

    root = shared_path(*SLAM)
    seq = R.open_rgbd(root)
    assert len(seq) == 5 and seq.ground_truth_kind == "camera"
    k = seq.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == R.SLAMBOOK_INTRINSICS
    f = seq[2]
    raw = cv2.imread(str(root / "depth" / "3.pgm"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(f.depth, raw / 1000.0, rtol=1e-6)
    valid = np.count_nonzero(f.depth)
    assert 200_000 < valid < 230_000 and f.depth.max() < 10
    poses = R.read_pose_list(root / "pose.txt")
    np.testing.assert_allclose(poses.positions[0], [-0.228993, 0.00645704, 0.0287837])
    np.testing.assert_allclose(poses.quaternions[0][[1, 2, 3, 0]],
                               np.array([-0.0004327, -0.113131, -0.0326832, 0.993042])
                               / np.linalg.norm([-0.0004327, -0.113131, -0.0326832, 0.993042]))
    np.testing.assert_allclose(seq.ground_truth.positions, poses.positions)


def test_pose_list_and_pairs_malformed(tmp_path):
    p = tmp_path / "pose.txt"
    p.write_text("1 2 3 0 0 0\n")
    with pytest.raises(R.RGBDFormatError, match="line 1: expected 7 values"):
        R.read_pose_list(p)
    p.write_text("1 2 3 0 0 0 0\n")
    with pytest.raises(R.RGBDFormatError, match="zero quaternion"):
        R.read_pose_list(p)
    f = _frames(1)[0]
    (tmp_path / "color").mkdir()
    (tmp_path / "depth").mkdir()
    R._write_png(tmp_path / "color" / "1.png", f.color)
    R.write_pgm(tmp_path / "depth" / "1.pgm", np.zeros((24, 31), np.uint16))
    with pytest.raises(R.RGBDFormatError, match="depth size"):
        R.read_rgbd_pair(tmp_path / "color" / "1.png", tmp_path / "depth" / "1.pgm",
                         (30, 30, 15, 11))
    R.write_pgm(tmp_path / "depth" / "1.pgm", (f.depth * 1000).astype(np.uint16))
    fr = R.read_rgbd_pair(tmp_path / "color" / "1.png", tmp_path / "depth" / "1.pgm",
                          (30, 30, 15, 11))
    np.testing.assert_allclose(fr.depth, np.floor(f.depth * 1000) / 1000, atol=1e-6)
    p.write_text("0 0 0 0 0 0 1\n0 0 0 0 0 0 1\n")
    with pytest.raises(R.RGBDFormatError, match="2 poses for 1 frames"):
        R.open_rgbd(tmp_path)


def test_open_rgbd_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        R.open_rgbd(tmp_path / "missing")
    with pytest.raises(R.RGBDFormatError, match="unrecognised RGB-D source"):
        R.open_rgbd(tmp_path)
    with pytest.raises(ValueError, match="synthetic"):
        R.open_rgbd("synthetic:x")
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(R.RGBDFormatError, match="not a readable image"):
        R.read_image(tmp_path / "broken.png")


def _complete_images() -> dict[str, bytes]:
    """Complete image files of the layouts a truncation check must walk: a real photo as
    distributed (AFLW2000-3D), the same image re-encoded progressive, with restart markers,
    with an EXIF thumbnail (a whole JPEG, end marker included, inside an APP1 segment), with a
    phone's appended video (bytes after the end marker), and as PNG."""
    cv2 = pytest.importorskip("cv2")
    photo = (shared_path("aflw2000_3d_sample") / "image00050.jpg").read_bytes()
    img = cv2.imdecode(np.frombuffer(photo, np.uint8), cv2.IMREAD_COLOR)

    def jpeg(im, *params):
        return cv2.imencode(".jpg", im, list(params))[1].tobytes()

    thumb = jpeg(img[::8, ::8])
    exif = photo[:2] + b"\xff\xe1" + (len(thumb) + 8).to_bytes(2, "big") + b"Exif\0\0" \
        + thumb + photo[2:]
    video = np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes()
    return {"photo": photo, "progressive": jpeg(img, cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
            "restart markers": jpeg(img, cv2.IMWRITE_JPEG_RST_INTERVAL, 2),
            "exif thumbnail": exif, "appended video": exif + video,
            "png": cv2.imencode(".png", img)[1].tobytes()}


def test_truncated_images_are_refused_before_decoding(tmp_path, capfd):
    """A JPEG or PNG file cut anywhere after its signature (an interrupted copy) is a one-line
    RGBDFormatError naming it, and libjpeg / libpng print nothing (they are not called);
    complete files of every layout read as before. Reference: Pillow, which decodes the whole
    file and refuses exactly the same cuts (150 cut points spread over each file) except in
    its last 32 bytes."""
    import io

    from PIL import Image

    def pillow_reads(data: bytes) -> bool:
        try:
            with Image.open(io.BytesIO(data)) as im:
                im.load()
            return True
        except (OSError, SyntaxError):  # Pillow's error for a broken PNG chunk is a SyntaxError
            return False

    path = tmp_path / "image"
    for name, data in _complete_images().items():
        assert pillow_reads(data) and not R._truncated(data), name
        path.write_bytes(data)
        assert R.read_image(path).ndim == 3, name
        end = len(data) if name != "appended video" else len(data) - 50_000
        for cut in np.linspace(8, end - 33, 150).astype(int):
            assert R._truncated(data[:cut]) == (not pillow_reads(data[:cut])), (name, cut)
        # cut within its last 32 bytes (the end marker; PNG: the compressed stream's checksum,
        # the last chunk's and the IEND chunk): refused too, as OpenCV refuses them (Pillow
        # reads a PNG missing its last 21 bytes, and libjpeg forgives a missing end marker
        # after restart markers)
        assert all(R._truncated(data[:cut]) for cut in range(end - 32, end)), name
        cuts = [end // 2]
        path.write_bytes(data[:cuts[0]])
        with pytest.raises(R.RGBDFormatError, match="truncated: the file ends before its image"):
            R.read_image(path)
    path.write_bytes(b"")
    with pytest.raises(R.RGBDFormatError, match="empty file"):
        R.read_image(path)
    assert capfd.readouterr().err == ""


def test_synthetic_adapter():
    """``open_rgbd("synthetic:N:SEED")`` wraps phjax.vision.synthetic_rgbd: BGR, intrinsics, GT."""
    from phjax.vision.synthetic_rgbd import synthetic_rgbd_sequence

    kw = {"width": 160, "height": 120, "fx": 131.25, "fy": 131.25}
    seq = R.synthetic_rgbd(2, seed=3, **kw)
    raw = synthetic_rgbd_sequence(2, seed=3, **kw)
    f, g = seq[1], raw[1]
    np.testing.assert_array_equal(f.color, g.color[..., ::-1])
    np.testing.assert_array_equal(f.depth, g.depth)
    assert (f.intrinsics.fx, f.intrinsics.cx, f.intrinsics.width) == (131.25, 79.5, 160)
    assert seq.ground_truth_kind == "head" and f.timestamp == g.timestamp
    np.testing.assert_allclose(seq.ground_truth.positions[1], g.head_position)
    np.testing.assert_allclose(seq.ground_truth.quaternions[1], g.head_quaternion)
    assert len(R.open_rgbd("synthetic:2:3", **kw)) == 2
