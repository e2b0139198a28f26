"""The checks behind `posecast`'s options, and the parser that reports a bad one.

Every value is checked while the command line is parsed, before anything connects,
compiles or loads, and a bad one ends the command with one line on stderr that names the
option (``posecast view: --fps must be a positive number, got '0'``) and status 2, as
argparse does. Each check is an argparse ``type``: it returns the value converted, or
raises ``ArgumentTypeError`` with the rule in plain words.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn
from urllib.parse import urlsplit

# light modules only (the parser uses these types): the rest is imported where it is used
from posecast.protocol.sizes import MAX_NAME_CHARS, MAX_RATE_HZ, MAX_TOKEN_CHARS
from posecast.solver.tracking.devices import parse_devices

if TYPE_CHECKING:
    from posecast.client.bench.network import NetworkSpec
    from posecast.solver.tracking.dropouts import DropoutSpec

LOG_LEVELS = ("debug", "info", "warning", "error")
MAX_OFFSET_M = 100.0  # a shift further than this is a typo (the protocol caps positions)
MIN_SIZE, MAX_SIZE = 16, 8192  # pixels, each side of a rendered frame
SOURCE_FORMS = "openvr, vive:FILE or bvh:FILE"
DURATION_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
MAX_DURATION_S = 365 * 86400.0  # a join token for over a year is a typo

# argparse prefixes "argument --fps: "; our own messages read on from the option's name
_OWN_MESSAGE = ("must ", "is ", "names ", "has ")


class Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows each option's default, but not when there is nothing to say: no
    default (None), a switch (True/False), or help text that gives it already."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (not action.option_strings or default is None or default is argparse.SUPPRESS
                or isinstance(default, bool) or "default" in text):
            return text
        return text + " (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An ArgumentParser (its subcommands too) with ``Formatter`` help, whose errors are
    one line: the command, the option and what is wrong, and where to read more."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", Formatter)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        # as Python 3.13 does: "-1.5,0" (--offset) is a value, not an unknown option
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str) -> NoReturn:
        found = re.fullmatch(r"argument (\S+): (.*)", message, re.DOTALL)
        if found is not None:
            option, why = found.groups()
            message = f"{option} {why}" if why.startswith(_OWN_MESSAGE) else f"{option}: {why}"
        message = " ".join(message.split())  # one line, whatever argparse wrapped
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def subparsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """Every subcommand's parser under ``parser``, nested ones too (bench solver ...)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases: once each
                yield child
                yield from subparsers(child)


# --------------------------------------------------------------------------- numbers
def _number(text: str, kind: type[int] | type[float]) -> float:
    try:
        value = kind(text)
    except ValueError:
        word = "a whole number" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"must be {word}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of 1 or more, got {text!r}")
    return value


def count(text: str) -> int:
    """A count that may be zero (players, spectators)."""
    value = int(_number(text, int))
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a whole number of 0 or more, got {text!r}")
    return value


def positive_float(text: str) -> float:
    value = _number(text, float)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    value = _number(text, float)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f"must be a number of 0 or more, got {text!r}")
    return value


def fraction(text: str) -> float:
    """A weight in [0, 1): 1 would never let a new value in."""
    value = _number(text, float)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be at least 0 and below 1, got {text!r}")
    return value


def rate_hz(text: str) -> float:
    value = _number(text, float)
    if not 0.0 < value <= MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(
            f"must be a rate above 0 and at most {MAX_RATE_HZ:g} per second, got {text!r}")
    return value


def port(text: str) -> int:
    value = int(_number(text, int))
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(
            f"must be a port number from 0 to 65535 (0: any free port), got {text!r}")
    return value


