"""A command's options from a TOML file (``posecast serve --config posecast.toml``).

Each key is an option's name with ``_`` or ``-`` (``busy_poll`` or ``busy-poll`` for
``--busy-poll``) and is checked and converted by that option's own argparse action: its
``type``, its ``choices``, a switch takes true or false, a repeatable option (``--limit``)
a list or a table of NAME = VALUE (``[limits]``). The values become the parser's defaults,
so that the command line, parsed again, overrides the file. Nothing here names an option:
an option added to a command is a key of its file at once.

It lives in client/ beside the CLI because it works on the CLI's argparse parsers; the
server never sees a file, only the values. ``config_defaults`` is pure (a parsed table in,
defaults out); ``read_config`` and ``apply_config`` read the file.
"""

from __future__ import annotations

import argparse
import difflib
import re
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from posecast.client.cli.arguments import _OWN_MESSAGE

# argparse's own actions that are not settings
_NOT_KEYS = (argparse._HelpAction, argparse._VersionAction)


class ConfigError(ValueError):
    """One line: the file, the line when known, the key and what is wrong with it."""


def read_config(path: Path) -> tuple[dict[str, Any], str]:
    """The file's table and its text (for line numbers); a ConfigError if it cannot be
    read or is not TOML (tomllib's message names the line and column)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot read {path}: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"cannot read {path}: byte {err.start} is not UTF-8 text, "
                          "as TOML must be") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path} is not valid TOML: {err}") from None


def option_keys(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """Every key a file may hold for ``parser``, in ``_`` form, with its action; a
    repeatable option is also named in the plural (``limits`` for ``--limit``)."""
    keys: dict[str, argparse.Action] = {}
    for action in parser._actions:
        if isinstance(action, _NOT_KEYS) or action.dest == "config":
            continue
        for option in action.option_strings:
            if option.startswith("--"):
                keys[_key(option[2:])] = action
                if isinstance(action, argparse._AppendAction):
                    keys[_key(option[2:]) + "s"] = action
    return keys


def config_defaults(parser: argparse.ArgumentParser, table: dict[str, Any],
                    text: str = "") -> dict[str, Any]:
    """``{dest: value}`` for ``parser.set_defaults`` from a file's parsed ``table``, each
    value converted and checked by its option's action; ``text`` (the file) gives the
    line of a bad key. A ConfigError names the first bad key."""
    keys = option_keys(parser)
    defaults: dict[str, Any] = {}
    given: dict[str, str] = {}  # dest -> the key that set it, to refuse two keys for one
    for key, value in table.items():
        where = _where(text, key)
        action = keys.get(_key(key))
        if action is None:
            near = difflib.get_close_matches(_key(key), keys, n=1)
            raise ConfigError(f"{where}unknown key {key!r}"
                              + (f" (did you mean {near[0]!r}?)" if near else "")
                              + f"; the keys are {', '.join(_shown(keys))}")
        if action.dest in given:
            raise ConfigError(f"{where}{key!r} sets what {given[action.dest]!r} sets already")
        given[action.dest] = key
        if isinstance(value, dict) and isinstance(action, argparse._AppendAction):
            defaults[action.dest] = list(_table(action, key, value, text))
            continue
        try:
            defaults[action.dest] = _value(action, key, value)
        except ConfigError as err:
            raise ConfigError(f"{where}{err}") from None
    return defaults


def apply_config(root: argparse.ArgumentParser, command: argparse.ArgumentParser,
                 path: Path) -> None:
    """Make the file's values the defaults of ``command`` (a subcommand's parser of
    ``root``), so that parsing the command line again gives flags the last word."""
    table, text = read_config(path)
    try:
        defaults = config_defaults(command, table, text)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    actions = {action.dest: action for action in command._actions}
    for dest, value in defaults.items():
        action = actions[dest]
        action.required = False  # the file gave it
        # a global option repeated on the command (--log-level) has no default there: set
        # on the command, the file's value would hide the same flag given before it
        target = root if action.default is argparse.SUPPRESS else command
        target.set_defaults(**{dest: value})


# --------------------------------------------------------------------------- values
def _value(action: argparse.Action, key: str, value: Any) -> Any:
    if isinstance(action, argparse.BooleanOptionalAction):
        on = _switch(key, value)
        return on if _key(key) == _key(action.option_strings[0][2:]) else not on
    if isinstance(action, argparse._StoreConstAction):  # store_true/false and others
        return action.const if _switch(key, value) else action.default
    if isinstance(action, argparse._AppendAction):
        items = value if isinstance(value, list) else [value]
        return [_convert(action, key, item) for item in items]
    if type(action) is argparse._StoreAction:
        if action.nargs in ("*", "+") or isinstance(action.nargs, int):
            if not isinstance(value, list):
                raise ConfigError(f"{key} takes a list, e.g. {key} = [...], got {value!r}")
            return [_convert(action, key, item) for item in value]
        return _convert(action, key, value)
    raise ConfigError(f"{key} cannot be set from a file, only on the command line")


def _switch(key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key} is a switch: true or false, got {_shown_value(value)}")
    return value


def _table(action: argparse.Action, key: str, table: dict[str, Any],
           text: str) -> Iterator[Any]:
    """A table of NAME = VALUE for an option that takes NAME=VALUE (``[limits]`` for
    ``--limit``), each converted by the option; an error names the line of its NAME."""
    for name, value in table.items():
        where = f"{_where(text, key, name)}in [{key}]: "
        if isinstance(value, dict | list | bool):
            raise ConfigError(f"{where}{name} takes a number or a text, "
                              f"got {_shown_value(value)}")
        try:
            yield _convert(action, key, f"{name}={value}")
        except ConfigError as err:
            raise ConfigError(f"{where}{str(err).removeprefix(key).lstrip(': ')}") from None


def _convert(action: argparse.Action, key: str, value: Any) -> Any:
    """One value through the option's own ``type`` and ``choices``, as argparse would
    on the command line (numbers as their text: the checks take text)."""
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise ConfigError(f"{key} takes a value such as {key} = "
                          f"{'1' if action.type is not None else repr('text')}, "
                          f"got {_shown_value(value)}")
    text = value if isinstance(value, str) else str(value)
    convert = action.type if callable(action.type) else str
    try:
        result = convert(text)
    except argparse.ArgumentTypeError as err:
        why = str(err)
        raise ConfigError(f"{key} {why}" if why.startswith(_OWN_MESSAGE)
                          else f"{key}: {why}") from None
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: invalid value {text!r}") from None
    if action.choices is not None and result not in action.choices:
        raise ConfigError(f"{key} must be one of {', '.join(map(str, action.choices))}, "
                          f"got {text!r}")
    return result


# --------------------------------------------------------------------------- words
def _key(name: str) -> str:
    return name.replace("-", "_")


def _shown(keys: dict[str, argparse.Action]) -> list[str]:
    """The keys once each: an append option under its plural (``limits``) only."""
    shown: dict[int, str] = {}
    for key, action in keys.items():
        shown[id(action)] = key if id(action) not in shown or key.endswith("s") \
            else shown[id(action)]
    return list(shown.values())


def _shown_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "a list"
    return repr(value)


def _where(text: str, key: str, name: str | None = None) -> str:
    """'line N: ' where ``text`` (a TOML file) sets the top-level ``key`` (``key = ...``
    before any table, or a ``[key]`` table anywhere), or with ``name``, where the table
    ``[key]`` sets ``name``; '' if not found."""
    def pattern(word: str, form: str) -> re.Pattern[str]:
        quoted = rf"""(?:{re.escape(word)}|"{re.escape(word)}"|'{re.escape(word)}')"""
        return re.compile(form.replace("WORD", quoted))

    assignment, header = pattern(key, r"\s*WORD\s*="), pattern(key, r"\s*\[\s*WORD\s*\]")
    inner = pattern(name or "", r"\s*WORD\s*=")
    top_level, in_table = True, False  # a key after a table header belongs to that table
    for number, line in enumerate(text.splitlines(), 1):
        if name is None and (header.match(line) or (top_level and assignment.match(line))):
            return f"line {number}: "
        if name is not None and in_table and inner.match(line):
            return f"line {number}: "
        if line.lstrip().startswith("["):
            top_level, in_table = False, bool(header.match(line))
    return ""
