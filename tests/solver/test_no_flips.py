"""No catastrophic frames: an arm raised overhead and back, bent and twisting, with the
wrist flexing and deviating, is followed without the elbow jumping across its circle; a
body turned upside down is solved as well as upright; the paper's solver wins no clip."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from posecast.solver.evaluation import EvalOptions, evaluate_vive
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.kernels import composed
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.readers.vive import read_vive
from posecast.solver.rig import Rig, build_rig

SharedData = Callable[[str], Path]


def _raised_arms(rig: Rig, seed: int, frames: int = 400) -> np.ndarray:
    """Local rotations (F, J, 4): both arms from the side to overhead and back."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)
    local = np.tile(rig.canonical, (frames, 1, 1))
    for side in "lr":
        u, fa, h = (rig.role(f"{r}_{side}") for r in ("upperarm", "forearm", "hand"))
        z = np.radians(105) * np.sin(np.pi * t) ** 2 + np.radians(rng.uniform(-10, 0))
        x = np.radians(rng.uniform(-20, 60)) * np.sin(2 * np.pi * t + rng.uniform(0, 6))
        twist = np.radians(rng.uniform(-60, 60)) * np.sin(3 * np.pi * t)
        bend = np.radians(rng.uniform(0, 90)) * (0.5 + 0.5 * np.sin(5 * np.pi * t))
        pronation = np.radians(rng.uniform(-80, 80)) * np.sin(2 * np.pi * t)
        flex = np.radians(rng.uniform(-50, 50)) * np.sin(4 * np.pi * t + 1)
        deviation = np.radians(rng.uniform(-25, 25)) * np.sin(3 * np.pi * t)
        for f in range(frames):
            local[f, h] = composed(tuple(rig.pre[h]), tuple(rig.post[h]), flex[f], 0.0,
                                   deviation[f])
            local[f, u] = composed(tuple(rig.pre[u]), tuple(rig.post[u]), x[f], twist[f], z[f])
            local[f, fa] = composed(tuple(rig.pre[fa]), tuple(rig.post[fa]), bend[f],
                                    pronation[f], 0.0)
    return local


def test_the_elbow_never_jumps_across_its_circle() -> None:
    rig = build_rig(load_makehuman().skeleton)
    sk = rig.skeleton
    local = _raised_arms(rig, seed=0)
    frames = local.shape[0]
    root = np.tile(sk.offsets[0], (frames, 1))
    gq, gp = forward_kinematics(sk, local, root)
    targets = np.concatenate([gp[:, rig.effectors], gq[:, rig.effectors]], axis=-1)
    solver = Solver(rig, "analytic")
    state = PoseBatch.canonical(rig, 1)
    state.root[0] = root[0]
    solved = np.empty_like(local)
    for f in range(frames):
        solver.solve(targets[f: f + 1], state, sk.offsets[None])
        solved[f] = state.rotations[0]
    _, sp = forward_kinematics(sk, solved, root)
    for side in "lr":
        elbow, hand = rig.role(f"forearm_{side}"), rig.role(f"hand_{side}")
        # the hands are reached in every frame
        assert np.linalg.norm(sp[:, hand] - gp[:, hand], axis=-1).max() < 0.005
        # the true elbow moves at most ~5 mm a frame; a swivel flip moved the solved one
        # 85-89 mm in a frame (the neutral-wrist elbow passing near the shoulder-wrist
        # line; the pull down flipping sign with the elbow at the top of its circle)
        truth = np.linalg.norm(np.diff(gp[:, elbow], axis=0), axis=-1).max()
        step = np.linalg.norm(np.diff(sp[:, elbow], axis=0), axis=-1).max()
        assert truth < 0.006
        assert step < 0.025, f"elbow_{side} jumped {step * 1000:.0f} mm in a frame"


def test_the_papers_solver_beats_the_default_on_no_vive_clip(shared_data: SharedData) -> None:
    """Every shared Vive recording, both solvers: the default is better in the mean, in
    the forearms and knees it never sees, and in its worst 1% of frames."""
    folder = shared_data("vive")
    clips = sorted(folder.glob("*.csv"))
    assert len(clips) >= 10
    for path in clips:
        rec = read_vive(path)
        ours = evaluate_vive(rec, EvalOptions("analytic"))
        paper = evaluate_vive(rec, EvalOptions("paper"))
        name = path.name
        assert ours.mean_error_mm < paper.mean_error_mm, name
        assert ours.heldout_error_mm < paper.heldout_error_mm, name
        assert ours.extra["p99_frame_error_mm"] < paper.extra["p99_frame_error_mm"], name


def test_a_body_turned_over_is_solved_as_well_as_upright() -> None:
    """The built-in walk turned upside down and laid on its back as a whole: the
    trackers move with it, so the solved body should be as good as upright (only the
    bent elbow's pull towards the ground is fixed to the world)."""
    import dataclasses

    from posecast.client.builtin import builtin_motion_path
    from posecast.solver import rotations as R
    from posecast.solver.evaluation import evaluate_bvh
    from posecast.solver.readers.bvh import read_bvh

    motion = read_bvh(builtin_motion_path())
    upright = evaluate_bvh(motion)
    for axis, angle in (((0.0, 0.0, 1.0), np.pi), ((1.0, 0.0, 0.0), np.pi / 2)):
        turn = R.from_axis_angle(np.array(axis), np.array(angle))
        rot, trans = motion.rotations.copy(), motion.translations.copy()
        rot[:, 0] = R.mul(turn, rot[:, 0])
        trans[:, 0] = R.rotate(turn, trans[:, 0])
        turned = evaluate_bvh(dataclasses.replace(motion, rotations=rot, translations=trans))
        assert abs(turned.mean_error_mm - upright.mean_error_mm) < 1.0
        assert turned.extra["p99_frame_error_mm"] < upright.extra["p99_frame_error_mm"] + 5.0
