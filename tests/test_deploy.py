"""deploy/: the example config holds every serve option with its default and loads; the
systemd unit passes ``systemd-analyze verify`` with nothing to say and its ExecStart is a
valid serve command; the Dockerfile runs as a user of its own, warms the kernels as that
user, exposes serve's port and checks /healthz; and the healthcheck script answers for a
real server over http and https, and for none."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from test_cli_errors import WAIT, Command, _closed_port

from posecast.client import arguments
from posecast.client.cli import _parser
from posecast.client.config_file import config_defaults, option_keys
from posecast.server.limits import ServerLimits

REPO = Path(__file__).resolve().parent.parent
DEPLOY = REPO / "deploy"
EXAMPLE = DEPLOY / "posecast.toml"
UNIT = DEPLOY / "posecast.service"
DOCKERFILE = DEPLOY / "Dockerfile"
HEALTHCHECK = DEPLOY / "healthcheck.py"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
OPENSSL = shutil.which("openssl")

# `# key = value`: a commented setting of the example (a comment in words has no " = ")
_COMMENTED = re.compile(r"^#\s*([A-Za-z_][\w-]*)\s*=\s*(.+)$")


def _serve() -> argparse.ArgumentParser:
    return next(p for p in arguments.subparsers(_parser()) if p.prog == "posecast serve")


def _example_settings() -> tuple[dict[str, str], dict[str, str]]:
    """The example's commented settings, ``{key: value text}``, top level and [limits]."""
    top: dict[str, str] = {}
    limits: dict[str, str] = {}
    table = top
    for line in EXAMPLE.read_text().splitlines():
        if line.strip() == "[limits]":
            table = limits
        found = _COMMENTED.match(line)
        if found:
            key, value = found.groups()
            assert key not in table, f"{key} is shown twice in {EXAMPLE.name}"
            table[key] = value
    return top, limits


# --------------------------------------------------------------------------- example config
def test_the_example_config_loads() -> None:
    text = EXAMPLE.read_text()
    defaults = config_defaults(_serve(), tomllib.loads(text), text)
    assert defaults["host"] == "0.0.0.0"  # a server for others: its one active setting


def test_the_example_shows_every_serve_option_and_nothing_else() -> None:
    serve = _serve()
    keys = option_keys(serve)
    top, limits = _example_settings()
    for key in top:
        assert key.replace("-", "_") in keys, f"{key} in {EXAMPLE.name} is no serve option"
    shown = {id(keys[k.replace("-", "_")]) for k in top} | {id(keys["limits"])}
    missing = [k for k, action in keys.items() if id(action) not in shown and k != "limits"]
    assert not missing, f"serve options missing from {EXAMPLE.name}: {missing}"
    assert list(limits) == [f.name for f in dataclasses.fields(ServerLimits)]


def test_each_commented_value_is_the_options_default() -> None:
    """Uncommenting a line changes nothing: the example cannot go stale on a default."""
    serve = _serve()
    keys = option_keys(serve)
    top, limits = _example_settings()
    for key, text in top.items():
        action = keys[key.replace("-", "_")]
        if action.default is None:  # an example path (checked: it must exist) or address
            continue
        value = config_defaults(serve, tomllib.loads(f"{key} = {text}"))[action.dest]
        if action.default is not argparse.SUPPRESS:  # else a global option (log_level)
            assert value == action.default, f"{key}: {value!r} is not the default"
    loaded = ServerLimits().with_text([f"{k}={tomllib.loads(f'v = {v}')['v']}"
                                       for k, v in limits.items()])
    assert loaded == ServerLimits()


# --------------------------------------------------------------------------- systemd unit
def _unit_lines() -> dict[str, list[str]]:
    values: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            values.setdefault(key, []).append(value)
    return values


def test_the_unit_is_hardened_but_lets_numba_jit() -> None:
    unit = _unit_lines()
    for key, value in [("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"),
                       ("ProtectHome", "yes"), ("PrivateTmp", "yes"),
                       ("PrivateDevices", "yes"), ("LockPersonality", "yes"),
                       ("CapabilityBoundingSet", ""), ("SystemCallFilter", "@system-service"),
                       ("DynamicUser", "yes"), ("Restart", "on-failure"),
                       ("CacheDirectory", "posecast")]:
        assert value in unit.get(key, []), f"{UNIT.name}: no {key}={value}"
    assert "AF_INET" in unit["RestrictAddressFamilies"][0].split()
    # numba's LLVM JIT writes code and then runs it: this option would kill the server
    assert "MemoryDenyWriteExecute" not in unit
    assert any(v.startswith("NUMBA_CACHE_DIR=%C/posecast") for v in unit["Environment"])


