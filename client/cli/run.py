"""The `posecast` command: parses arguments and calls library functions (thin on purpose,
so that tests call the same functions). ``main`` dispatches to one module per command;
each imports its libraries when it runs (the parser needs none)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from posecast.client.cli import arguments as arg
from posecast.client.cli.common import cafile_without_tls, fail, session_words
from posecast.client.cli.parser import _parser
from posecast.solver.tracking.devices import DEFAULT_SET, PRESETS

if TYPE_CHECKING:
    from posecast.client.jit import CompileNotice


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if getattr(args, "config", None) is not None:  # the file's values become defaults
        args = _with_config(parser, args, argv)
    if args.command is None or (args.command == "bench" and args.bench is None):
        args.show_help()
        return 0
    _configure_logging(args.command, args.log_level)
    from posecast.client.jit import CompileNotice  # numba: only once a command runs

    notice = CompileNotice().install()  # a command that must compile kernels says so
    try:
        return _command(args, notice)
    except KeyboardInterrupt:  # Ctrl-C where no command handles it (e.g. while compiling)
        print(f"posecast {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:  # process-wide: tests call main() many times, each with its own stderr
        notice.close()
        notice.uninstall()


def _with_config(parser: argparse.ArgumentParser, args: argparse.Namespace,
                 argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line parsed again over ``--config``'s values; a bad file is one line
    naming its line and key, exit 2, as a bad flag."""
    from posecast.client.cli.config_file import ConfigError, apply_config

    command = next(child for child in arg.subparsers(parser)
                   if child.prog == f"{parser.prog} {args.command}")
    try:
        apply_config(parser, command, args.config)
    except ConfigError as err:
        command.error(f"--config {err}")
    return parser.parse_args(argv)


def _configure_logging(command: str, level_name: str | None) -> None:
    """Diagnostics go through logging to stderr: from info up for serve (its log of who
    joins and leaves), from warning up for the others, whose results go to stdout."""
    level = getattr(logging, (level_name or ("info" if command == "serve" else "warning"))
                    .upper())
    logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s"
                        if command == "serve" else
                        f"posecast {command}: %(levelname)s: %(message)s")
    logging.getLogger().setLevel(level)
    # websockets' own "connection open/closed" lines name nobody: ours do (server.app)
    logging.getLogger("websockets").setLevel(logging.DEBUG if level <= logging.DEBUG
                                             else logging.WARNING)
    logging.getLogger("numba").setLevel(logging.WARNING)  # its debug output is the compiler's


def _eval_flags_given(args: argparse.Namespace, *more: tuple[str, bool]) -> list[str]:
    """The options of eval given that the cross-validations do not take."""
    return [flag for flag, on in (
        ("--delay-ms", args.delay_ms is not None), ("--predict", args.predict),
        ("--map", args.map is not None), ("--dropouts", args.dropouts is not None),
        ("--naive", args.naive),
        ("--devices", set(args.devices) != set(PRESETS[DEFAULT_SET])), *more) if on]


