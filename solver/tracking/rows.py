"""Avatars' tracking as rows of arrays: each avatar's mounts, body shape and tracking
state, the device poses of its newest frame, and the targets and weights the solver
takes. Staging a frame is a few array operations; ``fill`` makes the targets of any set
of rows in one compiled call."""

from __future__ import annotations

import functools
from collections.abc import Iterable

import numpy as np
from numba import njit
from numpy.typing import NDArray

from posecast.solver.calibration import Calibration, Mount
from posecast.solver.kernels import bone_target_row
from posecast.solver.tracking.body_model import SHIPPED, BodyModel
from posecast.solver.tracking.devices import DEVICES, ELBOW_L, KNEE_R, SLOT
from posecast.solver.tracking.fill import fill_batch, new_state
from posecast.solver.tracking.layout import ND, SHAPE_SIZE, STATE_SIZE
from posecast.solver.tracking.shape import body_shape, bone_poses

Array = NDArray[np.float64]


@njit(cache=True)
def stage_row(row, slots, poses, t, dev, present, has, mount_p, mount_q, times, filled):
    """``TrackingRows.stage`` over the arrays: each mounted device's bone pose through its
    mount (an elbow's or knee's: its own position and its mount, which it steers by),
    the present flags and the time; the row is due a fill. False if the frame has a
    device not mounted."""
    filled[row] = False
    for d in range(present.shape[1]):
        present[row, d] = False
    every = True
    for i in range(slots.shape[0]):
        s = slots[i]
        if not has[row, s]:
            every = False
            continue
        present[row, s] = True
        if ELBOW_L <= s <= KNEE_R:
            for k in range(3):
                dev[row, s, k] = poses[i, k]
                dev[row, s, 3 + k] = mount_p[row, s, k]
            dev[row, s, 6] = 0.0
        else:
            bone_target_row(poses, i, mount_p[row], mount_q[row], s, dev[row], s)
    times[row] = t
    return every


@functools.lru_cache(maxsize=256)  # bounded: the roles come from clients
def slots_of(roles: tuple[str, ...]) -> NDArray[np.intp]:
    """The slot of each role of a frame (read-only; cached: a player sends the same roles
    every frame)."""
    index = np.array([SLOT[r] for r in roles], dtype=np.intp)
    index.flags.writeable = False
    return index


class TrackingRows:
    """The tracking of up to ``capacity`` avatars (grows by doubling)."""

    def __init__(self, capacity: int = 8) -> None:
        self.dev = np.zeros((capacity, ND, 7))  # this frame's bone poses from devices
        self.present = np.zeros((capacity, ND), dtype=np.bool_)
        self.has = np.zeros((capacity, ND), dtype=np.bool_)  # mounted: the avatar's set
        self.t = np.zeros(capacity)
        self.shape = np.zeros((capacity, SHAPE_SIZE))
        self.state = np.zeros((capacity, STATE_SIZE))
        self.targets = np.zeros((capacity, ND, 7))
        self.weights = np.zeros((capacity, ND))
        self.mount_p = np.zeros((capacity, ND, 3))
        self.mount_q = np.tile([0.0, 0.0, 0.0, 1.0], (capacity, ND, 1))
        # the targets and weights are of the row's staged frame: ``fill`` skips it
        self.filled = np.zeros(capacity, dtype=np.bool_)

    _ARRAYS = ("dev", "present", "has", "t", "shape", "state", "targets", "weights",
               "mount_p", "mount_q", "filled")

    @property
    def capacity(self) -> int:
        return int(self.t.shape[0])

    def grow(self) -> None:
        for name in self._ARRAYS:
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, a.copy()]))

    def calibrate(self, row: int, cal: Calibration, devices: Iterable[str] | None = None,
                  floor: float = 0.0, naive: bool = False, first: Array | None = None,
                  model: BodyModel = SHIPPED) -> None:
        """Row ``row`` tracks an avatar of this calibration from now on, with the devices
        it has mounts for (or those of ``devices`` it has). ``first`` (ND, 7): the bone
        poses the devices give when tracking starts, where they differ from the
        calibration pose's (a mocap clip's first frame); ``naive``: the baseline model;
        ``model``: the body model's constants."""
        self.has[row] = False
        self.present[row] = False
        self.filled[row] = False
        for name in cal.mounts if devices is None else devices:
            if name in cal.mounts:
                self.mount(row, name, cal.mounts[name])
        self.shape[row] = body_shape(cal.rig, cal.offsets, cal.pose, cal.root, floor,
                                     naive, model)
        start = bone_poses(cal.rig, cal.offsets, cal.pose, cal.root)
        if first is not None:
            start[self.has[row]] = first[self.has[row]]
        self.state[row] = new_state(self.shape[row], start, self.has[row])

    def mount(self, row: int, device: str, mount: Mount) -> None:
        """The avatar of ``row`` uses ``device`` through ``mount`` (a device that first
        appears after calibration is mounted when it does)."""
        s = SLOT[device]
        self.has[row, s] = True
        self.mount_p[row, s] = mount.position
        self.mount_q[row, s] = mount.rotation

    def stage(self, row: int, slots: NDArray[np.intp], poses: Array, t: float) -> bool:
        """A frame's device poses (n, 7) at ``slots``, taken at time ``t`` (s), as the
        row's next frame; devices the avatar has not mounted are left out (False when
        the frame has any). One compiled call: a server stages every frame it reads."""
        return bool(stage_row(row, slots, poses, t, self.dev, self.present, self.has,
                              self.mount_p, self.mount_q, self.t, self.filled))

    def lost(self, row: int) -> NDArray[np.bool_]:
        """(ND,) the devices the avatar uses that its newest frame lacks."""
        return self.has[row] & ~self.present[row]

    def fill(self, rows: NDArray[np.intp]) -> None:
        """The targets and weights of these rows from their staged frames: once a frame
        (a row filled since its last ``stage`` is left as it is), whichever thread of a
        shared solve (``solver.ik.shared``) or repeated solve asks."""
        fill_batch(rows, self.filled, self.dev, self.present, self.has, self.t, self.shape,
                   self.state, self.targets, self.weights)


def lost_roles(lost: NDArray[np.bool_]) -> tuple[str, ...]:
    return tuple(DEVICES[i] for i in np.flatnonzero(lost))
