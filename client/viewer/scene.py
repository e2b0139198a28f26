"""From a spectator's connection to what to draw: fitted avatars, interpolated poses, cameras.

A ``ViewerSpectator`` is the headless ``Spectator`` that also hands every frame to an
``Interpolator`` as it arrives (the snapshot buffers need every frame, not just the
latest). ``SpectatorScene`` works with either: given a plain ``Spectator`` that is already
running, it polls ``spectator.latest`` each time it is asked (coarser: frames that arrived
between two polls are skipped, which interpolation smooths over). It fits the mesh to each
avatar of the roster once (again when the avatar is recalibrated) and turns a local
instant into ``AvatarDraw``s and the camera of the chosen view.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass
from pathlib import Path

from posecast.client.session.spectator import ReceivedFrame, Spectator, frame_of
from posecast.client.viewer.camera import Camera, OrbitCamera, first_person, mirror
from posecast.client.viewer.interpolation import Interpolator, Mode, Sampled
from posecast.client.viewer.renderer import AvatarDraw, PosedScene
from posecast.client.viewer.skinning import FittedAvatar, SkeletonMismatchError, fit_avatar
from posecast.protocol import AvatarBatch, AvatarFrame, AvatarInfo, AvatarRoster, ClockEstimator
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman

log = logging.getLogger(__name__)


class ViewMode(enum.Enum):
    ORBIT = "orbit"
    FIRST_PERSON = "first-person"
    MIRROR = "mirror"


class ViewerSpectator(Spectator):
    """A Spectator whose every received frame also goes to ``interpolator``."""

    def __init__(self, url: str, room: str, name: str, interpolator: Interpolator | None = None,
                 max_rate_hz: float | None = None, token: str | None = None,
                 cafile: Path | None = None) -> None:
        super().__init__(url, room, name, max_rate_hz=max_rate_hz, token=token,
                         cafile=cafile)
        self.interpolator = interpolator or Interpolator()

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        for f in batch.frames:
            self.interpolator.push(f, t_local)

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        for avatar_id in roster.removed:
            self.interpolator.remove(avatar_id)


@dataclass
class SceneFrame:
    """The avatars to draw at one instant (parallel lists)."""

    ids: list[int]
    draws: list[AvatarDraw]
    sampled: list[Sampled]

    def __len__(self) -> int:
        return len(self.ids)


class SpectatorScene:
    """What a running spectator's room looks like now; see the module docstring."""

    def __init__(self, spectator: Spectator, mesh: SkinnedMesh | None = None,
                 interpolator: Interpolator | None = None) -> None:
        self.spectator = spectator
        self.mesh = mesh or load_makehuman()
        if isinstance(spectator, ViewerSpectator):
            self.interpolator = spectator.interpolator
            self._polling = False
        else:
            self.interpolator = interpolator or Interpolator()
            self._polling = True
        self._fitted: dict[int, tuple[AvatarInfo, FittedAvatar]] = {}
        self._refused: set[int] = set()  # avatars whose skeleton cannot wear the mesh
        self._polled: dict[int, ReceivedFrame] = {}

    @property
    def clock(self) -> ClockEstimator | None:
        """The spectator's server-clock estimate (None before it has connected)."""
        session = self.spectator.session
        return session.clock if session is not None else None

    def _sync(self) -> None:
        roster = self.spectator.roster
        for avatar_id in [a for a in self._fitted if a not in roster]:
            del self._fitted[avatar_id]
            self.interpolator.remove(avatar_id)
            self._polled.pop(avatar_id, None)
        for avatar_id, info in list(roster.items()):
            known = self._fitted.get(avatar_id)
            if known is not None and known[0] is info:
                continue
            try:
                self._fitted[avatar_id] = (info, fit_avatar(self.mesh, info))
                self._refused.discard(avatar_id)
            except SkeletonMismatchError as err:
                if avatar_id not in self._refused:
                    log.warning("not drawing avatar: %s", err)
                    self._refused.add(avatar_id)
        if self._polling:
            for avatar_id, received in list(self.spectator.latest.items()):
                if self._polled.get(avatar_id) is not received:
                    self._polled[avatar_id] = received
                    self.interpolator.push(frame_of(received), received[2])

    def frame(self, now: float) -> SceneFrame:
        """Poses of every drawable avatar at local time ``now`` (``client.sources.now``)."""
        self._sync()
        clock = self.clock  # predict mode carries poses to now on the server clock
        sampled = self.interpolator.sample(
            now, clock.to_server if clock is not None and clock.synced else None)
        ids, draws, samples = [], [], []
        for avatar_id in sorted(sampled):
            fitted = self._fitted.get(avatar_id)
            s = sampled[avatar_id]
            if fitted is None or s.rotations.shape[0] != len(fitted[1].order):
                continue  # no skeleton yet (the roster comes first), or a stale one
            ids.append(avatar_id)
            draws.append(AvatarDraw(fitted[1], s.rotations, s.root))
            samples.append(s)
        return SceneFrame(ids, draws, samples)

    def lost(self, avatar_id: int) -> int:
        """The avatar's devices its newest frame lacked (protocol.roles bits; 0 before
        its first frame). The newest, not the drawn one: it says what is lost now."""
        received = self.spectator.latest.get(avatar_id)
        if received is None:
            return 0
        batch, row, _ = received
        return int(batch.lost[row])

    def newest(self) -> list[tuple[AvatarInfo, AvatarFrame]]:
        """Every avatar of the roster that has a frame, with its newest, by id."""
        roster, latest = self.spectator.roster, self.spectator.latest
        return [(roster[a], frame_of(latest[a])) for a in sorted(roster) if a in latest]

    @property
    def mode(self) -> Mode:
        return self.interpolator.mode


def view_target(view: ViewMode, ids: list[int], player: int | None) -> int | None:
    """Index (into ``ids``) of the avatar whose eyes the view uses; None for the orbit
    camera or an empty room. First-person and mirror views follow ``player`` (an avatar
    id), or the first avatar when that one is absent."""
    if view is ViewMode.ORBIT or not ids:
        return None
    return ids.index(player) if player in ids else 0


def view_camera(view: ViewMode, orbit: OrbitCamera, scene: PosedScene, target: int | None,
                head: int, aspect: float) -> Camera:
    """The camera of ``view``; ``target`` from view_target, ``head`` the head joint's
    index (mesh order)."""
    if view is ViewMode.ORBIT or target is None:
        return orbit.camera(aspect)
    q, p = scene.global_rot[target, head], scene.global_pos[target, head]
    eye = scene.draws[target].avatar.eye
    if view is ViewMode.FIRST_PERSON:
        return first_person(q, p, eye, aspect)
    return mirror(q, p, eye, aspect)
