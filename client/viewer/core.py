"""One viewer frame, shared by the window and the headless renderer.

``Viewer.draw(now)`` samples the scene at local time ``now``, poses every avatar (one FK
call), picks the camera of the view, draws avatars, grid, name labels and HUD into the
renderer's target; the caller then makes the frame visible (swap buffers, or read the
pixels back) and calls ``presented`` with the time that happened, which records

- ``capture_to_render``: present time - the capture instant of the pose drawn, per avatar
  per frame, on the server clock (only once the connection's clock is synced). In
  interpolation mode it includes the playout delay, by design: it is what the viewer sees.
- ``receive_to_render``: present time - arrival of the avatar's newest frame, once per
  frame received (local clock): how long a received pose waits to reach the screen.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from posecast.client.measure.latency import LatencyRecorder
from posecast.client.measure.reports import REPORT_INTERVAL_S, Reports
from posecast.client.viewer.camera import Camera, OrbitCamera
from posecast.client.viewer.interpolation import Mode
from posecast.client.viewer.marker import MARKER_JOINTS, MarkerOverlay, marker_centres
from posecast.client.viewer.overlay import (
    TextItem,
    TextOverlay,
    hud_lines,
    label_items,
    label_text,
)
from posecast.client.viewer.renderer import PosedScene, Renderer, avatar_color
from posecast.client.viewer.scene import (
    SceneFrame,
    SpectatorScene,
    ViewMode,
    view_camera,
    view_target,
)
from posecast.protocol import encode

HUD_REFRESH_S = 0.25  # the HUD's numbers change this often (readable, and cheap)
HUD_WINDOW = 2000  # latency samples per stage the HUD's percentiles look back over
FRAMING_SMOOTHING = 0.15  # auto-framing moves this fraction of the way each frame


@dataclass
class ViewerStats:
    """What a viewer presented. Latencies in seconds (``as_json``: milliseconds)."""

    frames: int = 0
    avatar_frames: int = 0  # avatars drawn, summed over frames
    files: list[Path] = field(default_factory=list)
    latency: LatencyRecorder = field(default_factory=LatencyRecorder)
    frame_seconds: list[float] = field(default_factory=list)  # draw + read back, per frame

    def frame_ms(self) -> dict[str, float]:
        if not self.frame_seconds:
            return {}
        t = np.asarray(self.frame_seconds) * 1e3
        return {"p50": float(np.percentile(t, 50)), "p99": float(np.percentile(t, 99))}

    def as_json(self) -> dict[str, object]:
        return {"frames": self.frames, "avatar_frames": self.avatar_frames,
                "frame_ms": self.frame_ms(), "latency_ms": self.latency.summary()}


@dataclass
class DrawnFrame:
    scene: SceneFrame
    posed: PosedScene
    camera: Camera
    t_drawn: float  # local clock, when drawing started


class Viewer:
    """Draws a SpectatorScene with a Renderer; see the module docstring."""

    def __init__(self, renderer: Renderer, scene: SpectatorScene,
                 orbit: OrbitCamera | None = None, view: ViewMode = ViewMode.ORBIT,
                 player: int | None = None, labels: bool = True, hud: bool = True,
                 auto_frame: bool = True, marker: str | None = None) -> None:
        self.renderer = renderer
        self.scene = scene
        self.orbit = orbit or OrbitCamera()
        self.view = view
        self.player = player  # avatar id for first-person and mirror views
        self.labels, self.hud = labels, hud
        self.auto_frame = auto_frame  # keep every avatar in the orbit camera's view
        self.overlay = TextOverlay(renderer.ctx) if (labels or hud) else None
        # view --marker: a pattern on this joint (mesh order) for latency-video to follow
        self.marker = (None if marker is None else
                       renderer.mesh.skeleton.index(MARKER_JOINTS.get(marker, marker)))
        self.markers = MarkerOverlay(renderer.ctx) if marker is not None else None
        self.stats = ViewerStats()
        self._presents: deque[float] = deque(maxlen=240)
        self._hud_text = ""
        self._hud_at = -math.inf
        self._counted: dict[int, int] = {}  # avatar id -> seq whose arrival was recorded
        # what it presented, for the server's /metrics (as the browser page and a
        # headset report theirs): sent from the frame loop, twice a second
        self.reports = Reports("desktop")
        self._reported_at = -math.inf

    def warm_up(self) -> None:
        """Compile every shader now (see Renderer.warm_up), not in the first frame."""
        r = self.renderer
        r.warm_up()
        if self.overlay is not None:
            self.overlay.draw([TextItem("posecast", 0, 0)], r.width, r.height)
            r.ctx.finish()

    @property
    def aspect(self) -> float:
        return self.renderer.width / self.renderer.height

    def draw(self, now: float) -> DrawnFrame:
        """Draw the scene as it is at local time ``now`` into the renderer's target."""
        frame = self.scene.frame(now)
        target = view_target(self.view, frame.ids, self.player)
        for b, d in enumerate(frame.draws):
            d.hide_head = b == target and self.view is ViewMode.FIRST_PERSON
        r = self.renderer
        posed = r.pose(frame.draws)
        if self.auto_frame and self.view is ViewMode.ORBIT and len(posed):
            self._follow(posed)
        camera = view_camera(self.view, self.orbit, posed, target, r.head_joint, self.aspect)
        r.render(posed, camera)
        if self.overlay is not None:
            items: list[TextItem] = []
            if self.labels and len(posed):
                shown = [b for b in range(len(posed)) if b != target
                         or self.view is ViewMode.ORBIT]
                tops = r.head_tops(posed)[shown]
                names = [label_text(frame.draws[b].avatar.info.display_name,
                                    self.scene.lost(frame.ids[b])) for b in shown]
                items += label_items(names, [avatar_color(frame.ids[b]) for b in shown],
                                     tops, camera, r.width, r.height)
            if self.hud:
                items.append(TextItem(self._hud(now, len(frame)), 10, 10))
            self.overlay.draw(items, r.width, r.height)
        if self.markers is not None and self.marker is not None:
            self.markers.draw(marker_centres(posed, self.marker, camera, r.width, r.height),
                              r.width, r.height)
        return DrawnFrame(frame, posed, camera, now)

    def _follow(self, posed: PosedScene) -> None:
        """Ease the orbit camera towards framing every avatar's joints."""
        want = OrbitCamera(self.orbit.yaw, self.orbit.pitch, self.orbit.distance,
                           self.orbit.target, self.orbit.fov_y)
        want.frame(posed.global_pos.reshape(-1, 3))
        a = FRAMING_SMOOTHING if self.stats.frames else 1.0
        t0, t1 = np.asarray(self.orbit.target), np.asarray(want.target)
        t = t0 + a * (t1 - t0)
        self.orbit.target = (float(t[0]), float(t[1]), float(t[2]))
        self.orbit.distance += a * (want.distance - self.orbit.distance)

    def presented(self, drawn: DrawnFrame, t_present: float) -> None:
        """Record that ``drawn`` became visible at local time ``t_present``."""
        stats = self.stats
        stats.frames += 1
        stats.avatar_frames += len(drawn.scene)
        stats.frame_seconds.append(t_present - drawn.t_drawn)
        self._presents.append(t_present)
        clock = self.scene.clock
        synced = clock is not None and clock.synced
        t_server = clock.to_server(t_present) if clock is not None and synced else None
        capture = []
        receive = []
        first: list[tuple[float, float]] = []  # each frame's first presentation
        for avatar_id, s in zip(drawn.scene.ids, drawn.scene.sampled, strict=True):
            if t_server is not None:
                capture.append(t_server - s.t_capture)
            if self._counted.get(avatar_id) != s.newest.seq:
                self._counted[avatar_id] = s.newest.seq
                receive.append(t_present - s.newest.t_arrival)
                first.append((s.newest.t_capture, s.newest.t_arrival))
        if capture:
            stats.latency.add_values("capture_to_render", capture)
        if receive:
            stats.latency.add_values("receive_to_render", receive)
        self.reports.add(None, first, t_present)
        sampled = drawn.scene.sampled
        self.reports.show(self.scene.mode.value, list(drawn.scene.ids),
                          [s.root for s in sampled], [s.rotations for s in sampled],
                          t_present)
        self._report(t_present)

    def _report(self, t_local: float) -> None:
        """Send what was presented since the last report when one is due: written at
        once (the frame loop must not wait), dropped if the connection is backed up."""
        reports = self.reports
        if not reports.enabled or t_local - self._reported_at < REPORT_INTERVAL_S:
            return
        self._reported_at = t_local
        spectator = self.scene.spectator
        session = spectator.session
        if session is None:
            return
        if reports.stop_if_refused(spectator.stats.last_error):
            return
        report = reports.take(session.clock)
        if report is not None and session.send_now(encode(report)):
            reports.sent += 1

    def fps(self) -> float:
        p = self._presents
        if len(p) < 2 or p[-1] <= p[0]:
            return 0.0
        recent = [t for t in p if t >= p[-1] - 1.0]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def _hud(self, now: float, avatars: int) -> str:
        if now - self._hud_at >= HUD_REFRESH_S:
            self._hud_at = now
            latency = _recent_summary([self.scene.spectator.stats.latency,
                                       self.stats.latency])
            mode = self.scene.mode
            delays = self.scene.interpolator.delays()
            delay = (1e3 * float(np.median(list(delays.values())))
                     if mode is Mode.INTERPOLATE and delays else None)
            self._hud_text = "\n".join(hud_lines(latency, self.fps(), avatars, mode.value,
                                                 delay, self.view.value, self.scene.newest()))
        return self._hud_text

    def release(self) -> None:
        if self.overlay is not None:
            self.overlay.release()
        if self.markers is not None:
            self.markers.release()


def _recent_summary(recorders: list[LatencyRecorder]) -> Mapping[str, Mapping[str, float]]:
    """p50/p99 in ms of the latest HUD_WINDOW samples of every stage."""
    out: dict[str, dict[str, float]] = {}
    for rec in recorders:
        for stage in rec.stages:
            values = rec.samples(stage)[-HUD_WINDOW:]
            if len(values):
                p50, p99 = np.percentile(values, [50.0, 99.0]) * 1e3
                out[stage] = {"p50": float(p50), "p99": float(p99)}
    return out
