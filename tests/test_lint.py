"""The linter of CONTRIBUTING.md passes on the whole tree (rule set pinned in pyproject.toml)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import REPO


def test_ruff_check_passes():
    pytest.importorskip("ruff", reason="ruff comes with the dev extra")
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format",
                          "concise", str(REPO)], capture_output=True, text=True, cwd=REPO,
                         timeout=120, check=False)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
