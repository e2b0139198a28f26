"""The avatars of one room as solver state: each avatar's calibration and last pose, and
one batched solve for whichever avatars have a new tracker frame.

No sockets here: the room hands in device poses and gets rotations back, so this is what
tests compare against the offline solve of the same recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver import rotations as R
from solver.calibration import EFFECTOR_DEVICES, Calibration, calibrate
from solver.fk import forward_kinematics
from solver.ik import PoseBatch, Solver
from solver.rig import EFFECTORS, Rig


class NotCalibratedError(ValueError):
    """A tracker frame for an avatar that has not sent its T-pose yet."""


@dataclass
class AvatarState:
    calibration: Calibration
    rotations: NDArray[np.float64]  # (J, 4) last solved local rotations (warm start)
    root: NDArray[np.float64]  # (3,)
    # the driving devices' mounts, in EFFECTOR_DEVICES order, for one vectorised targets call
    mount_positions: NDArray[np.float64]  # (6, 3)
    mount_rotations: NDArray[np.float64]  # (6, 4)


def driving_indices(roles: tuple[str, ...]) -> list[int]:
    """Where each driving device (EFFECTOR_DEVICES order) is in a frame's roles."""
    try:
        return [roles.index(d) for d in EFFECTOR_DEVICES]
    except ValueError:
        missing = [d for d in EFFECTOR_DEVICES if d not in roles]
        raise ValueError(f"the frame lacks the driving devices {', '.join(missing)}") from None


@dataclass(frozen=True)
class Solved:
    """One batch's result: per avatar, in the order asked."""

    avatar_ids: tuple[int, ...]
    rotations: NDArray[np.float64]  # (B, J, 4)
    roots: NDArray[np.float64]  # (B, 3)


def pose_dicts(roles: tuple[str, ...], positions: NDArray[np.float64],
               rotations: NDArray[np.float64]) -> tuple[dict[str, NDArray[np.float64]],
                                                         dict[str, NDArray[np.float64]]]:
    return ({r: positions[i] for i, r in enumerate(roles)},
            {r: rotations[i] for i, r in enumerate(roles)})


class AvatarSolver:
    """Calibrate avatars and solve any subset of them in one call to the solver."""

    def __init__(self, rig: Rig, solver: str = "analytic") -> None:
        self.rig = rig
        self.solver = Solver(rig, solver)
        self.avatars: dict[int, AvatarState] = {}

    def warm_up(self) -> None:
        """Solve once now: loading the compiled solver takes ~0.2 s, not the first frame's."""
        state = PoseBatch.canonical(self.rig, 1)
        gq, gp = forward_kinematics(self.rig.skeleton, state.rotations, state.root)
        eff = self.rig.effectors
        self.solver.solve(np.concatenate([gp[:, eff], gq[:, eff]], axis=-1), state)

    def calibrate(self, avatar_id: int, roles: tuple[str, ...],
                  positions: NDArray[np.float64], rotations: NDArray[np.float64]
                  ) -> Calibration:
        """Calibrate (or recalibrate) an avatar from a T-pose sample of its devices."""
        pos, rot = pose_dicts(roles, positions, rotations)
        cal = calibrate(self.rig, pos, rot)
        mounts = [cal.mounts[d] for d in EFFECTOR_DEVICES]
        self.avatars[avatar_id] = AvatarState(
            cal, cal.pose.copy(), cal.root.copy(),
            np.array([m.position for m in mounts]), np.array([m.rotation for m in mounts]))
        return cal

    def remove(self, avatar_id: int) -> None:
        self.avatars.pop(avatar_id, None)

    def solve(self, frames: list[tuple[int, tuple[str, ...], NDArray[np.float64],
                                       NDArray[np.float64]]]) -> Solved:
        """Solve the avatars of ``frames`` [(avatar id, roles, positions (D, 3), rotations
        (D, 4))] as one batch, each warm-started from its last pose."""
        B = len(frames)
        J = self.rig.skeleton.num_joints
        device_p = np.empty((B, len(EFFECTORS), 3))
        device_q = np.empty((B, len(EFFECTORS), 4))
        mount_p = np.empty((B, len(EFFECTORS), 3))
        mount_q = np.empty((B, len(EFFECTORS), 4))
        state = PoseBatch(np.empty((B, J, 4)), np.empty((B, 3)))
        offsets = np.empty((B, J, 3))
        for b, (avatar_id, roles, positions, rotations) in enumerate(frames):
            avatar = self.avatars.get(avatar_id)
            if avatar is None:
                raise NotCalibratedError(f"avatar {avatar_id} has not been calibrated: "
                                        "send a calibrate message (T-pose) first")
            idx = driving_indices(roles)
            device_p[b] = positions[idx]
            device_q[b] = rotations[idx]
            mount_p[b] = avatar.mount_positions
            mount_q[b] = avatar.mount_rotations
            state.rotations[b] = avatar.rotations
            state.root[b] = avatar.root
            offsets[b] = avatar.calibration.offsets
        # bone target = device pose with the mount taken off (Calibration.targets, batched)
        targets = np.empty((B, len(EFFECTORS), 7))
        bone_q = R.mul(device_q, R.conjugate(mount_q))
        targets[..., :3] = device_p - R.rotate(bone_q, mount_p)
        targets[..., 3:] = bone_q
        self.solver.solve(targets, state, offsets)
        ids = tuple(f[0] for f in frames)
        for b, avatar_id in enumerate(ids):
            avatar = self.avatars[avatar_id]
            avatar.rotations = state.rotations[b].copy()
            avatar.root = state.root[b].copy()
        return Solved(ids, state.rotations, state.root)