def test_the_units_command_is_a_valid_serve_command(tmp_path: Path) -> None:
    """ExecStart parsed by serve's own parser, %d (the credentials) a folder with a secret."""
    (tmp_path / "secret").write_text("s" * 64 + "\n")
    argv = shlex.split(_unit_lines()["ExecStart"][0].replace("%d", str(tmp_path)))
    assert Path(argv[0]).name == "posecast" and argv[1] == "serve"
    config = argv.index("--config") + 1
    argv[config] = str(EXAMPLE)  # /etc/posecast/posecast.toml, installed from here
    args = _parser().parse_args(argv[1:])
    assert args.config == EXAMPLE and args.secret_file == tmp_path / "secret"


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="no systemd-analyze on this machine")
def test_systemd_analyze_verifies_the_unit_with_nothing_to_say(tmp_path: Path) -> None:
    # verify wants ExecStart's program to exist: this checkout's posecast stands in for
    # /opt/posecast's
    posecast = Path(sys.executable).parent / "posecast"
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace("/opt/posecast/bin/posecast", str(posecast)))
    proc = subprocess.run([SYSTEMD_ANALYZE or "", "verify", str(unit)], capture_output=True,
                          text=True, timeout=WAIT)
    # an unknown key or syscall group is only a warning there (status 0): none allowed
    assert proc.returncode == 0 and proc.stderr == "" and proc.stdout == "", proc.stderr
    security = subprocess.run([SYSTEMD_ANALYZE or "", "security", "--offline=yes",
                               str(unit)], capture_output=True, text=True, timeout=WAIT)
    found = re.search(r"Overall exposure level for \S+: ([\d.]+)", security.stdout)
    if security.returncode != 0 or found is None:
        pytest.skip(f"systemd-analyze security --offline is not here: {security.stderr}")
    assert float(found.group(1)) <= 2.0, security.stdout  # systemd's own "OK" band (1.2 now)


