"""The `posecast` command: parses arguments and calls library functions (thin on purpose,
so that tests call the same functions)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from solver.ik import DEFAULT_SOLVER, SOLVERS, SolverOptions


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

    bench = sub.add_parser("bench", help="measure speed")
    bsub = bench.add_subparsers(dest="bench", required=True)
    bs = bsub.add_parser("solver", help="microseconds per avatar-frame at several batch sizes")
    bs.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER)
    bs.add_argument("--avatars", type=_positive_ints, default=[1, 10, 100])
    bs.add_argument("--max-iterations", type=int, default=None)
    bs.add_argument("--seconds", type=float, default=2.0, help="time spent per batch size")
    bs.add_argument("--json", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "eval":
        from client.eval_command import run_eval

        return run_eval(args.files, args.solver, args.max_iterations, args.calibration,
                        args.smoothing, args.json)
    if args.command == "bench" and args.bench == "solver":
        from client.bench import bench_solver, format_solver_table

        result = bench_solver(args.solver, args.avatars,
                              SolverOptions(max_iterations=args.max_iterations), args.seconds)
        print(json.dumps(result) if args.json else format_solver_table(result))
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
