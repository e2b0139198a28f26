"""deploy/: the example config holds every serve option with its default and loads; the
systemd unit passes ``systemd-analyze verify`` with nothing to say and its ExecStart is a
valid serve command; the Dockerfile runs as a user of its own, warms the kernels as that
user, exposes serve's port and checks /healthz; the healthcheck script answers for a
real server over http and https, and for none; and compose.yaml's processes are valid
`serve --redis` commands, each reached through the Caddyfile's route that its
--public-url names, sharing one secret and waiting for a healthy Redis."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import tomllib
import urllib.request
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml
from commands import WAIT, Command, closed_port
from conftest import REPO_ROOT
from test_cluster import Process, running, until

from posecast.client.bench.redis_process import RedisMissingError, RedisProcess, free_port
from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import _parser, arguments
from posecast.client.cli.config_file import config_defaults, option_keys
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.sources import open_source
from posecast.server.limits import ServerLimits

REPO = REPO_ROOT
DEPLOY = REPO / "deploy"
EXAMPLE = DEPLOY / "posecast.toml"
UNIT = DEPLOY / "posecast.service"
DOCKERFILE = DEPLOY / "Dockerfile"
HEALTHCHECK = DEPLOY / "healthcheck.py"
COMPOSE = DEPLOY / "compose.yaml"
CADDYFILE = DEPLOY / "Caddyfile"
CADDY = shutil.which("caddy")
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
    port = closed_port()
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


# --------------------------------------------------------------------------- compose.yaml
# a secret as `openssl rand -hex 32` makes one: what deploy/.env holds
SECRET_ENV = {"POSECAST_SECRET": "ab" * 32}
_VARIABLE = re.compile(r"\$(?:\$|\{(\w+)(?:(:?[-?+])([^}]*))?\}|(\w+))")


def _interpolate(value: Any, env: Mapping[str, str]) -> Any:
    """Compose's ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?error}, ${VAR:+other}
    and $$ in every string of ``value``; ValueError where Compose refuses to start."""
    if isinstance(value, dict):
        return {k: _interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [_interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def one(found: re.Match[str]) -> str:
        if found.group(0) == "$$":
            return "$"
        name = found.group(1) or found.group(4)
        how, text = found.group(2), found.group(3) or ""
        given = env.get(name)
        # with the colon, set to "" counts as unset
        present = given is not None and (given != "" or not how or ":" not in how)
        if how in ("-", ":-"):
            return given or "" if present else text
        if how in ("?", ":?"):
            if not present:
                raise ValueError(f"required variable {name} is missing a value: {text}")
            return given or ""
        if how in ("+", ":+"):
            return text if present else ""
        return given or ""

    return _VARIABLE.sub(one, value)


def _compose(env: Mapping[str, str] = SECRET_ENV) -> dict[str, Any]:
    """compose.yaml as Compose reads it: YAML with its anchors and merge keys, then the
    variables of ``env`` (the shell's and deploy/.env's)."""
    loaded = yaml.safe_load(COMPOSE.read_text())
    return _interpolate({k: v for k, v in loaded.items() if not k.startswith("x-")}, env)


def _posecast_services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The services built from deploy/Dockerfile, by name."""
    return {name: service for name, service in compose["services"].items()
            if "build" in service and (COMPOSE.parent / service["build"]["context"]
                                       / service["build"]["dockerfile"]).resolve()
            == DOCKERFILE}


def _environment(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):  # the - KEY=VALUE form
        return dict(item.partition("=")[::2] for item in env)
    return {k: str(v) for k, v in env.items()}


def _serve_args(service: dict[str, Any]) -> argparse.Namespace:
    """The image's entry point, then the service's command (more serve flags), parsed by
    serve's own parser: a bad flag or URL fails here as it would in the container."""
    entry = json.loads(next(rest for word, rest in _instructions() if word == "ENTRYPOINT"))
    assert "entrypoint" not in service, "the image's entry point is the serve command"
    command = service["command"]
    assert isinstance(command, list), "the exec form: no shell between Compose and serve"
    argv = [*entry, *command]
    argv[argv.index("--config") + 1] = str(EXAMPLE)  # the image's copy of it
    assert argv[:2] == ["posecast", "serve"]
    return _parser().parse_args(argv[1:])


