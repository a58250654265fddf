"""Startup cost of phjax (issue 29, "Measure first"): import time, compile time of each public
jitted entry point, first-call wall time, and the CLI commands with a cold and a warm cache.

    python benchmarks/bench_startup.py                        # everything, float32 (10-20 min)
    python benchmarks/bench_startup.py --quick                # no CLI / demo / live part
    python benchmarks/bench_startup.py --only import,track --dtype float64 --json startup.json
    python benchmarks/bench_startup.py --root DIR             # the phjax of DIR (e.g. a git archive)

Every measurement runs in a fresh Python process (``python -c`` or this script with
``--child``), so nothing is warm; JAX's persistent compilation cache is off except in the CLI
part, where ``PHJAX_CACHE_DIR`` points at a new empty folder (cold) and the same command runs
again on that folder (warm). Each entry point runs in two processes: ``aot`` lowers and
compiles its jitted core ahead of time (``jit(f).trace(...).lower().compile()``, stand-ins on
the jitted internals catch the arguments the public function passes) and then runs it;
``call`` times the plain first call of the public function (compile + run) and counts the
compilations it caused (a ``jax.monitoring`` listener on
``/jax/core/compile/backend_compile_duration``). Output: Markdown on stdout, progress on stderr.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PKG_ROOT = ROOT  # the checkout whose phjax the children import (--root)
MARK = "BENCH_STARTUP_JSON "
ENTRIES = ("track", "reconstruct", "stream", "sample", "shape", "imm", "kalman", "grad",
           "head_pose")
PARTS = ("import", *ENTRIES, "cli", "live")
BACKEND = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
TO_MLIR = "/jax/core/compile/jaxpr_to_mlir_module_duration"
SMOOTH_FILE = "tum_rgbd_groundtruth/fr1_xyz-groundtruth.txt"  # 30 s, 3000 poses at 100 Hz


def _shared_data() -> Path:
    return Path(os.environ.get("PHJAX_SHARED_DATA") or ROOT.parent / "shared" / "data")


# ------------------------------------------------------------------ parent: fresh processes
def _env(**extra) -> dict:
    """The children's environment: ``PKG_ROOT`` first on the path, no inherited cache."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "PHJAX_NO_COMPILATION_CACHE",
                        "PHJAX_CACHE_DIR")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(PKG_ROOT), env.get("PYTHONPATH")) if p)
    env["PHJAX_SHARED_DATA"] = str(_shared_data())
    env.update(extra)
    return env


def run_json(cmd: list[str], timeout: float = 1200, **env) -> dict:
    """Run ``cmd`` in a fresh process (JAX's persistent cache off); the JSON of the last line
    it printed that starts with ``MARK``, or ``{"error": ...}``."""
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=PKG_ROOT,
                           env=_env(JAX_ENABLE_COMPILATION_CACHE="false", **env), check=False)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    for line in reversed(r.stdout.splitlines()):
        if line.startswith(MARK):
            return json.loads(line[len(MARK):])
    tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
    return {"error": f"exit {r.returncode}: {tail[:200]}"}


def run_snippet(code: str, **kw) -> dict:
    return run_json([sys.executable, "-c", code], **kw)


def run_child(entry: str, mode: str, dtype: str, *extra: str) -> dict:
    return run_json([sys.executable, __file__, "--child", entry, "--mode", mode, "--dtype", dtype,
                     *extra])


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


_IMPORT = """import json, sys, time
t0 = time.perf_counter()
import {modules}
s = time.perf_counter() - t0
heavy = [m for m in ("scipy", "matplotlib", "cv2", "torch", "kornia") if m in sys.modules]
print({mark!r} + json.dumps({{"s": s, "heavy": heavy}}))
"""


def measure_import(repeats: int = 3) -> dict:
    """``import jax`` and ``import jax, phjax`` in alternating fresh processes."""
    out = {}
    for _ in range(repeats):
        for modules in ("jax", "jax, phjax"):
            t0 = time.perf_counter()
            r = run_snippet(_IMPORT.format(modules=modules, mark=MARK))
            r["process_s"] = time.perf_counter() - t0
            out.setdefault(modules, []).append(r)
    return out


