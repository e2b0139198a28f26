"""`posecast bench solver`: microseconds per avatar-frame, batched, on a real motion.

The targets come from the built-in CMU walk replayed as six 6-DoF trackers (every
avatar a different frame, so the batch is not one pose repeated). Each batch size is
timed for a fixed wall time after a warm-up call that also compiles; we report the
median and p99 of per-call times divided by the batch size."""

from __future__ import annotations

import time

import numpy as np

from posecast.client.builtin import builtin_motion_path
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver, SolverOptions
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.rig import build_rig


def bench_solver(name: str, batch_sizes: list[int], options: SolverOptions,
                 seconds: float = 2.0) -> dict[str, object]:
    motion = read_bvh(builtin_motion_path())
    sk = motion.skeleton
    rig = build_rig(sk)
    rot = motion.rotations[motion.first_frame:]
    trans = motion.translations[motion.first_frame:]
    gq, gp = forward_kinematics(sk, rot, trans[:, 0], trans)
    eff = rig.effectors
    all_targets = np.concatenate([gp[:, eff], gq[:, eff]], axis=-1)
    F = all_targets.shape[0]
    solver = Solver(rig, name, options)
    results = []
    for B in batch_sizes:
        state = PoseBatch.canonical(rig, B)
        start = np.arange(B) * 7 % F
        solver.solve(all_targets[start], state)  # warm-up (and JIT compile)
        times: list[float] = []
        t_end = time.perf_counter() + seconds
        f = 0
        while time.perf_counter() < t_end or len(times) < 20:
            targets = all_targets[(start + f) % F]
            t0 = time.perf_counter()
            solver.solve(targets, state)
            times.append(time.perf_counter() - t0)
            f += 1
        per = np.array(times) / B * 1e6
        results.append({"avatars": B, "us_per_avatar_frame": round(float(np.median(per)), 2),
                        "us_per_avatar_frame_p99": round(float(np.percentile(per, 99)), 2),
                        "calls": len(times)})
    return {"solver": name, "max_iterations": solver.max_iterations, "results": results}


def format_solver_table(result: dict[str, object]) -> str:
    lines = [f"solver {result['solver']} (at most {result['max_iterations']} iterations "
             "per chain)", "avatars  us/avatar-frame p50    p99   calls"]
    for r in result["results"]:  # type: ignore[attr-defined]
        lines.append(f"{r['avatars']:7d}  {r['us_per_avatar_frame']:19.2f} "
                     f"{r['us_per_avatar_frame_p99']:7.2f} {r['calls']:7d}")
    return "\n".join(lines)
