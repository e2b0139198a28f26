"""Replays a Vive tracker recording (the format of ``../shared/data/vive``) as a pose source.

Frame 0 of a recording is the player's T-pose, so it is the calibration sample; ``read``
then gives frames 1, 2, ... one per call (the player paces the calls at ``rate_hz``), and
either ends or, looped, starts again at frame 1. Device names in the recordings are the
roles already (``solver.motion.VIVE_DEVICES``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posecast.client.sources.base import ROLES, DeviceSample, SourceError, now
from posecast.solver.readers.vive import VIVE_FPS, read_vive


class ViveFileSource:
    """A Vive recording replayed frame by frame; see the module docstring."""

    def __init__(self, path: str | Path, loop: bool = False, rate_hz: float = VIVE_FPS) -> None:
        if not rate_hz > 0.0:
            raise SourceError(f"rate must be a positive number of Hz, got {rate_hz}")
        try:
            rec = read_vive(path)  # a FormatError (file, line, what) propagates as it is
        except OSError as err:
            raise SourceError(f"{path}: cannot read the recording: {err.strerror}") from None
        if rec.num_frames < 2:
            raise SourceError(f"{path}: a recording needs a calibration frame and at least "
                              f"one more, found {rec.num_frames}")
        order = [rec.device(r) for r in ROLES if r in rec.devices]  # one role order everywhere
        self.roles = tuple(rec.devices[d] for d in order)
        # every frame's rows as a player sends them (position | quaternion)
        self.poses = np.concatenate([rec.positions[:, order], rec.rotations[:, order]],
                                    axis=2)
        self.rate_hz = float(rate_hz)
        self.loop = loop
        self.next_frame = 1

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    def _sample(self, f: int) -> DeviceSample:
        return DeviceSample(now(), self.roles, self.poses[f].copy())

    def calibration(self) -> DeviceSample:
        return self._sample(0)

    def read(self) -> DeviceSample | None:
        if self.next_frame >= self.num_frames:
            if not self.loop:
                return None
            self.next_frame = 1  # frame 0 is the T-pose, not part of the motion
        sample = self._sample(self.next_frame)
        self.next_frame += 1
        return sample

    def close(self) -> None:
        pass
