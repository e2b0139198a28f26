"""`posecast bench server`: how many players (90 Hz) and spectators one server process
sustains on this machine with the p99 of its own stage (frame received -> batch sent)
within the budget.

Each step runs a short demo (server in its own process, clients in this one) with as
many spectators as players, and grows the count until the p99 `server` stage or a lost
frame says stop. Clients and server share this machine's cores, so the figure is the
server's capacity *next to* its load generator: a lower bound for a dedicated host.
"""

from __future__ import annotations

from collections.abc import Callable

from posecast.client.bench.demo import DemoResult, run_demo

BUDGET_MS = 2.0


def bench_server(counts: list[int], seconds: float = 4.0, budget_ms: float = BUDGET_MS,
                 progress: Callable[[DemoResult], None] | None = None,
                 helper: bool | None = None) -> dict[str, object]:
    """``helper``: as ``run_demo``'s (False: the server solves alone)."""
    steps = []
    best = 0
    for n in counts:
        result = run_demo(players=n, spectators=n, seconds=seconds, helper=helper)
        summary = result.latency.summary()
        p99 = summary.get("server", {}).get("p99", float("inf"))
        complete = result.frames_delivered == result.frames_solved * n
        ok = p99 <= budget_ms and complete
        steps.append({"players": n, "spectators": n, "server_p99_ms": round(p99, 3),
                      "capture_to_spectator_p99_ms": round(
                          summary.get("capture_to_spectator", {}).get("p99", float("nan")), 3),
                      "frames_solved": result.frames_solved,
                      "frames_delivered": result.frames_delivered, "within_budget": ok})
        if progress is not None:
            progress(result)
        if not ok:
            break
        best = n
    return {"budget_ms": budget_ms, "max_players": best, "max_spectators": best,
            "steps": steps}


def format_server_table(result: dict[str, object]) -> str:
    steps = result["steps"]
    assert isinstance(steps, list)
    lines = [f"{'players':>7}  {'spectators':>10}  {'server p99 ms':>13}  "
             f"{'capture->spectator p99 ms':>25}  {'within budget':>13}"]
    for s in steps:
        lines.append(f"{s['players']:>7}  {s['spectators']:>10}  {s['server_p99_ms']:>13.3f}  "
                     f"{s['capture_to_spectator_p99_ms']:>25.3f}  "
                     f"{'yes' if s['within_budget'] else 'no':>13}")
    lines.append(f"sustained: {result['max_players']} players and {result['max_spectators']} "
                 f"spectators with p99 server <= {result['budget_ms']} ms")
    return "\n".join(lines)