def test_compose_runs_redis_three_processes_from_the_image_and_the_proxy() -> None:
    compose = _compose()
    services = compose["services"]
    processes = _posecast_services(compose)
    assert sorted(processes) == ["posecast-1", "posecast-2", "posecast-3"]
    assert set(services) == {"redis", "proxy", *processes}
    assert services["redis"]["image"].split(":") == ["redis", "7"]
    for name, service in processes.items():
        assert (COMPOSE.parent / service["build"]["context"]).resolve() == REPO, name
        assert service["restart"] == "unless-stopped", name
        assert "ports" not in service, f"{name}: players come in through the proxy"
    # built once, as one image for all three
    assert len({service["image"] for service in processes.values()}) == 1


@pytest.mark.parametrize("host", [None, "play.example.net"], ids=["default", "POSECAST_HOST"])
def test_each_process_is_a_valid_serve_redis_command_with_its_own_public_url(
        host: str | None) -> None:
    env = {**SECRET_ENV, **({"POSECAST_HOST": host} if host else {})}
    compose = _compose(env)
    processes = _posecast_services(compose)
    port = _serve()._option_string_actions["--port"].default
    urls = set()
    for name, service in processes.items():
        args = _serve_args(service)
        assert args.command == "serve" and args.host == "0.0.0.0", name
        # the port the healthcheck asks (the config's, 8765) and the proxy dials
        assert args.port == port, name
        redis = urlsplit(args.redis)
        assert redis.scheme == "redis" and redis.hostname in compose["services"], name
        assert redis.hostname == "redis" and (redis.port or 6379) == 6379, name
        public = urlsplit(args.public_url)
        assert public.scheme == "wss", f"{name}: the proxy serves TLS"
        assert public.hostname == (host or "posecast.example.org"), name
        assert public.path == f"/s{name.rpartition('-')[2]}/", name
        urls.add(args.public_url)
    assert len(urls) == len(processes), "two processes would send players to one place"


def test_every_process_has_the_same_secret_from_the_environment() -> None:
    raw = yaml.safe_load(COMPOSE.read_text())["services"]
    compose = _compose()
    sources = {_environment(raw[name]).get("POSECAST_SECRET")
               for name in _posecast_services(compose)}
    assert len(sources) == 1, f"the processes' secrets come from different places: {sources}"
    source = sources.pop()
    assert source is not None and source.startswith("${POSECAST_SECRET"), source
    for name, service in _posecast_services(compose).items():
        assert _environment(service)["POSECAST_SECRET"] == SECRET_ENV["POSECAST_SECRET"], name
    # deploy/.env, where it is kept, stays out of git and of the image's build context
    assert "**/.env" in (REPO / ".dockerignore").read_text().split()
    assert ".env" in (REPO / ".gitignore").read_text().split()
    # no secret given: Compose refuses to start, rather than three open servers
    with pytest.raises(ValueError, match="POSECAST_SECRET"):
        _compose({})
    with pytest.raises(ValueError, match="POSECAST_SECRET"):
        _compose({"POSECAST_SECRET": ""})


def test_redis_is_checked_and_the_processes_wait_for_it() -> None:
    compose = _compose()
    redis = compose["services"]["redis"]
    assert redis["healthcheck"]["test"][:1] in (["CMD"], ["CMD-SHELL"])
    assert " ".join(redis["healthcheck"]["test"][1:]) == "redis-cli ping"
    # nothing in Redis outlives the processes that renew it: no snapshot, no AOF
    assert redis["command"][0] == "redis-server" and "--save" in redis["command"]
    steps = _instructions()
    check = next(rest for word, rest in steps if word == "HEALTHCHECK")
    image_check = json.loads(check[check.index("CMD") + len("CMD"):])
    for name, service in _posecast_services(compose).items():
        assert service["depends_on"]["redis"]["condition"] == "service_healthy", name
        # serve's own /healthz, as the image's HEALTHCHECK asks it
        assert service["healthcheck"]["test"] == ["CMD", *image_check], name


def test_the_proxy_is_caddy_on_80_and_443_with_the_caddyfile() -> None:
    compose = _compose()
    proxy = compose["services"]["proxy"]
    assert proxy["image"].split(":")[0] == "caddy"
    published = {str(p).split(":")[0] for p in proxy["ports"]}
    assert {"80", "443"} <= published
    mounts = [v.split(":") for v in proxy["volumes"]]
    caddyfile = next(m for m in mounts if m[1] == "/etc/caddy/Caddyfile")
    assert (COMPOSE.parent / caddyfile[0]).resolve() == CADDYFILE
    assert any(m[1] == "/data" for m in mounts), "certificates lost with the container"
    assert set(proxy["depends_on"]) == set(_posecast_services(compose))
    # the site's name is the one the public URLs carry
    raw = yaml.safe_load(COMPOSE.read_text())["services"]["proxy"]
    assert _environment(raw)["POSECAST_HOST"] == "${POSECAST_HOST:-posecast.example.org}"
    assert _caddy_env(_site().words[0], {}) == "posecast.example.org"
    assert _caddy_env(_site().words[0], {"POSECAST_HOST": "a.example"}) == "a.example"