# --------------------------------------------------------------------------- Dockerfile
def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments left out."""
    text = re.sub(r"\\\n\s*", " ", "\n".join(
        line for line in DOCKERFILE.read_text().splitlines()
        if not line.lstrip().startswith("#")))
    return [(word.upper(), rest.strip()) for word, _, rest
            in (line.strip().partition(" ") for line in text.splitlines() if line.strip())]


def test_the_image_runs_as_a_user_of_its_own_after_warming_as_it() -> None:
    steps = _instructions()
    users = [i for i, (word, _) in enumerate(steps) if word == "USER"]
    assert users, "no USER: the server would run as root"
    user = steps[users[-1]][1]
    assert user not in ("root", "0") and not user.startswith(("root:", "0:"))
    warm = next(i for i, (word, rest) in enumerate(steps)
                if word == "RUN" and rest == "posecast warm")
    assert warm > users[-1], "kernels warmed as root: the runtime user could not use them"
    env = " ".join(rest for word, rest in steps if word == "ENV")
    assert "NUMBA_CACHE_DIR=/var/cache/posecast" in env
    assert "--home-dir /var/cache/posecast" in " ".join(r for w, r in steps if w == "RUN")


def test_the_image_is_slim_python_3_11_up_with_the_viewers_gl() -> None:
    steps = _instructions()
    python = re.search(r"ARG PYTHON=3\.(\d+)", DOCKERFILE.read_text())
    assert python is not None and int(python.group(1)) >= 11
    bases = [rest for word, rest in steps if word == "FROM"]
    assert bases and all(b.startswith("python:${PYTHON}-slim") for b in bases)
    apt = " ".join(rest for word, rest in steps if word == "RUN" and "apt-get" in rest)
    assert {"libegl1", "libgl1", "libgl1-mesa-dri"} <= set(apt.split())


def test_the_image_exposes_serves_port_and_checks_healthz() -> None:
    steps = _instructions()
    port = _serve()._option_string_actions["--port"].default
    assert [rest for word, rest in steps if word == "EXPOSE"] == [str(port)]
    check = [rest for word, rest in steps if word == "HEALTHCHECK"]
    assert len(check) == 1 and "/usr/local/lib/posecast/healthcheck.py" in check[0]
    copies = [rest.split() for word, rest in steps if word == "COPY" and "--from" not in rest]
    assert ["deploy/healthcheck.py", "/usr/local/lib/posecast/healthcheck.py"] in copies
    assert ["deploy/posecast.toml", "/etc/posecast/posecast.toml"] in copies
    sys.path.insert(0, str(DEPLOY))
    try:
        import healthcheck  # deploy/healthcheck.py
    finally:
        sys.path.remove(str(DEPLOY))
    assert port == healthcheck.DEFAULT_PORT
    assert healthcheck.DEFAULT_CONFIG == "/etc/posecast/posecast.toml"


def test_the_images_entry_point_is_a_valid_serve_command() -> None:
    steps = _instructions()
    entry = json.loads(next(rest for word, rest in steps if word == "ENTRYPOINT"))
    assert entry[:4] == ["posecast", "serve", "--host", "0.0.0.0"]
    entry[entry.index("--config") + 1] = str(EXAMPLE)  # the image's copy of it
    args = _parser().parse_args(entry[1:])
    assert (args.host, args.config) == ("0.0.0.0", EXAMPLE)


def test_the_build_context_leaves_out_the_venv_and_git() -> None:
    ignored = (REPO / ".dockerignore").read_text().split()
    assert {".git", ".venv", "**/__pycache__"} <= set(ignored)
    for word, rest in _instructions():  # what the image copies from the context is there
        if word == "COPY" and "--from" not in rest:
            source = rest.split()[0]
            assert source == "." or (REPO / source).exists(), source
            assert not any(source.startswith(i) for i in ignored if i != "."), source


# --------------------------------------------------------------------------- healthcheck
def _healthcheck(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(HEALTHCHECK)], capture_output=True, text=True,
                          timeout=WAIT, env={**os.environ, **env})


@pytest.fixture(scope="module")
def certificate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    if OPENSSL is None:
        pytest.skip("no openssl command line here: the test makes its certificate with it")
    d = tmp_path_factory.mktemp("deploy_tls")
    subprocess.run([OPENSSL or "", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                    "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", "key.pem", "-out",
                    "cert.pem", "-days", "2", "-subj", "/CN=posecast.example.org"],
                   cwd=d, check=True, capture_output=True, timeout=60)
    return d / "cert.pem", d / "key.pem"


@pytest.mark.parametrize("tls", [False, True], ids=["http", "https"])
def test_the_healthcheck_passes_for_a_serving_server_and_fails_without_one(
        tls: bool, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    port = _closed_port()
    config = tmp_path / "posecast.toml"
    settings = f'host = "127.0.0.1"\nport = {port}\n'
    if tls:  # a certificate for the public name: the loopback check must not mind
        cert, key = request.getfixturevalue("certificate")
        settings += f'certfile = "{cert}"\nkeyfile = "{key}"\n'
    config.write_text(settings)
    env = {"POSECAST_CONFIG": str(config)}
    serve = Command("serve", "--config", str(config), cwd=tmp_path)
    try:
        serve.wait_for(f"posecast server on {'wss' if tls else 'ws'}://127.0.0.1:{port}")
        passed = _healthcheck(env)
        assert passed.returncode == 0, passed.stderr
        scheme = "https" if tls else "http"
        wrong = _healthcheck({**env, "POSECAST_HEALTHZ_URL":
                              f"{scheme}://127.0.0.1:{port}/no-such-page"})
        assert wrong.returncode == 1 and "answered 404" in wrong.stderr
    finally:
        serve.proc.send_signal(signal.SIGTERM)
        code, _, err = serve.finish()
    assert code == 0, err
    failed = _healthcheck(env)  # nothing listens there now
    assert failed.returncode == 1
    assert failed.stderr.startswith(f"healthcheck: {scheme}://127.0.0.1:{port}/healthz: ")
