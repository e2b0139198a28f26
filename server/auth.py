"""Join tokens: who may join which room, as what, until when.

A server with a secret accepts a Hello only with a token signed with that secret for
the Hello's room and role (``JoinTokens.verify``). Tokens are JWTs (HS256) with the
claims ``room``, ``role``, ``exp``, ``iat`` and optionally ``name`` (the one display name
it admits): ``posecast token`` mints them, and so can a host's web site with any JWT
library. Each refusal is a ``TokenError`` whose text is one line naming the reason.

The secret comes from a file (``--secret-file``) or the environment (POSECAST_SECRET);
a secret under MIN_SECRET_BYTES is refused, as HS256 needs a key as long as its hash.
No sockets here: the server (``server.app``) asks, this module answers.
"""

from __future__ import annotations

import ipaddress
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, cast

import jwt

from posecast.protocol.validation import MAX_TOKEN_CHARS, check_room_name

Role = Literal["player", "spectator"]
ROLES: tuple[Role, ...] = ("player", "spectator")
ALGORITHM = "HS256"
SECRET_ENV = "POSECAST_SECRET"
MIN_SECRET_BYTES = 32  # HS256's own hash size: a shorter key is easier to guess than to steal
LEEWAY_S = 5.0  # clocks of the minting host and the server may disagree by this much
MAX_TTL_S = 365 * 86400.0  # a token for longer than a year is a typo (and nothing revokes it)


class SecretError(ValueError):
    """The secret is missing, unreadable or too short; ``str()`` is one line."""


class TokenError(ValueError):
    """A join token does not admit this Hello; ``str()`` is the reason, one line."""


@dataclass(frozen=True)
class Grant:
    """What a valid token admits."""

    room: str
    role: Role
    expires: float  # unix time
    name: str | None = None  # the only display name it admits, if it names one


# --------------------------------------------------------------------------- the secret
def check_secret(secret: bytes, where: str) -> bytes:
    """``secret`` if it is long enough, else SecretError naming ``where`` it came from."""
    if not secret:
        raise SecretError(f"{where} is empty: it must hold the secret "
                          f"({MIN_SECRET_BYTES} bytes or more)")
    if len(secret) < MIN_SECRET_BYTES:
        raise SecretError(f"the secret in {where} is {len(secret)} bytes; use "
                          f"{MIN_SECRET_BYTES} or more (e.g. openssl rand -hex 32 > FILE)")
    return secret


