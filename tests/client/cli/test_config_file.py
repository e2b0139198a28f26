"""``posecast serve --config FILE.toml``: every serve option from a file, checked by the
option's own rules, the command line over it; a bad file is one line naming the line and
the key, exit 2. The last tests run the real command and see it listen where the file
and the flags say."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from commands import WAIT, Command, closed_port
from test_cli_errors import _one_line

from posecast.client.cli import _parser, _with_config, arguments, main
from posecast.client.cli.config_file import ConfigError, config_defaults, option_keys


def _serve_parser() -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    root = _parser()
    serve = next(p for p in arguments.subparsers(root) if p.prog == "posecast serve")
    return root, serve


def _parse(tmp_path: Path, toml: str, *flags: str) -> argparse.Namespace:
    """serve's arguments as main() sees them, with ``toml`` as the config file."""
    config = tmp_path / "posecast.toml"
    config.write_text(toml)
    root, _ = _serve_parser()
    argv = ["serve", "--config", str(config), *flags]
    return _with_config(root, root.parse_args(argv), argv)


def test_every_serve_option_is_a_key_and_none_other() -> None:
    _, serve = _serve_parser()
    options = {o[2:].replace("-", "_") for a in serve._actions for o in a.option_strings
               if o.startswith("--") and o not in ("--help", "--config")}
    assert set(option_keys(serve)) == options | {"limits"}  # --limit's plural too


def test_values_are_converted_by_each_options_own_rules(tmp_path: Path) -> None:
    args = _parse(tmp_path, """
host = "0.0.0.0"
port = 9001
solver = "dls"
busy-poll = true
no_helper = true
log_level = "debug"

[limits]
players_per_room = 200   # raised with avatars_per_room: checked together at start
avatars_per_room = 400
frames_per_s = 480
""")
    assert (args.host, args.port, args.solver) == ("0.0.0.0", 9001, "dls")
    assert args.busy_poll is True and args.helper is False
    assert args.log_level == "debug"
    assert args.limit == ["players_per_room=200", "avatars_per_room=400", "frames_per_s=480"]


def test_a_file_of_nothing_changes_nothing(tmp_path: Path) -> None:
    root, _ = _serve_parser()
    plain = vars(root.parse_args(["serve"]))
    configured = vars(_parse(tmp_path, "# only comments\n[limits]\n"))
    assert configured.pop("config") is not None and plain.pop("config") is None
    assert {k: v for k, v in configured.items() if k != "show_help"} == \
        {k: v for k, v in plain.items() if k != "show_help"}


def test_flags_override_the_file(tmp_path: Path) -> None:
    toml = 'port = 9001\nsolver = "dls"\nlog_level = "error"\n[limits]\nmax_queue = 8\n'
    args = _parse(tmp_path, toml, "--port", "9002", "--limit", "max_queue=4",
                  "--log-level", "info")
    assert (args.port, args.solver, args.log_level) == (9002, "dls", "info")
    assert args.limit == ["max_queue=8", "max_queue=4"]  # applied in order: the flag wins
    # --log-level before the command as well: the file must not hide it
    config = tmp_path / "posecast.toml"
    root, _ = _serve_parser()
    argv = ["--log-level", "warning", "serve", "--config", str(config)]
    assert _with_config(root, root.parse_args(argv), argv).log_level == "warning"


def test_switches_take_true_or_false(tmp_path: Path) -> None:
    assert _parse(tmp_path, "busy_poll = false\n").busy_poll is False
    assert _parse(tmp_path, "no_helper = false\n").helper is True
    assert _parse(tmp_path, "no-helper = true\n").helper is False


