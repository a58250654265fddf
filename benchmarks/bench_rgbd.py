"""RGB-D head-pose front-end: per-stage timings and throughput at 640x480, both backends.

    python benchmarks/bench_rgbd.py [--frames 60] [--repeats 3] [--skip-kornia]

Streams (all 640x480, depth registered to colour, frames decoded/rendered before timing):
* ``synthetic``: the rendered head of :mod:`phjax.vision.synthetic_rgbd` (smooth seated motion at
  30 Hz; the typical case: RANSAC + one ICP run per frame). Accuracy against its ground truth
  is printed as well (rotation/position error with the first frame as ground-truth reference).
* ``biwi-cycle``: the three Biwi sample frames in a loop, i.e. 30-62 degree jumps every frame
  (worst case: keyframe switches and the all-candidate ICP fallback).

Per frame the estimator reports the time of each stage (``HeadPoseResult.timings``):
``detect`` (downscale to 320x240 + YuNet), ``features`` (ORB in the face box), ``jax`` (lifting,
organised crop + normals, matching, RANSAC, ICP, one dispatch each for observe/estimate) and
``total`` (whole ``process`` call). Medians and 90th percentiles over all frames after the
first ``--warmup`` (compilation excluded). Frame I/O is timed separately (Biwi: PNG + RLE depth
decoding + depth-to-colour registration). Kornia: batched detection throughput (frames/s) and
the full pipeline with the kornia backend.
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

from phjax.vision import face_detection as F  # noqa: E402
from phjax.vision import head_pose as H  # noqa: E402
from phjax.vision import rgbd_io as R  # noqa: E402
from phjax._np_quat import np_qconj, np_qmul, np_rotvec  # noqa: E402
from phjax.datasets import shared_data_dir  # noqa: E402
from _models import seeded_cache  # noqa: E402


def _stats(results, warmup):
    rows = {}
    rs = [r for r in results[warmup:] if r.timings]
    for k in ("detect", "features", "jax", "total"):
        v = np.array([r.timings.get(k, np.nan) for r in rs]) * 1e3
        v = v[np.isfinite(v)]
        rows[k] = (float(np.median(v)), float(np.percentile(v, 90))) if v.size else (np.nan,) * 2
    return rows


def _run(frames, cfg, detector, reference=None):
    est = H.HeadPoseEstimator(frames[0].intrinsics, cfg, detector=detector,
                              reference_pose=reference)
    t0 = time.perf_counter()
    res = [est.process_frame(f) for f in frames]
    return res, time.perf_counter() - t0, est


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames per stream")
    ap.add_argument("--warmup", type=int, default=5, help="frames excluded from the statistics")
    ap.add_argument("--model-dir", default=None)
    ap.add_argument("--skip-kornia", action="store_true")
    ap.add_argument("--skip-synthetic", action="store_true")
    args = ap.parse_args(argv)
    import cv2
    import jax

    tmp = tempfile.mkdtemp(prefix="phjax_bench_")
    os.environ.setdefault("TORCH_HOME", os.path.join(tmp, "torch"))
    cache = seeded_cache(args.model_dir or os.path.join(tmp, "models"),
                         (F.YUNET_ONNX, F.YUNET_KORNIA))
    print(f"# phjax RGB-D front-end benchmark (jax {jax.__version__}, opencv {cv2.__version__}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f})\n")

    streams = {}
    data = shared_data_dir()
    biwi = data / "biwi_kinect_head_pose_samples" if data else None
    if biwi is not None and biwi.is_dir():
        seq = R.read_biwi(biwi)
        base = [seq[i] for i in range(len(seq))]  # first pass compiles the registration
        t0 = time.perf_counter()
        for i in range(len(seq)):
            seq[i]
        t_io = (time.perf_counter() - t0) / len(seq)
        streams["biwi-cycle"] = ([base[i % 3] for i in range(args.frames)], None, None)
        print(f"Biwi frame I/O (PNG + RLE depth + registration): {1e3 * t_io:.1f} ms/frame\n")
    if not args.skip_synthetic:
        t0 = time.perf_counter()
        syn = R.synthetic_rgbd(args.frames, seed=0)
        frames = [syn[i] for i in range(len(syn))]
        gt = syn.ground_truth
        print(f"synthetic frames rendered in {time.perf_counter() - t0:.1f} s (not timed below)\n")
        streams = {"synthetic": (frames, gt, (gt.quaternions[0], gt.positions[0])), **streams}

    backends = ["opencv"] + ([] if args.skip_kornia else ["kornia"])
    dets = {b: F.FaceDetector(b, model_dir=cache) for b in backends}
    print("| stream | backend | detect ms | features ms | jax ms | total ms (p90) | FPS "
          "(median total) | OK frames | keyframes |")
    print("|---|---|---|---|---|---|---|---|---|")
    accuracy = []
    for name, (frames, gt, ref) in streams.items():
        for b in backends:
            cfg = H.HeadPoseConfig(backend=b)
            res, _, est = _run(frames, cfg, dets[b], ref)
            st = _stats(res, args.warmup)
            ok = sum(r.ok for r in res)
            print(f"| {name} | {b} | {st['detect'][0]:.1f} | {st['features'][0]:.1f} | "
                  f"{st['jax'][0]:.1f} | {st['total'][0]:.1f} ({st['total'][1]:.1f}) | "
                  f"{1e3 / st['total'][0]:.1f} | {ok}/{len(res)} | {est.num_keyframes} |")
            if gt is not None:
                sel = [i for i, r in enumerate(res) if r.ok]
                ang = [np.degrees(np.linalg.norm(np_rotvec(np_qmul(np_qconj(gt.quaternions[i]),
                                                                   res[i].quaternion))))
                       for i in sel]
                pos = [1e3 * np.linalg.norm(res[i].position - gt.positions[i]) for i in sel]
                accuracy.append((name, b, np.median(ang), np.max(ang), np.median(pos),
                                 np.max(pos)))
    if accuracy:
        print("\n| stream | backend | rot err median deg | max deg | pos err median mm | "
              "max mm |")
        print("|---|---|---|---|---|---|")
        for row in accuracy:
            print("| {} | {} | {:.2f} | {:.2f} | {:.2f} | {:.2f} |".format(*row))

    if "kornia" in dets and streams:
        frames = next(iter(streams.values()))[0][:16]
        imgs = [f.color for f in frames]
        print("\nDetection only (320x240 input after downscaling), frames/s:")
        for b in backends:
            d = dets[b]
            d.detect_batch(imgs[:2])
            for bs in ((1, 8) if b == "kornia" else (1,)):
                t0 = time.perf_counter()
                for i in range(0, len(imgs), bs):
                    d.detect_batch(imgs[i:i + bs])
                dt = time.perf_counter() - t0
                print(f"- {b}, batch {bs}: {len(imgs) / dt:.1f} frames/s "
                      f"({1e3 * dt / len(imgs):.1f} ms/frame)")


if __name__ == "__main__":
    main()