def read_secret_file(path: Path) -> bytes:
    """The secret in ``path`` without its trailing newline (``echo`` adds one)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SecretError(f"no such secret file: {str(path)!r}") from None
    except IsADirectoryError:
        raise SecretError(f"the secret file {str(path)!r} is a folder") from None
    except OSError as err:
        raise SecretError(f"cannot read the secret file {str(path)!r}: "
                          f"{err.strerror or err}") from None
    return check_secret(data.rstrip(b"\r\n"), repr(str(path)))


def load_secret(path: Path | None, environ: Mapping[str, str]) -> bytes | None:
    """The secret from ``path`` if given, else from POSECAST_SECRET, else None (open)."""
    if path is not None:
        return read_secret_file(path)
    value = environ.get(SECRET_ENV)
    if value is None:
        return None
    return check_secret(value.encode(), SECRET_ENV)


# --------------------------------------------------------------------------- tokens
class JoinTokens:
    """Mints and verifies join tokens with one secret; ``clock`` is unix time."""

    def __init__(self, secret: bytes, leeway_s: float = LEEWAY_S,
                 clock: Callable[[], float] = time.time) -> None:
        self._secret = check_secret(secret, "the secret")
        self.leeway_s = leeway_s
        self.clock = clock

    def mint(self, room: str, role: Role, ttl_s: float, name: str | None = None,
             now: float | None = None) -> str:
        """A token for ``role`` in ``room``, valid ``ttl_s`` seconds from ``now``."""
        check_room_name(room)
        if role not in ROLES:
            raise ValueError(f"role must be player or spectator, got {role!r}")
        if not 0 < ttl_s <= MAX_TTL_S:
            raise ValueError(f"ttl must be above 0 and at most {MAX_TTL_S:g} s, got {ttl_s!r}")
        t = self.clock() if now is None else now
        claims: dict[str, Any] = {"room": room, "role": role, "iat": math.floor(t),
                                  "exp": math.floor(t + ttl_s)}
        if name is not None:
            claims["name"] = name
        token = jwt.encode(claims, self._secret, algorithm=ALGORITHM)
        if len(token) > MAX_TOKEN_CHARS:  # only a name of many escaped characters gets here
            raise ValueError(f"the token would be {len(token)} characters, over the "
                             f"protocol's {MAX_TOKEN_CHARS}: use a shorter name")
        return token

    def verify(self, token: str | None, room: str, role: str, name: str | None = None,
               now: float | None = None) -> Grant:
        """The Grant of ``token`` if it admits ``role`` in ``room`` (as ``name``, if
        the token names one) now; else TokenError with the reason."""
        if token is None:
            raise TokenError("this server needs a join token (hello.token): ask the host "
                               "for one (posecast token) and pass it with --token")
        try:
            claims = jwt.decode(token, self._secret, algorithms=[ALGORITHM],
                                options={"verify_exp": False, "verify_iat": False,
                                         "verify_nbf": False})
        except jwt.InvalidSignatureError:
            raise TokenError("the join token is not signed with this server's secret"
                               ) from None
        except jwt.InvalidAlgorithmError:
            raise TokenError(f"the join token is not signed with {ALGORITHM}") from None
        except jwt.InvalidTokenError:
            raise TokenError("the join token is malformed: not a JWT (a token from "
                               "posecast token has three dot-separated parts)") from None
        grant = _grant(claims)
        t = self.clock() if now is None else now
        if t > grant.expires + self.leeway_s:
            raise TokenError(f"the join token expired at {_utc(grant.expires)} "
                               f"({_duration(t - grant.expires)} ago)")
        issued = claims["iat"]
        if issued > t + self.leeway_s:
            raise TokenError(f"the join token was issued at {_utc(issued)}, "
                               f"{_duration(issued - t)} ahead of this server's clock: "
                               "check the clocks")
        if grant.room != room:
            raise TokenError(f"the join token is for room {grant.room!r}, not {room!r}")
        # a player's token also admits them as a spectator of their room: a headset
        # (play --hmd) watches the room it plays in on a second connection
        if grant.role != role and not (grant.role == "player" and role == "spectator"):
            raise TokenError(f"the join token is for a {grant.role}, not a {role}")
        if grant.name is not None and name is not None and grant.name != name:
            raise TokenError(f"the join token is for the name {grant.name!r}, not {name!r}")
        return grant


def is_loopback(host: str | None) -> bool:
    """True if ``host`` (a listening address) is reached only from this machine."""
    if host in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host or "").is_loopback
    except ValueError:  # "" and None listen everywhere; a name may resolve anywhere
        return False


def _grant(claims: dict[str, Any]) -> Grant:
    """The claims, checked: signed by us, but perhaps by a web site's own code."""
    for claim in ("room", "role", "exp", "iat"):
        if claim not in claims:
            raise TokenError(f"the join token has no {claim!r} claim")
    room, role, name = claims["room"], claims["role"], claims.get("name")
    if not isinstance(room, str):
        raise TokenError(f"the join token's 'room' claim is not text: {room!r:.40}")
    if role not in ROLES:
        raise TokenError(f"the join token's 'role' claim must be player or spectator, "
                           f"got {role!r:.40}")
    for claim in ("exp", "iat"):
        value = claims[claim]
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value):
            raise TokenError(f"the join token's {claim!r} claim is not a unix time: "
                               f"{value!r:.40}")
    if name is not None and not isinstance(name, str):
        raise TokenError(f"the join token's 'name' claim is not text: {name!r:.40}")
    return Grant(room, cast(Role, role), float(claims["exp"]), name)


def _utc(t: float) -> str:
    try:
        return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, OSError, ValueError):  # a year beyond 9999 or before 1
        return f"unix time {t:g}"


def _duration(seconds: float) -> str:
    """Seconds in the unit a person reads: 12 s, 3 min, 2.5 h, 4.0 d."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} d"
