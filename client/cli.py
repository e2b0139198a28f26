"""The `posecast` command: parses arguments and calls library functions (thin on purpose,
so that tests call the same functions)."""

from __future__ import annotations

import argparse
import atexit
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from posecast.client.jit import CompileNotice, warm_kernels
from posecast.solver.ik import DEFAULT_SOLVER, SOLVERS, SolverOptions

if TYPE_CHECKING:
    from posecast.client.player import Player, PlayerStats


def _positive_ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}") from None
    if not values or any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive numbers, got {text!r}")
    return values


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="posecast", description=(
        "Stream full-body VR poses: calibrate, solve and score avatars from Vive trackers."))
    sub = p.add_subparsers(dest="command", required=True)

    ev = sub.add_parser("eval", help="reconstruct recordings (Vive .csv or .bvh) and score them")
    ev.add_argument("files", nargs="*", type=Path,
                    help="recordings; none: the built-in CMU motion clip")
    ev.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER)
    ev.add_argument("--max-iterations", type=_positive_ints, default=None,
                    help="iteration limit per chain; several (5,10,30) compare them")
    ev.add_argument("--calibration", choices=("fit", "uniform"), default="fit")
    ev.add_argument("--smoothing", type=float, default=0.0,
                    help="SLERP smoothing, weight of the previous frame in [0, 1)")
    ev.add_argument("--json", action="store_true", help="print one JSON document")

    sub.add_parser("warm", help="compile the solver kernels now, into numba's on-disk cache "
                   "(make setup runs it; other commands compile what they lack on first use)")

    sv = sub.add_parser("serve", help="host sessions: the websockets server")
    sv.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (0.0.0.0 for every interface)")
    sv.add_argument("--port", type=int, default=8765)
    sv.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER)
    sv.add_argument("--busy-poll", action="store_true",
                    help="never sleep: poll, and keep the frame path warm between bursts "
                         "(lower latency; takes a whole core, give it one)")
    sv.add_argument("--no-helper", dest="helper", action="store_false",
                    help="with --busy-poll on some cores only (taskset), a helper thread "
                         "spins on the others and takes part of each batch; this turns "
                         "it off")

    pl = sub.add_parser("play", help="join a session as a tracked player")
    pl.add_argument("--server", required=True, help="ws://host:port")
    pl.add_argument("--room", required=True)
    pl.add_argument("--source", default="openvr",
                    help="openvr | vive:FILE | bvh:FILE (default: openvr)")
    pl.add_argument("--name", default="player")
    pl.add_argument("--token", default=None,
                    help="a secret of yours: reconnecting with it keeps your avatar")
    pl.add_argument("--devices", type=Path, default=None,
                    help="TOML file mapping tracker serial numbers to roles (openvr)")
    pl.add_argument("--loop", action="store_true", help="replay a recording forever")
    pl.add_argument("--seconds", type=float, default=None)
    pl.add_argument("--calibrate-in", type=float, default=None,
                    help="seconds to get into the T-pose before calibrating "
                         "(default: 3 for openvr, 0 for recordings); press Enter to "
                         "recalibrate while playing")

    vw = sub.add_parser("view", help="watch a room: skinned avatars in a window, or to PNGs")
    vw.add_argument("--server", required=True, help="ws://host:port")
    vw.add_argument("--room", required=True)
    vw.add_argument("--headless", action="store_true",
                    help="no window: render through EGL to PNG files in --out")
    vw.add_argument("--frames", type=int, default=None,
                    help="stop after this many frames (headless default: 100)")
    vw.add_argument("--out", type=Path, default=Path("frames"), help="PNG folder (headless)")
    vw.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    vw.add_argument("--fps", type=float, default=30.0)
    vw.add_argument("--mode", choices=("interpolate", "zero-buffer"), default="interpolate",
                    help="interpolate: render slightly behind, SLERP between frames; "
                         "zero-buffer: the newest frame, least latency")
    vw.add_argument("--view", choices=("orbit", "first-person", "mirror"), default="orbit")
    vw.add_argument("--screenshot", type=Path, default=None,
                    help="window: save the last frame shown as a PNG")
    vw.add_argument("--max-rate", type=float, default=None,
                    help="ask the server for at most this many batches per second")

    dm = sub.add_parser("demo", help="a whole session on this machine, with latency table")
    dm.add_argument("--render", type=Path, default=None,
                    help="also run a headless viewer writing PNG frames to this folder")
    dm.add_argument("--render-mode", choices=("interpolate", "zero-buffer"),
                    default="interpolate", help="the viewer's snapshot mode (with --render)")
    dm.add_argument("--players", type=int, default=4)
    dm.add_argument("--spectators", type=int, default=2)
    dm.add_argument("--seconds", type=float, default=10.0)
    dm.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER)
    dm.add_argument("--no-busy-poll", dest="busy_poll", action="store_false",
                    help="the server sleeps between bursts (by default it busy-polls "
                         "when it has a core of its own)")
    dm.add_argument("--no-helper", dest="helper", action="store_false",
                    help="the server solves alone (by default, busy polling, a helper "
                         "thread spins on the clients' core and takes part of each batch)")
    dm.add_argument("--json", action="store_true")

    bench = sub.add_parser("bench", help="measure speed")
    bsub = bench.add_subparsers(dest="bench", required=True)
    bs = bsub.add_parser("solver", help="microseconds per avatar-frame at several batch sizes")
    bs.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER)
    bs.add_argument("--avatars", type=_positive_ints, default=[1, 10, 100])
    bs.add_argument("--max-iterations", type=int, default=None)
    bs.add_argument("--seconds", type=float, default=2.0, help="time spent per batch size")
    bs.add_argument("--json", action="store_true")
    bp = bsub.add_parser("protocol", help="wire sizes, quantization error, codec timings")
    bp.add_argument("--json", action="store_true")
    br = bsub.add_parser("render", help="ms per frame of the viewer (software GL here)")
    br.add_argument("--avatars", type=int, default=16)
    br.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    br.add_argument("--frames", type=int, default=120)
    br.add_argument("--out", type=Path, default=None, help="save the last frame as PNG")
    br.add_argument("--json", action="store_true")
    bv = bsub.add_parser("server", help="players and spectators one server sustains")
    bv.add_argument("--counts", type=_positive_ints, default=[4, 8, 16, 24, 32, 48, 64],
                    help="players (= spectators) to try, in order")
    bv.add_argument("--seconds", type=float, default=4.0, help="length of each step")
    bv.add_argument("--no-helper", dest="helper", action="store_false",
                    help="the server solves alone (see demo --no-helper)")
    bv.add_argument("--json", action="store_true")
    bu = bsub.add_parser("startup", help="seconds the first commands take after set-up "
                         "(--version, serve until listening, eval of the built-in clip)")
    bu.add_argument("--runs", type=_positive_ints, default=[5],
                    help="fresh processes per command (default: 5)")
    bu.add_argument("--json", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    notice = CompileNotice().install()  # a command that must compile kernels says so
    atexit.register(notice.close)
    if args.command == "warm":
        print(f"kernels ready in {warm_kernels(notice):.1f} s")
        return 0
    if args.command in ("demo", "bench"):  # before their processes start, each would compile
        warm_kernels(notice)
    if args.command == "eval":
        from posecast.client.eval_command import run_eval

        return run_eval(args.files, args.solver, args.max_iterations, args.calibration,
                        args.smoothing, args.json)
    if args.command == "serve":
        return _serve(args)
    if args.command == "play":
        return _play(args)
    if args.command == "demo":
        return _demo(args)
    if args.command == "view":
        return _view(args)
    if args.command == "bench" and args.bench == "solver":
        from posecast.client.bench import bench_solver, format_solver_table

        result = bench_solver(args.solver, args.avatars,
                              SolverOptions(max_iterations=args.max_iterations), args.seconds)
        print(json.dumps(result) if args.json else format_solver_table(result))
        return 0
    if args.command == "bench" and args.bench == "protocol":
        from posecast.client.bench_protocol import bench_protocol, format_protocol_table

        doc = bench_protocol()
        print(json.dumps(doc) if args.json else format_protocol_table(doc))
        return 0
    if args.command == "bench" and args.bench == "render":
        from posecast.client.viewer.bench import bench_render, format_render_table

        width, height = _size(args.size)
        result = bench_render(args.avatars, width, height, args.frames, out=args.out)
        print(json.dumps(result) if args.json else format_render_table(result))
        return 0
    if args.command == "bench" and args.bench == "server":
        from posecast.client.bench_server import bench_server, format_server_table

        result = bench_server(args.counts, args.seconds,
                              helper=None if args.helper else False)
        print(json.dumps(result) if args.json else format_server_table(result))
        return 0
    if args.command == "bench" and args.bench == "startup":
        from posecast.client.bench_startup import bench_startup, format_startup_table

        doc = bench_startup(args.runs[0])
        print(json.dumps(doc) if args.json else format_startup_table(doc))
        return 0
    return 2


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"posecast: --size expects WIDTHxHEIGHT, got {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise SystemExit(f"posecast: --size {text!r} is out of range (16..8192)")
    return w, h


def _view(args: argparse.Namespace) -> int:
    import asyncio

    from posecast.client.connection import SessionError
    from posecast.client.viewer import (
        GLUnavailableError,
        Mode,
        NoDisplayError,
        ViewerStats,
        ViewMode,
        run_headless_viewer,
        run_window_viewer,
    )

    width, height = _size(args.size)
    mode, view = Mode(args.mode), ViewMode(args.view)
    stats: ViewerStats
    try:
        if args.headless:
            stats = asyncio.run(run_headless_viewer(
                args.server, args.room, args.frames or 100, args.out, width, height,
                interval_ms=1000.0 / args.fps, mode=mode, view=view,
                max_rate_hz=args.max_rate))
        else:
            stats = asyncio.run(run_window_viewer(
                args.server, args.room, width, height, fps=args.fps, mode=mode, view=view,
                max_rate_hz=args.max_rate, frames=args.frames, screenshot=args.screenshot))
    except (NoDisplayError, GLUnavailableError, SessionError) as err:
        return _fail("view", err)
    except KeyboardInterrupt:
        return 130
    print(json.dumps(stats.as_json()))
    return 0


def _fail(command: str, message: object) -> int:
    print(f"posecast {command}: {message}", file=sys.stderr)
    return 1


def _serve(args: argparse.Namespace) -> int:
    import asyncio
    import logging

    from posecast.server.app import Session, install_fast_loop, run_server

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    install_fast_loop()
    session = Session(solver=args.solver, busy=args.busy_poll,
                      helper=None if args.helper else False)
    try:
        asyncio.run(run_server(args.host, args.port, session, handle_signals=True))
    except OSError as err:
        return _fail("serve", f"cannot listen on {args.host}:{args.port}: {err.strerror}")
    print(json.dumps(session.metrics.as_json()))
    return 0


def _play(args: argparse.Namespace) -> int:
    import asyncio

    from posecast.client.connection import SessionError
    from posecast.client.player import Player
    from posecast.client.sources import open_source
    from posecast.client.sources.base import SourceError
    from posecast.solver.readers.errors import FormatError

    try:
        source = open_source(args.source, args.devices, loop=args.loop)
    except (SourceError, FormatError) as err:
        return _fail("play", err)
    delay = args.calibrate_in if args.calibrate_in is not None else (
        3.0 if args.source == "openvr" else 0.0)
    player = Player(args.server, args.room, args.name, source, token=args.token)
    try:
        stats = asyncio.run(_play_live(player, delay, args.seconds))
    except SessionError as err:
        return _fail("play", err)
    except KeyboardInterrupt:
        return 130
    finally:
        source.close()
    print(f"sent {stats.frames_sent} frames in {stats.seconds:.1f} s"
          + (f"; server errors: {dict(stats.errors)}" if stats.errors else ""))
    return 0


async def _play_live(player: Player, delay: float, seconds: float | None) -> PlayerStats:
    """Count the player into the T-pose, then stream; Enter on a terminal recalibrates."""
    import asyncio

    for left in range(math.ceil(delay), 0, -1):
        print(f"stand in a T-pose, arms out sideways: calibrating in {left} s", flush=True)
        await asyncio.sleep(min(1.0, delay - (left - 1)))
    loop = asyncio.get_running_loop()
    interactive = sys.stdin.isatty()
    if interactive:
        def recalibrate() -> None:
            sys.stdin.readline()
            print("recalibrating: hold the T-pose", flush=True)
            player.recalibrate()
        loop.add_reader(sys.stdin.fileno(), recalibrate)
    try:
        return await player.run(seconds)
    finally:
        if interactive:
            loop.remove_reader(sys.stdin.fileno())


def _demo(args: argparse.Namespace) -> int:
    from posecast.client.demo import run_demo
    from posecast.client.latency import format_latency_table

    if args.players < 0 or args.spectators < 0 or args.seconds <= 0:
        return _fail("demo", "players and spectators must be >= 0 and seconds > 0")
    result = run_demo(args.players, args.spectators, args.seconds, solver=args.solver,
                      render=args.render, render_mode=args.render_mode,
                      busy=None if args.busy_poll else False,
                      helper=None if args.helper else False)
    if args.json:
        print(json.dumps(result.as_json()))
    else:
        print(f"{result.players} players, {result.spectators} spectators, "
              f"{result.seconds:g} s: sent {result.frames_sent}, solved "
              f"{result.frames_solved}, delivered {result.frames_delivered} avatar-frames "
              f"(dropped {result.frames_dropped})")
        print(format_latency_table(result.latency.summary(), result.latency.counts()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
