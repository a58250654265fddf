"""The documentation: links between the Markdown files resolve, and the mkdocs site (API pages
from the docstrings, guide pages) builds with ``mkdocs build --strict``."""

import importlib
import importlib.util
import os
import re
import subprocess
import sys

import pytest
from conftest import REPO

_LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")
_DOCS = ["README.md", "CONTRIBUTING.md", "docs/results.md", "benchmarks/README.md",
         "experiments/README.md"]


def _load_hooks():
    spec = importlib.util.spec_from_file_location("phjax_docs_hooks", REPO / "docs" / "hooks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name", _DOCS)
def test_relative_links_resolve(name):
    """Every relative link of the repository's Markdown points at an existing file (on GitHub)."""
    path = REPO / name
    text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.MULTILINE | re.DOTALL)
    targets = [t for t in _LINK.findall(text) if not re.match(r"^([a-z]+:|#)", t)]
    missing = [t for t in targets if not (path.parent / t.split("#")[0]).exists()]
    assert not missing, f"{name}: broken links {missing}"


def test_hook_rewrites_links_for_the_site():
    hooks = _load_hooks()
    text = ("[r](docs/results.md#tuning) ![f](docs/fig1.png) [c](CONTRIBUTING.md) "
            "[b](benchmarks/README.md) [s](experiments/fig1.py) [w](https://x.org/a.md)\n"
            "```python\nx = [1](2)\n```\n")
    out = hooks._rewrite_links(text, "README.md", "index.md")
    assert "[r](results.md#tuning)" in out and "![f](fig1.png)" in out
    assert "[c](contributing.md)" in out and "[b](benchmarks.md)" in out
    assert " s " in out and "[w](https://x.org/a.md)" in out  # not on the site: plain text
    assert "x = [1](2)" in out  # code untouched
    # from a page under docs/, links written relative to docs/
    assert hooks._rewrite_links("[e](../experiments/README.md)", "docs/results.md",
                                "results.md") == "[e](experiments.md)"


def test_mkdocs_build_strict(tmp_path):
    for mod in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        try:
            importlib.import_module(mod)
        except ImportError:
            pytest.skip(f"{mod} is not installed (pip install -e '.[docs]')")
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f",
                          str(REPO / "mkdocs.yml"), "-d", str(site)], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=300, check=False)
    assert res.returncode == 0, res.stderr[-5000:]
    # one API page per subpackage, generated from the docstrings
    for sub, name in [("curves", "hermite_quintic"), ("tracking", "TrackerStream"),
                      ("vision", "HeadPoseEstimator"), ("motion", "synthetic_head_motion"),
                      ("evaluation", "evaluate_recording"), ("io", "read_trajectory"),
                      ("quaternion", "quat_slerp")]:
        page = (site / "api" / sub / "index.html").read_text(encoding="utf-8")
        assert f'id="phjax.{sub}.{name}"' in page, (sub, name)
        assert ":class:`" not in page and ":func:`" not in page  # Sphinx roles shown as code
    # the executed notebooks are pages with their figures
    for nb in sorted((REPO / "notebooks").glob("*.ipynb")):
        page = (site / "notebooks" / nb.stem / "index.html").read_text(encoding="utf-8")
        assert 'src="data:image/png;base64,' in page, nb.name
    index = (site / "index.html").read_text(encoding="utf-8")
    assert "Quickstart" in index and 'href="results/' in index  # the README, links rewritten


def test_notebooks_are_paired_and_executed():
    """Every jupytext script in notebooks/ has an executed .ipynb beside it with the same code."""
    nbformat = pytest.importorskip("nbformat")
    jupytext = pytest.importorskip("jupytext")
    scripts = sorted((REPO / "notebooks").glob("*.py"))
    assert scripts
    for script in scripts:
        ipynb = script.with_suffix(".ipynb")
        assert ipynb.exists(), f"{ipynb.name} missing: jupytext --sync {script.name}, then execute"
        executed = nbformat.read(ipynb, as_version=4)
        paired = jupytext.read(script)
        code = [c.source for c in executed.cells if c.cell_type == "code"]
        assert code == [c.source for c in paired.cells if c.cell_type == "code"], (
            f"{ipynb.name} is out of date with {script.name}")
        assert all(c.execution_count for c in executed.cells if c.cell_type == "code"), ipynb.name
        assert not any(o.output_type == "error" for c in executed.cells
                       if c.cell_type == "code" for o in c.outputs), ipynb.name


def test_docstring_rst_rewrites():
    """The API pages show Sphinx roles as code and RST simple tables as lists."""
    pytest.importorskip("griffe")
    spec = importlib.util.spec_from_file_location("phjax_griffe_rst",
                                                  REPO / "docs" / "griffe_rst_roles.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod._ROLE.sub(mod._plain, "see :func:`~phjax.io.read_tum` and :class:`Trajectory`") == (
        "see `read_tum` and `Trajectory`")
    table = "==  ====\n``a``  one\n       more\n``b``  two\n==  ====\nafter"
    table = table.replace("==  ====", "=====  ====")
    assert mod._simple_tables(table) == "- ``a``: one more\n- ``b``: two\nafter"
