"""`posecast demo`: a server, players and spectators on this machine, and their figures."""

from __future__ import annotations

import argparse
import json
import sys

from posecast.server.limits import ServerLimits


def _demo(args: argparse.Namespace) -> int:
    from posecast.client.bench.browser import BrowserFailedError, BrowserMissingError
    from posecast.client.bench.demo import DemoError, run_demo
    from posecast.client.bench.redis_process import RedisMissingError
    from posecast.client.measure.latency import format_latency_table

    try:
        limits = ServerLimits().with_text(args.limit)
    except ValueError as err:  # limits that do not go together (see _limit)
        print(f"posecast demo: {err} (--limit)", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        result = run_demo(args.players, args.spectators, args.seconds, solver=args.solver,
                          render=args.render, render_mode=args.render_mode,
                          busy=None if args.busy_poll else False,
                          helper=None if args.helper else False, network=args.network,
                          limits=limits, servers=args.servers, devices=args.devices,
                          dropouts=args.dropouts, browser=args.browser)
    except RedisMissingError as err:
        print(f"posecast demo: --servers {args.servers}: {err}", file=sys.stderr)
        return 1
    except DemoError as err:  # e.g. a link whose stalls make the server refuse frames
        print(f"posecast demo: {err}", file=sys.stderr)
        return 1
    except (BrowserMissingError, BrowserFailedError) as err:
        print(f"posecast demo: --browser: {err}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result.as_json()))
    else:
        print(result.format_counts())
        print(format_latency_table(result.latency.summary(), result.latency.counts()))
        print(result.format_display_error())
    return 0

