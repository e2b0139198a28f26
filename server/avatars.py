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

from posecast.server.helper import SolveHelper
from posecast.solver.calibration import EFFECTOR_DEVICES, Calibration, calibrate
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.ik.shared import solve_analytic_shared
from posecast.solver.kernels import bone_targets
from posecast.solver.rig import EFFECTORS, Rig

Array = NDArray[np.float64]


class NotCalibratedError(ValueError):
    """A tracker frame for an avatar that has not sent its T-pose yet."""


def pose_dicts(roles: tuple[str, ...], positions: Array,
               rotations: Array) -> tuple[dict[str, Array], dict[str, Array]]:
    return ({r: positions[i] for i, r in enumerate(roles)},
            {r: rotations[i] for i, r in enumerate(roles)})


# bounded: the roles come from clients, and ten roles have 3.6 million orders
@functools.lru_cache(maxsize=256)
def driving_indices(roles: tuple[str, ...]) -> NDArray[np.intp]:
    """Where each driving device (EFFECTOR_DEVICES order) is in a frame's roles (cached:
    a player sends the same roles every frame; read-only, as the cache shares it). An
    index array, not a list: ``take`` with it costs 0.3 us, indexing with a list 1.5."""
    missing = [d for d in EFFECTOR_DEVICES if d not in roles]
    if missing:
        raise ValueError(f"the frame lacks the driving devices {', '.join(missing)}")
    index = np.array([roles.index(d) for d in EFFECTOR_DEVICES], dtype=np.intp)
    index.flags.writeable = False
    return index


class AvatarSolver:
    """Calibrate avatars and solve any subset of them in one call to the solver."""

    def __init__(self, rig: Rig, solver: str = "analytic", capacity: int = 8,
                 helper_cores: tuple[int, ...] = ()) -> None:
        """``helper_cores``: solve each batch with a helper thread spinning there
        (``server.helper``; the analytic solver only)."""
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
        self._targets = np.empty((capacity, E, 7))  # staged: each avatar's next targets
        self._iterations = np.zeros(capacity, dtype=np.int64)
        self.helper_cores = helper_cores if solver == "analytic" else ()
        self._helper: SolveHelper | None = None

    def warm_up(self) -> None:
        """Solve once now: loading the compiled solver takes ~0.2 s, not the first frame's."""
        state = PoseBatch.canonical(self.rig, 1)
        gq, gp = forward_kinematics(self.rig.skeleton, state.rotations, state.root)
        eff = self.rig.effectors
        self.solver.solve(np.concatenate([gp[:, eff], gq[:, eff]], axis=-1), state)
        bone_targets(np.zeros((1, 7)), np.zeros((1, 3)), np.tile([0.0, 0, 0, 1], (1, 1)),
                     np.empty((1, 7)))
        helper = self.helper()
        if helper is not None:  # its loop and the shared solve load now too (n = 0)
            solve_analytic_shared(*helper.batch_args(0))

    def _new_slot(self) -> int:
        used = set(self._slot.values())
        free = next((s for s in range(len(self._roots)) if s not in used), None)
        if free is None:  # grow: double every array
            free = len(self._roots)
            restart = self._helper is not None
            if self._helper is not None:  # it holds the arrays being replaced
                self._helper.stop(wait=False)
                self._helper = None
            for name in ("_rotations", "_roots", "_offsets", "_mount_p", "_mount_q",
                         "_targets", "_iterations"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.empty_like(a)]))
            if restart:  # here, as a player calibrates, not in the next frame's solve
                self.helper()
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

    def stage(self, avatar_id: int, roles: tuple[str, ...], poses: Array) -> None:
        """Take a frame's driving devices (poses (D, 7): position | quaternion) as the
        avatar's targets for its next solve; a newer frame replaces an older one. A room
        stages each frame as it arrives, while the rest of the burst is still coming in,
        so the solve itself only gathers rows."""
        slot = self._slot.get(avatar_id)
        if slot is None:
            raise NotCalibratedError(f"avatar {avatar_id} has not been calibrated: "
                                     "send a calibrate message (T-pose) first")
        device = poses.take(driving_indices(roles), axis=0)  # new (E, 7), C order
        bone_targets(device, self._mount_p[slot], self._mount_q[slot], self._targets[slot])

    def helper(self) -> SolveHelper | None:
        """The helper thread over the current arrays (started on first use), if any."""
        if self._helper is None and self.helper_cores:
            self._helper = SolveHelper(self.helper_cores, self._analytic_args(),
                                       len(self._roots), self.rig.skeleton.num_joints)
        return self._helper

    def close(self) -> None:
        """Stop the helper thread, if one runs (a later solve starts a new one)."""
        if self._helper is not None:
            self._helper.stop()
            self._helper = None

    def _analytic_args(self) -> tuple[object, ...]:
        return self.solver.analytic_args(self._offsets, self._targets, self._rotations,
                                       self._roots, self._iterations)

    def solve_staged(self, avatar_ids: list[int]) -> PoseBatch:
        """Solve these avatars (each staged) as one batch, each warm-started from its last
        pose; their new poses in the order asked (new arrays: the next solve does not
        change them)."""
        slot_list = [self._slot[a] for a in avatar_ids]
        helper = self.helper() if slot_list else None
        if helper is not None:  # in place, wherever the rows are, with the helper
            n = len(slot_list)
            helper.rows[:n] = slot_list
            solve_analytic_shared(*helper.batch_args(n))
            slots = helper.rows[:n]
            return PoseBatch(self._rotations[slots], self._roots[slots],
                             self._iterations[slots])
        first = slot_list[0] if slot_list else 0
        if slot_list == list(range(first, first + len(slot_list))):
            # side by side in slot order (a room's whole burst, sorted by slot): solve the
            # rows where they are, without gathering and scattering four arrays
            rows = slice(first, first + len(slot_list))
            state = PoseBatch(self._rotations[rows], self._roots[rows])
            self.solver.solve(self._targets[rows], state, self._offsets[rows])
            return PoseBatch(state.rotations.copy(), state.root.copy(), state.iterations)
        slots = np.array(slot_list, dtype=np.intp)
        state = PoseBatch(self._rotations[slots], self._roots[slots])
        self.solver.solve(self._targets[slots], state, self._offsets[slots])
        self._rotations[slots] = state.rotations
        self._roots[slots] = state.root
        return state

    def slot_order(self, avatar_id: int) -> int:
        """Where the avatar's rows are: a batch in this order solves in place."""
        return self._slot[avatar_id]

    def solve(self, frames: list[tuple[int, tuple[str, ...], Array]]) -> PoseBatch:
        """Solve the avatars of ``frames`` [(avatar id, roles, poses (D, 7): position |
        quaternion)] as one batch: ``stage`` each, then ``solve_staged``."""
        for avatar_id, roles, poses in frames:
            self.stage(avatar_id, roles, poses)
        return self.solve_staged([avatar_id for avatar_id, _, _ in frames])