def _phjax_cmd() -> list[str]:
    script = Path(sys.executable).with_name("phjax")
    return [str(script)] if script.exists() else [sys.executable, "-m", "phjax"]


def run_wall(cmd: list[str], cache: Path, cwd: Path, timeout: float) -> dict:
    """Wall time of a CLI command from start to exit with the persistent cache in ``cache``."""
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                           env=_env(PHJAX_CACHE_DIR=str(cache)), check=False)
    except subprocess.TimeoutExpired:
        return {"s": None, "error": f"over {timeout:.0f} s (stopped)"}
    res = {"s": time.perf_counter() - t0, "rc": r.returncode}
    if r.returncode:
        res["error"] = (r.stderr.strip().splitlines() or ["?"])[-1][:200]
    return res


def measure_cli(tmp: Path, demo_limit: float) -> list[dict]:
    smooth_in = _shared_data() / SMOOTH_FILE
    cmds = [("phjax --help", ["--help"], 300),
            ("phjax demo --duration 10 --plot '' --no-progress",
             ["demo", "--duration", "10", "--plot", "", "--no-progress"], 900),
            ("phjax demo (default: 60 s, plot)", ["demo"], demo_limit),
            (f"phjax smooth {smooth_in.name} -o out.txt",
             ["smooth", str(smooth_in), "-o", "out.txt"], 900),
            (f"phjax smooth {smooth_in.name} -o out.txt --offline",
             ["smooth", str(smooth_in), "-o", "out.txt", "--offline"], 900)]
    rows = []
    for i, (label, args, limit) in enumerate(cmds):
        if "smooth" in args and not smooth_in.is_file():
            rows.append({"label": label, "note": f"skipped: {smooth_in} not found"})
            continue
        cache = tmp / f"cache{i}"
        _log(f"cli: {label} (cold)")
        cold = run_wall(_phjax_cmd() + args, cache, tmp, limit)
        files = sum(1 for f in cache.rglob("*") if f.is_file() and not f.name.startswith("."))
        warm = None
        if cold["s"] is not None:
            _log(f"cli: {label} (warm)")
            warm = run_wall(_phjax_cmd() + args, cache, tmp, limit)
        rows.append({"label": label, "cold": cold, "warm": warm, "cache_files": files})
    return rows


def _first_packet(cmd: list[str], sock: socket.socket, cache: Path, cwd: Path,
                  timeout: float) -> dict:
    """Seconds from starting ``cmd`` to the first datagram on ``sock``; stops the command."""
    t0 = time.perf_counter()
    with open(cwd / "live.err", "w") as err:
        proc = subprocess.Popen(cmd, cwd=cwd, env=_env(PHJAX_CACHE_DIR=str(cache)),
                                stdout=subprocess.DEVNULL, stderr=err)
        res = {"s": None, "error": f"no packet within {timeout:.0f} s"}
        try:
            while time.perf_counter() - t0 < timeout:
                try:
                    sock.recv(256)
                    res = {"s": time.perf_counter() - t0}
                    break
                except TimeoutError:
                    if proc.poll() is not None:
                        res = {"s": None, "error": f"exited {proc.returncode} before a packet"}
                        break
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    while True:  # drop what is left of this run
        try:
            sock.recv(256)
        except TimeoutError:
            break
    return res


def measure_live(tmp: Path) -> list[dict]:
    """``phjax live poses:FILE`` to an opentrack listener on loopback: start to first packet."""
    t, p, q = _motion(3000, seed=2)
    poses = tmp / "poses.tum"
    np.savetxt(poses, np.c_[t, p, q[:, 1:], q[:, :1]], fmt="%.6f")  # TUM: t x y z qx qy qz qw
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    cmd = _phjax_cmd() + ["live", f"poses:{poses}", "--output",
                          f"opentrack://127.0.0.1:{sock.getsockname()[1]}", "--quiet",
                          "--duration", "120"]
    res = {"label": "phjax live poses:FILE -o opentrack://127.0.0.1 (start to first packet)"}
    try:
        for run in ("cold", "warm"):
            _log(f"live ({run})")
            res[run] = _first_packet(cmd, sock, tmp / "cache_live", tmp, 300)
    finally:
        sock.close()
    return [res]