def _command(args: argparse.Namespace, notice: CompileNotice) -> int:
    from posecast.client.jit import warm_kernels

    if args.command == "warm":
        workers = min(2, os.cpu_count() or 1)  # the slowest step takes most of the time
        print(f"kernels ready in {warm_kernels(notice, workers):.1f} s")
        return 0
    if args.command in ("demo", "bench"):  # before their processes start, each would compile
        warm_kernels(notice)
    if args.command == "eval" and args.cross_validate_body:
        from posecast.client.cli.crossval_body import run_cross_validate_body

        return run_cross_validate_body(
            args.files, args.solver, args.max_iterations, args.json,
            given=_eval_flags_given(args, ("--smoothing", args.smoothing != 0.0),
                                    ("--cross-validate", args.cross_validate)))
    if args.command == "eval" and args.cross_validate:
        from posecast.client.cli.crossval import run_cross_validate

        return run_cross_validate(args.files, args.solver, args.max_iterations,
                                  args.calibration, args.smoothing, args.json,
                                  given=_eval_flags_given(args))
    if args.command == "eval":
        from posecast.client.cli.eval import run_eval

        return run_eval(args.files, args.solver, args.max_iterations, args.calibration,
                        args.smoothing, args.json, delay_ms=args.delay_ms,
                        predict=args.predict, predictor=args.predictor,
                        predict_on=args.predict_on, joint_map=args.map,
                        devices=args.devices, dropouts=args.dropouts, naive=args.naive)
    if args.command == "token":
        from posecast.client.cli.serve import _token

        return _token(args)
    if args.command == "latency-video":
        from posecast.client.measure.latency_video import run_latency_video

        return run_latency_video(args.video, args.tracker_box, args.avatar_box,
                                 tracker=args.tracker, select=args.select, fps=args.fps,
                                 plot=args.plot, as_json=args.json)
    if args.command == "record":
        from posecast.client.cli.record import run_record
        from posecast.client.session.connection import SessionError

        if (status := cafile_without_tls("record", args)) is not None:
            return status
        try:
            return run_record(args.server, args.room, args.out, args.seconds, args.token,
                              args.cafile, args.reconnect)
        except SessionError as err:
            return fail("record", session_words(err))
        except OSError as err:  # the file (made since the arguments were checked)
            return fail("record", f"{args.out}: {err.strerror or err}")
    if args.command == "replay":
        from posecast.client.cli.record import run_replay
        from posecast.client.session.connection import SessionError

        if (status := cafile_without_tls("replay", args)) is not None:
            return status
        try:
            return run_replay(args.file, args.server, args.room, args.speed, args.loop,
                              args.token, args.cafile)
        except SessionError as err:
            return fail("replay", session_words(err))
    if args.command == "export":
        from posecast.client.cli.export import run_export

        return run_export(args.file, args.bvh, args.fps)
    if args.command == "vmc":
        from posecast.client.cli.vmc import run_vmc_command
        from posecast.client.interop.vmc import VmcError
        from posecast.client.session.connection import SessionError

        if (status := cafile_without_tls("vmc", args)) is not None:
            return status
        host, port = args.to
        try:
            return run_vmc_command(args.server, args.room, args.avatar, host, port,
                                   args.seconds, args.rate, args.token, args.cafile)
        except SessionError as err:
            return fail("vmc", session_words(err))
        except VmcError as err:
            return fail("vmc", err)
    if args.command == "serve":
        from posecast.client.cli.serve import _serve

        return _serve(args)
    if args.command == "play":
        from posecast.client.cli.play import _play

        return _play(args)
    if args.command == "demo":
        from posecast.client.cli.demo import _demo

        return _demo(args)
    if args.command == "view":
        from posecast.client.cli.view import _view

        return _view(args)
    if args.command == "bench" and args.bench == "solver":
        from posecast.client.bench.solver import bench_solver, format_solver_table
        from posecast.solver.ik import SolverOptions

        result = bench_solver(args.solver, args.avatars,
                              SolverOptions(max_iterations=args.max_iterations), args.seconds,
                              args.devices)
        print(json.dumps(result) if args.json else format_solver_table(result))
        return 0
    if args.command == "bench" and args.bench == "protocol":
        from posecast.client.bench.protocol import bench_protocol, format_protocol_table

        doc = bench_protocol()
        print(json.dumps(doc) if args.json else format_protocol_table(doc))
        return 0
    if args.command == "bench" and args.bench == "render":
        from posecast.client.viewer.bench import bench_render, format_render_table

        width, height = args.size
        result = bench_render(args.avatars, width, height, args.frames, out=args.out)
        print(json.dumps(result) if args.json else format_render_table(result))
        return 0
    if args.command == "bench" and args.bench == "server":
        from posecast.client.bench.server import bench_server, format_server_table

        result = bench_server(args.counts, args.seconds,
                              helper=None if args.helper else False)
        print(json.dumps(result) if args.json else format_server_table(result))
        return 0
    if args.command == "bench" and args.bench == "soak":
        from posecast.client.bench.soak import bench_soak, format_soak_table, plot_soak

        doc = bench_soak(args.minutes, args.players, args.spectators, args.interval)
        if args.plot is not None:
            plot_soak(doc, args.plot)
        print(json.dumps(doc) if args.json else format_soak_table(doc))
        return 0
    if args.command == "bench" and args.bench == "prediction":
        from posecast.client.bench.prediction import (
            bench_prediction,
            format_prediction_table,
            main_files,
        )

        files = main_files(args.files)
        if files is None:
            return 2
        doc = bench_prediction(files)
        print(json.dumps(doc) if args.json else format_prediction_table(doc))
        return 0
    if args.command == "bench" and args.bench == "hostile":
        from posecast.client.bench.hostile import bench_hostile, format_hostile_table

        doc = bench_hostile(args.attack, args.seconds)
        print(json.dumps(doc) if args.json else format_hostile_table(doc))
        return 0
    if args.command == "bench" and args.bench == "fanout":
        return _bench_fanout(args)
    if args.command == "bench" and args.bench == "page":
        return _bench_page(args)
    if args.command == "bench" and args.bench == "headset":
        from posecast.client.bench.headset import bench_headset, format_headset_table, say
        from posecast.client.viewer.renderer import GLUnavailableError

        if any(f > 2.0 for f in args.scales):
            return fail("bench headset", "--scales: at most 2 (3024x3360 an eye)")
        try:
            doc = bench_headset(args.scales, args.frames, args.others, progress=say)
        except GLUnavailableError as err:
            return fail("bench headset", err)
        print(json.dumps(doc) if args.json else format_headset_table(doc))
        return 0
    if args.command == "bench" and args.bench == "startup":
        from posecast.client.bench.startup import bench_startup, format_startup_table

        doc = bench_startup(args.runs)
        print(json.dumps(doc) if args.json else format_startup_table(doc))
        return 0
    return 2


def _bench_fanout(args: argparse.Namespace) -> int:
    from posecast.client.bench.fanout import bench_fanout, format_fanout_table, format_step
    from posecast.client.bench.redis_process import RedisMissingError

    try:  # a line per step as it ends: a whole run takes minutes
        doc = bench_fanout(args.processes, args.players, args.start, args.seconds,
                           args.budget_ms, args.max, args.repeat,
                           progress=lambda step: print(format_step(step), file=sys.stderr,
                                                       flush=True))
    except RedisMissingError as err:
        return fail("bench fanout", err)
    except RuntimeError as err:  # spectators that could not join, a server that died
        return fail("bench fanout", err)
    print(json.dumps(doc) if args.json else format_fanout_table(doc))
    return 0


def _bench_page(args: argparse.Namespace) -> int:
    from posecast.client.bench.browser import BrowserMissingError
    from posecast.client.bench.page import bench_page, format_page_table

    try:  # a line per turn and mode as it ends: Chromium draws a few frames a second
        doc = bench_page(args.avatars, args.frames, args.turns,
                         progress=lambda line: print(line, file=sys.stderr, flush=True))
    except BrowserMissingError as err:
        return fail("bench page", err)
    except RuntimeError as err:  # a page that never drew its avatars, a server that died
        return fail("bench page", err)
    print(json.dumps(doc) if args.json else format_page_table(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
