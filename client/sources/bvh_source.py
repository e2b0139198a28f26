"""Simulated trackers from a motion-capture (BVH) file: a player without VR hardware.

Devices sit on the performer's joints as the trackers of ``posecast eval`` do
(``solver.evaluation.evaluate_bvh``): the hip on the pelvis joint, hands and feet on their
joints, each at that joint's global pose; a knee device on the knee (shin joint) and a
forearm device halfway along the forearm, where a strap holds it. The head device is a
headset: rigidly on the head joint but at the eyes (``calibrate``'s prior
``EYE_FROM_HEAD_JOINT``), because calibration sizes the avatar by putting its eyes at the
HMD; a device on the head joint itself made the built-in walker's avatar 4% too small and
its hanging arms up to 8 cm short of the hands.

The calibration sample is the performer's T-pose: the skeleton's canonical pose (arms
sideways, legs straight; ``solver.rig``) turned to the heading of the first motion frame
and standing where the first frame stands. Floors: the clip is shifted so that the lowest
joint of its first motion frame is at y = 0, and the T-pose's lowest joint likewise: the
convention of ``solver.calibration.calibrate``, which stands the avatar's lowest joint on
y = 0. Joints are inside the feet, so a file whose floor is the sole (Bandai: toes 4.2 cm
up) moves down by those centimetres, every frame alike.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numba import njit, types
from numpy.typing import NDArray

from posecast.client.sources.base import ROLES as ALL_ROLES
from posecast.client.sources.base import DeviceSample, SourceError, now
from posecast.solver import rotations as R
from posecast.solver.calibration import EFFECTOR_DEVICES, EYE_FROM_HEAD_JOINT
from posecast.solver.evaluation import _reference_pose
from posecast.solver.fk import forward_kinematics
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.vive import VIVE_FPS
from posecast.solver.rig import EFFECTORS, Rig, build_rig, global_pose

Array = NDArray[np.float64]

# device -> (joint role it is on, joint role it lies toward or None): eval's trackers plus
# forearms and knees
DEVICE_JOINTS: dict[str, tuple[str, str | None]] = {
    **{dev: (joint, None) for dev, joint in zip(EFFECTOR_DEVICES, EFFECTORS, strict=True)},
    "left_forearm": ("forearm_l", "hand_l"), "right_forearm": ("forearm_r", "hand_r"),
    "left_knee": ("shin_l", None), "right_knee": ("shin_r", None),
}
FOREARM_AT = 0.5  # fraction of the way from elbow to wrist
# the devices simulated: a full Vive rig (head, controllers, the seven tracker roles of
# the paper authors' recordings); a chest tracker is rare, eval simulates it on request
ROLES = tuple(r for r in ALL_ROLES if r != "chest")


class BvhSource:
    """Simulated trackers on a BVH performer; see the module docstring."""

    def __init__(self, path: str | Path, loop: bool = False,
                 rate_hz: float | None = None, offset: tuple[float, float] = (0.0, 0.0),
                 start_frame: int = 0, smooth: bool = False,
                 devices: tuple[str, ...] | None = None) -> None:
        """``smooth``: sample the clip between its frames at the read's instant (position
        lerp, rotation slerp) instead of at the nearest frame, as a headset samples a
        body: at 90 Hz from 120 fps, nearest frames step 1, 2, 1 frames apart, a body
        whose speed jumps +-50% every sample, which no velocity-based prediction
        follows (the demo's display error)."""
        try:
            motion = read_bvh(path)  # a FormatError (file, line, what) propagates as it is
        except OSError as err:
            raise SourceError(f"{path}: cannot read the motion file: {err.strerror}") from None
        frames = slice(motion.first_frame, motion.num_frames)
        rot, trans = motion.rotations[frames], motion.translations[frames]
        if rot.shape[0] < 1:
            raise SourceError(f"{path}: no motion frames after the bind pose")
        # the performer as evaluate_bvh sees them: first motion frame's bones, canonical rig
        self.skeleton = motion.skeleton.with_offsets(trans[0])
        self.rig = build_rig(self.skeleton, _reference_pose(motion))
        self._body = sorted({j for joints in self.rig.roles.values() for j in joints})
        canon_q, canon_p = global_pose(self.skeleton, self.rig.canonical)
        # canonical pose: body axes = world axes, so the eye offset is in world coordinates
        head = self.rig.role("head")
        self.hmd_offset = R.rotate(R.conjugate(canon_q[head]), EYE_FROM_HEAD_JOINT)
        gq, gp = forward_kinematics(self.skeleton, rot, trans[:, 0], trans)
        gp[..., 1] -= gp[0, self._body, 1].min()  # the first frame stands on y = 0
        positions, rotations = self._devices(gq, gp)
        tq, tp = self._place_tpose(canon_q, canon_p, gp[0])
        self.tpose_positions, self.tpose_rotations = (a[0] for a in self._devices(tq, tp))
        # several players replaying one clip stand apart and move out of step
        shift = np.array([offset[0], 0.0, offset[1]])
        self.tpose_positions = self.tpose_positions + shift
        # every frame's rows as a player sends them (position | quaternion), of the
        # devices asked for (``devices``: a tracker set; the rest are never simulated)
        self.roles = ROLES if devices is None else tuple(r for r in ROLES if r in devices)
        keep = [ROLES.index(r) for r in self.roles]
        self.tpose_positions = self.tpose_positions[keep]
        self.tpose_rotations = self.tpose_rotations[keep]
        self.poses = np.concatenate([positions + shift, rotations], axis=2)[:, keep]
        self._frames = int(self.poses.shape[0])
        # a headset samples at its own rate (90 Hz for a Vive), not the capture's: replay
        # at rate_hz by stepping through the clip by time, nearest frame
        self.rate_hz = float(rate_hz or motion.fps)
        self._step = float(motion.fps) / self.rate_hz
        self.loop = loop
        self.smooth = smooth
        if smooth:  # each frame's step to the next, for a read between them in 3 numpy calls
            self._delta = self._steps_to_next()
        self.next_frame = start_frame % self.num_frames
        self._position = float(self.next_frame)

    def _devices(self, gq: Array, gp: Array) -> tuple[Array, Array]:
        """Device positions (F, D, 3) and rotations (F, D, 4), ROLES order, from global
        joint rotations (F, J, 4) and positions (F, J, 3)."""
        pos = np.empty((gq.shape[0], len(ROLES), 3))
        rot = np.empty((gq.shape[0], len(ROLES), 4))
        for d, name in enumerate(ROLES):
            joint, toward = DEVICE_JOINTS[name]
            j = self.rig.role(joint)
            pos[:, d] = gp[:, j]
            if toward is not None:
                pos[:, d] += FOREARM_AT * (gp[:, self.rig.role(toward)] - gp[:, j])
            if name == "head":
                pos[:, d] += R.rotate(gq[:, j], self.hmd_offset)
            rot[:, d] = gq[:, j]
        return pos, rot

    def _place_tpose(self, cq: Array, cp: Array, first: Array) -> tuple[Array, Array]:
        """The canonical pose's global joint poses (1, J, 4/3), turned to the first frame's
        heading, its pelvis over the first frame's, its lowest joint on y = 0."""
        yaw = _heading(self.rig, first)
        cq, cp = R.mul(yaw, cq), R.rotate(yaw, cp)
        pelvis = self.rig.role("pelvis")
        cp += np.array([first[pelvis, 0] - cp[pelvis, 0], -cp[self._body, 1].min(),
                        first[pelvis, 2] - cp[pelvis, 2]])
        return cq[None], cp[None]

    @property
    def num_frames(self) -> int:
        """Motion frames (a file's bind-pose frame excluded)."""
        return self._frames

    def calibration(self) -> DeviceSample:
        return DeviceSample.of(now(), self.roles, self.tpose_positions, self.tpose_rotations)

    def read(self) -> DeviceSample | None:
        # 16 demo players each read 90 times a second on one core: locals, not properties
        frames = self._frames
        if self.next_frame >= frames:
            if not self.loop:
                return None
            self.next_frame = 0
        f = self.next_frame
        at = self._position
        position = at + self._step
        if self.loop and round(position) >= frames:
            position -= frames
        self._position = position
        self.next_frame = round(position)
        if self.smooth:
            return DeviceSample(now(), self.roles, self._between(at))
        return DeviceSample(now(), self.roles, self.poses[f].copy())

    def _steps_to_next(self) -> Array:
        """(F, D, 7): each frame's rows subtracted from the next frame's (the last's next:
        the first when looping, else itself), quaternions taken on the same hemisphere."""
        following = np.roll(self.poses, -1, axis=0)
        if not self.loop:
            following[-1] = self.poses[-1]
        flip = np.sum(self.poses[..., 3:] * following[..., 3:], axis=-1) < 0.0
        following[..., 3:][flip] *= -1.0
        return following - self.poses

    def _between(self, at: float) -> Array:
        """The rows at fractional frame ``at`` (new): a lerp of positions and a normalised
        lerp of rotations between its two frames. Neighbouring frames' rotations are a few
        degrees apart, where slerp differs from it by under 0.01 deg and costs ~10x as
        much."""
        frames = self._frames
        if self.loop:  # just before the wrap, a read's position is a little below 0
            at %= frames
        i = min(max(int(at), 0), frames - 1)
        return _lerp_rows(self.poses, self._delta, i, min(max(at - i, 0.0), 1.0))

    def close(self) -> None:
        pass


def tracker_recording(path: str | Path, seconds: float,
                      rate_hz: float = VIVE_FPS) -> ViveRecording:
    """A clip's simulated trackers as a Vive recording: frame 0 the T-pose (the
    calibration sample, as in the paper authors' files), then ``seconds`` of motion."""
    source = BvhSource(path, rate_hz=rate_hz)
    frames = [np.concatenate([source.tpose_positions, source.tpose_rotations], axis=1)]
    while len(frames) <= round(seconds * rate_hz) and (sample := source.read()) is not None:
        frames.append(sample.poses)
    poses = np.stack(frames)
    return ViveRecording(devices=ROLES, positions=np.ascontiguousarray(poses[..., :3]),
                         rotations=np.ascontiguousarray(poses[..., 3:]), fps=rate_hz,
                         source=str(path))


def _heading(rig: Rig, gp: Array) -> Array:
    """Yaw (quaternion) turning the canonical facing (+z, left +x) to a pose's facing,
    from the pose's global joint positions (J, 3)."""
    left = gp[rig.role("thigh_l")] - gp[rig.role("thigh_r")]
    left[1] = 0.0
    x = R.normalize_vec(left)
    y = np.array([0.0, 1.0, 0.0])
    return R.from_matrix(np.stack([x, y, np.cross(x, y)], axis=1))


_FRAMES = types.Array(types.float64, 3, "A", readonly=True)


@njit(types.float64[:, ::1](_FRAMES, _FRAMES, types.int64, types.float64), cache=True)
def _lerp_rows(poses: NDArray[np.float64], delta: NDArray[np.float64], i: int, w: float
               ) -> Array:
    """poses[i] + w * delta[i], each row's quaternion normalised: in one compiled pass, as
    16 demo players each read 90 times a second on the clients' one core (numpy's five
    calls took ~10 us a read, a quarter of the players' process, and spread a tick's
    frames over more of the server's bursts)."""
    rows = np.empty((poses.shape[1], 7))
    for d in range(poses.shape[1]):
        for c in range(7):
            rows[d, c] = poses[i, d, c] + w * delta[i, d, c]
        inv = 1.0 / math.sqrt(rows[d, 3] ** 2 + rows[d, 4] ** 2 + rows[d, 5] ** 2
                              + rows[d, 6] ** 2)
        for c in range(3, 7):
            rows[d, c] *= inv
    return rows
