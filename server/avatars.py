"""The avatars of one room as solver state: each avatar's calibration and last pose, and
one batched solve for whichever avatars have a new tracker frame.

No sockets here: the room hands in device poses and gets rotations back, so this is what
tests compare against the offline solve of the same recording. Every avatar's state lives
in one slot of shared arrays, so gathering a batch and scattering its result are a few
array operations whatever the number of avatars.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.pose_coding import PoseCoding, coding_bits
from posecast.protocol.roles import role_bits
from posecast.server.helper import SolveHelper
from posecast.solver.calibration import Calibration, calibrate, mount_device
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.ik.chains import driven_joints
from posecast.solver.ik.shared import solve_analytic_shared
from posecast.solver.rig import Rig
from posecast.solver.tracking.rows import TrackingRows, lost_roles, slots_of

Array = NDArray[np.float64]


class NotCalibratedError(ValueError):
    """A tracker frame for an avatar that has not sent its T-pose yet."""


def pose_dicts(roles: tuple[str, ...], positions: Array,
               rotations: Array) -> tuple[dict[str, Array], dict[str, Array]]:
    return ({r: positions[i] for i, r in enumerate(roles)},
            {r: rotations[i] for i, r in enumerate(roles)})


@functools.lru_cache(maxsize=256)  # bounded: the roles come from clients
def _present_bits(roles: tuple[str, ...]) -> int:
    return role_bits(roles)


@functools.lru_cache(maxsize=8)  # a server has one rig
def _coding_fields(rig: Rig) -> dict[str, Any]:
    driven = driven_joints(rig)
    return {"driven": tuple(driven.tolist()),
            "bits": tuple(coding_bits(rig.lo[j], rig.hi[j]) for j in driven.tolist()),
            "lo": rig.lo[driven], "hi": rig.hi[driven], "pre": rig.pre[driven],
            "post": rig.post[driven]}


def rig_coding(rig: Rig, rest: Array | None = None) -> PoseCoding:
    """The PoseCoding of an avatar solved on ``rig``: the joints a solve turns, each in
    the fewest bits its limits allow; ``rest`` (J, 4) the others' rotations (default the
    canonical pose). The same for every avatar but its rest."""
    return PoseCoding(rest=rig.canonical if rest is None else rest, **_coding_fields(rig))


class AvatarSolver:
    """Calibrate avatars and solve any subset of them in one call to the solver, from
    whatever devices each frame has (``solver.tracking``)."""

    def __init__(self, rig: Rig, solver: str = "analytic", capacity: int = 8,
                 helper_cores: tuple[int, ...] = (), shared: bool = False) -> None:
        """``helper_cores``: solve each batch with a helper thread spinning there
        (``server.helper``; the analytic solver only). ``shared``: solve through the
        helper's compiled code even with no thread (the server's warm path: a twin
        solved by other code would leave the rooms' solve cold)."""
        self.rig = rig
        self.solver = Solver(rig, solver)
        self.calibrations: dict[int, Calibration] = {}
        self._slot: dict[int, int] = {}
        self._has_bits: dict[int, int] = {}  # each avatar's devices (protocol.roles bits)
        J = rig.skeleton.num_joints
        self.tracking = TrackingRows(capacity)  # mounts, body model, targets per slot
        self._rotations = np.empty((capacity, J, 4))  # last solved pose (warm start)
        self._roots = np.empty((capacity, 3))
        self._offsets = np.empty((capacity, J, 3))  # each avatar's bone lengths
        self._iterations = np.zeros(capacity, dtype=np.int64)
        self.helper_cores = helper_cores if solver == "analytic" else ()
        self._shared = shared and solver == "analytic"
        self._helper: SolveHelper | None = None

    def warm_up(self) -> None:
        """Solve once now: loading the compiled solver and the tracking takes ~0.2 s, not
        the first frame's."""
        state = PoseBatch.canonical(self.rig, 1)
        gq, gp = forward_kinematics(self.rig.skeleton, state.rotations, state.root)
        eff = self.rig.effectors
        self.solver.solve(np.concatenate([gp[:, eff], gq[:, eff]], axis=-1), state)
        rows = TrackingRows(1)
        # the argument types a stage meets: a decoded frame's poses and the cached slot
        # index arrays are read-only, an evaluation's are not
        for writable in (True, False):
            poses, slots = np.zeros((0, 7)), np.zeros(0, dtype=np.intp)
            for frozen in (False, True):
                poses.flags.writeable = writable
                slots.flags.writeable = not frozen
                rows.stage(0, slots, poses, 0.0)
        rows.fill(np.zeros(1, dtype=np.intp))
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
            for name in ("_rotations", "_roots", "_offsets", "_iterations"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.empty_like(a)]))
            self.tracking.grow()
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
        self.tracking.calibrate(slot, cal)
        self._has_bits[avatar_id] = role_bits(self.devices(avatar_id))
        return cal

    def coding(self, avatar_id: int) -> PoseCoding:
        """How the avatar's frames travel (``protocol.pose_coding``): its driven joints,
        and the rotations it was calibrated with for the others."""
        return rig_coding(self.rig, self.calibrations[avatar_id].pose)

    def remove(self, avatar_id: int) -> None:
        self.calibrations.pop(avatar_id, None)
        self._slot.pop(avatar_id, None)
        self._has_bits.pop(avatar_id, None)

    def devices(self, avatar_id: int) -> tuple[str, ...]:
        """The devices the avatar uses (calibrated with, or mounted since)."""
        return lost_roles(self.tracking.has[self._slot[avatar_id]])

    def lost(self, avatar_id: int) -> NDArray[np.bool_]:
        """(ND,) in ``solver.tracking.devices`` order: the devices the avatar uses that
        its newest frame lacks."""
        return self.tracking.lost(self._slot[avatar_id])

    def stage(self, avatar_id: int, roles: tuple[str, ...], poses: Array,
              t: float = 0.0) -> tuple[int, tuple[str, ...]]:
        """Take a frame (poses (D, 7): position | quaternion, captured at ``t`` s) as the
        avatar's next; a newer frame replaces an older one. Any devices may be missing:
        returns the avatar's devices the frame lacks (``protocol.roles`` bits), and the
        devices it had not used before, which are mounted where the body was last
        solved. A room stages each frame as it arrives, while the rest of the burst is
        still coming in, so the solve itself only gathers rows."""
        slot = self._slot.get(avatar_id)
        if slot is None:
            raise NotCalibratedError(f"avatar {avatar_id} has not been calibrated: "
                                     "send a calibrate message (T-pose) first")
        slots = slots_of(roles)
        new: tuple[str, ...] = ()
        if not self.tracking.stage(slot, slots, poses, t):  # devices never seen before
            new = tuple(r for r, s in zip(roles, slots.tolist(), strict=True)
                        if not self.tracking.has[slot, s])
            for role in new:
                row = poses[roles.index(role)]
                self.tracking.mount(slot, role, mount_device(
                    self.rig, self._offsets[slot], self._rotations[slot], self._roots[slot],
                    role, row[:3], row[3:]))
            self._has_bits[avatar_id] = role_bits(self.devices(avatar_id))
            self.tracking.stage(slot, slots, poses, t)
        return self._has_bits[avatar_id] & ~_present_bits(roles), new

    def helper(self) -> SolveHelper | None:
        """The helper thread over the current arrays (started on first use), if any."""
        if self._helper is None and (self.helper_cores or self._shared):
            self._helper = SolveHelper(self.helper_cores, self._analytic_args(),
                                       len(self._roots), self.rig.skeleton.num_joints)
        return self._helper

    def close(self) -> None:
        """Stop the helper thread, if one runs (a later solve starts a new one)."""
        if self._helper is not None:
            self._helper.stop()
            self._helper = None

    def _analytic_args(self) -> tuple[object, ...]:
        t = self.tracking
        return (*self.solver.analytic_args(self._offsets, t.targets, t.weights,
                                           self._rotations, self._roots, self._iterations),
                t.filled, t.dev, t.present, t.has, t.t, t.shape, t.state)

    def solve_staged(self, avatar_ids: list[int]) -> PoseBatch:
        """Solve these avatars (each staged) as one batch, each warm-started from its last
        pose; their new poses in the order asked (new arrays: the next solve does not
        change them). Each frame's targets are made once (``TrackingRows.fill``)."""
        slot_list = [self._slot[a] for a in avatar_ids]
        t = self.tracking
        helper = self.helper() if slot_list else None
        if helper is not None:  # in place, wherever the rows are, with the helper (who
            # claims an avatar fills its targets, so the helper takes half of that too)
            n = len(slot_list)
            helper.rows[:n] = slot_list
            solve_analytic_shared(*helper.batch_args(n))
            slots = helper.rows[:n]
            return PoseBatch(self._rotations[slots], self._roots[slots],
                             self._iterations[slots])
        if slot_list:
            t.fill(np.array(slot_list, dtype=np.intp))
        first = slot_list[0] if slot_list else 0
        if slot_list == list(range(first, first + len(slot_list))):
            # side by side in slot order (a room's whole burst, sorted by slot): solve the
            # rows where they are, without gathering and scattering four arrays
            rows = slice(first, first + len(slot_list))
            state = PoseBatch(self._rotations[rows], self._roots[rows])
            self.solver.solve(t.targets[rows], state, self._offsets[rows], t.weights[rows])
            return PoseBatch(state.rotations.copy(), state.root.copy(), state.iterations)
        slots = np.array(slot_list, dtype=np.intp)
        state = PoseBatch(self._rotations[slots], self._roots[slots])
        self.solver.solve(t.targets[slots], state, self._offsets[slots], t.weights[slots])
        self._rotations[slots] = state.rotations
        self._roots[slots] = state.root
        return state

    def slot_order(self, avatar_id: int) -> int:
        """Where the avatar's rows are: a batch in this order solves in place."""
        return self._slot[avatar_id]

    def solve(self, frames: list[tuple[int, tuple[str, ...], Array]],
              t: float = 0.0) -> PoseBatch:
        """Solve the avatars of ``frames`` [(avatar id, roles, poses (D, 7): position |
        quaternion)], all captured at ``t``, as one batch: ``stage`` each, then
        ``solve_staged``."""
        for avatar_id, roles, poses in frames:
            self.stage(avatar_id, roles, poses, t)
        return self.solve_staged([avatar_id for avatar_id, _, _ in frames])
