"""The headset's frame loop, on a thread of its own that owns the GL context.

Each frame: the display's poses for the frame (blocking until it is due); the player's
own body solved from those very poses; the others as the spectator connection's
snapshot buffers predict them now (under ``lock``: the session's thread pushes frames
into them); one batched FK for everyone; then per eye the reflected pass into the
mirror's texture and the eye's own pass (own head hidden: the camera is inside it),
the mirror, names and HUD; both eyes handed to the display. ``pose_to_submit`` is the
time from the poses to the hand-over, the latency this loop adds to SteamVR's own
motion-to-photon.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import moderngl
import numpy as np

from posecast.client.headset.displays import Display, HeadsetFrame
from posecast.client.headset.local_body import LocalBody
from posecast.client.headset.room import (
    Mirror,
    anchored_text,
    hud_anchor,
    place_mirror,
)
from posecast.client.headset.stereo import eye_cameras, heading_of, reflected
from posecast.client.measure.latency import LatencyRecorder
from posecast.client.sources.base import DeviceSample, now
from posecast.client.viewer.camera import Camera
from posecast.client.viewer.overlay import TextItem, TextOverlay, label_items, label_text
from posecast.client.viewer.renderer import (
    AvatarDraw,
    PosedScene,
    Renderer,
    avatar_color,
    create_headless_context,
)
from posecast.client.viewer.scene import SpectatorScene
from posecast.client.viewer.skinning import FittedAvatar, fit_avatar

log = logging.getLogger(__name__)

STANDING_EYES_M = 1.65  # where the eyes are before the headset is first tracked
HUD_REFRESH_S = 0.25


class PlayerLink(Protocol):
    """What the frame loop reads of the player on the session's thread."""

    @property
    def tpose(self) -> tuple[int, DeviceSample] | None:
        """(a number that grows with each calibration, the T-pose sent), or None."""
        ...

    @property
    def avatar_id(self) -> int | None: ...

    @property
    def name(self) -> str: ...

    @property
    def status(self) -> str:
        """A line on the connection and calibration, for the HUD."""
        ...


@dataclass(frozen=True)
class DrawnHeadset:
    """What the last frame drew: the posed avatars (the own body first, ``own`` of them,
    with its head; ``seen``: as the eyes saw them, head hidden), the others' avatar ids
    in the order after it, and the eyes' cameras."""

    posed: PosedScene
    seen: PosedScene
    own: int
    others: list[int]
    cameras: tuple[Camera, Camera]


@dataclass
class HeadsetStats:
    """What the headset showed. Latencies in seconds (``as_json``: milliseconds)."""

    frames: int = 0
    latency: LatencyRecorder = field(default_factory=LatencyRecorder)  # pose_to_submit,
    # frame (draw to hand-over), capture_to_render (the others' poses, server clock)
    width: int = 0
    height: int = 0
    errors: dict[str, int] = field(default_factory=dict)  # the compositor's refusals

    def as_json(self) -> dict[str, object]:
        return {"frames": self.frames, "eye_size": [self.width, self.height],
                "latency_ms": self.latency.summary(), "compositor_errors": self.errors}


@dataclass
class HeadsetFrameDone:
    """What one presented headset frame tells the session's reports."""

    pose_to_submit: float  # seconds from its poses to its submission
    first: list[tuple[float, float]]  # (t_capture server, t_received local), first drawn
    shown: list[tuple[int, np.ndarray, np.ndarray]]  # the others: (id, root, rotations)
    mode: str | None  # the playout mode they were shown in (None: alone)
    t_presented: float  # local clock


