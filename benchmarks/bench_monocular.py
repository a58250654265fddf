"""Monocular (colour-only) head pose: accuracy on labelled photos and speed at 640x480.

    python benchmarks/bench_monocular.py [--repeats 3] [--live-seconds 8] [--skip-live]

Estimators (:class:`phjax.vision.monocular.MonocularHeadPose`):

* ``net``: opentrack's head-pose network (onnxruntime, one thread) on a YuNet box
  (the default of ``phjax live``); ``net, tracked``: the same image a second time, cropped at
  the network's own box of the first pass (what every video frame after the first sees);
  ``net, localizer box``: opentrack's head localizer instead of YuNet;
* ``landmarks``: YuNet's five landmarks + PnP against a generic face (the earlier front end,
  now a fallback option).

Tables (Markdown on stdout):

1. Accuracy on the 16 labelled AFLW2000-3D photos of ``shared/data/aflw2000_3d_sample``
   (450 x 450; intrinsics from a 45 degree field of view, which only the landmark method
   uses): poses returned, MAE of pitch / yaw / roll (the Hopenet / 6DRepNet protocol: Euler
   angles in the labels' convention, see SOURCE.md), their mean, geodesic error. The network's
   rotation is compared as seen in the crop (``crop_quaternion``; the labels come from a
   weak-perspective fit, relative to the viewing ray), the landmark method's camera-frame
   rotation is turned into the same frame by the inverse ray rotation.
2. Depth: the estimated distance over the distance implied by the label's fitted 3D face
   (``Pose_Para`` scale: pixels per micrometre of the Basel face model, so the true distance is
   ``f / (scale * 1e6)`` for a focal length ``f``; the ratio does not depend on ``f``), and on
   the three Biwi frames of a calibrated Kinect colour camera (ground-truth head centre).
3. The synthetic head (``phjax.vision.synthetic_rgbd``, 640 x 480, exact ground truth):
   rotation relative to the first frame, absolute rotation, distance.
4. Time per frame at 640 x 480 (the AFLW photos on a grey 640 x 480 canvas, moving 6 px a
   frame): median / p90 ms and frames per second (1000 / mean ms) of the whole ``process`` call,
   per method, and its mean process CPU time (all threads; less sensitive to other jobs); then the parts: YuNet, the localizer and the pose network with onnxruntime
   (1 and 2 threads) and OpenCV's DNN module where it runs the model.
5. ``phjax live`` end to end: a video file (the moving photos, MJPG) through
   :class:`phjax.live.VideoSource` and the live tracker (render loop at 120 Hz, real clock),
   frames processed per second.

Models: the model cache (``--model-dir`` / ``$PHJAX_MODEL_DIR``), seeded from
``shared/data/head_pose_models`` and ``shared/data/yunet_face_detection`` when files are missing.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.datasets import shared_data_dir
from _models import seeded_cache
from phjax.vision import face_detection as F
from phjax.vision.monocular import (
    MonocularHeadPose,
    intrinsics_from_fov,
    ray_quaternion,
)

P = np.diag([1.0, 1.0, -1.0])


def _rotation():
    from scipy.spatial.transform import Rotation

    return Rotation


def label_matrix(pitch, yaw, roll):
    """AFLW2000-3D label -> head-to-image rotation (``aflw2000_3d_sample/SOURCE.md``)."""
    return P @ _rotation().from_euler("XYZ", [pitch, -yaw, roll]).as_matrix() @ P


def matrix(q):
    return _rotation().from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def euler_deg(m):
    e = _rotation().from_matrix(P @ m @ P).as_euler("XYZ")
    return np.degrees([e[0], -e[1], e[2]])


def geodesic_deg(a, b):
    return float(np.degrees(_rotation().from_matrix(a.T @ b).magnitude()))


def _crop_rotation(r):
    """The rotation relative to the viewing ray (the labels' frame) of any result."""
    if r.method == "net":
        return matrix(r.crop_quaternion)
    return matrix(np_qmul(np_qconj(ray_quaternion(r.position)), r.quaternion))


def _aflw(data):
    import cv2
    from scipy.io import loadmat

    root = data / "aflw2000_3d_sample"
    out = []
    for p in sorted(root.glob("image*.jpg")):
        out.append((p.stem[5:], cv2.imread(str(p)), loadmat(p.with_suffix(".mat"))))
    return out


# ----------------------------------------------------------------------------- accuracy
def accuracy_table(photos, cache):
    intr = intrinsics_from_fov(450, 450, 45.0)
    det = F.FaceDetector("opencv", model_dir=cache)
    variants = {
        "net (YuNet box)": {"method": "net", "detector": det, "track": False},
        "net, tracked (2nd pass from its own box)": {"method": "net", "detector": det,
                                                     "track": True},
        "net (localizer box)": {"method": "net", "detector": "localizer", "track": False},
        "landmarks (YuNet 5 points + PnP)": {"method": "landmarks", "detector": det},
    }
    print("## Accuracy on the AFLW2000-3D sample (16 photos, all labels within ±71°)\n")
    print("| estimator | poses | MAE pitch / yaw / roll [deg] | mean | geodesic mean / median "
          "/ max [deg] | worst |")
    print("|---|---|---|---|---|---|")
    per_image = {}
    for name, kw in variants.items():
        est = MonocularHeadPose(intr, model_dir=cache, **kw)
        errs, geo, ids = [], [], []
        for i, img, mat in photos:
            est.reset()
            r = est.process(img)
            if kw.get("track"):
                r = est.process(img)  # the second frame is cropped at the network's box
                assert r.face_source == "tracked" or not r.ok
            if not r.ok:
                continue
            pose = mat["Pose_Para"][0, :3]
            m = _crop_rotation(r)
            errs.append(np.abs(euler_deg(m) - np.degrees(pose)))
            geo.append(geodesic_deg(label_matrix(*pose), m))
            ids.append(i)
        errs, geo = np.array(errs), np.array(geo)
        per_image[name] = dict(zip(ids, geo))
        mae = errs.mean(0)
        w = int(np.argmax(geo))
        print(f"| {name} | {len(geo)} / {len(photos)} | {mae[0]:.2f} / {mae[1]:.2f} / "
              f"{mae[2]:.2f} | **{mae.mean():.2f}** | {geo.mean():.2f} / {np.median(geo):.2f} / "
              f"{geo.max():.2f} | {ids[w]} |")
    print("\nGeodesic error per image [deg] (labels pitch / yaw / roll in brackets):\n")
    names = list(variants)
    print("| image | label [deg] | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for i, _, mat in photos:
        lab = np.degrees(mat["Pose_Para"][0, :3])
        cells = [f"{per_image[n][i]:.1f}" if i in per_image[n] else "no pose" for n in names]
        print(f"| {i} | {lab[0]:.0f} / {lab[1]:.0f} / {lab[2]:.0f} | " + " | ".join(cells) + " |")


def depth_table(photos, cache, data):
    intr = intrinsics_from_fov(450, 450, 45.0)
    det = F.FaceDetector("opencv", model_dir=cache)
    f = float(intr.fy)
    print("\n## Depth from the assumed head size\n")
    print("Estimated over true distance (1.00 = exact). AFLW: the label's fitted 3D face gives "
          "the image scale s (px per µm of the Basel face model), so a point at that scale is "
          "at f / (s 1e6) for any focal length f; net: the distance of the head centre from "
          "its size, landmarks: the PnP distance of the pupils' midpoint. A weak-perspective "
          "label does not say which depth of the head its scale belongs to (the face and the "
          "head centre are ~9 cm apart, ~20 % of these photos' apparent distance at a 45° "
          "field of view), so on AFLW the spread (std, min, max) is the measurement, the level "
          "is not. Biwi: the annotated head centre, calibrated colour camera, one subject.\n")
    print("| data | estimator | n | median | mean | std | min | max |")
    print("|---|---|---|---|---|---|---|---|")
    for method in ("net", "landmarks"):
        est = MonocularHeadPose(intr, method=method, detector=det, model_dir=cache, track=False)
        ratios = []
        for _, img, mat in photos:
            est.reset()
            r = est.process(img)
            if r.ok:
                z = r.position[2]
                if method == "landmarks":  # the pupils' midpoint, not the model origin
                    z = (matrix(r.quaternion) @ est.model[:2].mean(0) + r.position)[2]
                ratios.append(z * mat["Pose_Para"][0, 6] * 1e6 / f)
        ratios = np.array(ratios)
        label = ("net (head size 0.20 m), head centre" if method == "net"
                 else "landmarks (IPD 63 mm), pupils")
        print(f"| AFLW sample | {label} | {len(ratios)} | {np.median(ratios):.3f} | "
              f"{ratios.mean():.3f} | {ratios.std():.3f} | {ratios.min():.3f} | "
              f"{ratios.max():.3f} |")
    root = data / "biwi_kinect_head_pose_samples"
    if not root.is_dir():
        return
    from phjax.io import biwi_pose_to_quaternion, read_biwi_pose
    from phjax.vision import rgbd_io as R

    cal = R.read_biwi_calibration(root / "rgb.cal")
    rows = []
    for method in ("net", "landmarks"):
        est = MonocularHeadPose(cal.intrinsics, method=method, detector=det, model_dir=cache,
                                track=False)
        ratios, rot = [], []
        for n in ("00054", "00427", "unknown"):
            fr = R.read_biwi_frame(root, n)
            rm, t = R.biwi_pose_in_color_frame(*read_biwi_pose(root / f"frame_{n}_pose.txt"),
                                               cal)
            est.reset()
            r = est.process(np.ascontiguousarray(fr.color[..., ::-1]))
            if r.ok:
                ratios.append(np.linalg.norm(r.position) / np.linalg.norm(t))
                rot.append(np.degrees(np.linalg.norm(np_rotvec(np_qmul(
                    np_qconj(biwi_pose_to_quaternion(rm)), r.quaternion)))))
        ratios = np.array(ratios)
        print(f"| Biwi (3 frames) | {method} | {len(ratios)} | {np.median(ratios):.3f} | "
              f"{ratios.mean():.3f} | {ratios.std():.3f} | {ratios.min():.3f} | "
              f"{ratios.max():.3f} |")
        rows.append((method, rot))
    for method, rot in rows:
        print(f"\nBiwi camera-frame orientation error ({method}): "
              + ", ".join(f"{x:.1f}" for x in rot) + " deg")


def synthetic_table(cache, n=24, stride=5):
    from phjax.vision import CameraIntrinsics, synthetic_rgbd_sequence

    seq = synthetic_rgbd_sequence(n * stride, depth_noise=False)
    k = seq.intrinsics
    intr = CameraIntrinsics(fx=float(k.fx), fy=float(k.fy), cx=float(k.cx), cy=float(k.cy),
                            width=seq.width, height=seq.height)
    frames = [np.ascontiguousarray(seq[i].color[..., ::-1]) for i in range(0, n * stride, stride)]
    gt = np_qmul(seq.head_quaternions[::stride][:n], np.array([0.0, 0.0, 0.0, 1.0]))
    gpos = seq.head_positions[::stride][:n]

    def ang(a, b):
        return np.degrees(np.linalg.norm(np_rotvec(np_qmul(a, np_qconj(b))), axis=-1))

    print(f"\n## Synthetic head ({n} frames, every {stride}th of a 30 Hz sequence, 640 x 480)\n")
    print("| estimator | poses | relative rotation error median / max [deg] | absolute "
          "median [deg] | distance error median / max [mm] |")
    print("|---|---|---|---|---|")
    for method in ("net", "landmarks"):
        est = MonocularHeadPose(intr, method=method, model_dir=cache)
        rs = [est.process(f_, i / 6) for i, f_ in enumerate(frames)]
        q = np.array([r.quaternion for r in rs])
        p = np.array([r.position for r in rs])
        ok = np.isfinite(q).all(1)
        rel = ang(np_qmul(q[ok], np_qconj(q[ok][:1])), np_qmul(gt[ok], np_qconj(gt[ok][:1])))
        dz = 1e3 * np.abs(p[ok, 2] - gpos[ok, 2])
        print(f"| {method} | {ok.sum()} / {n} | {np.median(rel):.2f} / {rel.max():.2f} | "
              f"{np.median(ang(q[ok], gt[ok])):.1f} | {np.median(dz):.0f} / {dz.max():.0f} |")
    moved = ang(np_qmul(gt, np_qconj(gt[:1])), np.array([1.0, 0, 0, 0]))
    print(f"\n(the head turns up to {moved.max():.0f} deg from the first frame)")


# ------------------------------------------------------------------------------- speed
def canvas_frames(photos, steps=12):
    """Each photo at 300 x 300 on a grey 640 x 480 canvas, moving 6 px a frame."""
    import cv2

    out = []
    for _, img, _ in photos:
        small = cv2.resize(img, (300, 300), interpolation=cv2.INTER_AREA)
        for s in range(steps):
            f = np.full((480, 640, 3), 128, np.uint8)
            x0 = 100 + 6 * s
            f[90:390, x0:x0 + 300] = small
            out.append(f)
    return out


def _time_calls(fn, items, repeats, cpu=None):
    """Wall-clock ms per call; with a list ``cpu``, also the process CPU ms of each call
    (all threads) appended to it: on a loaded machine the wall time includes waiting for a
    core, the CPU time mostly does not."""
    ts = []
    for _ in range(repeats):
        for it in items:
            c0, t0 = time.process_time(), time.perf_counter()
            fn(it)
            ts.append(time.perf_counter() - t0)
            if cpu is not None:
                cpu.append(1e3 * (time.process_time() - c0))
    return 1e3 * np.array(ts)


def speed_table(photos, cache, repeats):
    import cv2

    frames = canvas_frames(photos)
    intr = intrinsics_from_fov(640, 480, 60.0)
    print(f"\n## Time per frame at 640 x 480 ({len(frames)} frames x {repeats}; load average "
          f"{os.getloadavg()[0]:.1f} before)\n")
    print("| estimator | OK | median ms | p90 ms | frames/s (1000 / mean) | CPU ms / frame "
          "(mean) |")
    print("|---|---|---|---|---|---|")
    det = F.FaceDetector("opencv", model_dir=cache)
    variants = {
        "net, YuNet every frame": {"method": "net", "detector": det, "track": False},
        "net, tracked box (video; default)": {"method": "net", "detector": det, "track": True},
        "net, localizer every frame": {"method": "net", "detector": "localizer",
                                       "track": False},
        "landmarks (YuNet + PnP)": {"method": "landmarks", "detector": det},
    }
    for name, kw in variants.items():
        est = MonocularHeadPose(intr, model_dir=cache, **kw)
        for f_ in frames[:5]:
            est.process(f_)
        est.reset()
        oks: list[bool] = []
        cpu: list[float] = []
        ms = _time_calls(lambda f_, est=est, oks=oks: oks.append(est.process(f_).ok), frames,
                         repeats, cpu)
        print(f"| {name} | {np.mean(oks):.0%} | {np.median(ms):.2f} | "
              f"{np.percentile(ms, 90):.2f} | {1e3 / ms.mean():.0f} | {np.mean(cpu):.2f} |")

    # parts
    from phjax.vision._head_pose_net import HeadLocalizer, HeadPoseNet, crop_input

    greys = [cv2.cvtColor(f_, cv2.COLOR_BGR2GRAY) for f_ in frames]
    box = np.array([130.0, 110.0, 240.0, 260.0])
    print("\n| part | runtime | median ms | p90 ms |")
    print("|---|---|---|---|")
    ms = _time_calls(det.detect, frames, repeats)
    print(f"| YuNet (320 px wide input, incl. resize) | OpenCV | {np.median(ms):.2f} | "
          f"{np.percentile(ms, 90):.2f} |")
    ms = _time_calls(lambda g: crop_input(g, box), greys, repeats)
    print(f"| crop + brightness normalisation | NumPy / OpenCV | {np.median(ms):.2f} | "
          f"{np.percentile(ms, 90):.2f} |")
    x = crop_input(greys[0], box)[0]
    xl = np.zeros((1, 1, 224, 288), np.float32)
    for threads in (1, 2):
        net = HeadPoseNet(cache, threads=threads)
        ms = _time_calls(lambda _, net=net: net.run(x), range(len(frames)), repeats)
        print(f"| pose network | onnxruntime, {threads} thread{'s' if threads > 1 else ''} | "
              f"{np.median(ms):.2f} | {np.percentile(ms, 90):.2f} |")
        loc = HeadLocalizer(cache, threads=threads)
        ms = _time_calls(loc.locate, greys, repeats)
        print(f"| head localizer (incl. resize) | onnxruntime, {threads} thread"
              f"{'s' if threads > 1 else ''} | {np.median(ms):.2f} | "
              f"{np.percentile(ms, 90):.2f} |")
        ms = _time_calls(lambda _, loc=loc: loc.session.run(None, {"x": xl}), range(len(frames)),
                         repeats)
        print(f"| head localizer (network only) | onnxruntime, {threads} thread"
              f"{'s' if threads > 1 else ''} | {np.median(ms):.2f} | "
              f"{np.percentile(ms, 90):.2f} |")
    for name, model, inp in (("pose network", F.HEAD_POSE_ONNX, x),
                             ("head localizer (network only)", F.HEAD_LOCALIZER_ONNX, xl)):
        try:
            dnn = cv2.dnn.readNetFromONNX(str(F.model_path(model, cache)))
            outs = list(dnn.getUnconnectedOutLayersNames())

            def run(_, dnn=dnn, outs=outs, inp=inp):
                dnn.setInput(inp)
                return dnn.forward(outs)

            run(None)
            ms = _time_calls(run, range(len(frames)), repeats)
            print(f"| {name} | OpenCV DNN {cv2.__version__} | {np.median(ms):.2f} | "
                  f"{np.percentile(ms, 90):.2f} |")
        except cv2.error as e:
            msg = str(e).strip().splitlines()
            where = next((ln for ln in msg if "error:" in ln), msg[-1])[:90]
            print(f"| {name} | OpenCV DNN {cv2.__version__} | fails: `{where}` | - |")


def live_table(photos, cache, seconds):
    import cv2

    from phjax.live import LiveTracker, VideoSource

    frames = canvas_frames(photos, steps=20)
    with tempfile.TemporaryDirectory() as tmp:
        print(f"\n## phjax live, video file end to end (640 x 480 MJPG; render loop 120 Hz; "
              f"load average {os.getloadavg()[0]:.1f} before)\n")
        print("| file rate [Hz] | monocular | run [s] | frames processed | processed/s | "
              "poses OK | render Hz |")
        print("|---|---|---|---|---|---|---|")
        for fps in (30.0, 240.0):
            path = Path(tmp) / f"moving_{fps:.0f}.avi"
            n = int(seconds * fps)
            w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (640, 480))
            for i in range(n):
                w.write(frames[i % len(frames)])
            w.release()
            for method in ("net", "landmarks"):
                src = VideoSource(str(path), model_dir=cache, monocular=method)
                lt = LiveTracker(src, rate=120.0, linger=0.0)
                lt.run()
                s = lt.stats()
                ok = s["status"].get("OK", 0)
                print(f"| {fps:.0f} | {method} | {s['elapsed']:.1f} | {s['frames']} of {n} | "
                      f"{s['frames'] / s['elapsed']:.1f} | {ok / max(s['frames'], 1):.0%} | "
                      f"{s['render_hz']:.0f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="passes over the timing frames")
    ap.add_argument("--model-dir", default=None)
    ap.add_argument("--live-seconds", type=float, default=8.0,
                    help="length of the phjax live video runs, s")
    ap.add_argument("--skip-live", action="store_true")
    ap.add_argument("--skip-synthetic", action="store_true")
    args = ap.parse_args(argv)

    import cv2
    import onnxruntime

    data = shared_data_dir()
    if data is None or not (data / "aflw2000_3d_sample").is_dir():
        raise SystemExit("shared/data/aflw2000_3d_sample not found (set $PHJAX_SHARED_DATA)")
    cache = seeded_cache(args.model_dir,
                         [m for m in F.KNOWN_MODELS if m is not F.YUNET_KORNIA])
    photos = _aflw(data)
    print(f"# phjax monocular head-pose benchmark (onnxruntime {onnxruntime.__version__}, "
          f"opencv {cv2.__version__}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})\n")
    accuracy_table(photos, cache)
    depth_table(photos, cache, data)
    if not args.skip_synthetic:
        synthetic_table(cache)
    speed_table(photos, cache, args.repeats)
    if not args.skip_live:
        import jax

        jax.config.update("jax_enable_x64", True)
        jax.config.update("jax_cpu_enable_async_dispatch", False)
        live_table(photos, cache, args.live_seconds)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
