"""Start-up: ``import phjax`` loads no heavy optional part (they load on first use, and every
public name still resolves), and ``phjax.enable_compilation_cache`` lets a second process load
what the first compiled. Each check runs in a fresh interpreter (nothing imported or compiled
beforehand)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: modules that ``import phjax`` must not import (optional extras, solver stacks, CLI / live;
#: and, since every part loads on first use, the core too: equinox and phjax's own modules)
HEAVY = ("optimistix", "lineax", "cv2", "torch", "kornia", "scipy", "matplotlib", "onnxruntime",
         "phjax.vision", "phjax.live", "phjax.cli", "phjax.evaluation", "phjax.tracking.tuning",
         "phjax.curves.shape", "equinox", "phjax.tracking", "phjax.curves", "phjax.batch")


def _python(code: str, env: dict | None = None) -> str:
    full = dict(os.environ, PYTHONPATH=str(REPO), **(env or {}))
    full.pop("JAX_ENABLE_X64", None)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=full, timeout=600, check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout.strip().splitlines()[-1]


def test_import_loads_no_heavy_part_and_every_public_name_resolves():
    out = json.loads(_python(
        "import sys, json, phjax\n"
        f"loaded = sorted(m for m in {HEAVY!r} if m in sys.modules)\n"
        "missing = [n for n in phjax.__all__ if getattr(phjax, n, None) is None]\n"
        "lazy = [n for n in ('optimize_shape', 'tune_tracker', 'HeadPoseEstimator', 'vision',\n"
        "                    'evaluation', 'live', 'io', 'head_pose') if n in dir(phjax)]\n"
        "print(json.dumps({'loaded': loaded, 'missing': missing, 'lazy': lazy,\n"
        "                  'after': 'optimistix' in sys.modules}))"))
    assert out["loaded"] == [], f"import phjax loaded {out['loaded']}"
    assert out["missing"] == []
    assert len(out["lazy"]) == 8  # listed by dir() before they are imported
    assert out["after"]  # resolving the names above imported them on demand


def test_core_names_load_on_first_use():
    """``from phjax import track`` and ``phjax.TrackerConfig`` import the core on demand and
    give the same objects as their modules."""
    out = _python(
        "import sys, phjax\n"
        "from phjax import track, quat_mul\n"
        "import phjax.tracking.tracker as T, phjax.quaternion as Q\n"
        "print(track is T.track and quat_mul is Q.quat_mul and 'equinox' in sys.modules\n"
        "      and phjax.TrackerConfig is T.TrackerConfig and 'track' in vars(phjax))")
    assert out == "True"


def test_compilation_cache_second_process_loads_instead_of_compiling(tmp_path):
    code = (
        "import jax, jax.monitoring, phjax\n"
        "hits = []\n"
        "jax.monitoring.register_event_listener(\n"
        "    lambda e, **_: hits.append(e) if e == '/jax/compilation_cache/cache_hits' else None)\n"
        f"folder = phjax.enable_compilation_cache({str(tmp_path / 'cache')!r}, min_compile_time=0)\n"
        "c = phjax.hermite_quintic([0., 0, 0], [1., 0, 0], [0., 1, 0], [1., 0, 0])\n"
        "c.position(jax.numpy.linspace(0, 1, 5)).block_until_ready()\n"
        "print(len(hits), sum(1 for _ in folder.iterdir()))")
    first = _python(code).split()
    second = _python(code).split()
    assert first[0] == "0" and int(first[1]) > 0, first  # compiled and written
    assert int(second[0]) > 0, second  # loaded from the folder
