"""A source's devices narrowed to a tracker set and losing some at random
(``play --devices SET --dropouts SPEC``): what a player with fewer trackers, or with
trackers hidden from the base stations now and then, would send. A lost device is left
out of the frame, exactly as the OpenVR source leaves out a device that is not tracked."""

from __future__ import annotations

import numpy as np

from posecast.client.sources.base import DeviceSample, PoseSource
from posecast.solver.tracking.dropouts import DropoutSchedule, DropoutSpec


class TrackerSetSource:
    """``source`` with only the ``devices`` given (None: all it has), each but the head
    lost as ``dropouts`` says (None: never), counted from the first frame read."""

    def __init__(self, source: PoseSource, devices: tuple[str, ...] | None = None,
                 dropouts: DropoutSpec | None = None) -> None:
        self.source = source
        self.devices = devices
        self.rate_hz = source.rate_hz
        self.schedule = DropoutSchedule(dropouts) if dropouts is not None else None
        self._t0: float | None = None

    def _kept(self, sample: DeviceSample, lose: bool) -> DeviceSample:
        t = sample.t_capture
        if self._t0 is None:
            self._t0 = t
        keep = [i for i, r in enumerate(sample.roles)
                if (self.devices is None or r in self.devices)
                and not (lose and self.schedule is not None
                         and self.schedule.lost(r, t - self._t0))]
        if len(keep) == len(sample.roles):
            return sample
        index = np.array(keep, dtype=np.intp)
        return DeviceSample(t, tuple(sample.roles[i] for i in keep), sample.poses[index])

    def calibration(self) -> DeviceSample:
        """The T-pose with the set's devices (nothing is lost for it)."""
        return self._kept(self.source.calibration(), lose=False)

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        return None if sample is None else self._kept(sample, lose=True)

    def close(self) -> None:
        self.source.close()