class HeadsetView:
    """Draws the room into ``display``'s eyes until stopped; see the module docstring.

    ``others``: the spectator connection's scene (None: alone), read under ``lock``.
    ``on_frame``: called on this thread after each frame with a ``HeadsetFrameDone``
    (pose_to_submit, the others drawn for the first time, the others as shown, when),
    for the session's reports.
    """

    def __init__(self, display: Display, link: PlayerLink, others: SpectatorScene | None,
                 lock: threading.Lock, body: LocalBody | None = None,
                 mirror_distance: float | None = 2.0, frames: int | None = None,
                 on_frame: Callable[[HeadsetFrameDone], None] | None = None) -> None:
        self.display = display
        self.link = link
        self.others = others
        self.lock = lock
        self.body = body or LocalBody()
        self.mirror_distance = mirror_distance
        self.frames = frames
        self.on_frame = on_frame
        self.stats = HeadsetStats(width=display.setup.width, height=display.setup.height)
        self.error: BaseException | None = None
        self.ctx: moderngl.Context | None = None  # the loop's, while it runs
        self.textures: tuple[moderngl.Texture, moderngl.Texture] | None = None
        self._calibration = -1
        self._own: FittedAvatar | None = None
        self._mirror: Mirror | None = None
        self._head = np.eye(4)
        self._head[1, 3] = STANDING_EYES_M
        self._hud = ""
        self._hud_at = -math.inf
        # the others of the frame drawn last, as shown: (id, root, rotations)
        self._shown: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._counted: dict[int, int] = {}  # avatar id -> seq whose presentation counted
        self.last: DrawnHeadset | None = None  # the frame drawn last (tests look at it)

    # ------------------------------------------------------------------ the thread
    def run(self, stop: threading.Event, done: Callable[[], None] | None = None) -> None:
        """The loop (the thread's target): until ``stop``, ``frames`` frames, or the
        display ends; an exception is kept in ``error``; ``done`` is called last."""
        try:
            self._run(stop)
        except BaseException as err:  # reported by the session, on its thread
            self.error = err
        finally:
            if done is not None:
                done()

    def _run(self, stop: threading.Event) -> None:
        setup = self.display.setup
        size = (setup.width, setup.height)
        ctx = self.ctx = create_headless_context()
        textures = (ctx.texture(size, 4), ctx.texture(size, 4))
        depths = [ctx.depth_renderbuffer(size) for _ in range(2)]
        fbos = [ctx.framebuffer(color_attachments=[t], depth_attachment=d)
                for t, d in zip(textures, depths, strict=True)]
        self.textures = textures
        renderer = Renderer(ctx, *size, target=fbos[0])
        overlay = TextOverlay(ctx, font_size=max(15, setup.height // 40))
        try:
            renderer.warm_up()
            self.body.warm_up()
            while not stop.is_set():
                if self.frames is not None and self.stats.frames >= self.frames:
                    break
                frame = self.display.next_frame(stop)
                if frame is None:
                    if self.display.ended:
                        break
                    continue
                t_drawn = now()
                drawn = self._draw(frame, renderer, overlay, fbos, size)
                t_presented = self.display.present(ctx, textures)
                self._presented(frame, drawn, t_drawn, t_presented)
        finally:
            if self._mirror is not None:
                self._mirror.release()
            overlay.release()
            renderer.release()
            for fbo in fbos:
                fbo.release()
            for depth in depths:
                depth.release()
            for texture in textures:
                texture.release()
            self.body.close()
            self.ctx = None
            ctx.release()

    # ------------------------------------------------------------------ a frame
    def _calibrate(self, renderer: Renderer) -> None:
        """Calibrate the own body (and place the mirror) when the player sent a T-pose."""
        tpose = self.link.tpose
        if tpose is None or tpose[0] == self._calibration:
            return
        self._calibration, sample = tpose
        avatar_id = self.link.avatar_id
        try:
            info = self.body.calibrate(sample, 0 if avatar_id is None else avatar_id,
                                       self.link.name)
        except ValueError as err:  # the server refuses it too, with the same words
            log.warning("headset: not calibrated: %s", err)
            return
        self._own = fit_avatar(renderer.mesh, info)
        if self.mirror_distance is not None and "head" in sample.roles:
            pos = {r: sample.positions[i] for i, r in enumerate(sample.roles)}
            if self._mirror is not None:
                self._mirror.release()
            self._mirror = Mirror(renderer.ctx, place_mirror(
                pos["head"], heading_of(pos), self.mirror_distance))

    def _draw(self, frame: HeadsetFrame, renderer: Renderer, overlay: TextOverlay,
              fbos: list[moderngl.Framebuffer], size: tuple[int, int]
              ) -> list[tuple[int, float, float, int]]:
        """Both eyes of one frame; the others drawn: (id, t_capture, t_arrival, seq)."""
        self._calibrate(renderer)
        own_id = self.link.avatar_id
        draws: list[AvatarDraw] = []
        if self._own is not None and frame.sample is not None:
            solved = self.body.solve(frame.sample)
            color = avatar_color(own_id if own_id is not None else 0)
            draws.append(AvatarDraw(self._own, solved.rotations, solved.root, color))
        own = len(draws)  # the own body is draws[:own]
        names: list[str] = []
        colors: list[tuple[float, float, float]] = []
        drawn: list[tuple[int, float, float, int]] = []
        self._shown = []
        others: list[int] = []
        if self.others is not None:
            with self.lock:
                scene = self.others.frame(now())
                lost = [self.others.lost(a) for a in scene.ids]
            for avatar_id, d, s, gone in zip(scene.ids, scene.draws, scene.sampled, lost,
                                             strict=True):
                if avatar_id == own_id:
                    continue  # drawn from the local solve instead
                draws.append(d)
                others.append(avatar_id)
                names.append(label_text(d.avatar.info.display_name, gone))
                colors.append(avatar_color(avatar_id))
                drawn.append((avatar_id, s.t_capture, s.newest.t_arrival, s.newest.seq))
                self._shown.append((avatar_id, s.root, s.rotations))
        posed = renderer.pose(draws)
        seen = renderer.without_heads(posed, list(range(own)))
        if frame.head is not None:
            self._head = frame.head
        cams = eye_cameras(self._head, self.display.setup)
        tops = renderer.head_tops(posed)[own:] if len(draws) > own else np.empty((0, 3))
        hud = self._hud_text(len(draws))
        mirror = self._mirror
        for fbo, cam in zip(fbos, cams, strict=True):
            in_mirror = mirror is not None and mirror.visible(cam)
            if mirror is not None and in_mirror:
                target, msize = mirror.target(size)
                plane = mirror.placement.plane
                renderer.render(posed, reflected(cam, plane), target=target, size=msize,
                                clip_plane=plane)
            renderer.render(seen, cam, target=fbo, size=size)
            if mirror is not None and in_mirror:
                mirror.draw(cam, size)
            items: list[TextItem] = label_items(names, colors, tops, cam, *size)
            item = anchored_text(hud, hud_anchor(self._head), cam, *size)
            if item is not None:
                items.append(item)
            overlay.draw(items, *size)
        self.last = DrawnHeadset(posed, seen, own, others, cams)
        return drawn

    def _hud_text(self, avatars: int) -> str:
        t = now()
        if t - self._hud_at >= HUD_REFRESH_S:
            self._hud_at = t
            lines = [self.link.status]
            values = self.stats.latency.samples("pose_to_submit")[-500:] \
                if "pose_to_submit" in self.stats.latency.stages else np.empty(0)
            if len(values):
                p50, p99 = np.percentile(values, [50.0, 99.0]) * 1e3
                lines.append(f"pose to submit {p50:.1f} / {p99:.1f} ms (p50/p99)")
            lines.append(f"{avatars} in the room")
            self._hud = "\n".join(lines)
        return self._hud

    def _presented(self, frame: HeadsetFrame, drawn: list[tuple[int, float, float, int]],
                   t_drawn: float, t_presented: float) -> None:
        stats = self.stats
        stats.frames += 1
        pose_to_submit = t_presented - frame.t_poses
        stats.latency.add_values("pose_to_submit", [pose_to_submit])
        stats.latency.add_values("frame", [t_presented - t_drawn])
        first = []
        for avatar_id, t_capture, t_arrival, seq in drawn:
            if self._counted.get(avatar_id) != seq:
                self._counted[avatar_id] = seq
                first.append((t_capture, t_arrival))
        errors = getattr(getattr(self.display, "compositor", None), "errors", None)
        if errors:
            stats.errors = dict(errors)
        if self.on_frame is not None:
            mode = self.others.mode.value if self.others is not None else None
            self.on_frame(HeadsetFrameDone(pose_to_submit, first, self._shown, mode,
                                           t_presented))
