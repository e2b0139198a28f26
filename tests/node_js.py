"""Running the browser page's JavaScript tests (client/web/test/*.test.mjs) from pytest:
each is driven by a fixture the Python test writes, so that one algorithm is held equal
in both languages."""

from __future__ import annotations

import shutil
import subprocess

import pytest
from conftest import REPO_ROOT

WEB = REPO_ROOT / "client" / "web"
NODE_TIMEOUT = 120.0  # seconds: node starts in well under one


def node_path() -> str:
    """Node.js, or skip (fail where the page's packages were not installed)."""
    path = shutil.which("node")
    if path is None:
        pytest.skip("no node on this machine: the page's JavaScript tests need Node.js "
                    "(apt-get install nodejs npm; make setup)")
    if not (WEB / "node_modules" / "@msgpack" / "msgpack").is_dir():
        pytest.fail("client/web/node_modules is missing: run make setup (npm ci)")
    return path


def run_node_test(node: str, name: str, env: dict[str, str]) -> str:
    """Run client/web/test/NAME with Node's test runner; its output, once every test in
    it passed and none was skipped."""
    proc = subprocess.run([node, "--test", str(WEB / "test" / name)],
                          capture_output=True, text=True, timeout=NODE_TIMEOUT, cwd=WEB,
                          env={"PATH": "/usr/bin:/bin", **env})
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "# fail 0" in proc.stdout and "# skipped 0" in proc.stdout, proc.stdout
    return proc.stdout
