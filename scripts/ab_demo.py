#!/usr/bin/env python3
"""Alternated A/B of `posecast demo` against an older commit, on this machine.

    python scripts/ab_demo.py --old 9c29c91~1 [--pairs 3] [--players 16] \
        [--spectators 16] [--seconds 20] [--json FILE] [--parts]

The older commit is checked out into a git worktree under the temporary folder (kept for
the next run, with its compiled kernels: `git worktree remove` it when done) and run
from there with this checkout's virtual environment (before the namespace move the packages were
top-level: `client.cli`; after, `posecast.client.cli`). Each side is warmed up once (its
compiled kernels; the run is thrown away), then the pairs run one after the other, old
then new, so that a drift of the machine (another load, a throttled CPU) falls on both.
It prints each run's p99s, the medians of each side and their ratios, and whether the
new code is within 10% of the old on the two network hops and no higher on the server
(issue 30's rule for the loopback tails). A tail on a shared VM moves by more than that
from one minute to the next: read the pairs, not one run.

``--parts`` also times where each side's server spends a frame's server stage
(``scripts/ab_parts``, loaded into both trees unchanged): the wait from its arrival to its
batch's solve (the burst's window, and any batch before it), the solve, and the work
from the solve to the send.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent
STAGES = ("capture_to_server", "server", "network_to_spectator", "capture_to_spectator")
HOPS = ("capture_to_server", "network_to_spectator")  # within 10% of the old code's
PARTS_HOOK = HERE / "scripts" / "ab_parts"  # a sitecustomize that times a demo's server
SETTLE_S = 2.0  # the first seconds of a run's batches are left out of its parts (joins)
PARTS = ("wait_p50_ms", "wait_p99_ms", "solve_us", "solve_us_per_avatar",
         "solve_to_send_us", "frames_per_batch")
TIMEOUT_S = 900  # a cold run compiles its kernels first


def _module(tree: Path) -> str:
    return "posecast.client.cli" if (tree / "posecast").is_dir() else "client.cli"


def _demo(tree: Path, args: argparse.Namespace, seconds: float,
          parts: Path | None = None) -> dict[str, dict[str, float]]:
    """One demo run's latency stages; with ``parts`` (a file prefix), its server timed
    there as well (``PARTS_HOOK``)."""
    cmd = [sys.executable, "-m", _module(tree), "demo", "--players", str(args.players),
           "--spectators", str(args.spectators), "--seconds", str(seconds), "--json"]
    env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}
    if parts is not None:
        env.update(PYTHONPATH=f"{PARTS_HOOK}:{tree}", POSECAST_AB_PARTS=str(parts))
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)
    if done.returncode != 0:
        raise SystemExit(f"ab_demo: the demo in {tree} failed: {done.stderr.strip()[-400:]}")
    doc = json.loads(done.stdout)
    return {k: v for k, v in doc["latency_ms"].items() if k in STAGES}


def _parts(prefix: Path) -> dict[str, float]:
    """A run's server stage in parts (``PARTS``), from the rows its server wrote (one per
    frame: arrival, batch began, solve start, solve end, sent, batch size)."""
    files = sorted(prefix.parent.glob(f"{prefix.name}.*.f64"), key=lambda f: f.stat().st_size)
    if not files:
        raise SystemExit(f"ab_demo --parts: no server wrote {prefix}.*.f64 (was the hook "
                         f"loaded? {PARTS_HOOK})")
    data = files[-1].read_bytes()  # whole rows only: the server may end mid-row (os._exit)
    rows = np.frombuffer(data[:len(data) // 48 * 48]).reshape(-1, 6)
    if len(rows) == 0:
        raise SystemExit(f"ab_demo --parts: {files[-1]} holds no whole batch")
    rows = rows[rows[:, 0] >= rows[0, 0] + SETTLE_S]
    arrival, _, start, end, sent, size = rows.T
    wait = (start - arrival) * 1e3
    _, first = np.unique(start, return_index=True)  # one row per batch
    solve = (end - start)[first] * 1e6
    return {"wait_p50_ms": float(np.median(wait)),
            "wait_p99_ms": float(np.percentile(wait, 99)),
            "solve_us": float(np.median(solve)),
            "solve_us_per_avatar": float(np.median(solve / size[first])),
            "solve_to_send_us": float(np.median((sent - end)[first] * 1e6)),
            "frames_per_batch": float(np.mean(size[first]))}


def _parts_line(p: dict[str, float]) -> str:
    return (f"waits p50 {p['wait_p50_ms']:.2f} p99 {p['wait_p99_ms']:.2f} ms for its solve, "
            f"solve {p['solve_us']:.0f} us a batch ({p['solve_us_per_avatar']:.1f} an "
            f"avatar), solve to send {p['solve_to_send_us']:.0f} us, "
            f"{p['frames_per_batch']:.1f} frames a batch")


def _warm(tree: Path, args: argparse.Namespace) -> None:
    """A short demo, thrown away, so that both sides' kernels are compiled and cached. An
    older demo gives its embedded server 60 s to start, less than a cold compile takes
    here: each try caches what it compiled, so a few tries get there."""
    for attempt in range(4):
        try:
            _demo(tree, args, 2.0)
            return
        except SystemExit as err:
            if attempt == 3:
                raise
            print(f"  (warm-up {attempt + 1} of {tree.name} did not finish: {str(err)[-80:]};"
                  f" again)", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--old", required=True, help="the older commit (any git revision)")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--players", type=int, default=16)
    parser.add_argument("--spectators", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--json", type=Path, help="also write every run's figures here")
    parser.add_argument("--parts", action="store_true",
                        help="also time each server's stage in parts (scripts/ab_parts)")
    args = parser.parse_args()
    if args.pairs < 1 or args.seconds <= 0:
        parser.error("--pairs must be >= 1 and --seconds > 0")
    rev = subprocess.run(["git", "rev-parse", "--verify", f"{args.old}^{{commit}}"],
                         cwd=HERE, capture_output=True, text=True)
    if rev.returncode != 0:
        parser.error(f"--old {args.old!r} is not a commit of this repository")
    sha = rev.stdout.strip()
    # kept between runs (its compiled kernels with it: a cold start compiles for minutes)
    old = Path(tempfile.gettempdir()) / f"posecast-ab-{sha[:12]}"
    if not (old / ".git").exists():
        subprocess.run(["git", "worktree", "prune"], cwd=HERE, capture_output=True)
        subprocess.run(["git", "worktree", "add", "--detach", str(old), sha], cwd=HERE,
                       check=True, capture_output=True)
    runs: dict[str, list[dict[str, dict[str, float]]]] = {"old": [], "new": []}
    print(f"old {sha[:10]} in {old}; warming both sides up (a cold one compiles) ...",
          flush=True)
    for tree in (old, HERE):
        _warm(tree, args)
    parts: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
    with tempfile.TemporaryDirectory(prefix="posecast-ab-parts-") as scratch:
        for i in range(1, args.pairs + 1):
            for side, tree in (("old", old), ("new", HERE)):
                prefix = Path(scratch) / f"{side}{i}" if args.parts else None
                figures = _demo(tree, args, args.seconds, prefix)
                runs[side].append(figures)
                print(f"{side} {i}: " + "  ".join(
                    f"{k} {figures[k]['p99']:.2f}" for k in STAGES if k in figures),
                    flush=True)
                if prefix is not None:
                    parts[side].append(_parts(prefix))
                    print(f"  its server: a frame {_parts_line(parts[side][-1])}", flush=True)
    print(f"\np99 medians of {args.pairs} alternated pairs (ms), "
          f"{args.players} players + {args.spectators} spectators:")
    print(f"{'stage':<22}{'old':>8}{'new':>8}{'new/old':>9}")
    verdict = []
    for k in STAGES:
        o = statistics.median(r[k]["p99"] for r in runs["old"])
        n = statistics.median(r[k]["p99"] for r in runs["new"])
        print(f"{k:<22}{o:>8.2f}{n:>8.2f}{n / o:>9.2f}")
        if k in HOPS:
            verdict.append(f"{k} {'within' if n <= 1.1 * o else 'beyond'} 10%")
        elif k == "server":
            verdict.append(f"server {'no higher' if n <= o else 'higher'}")
    print("; ".join(verdict))
    if args.parts:
        print("\nthe server stage in parts, medians of the runs:")
        for side in ("old", "new"):
            median = {k: statistics.median(p[k] for p in parts[side]) for k in PARTS}
            print(f"{side}: a frame {_parts_line(median)}")
    if args.json is not None:
        args.json.write_text(json.dumps({"old": args.old, "runs": runs, "parts": parts},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
