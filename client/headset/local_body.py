"""The player's own avatar, solved on the player's machine from the poses of the frame.

The paper's low-latency path: the body the player sees of themself is solved from the
very poses the frame is drawn with (the compositor's, predicted for when the frame
reaches the eyes), not from what comes back from the server a round trip later. It is
the server's own solver state (``server.avatars.AvatarSolver``, the same rig, solver and
calibration), so the body the player sees and the one everyone else sees agree: from
the same T-pose and poses they are the same rotations (a test holds them to it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.client.sources.base import DeviceSample
from posecast.protocol import AvatarInfo
from posecast.protocol.roles import DEVICE_ROLES
from posecast.server.avatars import AvatarSolver
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig

Array = NDArray[np.float64]
SELF = 0  # the one avatar's id in the local solver


@dataclass(frozen=True)
class SolvedBody:
    rotations: Array  # (J, 4) local joint rotations, the skeleton's joint order
    root: Array  # (3,) the root joint's position


class LocalBody:
    """Calibrate once from the T-pose the player sent, then solve every frame."""

    def __init__(self, rig: Rig | None = None, solver: str = "analytic") -> None:
        self.rig = rig or build_rig(load_makehuman().skeleton)
        self._avatars = AvatarSolver(self.rig, solver, capacity=1)
        self.info: AvatarInfo | None = None
        self.tpose: DeviceSample | None = None  # what it was calibrated with

    def warm_up(self) -> None:
        """Load the compiled solver now, not in the first frame."""
        self._avatars.warm_up()

    @property
    def calibrated(self) -> bool:
        return self.info is not None

    def calibrate(self, tpose: DeviceSample, avatar_id: int, name: str) -> AvatarInfo:
        """Calibrate from the T-pose sample (ValueError as the server's for a pose that
        is none); the skeleton as the server's roster describes it."""
        cal = self._avatars.calibrate(SELF, tpose.roles, tpose.positions, tpose.rotations)
        sk = self.rig.skeleton
        devices = self._avatars.devices(SELF)
        self.info = AvatarInfo(
            avatar_id=avatar_id, display_name=name, joint_names=sk.names,
            parents=tuple(int(p) for p in sk.parents), rest_offsets=cal.offsets,
            devices=tuple(r for r in DEVICE_ROLES if r in devices))
        self.tpose = tpose
        return self.info

    def solve(self, sample: DeviceSample) -> SolvedBody:
        """The body for this frame's poses (any subset of the devices: those missing are
        carried on as the server does)."""
        if self.info is None:
            raise RuntimeError("solve before calibrate")
        self._avatars.stage(SELF, sample.roles, sample.poses, sample.t_capture)
        state = self._avatars.solve_staged([SELF])
        return SolvedBody(state.rotations[0].copy(), state.root[0].copy())

    def close(self) -> None:
        self._avatars.close()
