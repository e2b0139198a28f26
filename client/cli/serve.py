"""`posecast serve` and `posecast token`: hosting sessions, and minting join tokens."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from posecast.client.cli.common import fail, usage
from posecast.server.limits import ServerLimits

if TYPE_CHECKING:
    import ssl

    from posecast.server.auth import JoinTokens


def _join_tokens(secret_file: Path | None) -> JoinTokens | None:
    """Tokens with the secret of --secret-file, else of $POSECAST_SECRET, else None;
    SecretError (one line) if that secret is unreadable or too short."""
    from posecast.server.auth import JoinTokens, load_secret

    secret = load_secret(secret_file, os.environ)
    return JoinTokens(secret) if secret is not None else None


def _token(args: argparse.Namespace) -> int:
    from posecast.server.auth import SECRET_ENV, SecretError

    try:
        tokens = _join_tokens(args.secret_file)
    except SecretError as err:
        return usage("token", str(err))
    if tokens is None:
        return usage("token", f"needs the server's secret: --secret-file FILE, or "
                      f"${SECRET_ENV}")
    try:
        print(tokens.mint(args.room, args.role, args.ttl, args.name))
    except ValueError as err:
        return usage("token", str(err))
    return 0


def _serve(args: argparse.Namespace) -> int:
    from posecast.server.app import Session
    from posecast.server.auth import SecretError
    from posecast.server.serving import install_fast_loop, run_server

    try:
        tokens = _join_tokens(args.secret_file)
    except SecretError as err:  # $POSECAST_SECRET too short (a file is checked on parsing)
        return usage("serve", str(err))

    try:
        limits = ServerLimits().with_text(args.limit)
    except ValueError as err:  # limits that do not go together (see _limit)
        print(f"posecast serve: {err} (--limit, or [limits] in --config; see posecast serve "
              "--help)", file=sys.stderr)
        raise SystemExit(2) from None  # a usage error, as argparse ends one
    try:  # before the solver warms up: a bad certificate is told at once
        tls = _server_tls(args)
    except ValueError as err:
        print(f"posecast serve: {err} (see posecast serve --help)", file=sys.stderr)
        return 2
    if args.public_url is not None and args.redis is None:
        return usage("serve", "--public-url is for --redis: where other processes send "
                               "this one's players")
    install_fast_loop()
    cluster = None
    if args.redis is not None:
        from posecast.server.cluster import Cluster
        cluster = Cluster(args.redis, args.public_url or "")
    session = Session(tokens=tokens, solver=args.solver, busy=args.busy_poll,
                      helper=None if args.helper else False,
                      limits=limits, cluster=cluster,
                      trusted_proxies=args.trusted_proxies or ())
    from posecast.server.cluster import ClusterError
    try:
        asyncio.run(run_server(args.host, args.port, session, handle_signals=True,
                               tls=tls, origins=args.origins))
    except ClusterError as err:
        return fail("serve", f"{err} (is redis-server running there?)")
    except OSError as err:
        return fail("serve", f"cannot listen on {args.host}:{args.port}: {err.strerror}")
    print(json.dumps(session.metrics.as_json()))
    return 0


def _server_tls(args: argparse.Namespace) -> ssl.SSLContext | None:
    """serve's TLS context from --certfile and --keyfile (None: neither); ValueError
    in one line (server.tls.TLSConfigError) if they cannot serve."""
    from posecast.server.tls import server_tls_context

    if args.certfile is None and args.keyfile is None:
        return None
    if args.certfile is None or args.keyfile is None:
        given, missing = (("--certfile", "--keyfile") if args.keyfile is None
                          else ("--keyfile", "--certfile"))
        raise ValueError(f"{given} needs {missing} too")
    return server_tls_context(args.certfile, args.keyfile)
