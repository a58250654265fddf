"""YuNet face detection: model cache (no network), both backends on the Biwi samples."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from conftest import shared_path, yunet_models
from hypothesis import given, settings
from hypothesis import strategies as st

from phjax.vision import face_detection as F
from phjax.vision import rgbd_io as R

FRAMES = ("00054", "00427", "unknown")


@pytest.fixture
def model_cache(tmp_path, monkeypatch):
    """A model cache in tmp_path seeded from the shared folder; torch hub also in tmp_path."""
    src = yunet_models()
    cache = tmp_path / "models"
    monkeypatch.setenv("PHJAX_MODEL_DIR", str(cache))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    F.seed_model_cache(src)
    return cache


@pytest.fixture(scope="module")
def biwi_images():
    root = shared_path("biwi_kinect_head_pose_samples")
    return [R.read_image(root / f"frame_{f}_rgb.png") for f in FRAMES]


@pytest.fixture(scope="module")
def detectors(tmp_path_factory):
    """Both backends, loaded once for the module from a seeded cache."""
    src = yunet_models()
    cache = tmp_path_factory.mktemp("models")
    mp = pytest.MonkeyPatch()
    mp.setenv("TORCH_HOME", str(tmp_path_factory.mktemp("torch")))
    F.seed_model_cache(src, cache)
    dets = {b: F.FaceDetector(b, model_dir=cache) for b in F.BACKENDS}
    yield dets
    mp.undo()


# ------------------------------------------------------------------------------ model cache
def test_seed_model_cache(model_cache):
    names = sorted(p.name for p in model_cache.iterdir())
    assert names == ["face_detection_yunet_2023mar.onnx", "yunet_final.pth"]
    for m in F.MODELS.values():
        p = F.model_path(m)  # verified against the recorded sha256
        assert p.parent == model_cache
        assert hashlib.sha256(p.read_bytes()).hexdigest() == m.sha256
    # idempotent; unrelated files in the source folder are ignored
    again = F.seed_model_cache(yunet_models())
    assert sorted(p.name for p in again) == names


def test_model_dir_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("PHJAX_MODEL_DIR", raising=False)
    assert F.model_dir().parts[-3:] == (".cache", "phjax", "models")
    monkeypatch.setenv("PHJAX_MODEL_DIR", str(tmp_path))
    assert F.model_dir() == tmp_path
    assert F.model_dir(tmp_path / "x") == tmp_path / "x"


def test_missing_and_corrupt_models(tmp_path):
    with pytest.raises(F.ModelNotFoundError) as e:
        F.model_path("yunet-onnx", tmp_path)
    msg = str(e.value)
    assert "download_model" in msg and "PHJAX_MODEL_DIR" in msg and F.YUNET_ONNX.urls[0] in msg
    (tmp_path / F.YUNET_ONNX.filename).write_bytes(b"corrupt")
    with pytest.raises(ValueError, match="sha256"):
        F.model_path(F.YUNET_ONNX, tmp_path)
    with pytest.raises(ValueError, match="unknown model"):
        F.model_path("nope", tmp_path)
    with pytest.raises(F.ModelNotFoundError):
        F.FaceDetector("opencv", model_dir=tmp_path / "empty")


def test_download_model_from_file_url(tmp_path):
    """The urllib download path (file:// URLs, so no network): verify, rename, clean up."""
    payload = b"weights" * 100
    src = tmp_path / "served.bin"
    src.write_bytes(payload)
    good = F.ModelFile("toy", "toy.bin", hashlib.sha256(payload).hexdigest(), len(payload),
                       ("file:///nonexistent/toy.bin", src.as_uri()))
    out = F.download_model(good, tmp_path / "cache")
    assert out.read_bytes() == payload
    bad = F.ModelFile("toy", "bad.bin", "0" * 64, len(payload), (src.as_uri(),))
    with pytest.raises(OSError, match="could not download"):
        F.download_model(bad, tmp_path / "cache")
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["toy.bin"]


# ------------------------------------------------------------------------------ result type
@settings(max_examples=30)
@given(st.lists(st.floats(-1e3, 1e3), min_size=14, max_size=14), st.floats(0, 1),
       st.floats(0.1, 4), st.floats(0.1, 4))
def test_face_detection_array_and_scaling(vals, score, sx, sy):
    row = np.asarray(vals + [score], np.float32)
    f = F.FaceDetection.from_array(row)
    np.testing.assert_array_equal(f.to_array(), row)
    g = f.scaled(sx, sy).scaled(1 / sx, 1 / sy)
    np.testing.assert_allclose(g.landmarks, f.landmarks, atol=1e-2)
    np.testing.assert_allclose(g.box, f.box, atol=1e-2)
    # scaling maps pixel centres: the box centre moves like a landmark at the centre
    c = f.scaled(sx, sy).center
    np.testing.assert_allclose(c, (f.center + 0.5) * [sx, sy] - 0.5, rtol=1e-4, atol=1e-2)


# ------------------------------------------------------------------------------- detection
def _check_face(face, shape):
    x, y, w, h = face.box
    assert 0.6 <= face.score <= 1.0
    assert 40 < w < 200 and 40 < h < 200 and 0 <= x and x + w <= shape[1]
    lm = face.landmarks
    assert lm.shape == (5, 2)
    inside = (lm[:, 0] > x - 5) & (lm[:, 0] < x + w + 5) & (lm[:, 1] > y - 5) & (
        lm[:, 1] < y + h + 5)
    assert inside.all()
    # order: subject's right eye on the image left, nose below the eyes, mouth below the nose
    assert lm[0, 0] < lm[1, 0] and lm[3, 0] < lm[4, 0]
    assert lm[2, 1] > max(lm[0, 1], lm[1, 1]) and min(lm[3, 1], lm[4, 1]) > lm[2, 1] - 5


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_one_face_per_biwi_frame(detectors, biwi_images, backend):
    for img in biwi_images:
        faces = detectors[backend].detect(img)
        assert len(faces) == 1, [f.score for f in faces]
        _check_face(faces[0], img.shape)


def test_backends_agree_within_8px(detectors, biwi_images):
    cv = [detectors["opencv"].detect(img)[0] for img in biwi_images]
    kn = detectors["kornia"].detect_batch(biwi_images)  # batched path
    for a, b in zip(cv, kn):
        d = np.linalg.norm(a.landmarks - b[0].landmarks, axis=1)
        assert d.max() < 8.0, d
        # boxes overlap strongly (IoU)
        x0, y0 = np.maximum(a.box[:2], b[0].box[:2])
        x1, y1 = np.minimum(a.box[:2] + a.box[2:], b[0].box[:2] + b[0].box[2:])
        inter = max(x1 - x0, 0) * max(y1 - y0, 0)
        union = np.prod(a.box[2:]) + np.prod(b[0].box[2:]) - inter
        assert inter / union > 0.7


def test_batch_equals_single_and_full_resolution(detectors, biwi_images, model_cache):
    kn = detectors["kornia"]
    batch = kn.detect_batch(biwi_images)
    for img, faces in zip(biwi_images, batch):
        single = kn.detect(img)
        np.testing.assert_allclose(single[0].landmarks, faces[0].landmarks, atol=1e-3)
    full = F.FaceDetector("opencv", detect_width=None)  # full 640x480 input
    small = detectors["opencv"]
    for img in biwi_images:
        d = np.linalg.norm(full.detect(img)[0].landmarks - small.detect(img)[0].landmarks, axis=1)
        assert d.max() < 10.0


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_no_face(detectors, backend):
    rng = np.random.default_rng(0)
    blank = np.zeros((480, 640, 3), np.uint8)
    noise = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    out = detectors[backend].detect_batch([blank, noise])
    assert out == [[], []]


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_frames_smaller_than_the_network_input(detectors, biwi_images, backend):
    """Frames under kornia's 64 px pooling limit are padded, not an exception (opencv pads
    internally); a face found there lies inside the frame."""
    cv2 = pytest.importorskip("cv2")
    for w, h in [(1, 1), (16, 16), (48, 48), (64, 48), (640, 40), (40, 640), (300, 2)]:
        img = cv2.resize(biwi_images[0], (w, h), interpolation=cv2.INTER_AREA)
        for f in detectors[backend].detect(img):
            c = f.center
            assert 0 <= c[0] < w and 0 <= c[1] < h, (w, h, f)


def test_bad_input(detectors):
    with pytest.raises(ValueError, match="uint8"):
        detectors["opencv"].detect(np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match="backend"):
        F.FaceDetector("dlib")


# ------------------------------------------------------------------- plausibility, arguments
AFLW_IDS = ("00050", "00081", "00251", "00430", "00475", "00514", "00516", "01038", "01322",
            "02283", "02420", "02545", "02616", "03324", "03614", "04331")


def _noise(rng, kind, h, w):
    if kind == "uniform":
        return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    if kind == "uniform_grey":
        return rng.integers(0, 256, (h, w, 1), dtype=np.uint8).repeat(3, 2)
    if kind == "gauss":
        return np.clip(rng.normal(128, 40, (h, w, 3)), 0, 255).astype(np.uint8)
    return (rng.random((h, w, 1)) > 0.5).astype(np.uint8).repeat(3, 2) * 255  # salt-pepper


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_no_face_in_pixel_noise_and_every_face_kept(detectors, backend, monkeypatch):
    """The plausibility check (pixels in the box spatially correlated, at most a quarter of the
    box outside the image): the kornia weights found a face over most of square and portrait
    noise frames with scores up to 0.999 (measured before the check: 68 of 99 such frames at
    its default threshold). Now no noise frame has a face, and every AFLW face found without
    the check is still found, upright and rotated in the image plane by 45 degrees, at the
    same place (the check only removes detections; measured:
    pixel correlation 0.86-0.997 in faces, at most 0.18 in noise; the bound is 0.5)."""
    cv2 = pytest.importorskip("cv2")
    det = detectors[backend]
    rng = np.random.default_rng(5)
    hits = []
    for h, w in [(320, 320), (450, 450), (600, 450), (640, 640), (240, 320)]:
        for kind in ("uniform", "uniform_grey", "gauss", "saltpepper"):
            faces = det.detect(_noise(rng, kind, h, w))
            if faces:
                hits.append((kind, h, w, round(faces[0].score, 3)))
    assert hits == []
    root = shared_path("aflw2000_3d_sample")
    found = 0
    for i in AFLW_IDS:
        img = cv2.imread(str(root / f"image{i}.jpg"))
        for ang in (0.0, -45.0, 45.0):
            a = cv2.getRotationMatrix2D((224.5, 224.5), ang, 1.0)
            im = cv2.warpAffine(img, a, (450, 450), borderMode=cv2.BORDER_REPLICATE)
            with monkeypatch.context() as m:
                m.setattr(F, "plausible_detection", lambda face, image: True)
                unchecked = det.detect(im)
            faces = det.detect(im)
            assert len(faces) == len(unchecked), (i, ang)
            for f, g in zip(faces, unchecked):
                np.testing.assert_array_equal(f.box, g.box)
            found += bool(faces)
    print(f"{backend}: {found} of 48 faces")
    assert found >= 40  # of 48, so the comparison above is not empty (measured: 44 OpenCV,
    # 46 kornia; the others are not found at 45 degrees with or without the check)


def test_a_box_mostly_outside_the_image_is_rejected(detectors, biwi_images):
    """A detection reaching more than a quarter of its width past the image is dropped, for
    either backend (the check is applied in FaceDetector, not in a backend)."""
    for det in detectors.values():
        img = biwi_images[0]
        small, sx, sy = det._resize(img)
        row = det._impl([small])[0][0].copy()
        impl = det._impl
        try:
            for shift, kept in ((0.0, True), (0.2, True), (0.3, False), (0.6, False)):
                moved = row.copy()
                moved[0] = -shift * row[2]  # box from the left edge, `shift` of it outside
                det._impl = lambda imgs, r=moved: [r[None]]
                assert bool(det.detect(img)) == kept, (det.backend, shift)
        finally:
            det._impl = impl


@pytest.mark.parametrize("backend", F.BACKENDS)
def test_detector_arguments_are_checked_and_top_k_means_the_same(detectors, backend,
                                                                 model_cache, biwi_images):
    """Bad thresholds were a cv2.error late (OpenCV) or 20 / 0 faces (kornia); top_k=0 meant
    1 face on OpenCV and 0 on kornia. Now a ValueError when built, and top_k is the number of
    faces returned on both backends."""
    bad = [{"score_threshold": -1.0}, {"score_threshold": float("nan")},
           {"score_threshold": 2.0}, {"score_threshold": "0.5"},
           {"nms_threshold": float("nan")}, {"nms_threshold": 0.0}, {"nms_threshold": 1.5},
           {"top_k": 0}, {"top_k": -1}, {"top_k": 2.5}, {"top_k": True}]
    for kw in bad:
        with pytest.raises(ValueError, match=next(iter(kw))):
            F.FaceDetector(backend, **kw)
    # two faces side by side: top_k=1 returns the better one, top_k=2 both
    pair = np.concatenate([biwi_images[0][:, 160:480], biwi_images[1][:, 160:480]], axis=1)
    both = detectors[backend].detect(pair)
    assert len(both) == 2
    for k in (1, 2):
        faces = F.FaceDetector(backend, top_k=k, score_threshold=0.5).detect(pair)
        assert len(faces) == k
        np.testing.assert_allclose(faces[0].box, both[0].box, atol=1e-3)
