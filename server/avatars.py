"""The avatars of one room as solver state: each avatar's calibration and last pose, and
one batched solve for whichever avatars have a new tracker frame.

No sockets here: the room hands in device poses and gets rotations back, so this is what
tests compare against the offline solve of the same recording. Every avatar's state lives
in one slot of shared arrays, so gathering a batch and scattering its result are a few
array operations whatever the number of avatars.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from solver.calibration import EFFECTOR_DEVICES, Calibration, calibrate
from solver.fk import forward_kinematics
from solver.ik import PoseBatch, Solver
from solver.kernels import bone_targets
from solver.rig import EFFECTORS, Rig

Array = NDArray[np.float64]


class NotCalibratedError(ValueError):
    """A tracker frame for an avatar that has not sent its T-pose yet."""


def pose_dicts(roles: tuple[str, ...], positions: Array,
               rotations: Array) -> tuple[dict[str, Array], dict[str, Array]]:
    return ({r: positions[i] for i, r in enumerate(roles)},
            {r: rotations[i] for i, r in enumerate(roles)})


# bounded: the roles come from clients, and ten roles have 3.6 million orders
@functools.lru_cache(maxsize=256)
def driving_indices(roles: tuple[str, ...]) -> list[int]:
    """Where each driving device (EFFECTOR_DEVICES order) is in a frame's roles (cached:
    a player sends the same roles every frame)."""
    missing = [d for d in EFFECTOR_DEVICES if d not in roles]
    if missing:
        raise ValueError(f"the frame lacks the driving devices {', '.join(missing)}")
    return [roles.index(d) for d in EFFECTOR_DEVICES]


class AvatarSolver:
    """Calibrate avatars and solve any subset of them in one call to the solver."""

    def __init__(self, rig: Rig, solver: str = "analytic", capacity: int = 8) -> None:
        self.rig = rig
        self.solver = Solver(rig, solver)
        self.calibrations: dict[int, Calibration] = {}
        self._slot: dict[int, int] = {}
        J, E = rig.skeleton.num_joints, len(EFFECTORS)
        self._rotations = np.empty((capacity, J, 4))  # last solved pose (warm start)
        self._roots = np.empty((capacity, 3))
        self._offsets = np.empty((capacity, J, 3))  # each avatar's bone lengths
        self._mount_p = np.empty((capacity, E, 3))  # driving devices' mounts
        self._mount_q = np.empty((capacity, E, 4))

    def warm_up(self) -> None:
        """Solve once now: loading the compiled solver takes ~0.2 s, not the first frame's."""
        state = PoseBatch.canonical(self.rig, 1)
        gq, gp = forward_kinematics(self.rig.skeleton, state.rotations, state.root)
        eff = self.rig.effectors
        self.solver.solve(np.concatenate([gp[:, eff], gq[:, eff]], axis=-1), state)
        bone_targets(np.zeros((1, 7)), np.zeros((1, 3)), np.tile([0.0, 0, 0, 1], (1, 1)),
                     np.empty((1, 7)))

    def _new_slot(self) -> int:
        used = set(self._slot.values())
        free = next((s for s in range(len(self._roots)) if s not in used), None)
        if free is None:  # grow: double every array
            free = len(self._roots)
            for name in ("_rotations", "_roots", "_offsets", "_mount_p", "_mount_q"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.empty_like(a)]))
        return free

    def calibrate(self, avatar_id: int, roles: tuple[str, ...], positions: Array,
                  rotations: Array) -> Calibration:
        """Calibrate (or recalibrate) an avatar from a T-pose sample of its devices."""
        pos, rot = pose_dicts(roles, positions, rotations)
        cal = calibrate(self.rig, pos, rot)
        slot = self._slot.get(avatar_id)
        if slot is None:
            slot = self._slot[avatar_id] = self._new_slot()
        self.calibrations[avatar_id] = cal
        self._rotations[slot] = cal.pose
        self._roots[slot] = cal.root
        self._offsets[slot] = cal.offsets
        self._mount_p[slot], self._mount_q[slot] = cal.effector_mounts()
        return cal

    def remove(self, avatar_id: int) -> None:
        self.calibrations.pop(avatar_id, None)
        self._slot.pop(avatar_id, None)

    def solve(self, frames: list[tuple[int, tuple[str, ...], Array]]) -> PoseBatch:
        """Solve the avatars of ``frames`` [(avatar id, roles, poses (D, 7): position |
        quaternion)] as one batch, each warm-started from its last pose; their new poses
        in the order asked."""
        B = len(frames)
        slots = np.empty(B, dtype=np.intp)
        for b, (avatar_id, _, _) in enumerate(frames):
            slot = self._slot.get(avatar_id)
            if slot is None:
                raise NotCalibratedError(f"avatar {avatar_id} has not been calibrated: "
                                         "send a calibrate message (T-pose) first")
            slots[b] = slot
        device = self._driving_poses(frames)
        E = len(EFFECTORS)
        targets = np.empty((B, E, 7))  # C order: the kernel writes through reshape views
        bone_targets(device.reshape(B * E, 7), self._mount_p[slots].reshape(B * E, 3),
                     self._mount_q[slots].reshape(B * E, 4), targets.reshape(B * E, 7))
        state = PoseBatch(self._rotations[slots], self._roots[slots])
        self.solver.solve(targets, state, self._offsets[slots])
        self._rotations[slots] = state.rotations
        self._roots[slots] = state.root
        return state

    @staticmethod
    def _driving_poses(frames: list[tuple[int, tuple[str, ...], Array]]) -> Array:
        """(B, E, 7) poses of the driving devices; one gather when every frame has the
        same roles in the same order (as a room of the same client software sends)."""
        roles = frames[0][1]
        if all(f[1] == roles for f in frames):
            gathered = np.stack([f[2] for f in frames])[:, driving_indices(roles)]
        else:
            gathered = np.stack([poses[driving_indices(r)] for _, r, poses in frames])
        return np.ascontiguousarray(gathered)  # reshaped below: must be a view, not a copy
