"""The CI switch for the shared data: ``$PHJAX_REQUIRE_SHARED_DATA`` turns "absent" into an error."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap

import conftest
import pytest
from conftest import REPO


@pytest.fixture
def no_shared_data(tmp_path, monkeypatch):
    """``shared_path`` pointed at a folder that does not exist."""
    monkeypatch.setattr(conftest, "SHARED_DATA", tmp_path / "missing")
    monkeypatch.setenv("HOME", str(tmp_path))  # no user model cache either
    monkeypatch.delenv("PHJAX_MODEL_DIR", raising=False)
    return tmp_path / "missing"


@pytest.mark.parametrize("value", ["", "0"])
def test_missing_shared_data_skips_by_default(no_shared_data, monkeypatch, value):
    monkeypatch.setenv(conftest.REQUIRE_SHARED_DATA, value)
    with pytest.raises(pytest.skip.Exception, match="shared data not found"):
        conftest.shared_path("tum_rgbd_groundtruth")
    with pytest.raises(pytest.skip.Exception, match="yunet_face_detection"):
        conftest.yunet_models()


@pytest.mark.parametrize("value", ["1", "yes"])
def test_missing_shared_data_fails_when_required(no_shared_data, monkeypatch, value):
    monkeypatch.setenv(conftest.REQUIRE_SHARED_DATA, value)
    with pytest.raises(pytest.fail.Exception, match=conftest.REQUIRE_SHARED_DATA):
        conftest.shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt")
    with pytest.raises(pytest.fail.Exception, match="yunet_face_detection"):
        conftest.yunet_models()


def test_present_shared_data_is_returned(tmp_path, monkeypatch):
    (tmp_path / "some_set").mkdir()
    monkeypatch.setattr(conftest, "SHARED_DATA", tmp_path)
    monkeypatch.setenv(conftest.REQUIRE_SHARED_DATA, "1")
    assert conftest.shared_path("some_set") == tmp_path / "some_set"


def test_yunet_models_fall_back_to_the_model_cache(no_shared_data, tmp_path, monkeypatch):
    """Tests that only need the detector depend on the YuNet files, not on the data set."""
    cache = tmp_path / "models"
    cache.mkdir()
    monkeypatch.setenv("PHJAX_MODEL_DIR", str(cache))
    monkeypatch.setenv(conftest.REQUIRE_SHARED_DATA, "1")
    for name in conftest.YUNET_FILES:
        with pytest.raises(pytest.fail.Exception):  # both files are needed
            conftest.yunet_models()
        (cache / name).write_bytes(b"")
    assert conftest.yunet_models() == cache


def test_ci_sets_the_switch_before_running_the_tests():
    text = (REPO / ".ci" / "run").read_text()
    lines = [ln.strip() for ln in text.splitlines()]
    switch = [i for i, ln in enumerate(lines)
              if re.fullmatch(r"export PHJAX_REQUIRE_SHARED_DATA=1", ln)]
    run = [i for i, ln in enumerate(lines) if ln.startswith("eval ")]
    assert switch and run and switch[0] < run[0]


def test_switch_makes_a_real_data_test_fail_in_pytest(tmp_path):
    """End to end: with the data folder missing, a test using ``shared_path`` is skipped by
    default and fails (exit status 1) with the switch set."""
    test = tmp_path / "test_uses_data.py"
    test.write_text(textwrap.dedent("""
        from conftest import shared_path

        def test_needs_data():
            shared_path("tum_rgbd_groundtruth")
    """))
    (tmp_path / "pytest.ini").write_text("[pytest]\n")  # not the repository's configuration
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test)]
    env = {"PATH": "", "PYTHONPATH": f"{REPO / 'tests'}:{REPO}",
           "PHJAX_SHARED_DATA": str(tmp_path / "missing"), "JAX_PLATFORMS": "cpu"}
    skipped = subprocess.run(cmd, check=False, env=env, capture_output=True, text=True, cwd=tmp_path)
    assert skipped.returncode == 0 and "1 skipped" in skipped.stdout, skipped.stdout
    failed = subprocess.run(cmd, check=False, env=env | {conftest.REQUIRE_SHARED_DATA: "1"},
                            capture_output=True, text=True, cwd=tmp_path)
    assert failed.returncode == 1 and "1 failed" in failed.stdout, failed.stdout
    assert "PHJAX_REQUIRE_SHARED_DATA is set" in failed.stdout