# --------------------------------------------------------------------------- Caddyfile
@dataclasses.dataclass
class _Block:
    """A Caddyfile line (its words) and the block it opens, if any."""

    words: list[str]
    body: list[_Block]

    def first(self, directive: str) -> _Block:
        return next(b for b in self.body if b.words[0] == directive)


def _caddyfile() -> list[_Block]:
    root = _Block([], [])
    stack = [root]
    for number, line in enumerate(CADDYFILE.read_text().splitlines(), 1):
        words = []
        for word in line.split():
            if word.startswith("#"):
                break
            words.append(word)
        if words == ["}"]:
            stack.pop()
            assert stack, f"{CADDYFILE.name}: line {number}: a }} that closes nothing"
        elif words:
            block = _Block(words[:-1] if words[-1] == "{" else words, [])
            stack[-1].body.append(block)
            if words[-1] == "{":
                stack.append(block)
    assert len(stack) == 1, f"{CADDYFILE.name}: a {{ never closed"
    return root.body


def _site() -> _Block:
    sites = [b for b in _caddyfile() if b.body and b.words]
    assert len(sites) == 1, "one site: the service's public name"
    return sites[0]


def _caddy_env(text: str, env: Mapping[str, str]) -> str:
    """Caddy's {$VAR} and {$VAR:default} in a Caddyfile."""
    return re.sub(r"\{\$(\w+)(?::([^}]*))?\}",
                  lambda m: env.get(m.group(1)) or m.group(2) or "", text)


def _path_matches(pattern: str, path: str) -> bool:
    """Caddy's path matcher, case-insensitive: /a/* a prefix, */a a suffix, *a* a part,
    other * a glob of one segment, else the whole path."""
    pattern, path = pattern.lower(), path.lower()
    if len(pattern) > 1 and pattern.startswith("*") and pattern.endswith("*"):
        return pattern[1:-1] in path
    if pattern.startswith("*"):
        return path.endswith(pattern[1:])
    if pattern.endswith("*"):
        return path.startswith(pattern[:-1])
    if "*" in pattern:
        return re.fullmatch(re.escape(pattern).replace(r"\*", "[^/]*"), path) is not None
    return path == pattern


Route = tuple[list[str], str, dict[str, Any]]  # upstreams, the path they see, proxy options


def _route_by_reading(path: str) -> Route:
    """Where the Caddyfile sends ``path``, read as Caddy does: handle and handle_path
    blocks exclude each other; one with a path matcher before the catch-all (longest
    first); handle_path strips what its matcher names before the *."""
    blocks = [b for b in _site().body if b.words[0] in ("handle", "handle_path")]
    matched = sorted((b for b in blocks if len(b.words) == 2 and b.words[1].startswith("/")),
                     key=lambda b: -len(b.words[1]))
    for block in [*matched, *(b for b in blocks if len(b.words) == 1)]:
        if len(block.words) == 2 and not _path_matches(block.words[1], path):
            continue
        if block.words[0] == "handle_path":
            path = path[len(block.words[1].rstrip("*").rstrip("/")):] or "/"
        proxy = block.first("reverse_proxy")
        options = {b.words[0]: b.words[1:] for b in proxy.body}
        return proxy.words[1:], path, options
    raise AssertionError(f"{CADDYFILE.name} sends {path} nowhere")


def _route_by_caddy(adapted: dict[str, Any]) -> Any:
    """Where Caddy's own JSON of the Caddyfile (``caddy adapt``) sends a path, for a client
    outside the private ranges."""
    server = next(iter(adapted["apps"]["http"]["servers"].values()))
    site = server["routes"][0]
    routes = site["handle"][0]["routes"]

    def route(path: str) -> Route:
        for entry in routes:
            sets = entry.get("match", [{}])
            if not any(_path_matches_any(s.get("path", ["*"]), path) for s in sets):
                continue
            upstreams: list[str] = []
            options: dict[str, Any] = {}
            for handler in _handlers(entry["handle"]):
                if handler["handler"] == "static_response":
                    return [], f"status {handler.get('status_code', 200)}", {}
                if handler["handler"] == "rewrite" and "strip_path_prefix" in handler:
                    prefix = handler["strip_path_prefix"]
                    if path.lower().startswith(prefix.lower()):
                        path = path[len(prefix):] or "/"
                if handler["handler"] == "reverse_proxy":
                    upstreams = [u["dial"] for u in handler["upstreams"]]
                    options = handler
            return upstreams, path, options
        raise AssertionError(f"caddy sends {path} nowhere")
    return route


