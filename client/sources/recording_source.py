"""``posecast play --record FILE``: another source's raw device poses kept in the Vive
recording format (docs/vive-format.md), so that a session can be solved again later with
``posecast eval FILE`` or replayed with ``play --source vive:FILE``.

Frame 0 is the calibration T-pose, as the format wants; then every sample the player
reads. The format has one set of devices for the whole file: a sample without one of the
first frame's devices (a tracker that lost tracking) is left out and counted. The format
has no timestamps either: its frames are read as 90 Hz apart, so a source at another rate
is said once. Each frame is written and flushed whole.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import IO

import numpy as np

from posecast.client.sources.base import DeviceSample, PoseSource
from posecast.solver.readers.vive import HEADER, TAGS, file_tags, format_vive_frame

log = logging.getLogger(__name__)

FORMAT_RATE_HZ = 90.0  # what the format's readers take its frames to be


class RecordingSource:
    """``source`` as it is, its samples also written to ``path`` (a new file)."""

    def __init__(self, source: PoseSource, path: Path) -> None:
        self.source = source
        self.path = path
        self.rate_hz = source.rate_hz
        self.frames = 0
        self.skipped = 0  # samples lacking a device of the first frame
        self._file: IO[str] = open(path, "x", encoding="ascii")  # noqa: SIM115 (close())
        self._tags: list[str] | None = None
        self._order: dict[tuple[str, ...], list[int] | None] = {}

    def calibration(self) -> DeviceSample:
        sample = self.source.calibration()
        if self._tags is None:  # the first T-pose is frame 0; a recalibration is not kept
            self._tags = file_tags(sample.roles)
            self._file.write(" ".join(HEADER) + "\n")
            self._write(sample)
            if abs(self.rate_hz - FORMAT_RATE_HZ) > 0.5:
                log.warning("%s: recording at %g Hz, but Vive recordings are read as "
                            "%g Hz", self.path, self.rate_hz, FORMAT_RATE_HZ)
        return sample

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        if sample is not None and self._tags is not None:
            self._write(sample)
        return sample

    def _write(self, sample: DeviceSample) -> None:
        if sample.roles not in self._order:  # new roles: where the file's devices are
            wanted = [TAGS[t] for t in self._tags or ()]
            self._order[sample.roles] = ([sample.roles.index(r) for r in wanted]
                                         if all(r in sample.roles for r in wanted) else None)
        order = self._order[sample.roles]
        if order is None:
            self.skipped += 1
            return
        self._file.write(format_vive_frame(self._tags or [], np.asarray(sample.poses)[order]))
        self._file.flush()
        self.frames += 1

    def close(self) -> None:
        self._file.close()
        self.source.close()
