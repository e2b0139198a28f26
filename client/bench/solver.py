"""`posecast bench solver`: microseconds per avatar-frame, batched, on a real motion.

The built-in CMU walk is replayed as the trackers of a tracker set (``--devices``; the
joints stand in for the devices, as in ``posecast eval``), every avatar at a different
frame, so the batch is not one pose repeated. A call is what a server does for a batch
once its frames are staged: the targets made (``solver.tracking``: the body model fills
what the set lacks) and the solve. Each batch size is timed for a fixed wall time after
a warm-up call that also compiles; we report the median and p99 of per-call times
divided by the batch size."""

from __future__ import annotations

import time

import numpy as np

from posecast.client.builtin import builtin_motion_path
from posecast.solver.evaluation import performer_calibration
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver, SolverOptions
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.rig import build_rig
from posecast.solver.tracking.devices import BONES, DEFAULT_SET, DEVICES, PRESETS
from posecast.solver.tracking.rows import TrackingRows, slots_of


def bench_solver(name: str, batch_sizes: list[int], options: SolverOptions,
                 seconds: float = 2.0,
                 devices: tuple[str, ...] = PRESETS[DEFAULT_SET]) -> dict[str, object]:
    motion = read_bvh(builtin_motion_path())
    sk = motion.skeleton
    rig = build_rig(sk)
    rot = motion.rotations[motion.first_frame:]
    trans = motion.translations[motion.first_frame:]
    gq, gp = forward_kinematics(sk, rot, trans[:, 0], trans)
    joints = [rig.role(BONES[DEVICES.index(d)]) for d in devices]
    poses = np.concatenate([gp[:, joints], gq[:, joints]], axis=-1)  # (F, D, 7)
    F = poses.shape[0]
    slots = slots_of(devices)
    head = rig.role("head")
    floor = float(gp[0, :, 1].min())
    cal = performer_calibration(rig, sk.offsets, gp[0, head], gq[0, head], floor)
    solver = Solver(rig, name, options)
    results = []
    for B in batch_sizes:
        rows = TrackingRows(B)
        every = np.arange(B, dtype=np.intp)
        for b in every:
            rows.calibrate(int(b), cal, devices, floor)
        state = PoseBatch.canonical(rig, B)
        offsets = np.broadcast_to(sk.offsets, (B, *sk.offsets.shape)).copy()
        start = np.arange(B) * 7 % F

        def stage(f: int, rows: TrackingRows = rows, start: np.ndarray = start) -> None:
            for b in range(rows.capacity):
                rows.stage(b, slots, poses[(start[b] + f) % F], f / motion.fps)

        stage(0)  # warm-up (and JIT compile)
        rows.fill(every)
        solver.solve(rows.targets, state, offsets, rows.weights)
        times: list[float] = []
        t_end = time.perf_counter() + seconds
        f = 1
        while time.perf_counter() < t_end or len(times) < 20:
            stage(f)
            t0 = time.perf_counter()
            rows.fill(every)
            solver.solve(rows.targets, state, offsets, rows.weights)
            times.append(time.perf_counter() - t0)
            f += 1
        per = np.array(times) / B * 1e6
        results.append({"avatars": B, "us_per_avatar_frame": round(float(np.median(per)), 2),
                        "us_per_avatar_frame_p99": round(float(np.percentile(per, 99)), 2),
                        "calls": len(times)})
    return {"solver": name, "devices": list(devices),
            "max_iterations": solver.max_iterations, "results": results}


def format_solver_table(result: dict[str, object]) -> str:
    lines = [f"solver {result['solver']} (at most {result['max_iterations']} iterations "
             f"per chain), devices {', '.join(result['devices'])}",  # type: ignore[arg-type]
             "avatars  us/avatar-frame p50    p99   calls"]
    for r in result["results"]:  # type: ignore[attr-defined]
        lines.append(f"{r['avatars']:7d}  {r['us_per_avatar_frame']:19.2f} "
                     f"{r['us_per_avatar_frame_p99']:7.2f} {r['calls']:7d}")
    return "\n".join(lines)