def _path_matches_any(patterns: list[str], path: str) -> bool:
    return any(p == "*" or _path_matches(p, path) for p in patterns)


def _handlers(handlers: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every handler in order, subroutes opened (their routes here have no matchers)."""
    flat = []
    for handler in handlers:
        if handler["handler"] == "subroute":
            for route in handler["routes"]:
                flat.extend(_handlers(route["handle"]))
        else:
            flat.append(handler)
    return flat


def _check_routes(route: Any) -> None:
    """Each process's public URL reaches that process alone, with the prefix gone; the
    rest goes to all of them, load-balanced over those passing /healthz."""
    compose = _compose()
    processes = _posecast_services(compose)
    everyone = {f"{name}:{_serve_args(s).port}" for name, s in processes.items()}
    for name, service in processes.items():
        public = urlsplit(_serve_args(service).public_url).path
        upstreams, seen, _ = route(public)
        assert upstreams == [f"{name}:{_serve_args(service).port}"], (public, upstreams)
        assert seen == "/", f"{public} reaches {name} as {seen}"
        upstreams, seen, _ = route(public + "healthz")  # the same process's own pages
        assert upstreams == [f"{name}:{_serve_args(service).port}"] and seen == "/healthz"
    for path in ("/", "/static/main.js", "/healthz", "/avatar.json", "/s1", "/s12/"):
        upstreams, seen, options = route(path)
        assert set(upstreams) == everyone and len(upstreams) == len(everyone), path
        assert seen == path, f"{path} reaches a process as {seen}"
        assert options, f"{path}: no load balancing or health checks"


def test_the_caddyfile_routes_each_process_and_balances_the_rest() -> None:
    _check_routes(_route_by_reading)
    options = _route_by_reading("/")[2]
    assert options["health_uri"] == ["/healthz"]
    assert "lb_policy" in options and "lb_try_duration" in options


@pytest.mark.skipif(CADDY is None, reason="no caddy here (Debian: apt-get install caddy)")
def test_caddy_itself_reads_the_caddyfile_the_same_way() -> None:
    """caddy adapt: the Caddyfile as Caddy understands it (JSON), routed the same way."""
    proc = subprocess.run([CADDY or "", "adapt", "--config", str(CADDYFILE), "--adapter",
                           "caddyfile"], capture_output=True, text=True, timeout=WAIT,
                          env={**os.environ, "POSECAST_HOST": "play.example.net"})
    assert proc.returncode == 0, proc.stderr
    adapted = json.loads(proc.stdout)
    server = next(iter(adapted["apps"]["http"]["servers"].values()))
    assert server["routes"][0]["match"] == [{"host": ["play.example.net"]}]
    route = _route_by_caddy(adapted)
    _check_routes(route)
    balanced = route("/")[2]
    assert balanced["health_checks"]["active"]["uri"] == "/healthz"
    assert balanced["load_balancing"]["try_duration"] > 0
    # a process's /metrics from outside: refused (the monitoring network scrapes it)
    assert route("/s1/metrics")[1] == "status 403" and route("/metrics")[1] == "status 403"


def _local_caddyfile(proxy_port: int, upstreams: Mapping[str, int]) -> str:
    """The Caddyfile on this machine: plain http on 127.0.0.1:``proxy_port`` for the site,
    each service's address (posecast-1:8765) the port of a process here, no admin API."""
    text = CADDYFILE.read_text()
    site = _site().words[0]
    assert text.count(f"{site} {{") == 1
    text = text.replace(f"{site} {{", f"http://127.0.0.1:{proxy_port} {{")
    for address, port in upstreams.items():
        assert address in text, address
        text = re.sub(rf"(?<![\w-]){re.escape(address)}(?![\w-])", f"127.0.0.1:{port}", text)
    return "{\n\tadmin off\n}\n" + text


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return reply.status, reply.read()
    except OSError:
        return 0, b""


@pytest.mark.skipif(CADDY is None, reason="no caddy here (Debian: apt-get install caddy)")
def test_through_caddy_players_reach_the_owners_route_and_spectators_any_process(
        tmp_path: Path) -> None:
    """The Caddyfile served by a real Caddy in front of three processes sharing a real
    Redis (in this event loop, each with the --public-url of its route): players and
    spectators all given the proxy's / only. The second player lands on another process
    and is sent to the owner's /sK/, which reaches that process; spectators on the
    others receive both players' frames; /sK/healthz is process K's."""
    try:
        redis = RedisProcess().start()
    except RedisMissingError as err:
        pytest.skip(str(err))
    compose = _compose()
    names = sorted(_posecast_services(compose))
    proxy_port = free_port()
    proxy = f"ws://127.0.0.1:{proxy_port}"
    log = tmp_path / "caddy.log"

    async def main() -> None:
        processes = [Process(redis.url) for _ in names]
        for k, process in enumerate(processes, 1):
            process.cluster.public_url = f"{proxy}/s{k}/"
        async with contextlib.AsyncExitStack() as stack:
            for process in processes:
                await stack.enter_async_context(process)
            config = tmp_path / "Caddyfile"
            config.write_text(_local_caddyfile(proxy_port, {
                f"{name}:{_serve_args(compose['services'][name]).port}": p.port
                for name, p in zip(names, processes, strict=True)}))
            with log.open("w") as out:
                caddy = await asyncio.create_subprocess_exec(
                    CADDY or "", "run", "--config", str(config), "--adapter", "caddyfile",
                    stdout=out, stderr=out, env={**os.environ,
                                                 "XDG_CONFIG_HOME": str(tmp_path / "config"),
                                                 "XDG_DATA_HOME": str(tmp_path / "data")})
            stack.push_async_callback(_stop, caddy)
            t_end = time.monotonic() + WAIT
            while (await asyncio.to_thread(_get, f"http://127.0.0.1:{proxy_port}/healthz")
                   )[0] != 200:
                assert caddy.returncode is None, log.read_text()[-2000:]
                assert time.monotonic() < t_end, "caddy never answered"
                await asyncio.sleep(0.1)
            status, page = await asyncio.to_thread(
                _get, f"http://127.0.0.1:{proxy_port}/?room=hall")
            assert status == 200 and b"<html" in page.lower()

            sources = [open_source(f"bvh:{builtin_motion_path()}", loop=True)
                       for _ in range(2)]
            stack.callback(lambda: [s.close() for s in sources])
            first, second = (Player(f"{proxy}/", "hall", f"p{i}", s)
                             for i, s in enumerate(sources))
            await stack.enter_async_context(running(first))
            await until(lambda: any(p.session.metrics.frames_solved > 10 for p in processes),
                        "the first player's process owning the room")
            k, owner = next((k, p) for k, p in enumerate(processes, 1)
                            if p.session.metrics.frames_solved)
            # least_conn: the second goes to a process without the first, and on
            await stack.enter_async_context(running(second))
            await until(lambda: second.stats.frames_sent > 20, "the second streaming")
            assert second.session is not None and second.session.url == f"{proxy}/s{k}/"
            assert sum(p.cluster.stats.redirects for p in processes) == 1
            assert {first.stats.avatar_id, second.stats.avatar_id} <= set(
                owner.session.rooms["hall"].avatars)
            for j in range(1, len(processes) + 1):  # /sJ/ is process J
                status, body = await asyncio.to_thread(
                    _get, f"http://127.0.0.1:{proxy_port}/s{j}/healthz")
                assert status == 200 and json.loads(body)["players"] == (2 if j == k else 0)

            viewers = [Spectator(f"{proxy}/", "hall", f"v{i}") for i in range(2)]
            await stack.enter_async_context(running(*viewers))
            ids = {first.stats.avatar_id, second.stats.avatar_id}
            await until(lambda: all(set(v.stats.frames_per_avatar) == ids
                                    and min(v.stats.frames_per_avatar.values()) > 20
                                    for v in viewers), "both players' frames to the viewers")
            elsewhere = sum(len(p.session.rooms["hall"].spectators) for p in processes
                            if p is not owner and "hall" in p.session.rooms)
            assert elsewhere >= 1, "no spectator went through another process"

    try:
        asyncio.run(main())
    finally:
        redis.stop()


async def _stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.terminate()
    await asyncio.wait_for(proc.wait(), WAIT)