def size(text: str) -> tuple[int, int]:
    """WIDTHxHEIGHT in pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT, e.g. 1280x720, got {text!r}"
                                         ) from None
    if not (MIN_SIZE <= w <= MAX_SIZE and MIN_SIZE <= h <= MAX_SIZE):
        raise argparse.ArgumentTypeError(
            f"must be WIDTHxHEIGHT with each side {MIN_SIZE} to {MAX_SIZE}, got {text!r}")
    return w, h


def offset(text: str) -> tuple[float, float]:
    """X,Z in metres: a sideways shift of every pose."""
    try:
        x, z = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be two numbers X,Z in metres, e.g. 1.5,0, got {text!r}") from None
    if not all(math.isfinite(v) and abs(v) <= MAX_OFFSET_M for v in (x, z)):
        raise argparse.ArgumentTypeError(
            f"must be two numbers X,Z each within +-{MAX_OFFSET_M:g} m, got {text!r}")
    return x, z


# --------------------------------------------------------------------------- session
def server_url(text: str) -> str:
    """A websocket URL: ws:// or wss://, a host, a port in 1..65535 if given; or several,
    comma-separated (the processes of one service, tried in turn)."""
    urls = [u.strip() for u in text.split(",")]
    if len(urls) > 1:
        if not all(urls):
            raise argparse.ArgumentTypeError(f"has an empty URL in its list: {text!r}")
        if len({urlsplit(u).scheme for u in urls}) > 1:
            raise argparse.ArgumentTypeError(f"mixes ws:// and wss:// URLs: {text!r}")
        return ",".join(server_url(u) for u in urls)
    parts = urlsplit(text)
    if parts.scheme not in ("ws", "wss"):
        raise argparse.ArgumentTypeError(
            f"must be a websocket URL such as ws://HOST:8765 (or wss://), got {text!r}")
    if not parts.hostname:
        raise argparse.ArgumentTypeError(f"has no host name: expected ws://HOST:PORT, "
                                         f"got {text!r}")
    try:
        number = parts.port
    except ValueError:
        number = 0
    if number == 0 or (number is None and parts.netloc.endswith(":")):
        raise argparse.ArgumentTypeError(
            f"must have a port number from 1 to 65535, got {text!r}")
    return text


def room(text: str) -> str:
    try:
        from posecast.protocol.validation import check_room_name

        return check_room_name(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def display_name(text: str) -> str:
    if not (1 <= len(text) <= MAX_NAME_CHARS and text.isprintable()):
        raise argparse.ArgumentTypeError(
            f"must be 1 to {MAX_NAME_CHARS} printable characters, got {text[:80]!r}")
    return text


def token(text: str) -> str:
    if not 1 <= len(text) <= MAX_TOKEN_CHARS:
        raise argparse.ArgumentTypeError(
            f"must be 1 to {MAX_TOKEN_CHARS} characters, got {len(text)}")
    return text


def duration(text: str) -> float:
    """Seconds from 90s, 15m, 2h, 7d or bare seconds (3600)."""
    number, unit = (text[:-1], text[-1]) if text[-1:] in DURATION_UNITS else (text, "s")
    try:
        value = float(number) * DURATION_UNITS[unit]
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or not number.strip():
        raise argparse.ArgumentTypeError(
            f"must be a duration such as 90s, 15m, 2h, 7d or seconds (3600), got {text!r}")
    if not 0.0 < value <= MAX_DURATION_S:
        raise argparse.ArgumentTypeError(
            f"must be above 0 and at most 365d, got {text!r}")
    return value


def network(text: str) -> NetworkSpec:
    """An emulated link for demo --network: 40ms+-10ms[,stall=200ms/5s][,seed=N]."""
    try:
        from posecast.client.bench.network import parse_network_spec

        return parse_network_spec(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


# --------------------------------------------------------------------------- files
def existing_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        why = "is a folder, not a file" if path.is_dir() else "no such file"
        raise argparse.ArgumentTypeError(f"{why}: {text!r}")
    return path


def devices(text: str) -> tuple[str, ...]:
    """A tracker set (``solver.tracking.devices.parse_devices``)."""
    try:
        return parse_devices(text)
    except ValueError as err:  # "--devices 'x': expected ..." -> "expected ..."
        raise argparse.ArgumentTypeError(str(err).split(": ", 1)[1]) from None


def dropouts(text: str) -> DropoutSpec:
    """Simulated tracking losses (``solver.tracking.dropouts.parse_dropouts``)."""
    try:
        from posecast.solver.tracking.dropouts import parse_dropouts

        return parse_dropouts(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).split(": ", 1)[1]) from None


def ca_file(text: str) -> Path:
    """PEM CA certificates that a wss:// server's certificate must chain to."""
    from posecast.client.session.tls import CAFileError, client_tls_context

    path = existing_file(text)
    try:
        client_tls_context(path)
    except CAFileError as err:
        raise argparse.ArgumentTypeError(f"{err.why}: {text!r}") from None
    return path


def out_dir(text: str) -> Path:
    """A folder to write into: made if missing, but never a file's name."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"must be a folder, but {text!r} is a file")
    return path


def out_file(text: str) -> Path:
    """A file to write: in a folder that exists, and not a folder itself."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"must be a file name, but {text!r} is a folder")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"names a folder that does not exist: {text!r}")
    return path


def new_file(text: str) -> Path:
    """A file to make: ``out_file``, and not one that exists (recordings are never
    written over)."""
    path = out_file(text)
    if path.exists():
        raise argparse.ArgumentTypeError(f"{text!r} exists; recordings are never written "
                                         "over: choose another name or remove it")
    return path


def vmc_target(text: str) -> tuple[str, int]:
    """A VMC receiver: HOST:PORT, HOST (port 39539) or [IPv6]:PORT."""
    from posecast.client.interop.vmc import VmcError, check_target, parse_target

    try:
        host, port = parse_target(text)
        check_target(host, port)
    except VmcError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return host, port


def source(text: str) -> str:
    """openvr, or vive:FILE / bvh:FILE naming a file that exists."""
    kind, sep, path = text.partition(":")  # only the first colon: "vive:C:\\rec.csv"
    if kind == "openvr" and not sep:
        return text
    if kind not in ("vive", "bvh") or not path:
        raise argparse.ArgumentTypeError(f"must be {SOURCE_FORMS}, got {text!r}")
    if not Path(path).is_file():
        raise argparse.ArgumentTypeError(f"no such file: {path!r}")
    return text


def box(text: str) -> tuple[int, int, int, int]:
    """A box in a video frame for latency-video: X,Y,W,H pixels, (X, Y) its top-left."""
    parts = text.split(",")
    try:
        x, y, w, h = (int(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be X,Y,W,H in whole pixels (top-left corner, width, height), "
            f"got {text!r}") from None
    if x < 0 or y < 0 or w < 1 or h < 1:
        raise argparse.ArgumentTypeError(
            f"must have X, Y of 0 or more and W, H of 1 or more, got {text!r}")
    return x, y, w, h
