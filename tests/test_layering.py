"""The layering of the packages, read from every module's imports (docs/architecture.md,
"Layout"). Imports inside functions count: a lazy import is still a dependency.

- protocol/ and solver/ are pure: no network, process, GPU or device library. websockets'
  sans-I/O core (frames, protocol, streams, exceptions, and speedups' apply_mask) is
  allowed: protocol.arrivals stamps its frames and reads a lone frame where its parser
  (a StreamReader's generators) waits between frames, protocol.framing masks a
  player's. solver.readers parse files given by path (text in, arrays out).
- server/ never imports client/.
- in client/, nothing imports ``cli`` and only ``cli`` imports ``bench``; no package
  imports another's underscore (private) modules or names.
- in client/, only ``cli`` and ``bench`` (the demo embeds a server) import server/
  (../shared/DESIGN.md); elsewhere only ``server.avatars``, the batched solver state, so
  that the display error and the kernel warm-up solve as the server does.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PURE = ("protocol", "solver")
# libraries that do I/O beyond reading a file: sockets, processes, event loops, GPUs,
# devices, video
IO_LIBRARIES = frozenset({
    "asyncio", "socket", "ssl", "select", "selectors", "signal", "subprocess",
    "multiprocessing", "threading", "http", "urllib", "uvloop", "redis", "websockets",
    "moderngl", "glfw", "openvr", "cv2", "PIL", "pythonosc", "prometheus_client",
})
SANS_IO_WEBSOCKETS = ("websockets.frames", "websockets.protocol", "websockets.streams",
                      "websockets.exceptions", "websockets.speedups")
SERVER_IMPORTERS = frozenset({"cli", "bench"})
SERVER_SHARED = "posecast.server.avatars"


@dataclass(frozen=True)
class Imported:
    module: str  # the module named in the import
    names: tuple[str, ...]  # what a ``from`` import takes from it (empty: ``import x``)
    line: int


def imports_of(source: str) -> list[Imported]:
    """Every import of a module's source, at any depth, absolute names."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [Imported(a.name, (), node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append(Imported(node.module, tuple(a.name for a in node.names),
                                  node.lineno))
    return found


def violations(package: str, module: str, source: str) -> list[str]:
    """What the module ``module`` (a path under the repository, e.g. "client/cli/run.py")
    of ``package`` imports against the rules above, a line each."""
    found = []
    for imp in imports_of(source):
        where = f"{module}:{imp.line} imports {imp.module}"
        top = imp.module.split(".")[0]
        if package in PURE and top in IO_LIBRARIES \
                and not imp.module.startswith(SANS_IO_WEBSOCKETS):
            found.append(f"{where}: {package}/ is pure, {top} does I/O")
        if package == "server" and imp.module.startswith("posecast.client"):
            found.append(f"{where}: server/ never imports client/")
        if package.startswith("client.") and imp.module.startswith("posecast.client."):
            found += _client_rule(package.split(".")[1], where, imp)
        if package.startswith("client.") and imp.module.startswith("posecast.server") \
                and package.split(".")[1] not in SERVER_IMPORTERS \
                and not imp.module.startswith(SERVER_SHARED):
            found.append(f"{where}: in client/, only cli and bench import server/")
    return found


def _client_rule(own: str, where: str, imp: Imported) -> list[str]:
    parts = imp.module.split(".")[2:]  # after posecast.client
    other = parts[0]
    if other == own:
        return []
    found = []
    if other == "cli":
        found.append(f"{where}: nothing imports the command line (client.cli)")
    if other == "bench" and own != "cli":
        found.append(f"{where}: only client.cli imports client.bench")
    private = [p for p in parts[1:] if p.startswith("_") and p != "__init__"]
    private += [n for n in imp.names if n.startswith("_")]
    if private:
        found.append(f"{where}: {', '.join(private)} is private to client.{other}")
    return found


def package_of(path: Path) -> str:
    """"protocol", "solver", "server", or "client.<package>" ("client.<module>" for a
    module directly in client/)."""
    parts = path.relative_to(REPO).parts
    if parts[0] != "client":
        return parts[0]
    return f"client.{Path(parts[1]).stem}"


def all_violations() -> list[str]:
    found = []
    for folder in ("protocol", "solver", "server", "client"):
        for path in sorted((REPO / folder).rglob("*.py")):
            if "node_modules" in path.parts:
                continue
            found += violations(package_of(path), str(path.relative_to(REPO)),
                                path.read_text())
    return found


def test_the_packages_keep_their_layers() -> None:
    assert all_violations() == []


@pytest.mark.parametrize("package, module, source, words", [
    ("solver", "solver/fk.py", "import asyncio", "solver/ is pure"),
    ("protocol", "protocol/codec.py", "def f():\n    from websockets.asyncio.client import connect",
     "protocol/ is pure"),
    ("server", "server/room.py", "from posecast.client.session.player import Player",
     "server/ never imports client/"),
    ("client.session", "client/session/player.py", "from posecast.client.cli import main",
     "nothing imports the command line"),
    ("client.measure", "client/measure/plot.py", "from posecast.client.bench.demo import x",
     "only client.cli imports client.bench"),
    ("client.viewer", "client/viewer/core.py",
     "from posecast.client.session.connection import _sync", "_sync is private"),
    ("client.viewer", "client/viewer/core.py",
     "import posecast.client.session._internals", "_internals is private"),
    ("client.session", "client/session/player.py", "from posecast.server.app import Session",
     "only cli and bench import server/"),
])
def test_each_rule_fails_on_a_forbidden_import(package: str, module: str, source: str,
                                               words: str) -> None:
    """The rules are live: each forbidden import added to a module is reported."""
    found = violations(package, module, source)
    assert len(found) == 1 and words in found[0], found


@pytest.mark.parametrize("package, source", [
    ("protocol", "from websockets.frames import Frame"),  # the sans-I/O core
    ("solver", "from pathlib import Path"),  # readers take a path
    ("client.cli", "from posecast.client.bench.demo import run_demo"),
    ("client.bench", "from posecast.client.session.player import Player"),
    ("client.session", "from posecast.client.session.connection import _anything"),
    ("client.bench", "from posecast.server.serving import run_server"),
    ("client.measure", "from posecast.server.avatars import AvatarSolver"),
])
def test_what_the_rules_allow(package: str, source: str) -> None:
    assert violations(package, "x.py", source) == []
