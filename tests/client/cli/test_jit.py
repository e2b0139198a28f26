"""Compiled kernels: a command that must compile says so, and `posecast warm` (run by
make setup) leaves nothing for any later command to compile."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np

from posecast.client.jit import CompileNotice

NOTICE = "compiling solver kernels, first run only"


def _posecast(args: list[str], cache: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", *args], env=env,
                          cwd=cwd, capture_output=True, text=True, timeout=900)


def _cache_files(cache: Path) -> dict[str, float]:
    return {str(p): p.stat().st_mtime for p in cache.rglob("*") if p.is_file()}


def test_warm_compiles_once_and_later_commands_compile_nothing(tmp_path: Path) -> None:
    cache = tmp_path / "numba-cache"  # empty: as on a fresh install
    first = _posecast(["warm"], cache, tmp_path)
    assert first.returncode == 0, first.stderr
    assert NOTICE in first.stderr
    assert "kernels in" in first.stderr and "cached for next time" in first.stderr
    assert "kernels ready" in first.stdout
    warmed = _cache_files(cache)
    assert len(warmed) > 20

    again = _posecast(["warm"], cache, tmp_path)
    assert again.returncode == 0 and NOTICE not in again.stderr

    evaluated = _posecast(["eval", "--json"], cache, tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr
    assert NOTICE not in evaluated.stderr
    # the demo's server, players, spectators and headless viewer are processes of their
    # own, which print no notice: a kernel any of them compiled would be a new cache file
    demo = _posecast(["demo", "--players", "2", "--spectators", "1", "--seconds", "1",
                      "--render", str(tmp_path / "frames"), "--json"], cache, tmp_path)
    assert demo.returncode == 0, demo.stderr
    assert NOTICE not in demo.stderr
    assert _cache_files(cache) == warmed


def test_the_notice_counts_compiles_and_says_what_they_cost() -> None:
    @numba.njit(cache=False)
    def twice(x: np.ndarray) -> np.ndarray:
        return x * 2

    out = io.StringIO()
    notice = CompileNotice(out).install()
    try:
        twice(np.ones(3))
        twice(np.ones(4))  # the same signature: nothing more to compile
        assert out.getvalue().count(NOTICE) == 1
        assert notice.compiled == 1
        twice(np.ones(3, dtype=np.int64))  # a new signature compiles again, quietly
        assert out.getvalue().count(NOTICE) == 1 and notice.compiled == 2
        notice.close()
    finally:
        notice.uninstall()
    assert "compiled 2 kernels in" in out.getvalue()
    twice(np.ones(3, dtype=np.float32))  # uninstalled: says nothing
    assert out.getvalue().count("\n") == 2