BAD_FILES: list[tuple[str, str]] = [  # (file, words the one line must hold)
    ("prot = 8765\n", "line 1: unknown key 'prot' (did you mean 'port'?)"),
    ('host = "h"\nport = "eighty"\n', "line 2: port must be a whole number, got 'eighty'"),
    ("port = 70000\n", "line 1: port must be a port number from 0 to 65535"),
    ("port = 80.5\n", "line 1: port must be a whole number, got '80.5'"),
    ('solver = "fast"\n', "line 1: solver must be one of analytic, dls, paper, got 'fast'"),
    ("busy_poll = 1\n", "line 1: busy_poll is a switch: true or false, got 1"),
    ("host = true\n", "line 1: host takes a value"),
    ('host = ["a", "b"]\n', "line 1: host takes a value"),
    ("busy_poll = true\nbusy-poll = false\n", "line 2: 'busy-poll' sets what 'busy_poll'"),
    ("port = \n", "is not valid TOML: Invalid value (at line 1, column 8)"),
    ("[server]\nport = 1\n", "line 1: unknown key 'server'"),
    ("[limits]\nmax_queue = 8\nrooms = 0\n", "line 3: in [limits]: limit rooms must be positive"),
    ("[limits]\nroom = 3\n", "line 2: in [limits]: unknown limit 'room'"),
    ("[limits]\nrooms = true\n", "line 2: in [limits]: rooms takes a number or a text"),
    ('[limits]\nrooms = "many"\n', "line 2: in [limits]: limit rooms takes an integer"),
]


@pytest.mark.parametrize(("toml", "words"), BAD_FILES, ids=[t for t, _ in BAD_FILES])
def test_a_bad_file_is_one_line_naming_the_line_and_key(
        toml: str, words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "posecast.toml"
    config.write_text(toml)
    with pytest.raises(SystemExit) as exit_info:
        main(["serve", "--config", str(config)])
    assert exit_info.value.code == 2
    line = _one_line(capsys.readouterr().err, "serve", "--config")
    assert words in line and str(config) in line, line


def test_a_missing_or_unreadable_file_is_one_line(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    cases = [(["--config", str(tmp_path / "none.toml")], "no such file"),
             (["--config", str(tmp_path)], "is a folder"),
             (["--config", str(tmp_path / "binary.toml")], "byte 0 is not UTF-8 text")]
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfeport = 1\n")
    for flags, words in cases:
        with pytest.raises(SystemExit) as exit_info:
            main(["serve", *flags])
        assert exit_info.value.code == 2
        assert words in _one_line(capsys.readouterr().err, "serve", "--config")


def test_limits_that_go_together_are_one_line_when_they_do_not(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "posecast.toml"
    config.write_text("[limits]\nplayers_per_room = 200\n")  # over avatars_per_room's 128
    with pytest.raises(SystemExit) as exit_info:
        main(["serve", "--config", str(config)])
    assert exit_info.value.code == 2
    line = _one_line(capsys.readouterr().err, "serve", "[limits]")
    assert "avatars_per_room (128) must be at least players_per_room (200)" in line


def test_config_defaults_is_pure_and_says_which_key() -> None:
    _, serve = _serve_parser()
    assert config_defaults(serve, {"port": 0, "limits": {"rooms": 3}}) == \
        {"port": 0, "limit": ["rooms=3"]}
    with pytest.raises(ConfigError, match=r"^unknown key 'hots'"):
        config_defaults(serve, {"hots": "x"})  # no text given: no line number


# --------------------------------------------------------------------------- real server
def test_the_real_server_listens_where_the_file_says_unless_a_flag_says_otherwise(
        tmp_path: Path) -> None:
    from_file, from_flag = closed_port(), closed_port()
    config = tmp_path / "posecast.toml"
    config.write_text(f'host = "127.0.0.1"\nport = {from_file}\nsolver = "dls"\n'
                      "[limits]\nrooms = 2\n")
    for flags, port in (([], from_file), (["--port", str(from_flag)], from_flag)):
        serve = Command("serve", "--config", str(config), *flags, cwd=tmp_path)
        try:
            serve.wait_for(f"posecast server on ws://127.0.0.1:{port}")
        finally:
            serve.proc.send_signal(signal.SIGTERM)
            code, out, err = serve.finish()
        assert code == 0, err
        assert '"connections": 0' in out  # its counters, printed as it stops


def test_the_real_command_with_a_bad_file_never_shows_a_traceback(tmp_path: Path) -> None:
    config = tmp_path / "posecast.toml"
    config.write_text("[limits]\nconnections = -1\n")
    proc = subprocess.run([sys.executable, "-m", "posecast.client.cli", "serve",
                           "--config", str(config)],
                          capture_output=True, text=True, timeout=WAIT, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    line = _one_line(proc.stderr, "serve", "--config")
    assert "line 2: in [limits]: limit connections must be positive, got -1" in line
