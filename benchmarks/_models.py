"""The benchmarks' model cache: seeded from the shared data folder, never downloaded.

``seeded_cache(model_dir, models)`` returns the model cache (``model_dir``, else
``$PHJAX_MODEL_DIR``, else the user's cache) after copying any of ``models`` it lacks from
``shared/data/yunet_face_detection`` and ``shared/data/head_pose_models``
(:func:`phjax.vision.face_detection.seed_model_cache` checks sizes and SHA-256). A model
found in neither ends the script with a one-line message (exit code 1).
"""

from __future__ import annotations

from pathlib import Path

from phjax.datasets import shared_data_dir
from phjax.vision import face_detection as F

SHARED_MODEL_FOLDERS = ("yunet_face_detection", "head_pose_models")


def _missing(models, cache: Path) -> list[str]:
    out = []
    for m in models:
        try:
            F.model_path(m, cache)
        except (FileNotFoundError, ValueError):
            out.append(m.filename)
    return out


def seeded_cache(model_dir, models=(F.YUNET_ONNX,)) -> Path:
    """The model cache holding every one of ``models`` (seeded from the shared data)."""
    cache = F.model_dir(model_dir)
    if not _missing(models, cache):
        return cache
    data = shared_data_dir()
    for sub in SHARED_MODEL_FOLDERS:
        if data is not None and (data / sub).is_dir():
            F.seed_model_cache(data / sub, cache)
    missing = _missing(models, cache)
    if missing:
        where = (f"nor in {data}" if data is not None
                 else "and there is no shared data folder ($PHJAX_SHARED_DATA)")
        raise SystemExit(f"models {', '.join(missing)} are not in {cache} {where}; "
                         "point --model-dir at a folder holding them or run "
                         "phjax.vision.face_detection.download_model(...)")
    return cache