# ------------------------------------------------------------------ children: what they run
def _motion(n: int, rate: float = 30.0, seed: int = 0):
    """``n`` frames of a smooth head-like motion (NumPy only, so nothing in JAX gets warm)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    f, ph = rng.uniform(0.1, 0.8, (2, 3)), rng.uniform(0, 2 * np.pi, (2, 3))
    p = [0, 0, 0.7] + 0.05 * np.sin(2 * np.pi * f[0] * t[:, None] + ph[0])
    rv = 0.3 * np.sin(2 * np.pi * f[1] * t[:, None] + ph[1])
    a = np.linalg.norm(rv, axis=1, keepdims=True)
    q = np.c_[np.cos(a / 2), np.sin(a / 2) * rv / np.maximum(a, 1e-12)]
    return t, p, q


def _recording(n: int, dtype, seed: int = 0):
    """A noisy 30 Hz recording with 5 % lost frames (NaN rows) and 120 Hz render times."""
    t, p, q = _motion(n, seed=seed)
    rng = np.random.default_rng(seed + 100)
    p = p + 0.005 * rng.normal(size=p.shape)
    lost = rng.random(n) < 0.05
    p[lost], q[lost] = np.nan, np.nan
    render = np.arange(0.1, n / 30.0, 1 / 120)
    return tuple(np.asarray(x, dtype) for x in (t, p, q, render))


def _fusions(hlo: str) -> dict:
    """Fusion instructions of an optimised HLO module: in ENTRY, and in all computations."""
    lines = hlo.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.startswith("ENTRY")), len(lines))
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("}")), len(lines))
    is_fusion = re.compile(r"\sfusion\(").search
    return {"fusions_entry": sum(bool(is_fusion(ln)) for ln in lines[start:end]),
            "fusions_all": sum(bool(is_fusion(ln)) for ln in lines)}


class Probe:
    """Stands in for a jitted function: a call with new argument shapes is first traced,
    lowered and compiled ahead of time (timed, HLO measured), then run (timed)."""

    def __init__(self, ctx, label, fn, jitted=None):
        self._ctx, self._label, self._fn, self._jitted = ctx, label, fn, jitted or fn
        self._seen = set()

    def __getattr__(self, name):
        return getattr(self._fn, name)

    def __call__(self, *args, **kwargs):
        import jax

        leaves, treedef = jax.tree.flatten((args, kwargs))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._fn(*args, **kwargs)
        key = (str(treedef), tuple((x.shape, str(x.dtype)) if hasattr(x, "shape") else
                                   type(x).__name__ if isinstance(x, (int, float)) else repr(x)
                                   for x in leaves))
        if key in self._seen:
            return self._fn(*args, **kwargs)
        self._seen.add(key)
        static = ", ".join(f"{k}={v!r}" for k, v in kwargs.items() if isinstance(v, (str, int)))
        label = f"{self._label}({static})" if static else self._label
        return self._ctx.aot(label, self._jitted, args, kwargs, lambda: self._fn(*args, **kwargs))


class Ctx:
    """A child's measurements: ``aot`` mode compiles through probes, ``call`` mode times the
    public calls."""

    def __init__(self, mode: str):
        import jax

        self.aot_mode = mode == "aot"
        self.rows: list[dict] = []
        self.events: list[tuple[str, float]] = []
        jax.monitoring.register_event_duration_secs_listener(
            lambda event, secs, **_: self.events.append((event, secs)))

    def compiles_since(self, start: int) -> dict:
        ev = self.events[start:]
        total = lambda name: sum(s for e, s in ev if e == name)
        return {"compiles": sum(e == BACKEND for e, _ in ev), "backend_s": total(BACKEND),
                "trace_s": total(TRACE), "mlir_s": total(TO_MLIR)}

    def wrap(self, fn, label, jitted=None):
        return Probe(self, label, fn, jitted) if self.aot_mode else fn

    def patch(self, owner, name, label, jitted=None):
        if self.aot_mode:
            setattr(owner, name, Probe(self, label, getattr(owner, name), jitted))

    def aot(self, label, jitted, args, kwargs, run):
        import jax

        t0 = time.perf_counter()
        traced = jitted.trace(*args, **kwargs)
        t1 = time.perf_counter()
        lowered = traced.lower()
        t2 = time.perf_counter()
        compiled = lowered.compile()
        t3 = time.perf_counter()
        start = len(self.events)
        out = jax.block_until_ready(run())
        t4 = time.perf_counter()
        self.rows.append({"label": label, "trace_s": t1 - t0, "lower_s": t2 - t1,
                          "compile_s": t3 - t2, "run_s": t4 - t3,
                          "run_compiles": self.compiles_since(start)["compiles"],
                          "hlo_lines": len(lowered.as_text().splitlines()),
                          **_fusions(compiled.as_text())})
        return out

    def call(self, label, fn, again=True):
        """``fn()`` once (call mode: timed with the compilations it caused, then once more)."""
        import jax

        if self.aot_mode:
            return fn()
        start = len(self.events)
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        row = {"label": label, "first_s": time.perf_counter() - t0, **self.compiles_since(start)}
        if again:
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            row["again_s"] = time.perf_counter() - t0
        self.rows.append(row)
        return out


def entry_track(ctx, dtype, _):
    import phjax
    from phjax.tracking import tracker

    ctx.patch(tracker, "_track_core", "tracker._track_core")
    t, p, q, r = _recording(300, dtype)
    ctx.call("phjax.track, N=300 (10 s at 30 Hz), 1188 render times",
             lambda: phjax.track(t, p, q, r, dtype=dtype))
    if not ctx.aot_mode:
        t, p, q, r = _recording(370, dtype, seed=1)
        ctx.call("phjax.track, N=370 next (same process)",
                 lambda: phjax.track(t, p, q, r, dtype=dtype))


def entry_reconstruct(ctx, dtype, _):
    import phjax
    from phjax.tracking import tracker

    ctx.patch(tracker, "_reconstruct_core", "tracker._reconstruct_core")
    t, p, q, r = _recording(300, dtype)
    ctx.call("phjax.reconstruct, N=300", lambda: phjax.reconstruct(t, p, q, r, dtype=dtype))


def entry_stream(ctx, dtype, _):
    import phjax
    from phjax.tracking import stream as S

    if ctx.aot_mode:
        make = S._sample_on_leaves
        S._sample_on_leaves = functools.cache(
            lambda d: Probe(ctx, "stream._sample_on_leaves (jit)", make(d)))
    st = ctx.call("phjax.TrackerStream() (tracker_init)", lambda: phjax.TrackerStream(dtype=dtype),
                  again=False)
    ctx.patch(st, "_update", "stream._on_leaves(_update) (jit)")
    pos, quat = np.asarray([0.0, 0.0, 0.7], dtype), np.asarray([1.0, 0, 0, 0], dtype)
    ctx.call("TrackerStream.update, first", lambda: (st.update(0.0, pos, quat), st._leaves))
    ctx.call("TrackerStream.sample, first", lambda: st.sample(0.01))
    if not ctx.aot_mode:
        ctx.rows.append({"label": "TrackerStream() + first update + first sample (sum)",
                         **{k: sum(r[k] for r in ctx.rows) for k in ("first_s", "compiles",
                                                                     "backend_s", "trace_s",
                                                                     "mlir_s")}})
        if hasattr(st, "wait_compiled"):  # fast start: the optimised update compiles behind
            ctx.call("then: optimised update ready (background compile)",
                     lambda: st.wait_compiled(), again=False)


def entry_sample(ctx, dtype, _):
    import phjax
    from phjax.curves import ph_quintic, sampling

    ctx.patch(ph_quintic, "_hermite_jit", "ph_quintic._hermite_jit")
    ctx.patch(sampling, "_sample_jit", "sampling._sample_jit")
    rng = np.random.default_rng(0)
    p0, p1, d0, d1 = (np.asarray(rng.normal(size=(1000, 3)), dtype) for _ in range(4))
    curves = ctx.call("phjax.hermite_quintic, 1000 segments",
                      lambda: phjax.hermite_quintic(p0, p1, d0, d1))
    ctx.call("phjax.sample, 1000 x 100, by time", lambda: phjax.sample(curves, 100))
    ctx.call("phjax.sample, 1000 x 100, by arc length",
             lambda: phjax.sample(curves, 100, by="arclength"))


def entry_shape(ctx, dtype, _):
    import phjax
    from phjax.curves import shape

    ctx.patch(shape, "_solve_compiled", "shape._solve_jit (solver)", jitted=shape._solve_jit)
    ctx.patch(shape, "_outputs_jit", "shape._outputs_jit (curves, record)")
    t, p, _ = _motion(257)
    v = np.gradient(p, t, axis=0) * (t[1] - t[0])
    args = [np.asarray(x, dtype) for x in (p[:-1], p[1:], v[:-1], v[1:])]
    ctx.call("phjax.optimize_shape, 256 segments (bending energy)",
             lambda: phjax.optimize_shape(*args))


def entry_imm(ctx, dtype, _):
    import phjax

    imm_filter = ctx.wrap(phjax.tracking.imm_filter, "tracking.imm_filter")
    t, p, q, _ = _recording(300, dtype)
    ctx.call("phjax.tracking.imm_filter, N=300",
             lambda: imm_filter(phjax.TrackerConfig().imm, t, p, q))


def entry_kalman(ctx, dtype, _):
    import phjax

    kalman_filter = ctx.wrap(phjax.kalman_filter, "kalman_filter")
    t, p, q, _ = _recording(300, dtype)
    ctx.call("phjax.kalman_filter, N=300",
             lambda: kalman_filter(phjax.TrackerConfig().kalman, t, p, q))


def entry_grad(ctx, dtype, _):
    """Gradients as a user (``jax.grad`` of a loss of ``track``'s output with respect to the
    config) and as gradient tuning (the tuning loss's value and gradient) first meet them."""
    import jax
    import jax.numpy as jnp

    import phjax
    from phjax.tracking import tuning

    t, p, q, r = (jnp.asarray(x) for x in _recording(300, dtype))

    def loss(config):
        pos, quat = phjax.track(t, p, q, r, config=config)
        return jnp.nanmean(pos ** 2) + jnp.nanmean(quat[:, 1:] ** 2)

    grad = ctx.wrap(jax.jit(jax.grad(loss)), "jax.jit(jax.grad(loss of phjax.track))")
    ctx.call("jax.grad of a loss of phjax.track, N=300, w.r.t. the config",
             lambda: grad(phjax.TrackerConfig()))
    if not ctx.aot_mode:  # the tuning loss compiles inside the problem's own jit
        gt = _motion(1200, rate=120.0, seed=3)
        problem = tuning.make_problem(tuning.prepare_recordings([gt], seed=0, dtype=dtype),
                                      lam=0.3)
        y = problem.params_from_config(phjax.TrackerConfig())
        ctx.call("tuning: value and gradient of the loss, one 10 s recording",
                 lambda: problem.value_and_grad(y))


def entry_head_pose(ctx, _, frame):
    from phjax.vision import face_detection, head_pose, rgbd_io

    for name in ("_observe", "_make_keyframe", "_estimate"):
        ctx.patch(head_pose, name, f"head_pose.{name}")
    f = np.load(frame)
    intr = rgbd_io.CameraIntrinsics(*(float(f[k]) for k in ("fx", "fy", "cx", "cy")),
                                    width=int(f["width"]), height=int(f["height"]))
    models = Path(tempfile.mkdtemp(prefix="phjax_models_"))
    face_detection.seed_model_cache(_shared_data() / "yunet_face_detection", models)
    est = ctx.call("HeadPoseEstimator() (YuNet, OpenCV)",
                   lambda: head_pose.HeadPoseEstimator(intr, model_dir=models), again=False)
    color, depth = f["color"], f["depth"]
    res = ctx.call("HeadPoseEstimator.process, frame 1 (keyframe)",
                   lambda: est.process(color, depth, 0.0), again=False)
    ctx.call("HeadPoseEstimator.process, same frame again (alignment)",
             lambda: est.process(color, depth, 1 / 30))
    shutil.rmtree(models, ignore_errors=True)
    return f"first frame status {res.status.name}"


def render_frame(path: str) -> None:
    """Frame 0 of the synthetic RGB-D head (BGR, depth, intrinsics) to ``path`` (.npz)."""
    from phjax.vision import rgbd_io

    f = rgbd_io.synthetic_rgbd(1, seed=0)[0]
    k = f.intrinsics
    np.savez(path, color=f.color, depth=f.depth, fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy,
             width=k.width, height=k.height)


def child(entry: str, mode: str, dtype: str, frame: str | None) -> None:
    import jax

    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    if entry == "render":
        render_frame(frame)
        print(MARK + json.dumps({"rows": []}))
        return
    ctx = Ctx(mode)
    note = globals()[f"entry_{entry}"](ctx, np.dtype(dtype).type, frame)
    print(MARK + json.dumps({"rows": ctx.rows, "note": note}))


# ------------------------------------------------------------------ report
def _f(x, digits=2) -> str:
    return "-" if x is None else f"{x:.{digits}f}" if isinstance(x, float) else str(x)


def _table(headers, rows) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(_f(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def _git() -> str:
    def git(*a):
        r = subprocess.run(["git", *a], cwd=PKG_ROOT, capture_output=True, text=True,
                           check=False)
        return r.stdout.strip() if r.returncode == 0 else ""
    if not (head := git("rev-parse", "--short", "HEAD")) or git("rev-parse", "--show-prefix"):
        return f"? ({PKG_ROOT} is not the top of a git checkout)"
    return head + (" + uncommitted changes in phjax/" if git("status", "--short", "phjax") else "")


def _sources_hash() -> str:
    """sha1 of the package's ``.py`` files (did the measured code change during the run?)."""
    h = hashlib.sha1()
    for f in sorted((PKG_ROOT / "phjax").rglob("*.py")):
        h.update(str(f.relative_to(PKG_ROOT)).encode() + f.read_bytes())
    return h.hexdigest()[:10]


def report(res: dict, header: str) -> str:
    parts = [header]
    if "import" in res:
        imp = res["import"]
        best = {m: min((r["s"] for r in rs if "s" in r), default=None) for m, rs in imp.items()}
        rows = [(f"`import {m}`", best[m], " / ".join(_f(r.get("s")) for r in rs),
                 min(r["process_s"] for r in rs), ", ".join(rs[-1].get("heavy", [])) or "-")
                for m, rs in imp.items()]
        parts.append("Import (best of 3 fresh processes; in-process time of the import statement):"
                     "\n\n" + _table(["import", "best s", "runs s", "process wall best s",
                                      "heavy modules loaded"], rows))
        if best.get("jax") and best.get("jax, phjax"):
            ratio = best["jax, phjax"] / best["jax"]
            parts[-1] += f"\n\n`import jax, phjax` / `import jax` = **{ratio:.2f}**"
    aot, call = [], []
    for e in ENTRIES:
        if e not in res:
            continue
        r = res[e]
        if "skipped" in r:
            call.append((e, r["skipped"]) + ("-",) * 6)
            continue
        for mode, rows in (("aot", aot), ("call", call)):
            c = r[mode]
            if "error" in c:
                rows.append((e, f"error: {c['error']}") + ("-",) * (7 if mode == "aot" else 6))
                continue
            for x in c["rows"]:
                if mode == "aot":
                    run = _f(x["run_s"]) + (f" (+{x['run_compiles']} compiles)"
                                            if x["run_compiles"] else "")
                    rows.append((e, f"`{x['label']}`", x["trace_s"], x["lower_s"], x["compile_s"],
                                 run, x["hlo_lines"], x["fusions_entry"], x["fusions_all"]))
                else:
                    rows.append((e, x["label"], x["first_s"], x["compiles"], x["backend_s"],
                                 x["trace_s"], x["mlir_s"], x.get("again_s")))
            if mode == "call" and c.get("note"):
                rows.append((e, f"({c['note']})") + ("",) * 6)
    if aot:
        parts.append("Compile, ahead of time (one fresh process per entry point; the jitted core "
                     "with the arguments the public call passes; s):\n\n" + _table(
                         ["entry", "jitted function", "trace s", "lower s", "compile s",
                          "first run s", "StableHLO lines", "fusions ENTRY", "fusions all"], aot))
    if call:
        parts.append("First call of the public function (another fresh process per entry point; "
                     "wall time incl. compilation, then the same call again):\n\n" + _table(
                         ["entry", "call", "first call s", "compilations", "backend compile s",
                          "trace s", "to-MLIR s", "again s"], call))
    cli = res.get("cli", []) + res.get("live", [])
    if cli:
        def cell(x):
            return "-" if x is None else x.get("error", "") if x.get("s") is None else (
                _f(x["s"]) + (f" (exit {x['rc']}: {x['error']})" if x.get("rc") else ""))
        rows = [(f"`{r['label']}`", r["note"], "-", "-") if "note" in r else
                (f"`{r['label']}`", cell(r["cold"]), cell(r["warm"]), r.get("cache_files", "-"))
                for r in cli]
        parts.append("CLI, wall time from start to exit (live: to the first UDP packet); cold = "
                     "new empty `PHJAX_CACHE_DIR`, warm = the same folder again:\n\n" +
                     _table(["command", "cold s", "warm s", "files in cache after cold"], rows))
    return "\n\n".join(parts) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--only", default="", help=f"comma-separated parts of {','.join(PARTS)}")
    ap.add_argument("--quick", action="store_true", help="skip the CLI, demo and live parts")
    ap.add_argument("--json", metavar="PATH", help="also write the raw results as JSON")
    ap.add_argument("--demo-limit", type=float, default=300,
                    help="stop the default demo after this many seconds (default 300)")
    ap.add_argument("--root", type=Path, default=ROOT,
                    help="measure the phjax package of this checkout or export (default: this one)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="call", help=argparse.SUPPRESS)
    ap.add_argument("--frame", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.mode, args.dtype, args.frame)
        return 0
    global PKG_ROOT
    PKG_ROOT = args.root.resolve()
    parts = [p for p in args.only.split(",") if p] or list(PARTS)
    if bad := set(parts) - set(PARTS):
        ap.error(f"unknown parts {sorted(bad)}; choose from {','.join(PARTS)}")
    if args.quick:
        parts = [p for p in parts if p not in ("cli", "live")]
    load0 = os.getloadavg()
    spec = run_snippet("import importlib.util as u, json; "
                       f"print({MARK!r} + json.dumps({{'path': u.find_spec('phjax').origin}}))")
    version = importlib.metadata.version
    header = (f"# phjax startup benchmark ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})"
              f"\n\nphjax from `{spec.get('path', spec)}`, commit {_git()} (phjax/*.py sha1 "
              f"{(sources := _sources_hash())}); jax {version('jax')}, "
              f"jaxlib {version('jaxlib')}, Python {sys.version.split()[0]}; dtype "
              f"{args.dtype}; os.cpu_count() = {os.cpu_count()}; nice {os.nice(0)}; XLA_FLAGS="
              f"{os.environ.get('XLA_FLAGS', '')!r}; load average (1/5/15 min) at the start "
              + "/".join(f"{x:.2f}" for x in load0))
    res: dict = {}
    with tempfile.TemporaryDirectory(prefix="phjax_startup_") as tmp:
        tmp = Path(tmp)
        if "import" in parts:
            _log("import")
            res["import"] = measure_import()
        frame = tmp / "frame.npz"
        for e in (e for e in ENTRIES if e in parts):
            extra = ()
            if e == "head_pose":
                if importlib.util.find_spec("cv2") is None:
                    res[e] = {"skipped": "skipped: the vision extra (opencv) is not installed"}
                    continue
                _log("head_pose: rendering the synthetic frame")
                if "error" in (r := run_child("render", "call", args.dtype, "--frame", str(frame))):
                    res[e] = {"skipped": f"skipped: rendering the frame failed ({r['error']})"}
                    continue
                extra = ("--frame", str(frame))
            res[e] = {}
            for mode in ("aot", "call"):
                _log(f"{e} ({mode})")
                res[e][mode] = run_child(e, mode, args.dtype, *extra)
        if "cli" in parts:
            res["cli"] = measure_cli(tmp, args.demo_limit)
        if "live" in parts:
            res["live"] = measure_live(tmp)
    load1 = os.getloadavg()
    header += ", at the end " + "/".join(f"{x:.2f}" for x in load1) + "."
    if (now := _sources_hash()) != sources:
        header += f" **The phjax sources changed during the run** (sha1 now {now})."
    print(report(res, header))
    if args.json:
        Path(args.json).write_text(json.dumps({"header": header, "results": res}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
