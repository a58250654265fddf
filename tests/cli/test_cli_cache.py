"""The CLI turns JAX's persistent compilation cache on for one command (folder from
PHJAX_CACHE_DIR / XDG_CACHE_HOME / ~/.cache), says so before a first run compiles, reuses it on
the next run, restores JAX's settings afterwards, and honours the opt-outs."""

from __future__ import annotations

from pathlib import Path

import jax
import pytest

import phjax.cli._main as cli_main
from phjax.cli import main
from phjax.cli._cache import cache_dir


@pytest.fixture
def cache_env(tmp_path, monkeypatch):
    folder = tmp_path / "jax-cache"
    monkeypatch.setenv("PHJAX_CACHE_DIR", str(folder))
    monkeypatch.delenv("PHJAX_NO_COMPILATION_CACHE", raising=False)
    return folder


@pytest.fixture
def seen(monkeypatch):
    """Replace ``demo-curve`` by a stub recording JAX's cache folder while it runs."""
    record = []

    def stub(args):
        record.append(jax.config.jax_compilation_cache_dir)
        return 0

    monkeypatch.setattr(cli_main, "cmd_demo_curve", stub)
    return record


def test_cache_folder_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("PHJAX_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "phjax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "phjax" / "jax"
    monkeypatch.setenv("PHJAX_CACHE_DIR", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine"


def test_cli_sets_the_cache_folder_for_the_command_only(cache_env, seen):
    before = jax.config.jax_compilation_cache_dir
    assert main(["demo-curve"]) == 0
    assert seen == [str(cache_env)]
    assert jax.config.jax_compilation_cache_dir == before  # restored after the command


@pytest.mark.parametrize("how", ["env", "flag before", "flag after"])
def test_opt_out(cache_env, seen, monkeypatch, how):
    argv = ["demo-curve"]
    if how == "env":
        monkeypatch.setenv("PHJAX_NO_COMPILATION_CACHE", "1")
    else:
        argv = ["--no-cache", *argv] if how == "flag before" else [*argv, "--no-cache"]
    before = jax.config.jax_compilation_cache_dir
    assert main(argv) == 0
    assert seen == [before]
    assert not cache_env.exists()


def test_first_run_compiles_with_a_note_second_run_loads(cache_env, tmp_path, capsys):
    src = tmp_path / "walk.txt"
    src.write_text("".join(f"{0.1 * k} {0.01 * k} {0.02 * k * k} 0 0 0 0 1\n" for k in range(12)))
    argv = ["demo-curve", str(src), "--samples", "7"]
    jax.clear_caches()  # nothing compiled in memory: the run compiles (or loads) everything
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert f"phjax: compiling (first run of 'demo-curve'; cached in {cache_env}" in err
    assert len(err.strip().splitlines()) == 1
    written = sorted(p for p in Path(cache_env).iterdir() if not p.name.startswith("."))
    assert written, "compiled programs are written to the cache folder"
    assert any(p.name.startswith(".phjax-ran-demo-curve-") for p in Path(cache_env).iterdir())
    hits = []

    def count(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    jax.clear_caches()
    jax.monitoring.register_event_listener(count)
    try:
        assert main(argv) == 0
    finally:
        jax.monitoring.unregister_event_listener(count)
    assert "compiling" not in capsys.readouterr().err  # not a first run any more
    assert len(hits) >= len(written), (len(hits), len(written))  # every written program loaded


def test_first_run_note_once_per_command(cache_env, monkeypatch, capsys):
    """The note comes before the first compilation of a command's first successful run (a
    marker in the cache folder records the run), so a command run after another still gets
    it; a failed run does not count."""
    import phjax.cli._tracking as cli_tracking

    calls = []

    def compiling_stub(status):
        def stub(args):
            calls.append(args.command)
            jax.clear_caches()
            jax.jit(lambda x: x * len(calls))(1.0).block_until_ready()
            return status
        return stub

    monkeypatch.setattr(cli_main, "cmd_demo_curve", compiling_stub(0))
    monkeypatch.setattr(cli_tracking, "cmd_smooth", compiling_stub(1))

    def note(argv):
        main(argv)
        return "phjax: compiling (first run" in capsys.readouterr().err

    assert note(["demo-curve"])
    cache_env.mkdir(exist_ok=True)  # as JAX's first write would (the tiny program is not stored)
    main(["demo-curve"])
    capsys.readouterr()
    assert not note(["demo-curve"])
    smooth = ["smooth", "in.txt", "-o", "out.txt"]
    assert note(smooth)
    assert note(smooth)  # its run failed (status 1): still a first run
