"""What a viewer reports to the server of the frames it presented (ViewerReport), so that
the server's /metrics holds every spectator's presentation latency: the browser page's
(client/web/src/report.js), a headset's and the desktop and headless viewers'.

Each avatar-frame counts once, when it is first presented: its capture time (server
clock, from the batch), when its batch reached the viewer's process and when the frame
was presented (local clock, converted to the server clock as the report is taken, both
with the same offset: presented never precedes received). A busier room is sampled (a
reservoir of MAX_REPORT_ROWS rows a report), so that every frame is equally likely to be
in the server's histograms however many avatars there are.

A report also carries a few avatars as they were presented (ShownPose, a reservoir of
MAX_REPORT_POSES over every avatar of every frame), from which the server measures the
display error in its /metrics (``server.display_error``).
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

import numpy as np

from posecast.protocol import ClockEstimator, ShownPose, ViewerReport
from posecast.protocol.messages import MAX_REPORT_POSES, MAX_REPORT_ROWS

if TYPE_CHECKING:
    from posecast.client.headset.view import HeadsetFrameDone

REPORT_INTERVAL_S = 0.5  # as the browser page's: the server takes 4 a second


class Reports:
    """A viewer's figures for the server, added by its frame loop and taken by whatever
    sends them (a headset's frame loop runs on a thread of its own: hence the lock)."""

    def __init__(self, viewer: str, seed: int = 0) -> None:
        self._lock = threading.Lock()
        self._pose_to_submit: list[float] = []
        self._rows: list[tuple[float, float, float]] = []  # t_capture (server), local x2
        self._seen = 0
        # (avatar id, t_presented local, root, rotations) of avatars as presented
        self._shown: list[tuple[int, float, np.ndarray, np.ndarray]] = []
        self._shown_seen = 0
        self._random = np.random.default_rng(seed)
        self.viewer = viewer  # ViewerReport.viewer: desktop, headset
        self.mode: str | None = None  # the playout mode the shown poses come from
        self.sent = 0
        self.enabled = True

    def headset_frame(self, done: HeadsetFrameDone) -> None:
        """A headset frame (``HeadsetView``'s ``on_frame``): its timings and the others
        as shown."""
        self.add(done.pose_to_submit, done.first, done.t_presented)
        if done.shown and done.mode is not None:
            ids, roots, rotations = zip(*done.shown, strict=True)
            self.show(done.mode, list(ids), list(roots), list(rotations), done.t_presented)

    def show(self, mode: str, avatar_ids: list[int], roots: list[np.ndarray],
             rotations: list[np.ndarray], t_presented: float) -> None:
        """The avatars a frame presented at ``t_presented`` (local), in playout
        ``mode``: each equally likely to be one of the report's shown poses. The
        arrays are kept as they are: a viewer's sampled poses are never written to."""
        with self._lock:
            if mode != self.mode:  # poses of the old mode are not this report's
                self.mode, self._shown, self._shown_seen = mode, [], 0
            for avatar_id, root, rot in zip(avatar_ids, roots, rotations, strict=True):
                self._shown_seen += 1
                if len(self._shown) < MAX_REPORT_POSES:
                    self._shown.append((avatar_id, t_presented, root, rot))
                    continue
                k = int(self._random.integers(self._shown_seen))
                if k < MAX_REPORT_POSES:
                    self._shown[k] = (avatar_id, t_presented, root, rot)

    def add(self, pose_to_submit: float | None, first: list[tuple[float, float]],
            t_presented: float) -> None:
        """One presented frame: ``first`` (t_capture on the server clock, t_received
        local) of the avatar-frames it showed for the first time; ``pose_to_submit`` a
        headset frame's (None for a screen's)."""
        with self._lock:
            if pose_to_submit is not None and len(self._pose_to_submit) < MAX_REPORT_ROWS:
                self._pose_to_submit.append(min(max(pose_to_submit, 0.0), 1.0))
            for t_capture, t_received in first:
                self._seen += 1
                row = (t_capture, t_received, t_presented)
                if len(self._rows) < MAX_REPORT_ROWS:
                    self._rows.append(row)
                else:
                    k = int(self._random.integers(self._seen))
                    if k < MAX_REPORT_ROWS:
                        self._rows[k] = row

    def stop_if_refused(self, last_error: str | None) -> bool:
        """Stop reporting once the server refused a report (its last error names
        viewer_report: a server before protocol 1, or before a headset's
        pose_to_submit); True if it did."""
        if "viewer_report" in (last_error or ""):
            self.enabled = False
        return not self.enabled

    def take(self, clock: ClockEstimator) -> ViewerReport | None:
        """The report of what was added since the last, on the server clock; None when
        there is nothing (or the clock is not synced: rows then wait)."""
        with self._lock:
            if not (self._pose_to_submit or self._rows or self._shown) or not clock.synced:
                return None
            durations, rows, shown = self._pose_to_submit, self._rows, self._shown
            self._pose_to_submit, self._rows, self._seen = [], [], 0
            self._shown, self._shown_seen = [], 0
        offset = clock.offset  # one offset for both columns: presented never precedes
        table = np.array(rows, dtype=np.float64).reshape(-1, 3)
        return ViewerReport(t_capture=table[:, 0], t_received=table[:, 1] + offset,
                            t_presented=table[:, 2] + offset,
                            pose_to_submit=np.array(durations, dtype=np.float64)
                            if durations else None,
                            shown=tuple(ShownPose(avatar_id=a, t_presented=t + offset,
                                                  root=root, rotations=rot)
                                        for a, t, root, rot in shown),
                            viewer=self.viewer, mode=self.mode)  # type: ignore[arg-type]
