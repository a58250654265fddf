"""Every ```python block of README.md runs as written: in order, in one fresh process, as a user
who pastes them one after the other would run them (a temporary working directory, the float32
default, no test configuration)."""

import os
import re
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO, shared_path

_BLOCK = re.compile(r"^```python[^\n]*\n(.*?)^```\s*$", re.MULTILINE | re.DOTALL)


def readme_python_blocks() -> list[tuple[int, str]]:
    """``(first line number, source)`` of every ```python block of README.md, in order."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    return [(text.count("\n", 0, m.start(1)) + 1, m.group(1)) for m in _BLOCK.finditer(text)]


_RUNNER = textwrap.dedent(
    r"""
    import json, sys, traceback
    blocks, readme = json.load(open(sys.argv[1])), sys.argv[2]
    namespace = {"__name__": "__main__"}
    for line, source in blocks:
        print(f"--- README.md block at line {line}", flush=True)
        try:
            # padded so that tracebacks give the README's own line numbers
            exec(compile("\n" * (line - 1) + source, readme, "exec"), namespace)
        except BaseException:
            traceback.print_exc()
            print(f"FAILED: README.md block at line {line}", file=sys.stderr)
            sys.exit(1)
    print("all README blocks ran", flush=True)
    """
)


def test_readme_has_python_blocks_and_setup_commands():
    blocks = readme_python_blocks()
    assert len(blocks) >= 8, "the README's task sections should each have a python snippet"
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    # .ci/run executes the line after "# (b)"; the main job is the line after "# (a)"
    a, b = lines.index(next(x for x in lines if x.startswith("# (a)"))), lines.index(
        next(x for x in lines if x.startswith("# (b)")))
    assert "pip install -e" in lines[a + 1] and lines[a + 1].rstrip().endswith("phjax demo")
    assert "pip install -e" in lines[b + 1] and "pytest" in lines[b + 1]
    # the real-time tests skip in xdist workers (tests/conftest.py): the command runs them alone
    assert lines[b + 1].rstrip().endswith("python -m pytest -q -m serial")


@pytest.mark.slow
def test_readme_python_blocks_run_in_order(tmp_path):
    # the RGB-D snippet needs the vision extra and seeds the face-detector cache from
    # ../shared/data
    pytest.importorskip("cv2", reason="the RGB-D snippet needs the vision extra (opencv)")
    shared_path("yunet_face_detection")
    import json

    blocks = tmp_path / "blocks.json"
    blocks.write_text(json.dumps(readme_python_blocks()))
    runner = tmp_path / "run_readme.py"
    runner.write_text(_RUNNER)
    work = tmp_path / "work"
    work.mkdir()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["PHJAX_MODEL_DIR"] = str(tmp_path / "models")  # never touch the user's model cache
    env.setdefault("PHJAX_SHARED_DATA", str(REPO.parent / "shared" / "data"))
    env["MPLBACKEND"] = "Agg"
    # pj.enable_compilation_cache() in the quickstart: this run's shared cache, not ~/.cache
    env["PHJAX_CACHE_DIR"] = os.environ.get("PHJAX_TEST_CACHE_DIR") or str(tmp_path / "jax-cache")
    env.pop("JAX_ENABLE_X64", None)
    res = subprocess.run([sys.executable, str(runner), str(blocks), str(REPO / "README.md")],
                         cwd=work, env=env, capture_output=True, text=True, timeout=1200,
                         check=False)
    assert res.returncode == 0, (res.stdout[-3000:] + "\n" + res.stderr[-6000:])
    assert "all README blocks ran" in res.stdout
    # the "smooth a recording" snippet wrote its files where the user runs it
    assert (work / "camera.txt").exists() and (work / "smooth.txt").exists()
