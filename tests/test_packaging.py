"""The distribution installs one import package, `posecast`, holding every module of the
top-level folders, and the code imports only through it."""

from __future__ import annotations

import ast
import importlib.metadata
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
FOLDERS = ("protocol", "solver", "server", "client")


def _sources() -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (REPO / folder).rglob("*.py")
                  if "__pycache__" not in p.parts)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> zipfile.ZipFile:
    out = tmp_path_factory.mktemp("wheel")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet",
                           "-w", str(out), str(REPO)], capture_output=True, text=True)
    if proc.returncode != 0:
        if "Could not find a version" in proc.stderr or "No matching distribution" in proc.stderr:
            pytest.skip("building the wheel needs setuptools from the package index")
        raise AssertionError(proc.stderr[-2000:])
    (path,) = out.glob("posecast-*.whl")
    return zipfile.ZipFile(path)


def test_the_wheel_has_one_top_level_name(wheel: zipfile.ZipFile) -> None:
    tops = {name.split("/")[0] for name in wheel.namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"posecast"}
    (top_level,) = [n for n in wheel.namelist() if n.endswith(".dist-info/top_level.txt")]
    assert wheel.read(top_level).decode().split() == ["posecast"]


def test_the_wheel_holds_every_module_and_asset(wheel: zipfile.ZipFile) -> None:
    names = set(wheel.namelist())
    expected = {"posecast/" + p.relative_to(REPO).as_posix() for p in _sources()}
    assert expected - names == set()
    assets = [p for folder in FOLDERS for p in (REPO / folder / "assets").glob("*")]
    assert assets, "the rig and the built-in clip ship in the folders' assets/"
    for asset in assets:
        assert "posecast/" + asset.relative_to(REPO).as_posix() in names


def test_the_wheel_declares_the_licence(wheel: zipfile.ZipFile) -> None:
    (meta,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    text = wheel.read(meta).decode()
    assert "License-Expression: MIT" in text
    assert any(n.endswith("/licenses/LICENSE") for n in wheel.namelist())


def test_the_installed_distribution_provides_only_posecast() -> None:
    provided = {name for name, dists in importlib.metadata.packages_distributions().items()
                if "posecast" in dists}
    assert provided == {"posecast"}


def test_the_code_imports_its_parts_through_posecast() -> None:
    bad = []
    for path in [*_sources(), *sorted((REPO / "tests").glob("*.py"))]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom)
                     and node.level == 0 else [])
            bad += [f"{path.relative_to(REPO)}:{node.lineno} {n}" for n in names
                    if n.split(".")[0] in FOLDERS]
    assert bad == []


def test_version() -> None:
    import posecast

    assert posecast.__version__ == importlib.metadata.version("posecast")


def test_the_wheel_ships_the_built_browser_spectator(wheel: zipfile.ZipFile) -> None:
    """`make setup` builds client/web into server/static; the wheel holds the page and
    every file it names, so an installed `posecast serve` serves it."""
    import re

    names = set(wheel.namelist())
    static = "posecast/server/static/"
    assert static + "index.html" in names, "no page in the wheel: run make setup first"
    page = wheel.read(static + "index.html").decode()
    named = re.findall(r'"/static/([^"]+)"', page)
    assert {n.split("-")[0] for n in named} == {"app", "network"}
    assert {static + n for n in named} <= names
    assert static + "licenses.txt" in names
