"""What the command modules share: one-line failures and usage errors, and words for a
lost session."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

if TYPE_CHECKING:

    from posecast.client.session.connection import SessionError


def fail(command: str, message: object) -> int:
    print(f"posecast {command}: {message}", file=sys.stderr)
    return 1


def session_words(err: SessionError) -> str:
    """'cannot reach URL: why' when no websocket opened; else the session's own line
    (the server's reason when it refused the join)."""
    return str(err) if err.reached else f"cannot reach {err.url}: {err.reason}"


def usage(command: str, message: str) -> int:
    """A bad command line found after parsing: one line, as argparse's, status 2."""
    print(f"posecast {command}: {message} (see posecast {command} --help)", file=sys.stderr)
    return 2


def cafile_without_tls(command: str, args: argparse.Namespace) -> int | None:
    """Status 2 if --cafile came with a ws:// URL, where it would silently do nothing."""
    if args.cafile is None or urlsplit(args.server).scheme == "wss":
        return None
    print(f"posecast {command}: --cafile is for wss:// servers, but --server is "
          f"{args.server!r} (see posecast {command} --help)", file=sys.stderr)
    return 2
